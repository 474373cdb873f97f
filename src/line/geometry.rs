//! Web geometry: where each frame's sensor rows lie on the moving web, and
//! the highest line speed the optics allow.
//!
//! Conventions. The web moves along the sensor's columns; one web row is one
//! sensor row long. A frame exposed with the web at position `p` (in web
//! rows, from the encoder or from a constant speed and the frame time) sees
//! web rows `round(p) … round(p) + rows_in_view − 1` on sensor rows
//! `0 … rows_in_view − 1`: a web row enters the view at the last sensor row
//! and leaves it past row 0, so rows leave the view, and complete, in web
//! order.
//!
//! The limit. Bands come at `band_rate` per second, one frame each; a web
//! row is in view while `round(p)` runs over `rows_in_view` consecutive
//! values. At speed `v` (rows/s) the frames are `v / band_rate` rows apart,
//! so any window of `rows_in_view` rows holds at least
//! `floor(rows_in_view · band_rate / v)` frames, and `n` consecutive frames
//! hold every band of a cyclic sweep. Every row sees every band exactly when
//! `v ≤ rows_in_view · band_rate / n_bands` ([`LineGeometry::max_speed`]);
//! the unit tests check this against a brute-force simulation.
//!
//! Pure arithmetic: no I/O, no clock.

use super::LineError;

/// How the web's position is known.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Motion {
    /// An encoder count per frame (frame metadata), `rows_per_count` web rows
    /// per count (the camera's calibration).
    Encoder {
        /// Web rows per encoder count.
        rows_per_count: f64,
    },
    /// A constant speed, web rows per second, timed by the frame timestamps.
    Constant {
        /// Web rows per second.
        rows_per_s: f64,
    },
}

/// The optics and the sweep, as far as the line speed is concerned.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LineGeometry {
    /// Sensor rows that see the web (the field of view along the web).
    pub rows_in_view: usize,
    /// Bands per sweep.
    pub n_bands: usize,
    /// Bands delivered per second (one frame each).
    pub band_rate_hz: f64,
}

impl LineGeometry {
    /// Check that the numbers make sense.
    pub fn new(
        rows_in_view: usize,
        n_bands: usize,
        band_rate_hz: f64,
    ) -> Result<LineGeometry, LineError> {
        if rows_in_view == 0 || n_bands == 0 {
            return Err(LineError::Config(format!(
                "line geometry needs rows in view and bands (got {rows_in_view} rows, {n_bands} bands)"
            )));
        }
        if !(band_rate_hz.is_finite() && band_rate_hz > 0.0) {
            return Err(LineError::Config(format!(
                "band rate must be a positive number of bands per second, got {band_rate_hz}"
            )));
        }
        Ok(LineGeometry {
            rows_in_view,
            n_bands,
            band_rate_hz,
        })
    }

    /// The highest web speed, rows/s, at which every web row is seen in
    /// every band: `rows_in_view · band_rate / n_bands`.
    pub fn max_speed(&self) -> f64 {
        self.rows_in_view as f64 * self.band_rate_hz / self.n_bands as f64
    }

    /// The sweep time, s.
    pub fn sweep_s(&self) -> f64 {
        self.n_bands as f64 / self.band_rate_hz
    }

    /// One line with the numbers, for logs and `--help`-style prints.
    pub fn describe(&self) -> String {
        format!(
            "{} rows in view × {:.2} bands/s / {} bands = highest line speed {:.2} rows/s",
            self.rows_in_view,
            self.band_rate_hz,
            self.n_bands,
            self.max_speed()
        )
    }

    /// Refuse a speed (rows/s) at which some rows would miss a band, with
    /// the numbers.
    pub fn check_speed(&self, rows_per_s: f64) -> Result<(), LineError> {
        if !rows_per_s.is_finite() || rows_per_s < 0.0 {
            return Err(LineError::Config(format!(
                "line speed must be a non-negative number of rows per second, got {rows_per_s}"
            )));
        }
        let max = self.max_speed();
        if rows_per_s > max * (1.0 + 1e-12) {
            return Err(LineError::TooFast {
                speed: rows_per_s,
                max,
                rows_in_view: self.rows_in_view,
                band_rate_hz: self.band_rate_hz,
                n_bands: self.n_bands,
            });
        }
        Ok(())
    }
}

/// The band rate of a stepped filter on a free-running camera: after each
/// accepted frame (exposure `exposure_ns`) the filter is commanded and
/// settles within `settle_max_ns`; the next usable frame is the first that
/// starts after that, on a grid of `frame_period_ns`.
pub fn stepped_band_rate(frame_period_ns: u64, exposure_ns: u64, settle_max_ns: u64) -> f64 {
    let period = frame_period_ns.max(1);
    // Frame k starts at k·period; the next usable one starts at or after
    // k·period + exposure + settle.
    let frames = (exposure_ns + settle_max_ns).div_ceil(period).max(1);
    1e9 / (frames * period) as f64
}

/// Where the web is in a frame: the web row seen by sensor row 0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Registration {
    motion: Motion,
    origin: Option<u64>,
}

impl Registration {
    /// Register frames with `motion`. By encoder, web rows are absolute
    /// (count × rows per count); at constant speed, the first frame's
    /// sensor row 0 is web row 0.
    pub fn new(motion: Motion) -> Result<Registration, LineError> {
        let ok = match motion {
            Motion::Encoder { rows_per_count } => {
                rows_per_count.is_finite() && rows_per_count > 0.0
            }
            Motion::Constant { rows_per_s } => rows_per_s.is_finite() && rows_per_s >= 0.0,
        };
        if !ok {
            return Err(LineError::Config(format!("bad web motion {motion:?}")));
        }
        Ok(Registration {
            motion,
            origin: None,
        })
    }

    /// The web position (rows, fractional) of sensor row 0 in a frame with
    /// this encoder count and timestamp. A frame without the encoder count
    /// an encoder registration needs is an error.
    pub fn position(&mut self, encoder: Option<i64>, timestamp_ns: u64) -> Result<f64, LineError> {
        match self.motion {
            Motion::Encoder { rows_per_count } => {
                let c = encoder.ok_or(LineError::NoEncoder)?;
                Ok(c as f64 * rows_per_count)
            }
            Motion::Constant { rows_per_s } => {
                let t0 = *self.origin.get_or_insert(timestamp_ns);
                Ok(timestamp_ns.saturating_sub(t0) as f64 * 1e-9 * rows_per_s)
            }
        }
    }
}

/// The web row seen by sensor row 0 at position `p`.
pub fn first_row(p: f64) -> i64 {
    p.round() as i64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute force: frames every `step` rows (starting at `phase`), band
    /// `k mod n` on frame `k`; for each web row well inside the run, the
    /// bands it was seen in. Returns whether every such row saw every band.
    fn all_rows_complete(rows_in_view: usize, n: usize, step: f64, phase: f64) -> bool {
        let frames = 40 * n + (4.0 * rows_in_view as f64 / step.max(1e-9)) as usize;
        let mut seen: std::collections::BTreeMap<i64, Vec<bool>> = Default::default();
        for k in 0..frames {
            let first = first_row(phase + k as f64 * step);
            for y in 0..rows_in_view as i64 {
                seen.entry(first + y).or_insert_with(|| vec![false; n])[k % n] = true;
            }
        }
        let last_first = first_row(phase + (frames - 1) as f64 * step);
        // Rows that entered after the first frame and left before the last.
        seen.iter()
            .filter(|(&w, _)| w >= first_row(phase) + rows_in_view as i64 && w < last_first)
            .all(|(_, b)| b.iter().all(|&x| x))
    }

    #[test]
    fn limit_formula_matches_brute_force() {
        for &(h, n) in &[(8usize, 3usize), (16, 5), (31, 31), (40, 7), (64, 31)] {
            let g = LineGeometry::new(h, n, 20.0).unwrap();
            let step_max = g.max_speed() / g.band_rate_hz; // rows per frame
            assert!((step_max - h as f64 / n as f64).abs() < 1e-12);
            // At and below the limit, every phase gives complete rows.
            for &f in &[0.3, 0.7, 0.95, 1.0] {
                for ph in 0..7 {
                    let phase = ph as f64 / 7.0 + 0.013;
                    assert!(
                        all_rows_complete(h, n, step_max * f, phase),
                        "h {h} n {n} at {f} of the limit, phase {phase}: a row missed a band"
                    );
                }
            }
            // A little above it, some row misses a band for some phase.
            let over = step_max * 1.02;
            assert!(
                (0..7).any(|ph| !all_rows_complete(h, n, over, ph as f64 / 7.0 + 0.013)),
                "h {h} n {n}: 2% above the limit and every row still complete"
            );
        }
    }

    #[test]
    fn refuses_too_fast_with_numbers() {
        let g = LineGeometry::new(64, 31, 20.0).unwrap();
        assert!((g.max_speed() - 64.0 * 20.0 / 31.0).abs() < 1e-12);
        g.check_speed(g.max_speed()).unwrap();
        let e = g.check_speed(42.0).unwrap_err().to_string();
        for s in ["42", "41.29", "64", "20", "31"] {
            assert!(e.contains(s), "{e:?} lacks {s}");
        }
        assert!(g.check_speed(f64::NAN).is_err());
        assert!(LineGeometry::new(0, 31, 20.0).is_err());
        assert!(LineGeometry::new(10, 31, 0.0).is_err());
    }

    #[test]
    fn stepped_band_rate_counts_whole_frames() {
        // 10 ms frames, 8 ms exposure, 45 ms settle: the next usable frame
        // is 6 periods later (53 ms → 60 ms).
        let r = stepped_band_rate(10_000_000, 8_000_000, 45_000_000);
        assert!((r - 1e9 / 60e6).abs() < 1e-9);
        // Settling within the frame gap: one band per frame.
        assert!((stepped_band_rate(10_000_000, 5_000_000, 0) - 100.0).abs() < 1e-9);
    }

    #[test]
    fn registration_from_encoder_and_speed() {
        let mut r = Registration::new(Motion::Encoder {
            rows_per_count: 0.25,
        })
        .unwrap();
        assert_eq!(r.position(Some(100), 0).unwrap(), 25.0);
        assert_eq!(r.position(Some(140), 5).unwrap(), 35.0);
        assert!(matches!(r.position(None, 9), Err(LineError::NoEncoder)));
        let mut c = Registration::new(Motion::Constant { rows_per_s: 40.0 }).unwrap();
        assert_eq!(c.position(None, 1_000_000_000).unwrap(), 0.0);
        assert!((c.position(None, 1_500_000_000).unwrap() - 20.0).abs() < 1e-9);
        assert!(Registration::new(Motion::Encoder {
            rows_per_count: 0.0
        })
        .is_err());
    }
}
