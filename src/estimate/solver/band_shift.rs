//! The filter's wavelength calibration: one shift of every band centre,
//! fitted on the image where the data need it.
//!
//! A liquid-crystal filter's pass-band centres drift with temperature and
//! age by a nanometre or more, and a spectrometer's pixel-to-wavelength
//! map by as much. A shift Δ of every centre moves each band's fringe
//! phase δ = 4π·d·q(λ)/λ by Δ·∂δ/∂λ. A thickness scales the phase alike
//! in every band, so it takes up the mean of that change (d·Δ·⟨1/λ −
//! q′/q⟩, ~0.2 % per nm) and leaves the rest, which grows with the film's
//! order: a hard coat of 1–4 µm fails every pixel's χ² at 1 nm, the
//! paper's cylinder the image test at 2 nm, while a thin coating at 3 nm
//! passes every test with thicknesses 4 % valid and wrong.
//!
//! Under `band_shift = "auto"` (the default) the index sample's χ², each
//! pixel refitted, is profiled over the shift at the index found without
//! one; a shift is taken only where it lowers χ² by more than
//! [`SHIFT_DCHI2`] (as one gain of the level) and lies within
//! [`MAX_AUTO_SHIFT_NM`] (past it the misfit is not a calibration's).
//! Then every model and table is built on the shifted centres, the index
//! is searched again, and the shift's σ (from the profile's curvature)
//! goes into each valid pixel's σ_d through d·∂ln d/∂Δ. A given shift
//! (`band_shift = 1.5`) is applied from the start and carries no σ.

use super::bands::BandTable;
use super::index::SamplePixel;
use super::search::FringeBasis;
use super::{film_dispersion_ratios, IndexEstimate, Solver};
use crate::estimate::level::LevelMode;
use crate::estimate::{EstimateError, PixelEstimate};
use crate::optics::band::Band;
use crate::optics::dispersion::Dispersion;
use crate::scene::{AngleKnowledge, BandShift, FilmKnowledge};

/// The profile's first step either side of no shift, nm.
const PROBE_NM: f64 = 1.0;
/// The largest shift `auto` takes for a calibration error, nm: a liquid-
/// crystal filter is specified to a fraction of its ~10 nm passband, and
/// a misfit that asks for more is something else (a wrong film, a header
/// in the wrong unit), left to the tests that flag it.
pub const MAX_AUTO_SHIFT_NM: f64 = 5.0;
/// The drop in the sample's χ² a shift must bring to be taken (one
/// parameter, as one gain of the level: p ≈ 1e-4 on clean data).
pub const SHIFT_DCHI2: f64 = 15.0;
/// Evaluations of the profile's search at most (the three first
/// included).
const MAX_EVALS: usize = 10;
/// The half-width of the stencil the shift's σ is read from, nm (at
/// first; then four of its σ, down to [`MIN_STENCIL_NM`]).
const STENCIL_NM: f64 = 0.25;
/// The narrowest stencil, nm.
const MIN_STENCIL_NM: f64 = 0.01;
/// The share of a shift's drop in χ² that must come from pixels whose fit
/// at the shift passes the χ² test.
const EXPLAINED_SHARE: f64 = 0.5;
/// How far the thicknesses' measured response to a shift may stray from
/// the phase's alone (a fraction of it) for the shift to be taken.
const RESPONSE_TOLERANCE: f64 = 0.5;

/// The band shift in force and how it was found.
#[derive(Clone, Debug, Default)]
pub(super) struct ShiftState {
    /// Every true centre is the nominal one plus this, nm.
    pub nm: f64,
    /// Its σ, nm (0: given, or none fitted).
    pub sigma: f64,
    /// `auto`: fitted on the first image where the data need it.
    pub auto: bool,
    /// ∂ln d/∂Δ at the scene's middle angle, 1/nm (the thickness's
    /// response to the shift, for its share of σ_d).
    pub dlnd: f64,
    /// What the profile found (for summaries).
    pub note: String,
    /// The last profile found a shift that lowers χ², but mostly on pixels
    /// it leaves unfitted (worth a look again once a level is in force).
    pub unexplained: bool,
}

impl ShiftState {
    /// The state a scene asks for before any image is seen.
    pub fn given(b: BandShift) -> ShiftState {
        match b {
            BandShift::Auto => ShiftState {
                auto: true,
                ..Default::default()
            },
            BandShift::Given(nm) => ShiftState {
                nm,
                note: if nm == 0.0 {
                    String::new()
                } else {
                    format!("{nm:+.2} nm (given)")
                },
                ..Default::default()
            },
        }
    }
}

/// What the shift's profile found.
struct ShiftProfile {
    /// The least point, nm.
    best: f64,
    /// χ² at no shift less χ² there.
    dchi2: f64,
    /// σ of the shift from the stencil's curvature (NaN: none upward).
    sigma: f64,
    /// The part of `dchi2` on pixels whose fit at `best` passes.
    explained: f64,
}

/// `bands` with every centre moved by `nm`.
pub(super) fn shifted(bands: &[Band], nm: f64) -> Vec<Band> {
    bands
        .iter()
        .map(|b| Band {
            center_nm: b.center_nm + nm,
            fwhm_nm: b.fwhm_nm,
        })
        .collect()
}

/// The vertex and curvature (second derivative) of the parabola through
/// three points, `None` where they are collinear or coincide.
fn parabola(p: [(f64, f64); 3]) -> Option<(f64, f64)> {
    let [(x0, y0), (x1, y1), (x2, y2)] = p;
    let d01 = (y1 - y0) / (x1 - x0);
    let d12 = (y2 - y1) / (x2 - x1);
    let a = (d12 - d01) / (x2 - x0);
    if !(a.is_finite() && a != 0.0) {
        return None;
    }
    // y = y0 + d01 (x − x0) + a (x − x0)(x − x1): y′ = 0 at the vertex.
    let vertex = 0.5 * (x0 + x1) - d01 / (2.0 * a);
    Some((vertex, 2.0 * a))
}

impl Solver {
    /// The band shift in force, nm, its σ and the note on how it was found.
    pub fn band_shift(&self) -> (f64, f64, &str) {
        (self.shift.nm, self.shift.sigma, &self.shift.note)
    }

    /// Under `auto`, back to the nominal centres (models re-prepared where
    /// the film is known) before the next image's shift is fitted.
    pub(super) fn reset_band_shift(&mut self) -> Result<(), EstimateError> {
        if !self.shift.auto || self.shift.nm == 0.0 {
            return Ok(());
        }
        self.set_band_shift(0.0);
        self.shift.sigma = 0.0;
        self.prepare_known_film()
    }

    /// Put back a shift state saved before a look that found nothing
    /// (models of a known film re-prepared on its centres).
    pub(super) fn restore_band_shift(&mut self, saved: ShiftState) -> Result<(), EstimateError> {
        self.set_band_shift(saved.nm);
        self.shift = saved;
        self.prepare_known_film()
    }

    /// A known film's model and tables built again on the bands in force
    /// (an unknown film's are built with its index).
    fn prepare_known_film(&mut self) -> Result<(), EstimateError> {
        if let FilmKnowledge::Known(d) = &self.scene.film {
            let d = d.clone();
            self.prepared = Some(self.prepare(&d)?);
        }
        Ok(())
    }

    /// Build the band layout and the fringe search on the nominal centres
    /// moved by `nm` (models prepared afterwards use them).
    fn set_band_shift(&mut self, nm: f64) {
        self.shift.nm = nm;
        self.bands = shifted(&self.nominal_bands, nm);
        self.table = BandTable::new(&self.bands);
        let rho = film_dispersion_ratios(&self.scene.film, &self.bands);
        self.basis = FringeBasis::new(&self.bands, &rho, self.g_search);
        self.index_step = None;
        self.share_table = std::sync::OnceLock::new();
    }

    /// The sample's χ² (against the noise model's typical variance) with
    /// the bands shifted by `nm` and the film `film`, each pixel refitted;
    /// and each pixel's, with whether it passes the χ² test.
    fn shift_cost(
        &mut self,
        nm: f64,
        film: &Dispersion,
        sample: &[SamplePixel],
        var: f64,
    ) -> Result<(f64, Vec<(f64, bool)>), EstimateError> {
        let fits = self.fits_at(nm, film, sample)?;
        // Each pixel's χ² (capped as the index profile caps it) and
        // whether it passes the χ² test.
        let per: Vec<(f64, bool)> = sample
            .iter()
            .zip(&fits)
            .map(|(px, &(_, sse))| {
                if sse.is_finite() {
                    let p = if px.theta.is_some() { 1 } else { 2 };
                    let n = px.spectrum.iter().filter(|v| v.is_finite()).count();
                    let chi2 = sse / var;
                    let passes = chi2 <= self.chi2.threshold(n.saturating_sub(p).max(1));
                    (self.gross_capped(sse, n, p) / var, passes)
                } else {
                    (0.0, false)
                }
            })
            .collect();
        Ok((per.iter().map(|p| p.0).sum(), per))
    }

    /// Each sample pixel fitted with the bands shifted by `nm` and the
    /// film `film`: its thickness and residual.
    fn fits_at(
        &mut self,
        nm: f64,
        film: &Dispersion,
        sample: &[SamplePixel],
    ) -> Result<Vec<(f64, f64)>, EstimateError> {
        use rayon::prelude::*;
        self.set_band_shift(nm);
        let prep = self.prepare_with(film, false)?;
        // The fits start from fringe candidates found on these bands (the
        // nominal ones' candidates put a 4 nm shift's minimum 0.08 nm off,
        // 5 of its σ, on a hard coat).
        let sample = self.with_candidates(sample);
        Ok(sample
            .par_iter()
            .map_init(super::Scratch::default, |scratch, px| {
                let (est, sse) = self.solve_with(&prep, super::Job::sample(px), scratch);
                (est.thickness_nm, sse)
            })
            .collect())
    }

    /// `sample` with each pixel's fringe candidates found afresh on the
    /// bands in force.
    pub(super) fn with_candidates(&self, sample: &[SamplePixel]) -> Vec<SamplePixel> {
        use rayon::prelude::*;
        sample
            .par_iter()
            .map_init(super::Scratch::default, |scratch, p| SamplePixel {
                site: p.site,
                ..self.sample_pixel(p.spectrum.clone(), p.theta, scratch)
            })
            .collect()
    }

    /// Under `auto`, fit the band shift on `sample` at the index `est`
    /// (found without one); where the data need it, build every model of
    /// a known film on the shifted centres and return `true`: the caller
    /// draws its sample again (its fringe candidates were found on the
    /// nominal bands) and searches an unknown index on it.
    pub(super) fn fit_band_shift(
        &mut self,
        sample: &[SamplePixel],
        est: &IndexEstimate,
    ) -> Result<bool, EstimateError> {
        if !self.shift.auto || self.scene.level == LevelMode::Free || est.at_bound {
            return Ok(false);
        }
        self.shift.sigma = 0.0;
        self.shift.note.clear();
        self.shift.unexplained = false;
        let Some(var) = self
            .noise
            .as_ref()
            .map(|n| n.typical_sigma(0.05).powi(2))
            .filter(|v| *v > 0.0 && v.is_finite())
        else {
            return Ok(false);
        };
        let film = match &self.scene.film {
            FilmKnowledge::Known(d) => d.clone(),
            FilmKnowledge::Unknown { .. } => Dispersion::constant(est.n),
        };
        let reach = MAX_AUTO_SHIFT_NM + PROBE_NM;
        let (lo, hi) = self.shift_bounds(&film);
        let bounds = (lo.max(-reach), hi.min(reach));
        if bounds.1 - bounds.0 < 2.0 * PROBE_NM {
            self.shift.note = format!(
                "none (the media's tables leave the bands {:.1} to {:+.1} nm to move)",
                bounds.0, bounds.1
            );
            return Ok(false);
        }
        let profile = match self.shift_profile(&film, sample, var, bounds) {
            Ok(p) => p,
            Err(e) => {
                self.set_band_shift(0.0);
                self.shift.note = format!("none (the profile failed: {e})");
                return Ok(false);
            }
        };
        let ShiftProfile {
            best,
            dchi2,
            sigma,
            explained,
        } = profile;
        let take = dchi2 > SHIFT_DCHI2
            && explained >= SHIFT_DCHI2.max(EXPLAINED_SHARE * dchi2)
            && best.abs() <= MAX_AUTO_SHIFT_NM
            && sigma.is_finite();
        if !take {
            self.set_band_shift(0.0);
            self.shift.note = if best.abs() > MAX_AUTO_SHIFT_NM && dchi2 > SHIFT_DCHI2 {
                format!(
                    "none (the misfit would take {best:+.1} nm, beyond a filter's calibration error of ±{MAX_AUTO_SHIFT_NM} nm)"
                )
            } else if dchi2 > SHIFT_DCHI2 && explained < SHIFT_DCHI2.max(EXPLAINED_SHARE * dchi2) {
                self.shift.unexplained = true;
                format!(
                    "none (a shift of {best:+.2} nm would lower χ² by {dchi2:.0}, but only {:.0} of it on pixels it leaves fitting: the misfit of pixels no shift fits, not the filter's)",
                    explained.max(0.0)
                )
            } else if best == 0.0 {
                "none (χ² is least without one)".to_string()
            } else {
                format!(
                    "none (a shift of {best:+.2} nm would lower χ² by {:.1}, threshold {SHIFT_DCHI2})",
                    dchi2.max(0.0)
                )
            };
            return Ok(false);
        }
        // The thicknesses' response to the shift, measured on the sample,
        // against the phase's alone: where the pixels' angles take the
        // shift up, the data cannot tell one from the other (a hard coat
        // near normal incidence with the angle free moved 40 nm per nm of
        // shift, ten times the phase's 4; its profile has minima where the
        // angles make up the difference, and taken, shifts of 2 and 4 nm
        // were read 1.81 and 4.23, 2 526 and 3 759 of 6 000 pixels valid
        // and wrong), and the misfit is left flagged.
        let phase = self.thickness_per_shift(&film);
        let h = (2.0 * sigma).max(STENCIL_NM);
        let measured = self.measured_thickness_per_shift(best, h, &film, sample)?;
        if !(measured.is_finite() && (measured - phase).abs() <= RESPONSE_TOLERANCE * phase.abs()) {
            self.set_band_shift(0.0);
            self.shift.note = format!(
                "none (a shift of {best:+.2} nm would lower χ² by {dchi2:.0}, but moves thicknesses by {:.2} %/nm against the phase's {:.2} %/nm: the pixels' angles take it up, so it cannot be told from them)",
                100.0 * measured,
                100.0 * phase
            );
            return Ok(false);
        }
        self.set_band_shift(best);
        self.shift.sigma = sigma;
        self.shift.dlnd = measured;
        self.shift.note = format!(
            "{best:+.2} ± {sigma:.2} nm (fitted: χ² {dchi2:.0} lower than with none, threshold {SHIFT_DCHI2})"
        );
        tracing::info!(
            shift_nm = best,
            sigma_nm = sigma,
            dchi2,
            "band shift fitted"
        );
        self.prepare_known_film()?;
        Ok(true)
    }

    /// The sample's χ² profiled over the shift within `bounds`: 0 and a
    /// probe either side, parabolic steps of at most two probes, then a
    /// close stencil about the least point for the curvature.
    fn shift_profile(
        &mut self,
        film: &Dispersion,
        sample: &[SamplePixel],
        var: f64,
        bounds: (f64, f64),
    ) -> Result<ShiftProfile, EstimateError> {
        let mut per_pixel: Vec<(f64, Vec<(f64, bool)>)> = Vec::new();
        let mut pts: Vec<(f64, f64)> = Vec::with_capacity(MAX_EVALS);
        let eval = |s: &mut Solver,
                    per: &mut Vec<(f64, Vec<(f64, bool)>)>,
                    nm: f64|
         -> Result<f64, EstimateError> {
            let (total, p) = s.shift_cost(nm, film, sample, var)?;
            per.push((nm, p));
            Ok(total)
        };
        for nm in first_probes(bounds) {
            pts.push((nm, eval(self, &mut per_pixel, nm)?));
        }
        while pts.len() < MAX_EVALS {
            let (next, done) = next_probe(&pts, bounds);
            if done {
                break;
            }
            pts.push((next, eval(self, &mut per_pixel, next)?));
        }
        let c0 = pts[0].1;
        let least = |pts: &[(f64, f64)]| {
            *pts.iter()
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .expect("three points")
        };
        let mut curvature = f64::NAN;
        if c0 - least(&pts).1 > SHIFT_DCHI2 {
            // The curvature from a close stencil about the least point
            // (far from it a thick film's profile is no parabola: its
            // pixels change fringe order), the least point moved to the
            // stencil's vertex until that lies within a tenth of σ of it.
            // The stencil narrows to a few σ once one is known: a hard
            // coat's σ of ~0.003 nm under a ±0.25 nm stencil left its
            // vertex 0.02 nm off where the profile is not yet a parabola.
            let mut h = STENCIL_NM;
            for _ in 0..5 {
                let (best, c_best) = least(&pts);
                let lo = (best - h).max(bounds.0);
                let hi = (best + h).min(bounds.1);
                if hi - lo < h {
                    break;
                }
                let cl = eval(self, &mut per_pixel, lo)?;
                let ch = eval(self, &mut per_pixel, hi)?;
                pts.extend([(lo, cl), (hi, ch)]);
                let Some((v, k)) = parabola([(lo, cl), (best, c_best), (hi, ch)]) else {
                    break;
                };
                // A narrowed stencil that curves down (a profile jagged at
                // that scale) keeps the wider one's curvature.
                if k <= 0.0 || k.is_nan() {
                    break;
                }
                curvature = k;
                if (v - best).abs() < 0.1 * (2.0 / k).sqrt() {
                    break;
                }
                h = (4.0 * (2.0 / k).sqrt()).clamp(MIN_STENCIL_NM, STENCIL_NM);
                let v = v.clamp(lo, hi);
                pts.push((v, eval(self, &mut per_pixel, v)?));
            }
        }
        let (best, c_best) = least(&pts);
        tracing::debug!(?pts, "band shift profile (nm, χ²)");
        Ok(ShiftProfile {
            best,
            dchi2: c0 - c_best,
            sigma: if curvature > 0.0 {
                (2.0 / curvature).sqrt()
            } else {
                f64::NAN
            },
            explained: explained_drop(&per_pixel, best),
        })
    }

    /// ∂ln d/∂Δ measured on `sample`: each pixel refitted at `at ± h`,
    /// the median of its thickness's relative change per nm.
    fn measured_thickness_per_shift(
        &mut self,
        at: f64,
        h: f64,
        film: &Dispersion,
        sample: &[SamplePixel],
    ) -> Result<f64, EstimateError> {
        let mut d = [Vec::new(), Vec::new()];
        for (k, nm) in [at - h, at + h].into_iter().enumerate() {
            d[k] = self
                .fits_at(nm, film, sample)?
                .into_iter()
                .map(|(t, sse)| {
                    if sse.is_finite() && t > 0.0 {
                        t
                    } else {
                        f64::NAN
                    }
                })
                .collect();
        }
        let mut r: Vec<f64> = d[0]
            .iter()
            .zip(&d[1])
            .map(|(&a, &b)| (b - a) / (h * (a + b)))
            .filter(|v| v.is_finite())
            .collect();
        if r.is_empty() {
            return Ok(f64::NAN);
        }
        let mid = r.len() / 2;
        Ok(*r.select_nth_unstable_by(mid, f64::total_cmp).1)
    }

    /// The shifts every medium's model covers at every band centre, nm
    /// (a tabulated substrate from 400 nm leaves bands from 400 nm no
    /// shift below 0).
    fn shift_bounds(&self, film: &Dispersion) -> (f64, f64) {
        let (c_lo, c_hi) = self
            .nominal_bands
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
                (a.min(x.center_nm), b.max(x.center_nm))
            });
        [&self.scene.ambient, &self.scene.substrate, film]
            .iter()
            .filter_map(|m| m.range_nm())
            .fold((f64::NEG_INFINITY, f64::INFINITY), |(a, b), (lo, hi)| {
                (a.max(lo - c_lo), b.min(hi - c_hi))
            })
    }

    /// ∂ln d/∂Δ: how a thickness follows a shift of every band centre
    /// (the phase 4π·d·q(λ)/λ held in the mean over the bands), at the
    /// scene's middle angle; 1/nm.
    fn thickness_per_shift(&self, film: &Dispersion) -> f64 {
        let th = match self.scene.angle {
            AngleKnowledge::Uniform(t) => t,
            _ => 0.5 * (self.theta_range.0 + self.theta_range.1),
        };
        let n_at = |l: f64| film.index_at(l).map_or(f64::NAN, |n| n.re);
        let sum: f64 = self
            .bands
            .iter()
            .map(|b| {
                let l = b.center_nm;
                let n0 = self.scene.ambient.index_at(l).map_or(1.0, |n| n.re);
                let kx = n0 * th.sin();
                let n = n_at(l);
                let dn = 0.5 * (n_at(l + 0.5) - n_at(l - 0.5));
                let q2 = n * n - kx * kx;
                // The model's phase at the centre moved by Δ must stay the
                // data's: d·q(λ+Δ)/(λ+Δ) constant, so ∂ln d/∂Δ = 1/λ − q′/q,
                // with q′/q = n·n′/q².
                1.0 / l - n * dn / q2
            })
            .filter(|v| v.is_finite())
            .sum();
        sum / self.bands.len() as f64
    }

    /// The shift's share of a valid pixel's σ_d.
    pub(super) fn with_band_shift(&self, est: &mut PixelEstimate) {
        if est.is_valid() && self.shift.sigma > 0.0 {
            let s = est.thickness_nm * self.shift.dlnd * self.shift.sigma;
            est.sigma_thickness_nm = est.sigma_thickness_nm.hypot(s);
        }
    }
}

/// The drop in χ² from no shift to `best` over the pixels it explains
/// (their fit at `best` passes the χ² test): a filter's shift moves
/// every pixel's fringes into place, while pixels the model cannot fit
/// at any shift (films past the range at grazing angles: on noise-free
/// data 35 of 389 pixels, none fitting, asked for −1.4 nm) move to
/// whatever shift suits their misfit.
fn explained_drop(per_pixel: &[(f64, Vec<(f64, bool)>)], best: f64) -> f64 {
    let at = |nm: f64| per_pixel.iter().find(|(x, _)| *x == nm).map(|(_, v)| v);
    let (Some(c0), Some(cb)) = (at(0.0), at(best)) else {
        return f64::NAN;
    };
    c0.iter()
        .zip(cb)
        .filter(|(_, b)| b.1)
        .map(|(a, b)| a.0 - b.0)
        .sum()
}

/// The three evaluated points nearest `x`, by shift.
fn nearest_three(pts: &[(f64, f64)], x: f64) -> Option<[(f64, f64); 3]> {
    let mut v = pts.to_vec();
    v.sort_by(|a, b| (a.0 - x).abs().total_cmp(&(b.0 - x).abs()));
    v.truncate(3);
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    (v.len() == 3).then(|| [v[0], v[1], v[2]])
}

/// The profile's first three shifts: none and a probe either side, or
/// (where the bounds cut one side off) one and two probes on the other.
fn first_probes((lo, hi): (f64, f64)) -> [f64; 3] {
    if -PROBE_NM < lo {
        [0.0, PROBE_NM, 2.0 * PROBE_NM]
    } else if PROBE_NM > hi {
        [0.0, -PROBE_NM, -2.0 * PROBE_NM]
    } else {
        [0.0, -PROBE_NM, PROBE_NM]
    }
}

/// The next shift to evaluate, and whether the profile is done: the
/// vertex of the parabola about the least point, at most two probes from
/// it and within `bounds`; without an upward parabola two probes toward
/// the lower side. Done when the next point lies within 0.05 nm of one
/// evaluated, or past the bounds.
fn next_probe(pts: &[(f64, f64)], (lo, hi): (f64, f64)) -> (f64, bool) {
    let &(best, _) = pts
        .iter()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("points");
    let three = nearest_three(pts, best).expect("three points");
    let step = 2.0 * PROBE_NM;
    let next = match parabola(three) {
        Some((v, k)) if k > 0.0 => v.clamp(best - step, best + step),
        _ => {
            // Downhill: from the least point away from the costlier side.
            let lo = three[0].1 < three[2].1;
            if lo {
                best - step
            } else {
                best + step
            }
        }
    };
    let next = next.clamp(lo.min(0.0), hi.max(0.0));
    let seen = pts.iter().any(|p| (p.0 - next).abs() < 0.05);
    (next, seen)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_parabola_through_three_points_has_their_vertex_and_curvature() {
        let f = |x: f64| 3.0 + 2.5 * (x - 0.7) * (x - 0.7);
        let (v, k) = parabola([(-1.0, f(-1.0)), (0.0, f(0.0)), (2.0, f(2.0))]).unwrap();
        assert!((v - 0.7).abs() < 1e-12, "{v}");
        assert!((k - 5.0).abs() < 1e-12, "{k}");
        assert!(parabola([(0.0, 1.0), (1.0, 2.0), (2.0, 3.0)]).is_none());
    }

    #[test]
    fn only_pixels_the_shift_leaves_fitting_count_as_explained() {
        // Three pixels: two fit at the shift (gains 5 and 3), one fits at
        // neither (gain 100): 8 of the 108 explained.
        let per = vec![
            (0.0, vec![(20.0, false), (13.0, true), (500.0, false)]),
            (1.5, vec![(15.0, true), (10.0, true), (400.0, false)]),
        ];
        assert_eq!(explained_drop(&per, 1.5), 8.0);
        assert!(explained_drop(&per, 0.7).is_nan());
    }

    #[test]
    fn the_probe_walks_downhill_then_settles_on_the_vertex() {
        // A profile whose minimum lies 3.3 nm off: first a step of two
        // probes, then the vertex.
        let f = |x: f64| 0.8 * (x - 3.3) * (x - 3.3);
        let mut pts: Vec<(f64, f64)> = [0.0, -1.0, 1.0].iter().map(|&x| (x, f(x))).collect();
        for _ in 0..6 {
            let (x, done) = next_probe(&pts, (-6.0, 6.0));
            if done {
                break;
            }
            pts.push((x, f(x)));
        }
        let best = pts.iter().min_by(|a, b| a.1.total_cmp(&b.1)).unwrap().0;
        assert!((best - 3.3).abs() < 1e-9, "{pts:?}");
    }
}
