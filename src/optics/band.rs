//! A filter band (centre, FWHM) and integration of a spectral function over
//! its Gaussian passband, with the criterion for when integrating matters.
//!
//! # Passband and quadrature
//!
//! The tunable filter's passband is modelled as a Gaussian of standard
//! deviation `σ = FWHM / (2 sqrt(2 ln 2))`, normalised to unit area, so a
//! band measures `∫ R(λ) g(λ) dλ`. It is evaluated by 9-point Gauss–Hermite
//! quadrature: nodes `λc + sqrt(2) σ xᵢ` (outermost at ±4.51 σ = ±1.92 FWHM),
//! weights normalised to sum to 1. It is exact for polynomials in λ up to
//! degree 17. For a fringe `cos(2π λ/P + φ)` the remainder theorem bounds the
//! error by `u¹⁸ / (18!/9!) = u¹⁸ / 1.76·10¹⁰` (in units of the fringe
//! amplitude) with `u = 2πσ/P`:
//! below 6e-11 for a fringe period `P ≥ 2.7 FWHM` (u ≤ 1), below 1.5e-5 for
//! `P ≥ 1.33 FWHM` (u ≤ 2). Shorter periods than about one FWHM are washed
//! out by the passband to less than 5% of their amplitude and no longer
//! resolved by 9 nodes; a film that thick is outside what a band-sequential
//! camera can measure anyway.
//!
//! # When to integrate
//!
//! Near the band centre a film's fringe has phase `Δ(λ) = 4π g / λ`, with
//! `g = n2 d cos θ2` the optical thickness, so its local period in wavelength
//! is `P = λ² / (2 g)`. Averaging `cos Δ` over the Gaussian passband (phase
//! linear across the band) multiplies the fringe by
//!
//! ```text
//! A(g) = exp(−(2πσ/P)² / 2) = exp(−(π · FWHM · 2g / λ²)² / (4 ln 2))
//! ```
//!
//! Point sampling at the centre therefore errs by `a (1 − A) |cos Δc|`, where
//! `a` is the fringe's amplitude (half its peak-to-valley swing). The phase is
//! not quite linear in λ: its curvature `Δ'' = 8π g/λ³` shifts the averaged
//! fringe by `φ = Δ'' σ²/2 = 4π g σ²/λ³`, which dominates for thin films
//! (`φ ∝ g` while `1 − A ∝ g²`). Together, to first order in `φ`:
//!
//! ```text
//! point-sampling error ≤ a · ((1 − A) + A·φ)          (Band::point_sampling_error)
//! ```
//!
//! The rule: integrate when this exceeds `tolerance`, a reflectance error you
//! accept (e.g. a fraction of the noise σ_R). [`Band::needs_integration`] uses
//! the worst case `a = ½` (a fringe cannot swing more than 0 → 1);
//! [`Band::needs_integration_for`] takes the actual amplitude, which a caller
//! with the Fresnel coefficients has: `a = (R(cos Δ = 1) − R(cos Δ = −1)) / 2`.
//!
//! # How many nodes
//!
//! Rules of 3, 5 and 7 points are offered besides the 9-point one
//! ([`Band::nodes_of`]). The `n`-point rule's error on a pure fringe is
//! bounded by `u²ⁿ · n!/(2n)!`, but a film's reflectance is no pure
//! fringe: its harmonics (relative size `|r12 r23|^{k−1}`) run `k` times
//! faster and its phase `4πg/λ` is curved, and both are integrated worse
//! than the fundamental. So the estimator does not trust a bound: it
//! compares the film model on fewer nodes with the 9-point one where the
//! error is largest, and keeps the fewest that agree within its tolerance
//! (`estimate::solver`, `fewest_nodes`).
//!
//! Neglected: higher harmonics of `R(Δ)` (relative size `|r12 r23|`, and
//! attenuated faster, as `A^{k²}`), higher orders of the phase curvature, and
//! the much slower dispersion of the Fresnel coefficients. For `1 − A ≪ 1`, `1 − A ≈ (π · FWHM · 2g/λ²)²/(4 ln 2)`,
//! so the error grows as `g²`: e.g. FWHM 10 nm at 400 nm, `g` = 650 nm
//! (the paper's film) gives `1 − A ≈ 0.023`: with its fringe amplitude a ≈ 0.03
//! that is a 7e-4 reflectance error, comparable to the noise σ_R = 0.001.

use super::dispersion::OpticsError;

/// Number of quadrature nodes.
pub const N_NODES: usize = 9;

/// The largest possible fringe amplitude of a reflectance (a swing 0 → 1).
pub const MAX_FRINGE_AMPLITUDE: f64 = 0.5;

/// Gauss–Hermite abscissae `x` for the weight `e^{−x²}` (9 points).
const GH_X: [f64; N_NODES] = [
    -3.190_993_201_781_527_6,
    -2.266_580_584_531_843,
    -1.468_553_289_216_668,
    -0.723_551_018_752_837_6,
    0.0,
    0.723_551_018_752_837_6,
    1.468_553_289_216_668,
    2.266_580_584_531_843,
    3.190_993_201_781_527_6,
];

/// Gauss–Hermite weights divided by `sqrt(π)`, so they sum to 1.
const GH_W: [f64; N_NODES] = [
    2.2345844007746583e-05,
    0.002789141321231769,
    0.04991640676521787,
    0.24409750289493945,
    0.40634920634920635, // 128/315
    0.24409750289493945,
    0.04991640676521787,
    0.002789141321231769,
    2.2345844007746583e-05,
];

/// The Gauss–Hermite rules a model may integrate a band with, fewest
/// nodes first (odd, so the band centre is a node).
pub const RULES: [usize; 4] = [3, 5, 7, 9];

/// 3-, 5- and 7-point Gauss–Hermite abscissae and weights (÷ sqrt(π)).
const GH3: ([f64; 3], [f64; 3]) = (
    [-1.224_744_871_391_589, 0.0, 1.224_744_871_391_589],
    [1.0 / 6.0, 2.0 / 3.0, 1.0 / 6.0],
);
const GH5: ([f64; 5], [f64; 5]) = (
    [
        -2.020_182_870_456_085_6,
        -0.958_572_464_613_818_5,
        0.0,
        0.958_572_464_613_818_5,
        2.020_182_870_456_085_6,
    ],
    [
        0.011_257_411_327_720_693,
        0.222_075_922_005_612_6,
        0.533_333_333_333_333_3, // 8/15
        0.222_075_922_005_612_6,
        0.011_257_411_327_720_693,
    ],
);
const GH7: ([f64; 7], [f64; 7]) = (
    [
        -2.651_961_356_835_233_4,
        -1.673_551_628_767_471_4,
        -0.816_287_882_858_964_6,
        0.0,
        0.816_287_882_858_964_6,
        1.673_551_628_767_471_4,
        2.651_961_356_835_233_4,
    ],
    [
        0.000_548_268_855_972_218_2,
        0.030_757_123_967_586_51,
        0.240_123_178_605_012_73,
        0.457_142_857_142_857_13, // 16/35
        0.240_123_178_605_012_73,
        0.030_757_123_967_586_51,
        0.000_548_268_855_972_218_2,
    ],
);

/// FWHM / σ of a Gaussian: 2 sqrt(2 ln 2).
const FWHM_PER_SIGMA: f64 = 2.3548200450309493;

/// One spectral band of the tunable filter.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Band {
    /// Centre wavelength, nm.
    pub center_nm: f64,
    /// Full width at half maximum of the (Gaussian) passband, nm. Zero means
    /// an ideal monochromatic band.
    pub fwhm_nm: f64,
}

impl Band {
    /// A validated band: finite, `center > 0`, `fwhm ≥ 0`, and every
    /// quadrature node at a positive wavelength (`fwhm` below ≈ 0.52·centre).
    pub fn new(center_nm: f64, fwhm_nm: f64) -> Result<Self, OpticsError> {
        if !(center_nm.is_finite() && center_nm > 0.0) {
            return Err(OpticsError::Invalid(format!(
                "band centre must be finite and > 0 nm, got {center_nm}"
            )));
        }
        if !(fwhm_nm.is_finite() && fwhm_nm >= 0.0) {
            return Err(OpticsError::Invalid(format!(
                "band FWHM must be finite and ≥ 0 nm, got {fwhm_nm} (centre {center_nm} nm)"
            )));
        }
        let band = Band { center_nm, fwhm_nm };
        if band.nodes()[0].0 <= 0.0 {
            return Err(OpticsError::Invalid(format!(
                "band FWHM {fwhm_nm} nm is too wide for centre {center_nm} nm (passband reaches λ ≤ 0)"
            )));
        }
        Ok(band)
    }

    /// Standard deviation of the Gaussian passband, nm.
    pub fn sigma_nm(&self) -> f64 {
        self.fwhm_nm / FWHM_PER_SIGMA
    }

    /// Quadrature nodes `(wavelength_nm, weight)`, weights summing to 1, so
    /// callers can precompute indices or Fresnel coefficients per node.
    pub fn nodes(&self) -> [(f64, f64); N_NODES] {
        let h = std::f64::consts::SQRT_2 * self.sigma_nm();
        std::array::from_fn(|i| (self.center_nm + h * GH_X[i], GH_W[i]))
    }

    /// The nodes of the `n`-point rule (one of [`RULES`]; any other count
    /// above 1 takes the 9-point rule, 1 or less the band centre alone).
    pub fn nodes_of(&self, n: usize) -> Vec<(f64, f64)> {
        let (x, w): (&[f64], &[f64]) = match n {
            0 | 1 => return vec![(self.center_nm, 1.0)],
            3 => (&GH3.0, &GH3.1),
            5 => (&GH5.0, &GH5.1),
            7 => (&GH7.0, &GH7.1),
            _ => (&GH_X, &GH_W),
        };
        let h = std::f64::consts::SQRT_2 * self.sigma_nm();
        x.iter()
            .zip(w)
            .map(|(&x, &w)| (self.center_nm + h * x, w))
            .collect()
    }

    /// `∫ f(λ) g(λ) dλ` over the normalised Gaussian passband.
    pub fn integrate(&self, f: impl Fn(f64) -> f64) -> f64 {
        if self.fwhm_nm == 0.0 {
            return f(self.center_nm);
        }
        self.nodes().iter().map(|&(l, w)| w * f(l)).sum()
    }

    /// The factor `A(g)` by which the passband attenuates a fringe of a film
    /// with optical thickness `g = n2 d cos θ2` (nm) at this band; 1 means
    /// point sampling is exact.
    pub fn attenuation(&self, optical_thickness_nm: f64) -> f64 {
        let x = std::f64::consts::PI * self.fwhm_nm * 2.0 * optical_thickness_nm
            / (self.center_nm * self.center_nm);
        (-x * x / (4.0 * std::f64::consts::LN_2)).exp()
    }

    /// The phase shift `φ = 4π g σ² / λ³` (radians) the curvature of `Δ(λ)`
    /// gives the passband-averaged fringe.
    pub fn chirp_phase(&self, optical_thickness_nm: f64) -> f64 {
        let s = self.sigma_nm();
        4.0 * std::f64::consts::PI * optical_thickness_nm.abs() * s * s / self.center_nm.powi(3)
    }

    /// The largest error of sampling the fringe at the band centre instead
    /// of integrating: `a ((1 − A(g)) + A(g) φ(g))` for a fringe of amplitude `a`.
    pub fn point_sampling_error(&self, optical_thickness_nm: f64, fringe_amplitude: f64) -> f64 {
        let a = self.attenuation(optical_thickness_nm);
        fringe_amplitude.abs() * ((1.0 - a) + a * self.chirp_phase(optical_thickness_nm))
    }

    /// Whether point sampling could err by more than `tolerance` (a
    /// reflectance) for a film of optical thickness `g` nm, assuming the
    /// worst-case fringe amplitude ½. Non-finite input answers `true` (the
    /// safe side).
    pub fn needs_integration(&self, optical_thickness_nm: f64, tolerance: f64) -> bool {
        self.needs_integration_for(optical_thickness_nm, MAX_FRINGE_AMPLITUDE, tolerance)
    }

    /// As [`Band::needs_integration`] for a fringe of known amplitude `a`
    /// (half the peak-to-valley reflectance swing).
    pub fn needs_integration_for(
        &self,
        optical_thickness_nm: f64,
        fringe_amplitude: f64,
        tolerance: f64,
    ) -> bool {
        let e = self.point_sampling_error(optical_thickness_nm, fringe_amplitude);
        e.is_nan() || tolerance.is_nan() || e > tolerance
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_and_moments_are_those_of_a_gaussian() {
        // E[z^2k] of a standard normal is (2k − 1)!!; 9-point GH is exact to
        // degree 17, so moments up to z^16 must match to rounding.
        let b = Band::new(500.0, 10.0).unwrap();
        let s = b.sigma_nm();
        let mut dfact = 1.0;
        for k in 0..=8 {
            let m = b.integrate(|l| ((l - 500.0) / s).powi(2 * k));
            assert!(
                (m - dfact).abs() <= 1e-13 * dfact,
                "moment {}: {m} vs {dfact}",
                2 * k
            );
            let odd = b.integrate(|l| ((l - 500.0) / s).powi(2 * k + 1));
            assert!(odd.abs() <= 1e-12 * dfact.max(1.0));
            dfact *= (2 * k + 1) as f64;
        }
        assert!((b.integrate(|_| 0.37) - 0.37).abs() < 1e-15);
    }

    /// Every rule integrates the Gaussian's moments exactly up to degree
    /// 2n − 1 (the even ones are (2k − 1)!!), and misses the next even one:
    /// so its nodes and weights are those of the n-point rule.
    #[test]
    fn every_rule_has_the_moments_of_a_gaussian_to_its_degree() {
        let b = Band::new(500.0, 10.0).unwrap();
        let s = b.sigma_nm();
        for n in RULES {
            let nodes = b.nodes_of(n);
            assert_eq!(nodes.len(), n);
            let moment = |p: i32| -> f64 {
                nodes
                    .iter()
                    .map(|&(l, w)| w * ((l - 500.0) / s).powi(p))
                    .sum()
            };
            let mut dfact = 1.0;
            for k in 0..n {
                let m = moment(2 * k as i32);
                assert!(
                    (m - dfact).abs() <= 1e-12 * dfact,
                    "{n} nodes, moment {}: {m}",
                    2 * k
                );
                assert!(moment(2 * k as i32 + 1).abs() <= 1e-11 * dfact.max(1.0));
                dfact *= (2 * k + 1) as f64;
            }
            // Degree 2n: (2n − 1)!! exactly is beyond the rule.
            assert!(
                (moment(2 * n as i32) - dfact).abs() > 1e-3 * dfact,
                "{n} nodes"
            );
        }
        assert_eq!(b.nodes_of(1), vec![(500.0, 1.0)]);
    }

    #[test]
    fn fwhm_is_the_full_width_at_half_maximum() {
        let b = Band::new(500.0, 10.0).unwrap();
        let s = b.sigma_nm();
        let half = (-(5.0f64 * 5.0) / (2.0 * s * s)).exp();
        assert!((half - 0.5).abs() < 1e-15);
    }

    #[test]
    fn cos_fringe_matches_the_gaussian_attenuation() {
        // ∫ cos(2π(λ − λc)/P + φ) N(λc, σ²) dλ = cos φ · exp(−(2πσ/P)²/2),
        // to within the remainder bound u¹⁸ / (18!/9!).
        let b = Band::new(550.0, 12.0).unwrap();
        let s = b.sigma_nm();
        for p in [1e6, 200.0, 60.0, 30.0, 20.0, 15.0] {
            let u = 2.0 * std::f64::consts::PI * s / p;
            let bound = u.powi(18) / 17_643_225_600.0 + 1e-15;
            for phi in [0.0, 0.4, 1.3, 2.9] {
                let got =
                    b.integrate(|l| (2.0 * std::f64::consts::PI * (l - 550.0) / p + phi).cos());
                let want = phi.cos() * (-u * u / 2.0).exp();
                assert!(
                    (got - want).abs() <= bound,
                    "P = {p}, φ = {phi}: {got} vs {want}, bound {bound}"
                );
            }
        }
    }

    #[test]
    fn zero_width_band_point_samples_and_bad_bands_are_refused() {
        let b = Band::new(500.0, 0.0).unwrap();
        assert_eq!(b.integrate(|l| l * l), 250_000.0);
        assert!(!b.needs_integration(1e5, 1e-9));
        assert!(Band::new(f64::NAN, 10.0).is_err());
        assert!(Band::new(500.0, -1.0).is_err());
        assert!(Band::new(500.0, 400.0).is_err());
        assert!(Band::new(0.0, 1.0).is_err());
        let b = Band::new(500.0, 10.0).unwrap();
        assert!(b.needs_integration(f64::NAN, 1e-3));
    }

    #[test]
    fn criterion_grows_with_thickness_and_band_width() {
        let narrow = Band::new(450.0, 5.0).unwrap();
        let wide = Band::new(450.0, 20.0).unwrap();
        assert_eq!(narrow.attenuation(0.0), 1.0);
        assert!(!narrow.needs_integration(0.0, 1e-6));
        let mut last = 1.0;
        for g in [100.0, 300.0, 600.0, 1200.0] {
            let a = narrow.attenuation(g);
            assert!(a < last && wide.attenuation(g) < a);
            last = a;
        }
        // 1 − A ≈ (π FWHM 2g/λ²)²/(4 ln 2) for small arguments.
        let x = std::f64::consts::PI * 5.0 * 2.0 * 100.0 / (450.0f64 * 450.0);
        let approx = x * x / (4.0 * std::f64::consts::LN_2);
        assert!(((1.0 - narrow.attenuation(100.0)) / approx - 1.0).abs() < approx);
    }
}
