//! Has the calibration moved since it was estimated? A live run
//! estimates the film index, the noise, the level and the filter's band
//! shift on its first sweep and keeps them; a lamp that dims or
//! brightens, stray light that comes and goes, a white reference that no
//! longer matches the light, a liquid-crystal filter whose pass bands
//! drift as it warms — all after that — leave every later sweep off by a
//! gain, an offset or a shift of the band centres. Where each pixel's
//! angle is free, its thickness and angle take most of such a change up
//! and its own χ² test passes (the paper's cylinder with its white
//! reference 5 % high read 5.7 nm off, all valid, before the level was
//! estimated at all), so the pixels' tests do not show it; a change
//! shared by many pixels does.
//!
//! The look ([`Solver::level_drift`]): a sample of [`DRIFT_SAMPLE_PIXELS`]
//! of the sweep, each pixel fitted under the estimates in force, and one
//! Gauss–Newton step each of a gain, of an offset, of both, and of a shift
//! of every band centre (with one gain) on top of them, shared by the
//! sample, every pixel's thickness and angle eliminated and the film index
//! held where it was estimated (it was estimated with the level; held, it
//! pins the gain tighter). Under the same calibration each step is zero;
//! against its covariance it is χ² on one or two degrees of freedom. The
//! calibration has moved where one is beyond its limit
//! ([`MAX_DRIFT_CHI2_ONE`], [`MAX_DRIFT_CHI2`]) and the step would move
//! the sample's thicknesses by more than [`MIN_ACROSS_SHIFT`] of their σ.
//! On the paper's cylinder a 256-pixel look measures a gain to ±0.5 % and
//! a band shift to ±0.1 nm. The caller then estimates everything again
//! (the live runner: on the same sweep, before solving it).

use super::level_across::{chi2_two, median_shift, MIN_ACROSS_SHIFT};
use super::Solver;
use crate::estimate::level::{level_step, LevelBasis, LevelMode};
use crate::estimate::{Cube, EstimateError};

/// Pixels fitted per look: a 1 % gain on the paper's cylinder moves the
/// step by ~4 of its σ on 256 of them, and their fits take a few ms.
pub const DRIFT_SAMPLE_PIXELS: usize = 256;

/// The χ² (two degrees of freedom) beyond which the level has moved: as
/// the halves' across the image, p ≈ 1e-5 per look (~3e-4 with the
/// level's σ running 1.2× narrow).
pub const MAX_DRIFT_CHI2: f64 = 23.0;

/// The same for the gain or the offset alone (one degree of freedom,
/// p ≈ 1e-5 each). A gain and an offset trade where the sample's
/// reflectances span little (0.03–0.08 on the paper's cylinder: their
/// estimates correlate at 0.9), so alone each is measured ~2.4× tighter.
pub const MAX_DRIFT_CHI2_ONE: f64 = 19.5;

/// The χ² per sample pixel beyond which a change matters though it moves
/// no thickness: one noise variance, a fraction of a pixel's own test's
/// margin (clean looks read ~0.004 per pixel).
pub const MIN_PIXEL_CHI2: f64 = 1.0;

/// How far the level in force is from the one a sweep shows.
#[derive(Clone, Debug, PartialEq)]
pub struct LevelDrift {
    /// The gain the sweep asks for on top of the level's (added to every
    /// band's), and its σ.
    pub gain: (f64, f64),
    /// The offset it asks for on top, and its σ.
    pub offset: (f64, f64),
    /// The shift of the filter's band centres it asks for, nm, and its σ.
    pub band_shift: (f64, f64),
    /// χ² of the look that stands out most: the gain alone, the offset
    /// alone (one degree of freedom each; the other then reads 0 ± 0), or
    /// the two jointly (two).
    pub chi2: f64,
    /// Its limit: [`MAX_DRIFT_CHI2_ONE`] or [`MAX_DRIFT_CHI2`].
    pub limit: f64,
    /// How far the step moves the sample's thicknesses, in their σ
    /// (median over the sample).
    pub shift: f64,
    /// Sample pixels fitted.
    pub pixels: usize,
}

impl LevelDrift {
    /// Whether the look that stands out is a gain or an offset (the
    /// light, the white reference, stray light), not the filter's bands.
    pub fn is_level(&self) -> bool {
        self.gain.1 > 0.0 || self.offset.1 > 0.0
    }

    /// Whether the calibration has moved beyond its noise, by enough to
    /// matter: it moves the thicknesses by more than [`MIN_ACROSS_SHIFT`]
    /// of their σ, or raises the pixels' χ² by more than
    /// [`MIN_PIXEL_CHI2`] each on average (their own tests then flag them,
    /// or nearly: a 5 % gain on a web whose film and angle are known moved
    /// its thicknesses by 0.2 σ and raised each pixel's χ² by ~100).
    pub fn moved(&self) -> bool {
        self.chi2 > self.limit
            && (self.shift > MIN_ACROSS_SHIFT || self.chi2 > MIN_PIXEL_CHI2 * self.pixels as f64)
    }

    /// One line for a log or a summary: what the look measured, on top
    /// of the estimates in force.
    pub fn describe(&self) -> String {
        let what = if self.band_shift.1 > 0.0 {
            format!(
                "the filter's band centres {:+.2} ± {:.2} nm",
                self.band_shift.0, self.band_shift.1
            )
        } else {
            let mut parts = Vec::new();
            if self.gain.1 > 0.0 {
                parts.push(format!("gain {:+.4} ± {:.4}", self.gain.0, self.gain.1));
            }
            if self.offset.1 > 0.0 {
                parts.push(format!(
                    "offset {:+.5} ± {:.5}",
                    self.offset.0, self.offset.1
                ));
            }
            parts.join(", ")
        };
        format!(
            "{what} on top of those in force: χ² = {:.1} (limit {:.1}), {:.2} σ in thickness over {} pixels",
            self.chi2, self.limit, self.shift, self.pixels
        )
    }
}

impl Solver {
    /// Estimate the film index, noise, level and band shift again on
    /// `cube` after a look ([`Solver::level_drift`]) found the calibration
    /// moved — by a gain or an offset where `level_moved` — and look at
    /// `cube` once more under the new estimates. `auto` keeps `absolute`
    /// where its test on this one image does not show the level: with the
    /// angle and index free a gain of ~3 % trades with them and shows
    /// little, and every thickness moves by several σ. But the look has
    /// shown it, against the estimates in force, at p ≈ 1e-5: there the
    /// level is modelled (`scaled`) on this image. An explicit `absolute`
    /// stays (its own test flags the image). Returns the second look where
    /// it still sees the calibration move: the new estimates do not explain
    /// the data they came from, and the caller flags what it solves with
    /// them ([`Solver::flag_calibration`]).
    pub fn estimate_again(
        &mut self,
        cube: &Cube,
        level_moved: bool,
    ) -> Result<Option<LevelDrift>, EstimateError> {
        let est = self.estimate_film_index(cube)?;
        self.set_film_index(est)?;
        if level_moved
            && self.level_mode == LevelMode::Absolute
            && self.scene.level == LevelMode::Auto
        {
            self.scene.level = LevelMode::Scaled;
            let again = self
                .estimate_film_index(cube)
                .and_then(|est| self.set_film_index(est));
            self.scene.level = LevelMode::Auto;
            again?;
        }
        Ok(self.level_drift(cube).filter(|d| d.moved()))
    }

    /// How far the level and band centres in force are from those `cube`
    /// shows (see the module's header). None before the image-wide stage
    /// has run, under `free` (every pixel has its own level), without a
    /// noise level, or where too few sample pixels fit.
    pub fn level_drift(&self, cube: &Cube) -> Option<LevelDrift> {
        if self.scene.level == LevelMode::Free || self.index.is_none() {
            return None;
        }
        let noise = self.raw_noise.clone().or_else(|| self.noise.clone())?;
        let (var, wn) = self.level_weights(&noise);
        let sample = self.sample_pixels(cube, DRIFT_SAMPLE_PIXELS);
        let mut fits = self.level_pixels(&sample, &self.level);
        // The film index held where it was estimated.
        fits.iter_mut().for_each(|p| p.extra.clear());
        fits.retain(|p| p.d.is_finite() && p.sigma_d > 0.0 && !p.jac.is_empty());
        if fits.len() < DRIFT_SAMPLE_PIXELS / 4 {
            return None;
        }
        // A lamp moves the gain, stray light the offset: each alone (one
        // degree of freedom, the sharper test of either), and both.
        let mut best: Option<([f64; 2], [f64; 2], f64, f64)> = None;
        for (basis, limit) in [
            (LevelBasis::Gain, MAX_DRIFT_CHI2_ONE),
            (LevelBasis::Offset, MAX_DRIFT_CHI2_ONE),
            (LevelBasis::GainOffset, MAX_DRIFT_CHI2),
        ] {
            let Some(step) = level_step(&fits, &self.level, basis, &wn, &var) else {
                continue;
            };
            let d = [
                step.level.gain.first()? - self.level.gain.first()?,
                step.level.offset.first()? - self.level.offset.first()?,
            ];
            let share = &step.level.share;
            let (sg, so, chi2) = match basis {
                LevelBasis::Gain => {
                    let v = share.cov_entry(0, 0);
                    (v.sqrt(), 0.0, d[0] * d[0] / v)
                }
                LevelBasis::Offset => {
                    let v = share.cov_entry(0, 0);
                    (0.0, v.sqrt(), d[1] * d[1] / v)
                }
                _ => {
                    let c = [
                        share.cov_entry(0, 0),
                        share.cov_entry(0, 1),
                        share.cov_entry(1, 1),
                    ];
                    let Some(chi2) = chi2_two(d, c) else {
                        continue;
                    };
                    (c[0].sqrt(), c[2].sqrt(), chi2)
                }
            };
            if !(chi2.is_finite() && d.iter().all(|v| v.is_finite())) {
                continue;
            }
            if best.as_ref().is_none_or(|b| chi2 / limit > b.2 / b.3) {
                best = Some((d, [sg, so], chi2, limit));
            }
        }
        let (d, sd, chi2, limit) = best?;
        // `median_shift` takes the gain relative to the level's.
        let g = self.level.gain.iter().sum::<f64>() / self.level.gain.len().max(1) as f64;
        let shift = median_shift(&fits, &self.level, [d[0] / g, d[1]], &var);
        let level_look = LevelDrift {
            gain: (d[0], sd[0]),
            offset: (d[1], sd[1]),
            band_shift: (0.0, 0.0),
            chi2,
            limit,
            shift,
            pixels: fits.len(),
        };
        // The filter's centres moved: each band's fringe phase 4π·n·d·cos θ/λ
        // moves as a thickness change of −d·Δ/λ_k would, so its response is
        // −(d/λ_k)·∂R_k/∂d (the film's dispersion and the interfaces'
        // change over a nanometre neglected), fitted with one gain.
        // (The looks above are done with the pixels' extras: the shift's
        // response takes their place.)
        for p in &mut fits {
            p.extra = vec![(0..p.r.len())
                .map(|k| -self.level.gain[k] * p.d * wn[k] * p.jac[0][k])
                .collect()];
        }
        let band_look =
            level_step(&fits, &self.level, LevelBasis::Gain, &wn, &var).and_then(|step| {
                let (ds, vs) = (*step.extra_step.first()?, *step.extra_var.first()?);
                let chi2 = ds * ds / vs;
                // The thicknesses take up the shift's mean phase, ~d·Δ·⟨1/λ⟩.
                let mean_wn = wn.iter().sum::<f64>() / wn.len().max(1) as f64;
                let mut moved: Vec<f64> = fits
                    .iter()
                    .map(|p| (p.d * ds * mean_wn).abs() / p.sigma_d)
                    .filter(|v| v.is_finite())
                    .collect();
                if moved.is_empty() {
                    return None;
                }
                let mid = moved.len() / 2;
                let shift = *moved.select_nth_unstable_by(mid, f64::total_cmp).1;
                (chi2.is_finite() && vs > 0.0).then_some(LevelDrift {
                    gain: (0.0, 0.0),
                    offset: (0.0, 0.0),
                    band_shift: (ds, vs.sqrt()),
                    chi2,
                    limit: MAX_DRIFT_CHI2_ONE,
                    shift,
                    pixels: fits.len(),
                })
            });
        let look = match band_look {
            Some(b) if b.chi2 / b.limit > level_look.chi2 / level_look.limit => b,
            _ => level_look,
        };
        Some(look)
    }
}

#[cfg(test)]
mod tests {
    use crate::estimate::Mode;
    use crate::synth::{add_noise, scene_bands, Renderer};

    /// On the paper's cylinder (film index and angles free), the level
    /// estimated on one image holds on another of the same scene with
    /// fresh noise (over eight draws χ² stays below its limit), and a gain
    /// of −3 %, an offset of +0.003 or the filter's centres 2 nm off is
    /// seen, measured to within four of its σ.
    #[test]
    fn a_gain_or_offset_since_the_level_was_estimated_is_seen() {
        let scene = crate::scene::Scene::paper_cylinder();
        let bands = scene_bands(&scene).unwrap();
        let clean = Renderer::new(&scene).unwrap().render_cube(&bands).unwrap();
        let mut first = clean.clone();
        add_noise(&mut first.data, 0.001, 1);
        let mut solver = super::Solver::new(&scene, &bands, Mode::Balanced).unwrap();
        let est = solver.estimate_film_index(&first).unwrap();
        solver.set_film_index(est).unwrap();
        for seed in 2..10 {
            let mut next = clean.clone();
            add_noise(&mut next.data, 0.001, seed);
            let d = solver.level_drift(&next).expect("a look");
            assert!(!d.moved() && d.chi2 < d.limit, "seed {seed}: {d:?}");
        }
        for (gain, offset) in [(0.97, 0.0), (1.0, 0.003)] {
            let mut next = clean.clone();
            for v in &mut next.data {
                *v = (f64::from(*v) * gain + offset) as f32;
            }
            add_noise(&mut next.data, 0.001, 11);
            let d = solver.level_drift(&next).expect("a look");
            assert!(d.moved(), "{gain} {offset}: {d:?}");
            // The step is additive to the level's gain (~1 here).
            assert!(
                (d.gain.0 - (gain - 1.0)).abs() < 4.0 * d.gain.1 + 0.002,
                "{d:?}"
            );
            assert!(
                (d.offset.0 - offset).abs() < 4.0 * d.offset.1 + 2e-4,
                "{d:?}"
            );
        }
        // The filter's centres 2 nm off (rendered there, read as nominal):
        // seen as a band shift, measured to within four of its σ.
        let moved: Vec<_> = bands
            .iter()
            .map(|b| crate::optics::band::Band {
                center_nm: b.center_nm + 2.0,
                ..*b
            })
            .collect();
        let mut next = Renderer::new(&scene).unwrap().render_cube(&moved).unwrap();
        next.bands = bands.clone();
        add_noise(&mut next.data, 0.001, 12);
        let d = solver.level_drift(&next).expect("a look");
        assert!(d.moved() && d.band_shift.1 > 0.0, "{d:?}");
        assert!(
            (d.band_shift.0 - 2.0).abs() < 4.0 * d.band_shift.1 + 0.1,
            "{d:?}"
        );
    }
}
