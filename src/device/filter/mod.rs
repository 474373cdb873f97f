//! The tunable-filter controller, behind a small trait.
//!
//! [`FilterController`] is what the pipeline uses: tune to a band and wait
//! until it has settled, define and run a sequence, query status, version and
//! reset. [`varispec::VariSpec`] implements it over a serial port for
//! VariSpec-protocol controllers (a real CRi VariSpec, or irid's emulated
//! firmware on a pseudo-terminal, see `lctf_firmware::emu`). [`reply`] is
//! the pure reply parser. Every call returns within a bound derived from the
//! configured timeouts; none waits forever.

pub mod reply;
pub mod varispec;

use std::time::Duration;

pub use reply::ReplyError;
pub use varispec::{VariSpec, VariSpecOptions};

/// What the controller says about itself (`V?`).
#[derive(Debug, Clone, PartialEq)]
pub struct ControllerInfo {
    /// Firmware revision.
    pub revision: String,
    /// Shortest tunable wavelength, nm.
    pub min_nm: f64,
    /// Longest tunable wavelength, nm.
    pub max_nm: f64,
    /// Serial number.
    pub serial: u32,
}

/// The controller's state (`@`, `!`, `W?`, `R?`, `Y?`).
#[derive(Debug, Clone, PartialEq)]
pub struct Status {
    /// The raw status byte.
    pub raw: u8,
    /// Initialisation (`I`) done.
    pub initialised: bool,
    /// Exercise (`E`) done.
    pub exercised: bool,
    /// A palette is defined.
    pub palette_defined: bool,
    /// The filter is moving or running `I`/`E`.
    pub busy: bool,
    /// The pending error code (0 = none).
    pub error_code: u8,
    /// The wavelength register, nm (`None`: no valid wavelength set).
    pub wavelength_nm: Option<f64>,
    /// Liquid-crystal temperature, °C.
    pub temperature_c: f64,
}

/// Errors of the filter-controller layer. Each quotes what the controller
/// sent, so a log line is enough to diagnose the line or the unit.
#[derive(Debug, thiserror::Error)]
pub enum FilterError {
    /// The serial port could not be opened or configured.
    #[error("cannot open serial port {port}: {source}")]
    Open {
        port: String,
        source: serialport::Error,
    },
    /// Reading or writing the port failed.
    #[error("serial I/O error: {0}")]
    Io(#[from] std::io::Error),
    /// Nothing (or not enough) arrived in time.
    #[error("timed out after {waited:?} waiting for {what}; received {got:?}")]
    Timeout {
        what: String,
        waited: Duration,
        got: String,
    },
    /// More than a reply's worth of bytes without a line end: line noise,
    /// a wrong baud rate, or a device that is not the controller.
    #[error("controller sent more than {limit} bytes without a line end while waiting for {what}; they began {head:?}")]
    LineTooLong {
        what: String,
        limit: usize,
        head: String,
    },
    /// The echo differs from the command (bytes lost or garbled on the line).
    #[error("controller echoed {echoed:?} to command {sent:?}")]
    Echo { sent: String, echoed: String },
    /// The reply could not be parsed.
    #[error("controller replied {reply:?} to {command:?}: {why}")]
    Reply {
        command: String,
        reply: String,
        why: ReplyError,
    },
    /// The controller reported an error code after a command.
    #[error("controller reported error {code} ({meaning}) after {command:?}")]
    Controller {
        command: String,
        code: u8,
        meaning: &'static str,
    },
    /// A requested wavelength lies outside the controller's range.
    #[error("{nm} nm is outside the filter's range {min_nm}-{max_nm} nm")]
    OutOfRange { nm: f64, min_nm: f64, max_nm: f64 },
    /// A sequence is empty or longer than the palette.
    #[error("sequence of {len} bands does not fit the 1..={max} palette")]
    Sequence { len: usize, max: usize },
    /// The filter is still busy when the wait ended.
    #[error("filter still busy after {0:?}")]
    NotSettled(Duration),
}

impl FilterError {
    /// Whether retrying the same idempotent command may succeed (line noise,
    /// a lost byte, a spurious error), as opposed to a definite answer.
    pub fn is_transient(&self) -> bool {
        matches!(
            self,
            Self::Timeout { .. }
                | Self::LineTooLong { .. }
                | Self::Echo { .. }
                | Self::Reply { .. }
                | Self::Controller { .. }
        )
    }
}

/// Meaning of a controller error code (VariSpec numbering).
pub fn error_meaning(code: u8) -> &'static str {
    lctf_firmware::ErrorCode::from_code(code).map_or("unknown error", |e| e.meaning())
}

/// A tunable-filter controller.
pub trait FilterController {
    /// Revision, range and serial number.
    fn version(&mut self) -> Result<ControllerInfo, FilterError>;
    /// Start tuning to `nm`; returns once the controller accepted it.
    fn set_wavelength(&mut self, nm: f64) -> Result<(), FilterError>;
    /// Wait until the filter has settled; returns the time from sending the
    /// last tuning command to the first "idle" answer (an upper bound on the
    /// true settle time, never below it).
    fn wait_settled(&mut self, timeout: Duration) -> Result<Duration, FilterError>;
    /// Tune and wait: the settle time.
    fn tune(&mut self, nm: f64, timeout: Duration) -> Result<Duration, FilterError> {
        self.set_wavelength(nm)?;
        self.wait_settled(timeout)
    }
    /// Load `wavelengths_nm` as the palette (entries 0..n), replacing it.
    fn define_sequence(&mut self, wavelengths_nm: &[f64]) -> Result<(), FilterError>;
    /// Tune to palette entry `idx`.
    fn select_palette(&mut self, idx: usize) -> Result<(), FilterError>;
    /// Let the sync input step through the palette, one entry every
    /// `every_nth` pulses (0 = sync input ignored).
    fn arm_sync(&mut self, every_nth: u16) -> Result<(), FilterError>;
    /// Advance the sequence by one step from software (`X`).
    fn trigger(&mut self) -> Result<(), FilterError>;
    /// Status flags, busy, pending error, wavelength and temperature.
    fn status(&mut self) -> Result<Status, FilterError>;
    /// Initialise (and exercise) if the controller needs it, waiting up to
    /// `timeout`.
    fn ensure_ready(&mut self, timeout: Duration) -> Result<(), FilterError>;
    /// Abort whatever runs, clear the pending error and resynchronise.
    fn reset(&mut self) -> Result<(), FilterError>;
}
