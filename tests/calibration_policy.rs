//! One calibration policy for `irid run` and `irid fit --dark/--white`:
//! the same raw counts, dark and white give bit-identical reflectance, and
//! the same tagged NaNs, through the live pipeline's path (frames averaged
//! into a `Calibration`, converted by its `Calibrator`) and the ENVI path
//! (`read_calibrated` of u16 cubes) — a saturated sample, a saturated white,
//! a low-contrast pixel, a pixel whose white is below its dark, and a band
//! the packed form cannot hold included.

use irid::device::camera::{Frame, PixelFormat};
use irid::estimate::{nan_reason, Cube, Reason};
use irid::io::envi::{write_cube, DataType, WriteOptions};
use irid::optics::band::Band;
use irid::pipeline::calibration::{
    read_calibrated, Accumulator, CalMeta, Calibration, CalibrationPolicy, Calibrator,
};
use std::path::{Path, PathBuf};

const W: usize = 8;
const H: usize = 2;
const N: usize = W * H;
const BANDS: usize = 3;
const EXPOSURE_US: u32 = 4000;
const WHITE_R: f32 = 0.99;

/// Dark, white and raw counts, band-sequential.
struct Counts {
    dark: Vec<u16>,
    white: Vec<u16>,
    raw: Vec<u16>,
}

/// The probes, by pixel index in every band: see `expected`.
const SATURATED_SAMPLE: usize = 1; // raw at full scale in band 1
const SATURATED_WHITE: usize = 2; // white at full scale in band 0
const LOW_CONTRAST: usize = 3; // white − dark = 300 < 655.35 in band 2
const WHITE_BELOW_DARK: usize = 4; // in band 1
const AT_THE_FLOOR: usize = 5; // white − dark = 656: just usable, every band

fn counts() -> Counts {
    let (mut dark, mut white, mut raw) = (vec![], vec![], vec![]);
    for b in 0..BANDS {
        for i in 0..N {
            // Band 2's darks spread over 28 000 counts at ~700 counts of
            // contrast: more than the packed form holds, so it stays f32
            // (the other loop).
            let (d, contrast) = if b == 2 {
                (100 + (i as u16) * 1900, 700 + (i as u16) * 20)
            } else {
                (
                    90 + ((i * 7 + b * 3) % 23) as u16,
                    20000 + (i as u16) * 1500 + (b as u16) * 700,
                )
            };
            let mut w = d + contrast;
            let mut r = d + (contrast / 3) + (i as u16) * 11;
            match (i, b) {
                (SATURATED_SAMPLE, 1) => r = u16::MAX,
                (SATURATED_WHITE, 0) => w = u16::MAX,
                (LOW_CONTRAST, 2) => w = d + 300,
                (WHITE_BELOW_DARK, 1) => w = d - 50,
                (AT_THE_FLOOR, _) => {
                    w = d + 656;
                    r = d + 200;
                }
                _ => {}
            }
            dark.push(d);
            white.push(w);
            raw.push(r);
        }
    }
    Counts { dark, white, raw }
}

/// The reason each probe must carry in its band, `None` elsewhere.
fn expected(i: usize, b: usize) -> Option<Reason> {
    match (i, b) {
        (SATURATED_SAMPLE, 1) | (SATURATED_WHITE, 0) => Some(Reason::Saturated),
        (LOW_CONTRAST, 2) | (WHITE_BELOW_DARK, 1) => Some(Reason::Dark),
        _ => None,
    }
}

fn bands() -> Vec<Band> {
    (0..BANDS)
        .map(|b| Band {
            center_nm: 450.0 + 100.0 * b as f64,
            fwhm_nm: 0.0,
        })
        .collect()
}

/// `irid run`'s path: one frame per reference per band, averaged, flagged
/// by the camera format's policy, and each raw frame converted.
fn pipeline_path(c: &Counts) -> (Calibrator, Vec<f32>) {
    let frame = |plane: &[u16]| {
        let mut f = Frame::with_size(W as u32, H as u32, PixelFormat::Y16);
        f.meta.exposure_us = EXPOSURE_US;
        f.data.copy_from_slice(plane);
        f
    };
    let (mut dark, mut white) = (Accumulator::new(N, BANDS), Accumulator::new(N, BANDS));
    for b in 0..BANDS {
        dark.add(b, &frame(&c.dark[b * N..(b + 1) * N])).unwrap();
        white.add(b, &frame(&c.white[b * N..(b + 1) * N])).unwrap();
    }
    let meta = CalMeta {
        version: 1,
        width: W as u32,
        height: H as u32,
        bands_nm: bands().iter().map(|b| b.center_nm).collect(),
        exposure_us: EXPOSURE_US,
        gain: 1.0,
        format: PixelFormat::Y16,
        camera_id: "test".into(),
        created_unix_s: 0,
        white_reflectance: f64::from(WHITE_R),
        frames: 1,
        noise: None,
    };
    let policy = CalibrationPolicy::for_format(PixelFormat::Y16);
    let cal = Calibrator::new(&Calibration::from_references(meta, &dark, &white, &policy));
    let mut out = vec![0.0f32; N * BANDS];
    for b in 0..BANDS {
        let f = frame(&c.raw[b * N..(b + 1) * N]);
        let sat = f.meta.format.max_value();
        cal.apply(b, &f.data, sat, EXPOSURE_US, &mut out[b * N..(b + 1) * N]);
    }
    (cal, out)
}

/// Write `plane` counts as a u16 ENVI cube (stored values = counts).
fn write_u16(dir: &Path, name: &str, counts: &[u16]) -> PathBuf {
    let cube = Cube {
        width: W,
        height: H,
        bands: bands(),
        data: counts.iter().map(|&c| f32::from(c)).collect(),
    };
    let p = dir.join(format!("{name}.hdr"));
    let opts = WriteOptions {
        data_type: DataType::U16,
        reflectance_scale_factor: Some(1.0),
        ..Default::default()
    };
    write_cube(&p, &cube, &opts).unwrap();
    p
}

#[test]
fn run_and_fit_calibrate_the_same_counts_to_the_same_bits() {
    let c = counts();
    let (cal, via_run) = pipeline_path(&c);
    // Both loops are exercised: band 2 stays f32, the others pack.
    assert_eq!(cal.packed_bands(), 2);

    let dir = tempfile::tempdir().unwrap();
    let raw = write_u16(dir.path(), "raw", &c.raw);
    let dark = write_u16(dir.path(), "dark", &c.dark);
    let white = write_u16(dir.path(), "white", &c.white);
    // u16 cubes: full scale 65535 by default, as for a Y16 camera.
    let cube = read_calibrated(&raw, &dark, &white, WHITE_R, None).unwrap();
    assert_eq!((cube.width, cube.height, cube.bands.len()), (W, H, BANDS));

    for b in 0..BANDS {
        for i in 0..N {
            let (r, f) = (via_run[b * N + i], cube.data[b * N + i]);
            let at = format!(
                "band {b} pixel {i}: run {r} ({:#x}), fit {f} ({:#x})",
                r.to_bits(),
                f.to_bits()
            );
            assert_eq!(r.to_bits(), f.to_bits(), "{at}");
            assert_eq!(nan_reason(r), expected(i, b), "{at}");
            if expected(i, b).is_none() {
                // Within the packed bound of the f32 formula.
                let k = b * N + i;
                let want = WHITE_R * (f32::from(c.raw[k]) - f32::from(c.dark[k]))
                    / (f32::from(c.white[k]) - f32::from(c.dark[k]));
                assert!(
                    (r - want).abs() <= 2e-5 * want.abs().max(1.0),
                    "{at}: want {want}"
                );
            }
        }
    }
    // The tags reach the per-pixel reasons.
    let reason = |i: usize| cube.input_reason(i % W, i / W);
    assert_eq!(reason(SATURATED_SAMPLE), Some(Reason::Saturated));
    assert_eq!(reason(SATURATED_WHITE), Some(Reason::Saturated));
    assert_eq!(reason(LOW_CONTRAST), Some(Reason::Dark));
    assert_eq!(reason(WHITE_BELOW_DARK), Some(Reason::Dark));
    assert_eq!(reason(AT_THE_FLOOR), None);
    assert_eq!(reason(0), None);
}

#[test]
fn an_explicit_full_scale_moves_both_rules() {
    // A 12-bit sensor stored in u16: full scale 4095, floor 40.95 counts.
    let dir = tempfile::tempdir().unwrap();
    let one = |name: &str, v: [u16; 4]| {
        let cube = Cube {
            width: 4,
            height: 1,
            bands: vec![Band {
                center_nm: 500.0,
                fwhm_nm: 0.0,
            }],
            data: v.iter().map(|&c| f32::from(c)).collect(),
        };
        let p = dir.path().join(format!("{name}.hdr"));
        let opts = WriteOptions {
            data_type: DataType::U16,
            reflectance_scale_factor: Some(1.0),
            ..Default::default()
        };
        write_cube(&p, &cube, &opts).unwrap();
        p
    };
    let dark = one("dark", [60, 60, 60, 60]);
    let white = one("white", [160, 3000, 3000, 4095]);
    let raw = one("raw", [100, 4095, 1000, 1000]);
    let at_16 = read_calibrated(&raw, &dark, &white, 1.0, None).unwrap();
    let at_12 = read_calibrated(&raw, &dark, &white, 1.0, Some(4095.0)).unwrap();
    let tags = |c: &Cube| c.data.iter().map(|&v| nan_reason(v)).collect::<Vec<_>>();
    // 16-bit rules: 100 counts of contrast is below 655; nothing saturates.
    assert_eq!(tags(&at_16), [Some(Reason::Dark), None, None, None]);
    // 12-bit rules: 100 counts is usable; 4095 saturates, sample and white.
    assert_eq!(
        tags(&at_12),
        [None, Some(Reason::Saturated), None, Some(Reason::Saturated)]
    );
    assert!((at_12.data[0] - 0.4).abs() < 2e-5);
    assert!((at_12.data[2] - 940.0 / 2940.0).abs() < 2e-5);
}
