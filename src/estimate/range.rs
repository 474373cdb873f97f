//! The thickness range the bands can resolve, from the physics of sampling.
//!
//! A film of optical thickness `g = n2·d·cos θ2` modulates reflectance as
//! `cos(4π g σ)` in wavenumber `σ = 1/λ`. Between two adjacent bands the
//! phase steps by `4π g Δσ`; past π the fringe is undersampled and aliases
//! onto a thinner film that fits about as well. And a band of width FWHM
//! averages the fringe down to a contrast
//! `A = exp(−(π·FWHM·2g/λ²)² / (4 ln 2))` (see `optics::band`): once little
//! is left, no fringe is seen at all. The thickest optical thickness irid
//! trusts is the smaller of the two limits; a pixel whose fit lands beyond
//! it is flagged "fringes unresolved", never reported.

use crate::optics::band::Band;

/// Largest phase step between adjacent bands irid trusts, radians: 80 % of
/// Nyquist's π, so a fringe just inside the range still has a few samples
/// per period where the bands are sparsest.
pub const MAX_PHASE_STEP_RAD: f64 = 0.8 * std::f64::consts::PI;

/// Smallest fringe contrast left after the passband that irid trusts.
pub const MIN_CONTRAST: f64 = 0.3;

/// What limits the optical thickness.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RangeLimit {
    /// The spacing of the bands (aliasing).
    Sampling,
    /// The passband width (fringe contrast).
    Passband,
}

/// The largest optical thickness `g` (nm) the band set resolves, and why.
pub fn max_optical_thickness(bands: &[Band]) -> (f64, RangeLimit) {
    let mut centers: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    centers.sort_by(f64::total_cmp);
    // The widest step in wavenumber between adjacent bands (the blue end for
    // bands evenly spaced in wavelength).
    let dsigma = centers
        .windows(2)
        .map(|w| 1.0 / w[0] - 1.0 / w[1])
        .filter(|d| *d > 0.0)
        .fold(0.0, f64::max);
    let g_sampling = if dsigma > 0.0 {
        MAX_PHASE_STEP_RAD / (4.0 * std::f64::consts::PI * dsigma)
    } else {
        f64::INFINITY
    };
    // Contrast A(g) ≥ MIN_CONTRAST on the band that loses it first.
    let k = (4.0 * std::f64::consts::LN_2 * (1.0 / MIN_CONTRAST).ln()).sqrt();
    let g_passband = bands
        .iter()
        .filter(|b| b.fwhm_nm > 0.0)
        .map(|b| k * b.center_nm * b.center_nm / (2.0 * std::f64::consts::PI * b.fwhm_nm))
        .fold(f64::INFINITY, f64::min);
    if g_passband < g_sampling {
        (g_passband, RangeLimit::Passband)
    } else {
        (g_sampling, RangeLimit::Sampling)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn bands(lo: f64, hi: f64, step: f64, fwhm: f64) -> Vec<Band> {
        let n = ((hi - lo) / step).round() as usize + 1;
        (0..n)
            .map(|i| Band::new(lo + step * i as f64, fwhm).unwrap())
            .collect()
    }

    #[test]
    fn sampling_limit_is_the_phase_step_at_the_sparsest_pair() {
        let b = bands(400.0, 700.0, 10.0, 0.0);
        let (g, why) = max_optical_thickness(&b);
        assert_eq!(why, RangeLimit::Sampling);
        // At that g the phase step between 400 and 410 nm is exactly the limit,
        // and every other pair steps less.
        let step = |a: f64, c: f64| 4.0 * PI * g * (1.0 / a - 1.0 / c);
        assert!((step(400.0, 410.0) - MAX_PHASE_STEP_RAD).abs() < 1e-9);
        assert!(step(690.0, 700.0) < MAX_PHASE_STEP_RAD);
        // 10 nm bands from 400 nm resolve ~3.3 µm of optical thickness, 5 nm twice that.
        assert!((3200.0..3400.0).contains(&g), "{g}");
        let (g5, _) = max_optical_thickness(&bands(400.0, 700.0, 5.0, 0.0));
        assert!((g5 / g - 2.0).abs() < 0.03, "{g5}");
    }

    #[test]
    fn a_wide_passband_limits_before_the_sampling() {
        // 1 nm steps but 20 nm wide bands: the contrast runs out first.
        let b = bands(400.0, 700.0, 1.0, 20.0);
        let (g, why) = max_optical_thickness(&b);
        assert_eq!(why, RangeLimit::Passband);
        // Second formulation: the band's own attenuation at that g.
        assert!((b[0].attenuation(g) - MIN_CONTRAST).abs() < 1e-9);
        assert!(b.iter().all(|x| x.attenuation(g) >= MIN_CONTRAST - 1e-12));
    }
}
