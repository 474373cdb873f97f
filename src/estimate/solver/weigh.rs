//! Stage 4a, the bands weighed by their noise. Where the noise model gives
//! the bands different variances — a camera behind a tunable filter gets
//! 5–25× more light in the red than in the blue, a spectrometer's range
//! ends are noisier — the best fit, found with every band weighed alike
//! (the tables, the scans and the order checks weigh them so), is refined
//! once more with each band weighed by the inverse of its noise variance:
//! the efficient fit, whose σ is the weighted least-squares one. Unweighted
//! least squares loses ~1.23× in thickness error under a camera's noise
//! (`benches/live_solve.rs`).
//!
//! The weights are the instrument's noise at the fit's model values, not
//! at the data (weights that follow the noise would pull the fit towards
//! the bands that happened to read low), and without the reflectance
//! scale's accuracy: a scale error is common to every band and widens σ
//! by refits elsewhere (`Solver::widen_for_scale`), it is not noise to
//! average.

use super::table::ThicknessTable;
use super::{Fit, Scratch, Solver};
use crate::estimate::model::FilmModel;
use crate::estimate::noise::{band_var, NoiseModel};

/// Unweighted least squares' variance over the weighted one above which
/// the bands are weighed (see [`Solver::bands_weigh_differently`]).
const WEIGH_ABOVE: f64 = 1.02;

impl Solver {
    /// Whether the instrument's noise (the scale accuracy aside) differs
    /// enough between bands, or with the reflectance, for weights to
    /// matter. Unweighted least squares' variance over the weighted one is
    /// `(Σ J²v)(Σ J²/v)/(Σ J²)²`, which for equal slopes is
    /// `mean(v)·mean(1/v)`: weighed where that exceeds 1.02 (σ 1 % wider)
    /// at the reflectances 0.02 and 0.5, the variances of a
    /// band at those two counted as two bands. A noise estimated from the
    /// data per band scatters by ~1 % in σ (the index 1.0001–1.0004 on
    /// the scene matrix), where weighing would only cost time (read noise
    /// through a tunable filter: 25× in variance; a spectrometer's range
    /// ends: 10–100×).
    pub(super) fn bands_weigh_differently(&self) -> bool {
        self.noise.as_ref().is_some_and(|n| {
            let (mut sv, mut si, mut m) = (0.0, 0.0, 0.0);
            for k in 0..n.var0.len() {
                for r in [0.02, 0.5] {
                    let v = band_var(n.var0[k], n.shot[k], 0.0, r);
                    sv += v;
                    si += 1.0 / v;
                    m += 1.0;
                }
            }
            let spread = sv * si / (m * m);
            spread > WEIGH_ABOVE
        })
    }

    /// `best` refined with each band weighed by the inverse of its noise
    /// variance at `best`'s model values, and the harmonic mean of those
    /// variances over the bands used. The weights are scaled to a
    /// harmonic mean of 1, so the fit's residual and `JᵀJ` stay in that
    /// mean variance's units: `σ² = max(sse/dof, mean)/JᵀJ` is the
    /// weighted least-squares σ. The fit's `chi2` is its χ² against the
    /// full noise model and the bands' arithmetic mean variance, as every
    /// fit's is. `None` where the weights would all be equal, where
    /// nothing is judged, or where the weighted fit left `best`'s basin
    /// (more than `basin` nm away: the unweighted one already lies within
    /// a few σ of the weighted one, so such a move is no refinement).
    ///
    /// With the angle known, one Gauss–Newton step, on `table`'s
    /// interpolant where the fit was made on it, else with the exact model:
    /// the two fits lie a fraction of σ apart, where the model is linear
    /// to far below σ (a step's error goes as its square over the
    /// fringe's scale), so a second step would not move the fit. With the
    /// angle free, the refinement with the weights (its valley is curved).
    pub(super) fn weighed_fit(
        &self,
        model: &FilmModel,
        table: Option<&ThicknessTable>,
        best: &Fit,
        free_theta: bool,
        basin: f64,
        scratch: &mut Scratch,
    ) -> Option<(Fit, f64)> {
        let noise = self
            .noise
            .as_ref()
            .filter(|_| self.weigh_bands && self.judging())?;
        if noise.var0.len() != scratch.spectrum.len() {
            return None;
        }
        if free_theta {
            return self.weighed_refit(model, best, basin, scratch);
        }
        // The model and its slopes at the fit: where the refinement that
        // made it left them (`cur`, most fits off a table), else evaluated.
        let holds = scratch
            .cur_at
            .is_some_and(|c| c.holds(model.id(), best.d, best.theta));
        let range = match table {
            Some(t) => {
                t.interp(best.d, &mut scratch.trial.r, &mut scratch.trial.dr_dd);
                t.d_range()
            }
            None => {
                if !holds {
                    model.eval(best.d, best.theta, &mut scratch.trial, true);
                }
                (self.d_min, self.d_max)
            }
        };
        let at = if table.is_none() && holds {
            &scratch.cur
        } else {
            &scratch.trial
        };
        let (y, mask) = (&scratch.spectrum, &scratch.weight);
        let step = Step::at(noise, y, mask, &at.r, &at.dr_dd)?;
        let d = (best.d + step.g / step.a).clamp(range.0, range.1);
        if !(d.is_finite() && (d - best.d).abs() <= basin) {
            return None;
        }
        let chi2 = match (table, &self.flat_noise) {
            (Some(t), Some(flat)) => t.chi2_flat(d, y, mask, flat),
            (Some(t), None) => t.chi2_model(d, y, mask, noise),
            (None, _) => {
                scratch.cur_at = None;
                model.eval(d, best.theta, &mut scratch.cur, false);
                self.chi2_and_noise_var(scratch, &scratch.cur.r)
            }
        };
        // The residual after the step, to second order (the step lowers
        // it by g²/a), and JᵀJ at its start: both in the mean's units.
        let fit = Fit {
            d,
            sse: (step.sse - step.g * step.g / step.a).max(0.0) * step.mean_var,
            jtj: [step.a * step.mean_var, 0.0, 0.0],
            chi2: Some(chi2),
            ..*best
        };
        chi2.0.is_finite().then_some((fit, step.mean_var))
    }

    /// [`Solver::weighed_fit`] with the angle free: the refinement from
    /// `best` with the weights in `scratch.weight` (the mask restored
    /// after).
    fn weighed_refit(
        &self,
        model: &FilmModel,
        best: &Fit,
        basin: f64,
        scratch: &mut Scratch,
    ) -> Option<(Fit, f64)> {
        let noise = self.noise.as_ref()?;
        let n = scratch.spectrum.len();
        // The model at the fit: where the refinement that made it left it
        // (`cur`), else evaluated.
        let holds = scratch
            .cur_at
            .is_some_and(|c| c.holds(model.id(), best.d, best.theta));
        if !holds {
            model.eval(best.d, best.theta, &mut scratch.trial, false);
        }
        let at = if holds {
            &scratch.cur.r
        } else {
            &scratch.trial.r
        };
        // The mask of bands used, kept to restore.
        scratch.band_mask.clear();
        scratch.band_mask.extend_from_slice(&scratch.weight);
        let (mut inv_sum, mut used) = (0.0, 0.0);
        let bands = scratch.weight[..n]
            .iter_mut()
            .zip(&scratch.band_mask)
            .zip(at)
            .zip(noise.var0.iter().zip(&noise.shot));
        for (((w, &m), &r), (&var0, &shot)) in bands {
            *w = m / band_var(var0, shot, 0.0, r);
            inv_sum += *w;
            used += m;
        }
        if !(inv_sum > 0.0 && inv_sum.is_finite()) {
            scratch.weight.copy_from_slice(&scratch.band_mask);
            return None;
        }
        let mean_var = used / inv_sum;
        for w in &mut scratch.weight {
            *w *= mean_var;
        }
        let iters = super::Effort::of(self.mode).iters;
        // The refinement leaves the model at its fit in `cur`.
        let mut fit = self.refine(model, best.d, best.theta, true, iters, scratch);
        scratch.weight.copy_from_slice(&scratch.band_mask);
        if !(fit.sse.is_finite() && fit.d.is_finite() && (fit.d - best.d).abs() <= basin) {
            return None;
        }
        fit.chi2 =
            Some(self.chi2_and_noise_var(scratch, &scratch.cur.r)).filter(|c| c.0.is_finite());
        fit.chi2.is_some().then_some((fit, mean_var))
    }
}

/// The sums of one weighted Gauss–Newton step in the thickness, each band
/// weighed by the inverse of the instrument's variance at the model value.
struct Step {
    /// `Σ w J²`.
    a: f64,
    /// `Σ w J e`.
    g: f64,
    /// `Σ w e²`.
    sse: f64,
    /// The bands' harmonic-mean variance, `n / Σ 1/v`.
    mean_var: f64,
}

impl Step {
    /// The step's sums for spectrum `y` (bands used where `mask` is 1)
    /// against model values `r` with slopes `j`; `None` where no band
    /// carries a slope.
    fn at(noise: &NoiseModel, y: &[f64], mask: &[f64], r: &[f64], j: &[f64]) -> Option<Step> {
        let (mut a, mut g, mut sse, mut inv_sum, mut used) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for k in 0..y.len() {
            let w = mask[k] / band_var(noise.var0[k], noise.shot[k], 0.0, r[k]);
            let e = y[k] - r[k];
            a += w * j[k] * j[k];
            g += w * j[k] * e;
            sse += w * e * e;
            inv_sum += w;
            used += mask[k];
        }
        (a > 0.0 && a.is_finite() && inv_sum > 0.0).then(|| Step {
            a,
            g,
            sse,
            mean_var: used / inv_sum,
        })
    }
}
