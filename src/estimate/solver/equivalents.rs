//! Film indices that reflect exactly as the one found, at the same angle.
//!
//! A lossless film on a lossless substrate reflects, in one polarisation,
//! through its two interfaces' Fresnel coefficients and its phase alone:
//! R = (r12² + r23² + 2 r12 r23 cos δ) / (1 + r12² r23² + 2 r12 r23 cos δ),
//! δ = 4π q2 d / λ. With the interfaces written through their admittances
//! (η = q = n cos θ in s light, η = n² / q in p light), r_ij = (η_i − η_j) /
//! (η_i + η_j), and another film index gives the same R at every
//! wavelength wherever it gives the same pair of coefficients, either way
//! round, with the thickness that keeps q2·d:
//!
//! - the **twin**, η2' = η1·η3 / η2, which swaps r12 and r23 (at normal
//!   incidence n2' = n1·n3 / n2, the paper's twin);
//! - in p light, the **double**: η = n² / √(n² − n1² sin²θ) is not
//!   monotonic in n (least at n² = 2 n1² sin²θ), so a second index shares
//!   η2 itself, n2'² = η2² − n2², and the twin's η has two roots too.
//!
//! With the angle given, the index search meets these as one profile with
//! two minima. With the angle free, each pixel's angle moves too and the
//! profile's minima are sharp: a coarse grid can miss the other one (s
//! light at 45° on 5–300 nm films of 1.46 on silicon read 2.23, its twin,
//! and every thickness 40 % thin and valid). So the search also evaluates
//! the sample at each equivalent of its best index, at the sample's
//! typical angle, each pixel fitted afresh and from its own fit carried
//! over exactly (a fresh fit at the other branch can miss its basin),
//! refines the near ones, and the twin test weighs them all. In unpolarised light
//! neither is exact (s and p would need the same map), but they are where
//! near-equivalents lie, and cost one evaluation each (a refinement where
//! near).

use super::index::SamplePixel;
use super::{Effort, Job, Prepared, Scratch, Solver};
use crate::optics::dispersion::Dispersion;
use rayon::prelude::*;

impl Solver {
    /// One sample pixel's fit under `prep` (d, θ in radians; `None` where
    /// none) and its residual, capped as the profile caps it; its spectrum
    /// is left loaded in `scratch`.
    fn lone_fit(
        &self,
        prep: &Prepared,
        px: &SamplePixel,
        scratch: &mut Scratch,
    ) -> (Option<(f64, f64)>, f64) {
        let (_, sse) = self.solve_with(prep, Job::sample(px), scratch);
        let at = (scratch.last_fit_d, scratch.last_fit_theta);
        let ok = sse.is_finite() && at.0.is_finite() && at.1.is_finite();
        (ok.then_some(at), self.sample_capped(sse, px))
    }

    /// [`Solver::gross_capped`] for a sample pixel's residual: its usable
    /// bands, and one parameter more where its angle is free.
    fn sample_capped(&self, sse: f64, px: &SamplePixel) -> f64 {
        let n_obs = px.spectrum.iter().filter(|v| v.is_finite()).count();
        let p = if px.theta.is_some() { 1 } else { 2 };
        self.gross_capped(sse, n_obs, p)
    }

    /// The indices that reflect exactly as `n` does at the sample's typical
    /// angle (its median known angle, else its fits' median at `n`), each
    /// with the sample's summed residual there less its residual at `n`,
    /// both from the same fits: at the equivalent each pixel also starts
    /// from its fit at `n` carried over exactly (same angle, the thickness
    /// that keeps n2·d·cos θ2), so an exact equivalent shows Δ ≈ 0 whatever
    /// a fresh search finds there.
    pub(super) fn equivalents_of(&self, n: f64, sample: &[SamplePixel]) -> Vec<(f64, f64)> {
        let Ok(prep) = self.prepare_with(&Dispersion::constant(n), false) else {
            return Vec::new();
        };
        let fits: Vec<_> = sample
            .par_iter()
            .map_init(Scratch::default, |scratch, px| {
                self.lone_fit(&prep, px, scratch)
            })
            .collect();
        let mut angles: Vec<f64> = sample
            .iter()
            .zip(&fits)
            .filter_map(|(p, f)| p.theta.or(f.0.map(|a| a.1)))
            .collect();
        if angles.is_empty() {
            return Vec::new();
        }
        let mid = angles.len() / 2;
        let theta = *angles.select_nth_unstable_by(mid, f64::total_cmp).1;
        let (n1, n3) = prep.model.ambient_substrate_mid();
        let w = self.scene.polarization.s_weight();
        let (eq, k) = equivalent_indices(n1.re, n, n3.re, theta, w);
        let at_n: f64 = fits.iter().map(|f| f.1).sum();
        let kx2 = |th: f64| (n1.re * th.sin()).powi(2);
        eq[..k]
            .iter()
            .filter_map(|&m| {
                let prep_m = self.prepare_with(&Dispersion::constant(m), false).ok()?;
                let carried: f64 = sample
                    .par_iter()
                    .zip(&fits)
                    .map_init(Scratch::default, |scratch, (px, f)| {
                        // The fresh fit, which leaves the pixel's spectrum
                        // loaded for the carried one's refinement.
                        let fresh = self.lone_fit(&prep_m, px, scratch).1;
                        let Some((d, th)) = f.0 else {
                            return fresh;
                        };
                        let q = |x: f64| (x * x - kx2(th)).max(1e-12).sqrt();
                        scratch.cur_at = None;
                        let free = px.theta.is_none();
                        let fit = self.refine(
                            &prep_m.model,
                            d * q(n) / q(m),
                            th,
                            free,
                            Effort::INDEX_SEARCH.iters,
                            scratch,
                        );
                        if fit.sse.is_finite() {
                            fresh.min(self.sample_capped(fit.sse, px))
                        } else {
                            fresh
                        }
                    })
                    .sum();
                Some((m, carried - at_n))
            })
            .collect()
    }
}

/// The equivalent indices of a film of index `n2` between an ambient `n1`
/// and a substrate `n3` seen at `theta` (rad) in light whose s share is
/// `s_weight`: up to three indices above the ambient's, none equal to
/// `n2` itself.
pub(super) fn equivalent_indices(
    n1: f64,
    n2: f64,
    n3: f64,
    theta: f64,
    s_weight: f64,
) -> ([f64; 3], usize) {
    let mut out = [f64::NAN; 3];
    let mut k = 0;
    let a = (n1 * theta.sin()).powi(2);
    let q = |n: f64| (n * n - a).max(0.0).sqrt();
    let (q1, q2, q3) = (q(n1), q(n2), q(n3));
    let mut push = |x: f64| {
        // x = n'², a film index above the ambient's, not n2 again.
        let fresh = |m: f64| (m - n2).abs() > 1e-6 && out[..k].iter().all(|o| (o - m).abs() > 1e-6);
        if x.is_finite() && x > a && x.sqrt() > n1 && fresh(x.sqrt()) && k < 3 {
            out[k] = x.sqrt();
            k += 1;
        }
    };
    if q1 <= 0.0 || q2 <= 0.0 || q3 <= 0.0 {
        return (out, 0);
    }
    if s_weight > 0.0 {
        // s: η = q, so q2' = q1·q3 / q2.
        let q2t = q1 * q3 / q2;
        push(q2t * q2t + a);
    }
    if s_weight < 1.0 {
        // p: η = n² / q; n'² = x solves x² − η'² x + η'² a = 0.
        let eta = |n: f64, q: f64| n * n / q;
        let (e1, e2, e3) = (eta(n1, q1), eta(n2, q2), eta(n3, q3));
        let twin = e1 * e3 / e2;
        let t2 = twin * twin;
        let disc = t2 * t2 - 4.0 * t2 * a;
        if disc >= 0.0 {
            push(0.5 * (t2 + disc.sqrt()));
            push(0.5 * (t2 - disc.sqrt()));
        }
        // The double: the other root of η2's own quadratic.
        push(e2 * e2 - n2 * n2);
    }
    (out, k)
}

#[cfg(test)]
mod tests {
    use super::equivalent_indices;
    use crate::optics::tmm::{self, Layer};
    use crate::optics::{Complex64, Polarization};

    /// Every equivalent reflects as the original at every wavelength, by
    /// the characteristic-matrix method (not the Airy form the module's
    /// argument uses), thickness scaled to keep q2·d.
    #[test]
    fn equivalents_reflect_alike_by_the_characteristic_matrix() {
        let c = |x: f64| Complex64::new(x, 0.0);
        let mut checked = 0;
        for (n2, n3) in [(1.38, 1.6), (1.46, 3.88), (2.1, 1.52), (1.2, 1.5)] {
            for deg in [0.0f64, 20.0, 45.0, 65.0, 80.0] {
                let th = deg.to_radians();
                for (pol, w) in [(Polarization::S, 1.0), (Polarization::P, 0.0)] {
                    let (eq, k) = equivalent_indices(1.0, n2, n3, th, w);
                    let q = |n: f64| (n * n - th.sin().powi(2)).sqrt();
                    for &m in &eq[..k] {
                        let d = 180.0;
                        let dm = d * q(n2) / q(m);
                        for lam in [400.0, 473.0, 550.0, 612.0, 700.0] {
                            let r = |n: f64, d: f64| {
                                let film = [Layer::real(n, d)];
                                tmm::reflectance(c(1.0), &film, c(n3), th, lam, pol)
                            };
                            let (r0, r1) = (r(n2, d), r(m, dm));
                            assert!(
                                (r0 - r1).abs() < 1e-12,
                                "{pol:?} {deg}° n2 {n2} on {n3}: {m} gives {r1} for {r0} at {lam}"
                            );
                        }
                        checked += 1;
                    }
                }
            }
        }
        // s light always has its twin (above the ambient here); p light
        // adds doubles and its twin's roots where they exist.
        assert!(checked >= 40, "{checked} equivalents checked");
    }

    /// At normal incidence the twin is the paper's n1·n3 / n2 (s and p
    /// alike), and the p double coincides with n2 itself (no other index).
    #[test]
    fn the_normal_incidence_twin_is_the_papers() {
        for w in [1.0, 0.0, 0.5] {
            let (eq, k) = equivalent_indices(1.0, 1.38, 1.6, 0.0, w);
            assert!(k >= 1);
            assert!(
                eq[..k].iter().all(|&m| (m - 1.6 / 1.38).abs() < 1e-12),
                "{eq:?}"
            );
        }
    }
}
