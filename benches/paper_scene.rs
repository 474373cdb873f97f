//! Speed and accuracy of every mode on the paper's simulated cylinder
//! (140 × 14 pixels, 31 bands, σ = 0.001), with the angle unknown and known.
//! Prints one line per case and the machine it ran on. Not a test: it
//! asserts nothing.
//!
//! `cargo bench --bench paper_scene` (add `-- --repeat N` to tile the scene
//! N×N times for steadier speed numbers, `--best-of K` to time each fit K
//! times and report the fastest, which a busy machine disturbs least,
//! `--mode M` for one mode only, `--angle known|unknown` for one case, and `--scene FILE` to run another scene
//! TOML with a `[truth]` section instead of the paper's; `--bins` adds the
//! accuracy per 100 nm of true thickness, `--worst` the worst pixel).

mod common;

use irid::estimate::{Mode, Solver};
use irid::scene::{AngleKnowledge, Scene};
use irid::synth::{compare, scene_bands, Renderer};
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let repeat: usize = args
        .iter()
        .position(|a| a == "--repeat")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let best_of: usize = args
        .iter()
        .position(|a| a == "--best-of")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(1)
        .max(1);
    println!("machine: {}", common::machine());
    let scene_arg = args
        .iter()
        .position(|a| a == "--scene")
        .and_then(|i| args.get(i + 1));
    let scene = match scene_arg {
        Some(p) => Scene::load(std::path::Path::new(p)).expect("scene"),
        None => Scene::paper_cylinder(),
    };
    let bands = scene_bands(&scene).unwrap();
    let renderer = Renderer::new(&scene).unwrap();
    let truth = renderer.truth_maps(&bands);
    let (cube, truth_t, _) = common::render_tiled(&scene, &bands, repeat);
    println!(
        "scene: {} {}x{} px, {} bands, sigma {}",
        scene_arg.map_or("paper cylinder", String::as_str),
        cube.width,
        cube.height,
        bands.len(),
        renderer.noise().0
    );
    // The Cramér–Rao bound per pixel at the truth: an independent
    // yardstick for the errors printed below (an efficient estimator's mean
    // |Δd| is ≈ 0.80 σ).
    let (s2, s1) = common::crb(&scene, &bands, &truth, renderer.noise().0);
    println!(
        "Cramér–Rao bound on σ_d, mean over the scene: {s2:.3} nm (angle unknown), {s1:.3} nm (angle known) → efficient mean |Δd| ≈ {:.3} / {:.3} nm",
        0.798 * s2,
        0.798 * s1
    );
    let angle_arg = args
        .iter()
        .position(|a| a == "--angle")
        .and_then(|i| args.get(i + 1))
        .cloned();
    for angle_known in [false, true] {
        if let Some(a) = &angle_arg {
            if a != if angle_known { "known" } else { "unknown" } {
                continue;
            }
        }
        let mut sc = scene.clone();
        if angle_known {
            sc.angle = AngleKnowledge::Map {
                width: truth_t.width,
                height: truth_t.height,
                deg: truth_t.theta_deg.clone(),
            };
        }
        for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
            if let Some(i) = args.iter().position(|a| a == "--mode") {
                if args.get(i + 1).map(String::as_str) != Some(mode.name()) {
                    continue;
                }
            }
            let mut solver = Solver::new(&sc, &bands, mode).unwrap();
            let t0 = Instant::now();
            let idx = solver.estimate_film_index(&cube).unwrap();
            let t_index = t0.elapsed().as_secs_f64();
            let (maps, t_fit) = common::time_fits(&mut solver, &cube, best_of);
            let acc = compare(&maps, &truth_t);
            if args.iter().any(|a| a == "--bins") {
                // Accuracy per 100 nm of true thickness.
                let mut bins: std::collections::BTreeMap<i64, (usize, usize, f64, f64, usize)> =
                    Default::default();
                for i in 0..maps.thickness_nm.len() {
                    let t = f64::from(truth_t.thickness_nm[i]);
                    let b = bins.entry((t / 100.0).floor() as i64).or_default();
                    b.0 += 1;
                    if maps.valid[i] > 0.5 {
                        let e = (f64::from(maps.thickness_nm[i]) - t).abs();
                        b.1 += 1;
                        b.2 += e;
                        b.3 = b.3.max(e);
                        if e <= 2.0 * f64::from(maps.sigma_thickness_nm[i]) {
                            b.4 += 1;
                        }
                    }
                }
                for (k, (n, v, sum, max, cov)) in bins {
                    println!(
                        "  d {:5}-{:5} nm: {:6} px valid {:5.1}% MAE {:7.3} max {:8.2} |e|<=2σ {:5.1}%",
                        k * 100,
                        k * 100 + 100,
                        n,
                        100.0 * v as f64 / n as f64,
                        sum / v.max(1) as f64,
                        max,
                        100.0 * cov as f64 / v.max(1) as f64
                    );
                }
            }
            if args.iter().any(|a| a == "--worst") {
                let mut worst = (0.0f32, 0usize);
                for i in 0..maps.thickness_nm.len() {
                    let e = (maps.thickness_nm[i] - truth_t.thickness_nm[i]).abs();
                    if e > worst.0 {
                        worst = (e, i);
                    }
                }
                let i = worst.1;
                println!(
                    "worst pixel ({}, {}): truth d {} θ {} | est d {} θ {} σd {} rms {}",
                    i % maps.width,
                    i / maps.width,
                    truth_t.thickness_nm[i],
                    truth_t.theta_deg[i],
                    maps.thickness_nm[i],
                    maps.theta_deg[i],
                    maps.sigma_thickness_nm[i],
                    maps.residual_rms[i]
                );
            }
            println!(
                "{:9} angle {:7} n2 {:.5}±{:.5} (err {:+.5}) index {:.2}s | {:>9.0} px/s | valid {:5.1}% MAE {:.3} nm p99 {:.3} max {:.2} | theta MAE(>=20) {:.3} max(<20,unflagged) {:.2} | |e|<=2σ {:.1}%  {}",
                mode.name(),
                if angle_known { "known" } else { "unknown" },
                idx.n,
                idx.sigma,
                idx.n - truth.n_film,
                t_index,
                (cube.width * cube.height) as f64 / t_fit,
                100.0 * acc.valid_fraction,
                acc.thickness_mae_nm,
                acc.thickness_p99_nm,
                acc.thickness_max_nm,
                acc.theta_mae_ge20_deg,
                acc.theta_max_lt20_unflagged_deg,
                100.0 * acc.coverage_2sigma,
                idx.note
            );
        }
    }
}
