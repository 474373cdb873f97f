//! A pixel against a thickness table: from the previous pixel's basin
//! where that settles it, the scan's best minima otherwise, each refined
//! on the interpolant (or with the exact model between a binned map's
//! angles), judged as every fit is; runs of poor fits settled without a
//! scan.

use super::{GridMin, Hint, ThicknessTable, ORDER_GAP_SAFE, RAMP_STEPS};
use crate::estimate::noise::FlatNoise;
use crate::estimate::solver::alternatives::{OrderMargin, WEAK_FRINGES};
use crate::estimate::solver::poor::TABLE_MARGIN;
use crate::estimate::solver::refine::sse;
use crate::estimate::solver::unresolved::UnresolvedRun;
use crate::estimate::solver::{Effort, Fit, Prepared, Scratch, Solver};
use crate::estimate::{PixelEstimate, Reason};

/// Angles this close share a row's table walk (`fast` with the angle
/// free moves between angle bins along a row).
const NEAR_ANGLE_RAD: f64 = 0.2 * std::f64::consts::PI / 180.0;

impl Solver {
    /// One pixel against a table: the best grid minima (two in `balanced`,
    /// to judge the fringe order), each refined, then judged as every fit
    /// is. At the table's own angle the refinement runs on the interpolant;
    /// at a nearby one (a binned angle map) the minima are carried to the
    /// pixel's angle at equal optical thickness and refined with the exact
    /// model there.
    #[allow(clippy::too_many_arguments)]
    pub(in crate::estimate::solver) fn solve_table(
        &self,
        prep: &Prepared,
        table: &ThicknessTable,
        table_theta: f64,
        theta: f64,
        n_ok: usize,
        noise: Option<f64>,
        effort: Effort,
        lam_min: f64,
        scratch: &mut Scratch,
    ) -> (PixelEstimate, f64) {
        let exact = table_theta.to_bits() == theta.to_bits();
        if exact {
            if let Some(flat) = self.table_poor_noise(prep, theta, n_ok, noise, scratch) {
                if let Some(out) = self.poor_as_before(theta.to_bits(), flat, n_ok, 1, scratch) {
                    return out;
                }
            }
        }
        let key = theta.to_bits();
        if exact && effort.warm {
            if let Some(out) = self.unresolved_as_before(prep, table, theta, n_ok, false, scratch) {
                return out;
            }
        }
        // From the previous pixel's basin and its neighbouring orders, where
        // that settles the pixel; the full scan otherwise. (`fast` once
        // took the previous pixel's basin alone wherever it passed the χ²
        // test: at σ = 0.01 on the thin coating 1.2 % of its valid pixels
        // were a fringe order off.)
        if exact && effort.warm {
            // A hint from a nearby angle serves too (a row on its
            // estimated angle moves from bin to bin): the thickness moves
            // by d·Δq/q, ~0.1 % for 0.2° (12 nm at 10 µm, a tenth of a
            // fringe), within the walk's window.
            let near =
                |h: &Hint| h.key == key || (f64::from_bits(h.key) - theta).abs() < NEAR_ANGLE_RAD;
            if let Some(hint) = scratch.hint.filter(near) {
                let verify = effort.verify_order;
                let j0 = table.interval_index(hint.predicted(table.step()));
                if let Some(out) = self.table_warm(
                    prep, table, theta, j0, n_ok, noise, lam_min, verify, scratch,
                ) {
                    scratch.hint = Some(Hint {
                        key,
                        ..hint.then(out.0.thickness_nm)
                    });
                    // A valid pixel ends the run of poor ones: the next
                    // poor pixel scans and becomes the reference (the
                    // distance to a stale one would be paid on every
                    // pixel and seldom settle one).
                    scratch.poor = None;
                    scratch.unresolved = None;
                    return out;
                }
            }
            scratch.order_margin = None;
        }
        // The best minima: two in `fast` and `balanced` (the second judges
        // the fringe order), three in `accurate`.
        let mut mins = [GridMin { j: 0, sse: 0.0 }; 3];
        let keep = if effort.verify_order { 3 } else { 2 };
        scratch.table_scans += 1;
        let n = table.minima(
            &scratch.spectrum,
            &scratch.weight,
            &mut scratch.grid,
            &mut mins[..keep],
        );
        // At the table's own angle every minimum is fitted on the
        // interpolant (as good as exact here); `accurate` then refines with
        // the exact model those close to the best ([`Solver::refine_close`]).
        // Between a binned map's angles, every minimum is refined with the
        // exact model from its grid point at equal optical thickness.
        // Between a binned map's angles the runner-up is not refitted where
        // it is the best's neighbouring order and the table's noise-free
        // orders lie far apart there: every other basin scanned worse than
        // it, so none can come within the ambiguity margin.
        let n = if !exact && !effort.verify_order && n == 2 && self.order_settled(table, &mins) {
            1
        } else {
            n
        };
        let mut fits = [Fit::default(); 3];
        if exact {
            for (f, g) in fits.iter_mut().zip(&mins[..n]) {
                *f = self.table_fit(table, *g, theta, effort, scratch);
            }
            if effort.verify_order {
                self.refine_close(prep, theta, n_ok, &mut fits[..n], scratch);
            }
        } else {
            let scale = prep.model.q2_mid(table_theta) / prep.model.q2_mid(theta);
            for (f, g) in fits.iter_mut().zip(&mins[..n]) {
                let d0 = table.d_at(g.j) * scale;
                *f = self.exact_refit(prep, d0, theta, scratch);
            }
        }
        let out = self.finish(&fits[..n], n_ok, Some(theta), noise, prep, lam_min, scratch);
        // A scan that found nothing passing after the row's last pixel
        // past the range (its run spent): the walk from there, once more.
        if exact && effort.warm && out.0.reason == Reason::PoorFit {
            if let Some(out) = self.unresolved_as_before(prep, table, theta, n_ok, true, scratch) {
                scratch.poor = None;
                return out;
            }
        }
        scratch.hint = (exact && out.0.is_valid()).then(|| {
            let hint = scratch.hint.filter(|h| h.key == key);
            hint.unwrap_or(Hint::start(key)).then(out.0.thickness_nm)
        });
        if out.0.is_valid() {
            scratch.poor = None;
        }
        scratch.unresolved = (exact && out.0.reason == Reason::Unresolved)
            .then(|| UnresolvedRun::new(key, scratch.last_fit_d, theta));
        if exact && out.0.reason == Reason::PoorFit {
            let min_sse = fits[..n]
                .iter()
                .map(|f| f.sse)
                .fold(f64::INFINITY, f64::min);
            if let Some(flat) = self.table_poor_noise(prep, theta, n_ok, noise, scratch) {
                self.note_poor(
                    (theta.to_bits(), TABLE_MARGIN, u32::MAX),
                    flat,
                    min_sse,
                    scratch,
                );
            }
        }
        out
    }

    /// A pixel after one the scan found beyond the resolved range (a
    /// thickness past what the bands resolve, flagged "fringes
    /// unresolved"), settled without a scan where its own fit says the
    /// same: the walk from that pixel's thickness on the interpolant ends
    /// beyond the range and passes the χ² test. Such a pixel is flagged
    /// whatever a scan would add: another basin in range that fits about
    /// as well flags it ambiguous; one that fits clearly better would be
    /// an alias the bands cannot tell from it (a film's thickness moves
    /// little from one pixel to the next, so the walk stays in its
    /// basin; see [`crate::estimate::solver::unresolved`]). The table's
    /// grid reaches twice the resolved range for these walks
    /// ([`ThicknessTable::new_reaching`]); the scan keeps to the range.
    /// The thick hard coat's 28 % of such pixels each took a scan (or the
    /// poor reference's test beside it): ~2.3 µs against ~0.5 µs for a
    /// valid pixel. Every mode: `accurate` weighs every pixel's order,
    /// but only to judge a fit it may call valid, and these it flags
    /// whatever the order (as with the angle free). `renew`: after a scan
    /// that found nothing passing, the spent run's last fit is walked
    /// from once more and, where that settles the pixel, starts a run
    /// afresh.
    fn unresolved_as_before(
        &self,
        prep: &Prepared,
        table: &ThicknessTable,
        theta: f64,
        n_ok: usize,
        renew: bool,
        scratch: &mut Scratch,
    ) -> Option<(PixelEstimate, f64)> {
        let run = scratch
            .unresolved
            .filter(|u| u.key == theta.to_bits() && (renew || u.left > 0))?;
        let j0 = table.interval_index(run.predicted(RAMP_STEPS * table.step()));
        let (d, sse, _) = table.fit_near(&scratch.spectrum, n_ok, j0)?;
        if self.bound_reason(prep, d, theta, Some(theta)) != Some(Reason::Unresolved) {
            return None;
        }
        let (chi2, _) = self.tabled_chi2(table, d, sse, (n_ok, 1), scratch)?;
        if !self.fit_passes(chi2, n_ok, 1) {
            return None;
        }
        scratch.unresolved = Some(run.after(d, theta, renew));
        scratch.last_fit_d = d;
        scratch.last_fit_theta = theta;
        Some((PixelEstimate::invalid(Reason::Unresolved), sse))
    }

    /// Where a poor pixel's bound ([`super::super::poor`]) applies on the
    /// table at `theta`: as everywhere (judged, one variance per band, a
    /// complete spectrum), and the fringes there leave the pixel no
    /// competitor beyond the table (the alternative checks add no fit at a
    /// known angle, so the scan's minima are every fit weighed).
    fn table_poor_noise(
        &self,
        prep: &Prepared,
        theta: f64,
        n_ok: usize,
        noise: Option<f64>,
        scratch: &Scratch,
    ) -> Option<&FlatNoise> {
        let flat = self.poor_noise(n_ok, noise, scratch)?;
        let sigma = noise?;
        (self.fringe_signal(prep, theta, n_ok, sigma, scratch) >= WEAK_FRINGES).then_some(flat)
    }

    /// `balanced` (and `accurate`) from grid interval `j0`, the one
    /// holding the previous pixel's fit (a film changes little from one pixel to the next): the
    /// residual's minimum walked to from there, and the better of its
    /// neighbouring fringe
    /// orders (one fringe more or fewer in optical thickness) walked to in
    /// turn, judged together as the scan's two best minima are (an order
    /// that fits as well flags the pixel ambiguous). `Some` only where that
    /// settles the pixel: the fringes strong enough that no other basin
    /// can pass the χ² test beside the fit (the gates of the alternative
    /// checks, [`Solver::fringes_exclude_alternatives`]), both walks ending
    /// at a minimum of the interpolant, and the estimate valid; anything
    /// else (an order jump, an edge, a flag) takes the full scan.
    /// `accurate` (`verify`) weighs the order on every pixel and refines
    /// the fits close to the best with the exact model, as after its scan.
    #[allow(clippy::too_many_arguments)]
    fn table_warm(
        &self,
        prep: &Prepared,
        table: &ThicknessTable,
        theta: f64,
        j0: usize,
        n_ok: usize,
        noise: Option<f64>,
        lam_min: f64,
        verify: bool,
        scratch: &mut Scratch,
    ) -> Option<(PixelEstimate, f64)> {
        let sigma = noise.filter(|_| self.judging())?;
        if !self.fringes_exclude_alternatives(
            self.fringe_signal(prep, theta, n_ok, sigma, scratch),
            false,
        ) {
            return None;
        }
        let (d, e, a) = table.fit_near(&scratch.spectrum, n_ok, j0)?;
        let fit = Fit {
            d,
            theta,
            sse: e,
            jtj: [a, 0.0, 0.0],
            tabled: true,
            stalled: false,
            chi2: None,
        };
        let dd = 0.5 / self.table.sigma_center / scratch.q2_mid(prep, theta);
        let mut fits = [fit; 2];
        let key = theta.to_bits();
        // Where the previous pixel's neighbouring order fell far short of
        // its fit and this fit moved little, it is not weighed again.
        let carried = OrderMargin::carried(scratch.order_margin, key, d, dd).filter(|_| !verify);
        // Nor where the noise-free orders lie far apart at this thickness.
        // (Compared as a product: the branch does not wait on a division.)
        let gap = self
            .max_noise_var_at(prep, table, theta, scratch)
            .map(|v| (table.order_gap(d), v))
            .filter(|&(g, v)| g >= ORDER_GAP_SAFE * v);
        let (n, margin) = if let Some((g, v)) = gap.filter(|_| !verify) {
            (1, g / v)
        } else if let Some(m) = carried {
            (1, m)
        } else {
            let (lo, hi) = table.d_range();
            let mut trial = std::mem::take(&mut scratch.trial);
            let mut alt: Option<(f64, f64)> = None;
            for da in [d - dd, d + dd] {
                if !(lo..=hi).contains(&da) {
                    continue;
                }
                table.values(da, &mut trial.r);
                let ea = sse(&scratch.spectrum, &scratch.weight, &trial.r);
                if alt.is_none_or(|(_, b)| ea < b) {
                    alt = Some((da, ea));
                }
            }
            scratch.trial = trial;
            match alt {
                Some((da, _)) => {
                    let j = table.interval_index(da);
                    let (d2, e2, a2) = table.fit_near(&scratch.spectrum, n_ok, j)?;
                    fits[1] = Fit {
                        d: d2,
                        sse: e2,
                        jtj: [a2, 0.0, 0.0],
                        ..fit
                    };
                    (2, (e2 - e) / (sigma * sigma))
                }
                None => (1, f64::INFINITY),
            }
        };
        scratch.order_margin = Some(OrderMargin::new(key, d, margin));
        if verify {
            self.refine_close(prep, theta, n_ok, &mut fits[..n], scratch);
        }
        let out = self.finish(&fits[..n], n_ok, Some(theta), noise, prep, lam_min, scratch);
        out.0.is_valid().then_some(out)
    }

    /// Whether the scan's runner-up `mins[1]` is the best's (`mins[0]`)
    /// neighbouring fringe order (half to one and a half fringes away,
    /// give or take a grid step; not a second dip of the same basin) and
    /// the noise-free orders there lie ≥ [`ORDER_GAP_SAFE`] noise
    /// variances apart ([`ThicknessTable::order_gap`]): then the runner-up
    /// trails by about that gap, and every basin farther off trails it.
    fn order_settled(&self, table: &ThicknessTable, mins: &[GridMin]) -> bool {
        let [best, second, ..] = mins else {
            return false;
        };
        let apart = best.j.abs_diff(second.j) as f64;
        (0.5 * table.fringe - 1.0..=1.5 * table.fringe + 1.0).contains(&apart)
            && self
                .max_noise_var_on(table)
                .is_some_and(|v| table.order_gap(table.d_at(best.j)) >= ORDER_GAP_SAFE * v)
    }

    /// [`Self::max_noise_var_on`] for the table at `theta`, its own
    /// angle, kept for the next pixel at that angle.
    fn max_noise_var_at(
        &self,
        prep: &Prepared,
        table: &ThicknessTable,
        theta: f64,
        scratch: &Scratch,
    ) -> Option<f64> {
        let mut memo = scratch.angle_memo(prep, theta);
        if let Some((_, v)) = memo.max_var.filter(|m| m.0 == self.noise_gen) {
            return Some(v);
        }
        let v = self.max_noise_var_on(table)?;
        memo.max_var = Some((self.noise_gen, v));
        scratch.angle_memo.set(Some(memo));
        Some(v)
    }

    /// The largest noise variance of any band at the reflectances `table`
    /// spans (`None` without a noise model).
    fn max_noise_var_on(&self, table: &ThicknessTable) -> Option<f64> {
        self.max_noise_var_below(table.r_max())
    }

    /// The largest noise variance of any band at reflectances up to
    /// `r_max` (`None` without a noise model; a flat model's one largest).
    pub(in crate::estimate::solver) fn max_noise_var_below(&self, r_max: f64) -> Option<f64> {
        if self.flat_noise.is_some() {
            return Some(self.max_flat_var);
        }
        self.noise.as_ref().map(|n| n.max_var_below(r_max))
    }

    /// `accurate`: the fits on the interpolant within 25 residual variances
    /// of the best refined with the exact model (and the passband
    /// integrated where the band criterion asks for it); a clearly worse
    /// order cannot become the best or an ambiguity
    /// ([`super::fringes::AMBIGUITY_CHI2`] variances).
    fn refine_close(
        &self,
        prep: &Prepared,
        theta: f64,
        n_ok: usize,
        fits: &mut [Fit],
        scratch: &mut Scratch,
    ) {
        let best = fits.iter().map(|f| f.sse).fold(f64::INFINITY, f64::min);
        let var = best / n_ok.saturating_sub(1).max(1) as f64;
        for f in fits.iter_mut().filter(|f| f.sse <= best + 25.0 * var) {
            *f = self.exact_refit(prep, f.d, theta, scratch);
        }
    }

    /// The exact model's fit at the known `theta` from `d0`.
    fn exact_refit(&self, prep: &Prepared, d0: f64, theta: f64, scratch: &mut Scratch) -> Fit {
        let iters = Effort::of(self.mode).iters;
        self.refine(&prep.model, d0, theta, false, iters, scratch)
    }

    /// Refine grid minimum `g` on the interpolant.
    fn table_fit(
        &self,
        table: &ThicknessTable,
        g: GridMin,
        theta: f64,
        effort: Effort,
        scratch: &mut Scratch,
    ) -> Fit {
        let (y, w) = (&scratch.spectrum, &scratch.weight);
        let (d, sse, a) = table.fit(y, w, g.j, effort.iters, &mut scratch.grid);
        Fit {
            d,
            theta,
            sse,
            jtj: [a, 0.0, 0.0],
            tabled: true,
            stalled: false,
            chi2: None,
        }
    }
}
