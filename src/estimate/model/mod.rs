//! The forward model the estimators fit: reflectance of one film at every
//! band for a thickness and an angle, with its thickness derivative.
//!
//! Two paths share one interface. For lossless media below every critical
//! angle the Fresnel coefficients are real and thickness enters only through
//! `cos Δ` (the paper's "cost structure"): coefficients are computed once per
//! angle (once per band only if a medium disperses) and each band then costs
//! one `sin_cos`. Anything else — an absorbing film or substrate, total
//! internal reflection — takes the general complex Airy form.
//!
//! A band is a set of nodes (wavelength, weight): one node for a point
//! sample, several when the passband has to be integrated. The model value
//! of a band is the weighted sum over its nodes.

/// `for $i in 0..$n { $body }` for the vectorised kernels: whole vectors
/// of eight (one AVX-512 register of `f64`, two of AVX2), each an inner
/// loop of constant length that compiles to straight vector code, then the
/// last partial vector again from its end, overlapping the one before (the
/// body must give the same result twice); fewer than eight, one by one. A
/// scalar tail cost as much as a dozen nodes in vectors: with vectors of
/// four, 31 bands left eight bands to scalar code on AVX-512 (the
/// compiler's remainder of 28 and the tail of four), half the kernel's
/// time. A macro, not a closure: a closure is not compiled with the
/// kernel's target features.
macro_rules! overlapped {
    ($i:ident in $n:expr, in($($x:ident),*), out($($y:ident),*) => $body:block) => {{
        #![allow(clippy::needless_range_loop)] // several arrays, indexed alike
        const L: usize = 8;
        let n: usize = $n;
        if n < L {
            for $i in 0..n $body
        } else {
            let mut base = 0;
            loop {
                {
                    // Each array cut to the vector: no bounds check is
                    // left in the loop, which then compiles to vector code.
                    $(let $x = &$x[base..base + L];)*
                    $(let $y = &mut $y[base..base + L];)*
                    for $i in 0..L $body
                }
                if base + L == n {
                    break;
                }
                // The next vector, or the last one ending at n.
                base = (base + L).min(n - L);
            }
        }
    }};
}

mod node;
mod real;
mod real32;

use super::fastmath::{sin_cos, sin_cos_bounded};
use crate::optics::airy;
use crate::optics::band::Band;
use crate::optics::dispersion::Dispersion;
use crate::optics::{Complex64, Media, Polarization};
use multiversion::multiversion;
use node::NodeCoef;
use real::{real_nodes_kernel, RealArgs, RealNodes};
use real32::{real_nodes_kernel32, RealNodes32};
use std::f64::consts::PI;
use std::sync::atomic::{AtomicU64, Ordering};

/// Angle step of the finite differences of the Fresnel coefficients, rad.
const THETA_STEP: f64 = 1e-6;

/// Coefficients of both polarisations at an angle and a step beyond it.
#[derive(Clone, Copy, Debug)]
struct CoeffSet {
    cs: Coeffs,
    cp: Coeffs,
    cs_h: Coeffs,
    cp_h: Coeffs,
    q2: f64,
    dq2: f64,
}

/// The polarisation mix of the real path, with each coefficient's change
/// per radian of incidence angle.
#[derive(Clone, Copy, Debug)]
struct Pol {
    ws: f64,
    wp: f64,
    s: Coeffs,
    p: Coeffs,
    ds: Coeffs,
    dp: Coeffs,
}

impl Pol {
    fn new(ws: f64, k: &CoeffSet) -> Pol {
        let slope = |a: Coeffs, b: Coeffs| Coeffs {
            a: (b.a - a.a) / THETA_STEP,
            b: (b.b - a.b) / THETA_STEP,
            c: (b.c - a.c) / THETA_STEP,
        };
        Pol {
            ws,
            wp: 1.0 - ws,
            s: k.cs,
            p: k.cp,
            ds: slope(k.cs, k.cs_h),
            dp: slope(k.cp, k.cp_h),
        }
    }

    #[inline(always)]
    fn value(&self, x: f64) -> f64 {
        let one = |c: Coeffs| (c.a + c.b * x) / (c.c + c.b * x);
        if self.wp == 0.0 {
            one(self.s)
        } else if self.ws == 0.0 {
            one(self.p)
        } else {
            self.ws * one(self.s) + self.wp * one(self.p)
        }
    }

    /// R, dR/dx at fixed coefficients, and dR/dθ through the coefficients.
    #[inline(always)]
    fn value_slopes(&self, x: f64) -> (f64, f64, f64) {
        let one = |c: Coeffs, dc: Coeffs| {
            let inv = 1.0 / (c.c + c.b * x);
            let r = (c.a + c.b * x) * inv;
            let dx = c.b * (c.c - c.a) * inv * inv;
            let dth = (dc.a + x * dc.b - r * (dc.c + x * dc.b)) * inv;
            (r, dx, dth)
        };
        if self.wp == 0.0 {
            one(self.s, self.ds)
        } else if self.ws == 0.0 {
            one(self.p, self.dp)
        } else {
            let (r1, x1, t1) = one(self.s, self.ds);
            let (r2, x2, t2) = one(self.p, self.dp);
            (
                self.ws * r1 + self.wp * r2,
                self.ws * x1 + self.wp * x2,
                self.ws * t1 + self.wp * t2,
            )
        }
    }
}

/// Scalars of [`uniform_kernel`].
#[derive(Clone, Copy)]
struct UniformArgs {
    d: f64,
    q2: f64,
    dq2: f64,
    pol: Pol,
    deriv: bool,
}

/// The band loop of the uniform real path, compiled for the best vector
/// unit the CPU offers (chosen once at run time; the baseline build runs
/// everywhere).
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn uniform_kernel(w: &[f64], a: UniformArgs, r: &mut [f64], dd: &mut [f64], dth: &mut [f64]) {
    let UniformArgs {
        d,
        q2,
        dq2,
        pol,
        deriv,
    } = a;
    let kd = q2 * d;
    let n = w.len().min(r.len()).min(dd.len()).min(dth.len());
    let (w, r, dd, dth) = (&w[..n], &mut r[..n], &mut dd[..n], &mut dth[..n]);
    if !deriv {
        overlapped!(i in n, in(w), out(r) => {
            let (_, c) = sin_cos_bounded(w[i] * kd);
            r[i] = pol.value(c);
        });
        return;
    }
    // One polarisation (the common case) gets its own loop so it vectorises
    // without per-band branches.
    let single = if pol.wp == 0.0 {
        Some((pol.s, pol.ds))
    } else if pol.ws == 0.0 {
        Some((pol.p, pol.dp))
    } else {
        None
    };
    match single {
        Some((cf, dc)) => {
            overlapped!(i in n, in(w), out(r, dd, dth) => {
                let (sn, x) = sin_cos_bounded(w[i] * kd);
                let inv = 1.0 / (cf.c + cf.b * x);
                let rv = (cf.a + cf.b * x) * inv;
                let dx = cf.b * (cf.c - cf.a) * inv * inv;
                let dcoef = (dc.a + x * dc.b - rv * (dc.c + x * dc.b)) * inv;
                r[i] = rv;
                let dphase = -sn * w[i];
                dd[i] = dx * dphase * q2;
                dth[i] = dcoef + dx * dphase * d * dq2;
            });
        }
        None => {
            overlapped!(i in n, in(w), out(r, dd, dth) => {
                let (sn, x) = sin_cos_bounded(w[i] * kd);
                let (rv, dx, dcoef) = pol.value_slopes(x);
                r[i] = rv;
                let dphase = -sn * w[i];
                dd[i] = dx * dphase * q2;
                dth[i] = dcoef + dx * dphase * d * dq2;
            });
        }
    }
}

/// Sine and cosine of an angle and of the angle one [`THETA_STEP`] beyond.
#[derive(Clone, Copy, Debug)]
struct AngleAt {
    theta: f64,
    s: f64,
    c: f64,
    sh: f64,
    ch: f64,
}

impl AngleAt {
    fn new(theta: f64) -> Self {
        let (s, c) = sin_cos(theta);
        let (sh, ch) = sin_cos(theta + THETA_STEP);
        AngleAt {
            theta,
            s,
            c,
            sh,
            ch,
        }
    }
}

/// One quadrature node of a band.
#[derive(Clone, Copy, Debug)]
struct Node {
    /// Index of the band (cube plane) it contributes to.
    band: usize,
    /// Weight (a band's weights sum to 1).
    weight: f64,
    /// Wavelength, nm.
    lambda: f64,
    /// `4π / λ`.
    w: f64,
    n1: Complex64,
    n2: Complex64,
    n3: Complex64,
}

/// Fresnel pair of one polarisation for the real path.
#[derive(Clone, Copy, Debug, Default)]
struct Coeffs {
    a: f64,
    b: f64,
    c: f64,
}

impl Coeffs {
    fn new(r12: f64, r23: f64) -> Self {
        Coeffs {
            a: r12 * r12 + r23 * r23,
            b: 2.0 * r12 * r23,
            c: 1.0 + r12 * r12 * r23 * r23,
        }
    }

    /// R and dR/d(cos Δ).
    #[inline(always)]
    fn eval(self, x: f64) -> (f64, f64) {
        let den = self.c + self.b * x;
        let inv = 1.0 / den;
        (
            (self.a + self.b * x) * inv,
            self.b * (self.c - self.a) * inv * inv,
        )
    }
}

/// The largest change of any reflectance for which a substrate's
/// absorption is neglected: a fiftieth of the lowest noise level irid
/// accepts (1e-4), a fifth of the thickness tables' interpolation
/// tolerance. (A PET web, k ≈ 2e-6, changes R by up to ~7e-7.)
const LOSSLESS_TOL: f64 = 2e-6;

/// Whether dropping the substrate's extinction at this node changes the
/// reflectance of either polarisation by less than [`LOSSLESS_TOL`], at
/// every film phase (eight per period: the substrate's loss enters only
/// through the film/substrate coefficient, not the phase) and angle (ten,
/// from normal incidence to 88°), with a margin for what lies
/// between the samples (twice the largest sampled change must stay within
/// it). Always false for a film or ambient that absorbs.
fn substrate_loss_negligible(n: &Node) -> bool {
    let lossy = Media {
        n1: n.n1,
        n2: n.n2,
        n3: n.n3,
    };
    let lossless = Media {
        n3: Complex64::new(n.n3.re, 0.0),
        ..lossy
    };
    for deg in [0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 88.0f64] {
        let th = deg.to_radians();
        let q2 = airy::normal_component(n.n2, n.n1 * th.sin()).re;
        // Past the film's critical angle (or NaN): not the real path's case.
        if q2.is_nan() || q2 <= 0.0 {
            return false;
        }
        for i in 0..8 {
            let phase = (i as f64 + 0.5) * PI / 4.0;
            let d = phase / (n.w * q2);
            let a = airy::reflectance_sp(lossy, d, th, n.lambda);
            let b = airy::reflectance_sp(lossless, d, th, n.lambda);
            if (a.0 - b.0).abs().max((a.1 - b.1).abs()) * 2.0 > LOSSLESS_TOL {
                return false;
            }
        }
    }
    true
}

/// Identity of each built model, so a scratch's cached coefficients are
/// never reused for another model.
static NEXT_MODEL_ID: AtomicU64 = AtomicU64::new(1);

/// Step of the angle grid the general path interpolates its coefficients
/// on, rad (0.25°).
const GRID_STEP: f64 = 0.25 * PI / 180.0;

/// Every node's coefficients on an angle grid `i · GRID_STEP`, up to
/// `n_t` angles, row-major by angle.
#[derive(Debug)]
struct AngleGrid {
    n_t: usize,
    coef: Vec<NodeCoef>,
}

/// The forward model for one film index (known or trial) and one band set.
#[derive(Clone, Debug)]
pub struct FilmModel {
    /// The general path's coefficient grid, built once the model has
    /// computed as many coefficient sets by hand as the grid holds.
    grid: std::sync::Arc<std::sync::OnceLock<AngleGrid>>,
    /// Coefficient sets computed without the grid so far.
    misses: std::sync::Arc<AtomicU64>,
    /// Identity for the coefficient cache in [`ModelOut`].
    id: u64,
    nodes: Vec<Node>,
    /// `4π/λ` per band, for the uniform path.
    w: Vec<f64>,
    /// Largest sin θ1 below every critical angle (film and substrate).
    sin_critical: f64,
    n_bands: usize,
    /// All media lossless and real at every node.
    real: bool,
    /// Every node has the same indices (no dispersion).
    uniform: bool,
    /// The real path's per-node constants where the media are lossless
    /// but disperse (empty otherwise).
    real_nodes: RealNodes,
    /// The same in `f32`, for films and angles where that is exact enough.
    real_nodes32: RealNodes32,
    /// Node `i` is band `i`'s only node (every band point-sampled).
    one_node_per_band: bool,
    s_weight: f64,
    /// Film index at the middle band (real part).
    n2_mid: f64,
    /// Ambient index (real part), for the Snell invariant.
    n1_mid: f64,
}

/// Per-band model values and derivatives.
#[derive(Clone, Debug, Default)]
pub struct ModelOut {
    /// Reflectance per band.
    pub r: Vec<f64>,
    /// dR/dd per band (per nm).
    pub dr_dd: Vec<f64>,
    /// dR/dθ per band (per radian).
    pub dr_dth: Vec<f64>,
    /// The general path's per-node coefficients at one angle, kept between
    /// evaluations at that angle (a known angle pays for them once).
    coef: Vec<NodeCoef>,
    /// `(model id, angle bits)` the coefficients belong to.
    coef_key: (u64, u64),
    /// Per-node values of the real dispersive path where a band has
    /// several nodes (sized on first use).
    node: [Vec<f64>; 3],
}

impl ModelOut {
    /// Buffers for `n` bands.
    pub fn new(n: usize) -> Self {
        ModelOut {
            r: vec![0.0; n],
            dr_dd: vec![0.0; n],
            dr_dth: vec![0.0; n],
            coef: Vec::new(),
            coef_key: (0, 0),
            node: Default::default(),
        }
    }
}

/// Node coefficients with each band at its own incidence angle (see
/// [`FilmModel::band_angles`]).
#[derive(Clone, Debug, Default)]
pub struct BandAngles {
    coef: Vec<NodeCoef>,
    /// The model they belong to.
    model_id: u64,
}

impl BandAngles {
    /// Whether these coefficients were computed by `model`.
    pub fn belongs_to(&self, model: &FilmModel) -> bool {
        self.model_id == model.id && self.coef.len() == model.nodes.len()
    }
}

impl FilmModel {
    /// The node coefficients with band `b` at incidence angle `thetas[b]`
    /// (rad), into `out` (its buffer reused): for spectra whose bands were
    /// seen at different angles. Computed once per set of angles; each
    /// thickness then costs what one evaluation at one angle does
    /// ([`FilmModel::eval_band_angles`]). Bands beyond `thetas` are at the
    /// last angle given.
    pub fn band_angles(&self, thetas: &[f64], out: &mut BandAngles) {
        out.coef.clear();
        out.model_id = self.id;
        let last = thetas.last().copied().unwrap_or(0.0);
        for n in &self.nodes {
            let t = thetas.get(n.band).copied().unwrap_or(last);
            out.coef.push(NodeCoef::new(
                [n.n1, n.n2, n.n3],
                n.w,
                t.sin(),
                (t + THETA_STEP).sin(),
                THETA_STEP,
            ));
        }
    }

    /// Reflectance per band at thickness `d` (nm), each band at the angle
    /// `angles` gives it (the general path's exact Airy form). `r` holds
    /// [`FilmModel::n_bands`] values; NaN everywhere when `angles` belongs
    /// to another model.
    pub fn eval_band_angles(&self, angles: &BandAngles, d: f64, r: &mut [f64]) {
        let nb = self.n_bands.min(r.len());
        if !angles.belongs_to(self) {
            r[..nb].fill(f64::NAN);
            return;
        }
        r[..nb].fill(0.0);
        for (n, c) in self.nodes.iter().zip(&angles.coef) {
            if n.band < nb {
                r[n.band] += n.weight * c.eval(d, self.s_weight, false).0;
            }
        }
    }

    /// [`FilmModel::eval_band_angles`] with dR/dd per band into `dr_dd`.
    pub fn eval_band_angles_deriv(
        &self,
        angles: &BandAngles,
        d: f64,
        r: &mut [f64],
        dr_dd: &mut [f64],
    ) {
        let nb = self.n_bands.min(r.len()).min(dr_dd.len());
        if !angles.belongs_to(self) {
            r[..nb].fill(f64::NAN);
            dr_dd[..nb].fill(f64::NAN);
            return;
        }
        r[..nb].fill(0.0);
        dr_dd[..nb].fill(0.0);
        for (n, c) in self.nodes.iter().zip(&angles.coef) {
            if n.band < nb {
                let (v, dd, _) = c.eval(d, self.s_weight, true);
                r[n.band] += n.weight * v;
                dr_dd[n.band] += n.weight * dd;
            }
        }
    }

    /// Build the model. `integrate[i]` selects passband integration for band
    /// `i` (if it has a width, with the 9-point rule); other bands are
    /// point-sampled at their centre.
    pub fn new(
        bands: &[Band],
        ambient: &Dispersion,
        film: &Dispersion,
        substrate: &Dispersion,
        pol: Polarization,
        integrate: &[bool],
    ) -> Result<FilmModel, (&'static str, crate::optics::dispersion::OpticsError)> {
        let nodes: Vec<usize> = integrate
            .iter()
            .map(|&i| if i { crate::optics::band::N_NODES } else { 1 })
            .collect();
        Self::with_nodes(bands, ambient, film, substrate, pol, &nodes)
    }

    /// Build the model with band `i`'s passband integrated on `nodes[i]`
    /// Gauss–Hermite nodes ([`Band::nodes_of`]; 1, or a band without a
    /// width: its centre alone).
    pub fn with_nodes(
        bands: &[Band],
        ambient: &Dispersion,
        film: &Dispersion,
        substrate: &Dispersion,
        pol: Polarization,
        nodes_per_band: &[usize],
    ) -> Result<FilmModel, (&'static str, crate::optics::dispersion::OpticsError)> {
        let mut nodes: Vec<Node> = Vec::new();
        for (i, band) in bands.iter().enumerate() {
            let n = match band.fwhm_nm > 0.0 {
                true => nodes_per_band.get(i).copied().unwrap_or(1),
                false => 1,
            };
            let pts = band.nodes_of(n);
            for (lambda, weight) in pts {
                nodes.push(Node {
                    band: i,
                    weight,
                    lambda,
                    w: 4.0 * PI / lambda,
                    n1: ambient
                        .index_in_passband(lambda, band.center_nm)
                        .map_err(|e| ("ambient", e))?,
                    n2: film
                        .index_in_passband(lambda, band.center_nm)
                        .map_err(|e| ("film", e))?,
                    n3: substrate
                        .index_in_passband(lambda, band.center_nm)
                        .map_err(|e| ("substrate", e))?,
                });
            }
        }
        // A substrate whose absorption changes no reflectance by more than
        // LOSSLESS_TOL (e.g. a polymer web, k ~ 1e-6) is taken as lossless:
        // the exact real path then applies.
        if nodes.iter().all(|n| n.n1.im == 0.0 && n.n2.im == 0.0)
            && nodes.iter().any(|n| n.n3.im != 0.0)
            && nodes.iter().all(substrate_loss_negligible)
        {
            for n in &mut nodes {
                n.n3 = Complex64::new(n.n3.re, 0.0);
            }
        }
        let real = nodes
            .iter()
            .all(|n| n.n1.im == 0.0 && n.n2.im == 0.0 && n.n3.im == 0.0);
        let first = nodes.first().copied();
        let uniform = first.is_some_and(|f| {
            nodes
                .iter()
                .all(|n| n.n1 == f.n1 && n.n2 == f.n2 && n.n3 == f.n3)
        });
        let mid = bands.len() / 2;
        let mid_node = nodes.iter().find(|n| n.band == mid).copied().or(first);
        let sin_critical = nodes
            .iter()
            .map(|n| (n.n2.re / n.n1.re).min(n.n3.re / n.n1.re))
            .fold(f64::INFINITY, f64::min);
        let one_node_per_band =
            nodes.len() == bands.len() && nodes.iter().enumerate().all(|(i, n)| n.band == i);
        // Lossless media take the real path node by node where they
        // disperse or a passband is integrated (uniform media sampled at
        // the band centres take the uniform path).
        let real_nodes = if real && !(uniform && one_node_per_band) {
            RealNodes::new(&nodes)
        } else {
            RealNodes::default()
        };
        Ok(FilmModel {
            real_nodes32: RealNodes32::new(&real_nodes),
            real_nodes,
            one_node_per_band,
            grid: Default::default(),
            misses: Default::default(),
            id: NEXT_MODEL_ID.fetch_add(1, Ordering::Relaxed),
            sin_critical,
            w: nodes.iter().map(|n| n.w).collect(),
            n_bands: bands.len(),
            real,
            uniform,
            s_weight: pol.s_weight(),
            n2_mid: mid_node.map_or(1.0, |n| n.n2.re),
            n1_mid: mid_node.map_or(1.0, |n| n.n1.re),
            nodes,
        })
    }

    /// Number of bands.
    pub fn n_bands(&self) -> usize {
        self.n_bands
    }

    /// Ambient and substrate indices at the middle band.
    pub fn ambient_substrate_mid(&self) -> (Complex64, Complex64) {
        let mid = self.n_bands / 2;
        self.nodes
            .iter()
            .find(|n| n.band == mid)
            .map_or((Complex64::new(1.0, 0.0), Complex64::new(1.5, 0.0)), |n| {
                (n.n1, n.n3)
            })
    }

    /// Ambient index at the middle band.
    pub fn n1_mid(&self) -> f64 {
        self.n1_mid
    }

    /// Film index at the middle band.
    pub fn n2_mid(&self) -> f64 {
        self.n2_mid
    }

    /// `n2 cos θ2` at the middle band: the factor between thickness and
    /// optical thickness `g = d·n2·cos θ2`.
    pub fn q2_mid(&self, theta: f64) -> f64 {
        let kx = self.n1_mid * sin_cos(theta).0;
        (self.n2_mid * self.n2_mid - kx * kx).max(1e-12).sqrt()
    }

    /// The fastest rate at which any node's phase `4π q2 / λ` moves with
    /// thickness at angle `theta`, rad per nm.
    pub fn max_phase_rate(&self, theta: f64) -> f64 {
        let s = sin_cos(theta).0;
        self.nodes
            .iter()
            .map(|n| n.w * airy::normal_component(n.n2, n.n1 * s).re.abs())
            .fold(0.0, f64::max)
    }

    /// Each band's phase rate `x_k = Re(n2 cos θ2)/λ`, passband-weighted,
    /// per nm: the film's phase `4π d x_k` puts R's extrema in thickness at
    /// `4 d x_k = m` for whole `m` (the fringe orders).
    pub fn phase_rates(&self, theta: f64) -> Vec<f64> {
        let s = sin_cos(theta).0;
        let mut x = vec![0.0; self.n_bands];
        for n in &self.nodes {
            let q = airy::normal_component(n.n2, n.n1 * s).re;
            x[n.band] += n.weight * q / n.lambda;
        }
        x
    }

    /// Whether the fast real path applies at angle `theta`.
    fn real_at(&self, theta: f64) -> bool {
        self.real && sin_cos(theta).0 < self.sin_critical
    }

    /// A number no other model has: what [`FilmModel::eval`] gives
    /// depends on the model, the thickness and the angle alone.
    pub fn id(&self) -> u64 {
        self.id
    }

    /// Model reflectance per band at thickness `d` (nm) and angle `theta`
    /// (rad); with `with_derivative`, also dR/dd and dR/dθ.
    pub fn eval(&self, d: f64, theta: f64, out: &mut ModelOut, with_derivative: bool) {
        // The angle's sines once per evaluation, shared by the real-path
        // test and every node's coefficients.
        let a = AngleAt::new(theta);
        let real = self.real && a.s.max(a.sh) < self.sin_critical;
        if real && self.uniform && self.nodes.len() == self.n_bands {
            // Overwrites every band: no clearing needed.
            self.eval_real_uniform(d, &a, out, with_derivative);
            return;
        }
        if real && self.real_nodes.len() == self.nodes.len() {
            self.eval_real_nodes(d, &a, out, with_derivative);
            return;
        }
        out.r[..self.n_bands].fill(0.0);
        if with_derivative {
            out.dr_dd[..self.n_bands].fill(0.0);
            out.dr_dth[..self.n_bands].fill(0.0);
        }
        self.eval_general(d, theta, &a, out, with_derivative);
    }

    /// The coefficient grid of the general path, built on first use: from
    /// normal incidence up to 89° or to 98 % of the sine of the lowest
    /// critical angle (where the coefficients stop being smooth), whichever
    /// comes first. `None` where the media are uniform and lossless (the
    /// uniform path needs none) or the ambient absorbs, and until the model
    /// has been evaluated at enough distinct angles to pay for it.
    fn angle_grid(&self) -> Option<&AngleGrid> {
        if (self.real && self.uniform) || self.nodes.iter().any(|n| n.n1.im != 0.0) {
            return None;
        }
        if let Some(g) = self.grid.get() {
            return (g.n_t >= 2).then_some(g);
        }
        // Built only once it pays: after as many misses as it has angles.
        if self.misses.fetch_add(1, Ordering::Relaxed) < (89.0 / 0.25) as u64 {
            return None;
        }
        let g = self.grid.get_or_init(|| {
            let s_max = (0.98 * self.sin_critical).min(89f64.to_radians().sin());
            let t_max = if s_max >= 1.0 {
                89f64.to_radians()
            } else {
                s_max.asin()
            };
            let n_t = (t_max / GRID_STEP).floor() as usize + 1;
            let mut coef = Vec::with_capacity(n_t * self.nodes.len());
            for i in 0..n_t {
                let th = i as f64 * GRID_STEP;
                let (s, sh) = (th.sin(), (th + THETA_STEP).sin());
                coef.extend(
                    self.nodes
                        .iter()
                        .map(|n| NodeCoef::new([n.n1, n.n2, n.n3], n.w, s, sh, THETA_STEP)),
                );
            }
            AngleGrid { n_t, coef }
        });
        (g.n_t >= 2).then_some(g)
    }

    /// Any media: per-node coefficients at `theta`, computed once per angle
    /// and cached in `out`, then one `sin_cos` (and an `exp` where the film
    /// absorbs) per node.
    fn eval_general(&self, d: f64, theta: f64, a: &AngleAt, out: &mut ModelOut, deriv: bool) {
        let key = (self.id, theta.to_bits());
        if out.coef_key != key || out.coef.len() != self.nodes.len() {
            out.coef.clear();
            let nn = self.nodes.len();
            match self.angle_grid() {
                Some(g) if theta >= 0.0 && theta < (g.n_t - 1) as f64 * GRID_STEP => {
                    let x = theta / GRID_STEP;
                    let i = (x as usize).min(g.n_t - 2);
                    let t = x - i as f64;
                    let (lo, hi) = (
                        &g.coef[i * nn..(i + 1) * nn],
                        &g.coef[(i + 1) * nn..(i + 2) * nn],
                    );
                    out.coef.extend(
                        lo.iter()
                            .zip(hi)
                            .map(|(a, b)| NodeCoef::between(a, b, t, GRID_STEP)),
                    );
                }
                _ => out.coef.extend(
                    self.nodes
                        .iter()
                        .map(|n| NodeCoef::new([n.n1, n.n2, n.n3], n.w, a.s, a.sh, THETA_STEP)),
                ),
            }
            out.coef_key = key;
        }
        let ws = self.s_weight;
        for (n, c) in self.nodes.iter().zip(&out.coef) {
            let (rv, dd, dth) = c.eval(d, ws, deriv);
            out.r[n.band] += n.weight * rv;
            if deriv {
                out.dr_dd[n.band] += n.weight * dd;
                out.dr_dth[n.band] += n.weight * dth;
            }
        }
    }

    fn coeffs(&self, n: &Node, s: f64, c: f64) -> (Coeffs, Coeffs, f64) {
        let (n1, n2, n3) = (n.n1.re, n.n2.re, n.n3.re);
        let kx = n1 * s;
        let q1 = n1 * c;
        let q2 = (n2 * n2 - kx * kx).sqrt();
        let q3 = (n3 * n3 - kx * kx).sqrt();
        let cs = Coeffs::new((q1 - q2) / (q1 + q2), (q2 - q3) / (q2 + q3));
        let (n1s, n2s, n3s) = (n1 * n1, n2 * n2, n3 * n3);
        let cp = Coeffs::new(
            (n2s * q1 - n1s * q2) / (n2s * q1 + n1s * q2),
            (n3s * q2 - n2s * q3) / (n3s * q2 + n2s * q3),
        );
        (cs, cp, q2)
    }

    /// Both polarisations' coefficients at `theta` and their change over
    /// [`THETA_STEP`], with `q2` and `dq2/dθ`.
    #[inline]
    fn coeffs_with_slope(&self, n: &Node, a: &AngleAt) -> CoeffSet {
        let (cs, cp, q2) = self.coeffs(n, a.s, a.c);
        let (cs_h, cp_h, q2_h) = self.coeffs(n, a.sh, a.ch);
        CoeffSet {
            cs,
            cp,
            cs_h,
            cp_h,
            q2,
            dq2: (q2_h - q2) / THETA_STEP,
        }
    }

    /// The common case: lossless, non-dispersive media, one node per band.
    /// Written as straight loops over bands (phases, then `sin_cos`, then
    /// the rational function) so the compiler vectorises them.
    fn eval_real_uniform(&self, d: f64, a: &AngleAt, out: &mut ModelOut, deriv: bool) {
        let k = self.coeffs_with_slope(&self.nodes[0], a);
        let nb = self.n_bands;
        let pol = Pol::new(self.s_weight, &k);
        let ModelOut {
            r, dr_dd, dr_dth, ..
        } = out;
        uniform_kernel(
            &self.w[..nb],
            UniformArgs {
                d,
                q2: k.q2,
                dq2: k.dq2,
                pol,
                deriv,
            },
            &mut r[..nb],
            &mut dr_dd[..nb],
            &mut dr_dth[..nb],
        );
    }

    /// Every node of the real dispersive path: in `f32` lanes where they
    /// are exact enough ([`real32`]), else in `f64`.
    fn real_kernel(&self, args: RealArgs, r: &mut [f64], dd: &mut [f64], dth: &mut [f64]) {
        if self.real_nodes32.applies(args.d, args.s) {
            real_nodes_kernel32(&self.real_nodes32, args, r, dd, dth);
        } else {
            real_nodes_kernel(&self.real_nodes, args, r, dd, dth);
        }
    }

    /// Lossless dispersive media ([`real`]): every node exact at its own
    /// indices, straight into the bands where each band is one node,
    /// summed by weight where passbands are integrated.
    fn eval_real_nodes(&self, d: f64, a: &AngleAt, out: &mut ModelOut, deriv: bool) {
        let (sm, cm) = sin_cos(a.theta + 0.5 * THETA_STEP);
        let args = RealArgs {
            s: a.s,
            c: a.c,
            sm,
            cm,
            d,
            ws: self.s_weight,
            deriv,
        };
        let nb = self.n_bands;
        if self.one_node_per_band {
            let ModelOut {
                r, dr_dd, dr_dth, ..
            } = out;
            self.real_kernel(args, &mut r[..nb], &mut dr_dd[..nb], &mut dr_dth[..nb]);
            return;
        }
        let nn = self.nodes.len();
        for v in &mut out.node {
            v.resize(nn, 0.0);
        }
        let [nr, ndd, ndth] = &mut out.node;
        self.real_kernel(args, nr, ndd, ndth);
        out.r[..nb].fill(0.0);
        if deriv {
            out.dr_dd[..nb].fill(0.0);
            out.dr_dth[..nb].fill(0.0);
        }
        for (i, n) in self.nodes.iter().enumerate() {
            out.r[n.band] += n.weight * nr[i];
            if deriv {
                out.dr_dd[n.band] += n.weight * ndd[i];
                out.dr_dth[n.band] += n.weight * ndth[i];
            }
        }
    }

    /// The complex Airy summation per node: the reference the other paths
    /// are tested against.
    #[cfg(test)]
    fn eval_complex(&self, d: f64, theta: f64, out: &mut ModelOut, deriv: bool) {
        let pol = Polarization::Mixed {
            s_weight: self.s_weight,
        };
        // A thickness step small against every fringe but far above rounding.
        let h = 1e-3;
        for n in &self.nodes {
            let m = Media {
                n1: n.n1,
                n2: n.n2,
                n3: n.n3,
            };
            let r = airy::reflectance(m, d, theta, n.lambda, pol);
            out.r[n.band] += n.weight * r;
            if deriv {
                let rp = airy::reflectance(m, d + h, theta, n.lambda, pol);
                out.dr_dd[n.band] += n.weight * (rp - r) / h;
                let rt = airy::reflectance(m, d, theta + THETA_STEP, n.lambda, pol);
                out.dr_dth[n.band] += n.weight * (rt - r) / THETA_STEP;
            }
        }
    }

    /// The levels a cosine fit of the fringes reads at the middle band:
    /// `A ± B` of the mean `A` and first harmonic `B` of R over one period
    /// of the phase Δ (32-point quadrature), at `cos Δ = 1` and `−1`. Not
    /// the envelopes: a contrasty film's Airy fringes are far from a
    /// cosine (silicon nitride on silica: a cosine's swing is ~15 % below
    /// the extremes' and centred lower), so a fringe search's levels are
    /// matched to these.
    pub fn cosine_levels(&self, theta: f64) -> (f64, f64) {
        const N: usize = 32;
        let mid = self.n_bands / 2;
        let Some(n) = self.nodes.iter().find(|n| n.band == mid) else {
            return (f64::NAN, f64::NAN);
        };
        let real = self.real_at(theta).then(|| {
            let (s, c) = theta.sin_cos();
            let (cs, cp, _) = self.coeffs(n, s, c);
            (cs, cp)
        });
        let period = n.lambda / (2.0 * self.q2_mid(theta));
        let ws = self.s_weight;
        let (mut mean, mut first) = (0.0, 0.0);
        for j in 0..N {
            let phase = 2.0 * std::f64::consts::PI * j as f64 / N as f64;
            let cd = phase.cos();
            let r = match &real {
                Some((cs, cp)) => ws * cs.eval(cd).0 + (1.0 - ws) * cp.eval(cd).0,
                None => self.airy_at(n, period * j as f64 / N as f64, theta),
            };
            mean += r;
            first += r * cd;
        }
        let (a, b) = (mean / N as f64, 2.0 * first / N as f64);
        (a + b, a - b)
    }

    /// Reflectance at the half-wave (`cos Δ = 1`) and quarter-wave
    /// (`cos Δ = −1`) points at the middle band: the two envelopes the
    /// fringes swing between.
    pub fn envelopes(&self, theta: f64) -> (f64, f64) {
        let mid = self.n_bands / 2;
        let Some(n) = self.nodes.iter().find(|n| n.band == mid) else {
            return (f64::NAN, f64::NAN);
        };
        if self.real_at(theta) {
            let (s, c) = theta.sin_cos();
            let (cs, cp, _) = self.coeffs(n, s, c);
            let ws = self.s_weight;
            let hi = ws * cs.eval(1.0).0 + (1.0 - ws) * cp.eval(1.0).0;
            let lo = ws * cs.eval(-1.0).0 + (1.0 - ws) * cp.eval(-1.0).0;
            (hi, lo)
        } else {
            let half = n.lambda / (2.0 * self.q2_mid(theta));
            (
                self.airy_at(n, half, theta),
                self.airy_at(n, half / 2.0, theta),
            )
        }
    }

    /// Node `n`'s reflectance at thickness `d` and angle `theta` from the
    /// complex Airy sum, in the model's polarisation mix.
    fn airy_at(&self, n: &Node, d: f64, theta: f64) -> f64 {
        let m = Media {
            n1: n.n1,
            n2: n.n2,
            n3: n.n3,
        };
        let pol = Polarization::Mixed {
            s_weight: self.s_weight,
        };
        airy::reflectance(m, d, theta, n.lambda, pol)
    }

    /// The Cramér–Rao bound on a pixel's thickness at `(d, theta)` with
    /// reflectance noise `sigma_r` in every band, `σ_R² (JᵀJ)⁻¹` from the
    /// model's exact Jacobian: `(angle unknown, angle known)`, nm (the
    /// first infinite where the angle's direction is flat, at θ = 0).
    /// `out` is working memory.
    pub fn thickness_crb(
        &self,
        d: f64,
        theta: f64,
        sigma_r: f64,
        out: &mut ModelOut,
    ) -> (f64, f64) {
        self.eval(d, theta, out, true);
        let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
        for k in 0..self.n_bands {
            a += out.dr_dd[k] * out.dr_dd[k];
            b += out.dr_dd[k] * out.dr_dth[k];
            c += out.dr_dth[k] * out.dr_dth[k];
        }
        (sigma_r * (c / (a * c - b * b)).sqrt(), sigma_r / a.sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bands() -> Vec<Band> {
        (0..31)
            .map(|i| Band {
                center_nm: 400.0 + 10.0 * i as f64,
                fwhm_nm: 0.0,
            })
            .collect()
    }

    /// The cosine levels against a second formulation: the mean and first
    /// harmonic of R over one fringe, from the complex Airy sum
    /// (`airy::reflectance`) sampled at 720 thicknesses across one period
    /// at the middle band; and the weak-film limit, where R is a cosine in
    /// the phase and the levels are the envelopes.
    #[test]
    fn cosine_levels_are_the_fringes_mean_and_first_harmonic() {
        for (n2, n3) in [(2.05, 1.46), (1.37, 1.6), (1.45, 1.46)] {
            for pol in [Polarization::S, Polarization::P, Polarization::Unpolarized] {
                let m = FilmModel::new(
                    &bands(),
                    &Dispersion::constant(1.0),
                    &Dispersion::constant(n2),
                    &Dispersion::constant(n3),
                    pol,
                    &[false; 31],
                )
                .unwrap();
                for th in [0.0f64, 0.4, 1.0] {
                    let lambda = bands()[15].center_nm;
                    let period = lambda / (2.0 * m.q2_mid(th));
                    let media = Media {
                        n1: Complex64::new(1.0, 0.0),
                        n2: Complex64::new(n2, 0.0),
                        n3: Complex64::new(n3, 0.0),
                    };
                    let pol_mix = Polarization::Mixed {
                        s_weight: pol.s_weight(),
                    };
                    let (mut mean, mut first) = (0.0, 0.0);
                    const N: usize = 720;
                    for j in 0..N {
                        let d = period * j as f64 / N as f64;
                        let r = airy::reflectance(media, d, th, lambda, pol_mix);
                        let phase = 2.0 * std::f64::consts::PI * j as f64 / N as f64;
                        mean += r / N as f64;
                        first += 2.0 * r * phase.cos() / N as f64;
                    }
                    let (hi, lo) = m.cosine_levels(th);
                    assert!(
                        (hi - (mean + first)).abs() < 1e-9 && (lo - (mean - first)).abs() < 1e-9,
                        "n2 {n2} n3 {n3} {pol:?} θ {th}: {hi} {lo} vs {} {}",
                        mean + first,
                        mean - first
                    );
                    let (eh, el) = m.envelopes(th);
                    let swing = (eh - el).abs();
                    if n2 == 1.45 {
                        // |r23| ~ 0.003: second harmonic ~ r12·r23 of the swing.
                        assert!((hi - eh).abs() < 0.01 * swing && (lo - el).abs() < 0.01 * swing);
                    }
                }
            }
        }
    }

    /// The largest difference over the bands between the model as it runs
    /// (`out`, with its derivatives where `deriv`) and the complex Airy
    /// sum (`refr`) at `d`, `th`.
    fn worst_against_airy(
        m: &FilmModel,
        d: f64,
        th: f64,
        out: &mut ModelOut,
        refr: &mut ModelOut,
        deriv: bool,
    ) -> f64 {
        m.eval(d, th, out, deriv);
        refr.r.fill(0.0);
        m.eval_complex(d, th, refr, false);
        (0..m.n_bands)
            .map(|k| (out.r[k] - refr.r[k]).abs())
            .fold(0.0, f64::max)
    }

    /// The paper's film (1.37 on 1.6 in air) on `bands`, each band
    /// integrated over its passband where `integrate`.
    fn paper_film(bands: &[Band], pol: Polarization, integrate: bool) -> FilmModel {
        FilmModel::new(
            bands,
            &Dispersion::constant(1.0),
            &Dispersion::constant(1.37),
            &Dispersion::constant(1.6),
            pol,
            &vec![integrate; bands.len()],
        )
        .unwrap()
    }

    #[test]
    fn real_path_matches_complex_airy_and_derivative_matches_difference() {
        for pol in [Polarization::S, Polarization::P, Polarization::Unpolarized] {
            let m = paper_film(&bands(), pol, false);
            let mut out = ModelOut::new(31);
            let mut out2 = ModelOut::new(31);
            let (d, th) = (487.0, 0.5);
            m.eval(d, th, &mut out, true);
            m.eval_complex(d, th, &mut out2, false);
            for k in 0..31 {
                assert!((out.r[k] - out2.r[k]).abs() < 1e-13);
            }
            m.eval(d + 1e-4, th, &mut out2, false);
            for k in 0..31 {
                let fd = (out2.r[k] - out.r[k]) / 1e-4;
                assert!((fd - out.dr_dd[k]).abs() < 1e-6, "{fd} {}", out.dr_dd[k]);
            }
            // Central difference in θ: error O(h²) ~ 1e-8 · R''' .
            m.eval(d, th + 1e-4, &mut out2, false);
            let mut lo = ModelOut::new(31);
            m.eval(d, th - 1e-4, &mut lo, false);
            for k in 0..31 {
                let fd = (out2.r[k] - lo.r[k]) / 2e-4;
                assert!((fd - out.dr_dth[k]).abs() < 1e-5, "{fd} {}", out.dr_dth[k]);
            }
        }
    }

    /// Uniform lossless media with integrated passbands take the real
    /// path node by node (not the general complex one, ~10× slower), and
    /// it agrees with the complex Airy sum.
    #[test]
    fn integrated_uniform_media_take_the_real_path() {
        let mut wide = bands();
        for b in &mut wide {
            b.fwhm_nm = 10.0;
        }
        for pol in [Polarization::S, Polarization::P, Polarization::Unpolarized] {
            let m = paper_film(&wide, pol, true);
            assert_eq!(m.nodes.len(), 9 * 31);
            assert_eq!(m.real_nodes.len(), m.nodes.len(), "the real path applies");
            let (mut out, mut refr) = (ModelOut::new(31), ModelOut::new(31));
            for (d, deg) in [(87.0, 0.0), (487.0, 12.5), (1312.0, 45.0), (3001.0, 80.0)] {
                let th = f64::to_radians(deg);
                let worst = worst_against_airy(&m, d, th, &mut out, &mut refr, false);
                // The f32 lanes' budget where they apply (`real32`).
                assert!(worst < 1e-5, "{pol:?} {d} nm at {deg}°: {worst}");
            }
        }
    }

    /// The real dispersive path against the complex Airy sum (a second
    /// formulation): dispersive film and substrate, each polarisation,
    /// point-sampled and integrated passbands, from normal incidence to
    /// near the film's critical angle; dR/dd and dR/dθ against central
    /// differences of the Airy sum.
    #[test]
    fn real_dispersive_path_matches_the_airy_sum() {
        // λ in µm: n_film 1.475 → 1.467, n_sub 1.656 → 1.605 over the band.
        let film = Dispersion::cauchy(1.46, 0.0036, 0.0, 0.0).unwrap();
        let sub = Dispersion::cauchy(1.58, 0.0090, 1e-3, 0.0).unwrap();
        let mut wide = bands();
        for b in &mut wide {
            b.fwhm_nm = 12.0;
        }
        for (bs, integrate) in [(bands(), false), (wide, true)] {
            for pol in [Polarization::S, Polarization::P, Polarization::Unpolarized] {
                let m = FilmModel::new(
                    &bs,
                    &Dispersion::constant(1.0),
                    &film,
                    &sub,
                    pol,
                    &[integrate; 31],
                )
                .unwrap();
                assert_eq!(m.real_nodes.len(), m.nodes.len(), "the real path applies");
                // The f64 kernel alone (its f32 lanes taken away), then the
                // model as it runs: f32 lanes where they apply, within
                // their error budget (`real32`: |ΔR| ≲ 1e-5; here, at
                // phases up to ~140 rad, 1e-6).
                let mut m64 = m.clone();
                m64.real_nodes32 = RealNodes32::default();
                for (m, tol) in [(&m64, 1e-13), (&m, 1e-6)] {
                    let mut out = ModelOut::new(31);
                    let (mut refr, mut hi, mut lo) =
                        (ModelOut::new(31), ModelOut::new(31), ModelOut::new(31));
                    for (d, deg) in [(87.0, 0.0), (487.0, 12.5), (1312.0, 45.0), (3001.0, 80.0)] {
                        let th = f64::to_radians(deg);
                        assert_eq!(
                            m.real_nodes32.applies(d, th.sin()),
                            tol > 1e-13,
                            "{d} nm at {deg}°: the f32 lanes apply in the model as it runs"
                        );
                        let worst = worst_against_airy(m, d, th, &mut out, &mut refr, true);
                        assert!(worst < tol, "{deg}°: {worst}");
                        let (e_d, e_t) = (1e-4, 1e-5);
                        for (step, analytic, scale) in [
                            ((e_d, 0.0), &out.dr_dd, 1e-7),
                            ((0.0, e_t), &out.dr_dth, 1e-6),
                        ] {
                            hi.r.fill(0.0);
                            lo.r.fill(0.0);
                            m.eval_complex(d + step.0, th + step.1, &mut hi, false);
                            m.eval_complex(d - step.0, (th - step.1).abs(), &mut lo, false);
                            let h = 2.0 * (step.0 + step.1);
                            for (k, &an) in analytic.iter().enumerate().take(31) {
                                let fd = (hi.r[k] - lo.r[k]) / h;
                                assert!(
                                    (fd - an).abs() < scale * (1.0 + fd.abs()) * 10.0,
                                    "{pol:?} {deg}° band {k}: {fd} vs {an}"
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    /// At the edge of the `f32` lanes' range (a phase of ~390 rad at the
    /// bluest node, a few µm of film) they stay within their error budget
    /// of the complex Airy sum (|ΔR| ≲ 1e-5, `real32`), and just past it
    /// the `f64` kernel takes over.
    #[test]
    fn the_f32_lanes_hold_their_budget_to_the_edge_of_their_range() {
        let film = Dispersion::cauchy(1.46, 0.0036, 0.0, 0.0).unwrap();
        let sub = Dispersion::cauchy(1.58, 0.0090, 1e-3, 0.0).unwrap();
        let pol = Polarization::Unpolarized;
        let m = FilmModel::new(
            &bands(),
            &Dispersion::constant(1.0),
            &film,
            &sub,
            pol,
            &[false; 31],
        )
        .unwrap();
        let edge = real32::MAX_PHASE / m.real_nodes32.phase_rate();
        let (mut out, mut refr) = (ModelOut::new(31), ModelOut::new(31));
        for (d, deg) in [(0.97 * edge, 0.0), (0.97 * edge, 60.0), (0.9 * edge, 79.0)] {
            let th = f64::to_radians(deg);
            assert!(m.real_nodes32.applies(d, th.sin()), "{d} nm at {deg}°");
            m.eval(d, th, &mut out, false);
            refr.r.fill(0.0); // the complex sum adds into its output
            m.eval_complex(d, th, &mut refr, false);
            let worst = (0..31)
                .map(|k| (out.r[k] - refr.r[k]).abs())
                .fold(0.0, f64::max);
            // Measured 4–7e-7, inside the budget of 1e-5 (which allows
            // for `q2`'s worst rounding at 400 rad).
            assert!(worst < 2e-6, "{d} nm at {deg}°: {worst}");
        }
        assert!(!m.real_nodes32.applies(1.01 * edge, 0.0));
        assert!(!m
            .real_nodes32
            .applies(0.5 * edge, f64::to_radians(81.0).sin()));
    }

    /// A substrate that barely absorbs (a polymer web, k ~ 1e-6) is taken
    /// as lossless — the real path, within 1e-6 of the complex Airy sum
    /// with its absorption — and one that absorbs (k = 0.01) is not.
    #[test]
    fn a_barely_absorbing_substrate_takes_the_real_path() {
        let film = Dispersion::cauchy(1.46, 0.0036, 0.0, 0.0).unwrap();
        for (k, real) in [(2e-6, true), (0.01, false)] {
            let sub = Dispersion::cauchy(1.58, 0.0090, 1e-3, k).unwrap();
            let m = FilmModel::new(
                &bands(),
                &Dispersion::constant(1.0),
                &film,
                &sub,
                Polarization::Unpolarized,
                &[false; 31],
            )
            .unwrap();
            assert_eq!(m.real, real, "k = {k}");
            let mut out = ModelOut::new(31);
            for (d, deg) in [(150.0, 5.0), (777.0, 45.0), (4000.0, 75.0)] {
                let th = f64::to_radians(deg);
                m.eval(d, th, &mut out, false);
                for (kb, band) in bands().iter().enumerate() {
                    let media = Media {
                        n1: Complex64::new(1.0, 0.0),
                        n2: film.index_at(band.center_nm).unwrap(),
                        n3: sub.index_at(band.center_nm).unwrap(),
                    };
                    let exact =
                        airy::reflectance(media, d, th, band.center_nm, Polarization::Unpolarized);
                    let tol = if real { LOSSLESS_TOL / 2.0 } else { 1e-8 };
                    assert!(
                        (out.r[kb] - exact).abs() < tol,
                        "k {k} {deg}°: {} vs {exact}",
                        out.r[kb]
                    );
                }
            }
        }
    }

    /// Once the general path's angle grid is in use, its interpolated
    /// coefficients give the complex Airy sum's reflectance (a second
    /// formulation) to 1e-8 — four orders below the lowest noise level
    /// irid accepts (1e-4) — and the angle derivative to the central
    /// difference of it.
    #[test]
    fn interpolated_angle_grid_matches_the_airy_sum() {
        let m = FilmModel::new(
            &bands(),
            &Dispersion::constant(1.0),
            &Dispersion::constant_nk(2.1, 0.01).unwrap(),
            &Dispersion::constant_nk(1.57, 0.002).unwrap(),
            Polarization::Unpolarized,
            &[false; 31],
        )
        .unwrap();
        let mut out = ModelOut::new(31);
        // Enough distinct angles for the grid to be built.
        for i in 0..400 {
            m.eval(300.0, 0.001 + i as f64 * 1e-3, &mut out, false);
        }
        assert!(m.grid.get().is_some(), "the grid is built once it pays");
        let mut reference = ModelOut::new(31);
        let mut lo = ModelOut::new(31);
        for deg in [0.3, 7.77, 33.3, 61.1, 80.05] {
            let th = f64::to_radians(deg);
            m.eval(812.0, th, &mut out, true);
            reference.r.fill(0.0);
            m.eval_complex(812.0, th, &mut reference, false);
            for k in 0..31 {
                assert!(
                    (out.r[k] - reference.r[k]).abs() < 1e-8,
                    "{deg}: {} vs {}",
                    out.r[k],
                    reference.r[k]
                );
            }
            let e = 1e-5;
            reference.r.fill(0.0);
            lo.r.fill(0.0);
            m.eval_complex(812.0, th + e, &mut reference, false);
            m.eval_complex(812.0, th - e, &mut lo, false);
            for k in 0..31 {
                let fd = (reference.r[k] - lo.r[k]) / (2.0 * e);
                assert!(
                    (fd - out.dr_dth[k]).abs() < 1e-4 * (1.0 + fd.abs()),
                    "{deg}: {fd} vs {}",
                    out.dr_dth[k]
                );
            }
        }
    }
}
