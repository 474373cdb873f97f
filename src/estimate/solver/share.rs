//! The image-wide level's share of each pixel's σ: how far the pixel's own
//! fit moves its thickness and angle when the level's parameters (and the
//! film index estimated with them) move, `t = A⁻¹B`, and the variance
//! `tᵀΣt` that carries into σ ([`LevelShare`]). At a scene's one known
//! angle the responses are tabled over thickness once per level
//! ([`ShareTable`]); elsewhere each pixel's fit is evaluated again.

use super::level_fit::INDEX_DN;
use super::{Prepared, Scratch, Solver};
use crate::estimate::level::LevelShare;
use crate::estimate::model::ModelOut;
use crate::estimate::{PixelEstimate, Reason};
use crate::scene::AngleKnowledge;

/// Points of a [`ShareTable`] over the thickness range: on a 10 µm range
/// 2.4 nm apart, a tenth of the ~25 nm over which one band's reflectance
/// turns. A unit test checks the interpolated share against the direct
/// evaluation over the thin coating's range: within 0.7 % (at 2 nm apart
/// there, 5 %).
const SHARE_TABLE_POINTS: usize = 4096;

/// Grid steps from zero thickness below which a [`ShareTable`] is not
/// read: toward zero the response grows like a power of 1/d, faster than
/// a linear interpolant follows.
const SHARE_TABLE_FROM: f64 = 40.0;

/// The response of a pixel's thickness to the level's parameters over
/// thickness at the one known angle of a scene, for pixels with every
/// band (see [`Solver::share_var`]): one model evaluation per table point
/// instead of one per pixel. The responses are interpolated, not their
/// quadratic form, which has a double root wherever one passes zero.
#[derive(Clone, Debug)]
pub(super) struct ShareTable {
    step: f64,
    /// Parameters per point.
    m: usize,
    /// The responses, point-major.
    t: Vec<f64>,
}

impl ShareTable {
    /// The share of σ_d² at thickness `d` (none for the known angle),
    /// from the responses linearly interpolated into `work`; `None`
    /// outside the table or next to a point that could not be told.
    pub(super) fn at(
        &self,
        d: f64,
        share: &LevelShare,
        work: &mut Vec<[f64; 2]>,
    ) -> Option<(f64, f64)> {
        let points = self.t.len() / self.m.max(1);
        let x = d / self.step;
        if self.m == 0
            || points < 2
            || x.is_nan()
            || x < SHARE_TABLE_FROM
            || x > (points - 1) as f64
        {
            return None;
        }
        let i = (x as usize).min(points - 2);
        let f = x - i as f64;
        let (a, b) = (&self.t[i * self.m..], &self.t[(i + 1) * self.m..]);
        if a[0].is_nan() || b[0].is_nan() {
            return None;
        }
        work.clear();
        work.extend((0..self.m).map(|j| [(1.0 - f) * a[j] + f * b[j], 0.0]));
        Some(share.quad(work))
    }
}

/// Working memory of [`Solver::with_level`]: the model and its
/// derivatives at a pixel's fit, the model one step up in the index, and
/// the measured values' derivative with respect to the index.
#[derive(Clone, Debug, Default)]
pub(super) struct ShareScratch {
    out: ModelOut,
    up: ModelOut,
    dn: Vec<f64>,
    work: Vec<[f64; 2]>,
}

impl Solver {
    /// The image-wide level's share of a valid pixel's σ (thickness and,
    /// where `angle_free`, angle), through the pixel's own fit to its
    /// `spectrum` ([`crate::estimate::level::LevelShare`]).
    pub(super) fn with_level(
        &self,
        prep: &Prepared,
        spectrum: &[f64],
        angle_free: bool,
        est: &mut PixelEstimate,
        scratch: &mut Scratch,
    ) {
        if est.is_valid() && (self.calibration_suspect || self.estimates_unexplained) {
            *est = PixelEstimate::invalid(Reason::PoorFit);
        }
        self.with_band_shift(est);
        let share = &self.level.share;
        if !est.is_valid() || share.is_empty() {
            return;
        }
        let (d, th) = (est.thickness_nm, est.theta_deg.to_radians());
        let tabled = match (&self.scene.angle, angle_free) {
            (&AngleKnowledge::Uniform(t0), false) if spectrum.iter().all(|v| v.is_finite()) => self
                .share_table
                .get_or_init(|| self.share_table_at(prep, t0))
                .as_ref()
                .and_then(|t| t.at(d, &self.level.share, &mut scratch.share.work)),
            _ => None,
        };
        let Some((vd, vt)) =
            tabled.or_else(|| self.share_var(prep, spectrum, d, th, angle_free, scratch))
        else {
            return;
        };
        est.sigma_thickness_nm = est.sigma_thickness_nm.hypot(vd.sqrt());
        est.sigma_theta_deg = est.sigma_theta_deg.hypot(vt.sqrt().to_degrees());
    }

    /// The level's share of the variance of a pixel's thickness and (where
    /// `angle_free`) angle at its fit `(d, th)` to `spectrum`; `None` where
    /// it cannot be told (a global parameter the pixel cannot differentiate:
    /// not reached, the level's only one is the index, whose model is kept
    /// with it).
    pub(super) fn share_var(
        &self,
        prep: &Prepared,
        spectrum: &[f64],
        d: f64,
        th: f64,
        angle_free: bool,
        scratch: &mut Scratch,
    ) -> Option<(f64, f64)> {
        let share = &self.level.share;
        let nb = self.bands.len();
        let s = &mut scratch.share;
        if s.dn.len() != nb {
            *s = ShareScratch {
                out: ModelOut::new(nb),
                up: ModelOut::new(nb),
                dn: vec![0.0; nb],
                work: Vec::new(),
            };
        }
        prep.model.eval(d, th, &mut s.out, true);
        let with_index = match (share.n_extra(), &self.index_step) {
            (0, _) => false,
            (1, Some(up)) => {
                up.eval(d, th, &mut s.up, false);
                for k in 0..nb {
                    s.dn[k] = self.level.gain[k] * (s.up.r[k] - s.out.r[k]) / INDEX_DN;
                }
                true
            }
            _ => return None,
        };
        let extra: &[&[f64]] = if with_index { &[&s.dn[..]] } else { &[] };
        Some(share.var_of(
            spectrum,
            &self.level.gain,
            &s.out.r,
            &s.out.dr_dd,
            angle_free.then_some(&s.out.dr_dth[..]),
            extra,
            &mut s.work,
        ))
    }

    /// [`Solver::share_var`] of a pixel with every band, at the one known
    /// angle `th`, over the thickness range on a grid fine enough for
    /// linear interpolation ([`ShareTable`]); `None` where the range is
    /// empty or a point cannot be told.
    fn share_table_at(&self, prep: &Prepared, th: f64) -> Option<ShareTable> {
        let hi = self.d_max.max(1.0);
        let n = SHARE_TABLE_POINTS;
        let step = hi / (n - 1) as f64;
        let all = vec![0.0; self.bands.len()];
        let mut scratch = Scratch::default();
        let m = self.level.share.n_params();
        let mut t = Vec::with_capacity(n * m);
        for i in 0..n {
            self.share_var(prep, &all, i as f64 * step, th, false, &mut scratch)?;
            let w = &scratch.share.work;
            if w.len() == m {
                t.extend(w.iter().map(|r| r[0]));
            } else {
                // A point whose own fit is singular (no fringe slope at
                // zero thickness): not read (see `ShareTable::at`).
                t.extend(std::iter::repeat_n(f64::NAN, m));
            }
        }
        Some(ShareTable { step, m, t })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimate::level::LevelMode;
    use crate::estimate::Mode;
    use crate::scene::Scene;
    use crate::synth::{scene_bands, Renderer};

    #[test]
    fn the_tabled_level_share_is_the_direct_one() {
        // The thin coating at its one known angle with a white reference
        // 5 % high: the level is fitted, and the share each pixel carries
        // is read off the table. It must be what evaluating the model at
        // the pixel's thickness gives, anywhere in the range.
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/data/scenes/thin-line.toml");
        let mut scene = Scene::load(std::path::Path::new(path)).expect("the scene");
        let truth = scene.truth.as_mut().expect("its truth");
        (truth.width, truth.height) = (96, 64);
        let bands = scene_bands(&scene).expect("its bands");
        let mut cube = Renderer::new(&scene)
            .expect("it renders")
            .render_cube(&bands)
            .expect("the cube");
        cube.data
            .iter_mut()
            .for_each(|v| *v = (f64::from(*v) / 1.05) as f32);
        let mut solver = Solver::new(&scene, &cube.bands, Mode::Balanced).expect("the solver");
        solver.estimate_film_index(&cube).expect("the level");
        assert_eq!(solver.level().1, LevelMode::Scaled);
        let AngleKnowledge::Uniform(t0) = solver.scene.angle else {
            panic!("the scene's angle is one known angle");
        };
        let prep = solver.prepared.clone().expect("prepared");
        let table = solver.share_table_at(&prep, t0).expect("the table");
        let all = vec![0.0; bands.len()];
        let mut scratch = Scratch::default();
        let (lo, hi, _) = solver.thickness_range();
        // Measured against the share itself, or a thousandth of its mean
        // over the range where it passes through zero (where the
        // thickness does not follow the level at all).
        let mut work = Vec::new();
        let points = table.t.len() / table.m;
        let mean = (0..points)
            .filter_map(|i| table.at(i as f64 * table.step, &solver.level.share, &mut work))
            .map(|v| v.0)
            .sum::<f64>()
            / points as f64;
        let mut largest: f64 = 0.0;
        let mut read = 0;
        for i in 0..997 {
            let d = lo + (hi - lo) * (i as f64 + 0.37) / 997.0;
            let (direct, _) = solver
                .share_var(&prep, &all, d, t0, false, &mut scratch)
                .expect("the share");
            let Some((tabled, angle)) = table.at(d, &solver.level.share, &mut work) else {
                assert!(d < SHARE_TABLE_FROM * table.step, "{d} nm not in the table");
                continue;
            };
            read += 1;
            assert!(direct >= 0.0 && angle == 0.0, "{d} nm");
            largest = largest.max((tabled - direct).abs() / direct.max(1e-3 * mean));
        }
        assert!(
            read > 900 && largest < 0.01,
            "{read} read, largest relative difference {largest}"
        );
        eprintln!("largest relative difference {largest:.2e}");
    }
}
