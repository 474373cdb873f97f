//! Estimation: per-pixel film thickness (and, where the scene leaves them
//! unknown, incidence angle and the film's index) from reflectance spectra.
//!
//! Pure numeric code: no I/O, no clock, no threads of its own (the caller
//! may run rows in parallel; [`Solver`] is `Sync`).
//!
//! - [`cube`]: the in-memory spectral cube (band-sequential reflectance).
//! - [`detect`]: fringe-extremum candidates of many pixels at once.
//! - [`maps`]: the parameter maps a fit produces, with validity reasons.
//! - [`noise`]: the reflectance noise model, independent of any fit.
//! - [`quality`]: the χ² test every pixel's fit must pass.
//! - [`level`]: the instrument's gain and offset, modelled where the data need it.
//! - [`range`]: the thickness range the bands resolve.
//! - [`solver`]: the per-pixel solver and the global film-index search.
//!
//! Only what the scene leaves unknown is estimated: a known angle, index or
//! material is used as given and the cheaper path is taken.
#![forbid(unsafe_code)]

pub mod angle;
pub mod cube;
pub mod detect;
pub mod fastmath;
mod lanes;
pub mod level;
pub mod maps;
pub mod model;
pub mod noise;
pub mod quality;
pub mod range;
pub mod solver;

pub use cube::{nan_reason, Cube, DARK_NAN, SATURATED_NAN};
pub use maps::{MapRowMut, ParamMaps, PixelEstimate, Reason};
pub use solver::{IndexEstimate, Solver};

/// Speed/accuracy trade-off of the per-pixel solver.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Mode {
    /// Closed forms on the fringe extrema: extrema located between bands in
    /// wavenumber, order from their spacing and the interference lattice,
    /// angle from the half-wave level, thickness from Eq. 14; σ propagated
    /// from the extrema fits. Pixels with fewer than two extrema fall back
    /// to the candidate search.
    Fast,
    /// The fast estimate as a start, then a joint Gauss–Newton /
    /// Levenberg–Marquardt refinement of the unknowns on the whole spectrum
    /// with the exact model; the full fringe-order search only where the
    /// closed form is unavailable or leaves residuals above the noise.
    Balanced,
    /// Balanced, refined to convergence, plus the best competing fringe
    /// order refined too (pixels where it fits as well are flagged
    /// "ambiguous order"), and passband integration where the band width
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
    /// The level model cannot be used as asked.
    #[error("level: {0}")]
    Level(String),
}
