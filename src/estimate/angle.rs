//! Incidence angle from the half-wave reflectance (paper Eq. 8–11), inverted
//! exactly.
//!
//! At a half-wave point (`cos Δ = 1`) the film is an absentee layer: the
//! reflectance is the bare ambient/substrate interface's, whatever the film
//! (Eq. 9–10). For lossless media the Fresnel coefficient of that interface
//! can be solved for the angle in closed form. With `t = q3/q1`
//! (`q = n cos θ`):
//!
//! - s: `r = (q1 − q3)/(q1 + q3)` ⇒ `t = (1 − r)/(1 + r)`;
//! - p: `r = (n3² q1 − n1² q3)/(n3² q1 + n1² q3)` ⇒ `t = (n3²/n1²)(1 − r)/(1 + r)`;
//!
//! and `q3² = n3² − n1² sin² θ`, `q1² = n1² (1 − sin² θ)` give
//! `sin² θ = (t² n1² − n3²) / (n1² (t² − 1))`.
//!
//! `R = r²` leaves the sign of `r` open. For s (and for p below Brewster's
//! angle when `n3 > n1`) one sign is physical; for p both signs give an
//! angle, one each side of Brewster's angle, and the caller must choose (the
//! quarter-wave level or a prior does). Unpolarised light has no closed form:
//! [`half_wave_angles`] returns nothing and the caller inverts numerically.

use crate::optics::Polarization;

/// The angles (radians, in \[0, π/2)) whose bare-interface reflectance for
/// `pol` equals `r_half`, for real indices `n1` (ambient) and `n3`
/// (substrate). At most two; none for unpolarised or mixed light, or when
/// no angle produces that reflectance.
pub fn half_wave_angles(r_half: f64, n1: f64, n3: f64, pol: Polarization) -> [Option<f64>; 2] {
    half_wave_sin2(r_half, n1, n3, pol).map(|s2| s2.map(|s2| s2.sqrt().asin()))
}

/// As [`half_wave_angles`], as `sin² θ` (what the thickness needs; the
/// angle itself costs an arcsine more).
pub fn half_wave_sin2(r_half: f64, n1: f64, n3: f64, pol: Polarization) -> [Option<f64>; 2] {
    let mut out = [None, None];
    if !(r_half.is_finite() && (0.0..1.0).contains(&r_half) && n1 > 0.0 && n3 > 0.0) {
        return out;
    }
    let scale = match pol {
        Polarization::S => 1.0,
        Polarization::P => (n3 * n3) / (n1 * n1),
        _ => return out,
    };
    let root = r_half.sqrt();
    for (slot, r) in out.iter_mut().zip([root, -root]) {
        // t = a/c, and sin²θ with numerator and denominator times c² (one
        // division instead of two; c = 1 + r > 0 as |r| < 1).
        let (a, c) = (scale * (1.0 - r), 1.0 + r);
        let den = n1 * n1 * (a * a - c * c);
        if den == 0.0 {
            continue;
        }
        let s2 = (a * a * n1 * n1 - n3 * n3 * c * c) / den;
        if (0.0..1.0).contains(&s2) {
            *slot = Some(s2);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::airy::bare_reflectance;
    use crate::optics::Complex64;

    fn forward(theta: f64, n1: f64, n3: f64, pol: Polarization) -> f64 {
        bare_reflectance(Complex64::new(n1, 0.0), Complex64::new(n3, 0.0), theta, pol)
    }

    #[test]
    fn s_inversion_round_trips_through_the_airy_model() {
        for (n1, n3) in [(1.0, 1.6), (1.0, 1.5), (1.33, 1.6), (1.0, 3.5)] {
            for deg in [0.5, 10.0, 20.0, 42.5, 60.0, 85.0] {
                let th = f64::to_radians(deg);
                let r = forward(th, n1, n3, Polarization::S);
                let sols: Vec<f64> = half_wave_angles(r, n1, n3, Polarization::S)
                    .into_iter()
                    .flatten()
                    .collect();
                assert_eq!(sols.len(), 1, "{n1} {n3} {deg}: {sols:?}");
                assert!((sols[0] - th).abs() < 1e-9, "{n1} {n3} {deg}: {sols:?}");
            }
        }
    }

    #[test]
    fn p_inversion_gives_both_sides_of_brewster() {
        let (n1, n3) = (1.0f64, 1.6f64);
        let brewster = (n3 / n1).atan();
        for deg in [10.0, 30.0, 50.0, 70.0, 80.0] {
            let th = f64::to_radians(deg);
            let r = forward(th, n1, n3, Polarization::P);
            let sols: Vec<f64> = half_wave_angles(r, n1, n3, Polarization::P)
                .into_iter()
                .flatten()
                .collect();
            assert!(
                sols.iter().any(|s| (s - th).abs() < 1e-8),
                "{deg}: {sols:?}"
            );
            // Any second solution lies on the other side of Brewster's angle
            // and reproduces the same reflectance.
            for s in &sols {
                assert!((forward(*s, n1, n3, Polarization::P) - r).abs() < 1e-12);
                if (s - th).abs() > 1e-8 {
                    assert!((s - brewster) * (th - brewster) < 0.0);
                }
            }
        }
    }

    #[test]
    fn impossible_levels_give_no_angle() {
        // Below the normal-incidence value no s angle exists.
        let r0 = forward(0.0, 1.0, 1.6, Polarization::S);
        assert_eq!(
            half_wave_angles(r0 * 0.5, 1.0, 1.6, Polarization::S),
            [None, None]
        );
        assert_eq!(
            half_wave_angles(f64::NAN, 1.0, 1.6, Polarization::S),
            [None, None]
        );
        assert_eq!(
            half_wave_angles(0.05, 1.0, 1.6, Polarization::Unpolarized),
            [None, None]
        );
    }
}
