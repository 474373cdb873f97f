//! Radiometric calibration: dark and white references per band, and the
//! per-frame conversion of counts to reflectance — for `irid run` and for
//! `irid fit --dark/--white` alike.
//!
//! `R = (counts − dark) / (white − dark) × R_white × (t_white / t_frame)`:
//! the exposure ratio normalises frames taken at another exposure than the
//! white reference. One [`CalibrationPolicy`] decides what cannot be
//! calibrated, for both commands: a sample at or above the sensor's full
//! scale is saturated, and so is a pixel whose white reference reached it;
//! a pixel whose white stands less than 1 % of full scale above its dark
//! (or below it) is too dark; one with no valid reference sample is dead.
//! Such values come out as NaN (a missing band for that pixel), never as a
//! wrong number, and the NaN carries the reason: [`SATURATED_NAN`] or
//! [`DARK_NAN`] (see [`crate::estimate::cube`]), so the maps can say why.
//! Saturated samples are left out of the reference averages, not averaged
//! in.
//!
//! [`read_calibrated`] reads raw-count ENVI cubes with dark and white
//! reference cubes and converts them through the same [`Calibrator`] the
//! live pipeline uses, so equal counts give bit-identical reflectance.
//!
//! A calibration file (`.ircal`) is one line of JSON metadata (size, bands,
//! exposure, gain, camera id, creation time, white reflectance), a newline,
//! then little-endian f32 dark planes, f32 white planes and u8 flag planes,
//! band-sequential. [`Calibration::check`] refuses one taken for another
//! size, band set, exposure or camera, or older than allowed, with a message
//! that says what differs.

use crate::device::camera::{CameraInfo, Frame, PixelFormat};
use crate::estimate::cube::{nan_reason, Cube, DARK_NAN, SATURATED_NAN};
use crate::estimate::Reason;
use crate::io::{envi, IoError};
use multiversion::multiversion;
use rayon::prelude::*;
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

    /// The value a flagged pixel's bands take: [`SATURATED_NAN`] if
    /// `flags` has [`SATURATED`] (saturation wins: it is the thing to fix
    /// first), [`DARK_NAN`] for [`DARK`] or [`DEAD`]; for 0 (not flagged),
    /// `None`.
    ///
    /// [`SATURATED_NAN`]: crate::estimate::cube::SATURATED_NAN
    /// [`DARK_NAN`]: crate::estimate::cube::DARK_NAN
    pub fn tag(flags: u8) -> Option<f32> {
        use crate::estimate::cube::{DARK_NAN, SATURATED_NAN};
        if flags & SATURATED != 0 {
            Some(SATURATED_NAN)
        } else if flags != 0 {
            Some(DARK_NAN)
        } else {
            None
        }
    }
}

/// The one rule for what can be calibrated, shared by `irid run` (camera
/// frames) and `irid fit --dark/--white` (ENVI cubes).
///
/// - A sample is **saturated** at or above `saturation_level` (the
///   sensor's full scale): it becomes [`SATURATED_NAN`]. A pixel whose
///   white reference saturated is flagged [`flag::SATURATED`] in every
///   frame.
/// - A pixel is **dark** when `white − dark` is below `min_contrast` (1 %
///   of full scale), not positive, or not a number, and **dead** when a
///   reference has no valid sample: flagged [`flag::DARK`] /
///   [`flag::DEAD`], its bands become [`DARK_NAN`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CalibrationPolicy {
    /// Counts at or above which a sample is saturated; `+∞` where the full
    /// scale is unknown (nothing saturates).
    pub saturation_level: f32,
    /// The least `white − dark`, counts, of a usable pixel (`white > dark`
    /// is always required).
    pub min_contrast: f32,
}

impl CalibrationPolicy {
    /// The contrast floor as a fraction of full scale.
    pub const MIN_CONTRAST_FRACTION: f32 = 0.01;

    /// The policy for a sensor of full scale `full_scale` counts: saturated
    /// at full scale, a floor of 1 % of it. `+∞` (unknown full scale): no
    /// saturation and no floor beyond `white > dark`.
    pub fn for_full_scale(full_scale: f32) -> CalibrationPolicy {
        let min_contrast = if full_scale.is_finite() {
            full_scale * Self::MIN_CONTRAST_FRACTION
        } else {
            0.0
        };
        CalibrationPolicy {
            saturation_level: full_scale,
            min_contrast,
        }
    }

    /// The policy for a camera pixel format (full scale = its largest
    /// value).
    pub fn for_format(format: PixelFormat) -> CalibrationPolicy {
        Self::for_full_scale(f32::from(format.max_value()))
    }

    /// Whether a sample of `counts` is saturated.
    pub fn is_saturated(&self, counts: f32) -> bool {
        counts >= self.saturation_level
    }

    /// The [`flag`] bits of a pixel with mean `dark` and `white` (NaN where
    /// a reference has no valid sample); `white_saturated` if some white
    /// sample saturated (and was left out of the mean). A white mean at or
    /// above the saturation level counts as saturated too.
    pub fn flags(&self, dark: f32, white: f32, white_saturated: bool) -> u8 {
        let mut f = 0;
        if white_saturated || self.is_saturated(white) {
            f |= flag::SATURATED;
        }
        let contrast = white - dark;
        if !(dark.is_finite() && white.is_finite()) {
            f |= flag::DEAD;
        } else if !(contrast >= self.min_contrast && contrast > 0.0) {
            f |= flag::DARK;
        }
        f
    }
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
    /// A raw-count or reference ENVI cube could not be read or does not fit.
    #[error(transparent)]
    Envi(#[from] IoError),
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
    /// The camera's reflectance noise per band, measured on the repeated
    /// reference frames (none with one frame per band).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise: Option<CalNoise>,
}

/// The camera's reflectance noise per band, `σ_R² = var0 + shot·R`:
/// read noise from the dark frames' scatter, shot noise from the white
/// frames' excess over it, both scaled to reflectance by the band's
/// median white − dark, plus the references' own averaging error.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalNoise {
    /// Signal-independent reflectance variance per band.
    pub var0: Vec<f64>,
    /// Reflectance variance per unit reflectance per band.
    pub shot: Vec<f64>,
}

impl CalNoise {
    /// As the estimator's noise model.
    pub fn model(&self) -> crate::estimate::noise::NoiseModel {
        crate::estimate::noise::NoiseModel {
            var0: self.var0.clone(),
            shot: self.shot.clone(),
            rel2: 0.0,
            source: crate::estimate::noise::NoiseSource::Camera,
        }
    }
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
    sum2: Vec<f64>,
    count: Vec<u32>,
    saturated: Vec<bool>,
}

impl Accumulator {
    /// For `bands` planes of `n` pixels.
    pub fn new(n: usize, bands: usize) -> Self {
        Accumulator {
            n,
            sum: vec![0.0; n * bands],
            sum2: vec![0.0; n * bands],
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
        let policy = CalibrationPolicy::for_format(frame.meta.format);
        let o = band * self.n;
        let (sum, sum2, count, satd) = (
            &mut self.sum[o..o + self.n],
            &mut self.sum2[o..o + self.n],
            &mut self.count[o..o + self.n],
            &mut self.saturated[o..o + self.n],
        );
        for i in 0..self.n {
            if policy.is_saturated(f32::from(px[i])) {
                satd[i] = true;
            } else {
                let v = f64::from(px[i]);
                sum[i] += v;
                sum2[i] += v * v;
                count[i] += 1;
            }
        }
        Ok(())
    }

    /// The means (NaN where no sample was valid) and which pixels saw a
    /// saturated sample.
    fn mean(&self) -> (Vec<f32>, Vec<bool>) {
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
        (mean, self.saturated.clone())
    }
}

impl Accumulator {
    /// Band `band`'s median over pixels of the frame-to-frame variance of
    /// counts (unbiased for the median of a χ² of few degrees of freedom)
    /// and its median mean, from pixels with at least two valid
    /// frames; `None` with fewer than 16 such pixels.
    fn band_scatter(&self, band: usize) -> Option<(f64, f64)> {
        let o = band * self.n;
        let mut var = Vec::new();
        let mut mean = Vec::new();
        for i in o..o + self.n {
            let c = f64::from(self.count[i]);
            if self.count[i] >= 2 && !self.saturated[i] {
                let m = self.sum[i] / c;
                // s² has ν = c − 1 degrees of freedom: its median is
                // σ²·(1 − 2/(9ν))³ (Wilson–Hilferty), 0.47 σ² from two
                // frames; divided out, the median over pixels is σ².
                let nu = c - 1.0;
                let median_factor = (1.0 - 2.0 / (9.0 * nu)).powi(3);
                var.push(((self.sum2[i] - c * m * m) / nu).max(0.0) / median_factor);
                mean.push(m);
            }
        }
        if var.len() < 16 {
            return None;
        }
        Some((median(&mut var), median(&mut mean)))
    }
}

fn median(v: &mut [f64]) -> f64 {
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// The camera's reflectance noise from the references' frame-to-frame
/// scatter (see [`CalNoise`]); `None` with one frame per band or too few
/// usable pixels in any band.
fn reference_noise(
    dark: &Accumulator,
    white: &Accumulator,
    bands: usize,
    frames: u32,
    white_reflectance: f64,
) -> Option<CalNoise> {
    if frames < 2 {
        return None;
    }
    let f = f64::from(frames);
    let mut var0 = Vec::with_capacity(bands);
    let mut shot = Vec::with_capacity(bands);
    for k in 0..bands {
        let (vd, md) = dark.band_scatter(k)?;
        let (vw, mw) = white.band_scatter(k)?;
        let span = mw - md;
        if span.is_nan() || span <= 0.0 {
            return None;
        }
        // Counts: var(c) = vd + b·(c − dark), b from the white's excess.
        let b = ((vw - vd) / span).max(0.0);
        // R = (c − d)/(w − d)·R_w: s converts counts to reflectance.
        let s = white_reflectance / span;
        // A frame's own noise, then the references' averaging error (the
        // dark mean's shifts every R alike; the white mean's scales it).
        var0.push(vd * s * s * (1.0 + 1.0 / f));
        // The white mean's error adds R²·vw·s²/(F·R_w²) ≤ R·vw·s²/(F·R_w).
        shot.push(b * s + vw * s * s / (f * white_reflectance));
    }
    Some(CalNoise { var0, shot })
}

impl Calibration {
    /// Build from accumulated dark and white references, flagging pixels by
    /// `policy` (a reference with no valid sample has a NaN mean: dead).
    pub fn from_references(
        meta: CalMeta,
        dark: &Accumulator,
        white: &Accumulator,
        policy: &CalibrationPolicy,
    ) -> Calibration {
        let mut meta = meta;
        if meta.noise.is_none() {
            meta.noise = reference_noise(
                dark,
                white,
                meta.bands_nm.len(),
                meta.frames,
                meta.white_reflectance,
            );
        }
        let (d, _) = dark.mean();
        let (w, w_sat) = white.mean();
        let flags = d
            .iter()
            .zip(&w)
            .zip(&w_sat)
            .map(|((&d, &w), &sat)| policy.flags(d, w, sat))
            .collect();
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

    /// Write to `path`, atomically (see [`crate::io::atomic`]): a crash or a
    /// full disk never leaves a damaged calibration under that name.
    pub fn save(&self, path: &Path) -> Result<(), CalibrationError> {
        self.save_with(path, crate::io::atomic::Overwrite::Replace)
    }

    /// [`Calibration::save`], refusing to replace an existing file when
    /// `overwrite` says so.
    pub fn save_with(
        &self,
        path: &Path,
        overwrite: crate::io::atomic::Overwrite,
    ) -> Result<(), CalibrationError> {
        let header = serde_json::to_string(&self.meta).expect("metadata serialises");
        crate::io::atomic::write_atomically(path, overwrite, |out| {
            out.write_all(b"IRIDCAL1 ")?;
            out.write_all(header.as_bytes())?;
            out.write_all(b"\n")?;
            for v in self.dark.iter().chain(&self.white) {
                out.write_all(&v.to_le_bytes())?;
            }
            out.write_all(&self.flags)
        })
        .map_err(CalibrationError::Envi)
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

/// The full scale of raw counts stored as ENVI `data_type` when the user
/// does not give it: the type's range for u8 and u16 (what a camera
/// writes natively, as `irid run` takes a Grey8 or Y16 camera's), unknown
/// (`+∞`) for the others.
pub fn envi_full_scale(data_type: envi::DataType) -> f32 {
    match data_type {
        envi::DataType::U8 => f32::from(u8::MAX),
        envi::DataType::U16 => f32::from(u16::MAX),
        _ => f32::INFINITY,
    }
}

/// Calibrate `raw`, band-sequential counts in planes of `n` pixels, to
/// reflectance in place, with mean `dark` and `white` references of the
/// same layout: flags by `policy`, then the [`Calibrator`] `irid run` uses
/// (the references count as taken at the frames' exposure).
pub fn calibrate_counts(
    raw: &mut [f32],
    dark: Vec<f32>,
    white: Vec<f32>,
    n: usize,
    white_reflectance: f32,
    policy: &CalibrationPolicy,
) {
    let flags: Vec<u8> = dark
        .iter()
        .zip(&white)
        .map(|(&d, &w)| policy.flags(d, w, false))
        .collect();
    let cal = Calibrator::from_planes(n, dark, white, &flags, white_reflectance, 1);
    if n == 0 {
        return;
    }
    let mut out = vec![0.0f32; n];
    for (b, plane) in raw.chunks_exact_mut(n).enumerate() {
        cal.apply_counts(b, plane, policy.saturation_level, 1, &mut out);
        plane.copy_from_slice(&out);
    }
}

/// Read a raw-count ENVI cube and its dark and white reference cubes (same
/// size and bands; see [`envi::read_references`]) and calibrate to
/// reflectance by [`CalibrationPolicy::for_full_scale`] with `full_scale`
/// (default [`envi_full_scale`] of the cube's data type), exactly as `irid
/// run` calibrates frames. Stored values are used as they are: a scale
/// factor common to the three cancels. A non-finite raw value (e.g. the
/// `data ignore value`) stays a plain NaN.
pub fn read_calibrated(
    cube_path: &Path,
    dark_path: &Path,
    white_path: &Path,
    white_reflectance: f32,
    full_scale: Option<f32>,
) -> Result<Cube, CalibrationError> {
    let raw = envi::read_image(cube_path)?;
    let bands = envi::header_bands(&raw.header, &raw.header_path)?;
    let (dark, white) = envi::read_references(&raw, dark_path, white_path)?;
    let policy = CalibrationPolicy::for_full_scale(
        full_scale.unwrap_or_else(|| envi_full_scale(raw.header.data_type)),
    );
    let (width, height) = (raw.header.samples, raw.header.lines);
    let mut data = raw.data;
    calibrate_counts(
        &mut data,
        dark.data,
        white.data,
        width * height,
        white_reflectance,
        &policy,
    );
    Ok(Cube {
        width,
        height,
        bands,
        data,
    })
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

/// The systematic error of the packed calibration against the f32 formula
/// `(counts − dark) × white_reflectance / (white − dark)`, in reflectance,
/// for |R| ≤ 1 (relative to |R| above): a band whose pixels cannot all be
/// packed within it keeps f32 planes. Reflectance noise is ~1e-3.
pub const PACKED_ERROR_BOUND: f32 = 2e-5;

/// Share of [`PACKED_ERROR_BOUND`] for the quantisation of dark and gain;
/// the rest covers f32 rounding (≲ 1e-6 for |R| ≤ 1; see `Packing`).
const QUANT_BUDGET: f64 = 1.9e-5;

/// Code of a pixel flagged dark or dead (never a valid code: the dark field
/// of a valid code is at most its maximum − 1, so any code whose dark field
/// is all ones, [`FLAGGED_SATURATED`] too, is free).
const FLAGGED_DARK: u32 = u32::MAX;

/// Code of a pixel flagged saturated (the white reference saturated).
const FLAGGED_SATURATED: u32 = u32::MAX - 1;

/// The code of a flagged pixel whose scale holds the tag `s`.
fn flagged_code(s: f32) -> u32 {
    match nan_reason(s) {
        Some(Reason::Saturated) => FLAGGED_SATURATED,
        _ => FLAGGED_DARK,
    }
}

/// Bits of 1.0f32.
const ONE_BITS: u32 = 0x3F80_0000;

/// How one band's calibration is packed into one u32 per pixel.
///
/// A pixel's scale `s = R_white / (white − dark)` is `scale × γ` with
/// `γ ≥ 1` a small float: its code `qg` (the low `gain_bits` bits) is the
/// bit pattern of `γ` above 1.0 shifted down by `gain_shift` (`23 −
/// gain_shift` mantissa bits, the rest exponent bits), so decoding is a
/// shift and an add, and its relative error is at most 2^-(mantissa + 1)
/// (7.6e-6 with 16 bits, 1.5e-5 with 15). The dark `d` is `dark_base +
/// dark_unit × qd / γ` (`qd` the high bits): stored in steps proportional
/// to `1/s`, its error costs every pixel the same reflectance, `scale ×
/// dark_unit / 2`, and a pixel of high contrast may lie far from the base.
/// Then `R = k × scale × ((c − dark_base) × γ − dark_unit × qd)`: per
/// pixel a mask, two shifts, an add, two conversions, two subtracts, three
/// multiplies and the NaN select.
/// How the 32 bits split between gain and dark is chosen per band for the
/// smallest bound; each pixel's error is then checked, not assumed.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Packing {
    /// Reflectance per count at γ = 1 (the band's least scale).
    scale: f32,
    /// Integer-valued, at or below every dark of the band.
    dark_base: f32,
    /// Dark step × γ.
    dark_unit: f32,
    /// Bits of the gain code (low bits).
    gain_bits: u32,
    /// 23 − mantissa bits of the gain code.
    gain_shift: u32,
    /// Largest quantisation error over the band's pixels, reflectance for
    /// |R| ≤ 1 (checked at preparation).
    max_error: f32,
}

impl Packing {
    /// A band with no usable pixel, or the identity's: γ = 1, dark 0.
    const PLAIN: Packing = Packing {
        scale: 1.0,
        dark_base: 0.0,
        dark_unit: 1.0,
        gain_bits: 16,
        gain_shift: 7,
        max_error: 0.0,
    };

    fn gain_mask(&self) -> u32 {
        (1u32 << self.gain_bits) - 1
    }

    fn dark_max(&self) -> u32 {
        // Leave the all-ones dark field free so no valid code is flagged.
        (1u32 << (32 - self.gain_bits)) - 2
    }

    fn gamma(&self, q: u32) -> f32 {
        f32::from_bits(((q & self.gain_mask()) << self.gain_shift) + ONE_BITS)
    }

    fn gain_code(&self, s: f32, inv_scale: f64) -> u32 {
        let g = (f64::from(s) * inv_scale) as f32;
        let above = g.to_bits().saturating_sub(ONE_BITS);
        let half = 1u32 << (self.gain_shift - 1);
        ((above + half) >> self.gain_shift).min(self.gain_mask())
    }

    /// Pack one band: `dark` and `scale` (a tagged NaN where flagged) in, the codes
    /// out in `code`, as f32 bit patterns (the codes go over the white plane
    /// they were computed from). `None` if some pixel cannot be packed
    /// within the budget (the band then stays f32); `gain` is scratch.
    fn pack(dark: &[f32], scale: &[f32], code: &mut [f32], gain: &mut Vec<u32>) -> Option<Packing> {
        let (mut smin, mut smax, mut dmin) = (f32::INFINITY, 0.0f32, f32::INFINITY);
        let mut any = false;
        for (&d, &s) in dark.iter().zip(scale) {
            if s.is_nan() {
                continue;
            }
            if !(s.is_finite() && s > 0.0 && d.is_finite()) {
                return None;
            }
            any = true;
            smin = smin.min(s);
            smax = smax.max(s);
            dmin = dmin.min(d);
        }
        if !any {
            for (c, &s) in code.iter_mut().zip(scale) {
                *c = f32::from_bits(flagged_code(s));
            }
            return Some(Packing::PLAIN);
        }
        let dark_base = f64::from(dmin).floor();
        if dark_base.abs() >= f64::from(1u32 << 23) {
            return None;
        }
        // Spread of the darks in reflectance: what the dark field must span.
        let mut spread = 0.0f64;
        for (&d, &s) in dark.iter().zip(scale) {
            if !s.is_nan() {
                spread = spread.max((f64::from(d) - dark_base) * f64::from(s));
            }
        }
        let range = f64::from(smax) / f64::from(smin);
        // The split with the least bound: gain error 2^-(m+1) for m
        // mantissa bits, dark error spread / (2 × dark steps); γ spans up
        // to 2^(2^x) with x exponent bits (less a rounding margin).
        let mut best: Option<(f64, u32, u32)> = None;
        for m in 15u32..=18 {
            for x in 0u32..=3 {
                if range * (1.0 + 2f64.powi(-(m as i32))) >= 2f64.powi(1 << x) {
                    continue;
                }
                let gain_bits = m + x;
                let steps = f64::from((1u32 << (32 - gain_bits)) - 2);
                let bound = 2f64.powi(-(m as i32 + 1)) + spread / (2.0 * steps);
                if best.is_none_or(|(b, _, _)| bound < b) {
                    best = Some((bound, gain_bits, 23 - m));
                }
            }
        }
        let (_, gain_bits, gain_shift) = best?;
        let mut p = Packing {
            scale: smin,
            dark_base: dark_base as f32,
            dark_unit: 1.0,
            gain_bits,
            gain_shift,
            max_error: 0.0,
        };
        // Gain codes, and the dark step from the decoded γ so the largest
        // dark fits.
        let inv = 1.0 / f64::from(smin);
        gain.clear();
        let mut top = 0.0f64;
        for (&d, &s) in dark.iter().zip(scale) {
            let q = if s.is_nan() { 0 } else { p.gain_code(s, inv) };
            gain.push(q);
            if !s.is_nan() {
                top = top.max((f64::from(d) - dark_base) * f64::from(p.gamma(q)));
            }
        }
        let unit = (top / f64::from(p.dark_max())) as f32;
        // Rounded up, so the largest dark does not clamp.
        p.dark_unit = if unit > 0.0 {
            f32::from_bits(unit.to_bits() + 1)
        } else {
            1.0
        };
        // Dark codes, and each pixel's error `|d − d'| s' + |s' − s| / s`
        // with `s' = scale γ'`, `(d − d') s' = ((d − base) γ' − unit qd) scale`.
        let (unit, sc, dmax) = (f64::from(p.dark_unit), f64::from(p.scale), p.dark_max());
        let inv_unit = 1.0 / unit;
        let mut worst = 0.0f64;
        for (((c, &d), &s), &q) in code.iter_mut().zip(dark).zip(scale).zip(gain.iter()) {
            if s.is_nan() {
                *c = f32::from_bits(flagged_code(s));
                continue;
            }
            let g = f64::from(p.gamma(q));
            let x = (f64::from(d) - dark_base) * g;
            // x ≥ 0; round to nearest by truncation (f64::round is a libm
            // call on the baseline target).
            let qd = ((x * inv_unit + 0.5) as u32).min(dmax);
            let e = (x - unit * f64::from(qd)).abs() * sc + (sc * g / f64::from(s) - 1.0).abs();
            worst = worst.max(e);
            *c = f32::from_bits((qd << gain_bits) | q);
        }
        if worst > QUANT_BUDGET {
            return None;
        }
        p.max_error = worst as f32;
        Some(p)
    }
}

/// How one band is stored.
#[derive(Clone, Copy, Debug)]
enum BandForm {
    /// Packed codes at `band × n` of `code`.
    Packed(Packing),
    /// f32 offset and scale planes at `at` of `offset`/`scale` (a band the
    /// packed form cannot hold within [`PACKED_ERROR_BOUND`]).
    Full { at: usize },
}

/// The calibration prepared for the per-frame path, per band and pixel one
/// u32 packing dark and gain (4 bytes read per pixel-band; see `Packing`),
/// within [`PACKED_ERROR_BOUND`] of the f32 formula (at the reference
/// exposure; the error scales with the exposure ratio, as R does). A band
/// that cannot be packed that closely keeps f32 dark and scale planes (8
/// bytes): one whose white − dark varies more than 256× across the band, or
/// whose darks spread far more than the contrast of its dimmest pixels
/// (dark 0…4000 at 50 counts of contrast, say). Flagged pixels and
/// saturated samples come out NaN.
#[derive(Clone, Debug)]
pub struct Calibrator {
    n: usize,
    forms: Vec<BandForm>,
    code: Vec<u32>,
    offset: Vec<f32>,
    scale: Vec<f32>,
    exposure_us: u32,
    /// The camera's reflectance noise, where the calibration measured it.
    noise: Option<CalNoise>,
}

impl Calibrator {
    /// Prepare `cal`.
    pub fn new(cal: &Calibration) -> Calibrator {
        Calibrator::from_calibration(cal.clone())
    }

    /// Prepare `cal`, reusing its planes (the codes are written over the
    /// white plane: no second copy of a large calibration in memory).
    pub fn from_calibration(cal: Calibration) -> Calibrator {
        let n = cal.meta.width as usize * cal.meta.height as usize;
        let rw = cal.meta.white_reflectance as f32;
        let Calibration {
            meta,
            dark,
            white,
            flags,
        } = cal;
        let mut c = Calibrator::from_planes(n, dark, white, &flags, rw, meta.exposure_us);
        c.noise = meta.noise;
        c
    }

    /// The camera's reflectance noise measured with the references.
    pub fn noise(&self) -> Option<&CalNoise> {
        self.noise.as_ref()
    }

    /// Prepare band-sequential `dark`, `white` and [`flag`] planes of `n`
    /// pixels, for a white of reflectance `rw` taken at `exposure_us`
    /// (the codes are written over `white`).
    pub fn from_planes(
        n: usize,
        dark: Vec<f32>,
        mut white: Vec<f32>,
        flags: &[u8],
        rw: f32,
        exposure_us: u32,
    ) -> Calibrator {
        let len = dark.len().min(white.len()).min(flags.len());
        let bands = len.checked_div(n).unwrap_or(0);
        // Bands in parallel; each keeps its codes in its white plane, or
        // hands back its scale plane if it stays f32. The codes are stored
        // as f32 bit patterns (to_bits/from_bits are transmutes: bits
        // survive), and collecting into Vec<u32> below reuses the
        // allocation.
        let packed: Vec<(Option<Packing>, Vec<f32>)> = if bands == 0 {
            Vec::new()
        } else {
            white[..bands * n]
                .par_chunks_mut(n)
                .zip(dark.par_chunks(n))
                .zip(flags.par_chunks(n))
                .map_init(
                    || (vec![0.0f32; n], Vec::new()),
                    |(s, gain), ((w, d), f)| {
                        for (((s, &w), &d), &f) in s.iter_mut().zip(w.iter()).zip(d).zip(f) {
                            *s = flag::tag(f).unwrap_or_else(|| rw / (w - d));
                        }
                        match Packing::pack(d, s, w, gain) {
                            Some(p) => (Some(p), Vec::new()),
                            None => {
                                w.fill(f32::from_bits(FLAGGED_DARK));
                                (None, s.clone())
                            }
                        }
                    },
                )
                .collect()
        };
        let mut forms = Vec::with_capacity(bands);
        let (mut offset, mut scale) = (Vec::new(), Vec::new());
        for (b, (p, s)) in packed.into_iter().enumerate() {
            match p {
                Some(p) => forms.push(BandForm::Packed(p)),
                None => {
                    forms.push(BandForm::Full { at: offset.len() });
                    offset.extend_from_slice(&dark[b * n..(b + 1) * n]);
                    scale.extend_from_slice(&s);
                }
            }
        }
        drop(dark);
        let code = white.into_iter().map(f32::to_bits).collect();
        Calibrator {
            n,
            forms,
            code,
            offset,
            scale,
            exposure_us,
            noise: None,
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
        let p = Packing {
            scale: 1.0 / f32::from(format.max_value()),
            ..Packing::PLAIN
        };
        Calibrator {
            n,
            forms: vec![BandForm::Packed(p); bands],
            code: vec![0; n * bands],
            offset: Vec::new(),
            scale: Vec::new(),
            exposure_us,
            noise: None,
        }
    }

    /// Pixels per plane.
    pub fn plane_len(&self) -> usize {
        self.n
    }

    /// Bands held packed (the rest keep f32 planes).
    pub fn packed_bands(&self) -> usize {
        self.forms
            .iter()
            .filter(|f| matches!(f, BandForm::Packed(_)))
            .count()
    }

    /// The largest error of the packed bands against the f32 formula,
    /// reflectance for |R| ≤ 1, as checked at preparation (quantisation
    /// only; f32 rounding adds ≲ 1e-6). At most [`PACKED_ERROR_BOUND`].
    pub fn packed_error(&self) -> f32 {
        self.forms
            .iter()
            .map(|f| match f {
                BandForm::Packed(p) => p.max_error,
                BandForm::Full { .. } => 0.0,
            })
            .fold(0.0, f32::max)
    }

    /// Bytes of calibration read per pixel-band by [`Calibrator::apply_row`]
    /// (for the benchmark's bandwidth account): 4 packed, 8 in f32.
    pub fn bytes_per_pixel_band(&self) -> f64 {
        let bands = self.forms.len().max(1) as f64;
        let packed = self.packed_bands() as f64;
        (4.0 * packed + 8.0 * (bands - packed)) / bands
    }

    /// Convert `counts` (band `band`, exposure `exposure_us`) to reflectance
    /// in `out`. Saturated samples (`>= sat`) become [`SATURATED_NAN`],
    /// flagged pixels their flag's tag ([`flag::tag`]).
    pub fn apply(&self, band: usize, counts: &[u16], sat: u16, exposure_us: u32, out: &mut [f32]) {
        self.apply_row(band, 0, counts, sat, exposure_us, out);
    }

    /// As [`Calibrator::apply`] for the pixels starting at `first` (a row):
    /// the hot loop of ingest, branch-free, vectorised, no allocation.
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
        let Some(&form) = self.forms.get(band) else {
            return;
        };
        let k = self.exposure_us as f32 / exposure_us.max(1) as f32;
        match form {
            BandForm::Packed(p) => {
                let o = band * self.n + first;
                if let Some(code) = self.code.get(o..o + n) {
                    apply_packed(&counts[..n], code, &mut out[..n], p, k, sat);
                }
            }
            BandForm::Full { at } => {
                let o = at + first;
                if let (Some(off), Some(sc)) = (self.offset.get(o..o + n), self.scale.get(o..o + n))
                {
                    apply_full(&counts[..n], off, sc, &mut out[..n], k, sat);
                }
            }
        }
    }

    /// As [`Calibrator::apply`] for counts stored as f32 (an ENVI cube of
    /// raw counts), with the same arithmetic: integer counts give the bits
    /// [`Calibrator::apply`] gives. A non-finite count (a missing value)
    /// gives a plain NaN; `sat` is the policy's saturation level. Not the
    /// hot path: one pass per cube.
    pub fn apply_counts(
        &self,
        band: usize,
        counts: &[f32],
        sat: f32,
        exposure_us: u32,
        out: &mut [f32],
    ) {
        let n = counts.len().min(out.len()).min(self.n);
        let Some(&form) = self.forms.get(band) else {
            return;
        };
        let k = self.exposure_us as f32 / exposure_us.max(1) as f32;
        let samples = counts[..n].iter().zip(out[..n].iter_mut());
        match form {
            BandForm::Packed(p) => {
                let o = band * self.n;
                let Some(code) = self.code.get(o..o + n) else {
                    return;
                };
                let l = PackedLoop::new(p, k);
                for ((&c, o), &q) in samples.zip(code) {
                    *o = if c.is_finite() {
                        l.sample(c, c >= sat, q)
                    } else {
                        f32::NAN
                    };
                }
            }
            BandForm::Full { at } => {
                let (Some(off), Some(sc)) =
                    (self.offset.get(at..at + n), self.scale.get(at..at + n))
                else {
                    return;
                };
                for (((&c, o), &d), &s) in samples.zip(off).zip(sc) {
                    *o = if c.is_finite() {
                        full_sample(c, c >= sat, d, s, k)
                    } else {
                        f32::NAN
                    };
                }
            }
        }
    }
}

/// The constants of the packed loop for one band and exposure ratio `k`.
#[derive(Clone, Copy)]
struct PackedLoop {
    mask: u32,
    shift: u32,
    bits: u32,
    base: f32,
    unit: f32,
    ks: f32,
}

impl PackedLoop {
    #[inline(always)]
    fn new(p: Packing, k: f32) -> PackedLoop {
        PackedLoop {
            mask: p.gain_mask(),
            shift: p.gain_shift,
            bits: p.gain_bits,
            base: p.dark_base,
            unit: p.dark_unit,
            ks: p.scale * k,
        }
    }

    /// One sample of `c` counts with code `q`: the reflectance, or the tag
    /// of a saturated sample or a flagged pixel — by selects, not branches
    /// (a saturated sample wins over a dark flag).
    #[inline(always)]
    fn sample(&self, c: f32, saturated: bool, q: u32) -> f32 {
        let g = f32::from_bits(((q & self.mask) << self.shift).wrapping_add(ONE_BITS));
        let qd = q.wrapping_shr(self.bits) as i32 as f32;
        let r = ((c - self.base) * g - self.unit * qd) * self.ks;
        let v = if q == FLAGGED_DARK { DARK_NAN } else { r };
        if saturated || q == FLAGGED_SATURATED {
            SATURATED_NAN
        } else {
            v
        }
    }
}

/// One sample of an unpacked band: dark `d`, scale `s` (a flagged pixel's
/// scale is its tag, passed through by a select: arithmetic need not keep a
/// NaN's payload).
#[inline(always)]
fn full_sample(c: f32, saturated: bool, d: f32, s: f32, k: f32) -> f32 {
    let r = (c - d) * (s * k);
    let v = if s.is_nan() { s } else { r };
    if saturated {
        SATURATED_NAN
    } else {
        v
    }
}

/// The packed hot loop (see `Packing`), compiled for the best vector unit
/// the CPU offers. Flagged pixels and saturated samples give their tagged
/// NaN by a select, not a branch.
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn apply_packed(counts: &[u16], code: &[u32], out: &mut [f32], p: Packing, k: f32, sat: u16) {
    let n = counts.len().min(code.len()).min(out.len());
    let l = PackedLoop::new(p, k);
    for ((o, &c), &q) in out[..n].iter_mut().zip(&counts[..n]).zip(&code[..n]) {
        *o = l.sample(f32::from(c), c >= sat, q);
    }
}

/// The f32 loop for a band kept unpacked.
#[multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1", "aarch64+neon"))]
fn apply_full(counts: &[u16], off: &[f32], sc: &[f32], out: &mut [f32], k: f32, sat: u16) {
    for (((o, &c), &d), &s) in out.iter_mut().zip(counts).zip(off).zip(sc) {
        *o = full_sample(f32::from(c), c >= sat, d, s, k);
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
            noise: None,
        }
    }

    fn frame(v: [u16; 4]) -> Frame {
        let mut f = Frame::with_size(2, 2, PixelFormat::Y16);
        f.data.copy_from_slice(&v);
        f
    }

    /// The camera noise model against a second formulation: frames drawn
    /// with read noise σ_r and shot noise (variance = signal × g, counts),
    /// calibrated to reflectance one by one; the model's σ_R at the
    /// scene's reflectance must match the frames' own scatter about their
    /// mean, (σ_r² + (c − d)·g)·(R_w/(w − d))², plus the references'
    /// averaging error, which stays fixed from frame to frame and is
    /// checked separately.
    #[test]
    fn camera_noise_from_repeated_references_matches_the_frames_scatter() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let (w_px, h_px) = (16u32, 16u32);
        let n = (w_px * h_px) as usize;
        let (read, g, dark, white, scene, rw) = (6.0, 0.5, 100.0, 3000.0, 900.0, 0.9);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let z = Normal::new(0.0, 1.0).unwrap();
        let draw = |level: f64, rng: &mut rand_chacha::ChaCha8Rng| {
            let mut f = Frame::with_size(w_px, h_px, PixelFormat::Y16);
            let sd = (read * read + (level - dark) * g).sqrt();
            for v in f.data.iter_mut() {
                *v = (level + sd * z.sample(rng)).round().clamp(0.0, 65535.0) as u16;
            }
            f
        };
        let frames = 16u32;
        let (mut da, mut wa) = (Accumulator::new(n, 1), Accumulator::new(n, 1));
        for _ in 0..frames {
            da.add(0, &draw(dark, &mut rng)).unwrap();
            wa.add(0, &draw(white, &mut rng)).unwrap();
        }
        let m = CalMeta {
            width: w_px,
            height: h_px,
            white_reflectance: rw,
            frames,
            ..meta()
        };
        let cal = Calibration::from_references(
            m,
            &da,
            &wa,
            &CalibrationPolicy::for_format(PixelFormat::Y16),
        );
        let noise = cal
            .meta
            .noise
            .clone()
            .expect("measured with 16 frames")
            .model();
        // The scene, calibrated frame by frame: each pixel's scatter over
        // 200 frames about its own mean.
        let cz = Calibrator::new(&cal);
        let mut sum = vec![0.0f64; n];
        let mut sum2 = vec![0.0f64; n];
        let mut out = vec![0f32; n];
        let reps = 200;
        for _ in 0..reps {
            let f = draw(scene, &mut rng);
            cz.apply(0, &f.data, u16::MAX, 1000, &mut out);
            for i in 0..n {
                let r = f64::from(out[i]);
                sum[i] += r;
                sum2[i] += r * r;
            }
        }
        let mut var: Vec<f64> = (0..n)
            .map(|i| {
                let m = sum[i] / f64::from(reps);
                (sum2[i] - f64::from(reps) * m * m) / f64::from(reps - 1)
            })
            .collect();
        var.sort_by(f64::total_cmp);
        let temporal = var[n / 2];
        let r = rw * (scene - dark) / (white - dark);
        let s = rw / (white - dark);
        let expected = (read * read + (scene - dark) * g) * s * s;
        // The frames agree with the second formulation (sampling: 200
        // frames × 256 pixels, the median within a few %).
        assert!(
            (temporal / expected - 1.0).abs() < 0.05,
            "{temporal} vs {expected}"
        );
        // The model adds the references' fixed error (1/16 of a frame's
        // variance from each reference, scaled): above the temporal
        // scatter by that much, no more.
        let model = noise.var(0, r);
        assert!(
            model >= expected * 0.95 && model <= expected * 1.25,
            "model {model} vs frames {expected}"
        );
        // Two frames per band (one degree of freedom per pixel: the
        // median of s² is 0.45 σ², corrected): the read noise still comes
        // out right, σ_r²·s²·(1 + 1/2), within the median's sampling error
        // over 256 pixels.
        let (mut d2, mut w2) = (Accumulator::new(n, 1), Accumulator::new(n, 1));
        for _ in 0..2 {
            d2.add(0, &draw(dark, &mut rng)).unwrap();
            w2.add(0, &draw(white, &mut rng)).unwrap();
        }
        let m2 = CalMeta {
            width: w_px,
            height: h_px,
            white_reflectance: rw,
            frames: 2,
            ..meta()
        };
        let cal2 = Calibration::from_references(
            m2,
            &d2,
            &w2,
            &CalibrationPolicy::for_format(PixelFormat::Y16),
        );
        let var0 = cal2.meta.noise.expect("two frames measure").var0[0];
        let want = read * read * s * s * 1.5;
        assert!((var0 / want - 1.0).abs() < 0.3, "{var0} vs {want}");
        // One frame per band measures nothing.
        let one = CalMeta {
            frames: 1,
            ..meta()
        };
        let cal1 = Calibration::from_references(
            one,
            &da,
            &wa,
            &CalibrationPolicy::for_format(PixelFormat::Y16),
        );
        assert!(cal1.meta.noise.is_none());
    }

    #[test]
    fn math_flags_and_exposure_normalisation() {
        let mut d = Accumulator::new(4, 1);
        let mut w = Accumulator::new(4, 1);
        d.add(0, &frame([100, 100, 5000, 100])).unwrap();
        // Pixel 1 saturated in the white, pixel 2 dark brighter than white.
        w.add(0, &frame([1100, 65535, 1000, 100])).unwrap();
        let policy = CalibrationPolicy {
            saturation_level: 65535.0,
            min_contrast: 10.0,
        };
        let cal = Calibration::from_references(meta(), &d, &w, &policy);
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
    fn the_noise_model_survives_its_json_header_bit_for_bit() {
        // A recording and a calibration file carry the camera's noise in
        // their JSON header; a replay must judge with exactly the live
        // run's variances (one unit in the last place off moved a level's
        // fit in the 12th digit and flipped σ bits in the replayed maps).
        // Values a best-effort float parser reads one ulp off:
        let var0 = vec![
            4.618_744_340_240_223_7e-7,
            3.349_800_507_325_057_5e-7,
            1.137_373_361_724_169_4e-7,
        ];
        let mut m = meta();
        m.noise = Some(CalNoise {
            var0: var0.clone(),
            shot: var0.iter().map(|v| v * 3.7).collect(),
        });
        let back: CalMeta = serde_json::from_str(&serde_json::to_string(&m).unwrap()).unwrap();
        let noise = back.noise.expect("the noise is kept");
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
        assert_eq!(bits(&noise.var0), bits(&var0));
        assert_eq!(bits(&noise.shot), bits(&m.noise.unwrap().shot));
    }

    #[test]
    fn round_trip_and_refusals() {
        let mut d = Accumulator::new(4, 1);
        d.add(0, &frame([1, 2, 3, 4])).unwrap();
        let cal =
            Calibration::from_references(meta(), &d, &d, &CalibrationPolicy::for_full_scale(100.0));
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

    /// The unpacked f32 formula the packed form must match.
    fn reference(d: f32, w: f32, f: u8, rw: f32, c: u16, sat: u16, k: f32) -> f32 {
        let s = if f == 0 { rw / (w - d) } else { f32::NAN };
        let r = (f32::from(c) - d) * (s * k);
        if c >= sat {
            f32::NAN
        } else {
            r
        }
    }

    /// A calibration of `bands` planes of `w × 1` pixels.
    fn calibration(
        w: u32,
        format: PixelFormat,
        dark: Vec<f32>,
        white: Vec<f32>,
        flags: Vec<u8>,
    ) -> Calibration {
        let bands = dark.len() / w as usize;
        Calibration {
            meta: CalMeta {
                width: w,
                height: 1,
                bands_nm: (0..bands).map(|b| 500.0 + b as f64).collect(),
                format,
                ..meta()
            },
            dark,
            white,
            flags,
        }
    }

    /// Counts that probe a pixel: below and at dark, across the white
    /// range, past white, up to saturation, and a few at random.
    fn probes(d: f32, w: f32, sat: u16, rng: &mut impl rand::Rng) -> Vec<u16> {
        let mut c: Vec<f32> = vec![0.0, d - 1.0, d, d + 1.0];
        for t in [0.001, 0.01, 0.1, 0.5, 0.9, 1.0, 1.2] {
            c.push(d + t * (w - d));
        }
        c.extend([f32::from(sat) - 1.0, f32::from(sat)]);
        c.extend((0..4).map(|_| rng.random::<f32>() * f32::from(sat)));
        c.into_iter()
            .map(|v| v.round().clamp(0.0, f32::from(sat)) as u16)
            .collect()
    }

    /// Apply `c` to every band of `cal` at every probe and compare with
    /// the f32 formula; returns the worst error, normalised by max(1, |R|).
    fn worst_error(cal: &Calibration, c: &Calibrator, k: f32, rng: &mut impl rand::Rng) -> f64 {
        let n = cal.meta.width as usize;
        let sat = cal.meta.format.max_value();
        let rw = cal.meta.white_reflectance as f32;
        let e_us = (cal.meta.exposure_us as f32 / k).round() as u32;
        let k = cal.meta.exposure_us as f32 / e_us as f32;
        let mut worst = 0.0f64;
        let mut out = vec![0.0f32; n];
        for b in 0..cal.dark.len() / n {
            let r = b * n..(b + 1) * n;
            let (d, w, f) = (&cal.dark[r.clone()], &cal.white[r.clone()], &cal.flags[r]);
            let probes: Vec<Vec<u16>> = (0..n).map(|i| probes(d[i], w[i], sat, rng)).collect();
            for j in 0..probes[0].len() {
                let counts: Vec<u16> = probes.iter().map(|p| p[j]).collect();
                c.apply(b, &counts, sat, e_us, &mut out);
                for i in 0..n {
                    let want = reference(d[i], w[i], f[i], rw, counts[i], sat, k);
                    let got = out[i];
                    assert_eq!(
                        want.is_nan(),
                        got.is_nan(),
                        "band {b} pixel {i} counts {}: {got} for {want}",
                        counts[i]
                    );
                    if !want.is_nan() {
                        let e = f64::from((got - want).abs()) / f64::from(want.abs()).max(1.0);
                        worst = worst.max(e);
                    }
                }
            }
        }
        worst
    }

    /// One band per (sensor, dark level, contrast): `n` pixels with dark
    /// non-uniformity (± 1 count + 0.5 % of the dark, non-integer means),
    /// the contrast `white − dark` spread 2.5× (vignetting) up to `top`,
    /// and a few flagged pixels.
    fn sensor_bands(
        format: PixelFormat,
        darks: &[f32],
        tops: &[f32],
        n: usize,
        rng: &mut impl rand::Rng,
    ) -> Calibration {
        let max = f32::from(format.max_value());
        let (mut dark, mut white, mut flags) = (Vec::new(), Vec::new(), Vec::new());
        for &d0 in darks {
            for &top in tops {
                let top = top.min(max - 2.0 - 1.02 * d0 - 1.0);
                if top < 50.0 {
                    continue;
                }
                for i in 0..n {
                    let d = (d0 + (1.0 + 0.005 * d0) * (2.0 * rng.random::<f32>() - 1.0)).max(0.0);
                    let d = (d * 16.0).round() / 16.0 + 1.0 / 64.0;
                    let contrast = top * (0.4 + 0.6 * rng.random::<f32>());
                    dark.push(d);
                    white.push(d + contrast);
                    flags.push(if i % 97 == 5 { flag::DARK } else { 0 });
                }
            }
        }
        calibration(n as u32, format, dark, white, flags)
    }

    const SENSORS: [(PixelFormat, [f32; 4]); 4] = [
        (PixelFormat::Grey8, [0.0, 4.0, 16.0, 60.0]),
        (PixelFormat::Y10, [0.0, 16.0, 64.0, 300.0]),
        (PixelFormat::Y12, [0.0, 64.0, 256.0, 1200.0]),
        (PixelFormat::Y16, [0.0, 256.0, 1000.0, 4000.0]),
    ];
    /// Largest contrast per band (the least is 0.4× that: 50 counts and up).
    const TOPS: [f32; 6] = [125.0, 500.0, 2500.0, 10000.0, 40000.0, 65000.0];

    #[test]
    fn packed_matches_the_f32_formula_over_sensor_ranges() {
        use rand::SeedableRng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for (format, darks) in SENSORS {
            let cal = sensor_bands(format, &darks, &TOPS, 256, &mut rng);
            let c = Calibrator::new(&cal);
            let bands = cal.dark.len() / 256;
            assert!(bands > 0);
            // The packed form holds every one of these bands.
            assert_eq!(c.packed_bands(), bands, "{format:?}");
            assert_eq!(c.bytes_per_pixel_band(), 4.0);
            assert!(c.packed_error() <= 1.9e-5);
            for k in [1.0, 0.5, 2.0] {
                let e = worst_error(&cal, &c, k, &mut rng);
                // The error scales with the exposure ratio, like R.
                assert!(
                    e <= f64::from(PACKED_ERROR_BOUND) * f64::from(k.max(1.0)),
                    "{format:?} k {k}: error {e:e}"
                );
            }
        }
    }

    #[test]
    fn bands_that_cannot_be_packed_keep_f32_and_stay_exact() {
        use rand::SeedableRng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let n = 64;
        let (mut dark, mut white) = (Vec::new(), Vec::new());
        // Band 0: contrast from 50 to 65000 counts in one band (gain range
        // 1300×). Band 1: darks 0…4000 at 50 counts of contrast. Band 2:
        // realistic, packs.
        for i in 0..n {
            let t = i as f32 / (n - 1) as f32;
            dark.push(100.0);
            white.push(150.0 + t * 65000.0);
        }
        for i in 0..n {
            dark.push(4000.0 * (i as f32 / (n - 1) as f32) + 0.3);
            white.push(dark[n + i] + 50.0);
        }
        for i in 0..n {
            dark.push(200.0 + 0.25 * (i % 5) as f32);
            white.push(dark[2 * n + i] + 3000.0 + 20.0 * i as f32);
        }
        let flags = vec![0; 3 * n];
        let cal = calibration(n as u32, PixelFormat::Y16, dark, white, flags);
        let c = Calibrator::new(&cal);
        assert_eq!(c.packed_bands(), 1);
        assert!((c.bytes_per_pixel_band() - 20.0 / 3.0).abs() < 1e-9);
        let e = worst_error(&cal, &c, 1.0, &mut rng);
        assert!(e <= f64::from(PACKED_ERROR_BOUND), "error {e:e}");
        // The f32 bands compute exactly the formula.
        let mut out = vec![0.0; n];
        let counts: Vec<u16> = (0..n).map(|i| (i * 997 % 65535) as u16).collect();
        for b in 0..2 {
            c.apply(b, &counts, 65535, 1000, &mut out);
            for i in 0..n {
                let j = b * n + i;
                let want = reference(cal.dark[j], cal.white[j], 0, 0.9, counts[i], 65535, 1.0);
                assert!(want.to_bits() == out[i].to_bits() || want.is_nan() && out[i].is_nan());
            }
        }
    }

    #[test]
    fn flagged_pixels_and_saturated_samples_are_nan_packed_or_not() {
        let n = 8;
        let mut dark = vec![64.0f32; 2 * n];
        let mut white: Vec<f32> = (0..2 * n).map(|i| 1000.0 + 10.0 * i as f32).collect();
        // Band 1 cannot be packed (gain range 500×).
        dark[n..].fill(10.0);
        white[n + 1] = 12.0;
        white[n + 2] = 1020.0;
        let mut flags = vec![0u8; 2 * n];
        for b in 0..2 {
            flags[b * n + 3] = flag::SATURATED;
            flags[b * n + 4] = flag::DARK;
            flags[b * n + 5] = flag::DEAD | flag::SATURATED;
            flags[b * n + 6] = flag::DEAD;
        }
        let cal = calibration(n as u32, PixelFormat::Y10, dark, white, flags.clone());
        let c = Calibrator::new(&cal);
        assert_eq!(c.packed_bands(), 1);
        let mut out = vec![0.0f32; n];
        let mut out_f32 = vec![0.0f32; n];
        for b in 0..2 {
            for v in [0u16, 64, 500, 1022, 1023, 5000] {
                let counts = vec![v; n];
                c.apply(b, &counts, 1023, 1000, &mut out);
                // The f32-count entry (ENVI raw cubes) gives the same bits.
                let counts_f32: Vec<f32> = counts.iter().map(|&c| f32::from(c)).collect();
                c.apply_counts(b, &counts_f32, 1023.0, 1000, &mut out_f32);
                for i in 0..n {
                    let f = flags[b * n + i];
                    let want = if v >= 1023 || f & flag::SATURATED != 0 {
                        Some(Reason::Saturated)
                    } else if f != 0 {
                        Some(Reason::Dark)
                    } else {
                        None
                    };
                    let at = format!("band {b} pixel {i} counts {v}");
                    assert_eq!(nan_reason(out[i]), want, "{at}: {}", out[i]);
                    assert_eq!(out[i].is_nan(), want.is_some(), "{at}");
                    assert_eq!(out[i].to_bits(), out_f32[i].to_bits(), "{at}");
                }
            }
        }
        // A missing raw value stays a plain NaN (not a calibration tag).
        for b in 0..2 {
            c.apply_counts(
                b,
                &[f32::NAN, f32::INFINITY, -f32::INFINITY],
                1023.0,
                1000,
                &mut out_f32[..3],
            );
            assert!(out_f32[..3]
                .iter()
                .all(|v| v.is_nan() && nan_reason(*v).is_none()));
        }
        // Rows: the same through apply_row at an offset.
        let mut row = vec![0.0f32; 3];
        c.apply_row(0, 3, &[500, 500, 500], 1023, 1000, &mut row);
        let tags: Vec<_> = row.iter().map(|&r| nan_reason(r)).collect();
        assert_eq!(
            tags,
            [
                Some(Reason::Saturated),
                Some(Reason::Dark),
                Some(Reason::Saturated)
            ]
        );
        // Past the end of the plane: only the pixels it has are written.
        row.fill(0.0);
        c.apply_row(0, 6, &[500, 1023, 500], 1023, 1000, &mut row);
        assert_eq!(nan_reason(row[0]), Some(Reason::Dark), "dead pixel 6");
        assert_eq!(nan_reason(row[1]), Some(Reason::Saturated));
        assert_eq!(row[2], 0.0);
        c.apply_row(0, 7, &[500], 1023, 1000, &mut row[..1]);
        assert!(row[0].is_finite());
    }

    #[test]
    fn exposure_normalisation_packed() {
        let n = 4;
        let dark = vec![100.0, 100.5, 101.0, 99.25];
        let white = vec![2100.0, 2300.5, 1901.0, 2099.25];
        let cal = calibration(n as u32, PixelFormat::Y12, dark, white, vec![0; n]);
        let c = Calibrator::new(&cal);
        assert_eq!(c.packed_bands(), 1);
        let mut at_cal = vec![0.0f32; n];
        let mut at_twice = vec![0.0f32; n];
        c.apply(0, &[1100, 1100, 1100, 1100], 4095, 1000, &mut at_cal);
        // Twice the exposure, twice the counts above dark: the same R.
        let twice: Vec<u16> = cal
            .dark
            .iter()
            .map(|&d| (d + 2.0 * (1100.0 - d)).round() as u16)
            .collect();
        c.apply(0, &twice, 4095, 2000, &mut at_twice);
        for i in 0..n {
            let want = 0.9 * (1100.0 - cal.dark[i]) / (cal.white[i] - cal.dark[i]);
            assert!((at_cal[i] - want).abs() < 2e-5, "{} {want}", at_cal[i]);
            // Rounding the doubled counts costs at most half a count.
            let half = 0.5 * 0.9 / (cal.white[i] - cal.dark[i]) / 2.0;
            assert!((at_twice[i] - want).abs() < half + 2e-5);
        }
    }

    #[test]
    fn identity_is_counts_over_full_scale() {
        for format in [PixelFormat::Grey8, PixelFormat::Y12, PixelFormat::Y16] {
            let max = format.max_value();
            let c = Calibrator::identity(4, 2, 3, format, 1000);
            assert_eq!((c.plane_len(), c.packed_bands()), (8, 3));
            let counts: Vec<u16> = (0..8).map(|i| (u32::from(max) * i / 7) as u16).collect();
            let mut out = vec![0.0f32; 8];
            c.apply(2, &counts, max, 1000, &mut out);
            for i in 0..8 {
                let want = f32::from(counts[i]) * (1.0 / f32::from(max));
                assert_eq!(out[i].is_nan(), counts[i] >= max);
                if counts[i] < max {
                    assert_eq!(out[i], want, "{format:?} {}", counts[i]);
                }
            }
            // At half the exposure of the reference: twice the reflectance.
            c.apply(0, &counts[..4], max, 500, &mut out[..4]);
            assert_eq!(out[1], 2.0 * f32::from(counts[1]) / f32::from(max));
            // A band it does not have leaves the output alone.
            out.fill(7.0);
            c.apply(3, &counts, max, 1000, &mut out);
            assert!(out.iter().all(|&v| v == 7.0));
        }
    }
}
