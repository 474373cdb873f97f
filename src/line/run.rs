//! The line runner: camera + filter sequencing → calibration → web
//! registration → per-web-row accumulation (the capture side) → row
//! solving, statistics and alarms (the row stage, [`super::stage`]) → row
//! sinks.
//!
//! Threads ([`Threading::Split`], the default):
//!
//! ```text
//!  capture + calibrate + register + accumulate ──bounded(16 frames) rows──▶ solve + sink (stats, alarms)
//!          ▲ ◀────────────── bounded free row buffers ──────────────────────┘        │ bounded(segments)
//!                                                       EXR segment writer + publishers ◀┘ (super::output)
//! ```
//!
//! The row stage sees the same rows in the same order as in
//! [`Threading::Inline`] (every stage in the capture loop), and each row is
//! solved by one thread, so the rows, segments and alarms do not depend on
//! the threading or the thread count (tested). Backpressure: when the row
//! thread is 16 frames' rows behind, capture waits for it (counted in
//! [`LineReport::capture_waits`]); a real camera loses frames meanwhile,
//! which are counted as dropped and whose rows come out flagged "missing
//! bands". Memory stays bounded either way.
//!
//! Each accepted frame is calibrated, registered to the web (encoder count
//! or constant speed) and spread over the web rows in view; every row that
//! finishes is solved and handed to the sink, in web order. Rows still in
//! view when the run ends are not emitted (counted as run-out).
//!
//! **Latency** of a row: from the moment the frame that brought its last
//! band was returned by the camera to the moment the sink returned from the
//! row (statistics and alarms done; the segment file and the messages are
//! written by the output's own thread and are not on this path). It
//! includes calibration, accumulation, any wait in the queue to the row
//! thread, solving and the sink. Rows of the warm-up are not counted (they
//! wait for the noise level, see [`super::solve`]), nor rows read while the
//! warm-up was being solved (they wait for it): those are reported apart
//! ([`LineReport::warmup_wait_rows`], [`LineReport::warmup_wait_ms_max`]).

use super::accumulate::FinishedRow;
use super::accumulate::{Accumulator, RowCounts};
use super::geometry::{first_row, LineGeometry, Motion, Registration};
use super::solve::{RowSolver, WebRowOut};
use super::stage::{Batch, RowStage, StageReport};
use super::LineError;
use crate::device::camera::{CameraError, Frame, FrameSource};
use crate::estimate::Mode;
use crate::optics::band::Band;
use crate::pipeline::calibration::Calibrator;
use crate::pipeline::runner::CaptureTap;
use crate::pipeline::sequencer::{BandTuner, Discard, SeqMode, Sequencer, Verdict};
use crate::scene::Scene;
use crossbeam_channel::{Receiver, Sender, TrySendError};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Where emitted web rows go.
pub trait WebRowSink {
    /// One row, in web order.
    fn on_row(&mut self, row: &WebRowOut) -> Result<(), String>;
    /// The estimator's map metadata (mode, bands, film index), given once
    /// it is known, before the first row.
    fn set_map_meta(&mut self, _meta: crate::estimate::maps::MapMeta) {}
    /// The run ended (flush what is buffered).
    fn finish(&mut self) -> Result<(), String> {
        Ok(())
    }
}

/// A sink that keeps every row (tests).
#[derive(Default)]
pub struct CollectRows {
    /// Rows, in order.
    pub rows: Vec<WebRowOut>,
}

impl WebRowSink for CollectRows {
    fn on_row(&mut self, row: &WebRowOut) -> Result<(), String> {
        self.rows.push(row.clone());
        Ok(())
    }
}

/// What to run.
pub struct LineSetup {
    /// The scene: media, knowledge and bands for the estimator.
    pub scene: Scene,
    /// Bands, in plane order.
    pub bands: Vec<Band>,
    /// Capture order (band indices).
    pub order: Vec<usize>,
    /// Counts → reflectance.
    pub calibrator: Calibrator,
    /// How the web's position is known.
    pub motion: Motion,
    /// The optics and band rate (for the speed check).
    pub geometry: LineGeometry,
    /// The nominal line speed, rows/s, checked against the optics' limit.
    pub nominal_speed: f64,
    /// Run above the limit anyway (rows that miss bands are flagged).
    pub allow_over_speed: bool,
    /// Solver mode.
    pub mode: Mode,
    /// Complete rows that teach the estimator the noise level first.
    pub warmup_rows: usize,
    /// How the stages are spread over threads.
    pub threading: Threading,
    /// The incidence angle of each sensor row, radians (None: every row at
    /// the scene's angle); each band of a web row is then modelled at the
    /// angle of the sensor row it was seen at ([`super::angles`]).
    pub sensor_angles: Option<Vec<f64>>,
    /// When that angle correction is applied (by default where the spread
    /// of a row's angles matters).
    pub angle_correction: super::angles::Correction,
}

/// When to stop.
#[derive(Clone, Copy, Debug)]
pub struct LineLimits {
    /// Frames to read (None: until the source ends or the stop flag).
    pub frames: Option<u64>,
    /// How long to wait for a frame.
    pub frame_timeout: Duration,
}

/// What happened in a run.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct LineReport {
    /// Web rows by outcome.
    pub rows: RowCounts,
    /// Rows handed to the sink.
    pub rows_emitted: u64,
    /// Of those, rows whose bands were modelled at the incidence angles of
    /// the sensor rows they were seen at (the spread mattered; see
    /// [`super::angles`]).
    pub rows_angle_corrected: u64,
    /// Rows still in view at the end (not emitted).
    pub rows_run_out: u64,
    /// Frames read.
    pub frames_total: u64,
    /// Frames used as a band.
    pub frames_accepted: u64,
    /// Frames discarded while the filter settled.
    pub frames_settling: u64,
    /// Frames lost (sequence gaps), malformed or stale.
    pub frames_dropped: u64,
    /// Measured band rate, bands per second of frame time.
    pub band_rate_hz: f64,
    /// Measured web speed, rows per second of frame time.
    pub speed_rows_per_s: f64,
    /// Largest latency of a row after its last band, ms: from the return
    /// of the camera's read of the frame that brought the row's last band
    /// to the return of the sink from the row (warm-up excluded).
    pub latency_ms_max: f64,
    /// Mean of that latency, ms.
    pub latency_ms_mean: f64,
    /// 99th percentile of that latency, ms (to the 1 ms bin above).
    pub latency_ms_p99: f64,
    /// Complete rows read while the warm-up's rows were being solved: they
    /// waited for that one-off start-up work and are counted apart.
    pub warmup_wait_rows: u64,
    /// The largest latency among them, ms.
    pub warmup_wait_ms_max: f64,
    /// Frames whose finished rows found the row thread's queue full: the
    /// capture waited for the solver (a real camera loses frames meanwhile,
    /// counted in `frames_dropped`; rows that miss a band are flagged).
    pub capture_waits: u64,
    /// Times the calibration (the noise, level, band shift and, where
    /// unknown, the film index) was estimated again after the warm-up,
    /// because the look every [`super::solve::LOOK_EVERY`] warm-ups' worth
    /// of rows saw it move.
    pub relooks: u64,
    /// Of those looks, the ones at which the calibration had moved at
    /// [`super::solve::UNSETTLED_LOOKS`] or more looks in a row (a lamp
    /// that flickers): every row was flagged from then until a look found
    /// it steady.
    pub unsettled_looks: u64,
}

/// How the stages are spread over threads.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Threading {
    /// Capture, calibration, registration and accumulation on the calling
    /// thread; row solving, statistics and alarms on a second thread fed
    /// by a bounded channel (the rows of several frames solved in parallel
    /// when it is behind). The default.
    #[default]
    Split,
    /// Everything in the capture loop (the reference the split run is
    /// checked against; the rows one frame finishes still solved in
    /// parallel).
    Inline,
}

/// Frames' worth of finished rows the solve thread may have waiting before
/// capture waits for it.
const ROW_QUEUE_FRAMES: usize = 16;

enum Msg {
    Rows(Batch),
    End,
}

/// The capture side: camera + sequencer → calibration → registration →
/// accumulation.
struct Front<'a> {
    source: &'a mut dyn FrameSource,
    tuner: &'a mut dyn BandTuner,
    calibrator: Calibrator,
    seq: Sequencer,
    reg: Registration,
    acc: Accumulator,
    frame: Frame,
    refl: Vec<f32>,
    rep: LineReport,
    last_seq: Option<u64>,
    span: Option<((u64, f64), (u64, f64))>,
    info_wh: (u32, u32),
    /// When the last frame was read: a row's latency starts here.
    t_read: Instant,
    /// Sees every frame read and the sequencer's verdict (the recorder).
    tap: Option<&'a mut dyn CaptureTap>,
}

impl Front<'_> {
    /// Rows the accumulator keeps in view.
    fn acc_rows(&self) -> usize {
        self.info_wh.1 as usize
    }

    /// Read and take in one frame; the rows it finished go to `finished`.
    /// `Ok(false)`: the source ended.
    fn step(
        &mut self,
        limits: &LineLimits,
        finished: &mut Vec<FinishedRow>,
    ) -> Result<bool, LineError> {
        let rep = &mut self.rep;
        match self
            .source
            .next_frame(&mut self.frame, limits.frame_timeout)
        {
            Ok(()) => {}
            Err(CameraError::Ended) => return Ok(false),
            Err(CameraError::BadFrame { seq, message }) => {
                tracing::warn!(seq, %message, "bad frame");
                rep.frames_total += 1;
                rep.frames_dropped += 1;
                return Ok(true);
            }
            Err(e) => return Err(LineError::Camera(e)),
        }
        self.t_read = Instant::now();
        rep.frames_total += 1;
        let m = self.frame.meta;
        if let Some(l) = self.last_seq {
            if m.seq > l + 1 {
                rep.frames_dropped += m.seq - l - 1;
            }
        }
        self.last_seq = Some(self.last_seq.map_or(m.seq, |l| l.max(m.seq)));
        let valid = self.frame.pixels().is_ok() && (m.width, m.height) == self.info_wh;
        let tap = &mut self.tap;
        let verdict = self
            .seq
            .on_frame(&m, valid, self.tuner, &mut |x| {
                if let Some(t) = tap.as_deref_mut() {
                    t.on_missing(x.sweep, x.band);
                }
            })
            .map_err(|e| LineError::Sequencer(e.to_string()))?;
        if let Some(t) = self.tap.as_deref_mut() {
            t.on_frame(&self.frame, Some(verdict));
        }
        // The web moves whether or not the frame is used.
        let pos = self.reg.position(m.encoder, m.timestamp_ns)?;
        match self.span {
            None => self.span = Some(((m.timestamp_ns, pos), (m.timestamp_ns, pos))),
            Some((a, _)) => self.span = Some((a, (m.timestamp_ns, pos))),
        }
        let band = match verdict {
            Verdict::Accept { band, .. } => band,
            Verdict::Discard(Discard::Settling) => {
                rep.frames_settling += 1;
                return Ok(true);
            }
            Verdict::Discard(_) => {
                rep.frames_dropped += 1;
                return Ok(true);
            }
        };
        rep.frames_accepted += 1;
        let Ok(px) = self.frame.pixels() else {
            return Ok(true);
        };
        let sat = m.format.max_value();
        self.calibrator
            .apply(band, px, sat, m.exposure_us, &mut self.refl);
        self.acc
            .ingest(first_row(pos), band, m.timestamp_ns, &self.refl, &mut |r| {
                finished.push(r)
            });
        Ok(true)
    }

    fn report(mut self, stage: StageReport) -> LineReport {
        let rep = &mut self.rep;
        rep.rows = self.acc.counts();
        rep.rows_run_out = self.acc.rows_in_ring() as u64;
        if let Some(((t0, p0), (t1, p1))) = self.span {
            if t1 > t0 {
                let dt = (t1 - t0) as f64 * 1e-9;
                rep.band_rate_hz = rep.frames_accepted as f64 / dt;
                rep.speed_rows_per_s = (p1 - p0) / dt;
            }
        }
        rep.rows_emitted = stage.rows_emitted;
        rep.rows_angle_corrected = stage.rows_angle_corrected;
        rep.latency_ms_max = stage.latency_max_ms;
        rep.latency_ms_p99 = stage.latency_hist.quantile(0.99);
        rep.warmup_wait_rows = stage.warmup_wait_rows;
        rep.warmup_wait_ms_max = stage.warmup_wait_max_ms;
        rep.relooks = stage.relooks;
        rep.unsettled_looks = stage.unsettled_looks;
        rep.latency_ms_mean = if stage.latency_n > 0 {
            stage.latency_sum_ms / stage.latency_n as f64
        } else {
            0.0
        };
        self.rep
    }
}

/// Run the line until the limits, the end of the source or the stop flag.
pub fn run_line(
    source: &mut dyn FrameSource,
    tuner: &mut dyn BandTuner,
    setup: LineSetup,
    limits: &LineLimits,
    sink: &mut (dyn WebRowSink + Send),
    stop: &AtomicBool,
) -> Result<LineReport, LineError> {
    run_line_tapped(source, tuner, setup, limits, sink, None, stop)
}

/// [`run_line`] with a tap that sees every frame read and the sequencer's
/// verdict on it (the recorder, `irid run --scene web --record`).
pub fn run_line_tapped<'a>(
    source: &'a mut dyn FrameSource,
    tuner: &'a mut dyn BandTuner,
    setup: LineSetup,
    limits: &LineLimits,
    sink: &mut (dyn WebRowSink + Send),
    tap: Option<&'a mut dyn CaptureTap>,
    stop: &AtomicBool,
) -> Result<LineReport, LineError> {
    if !setup.allow_over_speed {
        setup.geometry.check_speed(setup.nominal_speed)?;
    }
    let info = source.info();
    let (w, h) = (info.width as usize, info.height as usize);
    if setup.calibrator.plane_len() != w * h {
        return Err(LineError::Config(format!(
            "calibration is for {} pixels per frame, the camera delivers {w}×{h}",
            setup.calibrator.plane_len()
        )));
    }
    if h != setup.geometry.rows_in_view || setup.bands.len() != setup.geometry.n_bands {
        return Err(LineError::Config(format!(
            "geometry says {} rows in view and {} bands, the camera has {h} rows and the sweep {} bands",
            setup.geometry.rows_in_view,
            setup.geometry.n_bands,
            setup.bands.len()
        )));
    }
    let bands_nm: Vec<f64> = setup.bands.iter().map(|b| b.center_nm).collect();
    let seq = Sequencer::new(SeqMode::Stepped, bands_nm, setup.order.clone(), None)
        .map_err(|e| LineError::Config(e.to_string()))?;
    if let Some(a) = &setup.sensor_angles {
        if a.len() != h {
            return Err(LineError::Config(format!(
                "{} incidence angles per sensor row, the camera has {h} rows",
                a.len()
            )));
        }
    }
    let mut solver = RowSolver::new(&setup.scene, &setup.bands, setup.mode, w, setup.warmup_rows)?;
    if let Some(a) = setup.sensor_angles {
        solver.set_sensor_angles(a, setup.angle_correction)?;
    }
    let front = Front {
        source,
        tuner,
        calibrator: setup.calibrator,
        seq,
        reg: Registration::new(setup.motion)?,
        acc: Accumulator::new(w, h, setup.bands.len()),
        frame: Frame::with_size(info.width, info.height, info.format),
        refl: vec![0.0f32; w * h],
        rep: LineReport::default(),
        last_seq: None,
        span: None,
        info_wh: (info.width, info.height),
        t_read: Instant::now(),
        tap,
    };
    let stage = RowStage::new(solver, sink);
    match setup.threading {
        Threading::Inline => run_inline(front, stage, limits, stop),
        Threading::Split => run_split(front, stage, limits, stop),
    }
}

fn should_stop(rep: &LineReport, limits: &LineLimits, stop: &AtomicBool) -> bool {
    stop.load(Ordering::Relaxed) || limits.frames.is_some_and(|n| rep.frames_total >= n)
}

/// Every stage in the capture loop.
fn run_inline(
    mut front: Front,
    mut stage: RowStage,
    limits: &LineLimits,
    stop: &AtomicBool,
) -> Result<LineReport, LineError> {
    let mut finished = Vec::new();
    let mut batches = Vec::with_capacity(1);
    while !should_stop(&front.rep, limits, stop) {
        if !front.step(limits, &mut finished)? {
            break;
        }
        if finished.is_empty() {
            continue;
        }
        batches.push(Batch {
            rows: std::mem::take(&mut finished),
            t_read: front.t_read,
        });
        let acc = &mut front.acc;
        stage
            .push(&mut batches, &mut |r| acc.recycle(r))
            .map_err(LineError::Sink)?;
    }
    let st = stage.finish().map_err(LineError::Sink)?;
    Ok(front.report(st))
}

/// Capture on the calling thread, the row stage on its own (see
/// [`Threading::Split`]).
fn run_split(
    mut front: Front,
    stage: RowStage,
    limits: &LineLimits,
    stop: &AtomicBool,
) -> Result<LineReport, LineError> {
    let (tx, rx) = crossbeam_channel::bounded::<Msg>(ROW_QUEUE_FRAMES);
    let (free_tx, free_rx) = crossbeam_channel::bounded::<FinishedRow>(2 * front.acc_rows());
    std::thread::scope(|s| {
        let solving = std::thread::Builder::new()
            .name("irid-line-rows".into())
            .spawn_scoped(s, move || solve_loop(stage, rx, free_tx))
            .map_err(|e| LineError::Config(format!("starting the row thread: {e}")))?;
        let captured = capture_loop(&mut front, limits, stop, &tx, &free_rx);
        if captured.is_ok() {
            // A row thread that already stopped reports why at the join.
            let _ = tx.send(Msg::End);
        }
        drop(tx);
        let stage = solving
            .join()
            .map_err(|_| LineError::Panicked("row solving".into()))?;
        captured?;
        match stage.map_err(LineError::Sink)? {
            Some(st) => Ok(front.report(st)),
            None => Err(LineError::Panicked("row solving".into())),
        }
    })
}

/// The capture side of [`run_split`]: frames in, batches of finished rows
/// out; waits (counted) when the row thread's queue is full.
fn capture_loop(
    front: &mut Front,
    limits: &LineLimits,
    stop: &AtomicBool,
    tx: &Sender<Msg>,
    free: &Receiver<FinishedRow>,
) -> Result<(), LineError> {
    let mut finished = Vec::new();
    while !should_stop(&front.rep, limits, stop) {
        for r in free.try_iter() {
            front.acc.recycle(r);
        }
        if !front.step(limits, &mut finished)? {
            break;
        }
        if finished.is_empty() {
            continue;
        }
        let msg = Msg::Rows(Batch {
            rows: std::mem::take(&mut finished),
            t_read: front.t_read,
        });
        let sent = match tx.try_send(msg) {
            Ok(()) => Ok(()),
            Err(TrySendError::Full(msg)) => {
                front.rep.capture_waits += 1;
                tx.send(msg).map_err(|_| ())
            }
            Err(TrySendError::Disconnected(_)) => Err(()),
        };
        if sent.is_err() {
            // The row thread stopped (its error is returned by the join).
            break;
        }
    }
    Ok(())
}

/// The row thread: batches in, rows to the sink. `Ok(None)`: the capture
/// side ended without `End` (it failed; nothing more is emitted).
fn solve_loop(
    mut stage: RowStage,
    rx: Receiver<Msg>,
    free: Sender<FinishedRow>,
) -> Result<Option<StageReport>, String> {
    let mut batches = Vec::new();
    while let Ok(first) = rx.recv() {
        let mut end = false;
        for m in std::iter::once(first).chain(rx.try_iter()) {
            match m {
                Msg::Rows(b) => batches.push(b),
                Msg::End => {
                    end = true;
                    break;
                }
            }
        }
        stage.push(&mut batches, &mut |r| {
            let _ = free.try_send(r);
        })?;
        if end {
            return stage.finish().map(Some);
        }
    }
    Ok(None)
}
