//! How far apart a film's neighbouring fringe orders lie with the angle
//! free, noise-free, on a grid over optical thickness and angle: where
//! they lie far apart, `balanced`'s warm pixel need not weigh them again.
//!
//! With the angle known the thickness table holds this gap over thickness
//! ([`super::table::ThicknessTable::order_gap`]). With the angle free each
//! warm pixel refines its neighbouring order (one fringe more or fewer,
//! the angle free too: [`Solver::with_neighbour_order`]) to see that it
//! fits clearly worse; on the thick hard coat that costs about twice the
//! pixel's own refinement, and every such order fell short by more than
//! ten thousand noise variances. The gap is what that check measures
//! without the noise: at a grid point `(g, θ)` (optical thickness `g =
//! d·q2`, angle θ), the model's own spectrum there taken as the data, the
//! neighbouring orders refined from the same fringe phase one fringe away
//! with the angle free, to convergence; the lesser of the two residuals
//! is the gap (in reflectance², with the largest reflectance of the
//! point's spectrum to find the largest noise variance against which it
//! is read).
//!
//! A pixel takes the least gap of its cell's four corners. Where that is
//! ≥ [`super::table::ORDER_GAP_SAFE`] times the largest noise variance,
//! the order is not weighed: the noise moves the neighbouring order's
//! ΔSSE by about 2√gap variances (at 250, ±32 at one σ, ±158 at five),
//! nowhere near the ambiguity margin; inside a cell the gap stays above
//! 0.75 of its least corner (0.90 measured; the unit test below). A corner
//! within a fringe of the thickness range's ends (a neighbouring order
//! outside it) is never safe: the pixel weighs its orders as before.
//!
//! The grid is filled on first use, by whichever thread reaches a corner
//! first (a corner's value depends on the corner and the noise model
//! alone, so threads that race compute the same bits); it lives with the
//! prepared model and is kept for every later image (a live run's sweeps)
//! until the noise model changes.

use super::{Prepared, Scratch, Solver};
use crate::estimate::model::ModelOut;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};

/// Grid steps per fringe in optical thickness.
const STEPS_PER_FRINGE: f64 = 8.0;

/// Angle step of the grid, radians (0.5°).
const THETA_STEP: f64 = 0.5 * std::f64::consts::PI / 180.0;

/// The most grid points a model keeps (8 MB); a finer grid is not kept
/// and every warm pixel weighs its orders.
const MAX_POINTS: usize = 1 << 20;

/// Refinement iterations for a neighbouring order's floor.
const ITERS: usize = 25;

/// Refinements in a row, from where the last stopped, before a
/// neighbouring order's floor is given up (no gap claimed).
const RESTARTS: usize = 4;

/// A grid point not yet computed.
const UNSET: u64 = u64::MAX;

/// The grid: its geometry and, once used, its points (the gap's and the
/// largest reflectance's `f32` bits, packed; a negative gap marks a point
/// whose neighbouring orders leave the thickness range).
#[derive(Clone, Debug)]
pub(super) struct OrderGaps {
    g_step: f64,
    n_g: usize,
    theta_lo: f64,
    n_t: usize,
    points: Arc<OnceLock<Box<[AtomicU64]>>>,
}

impl OrderGaps {
    /// The grid for optical thicknesses to `g_hi` (nm), one fringe being
    /// `fringe` nm of it, and angles over `theta` (radians); `None` where
    /// it would hold more than [`MAX_POINTS`].
    pub(super) fn new(g_hi: f64, fringe: f64, theta: (f64, f64)) -> Option<OrderGaps> {
        let g_step = fringe / STEPS_PER_FRINGE;
        if !(g_step > 0.0 && g_hi.is_finite() && theta.1 >= theta.0) {
            return None;
        }
        let n_g = (g_hi / g_step).ceil() as usize + 2;
        let n_t = ((theta.1 - theta.0) / THETA_STEP).ceil() as usize + 2;
        (n_g.checked_mul(n_t)? <= MAX_POINTS).then(|| OrderGaps {
            g_step,
            n_g,
            theta_lo: theta.0,
            n_t,
            points: Arc::new(OnceLock::new()),
        })
    }

    /// The same grid with no point computed.
    pub(super) fn emptied(&self) -> OrderGaps {
        OrderGaps {
            points: Arc::new(OnceLock::new()),
            ..self.clone()
        }
    }

    /// The grid point `(i, j)`'s optical thickness and angle.
    fn at(&self, i: usize, j: usize) -> (f64, f64) {
        (
            i as f64 * self.g_step,
            self.theta_lo + j as f64 * THETA_STEP,
        )
    }

    /// The cell holding `(g, θ)`: its lower corner, if the grid has it.
    fn cell(&self, g: f64, theta: f64) -> Option<(usize, usize)> {
        let x = g / self.g_step;
        let y = (theta - self.theta_lo) / THETA_STEP;
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        let (i, j) = (x as usize, y as usize);
        (i + 1 < self.n_g && j + 1 < self.n_t).then_some((i, j))
    }

    /// Grid points computed so far.
    #[cfg(test)]
    fn filled(&self) -> usize {
        self.points.get().map_or(0, |p| {
            p.iter()
                .filter(|v| v.load(Ordering::Relaxed) != UNSET)
                .count()
        })
    }

    fn points(&self) -> &[AtomicU64] {
        self.points.get_or_init(|| {
            (0..self.n_g * self.n_t)
                .map(|_| AtomicU64::new(UNSET))
                .collect()
        })
    }
}

/// A point's value packed: the gap and the largest noise variance it is
/// read against.
fn pack(gap: f32, var: f32) -> u64 {
    (u64::from(gap.to_bits()) << 32) | u64::from(var.to_bits())
}

fn unpack(v: u64) -> (f32, f32) {
    (f32::from_bits((v >> 32) as u32), f32::from_bits(v as u32))
}

/// `x` in `f32`, rounded towards `up` (+∞) or towards −∞.
fn to_f32(x: f64, up: bool) -> f32 {
    let y = x as f32;
    let past = if up {
        f64::from(y) < x
    } else {
        f64::from(y) > x
    };
    if past && y.is_finite() && y != 0.0 {
        // One ulp back towards x (x and y share their sign here).
        let step = if (y > 0.0) == up { 1 } else { -1i32 };
        f32::from_bits((y.to_bits() as i32 + step) as u32)
    } else {
        y
    }
}

impl Solver {
    /// The noise-free gap between the fringe order of a fit at optical
    /// thickness `g` and angle `theta` and its neighbours (the angle free),
    /// in the largest noise variance of any band at the reflectances
    /// there: the least gap over the grid cell's corners in the largest of
    /// their variances. `None` where the grid is not kept, the point lies
    /// outside it, or no noise model is known; 0 near the thickness
    /// range's ends.
    pub(super) fn free_order_gap(
        &self,
        prep: &Prepared,
        g: f64,
        theta: f64,
        scratch: &mut Scratch,
    ) -> Option<f64> {
        let gaps = prep.order_gaps.as_ref()?;
        self.noise.as_ref()?;
        let (i, j) = gaps.cell(g, theta)?;
        let (mut gap, mut var) = (f32::INFINITY, 0f32);
        for (a, b) in [(i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1)] {
            let (g_c, v_c) = self.gap_point(prep, gaps, a, b, scratch);
            if g_c.is_nan() || g_c < 0.0 {
                return Some(0.0);
            }
            gap = gap.min(g_c);
            var = var.max(v_c);
        }
        (var > 0.0).then(|| f64::from(gap) / f64::from(var))
    }

    /// Grid point `(i, j)`, computed on first use: its gap (rounded down)
    /// and the largest noise variance of any band at its reflectances
    /// (rounded up; within a cell the reflectance moves a little from its
    /// corners', so a margin of 0.05 on the largest). The grid starts
    /// afresh with each noise model, so the variance is the one in force,
    /// and no pixel pays for it again.
    fn gap_point(
        &self,
        prep: &Prepared,
        gaps: &OrderGaps,
        i: usize,
        j: usize,
        scratch: &mut Scratch,
    ) -> (f32, f32) {
        let cell = &gaps.points()[i * gaps.n_t + j];
        let v = cell.load(Ordering::Relaxed);
        if v != UNSET {
            return unpack(v);
        }
        let (g, theta) = gaps.at(i, j);
        let (gap, r_max) = self.order_gap_free_at(prep, g, theta, scratch);
        let var = self
            .max_noise_var_below((r_max + 0.05).min(1.0))
            .unwrap_or(f64::NAN);
        let v = pack(to_f32(gap, false), to_f32(var, true));
        cell.store(v, Ordering::Relaxed);
        unpack(v)
    }

    /// The noise-free gap at optical thickness `g` and angle `theta` (see
    /// the module): the model's spectrum there as the data, every band
    /// used, each neighbouring order refined with the angle free from the
    /// same fringe phase a fringe away, as the warm pixel's check starts
    /// it. Returns the lesser residual (−1 where a neighbouring order
    /// leaves the thickness range) and the spectrum's largest reflectance.
    /// The pixel's spectrum, weights and the model evaluation its
    /// refinement left are kept aside meanwhile and put back.
    pub(super) fn order_gap_free_at(
        &self,
        prep: &Prepared,
        g: f64,
        theta: f64,
        scratch: &mut Scratch,
    ) -> (f64, f64) {
        let q2 = prep.model.q2_mid(theta);
        let dg = 0.5 / self.table.sigma_center;
        let d = g / q2;
        if !(g - dg >= 0.0 && (g + dg) / q2 <= self.d_max && d >= self.d_min) {
            return (-1.0, 1.0);
        }
        let n = scratch.spectrum.len();
        if scratch.gap_cur.r.len() != n {
            scratch.gap_cur = ModelOut::new(n);
            scratch.gap_y = vec![0.0; n];
            scratch.gap_w = vec![1.0; n];
        }
        // The pixel's state aside; the point's spectrum in its place, and
        // the strict stopping rule whatever the solve in progress uses (a
        // point's value depends on the point and the noise model alone).
        std::mem::swap(&mut scratch.cur, &mut scratch.gap_cur);
        let cur_at = scratch.cur_at.take();
        let step_chi2 = std::mem::take(&mut scratch.step_chi2);
        prep.model.eval(d, theta, &mut scratch.cur, false);
        scratch.gap_y.copy_from_slice(&scratch.cur.r[..n]);
        let r_max = scratch.gap_y.iter().fold(0f64, |a, &b| a.max(b));
        std::mem::swap(&mut scratch.spectrum, &mut scratch.gap_y);
        std::mem::swap(&mut scratch.weight, &mut scratch.gap_w);
        let mut gap = f64::INFINITY;
        for ga in [g - dg, g + dg] {
            // A refinement that crawls along a bend of the valley (or
            // the angle's bound) is taken on from where it stopped.
            let mut f = self.refine(&prep.model, ga / q2, theta, true, ITERS, scratch);
            for _ in 1..RESTARTS {
                if !f.stalled {
                    break;
                }
                f = self.refine(&prep.model, f.d, f.theta, true, ITERS, scratch);
            }
            // A refinement that ran out of steps may stand above its
            // basin's floor: no gap is claimed from it.
            gap = gap.min(if f.sse.is_finite() && !f.stalled {
                f.sse
            } else {
                0.0
            });
        }
        std::mem::swap(&mut scratch.spectrum, &mut scratch.gap_y);
        std::mem::swap(&mut scratch.weight, &mut scratch.gap_w);
        std::mem::swap(&mut scratch.cur, &mut scratch.gap_cur);
        scratch.cur_at = cur_at;
        scratch.step_chi2 = step_chi2;
        (gap, r_max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimate::noise::{NoiseModel, NoiseSource};
    use crate::estimate::Mode;
    use crate::optics::dispersion::Dispersion;
    use crate::scene::{FilmKnowledge, Scene};
    use crate::synth::scene_bands;

    fn solver(name: &str) -> Solver {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes");
        let mut scene = Scene::load(&dir.join(format!("{name}.toml"))).expect("the scene loads");
        if !matches!(scene.film, FilmKnowledge::Known(_)) {
            scene.film = FilmKnowledge::Known(Dispersion::constant(1.37));
        }
        let bands = scene_bands(&scene).expect("its bands");
        let mut s = Solver::new(&scene, &bands, Mode::Balanced).expect("its solver");
        // The scenes' noise, as an image's estimate would give it (the
        // refinements' stopping rule reads it).
        s.set_noise(NoiseModel::uniform(0.001, bands.len(), NoiseSource::Given));
        s
    }

    /// A point's gap rounds down and its variance up into `f32`.
    #[test]
    fn stored_values_round_the_safe_way() {
        for x in [
            1e-8,
            3.3e-7,
            0.1,
            1.0 / 3.0,
            250.0 + 1e-9,
            7.0e5,
            -1.0,
            -0.3,
        ] {
            let (lo, hi) = (to_f32(x, false), to_f32(x, true));
            assert!(f64::from(lo) <= x && f64::from(hi) >= x, "{x}: {lo} {hi}");
            assert!(hi.to_bits().abs_diff(lo.to_bits()) <= 1, "{x}: {lo} {hi}");
        }
    }

    /// A pixel reads the least gap of its cell's corners: inside a cell
    /// the gap (computed there as at a corner) stays above 0.75 of that
    /// on s, p and unpolarised light, a thin, a thick and a dispersive
    /// film, at angles across the search range. [`ORDER_GAP_SAFE`]
    /// allows for it: 0.75 · 250 = 188 variances, from which five σ of
    /// noise (2√188·5 = 137) still leave 51, well beyond the ambiguity
    /// margin (9 at up to 1.8 noise variances: 16). Measured: 0.90 at
    /// worst over ~2 000 interior points; 0.84 on a grid twice as coarse.
    ///
    /// [`ORDER_GAP_SAFE`]: crate::estimate::solver::table::ORDER_GAP_SAFE
    #[test]
    fn the_gap_inside_a_cell_stays_near_its_corners() {
        for name in [
            "thick-hardcoat",
            "thin-coating",
            "dispersive-p61",
            "paper-cylinder",
        ] {
            let s = solver(name);
            let prep = s.prepared.as_ref().expect("a known film is prepared");
            assert!(prep.order_gaps.is_some(), "{name}: balanced, angle free");
            let mut scratch = Scratch::default();
            scratch.ensure(s.bands.len());
            let fringe = 0.5 / s.table.sigma_center;
            let (lo, hi) = s.theta_range;
            let (dg, dt) = (fringe / STEPS_PER_FRINGE, THETA_STEP);
            let g_hi = s.d_max * prep.model.q2_mid(hi);
            let (mut worst, mut inside, mut cells) = (f64::INFINITY, 0, 0);
            for k in 0..200 {
                // Cells spread over the range (a low-discrepancy walk).
                let u = (k as f64 * 0.618_034).fract();
                let v = (k as f64 * 0.414_214).fract();
                let g0 = ((2.0 * fringe + u * (g_hi - 4.0 * fringe)) / dg).floor() * dg;
                let t0 = lo + ((v * (hi - lo - dt)) / dt).floor() * dt;
                let least = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)]
                    .map(|(a, b)| {
                        s.order_gap_free_at(prep, g0 + a * dg, t0 + b * dt, &mut scratch)
                            .0
                    })
                    .into_iter()
                    .fold(f64::INFINITY, f64::min);
                // A corner whose refinement stalled (or past the range)
                // claims no gap: its cell is weighed pixel by pixel.
                if least.is_nan() || least <= 0.0 {
                    continue;
                }
                cells += 1;
                for (a, b) in [(0.5, 0.5), (0.25, 0.75), (0.8, 0.2)] {
                    let g = s
                        .order_gap_free_at(prep, g0 + a * dg, t0 + b * dt, &mut scratch)
                        .0;
                    if g > 0.0 {
                        worst = worst.min(g / least);
                        inside += 1;
                    }
                }
            }
            assert!(
                cells >= 150 && inside >= 400,
                "{name}: {cells} cells, {inside} points"
            );
            assert!(
                worst >= 0.75,
                "{name}: the gap fell to {worst:.3} of its cell's least corner"
            );
        }
    }

    /// Skipping the far orders changes no pixel's verdict: noisy images
    /// fitted with the grid and without it (every warm pixel weighing its
    /// orders) give every pixel the same reason, and the same thickness
    /// and angle to within a quarter of their σ — where the noise-free
    /// orders lie ≥ 250 variances apart the weighed order never comes near
    /// the ambiguity margin. (Not to the bit: a refinement that weighed
    /// the order leaves another model evaluation behind for the next
    /// pixel's warm start, which then converges to the same minimum by
    /// another path; `balanced` stops within 0.1 σ of it, so two stops
    /// lie within 0.2 σ.) The thick hard coat at the scenes' noise (every
    /// warm pixel skips), the thin coating at it too (films within a
    /// fringe of the range's ends weigh, the rest skip), dispersive p
    /// light at three times it (gaps a ninth as many variances).
    #[test]
    fn skipping_far_orders_changes_no_verdict() {
        use crate::synth::Renderer;
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes");
        for (name, sigma) in [
            ("thick-hardcoat", 0.001),
            ("thin-coating", 0.001),
            ("dispersive-p61", 0.003),
        ] {
            let mut scene = Scene::load(&dir.join(format!("{name}.toml"))).expect("the scene");
            let truth = scene.truth.as_mut().expect("a truth to render");
            truth.noise_sigma = sigma;
            let bands = scene_bands(&scene).expect("its bands");
            let cube = Renderer::new(&scene)
                .and_then(|r| r.render_cube(&bands))
                .expect("the cube renders");
            let mut with = Solver::new(&scene, &bands, Mode::Balanced).expect("its solver");
            with.estimate_film_index(&cube).expect("noise and level");
            let mut without = with.clone();
            let gaps = with.prepared.as_ref().and_then(|p| p.order_gaps.clone());
            let gaps = gaps.expect("balanced with the angle free keeps a grid");
            without.prepared.as_mut().expect("prepared").order_gaps = None;
            let a = with.fit_cube(&cube).expect("fits");
            let b = without.fit_cube(&cube).expect("fits");
            assert!(gaps.filled() > 0, "{name}: the grid was never asked");
            let valid = a.valid.iter().filter(|&&v| v != 0.0).count();
            assert!(valid * 5 > a.valid.len(), "{name}: {valid} valid");
            let mut moved = 0;
            for i in 0..a.reason.len() {
                assert_eq!(
                    a.reason[i], b.reason[i],
                    "{name} σ {sigma}: pixel {i}'s reason"
                );
                if a.valid[i] == 0.0 {
                    continue;
                }
                let (sd, st) = (a.sigma_thickness_nm[i], a.sigma_theta_deg[i]);
                let dd = (a.thickness_nm[i] - b.thickness_nm[i]).abs();
                let dt = (a.theta_deg[i] - b.theta_deg[i]).abs();
                let ds = (a.sigma_thickness_nm[i] / b.sigma_thickness_nm[i] - 1.0).abs();
                assert!(
                    dd <= 0.25 * sd && dt <= 0.25 * st && ds <= 0.05,
                    "{name} σ {sigma}: pixel {i}: Δd {dd} (σ {sd}), Δθ {dt} (σ {st}), σ ×{ds}"
                );
                moved += usize::from(dd > 0.0);
            }
            // Not vacuous: the two runs did take different paths.
            assert!(
                moved > 0 || name != "thick-hardcoat",
                "{name}: nothing moved"
            );
        }
    }

    /// The same on data the model did not render: a white reference off
    /// by a smooth gain of 3–5 % across the bands and stray light of
    /// 0.003 on the thick hard coat and dispersive p light (`auto` level).
    /// With the grid and without it every pixel keeps its reason and its
    /// thickness within a quarter σ; and with the grid at most 1 % of the
    /// pixels are valid and wrong (off the truth by more than max(3σ,
    /// 2 nm)).
    #[test]
    fn skipping_far_orders_on_miscalibrated_data_changes_no_verdict() {
        use crate::synth::Renderer;
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes");
        for name in ["thick-hardcoat", "dispersive-p61"] {
            let scene = Scene::load(&dir.join(format!("{name}.toml"))).expect("the scene");
            let bands = scene_bands(&scene).expect("its bands");
            let r = Renderer::new(&scene).expect("renders");
            let truth = r.truth_maps(&bands);
            let mut cube = r.render_cube(&bands).expect("the cube renders");
            let nb = bands.len();
            for b in 0..nb {
                let gain = 1.03 + 0.02 * b as f32 / (nb - 1) as f32;
                for v in cube.plane_mut(b) {
                    *v = *v * gain + 0.003;
                }
            }
            let mut with = Solver::new(&scene, &bands, Mode::Balanced).expect("its solver");
            with.estimate_film_index(&cube).expect("noise and level");
            let mut without = with.clone();
            without.prepared.as_mut().expect("prepared").order_gaps = None;
            let a = with.fit_cube(&cube).expect("fits");
            let b = without.fit_cube(&cube).expect("fits");
            let (mut valid, mut wrong) = (0, 0);
            for i in 0..a.reason.len() {
                assert_eq!(a.reason[i], b.reason[i], "{name}: pixel {i}'s reason");
                if a.valid[i] == 0.0 {
                    continue;
                }
                valid += 1;
                let sd = f64::from(a.sigma_thickness_nm[i]);
                let dd = f64::from((a.thickness_nm[i] - b.thickness_nm[i]).abs());
                assert!(dd <= 0.25 * sd, "{name}: pixel {i}: Δd {dd} (σ {sd})");
                let err = f64::from((a.thickness_nm[i] - truth.thickness_nm[i]).abs());
                wrong += usize::from(err > (3.0 * sd).max(2.0));
            }
            // Not passed by flagging: the level corrects the calibration
            // (measured: 4 320 of 6 000 and 3 994 of 4 000 valid, 6 and 0
            // of them wrong).
            assert!(valid * 2 > a.reason.len(), "{name}: {valid} valid");
            assert!(
                wrong * 100 <= a.reason.len(),
                "{name}: {wrong} of {valid} valid pixels wrong"
            );
        }
    }
}
