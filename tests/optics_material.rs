//! The material library on the bundled refractiveindex.info files, on
//! hand-written fixtures (valid, invalid, damaged), and "an error, not a panic"
//! on mutated input.
//!
//! Reference indices are the published values of each source (not this
//! code's output); tolerances reflect how many digits those sources quote.

use irid::optics::dispersion::{Dispersion, OpticsError};
use irid::optics::material::{Material, MaterialLibrary, BUILTIN, DATA_DIR};
use proptest::prelude::*;

fn lib() -> MaterialLibrary {
    MaterialLibrary::default()
}

#[test]
fn sellmeier_files_give_the_published_indices() {
    // Malitson 1965: fused silica n = 1.45846 at the He d line (587.56 nm).
    // Dodge 1984: MgF2 n_o = 1.3777 at the Na D line, 589.3 nm (quoted to 1e-4).
    // Malitson & Dodge 1972: sapphire n_o = 1.76820 at 587.56 nm.
    for (name, lam, want, tol) in [
        ("SiO2-Malitson", 587.56, 1.45846, 2e-5),
        ("MgF2-Dodge-o", 589.3, 1.3777, 1e-4),
        ("Al2O3-Malitson-o", 587.56, 1.7682, 2e-4),
    ] {
        let n = lib().get(name).unwrap().index_at(lam).unwrap();
        assert!((n.re - want).abs() < tol && n.im == 0.0, "{name}: {n}");
    }
    // Devore 1951 (formula 4): n_o² = 5.913 + 0.2441/(λ² − 0.0803), λ in µm.
    let l: f64 = 0.55;
    let want = (5.913 + 0.2441 / (l * l - 0.0803)).sqrt();
    let n = lib().get("TiO2-Devore-o").unwrap().index_at(550.0).unwrap();
    assert!((n.re - want).abs() < 1e-12);
    // Luke 2015: n² − 1 = 3.0249 λ²/(λ² − 0.1353406²) + 40314 λ²/(λ² − 1239.842²).
    let l: f64 = 1.55;
    let want = (1.0
        + 3.0249 * l * l / (l * l - 0.1353406f64.powi(2))
        + 40314.0 * l * l / (l * l - 1239.842f64.powi(2)))
    .sqrt();
    let n = lib().get("Si3N4-Luke").unwrap().index_at(1550.0).unwrap();
    assert!((n.re - want).abs() < 1e-12);
}

/// The row of a bundled table at `lam_um`, read straight from the file text.
fn row(name: &str, lam_um: &str) -> (f64, f64, f64) {
    let text = BUILTIN.iter().find(|(n, _)| *n == name).unwrap().1;
    let line = text
        .lines()
        .map(str::trim)
        .find(|l| l.split_whitespace().next() == Some(lam_um))
        .unwrap();
    let v: Vec<f64> = line
        .split_whitespace()
        .map(|t| t.parse().unwrap())
        .collect();
    (v[0] * 1e3, v[1], v[2])
}

#[test]
fn tables_return_their_rows_and_interpolate_between() {
    for (name, a, b) in [
        ("Si-Green-2008", "5.0000e-01", "5.1000e-01"),
        ("PET-Zhang", "0.50", "0.51"),
        ("H2O-Hale", "0.500", "0.525"),
    ] {
        let m = lib().get(name).unwrap();
        let (la, na, ka) = row(name, a);
        let (lb, nb, kb) = row(name, b);
        let i = m.index_at(la).unwrap();
        assert!(
            (i.re - na).abs() < 1e-12 && (i.im - ka).abs() < 1e-18,
            "{name}: {i}"
        );
        let mid = m.index_at(0.5 * (la + lb)).unwrap();
        assert!(
            (mid.re - 0.5 * (na + nb)).abs() < 1e-12 && (mid.im - 0.5 * (ka + kb)).abs() < 1e-15
        );
    }
    // Silicon absorbs in the visible, PET barely, the formulas not at all.
    assert!(!lib()
        .get("Si-Green-2008")
        .unwrap()
        .dispersion
        .is_lossless_in(400.0, 700.0));
    assert!(lib()
        .get("SiO2-Malitson")
        .unwrap()
        .dispersion
        .is_lossless_in(400.0, 700.0));
}

#[test]
fn out_of_range_is_refused_naming_the_material() {
    match lib().get("SiO2-Malitson").unwrap().index_at(200.0) {
        Err(OpticsError::OutOfRange {
            what,
            min_nm,
            max_nm,
            ..
        }) => {
            assert_eq!(what, "SiO2-Malitson");
            assert!((min_nm - 210.0).abs() < 1e-9 && (max_nm - 6700.0).abs() < 1e-9);
        }
        other => panic!("{other:?}"),
    }
    // TiO2-Devore starts at 430 nm: the visible band's blue end is outside.
    let e = lib()
        .get("TiO2-Devore-o")
        .unwrap()
        .index_at(400.0)
        .unwrap_err();
    assert!(
        e.to_string().contains("TiO2-Devore-o") && e.to_string().contains("430"),
        "{e}"
    );
    assert!(lib()
        .get("Si-Green-2008")
        .unwrap()
        .index_at(1500.0)
        .is_err());
}

#[test]
fn resolve_accepts_names_and_paths() {
    let by_name = lib().resolve("MgF2-Dodge-o").unwrap();
    let by_case = lib().resolve("mgf2-dodge-o").unwrap();
    let path = format!("{DATA_DIR}/MgF2-Dodge-o.yml");
    let by_path = lib().resolve(&path).unwrap();
    assert_eq!(by_name, by_case);
    assert_eq!(by_name.dispersion, by_path.dispersion);
    assert_eq!(by_path.name, "MgF2-Dodge-o");
    assert!(MaterialLibrary::builtin().resolve("MgF2-Dodge-o").is_ok());
    let e = lib().resolve("Unobtainium").unwrap_err().to_string();
    assert!(
        e.contains("Unobtainium") && e.contains("SiO2-Malitson"),
        "{e}"
    );
    let e = lib().resolve("/nonexistent/x.yml").unwrap_err().to_string();
    assert!(e.contains("/nonexistent/x.yml"), "{e}");
}

#[test]
fn embedded_copies_match_the_repository_files() {
    for (name, text) in BUILTIN {
        let on_disk = std::fs::read_to_string(format!("{DATA_DIR}/{name}.yml")).unwrap();
        assert_eq!(&on_disk, text, "{name}");
    }
}

#[test]
fn formula_with_tabulated_k_combines_and_intersects_ranges() {
    let text = "DATA:\n  - type: formula 1\n    wavelength_range: 0.3 1.0\n    coefficients: 0 1.0 0.1\n  - type: tabulated k\n    data: |\n        0.40 0.0\n        0.80 0.2\n";
    let m = Material::from_yaml_str("fixture", text).unwrap();
    assert_eq!(m.dispersion.range_nm(), Some((400.0, 800.0)));
    let i = m.index_at(600.0).unwrap();
    let l: f64 = 0.6;
    let n = (1.0 + l * l / (l * l - 0.01)).sqrt();
    assert!((i.re - n).abs() < 1e-14 && (i.im - 0.1).abs() < 1e-14);
    assert!(m.index_at(350.0).is_err());
    assert!(matches!(m.dispersion, Dispersion::Combined { .. }));
    // Tabulated n plus tabulated k.
    let text = "DATA:\n  - type: tabulated n\n    data: |\n        0.4 1.5\n        0.8 1.4\n  - type: tabulated k\n    data: |\n        0.4 0.0\n        0.8 0.2\n";
    let i = Material::from_yaml_str("fixture", text)
        .unwrap()
        .index_at(600.0)
        .unwrap();
    assert!((i.re - 1.45).abs() < 1e-14 && (i.im - 0.1).abs() < 1e-14);
}

#[test]
fn damaged_files_are_errors_naming_file_and_field() {
    let cases: &[(&str, &str)] = &[
        ("", "-"),
        ("REFERENCES: x\n", "DATA"),
        ("DATA: 3\n", "DATA"),
        ("DATA: []\n", "DATA"),
        ("DATA:\n  - type: formula 1\n    wavelength_range: 0.2 7\n    coefficients: 0 abc 0.1\n", "DATA[0].coefficients"),
        ("DATA:\n  - type: formula 1\n    wavelength_range: 0.2 7\n    coefficients: 0 1.0\n", "DATA[0].coefficients"),
        ("DATA:\n  - type: formula 1\n    coefficients: 0 1.0 0.1\n", "DATA[0].wavelength_range"),
        ("DATA:\n  - type: formula 1\n    wavelength_range: 0.7 0.2\n    coefficients: 0 1.0 0.1\n", "DATA[0].wavelength_range"),
        ("DATA:\n  - type: formula 9\n    wavelength_range: 0.2 7\n    coefficients: 1 2 3\n", "DATA[0].type"),
        ("DATA:\n  - type: magic\n", "DATA[0].type"),
        ("DATA:\n  - coefficients: 1 2\n", "DATA[0].type"),
        ("DATA:\n  - type: tabulated nk\n    data: |\n        0.4 1.5 0\n        0.5 1.4\n", "DATA[0].data row 2"),
        ("DATA:\n  - type: tabulated nk\n    data: |\n        0.5 1.5 0\n        0.4 1.4 0\n", "DATA[0].data"),
        ("DATA:\n  - type: tabulated nk\n    data: |\n        0.4 1.5 -0.1\n        0.5 1.4 0\n", "DATA[0].data"),
        ("DATA:\n  - type: tabulated nk\n    data: |\n        0.4 1.5 nan\n        0.5 1.4 0\n", "DATA[0].data row 1"),
        ("DATA:\n  - type: tabulated k\n    data: |\n        0.4 0.1\n        0.5 0.1\n", "DATA"),
        ("DATA:\n  - type: tabulated nk\n", "DATA[0].data"),
        ("DATA:\n  - type: tabulated n\n    data: |\n        0.4 1.5\n        0.5 1.4\n  - type: tabulated nk\n    data: |\n        0.4 1.5 0\n        0.5 1.4 0\n", "DATA[1].type"),
        ("DATA: [unclosed\n", "-"),
    ];
    for (text, field) in cases {
        match Material::from_yaml_str("fixture.yml", text) {
            Err(OpticsError::File {
                file,
                field: f,
                message,
            }) => {
                assert_eq!(file, "fixture.yml");
                assert_eq!(&f, field, "{text:?}: {message}");
            }
            other => panic!("{text:?}: expected a file error at {field}, got {other:?}"),
        }
    }
    // From disk, the error names the path.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("broken.yml");
    std::fs::write(&p, "DATA:\n  - type: formula 1\n").unwrap();
    let e = Material::from_file(&p).unwrap_err().to_string();
    assert!(e.contains("broken.yml") && e.contains("DATA[0]"), "{e}");
    // And a directory added to the library is searched by name.
    std::fs::write(
        dir.path().join("Air.yml"),
        "DATA:\n  - type: formula 5\n    wavelength_range: 0.2 2\n    coefficients: 1.0003\n",
    )
    .unwrap();
    let air = MaterialLibrary::builtin()
        .with_dir(dir.path())
        .get("Air")
        .unwrap();
    assert!((air.index_at(500.0).unwrap().re - 1.0003).abs() < 1e-15);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    /// Truncated or byte-mutated real files: an error or a material, never a
    /// panic; a material that parses evaluates without panicking.
    #[test]
    fn mutated_files_never_panic(which in 0..BUILTIN.len(), cut in 0.0f64..1.0, pos in 0.0f64..1.0, byte in 0u8..128) {
        let text = BUILTIN[which].1;
        let mut bytes = text.as_bytes()[..(text.len() as f64 * cut) as usize].to_vec();
        if !bytes.is_empty() {
            let i = ((bytes.len() - 1) as f64 * pos) as usize;
            bytes[i] = byte;
        }
        let s = String::from_utf8_lossy(&bytes);
        if let Ok(m) = Material::from_yaml_str("mutated", &s) {
            // Whatever a mutated file parses to, an index it returns is a
            // physical one, and a wavelength that is none is refused.
            for l in [300.0, 500.0, 700.0, 1e9] {
                if let Ok(n) = m.index_at(l) {
                    prop_assert!(n.re.is_finite() && n.re > 0.0 && n.im.is_finite() && n.im >= 0.0,
                        "{} nm: {}", l, n);
                }
            }
            prop_assert!(m.index_at(-1.0).is_err());
        }
    }
}
