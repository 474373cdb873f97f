//! Dispersion models: how a medium's complex index varies with wavelength.
//!
//! Wavelengths are in nm at this interface; the refractiveindex.info formulas
//! take µm internally. A model built from a table or a file knows its valid
//! range and refuses wavelengths outside it.

use super::Complex64;

/// Errors of the optics layer.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum OpticsError {
    /// A wavelength outside a model's valid range.
    #[error("wavelength {wavelength_nm} nm is outside {what}'s valid range {min_nm}–{max_nm} nm")]
    OutOfRange {
        /// What was asked.
        wavelength_nm: f64,
        /// Name of the model or file.
        what: String,
        /// Lower limit.
        min_nm: f64,
        /// Upper limit.
        max_nm: f64,
    },
    /// A model that cannot be built or evaluated.
    #[error("{0}")]
    Invalid(String),
}

/// A wavelength-dependent complex refractive index `n + ik`.
#[derive(Clone, Debug, PartialEq)]
pub enum Dispersion {
    /// The same index at every wavelength.
    Constant(Complex64),
}

impl Dispersion {
    /// A lossless constant index.
    pub fn constant(n: f64) -> Self {
        Dispersion::Constant(Complex64::new(n, 0.0))
    }

    /// The complex index at `wavelength_nm`.
    pub fn index_at(&self, wavelength_nm: f64) -> Result<Complex64, OpticsError> {
        let _ = wavelength_nm;
        match self {
            Dispersion::Constant(n) => Ok(*n),
        }
    }

    /// The valid wavelength range in nm, if the model has one.
    pub fn range_nm(&self) -> Option<(f64, f64)> {
        match self {
            Dispersion::Constant(_) => None,
        }
    }
}
