//! The per-pixel solver and the global film-index search.
//!
//! Per pixel, in every mode but `fast`:
//!
//! 1. **Fringe search** (independent of the film index): the spectrum is
//!    projected on `A + B·cos(4π g / λ)` for a grid of optical thicknesses
//!    `g = d·n2·cos θ2` (basis and normal equations precomputed per band
//!    set, so a grid point costs one dot product). Local minima of the
//!    residual whose `B` has the sign the scene's indices allow (half-wave
//!    points are peaks for `n1 < n2 < n3`, valleys for `n2 > n3`) are the
//!    candidate fringe orders: the interference lattice of Eq. 12–15
//!    without a film-index grid.
//! 2. **Angle start** (only when unknown): the fitted `A ± B` are the
//!    half- and quarter-wave envelopes; the angle whose model envelopes
//!    match them best (Eq. 8–11 generalised to both envelopes, peaks or
//!    valleys) starts the refinement.
//! 3. **Refinement**: Levenberg–Marquardt on the unknowns (thickness, and the
//!    angle when unknown) with the exact model ([`super::model`]); standard
//!    errors from the Jacobian scaled by the residual variance.
//! 4. **Checks**: a second candidate order refined too; if it fits as well
//!    the pixel is flagged "ambiguous order". A weak angle is flagged "angle
//!    not identifiable" with its (large) σ.
//!
//! The film index, uniform over an object, is estimated once from a sample
//! of pixels by profiling the summed per-pixel residual over the index
//! (coarse grid, then a local quadratic fit), which also gives its standard
//! error. Both branches of the n2 ↔ n1·n3/n2 near-symmetry are located and
//! the χ² difference between them is reported; a prior breaks a tie the data
//! cannot.
//!
//! The stages, one file each:
//!
//! - `bands.rs`: the bands by wavelength, and the least-squares parabola
//!   window around each band.
//! - `search.rs`: the fringe search (1).
//! - `closed_form.rs`: the closed forms on the fringe extrema (`fast`, and
//!   the start of the other modes), and the angle start (2).
//! - `refine.rs`: the refinement (3) and the profile bounds on σ.
//! - `pixel.rs`: one pixel through the stages, and the checks (4).
//! - `order_gaps.rs`: how far apart the neighbouring fringe orders lie
//!   with the angle free, noise-free, on a grid (`balanced`'s warm pixels
//!   skip weighing orders that lie far apart).
//! - `weigh.rs`: the best fit refined with the bands weighed by their
//!   noise, where their variances differ (4a).
//! - `row.rs`: rows and whole cubes.
//! - `index.rs`: the global film-index search.
//! - `equivalents.rs`: the indices that reflect exactly as the one found
//!   (the twin, in p light the index of equal admittance), weighed as
//!   branches of the index.
//! - `angle_grid.rs`: the index search's extra angle starts for a thin
//!   lone pixel.
//! - `level_fit.rs`: the image-wide level (`scaled`, and `auto`'s test).
//! - `free.rs`: the per-pixel free level (normalised intensities).
//! - `judge.rs`: the fit-quality test and flags against the noise model,
//!   the physical thickness range and the search bounds.
//! - `passband.rs`: how many quadrature nodes each band's passband takes.
//! - `linalg.rs`: 3×3 linear algebra.

mod alternatives;
mod angle_grid;
mod angle_map;
mod band_shift;
mod bands;
mod closed_form;
mod equivalents;
mod free;
mod fringes;
mod image_fit;
mod index;
mod judge;
mod level_across;
mod level_drift;
pub use level_drift::{LevelDrift, DRIFT_SAMPLE_PIXELS, MAX_DRIFT_CHI2, MAX_DRIFT_CHI2_ONE};
mod level_fit;
mod level_hedge;
mod linalg;
mod order_gaps;
mod passband;
mod pixel;
mod poor;
mod profile_bias;
mod refine;
mod row;
mod search;
mod share;
mod table;
mod unresolved;
mod weigh;

use super::level::{Level, LevelMode};
use super::model::{FilmModel, ModelOut};
use super::noise::{FlatNoise, NoiseModel};
use super::quality::Chi2Test;
use super::range::RangeLimit;
use super::{EstimateError, Mode, PixelEstimate, Reason};
use crate::optics::band::Band;
use crate::optics::dispersion::Dispersion;
use crate::optics::Polarization;
use crate::scene::{AngleKnowledge, FilmKnowledge, Scene};
use bands::BandTable;
use closed_form::Slopes;
use index::SamplePixel;
use search::FringeBasis;
use share::{ShareScratch, ShareTable};
use std::cell::Cell;
use std::f64::consts::PI;
use std::sync::Arc;

/// The film index used for a fit: estimated once from the image, or known.
#[derive(Clone, Debug, PartialEq)]
pub struct IndexEstimate {
    /// Index (at the middle band for a dispersive known film).
    pub n: f64,
    /// Standard error (0 when known).
    pub sigma: f64,
    /// Whether it was estimated.
    pub estimated: bool,
    /// The other branch of the n2 ↔ n1·n3/n2 near-symmetry, if one was found.
    pub twin: Option<f64>,
    /// χ² by which the twin fits worse (large: resolved; small: ambiguous).
    pub twin_delta_chi2: f64,
    /// Typical reflectance noise σ of the noise model in force (NaN until
    /// one is known).
    pub noise_sigma: f64,
    /// A human-readable note (e.g. "twin not resolved; prior used").
    pub note: String,
    /// The twin branch fits about as well and nothing chose between them:
    /// every pixel's σ then spans both branches.
    pub ambiguous: bool,
    /// The estimate is pinned at a bound of its search range: every pixel
    /// is flagged "at search bound".
    pub at_bound: bool,
    /// Estimated jointly with the image-wide level: its share of σ_d is
    /// carried by the level's inflation factor, not added again.
    pub sigma_in_level: bool,
    /// The index found again on the sample scaled by 1 ± ε (a reflectance
    /// scale accurate to ε): half their spread is part of `sigma`, and each
    /// pixel's σ_d spans the thicknesses the two carry at the pixel's
    /// optical thickness (not a linearisation: one spectrum can put the two
    /// far apart).
    pub scale_branches: Option<[f64; 2]>,
    /// Where the index is ambiguous, the least and the greatest of the
    /// indices that fit as well (the twin among them): every pixel's σ_d
    /// spans the thicknesses they give it.
    pub branches: Option<[f64; 2]>,
}

/// The optical thickness `fast`'s angle bins tabulate to, for a sample
/// whose films reach `g`: as much again, and at least two orders at the
/// longest wavelength `lam_max` (one order is λ/2 in `g`).
fn bins_g_limit(g: f64, lam_max: f64) -> f64 {
    g + (0.5 * g).max(lam_max)
}

/// Pixels in a row whose closed form served nothing before `fast`'s row
/// path stops looking for one.
const CLOSED_FORM_SKIP_AFTER: u32 = 4;

/// While it does not look, it still does on every this-many-th pixel, so a
/// scene that changes along the row gets its closed form back.
const CLOSED_FORM_RETRY: u32 = 16;

/// Pixels sampled (on a jittered grid) for the global film-index search
/// (every mode).
pub const INDEX_SAMPLE_PIXELS: usize = 400;

/// Pixels sampled for an image-wide level once the index sample has shown
/// one (its gain trades with the pixels' angles: more pixels pin it).
pub const LEVEL_SAMPLE_PIXELS: usize = 1600;

/// Reflectance error of point sampling above which a band's passband is
/// integrated, in every mode, at the thickest optical thickness the range
/// holds: a tenth of a quiet camera's noise (1e-4). An error shared by
/// every pixel does not average out: on the paper's cylinder with 10 nm
/// passbands, point sampling erred by ~2e-4 (a fifth of its noise) and
/// every mode was biased by 1–3.6 nm with σ covering 6–44 % of the errors.
pub const INTEGRATION_TOLERANCE: f64 = 1e-5;

/// Largest number of bands a pixel may have.
pub const MAX_BANDS: usize = 512;

/// Band centres the solver accepts, nm: extreme ultraviolet to far
/// infrared. Outside, a "wavelength" is almost surely in the wrong unit
/// (0.4–0.7 read as nm), and the grids sized from it would be absurd.
pub const BAND_RANGE_NM: (f64, f64) = (10.0, 1.0e6);

/// Angle σ above which the angle is reported as not identifiable, degrees.
pub const ANGLE_SIGMA_LIMIT_DEG: f64 = 0.25;

/// Reusable per-thread working memory of the solver.
#[derive(Clone, Debug, Default)]
pub struct Scratch {
    /// One spectrum read from the cube (`fast`'s band-major pass, the
    /// scale accuracy's refits); the row's own pixels are read from
    /// `batch`.
    pixel: Vec<f64>,
    /// The row being solved, band by band (`row[k·width + x]`).
    row: Vec<f32>,
    /// [`row::GATHER`] pixels' spectra, pixel-major, gathered from `row`.
    batch: Vec<f64>,
    /// That spectrum scaled by 1 ± ε (the scale accuracy's refits).
    scaled: Vec<f64>,
    /// A row's angle samples (x, sin²θ, its σ) (`angle_map`).
    angle_samples: Vec<(f64, f64, f64)>,
    /// The same samples' table fits, `(x, g, d, σ_d)` (`angle_map`).
    sample_fits: Vec<(f64, f64, f64, f64)>,
    sorted_y: Vec<f64>,
    spectrum: Vec<f64>,
    weight: Vec<f64>,
    /// The bands used (1) and not (0), kept while `weight` holds the
    /// noise's weights (`Solver::weighed_fit`).
    band_mask: Vec<f64>,
    cur: ModelOut,
    /// What `cur` holds, where a refinement left it: a refinement
    /// starting there (the next pixel's warm start from this fit) need
    /// not evaluate it again. Whatever else writes `cur` clears it.
    cur_at: Option<refine::CurAt>,
    trial: ModelOut,
    /// The thickness table's working memory.
    grid: table::GridScratch,
    /// The previous pixel's table (angle bits) and fitted thickness, and
    /// the one before it at the same table (NaN where it had none), within
    /// the current row: where the walk on the table starts.
    hint: Option<table::Hint>,
    /// `balanced`: how far the previous pixel's neighbouring fringe order
    /// fell short of its fit, within the current row.
    order_margin: Option<alternatives::OrderMargin>,
    /// The stopping rule of the solve in progress (its `Effort`'s; 0 until
    /// a solve sets it, read as [`refine::STEP_CHI2`]).
    step_chi2: f64,
    /// The previous pixel's valid fit (d, θ) within the current row, the
    /// fitted path's first start (see `Solver::try_warm`).
    warm: Option<(f64, f64)>,
    /// The valid fit before `warm`, where the two were neighbours in the
    /// row: with it the warm start follows the row's ramp.
    warm_before: Option<(f64, f64)>,
    /// σ of `warm`'s thickness and angle (radians): a step between
    /// neighbours within a few σ is noise, not a ramp to follow.
    warm_sigma: (f64, f64),
    /// A pixel of the current row that no fit of a full search explained:
    /// the search (a table's angle bits, or `poor::FREE_ANGLE`) and a floor
    /// under its √χ² at every fit; its spectrum in `poor_y` (see
    /// `Solver::poor_as_before`).
    poor: Option<poor::PoorRef>,
    poor_y: Vec<f64>,
    /// The row's last pixel a search (a table's scan, or the angle-free
    /// fringe search) found beyond the resolved range, and how many may
    /// still follow it (`unresolved`).
    unresolved: Option<unresolved::UnresolvedRun>,
    /// The pixel just solved was settled by the angle-free run above.
    unresolved_settled: bool,
    /// Full scans of a thickness table made with this scratch.
    table_scans: usize,
    /// Fringe searches made (see [`Scratch::fringe_searches`]).
    fringe_searches: usize,
    /// The previous pixel in the row was settled by `balanced`'s closed
    /// form (its neighbour then looks for one first, before its warm start).
    closed_form_last: bool,
    /// Pixels in a row whose closed form served nothing (none found, or
    /// one its judgement did not keep); from
    /// [`CLOSED_FORM_SKIP_AFTER`] on, `fast`'s row path stops looking for
    /// it but on every [`CLOSED_FORM_RETRY`]th pixel.
    closed_form_misses: u32,
    /// The thickness of the last pixel's best fit, judged or not (NaN: no
    /// fit was made).
    last_fit_d: f64,
    /// Its angle, where the fit went through [`Solver::finish`] (the only
    /// reader, the index's profile bias, solves there).
    last_fit_theta: f64,
    /// Per pixel of the last row solved: that thickness.
    fits: Vec<f64>,
    /// The last angle's per-angle quantities (a row's pixels mostly share
    /// one known angle): see [`AngleMemo`].
    angle_memo: Cell<Option<AngleMemo>>,
    /// Where the last table lookup found its angle (`Tables::get_hinted`).
    table_hint: Cell<usize>,
    /// The last angle bin looked up, as (angle bits, bin)
    /// (`AngleBins::at_hinted`).
    bin_hint: Cell<Option<(u64, usize)>>,
    /// The level's share of σ (`Solver::with_level`).
    share: ShareScratch,
    /// A grid point's spectrum, weights and model evaluations while its
    /// neighbouring orders' gap is computed (`order_gaps`).
    gap_y: Vec<f64>,
    gap_w: Vec<f64>,
    gap_cur: ModelOut,
}

/// The next pixel's value of a coordinate along a row: on the line
/// through the last two fits `before` and `x` where their step is more
/// than `least` and at most `most` (a smaller step is noise, a larger one
/// an edge or an order change), else `x` (also where `before` is NaN).
/// Shared by the tables' walk ([`table::Hint`]) and the fitted path's warm
/// start ([`Scratch::warm_start`]).
fn on_ramp(x: f64, before: f64, least: f64, most: f64) -> f64 {
    let step = x - before;
    if step.abs() > least && step.abs() <= most {
        x + step
    } else {
        x
    }
}

impl Scratch {
    /// After [`Solver::solve_row`]: each pixel's best-fit thickness, nm,
    /// whether the fit passed its checks or was flagged (a poor fit still
    /// says where its minimum lies); NaN where no fit was made (missing
    /// bands, a spectrum beyond the model, a poor fit settled by its
    /// distance to an earlier one in the row without a scan).
    pub fn fit_thickness(&self) -> &[f64] {
        &self.fits
    }

    /// Full scans of a thickness table made with this scratch so far (a
    /// pixel a row settles from its neighbour's walk makes none).
    pub fn table_scans(&self) -> usize {
        self.table_scans
    }

    /// Fringe searches (stage 1, the angle-free path's full search) made
    /// with this scratch so far (a pixel a row settles from its
    /// neighbour's fit makes none).
    pub fn fringe_searches(&self) -> usize {
        self.fringe_searches
    }

    /// Forget the previous pixel (its table walk, fringe-order margin,
    /// warm start, poor or unresolved fit, closed form and the model
    /// evaluation its refinement left, which a start within rounding of it
    /// would take):
    /// what follows is solved as if first, whichever thread solved what
    /// before it.
    fn start_afresh(&mut self) {
        self.cur_at = None;
        self.hint = None;
        self.order_margin = None;
        self.warm = None;
        self.warm_before = None;
        self.closed_form_last = false;
        self.closed_form_misses = 0;
        self.poor = None;
        self.unresolved = None;
        self.unresolved_settled = false;
        self.step_chi2 = 0.0;
    }

    /// After a pixel of a row: [`Scratch::note_warm`], and its best-fit
    /// thickness (its last fit's where it was flagged) pushed to `fits`
    /// ([`Scratch::fit_thickness`]).
    fn note_fit(&mut self, est: &PixelEstimate, fits: &mut Vec<f64>) {
        self.note_warm(est);
        fits.push(if est.is_valid() {
            est.thickness_nm
        } else {
            self.last_fit_d
        });
    }

    /// After a pixel of a row: its fit as the next pixel's warm start if
    /// valid, none otherwise; a valid pixel also ends a run of poor ones.
    fn note_warm(&mut self, est: &PixelEstimate) {
        if est.is_valid() {
            // A valid pixel ends a run of poor ones (`poor`).
            self.poor = None;
        }
        let fit = est
            .is_valid()
            .then(|| (est.thickness_nm, est.theta_deg.to_radians()));
        self.warm_before = fit.and(self.warm);
        self.warm = fit;
        self.warm_sigma = (est.sigma_thickness_nm, est.sigma_theta_deg.to_radians());
    }

    /// The warm start (`warm`), on the row's ramp ([`on_ramp`]): each
    /// coordinate on the line through the last two fits where they lie
    /// apart by more than three of its σ (a smaller step is the fits'
    /// noise: extrapolated, it would double it) and close enough to be a
    /// slope, not an edge or an order change (`most_d` in thickness,
    /// [`Solver::ramp_limit`]; 0.6° in angle). Kept out of line: written
    /// into `try_warm`, it cost the thin coating's angle-free solve 13 %
    /// with the ramp disabled (measured), a code-generation effect.
    #[inline(never)]
    fn warm_start(&self, most_d: f64) -> Option<(f64, f64)> {
        let (d, th) = self.warm?;
        let Some((db, tb)) = self.warm_before else {
            return Some((d, th));
        };
        let (sd, st) = self.warm_sigma;
        Some((
            on_ramp(d, db, 3.0 * sd, most_d).max(0.0),
            on_ramp(th, tb, 3.0 * st, 0.01),
        ))
    }

    fn ensure(&mut self, n: usize) {
        if self.spectrum.len() != n {
            self.spectrum = vec![0.0; n];
            self.weight = vec![0.0; n];
            self.cur = ModelOut::new(n);
            self.cur_at = None;
            self.trial = ModelOut::new(n);
        }
    }

    /// Take `spectrum` in (sized to it): finite values weighted 1, the rest
    /// 0 and weighted 0; returns how many are finite.
    fn load(&mut self, spectrum: &[f64]) -> usize {
        self.ensure(spectrum.len());
        let mut n_ok = 0;
        for (k, &v) in spectrum.iter().enumerate() {
            let ok = v.is_finite();
            self.spectrum[k] = if ok { v } else { 0.0 };
            self.weight[k] = if ok { 1.0 } else { 0.0 };
            n_ok += usize::from(ok);
        }
        n_ok
    }

    /// The memo of `theta` under `prep`, begun afresh where the last one
    /// was another angle's or another model's.
    fn angle_memo(&self, prep: &Prepared, theta: f64) -> AngleMemo {
        let key = theta.to_bits();
        match self
            .angle_memo
            .get()
            .filter(|m| m.theta == key && m.prep == prep.id)
        {
            Some(m) => m,
            None => {
                let m = AngleMemo {
                    prep: prep.id,
                    theta: key,
                    q2: prep.model.q2_mid(theta),
                    signal: None,
                    max_var: None,
                };
                self.angle_memo.set(Some(m));
                m
            }
        }
    }

    /// `FilmModel::q2_mid(theta)` of `prep`'s model.
    fn q2_mid(&self, prep: &Prepared, theta: f64) -> f64 {
        self.angle_memo(prep, theta).q2
    }
}

/// What depends on the angle alone (and on the bands used and the noise),
/// kept for the next pixel at the same angle (a row's pixels mostly share
/// one known angle): the film's normal wave-vector component at the band
/// range's centre (`FilmModel::q2_mid`) and the fringe signal
/// (`Solver::fringe_signal`). Keyed by the [`Prepared`] it was computed
/// from (the index search solves with many models) and the angle's bits.
#[derive(Clone, Copy, Debug)]
struct AngleMemo {
    prep: u64,
    theta: u64,
    q2: f64,
    /// `(n_ok, σ bits, signal)` once asked for.
    signal: Option<(usize, u64, f64)>,
    /// `(noise generation, variance)`: the largest noise variance on the
    /// table at this angle, once asked for.
    max_var: Option<(u64, f64)>,
}

/// How hard the per-pixel solve works: what a [`Mode`] means in practice.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Effort {
    /// Try the closed-form extrema path first.
    closed_form: bool,
    /// Stop at the closed form.
    closed_form_only: bool,
    /// How many candidate starts are refined.
    n_refine: usize,
    /// With the angle free, also start a thin film from a grid of angles
    /// and optical thicknesses (the index search: see `angle_grid`).
    angle_grid: bool,
    /// ... and a fit pinned at an end of the angle range, whatever its
    /// thickness (the twin test's runner-up: see `angle_grid`).
    grid_pinned: bool,
    /// Iteration cap of each refinement.
    iters: usize,
    /// Fit against the thickness table where one was built for the
    /// pixel's angle (one unknown left).
    table: bool,
    /// After a closed-form start, also refine the best other fringe order
    /// and flag the pixel if it fits as well.
    verify_order: bool,
    /// Where the closed form does not apply, start from the previous
    /// pixel's valid fit in the row before searching (see `Solver::try_warm`).
    warm: bool,
    /// Refine the best fit once more with the bands weighed by their
    /// noise, where it differs between them (`weigh.rs`).
    weigh: bool,
    /// A refinement with the exact model stops where its next step would
    /// lower χ² by under this many noise variances (where its quadratic
    /// model has been borne out; [`refine::STEP_CHI2`] elsewhere).
    step_chi2: f64,
}

impl Effort {
    fn of(mode: Mode) -> Effort {
        match mode {
            Mode::Fast => Effort {
                closed_form: true,
                closed_form_only: true,
                n_refine: 1,
                angle_grid: false,
                grid_pinned: false,
                // A cap, not a count: converged fits stop early, and one
                // stopped short in a flat valley (thick films, angle
                // unknown) must not pass for a minimum.
                iters: 25,
                table: true,
                verify_order: false,
                warm: true,
                // `fast` keeps its speed: weighed alike, its error under a
                // camera's noise is 1.23× the efficient one.
                weigh: false,
                step_chi2: refine::FAST_STEP_CHI2,
            },
            Mode::Balanced => Effort {
                closed_form: true,
                closed_form_only: false,
                n_refine: 2,
                angle_grid: false,
                grid_pinned: false,
                iters: 25,
                table: true,
                verify_order: false,
                warm: true,
                weigh: true,
                step_chi2: refine::BALANCED_STEP_CHI2,
            },
            Mode::Accurate => Effort {
                closed_form: true,
                closed_form_only: false,
                n_refine: 3,
                angle_grid: false,
                grid_pinned: false,
                iters: 25,
                table: true,
                verify_order: true,
                warm: true,
                weigh: true,
                step_chi2: refine::STEP_CHI2,
            },
        }
    }

    /// The global index search and the level fit: the full candidate
    /// search (no noise level is known yet to judge a closed-form start),
    /// three orders refined to convergence — a fit left short of its
    /// minimum would pass its residual off as a calibration error (the
    /// strict stopping rule in every mode: 400 pixels each 0.1 variance
    /// short would move the level test's Δχ² by tens).
    const INDEX_SEARCH: Effort = Effort {
        closed_form: false,
        closed_form_only: false,
        n_refine: 3,
        angle_grid: true,
        grid_pinned: false,
        iters: 25,
        table: false,
        verify_order: false,
        warm: false,
        weigh: false,
        step_chi2: refine::STEP_CHI2,
    };
}

/// One pixel's solve request.
#[derive(Clone, Copy)]
struct Job<'a> {
    /// Reflectance per band (NaN: missing).
    spectrum: &'a [f64],
    /// Known angle, radians.
    theta_known: Option<f64>,
    /// Reflectance noise σ of the image, once known.
    noise: Option<f64>,
    effort: Effort,
    /// Precomputed fringe candidates (index search).
    pre: Option<&'a SamplePixel>,
    /// A closed-form estimate (d, θ in radians) the caller already found and
    /// judged wanting: refined from, not recomputed.
    start: Option<(f64, f64)>,
}

impl<'a> Job<'a> {
    /// A lone sample pixel of the index search: untested, its fringe
    /// candidates precomputed, searched in full.
    fn sample(px: &'a SamplePixel) -> Job<'a> {
        Job {
            spectrum: &px.spectrum,
            theta_known: px.theta,
            noise: None,
            effort: Effort::INDEX_SEARCH,
            pre: Some(px),
            start: None,
        }
    }

    /// [`Job::sample`] searched further: a fit pinned at an end of the
    /// angle range also starts from the angle grid (the twin test's
    /// runner-up).
    fn sample_pinned(px: &'a SamplePixel) -> Job<'a> {
        let mut job = Job::sample(px);
        job.effort.grid_pinned = true;
        job
    }
}

/// Result of refining one start.
#[derive(Clone, Copy, Debug, Default)]
struct Fit {
    d: f64,
    theta: f64,
    sse: f64,
    /// `JᵀJ` entries (dd, dθ, θθ).
    jtj: [f64; 3],
    /// Fitted on the thickness table at `theta` (judged on its
    /// interpolant, within 1e-5 of the fringe amplitude of the model).
    tabled: bool,
    /// The refinement ran out of iterations still moving (not at a
    /// minimum).
    stalled: bool,
    /// χ² against the noise model and the mean noise variance at the fit,
    /// where the refinement left the model there (its last evaluation):
    /// `finish` then need not evaluate it again. `None` elsewhere.
    chi2: Option<(f64, f64)>,
}

/// Everything that depends on the film index.
#[derive(Clone, Debug)]
struct Prepared {
    /// Unique among the solver's preparations (see [`AngleMemo`]).
    id: u64,
    model: FilmModel,
    /// Expected sign of the fringe term (+1: half-wave points are peaks).
    sign: f64,
    /// Angle table for the start: (θ, R(cos Δ = 1), R(cos Δ = −1)).
    table: Vec<(f64, f64, f64)>,
    /// The same for a fringe search's cosine fit: (θ, A + B, A − B) of
    /// R's mean and first harmonic ([`FilmModel::cosine_levels`]).
    cosine_table: Vec<(f64, f64, f64)>,
    /// The half-wave envelope's slope dR/dθ between table entries.
    slopes: Slopes,
    /// The range of reflectance the model can produce over every thickness
    /// and angle (half- and quarter-wave envelopes, middle band).
    envelope_range: (f64, f64),
    /// Real ambient and substrate indices at the middle band, when the
    /// half-wave level can be inverted in closed form (lossless, s or p).
    closed_form: Option<(f64, f64, Polarization)>,
    /// How many quadrature nodes `model` integrates each band's passband
    /// on (1: its centre alone).
    integrate: Vec<usize>,
    /// The model over thickness at each known angle (`fast`, `balanced`).
    tables: table::Tables,
    /// `fast` with the angle free: tables on a fine angle grid, built as
    /// the rows' estimated angles need them ([`angle_map`]); the grid is
    /// laid when the first row needs it, once the noise level that sets
    /// its fineness is known.
    angle_bins: Option<Arc<std::sync::OnceLock<Option<table::AngleBins>>>>,
    /// `balanced` with the angle free: the neighbouring fringe orders' gap
    /// over optical thickness and angle, filled as pixels reach it.
    order_gaps: Option<order_gaps::OrderGaps>,
}

impl Prepared {
    /// The table at exactly angle `theta`: a known angle's, or the angle
    /// bin's there (`fast` with the angle free).
    fn table_at<'a>(&'a self, theta: f64, scratch: &Scratch) -> Option<&'a table::ThicknessTable> {
        self.tables
            .get_hinted(theta, &scratch.table_hint)
            .or_else(|| self.bins()?.at_hinted(theta, &scratch.bin_hint))
    }

    /// The angle bins, once their grid is laid.
    fn bins(&self) -> Option<&table::AngleBins> {
        self.angle_bins.as_ref()?.get()?.as_ref()
    }
}

/// Solves pixels for the scene's unknowns.
#[derive(Clone, Debug)]
pub struct Solver {
    scene: Scene,
    bands: Vec<Band>,
    mode: Mode,
    index: Option<IndexEstimate>,
    prepared: Option<Prepared>,
    basis: FringeBasis,
    theta_range: (f64, f64),
    /// sin² of the angle range's ends.
    sin2_range: (f64, f64),
    /// Thinnest film considered, nm.
    d_min: f64,
    /// Thickest film considered, nm.
    d_max: f64,
    /// `d_max` was set by the user (then a fit pinned there is flagged
    /// "at search bound"; otherwise the physical range flags it).
    d_max_given: bool,
    /// Largest optical thickness the bands resolve, nm, and what limits it.
    g_max: (f64, RangeLimit),
    /// The noise model the fits are judged against, once known: the
    /// data's own ([`Solver::raw_noise`]) while the level is fitted, and
    /// the noise of the data corrected by the level in force once it is
    /// settled ([`NoiseModel::under_level`]: σ/g).
    noise: Option<NoiseModel>,
    /// The noise model of the data as measured (given, the camera's, or
    /// estimated from the cube), with the scale accuracy.
    raw_noise: Option<NoiseModel>,
    /// The same, where its variances do not depend on R (χ² without a
    /// division per band).
    flat_noise: Option<FlatNoise>,
    /// The smallest noise variance of any band (0 without a noise model):
    /// a refinement whose next step would lower χ² by less than
    /// [`refine::STEP_CHI2`] of it has converged.
    min_noise_var: f64,
    /// With [`Solver::flat_noise`], its largest variance of any band.
    max_flat_var: f64,
    /// The instrument's noise differs between bands or with the
    /// reflectance: the best fits are weighed again (`weigh.rs`).
    weigh_bands: bool,
    /// A number no other noise model of any solver has had (memos of what
    /// depends on the noise are keyed by it).
    noise_gen: u64,
    /// The χ² test.
    chi2: Chi2Test,
    /// The image-wide level in force (identity unless `scaled`).
    level: Level,
    /// The level model in force (`auto` resolved to what it chose).
    level_mode: LevelMode,
    /// What the level estimate found (for summaries).
    level_note: String,
    /// The level in force is `auto`'s hedge, weighed at this probability
    /// against the calibration (`level_hedge`).
    level_hedge: Option<f64>,
    /// `absolute` was asked for, but the image shows a correctable
    /// calibration error: every pixel is flagged.
    calibration_suspect: bool,
    /// A caller found the image-wide estimates not explaining data they
    /// should ([`Solver::flag_calibration`]): every pixel is flagged until
    /// it clears this or they are estimated again.
    estimates_unexplained: bool,
    /// The largest optical thickness (`d·q2_mid(θ)`) of the index stage's
    /// last sample of fits, where nearly all of it fitted: `fast`'s angle
    /// bins tabulate up to [`bins_g_limit`] of it instead of the whole
    /// resolved range ([`Solver::angle_bins`]).
    sample_g: Option<f64>,
    /// The median angle, rad, of the same sample's fits (at least 100 of
    /// them): where `fast`'s rows on their estimated angle start their
    /// first sample ([`Solver::solve_row_on_angle`]).
    sample_theta: Option<f64>,
    /// Whether the same sample's fits say a row's line from half its
    /// samples would add little to a pixel's σ (`half_the_samples_serve`
    /// in `angle_map`): `fast`'s rows then take half their samples first,
    /// and the rest only where those fall short.
    row_samples_halved: bool,
    /// The model one small step up in the film index, where the index is
    /// estimated jointly with the level: each pixel's derivative with
    /// respect to it carries the index's share of the level's covariance.
    index_step: Option<FilmModel>,
    /// Each pixel's response to the level over thickness at the scene's one
    /// known angle, built on first use after the level or index last
    /// changed (`share.rs`).
    share_table: std::sync::OnceLock<Option<ShareTable>>,
    /// Raise the model-free noise estimate to the index sample's pooled
    /// residual (see [`Solver::set_residual_noise_floor`]).
    residual_noise_floor: bool,
    /// The band layout: bands by wavelength, the range in wavenumber,
    /// the parabola windows.
    table: BandTable,
    /// The bands as the cube names them; [`Solver::bands`] are these
    /// shifted by the band shift in force (`band_shift.rs`).
    nominal_bands: Vec<Band>,
    /// The largest optical thickness the fringe search covers, nm.
    g_search: f64,
    /// The band shift in force, its σ and how it was found.
    shift: band_shift::ShiftState,
}

impl Solver {
    /// A solver for `scene` observed in `bands` (cube plane order).
    pub fn new(scene: &Scene, bands: &[Band], mode: Mode) -> Result<Solver, EstimateError> {
        let nominal_bands = bands.to_vec();
        let shift = band_shift::ShiftState::given(scene.band_shift);
        let shifted = band_shift::shifted(bands, shift.nm);
        let bands = &shifted[..];
        if bands.len() < 4 {
            return Err(EstimateError::Bands(format!(
                "need at least 4 bands, got {}",
                bands.len()
            )));
        }
        if bands.len() > MAX_BANDS {
            return Err(EstimateError::Bands(format!(
                "at most {MAX_BANDS} bands, got {}",
                bands.len()
            )));
        }
        if let Some(b) = bands
            .iter()
            .find(|b| !(b.center_nm.is_finite() && b.center_nm > 0.0 && b.fwhm_nm >= 0.0))
        {
            return Err(EstimateError::Bands(format!(
                "band centre {} nm / FWHM {} nm is not usable",
                b.center_nm, b.fwhm_nm
            )));
        }
        if let Some(b) = bands
            .iter()
            .find(|b| !(BAND_RANGE_NM.0..=BAND_RANGE_NM.1).contains(&b.center_nm))
        {
            return Err(EstimateError::Bands(format!(
                "band centre {} nm is outside {}–{} nm, where thin-film optics with these \
                 media apply: check the wavelength units",
                b.center_nm, BAND_RANGE_NM.0, BAND_RANGE_NM.1
            )));
        }
        let n2_hi = match &scene.film {
            FilmKnowledge::Known(d) => bands
                .iter()
                .filter_map(|b| d.index_at(b.center_nm).ok())
                .map(|n| n.re)
                .fold(1.0, f64::max),
            FilmKnowledge::Unknown { search, .. } => search.1,
        };
        let theta_range = match scene.angle {
            AngleKnowledge::Unknown { search } => search,
            _ => (0.0, 89f64.to_radians()),
        };
        let g_max = super::range::max_optical_thickness(bands);
        // The thickest film whose optical thickness the bands resolve at the
        // most oblique angle considered (the physical range), unless given.
        let n2_lo = match &scene.film {
            FilmKnowledge::Known(d) => bands
                .iter()
                .filter_map(|b| d.index_at(b.center_nm).ok())
                .map(|n| n.re)
                .fold(f64::INFINITY, f64::min),
            FilmKnowledge::Unknown { search, .. } => search.0.max(1.0),
        };
        let theta_hi = match scene.angle {
            AngleKnowledge::Uniform(t) => t,
            _ => theta_range.1,
        };
        let kx = scene
            .ambient
            .index_at(bands[0].center_nm)
            .map_or(1.0, |n| n.re)
            * theta_hi.sin();
        let q_lo = (n2_lo * n2_lo - kx * kx).max(0.09 * n2_lo * n2_lo).sqrt();
        let d_max = match scene.max_thickness_nm {
            Some(d) => d,
            // A little past the resolved range, so a film beyond it is
            // found there and flagged "fringes unresolved".
            None => (1.05 * g_max.0 / q_lo).min(crate::scene::MAX_THICKNESS_LIMIT_NM),
        };
        let d_min = scene.min_thickness_nm.min(0.5 * d_max);
        // The search covers what may be reported, and a little past the
        // resolved range so a film beyond it is found and flagged.
        let g_search = (d_max * n2_hi).min(1.05 * g_max.0);
        // Sized before allocating: wavelengths in the wrong unit (a header
        // giving 0.001–0.031 "nm") or all bands at one centre would ask for
        // gigabytes.
        let rho = film_dispersion_ratios(&scene.film, bands);
        let need = FringeBasis::bytes_needed(bands, &rho, g_search);
        if need.is_nan() || need > search::BASIS_BUDGET_BYTES as f64 {
            let (lo, hi) = bands.iter().fold((f64::INFINITY, 0.0f64), |(a, b), x| {
                (a.min(x.center_nm), b.max(x.center_nm))
            });
            return Err(EstimateError::Bands(format!(
                "band centres {lo}–{hi} nm with films up to {d_max:.0} nm would need a \
                 fringe-search grid of {:.3e} bytes (at most {} MB): are the centres in nm, \
                 and distinct?",
                need,
                search::BASIS_BUDGET_BYTES >> 20
            )));
        }
        let basis = FringeBasis::new(bands, &rho, g_search);
        let mut solver = Solver {
            scene: scene.clone(),
            bands: bands.to_vec(),
            mode,
            index: None,
            prepared: None,
            basis,
            theta_range,
            sin2_range: (theta_range.0.sin().powi(2), theta_range.1.sin().powi(2)),
            d_min,
            d_max,
            d_max_given: scene.max_thickness_nm.is_some(),
            g_max,
            noise: None,
            raw_noise: None,
            flat_noise: None,
            min_noise_var: 0.0,
            max_flat_var: f64::INFINITY,
            weigh_bands: false,
            noise_gen: 0,
            chi2: Chi2Test::flagging(MAX_BANDS),
            level: Level::identity(bands.len()),
            level_mode: match scene.level {
                LevelMode::Auto => LevelMode::Absolute,
                l => l,
            },
            level_note: String::new(),
            level_hedge: None,
            calibration_suspect: false,
            estimates_unexplained: false,
            sample_g: None,
            sample_theta: None,
            row_samples_halved: false,
            index_step: None,
            share_table: std::sync::OnceLock::new(),
            residual_noise_floor: false,
            table: BandTable::new(bands),
            nominal_bands,
            g_search,
            shift,
        };
        if let FilmKnowledge::Known(film) = &scene.film {
            let film = film.clone();
            let prepared = solver.prepare(&film)?;
            let n = prepared.model.n2_mid();
            solver.prepared = Some(prepared);
            solver.index = Some(IndexEstimate {
                n,
                sigma: 0.0,
                estimated: false,
                twin: None,
                twin_delta_chi2: f64::NAN,
                noise_sigma: f64::NAN,
                note: "known".into(),
                ambiguous: false,
                at_bound: false,
                sigma_in_level: false,
                scale_branches: None,
                branches: None,
            });
        }
        if scene.level == LevelMode::Free {
            if !matches!(scene.film, FilmKnowledge::Known(_)) {
                return Err(EstimateError::Level(
                    "the free level needs the film index (--n2 or --material2): with a free scale per pixel only the optical thickness is seen".into(),
                ));
            }
            if matches!(scene.angle, AngleKnowledge::Unknown { .. }) {
                return Err(EstimateError::Level(
                    "the free level needs the incidence angle (--theta-deg or --theta-map)".into(),
                ));
            }
        }
        if let Some(s) = scene.noise_sigma {
            solver.set_noise(NoiseModel::uniform(
                s,
                bands.len(),
                super::noise::NoiseSource::Given,
            ));
        }
        Ok(solver)
    }

    fn prepare(&self, film: &Dispersion) -> Result<Prepared, EstimateError> {
        self.prepare_with(film, true)
    }

    /// The model for `film`, with its thickness tables where `tabled` (the
    /// film-index profile fits its sample without them: a table per trial
    /// index is most of the search's cost on a spectrometer's hundreds of
    /// bands and tens of micrometres of range).
    fn prepare_with(&self, film: &Dispersion, tabled: bool) -> Result<Prepared, EstimateError> {
        let model_with = |nodes: &[usize]| {
            FilmModel::with_nodes(
                &self.bands,
                &self.scene.ambient,
                film,
                &self.scene.substrate,
                self.scene.polarization,
                nodes,
            )
            .map_err(|(medium, source)| EstimateError::Optics { medium, source })
        };
        let point = model_with(&vec![1; self.bands.len()])?;
        let (lo, hi) = self.theta_range;
        // The envelopes of the point-sampled model (the closed form's
        // levels and the range of what a film can reflect).
        let steps = (((hi - lo).to_degrees() / 0.5).ceil() as usize).max(1);
        let table: Vec<(f64, f64, f64)> = (0..=steps)
            .map(|i| {
                let th = lo + (hi - lo) * i as f64 / steps as f64;
                let (h, l) = point.envelopes(th);
                (th, h, l)
            })
            .collect();
        let cosine_table: Vec<(f64, f64, f64)> = table
            .iter()
            .map(|&(th, _, _)| {
                let (h, l) = point.cosine_levels(th);
                (th, h, l)
            })
            .collect();
        let mid_th = match self.scene.angle {
            AngleKnowledge::Uniform(t) => t,
            _ => 0.5 * (lo + hi),
        };
        let (h, l) = point.envelopes(mid_th);
        let sign = if h >= l { 1.0 } else { -1.0 };
        let (n1, n3) = point.ambient_substrate_mid();
        let pol = self.scene.polarization;
        let closed_form =
            (n1.im == 0.0 && n3.im == 0.0 && matches!(pol, Polarization::S | Polarization::P))
                .then_some((n1.re, n3.re, pol));
        let fringe_amplitude = table
            .iter()
            .map(|e| 0.5 * (e.1 - e.2).abs())
            .filter(|a| a.is_finite())
            .fold(0.0, f64::max);
        // The passband, integrated on each band where point sampling would
        // err beyond the tolerance for the thickest film of the range (at
        // the range's smallest angle) and the largest fringe amplitude; the
        // model every fit and table of this index then uses.
        let g_top = self.d_max * point.q2_mid(lo);
        let integrated: Vec<bool> = self
            .bands
            .iter()
            .map(|b| {
                b.fwhm_nm > 0.0
                    && b.needs_integration_for(g_top, fringe_amplitude, INTEGRATION_TOLERANCE)
            })
            .collect();
        let (integrate, model) = if integrated.iter().any(|&i| i) {
            // On each band the fewest quadrature nodes within the
            // tolerance (`passband.rs`).
            let nine: Vec<usize> = integrated
                .iter()
                .map(|&i| if i { crate::optics::band::N_NODES } else { 1 })
                .collect();
            let full = model_with(&nine)?;
            // Up to the thickest film the bands resolve: past it a fit is
            // flagged whatever the model (`judge.rs`, the range rule).
            let q = point.q2_mid(lo);
            let probes = passband::Probes {
                d_range: (self.d_min, self.d_max.min(self.g_max.0 / q).max(self.d_min)),
                theta_range: (lo, hi),
                period_nm: self.band_span().0 / (2.0 * q),
            };
            let nodes = passband::fewest_nodes(
                &full,
                &integrated,
                &probes,
                INTEGRATION_TOLERANCE,
                model_with,
            )?;
            tracing::debug!(?nodes, "passband nodes per band");
            if nodes == nine {
                (nodes, full)
            } else {
                let model = model_with(&nodes)?;
                (nodes, model)
            }
        } else {
            (vec![1; self.bands.len()], point)
        };
        let slopes = Slopes::new(&table);
        let envelope_range = table
            .iter()
            .flat_map(|e| [e.1, e.2])
            .filter(|v| v.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                (a.min(v), b.max(v))
            });
        let tables = if tabled {
            let tables = self.build_tables(&model);
            tracing::debug!(bytes = tables.bytes(), "thickness tables built");
            tables
        } else {
            table::Tables::default()
        };
        let angle_bins = (tabled && self.angle_bins_apply()).then(Default::default);
        // Only `balanced` weighs a warm pixel's orders with the angle free
        // on a model it keeps (`accurate` weighs them on every pixel).
        let order_gaps = (tabled
            && self.mode == Mode::Balanced
            && matches!(self.scene.angle, AngleKnowledge::Unknown { .. }))
        .then(|| {
            let g_hi = self.d_max * model.q2_mid(lo);
            order_gaps::OrderGaps::new(g_hi, 0.5 / self.table.sigma_center, (lo, hi))
        })
        .flatten();
        static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        Ok(Prepared {
            id: NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            tables,
            angle_bins,
            order_gaps,
            model,
            envelope_range,
            sign,
            slopes,
            table,
            cosine_table,
            closed_form,
            integrate,
        })
    }

    /// Thickness tables at each known angle, where one unknown is left (in
    /// every mode but the free level; `accurate` takes its starts from
    /// them and refines with the exact model).
    fn build_tables(&self, model: &FilmModel) -> table::Tables {
        /// A map with more distinct angles than this fits pixel by pixel.
        const MAX_TABLES: usize = 4096;
        if self.scene.level == LevelMode::Free {
            return table::Tables::default();
        }
        // The thicknesses a table scans at angle t: what the search covers;
        // its walks reach twice the resolved range where the range is the
        // physics' (as the angle-free refinement past it does,
        // [`unresolved`]), not one the user set.
        let g_hi = 1.05 * self.g_max.0;
        let range = |t: f64| {
            let q = model.q2_mid(t).max(1e-6);
            let d_hi = self.d_max.min(g_hi / q).max(self.d_min);
            let reach = self.run_reach(q).map_or(d_hi, |r| {
                r.min(crate::scene::MAX_THICKNESS_LIMIT_NM).max(d_hi)
            });
            (self.d_min, d_hi, reach)
        };
        let angles: Vec<f64> = match &self.scene.angle {
            AngleKnowledge::Uniform(t) => vec![*t],
            AngleKnowledge::Map { deg, .. } => {
                let mut bits: Vec<u32> = deg
                    .iter()
                    .filter(|d| d.is_finite() && (0.0..90.0).contains(*d))
                    .map(|d| d.to_bits())
                    .collect();
                bits.sort_unstable();
                bits.dedup();
                if bits.len() > MAX_TABLES {
                    // A continuous map: tables on a 0.1° grid give each
                    // pixel its start, refined at its own angle.
                    let deg = |b: &u32| f64::from(f32::from_bits(*b)).to_radians();
                    let (Some(lo), Some(hi)) = (bits.first(), bits.last()) else {
                        return table::Tables::default();
                    };
                    return table::Tables::binned(
                        model,
                        (deg(lo), deg(hi)),
                        0.1f64.to_radians(),
                        0.5f64.to_radians(),
                        range,
                    );
                }
                // Exactly as `AngleKnowledge::known_at` converts them.
                bits.iter()
                    .map(|&b| f64::from(f32::from_bits(b)).to_radians())
                    .collect()
            }
            AngleKnowledge::Unknown { .. } => return table::Tables::default(),
        };
        let angles: Vec<f64> = angles
            .into_iter()
            .filter(|t| t.is_finite() && (0.0..PI / 2.0).contains(t))
            .collect();
        table::Tables::build(model, &angles, range)
    }

    /// `fast` with the angle free (and the level not free): each row is
    /// solved on its estimated angle ([`angle_map`]).
    fn angle_bins_apply(&self) -> bool {
        matches!(self.scene.angle, AngleKnowledge::Unknown { .. })
            && self.mode == Mode::Fast
            && self.scene.level != LevelMode::Free
    }

    /// The angle grid for `model`, as fine as moving a pixel to its bin
    /// may change the model by a tenth of the noise level `noise` (and no
    /// finer than the tables' interpolation tolerance).
    fn angle_bins(&self, model: &FilmModel, noise: f64) -> Option<table::AngleBins> {
        let AngleKnowledge::Unknown { search } = self.scene.angle else {
            return None;
        };
        let range = table::BinRange {
            d_min: self.d_min,
            d_max: self.d_max,
            g_hi: 1.05 * self.g_max.0,
            g_reach: self.run_reach(1.0),
        };
        // Tabulated about the films the image's sample shows (its thickest
        // optical thickness and as much again, at least two orders
        // more), not the whole resolved range: a pixel past a table is
        // not explained there and takes the angle-free fit, which searches
        // the whole range. On the 150–350 nm dispersive film each of its
        // ~100 bins had tabulated 0–3 µm and walked to 6 µm.
        let range = match self.sample_g {
            Some(g) => {
                let lam_max = self.bands.iter().map(|b| b.center_nm).fold(0.0, f64::max);
                let g = bins_g_limit(g, lam_max);
                table::BinRange {
                    g_hi: range.g_hi.min(g),
                    g_reach: range.g_reach.map(|r| r.min(g)),
                    ..range
                }
            }
            None => range,
        };
        let hi = search.1.min(PI / 2.0 - 1e-9);
        let tol = if noise.is_finite() {
            (0.1 * noise).max(table::INTERP_TOL)
        } else {
            table::INTERP_TOL
        };
        table::AngleBins::new(model, (search.0.max(0.0), hi), range, tol)
    }

    /// The mode.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// The bands, in cube plane order.
    pub fn bands(&self) -> &[Band] {
        &self.bands
    }

    /// The film index in use, once known or estimated.
    pub fn film_index(&self) -> Option<&IndexEstimate> {
        self.index.as_ref()
    }

    /// Use this film index from now on (e.g. one estimated on an earlier sweep).
    pub fn set_film_index(&mut self, est: IndexEstimate) -> Result<(), EstimateError> {
        self.index_step = None;
        self.share_table = std::sync::OnceLock::new();
        if let FilmKnowledge::Unknown { .. } = self.scene.film {
            self.prepared = Some(self.prepare(&Dispersion::constant(est.n))?);
            if est.sigma_in_level {
                self.index_step = self.index_step_model(est.n);
            }
        }
        self.index = Some(est);
        Ok(())
    }

    /// Solve one pixel. `spectrum` is in band order (NaN marks a missing
    /// band); `theta_known` is the pixel's known angle in radians.
    ///
    /// Before the film index is known (or estimated) every pixel is
    /// invalid ([`Reason::Masked`]).
    pub fn solve_pixel(
        &self,
        spectrum: &[f64],
        theta_known: Option<f64>,
        scratch: &mut Scratch,
    ) -> PixelEstimate {
        self.solve_pixel_with(spectrum, theta_known, scratch, Effort::of(self.mode), None)
    }

    /// [`Solver::solve_pixel`] at a given effort.
    fn solve_pixel_with(
        &self,
        spectrum: &[f64],
        theta_known: Option<f64>,
        scratch: &mut Scratch,
        effort: Effort,
        start: Option<(f64, f64)>,
    ) -> PixelEstimate {
        let (Some(prep), Some(index)) = (&self.prepared, &self.index) else {
            return PixelEstimate::invalid(Reason::Masked);
        };
        let noise = index.noise_sigma.is_finite().then_some(index.noise_sigma);
        if self.level_mode == LevelMode::Free {
            let mut est = self.solve_free(prep, spectrum, theta_known, scratch);
            Self::with_index(prep, index, &mut est, scratch);
            return est;
        }
        let (mut est, _) = self.solve_with(
            prep,
            Job {
                spectrum,
                theta_known,
                noise,
                effort,
                pre: None,
                start,
            },
            scratch,
        );
        if theta_known.is_none() {
            scratch.note_unresolved(est.reason);
        }
        self.with_level(prep, spectrum, theta_known.is_none(), &mut est, scratch);
        Self::with_index(prep, index, &mut est, scratch);
        est
    }

    /// The global index and its share of the thickness error.
    fn with_index(
        prep: &Prepared,
        index: &IndexEstimate,
        est: &mut PixelEstimate,
        scratch: &Scratch,
    ) {
        if est.is_valid() && index.at_bound {
            *est = PixelEstimate::invalid(Reason::AtBound);
        }
        if est.is_valid() {
            est.n_film = index.n;
            let twin = index.twin.filter(|_| index.ambiguous);
            let sigma_n_free = !index.sigma_in_level && index.sigma != 0.0;
            if !sigma_n_free && index.scale_branches.is_none() && twin.is_none() {
                // A known index (or one whose error the level carries):
                // nothing to add.
                return;
            }
            // The global index's own error moves the thickness at fixed
            // optical thickness: ∂d/∂n2 = −d·n2/q2².
            let q2 = scratch.q2_mid(prep, est.theta_deg.to_radians());
            let dd_dn = est.thickness_nm * index.n / (q2 * q2);
            // The thickness at the pixel's optical thickness under index t.
            let kx2 = index.n * index.n - q2 * q2;
            let d_at = |t: f64| est.thickness_nm * q2 / (t * t - kx2).max(1e-12).sqrt();
            // The scale's branches: half the span of their thicknesses
            // (exact at fixed optical thickness), in place of their share
            // of σ_n in the linear term.
            let (sigma_n, scale) = match index.scale_branches {
                Some([p, m]) => {
                    let spread = 0.5 * (p - m).abs();
                    let rest = (index.sigma * index.sigma - spread * spread)
                        .max(0.0)
                        .sqrt();
                    (rest, 0.5 * (d_at(p) - d_at(m)).abs())
                }
                None => (index.sigma, 0.0),
            };
            let sigma_n = if index.sigma_in_level { 0.0 } else { sigma_n };
            let (a, b) = (est.sigma_thickness_nm, dd_dn * sigma_n);
            // An unresolved twin or equivalent: the thickness on another
            // branch (same optical thickness) is as likely, so σ spans
            // every branch.
            let c = match (index.ambiguous, index.branches, index.twin) {
                (true, Some([lo, hi]), _) => {
                    let d = est.thickness_nm;
                    (d_at(lo) - d).abs().max((d_at(hi) - d).abs())
                }
                (true, None, Some(t)) => (d_at(t) - est.thickness_nm).abs(),
                _ => 0.0,
            };
            est.sigma_thickness_nm = (a * a + b * b + c * c + scale * scale).sqrt();
        }
    }

    /// Use this noise model from now on (given, measured by the camera's
    /// calibration, or estimated from the data): the noise of the data as
    /// measured; pixels solved under a level are judged against it as the
    /// level carries it ([`NoiseModel::under_level`]).
    pub fn set_noise(&mut self, noise: NoiseModel) {
        let noise = noise.with_accuracy(self.scene.reflectance_accuracy);
        let typical = noise.typical_sigma(0.05);
        self.raw_noise = Some(noise);
        if let Some(i) = &mut self.index {
            i.noise_sigma = typical;
        }
        self.judge_noise(true);
    }

    /// Judge fits against the measured noise, as the level in force
    /// carries it where `under_level` (the identity leaves it as it is).
    /// Memos that read the noise start afresh only where that changes it.
    fn judge_noise(&mut self, under_level: bool) {
        let Some(raw) = &self.raw_noise else {
            return;
        };
        let noise = match under_level {
            true => raw.under_level(&self.level.gain, &self.level.offset),
            false => raw.clone(),
        };
        if self.noise.as_ref() == Some(&noise) {
            return;
        }
        self.flat_noise = noise.flat();
        self.min_noise_var = noise.min_var();
        self.max_flat_var = self
            .flat_noise
            .as_ref()
            .map_or(f64::INFINITY, |f| 1.0 / f.min_inv_var());
        self.noise = Some(noise);
        self.weigh_bands = self.bands_weigh_differently();
        static NOISE_GEN: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
        self.noise_gen = NOISE_GEN.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        // The orders' gaps were refined to a stopping rule that reads the
        // noise: a new noise model starts them afresh, so a pixel's verdict
        // never depends on which noise model came before.
        if let Some(g) = self.prepared.as_mut().and_then(|p| p.order_gaps.as_mut()) {
            *g = g.emptied();
        }
    }

    /// Let the index sample's pooled residual raise the model-free noise
    /// estimate (the live runner, until the camera's own noise is measured
    /// by its calibration).
    pub fn set_residual_noise_floor(&mut self, on: bool) {
        self.residual_noise_floor = on;
    }

    /// The noise model of the data as measured, once known (pixels under
    /// a level are judged against it divided by the level's gain).
    pub fn noise(&self) -> Option<&NoiseModel> {
        self.raw_noise.as_ref()
    }

    /// The image-wide level in force and the level model it came from.
    pub fn level(&self) -> (&Level, LevelMode, &str) {
        (&self.level, self.level_mode, &self.level_note)
    }

    /// Flag every pixel ("poor fit", the level's note saying `why`) until
    /// [`Solver::clear_calibration_flag`] or the image-wide estimates are
    /// made again: a caller found them not explaining the data they came
    /// from (a live run's look at the sweep they were estimated on,
    /// [`Solver::level_drift`], still sees the calibration move).
    pub fn flag_calibration(&mut self, why: &str) {
        self.estimates_unexplained = true;
        self.level_note = format!("{}; {why}: every pixel flagged poor fit", self.level_note);
    }

    /// Lift [`Solver::flag_calibration`]'s flag: the estimates in force
    /// explain the data again (a later sweep's look finds nothing moved).
    /// The image's own tests' flags stay.
    pub fn clear_calibration_flag(&mut self) {
        self.estimates_unexplained = false;
    }

    /// Use this level from now on (e.g. one estimated on an earlier sweep).
    pub fn set_level(&mut self, level: Level, mode: LevelMode, note: String) {
        self.calibration_suspect = false;
        self.estimates_unexplained = false;
        self.level_hedge = None;
        self.level = level;
        self.level_mode = mode;
        self.level_note = note;
        self.share_table = std::sync::OnceLock::new();
        self.judge_noise(true);
    }

    /// The shortest and longest band centre, nm.
    fn band_span(&self) -> (f64, f64) {
        (
            self.table.sorted.first().map_or(400.0, |b| b.1),
            self.table.sorted.last().map_or(700.0, |b| b.1),
        )
    }

    /// The scene's incidence-angle knowledge.
    pub fn scene_angle(&self) -> &AngleKnowledge {
        &self.scene.angle
    }

    /// The forward model at the film index in use (None until the index is
    /// known or estimated): the point-sampled reflectance every fit
    /// compares the data with.
    pub fn film_model(&self) -> Option<&FilmModel> {
        self.prepared.as_ref().map(|p| &p.model)
    }

    /// The thickness range searched, nm, and the largest optical thickness
    /// the bands resolve.
    pub fn thickness_range(&self) -> (f64, f64, f64) {
        (self.d_min, self.d_max, self.g_max.0)
    }
}

/// A known film's index at each band over its index at the middle band
/// (where the model's `n2_mid` is taken), real parts; empty for a film of
/// unknown, constant index or where the index cannot be evaluated.
fn film_dispersion_ratios(film: &FilmKnowledge, bands: &[Band]) -> Vec<f64> {
    let FilmKnowledge::Known(disp) = film else {
        return Vec::new();
    };
    let Some(mid) = bands.get(bands.len() / 2) else {
        return Vec::new();
    };
    let n_at = |nm: f64| {
        disp.index_at(nm)
            .ok()
            .map(|n| n.re)
            .filter(|n| n.is_finite() && *n > 0.0)
    };
    let Some(n_mid) = n_at(mid.center_nm) else {
        return Vec::new();
    };
    bands
        .iter()
        .map(|b| n_at(b.center_nm).map(|n| n / n_mid))
        .collect::<Option<Vec<f64>>>()
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::Scratch;
    use crate::estimate::{PixelEstimate, Reason};

    fn fit(d: f64, theta_deg: f64, sigma_d: f64, sigma_theta_deg: f64) -> PixelEstimate {
        PixelEstimate {
            thickness_nm: d,
            n_film: 1.46,
            theta_deg,
            sigma_thickness_nm: sigma_d,
            sigma_theta_deg,
            residual_rms: 1e-3,
            reason: Reason::Ok,
        }
    }

    /// The warm start follows the row's ramp only where the last two fits
    /// moved by more than three σ and less than an edge's jump, each
    /// coordinate on its own; an invalid pixel breaks the ramp.
    #[test]
    fn the_warm_start_follows_a_ramp_not_noise_nor_an_edge() {
        let mut s = Scratch::default();
        assert_eq!(s.warm_start(2.0), None);
        s.note_warm(&fit(100.0, 30.0, 0.02, 0.01));
        // One fit: no slope yet.
        assert_eq!(s.warm_start(2.0), Some((100.0, 30f64.to_radians())));
        // d moved 0.5 nm (25 σ): extrapolated; θ moved 0.005° (half a σ):
        // noise, kept.
        s.note_warm(&fit(100.5, 30.005, 0.02, 0.01));
        let (d, th) = s.warm_start(2.0).unwrap();
        assert!((d - 101.0).abs() < 1e-12, "{d}");
        assert_eq!(th, 30.005f64.to_radians());
        // θ moved 0.1° (10 σ, under 0.6°): extrapolated too.
        s.note_warm(&fit(101.0, 30.105, 0.02, 0.01));
        let (d, th) = s.warm_start(2.0).unwrap();
        assert!((d - 101.5).abs() < 1e-12, "{d}");
        assert!((th - 30.205f64.to_radians()).abs() < 1e-12, "{th}");
        // A step within 3σ of the thickness: noise, not followed.
        s.note_warm(&fit(101.04, 30.105, 0.02, 0.01));
        assert_eq!(s.warm_start(2.0).unwrap().0, 101.04);
        // A jump of 5 nm: an edge or an order change, not followed.
        s.note_warm(&fit(106.04, 30.105, 0.02, 0.01));
        assert_eq!(s.warm_start(2.0).unwrap().0, 106.04);
        // An invalid pixel ends the row's warm start and its ramp; the
        // next valid fit starts a new one.
        s.note_warm(&PixelEstimate::invalid(Reason::PoorFit));
        assert_eq!(s.warm_start(2.0), None);
        s.note_warm(&fit(107.0, 30.105, 0.02, 0.01));
        assert_eq!(s.warm_start(2.0).unwrap().0, 107.0);
        // A new row starts afresh; a ramp never starts below zero.
        s.start_afresh();
        assert_eq!(s.warm_start(2.0), None);
        s.note_warm(&fit(1.5, 30.0, 0.02, 0.01));
        s.note_warm(&fit(0.3, 30.0, 0.02, 0.01));
        assert_eq!(s.warm_start(2.0).unwrap().0, 0.0);
        // A thick film's ramp (10 nm a pixel) is followed up to the limit
        // given (a quarter fringe there), not past it.
        s.start_afresh();
        s.note_warm(&fit(3000.0, 8.0, 0.03, 0.05));
        s.note_warm(&fit(3010.0, 8.0, 0.03, 0.05));
        assert_eq!(s.warm_start(30.0).unwrap().0, 3020.0);
        assert_eq!(s.warm_start(8.0).unwrap().0, 3010.0);
    }
}
