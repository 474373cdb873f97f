//! `auto`'s hedge: a level the data hint at but do not establish.
//!
//! Where each pixel's angle (and the film index) is free, a gain trades
//! with them, so a white reference a few percent off lowers χ² too little
//! to pass `auto`'s test (p = 1e-4) and yet moves every thickness by
//! several σ: on the paper's cylinder a reference 3 % low left 99 % of the
//! pixels valid and 3.5 nm off. Neither choice is honest there: the
//! calibration trusted (σ too small) or the level taken on weak evidence
//! (twice the error on clean images).
//!
//! So below the test `auto` weighs three models by their evidence: the
//! calibration right (prior [`PRIOR_CALIBRATED`]), or off by one gain, or
//! by one offset, each error drawn from a normal slab of a few percent
//! ([`GAIN_SLAB`], [`OFFSET_SLAB`]). With the estimate `γ̂ ± σ` and
//! `Δχ² = γ̂²/σ²` the data's likelihood ratio, the Bayes factor of a slab
//! `ε` against the exact value is, for normal errors exactly,
//! `exp(½Δχ²·ε²/(ε² + σ²)) / √(1 + ε²/σ²)`. Every pixel is then fitted
//! under the posterior mixture as one level: its mean, and its covariance
//! `Σ w_m (Σ_m + (μ_m − μ)(μ_m − μ)ᵀ)` over the gain, the offset and the
//! film index, which each pixel's σ carries through its own fit
//! ([`crate::estimate::level::LevelShare`]). A clean image (Δχ² ~ 1)
//! weighs a level at a few percent, moves nothing and widens σ a little;
//! one whose evidence nears the test is mostly corrected, and σ spans what
//! is left of the doubt.

use super::index::SamplePixel;
use super::{IndexEstimate, Solver};
use crate::estimate::level::{Level, LevelBasis, LevelPixel};
use crate::estimate::EstimateError;
use crate::scene::FilmKnowledge;

/// Which look at the image a level fit is: the index sample's, after
/// which a level (or a hedge) is looked for again on a sample four times
/// larger, or that final one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Look {
    First,
    Final,
}

impl Look {
    /// The smallest weight of the two levels together for a hedge. On the
    /// first look, one in a hundred: a 3 % gain error on the paper's
    /// cylinder reads Δχ² ~ 4 on 400 pixels and ~ 15 on 1 600, so a hint
    /// there earns the larger sample (which nearly every image then takes:
    /// the prior alone weighs a level at ~1 %). On the final look, one in
    /// twenty, half the prior's: below it the data argue for the
    /// calibration, the mixture would move thicknesses by a few
    /// hundredths of a level's shift and widen σ by a few percent, and the
    /// image stays absolute (measured over 32 clean images: the mean
    /// |Δd| rose from 0.37 to 0.39 nm with a floor of 0.01).
    pub(super) fn min_weight(self) -> f64 {
        match self {
            Look::First => 0.01,
            Look::Final => 0.05,
        }
    }
}

/// Prior probability that the calibration is right (the rest split evenly
/// between a gain error and an offset error): a calibrated instrument is
/// trusted nine times in ten.
pub(super) const PRIOR_CALIBRATED: f64 = 0.9;

/// σ of a gain error when there is one: "a few percent" (a white
/// reference 3–8 % off, lamp drift).
pub(super) const GAIN_SLAB: f64 = 0.03;

/// σ of an offset error when there is one: stray light of a few tenths of
/// a percent of full reflectance.
pub(super) const OFFSET_SLAB: f64 = 0.005;

/// A mixture of levels weighed against the identity
/// ([`Solver::hedge_level`]).
pub(super) struct Hedge {
    /// The mixture as one level.
    pub level: Level,
    /// The index under the mixture (where it is estimated).
    pub est: IndexEstimate,
    /// The posterior weights of a gain error and of an offset error.
    pub weights: [f64; 2],
    /// The gain and the offset each fitted alone.
    pub fitted: [f64; 2],
    /// Their χ² below absolute's.
    pub delta_chi2: [f64; 2],
}

/// The Bayes factor (log) of a parameter drawn from a normal slab of σ
/// `slab` against its exact value 0, from its estimate's σ `sigma` and
/// the likelihood ratio `delta_chi2` (`γ̂²/σ²`).
pub(super) fn log_slab_factor(delta_chi2: f64, sigma: f64, slab: f64) -> f64 {
    if !(delta_chi2.is_finite() && sigma > 0.0 && slab > 0.0) {
        return f64::NEG_INFINITY;
    }
    let r = slab * slab / (sigma * sigma);
    0.5 * delta_chi2.max(0.0) * r / (1.0 + r) - 0.5 * (1.0 + r).ln()
}

/// Posterior weights of (calibrated, gain, offset) from the two levels'
/// log Bayes factors against the calibration.
pub(super) fn posterior(log_bf: [f64; 2]) -> [f64; 3] {
    let alt = 0.5 * (1.0 - PRIOR_CALIBRATED);
    let logs = [
        PRIOR_CALIBRATED.ln(),
        alt.ln() + log_bf[0],
        alt.ln() + log_bf[1],
    ];
    let top = logs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let e = logs.map(|l| (l - top).exp());
    let sum: f64 = e.iter().sum();
    e.map(|v| v / sum)
}

impl Solver {
    /// One gain and one offset, each fitted alone, weighed against the
    /// identity ([`posterior`]); the mixture where the two together reach
    /// the look's [`Look::min_weight`] and each is a plausible calibration error,
    /// `None` otherwise. `abs` are the sample's pixels fitted under the
    /// identity and `chi2_abs` their best χ² there. The film index (where
    /// unknown) is left at `est_abs`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn hedge_level(
        &mut self,
        sample: &[SamplePixel],
        abs: &[LevelPixel],
        chi2_abs: f64,
        est_abs: &IndexEstimate,
        wn: &[f64],
        var: &[f64],
        look: Look,
    ) -> Result<Option<Hedge>, EstimateError> {
        let unknown_index = matches!(self.scene.film, FilmKnowledge::Unknown { .. });
        let mut chi2_abs = chi2_abs;
        let mut fits = Vec::with_capacity(2);
        for basis in [LevelBasis::Gain, LevelBasis::Offset] {
            let (lv, chi2_start, chi2, est) =
                self.level_from_identity(sample, abs, basis, est_abs, wn, var)?;
            chi2_abs = chi2_abs.min(chi2_start);
            fits.push((lv, chi2, est));
        }
        if unknown_index {
            self.set_film_index(est_abs.clone())?;
        }
        let (g, o) = (&fits[0], &fits[1]);
        if !(g.0.is_plausible() && o.0.is_plausible())
            || g.0.share.n_params() != o.0.share.n_params()
        {
            return Ok(None);
        }
        let delta_chi2 = [chi2_abs - g.1, chi2_abs - o.1].map(|d| d.max(0.0));
        let sig = [g.0.share.cov_entry(0, 0), o.0.share.cov_entry(0, 0)].map(f64::sqrt);
        let w = posterior([
            log_slab_factor(delta_chi2[0], sig[0], GAIN_SLAB),
            log_slab_factor(delta_chi2[1], sig[1], OFFSET_SLAB),
        ]);
        let weight = w[1] + w[2];
        if weight.is_nan() || weight < look.min_weight() {
            return Ok(None);
        }
        // The three models' means and covariances over (gain − 1, offset,
        // index…).
        let extra = g.0.share.n_extra();
        let m = 2 + extra;
        let n_of = |e: &IndexEstimate| if unknown_index { e.n } else { 0.0 };
        let mut means = [vec![0.0; m], vec![0.0; m], vec![0.0; m]];
        let mut covs = [vec![0.0; m * m], vec![0.0; m * m], vec![0.0; m * m]];
        // The reflectance scale's share of the index's σ (a spectrum
        // table's accuracy ε: the index found again at 1 ± ε) stays apart,
        // as the pixels carry it through the two branches.
        let spread = est_abs
            .scale_branches
            .map_or(0.0, |b| 0.5 * (b[0] - b[1]).abs());
        if extra > 0 {
            means[0][2] = n_of(est_abs);
            covs[0][2 * m + 2] = (est_abs.sigma.powi(2) - spread * spread).max(0.0);
        }
        for (i, (lv, _, est)) in fits.iter().enumerate() {
            let (mean, cov) = (&mut means[i + 1], &mut covs[i + 1]);
            mean[0] = lv.gain[0] - 1.0;
            mean[1] = lv.offset[0];
            if extra > 0 {
                mean[2] = n_of(est);
            }
            // The fit's own parameters: its level parameter at `i`, the
            // extras after the level.
            let at = |j: usize| if j == 0 { i } else { 1 + j };
            let mj = lv.share.n_params();
            for j in 0..mj {
                for l in 0..mj {
                    cov[at(j) * m + at(l)] = lv.share.cov_entry(j, l);
                }
            }
        }
        let mu: Vec<f64> = (0..m)
            .map(|j| (0..3).map(|c| w[c] * means[c][j]).sum())
            .collect();
        let mut cov = vec![0.0; m * m];
        for c in 0..3 {
            for j in 0..m {
                for l in 0..m {
                    let dj = means[c][j] - mu[j];
                    let dl = means[c][l] - mu[l];
                    cov[j * m + l] += w[c] * (covs[c][j * m + l] + dj * dl);
                }
            }
        }
        let level = Level::gain_offset(
            1.0 + mu[0],
            mu[1],
            cov.clone(),
            extra,
            g.0.share.weights().to_vec(),
        );
        let mut est = est_abs.clone();
        if unknown_index {
            est.n = mu[2];
            est.sigma = cov[2 * m + 2].max(0.0).sqrt().hypot(spread);
            // The index's σ is in the mixture's covariance, which each
            // pixel's σ carries.
            est.sigma_in_level = true;
        }
        Ok(Some(Hedge {
            level,
            est,
            weights: [w[1], w[2]],
            fitted: [g.0.gain[0], o.0.offset[0]],
            delta_chi2,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_slab_factor_is_the_ratio_of_the_two_normal_likelihoods() {
        // γ̂ ~ N(0, σ²) under the exact value, N(0, σ² + ε²) under the
        // slab: their density ratio at γ̂, directly.
        let normal =
            |x: f64, v: f64| (-0.5 * x * x / v).exp() / (2.0 * std::f64::consts::PI * v).sqrt();
        for (g, s, e) in [
            (0.01, 0.0075, 0.03),
            (0.0, 0.002, 0.005),
            (0.05, 0.01, 0.03),
        ] {
            let direct = (normal(g, s * s + e * e) / normal(g, s * s)).ln();
            let ours = log_slab_factor((g / s) * (g / s), s, e);
            assert!(
                (direct - ours).abs() < 1e-9,
                "{g} {s} {e}: {direct} vs {ours}"
            );
        }
        assert_eq!(log_slab_factor(f64::NAN, 0.01, 0.03), f64::NEG_INFINITY);
        assert_eq!(log_slab_factor(4.0, 0.0, 0.03), f64::NEG_INFINITY);
    }

    #[test]
    fn the_posterior_weighs_the_prior_by_the_evidence() {
        // No evidence either way: the prior.
        let w = posterior([0.0, 0.0]);
        let alt = 0.5 * (1.0 - PRIOR_CALIBRATED);
        assert!((w[0] - PRIOR_CALIBRATED).abs() < 1e-12 && (w[1] - alt).abs() < 1e-12);
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        // Odds against the calibration move by the Bayes factor.
        let w = posterior([3.0, f64::NEG_INFINITY]);
        let odds = w[1] / w[0];
        assert!(
            (odds - alt / PRIOR_CALIBRATED * 3f64.exp()).abs() < 1e-9,
            "{odds}"
        );
        assert_eq!(w[2], 0.0);
        // Overwhelming evidence for a gain: the gain.
        assert!(posterior([200.0, 1.0])[1] > 0.999_999);
    }
}
