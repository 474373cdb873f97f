//! A recording as a camera and a filter: [`ReplaySource`] (a
//! [`FrameSource`]) and [`ReplayTuner`] (a [`BandTuner`]) share one cursor
//! over the file, so the pipeline replays unchanged.
//!
//! The sequencer is a pure state machine of frame metadata and the
//! filter's settled times, so feeding it the recorded frames and answering
//! each command with the recorded settled time reproduces every pairing of
//! the live run — and so, with the same scene, mode and calibration, the
//! same maps, bit for bit. Where the replay asks for a band the live run
//! did not command next (the live run abandoned a sweep for back-pressure,
//! the recorder lost a frame), the tuner answers with the next recorded
//! command for that band: frames before it are discarded as settling, so
//! a frame is still only ever paired with the band the filter passed.
//!
//! Reading is streaming: one chunk in memory, plus the frames read ahead
//! while looking for a filter command (at most [`MAX_READ_AHEAD`]).

use super::reader::{Damage, RawMsg, RecordReader};
use super::{decode_frame_meta, decode_samples, RecordError, Session, TuneEvent};
use super::{TOPIC_CALIBRATION, TOPIC_FILTER, TOPIC_FRAME, TOPIC_LINE, TOPIC_SESSION};
use crate::device::camera::{CameraError, CameraInfo, Frame, FrameSource};
use crate::pipeline::sequencer::{BandTuner, TuneError};
use std::collections::VecDeque;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Frames the tuner may read ahead looking for a filter command.
pub const MAX_READ_AHEAD: usize = 1024;

/// What replay found, shared by the source and the tuner.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReplayStats {
    /// Frames handed to the pipeline.
    pub frames: u64,
    /// Frame messages refused (malformed, wrong size).
    pub bad_frames: u64,
    /// Filter commands the replay asked for that the live run did not make
    /// next (the tuner skipped ahead).
    pub diverged: u64,
    /// Damage in the file.
    pub damage: Vec<Damage>,
    /// Whether the file was closed properly.
    pub closed: bool,
}

struct Cursor {
    reader: RecordReader,
    frames: VecDeque<RawMsg>,
    tunes: VecDeque<TuneEvent>,
    stats: ReplayStats,
}

impl Cursor {
    /// Read one message into the queues; false at the end.
    fn pump(&mut self) -> bool {
        let Some(m) = self.reader.next_message() else {
            return false;
        };
        match m.topic.as_str() {
            TOPIC_FRAME => self.frames.push_back(m),
            TOPIC_FILTER => {
                if let Ok(ev) = serde_json::from_slice::<TuneEvent>(&m.data) {
                    self.tunes.push_back(ev);
                }
            }
            _ => {}
        }
        true
    }
}

/// A recording opened for replay.
pub struct Recording {
    /// The session.
    pub session: Session,
    /// The calibration's `.ircal` bytes.
    pub calibration: Vec<u8>,
    /// A production-line recording's `/irid/line` message (JSON; written
    /// before the calibration), None for a static scene.
    pub line: Option<Vec<u8>>,
    cursor: Arc<Mutex<Cursor>>,
}

fn lock(c: &Mutex<Cursor>) -> std::sync::MutexGuard<'_, Cursor> {
    c.lock().unwrap_or_else(|p| p.into_inner())
}

impl Recording {
    /// Open `path` and read its session and calibration (the first two
    /// messages; a line recording's configuration is between them).
    pub fn open(path: &Path) -> Result<Recording, RecordError> {
        let mut reader = RecordReader::open(path)?;
        let fmt = |message: String| RecordError::Format {
            path: path.display().to_string(),
            message,
        };
        let (mut session, mut calibration, mut line) = (None, None, None);
        let mut early = VecDeque::new();
        while session.is_none() || calibration.is_none() {
            let Some(m) = reader.next_message() else {
                let what = if session.is_none() {
                    "session"
                } else {
                    "calibration"
                };
                let damage: Vec<String> =
                    reader.damage().iter().map(|d| d.message.clone()).collect();
                return Err(fmt(format!(
                    "no {what} message: not an irid recording, or its start is damaged{}",
                    if damage.is_empty() {
                        String::new()
                    } else {
                        format!(" ({})", damage.join("; "))
                    }
                )));
            };
            match m.topic.as_str() {
                TOPIC_SESSION => {
                    session = Some(
                        serde_json::from_slice::<Session>(&m.data)
                            .map_err(|e| fmt(format!("session: {e}")))?,
                    )
                }
                TOPIC_CALIBRATION => calibration = Some(m.data),
                TOPIC_LINE => line = Some(m.data),
                _ if early.len() < 64 => early.push_back(m),
                _ => {}
            }
        }
        let session: Session = session.expect("set above");
        let px = u64::from(session.width) * u64::from(session.height);
        if px == 0 || px > 1 << 26 || session.order.len() != session.bands_nm.len() {
            return Err(fmt(format!(
                "session: implausible {}×{} frames or {} bands in an order of {}",
                session.width,
                session.height,
                session.bands_nm.len(),
                session.order.len()
            )));
        }
        let mut cursor = Cursor {
            reader,
            frames: VecDeque::new(),
            tunes: VecDeque::new(),
            stats: ReplayStats::default(),
        };
        for m in early {
            match m.topic.as_str() {
                TOPIC_FRAME => cursor.frames.push_back(m),
                TOPIC_FILTER => {
                    if let Ok(ev) = serde_json::from_slice(&m.data) {
                        cursor.tunes.push_back(ev);
                    }
                }
                _ => {}
            }
        }
        Ok(Recording {
            session,
            calibration: calibration.expect("set above"),
            line,
            cursor: Arc::new(Mutex::new(cursor)),
        })
    }

    /// The camera: recorded frames in order, as fast as possible or paced
    /// by their timestamps at `speed` × real time.
    pub fn source(&self, speed: Option<f64>) -> ReplaySource {
        let s = &self.session;
        ReplaySource {
            cursor: self.cursor.clone(),
            info: CameraInfo {
                id: format!("replay of {}", s.camera_id),
                width: s.width,
                height: s.height,
                format: s.format,
                exposure_us: s.exposure_us,
                gain: s.gain,
            },
            speed: speed.filter(|x| x.is_finite() && *x > 0.0),
            t0: None,
            progress: None,
        }
    }

    /// The filter: answers each command with the recorded settled time.
    pub fn tuner(&self) -> ReplayTuner {
        ReplayTuner {
            cursor: self.cursor.clone(),
            label: format!("recorded {}", self.session.filter),
        }
    }

    /// What replay found so far (call after the run for the totals).
    pub fn stats(&self) -> ReplayStats {
        let c = lock(&self.cursor);
        let mut s = c.stats.clone();
        s.damage = c.reader.damage().to_vec();
        s.closed = c.reader.closed();
        s
    }
}

/// Progress callback: (bytes read, file size).
pub type Progress = Box<dyn FnMut(u64, u64) + Send>;

/// Recorded frames as a camera.
pub struct ReplaySource {
    cursor: Arc<Mutex<Cursor>>,
    info: CameraInfo,
    speed: Option<f64>,
    t0: Option<(Instant, u64)>,
    progress: Option<Progress>,
}

impl ReplaySource {
    /// Report progress after each frame.
    pub fn with_progress(mut self, p: Progress) -> Self {
        self.progress = Some(p);
        self
    }

    fn pace(&mut self, ts: u64) {
        let Some(speed) = self.speed else { return };
        let (start, ts0) = *self.t0.get_or_insert((Instant::now(), ts));
        let due = Duration::from_secs_f64(ts.saturating_sub(ts0) as f64 / 1e9 / speed);
        if let Some(wait) = due.checked_sub(start.elapsed()) {
            std::thread::sleep(wait);
        }
    }
}

impl FrameSource for ReplaySource {
    fn info(&self) -> CameraInfo {
        self.info.clone()
    }

    fn next_frame(&mut self, out: &mut Frame, _timeout: Duration) -> Result<(), CameraError> {
        let (m, pos) = {
            let mut c = lock(&self.cursor);
            loop {
                if let Some(m) = c.frames.pop_front() {
                    break (m, c.reader.progress());
                }
                if !c.pump() {
                    return Err(CameraError::Ended);
                }
            }
        };
        let meta = match decode_frame_meta(&m.data) {
            Ok(meta) => meta,
            Err(message) => {
                lock(&self.cursor).stats.bad_frames += 1;
                return Err(CameraError::BadFrame { seq: 0, message });
            }
        };
        if out.data.len() < meta.len() {
            lock(&self.cursor).stats.bad_frames += 1;
            return Err(CameraError::BadFrame {
                seq: meta.seq,
                message: format!(
                    "{}×{} frame in a recording of {}×{} frames",
                    meta.width, meta.height, self.info.width, self.info.height
                ),
            });
        }
        decode_samples(&m.data, &mut out.data[..meta.len()]);
        out.meta = meta;
        self.pace(meta.timestamp_ns);
        lock(&self.cursor).stats.frames += 1;
        if let Some(p) = self.progress.as_mut() {
            p(pos.0, pos.1);
        }
        Ok(())
    }

    fn set_exposure(&mut self, _exposure_us: u32) -> Result<u32, CameraError> {
        Err(CameraError::Unsupported(
            "a recording's exposure is what it was".into(),
        ))
    }
}

/// Recorded filter commands as a filter.
pub struct ReplayTuner {
    cursor: Arc<Mutex<Cursor>>,
    label: String,
}

impl BandTuner for ReplayTuner {
    fn tune(&mut self, nm: f64, now_ns: u64) -> Result<u64, TuneError> {
        let mut c = lock(&self.cursor);
        let mut skipped = 0u64;
        loop {
            while let Some(ev) = c.tunes.pop_front() {
                if ev.nm.to_bits() != nm.to_bits() {
                    skipped += 1;
                    continue;
                }
                c.stats.diverged += u64::from(skipped > 0 || ev.now_ns != now_ns);
                return match (ev.settled_ns, ev.error) {
                    (Some(t), _) => Ok(t),
                    (None, Some(e)) if e.starts_with("timeout") => Err(TuneError::Timeout {
                        nm,
                        timeout: Duration::ZERO,
                    }),
                    (None, e) => Err(TuneError::Refused {
                        nm,
                        message: format!("(recorded) {}", e.unwrap_or_default()),
                    }),
                };
            }
            if c.frames.len() >= MAX_READ_AHEAD || !c.pump() {
                // No such command recorded: the band never settles, the
                // remaining frames are discarded and the stream ends.
                c.stats.diverged += 1;
                return Ok(u64::MAX);
            }
        }
    }

    fn describe(&self) -> String {
        self.label.clone()
    }
}
