//! Judging a fit: the χ² test against the noise model (never against the
//! fit's own residual), the physical thickness range, the search bounds,
//! and data beyond anything the model can produce.

#![allow(clippy::needless_range_loop)] // band-indexed numeric loops read clearer with indices

use super::{Prepared, Scratch, Solver};
use crate::estimate::model::FilmModel;
use crate::estimate::Reason;

/// How close to a bound of its search an estimate may come before it is
/// "pinned" there: a fraction of the searched span.
const BOUND_FRACTION: f64 = 1e-4;

/// The least fringe signal (in noise variances, see
/// [`Solver::film_invisible`]) a valid thickness needs: 25, a 5σ fringe.
pub(super) const MIN_VISIBILITY: f64 = 25.0;

impl Solver {
    /// Whether pixels are judged (a noise model is known).
    pub(super) fn judging(&self) -> bool {
        self.noise.is_some()
    }

    /// χ² of the spectrum in `s` (weights mark the bands used) against the
    /// reflectance `r`, each band weighted by the noise model's variance at
    /// the model value. NaN when no noise model is known. (The image-wide
    /// level's own uncertainty is common to all pixels and mostly absorbed
    /// by each pixel's fit; it widens σ instead, see `Level::sigma_inflation`.)
    pub(super) fn chi2_of(&self, s: &Scratch, r: &[f64]) -> f64 {
        let Some(noise) = &self.noise else {
            return f64::NAN;
        };
        let mut chi2 = 0.0;
        for k in 0..s.spectrum.len() {
            if s.weight[k] == 0.0 {
                continue;
            }
            let e = s.spectrum[k] - r[k];
            chi2 += s.weight[k] * e * e / noise.var(k, r[k]);
        }
        chi2
    }

    /// χ² of the model at `(d, θ)` (evaluated into `s.trial`).
    pub(super) fn chi2_at(&self, model: &FilmModel, d: f64, theta: f64, s: &mut Scratch) -> f64 {
        let mut trial = std::mem::take(&mut s.trial);
        model.eval(d, theta, &mut trial, false);
        let c = self.chi2_of(s, &trial.r);
        s.trial = trial;
        c
    }

    /// Whether a fit with `chi2` over `n_ok` bands and `n_par` fitted
    /// parameters passes the test (always, when nothing is judged).
    pub(super) fn fit_passes(&self, chi2: f64, n_ok: usize, n_par: usize) -> bool {
        if !self.judging() {
            return true;
        }
        chi2.is_finite() && self.chi2.passes(chi2, n_ok.saturating_sub(n_par).max(1))
    }

    /// The mean noise variance of the bands used, at the
    /// fitted reflectance `r`: the floor under a fit's residual variance
    /// when σ is computed, so a lucky small residual never claims more
    /// precision than the instrument has.
    pub(super) fn noise_var(&self, s: &Scratch, r: &[f64]) -> f64 {
        let Some(noise) = &self.noise else {
            return 0.0;
        };
        let (mut v, mut n) = (0.0, 0.0);
        for k in 0..s.spectrum.len() {
            if s.weight[k] != 0.0 {
                v += noise.var(k, r[k]);
                n += 1.0;
            }
        }
        if n > 0.0 {
            v / n
        } else {
            0.0
        }
    }

    /// A flag for an estimate outside the range the bands resolve or pinned
    /// at a bound of its search.
    pub(super) fn bound_reason(
        &self,
        prep: &Prepared,
        d: f64,
        theta: f64,
        theta_known: Option<f64>,
    ) -> Option<Reason> {
        let g = d * prep.model.q2_mid(theta);
        if g > self.g_max.0 {
            return Some(Reason::Unresolved);
        }
        let span = (self.d_max - self.d_min).max(1.0);
        if self.d_max_given && d >= self.d_max - BOUND_FRACTION * span {
            return Some(Reason::AtBound);
        }
        if self.d_min > 0.0 && d <= self.d_min + BOUND_FRACTION * span {
            return Some(Reason::AtBound);
        }
        if theta_known.is_none() {
            let (lo, hi) = self.theta_range;
            let eps = BOUND_FRACTION * (hi - lo).max(1e-6);
            // Normal incidence is a natural end (R is even in θ), not a bound.
            if theta >= hi - eps || (lo > 0.0 && theta <= lo + eps) {
                return Some(Reason::AtBound);
            }
        }
        None
    }

    /// Whether the film's fringes at `theta` are too shallow for `n_ok`
    /// bands at noise variance `var` to place them: the deepest modulation
    /// any thickness can give (half- against quarter-wave level, peak to
    /// peak `c`) carries `n_ok·c²/8` of signal energy, and below
    /// [`MIN_VISIBILITY`] noise variances no fringe order can be told from
    /// another (a film index close to the ambient's or the substrate's, p
    /// light near Brewster's angle). The linearised σ then claims a
    /// precision the data do not have. (Asking for the χ² test's threshold
    /// instead, ~50 at 31 bands, also flagged a film out of range seen
    /// through an index-matched interface near Brewster's angle, but took
    /// every valid pixel of the thin coating at σ = 0.01, whose fits were
    /// right: 1.24× the Cramér–Rao bound, 95 % within 2σ.)
    pub(super) fn film_invisible(
        &self,
        prep: &Prepared,
        theta: f64,
        n_ok: usize,
        var: f64,
    ) -> bool {
        if !(self.judging() && var > 0.0 && theta.is_finite()) {
            return false;
        }
        let (h, q) = prep.envelopes_at(theta);
        let c = (h - q).abs();
        c.is_finite() && n_ok as f64 * c * c / (8.0 * var) < MIN_VISIBILITY
    }

    /// Whether a spectrum with this mean lies beyond anything the model can
    /// produce (e.g. a cube that is not reflectance): outside the model's
    /// envelope range by more than a tenth of it and five noise σ.
    pub(super) fn out_of_model(&self, prep: &Prepared, mean: f64, theta: Option<f64>) -> bool {
        // At a known angle the levels a film can reach are that angle's
        // envelopes; at an unknown one, any angle's.
        let (lo, hi) = match theta {
            Some(t) if t.is_finite() => {
                let (h, l) = prep.envelopes_at(t);
                (h.min(l), h.max(l))
            }
            _ => prep.envelope_range,
        };
        if !(lo.is_finite() && hi.is_finite()) {
            return false;
        }
        let sigma = self.noise.as_ref().map_or(0.0, |n| n.typical_sigma(mean));
        let margin = 0.1 * (hi - lo).max(0.01) + 5.0 * sigma;
        mean > hi + margin || mean < lo - margin
    }
}
