//! `irid fit`: an ENVI cube or a spectrum table in, parameter maps out —
//! one OpenEXR file, or a CSV with one row per pixel or spectrum.
//!
//! The input is ENVI when its name ends in `.hdr`, when it starts with
//! `ENVI`, or when it is a data file with an ENVI header beside it and not
//! a `.csv`, `.tsv` or `.txt`; anything else is read as a spectrum table
//! ([`crate::io::spectrum_table`]), which `--wavelength-range` and `--bands`
//! can cut and resample before the fit.
//!
//! The scene is the `--scene` file (or one that knows only an ambient of
//! n = 1), edited by the command-line overrides before it is resolved, so a
//! value given on the command line is known and never estimated. The fit
//! alone is timed, here: the estimation core never reads the clock.

use super::common::{parse_wavelengths, SceneOverrides, SceneSource};
use crate::estimate::level::LevelMode;
use crate::estimate::solver::MAX_BANDS;
use crate::estimate::{Cube, Mode, ParamMaps, Reason, Solver};
use crate::io::spectrum_table::{self, SpectrumTable};
use crate::io::{envi, exr_maps, results_csv};
use crate::pipeline::calibration;
use crate::scene::{AngleKnowledge, Scene};
use anyhow::{bail, Context};
use serde::Serialize;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `irid fit`.
#[derive(Debug, clap::Args)]
pub struct FitArgs {
    /// The input: an ENVI cube (its `.hdr`, or the data file beside one) or
    /// a spectrum table (`.csv`, `.tsv`, `.txt`, `.dat`, … : a wavelength
    /// column, then one column per spectrum).
    #[arg(value_name = "INPUT")]
    pub cube: PathBuf,
    /// Output: a name ending in `.csv` gets one CSV row per spectrum or
    /// pixel; any other an OpenEXR file of parameter maps.
    #[arg(long, value_name = "OUT.exr|OUT.csv")]
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
    /// Spectrum tables: keep only the rows with LO ≤ wavelength ≤ HI (nm).
    #[arg(long, value_name = "LO:HI")]
    pub wavelength_range: Option<String>,
    /// Spectrum tables: every value is percent reflectance (divided by
    /// 100; columns headed with `%` are read so without it).
    #[arg(long)]
    pub percent: bool,
    /// Spectrum tables: resample onto bands LO, LO+STEP, … ≤ HI (nm), each
    /// the mean of the table values within ±STEP/2 of its centre (FWHM STEP).
    #[arg(long, value_name = "LO:HI:STEP")]
    pub bands: Option<String>,
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
    /// Replace existing output files (without it, an existing output is an
    /// error and is left untouched).
    #[arg(long)]
    pub force: bool,
    /// Also write a PNG preview of the thickness map beside the EXR
    /// (`OUT.png`).
    #[arg(long)]
    pub png: bool,
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
    /// Typical reflectance noise σ every fit was judged against (NaN: none
    /// could be had independently of the fits, which were then not tested).
    pub noise_sigma: f64,
    /// Where that σ came from: `given`, `camera`, `data` or `none`.
    pub noise_source: &'static str,
    /// Accuracy of the reflectance scale added to the noise, a fraction of
    /// R (0: none).
    pub reflectance_accuracy: f64,
    /// The level model in force (`auto` resolved to its choice).
    pub level: &'static str,
    /// Mean gain of the image-wide level over bands (1 when absolute).
    pub level_gain: f64,
    /// Mean offset of the image-wide level over bands (0 when absolute).
    pub level_offset: f64,
    /// What the level estimate found.
    pub level_note: String,
    /// The band shift in force, nm (true centre = nominal + shift).
    pub band_shift_nm: f64,
    /// Its σ, nm (0: given or none).
    pub band_shift_sigma_nm: f64,
    /// How the band shift was found (empty: none asked for).
    pub band_shift_note: String,
    /// The film-index note (twin resolved or not, search bound).
    pub n_film_note: String,
    /// The index twin could not be told apart: σ spans both branches.
    pub n_film_ambiguous: bool,
    /// The thickness range searched, nm.
    pub thickness_range_nm: [f64; 2],
}

/// The reflectance-scale accuracy a spectrum table's absolute reflectance is
/// judged with unless told (`--reflectance-accuracy`, the scene's
/// `[measurement] reflectance_accuracy`): 10 % of R. A spectrometer's
/// reflectance is a ratio to a reference (a bare wafer, a mirror) whose own
/// table, focus height and lamp drift leave errors smooth in wavelength of a
/// few percent, and lamp lines leave wiggles where they are divided out;
/// nine measured spectra of polymer films on silicon (401–1041 nm, README
/// "Real spectra") depart from irid's model, the film index one number, by
/// 1–8 % of R where their noise is 0.02–0.05 %: judged at 6 % five of them
/// passed, at 8 % eight, at 10 % all nine, every one within 2.5 % of its
/// reference (σ_d 1.9–2.3 nm on the ~105 nm films). Not
/// under `--level free`, whose per-spectrum scale models the reference
/// itself.
pub const TABLE_REFLECTANCE_ACCURACY: f64 = 0.10;

/// Build the scene of a fit from `--scene` and the overrides.
pub fn build_scene(a: &FitArgs) -> anyhow::Result<Scene> {
    scene_with_overrides(a.scene.as_deref(), &a.overrides)
}

/// `scene` (else one that knows only an ambient of n = 1) edited by the
/// command-line overrides, without its synthetic truth; the substrate must
/// be known.
pub fn scene_with_overrides(
    scene: Option<&std::path::Path>,
    overrides: &SceneOverrides,
) -> anyhow::Result<Scene> {
    let mut src = match scene {
        Some(p) => SceneSource::load(p)?,
        None => SceneSource::empty(),
    };
    // The fit needs no synthetic truth, and a truth that an override makes
    // inconsistent must not stop it.
    src.file.truth = None;
    overrides.apply(&mut src.file)?;
    if !src.file.substrate.is_given() {
        bail!("the substrate is unknown: give --n3 N (or --material3 NAME, or a --scene with [substrate])");
    }
    src.resolve()
}

/// What kind of file `irid fit` reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InputKind {
    /// An ENVI cube.
    Envi,
    /// A spectrum table (text).
    Table,
}

/// The kind of `path`: ENVI for a `.hdr`, a file starting with `ENVI`, or
/// a data file with a header beside it (unless named `.csv`, `.tsv` or
/// `.txt`); a spectrum table otherwise.
pub fn input_kind(path: &Path) -> InputKind {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    if ext == "hdr" {
        return InputKind::Envi;
    }
    let mut magic = [0u8; 4];
    let starts_envi = std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut magic))
        .is_ok()
        && &magic == b"ENVI";
    if starts_envi {
        return InputKind::Envi;
    }
    if matches!(ext.as_str(), "csv" | "tsv" | "txt") {
        return InputKind::Table;
    }
    if envi::resolve_paths(path).is_ok() {
        InputKind::Envi
    } else {
        InputKind::Table
    }
}

/// What the fit reads: the cube, and the spectrum names of a table.
struct Input {
    cube: Cube,
    names: Option<Vec<String>>,
}

fn read_input(a: &FitArgs) -> anyhow::Result<Input> {
    match input_kind(&a.cube) {
        InputKind::Envi => {
            if a.bands.is_some() || a.wavelength_range.is_some() || a.percent {
                bail!(
                    "--bands, --wavelength-range and --percent apply to spectrum tables; {} is an ENVI cube, fitted in its own bands and reflectance",
                    a.cube.display()
                );
            }
            Ok(Input {
                cube: read_envi(a)?,
                names: None,
            })
        }
        InputKind::Table => {
            if a.dark.is_some() {
                bail!(
                    "--dark/--white apply to ENVI cubes; {} is read as a spectrum table (of reflectance)",
                    a.cube.display()
                );
            }
            let table = read_table(a)?;
            Ok(Input {
                cube: table.cube,
                names: Some(table.names),
            })
        }
    }
}

/// Parse `LO:HI` (nm).
fn parse_range(text: &str) -> Result<(f64, f64), String> {
    let parts: Vec<Option<f64>> = text
        .split(':')
        .map(|p| p.trim().parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect();
    match parts[..] {
        [Some(lo), Some(hi)] if lo <= hi => Ok((lo, hi)),
        _ => Err(format!("a range is LO:HI in nm with LO ≤ HI, not {text:?}")),
    }
}

/// Parse `LO:HI:STEP` (nm): the band centres and the step.
fn parse_band_grid(text: &str) -> Result<(Vec<f64>, f64), String> {
    if text.split(':').count() != 3 {
        return Err(format!("bands are LO:HI:STEP in nm, not {text:?}"));
    }
    let centers = parse_wavelengths(text)?;
    let step = text
        .rsplit(':')
        .next()
        .and_then(|s| s.trim().parse::<f64>().ok())
        .ok_or_else(|| format!("bands are LO:HI:STEP in nm, not {text:?}"))?;
    Ok((centers, step))
}

fn span(t: &SpectrumTable) -> String {
    let (lo, hi) = t.wavelength_range();
    format!("{lo}–{hi} nm")
}

/// Read a spectrum table and apply `--wavelength-range` and `--bands`.
fn read_table(a: &FitArgs) -> anyhow::Result<SpectrumTable> {
    let path = &a.cube;
    let mut table = spectrum_table::read_table(path)?;
    let percent = if a.percent {
        table.cube.data.iter_mut().for_each(|v| *v *= 0.01);
        Vec::new()
    } else {
        table.percent_to_fraction()
    };
    if !percent.is_empty() {
        eprintln!(
            "irid fit: note: {} spectrum column(s) headed in percent divided by 100 ({})",
            percent.len(),
            percent
                .iter()
                .take(4)
                .cloned()
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let spikes = table.repair_spikes();
    if !spikes.is_empty() {
        let list: Vec<String> = spikes.iter().take(8).map(|l| format!("{l}")).collect();
        eprintln!(
            "irid fit: note: {} isolated spike(s) replaced by their neighbours' median (at {} nm{})",
            spikes.len(),
            list.join(", "),
            if spikes.len() > 8 { ", …" } else { "" }
        );
    }
    if let Some(r) = &a.wavelength_range {
        let (lo, hi) = parse_range(r).map_err(|m| anyhow::anyhow!("--wavelength-range: {m}"))?;
        let all = span(&table);
        table = table.select_range(lo, hi);
        if table.rows() < spectrum_table::MIN_ROWS {
            bail!(
                "--wavelength-range {r}: keeps {} rows of {} (which covers {all}); irid needs at least {}",
                table.rows(),
                path.display(),
                spectrum_table::MIN_ROWS
            );
        }
    }
    if let Some(b) = &a.bands {
        let (centers, step) = parse_band_grid(b).map_err(|m| anyhow::anyhow!("--bands: {m}"))?;
        if centers.len() > MAX_BANDS {
            bail!(
                "--bands {b}: {} bands, but irid fits at most {MAX_BANDS}: take a larger STEP or a narrower range",
                centers.len()
            );
        }
        let covers = span(&table);
        table = table
            .resample(&centers, step)
            .map_err(|m| anyhow::anyhow!("--bands {b}: {m}"))?;
        let dropped = table.drop_empty_bands();
        if table.rows() < spectrum_table::MIN_ROWS {
            bail!(
                "--bands {b}: only {} of {} bands have table values within ±{} nm (the table covers {covers})",
                table.rows(),
                centers.len(),
                step / 2.0
            );
        }
        if dropped > 0 {
            eprintln!(
                "irid fit: note: {dropped} of {} bands have no table value within ±{} nm (the table covers {covers}) and are left out",
                centers.len(),
                step / 2.0
            );
        }
    } else {
        let dropped = table.drop_empty_bands();
        if dropped > 0 {
            eprintln!(
                "irid fit: note: {dropped} rows of {} are empty (NaN) in every spectrum and are left out",
                path.display()
            );
        }
        if table.rows() > MAX_BANDS {
            // More rows than the fit takes: average every `k` neighbouring
            // rows into one band (its passband the bin), `k` the smallest
            // that fits, so every band averages as many samples and shares
            // one noise level.
            let (lo, hi) = table.wavelength_range();
            let rows = table.rows();
            let k = rows.div_ceil(MAX_BANDS);
            let step = (hi - lo) / (rows - 1) as f64 * k as f64;
            let centers: Vec<f64> = (0..rows / k)
                .map(|i| lo + step * (i as f64 + 0.5) - step / k as f64 / 2.0)
                .collect();
            table = table
                .resample(&centers, step)
                .map_err(|m| anyhow::anyhow!("{}: {m}", path.display()))?;
            table.drop_empty_bands();
            eprintln!(
                "irid fit: note: {} has {rows} wavelengths, more than the {MAX_BANDS} bands irid fits: every {k} averaged, into {} bands of {step:.3} nm ({lo:.1}–{hi:.1} nm; choose with --bands LO:HI:STEP)",
                path.display(),
                table.rows()
            );
        }
    }
    Ok(table)
}

fn read_envi(a: &FitArgs) -> anyhow::Result<Cube> {
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
    if a.png && is_csv(&a.out) {
        bail!("--png draws a map: give an OpenEXR --out, not CSV");
    }
    let mut scene = build_scene(a)?;
    if input_kind(&a.cube) == InputKind::Table
        && scene.level != LevelMode::Free
        && scene.reflectance_accuracy == 0.0
        && a.overrides.reflectance_accuracy.is_none()
    {
        // An absolute reflectance from a spectrometer is only as good as its
        // reference: see TABLE_REFLECTANCE_ACCURACY.
        scene.reflectance_accuracy = TABLE_REFLECTANCE_ACCURACY;
    }
    let Input { cube, names } = read_input(a)?;
    // Refused after the arguments and input are checked, before the fit;
    // the write itself is atomic (io::atomic).
    crate::io::atomic::check_new(&a.out, super::common::overwrite(a.force))?;
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
        .context("the image-wide stage (noise, level, film index)")?;
    let index_s = start.elapsed().as_secs_f64();
    let bar = super::progress::bar(cube.height as u64, "fitting rows");
    let result = pool.install(|| solver.fit_cube_with_progress(&cube, &|_| bar.inc(1)));
    bar.finish_and_clear();
    let elapsed = start.elapsed().as_secs_f64();
    let solve_s = elapsed - index_s;
    let maps = result.context("fitting")?;
    if is_csv(&a.out) {
        results_csv::write_results(&a.out, &maps, names.as_deref())?;
    } else {
        exr_maps::write_maps(&a.out, &maps)?;
        if a.png {
            crate::render::map::write_preview(&a.out, &maps)?;
        }
    }
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
        noise_sigma: solver
            .noise()
            .map_or(f64::NAN, |n| n.instrument_sigma(0.05)),
        noise_source: solver.noise().map_or("none", |n| n.source.name()),
        reflectance_accuracy: solver.noise().map_or(0.0, |n| n.accuracy()),
        level: solver.level().1.name(),
        level_gain: solver.level().0.mean().0,
        level_offset: solver.level().0.mean().1,
        level_note: solver.level().2.to_string(),
        band_shift_nm: solver.band_shift().0,
        band_shift_sigma_nm: solver.band_shift().1,
        band_shift_note: solver.band_shift().2.to_string(),
        n_film_note: maps.meta.n_film_note.clone(),
        n_film_ambiguous: solver.film_index().is_some_and(|i| i.ambiguous),
        thickness_range_nm: {
            let (lo, hi, _) = solver.thickness_range();
            [lo, hi]
        },
    };
    if a.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        eprintln!("{}", human_summary(&summary, &maps, &a.out));
    }
    Ok(())
}

/// Whether `--out` asks for CSV.
fn is_csv(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"))
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
    text.push_str(&format!(
        "\n  judged against noise σ = {:.2e} ({}){}; level {}{}; band shift {}; thickness {:.0}–{:.0} nm",
        s.noise_sigma,
        s.noise_source,
        if s.reflectance_accuracy > 0.0 {
            format!(
                " and a reflectance scale accurate to {:.1} % of R",
                100.0 * s.reflectance_accuracy
            )
        } else {
            String::new()
        },
        s.level,
        if s.level_note.is_empty() {
            String::new()
        } else {
            format!(": {}", s.level_note)
        },
        if s.band_shift_note.is_empty() {
            "none"
        } else {
            &s.band_shift_note
        },
        s.thickness_range_nm[0],
        s.thickness_range_nm[1]
    ));
    text
}
