//! The live pipeline's solve stage alone: a scene as `irid run` sees it —
//! the synthetic camera's sensor noise (read and shot noise through the
//! LCTF's transmission, the noise model its calibration measures) on the
//! noise-free rendering, tiled to a camera frame — fitted with that noise
//! model on N threads, best of K. Not a test: it asserts nothing.
//!
//! `cargo bench --bench live_solve` (options after `--`: `--scene FILE`,
//! default `data/scenes/thin-line.toml`; `--pixels N`, default 1 310 720 =
//! 1280 × 1024; `--mode M`, default every mode; `--threads N`, default 1;
//! `--best-of K`, default 3).
//!
//! Prints pixels/s per mode, the valid fraction, the mean |Δd| against
//! the Cramér–Rao-efficient one under this noise (each band weighed by its
//! own variance at the pixel's reflectance; "ratio" is irid's over it),
//! the fraction within 2σ, the valid pixels farther than max(3σ, 2 nm)
//! from the truth, and the time one camera frame's sweep takes at
//! that speed.

mod common;

use irid::device::camera::synthetic::{lctf_transmission, SensorModel};
use irid::estimate::model::ModelOut;
use irid::estimate::noise::{NoiseModel, NoiseSource};
use irid::estimate::{Mode, Solver};
use irid::scene::Scene;
use irid::synth::{compare, scene_bands};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use std::path::Path;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let scene_path = common::arg::<String>(&args, "--scene")
        .map_or_else(|| root.join("data/scenes/thin-line.toml"), Into::into);
    let pixels: usize = common::arg(&args, "--pixels").unwrap_or(1280 * 1024);
    let threads: usize = common::arg(&args, "--threads").unwrap_or(1);
    let best_of: usize = common::arg(&args, "--best-of").unwrap_or(3);
    let only_mode: Option<String> = common::arg(&args, "--mode");
    let scene = Scene::load(&scene_path).expect("scene");
    let bands = scene_bands(&scene).expect("the scene's bands");
    let repeat = common::repeat_for(&scene, pixels);
    let (mut cube, truth, _, seed) = common::render_tiled_clean(&scene, &bands, repeat);
    // The camera's noise in reflectance: counts = g·R + dark + read and
    // shot noise, g the band's gain (exposure × LCTF transmission), so
    // var(R) = read²/g² + R·(counts per electron)/g.
    let s = SensorModel::default();
    let gain: Vec<f64> = bands
        .iter()
        .map(|b| s.counts_per_us * f64::from(s.exposure_us) * lctf_transmission(b.center_nm))
        .collect();
    let var0: Vec<f64> = gain
        .iter()
        .map(|g| s.read_noise.powi(2) / (g * g))
        .collect();
    let shot: Vec<f64> = gain.iter().map(|g| s.counts_per_electron / g).collect();
    let plane = cube.width * cube.height;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    for (k, p) in cube.data.chunks_mut(plane).enumerate() {
        for v in p {
            let r = f64::from(*v);
            let sd = (var0[k] + shot[k] * r.max(0.0)).sqrt();
            let z: f64 = StandardNormal.sample(&mut rng);
            *v = (r + sd * z) as f32;
        }
    }
    let (efficient, unweighted) = efficient_mae(&scene, &bands, &truth, &var0, &shot);
    let noise = NoiseModel {
        var0,
        shot,
        rel2: 0.0,
        source: NoiseSource::Camera,
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool");
    println!("machine: {}", common::machine());
    println!(
        "{}: {} × {} pixels, {} bands, camera noise, {threads} thread(s), best of {best_of}",
        scene_path.display(),
        cube.width,
        cube.height,
        bands.len()
    );
    println!(
        "efficient mean |Δd| {efficient:.3} nm; least squares weighing every band alike: {unweighted:.3} nm ({:.2}×)",
        unweighted / efficient
    );
    println!();
    println!("| mode | pixels/s | valid | mean \\|Δd\\| | efficient | ratio | \\|Δd\\| ≤ 2σ | valid and wrong | 1280 × 1024 takes |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
        if only_mode.as_deref().is_some_and(|m| m != mode.name()) {
            continue;
        }
        let mut solver = Solver::new(&scene, &bands, mode).expect("the scene's solver");
        solver.set_noise(noise.clone());
        // As the live runner does on its first sweep.
        let est = solver
            .estimate_film_index(&cube)
            .expect("the film index is estimated");
        solver
            .set_film_index(est)
            .expect("the film index is usable");
        let (maps, t) = pool.install(|| common::time_fits(&mut solver, &cube, best_of));
        let acc = compare(&maps, &truth);
        let px = plane as f64 / t;
        println!(
            "| `{}` | {:.2} M | {:.1} % | {:.3} nm | {efficient:.3} nm | {:.2} | {:.1} % | {:.2} % | {:.0} ms |",
            mode.name(),
            px / 1e6,
            100.0 * acc.valid_fraction,
            acc.thickness_mae_nm,
            acc.thickness_mae_nm / efficient,
            100.0 * acc.coverage_2sigma,
            100.0 * acc.valid_wrong_fraction,
            1280.0 * 1024.0 / px * 1e3,
        );
    }
}

/// The mean |Δd| of an efficient estimator (0.798 σ_CRB, the angle and
/// index known) under per-band noise `var0 + shot·R`, over every 16th
/// pixel of the truth: `σ_CRB² = 1 / Σ_k (∂R_k/∂d)² / σ_k²(R_k)`; and
/// that of least squares weighing every band alike,
/// `σ² = Σ_k J_k² σ_k² / (Σ_k J_k²)²` (`J = ∂R/∂d`).
fn efficient_mae(
    scene: &Scene,
    bands: &[irid::optics::band::Band],
    truth: &irid::synth::TruthMaps,
    var0: &[f64],
    shot: &[f64],
) -> (f64, f64) {
    let model = common::truth_model(scene, bands, truth);
    let mut out = ModelOut::new(bands.len());
    let (mut sum, mut sum_ls, mut n) = (0.0, 0.0, 0.0);
    for i in (0..truth.thickness_nm.len()).step_by(16) {
        let d = f64::from(truth.thickness_nm[i]);
        let th = f64::from(truth.theta_deg[i]).to_radians();
        model.eval(d, th, &mut out, true);
        let var = |k: usize| var0[k] + shot[k] * out.r[k].max(0.0);
        let j2 = |k: usize| out.dr_dd[k].powi(2);
        let info: f64 = (0..bands.len()).map(|k| j2(k) / var(k)).sum();
        let jj: f64 = (0..bands.len()).map(j2).sum();
        let jvj: f64 = (0..bands.len()).map(|k| j2(k) * var(k)).sum();
        sum += info.recip().sqrt();
        sum_ls += jvj.sqrt() / jj;
        n += 1.0;
    }
    let k = common::EFFICIENT_MAE_PER_SIGMA / n;
    (k * sum, k * sum_ls)
}
