//! Per-band incidence angles: where the geometry makes the incidence angle
//! depend on the sensor row, each band of a web row was seen at the angle
//! of the sensor row it was seen at, and the model uses those angles where
//! the spread matters (and only there).
//!
//! The row solver keeps its fast thickness table at the scene's angle θ_c.
//! For a complete row whose band `b` was seen at θ_b:
//!
//! 1. the row is solved at θ_c, giving each pixel's thickness d̂ (its best
//!    fit, flagged or not);
//! 2. **the rule**: the least-squares thickness is biased by at most
//!    ‖e‖₂/‖J‖ while its σ is σ_R/‖J‖, where `e_b(d) = R_b(d, θ_b) −
//!    R_b(d, θ_c)` is the misfit the spread causes; so the bias is below a
//!    tenth of σ wherever ‖e‖₂ ≤ 0.1·σ_R. A bound of ‖e‖₂ over the row's
//!    thicknesses (its d̂, ±10 nm), `sqrt(Σ_b G_b² (θ_b − θ_c)²)` with
//!    `G_b` the largest |∂R_b/∂θ| over those thicknesses and the view's
//!    angles (tabulated per 10 nm over the solver's whole thickness range
//!    when the angles are set: a per-row cost of one sum over the bands),
//!    is compared with 0.1·σ_R (σ_R: the solver's noise level, given or
//!    learnt; when none is known, every row is corrected). At or below it
//!    the row stands as solved (tested: the bound is above the true
//!    maximum of ‖e‖₂, by ≤ 1.7× on the demo's film);
//! 3. above it, each pixel's thickness is refined by Gauss–Newton on the
//!    model with every band at its own angle, from d̂ (no search: the
//!    first solve found the fringe order), the spectrum is corrected,
//!    `y' = y − e(d)` (after the image-wide level, in the reflectance the
//!    solver fits), and the row is solved again ([`ITERATIONS`] = once).
//!    At the per-band fit `y'` is explained by the model at θ_c exactly as
//!    `y` is by the model at the bands' angles, so the solver's answer is
//!    that fit and its residual `y − R(d, θ_b)`: the χ² test, the flags
//!    and σ judge the true model. (A plain fixed-point iteration, `y' =
//!    y − e(d̂)` solved again, contracts by ~50× per step but costs a full
//!    solve per step; two were 4× slower than this.)
//!
//! `e` and the per-band model are exact: the node coefficients of the
//! general Airy form ([`FilmModel::band_angles`]) are computed once per row
//! with each band at its own angle, and once at θ_c, whatever the number
//! of distinct angles; a row then tabulates `R(d, θ_b)` and `e(d)` with
//! their slopes at 1 nm over its thicknesses (±15 nm) for cubic Hermite
//! interpolation (< 1e-9 in reflectance; rows spanning more than 400 nm
//! evaluate the model per pixel instead). (Interpolating R quadratically
//! in θ between the view's extreme angles and θ_c was tried first: over
//! ±4° the film's phase moves by up to 0.8 rad at 1.2 µm, and the
//! interpolation erred by 6e-4 in reflectance — more than half the noise.)
//!
//! Cost, a corrected row: about 2.4× an uncorrected one (the second solve
//! and the table); rows the rule leaves alone: one sum over the bands.
//!
//! Pure numeric code: no I/O, no clock.

#![forbid(unsafe_code)]

use super::LineError;
use crate::estimate::model::{BandAngles, FilmModel, ModelOut};
use crate::estimate::solver::Scratch;
use crate::estimate::{Cube, PixelEstimate, Solver};

/// When the angle correction is applied.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Correction {
    /// Where the spread of a row's angles matters (the rule of the module
    /// header). The default.
    #[default]
    Auto,
    /// Never: every band modelled at the scene's angle (for comparison).
    Off,
    /// On every complete row whose bands were seen at different angles.
    Always,
}

/// Solves of a corrected row after its first (each from thicknesses
/// refined on the per-band model, see `SensorAngles::iterate`).
pub const ITERATIONS: usize = 1;

/// Gauss–Newton steps per pixel on the per-band model.
const NEWTON_STEPS: usize = 8;

/// Largest Gauss–Newton step, nm (a fraction of a fringe: the first solve
/// found the order).
const MAX_STEP_NM: f64 = 10.0;

/// The correction is applied where the bound on ‖e‖₂ exceeds this fraction
/// of the noise σ (the bias it leaves is then below this fraction of σ_d).
pub const THRESHOLD: f64 = 0.1;

/// Thickness bins of the slope bound, nm.
const BIN_NM: f64 = 10.0;

/// Angles across the view at which the slope bound samples |∂R/∂θ|.
const BOUND_ANGLES: usize = 5;

/// The incidence angle of each sensor row, and what the correction needs.
#[derive(Clone, Debug)]
pub struct SensorAngles {
    theta_c: f64,
    rows: Vec<f64>,
    /// Every band at θ_c.
    centre: BandAngles,
    /// `G_b` per thickness bin: `g[bin · n_bands + b]`.
    g: Vec<f64>,
    g_d0: f64,
    n_bands: usize,
    mode: Correction,
}

/// One row's per-band angles.
#[derive(Clone, Debug, Default)]
pub struct RowAngles {
    /// θ_b per band, rad.
    theta: Vec<f64>,
    /// The model's coefficients at them.
    at: BandAngles,
    /// θ_b − θ_c per band, rad.
    dtheta: Vec<f64>,
    /// Some band off θ_c.
    spread: bool,
}

/// Working memory of the correction (one per thread).
#[derive(Clone, Debug, Default)]
pub struct AngleScratch {
    row: RowAngles,
    /// The row's reflectance before the correction.
    base: Vec<f32>,
    /// Thickness per pixel the misfit is evaluated at.
    d: Vec<f64>,
    e: Vec<f64>,
    buf: Vec<f64>,
    /// One pixel's spectrum.
    y: Vec<f64>,
    table: RowTable,
}

impl SensorAngles {
    /// Angles `rows` (rad, one per sensor row) around the scene's `theta_c`
    /// for the film `model`, whose fits search `d_range` (nm).
    pub fn new(
        theta_c: f64,
        rows: Vec<f64>,
        model: &FilmModel,
        d_range: (f64, f64),
        mode: Correction,
    ) -> Result<SensorAngles, LineError> {
        let ok = |t: f64| t.is_finite() && (0.0..std::f64::consts::FRAC_PI_2).contains(&t);
        if !ok(theta_c) || rows.iter().any(|&t| !ok(t)) || rows.is_empty() {
            return Err(LineError::Config(format!(
                "incidence angles per sensor row must lie in 0–90° (centre {:.3}°, rows {:.3?}°)",
                theta_c.to_degrees(),
                rows.iter().map(|t| t.to_degrees()).collect::<Vec<_>>()
            )));
        }
        let lo = rows.iter().copied().fold(theta_c, f64::min);
        let hi = rows.iter().copied().fold(theta_c, f64::max);
        let n_bands = model.n_bands();
        let mut centre = BandAngles::default();
        model.band_angles(&vec![theta_c; n_bands], &mut centre);
        let mut a = SensorAngles {
            theta_c,
            rows,
            centre,
            g: Vec::new(),
            g_d0: d_range.0,
            n_bands,
            mode,
        };
        a.g = slope_bound(model, (lo, hi), d_range, n_bands);
        Ok(a)
    }

    /// The scene's angle, rad.
    pub fn centre(&self) -> f64 {
        self.theta_c
    }

    /// The angle of each sensor row, rad.
    pub fn rows(&self) -> &[f64] {
        &self.rows
    }

    /// When the correction applies.
    pub fn mode(&self) -> Correction {
        self.mode
    }

    /// The angle a band seen at sensor row `s` was seen at (θ_c if unseen
    /// or beyond the table).
    fn angle_of(&self, s: u32) -> f64 {
        self.rows.get(s as usize).copied().unwrap_or(self.theta_c)
    }

    /// The angles of a row whose band `b` was seen at `sensor_rows[b]`,
    /// with `model`'s coefficients at them.
    pub fn row(&self, model: &FilmModel, sensor_rows: &[u32], out: &mut RowAngles) {
        out.theta.clear();
        out.theta
            .extend(sensor_rows.iter().map(|&s| self.angle_of(s)));
        out.dtheta.clear();
        out.dtheta
            .extend(out.theta.iter().map(|&t| t - self.theta_c));
        out.spread = out.dtheta.iter().any(|&d| d != 0.0);
        if out.spread {
            model.band_angles(&out.theta, &mut out.at);
        }
    }

    /// A bound on max ‖e(d)‖₂ over thicknesses `d_lo`–`d_hi` (nm) for a
    /// row's angles: `sqrt(Σ_b G_b² (θ_b − θ_c)²)`.
    pub fn bound(&self, row: &RowAngles, d_lo: f64, d_hi: f64) -> f64 {
        let nb = self.n_bands;
        let n_bins = self.g.len() / nb.max(1);
        if n_bins == 0 {
            return f64::INFINITY;
        }
        let bin = |d: f64| (((d - self.g_d0) / BIN_NM).floor().max(0.0) as usize).min(n_bins - 1);
        let (b0, b1) = (bin(d_lo), bin(d_hi));
        let mut sum = 0.0;
        for (b, &dt) in row.dtheta.iter().enumerate().take(nb) {
            if dt == 0.0 {
                continue;
            }
            let g = (b0..=b1).map(|i| self.g[i * nb + b]).fold(0.0, f64::max);
            sum += g * g * dt * dt;
        }
        sum.sqrt()
    }

    /// `e_b(d) = R_b(d, θ_b) − R_b(d, θ_c)` for a row's angles, into `e`
    /// (`buf`: working memory).
    pub fn misfit(
        &self,
        model: &FilmModel,
        row: &RowAngles,
        d: f64,
        e: &mut Vec<f64>,
        buf: &mut Vec<f64>,
    ) {
        let nb = row.dtheta.len();
        e.clear();
        e.resize(nb, 0.0);
        if !row.spread {
            return;
        }
        buf.resize(nb, 0.0);
        model.eval_band_angles(&row.at, d, e);
        model.eval_band_angles(&self.centre, d, buf);
        for (eb, &rc) in e.iter_mut().zip(buf.iter()) {
            *eb -= rc;
        }
    }

    /// After `solver` solved the one-row `cube` into `est` (at θ_c, with
    /// `scratch`): correct the row for its bands' angles where the rule
    /// asks for it (or always / never, as set), solving it again. Returns
    /// whether it was corrected; `cube` then holds the corrected spectra.
    pub fn correct_row(
        &self,
        solver: &Solver,
        cube: &mut Cube,
        sensor_rows: &[u32],
        est: &mut [PixelEstimate],
        scratch: &mut Scratch,
        sc: &mut AngleScratch,
    ) -> bool {
        let Some(model) = solver.film_model() else {
            return false;
        };
        if self.mode == Correction::Off || !self.centre.belongs_to(model) {
            return false;
        }
        self.row(model, sensor_rows, &mut sc.row);
        if !sc.row.spread || !fit_thicknesses(est, scratch, &mut sc.d) {
            return false;
        }
        if self.mode == Correction::Auto {
            let (lo, hi) =
                sc.d.iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &d| {
                        (a.min(d), b.max(d))
                    });
            let sigma = solver.noise().map(|n| n.typical_sigma(0.05));
            if sigma.is_some_and(|s| self.bound(&sc.row, lo - BIN_NM, hi + BIN_NM) <= THRESHOLD * s)
            {
                return false;
            }
        }
        self.iterate(solver, model, cube, est, scratch, sc, ITERATIONS);
        true
    }

    /// The correction from the thicknesses in `sc.d`: per pixel, the
    /// thickness refined by Gauss–Newton on the model with each band at its
    /// own angle (cheap: no search, the first solve found the fringe
    /// order), then the row's spectra less e at it, solved again by the
    /// solver (its flags and σ on the corrected spectra) — `solves` times.
    /// The per-band model comes from the row's table ([`RowTable`]) where
    /// the row's thicknesses span less than [`TABLE_MAX_NM`], else from
    /// the model itself.
    #[allow(clippy::too_many_arguments)]
    fn iterate(
        &self,
        solver: &Solver,
        model: &FilmModel,
        cube: &mut Cube,
        est: &mut [PixelEstimate],
        scratch: &mut Scratch,
        sc: &mut AngleScratch,
        solves: usize,
    ) {
        let w = cube.width;
        let nb = cube.bands.len();
        sc.base.clear();
        sc.base.extend_from_slice(&cube.data[..w * nb]);
        for _ in 0..solves {
            let (lo, hi) = range(&sc.d);
            let tabled = sc.table.build(
                model,
                &sc.row.at,
                &self.centre,
                (lo - TABLE_MARGIN_NM, hi + TABLE_MARGIN_NM),
                nb,
            );
            for x in 0..w {
                sc.y.clear();
                sc.y.extend((0..nb).map(|b| f64::from(sc.base[b * w + x])));
                let table = tabled.then_some(&sc.table);
                let d = self.refine(
                    model,
                    &sc.row,
                    table,
                    &sc.y,
                    sc.d[x],
                    &mut sc.e,
                    &mut sc.buf,
                );
                sc.d[x] = d;
                match table.filter(|t| t.covers(d)) {
                    Some(t) => t.misfit(d, &mut sc.e),
                    None => self.misfit(model, &sc.row, d, &mut sc.e, &mut sc.buf),
                }
                for (b, &eb) in sc.e.iter().enumerate() {
                    let i = b * w + x;
                    let v = sc.base[i];
                    cube.data[i] = if v.is_finite() { v - eb as f32 } else { v };
                }
            }
            solver.solve_row(cube, 0, est, scratch);
            if !fit_thicknesses(est, scratch, &mut sc.d) {
                break;
            }
        }
    }

    /// Gauss–Newton on `‖y − R(d, θ_b)‖²` from `d0` (steps of at most
    /// [`MAX_STEP_NM`], until one is below 1e-6 nm or [`NEWTON_STEPS`]).
    #[allow(clippy::too_many_arguments)]
    fn refine(
        &self,
        model: &FilmModel,
        row: &RowAngles,
        table: Option<&RowTable>,
        y: &[f64],
        d0: f64,
        r: &mut Vec<f64>,
        dr: &mut Vec<f64>,
    ) -> f64 {
        let nb = y.len();
        r.resize(nb, 0.0);
        dr.resize(nb, 0.0);
        let mut d = d0;
        for _ in 0..NEWTON_STEPS {
            match table.filter(|t| t.covers(d)) {
                Some(t) => t.model(d, r, dr),
                None => model.eval_band_angles_deriv(&row.at, d, r, dr),
            }
            let (mut num, mut den) = (0.0, 0.0);
            for b in 0..nb {
                if y[b].is_finite() {
                    num += (y[b] - r[b]) * dr[b];
                    den += dr[b] * dr[b];
                }
            }
            if !(den > 0.0 && num.is_finite()) {
                break;
            }
            let step = (num / den).clamp(-MAX_STEP_NM, MAX_STEP_NM);
            d = (d + step).max(0.0);
            if step.abs() < 1e-6 {
                break;
            }
        }
        if d.is_finite() {
            d
        } else {
            d0
        }
    }
}

/// Thickness step of a row's table, nm: cubic Hermite interpolation of a
/// fringe whose phase moves ≤ 0.05 rad/nm errs by ≲ A·(0.05 h)⁴/384 —
/// 2e-10 for a fringe amplitude A = 0.05 at h = 1 nm.
const TABLE_STEP_NM: f64 = 1.0;

/// A row's table covers its thicknesses and this much beyond, nm (room
/// for the Gauss–Newton steps; beyond, the model itself is evaluated).
const TABLE_MARGIN_NM: f64 = 15.0;

/// Rows whose thicknesses span more than this evaluate the model per
/// pixel instead (a table would cost more than it saves).
const TABLE_MAX_NM: f64 = 400.0;

/// A row's per-band model over its thickness range at [`TABLE_STEP_NM`]:
/// `R(d, θ_b)` and `e(d)` with their d-slopes, interpolated as cubic
/// Hermite splines — two model evaluations per sample instead of per pixel
/// and step.
#[derive(Clone, Debug, Default)]
struct RowTable {
    d0: f64,
    n: usize,
    nb: usize,
    /// `v[j · nb + b]` = [R, dR/dd, e, de/dd] at `d0 + j·step`.
    v: Vec<[f64; 4]>,
    r: Vec<f64>,
    dr: Vec<f64>,
    rc: Vec<f64>,
    drc: Vec<f64>,
}

impl RowTable {
    /// Tabulate over `span` (false: too wide, not built).
    fn build(
        &mut self,
        model: &FilmModel,
        at: &BandAngles,
        centre: &BandAngles,
        span: (f64, f64),
        nb: usize,
    ) -> bool {
        let (lo, hi) = (span.0.max(0.0), span.1);
        let width = hi - lo;
        if width.is_nan() || width > TABLE_MAX_NM + 2.0 * TABLE_MARGIN_NM || !lo.is_finite() {
            return false;
        }
        self.d0 = lo;
        self.n = ((hi - lo) / TABLE_STEP_NM).ceil() as usize + 1;
        self.nb = nb;
        self.v.clear();
        for v in [&mut self.r, &mut self.dr, &mut self.rc, &mut self.drc] {
            v.resize(nb, 0.0);
        }
        for j in 0..self.n {
            let d = lo + j as f64 * TABLE_STEP_NM;
            model.eval_band_angles_deriv(at, d, &mut self.r, &mut self.dr);
            model.eval_band_angles_deriv(centre, d, &mut self.rc, &mut self.drc);
            for b in 0..nb {
                self.v.push([
                    self.r[b],
                    self.dr[b],
                    self.r[b] - self.rc[b],
                    self.dr[b] - self.drc[b],
                ]);
            }
        }
        true
    }

    fn covers(&self, d: f64) -> bool {
        d >= self.d0 && d <= self.d0 + (self.n.saturating_sub(1)) as f64 * TABLE_STEP_NM
    }

    /// Interval and Hermite basis at `d` (inside the table).
    fn basis(&self, d: f64) -> (usize, [f64; 4], f64) {
        let x = (d - self.d0) / TABLE_STEP_NM;
        let j = (x.floor() as usize).min(self.n.saturating_sub(2));
        let t = x - j as f64;
        let (t2, t3) = (t * t, t * t * t);
        let h = TABLE_STEP_NM;
        (
            j,
            [
                2.0 * t3 - 3.0 * t2 + 1.0,
                (t3 - 2.0 * t2 + t) * h,
                -2.0 * t3 + 3.0 * t2,
                (t3 - t2) * h,
            ],
            t,
        )
    }

    /// `R(d, θ_b)` and its d-slope (linear between samples: it only steers
    /// the steps).
    fn model(&self, d: f64, r: &mut [f64], dr: &mut [f64]) {
        let (j, w, t) = self.basis(d);
        let (a, b) = (&self.v[j * self.nb..], &self.v[(j + 1) * self.nb..]);
        for k in 0..self.nb.min(r.len()).min(dr.len()) {
            let (p, q) = (a[k], b[k]);
            r[k] = w[0] * p[0] + w[1] * p[1] + w[2] * q[0] + w[3] * q[1];
            dr[k] = p[1] + t * (q[1] - p[1]);
        }
    }

    /// `e(d)`.
    fn misfit(&self, d: f64, e: &mut Vec<f64>) {
        let (j, w, _) = self.basis(d);
        let (a, b) = (&self.v[j * self.nb..], &self.v[(j + 1) * self.nb..]);
        e.clear();
        e.extend(
            (0..self.nb).map(|k| w[0] * a[k][2] + w[1] * a[k][3] + w[2] * b[k][2] + w[3] * b[k][3]),
        );
    }
}

/// The smallest and largest of `v`.
fn range(v: &[f64]) -> (f64, f64) {
    v.iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &d| {
            (a.min(d), b.max(d))
        })
}

/// Each pixel's thickness to evaluate the misfit at: its estimate, else its
/// (flagged) best fit, else its nearest neighbour's in the row. False when
/// no pixel has one.
fn fit_thicknesses(est: &[PixelEstimate], scratch: &Scratch, d: &mut Vec<f64>) -> bool {
    let fits = scratch.fit_thickness();
    d.clear();
    d.extend(est.iter().enumerate().map(|(x, e)| {
        if e.is_valid() {
            e.thickness_nm
        } else {
            fits.get(x).copied().unwrap_or(f64::NAN)
        }
    }));
    let Some(first) = d.iter().position(|v| v.is_finite()) else {
        return false;
    };
    // Forward fill, then the leading gap from the first finite value.
    let mut last = d[first];
    for v in d.iter_mut().skip(first) {
        if v.is_finite() {
            last = *v;
        } else {
            *v = last;
        }
    }
    let head = d[first];
    d[..first].fill(head);
    true
}

/// `G_b` per thickness bin of [`BIN_NM`] from `d_range.0`: the largest
/// |∂R_b/∂θ| over the bin and [`BOUND_ANGLES`] angles across `theta`,
/// sampled finely enough in d (a phase step ≤ 0.05 rad: the sampled
/// maximum is within 0.1 % of the true one).
fn slope_bound(model: &FilmModel, theta: (f64, f64), d_range: (f64, f64), nb: usize) -> Vec<f64> {
    let (d_lo, d_hi) = (d_range.0.max(0.0), d_range.1.max(d_range.0 + BIN_NM));
    let n_bins = ((d_hi - d_lo) / BIN_NM).ceil().max(1.0) as usize;
    let mut g = vec![0.0f64; n_bins * nb];
    let mut out = ModelOut::new(nb);
    for i in 0..BOUND_ANGLES {
        let t = theta.0 + (theta.1 - theta.0) * i as f64 / (BOUND_ANGLES - 1) as f64;
        let step = (0.05 / model.max_phase_rate(t).max(1e-9)).min(BIN_NM / 4.0);
        let n = ((d_hi - d_lo) / step).ceil() as usize + 1;
        for j in 0..n {
            let d = (d_lo + j as f64 * step).min(d_hi);
            model.eval(d, t, &mut out, true);
            // A sample on a bin edge counts for both bins.
            let x = (d - d_lo) / BIN_NM;
            let bins = [x.floor() as usize, (x.ceil() as usize).max(1) - 1];
            for bin in bins {
                let bin = bin.min(n_bins - 1);
                for (b, &s) in out.dr_dth.iter().enumerate().take(nb) {
                    let v = &mut g[bin * nb + b];
                    *v = v.max(s.abs());
                }
            }
        }
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::band::Band;
    use crate::optics::dispersion::Dispersion;
    use crate::optics::{airy, Media, Polarization};

    fn model(bands: &[Band]) -> FilmModel {
        FilmModel::new(
            bands,
            &Dispersion::constant(1.0),
            &Dispersion::constant(1.46),
            &Dispersion::constant(1.65),
            Polarization::Unpolarized,
            &vec![false; bands.len()],
        )
        .unwrap()
    }

    fn bands() -> Vec<Band> {
        (0..31)
            .map(|i| Band::new(400.0 + 10.0 * i as f64, 0.0).unwrap())
            .collect()
    }

    /// ±4° across 24 rows around 30°, every band at another row.
    fn setup(mode: Correction) -> (SensorAngles, FilmModel, Vec<u32>) {
        let b = bands();
        let m = model(&b);
        let tc = 30f64.to_radians();
        let rows: Vec<f64> = (0..24)
            .map(|s| tc + (s as f64 - 11.5) * (8.0 / 23.0f64).to_radians())
            .collect();
        let a = SensorAngles::new(tc, rows, &m, (0.0, 1200.0), mode).unwrap();
        let sensor_rows: Vec<u32> = (0..31).map(|b| (b * 7 % 24) as u32).collect();
        (a, m, sensor_rows)
    }

    #[test]
    fn misfit_matches_airy_at_each_bands_angle() {
        let (a, m, rows) = setup(Correction::Auto);
        let mut ra = RowAngles::default();
        a.row(&m, &rows, &mut ra);
        assert!(ra.spread);
        let media = Media::real(1.0, 1.46, 1.65);
        let (mut e, mut buf) = (Vec::new(), Vec::new());
        let (mut worst, mut largest) = (0.0f64, 0.0f64);
        for d in (0..=240).map(|i| 5.0 * i as f64) {
            a.misfit(&m, &ra, d, &mut e, &mut buf);
            for (b, band) in bands().iter().enumerate() {
                let lam = band.center_nm;
                let r = |t: f64| airy::reflectance(media, d, t, lam, Polarization::Unpolarized);
                let exact = r(a.angle_of(rows[b])) - r(a.centre());
                worst = worst.max((e[b] - exact).abs());
                largest = largest.max(exact.abs());
            }
        }
        // Two formulations of the same Airy reflectance (real coefficients
        // and cos Δ here, complex amplitudes in `optics::airy`): they agree
        // to rounding (phases up to ~55 rad, each good to ~1e-14; measured
        // 3e-16). 1e-12 allows for that and is a ten-billionth of the
        // misfit, which must itself be large (else the test shows nothing).
        eprintln!("misfit error {worst:e}, misfit up to {largest:e}");
        assert!(largest > 5e-3, "the spread barely matters: {largest}");
        assert!(
            worst < 1e-12,
            "misfit error {worst:e} (misfit up to {largest:e})"
        );
    }

    #[test]
    fn the_bound_covers_the_misfit_and_vanishes_without_spread() {
        let (a, m, rows) = setup(Correction::Auto);
        let mut ra = RowAngles::default();
        a.row(&m, &rows, &mut ra);
        let (mut e, mut buf) = (Vec::new(), Vec::new());
        for lo in [0.0, 300.0, 800.0] {
            let hi = lo + 60.0;
            let bound = a.bound(&ra, lo, hi);
            let worst = (0..=600)
                .map(|i| {
                    a.misfit(&m, &ra, lo + 0.1 * i as f64, &mut e, &mut buf);
                    e.iter().map(|v| v * v).sum::<f64>().sqrt()
                })
                .fold(0.0, f64::max);
            // A bound, and not a loose one: the bands' worst slopes fall at
            // different thicknesses, so it is above the worst misfit by
            // at most ~√2 — 3× leaves room and still fails a wrong bound.
            eprintln!("{lo}: bound {bound:e}, worst {worst:e}");
            assert!(
                bound >= worst && bound < 3.0 * worst,
                "{lo}: {bound} vs {worst}"
            );
        }
        // Every band at the centre row's angle: nothing to correct.
        let centre = vec![u32::MAX; 31];
        a.row(&m, &centre, &mut ra);
        assert!(!ra.spread);
        assert_eq!(a.bound(&ra, 0.0, 1200.0), 0.0);
    }

    /// Noise-free spectra of the demo's film, each band at its own angle
    /// (±4° around 30°): the first solve at 30° is biased; one correction
    /// (Gauss–Newton on the per-band model, then the solver on the
    /// corrected spectra) leaves nothing a second one would remove.
    #[test]
    fn one_correction_reaches_the_per_band_fit() {
        use crate::estimate::Mode;
        use crate::scene::Scene;
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes/web-film.toml");
        let scene = Scene::load(&path).unwrap();
        let bands = scene.bands.clone().unwrap();
        let solver = Solver::new(&scene, &bands, Mode::Balanced).unwrap();
        let model = solver.film_model().unwrap();
        let tc = 30f64.to_radians();
        let rows: Vec<f64> = (0..24)
            .map(|s| tc + (s as f64 - 11.5) * (8.0 / 23.0f64).to_radians())
            .collect();
        let (lo, hi, _) = solver.thickness_range();
        let a = SensorAngles::new(tc, rows, model, (lo, hi), Correction::Always).unwrap();
        let sensor_rows: Vec<u32> = (0..31).map(|b| (b * 7 % 24) as u32).collect();
        let mut ra = RowAngles::default();
        a.row(model, &sensor_rows, &mut ra);
        let w = 24;
        let truth: Vec<f64> = (0..w).map(|x| 270.0 + 4.5 * x as f64).collect();
        let mut cube = Cube::zeros(w, 1, bands.clone());
        let mut r = vec![0.0; bands.len()];
        for (x, &d) in truth.iter().enumerate() {
            model.eval_band_angles(&ra.at, d, &mut r);
            for (b, &v) in r.iter().enumerate() {
                cube.data[b * w + x] = v as f32;
            }
        }
        let mut errs = Vec::new();
        for n in 0..3 {
            let mut c = cube.clone();
            let mut est = vec![PixelEstimate::invalid(crate::estimate::Reason::Masked); w];
            let (mut scratch, mut sc) = (Scratch::default(), AngleScratch::default());
            solver.solve_row(&c, 0, &mut est, &mut scratch);
            assert!(fit_thicknesses(&est, &scratch, &mut sc.d));
            sc.row = ra.clone();
            a.iterate(&solver, model, &mut c, &mut est, &mut scratch, &mut sc, n);
            let worst =
                sc.d.iter()
                    .zip(&truth)
                    .map(|(d, t)| (d - t).abs())
                    .fold(0.0, f64::max);
            if n > 0 {
                // At the fixed point the model explains the data: valid.
                assert!(est.iter().all(|e| e.is_valid()), "{n}: {est:?}");
            }
            errs.push(worst);
        }
        eprintln!("worst error after 0, 1, 2 corrections: {errs:?} nm");
        // Uncorrected: biased by about 2σ here (σ ≈ 0.45 nm at noise
        // 0.001; measured 0.84 nm).
        assert!(errs[0] > 0.5, "{errs:?}");
        // Corrected: within 2 % of σ of the truth (measured 6e-5 nm: the
        // f32 spectra and the solver's own convergence), and a second
        // correction changes it by no more than that.
        assert!(errs[1] < 0.01, "{errs:?}");
        assert!((errs[2] - errs[1]).abs() < 0.01, "{errs:?}");
    }

    #[test]
    fn the_rows_table_matches_the_model() {
        let (a, m, rows) = setup(Correction::Auto);
        let mut ra = RowAngles::default();
        a.row(&m, &rows, &mut ra);
        let mut t = RowTable::default();
        assert!(t.build(&m, &ra.at, &a.centre, (280.0, 420.0), 31));
        assert!(!t.clone().build(&m, &ra.at, &a.centre, (0.0, 2000.0), 31));
        let (mut e, mut e_ref, mut buf) = (Vec::new(), Vec::new(), Vec::new());
        let (mut r, mut dr) = (vec![0.0; 31], vec![0.0; 31]);
        let (mut r_ref, mut dr_ref) = (vec![0.0; 31], vec![0.0; 31]);
        let (mut worst_r, mut worst_e, mut worst_dr) = (0.0f64, 0.0f64, 0.0f64);
        for i in 0..=1400 {
            let d = 280.0 + 0.1 * i as f64 + 0.0123;
            if !t.covers(d) {
                continue;
            }
            t.misfit(d, &mut e);
            a.misfit(&m, &ra, d, &mut e_ref, &mut buf);
            t.model(d, &mut r, &mut dr);
            m.eval_band_angles_deriv(&ra.at, d, &mut r_ref, &mut dr_ref);
            for b in 0..31 {
                worst_e = worst_e.max((e[b] - e_ref[b]).abs());
                worst_r = worst_r.max((r[b] - r_ref[b]).abs());
                worst_dr = worst_dr.max(
                    (dr[b] - dr_ref[b]).abs() / dr_ref.iter().map(|v| v.abs()).fold(0.0, f64::max),
                );
            }
        }
        eprintln!("table error: R {worst_r:e}, e {worst_e:e}, dR/dd (relative) {worst_dr:e}");
        // Values: the Hermite bound of TABLE_STEP_NM (2e-10), with room —
        // far below what moves a thickness (σ_R = 1e-3). The slope only
        // steers Gauss–Newton: linear between samples, a few % is enough.
        assert!(worst_r < 1e-8 && worst_e < 1e-8, "{worst_r:e} {worst_e:e}");
        assert!(worst_dr < 0.05, "{worst_dr:e}");
    }

    #[test]
    fn refuses_angles_outside_the_quadrant() {
        let b = bands();
        let m = model(&b);
        let e =
            SensorAngles::new(0.5, vec![0.5, 1.7], &m, (0.0, 100.0), Correction::Auto).unwrap_err();
        assert!(e.to_string().contains("0–90°"), "{e}");
    }
}
