//! A stage that fails stops the run: the error names the stage, sweeps
//! finished before the failure are written, and the run returns promptly
//! even when it was asked to run until stopped (no stage waits on a dead
//! one). Each stage is failed on its own, threaded and on one thread: the
//! camera through the fault wrapper, the sink by returning an error, and
//! ingest, solve and sink by an injected panic.

mod pipeline_common;

use irid::device::camera::faults::{FaultConfig, FaultySource};
use irid::device::camera::{CameraError, CameraInfo, Frame, FrameSource, Target};
use irid::pipeline::output::SweepSummary;
use irid::pipeline::runner::{run, CollectSink, RunConfig, RunError, SweepSink};
use irid::pipeline::stage::{Stage, StageFault};
use pipeline_common::*;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// How long a failed run may take to return after the failure. The issue
/// asks for a second; the threaded run may be inside one solve of this
/// 140 × 14 image (tens of ms) or one frame wait (2 ms frames) when it
/// notices, so a second is ample even on a loaded machine.
const PROMPT: Duration = Duration::from_secs(1);

/// A generous bound on whole runs that fail within their first sweeps
/// (a hang would never return).
const WHOLE_RUN: Duration = Duration::from_secs(20);

fn unbounded(single: bool, fault: Option<StageFault>) -> RunConfig {
    RunConfig {
        sweeps: None,
        fault,
        ..config(1, single)
    }
}

/// Records when its inner source first failed.
struct Clocked<S> {
    inner: S,
    failed_at: Arc<Mutex<Option<Instant>>>,
}

impl<S: FrameSource> FrameSource for Clocked<S> {
    fn info(&self) -> CameraInfo {
        self.inner.info()
    }
    fn next_frame(&mut self, out: &mut Frame, timeout: Duration) -> Result<(), CameraError> {
        let r = self.inner.next_frame(out, timeout);
        if r.is_err() {
            self.failed_at
                .lock()
                .unwrap()
                .get_or_insert_with(Instant::now);
        }
        r
    }
    fn set_exposure(&mut self, e: u32) -> Result<u32, CameraError> {
        self.inner.set_exposure(e)
    }
    fn set_gain(&mut self, g: f32) -> Result<f32, CameraError> {
        self.inner.set_gain(g)
    }
    fn set_target(&mut self, t: Target) -> Result<bool, CameraError> {
        self.inner.set_target(t)
    }
}

#[test]
fn a_camera_failure_ends_the_run_with_finished_sweeps_written() {
    for single in [true, false] {
        let mut r = rig(11, "ascending", false);
        r.cam.set_realtime(!single);
        let setup = r.setup(false);
        let cam = std::mem::replace(
            &mut r.cam,
            irid::device::camera::synthetic::SyntheticCamera::new(
                &r.scene,
                &r.bands,
                r.view.clone(),
                Default::default(),
            )
            .unwrap(),
        );
        let failed_at = Arc::new(Mutex::new(None));
        // Each band takes ~4 frames (2–3 exposed while the filter settles):
        // 300 frames are two sweeps and more, so at least the first is
        // solved by the time the camera fails.
        let mut src = Clocked {
            inner: FaultySource::new(cam, FaultConfig::fails_after(300)),
            failed_at: failed_at.clone(),
        };
        let mut sink = CollectSink::default();
        let stop = AtomicBool::new(false);
        let err = run(
            &mut src,
            &mut r.tuner,
            setup,
            &unbounded(single, None),
            &mut sink,
            &stop,
        )
        .unwrap_err();
        let returned = Instant::now();
        assert!(matches!(err, RunError::Camera(_)), "{err}");
        assert!(err.to_string().starts_with("camera: "), "{err}");
        let failed = failed_at.lock().unwrap().expect("the camera failed");
        // The sweep being solved when the camera failed is finished and
        // written (its latency bounds that solve); queued ones are dropped.
        let solve = sink
            .summaries
            .iter()
            .map(|s| Duration::from_secs_f64(s.latency_ms / 1e3))
            .max()
            .unwrap_or_default();
        assert!(
            returned - failed < PROMPT + solve,
            "single {single}: {:?} after the failure, a solve takes {solve:?}",
            returned - failed
        );
        assert!(
            !sink.summaries.is_empty(),
            "single {single}: finished sweeps written: {}",
            sink.summaries.len()
        );
    }
}

/// Fails on its `n + 1`-th map.
struct FailingSink {
    n: usize,
    seen: usize,
    failed_at: Option<Instant>,
}

impl SweepSink for FailingSink {
    fn on_sweep(&mut self, _: &SweepSummary, _: &irid::estimate::ParamMaps) -> Result<(), String> {
        if self.seen == self.n {
            self.failed_at = Some(Instant::now());
            return Err("writing out/sweep-000001.exr: No space left on device".into());
        }
        self.seen += 1;
        Ok(())
    }
}

#[test]
fn a_sink_error_ends_the_run_promptly() {
    for single in [true, false] {
        let mut r = rig(12, "ascending", false);
        let mut sink = FailingSink {
            n: 1,
            seen: 0,
            failed_at: None,
        };
        let stop = AtomicBool::new(false);
        let err = r
            .go(false, &unbounded(single, None), &mut sink, &stop)
            .unwrap_err();
        let returned = Instant::now();
        assert!(matches!(err, RunError::Sink(_)), "{err}");
        assert!(err.to_string().contains("No space left"), "{err}");
        assert_eq!(sink.seen, 1, "the first sweep was written");
        let failed = sink.failed_at.unwrap();
        assert!(returned - failed < PROMPT, "{:?}", returned - failed);
    }
}

/// Inject a panic into `stage` after `after` items; the run must return
/// the stage's name, having written `min_written` maps, quickly.
fn panics_in(stage: Stage, after: u64, min_written: usize) {
    for single in [true, false] {
        let mut r = rig(13, "ascending", false);
        let mut sink = CollectSink::default();
        let stop = AtomicBool::new(false);
        let t0 = Instant::now();
        let cfg = unbounded(single, Some(StageFault { stage, after }));
        let err = r.go(false, &cfg, &mut sink, &stop).unwrap_err();
        let took = t0.elapsed();
        match &err {
            RunError::Panicked { stage: s, message } => {
                assert_eq!(*s, stage, "{err}");
                assert!(message.contains("injected fault"), "{err}");
            }
            e => panic!("single {single}: expected a {stage} panic, got {e}"),
        }
        assert!(
            err.to_string()
                .contains(&format!("the {stage} stage failed")),
            "{err}"
        );
        assert!(
            sink.maps.len() >= min_written,
            "single {single}: {stage}: {} maps written, want ≥ {min_written}",
            sink.maps.len()
        );
        assert!(took < WHOLE_RUN, "single {single}: {stage}: {took:?}");
    }
}

#[test]
fn an_ingest_panic_is_reported_not_swallowed() {
    // 31 frames complete a sweep (stepped mode: only accepted frames reach
    // ingest); the panic comes in the second sweep, after the first is done.
    panics_in(Stage::Ingest, 40, 1);
}

#[test]
fn a_solve_panic_stops_the_run() {
    panics_in(Stage::Solve, 1, 1);
}

#[test]
fn a_sink_panic_stops_the_run() {
    panics_in(Stage::Sink, 1, 1);
}

#[test]
fn a_capture_panic_stops_the_run() {
    // ~4 frames per band: 200 frames are past the first sweep.
    panics_in(Stage::Capture, 200, 1);
}
