//! Runs of films past the resolved range settled without a search. Once a
//! full search (a table's scan, or the angle-free fringe search with its
//! starts and alternatives) flagged a pixel "fringes unresolved" — its
//! fit passes the χ² test at an optical thickness beyond what the bands
//! resolve — the next pixels of the row start from that fit: where a
//! pixel's own fit from there also ends beyond the range and passes, it
//! is flagged the same without the search. Such a pixel is flagged
//! whatever a search would add: another basin in range that fits about
//! as well flags it ambiguous; one that fits clearly better would be an
//! alias the bands cannot tell from it (a film's thickness moves little
//! from one pixel to the next, so the fit stays in its basin). At most
//! [`UNRESOLVED_RUN`] pixels follow one search.
//!
//! On a table the fit is the walk on the interpolant
//! (`table::solve`, `fast` and `balanced`: `accurate` weighs every
//! pixel's order there, at a scan's cost of ~2 µs). With the angle free
//! it is a refinement in thickness and angle (here, every mode), and one
//! more fit weighed where a search found nothing passing: the search it
//! spares costs 20–50 model evaluations (on the thick hard coat, angle
//! unknown, `balanced`: 14–23 µs a pixel past the range against 5.5 µs
//! for a valid one, the 28 % of the image past the range 53 % of its
//! time).

use super::poor::FREE_ANGLE;
use super::{Prepared, Scratch, Solver};
use crate::estimate::{PixelEstimate, Reason};

/// Pixels one search beyond the resolved range may settle before a
/// search runs again. Every pixel a run settles is flagged, so the bound
/// limits only how long flags go unconfirmed by a search (a film that
/// returns into range ends the run at once: its walk no longer ends past
/// the range). 16 until 2026-12-06; at 64 the thick hard coat with its
/// angle known, `fast`, one thread, ran 8–18 % faster (a scan ~2.2 µs, a
/// run's pixel one walk on the interpolant), reason codes identical.
pub(super) const UNRESOLVED_RUN: u32 = 64;

/// The row's last pixel a search found beyond the resolved range: the
/// search (a table's angle bits, or [`FREE_ANGLE`]), its fit's thickness
/// and angle (and the thickness of the run's pixel before it, NaN at its
/// start), and how many pixels may still follow it without a search.
#[derive(Clone, Copy, Debug)]
pub(super) struct UnresolvedRun {
    pub(super) key: u64,
    pub(super) d: f64,
    pub(super) before: f64,
    pub(super) theta: f64,
    pub(super) left: u32,
}

impl UnresolvedRun {
    /// A run from a search under `key` that flagged its pixel at
    /// (`d`, `theta`).
    pub(super) fn new(key: u64, d: f64, theta: f64) -> UnresolvedRun {
        UnresolvedRun {
            key,
            d,
            before: f64::NAN,
            theta,
            left: UNRESOLVED_RUN,
        }
    }

    /// The next pixel's likely thickness: on the line through the run's
    /// last two fits where they lie at most `most` apart, else the last
    /// ([`super::on_ramp`]). A film past the range still moves along its
    /// ramp: on the thick hard coat two grid steps a pixel, which a walk
    /// from the last fit crossed interval by interval.
    pub(super) fn predicted(&self, most: f64) -> f64 {
        super::on_ramp(self.d, self.before, f64::NEG_INFINITY, most)
    }

    /// The run after one more pixel settled at (`d`, `theta`), free to
    /// settle [`UNRESOLVED_RUN`] pixels again where `renewed` (a search
    /// found nothing passing and the run settled the pixel instead): on
    /// its ramp still.
    pub(super) fn after(self, d: f64, theta: f64, renewed: bool) -> UnresolvedRun {
        let next = self.then(d, theta);
        if renewed {
            UnresolvedRun {
                left: UNRESOLVED_RUN,
                ..next
            }
        } else {
            next
        }
    }

    /// The run after one more pixel settled at (`d`, `theta`).
    fn then(self, d: f64, theta: f64) -> UnresolvedRun {
        UnresolvedRun {
            d,
            before: self.d,
            theta,
            left: self.left.saturating_sub(1),
            ..self
        }
    }
}

impl Scratch {
    /// After an angle-free pixel: a full search that found its film past
    /// the resolved range (`reason`) starts a run, a pixel the run settled
    /// continues it, anything else ends it. Out of line, as the rest of
    /// this module: inlined into the per-pixel path, this bookkeeping
    /// slowed the thin coating's valid pixels by 5–8 % (code generation;
    /// measured interleaved).
    /// No run past the resolved range to follow (before a pixel solved
    /// out of the row's order: the scaled refits of a valid pixel).
    pub(super) fn end_unresolved_run(&mut self) {
        self.unresolved = None;
        self.unresolved_settled = false;
    }

    #[inline(never)]
    pub(super) fn note_unresolved(&mut self, reason: Reason) {
        if std::mem::take(&mut self.unresolved_settled) {
            return;
        }
        let at = (self.last_fit_d, self.last_fit_theta);
        self.unresolved = (reason == Reason::Unresolved && at.0.is_finite() && at.1.is_finite())
            .then(|| UnresolvedRun::new(FREE_ANGLE, at.0, at.1));
    }
}

impl Solver {
    /// How far a run past the resolved range may follow a film whose
    /// normal wave vector at the band centre is `q` (`n2 cos θ2`): twice
    /// the resolved range, as the check for a film past the range looks,
    /// where the range is the physics'; `None` where the user set it (a
    /// film past it is "at search bound" instead). The angle-free
    /// refinement's bound and the tables' reach.
    pub(super) fn run_reach(&self, q: f64) -> Option<f64> {
        (!self.d_max_given).then(|| 2.0 * self.g_max.0 / q)
    }

    /// With the angle free: the pixel in `scratch` refined from the row's
    /// last unresolved fit, and flagged "fringes unresolved" where that
    /// fit converged beyond the resolved range and passes the χ² test
    /// (judged pixels only; `n_ok` bands used, `iters` the mode's
    /// refinement budget). Before a search, only while the run may still
    /// settle pixels; after a search that found nothing passing
    /// (`searched`), also from a run that may not: the fit is then one
    /// more weighed beside the search's, and the only one that passes.
    /// A pixel settled here marks itself so (`unresolved_settled`), for
    /// [`Scratch::note_unresolved`] to keep the run as this left it.
    /// (Where the run may still settle pixels, the same refinement failed
    /// before the search; skipping its repeat gained nothing measurable.)
    #[inline(never)]
    pub(super) fn unresolved_free(
        &self,
        prep: &Prepared,
        n_ok: usize,
        iters: usize,
        searched: bool,
        scratch: &mut Scratch,
    ) -> Option<(PixelEstimate, f64)> {
        let run = scratch
            .unresolved
            .filter(|u| u.key == FREE_ANGLE && (searched || u.left > 0))?;
        // Past the search's range too (to twice the resolved one, as the
        // check for a film past the range looks), unless the range is the
        // user's: a film there is flagged all the same, and the row's
        // run follows it instead of a search per pixel.
        let d_hi = self
            .run_reach(prep.model.q2_mid(run.theta))
            .map_or(self.d_max, |r| self.d_max.max(r));
        let range = (self.d_min, d_hi);
        let d0 = run.predicted(self.ramp_limit(prep));
        let fit = self.refine_within(&prep.model, d0, run.theta, true, iters, range, scratch);
        if fit.stalled || !(fit.sse.is_finite() && fit.d.is_finite() && fit.theta.is_finite()) {
            return None;
        }
        if self.bound_reason(prep, fit.d, fit.theta, None) != Some(Reason::Unresolved) {
            return None;
        }
        let (chi2, _) = fit.chi2?;
        if !self.fit_passes(chi2, n_ok, 2) {
            return None;
        }
        // After a search the run starts afresh, on its ramp still.
        scratch.unresolved = Some(run.after(fit.d, fit.theta, searched));
        scratch.unresolved_settled = true;
        scratch.last_fit_d = fit.d;
        scratch.last_fit_theta = fit.theta;
        Some((PixelEstimate::invalid(Reason::Unresolved), fit.sse))
    }
}
