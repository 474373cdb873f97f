//! The streaming pipeline: frames from a camera behind a tunable filter in,
//! thickness maps out, at line rate.
//!
//! - [`sequencer`]: pairs frames with bands (software-stepped or triggered),
//!   discards frames exposed while the filter settles, never shifts a frame
//!   onto the wrong band; the [`sequencer::BandTuner`] trait is all it needs
//!   of a filter.
//! - [`calibration`]: dark/white references, counts → reflectance, flags.
//! - [`tracker`]: per-sweep, per-pixel incremental state (planes, extrema).
//! - [`runner`]: threads, the lock-free frame ring, bounded channels, the
//!   overflow policy, the single-threaded deterministic mode.
//! - [`stage`]: the stages by name, and how a failing one stops the run.
//! - [`output`]: per-sweep EXR maps and summary lines.
//! - [`profile`]: a tracing layer that records stage latencies.
//!
//! The pipeline never reads the clock for anything that shapes a map:
//! pairing uses frame timestamps; wall time only measures latency.

pub mod calibration;
pub mod output;
pub mod profile;
pub mod runner;
pub mod sequencer;
pub mod stage;
pub mod tracker;
