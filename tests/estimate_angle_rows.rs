//! `fast` with the angle free, solved row by row on each row's estimated
//! angle (`src/estimate/solver/angle_map.rs`): checked against the truth
//! and against every pixel fitted alone (the angle-free fit, a fresh
//! scratch), on the bundled scenes and on cubes rendered here with angle
//! fields the scenes' own renderer does not make.
//!
//! What a row's angle may claim: its pixels are fitted with the angle of a
//! line through a sample of free fits, so a pixel's thickness error is its
//! known-angle error plus the line's. Tolerances: the 2σ coverage of an
//! honest σ is 95.4 % and the mean of (Δd/σ)² is 1. A row's pixels share
//! their line's angle error, so where it dominates σ_d (the thick hard
//! coat) both are means over the rows, not the pixels (14–24 rows a
//! scene): coverage ≥ 0.88 catches a σ that ignores the line's error
//! (≪ 0.9 on the thick hard coat), and (Δd/σ)² in [0.3, 1.6] one that is
//! the lone fit's (~0.05–0.3 where the line is much sharper than a pixel's
//! angle).

mod scene_common;
use irid::estimate::solver::Scratch;
use irid::estimate::{Cube, Mode, ParamMaps, PixelEstimate, Reason, Solver};
use irid::scene::{FilmKnowledge, Scene};
use irid::synth::{add_noise, scene_bands, Renderer, TruthMaps};
use scene_common::point_model;
use std::path::Path;

/// A bundled scene, `width` × `height`, noise seed 5, with its noise σ
/// and film given to the estimator: a few rows of a steep scene read the
/// σ estimated from the data high, and a film index estimated from them
/// shares its error with every pixel (its share of σ then dominates on
/// thick films, and one draw of it covers all pixels or none) — either
/// would hide what the rows' own σ claims.
fn bundled(name: &str, width: usize, height: usize) -> Scene {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("data/scenes/{name}.toml"));
    let mut s = Scene::load(&path).expect("the bundled scene loads");
    let t = s.truth.as_mut().expect("the scene has a truth");
    (t.width, t.height, t.seed) = (width, height, 5);
    s.noise_sigma = Some(t.noise_sigma);
    s.film = FilmKnowledge::Known(t.film.clone());
    s
}

/// Every pixel of `cube` fitted alone (a fresh scratch: no row, no line).
fn lone_fits(solver: &Solver, cube: &Cube) -> Vec<PixelEstimate> {
    let mut spec = vec![0.0; cube.bands.len()];
    let mut out = Vec::with_capacity(cube.width * cube.height);
    for y in 0..cube.height {
        for x in 0..cube.width {
            cube.spectrum_into(x, y, &mut spec);
            out.push(solver.solve_pixel(&spec, None, &mut Scratch::default()));
        }
    }
    out
}

/// Scene `s` rendered (its truth's noise) and fitted in `fast`, rows on
/// their angle and every pixel alone: the solver, the rows' maps, the lone
/// fits and the truth.
fn rows_and_lone(s: &Scene) -> (Solver, ParamMaps, Vec<PixelEstimate>, TruthMaps) {
    let bands = scene_bands(s).unwrap();
    let r = Renderer::new(s).unwrap();
    let cube = r.render_cube(&bands).unwrap();
    let truth = r.truth_maps(&bands);
    let mut solver = Solver::new(s, &bands, Mode::Fast).unwrap();
    let rows = solver.fit_cube(&cube).unwrap();
    let lone = lone_fits(&solver, &cube);
    (solver, rows, lone, truth)
}

/// Over the valid pixels: count, mean |Δd|, the fraction within 2σ, the
/// count off by more than max(3σ, 2 nm) (valid and wrong), and the mean of
/// (Δd/σ)² (each capped at 25: the wrong are counted apart).
fn score(d: &[f64], sigma: &[f64], valid: &[bool], truth: &[f32]) -> Score {
    let (mut n, mut sum, mut within, mut wrong, mut z2) = (0, 0.0, 0, 0, 0.0);
    for i in 0..d.len() {
        if !valid[i] {
            continue;
        }
        let e = (d[i] - f64::from(truth[i])).abs();
        n += 1;
        sum += e;
        within += usize::from(e <= 2.0 * sigma[i]);
        wrong += usize::from(e > (3.0 * sigma[i]).max(2.0));
        z2 += (e / sigma[i]).powi(2).min(25.0);
    }
    let n1 = n.max(1) as f64;
    (n, sum / n1, within as f64 / n1, wrong, z2 / n1)
}

/// See [`score`].
type Score = (usize, f64, f64, usize, f64);

fn score_maps(m: &ParamMaps, truth: &[f32]) -> Score {
    let d: Vec<f64> = m.thickness_nm.iter().map(|&v| f64::from(v)).collect();
    let s: Vec<f64> = m.sigma_thickness_nm.iter().map(|&v| f64::from(v)).collect();
    let v: Vec<bool> = m.valid.iter().map(|&v| v > 0.5).collect();
    score(&d, &s, &v, truth)
}

fn score_lone(p: &[PixelEstimate], truth: &[f32]) -> Score {
    let d: Vec<f64> = p.iter().map(|e| e.thickness_nm).collect();
    let s: Vec<f64> = p.iter().map(|e| e.sigma_thickness_nm).collect();
    let v: Vec<bool> = p.iter().map(|e| e.is_valid()).collect();
    score(&d, &s, &v, truth)
}

/// The fraction of valid pixels whose angle lies within 3 σ_θ of the truth.
fn angle_within_3_sigma(m: &ParamMaps, truth_deg: &[f32]) -> f64 {
    let (mut n, mut ok) = (0, 0);
    for (i, t) in truth_deg.iter().enumerate() {
        if m.valid[i] > 0.5 {
            n += 1;
            let e = (m.theta_deg[i] - t).abs();
            ok += usize::from(e <= 3.0 * m.sigma_theta_deg[i] + 1e-4);
        }
    }
    ok as f64 / n.max(1) as f64
}

/// On every bundled scene class the rows are at least as accurate as the
/// lone fits (the line's angle is sharper than any one pixel's), as often
/// valid, no more often valid and wrong (≤ 1 %), with a σ whose 2σ
/// coverage is honest from both sides, and an angle whose σ_θ covers the
/// truth.
#[test]
fn rows_on_their_angle_beat_lone_fits_with_an_honest_sigma() {
    for (name, w, h) in [
        ("paper-cylinder", 280, 14),
        ("thin-coating", 340, 16),
        ("wide-range", 280, 16),
        ("thick-hardcoat", 300, 24),
        ("dispersive-p61", 240, 16),
    ] {
        let (_, rows, lone, truth) = rows_and_lone(&bundled(name, w, h));
        let (nr, mae_r, cov_r, wrong_r, z2_r) = score_maps(&rows, &truth.thickness_nm);
        let (nl, mae_l, cov_l, wrong_l, _) = score_lone(&lone, &truth.thickness_nm);
        let angle_ok = angle_within_3_sigma(&rows, &truth.theta_deg);
        eprintln!(
            "{name}: rows {nr} valid, MAE {mae_r:.3} nm, 2σ {cov_r:.3}, (Δd/σ)² {z2_r:.2}, {wrong_r} wrong, angle ok {angle_ok:.3}; \
             lone {nl} valid, MAE {mae_l:.3} nm, 2σ {cov_l:.3}, {wrong_l} wrong"
        );
        let total = w * h;
        assert!(nr + total / 100 >= nl, "{name}: {nr} valid rows, {nl} lone");
        assert!(mae_r <= 1.02 * mae_l, "{name}: MAE {mae_r} vs lone {mae_l}");
        assert!(
            wrong_r * 100 <= nr,
            "{name}: {wrong_r} of {nr} valid and wrong"
        );
        assert!(cov_r >= 0.88, "{name}: 2σ coverage {cov_r}");
        // From above: a σ the lone fit's would give (Δd/σ)² ~0.05–0.3
        // here; the thick hard coat's rows, whose σ is the line's angle
        // error, are conservative by 1.6× (0.38).
        assert!((0.3..1.6).contains(&z2_r), "{name}: mean (Δd/σ)² {z2_r}");
        assert!(angle_ok >= 0.95, "{name}: angle within 3σ_θ on {angle_ok}");
    }
}

/// A film on PET seen at angles `theta(x, y)` (degrees), thicknesses
/// `d(x, y)`, σ_R = 0.002 given to the estimator: a cube rendered here, so
/// the angle field is any function, not one the scene format names.
fn cube_with_angles(
    (w, h): (usize, usize),
    d: impl Fn(usize, usize) -> f64,
    theta: impl Fn(usize, usize) -> f64,
) -> (Scene, Cube, Vec<f32>, Vec<f32>) {
    let text = r#"
[ambient]
n = 1.0
[substrate]
material = "PET-Zhang"
[film]
material = "SiO2-Malitson"
[angle]
search_deg = [0.0, 80.0]
[light]
polarization = "s"
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[measurement]
noise_sigma = 0.002
"#;
    let s = Scene::from_toml(text, "<test>", Path::new(".")).unwrap();
    assert!(matches!(s.film, FilmKnowledge::Known(_)));
    let bands = scene_bands(&s).unwrap();
    let model = point_model(&s, &bands);
    let mut cube = Cube::zeros(w, h, bands.clone());
    let mut out = irid::estimate::model::ModelOut::new(bands.len());
    let (mut td, mut tt) = (vec![0f32; w * h], vec![0f32; w * h]);
    for y in 0..h {
        for x in 0..w {
            let (dd, th) = (d(x, y), theta(x, y));
            model.eval(dd, th.to_radians(), &mut out, false);
            for (k, r) in out.r[..bands.len()].iter().enumerate() {
                cube.plane_mut(k)[y * w + x] = *r as f32;
            }
            td[y * w + x] = dd as f32;
            tt[y * w + x] = th as f32;
        }
    }
    add_noise(&mut cube.data, 0.002, 11);
    (s, cube, td, tt)
}

/// The angle changing along the rows, linearly (a cylinder whose axis runs
/// down the image): each row's line follows the slope, and its pixels'
/// angles and thicknesses are right within their σ.
#[test]
fn a_rows_angle_that_changes_along_it_is_followed() {
    let (w, h) = (320, 4);
    let (s, cube, td, tt) = cube_with_angles(
        (w, h),
        |x, _| 300.0 + 2.5 * x as f64,
        |x, y| 22.0 + 0.05 * x as f64 + 3.0 * y as f64,
    );
    let mut solver = Solver::new(&s, &cube.bands, Mode::Fast).unwrap();
    let rows = solver.fit_cube(&cube).unwrap();
    let lone = lone_fits(&solver, &cube);
    let (nr, mae_r, cov_r, wrong_r, z2_r) = score_maps(&rows, &td);
    let (nl, mae_l, _, _, _) = score_lone(&lone, &td);
    let angle_ok = angle_within_3_sigma(&rows, &tt);
    eprintln!("sloped rows: {nr} valid, MAE {mae_r:.3} (lone {nl}, {mae_l:.3}), 2σ {cov_r:.3}, (Δd/σ)² {z2_r:.2}, {wrong_r} wrong, angle {angle_ok:.3}");
    assert!(nr + w * h / 100 >= nl);
    assert!(mae_r <= 1.02 * mae_l, "MAE {mae_r} vs lone {mae_l}");
    assert!(wrong_r * 100 <= nr, "{wrong_r} of {nr} valid and wrong");
    assert!((0.88..=0.995).contains(&cov_r), "2σ coverage {cov_r}");
    assert!((0.5..1.6).contains(&z2_r), "mean (Δd/σ)² {z2_r}");
    assert!(angle_ok >= 0.95, "angle within 3σ_θ on {angle_ok}");
    // The line follows the slope: a row's first and last valid angles are
    // ~16° apart, not one angle for the row.
    let row0: Vec<f32> = (0..w)
        .filter(|&x| rows.valid[x] > 0.5)
        .map(|x| rows.theta_deg[x])
        .collect();
    let span = row0.last().unwrap() - row0.first().unwrap();
    assert!((14.0..18.0).contains(&span), "row 0's angle spans {span}°");
}

/// An angle that waves along the row (±6° over 60 pixels: a rippled web)
/// follows no line: its samples scatter about one far beyond their σ, the
/// row is refused, and every pixel takes the free fit, exactly as alone
/// in its verdict and within its σ in its value; nothing valid is wrong.
#[test]
fn a_row_whose_angle_follows_no_line_is_fitted_pixel_by_pixel() {
    let (w, h) = (320, 3);
    let (s, cube, td, _) = cube_with_angles(
        (w, h),
        |x, _| 400.0 + 2.0 * x as f64,
        |x, _| 35.0 + 6.0 * (std::f64::consts::TAU * x as f64 / 60.0).sin(),
    );
    let mut solver = Solver::new(&s, &cube.bands, Mode::Fast).unwrap();
    let rows = solver.fit_cube(&cube).unwrap();
    let lone = lone_fits(&solver, &cube);
    let (nr, _, cov_r, wrong_r, _) = score_maps(&rows, &td);
    let (mut same_reason, mut close) = (0, 0);
    for (i, p) in lone.iter().enumerate() {
        same_reason += usize::from(rows.reason[i] as u8 == p.reason as u8);
        if p.is_valid() && rows.valid[i] > 0.5 {
            let dd = (f64::from(rows.thickness_nm[i]) - p.thickness_nm).abs();
            close += usize::from(dd <= 0.65 * p.sigma_thickness_nm);
        }
    }
    eprintln!("waving angle: {nr} valid, 2σ {cov_r:.3}, {wrong_r} wrong; {same_reason} verdicts as alone, {close} within 0.65σ");
    assert!(nr * 10 >= w * h * 9, "{nr} valid");
    assert!(wrong_r * 100 <= nr, "{wrong_r} of {nr} valid and wrong");
    assert!(
        same_reason * 50 >= w * h * 49,
        "{same_reason} verdicts as alone"
    );
    assert!(
        close * 50 >= nr * 49,
        "{close} of {nr} within 0.65σ of alone"
    );
    // The free fits' σ_θ is a pixel's (degrees), not a line's.
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let median_st = median(
        (0..w * h)
            .filter(|&i| rows.valid[i] > 0.5)
            .map(|i| f64::from(rows.sigma_theta_deg[i]))
            .collect(),
    );
    let lone_st = median(
        lone.iter()
            .filter(|p| p.is_valid())
            .map(|p| p.sigma_theta_deg)
            .collect(),
    );
    assert!(
        (median_st - lone_st).abs() <= 0.1 * lone_st,
        "median σ_θ {median_st} vs alone {lone_st}"
    );
    assert!(rows.reason.iter().all(|&r| r as u8 != Reason::Masked as u8));
}

/// Spectra no film makes inside a row (a ripple over 40 columns, 30× the
/// noise) and a dead row: the ripple's pixels are flagged whichever path
/// they take (the line's angle, the free fit, a run of failures), the
/// dead row is flagged as input, and the row's other pixels keep their
/// line (valid, right, as many as a clean row's).
#[test]
fn spectra_no_film_makes_inside_a_row_are_flagged_and_the_rest_keep_the_line() {
    let (w, h) = (320, 4);
    let (s, mut cube, td, _) = cube_with_angles(
        (w, h),
        |x, _| 300.0 + 2.5 * x as f64,
        |_, y| 30.0 + 2.0 * y as f64,
    );
    scene_common::add_ripple(&mut cube, 100..140);
    let n = cube.plane_len();
    for k in 0..cube.bands.len() {
        cube.data[k * n + 3 * w..k * n + 4 * w].fill(0.0);
    }
    let mut solver = Solver::new(&s, &cube.bands, Mode::Fast).unwrap();
    let rows = solver.fit_cube(&cube).unwrap();
    let (nr, mae, _, wrong, _) = score_maps(&rows, &td);
    let ripple_valid = (0..3)
        .flat_map(|y| (100..140).map(move |x| y * w + x))
        .filter(|&i| rows.valid[i] > 0.5)
        .count();
    let dead_valid = (3 * w..4 * w).filter(|&i| rows.valid[i] > 0.5).count();
    eprintln!("ripple: {nr} valid, MAE {mae:.3}, {wrong} wrong, {ripple_valid} ripple valid, {dead_valid} dead valid");
    assert_eq!(ripple_valid, 0, "a ripple no film makes is never valid");
    assert_eq!(dead_valid, 0, "a dead row is never valid");
    assert!(wrong * 100 <= nr, "{wrong} of {nr} valid and wrong");
    // Every clean pixel of the three live rows but a few at the ripple's
    // edges.
    assert!(nr >= 3 * (w - 40) - 12, "{nr} valid of {}", 3 * (w - 40));
}

/// Where the image's own sample says a line from half a row's samples is
/// a small share of a pixel's σ (dispersive p at 45°: ~0.17 of it), the
/// rows take half their samples first; where it is most of it (the thick
/// hard coat at 8°: ~20×), every sample. Either way the rows keep what
/// the rows test above asks of them: as accurate as the lone fits, ≤ 1 %
/// valid and wrong, and a σ honest from both sides. The noise is
/// estimated here (the stage that samples the image runs only then).
#[test]
fn rows_take_half_their_samples_where_the_image_says_they_serve() {
    for (name, w, h, halved) in [
        ("dispersive-p61", 240, 16, true),
        ("thick-hardcoat", 300, 24, false),
    ] {
        let mut s = bundled(name, w, h);
        s.noise_sigma = None;
        let (solver, rows, lone, truth) = rows_and_lone(&s);
        let (nr, mae_r, cov_r, wrong_r, z2_r) = score_maps(&rows, &truth.thickness_nm);
        let (nl, mae_l, _, _, _) = score_lone(&lone, &truth.thickness_nm);
        eprintln!(
            "{name}: halved {}; rows {nr} valid, MAE {mae_r:.3} nm, 2σ {cov_r:.3}, (Δd/σ)² {z2_r:.2}, {wrong_r} wrong; lone {nl} valid, MAE {mae_l:.3} nm",
            solver.row_samples_halved()
        );
        assert_eq!(solver.row_samples_halved(), halved, "{name}");
        assert!(nr + w * h / 100 >= nl, "{name}: {nr} valid rows, {nl} lone");
        assert!(mae_r <= 1.02 * mae_l, "{name}: MAE {mae_r} vs lone {mae_l}");
        assert!(wrong_r * 100 <= nr, "{name}: {wrong_r} of {nr} wrong");
        assert!(cov_r >= 0.88, "{name}: 2σ coverage {cov_r}");
        assert!((0.3..1.6).contains(&z2_r), "{name}: mean (Δd/σ)² {z2_r}");
    }
}
