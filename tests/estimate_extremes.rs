//! Noise-free extremes across the physical domain: normal to grazing
//! incidence (0–89.5°), film indices from nearly the ambient's (1.01) to
//! nearly the substrate's (1.59 on 1.60), films of 0–3000 nm (past what
//! 10 nm bands resolve), s, p and unpolarised light, the angle known and
//! unknown, every mode. On data without noise a valid pixel must lie within
//! max(3σ, 2 nm) of the truth; what the data cannot tell must be flagged.

mod scene_common;

use irid::estimate::{Mode, Solver};
use irid::scene::Scene;
use irid::synth::{scene_bands, Renderer};
use scene_common::with_known_angle;
use std::path::Path;

/// A 31 × 19 image: thickness 0–3000 nm across, angle 0–89.5° down,
/// 400–700 nm in bands `step` nm apart.
fn scene(n2: f64, pol: &str, known: bool, step: u32) -> Scene {
    noisy_scene(n2, pol, known, step, 0.0, 1)
}

/// [`scene`] with noise of σ `noise` drawn from `seed`.
fn noisy_scene(n2: f64, pol: &str, known: bool, step: u32, noise: f64, seed: u64) -> Scene {
    let text = format!(
        r#"
[ambient]
n = 1.0
[substrate]
n = 1.6
[film]
n = {n2}
[light]
polarization = "{pol}"
[bands]
start_nm = 400
stop_nm = 700
step_nm = {step}
fwhm_nm = 0
[truth]
width = 31
height = 19
thickness_nm = {{ linear_x = [0.0, 3000.0] }}
angle_deg = {{ linear_y = [0.0, 89.5] }}
noise_sigma = {noise}
seed = {seed}
"#
    );
    let s = Scene::from_toml(&text, "<extremes>", Path::new(".")).expect("scene parses");
    if known {
        with_known_angle(s)
    } else {
        s
    }
}

/// The valid pixels farther than max(3σ, 2 nm) from the truth, per case and
/// mode, with how many pixels were valid (printed, so a run shows that the
/// check is not passed by flagging everything).
fn wrong_pixels(n2: f64, pol: &str, known: bool, step: u32, modes: &[Mode]) -> Vec<String> {
    let s = scene(n2, pol, known, step);
    let bands = scene_bands(&s).unwrap();
    let r = Renderer::new(&s).unwrap();
    let cube = r.render_cube(&bands).unwrap();
    let truth = r.truth_maps(&bands);
    let mut out = vec![];
    for &mode in modes {
        let mut solver = Solver::new(&s, &bands, mode).unwrap();
        let maps = solver.fit_cube(&cube).unwrap();
        let n = maps.width * maps.height;
        let mut valid = 0;
        for i in 0..n {
            if maps.valid[i] < 0.5 {
                continue;
            }
            valid += 1;
            let d = f64::from(truth.thickness_nm[i]);
            let err = f64::from(maps.thickness_nm[i]) - d;
            let tol = (3.0 * f64::from(maps.sigma_thickness_nm[i])).max(2.0);
            if err.abs() > tol {
                out.push(format!(
                    "n2 {n2} {pol} angle known {known} {step} nm {mode:?}: d {d:.0} nm θ {:.1}°: {:.1} ± {:.2} nm (θ̂ {:.2}°)",
                    truth.theta_deg[i],
                    maps.thickness_nm[i],
                    maps.sigma_thickness_nm[i],
                    maps.theta_deg[i]
                ));
            }
        }
        eprintln!("n2 {n2} {pol} angle known {known} {step} nm {mode:?}: {valid} of {n} valid");
        // Most of the domain is measurable: flagging everything would pass
        // the check above. At least half the pixels stay valid; in p light
        // with the angle unknown, a third (around Brewster's angle, ~58° on
        // 1.6, the film's interfaces reflect next to nothing in p, so rows
        // of angles carry no fringe to fit, and a free angle finds the
        // same level on either side of it).
        let min_valid = if pol == "p" && !known { 1.0 / 3.0 } else { 0.5 };
        assert!(
            valid as f64 >= min_valid * n as f64,
            "n2 {n2} {pol} {known} {mode:?}: {valid} of {n} valid"
        );
    }
    out
}

const ALL: [Mode; 3] = [Mode::Fast, Mode::Balanced, Mode::Accurate];

/// The whole sweep: four film indices, s, p and unpolarised light, the
/// angle known and unknown, every mode. (Once open, now closed: a film
/// index-matched to its substrate (1.59 on 1.60) in p light, where films
/// past the range at 54.7° (near Brewster's angle, fringes of ~28 noise
/// variances, aliased) read ~47 nm; and in `fast`, unpolarised with the
/// angle unknown, a closed form 3.8 nm off at 1200 nm claiming σ 1.1 nm.)
#[test]
fn noise_free_extremes_are_never_valid_and_wrong() {
    let mut wrong = vec![];
    for n2 in [1.01, 1.2, 1.37, 1.59] {
        for pol in ["s", "p", "u"] {
            for known in [true, false] {
                wrong.extend(wrong_pixels(n2, pol, known, 10, &ALL));
            }
        }
    }
    assert!(wrong.is_empty(), "valid and wrong:\n{}", wrong.join("\n"));
}

/// The same at 61 bands (5 nm apart): films resolved to 6.5 µm of optical
/// thickness, so the angle's share of the fit changes. Found by this
/// sweep and fixed: unpolarised light near normal incidence with the angle
/// free, where R is even in θ and the residual stays flat towards 0° far
/// beyond the linearised σ_θ (a 2.2 µm film at 0° read 2250 ± 8.5 nm at
/// 14.6°; now the profile widens σ_θ where a probe towards normal
/// incidence stays within a variance). p light is in the two tests
/// below.
#[test]
fn noise_free_extremes_at_61_bands() {
    let mut wrong = vec![];
    for n2 in [1.01, 1.2, 1.37, 1.59] {
        for pol in ["s", "u"] {
            for known in [true, false] {
                wrong.extend(wrong_pixels(n2, pol, known, 5, &ALL));
            }
        }
    }
    assert!(wrong.is_empty(), "valid and wrong:\n{}", wrong.join("\n"));
}

/// p light at 61 bands, the angle known and free, n2 1.01–1.59. Found by
/// this sweep and fixed: n2 1.37, a 200 nm film at 54.7°
/// read 79 ± 0.5 nm at 52.2°, valid in every mode — across the ambient–
/// film Brewster angle (53.9°) the fringes shift by a quarter wave, and
/// the mirror side's scan led back to the fitted side; now its angle
/// moves stay on the mirror's side and its second basin is refined too.
/// At n2 1.59 on 1.60, once open:
/// one pixel per mode read 325 ± 1.6 nm at 65.9° for 200 nm at 44.8°, on
/// the far side of the ambient–film Brewster angle (57.8°), where the
/// fitted side's fringes are weak (under ten χ² thresholds); the mirror
/// check's scan refined to a 51 nm basin on the truth's side, not to the
/// truth. Closed by refining the previous pixel's fit beside the search's
/// (a film changes little from one pixel to the next): its basin is the
/// truth's, and the better fit wins.
#[test]
fn noise_free_extremes_at_61_bands_p_light() {
    let mut wrong = vec![];
    for n2 in [1.01, 1.2, 1.37, 1.59] {
        for known in [true, false] {
            wrong.extend(wrong_pixels(n2, "p", known, 5, &ALL));
        }
    }
    assert!(wrong.is_empty(), "valid and wrong:\n{}", wrong.join("\n"));
}

/// With one noise variance for every band, a fit on a thickness table is
/// judged from its own residual (χ² = SSE/σ², `FlatNoise::uniform`); with
/// per-band variances, from the model values again. Both judge alike: a
/// noisy image (σ = 0.002, 0–3000 nm, 0–89.5°, the angle known) judged
/// against a uniform σ and against the same σ with one band differing by
/// 1e-9 gives every pixel the same validity, thickness and σ, in every
/// mode.
#[test]
fn a_uniform_noise_judges_table_fits_as_the_per_band_path_does() {
    use irid::estimate::noise::{NoiseModel, NoiseSource};
    let s = noisy_scene(1.37, "u", true, 10, 0.002, 3);
    let bands = scene_bands(&s).unwrap();
    let cube = Renderer::new(&s).unwrap().render_cube(&bands).unwrap();
    let nb = bands.len();
    for &mode in &ALL {
        let fit = |per_band: bool| {
            let mut solver = Solver::new(&s, &bands, mode).unwrap();
            let noise = if per_band {
                let mut sig = vec![0.002; nb];
                sig[nb / 2] *= 1.0 + 1e-9;
                NoiseModel::per_band(&sig, NoiseSource::Given)
            } else {
                NoiseModel::uniform(0.002, nb, NoiseSource::Given)
            };
            solver.set_noise(noise);
            solver.fit_cube(&cube).unwrap()
        };
        let (a, b) = (fit(false), fit(true));
        let mut valid = 0;
        for i in 0..a.width * a.height {
            assert_eq!(a.valid[i], b.valid[i], "{mode:?} pixel {i}");
            if a.valid[i] > 0.5 {
                valid += 1;
                let (da, db) = (a.thickness_nm[i], b.thickness_nm[i]);
                assert!((da - db).abs() <= 1e-3, "{mode:?} pixel {i}: {da} vs {db}");
                let (sa, sb) = (a.sigma_thickness_nm[i], b.sigma_thickness_nm[i]);
                assert!(
                    (sa - sb).abs() <= 1e-4 * sa,
                    "{mode:?} pixel {i}: σ {sa} vs {sb}"
                );
            }
        }
        // Not passed by flagging everything.
        assert!(valid > a.width * a.height / 2, "{mode:?}: {valid} valid");
    }
}

/// Silicon nitride on fused silica, unpolarised, 400–700 nm, the angle
/// free (0–80°): `width` × `height` pixels, thickness `d` across, angles
/// `rows` (first, step) down, bands `step_nm` apart, noise σ `noise` from
/// `seed`.
struct ThickImage {
    step_nm: u32,
    width: usize,
    height: usize,
    d: [f64; 2],
    rows: [f64; 2],
    noise: f64,
    seed: u64,
}

impl Default for ThickImage {
    /// 61 bands at 5 nm, 1–3 µm, from normal incidence in 2° steps, no
    /// noise.
    fn default() -> Self {
        ThickImage {
            step_nm: 5,
            width: 21,
            height: 8,
            d: [1000.0, 3000.0],
            rows: [0.0, 2.0],
            noise: 0.0,
            seed: 1,
        }
    }
}

impl ThickImage {
    fn scene(&self) -> Scene {
        let ThickImage {
            step_nm,
            width,
            height,
            d: [d0, d1],
            rows: [t0, dt],
            noise,
            seed,
        } = self;
        let text = format!(
            r#"
[ambient]
n = 1.0
[substrate]
material = "SiO2-Malitson"
[film]
material = "Si3N4-Luke"
[angle]
search_deg = [0.0, 80.0]
[light]
polarization = "u"
[bands]
start_nm = 400
stop_nm = 700
step_nm = {step_nm}
fwhm_nm = 0
[truth]
width = {width}
height = {height}
film_material = "Si3N4-Luke"
thickness_nm = {{ linear_x = [{d0:.1}, {d1:.1}] }}
angle_deg = {{ rows = [{t0:.1}, {dt:.1}] }}
noise_sigma = {noise}
seed = {seed}
"#
        );
        Scene::from_toml(&text, "<thick>", Path::new(".")).expect("scene parses")
    }
}

/// A thick dispersive film near normal incidence with the angle free: the
/// fringes fix the optical thickness d·n2·cos θ2 tightly and the angle
/// barely (σ_θ ~ 1–3°), so the residual's valley is a thin parabola in
/// (d, θ). On data without noise its floor is the truth, and a refinement
/// that reaches the floor reads it: every valid pixel within 0.1 nm (the
/// convergence test stops at steps of 0.005 nm; a fit stalled on the
/// valley's wall was 4–14 nm off), the angle within 0.2°, and the films the
/// 5 nm bands resolve (d·n2 ≲ 6.5 µm) valid. `fast` stops where a step
/// would lower χ² by under 0.1 noise variance, within √0.1 = 0.32 of its σ
/// of the floor along any direction: there each within 0.35 σ (and still
/// within 0.1 nm or 0.2° where that is wider).
#[test]
fn a_thick_film_near_normal_incidence_reaches_the_valley_floor() {
    let s = ThickImage::default().scene();
    let bands = scene_bands(&s).unwrap();
    let r = Renderer::new(&s).unwrap();
    let cube = r.render_cube(&bands).unwrap();
    let truth = r.truth_maps(&bands);
    for &mode in &ALL {
        let maps = Solver::new(&s, &bands, mode)
            .unwrap()
            .fit_cube(&cube)
            .unwrap();
        let n = maps.width * maps.height;
        let mut valid = 0;
        for i in 0..n {
            if maps.valid[i] < 0.5 {
                continue;
            }
            valid += 1;
            let (d, th) = (truth.thickness_nm[i], truth.theta_deg[i]);
            let (dh, thh) = (maps.thickness_nm[i], maps.theta_deg[i]);
            let (sd, st) = (maps.sigma_thickness_nm[i], maps.sigma_theta_deg[i]);
            let (tol_d, tol_th) = match mode {
                Mode::Fast => ((0.35 * sd).max(0.1), (0.35 * st).max(0.2)),
                _ => (0.1, 0.2),
            };
            assert!(
                (dh - d).abs() <= tol_d && (thh - th).abs() <= tol_th,
                "{mode:?}: {d} nm at {th}° read {dh} nm at {thh}° (σ {sd} nm, {st}°)"
            );
        }
        assert!(valid >= n * 9 / 10, "{mode:?}: {valid} of {n} valid");
    }
}

/// The same film with noise (σ = 0.001), 5–19°: the thickness is as good as
/// the data allow and σ says how good. The Cramér–Rao bound of each pixel
/// (d and θ unknown, from the model's exact derivatives at the truth)
/// gives an efficient estimator's mean |Δd| of 0.798·σ_CRB; the fits reach
/// it within 15 % (the issue's `balanced` target; 2 400 pixels put the
/// sampling error of a mean near 2 %). 2σ covers between 90 % and 98.5 %
/// of them (Gaussian: 95.4 %, binomial σ 0.4 %: the upper end is seven σ
/// above it). Before the refinement stepped along the valley the mean was
/// 1.5× efficient, every mode; with σ from the (d, θ) linearisation
/// widened by the angle's profile 98.9 % were covered here (99.2 % on the
/// scene matrix's hard coat).
#[test]
fn a_thick_film_near_normal_incidence_is_efficient_and_its_sigma_honest() {
    use irid::estimate::model::ModelOut;
    use irid::estimate::noise::{NoiseModel, NoiseSource};
    const SIGMA_R: f64 = 0.001;
    let (mut err_sum, mut eff_sum, mut covered, mut valid, mut n) = (0.0, 0.0, 0, 0, 0);
    for seed in 1..=4 {
        let s = ThickImage {
            width: 75,
            rows: [5.0, 2.0],
            noise: SIGMA_R,
            seed,
            ..ThickImage::default()
        }
        .scene();
        let bands = scene_bands(&s).unwrap();
        let r = Renderer::new(&s).unwrap();
        let cube = r.render_cube(&bands).unwrap();
        let truth = r.truth_maps(&bands);
        let model = scene_common::point_model(&s, &bands);
        let mut out = ModelOut::new(bands.len());
        // The instrument's noise, as `irid run` measures it from its
        // calibration frames: estimated from this image without a model it
        // reads 1.7× high (27 nm of film per pixel and 2° per row leave
        // fringes in every difference), and σ is then wide by as much.
        let mut solver = Solver::new(&s, &bands, Mode::Balanced).unwrap();
        solver.set_noise(NoiseModel::uniform(
            SIGMA_R,
            bands.len(),
            NoiseSource::Given,
        ));
        let maps = solver.fit_cube(&cube).unwrap();
        for i in 0..maps.width * maps.height {
            n += 1;
            if maps.valid[i] < 0.5 {
                continue;
            }
            valid += 1;
            let (d, th) = (
                f64::from(truth.thickness_nm[i]),
                f64::from(truth.theta_deg[i]).to_radians(),
            );
            eff_sum += 0.798 * model.thickness_crb(d, th, SIGMA_R, &mut out).0;
            let err = (f64::from(maps.thickness_nm[i]) - d).abs();
            err_sum += err;
            if err <= 2.0 * f64::from(maps.sigma_thickness_nm[i]) {
                covered += 1;
            }
        }
    }
    let (mae, efficient) = (err_sum / valid as f64, eff_sum / valid as f64);
    let coverage = covered as f64 / valid as f64;
    eprintln!(
        "{valid} of {n} valid: MAE {mae:.3} nm, efficient {efficient:.3} nm, 2σ {coverage:.3}"
    );
    assert!(valid >= n * 9 / 10, "{valid} of {n} valid");
    assert!(
        mae <= 1.15 * efficient,
        "MAE {mae} nm, efficient {efficient} nm"
    );
    assert!((0.90..=0.985).contains(&coverage), "2σ covers {coverage}");
}

/// Dispersive films of 5–12 µm at a spectrometer's 1 nm sampling (301
/// bands, resolving films to ~19 µm), the angle free, without noise: the
/// fringe search's basis follows the film's dispersion (silicon nitride's
/// index falls 4 % over 400–700 nm, which at 8 µm puts a constant-index
/// cosine radians off at the ends: the search found no order and films of
/// 6 µm and more were all "poor fit"). Every pixel valid, within 0.5 nm.
#[test]
fn thick_dispersive_films_at_a_spectrometers_sampling_are_found_with_the_angle_free() {
    use irid::estimate::noise::{NoiseModel, NoiseSource};
    let s = ThickImage {
        step_nm: 1,
        width: 8,
        height: 2,
        d: [5000.0, 12000.0],
        rows: [5.0, 25.0],
        ..ThickImage::default()
    }
    .scene();
    let bands = scene_bands(&s).unwrap();
    let r = Renderer::new(&s).unwrap();
    let cube = r.render_cube(&bands).unwrap();
    let truth = r.truth_maps(&bands);
    for mode in [Mode::Fast, Mode::Balanced] {
        let mut solver = Solver::new(&s, &bands, mode).unwrap();
        solver.set_noise(NoiseModel::uniform(0.001, bands.len(), NoiseSource::Given));
        let maps = solver.fit_cube(&cube).unwrap();
        for i in 0..maps.width * maps.height {
            let (d, dh) = (truth.thickness_nm[i], maps.thickness_nm[i]);
            assert!(
                maps.valid[i] > 0.5 && (dh - d).abs() <= 0.5,
                "{mode:?}: {d} nm at {}° read {dh} nm at {}° (reason {})",
                truth.theta_deg[i],
                maps.theta_deg[i],
                maps.reason[i]
            );
        }
    }
}
