//! Stage 3, the refinement: Levenberg–Marquardt on the thickness (and the
//! angle when unknown) with the exact model — with the angle free in the
//! coordinates where its valley is straight (optical thickness, sin²θ),
//! and σ formed there — and the profile bound that stands in for a
//! linearised σ near zero thickness.

use super::{Fit, Scratch, Solver};
use crate::estimate::fastmath::sin_cos;
use crate::estimate::model::{FilmModel, ModelOut};
use multiversion::multiversion;

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
        // From where an earlier refinement left `cur` (the previous
        // pixel's fit: its warm start), that evaluation serves.
        match s
            .cur_at
            .filter(|c| c.serves(model.id(), d, th, (d_lo, d_hi), (lo, hi)))
        {
            Some(c) => (d, th) = c.at,
            None => eval(d, th, &mut s.cur),
        }
        let mut cur_sse = sse(&s.spectrum, &s.weight, &s.cur.r);
        let mut mu = 1e-4;
        // Never jump more than a quarter fringe in one step.
        let max_dd = 0.25 * 400.0 / (2.0 * model.n2_mid());
        let valley = Valley::new(model);
        let mut stalled = true;
        // The raw sums at (d, θ), while they are its.
        let mut final_sums = None;
        // The last step lowered the residual as its quadratic model said
        // (to 10 %): only then may the mode's looser rule stop the next.
        let mut quadratic = false;
        let near_zero = 0.1 * self.band_span().0;
        for _ in 0..iters {
            // With the angle free the steps are taken in (g, s): the
            // optical thickness g = d·n2·cos θ2 and s = sin²θ. The fringes
            // depend on d and θ almost only through g, so the valley of the
            // residual, a parabola in (d, θ) (d ∝ 1/cos θ2) whose width in d
            // is a thick film's σ_d (hundredths of a nm at 3 µm), is nearly
            // straight there; steps in (d, θ) overshoot its bend and crawl
            // (a 3 µm film at 9° stopped at 14.5°, 14 nm off, χ² 46 above
            // its minimum). R is smooth in s, so normal incidence is no
            // longer a point where the angle's slope vanishes.
            let jac = valley.jacobian(d, th, free_theta);
            let sums = raw_sums(s, free_theta);
            final_sums = Some(sums);
            let [a, b, c, gd, gt] = jac.apply_sums(sums);
            let mut accepted = false;
            for _ in 0..6 {
                let (sd, st) = if free_theta {
                    let aa = a * (1.0 + mu) + 1e-300;
                    let cc = c * (1.0 + mu) + 1e-300;
                    let det = aa * cc - b * b;
                    if det <= 0.0 {
                        (gd / aa, 0.0)
                    } else {
                        ((cc * gd - b * gt) / det, (aa * gt - b * gd) / det)
                    }
                } else {
                    (gd / (a * (1.0 + mu) + 1e-12), 0.0)
                };
                let (nd_free, nt_free) = valley.step(&jac, d, th, sd, st, max_dd, free_theta);
                let nd = nd_free.clamp(d_lo, d_hi);
                let nt = nt_free.clamp(lo, hi);
                // An undamped step already below the convergence
                // tolerance, or one that would lower χ² by a negligible
                // amount (to first order, the Gauss–Newton step lowers
                // the residual by the step times the gradient; a fit off
                // its minimum by `tolerance` variances is off by
                // √tolerance σ along any direction: 0.01 σ by the strict
                // rule): the fit stays where it is, sparing the evaluation
                // that would only confirm it.
                let predicted = sd * gd + st * gt;
                // The mode's looser rule only where the quadratic model has
                // just been borne out, the step is the model's own (not cut
                // at a bound) and the film lies clear of d = 0, where R is
                // even in d and no quadratic model holds.
                let loose = quadratic && nd == nd_free && nt == nt_free && d >= near_zero;
                let tolerance = if loose {
                    s.step_chi2.max(STEP_CHI2)
                } else {
                    STEP_CHI2
                };
                if mu <= 1e-3
                    && (((nd - d).abs() < 5e-3 && (nt - th).abs() < 2e-5)
                        || (self.min_noise_var > 0.0 && predicted < tolerance * self.min_noise_var))
                {
                    break;
                }
                eval(nd, nt, &mut s.trial);
                let new_sse = sse(&s.spectrum, &s.weight, &s.trial.r);
                if new_sse <= cur_sse {
                    // Converged once a step is far below the statistical error
                    // (σ_d ~ 0.3 nm, σ_θ ~ 1e-3 rad at the paper's noise) or
                    // the residual no longer moves.
                    let small = ((nd - d).abs() < 5e-3 && (nt - th).abs() < 2e-5)
                        || cur_sse - new_sse <= 1e-8 * cur_sse;
                    quadratic = mu <= 1e-3 && ((cur_sse - new_sse) / predicted - 1.0).abs() <= 0.1;
                    d = nd;
                    th = nt;
                    cur_sse = new_sse;
                    final_sums = None;
                    std::mem::swap(&mut s.cur, &mut s.trial);
                    mu = (mu * 0.3).max(1e-9);
                    accepted = !small;
                    break;
                }
                mu = (mu * 10.0).max(1e-3);
            }
            if !accepted {
                stalled = false;
                break;
            }
        }
        s.cur_at = Some(CurAt {
            model: model.id(),
            at: (d, th),
        });
        let [a, b, c, _, _] = final_sums.unwrap_or_else(|| raw_sums(s, free_theta));
        Fit {
            d,
            theta: th,
            sse: cur_sse,
            jtj: [a, b, c],
            tabled: false,
            stalled: stalled && iters > 0,
            // The model at the fit is in `cur`: its χ² costs one pass.
            chi2: self
                .judging()
                .then(|| self.chi2_and_noise_var(s, &s.cur.r))
                .filter(|c| c.0.is_finite()),
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
}

/// A refinement stops where its next step would lower χ² by less than
/// this (in noise variances; see `Solver::min_noise_var`): `accurate`'s
/// rule, and every mode's wherever its looser one does not apply.
pub(super) const STEP_CHI2: f64 = 1e-4;

/// `fast`'s: a fit within √0.1 = 0.32 σ of its minimum along any
/// direction.
pub(super) const FAST_STEP_CHI2: f64 = 1e-1;

/// `balanced`'s: within 0.1 σ (its variance at most 1 % above the
/// minimum's).
pub(super) const BALANCED_STEP_CHI2: f64 = 1e-2;

/// Where [`Scratch`]'s `cur` holds the model with its derivatives: left
/// there by a refinement of `model` (its id) that ended at `at`.
#[derive(Clone, Copy, Debug)]
pub(super) struct CurAt {
    model: u64,
    at: (f64, f64),
}

impl CurAt {
    /// Whether a refinement of `model` starting at `(d, θ)` within the
    /// given ranges may take `cur` as it is: the start is `at` (to
    /// rounding: a warm start's angle went through degrees and back, and
    /// a start that close is the same start), within the ranges.
    fn serves(&self, model: u64, d: f64, th: f64, dr: (f64, f64), tr: (f64, f64)) -> bool {
        self.holds(model, d, th)
            && (dr.0..=dr.1).contains(&self.at.0)
            && (tr.0..=tr.1).contains(&self.at.1)
    }

    /// Whether `cur` holds `model` at `(d, θ)` (to rounding).
    pub(super) fn holds(&self, model: u64, d: f64, th: f64) -> bool {
        let near = |a: f64, b: f64| (a - b).abs() <= 1e-9 * (1.0 + b.abs());
        self.model == model && near(d, self.at.0) && near(th, self.at.1)
    }
}

/// `Σ w (y − r)²`, in four independent lanes (a single sum waits on
/// each addition; four vectorise).
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn sse(y: &[f64], w: &[f64], r: &[f64]) -> f64 {
    let n = y.len().min(w.len()).min(r.len());
    let (y, w, r) = (&y[..n], &w[..n], &r[..n]);
    let mut acc = [0.0; 4];
    let whole = n - n % 4;
    for k0 in (0..whole).step_by(4) {
        for l in 0..4 {
            let e = y[k0 + l] - r[k0 + l];
            acc[l] += w[k0 + l] * e * e;
        }
    }
    for k in whole..n {
        let e = y[k] - r[k];
        acc[0] += w[k] * e * e;
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3])
}

/// The weighted sums of one Gauss–Newton step in `(d, θ)`: `[Σ w jd²,
/// Σ w jd jt, Σ w jt², Σ w jd e, Σ w jt e]`, `e = y − r`; with `theta`
/// false the angle's terms are 0 (its slope may not even be computed).
/// Four independent lanes, so the band loop vectorises.
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn normal_sums(y: &[f64], w: &[f64], r: &[f64], jd: &[f64], jt: &[f64], theta: bool) -> [f64; 5] {
    let n = y
        .len()
        .min(w.len())
        .min(r.len())
        .min(jd.len())
        .min(jt.len());
    let (y, w, r, jd, jt) = (&y[..n], &w[..n], &r[..n], &jd[..n], &jt[..n]);
    let mut acc = [[0.0; 4]; 5];
    let whole = n - n % 4;
    let term = |acc: &mut [[f64; 4]; 5], l: usize, k: usize| {
        let e = y[k] - r[k];
        let wd = w[k] * jd[k];
        // No NaN from a slope not computed.
        let t = if theta { jt[k] } else { 0.0 };
        acc[0][l] += wd * jd[k];
        acc[1][l] += wd * t;
        acc[2][l] += w[k] * t * t;
        acc[3][l] += wd * e;
        acc[4][l] += w[k] * t * e;
    };
    for k0 in (0..whole).step_by(4) {
        for l in 0..4 {
            term(&mut acc, l, k0 + l);
        }
    }
    for k in whole..n {
        term(&mut acc, 0, k);
    }
    acc.map(|a| (a[0] + a[1]) + (a[2] + a[3]))
}

/// The refinement's coordinates with the angle free: the optical thickness
/// `g = d·q(s)`, `q(s) = √(n2² − n1²·s)` at the middle band, and
/// `s = sin²θ`; with the angle known, `d` itself.
struct Valley {
    n1_sq: f64,
    n2_sq: f64,
}

/// The chain rule from `(∂R/∂d, ∂R/∂θ)` to the step's coordinates at one
/// point.
struct ValleyJacobian {
    /// `∂d/∂g` (1 with the angle known).
    dd_dg: f64,
    /// `∂d/∂s` at fixed `g`.
    dd_ds: f64,
    /// `∂θ/∂s`.
    dth_ds: f64,
    /// `s = sin²θ`, `sin θ`, `cos θ` and `g` at the point.
    s0: f64,
    sn: f64,
    cs: f64,
    g0: f64,
}

/// [`normal_sums`] of the current evaluation in `s`.
fn raw_sums(s: &Scratch, theta: bool) -> [f64; 5] {
    let c = &s.cur;
    normal_sums(&s.spectrum, &s.weight, &c.r, &c.dr_dd, &c.dr_dth, theta)
}

impl ValleyJacobian {
    /// The Gauss–Newton matrix and gradient in the step's coordinates,
    /// `[a, b, c, gd, gt]`, from the raw sums in `(d, θ)` ([`normal_sums`]):
    /// the chain rule of [`ValleyJacobian::apply`] taken on the sums (it is
    /// linear), not band by band.
    fn apply_sums(&self, [sdd, sdt, stt, gd, gt]: [f64; 5]) -> [f64; 5] {
        let g = self.dd_dg;
        if self.dth_ds == 0.0 {
            return [g * g * sdd, 0.0, 0.0, g * gd, 0.0];
        }
        let (u, v) = (self.dd_ds, self.dth_ds);
        [
            g * g * sdd,
            g * (u * sdd + v * sdt),
            u * u * sdd + 2.0 * u * v * sdt + v * v * stt,
            g * gd,
            u * gd + v * gt,
        ]
    }

    /// `(∂R/∂g, ∂R/∂s)` from `(∂R/∂d, ∂R/∂θ)` (with the angle known,
    /// `(∂R/∂d, 0)`).
    #[cfg(test)]
    fn apply(&self, jd: f64, jt: f64) -> (f64, f64) {
        if self.dth_ds == 0.0 {
            // The angle held: its slope may not even be computed.
            return (jd * self.dd_dg, 0.0);
        }
        (jd * self.dd_dg, jd * self.dd_ds + jt * self.dth_ds)
    }
}

/// The smallest angle a step in `s` lands on (rad): `∂θ/∂s` is infinite at
/// 0 while `∂R/∂θ` vanishes there, and their product, `∂R/∂s`, is finite;
/// a hair off zero both are finite (θ = 1e-6 rad reads 0.00006°).
const MIN_STEP_THETA: f64 = 1e-6;

/// σ of thickness and angle (rad) with the angle free, from the fit's
/// Gauss–Newton matrix `jtj` in (d, θ) and the residual variance `var`,
/// with the angle's search range `(lo, hi)` (its sin²θ, `(s_lo, s_hi)`,
/// the solver's, not worked out per pixel) as a uniform prior on sin²θ (a
/// flat direction gives a large, finite σ). The covariance is formed in
/// (g, s), where the model is nearly linear even at normal incidence (in θ
/// the thickness moves as θ² there and a linearised σ says nothing), and
/// carried to d = g/q(s); σ_θ is half the angle spanned by s ± σ_s.
pub(super) fn free_angle_sigma(
    model: &FilmModel,
    best: &Fit,
    var: f64,
    (lo, hi): (f64, f64),
    (s_lo, s_hi): (f64, f64),
) -> (f64, f64) {
    let v = Valley::new(model);
    let m = v.jacobian(best.d, best.theta, true);
    let [a, b, c] = best.jtj;
    // Mᵀ·JᵀJ·M with M = ∂(d, θ)/∂(g, s).
    let a2 = m.dd_dg * m.dd_dg * a;
    let b2 = m.dd_dg * (a * m.dd_ds + b * m.dth_ds);
    let c2 = m.dd_ds * m.dd_ds * a + 2.0 * m.dd_ds * m.dth_ds * b + m.dth_ds * m.dth_ds * c;
    let c2 = c2 + 12.0 / ((s_hi - s_lo) * (s_hi - s_lo)).max(1e-12) * var;
    let det = a2 * c2 - b2 * b2;
    if det.is_nan() || det <= 0.0 {
        return (f64::INFINITY, (hi - lo) / 12f64.sqrt());
    }
    // d = g/q(s): its variance through (∂d/∂g, ∂d/∂s) = (dd_dg, dd_ds).
    let var_d = var
        * (m.dd_dg * m.dd_dg * c2 - 2.0 * m.dd_dg * m.dd_ds * b2 + m.dd_ds * m.dd_ds * a2)
        / det;
    let sig_s = (var * a2 / det).sqrt();
    let s0 = best.theta.sin().powi(2);
    let th_at = |s: f64| s.clamp(0.0, 1.0).sqrt().asin();
    let sig_th = 0.5 * (th_at(s0 + sig_s) - th_at(s0 - sig_s));
    (var_d.max(0.0).sqrt(), sig_th)
}

impl Valley {
    fn new(model: &FilmModel) -> Valley {
        Valley {
            n1_sq: model.n1_mid() * model.n1_mid(),
            n2_sq: model.n2_mid() * model.n2_mid(),
        }
    }

    fn q(&self, s: f64) -> f64 {
        (self.n2_sq - self.n1_sq * s).max(1e-12).sqrt()
    }

    fn jacobian(&self, d: f64, th: f64, free_theta: bool) -> ValleyJacobian {
        if !free_theta {
            return ValleyJacobian {
                dd_dg: 1.0,
                dd_ds: 0.0,
                dth_ds: 0.0,
                s0: 0.0,
                sn: 0.0,
                cs: 1.0,
                g0: d,
            };
        }
        let (sn, cs) = sin_cos(th.max(MIN_STEP_THETA));
        let s0 = sn * sn;
        let q = self.q(s0);
        ValleyJacobian {
            dd_dg: 1.0 / q,
            dd_ds: d * self.n1_sq / (2.0 * q * q),
            dth_ds: 1.0 / (2.0 * sn * cs).max(1e-12),
            s0,
            sn,
            cs,
            g0: d * q,
        }
    }

    /// The point `(d, θ)` a step `(Δg, Δs)` leads to (with the angle known,
    /// `Δd`), the step shortened along its direction so that `d` moves at
    /// most `max_dd` and θ at most 0.1 rad.
    /// `at` is the point's [`Valley::jacobian`].
    #[allow(clippy::too_many_arguments)]
    fn step(
        &self,
        at: &ValleyJacobian,
        d: f64,
        th: f64,
        sd: f64,
        st: f64,
        max_dd: f64,
        free_theta: bool,
    ) -> (f64, f64) {
        if !free_theta {
            return (d + sd.clamp(-max_dd, max_dd), th);
        }
        let th = th.max(MIN_STEP_THETA);
        let (s0, g0, sn0, cs0) = (at.s0, at.g0, at.sn, at.cs);
        let at = |t: f64| {
            let s = (s0 + t * st).clamp(MIN_STEP_THETA * MIN_STEP_THETA, 1.0);
            // θ from the angle moved: sin(θ − θ0) = sin θ cos θ0 − cos θ sin θ0,
            // its arcsine by series for the usual small move (the next
            // term at 0.2 rad is 1e-8 rad; the pair evaluated is (d, θ)
            // either way), the library's beyond.
            let x = s.sqrt() * cs0 - (1.0 - s).max(0.0).sqrt() * sn0;
            let dth = if x.abs() < 0.2 {
                let x2 = x * x;
                x * (1.0 + x2 * (1.0 / 6.0 + x2 * (3.0 / 40.0 + x2 * (5.0 / 112.0))))
            } else {
                x.clamp(-1.0, 1.0).asin()
            };
            ((g0 + t * sd) / self.q(s), th + dth)
        };
        let (nd, nt) = at(1.0);
        let over = ((nd - d).abs() / max_dd).max((nt - th).abs() / 0.1);
        if over > 1.0 && over.is_finite() {
            at(1.0 / over)
        } else {
            (nd, nt)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The chain rule taken on the sums equals the step's sums formed band
    /// by band, with the angle free and held (a NaN slope where the angle
    /// is held is never read), and the lanes' `sse` equals the plain sum.
    #[test]
    fn the_sums_chain_rule_matches_band_by_band() {
        let n = 37; // not a multiple of four: the tail counts too
        let f = |k: usize, a: f64, b: f64| (a * k as f64 + b).sin();
        let y: Vec<f64> = (0..n).map(|k| 0.3 + 0.1 * f(k, 0.7, 0.1)).collect();
        let r: Vec<f64> = (0..n).map(|k| 0.3 + 0.1 * f(k, 0.69, 0.2)).collect();
        let w: Vec<f64> = (0..n)
            .map(|k| {
                if k == 5 {
                    0.0
                } else {
                    1.0 + 0.5 * f(k, 1.3, 0.0)
                }
            })
            .collect();
        let jd: Vec<f64> = (0..n).map(|k| 0.01 * f(k, 0.4, 1.0)).collect();
        let jt: Vec<f64> = (0..n).map(|k| 0.2 * f(k, 0.9, -0.3)).collect();
        let valley = Valley {
            n1_sq: 1.0,
            n2_sq: 1.46 * 1.46,
        };
        for free in [true, false] {
            let jac = valley.jacobian(812.0, 0.4, free);
            let jt_used: Vec<f64> = if free { jt.clone() } else { vec![f64::NAN; n] };
            let sums = normal_sums(&y, &w, &r, &jd, &jt_used, free);
            let got = jac.apply_sums(sums);
            let mut want = [0.0; 5];
            for k in 0..n {
                let (a, b) = jac.apply(jd[k], jt_used[k]);
                let e = y[k] - r[k];
                for (v, t) in want.iter_mut().zip([a * a, a * b, b * b, a * e, b * e]) {
                    *v += w[k] * t;
                }
            }
            for (g, w) in got.iter().zip(want) {
                assert!(
                    (g - w).abs() <= 1e-12 * (w.abs() + 1e-12),
                    "{free}: {got:?} vs {want:?}"
                );
            }
            assert_eq!(got[1] == 0.0 && got[2] == 0.0 && got[4] == 0.0, !free);
        }
        let plain: f64 = (0..n).map(|k| w[k] * (y[k] - r[k]).powi(2)).sum();
        assert!((sse(&y, &w, &r) - plain).abs() <= 1e-14 * plain);
    }
}
