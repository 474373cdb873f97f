//! Alternative fits: the basins a fresh search never looks at, weighed
//! against its best fit like a second fringe order (the better one wins;
//! if both fit alike, the order is ambiguous).
//!
//! - **Past the resolved range** (any light, the angle known or free):
//!   where the fringes are weak, a film beyond what the bands resolve
//!   (up to twice it) aliases into a passing in-range fit; one there that
//!   fits as well flags the pixel "fringes unresolved" (or ambiguous).
//!
//! With the angle free, also:
//!
//! - **Mirror angles** (p light): an interface's p reflection vanishes at
//!   its Brewster angle and grows again beyond it, so an angle on one side
//!   and its mirror image on the other (equal |r_p|) give nearly the same
//!   level, and the film's optical thickness takes up the rest. The angle
//!   start comes from the level, so the search sees only one side.
//! - **Weak fringes** (any light): where the fringes carry little more
//!   signal than the χ² test lets pass, a local fit at a thickness far off
//!   passes the test. There, the whole thickness range is scanned at the
//!   fitted angle (and the mirror angles).
//! - **Below the first fringe** (any light): a film's phase hardly changes
//!   across the bands, so a thicker or thinner sub-fringe film differs by
//!   little more than a level, which the angle absorbs (a bare substrate
//!   at 74.6° passed for a 101 nm film). The sub-fringe range is scanned.
//!
//! On noise-free extremes (film index 1.01–1.59 on 1.60, p light, 0–89.5°)
//! these turned wrong valid fits of 0.1–3 µm error into right ones or
//! flags. Each check runs only where the fit's fringes are weak enough for
//! its alternative to pass the χ² test ([`SUB_FRINGE_BELOW`],
//! [`MIRROR_BELOW`], [`WEAK_FRINGES`], in χ² thresholds of fringe signal),
//! and a start is refined only if its scan point comes within reach of the
//! fit: the scene matrix's classes (fringes of hundreds of thresholds and
//! more) keep their speed.

use super::refine::sse;
use super::{Fit, Prepared, Scratch, Solver};
use crate::estimate::model::FilmModel;

/// A fit's neighbouring fringe orders are weighed again only where the
/// previous pixel's fell short of its fit by less than this many noise
/// variances of ΔSSE, or the fit moved (see [`OrderMargin`]).
pub(super) const ORDER_MARGIN_SKIP: f64 = 100.0;

/// How far the previous pixel's neighbouring fringe order (one fringe more
/// or fewer) fell short of its fit in the row, ΔSSE in noise variances, and
/// where that fit stood: on a table (`key`: its angle's bits) its
/// thickness, on the fitted path (`key`: [`OrderMargin::FITTED`]) its
/// optical thickness. Where the margin was wide (≥ [`ORDER_MARGIN_SKIP`])
/// and this pixel's fit moved by under a twentieth of a fringe, the order
/// cannot have come within the ambiguity margin (9): the noise moves ΔSSE
/// by about 2√ΔSSE variances, and a film does not close 91 of them in one
/// pixel. The margin is then carried at half, so the order is weighed
/// again within a few pixels, and at least every fifth (the margin kept
/// is capped at 16 × [`ORDER_MARGIN_SKIP`]).
#[derive(Clone, Copy, Debug)]
pub(super) struct OrderMargin {
    key: u64,
    at: f64,
    margin: f64,
}

impl OrderMargin {
    /// The fitted path's key (a NaN pattern: no table's angle).
    pub(super) const FITTED: u64 = u64::MAX;

    /// A fit at `at` on `key`, its neighbouring order `margin` behind.
    pub(super) fn new(key: u64, at: f64, margin: f64) -> OrderMargin {
        OrderMargin {
            key,
            at,
            margin: margin.min(16.0 * ORDER_MARGIN_SKIP),
        }
    }

    /// The margin carried from `prev` to a fit at `at` on `key` (`fringe`:
    /// one fringe in `at`'s unit), where the order need not be weighed.
    pub(super) fn carried(
        prev: Option<OrderMargin>,
        key: u64,
        at: f64,
        fringe: f64,
    ) -> Option<f64> {
        prev.filter(|p| {
            p.key == key && (at - p.at).abs() < 0.05 * fringe && p.margin >= ORDER_MARGIN_SKIP
        })
        .map(|p| 0.5 * p.margin)
    }
}

/// Fringes below this many χ² thresholds of signal are "weak": the whole
/// range is scanned for another basin.
pub(super) const WEAK_FRINGES: f64 = 10.0;

/// A film below its first fringe is checked against the sub-fringe range
/// where its fringes carry less than this many χ² thresholds: the
/// alternative differs from it by what the angle cannot absorb of a slowly
/// varying fringe term, a few % of its signal (a bare substrate at 74.6°
/// in p light passed for a 101 nm film with 20 thresholds of signal: twice
/// that is checked). Stronger fringes leave any such alternative failing
/// the χ² test; a thin coating of silica on PET at σ = 0.001 (~120
/// thresholds) never runs it.
const SUB_FRINGE_BELOW: f64 = 40.0;

/// A fit in p light is checked against its mirror angles where its
/// fringes carry less than this many χ² thresholds. Across a Brewster
/// angle an interface changes sign, a half-period shift no one optical
/// thickness reproduces at every wavelength, so only weak fringes let a
/// mirror fit pass (on a film of index 1.01 on 1.60, one passed with 47
/// thresholds: four times that is checked). TiO2 on PET at σ = 0.001
/// (thousands) never runs it.
const MIRROR_BELOW: f64 = 200.0;

/// A mirror angle's scan start is refined where its residual lies within
/// this many times the fit's fringe signal of the fit's (see `mirror_gate`).
const MIRROR_SCAN_SLACK: f64 = 1.5;

/// Refinement iterations for an alternative start.
const ITERS: usize = 25;

impl Solver {
    /// The alternatives to the best of `fits` (judged pixels only), pushed
    /// to `out` while it has room.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn alternative_fits(
        &self,
        fits: &[Fit],
        n_ok: usize,
        theta_known: Option<f64>,
        noise: Option<f64>,
        prep: &Prepared,
        scratch: &mut Scratch,
        out: &mut heapless::Vec<Fit, 5>,
    ) {
        let Some(sigma) = noise.filter(|_| self.judging()) else {
            return;
        };
        let free = theta_known.is_none();
        let Some(best) = fits
            .iter()
            .filter(|f| f.sse.is_finite() && f.d.is_finite() && f.theta.is_finite())
            .min_by(|a, b| a.sse.total_cmp(&b.sse))
        else {
            return;
        };
        let model = &prep.model;
        let signal = self.fringe_signal(prep, best.theta, n_ok, sigma, scratch);
        let weak = signal < WEAK_FRINGES;
        if !weak && !free {
            // The angle known and the fringes strong: no alternative.
            return;
        }

        let step = 0.125 / self.table.sigma_center;
        let q2 = scratch.q2_mid(prep, best.theta);
        let (g0, g_max) = (best.d * q2, self.d_max * q2);
        let (lam_min, lam_max) = self.band_span();
        let thin = g0 < 0.5 * lam_max && signal < SUB_FRINGE_BELOW;
        // A start is refined only where its scan point comes within this
        // of the fit's residual: a basin that far off cannot end within
        // the ambiguity margin (Δχ² < 9) after a refinement that moves the
        // thickness by less than a grid step. Strong fringes put every
        // other basin far beyond it, so ordinary pixels pay the scan only.
        let threshold = self.chi2.threshold(n_ok.saturating_sub(2).max(1));
        let gate = best.sse + WEAK_FRINGES * threshold * sigma * sigma;
        // A mirror angle's scan points sit up to a sixteenth of a wave of
        // optical thickness from its basin's floor (a phase of up to
        // ~π/3 at the bluest band), where the residual climbs by up to
        // about the fringes' whole signal: the gate lets that much
        // through.
        let mirror_gate =
            best.sse + (MIRROR_SCAN_SLACK * signal).max(WEAK_FRINGES) * threshold * sigma * sigma;
        let in_range = (self.d_min, self.d_max);
        let mut push = |start: Option<(f64, f64, f64)>,
                        bounds: (f64, f64),
                        gate: f64,
                        scratch: &mut Scratch| {
            let Some((d, th, e)) = start else { return };
            if out.is_full() || e > gate {
                return;
            }
            let f = self.refine_within(model, d, th, free, ITERS, bounds, scratch);
            if f.sse.is_finite() {
                // Room checked above.
                let _ = out.push(f);
            }
        };
        if weak {
            // Past the resolved range (to twice it), where point samples
            // alias: weak fringes of a thicker film pass for an in-range
            // one (a 2.8 µm film index-matched to its substrate, seen near
            // Brewster's angle, read 47 nm). A film there that fits as
            // well leaves the pixel flagged "fringes unresolved".
            let q = prep.model.q2_mid(best.theta);
            let g_res = self.g_max.0;
            let bounds = (self.d_min, 2.0 * g_res / q);
            let span = (g_res, 2.0 * g_res);
            let start = self.scan_start(model, best.theta, span, step, None, bounds, free, scratch);
            push(start, bounds, gate, scratch);
        }
        if !free {
            return;
        }
        if self.scene.polarization.s_weight() < 0.5 && signal < MIRROR_BELOW {
            let (n1, n3) = prep.model.ambient_substrate_mid();
            let (n1, n2, n3) = (n1.re, prep.model.n2_mid(), n3.re);
            // Ambient–film, film–substrate.
            for (ni, nj) in [(n1, n2), (n2, n3)] {
                let Some(tm) = mirror_angle(n1, ni, nj, best.theta, self.theta_range) else {
                    continue;
                };
                if (tm - best.theta).abs() < 1f64.to_radians() {
                    continue;
                }
                // Across the Brewster angle the interface's reflection
                // changes sign, which shifts the fringes by half a period (a
                // quarter wave of optical thickness): a few optical
                // thicknesses around the same one, up to 3/8 wave off; from
                // zero for a film below its first fringe (whose own fit may
                // be a sub-fringe stand-in); the whole range where the
                // fringes are weak.
                let span = if weak {
                    (0.0, g_max)
                } else if thin {
                    (0.0, 0.5 * lam_max + 3.0 * step)
                } else {
                    (g0 - 3.0 * step, g0 + 3.0 * step)
                };
                // The scan's angle moves stay on the mirror's side, short
                // of half-way to the Brewster angle, where the fringes fade
                // and any thickness fits about as well as another.
                let side = brewster(n1, ni, nj).map_or(self.theta_range, |tb| {
                    let (lo, hi) = self.theta_range;
                    let mid = 0.5 * (tb + tm);
                    if tm > tb {
                        (mid.min(tm), hi)
                    } else {
                        (lo, mid.max(tm))
                    }
                });
                let start =
                    self.scan_start_in(model, tm, span, step, None, in_range, side, scratch);
                push(start, in_range, mirror_gate, scratch);
                // And the next best away from it: near a Brewster angle the
                // scan's best can lead back to the fitted side (noise-free
                // p light at 61 bands, n2 1.37: a 200 nm film at 54.7° read
                // 79 nm at 52.2°, valid, while the mirror side's second
                // basin refines to the truth). Weak fringes scan the whole
                // range below instead.
                if let Some((d, th, _)) = start.filter(|_| !weak) {
                    let away = Some((d * model.q2_mid(th), 1.5 * step));
                    let next =
                        self.scan_start_in(model, tm, span, step, away, in_range, side, scratch);
                    push(next, in_range, mirror_gate, scratch);
                }
            }
        }
        if weak {
            // The same side, away from the fitted basin.
            let start = self.scan_start(
                model,
                best.theta,
                (0.0, g_max),
                step,
                Some((g0, 2.0 * step)),
                in_range,
                true,
                scratch,
            );
            push(start, in_range, gate, scratch);
        }
        if thin {
            // A film below its first fringe: its phase hardly changes
            // across the bands, so a thicker or thinner one differs by
            // little more than a level, which the angle absorbs. The
            // sub-fringe range at twice the density, away from the fit by
            // what counts as another order.
            let start = self.scan_start(
                model,
                best.theta,
                (0.0, 0.5 * lam_max),
                0.5 * step,
                Some((g0, 0.125 * lam_min)),
                in_range,
                true,
                scratch,
            );
            push(start, in_range, gate, scratch);
        }
    }

    /// The fringe signal at angle `theta` in χ² thresholds: the energy of
    /// the deepest modulation any thickness gives there (`n_ok·c²/8` over
    /// the noise variance, `c` the envelopes' difference).
    pub(super) fn fringe_signal(
        &self,
        prep: &Prepared,
        theta: f64,
        n_ok: usize,
        sigma: f64,
        scratch: &Scratch,
    ) -> f64 {
        let mut memo = scratch.angle_memo(prep, theta);
        let key = (n_ok, sigma.to_bits());
        if let Some((n, s, signal)) = memo.signal {
            if (n, s) == key {
                return signal;
            }
        }
        let (h, q) = prep.envelopes_at(theta);
        let c = (h - q).abs();
        let energy = n_ok as f64 * c * c / (8.0 * sigma * sigma);
        let signal = energy / self.chi2.threshold(n_ok.saturating_sub(2).max(1));
        memo.signal = Some((key.0, key.1, signal));
        scratch.angle_memo.set(Some(memo));
        signal
    }

    /// Whether a local fit's fringes are strong enough that none of the
    /// alternatives above could pass the χ² test beside it: at or above
    /// every check's gate that applies to this light and angle (the
    /// mirror angles only where the angle is `free`; with it known, the
    /// sub-fringe gate stands for every light as before).
    pub(super) fn fringes_exclude_alternatives(&self, signal: f64, free: bool) -> bool {
        let gate = if free && self.scene.polarization.s_weight() < 0.5 {
            MIRROR_BELOW
        } else {
            SUB_FRINGE_BELOW
        };
        signal >= gate.max(WEAK_FRINGES)
    }

    /// The best start on a grid of optical thickness (`span`, in `step`s)
    /// at angle `theta`, each point judged with the angle moved to its best
    /// to first order (a mirror angle is approximate, and far from normal
    /// incidence the level is steep in the angle); grid points within
    /// `exclude` = (g, half-width) are skipped, and so are thicknesses
    /// outside `d_range`; with the angle known (`free` false) it stays.
    /// Returns (d, θ, its SSE).
    #[allow(clippy::too_many_arguments)]
    fn scan_start(
        &self,
        model: &FilmModel,
        theta: f64,
        span: (f64, f64),
        step: f64,
        exclude: Option<(f64, f64)>,
        d_range: (f64, f64),
        free: bool,
        scratch: &mut Scratch,
    ) -> Option<(f64, f64, f64)> {
        let th_range = if free {
            self.theta_range
        } else {
            (theta, theta)
        };
        self.scan_start_in(
            model, theta, span, step, exclude, d_range, th_range, scratch,
        )
    }

    /// [`Self::scan_start`] with the angle free within `(lo, hi)` (fixed
    /// where they are equal).
    #[allow(clippy::too_many_arguments)]
    fn scan_start_in(
        &self,
        model: &FilmModel,
        theta: f64,
        span: (f64, f64),
        step: f64,
        exclude: Option<(f64, f64)>,
        d_range: (f64, f64),
        (lo, hi): (f64, f64),
        scratch: &mut Scratch,
    ) -> Option<(f64, f64, f64)> {
        let free = hi > lo;
        let q = model.q2_mid(theta);
        let mut best = (f64::NAN, f64::NAN, f64::INFINITY);
        let k0 = (span.0.max(0.0) / step).ceil() as i64;
        let k1 = (span.1 / step).floor() as i64;
        for k in k0..=k1 {
            let g = k as f64 * step;
            if exclude.is_some_and(|(g0, w)| (g - g0).abs() < w) {
                continue;
            }
            let d = g / q;
            if !(d_range.0..=d_range.1).contains(&d) {
                continue;
            }
            // The angle's derivative only where the angle may move.
            model.eval(d, theta, &mut scratch.trial, free);
            let (mut ej, mut jj) = (0.0, 0.0);
            for b in (0..scratch.spectrum.len()).filter(|_| free) {
                let (w, j) = (scratch.weight[b], scratch.trial.dr_dth[b]);
                ej += w * (scratch.spectrum[b] - scratch.trial.r[b]) * j;
                jj += w * j * j;
            }
            let e2 = sse(&scratch.spectrum, &scratch.weight, &scratch.trial.r);
            let (e, dt) = if free && jj > 0.0 {
                (e2 - ej * ej / jj, (ej / jj).clamp(-0.05, 0.05))
            } else {
                (e2, 0.0)
            };
            if e < best.2 {
                best = (d, (theta + dt).clamp(lo, hi), e);
            }
        }
        best.0.is_finite().then_some(best)
    }
}

/// |r_p| of the interface from index `ni` to `nj`, seen at external angle
/// `theta` from an ambient of index `n1` (lossless, mid-band).
fn rp_abs(n1: f64, ni: f64, nj: f64, theta: f64) -> f64 {
    let kx = n1 * theta.sin();
    let ci = (1.0 - (kx / ni).powi(2)).max(0.0).sqrt();
    let cj = (1.0 - (kx / nj).powi(2)).max(0.0).sqrt();
    ((nj * ci - ni * cj) / (nj * ci + ni * cj)).abs()
}

/// The external angle at which the interface from index `ni` to `nj`
/// reflects no p light, seen from an ambient of index `n1` (lossless,
/// mid-band); `None` where no external angle reaches it.
fn brewster(n1: f64, ni: f64, nj: f64) -> Option<f64> {
    // tan θ_i = nj / ni inside medium i; outside, by Snell.
    let sb = ni * nj / (n1 * (ni * ni + nj * nj).sqrt());
    (sb.is_finite() && sb < 1.0).then(|| sb.asin())
}

/// The external angle on the other side of the interface's Brewster angle
/// (within `range`) at which |r_p| equals its value at `theta`, by
/// bisection (|r_p| rises away from the Brewster angle on either side);
/// `None` if there is none.
fn mirror_angle(n1: f64, ni: f64, nj: f64, theta: f64, range: (f64, f64)) -> Option<f64> {
    let tb = brewster(n1, ni, nj).filter(|_| theta.is_finite())?;
    let target = rp_abs(n1, ni, nj, theta);
    let f = |t: f64| rp_abs(n1, ni, nj, t) - target;
    // From the Brewster angle (f < 0) to the far end of the other side.
    let (mut near, mut far) = if theta < tb {
        (tb, range.1.min(std::f64::consts::FRAC_PI_2 - 1e-9))
    } else {
        (tb, range.0.max(0.0))
    };
    if (far - near).abs() < 1e-12 || f(far) < 0.0 {
        return None;
    }
    for _ in 0..60 {
        let mid = 0.5 * (near + far);
        if f(mid) < 0.0 {
            near = mid;
        } else {
            far = mid;
        }
    }
    Some(0.5 * (near + far))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Brewster angle from the Fresnel formula itself (|r_p| = 0) and
    /// the mirror image against a direct evaluation on both sides.
    #[test]
    fn mirror_angles_have_equal_p_reflection() {
        for (n1, ni, nj) in [
            (1.0f64, 1.0f64, 1.5f64),
            (1.0, 1.37, 1.6),
            (1.0, 1.01, 1.6),
            (1.33, 1.33, 1.5),
        ] {
            let sb = ni * nj / (n1 * (ni * ni + nj * nj).sqrt());
            if sb >= 1.0 {
                continue;
            }
            let tb = sb.asin();
            assert!(rp_abs(n1, ni, nj, tb) < 1e-12, "{n1} {ni} {nj}");
            for dt in [-0.4, -0.2, -0.05, 0.05, 0.2] {
                let t = tb + dt;
                let range = (0.0, 89.5f64.to_radians());
                if let Some(m) = mirror_angle(n1, ni, nj, t, range) {
                    // The other side, and the same |r_p|.
                    assert!((m - tb) * dt < 0.0, "{t} → {m}");
                    let (a, b) = (rp_abs(n1, ni, nj, t), rp_abs(n1, ni, nj, m));
                    assert!((a - b).abs() < 1e-9, "{a} {b}");
                } else {
                    // None only when the other side never reaches it.
                    let end = if dt < 0.0 { range.1 } else { 0.0 };
                    assert!(rp_abs(n1, ni, nj, end) < rp_abs(n1, ni, nj, t));
                }
            }
        }
        // Index-matched interfaces have no Brewster angle seen from air.
        assert!(mirror_angle(1.0, 1.59, 1.6, 0.5, (0.0, 1.5)).is_none());
    }
}
