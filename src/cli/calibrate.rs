//! `irid calibrate`: capture dark and white references per band and store
//! them (`.ircal`) with what they were taken for (size, bands, exposure,
//! gain, camera, time), so `irid run` can refuse a stale or mismatched one.
//!
//! With `--config line.toml` the operator is asked to cap the lens and to
//! place the white reference; without, the demo rig calibrates itself.

use super::run::{ask_operator, now_unix_s, RunArgs};
use crate::device::rig::{demo_rig, hardware_rig, DemoOptions};
use crate::pipeline::calibration::flag;
use anyhow::Context;
use std::path::PathBuf;

/// Arguments of `irid calibrate`.
#[derive(clap::Args, Debug, Clone)]
pub struct CalibrateArgs {
    /// Line configuration; without it, calibrate the demo rig.
    #[arg(long, value_name = "line.toml")]
    pub config: Option<PathBuf>,
    /// Where to write the calibration.
    #[arg(long, default_value = "calibration.ircal")]
    pub out: PathBuf,
    /// Frames averaged per band and reference.
    #[arg(long, default_value_t = 8)]
    pub frames: u32,
    /// Reflectance of the white reference (default: line.toml's, else 0.99).
    #[arg(long)]
    pub white_reflectance: Option<f64>,
    /// Demo: image size.
    #[arg(long, value_name = "WxH")]
    pub size: Option<String>,
    /// Replace existing output files (without it, an existing output is an
    /// error and is left untouched).
    #[arg(long)]
    pub force: bool,
}

/// Run `irid calibrate`.
pub fn run(args: &CalibrateArgs) -> anyhow::Result<()> {
    let overwrite = super::common::overwrite(args.force);
    crate::io::atomic::check_new(&args.out, overwrite)?;
    let (mut rig, white) = match &args.config {
        Some(p) => {
            let (rig, line) = hardware_rig(p)?;
            (rig, line.calibration.white_reflectance)
        }
        None => {
            let demo = DemoOptions {
                size: args.size.clone(),
                ..RunArgs::defaults().demo_options()
            };
            (demo_rig(&demo)?, 0.99)
        }
    };
    let white = args.white_reflectance.unwrap_or(white);
    if !(white > 0.0 && white <= 1.0) {
        anyhow::bail!("--white-reflectance must lie in (0, 1], not {white}");
    }
    let cal =
        rig.capture_calibration(args.frames.max(1), white, now_unix_s(), &mut ask_operator)?;
    cal.save_with(&args.out, overwrite)
        .with_context(|| format!("saving {}", args.out.display()))?;
    let count = |f: u8| cal.flags.iter().filter(|&&x| x & f != 0).count();
    println!(
        "{}: {}×{}, {} bands, exposure {} µs, {} frames each; flagged samples: {} saturated, {} dark, {} dead (of {})",
        args.out.display(),
        cal.meta.width,
        cal.meta.height,
        cal.meta.bands_nm.len(),
        cal.meta.exposure_us,
        cal.meta.frames,
        count(flag::SATURATED),
        count(flag::DARK),
        count(flag::DEAD),
        cal.flags.len()
    );
    Ok(())
}
