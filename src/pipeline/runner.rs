//! Running the pipeline: capture → ingest (calibrate + track) → solve →
//! sink, threaded or on one thread.
//!
//! Threads and queues (threaded mode):
//!
//! ```text
//!  capture ──SPSC ring (Packet)──▶ ingest ──bounded(k) SweepBuf──▶ solve ──bounded(k) maps──▶ sink
//!     ▲ ◀──SPSC ring (free Frame)──┘  ▲ ◀────bounded free SweepBuf─┘  ▲ ◀──bounded free maps──┘
//! ```
//!
//! - The capture thread never blocks on processing: it takes an empty frame
//!   from a fixed pool (a lock-free `ringbuf` SPSC ring of buffers, sized
//!   once) and hands the filled frame on through another. When the pool is
//!   empty and the sequencer wanted the frame, processing is behind: the
//!   **whole sweep** in progress is abandoned (never a single band, silently),
//!   the sequencer restarts at the next sweep, and the drop is counted.
//! - Ingest fills a sweep buffer taken from a bounded pool of sweep buffers;
//!   if none is free when a sweep begins (the solver is behind), that whole
//!   sweep is skipped and counted.
//! - It does block on the filter controller: in stepped mode the sequencer
//!   commands each band over serial I/O from the capture thread and waits
//!   for the reply (with retries, up to the controller's timeout). Frames
//!   the camera exposes meanwhile were taken while the filter moved and are
//!   of no use; those the camera or its driver lost during such a call (a
//!   gap in its frame counter right after a tune) are counted apart, in
//!   [`RunReport::frames_lost_tuning`], not as faults.
//! - The solver solves a completed sweep's rows in parallel (rayon) and the
//!   map is complete before the next sweep's: sweeps are solved in order,
//!   one at a time.
//! - The sink writes maps in order.
//!
//! Single-threaded mode runs the same stages in one loop: the same seed and
//! configuration give bit-identical maps (only `latency_ms` differs).
//!
//! Stopping (Ctrl-C sets the stop flag): capture ends, the sweep in progress
//! is abandoned, every completed sweep is solved and written, and the run
//! returns normally.
//!
//! Failing (see [`super::stage`]): a stage that panics or returns an error
//! raises a halt flag every other stage checks, so nothing waits on a dead
//! stage; sweeps already solved are still written, and the run returns the
//! error, naming the stage ([`RunError::Panicked`] for a panic).

use super::calibration::Calibrator;
use super::output::SweepSummary;
use super::sequencer::{
    BandTuner, Discard, SeqMode, Sequencer, SequencerError, TuneError, Verdict,
};
use super::stage::{catch, HaltOnDrop, Stage, StageFault};
use super::tracker::{SweepBuf, TrackError, Tracker};
use crate::device::camera::{CameraError, Frame, FrameSource};
use crate::estimate::solver::Scratch;
use crate::estimate::{Cube, EstimateError, MapRowMut, Mode, ParamMaps, PixelEstimate, Solver};
use crate::optics::band::Band;
use crate::scene::Scene;
use ringbuf::traits::{Consumer, Producer, Split};
use ringbuf::HeapRb;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Errors that end a run.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The camera failed.
    #[error("camera: {0}")]
    Camera(#[from] CameraError),
    /// The filter or the sequencing failed.
    #[error("{0}")]
    Sequencer(#[from] SequencerError),
    /// The estimator could not be set up.
    #[error("estimator: {0}")]
    Estimate(#[from] EstimateError),
    /// The sink failed (writing a map).
    #[error("output: {0}")]
    Sink(String),
    /// Inconsistent set-up.
    #[error("pipeline: {0}")]
    Config(String),
    /// A stage panicked (a bug): the run was stopped.
    #[error("the {stage} stage failed: {message}")]
    Panicked {
        /// The stage.
        stage: Stage,
        /// The panic's message.
        message: String,
    },
}

/// Where finished maps go.
pub trait SweepSink: Send {
    /// One finished sweep, in order.
    fn on_sweep(&mut self, summary: &SweepSummary, maps: &ParamMaps) -> Result<(), String>;
}

/// Receives a sweep's map rows as they are solved, in order, on the solve
/// thread, before the sweep's map is complete. A moving-web mode emits map
/// rows at line rate through this; a static scene may ignore it.
pub trait RowSink {
    /// Rows `rows` of sweep `sweep` are final in `maps`.
    fn on_rows(&mut self, sweep: u64, rows: std::ops::Range<usize>, maps: &ParamMaps);
}

/// A [`RowSink`] that ignores rows.
pub struct NoRows;

impl RowSink for NoRows {
    fn on_rows(&mut self, _: u64, _: std::ops::Range<usize>, _: &ParamMaps) {}
}

/// Sees, on the capture thread, every frame capture reads and what the
/// sequencer made of it (a recorder). It must not block: capture never
/// waits for it.
pub trait CaptureTap: Send {
    /// A frame read from the camera, with the sequencer's verdict, or
    /// `None` when the frame was paired but its sweep was abandoned because
    /// processing is behind.
    fn on_frame(&mut self, frame: &Frame, verdict: Option<Verdict>);
    /// A band slot given up (triggered mode gap).
    fn on_missing(&mut self, sweep: u64, band: usize);
    /// A whole sweep given up because processing fell behind.
    fn on_abandoned(&mut self, sweep: u64);
}

/// A sink that keeps everything (tests).
#[derive(Default)]
pub struct CollectSink {
    /// Summaries.
    pub summaries: Vec<SweepSummary>,
    /// Maps.
    pub maps: Vec<ParamMaps>,
}

impl SweepSink for CollectSink {
    fn on_sweep(&mut self, summary: &SweepSummary, maps: &ParamMaps) -> Result<(), String> {
        self.summaries.push(summary.clone());
        self.maps.push(maps.clone());
        Ok(())
    }
}

/// What to run.
pub struct Setup {
    /// The scene (knowledge for the solver).
    pub scene: Scene,
    /// Bands, in plane order.
    pub bands: Vec<Band>,
    /// Capture order (band indices).
    pub order: Vec<usize>,
    /// Stepped or triggered.
    pub seq_mode: SeqMode,
    /// Counts → reflectance.
    pub calibrator: Calibrator,
}

/// How to run.
#[derive(Clone, Debug)]
pub struct RunConfig {
    /// Sweeps to complete (None: until stopped).
    pub sweeps: Option<u64>,
    /// Solver mode.
    pub mode: Mode,
    /// Solver threads (None: rayon's default).
    pub threads: Option<usize>,
    /// Everything on the calling thread, deterministically.
    pub single_thread: bool,
    /// Frame buffers in the capture pool.
    pub frame_pool: usize,
    /// Sweep buffers (one filling, the others queued or solving).
    pub sweep_buffers: usize,
    /// How long to wait for a frame before giving up.
    pub frame_timeout: Duration,
    /// Track every pixel's fringe-extremum candidates while bands arrive
    /// (see [`crate::pipeline::tracker`]): `fast` then skips its detection
    /// pass after the last band, at a cost on each frame's ingest that on
    /// two cores outweighs what it saves (off by default).
    pub track_extrema: bool,
    /// Rows solved (in parallel) and emitted together; 0: a sixteenth of
    /// the image.
    pub row_block: usize,
    /// A panic injected into one stage (tests of the failure paths).
    #[doc(hidden)]
    pub fault: Option<StageFault>,
    /// Never drop for back-pressure: capture waits for a free frame buffer
    /// and ingest for a free sweep buffer (a replay, whose source can
    /// always wait, must not lose what the live run kept).
    pub lossless: bool,
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            sweeps: Some(3),
            mode: Mode::Balanced,
            threads: None,
            single_thread: false,
            frame_pool: 32,
            sweep_buffers: 3,
            frame_timeout: Duration::from_secs(2),
            track_extrema: false,
            row_block: 0,
            fault: None,
            lossless: false,
        }
    }
}

/// What happened in a run.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunReport {
    /// Maps delivered to the sink.
    pub sweeps_completed: u64,
    /// Whole sweeps dropped (processing behind, or stopped mid-sweep).
    pub sweeps_dropped: u64,
    /// Frames lost, refused, duplicated or stale.
    pub frames_dropped: u64,
    /// Frames discarded because the filter was settling.
    pub frames_settling: u64,
    /// Frames read from the camera.
    pub frames_total: u64,
    /// Frames the camera lost while capture waited on the filter
    /// controller (stepped mode; taken while the filter moved, so of no
    /// use, and not counted in `frames_dropped`).
    pub frames_lost_tuning: u64,
    /// Frames read while capture held the second sweep back until the
    /// first sweep's set-up (film index, noise, level) was done, or a
    /// later sweep's look again ([`RunReport::relooks`]).
    pub frames_held: u64,
    /// Sweeps on which the film index, noise, level and band shift were
    /// estimated again because the calibration (the level or the band
    /// centres) had moved or poor fits rose.
    pub relooks: u64,
    /// Whether the run was stopped early.
    pub stopped: bool,
}

#[derive(Default)]
struct Counters {
    frames_dropped: AtomicU64,
    sweeps_dropped: AtomicU64,
    frames_settling: AtomicU64,
    frames_total: AtomicU64,
    frames_lost_tuning: AtomicU64,
    frames_held: AtomicU64,
    relooks: AtomicU64,
    /// Raised before the run where the first sweep must establish the film
    /// index, the noise or the level, lowered by solve when that is done:
    /// meanwhile capture holds the second sweep back (stepped mode) or
    /// skips the sweeps that start (triggered), so none queues behind the
    /// set-up, and the first sweep after it is fresh.
    setup_hold: AtomicBool,
}

/// A tuner that notes whether it was called (capture then knows a gap in
/// the camera's frame counter fell while it waited on the controller).
struct NoteTuning<'a> {
    inner: &'a mut dyn BandTuner,
    tuned: bool,
}

impl BandTuner for NoteTuning<'_> {
    fn tune(&mut self, nm: f64, now_ns: u64) -> Result<u64, TuneError> {
        self.tuned = true;
        self.inner.tune(nm, now_ns)
    }
    fn describe(&self) -> String {
        self.inner.describe()
    }
}

/// What capture hands ingest.
enum Packet {
    Frame {
        sweep: u64,
        band: usize,
        frame: Frame,
    },
    Missing {
        sweep: u64,
        band: usize,
    },
    Abandoned {
        sweep: u64,
    },
    /// A sweep not taken while the first sweep's set-up was done
    /// (triggered mode): not wanted, and not a drop.
    Skipped {
        sweep: u64,
    },
    End,
}

/// The capture stage: camera + sequencer + filter.
struct Capture<'a> {
    source: &'a mut dyn FrameSource,
    tuner: &'a mut dyn BandTuner,
    seq: Sequencer,
    spare: Frame,
    timeout: Duration,
    last_seq: Option<u64>,
    counters: Arc<Counters>,
    width: u32,
    height: u32,
    /// The last frame's handling called the filter controller.
    after_tune: bool,
    fault: Option<StageFault>,
    handled: u64,
    tap: Option<&'a mut dyn CaptureTap>,
    /// The sweep in progress was skipped for the set-up (triggered mode).
    skipping: bool,
}

enum Step {
    Continue,
    Done,
}

impl Capture<'_> {
    /// Capture one frame into a pooled buffer (`buf`, or the spare when the
    /// pool is empty) and emit what it means.
    fn step(
        &mut self,
        buf: Option<Frame>,
        emit: &mut dyn FnMut(Packet),
        recycle: &mut dyn FnMut(Frame),
    ) -> Result<Step, RunError> {
        if self.seq.finished() {
            if let Some(b) = buf {
                recycle(b);
            }
            return Ok(Step::Done);
        }
        if self.counters.setup_hold.load(Ordering::Acquire) && self.seq.at_sweep_start() {
            return self.hold(buf, recycle);
        }
        let (pooled, mut frame) = self.take_frame(buf);
        let _span = tracing::info_span!("capture.frame").entered();
        StageFault::check(self.fault, Stage::Capture, &mut self.handled);
        // A frame the sequencer will discard as exposed while the filter
        // settled is never read (copied out of the driver, or rendered),
        // unless a tap (a recording) keeps every frame.
        let seq = &self.seq;
        let skip_settling = self.tap.is_none();
        let got = self
            .source
            .next_frame_if(&mut frame, self.timeout, &mut |m| {
                !(skip_settling && seq.discards_as_settling(m))
            });
        self.counters.frames_total.fetch_add(1, Ordering::Relaxed);
        let result = match got {
            Ok(filled) => {
                let m = frame.meta;
                // Gaps in the camera's counter are frames lost before us.
                if let Some(last) = self.last_seq {
                    if m.seq > last + 1 {
                        let lost = if self.after_tune {
                            &self.counters.frames_lost_tuning
                        } else {
                            &self.counters.frames_dropped
                        };
                        lost.fetch_add(m.seq - last - 1, Ordering::Relaxed);
                    }
                }
                self.last_seq = Some(self.last_seq.map_or(m.seq, |l| l.max(m.seq)));
                let valid =
                    frame.pixels().is_ok() && (m.width, m.height) == (self.width, self.height);
                let mut tuner = NoteTuning {
                    inner: &mut *self.tuner,
                    tuned: false,
                };
                let mut tap = self.tap.as_deref_mut();
                let v = self.seq.on_frame(&m, valid, &mut tuner, &mut |x| {
                    if let Some(t) = tap.as_deref_mut() {
                        t.on_missing(x.sweep, x.band);
                    }
                    emit(Packet::Missing {
                        sweep: x.sweep,
                        band: x.band,
                    })
                });
                self.after_tune = tuner.tuned;
                let v = v?;
                debug_assert!(filled || v == Verdict::Discard(Discard::Settling));
                if let Verdict::Accept { sweep, .. } = v {
                    self.skipping = false;
                    if sweep > 0 && self.counters.setup_hold.load(Ordering::Acquire) {
                        // Triggered mode: the controller cycles on its own,
                        // so a sweep that starts during the set-up is not
                        // taken (the stepped sequence is held instead).
                        let s = self.seq.skip_sweep(self.tuner, m.timestamp_ns)?;
                        self.skipping = true;
                        self.counters.frames_held.fetch_add(1, Ordering::Relaxed);
                        if let Some(t) = self.tap.as_deref_mut() {
                            t.on_frame(&frame, Some(Verdict::Discard(Discard::Held)));
                        }
                        emit(Packet::Skipped { sweep: s });
                        self.give_back(pooled, frame, recycle);
                        return Ok(Step::Continue);
                    }
                }
                if let Some(t) = tap {
                    let paired = pooled || !matches!(v, Verdict::Accept { .. });
                    t.on_frame(&frame, paired.then_some(v));
                }
                match v {
                    Verdict::Accept { sweep, band } if pooled => {
                        emit(Packet::Frame { sweep, band, frame });
                        return Ok(Step::Continue);
                    }
                    Verdict::Accept { .. } => {
                        // No buffer: processing is behind. Drop the sweep.
                        let now = m.timestamp_ns + u64::from(m.exposure_us) * 1000;
                        let s = self.seq.abandon_sweep(self.tuner, now)?;
                        self.after_tune = true;
                        tracing::warn!(sweep = s, "frame pool empty: sweep abandoned");
                        self.counters.frames_dropped.fetch_add(1, Ordering::Relaxed);
                        if let Some(t) = self.tap.as_deref_mut() {
                            t.on_abandoned(s);
                        }
                        emit(Packet::Abandoned { sweep: s });
                    }
                    Verdict::Discard(Discard::Settling) => {
                        self.counters
                            .frames_settling
                            .fetch_add(1, Ordering::Relaxed);
                    }
                    Verdict::Discard(Discard::Bad | Discard::Stale) => {
                        self.counters.frames_dropped.fetch_add(1, Ordering::Relaxed);
                    }
                    Verdict::Discard(Discard::Abandoned) if self.skipping => {
                        self.counters.frames_held.fetch_add(1, Ordering::Relaxed);
                    }
                    Verdict::Discard(Discard::Abandoned | Discard::Done | Discard::Held) => {}
                }
                Ok(Step::Continue)
            }
            Err(e) => self.read_failed(e),
        };
        self.give_back(pooled, frame, recycle);
        result
    }

    /// A failed read: a bad frame is counted and skipped, a recording's
    /// end ends the run normally, anything else is the camera's error.
    fn read_failed(&self, e: CameraError) -> Result<Step, RunError> {
        match e {
            CameraError::BadFrame { seq, message } => {
                tracing::warn!(seq, %message, "bad frame");
                self.counters.frames_dropped.fetch_add(1, Ordering::Relaxed);
                Ok(Step::Continue)
            }
            CameraError::Ended => Ok(Step::Done),
            e => Err(RunError::Camera(e)),
        }
    }

    /// The frame to read into: `buf` from the pool (true), or the spare.
    fn take_frame(&mut self, buf: Option<Frame>) -> (bool, Frame) {
        let format = self.spare.meta.format;
        // An empty Vec does not allocate.
        let spare = || std::mem::replace(&mut self.spare, Frame::with_size(0, 0, format));
        (buf.is_some(), buf.unwrap_or_else(spare))
    }

    /// A frame not passed on: back to the pool, or kept as the spare.
    fn give_back(&mut self, pooled: bool, frame: Frame, recycle: &mut dyn FnMut(Frame)) {
        if pooled {
            recycle(frame);
        } else {
            self.spare = frame;
        }
    }

    /// Read one frame and discard it as held: the camera keeps running (its
    /// driver's queue never overflows) and no pixel is copied. The filter
    /// waits, settled, on the next sweep's first band, so the first frame
    /// read after the hold starts that sweep. A recording keeps a held
    /// frame's metadata and verdict, not its pixels: a replay never sees
    /// it, and pairs the next frame as the live run did.
    fn hold(
        &mut self,
        buf: Option<Frame>,
        recycle: &mut dyn FnMut(Frame),
    ) -> Result<Step, RunError> {
        let (pooled, mut frame) = self.take_frame(buf);
        let got = self
            .source
            .next_frame_if(&mut frame, self.timeout, &mut |_| false);
        self.counters.frames_total.fetch_add(1, Ordering::Relaxed);
        let result = match got {
            Ok(_) => {
                let m = frame.meta;
                if let Some(last) = self.last_seq {
                    if m.seq > last + 1 {
                        // Lost while held: of no use either way.
                        self.counters
                            .frames_held
                            .fetch_add(m.seq - last - 1, Ordering::Relaxed);
                    }
                }
                self.last_seq = Some(self.last_seq.map_or(m.seq, |l| l.max(m.seq)));
                self.counters.frames_held.fetch_add(1, Ordering::Relaxed);
                if let Some(t) = self.tap.as_deref_mut() {
                    t.on_frame(&frame, Some(Verdict::Discard(Discard::Held)));
                }
                Ok(Step::Continue)
            }
            Err(e) => self.read_failed(e),
        };
        self.give_back(pooled, frame, recycle);
        result
    }
}

/// Free sweep buffers.
trait SweepPool {
    fn take(&mut self) -> Option<SweepBuf>;
    fn give(&mut self, b: SweepBuf);
}

impl SweepPool for Vec<SweepBuf> {
    fn take(&mut self) -> Option<SweepBuf> {
        self.pop()
    }
    fn give(&mut self, b: SweepBuf) {
        self.push(b);
    }
}

struct ChannelPool {
    rx: crossbeam_channel::Receiver<SweepBuf>,
    tx: crossbeam_channel::Sender<SweepBuf>,
    /// Wait for the solver to free a buffer rather than skip a sweep.
    wait: bool,
}

impl SweepPool for ChannelPool {
    fn take(&mut self) -> Option<SweepBuf> {
        if self.wait {
            // The solver always hands its buffer back: this ends.
            return self.rx.recv().ok();
        }
        self.rx.try_recv().ok()
    }
    fn give(&mut self, b: SweepBuf) {
        // Bounded by the number of buffers: never full.
        let _ = self.tx.try_send(b);
    }
}

/// The ingest stage: calibration + tracking into sweep buffers.
struct Ingest {
    tracker: Tracker,
    cal: Calibrator,
    current: Option<SweepBuf>,
    /// Sweeps at or below this are not wanted any more.
    floor: Option<u64>,
    counters: Arc<Counters>,
    fault: Option<StageFault>,
    handled: u64,
}

impl Ingest {
    fn drop_current(&mut self, pool: &mut dyn SweepPool) {
        if let Some(b) = self.current.take() {
            self.counters.sweeps_dropped.fetch_add(1, Ordering::Relaxed);
            self.floor = Some(b.sweep);
            pool.give(b);
        }
    }

    /// Handle one packet; a completed sweep goes to `done`; a frame buffer
    /// is returned for recycling.
    fn on_packet(
        &mut self,
        p: Packet,
        pool: &mut dyn SweepPool,
        done: &mut dyn FnMut(SweepBuf, Instant),
    ) -> Option<Frame> {
        StageFault::check(self.fault, Stage::Ingest, &mut self.handled);
        let (sweep, band, frame) = match p {
            Packet::End => {
                // An incomplete sweep at the end is abandoned.
                self.drop_current(pool);
                return None;
            }
            Packet::Abandoned { sweep } => {
                if self.current.as_ref().is_some_and(|b| b.sweep == sweep) {
                    self.drop_current(pool);
                } else {
                    self.counters.sweeps_dropped.fetch_add(1, Ordering::Relaxed);
                }
                self.floor = Some(self.floor.map_or(sweep, |f| f.max(sweep)));
                return None;
            }
            Packet::Skipped { sweep } => {
                self.floor = Some(self.floor.map_or(sweep, |f| f.max(sweep)));
                return None;
            }
            Packet::Missing { sweep, band } => (sweep, band, None),
            Packet::Frame { sweep, band, frame } => (sweep, band, Some(frame)),
        };
        let _span = tracing::info_span!("ingest.frame", sweep, band).entered();
        let stale = self.floor.is_some_and(|f| sweep <= f)
            || self.current.as_ref().is_some_and(|b| sweep < b.sweep);
        if stale {
            if frame.is_some() {
                self.counters.frames_dropped.fetch_add(1, Ordering::Relaxed);
            }
            return frame;
        }
        if self.current.as_ref().is_some_and(|b| b.sweep < sweep) {
            // A later sweep began before this one completed: abandon it.
            self.drop_current(pool);
        }
        if self.current.is_none() {
            match pool.take() {
                Some(mut b) => {
                    self.tracker.begin(&mut b, sweep);
                    self.current = Some(b);
                }
                None => {
                    // The solver is behind: skip this whole sweep.
                    tracing::warn!(sweep, "no free sweep buffer: sweep dropped");
                    self.counters.sweeps_dropped.fetch_add(1, Ordering::Relaxed);
                    self.floor = Some(sweep);
                    if frame.is_some() {
                        self.counters.frames_dropped.fetch_add(1, Ordering::Relaxed);
                    }
                    return frame;
                }
            }
        }
        let buf = self.current.as_mut().expect("set above");
        let r: Result<bool, TrackError> = match &frame {
            Some(f) => self.tracker.ingest(buf, band, f, &self.cal),
            None => self.tracker.mark_missing(buf, band),
        };
        match r {
            Ok(true) => {
                let b = self.current.take().expect("set above");
                done(b, Instant::now());
            }
            Ok(false) => {}
            Err(e) => {
                tracing::warn!(%e, "frame refused");
                buf.frames_dropped += 1;
                self.counters.frames_dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
        frame
    }
}

/// The solve stage.
struct Solve {
    solver: Solver,
    scratch: Scratch,
    /// Rows solved (in parallel) and emitted together.
    block: usize,
    index_tried: bool,
    /// The sweep corrected by the image-wide level, when one is in force
    /// (allocated on first use, reused after).
    level_buf: Option<Cube>,
    /// One block of rows' estimates (each row is written into the maps by
    /// the thread that solved it).
    estimates: Vec<PixelEstimate>,
    counters: Arc<Counters>,
    reported_frames: u64,
    reported_sweeps: u64,
    fault: Option<StageFault>,
    handled: u64,
    /// Whether the look again on a later sweep may hold capture back
    /// (threaded, not lossless: as the first sweep's set-up).
    hold_allowed: bool,
    drift: Drift,
}

/// When to look at the image-wide estimates again on a live run
/// ([`Solver::level_drift`], and the sweep's poor fits).
#[derive(Debug)]
struct Drift {
    /// The poor-fit fraction of the first sweep solved after the last
    /// look: what this scene shows under its calibration.
    baseline: Option<f64>,
    /// The last sweep's poor fits rose beyond [`POOR_ROSE`] of it.
    poor_rose: bool,
    /// The last sweep's poor-fit fraction.
    last: f64,
    /// Sweeps to pass before the next check.
    wait: u64,
    /// One more than the sweeps to wait after a look before the next
    /// check: 1 after a check that passed, doubling with every look the
    /// next check does not clear, up to [`MAX_RELOOK_WAIT`], so a change no
    /// look can model costs a look now and then, not every sweep.
    backoff: u64,
    /// The last sweep's estimates came from a look that saw a change
    /// (provisional: the change may have straddled that sweep, whose bands
    /// then saw both sides of it); this sweep estimates them again.
    confirm: bool,
    /// That look saw a gain or an offset
    /// ([`crate::estimate::solver::LevelDrift::is_level`]).
    level_moved: bool,
}

/// The poor fits have risen where their fraction exceeds this many times
/// the baseline's, and [`MIN_POOR_FRACTION`] (a filter's pass bands
/// drifting moves every pixel's fringes; the χ² test flags ~1 % of clean
/// pixels).
const POOR_ROSE: f64 = 3.0;
const MIN_POOR_FRACTION: f64 = 0.05;
const MAX_RELOOK_WAIT: u64 = 64;

impl Drift {
    fn new() -> Drift {
        Drift {
            baseline: None,
            poor_rose: false,
            last: 0.0,
            wait: 0,
            backoff: 1,
            confirm: false,
            level_moved: false,
        }
    }

    /// Note a solved sweep's maps: its poor fits among its judged pixels.
    fn note(&mut self, maps: &ParamMaps) {
        let poor_code = crate::estimate::Reason::PoorFit as u8 as f32;
        let (mut poor, mut judged) = (0usize, 0usize);
        for (&v, &r) in maps.valid.iter().zip(&maps.reason) {
            let p = r == poor_code;
            poor += usize::from(p);
            judged += usize::from(p || v > 0.5);
        }
        if judged == 0 {
            return;
        }
        let f = poor as f64 / judged as f64;
        self.last = f;
        match self.baseline {
            None => self.baseline = Some(f),
            Some(b) => self.poor_rose = f > MIN_POOR_FRACTION.max(POOR_ROSE * b),
        }
    }
}

impl Solve {
    fn solve(
        &mut self,
        buf: &SweepBuf,
        maps: &mut ParamMaps,
        pool: Option<&rayon::ThreadPool>,
        rows: &mut dyn RowSink,
    ) -> SweepSummary {
        let _span = tracing::info_span!("solve.sweep", sweep = buf.sweep).entered();
        StageFault::check(self.fault, Stage::Solve, &mut self.handled);
        let cube = &buf.cube;
        // The film index where unknown, and in every case the noise level
        // and the image-wide level the fits are judged against (a known
        // film still needs them: without, no pixel would be judged).
        let set_up = self
            .solver
            .film_index()
            .is_none_or(|i| !i.noise_sigma.is_finite());
        if set_up {
            let _s = tracing::info_span!("solve.index").entered();
            match self.solver.estimate_film_index(cube) {
                Ok(est) => {
                    if let Err(e) = self.solver.set_film_index(est) {
                        tracing::warn!(%e, "film index not usable");
                    }
                }
                Err(e) => {
                    if !self.index_tried {
                        tracing::warn!(%e, "film index not estimated on this sweep; trying again on the next");
                    }
                }
            }
            self.index_tried = true;
        }
        // The set-up is done (or failed, and is tried again on the next
        // sweep without holding capture back): the next sweep may start.
        self.counters.setup_hold.store(false, Ordering::Release);
        let relook = if set_up {
            None
        } else {
            self.look_again(cube, buf.sweep)
        };
        // Pixels are solved on data corrected by the image-wide level, when
        // one is in force (`scaled`, or `auto` that chose it).
        let cube = if self.solver.level().0.is_identity() {
            &buf.cube
        } else {
            let dst = self
                .level_buf
                .get_or_insert_with(|| Cube::zeros(0, 0, Vec::new()));
            self.solver.correct_into(&buf.cube, dst);
            &*dst
        };
        let (w, h) = (cube.width, cube.height);
        let solver = &self.solver;
        let candidates = buf.candidates.as_ref();
        // Row blocks in order: rows within a block are solved in parallel,
        // and each block is emitted as soon as it is done, so at most one
        // block is in flight and rows leave in order.
        let block = self.block;
        let mut y0 = 0;
        while y0 < h {
            let y1 = (y0 + block).min(h);
            let est = &mut self.estimates[..(y1 - y0) * w];
            // Each row is solved and written into its row of the maps by
            // the same thread (no serial copy after the block).
            let mut map_rows = maps.rows_mut(y0..y1);
            let run_rows = |est: &mut [PixelEstimate], map_rows: &mut [MapRowMut<'_>]| {
                use rayon::prelude::*;
                est.par_chunks_mut(w.max(1))
                    .zip(map_rows.par_iter_mut())
                    .enumerate()
                    .for_each_init(Scratch::default, |scr, (dy, (row, out))| {
                        solver.solve_row_with(cube, y0 + dy, row, scr, candidates);
                        out.set_all(row);
                    });
            };
            match pool {
                Some(p) => p.install(|| run_rows(est, &mut map_rows)),
                None => {
                    for (dy, (row, out)) in est.chunks_mut(w.max(1)).zip(&mut map_rows).enumerate()
                    {
                        solver.solve_row_with(cube, y0 + dy, row, &mut self.scratch, candidates);
                        out.set_all(row);
                    }
                }
            }
            drop(map_rows);
            rows.on_rows(buf.sweep, y0..y1, maps);
            y0 = y1;
        }
        // Per sweep, not per frame: the small allocations here are fine.
        maps.meta = self.solver.map_meta();
        if self.solver.film_index().is_none() {
            maps.meta.n_film_note = "film index not available".into();
        }
        let mut s = SweepSummary::from_maps(buf.sweep, maps);
        let fd = self.counters.frames_dropped.load(Ordering::Relaxed);
        let sd = self.counters.sweeps_dropped.load(Ordering::Relaxed);
        s.frames_dropped = fd - self.reported_frames;
        s.sweeps_dropped = sd - self.reported_sweeps;
        (self.reported_frames, self.reported_sweeps) = (fd, sd);
        s.missing_bands = buf.missing();
        s.relook = relook;
        self.drift.note(maps);
        s
    }

    /// On a sweep after the set-up: where the level or the band centres
    /// have moved since they were estimated ([`Solver::level_drift`]) or
    /// the last sweep's poor fits rose, estimate the film index,
    /// noise, level and band shift again on this sweep before solving it,
    /// holding capture back meanwhile as for the set-up. Returns why, and
    /// what they came to.
    fn look_again(&mut self, cube: &Cube, sweep: u64) -> Option<String> {
        self.solver.film_index()?;
        let confirm = std::mem::take(&mut self.drift.confirm);
        if self.drift.wait > 0 && !confirm {
            self.drift.wait -= 1;
            return None;
        }
        let mut level_moved = confirm && self.drift.level_moved;
        let why = if confirm {
            "confirming the last look's estimates on the sweep after it (the change may have straddled that one)".to_string()
        } else if self.drift.poor_rose {
            format!(
                "poor fits rose to {:.1} % of the judged pixels (from {:.1} % after the last look)",
                100.0 * self.drift.last,
                100.0 * self.drift.baseline.unwrap_or(0.0)
            )
        } else {
            let _s = tracing::info_span!("solve.drift").entered();
            match self.solver.level_drift(cube) {
                Some(d) if d.moved() => {
                    level_moved = d.is_level();
                    format!("the calibration moved: {}", d.describe())
                }
                _ => {
                    // The estimates in force explain this sweep: a flag a
                    // straddled sweep's look left is lifted.
                    self.solver.clear_calibration_flag();
                    self.drift.backoff = 1;
                    return None;
                }
            }
        };
        if self.hold_allowed {
            self.counters.setup_hold.store(true, Ordering::Release);
        }
        let looked = {
            let _s = tracing::info_span!("solve.relook").entered();
            self.solver.estimate_again(cube, level_moved)
        };
        self.counters.setup_hold.store(false, Ordering::Release);
        self.counters.relooks.fetch_add(1, Ordering::Relaxed);
        self.drift.baseline = None;
        self.drift.poor_rose = false;
        // The next sweep is checked again (the change may have straddled
        // this one, whose level then fits neither side of it); a check that
        // fires again waits longer before its look.
        self.drift.wait = self.drift.backoff - 1;
        self.drift.backoff = (2 * self.drift.backoff).min(MAX_RELOOK_WAIT);
        // Estimates from a sweep a change may have straddled are
        // provisional: this sweep is flagged, and the next estimates them
        // again (a confirmation is not itself confirmed).
        self.drift.confirm = !confirm;
        self.drift.level_moved = level_moved;
        let outcome = match looked {
            Ok(still) => {
                let (level, mode, _) = self.solver.level();
                let (g, o) = level.mean();
                let n = self.solver.film_index().map_or(f64::NAN, |i| i.n);
                let now = format!(
                    "now n = {n:.4}, level {} (mean gain {g:.4}, offset {o:+.5}), band shift {:+.2} nm",
                    mode.name(),
                    self.solver.band_shift().0
                );
                match still {
                    Some(d) => {
                        // The estimates just made do not explain the sweep
                        // they came from: flagged, and the next sweep
                        // looked at at once.
                        let why = format!(
                            "these estimates do not explain the sweep either ({})",
                            d.describe()
                        );
                        self.solver.flag_calibration(&why);
                        self.drift.wait = 0;
                        self.drift.backoff = 1;
                        format!("{now}; {why}: every pixel flagged")
                    }
                    None if !confirm => {
                        let why = "provisional until the next sweep confirms them";
                        self.solver.flag_calibration(why);
                        format!("{now}; {why}: every pixel flagged")
                    }
                    None => now,
                }
            }
            Err(e) => format!("not estimated again ({e})"),
        };
        tracing::info!(sweep, %why, %outcome, "image-wide estimates looked at again");
        Some(format!("{why}; {outcome}"))
    }
}

/// Run the pipeline until `cfg.sweeps` maps are delivered, the stop flag is
/// set, or an error occurs. Completed sweeps are always flushed to the sink.
pub fn run(
    source: &mut dyn FrameSource,
    tuner: &mut dyn BandTuner,
    setup: Setup,
    cfg: &RunConfig,
    sink: &mut dyn SweepSink,
    stop: &AtomicBool,
) -> Result<RunReport, RunError> {
    run_with_rows(source, tuner, setup, cfg, sink, &mut NoRows, stop)
}

/// [`run`], also handing each sweep's rows to `rows` as they are solved.
pub fn run_with_rows(
    source: &mut dyn FrameSource,
    tuner: &mut dyn BandTuner,
    setup: Setup,
    cfg: &RunConfig,
    sink: &mut dyn SweepSink,
    rows: &mut dyn RowSink,
    stop: &AtomicBool,
) -> Result<RunReport, RunError> {
    run_tapped(source, tuner, setup, cfg, sink, rows, None, stop)
}

/// [`run_with_rows`], also showing `tap` every frame capture reads and
/// the sequencer's verdict (a recorder).
#[allow(clippy::too_many_arguments)]
pub fn run_tapped(
    source: &mut dyn FrameSource,
    tuner: &mut dyn BandTuner,
    setup: Setup,
    cfg: &RunConfig,
    sink: &mut dyn SweepSink,
    rows: &mut dyn RowSink,
    tap: Option<&mut dyn CaptureTap>,
    stop: &AtomicBool,
) -> Result<RunReport, RunError> {
    let info = source.info();
    let (w, h) = (info.width as usize, info.height as usize);
    if setup.calibrator.plane_len() != w * h {
        return Err(RunError::Config(format!(
            "calibration is for {} pixels per frame, the camera delivers {w}×{h}",
            setup.calibrator.plane_len()
        )));
    }
    let bands_nm: Vec<f64> = setup.bands.iter().map(|b| b.center_nm).collect();
    let seq = Sequencer::new(setup.seq_mode, bands_nm, setup.order.clone(), cfg.sweeps)?;
    let mut solver = Solver::new(&setup.scene, &setup.bands, cfg.mode)?;
    solver.set_residual_noise_floor(setup.scene.noise_sigma.is_none());
    // The camera's noise measured with the references, where the scene
    // gives none: every fit is judged against it from the first sweep.
    if let (None, Some(noise)) = (setup.scene.noise_sigma, setup.calibrator.noise()) {
        solver.set_noise(noise.model());
        solver.set_residual_noise_floor(false);
    }
    let counters = Arc::new(Counters::default());
    let mut capture = Capture {
        source,
        tuner,
        seq,
        spare: Frame::with_size(info.width, info.height, info.format),
        timeout: cfg.frame_timeout,
        last_seq: None,
        counters: counters.clone(),
        width: info.width,
        height: info.height,
        after_tune: false,
        fault: cfg.fault,
        handled: 0,
        // Re-borrowed for the capture stage's lifetime.
        tap: match tap {
            Some(t) => Some(t),
            None => None,
        },
        skipping: false,
    };
    // The first sweep's set-up (film index, noise, level) takes several
    // sweep periods on a large image: capture holds the second sweep back
    // until it is done, instead of queueing and then dropping the sweeps
    // behind it (in triggered mode, where the controller cycles on its
    // own, the sweeps that start meanwhile are skipped). Not where a replay
    // (lossless) reads as fast as it can, nor on one thread (capture waits
    // for the solve anyway).
    let needs_setup = solver
        .film_index()
        .is_none_or(|i| !i.noise_sigma.is_finite());
    counters.setup_hold.store(
        needs_setup && !cfg.lossless && !cfg.single_thread,
        Ordering::Release,
    );
    let tracker = Tracker::new(w, h, &setup.bands).track_extrema(cfg.track_extrema);
    let n_sweep_bufs = cfg.sweep_buffers.max(1);
    let sweep_bufs: Vec<SweepBuf> = (0..n_sweep_bufs).map(|_| tracker.new_sweep_buf()).collect();
    let mut ingest = Ingest {
        tracker,
        cal: setup.calibrator,
        current: None,
        floor: None,
        counters: counters.clone(),
        fault: cfg.fault,
        handled: 0,
    };
    let block = if cfg.row_block > 0 {
        cfg.row_block.min(h.max(1))
    } else {
        h.div_ceil(16).max(1)
    };
    let mut solve = Solve {
        solver,
        scratch: Scratch::default(),
        block,
        index_tried: false,
        level_buf: None,
        estimates: vec![PixelEstimate::invalid(crate::estimate::Reason::Masked); block * w],
        counters: counters.clone(),
        reported_frames: 0,
        reported_sweeps: 0,
        fault: cfg.fault,
        handled: 0,
        hold_allowed: !cfg.lossless && !cfg.single_thread,
        drift: Drift::new(),
    };
    let n_bands = setup.order.len();
    let (completed, stopped) = if cfg.single_thread {
        run_single(
            &mut capture,
            &mut ingest,
            &mut solve,
            sweep_bufs,
            (w, h),
            cfg,
            sink,
            rows,
            stop,
        )?
    } else {
        let wiring = Threaded {
            size: (w, h),
            format: info.format,
            n_bands,
            counters: &counters,
        };
        wiring.run(capture, ingest, solve, sweep_bufs, cfg, sink, rows, stop)?
    };
    Ok(RunReport {
        sweeps_completed: completed,
        sweeps_dropped: counters.sweeps_dropped.load(Ordering::Relaxed),
        frames_dropped: counters.frames_dropped.load(Ordering::Relaxed),
        frames_settling: counters.frames_settling.load(Ordering::Relaxed),
        frames_total: counters.frames_total.load(Ordering::Relaxed),
        frames_lost_tuning: counters.frames_lost_tuning.load(Ordering::Relaxed),
        frames_held: counters.frames_held.load(Ordering::Relaxed),
        relooks: counters.relooks.load(Ordering::Relaxed),
        stopped,
    })
}

/// The pipeline on the caller's thread: capture one frame, ingest what it
/// produced, solve and write a sweep the moment it completes. Returns the
/// sweeps written and whether the stop flag ended the run.
#[allow(clippy::too_many_arguments)]
fn run_single(
    capture: &mut Capture<'_>,
    ingest: &mut Ingest,
    solve: &mut Solve,
    mut sweep_bufs: Vec<SweepBuf>,
    (w, h): (usize, usize),
    cfg: &RunConfig,
    sink: &mut dyn SweepSink,
    rows: &mut dyn RowSink,
    stop: &AtomicBool,
) -> Result<(u64, bool), RunError> {
    let mut stopped = false;
    let mut completed = 0u64;
    let format = capture.spare.meta.format;
    let mut maps = ParamMaps::new(w, h);
    let mut pool: Vec<Frame> = vec![Frame::with_size(w as u32, h as u32, format)];
    let mut packets: std::collections::VecDeque<Packet> =
        std::collections::VecDeque::with_capacity(64);
    let mut result = Ok(());
    let mut sink_faults = 0;
    loop {
        if stop.load(Ordering::Relaxed) {
            stopped = true;
            packets.push_back(Packet::End);
        } else {
            let step = catch(|| {
                capture.step(pool.pop(), &mut |p| packets.push_back(p), &mut |f| {
                    pool.push(f)
                })
            })
            .unwrap_or_else(|message| {
                Err(RunError::Panicked {
                    stage: Stage::Capture,
                    message,
                })
            });
            match step {
                Ok(Step::Continue) => {}
                Ok(Step::Done) => packets.push_back(Packet::End),
                Err(e) => {
                    result = Err(e);
                    packets.push_back(Packet::End);
                }
            }
        }
        let mut ended = false;
        while let Some(p) = packets.pop_front() {
            ended |= matches!(p, Packet::End);
            let mut finished: Option<(SweepBuf, Instant)> = None;
            let f =
                catch(|| ingest.on_packet(p, &mut sweep_bufs, &mut |b, t| finished = Some((b, t))))
                    .map_err(|message| RunError::Panicked {
                        stage: Stage::Ingest,
                        message,
                    })?;
            if let Some(f) = f {
                pool.push(f);
            }
            if let Some((b, t)) = finished {
                let mut s =
                    catch(|| solve.solve(&b, &mut maps, None, rows)).map_err(|message| {
                        RunError::Panicked {
                            stage: Stage::Solve,
                            message,
                        }
                    })?;
                s.latency_ms = t.elapsed().as_secs_f64() * 1e3;
                let _span = tracing::info_span!("write.sweep", sweep = b.sweep).entered();
                catch(|| {
                    StageFault::check(cfg.fault, Stage::Sink, &mut sink_faults);
                    sink.on_sweep(&s, &maps)
                })
                .map_err(|message| RunError::Panicked {
                    stage: Stage::Sink,
                    message,
                })?
                .map_err(RunError::Sink)?;
                completed += 1;
                sweep_bufs.push(b);
            }
        }
        if ended {
            break;
        }
    }
    result?;
    Ok((completed, stopped))
}

/// The threaded wiring: capture, ingest and the sink on their own threads,
/// the solver on the caller's (with a rayon pool for rows), joined by
/// lock-free rings (frames) and bounded channels (sweeps, maps).
struct Threaded<'c> {
    size: (usize, usize),
    format: crate::device::camera::PixelFormat,
    n_bands: usize,
    counters: &'c Arc<Counters>,
}

impl Threaded<'_> {
    /// Run until the sequencer is done, the stop flag is set or a stage
    /// fails: the sweeps written and whether the stop flag ended the run.
    #[allow(clippy::too_many_arguments)]
    fn run(
        &self,
        mut capture: Capture<'_>,
        mut ingest: Ingest,
        mut solve: Solve,
        mut sweep_bufs: Vec<SweepBuf>,
        cfg: &RunConfig,
        sink: &mut dyn SweepSink,
        rows: &mut dyn RowSink,
        stop: &AtomicBool,
    ) -> Result<(u64, bool), RunError> {
        let (w, h) = self.size;
        let counters = self.counters;
        let n_sweep_bufs = sweep_bufs.len().max(1);
        let mut stopped = false;
        let mut completed = 0u64;
        let rayon_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(cfg.threads.unwrap_or(0))
            .thread_name(|i| format!("irid-solve-{i}"))
            .build()
            .map_err(|e| RunError::Config(format!("solver thread pool: {e}")))?;
        let n_frames = cfg.frame_pool.max(2);
        let (mut free_prod, mut free_cons) = HeapRb::<Frame>::new(n_frames).split();
        for _ in 0..n_frames {
            let _ = free_prod.try_push(Frame::with_size(w as u32, h as u32, self.format));
        }
        // Room for every pooled frame plus markers.
        let (mut pkt_prod, mut pkt_cons) =
            HeapRb::<Packet>::new(n_frames + 2 * self.n_bands + 4).split();
        // Capture → ingest doorbell: the ring is lock-free, the bell only
        // wakes a sleeping ingest.
        let (bell_tx, bell_rx) = crossbeam_channel::bounded::<()>(1);
        let (free_sweep_tx, free_sweep_rx) = crossbeam_channel::bounded::<SweepBuf>(n_sweep_bufs);
        for b in sweep_bufs.drain(..) {
            let _ = free_sweep_tx.send(b);
        }
        let (done_tx, done_rx) = crossbeam_channel::bounded::<(SweepBuf, Instant)>(n_sweep_bufs);
        let (maps_tx, maps_rx) = crossbeam_channel::bounded::<(SweepSummary, ParamMaps)>(2);
        let (free_maps_tx, free_maps_rx) = crossbeam_channel::bounded::<ParamMaps>(2);
        for _ in 0..2 {
            let _ = free_maps_tx.send(ParamMaps::new(w, h));
        }
        // Raised by a failing stage: every loop below checks it, so no
        // stage waits on one that is gone.
        let halt = &AtomicBool::new(false);
        let lossless = cfg.lossless;
        let outcome = std::thread::scope(|sc| -> Result<(), RunError> {
            let cap = std::thread::Builder::new()
                .name("irid-capture".into())
                .spawn_scoped(sc, move || -> Result<bool, RunError> {
                    let _guard = HaltOnDrop(halt);
                    let mut stopped = false;
                    let mut result = Ok(());
                    // Frames the capture thread did not pass on, reused first.
                    let mut stash: Vec<Frame> = Vec::with_capacity(n_frames + 1);
                    loop {
                        if stop.load(Ordering::Relaxed) {
                            stopped = true;
                            break;
                        }
                        if halt.load(Ordering::Relaxed) {
                            break;
                        }
                        let mut overflow = false;
                        let mut buf = stash.pop().or_else(|| free_cons.try_pop());
                        while lossless && buf.is_none() && !stop.load(Ordering::Relaxed) {
                            std::thread::sleep(Duration::from_micros(100));
                            buf = free_cons.try_pop();
                        }
                        let r = capture.step(
                            buf,
                            &mut |p| {
                                if let Err(p) = pkt_prod.try_push(p) {
                                    // Cannot happen by sizing; never lose silently.
                                    overflow = true;
                                    drop(p);
                                } else {
                                    // Wake ingest if it sleeps (never blocks:
                                    // one pending ring is enough).
                                    let _ = bell_tx.try_send(());
                                }
                            },
                            &mut |f| stash.push(f),
                        );
                        if overflow {
                            capture
                                .counters
                                .sweeps_dropped
                                .fetch_add(1, Ordering::Relaxed);
                        }
                        match r {
                            Ok(Step::Continue) => {}
                            Ok(Step::Done) => break,
                            Err(e) => {
                                halt.store(true, Ordering::SeqCst);
                                result = Err(e);
                                break;
                            }
                        }
                    }
                    let mut end = Packet::End;
                    while let Err(p) = pkt_prod.try_push(end) {
                        if halt.load(Ordering::Relaxed) {
                            // Ingest is gone: nobody would read the marker.
                            break;
                        }
                        end = p;
                        std::thread::sleep(Duration::from_micros(200));
                    }
                    let _ = bell_tx.try_send(());
                    result.map(|()| stopped)
                })
                .map_err(|e| RunError::Config(format!("spawn: {e}")))?;
            let mut sweep_pool = ChannelPool {
                rx: free_sweep_rx,
                tx: free_sweep_tx.clone(),
                wait: lossless,
            };
            let ing = std::thread::Builder::new()
                .name("irid-ingest".into())
                .spawn_scoped(sc, move || {
                    let _guard = HaltOnDrop(halt);
                    let mut idle = 0u32;
                    loop {
                        let Some(p) = pkt_cons.try_pop() else {
                            if halt.load(Ordering::Relaxed) {
                                // Capture died before its end marker.
                                break;
                            }
                            // Spin briefly (a frame is often just behind),
                            // then sleep until capture rings the bell: an
                            // idle ingest costs no CPU the solver needs.
                            idle += 1;
                            if idle < 64 {
                                std::hint::spin_loop();
                            } else {
                                let _ = bell_rx.recv_timeout(Duration::from_millis(20));
                            }
                            continue;
                        };
                        idle = 0;
                        let end = matches!(p, Packet::End);
                        let f = ingest.on_packet(p, &mut sweep_pool, &mut |b, t| {
                            // Bounded by the number of sweep buffers: never blocks.
                            let _ = done_tx.send((b, t));
                        });
                        if let Some(f) = f {
                            let _ = free_prod.try_push(f);
                        }
                        if end {
                            break;
                        }
                    }
                })
                .map_err(|e| RunError::Config(format!("spawn: {e}")))?;
            let sink_thread = std::thread::Builder::new()
                .name("irid-sink".into())
                .spawn_scoped(sc, move || -> Result<u64, RunError> {
                    let _guard = HaltOnDrop(halt);
                    let mut fault_count = 0;
                    let mut n = 0;
                    let mut err = None;
                    for (s, maps) in maps_rx.iter() {
                        if err.is_none() {
                            let _span =
                                tracing::info_span!("write.sweep", sweep = s.sweep).entered();
                            StageFault::check(cfg.fault, Stage::Sink, &mut fault_count);
                            match sink.on_sweep(&s, &maps) {
                                Ok(()) => n += 1,
                                Err(e) => {
                                    halt.store(true, Ordering::SeqCst);
                                    err = Some(RunError::Sink(e));
                                }
                            }
                        }
                        let _ = free_maps_tx.try_send(maps);
                    }
                    err.map_or(Ok(n), Err)
                })
                .map_err(|e| RunError::Config(format!("spawn: {e}")))?;
            // Solve on this thread.
            let mut solve_result = Ok(());
            for (b, t) in done_rx.iter() {
                // After a failure the sweep being solved is finished and
                // written; those still queued are dropped (counted), so the
                // run ends within one solve.
                if halt.load(Ordering::Relaxed) {
                    counters.sweeps_dropped.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                let mut maps = free_maps_rx.recv().unwrap_or_else(|_| ParamMaps::new(w, h));
                let solved = catch(|| solve.solve(&b, &mut maps, Some(&rayon_pool), rows));
                let mut s = match solved {
                    Ok(s) => s,
                    Err(message) => {
                        halt.store(true, Ordering::SeqCst);
                        solve_result = Err(RunError::Panicked {
                            stage: Stage::Solve,
                            message,
                        });
                        break;
                    }
                };
                s.latency_ms = t.elapsed().as_secs_f64() * 1e3;
                let _ = free_sweep_tx.try_send(b);
                if maps_tx.send((s, maps)).is_err() {
                    break;
                }
            }
            drop(maps_tx);
            // Solving stopped early: ingest must not wait on a full queue.
            drop(done_rx);
            let panicked = |stage| {
                move |p: Box<dyn std::any::Any + Send>| RunError::Panicked {
                    stage,
                    message: super::stage::panic_message(&*p),
                }
            };
            let ing_result = ing.join().map_err(panicked(Stage::Ingest));
            let cap_result = cap
                .join()
                .unwrap_or_else(|p| Err(panicked(Stage::Capture)(p)));
            let sink_result = sink_thread
                .join()
                .unwrap_or_else(|p| Err(panicked(Stage::Sink)(p)));
            // The first failure in pipeline order is the cause; later
            // stages only saw it stop.
            ing_result?;
            solve_result?;
            completed = sink_result?;
            stopped = cap_result?;
            Ok(())
        });
        outcome?;
        Ok((completed, stopped))
    }
}
