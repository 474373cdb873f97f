//! The solver on hostile input: any spectrum (random, NaN, infinite, huge,
//! negative, constant), any known angle, every mode — an estimate that is
//! finite in every field, or an invalid pixel with a reason; never a panic.

use irid::estimate::{Mode, Reason, Solver};
use irid::scene::Scene;
use irid::synth::scene_bands;
use proptest::prelude::*;

fn value() -> impl Strategy<Value = f64> {
    prop_oneof![
        8 => 0.0f64..0.2,
        1 => -1.0f64..2.0,
        1 => prop_oneof![
            Just(f64::NAN),
            Just(f64::INFINITY),
            Just(f64::NEG_INFINITY),
            Just(0.0),
            Just(1.0),
            Just(1e300),
            Just(-1e-300),
        ],
    ]
}

fn check(e: &irid::estimate::PixelEstimate) {
    if e.is_valid() {
        for v in [
            e.thickness_nm,
            e.n_film,
            e.theta_deg,
            e.sigma_thickness_nm,
            e.sigma_theta_deg,
            e.residual_rms,
        ] {
            assert!(
                v.is_finite(),
                "valid estimate with a non-finite field: {e:?}"
            );
        }
        assert!(e.thickness_nm >= 0.0 && e.sigma_thickness_nm >= 0.0);
    } else {
        assert!(e.reason != Reason::Ok && e.reason != Reason::AngleNotIdentifiable);
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    #[test]
    fn any_spectrum_gives_finite_or_flagged(
        spec in proptest::collection::vec(value(), 31),
        theta in prop_oneof![Just(None), (-1.0f64..2.0).prop_map(Some), Just(Some(f64::NAN))],
        mode in prop_oneof![Just(Mode::Fast), Just(Mode::Balanced), Just(Mode::Accurate)],
    ) {
        let text = irid::scene::PAPER_CYLINDER.replace("search = [1.0, 1.6]", "n = 1.37");
        let scene = Scene::from_toml(&text, "t", std::path::Path::new(".")).unwrap();
        let bands = scene_bands(&scene).unwrap();
        let mut solver = Solver::new(&scene, &bands, mode).unwrap();
        // A noise level as an index search would have set it.
        let mut idx = solver.film_index().unwrap().clone();
        idx.noise_sigma = 0.001;
        solver.set_film_index(idx).unwrap();
        let mut scratch = irid::estimate::solver::Scratch::default();
        let e = solver.solve_pixel(&spec, theta, &mut scratch);
        check(&e);
    }

    #[test]
    fn wrong_length_spectra_are_refused(len in 0usize..80) {
        let scene = Scene::paper_cylinder();
        let bands = scene_bands(&scene).unwrap();
        let mut solver = Solver::new(&scene, &bands, Mode::Balanced).unwrap();
        let mut idx = irid::estimate::IndexEstimate {
            n: 1.37, sigma: 0.0, estimated: false, twin: None, twin_delta_chi2: f64::NAN,
            noise_sigma: 0.001, note: String::new(), ambiguous: false, at_bound: false, sigma_in_level: false,
            scale_branches: None, branches: None,
        };
        idx.noise_sigma = 0.001;
        solver.set_film_index(idx).unwrap();
        let mut scratch = irid::estimate::solver::Scratch::default();
        let e = solver.solve_pixel(&vec![0.05; len], None, &mut scratch);
        check(&e);
        if len != 31 {
            prop_assert!(!e.is_valid());
        }
    }
}
