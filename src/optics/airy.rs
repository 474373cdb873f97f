//! Single-film reflectance by the Airy summation (paper Eq. 4–7).
//!
//! `r = (r12 + r23 e^{iΔ}) / (1 + r12 r23 e^{iΔ})`, `R = |r|²`, with Fresnel
//! coefficients written in terms of the normal wave-vector components
//! `q_j = n_j cos θ_j = sqrt(n_j² − (n1 sin θ1)²)`. Choosing the root with
//! `Im q ≥ 0` makes total internal reflection, absorbing media and grazing
//! incidence come out finite and physical without special cases.
//!
//! [`RealFilm`] is the fast path for lossless media below the critical angle,
//! where every coefficient is real and `R` depends on thickness only through
//! `cos Δ` (see the paper page, "Cost structure").

use super::{Complex64, Media, Polarization};
use std::f64::consts::PI;

/// Normal component `n cos θ` of the wave vector in a medium of index `n`,
/// for the Snell invariant `kx = n1 sin θ1`, with the decaying branch (`Im ≥ 0`).
pub fn normal_component(n: Complex64, kx: Complex64) -> Complex64 {
    let q = (n * n - kx * kx).sqrt();
    // `sqrt` returns the principal root (Re ≥ 0); flip to the decaying branch.
    if q.im < 0.0 || (q.im == 0.0 && q.re < 0.0) {
        -q
    } else {
        q
    }
}

/// Fresnel amplitude reflection coefficient for s polarisation (Eq. 6),
/// written with normal components `qi = ni cos θi`.
pub fn fresnel_s(qi: Complex64, qj: Complex64) -> Complex64 {
    let den = qi + qj;
    if den.norm_sqr() == 0.0 {
        // Both components vanish only at exact grazing incidence between
        // equal media: nothing to reflect off.
        return Complex64::new(0.0, 0.0);
    }
    (qi - qj) / den
}

/// Fresnel amplitude reflection coefficient for p polarisation (Eq. 7):
/// `(nj² qi − ni² qj) / (nj² qi + ni² qj)`, which equals
/// `(nj cos θi − ni cos θj) / (nj cos θi + ni cos θj)`.
pub fn fresnel_p(ni: Complex64, nj: Complex64, qi: Complex64, qj: Complex64) -> Complex64 {
    let a = nj * nj * qi;
    let b = ni * ni * qj;
    let den = a + b;
    if den.norm_sqr() == 0.0 {
        return Complex64::new(0.0, 0.0);
    }
    (a - b) / den
}

/// Amplitude reflection coefficients `(r_s, r_p)` of the film stack.
pub fn amplitude(
    media: Media,
    d_nm: f64,
    theta1: f64,
    wavelength_nm: f64,
) -> (Complex64, Complex64) {
    let kx = media.n1 * theta1.sin();
    let q1 = normal_component(media.n1, kx);
    let q2 = normal_component(media.n2, kx);
    let q3 = normal_component(media.n3, kx);
    // e^{iΔ} with Δ = 4π d q2 / λ (Eq. 2–3 with φ = 2 d n2 cos θ2).
    let phase = Complex64::new(0.0, 4.0 * PI * d_nm / wavelength_nm) * q2;
    let e = phase.exp();
    let combine = |r12: Complex64, r23: Complex64| {
        let num = r12 + r23 * e;
        let den = Complex64::new(1.0, 0.0) + r12 * r23 * e;
        if den.norm_sqr() == 0.0 {
            // |r12 r23| = 1 with the phase against it: a lossless resonance
            // that only an exactly tuned, perfectly reflecting pair reaches.
            Complex64::new(1.0, 0.0)
        } else {
            num / den
        }
    };
    let rs = combine(fresnel_s(q1, q2), fresnel_s(q2, q3));
    let rp = combine(
        fresnel_p(media.n1, media.n2, q1, q2),
        fresnel_p(media.n2, media.n3, q2, q3),
    );
    (rs, rp)
}

/// Reflectances `(R_s, R_p)` of a film of thickness `d_nm` at incidence
/// `theta1` (radians, in the ambient) and vacuum wavelength `wavelength_nm`.
pub fn reflectance_sp(media: Media, d_nm: f64, theta1: f64, wavelength_nm: f64) -> (f64, f64) {
    let (rs, rp) = amplitude(media, d_nm, theta1, wavelength_nm);
    (rs.norm_sqr().min(1.0), rp.norm_sqr().min(1.0))
}

/// Observed reflectance for the given polarisation (Eq. 5).
pub fn reflectance(
    media: Media,
    d_nm: f64,
    theta1: f64,
    wavelength_nm: f64,
    pol: Polarization,
) -> f64 {
    let (rs, rp) = reflectance_sp(media, d_nm, theta1, wavelength_nm);
    let w = pol.s_weight();
    w * rs + (1.0 - w) * rp
}

/// Reflectance of the bare interface between ambient and substrate (d = 0);
/// for `n1 < n2 < n3` this is also the film's reflectance at its half-wave
/// points (Eq. 9–10).
pub fn bare_reflectance(n1: Complex64, n3: Complex64, theta1: f64, pol: Polarization) -> f64 {
    reflectance(Media { n1, n2: n1, n3 }, 0.0, theta1, 550.0, pol)
}

/// Real Fresnel coefficients of a lossless film below every critical angle,
/// for one polarisation at one band: `R(Δ) = (a + b cos Δ) / (c + b cos Δ)`
/// with `a = r12² + r23²`, `b = 2 r12 r23`, `c = 1 + r12² r23²`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RealFilm {
    /// Ambient/film coefficient.
    pub r12: f64,
    /// Film/substrate coefficient.
    pub r23: f64,
}

impl RealFilm {
    /// `R` for the given `cos Δ`.
    #[inline]
    pub fn reflectance(self, cos_delta: f64) -> f64 {
        let b = 2.0 * self.r12 * self.r23;
        let a = self.r12 * self.r12 + self.r23 * self.r23;
        let c = 1.0 + self.r12 * self.r12 * self.r23 * self.r23;
        (a + b * cos_delta) / (c + b * cos_delta)
    }

    /// Reflectance at the half-wave points (`cos Δ = 1`): the bare substrate's
    /// when `r12 r23 > 0` (a peak for n1 < n2 < n3), a valley otherwise.
    #[inline]
    pub fn half_wave(self) -> f64 {
        self.reflectance(1.0)
    }

    /// Reflectance at the quarter-wave points (`cos Δ = −1`).
    #[inline]
    pub fn quarter_wave(self) -> f64 {
        self.reflectance(-1.0)
    }
}

/// Real-coefficient s and p Fresnel pairs for lossless media at real angles
/// below any critical angle; `None` where a normal component is not real
/// (total internal reflection), where the complex path is needed.
pub fn real_film(n1: f64, n2: f64, n3: f64, sin_theta1: f64) -> Option<(RealFilm, RealFilm)> {
    let kx2 = (n1 * sin_theta1).powi(2);
    let q1sq = n1 * n1 - kx2;
    let q2sq = n2 * n2 - kx2;
    let q3sq = n3 * n3 - kx2;
    if q1sq < 0.0 || q2sq <= 0.0 || q3sq <= 0.0 {
        return None;
    }
    let (q1, q2, q3) = (q1sq.sqrt(), q2sq.sqrt(), q3sq.sqrt());
    let s = RealFilm {
        r12: (q1 - q2) / (q1 + q2),
        r23: (q2 - q3) / (q2 + q3),
    };
    let p12 = n2 * n2 * q1 + n1 * n1 * q2;
    let p23 = n3 * n3 * q2 + n2 * n2 * q3;
    let p = RealFilm {
        r12: (n2 * n2 * q1 - n1 * n1 * q2) / p12,
        r23: (n3 * n3 * q2 - n2 * n2 * q3) / p23,
    };
    Some((s, p))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn normal_incidence_bare_interface_matches_textbook() {
        // ((n1 − n3)/(n1 + n3))² for glass in air: 0.04 at n = 1.5.
        let r = reflectance(Media::real(1.0, 1.0, 1.5), 0.0, 0.0, 500.0, Polarization::S);
        assert!(close(r, 0.04, 1e-15), "{r}");
    }

    #[test]
    fn real_fast_path_agrees_with_complex_path() {
        let (n1, n2, n3) = (1.0, 1.37, 1.6);
        for deg in [0.0, 10.0, 35.0, 70.0] {
            let th = f64::to_radians(deg);
            let (s, p) = real_film(n1, n2, n3, th.sin()).unwrap();
            for lam in [400.0, 517.0, 700.0] {
                let d = 480.0;
                let q2 = (n2 * n2 - th.sin().powi(2)).sqrt();
                let cd = (4.0 * PI * d * q2 / lam).cos();
                let (rs, rp) = reflectance_sp(Media::real(n1, n2, n3), d, th, lam);
                assert!(close(s.reflectance(cd), rs, 1e-13));
                assert!(close(p.reflectance(cd), rp, 1e-13));
            }
        }
    }

    #[test]
    fn total_internal_reflection_is_finite_and_total() {
        // Glass ambient onto an air film on glass, beyond the critical angle:
        // a thick air gap reflects everything (frustrated TIR vanishes).
        let m = Media::real(1.5, 1.0, 1.5);
        let th = f64::to_radians(60.0);
        let (rs, rp) = reflectance_sp(m, 5000.0, th, 500.0);
        assert!(close(rs, 1.0, 1e-9) && close(rp, 1.0, 1e-9), "{rs} {rp}");
        // A thin gap lets some light tunnel through.
        let (rs, _) = reflectance_sp(m, 50.0, th, 500.0);
        assert!(rs.is_finite() && rs < 1.0 && rs > 0.0);
    }
}
