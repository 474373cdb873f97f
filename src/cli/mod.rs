//! Command-line front ends: `irid run` (the live pipeline; the default, so
//! `irid` alone runs the demo), `irid calibrate`, `irid fit`, `irid synth`,
//! `irid model`, `irid lctf`, `irid render`, and recordings: `irid replay`,
//! `irid inspect`.
//!
//! This layer reads the clock (to report speed), parses arguments, picks
//! files and thread pools, and turns every error into one line on stderr
//! and a non-zero exit code. It uses `anyhow`; the layers below have typed
//! errors. To add a subcommand, add a module with an `Args` struct and a
//! `run`, and a variant to [`Command`].

pub mod calibrate;
pub mod common;
pub mod export;
pub mod fit;
pub mod lctf;
pub mod line;
pub mod model;
pub mod progress;
pub mod record;
pub mod render;
pub mod report;
pub mod run;
pub mod serve;
pub mod synth;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// irid: thin-film thickness maps from spectral images.
#[derive(Debug, Parser)]
#[command(name = "irid", version, about, propagate_version = true)]
pub struct Cli {
    /// What to do (default: `run`, the live demo).
    #[command(subcommand)]
    pub command: Option<Command>,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
#[allow(clippy::large_enum_variant)] // parsed once per process
pub enum Command {
    /// Live thickness maps from a camera behind a tunable filter (with no
    /// `--config`: the demo on a synthetic camera and an emulated filter).
    Run(run::RunArgs),
    /// Capture dark and white references per band.
    Calibrate(calibrate::CalibrateArgs),
    /// Fit a spectral cube (ENVI) or a spectrum table and write parameter
    /// maps (OpenEXR) or per-spectrum results (CSV).
    Fit(fit::FitArgs),
    /// Render a synthetic ENVI cube from a scene, with its truth as EXR.
    Synth(synth::SynthArgs),
    /// Print the model reflectance of a single film for given parameters.
    Model(model::ModelArgs),
    /// Talk to the tunable-filter controller (or its emulator).
    Lctf(lctf::LctfArgs),
    /// Pictures: a map as PNG, the film's colour, the speed/accuracy chart.
    Render(render::RenderArgs),
    /// Replay a recording (MCAP) through the pipeline, with its own or
    /// another mode, scene or calibration; or an ENVI cube as one sweep.
    Replay(record::ReplayArgs),
    /// Record what the line sees (MCAP) without solving.
    Record(record::RecordArgs),
    /// List a recording's contents: channels, sweeps, bands, gaps, drops,
    /// damage.
    Inspect(record::InspectArgs),
    /// Write one recorded sweep's calibrated cube as ENVI.
    Export(export::ExportArgs),
}

/// Run a parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        None => run::run(&run::RunArgs::defaults()),
        Some(Command::Run(a)) => run::run(&a),
        Some(Command::Calibrate(a)) => calibrate::run(&a),
        Some(Command::Fit(a)) => fit::run(&a),
        Some(Command::Synth(a)) => synth::run(&a),
        Some(Command::Model(a)) => model::run(&a),
        Some(Command::Lctf(a)) => lctf::run(&a),
        Some(Command::Render(a)) => render::run(&a),
        Some(Command::Replay(a)) => record::replay(&a),
        Some(Command::Record(a)) => record::record_only(&a),
        Some(Command::Inspect(a)) => record::inspect(&a),
        Some(Command::Export(a)) => export::export(&a),
    }
}

/// Entry point of the `irid` binary.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("irid: error: {}", report::error_line(&e));
            ExitCode::FAILURE
        }
    }
}
