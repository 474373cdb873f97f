//! The accuracy-against-noise chart (`irid render --noise`): its table
//! read back as printed (a round trip through the bench's own row format,
//! beside the scene-matrix table it must not be confused with), malformed
//! tables refused with an error that names the line, one series per mode
//! in the SVG and the PNG, the Cramér–Rao bound the bench draws as the
//! limit scaling linearly with the noise, the README's measured table, and
//! the command (`irid render --noise`) on it and on a file without one.

#[path = "../benches/common/mod.rs"]
mod bench_common;
mod cli_common;

use cli_common::{fails_with, ok, s};
use irid::render::canvas::decode_png;
use irid::render::noise::{parse_table, write_chart, NoiseRow, HEADER, SIZE};
use irid::scene::Scene;
use irid::synth::scene_bands;
use std::path::Path;

const MODES: [&str; 3] = ["fast", "balanced", "accurate"];
/// The modes' colours (the charts' palette, in the modes' order).
const COLOURS: [(&str, [u8; 3]); 3] = [
    ("#1F77B4", [31, 119, 180]),
    ("#FF7F0E", [255, 127, 14]),
    ("#2CA02C", [44, 160, 44]),
];

/// Two scenes × `modes` × four noise levels, with values over several
/// decades; on the second scene nothing is valid at the highest noise.
fn rows(modes: &[&str]) -> Vec<NoiseRow> {
    let mut out = Vec::new();
    for (si, (scene, known)) in [("paper: 420–560 nm, n | s", false), ("thin", true)]
        .into_iter()
        .enumerate()
    {
        for (mi, mode) in modes.iter().enumerate() {
            for (k, sigma) in [0.0003, 0.001, 0.003, 0.03].into_iter().enumerate() {
                let efficient = 367.891_234 * sigma * (1.0 + si as f64);
                let blow_up = 1.0 + (k * k * mi) as f64 * 0.37;
                let none_valid = si == 1 && k == 3;
                let measured = |v: f64| if none_valid { f64::NAN } else { v };
                out.push(NoiseRow {
                    scene: scene.to_string(),
                    angle_known: known,
                    mode: mode.to_string(),
                    sigma_r: sigma,
                    valid_fraction: if none_valid {
                        0.0
                    } else {
                        0.99412 - 0.1 * k as f64
                    },
                    mean_err_nm: measured(efficient * blow_up * 1.003_71),
                    p99_err_nm: measured(efficient * 3.87654 * blow_up),
                    efficient_nm: efficient,
                    coverage_2sigma: measured(0.95 + 0.001_23 * k as f64),
                    valid_wrong: measured(0.001 * k as f64),
                });
            }
        }
    }
    out
}

/// A README-like text: prose, the trade table first, then the noise table.
fn document(rows: &[NoiseRow]) -> String {
    let mut t = String::from(
        "# irid\n\nprose\n\n\
         | scene | angle | mode | pixels/s | valid | mean \\|Δd\\| | efficient |\n\
         |---|---|---|---|---|---|---|\n\
         | paper | unknown | `fast` | 1.02 M | 99.4 % | 0.683 nm | 0.368 nm |\n\n\
         ### Accuracy against noise\n\n",
    );
    t.push_str(HEADER);
    t.push('\n');
    for r in rows {
        t.push_str(&r.markdown());
        t.push('\n');
    }
    t.push_str("\nmore prose | with a bar\n");
    t
}

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a.is_nan() && b.is_nan()) || (a - b).abs() <= rel * b.abs()
}

#[test]
fn the_table_reads_back_as_printed() {
    let want = rows(&MODES);
    let text = document(&want);
    let got = parse_table(&text).unwrap();
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(&want) {
        assert_eq!(
            (&g.scene, g.angle_known, &g.mode),
            (&w.scene, w.angle_known, &w.mode)
        );
        // σ is printed exactly; lengths to four significant digits (half a
        // unit of the fourth: 5e-4 relative); fractions to 0.1 %.
        assert_eq!(g.sigma_r, w.sigma_r);
        for (a, b) in [
            (g.mean_err_nm, w.mean_err_nm),
            (g.p99_err_nm, w.p99_err_nm),
            (g.efficient_nm, w.efficient_nm),
        ] {
            assert!(close(a, b, 5e-4), "{a} vs {b}");
        }
        for (a, b) in [
            (g.valid_fraction, w.valid_fraction),
            (g.coverage_2sigma, w.coverage_2sigma),
            (g.valid_wrong, w.valid_wrong),
        ] {
            assert!(
                (a.is_nan() && b.is_nan()) || (a - b).abs() <= 5e-4,
                "{a} vs {b}"
            );
        }
        // Printing what was read gives the same line (but for the ratio,
        // which is derived from the unrounded values).
        let cells = |r: &NoiseRow| {
            let mut c: Vec<String> = r.markdown().split(" | ").map(String::from).collect();
            c.remove(8);
            c
        };
        assert_eq!(cells(g), cells(w));
    }
    // The scene-matrix reader takes its own table, not this one.
    let trade = irid::render::trade::parse_table(&text).unwrap();
    assert_eq!(trade.len(), 1);
    // A table measured before the "valid and wrong" column still reads,
    // that column unknown (NaN) and the others as they were.
    let old: String = text
        .lines()
        .map(|l| match l.rfind(" | ") {
            Some(i) if l.starts_with('|') && l.matches(" | ").count() == 10 => {
                format!("{} |", &l[..i])
            }
            _ if l.starts_with("|---|") && l.matches("---").count() == 11 => {
                "|---|---|---|---|---|---|---|---|---|---|".to_string()
            }
            _ => l.to_string(),
        })
        .collect::<Vec<_>>()
        .join("\n");
    assert!(!old.contains("valid and wrong"), "{old}");
    let before = parse_table(&old).unwrap();
    assert_eq!(before.len(), got.len());
    for (b, g) in before.iter().zip(&got) {
        assert!(b.valid_wrong.is_nan());
        assert_eq!(b.coverage_2sigma.to_bits(), g.coverage_2sigma.to_bits());
        assert_eq!(b.mean_err_nm.to_bits(), g.mean_err_nm.to_bits());
    }
}

#[test]
fn malformed_tables_are_errors_naming_the_line() {
    let good = document(&rows(&MODES));
    let e = |text: &str| parse_table(text).unwrap_err().to_string();
    assert!(e("no table here").contains("no noise-sweep table"));
    // The scene-matrix table alone is not a noise table.
    let trade_only: String = good.split("### Accuracy").next().unwrap().to_string();
    assert!(e(&trade_only).contains("no noise-sweep table"));
    // Header and rule but no rows.
    assert!(e(&format!("{HEADER}\n\ntext")).contains("no rows"));
    // A bad σ, a zero σ, an unknown angle word, a cut-off row, a missing
    // column: each an error with the table line, none a panic.
    let first = rows(&MODES)[0].markdown();
    let line_no = good.lines().position(|l| l == first).unwrap() + 1;
    for (from, to, what) in [
        ("| 0.0003 |", "| lots |", "noise σ"),
        ("| 0.0003 |", "| 0 |", "noise σ"),
        ("| unknown |", "| maybe |", "angle"),
    ] {
        let broken = good.replacen(&first, &first.replacen(from, to, 1), 1);
        let msg = e(&broken);
        assert!(
            msg.contains(what) && msg.contains(&format!("line {line_no}")),
            "{msg}"
        );
    }
    let cut: String = first.split(" nm |").next().unwrap().to_string() + " |";
    assert!(e(&good.replacen(&first, &cut, 1)).contains(&format!("line {line_no}")));
    let no_p99 = good.replacen("| p99 \\|Δd\\| |", "| p98 \\|Δd\\| |", 1);
    assert!(e(&no_p99).contains("p99"));
}

fn count(svg: &str, needle: &str) -> usize {
    svg.matches(needle).count()
}

/// The contents of the SVG's text elements, trimmed.
fn texts(svg: &str) -> Vec<String> {
    svg.split("<text")
        .skip(1)
        .filter_map(|t| {
            let body = t.split_once('>')?.1;
            Some(body.split("</text>").next()?.trim().to_string())
        })
        .collect()
}

fn svg_of(rows: &[NoiseRow]) -> String {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("noise.svg");
    write_chart(rows, "noise", &out).unwrap();
    std::fs::read_to_string(&out).unwrap()
}

#[test]
fn the_svg_has_one_line_per_mode_and_panel() {
    let svg = svg_of(&rows(&MODES));
    assert!(svg.trim_start().starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    for ((mode, (hex, _)), shape) in MODES.iter().zip(COLOURS).zip(["polygon", "circle", "rect"]) {
        // A line per panel (two) and the legend's sample.
        let lines = count(
            &svg,
            &format!("stroke=\"{hex}\" stroke-width=\"2\" points="),
        );
        assert_eq!(lines, 3, "{mode}: {lines} lines");
        // A marker per noise level with valid pixels in each panel (4 + 3),
        // one in the legend.
        let markers = svg
            .split('<')
            .filter(|t| t.starts_with(shape) && t.contains(&format!("fill=\"{hex}\"")))
            .count();
        assert_eq!(markers, 8, "{mode}: {markers} markers");
        let legend = texts(&svg).iter().filter(|t| t == mode).count();
        assert_eq!(legend, 1, "{mode} legend");
    }
    let t = texts(&svg);
    for want in [
        "Cramér–Rao-efficient",
        "reflectance noise σ per band",
        "mean |thickness error|, nm",
        "thin, angle known",
        "σ = 0.03: no valid pixel (all flagged)",
    ] {
        assert!(t.iter().any(|x| x == want), "no {want:?} in {t:?}");
    }
    assert_eq!(
        t.iter().filter(|x| x.contains("no valid pixel")).count(),
        1,
        "the note is in the second panel only"
    );
    // Where fewer than 90 % are valid, the panel says so per mode.
    let low = "σ = 0.03: valid fast 69 %, balanced 69 %, accurate 69 %";
    assert_eq!(t.iter().filter(|x| *x == low).count(), 1, "{t:?}");
    let low = "σ = 0.003: valid fast 79 %, balanced 79 %, accurate 79 %";
    assert_eq!(t.iter().filter(|x| *x == low).count(), 2, "{t:?}");
    let mut all_valid = rows(&MODES);
    all_valid.retain(|r| r.valid_fraction > 0.0);
    assert!(!texts(&svg_of(&all_valid))
        .iter()
        .any(|x| x.contains("no valid pixel")));
    // Without `accurate`, neither its line nor its legend entry.
    let svg = svg_of(&rows(&MODES[..2]));
    assert_eq!(count(&svg, &format!("stroke=\"{}\"", COLOURS[2].0)), 0);
    assert!(!texts(&svg).iter().any(|t| t == "accurate"));
    assert_eq!(
        count(
            &svg,
            &format!("stroke=\"{}\" stroke-width=\"2\" points=", COLOURS[0].0)
        ),
        3
    );
}

#[test]
fn the_png_shows_each_mode_in_its_colour() {
    let dir = tempfile::tempdir().unwrap();
    let pixels_of = |rows: &[NoiseRow]| {
        let out = dir.path().join("noise.png");
        write_chart(rows, "noise", &out).unwrap();
        let img = decode_png(&std::fs::read(&out).unwrap()).unwrap();
        assert_eq!((img.width as u32, img.height as u32), SIZE);
        COLOURS.map(|(_, rgb)| img.data.chunks(3).filter(|p| *p == rgb).count())
    };
    let all = pixels_of(&rows(&MODES));
    // Each mode: two lines across a panel and eight markers, hundreds of
    // pixels at least.
    assert!(all.iter().all(|n| *n > 300), "{all:?}");
    let two = pixels_of(&rows(&MODES[..2]));
    assert!(two[0] > 300 && two[1] > 300 && two[2] == 0, "{two:?}");
}

#[test]
fn the_bound_scales_linearly_with_the_noise() {
    // σ_CRB = σ_R √((JᵀJ)⁻¹)_dd: at ten times the noise, ten times the
    // bound, on both swept scenes and with the angle known or not.
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes");
    for name in ["paper-cylinder", "thin-coating"] {
        let scene = Scene::load(&dir.join(format!("{name}.toml"))).unwrap();
        let bands = scene_bands(&scene).unwrap();
        let (_, truth, _, _) = bench_common::render_tiled_clean(&scene, &bands, 1);
        let (u1, k1) = bench_common::crb(&scene, &bands, &truth, 0.0003);
        let (u2, k2) = bench_common::crb(&scene, &bands, &truth, 0.03);
        for (lo, hi) in [(u1, u2), (k1, k2)] {
            assert!(lo > 0.0 && lo.is_finite(), "{name}: {lo}");
            assert!(
                ((hi / lo) / 100.0 - 1.0).abs() < 1e-6,
                "{name}: {lo} → {hi}"
            );
        }
    }
}

#[test]
fn the_readme_noise_table_parses_and_its_bound_scales_as_sigma() {
    let readme =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap();
    let rows = parse_table(&readme).unwrap();
    assert_eq!(rows.len(), 30, "2 cases × 5 noise levels × 3 modes");
    // Within each case every mode at every σ, and the efficient error per
    // σ one constant (to the four printed digits: 5e-4 each way).
    for known in [false, true] {
        let case: Vec<&NoiseRow> = rows.iter().filter(|r| r.angle_known == known).collect();
        assert_eq!(case.len(), 15);
        let per_sigma = case[0].efficient_nm / case[0].sigma_r;
        for r in &case {
            assert!(MODES.contains(&r.mode.as_str()), "{r:?}");
            let k = r.efficient_nm / r.sigma_r;
            assert!(
                (k / per_sigma - 1.0).abs() < 1e-3,
                "{r:?}: {k} vs {per_sigma}"
            );
        }
    }
}

#[test]
fn the_command_draws_the_readme_and_refuses_a_file_without_a_table() {
    let dir = tempfile::tempdir().unwrap();
    let readme = Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md");
    let out = dir.path().join("noise.svg");
    ok(&["render", "--noise", s(&readme), "--out", s(&out)]);
    let svg = std::fs::read_to_string(&out).unwrap();
    assert!(MODES.iter().all(|m| texts(&svg).iter().any(|t| t == m)));
    // An existing picture is kept unless --force.
    fails_with(
        &["render", "--noise", s(&readme), "--out", s(&out)],
        &["noise.svg", "exists", "--force"],
    );
    assert_eq!(std::fs::read_to_string(&out).unwrap(), svg);
    ok(&["render", "--noise", s(&readme), "--out", s(&out), "--force"]);
    let empty = dir.path().join("notes.md");
    std::fs::write(&empty, "# notes\n\nno table\n").unwrap();
    let fresh = dir.path().join("fresh.svg");
    fails_with(
        &["render", "--noise", s(&empty), "--out", s(&fresh)],
        &["notes.md", "no noise-sweep table"],
    );
    assert!(
        !fresh.exists(),
        "nothing written for a file without a table"
    );
    fails_with(
        &[
            "render",
            "--noise",
            s(&readme),
            "--trade",
            s(&readme),
            "--out",
            s(&out),
        ],
        &["cannot be used with"],
    );
}
