//! irid — live thin-film thickness maps from a camera behind a tunable filter.
//!
//! The crate is layered; each layer only uses the ones above it in this list:
//!
//! - [`optics`]: pure physics. Fresnel/Airy reflectance of a single film on a
//!   substrate, dispersion models, the material library, band passbands. No
//!   I/O, no clock, no threads.
//! - [`estimate`]: pure estimation. Per-pixel thickness / angle fits, the
//!   global film-index search, uncertainties and validity flags, the
//!   speed/accuracy modes.
//! - [`scene`]: the scene description (TOML) shared by `irid fit`, `irid synth`
//!   and `irid run`: what is known, what is estimated, and the synthetic truth.
//! - [`io`]: files. ENVI cubes, OpenEXR maps.
//! - [`device`]: hardware behind small traits: cameras ([`device::camera`]) and
//!   the tunable-filter controller ([`device::filter`]), each with a real, a
//!   synthetic/emulated and a fault-injecting implementation.
//! - [`pipeline`]: the streaming pipeline: sequencing frames onto bands,
//!   calibration, incremental per-pixel tracking, sweep solving, back-pressure.
//! - [`line`]: the production line: a moving web registered row by row
//!   (encoder or speed), per-web-row accumulation and solving, lane
//!   statistics, recipe alarms, EXR strip segments, MQTT publishing.
//! - [`render`]: pictures: maps as PNG with a colour bar, the film's colour
//!   (CIE 1931, D65, sRGB), the speed/accuracy and accuracy/noise charts.
//! - [`cli`]: the command-line front ends (`irid fit`, `irid run`, …).
//!
//! Time is always passed in, never read, below the [`cli`] layer, so tests and
//! replays are deterministic.

pub mod cli;
pub mod device;
pub mod estimate;
pub mod io;
pub mod line;
pub mod optics;
pub mod pipeline;
pub mod render;
pub mod scene;
pub mod synth;

/// The irid version, as written into output file headers.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
