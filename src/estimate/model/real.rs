//! The real path for dispersive media: lossless ambient, film and substrate
//! below every critical angle, with indices that change from node to node.
//!
//! At each node the Fresnel coefficients are real and thickness enters only
//! through `x = cos Δ`, `Δ = 4π d q2 / λ` with `q = n cos θ` (`q2`, `q3`
//! from Snell's invariant `kx = n1 sin θ`). Per polarisation, with
//! `a = r12² + r23²`, `b = 2 r12 r23`, `c = 1 + r12² r23²`:
//!
//! `R = (a + b x) / (c + b x)`.
//!
//! The angle derivative is analytic: `dq1/dθ = −n1 sin θ`,
//! `dq/dθ = −n1² sin θ cos θ / q` for the film and the substrate, and each
//! coefficient `r = (A − B)/(A + B)` moves as `2 (B dA − A dB)/(A + B)²`
//! (s: `A, B = q_i, q_j`; p: `A, B = n_j² q_i, n_i² q_j`). The angle's own
//! sine and cosine in it are taken half a `THETA_STEP` (1e-6 rad) beyond θ,
//! as the other paths' forward differences over that step are: a relative
//! change of ~1e-6 anywhere, but at normal incidence, where R is even in θ
//! and its true derivative vanishes, the refinement still sees the slope
//! the curvature gives over the step and can leave θ = 0 (with an exact
//! zero it never could). The tests check the values against the complex
//! Airy sum and the derivatives against its central differences.
//!
//! Nodes are laid out as plain arrays so the node loop vectorises: each
//! node costs two square roots and one `sin_cos`, with no angle grid and no
//! interpolation (exact at every angle).

use super::Node;
use crate::estimate::fastmath::sin_cos_bounded;
use multiversion::multiversion;

/// The nodes' constants, one array per quantity.
#[derive(Clone, Debug, Default)]
pub(super) struct RealNodes {
    /// `4π / λ`.
    w: Vec<f64>,
    n1: Vec<f64>,
    n1s: Vec<f64>,
    n2s: Vec<f64>,
    n3s: Vec<f64>,
}

impl RealNodes {
    /// The real parts of every node's indices (the caller has checked the
    /// media are lossless).
    pub(super) fn new(nodes: &[Node]) -> RealNodes {
        let sq = |v: f64| v * v;
        RealNodes {
            w: nodes.iter().map(|n| n.w).collect(),
            n1: nodes.iter().map(|n| n.n1.re).collect(),
            n1s: nodes.iter().map(|n| sq(n.n1.re)).collect(),
            n2s: nodes.iter().map(|n| sq(n.n2.re)).collect(),
            n3s: nodes.iter().map(|n| sq(n.n3.re)).collect(),
        }
    }

    /// Number of nodes.
    pub(super) fn len(&self) -> usize {
        self.w.len()
    }
}

/// The angle, thickness and polarisation mix of one evaluation.
#[derive(Clone, Copy, Debug)]
pub(super) struct RealArgs {
    /// `sin θ`, `cos θ`.
    pub s: f64,
    pub c: f64,
    /// `sin`, `cos` half a `THETA_STEP` beyond θ, for the derivative.
    pub sm: f64,
    pub cm: f64,
    pub d: f64,
    /// Weight of s (p takes the rest).
    pub ws: f64,
    pub deriv: bool,
}

/// `(A − B)/(A + B)` and its derivative from those of `A` and `B`.
#[inline(always)]
fn ratio(a: f64, b: f64, da: f64, db: f64) -> (f64, f64) {
    let inv = 1.0 / (a + b);
    ((a - b) * inv, 2.0 * (b * da - a * db) * inv * inv)
}

/// R, dR/dx and dR/dθ through the coefficients, of one polarisation with
/// coefficients `(r12, r23)` moving as `(d12, d23)` per radian.
#[inline(always)]
fn airy_real(r12: f64, r23: f64, d12: f64, d23: f64, x: f64) -> (f64, f64, f64) {
    let p = r12 * r23;
    let a = r12 * r12 + r23 * r23;
    let b = 2.0 * p;
    let c = 1.0 + p * p;
    let da = 2.0 * (r12 * d12 + r23 * d23);
    let db = 2.0 * (d12 * r23 + r12 * d23);
    let dc = p * db;
    let inv = 1.0 / (c + b * x);
    let r = (a + b * x) * inv;
    let dx = b * (c - a) * inv * inv;
    let dth = (da + x * db - r * (dc + x * db)) * inv;
    (r, dx, dth)
}

/// Every node's R (and dR/dd, dR/dθ with `deriv`), into `r`, `dd`, `dth`
/// (one value per node).
#[multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1", "aarch64+neon"))]
pub(super) fn real_nodes_kernel(
    k: &RealNodes,
    a: RealArgs,
    r: &mut [f64],
    dd: &mut [f64],
    dth: &mut [f64],
) {
    let n = k.len().min(r.len()).min(dd.len()).min(dth.len());
    let (w, n1, n1s, n2s, n3s) = (&k.w[..n], &k.n1[..n], &k.n1s[..n], &k.n2s[..n], &k.n3s[..n]);
    let (r, dd, dth) = (&mut r[..n], &mut dd[..n], &mut dth[..n]);
    let RealArgs {
        s,
        c,
        sm,
        cm,
        d,
        ws,
        deriv,
    } = a;
    let wp = 1.0 - ws;
    for i in 0..n {
        let kx2 = n1s[i] * s * s;
        let q1 = n1[i] * c;
        let q2 = (n2s[i] - kx2).sqrt();
        let q3 = (n3s[i] - kx2).sqrt();
        // d(q)/dθ: q1 directly; film and substrate through kx².
        let dk = n1s[i] * sm * cm;
        let (dq1, dq2, dq3) = (-n1[i] * sm, -dk / q2, -dk / q3);
        let (sn, x) = sin_cos_bounded(w[i] * d * q2);
        let (rs12, ds12) = ratio(q1, q2, dq1, dq2);
        let (rs23, ds23) = ratio(q2, q3, dq2, dq3);
        let (rp12, dp12) = ratio(n2s[i] * q1, n1s[i] * q2, n2s[i] * dq1, n1s[i] * dq2);
        let (rp23, dp23) = ratio(n3s[i] * q2, n2s[i] * q3, n3s[i] * dq2, n2s[i] * dq3);
        let (r_s, x_s, t_s) = airy_real(rs12, rs23, ds12, ds23, x);
        let (r_p, x_p, t_p) = airy_real(rp12, rp23, dp12, dp23, x);
        r[i] = ws * r_s + wp * r_p;
        if deriv {
            let dx = ws * x_s + wp * x_p;
            let dcoef = ws * t_s + wp * t_p;
            let dphase = -sn * w[i];
            dd[i] = dx * dphase * q2;
            dth[i] = dcoef + dx * dphase * d * dq2;
        }
    }
}
