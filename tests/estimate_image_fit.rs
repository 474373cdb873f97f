//! Data irid's fitted model did not render, where no single pixel can
//! tell: the image's fit taken as a whole, and wide passbands.
//!
//! - **The wrong polarisation.** The paper's cylinder rendered in
//!   unpolarised light and fitted as s-polarised: every pixel's own χ²
//!   passes (the angle and the film index absorb most of the difference),
//!   and before the image test 90–96 % of the pixels were valid, every one
//!   23–26 nm off. Together the pixels' χ² runs 13–15 % above the noise;
//!   the image is rejected and every pixel flagged "poor fit".
//! - **Clean images are not rejected**: every bundled scene, three noise
//!   seeds each (the test's null; its margin is `image_fit::MAX_EXCESS`).
//! - **Wide passbands are integrated in every mode.** With 10 nm
//!   (VariSpec-like) bands the paper's cylinder was read 1–3.6 nm off with
//!   σ covering 6–44 % of the errors (point sampling errs by ~2e-4, a
//!   fifth of the noise, on every pixel alike): now each mode is at its
//!   clean accuracy with honest σ.
//!
//! "Wrong" is |Δd| > max(3σ, 2 nm).

use irid::estimate::{Cube, Mode, ParamMaps, Reason, Solver};
use irid::scene::Scene;
use irid::synth::{compare, scene_bands, Renderer, TruthMaps};
use std::path::Path;

fn render(s: &Scene) -> (Cube, TruthMaps) {
    let bands = scene_bands(s).unwrap();
    let r = Renderer::new(s).unwrap();
    (r.render_cube(&bands).unwrap(), r.truth_maps(&bands))
}

fn fit(s: &Scene, cube: &Cube, mode: Mode) -> (ParamMaps, Solver) {
    let mut solver = Solver::new(s, &cube.bands, mode).unwrap();
    let maps = solver.fit_cube(cube).unwrap();
    (maps, solver)
}

fn scene(text: &str) -> Scene {
    Scene::from_toml(text, "test", Path::new(".")).unwrap()
}

fn rejected(solver: &Solver) -> bool {
    solver.level().2.contains("share a misfit")
}

#[test]
fn the_wrong_polarisation_is_flagged_not_fitted() {
    let unpolarised =
        irid::scene::PAPER_CYLINDER.replace("polarization = \"s\"", "polarization = \"u\"");
    let (cube, truth) = render(&scene(&unpolarised));
    // Fitted as the paper's s-polarised scene: the film index unknown,
    // then known (1.37, as rendered).
    let known = irid::scene::PAPER_CYLINDER.replace("search = [1.0, 1.6]", "n = 1.37");
    for (label, text) in [
        ("index unknown", irid::scene::PAPER_CYLINDER.to_string()),
        ("index known", known),
    ] {
        for mode in [Mode::Fast, Mode::Balanced] {
            let (maps, solver) = fit(&scene(&text), &cube, mode);
            let acc = compare(&maps, &truth);
            eprintln!("{label} {mode:?}: {acc:?} {}", solver.level().2);
            assert!(rejected(&solver), "{label} {mode:?}: {}", solver.level().2);
            assert_eq!(maps.valid_count(), 0, "{label} {mode:?}: {acc:?}");
            let poor = maps
                .reason
                .iter()
                .filter(|&&c| c as u8 == Reason::PoorFit as u8)
                .count();
            assert!(poor * 10 >= 9 * maps.reason.len(), "{label} {mode:?}");
        }
    }
}

/// A film index *given* wrong (1.37 for a film of 1.39, the angles free):
/// a gain of ~0.75 with an offset per band explains every sample pixel,
/// and the level's halves and the image test pass it (1.4 σ each). Taken
/// as a calibration error it made every pixel valid and ~34 nm off.
/// `auto` takes no gain beyond ±15 % for a calibration error
/// (`MAX_AUTO_GAIN_ERROR`): the image is flagged, every pixel. A real
/// calibration error of 8 % is still corrected
/// (`estimate_trust::calibration_errors_are_corrected_by_default_and_flagged_when_absolute`),
/// and the same cube with the index free reads 1.39 and its thicknesses.
#[test]
fn a_film_index_given_wrong_is_not_taken_for_a_calibration_error() {
    let film139 = irid::scene::PAPER_CYLINDER.replace("film_n = 1.37", "film_n = 1.39");
    let (cube, truth) = render(&scene(&film139));
    let given = irid::scene::PAPER_CYLINDER.replace("search = [1.0, 1.6]", "n = 1.37");
    for mode in [Mode::Fast, Mode::Balanced] {
        let (maps, solver) = fit(&scene(&given), &cube, mode);
        let note = solver.level().2;
        eprintln!("{mode:?}: {:?} {note}", compare(&maps, &truth));
        assert!(
            note.contains("beyond a calibration error"),
            "{mode:?}: {note}"
        );
        assert_eq!(maps.valid_count(), 0, "{mode:?}");
    }
    let (maps, solver) = fit(&scene(irid::scene::PAPER_CYLINDER), &cube, Mode::Balanced);
    let acc = compare(&maps, &truth);
    let n = solver.film_index().unwrap().n;
    assert!((n - 1.39).abs() < 0.002, "index {n}");
    assert!(
        acc.valid_fraction > 0.97 && acc.thickness_mae_nm < 0.5,
        "{acc:?}"
    );
}

#[test]
fn clean_images_are_not_rejected() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes");
    for name in [
        "paper-cylinder",
        "thin-coating",
        "thick-hardcoat",
        "dispersive-p61",
        "wide-range",
    ] {
        for seed in 1..=3u64 {
            let mut s = Scene::load(&dir.join(format!("{name}.toml"))).unwrap();
            let t = s.truth.as_mut().unwrap();
            t.seed = seed;
            if name == "wide-range" {
                (t.width, t.height) = (280, 28);
            }
            let (cube, truth) = render(&s);
            let (maps, solver) = fit(&s, &cube, Mode::Balanced);
            let acc = compare(&maps, &truth);
            eprintln!("{name} seed {seed}: {acc:?} {}", solver.level().2);
            let note = solver.level().2;
            assert!(!rejected(&solver), "{name} seed {seed}: {note}");
            // The statistic is N(0, 1) where the model holds: within ±4
            // (a two-sided bound, p ≈ 6e-5 each of 15 images).
            let z: f64 = note
                .split("noise variances per band (")
                .nth(1)
                .and_then(|t| t.split(" σ").next())
                .and_then(|t| t.parse().ok())
                .unwrap_or_else(|| panic!("{name} seed {seed}: no statistic in {note}"));
            assert!(z.abs() < 4.0, "{name} seed {seed}: z {z}");
            assert!(acc.coverage_2sigma >= 0.9, "{name} seed {seed}: {acc:?}");
        }
    }
}

#[test]
fn wide_passbands_are_integrated_in_every_mode() {
    // Film index and every pixel's angle unknown, as in the paper; the
    // clean scene's efficient mean error is 0.368 nm (estimate_scenes.rs),
    // and a 10 nm passband leaves these films ≥ 97 % of their fringe
    // contrast, so the bound moves by a few percent at most.
    let wide = irid::scene::PAPER_CYLINDER.replace("fwhm_nm = 0", "fwhm_nm = 10");
    let s = scene(&wide);
    let (cube, truth) = render(&s);
    for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
        let (maps, solver) = fit(&s, &cube, mode);
        let acc = compare(&maps, &truth);
        eprintln!("{mode:?}: {acc:?} {}", solver.level().2);
        assert!(acc.valid_fraction >= 0.97, "{mode:?}: {acc:?}");
        assert!(acc.thickness_mae_nm <= 1.25 * 0.368, "{mode:?}: {acc:?}");
        assert!(
            (0.9..=0.99).contains(&acc.coverage_2sigma),
            "{mode:?}: {acc:?}"
        );
        assert!(acc.valid_wrong_fraction <= 0.005, "{mode:?}: {acc:?}");
        // Nothing for a level to take up: the model is the data's.
        assert_eq!(solver.level().1.name(), "absolute", "{mode:?}");
    }
}
