//! The pipeline's stages by name, and what a failing stage leaves behind.
//!
//! A stage that panics or fails must not leave the others waiting for it:
//! each stage thread holds a [`HaltOnDrop`] guard that raises the shared
//! halt flag when the thread unwinds, every loop of the runner checks that
//! flag, and the run returns [`super::runner::RunError::Panicked`] naming the
//! stage. [`StageFault`] injects such a panic for tests (one stage, after a
//! given number of items), so each stage's failure path is exercised
//! without a broken camera or solver.

use std::sync::atomic::{AtomicBool, Ordering};

/// A stage of the live pipeline.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Camera, sequencer and filter controller.
    Capture,
    /// Calibration and tracking into sweep buffers.
    Ingest,
    /// The per-pixel estimation of a complete sweep.
    Solve,
    /// Writing maps and summaries.
    Sink,
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Stage::Capture => "capture",
            Stage::Ingest => "ingest",
            Stage::Solve => "solve",
            Stage::Sink => "sink",
        })
    }
}

/// A panic injected into one stage (tests): the stage panics on its
/// `after + 1`-th item (capture: frame, ingest: packet, solve: sweep,
/// sink: map).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StageFault {
    /// The stage that fails.
    pub stage: Stage,
    /// Items it handles before failing.
    pub after: u64,
}

impl StageFault {
    /// Count one item of `stage`; panic if this is the injected fault.
    pub(crate) fn check(fault: Option<StageFault>, stage: Stage, count: &mut u64) {
        if let Some(f) = fault {
            if f.stage == stage {
                if *count >= f.after {
                    panic!("injected fault in the {stage} stage");
                }
                *count += 1;
            }
        }
    }
}

/// Raises `flag` when dropped during a panic: a dying stage thread tells
/// the others to stop waiting for it.
pub(crate) struct HaltOnDrop<'a>(pub(crate) &'a AtomicBool);

impl Drop for HaltOnDrop<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.store(true, Ordering::SeqCst);
        }
    }
}

/// The message of a panic payload (`&str` or `String`; anything else is
/// described as such).
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic without a message".into()
    }
}

/// Run `f`, turning a panic into its message.
pub(crate) fn catch<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).map_err(|p| panic_message(&*p))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fault_fires_on_its_stage_after_its_count() {
        let f = Some(StageFault {
            stage: Stage::Solve,
            after: 2,
        });
        let mut n = 0;
        for _ in 0..10 {
            StageFault::check(f, Stage::Ingest, &mut n);
        }
        assert_eq!(n, 0, "another stage's items are not counted");
        let mut n = 0;
        assert!(catch(|| StageFault::check(f, Stage::Solve, &mut n)).is_ok());
        assert!(catch(|| StageFault::check(f, Stage::Solve, &mut n)).is_ok());
        let e = catch(|| StageFault::check(f, Stage::Solve, &mut n)).unwrap_err();
        assert_eq!(e, "injected fault in the solve stage");
    }

    #[test]
    fn the_guard_halts_only_when_unwinding() {
        let flag = AtomicBool::new(false);
        drop(HaltOnDrop(&flag));
        assert!(!flag.load(Ordering::SeqCst));
        let _ = catch(|| {
            let _g = HaltOnDrop(&flag);
            panic!("boom");
        });
        assert!(flag.load(Ordering::SeqCst));
    }
}
