//! The estimation core on synthetic scenes: the paper's cylinder and the
//! cases the paper page lists as hard (thin films, bare substrate, the index
//! twin, films denser than the substrate, p and unpolarised light, an
//! absorbing substrate, extreme angles, bad pixels).
//!
//! Tolerances come from the statistics, not from a run: the Cramér–Rao
//! bound for a pixel's thickness on the paper's scene is 0.44 nm with the
//! angle unknown and 0.28 nm with it known, so a mean absolute error of an
//! efficient estimator is ~0.8 of those (0.35 / 0.22 nm); the issue's
//! targets (0.5 / 0.3 nm) leave room for the angle-poor rows. A fringe-order
//! error is a jump of λ/(2 n2 cos θ2) ≈ 150–250 nm, so any bound of a few nm
//! on the worst pixel proves there is none.

mod scene_common;
use irid::estimate::{Cube, Mode, ParamMaps, Reason, Solver};
use irid::scene::{AngleKnowledge, FilmKnowledge, Scene};
use irid::synth::{compare, scene_bands, Accuracy, Renderer, TruthMaps};
use scene_common::{
    assert_agree_within, assert_rows_trustworthy, valid_and_wrong, with_known_angle,
};
use std::path::Path;

fn scene(text: &str) -> Scene {
    Scene::from_toml(text, "<test>", Path::new(".")).expect("test scene parses")
}

fn fit(
    scene: &Scene,
    mode: Mode,
) -> (
    ParamMaps,
    TruthMaps,
    Accuracy,
    irid::estimate::IndexEstimate,
) {
    let bands = scene_bands(scene).unwrap();
    let r = Renderer::new(scene).unwrap();
    let cube = r.render_cube(&bands).unwrap();
    let truth = r.truth_maps(&bands);
    let mut solver = Solver::new(scene, &bands, mode).unwrap();
    let maps = solver.fit_cube(&cube).unwrap();
    let idx = solver.film_index().unwrap().clone();
    let acc = compare(&maps, &truth);
    (maps, truth, acc, idx)
}

fn all_finite_or_flagged(maps: &ParamMaps) {
    for i in 0..maps.width * maps.height {
        if maps.valid[i] > 0.5 {
            for (name, ch) in maps.channels() {
                assert!(
                    ch[i].is_finite(),
                    "valid pixel {i} has non-finite {name}: d {} σ {} θ {} rms {}",
                    maps.thickness_nm[i],
                    maps.sigma_thickness_nm[i],
                    maps.theta_deg[i],
                    maps.residual_rms[i]
                );
            }
            assert!(maps.sigma_thickness_nm[i] >= 0.0);
        } else {
            assert!(
                maps.thickness_nm[i].is_nan(),
                "invalid pixel {i} holds a thickness"
            );
            assert!(maps.reason[i] > 0.0, "invalid pixel {i} has no reason");
        }
    }
}

#[test]
fn paper_cylinder_reaches_the_statistical_limit_with_the_angle_unknown() {
    let s = Scene::paper_cylinder();
    for mode in [Mode::Balanced, Mode::Accurate] {
        let (maps, truth, acc, idx) = fit(&s, mode);
        all_finite_or_flagged(&maps);
        assert!(
            (idx.n - truth.n_film).abs() < 1e-3,
            "{mode:?} index {idx:?}"
        );
        assert!(idx.estimated && idx.sigma > 0.0 && idx.sigma < 1e-3);
        // The twin branch near n1·n3/n2 ≈ 1.17 is found and rejected.
        let twin = idx.twin.expect("the twin branch is located");
        assert!((1.08..1.25).contains(&twin), "twin at {twin}");
        assert!(idx.twin_delta_chi2 > 25.0, "{idx:?}");
        assert!(acc.valid_fraction > 0.99, "{mode:?} {acc:?}");
        assert!(acc.thickness_mae_nm <= 0.5, "{mode:?} {acc:?}");
        assert!(acc.thickness_p99_nm < 2.0, "{mode:?} {acc:?}");
        assert!(acc.theta_mae_ge20_deg <= 0.2, "{mode:?} {acc:?}");
        assert!(acc.theta_max_lt20_unflagged_deg <= 1.0, "{mode:?} {acc:?}");
        assert!(acc.coverage_2sigma >= 0.9, "{mode:?} {acc:?}");
    }
}

#[test]
fn paper_cylinder_with_known_angle_is_sharper() {
    let s = with_known_angle(Scene::paper_cylinder());
    let (maps, truth, acc, idx) = fit(&s, Mode::Balanced);
    all_finite_or_flagged(&maps);
    assert!((idx.n - truth.n_film).abs() < 1e-3);
    assert!(acc.thickness_mae_nm <= 0.3, "{acc:?}");
    assert!(acc.thickness_p99_nm < 2.0, "{acc:?}");
    assert!(acc.coverage_2sigma >= 0.9, "{acc:?}");
    // The angle was given: reported as given, with no uncertainty.
    // (Pixels the χ² test flags, ~0.5 % of clean data, carry no angle.)
    for i in 0..maps.width * maps.height {
        if maps.valid[i] < 0.5 {
            continue;
        }
        assert!((maps.theta_deg[i] - truth.theta_deg[i]).abs() < 1e-3);
        assert_eq!(maps.sigma_theta_deg[i], 0.0);
    }
    assert!(maps.valid_count() * 100 >= 97 * maps.width * maps.height);
}

#[test]
fn fast_mode_beats_the_paper_by_far() {
    // The paper's own method reaches a mean error of ~45 nm (4.5 nm when
    // re-implemented faithfully); closed forms on interpolated extrema must
    // stay within a few nm with no order error.
    let (maps, _, acc, _) = fit(&Scene::paper_cylinder(), Mode::Fast);
    all_finite_or_flagged(&maps);
    assert!(acc.thickness_mae_nm < 2.0, "{acc:?}");
    assert!(acc.thickness_max_nm < 20.0, "{acc:?}");
    assert!(acc.coverage_2sigma >= 0.85, "{acc:?}");
}

#[test]
fn index_between_grid_steps_is_found_to_a_thousandth() {
    let text = irid::scene::PAPER_CYLINDER.replace("film_n = 1.37", "film_n = 1.3737");
    let (_, _, _, idx) = fit(&scene(&text), Mode::Balanced);
    assert!((idx.n - 1.3737).abs() < 1e-3, "{idx:?}");
}

#[test]
fn a_known_index_is_never_re_estimated() {
    let text = irid::scene::PAPER_CYLINDER.replace("search = [1.0, 1.6]", "n = 1.37");
    let s = scene(&text);
    assert!(matches!(s.film, FilmKnowledge::Known(_)));
    let (maps, _, acc, idx) = fit(&s, Mode::Balanced);
    assert!(!idx.estimated && idx.sigma == 0.0 && idx.n == 1.37);
    assert!(maps.meta.n_film == 1.37 && !maps.meta.n_film_estimated);
    assert!(acc.thickness_mae_nm <= 0.5, "{acc:?}");
}

const THIN: &str = r#"
[substrate]
n = 1.60
[film]
n = 1.37
[angle]
deg = 30.0
[light]
polarization = "s"
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[truth]
width = 41
height = 2
thickness_nm = { linear_x = [0.0, 200.0] }
noise_sigma = 0.001
seed = 7
"#;

#[test]
fn thin_films_keep_their_order_or_are_flagged_and_bare_substrate_is_zero() {
    let unknown_angle = THIN
        .replace("deg = 30.0", "search_deg = [0.0, 80.0]")
        .replace("seed = 7", "seed = 7\nangle_deg = { constant = 30.0 }");
    for (mode, text) in [
        (Mode::Balanced, THIN.to_string()),
        (Mode::Accurate, THIN.to_string()),
        (Mode::Accurate, unknown_angle),
    ] {
        let (maps, truth, _, _) = fit(&scene(&text), mode);
        all_finite_or_flagged(&maps);
        let mut valid = 0;
        for i in 0..maps.width * maps.height {
            if maps.valid[i] < 0.5 {
                continue;
            }
            valid += 1;
            let e = (maps.thickness_nm[i] - truth.thickness_nm[i]).abs();
            // Below the first fringe the level alone fixes d: errors are
            // larger than on fringes but never an order (≥ 150 nm).
            assert!(
                e < 5.0 + 4.0 * maps.sigma_thickness_nm[i],
                "{mode:?} pixel {i}: truth {} est {} σ {}",
                truth.thickness_nm[i],
                maps.thickness_nm[i],
                maps.sigma_thickness_nm[i]
            );
        }
        assert!(
            valid as f64 > 0.9 * (maps.width * maps.height) as f64,
            "{mode:?}: {valid}"
        );
        // d = 0 is reported as a bare substrate, not a spurious fringe.
        let d0 = maps.thickness_nm[0];
        assert!(
            maps.valid[0] > 0.5 && d0.abs() < 3.0,
            "bare substrate read as {d0} nm"
        );
    }
}

#[test]
fn unresolvable_twin_is_reported_and_a_prior_decides() {
    // At normal incidence the twin n1·n3/n2 is exact: no data can separate
    // the branches, so the solver must say so.
    let text = r#"
[substrate]
n = 1.60
[film]
search = [1.05, 1.58]
[angle]
deg = 0.0
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[truth]
width = 40
height = 4
film_n = 1.37
thickness_nm = { linear_x = [420.0, 560.0] }
noise_sigma = 0.001
seed = 3
"#;
    let (_, _, _, idx) = fit(&scene(text), Mode::Balanced);
    let twin = 1.6 / 1.37;
    let found = [Some(idx.n), idx.twin];
    assert!(
        found.iter().flatten().any(|n| (n - 1.37).abs() < 2e-3),
        "{idx:?}"
    );
    assert!(
        found.iter().flatten().any(|n| (n - twin).abs() < 5e-3),
        "{idx:?}"
    );
    assert!(
        idx.twin_delta_chi2 < 9.0 && idx.note.contains("AMBIGUOUS"),
        "{idx:?}"
    );
    let with_prior = text.replace(
        "search = [1.05, 1.58]",
        "search = [1.05, 1.58]\nprior = 1.35",
    );
    let (_, _, _, idx) = fit(&scene(&with_prior), Mode::Balanced);
    assert!((idx.n - 1.37).abs() < 2e-3, "{idx:?}");
    assert!(idx.note.contains("prior"), "{idx:?}");
}

#[test]
fn film_denser_than_substrate_has_valleys_at_half_wave_and_still_fits() {
    let text = r#"
[substrate]
n = 1.50
[film]
search = [1.55, 2.6]
[light]
polarization = "s"
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[truth]
width = 40
height = 8
film_n = 2.1
thickness_nm = { linear_x = [250.0, 400.0] }
angle_deg = { linear_y = [20.0, 45.0] }
noise_sigma = 0.001
seed = 11
"#;
    let (maps, truth, acc, idx) = fit(&scene(text), Mode::Accurate);
    all_finite_or_flagged(&maps);
    assert!((idx.n - truth.n_film).abs() < 1e-3, "{idx:?}");
    assert!(
        acc.valid_fraction > 0.95 && acc.thickness_mae_nm < 1.0,
        "{acc:?}"
    );
    assert!(acc.thickness_max_nm < 10.0, "{acc:?}");
}

#[test]
fn p_and_unpolarised_light_and_a_dispersive_known_film() {
    for pol in ["p", "u"] {
        let text = format!(
            r#"
[substrate]
material = "SiO2-Malitson"
[film]
material = "MgF2-Dodge-o"
[light]
polarization = "{pol}"
[bands]
start_nm = 420
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[truth]
width = 30
height = 6
thickness_nm = {{ linear_x = [300.0, 700.0] }}
angle_deg = {{ linear_y = [25.0, 50.0] }}
noise_sigma = 0.0005
seed = 5
"#
        );
        let (maps, truth, acc, idx) = fit(&scene(&text), Mode::Accurate);
        all_finite_or_flagged(&maps);
        assert!(!idx.estimated);
        // MgF2 on silica reflects weakly: fringes of ~0.005, so the error
        // budget is a few times the paper scene's.
        assert!(acc.thickness_max_nm < 15.0, "{pol}: {acc:?}");
        // The last row (50°) nears the film's Brewster angle in p light
        // (54°): its fringes fade, and another order at another angle
        // comes within the ambiguity margin (Δχ² < 9) on most of its
        // pixels — flagged so, never an error. Below it every pixel stays
        // valid.
        let n = maps.width * maps.height;
        let below = (0..n).filter(|&i| truth.theta_deg[i] < 48.0);
        let (valid_below, count_below) = below.fold((0, 0), |(v, c), i| {
            (v + usize::from(maps.valid[i] > 0.5), c + 1)
        });
        assert!(
            valid_below as f64 > 0.95 * count_below as f64,
            "{pol}: {valid_below} of {count_below} valid below 48°"
        );
        for i in (0..n).filter(|&i| maps.valid[i] <= 0.5) {
            assert_eq!(
                maps.reason[i],
                Reason::AmbiguousOrder as u8 as f32,
                "{pol}: pixel {i} at {}°",
                truth.theta_deg[i]
            );
        }
        assert!(acc.valid_fraction > 0.85, "{pol}: {acc:?}");
        assert!(acc.coverage_2sigma > 0.85, "{pol}: {acc:?}");
    }
}

#[test]
fn absorbing_substrate_takes_the_complex_path() {
    let text = r#"
[substrate]
material = "Si-Green-2008"
[film]
n = 1.46
[angle]
deg = 20.0
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[truth]
width = 20
height = 2
thickness_nm = { linear_x = [100.0, 900.0] }
noise_sigma = 0.001
seed = 9
"#;
    let (maps, _, acc, _) = fit(&scene(text), Mode::Balanced);
    all_finite_or_flagged(&maps);
    assert!(acc.valid_fraction > 0.9, "{acc:?}");
    assert!(acc.thickness_max_nm < 3.0, "{acc:?}");
}

/// The extreme scenes: grazing incidence, a film matching the substrate, a
/// film matching the ambient, total internal reflection in the film,
/// Brewster's angle for p. Film index known, angle unknown (searched over
/// the default 0–80°), thickness 0 → 1500 nm across 12 columns.
const EXTREMES: [(f64, f64, f64, &str, [f64; 2]); 5] = [
    (1.0, 1.37, 1.6, "s", [80.0, 89.0]),
    (1.0, 1.6, 1.6, "s", [10.0, 40.0]),
    (1.0, 1.0001, 1.6, "s", [10.0, 40.0]),
    (1.5, 1.0, 1.5, "s", [30.0, 60.0]),
    (1.0, 1.37, 1.6, "p", [50.0, 65.0]),
];

fn extreme_scene(case: (f64, f64, f64, &str, [f64; 2]), noise: f64) -> Scene {
    let (n1, n2, n3, pol, [a0, a1]) = case;
    scene(&format!(
        r#"
[ambient]
n = {n1}
[substrate]
n = {n3}
[film]
n = {n2}
[light]
polarization = "{pol}"
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[truth]
width = 12
height = 6
thickness_nm = {{ linear_x = [0.0, 1500.0] }}
angle_deg = {{ linear_y = [{a0:?}, {a1:?}] }}
noise_sigma = {noise:?}
seed = 1
"#
    ))
}

/// Whether a pixel of an extreme scene is physically identifiable with the
/// angle unknown: its angle inside the searched 0–80° (strictly below 80°:
/// a fit at the end of its search is flagged "at search bound"); no total internal
/// reflection (n1 sin θ below n2 and n3: the fringes exist); a fringe
/// contrast |R(δ = 0) − R(δ = π)| of at least 0.01, ten times the noise a
/// camera adds (σ_R = 0.001), for the scene's polarisation; and at least
/// two fringe extrema within 410–690 nm (one band in from the ends), since
/// one extremum or none cannot fix both thickness and angle.
fn identifiable(n1: f64, n2: f64, n3: f64, pol: &str, theta_deg: f64, d_nm: f64) -> bool {
    let s = n1 * theta_deg.to_radians().sin();
    if !(0.0..80.0).contains(&theta_deg) || s >= n2 || s >= n3 {
        return false;
    }
    let cos = |n: f64| (1.0 - (s / n).powi(2)).sqrt();
    let (c1, c2, c3) = (cos(n1), cos(n2), cos(n3));
    let r = |na: f64, ca: f64, nb: f64, cb: f64| match pol {
        "p" => (nb * ca - na * cb) / (nb * ca + na * cb),
        _ => (na * ca - nb * cb) / (na * ca + nb * cb),
    };
    let (r12, r23) = (r(n1, c1, n2, c2), r(n2, c2, n3, c3));
    let half_wave = ((r12 + r23) / (1.0 + r12 * r23)).powi(2);
    let quarter_wave = ((r12 - r23) / (1.0 - r12 * r23)).powi(2);
    if (half_wave - quarter_wave).abs() < 0.01 {
        return false;
    }
    // Extrema where 4 g / λ is an integer, g = n2 d cos θ2.
    let g = n2 * d_nm * c2;
    let extrema = (4.0 * g / 410.0).floor() - (4.0 * g / 690.0).ceil() + 1.0;
    extrema >= 2.0
}

/// Per case and mode: identifiable pixels, how many of them are valid,
/// and the valid pixels (identifiable or not) farther than max(3σ, 2 nm)
/// from the truth, on noise-free data.
struct ExtremeOutcome {
    label: String,
    identifiable: usize,
    identifiable_valid: usize,
    wrong: Vec<String>,
}

fn extreme_outcomes() -> Vec<ExtremeOutcome> {
    let mut out = vec![];
    for case in EXTREMES {
        let (n1, n2, n3, pol, ang) = case;
        let s = extreme_scene(case, 0.0);
        for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
            let (maps, truth, _, _) = fit(&s, mode);
            all_finite_or_flagged(&maps);
            let mut o = ExtremeOutcome {
                label: format!("n {n1}/{n2}/{n3} {pol} θ {ang:?} {mode:?}"),
                identifiable: 0,
                identifiable_valid: 0,
                wrong: vec![],
            };
            for i in 0..maps.width * maps.height {
                let (d, th) = (
                    f64::from(truth.thickness_nm[i]),
                    f64::from(truth.theta_deg[i]),
                );
                let valid = maps.valid[i] > 0.5;
                let ident = identifiable(n1, n2, n3, pol, th, d);
                if ident {
                    o.identifiable += 1;
                    o.identifiable_valid += usize::from(valid);
                }
                let err = f64::from(maps.thickness_nm[i]) - d;
                let tol = (3.0 * f64::from(maps.sigma_thickness_nm[i])).max(2.0);
                if valid && err.abs() > tol {
                    o.wrong.push(format!(
                        "d {d:.0} nm θ {th:.1}°{}: Δd {err:+.1} nm (σ {:.2}, reason {})",
                        if ident { " (identifiable)" } else { "" },
                        maps.sigma_thickness_nm[i],
                        maps.reason[i]
                    ));
                }
            }
            out.push(o);
        }
    }
    out
}

#[test]
fn extremes_give_finite_or_flagged_outputs() {
    // With the noise a camera adds, nothing panics and every output is a
    // finite estimate or flagged with a reason.
    for case in EXTREMES {
        for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
            let (maps, _, _, _) = fit(&extreme_scene(case, 0.001), mode);
            eprintln!("case {case:?} mode {mode:?}");
            all_finite_or_flagged(&maps);
        }
    }
    // Noise-free: the pixels that physically can be solved mostly are (at
    // least three quarters of them in every case and mode; flagging them all would
    // pass the check above).
    let outcomes = extreme_outcomes();
    for o in &outcomes {
        eprintln!(
            "{}: {} of {} identifiable pixels valid; {} valid pixels wrong",
            o.label,
            o.identifiable_valid,
            o.identifiable,
            o.wrong.len()
        );
        for w in &o.wrong {
            eprintln!("    {w}");
        }
    }
    for o in &outcomes {
        // p light near Brewster's angle (50–65°): the refinement does not
        // reach these pixels' fits from its starts (the fringe contrast
        // nearly vanishes), and the χ² test flags what it finds instead of
        // reporting it; solving them is open work. Every other case must
        // solve three quarters of its identifiable pixels.
        if o.label.contains(" p θ") {
            continue;
        }
        assert!(
            4 * o.identifiable_valid >= 3 * o.identifiable,
            "{}: only {} of {} identifiable pixels valid",
            o.label,
            o.identifiable_valid,
            o.identifiable
        );
    }
}

/// The strict half: on noise-free data, a pixel the solver calls valid is
/// within max(3σ, 2 nm) of the truth (`tests/estimate_extremes.rs` sweeps
/// the whole domain).
#[test]
fn extremes_never_call_a_wrong_pixel_valid() {
    let outcomes = extreme_outcomes();
    let wrong: Vec<String> = outcomes
        .iter()
        .filter(|o| !o.wrong.is_empty())
        .map(|o| format!("{}:\n    {}", o.label, o.wrong.join("\n    ")))
        .collect();
    assert!(
        wrong.is_empty(),
        "valid pixels farther than max(3σ, 2 nm) from the truth:\n{}",
        wrong.join("\n")
    );
}

#[test]
fn bad_pixels_are_flagged_with_a_reason_and_missing_bands_tolerated() {
    let s = Scene::paper_cylinder();
    let bands = scene_bands(&s).unwrap();
    let r = Renderer::new(&s).unwrap();
    let mut cube = r.render_cube(&bands).unwrap();
    let truth = r.truth_maps(&bands);
    let n = cube.plane_len();
    // Pixel 0: every band NaN. Pixel 1: one band missing. Pixel 2: a
    // reflectance of 7. Pixel 3: one infinite sample (treated as missing).
    for b in 0..bands.len() {
        cube.data[b * n] = f32::NAN;
    }
    cube.data[5 * n + 1] = f32::NAN;
    cube.data[3 * n + 2] = 7.0;
    cube.data[3 * n + 3] = f32::INFINITY;
    let mut solver = Solver::new(&s, &bands, Mode::Balanced).unwrap();
    let maps = solver.fit_cube(&cube).unwrap();
    all_finite_or_flagged(&maps);
    assert_eq!(maps.get(0, 0).reason, Reason::NonFinite);
    assert!(maps.get(1, 0).is_valid());
    assert!((maps.thickness_nm[1] - truth.thickness_nm[1]).abs() < 3.0);
    assert_eq!(maps.get(2, 0).reason, Reason::OutOfModel);
    assert!(maps.get(3, 0).is_valid());
    assert!((maps.thickness_nm[3] - truth.thickness_nm[3]).abs() < 3.0);
}

#[test]
fn a_lost_band_still_gives_the_index_and_the_maps() {
    // A dropped frame leaves one band NaN in every pixel (the pipeline's
    // "missing" band): the index search and the pixels go on without it.
    let s = Scene::paper_cylinder();
    let bands = scene_bands(&s).unwrap();
    let r = Renderer::new(&s).unwrap();
    let mut cube = r.render_cube(&bands).unwrap();
    let truth = r.truth_maps(&bands);
    cube.plane_mut(7).fill(f32::NAN);
    let mut solver = Solver::new(&s, &bands, Mode::Balanced).unwrap();
    let maps = solver.fit_cube(&cube).unwrap();
    let idx = solver.film_index().unwrap();
    assert!((idx.n - truth.n_film).abs() < 1e-3, "{idx:?}");
    let acc = compare(&maps, &truth);
    assert!(
        acc.valid_fraction > 0.99 && acc.thickness_mae_nm < 0.6,
        "{acc:?}"
    );
    assert!(acc.thickness_p99_nm < 2.5, "{acc:?}");
}

#[test]
fn nan_entries_of_an_angle_map_leave_those_angles_to_be_estimated() {
    let mut s = with_known_angle(Scene::paper_cylinder());
    if let AngleKnowledge::Map { deg, width, .. } = &mut s.angle {
        // Unknown angle over the bottom row (42.5°, well identifiable).
        let w = *width;
        let n = deg.len();
        deg[n - w..].fill(f32::NAN);
    }
    let (maps, truth, acc, _) = fit(&s, Mode::Balanced);
    all_finite_or_flagged(&maps);
    assert!(acc.thickness_mae_nm <= 0.5, "{acc:?}");
    let w = maps.width;
    let n = maps.width * maps.height;
    for i in n - w..n {
        if maps.valid[i] < 0.5 {
            continue;
        }
        // Estimated, hence with an uncertainty; and close to the truth.
        assert!(maps.sigma_theta_deg[i] > 0.0);
        assert!((maps.theta_deg[i] - truth.theta_deg[i]).abs() < 1.0);
    }
    for i in 0..n - w {
        if maps.valid[i] < 0.5 {
            continue;
        }
        assert_eq!(maps.sigma_theta_deg[i], 0.0);
    }
    assert!(maps.valid_count() * 100 >= 97 * n);
}

#[test]
fn every_mode_integrates_wide_passbands_where_they_matter() {
    // A 10 nm (VariSpec-like) passband and a thicker film: the fringes at
    // 400 nm are ~60 nm apart, so point sampling misreads their depth by
    // more than the noise (until 2026-12-07 `fast` and `balanced` did, and
    // were biased). Every mode integrates and stays honest.
    let text = irid::scene::PAPER_CYLINDER
        .replace("fwhm_nm = 0", "fwhm_nm = 10")
        .replace("linear_x = [420.0, 560.0]", "linear_x = [900.0, 1100.0]")
        .replace("search = [1.0, 1.6]", "n = 1.37");
    let s = scene(&text);
    for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
        let (maps, _, acc, _) = fit(&s, mode);
        all_finite_or_flagged(&maps);
        assert!(acc.valid_fraction > 0.95, "{mode:?} {acc:?}");
        // A 1000 nm film turns the weak low-angle rows' angle uncertainty
        // into d through 1/(n2 cos θ2) (up to ~10 nm at 10°, carried in
        // σ), so the mean error is above the paper scene's; the coverage
        // is what matters.
        assert!(acc.thickness_mae_nm < 1.0, "{mode:?} {acc:?}");
        assert!(
            (0.9..=0.99).contains(&acc.coverage_2sigma),
            "{mode:?} {acc:?}"
        );
    }
}

/// The paper's materials over 100 → 1500 nm: thin films with one extremum
/// or none, and thick ones whose fringes are too fast for a five-sample
/// parabola. Every mode keeps its orders (no error near a fringe jump of
/// ~150–250 nm) and its σ honest (≥ 90 % within 2σ) across the range;
/// `fast` serves what its closed form can and fits the rest. (Ideal bands:
/// with 10 nm passbands the thick end needs `accurate`'s integration.)
#[test]
fn a_wide_thickness_range_keeps_orders_and_honest_sigma_in_every_mode() {
    // The benchmark's wide-range scene, cut to 280 × 14 pixels with the
    // angle in the paper's 2.5° steps.
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes/wide-range.toml");
    let mut s = Scene::load(&path).expect("the bundled scene loads");
    let t = s.truth.as_mut().expect("the scene has a truth");
    (t.width, t.height, t.seed) = (280, 14, 3);
    t.angle_deg = irid::scene::Field::Rows([10.0, 2.5]);
    for mode in [Mode::Fast, Mode::Balanced] {
        let (maps, truth, acc, _) = fit(&s, mode);
        all_finite_or_flagged(&maps);
        assert!(acc.valid_fraction > 0.97, "{mode:?} {acc:?}");
        assert!(acc.coverage_2sigma >= 0.90, "{mode:?} {acc:?}");
        // No order error anywhere above the thinnest films (where the
        // angle and the thickness trade off within the noise).
        for i in 0..maps.valid.len() {
            let t = f64::from(truth.thickness_nm[i]);
            if maps.valid[i] > 0.5 && t > 200.0 {
                let e = (f64::from(maps.thickness_nm[i]) - t).abs();
                assert!(e < 30.0, "{mode:?}: pixel {i}, truth {t} nm, error {e} nm");
            }
        }
        let mae_limit = if mode == Mode::Fast { 1.5 } else { 1.0 };
        assert!(acc.thickness_mae_nm < mae_limit, "{mode:?} {acc:?}");
    }
}

/// The paper's cylinder cropped to `width` columns (its thickness ramp
/// kept): rows narrower than `angle_map`'s five samples take `fast`'s
/// band-major path with the angle free, as a wide row whose samples give
/// no line does.
fn narrow_paper_cylinder(width: usize) -> Scene {
    let mut s = Scene::paper_cylinder();
    s.truth.as_mut().expect("a truth").width = width;
    s
}

#[test]
fn fast_rows_agree_with_the_per_pixel_fast_path() {
    // The band-major row path must compute what the per-pixel path does.
    // Where its closed form is found wanting, the row path refines from
    // the previous pixel's fit first (a lone pixel has none and refines
    // from the closed form): both converge to the same minimum, to
    // `fast`'s tolerance (each within 0.32 σ of it).
    let s = narrow_paper_cylinder(36);
    let bands = scene_bands(&s).unwrap();
    let cube = Renderer::new(&s).unwrap().render_cube(&bands).unwrap();
    let mut solver = Solver::new(&s, &bands, Mode::Fast).unwrap();
    solver.estimate_film_index(&cube).unwrap();
    let mut scratch = irid::estimate::solver::Scratch::default();
    let mut row = vec![irid::estimate::PixelEstimate::invalid(Reason::Masked); cube.width];
    let mut spec = vec![0.0; bands.len()];
    let (mut same, mut valid, mut total) = (0, 0, 0);
    for y in 0..cube.height {
        solver.solve_row(&cube, y, &mut row, &mut scratch);
        for (x, r) in row.iter().enumerate() {
            cube.spectrum_into(x, y, &mut spec);
            let p = solver.solve_pixel(&spec, None, &mut scratch);
            total += 1;
            if let Some(identical) = assert_agree_within(&format!("({x}, {y})"), r, &p, 0.65) {
                valid += 1;
                same += usize::from(identical);
            }
        }
    }
    eprintln!("{same} of {valid} valid pixels identical, {total} pixels");
    // Not passed by flagging everything.
    assert!(
        valid as f64 > 0.95 * total as f64,
        "{valid} of {total} valid"
    );
}

/// A bundled scene (`data/scenes/NAME.toml`) cropped to `width` × 3
/// pixels, noise seed 5.
fn bundled(name: &str, width: usize) -> Scene {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("data/scenes/{name}.toml"));
    let mut s = Scene::load(&path).expect("the bundled scene loads");
    let t = s.truth.as_mut().expect("the scene has a truth");
    (t.width, t.height, t.seed) = (width, 3, 5);
    s
}

/// Scene `s` rendered, its truth, and a `mode` solver whose index, noise
/// and level are estimated from it; the scene must leave the angle free.
fn rendered_angle_free(s: &Scene, mode: Mode, label: &str) -> (Cube, TruthMaps, Solver) {
    let bands = scene_bands(s).unwrap();
    let r = Renderer::new(s).unwrap();
    let cube = r.render_cube(&bands).unwrap();
    let truth = r.truth_maps(&bands);
    let mut solver = Solver::new(s, &bands, mode).unwrap();
    solver.estimate_film_index(&cube).unwrap();
    assert!(solver.scene_angle().known_at(0, 0).is_none(), "{label}");
    (cube, truth, solver)
}

/// Rows against lone pixels, tallied: the rows trustworthy
/// ([`assert_rows_trustworthy`]) and at most 2 % of the pixels judged
/// otherwise alone (a lone search can miss the basin a row's start finds,
/// and the reverse).
fn assert_rows_as_lone(label: &str, valid: usize, total: usize, wrong: usize, differ: usize) {
    eprintln!("{label}: {valid} of {total} valid, {wrong} valid and wrong, {differ} judged otherwise alone");
    assert_rows_trustworthy(label, valid, total, wrong);
    assert!(
        differ as f64 <= 0.02 * total as f64,
        "{label}: {differ} judged otherwise"
    );
}

/// `fast` with the angle free, row by row, where the closed form serves
/// few pixels: a row stops looking for it after four pixels it served
/// nothing (none found, or one that missed the spectrum by a hundred
/// times the test's threshold: TiO2's dispersion moves its extrema off
/// the constant-index lattice), but on every sixteenth, and fits from the
/// previous pixel instead; a lone pixel always looks. Both must judge
/// (nearly) every pixel alike and agree on the valid ones within 0.65 σ,
/// as `fast_rows_agree_with_the_per_pixel_fast_path` (within twice the
/// wider σ along a valley where the angle is not identifiable, as the
/// `balanced` rows' test), and the rows stay right (at most 1 % valid and
/// wrong).
#[test]
fn fast_rows_that_stop_looking_for_a_closed_form_agree_with_lone_pixels() {
    // Rows narrower than five angle samples: the band-major path.
    for (name, width) in [("dispersive-p61", 36), ("thin-coating", 36)] {
        let (cube, truth, solver) = rendered_angle_free(&bundled(name, width), Mode::Fast, name);
        let (mut valid, mut total, mut wrong, mut differ) = (0, 0, 0, 0);
        scene_common::rows_against_lone(&solver, &cube, |x, y, r, p, _| {
            total += 1;
            let dd = (r.thickness_nm - p.thickness_nm).abs();
            if r.reason != p.reason {
                differ += 1;
            } else if r.reason == Reason::AngleNotIdentifiable {
                // Along a valley the data cannot resolve, two starts
                // stop at different points of it; each σ spans it.
                let span = r.sigma_thickness_nm.max(p.sigma_thickness_nm);
                assert!(dd < 2.0 * span, "{name} ({x}, {y}): {r:?} vs {p:?}");
            } else if r.is_valid() {
                assert!(
                    dd < 0.65 * r.sigma_thickness_nm,
                    "{name} ({x}, {y}): {r:?} vs {p:?}"
                );
            }
            valid += usize::from(r.is_valid());
            wrong += usize::from(valid_and_wrong(r, truth.thickness_nm[y * cube.width + x]));
        });
        assert_rows_as_lone(name, valid, total, wrong, differ);
    }
}

/// `balanced` with the angle free, row by row: a pixel starts from the
/// previous pixel's fit before looking for a closed form (unless the
/// closed form settled that pixel), and weighs its neighbouring fringe
/// orders only where the previous pixel's came close or the fit's fringe
/// phase moved; a lone pixel (a fresh scratch) takes the closed form or
/// the search and always weighs the orders. Both must judge every pixel
/// alike and agree on every valid one (within 0.05 σ or the refinement's
/// step; within the wider σ along a valley where the angle is not
/// identifiable, since each start stops at its own point of it), but for
/// a few pixels where one start finds a basin the other misses: on the
/// paper's cylinder, on a thin
/// unpolarised coating whose angle the data cannot tell (a flat valley in
/// (d, θ)), on a dispersive p scene at 61 bands, and on a steep ramp whose
/// fringe order changes every few pixels (the previous pixel's basin is
/// often the wrong one there).
#[test]
fn balanced_rows_with_the_angle_free_agree_with_lone_pixels() {
    let mut steep = bundled("wide-range", 32);
    steep.truth.as_mut().unwrap().thickness_nm = irid::scene::Field::Columns([300.0, 37.0]);
    let mut cylinder = Scene::paper_cylinder();
    cylinder.truth.as_mut().unwrap().height = 4;
    for (label, s) in [
        ("cylinder", cylinder),
        ("thin", bundled("thin-coating", 120)),
        ("dispersive p", bundled("dispersive-p61", 80)),
        ("steep", steep),
    ] {
        // Every scene here has the angle free: the lone pixel searches.
        let (cube, truth, solver) = rendered_angle_free(&s, Mode::Balanced, label);
        let (mut valid, mut total, mut wrong, mut differ) = (0, 0, 0, 0);
        scene_common::rows_against_lone(&solver, &cube, |x, y, r, p, _| {
            total += 1;
            let at = format!("{label} ({x}, {y})");
            if r.reason != p.reason {
                // A lone pixel's search can miss the basin its row's
                // start finds (flagging it), and the reverse: counted.
                differ += 1;
            } else if r.reason == Reason::AngleNotIdentifiable {
                // Along a valley the data cannot resolve, two starts
                // stop at different points of it; each σ spans it.
                let dd = (r.thickness_nm - p.thickness_nm).abs();
                let span = r.sigma_thickness_nm.max(p.sigma_thickness_nm);
                assert!(dd < 2.0 * span, "{at}: {r:?} vs {p:?}");
            } else if r.is_valid() {
                // Two converged fits of one minimum: within 0.05 σ, or
                // the refinement's stopping step (5e-3 nm) twice.
                let dd = (r.thickness_nm - p.thickness_nm).abs();
                assert!(
                    dd < (0.05 * r.sigma_thickness_nm).max(0.01),
                    "{at}: {r:?} vs {p:?}"
                );
                let ds = (r.sigma_thickness_nm - p.sigma_thickness_nm).abs();
                assert!(ds < 0.05 * r.sigma_thickness_nm, "{at}: {r:?} vs {p:?}");
            }
            valid += usize::from(r.is_valid());
            wrong += usize::from(valid_and_wrong(r, truth.thickness_nm[y * cube.width + x]));
        });
        assert_rows_as_lone(label, valid, total, wrong, differ);
    }
}

/// Films past what the bands resolve, the angle free (the bundled thick
/// hard coat: 1–4 µm of Si3N4 at 61 bands, resolved to ~3.2 µm): a row
/// flags every pixel past the range, most "fringes unresolved" (its fit
/// from its neighbour's passes there:
/// `unresolved_runs_with_the_angle_free_follow_the_row`, in
/// `estimate_tables.rs`; lone pixels searching afresh read most of them
/// "poor fit"); after a search that finds no fit it skips the next ones where the χ²
/// distance to that pixel proves no fit can pass (their best-fit thickness
/// then reads NaN) — only far from every fit, and never more than 16 in a
/// row before a search runs again (the angle-free search is not
/// exhaustive: a reference it got wrong must not flag a long run).
/// `balanced` and `accurate` (`fast` takes the row pass, which keeps no
/// per-pixel fit to tell a skipped pixel by).
#[test]
fn angle_free_runs_past_the_range_are_flagged_as_a_search_flags_them() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes/thick-hardcoat.toml");
    // Its 300 × 20 pixels: the noise is estimated from the data, between
    // rows whose angles differ by 0.1°.
    let s = Scene::load(&path).expect("the bundled scene loads");
    let bands = scene_bands(&s).unwrap();
    let cube = Renderer::new(&s).unwrap().render_cube(&bands).unwrap();
    for mode in [Mode::Balanced, Mode::Accurate] {
        let mut solver = Solver::new(&s, &bands, mode).unwrap();
        solver.estimate_film_index(&cube).unwrap();
        let mut scratch = irid::estimate::solver::Scratch::default();
        let mut row = vec![irid::estimate::PixelEstimate::invalid(Reason::Masked); cube.width];
        let mut spec = vec![0.0; bands.len()];
        let (mut poor, mut unresolved, mut skipped, mut longest) = (0, 0, 0, 0);
        for y in 0..cube.height {
            solver.solve_row(&cube, y, &mut row, &mut scratch);
            let mut run = 0;
            for (x, r) in row.iter().enumerate() {
                let at = format!("{} ({x}, {y})", mode.name());
                let skip = scratch.fit_thickness()[x].is_nan();
                if r.reason == Reason::PoorFit {
                    poor += 1;
                }
                if r.reason == Reason::Unresolved {
                    unresolved += 1;
                }
                if skip {
                    assert_eq!(r.reason, Reason::PoorFit, "{at}: skipped but {r:?}");
                    cube.spectrum_into(x, y, &mut spec);
                    let mut lone = irid::estimate::solver::Scratch::default();
                    let p = solver.solve_pixel(&spec, None, &mut lone);
                    assert_eq!(p.reason, Reason::PoorFit, "{at}: a search finds {p:?}");
                    skipped += 1;
                    run += 1;
                    longest = longest.max(run);
                } else {
                    run = 0;
                }
            }
        }
        eprintln!(
            "{}: {unresolved} unresolved, {poor} poor fits, {skipped} without a search, \
             longest run {longest}",
            mode.name()
        );
        // ~28 % of the ramp lies past the range, every pixel flagged, at
        // least three in four followed from the row's unresolved fits
        // (measured: 1 430 of 1 692 in `balanced`); the poor ones' spectra
        // move fast (10 nm a pixel), so a reference settles about every
        // other one (120 of 262).
        let n = cube.width * cube.height;
        assert!(
            poor + unresolved >= n / 4,
            "{}: {poor} + {unresolved}",
            mode.name()
        );
        assert!(unresolved >= 3 * poor, "{}: {poor} poor", mode.name());
        assert!(skipped >= poor / 3, "{}: {skipped} skipped", mode.name());
        assert!(longest <= 16, "{}: a run of {longest}", mode.name());
    }
    // A film of one thickness under a ripple no film makes (30× the noise,
    // over the middle of each row): the rippled spectra lie within the
    // noise of each other, so one reference could settle them all; it
    // settles 16, then a search runs again.
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes/thin-coating.toml");
    let mut s = Scene::load(&path).expect("the bundled scene loads");
    let t = s.truth.as_mut().unwrap();
    (t.width, t.height) = (90, 8);
    t.thickness_nm = irid::scene::Field::Constant(250.0);
    let bands = scene_bands(&s).unwrap();
    let mut cube = Renderer::new(&s).unwrap().render_cube(&bands).unwrap();
    let (w, h) = (cube.width, cube.height);
    let rippled = 20..70;
    scene_common::add_ripple(&mut cube, rippled.clone());
    let mut solver = Solver::new(&s, &bands, Mode::Balanced).unwrap();
    solver.estimate_film_index(&cube).unwrap();
    let mut scratch = irid::estimate::solver::Scratch::default();
    let mut row = vec![irid::estimate::PixelEstimate::invalid(Reason::Masked); w];
    let (mut searched, mut longest) = (0, 0);
    for y in 0..h {
        solver.solve_row(&cube, y, &mut row, &mut scratch);
        let mut run = 0;
        for x in rippled.clone() {
            assert_eq!(row[x].reason, Reason::PoorFit, "rippled ({x}, {y})");
            if scratch.fit_thickness()[x].is_nan() {
                run += 1;
                longest = longest.max(run);
            } else {
                searched += 1;
                run = 0;
            }
        }
    }
    eprintln!("rippled: {searched} searched, longest run {longest}");
    assert_eq!(longest, 16, "a reference settles at most 16 pixels");
    // 50 pixels a row: a search, 16 settled, a search, …
    assert!(
        searched >= 3 * h && searched <= 8 * h,
        "{searched} searched"
    );
}

#[test]
fn the_thickness_range_is_a_scene_setting() {
    let thick = r#"
[substrate]
n = 1.60
[film]
n = 1.37
max_thickness_nm = 3000
[angle]
deg = 20.0
[bands]
start_nm = 400
stop_nm = 700
step_nm = 5
fwhm_nm = 0
[truth]
width = 20
height = 2
thickness_nm = { linear_x = [2200.0, 2800.0] }
noise_sigma = 0.001
seed = 4
"#;
    let (maps, _, acc, _) = fit(&scene(thick), Mode::Balanced);
    all_finite_or_flagged(&maps);
    assert!(
        acc.valid_fraction > 0.95 && acc.thickness_max_nm < 3.0,
        "{acc:?}"
    );
    let bad = thick.replace("max_thickness_nm = 3000", "max_thickness_nm = -5");
    let err = Scene::from_toml(&bad, "<test>", Path::new("."))
        .unwrap_err()
        .to_string();
    assert!(err.contains("film.max_thickness_nm"), "{err}");
}

#[test]
fn fast_judges_a_weak_angle_as_the_full_fit_does() {
    // "Angle not identifiable" is a valid pixel's note: its σ_θ exceeds
    // 0.25°. `fast`'s closed form estimates σ_θ from the extrema's levels
    // alone, wider than the full model's; a closed form it then judged
    // against the full model kept that flag, so on the paper's cylinder
    // `fast` noted twice as many weak angles as `balanced` (85 165 against
    // 46 800 of 125 440 pixels in the scene matrix). Judged by the full
    // model's σ_θ, the verdicts agree pixel by pixel but for noise-level
    // ties at the limit.
    // (Rows narrow enough for the band-major path: wider ones are solved
    // on their estimated angle, whose σ_θ is the row's, not a pixel's.)
    let s = narrow_paper_cylinder(36);
    let (fast, ..) = fit(&s, Mode::Fast);
    let (balanced, ..) = fit(&s, Mode::Balanced);
    let weak = Reason::AngleNotIdentifiable as u8;
    let ok = Reason::Ok as u8;
    let (mut both_valid, mut differ, mut weak_fast, mut weak_balanced) = (0, 0, 0, 0);
    for (&f, &b) in fast.reason.iter().zip(&balanced.reason) {
        let (f, b) = (f as u8, b as u8);
        if !([ok, weak].contains(&f) && [ok, weak].contains(&b)) {
            continue;
        }
        both_valid += 1;
        differ += usize::from(f != b);
        weak_fast += usize::from(f == weak);
        weak_balanced += usize::from(b == weak);
    }
    eprintln!(
        "{both_valid} valid in both; weak angle: fast {weak_fast}, balanced {weak_balanced}; \
         {differ} verdicts differ"
    );
    // Both kinds of verdict occur (near normal incidence the angle is weak).
    assert!(weak_balanced > both_valid / 10 && weak_balanced < both_valid * 9 / 10);
    assert!(
        differ * 50 <= both_valid,
        "{differ} of {both_valid} verdicts differ (fast {weak_fast}, balanced {weak_balanced})"
    );
}
