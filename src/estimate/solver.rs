//! The per-pixel solver and the global film-index search.
//!
//! Per pixel, in every mode but `fast`:
//!
//! 1. **Fringe search** (independent of the film index): the spectrum is
//!    projected on `A + B·cos(4π g / λ)` for a grid of optical thicknesses
//!    `g = d·n2·cos θ2` (basis and normal equations precomputed per band
//!    set, so a grid point costs one dot product). Local minima of the
//!    residual whose `B` has the sign the scene's indices allow (half-wave
//!    points are peaks for `n1 < n2 < n3`, valleys for `n2 > n3`) are the
//!    candidate fringe orders: the interference lattice of Eq. 12–15
//!    without a film-index grid.
//! 2. **Angle start** (only when unknown): the fitted `A ± B` are the
//!    half- and quarter-wave envelopes; the angle whose model envelopes
//!    match them best (Eq. 8–11 generalised to both envelopes, peaks or
//!    valleys) starts the refinement.
//! 3. **Refinement**: Levenberg–Marquardt on the unknowns (thickness, and the
//!    angle when unknown) with the exact model ([`super::model`]); standard
//!    errors from the Jacobian scaled by the residual variance.
//! 4. **Checks**: a second candidate order refined too; if it fits as well
//!    the pixel is flagged "ambiguous order". A weak angle is flagged "angle
//!    not identifiable" with its (large) σ.
//!
//! The film index, uniform over an object, is estimated once from a sample
//! of pixels by profiling the summed per-pixel residual over the index
//! (coarse grid, then a local quadratic fit), which also gives its standard
//! error. Both branches of the n2 ↔ n1·n3/n2 near-symmetry are located and
//! the χ² difference between them is reported; a prior breaks a tie the data
//! cannot.

use super::angle::half_wave_sin2;
use super::detect::CandidatePlanes;
use super::fastmath::round;
use super::model::{FilmModel, ModelOut};
use super::{Cube, EstimateError, Mode, ParamMaps, PixelEstimate, Reason};
use crate::optics::band::Band;
use crate::optics::dispersion::Dispersion;
use crate::optics::Polarization;
use crate::scene::{AngleKnowledge, FilmKnowledge, Scene};
use rayon::prelude::*;
use std::f64::consts::PI;

/// The film index used for a fit: estimated once from the image, or known.
#[derive(Clone, Debug, PartialEq)]
pub struct IndexEstimate {
    /// Index (at the middle band for a dispersive known film).
    pub n: f64,
    /// Standard error (0 when known).
    pub sigma: f64,
    /// Whether it was estimated.
    pub estimated: bool,
    /// The other branch of the n2 ↔ n1·n3/n2 near-symmetry, if one was found.
    pub twin: Option<f64>,
    /// χ² by which the twin fits worse (large: resolved; small: ambiguous).
    pub twin_delta_chi2: f64,
    /// Reflectance noise σ estimated from the fit residuals.
    pub noise_sigma: f64,
    /// A human-readable note (e.g. "twin not resolved; prior used").
    pub note: String,
}

/// Pixels sampled (on a jittered grid) for the global film-index search
/// (half as many in `fast` mode).
pub const INDEX_SAMPLE_PIXELS: usize = 400;

/// Step of the coarse film-index profile.
const INDEX_GRID_STEP: f64 = 0.02;

/// Reflectance error of point sampling above which the accurate mode
/// integrates the passband (a fifth of the paper's noise level).
pub const INTEGRATION_TOLERANCE: f64 = 2e-4;

/// Largest number of bands a pixel may have.
pub const MAX_BANDS: usize = 512;

/// Angle σ above which the angle is reported as not identifiable, degrees.
pub const ANGLE_SIGMA_LIMIT_DEG: f64 = 0.25;

/// Reusable per-thread working memory of the solver.
#[derive(Clone, Debug, Default)]
pub struct Scratch {
    /// The caller's gathered spectrum (solve_row).
    pixel: Vec<f64>,
    sorted_y: Vec<f64>,
    spectrum: Vec<f64>,
    weight: Vec<f64>,
    cur: ModelOut,
    trial: ModelOut,
}

impl Scratch {
    fn ensure(&mut self, n: usize) {
        if self.spectrum.len() != n {
            self.spectrum = vec![0.0; n];
            self.weight = vec![0.0; n];
            self.cur = ModelOut::new(n);
            self.trial = ModelOut::new(n);
        }
    }
}

/// The fringe-search basis: `cos(4π g_j / λ_k)` for a grid of optical
/// thicknesses, with the inverse normal equations of `[1, cos]` per grid
/// point for a complete spectrum.
#[derive(Clone, Debug)]
struct FringeBasis {
    g: Vec<f64>,
    /// `basis[j * nb + k]`.
    basis: Vec<f32>,
    /// Inverse of `[[N, Σc], [Σc, Σc²]]`, as `(a, b, c)` of a symmetric 2×2;
    /// NaN where the basis is too close to constant to separate.
    minv: Vec<[f64; 3]>,
    nb: usize,
}

impl FringeBasis {
    fn new(bands: &[Band], g_max: f64) -> FringeBasis {
        let nb = bands.len();
        let lam_min = bands
            .iter()
            .map(|b| b.center_nm)
            .fold(f64::INFINITY, f64::min);
        // Phase step at the shortest wavelength ≤ 0.35 rad: the residual's
        // minimum is never missed between grid points.
        let step = 0.35 * lam_min / (4.0 * PI);
        let n = (g_max / step).ceil() as usize + 1;
        let mut g = Vec::with_capacity(n);
        let mut basis = Vec::with_capacity(n * nb);
        let mut minv = Vec::with_capacity(n);
        for j in 0..n {
            let gj = j as f64 * step;
            let (mut s1, mut s2) = (0.0, 0.0);
            for b in bands {
                let c = (4.0 * PI * gj / b.center_nm).cos();
                basis.push(c as f32);
                s1 += c;
                s2 += c * c;
            }
            let nf = nb as f64;
            let det = nf * s2 - s1 * s1;
            // Relative spread of the cosine across bands: below this the
            // fringe term is indistinguishable from the constant.
            if det > 0.02 * nf * nf {
                minv.push([s2 / det, -s1 / det, nf / det]);
            } else {
                minv.push([f64::NAN; 3]);
            }
            g.push(gj);
        }
        FringeBasis { g, basis, minv, nb }
    }
}

/// A candidate from the fringe search.
#[derive(Clone, Copy, Debug, Default)]
struct Candidate {
    g: f64,
    a: f64,
    b: f64,
    sse: f64,
}

const MAX_CANDIDATES: usize = 4;

/// How hard the per-pixel solve works: what a [`Mode`] means in practice.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Effort {
    /// Try the closed-form extrema path first.
    closed_form: bool,
    /// Stop at the closed form.
    closed_form_only: bool,
    /// How many candidate starts are refined.
    n_refine: usize,
    /// Iteration cap of each refinement.
    iters: usize,
    /// After a closed-form start, also refine the best other fringe order
    /// and flag the pixel if it fits as well.
    verify_order: bool,
}

impl Effort {
    fn of(mode: Mode) -> Effort {
        match mode {
            Mode::Fast => Effort {
                closed_form: true,
                closed_form_only: true,
                n_refine: 1,
                iters: 6,
                verify_order: false,
            },
            Mode::Balanced => Effort {
                closed_form: true,
                closed_form_only: false,
                n_refine: 2,
                iters: 8,
                verify_order: false,
            },
            Mode::Accurate => Effort {
                closed_form: true,
                closed_form_only: false,
                n_refine: 3,
                iters: 25,
                verify_order: true,
            },
        }
    }

    /// The global index search: the full candidate search (no noise level
    /// is known yet to judge a closed-form start), two orders refined.
    const INDEX_SEARCH: Effort = Effort {
        closed_form: false,
        closed_form_only: false,
        n_refine: 2,
        iters: 10,
        verify_order: false,
    };
}

/// A pixel of the global index search, with its fringe candidates for
/// both fringe signs precomputed (they do not depend on the film index).
#[derive(Clone, Debug)]
struct SamplePixel {
    spectrum: Vec<f64>,
    theta: Option<f64>,
    /// Candidates for sign +1 (index 0) and −1 (index 1).
    cands: [[Candidate; MAX_CANDIDATES]; 2],
    n_cands: [usize; 2],
}

/// A fringe extremum located between bands.
#[derive(Clone, Copy, Debug, Default)]
struct Ext {
    /// Wavenumber, nm⁻¹.
    pos: f64,
    /// Reflectance at the vertex.
    val: f64,
    /// +1 maximum, −1 minimum.
    kind: i8,
    /// The sorted band whose [`Window`] located it, the vertex offset in
    /// that window and 1/a of its parabola: enough for the variances,
    /// which are worked out only for the extrema the closed form keeps.
    band: u16,
    u: f64,
    inv_a: f64,
}

impl Ext {
    /// Variance factors (× σ_R²) of the position (nm⁻¹) and the level, by
    /// the delta method. Vertex u = −b/2a: ∂u/∂(a, b) = (−u/a, −1/2a);
    /// level v = c − b²/4a: ∂v/∂(a, b, c) = (u², u, 1).
    #[inline]
    fn var_pos(&self, win: &Window) -> f64 {
        let m = &win.minv;
        let (ga, gb) = (-self.u * self.inv_a, -0.5 * self.inv_a);
        (ga * ga * m[0][0] + 2.0 * ga * gb * m[0][1] + gb * gb * m[1][1]) * 1e-8
    }

    #[inline]
    fn var_val(&self, win: &Window) -> f64 {
        let m = &win.minv;
        let (u, u2) = (self.u, self.u * self.u);
        u2 * u2 * m[0][0]
            + u2 * m[1][1]
            + m[2][2]
            + 2.0 * (u2 * u * m[0][1] + u2 * m[0][2] + u * m[1][2])
    }
}

/// The least-squares parabola `v = a u² + b u + c` (u: wavenumber offset
/// from the candidate band, in 1e-4 nm⁻¹ for conditioning) through the
/// samples around one sorted band: five samples inside the band range,
/// four (0–3 or the last four) at the second and second-to-last bands, so
/// an extremum next to either end of the range is still located.
#[derive(Clone, Copy, Debug)]
struct Window {
    /// First sorted band of the window.
    lo: usize,
    /// Samples in the window (4 or 5).
    len: usize,
    /// Their wavenumber offsets (unused slots 0).
    u: [f64; 5],
    /// Inverse normal matrix.
    minv: [[f64; 3]; 3],
    /// The vertex must lie within this offset range.
    vertex: (f64, f64),
    /// Mean sample spacing (offset units).
    spacing: f64,
}

impl Window {
    fn new(sorted: &[(usize, f64, f64)], i: usize) -> Option<Window> {
        let nb = sorted.len();
        let (lo, len) = if i >= 2 && i + 2 < nb {
            (i - 2, 5)
        } else if i == 1 && nb >= 4 {
            (0, 4)
        } else if i + 2 == nb && nb >= 4 {
            (nb - 4, 4)
        } else {
            return None;
        };
        let x0 = sorted[i].2;
        let mut u = [0.0; 5];
        let mut m = [[0.0; 3]; 3];
        for k in 0..len {
            u[k] = (sorted[lo + k].2 - x0) * 1e4;
            let row = [u[k] * u[k], u[k], 1.0];
            for r in 0..3 {
                for c in 0..3 {
                    m[r][c] += row[r] * row[c];
                }
            }
        }
        let (u_min, u_max) = u[..len]
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        // The detection (on smoothed data) puts a real extremum within a
        // band of the candidate: the vertex may sit up to 1.5 band spacings
        // from it. A vertex further out is a flat noise parabola's, not an
        // extremum (and would win the merge of two of a kind by being
        // extrapolated). At an end, only within the samples.
        let vertex = if len == 5 {
            (1.5 * u[3], 1.5 * u[1])
        } else {
            (u_min, u_max)
        };
        Some(Window {
            lo,
            len,
            u,
            minv: inv3(m)?,
            vertex,
            spacing: (u_max - u_min) / (len - 1) as f64,
        })
    }
}

/// Most extrema kept per pixel.
const MAX_EXT: usize = 16;

/// Largest fringe phase step between neighbouring samples (rad) at which
/// `fast`'s parabola stands in for the fringe.
const MAX_PHASE_STEP: f64 = 0.75;

/// 1/k for the small counts the closed form divides by (k ≤ 5·MAX_EXT).
const INV_SMALL: [f64; 5 * MAX_EXT + 1] = {
    let mut t = [0.0; 5 * MAX_EXT + 1];
    let mut k = 1;
    while k < t.len() {
        t[k] = 1.0 / k as f64;
        k += 1;
    }
    t
};

/// Extrema of one pixel as they are found, in wavelength order, with the
/// merging rules, and the fits' residuals.
struct ExtremaAcc {
    ext: [Ext; MAX_EXT],
    n: usize,
    rss: f64,
    rdof: f64,
    /// Extrema closer in level than this are noise wiggles (3 σ_R).
    prominence: f64,
}

impl ExtremaAcc {
    fn new(noise: Option<f64>) -> Self {
        ExtremaAcc {
            ext: [Ext::default(); MAX_EXT],
            n: 0,
            rss: 0.0,
            rdof: 0.0,
            prominence: noise.map_or(0.0, |n| 3.0 * n),
        }
    }

    /// Empty again, for the next pixel (the slots are not cleared: only
    /// the first `n` are ever read).
    fn reset(&mut self) {
        self.n = 0;
        self.rss = 0.0;
        self.rdof = 0.0;
    }

    fn full(&self) -> bool {
        self.n >= MAX_EXT
    }

    fn push(&mut self, e: Ext) {
        let n = self.n;
        if n > 0 && self.ext[n - 1].kind == e.kind {
            // Two of a kind in a row: noise; keep the more extreme.
            if (e.val - self.ext[n - 1].val) * f64::from(e.kind) > 0.0 {
                self.ext[n - 1] = e;
            }
        } else if n > 0 && (e.val - self.ext[n - 1].val).abs() < self.prominence {
            // A wiggle of noise size on a flat fringe top: not a fringe
            // extremum (hysteresis). The next extremum of the earlier kind
            // then merges with it above.
        } else if n < MAX_EXT {
            self.ext[n] = e;
            self.n += 1;
        }
    }
}

/// One pixel's solve request.
#[derive(Clone, Copy)]
struct Job<'a> {
    /// Reflectance per band (NaN: missing).
    spectrum: &'a [f64],
    /// Known angle, radians.
    theta_known: Option<f64>,
    /// Reflectance noise σ of the image, once known.
    noise: Option<f64>,
    effort: Effort,
    /// Precomputed fringe candidates (index search).
    pre: Option<&'a SamplePixel>,
}

/// Result of refining one start.
#[derive(Clone, Copy, Debug, Default)]
struct Fit {
    d: f64,
    theta: f64,
    sse: f64,
    /// `JᵀJ` entries (dd, dθ, θθ).
    jtj: [f64; 3],
    /// Fitted with the passband-integrated model.
    integrated: bool,
}

/// Everything that depends on the film index.
#[derive(Clone, Debug)]
struct Prepared {
    model: FilmModel,
    /// Expected sign of the fringe term (+1: half-wave points are peaks).
    sign: f64,
    /// Angle table for the start: (θ, R(cos Δ = 1), R(cos Δ = −1)).
    table: Vec<(f64, f64, f64)>,
    /// The half-wave envelope's slope dR/dθ between table entries.
    slopes: Slopes,
    /// Real ambient and substrate indices at the middle band, when the
    /// half-wave level can be inverted in closed form (lossless, s or p).
    closed_form: Option<(f64, f64, Polarization)>,
    /// The model with the passband integrated on every band that has a
    /// width (accurate mode, bands with a width only).
    integrated: Option<FilmModel>,
    /// Largest fringe amplitude over the angle range, for the criterion.
    fringe_amplitude: f64,
}

/// Solves pixels for the scene's unknowns.
#[derive(Clone, Debug)]
pub struct Solver {
    scene: Scene,
    bands: Vec<Band>,
    mode: Mode,
    index: Option<IndexEstimate>,
    prepared: Option<Prepared>,
    basis: FringeBasis,
    theta_range: (f64, f64),
    /// sin² of the angle range's ends.
    sin2_range: (f64, f64),
    d_max: f64,
    /// Bands by increasing wavelength: (plane index, λ, wavenumber 1/λ).
    sorted: Vec<(usize, f64, f64)>,
    /// Centre of the band range in wavenumber, nm⁻¹.
    sigma_center: f64,
    /// The band range in wavenumber, nm⁻¹.
    sigma_range: (f64, f64),
    /// That range less 1.5 band spacings at each end, where an extremum
    /// is always found if it exists.
    interior: (f64, f64),
    /// The planes are already in increasing wavelength.
    sorted_identity: bool,
    /// The least-squares parabola around each sorted band (`None` at the
    /// two end bands or if singular).
    parabola: Vec<Option<Window>>,
}

impl Solver {
    /// A solver for `scene` observed in `bands` (cube plane order).
    pub fn new(scene: &Scene, bands: &[Band], mode: Mode) -> Result<Solver, EstimateError> {
        if bands.len() < 4 {
            return Err(EstimateError::Bands(format!(
                "need at least 4 bands, got {}",
                bands.len()
            )));
        }
        if bands.len() > MAX_BANDS {
            return Err(EstimateError::Bands(format!(
                "at most {MAX_BANDS} bands, got {}",
                bands.len()
            )));
        }
        if let Some(b) = bands
            .iter()
            .find(|b| !(b.center_nm.is_finite() && b.center_nm > 0.0 && b.fwhm_nm >= 0.0))
        {
            return Err(EstimateError::Bands(format!(
                "band centre {} nm / FWHM {} nm is not usable",
                b.center_nm, b.fwhm_nm
            )));
        }
        let n2_hi = match &scene.film {
            FilmKnowledge::Known(d) => bands
                .iter()
                .filter_map(|b| d.index_at(b.center_nm).ok())
                .map(|n| n.re)
                .fold(1.0, f64::max),
            FilmKnowledge::Unknown { search, .. } => search.1,
        };
        let d_max = scene.max_thickness_nm;
        let basis = FringeBasis::new(bands, d_max * n2_hi);
        let theta_range = match scene.angle {
            AngleKnowledge::Unknown { search } => search,
            _ => (0.0, 89f64.to_radians()),
        };
        let mut solver = Solver {
            scene: scene.clone(),
            bands: bands.to_vec(),
            mode,
            index: None,
            prepared: None,
            basis,
            theta_range,
            sin2_range: (theta_range.0.sin().powi(2), theta_range.1.sin().powi(2)),
            d_max,
            sorted: {
                let mut v: Vec<(usize, f64, f64)> = bands
                    .iter()
                    .enumerate()
                    .map(|(i, b)| (i, b.center_nm, 1.0 / b.center_nm))
                    .collect();
                v.sort_by(|a, b| a.1.total_cmp(&b.1));
                v
            },
            parabola: Vec::new(),
            sigma_center: 0.0,
            sigma_range: (0.0, 0.0),
            interior: (0.0, 0.0),
            sorted_identity: false,
        };
        solver.sorted_identity = solver.sorted.iter().enumerate().all(|(i, b)| b.0 == i);
        let (s_lo, s_hi) = solver
            .sorted
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(a, b), x| {
                (a.min(x.2), b.max(x.2))
            });
        solver.sigma_center = 0.5 * (s_lo + s_hi);
        solver.sigma_range = (s_lo, s_hi);
        solver.interior = {
            let sv: Vec<f64> = solver.sorted.iter().map(|b| b.2).collect();
            let k = sv.len();
            // sorted by increasing wavelength: wavenumber decreasing.
            let (hi_step, lo_step) = (sv[0] - sv[1], sv[k - 2] - sv[k - 1]);
            (s_lo + 1.5 * lo_step, s_hi - 1.5 * hi_step)
        };
        solver.parabola = (0..solver.sorted.len())
            .map(|i| Window::new(&solver.sorted, i))
            .collect();
        if let FilmKnowledge::Known(film) = &scene.film {
            let film = film.clone();
            let prepared = solver.prepare(&film)?;
            let n = prepared.model.n2_mid();
            solver.prepared = Some(prepared);
            solver.index = Some(IndexEstimate {
                n,
                sigma: 0.0,
                estimated: false,
                twin: None,
                twin_delta_chi2: f64::NAN,
                noise_sigma: f64::NAN,
                note: "known".into(),
            });
        }
        Ok(solver)
    }

    /// The model a fit should use: the passband-integrated one when some
    /// band would err by more than [`INTEGRATION_TOLERANCE`] if
    /// point-sampled at this fit's optical thickness (the criterion of
    /// `optics::band`), else the point-sampled one.
    fn model_for<'p>(&self, prep: &'p Prepared, fit: &Fit) -> &'p FilmModel {
        let Some(int) = &prep.integrated else {
            return &prep.model;
        };
        let g = fit.d * prep.model.q2_mid(fit.theta);
        if self.bands.iter().any(|b| {
            b.fwhm_nm > 0.0
                && b.needs_integration_for(g, prep.fringe_amplitude, INTEGRATION_TOLERANCE)
        }) {
            int
        } else {
            &prep.model
        }
    }

    fn prepare(&self, film: &Dispersion) -> Result<Prepared, EstimateError> {
        let model = FilmModel::new(
            &self.bands,
            &self.scene.ambient,
            film,
            &self.scene.substrate,
            self.scene.polarization,
            &vec![false; self.bands.len()],
        )
        .map_err(|(medium, source)| EstimateError::Optics { medium, source })?;
        let (lo, hi) = self.theta_range;
        let steps = (((hi - lo).to_degrees() / 0.5).ceil() as usize).max(1);
        let table: Vec<(f64, f64, f64)> = (0..=steps)
            .map(|i| {
                let th = lo + (hi - lo) * i as f64 / steps as f64;
                let (h, l) = model.envelopes(th);
                (th, h, l)
            })
            .collect();
        let mid_th = match self.scene.angle {
            AngleKnowledge::Uniform(t) => t,
            _ => 0.5 * (lo + hi),
        };
        let (h, l) = model.envelopes(mid_th);
        let sign = if h >= l { 1.0 } else { -1.0 };
        let (n1, n3) = model.ambient_substrate_mid();
        let pol = self.scene.polarization;
        let closed_form =
            (n1.im == 0.0 && n3.im == 0.0 && matches!(pol, Polarization::S | Polarization::P))
                .then_some((n1.re, n3.re, pol));
        let fringe_amplitude = table
            .iter()
            .map(|e| 0.5 * (e.1 - e.2).abs())
            .filter(|a| a.is_finite())
            .fold(0.0, f64::max);
        let integrated =
            if self.mode == Mode::Accurate && self.bands.iter().any(|b| b.fwhm_nm > 0.0) {
                let all = vec![true; self.bands.len()];
                Some(
                    FilmModel::new(
                        &self.bands,
                        &self.scene.ambient,
                        film,
                        &self.scene.substrate,
                        self.scene.polarization,
                        &all,
                    )
                    .map_err(|(medium, source)| EstimateError::Optics { medium, source })?,
                )
            } else {
                None
            };
        let slopes = Slopes::new(&table);
        Ok(Prepared {
            model,
            sign,
            slopes,
            table,
            closed_form,
            integrated,
            fringe_amplitude,
        })
    }

    /// The mode.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// The bands, in cube plane order.
    pub fn bands(&self) -> &[Band] {
        &self.bands
    }

    /// The film index in use, once known or estimated.
    pub fn film_index(&self) -> Option<&IndexEstimate> {
        self.index.as_ref()
    }

    /// Use this film index from now on (e.g. one estimated on an earlier sweep).
    pub fn set_film_index(&mut self, est: IndexEstimate) -> Result<(), EstimateError> {
        if let FilmKnowledge::Unknown { .. } = self.scene.film {
            self.prepared = Some(self.prepare(&Dispersion::constant(est.n))?);
        }
        self.index = Some(est);
        Ok(())
    }

    /// Solve one pixel. `spectrum` is in band order (NaN marks a missing
    /// band); `theta_known` is the pixel's known angle in radians.
    ///
    /// Before the film index is known (or estimated) every pixel is
    /// invalid ([`Reason::Masked`]).
    pub fn solve_pixel(
        &self,
        spectrum: &[f64],
        theta_known: Option<f64>,
        scratch: &mut Scratch,
    ) -> PixelEstimate {
        self.solve_pixel_with(spectrum, theta_known, scratch, Effort::of(self.mode))
    }

    /// [`Solver::solve_pixel`] at a given effort.
    fn solve_pixel_with(
        &self,
        spectrum: &[f64],
        theta_known: Option<f64>,
        scratch: &mut Scratch,
        effort: Effort,
    ) -> PixelEstimate {
        let (Some(prep), Some(index)) = (&self.prepared, &self.index) else {
            return PixelEstimate::invalid(Reason::Masked);
        };
        let noise = index.noise_sigma.is_finite().then_some(index.noise_sigma);
        let (mut est, _) = self.solve_with(
            prep,
            Job {
                spectrum,
                theta_known,
                noise,
                effort,
                pre: None,
            },
            scratch,
        );
        Self::with_index(prep, index, &mut est);
        est
    }

    /// The global index and its share of the thickness error.
    fn with_index(prep: &Prepared, index: &IndexEstimate, est: &mut PixelEstimate) {
        if est.is_valid() {
            est.n_film = index.n;
            // The global index's own error moves the thickness at fixed
            // optical thickness: ∂d/∂n2 = −d·n2/q2².
            let q2 = prep.model.q2_mid(est.theta_deg.to_radians());
            let dd_dn = est.thickness_nm * index.n / (q2 * q2);
            let (a, b) = (est.sigma_thickness_nm, dd_dn * index.sigma);
            est.sigma_thickness_nm = (a * a + b * b).sqrt();
        }
    }

    /// Solve row `y` of the cube into `out` (length `cube.width`).
    pub fn solve_row(
        &self,
        cube: &Cube,
        y: usize,
        out: &mut [PixelEstimate],
        scratch: &mut Scratch,
    ) {
        self.solve_row_with(cube, y, out, scratch, None);
    }

    /// As [`Solver::solve_row`], with the extremum candidates already found
    /// (by the live tracker, as the bands arrived): `fast` then skips its
    /// detection pass. Planes of another size are ignored.
    pub fn solve_row_with(
        &self,
        cube: &Cube,
        y: usize,
        out: &mut [PixelEstimate],
        scratch: &mut Scratch,
        candidates: Option<&CandidatePlanes>,
    ) {
        let mut pixel = std::mem::take(&mut scratch.pixel);
        pixel.resize(cube.bands.len(), 0.0);
        let mut done = 0;
        if self.mode == Mode::Fast {
            let pre = candidates.filter(|c| {
                c.size() == (cube.width, cube.height) && c.bands() == self.sorted.len()
            });
            done = self.solve_row_fast(cube, y, out, &mut pixel, scratch, pre);
        }
        for (x, o) in out.iter_mut().enumerate().take(cube.width).skip(done) {
            cube.spectrum_into(x, y, &mut pixel);
            *o = self.solve_pixel(&pixel, self.scene.angle.known_at(x, y), scratch);
        }
        scratch.pixel = pixel;
    }

    /// `fast` on a whole row, band-major: the extremum candidates of 64
    /// pixels at a time come from one branch-free pass over the band planes
    /// (bit masks per pixel), so only the few candidates are visited per
    /// pixel; the fits and closed forms are those of the per-pixel path, and
    /// a pixel they cannot serve takes it. Returns the pixels written (the
    /// whole row, or 0 when this path does not apply).
    fn solve_row_fast(
        &self,
        cube: &Cube,
        y: usize,
        out: &mut [PixelEstimate],
        pixel: &mut [f64],
        scratch: &mut Scratch,
        pre: Option<&CandidatePlanes>,
    ) -> usize {
        let (Some(prep), Some(index)) = (&self.prepared, &self.index) else {
            return 0;
        };
        let nb = self.sorted.len();
        let (w, n) = (cube.width, cube.plane_len());
        if !(7..=super::detect::MAX_DETECT_BANDS).contains(&nb)
            || cube.bands.len() != nb
            || out.len() < w
            || y >= cube.height
        {
            return 0;
        }
        let noise = index.noise_sigma.is_finite().then_some(index.noise_sigma);
        let data = &cube.data;
        let base = y * w;
        // Start of sorted band r's row in the cube.
        let row_of = |r: usize| self.sorted[r].0 * n + base;
        const CH: usize = super::detect::CHUNK;
        const NB: usize = super::detect::MAX_DETECT_BANDS;
        let mut rows: [&[f32]; NB] = [&[]; NB];
        // The chunk band-major in one block (band r's pixel j at r·CH + j),
        // so a window's samples are read without bounds checks.
        let mut flat = [0f32; CH * NB];
        let mut cand = super::detect::Candidates::default();
        let mut acc = ExtremaAcc::new(noise);
        let mut x0 = 0;
        while x0 < w {
            let m = (w - x0).min(CH);
            for (r, row) in rows[..nb].iter_mut().enumerate() {
                *row = &data[row_of(r) + x0..row_of(r) + x0 + m];
                flat[r * CH..r * CH + m].copy_from_slice(row);
            }
            match pre {
                Some(p) => p.unpack(y, x0 / CH, &mut cand),
                None => super::detect::detect(&rows[..nb], &mut cand),
            }
            let super::detect::Candidates {
                maxima,
                minima,
                bad,
            } = &cand;
            for j in 0..m {
                let x = x0 + j;
                let theta_known = self.scene.angle.known_at(x, y);
                let theta_ok =
                    theta_known.is_none_or(|t| t.is_finite() && (0.0..PI / 2.0).contains(&t));
                let mut est = None;
                if !bad[j] && theta_ok {
                    acc.reset();
                    let mut pending = maxima[j] | minima[j];
                    let mut next_free = 1;
                    while pending != 0 && !acc.full() {
                        let i = pending.trailing_zeros() as usize;
                        pending &= pending - 1;
                        if i < next_free {
                            // Next to the previous candidate.
                            continue;
                        }
                        let kind = if maxima[j] >> i & 1 == 1 { 1 } else { -1 };
                        let (lo, len) = self.parabola[i].as_ref().map_or((0, 0), |w| (w.lo, w.len));
                        let y5 = std::array::from_fn(|k| {
                            let v = f64::from(flat[((lo + k) % NB) * CH + j % CH]);
                            if k < len {
                                v
                            } else {
                                0.0
                            }
                        });
                        self.fit_extremum(i, kind, y5, &mut acc);
                        next_free = i + 2;
                    }
                    est = self.closed_form(prep, &acc, theta_known, noise, Some(index));
                }
                out[x] = match est {
                    Some(e) => e,
                    None => {
                        // The closed form was just tried on these very
                        // samples: straight to the fitted path.
                        cube.spectrum_into(x, y, pixel);
                        let effort = Effort {
                            closed_form: false,
                            ..Effort::of(Mode::Fast)
                        };
                        self.solve_pixel_with(pixel, theta_known, scratch, effort)
                    }
                };
            }
            x0 += m;
        }
        w
    }

    /// Fit a whole cube: the film index first where unknown, then every
    /// pixel, rows in parallel on the current rayon pool.
    pub fn fit_cube(&mut self, cube: &Cube) -> Result<ParamMaps, EstimateError> {
        self.check_cube(cube)?;
        if self
            .index
            .as_ref()
            .is_none_or(|i| !i.noise_sigma.is_finite())
        {
            self.estimate_film_index(cube)?;
        }
        let (w, h) = (cube.width, cube.height);
        let mut maps = ParamMaps::for_overwrite(w, h);
        // Rows in parallel, each written straight into its row of the maps
        // by the thread that solved it.
        maps.rows_mut(0..h)
            .into_par_iter()
            .enumerate()
            .for_each_init(
                || {
                    (
                        Scratch::default(),
                        vec![PixelEstimate::invalid(Reason::Masked); w],
                    )
                },
                |(scratch, est), (y, mut row)| {
                    self.solve_row(cube, y, est, scratch);
                    row.set_all(est);
                },
            );
        maps.meta = self.map_meta();
        Ok(maps)
    }

    /// Metadata for maps produced by this solver.
    pub fn map_meta(&self) -> super::maps::MapMeta {
        let idx = self.index.clone();
        super::maps::MapMeta {
            mode: self.mode.name().into(),
            wavelengths_nm: self.bands.iter().map(|b| b.center_nm).collect(),
            fwhm_nm: self.bands.iter().map(|b| b.fwhm_nm).collect(),
            n_film: idx.as_ref().map_or(f64::NAN, |i| i.n),
            n_film_sigma: idx.as_ref().map_or(f64::NAN, |i| i.sigma),
            n_film_estimated: idx.as_ref().is_some_and(|i| i.estimated),
            n_film_note: idx.map(|i| i.note).unwrap_or_default(),
            polarization: self.scene.polarization.name(),
        }
    }

    fn check_cube(&self, cube: &Cube) -> Result<(), EstimateError> {
        if cube.bands.len() != self.bands.len() {
            return Err(EstimateError::Shape(format!(
                "the cube has {} bands, the solver {}",
                cube.bands.len(),
                self.bands.len()
            )));
        }
        if cube.data.len() != cube.plane_len() * cube.bands.len() {
            return Err(EstimateError::Shape(
                "cube data length does not match its size".into(),
            ));
        }
        if let AngleKnowledge::Map { width, height, .. } = self.scene.angle {
            if (width, height) != (cube.width, cube.height) {
                return Err(EstimateError::Shape(format!(
                    "the angle map is {width}×{height}, the cube {}×{}",
                    cube.width, cube.height
                )));
            }
        }
        Ok(())
    }

    /// Estimate the film index from the cube when the scene leaves it
    /// unknown, and the reflectance noise from the fit residuals (also when
    /// the index is known). The result is kept for later pixels and sweeps.
    pub fn estimate_film_index(&mut self, cube: &Cube) -> Result<IndexEstimate, EstimateError> {
        self.check_cube(cube)?;
        // `fast` trades some of the index's precision (σ_n grows by √2, still
        // far below 0.001) for a first map that is not late.
        let n_sample = if self.mode == Mode::Fast {
            INDEX_SAMPLE_PIXELS / 2
        } else {
            INDEX_SAMPLE_PIXELS
        };
        let sample = self.sample_pixels(cube, n_sample);
        if sample.is_empty() {
            return Err(EstimateError::FilmIndex(
                "no pixel has a complete, finite spectrum".into(),
            ));
        }
        let est = match self.scene.film.clone() {
            FilmKnowledge::Known(_) => {
                let mut est = self.index.clone().expect("known index set at construction");
                let prep = self.prepared.clone().expect("known index prepared");
                let (sse, n_obs, n_par, _) = self.sample_sse(&prep, &sample);
                est.noise_sigma = (sse / (n_obs - n_par).max(1.0)).sqrt();
                est
            }
            FilmKnowledge::Unknown { search, prior } => {
                self.search_index(&sample, search, prior)?
            }
        };
        self.set_film_index(est.clone())?;
        Ok(est)
    }

    /// Up to `max` pixels on a regular lattice with complete spectra, with
    /// their known angles.
    fn sample_pixels(&self, cube: &Cube, max: usize) -> Vec<SamplePixel> {
        let (w, h) = (cube.width, cube.height);
        // A 2-D stratified grid (cells of the image's aspect), one pixel per
        // cell at a golden-ratio offset, so periodic structure in the scene
        // cannot alias the sample onto a few columns.
        let max = max.max(1);
        let nx =
            ((max as f64 * w as f64 / h.max(1) as f64).sqrt().ceil() as usize).clamp(1, w.max(1));
        let ny = max.div_ceil(nx).clamp(1, h.max(1));
        const PHI: f64 = 0.618_033_988_749_895;
        let mut out = Vec::new();
        let nb = cube.bands.len();
        let mut spec = vec![0.0; nb];
        let mut scratch = Scratch::default();
        scratch.ensure(nb);
        for k in 0..nx * ny {
            let (i, j) = (k % nx, k / nx);
            let fx = (i as f64 + (j as f64 * PHI).fract()) / nx as f64;
            let fy = (j as f64 + (i as f64 * PHI).fract()) / ny as f64;
            let x = ((fx * w as f64) as usize).min(w - 1);
            let y = ((fy * h as f64) as usize).min(h - 1);
            cube.spectrum_into(x, y, &mut spec);
            // Missing bands (NaN: a dropped frame) are allowed as in any
            // pixel's solve, up to a quarter of them.
            let n_ok = spec.iter().filter(|v| v.is_finite()).count();
            let in_range = spec
                .iter()
                .all(|v| !v.is_finite() || (-0.2..=1.2).contains(v));
            if in_range && 4 * n_ok >= 3 * nb && !spec.iter().any(|v| v.is_infinite()) {
                for (k, &v) in spec.iter().enumerate() {
                    let ok = v.is_finite();
                    scratch.spectrum[k] = if ok { v } else { 0.0 };
                    scratch.weight[k] = if ok { 1.0 } else { 0.0 };
                }
                let complete = n_ok == nb;
                let mut cands = [[Candidate::default(); MAX_CANDIDATES]; 2];
                let mut n_cands = [0; 2];
                for (k, sign) in [1.0, -1.0].into_iter().enumerate() {
                    n_cands[k] = self.fringe_search(&scratch, sign, complete, &mut cands[k]);
                }
                out.push(SamplePixel {
                    spectrum: spec.clone(),
                    theta: self.scene.angle.known_at(x, y),
                    cands,
                    n_cands,
                });
            }
        }
        out
    }

    /// Summed residual of the sample under a prepared index: `(sse,
    /// observations, fitted parameters, pixels fitted)`.
    fn sample_sse(&self, prep: &Prepared, sample: &[SamplePixel]) -> (f64, f64, f64, f64) {
        sample
            .par_iter()
            .map_init(Scratch::default, |scratch, px| {
                let (spec, th) = (&px.spectrum, &px.theta);
                let job = Job {
                    spectrum: spec,
                    theta_known: *th,
                    noise: None,
                    effort: Effort::INDEX_SEARCH,
                    pre: Some(px),
                };
                let (est, sse) = self.solve_with(prep, job, scratch);
                if est.is_valid() && sse.is_finite() {
                    let p = if th.is_some() { 1.0 } else { 2.0 };
                    let n = spec.iter().filter(|v| v.is_finite()).count();
                    (sse, n as f64, p, 1.0)
                } else {
                    (0.0, 0.0, 0.0, 0.0)
                }
            })
            .reduce(
                || (0.0, 0.0, 0.0, 0.0),
                |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2, a.3 + b.3),
            )
    }

    fn profile_at(
        &self,
        n: f64,
        sample: &[SamplePixel],
    ) -> Result<(f64, f64, f64, f64), EstimateError> {
        let prep = self.prepare(&Dispersion::constant(n))?;
        Ok(self.sample_sse(&prep, sample))
    }

    fn search_index(
        &self,
        sample: &[SamplePixel],
        search: (f64, f64),
        prior: Option<f64>,
    ) -> Result<IndexEstimate, EstimateError> {
        // Coarse profile on a 0.02 grid (twice the paper's step: the
        // profile's basin is wider, and the local fit below refines it far
        // past 0.01); pixels a trial index
        // cannot fit at all are charged their total sum of squares so that
        // dropping them never looks like a better fit.
        let (lo, hi) = search;
        let lo = lo.max(1.0 + 1e-3);
        let steps = ((hi - lo) / INDEX_GRID_STEP).round().max(2.0) as usize;
        let grid: Vec<f64> = (0..=steps)
            .map(|i| lo + (hi - lo) * i as f64 / steps as f64)
            .collect();
        let total_ss: f64 = sample
            .iter()
            .map(|px| {
                let s = &px.spectrum;
                let ok = s.iter().filter(|v| v.is_finite());
                let n = ok.clone().count().max(1) as f64;
                let m = ok.clone().sum::<f64>() / n;
                ok.map(|v| (v - m) * (v - m)).sum::<f64>()
            })
            .sum();
        let cost = |n: f64| -> Result<f64, EstimateError> {
            let (sse, _, _, fitted) = self.profile_at(n, sample)?;
            let missing = sample.len() as f64 - fitted;
            Ok(sse + missing * total_ss / sample.len() as f64)
        };
        let mut prof = Vec::with_capacity(grid.len());
        for &n in &grid {
            prof.push(cost(n)?);
        }
        // Local minima of the coarse profile, best first.
        let mut minima: Vec<usize> = (0..prof.len())
            .filter(|&i| {
                (i == 0 || prof[i] <= prof[i - 1])
                    && (i + 1 == prof.len() || prof[i] <= prof[i + 1])
            })
            .collect();
        minima.sort_by(|&a, &b| prof[a].total_cmp(&prof[b]));
        if minima.is_empty() || !prof[minima[0]].is_finite() {
            return Err(EstimateError::FilmIndex(
                "the index profile has no minimum".into(),
            ));
        }
        // Refine the best two well-separated minima with a local quadratic.
        let mut refined: Vec<(f64, f64, f64)> = Vec::new(); // (n, sse, curvature)
        for &i in minima.iter().take(4) {
            if refined.iter().any(|r| (r.0 - grid[i]).abs() < 0.04) {
                continue;
            }
            let r = self.refine_index(grid[i], (lo, hi), &cost)?;
            refined.push(r);
            if refined.len() == 2 {
                break;
            }
        }
        refined.sort_by(|a, b| a.1.total_cmp(&b.1));
        let (_, n_obs, n_par, _) = self.profile_at(refined[0].0, sample)?;
        let dof = (n_obs - n_par - 1.0).max(1.0);
        let var = refined[0].1 / dof;
        let noise_sigma = var.sqrt();
        let mut best = refined[0];
        let mut note = String::new();
        let (twin, dchi2) = match refined.get(1) {
            Some(t) => (Some(t.0), (t.1 - best.1) / var),
            None => (None, f64::INFINITY),
        };
        if let Some(tn) = twin {
            if dchi2 < 9.0 {
                if let Some(p) = prior {
                    if (tn - p).abs() < (best.0 - p).abs() {
                        let other = best;
                        best = refined[1];
                        note = format!(
                            "twin branches {:.4} and {:.4} not resolved by the data (Δχ² = {:.1}); the prior chose",
                            best.0, other.0, dchi2
                        );
                    } else {
                        note = format!(
                            "twin at {:.4} not resolved by the data (Δχ² = {:.1}); the prior chose",
                            tn, dchi2
                        );
                    }
                } else {
                    note = format!(
                        "AMBIGUOUS: twin at {:.4} fits almost as well (Δχ² = {:.1}); give a prior or the index",
                        tn, dchi2
                    );
                }
            } else {
                note = format!("twin at {:.4} rejected (Δχ² = {:.0})", tn, dchi2);
            }
        }
        let sigma = if best.2 > 0.0 {
            (var / best.2).sqrt()
        } else {
            f64::NAN
        };
        Ok(IndexEstimate {
            n: best.0,
            sigma,
            estimated: true,
            twin,
            twin_delta_chi2: dchi2,
            noise_sigma,
            note,
        })
    }

    /// Fit `sse ≈ s0 + κ (n − n0)²` on a fine local grid around `n_start`;
    /// returns `(n0, s0, κ)`.
    fn refine_index(
        &self,
        n_start: f64,
        bounds: (f64, f64),
        cost: &dyn Fn(f64) -> Result<f64, EstimateError>,
    ) -> Result<(f64, f64, f64), EstimateError> {
        let mut center = n_start;
        let mut half = INDEX_GRID_STEP;
        let mut result = (center, f64::INFINITY, 0.0);
        for _ in 0..3 {
            let pts: Vec<f64> = (-3..=3)
                .map(|i| (center + half * i as f64 / 3.0).clamp(bounds.0, bounds.1))
                .collect();
            let mut vals = Vec::with_capacity(pts.len());
            for &p in &pts {
                vals.push(cost(p)?);
            }
            // Least-squares parabola in u = n − center.
            let (mut s0, mut s1, mut s2, mut s3, mut s4) = (0.0, 0.0, 0.0, 0.0, 0.0);
            let (mut t0, mut t1, mut t2) = (0.0, 0.0, 0.0);
            for (&p, &v) in pts.iter().zip(&vals) {
                let u = p - center;
                let u2 = u * u;
                s0 += 1.0;
                s1 += u;
                s2 += u2;
                s3 += u2 * u;
                s4 += u2 * u2;
                t0 += v;
                t1 += v * u;
                t2 += v * u2;
            }
            let m = [[s4, s3, s2], [s3, s2, s1], [s2, s1, s0]];
            let Some([a, b, c]) = solve3(m, [t2, t1, t0]) else {
                break;
            };
            let (imin, vmin) = vals
                .iter()
                .enumerate()
                .min_by(|x, y| x.1.total_cmp(y.1))
                .map(|(i, v)| (i, *v))
                .unwrap_or((3, f64::INFINITY));
            if a > 0.0 {
                let u = (-b / (2.0 * a)).clamp(-half, half);
                let n0 = (center + u).clamp(bounds.0, bounds.1);
                let s = c - b * b / (4.0 * a);
                result = (n0, s.max(0.0).min(vmin), a);
                center = n0;
            } else {
                center = pts[imin];
                result = (center, vmin, 0.0);
            }
            half *= 0.3;
        }
        // The value at the vertex itself, not the parabola's.
        let s = cost(result.0)?;
        Ok((result.0, s, result.2))
    }

    /// Solve one pixel against a prepared index; returns the estimate (with
    /// σ from the fit alone) and its residual sum of squares.
    fn solve_with(
        &self,
        prep: &Prepared,
        job: Job<'_>,
        scratch: &mut Scratch,
    ) -> (PixelEstimate, f64) {
        let Job {
            spectrum,
            theta_known,
            noise,
            effort,
            pre,
        } = job;
        let nb = self.bands.len();
        if spectrum.len() != nb {
            return (PixelEstimate::invalid(Reason::MissingBands), f64::NAN);
        }
        scratch.ensure(nb);
        let mut n_ok = 0usize;
        for (k, &v) in spectrum.iter().enumerate() {
            if v.is_finite() {
                if !(-0.2..=1.2).contains(&v) {
                    return (PixelEstimate::invalid(Reason::OutOfModel), f64::NAN);
                }
                scratch.spectrum[k] = v;
                scratch.weight[k] = 1.0;
                n_ok += 1;
            } else {
                scratch.spectrum[k] = 0.0;
                scratch.weight[k] = 0.0;
            }
        }
        if n_ok == 0 {
            return (PixelEstimate::invalid(Reason::NonFinite), f64::NAN);
        }
        let n_par = if theta_known.is_some() { 1 } else { 2 };
        if n_ok < nb.div_ceil(2).max(n_par + 3) {
            let reason = if spectrum.iter().any(|v| v.is_infinite()) {
                Reason::NonFinite
            } else {
                Reason::MissingBands
            };
            return (PixelEstimate::invalid(reason), f64::NAN);
        }
        if let Some(t) = theta_known {
            if !(t.is_finite() && (0.0..PI / 2.0).contains(&t)) {
                return (PixelEstimate::invalid(Reason::OutOfModel), f64::NAN);
            }
        }
        let lam_min = self.sorted.first().map_or(400.0, |b| b.1);
        if effort.closed_form && n_ok == nb {
            if let Some(fe) = self.extrema_estimate(prep, theta_known, noise, scratch) {
                if effort.closed_form_only {
                    return (fe, f64::NAN);
                }
                let fit = self.refine(
                    &prep.model,
                    fe.thickness_nm,
                    fe.theta_deg.to_radians(),
                    theta_known.is_none(),
                    effort.iters,
                    scratch,
                );
                let rms = (fit.sse / n_ok as f64).sqrt();
                // A wrong order leaves fringe-sized residuals; only then is
                // the full search worth its cost.
                let good = noise.is_some_and(|n| rms <= 2.0 * n);
                if good && !effort.verify_order {
                    return self.finish(&[fit], n_ok, theta_known, noise, prep, lam_min, scratch);
                }
                if good {
                    // Where this pixel's fringes are fast enough for the
                    // passband to matter, refit with the integrated model
                    // (and judge the competing order with it too).
                    let model = self.model_for(prep, &fit);
                    let fit = if std::ptr::eq(model, &prep.model) {
                        fit
                    } else {
                        let free = theta_known.is_none();
                        let mut f =
                            self.refine(model, fit.d, fit.theta, free, effort.iters, scratch);
                        f.integrated = true;
                        f
                    };
                    // The neighbouring orders on the lattice: the same fringe
                    // phase at the band-range centre, one fringe more or
                    // fewer. The better one is refined; if it fits as well,
                    // the order is ambiguous.
                    let q2 = prep.model.q2_mid(fit.theta);
                    let g = fit.d * q2;
                    let dg = 0.5 / self.sigma_center;
                    let mut alt = None;
                    let mut alt_sse = f64::INFINITY;
                    for ga in [g - dg, g + dg] {
                        if ga < 0.0 || ga / q2 > self.d_max {
                            continue;
                        }
                        model.eval(ga / q2, fit.theta, &mut scratch.trial, false);
                        let e = sse(&scratch.spectrum, &scratch.weight, &scratch.trial.r);
                        if e < alt_sse {
                            alt_sse = e;
                            alt = Some(ga / q2);
                        }
                    }
                    let mut fits = [fit, fit];
                    let mut n_fits = 1;
                    if let Some(d_alt) = alt {
                        // Two steps tell a clearly worse order; only a close
                        // one is refined to convergence.
                        let free = theta_known.is_none();
                        let mut f = self.refine(model, d_alt, fit.theta, free, 2, scratch);
                        let var = fit.sse / (n_ok.saturating_sub(2).max(1)) as f64;
                        if f.sse < fit.sse + 25.0 * var {
                            f = self.refine(model, f.d, f.theta, free, effort.iters, scratch);
                        }
                        f.integrated = fit.integrated;
                        fits[1] = f;
                        n_fits = 2;
                    }
                    return self.finish(
                        &fits[..n_fits],
                        n_ok,
                        theta_known,
                        noise,
                        prep,
                        lam_min,
                        scratch,
                    );
                }
            }
        }
        let mut cands = [Candidate::default(); MAX_CANDIDATES];
        let n_cands = match pre {
            Some(px) => {
                let k = usize::from(prep.sign < 0.0);
                cands = px.cands[k];
                px.n_cands[k]
            }
            None => self.fringe_search(scratch, prep.sign, n_ok == nb, &mut cands),
        };

        // Angle start.
        let theta0 = match theta_known {
            Some(t) => t,
            None => {
                let c = if n_cands > 0 {
                    cands[0]
                } else {
                    let mean = scratch.spectrum.iter().sum::<f64>() / n_ok as f64;
                    Candidate {
                        a: mean,
                        ..Default::default()
                    }
                };
                angle_start(&prep.table, Some(c.a + c.b), Some(c.a - c.b))
            }
        };
        let q2 = prep.model.q2_mid(theta0);
        // Starts: the fringe candidates, plus a bare substrate and a thin
        // film below the first fringe.
        let mut starts: [(f64, f64); MAX_CANDIDATES + 2] =
            [(0.0, f64::INFINITY); MAX_CANDIDATES + 2];
        let mut n_starts = 0;
        for c in &cands[..n_cands] {
            starts[n_starts] = (c.g / q2, 0.0);
            n_starts += 1;
        }
        starts[n_starts] = (0.0, 0.0);
        starts[n_starts + 1] = (lam_min / (8.0 * q2), 0.0);
        n_starts += 2;
        for s in &mut starts[..n_starts] {
            prep.model.eval(s.0, theta0, &mut scratch.cur, false);
            s.1 = sse(&scratch.spectrum, &scratch.weight, &scratch.cur.r);
        }
        starts[..n_starts].sort_by(|a, b| a.1.total_cmp(&b.1));
        let (n_refine, iters) = (effort.n_refine, effort.iters);
        let mut fits = [Fit::default(); 3];
        let mut n_fits = 0;
        for st in starts[..n_starts.min(n_refine)].iter() {
            if !st.1.is_finite() {
                continue;
            }
            fits[n_fits] = self.refine(
                &prep.model,
                st.0,
                theta0,
                theta_known.is_none(),
                iters,
                scratch,
            );
            n_fits += 1;
        }
        if effort.verify_order {
            // As on the closed-form path: fits whose fringes the passband
            // affects are redone with the integrated model.
            for f in &mut fits[..n_fits] {
                let model = self.model_for(prep, f);
                if !std::ptr::eq(model, &prep.model) {
                    *f = self.refine(model, f.d, f.theta, theta_known.is_none(), iters, scratch);
                    f.integrated = true;
                }
            }
        }
        self.finish(
            &fits[..n_fits],
            n_ok,
            theta_known,
            noise,
            prep,
            lam_min,
            scratch,
        )
    }

    /// From refined fits to an estimate: best fit, covariance, flags.
    #[allow(clippy::too_many_arguments)]
    fn finish(
        &self,
        fits: &[Fit],
        n_ok: usize,
        theta_known: Option<f64>,
        noise: Option<f64>,
        prep: &Prepared,
        lam_min: f64,
        scratch: &mut Scratch,
    ) -> (PixelEstimate, f64) {
        let n_par = if theta_known.is_some() { 1 } else { 2 };
        let mut order = [0usize, 1, 2];
        let order = &mut order[..fits.len().min(3)];
        order.sort_by(|&a, &b| fits[a].sse.total_cmp(&fits[b].sse));
        let Some(best) = order.first().map(|&i| fits[i]) else {
            return (PixelEstimate::invalid(Reason::PoorFit), f64::NAN);
        };
        if !(best.sse.is_finite() && best.d.is_finite() && best.theta.is_finite()) {
            return (PixelEstimate::invalid(Reason::PoorFit), f64::NAN);
        }
        let q2 = prep.model.q2_mid(best.theta);
        let dof = (n_ok - n_par).max(1) as f64;
        let var = (best.sse / dof).max(1e-14);
        // Covariance with a weak prior on the angle (its search range as a
        // uniform distribution) so a flat direction gives a large, finite σ.
        let (sig_d, sig_th) = if theta_known.is_some() {
            ((var / best.jtj[0].max(1e-300)).sqrt(), 0.0)
        } else {
            let (lo, hi) = self.theta_range;
            let prior = 12.0 / ((hi - lo) * (hi - lo)).max(1e-6);
            let a = best.jtj[0];
            let b = best.jtj[1];
            let c = best.jtj[2] + prior * var;
            let det = a * c - b * b;
            if det > 0.0 {
                ((var * c / det).sqrt(), (var * a / det).sqrt())
            } else {
                (f64::INFINITY, (hi - lo) / 12f64.sqrt())
            }
        };
        // Near d = 0 the reflectance is even in d (dR/dd = 0 at d = 0), so
        // the linearised σ is meaningless: take the one-sided profile bound
        // instead, the d at which the residual grows by one variance.
        let model = match (&prep.integrated, best.integrated) {
            (Some(m), true) => m,
            _ => &prep.model,
        };
        let sig_d = if best.d < 0.1 * lam_min && (sig_d.is_nan() || sig_d >= 0.05 * lam_min) {
            self.profile_sigma_d(model, best, var, scratch)
        } else {
            sig_d
        };
        // A weak angle: the linearised σ_θ says little (at θ = 0, R is even
        // in θ and dR/dθ vanishes). Take the profile bound instead — the
        // angle at which the residual, with the optical thickness held,
        // grows by one variance — and carry its share into d, which at
        // fixed optical thickness moves as 1/(n2 cos θ2).
        let (sig_d, sig_th) =
            if theta_known.is_none() && sig_th.to_degrees() > ANGLE_SIGMA_LIMIT_DEG {
                let (lo, hi) = self.theta_range;
                // Inside the range the linearised σ stands; at a bound (where the
                // slope vanishes or the clamp hides the other side) profile.
                let at_bound = best.theta - lo < sig_th || hi - best.theta < sig_th;
                let sig_th = if !sig_th.is_finite() || at_bound {
                    let th_bound = self.profile_sigma_theta(model, best, var, scratch);
                    if sig_th.is_finite() {
                        sig_th.min(th_bound.max(1e-6))
                    } else {
                        th_bound
                    }
                } else {
                    sig_th
                };
                let q = |t: f64| model.q2_mid(t.clamp(lo, hi));
                let q0 = q(best.theta);
                let shift = [best.theta - sig_th, best.theta + sig_th]
                    .iter()
                    .map(|&t| (best.d * (q0 / q(t) - 1.0)).abs())
                    .fold(0.0, f64::max);
                ((sig_d * sig_d + shift * shift).sqrt(), sig_th)
            } else {
                (sig_d, sig_th)
            };
        let rms = (best.sse / n_ok as f64).sqrt();
        let mut reason = Reason::Ok;
        // A second order that fits as well as the best is an ambiguity.
        if let Some(second) = order.get(1).map(|&i| fits[i]) {
            let apart = (second.d - best.d).abs() > 0.25 * lam_min / (2.0 * q2);
            if apart && second.sse - best.sse < 4.0 * var {
                reason = Reason::AmbiguousOrder;
            }
        }
        if let Some(noise) = noise {
            if rms > 4.0 * noise && rms > 1e-4 {
                reason = Reason::PoorFit;
            }
        }
        if reason == Reason::Ok && !sig_d.is_finite() {
            reason = Reason::NoFringe;
        }
        if reason == Reason::Ok
            && theta_known.is_none()
            && sig_th.to_degrees() > ANGLE_SIGMA_LIMIT_DEG
        {
            reason = Reason::AngleNotIdentifiable;
        }
        let est = PixelEstimate {
            thickness_nm: best.d,
            n_film: prep.model.n2_mid(),
            theta_deg: best.theta.to_degrees(),
            sigma_thickness_nm: sig_d,
            sigma_theta_deg: sig_th.to_degrees(),
            residual_rms: rms,
            reason,
        };
        if est.is_valid() {
            (est, best.sse)
        } else {
            (PixelEstimate::invalid(reason), best.sse)
        }
    }

    /// One-sided profile bound on the thickness near zero: the smallest
    /// `δ > d` whose residual (angle held) exceeds the best by one variance,
    /// minus `d`.
    fn profile_sigma_d(&self, model: &FilmModel, best: Fit, var: f64, s: &mut Scratch) -> f64 {
        let target = best.sse + var;
        let mut lo = best.d;
        let mut hi = best.d + 1.0;
        let mut grow = 0;
        loop {
            model.eval(hi, best.theta, &mut s.trial, false);
            if sse(&s.spectrum, &s.weight, &s.trial.r) > target || grow > 12 {
                break;
            }
            lo = hi;
            hi = best.d + 2.0 * (hi - best.d);
            grow += 1;
        }
        for _ in 0..20 {
            let mid = 0.5 * (lo + hi);
            model.eval(mid, best.theta, &mut s.trial, false);
            if sse(&s.spectrum, &s.weight, &s.trial.r) > target {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        0.5 * (lo + hi) - best.d
    }

    /// Profile bound on a weak angle: the larger of the two distances from
    /// the fitted angle (within the search range) at which the residual,
    /// with the optical thickness `g = d·n2 cos θ2` held, exceeds the best
    /// by one variance; the range's extent if it never does.
    fn profile_sigma_theta(&self, model: &FilmModel, best: Fit, var: f64, s: &mut Scratch) -> f64 {
        let (lo, hi) = self.theta_range;
        let g = best.d * model.q2_mid(best.theta);
        let target = best.sse + var;
        let mut bound: f64 = 0.0;
        for dir in [1.0, -1.0] {
            let limit = if dir > 0.0 {
                hi - best.theta
            } else {
                best.theta - lo
            };
            if limit <= 0.0 {
                continue;
            }
            let mut sse_at = |step: f64| {
                let t = best.theta + dir * step;
                model.eval(g / model.q2_mid(t), t, &mut s.trial, false);
                sse(&s.spectrum, &s.weight, &s.trial.r)
            };
            if sse_at(limit) <= target {
                bound = bound.max(limit);
                continue;
            }
            let (mut a, mut b) = (0.0, limit);
            for _ in 0..10 {
                let m = 0.5 * (a + b);
                if sse_at(m) > target {
                    b = m;
                } else {
                    a = m;
                }
            }
            bound = bound.max(0.5 * (a + b));
        }
        bound
    }

    /// The closed-form path: fringe extrema located between bands (a
    /// least-squares parabola in wavenumber through five samples), the order
    /// from their spacing and the interference lattice, the angle from the
    /// extrema levels, the thickness from Eq. 14. `None` when fewer than two
    /// consistent extrema are in range (the caller then searches).
    ///
    /// σ comes from the parabola fits' covariance (reflectance noise from
    /// `noise`, else from the fits' own residuals), propagated to the
    /// extremum positions and levels, then to g, θ (σ_R / |dR/dθ|) and d.
    fn extrema_estimate(
        &self,
        prep: &Prepared,
        theta_known: Option<f64>,
        noise: Option<f64>,
        scratch: &mut Scratch,
    ) -> Option<PixelEstimate> {
        let nb = self.sorted.len();
        if nb < 7 {
            return None;
        }
        // The spectrum by increasing wavelength (no copy when the planes are
        // already in that order).
        let Scratch {
            spectrum, sorted_y, ..
        } = scratch;
        let ys: &[f64] = if self.sorted_identity {
            &spectrum[..nb]
        } else {
            sorted_y.resize(nb, 0.0);
            for (i, b) in self.sorted.iter().enumerate() {
                sorted_y[i] = spectrum[b.0];
            }
            &sorted_y[..]
        };
        // [1 2 1]-smoothed value at i, for detection only (fits use raw
        // data), the ends reflected.
        let smooth = |i: usize| {
            let a = ys[i.saturating_sub(1)] as f32;
            let c = ys[(i + 1).min(nb - 1)] as f32;
            super::detect::smooth3(a, ys[i] as f32, c)
        };
        let mut acc = ExtremaAcc::new(noise);
        let mut i = 1;
        let (mut a, mut b) = (smooth(0), smooth(1));
        while i + 1 < nb && !acc.full() {
            let c = smooth(i + 1);
            let kind: i8 = if b > a && b >= c {
                1
            } else if b < a && b <= c {
                -1
            } else {
                0
            };
            if kind == 0 {
                (a, b) = (b, c);
                i += 1;
                continue;
            }
            let win = self.parabola[i].as_ref().map_or((0, 0), |w| (w.lo, w.len));
            let y5 = std::array::from_fn(|k| if k < win.1 { ys[win.0 + k] } else { 0.0 });
            self.fit_extremum(i, kind, y5, &mut acc);
            i += 2;
            if i + 1 < nb {
                (a, b) = (smooth(i - 1), smooth(i));
            }
        }
        self.closed_form(prep, &acc, theta_known, noise, None)
    }

    /// Fit the parabola of sorted band `i`'s [`Window`] (a candidate
    /// extremum of kind `kind`) to `y` (the window's samples, unused slots
    /// 0) and hand a usable extremum to `acc`.
    #[inline]
    fn fit_extremum(&self, i: usize, kind: i8, y: [f64; 5], acc: &mut ExtremaAcc) {
        let Some(win) = &self.parabola[i] else {
            return;
        };
        let (mut t0, mut t1, mut t2, mut tvv) = (0.0, 0.0, 0.0, 0.0);
        for (&u, &v) in win.u.iter().zip(&y) {
            let vu = v * u;
            t2 += vu * u;
            t1 += vu;
            t0 += v;
            tvv += v * v;
        }
        let m = &win.minv;
        let qa = m[0][0] * t2 + m[0][1] * t1 + m[0][2] * t0;
        let qb = m[1][0] * t2 + m[1][1] * t1 + m[1][2] * t0;
        let qc = m[2][0] * t2 + m[2][1] * t1 + m[2][2] * t0;
        if qa * f64::from(kind) >= 0.0 {
            return;
        }
        let inv_a = 1.0 / qa;
        let u = -0.5 * qb * inv_a;
        if !(win.vertex.0..=win.vertex.1).contains(&u) {
            return;
        }
        acc.rss += (tvv - (qa * t2 + qb * t1 + qc * t0)).max(0.0);
        acc.rdof += (win.len - 3) as f64;
        acc.push(Ext {
            pos: self.sorted[i].2 + u * 1e-4,
            val: qc + 0.5 * qb * u,
            kind,
            band: i as u16,
            u,
            inv_a,
        });
    }

    /// [`Ext::var_pos`] in its window.
    #[inline]
    fn ext_var_pos(&self, e: &Ext) -> f64 {
        self.parabola[usize::from(e.band)]
            .as_ref()
            .map_or(f64::INFINITY, |w| e.var_pos(w))
    }

    /// [`Ext::var_val`] in its window.
    #[inline]
    fn ext_var_val(&self, e: &Ext) -> f64 {
        self.parabola[usize::from(e.band)]
            .as_ref()
            .map_or(f64::INFINITY, |w| e.var_val(w))
    }

    /// Lattice, angle and thickness from located extrema. With `index`
    /// (the global film index), its value and its share of σ_d are
    /// included, as [`Solver::with_index`] would.
    ///
    /// The divider is this path's bottleneck, so divisions and square
    /// roots are kept to those the result needs.
    fn closed_form(
        &self,
        prep: &Prepared,
        acc: &ExtremaAcc,
        theta_known: Option<f64>,
        noise: Option<f64>,
        index: Option<&IndexEstimate>,
    ) -> Option<PixelEstimate> {
        let n_ext = acc.n;
        if n_ext < 2 {
            return None;
        }
        let (rss, rdof) = (acc.rss, acc.rdof);
        let ext = &acc.ext[..n_ext];
        let var_r = match noise {
            Some(n) => n * n,
            None if rdof > 0.0 => rss / rdof,
            None => return None,
        };
        // Adjacent extrema are a quarter wave apart in phase: Δσ = 1/(4g).
        let span = (ext[n_ext - 1].pos - ext[0].pos).abs();
        if span <= 0.0 {
            return None;
        }
        let g0 = (n_ext - 1) as f64 / (4.0 * span);
        // Lattice: at a half-wave point 2gσ = m, at a quarter-wave point
        // 2gσ = m + ½; which kind is the half-wave point follows the sign.
        // Each extremum's g_i = k/(2σ) (k = m + offset) is weighted by its
        // inverse variance var(g_i) = g_i² var(σ)/σ², i.e. by
        // w_i = 4σ⁴/(k² var(σ)) with w_i g_i = 2σ³ k/(k² var(σ)); the
        // common factor σ_R² cancels in g and returns in var(g).
        // One pass: the order and weight of each extremum, and the sums
        // of the half- and quarter-wave levels for the angle.
        let half_kind: i8 = if prep.sign > 0.0 { 1 } else { -1 };
        let want_angle = theta_known.is_none();
        let (mut wsum, mut gsum) = (0.0, 0.0);
        let (mut hw, mut qw, mut nh, mut nq, mut var_hw) = (0.0f64, 0.0f64, 0usize, 0usize, 0.0);
        let mut orders = [0.0; MAX_EXT];
        for (e, order) in ext.iter().zip(&mut orders) {
            let half = e.kind == half_kind;
            let off = if half { 0.0 } else { 0.5 };
            let m = round(2.0 * g0 * e.pos - off);
            if m < 0.0 {
                return None;
            }
            *order = m + off;
            let k = m + off;
            let b = 1.0 / (k * k * self.ext_var_pos(e).max(f64::MIN_POSITIVE));
            let p2 = e.pos * e.pos;
            wsum += 4.0 * p2 * p2 * b;
            gsum += 2.0 * p2 * e.pos * k * b;
            if want_angle {
                if half {
                    hw += e.val;
                    var_hw += self.ext_var_val(e);
                    nh += 1;
                } else {
                    qw += e.val;
                    nq += 1;
                }
            }
        }
        let inv_wsum = 1.0 / wsum;
        let g = gsum * inv_wsum;
        let var_g = var_r * inv_wsum;
        // Adjacent extrema must agree on the order they imply.
        if !g.is_finite() || (g - g0).abs() > 0.25 * g0 {
            return None;
        }
        // Every extremum must sit on the same lattice (within 0.08 of its
        // order k = m + offset): one that implies a different order means
        // the spacing estimate was off.
        for (e, &k) in ext.iter().zip(&orders) {
            if (2.0 * g * e.pos - k).abs() > 0.08 {
                return None;
            }
        }
        // A parabola stands in for the fringe's cosine only while the
        // phase moves little between samples: at ω·h = 0.75 rad the
        // quartic term it misses biases a vertex level by 2.7 % of the
        // fringe amplitude (−(2.06/24)(ωh)⁴ for five samples), about the
        // noise; faster fringes (thick films) take the fitted path.
        let omega = 4.0 * PI * g * 1e-4;
        for e in ext {
            let h = self.parabola[usize::from(e.band)]
                .as_ref()
                .map_or(f64::INFINITY, |w| w.spacing);
            if omega * h > MAX_PHASE_STEP {
                return None;
            }
        }
        // Every lattice point well inside the band range must have been
        // found: a spacing that predicts an extremum where the spectrum has
        // none is not this pixel's (two extrema alone fit any spacing).
        // Near an end, a fringe top flattened against it can escape the
        // detection: only points an eighth wave inside are required.
        let eighth = 0.125 / g;
        let lo_s = self.interior.0.max(self.sigma_range.0 + eighth);
        let hi_s = self.interior.1.min(self.sigma_range.1 - eighth);
        // Half-integers strictly between: ⌈4g·hi⌉ − ⌊4g·lo⌋ − 1, with the
        // rounding of `fastmath` (libm's floor is a call without SSE4.1).
        let expected = round(4.0 * g * hi_s + 0.5) - round(4.0 * g * lo_s - 0.5) - 1.0;
        // Found extrema count by their lattice points, so one measured
        // just across a bound is not told apart from its prediction.
        let (k_lo, k_hi) = (2.0 * g * lo_s, 2.0 * g * hi_s);
        let found = orders[..n_ext]
            .iter()
            .filter(|&&k| k > k_lo && k < k_hi)
            .count();
        if expected > found as f64 {
            return None;
        }
        let n1 = prep.model.n1_mid();
        let (theta, s2, var_theta) = match theta_known {
            Some(t) => {
                let s = super::fastmath::sin_cos(t).0;
                (t, s * s, 0.0)
            }
            None => {
                let (lo, hi) = self.theta_range;
                let half = (nh > 0).then(|| hw * INV_SMALL[nh]);
                let quarter = (nq > 0).then(|| qw * INV_SMALL[nq]);
                // sin²θ of the half-wave level, inverted exactly where the
                // media allow it.
                let exact = match (prep.closed_form, half) {
                    (Some((n1, n3, pol)), Some(h)) => match half_wave_sin2(h, n1, n3, pol) {
                        [Some(a), None] | [None, Some(a)] => Some(a),
                        // Both sides of Brewster's angle: the quarter-wave
                        // level (through the table) decides.
                        [Some(a), Some(b)] => {
                            let t = angle_start(&prep.table, half, quarter);
                            let (ta, tb) = (a.sqrt().asin(), b.sqrt().asin());
                            Some(if (ta - t).abs() <= (tb - t).abs() {
                                a
                            } else {
                                b
                            })
                        }
                        // Below the normal-incidence level: noise on a
                        // near-normal pixel.
                        [None, None] if h < prep.table[0].1 && pol == Polarization::S => {
                            Some(self.sin2_range.0)
                        }
                        [None, None] => None,
                    },
                    _ => None,
                };
                let (t, s2) = match exact {
                    Some(s2) if s2 < self.sin2_range.0 => (lo, self.sin2_range.0),
                    Some(s2) if s2 > self.sin2_range.1 => (hi, self.sin2_range.1),
                    Some(s2) => (s2.sqrt().asin(), s2),
                    None => {
                        let t = angle_start(&prep.table, half, quarter);
                        let s = super::fastmath::sin_cos(t).0;
                        (t, s * s)
                    }
                };
                // σ_θ = σ_R / |dR/dθ| of the mean half-wave level (Eq.
                // 10's slope), capped at a uniform spread over the range.
                let slope = prep.slopes.at(t);
                let cap = (hi - lo) * (hi - lo) / 12.0;
                let var_t = if nh > 0 && slope != 0.0 {
                    let nhf = nh as f64;
                    (var_hw * var_r / (nhf * nhf * slope * slope)).min(cap)
                } else {
                    cap
                };
                (t, s2, var_t)
            }
        };
        // Two extrema alone carry no check of their spacing (any spacing
        // is a quarter wave of some g): a noise wiggle on a thin film's
        // slope would pass as a fringe of a thick one. Their levels must
        // then be the model's half- and quarter-wave levels at this angle.
        if n_ext == 2 {
            let (env_h, env_q) = prep.envelopes_at(theta);
            let sd_r = var_r.sqrt();
            let tol = 0.2 * (env_h - env_q).abs() + 5.0 * sd_r;
            for e in ext {
                let env = if e.kind == half_kind { env_h } else { env_q };
                // (NaN fails too.)
                if (e.val - env).abs().partial_cmp(&tol) != Some(std::cmp::Ordering::Less) {
                    return None;
                }
            }
        }
        // q2 = n2 cos θ2 = √(n2² − n1² sin²θ), as `FilmModel::q2_mid`.
        let n2 = prep.model.n2_mid();
        let q2 = (n2 * n2 - n1 * n1 * s2).max(1e-12).sqrt();
        let inv_q2 = 1.0 / q2;
        let d = g * inv_q2;
        if !(d.is_finite() && d >= 0.0 && d <= self.d_max) {
            return None;
        }
        // d = g/q2(θ): the angle's error moves d through
        // dq2/dθ = −n1² sinθ cosθ / q2; the global index's through
        // ∂d/∂n2 = −d·n2/q2² at fixed optical thickness.
        let dq2 = n1 * n1 * (s2 * (1.0 - s2)).max(0.0).sqrt() * inv_q2;
        let dd_dtheta = d * dq2 * inv_q2;
        let mut var_d = var_g * inv_q2 * inv_q2 + dd_dtheta * dd_dtheta * var_theta;
        let mut n_film = n2;
        if let Some(index) = index {
            let dd_dn = d * index.n * inv_q2 * inv_q2;
            var_d += dd_dn * dd_dn * index.sigma * index.sigma;
            n_film = index.n;
        }
        let sigma_theta = var_theta.sqrt();
        let reason = if theta_known.is_none() && sigma_theta.to_degrees() > ANGLE_SIGMA_LIMIT_DEG {
            Reason::AngleNotIdentifiable
        } else {
            Reason::Ok
        };
        Some(PixelEstimate {
            thickness_nm: d,
            n_film,
            theta_deg: theta.to_degrees(),
            sigma_thickness_nm: var_d.sqrt(),
            sigma_theta_deg: sigma_theta.to_degrees(),
            residual_rms: (rss * INV_SMALL[5 * n_ext.min(MAX_EXT)]).sqrt(),
            reason,
        })
    }

    /// Candidate optical thicknesses: local minima of the projection
    /// residual with the allowed fringe sign, best first.
    fn fringe_search(
        &self,
        scratch: &Scratch,
        sign: f64,
        complete: bool,
        out: &mut [Candidate; MAX_CANDIDATES],
    ) -> usize {
        let fb = &self.basis;
        let nb = fb.nb;
        let y = &scratch.spectrum;
        let wgt = &scratch.weight;
        let n_ok: f64 = wgt.iter().sum();
        let s_r: f64 = y.iter().sum();
        let s_rr: f64 = y.iter().map(|v| v * v).sum();
        let yf: [f32; MAX_BANDS] = {
            let mut a = [0f32; MAX_BANDS];
            for (d, s) in a.iter_mut().zip(y) {
                *d = *s as f32;
            }
            a
        };
        let yf = &yf[..nb];
        let mut prev2 = f64::INFINITY;
        let mut prev = f64::INFINITY;
        let mut prev_c = Candidate::default();
        let mut n = 0usize;
        let push = |c: Candidate, out: &mut [Candidate; MAX_CANDIDATES], n: &mut usize| {
            // Keep the best MAX_CANDIDATES by residual.
            if *n < MAX_CANDIDATES {
                out[*n] = c;
                *n += 1;
            } else if let Some(worst) = out
                .iter_mut()
                .max_by(|a, b| a.sse.total_cmp(&b.sse))
                .filter(|w| w.sse > c.sse)
            {
                *worst = c;
            }
        };
        for j in 0..fb.g.len() {
            let basis = &fb.basis[j * nb..(j + 1) * nb];
            let s_rc = f64::from(dot(yf, basis));
            let [a, b, c] = if complete {
                fb.minv[j]
            } else {
                let (mut s1, mut s2) = (0.0, 0.0);
                for k in 0..nb {
                    let cv = f64::from(basis[k]) * wgt[k];
                    s1 += cv;
                    s2 += cv * f64::from(basis[k]);
                }
                let det = n_ok * s2 - s1 * s1;
                if det > 0.02 * n_ok * n_ok {
                    [s2 / det, -s1 / det, n_ok / det]
                } else {
                    [f64::NAN; 3]
                }
            };
            let (cur, cand) = if a.is_nan() {
                (f64::INFINITY, Candidate::default())
            } else {
                let amp_a = a * s_r + b * s_rc;
                let amp_b = b * s_r + c * s_rc;
                let e = s_rr - (amp_a * s_r + amp_b * s_rc);
                if amp_b * sign < 0.0 {
                    (f64::INFINITY, Candidate::default())
                } else {
                    (
                        e,
                        Candidate {
                            g: fb.g[j],
                            a: amp_a,
                            b: amp_b,
                            sse: e,
                        },
                    )
                }
            };
            if prev.is_finite() && prev <= prev2 && prev < cur {
                push(prev_c, out, &mut n);
            }
            prev2 = prev;
            prev = cur;
            prev_c = cand;
        }
        if prev.is_finite() && prev <= prev2 {
            push(prev_c, out, &mut n);
        }
        out[..n].sort_by(|a, b| a.sse.total_cmp(&b.sse));
        n
    }

    /// Levenberg–Marquardt on thickness (and angle when `free_theta`).
    fn refine(
        &self,
        model: &FilmModel,
        d0: f64,
        theta0: f64,
        free_theta: bool,
        iters: usize,
        s: &mut Scratch,
    ) -> Fit {
        let (lo, hi) = self.theta_range;
        let eval = |d: f64, th: f64, out: &mut ModelOut| {
            model.eval(d, th, out, true);
        };
        let (mut d, mut th) = (d0.clamp(0.0, self.d_max), theta0);
        eval(d, th, &mut s.cur);
        let mut cur_sse = sse(&s.spectrum, &s.weight, &s.cur.r);
        let mut mu = 1e-4;
        for _ in 0..iters {
            let (mut a, mut b, mut c, mut gd, mut gt) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for k in 0..s.spectrum.len() {
                let w = s.weight[k];
                let e = s.spectrum[k] - s.cur.r[k];
                let jd = s.cur.dr_dd[k];
                let jt = if free_theta { s.cur.dr_dth[k] } else { 0.0 };
                a += w * jd * jd;
                b += w * jd * jt;
                c += w * jt * jt;
                gd += w * jd * e;
                gt += w * jt * e;
            }
            let mut accepted = false;
            for _ in 0..6 {
                let (sd, st) = if free_theta {
                    let aa = a * (1.0 + mu) + 1e-12;
                    let cc = c * (1.0 + mu) + 1e-12;
                    let det = aa * cc - b * b;
                    if det <= 0.0 {
                        (gd / aa, 0.0)
                    } else {
                        ((cc * gd - b * gt) / det, (aa * gt - b * gd) / det)
                    }
                } else {
                    (gd / (a * (1.0 + mu) + 1e-12), 0.0)
                };
                // Never jump more than a quarter fringe in one step.
                let max_dd = 0.25 * 400.0 / (2.0 * model.n2_mid());
                let nd = (d + sd.clamp(-max_dd, max_dd)).clamp(0.0, self.d_max);
                let nt = (th + st.clamp(-0.1, 0.1)).clamp(lo, hi);
                eval(nd, nt, &mut s.trial);
                let new_sse = sse(&s.spectrum, &s.weight, &s.trial.r);
                if new_sse <= cur_sse {
                    // Converged once a step is far below the statistical error
                    // (σ_d ~ 0.3 nm, σ_θ ~ 1e-3 rad at the paper's noise) or
                    // the residual no longer moves.
                    let small = ((nd - d).abs() < 5e-3 && (nt - th).abs() < 2e-5)
                        || cur_sse - new_sse <= 1e-8 * cur_sse;
                    d = nd;
                    th = nt;
                    cur_sse = new_sse;
                    std::mem::swap(&mut s.cur, &mut s.trial);
                    mu = (mu * 0.3).max(1e-9);
                    accepted = !small;
                    break;
                }
                mu = (mu * 10.0).max(1e-3);
            }
            if !accepted {
                break;
            }
        }
        let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
        for k in 0..s.spectrum.len() {
            let w = s.weight[k];
            let jd = s.cur.dr_dd[k];
            let jt = if free_theta { s.cur.dr_dth[k] } else { 0.0 };
            a += w * jd * jd;
            b += w * jd * jt;
            c += w * jt * jt;
        }
        Fit {
            d,
            theta: th,
            sse: cur_sse,
            jtj: [a, b, c],
            integrated: false,
        }
    }
}

/// The angle whose model envelopes best match the fitted half-wave and
/// quarter-wave levels, refined by a parabola through the best table entry.
fn angle_start(table: &[(f64, f64, f64)], half: Option<f64>, quarter: Option<f64>) -> f64 {
    let cost = |e: &(f64, f64, f64)| {
        half.map_or(0.0, |h| (e.1 - h).powi(2)) + quarter.map_or(0.0, |q| (e.2 - q).powi(2))
    };
    // Coarse to fine: every fourth entry, then the neighbourhood of the best
    // (the cost is smooth on the 0.5° table, so its minimum is not skipped).
    let best_in = |range: std::ops::Range<usize>, step: usize| {
        range
            .step_by(step)
            .filter(|&i| table[i].1.is_finite() && table[i].2.is_finite())
            .min_by(|&a, &b| cost(&table[a]).total_cmp(&cost(&table[b])))
    };
    let Some(coarse) = best_in(0..table.len(), 4) else {
        return 0.0;
    };
    let lo = coarse.saturating_sub(4);
    let hi = (coarse + 5).min(table.len());
    let Some(i) = best_in(lo..hi, 1) else {
        return table[coarse].0;
    };
    if i == 0 || i + 1 >= table.len() {
        return table[i].0;
    }
    let (c0, c1, c2) = (cost(&table[i - 1]), cost(&table[i]), cost(&table[i + 1]));
    let den = c0 - 2.0 * c1 + c2;
    let step = table[i + 1].0 - table[i].0;
    if den > 0.0 {
        table[i].0 + 0.5 * step * (c0 - c2) / den
    } else {
        table[i].0
    }
}

#[inline]
fn sse(y: &[f64], w: &[f64], r: &[f64]) -> f64 {
    y.iter()
        .zip(w)
        .zip(r)
        .map(|((y, w), r)| w * (y - r) * (y - r))
        .sum()
}

/// f32 dot product with independent accumulators so it vectorises.
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let ca = a.chunks_exact(8);
    let cb = b.chunks_exact(8);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i] * y[i];
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

impl Prepared {
    /// The half- and quarter-wave levels at `theta`, interpolated in the
    /// angle table (its ends beyond it).
    fn envelopes_at(&self, theta: f64) -> (f64, f64) {
        let t = &self.table;
        let sl = &self.slopes;
        if t.len() < 2 {
            return t.first().map_or((f64::NAN, f64::NAN), |e| (e.1, e.2));
        }
        let x = ((theta - sl.t0) * sl.inv_step).clamp(0.0, (t.len() - 1) as f64);
        let k = (x as usize).min(t.len() - 2);
        let f = x - k as f64;
        let (a, b) = (t[k], t[k + 1]);
        (a.1 + f * (b.1 - a.1), a.2 + f * (b.2 - a.2))
    }
}

/// Slope dR/dθ of the half-wave envelope, per interval of the (uniform)
/// angle table, looked up without a division.
#[derive(Clone, Debug)]
struct Slopes {
    t0: f64,
    inv_step: f64,
    slope: Vec<f64>,
}

impl Slopes {
    fn new(table: &[(f64, f64, f64)]) -> Slopes {
        let step = if table.len() >= 2 {
            table[1].0 - table[0].0
        } else {
            0.0
        };
        Slopes {
            t0: table.first().map_or(0.0, |e| e.0),
            inv_step: if step > 0.0 { 1.0 / step } else { 0.0 },
            slope: table
                .windows(2)
                .map(|w| (w[1].1 - w[0].1) / (w[1].0 - w[0].0))
                .collect(),
        }
    }

    /// The slope at `theta` (the end intervals beyond the table).
    #[inline]
    fn at(&self, theta: f64) -> f64 {
        let k = ((theta - self.t0) * self.inv_step).max(0.0) as usize;
        self.slope
            .get(k.min(self.slope.len().saturating_sub(1)))
            .copied()
            .unwrap_or(0.0)
    }
}

/// Inverse of a 3×3 matrix by cofactors; `None` if singular.
fn inv3(m: [[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c =
        |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let cof = [
        [c(1, 2, 1, 2), -c(1, 2, 0, 2), c(1, 2, 0, 1)],
        [-c(0, 2, 1, 2), c(0, 2, 0, 2), -c(0, 2, 0, 1)],
        [c(0, 1, 1, 2), -c(0, 1, 0, 2), c(0, 1, 0, 1)],
    ];
    let det = m[0][0] * cof[0][0] + m[0][1] * cof[0][1] + m[0][2] * cof[0][2];
    if !det.is_finite() || det.abs() < 1e-300 {
        return None;
    }
    // inverse = adjugate / det, adjugate = cofactor transposed.
    Some(std::array::from_fn(|r| {
        std::array::from_fn(|c| cof[c][r] / det)
    }))
}

/// Solve a 3×3 linear system by Cramer's rule; `None` if singular.
fn solve3(m: [[f64; 3]; 3], v: [f64; 3]) -> Option<[f64; 3]> {
    let det3 = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det3(m);
    if d.abs() < 1e-300 || !d.is_finite() {
        return None;
    }
    let mut out = [0.0; 3];
    for (i, o) in out.iter_mut().enumerate() {
        let mut mi = m;
        for r in 0..3 {
            mi[r][i] = v[r];
        }
        *o = det3(mi) / d;
    }
    Some(out)
}
