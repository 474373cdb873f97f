//! The free level: every pixel has its own scale, offset and slow envelope,
//! `y_k = R_k(d)·(c0 + c1·u_k + … + c_m·u_k^m) + b` with `u` the band's
//! wavenumber normalised to [−1, 1] — for normalised or uncalibrated
//! intensities, where only the fringes' positions and shapes carry the
//! thickness.
//!
//! First the fringe positions ([`fringes`](super::fringes)): no extremum
//! standing out of the noise flags the pixel "no fringe". Where the
//! positions leave the order open (one extremum, or two to four that fit
//! several order sets), the spectrum's shape chooses: a slow offset and
//! scale, `y ≈ (a₀ + a₁u) + R·(c₀ + c₁u)` with `c₀ > 0`, fitted near each
//! candidate, must prefer one by a wide margin (Δχ² ≥ 25 after scaling by
//! its own reduced χ², and more than its whole misfit); the chosen film
//! must put as many extrema in the band as were found (a lamp's bump on a
//! thin film mimics a fringe's shape, not its count); and from one
//! extremum, the thickness must not move by more than σ when the offset's
//! slope is dropped, and must win by the same margins when the scale may
//! curve (a lamp's bump can narrow a hump into a higher order's shape).
//! Otherwise "ambiguous order": one broad hump moves with the envelope.
//! Whatever the positions say from at most four extrema, a film too thin
//! for a pair of fringes must not explain the shape about as well
//! (Δχ² < 25, scaled the same way), with a straight scale or a curved
//! one: a lamp's bump and noise can pass for a few extrema — "ambiguous
//! order" again. Then,
//! within one fringe order of what
//! the positions say, variable projection: for each trial thickness the
//! linear coefficients are solved by least squares, the thickness searched
//! on a grid of its profile, then refined by golden section; σ from the
//! profile's curvature. The envelope degree (0, 2 or 4) is the lowest the
//! data accept: a higher one is taken only when it lowers χ² by more than
//! its extra parameters explain at p = 0.001 — modelling only what the
//! spectrum requires. Where even that model fails the χ² test (or no noise
//! level judges it), the fringe positions' own answer and σ stand.

#![allow(clippy::needless_range_loop)] // band-indexed numeric loops read clearer with indices

use super::fringes::{self, FringeFit};
use super::{Prepared, Scratch, Solver};
use crate::estimate::level::solve_spd;
use crate::estimate::quality::chi2_upper_quantile;
use crate::estimate::{PixelEstimate, Reason};
use std::f64::consts::PI;

/// Envelope degrees tried, lowest first.
const DEGREES: [usize; 3] = [0, 2, 4];
/// Probability at which a higher envelope degree is accepted.
const DEGREE_PROBABILITY: f64 = 1e-3;
/// Grid points per quarter fringe (at the shortest wavelength).
const GRID_PER_QUARTER_FRINGE: f64 = 4.0;
/// Local minima of the grid profile refined per degree.
const REFINED_MINIMA: usize = 4;
/// Largest relative σ of a valid thickness: beyond it the fringes no longer
/// pin the thickness once the level is free ("no fringe in range").
const MAX_RELATIVE_SIGMA: f64 = 0.033;
/// Largest relative σ of a thickness read from fringe positions alone
/// (their scatter, not the noise, sets it).
const MAX_FRINGE_RELATIVE_SIGMA: f64 = 0.05;
/// χ², scaled by the level model's own reduced χ² where above one, by
/// which the spectrum's shape must prefer one of the order sets the fringe
/// positions leave open (five σ: the misfit of a measured spectrum is
/// systematic, so the margin is wide).
const RESOLVE_CHI2: f64 = 25.0;
/// Grid points per candidate order's search window.
const RESOLVE_GRID: usize = 8;
/// Largest rms distance of the extrema from their orders, in orders: beyond
/// it the extrema are not one film's fringes.
const MAX_ORDER_RMS: f64 = 0.25;

impl Solver {
    /// One pixel under the free level (angle and film index known).
    pub(super) fn solve_free(
        &self,
        prep: &Prepared,
        spectrum: &[f64],
        theta_known: Option<f64>,
        scratch: &mut Scratch,
    ) -> PixelEstimate {
        let nb = self.bands.len();
        let Some(theta) = theta_known.filter(|t| t.is_finite() && (0.0..PI / 2.0).contains(t))
        else {
            return PixelEstimate::invalid(Reason::OutOfModel);
        };
        if spectrum.len() != nb {
            return PixelEstimate::invalid(Reason::MissingBands);
        }
        let n_ok = scratch.load(spectrum);
        if n_ok == 0 {
            return PixelEstimate::invalid(Reason::NonFinite);
        }
        if n_ok < nb.div_ceil(2).max(10) {
            return PixelEstimate::invalid(Reason::MissingBands);
        }
        let (s_lo, s_hi) = self.table.sigma_range;
        let half = 0.5 * (s_hi - s_lo).max(1e-12);
        let u: Vec<f64> = self
            .bands
            .iter()
            .map(|b| (1.0 / b.center_nm - s_lo) / half - 1.0)
            .collect();
        let q2 = prep.model.q2_mid(theta);
        let lam_min = self.band_span().0;
        let step = lam_min / (4.0 * GRID_PER_QUARTER_FRINGE * 2.0 * q2);
        // The fringe positions first: where they stand out, the level
        // model is only asked about the orders around them.
        let Some(fringes) = self.fringe_positions(prep, theta, scratch) else {
            // Fewer than two fringe extrema stand out: with the level free,
            // one broad hump's position moves with the envelope, and no
            // thickness can be read honestly.
            return PixelEstimate::invalid(Reason::NoFringe);
        };
        let order = 1.0 / (4.0 * fringes.x_mean);
        let (d_lo, d_hi) = (
            (fringes.fit.d - order).max(self.d_min),
            (fringes.fit.d + order).min(self.d_max),
        );
        let n_grid = (((d_hi - d_lo) / step).ceil() as usize + 1).min(200_000);
        let mut trial = std::mem::take(&mut scratch.trial);
        // The profile of every degree on the grid.
        let mut prof: Vec<[f64; 3]> = Vec::with_capacity(n_grid);
        for i in 0..n_grid {
            let d = (d_lo + step * i as f64).min(d_hi);
            prep.model.eval(d, theta, &mut trial, false);
            prof.push(profile_sse(scratch, &trial.r, &u));
        }
        let sse_at = |j: usize, d: f64, trial: &mut crate::estimate::model::ModelOut| {
            prep.model.eval(d, theta, trial, false);
            profile_sse(scratch, &trial.r, &u)[j]
        };
        // For each degree, the grid's best local minima refined by golden
        // section on their bracketing cells (a grid point can sit far up a
        // sharp minimum's walls, so minima are compared refined): the two
        // best as (d, SSE).
        let mut best = [[(f64::NAN, f64::INFINITY); 2]; DEGREES.len()];
        for (j, best_j) in best.iter_mut().enumerate() {
            let mut minima: Vec<usize> = (0..prof.len())
                .filter(|&i| {
                    let here = prof[i][j];
                    (i == 0 || prof[i - 1][j] >= here)
                        && (i + 1 == prof.len() || prof[i + 1][j] >= here)
                })
                .collect();
            minima.sort_by(|&x, &y| prof[x][j].total_cmp(&prof[y][j]));
            let mut refined: Vec<(f64, f64)> = minima
                .iter()
                .take(REFINED_MINIMA)
                .map(|&i| {
                    let lo = (d_lo + step * i as f64 - step).max(d_lo);
                    let hi = (d_lo + step * i as f64 + step).min(d_hi);
                    golden(lo, hi, |d| sse_at(j, d, &mut trial))
                })
                .collect();
            refined.sort_by(|x, y| x.1.total_cmp(&y.1));
            for (slot, r) in best_j.iter_mut().zip(&refined) {
                *slot = *r;
            }
        }
        let var_noise = self.noise_var(scratch, &vec![0.0; nb]);
        // Degree: the lowest whose best fit a higher one does not beat
        // significantly.
        let mut deg_j = 0;
        for j in 1..DEGREES.len() {
            let (lo_sse, hi_sse) = (best[deg_j][0].1, best[j][0].1);
            let extra = (DEGREES[j] - DEGREES[deg_j]) as f64;
            let var = if var_noise > 0.0 {
                var_noise
            } else {
                hi_sse / (n_ok as f64 - DEGREES[j] as f64 - 3.0).max(1.0)
            };
            if (lo_sse - hi_sse) / var > chi2_upper_quantile(extra, DEGREE_PROBABILITY) {
                deg_j = j;
            }
        }
        let n_lin = DEGREES[deg_j] + 2;
        let ((d, sse), (_, second)) = (best[deg_j][0], best[deg_j][1]);
        let dof = n_ok.saturating_sub(n_lin + 1).max(1);
        let var = (sse / dof as f64).max(var_noise).max(1e-14);
        // σ from the profile's curvature: SSE(d ± h) ≈ SSE + (SSE''/2)·h².
        let h = (0.02 * step).max(1e-3);
        let curv = (sse_at(deg_j, d + h, &mut trial) + sse_at(deg_j, (d - h).max(0.0), &mut trial)
            - 2.0 * sse)
            / (h * h);
        let sigma = if curv > 0.0 {
            (2.0 * var / curv).sqrt()
        } else {
            f64::INFINITY
        };
        let chi2 = sse / var_noise.max(1e-300);
        let level_fits = self.judging() && self.fit_passes(chi2, n_ok, n_lin + 1);
        if !level_fits {
            // The level model misses the spectrum (or nothing judges it):
            // the fringe positions alone, with their own σ — their order
            // chosen by the spectrum's shape where the positions leave it
            // open.
            let rms = (sse_at(deg_j, fringes.fit.d, &mut trial) / n_ok as f64).sqrt();
            let mut fit = fringes.fit;
            if fit.ambiguous || fit.n_extrema <= fringes::MAX_CANDIDATES {
                let shape = ShapeFit::new(prep, theta, &fringes, &u, scratch);
                if fit.ambiguous {
                    if let Some((d, sigma)) = self.resolve_orders(&shape, &mut trial) {
                        (fit.d, fit.sigma, fit.ambiguous) = (d, sigma, false);
                    }
                }
                if !fit.ambiguous && self.thinner_film_fits(&shape, &mut trial, fit.d) {
                    fit.ambiguous = true;
                }
            }
            scratch.trial = trial;
            return self.fringe_estimate(prep, &fit, theta, rms);
        }
        // A thinner film explains the shape as well: the extrema found may
        // not be this film's fringes.
        let thinner = fringes.fit.n_extrema <= fringes::MAX_CANDIDATES
            && self.thinner_film_fits(
                &ShapeFit::new(prep, theta, &fringes, &u, scratch),
                &mut trial,
                d,
            );
        scratch.trial = trial;
        let mut reason = Reason::Ok;
        // Another fringe order about as good: ambiguous.
        if (second - sse) / var < fringes::AMBIGUITY_CHI2 || thinner {
            reason = Reason::AmbiguousOrder;
        }
        if self.judging() && !self.fit_passes(chi2, n_ok, n_lin + 1) {
            reason = Reason::PoorFit;
        }
        if reason == Reason::Ok && !(sigma.is_finite() && sigma <= MAX_RELATIVE_SIGMA * d.max(1.0))
        {
            reason = Reason::NoFringe;
        }
        if reason == Reason::Ok {
            if let Some(r) = self.bound_reason(prep, d, theta, Some(theta)) {
                reason = r;
            }
        }
        if !reason.is_valid() {
            return PixelEstimate::invalid(reason);
        }
        PixelEstimate {
            thickness_nm: d,
            n_film: prep.model.n2_mid(),
            theta_deg: theta.to_degrees(),
            sigma_thickness_nm: sigma,
            sigma_theta_deg: 0.0,
            residual_rms: (sse / n_ok as f64).sqrt(),
            reason,
        }
    }
}

/// The fringe analysis of a pixel, with the mean phase rate of its bands
/// and the noise variance of each band (band order; 0 where missing).
struct PixelFringes {
    fit: FringeFit,
    x_mean: f64,
    /// Lowest and highest phase rate, and the bands' count.
    x_range: (f64, f64, usize),
    var: Vec<f64>,
}

impl PixelFringes {
    /// Each band's weight, the inverse of its noise variance (0 where the
    /// band is missing or has no variance).
    fn weights(&self, scratch: &Scratch) -> Vec<f64> {
        (0..self.var.len())
            .map(|k| {
                let v = self.var[k];
                if scratch.weight[k] > 0.0 && v > 0.0 {
                    1.0 / v
                } else {
                    0.0
                }
            })
            .collect()
    }

    /// How many extrema a film of thickness `d` puts where the fringe
    /// analysis would find them: whole orders `4 d x = m` inside the band,
    /// short of its ends by the margin [`fringes::fit`] keeps there.
    fn extrema_expected(&self, d: f64) -> usize {
        let (lo, hi, n) = self.x_range;
        let dx = (hi - lo) / (n.max(2) - 1) as f64;
        let h = (1.0 / (16.0 * d * dx))
            .clamp(2.0, (n / 8).max(2) as f64)
            .floor();
        let margin = (h / 2.0).floor().max(2.0) * dx;
        let (a, b) = (4.0 * d * (lo + margin), 4.0 * d * (hi - margin));
        if b < a {
            return 0;
        }
        (b.floor() - a.ceil() + 1.0).max(0.0) as usize
    }
}

impl Solver {
    /// The fringe positions of the spectrum in `scratch` (see
    /// [`fringes`](super::fringes)), its bands sorted by phase rate, each
    /// weighted by the noise model's variance — or, with none, by a local
    /// estimate from the spectrum's second differences.
    fn fringe_positions(
        &self,
        prep: &Prepared,
        theta: f64,
        scratch: &Scratch,
    ) -> Option<PixelFringes> {
        let rates = prep.model.phase_rates(theta);
        let mut idx: Vec<usize> = (0..rates.len())
            .filter(|&k| scratch.weight[k] > 0.0 && rates[k] > 0.0)
            .collect();
        idx.sort_by(|&a, &b| rates[b].total_cmp(&rates[a]));
        let x: Vec<f64> = idx.iter().map(|&k| rates[k]).collect();
        let y: Vec<f64> = idx.iter().map(|&k| scratch.spectrum[k]).collect();
        let var: Vec<f64> = match &self.noise {
            Some(noise) => idx
                .iter()
                .map(|&k| noise.var(k, scratch.spectrum[k]))
                .collect(),
            None => fringes::local_variance(&y),
        };
        let (half, quarter) = prep.model.envelopes(theta);
        let fit = fringes::fit(&x, &y, &var, quarter > half, (self.d_min, self.d_max))?;
        let x_mean = x.iter().sum::<f64>() / x.len() as f64;
        let x_range = (x[x.len() - 1], x[0], x.len());
        let mut var_band = vec![0.0; rates.len()];
        for (&k, &v) in idx.iter().zip(&var) {
            var_band[k] = v;
        }
        Some(PixelFringes {
            fit,
            x_mean,
            x_range,
            var: var_band,
        })
    }

    /// The order set, among those the fringe positions leave open, whose
    /// thickness the whole spectrum's shape prefers: the level model
    /// `y ≈ (a₀ + a₁u) + R·(c₀ + c₁u)` (a slow offset and scale, noise-
    /// weighted) fitted near each candidate. Its χ² is scaled by its own
    /// reduced χ² where that exceeds one (a measured spectrum's shape is
    /// never exactly the model's), and the best must win by
    /// [`RESOLVE_CHI2`]; `None` otherwise — the pixel stays ambiguous.
    fn resolve_orders(
        &self,
        shape: &ShapeFit,
        trial: &mut crate::estimate::model::ModelOut,
    ) -> Option<(f64, f64)> {
        let f = shape.fringes;
        let cands: Vec<(f64, f64)> = f
            .fit
            .candidates
            .iter()
            .copied()
            .filter(|c| c.0.is_finite())
            .collect();
        if cands.len() < 2 {
            return None;
        }
        let n_ok = shape.n_ok;
        let mut sse_at = |d: f64, curved: bool| shape.sse(trial, d, curved);
        let half_order = 1.0 / (8.0 * f.x_mean);
        let sse = self.candidate_minima(&cands, half_order, &mut |d| sse_at(d, false));
        let birge = (sse[0].0 / n_ok.saturating_sub(5).max(1) as f64).max(1.0);
        // The loser's excess misfit must also exceed all the winner's: a
        // systematic misfit that large could tip the balance either way.
        let margin = sse[1].0 - sse[0].0;
        // Every candidate must be fitted by a positive scale: where one
        // is not, the fringe is too weak for its shape to tell.
        let all_fitted = sse.iter().all(|c| c.0.is_finite());
        if !(all_fitted && sse[0].2 && margin / birge >= RESOLVE_CHI2 && margin >= sse[0].0) {
            return None;
        }
        let (d_c, sigma_c) = cands[sse[0].1];
        // The chosen film must put as many extrema in the band as were
        // found: a lamp's bump on a thin film can mimic a fringe's shape,
        // not its count.
        if f.extrema_expected(sse[0].3) != f.fit.n_extrema {
            return None;
        }
        if f.fit.n_extrema > 1 {
            return Some((d_c, sigma_c));
        }
        // One extremum: its order is read from the hump's width, which a
        // lamp's bump can change. The same order must win, by the same
        // margins, when the scale may curve too.
        let curved = self.candidate_minima(&cands, half_order, &mut |d| sse_at(d, true));
        let curved_margin = curved[1].0 - curved[0].0;
        let curved_birge = (curved[0].0 / n_ok.saturating_sub(6).max(1) as f64).max(1.0);
        if !(curved[0].1 == sse[0].1
            && curved_margin / curved_birge >= RESOLVE_CHI2
            && curved_margin >= curved[0].0)
        {
            return None;
        }
        // One extremum: its position is pulled by the envelope, so the
        // shape's own minimum, σ from the profile's curvature (scaled as
        // the χ²), never below the extremum's.
        let d = sse[0].3;
        let h = 1e-3 * d.max(1.0);
        let curv = (sse_at(d + h, false) + sse_at(d - h, false) - 2.0 * sse[0].0) / (h * h);
        let sigma = if curv > 0.0 {
            (2.0 * birge / curv).sqrt().max(sigma_c * d / d_c)
        } else {
            f64::INFINITY
        };
        // The answer must not hinge on the envelope: with a constant
        // offset instead of a sloped one, the minimum near it must stay
        // within σ (the difference then joins σ).
        let mut flat_at = |d: f64| {
            shape.prep.model.eval(d, shape.theta, trial, false);
            let (r, u) = (&trial.r, shape.u);
            match fringes::weighted_lsq::<3>(shape.y, &shape.w, |k| [1.0, r[k], r[k] * u[k]]) {
                Some((sse, c)) if c[1] > 0.0 => sse,
                _ => f64::INFINITY,
            }
        };
        let (lo, hi) = (
            (d - 2.0 * sigma).max(self.d_min),
            (d + 2.0 * sigma).min(self.d_max),
        );
        let (d_flat, v_flat) = golden(lo, hi, &mut flat_at);
        let shift = (d_flat - d).abs();
        let pinned = d_flat - lo < 1e-3 * sigma || hi - d_flat < 1e-3 * sigma;
        (v_flat.is_finite() && !pinned && shift <= sigma).then_some((d, sigma.max(shift)))
    }

    /// Each candidate's best fit under `sse_at`, best first, as
    /// `(SSE, candidate, interior, d)`. Candidates are two orders apart;
    /// each is searched within half an order (a grid, then golden section
    /// on its best cell), short of the neighbouring order a sign-flipped
    /// scale would also fit; a minimum at the window's edge (not interior)
    /// belongs to no candidate.
    fn candidate_minima(
        &self,
        cands: &[(f64, f64)],
        half_order: f64,
        sse_at: &mut impl FnMut(f64) -> f64,
    ) -> Vec<(f64, usize, bool, f64)> {
        let mut sse: Vec<(f64, usize, bool, f64)> = cands
            .iter()
            .enumerate()
            .map(|(i, &(d0, _))| {
                let (lo, hi) = (
                    (d0 - half_order).max(self.d_min),
                    (d0 + half_order).min(self.d_max),
                );
                let step = (hi - lo) / RESOLVE_GRID as f64;
                let best = (0..=RESOLVE_GRID)
                    .map(|j| lo + step * j as f64)
                    .map(|d| (sse_at(d), d))
                    .min_by(|a, b| a.0.total_cmp(&b.0))
                    .map_or(lo, |b| b.1);
                let (d, v) = golden((best - step).max(lo), (best + step).min(hi), &mut *sse_at);
                let interior = d - lo > step && hi - d > step;
                (v, i, interior, d)
            })
            .collect();
        sse.sort_by(|a, b| a.0.total_cmp(&b.0));
        sse
    }

    /// Whether a film without a pair of fringes in the band (at most one
    /// extremum: a broad hump) explains the spectrum's shape about as well
    /// as `d` does (the shape model of
    /// [`resolve_orders`](Self::resolve_orders), `d` refined within half a
    /// step): then the few extrema found may be a lamp's bump and noise on
    /// a film too thin for fringes, and `d` cannot be trusted. (Films with
    /// more extrema than one but fewer than found are not asked: their
    /// positions were already weighed against the found ones.) Asked only
    /// where at most [`MAX_CANDIDATES`](fringes::MAX_CANDIDATES) extrema
    /// were found: more, standing out of the noise and spaced as one
    /// film's fringes, no single hump can mimic.
    fn thinner_film_fits(
        &self,
        shape: &ShapeFit,
        trial: &mut crate::estimate::model::ModelOut,
        d: f64,
    ) -> bool {
        let (f, n_ok) = (shape.fringes, shape.n_ok);
        if f.fit.n_extrema > fringes::MAX_CANDIDATES {
            return false;
        }
        let step_d = 1.0 / (4.0 * f.x_mean);
        // Two whole orders span the band from here up.
        let (x_lo, x_hi, _) = f.x_range;
        let top = (d - step_d).min(1.0 / (2.0 * (x_hi - x_lo).max(1e-12)));
        if top <= self.d_min {
            return false;
        }
        // Grid of an eighth of a step, then golden section on the best cell.
        let n = (((top - self.d_min) / (step_d / 8.0)).ceil() as usize).clamp(1, 4096);
        let h = (top - self.d_min) / n as f64;
        // With a straight scale, and with one that may curve (a lamp's
        // bump): the thin film must lose by the margin under both.
        [false, true].into_iter().any(|curved| {
            let mut sse_at = |d: f64| shape.sse(trial, d, curved);
            let (_, here) = golden(
                (d - 0.5 * step_d).max(self.d_min),
                (d + 0.5 * step_d).min(self.d_max),
                &mut sse_at,
            );
            let (best, v) = (0..=n)
                .map(|i| self.d_min + h * i as f64)
                .filter(|&x| f.extrema_expected(x) <= 1)
                .map(|x| (x, sse_at(x)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap_or((self.d_min, f64::INFINITY));
            let v = if v.is_finite() {
                golden((best - h).max(self.d_min), (best + h).min(top), &mut sse_at).1
            } else {
                v
            };
            let dof = n_ok.saturating_sub(5 + usize::from(curved)).max(1);
            let birge = (here / dof as f64).max(1.0);
            !here.is_finite() || (v - here) / birge < RESOLVE_CHI2
        })
    }

    /// A pixel's estimate from its fringe positions alone.
    fn fringe_estimate(
        &self,
        prep: &Prepared,
        f: &FringeFit,
        theta: f64,
        residual_rms: f64,
    ) -> PixelEstimate {
        let reason = if f.ambiguous {
            Reason::AmbiguousOrder
        } else if f.order_rms > MAX_ORDER_RMS {
            Reason::PoorFit
        } else if !(f.sigma.is_finite() && f.sigma <= MAX_FRINGE_RELATIVE_SIGMA * f.d) {
            Reason::NoFringe
        } else {
            self.bound_reason(prep, f.d, theta, Some(theta))
                .unwrap_or(Reason::Ok)
        };
        if !reason.is_valid() {
            return PixelEstimate::invalid(reason);
        }
        PixelEstimate {
            thickness_nm: f.d,
            n_film: prep.model.n2_mid(),
            theta_deg: theta.to_degrees(),
            sigma_thickness_nm: f.sigma,
            sigma_theta_deg: 0.0,
            residual_rms,
            reason,
        }
    }
}

/// One pixel's spectrum, weights and fringe analysis, for the shape model
/// `y ≈ (a₀ + a₁u) + R(d)·(c₀ + c₁u [+ c₂u²])` that settles the fringe
/// order where the positions leave it open.
struct ShapeFit<'a> {
    prep: &'a Prepared,
    theta: f64,
    fringes: &'a PixelFringes,
    y: &'a [f64],
    /// Each band's weight, the inverse of its noise variance.
    w: Vec<f64>,
    u: &'a [f64],
    /// Bands with a weight.
    n_ok: usize,
}

impl<'a> ShapeFit<'a> {
    fn new(
        prep: &'a Prepared,
        theta: f64,
        fringes: &'a PixelFringes,
        u: &'a [f64],
        scratch: &'a Scratch,
    ) -> ShapeFit<'a> {
        let w = fringes.weights(scratch);
        let n_ok = w.iter().filter(|&&w| w > 0.0).count();
        ShapeFit {
            prep,
            theta,
            fringes,
            y: &scratch.spectrum,
            w,
            u,
            n_ok,
        }
    }

    /// Weighted residual sum of squares of the shape model at thickness
    /// `d` (the scale `curved` or not); infinite where the scale is not
    /// positive mid-band (a negative one turns maxima into minima: the
    /// neighbouring order) or the fit is singular.
    fn sse(&self, trial: &mut crate::estimate::model::ModelOut, d: f64, curved: bool) -> f64 {
        self.prep.model.eval(d, self.theta, trial, false);
        let (r, u, y, w) = (&trial.r, self.u, self.y, &self.w);
        let fit = if curved {
            fringes::weighted_lsq::<5>(y, w, |k| [1.0, u[k], r[k], r[k] * u[k], r[k] * u[k] * u[k]])
                .map(|(sse, c)| (sse, c[2] > 0.0))
        } else {
            fringes::weighted_lsq::<4>(y, w, |k| [1.0, u[k], r[k], r[k] * u[k]])
                .map(|(sse, c)| (sse, c[2] > 0.0))
        };
        match fit {
            Some((sse, true)) => sse,
            _ => f64::INFINITY,
        }
    }
}

/// Golden-section minimum of `f` on `[lo, hi]`: `(x, f(x))`.
pub(super) fn golden(lo: f64, hi: f64, mut f: impl FnMut(f64) -> f64) -> (f64, f64) {
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut a, mut b) = (lo, hi);
    let (mut c, mut e) = (b - g * (b - a), a + g * (b - a));
    let (mut fc, mut fe) = (f(c), f(e));
    for _ in 0..48 {
        if fc < fe {
            (b, e, fe) = (e, c, fc);
            c = b - g * (b - a);
            fc = f(c);
        } else {
            (a, c, fc) = (c, e, fe);
            e = a + g * (b - a);
            fe = f(e);
        }
    }
    let x = 0.5 * (a + b);
    (x, f(x))
}

/// Residual sum of squares of `y ≈ R·(c0 + c1 u + … + c_m u^m) + b` for
/// each degree in [`DEGREES`], the coefficients solved by least squares.
fn profile_sse(s: &Scratch, r: &[f64], u: &[f64]) -> [f64; 3] {
    const N: usize = 6;
    // Normal equations of the largest basis; smaller ones are its leading
    // blocks (basis order: 1, R, R u, R u², R u³, R u⁴).
    let mut ata = [0.0f64; N * N];
    let mut aty = [0.0f64; N];
    let mut yy = 0.0;
    for k in 0..s.spectrum.len() {
        let w = s.weight[k];
        if w == 0.0 {
            continue;
        }
        let y = s.spectrum[k];
        let mut f = [1.0, r[k], 0.0, 0.0, 0.0, 0.0];
        for j in 2..N {
            f[j] = f[j - 1] * u[k];
        }
        yy += w * y * y;
        for i in 0..N {
            aty[i] += w * f[i] * y;
            for j in 0..=i {
                ata[i * N + j] += w * f[i] * f[j];
            }
        }
    }
    let mut out = [f64::INFINITY; 3];
    for (slot, &deg) in DEGREES.iter().enumerate() {
        let n = deg + 2;
        let mut a = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..=i {
                let v = ata[i * N + j];
                a[i * n + j] = v;
                a[j * n + i] = v;
            }
            a[i * n + i] *= 1.0 + 1e-12;
        }
        if let Some(c) = solve_spd(&a, n, &aty[..n]) {
            let fit: f64 = c.iter().zip(&aty[..n]).map(|(c, b)| c * b).sum();
            out[slot] = (yy - fit).max(0.0);
        }
    }
    out
}
