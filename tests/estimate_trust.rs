//! Trust on data irid's model did not render as it is: calibration errors
//! (a white reference off in gain, per band, stray light), a cube that is
//! not reflectance, films past the bands' range, a wrong substrate. Each
//! asserts accuracy where the level model corrects the error, and a flag
//! with the right reason where nothing can — never a confident wrong
//! number.
//!
//! "Wrong" is |Δd| > max(3σ, 2 nm): a pixel the estimate's own σ does not
//! cover. The paper's cylinder has σ_R = 0.001; its Cramér–Rao bound gives
//! a mean |Δd| of 0.37 nm with the angle unknown (see estimate_scenes.rs).

mod scene_common;
use irid::estimate::level::LevelMode;
use irid::estimate::{Cube, Mode, ParamMaps, Reason, Solver};
use irid::scene::Scene;
use irid::synth::{compare, scene_bands, Accuracy, Renderer, TruthMaps};
use scene_common::with_known_angle;

fn render(s: &Scene) -> (Cube, TruthMaps) {
    let bands = scene_bands(s).unwrap();
    let r = Renderer::new(s).unwrap();
    (r.render_cube(&bands).unwrap(), r.truth_maps(&bands))
}

/// Apply `y = gain_k·R + offset` per band.
fn miscalibrate(cube: &mut Cube, gain: &dyn Fn(usize) -> f64, offset: f64) {
    let n = cube.plane_len();
    for k in 0..cube.bands.len() {
        let g = gain(k);
        for v in &mut cube.data[k * n..(k + 1) * n] {
            *v = (f64::from(*v) * g + offset) as f32;
        }
    }
}

/// Per-band gain errors of ±`amp`, deterministic and irregular.
fn per_band(amp: f64) -> impl Fn(usize) -> f64 {
    move |k| 1.0 + amp * (((k * 37 + 11) % 13) as f64 / 6.0 - 1.0)
}

fn fit_with(s: &Scene, cube: &Cube, mode: Mode) -> (ParamMaps, Solver) {
    let mut solver = Solver::new(s, &cube.bands, mode).unwrap();
    let maps = solver.fit_cube(cube).unwrap();
    (maps, solver)
}

/// Fraction of all pixels that are valid and wrong.
fn valid_wrong(maps: &ParamMaps, truth: &TruthMaps) -> f64 {
    let n = maps.width * maps.height;
    let bad = (0..n)
        .filter(|&i| maps.valid[i] > 0.5)
        .filter(|&i| {
            let e = (maps.thickness_nm[i] - truth.thickness_nm[i]).abs() as f64;
            e > (3.0 * maps.sigma_thickness_nm[i] as f64).max(2.0)
        })
        .count();
    bad as f64 / n as f64
}

fn count(maps: &ParamMaps, r: Reason) -> usize {
    maps.reason.iter().filter(|&&c| c as u8 == r as u8).count()
}

/// Fit `cube` under `s` in `mode`, report it as `label` and return the
/// maps, the solver and the fraction of pixels valid and wrong.
fn fit_reported(
    label: &str,
    s: &Scene,
    cube: &Cube,
    truth: &TruthMaps,
    mode: Mode,
) -> (ParamMaps, Solver, f64) {
    let (maps, solver) = fit_with(s, cube, mode);
    let wrong = valid_wrong(&maps, truth);
    let label = format!("{label} {}", mode.name());
    report(&label, &compare(&maps, truth), wrong, &solver);
    (maps, solver, wrong)
}

fn report(label: &str, acc: &Accuracy, wrong: f64, solver: &Solver) {
    let (l, _, _) = solver.level();
    let vg = l.var_gain.iter().sum::<f64>() / l.var_gain.len() as f64;
    eprintln!(
        "{label}: sd_gain {:.2e} index {:?} valid {:.3} MAE {:.3} nm p99 {:.2} cover {:.3} wrong {:.4} level {} ({})",
        vg.sqrt(),
        solver.film_index().map(|i| (i.n, i.sigma, i.note.clone())),
        acc.valid_fraction,
        acc.thickness_mae_nm,
        acc.thickness_p99_nm,
        acc.coverage_2sigma,
        wrong,
        solver.level().1.name(),
        solver.level().2
    );
}

/// A per-band gain (applied as `y = gain·R + offset`).
type Gain = Box<dyn Fn(usize) -> f64>;

/// The issue's calibration errors on the paper's cylinder: label, gain,
/// offset, and the Cramér–Rao bound of each case under the level that
/// describes it (film index unknown, every pixel's angle unknown): the
/// mean |Δd| an efficient estimator reaches, from an independent
/// formulation (`python3 tools/level_crb.py`). A level with more
/// parameters than the error needs costs precision (stray light fitted as
/// a gain and an offset: 0.99 nm; a per-band gain fitted with per-band
/// offsets too: 1.06 nm), which 1.3× the bound does not allow.
fn calibration_cases() -> Vec<(&'static str, Gain, f64, f64)> {
    vec![
        ("white 5 % high", Box::new(|_| 1.0 / 1.05), 0.0, 0.752),
        ("white 8 % low", Box::new(|_| 1.0 / 0.92), 0.0, 0.649),
        ("stray light +0.004", Box::new(|_| 1.0), 0.004, 0.369),
        ("per-band ±6 %", Box::new(per_band(0.06)), 0.0, 0.740),
    ]
}

/// The paper's cylinder with noise seed `seed`, rendered and
/// miscalibrated by `gain` and `offset`: the scene, the cube and the truth.
fn miscalibrated_cylinder(
    seed: u64,
    gain: &dyn Fn(usize) -> f64,
    offset: f64,
) -> (Scene, Cube, TruthMaps) {
    let mut base = Scene::paper_cylinder();
    base.truth.as_mut().unwrap().seed = seed;
    let (mut cube, truth) = render(&base);
    miscalibrate(&mut cube, gain, offset);
    (base, cube, truth)
}

#[test]
fn calibration_errors_are_corrected_by_default_and_flagged_when_absolute() {
    // A level error is shared by every pixel of an image, so one image's
    // coverage is not a binomial count: what σ must cover is the scatter
    // of the level estimate over noise realisations. Four seeds per case;
    // the bounds: `calibration_cases`.
    for (label, gain, offset, bound) in calibration_cases() {
        let (mut covered, mut valid, mut total, mut abs_err, mut sig) = (0, 0, 0, 0.0, 0.0);
        for seed in 1..=4u64 {
            let (base, cube, truth) = miscalibrated_cylinder(seed, &gain, offset);
            // The default level (auto) corrects it.
            let (maps, solver) = fit_with(&base, &cube, Mode::Balanced);
            let acc = compare(&maps, &truth);
            let wrong = valid_wrong(&maps, &truth);
            report(&format!("{label} seed {seed}"), &acc, wrong, &solver);
            assert_eq!(solver.level().1, LevelMode::Scaled, "{label} seed {seed}");
            assert!(acc.valid_fraction >= 0.95, "{label} seed {seed}: {acc:?}");
            let n = maps.width * maps.height;
            for i in (0..n).filter(|&i| maps.valid[i] > 0.5) {
                let e = (maps.thickness_nm[i] - truth.thickness_nm[i]).abs() as f64;
                let s = maps.sigma_thickness_nm[i] as f64;
                covered += usize::from(e <= 2.0 * s);
                abs_err += e;
                sig += s;
                valid += 1;
            }
            total += n;
            // Told to trust the calibration, irid flags instead of guessing.
            let mut s = base.clone();
            s.level = LevelMode::Absolute;
            let (maps, solver) = fit_with(&s, &cube, Mode::Balanced);
            let acc = compare(&maps, &truth);
            let wrong = valid_wrong(&maps, &truth);
            report(
                &format!("{label} seed {seed}, absolute"),
                &acc,
                wrong,
                &solver,
            );
            assert!(
                wrong <= 0.01,
                "{label} seed {seed} absolute: {wrong} {acc:?}"
            );
        }
        let coverage = covered as f64 / valid as f64;
        let (mae, mean_sigma) = (abs_err / valid as f64, sig / valid as f64);
        eprintln!("{label}: pooled coverage {coverage:.3}, mean |Δd| {mae:.2} nm, mean σ {mean_sigma:.2} nm, valid {:.3}", valid as f64 / total as f64);
        // σ neither too small nor too large over the realisations; and the
        // error what a Gaussian of that σ gives (E|x| = 0.8 σ), within
        // the spread of four shared level errors.
        assert!((0.88..=0.995).contains(&coverage), "{label}: {coverage}");
        assert!(mae <= 1.2 * mean_sigma, "{label}: {mae} vs σ {mean_sigma}");
        assert!(
            mae <= 1.3 * bound,
            "{label}: {mae} nm vs the bound's {bound} nm"
        );
    }
}

/// Pixels are solved on data the level corrected, (y − o)/g, whose noise
/// is σ/g: judged against the data's own σ, a cube reading 8 % low
/// (g = 0.92) flagged 4.0 % of its pixels "poor fit" against 0.7 % clean
/// (the χ² of a good fit reads 1/g² = 1.18× high). Judged against σ/g the
/// flags are the clean image's, within 1 % of the pixels (the binomial
/// spread of the difference on 1 960 pixels is 0.3 %), while the noise
/// reported stays the data's.
#[test]
fn pixels_under_a_level_are_judged_against_the_noise_it_leaves() {
    for seed in 1..=2u64 {
        let (base, clean, _) = miscalibrated_cylinder(seed, &|_| 1.0, 0.0);
        let (maps, solver) = fit_with(&base, &clean, Mode::Balanced);
        let n = (maps.width * maps.height) as f64;
        let poor_clean = count(&maps, Reason::PoorFit) as f64 / n;
        let sigma_clean = solver.noise().unwrap().typical_sigma(0.05);
        let (_, low, truth) = miscalibrated_cylinder(seed, &|_| 0.92, 0.0);
        let (maps, solver) = fit_with(&base, &low, Mode::Balanced);
        report(
            &format!("×0.92 seed {seed}"),
            &compare(&maps, &truth),
            valid_wrong(&maps, &truth),
            &solver,
        );
        let (level, mode, _) = solver.level();
        assert_eq!(mode, LevelMode::Scaled, "seed {seed}");
        assert!(
            (level.gain[0] - 0.92).abs() < 0.05,
            "seed {seed}: {:?}",
            level.gain
        );
        let poor = count(&maps, Reason::PoorFit) as f64 / n;
        assert!(
            poor <= poor_clean + 0.01,
            "seed {seed}: {poor:.4} of the pixels poor fit, {poor_clean:.4} clean"
        );
        // The data's own noise, 8 % smaller than the clean cube's.
        let sigma = solver.noise().unwrap().typical_sigma(0.05);
        assert!(
            (sigma / sigma_clean - 0.92).abs() < 0.03,
            "seed {seed}: σ {sigma:.3e} against {sigma_clean:.3e} clean"
        );
    }
}

#[test]
fn each_pixel_carries_the_level_share_its_own_fit_gives_it() {
    // Two images (noise seeds 101 and 106 of `cargo bench --bench
    // level_seeds`) whose fitted gain comes out about 2 of its σ off, low and
    // high: every thickness then moves with the gain, and σ must carry
    // that share pixel by pixel. The rows at large angles, whose own σ is
    // smallest, must be off by as many of their σ as the rows near normal
    // incidence (one factor for every pixel, set by the median pixel,
    // left them 2.8 against 1.5), and every angle by as many of its σ as
    // its thickness (with no share, angles were 3.4–6.1 of their σ off).
    for seed in [101, 106] {
        let (base, cube, truth) = miscalibrated_cylinder(seed, &|_| 1.0 / 1.05, 0.0);
        let (maps, solver) = fit_with(&base, &cube, Mode::Balanced);
        let (level, mode, _) = solver.level();
        assert_eq!(mode, LevelMode::Scaled);
        let z_gain = (level.gain[0] - 1.0 / 1.05) / level.var_gain[0].sqrt();
        // The premise: the gain is well off on these images.
        assert!(z_gain.abs() > 1.5, "seed {seed}: gain z {z_gain:.2}");
        // Σ z² and counts: thickness in the four rows at 10–17.5°, in the
        // four at 35–42.5°, and the angle over every valid pixel.
        let (mut z2, mut nz) = ([0.0f64; 3], [0usize; 3]);
        let mut add = |k: usize, z: f64| {
            z2[k] += z * z;
            nz[k] += 1;
        };
        for i in (0..maps.width * maps.height).filter(|&i| maps.valid[i] > 0.5) {
            let zd = f64::from(maps.thickness_nm[i] - truth.thickness_nm[i])
                / f64::from(maps.sigma_thickness_nm[i]);
            let zt = f64::from(maps.theta_deg[i] - truth.theta_deg[i])
                / f64::from(maps.sigma_theta_deg[i]);
            match i / maps.width {
                r if r < 4 => add(0, zd),
                r if r + 4 >= maps.height => add(1, zd),
                _ => {}
            }
            add(2, zt);
        }
        let rms = |k: usize| (z2[k] / nz[k] as f64).sqrt();
        let (low, high, angle) = (rms(0), rms(1), rms(2));
        eprintln!("seed {seed}: gain z {z_gain:+.2}; thickness RMS z {low:.2} at 10–17.5°, {high:.2} at 35–42.5°; angle RMS z {angle:.2}");
        assert!(
            (0.8..=1.25).contains(&(high / low)),
            "seed {seed}: thickness RMS z {low:.2} near normal incidence, {high:.2} at large angles"
        );
        assert!(
            (0.6..=1.4).contains(&(angle / (0.5 * (low + high)))),
            "seed {seed}: angle RMS z {angle:.2} against the thickness's {low:.2}–{high:.2}"
        );
        // And none of it beyond what the gain's own error explains.
        assert!(high.max(low) <= z_gain.abs() + 0.5, "seed {seed}");
    }
}

#[test]
fn clean_data_keep_the_absolute_level_and_the_statistical_limit() {
    let base = Scene::paper_cylinder();
    let (cube, truth) = render(&base);
    for mode in [Mode::Fast, Mode::Balanced] {
        let (maps, solver) = fit_with(&base, &cube, mode);
        let acc = compare(&maps, &truth);
        let wrong = valid_wrong(&maps, &truth);
        report(mode.name(), &acc, wrong, &solver);
        assert_eq!(solver.level().1, LevelMode::Absolute);
        // The χ² test flags about its nominal 0.5 % of clean pixels (plus
        // the angle-poor rows' few): ≥ 97 % stay valid.
        assert!(acc.valid_fraction >= 0.97, "{mode:?}: {acc:?}");
        // The bound's efficient mean error here is ~0.37 nm: both modes
        // reach it (`fast` by one Gauss–Newton step from its closed form).
        assert!(acc.thickness_mae_nm <= 0.42, "{mode:?}: {acc:?}");
        assert!(
            (0.90..=0.995).contains(&acc.coverage_2sigma),
            "{mode:?}: {acc:?}"
        );
        assert!(wrong <= 0.005, "{mode:?}: {wrong}");
    }
}

#[test]
fn a_cube_that_is_not_reflectance_is_never_valid_and_wrong() {
    let base = Scene::paper_cylinder();
    let (mut cube, truth) = render(&base);
    miscalibrate(&mut cube, &|_| 5.0, 0.1);
    for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
        let mut s = base.clone();
        s.level = LevelMode::Absolute;
        let (maps, solver) = fit_with(&s, &cube, mode);
        let acc = compare(&maps, &truth);
        report(
            &format!("x5+0.1 {}", mode.name()),
            &acc,
            valid_wrong(&maps, &truth),
            &solver,
        );
        assert_eq!(maps.valid_count(), 0, "{mode:?}");
        let n = maps.width * maps.height;
        // With the angle free, steep incidence reaches such levels, but no
        // film explains the spectrum's shape.
        let flagged = count(&maps, Reason::OutOfModel) + count(&maps, Reason::PoorFit);
        assert!(flagged * 10 >= 9 * n, "{mode:?}");
        // auto either corrects it or flags it: never valid and wrong.
        let (_, _, wrong) = fit_reported("x5+0.1 auto", &base, &cube, &truth, mode);
        assert!(wrong <= 0.01, "{mode:?}: {wrong}");
    }
    // With the angle known, the levels alone lie beyond anything a film on
    // this substrate reflects: "out of model".
    let mut s = with_known_angle(base.clone());
    s.level = LevelMode::Absolute;
    let (maps, _) = fit_with(&s, &cube, Mode::Balanced);
    let n = maps.width * maps.height;
    assert_eq!(maps.valid_count(), 0);
    assert!(count(&maps, Reason::OutOfModel) * 10 >= 9 * n);
}

#[test]
fn each_input_problem_gets_its_reason() {
    use irid::estimate::cube::{DARK_NAN, SATURATED_NAN};
    // The paper's cylinder with the angle known, seeded with one bad pixel
    // of each kind in its first row.
    let base = with_known_angle(Scene::paper_cylinder());
    let (mut cube, _) = render(&base);
    let n = cube.plane_len();
    let nb = cube.bands.len();
    let set = |cube: &mut Cube, x: usize, f: &dyn Fn(usize, f32) -> f32| {
        for k in 0..nb {
            let v = cube.data[k * n + x];
            cube.data[k * n + x] = f(k, v);
        }
    };
    set(&mut cube, 0, &|_, _| f32::INFINITY);
    set(&mut cube, 1, &|_, _| DARK_NAN);
    set(&mut cube, 2, &|_, _| SATURATED_NAN);
    set(&mut cube, 3, &|k, v| if k % 3 == 0 { v } else { f32::NAN });
    // Far brighter than any film on this substrate reflects at its angle.
    set(&mut cube, 4, &|_, _| 0.9);
    // A fringe-sized wiggle no film makes.
    set(&mut cube, 5, &|k, v| {
        v + 0.01 * ((k % 2) as f32 * 2.0 - 1.0)
    });
    let (maps, _) = fit_with(&base, &cube, Mode::Balanced);
    let expect = [
        Reason::NonFinite,
        Reason::Dark,
        Reason::Saturated,
        Reason::MissingBands,
        Reason::OutOfModel,
        Reason::PoorFit,
    ];
    for (x, r) in expect.iter().enumerate() {
        assert_eq!(maps.reason[x] as u8, *r as u8, "pixel {x}");
        assert!(maps.valid[x] < 0.5 && maps.thickness_nm[x].is_nan());
    }
    // The rest of the image is unaffected.
    assert!(maps.valid_count() * 100 >= 97 * (n - expect.len()));

    // A film past what 10 nm bands resolve (optical thickness ≥ 3.3 µm):
    // never a valid number; the fit lands beyond the range (11) or fails.
    let thick = Scene::from_toml(
        r#"
[ambient]
n = 1.0
[substrate]
n = 1.6
[film]
n = 1.37
[angle]
deg = 10.0
[light]
polarization = "s"
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[truth]
width = 40
height = 4
thickness_nm = { linear_x = [2500.0, 3000.0] }
angle_deg = { constant = 10.0 }
noise_sigma = 0.001
seed = 1
"#,
        "<test>",
        std::path::Path::new("."),
    )
    .unwrap();
    let (cube, _) = render(&thick);
    let (maps, _) = fit_with(&thick, &cube, Mode::Balanced);
    assert_eq!(maps.valid_count(), 0);
    assert!(count(&maps, Reason::Unresolved) > 0, "{:?}", maps.reason);
    assert_eq!(
        count(&maps, Reason::Unresolved) + count(&maps, Reason::PoorFit),
        maps.width * maps.height
    );

    // A film index pinned at an end of its search: every pixel says so.
    let mut narrow = Scene::paper_cylinder();
    if let irid::scene::FilmKnowledge::Unknown { search, .. } = &mut narrow.film {
        *search = (1.45, 1.6);
    }
    let (cube, _) = render(&narrow);
    let (maps, solver) = fit_with(&narrow, &cube, Mode::Balanced);
    assert!(solver.film_index().unwrap().at_bound);
    assert_eq!(maps.valid_count(), 0);
    assert!(count(&maps, Reason::AtBound) > 0);
}

#[test]
fn the_free_level_reads_thickness_from_normalised_intensities() {
    // Free-standing water films (H2O-Hale, air both sides, normal
    // incidence) seen as a spectrometer sees them after an imperfect lamp
    // division: scaled, offset and tilted by a slow envelope the model was
    // never told, then noise.
    let s = Scene::from_toml(
        r#"
[ambient]
n = 1.0
[substrate]
n = 1.0
[film]
material = "H2O-Hale"
[angle]
deg = 0.0
[light]
polarization = "u"
[measurement]
level = "free"
[bands]
start_nm = 450
stop_nm = 900
step_nm = 3
fwhm_nm = 0
[truth]
width = 60
height = 1
film_material = "H2O-Hale"
thickness_nm = { linear_x = [300.0, 3000.0] }
angle_deg = { constant = 0.0 }
noise_sigma = 0.0005
seed = 3
"#,
        "<test>",
        std::path::Path::new("."),
    )
    .unwrap();
    let (mut cube, truth) = render(&s);
    let n = cube.plane_len();
    let nb = cube.bands.len();
    for k in 0..nb {
        let u = 2.0 * k as f64 / (nb - 1) as f64 - 1.0;
        let env = 6.0 * (1.0 + 0.25 * u - 0.15 * u * u);
        for v in &mut cube.data[k * n..(k + 1) * n] {
            *v = (f64::from(*v) * env + 0.12) as f32;
        }
    }
    let (maps, _) = fit_with(&s, &cube, Mode::Balanced);
    let mut valid = 0;
    for x in 0..n {
        let d = f64::from(truth.thickness_nm[x]);
        if maps.valid[x] < 0.5 {
            continue;
        }
        valid += 1;
        let e = (f64::from(maps.thickness_nm[x]) - d).abs();
        let sig = f64::from(maps.sigma_thickness_nm[x]);
        // Within 1 % of the truth and within 3σ + 1 nm of it: the
        // thickness comes from the fringes, not the level.
        assert!(e <= 0.01 * d, "d {d:.0}: error {e:.2} nm (σ {sig:.2})");
        assert!(
            e <= 3.0 * sig + 1.0,
            "d {d:.0}: error {e:.2} nm, σ {sig:.2}"
        );
    }
    assert!(
        valid * 10 >= 9 * n,
        "{valid} of {n} valid: {:?}",
        maps.reason
    );
}

/// A reflectance scale accurate to ε (`[measurement]
/// reflectance_accuracy`), on the paper's cylinder (angle per pixel and
/// index known) with its white reference 4 % high and the level held
/// absolute: every pixel's σ_d carries the scale's share (the fit on the
/// spectrum ×(1 ± ε)), in `fit_cube` and in the row solve the live runner
/// and the line use alike; judged exact (ε = 0) the same data are flagged
/// or wrong, judged with ε = 5 % none is valid and wrong.
#[test]
fn a_scale_accuracy_widens_sigma_on_every_path() {
    let mut s = with_known_angle(Scene::paper_cylinder());
    s.level = LevelMode::Absolute;
    if let irid::scene::FilmKnowledge::Unknown { .. } = s.film {
        s.film =
            irid::scene::FilmKnowledge::Known(irid::optics::dispersion::Dispersion::constant(1.37));
    }
    let (mut cube, truth) = render(&s);
    miscalibrate(&mut cube, &|_| 1.04, 0.0);
    let exact = fit_with(&s, &cube, Mode::Balanced).0;
    s.reflectance_accuracy = 0.05;
    let (maps, mut solver) = fit_with(&s, &cube, Mode::Balanced);
    let acc = compare(&maps, &truth);
    let wrong = valid_wrong(&maps, &truth);
    eprintln!(
        "exact: valid {:.3} wrong {:.4}; ε 5 %: valid {:.3} MAE {:.3} cover {:.3} wrong {:.4}",
        compare(&exact, &truth).valid_fraction,
        valid_wrong(&exact, &truth),
        acc.valid_fraction,
        acc.thickness_mae_nm,
        acc.coverage_2sigma,
        wrong
    );
    let exact_ok = 1.0 - compare(&exact, &truth).valid_fraction + valid_wrong(&exact, &truth);
    assert!(exact_ok > 0.5, "judged exact, a 4 % gain must show");
    assert!(
        acc.valid_fraction > 0.9 && wrong <= 0.01,
        "{acc:?} wrong {wrong}"
    );
    // The row solve gives every pixel the same estimate and σ.
    solver.estimate_film_index(&cube).unwrap();
    let mut scratch = irid::estimate::solver::Scratch::default();
    let mut row = vec![irid::estimate::PixelEstimate::invalid(Reason::PoorFit); cube.width];
    for y in 0..cube.height {
        solver.solve_row(&cube, y, &mut row, &mut scratch);
        for (x, e) in row.iter().enumerate() {
            let i = y * cube.width + x;
            assert_eq!(e.is_valid(), maps.valid[i] > 0.5, "pixel {x},{y}");
            if e.is_valid() {
                let (a, b) = (e.sigma_thickness_nm, f64::from(maps.sigma_thickness_nm[i]));
                assert!((a - b).abs() <= 1e-3 * b, "pixel {x},{y}: σ {a} vs {b}");
            }
        }
    }
}

/// A valid pixel's fringes must be deep enough to place, whatever path
/// found it: at the pixel's fitted angle, the fringes' whole signal
/// Σ_k c_k²/8 (c_k band k's peak-to-peak over one fringe of thickness,
/// found here by scanning the model, a second formulation of the
/// solver's half- against quarter-wave envelopes) must reach the
/// visibility bar, 25 noise variances — less a fifth for the two
/// formulations' difference. The paper's film, its index given and the
/// angle free, at σ_R = 0.03: `fast`'s closed form once noted a weak
/// angle ("angle not identifiable", valid) before testing visibility,
/// and so passed pixels whose fringes the noise buries.
/// The paper's cylinder (a film of index 1.37, `film` the estimator's
/// knowledge of it) with the angle free, at reflectance noise `sigma`
/// (given to the estimator too) from `seed`, `width` × `height` pixels: 420
/// → 560 nm across, the angle from 10° down the rows in steps that reach
/// 42.5° at the last.
fn noisy_cylinder(sigma: f64, width: usize, height: usize, film: &str, seed: u64) -> Scene {
    let step = 32.5 / (height - 1) as f64;
    let text = format!(
        r#"
[ambient]
n = 1.0
[substrate]
n = 1.60
[film]
{film}
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
noise_sigma = {sigma}
[truth]
film_n = 1.37
width = {width}
height = {height}
thickness_nm = {{ linear_x = [420.0, 560.0] }}
angle_deg = {{ rows = [10.0, {step}] }}
noise_sigma = {sigma}
seed = {seed}
"#
    );
    Scene::from_toml(&text, "<test>", std::path::Path::new(".")).unwrap()
}

/// Where the noise is as strong as the fringes (σ_R = 0.03 on the paper's
/// cylinder, the angle free), a film in another basin of (d, θ) can fit
/// about as well as the true one: an order off, or a ~100 nm film at 45°
/// for a ~500 nm one at 15°. Such a pixel is ambiguous, never valid. Each
/// mode keeps at most 0.5 % of its valid pixels more than 100 nm off (two
/// thirds of a fringe at the bluest band; a right pixel's σ is 5–30 nm
/// here); 0.24–0.30 % are, where the other basin fits better by more than
/// the margin (the noise's own tail). Before the ambiguity test weighed the
/// best fit in another basin rather than the runner-up (which may be the
/// best's own basin reached from another start), 1.4–2.2 % of every mode's
/// were; with that alone, 2.2 % of `fast`'s, whose closed form settled weak
/// fringes without weighing the other basins.
#[test]
fn a_valid_pixel_is_in_the_right_basin_where_noise_rivals_the_fringes() {
    let s = noisy_cylinder(0.03, 280, 56, "n = 1.37", 1);
    let (cube, truth) = render(&s);
    let mut results = Vec::new();
    for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
        let (maps, _) = fit_with(&s, &cube, mode);
        let valid: Vec<usize> = (0..maps.width * maps.height)
            .filter(|&i| maps.valid[i] > 0.5)
            .collect();
        let far = valid
            .iter()
            .filter(|&&i| (maps.thickness_nm[i] - truth.thickness_nm[i]).abs() > 100.0)
            .count();
        eprintln!(
            "{mode:?}: {far} of {} valid pixels > 100 nm off",
            valid.len()
        );
        results.push((mode, far, valid.len()));
    }
    for (mode, far, valid) in results {
        assert!(valid > 500, "{mode:?}: {valid} valid: nothing to judge");
        assert!(
            far as f64 <= 0.005 * valid as f64,
            "{mode:?}: {far} of {valid} valid pixels in another basin"
        );
    }
}

/// The film index shared by every pixel, each with its own thickness and
/// angle: where the noise rivals the fringes (σ_R = 0.03), the profile
/// over the index is biased (−0.010 for the paper's cylinder, 3.5 of its
/// σ), and every thickness follows. Rendered samples measure the bias and
/// it is removed: on four noise seeds each estimate lies within 3σ of the
/// truth (−0.0025…+0.0041 with σ 0.0033–0.0038; without the correction
/// the first seed read 1.3590 ± 0.0030, 3.7σ off), σ is not widened to
/// get there (at most 0.006), and the note says so. A clean image's index
/// is left as the profile gives it. The level is held absolute: its own
/// test is not what is judged.
#[test]
fn the_film_index_is_not_biased_where_noise_rivals_the_fringes() {
    let unknown = "search = [1.0, 1.6]";
    for seed in 1..=4 {
        let mut s = noisy_cylinder(0.03, 140, 28, unknown, seed);
        s.level = LevelMode::Absolute;
        let (cube, _) = render(&s);
        let mut solver = Solver::new(&s, &cube.bands, Mode::Balanced).unwrap();
        let est = solver.estimate_film_index(&cube).unwrap();
        eprintln!(
            "seed {seed}: n = {:.4} ± {:.4} ({})",
            est.n, est.sigma, est.note
        );
        assert!(
            (est.n - 1.37).abs() <= 3.0 * est.sigma && est.sigma <= 0.006,
            "seed {seed}: n = {:.4} ± {:.4} for 1.37",
            est.n,
            est.sigma
        );
        assert!(est.note.contains("bias"), "{}", est.note);
    }
    let mut s = noisy_cylinder(0.001, 140, 28, unknown, 1);
    s.level = LevelMode::Absolute;
    let (cube, _) = render(&s);
    let mut solver = Solver::new(&s, &cube.bands, Mode::Balanced).unwrap();
    let est = solver.estimate_film_index(&cube).unwrap();
    assert!(!est.note.contains("bias"), "{}", est.note);
    assert!((est.n - 1.37).abs() <= 3.0 * est.sigma, "{est:?}");
}

#[test]
fn no_valid_pixel_has_fringes_the_noise_buries() {
    use irid::estimate::model::ModelOut;
    let sigma = 0.03;
    let s = noisy_cylinder(sigma, 140, 14, "n = 1.37", 1);
    let bands = scene_bands(&s).unwrap();
    let (cube, _) = render(&s);
    let model = scene_common::point_model(&s, &bands);
    let mut out = ModelOut::new(bands.len());
    for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
        let mut solver = Solver::new(&s, &bands, mode).unwrap();
        let maps = solver.fit_cube(&cube).unwrap();
        let (mut valid, mut buried) = (0, 0);
        for i in 0..maps.width * maps.height {
            if maps.valid[i] < 0.5 {
                continue;
            }
            valid += 1;
            let theta = f64::from(maps.theta_deg[i]).to_radians();
            // One fringe at the reddest band: 700 / (2·q2) < 300 nm.
            let (mut lo, mut hi) = (vec![f64::INFINITY; bands.len()], vec![0.0f64; bands.len()]);
            for j in 0..=600 {
                model.eval(0.5 * f64::from(j), theta, &mut out, false);
                for (k, &r) in out.r.iter().enumerate() {
                    lo[k] = lo[k].min(r);
                    hi[k] = hi[k].max(r);
                }
            }
            let signal: f64 = lo
                .iter()
                .zip(&hi)
                .map(|(a, b)| (b - a) * (b - a) / 8.0)
                .sum();
            if signal / (sigma * sigma) < 0.8 * 25.0 {
                buried += 1;
            }
        }
        eprintln!("{mode:?}: {valid} valid, {buried} with fringes under the bar");
        assert!(valid > 0, "{mode:?}: nothing valid to judge");
        assert_eq!(buried, 0, "{mode:?}: {buried} of {valid} valid pixels");
    }
}

/// A dispersive film (fused silica, Sellmeier) fitted with its index
/// unknown — one constant index — on a PET web, unpolarised, the angle
/// free: no constant index explains the fringes, and the misfit it leaves
/// is no calibration error. A level absorbs much of it (a gain and an
/// offset per band, Δχ² in the thousands), but one fitted on the thinner
/// films and one on the thicker differ by ~19 σ, where every calibration
/// error of the tests above leaves their two halves within 2.3 σ. Until
/// that test `auto` took the level and left 74 % of the pixels valid and
/// 5.6 nm off on average (σ ~1 nm); now every mode flags them.
#[test]
fn a_constant_index_for_a_dispersive_film_is_flagged_not_taken_for_a_level() {
    let text = r#"
[ambient]
n = 1.0
[substrate]
material = "PET-Zhang"
[film]
[angle]
search_deg = [0.0, 80.0]
[light]
polarization = "u"
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[truth]
width = 170
height = 12
film_material = "SiO2-Malitson"
thickness_nm = { linear_x = [60.0, 400.0] }
angle_deg = { rows = [28.0, 0.3] }
noise_sigma = 0.001
seed = 3
"#;
    let s = Scene::from_toml(text, "<test>", std::path::Path::new(".")).unwrap();
    let (cube, truth) = render(&s);
    for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
        let label = "dispersive film, constant index";
        let (_, solver, wrong) = fit_reported(label, &s, &cube, &truth, mode);
        assert!(wrong <= 0.01, "{mode:?}: {wrong}");
        let note = solver.level().2;
        assert_eq!(solver.level().1, LevelMode::Absolute, "{mode:?}: {note}");
        if mode != Mode::Accurate {
            // `accurate` integrates passbands and tests no level.
            // The halves part, or the level's gain (0.85) is beyond a
            // calibration's (`MAX_AUTO_GAIN_ERROR`): either flags it.
            assert!(
                note.contains("no calibration error")
                    || note.contains("beyond a calibration error"),
                "{mode:?}: {note}"
            );
        }
    }
}

#[test]
fn a_calibration_error_below_the_test_is_hedged_not_trusted() {
    // A white reference 3 % low on the paper's cylinder (index and every
    // angle unknown): the gain trades with the angles, so the level test
    // (p = 1e-4) rarely sees it, and `absolute` left 99 % of the pixels
    // valid and 3.5 nm off (σ ~0.4 nm). `auto` now weighs a gain and an
    // offset against the calibration by their evidence and fits under the
    // mixture (`level_hedge`). Over `level_seeds`' 32 images about one in
    // seven still reads mostly wrong — where the noise hides the gain, no
    // method can tell it from a clean image — so the suite's four seeds
    // are pooled, and what is asserted is what the mixture guarantees on
    // average: most images corrected, the error against σ no worse than
    // a Gaussian's tail allows pooled over the four.
    let (mut wrong, mut err, mut valid, mut levels) = (0.0, 0.0, 0, 0);
    for seed in 1..=4u64 {
        let mut base = Scene::paper_cylinder();
        base.truth.as_mut().unwrap().seed = seed;
        let (mut cube, truth) = render(&base);
        miscalibrate(&mut cube, &|_| 1.03, 0.0);
        let (maps, solver, w) = fit_reported(
            &format!("white 3 % low seed {seed}"),
            &base,
            &cube,
            &truth,
            Mode::Balanced,
        );
        wrong += w / 4.0;
        levels += usize::from(solver.level().1 == LevelMode::Scaled);
        for i in (0..maps.width * maps.height).filter(|&i| maps.valid[i] > 0.5) {
            err += (maps.thickness_nm[i] - truth.thickness_nm[i]).abs() as f64;
            valid += 1;
        }
    }
    let mae = err / valid as f64;
    eprintln!("white 3 % low: {levels} of 4 images levelled, mean |Δd| {mae:.2} nm, valid and wrong {wrong:.3}");
    assert_eq!(levels, 4);
    assert!(wrong <= 0.25, "{wrong}");
    assert!(mae <= 2.0, "{mae}");
}

/// `fast` with the angle free solves each row on an angle estimated from
/// its samples' free fits; under an image-wide level error every sample's
/// angle moves alike, so the row's angle does, and each pixel's thickness
/// with it. Its σ must carry the level's share as a free fit's does (with
/// a known angle's share, 56–69 % of the pixels lay within 2σ). The same
/// cases and bounds as `calibration_errors_are_corrected_by_default_…`
/// (`balanced`): valid ≥ 95 %, mean |Δd| ≤ 1.3× the case's bound, 2σ
/// coverage ≥ 0.88 over four seeds (four draws of the level's error: no
/// bound from above is possible from them), at most 1 % valid and wrong.
#[test]
fn fast_rows_on_their_angle_carry_the_levels_share_of_sigma() {
    for (label, gain, offset, bound) in calibration_cases() {
        let (mut covered, mut valid, mut total, mut abs_err, mut wrong) = (0, 0, 0, 0.0, 0.0);
        for seed in 1..=4u64 {
            let (base, cube, truth) = miscalibrated_cylinder(seed, &gain, offset);
            let (maps, _) = fit_with(&base, &cube, Mode::Fast);
            wrong = f64::max(wrong, valid_wrong(&maps, &truth));
            let n = maps.width * maps.height;
            total += n;
            for i in (0..n).filter(|&i| maps.valid[i] > 0.5) {
                let e = (maps.thickness_nm[i] - truth.thickness_nm[i]).abs() as f64;
                covered += usize::from(e <= 2.0 * maps.sigma_thickness_nm[i] as f64);
                valid += 1;
                abs_err += e;
            }
        }
        let (vf, mae, cov) = (
            valid as f64 / total as f64,
            abs_err / valid as f64,
            covered as f64 / valid as f64,
        );
        eprintln!(
            "{label}: valid {vf:.3}, MAE {mae:.3} nm, 2σ {cov:.3}, valid and wrong ≤ {wrong:.4}"
        );
        assert!(vf >= 0.95, "{label}: valid {vf}");
        assert!(mae <= 1.3 * bound, "{label}: MAE {mae} against {bound}");
        assert!(cov >= 0.88, "{label}: 2σ coverage {cov}");
        assert!(wrong <= 0.01, "{label}: {wrong} valid and wrong");
    }
}
