//! The line runner: camera + filter sequencing → calibration → web
//! registration → per-web-row accumulation → row solving → row sinks, on
//! one thread (deterministic: the same seed gives the same rows); only the
//! rows one frame finishes are solved in parallel (rayon), each row by one
//! thread, so the result does not depend on the thread count.
//!
//! Each accepted frame is calibrated, registered to the web (encoder count
//! or constant speed) and spread over the web rows in view; every row that
//! finishes is solved and handed to the sink at once, in web order. Rows
//! still in view when the run ends are not emitted (counted as run-out).
//!
//! Latency is measured from the moment the frame that finished a row was
//! read to the moment the row reached the sink (warm-up rows aside: they
//! wait for the noise level, see [`super::solve`]).

use super::accumulate::{Accumulator, RowCounts};
use super::geometry::{first_row, LineGeometry, Motion, Registration};
use super::solve::{RowSolver, WebRowOut};
use super::LineError;
use crate::device::camera::{CameraError, Frame, FrameSource};
use crate::estimate::Mode;
use crate::optics::band::Band;
use crate::pipeline::calibration::Calibrator;
use crate::pipeline::runner::CaptureTap;
use crate::pipeline::sequencer::{BandTuner, Discard, SeqMode, Sequencer, Verdict};
use crate::scene::Scene;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Where emitted web rows go.
pub trait WebRowSink {
    /// One row, in web order.
    fn on_row(&mut self, row: &WebRowOut) -> Result<(), String>;
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
    /// Largest latency of a row after its last band, ms (warm-up excluded).
    pub latency_ms_max: f64,
    /// Mean of that latency, ms.
    pub latency_ms_mean: f64,
}

struct Pending {
    row: WebRowOut,
}

/// Run the line until the limits, the end of the source or the stop flag.
///
/// The source is anything that delivers frames (the live camera, a
/// recording replayed), the tuner anything that steps the filter.
pub fn run_line(
    source: &mut dyn FrameSource,
    tuner: &mut dyn BandTuner,
    setup: LineSetup,
    limits: &LineLimits,
    sink: &mut dyn WebRowSink,
    stop: &AtomicBool,
) -> Result<LineReport, LineError> {
    run_line_tapped(source, tuner, setup, limits, sink, None, stop)
}

/// [`run_line`] with a tap that sees every frame read and the sequencer's
/// verdict on it (the recorder, `irid run --scene web --record`).
pub fn run_line_tapped(
    source: &mut dyn FrameSource,
    tuner: &mut dyn BandTuner,
    setup: LineSetup,
    limits: &LineLimits,
    sink: &mut dyn WebRowSink,
    mut tap: Option<&mut dyn CaptureTap>,
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
    let mut seq = Sequencer::new(SeqMode::Stepped, bands_nm, setup.order.clone(), None)
        .map_err(|e| LineError::Config(e.to_string()))?;
    let mut reg = Registration::new(setup.motion)?;
    let mut acc = Accumulator::new(w, h, setup.bands.len());
    let mut solver = RowSolver::new(&setup.scene, &setup.bands, setup.mode, w, setup.warmup_rows)?;
    let mut frame = Frame::with_size(info.width, info.height, info.format);
    let mut refl = vec![0.0f32; w * h];
    let mut rep = LineReport::default();
    let mut last_seq: Option<u64> = None;
    let mut finished = Vec::new();
    let mut emitted: Vec<Pending> = Vec::new();
    let (mut lat_sum, mut lat_n) = (0.0, 0u64);
    let mut span: Option<((u64, f64), (u64, f64))> = None;
    let mut sink_err: Option<String> = None;
    loop {
        if stop.load(Ordering::Relaxed) || limits.frames.is_some_and(|n| rep.frames_total >= n) {
            break;
        }
        match source.next_frame(&mut frame, limits.frame_timeout) {
            Ok(()) => {}
            Err(CameraError::Ended) => break,
            Err(CameraError::BadFrame { seq, message }) => {
                tracing::warn!(seq, %message, "bad frame");
                rep.frames_total += 1;
                rep.frames_dropped += 1;
                continue;
            }
            Err(e) => return Err(LineError::Camera(e)),
        }
        let t_read = Instant::now();
        rep.frames_total += 1;
        let m = frame.meta;
        if let Some(l) = last_seq {
            if m.seq > l + 1 {
                rep.frames_dropped += m.seq - l - 1;
            }
        }
        last_seq = Some(last_seq.map_or(m.seq, |l| l.max(m.seq)));
        let valid = frame.pixels().is_ok() && (m.width, m.height) == (info.width, info.height);
        let verdict = seq
            .on_frame(&m, valid, tuner, &mut |x| {
                if let Some(t) = tap.as_deref_mut() {
                    t.on_missing(x.sweep, x.band);
                }
            })
            .map_err(|e| LineError::Sequencer(e.to_string()))?;
        if let Some(t) = tap.as_deref_mut() {
            t.on_frame(&frame, Some(verdict));
        }
        // The web moves whether or not the frame is used.
        let pos = reg.position(m.encoder, m.timestamp_ns)?;
        match span {
            None => span = Some(((m.timestamp_ns, pos), (m.timestamp_ns, pos))),
            Some((a, _)) => span = Some((a, (m.timestamp_ns, pos))),
        }
        let band = match verdict {
            Verdict::Accept { band, .. } => band,
            Verdict::Discard(Discard::Settling) => {
                rep.frames_settling += 1;
                continue;
            }
            Verdict::Discard(_) => {
                rep.frames_dropped += 1;
                continue;
            }
        };
        rep.frames_accepted += 1;
        let Ok(px) = frame.pixels() else { continue };
        let sat = m.format.max_value();
        setup
            .calibrator
            .apply(band, px, sat, m.exposure_us, &mut refl);
        acc.ingest(first_row(pos), band, m.timestamp_ns, &refl, &mut |r| {
            finished.push(r)
        });
        let was_ready = solver.ready();
        solver.push_all(&mut finished, &mut |out, buf| {
            emitted.push(Pending { row: out });
            acc.recycle(buf);
        });
        for p in emitted.drain(..) {
            if sink_err.is_none() {
                if let Err(e) = sink.on_row(&p.row) {
                    sink_err = Some(e);
                }
            }
            rep.rows_emitted += 1;
            if was_ready && p.row.complete {
                let l = t_read.elapsed().as_secs_f64() * 1e3;
                lat_sum += l;
                lat_n += 1;
                rep.latency_ms_max = rep.latency_ms_max.max(l);
            }
        }
        if let Some(e) = sink_err.take() {
            return Err(LineError::Sink(e));
        }
    }
    solver.flush(&mut |out, _| emitted.push(Pending { row: out }));
    for p in emitted.drain(..) {
        sink.on_row(&p.row).map_err(LineError::Sink)?;
        rep.rows_emitted += 1;
    }
    sink.finish().map_err(LineError::Sink)?;
    rep.rows = acc.counts();
    rep.rows_run_out = acc.rows_in_ring() as u64;
    if let Some(((t0, p0), (t1, p1))) = span {
        if t1 > t0 {
            let dt = (t1 - t0) as f64 * 1e-9;
            rep.band_rate_hz = rep.frames_accepted as f64 / dt;
            rep.speed_rows_per_s = (p1 - p0) / dt;
        }
    }
    rep.latency_ms_mean = if lat_n > 0 {
        lat_sum / lat_n as f64
    } else {
        0.0
    };
    Ok(rep)
}
