//! `irid fit` on spectrum tables and with CSV output, as a user runs it:
//! spectra rendered with irid's own model (films of n = 1.46 on n = 1.52
//! at normal incidence) written as a table, fitted, and the thicknesses
//! read back from the CSV; a 1 nm spectrometer file averaged into bands;
//! cubes to CSV; errors naming the file and line; no partial output.

mod cli_common;
use cli_common::{fails_with, ok, s};
use irid::io::results_csv::HEADER;
use irid::optics::{airy, Complex64, Media, Polarization};
use std::path::Path;

const THICKNESSES: [f64; 3] = [300.0, 500.0, 800.0];

/// Model reflectance of a film of `d` nm (n = 1.46) on n = 1.52 in air at
/// normal incidence.
fn reflectance(d: f64, lam: f64) -> f64 {
    let media = Media {
        n1: Complex64::new(1.0, 0.0),
        n2: Complex64::new(1.46, 0.0),
        n3: Complex64::new(1.52, 0.0),
    };
    airy::reflectance(media, d, 0.0, lam, Polarization::S)
}

/// Rows `(wavelength as written, λ nm)`, rendered for [`THICKNESSES`] into
/// a table with separator `sep`.
fn table(header: Option<&str>, rows: &[(String, f64)], sep: &str) -> String {
    let mut text = String::from("# rendered by irid's model\n");
    if let Some(h) = header {
        text.push_str(h);
        text.push('\n');
    }
    for (w, lam) in rows {
        text.push_str(w);
        for d in THICKNESSES {
            text.push_str(&format!("{sep}{}", reflectance(d, *lam)));
        }
        text.push('\n');
    }
    text
}

struct Row {
    fields: Vec<String>,
}

impl Row {
    fn f(&self, i: usize) -> f64 {
        self.fields[i].parse().unwrap()
    }
}

/// The result CSV: its header checked, then the rows.
fn read_csv(path: &Path) -> Vec<Row> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some(HEADER));
    lines
        .map(|l| Row {
            fields: l.split(',').map(str::to_string).collect(),
        })
        .collect()
}

fn fit_args<'a>(input: &'a str, out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut v = vec![
        "fit",
        input,
        "--out",
        out,
        "--n3",
        "1.52",
        "--n2",
        "1.46",
        "--theta-deg",
        "0",
        // Tests here write `res` more than once.
        "--force",
    ];
    v.extend_from_slice(extra);
    v
}

fn assert_thicknesses(rows: &[Row], names: &[&str], tol: f64) {
    assert_eq!(rows.len(), THICKNESSES.len());
    for (x, (row, d)) in rows.iter().zip(THICKNESSES).enumerate() {
        assert_eq!(row.fields[0], names[x]);
        assert_eq!((row.f(1), row.f(2)), (x as f64, 0.0));
        assert_eq!(row.fields[9], "1", "valid: {:?}", row.fields);
        let got = row.f(3);
        assert!((got - d).abs() <= tol, "{}: {got} nm, want {d}", names[x]);
        assert!(row.f(4) >= 0.0, "σ {}", row.fields[4]);
        assert_eq!(row.fields[5], "1.46");
        assert_eq!(row.f(6), 0.0);
    }
}

#[test]
fn a_rendered_table_fits_back_to_its_thicknesses() {
    let dir = tempfile::tempdir().unwrap();
    let rows: Vec<(String, f64)> = (0..=300)
        .map(|i| {
            let lam = 400.0 + 2.0 * i as f64;
            (lam.to_string(), lam)
        })
        .collect();
    let input = dir.path().join("table.csv");
    std::fs::write(
        &input,
        table(Some("wavelength_nm,film300,film500,film800"), &rows, ","),
    )
    .unwrap();
    let res = dir.path().join("res.csv");
    let out = ok(&fit_args(s(&input), s(&res), &["--json"]));
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        (j["pixels"].as_u64(), j["valid_pixels"].as_u64()),
        (Some(3), Some(3))
    );
    // The noise reported is the data's (here the 1e-4 floor of a
    // noise-free table), not the σ the fits are judged with, which adds a
    // table's default 10 % reflectance accuracy: √(1e-8 + (0.1 · 0.05)²)
    // ≈ 5e-3 at R = 0.05.
    let sigma = j["noise_sigma"].as_f64().unwrap();
    assert!((0.99e-4..=2e-4).contains(&sigma), "noise_sigma {sigma}");
    let csv = read_csv(&res);
    assert_thicknesses(&csv, &["film300", "film500", "film800"], 1.0);
    for row in &csv {
        assert_eq!((&row.fields[10][..], &row.fields[11][..]), ("0", "ok"));
    }
    // No temporary file is left beside the result.
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert_eq!(names.len(), 2, "{names:?}");

    // The same table as OpenEXR maps, one pixel per spectrum.
    let maps = dir.path().join("res.exr");
    ok(&fit_args(s(&input), s(&maps), &[]));
    let m = irid::io::exr_maps::read_maps(&maps).unwrap();
    assert_eq!((m.width, m.height), (3, 1));
    for (x, d) in THICKNESSES.iter().enumerate() {
        assert!((f64::from(m.thickness_nm[x]) - d).abs() <= 1.0);
    }
}

#[test]
fn a_missing_value_leaves_the_fit_valid() {
    let dir = tempfile::tempdir().unwrap();
    let rows: Vec<(String, f64)> = (0..=60)
        .map(|i| {
            let lam = 400.0 + 10.0 * i as f64;
            (lam.to_string(), lam)
        })
        .collect();
    let mut text = table(None, &rows, " ");
    // A missing value in the second spectrum, on the 11th data row.
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    let mut cells: Vec<String> = lines[11].split(' ').map(str::to_string).collect();
    cells[2] = "nan".into();
    lines[11] = cells.join(" ");
    text = lines.join("\n");
    let input = dir.path().join("spectra.txt");
    std::fs::write(&input, text).unwrap();
    let res = dir.path().join("r.csv");
    ok(&fit_args(s(&input), s(&res), &[]));
    assert_thicknesses(
        &read_csv(&res),
        &["spectrum1", "spectrum2", "spectrum3"],
        1.0,
    );
}

/// A 1 nm spectrometer file from 250 nm to 1.2 µm, in µm, descending,
/// whitespace-separated: too many rows for the solver.
fn spectrometer_file(dir: &Path) -> std::path::PathBuf {
    let rows: Vec<(String, f64)> = (250..=1200)
        .rev()
        .map(|nm| (format!("{:.3}", nm as f64 / 1000.0), nm as f64))
        .collect();
    let input = dir.join("spectrometer.dat");
    std::fs::write(&input, table(Some("wavelength(um) a b c"), &rows, "\t")).unwrap();
    input
}

#[test]
fn a_fine_spectrometer_file_is_averaged_into_bands() {
    let dir = tempfile::tempdir().unwrap();
    let input = spectrometer_file(dir.path());
    let res = dir.path().join("res.csv");
    // 951 rows, more than the solver's 512 bands: every two averaged (475
    // bands of 2 nm, 250–1200 nm), said on the console, and fitted.
    let out = ok(&fit_args(s(&input), s(&res), &[]));
    let err = String::from_utf8_lossy(&out.stderr);
    for f in [
        "spectrometer.dat",
        "951 wavelengths",
        "every 2 averaged, into 475 bands of 2.000 nm",
        "--bands LO:HI:STEP",
    ] {
        assert!(err.contains(f), "{err:?} lacks {f:?}");
    }
    assert_thicknesses(&read_csv(&res), &["a", "b", "c"], 1.0);
    std::fs::remove_file(&res).unwrap();
    assert!(!res.exists());
    ok(&fit_args(s(&input), s(&res), &["--bands", "400:1000:4"]));
    assert_thicknesses(&read_csv(&res), &["a", "b", "c"], 1.0);
    // A range alone also brings the row count down.
    ok(&fit_args(
        s(&input),
        s(&res),
        &["--wavelength-range", "450:900"],
    ));
    assert_thicknesses(&read_csv(&res), &["a", "b", "c"], 1.0);
    // Bands past the table's end are left out, with a note.
    let out = ok(&fit_args(s(&input), s(&res), &["--bands", "1000:1400:5"]));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("40 of 81 bands have no table value"), "{err}");
    fails_with(
        &fit_args(s(&input), s(&res), &["--bands", "400:1000:1"]),
        &["601 bands", "at most 512"],
    );
    fails_with(
        &fit_args(s(&input), s(&res), &["--bands", "1300:1400:5"]),
        &["only 0 of 21 bands"],
    );
    fails_with(
        &fit_args(s(&input), s(&res), &["--bands", "400:1000"]),
        &["--bands", "LO:HI:STEP"],
    );
    fails_with(
        &fit_args(s(&input), s(&res), &["--wavelength-range", "400:401"]),
        &["--wavelength-range", "keeps 2 rows", "250–1200 nm"],
    );
}

#[test]
fn a_cube_to_csv() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("s.toml");
    std::fs::write(
        &scene,
        irid::scene::PAPER_CYLINDER
            .replace("width = 140", "width = 5")
            .replace("height = 14", "height = 2"),
    )
    .unwrap();
    let cube = dir.path().join("c.hdr");
    ok(&["synth", "--scene", s(&scene), "--out", s(&cube)]);
    let res = dir.path().join("c.CSV");
    ok(&[
        "fit",
        s(&cube),
        "--out",
        s(&res),
        "--scene",
        s(&scene),
        "--n2",
        "1.37",
        "--json",
    ]);
    let rows = read_csv(&res);
    assert_eq!(rows.len(), 10);
    assert_eq!(rows[0].fields[0], "x0y0");
    assert_eq!(rows[7].fields[0], "x2y1");
    assert_eq!((rows[7].f(1), rows[7].f(2)), (2.0, 1.0));
    for r in &rows {
        assert_eq!(r.fields.len(), 12);
        let d = r.f(3);
        assert!(d.is_nan() || (400.0..600.0).contains(&d), "{:?}", r.fields);
    }
    // Table options do not apply to cubes, nor dark/white to tables.
    fails_with(
        &[
            "fit",
            s(&cube),
            "--out",
            s(&res),
            "--scene",
            s(&scene),
            "--bands",
            "400:700:10",
        ],
        &["--bands", "ENVI"],
    );
    let t = dir.path().join("t.csv");
    std::fs::write(&t, "400,1\n410,1\n420,1\n430,1\n").unwrap();
    fails_with(
        &[
            "fit",
            s(&t),
            "--out",
            s(&res),
            "--n3",
            "1.5",
            "--dark",
            s(&cube),
            "--white",
            s(&cube),
        ],
        &["--dark", "spectrum table"],
    );
}

#[test]
fn table_errors_name_the_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.csv");
    std::fs::write(&bad, "wl,a,b\n400,1,2\n410,1\n420,1,2\n430,1,2\n").unwrap();
    let res = dir.path().join("res.csv");
    fails_with(
        &fit_args(s(&bad), s(&res), &[]),
        &["bad.csv", "line 3", "2 cells"],
    );
    assert!(!res.exists());
    fails_with(
        &fit_args(s(&dir.path().join("missing.csv")), s(&res), &[]),
        &["missing.csv"],
    );
    // A failed write leaves neither the result nor a temporary file.
    let rows: Vec<(String, f64)> = (0..=30)
        .map(|i| {
            let lam = 400.0 + 20.0 * i as f64;
            (lam.to_string(), lam)
        })
        .collect();
    let good = dir.path().join("good.csv");
    std::fs::write(&good, table(None, &rows, ",")).unwrap();
    let nowhere = dir.path().join("no-such-dir").join("res.csv");
    fails_with(&fit_args(s(&good), s(&nowhere), &[]), &["no-such-dir"]);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
}

/// Percent reflectance, as many spectrometers export it: columns headed
/// with `%` are divided by 100 (a note says so) and fit back to their
/// thicknesses; the same numbers without such a header are no reflectance
/// at all, and the error says what the values are and what to do
/// (nothing written).
#[test]
fn percent_tables_are_read_when_headed_and_refused_clearly_when_not() {
    let dir = tempfile::tempdir().unwrap();
    let rows: Vec<(String, f64)> = (0..=150)
        .map(|i| {
            let lam = 400.0 + 2.0 * i as f64;
            (lam.to_string(), lam)
        })
        .collect();
    let percent = |header: Option<&str>| {
        let mut text = String::new();
        if let Some(h) = header {
            text.push_str(h);
            text.push('\n');
        }
        for (w, lam) in &rows {
            text.push_str(w);
            for d in THICKNESSES {
                text.push_str(&format!("\t{}", 100.0 * reflectance(d, *lam)));
            }
            text.push('\n');
        }
        text
    };
    let headed = dir.path().join("headed.txt");
    std::fs::write(
        &headed,
        percent(Some("Wavelength (nm)\tR300 (%)\t%R 500\tR800 [%]")),
    )
    .unwrap();
    let res = dir.path().join("res.csv");
    let out = ok(&fit_args(s(&headed), s(&res), &[]));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("3 spectrum column(s) headed in percent divided by 100"),
        "{err}"
    );
    let csv = read_csv(&res);
    assert_thicknesses(&csv, &["R300 (%)", "%R 500", "R800 [%]"], 1.0);

    let bare = dir.path().join("bare.txt");
    std::fs::write(&bare, percent(None)).unwrap();
    let res2 = dir.path().join("res2.csv");
    fails_with(
        &fit_args(s(&bare), s(&res2), &[]),
        &[
            "reflectance's range",
            "percent? divide by 100",
            "--level free",
        ],
    );
    assert!(!res2.exists());
    // Told so, the same file fits.
    ok(&fit_args(s(&bare), s(&res2), &["--percent"]));
    assert_thicknesses(
        &read_csv(&res2),
        &["spectrum1", "spectrum2", "spectrum3"],
        1.0,
    );
}

/// A spectrometer file the model did not render: a film of a dispersive
/// index (n = 1.56 + 6000/λ², PS-like) on n = 3.9, fitted with one index;
/// the reflectance scale off by a smooth 0–4 % (a reference's error); noise
/// ten times larger at the range's ends than in its middle (a detector's
/// response); and a zero written at the last row. The thickness is read
/// within 2 % and valid under the default accuracy of a table (10 % of R)
/// where the dispersion leaves the fringes in place (thin films; a 610 nm
/// film is valid and right, or flagged "poor fit");
/// judged as exact (`--reflectance-accuracy 0 --level absolute`) the same
/// file fails the fit test; the spike is replaced, with a note; and with the index unknown the
/// result is valid and within 3σ, or flagged.
#[test]
fn a_spectrometer_file_is_judged_with_its_reflectance_accuracy() {
    let dir = tempfile::tempdir().unwrap();
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    let mut gauss = move || {
        // Sum of 12 uniforms, less 6: unit variance, deterministic.
        let mut acc = 0.0;
        for _ in 0..12 {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            acc += (seed >> 11) as f64 / (1u64 << 53) as f64;
        }
        acc - 6.0
    };
    for d in [95.0, 240.0, 610.0] {
        let mut text = String::from("wavelength_nm,film\n");
        for nm in 401..=1000 {
            let lam = nm as f64;
            let media = Media {
                n1: Complex64::new(1.0, 0.0),
                n2: Complex64::new(1.56 + 6000.0 / (lam * lam), 0.0),
                n3: Complex64::new(3.9, 0.0),
            };
            let r = airy::reflectance(media, d, 0.0, lam, Polarization::S);
            let gain = 1.0 + 0.04 * (lam - 401.0) / 599.0;
            let u = (lam - 700.0) / 300.0;
            let sigma = 3e-4 * (1.0 + 9.0 * u.powi(8));
            let v = if nm == 1000 {
                0.0
            } else {
                gain * r + sigma * gauss()
            };
            text.push_str(&format!("{nm},{v:.5}\n"));
        }
        let input = dir.path().join(format!("film{d}.csv"));
        std::fs::write(&input, text).unwrap();
        let res = dir.path().join("res.csv");
        let args = |extra: &[&'static str]| {
            let mut v: Vec<String> = [
                "fit",
                s(&input),
                "--out",
                s(&res),
                "--n3",
                "3.9",
                "--theta-deg",
                "0",
                "--force",
            ]
            .iter()
            .map(|a| a.to_string())
            .collect();
            v.extend(extra.iter().map(|a| a.to_string()));
            v
        };
        let run = |extra: &[&'static str]| {
            let a = args(extra);
            let refs: Vec<&str> = a.iter().map(String::as_str).collect();
            let out = ok(&refs);
            (
                String::from_utf8_lossy(&out.stderr).to_string(),
                read_csv(&res).remove(0),
            )
        };
        let (err, row) = run(&["--n2", "1.59"]);
        assert!(
            err.contains("1 isolated spike(s) replaced") && err.contains("1000 nm"),
            "{err}"
        );
        assert!(err.contains("accurate to 10.0 % of R"), "{err}");
        if d < 300.0 {
            assert_eq!(row.fields[9], "1", "{d} nm: {:?}", row.fields);
        } else if row.fields[9] == "0" {
            // Thicker, the index's dispersion shifts the fringes by more
            // than any scale error: one index is the wrong material.
            assert_eq!(row.fields[9..], ["0", "7", "poor fit"], "{d} nm");
            continue;
        }
        let got = row.f(3);
        assert!((got - d).abs() <= 0.02 * d, "{d} nm read {got}");
        // (`auto` may find and correct the scale error itself: absolute.)
        let (_, exact) = run(&[
            "--n2",
            "1.59",
            "--reflectance-accuracy",
            "0",
            "--level",
            "absolute",
        ]);
        assert_eq!(exact.fields[9..], ["0", "7", "poor fit"], "{d} nm");
        let (_, free) = run(&[]);
        if free.fields[9] == "1" {
            let (got, sigma) = (free.f(3), free.f(4));
            assert!(
                (got - d).abs() <= (0.1 * d).max(3.0 * sigma),
                "{d} nm, index unknown: {got} ± {sigma}"
            );
        }
    }
}
