//! Fit quality: every pixel's residuals are judged by a χ² test against the
//! noise model ([`super::noise`]), never against the fit's own residual.
//!
//! Under the model and the noise model, a least-squares fit's
//! `χ² = Σ r_k²/σ_k²` follows a χ² distribution with `n − p` degrees of
//! freedom (`n` bands used, `p` parameters fitted). A pixel whose χ² exceeds
//! the upper [`FLAG_PROBABILITY`] quantile is flagged "poor fit": on clean
//! data that happens to about that fraction of pixels; a misfit (a wrong
//! order, a calibration error the model does not carry, a film the model
//! cannot describe) raises χ² and is flagged.

/// Upper-tail probability at which a clean pixel is flagged "poor fit".
/// Half a percent, so that a noise level estimated a few percent low still
/// flags clean data at most ~1 % of the time.
pub const FLAG_PROBABILITY: f64 = 0.005;

/// Standard normal quantile: `z` with `P(Z > z) = p_upper` (Acklam's
/// rational approximation refined by one Halley step; |error| < 1e-12).
pub fn normal_upper_quantile(p_upper: f64) -> f64 {
    let p = 1.0 - p_upper;
    if p <= 0.0 {
        return f64::NEG_INFINITY;
    }
    if p >= 1.0 {
        return f64::INFINITY;
    }
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    let x = if p < 0.02425 {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - 0.02425 {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    };
    // One Halley step on Φ(x) − p.
    let e = 0.5 * erfc(-x / std::f64::consts::SQRT_2) - p;
    let u = e * (2.0 * std::f64::consts::PI).sqrt() * (x * x / 2.0).exp();
    x - u / (1.0 + x * u / 2.0)
}

/// Complementary error function (W. J. Cody's rational approximations as
/// in Numerical Recipes' `erfcc`, |relative error| < 1.2e-7), enough for
/// one refinement step of the quantile.
fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let r = t
        * (-z * z - 1.265_512_23
            + t * (1.000_023_68
                + t * (0.374_091_96
                    + t * (0.096_784_18
                        + t * (-0.186_288_06
                            + t * (0.278_868_07
                                + t * (-1.135_203_98
                                    + t * (1.488_515_87
                                        + t * (-0.822_152_23 + t * 0.170_872_77)))))))))
            .exp();
    if x >= 0.0 {
        r
    } else {
        2.0 - r
    }
}

/// Upper quantile of the χ² distribution with `dof` degrees of freedom:
/// exact for 1 and 2, Wilson–Hilferty's cube-root normal approximation
/// above (relative error below 1 % from 3 degrees of freedom on).
pub fn chi2_upper_quantile(dof: f64, p_upper: f64) -> f64 {
    if dof <= 0.0 {
        return f64::INFINITY;
    }
    if dof == 1.0 {
        let z = normal_upper_quantile(0.5 * p_upper);
        return z * z;
    }
    if dof == 2.0 {
        return -2.0 * p_upper.ln();
    }
    let z = normal_upper_quantile(p_upper);
    let a = 2.0 / (9.0 * dof);
    dof * (1.0 - a + z * a.sqrt()).powi(3)
}

/// The χ² thresholds for every number of degrees of freedom up to a limit,
/// computed once.
#[derive(Clone, Debug)]
pub struct Chi2Test {
    thresholds: Vec<f64>,
    p_upper: f64,
}

impl Chi2Test {
    /// Thresholds at upper-tail probability `p_upper` for 1..=`max_dof`.
    pub fn new(max_dof: usize, p_upper: f64) -> Chi2Test {
        Chi2Test {
            thresholds: (0..=max_dof)
                .map(|k| chi2_upper_quantile(k as f64, p_upper))
                .collect(),
            p_upper,
        }
    }

    /// The test irid flags pixels with.
    pub fn flagging(max_dof: usize) -> Chi2Test {
        Chi2Test::new(max_dof, FLAG_PROBABILITY)
    }

    /// The threshold for `dof` degrees of freedom (∞ for none).
    #[inline]
    pub fn threshold(&self, dof: usize) -> f64 {
        match self.thresholds.get(dof) {
            Some(&t) => t,
            None => chi2_upper_quantile(dof as f64, self.p_upper),
        }
    }

    /// Whether `chi2` with `dof` degrees of freedom is consistent with noise.
    #[inline]
    pub fn passes(&self, chi2: f64, dof: usize) -> bool {
        chi2 <= self.threshold(dof)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    #[test]
    fn normal_quantiles_match_tables() {
        // Tabulated values (Abramowitz & Stegun 26.2).
        for (p, z) in [
            (0.5, 0.0),
            (0.1, 1.281_551_565_545),
            (0.025, 1.959_963_984_540),
            (0.01, 2.326_347_874_041),
            (0.005, 2.575_829_303_549),
            (0.001, 3.090_232_306_168),
            (0.9, -1.281_551_565_545),
        ] {
            assert!((normal_upper_quantile(p) - z).abs() < 1e-6, "p {p}");
        }
    }

    #[test]
    fn chi2_quantiles_match_tables() {
        // Upper 1 % points (Abramowitz & Stegun 26.8): exact for 1 and 2
        // degrees of freedom, within 1 % above.
        for (dof, q) in [
            (1.0, 6.634_897),
            (2.0, 9.210_340),
            (3.0, 11.344_867),
            (10.0, 23.209_251),
            (29.0, 49.587_884),
            (59.0, 87.165_680),
        ] {
            let got = chi2_upper_quantile(dof, 0.01);
            let tol = if dof <= 2.0 { 1e-5 } else { 0.01 };
            assert!((got / q - 1.0).abs() < tol, "dof {dof}: {got} vs {q}");
        }
    }

    #[test]
    fn simulated_chi2_is_flagged_at_the_nominal_rate() {
        // Independent of the approximation: sums of squared normal draws.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let test = Chi2Test::new(64, 0.01);
        for dof in [3usize, 29, 59] {
            let n = 40_000;
            let flagged = (0..n)
                .filter(|_| {
                    let c: f64 = (0..dof)
                        .map(|_| {
                            let z: f64 = StandardNormal.sample(&mut rng);
                            z * z
                        })
                        .sum();
                    !test.passes(c, dof)
                })
                .count();
            let rate = flagged as f64 / n as f64;
            // Binomial σ at 1 % over 40 000 draws: 0.05 %; Wilson–Hilferty
            // adds at most ~0.1 % here.
            assert!((rate - 0.01).abs() < 0.0025, "dof {dof}: {rate}");
        }
    }
}
