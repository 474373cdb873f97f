//! `line.toml`: a production line's hardware as configured (camera,
//! filter controller, bands, sequence, calibration, scene). Only the schema
//! and its loading; `hardware.rs` opens what it names.

use crate::pipeline::sequencer::SeqMode;
use crate::scene::BandsSpec;
use std::path::{Path, PathBuf};

/// `line.toml` could not be read or parsed.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// Reading the file failed.
    #[error("cannot read {path}")]
    Read {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// The TOML is malformed or has unknown or missing fields.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: String,
        /// The parser's message.
        message: String,
    },
}

/// `line.toml`: a production line's hardware.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LineConfig {
    /// Scene file (what is known about the object), relative to line.toml.
    pub scene: PathBuf,
    /// Solver mode (overridden by `--mode` when given explicitly).
    pub mode: Option<String>,
    /// The camera.
    pub camera: CameraSection,
    /// The filter controller.
    pub filter: FilterSection,
    /// Bands (default: the scene's `[bands]`).
    #[serde(default)]
    pub bands: Option<BandsSpec>,
    /// Pairing.
    #[serde(default)]
    pub sequence: SequenceSection,
    /// Calibration.
    pub calibration: CalibrationSection,
}

/// `[camera]`.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSection {
    /// V4L2 device.
    pub device: String,
    /// `grey8`, `y10`, `y12`, `y16`.
    #[serde(default = "default_format")]
    pub format: String,
    /// Width (0: the device's).
    #[serde(default)]
    pub width: u32,
    /// Height (0: the device's).
    #[serde(default)]
    pub height: u32,
    /// Exposure, µs.
    pub exposure_us: u32,
    /// Analogue gain.
    pub gain: Option<f32>,
    /// Driver buffers.
    #[serde(default = "default_buffers")]
    pub buffers: u32,
}

fn default_format() -> String {
    "y16".into()
}
fn default_buffers() -> u32 {
    4
}

/// `[filter]`.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FilterSection {
    /// Serial port.
    pub port: String,
    /// Baud rate.
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Longest wait for the filter to settle, ms.
    #[serde(default = "default_settle_timeout")]
    pub settle_timeout_ms: u64,
}

fn default_baud() -> u32 {
    9600
}
fn default_settle_timeout() -> u64 {
    1000
}

/// `[sequence]`.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SequenceSection {
    /// `stepped` or `triggered`.
    #[serde(default = "default_seq_mode")]
    pub mode: SeqMode,
    /// `ascending`, `descending`, `interleaved`.
    #[serde(default = "default_order")]
    pub order: String,
}

impl Default for SequenceSection {
    fn default() -> Self {
        SequenceSection {
            mode: SeqMode::Stepped,
            order: default_order(),
        }
    }
}

fn default_seq_mode() -> SeqMode {
    SeqMode::Stepped
}
fn default_order() -> String {
    "ascending".into()
}

/// `[calibration]`.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationSection {
    /// The `.ircal` file written by `irid calibrate`.
    pub file: PathBuf,
    /// Refuse a calibration older than this, hours.
    #[serde(default = "default_max_age")]
    pub max_age_h: f64,
    /// Reflectance of the white reference.
    #[serde(default = "default_white")]
    pub white_reflectance: f64,
}

fn default_max_age() -> f64 {
    24.0
}
fn default_white() -> f64 {
    0.99
}

impl LineConfig {
    /// Read and check `line.toml`; also the folder its paths are
    /// relative to.
    pub fn load(path: &Path) -> Result<(LineConfig, PathBuf), ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.display().to_string(),
            source,
        })?;
        let cfg: LineConfig = toml::from_str(&text).map_err(|e| ConfigError::Parse {
            path: path.display().to_string(),
            message: e.to_string(),
        })?;
        Ok((cfg, path.parent().unwrap_or(Path::new(".")).to_path_buf()))
    }
}
