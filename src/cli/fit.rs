//! `irid fit`: an ENVI cube in, one OpenEXR file of parameter maps out.
//!
//! The scene is the `--scene` file (or one that knows only an ambient of
//! n = 1), edited by the command-line overrides before it is resolved, so a
//! value given on the command line is known and never estimated. The fit
//! alone is timed, here: the estimation core never reads the clock.

use super::common::{SceneOverrides, SceneSource};
use crate::estimate::{Cube, Mode, ParamMaps, Reason, Solver};
use crate::io::{envi, exr_maps};
use crate::pipeline::calibration;
use crate::scene::{AngleKnowledge, Scene};
use anyhow::{bail, Context};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

/// Arguments of `irid fit`.
#[derive(Debug, clap::Args)]
pub struct FitArgs {
    /// The ENVI cube (its `.hdr`, or the data file beside one).
    #[arg(value_name = "CUBE.hdr")]
    pub cube: PathBuf,
    /// Output OpenEXR file of parameter maps.
    #[arg(long, value_name = "MAPS.exr")]
    pub out: PathBuf,
    /// Scene TOML (media, what is known, search ranges).
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Dark reference cube: the input is raw counts.
    #[arg(long, value_name = "DARK.hdr", requires = "white")]
    pub dark: Option<PathBuf>,
    /// White reference cube: the input is raw counts.
    #[arg(long, value_name = "WHITE.hdr", requires = "dark")]
    pub white: Option<PathBuf>,
    /// Reflectance of the white reference.
    #[arg(long, value_name = "R", default_value_t = 1.0, requires = "white")]
    pub white_reflectance: f32,
    /// The sensor's full scale, counts, with --dark/--white: samples at or
    /// above it are saturated, and a pixel needs white − dark ≥ 1 % of it
    /// (default: 255 for u8 cubes, 65535 for u16, none for other types).
    #[arg(long, value_name = "COUNTS", requires = "white")]
    pub full_scale: Option<f32>,
    /// Scene overrides.
    #[command(flatten)]
    pub overrides: SceneOverrides,
    /// Speed/accuracy trade-off.
    #[arg(long, value_enum, default_value_t = Mode::Balanced)]
    pub mode: Mode,
    /// Worker threads (default: all cores).
    #[arg(long, value_name = "N")]
    pub threads: Option<usize>,
    /// Print a one-line JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
}

/// The `--json` summary line.
#[derive(Debug, Serialize)]
pub struct Summary {
    /// Pixels in the cube.
    pub pixels: usize,
    /// Pixels with a valid estimate.
    pub valid_pixels: usize,
    /// Film index used (estimated or known).
    pub n_film: f64,
    /// Its standard error (0 when known).
    pub n_film_sigma: f64,
    /// Whether the index was estimated.
    pub n_film_estimated: bool,
    /// Seconds spent fitting (reading and writing excluded): the global
    /// index search plus the per-pixel solve.
    pub elapsed_s: f64,
    /// Pixels per second of the whole fit (`pixels / elapsed_s`).
    pub pixels_per_s: f64,
    /// Seconds of the global film-index (and noise) estimate.
    pub index_s: f64,
    /// Seconds of the per-pixel solve.
    pub solve_s: f64,
    /// Pixels per second of the per-pixel solve alone.
    pub solve_pixels_per_s: f64,
    /// Solver mode.
    pub mode: &'static str,
}

/// Build the scene of a fit from `--scene` and the overrides.
pub fn build_scene(a: &FitArgs) -> anyhow::Result<Scene> {
    let mut src = match &a.scene {
        Some(p) => SceneSource::load(p)?,
        None => SceneSource::empty(),
    };
    // The fit needs no synthetic truth, and a truth that an override makes
    // inconsistent must not stop it.
    src.file.truth = None;
    a.overrides.apply(&mut src.file)?;
    if !src.file.substrate.is_given() {
        bail!("the substrate is unknown: give --n3 N (or --material3 NAME, or a --scene with [substrate])");
    }
    src.resolve()
}

fn read_input(a: &FitArgs) -> anyhow::Result<Cube> {
    Ok(match (&a.dark, &a.white) {
        (Some(d), Some(w)) => {
            anyhow::ensure!(
                a.white_reflectance.is_finite() && a.white_reflectance > 0.0,
                "--white-reflectance must be positive"
            );
            if let Some(f) = a.full_scale {
                anyhow::ensure!(f > 0.0, "--full-scale must be positive");
            }
            calibration::read_calibrated(&a.cube, d, w, a.white_reflectance, a.full_scale)?
        }
        _ => envi::read_cube(&a.cube)?,
    })
}

/// Run `irid fit`.
pub fn run(a: &FitArgs) -> anyhow::Result<()> {
    let scene = build_scene(a)?;
    let cube = read_input(a)?;
    if let AngleKnowledge::Map { width, height, .. } = &scene.angle {
        if (*width, *height) != (cube.width, cube.height) {
            bail!(
                "the angle map is {width} × {height} pixels but the cube {} is {} × {}",
                a.cube.display(),
                cube.width,
                cube.height
            );
        }
    }
    let mut solver = Solver::new(&scene, &cube.bands, a.mode).context("setting up the solver")?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(a.threads.unwrap_or(0))
        .build()
        .context("building the thread pool")?;
    let start = Instant::now();
    pool.install(|| solver.estimate_film_index(&cube))
        .context("estimating the film index")?;
    let index_s = start.elapsed().as_secs_f64();
    let result = pool.install(|| solver.fit_cube(&cube));
    let elapsed = start.elapsed().as_secs_f64();
    let solve_s = elapsed - index_s;
    let maps = result.context("fitting")?;
    exr_maps::write_maps(&a.out, &maps)?;
    let pixels = cube.width * cube.height;
    let summary = Summary {
        pixels,
        valid_pixels: maps.valid_count(),
        n_film: maps.meta.n_film,
        n_film_sigma: maps.meta.n_film_sigma,
        n_film_estimated: maps.meta.n_film_estimated,
        elapsed_s: elapsed,
        pixels_per_s: pixels as f64 / elapsed.max(1e-9),
        index_s,
        solve_s,
        solve_pixels_per_s: pixels as f64 / solve_s.max(1e-9),
        mode: a.mode.name(),
    };
    if a.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        eprintln!("{}", human_summary(&summary, &maps, &a.out));
    }
    Ok(())
}

fn human_summary(s: &Summary, maps: &ParamMaps, out: &std::path::Path) -> String {
    let mut counts = [0usize; Reason::ALL.len()];
    for r in &maps.reason {
        if let Some(r) = Reason::from_code(*r as u8) {
            counts[r as usize] += 1;
        }
    }
    let reasons: Vec<String> = Reason::ALL
        .iter()
        .filter(|r| **r != Reason::Ok && counts[**r as usize] > 0)
        .map(|r| format!("{} {}", counts[*r as usize], r.name()))
        .collect();
    let pct = 100.0 * s.valid_pixels as f64 / s.pixels.max(1) as f64;
    let mut text = format!(
        "irid fit: {} pixels, {} valid ({pct:.1}%); film index {:.5} ± {:.5} ({}); {:.3} s, {:.0} pixels/s ({}) → {}",
        s.pixels,
        s.valid_pixels,
        s.n_film,
        s.n_film_sigma,
        if s.n_film_estimated { "estimated" } else { "known" },
        s.elapsed_s,
        s.pixels_per_s,
        s.mode,
        out.display()
    );
    if !reasons.is_empty() {
        text.push_str(&format!("\n  flags: {}", reasons.join(", ")));
    }
    if !maps.meta.n_film_note.is_empty() {
        text.push_str(&format!("\n  film index: {}", maps.meta.n_film_note));
    }
    text
}
