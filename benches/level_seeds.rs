//! How far one image's calibration error is corrected, over many images:
//! the paper's cylinder (the film index and every pixel's angle unknown,
//! σ_R = 0.001) with a calibration error applied to the rendered
//! reflectance, fitted with the default level (`auto`, `balanced`), once
//! per noise seed. A level is shared by every pixel of an image, so one
//! image's coverage says little: what σ must cover is how the level's
//! estimate scatters between images, which only many seeds show.
//!
//! `cargo bench --bench level_seeds` (options after `--`: `--seeds N`
//! images per case, default 32; `--first S` the first seed, default 101,
//! past the trust suite's 1–4; `--case NAME` one case; `--index-known`
//! gives the solver the film index, 1.37, instead of searching it;
//! `--angle-known` gives it every pixel's true angle as a map).
//!
//! Prints, per case: how often each level was chosen; the mean |Δd| over
//! valid pixels (averaged over images); the 2σ coverage pooled over images
//! and the number of images whose own coverage is below 0.88; the valid
//! pixels farther than max(3σ, 2 nm) from the truth (mean and worst
//! image); and, where one gain was fitted, the RMS and mean of its error over
//! images against the mean σ it reported. Not a test: it asserts nothing.

mod common;

use irid::estimate::level::LevelMode;
use irid::estimate::{Cube, Mode, Solver};
use irid::scene::{AngleKnowledge, FilmKnowledge, Scene};
use irid::synth::{compare, scene_bands, Renderer};

/// A calibration error: `y_k = gain(k)·R_k + offset`.
struct Case {
    name: &'static str,
    gain: fn(usize) -> f64,
    offset: f64,
    /// The gain the level should find (for one gain's error), if any.
    true_gain: Option<f64>,
}

/// The trust suite's per-band gain errors of ±6 %.
fn per_band(k: usize) -> f64 {
    1.0 + 0.06 * (((k * 37 + 11) % 13) as f64 / 6.0 - 1.0)
}

const CASES: [Case; 6] = [
    Case {
        name: "clean",
        gain: |_| 1.0,
        offset: 0.0,
        true_gain: None,
    },
    Case {
        name: "white reference 5 % high",
        gain: |_| 1.0 / 1.05,
        offset: 0.0,
        true_gain: Some(1.0 / 1.05),
    },
    Case {
        name: "white reference 8 % low",
        gain: |_| 1.0 / 0.92,
        offset: 0.0,
        true_gain: Some(1.0 / 0.92),
    },
    Case {
        name: "white reference 3 % low",
        gain: |_| 1.03,
        offset: 0.0,
        true_gain: Some(1.03),
    },
    Case {
        name: "stray light +0.004",
        gain: |_| 1.0,
        offset: 0.004,
        true_gain: None,
    },
    Case {
        name: "per-band gain ±6 %",
        gain: per_band,
        offset: 0.0,
        true_gain: None,
    },
];

/// One image's outcome.
struct Image {
    scaled: bool,
    mae: f64,
    covered: usize,
    valid: usize,
    wrong: f64,
    gain: Option<(f64, f64)>,
}

fn fit_one(case: &Case, seed: u64, index_known: bool, angle_known: bool) -> Image {
    let mut scene = Scene::paper_cylinder();
    scene.truth.as_mut().expect("the paper's truth").seed = seed;
    if index_known {
        let film = scene
            .truth
            .as_ref()
            .expect("the paper's truth")
            .film
            .clone();
        scene.film = FilmKnowledge::Known(film);
    }
    let bands = scene_bands(&scene).expect("the scene's bands");
    let r = Renderer::new(&scene).expect("the scene renders");
    let mut cube: Cube = r.render_cube(&bands).expect("the cube renders");
    let truth = r.truth_maps(&bands);
    if angle_known {
        scene.angle = AngleKnowledge::Map {
            width: truth.width,
            height: truth.height,
            deg: truth.theta_deg.clone(),
        };
    }
    let n = cube.plane_len();
    for k in 0..cube.bands.len() {
        let g = (case.gain)(k);
        for v in &mut cube.data[k * n..(k + 1) * n] {
            *v = (f64::from(*v) * g + case.offset) as f32;
        }
    }
    let mut solver = Solver::new(&scene, &cube.bands, Mode::Balanced).expect("the solver");
    let maps = solver.fit_cube(&cube).expect("the cube fits");
    let acc = compare(&maps, &truth);
    let (mut covered, mut valid, mut wrong) = (0, 0, 0);
    for i in (0..n).filter(|&i| maps.valid[i] > 0.5) {
        let e = (maps.thickness_nm[i] - truth.thickness_nm[i]).abs() as f64;
        let s = maps.sigma_thickness_nm[i] as f64;
        covered += usize::from(e <= 2.0 * s);
        wrong += usize::from(e > (3.0 * s).max(2.0));
        valid += 1;
    }
    let (level, mode, note) = solver.level();
    let one_gain = note.contains("one gain,") && !note.contains("one gain, one offset");
    Image {
        scaled: mode == LevelMode::Scaled,
        mae: acc.thickness_mae_nm,
        covered,
        valid,
        wrong: wrong as f64 / n as f64,
        gain: one_gain.then(|| (level.gain[0], level.var_gain[0].sqrt())),
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = common::arg(&args, "--seeds").unwrap_or(32);
    let first: u64 = common::arg(&args, "--first").unwrap_or(101);
    let only: Option<String> = common::arg(&args, "--case");
    let index_known = args.iter().any(|a| a == "--index-known");
    let angle_known = args.iter().any(|a| a == "--angle-known");
    println!("{}", common::machine());
    println!();
    println!("| calibration error | images | level `scaled` | mean \\|Δd\\| | \\|Δd\\| ≤ 2σ, pooled | images below 0.88 | valid and wrong: mean / worst image | one gain: RMS error / mean error / mean σ |");
    println!("|---|---|---|---|---|---|---|---|");
    for case in CASES
        .iter()
        .filter(|c| only.as_deref().is_none_or(|o| c.name == o))
    {
        let images: Vec<Image> = (first..first + seeds)
            .map(|s| fit_one(case, s, index_known, angle_known))
            .collect();
        let m = images.len() as f64;
        let scaled = images.iter().filter(|i| i.scaled).count();
        let mae = images.iter().map(|i| i.mae).sum::<f64>() / m;
        let covered: usize = images.iter().map(|i| i.covered).sum();
        let valid: usize = images.iter().map(|i| i.valid).sum();
        let low = images
            .iter()
            .filter(|i| (i.covered as f64) < 0.88 * i.valid as f64)
            .count();
        let wrong_mean = images.iter().map(|i| i.wrong).sum::<f64>() / m;
        let wrong_max = images.iter().map(|i| i.wrong).fold(0.0, f64::max);
        let gains: Vec<(f64, f64)> = images.iter().filter_map(|i| i.gain).collect();
        let gain = match (case.true_gain, gains.is_empty()) {
            (Some(g0), false) => {
                let k = gains.len() as f64;
                let rms = (gains.iter().map(|(g, _)| (g - g0).powi(2)).sum::<f64>() / k).sqrt();
                let mean = gains.iter().map(|(g, _)| g - g0).sum::<f64>() / k;
                let sd = gains.iter().map(|(_, s)| s).sum::<f64>() / k;
                format!("{rms:.4} / {mean:+.4} / {sd:.4} ({} images)", gains.len())
            }
            _ => "—".into(),
        };
        println!(
            "| {} | {} | {} | {:.2} nm | {:.1} % | {} | {:.2} % / {:.1} % | {} |",
            case.name,
            images.len(),
            scaled,
            mae,
            100.0 * covered as f64 / valid.max(1) as f64,
            low,
            100.0 * wrong_mean,
            100.0 * wrong_max,
            gain
        );
    }
}
