//! Where one unknown remains (film index and angle known), the model over
//! thickness is a fixed curve: tabulate it once per angle and fit every
//! pixel against the table instead of searching fringes.
//!
//! The table holds `R` and `dR/dd` per band on a thickness grid fine enough
//! that the fastest band's phase moves [`PHASE_STEP`] between points. A
//! pixel's fit is then
//! 1. the residual at every grid point (one vectorised pass, f32), whose
//!    lowest local minima are the candidate fringe orders, and
//! 2. Gauss–Newton in `d` on the cubic Hermite interpolant of the table
//!    (f64, no transcendental functions), whose error at this step is
//!    ~h⁴R''''/384 ≈ 1e-5 of the fringe amplitude — far below any noise.
//!
//! The fit is then judged with the exact model (stage 4, unchanged), so an
//! interpolation error could cost a pixel its validity but never make a
//! wrong one valid.
//!
//! [`kernels`] holds the vector loops, [`poly`] one interval's residual
//! polynomial and its minimum, [`solve`] a pixel's solve against a table.

use crate::estimate::model::{FilmModel, ModelOut};
use crate::estimate::noise::{FlatNoise, NoiseModel};
use std::cell::Cell;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;

mod bins;
mod kernels;
mod poly;
mod solve;

pub use bins::{AngleBins, BinRange};

use kernels::{
    interp_chi2, interp_model_chi2, interp_values, interval_dots, minimum_keys, scan_blocked,
    scan_weighted,
};
use poly::{poly_min, residual_poly};

/// Largest phase change of any band between adjacent grid points, rad.
pub const PHASE_STEP: f64 = 0.3;

/// The largest interpolation error a table may have against the model
/// (reflectance): a tenth of the lowest noise level irid accepts (1e-4),
/// so it adds at most 0.01 to a band's χ² on noise-free data and 1e-4 of
/// the variance at the paper's noise. (A fiftieth halved the step on thick
/// films and dispersive p scenes for no measurable gain, at ~40 % of their
/// speed.)
pub const INTERP_TOL: f64 = 1e-5;

/// The residual is scanned on every `SCAN_STRIDE`-th grid point (a phase
/// step of at most 0.9 rad: a minimum's basin spans ±π), then the best
/// coarse minima walk downhill on the full grid.
const SCAN_STRIDE: usize = 3;

/// Where a row's next walk on a table starts: the thickness the previous
/// two valid pixels at that table (angle bits `key`) fitted, extrapolated
/// along the row. A film's thickness map is smooth, so a ramp's next
/// pixel lies near `2·d − before`; started from `d` alone, the walk paid
/// a second interval on 20–45 % of the pixels of the matrix's scenes.
#[derive(Clone, Copy, Debug)]
pub(in crate::estimate::solver) struct Hint {
    pub key: u64,
    /// The previous pixel's fit.
    pub d: f64,
    /// The fit before it (NaN where there was none).
    pub before: f64,
}

impl Hint {
    /// A row's first fit at table `key` is yet to come.
    pub fn start(key: u64) -> Hint {
        Hint {
            key,
            d: f64::NAN,
            before: f64::NAN,
        }
    }

    /// After a pixel fitted at `d`.
    pub fn then(self, d: f64) -> Hint {
        Hint {
            key: self.key,
            d,
            before: self.d,
        }
    }

    /// The next pixel's likely thickness: the line through the last two
    /// fits where they lie within [`RAMP_STEPS`] grid steps `h` of each
    /// other (a larger jump is an edge or an order change, not a slope to
    /// follow), else the last fit.
    pub fn predicted(&self, h: f64) -> f64 {
        super::on_ramp(self.d, self.before, f64::NEG_INFINITY, RAMP_STEPS * h)
    }
}

/// Grid steps from one pixel to the next that a walk on a table follows
/// as the row's ramp ([`Hint::predicted`], a run past the range).
pub(in crate::estimate::solver) const RAMP_STEPS: f64 = 4.0;

/// Grid intervals `fast` may walk from the previous pixel's fringe order
/// (±1.8 rad of the fastest band's phase) before it scans instead.
const HINT_WINDOW: usize = 6;

/// Bytes a table holds per grid point for `nb` bands (values and slopes,
/// the scan's transposed third, the sums, the order gap and the interval
/// cross sums).
fn bytes_per_point(nb: usize) -> usize {
    nb * 8 + nb.div_ceil(8) * 32 / SCAN_STRIDE + 8 + 4 + 48
}

/// The least separation of the neighbouring fringe orders, in the largest
/// noise variance, above which `fast` and `balanced` do not weigh them on
/// a table ([`ThicknessTable::order_gap`]). A noise-free gap `G` (in
/// variances) leaves a noisy spectrum's neighbouring order `G − 2√G·z`
/// behind its fit (`z` the noise's standard normal component along the
/// two orders' difference); at 250, even `z = 5` leaves 92 variances, ten
/// times the ambiguity margin (9) at the largest residual variance the χ²
/// test passes (1.8 noise variances at 31 bands).
pub(super) const ORDER_GAP_SAFE: f64 = 250.0;

/// Memory all of a solver's tables may take, bytes.
pub const TABLE_BUDGET_BYTES: usize = 256 << 20;

/// The model at one angle over a thickness grid.
#[derive(Debug)]
pub struct ThicknessTable {
    d0: f64,
    h: f64,
    /// `1 / h`: a pixel's position on the grid is a product, not a
    /// division its χ² and order checks wait on.
    inv_h: f64,
    m: usize,
    /// Grid points the scan covers (`≤ m`): the thicknesses a fit may
    /// report. The grid beyond reaches past the resolved range for the
    /// walks alone, so a film past it is fitted there and flagged
    /// "fringes unresolved" (see [`ThicknessTable::new_reaching`]).
    m_scan: usize,
    nb: usize,
    /// `nb` rounded up to whole vectors of 8 (the padding is zero).
    nbp: usize,
    /// `r[j * nbp + k]`: R of band k at `d0 + j h`, less `centre[k]`.
    r: Vec<f32>,
    /// Each band's mean R over the grid: stored and scanned values are
    /// deviations from it, so f32 resolves residuals far below `nb σ²`
    /// even where R itself is large (near grazing incidence R ≈ 0.6 and
    /// the fringes are 1e-3 deep).
    centre: Vec<f64>,
    /// `Σ_k R²` at each grid point, for the complete-spectrum residual.
    rr: Vec<f32>,
    /// `dr[j * nb + k]`: dR/dd, per nm.
    dr: Vec<f32>,
    /// The scanned rows (every [`SCAN_STRIDE`]-th) transposed in blocks
    /// of eight: `coarse[(b·nb + k)·8 + l]` is `r` of band `k` at grid
    /// point `(8b + l)·SCAN_STRIDE` (zero past the grid), so the scan
    /// computes eight grid points per vector with no horizontal sums.
    coarse: Vec<f32>,
    /// `Σ_k R²` at each scanned point, `+∞` past the grid (padded to
    /// whole blocks).
    coarse_rr: Vec<f32>,
    /// Per grid interval, the cross sums of its Hermite cubic's
    /// coefficients over the bands (see [`IntervalCubic`]): with them a
    /// complete spectrum's residual on the interval is a polynomial whose
    /// only pixel-dependent coefficients are four dot products.
    gram: Vec<[f64; 6]>,
    /// Per grid point `j`, the least `Σ_k (R_k(d') − R_k(d_j))²` over the
    /// neighbouring fringe orders (`|d' − d_j|` from half to one and a
    /// half fringes at the band range's centre): what a noise-free
    /// spectrum of thickness `d_j` separates its neighbouring orders by
    /// ([`ThicknessTable::order_gap`]). Taken where first asked for (the
    /// f32's bits; NaN until then): O(fringe · nb) a point, which over a
    /// whole fine table (a spectrometer's 600 bands to 100 µm) would cost
    /// seconds that a few spectra never use.
    gap: Vec<AtomicU32>,
    /// One fringe at the band range's centre, grid steps.
    fringe: f64,
    /// The largest reflectance of any band on the scanned grid.
    r_max: f64,
}

/// One band's cubic Hermite interpolant on a grid interval, in the
/// interval's own coordinate `t ∈ [0, 1]`:
/// `R(t) = A + c1·t + c2·t² + c3·t³` with `c1 = P·h`,
/// `c2 = 3(B − A) − (2P + Q)·h`, `c3 = 2(A − B) + (P + Q)·h`
/// (`A`, `B` the values and `P`, `Q` the slopes per nm at the ends).
/// The same interpolant as [`ThicknessTable::interp`], expanded in powers.
struct IntervalCubic;

impl IntervalCubic {
    #[inline(always)]
    fn coefficients(a: f64, b: f64, p: f64, q: f64, h: f64) -> (f64, f64, f64) {
        let (p, q) = (p * h, q * h);
        (p, 3.0 * (b - a) - 2.0 * p - q, 2.0 * (a - b) + p + q)
    }
}

/// Working memory of the grid scan (per thread).
#[derive(Clone, Debug, Default)]
pub struct GridScratch {
    y: Vec<f32>,
    yy: f32,
    complete: bool,
    w: Vec<f32>,
    sse: Vec<f32>,
    keys: Vec<f32>,
    r: Vec<f64>,
    dr: Vec<f64>,
}

/// The most minima [`ThicknessTable::minima`] returns.
pub const MAX_MINIMA: usize = 4;

/// The lowest value of the parabola through `(−1, l)`, `(0, c)`, `(1, r)`
/// (`c` itself where it does not curve upwards), never below zero.
fn parabola_min(l: f32, c: f32, r: f32) -> f32 {
    let a = 0.5 * (l + r) - c;
    if !(a > 0.0 && a.is_finite()) {
        return c;
    }
    let b = 0.5 * (r - l);
    (c - b * b / (4.0 * a)).max(0.0)
}

/// A local minimum of the residual over the grid.
#[derive(Clone, Copy, Debug)]
pub struct GridMin {
    pub j: usize,
    pub sse: f32,
}

impl ThicknessTable {
    /// Grid points needed for `model` at `theta` over `[d_lo, d_hi]`, and
    /// the step.
    pub fn size(model: &FilmModel, theta: f64, d_lo: f64, d_hi: f64) -> (usize, f64) {
        let k = model.max_phase_rate(theta).max(1e-9);
        let h = PHASE_STEP / k;
        let m = ((d_hi - d_lo).max(0.0) / h).ceil() as usize + 1;
        (m.max(2), h)
    }

    /// Tabulate `model` at `theta` over `[d_lo, d_hi]`, on a grid fine
    /// enough that the interpolant stays within [`INTERP_TOL`] of the model
    /// at the midpoints between grid points: the step is halved (at most
    /// three times) where the fringes are far from sinusoidal (high finesse,
    /// e.g. near grazing incidence).
    #[cfg(test)]
    pub fn new(model: &FilmModel, theta: f64, d_lo: f64, d_hi: f64) -> ThicknessTable {
        Self::new_reaching(model, theta, d_lo, d_hi, d_hi)
    }

    /// As [`ThicknessTable::new`], the grid continued to `d_reach`
    /// (`≥ d_hi`) for the walks from a previous pixel's fit, while the
    /// scan and everything it sets (each band's centre, the largest
    /// reflectance, the step's accuracy check) keep to `[d_lo, d_hi]`. A
    /// row's film that leaves the resolved range is then followed past
    /// it by the walks, and flagged "fringes unresolved" pixel by pixel
    /// at a walk's cost, where a scan over `[d_lo, d_hi]` finds nothing
    /// that fits and costs four times as much (the thick hard coat with
    /// its angle known: 28 % of its pixels past the range).
    pub fn new_reaching(
        model: &FilmModel,
        theta: f64,
        d_lo: f64,
        d_hi: f64,
        d_reach: f64,
    ) -> ThicknessTable {
        let (_, mut h) = Self::size(model, theta, d_lo, d_hi);
        let reach = d_reach.max(d_hi);
        let mut t = Self::with_step(model, theta, (d_lo, d_hi, reach), h);
        for _ in 0..3 {
            if t.midpoint_error(model, theta) <= INTERP_TOL {
                break;
            }
            h *= 0.5;
            t = Self::with_step(model, theta, (d_lo, d_hi, reach), h);
        }
        t
    }

    /// The largest difference between the interpolant and the model at
    /// the midpoints of (up to about a hundred, evenly spread) grid intervals.
    fn midpoint_error(&self, model: &FilmModel, theta: f64) -> f64 {
        let nb = self.nb;
        let mut out = ModelOut::new(nb);
        let (mut r, mut dr) = (vec![0.0; nb], vec![0.0; nb]);
        let stride = (self.m_scan / 97).max(1);
        let mut worst: f64 = 0.0;
        for j in (0..self.m_scan.saturating_sub(1)).step_by(stride) {
            let d = self.d_at(j) + 0.5 * self.h;
            model.eval(d, theta, &mut out, false);
            self.interp(d, &mut r, &mut dr);
            for (a, b) in r.iter().zip(&out.r[..nb]) {
                worst = worst.max((a - b).abs());
            }
        }
        worst
    }

    /// Tabulate `model` at `theta` over `[d_lo, d_reach]` with step `h`,
    /// scanned over `[d_lo, d_hi]`.
    fn with_step(
        model: &FilmModel,
        theta: f64,
        (d_lo, d_hi, d_reach): (f64, f64, f64),
        h: f64,
    ) -> ThicknessTable {
        let points = |d: f64| (((d - d_lo).max(0.0) / h).ceil() as usize + 1).max(2);
        let m = points(d_reach);
        let m_scan = points(d_hi).min(m);
        let nb = model.n_bands();
        let nbp = nb.div_ceil(8) * 8;
        let mut out = ModelOut::new(nb);
        let mut full = vec![0f64; m * nb];
        let mut dr = Vec::with_capacity(m * nb);
        let mut centre = vec![0f64; nb];
        for j in 0..m {
            model.eval(d_lo + j as f64 * h, theta, &mut out, true);
            full[j * nb..(j + 1) * nb].copy_from_slice(&out.r[..nb]);
            if j < m_scan {
                for (c, &v) in centre.iter_mut().zip(&out.r[..nb]) {
                    *c += v;
                }
            }
            dr.extend(out.dr_dd[..nb].iter().map(|&v| v as f32));
        }
        for c in &mut centre {
            *c /= m_scan as f64;
            if !c.is_finite() {
                *c = 0.0;
            }
        }
        let mut r = vec![0f32; m * nbp];
        let mut rr = Vec::with_capacity(m);
        for j in 0..m {
            let row = &mut r[j * nbp..j * nbp + nb];
            for ((d, &v), &c) in row.iter_mut().zip(&full[j * nb..(j + 1) * nb]).zip(&centre) {
                *d = (v - c) as f32;
            }
            rr.push(row.iter().map(|v| v * v).sum());
        }
        let mc = m_scan.div_ceil(SCAN_STRIDE);
        let blocks = mc.div_ceil(8);
        let mut coarse = vec![0f32; blocks * nb * 8];
        let mut coarse_rr = vec![f32::INFINITY; blocks * 8];
        for (i, crr) in coarse_rr.iter_mut().enumerate().take(mc) {
            let (b, l) = (i / 8, i % 8);
            let j = i * SCAN_STRIDE;
            for k in 0..nb {
                coarse[(b * nb + k) * 8 + l] = r[j * nbp + k];
            }
            *crr = rr[j];
        }
        let gram = (0..m - 1)
            .map(|j| {
                let mut g = [0f64; 6];
                for k in 0..nb {
                    let (c1, c2, c3) = IntervalCubic::coefficients(
                        f64::from(r[j * nbp + k]),
                        f64::from(r[(j + 1) * nbp + k]),
                        f64::from(dr[j * nb + k]),
                        f64::from(dr[(j + 1) * nb + k]),
                        h,
                    );
                    for (s, v) in
                        g.iter_mut()
                            .zip([c1 * c1, c1 * c2, c1 * c3, c2 * c2, c2 * c3, c3 * c3])
                    {
                        *s += v;
                    }
                }
                g
            })
            .collect();
        let gap = (0..m).map(|_| AtomicU32::new(f32::NAN.to_bits())).collect();
        let fringe = fringe_steps(model, theta, h);
        let r_max = (0..m_scan)
            .flat_map(|j| (0..nb).map(move |k| (j, k)))
            .map(|(j, k)| centre[k] + f64::from(r[j * nbp + k]))
            .fold(0.0, f64::max);
        ThicknessTable {
            d0: d_lo,
            h,
            inv_h: 1.0 / h,
            m,
            m_scan,
            nb,
            nbp,
            r,
            centre,
            rr,
            dr,
            coarse,
            coarse_rr,
            gram,
            gap,
            fringe,
            r_max,
        }
    }

    /// The noise-free separation of the neighbouring fringe orders around
    /// thickness `d`: the lesser of [`ThicknessTable::gap`] at the grid
    /// points either side of it (the gap swings by up to a third from one
    /// point to the next).
    pub fn order_gap(&self, d: f64) -> f64 {
        let x = (d - self.d0) * self.inv_h;
        let j = if x >= 0.0 {
            (x as usize).min(self.m - 1)
        } else {
            0
        };
        let b = (j + 1).min(self.m - 1);
        f64::from(self.gap_at(j).min(self.gap_at(b)))
    }

    /// [`ThicknessTable::gap`] at grid point `j`, computed on first use
    /// (threads that race compute the same value).
    fn gap_at(&self, j: usize) -> f32 {
        let cached = f32::from_bits(self.gap[j].load(Ordering::Relaxed));
        if !cached.is_nan() {
            return cached;
        }
        let g = order_gap_at(&self.r, self.nbp, self.nb, self.m, self.fringe, j);
        self.gap[j].store(g.to_bits(), Ordering::Relaxed);
        g
    }

    /// The largest reflectance of any band on the scanned grid.
    pub fn r_max(&self) -> f64 {
        self.r_max
    }

    /// Bytes the table holds.
    fn bytes(&self) -> usize {
        (self.r.len() + self.dr.len() + self.rr.len() + self.gap.len()) * 4
            + (self.coarse.len() + self.coarse_rr.len()) * 4
            + self.centre.len() * 8
            + self.gram.len() * 48
    }

    /// The grid point nearest to thickness `d` (the tests' starts).
    #[cfg(test)]
    pub fn index_of(&self, d: f64) -> usize {
        // Rounded by truncation of x + ½ (x ≥ 0): `round` and `floor` are
        // libm calls on baseline x86-64, and these run on every pixel.
        let x = (d - self.d0) / self.h;
        if x >= 0.0 {
            ((x + 0.5) as usize).min(self.m - 1)
        } else {
            0
        }
    }

    /// The grid interval holding thickness `d` (clamped to the grid): a
    /// walk from it toward the residual's minimum near `d` starts in the
    /// right interval, where a walk from the nearest grid point first
    /// tries the interval on its right and, half the time, steps back.
    pub fn interval_index(&self, d: f64) -> usize {
        self.interval_of(d).0
    }

    /// The grid step, nm.
    pub fn step(&self) -> f64 {
        self.h
    }

    /// Thickness of grid point `j`.
    pub fn d_at(&self, j: usize) -> f64 {
        self.d0 + j as f64 * self.h
    }

    /// The tabulated thickness range.
    pub fn d_range(&self) -> (f64, f64) {
        (self.d0, self.d_at(self.m.saturating_sub(1)))
    }

    /// Load a spectrum into the scan's working memory (f32, padded);
    /// returns whether it is complete (every weight 1).
    fn load(&self, y: &[f64], w: &[f64], buf: &mut GridScratch) -> bool {
        let (nb, nbp) = (self.nb, self.nbp);
        buf.y.clear();
        buf.y.extend(
            y[..nb]
                .iter()
                .zip(&self.centre)
                .map(|(&v, &c)| (v - c) as f32),
        );
        buf.y.resize(nbp, 0.0);
        buf.complete = w[..nb].iter().all(|&v| v == 1.0);
        if buf.complete {
            buf.yy = buf.y.iter().map(|v| v * v).sum();
        } else {
            buf.w.clear();
            buf.w.extend(w[..nb].iter().map(|&v| v as f32));
            buf.w.resize(nbp, 0.0);
        }
        buf.complete
    }

    /// The residual at grid point `j` of the loaded spectrum.
    fn sse_at(&self, j: usize, buf: &GridScratch) -> f32 {
        let nbp = self.nbp;
        let row = &self.r[j * nbp..(j + 1) * nbp];
        // Eight independent lanes, as in the scan (a plain f32 sum would
        // be one serial chain).
        let mut acc = [0f32; 8];
        if buf.complete {
            for (rv, yv) in row.chunks_exact(8).zip(buf.y.chunks_exact(8)) {
                for i in 0..8 {
                    acc[i] += rv[i] * yv[i];
                }
            }
            buf.yy - 2.0 * acc.iter().sum::<f32>() + self.rr[j]
        } else {
            let lanes = row.chunks_exact(8).zip(buf.y.chunks_exact(8));
            for ((rv, yv), wv) in lanes.zip(buf.w.chunks_exact(8)) {
                for i in 0..8 {
                    let e = yv[i] - rv[i];
                    acc[i] += wv[i] * e * e;
                }
            }
            acc.iter().sum()
        }
    }

    /// Walk downhill on the full grid from `g` to a local minimum.
    fn descend(&self, mut g: GridMin, buf: &GridScratch) -> GridMin {
        for _ in 0..self.m {
            let mut moved = false;
            for j in [g.j.wrapping_sub(1), g.j + 1] {
                if j < self.m {
                    let e = self.sse_at(j, buf);
                    if e < g.sse {
                        g = GridMin { j, sse: e };
                        moved = true;
                    }
                }
            }
            if !moved {
                break;
            }
        }
        g
    }

    /// The lowest local minima of `Σ w (y − R)²` over the grid, best first
    /// (at most `out.len()`); returns how many. `y` and `w` hold `nb`
    /// values; `buf` is working memory.
    pub fn minima(
        &self,
        y: &[f64],
        w: &[f64],
        buf: &mut GridScratch,
        out: &mut [GridMin],
    ) -> usize {
        let complete = self.load(y, w, buf);
        let mc = self.m_scan.div_ceil(SCAN_STRIDE);
        if complete {
            buf.sse.resize(self.coarse_rr.len(), 0.0);
            scan_blocked(
                &self.coarse,
                &self.coarse_rr,
                &buf.y[..self.nb],
                buf.yy,
                &mut buf.sse,
            );
        } else {
            buf.sse.resize(mc, 0.0);
            scan_weighted(&self.r, &buf.y, &buf.w, &mut buf.sse);
        }
        // Minima are ranked by the parabola through each and its
        // neighbours, not by the grid value: a narrow minimum (high
        // finesse) can sit between grid points far below its samples.
        // Every point's key at once (+∞ where it is no local minimum),
        // then the lowest few.
        buf.keys.resize(mc, f32::INFINITY);
        minimum_keys(&buf.sse[..mc], &mut buf.keys);
        let cap = out.len().min(MAX_MINIMA);
        let mut keys = [f32::INFINITY; MAX_MINIMA];
        let mut n = 0usize;
        // The worst key kept so far (any lower one is worth a look).
        let mut bar = f32::INFINITY;
        for (i, &key) in buf.keys.iter().enumerate() {
            // Keys are never NaN (+∞ stands for "no minimum").
            if key >= bar {
                continue;
            }
            let g = GridMin {
                j: i * SCAN_STRIDE,
                sse: buf.sse[i],
            };
            if n < cap {
                out[n] = g;
                keys[n] = key;
                n += 1;
            } else if let Some(worst) = (0..n).max_by(|&a, &b| keys[a].total_cmp(&keys[b])) {
                out[worst] = g;
                keys[worst] = key;
            }
            if n == cap {
                bar = keys[..n].iter().copied().fold(f32::NEG_INFINITY, f32::max);
            }
        }
        // Polish on the full grid, and rank by the fine parabola.
        for (g, key) in out[..n].iter_mut().zip(&mut keys) {
            *g = self.descend(*g, buf);
            let at = |j: Option<usize>| {
                j.filter(|&j| j < self.m)
                    .map_or(f32::INFINITY, |j| self.sse_at(j, buf))
            };
            *key = parabola_min(at(g.j.checked_sub(1)), g.sse, at(Some(g.j + 1)));
        }
        let mut idx: [usize; MAX_MINIMA] = std::array::from_fn(|i| i);
        idx[..n].sort_by(|&a, &b| {
            keys[a]
                .total_cmp(&keys[b])
                .then(out[a].sse.total_cmp(&out[b].sse))
        });
        let sorted: [GridMin; MAX_MINIMA] =
            std::array::from_fn(|i| if i < n { out[idx[i]] } else { out[0] });
        out[..n].copy_from_slice(&sorted[..n]);
        // Coarse minima may have led to the same fine one.
        let mut kept = 0;
        for i in 0..n {
            if !out[..kept].iter().any(|g| g.j == out[i].j) {
                out[kept] = out[i];
                kept += 1;
            }
        }
        kept
    }

    /// Grid interval `j` (points `j`, `j + 1`) holding `d`, clamped to the
    /// grid, and `d`'s position `t ∈ [0, 1]` in it.
    fn interval_of(&self, d: f64) -> (usize, f64) {
        let x = ((d - self.d0) * self.inv_h).clamp(0.0, (self.m - 1) as f64);
        // Truncation is `floor` here (x ≥ 0; NaN gives 0).
        let j = (x as usize).min(self.m - 2);
        (j, x - j as f64)
    }

    /// Values `[A, B]` and slopes `[P, Q]` of every band at the two ends of
    /// grid interval `j`. (Inlined: returned through memory, its slices
    /// were read back across the halves they were stored in.)
    #[inline(always)]
    fn ends(&self, j: usize) -> ([&[f32]; 2], [&[f32]; 2]) {
        let (nb, nbp) = (self.nb, self.nbp);
        (
            [
                &self.r[j * nbp..j * nbp + nb],
                &self.r[(j + 1) * nbp..(j + 1) * nbp + nb],
            ],
            [
                &self.dr[j * nb..(j + 1) * nb],
                &self.dr[(j + 1) * nb..(j + 2) * nb],
            ],
        )
    }

    /// The cubic Hermite basis at `t` (slope terms scaled by the step):
    /// `R = h00·A + h10·P + h01·B + h11·Q`.
    fn hermite(&self, t: f64) -> [f64; 4] {
        let (t2, t3, h) = (t * t, t * t * t, self.h);
        [
            2.0 * t3 - 3.0 * t2 + 1.0,
            (t3 - 2.0 * t2 + t) * h,
            -2.0 * t3 + 3.0 * t2,
            (t3 - t2) * h,
        ]
    }

    /// R and dR/dd of every band at `d` (inside the grid) by cubic Hermite
    /// interpolation.
    pub(in crate::estimate::solver) fn interp(&self, d: f64, r: &mut [f64], dr: &mut [f64]) {
        let (j, t) = self.interval_of(d);
        let [h00, h10, h01, h11] = self.hermite(t);
        let (t2, h) = (t * t, self.h);
        let (g00, g10, g01, g11) = (
            (6.0 * t2 - 6.0 * t) / h,
            3.0 * t2 - 4.0 * t + 1.0,
            (-6.0 * t2 + 6.0 * t) / h,
            3.0 * t2 - 2.0 * t,
        );
        let ([ra, rb], [da, db]) = self.ends(j);
        for k in 0..self.nb {
            let (a, b, p, q) = (
                f64::from(ra[k]),
                f64::from(rb[k]),
                f64::from(da[k]),
                f64::from(db[k]),
            );
            r[k] = self.centre[k] + h00 * a + h10 * p + h01 * b + h11 * q;
            dr[k] = g00 * a + g10 * p + g01 * b + g11 * q;
        }
    }

    /// R of every band at `d` on the interpolant (as the fit saw it): the
    /// interpolant of [`Self::interp`] without the slopes.
    pub fn values(&self, d: f64, r: &mut [f64]) {
        let (j, t) = self.interval_of(d);
        let (ends, slopes) = self.ends(j);
        interp_values(
            ends,
            slopes,
            &self.centre[..self.nb],
            self.hermite(t),
            &mut r[..self.nb],
        );
    }

    /// χ² of `y` (weights `w`) against the interpolant at `d` under `flat`
    /// noise, and the bands' mean variance: [`Self::values`] and
    /// [`FlatNoise::chi2_and_mean_var`] in one pass, with their arithmetic
    /// (the same numbers to the bit).
    pub fn chi2_flat(&self, d: f64, y: &[f64], w: &[f64], flat: &FlatNoise) -> (f64, f64) {
        let (j, t) = self.interval_of(d);
        let hm = self.hermite(t);
        let (r, dr) = self.ends(j);
        let (var, inv) = flat.parts();
        interp_chi2(r, dr, &self.centre[..self.nb], hm, y, w, var, inv)
    }

    /// χ² of `y` (weights `w`) against the interpolant at `d` under the
    /// reflectance-dependent `noise`, and the bands' mean variance:
    /// [`Self::values`] and [`NoiseModel::chi2_and_mean_var`] in one pass,
    /// in `f32` lanes (to ~1e-5 of χ² at a camera's noise, ~1e-4 at the
    /// σ floor: see `interp_model_chi2`).
    pub fn chi2_model(&self, d: f64, y: &[f64], w: &[f64], noise: &NoiseModel) -> (f64, f64) {
        let (j, t) = self.interval_of(d);
        let hm = self.hermite(t);
        let (r, dr) = self.ends(j);
        interp_model_chi2(r, dr, &self.centre[..self.nb], hm, y, w, noise)
    }

    /// The least-squares thickness near grid point `j` on the interpolant:
    /// for a complete spectrum the exact minimum of the residual polynomial
    /// ([`Self::fit_complete`]), otherwise Gauss–Newton (each step within
    /// one grid step; at most `iters`). Returns `(d, Σ w e², Σ w (dR/dd)²)`.
    pub fn fit(
        &self,
        y: &[f64],
        w: &[f64],
        j: usize,
        iters: usize,
        buf: &mut GridScratch,
    ) -> (f64, f64, f64) {
        if w[..self.nb].iter().all(|&v| v == 1.0) {
            self.fit_complete(y, j)
        } else {
            self.fit_gauss_newton(y, w, j, iters, buf)
        }
    }

    /// Gauss–Newton in `d` from grid point `j` on the interpolant (any
    /// weights), as [`Self::fit`].
    fn fit_gauss_newton(
        &self,
        y: &[f64],
        w: &[f64],
        j: usize,
        iters: usize,
        buf: &mut GridScratch,
    ) -> (f64, f64, f64) {
        let nb = self.nb;
        buf.r.resize(nb, 0.0);
        buf.dr.resize(nb, 0.0);
        let (r, dr) = (&mut buf.r[..], &mut buf.dr[..]);
        // Each step stays within a grid interval of where it starts, but
        // the walk may cross intervals: the grid point it starts from is
        // the nearest to a minimum, not always the one holding it.
        let (d_lo, d_hi) = (self.d0, self.d_at(self.m - 1));
        let mut d = self.d_at(j);
        let mut state = (f64::INFINITY, 0.0);
        // A converged step still gets one pass, for the residual at its end.
        let mut converged = false;
        for it in 0..=iters {
            self.interp(d, r, dr);
            let (mut e2, mut a, mut g) = (0.0, 0.0, 0.0);
            for k in 0..nb {
                let e = y[k] - r[k];
                e2 += w[k] * e * e;
                a += w[k] * dr[k] * dr[k];
                g += w[k] * dr[k] * e;
            }
            state = (e2, a);
            if converged || it == iters || a <= 0.0 {
                break;
            }
            let nd = (d + (g / a).clamp(-self.h, self.h)).clamp(d_lo, d_hi);
            converged = (nd - d).abs() < 1e-4 * self.h;
            d = nd;
        }
        (d, state.0, state.1)
    }
}

impl ThicknessTable {
    /// The residual of a complete spectrum on grid interval `i` (points
    /// `i`, `i + 1`) as a polynomial in the interval's `t`: four dot
    /// products over the bands, the rest from the interval's cross sums.
    fn interval_poly(&self, y: &[f64], i: usize) -> [f64; 7] {
        let nb = self.nb;
        let (r, dr) = self.ends(i);
        let [ee, e1, e2, e3] = interval_dots(r, dr, &y[..nb], &self.centre[..nb], self.h);
        residual_poly(ee, e1, e2, e3, &self.gram[i])
    }

    /// The least-squares thickness of a complete spectrum (every weight 1)
    /// on the interpolant near grid point `j`: the exact minimum of the
    /// residual polynomial on the interval beside `j` into which the
    /// residual falls, moving on (at most eight intervals) while the
    /// minimum sits on the far end. Returns `(d, Σ e², Σ (dR/dd)²)` as [`Self::fit`].
    fn fit_complete(&self, y: &[f64], j: usize) -> (f64, f64, f64) {
        self.walk_complete(y, j, 8).0
    }

    /// [`Self::fit_complete`] with at most `max_walk` intervals walked
    /// past the first; also says whether the minimum is a stationary
    /// point (not an interval end the residual still falls beyond, where
    /// the walk stopped short: the minimum lies elsewhere).
    ///
    /// Inlined: returned through memory, its tuple was read back across
    /// the halves it was stored in, a stalled load on every live pixel.
    #[inline(always)]
    fn walk_complete(&self, y: &[f64], j: usize, max_walk: usize) -> ((f64, f64, f64), bool) {
        let last = self.m - 2;
        // The interval right of `j` where the residual falls into it,
        // else the one on its left.
        let mut i = j.min(last);
        let mut p = self.interval_poly(y, i);
        if p[1] >= 0.0 && i > 0 && i == j {
            i -= 1;
            p = self.interval_poly(y, i);
        }
        let (mut t, mut v) = poly_min(&p);
        let left = t == 0.0;
        for _ in 0..max_walk {
            // The minimum on the interval's end: the residual still
            // falls beyond it (in the direction first taken).
            if left && t == 0.0 && i > 0 {
                i -= 1;
            } else if !left && t == 1.0 && i < last {
                i += 1;
            } else {
                break;
            }
            p = self.interval_poly(y, i);
            (t, v) = poly_min(&p);
        }
        let (best_i, best_t, best_v) = (i, t, v);
        let inside = (best_t > 0.0 || best_i == 0) && (best_t < 1.0 || best_i == last);
        let t = best_t;
        let [s11, s12, s13, s22, s23, s33] = self.gram[best_i];
        let a = (s11
            + t * (4.0 * s12 + t * (4.0 * s22 + 6.0 * s13 + t * (12.0 * s23 + t * 9.0 * s33))))
            / (self.h * self.h);
        ((self.d_at(best_i) + t * self.h, best_v.max(0.0), a), inside)
    }

    /// The fit from grid point `j0` (the interval holding the previous
    /// pixel's fit, [`Self::interval_index`]): the residual's minimum
    /// reached by walking downhill on the interpolant from there (at most [`HINT_WINDOW`] intervals), if the walk ends at
    /// a stationary point (else the fringe order changed: scan instead).
    /// Returns `(d, Σ e², Σ (dR/dd)²)` as [`Self::fit`]; complete spectra
    /// only (`n_ok`, the bands used, is every band: weights are 1 on the
    /// bands used), `None` otherwise.
    #[inline(always)]
    pub fn fit_near(&self, y: &[f64], n_ok: usize, j0: usize) -> Option<(f64, f64, f64)> {
        if n_ok != self.nb || j0 >= self.m {
            return None;
        }
        let (fit, inside) = self.walk_complete(y, j0, HINT_WINDOW);
        (inside && fit.0.is_finite() && fit.1.is_finite()).then_some(fit)
    }
}

/// One fringe at the band range's centre in grid steps of `h`: the film's
/// phase `4π d x` moves 2π over `1/(2 x)` at the centre's phase rate `x`
/// (the mean of the extreme bands' rates).
fn fringe_steps(model: &FilmModel, theta: f64, h: f64) -> f64 {
    let x = model.phase_rates(theta);
    let (lo, hi) = x
        .iter()
        .fold((f64::INFINITY, 0f64), |(a, b), &v| (a.min(v), b.max(v)));
    let centre = 0.5 * (lo + hi);
    if centre > 0.0 && h > 0.0 {
        0.5 / centre / h
    } else {
        f64::INFINITY
    }
}

/// [`ThicknessTable::gap`] at grid point `j` of rows `r` (stride `nbp`,
/// `nb` bands, `m` points), one fringe being `fringe` grid steps: the
/// least squared distance to the points half to one and a half fringes
/// away on either side (the neighbouring orders' basins; +∞ where neither
/// side is on the grid), each basin's floor from the parabola through the
/// three grid points around it. Every point, not every scanned one: the
/// gap swings with the bands' phases over half a fringe (a third of the
/// points overstated it by 16 % between them). O(fringe · nb).
fn order_gap_at(r: &[f32], nbp: usize, nb: usize, m: usize, fringe: f64, j: usize) -> f32 {
    if !fringe.is_finite() {
        return f32::INFINITY;
    }
    // The window in whole grid steps, taken wide (half a fringe is at
    // least one step in).
    let (near, far) = (
        ((0.5 * fringe).floor() as usize).max(1),
        (1.5 * fringe).ceil() as usize,
    );
    let dist = |b: usize| -> f32 {
        let (ra, rb) = (&r[j * nbp..j * nbp + nb], &r[b * nbp..b * nbp + nb]);
        ra.iter().zip(rb).map(|(x, y)| (x - y) * (x - y)).sum()
    };
    // The least over one side's window [lo, hi] (grid points): at every
    // point, and between points the parabola's floor through a bracketed
    // least (not one extrapolated past a monotone run). A neighbouring
    // order's basin is a fraction of a fringe wide (the bands dephase away
    // from its floor).
    let side = |lo: usize, hi: usize| -> f32 {
        let (mut least, mut last) = (f32::INFINITY, [f32::NAN; 2]);
        for i in lo..=hi {
            let v = dist(i);
            least = least.min(v);
            if last[1] <= last[0] && last[1] <= v {
                least = least.min(parabola_min(last[0], last[1], v));
            }
            last = [last[1], v];
        }
        least
    };
    let mut g = f32::INFINITY;
    if j >= near {
        g = g.min(side(j.saturating_sub(far), j - near));
    }
    if j + near < m {
        g = g.min(side(j + near, (j + far).min(m - 1)));
    }
    g
}

/// The tables of a solver: one per known angle (keyed by the angle's
/// bits, sorted: every pixel looks its table up, and a uniform angle's
/// one key is found without hashing), or, for an angle map with too many
/// distinct angles, one per bin of an angle grid.
#[derive(Clone, Debug, Default)]
pub struct Tables {
    by_angle: Vec<(u64, Arc<ThicknessTable>)>,
    bins: Option<Bins>,
}

/// Tables on an angle grid `lo + i·step`.
#[derive(Clone, Debug)]
struct Bins {
    lo: f64,
    step: f64,
    tables: Vec<Arc<ThicknessTable>>,
}

impl Tables {
    /// Tabulate `model` at each of `angles` over the thicknesses the angle
    /// allows (`range(θ)`: scanned `[lo, hi]`, walked to `reach`; the
    /// reach is dropped where it would break the budget), unless the
    /// tables would exceed [`TABLE_BUDGET_BYTES`] (then none: pixels take
    /// the search).
    pub fn build(
        model: &FilmModel,
        angles: &[f64],
        range: impl Fn(f64) -> (f64, f64, f64) + Sync,
    ) -> Tables {
        use rayon::prelude::*;
        let nb = model.n_bands();
        let bytes = |reach: bool| -> usize {
            angles
                .iter()
                .map(|&t| {
                    let (lo, hi, far) = range(t);
                    let hi = if reach { far.max(hi) } else { hi };
                    ThicknessTable::size(model, t, lo, hi).0 * bytes_per_point(nb)
                })
                .sum()
        };
        if angles.is_empty() || bytes(false) > TABLE_BUDGET_BYTES {
            return Tables::default();
        }
        let reach = bytes(true) <= TABLE_BUDGET_BYTES;
        let mut keys: Vec<u64> = angles.iter().map(|t| t.to_bits()).collect();
        keys.sort_unstable();
        keys.dedup();
        let by_angle = keys
            .par_iter()
            .map(|&k| {
                let t = f64::from_bits(k);
                let (lo, hi, far) = range(t);
                let far = if reach { far } else { hi };
                (
                    k,
                    Arc::new(ThicknessTable::new_reaching(model, t, lo, hi, far)),
                )
            })
            .collect();
        Tables {
            by_angle,
            bins: None,
        }
    }

    /// Tables on a grid of angles covering `[lo, hi]` at `step` (widened
    /// until they fit [`TABLE_BUDGET_BYTES`], up to `max_step`; beyond
    /// that, none), each over `range(θ)` as in [`Tables::build`] (the
    /// reach dropped first, before the step is widened).
    pub fn binned(
        model: &FilmModel,
        (lo, hi): (f64, f64),
        step: f64,
        max_step: f64,
        range: impl Fn(f64) -> (f64, f64, f64) + Sync,
    ) -> Tables {
        use rayon::prelude::*;
        let nb = model.n_bands();
        let bytes_at = |t: f64, reach: bool| {
            let (a, b, far) = range(t);
            let b = if reach { far.max(b) } else { b };
            ThicknessTable::size(model, t, a, b).0 * bytes_per_point(nb)
        };
        // The largest table of the span (the most oblique angle has the
        // shortest optical path but the widest range; take both ends).
        let per = |reach: bool| bytes_at(lo, reach).max(bytes_at(hi, reach)).max(1);
        let count = |s: f64| ((hi - lo) / s).ceil() as usize + 1;
        let reach = count(step) * per(true) <= TABLE_BUDGET_BYTES;
        let per = per(reach);
        let mut step = step;
        while count(step) * per > TABLE_BUDGET_BYTES && step <= max_step {
            step *= 1.5;
        }
        if step > max_step || hi.is_nan() || lo.is_nan() || hi < lo {
            return Tables::default();
        }
        let tables = (0..count(step))
            .into_par_iter()
            .map(|i| {
                let t = lo + i as f64 * step;
                let (a, b, far) = range(t);
                let far = if reach { far } else { b };
                Arc::new(ThicknessTable::new_reaching(model, t, a, b, far))
            })
            .collect();
        Tables {
            by_angle: Vec::new(),
            bins: Some(Bins { lo, step, tables }),
        }
    }

    /// The binned table nearest to `theta`, with its angle.
    pub fn nearest(&self, theta: f64) -> Option<(&ThicknessTable, f64)> {
        let b = self.bins.as_ref()?;
        let i = ((theta - b.lo) / b.step).round();
        if !(i >= 0.0 && (i as usize) < b.tables.len()) {
            return None;
        }
        let i = i as usize;
        Some((&*b.tables[i], b.lo + i as f64 * b.step))
    }

    /// The table at exactly this angle, if one was built: the position
    /// `hint` holds tried first (where the last lookup found its table: a
    /// row's pixels mostly share an angle), the position found left there.
    pub fn get_hinted(&self, theta: f64, hint: &Cell<usize>) -> Option<&ThicknessTable> {
        let key = theta.to_bits();
        let all = self.by_angle.as_slice();
        if let Some((k, t)) = all.get(hint.get()) {
            if *k == key {
                return Some(t);
            }
        }
        let i = all.binary_search_by_key(&key, |e| e.0).ok()?;
        hint.set(i);
        Some(&*all[i].1)
    }

    /// Whether any table was built.
    pub fn is_empty(&self) -> bool {
        self.by_angle.is_empty() && self.bins.is_none()
    }

    /// Bytes all tables hold.
    pub fn bytes(&self) -> usize {
        let bins = self
            .bins
            .as_ref()
            .map_or(0, |b| b.tables.iter().map(|t| t.bytes()).sum());
        self.by_angle.iter().map(|(_, t)| t.bytes()).sum::<usize>() + bins
    }
}

#[cfg(test)]
mod tests {
    use super::poly::poly_eval;
    use super::*;
    use crate::optics::band::Band;
    use crate::optics::dispersion::Dispersion;
    use crate::optics::Polarization;

    /// 1.46 on 1.6, unpolarised, 31 bands 400–700 nm (also the angle
    /// bins' tests' model).
    pub(super) fn model() -> FilmModel {
        let bands: Vec<Band> = (0..31)
            .map(|i| Band {
                center_nm: 400.0 + 10.0 * i as f64,
                fwhm_nm: 0.0,
            })
            .collect();
        FilmModel::new(
            &bands,
            &Dispersion::constant(1.0),
            &Dispersion::constant(1.46),
            &Dispersion::constant(1.6),
            Polarization::Unpolarized,
            &[false; 31],
        )
        .unwrap()
    }

    /// Case `i` of the fused χ² tests: the model's spectrum 0.3 nm off
    /// `d`, with a small pattern and `offset` added, and weights dropping
    /// two bands on every third case.
    fn spectrum_off_the_table(
        m: &FilmModel,
        d: f64,
        i: usize,
        offset: f64,
        out: &mut ModelOut,
    ) -> (Vec<f64>, Vec<f64>) {
        m.eval(d + 0.3, 0.4, out, false);
        let y = (out.r.iter().enumerate())
            .map(|(k, v)| v + 1e-3 * ((k * 7 + i) % 5) as f64 + offset)
            .collect();
        let mut w = vec![1.0; 31];
        if i % 3 == 0 {
            w[i % 31] = 0.0;
            w[(i + 11) % 31] = 0.0;
        }
        (y, w)
    }

    /// The fused χ² on the interpolant gives, to the bit, what the
    /// interpolant's values and the flat noise's χ² give one after the
    /// other (the estimate's χ² test must not depend on which path asked),
    /// with every band and with some bands left out.
    #[test]
    fn fused_chi2_matches_values_then_flat_chi2() {
        use crate::estimate::noise::{NoiseModel, NoiseSource};
        let m = model();
        let t = ThicknessTable::new(&m, 0.4, 0.0, 2000.0);
        let sigma: Vec<f64> = (0..31).map(|k| 0.001 + 1e-4 * k as f64).collect();
        let flat = NoiseModel::per_band(&sigma, NoiseSource::Given)
            .flat()
            .expect("per-band noise is flat");
        let mut out = ModelOut::new(31);
        let mut r = vec![0.0; 31];
        for i in 0..500 {
            let d = 3.1 + i as f64 * 3.97;
            let (y, w) = spectrum_off_the_table(&m, d, i, 0.0, &mut out);
            t.values(d, &mut r);
            let (c1, v1) = flat.chi2_and_mean_var(&y, &w, &r);
            let (c2, v2) = t.chi2_flat(d, &y, &w, &flat);
            assert!(c1 > 0.0 && v1 > 0.0);
            // And both what the definition gives, summed plainly.
            let (var, inv) = flat.parts();
            let plain: f64 = (0..31).map(|k| w[k] * (y[k] - r[k]).powi(2) * inv[k]).sum();
            let used = w.iter().filter(|&&x| x != 0.0).count() as f64;
            let mean: f64 = (0..31)
                .filter(|&k| w[k] != 0.0)
                .map(|k| var[k])
                .sum::<f64>()
                / used;
            assert!((c1 - plain).abs() <= 1e-12 * plain, "{c1} vs {plain}");
            assert!((v1 - mean).abs() <= 1e-12 * mean, "{v1} vs {mean}");
            assert_eq!(
                (c1.to_bits(), v1.to_bits()),
                (c2.to_bits(), v2.to_bits()),
                "d = {d}"
            );
        }
    }

    /// The fused χ² under a reflectance-dependent noise model (read, shot
    /// and scale terms, as a camera's calibration gives) is the values
    /// then [`NoiseModel::chi2_and_mean_var`] to the `f32` lanes'
    /// precision, and that is the definition summed plainly (to
    /// rounding), with bands dropped and spectra lying off the model by up
    /// to 0.02. The fused pass forms `y − R` in `f32`: ~1e-8 of rounding
    /// on a residual of σ ≥ 1e-3 here, so χ² within 1e-4 (ten times the
    /// expected error) and the mean variance, a sum of positive terms,
    /// within 1e-6.
    #[test]
    fn fused_chi2_matches_values_then_model_chi2() {
        use crate::estimate::noise::{NoiseModel, NoiseSource};
        let m = model();
        let t = ThicknessTable::new(&m, 0.4, 0.0, 2000.0);
        let noise = NoiseModel {
            var0: (0..31).map(|k| 1e-6 * (1.0 + 0.2 * k as f64)).collect(),
            shot: (0..31).map(|k| 4e-5 / (1.0 + 0.1 * k as f64)).collect(),
            rel2: 1e-4,
            source: NoiseSource::Camera,
        };
        let mut out = ModelOut::new(31);
        let mut r = vec![0.0; 31];
        let mut worst = 0f64;
        for i in 0..500 {
            let d = 3.1 + i as f64 * 3.97;
            let offset = if i % 7 == 0 { -0.02 } else { 0.0 };
            let (y, w) = spectrum_off_the_table(&m, d, i, offset, &mut out);
            t.values(d, &mut r);
            let (c1, v1) = noise.chi2_and_mean_var(&y, &w, &r);
            let (c2, v2) = t.chi2_model(d, &y, &w, &noise);
            let plain: f64 = (0..31)
                .map(|k| w[k] * (y[k] - r[k]).powi(2) / noise.var(k, r[k]))
                .sum();
            let used = w.iter().filter(|&&x| x != 0.0).count() as f64;
            let mean: f64 = (0..31)
                .filter(|&k| w[k] != 0.0)
                .map(|k| noise.var(k, r[k]))
                .sum::<f64>()
                / used;
            assert!(
                c1 > 0.0 && (c1 - plain).abs() <= 1e-12 * plain,
                "{c1} vs {plain}"
            );
            assert!((v1 - mean).abs() <= 1e-12 * mean, "{v1} vs {mean}");
            assert!((c2 - c1).abs() <= 1e-4 * c1, "d = {d}: {c2} vs {c1}");
            assert!((v2 - v1).abs() <= 1e-6 * v1, "d = {d}: {v2} vs {v1}");
            worst = worst.max((c2 - c1).abs() / c1);
        }
        // Not vacuous: f32 rounding shows, well inside the bound.
        assert!(
            worst > 0.0 && worst < 1e-4,
            "worst relative χ² error {worst}"
        );
    }

    /// The interpolant against the exact model between grid points: its
    /// error bound h⁴·max|R''''|/384 with |R''''| ≤ A·k⁴ (A the fringe
    /// amplitude, k the fastest phase rate) is A·PHASE_STEP⁴/384 ≈ 2e-5·A.
    #[test]
    fn interpolation_error_is_far_below_noise() {
        let m = model();
        let th = 0.5;
        let t = ThicknessTable::new(&m, th, 0.0, 3000.0);
        let mut out = ModelOut::new(31);
        let (mut r, mut dr) = ([0.0; 31], [0.0; 31]);
        let mut worst: f64 = 0.0;
        for i in 0..2000 {
            let d = 0.37 + i as f64 * 1.4993;
            m.eval(d, th, &mut out, true);
            t.interp(d, &mut r, &mut dr);
            for (a, b) in r.iter().zip(&out.r) {
                worst = worst.max((a - b).abs());
            }
            // The values alone are the same interpolant.
            let mut v = [0.0; 31];
            t.values(d, &mut v);
            assert_eq!(v, r, "at {d} nm");
        }
        // Fringe amplitude here is ≤ 0.05: bound 1e-6 plus f32 storage.
        assert!(worst < 2e-6, "{worst}");
    }

    /// The order gap against a second formulation: the exact model scanned
    /// every 0.1 nm over the neighbouring orders' windows (half to one and
    /// a half fringes away, the fringe from the film's normal wavevector at
    /// the bands' mean phase rate). The table's gap samples every grid
    /// point with a parabola through each basin's floor and takes the
    /// lesser of the two grid points around `d`: it must never claim
    /// orders farther apart than the scan finds at `d` (which would skip a
    /// check that was due) beyond the interpolation's few per cent, nor
    /// fall below the scan's least within a step of `d` (its windows a
    /// step wider).
    #[test]
    fn order_gap_matches_a_dense_model_scan() {
        let m = model();
        let th: f64 = 0.5;
        let t = ThicknessTable::new(&m, th, 0.0, 2500.0);
        let q = (1.46f64 * 1.46 - th.sin().powi(2)).sqrt();
        let fringe = 1.0 / (q / 400.0 + q / 700.0);
        let mut out = ModelOut::new(31);
        let mut at = |d: f64| -> Vec<f64> {
            m.eval(d, th, &mut out, false);
            out.r.clone()
        };
        // The scan over offsets [0.5, 1.5] fringes widened by `widen` nm
        // either way.
        let mut dense = |d: f64, widen: f64| -> f64 {
            let r0 = at(d);
            let mut least = f64::INFINITY;
            for i in 0..=((fringe + 2.0 * widen) / 0.1) as usize {
                let off = 0.5 * fringe - widen + 0.1 * i as f64;
                for d2 in [d - off, d + off] {
                    if (0.0..=2500.0).contains(&d2) {
                        let r = at(d2);
                        let e: f64 = r.iter().zip(&r0).map(|(a, b)| (a - b) * (a - b)).sum();
                        least = least.min(e);
                    }
                }
            }
            least
        };
        for i in 0..60 {
            let d = 13.7 + 41.3 * i as f64;
            let g = t.order_gap(d);
            let here = dense(d, 0.0);
            // The table's windows reach up to a grid step past the
            // scan's, and its grid points up to a step from `d`.
            let around = (-10..=10)
                .map(|k| dense(d + 0.1 * f64::from(k) * t.h, t.h))
                .fold(f64::INFINITY, f64::min);
            assert!(g <= 1.05 * here + 1e-9, "{d} nm: table {g}, scan {here}");
            assert!(
                g >= 0.95 * around - 1e-9,
                "{d} nm: table {g}, scan {around} around"
            );
        }
    }

    /// The residual polynomial's exact minimum against Gauss–Newton on the
    /// same interpolant (a second formulation of one fit): the same
    /// thickness, residual and curvature on noisy spectra of thin and
    /// thick films, and from a grid point a few steps off the minimum.
    #[test]
    fn polynomial_minimum_matches_gauss_newton_on_the_interpolant() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let m = model();
        let th = 0.4;
        let t = ThicknessTable::new(&m, th, 0.0, 2500.0);
        let mut out = ModelOut::new(31);
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let noise = Normal::new(0.0, 2e-3).unwrap();
        let mut buf = GridScratch::default();
        for i in 0..300 {
            let d_true = 20.0 + 8.13 * i as f64;
            m.eval(d_true, th, &mut out, false);
            let y: Vec<f64> = out.r.iter().map(|v| v + noise.sample(&mut rng)).collect();
            let j = (t.index_of(d_true) + i % 3).min(t.m - 1) - (i % 5 == 0) as usize;
            let (d1, e1, a1) = t.fit_complete(&y, j);
            let (d2, e2, a2) = t.fit_gauss_newton(&y, &[1.0; 31], j, 50, &mut buf);
            // Both converge to the interpolant's minimum nearest the start.
            if (d1 - d2).abs() < t.h {
                // Gauss–Newton stops within 1e-4 of a grid step (~1e-3 nm);
                // the polynomial's minimum is exact, so never higher.
                assert!((d1 - d2).abs() < 1e-3, "{d_true}: {d1} vs {d2}");
                assert!(
                    e1 <= e2 * (1.0 + 1e-12) && e2 - e1 <= 1e-6 * e2,
                    "{e1} vs {e2}"
                );
                assert!((a1 - a2).abs() <= 1e-4 * a2, "{a1} vs {a2}");
            } else {
                // Different local minima: the polynomial's is never worse.
                assert!(e1 <= e2 * (1.0 + 1e-9), "{d_true}: {e1} vs {e2}");
            }
        }
    }

    /// The residual a walk returns is the residual of the interpolant's
    /// values at the thickness it returns, band by band, within 1e-9 of it
    /// (the χ² test settles from it where the bands' spread of variance
    /// allows, sparing 1e-6 for this rounding), at noise from 1e-5 to
    /// 1e-2 and from starts up to a few grid steps off.
    #[test]
    fn a_walks_residual_is_the_interpolants_residual_at_its_thickness() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let m = model();
        let th = 0.4;
        let t = ThicknessTable::new(&m, th, 0.0, 2500.0);
        let mut out = ModelOut::new(31);
        let mut r = vec![0.0; 31];
        let mut rng = rand::rngs::StdRng::seed_from_u64(17);
        let mut walked = 0;
        for i in 0..600 {
            let sigma = [1e-5, 1e-4, 1e-3, 1e-2][i % 4];
            let noise = Normal::new(0.0, sigma).unwrap();
            let d_true = 15.0 + 4.07 * i as f64;
            m.eval(d_true, th, &mut out, false);
            let y: Vec<f64> = out.r.iter().map(|v| v + noise.sample(&mut rng)).collect();
            let j = (t.index_of(d_true) + i % 4).min(t.m - 1);
            let Some((d, sse, _)) = t.fit_near(&y, 31, j) else {
                continue;
            };
            walked += 1;
            t.values(d, &mut r);
            let direct: f64 = y.iter().zip(&r).map(|(a, b)| (a - b) * (a - b)).sum();
            assert!(
                (sse - direct).abs() <= 1e-9 * direct + 1e-18,
                "{d_true} nm, σ {sigma}: walk {sse}, direct {direct}"
            );
        }
        assert!(walked >= 500, "{walked} of 600 walks ended at a minimum");
    }

    /// `poly_min` against a dense scan of random sextics shaped like a
    /// residual on one interval (a parabola plus smaller higher powers, the
    /// vertex anywhere near or beyond the interval): never above the scan's
    /// lowest value by more than 1e-9 of it, and at the same place. Newton
    /// stops after a step under 1e-3, which leaves the point within
    /// ~K·1e-6 of the minimum (K = |p‴/2p″|, below 1 for these shapes) and
    /// the value within ~p″·1e-12 of it: for a residual, a billionth of a
    /// noise variance.
    #[test]
    fn polynomial_minimum_matches_a_dense_scan() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for _ in 0..2000 {
            let vertex: f64 = rng.random_range(-0.5..1.5);
            let curv: f64 = rng.random_range(0.01..10.0);
            let mut p = [0.0; 7];
            p[0] = 1.0 + curv * vertex * vertex;
            p[1] = -2.0 * curv * vertex;
            p[2] = curv;
            for c in &mut p[3..] {
                *c = curv * rng.random_range(-0.2..0.2);
            }
            let (t, v) = poly_min(&p);
            let scan = (0..=100_000)
                .map(|i| {
                    let x = i as f64 / 100_000.0;
                    (x, poly_eval(&p, x).0)
                })
                .fold((0.0, f64::INFINITY), |a, b| if b.1 < a.1 { b } else { a });
            assert!(v <= scan.1 + 1e-9 * scan.1.abs(), "{p:?}: {v} > {}", scan.1);
            assert!((t - scan.0).abs() < 2e-3, "{p:?}: t {t} vs {}", scan.0);
        }
    }

    /// The blocked scan against the residual computed directly in f64 at
    /// every scanned grid point (a table whose point count is not a
    /// multiple of the block, so the padding is exercised too).
    #[test]
    fn blocked_scan_matches_direct_residuals() {
        let m = model();
        let t = ThicknessTable::new(&m, 0.2, 0.0, 1234.5);
        assert!(t.m.div_ceil(SCAN_STRIDE) % 8 != 0);
        let mut out = ModelOut::new(31);
        m.eval(333.3, 0.2, &mut out, false);
        let y: Vec<f64> = out
            .r
            .iter()
            .enumerate()
            .map(|(k, v)| v + 1e-3 * (k as f64).sin())
            .collect();
        let mut buf = GridScratch::default();
        t.load(&y, &[1.0; 31], &mut buf);
        let mut sse = vec![0f32; t.coarse_rr.len()];
        scan_blocked(&t.coarse, &t.coarse_rr, &buf.y[..31], buf.yy, &mut sse);
        let yy: f64 = y
            .iter()
            .zip(&t.centre)
            .map(|(v, c)| (v - c) * (v - c))
            .sum();
        for (i, &got) in sse.iter().enumerate() {
            let j = i * SCAN_STRIDE;
            if j >= t.m {
                assert!(got.is_infinite());
                continue;
            }
            let direct: f64 = (0..31)
                .map(|k| {
                    let e = y[k] - t.centre[k] - f64::from(t.r[j * t.nbp + k]);
                    e * e
                })
                .sum();
            assert!(
                (f64::from(got) - direct).abs() < 1e-6 * yy,
                "{j}: {got} vs {direct}"
            );
        }
    }

    /// A noiseless spectrum is found at its true thickness from the grid.
    #[test]
    fn fit_recovers_the_thickness_of_a_model_spectrum() {
        let m = model();
        let th = 0.3;
        let t = ThicknessTable::new(&m, th, 0.0, 2000.0);
        let mut out = ModelOut::new(31);
        for d_true in [12.0, 187.3, 611.1, 1499.9] {
            m.eval(d_true, th, &mut out, false);
            let mut buf = GridScratch::default();
            let mut mins = [GridMin { j: 0, sse: 0.0 }; 2];
            let n = t.minima(&out.r, &[1.0; 31], &mut buf, &mut mins);
            assert!(n >= 1);
            let (d, e2, _) = t.fit(&out.r, &[1.0; 31], mins[0].j, 10, &mut buf);
            assert!((d - d_true).abs() < 0.01, "{d_true}: {d} ({e2})");
        }
    }

    /// A row's walk starts on the line through its last two fits: exact
    /// on a ramp, the last fit after a jump of more than four grid steps
    /// (an edge or an order change) and where there is no fit before it.
    #[test]
    fn the_next_walk_starts_on_the_rows_ramp() {
        let h = 0.5;
        let first = Hint::start(7).then(100.0);
        assert_eq!(first.predicted(h), 100.0);
        let ramp = first.then(101.5);
        assert_eq!(ramp.predicted(h), 103.0);
        let falling = ramp.then(100.0);
        assert_eq!(falling.predicted(h), 98.5);
        let edge = falling.then(100.0 + 4.0 * h + 0.01);
        assert_eq!(edge.predicted(h), 100.0 + 4.0 * h + 0.01);
        assert_eq!(edge.key, 7);
    }

    /// `fast`'s walk from the previous pixel's grid point: from a few grid
    /// points either side of the minimum it reaches the same fit as the
    /// scan's; from a neighbouring fringe order (a full fringe away, more
    /// than the walk may go) it lands on that order's own minimum or gives
    /// up, never on this one; a spectrum with a missing band is left to
    /// the weighted path.
    #[test]
    fn the_walk_from_a_hint_reaches_the_scans_minimum() {
        let m = model();
        let th = 0.3;
        let t = ThicknessTable::new(&m, th, 0.0, 2000.0);
        let mut out = ModelOut::new(31);
        let mut buf = GridScratch::default();
        for d_true in [187.3, 611.1, 1499.9] {
            m.eval(d_true, th, &mut out, false);
            let j = t.index_of(d_true);
            let (d_scan, e_scan, a_scan) = t.fit(&out.r, &[1.0; 31], j, 10, &mut buf);
            for off in [-4i64, -1, 0, 1, 4] {
                let j0 = (j as i64 + off) as usize;
                let (d, e2, a) = t.fit_near(&out.r, 31, j0).expect("walks");
                assert!(
                    (d - d_scan).abs() < 1e-9,
                    "{d_true} from {off}: {d} vs {d_scan}"
                );
                assert!((e2 - e_scan).abs() <= 1e-12 + 1e-9 * e_scan);
                assert!((a - a_scan).abs() <= 1e-9 * a_scan);
            }
            // A fringe (2π of the fastest band's phase) is ≥ 20 grid points.
            let fringe = (2.0 * std::f64::consts::PI / PHASE_STEP) as usize;
            if let Some(j0) = j.checked_sub(fringe) {
                if let Some((d, _, _)) = t.fit_near(&out.r, 31, j0) {
                    assert!(
                        (d - d_true).abs() > 10.0,
                        "{d_true}: reached {d} from a fringe away"
                    );
                }
            }
            // A spectrum missing a band (30 of 31 used) is not walked.
            assert!(t.fit_near(&out.r, 30, j).is_none());
        }
    }

    /// A table whose grid reaches past its scanned range scans exactly as
    /// the plain table over that range (the same minima and residuals,
    /// the same band centres and largest reflectance), while a walk from
    /// near a film past the range ends at that film's thickness, which
    /// the plain table cannot reach.
    #[test]
    fn a_table_reaching_past_its_scan_scans_as_before_and_walks_beyond() {
        let m = model();
        let th = 0.3;
        let plain = ThicknessTable::new(&m, th, 0.0, 2000.0);
        let far = ThicknessTable::new_reaching(&m, th, 0.0, 2000.0, 4000.0);
        assert_eq!(plain.d_range(), (0.0, plain.d_at(plain.m - 1)));
        assert!(far.d_range().1 >= 4000.0 && far.m > 3 * plain.m / 2);
        assert_eq!(far.m_scan, plain.m);
        assert_eq!(far.centre, plain.centre);
        assert_eq!(far.r_max(), plain.r_max());
        let mut out = ModelOut::new(31);
        let mut buf = GridScratch::default();
        let w = [1.0; 31];
        for d_true in [187.3, 1499.9, 1990.0] {
            m.eval(d_true, th, &mut out, false);
            let mut a = [GridMin { j: 0, sse: 0.0 }; 3];
            let mut b = a;
            let na = plain.minima(&out.r, &w, &mut buf, &mut a);
            let nb = far.minima(&out.r, &w, &mut buf, &mut b);
            assert_eq!(na, nb, "{d_true}");
            for (x, y) in a[..na].iter().zip(&b[..nb]) {
                assert_eq!((x.j, x.sse.to_bits()), (y.j, y.sse.to_bits()), "{d_true}");
            }
        }
        for d_true in [2600.0, 3500.0] {
            m.eval(d_true, th, &mut out, false);
            let j0 = far.interval_index(d_true - 2.0 * far.step());
            let (d, e2, _) = far.fit_near(&out.r, 31, j0).expect("walks past the scan");
            assert!((d - d_true).abs() < 0.05, "{d_true}: {d}");
            assert!(e2 < 1e-8, "{d_true}: residual {e2}");
            let end = plain.interval_index(d_true);
            assert!(plain
                .fit_near(&out.r, 31, end)
                .is_none_or(|(d, _, _)| (d - d_true).abs() > 500.0));
        }
    }
}
