//! `irid synth` and `irid fit` as a user runs them: files written and read
//! back, error messages for bad input (non-zero exit, the field named, no
//! panic), and the synth → fit loop on the paper's cylinder.

mod cli_common;
use cli_common::{fails_with, ok, s};
use irid::io::envi::read_cube;
use irid::io::exr_maps::{read_channels, read_maps};
use irid::scene::Scene;
use irid::synth::{scene_bands, Renderer};
use std::path::{Path, PathBuf};
use std::process::Output;

fn scene_file() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes/paper-cylinder.toml")
}

#[test]
fn synth_writes_the_rendered_cube_and_its_truth() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cube.hdr");
    ok(&["synth", "--out", s(&out), "--seed", "7"]);
    let cube = read_cube(&out).unwrap();
    let mut file: irid::scene::SceneFile = toml::from_str(irid::scene::PAPER_CYLINDER).unwrap();
    file.truth.as_mut().unwrap().seed = 7;
    let scene = Scene::resolve(&file, Path::new(".")).unwrap();
    let bands = scene_bands(&scene).unwrap();
    let want = Renderer::new(&scene).unwrap().render_cube(&bands).unwrap();
    assert_eq!(cube, want, "f32 ENVI is lossless");
    let truth = read_channels(&dir.path().join("cube.truth.exr")).unwrap();
    assert_eq!((truth.width, truth.height), (140, 14));
    let t = truth.channel("thickness_nm").unwrap();
    assert_eq!((t[0], t[139]), (420.0, 560.0));
    let a = truth.channel("theta_deg").unwrap();
    assert_eq!((a[0], a[140 * 13]), (10.0, 42.5));
    assert!(truth.channel("n_film").unwrap().iter().all(|n| *n == 1.37));
}

#[test]
fn synth_scene_file_and_integer_formats() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.hdr");
    let b = dir.path().join("b.hdr");
    ok(&[
        "synth",
        "--scene",
        s(&scene_file()),
        "--out",
        s(&a),
        "--noise",
        "0",
    ]);
    ok(&[
        "synth",
        "--out",
        s(&b),
        "--noise",
        "0",
        "--data-type",
        "u16",
        "--interleave",
        "bip",
        "--big-endian",
    ]);
    let (ca, cb) = (read_cube(&a).unwrap(), read_cube(&b).unwrap());
    assert_eq!(ca.bands, cb.bands);
    let worst = ca
        .data
        .iter()
        .zip(&cb.data)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(worst <= 0.5 / 10000.0 + 1e-7, "u16 quantisation {worst}");
    let hdr = std::fs::read_to_string(&b).unwrap();
    assert!(hdr.contains("data type = 12") && hdr.contains("interleave = bip"));
    assert!(hdr.contains("byte order = 1") && hdr.contains("reflectance scale factor = 10000"));
}

#[test]
fn synth_errors() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("no-truth.toml");
    std::fs::write(&scene, "[substrate]\nn = 1.6\n").unwrap();
    let out = dir.path().join("x.hdr");
    fails_with(
        &["synth", "--scene", s(&scene), "--out", s(&out)],
        &["no [truth] section"],
    );
    fails_with(&["synth", "--out", s(&out), "--noise=-1"], &["--noise"]);
    fails_with(
        &["synth", "--out", s(&out), "--data-type", "c64"],
        &["data type"],
    );
}

#[test]
fn fit_reports_bad_headers_by_field() {
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/envi");
    let dir = tempfile::tempdir().unwrap();
    let maps = dir.path().join("m.exr");
    for (file, fragment) in [
        (
            "invalid/bad_interleave.hdr",
            "field `interleave`: unknown value \"bsx\"",
        ),
        ("invalid/wavelength_count.hdr", "field `wavelength`"),
        ("damaged/short_data.hdr", "data file too short"),
        ("damaged/binary_header.hdr", "not an ENVI header"),
    ] {
        let cube = fixtures.join(file);
        fails_with(
            &["fit", s(&cube), "--out", s(&maps), "--n3", "1.6"],
            &[fragment, cube.file_stem().unwrap().to_str().unwrap()],
        );
    }
    fails_with(
        &[
            "fit",
            "/nonexistent/c.hdr",
            "--out",
            s(&maps),
            "--n3",
            "1.6",
        ],
        &["c.hdr"],
    );
    assert!(!maps.exists());
}

#[test]
fn fit_argument_errors() {
    let dir = tempfile::tempdir().unwrap();
    let cube = dir.path().join("c.hdr");
    ok(&["synth", "--out", s(&cube), "--noise", "0"]);
    let maps = dir.path().join("m.exr");
    fails_with(&["fit", s(&cube), "--out", s(&maps)], &["--n3"]);
    fails_with(
        &[
            "fit",
            s(&cube),
            "--out",
            s(&maps),
            "--n3",
            "1.6",
            "--pol",
            "q",
        ],
        &["--pol"],
    );
    fails_with(
        &[
            "fit",
            s(&cube),
            "--out",
            s(&maps),
            "--n3",
            "1.6",
            "--theta-deg",
            "95",
        ],
        &["angle.deg"],
    );
    fails_with(
        &[
            "fit",
            s(&cube),
            "--out",
            s(&maps),
            "--n3",
            "1.6",
            "--dark",
            s(&cube),
        ],
        &["--white"],
    );
    // An angle map of the wrong size.
    let small = dir.path().join("small.exr");
    irid::io::exr_maps::write_single(&small, "theta_deg", 3, 2, &[20.0; 6]).unwrap();
    fails_with(
        &[
            "fit",
            s(&cube),
            "--out",
            s(&maps),
            "--n3",
            "1.6",
            "--theta-map",
            s(&small),
        ],
        &["3 × 2", "140 × 14"],
    );
    // Dark/white references of another size.
    let other = dir.path().join("o.hdr");
    let scene = dir.path().join("s.toml");
    std::fs::write(
        &scene,
        irid::scene::PAPER_CYLINDER.replace("width = 140", "width = 10"),
    )
    .unwrap();
    ok(&["synth", "--scene", s(&scene), "--out", s(&other)]);
    fails_with(
        &[
            "fit",
            s(&cube),
            "--out",
            s(&maps),
            "--n3",
            "1.6",
            "--dark",
            s(&other),
            "--white",
            s(&other),
        ],
        &["sizes differ", "o.hdr"],
    );
}

/// A filter 2 nm off its calibration: the cube rendered at 402–702 nm,
/// its header naming 400–700 nm. `auto` finds the shift (JSON, EXR
/// attribute) and the thicknesses are right; bad `--band-shift` values
/// are refused naming the option.
#[test]
fn fit_finds_a_filter_off_its_wavelength_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("shifted.toml");
    std::fs::write(
        &scene,
        irid::scene::PAPER_CYLINDER
            .replace("start_nm = 400", "start_nm = 402")
            .replace("stop_nm = 700", "stop_nm = 702"),
    )
    .unwrap();
    let cube = dir.path().join("cube.hdr");
    ok(&["synth", "--scene", s(&scene), "--out", s(&cube)]);
    let header = std::fs::read_to_string(&cube).unwrap();
    let nominal: Vec<String> = (0..31).map(|k| (400 + 10 * k).to_string()).collect();
    let start = header
        .find("wavelength = {")
        .expect("wavelengths in the header");
    let end = start + header[start..].find('}').unwrap() + 1;
    let fixed = format!(
        "{}wavelength = {{{}}}{}",
        &header[..start],
        nominal.join(", "),
        &header[end..]
    );
    std::fs::write(&cube, fixed).unwrap();
    let maps_path = dir.path().join("maps.exr");
    let j = fit_json(&cube, &maps_path, &[]);
    let (got, sigma) = (
        j["band_shift_nm"].as_f64().unwrap(),
        j["band_shift_sigma_nm"].as_f64().unwrap(),
    );
    assert!(sigma > 0.0 && (got - 2.0).abs() <= 3.0 * sigma, "{j}");
    let maps = read_maps(&maps_path).unwrap();
    assert!(
        maps.meta
            .quality
            .iter()
            .any(|(k, v)| k == "band_shift" && v.contains("fitted")),
        "{:?}",
        maps.meta.quality
    );
    // The header's wavelengths are kept as the cube named them.
    assert_eq!(maps.meta.wavelengths_nm[0], 400.0);
    let (valid, mae) = valid_and_mean_error(&maps_path, &dir.path().join("cube.truth.exr"));
    assert!(valid >= 1900, "{valid} valid");
    assert!(mae <= 0.5, "mean |error| {mae} nm");
    for bad in ["sideways", "60", "nan"] {
        fails_with(
            &[
                "fit",
                s(&cube),
                "--scene",
                s(&scene_file()),
                "--out",
                s(&maps_path),
                "--force",
                "--band-shift",
                bad,
            ],
            &["--band-shift"],
        );
    }
}

/// `irid fit CUBE --scene <the cylinder's> --out MAPS --json EXTRA…`, its
/// JSON summary.
fn fit_json(cube: &Path, maps: &Path, extra: &[&str]) -> serde_json::Value {
    let scene = scene_file();
    let mut args = vec![
        "fit",
        s(cube),
        "--scene",
        s(&scene),
        "--out",
        s(maps),
        "--json",
    ];
    args.extend_from_slice(extra);
    summary(&ok(&args))
}

/// The valid pixels of `maps` and their mean |Δd| against the truth
/// `irid synth` wrote beside `cube` (`NAME.truth.exr`).
fn valid_and_mean_error(maps: &Path, truth: &Path) -> (usize, f64) {
    let maps = read_maps(maps).unwrap();
    let truth = read_channels(truth).unwrap();
    let t = truth.channel("thickness_nm").unwrap();
    let errs: Vec<f64> = (0..t.len())
        .filter(|&i| maps.valid[i] > 0.5)
        .map(|i| (maps.thickness_nm[i] - t[i]).abs() as f64)
        .collect();
    let n = errs.len();
    (n, errs.iter().sum::<f64>() / n.max(1) as f64)
}

fn summary(out: &Output) -> serde_json::Value {
    let text = String::from_utf8(out.stdout.clone()).unwrap();
    assert_eq!(text.lines().count(), 1, "{text}");
    serde_json::from_str(text.trim()).unwrap()
}

#[test]
fn synth_then_fit_recovers_the_cylinder() {
    let dir = tempfile::tempdir().unwrap();
    let cube = dir.path().join("cube.hdr");
    ok(&["synth", "--out", s(&cube)]);
    let maps_path = dir.path().join("maps.exr");
    let j = fit_json(&cube, &maps_path, &["--threads", "2"]);
    for key in [
        "pixels",
        "valid_pixels",
        "n_film",
        "n_film_sigma",
        "elapsed_s",
        "pixels_per_s",
        "mode",
    ] {
        assert!(j.get(key).is_some(), "no {key} in {j}");
    }
    assert_eq!(j["pixels"], 1960);
    assert_eq!(j["mode"], "balanced");
    // A calibrated filter: no band shift taken, and the summary says why.
    assert_eq!(j["band_shift_nm"], 0.0);
    let note = j["band_shift_note"].as_str().unwrap();
    assert!(note.starts_with("none"), "{note}");
    let n = j["n_film"].as_f64().unwrap();
    assert!((n - 1.37).abs() < 0.001, "n_film {n}");
    let maps = read_maps(&maps_path).unwrap();
    assert_eq!(maps.meta.mode, "balanced");
    assert_eq!(maps.meta.wavelengths_nm.len(), 31);
    let (valid, mae) = valid_and_mean_error(&maps_path, &dir.path().join("cube.truth.exr"));
    assert!(valid as f64 >= 0.9 * 1960.0, "{valid} valid");
    assert!(mae <= 0.5, "mean |error| {mae} nm");
}

#[test]
fn fit_with_known_film_and_angle_map_from_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let cube = dir.path().join("cube.hdr");
    ok(&["synth", "--out", s(&cube)]);
    let truth_path = dir.path().join("cube.truth.exr");
    let maps_path = dir.path().join("maps.exr");
    let out = ok(&[
        "fit",
        s(&cube),
        "--out",
        s(&maps_path),
        "--n3",
        "1.6",
        "--n2",
        "1.37",
        "--theta-map",
        s(&truth_path),
        "--pol",
        "s",
        "--mode",
        "fast",
        "--json",
    ]);
    let j = summary(&out);
    assert_eq!(j["n_film"].as_f64(), Some(1.37));
    assert_eq!(j["n_film_sigma"].as_f64(), Some(0.0));
    assert_eq!(j["mode"], "fast");
    let maps = read_maps(&maps_path).unwrap();
    assert!(!maps.meta.n_film_estimated);
    let truth = read_channels(&truth_path).unwrap();
    let a = truth.channel("theta_deg").unwrap();
    for (i, th) in maps.theta_deg.iter().enumerate() {
        if maps.valid[i] > 0.5 {
            assert!((th - a[i]).abs() < 1e-4, "known angle changed at {i}");
        }
    }
    // The thickness. With film and angle known, every pixel of this scene
    // (two or more fringe extrema, σ_R = 0.001) is identifiable: all must
    // be valid but for the χ² test's nominal flags. The Cramér–Rao bound
    // is σ_d ≈ 0.28 nm per pixel (README):
    // no honest σ is below it. `fast` uses only the extrema, and the σ it
    // reports is its own (≈ 0.7 nm here); a Gaussian error of σ has a mean
    // |Δd| of √(2/π)·σ ≈ 0.8σ, so the mean |Δd| must be ≈ 0.6 nm: 1 nm
    // (and 1.5 × 0.8 × the mean σ) leaves room for the noise of 1960
    // pixels while a wrong fringe order (≈ λ/(2 n2 cos θ2) ≈ 180 nm) on
    // even a dozen pixels breaks it. A Gaussian error is within 3σ 99.7 %
    // of the time; ≥ 90 % allows σ to be somewhat optimistic.
    let d = truth.channel("thickness_nm").unwrap();
    let n = maps.valid.len();
    let valid: Vec<usize> = (0..n).filter(|&i| maps.valid[i] > 0.5).collect();
    // The χ² test flags about 0.5 % of clean pixels by design (p = 0.005).
    assert!(valid.len() * 100 >= 98 * n, "{} of {n} valid", valid.len());
    let err = |i: usize| f64::from((maps.thickness_nm[i] - d[i]).abs());
    let sigma = |i: usize| f64::from(maps.sigma_thickness_nm[i]);
    let count = valid.len() as f64;
    let mean = valid.iter().map(|&i| err(i)).sum::<f64>() / count;
    let mean_sigma = valid.iter().map(|&i| sigma(i)).sum::<f64>() / count;
    let within = valid.iter().filter(|&&i| err(i) <= 3.0 * sigma(i)).count() as f64 / count;
    let max = valid.iter().map(|&i| err(i)).fold(0.0, f64::max);
    let stats = format!(
        "mean |Δd| {mean:.3} nm, max {max:.3} nm, mean σ {mean_sigma:.3} nm, {:.1} % within 3σ",
        100.0 * within
    );
    assert!(mean < 1.0, "{stats}");
    assert!(mean < 1.5 * 0.8 * mean_sigma, "σ too small: {stats}");
    assert!((0.25..1.5).contains(&mean_sigma), "{stats}");
    assert!(within >= 0.90, "{stats}");
    // No pixel on a wrong fringe order.
    assert!(max < 10.0, "{stats}");
}

#[test]
fn fit_raw_counts_with_dark_and_white() {
    // Raw counts = dark + R · (white − dark) with R the synthetic reflectance.
    use irid::io::envi::{write_cube, DataType, WriteOptions};
    let dir = tempfile::tempdir().unwrap();
    let refl = dir.path().join("r.hdr");
    ok(&["synth", "--out", s(&refl)]);
    let r = read_cube(&refl).unwrap();
    let mut raw = r.clone();
    let (mut dark, mut white) = (r.clone(), r.clone());
    for i in 0..r.data.len() {
        let (d, w) = (100.0 + (i % 7) as f32, 3000.0 + (i % 13) as f32 * 10.0);
        dark.data[i] = d;
        white.data[i] = w;
        raw.data[i] = d + r.data[i] * (w - d);
    }
    let counts = WriteOptions {
        data_type: DataType::F32,
        reflectance_scale_factor: Some(1.0),
        ..Default::default()
    };
    for (name, c) in [("raw", &raw), ("dark", &dark), ("white", &white)] {
        write_cube(&dir.path().join(format!("{name}.hdr")), c, &counts).unwrap();
    }
    let p = |n: &str| dir.path().join(format!("{n}.hdr"));
    let out = ok(&[
        "fit",
        s(&p("raw")),
        "--out",
        s(&dir.path().join("m.exr")),
        "--scene",
        s(&scene_file()),
        "--dark",
        s(&p("dark")),
        "--white",
        s(&p("white")),
        "--json",
    ]);
    let j = summary(&out);
    assert!((j["n_film"].as_f64().unwrap() - 1.37).abs() < 0.001);
}
