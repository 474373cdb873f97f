//! Accuracy against noise: every mode on the paper's cylinder (the angle
//! and the film index unknown, as in the paper) and on the thin coating
//! (the angle known, the production case), with the reflectance noise σ on
//! a log grid, each point against the Cramér–Rao bound at its σ. Prints the
//! machine and a Markdown table (`irid::render::noise`'s layout, which
//! `irid render --noise` reads back).
//!
//! `cargo bench --bench noise_sweep` (options after `--`: `--pixels N`
//! tiles each scene to at least N pixels, default 30 000; `--sigmas
//! A,B,…` the noise levels, default 0.0003,0.001,0.003,0.01,0.03;
//! `--scene NAME` and `--mode M` select rows).
//!
//! Each scene is rendered once without noise and tiled; every σ adds noise
//! from the same seed, so the levels differ by the scale of one noise
//! pattern and the curves are not jagged by draws. The film index, the
//! noise and the level are estimated afresh at every σ. Self-check: the
//! bound, computed anew at every σ, must scale as σ (within 1e-6).

mod common;

use irid::estimate::Mode;
use irid::render::noise::{NoiseRow, HEADER};
use irid::scene::Scene;
use irid::synth::{add_noise, compare, scene_bands};
use std::path::Path;

/// The cases swept: scene file under `data/scenes`, and whether the angle
/// is known (a per-pixel map of the truth).
const CASES: [(&str, bool); 2] = [("paper-cylinder", false), ("thin-coating", true)];

/// The default noise levels, reflectance per band.
const SIGMAS: [f64; 5] = [0.0003, 0.001, 0.003, 0.01, 0.03];

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let min_pixels: usize = common::arg(&args, "--pixels").unwrap_or(30_000);
    let sigmas: Vec<f64> = common::arg::<String>(&args, "--sigmas")
        .map(|s| s.split(',').filter_map(|v| v.trim().parse().ok()).collect())
        .unwrap_or_else(|| SIGMAS.to_vec());
    assert!(
        !sigmas.is_empty() && sigmas.iter().all(|s| *s > 0.0 && s.is_finite()),
        "--sigmas: positive numbers, comma-separated"
    );
    let only_scene: Option<String> = common::arg(&args, "--scene");
    let only_mode: Option<String> = common::arg(&args, "--mode");
    let modes: Vec<Mode> = [Mode::Fast, Mode::Balanced, Mode::Accurate]
        .into_iter()
        .filter(|m| only_mode.as_deref().is_none_or(|o| o == m.name()))
        .collect();
    let cases: Vec<(&str, bool)> = CASES
        .into_iter()
        .filter(|(n, _)| only_scene.as_deref().is_none_or(|s| s == *n))
        .collect();
    println!("machine: {}", common::machine());
    println!();
    println!("{HEADER}");
    let bar = common::bar(
        (cases.len() * sigmas.len() * modes.len()) as u64,
        "noise sweep",
    );
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes");
    for (name, angle_known) in cases {
        let label = common::SCENES
            .iter()
            .find(|(n, _)| *n == name)
            .map_or(name, |(_, l)| l);
        let scene = Scene::load(&dir.join(format!("{name}.toml"))).expect("scene");
        let bands = scene_bands(&scene).expect("the scene's bands");
        let repeat = common::repeat_for(&scene, min_pixels);
        let (clean, truth, _, seed) = common::render_tiled_clean(&scene, &bands, repeat);
        let sc = if angle_known {
            common::with_known_angle(&scene, &truth)
        } else {
            scene.clone()
        };
        let efficient_at = |sigma: f64| {
            let (unknown, known) = common::crb(&scene, &bands, &truth, sigma);
            common::EFFICIENT_MAE_PER_SIGMA * if angle_known { known } else { unknown }
        };
        let first = efficient_at(sigmas[0]);
        for &sigma in &sigmas {
            let efficient = efficient_at(sigma);
            let scale = (efficient / first) / (sigma / sigmas[0]);
            assert!(
                (scale - 1.0).abs() < 1e-6,
                "{name}: the Cramér–Rao bound does not scale as σ ({efficient} nm at σ {sigma}, {first} nm at σ {})",
                sigmas[0]
            );
            let mut cube = clean.clone();
            add_noise(&mut cube.data, sigma, seed);
            for &mode in &modes {
                let (_, maps, _, _) = common::run_mode(&sc, &bands, &cube, mode, 1);
                let acc = compare(&maps, &truth);
                // Nothing valid: no error to report (compare's 0 would
                // read as a perfect fit).
                let measured = |v: f64| {
                    if acc.valid_fraction > 0.0 {
                        v
                    } else {
                        f64::NAN
                    }
                };
                let row = NoiseRow {
                    scene: label.to_string(),
                    angle_known,
                    mode: mode.name().to_string(),
                    sigma_r: sigma,
                    valid_fraction: acc.valid_fraction,
                    mean_err_nm: measured(acc.thickness_mae_nm),
                    p99_err_nm: measured(acc.thickness_p99_nm),
                    efficient_nm: efficient,
                    coverage_2sigma: measured(acc.coverage_2sigma),
                    valid_wrong: measured(acc.valid_wrong_fraction),
                };
                bar.inc(1);
                bar.suspend(|| println!("{}", row.markdown()));
            }
        }
    }
    bar.finish_and_clear();
}
