//! ENVI cubes: round trips over every data type × interleave × byte order
//! from files written here byte by byte (independently of irid's writer),
//! the fixture manifest (valid / invalid / damaged), the writer, dark/white
//! calibration, and fuzz-style "an error, not a panic" properties.

use irid::estimate::{nan_reason, Cube, Reason};
use irid::io::envi::{
    self, parse_header, read_cube, read_image, write_cube, ByteOrder, DataType, Interleave,
    WriteOptions,
};
use irid::optics::band::Band;
use irid::pipeline::calibration::{
    calibrate_counts, read_calibrated, CalibrationPolicy, PACKED_ERROR_BOUND,
};
use proptest::prelude::*;
use std::path::{Path, PathBuf};

const S: usize = 4;
const L: usize = 3;
const B: usize = 5;

/// Stored value at (sample, line, band); negative for signed types so the
/// sign survives the round trip.
fn stored(s: usize, l: usize, b: usize, signed: bool) -> f64 {
    let v = (1 + s + 4 * l + 12 * b) as f64;
    if signed && (s + l) % 2 == 1 {
        -v
    } else {
        v
    }
}

fn file_order(il: Interleave) -> Vec<(usize, usize, usize)> {
    let mut out = Vec::new();
    match il {
        Interleave::Bsq => {
            for b in 0..B {
                for l in 0..L {
                    for s in 0..S {
                        out.push((s, l, b));
                    }
                }
            }
        }
        Interleave::Bil => {
            for l in 0..L {
                for b in 0..B {
                    for s in 0..S {
                        out.push((s, l, b));
                    }
                }
            }
        }
        Interleave::Bip => {
            for l in 0..L {
                for s in 0..S {
                    for b in 0..B {
                        out.push((s, l, b));
                    }
                }
            }
        }
    }
    out
}

/// Encode one value by hand (no shared code with the reader).
fn bytes_of(v: f64, t: DataType, big: bool) -> Vec<u8> {
    macro_rules! e {
        ($x:expr) => {
            if big {
                $x.to_be_bytes().to_vec()
            } else {
                $x.to_le_bytes().to_vec()
            }
        };
    }
    match t {
        DataType::U8 => vec![v as u8],
        DataType::I16 => e!(v as i16),
        DataType::U16 => e!(v as u16),
        DataType::I32 => e!(v as i32),
        DataType::U32 => e!(v as u32),
        DataType::F32 => e!(v as f32),
        DataType::F64 => e!(v),
    }
}

fn signed(t: DataType) -> bool {
    matches!(
        t,
        DataType::I16 | DataType::I32 | DataType::F32 | DataType::F64
    )
}

#[test]
fn every_type_interleave_and_byte_order_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    for t in DataType::ALL {
        for il in Interleave::ALL {
            for big in [false, true] {
                let offset = 7usize;
                let scale = 50.0;
                let name = format!("c_{}_{}_{}", t.code(), il.name(), big as u8);
                let mut data = vec![0xAAu8; offset];
                for (s, l, b) in file_order(il) {
                    data.extend(bytes_of(stored(s, l, b, signed(t)), t, big));
                }
                // Trailing bytes beyond the cube are allowed (and ignored).
                data.extend([1, 2, 3]);
                std::fs::write(dir.path().join(format!("{name}.img")), &data).unwrap();
                let hdr = format!(
                    "ENVI\nsamples = {S}\nlines = {L}\nbands = {B}\nheader offset = {offset}\n\
                     data type = {}\ninterleave = {}\nbyte order = {}\n\
                     wavelength = {{400, 450, 500, 550, 600}}\nfwhm = {{10, 10, 10, 12, 12}}\n\
                     reflectance scale factor = {scale}\n",
                    t.code(),
                    il.name(),
                    big as u8
                );
                let hpath = dir.path().join(format!("{name}.hdr"));
                std::fs::write(&hpath, hdr).unwrap();
                let cube = read_cube(&hpath).unwrap_or_else(|e| panic!("{name}: {e}"));
                assert_eq!((cube.width, cube.height, cube.bands.len()), (S, L, B));
                assert_eq!(
                    cube.bands[3],
                    Band {
                        center_nm: 550.0,
                        fwhm_nm: 12.0
                    }
                );
                for b in 0..B {
                    for l in 0..L {
                        for s in 0..S {
                            let got = cube.plane(b)[l * S + s];
                            let want = (stored(s, l, b, signed(t)) / scale) as f32;
                            assert_eq!(got, want, "{name} at s={s} l={l} b={b}");
                        }
                    }
                }
            }
        }
    }
}

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/envi")
}

#[test]
fn fixture_manifest_outcomes() {
    let manifest = std::fs::read_to_string(fixtures().join("expected.txt")).unwrap();
    let mut checked = 0;
    for line in manifest
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let (file, outcome) = line.split_once('\t').unwrap();
        let path = fixtures().join(file);
        let result = read_cube(&path);
        if let Some(scale) = outcome.strip_prefix("ok ") {
            let scale: f64 = scale.parse().unwrap();
            let cube = result.unwrap_or_else(|e| panic!("{file}: {e}"));
            assert_eq!((cube.width, cube.height, cube.bands.len()), (4, 3, 5));
            let centers: Vec<f64> = cube.bands.iter().map(|b| b.center_nm).collect();
            for (c, want) in centers.iter().zip([400.0, 450.0, 500.0, 550.0, 600.0]) {
                assert!((c - want).abs() < 1e-9, "{file}: {centers:?}");
            }
            for b in 0..5 {
                for l in 0..3 {
                    for s in 0..4 {
                        let want = ((1 + s + 4 * l + 12 * b) as f64 / scale) as f32;
                        assert_eq!(cube.plane(b)[l * 4 + s], want, "{file} s={s} l={l} b={b}");
                    }
                }
            }
        } else {
            let fragment = outcome.strip_prefix("error ").unwrap();
            let e = match result {
                Ok(_) => panic!("{file}: read, but should fail with {fragment:?}"),
                Err(e) => e.to_string(),
            };
            assert!(e.contains(fragment), "{file}: {e:?} lacks {fragment:?}");
            let name = Path::new(file).file_stem().unwrap().to_str().unwrap();
            assert!(e.contains(name), "{file}: the message {e:?} names no file");
        }
        checked += 1;
    }
    assert!(checked >= 20, "only {checked} fixtures");
}

#[test]
fn spectral_python_fixture_keeps_micrometre_fwhm_in_nm() {
    let cube = read_cube(&fixtures().join("valid/spy_u16_bip_be.hdr")).unwrap();
    assert!(cube.bands.iter().all(|b| (b.fwhm_nm - 10.0).abs() < 1e-9));
}

#[test]
fn data_file_can_be_named_instead_of_header() {
    let img = read_image(&fixtures().join("valid/spy_u16_bip_be.img")).unwrap();
    assert_eq!(img.header.bands, 5);
    assert!(img.header_path.ends_with("spy_u16_bip_be.hdr"));
}

fn test_cube(w: usize, h: usize, nb: usize) -> Cube {
    let bands = (0..nb)
        .map(|i| Band {
            center_nm: 400.0 + 12.5 * i as f64,
            fwhm_nm: 7.25,
        })
        .collect();
    let mut c = Cube::zeros(w, h, bands);
    for (i, v) in c.data.iter_mut().enumerate() {
        *v = ((i * 37) % 101) as f32 / 101.0;
    }
    c
}

#[test]
fn writer_round_trips_every_format() {
    let dir = tempfile::tempdir().unwrap();
    let cube = test_cube(5, 3, 4);
    for t in DataType::ALL {
        for il in Interleave::ALL {
            for bo in [ByteOrder::Little, ByteOrder::Big] {
                let opts = WriteOptions {
                    data_type: t,
                    interleave: il,
                    byte_order: bo,
                    header_offset: 3,
                    description: Some("round {trip} test".into()),
                    ..Default::default()
                };
                let p = dir
                    .path()
                    .join(format!("w{}{}{:?}.hdr", t.code(), il.name(), bo));
                let (hdr, data) = write_cube(&p, &cube, &opts).unwrap();
                assert_eq!(hdr, p);
                assert_eq!(data, p.with_extension("img"));
                let back = read_cube(&p).unwrap();
                assert_eq!(back.bands, cube.bands);
                // Integers quantise to half a step of the default scale.
                let tol = match t {
                    DataType::U8 => 0.5 / 255.0,
                    t if t.is_integer() => 0.5 / 10000.0,
                    _ => 0.0,
                } + 1e-7;
                for (a, b) in back.data.iter().zip(&cube.data) {
                    assert!((a - b).abs() <= tol, "{t:?} {il:?} {bo:?}: {a} vs {b}");
                }
            }
        }
    }
}

#[test]
fn writer_header_looks_like_spectral_python() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("spy.hdr");
    write_cube(&p, &test_cube(2, 2, 3), &WriteOptions::default()).unwrap();
    let text = std::fs::read_to_string(&p).unwrap();
    assert!(text.starts_with("ENVI\n"));
    for needle in [
        "data type = 4",
        "interleave = bsq",
        "byte order = 0",
        "wavelength units = Nanometers",
        "wavelength = {400, 412.5, 425}",
        "fwhm = {7.25, 7.25, 7.25}",
    ] {
        assert!(text.contains(needle), "{needle:?} not in\n{text}");
    }
    assert!(!text.contains("reflectance scale factor"));
}

#[test]
fn output_paths_follow_envi_conventions() {
    let p = |s: &str| PathBuf::from(s);
    assert_eq!(
        envi::output_paths(&p("a/c.hdr")),
        (p("a/c.hdr"), p("a/c.img"))
    );
    assert_eq!(
        envi::output_paths(&p("c.img.hdr")),
        (p("c.img.hdr"), p("c.img"))
    );
    assert_eq!(
        envi::output_paths(&p("c.raw")),
        (p("c.hdr"), p("c.raw").with_extension("img"))
    );
}

#[test]
fn calibration_divides_by_white_minus_dark() {
    let mut raw = vec![110.0f32, 50.0, 10.0, 200.0, f32::NAN, 30.0];
    let dark = [10.0f32, 10.0, 10.0, 100.0, 0.0, f32::INFINITY];
    let white = [210.0f32, 90.0, 5.0, 100.0, 100.0, 40.0];
    // Full scale unknown (float counts): only white > dark is required.
    let policy = CalibrationPolicy::for_full_scale(f32::INFINITY);
    calibrate_counts(&mut raw, dark.to_vec(), white.to_vec(), 6, 0.9, &policy);
    assert!((raw[0] - 0.45).abs() < PACKED_ERROR_BOUND, "{raw:?}");
    assert!((raw[1] - 0.45).abs() < PACKED_ERROR_BOUND);
    assert_eq!(nan_reason(raw[2]), Some(Reason::Dark), "white < dark");
    assert_eq!(nan_reason(raw[3]), Some(Reason::Dark), "white = dark");
    assert!(raw[4].is_nan(), "non-finite raw");
    assert_eq!(nan_reason(raw[4]), None, "a missing value is not a tag");
    assert_eq!(nan_reason(raw[5]), Some(Reason::Dark), "non-finite dark");
}

#[test]
fn calibrated_cube_from_files_and_mismatches() {
    let dir = tempfile::tempdir().unwrap();
    let mk = |name: &str, f: &dyn Fn(usize) -> f32, w: usize, nb: usize| {
        let mut c = test_cube(w, 2, nb);
        for (i, v) in c.data.iter_mut().enumerate() {
            *v = f(i);
        }
        let p = dir.path().join(format!("{name}.hdr"));
        // Raw counts: u16 with a unit scale factor.
        let opts = WriteOptions {
            data_type: DataType::U16,
            reflectance_scale_factor: Some(1.0),
            ..Default::default()
        };
        write_cube(&p, &c, &opts).unwrap();
        p
    };
    let dark = mk("dark", &|_| 100.0, 3, 4);
    let white = mk("white", &|i| if i == 5 { 50.0 } else { 1100.0 }, 3, 4);
    let raw = mk("raw", &|i| 100.0 + (i % 10) as f32 * 100.0, 3, 4);
    let cube = read_calibrated(&raw, &dark, &white, 1.0, None).unwrap();
    for (i, v) in cube.data.iter().enumerate() {
        if i == 5 {
            assert_eq!(nan_reason(*v), Some(Reason::Dark));
        } else {
            assert!((v - (i % 10) as f32 / 10.0).abs() < 1e-6, "{i}: {v}");
        }
    }
    let narrow = mk("narrow", &|_| 1.0, 2, 4);
    let e = read_calibrated(&raw, &dark, &narrow, 1.0, None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("sizes differ") && e.contains("narrow.hdr"),
        "{e}"
    );
    let fewer = mk("fewer", &|_| 1.0, 3, 3);
    let e = read_calibrated(&raw, &fewer, &white, 1.0, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("3 × 2 × 4 bands and 3 × 2 × 3 bands"), "{e}");
}

#[test]
fn truncated_data_is_an_error_for_every_length() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("t.hdr");
    let cube = test_cube(3, 2, 3);
    let (_, data) = write_cube(&p, &cube, &WriteOptions::default()).unwrap();
    let full = std::fs::read(&data).unwrap();
    for n in 0..full.len() {
        std::fs::write(&data, &full[..n]).unwrap();
        let e = read_cube(&p).unwrap_err().to_string();
        assert!(e.contains("too short") && e.contains("t.img"), "{n}: {e}");
    }
}

const GOOD: &str = "ENVI\ndescription = {\n fuzz base}\nsamples = 3\nlines = 2\nbands = 3\n\
header offset = 0\ndata type = 4\ninterleave = bil\nbyte order = 0\n\
wavelength units = nm\nwavelength = {400, 500, 600}\nfwhm = {5, 5, 5}\n\
reflectance scale factor = 1\n";

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn arbitrary_header_text_is_an_error_not_a_panic(text in "\\PC{0,400}") {
        // Without the magic on its first line no text is a header; with
        // it, random text is at most a header with a whole image's
        // dimensions, and any error names the file.
        if !text.trim_start().starts_with("ENVI") {
            let e = parse_header(&text, Path::new("fuzz.hdr"));
            prop_assert!(e.is_err(), "accepted without the magic: {:?}", text);
        }
        match parse_header(&format!("ENVI\n{text}"), Path::new("fuzz.hdr")) {
            Ok(h) => prop_assert!(h.samples > 0 && h.lines > 0 && h.bands > 0, "{:?}", text),
            Err(e) => prop_assert!(e.to_string().starts_with("fuzz.hdr"), "{}", e),
        }
    }

    #[test]
    fn garbled_headers_are_an_error_not_a_panic(
        cut in 0usize..GOOD.len(),
        len in 0usize..40,
        insert in "[ -~\n{}=;,]{0,20}",
    ) {
        let mut t: Vec<char> = GOOD.chars().collect();
        let end = (cut + len).min(t.len());
        t.splice(cut..end, insert.chars());
        let text: String = t.into_iter().collect();
        if let Err(e) = parse_header(&text, Path::new("fuzz.hdr")) {
            prop_assert!(e.to_string().starts_with("fuzz.hdr"));
        }
    }

    #[test]
    fn random_field_values_are_an_error_not_a_panic(
        key in prop::sample::select(vec!["samples", "lines", "bands", "data type",
            "interleave", "byte order", "header offset", "wavelength", "fwhm",
            "wavelength units", "reflectance scale factor", "data ignore value"]),
        value in "\\PC{0,30}",
    ) {
        let text = format!("{GOOD}{key} = {value}\n");
        if let Err(e) = parse_header(&text, Path::new("fuzz.hdr")) {
            let msg = e.to_string();
            prop_assert!(msg.contains(&format!("`{key}`")) || msg.contains("`bands`")
                || msg.contains("`samples`") || msg.contains("never closed")
                || msg.contains("`wavelength`") || msg.contains("`fwhm`"), "{}", msg);
        }
    }
}
