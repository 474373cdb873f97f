//! The image-wide level (`scaled`, and the test `auto` applies): a gain and
//! an offset per band shared by every pixel, estimated with the film index
//! on the index sample by Gauss–Newton with the pixels' own parameters
//! eliminated ([`crate::estimate::level::level_step`]), alternating with
//! the index search on the corrected sample.

#![allow(clippy::needless_range_loop)] // band-indexed numeric loops read clearer with indices

use super::index::SamplePixel;
use super::level_hedge::Look;
use super::{Effort, IndexEstimate, Job, Scratch, Solver};
use crate::estimate::level::{
    level_step, Level, LevelBasis, LevelMode, LevelPixel, AUTO_PROBABILITY, MAX_AUTO_GAIN_ERROR,
};
use crate::estimate::model::{FilmModel, ModelOut};
use crate::estimate::noise::NoiseModel;
use crate::estimate::quality::chi2_upper_quantile;
use crate::estimate::{Cube, EstimateError};
use crate::optics::dispersion::Dispersion;
use crate::scene::FilmKnowledge;
use rayon::prelude::*;

/// Gauss–Newton steps per round at most.
const MAX_STEPS: usize = 30;
/// A step that moves no gain or offset by more than this has converged.
const CONVERGED: f64 = 2e-5;
/// Where the pixels' refits wander along valleys the data leave flat (an
/// angle that trades with the gain), the steps never settle and χ² jitters
/// by tens around its floor: after this many steps in a row that lower the
/// best χ² by under [`STALL_CHI2`], the best level seen stands.
const STALL_STEPS: usize = 3;
/// χ² units: a fifteenth of the smallest threshold the level's tests use
/// (one degree of freedom at `AUTO_PROBABILITY`, 15.1), far below the
/// jitter of the pixels' refits that a test's outcome already carries.
const STALL_CHI2: f64 = 1.0;
/// A band's model reflectance must spread over the sample by at least this
/// (and three noise σ) for a gain and offset of its own to be told apart
/// from the pixels' parameters; otherwise the level is smooth.
const MIN_SPREAD: f64 = 0.003;
/// A level is modelled only where it moves the sample's thicknesses by
/// more than this many of their σ (median).
const MIN_MEDIAN_SHIFT: f64 = 2.0;
/// ... or where it lowers the sample's χ² by more than this per pixel.
const MIN_CHI2_PER_PIXEL: f64 = 1.0;
/// The step in the film index of the forward difference that gives the
/// measured values' derivative with respect to it.
pub(super) const INDEX_DN: f64 = 1e-4;
/// The most the levels fitted on the sample's thinner and thicker halves
/// may differ (in σ of their difference, the largest of four comparisons)
/// for the misfit to be one calibration error: 5 σ is p ≈ 6e-7 per
/// comparison (~2e-6 for four), with room for the level's σ running ~1.2×
/// narrow (README, "Over many images"); calibration errors over 256
/// images gave at most 2.54.
const MAX_HALVES_Z: f64 = 5.0;
/// Fewest pixels in each half for that comparison.
const MIN_HALF_PIXELS: usize = 40;
/// Fewest sample pixels for a gain and offset per band.
const MIN_PIXELS_PER_BAND_BASIS: usize = 50;

impl Solver {
    /// What a level step weighs each band by: the noise variance at a
    /// reflectance of 0.05, and the band's wavenumber 1/λ (its smooth
    /// basis's coordinate).
    pub(super) fn level_weights(&self, noise: &NoiseModel) -> (Vec<f64>, Vec<f64>) {
        let var = (0..self.bands.len()).map(|k| noise.var(k, 0.05)).collect();
        let wn = self.bands.iter().map(|b| 1.0 / b.center_nm).collect();
        (var, wn)
    }

    /// Fit the image-wide level on the sample where the scene asks for it
    /// (`scaled`) or the data show it is needed (`auto`); on success the
    /// level is in force and the index (re-estimated on the corrected
    /// sample where unknown) is returned. `None`: the absolute level stays.
    pub(super) fn fit_level(
        &mut self,
        sample: &[SamplePixel],
        est_abs: &IndexEstimate,
        look: Look,
    ) -> Result<Option<IndexEstimate>, EstimateError> {
        let Some(noise) = self.noise.clone() else {
            self.level_note = "absolute (no independent noise level to test against)".into();
            return Ok(None);
        };
        let nb = self.bands.len();
        let (var, wn) = self.level_weights(&noise);
        let identity = Level::identity(nb);
        let unknown_index = matches!(self.scene.film, FilmKnowledge::Unknown { .. });
        // Only pixels a level can explain take part: a first smooth fit,
        // then the pixels still far off it (films out of range, defects)
        // are left out, so they cannot pass for a calibration error.
        let all = self.level_pixels(sample, &identity);
        if all.is_empty() {
            return Ok(None);
        }
        // Trial levels: smooth, and per band where the sample can tell one.
        let mut trials = vec![(identity.clone(), est_abs.clone())];
        let mut est_trial = est_abs.clone();
        let (smooth_trial, _, _) = self.level_gauss_newton(
            sample,
            &identity,
            Some(all.clone()),
            LevelBasis::Smooth,
            &mut est_trial,
            &wn,
            &var,
        )?;
        trials.push((smooth_trial.clone(), est_trial.clone()));
        if self.level_basis(&all, &noise.typical_sigma(0.05)) == LevelBasis::PerBand {
            let (pb, _, _) = self.level_gauss_newton(
                sample,
                &smooth_trial,
                None,
                LevelBasis::PerBand,
                &mut est_trial,
                &wn,
                &var,
            )?;
            trials.push((pb, est_trial));
        }
        // A pixel is consistent if one of them explains it (judged with the
        // index found with that level, then reset).
        let mut consistent = std::collections::BTreeSet::new();
        for (t, e) in &trials {
            if unknown_index {
                self.set_film_index(e.clone())?;
            }
            for p in self.level_pixels(sample, t) {
                if pixel_chi2_passes(&p, t, &var) {
                    consistent.insert(p.id);
                }
            }
        }
        if unknown_index {
            self.set_film_index(est_abs.clone())?;
        }
        if 2 * consistent.len() < all.len() {
            self.level_note = format!(
                "absolute (only {} of {} sample pixels fit any level: the misfit is not a calibration error)",
                consistent.len(),
                all.len()
            );
            return Ok(None);
        }
        let kept: Vec<SamplePixel> = consistent.iter().map(|&i| sample[i].clone()).collect();
        let sample = &kept[..];
        let abs = self.level_pixels(sample, &identity);
        if abs.is_empty() {
            return Ok(None);
        }
        let mut est = est_abs.clone();
        // Model only what the data require: a smooth level first (4
        // parameters, so a common gain error is detected with the power of
        // a 4-degree test), a gain and offset per band only where they
        // lower χ² significantly beyond it.
        let (smooth, chi2_abs, chi2_smooth) = self.level_gauss_newton(
            sample,
            &identity,
            Some(abs.clone()),
            LevelBasis::Smooth,
            &mut est,
            &wn,
            &var,
        )?;
        let (mut level, mut basis, mut chi2_scaled) =
            (smooth.clone(), LevelBasis::Smooth, chi2_smooth);
        // Fewer parameters where they do as well: one gain or one offset
        // (whichever fits better), else one gain and one offset, each
        // tested against the smooth level (a white reference off is one
        // gain, stray light one offset; every parameter more trades with
        // the pixels' angles and the index and costs precision). The
        // smaller levels are nested in the smooth one, so none can beat
        // absolute by more than it does: where the smooth level's gain is
        // below the one-parameter test, they are not fitted at all.
        let one_param = chi2_upper_quantile(1.0, AUTO_PROBABILITY);
        if chi2_abs - chi2_smooth > one_param {
            let mut best_one: Option<(Level, LevelBasis, f64, IndexEstimate)> = None;
            for small in [LevelBasis::Gain, LevelBasis::Offset, LevelBasis::GainOffset] {
                if small == LevelBasis::GainOffset && best_one.is_some() {
                    break;
                }
                let (lv, _, chi2_small, est_small) =
                    self.level_from_identity(sample, &abs, small, est_abs, &wn, &var)?;
                let extra = (LevelBasis::Smooth.n_params(nb) - small.n_params(nb)) as f64;
                let passes =
                    chi2_small - chi2_smooth <= chi2_upper_quantile(extra, AUTO_PROBABILITY);
                if passes && best_one.as_ref().is_none_or(|b| chi2_small < b.2) {
                    best_one = Some((lv, small, chi2_small, est_small));
                }
            }
            if let Some((lv, small, chi2_small, est_small)) = best_one {
                (level, basis, chi2_scaled, est) = (lv, small, chi2_small, est_small);
            }
        }
        if unknown_index {
            self.set_film_index(est.clone())?;
        }
        if self.level_basis(&abs, &noise.typical_sigma(0.05)) == LevelBasis::PerBand {
            (level, basis, chi2_scaled, est) =
                self.per_band_level(sample, level, basis, chi2_scaled, est, &wn, &var)?;
        }
        if unknown_index {
            est.note = format!("{} (estimated jointly with the level)", est.note)
                .trim_start()
                .to_string();
        }
        // Against absolute, the chosen level's test decides (a per-band
        // level was only kept where it beat a smooth one significantly, so
        // the smooth one's test stands for it).
        let per_band = matches!(basis, LevelBasis::PerBand | LevelBasis::PerBandGain);
        let tested = if per_band {
            (LevelBasis::Smooth, chi2_smooth)
        } else {
            (basis, chi2_scaled)
        };
        // Absolute at its best: each pixel also refined from its fit under
        // the level. Where a fresh absolute search had left a pixel in a
        // wrong basin (p light near Brewster's angle, a film index-matched
        // to its substrate), the level must not be credited with the
        // better basin its refits found.
        let scaled_px = self.level_pixels(sample, &level);
        if unknown_index {
            self.set_film_index(est_abs.clone())?;
        }
        let ids: std::collections::BTreeSet<usize> = abs.iter().map(|p| p.id).collect();
        let abs: Vec<LevelPixel> = self
            .level_pixels_from(sample, &identity, &scaled_px)
            .into_iter()
            .filter(|p| ids.contains(&p.id))
            .collect();
        if unknown_index {
            self.set_film_index(est.clone())?;
        }
        let chi2_abs = level_step(&abs, &identity, tested.0, &wn, &var)
            .map_or(chi2_abs, |s| s.chi2.min(chi2_abs));
        let threshold = chi2_upper_quantile(tested.0.n_params(nb) as f64, AUTO_PROBABILITY);
        // Detected: the test passes (what `auto` would hedge is below it).
        let detected = chi2_abs - tested.1 > threshold || per_band;
        let delta = chi2_abs - chi2_scaled;
        let m = basis.n_params(nb);
        // And it must matter: a level worth modelling moves the sample's
        // thicknesses by more than their own σ (median over pixels). A
        // smaller one costs more precision (it trades with each pixel's
        // angle and the index) than the bias it removes.
        // Or the misfit it removes is large enough to fail pixels' own χ²
        // tests: on average more than one unit of χ² per pixel.
        let shift = median_shift(&abs, &scaled_px);
        let per_pixel = delta / abs.len() as f64;
        let significant = detected && (shift > MIN_MEDIAN_SHIFT || per_pixel > MIN_CHI2_PER_PIXEL);
        let (g, o) = level.mean();
        if self.scene.level == LevelMode::Absolute {
            // Told to trust the calibration: the level is only tested. A
            // significant, correctable misfit shared by the image means the
            // calibration is off, and no pixel's thickness can be trusted.
            self.level = identity;
            self.level_mode = LevelMode::Absolute;
            if unknown_index {
                self.set_film_index(est_abs.clone())?;
            }
            // A gain within the scale's stated accuracy ε (and no offset
            // beyond what ε allows at a reflectance of 0.05) is what ε
            // already covers in every pixel's χ² and σ: not suspect.
            let eps = self.noise.as_ref().map_or(0.0, |n| n.accuracy());
            let within_accuracy = eps > 0.0
                && level.gain.iter().all(|g| (g - 1.0).abs() <= eps)
                && level.offset.iter().all(|o| o.abs() <= 0.05 * eps);
            self.calibration_suspect = significant && level.is_plausible() && !within_accuracy;
            self.level_note = if self.calibration_suspect {
                format!(
                    "absolute as asked, but the image shows a calibration error (a gain {g:.4} and offset {o:.5} would lower χ² by {delta:.0} > {threshold:.0}): every pixel flagged poor fit; use --level auto or scaled"
                )
            } else {
                format!("absolute (a fitted level would lower χ² by {delta:.0}, threshold {threshold:.0}, and move thicknesses by {shift:.2} σ)")
            };
            return Ok(None);
        }
        let want = self.scene.level == LevelMode::Scaled || significant;
        if want && !level.is_plausible() {
            let note = format!(
                "absolute: the fitted level (gain {g:.3}, offset {o:.4}) is no calibration error but data that are not reflectance; pixels are judged as they are (use --level free for normalised intensities)"
            );
            return self.refuse_level(note, false, unknown_index.then_some(est_abs));
        }
        if want && self.scene.level == LevelMode::Auto && (g - 1.0).abs() > MAX_AUTO_GAIN_ERROR {
            let note = format!(
                "absolute: the image's misfit would take a gain of {g:.3} (offset {o:.4}), beyond a calibration error (±{:.0} %): a wrong film index, substrate or polarisation? every pixel flagged poor fit (use --level scaled if the reflectance scale is known to be that far off)",
                100.0 * MAX_AUTO_GAIN_ERROR
            );
            return self.refuse_level(note, true, unknown_index.then_some(est_abs));
        }
        let mut halves = None;
        if want && chi2_scaled.is_finite() {
            // One calibration error is the same for every film: a level
            // fitted on the thinner half of the sample must agree with one
            // fitted on the thicker half. A model error the level absorbs
            // (the wrong polarisation, a constant index for a dispersive
            // film) depends on the film, and the halves part.
            halves = self.level_halves_z(sample, &scaled_px, &level, basis, &est, &wn, &var)?;
            if let Some(z) = halves {
                if z > MAX_HALVES_Z {
                    let note = format!(
                        "absolute: the image's misfit is no calibration error (a level fitted on its thinner films and one on its thicker differ by {z:.1} σ: a wrong polarisation, film or substrate?): every pixel flagged poor fit"
                    );
                    return self.refuse_level(note, true, unknown_index.then_some(est_abs));
                }
            }
        }
        if want && chi2_scaled.is_finite() {
            self.level_note = format!(
                "scaled ({}, {} parameters): gain {:.4} (per band {:.4}–{:.4}), offset {:.5}; Δχ² = {:.0} against absolute (threshold {:.0}), thicknesses moved by {:.1} σ",
                match basis {
                    LevelBasis::PerBand => "gain and offset per band",
                    LevelBasis::PerBandGain => "gain per band",
                    LevelBasis::Smooth => "gain quadratic in wavenumber, one offset",
                    LevelBasis::GainOffset => "one gain, one offset",
                    LevelBasis::Gain => "one gain",
                    LevelBasis::Offset => "one offset",
                },
                m,
                g,
                level.gain.iter().copied().fold(f64::INFINITY, f64::min),
                level.gain.iter().copied().fold(f64::NEG_INFINITY, f64::max),
                o,
                delta,
                threshold,
                shift
            );
            if let Some(z) = halves {
                self.level_note += &format!(
                    "; the levels of the thinner and the thicker films agree within {z:.1} σ"
                );
            }
            self.level = level;
            self.share_table = std::sync::OnceLock::new();
            self.level_mode = LevelMode::Scaled;
            if unknown_index {
                // The index's σ is in the level's joint covariance, whose
                // share of σ_d the level's inflation factor already carries.
                est.sigma_in_level = true;
                self.set_film_index(est.clone())?;
            }
            Ok(Some(est))
        } else {
            if self.scene.level == LevelMode::Auto && !detected {
                // Below the test, a level the data hint at is weighed
                // against the calibration (see `level_hedge`).
                if let Some(h) =
                    self.hedge_level(sample, &abs, chi2_abs, est_abs, &wn, &var, look)?
                {
                    let (g, o) = h.level.mean();
                    self.level_note = format!(
                        "hedged: below the test ({threshold:.0}), a gain {:.4} (Δχ² {:.1}) and an offset {:.5} (Δχ² {:.1}) weighed against the calibration at p = {:.3} and {:.3}; applied as their mixture, gain {g:.4}, offset {o:.5}, the doubt in every σ",
                        h.fitted[0],
                        h.delta_chi2[0],
                        h.fitted[1],
                        h.delta_chi2[1],
                        h.weights[0],
                        h.weights[1],
                    );
                    self.level = h.level;
                    self.level_hedge = Some(h.weights[0] + h.weights[1]);
                    self.share_table = std::sync::OnceLock::new();
                    self.level_mode = LevelMode::Scaled;
                    if unknown_index {
                        self.set_film_index(h.est.clone())?;
                    }
                    return Ok(Some(h.est));
                }
            }
            self.level_note = format!(
                "absolute (a fitted level of {m} parameters would lower χ² by {delta:.0}, threshold {threshold:.0}, and move thicknesses by {shift:.2} σ, at least {MIN_MEDIAN_SHIFT} needed)"
            );
            self.level = identity;
            self.level_mode = LevelMode::Absolute;
            if unknown_index {
                // The index searched on the raw sample stands.
                self.set_film_index(est_abs.clone())?;
            }
            Ok(None)
        }
    }

    /// Keep the calibration (`absolute`) with `note`; every pixel flagged
    /// where `suspect`; the index searched on the raw sample (`est_abs`,
    /// where the index is unknown) stands.
    fn refuse_level(
        &mut self,
        note: String,
        suspect: bool,
        est_abs: Option<&IndexEstimate>,
    ) -> Result<Option<IndexEstimate>, EstimateError> {
        self.level_note = note;
        self.level = Level::identity(self.bands.len());
        self.level_mode = LevelMode::Absolute;
        self.calibration_suspect |= suspect;
        if let Some(est) = est_abs {
            self.set_film_index(est.clone())?;
        }
        Ok(None)
    }

    /// A level of `basis` fitted from the identity, the index (where
    /// unknown) starting from `est_abs`'s, with the sample's pixels as
    /// fitted under the identity (`abs`): the level, the sample's χ² at
    /// the start and at the end, and the index found with it.
    pub(super) fn level_from_identity(
        &mut self,
        sample: &[SamplePixel],
        abs: &[LevelPixel],
        basis: LevelBasis,
        est_abs: &IndexEstimate,
        wn: &[f64],
        var: &[f64],
    ) -> Result<(Level, f64, f64, IndexEstimate), EstimateError> {
        let mut est = est_abs.clone();
        if matches!(self.scene.film, FilmKnowledge::Unknown { .. }) {
            self.set_film_index(est_abs.clone())?;
        }
        let identity = Level::identity(self.bands.len());
        let (level, chi2_start, chi2) = self.level_gauss_newton(
            sample,
            &identity,
            Some(abs.to_vec()),
            basis,
            &mut est,
            wn,
            var,
        )?;
        Ok((level, chi2_start, chi2, est))
    }

    /// How far apart (in σ, the largest of four comparisons) the level
    /// fitted on the sample's thinner half and the one fitted on its
    /// thicker half lie: their value averaged over the blue and the red
    /// half of the bands, each at a low and a high reflectance of the
    /// sample. `None` where a half holds too few pixels to tell. The film
    /// index (where unknown) is estimated with each half's level and
    /// restored to `est` after.
    #[allow(clippy::too_many_arguments)]
    fn level_halves_z(
        &mut self,
        sample: &[SamplePixel],
        fits: &[LevelPixel],
        level: &Level,
        basis: LevelBasis,
        est: &IndexEstimate,
        wn: &[f64],
        var: &[f64],
    ) -> Result<Option<f64>, EstimateError> {
        if fits.len() < 2 * MIN_HALF_PIXELS {
            return Ok(None);
        }
        let unknown_index = matches!(self.scene.film, FilmKnowledge::Unknown { .. });
        let mut d: Vec<f64> = fits.iter().map(|p| p.d).collect();
        d.sort_by(f64::total_cmp);
        let median = d[d.len() / 2];
        let mut r: Vec<f64> = fits
            .iter()
            .map(|p| p.r.iter().sum::<f64>() / p.r.len().max(1) as f64)
            .collect();
        r.sort_by(f64::total_cmp);
        let (r_lo, r_hi) = (r[r.len() / 10], r[r.len() * 9 / 10]);
        let nb = self.bands.len();
        let mut halves = Vec::with_capacity(2);
        for thin in [true, false] {
            let half: Vec<SamplePixel> = fits
                .iter()
                .filter(|p| (p.d < median) == thin)
                .map(|p| sample[p.id].clone())
                .collect();
            if half.len() < MIN_HALF_PIXELS {
                return Ok(None);
            }
            if unknown_index {
                self.set_film_index(est.clone())?;
            }
            let mut est_half = est.clone();
            let (lv, _, chi2) =
                self.level_gauss_newton(&half, level, None, basis, &mut est_half, wn, var)?;
            if !chi2.is_finite() {
                return Ok(None);
            }
            halves.push(lv);
        }
        if unknown_index {
            self.set_film_index(est.clone())?;
        }
        let mut z: f64 = 0.0;
        for ks in [0..nb / 2, nb / 2..nb] {
            for rr in [r_lo, r_hi] {
                let (a, va) = halves[0].mean_at(ks.clone(), rr);
                let (b, vb) = halves[1].mean_at(ks.clone(), rr);
                let v = va + vb;
                if v.is_finite() && v > 0.0 {
                    z = z.max((a - b).abs() / v.sqrt());
                }
            }
        }
        Ok(Some(z))
    }

    /// A gain per band, or a gain and an offset per band, where either
    /// lowers the sample's χ² significantly beyond the level chosen so far
    /// (`level` of `basis`, χ² `chi2`, index `est`); the fewer parameters
    /// unless the offsets are needed too. Returns the level in force, with
    /// the film index set to go with it.
    #[allow(clippy::too_many_arguments)]
    fn per_band_level(
        &mut self,
        sample: &[SamplePixel],
        level: Level,
        basis: LevelBasis,
        chi2: f64,
        est: IndexEstimate,
        wn: &[f64],
        var: &[f64],
    ) -> Result<(Level, LevelBasis, f64, IndexEstimate), EstimateError> {
        let unknown_index = matches!(self.scene.film, FilmKnowledge::Unknown { .. });
        let nb = self.bands.len();
        let test = |extra: usize| chi2_upper_quantile(extra as f64, AUTO_PROBABILITY);
        let mut est_pb = est.clone();
        let (pb, _, chi2_pb) = self.level_gauss_newton(
            sample,
            &level,
            None,
            LevelBasis::PerBand,
            &mut est_pb,
            wn,
            var,
        )?;
        let m = basis.n_params(nb);
        let mut chosen = (level.clone(), basis, chi2, est.clone());
        // Only where a gain and an offset per band beat the level so far
        // significantly: then a gain per band alone where the offsets do
        // not beat it significantly in turn (fewer parameters, less traded
        // with the pixels' angles and the index).
        if chi2 - chi2_pb > test(2 * nb - m) {
            chosen = (pb, LevelBasis::PerBand, chi2_pb, est_pb);
            if unknown_index {
                self.set_film_index(est.clone())?;
            }
            let mut start = level;
            start.offset.iter_mut().for_each(|o| *o = 0.0);
            let mut est_g = est;
            let (pbg, _, chi2_g) = self.level_gauss_newton(
                sample,
                &start,
                None,
                LevelBasis::PerBandGain,
                &mut est_g,
                wn,
                var,
            )?;
            if chi2_g - chi2_pb <= test(nb) {
                chosen = (pbg, LevelBasis::PerBandGain, chi2_g, est_g);
            }
        }
        if unknown_index {
            self.set_film_index(chosen.3.clone())?;
        }
        Ok(chosen)
    }

    /// Gauss–Newton on the level and (where unknown) the film index
    /// together, from `start`, the pixels refitted on the corrected data
    /// every step. Returns the level and the sample's χ² at the start and
    /// at the end.
    #[allow(clippy::too_many_arguments)]
    fn level_gauss_newton(
        &mut self,
        sample: &[SamplePixel],
        start: &Level,
        start_pixels: Option<Vec<LevelPixel>>,
        basis: LevelBasis,
        est: &mut IndexEstimate,
        wn: &[f64],
        var: &[f64],
    ) -> Result<(Level, f64, f64), EstimateError> {
        let unknown_index = matches!(self.scene.film, FilmKnowledge::Unknown { .. });
        let mut level = start.clone();
        let mut chi2_start = f64::NAN;
        let mut px = match start_pixels {
            Some(p) => p,
            None => self.level_pixels(sample, &level),
        };
        // The best level seen (χ², level, index): a step that raises χ²
        // (the pixels' refits are nonlinear) is halved back toward it.
        let mut best: Option<(f64, Level, IndexEstimate)> = None;
        let mut stalled = 0;
        for step_no in 0..MAX_STEPS {
            let Some(step) = level_step(&px, &level, basis, wn, var) else {
                break;
            };
            if step_no == 0 {
                chi2_start = step.chi2;
            }
            if let Some((b, _, _)) = &best {
                stalled = if step.chi2 > b - STALL_CHI2 {
                    stalled + 1
                } else {
                    0
                };
                if stalled >= STALL_STEPS {
                    break;
                }
            }
            match &best {
                Some((b, bl, be)) if step.chi2 > *b => {
                    // Worse than the best: halfway back, then look again.
                    for k in 0..level.gain.len() {
                        level.gain[k] = 0.5 * (level.gain[k] + bl.gain[k]);
                        level.offset[k] = 0.5 * (level.offset[k] + bl.offset[k]);
                    }
                    let back = 0.5 * (est.n - be.n);
                    if unknown_index && back != 0.0 {
                        est.n -= back;
                        self.set_film_index(est.clone())?;
                    }
                    px = self.level_pixels(sample, &level);
                    if level_moved(&level, bl) < CONVERGED && back.abs() < 1e-5 {
                        break;
                    }
                    continue;
                }
                _ => best = Some((step.chi2, level.clone(), est.clone())),
            }
            level = step.level;
            let mut dn = 0.0;
            if unknown_index {
                if let (Some(&d), Some(&v)) = (step.extra_step.first(), step.extra_var.first()) {
                    dn = d.clamp(-0.02, 0.02);
                    est.n += dn;
                    est.sigma = v.sqrt();
                    self.set_film_index(est.clone())?;
                }
            }
            px = self.level_pixels(sample, &level);
            if step.change < CONVERGED && dn.abs() < 1e-5 {
                break;
            }
        }
        // χ² under the final level, the pixels' fits redone on its data;
        // the best seen if that was better.
        let mut chi2_end = level_step(&px, &level, basis, wn, var).map_or(f64::NAN, |s| s.chi2);
        if let Some((b, bl, be)) = best {
            if chi2_end.is_nan() || chi2_end > b {
                (chi2_end, level) = (b, bl);
                *est = be;
                if unknown_index {
                    self.set_film_index(est.clone())?;
                }
            }
        }
        Ok((level, chi2_start, chi2_end))
    }

    /// A gain and offset per band where the sample spreads every band's
    /// reflectance enough to tell them from the pixels' parameters; else
    /// the smooth level.
    fn level_basis(&self, px: &[LevelPixel], sigma: &f64) -> LevelBasis {
        if px.len() < MIN_PIXELS_PER_BAND_BASIS {
            return LevelBasis::Smooth;
        }
        let nb = self.bands.len();
        let min_spread = (0..nb)
            .map(|k| {
                let n = px.len() as f64;
                let mean = px.iter().map(|p| p.r[k]).sum::<f64>() / n;
                (px.iter().map(|p| (p.r[k] - mean).powi(2)).sum::<f64>() / n).sqrt()
            })
            .fold(f64::INFINITY, f64::min);
        if min_spread > MIN_SPREAD.max(3.0 * sigma) {
            LevelBasis::PerBand
        } else {
            LevelBasis::Smooth
        }
    }

    /// The model at film index `n` + [`INDEX_DN`] (point-sampled bands):
    /// the measured values' derivative with respect to the index, by a
    /// forward difference, where the index is estimated with the level.
    pub(super) fn index_step_model(&self, n: f64) -> Option<FilmModel> {
        FilmModel::with_nodes(
            &self.bands,
            &self.scene.ambient,
            &Dispersion::constant(n + INDEX_DN),
            &self.scene.substrate,
            self.scene.polarization,
            &self
                .prepared
                .as_ref()
                .map_or_else(|| vec![1; self.bands.len()], |p| p.integrate.clone()),
        )
        .ok()
    }

    /// Each sample pixel fitted on its spectrum corrected by `level`, as
    /// the level fit needs it: raw values, model and model derivatives.
    pub(super) fn level_pixels(&self, sample: &[SamplePixel], level: &Level) -> Vec<LevelPixel> {
        self.level_pixels_from(sample, level, &[])
    }

    /// As [`Solver::level_pixels`], each pixel also refined from the fit in
    /// `starts` with its id (a fit found under another level), and the
    /// better of the two kept: a level is then credited with what it
    /// corrects, never with a better basin it happened to lead a pixel's
    /// search into.
    fn level_pixels_from(
        &self,
        sample: &[SamplePixel],
        level: &Level,
        starts: &[LevelPixel],
    ) -> Vec<LevelPixel> {
        let Some(prep) = &self.prepared else {
            return Vec::new();
        };
        let nb = self.bands.len();
        // Where the index is unknown, the model one step up in n2 gives each
        // pixel's derivative with respect to it (estimated with the level).
        let up = match (&self.scene.film, &self.index) {
            (FilmKnowledge::Unknown { .. }, Some(i)) => self.index_step_model(i.n),
            _ => None,
        };
        sample
            .par_iter()
            .enumerate()
            .map_init(
                || {
                    (
                        Scratch::default(),
                        ModelOut::new(nb),
                        ModelOut::new(nb),
                        vec![0.0; nb],
                    )
                },
                |(scratch, out, out_up, corr), (id, px)| {
                    // Each pixel as if first: the level's fit never depends
                    // on how the sample was split between threads.
                    scratch.start_afresh();
                    for (k, (c, &y)) in corr.iter_mut().zip(&px.spectrum).enumerate() {
                        *c = level.correct(k, y);
                    }
                    let job = Job {
                        spectrum: corr,
                        theta_known: px.theta,
                        noise: None,
                        effort: Effort::INDEX_SEARCH,
                        pre: None,
                        start: None,
                    };
                    let (mut est, sse) = self.solve_with(prep, job, scratch);
                    let st = starts.binary_search_by_key(&id, |p| p.id).ok();
                    if let Some(st) = st.map(|i| &starts[i]) {
                        let (alt, alt_sse) = self.refit_from(prep, corr, px.theta, st, scratch);
                        if alt.is_valid() && (!est.is_valid() || alt_sse < sse) {
                            est = alt;
                        }
                    }
                    if !est.is_valid() {
                        return None;
                    }
                    let th = est.theta_deg.to_radians();
                    // A fit outside the range says nothing about the level.
                    if self
                        .bound_reason(prep, est.thickness_nm, th, px.theta)
                        .is_some()
                    {
                        return None;
                    }
                    prep.model.eval(est.thickness_nm, th, out, true);
                    let mut jac = vec![out.dr_dd[..nb].to_vec()];
                    if px.theta.is_none() {
                        jac.push(out.dr_dth[..nb].to_vec());
                    }
                    let extra = match &up {
                        Some(m) => {
                            m.eval(est.thickness_nm, th, out_up, false);
                            vec![(0..nb)
                                .map(|k| level.gain[k] * (out_up.r[k] - out.r[k]) / INDEX_DN)
                                .collect()]
                        }
                        None => Vec::new(),
                    };
                    Some(LevelPixel {
                        id,
                        d: est.thickness_nm,
                        sigma_d: est.sigma_thickness_nm,
                        theta: th,
                        y: px.spectrum.clone(),
                        r: out.r[..nb].to_vec(),
                        jac,
                        extra,
                    })
                },
            )
            .flatten()
            .collect()
    }

    /// One sample pixel's spectrum (already corrected) refined from
    /// another fit's thickness and angle, judged as the sample's own fits
    /// are (no noise model: the level test weighs χ² itself).
    fn refit_from(
        &self,
        prep: &super::Prepared,
        spectrum: &[f64],
        theta_known: Option<f64>,
        start: &LevelPixel,
        scratch: &mut Scratch,
    ) -> (crate::estimate::PixelEstimate, f64) {
        let nb = self.bands.len();
        let n_ok = scratch.load(spectrum);
        let n_par = if theta_known.is_some() { 1 } else { 2 };
        if n_ok < nb.div_ceil(2).max(n_par + 3) {
            return (
                crate::estimate::PixelEstimate::invalid(crate::estimate::Reason::MissingBands),
                f64::NAN,
            );
        }
        let theta0 = theta_known.unwrap_or(start.theta);
        let iters = Effort::INDEX_SEARCH.iters;
        let fit = self.refine(
            &prep.model,
            start.d,
            theta0,
            theta_known.is_none(),
            iters,
            scratch,
        );
        let lam_min = self.band_span().0;
        self.finish(&[fit], n_ok, theta_known, None, prep, lam_min, scratch)
    }

    /// Correct a cube by the level in force (nothing to do for the
    /// identity): what every pixel is then solved on.
    pub fn apply_level(&self, cube: &mut Cube) {
        let n = cube.plane_len();
        for k in 0..cube.bands.len().min(self.level.gain.len()) {
            let (o, inv) = self.level_band(k);
            // Non-finite values (missing, or tagged dark/saturated) are kept
            // bit for bit.
            for v in cube.data[k * n..(k + 1) * n]
                .iter_mut()
                .filter(|v| v.is_finite())
            {
                *v = (*v - o) * inv;
            }
        }
    }

    /// `src` corrected by the level in force, written into `dst` (whose
    /// buffer is reused from one sweep to the next).
    pub fn correct_into(&self, src: &Cube, dst: &mut Cube) {
        if dst.bands != src.bands {
            dst.bands = src.bands.clone();
        }
        (dst.width, dst.height) = (src.width, src.height);
        dst.data.resize(src.data.len(), 0.0);
        let n = src.plane_len();
        for k in 0..src.bands.len() {
            let (o, inv) = self.level_band(k);
            let range = k * n..(k + 1) * n;
            for (d, &v) in dst.data[range.clone()].iter_mut().zip(&src.data[range]) {
                *d = if v.is_finite() { (v - o) * inv } else { v };
            }
        }
    }

    /// Band `k`'s offset and inverse gain, as f32 (identity past the level).
    fn level_band(&self, k: usize) -> (f32, f32) {
        match (self.level.offset.get(k), self.level.gain.get(k)) {
            (Some(&o), Some(&g)) => (o as f32, 1.0 / g as f32),
            _ => (0.0, 1.0),
        }
    }
}

/// Largest difference of a gain or an offset between two levels.
fn level_moved(a: &Level, b: &Level) -> f64 {
    a.gain
        .iter()
        .zip(&b.gain)
        .chain(a.offset.iter().zip(&b.offset))
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// Median over the pixels fitted both ways of |d_b − d_a| / σ_a.
fn median_shift(a: &[LevelPixel], b: &[LevelPixel]) -> f64 {
    let by_id: std::collections::HashMap<usize, &LevelPixel> =
        b.iter().map(|p| (p.id, p)).collect();
    let mut shifts: Vec<f64> = a
        .iter()
        .filter_map(|p| {
            let q = by_id.get(&p.id)?;
            let s = (q.d - p.d).abs() / p.sigma_d;
            s.is_finite().then_some(s)
        })
        .collect();
    if shifts.is_empty() {
        return 0.0;
    }
    let mid = shifts.len() / 2;
    *shifts.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// Whether a pixel's values fit the model under `level` as well as noise
/// allows (its χ² below the 1e-4 upper quantile): the pixel is consistent
/// with an image-wide level.
pub(super) fn pixel_chi2_passes(p: &LevelPixel, level: &Level, var: &[f64]) -> bool {
    let (mut chi2, mut n) = (0.0, 0usize);
    for (k, (&y, &r)) in p.y.iter().zip(&p.r).enumerate() {
        if y.is_finite() && r.is_finite() {
            let e = y - level.gain[k] * r - level.offset[k];
            chi2 += e * e / var[k];
            n += 1;
        }
    }
    let dof = n.saturating_sub(p.jac.len()).max(1);
    chi2 <= chi2_upper_quantile(dof as f64, 1e-4)
}
