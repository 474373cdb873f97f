//! The general path of the forward model: any media (absorbing film or
//! substrate, dispersion, total internal reflection), with every angle-
//! dependent quantity computed once per angle and reused for every
//! thickness.
//!
//! With `e^{iΔ}` split into a phase `φ = Re Δ` and an attenuation
//! `E = e^{−Im Δ}`, the Airy reflectance of one polarisation is a ratio of
//! two real trigonometric polynomials in `φ`:
//!
//! ```text
//! N = |r12|² + |r23|² E² + 2E·Re(r12* r23 e^{iφ})
//! D = 1 + |r12 r23|² E² + 2E·Re(r12 r23 e^{iφ})
//! R = N / D
//! ```
//!
//! so a thickness costs one `sin_cos` (and one `exp` where the film
//! absorbs) per node, with analytic derivatives in thickness. The angle
//! derivative uses the change of each coefficient over a small angle step
//! (exact to first order, as the real path does).

use crate::estimate::fastmath::sin_cos;
use crate::optics::airy::{fresnel_p, fresnel_s, normal_component};
use crate::optics::Complex64;

/// One polarisation's coefficients at one node and angle.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct PolCoef {
    /// `|r12|²`.
    a: f64,
    /// `|r23|²`.
    b: f64,
    /// `|r12 r23|²`.
    ab: f64,
    /// `r12* r23`.
    p: Complex64,
    /// `r12 r23`.
    u: Complex64,
}

impl PolCoef {
    fn new(r12: Complex64, r23: Complex64) -> PolCoef {
        let a = r12.norm_sqr();
        let b = r23.norm_sqr();
        PolCoef {
            a,
            b,
            ab: a * b,
            p: r12.conj() * r23,
            u: r12 * r23,
        }
    }

    fn slope(self, other: PolCoef, h: f64) -> PolCoef {
        PolCoef {
            a: (other.a - self.a) / h,
            b: (other.b - self.b) / h,
            ab: (other.ab - self.ab) / h,
            p: (other.p - self.p) / h,
            u: (other.u - self.u) / h,
        }
    }
}

/// Everything one node needs at one angle: both polarisations, their slopes
/// in angle, and the film's normal wave-vector component with its slope.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct NodeCoef {
    s: PolCoef,
    p: PolCoef,
    ds: PolCoef,
    dp: PolCoef,
    /// `4π/λ · q2` (phase and attenuation per nm of thickness).
    k: Complex64,
    /// `d k / dθ`.
    dk: Complex64,
}

fn pol_pair(
    n1: Complex64,
    n2: Complex64,
    n3: Complex64,
    sin_t: f64,
) -> (PolCoef, PolCoef, Complex64) {
    let kx = n1 * sin_t;
    let q1 = normal_component(n1, kx);
    let q2 = normal_component(n2, kx);
    let q3 = normal_component(n3, kx);
    let s = PolCoef::new(fresnel_s(q1, q2), fresnel_s(q2, q3));
    let p = PolCoef::new(fresnel_p(n1, n2, q1, q2), fresnel_p(n2, n3, q2, q3));
    (s, p, q2)
}

/// Cubic Hermite interpolation at `t ∈ [0, 1]` of a value known with its
/// slope at both ends of an interval `h` wide; the slope is interpolated
/// linearly (it only steers the fits' steps).
#[inline(always)]
fn hermite(va: f64, da: f64, vb: f64, db: f64, t: f64, h: f64) -> (f64, f64) {
    let (t2, t3) = (t * t, t * t * t);
    let v = (2.0 * t3 - 3.0 * t2 + 1.0) * va
        + (t3 - 2.0 * t2 + t) * h * da
        + (-2.0 * t3 + 3.0 * t2) * vb
        + (t3 - t2) * h * db;
    (v, da + t * (db - da))
}

fn hermite_c(
    va: Complex64,
    da: Complex64,
    vb: Complex64,
    db: Complex64,
    t: f64,
    h: f64,
) -> (Complex64, Complex64) {
    let (re, dre) = hermite(va.re, da.re, vb.re, db.re, t, h);
    let (im, dim) = hermite(va.im, da.im, vb.im, db.im, t, h);
    (Complex64::new(re, im), Complex64::new(dre, dim))
}

impl PolCoef {
    fn hermite(
        a: (&PolCoef, &PolCoef),
        b: (&PolCoef, &PolCoef),
        t: f64,
        h: f64,
    ) -> (PolCoef, PolCoef) {
        let f = |va: f64, da: f64, vb: f64, db: f64| hermite(va, da, vb, db, t, h);
        let (av, ad) = f(a.0.a, a.1.a, b.0.a, b.1.a);
        let (bv, bd) = f(a.0.b, a.1.b, b.0.b, b.1.b);
        let (abv, abd) = f(a.0.ab, a.1.ab, b.0.ab, b.1.ab);
        let (pv, pd) = hermite_c(a.0.p, a.1.p, b.0.p, b.1.p, t, h);
        let (uv, ud) = hermite_c(a.0.u, a.1.u, b.0.u, b.1.u, t, h);
        (
            PolCoef {
                a: av,
                b: bv,
                ab: abv,
                p: pv,
                u: uv,
            },
            PolCoef {
                a: ad,
                b: bd,
                ab: abd,
                p: pd,
                u: ud,
            },
        )
    }
}

impl NodeCoef {
    /// The coefficients at fraction `t` of the way from `a` to `b`, two
    /// grid angles `h` radians apart: cubic Hermite in the angle with the
    /// slopes both ends carry (error ~h⁴/384 of the fourth derivative:
    /// ~1e-12 at a 0.25° grid away from critical angles).
    pub(super) fn between(a: &NodeCoef, b: &NodeCoef, t: f64, h: f64) -> NodeCoef {
        let (s, ds) = PolCoef::hermite((&a.s, &a.ds), (&b.s, &b.ds), t, h);
        let (p, dp) = PolCoef::hermite((&a.p, &a.dp), (&b.p, &b.dp), t, h);
        let (k, dk) = hermite_c(a.k, a.dk, b.k, b.dk, t, h);
        NodeCoef {
            s,
            p,
            ds,
            dp,
            k,
            dk,
        }
    }

    /// Coefficients of media `n1 | n2 | n3` at wavenumber factor `w = 4π/λ`,
    /// at the angle whose sine is `sin_t`, with slopes over the step to the
    /// angle whose sine is `sin_h` (`h` radians further).
    pub(super) fn new(n: [Complex64; 3], w: f64, sin_t: f64, sin_h: f64, h: f64) -> NodeCoef {
        let (s, p, q2) = pol_pair(n[0], n[1], n[2], sin_t);
        let (sh, ph, q2h) = pol_pair(n[0], n[1], n[2], sin_h);
        NodeCoef {
            s,
            p,
            ds: s.slope(sh, h),
            dp: p.slope(ph, h),
            k: q2 * w,
            dk: (q2h - q2) * (w / h),
        }
    }

    /// Reflectance of the s/p mix with weight `ws` on s at thickness `d`;
    /// with `deriv`, also dR/dd and dR/dθ.
    #[inline]
    pub(super) fn eval(&self, d: f64, ws: f64, deriv: bool) -> (f64, f64, f64) {
        let phi = self.k.re * d;
        let att = self.k.im * d;
        let e = if att == 0.0 { 1.0 } else { (-att).exp() };
        let (sn, cs) = sin_cos(phi);
        let one = |c: &PolCoef, dc: &PolCoef| -> (f64, f64, f64) {
            // Re(z e^{iφ}) and its φ-derivative Re(i z e^{iφ}).
            let re_p = c.p.re * cs - c.p.im * sn;
            let re_u = c.u.re * cs - c.u.im * sn;
            let n = c.a + c.b * e * e + 2.0 * e * re_p;
            let den = 1.0 + c.ab * e * e + 2.0 * e * re_u;
            if den <= 1e-300 {
                // A lossless resonance with |r12 r23| = 1: total reflection.
                return (1.0, 0.0, 0.0);
            }
            let inv = 1.0 / den;
            let r = n * inv;
            if !deriv {
                return (r, 0.0, 0.0);
            }
            let im_p = -(c.p.re * sn + c.p.im * cs);
            let im_u = -(c.u.re * sn + c.u.im * cs);
            // ∂/∂φ and ∂/∂(Im Δ) (E' = −E).
            let r_phi = 2.0 * e * (im_p - r * im_u) * inv;
            let r_att = (-2.0 * c.b * e * e - 2.0 * e * re_p
                + r * (2.0 * c.ab * e * e + 2.0 * e * re_u))
                * inv;
            let dd = r_phi * self.k.re + r_att * self.k.im;
            let re_dp = dc.p.re * cs - dc.p.im * sn;
            let re_du = dc.u.re * cs - dc.u.im * sn;
            let dn = dc.a + dc.b * e * e + 2.0 * e * re_dp;
            let dden = dc.ab * e * e + 2.0 * e * re_du;
            let dth = (dn - r * dden) * inv + d * (r_phi * self.dk.re + r_att * self.dk.im);
            (r, dd, dth)
        };
        if ws >= 1.0 {
            one(&self.s, &self.ds)
        } else if ws <= 0.0 {
            one(&self.p, &self.dp)
        } else {
            let (r1, d1, t1) = one(&self.s, &self.ds);
            let (r2, d2, t2) = one(&self.p, &self.dp);
            let wp = 1.0 - ws;
            (ws * r1 + wp * r2, ws * d1 + wp * d2, ws * t1 + wp * t2)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::{airy, Media, Polarization};
    use std::f64::consts::PI;

    /// Against the complex Airy summation (a second formulation), and the
    /// derivatives against central differences of it.
    #[test]
    fn matches_complex_airy_for_absorbing_and_tir_stacks() {
        let cases = [
            // Absorbing substrate (silicon-like), lossless film.
            [
                Complex64::new(1.0, 0.0),
                Complex64::new(1.46, 0.0),
                Complex64::new(4.0, 0.05),
            ],
            // Absorbing film on glass.
            [
                Complex64::new(1.0, 0.0),
                Complex64::new(2.4, 0.08),
                Complex64::new(1.52, 0.0),
            ],
            // Glass ambient, air gap (beyond the critical angle at 60°).
            [
                Complex64::new(1.5, 0.0),
                Complex64::new(1.0, 0.0),
                Complex64::new(1.5, 0.0),
            ],
        ];
        let h = 1e-7;
        for n in cases {
            let m = Media {
                n1: n[0],
                n2: n[1],
                n3: n[2],
            };
            for deg in [0.0f64, 25.0, 60.0] {
                let th = deg.to_radians();
                for lam in [420.0, 633.0] {
                    let w = 4.0 * PI / lam;
                    let c = NodeCoef::new(n, w, th.sin(), (th + h).sin(), h);
                    for d in [0.0, 85.0, 730.0] {
                        for (ws, pol) in [
                            (1.0, Polarization::S),
                            (0.0, Polarization::P),
                            (0.5, Polarization::Unpolarized),
                        ] {
                            let (r, dd, dth) = c.eval(d, ws, true);
                            let want = airy::reflectance(m, d, th, lam, pol);
                            assert!(
                                (r - want).abs() < 1e-12,
                                "{n:?} {deg} {lam} {d}: {r} vs {want}"
                            );
                            let e = 1e-4;
                            let fd = (airy::reflectance(m, d + e, th, lam, pol)
                                - airy::reflectance(m, (d - e).max(0.0), th, lam, pol))
                                / (d + e - (d - e).max(0.0));
                            assert!((dd - fd).abs() < 1e-6 * (1.0 + fd.abs()), "dd {dd} vs {fd}");
                            let te = 1e-5;
                            let ft = (airy::reflectance(m, d, th + te, lam, pol)
                                - airy::reflectance(m, d, (th - te).max(0.0), lam, pol))
                                / (th + te - (th - te).max(0.0));
                            assert!(
                                (dth - ft).abs() < 2e-4 * (1.0 + ft.abs()),
                                "dθ {dth} vs {ft}"
                            );
                        }
                    }
                }
            }
        }
    }
}
