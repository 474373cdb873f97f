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
//! node costs two square roots, two divisions (the reciprocals taken
//! together, see `node`) and one `sin_cos`, with no angle grid and no
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

    /// `[4π/λ, n1, n1², n2², n3²]` per node.
    pub(super) fn parts(&self) -> [&[f64]; 5] {
        [&self.w, &self.n1, &self.n1s, &self.n2s, &self.n3s]
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

/// `(A − B)/(A + B)` and its derivative from those of `A` and `B`, given
/// `1/(A + B)`.
#[inline(always)]
fn ratio(a: f64, b: f64, da: f64, db: f64, inv: f64) -> (f64, f64) {
    ((a - b) * inv, 2.0 * (b * da - a * db) * inv * inv)
}

/// R, dR/dx and dR/dθ through the coefficients, of one polarisation with
/// coefficients `(r12, r23)` moving as `(d12, d23)` per radian, given
/// `(a, b, c)` and `1/(c + b x)` (see [`airy_terms`]).
#[inline(always)]
fn airy_real(
    (r12, r23, d12, d23): (f64, f64, f64, f64),
    (a, b, c): (f64, f64, f64),
    x: f64,
    inv: f64,
) -> (f64, f64, f64) {
    let p = r12 * r23;
    let da = 2.0 * (r12 * d12 + r23 * d23);
    let db = 2.0 * (d12 * r23 + r12 * d23);
    let dc = p * db;
    let r = (a + b * x) * inv;
    let dx = b * (c - a) * inv * inv;
    let dth = (da + x * db - r * (dc + x * db)) * inv;
    (r, dx, dth)
}

/// `(a, b, c)` of one polarisation's `R = (a + b x)/(c + b x)`.
#[inline(always)]
fn airy_terms(r12: f64, r23: f64) -> (f64, f64, f64) {
    let p = r12 * r23;
    (r12 * r12 + r23 * r23, 2.0 * p, 1.0 + p * p)
}

/// The nodes' arrays cut to the nodes evaluated (equal lengths, so the
/// loops index them without bounds checks).
struct Cut<'a> {
    w: &'a [f64],
    n1: &'a [f64],
    n1s: &'a [f64],
    n2s: &'a [f64],
    n3s: &'a [f64],
}

/// One node's R, dR/dd and dR/dθ (0 and 0 without `DERIV`). The divisions are the kernel's cost
/// (a packed division takes as long as a dozen multiplications), so the
/// reciprocals are taken together: the six denominators of the wave
/// vectors and coefficients from one division of their product, the two
/// Airy denominators from another. Every factor lies within
/// ~1e-3…30 below the critical angles, so the products neither overflow
/// nor underflow, and each reciprocal keeps a few ulps.
#[inline(always)]
fn node<const DERIV: bool>(k: &Cut<'_>, i: usize, a: &RealArgs) -> (f64, f64, f64) {
    let (w, n1, n1s, n2s, n3s) = (k.w[i], k.n1[i], k.n1s[i], k.n2s[i], k.n3s[i]);
    let kx2 = n1s * a.s * a.s;
    let q1 = n1 * a.c;
    let q2 = (n2s - kx2).sqrt();
    let q3 = (n3s - kx2).sqrt();
    // Denominators: the film's and substrate's q (their angle slopes), and
    // the s and p coefficients' A + B at both interfaces.
    let (s12, s23) = (q1 + q2, q2 + q3);
    let (p12, p23) = (n2s * q1 + n1s * q2, n3s * q2 + n2s * q3);
    let (m_q, m_s, m_p) = (q2 * q3, s12 * s23, p12 * p23);
    let inv = 1.0 / (m_q * m_s * m_p);
    let (inv_q, inv_s, inv_p) = (inv * m_s * m_p, inv * m_q * m_p, inv * m_q * m_s);
    // d(q)/dθ: q1 directly; film and substrate through kx².
    let dk = n1s * a.sm * a.cm;
    let (dq1, dq2, dq3) = (-n1 * a.sm, -dk * inv_q * q3, -dk * inv_q * q2);
    let (sn, x) = sin_cos_bounded(w * a.d * q2);
    let (rs12, ds12) = ratio(q1, q2, dq1, dq2, inv_s * s23);
    let (rs23, ds23) = ratio(q2, q3, dq2, dq3, inv_s * s12);
    let (rp12, dp12) = ratio(n2s * q1, n1s * q2, n2s * dq1, n1s * dq2, inv_p * p23);
    let (rp23, dp23) = ratio(n3s * q2, n2s * q3, n3s * dq2, n2s * dq3, inv_p * p12);
    let (ts, tp) = (airy_terms(rs12, rs23), airy_terms(rp12, rp23));
    let (es, ep) = (ts.2 + ts.1 * x, tp.2 + tp.1 * x);
    let inv_e = 1.0 / (es * ep);
    let (r_s, x_s, t_s) = airy_real((rs12, rs23, ds12, ds23), ts, x, inv_e * ep);
    let (r_p, x_p, t_p) = airy_real((rp12, rp23, dp12, dp23), tp, x, inv_e * es);
    let wp = 1.0 - a.ws;
    let r = a.ws * r_s + wp * r_p;
    if !DERIV {
        return (r, 0.0, 0.0);
    }
    let dx = a.ws * x_s + wp * x_p;
    let dcoef = a.ws * t_s + wp * t_p;
    let dphase = -sn * w;
    (r, dx * dphase * q2, dcoef + dx * dphase * a.d * dq2)
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
    let cut = Cut {
        w: &k.w[..n],
        n1: &k.n1[..n],
        n1s: &k.n1s[..n],
        n2s: &k.n2s[..n],
        n3s: &k.n3s[..n],
    };
    let (r, dd, dth) = (&mut r[..n], &mut dd[..n], &mut dth[..n]);
    let (w, n1, n1s, n2s, n3s) = (cut.w, cut.n1, cut.n1s, cut.n2s, cut.n3s);
    if a.deriv {
        overlapped!(i in n, in(w, n1, n1s, n2s, n3s), out(r, dd, dth) => {
            let cut = Cut { w, n1, n1s, n2s, n3s };
            (r[i], dd[i], dth[i]) = node::<true>(&cut, i, &a);
        });
    } else {
        overlapped!(i in n, in(w, n1, n1s, n2s, n3s), out(r) => {
            let cut = Cut { w, n1, n1s, n2s, n3s };
            r[i] = node::<false>(&cut, i, &a).0;
        });
    }
}
