//! The real dispersive path ([`super::real`]) in sixteen `f32` lanes, where
//! single precision is exact enough: the same arithmetic per node, the
//! phase `Δ = w·d·q2` and its reduction by π/2 kept in `f64`.
//!
//! Error budget. Every factor of a node lies within ~1e-3…30 and the Airy
//! form has no cancellation below grazing incidence (`c − a =
//! (1 − r12²)(1 − r23²)`), so R comes out within a few ulps of `f32`
//! (~1e-7) of the `f64` path, except through the phase: `q2 = √(n2² −
//! kx²)` in `f32` is off by up to ~6e-8 of itself, which moves Δ by
//! 6e-8·Δ. The caller takes this path only where Δ ≤ [`MAX_PHASE`] (the
//! phase then off by at most 2.4e-5 rad, so |ΔR| ≲ 1e-5, a tenth of the
//! smallest noise irid judges against, 1e-4) and below [`MAX_SIN`] (80°).
//! Thickness stays `f64` in the phase, so a refinement's steps of 1e-4 nm
//! are not rounded away. Beyond those limits the `f64` kernel runs. The
//! tests hold this path to the complex Airy sum (within 7e-7 measured, up
//! to the edge of its range) for s, p and unpolarised light, values and
//! derivatives.
//!
//! Why: the node loop's cost is two square roots and two divisions per
//! node, which `f64` AVX2 does four at a time and `f32` eight, each
//! faster. A chunk is sixteen nodes: one AVX-512 register, or two AVX2
//! ones whose independent chains hide each other's division and root
//! latencies (sixteen against eight, one thread, medians of six runs:
//! the thick hard coat with the angle free 0.43 → 0.47 M pixels/s on
//! AVX2, 0.48 → 0.54 M on AVX-512).

use super::real::{RealArgs, RealNodes};
use crate::estimate::fastmath::{reduce_quadrant, sin_cos_reduced_f32};
use multiversion::multiversion;

/// Largest phase (rad) at any node for which the `f32` lanes are used.
pub(super) const MAX_PHASE: f64 = 400.0;
/// Largest sin θ for which they are (80°).
pub(super) const MAX_SIN: f64 = 0.985;

/// Lanes per chunk.
const L: usize = 16;

/// The nodes' constants in `f32`, padded to whole chunks of sixteen (the
/// padding is a benign node: ambient, film and substrate of index 1.5,
/// w = 0).
#[derive(Clone, Debug, Default)]
pub(super) struct RealNodes32 {
    w: Vec<f64>,
    n1: Vec<f32>,
    n1s: Vec<f32>,
    n2s: Vec<f32>,
    n3s: Vec<f32>,
    len: usize,
    /// Largest `w·n2` over the nodes: the phase per nm of film at normal
    /// incidence, an upper bound at any angle.
    phase_rate: f64,
}

impl RealNodes32 {
    /// The `f32` copy of `k`.
    pub(super) fn new(k: &RealNodes) -> RealNodes32 {
        let len = k.len();
        let padded = len.div_ceil(L) * L;
        let pad32 = |v: &[f64], fill: f32| {
            let mut o: Vec<f32> = v.iter().map(|&x| x as f32).collect();
            o.resize(padded, fill);
            o
        };
        let [w, n1, n1s, n2s, n3s] = k.parts();
        let mut w64 = w.to_vec();
        w64.resize(padded, 0.0);
        let phase_rate = w
            .iter()
            .zip(n2s)
            .map(|(&w, &n2s)| w * n2s.sqrt())
            .fold(0.0, f64::max);
        RealNodes32 {
            w: w64,
            n1: pad32(n1, 1.5),
            n1s: pad32(n1s, 2.25),
            n2s: pad32(n2s, 2.25),
            n3s: pad32(n3s, 2.25),
            len,
            phase_rate,
        }
    }

    /// The largest phase per nm of film at any node.
    #[cfg(test)]
    pub(super) fn phase_rate(&self) -> f64 {
        self.phase_rate
    }

    /// Whether the `f32` lanes are exact enough at thickness `d` (nm) and
    /// `sin θ = s` (see the module's error budget).
    pub(super) fn applies(&self, d: f64, s: f64) -> bool {
        self.len > 0 && d.abs() * self.phase_rate <= MAX_PHASE && s.abs() <= MAX_SIN
    }
}

/// `(A − B)/(A + B)` and its derivative, given `1/(A + B)`.
#[inline(always)]
fn ratio(a: f32, b: f32, da: f32, db: f32, inv: f32) -> (f32, f32) {
    ((a - b) * inv, 2.0 * (b * da - a * db) * inv * inv)
}

/// One chunk of sixteen nodes starting at `i0`: R, dR/dd, dR/dθ into the
/// chunk's outputs. `S` and `P` say which polarisations carry weight: a
/// polarised beam (an LCTF is a polariser) computes one side only.
#[inline(always)]
fn chunk<const DERIV: bool, const S: bool, const P: bool>(
    k: &RealNodes32,
    i0: usize,
    a: &RealArgs,
    out: &mut [[f64; L]; 3],
) {
    let (s, c) = (a.s as f32, a.c as f32);
    let dk_angle = (a.sm * a.cm) as f32;
    let (sm, ws) = (a.sm as f32, a.ws as f32);
    let wp = 1.0 - ws;
    let d32 = a.d as f32;
    // Fixed-size views: no bounds check in the lane loops, so they
    // vectorise.
    let lanes = |v: &[f32]| -> [f32; L] {
        let mut a = [0f32; L];
        a.copy_from_slice(&v[i0..i0 + L]);
        a
    };
    let (n1v, n1sv, n2sv, n3sv) = (lanes(&k.n1), lanes(&k.n1s), lanes(&k.n2s), lanes(&k.n3s));
    let mut wv = [0f64; L];
    wv.copy_from_slice(&k.w[i0..i0 + L]);
    let w32 = wv.map(|w| w as f32);
    let mut phase = [0f64; L];
    let mut q2v = [0f32; L];
    let mut pre = [[0f32; L]; 9];
    for l in 0..L {
        let (n1, n1s, n2s, n3s) = (n1v[l], n1sv[l], n2sv[l], n3sv[l]);
        let kx2 = n1s * s * s;
        let q1 = n1 * c;
        let q2 = (n2s - kx2).sqrt();
        let q3 = (n3s - kx2).sqrt();
        // Denominators of the side not computed are 1 (x·1 folds away).
        let (s12, s23) = (q1 + q2, q2 + q3);
        let (p12, p23) = (n2s * q1 + n1s * q2, n3s * q2 + n2s * q3);
        let m_q = q2 * q3;
        let m_s = if S { s12 * s23 } else { 1.0 };
        let m_p = if P { p12 * p23 } else { 1.0 };
        let inv = 1.0 / (m_q * m_s * m_p);
        let (inv_q, inv_s, inv_p) = (inv * m_s * m_p, inv * m_q * m_p, inv * m_q * m_s);
        let dk = n1s * dk_angle;
        let (dq1, dq2, dq3) = (-n1 * sm, -dk * inv_q * q3, -dk * inv_q * q2);
        if S {
            let (rs12, ds12) = ratio(q1, q2, dq1, dq2, inv_s * s23);
            let (rs23, ds23) = ratio(q2, q3, dq2, dq3, inv_s * s12);
            pre[0][l] = rs12;
            pre[1][l] = rs23;
            pre[2][l] = ds12;
            pre[3][l] = ds23;
        }
        if P {
            let (rp12, dp12) = ratio(n2s * q1, n1s * q2, n2s * dq1, n1s * dq2, inv_p * p23);
            let (rp23, dp23) = ratio(n3s * q2, n2s * q3, n3s * dq2, n2s * dq3, inv_p * p12);
            pre[4][l] = rp12;
            pre[5][l] = rp23;
            pre[6][l] = dp12;
            pre[7][l] = dp23;
        }
        pre[8][l] = dq2;
        q2v[l] = q2;
    }
    // The phase reduced by π/2 in f64 (see `fastmath::sin_cos_bounded`).
    for l in 0..L {
        phase[l] = wv[l] * a.d * f64::from(q2v[l]);
    }
    let mut red = [0f32; L];
    let mut res = [[0f32; L]; 3];
    let mut quad = [0u32; L];
    for l in 0..L {
        let (r, q) = reduce_quadrant(phase[l]);
        red[l] = r as f32;
        quad[l] = q as u32;
    }
    for l in 0..L {
        let (sn, x) = sin_cos_reduced_f32(red[l], quad[l]);
        let (rs12, rs23, ds12, ds23) = (pre[0][l], pre[1][l], pre[2][l], pre[3][l]);
        let (rp12, rp23, dp12, dp23) = (pre[4][l], pre[5][l], pre[6][l], pre[7][l]);
        let (ps, pp) = (rs12 * rs23, rp12 * rp23);
        let (as_, bs, cs) = (rs12 * rs12 + rs23 * rs23, 2.0 * ps, 1.0 + ps * ps);
        let (ap, bp, cp) = (rp12 * rp12 + rp23 * rp23, 2.0 * pp, 1.0 + pp * pp);
        let es = if S { cs + bs * x } else { 1.0 };
        let ep = if P { cp + bp * x } else { 1.0 };
        let inv_e = 1.0 / (es * ep);
        let (inv_s, inv_p) = (inv_e * ep, inv_e * es);
        let r_s = (as_ + bs * x) * inv_s;
        let r_p = (ap + bp * x) * inv_p;
        res[0][l] = match (S, P) {
            (true, false) => r_s,
            (false, true) => r_p,
            _ => ws * r_s + wp * r_p,
        };
        if DERIV {
            let x_s = bs * (cs - as_) * inv_s * inv_s;
            let x_p = bp * (cp - ap) * inv_p * inv_p;
            let t_s = {
                let da = 2.0 * (rs12 * ds12 + rs23 * ds23);
                let db = 2.0 * (ds12 * rs23 + rs12 * ds23);
                (da + x * db - r_s * (ps * db + x * db)) * inv_s
            };
            let t_p = {
                let da = 2.0 * (rp12 * dp12 + rp23 * dp23);
                let db = 2.0 * (dp12 * rp23 + rp12 * dp23);
                (da + x * db - r_p * (pp * db + x * db)) * inv_p
            };
            let (dx, dcoef) = match (S, P) {
                (true, false) => (x_s, t_s),
                (false, true) => (x_p, t_p),
                _ => (ws * x_s + wp * x_p, ws * t_s + wp * t_p),
            };
            let dphase = -sn * w32[l];
            res[1][l] = dx * dphase * q2v[l];
            res[2][l] = dcoef + dx * dphase * d32 * pre[8][l];
        }
    }
    for (o, r) in out.iter_mut().zip(&res) {
        for l in 0..L {
            o[l] = f64::from(r[l]);
        }
    }
}

/// [`super::real::real_nodes_kernel`] in sixteen `f32` lanes: every node's
/// R (and dR/dd, dR/dθ with `a.deriv`) into `r`, `dd`, `dth`.
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn real_nodes_kernel32(
    k: &RealNodes32,
    a: RealArgs,
    r: &mut [f64],
    dd: &mut [f64],
    dth: &mut [f64],
) {
    let n = k.len.min(r.len()).min(dd.len()).min(dth.len());
    let mut out = [[0f64; L]; 3];
    for i0 in (0..n).step_by(L) {
        match (a.deriv, a.ws) {
            (true, 1.0) => chunk::<true, true, false>(k, i0, &a, &mut out),
            (true, 0.0) => chunk::<true, false, true>(k, i0, &a, &mut out),
            (true, _) => chunk::<true, true, true>(k, i0, &a, &mut out),
            (false, 1.0) => chunk::<false, true, false>(k, i0, &a, &mut out),
            (false, 0.0) => chunk::<false, false, true>(k, i0, &a, &mut out),
            (false, _) => chunk::<false, true, true>(k, i0, &a, &mut out),
        }
        let outs: [&mut [f64]; 3] = [r, dd, dth];
        let used = if a.deriv { 3 } else { 1 };
        for (o, v) in outs.into_iter().zip(&out).take(used) {
            if let Some(dst) = o.get_mut(i0..i0 + L) {
                // A whole chunk: a fixed-size copy (no call to memcpy).
                let dst: &mut [f64; L] = dst.try_into().expect("L values");
                *dst = *v;
            } else {
                for (d, s) in o[i0..n].iter_mut().zip(v) {
                    *d = *s;
                }
            }
        }
    }
}
