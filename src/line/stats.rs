//! Statistics a line acts on: per web row and per lane (cross-web zone)
//! mean, σ, min/max, valid fraction and non-uniformity; a machine-direction
//! trend; process capability over a window of web.
//!
//! Definitions (thickness in nm, over the lane's valid pixels):
//! - σ: the sample standard deviation across the lane;
//! - non-uniformity: `(max − min) / (2 · mean)`, in percent (the ± band a
//!   coater quotes);
//! - trend: the least-squares slope of the lane means over the last
//!   `trend_rows` rows, nm per 1000 rows, and their mean;
//! - Cp = (USL − LSL) / 6σ, Cpk = min(USL − μ, μ − LSL) / 3σ, with μ and σ
//!   over every valid pixel of the lane in the last `window_rows` rows.
//!
//! Pure arithmetic over finished rows; O(1) work per row and lane for the
//! windows (running sums in fixed rings).

use super::solve::WebRowOut;
use std::collections::VecDeque;

/// Cross-web lanes: `[start, end)` pixel ranges.
#[derive(Clone, Debug, PartialEq)]
pub struct Lanes(pub Vec<(usize, usize)>);

impl Lanes {
    /// `n` lanes of equal width over `width` pixels.
    pub fn equal(width: usize, n: usize) -> Lanes {
        let n = n.clamp(1, width.max(1));
        Lanes(
            (0..n)
                .map(|i| (i * width / n, (i + 1) * width / n))
                .collect(),
        )
    }

    /// How many.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

/// One lane of one row.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct LaneStats {
    /// Mean thickness, nm (NaN: no valid pixel).
    pub mean_nm: f64,
    /// Standard deviation across the lane, nm.
    pub sigma_nm: f64,
    /// Thinnest, nm.
    pub min_nm: f64,
    /// Thickest, nm.
    pub max_nm: f64,
    /// Valid pixels / pixels.
    pub valid_fraction: f64,
    /// `(max − min) / (2 · mean)`, %.
    pub nonuniformity_pct: f64,
}

/// Statistics of one lane over `values` (valid thicknesses) of `pixels`.
pub fn lane_stats(values: impl Iterator<Item = f64>, pixels: usize) -> LaneStats {
    let (mut n, mut s, mut s2) = (0usize, 0.0, 0.0);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values {
        n += 1;
        s += v;
        s2 += v * v;
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if n == 0 {
        return LaneStats {
            mean_nm: f64::NAN,
            sigma_nm: f64::NAN,
            min_nm: f64::NAN,
            max_nm: f64::NAN,
            valid_fraction: 0.0,
            nonuniformity_pct: f64::NAN,
        };
    }
    let mean = s / n as f64;
    let var = if n > 1 {
        ((s2 - s * mean) / (n - 1) as f64).max(0.0)
    } else {
        0.0
    };
    LaneStats {
        mean_nm: mean,
        sigma_nm: var.sqrt(),
        min_nm: lo,
        max_nm: hi,
        valid_fraction: n as f64 / pixels.max(1) as f64,
        nonuniformity_pct: 100.0 * (hi - lo) / (2.0 * mean),
    }
}

/// Per-lane statistics of a row (all NaN, valid fraction 0, for a row that
/// missed bands).
pub fn row_stats(row: &WebRowOut, lanes: &Lanes) -> Vec<LaneStats> {
    lanes
        .0
        .iter()
        .map(|&(a, b)| {
            let est = &row.estimates[a.min(row.estimates.len())..b.min(row.estimates.len())];
            lane_stats(
                est.iter().filter(|e| e.is_valid()).map(|e| e.thickness_nm),
                est.len(),
            )
        })
        .collect()
}

/// Running sums over a window of rows.
#[derive(Clone, Debug, Default)]
struct Window {
    cap: usize,
    /// Per row: (n, Σ, Σ²).
    rows: VecDeque<(f64, f64, f64)>,
    tot: (f64, f64, f64),
}

impl Window {
    fn push(&mut self, v: (f64, f64, f64)) {
        if self.rows.len() == self.cap {
            if let Some(o) = self.rows.pop_front() {
                self.tot = (self.tot.0 - o.0, self.tot.1 - o.1, self.tot.2 - o.2);
            }
        }
        self.rows.push_back(v);
        self.tot = (self.tot.0 + v.0, self.tot.1 + v.1, self.tot.2 + v.2);
    }

    fn mean_sigma(&self) -> (f64, f64) {
        let (n, s, s2) = self.tot;
        if n < 2.0 {
            return (f64::NAN, f64::NAN);
        }
        let m = s / n;
        (m, ((s2 - s * m) / (n - 1.0)).max(0.0).sqrt())
    }
}

/// Process capability of a lane.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Capability {
    /// Mean over the window, nm.
    pub mean_nm: f64,
    /// σ over the window, nm.
    pub sigma_nm: f64,
    /// (USL − LSL) / 6σ.
    pub cp: f64,
    /// min(USL − μ, μ − LSL) / 3σ.
    pub cpk: f64,
}

/// Cp and Cpk for mean `m`, σ `s` and limits.
pub fn capability(m: f64, s: f64, lsl: f64, usl: f64) -> Capability {
    Capability {
        mean_nm: m,
        sigma_nm: s,
        cp: (usl - lsl) / (6.0 * s),
        cpk: (usl - m).min(m - lsl) / (3.0 * s),
    }
}

/// The machine-direction trend of a lane.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Trend {
    /// Mean of the lane means over the trend window, nm.
    pub mean_nm: f64,
    /// Least-squares slope, nm per 1000 rows.
    pub slope_nm_per_krow: f64,
}

/// Windows per lane: capability (pixels) and trend (lane means).
#[derive(Clone, Debug)]
pub struct LaneTracker {
    cap: Vec<Window>,
    trend_rows: usize,
    trend: Vec<VecDeque<(i64, f64)>>,
}

impl LaneTracker {
    /// Capability over `window_rows` rows, trend over `trend_rows`.
    pub fn new(lanes: usize, window_rows: usize, trend_rows: usize) -> LaneTracker {
        LaneTracker {
            cap: (0..lanes)
                .map(|_| Window {
                    cap: window_rows.max(1),
                    ..Default::default()
                })
                .collect(),
            trend_rows: trend_rows.max(2),
            trend: vec![VecDeque::new(); lanes],
        }
    }

    /// Add a row (its estimates, over `lanes`, and its lane statistics).
    pub fn push(&mut self, row: &WebRowOut, lanes: &Lanes, stats: &[LaneStats]) {
        for (i, &(a, b)) in lanes.0.iter().enumerate() {
            let mut acc = (0.0, 0.0, 0.0);
            for e in row.estimates.get(a..b).unwrap_or(&[]) {
                if e.is_valid() {
                    let v = e.thickness_nm;
                    acc = (acc.0 + 1.0, acc.1 + v, acc.2 + v * v);
                }
            }
            if let Some(w) = self.cap.get_mut(i) {
                w.push(acc);
            }
            if let (Some(t), Some(s)) = (self.trend.get_mut(i), stats.get(i)) {
                if s.mean_nm.is_finite() {
                    if t.len() == self.trend_rows {
                        t.pop_front();
                    }
                    t.push_back((row.index, s.mean_nm));
                }
            }
        }
    }

    /// Cp/Cpk of lane `i` against `[lsl, usl]`.
    pub fn capability(&self, i: usize, lsl: f64, usl: f64) -> Option<Capability> {
        let (m, s) = self.cap.get(i)?.mean_sigma();
        m.is_finite().then(|| capability(m, s, lsl, usl))
    }

    /// The trend of lane `i`.
    pub fn trend(&self, i: usize) -> Option<Trend> {
        let t = self.trend.get(i)?;
        if t.len() < 2 {
            return None;
        }
        let n = t.len() as f64;
        let mx = t.iter().map(|p| p.0 as f64).sum::<f64>() / n;
        let my = t.iter().map(|p| p.1).sum::<f64>() / n;
        let (mut sxy, mut sxx) = (0.0, 0.0);
        for &(x, y) in t {
            let dx = x as f64 - mx;
            sxy += dx * (y - my);
            sxx += dx * dx;
        }
        Some(Trend {
            mean_nm: my,
            slope_nm_per_krow: if sxx > 0.0 { 1000.0 * sxy / sxx } else { 0.0 },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimate::{PixelEstimate, Reason};

    fn row(index: i64, d: impl Fn(usize) -> f64, w: usize) -> WebRowOut {
        WebRowOut {
            index,
            time_ns: 0,
            complete: true,
            bands_seen: 31,
            sensor_row_spread: 0,
            angle_corrected: false,
            estimates: (0..w)
                .map(|x| {
                    let v = d(x);
                    if v.is_nan() {
                        PixelEstimate::invalid(Reason::PoorFit)
                    } else {
                        PixelEstimate {
                            thickness_nm: v,
                            n_film: 1.46,
                            theta_deg: 30.0,
                            sigma_thickness_nm: 0.5,
                            sigma_theta_deg: 0.0,
                            residual_rms: 0.001,
                            reason: Reason::Ok,
                        }
                    }
                })
                .collect(),
        }
    }

    #[test]
    fn lane_statistics_by_hand() {
        // Lane 0: 100, 102, 104, NaN; lane 1: all invalid.
        let r = row(
            0,
            |x| {
                if x < 3 {
                    100.0 + 2.0 * x as f64
                } else {
                    f64::NAN
                }
            },
            8,
        );
        let s = row_stats(&r, &Lanes::equal(8, 2));
        assert_eq!(s[0].mean_nm, 102.0);
        assert!((s[0].sigma_nm - 2.0).abs() < 1e-12);
        assert_eq!((s[0].min_nm, s[0].max_nm), (100.0, 104.0));
        assert_eq!(s[0].valid_fraction, 0.75);
        assert!((s[0].nonuniformity_pct - 100.0 * 4.0 / 204.0).abs() < 1e-12);
        assert_eq!(s[1].valid_fraction, 0.0);
        assert!(s[1].mean_nm.is_nan());
        assert_eq!(Lanes::equal(10, 3).0, vec![(0, 3), (3, 6), (6, 10)]);
    }

    #[test]
    fn capability_and_trend_match_their_definitions() {
        let lanes = Lanes::equal(4, 1);
        let mut t = LaneTracker::new(1, 1000, 100);
        // Means drift by 0.01 nm per row; within a row ±1 nm.
        for k in 0..100 {
            let r = row(
                k,
                |x| 300.0 + 0.01 * k as f64 + [-1.0, 1.0, -1.0, 1.0][x],
                4,
            );
            let s = row_stats(&r, &lanes);
            t.push(&r, &lanes, &s);
        }
        let tr = t.trend(0).unwrap();
        assert!((tr.slope_nm_per_krow - 10.0).abs() < 1e-9);
        assert!((tr.mean_nm - 300.495).abs() < 1e-9);
        let c = t.capability(0, 290.0, 310.0).unwrap();
        // Pooled σ: within-row ±1 and the drift's spread (0.29 nm).
        let drift_var = (0..100)
            .map(|k| (0.01 * k as f64 - 0.495).powi(2))
            .sum::<f64>()
            / 100.0;
        let sigma = ((400.0 * (1.0 + drift_var)) / 399.0).sqrt();
        assert!((c.sigma_nm - sigma).abs() < 1e-9);
        assert!((c.cp - 20.0 / (6.0 * sigma)).abs() < 1e-9);
        assert!((c.cpk - (310.0 - 300.495) / (3.0 * sigma)).abs() < 1e-9);
        // The window forgets: only the last 10 rows.
        let mut w = LaneTracker::new(1, 10, 10);
        for k in 0..50 {
            let r = row(
                k,
                |_| {
                    if k < 40 {
                        500.0
                    } else {
                        300.0 + (k % 2) as f64
                    }
                },
                4,
            );
            w.push(&r, &lanes, &row_stats(&r, &lanes));
        }
        let c = w.capability(0, 290.0, 310.0).unwrap();
        assert!((c.mean_nm - 300.5).abs() < 1e-9);
    }
}
