//! Estimation: per-pixel film thickness (and, where the scene leaves them
//! unknown, incidence angle and the film's index) from reflectance spectra.
//!
//! Pure numeric code: no I/O, no clock, no threads of its own (the caller
//! may run rows in parallel; [`Solver`] is `Sync`).
//!
//! - [`cube`]: the in-memory spectral cube (band-sequential reflectance).
//! - [`maps`]: the parameter maps a fit produces, with validity reasons.
//! - [`solver`]: the per-pixel solver and the global film-index search.
//!
//! Only what the scene leaves unknown is estimated: a known angle, index or
//! material is used as given and the cheaper path is taken.
#![forbid(unsafe_code)]

pub mod cube;
pub mod fastmath;
pub mod maps;
pub mod model;
pub mod solver;

pub use cube::Cube;
pub use maps::{ParamMaps, PixelEstimate, Reason};
pub use solver::{IndexEstimate, Solver};

/// Speed/accuracy trade-off of the per-pixel solver.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Mode {
    /// Extrema only, closed forms: order from the fringe spacing, angle from
    /// the half-wave reflectance, thickness from the extremum wavelength.
    Fast,
    /// Interference-lattice candidates scored on the whole spectrum, then a
    /// Gauss–Newton refinement of the unknowns.
    Balanced,
    /// A denser candidate search, joint Levenberg–Marquardt refinement of all
    /// unknowns to convergence, passband integration where the band width
    /// matters.
    Accurate,
}

impl Mode {
    /// Lower-case name, as on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Mode::Fast => "fast",
            Mode::Balanced => "balanced",
            Mode::Accurate => "accurate",
        }
    }
}

/// Errors of the estimation layer (set-up problems; per-pixel trouble is a
/// [`Reason`], not an error).
#[derive(Debug, thiserror::Error)]
pub enum EstimateError {
    /// The band set is unusable.
    #[error("bands: {0}")]
    Bands(String),
    /// A medium's index cannot be evaluated at a band.
    #[error("{medium}: {source}")]
    Optics {
        /// Which medium.
        medium: &'static str,
        /// Cause.
        source: crate::optics::dispersion::OpticsError,
    },
    /// The cube and the angle map or mask disagree.
    #[error("{0}")]
    Shape(String),
    /// The global film-index search found no usable pixels.
    #[error("film index: {0}")]
    FilmIndex(String),
}
