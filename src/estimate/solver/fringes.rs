//! Fringe positions: a thickness read from where a spectrum's extrema fall,
//! not from its level — the free level's answer when its model of the
//! level (a smooth scale and offset) does not fit a measured spectrum, as
//! a spectrometer's normalised intensity often does not (a lamp divided
//! out imperfectly, fringe contrast washed out towards the blue by the
//! spot's thickness spread).
//!
//! With `x_k = Re(n2 cos θ2)/λ_k` the film's phase is `4π d x_k`, and the
//! reflectance's extrema fall at `4 d x = m` for whole orders `m`: half-wave
//! orders (even `m`) at the bare substrate's reflectance, quarter-wave
//! orders (odd `m`) at the other envelope. A smooth scale and offset move
//! the extrema only slightly, so:
//!
//! 1. **Fringe period**: a periodogram over thickness of
//!    `y ≈ p₂(u) + (a₀ + a₁u) cos 4πdx + (b₀ + b₁u) sin 4πdx` (free phase,
//!    slow envelope, weighted by the noise) gives the period `1/(4d₀)`.
//! 2. **Extrema**: the spectrum, smoothed by a local quadratic over a quarter
//!    of a half-period, is cut into alternating maxima and minima; pairs
//!    less prominent than four noise σ of the smoothed curve are merged
//!    away, and the longest run spaced like the period is kept.
//! 3. **Orders**: whole orders of the right parity (a maximum is odd when
//!    the quarter-wave reflectance is the higher) fitted through the
//!    extrema, `d = Σ m x / (4 Σ x²)`; where the orders do not line up
//!    within a tenth of a fringe (a chirp the model lacks), or another set
//!    lines up about as well, the spacing alone: the slope of `x` against
//!    the extremum count (five extrema or more; with fewer, ambiguous
//!    orders are flagged).
//!
//! σ comes from the scatter of the extrema about the fit, and never falls
//! below a twentieth of a fringe over the mean order: a shift common to
//! all extrema (the envelope's pull, an error in the index table) does not
//! average down, so no claim of more precision than the positions carry.

#![allow(clippy::needless_range_loop)] // band-indexed numeric loops read clearer with indices

use crate::estimate::level::solve_spd;
use crate::estimate::quality::chi2_upper_quantile;

/// Smallest position error credited to one extremum, in fringe orders.
const MIN_ORDER_ERROR: f64 = 0.05;
/// Largest rms misfit of whole orders before the spacing alone is used.
const ORDER_FIT_RMS: f64 = 0.1;
/// Prominence of a kept extremum over its neighbours, in σ of the smoothed
/// spectrum.
const PROMINENCE_SIGMA: f64 = 4.0;
/// χ² margin of the best fringe order over the next below which they are
/// ambiguous (three σ; a ~1 % posterior for the second order), on every
/// path: the fringe search, the fitted and tabled paths, `free`.
pub(super) const AMBIGUITY_CHI2: f64 = 9.0;
/// Fewest extrema whose spacing alone gives a thickness.
const MIN_SPACING_EXTREMA: usize = 5;
/// False-alarm probability of a fringe detected in pure noise, over all
/// frequencies tried.
const DETECTION_PROBABILITY: f64 = 1e-3;
/// Periodogram grid points per peak width.
const GRID_PER_PEAK: f64 = 8.0;
/// Most ambiguous order sets reported.
pub(super) const MAX_CANDIDATES: usize = 4;

/// What the fringe positions say.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct FringeFit {
    /// Thickness, nm.
    pub d: f64,
    /// Its standard error, nm.
    pub sigma: f64,
    /// Extrema used.
    pub n_extrema: usize,
    /// Rms distance of the extrema from their fitted orders, in orders.
    pub order_rms: f64,
    /// Another set of whole orders lines up about as well.
    pub ambiguous: bool,
    /// Where ambiguous, the order sets within [`AMBIGUITY_CHI2`] of the
    /// best, best first: `(d, σ)` each (the rest `NaN`), for the level
    /// model's shape to choose between.
    pub candidates: [(f64, f64); MAX_CANDIDATES],
    /// Thickness from the periodogram alone, nm.
    pub period_d: f64,
}

/// The fringe analysis of one spectrum: `x` the phase rates, `y` the
/// values, `var` their noise variances (all sorted by descending `x`,
/// i.e. ascending wavelength); `max_is_odd` whether maxima are quarter-wave
/// orders. `None` when no fringe extremum stands out (one alone leaves
/// its order open: see [`single`]).
pub(super) fn fit(
    x: &[f64],
    y: &[f64],
    var: &[f64],
    max_is_odd: bool,
    d_range: (f64, f64),
) -> Option<FringeFit> {
    let n = x.len();
    if n < 8 || y.len() != n || var.len() != n {
        return None;
    }
    let period_d = period(x, y, var, d_range)?;
    let mut run = run_at(x, y, var, period_d);
    // A period the extrema contradict (the periodogram is weak below two
    // fringes): once more at the extrema's own spacing.
    if run.ext.len() >= 2 {
        let (first, last) = (run.ext[0].0, run.ext[run.ext.len() - 1].0);
        let gap = (x[first] - x[last]).abs() / (run.ext.len() - 1) as f64;
        let d1 = 1.0 / (4.0 * gap);
        if (d1 / period_d - 1.0).abs() > 0.2 {
            let again = run_at(x, y, var, d1);
            if again.ext.len() >= run.ext.len() {
                run = again;
            }
        }
    }
    if run.ext.len() == 1 {
        let f = single(
            x[run.ext[0].0],
            run.ext[0].1 == max_is_odd,
            d_range,
            period_d,
        );
        return f.d.is_finite().then_some(f);
    }
    if run.ext.len() < 2 {
        return None;
    }
    let xs: Vec<f64> = run.ext.iter().map(|e| x[e.0]).collect();
    let last_is_max = run.ext[run.ext.len() - 1].1;
    orders(&xs, &run.sigma_x, last_is_max == max_is_odd, d_range)
        .map(|f| FringeFit { period_d, ..f })
}

/// One extremum alone (at `x`, of odd order iff `odd`) fixes the
/// thickness only up to its order: the lowest orders in range, all open
/// ([`FringeFit::ambiguous`]), for the spectrum's shape to choose between.
/// Each with a twentieth of an order's position error.
fn single(x: f64, odd: bool, (d_min, d_max): (f64, f64), period_d: f64) -> FringeFit {
    let mut candidates = [(f64::NAN, f64::NAN); MAX_CANDIDATES];
    let orders = (0..).map(|j| 2 * j + if odd { 1 } else { 2 });
    let in_range = orders
        .map(|m| (m as f64, m as f64 / (4.0 * x)))
        .skip_while(|&(_, d)| d < d_min)
        .take_while(|&(_, d)| d <= d_max);
    for (slot, (m, d)) in candidates.iter_mut().zip(in_range) {
        *slot = (d, d * MIN_ORDER_ERROR / m);
    }
    FringeFit {
        d: candidates[0].0,
        sigma: candidates[0].1,
        n_extrema: 1,
        order_rms: 0.0,
        ambiguous: true,
        candidates,
        period_d,
    }
}

/// Noise variance of each sample of a densely sampled spectrum, from the
/// second differences around it (smooth signal cancels; a fringe sampled
/// coarsely does not, so this serves only where no noise model is known).
pub(super) fn local_variance(y: &[f64]) -> Vec<f64> {
    const HALF: usize = 15;
    let n = y.len();
    if n < 3 {
        return vec![1e-300; n];
    }
    let d2: Vec<f64> = (0..n)
        .map(|i| {
            let a = i.saturating_sub(1).min(n - 3);
            let v = y[a] - 2.0 * y[a + 1] + y[a + 2];
            v * v / 6.0
        })
        .collect();
    (0..n)
        .map(|i| {
            let (a, b) = (i.saturating_sub(HALF), (i + HALF + 1).min(n));
            (d2[a..b].iter().sum::<f64>() / (b - a) as f64).max(1e-300)
        })
        .collect()
}

/// A run of fringe extrema: (index, is-maximum) and each one's position
/// σ in `x`.
struct Run {
    ext: Vec<(usize, bool)>,
    sigma_x: Vec<f64>,
}

/// The extrema run of a spectrum smoothed for fringes of thickness `d0`.
fn run_at(x: &[f64], y: &[f64], var: &[f64], d0: f64) -> Run {
    let n = x.len();
    // Smoothing half-width: a quarter of a half-period, in samples.
    let dx = (x[0] - x[n - 1]).abs() / (n - 1) as f64;
    let half = 1.0 / (4.0 * d0) / dx.max(1e-300);
    let h = ((half / 4.0) as usize).clamp(2, (n / 8).max(2));
    let (ys, var_s, var_eff) = smooth(y, var, h);
    let ext = extrema(&ys, &var_s, h);
    let ext = spaced_run(x, &ext, d0);
    let sigma_x = ext
        .iter()
        .map(|&(i, _)| {
            let slope = (x[(i + 1).min(n - 1)] - x[i.saturating_sub(1)]).abs()
                / ((i + 1).min(n - 1) - i.saturating_sub(1)) as f64;
            vertex_sigma(y, var_eff[i], i, 2 * h) * slope
        })
        .collect();
    Run { ext, sigma_x }
}

/// Weighted least-squares residual `Σ w (y − f·c)²` of `y` on the basis
/// `f(k)` (the normal equations, lightly regularised); ∞ where singular.
/// At most 8 basis functions (the normal equations stay on the stack).
pub(super) fn weighted_sse<const P: usize>(
    y: &[f64],
    w: &[f64],
    f: impl Fn(usize) -> [f64; P],
) -> f64 {
    weighted_lsq(y, w, f).map_or(f64::INFINITY, |(sse, _)| sse)
}

/// The weighted least-squares fit behind [`weighted_sse`]: the residual
/// and the coefficients.
pub(super) fn weighted_lsq<const P: usize>(
    y: &[f64],
    w: &[f64],
    f: impl Fn(usize) -> [f64; P],
) -> Option<(f64, [f64; P])> {
    let mut buf = [0.0; 64];
    let ata = &mut buf[..P * P];
    let mut aty = [0.0; P];
    let mut yy = 0.0;
    for k in 0..y.len() {
        let fk = f(k);
        yy += w[k] * y[k] * y[k];
        for i in 0..P {
            aty[i] += w[k] * fk[i] * y[k];
            for j in 0..P {
                ata[i * P + j] += w[k] * fk[i] * fk[j];
            }
        }
    }
    for i in 0..P {
        ata[i * P + i] *= 1.0 + 1e-10;
    }
    let c = solve_spd(ata, P, &aty)?;
    let mut out = [0.0; P];
    out.copy_from_slice(&c[..P]);
    let sse = yy - out.iter().zip(&aty).map(|(c, b)| c * b).sum::<f64>();
    Some((sse, out))
}

/// Normal equations of the quadratic `a + b t + c t²` in `t = k − i` over
/// samples `k ∈ [lo, hi)` of `y`: `(AᵀA, Aᵀy)`.
fn local_quadratic(y: &[f64], i: usize, lo: usize, hi: usize) -> ([f64; 9], [f64; 3]) {
    let mut m = [0.0f64; 5];
    let mut r = [0.0f64; 3];
    for (k, &v) in y.iter().enumerate().take(hi).skip(lo) {
        let t = k as f64 - i as f64;
        let mut p = 1.0;
        for mj in m.iter_mut() {
            *mj += p;
            p *= t;
        }
        r[0] += v;
        r[1] += t * v;
        r[2] += t * t * v;
    }
    ([m[0], m[1], m[2], m[1], m[2], m[3], m[2], m[3], m[4]], r)
}

/// σ, in samples, of the vertex of the quadratic fitted to `y` over
/// `i ± w` (noise variance `var`): `σ_b / (2|c|)` for `y ≈ a + b t + c t²`
/// with `t = k − i` (the vertex sits near `t = 0`). Infinite where the
/// curve has no curvature to place a vertex by.
fn vertex_sigma(y: &[f64], var: f64, i: usize, w: usize) -> f64 {
    let n = y.len();
    let (ata, r) = local_quadratic(y, i, i.saturating_sub(w), (i + w + 1).min(n));
    let (Some(coef), Some(e1)) = (solve_spd(&ata, 3, &r), solve_spd(&ata, 3, &[0.0, 1.0, 0.0]))
    else {
        return f64::INFINITY;
    };
    let c = coef[2];
    if c == 0.0 {
        return f64::INFINITY;
    }
    (var * e1[1]).max(0.0).sqrt() / (2.0 * c.abs())
}

/// Thickness at the periodogram's peak (free phase, slow envelope).
fn period(x: &[f64], y: &[f64], var: &[f64], (d_min, d_max): (f64, f64)) -> Option<f64> {
    let n = x.len();
    let (x_hi, x_lo) = (x[0], x[n - 1]);
    let span = x_hi - x_lo;
    if span.is_nan() || span <= 0.0 {
        return None;
    }
    let u: Vec<f64> = x.iter().map(|v| 2.0 * (v - x_lo) / span - 1.0).collect();
    let w: Vec<f64> = var.iter().map(|v| 1.0 / v.max(1e-300)).collect();
    let sse = |d: f64| -> f64 {
        weighted_sse::<7>(y, &w, |k| {
            let (s, c) = (4.0 * std::f64::consts::PI * d * x[k]).sin_cos();
            [1.0, u[k], u[k] * u[k], c, c * u[k], s, s * u[k]]
        })
    };
    // A peak is ~1/(2·span) wide in d; start at half a fringe over the band.
    let step = 1.0 / (2.0 * span * GRID_PER_PEAK);
    let lo = d_min.max(1.0 / (4.0 * span));
    let hi = d_max;
    if hi.is_nan() || hi <= lo {
        return None;
    }
    let n_grid = (((hi - lo) / step).ceil() as usize + 1).min(20_000);
    let mut best = (f64::INFINITY, lo);
    for i in 0..n_grid {
        let d = (lo + step * i as f64).min(hi);
        let v = sse(d);
        if v < best.0 {
            best = (v, d);
        }
    }
    if !best.0.is_finite() {
        return None;
    }
    // A fringe at all? The sinusoid's four parameters must lower χ² by
    // more than noise would at any of the independent frequencies tried
    // (the look-elsewhere effect: p = 1e-3 over all of them).
    let baseline = weighted_sse::<3>(y, &w, |k| [1.0, u[k], u[k] * u[k]]);
    let n_freq = ((hi - lo) * 2.0 * span).max(1.0);
    if baseline - best.0 < chi2_upper_quantile(4.0, DETECTION_PROBABILITY / n_freq) {
        return None;
    }
    let (a, b) = ((best.1 - step).max(lo), (best.1 + step).min(hi));
    Some(super::free::golden(a, b, sse).0)
}

/// Local quadratic smoothing with half-width `h` (samples): the smoothed
/// values, their variances, and the noise variance of each sample.
fn smooth(y: &[f64], var: &[f64], h: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let n = y.len();
    let mut ys = vec![0.0; n];
    let mut vs = vec![0.0; n];
    for i in 0..n {
        let (a, b) = (i.saturating_sub(h), (i + h + 1).min(n));
        let (ata, r) = local_quadratic(y, i, a, b);
        let mean_var = var[a..b].iter().sum::<f64>() / (b - a) as f64;
        // Value at t = 0 and the weight vector's squared norm: the first row
        // of (AᵀA)⁻¹ gives both.
        let e0 = solve_spd(&ata, 3, &[1.0, 0.0, 0.0]);
        match e0 {
            Some(g) => {
                ys[i] = g[0] * r[0] + g[1] * r[1] + g[2] * r[2];
                // Var of Σ w_k y_k with w_k = g·(1, t, t²): wᵀw = g[0].
                vs[i] = mean_var * g[0].max(0.0);
            }
            None => {
                ys[i] = y[i];
                vs[i] = var[i];
            }
        }
    }
    // The noise the extrema must stand out of: the given variance, or the
    // scatter about the smoothed curve where that is larger (noise that
    // grows towards a weak lamp's end, which a single noise level
    // misses). The local quadratic follows the fringes, so the scatter is
    // noise; a sample's residual variance is σ²·(1 − g₀).
    let half_w = h.max(15);
    let resid: Vec<f64> = (0..n).map(|i| (y[i] - ys[i]).powi(2)).collect();
    let mut var_eff = vec![0.0; n];
    for i in 0..n {
        let (a, b) = (i.saturating_sub(half_w), (i + half_w + 1).min(n));
        let mean_r = resid[a..b].iter().sum::<f64>() / (b - a) as f64;
        let mean_v = var[a..b].iter().sum::<f64>() / (b - a) as f64;
        let g0 = if mean_v > 0.0 { vs[i] / mean_v } else { 0.0 };
        let local = mean_r / (1.0 - g0).max(0.5);
        var_eff[i] = mean_v.max(local);
        vs[i] = var_eff[i] * g0;
    }
    (ys, vs, var_eff)
}

/// Alternating extrema of `ys` (index, is-maximum), each standing out
/// from its neighbours by [`PROMINENCE_SIGMA`] noise σ, none within `h/2`
/// samples of an end (where the smoothing is one-sided).
fn extrema(ys: &[f64], var: &[f64], h: usize) -> Vec<(usize, bool)> {
    let n = ys.len();
    let mut ext: Vec<(usize, bool)> = Vec::new();
    for i in 1..n - 1 {
        let (a, b) = (ys[i] - ys[i - 1], ys[i + 1] - ys[i]);
        let kind = if a > 0.0 && b <= 0.0 {
            Some(true)
        } else if a < 0.0 && b >= 0.0 {
            Some(false)
        } else {
            None
        };
        if let Some(k) = kind {
            match ext.last_mut() {
                // Same kind again (a flat step): keep the more extreme.
                Some(last) if last.1 == k => {
                    if (k && ys[i] > ys[last.0]) || (!k && ys[i] < ys[last.0]) {
                        last.0 = i;
                    }
                }
                _ => ext.push((i, k)),
            }
        }
    }
    let thr = |i: usize, j: usize| PROMINENCE_SIGMA * (var[i] + var[j]).sqrt();
    // Merge away the least prominent adjacent pair until all stand out.
    loop {
        let worst = (0..ext.len().saturating_sub(1))
            .map(|j| {
                let (a, b) = (ext[j].0, ext[j + 1].0);
                (j, (ys[a] - ys[b]).abs() / thr(a, b))
            })
            .min_by(|p, q| p.1.total_cmp(&q.1));
        match worst {
            Some((j, r)) if r < 1.0 => {
                if j == 0 {
                    ext.remove(0);
                } else if j + 2 == ext.len() {
                    ext.pop();
                } else {
                    ext.drain(j..j + 2);
                }
            }
            _ => break,
        }
    }
    // An end extremum must stand out from the spectrum beyond it too, and
    // sit at least half a smoothing window in.
    let margin = (h / 2).max(2);
    let stands_out = |&(i, is_max): &(usize, bool), range: std::ops::Range<usize>| {
        let beyond = range.map(|k| ys[k]);
        let far = if is_max {
            beyond.fold(f64::INFINITY, f64::min)
        } else {
            beyond.fold(f64::NEG_INFINITY, f64::max)
        };
        (ys[i] - far).abs() >= thr(i, i) / std::f64::consts::SQRT_2
    };
    while let Some(&first) = ext.first() {
        if first.0 >= margin && stands_out(&first, 0..first.0) {
            break;
        }
        ext.remove(0);
    }
    while let Some(&last) = ext.last() {
        if last.0 + margin < n && stands_out(&last, last.0 + 1..n) {
            break;
        }
        ext.pop();
    }
    ext
}

/// The longest run of consecutive extrema spaced like the fringe period
/// (within half to twice `1/(4 d₀)` in `x`).
fn spaced_run(x: &[f64], ext: &[(usize, bool)], d0: f64) -> Vec<(usize, bool)> {
    let q = 1.0 / (4.0 * d0);
    let mut best = (0, 0);
    let mut start = 0;
    for j in 1..=ext.len() {
        let breaks = j == ext.len() || {
            let gap = (x[ext[j].0] - x[ext[j - 1].0]).abs();
            !(0.5 * q..=2.0 * q).contains(&gap)
        };
        if breaks {
            if j - start > best.1 - best.0 {
                best = (start, j);
            }
            start = j;
        }
    }
    ext[best.0..best.1].to_vec()
}

/// Whole orders through the extrema at `xs` (descending, position σ
/// `sigma_x`), the last of odd order iff `last_odd`; the spacing alone
/// where they do not line up.
fn orders(
    xs: &[f64],
    sigma_x: &[f64],
    last_odd: bool,
    (d_min, d_max): (f64, f64),
) -> Option<FringeFit> {
    let n = xs.len();
    let sxx: f64 = xs.iter().map(|x| x * x).sum();
    let m_cap = (4.0 * d_max * xs[n - 1]).ceil() as i64 + 2;
    // Per candidate: (χ² against the positions' σ, rms misfit, d, mean
    // order, relative σ of d), all kept for the ambiguous case.
    let mut all: Vec<(f64, f64, f64, f64, f64)> = Vec::new();
    let mut m_last = if last_odd { 1 } else { 2 };
    while m_last <= m_cap.max(1) {
        let ms = |j: usize| (m_last + (n - 1 - j) as i64) as f64;
        let d = (0..n).map(|j| ms(j) * xs[j]).sum::<f64>() / (4.0 * sxx);
        // Each extremum's position error in orders, never below the floor.
        let sm = |j: usize| (4.0 * d * sigma_x[j]).max(MIN_ORDER_ERROR);
        let chi2: f64 = (0..n)
            .map(|j| ((4.0 * d * xs[j] - ms(j)) / sm(j)).powi(2))
            .sum();
        let rms = ((0..n)
            .map(|j| (4.0 * d * xs[j] - ms(j)).powi(2))
            .sum::<f64>()
            / n as f64)
            .sqrt();
        let mean_m = (0..n).map(ms).sum::<f64>() / n as f64;
        // δd/d from the positions: 1/√Σ(m/σ_m)².
        let rel = 1.0 / (0..n).map(|j| (ms(j) / sm(j)).powi(2)).sum::<f64>().sqrt();
        if (d_min..=d_max).contains(&d) {
            all.push((chi2, rms, d, mean_m, rel));
        }
        m_last += 2;
    }
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    let &(chi2, rms, d_int, mean_m, rel) = all.first()?;
    let second = all.get(1).map_or(f64::INFINITY, |c| c.0);
    // Relative σ of an order set's thickness: random position errors
    // average down over the extrema; a shift common to them all (the
    // envelope's pull, the index table's error) does not, so never below
    // MIN_ORDER_ERROR of the mean order.
    let floor = |rel: f64, rms: f64, mean_m: f64| {
        rel.max(rms / (mean_m * (n as f64).sqrt()))
            .max(MIN_ORDER_ERROR / mean_m)
    };
    // The open order sets: those within AMBIGUITY_CHI2, and always the
    // best's two neighbours (a displaced extremum — washed-out contrast,
    // noise — can move the truth just past the margin).
    let near =
        |c: &(f64, f64, f64, f64, f64)| c.0 - chi2 < AMBIGUITY_CHI2 || (c.3 - mean_m).abs() < 2.5;
    let mut candidates = [(f64::NAN, f64::NAN); MAX_CANDIDATES];
    for (slot, c) in candidates.iter_mut().zip(all.iter().filter(|c| near(c))) {
        *slot = (c.2, c.2 * floor(c.4, c.1, c.3));
    }
    if !d_int.is_finite() || d_int <= 0.0 {
        return None;
    }
    // Another set of orders within AMBIGUITY_CHI2 of the best is as
    // plausible, given how well the extrema are placed.
    let ambiguous = second - chi2 < AMBIGUITY_CHI2;
    // Whole orders where they line up unambiguously, and wherever there
    // are too few extrema for their spacing to tell more (the spacing of
    // three or four extrema is a difference of positions the envelope
    // pulls: the orders' ambiguity is then the answer, a flag).
    if n < MIN_SPACING_EXTREMA || (!ambiguous && rms <= ORDER_FIT_RMS) {
        return Some(FringeFit {
            d: d_int,
            sigma: d_int * floor(rel, rms, mean_m),
            n_extrema: n,
            order_rms: rms,
            ambiguous,
            candidates,
            period_d: f64::NAN,
        });
    }
    // The spacing: x_j = a + b·j.
    let nf = n as f64;
    let jm = (nf - 1.0) / 2.0;
    let xm = xs.iter().sum::<f64>() / nf;
    let sjj: f64 = (0..n).map(|j| (j as f64 - jm).powi(2)).sum();
    let b = (0..n).map(|j| (j as f64 - jm) * (xs[j] - xm)).sum::<f64>() / sjj;
    if b.is_nan() || b >= 0.0 {
        return None;
    }
    let d = -1.0 / (4.0 * b);
    let res: f64 = (0..n)
        .map(|j| (xs[j] - xm - b * (j as f64 - jm)).powi(2))
        .sum();
    // Position scatter, in orders; the relative σ floored as for whole
    // orders.
    let scatter = ((res / (nf - 2.0)).sqrt() * 4.0 * d).max(MIN_ORDER_ERROR);
    let mean_m = 4.0 * d * xm;
    let rel = (scatter / sjj.sqrt()).max(MIN_ORDER_ERROR / mean_m);
    Some(FringeFit {
        d,
        sigma: d * rel,
        n_extrema: n,
        order_rms: scatter,
        ambiguous: false,
        candidates: [(f64::NAN, f64::NAN); MAX_CANDIDATES],
        period_d: f64::NAN,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A free-standing film's normalised intensity, written out by hand
    /// (not with irid's model): `I = a(λ) + s(λ)·F sin²δ/(1 + F sin²δ)`.
    fn spectrum(d: f64, n: f64, noise: f64) -> (Vec<f64>, Vec<f64>) {
        let r = (1.0 - n) / (1.0 + n);
        let f = 4.0 * r * r / (1.0 - r * r).powi(2);
        let mut state = 12345u64;
        let mut x = Vec::new();
        let mut y = Vec::new();
        for i in 0..400 {
            let lam = 400.0 + i as f64;
            let s = (2.0 * std::f64::consts::PI * n * d / lam).sin().powi(2);
            let env = 6.0 + 3.0 * (lam - 400.0) / 400.0;
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let e = ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * noise * 12f64.sqrt();
            x.push(n / lam);
            y.push(0.1 + 0.05 * (lam - 400.0) / 400.0 + env * f * s / (1.0 + f * s) + e);
        }
        (x, y)
    }

    #[test]
    fn orders_and_spacing_recover_the_thickness() {
        for &d in &[260.0, 480.0, 900.0, 1500.0, 2600.0] {
            let (x, y) = spectrum(d, 1.33, 0.003);
            let var = vec![0.003f64.powi(2); x.len()];
            let f = fit(&x, &y, &var, true, (20.0, 6000.0)).expect("fringes found");
            let err = (f.d - d).abs();
            assert!(err <= 0.02 * d, "d {d}: {f:?}");
            // σ neither smaller than the error it should cover nor useless.
            assert!(err <= 3.0 * f.sigma && f.sigma <= 0.03 * d, "d {d}: {f:?}");
            assert!(!f.ambiguous, "d {d}: {f:?}");
        }
    }

    #[test]
    fn a_flat_spectrum_has_no_fringes() {
        let x: Vec<f64> = (0..400).map(|i| 1.33 / (400.0 + i as f64)).collect();
        let y: Vec<f64> = (0..400).map(|i| 0.3 + 1e-4 * i as f64).collect();
        let var = vec![1e-6; 400];
        assert!(fit(&x, &y, &var, true, (20.0, 6000.0)).is_none());
    }
}
