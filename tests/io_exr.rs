//! OpenEXR maps and angle maps: round trips through temporary files, the
//! header attributes, non-ASCII metadata, damaged files (an error, not a
//! panic).

use irid::estimate::maps::MapMeta;
use irid::estimate::Cube;
use irid::estimate::{ParamMaps, PixelEstimate, Reason};
use irid::io::angle_map::load_degrees;
use irid::io::envi::{write_cube, WriteOptions};
use irid::io::exr_maps::{
    read_channels, read_maps, read_single, reason_legend, write_channels, write_maps, write_single,
    Channels,
};
use irid::optics::band::Band;

fn sample_maps() -> ParamMaps {
    let (w, h) = (7, 3);
    let mut m = ParamMaps::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let reason = if (x + y) % 5 == 0 {
                Reason::AmbiguousOrder
            } else if x == 6 {
                Reason::AngleNotIdentifiable
            } else {
                Reason::Ok
            };
            let e = PixelEstimate {
                thickness_nm: 420.0 + x as f64 + 0.125 * y as f64,
                n_film: 1.37,
                theta_deg: 10.0 + 2.5 * y as f64,
                sigma_thickness_nm: 0.3,
                sigma_theta_deg: 0.1,
                residual_rms: 1e-3,
                reason,
            };
            if reason.is_valid() {
                m.set(x, y, &e);
            } else {
                m.set(x, y, &PixelEstimate::invalid(reason));
            }
        }
    }
    m.meta = MapMeta {
        mode: "balanced".into(),
        wavelengths_nm: (0..31).map(|i| 400.0 + 10.0 * i as f64).collect(),
        fwhm_nm: vec![0.0; 31],
        n_film: 1.370_123_456_789,
        n_film_sigma: 1.5e-4,
        n_film_estimated: true,
        n_film_note: "twin n ≈ 1.17 rejected (Δχ² = 40), σ from 1960 px".into(),
        polarization: "s".into(),
        quality: vec![
            ("noise_sigma".into(), "0.001".into()),
            ("level".into(), "absolute".into()),
        ],
    };
    m
}

fn same_f32(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()))
}

#[test]
fn maps_round_trip_bit_exact_with_metadata() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("maps.exr");
    let m = sample_maps();
    write_maps(&p, &m).unwrap();
    let back = read_maps(&p).unwrap();
    assert_eq!((back.width, back.height), (m.width, m.height));
    for ((name, a), (_, b)) in m.channels().iter().zip(back.channels().iter()) {
        assert!(same_f32(a, b), "channel {name}");
    }
    assert_eq!(back.valid_count(), m.valid_count());
    assert_eq!(back.get(0, 0).reason, Reason::AmbiguousOrder);
    assert!(back.get(0, 0).thickness_nm.is_nan());
    assert_eq!(back.get(6, 1).reason, Reason::AngleNotIdentifiable);
    let (a, b) = (&m.meta, &back.meta);
    assert_eq!(b.mode, a.mode);
    assert_eq!(b.wavelengths_nm, a.wavelengths_nm);
    assert_eq!(b.fwhm_nm, a.fwhm_nm);
    assert_eq!(b.n_film, a.n_film);
    assert_eq!(b.n_film_sigma, a.n_film_sigma);
    assert_eq!(b.n_film_estimated, a.n_film_estimated);
    assert_eq!(b.polarization, a.polarization);
    // The note is transliterated to ASCII, not dropped and not a panic.
    assert_eq!(
        b.n_film_note,
        "twin n ~ 1.17 rejected (Delta chi^2 = 40), sigma from 1960 px"
    );
}

#[test]
fn map_file_header_documents_units_version_and_reasons() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("maps.exr");
    write_maps(&p, &sample_maps()).unwrap();
    let c = read_channels(&p).unwrap();
    let mut names: Vec<&str> = c.channels.iter().map(|(n, _)| n.as_str()).collect();
    names.sort();
    assert_eq!(
        names,
        [
            "n_film",
            "reason",
            "residual_rms",
            "sigma_theta_deg",
            "sigma_thickness_nm",
            "theta_deg",
            "thickness_nm",
            "valid"
        ]
    );
    assert_eq!(c.attribute("irid.version"), Some(irid::VERSION));
    assert_eq!(c.attribute("irid.units.thickness_nm"), Some("nm"));
    assert_eq!(c.attribute("irid.units.theta_deg"), Some("degrees"));
    assert_eq!(
        c.attribute("irid.reason_codes"),
        Some(reason_legend().as_str())
    );
    assert!(reason_legend().starts_with("0=ok; 1=non-finite input; 2=dark"));
    assert!(c
        .attribute("irid.wavelengths_nm")
        .unwrap()
        .starts_with("400,410,420"));
}

#[test]
fn missing_channel_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("one.exr");
    write_single(&p, "thickness_nm", 2, 2, &[1.0, 2.0, 3.0, 4.0]).unwrap();
    let e = read_maps(&p).unwrap_err().to_string();
    assert!(
        e.contains("no channel `n_film`") && e.contains("one.exr"),
        "{e}"
    );
}

#[test]
fn writer_refuses_inconsistent_input() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.exr");
    let c = Channels {
        width: 3,
        height: 2,
        channels: vec![("a".into(), vec![0.0; 5])],
        attributes: vec![],
    };
    let e = write_channels(&p, &c).unwrap_err().to_string();
    assert!(
        e.contains("channel `a` has 5 values for a 3 × 2 image"),
        "{e}"
    );
    let e = write_single(&p, "a", 0, 2, &[]).unwrap_err().to_string();
    assert!(e.contains("empty"), "{e}");
}

#[test]
fn damaged_exr_files_are_errors_not_panics() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("maps.exr");
    write_maps(&p, &sample_maps()).unwrap();
    let full = std::fs::read(&p).unwrap();
    let q = dir.path().join("cut.exr");
    let step = (full.len() / 97).max(1);
    for n in (0..full.len()).step_by(step) {
        std::fs::write(&q, &full[..n]).unwrap();
        assert!(read_maps(&q).is_err(), "truncated at {n} read fine");
    }
    // Flipped bytes: any outcome but a panic.
    for i in (0..full.len()).step_by(step) {
        let mut bad = full.clone();
        bad[i] ^= 0x5A;
        std::fs::write(&q, &bad).unwrap();
        let _ = read_maps(&q);
    }
}

#[test]
fn single_channel_picks_preferred_or_only() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x.exr");
    write_single(&p, "whatever", 3, 1, &[1.0, 2.0, 3.0]).unwrap();
    assert_eq!(
        read_single(&p, "theta_deg").unwrap(),
        (3, 1, vec![1.0, 2.0, 3.0])
    );
    let two = Channels {
        width: 1,
        height: 1,
        channels: vec![("a".into(), vec![1.0]), ("b".into(), vec![2.0])],
        attributes: vec![],
    };
    write_channels(&p, &two).unwrap();
    let e = read_single(&p, "theta_deg").unwrap_err().to_string();
    assert!(
        e.contains("2 channels (a, b) and none called `theta_deg`"),
        "{e}"
    );
}

#[test]
fn angle_map_from_exr_named_channel() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("angles.exr");
    let c = Channels {
        width: 2,
        height: 2,
        channels: vec![
            ("theta_deg".into(), vec![10.0, 20.0, 30.0, f32::NAN]),
            ("other".into(), vec![0.0; 4]),
        ],
        attributes: vec![],
    };
    write_channels(&p, &c).unwrap();
    let (w, h, d) = load_degrees(&p).unwrap();
    assert_eq!((w, h), (2, 2));
    assert_eq!(&d[..3], &[10.0, 20.0, 30.0]);
    assert!(d[3].is_nan());
}

fn envi_map(dir: &std::path::Path, name: &str, bands: usize, value: f32) -> std::path::PathBuf {
    let mut cube = Cube::zeros(
        3,
        2,
        (0..bands)
            .map(|i| Band {
                center_nm: 500.0 + i as f64,
                fwhm_nm: 0.0,
            })
            .collect(),
    );
    cube.data.iter_mut().for_each(|v| *v = value);
    let p = dir.join(format!("{name}.hdr"));
    write_cube(&p, &cube, &WriteOptions::default()).unwrap();
    p
}

#[test]
fn angle_map_from_envi() {
    let dir = tempfile::tempdir().unwrap();
    let p = envi_map(dir.path(), "theta", 1, 42.5);
    assert_eq!(load_degrees(&p).unwrap(), (3, 2, vec![42.5; 6]));
    let p = envi_map(dir.path(), "multi", 3, 42.5);
    let e = load_degrees(&p).unwrap_err().to_string();
    assert!(
        e.contains("multi.hdr: field `bands`: an angle map has one band, not 3"),
        "{e}"
    );
    let p = envi_map(dir.path(), "steep", 1, 95.0);
    let e = load_degrees(&p).unwrap_err().to_string();
    assert!(e.contains("outside [0°, 90°)"), "{e}");
}

#[test]
fn scene_angle_map_is_loaded_relative_to_the_scene() {
    let dir = tempfile::tempdir().unwrap();
    write_single(&dir.path().join("a.exr"), "theta_deg", 2, 1, &[12.0, 14.0]).unwrap();
    let toml = "[substrate]\nn = 1.6\n[angle]\nmap = \"a.exr\"\n";
    let scene = irid::scene::Scene::from_toml(toml, "t.toml", dir.path()).unwrap();
    match scene.angle {
        irid::scene::AngleKnowledge::Map { width, height, deg } => {
            assert_eq!((width, height, deg), (2, 1, vec![12.0, 14.0]));
        }
        other => panic!("{other:?}"),
    }
}
