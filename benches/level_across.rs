//! Is the level one across the image? Two surveys of the test that says
//! (`solver/level_across.rs`), with the calibration error applied to the
//! rendered reflectance and the default level (`auto`, `balanced`):
//!
//! - `--partial` (default): the paper's cylinder with an error on part of
//!   the view only (a half, a stripe of columns or rows, a gain rising
//!   across it, a blend toward grey), seeds 1 and 2. Every such image
//!   should be flagged where its error moves the thicknesses.
//! - `--shared`: the five benchmark scenes, six seeds each, clean and
//!   under four errors the whole image shares (white reference 8 % low
//!   and 5 % high, stray light +0.004, a per-band gain ±6 %): 150 images,
//!   none of which the test should flag.
//!
//! `cargo bench --bench level_across -- --shared` (`--seeds 1,2,3` to
//! choose the seeds). Prints one row per image: valid fraction, mean
//! |Δd|, 2σ coverage, valid pixels beyond max(3σ, 2 nm), and the test's
//! verdict from the level's note (the parts nearest or past their limit).
//! Not a test: it asserts nothing.

mod common;

use irid::estimate::{Cube, Mode, Solver};
use irid::scene::Scene;
use irid::synth::{compare, scene_bands, Renderer};

/// A calibration error: the measured value at column x, row y, band k
/// from the rendered one.
type Error = Box<dyn Fn(usize, usize, usize, f64) -> f64>;

fn scene(name: &str, seed: u64) -> Scene {
    let path = format!("{}/data/scenes/{name}.toml", env!("CARGO_MANIFEST_DIR"));
    let mut s = Scene::load(std::path::Path::new(&path)).expect("a scene of the repository");
    s.truth.as_mut().expect("a rendered scene").seed = seed;
    s
}

fn apply(cube: &mut Cube, f: &Error) {
    let (w, n) = (cube.width, cube.plane_len());
    for (k, plane) in cube.data.chunks_exact_mut(n).enumerate() {
        for (i, v) in plane.iter_mut().enumerate() {
            *v = f(i % w, i / w, k, f64::from(*v)) as f32;
        }
    }
}

fn run(name: &str, seed: u64, label: &str, f: &Error) {
    let s = scene(name, seed);
    let bands = scene_bands(&s).expect("the scene's bands");
    let r = Renderer::new(&s).expect("a renderer");
    let mut cube = r.render_cube(&bands).expect("a cube");
    let truth = r.truth_maps(&bands);
    apply(&mut cube, f);
    let mut solver = Solver::new(&s, &cube.bands, Mode::Balanced).expect("a solver");
    let maps = solver.fit_cube(&cube).expect("a fit");
    let acc = compare(&maps, &truth);
    let note = solver.level().2;
    let verdict = ["but the level differs across", "the level is one across"]
        .iter()
        .find_map(|t| note.find(t).map(|i| &note[i..]))
        .unwrap_or(note);
    let verdict: String = verdict.chars().take(240).collect();
    let wrong = (acc.valid_wrong_fraction * acc.valid_fraction * acc.pixels as f64).round();
    let (mae, cover) = if acc.valid_fraction > 0.0 {
        (
            format!("{:.2} nm", acc.thickness_mae_nm),
            format!("{:.1} %", 100.0 * acc.coverage_2sigma),
        )
    } else {
        ("—".into(), "—".into())
    };
    println!(
        "| {name} | {seed} | {label} | {:.1} % | {mae} | {cover} | {wrong} | {verdict} |",
        100.0 * acc.valid_fraction
    );
}

fn partial() -> Vec<(&'static str, Error)> {
    let w = 140.0;
    vec![
        ("clean", Box::new(|_, _, _, v| v)),
        (
            "upper half 5 % high",
            Box::new(|_, y, _, v| if y < 7 { v * 1.05 } else { v }),
        ),
        (
            "lower half 5 % high",
            Box::new(|_, y, _, v| if y >= 7 { v * 1.05 } else { v }),
        ),
        (
            "columns 40–59 × 0.94",
            Box::new(|x, _, _, v| if (40..60).contains(&x) { v * 0.94 } else { v }),
        ),
        (
            "columns 0–19 × 1.05",
            Box::new(|x, _, _, v| if x < 20 { v * 1.05 } else { v }),
        ),
        (
            "columns 100–119 + 0.003",
            Box::new(|x, _, _, v| {
                if (100..120).contains(&x) {
                    v + 0.003
                } else {
                    v
                }
            }),
        ),
        (
            "rows 3–4 × 1.05",
            Box::new(|_, y, _, v| if (3..5).contains(&y) { v * 1.05 } else { v }),
        ),
        (
            "gain rising 3 %",
            Box::new(move |x, _, _, v| v * (1.0 + 0.03 * x as f64 / w)),
        ),
        (
            "gain rising 6 %",
            Box::new(move |x, _, _, v| v * (1.0 + 0.06 * x as f64 / w)),
        ),
        (
            "columns 60–79 blended 20 % to 0.1",
            Box::new(|x, _, _, v| {
                if (60..80).contains(&x) {
                    0.8 * v + 0.02
                } else {
                    v
                }
            }),
        ),
    ]
}

fn shared() -> Vec<(&'static str, Error)> {
    vec![
        ("clean", Box::new(|_, _, _, v| v)),
        ("white reference 8 % low", Box::new(|_, _, _, v| v / 0.92)),
        ("white reference 5 % high", Box::new(|_, _, _, v| v / 1.05)),
        ("stray light +0.004", Box::new(|_, _, _, v| v + 0.004)),
        (
            "per-band gain ±6 %",
            Box::new(|_, _, k, v| v * if k % 2 == 0 { 1.06 } else { 0.94 }),
        ),
    ]
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let seeds_arg = args
        .iter()
        .position(|a| a == "--seeds")
        .and_then(|i| args.get(i + 1))
        .map(|s| {
            s.split(',')
                .filter_map(|x| x.parse().ok())
                .collect::<Vec<u64>>()
        });
    println!("machine: {}", common::machine());
    println!("| scene | seed | calibration | valid | mean \\|Δd\\| | ≤ 2σ | valid and wrong | the test |");
    println!("|---|---|---|---|---|---|---|---|");
    if args.iter().any(|a| a == "--shared") {
        let seeds = seeds_arg.unwrap_or_else(|| (1..=6).collect());
        for (name, _) in common::SCENES {
            for &seed in &seeds {
                for (label, f) in &shared() {
                    run(name, seed, label, f);
                }
            }
        }
    } else {
        let seeds = seeds_arg.unwrap_or_else(|| vec![1, 2]);
        for &seed in &seeds {
            for (label, f) in &partial() {
                run("paper-cylinder", seed, label, f);
            }
        }
    }
}
