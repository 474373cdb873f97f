//! An ENVI reflectance cube as a one-sweep frame stream, so `irid replay`
//! feeds it through the live pipeline unchanged (capture, sequencer,
//! calibration, tracking, solve, sink) — a cube from another instrument is
//! processed exactly as a recorded sweep is.
//!
//! The stream is one priming frame (the sequencer's first frame only
//! commands the first band) and then one frame per band in plane order;
//! the filter settles the instant it is told ([`InstantTuner`]). Frames are
//! 16-bit counts `round(R·K)` with `K = 60 000 / max(1, max R)`, and the
//! calibration that goes with them (dark 0, white `K`, a white of
//! reflectance one) turns them back into `R` to within `1/(2K)`
//! (≤ 8.4·10⁻⁶ for a reflectance below 1: far under any camera's noise). A sample that is
//! not a number is flagged dead in the calibration, as a dead pixel is;
//! a negative one becomes 0.

use crate::device::camera::{CameraError, CameraInfo, Frame, FrameMeta, FrameSource, PixelFormat};
use crate::estimate::cube::Cube;
use crate::pipeline::calibration::{flag, Calibrator};
use crate::pipeline::sequencer::{BandTuner, TuneError};
use std::time::Duration;

/// Counts at the cube's largest reflectance (below 16-bit saturation).
const TOP_COUNTS: f64 = 60_000.0;
/// Exposure stamped on every frame and on the calibration, µs.
const EXPOSURE_US: u32 = 1000;
/// Time between frames on the stream's clock, ns.
const FRAME_PERIOD_NS: u64 = 1_000_000;

/// The frames of one cube.
pub struct CubeStream {
    cube: Cube,
    counts_per_unit: f64,
    /// Frames delivered (the first is the priming frame).
    next: usize,
    label: String,
}

impl CubeStream {
    /// The stream of `cube` (`label` names it in logs).
    pub fn new(cube: Cube, label: &str) -> CubeStream {
        let top = cube
            .data
            .iter()
            .filter(|v| v.is_finite())
            .fold(1.0f32, |a, &b| a.max(b));
        CubeStream {
            counts_per_unit: TOP_COUNTS / f64::from(top),
            cube,
            next: 0,
            label: label.to_string(),
        }
    }

    /// The calibration that turns the stream's counts back into the cube's
    /// reflectance.
    pub fn calibrator(&self) -> Calibrator {
        let n = self.cube.width * self.cube.height;
        let len = n * self.cube.bands.len();
        let white = vec![self.counts_per_unit as f32; len];
        let flags: Vec<u8> = self
            .cube
            .data
            .iter()
            .map(|v| if v.is_finite() { 0 } else { flag::DEAD })
            .collect();
        Calibrator::from_planes(n, vec![0.0; len], white, &flags, 1.0, EXPOSURE_US)
    }

    /// The cube's bands, in plane order.
    pub fn bands(&self) -> &[crate::optics::band::Band] {
        &self.cube.bands
    }
}

impl FrameSource for CubeStream {
    fn info(&self) -> CameraInfo {
        CameraInfo {
            id: format!("ENVI cube {}", self.label),
            width: self.cube.width as u32,
            height: self.cube.height as u32,
            format: PixelFormat::Y16,
            exposure_us: EXPOSURE_US,
            gain: 1.0,
        }
    }

    fn next_frame(&mut self, out: &mut Frame, _timeout: Duration) -> Result<(), CameraError> {
        let nb = self.cube.bands.len();
        if self.next > nb {
            return Err(CameraError::Ended);
        }
        let n = self.cube.width * self.cube.height;
        if out.data.len() < n {
            return Err(CameraError::BufferTooSmall {
                have: out.data.len(),
                need: n,
            });
        }
        // Frame 0 primes the sequencer (it commands band 0 and is
        // discarded as settling); frame k ≥ 1 is plane k − 1.
        let plane = self.next.saturating_sub(1);
        let src = &self.cube.data[plane * n..(plane + 1) * n];
        let k = self.counts_per_unit;
        for (o, &r) in out.data[..n].iter_mut().zip(src) {
            *o = if r.is_finite() {
                (f64::from(r.max(0.0)) * k)
                    .round()
                    .min(f64::from(u16::MAX - 1)) as u16
            } else {
                0
            };
        }
        out.meta = FrameMeta {
            seq: self.next as u64,
            timestamp_ns: self.next as u64 * FRAME_PERIOD_NS,
            exposure_us: EXPOSURE_US,
            gain: 1.0,
            format: PixelFormat::Y16,
            width: self.cube.width as u32,
            height: self.cube.height as u32,
            trigger: None,
            encoder: None,
        };
        self.next += 1;
        Ok(())
    }

    fn set_exposure(&mut self, _exposure_us: u32) -> Result<u32, CameraError> {
        Err(CameraError::Unsupported(
            "a cube's exposure is fixed".into(),
        ))
    }
}

/// A filter that has settled the moment it is told (the cube's planes are
/// already one band each).
pub struct InstantTuner;

impl BandTuner for InstantTuner {
    fn tune(&mut self, _nm: f64, now_ns: u64) -> Result<u64, TuneError> {
        Ok(now_ns)
    }

    fn describe(&self) -> String {
        "the cube's own bands".into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::band::Band;

    #[test]
    fn counts_and_calibration_give_back_the_reflectance() {
        let bands = vec![
            Band {
                center_nm: 500.0,
                fwhm_nm: 10.0,
            },
            Band {
                center_nm: 600.0,
                fwhm_nm: 10.0,
            },
        ];
        let mut cube = Cube::zeros(3, 1, bands);
        cube.data = vec![0.0, 0.25, 1.3, 0.7, f32::NAN, 0.001];
        let mut s = CubeStream::new(cube.clone(), "t");
        let cal = s.calibrator();
        let mut f = Frame::with_size(3, 1, PixelFormat::Y16);
        let mut out = [0.0f32; 3];
        s.next_frame(&mut f, Duration::ZERO).unwrap(); // priming
        for b in 0..2 {
            s.next_frame(&mut f, Duration::ZERO).unwrap();
            assert_eq!(f.meta.seq, b as u64 + 1);
            cal.apply(b, &f.data[..3], u16::MAX, EXPOSURE_US, &mut out);
            for (got, want) in out.iter().zip(&cube.data[b * 3..b * 3 + 3]) {
                if want.is_finite() {
                    // Half a count at K = 60 000 / 1.3.
                    assert!(
                        (got - want).abs() <= 0.5 * 1.3 / 60_000.0 + 1e-7,
                        "{got} vs {want}"
                    );
                } else {
                    assert!(got.is_nan(), "a NaN sample stays missing, got {got}");
                }
            }
        }
        assert!(matches!(
            s.next_frame(&mut f, Duration::ZERO),
            Err(CameraError::Ended)
        ));
    }
}
