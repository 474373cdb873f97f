//! Device timing constants and the time scale.
//!
//! The firmware core counts time in *device microseconds*, always passed in
//! by the caller. [`TimeScale`] maps wall-clock time onto device time so the
//! emulator (and therefore tests and the demo) can run a real unit's timings
//! faster: at scale 100 the 30 s initialisation takes 0.3 s of wall time.

use core::time::Duration;

/// Duration of `I` (initialise) on a real unit, in device µs.
pub const INITIALISE_US: u64 = 30_000_000;

/// Duration of one `E` (exercise) cycle, in device µs (irid's choice).
pub const EXERCISE_CYCLE_US: u64 = 2_000_000;

/// Ratio of device time to wall time (≥ 1 runs faster than a real unit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeScale {
    factor: f64,
}

impl TimeScale {
    /// Real-time: one device second per wall second.
    pub const REAL: Self = Self { factor: 1.0 };

    /// A scale `factor` times faster than real time. Non-finite or
    /// non-positive factors fall back to real time.
    pub fn new(factor: f64) -> Self {
        if factor.is_finite() && factor > 0.0 {
            Self { factor }
        } else {
            Self::REAL
        }
    }

    /// The factor.
    pub fn factor(&self) -> f64 {
        self.factor
    }

    /// Device µs elapsed after `wall` of wall-clock time.
    pub fn device_us(&self, wall: Duration) -> u64 {
        (wall.as_secs_f64() * 1e6 * self.factor) as u64
    }

    /// Wall-clock time that `device_us` of device time takes.
    pub fn wall(&self, device_us: u64) -> Duration {
        // Saturate rather than panic on absurd inputs.
        Duration::try_from_secs_f64(device_us as f64 / 1e6 / self.factor).unwrap_or(Duration::MAX)
    }
}

impl Default for TimeScale {
    fn default() -> Self {
        Self::REAL
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scale_round_trips() {
        let s = TimeScale::new(100.0);
        assert_eq!(s.device_us(Duration::from_millis(300)), INITIALISE_US);
        assert_eq!(s.wall(INITIALISE_US), Duration::from_millis(300));
        assert_eq!(TimeScale::new(f64::NAN), TimeScale::REAL);
        assert_eq!(TimeScale::new(-1.0), TimeScale::REAL);
    }
}
