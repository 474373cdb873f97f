//! The instrument's level: what stands between the calibrated data and the
//! film's reflectance, modelled only where the data need it.
//!
//! - `absolute`: the calibration is trusted, `y = R`.
//! - `scaled`: the whole image shares an unknown gain and offset per band,
//!   `y_k = g_k·R_k + o_k` (a white reference a few percent off, lamp drift,
//!   stray light). They are estimated once, with the film index, from a
//!   sample of pixels: Gauss–Newton on the joint problem, the pixels' own
//!   parameters eliminated by the Schur complement, so the gain is never
//!   confused with what a pixel's thickness or angle explains. Only the
//!   parameters the data need are fitted ([`LevelBasis`]): one gain or one
//!   offset, else both, else a gain quadratic in wavenumber and one offset;
//!   a gain per band, and then an offset per band too, only where they do
//!   significantly better and the sample spreads every band's reflectance
//!   enough to tell them from the pixels' parameters. Every parameter more
//!   trades with each pixel's angle and the index and costs precision
//!   (`tools/level_crb.py` gives the bound under each). Their covariance
//!   enters every pixel's σ.
//! - `free`: every pixel has its own scale, offset and slow envelope (see
//!   the solver's free-level path): for normalised or uncalibrated
//!   intensities.
//! - `auto`: `absolute` unless the sample shows a correctable, systematic
//!   misfit: a likelihood-ratio test of `scaled` against `absolute` at
//!   [`AUTO_PROBABILITY`].

#![allow(clippy::needless_range_loop)] // band-indexed numeric loops read clearer with indices

/// How the level is modelled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum LevelMode {
    /// `absolute` unless the data show a correctable calibration error.
    Auto,
    /// Calibrated reflectance, trusted.
    Absolute,
    /// An image-wide gain and offset per band, estimated.
    Scaled,
    /// A scale, offset and slow envelope per pixel (normalised intensities).
    Free,
}

impl LevelMode {
    /// Name as on the command line.
    pub fn name(self) -> &'static str {
        match self {
            LevelMode::Auto => "auto",
            LevelMode::Absolute => "absolute",
            LevelMode::Scaled => "scaled",
            LevelMode::Free => "free",
        }
    }

    /// From a name.
    pub fn from_name(s: &str) -> Option<LevelMode> {
        match s {
            "auto" => Some(LevelMode::Auto),
            "absolute" => Some(LevelMode::Absolute),
            "scaled" => Some(LevelMode::Scaled),
            "free" => Some(LevelMode::Free),
            _ => None,
        }
    }
}

/// Upper-tail probability of the likelihood-ratio test with which `auto`
/// switches to `scaled`: clean data switch about once in 10 000 images (a
/// needless switch costs precision, since a level trades with each pixel's
/// angle and the film index).
pub const AUTO_PROBABILITY: f64 = 1e-4;

/// Prior σ of a band's gain about 1 and of its offset about 0 (weak: they
/// only keep an unidentifiable direction finite; a stronger prior would
/// pull a real gain error toward 1 where the data tell it only together
/// with the angle and the index).
pub const GAIN_PRIOR_SIGMA: f64 = 0.5;
/// See [`GAIN_PRIOR_SIGMA`].
pub const OFFSET_PRIOR_SIGMA: f64 = 0.2;

/// Largest gain error `scaled` corrects: beyond it the data are not a
/// miscalibrated reflectance but something else (normalised intensities,
/// raw counts), and correcting them would invent a film; they are flagged
/// instead (or fitted with the free level when asked).
pub const MAX_GAIN_ERROR: f64 = 0.3;
/// Largest offset `scaled` corrects (see [`MAX_GAIN_ERROR`]).
pub const MAX_OFFSET: f64 = 0.05;

/// Largest mean gain error `auto` takes for a calibration error. A white
/// reference, lamp drift or a reference tile's own table is off by a few
/// percent (the cases: 5 % high, 8 % low, ±6 % per band); 15 % is
/// twice the largest. A larger level is a model error it would absorb: on
/// the paper's cylinder a film index given 1.5 % off (1.37 for 1.39, the
/// angle free) took a gain of 0.754 and an offset per band, and every
/// pixel came out valid and 34 nm off. `auto` flags such an image instead;
/// `scaled`, asked for, still corrects up to [`MAX_GAIN_ERROR`].
pub const MAX_AUTO_GAIN_ERROR: f64 = 0.15;

/// An image-wide level: `y_k = gain[k]·R_k + offset[k]`, with covariances.
#[derive(Clone, Debug, PartialEq)]
pub struct Level {
    /// Gain per band (cube plane order).
    pub gain: Vec<f64>,
    /// Offset per band.
    pub offset: Vec<f64>,
    /// Variance of each gain.
    pub var_gain: Vec<f64>,
    /// Variance of each offset.
    pub var_offset: Vec<f64>,
    /// Covariance of each band's gain and offset.
    pub cov: Vec<f64>,
    /// The level's parametrisation and joint covariance, which carry its
    /// uncertainty into each pixel's σ ([`LevelShare::var_of`]).
    pub share: LevelShare,
}

/// What a pixel needs to carry the image-wide level's uncertainty into its
/// own σ: how each band's gain and offset follow the level's parameters,
/// and their covariance joint with the global parameters estimated with
/// them (the film index where unknown).
///
/// A pixel's thickness and angle respond to those parameters through its
/// own fit, `∂(d, θ)/∂γ = A⁻¹B` (its normal matrix A, its coupling B to the
/// parameters), so their variance from the level is `tᵀ Σ t`. The response
/// differs from pixel to pixel — a gain error common to all bands moves
/// one thickness far less than another, and far less than independent
/// band errors of its size would — so no one factor stands for it: on the
/// paper's cylinder a factor set by the sample's median left the rows at
/// large angles, whose own σ is smallest, 2.8 of their σ off where the
/// gain was 2.1 of its σ off.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LevelShare {
    /// Per band, per level parameter: (∂g_k/∂γ_j, ∂o_k/∂γ_j), `nb × m_level`.
    rows: Vec<(f64, f64)>,
    /// The level's own parameters.
    m_level: usize,
    /// Joint covariance of the level's parameters and the global ones
    /// (`m × m`, level first).
    cov: Vec<f64>,
    /// All parameters: the level's, then the global ones.
    m: usize,
    /// The band weights (1/σ²) the level was fitted with.
    w: Vec<f64>,
}

impl LevelShare {
    /// Whether there is a share to carry (a fitted level).
    pub fn is_empty(&self) -> bool {
        self.m == 0
    }

    /// The number of parameters: the level's and the global ones.
    pub fn n_params(&self) -> usize {
        self.m
    }

    /// Entry `(j, l)` of the joint covariance (NaN outside it).
    pub fn cov_entry(&self, j: usize, l: usize) -> f64 {
        if j < self.m && l < self.m && self.cov.len() == self.m * self.m {
            self.cov[j * self.m + l]
        } else {
            f64::NAN
        }
    }

    /// The band weights (1/σ²) the level was fitted with.
    pub fn weights(&self) -> &[f64] {
        &self.w
    }

    /// The number of global parameters beyond the level (whose per-band
    /// derivatives [`LevelShare::var_of`] takes in `extra`).
    pub fn n_extra(&self) -> usize {
        self.m - self.m_level
    }

    /// The variance the level adds to a pixel's thickness and angle, from
    /// its values `y` (non-finite: band not used), the level's gains, the
    /// model `r` at its fit, the model's derivatives with respect to
    /// thickness and (where estimated) angle, and the derivatives of the
    /// measured values with respect to each global parameter. Zero where
    /// the pixel's own normal matrix is singular or the inputs do not
    /// match the level. `work` is working memory (no allocation once it
    /// has grown to the level's parameters); it is left holding the
    /// responses `t` (see [`LevelShare::quad`]), or empty.
    #[allow(clippy::too_many_arguments)]
    pub fn var_of(
        &self,
        y: &[f64],
        gain: &[f64],
        r: &[f64],
        dr_dd: &[f64],
        dr_dth: Option<&[f64]>,
        extra: &[&[f64]],
        work: &mut Vec<[f64; 2]>,
    ) -> (f64, f64) {
        let nb = self.w.len();
        let (m, ml) = (self.m, self.m_level);
        if m == 0
            || extra.len() != m - ml
            || [y.len(), gain.len(), r.len(), dr_dd.len()]
                .iter()
                .any(|&l| l < nb)
            || dr_dth.is_some_and(|j| j.len() < nb)
            || extra.iter().any(|e| e.len() < nb)
            || self.rows.len() != nb * ml
            || self.cov.len() != m * m
        {
            work.clear();
            return (0.0, 0.0);
        }
        let mut a = [[0.0f64; 2]; 2];
        // B (m × 2), then t = A⁻¹B in its place.
        work.clear();
        work.resize(m, [0.0; 2]);
        let b = &mut work[..];
        for k in (0..nb).filter(|&k| y[k].is_finite() && r[k].is_finite()) {
            let w = self.w[k];
            let jl = [gain[k] * dr_dd[k], dr_dth.map_or(0.0, |j| gain[k] * j[k])];
            for i in 0..2 {
                for l in 0..2 {
                    a[i][l] += w * jl[i] * jl[l];
                }
            }
            for (j, bj) in b.iter_mut().enumerate() {
                let kv = if j < ml {
                    let (dg, doff) = self.rows[k * ml + j];
                    r[k] * dg + doff
                } else {
                    extra[j - ml][k]
                };
                if kv != 0.0 {
                    bj[0] += w * jl[0] * kv;
                    bj[1] += w * jl[1] * kv;
                }
            }
        }
        // A⁻¹ (the angle's row only where it is estimated).
        let Some(ainv) = local_inverse(a, dr_dth.is_some(), 0.0) else {
            work.clear();
            return (0.0, 0.0);
        };
        for bj in b.iter_mut() {
            *bj = times(&ainv, *bj);
        }
        self.quad(b)
    }

    /// `tᵀΣt` for the thickness and the angle, from their responses `t`
    /// to each parameter (as `work` holds them after
    /// [`LevelShare::var_of`]); zero where `t` does not match the level.
    pub fn quad(&self, t: &[[f64; 2]]) -> (f64, f64) {
        let m = self.m;
        if t.len() != m || self.cov.len() != m * m {
            return (0.0, 0.0);
        }
        let (mut vd, mut vt) = (0.0, 0.0);
        for j in 0..m {
            for l in 0..m {
                let c = self.cov[j * m + l];
                vd += t[j][0] * c * t[l][0];
                vt += t[j][1] * c * t[l][1];
            }
        }
        (vd.max(0.0), vt.max(0.0))
    }
}

/// The inverse of a pixel's local normal matrix `a` (symmetric), over its
/// thickness and, where `two`, its angle (else the angle's row and column
/// are zero), each diagonal raised by `ridge`; `None` where singular.
pub(crate) fn local_inverse(a: [[f64; 2]; 2], two: bool, ridge: f64) -> Option<[[f64; 2]; 2]> {
    let (p, q, r) = (a[0][0] + ridge, a[0][1], a[1][1] + ridge);
    if !two {
        return (p > 0.0).then(|| [[1.0 / p, 0.0], [0.0, 0.0]]);
    }
    let det = p * r - q * q;
    (det > 0.0).then(|| [[r / det, -q / det], [-q / det, p / det]])
}

/// `m·v` for a 2 × 2 matrix.
pub(crate) fn times(m: &[[f64; 2]; 2], v: [f64; 2]) -> [f64; 2] {
    [
        m[0][0] * v[0] + m[0][1] * v[1],
        m[1][0] * v[0] + m[1][1] * v[1],
    ]
}

impl Level {
    /// The identity level (absolute reflectance).
    pub fn identity(n_bands: usize) -> Level {
        Level {
            gain: vec![1.0; n_bands],
            offset: vec![0.0; n_bands],
            var_gain: vec![0.0; n_bands],
            var_offset: vec![0.0; n_bands],
            cov: vec![0.0; n_bands],
            share: LevelShare::default(),
        }
    }

    /// One gain and one offset for every band, `y_k = gain·R_k + offset`,
    /// with `cov` the joint covariance of (gain, offset) and `n_extra`
    /// global parameters after them (`(2 + n_extra)²`, row-major), fitted
    /// with band weights `w` (1/σ²).
    pub fn gain_offset(
        gain: f64,
        offset: f64,
        cov: Vec<f64>,
        n_extra: usize,
        w: Vec<f64>,
    ) -> Level {
        let nb = w.len();
        let m = 2 + n_extra;
        assert_eq!(
            cov.len(),
            m * m,
            "a covariance over the gain, the offset and the extras"
        );
        let mut out = Level::identity(nb);
        out.gain.fill(gain);
        out.offset.fill(offset);
        out.var_gain.fill(cov[0]);
        out.var_offset.fill(cov[m + 1]);
        out.cov.fill(cov[1]);
        out.share = LevelShare {
            rows: (0..nb).flat_map(|_| [(1.0, 0.0), (0.0, 1.0)]).collect(),
            m_level: 2,
            cov,
            m,
            w,
        };
        out
    }

    /// Whether this is the identity with no uncertainty.
    pub fn is_identity(&self) -> bool {
        self.gain.iter().all(|&g| g == 1.0)
            && self.offset.iter().all(|&o| o == 0.0)
            && self.var_gain.iter().all(|&v| v == 0.0)
            && self.var_offset.iter().all(|&v| v == 0.0)
    }

    /// Reflectance from a measured value of band `k`.
    #[inline]
    pub fn correct(&self, k: usize, y: f64) -> f64 {
        (y - self.offset[k]) / self.gain[k]
    }

    /// Whether the level is a plausible calibration error (within
    /// [`MAX_GAIN_ERROR`] and [`MAX_OFFSET`] on every band).
    pub fn is_plausible(&self) -> bool {
        self.gain.iter().all(|g| (g - 1.0).abs() <= MAX_GAIN_ERROR)
            && self.offset.iter().all(|o| o.abs() <= MAX_OFFSET)
    }

    /// The level's value at reflectance `r` averaged over the bands
    /// `ks`, `mean(g_k·r + o_k)`, and its variance from the level's joint
    /// covariance (NaN without one): a linear functional of the level's
    /// parameters, so two levels fitted on disjoint samples can be
    /// compared through it.
    pub fn mean_at(&self, ks: std::ops::Range<usize>, r: f64) -> (f64, f64) {
        let ks = ks.start.min(self.gain.len())..ks.end.min(self.gain.len());
        let n = ks.len().max(1) as f64;
        let value = ks
            .clone()
            .map(|k| self.gain[k] * r + self.offset[k])
            .sum::<f64>()
            / n;
        let sh = &self.share;
        let (m, ml) = (sh.m, sh.m_level);
        if m == 0 || sh.rows.len() < self.gain.len() * ml || sh.cov.len() != m * m {
            return (value, f64::NAN);
        }
        let u: Vec<f64> = (0..ml)
            .map(|j| {
                ks.clone()
                    .map(|k| {
                        let (dg, doff) = sh.rows[k * ml + j];
                        dg * r + doff
                    })
                    .sum::<f64>()
                    / n
            })
            .collect();
        let mut var = 0.0;
        for j in 0..ml {
            for l in 0..ml {
                var += u[j] * u[l] * sh.cov[j * m + l];
            }
        }
        (value, var)
    }

    /// The mean gain and offset over bands (for summaries).
    pub fn mean(&self) -> (f64, f64) {
        let n = self.gain.len().max(1) as f64;
        (
            self.gain.iter().sum::<f64>() / n,
            self.offset.iter().sum::<f64>() / n,
        )
    }
}

/// How the level's free parameters map onto per-band gains and offsets.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LevelBasis {
    /// A gain and an offset per band (`2·bands` parameters).
    PerBand,
    /// A gain per band, no offset (`bands` parameters): a white reference
    /// whose spectrum is off band by band.
    PerBandGain,
    /// Gain quadratic in wavenumber, one offset (4 parameters).
    Smooth,
    /// One gain and one offset for every band (2 parameters).
    GainOffset,
    /// One gain for every band (1 parameter): a white reference off.
    Gain,
    /// One offset for every band (1 parameter): stray light, a dark frame
    /// off.
    Offset,
}

impl LevelBasis {
    /// Number of free parameters for `nb` bands.
    pub fn n_params(self, nb: usize) -> usize {
        match self {
            LevelBasis::PerBand => 2 * nb,
            LevelBasis::PerBandGain => nb,
            LevelBasis::Smooth => 4,
            LevelBasis::GainOffset => 2,
            LevelBasis::Gain | LevelBasis::Offset => 1,
        }
    }

    /// `∂(gain_k, offset_k)/∂γ_j` for band `k` at normalised wavenumber `u`
    /// (in [−1, 1]): the two rows, as a closure over `j`.
    fn rows(self, k: usize, u: f64, j: usize) -> (f64, f64) {
        match self {
            LevelBasis::PerBand => (
                if j == 2 * k { 1.0 } else { 0.0 },
                if j == 2 * k + 1 { 1.0 } else { 0.0 },
            ),
            LevelBasis::PerBandGain => (if j == k { 1.0 } else { 0.0 }, 0.0),
            LevelBasis::Smooth => match j {
                0 => (1.0, 0.0),
                1 => (u, 0.0),
                2 => (u * u, 0.0),
                _ => (0.0, 1.0),
            },
            LevelBasis::GainOffset => match j {
                0 => (1.0, 0.0),
                _ => (0.0, 1.0),
            },
            LevelBasis::Gain => (1.0, 0.0),
            LevelBasis::Offset => (0.0, 1.0),
        }
    }
}

/// One sample pixel as the level fit sees it: raw values, the model at the
/// pixel's current parameters and its derivatives with respect to them.
#[derive(Clone, Debug, Default)]
pub struct LevelPixel {
    /// Measured values per band (NaN: missing).
    pub y: Vec<f64>,
    /// Model reflectance per band.
    pub r: Vec<f64>,
    /// Derivatives of the model per band, one vector per local parameter
    /// (thickness, and the angle when it is estimated).
    pub jac: Vec<Vec<f64>>,
    /// Derivatives of the measured value per band with respect to global
    /// parameters other than the level (the film index where unknown),
    /// estimated jointly with it.
    pub extra: Vec<Vec<f64>>,
    /// The caller's id of the pixel and its fitted thickness and σ (not
    /// used by the step; they tell what a level changes).
    pub id: usize,
    /// See [`LevelPixel::id`].
    pub d: f64,
    /// See [`LevelPixel::id`].
    pub sigma_d: f64,
    /// The fitted angle, radians (see [`LevelPixel::id`]).
    pub theta: f64,
}

/// Result of one Gauss–Newton step of the level.
#[derive(Clone, Debug)]
pub struct LevelStep {
    /// The updated level (with its covariance).
    pub level: Level,
    /// Largest change of a gain or offset in this step.
    pub change: f64,
    /// χ² of the sample at the level before the step.
    pub chi2: f64,
    /// Observations used.
    pub n_obs: usize,
    /// Steps of the extra global parameters.
    pub extra_step: Vec<f64>,
    /// Their variances.
    pub extra_var: Vec<f64>,
    /// Their covariance (`n_extra × n_extra`, row-major).
    pub extra_cov: Vec<f64>,
}

/// One Gauss–Newton step for the level from the sample's current fits,
/// the pixels' own parameters eliminated (Schur complement). `wavenumber`
/// holds each band's 1/λ; `var[k]` the noise variance of band `k`.
pub fn level_step(
    pixels: &[LevelPixel],
    level: &Level,
    basis: LevelBasis,
    wavenumber: &[f64],
    var: &[f64],
) -> Option<LevelStep> {
    let nb = level.gain.len();
    let m_level = basis.n_params(nb);
    let n_extra = pixels.first().map_or(0, |p| p.extra.len());
    let m = m_level + n_extra;
    let (s_lo, s_hi) = wavenumber
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &s| {
            (a.min(s), b.max(s))
        });
    let half = 0.5 * (s_hi - s_lo).max(1e-12);
    let u: Vec<f64> = wavenumber.iter().map(|s| (s - s_lo) / half - 1.0).collect();
    // Per band: the dense rows of ∂(g_k, o_k)/∂γ.
    let drow: Vec<Vec<(f64, f64)>> = (0..nb)
        .map(|k| {
            (0..m)
                .map(|j| {
                    if j < m_level {
                        basis.rows(k, u[k], j)
                    } else {
                        (0.0, 0.0)
                    }
                })
                .collect()
        })
        .collect();
    let mut s = vec![0.0; m * m];
    let mut rhs = vec![0.0; m];
    let mut chi2 = 0.0;
    let mut n_obs = 0;
    // K_p (nb × m): ∂y_k/∂γ_j = R_k·∂g_k/∂γ_j + ∂o_k/∂γ_j.
    let mut kmat = vec![0.0; nb * m];
    for px in pixels {
        let nl = px.jac.len();
        if nl == 0 || px.y.len() != nb || px.r.len() != nb || px.extra.len() != n_extra {
            continue;
        }
        // Local normal equations A (nl×nl), coupling B (nl×m), gradients.
        let mut a = [[0.0f64; 2]; 2];
        let mut b = vec![[0.0f64; 2]; m];
        let mut al = [0.0f64; 2];
        for k in 0..nb {
            let (y, r) = (px.y[k], px.r[k]);
            if !(y.is_finite() && r.is_finite()) {
                for j in 0..m {
                    kmat[k * m + j] = 0.0;
                }
                continue;
            }
            let w = 1.0 / var[k];
            let g = level.gain[k];
            let e = y - g * r - level.offset[k];
            chi2 += w * e * e;
            n_obs += 1;
            let jl = [
                g * px.jac[0][k],
                if nl > 1 { g * px.jac[1][k] } else { 0.0 },
            ];
            for i in 0..nl {
                al[i] += w * jl[i] * e;
                for l in 0..nl {
                    a[i][l] += w * jl[i] * jl[l];
                }
            }
            for j in 0..m {
                let (dg, doff) = drow[k][j];
                let kv = if j < m_level {
                    r * dg + doff
                } else {
                    px.extra[j - m_level][k]
                };
                kmat[k * m + j] = kv;
                if kv != 0.0 {
                    rhs[j] += w * kv * e;
                    for i in 0..nl {
                        b[j][i] += w * jl[i] * kv;
                    }
                }
            }
            // C += Kᵀ W K, only the non-zero entries of this band's row.
            for j in 0..m {
                let kj = kmat[k * m + j];
                if kj == 0.0 {
                    continue;
                }
                for l in 0..m {
                    let kl = kmat[k * m + l];
                    if kl != 0.0 {
                        s[j * m + l] += w * kj * kl;
                    }
                }
            }
        }
        // Eliminate the pixel: S −= Bᵀ A⁻¹ B, rhs −= Bᵀ A⁻¹ a.
        let Some(ainv) = local_inverse(a, nl == 2, 1e-12) else {
            continue;
        };
        let t: Vec<[f64; 2]> = b.iter().map(|bj| times(&ainv, *bj)).collect();
        for j in 0..m {
            if b[j] == [0.0, 0.0] {
                continue;
            }
            rhs[j] -= t[j][0] * al[0] + t[j][1] * al[1];
            for l in 0..m {
                s[j * m + l] -= t[j][0] * b[l][0] + t[j][1] * b[l][1];
            }
        }
    }
    if n_obs == 0 {
        return None;
    }
    // Weak priors toward the identity keep unidentifiable directions finite.
    let mut gamma = params_of(level, basis, &u);
    // The extra parameters are stepped from where they are (a ridge, no pull).
    gamma.resize(m, 0.0);
    for j in 0..m {
        let (dg, doff) = drow.iter().map(|r| r[j]).fold((0.0f64, 0.0f64), |a, v| {
            (a.0.max(v.0.abs()), a.1.max(v.1.abs()))
        });
        let ps = if dg > 0.0 {
            GAIN_PRIOR_SIGMA
        } else if doff > 0.0 {
            OFFSET_PRIOR_SIGMA
        } else {
            1.0
        };
        let p = 1.0 / (ps * ps);
        s[j * m + j] += p;
        rhs[j] -= p * gamma[j];
    }
    let l = cholesky(&s, m)?;
    let delta = chol_solve(&l, m, &rhs);
    let inv = chol_inverse(&l, m);
    let new_gamma: Vec<f64> = gamma.iter().zip(&delta).map(|(g, d)| g + d).collect();
    let mut out = Level::identity(nb);
    let mut change: f64 = 0.0;
    for k in 0..nb {
        let (mut g, mut o) = (1.0, 0.0);
        let (mut vg, mut vo, mut c) = (0.0, 0.0, 0.0);
        for j in 0..m {
            let (dgj, doj) = drow[k][j];
            g += dgj * new_gamma[j];
            o += doj * new_gamma[j];
            for l2 in 0..m {
                let (dgl, dol) = drow[k][l2];
                let v = inv[j * m + l2];
                vg += dgj * dgl * v;
                vo += doj * dol * v;
                c += dgj * dol * v;
            }
        }
        change = change
            .max((g - level.gain[k]).abs())
            .max((o - level.offset[k]).abs());
        out.gain[k] = g;
        out.offset[k] = o;
        out.var_gain[k] = vg;
        out.var_offset[k] = vo;
        out.cov[k] = c;
    }
    out.share = LevelShare {
        rows: (0..nb)
            .flat_map(|k| drow[k][..m_level].iter().copied())
            .collect(),
        m_level,
        cov: inv.clone(),
        m,
        w: var.iter().map(|v| 1.0 / v).collect(),
    };
    Some(LevelStep {
        level: out,
        change,
        chi2,
        n_obs,
        extra_step: delta[m_level..].to_vec(),
        extra_var: (m_level..m).map(|j| inv[j * m + j]).collect(),
        extra_cov: (m_level..m)
            .flat_map(|j| (m_level..m).map(move |l| (j, l)))
            .map(|(j, l)| inv[j * m + l])
            .collect(),
    })
}

/// The basis parameters of a level (gain − 1 and offset in the basis's
/// terms): per band exactly; smooth by least squares.
fn params_of(level: &Level, basis: LevelBasis, u: &[f64]) -> Vec<f64> {
    match basis {
        LevelBasis::PerBand => level
            .gain
            .iter()
            .zip(&level.offset)
            .flat_map(|(g, o)| [g - 1.0, *o])
            .collect(),
        LevelBasis::PerBandGain => level.gain.iter().map(|g| g - 1.0).collect(),
        LevelBasis::Smooth => {
            // Gain − 1 ≈ c0 + c1 u + c2 u²; offset = mean.
            let mut m = [[0.0; 3]; 3];
            let mut v = [0.0; 3];
            for (k, &uk) in u.iter().enumerate() {
                let f = [1.0, uk, uk * uk];
                for i in 0..3 {
                    v[i] += f[i] * (level.gain[k] - 1.0);
                    for j in 0..3 {
                        m[i][j] += f[i] * f[j];
                    }
                }
            }
            let flat: Vec<f64> = m.iter().flatten().copied().collect();
            let c = cholesky(&flat, 3)
                .map(|l| chol_solve(&l, 3, &v))
                .unwrap_or_else(|| vec![0.0; 3]);
            let o = level.offset.iter().sum::<f64>() / level.offset.len().max(1) as f64;
            vec![c[0], c[1], c[2], o]
        }
        LevelBasis::GainOffset | LevelBasis::Gain | LevelBasis::Offset => {
            let n = level.gain.len().max(1) as f64;
            let g = level.gain.iter().sum::<f64>() / n - 1.0;
            let o = level.offset.iter().sum::<f64>() / n;
            match basis {
                LevelBasis::Gain => vec![g],
                LevelBasis::Offset => vec![o],
                _ => vec![g, o],
            }
        }
    }
}

/// Solve the symmetric positive definite system `a x = b` (`n × n`,
/// row-major); `None` if `a` is not positive definite.
pub(crate) fn solve_spd(a: &[f64], n: usize, b: &[f64]) -> Option<Vec<f64>> {
    cholesky(a, n).map(|l| chol_solve(&l, n, b))
}

/// Cholesky factor (lower, row-major) of a symmetric positive definite
/// `n × n` matrix; `None` if it is not.
fn cholesky(a: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            if i == j {
                if s.is_nan() || s <= 0.0 {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    Some(l)
}

fn chol_solve(l: &[f64], n: usize, b: &[f64]) -> Vec<f64> {
    let mut y = b.to_vec();
    for i in 0..n {
        for k in 0..i {
            y[i] -= l[i * n + k] * y[k];
        }
        y[i] /= l[i * n + i];
    }
    for i in (0..n).rev() {
        for k in i + 1..n {
            y[i] -= l[k * n + i] * y[k];
        }
        y[i] /= l[i * n + i];
    }
    y
}

fn chol_inverse(l: &[f64], n: usize) -> Vec<f64> {
    let mut inv = vec![0.0; n * n];
    let mut e = vec![0.0; n];
    for j in 0..n {
        e.iter_mut().for_each(|v| *v = 0.0);
        e[j] = 1.0;
        let col = chol_solve(l, n, &e);
        for i in 0..n {
            inv[i * n + j] = col[i];
        }
    }
    inv
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pixels of a toy model `R_k = a_p + b·sin(φ_p + c_k)` with a local
    /// parameter φ_p; the data carry a known gain and offset per band.
    fn toy(gain: &[f64], offset: &[f64], phases: &[f64]) -> (Vec<LevelPixel>, Vec<f64>) {
        let nb = gain.len();
        let model = |phi: f64, k: usize| 0.05 + 0.03 * (phi + 0.4 * k as f64).sin();
        let dmodel = |phi: f64, k: usize| 0.03 * (phi + 0.4 * k as f64).cos();
        let px = phases
            .iter()
            .map(|&phi| LevelPixel {
                y: (0..nb)
                    .map(|k| gain[k] * model(phi, k) + offset[k])
                    .collect(),
                r: (0..nb).map(|k| model(phi, k)).collect(),
                jac: vec![(0..nb).map(|k| dmodel(phi, k)).collect()],
                extra: Vec::new(),
                id: 0,
                d: 0.0,
                sigma_d: 0.0,
                theta: 0.0,
            })
            .collect();
        let wn = (0..nb).map(|k| 1.0 / (400.0 + 10.0 * k as f64)).collect();
        (px, wn)
    }

    #[test]
    fn per_band_gain_and_offset_are_recovered_in_one_step() {
        // The model is linear in the level; with the pixels at their true
        // parameters one step lands on the truth.
        let nb = 12;
        let gain: Vec<f64> = (0..nb)
            .map(|k| 1.0 + 0.06 * ((k * 7) % 5) as f64 / 4.0 - 0.03)
            .collect();
        let offset: Vec<f64> = (0..nb).map(|k| 0.004 + 0.0002 * k as f64).collect();
        let phases: Vec<f64> = (0..200).map(|i| i as f64 * 0.071).collect();
        let (px, wn) = toy(&gain, &offset, &phases);
        let var = vec![1e-6; nb];
        let st = level_step(&px, &Level::identity(nb), LevelBasis::PerBand, &wn, &var).unwrap();
        for k in 0..nb {
            assert!((st.level.gain[k] - gain[k]).abs() < 2e-3, "gain {k}");
            assert!((st.level.offset[k] - offset[k]).abs() < 1e-4, "offset {k}");
            assert!(st.level.var_gain[k] > 0.0 && st.level.var_gain[k] < 1e-3);
        }
    }

    #[test]
    fn smooth_basis_fits_a_quadratic_gain_and_one_offset() {
        let nb = 31;
        let wn: Vec<f64> = (0..nb).map(|k| 1.0 / (400.0 + 10.0 * k as f64)).collect();
        let (lo, hi) = (wn[nb - 1], wn[0]);
        let gain: Vec<f64> = wn
            .iter()
            .map(|s| {
                let u = (s - lo) / (0.5 * (hi - lo)) - 1.0;
                1.05 - 0.02 * u + 0.01 * u * u
            })
            .collect();
        let offset = vec![0.004; nb];
        let phases: Vec<f64> = (0..50).map(|i| i as f64 * 0.13).collect();
        let (px, _) = toy(&gain, &offset, &phases);
        let var = vec![1e-6; nb];
        let st = level_step(&px, &Level::identity(nb), LevelBasis::Smooth, &wn, &var).unwrap();
        for k in 0..nb {
            assert!((st.level.gain[k] - gain[k]).abs() < 2e-3, "gain {k}");
            assert!((st.level.offset[k] - 0.004).abs() < 2e-4, "offset {k}");
        }
        // At the truth a second step barely moves.
        let st2 = level_step(&px, &st.level, LevelBasis::Smooth, &wn, &var).unwrap();
        assert!(st2.change < 1e-3, "{}", st2.change);
    }

    #[test]
    fn correction_inverts_the_level() {
        let mut l = Level::identity(2);
        l.gain = vec![1.05, 0.9];
        l.offset = vec![0.004, -0.001];
        for k in 0..2 {
            let r = 0.07;
            let y = l.gain[k] * r + l.offset[k];
            assert!((l.correct(k, y) - r).abs() < 1e-15);
        }
        assert!(Level::identity(3).is_identity() && !l.is_identity());
    }

    /// A pixel whose model is linear in its thickness and angle,
    /// `R_k = c_k + J_d,k·d + J_θ,k·θ`, fitted by weighted least squares to
    /// `y` under gains `g`, offsets `o` and an extra global parameter `ν`
    /// (`y_k ≈ g_k·R_k + o_k + e_k·ν`); the angle only where `angle_free`,
    /// held at `theta` otherwise.
    #[allow(clippy::too_many_arguments)]
    fn refit_linear(
        y: &[f64],
        g: &[f64],
        o: &[f64],
        nu: f64,
        c: &[f64],
        jac: [&[f64]; 2],
        e: &[f64],
        w: &[f64],
        angle_free: bool,
        theta: f64,
    ) -> [f64; 2] {
        let (mut a, mut v) = ([[0.0f64; 2]; 2], [0.0f64; 2]);
        for k in 0..y.len() {
            let j = [
                g[k] * jac[0][k],
                if angle_free { g[k] * jac[1][k] } else { 0.0 },
            ];
            let fixed = if angle_free { 0.0 } else { jac[1][k] * theta };
            let z = y[k] - g[k] * (c[k] + fixed) - o[k] - e[k] * nu;
            for i in 0..2 {
                v[i] += w[k] * j[i] * z;
                for l in 0..2 {
                    a[i][l] += w[k] * j[i] * j[l];
                }
            }
        }
        if !angle_free {
            return [v[0] / a[0][0], 0.0];
        }
        let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
        [
            (a[1][1] * v[0] - a[0][1] * v[1]) / det,
            (a[0][0] * v[1] - a[1][0] * v[0]) / det,
        ]
    }

    #[test]
    fn level_share_is_the_variance_of_a_refitted_pixel() {
        // Second formulation: move each of the level's parameters (and the
        // extra global one) by ±δ, refit the pixel, and take its response
        // by central differences; then `tᵀ C t` over a covariance C with
        // every parameter correlated must be what `var_of` carries.
        let nb = 11;
        let basis = LevelBasis::Smooth;
        let ml = basis.n_params(nb);
        let u: Vec<f64> = (0..nb).map(|k| -1.0 + 0.2 * k as f64).collect();
        let rows: Vec<(f64, f64)> = (0..nb)
            .flat_map(|k| (0..ml).map(move |j| (k, j)))
            .map(|(k, j)| basis.rows(k, u[k], j))
            .collect();
        let c: Vec<f64> = (0..nb)
            .map(|k| 0.05 + 0.02 * (0.9 * k as f64).sin())
            .collect();
        let jd: Vec<f64> = (0..nb).map(|k| 1e-3 * (0.7 * k as f64).cos()).collect();
        let jt: Vec<f64> = (0..nb)
            .map(|k| 0.02 * (0.3 * k as f64 + 1.0).sin())
            .collect();
        let e: Vec<f64> = (0..nb).map(|k| 0.1 * (0.5 * k as f64).cos()).collect();
        let w: Vec<f64> = (0..nb).map(|k| 1e6 / (1.0 + 0.1 * k as f64)).collect();
        let gain = vec![1.02; nb];
        let offset = vec![0.003; nb];
        let (d0, t0) = (3.0, 0.4);
        let r: Vec<f64> = (0..nb).map(|k| c[k] + jd[k] * d0 + jt[k] * t0).collect();
        let y: Vec<f64> = (0..nb).map(|k| gain[k] * r[k] + offset[k]).collect();
        let m = ml + 1;
        // A covariance with every pair correlated: L Lᵀ, L lower triangular.
        let l: Vec<f64> = (0..m * m)
            .map(|i| {
                let (a, b) = (i / m, i % m);
                if b > a {
                    0.0
                } else {
                    1e-3 * (1.0 + ((a * 3 + b * 5) % 7) as f64) / (1.0 + (a - b) as f64)
                }
            })
            .collect();
        let cov: Vec<f64> = (0..m * m)
            .map(|i| {
                (0..m)
                    .map(|q| l[(i / m) * m + q] * l[(i % m) * m + q])
                    .sum()
            })
            .collect();
        let share = LevelShare {
            rows: rows.clone(),
            m_level: ml,
            cov: cov.clone(),
            m,
            w: w.clone(),
        };
        for angle_free in [true, false] {
            let dh = 1e-6;
            let t: Vec<[f64; 2]> = (0..m)
                .map(|j| {
                    let at = |s: f64| {
                        let (mut g, mut o, mut nu) = (gain.clone(), offset.clone(), 0.0);
                        if j < ml {
                            for k in 0..nb {
                                g[k] += s * rows[k * ml + j].0;
                                o[k] += s * rows[k * ml + j].1;
                            }
                        } else {
                            nu = s;
                        }
                        refit_linear(&y, &g, &o, nu, &c, [&jd, &jt], &e, &w, angle_free, t0)
                    };
                    let (p, q) = (at(dh), at(-dh));
                    [(p[0] - q[0]) / (2.0 * dh), (p[1] - q[1]) / (2.0 * dh)]
                })
                .collect();
            let quad = |i: usize| -> f64 {
                (0..m)
                    .flat_map(|a| (0..m).map(move |b| (a, b)))
                    .map(|(a, b)| t[a][i] * cov[a * m + b] * t[b][i])
                    .sum()
            };
            let (vd, vt) = share.var_of(
                &y,
                &gain,
                &r,
                &jd,
                angle_free.then_some(&jt[..]),
                &[&e[..]],
                &mut Vec::new(),
            );
            let (want_d, want_t) = (quad(0), quad(1));
            assert!(
                want_d > 0.0 && (vd / want_d - 1.0).abs() < 1e-5,
                "σ_d² {vd} vs {want_d}"
            );
            if angle_free {
                assert!(
                    want_t > 0.0 && (vt / want_t - 1.0).abs() < 1e-5,
                    "σ_θ² {vt} vs {want_t}"
                );
            } else {
                assert_eq!(vt, 0.0);
            }
        }
        // A missing band is left out of the pixel's fit, as its refit does.
        let mut y_gap = y.clone();
        y_gap[4] = f64::NAN;
        let w = &mut Vec::new();
        let full = share.var_of(&y, &gain, &r, &jd, Some(&jt), &[&e], w);
        let gap = share.var_of(&y_gap, &gain, &r, &jd, Some(&jt), &[&e], w);
        assert!(gap.0.is_finite() && gap.0 != full.0);
        // Inputs that do not match the level carry nothing.
        assert_eq!(
            share.var_of(&y, &gain, &r, &jd, Some(&jt), &[], w),
            (0.0, 0.0)
        );
    }
}
