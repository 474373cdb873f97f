//! Colour physics and the film-colour comparison, checked against facts
//! that do not come from irid: the CIE tables' own sums and white points,
//! the sRGB standard's primaries and grey, and (end to end) the fit's
//! residual against the noise the cube was rendered with. Also the trade
//! chart's table parser on the README's own table.

mod cli_common;
use cli_common::{ok, s};
use irid::render::colour::{observer, srgb_encode, xyz_to_linear_srgb, xyz_to_srgb8, Cie};
use irid::render::trade::parse_table;
use std::path::Path;

#[test]
fn the_observer_integrates_to_equal_energy_white() {
    // The CIE 1931 functions are normalised so that the equal-energy
    // spectrum E has x = y = 1/3: the three sums agree (to 0.02 % over
    // 360–830 nm; the table's rounding).
    let obs = observer();
    assert_eq!(obs.len(), 471);
    let sum = |k: usize| obs.iter().map(|(_, v)| v[k]).sum::<f64>();
    let (x, y, z) = (sum(0), sum(1), sum(2));
    assert!((y - 106.857).abs() < 0.01, "Σȳ = {y}");
    let t = x + y + z;
    assert!((x / t - 1.0 / 3.0).abs() < 2e-4 && (y / t - 1.0 / 3.0).abs() < 2e-4);
}

#[test]
fn a_perfect_white_is_d65_and_renders_white() {
    // D65's white point over 360–830 nm from data/cie/SOURCE.md:
    // X, Y, Z = 95.0471, 100, 108.8829 (CIE 15:2004: 95.047, 100, 108.883).
    let xyz = Cie::get().xyz_of(|_| 1.0);
    for (got, want) in xyz.iter().zip([0.950471, 1.0, 1.088829]) {
        assert!((got - want).abs() < 2e-6, "{xyz:?}");
    }
    // sRGB's matrix maps D65 white to (1, 1, 1) within its 4-decimal
    // rounding.
    for c in xyz_to_linear_srgb(xyz) {
        assert!((c - 1.0).abs() < 2e-3, "{c}");
    }
    assert_eq!(xyz_to_srgb8(xyz, 1.0), [255, 255, 255]);
}

#[test]
fn an_18_percent_grey_card_is_srgb_118() {
    // The photographer's grey card: Y = 0.18 encodes to 0.4614 → 118/255,
    // neutral.
    let xyz = Cie::get().xyz_of(|_| 0.18);
    assert_eq!(xyz_to_srgb8(xyz, 1.0), [118, 118, 118]);
    assert!((srgb_encode(0.18) - 0.4614).abs() < 1e-4);
    assert_eq!(srgb_encode(0.002), 12.92 * 0.002, "linear toe");
}

#[test]
fn the_srgb_primaries_come_back_as_primaries() {
    // IEC 61966-2-1: the XYZ of the red, green and blue primaries.
    let prim = [
        [0.4124, 0.2126, 0.0193],
        [0.3576, 0.7152, 0.1192],
        [0.1805, 0.0722, 0.9505],
    ];
    for (k, p) in prim.iter().enumerate() {
        let rgb = xyz_to_linear_srgb(*p);
        for (j, c) in rgb.iter().enumerate() {
            let want = if j == k { 1.0 } else { 0.0 };
            assert!((c - want).abs() < 2e-3, "primary {k}: {rgb:?}");
        }
    }
    // Reflecting only beyond 600 nm: red, no green.
    let rgb = xyz_to_srgb8(
        Cie::get().xyz_of(|l| if l >= 600.0 { 1.0 } else { 0.0 }),
        1.0,
    );
    assert!(rgb[0] > 200 && rgb[1] < 60, "{rgb:?}");
}

#[test]
fn resynthesised_spectra_match_the_measured_cube_to_the_noise() {
    // The paper's cylinder, rendered with σ = 0.001; the fit leaves
    // 31 − 3 degrees of freedom a pixel (d, θ and the shared index ~0),
    // so the RMS of measured − re-synthesised is σ √(28/31) = 9.50e-4, to
    // about 1/√(2 · 60 000) ≈ 0.3 % statistically; 3 % allows for the
    // 14 flagged pixels and the index fit.
    let dir = tempfile::tempdir().unwrap();
    let cube = dir.path().join("cube.hdr");
    let maps = dir.path().join("maps.exr");
    let png = dir.path().join("colour.png");
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes/paper-cylinder.toml");
    ok(&["synth", "--out", s(&cube)]);
    ok(&["fit", s(&cube), "--out", s(&maps), "--scene", s(&scene)]);
    let out = ok(&[
        "render",
        s(&maps),
        "--colour",
        "--cube",
        s(&cube),
        "--scene",
        s(&scene),
        "--out",
        s(&png),
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    let rmse: f64 = text
        .split_whitespace()
        .nth(2)
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no RMSE in {text:?}"));
    let want = 0.001 * (28.0f64 / 31.0).sqrt();
    assert!(
        (rmse / want - 1.0).abs() < 0.03,
        "RMSE {rmse}, expected {want}"
    );

    // The two panels: the same colours to within what σ = 0.001 moves
    // them. At the picture's ×10 exposure a band's noise moves Y by up to
    // ~0.5 % (the end bands are held over ~half the visible range), which
    // the sRGB matrix (entries up to ~3) and gamma turn into σ ≈ 4 levels
    // a channel: a mean under 2 levels, and no sample beyond ~7σ.
    let cube = irid::io::envi::read_cube(&cube).unwrap();
    let maps = irid::io::exr_maps::read_maps(&maps).unwrap();
    let sc = irid::scene::Scene::load(&scene).unwrap();
    let cmp = irid::render::film_colour::compare(&cube, &maps, &sc, "t").unwrap();
    let (mut worst, mut total, mut n) = (0i32, 0i64, 0i64);
    for y in 0..cube.height {
        for x in 0..cube.width {
            if maps.valid[y * cube.width + x] < 0.5 {
                continue;
            }
            let at = |p: (usize, usize)| {
                cmp.image
                    .get(p.0 + x * cmp.scale, p.1 + y * cmp.scale)
                    .unwrap()
            };
            let (a, b) = (at(cmp.panels[0]), at(cmp.panels[1]));
            for k in 0..3 {
                let d = (a[k] as i32 - b[k] as i32).abs();
                worst = worst.max(d);
                total += d as i64;
                n += 1;
            }
        }
    }
    let mean = total as f64 / n as f64;
    assert!(
        mean < 2.0 && worst <= 30,
        "mean {mean} levels, worst {worst}"
    );
}

#[test]
fn the_readme_trade_table_parses() {
    let readme =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap();
    let rows = parse_table(&readme).unwrap();
    assert_eq!(rows.len(), 30, "5 scenes × 2 angle cases × 3 modes");
    let r = &rows[0];
    assert_eq!((r.mode.as_str(), r.angle_known), ("fast", false));
    // The first row read by hand (cells split on `|`, units by suffix),
    // whatever the numbers of the day are.
    let line = readme
        .lines()
        .find(|l| l.starts_with("| paper"))
        .expect("a paper row");
    let cells: Vec<&str> = line.split('|').map(str::trim).collect();
    let speed = |c: &str| -> f64 {
        let (v, unit) = c.split_once(' ').unwrap();
        v.parse::<f64>().unwrap() * if unit == "M" { 1e6 } else { 1e3 }
    };
    let nm = |c: &str| -> f64 { c.trim_end_matches(" nm").parse().unwrap() };
    let want = (speed(cells[4]), nm(cells[6]), nm(cells[8]));
    let got = (r.pixels_per_s, r.mean_err_nm, r.efficient_nm);
    assert!(
        (got.0 / want.0 - 1.0).abs() < 1e-9 && got.1 == want.1 && got.2 == want.2,
        "{got:?} vs {want:?}"
    );
    // No estimator beats the efficient error of its own case, but for
    // `fast` with the angle free, which shares each row's angle among its
    // pixels (a smoothness the per-pixel bound does not assume): that one
    // still cannot beat the bound with the angle known.
    for r in &rows {
        let floor = if r.mode == "fast" && !r.angle_known {
            rows.iter()
                .find(|k| k.scene == r.scene && k.angle_known && k.mode == r.mode)
                .expect("the known-angle case")
                .efficient_nm
        } else {
            r.efficient_nm
        };
        assert!(r.mean_err_nm >= 0.95 * floor, "{r:?}");
    }
    let broken = readme.replacen(&format!("| {} |", cells[4]), "| fast-ish |", 1);
    let e = parse_table(&broken).unwrap_err().to_string();
    assert!(e.contains("pixels/s"), "{e}");
    assert!(parse_table("no table here").is_err());
}
