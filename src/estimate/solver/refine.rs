//! Stage 3, the refinement: Levenberg–Marquardt on the thickness (and the
//! angle when unknown) with the exact model, and the profile bounds that
//! stand in for a linearised σ where it says little.

use super::{Fit, Scratch, Solver};
use crate::estimate::model::{FilmModel, ModelOut};

/// The smallest angle a free-angle refinement starts from (rad, ~3°).
pub(super) const MIN_FREE_THETA: f64 = 0.05;

impl Solver {
    /// Levenberg–Marquardt on thickness (and angle when `free_theta`),
    /// within the solver's thickness range.
    pub(super) fn refine(
        &self,
        model: &FilmModel,
        d0: f64,
        theta0: f64,
        free_theta: bool,
        iters: usize,
        s: &mut Scratch,
    ) -> Fit {
        let range = (self.d_min, self.d_max);
        self.refine_within(model, d0, theta0, free_theta, iters, range, s)
    }

    /// [`Solver::refine`] with the thickness held to `(d_lo, d_hi)` (the
    /// check for a film past the resolved range looks beyond it).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn refine_within(
        &self,
        model: &FilmModel,
        d0: f64,
        theta0: f64,
        free_theta: bool,
        iters: usize,
        (d_lo, d_hi): (f64, f64),
        s: &mut Scratch,
    ) -> Fit {
        let (lo, hi) = self.theta_range;
        let eval = |d: f64, th: f64, out: &mut ModelOut| {
            model.eval(d, th, out, true);
        };
        // R is even in θ: at normal incidence dR/dθ vanishes and the angle
        // could never leave it. A free angle starts a few degrees off (from
        // there the steps walk back to 0 where the data say so).
        let theta0 = if free_theta && theta0.abs() < MIN_FREE_THETA {
            MIN_FREE_THETA.min(hi).max(lo)
        } else {
            theta0
        };
        let (mut d, mut th) = (d0.clamp(d_lo, d_hi), theta0);
        eval(d, th, &mut s.cur);
        let mut cur_sse = sse(&s.spectrum, &s.weight, &s.cur.r);
        let mut mu = 1e-4;
        for _ in 0..iters {
            let (mut a, mut b, mut c, mut gd, mut gt) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for k in 0..s.spectrum.len() {
                let w = s.weight[k];
                let e = s.spectrum[k] - s.cur.r[k];
                let jd = s.cur.dr_dd[k];
                let jt = if free_theta { s.cur.dr_dth[k] } else { 0.0 };
                a += w * jd * jd;
                b += w * jd * jt;
                c += w * jt * jt;
                gd += w * jd * e;
                gt += w * jt * e;
            }
            let mut accepted = false;
            for _ in 0..6 {
                let (sd, st) = if free_theta {
                    let aa = a * (1.0 + mu) + 1e-12;
                    let cc = c * (1.0 + mu) + 1e-12;
                    let det = aa * cc - b * b;
                    if det <= 0.0 {
                        (gd / aa, 0.0)
                    } else {
                        ((cc * gd - b * gt) / det, (aa * gt - b * gd) / det)
                    }
                } else {
                    (gd / (a * (1.0 + mu) + 1e-12), 0.0)
                };
                // Never jump more than a quarter fringe in one step.
                let max_dd = 0.25 * 400.0 / (2.0 * model.n2_mid());
                let nd = (d + sd.clamp(-max_dd, max_dd)).clamp(d_lo, d_hi);
                let nt = (th + st.clamp(-0.1, 0.1)).clamp(lo, hi);
                eval(nd, nt, &mut s.trial);
                let new_sse = sse(&s.spectrum, &s.weight, &s.trial.r);
                if new_sse <= cur_sse {
                    // Converged once a step is far below the statistical error
                    // (σ_d ~ 0.3 nm, σ_θ ~ 1e-3 rad at the paper's noise) or
                    // the residual no longer moves.
                    let small = ((nd - d).abs() < 5e-3 && (nt - th).abs() < 2e-5)
                        || cur_sse - new_sse <= 1e-8 * cur_sse;
                    d = nd;
                    th = nt;
                    cur_sse = new_sse;
                    std::mem::swap(&mut s.cur, &mut s.trial);
                    mu = (mu * 0.3).max(1e-9);
                    accepted = !small;
                    break;
                }
                mu = (mu * 10.0).max(1e-3);
            }
            if !accepted {
                break;
            }
        }
        let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
        for k in 0..s.spectrum.len() {
            let w = s.weight[k];
            let jd = s.cur.dr_dd[k];
            let jt = if free_theta { s.cur.dr_dth[k] } else { 0.0 };
            a += w * jd * jd;
            b += w * jd * jt;
            c += w * jt * jt;
        }
        Fit {
            d,
            theta: th,
            sse: cur_sse,
            jtj: [a, b, c],
            integrated: false,
            tabled: false,
        }
    }

    /// One-sided profile bound on the thickness near zero: the smallest
    /// `δ > d` whose residual (angle held) exceeds the best by one variance,
    /// minus `d`.
    pub(super) fn profile_sigma_d(
        &self,
        model: &FilmModel,
        best: Fit,
        var: f64,
        s: &mut Scratch,
    ) -> f64 {
        let target = best.sse + var;
        let mut lo = best.d;
        let mut hi = best.d + 1.0;
        let mut grow = 0;
        loop {
            model.eval(hi, best.theta, &mut s.trial, false);
            if sse(&s.spectrum, &s.weight, &s.trial.r) > target || grow > 12 {
                break;
            }
            lo = hi;
            hi = best.d + 2.0 * (hi - best.d);
            grow += 1;
        }
        for _ in 0..20 {
            let mid = 0.5 * (lo + hi);
            model.eval(mid, best.theta, &mut s.trial, false);
            if sse(&s.spectrum, &s.weight, &s.trial.r) > target {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        0.5 * (lo + hi) - best.d
    }

    /// Whether the residual, the optical thickness held, stays within one
    /// variance of the best towards normal incidence beyond the linearised
    /// σ_θ: at the range's low end, or 3 σ_θ below the fit (R is even in
    /// θ, so near normal incidence the valley is flatter than its
    /// curvature at the fit says). Two model evaluations at most.
    pub(super) fn angle_valley_wider(
        &self,
        model: &FilmModel,
        best: Fit,
        var: f64,
        sig_th: f64,
        s: &mut Scratch,
    ) -> bool {
        let lo = self.theta_range.0;
        let g = best.d * model.q2_mid(best.theta);
        let target = best.sse + var;
        [lo, best.theta - 3.0 * sig_th]
            .into_iter()
            .filter(|&t| t >= lo && t < best.theta)
            .any(|t| {
                model.eval(g / model.q2_mid(t), t, &mut s.trial, false);
                sse(&s.spectrum, &s.weight, &s.trial.r) <= target
            })
    }

    /// Profile bound on a weak angle: the larger of the two distances from
    /// the fitted angle (within the search range) at which the residual,
    /// with the optical thickness `g = d·n2 cos θ2` held, exceeds the best
    /// by one variance; the range's extent if it never does.
    pub(super) fn profile_sigma_theta(
        &self,
        model: &FilmModel,
        best: Fit,
        var: f64,
        s: &mut Scratch,
    ) -> f64 {
        let (lo, hi) = self.theta_range;
        let g = best.d * model.q2_mid(best.theta);
        let target = best.sse + var;
        let mut bound: f64 = 0.0;
        for dir in [1.0, -1.0] {
            let limit = if dir > 0.0 {
                hi - best.theta
            } else {
                best.theta - lo
            };
            if limit <= 0.0 {
                continue;
            }
            let mut sse_at = |step: f64| {
                let t = best.theta + dir * step;
                model.eval(g / model.q2_mid(t), t, &mut s.trial, false);
                sse(&s.spectrum, &s.weight, &s.trial.r)
            };
            if sse_at(limit) <= target {
                bound = bound.max(limit);
                continue;
            }
            let (mut a, mut b) = (0.0, limit);
            for _ in 0..10 {
                let m = 0.5 * (a + b);
                if sse_at(m) > target {
                    b = m;
                } else {
                    a = m;
                }
            }
            bound = bound.max(0.5 * (a + b));
        }
        bound
    }
}

#[inline]
pub(super) fn sse(y: &[f64], w: &[f64], r: &[f64]) -> f64 {
    y.iter()
        .zip(w)
        .zip(r)
        .map(|((y, w), r)| w * (y - r) * (y - r))
        .sum()
}
