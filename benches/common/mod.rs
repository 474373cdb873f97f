//! Pieces the benchmarks share: the machine's name, a scene tiled to a
//! larger image, and the Cramér–Rao bound of a scene's truth.

#![allow(dead_code)]

use irid::estimate::model::{FilmModel, ModelOut};
use irid::estimate::{Cube, ParamMaps, Solver};
use irid::optics::band::Band;
use irid::optics::dispersion::Dispersion;
use irid::scene::{FilmKnowledge, Scene};
use irid::synth::{add_noise, Renderer, TruthMaps};

/// The CPU model and the number of threads the solver runs on.
pub fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    format!("{cpu}, {} threads", rayon::current_num_threads())
}

/// The scene rendered and tiled `repeat × repeat` times, with noise drawn
/// afresh for every pixel of the tiled image (tiles that repeated the same
/// noise would let image-wide estimates — the noise level, the level fit —
/// count one pixel's noise several times).
pub fn render_tiled(scene: &Scene, bands: &[Band], repeat: usize) -> (Cube, TruthMaps, f64) {
    let mut quiet = scene.clone();
    let (sigma, seed) = match quiet.truth.as_mut() {
        Some(t) => {
            let s = (t.noise_sigma, t.seed);
            t.noise_sigma = 0.0;
            s
        }
        None => (0.0, 0),
    };
    let r = Renderer::new(&quiet).expect("the scene renders");
    let truth = r.truth_maps(bands);
    let cube = r.render_cube(bands).expect("the scene renders");
    let (mut cube, truth) = tile(&cube, &truth, repeat);
    if sigma > 0.0 {
        add_noise(&mut cube.data, sigma, seed);
    }
    (cube, truth, sigma)
}

/// The cube and its truth tiled `repeat × repeat` times.
fn tile(cube: &Cube, truth: &TruthMaps, repeat: usize) -> (Cube, TruthMaps) {
    if repeat <= 1 {
        return (cube.clone(), truth.clone());
    }
    let bands = cube.bands.clone();
    let (w, h) = (cube.width * repeat, cube.height * repeat);
    let mut big = Cube::zeros(w, h, bands.clone());
    for b in 0..bands.len() {
        for y in 0..h {
            for x in 0..w {
                let v = cube.plane(b)[(y % cube.height) * cube.width + x % cube.width];
                big.plane_mut(b)[y * w + x] = v;
            }
        }
    }
    let src = |i: usize| (i / w % truth.height) * truth.width + i % w % truth.width;
    let mut t = truth.clone();
    t.thickness_nm = (0..w * h).map(|i| truth.thickness_nm[src(i)]).collect();
    t.theta_deg = (0..w * h).map(|i| truth.theta_deg[src(i)]).collect();
    t.width = w;
    t.height = h;
    (big, t)
}

/// The Cramér–Rao bound on σ_d per pixel at the truth, `σ_R² (JᵀJ)⁻¹` with
/// the exact model's Jacobian, averaged over the scene: `(angle unknown,
/// angle known)`. The film is the scene's known material, or the truth's
/// index where the scene leaves it unknown (its own uncertainty, shared by
/// every pixel, is left out).
pub fn crb(scene: &Scene, bands: &[Band], truth: &TruthMaps, sigma_r: f64) -> (f64, f64) {
    let film = match &scene.film {
        FilmKnowledge::Known(d) => d.clone(),
        FilmKnowledge::Unknown { .. } => Dispersion::constant(truth.n_film),
    };
    let model = FilmModel::new(
        bands,
        &scene.ambient,
        &film,
        &scene.substrate,
        scene.polarization,
        &vec![false; bands.len()],
    )
    .expect("the scene's model");
    let mut out = ModelOut::new(bands.len());
    let (mut s2, mut s1, mut n) = (0.0, 0.0, 0.0);
    for i in 0..truth.thickness_nm.len() {
        let d = f64::from(truth.thickness_nm[i]);
        let th = f64::from(truth.theta_deg[i]).to_radians();
        model.eval(d, th, &mut out, true);
        let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
        for k in 0..bands.len() {
            a += out.dr_dd[k] * out.dr_dd[k];
            b += out.dr_dd[k] * out.dr_dth[k];
            c += out.dr_dth[k] * out.dr_dth[k];
        }
        let unknown = sigma_r * (c / (a * c - b * b)).sqrt();
        // A flat angle direction (θ ≈ 0) leaves d unbounded: cap at the
        // scene's span so one pixel does not swamp the mean.
        s2 += if unknown.is_finite() {
            unknown.min(1e4)
        } else {
            1e4
        };
        s1 += sigma_r / a.sqrt();
        n += 1.0;
    }
    (s2 / n, s1 / n)
}

/// Fit `cube` `best_of` times (at least once); the last maps and the
/// fastest time, seconds.
pub fn time_fits(solver: &mut Solver, cube: &Cube, best_of: usize) -> (ParamMaps, f64) {
    let mut t_fit = f64::INFINITY;
    let mut maps = None;
    for _ in 0..best_of.max(1) {
        let t = std::time::Instant::now();
        let m = solver.fit_cube(cube).expect("the cube fits");
        t_fit = t_fit.min(t.elapsed().as_secs_f64());
        maps = Some(m);
    }
    (maps.expect("at least one fit"), t_fit)
}
