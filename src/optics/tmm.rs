//! Characteristic-matrix (Abelès / transfer-matrix) method for a stack of any
//! number of layers between an ambient and a substrate.
//!
//! This is deliberately a second, independent formulation of the physics in
//! [`super::airy`]: it shares no code with it (it has its own normal
//! components, its own Fresnel algebra), so agreement between the two is a
//! real check. It also gives transmittance, which the Airy module does not.
//!
//! # Formulation
//!
//! Time dependence `e^{−iωt}`, indices `n + ik` with `k ≥ 0`. With the Snell
//! invariant `kx = n_amb sin θ1`, each medium has the normal component
//! `q = n cos θ = sqrt(n² − kx²)` on the branch `Im q ≥ 0` (fields decay away
//! from the interface they come from; for lossless media past the critical
//! angle `q` is imaginary). Each polarisation is described by a pair of
//! tangential fields and an admittance `η`:
//!
//! - s: (E_y, H_x), `η = q`;
//! - p: (H_y, E_x), `η = q / n²` (the impedance of the TM wave; using it
//!   rather than the admittance `n²/q` keeps grazing incidence, `q → 0`, finite).
//!
//! A layer of thickness `d` has phase thickness `δ = 2π q d / λ` and maps the
//! fields at its bottom to those at its top by
//!
//! ```text
//! M = [[cos δ, −i sin δ / η], [−i η sin δ, cos δ]]
//! ```
//!
//! (the sign of `i` follows from `e^{−iωt}`). With `[B, C] = M₁ M₂ … [1, η_sub]`:
//!
//! ```text
//! r = (η₀ B − C) / (η₀ B + C),   t = 2 η₀ / (η₀ B + C)
//! R = |r|²,                      T = Re(η_sub) / Re(η₀) · |t|²
//! ```
//!
//! For s this is `T = Re(q_sub)/Re(q_amb) |t_E|²`; for p, `t` is the ratio of
//! the magnetic fields and `T = Re(q_sub/n_sub²)/Re(q_amb/n_amb²) |t_H|²`,
//! which is where the `n²` factors go. Both measure the power flux just inside
//! the substrate, so `R + T = 1` whenever ambient and layers are lossless,
//! even for an absorbing substrate (that is where `T` is absorbed).
//! The sign conventions make `r_s`, `r_p` the same complex numbers as
//! [`super::airy::amplitude`] returns.
//!
//! # Promises
//!
//! No panics. Evanescent and absorbing layers make `cos δ`, `sin δ` grow like
//! `e^{|Im δ|}`; each layer matrix is computed already divided by that factor
//! (the reflection coefficient is a ratio and does not see it; `t` is
//! multiplied back by `e^{−Σ|Im δ|}`), so thick evanescent gaps and strongly
//! absorbing layers neither overflow nor lose precision. Outputs are finite
//! for finite, physical input (`n ≠ 0`, `d ≥ 0`, `λ > 0`); `R` and `T` are not
//! clamped, so round-off shows rather than hides.

use super::{Complex64, Media, Polarization};
use std::f64::consts::PI;

/// One homogeneous layer: complex index and thickness in nm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Layer {
    /// Complex index `n + ik`.
    pub n: Complex64,
    /// Thickness, nm.
    pub d_nm: f64,
}

impl Layer {
    /// A layer with a complex index.
    pub fn new(n: Complex64, d_nm: f64) -> Self {
        Layer { n, d_nm }
    }

    /// A lossless layer.
    pub fn real(n: f64, d_nm: f64) -> Self {
        Layer {
            n: Complex64::new(n, 0.0),
            d_nm,
        }
    }
}

/// Amplitude and power coefficients of a stack for both polarisations.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Response {
    /// Amplitude reflection coefficient, s (ratio of E_y).
    pub r_s: Complex64,
    /// Amplitude reflection coefficient, p (ratio of H_y).
    pub r_p: Complex64,
    /// Amplitude transmission coefficient into the substrate, s (ratio of E_y).
    pub t_s: Complex64,
    /// Amplitude transmission coefficient into the substrate, p (ratio of H_y).
    pub t_p: Complex64,
    /// Reflectance `|r_s|²`.
    pub reflectance_s: f64,
    /// Reflectance `|r_p|²`.
    pub reflectance_p: f64,
    /// Transmittance (power into the substrate), s.
    pub transmittance_s: f64,
    /// Transmittance (power into the substrate), p.
    pub transmittance_p: f64,
}

const ZERO: Complex64 = Complex64::new(0.0, 0.0);
const ONE: Complex64 = Complex64::new(1.0, 0.0);
const I: Complex64 = Complex64::new(0.0, 1.0);

/// `sqrt(n² − kx²)` on the branch with `Im ≥ 0` (and `Re ≥ 0` when real).
fn decaying_sqrt(z: Complex64) -> Complex64 {
    let w = z.sqrt();
    if w.im < 0.0 || (w.im == 0.0 && w.re < 0.0) {
        -w
    } else {
        w
    }
}

/// `(cos δ, sin δ/δ) · e^{−|Im δ|}` and `sin δ · e^{−|Im δ|}`, overflow-free.
fn scaled_trig(delta: Complex64) -> (Complex64, Complex64, Complex64) {
    let s = delta.im.abs();
    // e^{±iδ − s} both have non-positive real exponents.
    let ep = (I * delta - s).exp();
    let em = (-I * delta - s).exp();
    let cos = (ep + em) * 0.5;
    let sin = (ep - em) / (2.0 * I);
    let sinc = if delta.norm() < 1e-4 {
        // sin δ/δ = 1 − δ²/6 + δ⁴/120; here e^{−s} ≈ 1 − s is kept exactly.
        let d2 = delta * delta;
        (ONE - d2 / 6.0 + d2 * d2 / 120.0) * (-s).exp()
    } else {
        sin / delta
    };
    (cos, sin, sinc)
}

/// r, t for one polarisation. `eta` maps (n, q) to the admittance; `q_over_eta`
/// is `q/η` (1 for s, `n²` for p), used for the `sin δ / η` entry so that a
/// layer with `q = 0` stays finite.
fn solve(
    ambient: Complex64,
    layers: &[Layer],
    substrate: Complex64,
    kx: Complex64,
    wavelength_nm: f64,
    p: bool,
) -> (Complex64, Complex64, f64) {
    let eta = |n: Complex64, q: Complex64| if p { q / (n * n) } else { q };
    let q0 = decaying_sqrt(ambient * ambient - kx * kx);
    let qs = decaying_sqrt(substrate * substrate - kx * kx);
    let eta0 = eta(ambient, q0);
    let eta_sub = eta(substrate, qs);

    // Multiply from the substrate upwards: [B, C] = M₁ (M₂ (… [1, η_sub])).
    let (mut b, mut c) = (ONE, eta_sub);
    let mut log_scale = 0.0;
    let k0 = 2.0 * PI / wavelength_nm;
    for layer in layers.iter().rev() {
        let q = decaying_sqrt(layer.n * layer.n - kx * kx);
        let e = eta(layer.n, q);
        let delta = q * (k0 * layer.d_nm);
        let (cos, sin, sinc) = scaled_trig(delta);
        // sin δ / η = k0 d (q/η) sinc δ.
        let q_over_eta = if p { layer.n * layer.n } else { ONE };
        let m12 = -I * q_over_eta * (k0 * layer.d_nm) * sinc;
        let m21 = -I * e * sin;
        let (nb, nc) = (cos * b + m12 * c, m21 * b + cos * c);
        // Keep [B, C] of order one; the common factor only affects t.
        let norm = nb.norm().max(nc.norm());
        if norm > 0.0 && norm.is_finite() {
            b = nb / norm;
            c = nc / norm;
            log_scale += delta.im.abs() + norm.ln();
        } else {
            b = nb;
            c = nc;
            log_scale += delta.im.abs();
        }
    }
    let den = eta0 * b + c;
    if den == ZERO {
        // Only reachable at exact grazing incidence onto a stack that
        // presents zero admittance too: nothing enters, all is reflected.
        return (-ONE, ZERO, 0.0);
    }
    let r = (eta0 * b - c) / den;
    let t = 2.0 * eta0 / den * (-log_scale).exp();
    let flux_in = eta0.re;
    let big_t = if flux_in > 0.0 {
        eta_sub.re / flux_in * t.norm_sqr()
    } else {
        0.0
    };
    (r, t, big_t)
}

/// Amplitude and power coefficients of the stack `ambient | layers… | substrate`
/// (layers listed from the ambient side) at incidence `theta1_rad` in the
/// ambient and vacuum wavelength `wavelength_nm`.
pub fn response(
    ambient: Complex64,
    layers: &[Layer],
    substrate: Complex64,
    theta1_rad: f64,
    wavelength_nm: f64,
) -> Response {
    let kx = ambient * theta1_rad.sin();
    let (r_s, t_s, ts) = solve(ambient, layers, substrate, kx, wavelength_nm, false);
    let (r_p, t_p, tp) = solve(ambient, layers, substrate, kx, wavelength_nm, true);
    Response {
        r_s,
        r_p,
        t_s,
        t_p,
        reflectance_s: r_s.norm_sqr(),
        reflectance_p: r_p.norm_sqr(),
        transmittance_s: ts,
        transmittance_p: tp,
    }
}

/// Reflectances `(R_s, R_p)` of the stack.
pub fn reflectance_sp(
    ambient: Complex64,
    layers: &[Layer],
    substrate: Complex64,
    theta1_rad: f64,
    wavelength_nm: f64,
) -> (f64, f64) {
    let r = response(ambient, layers, substrate, theta1_rad, wavelength_nm);
    (r.reflectance_s, r.reflectance_p)
}

/// Transmittances `(T_s, T_p)` into the substrate (power flux just inside it,
/// relative to the incident flux).
pub fn transmittance_sp(
    ambient: Complex64,
    layers: &[Layer],
    substrate: Complex64,
    theta1_rad: f64,
    wavelength_nm: f64,
) -> (f64, f64) {
    let r = response(ambient, layers, substrate, theta1_rad, wavelength_nm);
    (r.transmittance_s, r.transmittance_p)
}

/// Observed reflectance for the given polarisation.
pub fn reflectance(
    ambient: Complex64,
    layers: &[Layer],
    substrate: Complex64,
    theta1_rad: f64,
    wavelength_nm: f64,
    pol: Polarization,
) -> f64 {
    let (rs, rp) = reflectance_sp(ambient, layers, substrate, theta1_rad, wavelength_nm);
    let w = pol.s_weight();
    w * rs + (1.0 - w) * rp
}

/// [`response`] for the single-film stack of [`Media`] (the Airy geometry).
pub fn film_response(media: Media, d_nm: f64, theta1_rad: f64, wavelength_nm: f64) -> Response {
    response(
        media.n1,
        &[Layer::new(media.n2, d_nm)],
        media.n3,
        theta1_rad,
        wavelength_nm,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bare_interface_normal_incidence() {
        // ((1 − 1.5)/(1 + 1.5))² = 0.04; T = 0.96.
        let r = response(ONE, &[], Complex64::new(1.5, 0.0), 0.0, 500.0);
        assert!((r.reflectance_s - 0.04).abs() < 1e-15);
        assert!((r.transmittance_p - 0.96).abs() < 1e-15);
    }

    #[test]
    fn quarter_wave_antireflection() {
        // n2 = sqrt(n1 n3), n2 d = λ/4: R = 0 exactly at normal incidence.
        let n3 = 1.69f64;
        let n2 = n3.sqrt();
        let lam = 550.0;
        let (rs, rp) = reflectance_sp(
            ONE,
            &[Layer::real(n2, lam / (4.0 * n2))],
            Complex64::new(n3, 0.0),
            0.0,
            lam,
        );
        assert!(rs < 1e-28 && rp < 1e-28, "{rs} {rp}");
    }

    #[test]
    fn thick_evanescent_gap_does_not_overflow() {
        // 1e6 nm of air between glass beyond the critical angle: |Im δ| ~ 1e4.
        let g = Complex64::new(1.5, 0.0);
        let r = response(g, &[Layer::real(1.0, 1e6)], g, 1.2, 500.0);
        assert!(
            (r.reflectance_s - 1.0).abs() < 1e-12 && r.transmittance_s == 0.0,
            "{r:?}"
        );
        assert!(
            (r.reflectance_p - 1.0).abs() < 1e-12 && r.transmittance_p == 0.0,
            "{r:?}"
        );
    }
}
