//! Command-line front ends: `irid fit`, `irid synth`, `irid model`.
//!
//! This layer reads the clock (to report speed), parses arguments, picks
//! files and thread pools, and turns every error into one line on stderr
//! and a non-zero exit code. It uses `anyhow`; the layers below have typed
//! errors. To add a subcommand, add a module with an `Args` struct and a
//! `run`, and a variant to [`Command`].

pub mod common;
pub mod fit;
pub mod model;
pub mod synth;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// irid: thin-film thickness maps from spectral images.
#[derive(Debug, Parser)]
#[command(name = "irid", version, about, propagate_version = true)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Fit a spectral cube (ENVI) and write parameter maps (OpenEXR).
    Fit(fit::FitArgs),
    /// Render a synthetic ENVI cube from a scene, with its truth as EXR.
    Synth(synth::SynthArgs),
    /// Print the model reflectance of a single film for given parameters.
    Model(model::ModelArgs),
}

/// Run a parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Fit(a) => fit::run(&a),
        Command::Synth(a) => synth::run(&a),
        Command::Model(a) => model::run(&a),
    }
}

/// Entry point of the `irid` binary.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("irid: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
