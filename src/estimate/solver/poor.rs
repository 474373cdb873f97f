//! Runs of poor fits settled without a search. Once a full search (a
//! table's scan, or the angle-free fringe search with its starts and
//! alternatives) found nothing that fits a pixel, its spectrum is kept
//! with a floor under `√χ²` at every fit searched. By the triangle
//! inequality in the χ² norm, a later pixel of the row whose spectrum lies
//! within `dist` of it has `√χ² ≥ floor − dist` everywhere too; where that
//! exceeds a margin times the test's `√threshold` it is flagged "poor fit"
//! without a search. The reference stands until a search runs again or a
//! pixel comes out valid (a run of pixels past the resolved range, a
//! defect, a coating the model does not describe: a search costs tens of
//! fits, the distance one pass over the bands).
//!
//! The floor rests on what every "poor fit" flag rests on: that the
//! search's best fit is the spectrum's best. A table's scan visits every
//! thickness of its grid, so there the margin is 2 (χ² above four times
//! the threshold everywhere). The angle-free search starts from a few
//! fringe candidates and can miss the basin that fits (counted on the
//! scene matrix: references whose floor was 5–8 `√threshold` beside
//! pixels that fitted); there a reference serves only a spectrum far from
//! every fit (a margin of [`FREE_MARGIN`]) and at most [`FREE_RUN`]
//! pixels before a search runs again, so a search that missed costs a
//! bounded run of flags, never a wrong valid pixel.

use super::{Scratch, Solver};
use crate::estimate::noise::FlatNoise;
use crate::estimate::{PixelEstimate, Reason};

/// The reference key of the angle-free search (a table's is its angle's
/// bits; no finite angle has these).
pub(super) const FREE_ANGLE: u64 = u64::MAX;

/// The angle-free search's margin, in `√threshold` (χ² above 100× the
/// test's threshold at every fit).
pub(super) const FREE_MARGIN: f64 = 10.0;

/// Pixels one angle-free reference may settle before a search runs again.
pub(super) const FREE_RUN: u32 = 16;

/// A table scan's margin (exhaustive on its grid).
pub(super) const TABLE_MARGIN: f64 = 2.0;

/// The row's reference: a poor pixel's search, floor and how far it
/// still serves; its spectrum in `Scratch::poor_y`.
#[derive(Clone, Copy, Debug)]
pub(super) struct PoorRef {
    /// The search: a table's angle bits, or [`FREE_ANGLE`].
    key: u64,
    /// A floor under `√χ²` of the reference at every fit searched.
    floor: f64,
    /// The margin it must clear, in `√threshold`.
    margin: f64,
    /// Pixels it may still settle.
    left: u32,
}

impl Solver {
    /// The noise under which the bound applies to a pixel of `n_ok` bands:
    /// the fits are judged, with one variance per band, and the spectrum
    /// is complete (every weight 1).
    pub(super) fn poor_noise(
        &self,
        n_ok: usize,
        noise: Option<f64>,
        scratch: &Scratch,
    ) -> Option<&FlatNoise> {
        noise.filter(|_| self.judging())?;
        let flat = self.flat_noise.as_ref().filter(|_| self.noise.is_some())?;
        (n_ok == scratch.weight.len()).then_some(flat)
    }

    /// After a full search flagged the pixel in `scratch` "poor fit": its
    /// spectrum as the row's reference under `key` (to settle at most
    /// `run` pixels, beyond `margin`), with the floor
    /// `√(SSE_min · min 1/σ²)` (χ² weighs each band by at least the
    /// smallest inverse variance; `min_sse` is the least residual of every
    /// fit the search weighed).
    pub(super) fn note_poor(
        &self,
        (key, margin, run): (u64, f64, u32),
        flat: &FlatNoise,
        min_sse: f64,
        scratch: &mut Scratch,
    ) {
        let floor = (min_sse * flat.min_inv_var()).sqrt();
        if floor.is_finite() {
            scratch.poor_y.clear();
            scratch.poor_y.extend_from_slice(&scratch.spectrum);
            scratch.poor = Some(PoorRef {
                key,
                floor,
                margin,
                left: run,
            });
        }
    }

    /// The pixel in `scratch` flagged "poor fit" by the row's reference
    /// under `key`, where the bound settles it (`n_par` fitted parameters:
    /// the test's threshold is the pixel's own).
    pub(super) fn poor_as_before(
        &self,
        key: u64,
        flat: &FlatNoise,
        n_ok: usize,
        n_par: usize,
        scratch: &mut Scratch,
    ) -> Option<(PixelEstimate, f64)> {
        let r = scratch.poor.filter(|r| r.key == key && r.left > 0)?;
        if scratch.poor_y.len() != scratch.spectrum.len() {
            return None;
        }
        // Every weight is 1 here: the χ² between the two spectra.
        let (between, _) =
            flat.chi2_and_mean_var(&scratch.spectrum, &scratch.weight, &scratch.poor_y);
        let dist = between.sqrt();
        let threshold = self.chi2.threshold(n_ok.saturating_sub(n_par).max(1));
        (r.floor - dist > r.margin * threshold.sqrt()).then(|| {
            scratch.poor = Some(PoorRef {
                left: r.left - 1,
                ..r
            });
            scratch.last_fit_d = f64::NAN;
            (PixelEstimate::invalid(Reason::PoorFit), f64::NAN)
        })
    }
}
