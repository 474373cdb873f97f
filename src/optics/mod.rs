//! Thin-film optics: pure functions, no I/O, no clock.
//!
//! - [`airy`]: single-film reflectance by the Airy summation (paper Eq. 4–7),
//!   complex indices and complex cosines throughout, plus the real-coefficient
//!   fast path the estimators use.
//! - [`tmm`]: an independent characteristic-matrix (transfer-matrix)
//!   formulation, used to check [`airy`] and for transmittance.
//! - [`dispersion`]: constant, Cauchy, Sellmeier and tabulated n/k models.
//! - [`material`]: a material library that loads refractiveindex.info YAML.
//! - [`band`]: a filter band (centre, FWHM) and passband integration, with the
//!   criterion for when integrating matters.
//!
//! Conventions: wavelengths in nm, angles in radians (the CLI speaks degrees),
//! the time dependence is e^{-iωt} so an absorbing medium has `n + ik` with
//! `k ≥ 0` and normal wave-vector components are chosen with `Im ≥ 0`
//! (evanescent waves decay into the medium).
#![forbid(unsafe_code)]

pub mod airy;
pub mod band;
pub mod dispersion;
pub mod material;
pub mod tmm;

pub use num_complex::Complex64;

/// The polarisation state of the light the camera sees.
///
/// The observed reflectance is `w·R_s + (1 − w)·R_p` with `w` the s weight:
/// 1 for s, 0 for p, ½ for unpolarised light.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Polarization {
    /// Perpendicular (TE).
    S,
    /// Parallel (TM).
    P,
    /// Unpolarised: (R_s + R_p) / 2.
    Unpolarized,
    /// A partial mix with the given s weight in \[0, 1\].
    Mixed {
        /// Weight of R_s; R_p gets `1 − s_weight`.
        s_weight: f64,
    },
}

impl Polarization {
    /// The weight of R_s in the observed reflectance.
    pub fn s_weight(self) -> f64 {
        match self {
            Polarization::S => 1.0,
            Polarization::P => 0.0,
            Polarization::Unpolarized => 0.5,
            Polarization::Mixed { s_weight } => s_weight.clamp(0.0, 1.0),
        }
    }

    /// Parse `s`, `p`, `u` (or `unpolarized`), or a number in \[0, 1\] giving the s weight.
    pub fn parse(text: &str) -> Result<Self, String> {
        match text.trim().to_ascii_lowercase().as_str() {
            "s" | "te" => Ok(Polarization::S),
            "p" | "tm" => Ok(Polarization::P),
            "u" | "unpolarized" | "unpolarised" => Ok(Polarization::Unpolarized),
            other => match other.parse::<f64>() {
                Ok(w) if (0.0..=1.0).contains(&w) => Ok(Polarization::Mixed { s_weight: w }),
                _ => Err(format!(
                    "polarization must be s, p, u or an s weight in [0, 1], not {text:?}"
                )),
            },
        }
    }

    /// A short name for headers and summaries (`s`, `p`, `u`, or the s weight).
    pub fn name(self) -> String {
        match self {
            Polarization::S => "s".into(),
            Polarization::P => "p".into(),
            Polarization::Unpolarized => "u".into(),
            Polarization::Mixed { s_weight } => format!("{s_weight}"),
        }
    }
}

/// The three optical media of a single-film stack at one wavelength.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Media {
    /// Ambient (incidence medium), usually air.
    pub n1: Complex64,
    /// Film.
    pub n2: Complex64,
    /// Substrate (exit medium).
    pub n3: Complex64,
}

impl Media {
    /// Lossless media given by real indices.
    pub fn real(n1: f64, n2: f64, n3: f64) -> Self {
        Media {
            n1: Complex64::new(n1, 0.0),
            n2: Complex64::new(n2, 0.0),
            n3: Complex64::new(n3, 0.0),
        }
    }
}
