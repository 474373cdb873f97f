//! Filter bands (placeholder until the optics branch lands).

/// A filter band: centre and full width at half maximum, nm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Band {
    /// Centre wavelength, nm.
    pub center_nm: f64,
    /// Full width at half maximum, nm (0: an ideal, point-sampled band).
    pub fwhm_nm: f64,
}

impl Band {
    /// The band's response to a spectral function: a Gaussian passband
    /// average, or a point sample for an ideal band.
    pub fn integrate(&self, f: impl Fn(f64) -> f64) -> f64 {
        if self.fwhm_nm <= 0.0 {
            return f(self.center_nm);
        }
        // 3-point Gauss–Hermite (placeholder; the optics branch replaces it).
        let sigma = self.fwhm_nm / (8.0 * std::f64::consts::LN_2).sqrt();
        let h = (3.0f64).sqrt() * sigma;
        (f(self.center_nm - h) + 4.0 * f(self.center_nm) + f(self.center_nm + h)) / 6.0
    }
}

impl Band {
    /// Quadrature nodes `(wavelength_nm, weight)` of the passband (placeholder).
    pub fn nodes(&self) -> [(f64, f64); 3] {
        let sigma = self.fwhm_nm / (8.0 * std::f64::consts::LN_2).sqrt();
        let h = (3.0f64).sqrt() * sigma;
        [
            (self.center_nm - h, 1.0 / 6.0),
            (self.center_nm, 4.0 / 6.0),
            (self.center_nm + h, 1.0 / 6.0),
        ]
    }
}
