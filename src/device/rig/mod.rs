//! A rig: a camera and a filter with the scene, bands and sequence they run,
//! built from what a front end was given — the hardware of a `line.toml`
//! ([`hardware_rig`]) or the demo's synthetic camera behind an emulated
//! filter ([`demo_rig`]) — and its dark/white calibration
//! ([`Rig::capture_calibration`]).
//!
//! Library parts, so nothing below the command line imports the command
//! line: the CLI turns its flags into [`DemoOptions`] or a `line.toml`
//! path, asks the operator when a real camera needs the lens capped, and
//! reads the clock.
//!
//! - `config.rs`: the `line.toml` schema ([`LineConfig`], [`ConfigError`]);
//! - `demo.rs`: the demo rig, its scene file and the emulated VariSpec
//!   controller the demo, the tests and the benches run against;
//! - `hardware.rs`: the rig of a `line.toml` (V4L2 camera with feature
//!   `v4l2`, VariSpec controller on a serial port, stored calibration);
//! - `calibrate.rs`: dark and white references captured with a rig.

mod calibrate;
mod config;
mod demo;
mod hardware;

pub use config::{
    CalibrationSection, CameraSection, ConfigError, FilterSection, LineConfig, SequenceSection,
};
pub use demo::{demo_rig, demo_scene_file, emulated_varispec, DemoOptions};
pub use hardware::hardware_rig;

use crate::device::camera::{CameraError, FrameSource};
use crate::device::filter::FilterError;
use crate::optics::band::Band;
use crate::pipeline::calibration::CalibrationError;
use crate::pipeline::sequencer::{BandTuner, SeqMode};
use crate::scene::{Scene, SceneError};
use crate::synth::SynthError;
use std::path::PathBuf;

/// A camera and a filter, ready to run.
pub struct Rig {
    /// The camera.
    pub source: Box<dyn FrameSource>,
    /// The filter.
    pub tuner: Box<dyn BandTuner>,
    /// Scene knowledge.
    pub scene: Scene,
    /// Bands, plane order.
    pub bands: Vec<Band>,
    /// Capture order.
    pub order: Vec<usize>,
    /// Pairing.
    pub seq_mode: SeqMode,
    /// Stored calibration and its limits, for hardware (the demo
    /// calibrates itself at start).
    pub calibration: Option<StoredCalibration>,
    /// Keeps the emulated controller's pseudo-terminal alive.
    pub _emulator: Option<lctf_firmware::emu::EmulatorHandle>,
}

/// Where a hardware rig's calibration is stored and what it must meet
/// (`line.toml`'s `[calibration]`, its path resolved).
#[derive(Debug, Clone, PartialEq)]
pub struct StoredCalibration {
    /// The `.ircal` file.
    pub path: PathBuf,
    /// Refuse a calibration older than this, hours.
    pub max_age_h: f64,
    /// Reflectance of the white reference.
    pub white_reflectance: f64,
}

/// A rig could not be built or calibrated.
///
/// A variant with a cause names the step in its message and leaves the
/// cause to `source()` (as [`ConfigError::Read`] does), so a chain printed
/// link by link shows it once; the transparent ones are another layer's
/// error passed on unchanged.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    /// `line.toml` could not be read or parsed.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A scene file could not be read.
    #[error("cannot read scene {path}")]
    SceneRead {
        /// The file.
        path: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A scene file is not valid TOML for a scene.
    #[error("scene {path}: {message}")]
    SceneParse {
        /// The file.
        path: String,
        /// The parser's message.
        message: String,
    },
    /// The scene of a `line.toml` could not be loaded.
    #[error(transparent)]
    SceneLoad(SceneError),
    /// The scene (or `line.toml`'s `[bands]`) does not resolve.
    #[error("{what}")]
    Scene {
        /// Which part: `scene`, or `line.toml: [bands]`.
        what: String,
        /// Why.
        #[source]
        source: SceneError,
    },
    /// The scene or `line.toml` lacks a section the rig needs.
    #[error("{0}")]
    Incomplete(&'static str),
    /// The demo's image size is not `WxH` or out of range.
    #[error("{0}")]
    Size(String),
    /// The demo's band order is not one irid knows.
    #[error("unknown --order {0} (ascending, descending, interleaved)")]
    Order(String),
    /// `line.toml`'s `sequence.order` is not one irid knows.
    #[error("{path}: unknown sequence.order {order}")]
    SequenceOrder {
        /// The `line.toml`.
        path: String,
        /// The order given.
        order: String,
    },
    /// The synthetic camera could not render the scene.
    #[error("rendering the scene")]
    Render(#[source] SynthError),
    /// `camera.format` names no pixel format irid reads.
    #[error("camera.format {0}: grey8, y10, y12 or y16")]
    CameraFormat(String),
    /// `line.toml` names a V4L2 camera, but this irid has no V4L2 support.
    #[error("camera {0}: this irid was built without V4L2 support; rebuild with `cargo build --release --features v4l2`")]
    NoV4l2(String),
    /// The camera failed (opening, a control, switching its target).
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// The emulated filter controller failed.
    #[error(transparent)]
    Filter(#[from] FilterError),
    /// A step of setting up the filter controller failed.
    #[error("{step}")]
    Controller {
        /// What was being done.
        step: String,
        /// Why.
        #[source]
        source: FilterError,
    },
    /// Capturing a reference failed.
    #[error(transparent)]
    Calibration(#[from] CalibrationError),
    /// Waiting for the operator to set up a reference failed.
    #[error(transparent)]
    Operator(std::io::Error),
}
