//! One pixel's path through the stages: the closed-form start (refined,
//! its order checked), else the fringe search, the angle start and the
//! refinement of the best starts; then the checks (stage 4): best fit,
//! covariance, validity flags.

use super::alternatives::OrderMargin;
use super::angle_grid;
use super::closed_form::angle_start;
use super::fringes::AMBIGUITY_CHI2;
use super::poor::{FREE_ANGLE, FREE_MARGIN, FREE_RUN};
use super::refine::{free_angle_sigma, sse};
use super::search::{Candidate, MAX_CANDIDATES};
use super::table::ORDER_GAP_SAFE;
use super::{Effort, Fit, Job, Prepared, Scratch, Solver, ANGLE_SIGMA_LIMIT_DEG};
use crate::estimate::model::FilmModel;
use crate::estimate::{PixelEstimate, Reason};
use multiversion::multiversion;
use std::f64::consts::PI;
use wide::f64x4;

/// What the warm start needs of its pixel (see [`Solver::try_warm`]).
#[derive(Clone, Copy)]
struct WarmJob {
    theta_known: Option<f64>,
    n_ok: usize,
    noise: Option<f64>,
    effort: super::Effort,
    /// The pixel solves alone (no candidates found for it by the caller).
    alone: bool,
    /// The previous pixel's neighbouring-order margin in the row.
    prev_margin: Option<OrderMargin>,
}

/// A pixel's spectrum into `y` and its weights into `w` (finite values
/// weighted 1, the rest 0 and weighted 0): the bands used, whether any
/// lies beyond a reflectance, and their sum. Compiled for the best vector
/// unit, in one pass of four lanes (the sum in four partial sums, band k
/// into lane k mod 4, the bands past the last four summed in turn: one
/// running sum is a chain of dependent additions), the tail band by band.
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn load_spectrum(spectrum: &[f64], y: &mut [f64], w: &mut [f64]) -> (usize, bool, f64) {
    let n = spectrum.len().min(y.len()).min(w.len());
    let (spectrum, y, w) = (&spectrum[..n], &mut y[..n], &mut w[..n]);
    let mut acc = f64x4::ZERO;
    let (mut n_ok, mut beyond) = (0u32, 0u32);
    let (lo, hi) = (f64x4::splat(-0.2), f64x4::splat(1.2));
    let quads = spectrum
        .chunks_exact(4)
        .zip(y.chunks_exact_mut(4).zip(w.chunks_exact_mut(4)));
    for (s, (y, w)) in quads {
        // Branch-free in vector lanes: a finite value's mask is all ones,
        // the rest zero (a compare per lane had compiled to scalar
        // branches).
        let s = f64x4::new([s[0], s[1], s[2], s[3]]);
        let finite = s.is_finite();
        let v = s & finite;
        let inside = v.simd_ge(lo) & v.simd_le(hi);
        beyond |= (finite & !inside).to_bitmask();
        n_ok += finite.to_bitmask().count_ones();
        y.copy_from_slice(&v.to_array());
        w.copy_from_slice(&(finite & f64x4::ONE).to_array());
        acc += v;
    }
    let (mut ok_tail, mut beyond_tail) = (0u32, false);
    for k in n - n % 4..n {
        let v = spectrum[k];
        let ok = v.is_finite();
        beyond_tail |= ok & !(-0.2..=1.2).contains(&v);
        y[k] = if ok { v } else { 0.0 };
        w[k] = if ok { 1.0 } else { 0.0 };
        ok_tail += u32::from(ok);
    }
    let tail: f64 = y[n - n % 4..].iter().sum();
    let acc = acc.to_array();
    (
        (n_ok + ok_tail) as usize,
        beyond != 0 || beyond_tail,
        (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail,
    )
}

impl Solver {
    /// Solve one pixel against a prepared index; returns the estimate (with
    /// σ from the fit alone) and its residual sum of squares.
    pub(super) fn solve_with(
        &self,
        prep: &Prepared,
        job: Job<'_>,
        scratch: &mut Scratch,
    ) -> (PixelEstimate, f64) {
        let Job {
            spectrum,
            theta_known,
            noise,
            effort,
            pre,
            start: job_start,
        } = job;
        scratch.last_fit_d = f64::NAN;
        scratch.last_fit_theta = f64::NAN;
        scratch.step_chi2 = effort.step_chi2;
        let nb = self.bands.len();
        if spectrum.len() != nb {
            return (PixelEstimate::invalid(Reason::MissingBands), f64::NAN);
        }
        scratch.ensure(nb);
        let (n_ok, beyond, sum) =
            load_spectrum(spectrum, &mut scratch.spectrum, &mut scratch.weight);
        if beyond {
            return (PixelEstimate::invalid(Reason::OutOfModel), f64::NAN);
        }
        if n_ok == 0 {
            return (PixelEstimate::invalid(Reason::NonFinite), f64::NAN);
        }
        // Judged against the noise model once one is known (not while the
        // global index is searched: the caller passes no noise then).
        let judging = noise.is_some() && self.judging();
        if judging {
            let mean = sum / n_ok as f64;
            if self.out_of_model(prep, mean, theta_known) {
                return (PixelEstimate::invalid(Reason::OutOfModel), f64::NAN);
            }
        }
        let n_par = if theta_known.is_some() { 1 } else { 2 };
        if n_ok < nb.div_ceil(2).max(n_par + 3) {
            let reason = if spectrum.iter().any(|v| v.is_infinite()) {
                Reason::NonFinite
            } else {
                Reason::MissingBands
            };
            return (PixelEstimate::invalid(reason), f64::NAN);
        }
        if let Some(t) = theta_known {
            if !(t.is_finite() && (0.0..PI / 2.0).contains(&t)) {
                return (PixelEstimate::invalid(Reason::OutOfModel), f64::NAN);
            }
        }
        let lam_min = self.band_span().0;
        if let Some(t) = theta_known.filter(|_| effort.table && job_start.is_none()) {
            let found = match prep.table_at(t, scratch) {
                Some(table) => Some((table, t)),
                None => prep.tables.nearest(t),
            };
            if let Some((table, tt)) = found {
                return self.solve_table(prep, table, tt, t, n_ok, noise, effort, lam_min, scratch);
            }
        }
        // A run of pixels no fit explains: settled by the row's last full
        // search where the bound holds (`poor`).
        let free_poor = theta_known
            .is_none()
            .then(|| self.poor_noise(n_ok, noise, scratch))
            .flatten();
        if let Some(flat) = free_poor {
            if let Some(out) = self.poor_as_before(FREE_ANGLE, flat, n_ok, n_par, scratch) {
                return out;
            }
        }
        // A run of films past the resolved range: settled from the row's
        // last unresolved fit where this pixel's own fit ends there too
        // (`unresolved`).
        if theta_known.is_none() && judging && scratch.unresolved.is_some() {
            if let Some(out) = self.unresolved_free(prep, n_ok, effort.iters, false, scratch) {
                return out;
            }
        }
        // The previous pixel's fit in the row, refined and finished where it
        // stands (`warm_solve`); the margin of its neighbouring order is
        // kept only by a pixel that stands there too.
        let prev_margin = scratch.order_margin.take();
        let warm = |scratch: &mut Scratch| {
            let alone = pre.is_none();
            self.warm_solve(
                prep,
                WarmJob {
                    theta_known,
                    n_ok,
                    noise,
                    effort,
                    alone,
                    prev_margin,
                },
                lam_min,
                scratch,
            )
        };
        // The previous pixel's fit first, where it is trusted: after
        // `fast`'s closed form, found wanting by the caller, and in
        // `balanced` and `accurate` with the angle free before the closed
        // form is looked for, unless the closed form settled the previous
        // pixel (only `balanced`'s does; where a film shows too few
        // extrema for one, looking costs as much as the warm fit's
        // refinement).
        let mut warm_fit = None;
        let closed_form_last = std::mem::take(&mut scratch.closed_form_last);
        let warm_first = job_start.is_some()
            || (!effort.closed_form_only
                && !closed_form_last
                && scratch.warm.is_some()
                && theta_known.is_none());
        if warm_first && effort.warm {
            match warm(scratch) {
                Ok(out) => return out,
                Err(f) => warm_fit = f,
            }
        }
        if effort.closed_form && n_ok == nb {
            // The closed form: given by the caller (who found it wanting),
            // or found here.
            let start = match job_start {
                Some(s) => Some(s),
                None => match self.extrema_estimate(prep, theta_known, noise, scratch) {
                    Some(fe) => {
                        if effort.closed_form_only {
                            // The closed form is checked against the full
                            // model spectrum; one that does not explain it
                            // takes the fitted path from its estimate.
                            if !judging {
                                return (fe, f64::NAN);
                            }
                            match self.judge_closed_form(prep, fe, theta_known, n_ok, scratch) {
                                Ok(fe) => return (fe, f64::NAN),
                                Err(start) => Some(start),
                            }
                        } else {
                            Some((fe.thickness_nm, fe.theta_deg.to_radians()))
                        }
                    }
                    None => None,
                },
            };
            if let Some((d0, th0)) = start {
                let fit = self.refine(
                    &prep.model,
                    d0,
                    th0,
                    theta_known.is_none(),
                    effort.iters,
                    scratch,
                );
                let rms = (fit.sse / n_ok as f64).sqrt();
                // A wrong order leaves fringe-sized residuals; only then is
                // the full search worth its cost.
                let good = noise.is_some_and(|n| rms <= 2.0 * n);
                if good && !effort.verify_order {
                    let out = self.finish(&[fit], n_ok, theta_known, noise, prep, lam_min, scratch);
                    scratch.closed_form_last = true;
                    return out;
                }
                if good {
                    let (fits, n_fits) = self.with_neighbour_order(
                        prep,
                        &prep.model,
                        fit,
                        theta_known,
                        n_ok,
                        effort.iters,
                        scratch,
                    );
                    return self.finish(
                        &fits[..n_fits],
                        n_ok,
                        theta_known,
                        noise,
                        prep,
                        lam_min,
                        scratch,
                    );
                }
            }
        }
        // The previous pixel's fit in the row: the start itself where it
        // is trusted (`warm_accept`), else one more fit beside the
        // search's (tried already above where the caller gave a start).
        if warm_fit.is_none() && job_start.is_none() {
            match warm(scratch) {
                Ok(out) => return out,
                Err(f) => warm_fit = f,
            }
        }
        let mut cands = [Candidate::default(); MAX_CANDIDATES];
        let n_cands = match pre {
            Some(px) => {
                let k = usize::from(prep.sign < 0.0);
                cands = px.cands[k];
                px.n_cands[k]
            }
            None => {
                scratch.fringe_searches += 1;
                self.fringe_search(scratch, prep.sign, n_ok == nb, &mut cands)
            }
        };

        // Angle start.
        let theta0 = match theta_known {
            Some(t) => t,
            None => {
                let c = if n_cands > 0 {
                    cands[0]
                } else {
                    let mean = scratch.spectrum.iter().sum::<f64>() / n_ok as f64;
                    Candidate {
                        a: mean,
                        ..Default::default()
                    }
                };
                angle_start(&prep.cosine_table, Some(c.a + c.b), Some(c.a - c.b))
            }
        };
        let q2 = prep.model.q2_mid(theta0);
        // Starts: the fringe candidates, plus a bare substrate and a thin
        // film below the first fringe.
        let mut starts: [(f64, f64); MAX_CANDIDATES + 2] =
            [(0.0, f64::INFINITY); MAX_CANDIDATES + 2];
        let mut n_starts = 0;
        for c in &cands[..n_cands] {
            starts[n_starts] = (c.g / q2, 0.0);
            n_starts += 1;
        }
        starts[n_starts] = (0.0, 0.0);
        starts[n_starts + 1] = (lam_min / (8.0 * q2), 0.0);
        n_starts += 2;
        scratch.cur_at = None;
        for s in &mut starts[..n_starts] {
            prep.model.eval(s.0, theta0, &mut scratch.cur, false);
            s.1 = sse(&scratch.spectrum, &scratch.weight, &scratch.cur.r);
        }
        starts[..n_starts].sort_by(|a, b| a.1.total_cmp(&b.1));
        let (n_refine, iters) = (effort.n_refine, effort.iters);
        let mut fits = [Fit::default(); 3 + 2];
        let mut n_fits = 0;
        for st in starts[..n_starts.min(n_refine)].iter() {
            if !st.1.is_finite() {
                continue;
            }
            fits[n_fits] = self.refine(
                &prep.model,
                st.0,
                theta0,
                theta_known.is_none(),
                iters,
                scratch,
            );
            n_fits += 1;
        }
        // Only where the best fit so far is thin, or (the twin test's
        // runner-up) pinned at an end of the angle range (`angle_grid`).
        let (th_lo, th_hi) = self.theta_range;
        let rescue = |f: &Fit| {
            f.d * prep.model.q2_mid(f.theta) < angle_grid::THIN * lam_min
                || (effort.grid_pinned
                    && (f.theta <= th_lo + angle_grid::PINNED_RAD
                        || f.theta >= th_hi - angle_grid::PINNED_RAD))
        };
        let best_so_far = fits[..n_fits].iter().min_by(|a, b| a.sse.total_cmp(&b.sse));
        if effort.angle_grid && theta_known.is_none() && best_so_far.is_none_or(rescue) {
            let cands = &cands[..n_cands];
            n_fits +=
                self.angle_grid_fits(prep, cands, lam_min, iters, scratch, &mut fits[n_fits..]);
            // `finish` weighs the first three as the search's own.
            fits[..n_fits].sort_by(|a, b| a.sse.total_cmp(&b.sse));
            n_fits = n_fits.min(3);
        }
        if let Some(f) = warm_fit {
            // The neighbour's basin competes with the search's: a thin
            // film's search starts can lead to a shallower basin of the
            // (d, θ) valley, and a weak one's to a twin.
            if n_fits < 3 {
                fits[n_fits] = f;
                n_fits += 1;
            } else if let Some(worst) = fits[..3].iter_mut().max_by(|a, b| a.sse.total_cmp(&b.sse))
            {
                if f.sse < worst.sse {
                    *worst = f;
                }
            }
        }
        let out = self.finish(
            &fits[..n_fits],
            n_ok,
            theta_known,
            noise,
            prep,
            lam_min,
            scratch,
        );
        // The full search found nothing that fits: a film past the
        // resolved range, where the row's last unresolved fit leads to one
        // that does (`unresolved`; the run starts afresh from this
        // search), else the row's reference for the poor pixels after it.
        if out.0.reason == Reason::PoorFit && theta_known.is_none() && judging {
            if let Some(out) = self.unresolved_free(prep, n_ok, iters, true, scratch) {
                return out;
            }
        }
        if let (Reason::PoorFit, Some(flat)) = (out.0.reason, free_poor) {
            self.note_poor((FREE_ANGLE, FREE_MARGIN, FREE_RUN), flat, out.1, scratch);
        }
        out
    }

    /// [`Solver::try_warm`], finished where the warm fit stands: `Ok` with
    /// the pixel's estimate, else `Err` with the fit to weigh beside the
    /// search's.
    fn warm_solve(
        &self,
        prep: &Prepared,
        job: WarmJob,
        lam_min: f64,
        scratch: &mut Scratch,
    ) -> Result<(PixelEstimate, f64), Option<Fit>> {
        let (fits, n_fits) = self.try_warm(prep, job, scratch)?;
        Ok(self.finish(
            &fits[..n_fits],
            job.n_ok,
            job.theta_known,
            job.noise,
            prep,
            lam_min,
            scratch,
        ))
    }

    /// The largest step in thickness from one pixel to the next that the
    /// row's ramp follows (the warm start, a run past the range): a
    /// quarter fringe at the band range's centre at normal incidence (the
    /// least it is at any angle), ~30 nm for silicon nitride in the
    /// visible. An order change jumps a whole fringe; a smooth ramp, even
    /// the thick hard coat's 10 nm a pixel, stays below it.
    pub(super) fn ramp_limit(&self, prep: &Prepared) -> f64 {
        0.125 / (self.table.sigma_center * prep.model.n2_mid())
    }

    /// The previous pixel's fit in the row (`scratch.warm`), refined:
    /// `Ok` with the fits to finish where it stands on its own
    /// ([`Solver::warm_accept`], only if `alone` and the effort allows),
    /// else `Err` with the refined fit (none without a judged warm start)
    /// to weigh beside the search's.
    #[allow(clippy::type_complexity)]
    fn try_warm(
        &self,
        prep: &Prepared,
        job: WarmJob,
        scratch: &mut Scratch,
    ) -> Result<([Fit; 2], usize), Option<Fit>> {
        let WarmJob {
            theta_known,
            noise,
            effort,
            alone,
            ..
        } = job;
        let judging = noise.is_some() && self.judging();
        let Some((d0, th0)) = scratch
            .warm_start(self.ramp_limit(prep))
            .filter(|_| judging)
        else {
            return Err(None);
        };
        let th0 = theta_known.unwrap_or(th0);
        let free = theta_known.is_none();
        let fit = self.refine(&prep.model, d0, th0, free, effort.iters, scratch);
        if effort.warm && alone {
            if let Some(fits) = self.warm_accept(prep, fit, job, scratch) {
                return Ok(fits);
            }
        }
        Err(Some(fit))
    }

    /// Whether the fit refined from the previous pixel's valid fit in the
    /// row (where the closed form does not apply: a film below two
    /// extrema, the angle free) stands without the fringe search: a film
    /// changes little from one pixel to the next, so the refinement starts
    /// next to its minimum. It stands only where it converged, its fringes
    /// are too strong for another basin to pass beside it, and it passes
    /// the χ² test against the noise model; its neighbouring orders are
    /// then weighed against it as after a closed form (an order as good
    /// flags the pixel ambiguous), except in `fast`, which weighs one fit
    /// on its search path too. Otherwise (an edge, a jump of order, a
    /// flagged neighbour, weak fringes) the pixel takes the fringe search.
    /// `finish` runs the same alternative checks on either path.
    fn warm_accept(
        &self,
        prep: &Prepared,
        fit: Fit,
        job: WarmJob,
        scratch: &mut Scratch,
    ) -> Option<([Fit; 2], usize)> {
        let WarmJob {
            theta_known,
            n_ok,
            noise,
            effort,
            prev_margin,
            ..
        } = job;
        let sigma = noise?;
        if fit.stalled || !(fit.sse.is_finite() && fit.d.is_finite() && fit.theta.is_finite()) {
            return None;
        }
        // Only where the fringes are strong enough that no other basin
        // passes the χ² test beside a local fit (weak fringes leave flat
        // valleys and twin basins a local refinement cannot tell apart: a
        // film index-matched to its ambient read 75 nm for 100 nm from
        // its neighbour's start, valid).
        let signal = self.fringe_signal(prep, fit.theta, n_ok, sigma, scratch);
        if !self.fringes_exclude_alternatives(signal, theta_known.is_none()) {
            return None;
        }
        // The refinement leaves the model at its fit in `cur`.
        let cur = std::mem::take(&mut scratch.cur);
        let (chi2, _) = self.chi2_and_noise_var(scratch, &cur.r);
        scratch.cur = cur;
        if !self.fit_passes(chi2, n_ok, if theta_known.is_none() { 2 } else { 1 }) {
            return None;
        }
        if effort.n_refine < 2 {
            // `fast` weighs one fit, as on its search path.
            return Some(([fit, fit], 1));
        }
        if effort.verify_order {
            // `accurate`: weigh the neighbouring orders on every pixel (as
            // after its closed form).
            return Some(self.with_neighbour_order(
                prep,
                &prep.model,
                fit,
                theta_known,
                n_ok,
                effort.iters,
                scratch,
            ));
        }
        // The neighbouring orders, unless the previous pixel's fell far
        // short of its fit and this one's fringe phase moved little
        // ([`OrderMargin`]; here in optical thickness, which the angle
        // shares with the thickness).
        let g = fit.d * prep.model.q2_mid(fit.theta);
        let fringe = 0.5 / self.table.sigma_center;
        if let Some(m) = OrderMargin::carried(prev_margin, OrderMargin::FITTED, g, fringe) {
            scratch.order_margin = Some(OrderMargin::new(OrderMargin::FITTED, g, m));
            return Some(([fit, fit], 1));
        }
        // Nor where the noise-free orders lie far apart here
        // (`order_gaps`).
        if let Some(m) = self
            .free_order_gap(prep, g, fit.theta, scratch)
            .filter(|&m| m >= ORDER_GAP_SAFE)
        {
            scratch.order_margin = Some(OrderMargin::new(OrderMargin::FITTED, g, m));
            return Some(([fit, fit], 1));
        }
        let (fits, n) = self.with_neighbour_order(
            prep,
            &prep.model,
            fit,
            theta_known,
            n_ok,
            effort.iters,
            scratch,
        );
        let margin = if n == 2 {
            (fits[1].sse - fit.sse) / (sigma * sigma)
        } else {
            f64::INFINITY
        };
        scratch.order_margin = Some(OrderMargin::new(OrderMargin::FITTED, g, margin));
        Some((fits, n))
    }

    /// `fit` and its neighbouring orders on the lattice: the same fringe
    /// phase at the band-range centre, one fringe more or fewer. The better
    /// one is refined (two steps tell a clearly worse order; only a close
    /// one is refined to convergence), for `finish` to flag the pixel
    /// ambiguous if it fits as well.
    #[allow(clippy::too_many_arguments)]
    fn with_neighbour_order(
        &self,
        prep: &Prepared,
        model: &FilmModel,
        fit: Fit,
        theta_known: Option<f64>,
        n_ok: usize,
        iters: usize,
        scratch: &mut Scratch,
    ) -> ([Fit; 2], usize) {
        let q2 = prep.model.q2_mid(fit.theta);
        let g = fit.d * q2;
        let dg = 0.5 / self.table.sigma_center;
        let mut alt = None;
        let mut alt_sse = f64::INFINITY;
        for ga in [g - dg, g + dg] {
            if ga < 0.0 || ga / q2 > self.d_max {
                continue;
            }
            model.eval(ga / q2, fit.theta, &mut scratch.trial, false);
            let e = sse(&scratch.spectrum, &scratch.weight, &scratch.trial.r);
            if e < alt_sse {
                alt_sse = e;
                alt = Some(ga / q2);
            }
        }
        let mut fits = [fit, fit];
        let Some(d_alt) = alt else {
            return (fits, 1);
        };
        let free = theta_known.is_none();
        let mut f = self.refine(model, d_alt, fit.theta, free, 2, scratch);
        let var = fit.sse / (n_ok.saturating_sub(2).max(1)) as f64;
        if f.sse < fit.sse + 25.0 * var {
            f = self.refine(model, f.d, f.theta, free, iters, scratch);
        }
        fits[1] = f;
        (fits, 2)
    }

    /// From refined fits to an estimate: best fit, covariance, flags.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn finish(
        &self,
        fits: &[Fit],
        n_ok: usize,
        theta_known: Option<f64>,
        noise: Option<f64>,
        prep: &Prepared,
        lam_min: f64,
        scratch: &mut Scratch,
    ) -> (PixelEstimate, f64) {
        let n_par = if theta_known.is_some() { 1 } else { 2 };
        // Fits a fresh search never looks at compete too (see
        // `alternatives`): three fits and at most five alternatives (past
        // the range; with the angle free, two mirror angles, the whole
        // range, the sub-fringe range).
        let own = &fits[..fits.len().min(3)];
        // Not zeroed per pixel: most pixels have none (a zeroed array of
        // five fits was a quarter of this function's time on the paper's
        // cylinder, `perf annotate`).
        let mut alt = heapless::Vec::<Fit, 5>::new();
        self.alternative_fits(fits, n_ok, theta_known, noise, prep, scratch, &mut alt);
        let n_alt = alt.len();
        // Every fit, read where it lies (copying them into one array and
        // sorting it stalled on the copy: a tenth of this function's time).
        let all = || own.iter().chain(alt.iter());
        let by_sse = |a: &&Fit, b: &&Fit| a.sse.total_cmp(&b.sse);
        // The first of the lowest, as a stable sort's head, read in place
        // (a copy, its halves stored and a field loaded across them, stalled
        // on the store: a third of this function's time on a live pixel).
        let Some(best) = all().min_by(by_sse) else {
            return (PixelEstimate::invalid(Reason::PoorFit), f64::NAN);
        };
        scratch.last_fit_d = best.d;
        scratch.last_fit_theta = best.theta;
        if !(best.sse.is_finite() && best.d.is_finite() && best.theta.is_finite()) {
            return (PixelEstimate::invalid(Reason::PoorFit), f64::NAN);
        }
        let dof = (n_ok - n_par).max(1) as f64;
        let model = &prep.model;
        // The fit is judged against the noise model, and its σ never claims
        // more precision than the instrument's noise allows.
        let judging = noise.is_some() && self.judging();
        let tabled = if best.tabled {
            prep.table_at(best.theta, scratch)
        } else {
            None
        };
        // Another basin: more than a quarter fringe away.
        let basin = |s: &Scratch| 0.25 * lam_min / (2.0 * s.q2_mid(prep, best.theta));
        // Where the bands' noise differs, the best fit weighed by it
        // (`balanced` and `accurate`): its thickness, angle, χ² and σ are
        // reported; the order checks below keep the fits as weighed alike.
        let weighed = if judging && self.weigh_bands && Effort::of(self.mode).weigh {
            let (free, basin) = (theta_known.is_none(), basin(scratch));
            self.weighed_fit(model, tabled, best, free, basin, scratch)
        } else {
            None
        };
        let (chi2, noise_var) = if let Some(c) = weighed.and_then(|w| w.0.chi2) {
            c
        } else if let Some(c) = tabled
            .filter(|_| judging)
            .and_then(|t| self.tabled_chi2(t, best.d, best.sse, (n_ok, n_par), scratch))
        {
            c
        } else if let (true, Some(c)) = (judging, best.chi2) {
            // Left by the refinement at this very fit.
            c
        } else if judging {
            let mut trial = std::mem::take(&mut scratch.trial);
            match tabled {
                Some(t) => t.values(best.d, &mut trial.r),
                None => model.eval(best.d, best.theta, &mut trial, false),
            }
            let out = self.chi2_and_noise_var(scratch, &trial.r);
            scratch.trial = trial;
            out
        } else {
            (f64::NAN, 0.0)
        };
        let var = (best.sse / dof).max(noise_var).max(1e-14);
        // σ of the fit reported: the weighed one's in its own units.
        let (at, at_var) = match weighed {
            Some((w, mean_var)) => (w, (w.sse / dof).max(mean_var).max(1e-14)),
            None => (*best, var),
        };
        let (sig_d, sig_th) = if theta_known.is_some() {
            ((at_var / at.jtj[0].max(1e-300)).sqrt(), 0.0)
        } else {
            free_angle_sigma(model, &at, at_var, self.theta_range, self.sin2_range)
        };
        // Near d = 0 the reflectance is even in d (dR/dd = 0 at d = 0), so
        // the linearised σ is meaningless: take the one-sided profile bound
        // instead, the d at which the residual grows by one variance.
        let sig_d = if best.d < 0.1 * lam_min && (sig_d.is_nan() || sig_d >= 0.05 * lam_min) {
            self.profile_sigma_d(model, *best, var, scratch)
        } else {
            sig_d
        };
        let rms = (best.sse / n_ok as f64).sqrt();
        let mut reason = Reason::Ok;
        // A second order that fits as well as the best is an ambiguity: the
        // best fit in another basin, not merely the runner-up, which may be
        // the best's own basin reached from another start (σ_R = 0.03 on the
        // paper's cylinder, angle free: a ~100 nm film at 45° standing for
        // a ~500 nm one at 15° passed valid while the 500 nm basin, third,
        // fitted within the margin).
        // The best fit in another basin: the lowest of those apart from the
        // best (the best itself never is; a lone fit has none to weigh).
        if own.len() + n_alt > 1 {
            let basin = basin(scratch);
            let apart = |f: &&Fit| (f.d - best.d).abs() > basin;
            if let Some(second) = all().filter(apart).min_by(by_sse) {
                if second.sse - best.sse < AMBIGUITY_CHI2 * var {
                    reason = Reason::AmbiguousOrder;
                }
            }
        }
        if judging && !self.fit_passes(chi2, n_ok, n_par) {
            reason = Reason::PoorFit;
        }
        if judging && reason == Reason::Ok {
            if let Some(r) = self.bound_reason(prep, at.d, at.theta, theta_known) {
                reason = r;
            }
        }
        // A σ wider than the whole thickness range determines nothing (e.g.
        // a gap beyond total internal reflection, where R no longer
        // depends on d).
        let span = (self.d_max - self.d_min).max(1.0);
        if reason == Reason::Ok
            && (sig_d.is_nan()
                || sig_d >= span
                || (judging && self.film_invisible(prep, best.theta, n_ok, noise_var)))
        {
            reason = Reason::NoFringe;
        }
        if reason == Reason::Ok
            && theta_known.is_none()
            && sig_th.to_degrees() > ANGLE_SIGMA_LIMIT_DEG
        {
            reason = Reason::AngleNotIdentifiable;
        }
        scratch.last_fit_d = at.d;
        scratch.last_fit_theta = at.theta;
        let est = PixelEstimate {
            thickness_nm: at.d,
            n_film: prep.model.n2_mid(),
            theta_deg: at.theta.to_degrees(),
            sigma_thickness_nm: sig_d,
            sigma_theta_deg: sig_th.to_degrees(),
            residual_rms: rms,
            reason,
        };
        if est.is_valid() {
            (est, best.sse)
        } else {
            (PixelEstimate::invalid(reason), best.sse)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::load_spectrum;

    #[test]
    fn a_spectrum_loads_with_its_weights_count_sum_and_range_check() {
        // Lengths around the four lanes; missing values (NaN, ±∞) weigh 0
        // and count nothing, and only a finite value outside [−0.2, 1.2]
        // is beyond a reflectance.
        for n in [1, 3, 4, 5, 31] {
            let spectrum: Vec<f64> = (0..n)
                .map(|k| match k % 5 {
                    1 => f64::NAN,
                    3 if k > 5 => f64::INFINITY,
                    _ => 0.01 * k as f64,
                })
                .collect();
            let (mut y, mut w) = (vec![9.0; n], vec![9.0; n]);
            let (n_ok, beyond, sum) = load_spectrum(&spectrum, &mut y, &mut w);
            let ok: Vec<bool> = spectrum.iter().map(|v| v.is_finite()).collect();
            assert_eq!(n_ok, ok.iter().filter(|&&o| o).count(), "n {n}");
            assert!(!beyond, "n {n}");
            for k in 0..n {
                assert_eq!(w[k], if ok[k] { 1.0 } else { 0.0 });
                assert_eq!(y[k], if ok[k] { spectrum[k] } else { 0.0 });
            }
            let want: f64 = spectrum.iter().filter(|v| v.is_finite()).sum();
            assert!(
                (sum - want).abs() <= 1e-15 * n as f64,
                "n {n}: {sum} vs {want}"
            );
        }
        let (mut y, mut w) = (vec![0.0; 6], vec![0.0; 6]);
        for bad in [-0.21, 1.21, 5.0] {
            let s = [0.1, 0.2, bad, f64::NAN, 0.3, 0.4];
            assert!(load_spectrum(&s, &mut y, &mut w).1, "{bad}");
        }
        assert!(!load_spectrum(&[-0.2, 1.2, f64::NEG_INFINITY], &mut y[..3], &mut w[..3]).1);
    }
}
