//! Pieces the benchmarks share: the scene classes, the machine's name, a
//! scene tiled to a larger image (noisy, or clean for noise to be added at
//! several levels), the angle made known, one mode's fit timed, the
//! Cramér–Rao bound of a scene's truth, and a progress bar that stays off
//! pipes.

#![allow(dead_code)]

use irid::estimate::model::{FilmModel, ModelOut};
use irid::estimate::{Cube, Mode, ParamMaps, Solver};
use irid::optics::band::Band;
use irid::optics::dispersion::Dispersion;
use irid::scene::{AngleKnowledge, FilmKnowledge, Scene};
use irid::synth::{add_noise, Renderer, TruthMaps};

/// The scene classes: file under `data/scenes`, and what it stands for.
pub const SCENES: [(&str, &str); 5] = [
    (
        "paper-cylinder",
        "paper: 420–560 nm, n unknown, s, 31 bands",
    ),
    ("thin-coating", "thin 60–400 nm SiO2 on PET, u, 31 bands"),
    ("wide-range", "100–1500 nm, n unknown, s, 31 bands"),
    ("thick-hardcoat", "1–4 µm Si3N4 on silica, u, 61 bands"),
    ("dispersive-p61", "150–350 nm TiO2 on PET, p, 61 bands"),
];

/// Mean |Δd| of an efficient (unbiased, Gaussian) estimator per σ_CRB:
/// E|x| = σ √(2/π).
pub const EFFICIENT_MAE_PER_SIGMA: f64 = 0.798;

/// The value after `name` on the command line, parsed.
pub fn arg<T: std::str::FromStr>(args: &[String], name: &str) -> Option<T> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
}

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

/// How many times to tile the scene's truth image in each direction so
/// the tiled image has at least `min_pixels` pixels.
pub fn repeat_for(scene: &Scene, min_pixels: usize) -> usize {
    let n0 = scene.truth.as_ref().map_or(1, |t| t.width * t.height);
    (min_pixels as f64 / n0 as f64).sqrt().ceil().max(1.0) as usize
}

/// The scene rendered and tiled `repeat × repeat` times, with noise drawn
/// afresh for every pixel of the tiled image (tiles that repeated the same
/// noise would let image-wide estimates — the noise level, the level fit —
/// count one pixel's noise several times).
pub fn render_tiled(scene: &Scene, bands: &[Band], repeat: usize) -> (Cube, TruthMaps, f64) {
    let (mut cube, truth, sigma, seed) = render_tiled_clean(scene, bands, repeat);
    if sigma > 0.0 {
        add_noise(&mut cube.data, sigma, seed);
    }
    (cube, truth, sigma)
}

/// The scene rendered noise-free and tiled `repeat × repeat` times, with
/// the noise σ and seed its truth asks for (to add with
/// [`irid::synth::add_noise`], at that σ or any other).
pub fn render_tiled_clean(
    scene: &Scene,
    bands: &[Band],
    repeat: usize,
) -> (Cube, TruthMaps, f64, u64) {
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
    let (cube, truth) = tile(&cube, &truth, repeat);
    (cube, truth, sigma, seed)
}

/// `scene` with the angle known: the truth's per-pixel angle map.
pub fn with_known_angle(scene: &Scene, truth: &TruthMaps) -> Scene {
    let mut sc = scene.clone();
    sc.angle = AngleKnowledge::Map {
        width: truth.width,
        height: truth.height,
        deg: truth.theta_deg.clone(),
    };
    sc
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

/// The scene's model with the film the truth was rendered with (its
/// index where the scene leaves it unknown), point-sampled bands.
pub fn truth_model(scene: &Scene, bands: &[Band], truth: &TruthMaps) -> FilmModel {
    let film = match &scene.film {
        FilmKnowledge::Known(d) => d.clone(),
        FilmKnowledge::Unknown { .. } => Dispersion::constant(truth.n_film),
    };
    FilmModel::new(
        bands,
        &scene.ambient,
        &film,
        &scene.substrate,
        scene.polarization,
        &vec![false; bands.len()],
    )
    .expect("the scene's model")
}

/// The Cramér–Rao bound on σ_d per pixel at the truth, `σ_R² (JᵀJ)⁻¹` with
/// the exact model's Jacobian, averaged over the scene: `(angle unknown,
/// angle known)`. The film is the scene's known material, or the truth's
/// index where the scene leaves it unknown (its own uncertainty, shared by
/// every pixel, is left out).
pub fn crb(scene: &Scene, bands: &[Band], truth: &TruthMaps, sigma_r: f64) -> (f64, f64) {
    let model = truth_model(scene, bands, truth);
    let mut out = ModelOut::new(bands.len());
    let (mut s2, mut s1, mut n) = (0.0, 0.0, 0.0);
    for i in 0..truth.thickness_nm.len() {
        let d = f64::from(truth.thickness_nm[i]);
        let th = f64::from(truth.theta_deg[i]).to_radians();
        let (unknown, known) = model.thickness_crb(d, th, sigma_r, &mut out);
        // A flat angle direction (θ ≈ 0) leaves d unbounded: cap at the
        // scene's span so one pixel does not swamp the mean.
        s2 += if unknown.is_finite() {
            unknown.min(1e4)
        } else {
            1e4
        };
        s1 += known;
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

/// One mode on `cube`: the solver after its once-per-image stage (film
/// index, noise and level), the maps of the last of `best_of` fits, the
/// once-per-image stage's time and the fastest fit's, seconds.
pub fn run_mode(
    scene: &Scene,
    bands: &[Band],
    cube: &Cube,
    mode: Mode,
    best_of: usize,
) -> (Solver, ParamMaps, f64, f64) {
    let mut solver = Solver::new(scene, bands, mode).expect("the scene's solver");
    let t0 = std::time::Instant::now();
    solver
        .estimate_film_index(cube)
        .expect("the film index is estimated");
    let t_index = t0.elapsed().as_secs_f64();
    let (maps, t_fit) = time_fits(&mut solver, cube, best_of);
    (solver, maps, t_index, t_fit)
}

/// A bar of `len` steps labelled `what` on stderr when it is a terminal,
/// hidden otherwise: the table on stdout stays clean.
pub fn bar(len: u64, what: &str) -> indicatif::ProgressBar {
    if !std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        return indicatif::ProgressBar::hidden();
    }
    let b = indicatif::ProgressBar::new(len);
    b.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{elapsed_precise}] {wide_bar} {pos}/{len}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    b.set_message(what.to_string());
    b
}
