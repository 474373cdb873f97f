//! The image's fit as a whole. A misfit too small for any one pixel's χ²
//! test but shared by the image's pixels — the wrong polarisation, a film
//! or substrate the film index and the angles absorb in part — is seen in
//! the residuals of neighbouring pixels: their noise is independent, so
//! where the model holds their residuals are uncorrelated, while a misfit
//! of the model is the same in two pixels of nearly the same film and
//! angle. The image is then rejected: every pixel is flagged "poor fit"
//! with the reason in the level's note, since the global estimates (film
//! index, level, angles) that every thickness rests on are fitted to a
//! model the data refute.
//!
//! The test needs no noise level beyond the units of the misfit it
//! reports: a noise σ estimated a few percent low (as the model-free
//! estimate runs on small images) scales the shared misfit by as much,
//! but cannot make uncorrelated residuals correlated. Where the scene
//! gives a reflectance-scale accuracy ε > 0, a scale error is a misfit it
//! expects every pixel to share (σ carries it), and each residual's
//! component along its model is taken out first. Pairs with a gross
//! misfit (defects, films past the resolved range) are left out: they are
//! flagged one by one and say nothing about the rest.

#[cfg(doc)]
use super::index::IMAGE_FIT_PAIRS;
use super::{Scratch, Solver};
use crate::estimate::level::{Level, LevelMode, LevelPixel};
use crate::estimate::noise::NoiseModel;
use crate::estimate::quality::chi2_upper_quantile;
use crate::estimate::Cube;

/// The smallest shared misfit that rejects an image, in noise variances
/// per band: a misfit 3 % of the noise's variance, common to neighbouring
/// pixels. (The paper's cylinder in unpolarised light fitted as
/// s-polarised shares 0.07, z 8; clean scenes 0 within their scatter;
/// with at most [`IMAGE_FIT_PAIRS`] pairs of 29 degrees of freedom the
/// z threshold alone asks for ≥ 0.042.)
pub(super) const MAX_SHARED: f64 = 0.03;
/// ... and it must stand out of its scatter by this many standard errors.
pub(super) const MIN_Z: f64 = 5.0;
/// Fewest pairs for the test.
const MIN_PAIRS: usize = 20;
/// A pixel's χ² above this upper quantile is a gross misfit, left out.
const GROSS_P: f64 = 1e-4;

/// Neighbouring pixels' residuals against the noise model.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct ImageFit {
    /// Pairs of neighbouring pixels weighed (both fitted, neither gross).
    pub pairs: usize,
    /// Median over pairs of the residuals' product per band, in noise
    /// variances: the misfit the two pixels share (0 where the model holds).
    pub shared: f64,
    /// `shared` in standard errors of its median under the model.
    pub z: f64,
    /// The pixels' mean χ² per degree of freedom.
    pub chi2_dof: f64,
}

impl ImageFit {
    /// Whether the image's pixels share a misfit beyond their noise.
    pub fn rejected(&self) -> bool {
        self.pairs >= MIN_PAIRS && self.shared > MAX_SHARED && self.z > MIN_Z
    }
}

impl Solver {
    /// About `max` pairs of horizontally neighbouring pixels of `cube`,
    /// each fitted under the index and level in force; `None` where the
    /// test does not apply (no independent noise level, a free level, a
    /// noise level raised to the fits' own residual, an image one pixel
    /// wide). Fewer than `MIN_PAIRS` pairs never reject.
    pub(super) fn image_fit(&self, cube: &Cube, max: usize) -> Option<ImageFit> {
        let noise = self.noise.as_ref()?;
        if self.level_mode == LevelMode::Free || self.residual_noise_floor || cube.width < 2 {
            return None;
        }
        let mut scratch = Scratch::default();
        let mut spec = vec![0.0; cube.bands.len()];
        let mut pixels = Vec::new();
        for (x, y) in Self::sample_sites(cube, max) {
            let x2 = if x + 1 < cube.width { x + 1 } else { x - 1 };
            let a = self.sample_at(cube, x, y, false, &mut spec, &mut scratch);
            let b = self.sample_at(cube, x2, y, false, &mut spec, &mut scratch);
            if let (Some(a), Some(b)) = (a, b) {
                pixels.push(a);
                pixels.push(b);
            }
        }
        let fits = self.level_pixels(&pixels, &self.level);
        // A reflectance scale accurate to ε > 0 is a misfit every pixel
        // may share by the scene's own account (σ carries it): the test
        // then weighs what is left beside the scale.
        let scale_free = noise.accuracy() > 0.0;
        let nb = self.bands.len();
        let (mut e_a, mut e_b) = (vec![f64::NAN; nb], vec![f64::NAN; nb]);
        let mut shared = Vec::with_capacity(fits.len() / 2);
        let (mut dof_sum, mut chi2_sum) = (0.0, 0.0);
        for w in fits.windows(2) {
            let (a, b) = (&w[0], &w[1]);
            if a.id % 2 != 0 || b.id != a.id + 1 {
                continue;
            }
            // Whitened residuals; each pixel's χ² against the gross gate.
            let whiten = |p: &LevelPixel, e: &mut [f64]| {
                let (mut c, mut n) = (0.0, 0usize);
                for (k, (&y, &r)) in p.y.iter().zip(&p.r).enumerate() {
                    e[k] = f64::NAN;
                    if y.is_finite() && r.is_finite() {
                        let m = self.level.gain[k] * r + self.level.offset[k];
                        e[k] = (y - m) / noise.var(k, m).sqrt();
                        c += e[k] * e[k];
                        n += 1;
                    }
                }
                let dof = n.saturating_sub(p.jac.len()).max(1) as f64;
                (c <= chi2_upper_quantile(dof, GROSS_P)).then_some((c, dof))
            };
            let (Some((ca, da)), Some((cb, db))) = (whiten(a, &mut e_a), whiten(b, &mut e_b))
            else {
                continue;
            };
            if scale_free {
                without_scale(a, &mut e_a, &self.level, noise);
                without_scale(b, &mut e_b, &self.level, noise);
            }
            let (mut s, mut n) = (0.0, 0usize);
            for k in 0..nb {
                if e_a[k].is_finite() && e_b[k].is_finite() {
                    s += e_a[k] * e_b[k];
                    n += 1;
                }
            }
            let dof = 0.5 * (da + db);
            if n > 0 {
                // Per degree of freedom: the residuals span dof dimensions.
                shared.push(s / dof);
                (dof_sum, chi2_sum) = (dof_sum + da + db, chi2_sum + ca + cb);
            }
        }
        if shared.is_empty() {
            return None;
        }
        let m = shared.len();
        let mid = m / 2;
        let median = *shared.select_nth_unstable_by(mid, f64::total_cmp).1;
        // Under the model a pair's product per dof has mean 0 and σ
        // 1/√dof; its median over m pairs, 1.2533/√(m·dof).
        let dof = dof_sum / (2 * m) as f64;
        Some(ImageFit {
            pairs: m,
            shared: median,
            z: median * (m as f64 * dof).sqrt() / 1.2533,
            chi2_dof: chi2_sum / dof_sum,
        })
    }
}

/// `e` (whitened residuals of `p`) without its component along the
/// pixel's whitened model: what a scale error leaves.
fn without_scale(p: &LevelPixel, e: &mut [f64], level: &Level, noise: &NoiseModel) {
    let (mut em, mut mm) = (0.0, 0.0);
    let mut m = vec![0.0; e.len()];
    for (k, &r) in p.r.iter().enumerate() {
        if e[k].is_finite() && r.is_finite() {
            let v = level.gain[k] * r + level.offset[k];
            m[k] = v / noise.var(k, v).sqrt();
            (em, mm) = (em + e[k] * m[k], mm + m[k] * m[k]);
        }
    }
    if mm > 0.0 {
        let c = em / mm;
        for (e, m) in e.iter_mut().zip(&m) {
            if e.is_finite() {
                *e -= c * m;
            }
        }
    }
}
