//! The global film-index search: the summed residual of a sample of pixels
//! profiled over the index (coarse grid, then a local quadratic fit), both
//! branches of the n2 ↔ n1·n3/n2 near-symmetry compared.

use super::level_hedge::Look;
use super::linalg::solve3;
use super::search::{Candidate, MAX_CANDIDATES};
use super::{
    IndexEstimate, Job, Prepared, Scratch, Solver, INDEX_SAMPLE_PIXELS, LEVEL_SAMPLE_PIXELS,
};
use crate::estimate::level::{Level, LevelMode};
use crate::estimate::noise::NoiseModel;
use crate::estimate::{Cube, EstimateError};
use crate::optics::dispersion::Dispersion;
use crate::scene::FilmKnowledge;
use rayon::prelude::*;

/// A sample pixel's share of the index profile is capped at this many χ²
/// thresholds (see [`Solver::gross_capped`]): a wrong index 0.02 off raises
/// a pixel by tens of thresholds at most on the scene matrix's images.
const GROSS_MISFIT: f64 = 100.0;

/// An equivalent index whose profile lies within this many noise
/// variances of the best is refined and weighed as a twin (see
/// `equivalents`); the images of the scene matrix put theirs thousands
/// above.
const EQUIVALENT_NEAR: f64 = 100.0;

/// Step of the coarse film-index profile.
const INDEX_GRID_STEP: f64 = 0.02;

/// A runner-up within this many variances of the best index (and past
/// the tie, 9) is refined again before the twin test
/// ([`Solver::search_index`]).
const POLISH_BELOW: f64 = 100.0;

/// The first window of that second refinement: the first refinement's
/// second window (0.02 · 0.3), so over its three rounds it can move
/// ±0.008 in all.
const POLISH_HALF: f64 = 0.006;

/// A pixel of the global index search, with its fringe candidates for
/// both fringe signs precomputed (they do not depend on the film index).
#[derive(Clone, Debug)]
pub(super) struct SamplePixel {
    pub(super) spectrum: Vec<f64>,
    pub(super) theta: Option<f64>,
    /// Candidates for sign +1 (index 0) and −1 (index 1).
    pub(super) cands: [[Candidate; MAX_CANDIDATES]; 2],
    pub(super) n_cands: [usize; 2],
    /// Where in the image it lies, `(x, y)` (None: not from an image).
    pub(super) site: Option<(usize, usize)>,
}

/// How often the band shift is looked for again under a level.
const MAX_SHIFT_LOOKS: usize = 3;

/// Pairs of neighbouring pixels the image's fit is tested on.
pub(super) const IMAGE_FIT_PAIRS: usize = 800;

/// The most the live runner's residual floor may raise the model-free
/// noise estimate (a factor on σ).
const RESIDUAL_FLOOR_MAX: f64 = 1.5;

impl Solver {
    /// Estimate the film index from the cube when the scene leaves it
    /// unknown, and the reflectance noise from the fit residuals (also when
    /// the index is known). The result is kept for later pixels and sweeps.
    pub fn estimate_film_index(&mut self, cube: &Cube) -> Result<IndexEstimate, EstimateError> {
        self.check_cube(cube)?;
        // What a caller found unexplained is estimated afresh.
        self.estimates_unexplained = false;
        // A shift fitted on an earlier image is fitted afresh.
        self.reset_band_shift()?;
        // The noise level every fit is judged against comes first, and never
        // from the fits it judges: given, measured by the camera, or
        // estimated from the data without a model.
        if self.noise.is_none() {
            let per_band = self.scene.level != LevelMode::Free;
            if let Some(n) = NoiseModel::from_data_with(cube, per_band) {
                self.set_noise(n);
            }
        }
        // The level is fitted to the data as measured, against their own
        // noise (a level from an earlier look is fitted afresh).
        self.judge_noise(false);
        // Every mode takes the full sample: with half of it, `fast` once took
        // a few fits' local minima for a calibration error (a 1.4 % gain
        // that moved thicknesses by 5 σ on clean data).
        let n_sample = INDEX_SAMPLE_PIXELS;
        let mut sample = self.sample_pixels(cube, n_sample);
        if sample.is_empty() {
            return Err(EstimateError::FilmIndex(Self::why_no_sample(cube)));
        }
        let mut est = self.index_for(&sample)?;
        if self.residual_noise_floor {
            // The caller has no measured noise yet (the live runner before
            // the camera's noise is calibrated): the model-free estimate is
            // raised to the sample's pooled residual where that is larger.
            if let Some(prep) = self.prepared.clone() {
                let (sse, n_obs, n_par, _) = self.sample_sse(&prep, &sample, false);
                let res = (sse / (n_obs - n_par).max(1.0)).sqrt();
                let data = self
                    .raw_noise
                    .as_ref()
                    .map_or(0.0, |n| n.typical_sigma(0.05));
                if res.is_finite() && res > data {
                    // Scaled up as a whole: the bands keep their relative
                    // noise (a lamp's spectrum makes some bands noisier).
                    // By at most RESIDUAL_FLOOR_MAX: the model-free
                    // estimate may run low on camera noise, but a residual
                    // far above it is a misfit every pixel shares (a wrong
                    // film), which must fail, not raise the bar.
                    let noise = match self.raw_noise.take() {
                        Some(mut n) if data > 0.0 => {
                            let f = (res / data).min(RESIDUAL_FLOOR_MAX).powi(2);
                            n.var0.iter_mut().for_each(|v| *v *= f);
                            n.shot.iter_mut().for_each(|v| *v *= f);
                            n
                        }
                        _ => NoiseModel::uniform(
                            res,
                            self.bands.len(),
                            crate::estimate::noise::NoiseSource::Data,
                        ),
                    };
                    self.set_noise(noise);
                }
            }
        }
        // The filter's wavelength calibration, where the data show it
        // (`band_shift.rs`): before the level, whose per-band gains would
        // otherwise take up part of a shift's misfit.
        if self.fit_band_shift(&sample, &est)? {
            sample = self.sample_pixels(cube, n_sample);
            est = self.index_for(&sample)?;
        }
        est = self.level_stage(cube, &sample, est, n_sample)?;
        // A shift refused before the level because the pixels fitted at no
        // shift (a per-band gain error on top) is looked for again on the
        // data the level corrects; found, the level is fitted afresh on
        // the shifted bands. That level took up part of the shift (±6 %
        // per band and 2 nm: the first look under it read 1.59 nm), so
        // the two are fitted in turn until the shift settles within its σ.
        if self.level_mode == LevelMode::Scaled && self.shift.unexplained {
            for _ in 0..MAX_SHIFT_LOOKS {
                let before = self.band_shift().0;
                self.judge_noise(true);
                let corrected = self.corrected_sample(&sample);
                let saved = self.shift.clone();
                if !self.fit_band_shift(&corrected, &est)? {
                    if before != 0.0 {
                        // This look found nothing new: the last one holds.
                        self.restore_band_shift(saved)?;
                    }
                    break;
                }
                let nb = self.bands.len();
                self.set_level(Level::identity(nb), LevelMode::Absolute, String::new());
                self.judge_noise(false);
                sample = self.sample_pixels(cube, n_sample);
                est = self.index_for(&sample)?;
                est = self.level_stage(cube, &sample, est, n_sample)?;
                let (now, sigma, _) = self.band_shift();
                if (now - before).abs() <= sigma || self.level_mode != LevelMode::Scaled {
                    break;
                }
            }
        }
        // Pixels are solved on data corrected by the level, whose noise the
        // level scales: σ/g (a gain of 0.92 left 4 % of clean pixels
        // flagged when judged against the data's σ; one of 1.05 widened σ).
        self.judge_noise(true);
        // Where the fringes are weak the profile is biased; measured and
        // removed once the level is settled (a level test at the corrected
        // index would read the profile's own minimum as a misfit to fix).
        if let FilmKnowledge::Unknown { search, prior } = self.scene.film.clone() {
            est = self.with_profile_bias(&sample, search, prior, est);
        }
        if self.noise.is_none() {
            // No independent noise level (a tiny cube): the pooled residual
            // stands in, and the summary says that fits were not tested.
            let prep = self.prepared.clone().expect("index prepared");
            let (sse, n_obs, n_par, _) = self.sample_sse(&prep, &sample, false);
            est.noise_sigma = (sse / (n_obs - n_par).max(1.0)).sqrt();
        } else if let Some(n) = &self.raw_noise {
            est.noise_sigma = n.typical_sigma(0.05);
        }
        self.set_film_index(est.clone())?;
        // The image's fit as a whole (`image_fit`), said once in the note
        // however often the index is estimated.
        for tail in [
            "; the image's fit:",
            "; but neighbouring pixels share",
            "; the level is one across",
            "; but the level differs across",
        ] {
            if let Some(i) = self.level_note.find(tail) {
                self.level_note.truncate(i);
            }
        }
        if !self.calibration_suspect {
            match self.image_fit(cube, IMAGE_FIT_PAIRS) {
                Some(fit) if fit.rejected() => {
                    self.calibration_suspect = true;
                    self.level_note = format!(
                        "{}; but neighbouring pixels share a misfit their noise does not explain ({:.3} noise variances per band, {:.1} σ over {} pairs; χ²/dof {:.3}): a wrong polarisation, film or substrate? every pixel flagged poor fit",
                        self.level_note, fit.shared, fit.z, fit.pairs, fit.chi2_dof
                    );
                }
                Some(fit) => {
                    self.level_note = format!(
                        "{}; the image's fit: neighbouring pixels share {:.3} noise variances per band ({:.1} σ over {} pairs)",
                        self.level_note, fit.shared, fit.z, fit.pairs
                    );
                }
                None => {}
            }
        }
        // One level for the whole image (`level_across`): after the
        // image's fit, which names a wrong polarisation or film where the
        // neighbouring pixels show it.
        self.test_level_across(cube);
        Ok(est)
    }

    /// The level: absolute unless asked, or (auto) unless the sample
    /// shows a systematic misfit a gain and offset per band correct;
    /// where one is in force, fitted again with the index on a sample
    /// four times larger. Returns the index found with it.
    fn level_stage(
        &mut self,
        cube: &Cube,
        sample: &[SamplePixel],
        mut est: IndexEstimate,
        n_sample: usize,
    ) -> Result<IndexEstimate, EstimateError> {
        if self.scene.level != LevelMode::Free {
            let est_small = est.clone();
            // An image no larger than the index sample gets no second
            // look: its first is final.
            let look = if sample.len() < n_sample {
                Look::Final
            } else {
                Look::First
            };
            if let Some(fitted) = self.fit_level(sample, &est, look)? {
                est = fitted;
                // A level is in force. Its gain trades with each pixel's
                // angle and with the index, so it is fitted again, with the
                // index, on a sample four times larger (σ of the gain
                // halves); clean images keep the small sample's cost.
                let big = self.sample_pixels(cube, LEVEL_SAMPLE_PIXELS);
                if big.len() > sample.len() {
                    let nb = self.bands.len();
                    // A hedge (a level the small sample only hints at, as
                    // on most clean images) looks again with the index
                    // refined about the small sample's absolute one; a
                    // level the test established, with a new search.
                    let hedged = self.level_hedge.is_some();
                    self.set_level(Level::identity(nb), LevelMode::Absolute, String::new());
                    let est_abs = if hedged {
                        self.index_near(&big, &est_small)?
                    } else {
                        self.index_for(&big)?
                    };
                    est = match self.fit_level(&big, &est_abs, Look::Final)? {
                        Some(fitted) => fitted,
                        None => est_abs,
                    };
                }
            }
        }
        Ok(est)
    }

    /// `sample` with each spectrum corrected by the level in force,
    /// (y − o)/g, its fringe candidates found afresh.
    fn corrected_sample(&self, sample: &[SamplePixel]) -> Vec<SamplePixel> {
        let corrected: Vec<SamplePixel> = sample
            .iter()
            .map(|p| SamplePixel {
                spectrum: p
                    .spectrum
                    .iter()
                    .enumerate()
                    .map(|(k, &v)| self.level.correct(k, v))
                    .collect(),
                ..p.clone()
            })
            .collect();
        self.with_candidates(&corrected)
    }

    /// Why no pixel could be sampled: missing values, or values no
    /// reflectance takes (percent, raw counts, intensities).
    fn why_no_sample(cube: &Cube) -> String {
        let finite = cube.data.iter().filter(|v| v.is_finite());
        let (lo, hi) = finite.fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
        if lo.is_finite() && !(lo >= -0.2 && hi <= 1.2) {
            format!(
                "no pixel's spectrum lies within a reflectance's range (values span {lo} to {hi}, \
                 where a calibrated reflectance lies in 0–1): percent? divide by 100 (`irid fit \
                 --percent`; a table column headed with % is); intensities or counts? `--level \
                 free` fits them"
            )
        } else {
            "no pixel has a complete, finite spectrum (more than a quarter of its bands missing)"
                .into()
        }
    }

    /// The film index for a sample (searched where unknown), prepared for
    /// the pixels that follow.
    pub(super) fn index_for(
        &mut self,
        sample: &[SamplePixel],
    ) -> Result<IndexEstimate, EstimateError> {
        let est = match self.scene.film.clone() {
            FilmKnowledge::Known(_) => self.index.clone().expect("known index set at construction"),
            FilmKnowledge::Unknown { search, prior } => {
                let est = self.search_index(sample, search, prior)?;
                let eps = self.noise.as_ref().map_or(0.0, |n| n.accuracy());
                if eps > 0.0 && est.estimated && !est.at_bound {
                    self.with_scale_spread(sample, search, prior, eps, est)
                } else {
                    est
                }
            }
        };
        self.set_film_index(est.clone())?;
        Ok(est)
    }

    /// The index's share of the reflectance scale's accuracy ε: the
    /// index searched again on the sample scaled by 1 ± ε, half the spread
    /// added to σ in quadrature. A scale error is the same in every band,
    /// so the noise term ε·R (independent per band) cannot carry it: on a
    /// thin film, whose index shows only in the level, a 3 % scale moves
    /// the index by ~0.05, while the independent term leaves σ ≈ 0.005.
    fn with_scale_spread(
        &self,
        sample: &[SamplePixel],
        search: (f64, f64),
        prior: Option<f64>,
        eps: f64,
        mut est: IndexEstimate,
    ) -> IndexEstimate {
        let mut ns = [f64::NAN; 2];
        for (n, f) in ns.iter_mut().zip([1.0 + eps, 1.0 - eps]) {
            let scaled: Vec<SamplePixel> = sample
                .iter()
                .map(|p| SamplePixel {
                    spectrum: p.spectrum.iter().map(|v| v * f).collect(),
                    ..p.clone()
                })
                .collect();
            if let Ok(e) = self.search_index(&scaled, search, prior) {
                *n = e.n;
            }
        }
        let spread = if ns.iter().all(|n| n.is_finite()) {
            0.5 * (ns[0] - ns[1]).abs()
        } else {
            // The index is lost at one end of the scale's range: nothing
            // pins it.
            f64::INFINITY
        };
        est.sigma = est.sigma.hypot(spread);
        est.scale_branches = spread.is_finite().then_some(ns);
        est.note = format!(
            "{}{}σ includes ±{spread:.4} from the reflectance scale's {:.1} % accuracy",
            est.note,
            if est.note.is_empty() { "" } else { "; " },
            100.0 * eps
        );
        est
    }

    /// About `max` distinct pixels (at most every pixel of the cube) on a
    /// stratified lattice, those with complete enough spectra, with their
    /// known angles.
    pub(super) fn sample_pixels(&self, cube: &Cube, max: usize) -> Vec<SamplePixel> {
        let mut scratch = Scratch::default();
        let mut spec = vec![0.0; cube.bands.len()];
        Self::sample_sites(cube, max)
            .into_iter()
            .filter_map(|(x, y)| self.sample_at(cube, x, y, true, &mut spec, &mut scratch))
            .collect()
    }

    /// About `max` distinct pixel positions on a stratified lattice.
    pub(super) fn sample_sites(cube: &Cube, max: usize) -> Vec<(usize, usize)> {
        let (w, h) = (cube.width, cube.height);
        // A 2-D stratified grid (cells of the image's aspect), one pixel per
        // cell at a golden-ratio offset, so periodic structure in the scene
        // cannot alias the sample onto a few columns.
        let max = max.max(1);
        let nx =
            ((max as f64 * w as f64 / h.max(1) as f64).sqrt().ceil() as usize).clamp(1, w.max(1));
        let ny = max.div_ceil(nx).clamp(1, h.max(1));
        const PHI: f64 = 0.618_033_988_749_895;
        // Where the grid is finer than the image in one direction two
        // cells can land on one pixel: it is taken once (the same data
        // twice would count as twice the information, and σ of what the
        // sample estimates would shrink by what it does not know).
        let mut taken = std::collections::HashSet::with_capacity(nx * ny);
        let mut out = Vec::with_capacity(nx * ny);
        for k in 0..nx * ny {
            let (i, j) = (k % nx, k / nx);
            let fx = (i as f64 + (j as f64 * PHI).fract()) / nx as f64;
            let fy = (j as f64 + (i as f64 * PHI).fract()) / ny as f64;
            let x = ((fx * w as f64) as usize).min(w - 1);
            let y = ((fy * h as f64) as usize).min(h - 1);
            if taken.insert((x, y)) {
                out.push((x, y));
            }
        }
        out
    }

    /// The pixel at `(x, y)` as a sample pixel, where its spectrum is
    /// complete enough, within what a reflectance takes (any values under
    /// the free level) and not dark; with its fringe candidates where
    /// `search` (the index search starts from them; a fit as
    /// [`Solver::level_pixels`] makes does not).
    pub(super) fn sample_at(
        &self,
        cube: &Cube,
        x: usize,
        y: usize,
        search: bool,
        spec: &mut [f64],
        scratch: &mut Scratch,
    ) -> Option<SamplePixel> {
        let nb = cube.bands.len();
        cube.spectrum_into(x, y, spec);
        // Missing bands (NaN: a dropped frame) are allowed as in any
        // pixel's solve, up to a quarter of them.
        let n_ok = spec.iter().filter(|v| v.is_finite()).count();
        // Under `free` every pixel has its own scale: intensities and
        // counts are what it fits.
        let in_range = self.scene.level == LevelMode::Free
            || spec
                .iter()
                .all(|v| !v.is_finite() || (-0.2..=1.2).contains(v));
        (in_range
            && 4 * n_ok >= 3 * nb
            && !spec.iter().any(|v| v.is_infinite())
            && !self.dark(spec))
        .then(|| {
            let theta = self.scene.angle.known_at(x, y);
            let mut p = if search {
                self.sample_pixel(spec.to_vec(), theta, scratch)
            } else {
                SamplePixel {
                    spectrum: spec.to_vec(),
                    theta,
                    cands: [[Candidate::default(); MAX_CANDIDATES]; 2],
                    n_cands: [0; 2],
                    site: None,
                }
            };
            p.site = Some((x, y));
            p
        })
    }

    /// Whether a spectrum is zero within its noise: its mean within three σ
    /// of the mean (the noise model at R = 0), and every band within four
    /// σ: a closed shutter, a dead or masked pixel. (Every band within its
    /// noise is not enough: at σ_R = 0.03 most of the paper's cylinder
    /// reads so.) Such a spectrum says next to nothing of the film index,
    /// but its residual is least where the film reflects least, at the
    /// antireflection index √(n1·n3): six all-zero spectra among thirty
    /// pulled the index of the rest from 1.46 to 1.44 and their angles from
    /// 0° to 48°, every thickness ~20 % off and valid. It is left out of
    /// the sample (its own fit still judges it). Without a noise model,
    /// never.
    fn dark(&self, spec: &[f64]) -> bool {
        let Some(noise) = &self.noise else {
            return false;
        };
        let (mut sum, mut var, mut n) = (0.0, 0.0, 0usize);
        for (v, &v0) in spec.iter().zip(&noise.var0) {
            if v.is_finite() {
                if v.abs() > 4.0 * v0.sqrt() {
                    return false;
                }
                (sum, var, n) = (sum + v, var + v0, n + 1);
            }
        }
        n > 0 && sum.abs() <= 3.0 * var.sqrt()
    }

    /// A sample pixel of spectrum `spec` (missing bands NaN) at the known
    /// angle `theta`, with its fringe candidates for both signs.
    pub(super) fn sample_pixel(
        &self,
        spectrum: Vec<f64>,
        theta: Option<f64>,
        scratch: &mut Scratch,
    ) -> SamplePixel {
        scratch.ensure(spectrum.len());
        for (k, &v) in spectrum.iter().enumerate() {
            let ok = v.is_finite();
            scratch.spectrum[k] = if ok { v } else { 0.0 };
            scratch.weight[k] = if ok { 1.0 } else { 0.0 };
        }
        let complete = spectrum.iter().all(|v| v.is_finite());
        let mut cands = [[Candidate::default(); MAX_CANDIDATES]; 2];
        let mut n_cands = [0; 2];
        for (k, sign) in [1.0, -1.0].into_iter().enumerate() {
            n_cands[k] = self.fringe_search(scratch, sign, complete, &mut cands[k]);
        }
        SamplePixel {
            spectrum,
            theta,
            cands,
            n_cands,
            site: None,
        }
    }

    /// Summed residual of the sample under a prepared index: `(sse,
    /// observations, fitted parameters, pixels fitted)`; each pixel
    /// searched further where `pinned` ([`Job::sample_pinned`]).
    pub(super) fn sample_sse(
        &self,
        prep: &Prepared,
        sample: &[SamplePixel],
        pinned: bool,
    ) -> (f64, f64, f64, f64) {
        sample
            .par_iter()
            .map_init(Scratch::default, |scratch, px| {
                let (spec, th) = (&px.spectrum, &px.theta);
                let job = if pinned {
                    Job::sample_pinned(px)
                } else {
                    Job::sample(px)
                };
                let (_, sse) = self.solve_with(prep, job, scratch);
                // Every pixel with a fit counts, flagged or not: which
                // pixels pass the quality tests changes with the trial
                // index, and at high noise a profile over the passing ones
                // follows those flips, not the fit (σ = 0.03 on the
                // paper's cylinder: n 1.312 ± 0.0004 for a true 1.37).
                if sse.is_finite() {
                    let p = if th.is_some() { 1.0 } else { 2.0 };
                    let n = spec.iter().filter(|v| v.is_finite()).count();
                    (self.gross_capped(sse, n, p as usize), n as f64, p, 1.0)
                } else {
                    (0.0, 0.0, 0.0, 0.0)
                }
            })
            .reduce(
                || (0.0, 0.0, 0.0, 0.0),
                |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2, a.3 + b.3),
            )
    }

    /// A sample pixel's residual, at most [`GROSS_MISFIT`] χ² thresholds of
    /// the noise model: one defect the film cannot explain at any index
    /// (one spectrum in forty at 10⁵ variances) must not choose the index
    /// for the rest, which near their minimum each add about their degrees
    /// of freedom.
    pub(super) fn gross_capped(&self, sse: f64, n_obs: usize, n_par: usize) -> f64 {
        match &self.noise {
            Some(m) => {
                let var = m.typical_sigma(0.05).powi(2);
                let dof = n_obs.saturating_sub(n_par).max(1);
                sse.min(GROSS_MISFIT * self.chi2.threshold(dof) * var)
            }
            None => sse,
        }
    }

    fn profile_at(
        &self,
        n: f64,
        sample: &[SamplePixel],
        pinned: bool,
    ) -> Result<(f64, f64, f64, f64), EstimateError> {
        // Untabled: the sample's fits start from its fringe candidates and
        // never scan a table.
        let prep = self.prepare_with(&Dispersion::constant(n), false)?;
        Ok(self.sample_sse(&prep, sample, pinned))
    }

    /// The profile's cost of a trial index over `sample`: the summed
    /// residual, pixels the index cannot fit at all charged their total
    /// sum of squares (so that dropping them never looks like a better fit);
    /// each pixel searched further where `pinned` ([`Job::sample_pinned`]).
    fn index_cost<'a>(
        &'a self,
        sample: &'a [SamplePixel],
        pinned: bool,
    ) -> impl Fn(f64) -> Result<f64, EstimateError> + Sync + 'a {
        let total_ss: f64 = sample
            .iter()
            .map(|px| {
                let s = &px.spectrum;
                let ok = s.iter().filter(|v| v.is_finite());
                let n = ok.clone().count().max(1) as f64;
                let m = ok.clone().sum::<f64>() / n;
                ok.map(|v| (v - m) * (v - m)).sum::<f64>()
            })
            .sum();
        move |n: f64| -> Result<f64, EstimateError> {
            let (sse, _, _, fitted) = self.profile_at(n, sample, pinned)?;
            let missing = sample.len() as f64 - fitted;
            Ok(sse + missing * total_ss / sample.len() as f64)
        }
    }

    /// The film index for a larger `sample` of the image whose smaller one
    /// gave `near`: refined locally about it (the basin and the twin are
    /// the smaller sample's; a global search over four times the pixels
    /// would cost three times the local one), then prepared as
    /// [`Solver::index_for`] does. A known index is simply set.
    pub(super) fn index_near(
        &mut self,
        sample: &[SamplePixel],
        near: &IndexEstimate,
    ) -> Result<IndexEstimate, EstimateError> {
        let FilmKnowledge::Unknown { search, prior } = self.scene.film.clone() else {
            return self.index_for(sample);
        };
        if !near.estimated || near.at_bound || near.ambiguous {
            return self.index_for(sample);
        }
        let (lo, hi) = (search.0.max(1.0 + 1e-3), search.1);
        let (n, var, sigma) = {
            let cost = self.index_cost(sample, false);
            let (n, sse, curvature) = self.refine_index(near.n, (lo, hi), &cost)?;
            let var = self.index_var(n, sse, sample)?;
            let sigma = self.index_sigma((n, sse, curvature), var, (lo, hi), &cost)?;
            (n, var, sigma)
        };
        let at_bound = n <= lo + 2e-3 || n >= hi - 2e-3;
        if at_bound {
            return self.index_for(sample);
        }
        let est = IndexEstimate {
            n,
            sigma,
            noise_sigma: var.sqrt(),
            sigma_in_level: false,
            scale_branches: None,
            ..near.clone()
        };
        let eps = self.noise.as_ref().map_or(0.0, |m| m.accuracy());
        let est = if eps > 0.0 {
            self.with_scale_spread(sample, search, prior, eps, est)
        } else {
            est
        };
        self.set_film_index(est.clone())?;
        Ok(est)
    }

    pub(super) fn search_index(
        &self,
        sample: &[SamplePixel],
        search: (f64, f64),
        prior: Option<f64>,
    ) -> Result<IndexEstimate, EstimateError> {
        // Coarse profile on a 0.02 grid (twice the paper's step: the
        // profile's basin is wider, and the local fit below refines it far
        // past 0.01); pixels a trial index
        // cannot fit at all are charged their total sum of squares so that
        // dropping them never looks like a better fit.
        let (lo, hi) = search;
        let lo = lo.max(1.0 + 1e-3);
        let steps = ((hi - lo) / INDEX_GRID_STEP).round().max(2.0) as usize;
        let grid: Vec<f64> = (0..=steps)
            .map(|i| lo + (hi - lo) * i as f64 / steps as f64)
            .collect();
        let cost = self.index_cost(sample, false);
        // The trial indices in parallel too: a spectrum table's sample is
        // one or a few pixels.
        let prof = grid
            .par_iter()
            .map(|&n| cost(n))
            .collect::<Result<Vec<f64>, EstimateError>>()?;
        // Local minima of the coarse profile, best first.
        let mut minima: Vec<usize> = (0..prof.len())
            .filter(|&i| {
                (i == 0 || prof[i] <= prof[i - 1])
                    && (i + 1 == prof.len() || prof[i] <= prof[i + 1])
            })
            .collect();
        minima.sort_by(|&a, &b| prof[a].total_cmp(&prof[b]));
        if minima.is_empty() || !prof[minima[0]].is_finite() {
            return Err(EstimateError::FilmIndex(
                "the index profile has no minimum".into(),
            ));
        }
        // Refine the best two well-separated minima with a local quadratic.
        let mut refined: Vec<(f64, f64, f64)> = Vec::new(); // (n, sse, curvature)
        for &i in minima.iter().take(4) {
            if refined.iter().any(|r| (r.0 - grid[i]).abs() < 0.04) {
                continue;
            }
            let r = self.refine_index(grid[i], (lo, hi), &cost)?;
            refined.push(r);
            if refined.len() == 2 {
                break;
            }
        }
        refined.sort_by(|a, b| a.1.total_cmp(&b.1));
        // The best index's exact equivalents at the sample's typical angle
        // (`equivalents`): with the angle free their minima are sharp, and
        // the coarse grid can step over them. One evaluation each; refined
        // only where it comes near (an image
        // whose pixels see several angles breaks the equivalence, and
        // keeps the search's cost).
        let near_var = self.index_var(refined[0].0, refined[0].1, sample)?;
        let least = refined[0];
        for (m, delta) in self.equivalents_of(least.0, sample) {
            if !(lo..=hi).contains(&m) || (m - least.0).abs() < 0.04 {
                continue;
            }
            if delta / near_var >= EQUIVALENT_NEAR {
                continue;
            }
            // The carried fits' residual where it is the lower: an exact
            // equivalent the fresh fits miss stays a tie (also where the
            // coarse profile found its basin and refined it with them).
            let carried = least.1 + delta.max(0.0);
            match refined.iter_mut().find(|r| (r.0 - m).abs() < 0.04) {
                Some(r) => r.1 = r.1.min(carried),
                None => {
                    let mut r = self.refine_index(m, (lo, hi), &cost)?;
                    r.1 = r.1.min(carried);
                    refined.push(r);
                }
            }
        }
        refined.sort_by(|a, b| a.1.total_cmp(&b.1));
        // A runner-up past the tie but within [`POLISH_BELOW`] variances
        // is refined once more from where it stopped, each sample pixel
        // searched further ([`Job::sample_pinned`]): the twin test must
        // not rest on the refinement's resolution or a lone pixel's missed
        // basin. With the angle free a branch's minimum is sharp, and
        // three rounds can stop a few thousandths off it (1.46 on silicon
        // at 45° in unpolarised light, whose near-equivalent is 2.41 at
        // 56°: one image's runner-up stopped at 1.4632, Δχ² = 10); and
        // normal incidence, where R is even in θ, is a stationary point a
        // lone pixel's fit can stall at (another image's two pixels near
        // 245 nm, fitted there, charged the true index 660 variances,
        // Δχ² = 49). Both were rejected and every thickness read 44 %
        // thin, valid; polished, Δχ² = 0.0 and 0.5: ties, σ spanning both
        // branches. Only the runner-up, and only ever lowered: it turns a
        // rejection into a tie, never the reverse. (Searched further on
        // every trial index, the sample's fits bent a dispersive film's
        // misfit into a level, which the level test then missed.)
        if let [best, second, ..] = refined[..] {
            let d = (second.1 - best.1) / near_var;
            if (9.0..POLISH_BELOW).contains(&d) {
                let polish = self.index_cost(sample, true);
                let again = self.refine_index_from(second.0, POLISH_HALF, (lo, hi), &polish)?;
                if again.1 < second.1 {
                    refined[1] = again;
                    refined.sort_by(|a, b| a.1.total_cmp(&b.1));
                }
            }
        }
        // The least may have moved to an equivalent: its variance then.
        let var = if refined[0] == least {
            near_var
        } else {
            self.index_var(refined[0].0, refined[0].1, sample)?
        };
        let noise_sigma = var.sqrt();
        let mut best = refined[0];
        let mut note = String::new();
        let mut ambiguous = false;
        let mut branches = None;
        let (twin, dchi2) = match refined.get(1) {
            Some(t) => (Some(t.0), (t.1 - best.1) / var),
            None => (None, f64::INFINITY),
        };
        // Every refined minimum within Δχ² 9 of the least: the data do not
        // tell them apart (p light can hold four: the twin's two roots and
        // the index of equal admittance beside the truth).
        let tied: Vec<f64> = refined
            .iter()
            .filter(|r| (r.1 - refined[0].1) / var < 9.0)
            .map(|r| r.0)
            .collect();
        let list = |ns: &[f64]| {
            let v: Vec<String> = ns.iter().map(|n| format!("{n:.4}")).collect();
            v.join(", ")
        };
        if tied.len() > 1 {
            if let Some(p) = prior {
                let near = |r: &&(f64, f64, f64)| (r.0 - p).abs();
                let chosen = refined[..tied.len()]
                    .iter()
                    .min_by(|a, b| near(a).total_cmp(&near(b)))
                    .copied()
                    .unwrap_or(best);
                best = chosen;
                note = format!(
                    "branches {} not resolved by the data (Δχ² = {dchi2:.1}); the prior chose {:.4}",
                    list(&tied),
                    best.0
                );
            } else {
                ambiguous = true;
                let lo = tied.iter().copied().fold(f64::INFINITY, f64::min);
                let hi = tied.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                branches = Some([lo, hi]);
                note = if tied.len() == 2 {
                    format!(
                        "AMBIGUOUS: twin at {:.4} fits almost as well (Δχ² = {dchi2:.1}); give a prior or the index; σ spans both branches",
                        tied[1]
                    )
                } else {
                    format!(
                        "AMBIGUOUS: {} fit almost as well (Δχ² < 9); give a prior or the index; σ spans every branch",
                        list(&tied[1..])
                    )
                };
            }
        } else if let Some(tn) = twin {
            note = format!("twin at {:.4} rejected (Δχ² = {:.0})", tn, dchi2);
        }
        let sigma = self.index_sigma(best, var, (lo, hi), &cost)?;
        // Pinned at an end of the search range: the index may lie beyond.
        let at_bound = best.0 <= lo + 2e-3 || best.0 >= hi - 2e-3;
        if at_bound {
            note = format!(
                "AT SEARCH BOUND: the index {:.4} sits at an end of the search range [{lo}, {hi}]; widen `search` or give the index{}{}",
                best.0,
                if note.is_empty() { "" } else { "; " },
                note
            );
        }
        Ok(IndexEstimate {
            n: best.0,
            sigma,
            estimated: true,
            twin,
            twin_delta_chi2: dchi2,
            noise_sigma,
            note,
            ambiguous,
            at_bound,
            sigma_in_level: false,
            scale_branches: None,
            branches,
        })
    }

    /// The residual variance behind an index `n` whose profile left `sse`
    /// over `sample`: the larger of the residual's per degree of freedom
    /// and the noise model's (a misfit shared by the sample widens σ_n and
    /// the twin test, never narrows them).
    fn index_var(&self, n: f64, sse: f64, sample: &[SamplePixel]) -> Result<f64, EstimateError> {
        let (_, n_obs, n_par, _) = self.profile_at(n, sample, false)?;
        let dof = (n_obs - n_par - 1.0).max(1.0);
        let noise_var = self
            .noise
            .as_ref()
            .map_or(0.0, |m| m.typical_sigma(0.05).powi(2));
        Ok((sse / dof).max(noise_var))
    }

    /// σ of the index `best = (n, cost, κ)` under residual variance `var`:
    /// from the refinement's curvature κ where it found one; else (a
    /// minimum taken from an equivalent's carried fits, or a parabola
    /// without upward curvature) from the profile's second difference
    /// about `n`, over steps of 0.001, 0.004 and 0.016 until one curves
    /// upward; else half the search range. Never NaN: a valid pixel's σ
    /// includes it (with the reflectance scale exact, an unresolved twin
    /// on silicon once left every thickness valid with σ = NaN).
    fn index_sigma(
        &self,
        best: (f64, f64, f64),
        var: f64,
        (lo, hi): (f64, f64),
        cost: &dyn Fn(f64) -> Result<f64, EstimateError>,
    ) -> Result<f64, EstimateError> {
        let (n, _, curvature) = best;
        if curvature > 0.0 {
            return Ok((var / curvature).sqrt());
        }
        // The cost at `n` afresh, not `best`'s: that may be an
        // equivalent's carried fits, lower than any fresh evaluation, and
        // the difference must compare like with like.
        let c0 = cost(n)?;
        for h in [1e-3, 4e-3, 16e-3] {
            let (a, b) = ((n - h).max(lo), (n + h).min(hi));
            if b - a < h {
                continue;
            }
            let (ca, cb) = (cost(a)?, cost(b)?);
            // The second difference on a possibly one-sided stencil.
            let k = 2.0 * ((cb - c0) / (b - n) - (c0 - ca) / (n - a)) / (b - a);
            if k > 0.0 && k.is_finite() {
                return Ok((var / k).sqrt());
            }
        }
        Ok(0.5 * (hi - lo))
    }

    /// Fit `sse ≈ s0 + κ (n − n0)²` on a fine local grid around `n_start`;
    /// returns `(n0, s0, κ)`: the least cost evaluated (never a vertex worse
    /// than a point already seen: with the angle free a profile's minimum
    /// can be narrower than the grid, and a parabola through its flanks
    /// points away from it) and the last parabola's curvature.
    fn refine_index(
        &self,
        n_start: f64,
        bounds: (f64, f64),
        cost: &dyn Fn(f64) -> Result<f64, EstimateError>,
    ) -> Result<(f64, f64, f64), EstimateError> {
        self.refine_index_from(n_start, INDEX_GRID_STEP, bounds, cost)
    }

    /// [`Self::refine_index`] from a first window of `± half0`.
    fn refine_index_from(
        &self,
        n_start: f64,
        half0: f64,
        bounds: (f64, f64),
        cost: &dyn Fn(f64) -> Result<f64, EstimateError>,
    ) -> Result<(f64, f64, f64), EstimateError> {
        let mut center = n_start;
        let mut half = half0;
        let mut best = (center, f64::INFINITY);
        let mut curvature = 0.0;
        for _ in 0..3 {
            let pts: Vec<f64> = (-3..=3)
                .map(|i| (center + half * i as f64 / 3.0).clamp(bounds.0, bounds.1))
                .collect();
            let mut vals = Vec::with_capacity(pts.len());
            for &p in &pts {
                // The centre is the least point so far (the last round's
                // vertex, already evaluated): not solved again.
                let known = (p == best.0 && best.1.is_finite()).then_some(best.1);
                vals.push(match known {
                    Some(v) => v,
                    None => cost(p)?,
                });
            }
            for (&p, &v) in pts.iter().zip(&vals) {
                if v < best.1 {
                    best = (p, v);
                }
            }
            // Least-squares parabola in u = n − center.
            let (mut s0, mut s1, mut s2, mut s3, mut s4) = (0.0, 0.0, 0.0, 0.0, 0.0);
            let (mut t0, mut t1, mut t2) = (0.0, 0.0, 0.0);
            for (&p, &v) in pts.iter().zip(&vals) {
                let u = p - center;
                let u2 = u * u;
                s0 += 1.0;
                s1 += u;
                s2 += u2;
                s3 += u2 * u;
                s4 += u2 * u2;
                t0 += v;
                t1 += v * u;
                t2 += v * u2;
            }
            let m = [[s4, s3, s2], [s3, s2, s1], [s2, s1, s0]];
            let Some([a, b, _]) = solve3(m, [t2, t1, t0]) else {
                break;
            };
            curvature = a.max(0.0);
            if a > 0.0 {
                let u = (-b / (2.0 * a)).clamp(-half, half);
                let n0 = (center + u).clamp(bounds.0, bounds.1);
                // The vertex itself, not the parabola's value there.
                let v = cost(n0)?;
                if v < best.1 {
                    best = (n0, v);
                }
            }
            center = best.0;
            half *= 0.3;
        }
        Ok((best.0, best.1, curvature))
    }
}

#[cfg(test)]
mod tests {
    use crate::estimate::{Cube, Mode, Solver};
    use crate::optics::band::Band;
    use crate::scene::Scene;

    #[test]
    fn a_sample_never_holds_a_pixel_twice() {
        // Each pixel's first band carries its own index; lattices finer than
        // the image in one direction or both (the paper's 140 × 14 at 1600
        // pixels put 146 pixels in twice) must still give distinct pixels.
        let scene = Scene::paper_cylinder();
        let bands: Vec<Band> = (0..31)
            .map(|k| Band::new(400.0 + 10.0 * k as f64, 0.0).expect("a band"))
            .collect();
        let solver = Solver::new(&scene, &bands, Mode::Fast).expect("the solver");
        for (w, h, max) in [(140, 14, 1600), (64, 64, 1600), (7, 3, 400), (300, 2, 400)] {
            let mut cube = Cube::zeros(w, h, bands.clone());
            let n = w * h;
            for (k, v) in cube.data.iter_mut().enumerate() {
                let (band, i) = (k / n, k % n);
                *v = if band == 0 { i as f32 * 1e-4 } else { 0.05 };
            }
            let sample = solver.sample_pixels(&cube, max);
            let mut ids: Vec<usize> = sample
                .iter()
                .map(|p| (p.spectrum[0] * 1e4).round() as usize)
                .collect();
            let len = ids.len();
            ids.sort_unstable();
            ids.dedup();
            assert_eq!(ids.len(), len, "{w}×{h} at {max}: a pixel taken twice");
            // Most of what was asked (or of the image) is still there.
            assert!(2 * len >= max.min(n), "{w}×{h} at {max}: {len}");
            assert!(len <= n);
        }
    }
}
