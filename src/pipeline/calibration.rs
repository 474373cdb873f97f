//! Radiometric calibration: dark and white references per band, and the
//! per-frame conversion of counts to reflectance.
//!
//! `R = (counts − dark) / (white − dark) × R_white × (t_white / t_frame)`:
//! the exposure ratio normalises frames taken at another exposure than the
//! white reference. Pixels that cannot be calibrated are flagged, per band,
//! and come out as NaN (a missing band for that pixel), never as a wrong
//! number: saturated in the white reference, too dark (white − dark below a
//! floor, or dark brighter than white), dead (no response at all).
//! Saturated samples are left out of the averages, not averaged in.
//!
//! A calibration file (`.ircal`) is one line of JSON metadata (size, bands,
//! exposure, gain, camera id, creation time, white reflectance), a newline,
//! then little-endian f32 dark planes, f32 white planes and u8 flag planes,
//! band-sequential. [`Calibration::check`] refuses one taken for another
//! size, band set, exposure or camera, or older than allowed, with a message
//! that says what differs.

use crate::device::camera::{CameraInfo, Frame, PixelFormat};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

/// Per-pixel, per-band calibration flags.
pub mod flag {
    /// Saturated in the white reference.
    pub const SATURATED: u8 = 1;
    /// White barely above (or below) dark: no usable contrast.
    pub const DARK: u8 = 2;
    /// No valid sample at all (every white sample saturated or the pixel
    /// never responded).
    pub const DEAD: u8 = 4;
}

/// Calibration errors.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    /// The file could not be read or written.
    #[error("calibration {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file is not a calibration or is damaged.
    #[error("calibration {path}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Capturing a reference failed.
    #[error("capturing the {reference} reference: {message}")]
    Capture {
        /// `dark` or `white`.
        reference: &'static str,
        /// What went wrong.
        message: String,
    },
    /// The calibration does not fit this run.
    #[error("calibration {origin} does not fit this run: {message}; capture a new one with `irid calibrate`")]
    Mismatch {
        /// File or label.
        origin: String,
        /// What differs.
        message: String,
    },
}

/// What a calibration was taken for.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalMeta {
    /// Format version (1).
    pub version: u32,
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Band centres, nm, in plane order.
    pub bands_nm: Vec<f64>,
    /// Exposure of the references, µs.
    pub exposure_us: u32,
    /// Gain of the references.
    pub gain: f32,
    /// Pixel format.
    pub format: PixelFormat,
    /// Camera identifier.
    pub camera_id: String,
    /// Creation time, seconds since the Unix epoch.
    pub created_unix_s: u64,
    /// Reflectance of the white reference.
    pub white_reflectance: f64,
    /// Frames averaged per band and reference.
    pub frames: u32,
}

/// Dark and white references.
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    /// Metadata.
    pub meta: CalMeta,
    /// Mean dark counts, band-sequential.
    pub dark: Vec<f32>,
    /// Mean white counts, band-sequential.
    pub white: Vec<f32>,
    /// [`flag`] bits, band-sequential.
    pub flags: Vec<u8>,
}

/// What a run expects of a calibration.
#[derive(Clone, Debug)]
pub struct CalExpect {
    /// The camera.
    pub camera: CameraInfo,
    /// Band centres, nm, in plane order.
    pub bands_nm: Vec<f64>,
    /// Now, seconds since the Unix epoch (passed in).
    pub now_unix_s: u64,
    /// Maximum age, seconds.
    pub max_age_s: u64,
}

/// Accumulates frames of one reference (dark or white) per band, leaving
/// saturated samples out.
#[derive(Clone, Debug)]
pub struct Accumulator {
    n: usize,
    sum: Vec<f64>,
    count: Vec<u32>,
    saturated: Vec<bool>,
}

impl Accumulator {
    /// For `bands` planes of `n` pixels.
    pub fn new(n: usize, bands: usize) -> Self {
        Accumulator {
            n,
            sum: vec![0.0; n * bands],
            count: vec![0; n * bands],
            saturated: vec![false; n * bands],
        }
    }

    /// Add a frame as band `band`.
    pub fn add(&mut self, band: usize, frame: &Frame) -> Result<(), String> {
        let px = frame.pixels().map_err(|e| e.to_string())?;
        if px.len() != self.n {
            return Err(format!("frame of {} pixels, expected {}", px.len(), self.n));
        }
        let sat = frame.meta.format.max_value();
        let o = band * self.n;
        let (sum, count, satd) = (
            &mut self.sum[o..o + self.n],
            &mut self.count[o..o + self.n],
            &mut self.saturated[o..o + self.n],
        );
        for i in 0..self.n {
            if px[i] >= sat {
                satd[i] = true;
            } else {
                sum[i] += f64::from(px[i]);
                count[i] += 1;
            }
        }
        Ok(())
    }

    fn mean(&self) -> (Vec<f32>, Vec<bool>, Vec<bool>) {
        let mean = self
            .sum
            .iter()
            .zip(&self.count)
            .map(|(s, &c)| {
                if c > 0 {
                    (s / f64::from(c)) as f32
                } else {
                    f32::NAN
                }
            })
            .collect();
        let empty = self.count.iter().map(|&c| c == 0).collect();
        (mean, self.saturated.clone(), empty)
    }
}

impl Calibration {
    /// Build from accumulated dark and white references. `min_contrast` is
    /// the least `white − dark`, in counts, a usable pixel has.
    pub fn from_references(
        meta: CalMeta,
        dark: &Accumulator,
        white: &Accumulator,
        min_contrast: f32,
    ) -> Calibration {
        let (d, _, d_empty) = dark.mean();
        let (w, w_sat, w_empty) = white.mean();
        let mut flags = vec![0u8; d.len()];
        for i in 0..d.len() {
            let mut f = 0;
            if w_sat[i] {
                f |= flag::SATURATED;
            }
            if w_empty[i] || d_empty[i] {
                f |= flag::DEAD;
            } else if w[i] - d[i] < min_contrast || (w[i] - d[i]).is_nan() {
                f |= flag::DARK;
            }
            flags[i] = f;
        }
        Calibration {
            meta,
            dark: d,
            white: w,
            flags,
        }
    }

    /// Refuse a calibration that does not fit the run, saying why.
    pub fn check(&self, origin: &str, e: &CalExpect) -> Result<(), CalibrationError> {
        let m = &self.meta;
        let bad = |message: String| {
            Err(CalibrationError::Mismatch {
                origin: origin.to_string(),
                message,
            })
        };
        if (m.width, m.height) != (e.camera.width, e.camera.height) {
            return bad(format!(
                "taken for {}×{} frames, the camera delivers {}×{}",
                m.width, m.height, e.camera.width, e.camera.height
            ));
        }
        if m.bands_nm.len() != e.bands_nm.len()
            || m.bands_nm
                .iter()
                .zip(&e.bands_nm)
                .any(|(a, b)| (a - b).abs() > 0.01)
        {
            return bad(format!(
                "taken for bands {} nm, the run uses {} nm",
                fmt_bands(&m.bands_nm),
                fmt_bands(&e.bands_nm)
            ));
        }
        if m.exposure_us != e.camera.exposure_us {
            return bad(format!(
                "taken at {} µs exposure, the camera is set to {} µs",
                m.exposure_us, e.camera.exposure_us
            ));
        }
        if (m.gain - e.camera.gain).abs() > 1e-3 {
            return bad(format!(
                "taken at gain {}, the camera is at {}",
                m.gain, e.camera.gain
            ));
        }
        if m.format != e.camera.format {
            return bad(format!(
                "taken in {:?}, the camera delivers {:?}",
                m.format, e.camera.format
            ));
        }
        if m.camera_id != e.camera.id {
            return bad(format!(
                "taken with camera `{}`, this is `{}`",
                m.camera_id, e.camera.id
            ));
        }
        let age = e.now_unix_s.saturating_sub(m.created_unix_s);
        if age > e.max_age_s {
            return bad(format!(
                "it is {:.1} h old, older than the {:.1} h allowed (`max_age_h`)",
                age as f64 / 3600.0,
                e.max_age_s as f64 / 3600.0
            ));
        }
        let n = (m.width as usize) * (m.height as usize) * m.bands_nm.len();
        if self.dark.len() != n || self.white.len() != n || self.flags.len() != n {
            return bad("its planes do not match its header".into());
        }
        Ok(())
    }

    /// Write to `path`.
    pub fn save(&self, path: &Path) -> Result<(), CalibrationError> {
        let io = |source| CalibrationError::Io {
            path: path.to_path_buf(),
            source,
        };
        let mut out = std::io::BufWriter::new(std::fs::File::create(path).map_err(io)?);
        let header = serde_json::to_string(&self.meta).expect("metadata serialises");
        out.write_all(b"IRIDCAL1 ").map_err(io)?;
        out.write_all(header.as_bytes()).map_err(io)?;
        out.write_all(b"\n").map_err(io)?;
        for v in self.dark.iter().chain(&self.white) {
            out.write_all(&v.to_le_bytes()).map_err(io)?;
        }
        out.write_all(&self.flags).map_err(io)?;
        out.flush().map_err(io)
    }

    /// Read from `path`; a damaged file is an error naming what is wrong.
    pub fn load(path: &Path) -> Result<Calibration, CalibrationError> {
        let mut bytes = Vec::new();
        std::fs::File::open(path)
            .and_then(|mut f| f.read_to_end(&mut bytes))
            .map_err(|source| CalibrationError::Io {
                path: path.to_path_buf(),
                source,
            })?;
        Calibration::from_bytes(&bytes).map_err(|message| CalibrationError::Format {
            path: path.to_path_buf(),
            message,
        })
    }

    /// Parse the file format.
    pub fn from_bytes(bytes: &[u8]) -> Result<Calibration, String> {
        let rest = bytes
            .strip_prefix(b"IRIDCAL1 ")
            .ok_or("not an irid calibration (no IRIDCAL1 magic)")?;
        let nl = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or("header line is not terminated")?;
        let meta: CalMeta =
            serde_json::from_slice(&rest[..nl]).map_err(|e| format!("header: {e}"))?;
        if meta.version != 1 {
            return Err(format!("version {} (this irid reads 1)", meta.version));
        }
        let n = (meta.width as usize)
            .checked_mul(meta.height as usize)
            .and_then(|p| p.checked_mul(meta.bands_nm.len()))
            .filter(|&n| n > 0 && n < 1 << 32)
            .ok_or("header: implausible size")?;
        let body = &rest[nl + 1..];
        if body.len() != n * 9 {
            return Err(format!(
                "body holds {} bytes, the header implies {} ({}×{}×{} bands)",
                body.len(),
                n * 9,
                meta.width,
                meta.height,
                meta.bands_nm.len()
            ));
        }
        let f32s = |b: &[u8]| -> Vec<f32> {
            b.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        };
        Ok(Calibration {
            dark: f32s(&body[..4 * n]),
            white: f32s(&body[4 * n..8 * n]),
            flags: body[8 * n..].to_vec(),
            meta,
        })
    }
}

/// How to capture a reference.
#[derive(Clone, Copy, Debug)]
pub struct CapturePlan<'a> {
    /// Stepped or triggered pairing.
    pub mode: super::sequencer::SeqMode,
    /// Band centres, nm, plane order.
    pub bands_nm: &'a [f64],
    /// Capture order.
    pub order: &'a [usize],
    /// Frames averaged per band.
    pub frames: u32,
    /// Longest wait for one frame.
    pub timeout: std::time::Duration,
}

/// Capture one reference: `frames` settled frames per band, pairing frames
/// with bands by the same sequencer the run uses (so frames exposed while
/// the filter settles are never averaged in). A band lost to a triggered
/// gap has fewer frames averaged, never a wrong one.
pub fn capture_reference(
    reference: &'static str,
    source: &mut dyn crate::device::camera::FrameSource,
    tuner: &mut dyn super::sequencer::BandTuner,
    plan: &CapturePlan<'_>,
) -> Result<Accumulator, CalibrationError> {
    use super::sequencer::{Sequencer, Verdict};
    let CapturePlan {
        mode,
        bands_nm,
        order,
        frames,
        timeout,
    } = *plan;
    let err = |message: String| CalibrationError::Capture { reference, message };
    let info = source.info();
    let n = info.width as usize * info.height as usize;
    let mut acc = Accumulator::new(n, bands_nm.len());
    let mut seq = Sequencer::new(
        mode,
        bands_nm.to_vec(),
        order.to_vec(),
        Some(u64::from(frames.max(1))),
    )
    .map_err(|e| err(e.to_string()))?;
    let mut frame = Frame::with_size(info.width, info.height, info.format);
    // Bound the work: a camera that only ever delivers unusable frames
    // ends in an error, not a hang.
    let limit = 64 * u64::from(frames.max(1)) * bands_nm.len() as u64 + 64;
    for _ in 0..limit {
        if seq.finished() {
            return Ok(acc);
        }
        source
            .next_frame(&mut frame, timeout)
            .map_err(|e| err(e.to_string()))?;
        let valid = frame.pixels().map(|p| p.len() == n).unwrap_or(false);
        let v = seq
            .on_frame(&frame.meta, valid, tuner, &mut |_| {})
            .map_err(|e| err(e.to_string()))?;
        if let Verdict::Accept { band, .. } = v {
            acc.add(band, &frame).map_err(err)?;
        }
    }
    Err(err(format!("no usable frames after {limit} tries")))
}

fn fmt_bands(b: &[f64]) -> String {
    match (b.first(), b.last()) {
        (Some(f), Some(l)) => format!("{} bands {f}…{l}", b.len()),
        _ => "no bands".into(),
    }
}

/// The calibration prepared for the per-frame path: per band an offset and
/// a scale per pixel (NaN where flagged), so converting a frame is one
/// multiply-add per pixel.
#[derive(Clone, Debug)]
pub struct Calibrator {
    n: usize,
    offset: Vec<f32>,
    scale: Vec<f32>,
    exposure_us: u32,
}

impl Calibrator {
    /// Prepare `cal`.
    pub fn new(cal: &Calibration) -> Calibrator {
        Calibrator::from_calibration(cal.clone())
    }

    /// Prepare `cal`, reusing its planes (no second copy of a large
    /// calibration in memory).
    pub fn from_calibration(cal: Calibration) -> Calibrator {
        let n = cal.meta.width as usize * cal.meta.height as usize;
        let rw = cal.meta.white_reflectance as f32;
        let Calibration {
            meta,
            dark,
            mut white,
            flags,
        } = cal;
        for ((w, d), &f) in white.iter_mut().zip(&dark).zip(&flags) {
            *w = if f == 0 { rw / (*w - d) } else { f32::NAN };
        }
        Calibrator {
            n,
            offset: dark,
            scale: white,
            exposure_us: meta.exposure_us,
        }
    }

    /// The identity: counts scaled so that full scale is reflectance 1
    /// (for uncalibrated looks at raw data).
    pub fn identity(
        width: u32,
        height: u32,
        bands: usize,
        format: PixelFormat,
        exposure_us: u32,
    ) -> Calibrator {
        let n = width as usize * height as usize;
        Calibrator {
            n,
            offset: vec![0.0; n * bands],
            scale: vec![1.0 / f32::from(format.max_value()); n * bands],
            exposure_us,
        }
    }

    /// Pixels per plane.
    pub fn plane_len(&self) -> usize {
        self.n
    }

    /// Bytes of calibration read per pixel-band by [`Calibrator::apply_row`]
    /// (for the benchmark's bandwidth account).
    pub fn bytes_per_pixel_band(&self) -> f64 {
        8.0
    }

    /// Convert `counts` (band `band`, exposure `exposure_us`) to reflectance
    /// in `out`. Saturated samples (`>= sat`) become NaN.
    pub fn apply(&self, band: usize, counts: &[u16], sat: u16, exposure_us: u32, out: &mut [f32]) {
        self.apply_row(band, 0, counts, sat, exposure_us, out);
    }

    /// As [`Calibrator::apply`] for the pixels starting at `first` (a row):
    /// the hot loop of ingest, branch-free, vectorisable, no allocation.
    #[inline]
    pub fn apply_row(
        &self,
        band: usize,
        first: usize,
        counts: &[u16],
        sat: u16,
        exposure_us: u32,
        out: &mut [f32],
    ) {
        let n = counts
            .len()
            .min(out.len())
            .min(self.n.saturating_sub(first));
        let o = band * self.n + first;
        let (Some(off), Some(sc)) = (self.offset.get(o..o + n), self.scale.get(o..o + n)) else {
            return;
        };
        let k = self.exposure_us as f32 / exposure_us.max(1) as f32;
        for (((o, &c), &d), &s) in out[..n].iter_mut().zip(&counts[..n]).zip(off).zip(sc) {
            let r = (f32::from(c) - d) * (s * k);
            *o = if c >= sat { f32::NAN } else { r };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn meta() -> CalMeta {
        CalMeta {
            version: 1,
            width: 2,
            height: 2,
            bands_nm: vec![500.0],
            exposure_us: 1000,
            gain: 1.0,
            format: PixelFormat::Y16,
            camera_id: "test".into(),
            created_unix_s: 1000,
            white_reflectance: 0.9,
            frames: 1,
        }
    }

    fn frame(v: [u16; 4]) -> Frame {
        let mut f = Frame::with_size(2, 2, PixelFormat::Y16);
        f.data.copy_from_slice(&v);
        f
    }

    #[test]
    fn math_flags_and_exposure_normalisation() {
        let mut d = Accumulator::new(4, 1);
        let mut w = Accumulator::new(4, 1);
        d.add(0, &frame([100, 100, 5000, 100])).unwrap();
        // Pixel 1 saturated in the white, pixel 2 dark brighter than white.
        w.add(0, &frame([1100, 65535, 1000, 100])).unwrap();
        let cal = Calibration::from_references(meta(), &d, &w, 10.0);
        assert_eq!(
            cal.flags,
            vec![0, flag::SATURATED | flag::DEAD, flag::DARK, flag::DARK]
        );
        let c = Calibrator::new(&cal);
        let mut out = [0.0f32; 4];
        c.apply(0, &[600, 600, 600, 600], 65535, 1000, &mut out);
        assert!((out[0] - 0.45).abs() < 1e-6);
        assert!(out[1].is_nan() && out[2].is_nan() && out[3].is_nan());
        // Twice the exposure: half the reflectance per count above dark.
        c.apply(0, &[1100, 0, 0, 0], 65535, 2000, &mut out);
        assert!((out[0] - 0.45).abs() < 1e-6);
        c.apply(0, &[65535, 0, 0, 0], 65535, 1000, &mut out);
        assert!(out[0].is_nan());
    }

    #[test]
    fn round_trip_and_refusals() {
        let mut d = Accumulator::new(4, 1);
        d.add(0, &frame([1, 2, 3, 4])).unwrap();
        let cal = Calibration::from_references(meta(), &d, &d, 1.0);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.ircal");
        cal.save(&p).unwrap();
        let back = Calibration::load(&p).unwrap();
        assert_eq!(back.meta, cal.meta);
        assert_eq!(back.flags, cal.flags);
        let mut e = CalExpect {
            camera: CameraInfo {
                id: "test".into(),
                width: 2,
                height: 2,
                format: PixelFormat::Y16,
                exposure_us: 1000,
                gain: 1.0,
            },
            bands_nm: vec![500.0],
            now_unix_s: 2000,
            max_age_s: 3600,
        };
        back.check("c", &e).unwrap();
        e.camera.exposure_us = 2000;
        assert!(back
            .check("c", &e)
            .unwrap_err()
            .to_string()
            .contains("exposure"));
        e.camera.exposure_us = 1000;
        e.bands_nm = vec![510.0];
        assert!(back
            .check("c", &e)
            .unwrap_err()
            .to_string()
            .contains("bands"));
        e.bands_nm = vec![500.0];
        e.now_unix_s = 1_000_000;
        assert!(back.check("c", &e).unwrap_err().to_string().contains("old"));
        // Damaged files are errors, not panics.
        let bytes = std::fs::read(&p).unwrap();
        for cut in [0, 5, 20, bytes.len() - 1] {
            assert!(Calibration::from_bytes(&bytes[..cut]).is_err());
        }
    }
}
