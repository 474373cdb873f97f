//! `irid model` against closed forms evaluated here, independently of the
//! optics code: the bare interface at d = 0, the quarter-wave minimum and
//! the half-wave return to the bare substrate at normal incidence, and the
//! oblique Fresnel coefficients of a bare interface.

use std::process::{Command, Output};

fn irid(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_irid"))
        .args(args)
        .output()
        .expect("run irid")
}

fn model(args: &[&str]) -> Vec<(f64, f64)> {
    let mut all = vec!["model"];
    all.extend_from_slice(args);
    let out = irid(&all);
    assert!(
        out.status.success(),
        "irid {all:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| {
            let (a, b) = l.split_once(' ').expect("two columns");
            (a.parse().unwrap(), b.parse().unwrap())
        })
        .collect()
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-12 * b.abs().max(1e-3)
}

#[test]
fn bare_interface_at_zero_thickness() {
    let want = ((1.0f64 - 1.6) / (1.0 + 1.6)).powi(2);
    for pol in ["s", "p", "u", "0.3"] {
        let rows = model(&[
            "--n1",
            "1.0",
            "--n2",
            "1.37",
            "--k2",
            "0",
            "--n3",
            "1.6",
            "--k3",
            "0",
            "--d-nm",
            "0",
            "--theta-deg",
            "0",
            "--pol",
            pol,
            "--wavelengths",
            "400:700:10",
        ]);
        assert_eq!(rows.len(), 31);
        assert_eq!(rows[0].0, 400.0);
        assert_eq!(rows[30].0, 700.0);
        for (lam, r) in rows {
            assert!(close(r, want), "{pol} at {lam}: {r} vs {want}");
        }
    }
}

#[test]
fn quarter_and_half_wave_at_normal_incidence() {
    let (n1, n2, n3, d) = (1.0f64, 1.37f64, 1.6f64, 100.0f64);
    let quarter = 4.0 * n2 * d;
    let half = 2.0 * n2 * d;
    let list = format!("{quarter},{half}");
    let rows = model(&[
        "--n2",
        "1.37",
        "--n3",
        "1.6",
        "--d-nm",
        "100",
        "--wavelengths",
        &list,
    ]);
    let r_min = ((n1 * n3 - n2 * n2) / (n1 * n3 + n2 * n2)).powi(2);
    let r_bare = ((n1 - n3) / (n1 + n3)).powi(2);
    assert!(close(rows[0].1, r_min), "{} vs {r_min}", rows[0].1);
    assert!(close(rows[1].1, r_bare), "{} vs {r_bare}", rows[1].1);
}

#[test]
fn oblique_bare_interface_fresnel() {
    let (n1, n3) = (1.0f64, 1.5f64);
    let t1 = 30f64.to_radians();
    let c1 = t1.cos();
    let c3 = (1.0 - (n1 * t1.sin() / n3).powi(2)).sqrt();
    let rs = ((n1 * c1 - n3 * c3) / (n1 * c1 + n3 * c3)).powi(2);
    let rp = ((n3 * c1 - n1 * c3) / (n3 * c1 + n1 * c3)).powi(2);
    let args = |pol: &'static str| {
        vec![
            "--n2",
            "1.5",
            "--n3",
            "1.5",
            "--d-nm",
            "250",
            "--theta-deg",
            "30",
            "--pol",
            pol,
            "--wavelengths",
            "550",
        ]
    };
    assert!(close(model(&args("s"))[0].1, rs));
    assert!(close(model(&args("p"))[0].1, rp));
    assert!(close(model(&args("u"))[0].1, 0.5 * (rs + rp)));
}

#[test]
fn output_has_full_precision() {
    let rows = model(&[
        "--n2",
        "1.37",
        "--n3",
        "1.6",
        "--d-nm",
        "400",
        "--theta-deg",
        "30",
        "--wavelengths",
        "400:700:10",
    ]);
    let out = irid(&[
        "model",
        "--n2",
        "1.37",
        "--n3",
        "1.6",
        "--d-nm",
        "400",
        "--theta-deg",
        "30",
        "--wavelengths",
        "400:700:10",
    ]);
    let text = String::from_utf8(out.stdout).unwrap();
    // Shortest round-trip formatting: re-printing the parsed value gives the same text.
    for (line, (lam, r)) in text.lines().zip(rows) {
        assert_eq!(line, format!("{lam} {r}"));
    }
    // And not a fixed handful of decimals.
    assert!(text.lines().any(|l| l.len() > 20), "{text}");
}

#[test]
fn bad_arguments_fail_cleanly() {
    for (args, fragment) in [
        (
            vec![
                "model",
                "--n2",
                "1.4",
                "--n3",
                "1.6",
                "--d-nm",
                "1",
                "--pol",
                "x",
                "--wavelengths",
                "500",
            ],
            "--pol",
        ),
        (
            vec![
                "model",
                "--n2",
                "1.4",
                "--n3",
                "1.6",
                "--d-nm",
                "1",
                "--wavelengths",
                "700:400:10",
            ],
            "--wavelengths",
        ),
        (
            vec![
                "model",
                "--n2",
                "1.4",
                "--n3",
                "1.6",
                "--d-nm",
                "1",
                "--theta-deg",
                "95",
                "--wavelengths",
                "500",
            ],
            "--theta-deg",
        ),
        (
            vec![
                "model",
                "--n3",
                "1.6",
                "--d-nm",
                "1",
                "--wavelengths",
                "500",
            ],
            "--n2",
        ),
    ] {
        let out = irid(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} succeeded");
        assert!(err.contains(fragment), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
}
