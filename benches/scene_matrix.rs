//! Speed and accuracy of every mode across the scene classes irid serves,
//! each against its own Cramér–Rao bound: thin coatings, the paper's
//! range, thick films at 61 bands, dispersive materials, polarised and
//! unpolarised light, the angle known (a per-pixel map) and unknown, the
//! film index known and unknown. Prints a Markdown table and the machine.
//! Not a test: it asserts nothing.
//!
//! `cargo bench --bench scene_matrix` (options after `--`: `--pixels N`
//! tiles each scene to at least N pixels, default 100 000; `--best-of K`
//! times each fit K times and keeps the fastest; `--scene NAME` and
//! `--mode M` and `--angle known|unknown` select rows; `--threads N` fits
//! on N threads, all by default; `--levels` and `--reasons` print each
//! fit's level and its pixels' reason codes on stderr).
//!
//! Columns: pixels/s of the per-pixel solve on all threads (the film index
//! and the noise and level estimates are timed apart, once per image);
//! valid fraction; mean and 99th-percentile |Δd| over valid pixels; the
//! efficient mean |Δd| (0.798 σ_CRB); their ratio; the fraction of valid
//! pixels within 2σ.

mod common;

use irid::estimate::Mode;
use irid::scene::Scene;
use irid::synth::{compare, scene_bands};
use std::path::Path;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let min_pixels: usize = common::arg(&args, "--pixels").unwrap_or(100_000);
    let best_of: usize = common::arg(&args, "--best-of").unwrap_or(1).max(1);
    let only_scene: Option<String> = common::arg(&args, "--scene");
    let only_mode: Option<String> = common::arg(&args, "--mode");
    let only_angle: Option<String> = common::arg(&args, "--angle");
    // `--threads N`: the fits on a pool of N threads (per-core speed, and
    // steadier timings with a core left idle); all cores by default.
    let threads: usize = common::arg(&args, "--threads").unwrap_or(0);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool");
    println!("machine: {}", common::machine());
    println!();
    println!("| scene | angle | mode | pixels/s | valid | mean \\|Δd\\| | p99 \\|Δd\\| | efficient | ratio | \\|Δd\\| ≤ 2σ | index+noise+level |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes");
    // A bar on stderr when it is a terminal: the table on stdout stays clean.
    let jobs = common::SCENES
        .iter()
        .filter(|(n, _)| only_scene.as_deref().is_none_or(|s| s == *n))
        .count()
        * if only_angle.is_some() { 1 } else { 2 }
        * if only_mode.is_some() { 1 } else { 3 };
    let bar = common::bar(jobs as u64, "trade study");
    for (name, label) in common::SCENES {
        if only_scene.as_deref().is_some_and(|s| s != name) {
            continue;
        }
        let scene = Scene::load(&dir.join(format!("{name}.toml"))).expect("scene");
        let bands = scene_bands(&scene).unwrap();
        let repeat = common::repeat_for(&scene, min_pixels);
        let (cube, truth, sigma_r) = common::render_tiled(&scene, &bands, repeat);
        let (crb_unknown, crb_known) = common::crb(&scene, &bands, &truth, sigma_r);
        for angle_known in [false, true] {
            let angle = if angle_known { "known" } else { "unknown" };
            if only_angle.as_deref().is_some_and(|a| a != angle) {
                continue;
            }
            let sc = if angle_known {
                common::with_known_angle(&scene, &truth)
            } else {
                scene.clone()
            };
            let efficient =
                common::EFFICIENT_MAE_PER_SIGMA * if angle_known { crb_known } else { crb_unknown };
            for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
                if only_mode.as_deref().is_some_and(|m| m != mode.name()) {
                    continue;
                }
                let (solver, maps, t_index, t_fit) =
                    pool.install(|| common::run_mode(&sc, &bands, &cube, mode, best_of));
                let (_, level_mode, level_note) = solver.level();
                if args.iter().any(|a| a == "--levels") {
                    eprintln!(
                        "{name} {angle} {}: level {level_mode:?}: {level_note}",
                        mode.name()
                    );
                }
                bar.inc(1);
                if args.iter().any(|a| a == "--reasons") {
                    let mut counts = std::collections::BTreeMap::new();
                    for r in &maps.reason {
                        *counts.entry(*r as i32).or_insert(0usize) += 1;
                    }
                    eprintln!("{name} {angle} {}: reason codes {counts:?}", mode.name());
                }
                let acc = compare(&maps, &truth);
                let px = (cube.width * cube.height) as f64 / t_fit;
                bar.suspend(|| {
                    println!(
                        "| {label} | {angle} | `{}` | {} | {:.1} % | {:.3} nm | {:.2} nm | {:.3} nm | {:.2} | {:.1} % | {:.2} s |",
                        mode.name(),
                        if px >= 1e6 {
                            format!("{:.2} M", px / 1e6)
                        } else {
                            format!("{:.0} k", px / 1e3)
                        },
                        100.0 * acc.valid_fraction,
                        acc.thickness_mae_nm,
                        acc.thickness_p99_nm,
                        efficient,
                        acc.thickness_mae_nm / efficient,
                        100.0 * acc.coverage_2sigma,
                        t_index,
                    );
                });
            }
        }
    }
    bar.finish_and_clear();
}
