//! Is the level one for the whole image? A white reference that did not
//! fill the view, a lamp that lit one side more, stray light on part of
//! the field: the calibration is then off on part of the image only. An
//! image-wide level cannot correct that, and the pixels' own χ² tests do
//! not see it either, since each pixel's thickness and angle absorb most
//! of a gain error of a few percent (the paper's cylinder with its upper
//! half 5 % high: 969 of 1 960 pixels valid and wrong, the image-wide
//! test's Δχ² of 35 moving the thicknesses by 0.36 σ, too little to model).
//!
//! Run once the image-wide stage has settled (the index, the level, the
//! band shift and their looks), on a fresh sample of
//! [`super::LEVEL_SAMPLE_PIXELS`] refitted under them; only pixels whose
//! own fit passes its χ² take part (a film past the range or a defect is
//! no calibration). The other image-wide tests come first and name their
//! cause where they can (a wrong polarisation or film: the level's thinner
//! and thicker halves, the neighbouring pixels' shared misfit); a misfit
//! that differs across the image for another reason (a model error whose
//! size follows the angle or the thickness, as these vary across the
//! image) is flagged here as well, with a note that says so.
//!
//! The test: for each way of parting the sample — its halves at the
//! median column and at the median row, then windows an eighth and a
//! quarter of it wide along each axis (a white reference with a stripe of
//! dust, a lamp's fall-off at one edge) — one Gauss–Newton step
//! ([`level_step`]) of a gain and an offset shared by the image (with the
//! film index, where unknown) and of the part's gain and offset less the
//! rest's, every pixel's thickness and angle eliminated. Under one
//! calibration the difference is zero; against its covariance it is χ²
//! on two degrees of freedom. The parts differ where that is beyond
//! [`MAX_ACROSS_CHI2`] (the halves) or [`MAX_WINDOW_CHI2`] (a window, of
//! up to 30 tried) and one level for both would move the thicknesses by
//! more than [`MIN_ACROSS_SHIFT`] of their σ. A window must also change
//! its pixels' reflectance by more than the noise floor, and takes only
//! pixels whose fringe phase their fit knows to
//! [`MAX_WINDOW_PHASE_SIGMA`]: over a window's few pixels, the bias a
//! nonlinear fit leaves in each residual would otherwise read as a level.

use super::index::SamplePixel;
use super::level_fit::pixel_chi2_passes;
use super::{Solver, LEVEL_SAMPLE_PIXELS};
use crate::estimate::level::{
    level_step, local_inverse, times, Level, LevelBasis, LevelMode, LevelPixel,
};
use crate::estimate::noise::SIGMA_FLOOR;
use crate::estimate::Cube;

/// Fewest pixels in each half.
const MIN_PART_PIXELS: usize = 40;

/// The χ² (two degrees of freedom) beyond which the halves' gain and
/// offset differ too much for one calibration: 23 is p ≈ 1e-5 per split
/// (2e-5 for the two); with the level's σ running up to ~1.2× narrow
/// (README, "Over many images") it reads as 16, p ≈ 3e-4 per split.
pub(super) const MAX_ACROSS_CHI2: f64 = 23.0;

/// The χ² beyond which a window's gain and offset differ from the rest's:
/// at most [`WINDOW_STEPS`] + ([`WINDOW_STEPS`] − 1) windows along each
/// axis, 30 tests, and 2·ln(30 / 1e-5) ≈ 30 keeps them together at
/// p ≈ 1e-5 per image, as the halves.
pub(super) const MAX_WINDOW_CHI2: f64 = 30.0;

/// The σ of a pixel's fringe phase (rad) above which it takes no part in
/// the windows: a nonlinear fit's bias in the residual grows as its σ
/// squared and adds up over a window's pixels. The paper's cylinder's
/// pixels at σ_R = 0.001 know theirs to ~0.013, the thin coating's to
/// ~0.035 (0.18 at the 99th percentile); at σ_R = 0.01 the thin coating's
/// lie at 0.13–0.23, where a gain of −0.31 parted its thinnest films.
const MAX_WINDOW_PHASE_SIGMA: f64 = 0.1;

/// The windows' steps along an axis: its eighths.
const WINDOW_STEPS: usize = 8;

/// ... and it must matter: one level for both halves leaves each pixel's
/// thickness off by its share of half the difference, which must exceed
/// this many of its σ (median over the sample). A difference far below
/// the pixels' precision is no reason to flag them: a noise-free cube,
/// judged against the noise floor (1e-4) and pooled over its 435 sample
/// pixels, parted its halves by a gain of 1e-4 (χ² 32, a film
/// index-matched to its substrate at 61 bands, p light) that moves no
/// thickness by a tenth of its σ.
pub(super) const MIN_ACROSS_SHIFT: f64 = 0.5;

/// How the level differs across the image.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Across {
    /// The parts that differ most, named: "left and right halves",
    /// "columns 40–59 and the rest".
    pub split: String,
    /// The first part's gain less the second's, and its σ.
    pub gain: (f64, f64),
    /// The first part's offset less the second's, and its σ.
    pub offset: (f64, f64),
    /// χ² of the two differences jointly (two degrees of freedom).
    pub chi2: f64,
    /// The χ² beyond which they differ: [`MAX_ACROSS_CHI2`] for the
    /// halves, [`MAX_WINDOW_CHI2`] for a window.
    pub limit: f64,
    /// How far one level for both parts moves the pixels' thicknesses,
    /// in their σ (median): the halves' pixels each by its fit's response
    /// to half the difference; a window's by their response to their
    /// share of it (one less the window's fraction of the sample).
    pub shift: f64,
    /// The difference in reflectance over the part's pixels (RMS of
    /// `Δg·g_k·R_k + Δo`); a window's must exceed the noise floor
    /// ([`SIGMA_FLOOR`]): less is no calibration error any pixel could
    /// show (a noise-free film index-matched to its substrate in p light
    /// parted its thinnest films by a gain of 1e-4, χ² 38). Unbounded for
    /// the halves.
    pub size: f64,
}

impl Across {
    /// Whether the halves differ beyond one calibration, by enough to
    /// matter.
    pub fn differs(&self) -> bool {
        self.chi2 > self.limit && self.shift > MIN_ACROSS_SHIFT && self.size > SIGMA_FLOOR
    }
}

impl Solver {
    /// Whether the level in force is one for the whole image
    /// ([`level_across`]), on a fresh sample of `cube` refitted under the
    /// final index, level and band shift. Where it is not, every pixel is
    /// flagged (`calibration_suspect`) and the note says why; where it is,
    /// the note gives the test's χ². Nothing where an earlier test has
    /// flagged the image already, under `free` (every pixel has its own
    /// level), or without an independent noise level.
    pub(super) fn test_level_across(&mut self, cube: &Cube) {
        // A range from an earlier estimate says nothing of this image.
        self.sample_g = None;
        self.sample_theta = None;
        self.row_samples_halved = false;
        if self.calibration_suspect || self.scene.level == LevelMode::Free {
            return;
        }
        let Some(noise) = self.raw_noise.clone().or_else(|| self.noise.clone()) else {
            return;
        };
        let (var, wn) = self.level_weights(&noise);
        let sample = self.sample_pixels(cube, LEVEL_SAMPLE_PIXELS);
        let level = self.level.clone();
        let all = self.level_pixels(&sample, &level);
        self.note_sample_g(sample.len(), &all);
        let fits: Vec<LevelPixel> = all
            .into_iter()
            .filter(|p| pixel_chi2_passes(p, &level, &var))
            .collect();
        let linear = self.linear_over_sigma(&fits);
        let Some(a) = level_across(&sample, &fits, &linear, &level, &wn, &var) else {
            return;
        };
        if a.differs() {
            self.calibration_suspect = true;
            self.level_note = format!(
                "{}; but the level differs across the image (the gain of its {} differs by {:+.4} ± {:.4} and the offset by {:+.5} ± {:.5}: χ² = {:.0} on 2 degrees of freedom > {:.0}; one level for both would move thicknesses by {:.1} σ): a white reference that did not fill the view, light or stray light uneven over it, or a model error that follows the angle or the film across the image? every pixel flagged poor fit",
                self.level_note, a.split, a.gain.0, a.gain.1, a.offset.0, a.offset.1, a.chi2, a.limit, a.shift
            );
        } else {
            self.level_note = format!(
                "{}; the level is one across the image (its {} differ by χ² = {:.1} on 2 degrees of freedom, limit {:.0}; {:.2} σ in thickness)",
                self.level_note, a.split, a.chi2, a.limit, a.shift
            );
        }
    }
}

impl Solver {
    /// Keep the median angle of `fits` (where at least 100 fitted) for
    /// the first sample of `fast`'s rows on their angle, and their largest
    /// optical thickness (of a sample of `n` pixels) for `fast`'s angle
    /// bins, where nearly all of the sample
    /// fitted (at least 100 pixels and 98 %: films past the resolved range
    /// or out of the model leave the bins their whole range).
    fn note_sample_g(&mut self, n: usize, fits: &[LevelPixel]) {
        let Some(prep) = self.prepared.as_ref() else {
            return;
        };
        let mut thetas: Vec<f64> = fits
            .iter()
            .map(|p| p.theta)
            .filter(|t| t.is_finite())
            .collect();
        if thetas.len() >= 100 {
            let mid = thetas.len() / 2;
            self.sample_theta = Some(*thetas.select_nth_unstable_by(mid, f64::total_cmp).1);
            self.row_samples_halved = super::angle_map::half_the_samples_serve(&prep.model, fits);
        }
        if fits.len() < 100 || (fits.len() as f64) < 0.98 * n as f64 {
            return;
        }
        let mut hi = 0f64;
        for p in fits {
            let g = p.d * prep.model.q2_mid(p.theta);
            if !g.is_finite() {
                return;
            }
            hi = hi.max(g);
        }
        self.sample_g = Some(hi);
    }
}

impl Solver {
    /// Which of `fits` may take part in the windows: those whose fringe
    /// phase the fit knows to [`MAX_WINDOW_PHASE_SIGMA`] (4π·q₂·σ_d / λ at
    /// the bands' middle), so that their model is nearly linear over their
    /// own σ.
    fn linear_over_sigma(&self, fits: &[LevelPixel]) -> Vec<bool> {
        let Some(prep) = self.prepared.as_ref() else {
            return vec![false; fits.len()];
        };
        let (lo, hi) = self.band_span();
        let k = 4.0 * std::f64::consts::PI / (0.5 * (lo + hi));
        fits.iter()
            .map(|p| k * prep.model.q2_mid(p.theta) * p.sigma_d <= MAX_WINDOW_PHASE_SIGMA)
            .collect()
    }
}

/// One way of parting the sample: the pixels whose column (axis 0) or row
/// (axis 1) lies in `lo..hi`, against the rest.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Part {
    axis: usize,
    lo: usize,
    hi: usize,
    /// The split at the median: the image's halves.
    halves: bool,
}

impl Part {
    /// The two parts, named for the note.
    fn name(&self) -> String {
        match (self.halves, self.axis) {
            (true, 0) => "left and right halves".into(),
            (true, _) => "upper and lower halves".into(),
            (false, axis) => format!(
                "{} {}–{} and the rest",
                if axis == 0 { "columns" } else { "rows" },
                self.lo,
                self.hi - 1
            ),
        }
    }

    /// The χ² beyond which its parts differ.
    fn limit(&self) -> f64 {
        if self.halves {
            MAX_ACROSS_CHI2
        } else {
            MAX_WINDOW_CHI2
        }
    }
}

/// The ways of parting `sites` tried: along each axis, the halves at the
/// median (`halves`), or windows an eighth and a quarter of the sample
/// wide (at its eighths; not `halves`), each with at least
/// [`MIN_PART_PIXELS`] inside and out.
fn parts(sites: &[(usize, usize)], halves: bool) -> Vec<Part> {
    let mut parts = Vec::new();
    for axis in [0, 1] {
        let mut c: Vec<usize> = sites
            .iter()
            .map(|s| if axis == 0 { s.0 } else { s.1 })
            .collect();
        c.sort_unstable();
        let (Some(&first), Some(&last)) = (c.first(), c.last()) else {
            continue;
        };
        let count =
            |lo: usize, hi: usize| c.partition_point(|&v| v < hi) - c.partition_point(|&v| v < lo);
        let fits = |lo: usize, hi: usize| {
            let inside = count(lo, hi);
            inside >= MIN_PART_PIXELS && c.len() - inside >= MIN_PART_PIXELS
        };
        let median = c[c.len() / 2];
        if halves {
            if fits(first, median) {
                parts.push(Part {
                    axis,
                    lo: first,
                    hi: median,
                    halves: true,
                });
            }
            continue;
        }
        // The eighths' bounds, the last one past the sample's end.
        let mut bounds: Vec<usize> = (0..WINDOW_STEPS)
            .map(|i| c[i * c.len() / WINDOW_STEPS])
            .collect();
        bounds.push(last + 1);
        bounds.dedup();
        for width in [1, 2] {
            for i in 0..bounds.len().saturating_sub(width) {
                let (lo, hi) = (bounds[i], bounds[i + width]);
                let half = (lo == first && hi == median) || (lo == median && hi == last + 1);
                let part = Part {
                    axis,
                    lo,
                    hi,
                    halves: false,
                };
                if !half && fits(lo, hi) && !parts.contains(&part) {
                    parts.push(part);
                }
            }
        }
    }
    parts
}

/// The part of the sample's fitted pixels `fits` (ids into `sample`)
/// whose level differs most from the rest's ([`parts`]: the halves, and
/// windows an eighth and a quarter of the sample wide), stepped from
/// `level`; `wavenumber` and `var` as for [`level_step`]. The halves are
/// tried on every pixel of `fits`, the windows on those marked `linear`
/// only: pixels whose model is nearly linear over their own σ (a window
/// is small, and the bias a nonlinear fit leaves in each pixel's residual
/// adds up over it: a thin coating at σ_R = 0.01, phases known to ~0.16
/// rad, parted its thinnest eighth from the rest by a gain of −0.31 ±
/// 0.03 with no calibration error at all). Where any part differs
/// ([`Across::differs`]), the one furthest past its limit; else the one
/// nearest to it. None where no part leaves [`MIN_PART_PIXELS`] on each
/// side or the pixels carry no image position.
///
/// Each part is one step of a gain and an offset shared by the image
/// (with the film index, where unknown) and two more parameters: the
/// part's gain and offset less the rest's, to which its measured values
/// respond as `g·R` and 1 and the rest's not at all. Sharing the rest
/// keeps the comparison as sharp as the data allow: two halves fitted
/// apart each trade their gain with their own offset and index, and miss
/// a 5 % gain on half the paper's cylinder. Gain and offset are tested
/// jointly, as a partial error moves both (each part's pixels take part
/// of a gain up in their angles and leave the rest looking like an
/// offset).
pub(super) fn level_across(
    sample: &[SamplePixel],
    fits: &[LevelPixel],
    linear: &[bool],
    level: &Level,
    wavenumber: &[f64],
    var: &[f64],
) -> Option<Across> {
    let sites: Vec<(usize, usize)> = fits
        .iter()
        .map(|p| sample.get(p.id).and_then(|s| s.site))
        .collect::<Option<_>>()?;
    let keep = |i: &usize| linear.get(*i).copied().unwrap_or(false);
    let lin: Vec<usize> = (0..fits.len()).filter(keep).collect();
    let lin_fits: Vec<LevelPixel> = lin.iter().map(|&i| fits[i].clone()).collect();
    let lin_sites: Vec<(usize, usize)> = lin.iter().map(|&i| sites[i]).collect();
    let mut worst: Option<Across> = None;
    for (fits, sites, halves) in [(fits, &sites, true), (&lin_fits[..], &lin_sites, false)] {
        let mut px = fits.to_vec();
        for part in parts(sites, halves) {
            let Some(a) = part_across(part, fits, sites, &mut px, level, wavenumber, var) else {
                continue;
            };
            let key = |a: &Across| (a.differs(), a.chi2 / a.limit);
            if worst.as_ref().is_none_or(|w| key(&a) > key(w)) {
                worst = Some(a);
            }
        }
    }
    worst
}

/// One part's step against the rest ([`level_across`]); `px` holds a copy
/// of `fits` whose extras each part replaces.
fn part_across(
    part: Part,
    fits: &[LevelPixel],
    sites: &[(usize, usize)],
    px: &mut [LevelPixel],
    level: &Level,
    wavenumber: &[f64],
    var: &[f64],
) -> Option<Across> {
    let inside = |s: &(usize, usize)| {
        let c = if part.axis == 0 { s.0 } else { s.1 };
        (part.lo..part.hi).contains(&c)
    };
    // The part's two parameters after each pixel's own extras (the film
    // index's, where unknown), in `px`'s copies of `fits`.
    for ((p, f), s) in px.iter_mut().zip(fits).zip(sites) {
        let inside = if inside(s) { 1.0 } else { 0.0 };
        p.extra.truncate(f.extra.len());
        p.extra.push(
            (0..f.y.len())
                .map(|k| inside * level.gain[k] * f.r[k])
                .collect(),
        );
        p.extra.push(vec![inside; f.y.len()]);
    }
    let step = level_step(px, level, LevelBasis::GainOffset, wavenumber, var)?;
    let n = step.extra_step.len();
    if n < 2 || step.extra_cov.len() != n * n {
        return None;
    }
    let d = [step.extra_step[n - 2], step.extra_step[n - 1]];
    let c = [
        step.extra_cov[(n - 2) * n + n - 2],
        step.extra_cov[(n - 2) * n + n - 1],
        step.extra_cov[(n - 1) * n + n - 1],
    ];
    let chi2 = chi2_two(d, c)?;
    let within: Vec<&LevelPixel> = fits
        .iter()
        .zip(sites)
        .filter(|(_, s)| inside(s))
        .map(|(p, _)| p)
        .collect();
    // One level for both leaves each side off by its share of the
    // difference: the halves each by half of it; a window, which weighs
    // little in the level, by nearly all of it.
    let (shift, size) = if part.halves {
        let shift = median_shift(fits, level, [0.5 * d[0], 0.5 * d[1]], var);
        (shift, f64::INFINITY)
    } else {
        let share = 1.0 - within.len() as f64 / fits.len() as f64;
        let shift = median_shift(
            within.iter().copied(),
            level,
            [share * d[0], share * d[1]],
            var,
        );
        // The difference in reflectance over the window's pixels (RMS).
        let (mut sum, mut count) = (0.0, 0usize);
        for p in &within {
            for (k, r) in p.r.iter().enumerate() {
                let e = d[0] * level.gain[k] * r + d[1];
                if e.is_finite() {
                    sum += e * e;
                    count += 1;
                }
            }
        }
        (shift, (sum / count.max(1) as f64).sqrt())
    };
    Some(Across {
        split: part.name(),
        gain: (d[0], c[0].sqrt()),
        offset: (d[1], c[2].sqrt()),
        chi2,
        limit: part.limit(),
        shift,
        size,
    })
}

/// χ² of two differences `d` against their covariance `c` (`[c₀₀, c₀₁,
/// c₁₁]`); None where the covariance is singular or anything is not finite.
pub(super) fn chi2_two(d: [f64; 2], c: [f64; 3]) -> Option<f64> {
    let det = c[0] * c[2] - c[1] * c[1];
    if !(det > 0.0 && det.is_finite() && d.iter().all(|v| v.is_finite())) {
        return None;
    }
    Some((d[0] * d[0] * c[2] - 2.0 * d[0] * d[1] * c[1] + d[1] * d[1] * c[0]) / det)
}

/// The median over `fits` of |Δd|/σ_d, Δd each pixel's thickness response
/// (its own fit, thickness and angle free, the rest held) to a gain
/// `dg` and an offset `doff` on top of `level`.
pub(super) fn median_shift<'a>(
    fits: impl IntoIterator<Item = &'a LevelPixel>,
    level: &Level,
    [dg, doff]: [f64; 2],
    var: &[f64],
) -> f64 {
    let mut shifts: Vec<f64> = fits
        .into_iter()
        .filter_map(|p| {
            let nl = p.jac.len().min(2);
            if nl == 0 || p.sigma_d.is_nan() || p.sigma_d <= 0.0 {
                return None;
            }
            // Normal matrix A of the pixel's own parameters, and the
            // gradient of the misfit the level change leaves.
            let (mut a, mut b) = ([[0.0f64; 2]; 2], [0.0f64; 2]);
            for (k, (&y, &r)) in p.y.iter().zip(&p.r).enumerate() {
                if !(y.is_finite() && r.is_finite()) {
                    continue;
                }
                let (w, g) = (1.0 / var[k], level.gain[k]);
                let e = dg * g * r + doff;
                let j = [g * p.jac[0][k], if nl > 1 { g * p.jac[1][k] } else { 0.0 }];
                for i in 0..nl {
                    b[i] += w * j[i] * e;
                    for l in 0..nl {
                        a[i][l] += w * j[i] * j[l];
                    }
                }
            }
            let dd = times(&local_inverse(a, nl == 2, 0.0)?, b)[0];
            let s = dd.abs() / p.sigma_d;
            s.is_finite().then_some(s)
        })
        .collect();
    if shifts.is_empty() {
        return 0.0;
    }
    let mid = shifts.len() / 2;
    *shifts.select_nth_unstable_by(mid, f64::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A toy image: pixels whose model is a sinusoid over 21 bands with
    /// their own phase (a thickness), measured under a gain and noise.
    fn toy(
        n: usize,
        gain_of: impl Fn(usize) -> f64,
        noise: &mut impl FnMut() -> f64,
    ) -> Vec<LevelPixel> {
        let nb = 21;
        (0..n)
            .map(|i| {
                let phase = 0.37 * i as f64;
                let r: Vec<f64> = (0..nb)
                    .map(|k| 0.1 + 0.05 * (0.6 * k as f64 + phase).cos())
                    .collect();
                let dr: Vec<f64> = (0..nb)
                    .map(|k| -0.05 * (0.6 * k as f64 + phase).sin())
                    .collect();
                let y = r.iter().map(|v| gain_of(i) * v + 0.001 * noise()).collect();
                // The phase's σ at the noise's variance of 1e-6.
                let sigma_d = 1e-3 / dr.iter().map(|v| v * v).sum::<f64>().sqrt();
                LevelPixel {
                    y,
                    r,
                    jac: vec![dr],
                    extra: vec![],
                    id: i,
                    d: 0.0,
                    sigma_d,
                    theta: 0.0,
                }
            })
            .collect()
    }

    fn sample_at(sites: impl Iterator<Item = (usize, usize)>) -> Vec<SamplePixel> {
        sites
            .map(|s| SamplePixel {
                spectrum: vec![],
                theta: None,
                cands: Default::default(),
                n_cands: [0; 2],
                site: Some(s),
            })
            .collect()
    }

    fn normal(seed: u64) -> impl FnMut() -> f64 {
        let mut s = seed;
        move || {
            // Box–Muller on a 64-bit LCG.
            let mut u = || {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            (-2.0 * u().ln()).sqrt() * (std::f64::consts::TAU * u()).cos()
        }
    }

    #[test]
    fn a_gain_on_half_or_a_strip_only_is_seen_and_one_gain_is_not() {
        let nb = 21;
        let (wn, var): (Vec<f64>, Vec<f64>) = (0..nb)
            .map(|k| (1.0 / (400.0 + 10.0 * k as f64), 1e-6))
            .unzip();
        let (w, h) = (20, 10);
        let sample = sample_at((0..w * h).map(|i| (i % w, i / w)));
        let identity = Level::identity(nb);
        let all_linear = vec![true; w * h];
        // One gain everywhere (3 %): no part's χ² (two degrees of freedom
        // each, p ≈ 1e-5 at the halves' limit and 3e-7 at a window's)
        // reaches its limit over 20 noise draws, and the largest scatters
        // as the largest of the ~16 parts' χ²₂ does (mean 2 for one draw,
        // ~6.8 for 16 independent ones; less, as the parts overlap).
        let mut sum = 0.0;
        for seed in 0..20 {
            let fits = toy(w * h, |_| 1.03, &mut normal(seed));
            let a = level_across(&sample, &fits, &all_linear, &identity, &wn, &var)
                .expect("both splits");
            assert!(a.chi2 < a.limit && !a.differs(), "seed {seed}: {a:?}");
            sum += a.chi2;
        }
        assert!(
            (2.0..12.0).contains(&(sum / 20.0)),
            "mean χ² {}",
            sum / 20.0
        );
        // 3 % on the left half only: the left-right split, far beyond,
        // its gain difference measured to its σ.
        let fits = toy(
            w * h,
            |i| if i % w < w / 2 { 1.03 } else { 1.0 },
            &mut normal(1),
        );
        let a =
            level_across(&sample, &fits, &all_linear, &identity, &wn, &var).expect("both splits");
        assert_eq!(a.split, "left and right halves");
        assert!(a.chi2 > 10.0 * MAX_ACROSS_CHI2, "{a:?}");
        assert!((a.gain.0 - 0.03).abs() < 4.0 * a.gain.1, "{a:?}");
        // 4 % on the first quarter of the columns: a window's test, far
        // beyond its limit, and the window named. (Whether it matters is
        // the thicknesses' business: a toy's gain is nearly orthogonal to
        // its phase, and moves it by a few hundredths of its σ.)
        let fits = toy(
            w * h,
            |i| if i % w < 5 { 1.04 } else { 1.0 },
            &mut normal(2),
        );
        let a =
            level_across(&sample, &fits, &all_linear, &identity, &wn, &var).expect("both splits");
        assert_eq!(a.split, "columns 0–4 and the rest");
        assert!(a.chi2 > 10.0 * MAX_WINDOW_CHI2, "{a:?}");
        assert!(a.shift > 0.0 && a.shift < MIN_ACROSS_SHIFT, "{a:?}");
        assert!((a.gain.0 - 0.04).abs() < 4.0 * a.gain.1, "{a:?}");
        // Without image positions, no test.
        let mut anon = sample.clone();
        anon.iter_mut().for_each(|p| p.site = None);
        assert!(level_across(&anon, &fits, &all_linear, &identity, &wn, &var).is_none());
    }

    /// The shift's response, from each pixel's 2 × 2 normal matrix
    /// inverted in closed form (`local_inverse`, as the level step does),
    /// against the least-squares refit of the pixel's
    /// thickness and angle to the level change's misfit solved by
    /// Cholesky (`solve_spd`), for one pixel at a time: the median of one
    /// is that pixel's |Δd|/σ_d.
    #[test]
    fn the_shift_is_each_pixels_refit_to_the_level_change() {
        let nb = 31;
        let var: Vec<f64> = (0..nb)
            .map(|k| 1e-6 * (1.0 + 0.3 * (k % 4) as f64))
            .collect();
        let mut level = Level::identity(nb);
        level
            .gain
            .iter_mut()
            .enumerate()
            .for_each(|(k, g)| *g = 0.95 + 0.003 * k as f64);
        for (i, (dg, doff)) in [(0.02, 0.0), (0.0, 0.003), (-0.015, 0.001)]
            .into_iter()
            .enumerate()
        {
            let ph = 0.7 * i as f64;
            let r: Vec<f64> = (0..nb)
                .map(|k| 0.08 + 0.04 * (0.5 * k as f64 + ph).cos())
                .collect();
            let jd: Vec<f64> = (0..nb)
                .map(|k| -0.02 * (0.5 * k as f64 + ph).sin() * (1.0 + 0.01 * k as f64))
                .collect();
            let jt: Vec<f64> = (0..nb)
                .map(|k| 0.01 + 0.002 * (0.3 * k as f64).cos())
                .collect();
            let p = LevelPixel {
                y: r.clone(),
                r: r.clone(),
                jac: vec![jd.clone(), jt.clone()],
                sigma_d: 0.5,
                ..LevelPixel::default()
            };
            let got = median_shift([&p], &level, [dg, doff], &var);
            // The misfit e_k = dg·g_k·R_k + doff, fitted by g_k·(J·Δ).
            let mut a = vec![0.0; 4];
            let mut b = vec![0.0; 2];
            for k in 0..nb {
                let g = level.gain[k];
                let e = dg * g * r[k] + doff;
                let j = [g * jd[k], g * jt[k]];
                for u in 0..2 {
                    b[u] += j[u] * e / var[k];
                    for v in 0..2 {
                        a[u * 2 + v] += j[u] * j[v] / var[k];
                    }
                }
            }
            let delta = crate::estimate::level::solve_spd(&a, 2, &b).expect("positive definite");
            let want = delta[0].abs() / 0.5;
            assert!(
                (got - want).abs() <= 1e-9 * want.max(1.0),
                "{i}: {got} against {want}"
            );
            assert!(want > 0.0);
        }
    }

    /// `fast` with the angle free tabulates its angle bins about the
    /// optical thicknesses the index stage's sample shows (as much again
    /// and two orders more): on the paper's cylinder (420–560 nm) that is
    /// well short of the whole resolved range. A few small patches of a
    /// 1.6 µm film the sample may miss lie past the bins' tables: their
    /// pixels are not explained there and take the angle-free fit, so none
    /// is valid and wrong, and every pixel outside them is as before.
    #[test]
    fn films_past_the_bins_tables_take_the_angle_free_fit() {
        use crate::estimate::Mode;
        use crate::scene::Field;
        use crate::synth::{add_noise, scene_bands, Renderer};
        let mut scene = crate::scene::Scene::paper_cylinder();
        let t = scene.truth.as_mut().expect("the scene has a truth");
        (t.width, t.height) = (600, 14);
        let bands = scene_bands(&scene).unwrap();
        let mut cube = Renderer::new(&scene).unwrap().render_cube(&bands).unwrap();
        let mut truth = Renderer::new(&scene)
            .unwrap()
            .truth_maps(&bands)
            .thickness_nm;
        let mut thick = scene.clone();
        thick.truth.as_mut().unwrap().thickness_nm = Field::Constant(1600.0);
        let other = Renderer::new(&thick).unwrap().render_cube(&bands).unwrap();
        let (w, n) = (cube.width, cube.plane_len());
        // Four 2 × 2 patches on no site of the index's or the level's
        // samples (their lattice depends on the image's size alone).
        let sites: std::collections::HashSet<(usize, usize)> =
            Solver::sample_sites(&cube, LEVEL_SAMPLE_PIXELS)
                .into_iter()
                .chain(Solver::sample_sites(
                    &cube,
                    crate::estimate::solver::INDEX_SAMPLE_PIXELS,
                ))
                .collect();
        let mut patch = Vec::new();
        for (x0, y0) in [(13, 1), (201, 5), (412, 9), (587, 12)] {
            let (x0, y0) = (x0..w - 1)
                .flat_map(|x| (y0..y0 + 1).map(move |y| (x, y)))
                .find(|&(x, y)| {
                    [(0, 0), (1, 0), (0, 1), (1, 1)]
                        .iter()
                        .all(|(dx, dy)| !sites.contains(&(x + dx, y + dy)))
                })
                .expect("room between the sites");
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                patch.push((y0 + dy) * w + x0 + dx);
            }
        }
        for k in 0..bands.len() {
            for &i in &patch {
                cube.data[k * n + i] = other.data[k * n + i];
            }
        }
        for &i in &patch {
            truth[i] = 1600.0;
        }
        add_noise(&mut cube.data, 0.001, 7);
        let mut solver = Solver::new(&scene, &bands, Mode::Fast).unwrap();
        solver.estimate_film_index(&cube).unwrap();
        let g_hi = solver.sample_g.expect("the sample fitted");
        let prep = solver.prepared.as_ref().unwrap();
        let g_patch = 1600.0 * prep.model.q2_mid(40f64.to_radians());
        let g_bins = super::super::bins_g_limit(g_hi, 560.0);
        // The sample saw the cylinder's films, not the patches: the bins
        // stop short of them.
        assert!(
            g_bins < g_patch,
            "sample to {g_hi}, bins to {g_bins}, patch {g_patch}"
        );
        let maps = solver.fit_cube(&cube).unwrap();
        let (mut valid_patch, mut wrong, mut valid) = (0, 0, 0);
        for (i, &d_true) in truth.iter().enumerate() {
            if maps.valid[i] < 0.5 {
                continue;
            }
            valid += 1;
            valid_patch += usize::from(patch.contains(&i));
            let e = f64::from((maps.thickness_nm[i] - d_true).abs());
            if e > (3.0 * f64::from(maps.sigma_thickness_nm[i])).max(2.0) {
                wrong += 1;
            }
        }
        eprintln!("sample g ≤ {g_hi:.0}, bins to {g_bins:.0}, patch g {g_patch:.0}: {valid} valid, {valid_patch} of the patch's {}, {wrong} valid and wrong", patch.len());
        assert!(valid >= n * 97 / 100, "{valid} of {n} valid");
        // Noise alone puts ~1 in 1000 valid pixels past max(3σ, 2 nm).
        assert!(wrong <= n / 500, "{wrong} valid and wrong");
        // The patch is solved (by the angle-free fit where the bins do
        // not reach it): most of its pixels valid, and right.
        assert!(
            valid_patch >= patch.len() / 2,
            "{valid_patch} of the patch valid"
        );
    }
}
