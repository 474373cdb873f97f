//! `irid export`: one recorded sweep's calibrated cube as ENVI, so a
//! recording can be studied with the tools spectral imaging people already
//! use (Spectral Python, ENVI, QGIS).
//!
//! The sweep is what the live sequencer decided: the frames it accepted
//! for the sweep (their band from the `/irid/sequencer` verdicts),
//! calibrated with the recorded calibration (or another). Two linear
//! passes over the file — the verdicts, then the frames — keep memory at
//! one cube and one frame, whatever the recording's length (a progress
//! bar over both on a terminal). A band the
//! sweep never received is written as NaN and named on stderr.

use super::common::overwrite;
use crate::device::record::reader::RecordReader;
use crate::device::record::replay::Recording;
use crate::device::record::{decode_frame_meta, decode_samples, SeqEvent};
use crate::device::record::{TOPIC_FRAME, TOPIC_SEQUENCER};
use crate::estimate::cube::Cube;
use crate::io::envi;
use crate::pipeline::calibration::Calibrator;
use anyhow::Context;
use std::collections::HashMap;
use std::path::PathBuf;

/// Arguments of `irid export`.
#[derive(clap::Args, Debug, Clone)]
pub struct ExportArgs {
    /// The recording.
    #[arg(value_name = "FILE.mcap")]
    pub file: PathBuf,
    /// The sweep to export (as numbered by `irid inspect` and the sweep
    /// maps).
    #[arg(long)]
    pub sweep: u64,
    /// The ENVI header to write (`x.hdr`; the data go to `x.img`):
    /// reflectance, f32, band-sequential, wavelengths and FWHM in nm.
    #[arg(long, value_name = "OUT.hdr")]
    pub envi: PathBuf,
    /// Calibrate with this `.ircal` instead of the recorded calibration.
    #[arg(long, value_name = "FILE")]
    pub calibration: Option<PathBuf>,
    /// Replace existing output files.
    #[arg(long)]
    pub force: bool,
}

/// Run `irid export`.
pub fn export(args: &ExportArgs) -> anyhow::Result<()> {
    let rec = Recording::open(&args.file)?;
    let s = rec.session.clone();
    let cal = super::record::calibration_for(&rec, &args.file, args.calibration.as_deref())?;
    let nb = s.bands_nm.len();
    // Pass 1: which frame (sequence number) the sequencer gave each band.
    let mut band_of: HashMap<u64, usize> = HashMap::new();
    let mut missing = Vec::new();
    let len = std::fs::metadata(&args.file).map_or(0, |m| m.len());
    let bar = super::progress::bytes_bar(2 * len, &format!("export {}", args.file.display()));
    let mut reader = RecordReader::open(&args.file)?;
    while let Some(m) = reader.next_message() {
        bar.set_position(reader.progress().0);
        if m.topic != TOPIC_SEQUENCER {
            continue;
        }
        match serde_json::from_slice::<SeqEvent>(&m.data) {
            Ok(SeqEvent::Frame {
                seq,
                verdict,
                sweep: Some(sw),
                band: Some(b),
            }) if verdict == "accept" && sw == args.sweep && b < nb => {
                band_of.insert(seq, b);
            }
            Ok(SeqEvent::Missing { sweep, band }) if sweep == args.sweep => missing.push(band),
            _ => {}
        }
    }
    if band_of.is_empty() {
        anyhow::bail!(
            "{}: sweep {} has no accepted frame (see `irid inspect {}`)",
            args.file.display(),
            args.sweep,
            args.file.display()
        );
    }
    // Pass 2: calibrate those frames into their planes.
    let (w, h) = (s.width as usize, s.height as usize);
    let bands = s.bands();
    let mut cube = Cube::zeros(w, h, bands);
    cube.data.fill(f32::NAN);
    let calibrator = Calibrator::from_calibration(cal);
    let mut filled = vec![false; nb];
    let mut counts = vec![0u16; w * h];
    let mut reader = RecordReader::open(&args.file)?;
    while let Some(m) = reader.next_message() {
        bar.set_position(len + reader.progress().0);
        if m.topic != TOPIC_FRAME {
            continue;
        }
        let Ok(meta) = decode_frame_meta(&m.data) else {
            continue;
        };
        let Some(&b) = band_of.get(&meta.seq) else {
            continue;
        };
        if (meta.width, meta.height) != (s.width, s.height) {
            anyhow::bail!(
                "{}: frame {} is {}×{}, the session {}×{}",
                args.file.display(),
                meta.seq,
                meta.width,
                meta.height,
                s.width,
                s.height
            );
        }
        decode_samples(&m.data, &mut counts);
        let plane = &mut cube.data[b * w * h..(b + 1) * w * h];
        calibrator.apply(b, &counts, meta.format.max_value(), meta.exposure_us, plane);
        filled[b] = true;
    }
    bar.finish_and_clear();
    let absent: Vec<String> = (0..nb)
        .filter(|&b| !filled[b])
        .map(|b| format!("{:.1} nm", s.bands_nm[b]))
        .collect();
    // Both files are checked before either is written (write_cube itself
    // replaces: the policy is the command's).
    let (hdr_d, data_d) = envi::output_paths(&args.envi);
    crate::io::atomic::check_new(&hdr_d, overwrite(args.force))?;
    crate::io::atomic::check_new(&data_d, overwrite(args.force))?;
    let opts = envi::WriteOptions {
        description: Some(format!(
            "irid export of {} sweep {}: calibrated reflectance",
            args.file.display(),
            args.sweep
        )),
        ..envi::WriteOptions::default()
    };
    let (hdr, data) = envi::write_cube(&args.envi, &cube, &opts)
        .with_context(|| format!("writing {}", hdr_d.display()))?;
    eprintln!(
        "irid: sweep {} of {}: {} of {nb} bands, {w}×{h} → {} + {}",
        args.sweep,
        args.file.display(),
        nb - absent.len(),
        hdr.display(),
        data.display()
    );
    if !absent.is_empty() {
        eprintln!(
            "irid: bands never received in sweep {} (written as NaN){}: {}",
            args.sweep,
            if missing.is_empty() {
                String::new()
            } else {
                format!(", {} marked missing live", missing.len())
            },
            absent.join(", ")
        );
    }
    Ok(())
}
