//! `fast` with the angle free: each row's angle from a sparse sample of
//! angle-free fits, then every pixel of the row solved at that angle on
//! the known-angle table path.
//!
//! An angle-free fit costs three to six times a known-angle one (the
//! thickness–angle valley is walked in two dimensions, with the exact
//! model). But the incidence angle is a property of the part's shape and
//! the camera's view, smooth over the image, while the thickness is what
//! changes pixel to pixel. So, per row:
//!
//! 1. about [`SAMPLES_PER_ROW`] pixels, evenly spread, take the full
//!    angle-free fit (each started from the table fit at the samples'
//!    angle so far: a fringe search is most of a free fit's cost);
//! 2. where the samples are sharp enough for their mean to be unbiased
//!    ([`MAX_SIN2_SIGMA`]), their `sin²θ` (the angle's natural parameter)
//!    is followed along the row by local lines ([`RowAngles`]: each
//!    sample's [`WINDOW`] nearest, weighted by their σ, a constant where
//!    the slope is not significant), outliers clipped; a row whose samples
//!    change faster than a window can follow is solved pixel by pixel as
//!    before;
//! 3. every pixel of the row is solved at its nearest sample's line's
//!    angle `θ̂(x)` on the table of the nearest angle bin
//!    ([`super::table::AngleBins`]), moved back along the equal-phase line
//!    `d·q(θ)` to `θ̂`, and judged by χ² against the noise model like any
//!    known-angle fit; a pixel that fails takes the angle-free fit (an
//!    edge, a defect, an angle the lines do not follow), but for runs the
//!    free fit could not explain either ([`FAILED_RUN`]);
//! 4. its σ_d adds the line's angle error in quadrature, through the
//!    equal-phase slope `∂d/∂(sin²θ) = −d·q'/q`: the line's standard
//!    error, scaled up by its window's scatter where that exceeds the
//!    samples' own σ, and never below [`BIAS_FLOOR`] of one sample's (the
//!    free fits' common bias, which no mean removes). σ_θ and the weak
//!    angle flag follow the line's σ.
//!
//! What this assumes, and where it fails safe: a row's angle changing
//! smoothly on the scale of the samples' spacing. A bump in the angle
//! narrower than the spacing is seen by no sample; a pixel there is fitted
//! at the wrong angle, which the χ² test catches where the angle error is
//! larger than the free fit's σ_θ (a smaller one moves d along the valley
//! by less than the free fit's own σ_d, but by more than the σ this path
//! reports). `balanced` and `accurate` fit every pixel's angle.

use super::row::gather;
use super::table::Hint;
use super::{Scratch, Solver, ANGLE_SIGMA_LIMIT_DEG};
use crate::estimate::level::{LevelMode, LevelPixel};
use crate::estimate::model::FilmModel;
use crate::estimate::{PixelEstimate, Reason};

/// A row's samples: about this many, evenly spread ...
const SAMPLES_PER_ROW: usize = 12;

/// ... but no closer than this many pixels apart.
pub(super) const SAMPLE_STRIDE: usize = 8;

/// After this many consecutive pixels that neither the line's angle nor
/// the free fit explained, the next keep the line's flag without the free
/// fit ...
const FAILED_RUN: usize = 2;

/// ... but for every this many-th, which tries it again.
const RETRY_EVERY: usize = 16;

/// Fewest valid samples a row's line is fitted from.
const MIN_SAMPLES: usize = 5;

/// A sample whose leave-one-out residual exceeds this many robust σ is
/// left out of the lines.
const CLIP: f64 = 4.0;

/// The largest mean square of the samples' leave-one-out residuals (each
/// against the line its window's others give, in their combined σ) at
/// which the row is still solved on its lines. Clean samples give 1 ±
/// √(2/n); a field that changes faster than a window can follow gives
/// (its misfit/σ)².
const MAX_SCATTER: f64 = 4.0;

/// The largest median σ of the samples' `sin²θ` at which a row is solved
/// on their lines. A mean of angle-free fits is unbiased only where each
/// fit's likelihood is near quadratic in `sin²θ` over its σ; where the
/// noise rivals the fringes (σ_R = 0.03 on the paper's cylinder, σ(sin²θ)
/// ~0.06) fits fall into other (d, θ) basins and pull the mean 4–7° off
/// with a σ of a fraction of a degree. The thick hard coat at 8° (0.012)
/// and the paper's cylinder at σ_R = 0.001 (≤ 0.004) lie well inside.
const MAX_SIN2_SIGMA: f64 = 0.02;

/// A local line: `v(x) = a + b·(x − x0)` (`v` = sin²θ), with the
/// variances of `a` and `b` (uncorrelated at `x0`, the samples' weighted
/// mean).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct RowAngle {
    x0: f64,
    a: f64,
    b: f64,
    var_a: f64,
    var_b: f64,
}

/// A row's angle as local lines: each sample's line through its
/// [`WINDOW`] nearest samples, a pixel taking its nearest sample's. A
/// line through the whole row would bend a field that is straight in θ
/// (sin²θ is not; 22–38° bows by 0.01, ten times the row's σ) and any
/// shape a part's curvature gives; local lines follow both, and their σ
/// (a window's, ~1/3 of the row's) leaves the free fits' own small
/// nonlinear bias well inside it.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct RowAngles {
    xs: Vec<f64>,
    lines: Vec<RowAngle>,
}

/// A local line's σ is no smaller than this fraction of a sample's
/// (their median): an angle-free fit is biased at second order in its σ,
/// the same way in every sample, and averaging removes none of it. On the
/// thin coating (sin²θ's σ 0.017 a sample) the rows' angles sat
/// 0.25 σ_sample high on average; without the floor 5 % of the pixels'
/// angles lay beyond 3 σ_θ.
const BIAS_FLOOR: f64 = 0.15;

/// Samples each local line is fitted from.
const WINDOW: usize = 9;

impl RowAngles {
    /// The local lines through `samples` (x, value, σ): outliers clipped at
    /// [`CLIP`] robust σ of their leave-one-out residuals (a sample against
    /// the line its window's others give), the row refused (`None`) where
    /// too few remain or those residuals' mean square exceeds
    /// [`MAX_SCATTER`] (the field changes faster than a window can follow).
    /// `samples` is sorted by x and shortened by the clipping.
    pub fn fit(samples: &mut Vec<(f64, f64, f64)>) -> Option<RowAngles> {
        samples.retain(|s| s.0.is_finite() && s.1.is_finite() && s.2.is_finite() && s.2 >= 0.0);
        for s in samples.iter_mut() {
            // A fit's σ of (near) zero would weigh it alone.
            s.2 = s.2.max(1e-5);
        }
        samples.sort_by(|a, b| a.0.total_cmp(&b.0));
        loop {
            let n = samples.len();
            if n < MIN_SAMPLES {
                return None;
            }
            let r: Vec<f64> = (0..n).map(|i| loo_residual(samples, i)).collect();
            let mut abs: Vec<f64> = r.iter().map(|v| v.abs()).collect();
            abs.sort_unstable_by(f64::total_cmp);
            let robust = (1.4826 * abs[n / 2]).max(1.0);
            if abs[n - 1] > CLIP * robust {
                // The worst alone: an outlier also pulls its neighbours'
                // leave-one-out lines.
                let worst = (0..n)
                    .max_by(|&a, &b| r[a].abs().total_cmp(&r[b].abs()))
                    .unwrap_or(0);
                samples.remove(worst);
                continue;
            }
            let scatter = r.iter().map(|v| v * v).sum::<f64>() / n as f64;
            if scatter > MAX_SCATTER {
                return None;
            }
            // The free fits' own bias, which no mean of them removes.
            let floor = (BIAS_FLOOR * median_sigma(samples)).powi(2);
            let lines = (0..n)
                .map(|i| {
                    let w = &samples[window(n, i)];
                    let line = RowAngle::weighted(w);
                    let p = if line.b == 0.0 { 1 } else { 2 };
                    let chi2: f64 = w
                        .iter()
                        .map(|s| ((s.1 - line.at_raw(s.0)) / s.2).powi(2))
                        .sum();
                    let k = (chi2 / (w.len().saturating_sub(p).max(1)) as f64).max(1.0);
                    RowAngle {
                        var_a: line.var_a * k + floor,
                        var_b: line.var_b * k,
                        ..line
                    }
                })
                .collect();
            return Some(RowAngles {
                xs: samples.iter().map(|s| s.0).collect(),
                lines,
            });
        }
    }

    /// The value at `x` and its standard error: the nearest sample's line.
    pub fn at(&self, x: f64) -> (f64, f64) {
        let j = self.xs.partition_point(|&v| v < x);
        let j = match j {
            0 => 0,
            j if j >= self.xs.len() => self.xs.len() - 1,
            j if x - self.xs[j - 1] <= self.xs[j] - x => j - 1,
            j => j,
        };
        self.lines[j].at(x)
    }
}

/// The [`WINDOW`] samples (of `n`) nearest sample `i`.
fn window(n: usize, i: usize) -> std::ops::Range<usize> {
    let k = WINDOW.min(n);
    let lo = i.saturating_sub(k / 2).min(n - k);
    lo..lo + k
}

/// Sample `i` against the line through its window's other samples, in
/// their combined σ.
fn loo_residual(samples: &[(f64, f64, f64)], i: usize) -> f64 {
    let mut others = [(0.0, 0.0, 0.0); WINDOW];
    let mut m = 0;
    for j in window(samples.len(), i) {
        if j != i {
            others[m] = samples[j];
            m += 1;
        }
    }
    let line = RowAngle::weighted(&others[..m]);
    let (v, sv) = line.at(samples[i].0);
    (samples[i].1 - v) / (samples[i].2.powi(2) + sv * sv).sqrt()
}

impl RowAngle {
    /// The weighted least-squares line, or the constant where the slope
    /// is not significant (|b| < 3 σ_b, σ_b with the scatter about it).
    fn weighted(samples: &[(f64, f64, f64)]) -> RowAngle {
        let w = |s: &(f64, f64, f64)| 1.0 / (s.2 * s.2);
        let sw: f64 = samples.iter().map(w).sum();
        let x0 = samples.iter().map(|s| w(s) * s.0).sum::<f64>() / sw;
        let a = samples.iter().map(|s| w(s) * s.1).sum::<f64>() / sw;
        let sxx: f64 = samples.iter().map(|s| w(s) * (s.0 - x0).powi(2)).sum();
        let sxy: f64 = samples.iter().map(|s| w(s) * (s.0 - x0) * (s.1 - a)).sum();
        let constant = RowAngle {
            x0,
            a,
            b: 0.0,
            var_a: 1.0 / sw,
            var_b: 0.0,
        };
        if sxx <= 0.0 || samples.len() < 3 {
            return constant;
        }
        let b = sxy / sxx;
        let chi2: f64 = samples
            .iter()
            .map(|s| w(s) * (s.1 - a - b * (s.0 - x0)).powi(2))
            .sum();
        let scale = (chi2 / (samples.len() - 2) as f64).max(1.0);
        if b * b <= 9.0 * scale / sxx {
            return constant;
        }
        RowAngle {
            b,
            var_b: 1.0 / sxx,
            ..constant
        }
    }

    fn at_raw(&self, x: f64) -> f64 {
        self.a + self.b * (x - self.x0)
    }

    /// The value (sin²θ) at `x` and its standard error.
    pub fn at(&self, x: f64) -> (f64, f64) {
        let dx = x - self.x0;
        (self.at_raw(x), (self.var_a + dx * dx * self.var_b).sqrt())
    }
}

impl Solver {
    /// Whether `fast`'s rows on their estimated angle take half their
    /// samples first, as the index stage's sample said of this image
    /// ([`half_the_samples_serve`]); false before that stage or where it
    /// did not sample.
    pub fn row_samples_halved(&self) -> bool {
        self.row_samples_halved
    }

    /// Whether a row of `w` pixels is solved on its estimated angle.
    pub(super) fn row_angle_applies(&self, w: usize) -> bool {
        self.prepared
            .as_ref()
            .is_some_and(|p| p.angle_bins.is_some())
            && self.index.is_some()
            && self.level_mode != LevelMode::Free
            && w >= MIN_SAMPLES * SAMPLE_STRIDE
    }

    /// The row whose band lines are `rows` (`ws` apart) solved on its estimated
    /// angle into `out`, the fits' thicknesses pushed to `fits`; false
    /// (and `out` and `fits` untouched) where its samples do not give a
    /// line: the caller then solves the row pixel by pixel.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn solve_row_on_angle(
        &self,
        rows: &[f32],
        ws: usize,
        w: usize,
        out: &mut [PixelEstimate],
        fits: &mut Vec<f64>,
        batch: &mut Vec<f64>,
        scratch: &mut Scratch,
    ) -> bool {
        let (Some(prep), Some(index)) = (&self.prepared, &self.index) else {
            return false;
        };
        let Some(bins) = prep.angle_bins.as_ref().and_then(|b| {
            b.get_or_init(|| self.angle_bins(&prep.model, index.noise_sigma))
                .as_ref()
        }) else {
            return false;
        };
        let nb = self.bands.len();
        batch.resize(super::row::GATHER * nb, 0.0);
        // 1. The samples' angle-free fits, in order along the row; where
        // the image's sample says half of them serve
        // ([`half_the_samples_serve`]), every other one first, and the
        // rest only where the row's line from those is too loose.
        let mut samples = std::mem::take(&mut scratch.angle_samples);
        samples.clear();
        let stride = (w / SAMPLES_PER_ROW).max(SAMPLE_STRIDE);
        let mut sampler = RowSampler {
            fits: std::mem::take(&mut scratch.sample_fits),
            ..RowSampler::default()
        };
        sampler.fits.clear();
        let xs = || (stride / 2..w).step_by(stride);
        let sharp = |s: &[(f64, f64, f64)]| median_sigma(s) <= MAX_SIN2_SIGMA;
        let mut take = |x: usize, samples: &mut Vec<_>, sampler: &mut RowSampler| {
            let hint = sampler.before(x as f64);
            self.take_sample(rows, ws, x, hint, bins, batch, sampler, samples, scratch);
        };
        // 2. The row's line, where the samples' angles are sharp enough
        // for their mean to be unbiased.
        let line = if self.row_samples_halved {
            xs().step_by(2)
                .for_each(|x| take(x, &mut samples, &mut sampler));
            let mut half = samples.clone();
            let first = sharp(&half).then(|| RowAngles::fit(&mut half)).flatten();
            match first {
                Some(line) if self.line_is_tight(prep, &line, &sampler.fits) => Some(line),
                _ => {
                    // Each sample between two of the first half starts on
                    // the ramp of the two before it, as if taken in order.
                    xs().skip(1)
                        .step_by(2)
                        .for_each(|x| take(x, &mut samples, &mut sampler));
                    sharp(&samples)
                        .then(|| RowAngles::fit(&mut samples))
                        .flatten()
                }
            }
        } else {
            xs().for_each(|x| take(x, &mut samples, &mut sampler));
            sharp(&samples)
                .then(|| RowAngles::fit(&mut samples))
                .flatten()
        };
        scratch.angle_samples = samples;
        scratch.sample_fits = sampler.fits;
        let Some(line) = line else {
            scratch.start_afresh();
            return false;
        };
        // 3. Every pixel at the line's angle.
        scratch.start_afresh();
        let model = &prep.model;
        let q = |s: f64| model.q2_mid(s.clamp(0.0, 1.0).sqrt().asin());
        // Per angle (once per row where the line is flat): the angle, the
        // bin, the equal-phase factor q(θ_b)/q(θ̂) and dq/ds / q at θ̂.
        let mut memo: Option<(u64, f64, Option<f64>, f64, f64)> = None;
        // The reported σ_θ, per (sin²θ, σ) (constant along a flat row).
        let mut interval = (u64::MAX, u64::MAX, 0.0);
        // Consecutive pixels the free fit did not explain either.
        let mut failed_run = 0usize;
        let mut x0 = 0;
        while x0 < w {
            let m = super::row::GATHER.min(w - x0);
            gather(rows, ws, x0, m, nb, batch);
            for i in 0..m {
                let (x, pixel) = (x0 + i, &batch[i * nb..(i + 1) * nb]);
                let (s2, ss) = line.at(x as f64);
                let (t, bin, scale, rate) = match memo {
                    Some((k, t, b, sc, r)) if k == s2.to_bits() => (t, b, sc, r),
                    _ => {
                        let s2c = s2.clamp(0.0, 1.0);
                        let t = s2c.sqrt().asin();
                        let bin = bins.bin_of(t);
                        let qt = q(s2c);
                        let h = 1e-6;
                        let (a, b) = ((s2c - h).max(0.0), (s2c + h).min(1.0));
                        let rate = (q(b) - q(a)) / (b - a) / qt;
                        let scale = bin.map_or(1.0, |tb| model.q2_mid(tb) / qt);
                        memo = Some((s2.to_bits(), t, bin, scale, rate));
                        (t, bin, scale, rate)
                    }
                };
                scratch.last_fit_d = f64::NAN;
                let at_bin = bin.map(|tb| self.solve_pixel(pixel, Some(tb), scratch));
                let o = match at_bin {
                    Some(mut o) if o.is_valid() => {
                        failed_run = 0;
                        let d = o.thickness_nm * scale;
                        let (a, b) = (o.sigma_thickness_nm * scale, d * rate * ss);
                        let a2 =
                            self.level_share_free(prep, pixel, &o, (d, t), scale, a * a, scratch);
                        o.thickness_nm = d;
                        o.sigma_thickness_nm = (a2 + b * b).sqrt();
                        o.theta_deg = t.to_degrees();
                        if (interval.0, interval.1) != (s2.to_bits(), ss.to_bits()) {
                            let st = sin2_interval(s2, ss).to_degrees();
                            interval = (s2.to_bits(), ss.to_bits(), st);
                        }
                        o.sigma_theta_deg = interval.2;
                        // The line's angle is the pixel's: weak where the
                        // line's σ_θ is (as a free fit's is judged).
                        if o.reason == Reason::Ok && interval.2 > ANGLE_SIGMA_LIMIT_DEG {
                            o.reason = Reason::AngleNotIdentifiable;
                        }
                        o
                    }
                    Some(o) if is_input_reason(o.reason) => o,
                    // In a run of pixels the free fit could not explain
                    // either (a film past the resolved range, a defect):
                    // flagged as the line's angle left them, the free fit
                    // tried again every [`RETRY_EVERY`]-th pixel.
                    Some(o) if failed_run >= FAILED_RUN && failed_run % RETRY_EVERY != 0 => {
                        failed_run += 1;
                        o
                    }
                    // Off the grid, past the tables' budget, or not
                    // explained at the line's angle: the free fit.
                    other => {
                        // Started where the table left it, moved to the
                        // line's angle: a pixel the χ² test failed by a
                        // little (the noise's tail) is refined there and
                        // judged, without the search a gross misfit (an
                        // edge, a defect, another order) still gets.
                        let d0 = scratch.last_fit_d * scale;
                        let start = (other.is_some() && d0.is_finite()).then_some((d0, t));
                        scratch.last_fit_d = f64::NAN;
                        let effort = super::Effort::of(self.mode);
                        let o = self.solve_pixel_with(pixel, None, scratch, effort, start);
                        failed_run = if o.is_valid() { 0 } else { failed_run + 1 };
                        o
                    }
                };
                scratch.note_fit(&o, fits);
                out[x] = o;
            }
            x0 += m;
        }
        true
    }
}

/// A row line's share of a pixel's σ below which its first half of
/// samples serves: the line's σ of sin²θ moves a pixel's thickness by
/// `d·|dq/ds|/q·σ_s`, and where that is at most this fraction of the
/// pixel's own σ (their median over the samples) it widens σ by at most
/// 4 %; a line from every sample (each local line from 9 samples instead
/// of 6, ~1.2× narrower) would take at most 1.5 % of σ off it.
const TIGHT_LINE: f64 = 0.3;

/// A row's samples as they are taken: their angles' running weighted mean
/// (the next sample's starting angle) and each table fit `(x, g, d, σ_d)`
/// in order along the row (`g` its optical thickness, the next walks'
/// ramp).
#[derive(Default)]
struct RowSampler {
    sum_w: f64,
    sum_ws: f64,
    fits: Vec<(f64, f64, f64, f64)>,
    /// Whether a sample that failed at the row's angle has been through
    /// the free fit's search for nothing (see [`Solver::take_sample`]).
    searched_in_vain: bool,
}

impl RowSampler {
    /// The optical thickness at `x` on the line through the two table fits
    /// nearest before it (the nearest alone where there is one; the
    /// nearest after it where there is none): the ramp the row's samples
    /// taken in order would give.
    fn before(&self, x: f64) -> Option<f64> {
        let j = self.fits.partition_point(|f| f.0 < x);
        let mut ramp = SampleRamp::default();
        for f in &self.fits[j.saturating_sub(2)..j] {
            ramp.push(f.0, f.1);
        }
        ramp.at(x).or_else(|| self.fits.get(j).map(|f| f.1))
    }
}

impl Solver {
    /// One sample of a row at `x`: its table fit at the bin of the row's
    /// angle so far (its walk started at optical thickness `hint`), then
    /// its angle-free fit from there, pushed to `samples` as
    /// `(x, sin²θ, σ)` where valid.
    #[allow(clippy::too_many_arguments)]
    fn take_sample(
        &self,
        rows: &[f32],
        ws: usize,
        x: usize,
        hint: Option<f64>,
        bins: &super::table::AngleBins,
        batch: &mut [f64],
        sampler: &mut RowSampler,
        samples: &mut Vec<(f64, f64, f64)>,
        scratch: &mut Scratch,
    ) {
        let Some(prep) = &self.prepared else {
            return;
        };
        let nb = self.bands.len();
        gather(rows, ws, x, 1, nb, batch);
        let pixel = &batch[..nb];
        let angle = if sampler.sum_w > 0.0 {
            Some(
                (sampler.sum_ws / sampler.sum_w)
                    .clamp(0.0, 1.0)
                    .sqrt()
                    .asin(),
            )
        } else {
            self.sample_theta
        };
        let mut failed_at_bin = false;
        let start = angle.and_then(|t| bins.bin_of(t)).and_then(|tb| {
            let q = prep.model.q2_mid(tb);
            if let Some(g) = hint {
                scratch.hint = Some(Hint {
                    key: tb.to_bits(),
                    d: g / q,
                    before: f64::NAN,
                });
            }
            let o = self.solve_pixel(pixel, Some(tb), scratch);
            if o.is_valid() {
                let g = o.thickness_nm * q;
                let fit = (x as f64, g, o.thickness_nm, o.sigma_thickness_nm);
                let at = sampler.fits.partition_point(|f| f.0 < fit.0);
                sampler.fits.insert(at, fit);
            }
            failed_at_bin = unexplained(o.reason);
            o.is_valid().then_some((o.thickness_nm, tb))
        });
        // Once a sample's search found nothing the model explains (a film
        // past the resolved range, a defect), the row's later samples that
        // fail at the angle of its samples so far are dropped rather than
        // searched again, each search costing as much as ~70 of the row's
        // pixels (the thick hard coat's films past its range: a tenth of
        // its time). Not before the row has a sample of its own: until
        // then the angle tried is the image's, which the row may not share.
        if failed_at_bin && sampler.searched_in_vain && sampler.sum_w > 0.0 {
            return;
        }
        if start.is_some() {
            scratch.warm = start;
            scratch.warm_before = None;
        }
        let searches = scratch.fringe_searches;
        let o = self.solve_pixel(pixel, None, scratch);
        sampler.searched_in_vain |=
            failed_at_bin && scratch.fringe_searches > searches && unexplained(o.reason);
        scratch.note_warm(&o);
        if o.is_valid() {
            let (t, st) = (o.theta_deg.to_radians(), o.sigma_theta_deg.to_radians());
            let (s2, ss) = (sin2(t), sin2_sigma(t, st));
            samples.push((x as f64, s2, ss));
            if ss > 0.0 {
                sampler.sum_w += 1.0 / (ss * ss);
                sampler.sum_ws += s2 / (ss * ss);
            }
        }
    }

    /// Whether `line`'s share of a pixel's σ is at most [`TIGHT_LINE`] of
    /// the pixel's own at the samples' table fits `(x, g, d, σ_d)` (their
    /// median), so that the line from them serves the row.
    fn line_is_tight(
        &self,
        prep: &super::Prepared,
        line: &RowAngles,
        fits: &[(f64, f64, f64, f64)],
    ) -> bool {
        let q = |s: f64| prep.model.q2_mid(s.clamp(0.0, 1.0).sqrt().asin());
        let mut r: Vec<f64> = fits
            .iter()
            .filter(|f| f.3 > 0.0)
            .map(|&(x, _, d, sd)| {
                let (s2, ss) = line.at(x);
                let h = 1e-6;
                let (a, b) = ((s2 - h).max(0.0), (s2 + h).min(1.0));
                let rate = (q(b) - q(a)) / (b - a) / q(s2);
                (d * rate * ss).abs() / sd
            })
            .collect();
        if r.len() < MIN_SAMPLES {
            return false;
        }
        crate::estimate::noise::median(&mut r) <= TIGHT_LINE
    }
}

/// Whether a row's line from half its samples ([`SAMPLES_PER_ROW`] / 2, one
/// window) would add at most [`TIGHT_LINE`] of a pixel's own σ, predicted
/// from the image's sample of angle-free fits (each one's `JᵀJ` over
/// thickness and angle, their median): the line's σ of `sin²θ` is a
/// sample's over √6 with the free fits' bias floor, and the pixel's own σ
/// its thickness's at a known angle. Decided once per image, so that every
/// row (on whichever thread) samples alike.
pub(super) fn half_the_samples_serve(model: &FilmModel, fits: &[LevelPixel]) -> bool {
    let mut r: Vec<f64> = fits
        .iter()
        .filter_map(|p| half_line_share(model, p))
        .collect();
    if r.len() < 100 {
        return false;
    }
    crate::estimate::noise::median(&mut r) <= TIGHT_LINE
}

/// One fit's [`half_the_samples_serve`] ratio: the thickness error a line
/// from half a row's samples leaves (the free fit's σ of `sin²θ` over √6,
/// with the bias floor, moved to thickness at equal phase) over the
/// pixel's own σ at a known angle; `None` where its `JᵀJ` is singular.
fn half_line_share(model: &FilmModel, p: &LevelPixel) -> Option<f64> {
    let [jd, jt] = p.jac.as_slice() else {
        return None;
    };
    let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
    for (&u, &v) in jd.iter().zip(jt) {
        if u.is_finite() && v.is_finite() {
            (a, b, c) = (a + u * u, b + u * v, c + v * v);
        }
    }
    let det = a * c - b * b;
    if !(a > 0.0 && det > 0.0 && p.d.is_finite() && p.theta.is_finite()) {
        return None;
    }
    // The noise level the fit's own σ_d implies (σ_θ's floor near normal
    // incidence is not scale-free), then σ_d at a known angle and σ_θ.
    let noise = p.sigma_d / (c / det).sqrt();
    let (sd_known, st) = (noise / a.sqrt(), noise * (a / det).sqrt());
    let half = (SAMPLES_PER_ROW / 2).min(WINDOW) as f64;
    let line = sin2_sigma(p.theta, st) * (1.0 / half + BIAS_FLOOR * BIAS_FLOOR).sqrt();
    let q = |s: f64| model.q2_mid(s.clamp(0.0, 1.0).sqrt().asin());
    let (s2, h) = (sin2(p.theta), 1e-6);
    let (lo, hi) = ((s2 - h).max(0.0), (s2 + h).min(1.0));
    let rate = (q(hi) - q(lo)) / (hi - lo) / q(s2);
    Some((p.d * rate * line).abs() / sd_known).filter(|v| v.is_finite())
}

/// The last two samples' fits along a row, `(x, optical thickness)`.
#[derive(Default)]
struct SampleRamp {
    last: Option<(f64, f64)>,
    before: Option<(f64, f64)>,
}

impl SampleRamp {
    fn push(&mut self, x: f64, g: f64) {
        self.before = self.last.replace((x, g));
    }

    /// The optical thickness at `x` on the line through the two (the last
    /// alone where there is one).
    fn at(&self, x: f64) -> Option<f64> {
        let (x1, g1) = self.last?;
        Some(match self.before {
            Some((x0, g0)) if x1 != x0 => g1 + (g1 - g0) / (x1 - x0) * (x - x1),
            _ => g1,
        })
    }
}

impl Solver {
    /// A row pixel's variance `var` (its fit's at its bin, moved to the
    /// row's angle by `scale`) with the image-wide level's share taken as
    /// an angle-free fit's at `(d, θ)` instead of a known angle's. A level
    /// error moves every sample's angle alike, so the row's angle follows
    /// it as a free fit's would, and the pixel's thickness with it: with
    /// the known angle's share, σ covered 56–69 % of the paper's cylinder
    /// under a white reference 5–8 % off or a per-band ±6 % gain.
    #[allow(clippy::too_many_arguments)]
    fn level_share_free(
        &self,
        prep: &super::Prepared,
        spectrum: &[f64],
        at_bin: &PixelEstimate,
        (d, t): (f64, f64),
        scale: f64,
        var: f64,
        scratch: &mut Scratch,
    ) -> f64 {
        if self.level.share.is_empty() {
            return var;
        }
        let tb = at_bin.theta_deg.to_radians();
        let known = self.share_var(prep, spectrum, at_bin.thickness_nm, tb, false, scratch);
        let free = self.share_var(prep, spectrum, d, t, true, scratch);
        match (known, free) {
            (Some((vk, _)), Some((vf, _))) => (var - vk * scale * scale).max(0.0) + vf,
            _ => var,
        }
    }
}

/// The median σ of the samples' `sin²θ` (infinite without samples).
fn median_sigma(samples: &[(f64, f64, f64)]) -> f64 {
    if samples.is_empty() {
        return f64::INFINITY;
    }
    let mut s: Vec<f64> = samples.iter().map(|s| s.2).collect();
    crate::estimate::noise::median(&mut s)
}

/// `sin²θ`: the angle's natural parameter. The model depends on the
/// angle through it alone (`q = √(n² − n₁² sin²θ)`, `cos θ = √(1 − sin²θ)`),
/// so a fit's likelihood is near quadratic in it and its error near
/// independent of the estimate; in θ, σ_θ shrinks as θ̂ grows, and a mean
/// weighted by 1/σ_θ² leans to the larger angles (0.35° at 8°, a 2.5 σ
/// bias on the thick hard coat's rows).
fn sin2(t: f64) -> f64 {
    t.sin().powi(2)
}

/// σ of `sin²θ` from an angle-free fit's σ_θ: `|d sin²θ/dθ|·σ_θ`, taken no
/// nearer normal incidence than σ_θ (where sin²θ is flat in θ, a fit
/// pinned there still leaves sin²θ uncertain by ~2σ_θ²).
fn sin2_sigma(t: f64, st: f64) -> f64 {
    let t = t.abs().max(st);
    (2.0 * t).sin().abs() * st
}

/// The angle interval's half-width, radians, for `sin²θ = s ± σ_s`.
fn sin2_interval(s: f64, ss: f64) -> f64 {
    let at = |v: f64| v.clamp(0.0, 1.0).sqrt().asin();
    0.5 * (at(s + ss) - at(s - ss))
}

/// Flags no angle near the line's changes: the spectrum itself unusable,
/// or a film past what the bands resolve (the resolved range moves with
/// the angle by the equal-phase factor, a few parts per thousand).
/// A fit the model could not explain (a film past the resolved range, a
/// defect), as against one too weak to say (no fringe, an ambiguous
/// order, an angle not identifiable) or unusable input.
fn unexplained(r: Reason) -> bool {
    matches!(r, Reason::PoorFit | Reason::Unresolved)
}

fn is_input_reason(r: Reason) -> bool {
    matches!(
        r,
        Reason::NonFinite
            | Reason::MissingBands
            | Reason::OutOfModel
            | Reason::Masked
            | Reason::Unresolved
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimate::model::ModelOut;
    use crate::optics::band::Band;
    use crate::optics::dispersion::Dispersion;
    use crate::optics::Polarization;

    /// 1.46 on 1.6, unpolarised, 31 bands 400–700 nm.
    fn model() -> FilmModel {
        let bands: Vec<Band> = (0..31)
            .map(|i| Band {
                center_nm: 400.0 + 10.0 * i as f64,
                fwhm_nm: 0.0,
            })
            .collect();
        let c = Dispersion::constant;
        let pol = Polarization::Unpolarized;
        FilmModel::new(&bands, &c(1.0), &c(1.46), &c(1.6), pol, &[false; 31]).unwrap()
    }

    /// A sample pixel's fit at `(d, θ)` with the model's own derivatives
    /// and its free fit's σ_d at σ_R = 0.001.
    fn fit_at(m: &FilmModel, d: f64, t: f64) -> LevelPixel {
        let mut out = ModelOut::new(31);
        m.eval(d, t, &mut out, true);
        let sum = |u: &[f64], v: &[f64]| u.iter().zip(v).map(|(a, b)| a * b).sum::<f64>();
        let (a, b, c) = (
            sum(&out.dr_dd, &out.dr_dd),
            sum(&out.dr_dd, &out.dr_dth),
            sum(&out.dr_dth, &out.dr_dth),
        );
        LevelPixel {
            y: out.r.clone(),
            r: out.r.clone(),
            jac: vec![out.dr_dd.clone(), out.dr_dth.clone()],
            extra: Vec::new(),
            id: 0,
            d,
            sigma_d: 0.001 * (c / (a * c - b * b)).sqrt(),
            theta: t,
        }
    }

    /// The ratio against a second formulation: the Jacobian by central
    /// differences of the model's reflectance (not its derivatives), the
    /// free fit's σ_θ and the known angle's σ_d from the explicit 2 × 2
    /// inverse, and the thickness's rate at equal phase from
    /// `q² = n₂² − n₁²·sin²θ` (`∂d/∂s = d·n₁²/(2q²)`), not differences of q.
    /// Then the decision: a line from six samples is a small share of a
    /// thin film's σ at 45° (its angle is sharp, the thickness's lever on
    /// it short), and most of a 2 µm film's at 8° (near normal incidence
    /// `sin²θ` is flat and the lever is ~8× longer).
    #[test]
    fn half_the_samples_serve_where_their_line_is_a_small_share_of_sigma() {
        let m = model();
        let mut out = ModelOut::new(31);
        let mut r_at = |d: f64, t: f64| {
            m.eval(d, t, &mut out, false);
            out.r.clone()
        };
        for &(d, deg) in &[(150.0, 45.0), (250.0, 30.0), (900.0, 20.0), (2000.0, 8.0)] {
            let t = f64::to_radians(deg);
            let (hd, ht) = (1e-3, 1e-6);
            let (dp, dm) = (r_at(d + hd, t), r_at(d - hd, t));
            let (tp, tm) = (r_at(d, t + ht), r_at(d, t - ht));
            let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
            for k in 0..31 {
                let (u, v) = ((dp[k] - dm[k]) / (2.0 * hd), (tp[k] - tm[k]) / (2.0 * ht));
                (a, b, c) = (a + u * u, b + u * v, c + v * v);
            }
            let sigma_theta = 0.001 * (a / (a * c - b * b)).sqrt();
            let sigma_d = 0.001 / a.sqrt();
            // Taken no nearer normal incidence than σ_θ, as a row's samples.
            let sigma_s = (2.0 * t.max(sigma_theta)).sin() * sigma_theta;
            let s = t.sin().powi(2);
            let q2 = 1.46f64.powi(2) - s;
            let line = sigma_s * (1.0 / 6.0 + 0.15f64.powi(2)).sqrt();
            let want = d / (2.0 * q2) * line / sigma_d;
            let got = half_line_share(&m, &fit_at(&m, d, t)).unwrap();

            assert!(
                (got / want - 1.0).abs() < 1e-4,
                "{d} nm at {deg}°: {got} vs {want}"
            );
        }
        let many = |d: f64, deg: f64| -> Vec<LevelPixel> {
            (0..120)
                .map(|i| fit_at(&m, d + 0.5 * i as f64, f64::to_radians(deg)))
                .collect()
        };
        assert!(half_the_samples_serve(&m, &many(150.0, 45.0)));
        assert!(!half_the_samples_serve(&m, &many(2000.0, 8.0)));
        // Too few fits to say: every sample.
        assert!(!half_the_samples_serve(&m, &many(150.0, 45.0)[..99]));
    }

    #[test]
    fn a_samples_ramp_is_the_line_through_its_last_two() {
        let mut r = SampleRamp::default();
        assert_eq!(r.at(10.0), None);
        r.push(0.0, 100.0);
        // One fit: flat.
        assert_eq!(r.at(50.0), Some(100.0));
        r.push(40.0, 180.0);
        r.push(80.0, 240.0);
        // The last two (40, 180) and (80, 240): slope 1.5 per pixel; the
        // first no longer counts.
        let g = r.at(120.0).unwrap();
        assert!((g - 300.0).abs() < 1e-9, "{g}");
        // Back along the line too.
        let g = r.at(60.0).unwrap();
        assert!((g - 210.0).abs() < 1e-9, "{g}");
    }

    /// A deterministic standard normal sequence (Box–Muller on an LCG).
    fn normals(n: usize, seed: u64) -> Vec<f64> {
        let mut s = seed;
        let mut u = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| (-2.0 * u().ln()).sqrt() * (2.0 * std::f64::consts::PI * u()).cos())
            .collect()
    }

    #[test]
    fn a_flat_rows_angle_is_a_windows_weighted_mean_with_its_standard_error() {
        // Twenty samples of 0.5 with σ 0.01: a window's mean has σ 0.01/3,
        // widened by the bias floor to √((0.01/3)² + (0.3·0.01)²) = 0.0045,
        // and over many rows the error at a pixel has the window's spread.
        let (n, rows) = (20, 400);
        let z = normals(n * rows, 7);
        let (mut errs, mut sigmas) = (Vec::new(), Vec::new());
        for r in 0..rows {
            let mut s: Vec<_> = (0..n)
                .map(|i| (8.0 * i as f64, 0.5 + 0.01 * z[r * n + i], 0.01))
                .collect();
            let line = RowAngles::fit(&mut s).expect("a line");
            let (t, st) = line.at(80.0);
            errs.push(t - 0.5);
            sigmas.push(st);
        }
        let window: f64 = 0.01 / 3.0;
        let floored = window.hypot(BIAS_FLOOR * 0.01);
        sigmas.sort_by(f64::total_cmp);
        let median = sigmas[rows / 2] / floored;
        // The scatter scaling (≥ 1) widens a window's share a little.
        assert!(
            (1.0..1.2).contains(&median),
            "median σ {median} of the floored window's"
        );
        let rms = (errs.iter().map(|e| e * e).sum::<f64>() / rows as f64).sqrt() / window;
        assert!(
            (0.85..1.15).contains(&rms),
            "rms error {rms} of a window's σ"
        );
    }

    #[test]
    fn a_bowed_rows_angle_is_followed_and_an_outlier_is_clipped() {
        // A bow of 20 σ along the row and a slope: local lines follow both.
        let z = normals(40, 3);
        let truth = |x: f64| {
            let u = x / 312.0;
            0.3 + 1e-3 * x + 0.04 * 4.0 * u * (1.0 - u)
        };
        let mut s: Vec<_> = (0..40)
            .map(|i| {
                let x = 8.0 * i as f64;
                (x, truth(x) + 0.002 * z[i], 0.002)
            })
            .collect();
        s[11].1 += 0.2;
        let lines = RowAngles::fit(&mut s).expect("lines");
        assert_eq!(s.len(), 39, "the outlier is left out");
        for x in [0.0, 100.0, 156.0, 232.0, 312.0] {
            let (t, st) = lines.at(x);
            assert!(
                (t - truth(x)).abs() < 4.0 * st,
                "{x}: {t} vs {} ± {st}",
                truth(x)
            );
            assert!(st < 0.002, "better than one sample: {st}");
        }
    }

    #[test]
    fn a_row_whose_angle_changes_faster_than_a_window_is_refused() {
        // A wave of 10 σ over six samples.
        let mut s: Vec<_> = (0..40)
            .map(|i| {
                let x = 8.0 * i as f64;
                (
                    x,
                    0.5 + 0.02 * (std::f64::consts::TAU * x / 48.0).sin(),
                    0.002,
                )
            })
            .collect();
        assert_eq!(RowAngles::fit(&mut s), None);
        // Too few samples.
        let mut few = vec![(0.0, 0.5, 0.01); MIN_SAMPLES - 1];
        assert_eq!(RowAngles::fit(&mut few), None);
    }
}
