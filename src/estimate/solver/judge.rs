//! Judging a fit: the χ² test against the noise model (never against the
//! fit's own residual), the physical thickness range, the search bounds,
//! and data beyond anything the model can produce.

#![allow(clippy::needless_range_loop)] // band-indexed numeric loops read clearer with indices

use super::alternatives::WEAK_FRINGES;
use super::refine::MIN_FREE_THETA;
use super::table::ThicknessTable;
use super::{Prepared, Scratch, Solver, ANGLE_SIGMA_LIMIT_DEG};
use crate::estimate::lanes::{load, Chi2Lanes, F64x4};
use crate::estimate::noise::band_var4;
use crate::estimate::{PixelEstimate, Reason};
use multiversion::multiversion;

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

    /// `fast`'s closed form judged against the full model spectrum (in
    /// `s.spectrum`, all `n_ok` bands used): `Ok` with the estimate to
    /// report, or `Err((d, θ))` to refine from where it does not explain
    /// the spectrum (χ², a bound, a free angle at normal incidence where R
    /// is even in θ and the closed form's σ misses the angle's share).
    ///
    /// The closed form is not the least-squares fit. One Gauss–Newton step
    /// from it (noise-weighted, the model's derivatives at the same
    /// evaluation as χ²) says how far the fit lies: a step within a
    /// twentieth of a fringe is taken, and σ is the least-squares one
    /// there ((JᵀWJ)⁻¹ with the noise model's weights), widened by the
    /// Birge ratio where the χ² left after the step (to second order)
    /// exceeds its degrees of freedom (never narrowed); a longer step
    /// refines; σ_θ past the limit flags "angle not identifiable", as the
    /// closed form's own σ does, and fringes too shallow at the stepped
    /// angle flag "no fringe". Without the step, a
    /// closed form 3.8 nm off at 1200 nm (noise-free, angle free) claimed
    /// σ = 1.1 nm; with it `fast` reaches the bound on the paper's
    /// cylinder (mean error 0.365 nm against 0.68 nm).
    pub(super) fn judge_closed_form(
        &self,
        prep: &Prepared,
        mut fe: PixelEstimate,
        theta_known: Option<f64>,
        n_ok: usize,
        s: &mut Scratch,
    ) -> Result<PixelEstimate, (f64, f64)> {
        let (d, th) = (fe.thickness_nm, fe.theta_deg.to_radians());
        let free = theta_known.is_none();
        let n_par = if free { 2 } else { 1 };
        if free && th < MIN_FREE_THETA {
            return Err((d, th));
        }
        let Some(noise) = &self.noise else {
            return Ok(fe);
        };
        let mut t = std::mem::take(&mut s.trial);
        prep.model.eval(d, th, &mut t, true);
        let bands = JudgedBands {
            y: &s.spectrum,
            w: &s.weight,
            r: &t.r,
            jd: &t.dr_dd,
            jt: &t.dr_dth,
        };
        let ([a, b, c, gd, gt], (chi2, mean_var)) = match &self.flat_noise {
            Some(flat) => judged_sums_flat(bands, flat.parts(), free),
            None => judged_sums(bands, &noise.var0, &noise.shot, noise.rel2, free),
        };
        s.trial = t;
        let passes = self.fit_passes(chi2, n_ok, n_par);
        if !(passes && self.bound_reason(prep, d, th, theta_known).is_none()) {
            return Err((d, th));
        }
        if !fe.is_valid() {
            // Flagged by the closed form itself (a weak angle, no fringe),
            // on a spectrum it explains: the flag stands.
            return Ok(fe);
        }
        // The step and the least-squares covariance (the weights are the
        // noise model's: (JᵀWJ)⁻¹ is the covariance itself).
        let (sd, st, var_d, var_t) = if free {
            let det = a * c - b * b;
            if det > 0.0 {
                let step = ((c * gd - b * gt) / det, (a * gt - b * gd) / det);
                (step.0, step.1, c / det, a / det)
            } else {
                (f64::NAN, f64::NAN, f64::NAN, f64::NAN)
            }
        } else if a > 0.0 {
            (gd / a, 0.0, 1.0 / a, 0.0)
        } else {
            (f64::NAN, f64::NAN, f64::NAN, f64::NAN)
        };
        let (lam_min, _) = self.band_span();
        let fringe = lam_min / (2.0 * prep.model.q2_mid(th));
        let (nd, nt) = (d + sd, th + st);
        let (lo, hi) = self.theta_range;
        if !(sd.abs() <= 0.05 * fringe
            && (self.d_min..=self.d_max).contains(&nd)
            && (!free || (lo..=hi).contains(&nt)))
        {
            return Err((d, th));
        }
        // χ² after the step, to second order.
        let chi2 = (chi2 - (gd * sd + gt * st)).max(0.0);
        let birge = (chi2 / (n_ok - n_par).max(1) as f64).max(1.0).sqrt();
        let (sig_d, sig_t) = (birge * var_d.sqrt(), birge * var_t.sqrt().to_degrees());
        // The step may carry a free angle where the fringes fade (the
        // closed form tested visibility at its own angle): tested again
        // at the fit's.
        if free {
            let energy = self.fringe_energy(prep, nt, n_ok, mean_var);
            if energy < MIN_VISIBILITY {
                return Ok(PixelEstimate::invalid(Reason::NoFringe));
            }
            // Weak fringes with the angle free: another basin of (d, θ) —
            // a neighbouring order, a film far off at another angle — may
            // fit about as well, which only the full path's alternatives
            // weigh (σ_R = 0.03 on the paper's cylinder: 2.2 % of `fast`'s
            // valid pixels sat an order off, against `balanced`'s 0.2 %).
            let threshold = self.chi2.threshold(n_ok.saturating_sub(2).max(1));
            if energy < WEAK_FRINGES * threshold {
                return Err((nd, nt));
            }
        }
        // A weak angle as the closed form flags one, but by the full
        // model's σ: the closed form's own σ_θ, from the extrema's levels
        // alone, is wider (a pixel it flagged read Ok, σ_θ 0.22°, from the
        // previous pixel's fit in its row).
        fe.reason = if free && sig_t > ANGLE_SIGMA_LIMIT_DEG {
            Reason::AngleNotIdentifiable
        } else {
            Reason::Ok
        };
        fe.thickness_nm = nd;
        fe.theta_deg = nt.to_degrees();
        fe.sigma_thickness_nm = sig_d;
        fe.sigma_theta_deg = sig_t;
        Ok(fe)
    }

    /// χ² and the bands' mean noise variance of a fit on `table` (at its
    /// own angle) at `d`, whose residual on the interpolant is `sse`, with
    /// `n_ok` bands used and `n_par` parameters; `None` without a noise
    /// model. The fit left its residual on the very interpolant χ² would
    /// evaluate again: with one variance for every band χ² is that
    /// residual over it; with a variance per band their spread settles the
    /// test for most pixels of a complete spectrum; otherwise one pass
    /// over the bands (with a reflectance-dependent variance, the
    /// interpolant's values and χ² in one).
    pub(super) fn tabled_chi2(
        &self,
        table: &ThicknessTable,
        d: f64,
        sse: f64,
        (n_ok, n_par): (usize, usize),
        s: &Scratch,
    ) -> Option<(f64, f64)> {
        let noise = self.noise.as_ref()?;
        let Some(flat) = &self.flat_noise else {
            // Values and χ² under the reflectance-dependent noise in one
            // pass.
            return Some(table.chi2_model(d, &s.spectrum, &s.weight, noise));
        };
        if let Some((v, inv)) = flat.uniform() {
            return Some((sse * inv, v));
        }
        let complete = n_ok == s.weight.len();
        let threshold = self.chi2.threshold(n_ok.saturating_sub(n_par).max(1));
        flat.settle_complete(sse, threshold)
            .filter(|_| complete)
            .or_else(|| Some(table.chi2_flat(d, &s.spectrum, &s.weight, flat)))
    }

    /// Whether a fit with `chi2` over `n_ok` bands and `n_par` fitted
    /// parameters passes the test (always, when nothing is judged).
    pub(super) fn fit_passes(&self, chi2: f64, n_ok: usize, n_par: usize) -> bool {
        if !self.judging() {
            return true;
        }
        chi2.is_finite() && self.chi2.passes(chi2, n_ok.saturating_sub(n_par).max(1))
    }

    /// χ² of the spectrum in `s` (weights mark the bands used) against the
    /// reflectance `r`, each band weighted by the noise model's variance at
    /// the model value (NaN when no noise model is known), and the mean
    /// noise variance of those bands ([`Solver::noise_var`]), in one pass.
    /// (The image-wide level's own uncertainty is common to all pixels and
    /// mostly absorbed by each pixel's fit; it widens σ instead, see
    /// `Level::sigma_inflation`.)
    pub(super) fn chi2_and_noise_var(&self, s: &Scratch, r: &[f64]) -> (f64, f64) {
        match (&self.flat_noise, &self.noise) {
            (Some(flat), Some(_)) => flat.chi2_and_mean_var(&s.spectrum, &s.weight, r),
            (_, Some(noise)) => noise.chi2_and_mean_var(&s.spectrum, &s.weight, r),
            (_, None) => (f64::NAN, 0.0),
        }
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
        // q2 ≤ n2: most films are resolved whatever the angle, and skip it.
        if d * prep.model.n2_mid() > self.g_max.0 && d * prep.model.q2_mid(theta) > self.g_max.0 {
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
        // [`Solver::fringe_energy`] < MIN_VISIBILITY without its division
        // (`var` > 0; a NaN envelope compares false either way): on every
        // pixel's path, whose next step waited on it.
        let (h, q) = prep.envelopes_at(theta);
        let c = (h - q).abs();
        n_ok as f64 * c * c < MIN_VISIBILITY * 8.0 * var
    }

    /// The energy of the deepest fringe any thickness gives at `theta`
    /// over `n_ok` bands, in noise variances of `var`: `n_ok·c²/(8 var)`,
    /// `c` the envelopes' difference (NaN where they are not finite, which
    /// compares as neither invisible nor weak).
    pub(super) fn fringe_energy(&self, prep: &Prepared, theta: f64, n_ok: usize, var: f64) -> f64 {
        let (h, q) = prep.envelopes_at(theta);
        let c = (h - q).abs();
        n_ok as f64 * c * c / (8.0 * var)
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
        let margin = 0.1 * (hi - lo).max(0.01);
        if (lo - margin..=hi + margin).contains(&mean) {
            // Inside without the noise's share of the margin (σ ≥ 0 only
            // widens it): most pixels, spared a pass over the bands.
            return false;
        }
        let sigma = self.noise.as_ref().map_or(0.0, |n| n.typical_sigma(mean));
        let margin = margin + 5.0 * sigma;
        mean > hi + margin || mean < lo - margin
    }
}

/// One evaluation's bands for [`judged_sums`]: the spectrum `y` and its
/// weights `w` (0 drops a band), the model `r` and its slopes in d and θ.
#[derive(Clone, Copy)]
struct JudgedBands<'a> {
    y: &'a [f64],
    w: &'a [f64],
    r: &'a [f64],
    jd: &'a [f64],
    jt: &'a [f64],
}

impl JudgedBands<'_> {
    /// Bands every slice holds.
    fn len(&self) -> usize {
        self.y
            .len()
            .min(self.w.len())
            .min(self.r.len())
            .min(self.jd.len())
            .min(self.jt.len())
    }
}

/// The closed form's judgement summed four bands a step: χ², the noise
/// variances and the bands used as every χ² kernel sums them
/// ([`Chi2Lanes`]), and the Gauss–Newton sums, each band weighted by its
/// weight over its variance: `[Σ jd², Σ jd jt, Σ jt², Σ jd e, Σ jt e]`
/// (`e = y − r`).
struct JudgeLanes {
    chi2: Chi2Lanes,
    normal: [F64x4; 5],
}

impl JudgeLanes {
    /// Nothing summed yet.
    #[inline(always)]
    fn new() -> JudgeLanes {
        JudgeLanes {
            chi2: Chi2Lanes::new(),
            normal: [F64x4::ZERO; 5],
        }
    }

    /// Four bands: weights `w`, residuals `e`, slopes `jd` and `jt`, the
    /// variances `var` and their inverses `inv`.
    #[inline(always)]
    fn add(&mut self, w: F64x4, e: F64x4, (jd, jt): (F64x4, F64x4), var: F64x4, inv: F64x4) {
        self.chi2.add(w, e, var, inv);
        let wi = w * inv;
        let s = &mut self.normal;
        s[0] += wi * jd * jd;
        s[1] += wi * jd * jt;
        s[2] += wi * jt * jt;
        s[3] += wi * jd * e;
        s[4] += wi * jt * e;
    }

    /// The Gauss–Newton sums, each summed pairwise over its lanes, and χ²
    /// with the mean variance of the bands used.
    #[inline(always)]
    fn totals(self) -> ([f64; 5], (f64, f64)) {
        let normal = self.normal.map(|v| {
            let a = v.lanes_done();
            (a[0] + a[1]) + (a[2] + a[3])
        });
        (normal, self.chi2.sums().totals())
    }
}

/// Four values of `v` from `k`, those past `n` padded with `pad`.
#[inline(always)]
fn quad(v: &[f64], k: usize, n: usize, pad: f64) -> F64x4 {
    if k + 4 <= n {
        return load(&v[k..]);
    }
    let mut q = [pad; 4];
    for (l, x) in q.iter_mut().enumerate().take(n - k) {
        *x = v[k + l];
    }
    F64x4(q)
}

/// Four bands of `b` from band `k` (`[w, e, jd, jt, r]`; past `n` weight
/// 0, which adds nothing), with the angle's slope 0 unless `theta` (it
/// may not be computed).
#[inline(always)]
fn judged_quad(b: &JudgedBands, k: usize, n: usize, theta: bool) -> [F64x4; 5] {
    let r = quad(b.r, k, n, 0.0);
    let jt = if theta {
        quad(b.jt, k, n, 0.0)
    } else {
        F64x4::ZERO
    };
    [
        quad(b.w, k, n, 0.0),
        quad(b.y, k, n, 0.0) - r,
        quad(b.jd, k, n, 0.0),
        jt,
        r,
    ]
}

/// The sums of [`JudgeLanes`] over every band under a reflectance-dependent
/// noise model (`var0`, `shot`, `rel2`, as [`band_var4`] forms a band's
/// variance), four bands a step in `F64x4` lanes (the scalar band loop
/// had waited on each division in turn).
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn judged_sums(
    b: JudgedBands,
    var0: &[f64],
    shot: &[f64],
    rel2: f64,
    theta: bool,
) -> ([f64; 5], (f64, f64)) {
    let n = b.len().min(var0.len()).min(shot.len());
    let mut lanes = JudgeLanes::new();
    let rel = F64x4::splat(rel2);
    for k in (0..n).step_by(4) {
        let [w, e, jd, jt, r] = judged_quad(&b, k, n, theta);
        // Padding lanes: variance 1 (their weight 0 drops them).
        let var = band_var4(quad(var0, k, n, 1.0), quad(shot, k, n, 0.0), rel, r);
        lanes.add(w, e, (jd, jt), var, F64x4::ONE / var);
    }
    lanes.totals()
}

/// [`judged_sums`] where no variance depends on the reflectance: each
/// band's variance and its inverse given, no division.
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn judged_sums_flat(
    b: JudgedBands,
    (var, inv): (&[f64], &[f64]),
    theta: bool,
) -> ([f64; 5], (f64, f64)) {
    let n = b.len().min(var.len()).min(inv.len());
    let mut lanes = JudgeLanes::new();
    for k in (0..n).step_by(4) {
        let [w, e, jd, jt, _] = judged_quad(&b, k, n, theta);
        let (v, i) = (quad(var, k, n, 1.0), quad(inv, k, n, 1.0));
        lanes.add(w, e, (jd, jt), v, i);
    }
    lanes.totals()
}
