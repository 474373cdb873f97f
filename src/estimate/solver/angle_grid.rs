//! The index search's extra angle starts: a grid of angles beside the one
//! the fringe envelope gives.
//!
//! With the angle free, a pixel's search starts from the angle whose model
//! envelopes match the spectrum's level and fringe contrast. On a thin film
//! (a fringe or less in the band) the level is all there is, and in p light
//! or unpolarised light it is matched on both sides of a Brewster angle (or
//! by another index–angle pair that swaps the two interfaces' reflections):
//! one start sees one side. That is harmless for an image's pixels, whose
//! neighbours, mirror angles and alternatives are weighed on the way, but
//! the film-index search fits a sample of lone pixels at each trial index,
//! and a profile whose fits miss their basin at the true index is a profile
//! with its minimum elsewhere: p light at 65° on a 10–190 nm film of 1.38
//! gave n = 1.731 ± 0.0005 with 39 of 40 thicknesses valid and ~35 % off.
//!
//! So where the best of the index search's own fits leaves a lone pixel
//! below one and a half fringes ([`THIN`]), it also starts it from a grid
//! of angles, each at the fringe candidates' thicknesses and at optical
//! thicknesses a sixteenth of a fringe apart, and refines the
//! [`GRID_REFINED`] best. Gated on the best fit, not on any: a sub-fringe
//! start refines to a thin fit on almost every pixel, and the grid on
//! every pixel doubled the paper's index search and bent a dispersive
//! film's misfit (one index for fused silica) into a level its thinner and
//! thicker films shared, which the level's halves test then missed.
//!
//! The twin test's runner-up index is searched further
//! ([`PINNED_RAD`]): there a fit pinned at an end of the angle range takes
//! the grid too, whatever its thickness.

use super::refine::sse;
use super::search::Candidate;
use super::{Fit, Prepared, Scratch, Solver};

/// The grid's angles, degrees.
const GRID_DEG: [f64; 9] = [5.0, 15.0, 25.0, 35.0, 45.0, 55.0, 65.0, 75.0, 85.0];

/// Optical thicknesses of the grid: 0 to [`THIN`] in steps of λ_min/32
/// (a sixteenth of a fringe at the bluest band, whose fringe is λ_min/2 of
/// optical thickness: a start well within its basin's quarter fringe).
const GRID_G_STEP: f64 = 1.0 / 32.0;
const GRID_G_STEPS: usize = 24;

/// A pixel whose search's best fit lies below this optical thickness (in
/// λ_min: one and a half fringes at the bluest band) is a thin film the
/// grid serves; thicker films show fringes enough for their envelope.
/// (Three fringes served more, but cost the paper's cylinder's index
/// search 2.7×: most of its films lie below.)
pub(super) const THIN: f64 = GRID_G_STEP * GRID_G_STEPS as f64;

/// A lone pixel's best fit this close to an end of the angle range (rad,
/// a tenth of a degree) is pinned there; where the search asks for it
/// (the twin test's runner-up), the grid serves it whatever its
/// thickness: R is even in θ, so normal incidence is a stationary point
/// every refinement can stall at.
pub(super) const PINNED_RAD: f64 = 1.75e-3;

/// Grid starts refined.
const GRID_REFINED: usize = 2;

impl Solver {
    /// The best [`GRID_REFINED`] grid starts refined, into `out`; returns
    /// how many.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn angle_grid_fits(
        &self,
        prep: &Prepared,
        cands: &[Candidate],
        lam_min: f64,
        iters: usize,
        scratch: &mut Scratch,
        out: &mut [Fit],
    ) -> usize {
        let (lo, hi) = self.theta_range;
        // (d, θ, sse) of the best starts so far, worst last.
        let mut best = [(0.0, 0.0, f64::INFINITY); GRID_REFINED];
        for deg in GRID_DEG {
            let th = deg.to_radians();
            if th < lo || th > hi {
                continue;
            }
            let q2 = prep.model.q2_mid(th);
            let sub = (0..=GRID_G_STEPS).map(|j| j as f64 * GRID_G_STEP * lam_min / q2);
            let ds = cands.iter().map(|c| c.g / q2).chain(sub);
            for d in ds {
                if !d.is_finite() {
                    continue;
                }
                prep.model.eval(d, th, &mut scratch.cur, false);
                let e = sse(&scratch.spectrum, &scratch.weight, &scratch.cur.r);
                if e < best[GRID_REFINED - 1].2 {
                    best[GRID_REFINED - 1] = (d, th, e);
                    best.sort_by(|a, b| a.2.total_cmp(&b.2));
                }
            }
        }
        scratch.cur_at = None;
        let mut n = 0;
        for &(d, th, e) in &best {
            if n >= out.len() || !e.is_finite() {
                continue;
            }
            out[n] = self.refine(&prep.model, d, th, true, iters, scratch);
            n += 1;
        }
        n
    }
}
