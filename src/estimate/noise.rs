//! The reflectance noise model: how much a measured reflectance may scatter
//! about the truth, per band, known before any fit is judged.
//!
//! A fit's own residual cannot tell a good fit from a bad one: a misfit
//! shared by most pixels raises it as much as noise does. So the noise σ
//! comes from somewhere else:
//!
//! - **given**: `--noise-sigma`, the scene's `[noise] sigma`, or a σ per band;
//! - **camera**: read and shot noise measured on the repeated dark and white
//!   frames of a calibration, propagated through the calibration
//!   (`σ_R² = α + β·R` per band, see `pipeline::calibration`);
//! - **data**: estimated from the cube without any model, by robust
//!   (median-based) differences that cancel smooth signal: second
//!   differences between neighbouring pixels along each image axis, and
//!   fourth differences along wavelength where the bands are dense (per
//!   band, over a window of neighbouring bands: a spectrometer's noise grows
//!   tenfold towards the ends of its range). Signal only ever adds to such a
//!   difference, so the smallest estimate is the least contaminated one.
//!
//! On top of the noise, a **reflectance-scale accuracy** ε (`rel2` = ε²):
//! what a measured absolute reflectance may be off by, as a fraction of R,
//! from its reference (the reference's own table, focus height, lamp drift
//! between reference and sample, a lamp line imperfectly divided out). It is
//! not noise (it is smooth and the same in every repeat), so no difference
//! of the data measures it; it is a property of the instrument, given
//! (`--reflectance-accuracy`), and added in quadrature.

#![allow(clippy::needless_range_loop)] // band-indexed numeric loops read clearer with indices

use super::lanes::{load, Chi2Lanes, F64x4};
use super::Cube;
use multiversion::multiversion;

/// Where a noise level came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NoiseSource {
    /// Given by the user or the scene.
    Given,
    /// Measured on the camera's calibration frames.
    Camera,
    /// Estimated from the data without a model.
    Data,
}

impl NoiseSource {
    /// Name for summaries and file attributes.
    pub fn name(self) -> &'static str {
        match self {
            NoiseSource::Given => "given",
            NoiseSource::Camera => "camera",
            NoiseSource::Data => "data",
        }
    }
}

/// Smallest noise σ irid believes: 1e-4 in reflectance, ten times below
/// a good camera's (the paper's σ is 1e-3). Noise-free data are judged
/// against it: the refinement stops once a step is far below the
/// statistical error, which near Brewster's angle or at grazing incidence
/// can leave residuals of ~1e-5, and f32 storage adds ~1e-8; a misfit of a
/// few 1e-4 is still flagged.
pub const SIGMA_FLOOR: f64 = 1e-4;

/// Per-band reflectance noise:
/// `σ_k(R)² = var0[k] + shot[k]·max(R, 0) + rel2·R²`.
#[derive(Clone, Debug, PartialEq)]
pub struct NoiseModel {
    /// Signal-independent variance per band (cube plane order).
    pub var0: Vec<f64>,
    /// Signal-dependent (shot) variance per unit reflectance, per band.
    pub shot: Vec<f64>,
    /// Squared relative accuracy of the reflectance scale (ε², 0: exact).
    pub rel2: f64,
    /// Where it came from.
    pub source: NoiseSource,
}

/// A [`NoiseModel`] whose variances do not depend on the reflectance
/// ([`NoiseModel::flat`]): per band the variance and its inverse.
#[derive(Clone, Debug, PartialEq)]
pub struct FlatNoise {
    var: Vec<f64>,
    inv_var: Vec<f64>,
    /// The least and greatest inverse variance of any band.
    inv_range: (f64, f64),
    /// The mean variance of every band, as [`FlatNoise::chi2_and_mean_var`]
    /// gives it for a complete spectrum (to the bit).
    mean_var: f64,
}

impl FlatNoise {
    /// The one variance of every band and its inverse, where all bands
    /// share it (then χ² is a residual sum over it).
    pub fn uniform(&self) -> Option<(f64, f64)> {
        let (&v, &inv) = (self.var.first()?, self.inv_var.first()?);
        self.var.iter().all(|&x| x == v).then_some((v, inv))
    }

    /// Each band's variance and its inverse.
    pub fn parts(&self) -> (&[f64], &[f64]) {
        (&self.var, &self.inv_var)
    }

    /// The smallest inverse variance of any band (+∞ with no band).
    pub fn min_inv_var(&self) -> f64 {
        self.inv_range.0
    }

    /// Whether a complete spectrum whose residual sum of squares is `sse`
    /// passes a χ² test at `threshold`, where the bands' spread of variance
    /// settles it without the residual band by band: `χ² = Σ e²/σ²` lies
    /// between `sse` over the largest and over the smallest variance
    /// (a relative 1e-6 spared for the rounding of `sse`). `None` where
    /// the threshold falls between; the χ² returned lies on the side it
    /// settles, and the bands' mean variance comes with it.
    pub fn settle_complete(&self, sse: f64, threshold: f64) -> Option<(f64, f64)> {
        let (lo, hi) = (sse * self.inv_range.0, sse * self.inv_range.1);
        if !(lo.is_finite() && hi.is_finite() && sse >= 0.0) {
            return None;
        }
        if hi * (1.0 + 1e-6) <= threshold {
            Some((hi * (1.0 + 1e-6), self.mean_var))
        } else if lo * (1.0 - 1e-6) > threshold {
            Some((lo * (1.0 - 1e-6), self.mean_var))
        } else {
            None
        }
    }

    /// As [`NoiseModel::chi2_and_mean_var`] (the model values `r` only
    /// enter through the residual).
    pub fn chi2_and_mean_var(&self, y: &[f64], w: &[f64], r: &[f64]) -> (f64, f64) {
        flat_chi2(&self.var, &self.inv_var, y, w, r)
    }
}

/// One band's variance at reflectance `r`, `var0 + shot·R + rel2·R²` with
/// `R = max(r, 0)`, floored at [`SIGMA_FLOOR`]²: [`NoiseModel::var`], and
/// the tail of every χ² kernel that weighs bands by it.
#[inline(always)]
pub(crate) fn band_var(var0: f64, shot: f64, rel2: f64, r: f64) -> f64 {
    let r = r.max(0.0);
    (var0 + shot * r + rel2 * r * r).max(SIGMA_FLOOR * SIGMA_FLOOR)
}

/// [`band_var`] for four bands, lane for lane the same arithmetic.
#[inline(always)]
pub(crate) fn band_var4(var0: F64x4, shot: F64x4, rel2: F64x4, r: F64x4) -> F64x4 {
    let r = r.max(F64x4::ZERO);
    (var0 + shot * r + rel2 * r * r).max(F64x4::splat(SIGMA_FLOOR * SIGMA_FLOOR))
}

/// [`NoiseModel::chi2_and_mean_var`]: four bands at a time in `F64x4`
/// lanes (the divisions overlap), the tail band by band, with the same
/// arithmetic as [`NoiseModel::var`].
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn model_chi2(
    var0: &[f64],
    shot: &[f64],
    rel2: f64,
    y: &[f64],
    w: &[f64],
    r: &[f64],
) -> (f64, f64) {
    let n = y
        .len()
        .min(w.len())
        .min(r.len())
        .min(var0.len())
        .min(shot.len());
    let (y, w, r, var0, shot) = (&y[..n], &w[..n], &r[..n], &var0[..n], &shot[..n]);
    let rel4 = F64x4::splat(rel2);
    let mut lanes = Chi2Lanes::new();
    let quads = y.chunks_exact(4).zip(r.chunks_exact(4)).zip(
        w.chunks_exact(4)
            .zip(var0.chunks_exact(4).zip(shot.chunks_exact(4))),
    );
    for ((y, r), (w, (var0, shot))) in quads {
        let r = load(r);
        let var = band_var4(load(var0), load(shot), rel4, r);
        lanes.add_div(load(w), load(y) - r, var);
    }
    let mut sums = lanes.sums();
    for k in n - n % 4..n {
        let var = band_var(var0[k], shot[k], rel2, r[k]);
        sums.add_div(w[k], y[k] - r[k], var);
    }
    sums.totals()
}

/// [`FlatNoise::chi2_and_mean_var`]: four independent lanes, no branch and
/// no division per band.
#[allow(clippy::needless_range_loop)] // four lanes, indexed alike
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn flat_chi2(var: &[f64], inv: &[f64], y: &[f64], w: &[f64], r: &[f64]) -> (f64, f64) {
    let n = y
        .len()
        .min(w.len())
        .min(r.len())
        .min(var.len())
        .min(inv.len());
    let (y, w, r) = (&y[..n], &w[..n], &r[..n]);
    let (var, inv) = (&var[..n], &inv[..n]);
    // Four bands at a time in `F64x4` lanes (indexed lanes kept the loop
    // scalar: the bounds checks), the tail band by band, with the same
    // arithmetic (`lanes`).
    let mut lanes = Chi2Lanes::new();
    let quads = y.chunks_exact(4).zip(r.chunks_exact(4)).zip(
        w.chunks_exact(4)
            .zip(var.chunks_exact(4).zip(inv.chunks_exact(4))),
    );
    for ((y, r), (w, (var, inv))) in quads {
        lanes.add(load(w), load(y) - load(r), load(var), load(inv));
    }
    let mut sums = lanes.sums();
    for k in n - n % 4..n {
        sums.add(w[k], y[k] - r[k], var[k], inv[k]);
    }
    sums.totals()
}

impl NoiseModel {
    /// The same σ on every band.
    pub fn uniform(sigma: f64, n_bands: usize, source: NoiseSource) -> NoiseModel {
        let s = sigma.max(SIGMA_FLOOR);
        NoiseModel {
            var0: vec![s * s; n_bands],
            shot: vec![0.0; n_bands],
            rel2: 0.0,
            source,
        }
    }

    /// A σ per band.
    pub fn per_band(sigma: &[f64], source: NoiseSource) -> NoiseModel {
        NoiseModel {
            var0: sigma.iter().map(|s| s.max(SIGMA_FLOOR).powi(2)).collect(),
            shot: vec![0.0; sigma.len()],
            rel2: 0.0,
            source,
        }
    }

    /// The same noise with a reflectance-scale accuracy ε (a fraction of R)
    /// added in quadrature; the larger of ε and the one already in force.
    pub fn with_accuracy(mut self, eps: f64) -> NoiseModel {
        if eps.is_finite() && eps > 0.0 {
            self.rel2 = self.rel2.max(eps * eps);
        }
        self
    }

    /// The noise of data corrected by an image-wide level: where the
    /// measured `y_k = g_k·R_k + o_k` carries `var0 + shot·y`, the
    /// corrected `(y_k − o_k)/g_k` carries `(var0 + shot·o)/g² +
    /// (shot/g)·R` (a negative offset is not taken off the variance: near
    /// R = 0 the data's own floor holds). The scale accuracy is a fraction
    /// of R and stays. Bands past `gain`'s end, or with a gain that is not
    /// positive and finite, keep their noise.
    pub fn under_level(&self, gain: &[f64], offset: &[f64]) -> NoiseModel {
        let mut out = self.clone();
        for k in 0..out.var0.len().min(gain.len()).min(offset.len()) {
            let (g, o) = (gain[k], offset[k]);
            if !(g.is_finite() && g > 0.0 && o.is_finite()) {
                continue;
            }
            out.var0[k] = (self.var0[k] + self.shot[k] * o.max(0.0)) / (g * g);
            out.shot[k] = self.shot[k] / g;
        }
        out
    }

    /// The reflectance-scale accuracy ε in force (0: none).
    pub fn accuracy(&self) -> f64 {
        self.rel2.sqrt()
    }

    /// Number of bands.
    pub fn n_bands(&self) -> usize {
        self.var0.len()
    }

    /// The smallest variance of any band at a reflectance in [0, 1] (the
    /// ends and the vertex of the quadratic; 0 with no band).
    pub fn min_var(&self) -> f64 {
        let at = |k: usize| {
            let vertex = if self.rel2 > 0.0 {
                (-self.shot[k] / (2.0 * self.rel2)).clamp(0.0, 1.0)
            } else {
                0.0
            };
            self.var(k, 0.0)
                .min(self.var(k, 1.0))
                .min(self.var(k, vertex))
        };
        let min = (0..self.var0.len()).map(at).fold(f64::INFINITY, f64::min);
        if min.is_finite() {
            min
        } else {
            0.0
        }
    }

    /// The largest variance of any band at a reflectance in
    /// `[0, r_max]` (a variance is convex in the reflectance: the ends;
    /// 0 with no band).
    pub fn max_var_below(&self, r_max: f64) -> f64 {
        let r_max = r_max.max(0.0);
        (0..self.var0.len())
            .map(|k| self.var(k, 0.0).max(self.var(k, r_max)))
            .fold(0.0, f64::max)
    }

    /// Variance of band `k` at reflectance `r`.
    #[inline]
    pub fn var(&self, k: usize, r: f64) -> f64 {
        band_var(self.var0[k], self.shot[k], self.rel2, r)
    }

    /// χ² of `y` (weights `w`: 0 drops a band) against the model values
    /// `r`, each band weighted by its variance at `r`, and the mean
    /// variance of the bands used (0 when none is). Four independent lanes
    /// and no branch per band, so the divisions overlap (a single chain
    /// waited on each one).
    pub fn chi2_and_mean_var(&self, y: &[f64], w: &[f64], r: &[f64]) -> (f64, f64) {
        let n = y.len().min(w.len()).min(r.len()).min(self.var0.len());
        let (y, w, r) = (&y[..n], &w[..n], &r[..n]);
        let (var0, shot) = (&self.var0[..n], &self.shot[..n]);
        model_chi2(var0, shot, self.rel2, y, w, r)
    }

    /// The same model where no band's variance depends on the reflectance
    /// (no shot term, an exact scale): each band's inverse variance, once,
    /// so χ² needs no division per band. `None` otherwise.
    pub fn flat(&self) -> Option<FlatNoise> {
        if self.rel2 != 0.0 || self.shot.iter().any(|&s| s != 0.0) {
            return None;
        }
        let var: Vec<f64> = (0..self.var0.len()).map(|k| self.var(k, 0.0)).collect();
        let inv_var: Vec<f64> = var.iter().map(|v| 1.0 / v).collect();
        let inv_range = inv_var
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        let (ones, zeros) = (vec![1.0; var.len()], vec![0.0; var.len()]);
        let (_, mean_var) = flat_chi2(&var, &inv_var, &zeros, &ones, &zeros);
        Some(FlatNoise {
            var,
            inv_var,
            inv_range,
            mean_var,
        })
    }

    /// A typical σ (root mean variance over bands at reflectance `r`).
    pub fn typical_sigma(&self, r: f64) -> f64 {
        self.root_mean_var(self.rel2, r)
    }

    /// Root mean variance over bands at reflectance `r` with the scale
    /// accuracy `rel2` (ε²).
    fn root_mean_var(&self, rel2: f64, r: f64) -> f64 {
        let n = self.var0.len().max(1) as f64;
        let sum: f64 = (0..self.var0.len())
            .map(|k| band_var(self.var0[k], self.shot[k], rel2, r))
            .sum();
        (sum / n).sqrt()
    }

    /// The instrument's typical σ at reflectance `r`: [`typical_sigma`]
    /// without the reflectance-scale accuracy, which is reported beside it
    /// (a σ of 1e-3 judged with ε = 10 % would otherwise read 5e-3).
    ///
    /// [`typical_sigma`]: NoiseModel::typical_sigma
    pub fn instrument_sigma(&self, r: f64) -> f64 {
        self.root_mean_var(0.0, r)
    }

    /// Whether every band's variance is the same constant (a scalar σ).
    pub fn is_uniform(&self) -> bool {
        self.rel2 == 0.0
            && self.shot.iter().all(|&s| s == 0.0)
            && self.var0.windows(2).all(|w| w[0] == w[1])
    }

    /// Estimate the noise from the cube itself, without a model: per band,
    /// the smallest of the robust σ of second differences along x, along y
    /// and (for dense band sets) of fourth differences along wavelength.
    /// `None` when the cube is too small to tell.
    pub fn from_data(cube: &Cube) -> Option<NoiseModel> {
        Self::from_data_with(cube, true)
    }

    /// [`NoiseModel::from_data`], the estimate along wavelength per band
    /// (`per_band`) or pooled over all bands. The free level keeps the
    /// pooled one: its fringe-order margins were set against it, and with
    /// the per-band one a lamp's bump passed for a first-order fringe
    /// (`tests/free_level_spectra.rs`).
    pub fn from_data_with(cube: &Cube, per_band: bool) -> Option<NoiseModel> {
        let nb = cube.bands.len();
        let spectral = spectral_sigmas(cube).map(|(pooled, mut s)| {
            if !per_band {
                s.iter_mut().for_each(|v| *v = pooled);
            }
            s
        });
        let mut sig = Vec::with_capacity(nb);
        for k in 0..nb {
            let plane = cube.plane(k);
            let s = [
                axis_sigma(plane, cube.width, cube.height, 1),
                axis_sigma(plane, cube.width, cube.height, cube.width),
                spectral.as_ref().map(|s| s[k]),
            ]
            .into_iter()
            .flatten()
            .fold(f64::INFINITY, f64::min);
            sig.push(s);
        }
        // A band with too few usable samples takes the median of the others.
        let mut known: Vec<f64> = sig.iter().copied().filter(|s| s.is_finite()).collect();
        if known.is_empty() {
            return None;
        }
        let med = median(&mut known);
        for s in &mut sig {
            if !s.is_finite() {
                *s = med;
            }
        }
        Some(NoiseModel::per_band(&sig, NoiseSource::Data))
    }
}

/// Robust σ of white noise from second differences `v[i−s] − 2v[i] + v[i+s]`
/// (variance 6σ²) along one image axis (`stride` 1: x, `width`: y); at most
/// ~20 000 triples, spread over the plane. `None` with fewer than 30.
fn axis_sigma(plane: &[f32], width: usize, height: usize, stride: usize) -> Option<f64> {
    let (len_axis, n_lines) = if stride == 1 {
        (width, height)
    } else {
        (height, width)
    };
    if len_axis < 3 {
        return None;
    }
    let total = (len_axis - 2) * n_lines;
    let step = total.div_ceil(20_000).max(1);
    let mut d = Vec::with_capacity(total / step + 1);
    let mut t = 0;
    while t < total {
        let (line, pos) = (t / (len_axis - 2), t % (len_axis - 2) + 1);
        let i = if stride == 1 {
            line * width + pos
        } else {
            pos * width + line
        };
        let (a, b, c) = (plane[i - stride], plane[i], plane[i + stride]);
        let v = f64::from(a) - 2.0 * f64::from(b) + f64::from(c);
        if v.is_finite() {
            d.push(v.abs());
        }
        t += step;
    }
    if d.len() < 30 {
        return None;
    }
    Some(1.4826 * median(&mut d) / 6f64.sqrt())
}

/// Robust σ pooled over all bands, and per band (cube plane order), from
/// fourth differences along
/// wavelength (variance 70σ²), pooled over up to 2 000 pixels; only for band
/// sets of at least 16 bands whose steps in wavelength are even (within
/// 10 %), where a fringe changes little from one band to the next. `None`
/// otherwise.
///
/// Each band takes the differences centred within a window of its
/// neighbours (at least 31 centres, a tenth of the bands on denser sets),
/// and never less than the estimate pooled over all bands: a spectrometer's
/// noise grows tenfold towards its range's ends, which one pooled value
/// hides (the ends then fail every fit), while a window's median scatters
/// by ~1.25/√N and an estimate scattering low would fail clean spectra.
fn spectral_sigmas(cube: &Cube) -> Option<(f64, Vec<f64>)> {
    let nb = cube.bands.len();
    if nb < 16 {
        return None;
    }
    let mut order: Vec<usize> = (0..nb).collect();
    order.sort_by(|&a, &b| cube.bands[a].center_nm.total_cmp(&cube.bands[b].center_nm));
    let steps: Vec<f64> = order
        .windows(2)
        .map(|w| cube.bands[w[1]].center_nm - cube.bands[w[0]].center_nm)
        .collect();
    let (lo, hi) = steps
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &s| (a.min(s), b.max(s)));
    if !(lo > 0.0 && hi <= 1.1 * lo) {
        return None;
    }
    let n = cube.plane_len();
    let step = n.div_ceil(2_000).max(1);
    let mut spec = vec![0.0; nb];
    // |4th difference| per centre (sorted band position 2..nb−3).
    let mut by_centre: Vec<Vec<f64>> = vec![Vec::new(); nb];
    for i in (0..n).step_by(step) {
        for (k, &b) in order.iter().enumerate() {
            spec[k] = f64::from(cube.data[b * n + i]);
        }
        for (c, w) in spec.windows(5).enumerate() {
            let v = w[0] - 4.0 * w[1] + 6.0 * w[2] - 4.0 * w[3] + w[4];
            if v.is_finite() {
                by_centre[c + 2].push(v.abs());
            }
        }
    }
    let scale = 1.4826 / 70f64.sqrt();
    let mut all: Vec<f64> = by_centre.iter().flatten().copied().collect();
    if all.len() < 30 {
        return None;
    }
    let pooled = scale * median(&mut all);
    let (first, last) = (2, nb - 3);
    let half = 15.max(nb / 20);
    let mut out = vec![pooled; nb];
    let mut d = Vec::new();
    for (p, &b) in order.iter().enumerate() {
        // A window of 2·half + 1 centres, shifted inwards at the ends.
        let a = p.saturating_sub(half).max(first);
        let z = (a + 2 * half).min(last);
        let a = z.saturating_sub(2 * half).max(first);
        d.clear();
        for c in a..=z {
            d.extend_from_slice(&by_centre[c]);
        }
        if d.len() >= 30 {
            out[b] = (scale * median(&mut d)).max(pooled);
        }
    }
    Some((pooled, out))
}

/// Median (reorders `v`; `v` not empty).
pub(crate) fn median(v: &mut [f64]) -> f64 {
    let m = v.len() / 2;
    let (_, x, _) = v.select_nth_unstable_by(m, |a, b| a.total_cmp(b));
    *x
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::band::Band;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    /// Data measured through a level and corrected by it scatter as
    /// [`NoiseModel::under_level`] says: checked by drawing the measured
    /// values (read and shot noise at the measured signal) and taking the
    /// corrected values' sample variance, at three reflectances and gains
    /// below and above one. 40 000 draws: the sample variance is within
    /// 1.5 % of the truth at 2 σ (√(2/40 000) = 0.7 %); a model left at
    /// the raw noise misses by 14–18 % here, one dividing by g instead of
    /// g² by 8 %.
    #[test]
    fn corrected_data_scatter_as_the_noise_under_the_level() {
        let raw = NoiseModel {
            var0: vec![1e-6, 4e-6],
            shot: vec![2e-5, 0.0],
            rel2: 0.0,
            source: NoiseSource::Camera,
        };
        let (gain, offset) = ([0.92, 1.08], [0.01, 0.004]);
        let under = raw.under_level(&gain, &offset);
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let n = 40_000;
        for k in 0..2 {
            for r in [0.02, 0.1, 0.3] {
                let y0 = gain[k] * r + offset[k];
                let sd = raw.var(k, y0).sqrt();
                let normal = Normal::new(y0, sd).unwrap();
                let c: Vec<f64> = (0..n)
                    .map(|_| (normal.sample(&mut rng) - offset[k]) / gain[k])
                    .collect();
                let mean = c.iter().sum::<f64>() / n as f64;
                let var = c.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
                let want = under.var(k, r);
                assert!(
                    (var / want - 1.0).abs() < 0.015,
                    "band {k}, R {r}: sample variance {var:.4e}, model {want:.4e}"
                );
            }
        }
        // The identity level leaves the noise as it was.
        assert_eq!(raw.under_level(&[1.0, 1.0], &[0.0, 0.0]), raw);
    }

    /// Where the bands' spread of variance settles a complete spectrum's
    /// χ² test, it settles it as the band-by-band χ² does; it settles most
    /// spectra of noise at the bands' own σ (spread ±10 %), and the mean
    /// variance it returns is the band-by-band one to the bit.
    #[test]
    fn settled_chi2_tests_agree_with_the_band_by_band_chi2() {
        let sigma: Vec<f64> = (0..31)
            .map(|k| 0.001 * (0.9 + 0.2 * k as f64 / 30.0))
            .collect();
        let flat = NoiseModel::per_band(&sigma, NoiseSource::Given)
            .flat()
            .expect("flat");
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let (w, r) = (vec![1.0; 31], vec![0.0; 31]);
        let threshold = 50.9; // χ²(30) at p = 0.01
        let (mut settled, mut passed, mut failed) = (0, 0, 0);
        for i in 0..4000 {
            // Noise at 0.5–2× the bands' σ: clean, noisy and poor pixels.
            let scale = 0.5 + 1.5 * (i % 40) as f64 / 40.0;
            let y: Vec<f64> = sigma
                .iter()
                .map(|&s| Normal::new(0.0, s * scale).unwrap().sample(&mut rng))
                .collect();
            let sse: f64 = y.iter().map(|e| e * e).sum();
            let (chi2, mean) = flat.chi2_and_mean_var(&y, &w, &r);
            if let Some((c, m)) = flat.settle_complete(sse, threshold) {
                settled += 1;
                assert_eq!(c <= threshold, chi2 <= threshold, "sse {sse}");
                assert_eq!(m.to_bits(), mean.to_bits());
                if chi2 <= threshold {
                    passed += 1;
                } else {
                    failed += 1;
                }
            }
        }
        assert!(settled > 3000, "settled {settled} of 4000");
        assert!(
            passed > 500 && failed > 500,
            "passed {passed}, failed {failed}"
        );
    }

    #[test]
    fn min_var_is_the_least_variance_over_bands_and_reflectance() {
        let src = NoiseSource::Given;
        assert_eq!(NoiseModel::uniform(0.002, 5, src).min_var(), 0.002 * 0.002);
        let per = NoiseModel::per_band(&[0.003, 0.001, 0.002], src);
        assert_eq!(per.min_var(), 0.001 * 0.001);
        // A shot term that falls with R (as a fitted one may) against a
        // scale accuracy that rises: the least lies inside [0, 1], checked
        // against a dense scan of the variance itself.
        let mut m = NoiseModel::per_band(&[0.004, 0.003], src).with_accuracy(0.01);
        m.shot = vec![-8e-6, -1.2e-5];
        let scan = (0..2)
            .flat_map(|k| (0..=10_000).map(move |i| (k, f64::from(i) / 10_000.0)))
            .map(|(k, r)| m.var(k, r))
            .fold(f64::INFINITY, f64::min);
        assert!(
            (m.min_var() - scan).abs() <= 1e-6 * scan,
            "{} vs {scan}",
            m.min_var()
        );
        assert!(m.min_var() < 0.003 * 0.003);
        assert_eq!(NoiseModel::per_band(&[], src).min_var(), 0.0);
    }

    /// `max_var_below` against a dense scan of the variance over [0, r_max]
    /// (a shot term that falls with R against a scale accuracy that rises,
    /// so neither end alone is the largest for every band).
    #[test]
    fn the_instrument_sigma_leaves_the_scale_accuracy_out() {
        // σ = 1e-3 judged with ε = 10 %: at R = 0.05 the variance the fits
        // are judged with is 1e-6 + (0.1 · 0.05)², 26× the instrument's.
        let m = NoiseModel::uniform(1e-3, 4, NoiseSource::Given).with_accuracy(0.1);
        let judged = (1e-6_f64 + 0.005 * 0.005).sqrt();
        assert!((m.typical_sigma(0.05) - judged).abs() < 1e-12 * judged);
        assert!((m.instrument_sigma(0.05) - 1e-3).abs() < 1e-15);
        // A shot term stays the instrument's: σ² = 1e-6 + 4e-6 · R.
        let mut shot = NoiseModel::uniform(1e-3, 2, NoiseSource::Given).with_accuracy(0.1);
        shot.shot = vec![4e-6; 2];
        assert!((shot.instrument_sigma(0.5) - 3e-6_f64.sqrt()).abs() < 1e-15);
    }

    #[test]
    fn max_var_below_is_the_largest_variance_up_to_r_max() {
        let src = NoiseSource::Given;
        let mut m = NoiseModel::per_band(&[0.004, 0.003, 0.001], src).with_accuracy(0.02);
        m.shot = vec![-8e-6, 2e-5, -1e-6];
        for r_max in [0.0, 0.05, 0.2, 0.6, 1.0] {
            let scan = (0..3)
                .flat_map(|k| (0..=10_000).map(move |i| (k, r_max * f64::from(i) / 10_000.0)))
                .map(|(k, r)| m.var(k, r))
                .fold(0.0, f64::max);
            let got = m.max_var_below(r_max);
            assert!(
                (got - scan).abs() <= 1e-9 * scan,
                "{r_max}: {got} vs {scan}"
            );
        }
        assert_eq!(NoiseModel::per_band(&[], src).max_var_below(0.5), 0.0);
    }

    fn cube_with(
        w: usize,
        h: usize,
        nb: usize,
        f: impl Fn(usize, usize, usize) -> f64,
        sigma: f64,
    ) -> Cube {
        let bands: Vec<Band> = (0..nb)
            .map(|k| Band::new(400.0 + 10.0 * k as f64, 0.0).unwrap())
            .collect();
        let mut c = Cube::zeros(w, h, bands);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let noise = Normal::new(0.0, sigma).unwrap();
        for k in 0..nb {
            for y in 0..h {
                for x in 0..w {
                    let v = f(x, y, k) + noise.sample(&mut rng);
                    c.data[k * w * h + y * w + x] = v as f32;
                }
            }
        }
        c
    }

    #[test]
    fn white_noise_on_a_smooth_scene_is_recovered() {
        // A thickness ramp along x and an angle ramp along y: the signal's
        // first differences are as large as the noise, its second ones not.
        for sigma in [3e-4, 1e-3, 4e-3] {
            let c = cube_with(
                120,
                40,
                31,
                |x, y, k| {
                    let lam = 400.0 + 10.0 * k as f64;
                    let d = 400.0 + x as f64;
                    0.05 + 0.03 * (4.0 * std::f64::consts::PI * 1.37 * d / lam).cos()
                        + 0.001 * y as f64
                },
                sigma,
            );
            let m = NoiseModel::from_data(&c).unwrap();
            assert_eq!(m.source, NoiseSource::Data);
            for k in 0..31 {
                let s = m.var(k, 0.05).sqrt();
                // ~2 400 differences per band: the median's relative
                // error is about 1.25/sqrt(n) ≈ 2.5 %; allow 4 standard errors.
                assert!((s / sigma - 1.0).abs() < 0.1, "band {k}: {s} vs {sigma}");
            }
        }
    }

    #[test]
    fn a_single_dense_spectrum_uses_the_wavelength_axis() {
        // One pixel, 300 bands 1 nm apart: only the spectral estimate applies,
        // and a slow fringe barely enters its fourth differences.
        let nb = 300;
        let bands: Vec<Band> = (0..nb)
            .map(|k| Band::new(400.0 + k as f64, 0.0).unwrap())
            .collect();
        let mut c = Cube::zeros(1, 1, bands);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for k in 0..nb {
            let lam = 400.0 + k as f64;
            let r = 0.05 + 0.03 * (4.0 * std::f64::consts::PI * 1.4 * 800.0 / lam).cos();
            c.data[k] = (r + 2e-3 * (rng.random::<f64>() - 0.5) * 12f64.sqrt()) as f32;
        }
        let m = NoiseModel::from_data(&c).unwrap();
        let s = m.var(0, 0.05).sqrt();
        assert!((s / 2e-3 - 1.0).abs() < 0.25, "{s}");
    }

    /// A spectrometer's noise: 1e-3 at the ends of 400 bands, 1e-4 over the
    /// middle half. Per band, each end is read within a window's scatter
    /// (the median of 31 differences: ~±22 %, allowed ±35 %), the middle at
    /// the pooled value (its floor, here above the middle's own level);
    /// pooled, every band gets the same.
    #[test]
    fn a_spectrometers_noisy_ends_are_seen_per_band() {
        let nb = 400;
        let bands: Vec<Band> = (0..nb)
            .map(|k| Band::new(400.0 + k as f64, 0.0).unwrap())
            .collect();
        let truth = |k: usize| if (100..300).contains(&k) { 1e-4 } else { 1e-3 };
        let mut c = Cube::zeros(1, 1, bands);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let unit = Normal::new(0.0, 1.0).unwrap();
        for k in 0..nb {
            let lam = 400.0 + k as f64;
            let r = 0.1 + 0.05 * (4.0 * std::f64::consts::PI * 1.5 * 300.0 / lam).cos();
            c.data[k] = (r + truth(k) * unit.sample(&mut rng)) as f32;
        }
        let per_band = NoiseModel::from_data(&c).unwrap();
        let pooled = NoiseModel::from_data_with(&c, false).unwrap();
        for k in [0, 40, 360, 399] {
            let s = per_band.var(k, 0.0).sqrt();
            assert!((s / 1e-3 - 1.0).abs() < 0.35, "band {k}: {s}");
        }
        // The pooled median sits between the two levels (half the bands
        // each); the middle never goes below it.
        let p = pooled.var(0, 0.0).sqrt();
        assert!(p > 1e-4 && p < 4e-4, "{p}");
        for k in [170, 200, 230] {
            let s = per_band.var(k, 0.0).sqrt();
            assert!(s >= p && s < 1.2 * p, "band {k}: {s} against {p}");
            assert_eq!(pooled.var(k, 0.0), pooled.var(0, 0.0));
        }
    }

    /// The reflectance-scale accuracy adds (ε·R)² to every band's variance,
    /// the larger ε standing.
    #[test]
    fn the_scale_accuracy_adds_in_quadrature() {
        let m = NoiseModel::uniform(1e-3, 3, NoiseSource::Given)
            .with_accuracy(0.05)
            .with_accuracy(0.02);
        assert!((m.accuracy() - 0.05).abs() < 1e-15);
        assert!((m.var(1, 0.4) - (1e-6 + 0.02f64.powi(2))).abs() < 1e-15);
        assert!((m.var(1, -0.1) - 1e-6).abs() < 1e-18);
        assert!(!m.is_uniform());
    }

    #[test]
    fn noise_free_data_sit_on_the_floor_and_tiny_cubes_give_none() {
        let c = cube_with(50, 50, 8, |x, _, _| 0.04 + 1e-4 * x as f64, 0.0);
        let m = NoiseModel::from_data(&c).unwrap();
        assert!((m.var(0, 0.04).sqrt() - SIGMA_FLOOR).abs() < 1e-9);
        let tiny = cube_with(2, 2, 8, |_, _, _| 0.04, 1e-3);
        assert!(NoiseModel::from_data(&tiny).is_none());
    }

    /// The lane-wise χ² and mean variance against a plain loop over
    /// [`NoiseModel::var`] (lengths not a multiple of four, dropped bands).
    #[test]
    fn chi2_and_mean_variance_match_a_plain_sum() {
        for n in [1usize, 4, 7, 31] {
            let m = NoiseModel {
                var0: (0..n).map(|k| 1e-6 * (1.0 + k as f64)).collect(),
                shot: (0..n).map(|k| 1e-5 * (k % 3) as f64).collect(),
                rel2: if n == 7 { 4e-4 } else { 0.0 },
                source: NoiseSource::Given,
            };
            let y: Vec<f64> = (0..n).map(|k| 0.1 + 0.01 * (k as f64).sin()).collect();
            let r: Vec<f64> = (0..n).map(|k| 0.1 + 0.012 * (k as f64).cos()).collect();
            let w: Vec<f64> = (0..n).map(|k| if k % 5 == 2 { 0.0 } else { 1.0 }).collect();
            let (mut chi2, mut v, mut used) = (0.0, 0.0, 0.0);
            for k in 0..n {
                if w[k] != 0.0 {
                    chi2 += (y[k] - r[k]).powi(2) / m.var(k, r[k]);
                    v += m.var(k, r[k]);
                    used += 1.0;
                }
            }
            let (c, mv) = m.chi2_and_mean_var(&y, &w, &r);
            assert!((c - chi2).abs() <= 1e-12 * chi2, "{n}: {c} vs {chi2}");
            assert!((mv - v / used).abs() <= 1e-15, "{n}: {mv}");
        }
    }

    #[test]
    fn the_flat_form_gives_the_same_chi2_without_divisions() {
        for n in [1usize, 4, 7, 31] {
            let m = NoiseModel {
                var0: (0..n).map(|k| 1e-6 * (1.0 + k as f64)).collect(),
                shot: vec![0.0; n],
                rel2: 0.0,
                source: NoiseSource::Given,
            };
            let y: Vec<f64> = (0..n).map(|k| 0.1 + 0.01 * (k as f64).sin()).collect();
            let r: Vec<f64> = (0..n).map(|k| 0.1 + 0.012 * (k as f64).cos()).collect();
            let w: Vec<f64> = (0..n).map(|k| if k % 5 == 2 { 0.0 } else { 1.0 }).collect();
            let (c, v) = m.chi2_and_mean_var(&y, &w, &r);
            let (cf, vf) = m
                .flat()
                .expect("no shot term")
                .chi2_and_mean_var(&y, &w, &r);
            assert!((c - cf).abs() <= 1e-12 * c, "{n}: {c} vs {cf}");
            assert!((v - vf).abs() <= 1e-15, "{n}: {v} vs {vf}");
        }
        // A shot term or a scale accuracy makes the variance depend on R.
        let shot = NoiseModel {
            var0: vec![1e-6; 3],
            shot: vec![0.0, 1e-5, 0.0],
            rel2: 0.0,
            source: NoiseSource::Camera,
        };
        assert!(shot.flat().is_none());
        // One variance for every band, or not.
        let u = NoiseModel::uniform(2e-3, 5, NoiseSource::Given)
            .flat()
            .unwrap();
        let v = 2e-3 * 2e-3;
        assert_eq!(u.uniform(), Some((v, 1.0 / v)));
        let per = NoiseModel::per_band(&[1e-3, 2e-3], NoiseSource::Data)
            .flat()
            .unwrap();
        assert_eq!(per.uniform(), None);
        assert!(NoiseModel::uniform(1e-3, 3, NoiseSource::Given)
            .with_accuracy(0.05)
            .flat()
            .is_none());
    }

    #[test]
    fn shot_noise_grows_with_reflectance() {
        let m = NoiseModel {
            var0: vec![1e-6],
            shot: vec![1e-5],
            rel2: 0.0,
            source: NoiseSource::Camera,
        };
        assert!((m.var(0, 0.0) - 1e-6).abs() < 1e-18);
        assert!((m.var(0, 0.5) - 6e-6).abs() < 1e-18);
        assert!((m.var(0, -0.1) - 1e-6).abs() < 1e-18);
    }
}
