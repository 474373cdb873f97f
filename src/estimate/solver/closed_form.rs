//! The closed forms on the fringe extrema (`fast`, and the start of the
//! other modes): extrema located between bands, the order from their spacing
//! and the interference lattice, the angle from their levels, the thickness
//! from Eq. 14; and the angle start from the envelopes (stage 2).

use super::bands::Window;
use super::{IndexEstimate, Prepared, Scratch, Solver, ANGLE_SIGMA_LIMIT_DEG};
use crate::estimate::angle::half_wave_sin2;
use crate::estimate::fastmath::{self, round};
use crate::estimate::{detect, PixelEstimate, Reason};
use crate::optics::Polarization;
use std::f64::consts::PI;

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
pub(super) struct ExtremaAcc {
    ext: [Ext; MAX_EXT],
    n: usize,
    rss: f64,
    rdof: f64,
    /// Extrema closer in level than this are noise wiggles (3 σ_R).
    prominence: f64,
}

impl ExtremaAcc {
    pub(super) fn new(noise: Option<f64>) -> Self {
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
    pub(super) fn reset(&mut self) {
        self.n = 0;
        self.rss = 0.0;
        self.rdof = 0.0;
    }

    pub(super) fn full(&self) -> bool {
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

impl Solver {
    /// The closed-form path: fringe extrema located between bands (a
    /// least-squares parabola in wavenumber through five samples), the order
    /// from their spacing and the interference lattice, the angle from the
    /// extrema levels, the thickness from Eq. 14. `None` when fewer than two
    /// consistent extrema are in range (the caller then searches).
    ///
    /// σ comes from the parabola fits' covariance (reflectance noise from
    /// `noise`, else from the fits' own residuals), propagated to the
    /// extremum positions and levels, then to g, θ (σ_R / |dR/dθ|) and d.
    pub(super) fn extrema_estimate(
        &self,
        prep: &Prepared,
        theta_known: Option<f64>,
        noise: Option<f64>,
        scratch: &mut Scratch,
    ) -> Option<PixelEstimate> {
        let nb = self.table.sorted.len();
        if nb < 7 {
            return None;
        }
        // The spectrum by increasing wavelength (no copy when the planes are
        // already in that order).
        let Scratch {
            spectrum, sorted_y, ..
        } = scratch;
        let ys: &[f64] = if self.table.sorted_identity {
            &spectrum[..nb]
        } else {
            sorted_y.resize(nb, 0.0);
            for (i, b) in self.table.sorted.iter().enumerate() {
                sorted_y[i] = spectrum[b.0];
            }
            &sorted_y[..]
        };
        // [1 2 1]-smoothed value at i, for detection only (fits use raw
        // data), the ends reflected.
        let smooth = |i: usize| {
            let a = ys[i.saturating_sub(1)] as f32;
            let c = ys[(i + 1).min(nb - 1)] as f32;
            detect::smooth3(a, ys[i] as f32, c)
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
            let win = self.table.parabola[i]
                .as_ref()
                .map_or((0, 0), |w| (w.lo, w.len));
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
    pub(super) fn fit_extremum(&self, i: usize, kind: i8, y: [f64; 5], acc: &mut ExtremaAcc) {
        let Some(win) = &self.table.parabola[i] else {
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
            pos: self.table.sorted[i].2 + u * 1e-4,
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
        self.table.parabola[usize::from(e.band)]
            .as_ref()
            .map_or(f64::INFINITY, |w| e.var_pos(w))
    }

    /// [`Ext::var_val`] in its window.
    #[inline]
    fn ext_var_val(&self, e: &Ext) -> f64 {
        self.table.parabola[usize::from(e.band)]
            .as_ref()
            .map_or(f64::INFINITY, |w| e.var_val(w))
    }

    /// Lattice, angle and thickness from located extrema. With `index`
    /// (the global film index), its value and its share of σ_d are
    /// included, as [`Solver::with_index`] would.
    ///
    /// The divider is this path's bottleneck, so divisions and square
    /// roots are kept to those the result needs.
    pub(super) fn closed_form(
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
            let h = self.table.parabola[usize::from(e.band)]
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
        let lo_s = self.table.interior.0.max(self.table.sigma_range.0 + eighth);
        let hi_s = self.table.interior.1.min(self.table.sigma_range.1 - eighth);
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
                let s = fastmath::sin_cos(t).0;
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
                        let s = fastmath::sin_cos(t).0;
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
        // Fringes too shallow to place flag the pixel whatever its angle's
        // σ (a weak angle is a valid pixel's note, not a pass: it once
        // skipped this test).
        let reason = if noise.is_some() && self.film_invisible(prep, theta, self.bands.len(), var_r)
        {
            Reason::NoFringe
        } else if theta_known.is_none() && sigma_theta.to_degrees() > ANGLE_SIGMA_LIMIT_DEG {
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
}

/// The angle whose model envelopes best match the fitted half-wave and
/// quarter-wave levels, refined by a parabola through the best table entry.
pub(super) fn angle_start(
    table: &[(f64, f64, f64)],
    half: Option<f64>,
    quarter: Option<f64>,
) -> f64 {
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

impl Prepared {
    /// The half- and quarter-wave levels at `theta`, interpolated in the
    /// angle table (its ends beyond it).
    pub(super) fn envelopes_at(&self, theta: f64) -> (f64, f64) {
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
pub(super) struct Slopes {
    t0: f64,
    inv_step: f64,
    slope: Vec<f64>,
}

impl Slopes {
    pub(super) fn new(table: &[(f64, f64, f64)]) -> Slopes {
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
