//! Stage 1, the fringe search: the spectrum projected on
//! `A + B·cos(4π g·ρ_k / λ_k)` over a grid of optical thicknesses `g` (at
//! the middle band; `ρ_k` the film's index at band k over its index there,
//! 1 for a film of unknown, constant index); the local minima of the
//! residual with the allowed fringe sign are the candidate fringe orders.

use super::{Scratch, Solver, MAX_BANDS};
use crate::optics::band::Band;
use std::f64::consts::PI;

/// The fringe-search basis: `cos(4π g_j ρ_k / λ_k)` for a grid of optical
/// thicknesses, with the inverse normal equations of `[1, cos]` per grid
/// point for a complete spectrum.
#[derive(Clone, Debug)]
pub(super) struct FringeBasis {
    g: Vec<f64>,
    /// `basis[j * nb + k]`.
    basis: Vec<f32>,
    /// Inverse of `[[N, Σc], [Σc, Σc²]]`, as `(a, b, c)` of a symmetric 2×2;
    /// NaN where the basis is too close to constant to separate.
    minv: Vec<[f64; 3]>,
    nb: usize,
}

/// Bytes the fringe-search basis may take: far above any real band set
/// (400–700 nm at 1 nm up to 100 µm of film: ~10 MB), far below what a
/// header with nonsense wavelengths would ask for.
pub const BASIS_BUDGET_BYTES: usize = 64 << 20;

impl FringeBasis {
    /// Grid step (nm of optical thickness) and grid points for `bands`
    /// with relative indices `rho` (empty: all 1) up to `g_max`, computed
    /// in f64 so a nonsense band set cannot overflow.
    fn grid(bands: &[Band], rho: &[f64], g_max: f64) -> (f64, f64) {
        let lam_min = bands
            .iter()
            .enumerate()
            .map(|(k, b)| b.center_nm / rho.get(k).copied().unwrap_or(1.0).max(1e-3))
            .fold(f64::INFINITY, f64::min);
        // Phase step at the fastest band (smallest λ/ρ) ≤ 0.35 rad: the residual's
        // minimum is never missed between grid points.
        let step = 0.35 * lam_min / (4.0 * PI);
        (step, (g_max / step).ceil() + 1.0)
    }

    /// Bytes the basis for `bands` up to `g_max` would take (f64: may be
    /// far beyond memory, or NaN for nonsense input).
    pub(super) fn bytes_needed(bands: &[Band], rho: &[f64], g_max: f64) -> f64 {
        let (_, n) = Self::grid(bands, rho, g_max);
        n * (bands.len() as f64 * 4.0 + 32.0)
    }

    /// The basis for `bands` up to `g_max`; `rho` is each band's film
    /// index over the middle band's (a dispersive film's fringes are
    /// chirped: past a few µm a constant index puts them radians off at
    /// the band set's ends), empty for a film of constant index.
    pub(super) fn new(bands: &[Band], rho: &[f64], g_max: f64) -> FringeBasis {
        let nb = bands.len();
        let (step, n) = Self::grid(bands, rho, g_max);
        let n = n as usize;
        let mut g = Vec::with_capacity(n);
        let mut basis = Vec::with_capacity(n * nb);
        let mut minv = Vec::with_capacity(n);
        for j in 0..n {
            let gj = j as f64 * step;
            let (mut s1, mut s2) = (0.0, 0.0);
            for (k, b) in bands.iter().enumerate() {
                let r = rho.get(k).copied().unwrap_or(1.0);
                let c = (4.0 * PI * gj * r / b.center_nm).cos();
                basis.push(c as f32);
                s1 += c;
                s2 += c * c;
            }
            let nf = nb as f64;
            let det = nf * s2 - s1 * s1;
            // Relative spread of the cosine across bands: below this the
            // fringe term is indistinguishable from the constant.
            if det > 0.02 * nf * nf {
                minv.push([s2 / det, -s1 / det, nf / det]);
            } else {
                minv.push([f64::NAN; 3]);
            }
            g.push(gj);
        }
        FringeBasis { g, basis, minv, nb }
    }
}

/// A candidate from the fringe search.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Candidate {
    pub(super) g: f64,
    pub(super) a: f64,
    pub(super) b: f64,
    pub(super) sse: f64,
}

pub(super) const MAX_CANDIDATES: usize = 4;

impl Solver {
    /// Candidate optical thicknesses: local minima of the projection
    /// residual with the allowed fringe sign, best first.
    pub(super) fn fringe_search(
        &self,
        scratch: &Scratch,
        sign: f64,
        complete: bool,
        out: &mut [Candidate; MAX_CANDIDATES],
    ) -> usize {
        let fb = &self.basis;
        let nb = fb.nb;
        let y = &scratch.spectrum;
        let wgt = &scratch.weight;
        let n_ok: f64 = wgt.iter().sum();
        let s_r: f64 = y.iter().sum();
        let s_rr: f64 = y.iter().map(|v| v * v).sum();
        let yf: [f32; MAX_BANDS] = {
            let mut a = [0f32; MAX_BANDS];
            for (d, s) in a.iter_mut().zip(y) {
                *d = *s as f32;
            }
            a
        };
        let yf = &yf[..nb];
        let mut prev2 = f64::INFINITY;
        let mut prev = f64::INFINITY;
        let mut prev_c = Candidate::default();
        let mut n = 0usize;
        let push = |c: Candidate, out: &mut [Candidate; MAX_CANDIDATES], n: &mut usize| {
            // Keep the best MAX_CANDIDATES by residual.
            if *n < MAX_CANDIDATES {
                out[*n] = c;
                *n += 1;
            } else if let Some(worst) = out
                .iter_mut()
                .max_by(|a, b| a.sse.total_cmp(&b.sse))
                .filter(|w| w.sse > c.sse)
            {
                *worst = c;
            }
        };
        for j in 0..fb.g.len() {
            let basis = &fb.basis[j * nb..(j + 1) * nb];
            let s_rc = f64::from(dot(yf, basis));
            let [a, b, c] = if complete {
                fb.minv[j]
            } else {
                let (mut s1, mut s2) = (0.0, 0.0);
                for k in 0..nb {
                    let cv = f64::from(basis[k]) * wgt[k];
                    s1 += cv;
                    s2 += cv * f64::from(basis[k]);
                }
                let det = n_ok * s2 - s1 * s1;
                if det > 0.02 * n_ok * n_ok {
                    [s2 / det, -s1 / det, n_ok / det]
                } else {
                    [f64::NAN; 3]
                }
            };
            let (cur, cand) = if a.is_nan() {
                (f64::INFINITY, Candidate::default())
            } else {
                let amp_a = a * s_r + b * s_rc;
                let amp_b = b * s_r + c * s_rc;
                let e = s_rr - (amp_a * s_r + amp_b * s_rc);
                if amp_b * sign < 0.0 {
                    (f64::INFINITY, Candidate::default())
                } else {
                    (
                        e,
                        Candidate {
                            g: fb.g[j],
                            a: amp_a,
                            b: amp_b,
                            sse: e,
                        },
                    )
                }
            };
            if prev.is_finite() && prev <= prev2 && prev < cur {
                push(prev_c, out, &mut n);
            }
            prev2 = prev;
            prev = cur;
            prev_c = cand;
        }
        if prev.is_finite() && prev <= prev2 {
            push(prev_c, out, &mut n);
        }
        out[..n].sort_by(|a, b| a.sse.total_cmp(&b.sse));
        n
    }
}

/// f32 dot product with independent accumulators so it vectorises.
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let ca = a.chunks_exact(8);
    let cb = b.chunks_exact(8);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i] * y[i];
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}
