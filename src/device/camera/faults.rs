//! A fault-injecting wrapper around any [`FrameSource`], after smoltcp's
//! `FaultInjector`: it drops, duplicates, reorders or corrupts frames on a
//! seeded schedule, so each fault test is one line.
//!
//! Faults act on what the wrapped source delivers, as a flaky driver or USB
//! link would: a dropped frame leaves a gap in the sequence numbers, a
//! duplicate repeats a frame verbatim, a reordered frame is held back and
//! delivered after its successor, a corrupted frame claims a size its buffer
//! does not have (the consumer must refuse it, not panic).

use super::{CameraError, CameraInfo, Frame, FrameSource, Target};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Duration;

/// Probabilities (0 … 1) of each fault per delivered frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FaultConfig {
    /// Lose the frame.
    pub drop: f64,
    /// Deliver the frame twice.
    pub duplicate: f64,
    /// Swap the frame with the next one.
    pub reorder: f64,
    /// Deliver a frame whose metadata does not match its buffer.
    pub corrupt: f64,
    /// Seed of the schedule.
    pub seed: u64,
    /// Deliver this many frames untouched first.
    pub after: u64,
    /// Fail (an I/O error, as an unplugged camera) once this many frames
    /// were delivered.
    pub fail_after: Option<u64>,
}

impl FaultConfig {
    /// Only drops, with probability `p`.
    pub fn drops(p: f64, seed: u64) -> Self {
        FaultConfig {
            drop: p,
            seed,
            ..Default::default()
        }
    }
    /// Only duplicates.
    pub fn duplicates(p: f64, seed: u64) -> Self {
        FaultConfig {
            duplicate: p,
            seed,
            ..Default::default()
        }
    }
    /// Only reordering.
    pub fn reorders(p: f64, seed: u64) -> Self {
        FaultConfig {
            reorder: p,
            seed,
            ..Default::default()
        }
    }
    /// A camera that fails after `n` frames.
    pub fn fails_after(n: u64) -> Self {
        FaultConfig {
            fail_after: Some(n),
            ..Default::default()
        }
    }
    /// Only corruption.
    pub fn corrupts(p: f64, seed: u64) -> Self {
        FaultConfig {
            corrupt: p,
            seed,
            ..Default::default()
        }
    }
}

/// Counts of faults injected so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FaultStats {
    /// Frames dropped.
    pub dropped: u64,
    /// Frames duplicated.
    pub duplicated: u64,
    /// Frames reordered.
    pub reordered: u64,
    /// Frames corrupted.
    pub corrupted: u64,
}

/// The wrapper. Holds two spare frame buffers (allocated once) for
/// duplicates and held-back frames.
pub struct FaultySource<S: FrameSource> {
    inner: S,
    cfg: FaultConfig,
    rng: ChaCha8Rng,
    /// A frame to deliver before asking the inner source again.
    pending: Option<Frame>,
    spare: Option<Frame>,
    stats: FaultStats,
    delivered: u64,
}

impl<S: FrameSource> FaultySource<S> {
    /// Wrap `inner`.
    pub fn new(inner: S, cfg: FaultConfig) -> Self {
        let info = inner.info();
        let spare = Frame::with_size(info.width, info.height, info.format);
        FaultySource {
            inner,
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            cfg,
            pending: None,
            spare: Some(spare),
            stats: FaultStats::default(),
            delivered: 0,
        }
    }

    /// Faults injected so far.
    pub fn stats(&self) -> FaultStats {
        self.stats
    }

    /// The wrapped source.
    pub fn inner_mut(&mut self) -> &mut S {
        &mut self.inner
    }

    fn roll(&mut self, p: f64) -> bool {
        self.delivered > self.cfg.after && p > 0.0 && self.rng.random::<f64>() < p
    }
}

fn copy_into(dst: &mut Frame, src: &Frame) {
    let n = dst.data.len().min(src.data.len());
    dst.meta = src.meta;
    dst.data[..n].copy_from_slice(&src.data[..n]);
}

impl<S: FrameSource> FrameSource for FaultySource<S> {
    fn info(&self) -> CameraInfo {
        self.inner.info()
    }

    fn next_frame(&mut self, out: &mut Frame, timeout: Duration) -> Result<(), CameraError> {
        if self.cfg.fail_after.is_some_and(|n| self.delivered >= n) {
            return Err(CameraError::Io(std::io::Error::other(
                "injected failure: the camera stopped answering",
            )));
        }
        if let Some(p) = self.pending.take() {
            let n = p.data.len().min(out.data.len());
            out.meta = p.meta;
            out.data[..n].copy_from_slice(&p.data[..n]);
            self.spare = Some(p);
            return Ok(());
        }
        loop {
            self.inner.next_frame(out, timeout)?;
            self.delivered += 1;
            if self.roll(self.cfg.drop) {
                self.stats.dropped += 1;
                continue;
            }
            break;
        }
        if self.roll(self.cfg.duplicate) {
            if let Some(mut s) = self.spare.take() {
                copy_into(&mut s, out);
                self.pending = Some(s);
                self.stats.duplicated += 1;
            }
        } else if self.roll(self.cfg.reorder) {
            if let Some(mut s) = self.spare.take() {
                // Hold this frame back; deliver its successor first.
                copy_into(&mut s, out);
                self.inner.next_frame(out, timeout)?;
                self.pending = Some(s);
                self.stats.reordered += 1;
            }
        }
        if self.roll(self.cfg.corrupt) {
            out.meta.height = out.meta.height.saturating_mul(2).max(1);
            self.stats.corrupted += 1;
        }
        Ok(())
    }

    fn set_exposure(&mut self, exposure_us: u32) -> Result<u32, CameraError> {
        self.inner.set_exposure(exposure_us)
    }

    fn set_gain(&mut self, gain: f32) -> Result<f32, CameraError> {
        self.inner.set_gain(gain)
    }

    fn set_target(&mut self, target: Target) -> Result<bool, CameraError> {
        self.inner.set_target(target)
    }
}
