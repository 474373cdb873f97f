//! The production line: a moving web mapped row by row at line rate.
//!
//! On a coating line the film moves under the camera while the filter steps
//! through its bands, so each band of a stretch of film is seen at a
//! different sensor row. This layer follows the film, not the sensor:
//!
//! - [`geometry`]: where each frame's rows lie on the web (encoder or
//!   constant speed), and the highest line speed the optics allow;
//! - [`accumulate`]: per-web-row state in a ring sized by the field of view;
//!   a row is finished, in web order, as soon as it holds every band, or
//!   when it leaves the view without them (flagged "missing bands");
//! - [`solve`]: each finished row solved as a one-row cube;
//! - [`angles`]: where the incidence angle depends on the sensor row, each
//!   band modelled at its own angle where the spread matters;
//! - [`run`]: the line runner: capture on one thread, solving on another
//!   (deterministic: the same rows as all on one thread);
//! - `stage`: the row stage (solve, sink, latency);
//! - [`rig`]: the synthetic line (moving-web camera, emulated filter);
//! - [`recorded`]: the line configuration a recording stores, and the
//!   set-up rebuilt from it for a replay (the recording is then the frame
//!   source and the filter of [`run::run_line`]);
//! - [`stats`], [`recipe`], [`output`]: lane statistics, trend, Cp/Cpk,
//!   alarms, EXR strip segments, JSON messages to publishers;
//! - [`writer`]: the output worker (segment files and messages off the
//!   row path);
//! - [`mqtt`]: the MQTT publisher (bounded queue, delivery after reconnect).
//!
//! The layer sits beside [`crate::pipeline`] and reuses its pieces (the
//! camera trait, the sequencer, the calibrator, the solver). Registration
//! and accumulation read no clock (frame timestamps and encoder counts are
//! the web's time); only the latency measurement and the MQTT worker read
//! the wall clock.

pub mod accumulate;
pub mod angles;
pub mod geometry;
pub mod mqtt;
pub mod output;
pub mod recipe;
pub mod recorded;
pub mod rig;
pub mod run;
pub mod solve;
mod stage;
pub mod stats;
pub mod writer;

/// Errors of the line layer.
#[derive(Debug, thiserror::Error)]
pub enum LineError {
    /// A configuration that cannot work.
    #[error("line: {0}")]
    Config(String),
    /// The web is set to move faster than every row can be seen in every band.
    #[error(
        "line speed {speed:.2} rows/s is above the highest the optics allow, \
         {max:.2} rows/s ({rows_in_view} rows in view × {band_rate_hz:.2} bands/s / {n_bands} bands): \
         some rows would miss a band"
    )]
    TooFast {
        /// Requested speed, rows/s.
        speed: f64,
        /// Highest speed, rows/s.
        max: f64,
        /// Sensor rows that see the web.
        rows_in_view: usize,
        /// Bands per second.
        band_rate_hz: f64,
        /// Bands per sweep.
        n_bands: usize,
    },
    /// Encoder registration, but a frame carries no encoder count.
    #[error("a frame carries no encoder count (the line is registered by encoder)")]
    NoEncoder,
    /// The camera failed.
    #[error("camera: {0}")]
    Camera(crate::device::camera::CameraError),
    /// The filter or the sequencing failed.
    #[error("filter: {0}")]
    Sequencer(String),
    /// A row sink failed (writing, publishing).
    #[error("output: {0}")]
    Sink(String),
    /// A thread of the line died.
    #[error("line: the {0} thread panicked")]
    Panicked(String),
    /// The estimator could not be set up.
    #[error("estimator: {0}")]
    Estimate(crate::estimate::EstimateError),
}

// The causes are in the messages, so they are not also `source()`s (an
// error prints its source once).
impl From<crate::device::camera::CameraError> for LineError {
    fn from(e: crate::device::camera::CameraError) -> Self {
        LineError::Camera(e)
    }
}

impl From<crate::estimate::EstimateError> for LineError {
    fn from(e: crate::estimate::EstimateError) -> Self {
        LineError::Estimate(e)
    }
}
