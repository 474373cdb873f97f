//! Thickness tables on a fine grid of angles, each built when a pixel first
//! needs it: with the angle free, `fast` estimates each row's angle from a
//! sparse sample of angle-free fits ([`super::super::angle_map`]) and
//! solves the row's other pixels on the table of the grid angle nearest to
//! it, as if that angle were known.
//!
//! A pixel is solved *at* its bin's angle, not refined between bins (that
//! costs an exact-model fit per pixel): the row's angle moves to the bin,
//! and the thickness back along the film's equal-phase line (`d·q(θ)`
//! constant). That is exact in the phase; what is left is the Fresnel
//! coefficients' change over half a bin. So the grid is as fine as that
//! change requires: bin edges lie where the integral of `G(θ)/(2·tol)`
//! crosses an integer, `G` the largest `|dR/dθ|` along the equal-phase line
//! over the bands and a spread of thicknesses (measured on knots
//! [`KNOT_DEG`] apart), `tol` a tenth of the noise level — bins of 0.5°
//! near normal incidence, of 0.015° where p light's reflectance turns fast
//! on a high-index film. `moving_to_the_bin_…` checks the promise on a
//! grid of angles and thicknesses the construction did not sample.
//!
//! Only the bins a cube's rows use are built (a few per row on a curved
//! part, one on a flat one), each once, whichever thread needs it first;
//! the bytes built are capped at [`TABLE_BUDGET_BYTES`]: past the cap a
//! bin stays unbuilt and its pixels take the angle-free fit.

use super::{bytes_per_point, ThicknessTable, TABLE_BUDGET_BYTES};
use crate::estimate::model::{FilmModel, ModelOut};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};

/// The grid's knots, where the Fresnel slope is measured, degrees apart.
const KNOT_DEG: f64 = 0.25;

/// The widest bin, degrees (where the Fresnel coefficients hardly change
/// with the angle: near normal incidence).
const MAX_STEP_DEG: f64 = 0.5;

/// Most bins a grid may have (the tolerance is loosened beyond).
const MAX_BINS: f64 = 200_000.0;

/// The thicknesses a table covers at angle `θ`: scanned `[lo, hi]`,
/// walked to `reach` (as [`super::Tables::build`]'s `range`).
#[derive(Clone, Copy, Debug)]
pub struct BinRange {
    /// Thinnest film.
    pub d_min: f64,
    /// Thickest film the user allows.
    pub d_max: f64,
    /// Largest optical thickness scanned (`d·q` of the resolved range).
    pub g_hi: f64,
    /// Largest optical thickness walked to, where the range is the
    /// physics' (`None`: walks stop at the scan's end).
    pub g_reach: Option<f64>,
}

/// The largest `|dR/dθ|` along the equal-phase line `d·q(θ)` constant at
/// angle `t`, over the bands and a spread of thicknesses in `(lo, hi, _)`.
fn equal_phase_slope(model: &FilmModel, t: f64, (lo, hi, _): (f64, f64, f64)) -> f64 {
    const THICKNESSES: usize = 64;
    let h = 1e-5;
    let q = model.q2_mid(t);
    let dq = (model.q2_mid(t + h) - model.q2_mid((t - h).max(0.0))) / (t + h - (t - h).max(0.0));
    let mut out = ModelOut::new(model.n_bands());
    let mut worst: f64 = 0.0;
    for k in 0..THICKNESSES {
        // A low-discrepancy spread: the slope oscillates with the fringes.
        let f = (k as f64 * 0.618_033_988_749_895).fract();
        let d = lo + f * (hi - lo);
        model.eval(d, t, &mut out, true);
        let dd = -d * dq / q;
        for (a, b) in out.dr_dth.iter().zip(&out.dr_dd).take(model.n_bands()) {
            worst = worst.max((a + b * dd).abs());
        }
    }
    worst
}

impl BinRange {
    fn at(&self, model: &FilmModel, t: f64) -> (f64, f64, f64) {
        let q = model.q2_mid(t).max(1e-6);
        let d_hi = self.d_max.min(self.g_hi / q).max(self.d_min);
        let reach = self.g_reach.map_or(d_hi, |g| {
            (g / q).min(crate::scene::MAX_THICKNESS_LIMIT_NM).max(d_hi)
        });
        (self.d_min, d_hi, reach)
    }
}

/// Tables on a grid of angles, built on first use. The grid is finer where
/// the model changes faster with the angle at equal phase: bin `i` lies at
/// `u(θ) = i`, `u` the integral of `G(θ)/(2·tol)`, `G` the largest
/// `|∂R/∂θ|` along the equal-phase line over the bands and thicknesses, so
/// a pixel moved to its bin's angle errs by at most `tol` in reflectance.
pub struct AngleBins {
    /// The knots' angles, radians, and `u` at each.
    knots: Vec<f64>,
    u: Vec<f64>,
    cells: Vec<OnceLock<Option<Arc<ThicknessTable>>>>,
    model: FilmModel,
    range: BinRange,
    built: AtomicUsize,
}

impl std::fmt::Debug for AngleBins {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AngleBins")
            .field("span", &(self.knots.first(), self.knots.last()))
            .field("bins", &self.cells.len())
            .field("bytes_built", &self.built.load(Ordering::Relaxed))
            .finish()
    }
}

impl AngleBins {
    /// Bins over `[lo, hi]` (radians) for `model`, fine enough that moving
    /// a pixel to its bin's angle along the equal-phase line changes the
    /// model by at most `tol` in reflectance (or as fine as
    /// [`MAX_BINS`] allow). None where the span is empty or not finite.
    pub fn new(
        model: &FilmModel,
        (lo, hi): (f64, f64),
        range: BinRange,
        tol: f64,
    ) -> Option<AngleBins> {
        if !(lo.is_finite() && hi.is_finite() && hi >= lo && tol > 0.0) {
            return None;
        }
        let n_knots = ((hi - lo).to_degrees() / KNOT_DEG).ceil() as usize + 1;
        let knots: Vec<f64> = (0..n_knots)
            .map(|i| (lo + i as f64 * KNOT_DEG.to_radians()).min(hi))
            .collect();
        let slopes: Vec<f64> = knots
            .iter()
            .map(|&t| equal_phase_slope(model, t, range.at(model, t)))
            .collect();
        let floor = 2.0 * tol / MAX_STEP_DEG.to_radians();
        let mut u = vec![0.0; n_knots];
        for k in 1..n_knots {
            let g = 0.5 * (slopes[k - 1].max(floor) + slopes[k].max(floor));
            u[k] = u[k - 1] + g / (2.0 * tol) * (knots[k] - knots[k - 1]);
        }
        let total = u.last().copied().unwrap_or(0.0);
        if !total.is_finite() {
            return None;
        }
        if total > MAX_BINS {
            let k = MAX_BINS / total;
            u.iter_mut().for_each(|v| *v *= k);
        }
        let n = u.last().copied().unwrap_or(0.0).floor() as usize + 1;
        Some(AngleBins {
            knots,
            u,
            cells: (0..n).map(|_| OnceLock::new()).collect(),
            model: model.clone(),
            range,
            built: AtomicUsize::new(0),
        })
    }

    /// The grid angle nearest to `theta` (radians), if within the grid.
    pub fn bin_of(&self, theta: f64) -> Option<f64> {
        self.index_of(theta).map(|i| self.angle(i))
    }

    /// How many bins the grid has.
    #[cfg(test)]
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    fn index_of(&self, theta: f64) -> Option<usize> {
        let (lo, hi) = (*self.knots.first()?, *self.knots.last()?);
        if !(theta >= lo && theta <= hi) {
            return None;
        }
        let k = self
            .knots
            .partition_point(|&t| t <= theta)
            .clamp(1, self.knots.len() - 1);
        let (t0, t1) = (self.knots[k - 1], self.knots[k]);
        let f = if t1 > t0 {
            (theta - t0) / (t1 - t0)
        } else {
            0.0
        };
        let u = self.u[k - 1] + f * (self.u[k] - self.u[k - 1]);
        let i = u.round() as usize;
        (i < self.cells.len()).then_some(i)
    }

    /// Bin `i`'s angle: `u⁻¹(i)`.
    fn angle(&self, i: usize) -> f64 {
        let v = i as f64;
        let k = self
            .u
            .partition_point(|&u| u <= v)
            .clamp(1, self.u.len() - 1);
        let (u0, u1) = (self.u[k - 1], self.u[k]);
        let f = if u1 > u0 {
            ((v - u0) / (u1 - u0)).clamp(0.0, 1.0)
        } else {
            0.0
        };
        self.knots[k - 1] + f * (self.knots[k] - self.knots[k - 1])
    }

    /// The table at `theta`, which must be a grid angle exactly (as
    /// [`AngleBins::bin_of`] gives it), built now if it is not yet; none
    /// off the grid or past the byte cap.
    #[cfg(test)]
    pub fn at(&self, theta: f64) -> Option<&ThicknessTable> {
        let i = self.index_of(theta)?;
        if self.angle(i).to_bits() != theta.to_bits() {
            return None;
        }
        self.cell(i, theta)
    }

    /// [`AngleBins::at`], the bin of the last lookup (`hint`: its angle's
    /// bits and its index) taken without a search where the angle is the
    /// same: a row's pixels share their angle, or move through it slowly.
    pub fn at_hinted(
        &self,
        theta: f64,
        hint: &std::cell::Cell<Option<(u64, usize)>>,
    ) -> Option<&ThicknessTable> {
        let key = theta.to_bits();
        match hint.get() {
            Some((k, i)) if k == key && i < self.cells.len() => self.cell(i, theta),
            _ => {
                let i = self.index_of(theta)?;
                if self.angle(i).to_bits() != key {
                    return None;
                }
                hint.set(Some((key, i)));
                self.cell(i, theta)
            }
        }
    }

    /// Bin `i` (at angle `theta`), built now if it is not yet.
    fn cell(&self, i: usize, theta: f64) -> Option<&ThicknessTable> {
        self.cells[i]
            .get_or_init(|| {
                let (lo, hi, far) = self.range.at(&self.model, theta);
                let per = bytes_per_point(self.model.n_bands());
                let size = |b: f64| ThicknessTable::size(&self.model, theta, lo, b).0 * per;
                // Walks past the range only while the cap allows them.
                let far = if self.reserve(size(far)) {
                    far
                } else if self.reserve(size(hi)) {
                    hi
                } else {
                    return None;
                };
                let t = ThicknessTable::new_reaching(&self.model, theta, lo, hi, far);
                // The estimate reserved, the table's own size counted.
                let est = size(far);
                let real = t.bytes();
                if real < est {
                    self.built.fetch_sub(est - real, Ordering::Relaxed);
                }
                tracing::debug!(
                    theta_deg = theta.to_degrees(),
                    bytes = t.bytes(),
                    "angle bin built"
                );
                Some(Arc::new(t))
            })
            .as_deref()
    }

    /// Counts `bytes` against the cap; false (and nothing counted) where
    /// they would pass it. (The table's step may halve where its fringes
    /// are far from sinusoidal, up to eight times the estimate: the cap
    /// bounds the estimate, the budget's headroom the rest.)
    fn reserve(&self, bytes: usize) -> bool {
        self.built
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |b| {
                (b + bytes <= TABLE_BUDGET_BYTES).then_some(b + bytes)
            })
            .is_ok()
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::model;
    use super::*;

    /// 0–2000 nm, no reach past the scan.
    fn range() -> BinRange {
        BinRange {
            d_min: 0.0,
            d_max: 2000.0,
            g_hi: 3000.0,
            g_reach: None,
        }
    }

    #[test]
    fn a_bin_is_built_once_at_its_own_angle_and_off_grid_angles_get_none() {
        let m = model();
        let bins = AngleBins::new(&m, (0.0, 80f64.to_radians()), range(), 1e-5).expect("bins");
        let t = bins.bin_of(30.004f64.to_radians()).expect("in the grid");
        assert!((t.to_degrees() - 30.004).abs() < 0.5, "{}", t.to_degrees());
        assert_eq!(bins.bin_of(t), Some(t), "a bin's angle is its own bin");
        assert!(bins.at(t + 1e-7).is_none(), "off the grid");
        let a = bins.at(t).expect("built") as *const ThicknessTable;
        let b = bins.at(t).expect("kept") as *const ThicknessTable;
        assert_eq!(a, b, "built once");
        assert!(bins.bin_of(81f64.to_radians()).is_none());
        assert!(bins.bin_of(-1f64.to_radians()).is_none());
        // The table is the model's at that angle.
        let tb = bins.at(t).expect("built");
        let mut r = vec![0.0; 31];
        tb.values(500.0, &mut r);
        let mut out = ModelOut::new(31);
        m.eval(500.0, t, &mut out, false);
        for (a, b) in r.iter().zip(&out.r[..31]) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
    }

    /// The grid's promise, checked on a dense grid of angles and
    /// thicknesses the construction did not sample: a film at θ, moved to
    /// its bin's angle along the equal-phase line, reflects within the
    /// tolerance (twice it: the slope is sampled on 64 thicknesses and
    /// knots 0.25° apart) of what it does at θ.
    #[test]
    fn moving_to_the_bin_along_equal_phase_changes_the_model_by_at_most_the_tolerance() {
        let m = model();
        let tol = 1e-4;
        let bins = AngleBins::new(&m, (0.0, 75f64.to_radians()), range(), tol).expect("bins");
        let (mut at, mut moved) = (ModelOut::new(31), ModelOut::new(31));
        let mut worst: f64 = 0.0;
        for i in 0..300 {
            let th = (0.2 + 0.2477 * i as f64).to_radians();
            let tb = bins.bin_of(th).expect("in the grid");
            for j in 0..200 {
                let d = 3.0 + 9.871 * j as f64;
                m.eval(d, th, &mut at, false);
                m.eval(d * m.q2_mid(th) / m.q2_mid(tb), tb, &mut moved, false);
                for (a, b) in at.r[..31].iter().zip(&moved.r[..31]) {
                    worst = worst.max((a - b).abs());
                }
            }
        }
        eprintln!("worst {worst} bins {}", bins.len());
        assert!(worst <= 2.0 * tol, "worst {worst}");
        // Not needlessly fine: the grid's bins are at least a tenth as
        // wide as the tolerance allows on average.
        assert!(worst > 0.1 * tol, "worst {worst}");
        assert!(bins.len() < 20_000, "{} bins", bins.len());
    }
}
