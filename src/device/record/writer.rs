//! The recorder: an MCAP writer on its own thread.
//!
//! Capture hands it frames and events through a [`RecordTap`] (a
//! [`CaptureTap`] for the runner) and a [`RecordingTuner`] (wrapping the
//! filter). Both only ever `try_send` into one bounded channel: frames are
//! copied into buffers from a fixed pool, and when the pool is empty (the
//! disk is behind) the frame's pixels are dropped and counted — its
//! metadata and verdict are still recorded — and capture goes on.
//!
//! The recorder closes a chunk and syncs the file when a sweep's last band
//! is recorded (and at least once a second), so a crash loses at most the
//! sweep in progress.

use super::{
    encode_frame, json_schema, RecordError, RecorderEvent, SeqEvent, Session, TuneEvent, TOPICS,
    TOPIC_CALIBRATION, TOPIC_FILTER, TOPIC_FRAME, TOPIC_LINE, TOPIC_RECORDER, TOPIC_SEQUENCER,
    TOPIC_SESSION,
};
use crate::device::camera::Frame;
use crate::pipeline::runner::CaptureTap;
use crate::pipeline::sequencer::{BandTuner, Discard, TuneError, Verdict};
use crossbeam_channel::{Receiver, Sender, TrySendError};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Chunk compression.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compression {
    /// None.
    None,
    /// zstd (default level, on the recorder thread).
    Zstd,
    /// LZ4.
    Lz4,
}

/// How to record.
#[derive(Clone, Debug)]
pub struct RecordOptions {
    /// Chunk compression.
    pub compression: Compression,
    /// Frame buffers the recorder may hold (0: two sweeps' worth, at most
    /// 256 MiB).
    pub frame_pool: usize,
}

impl Default for RecordOptions {
    fn default() -> Self {
        RecordOptions {
            compression: Compression::Lz4,
            frame_pool: 0,
        }
    }
}

/// What a recording cost.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RecordStats {
    /// Frames written with their pixels.
    pub frames_written: u64,
    /// Frames whose pixels the recorder dropped (disk behind).
    pub frames_dropped: u64,
    /// Events the recorder dropped (never expected).
    pub events_dropped: u64,
    /// Message payload bytes (uncompressed).
    pub raw_bytes: u64,
    /// File size.
    pub file_bytes: u64,
    /// Wall time from start to close, s.
    pub elapsed_s: f64,
    /// Time the recorder thread spent encoding, compressing and writing, s.
    pub busy_s: f64,
    /// Chunks closed by a sweep boundary or the clock (file synced).
    pub flushes: u64,
}

impl RecordStats {
    /// Uncompressed MB per second of wall time (what the line produced).
    pub fn mb_per_s(&self) -> f64 {
        self.raw_bytes as f64 / 1e6 / self.elapsed_s.max(1e-9)
    }
    /// Uncompressed MB per second of recorder busy time (what it can take).
    pub fn capacity_mb_per_s(&self) -> f64 {
        self.raw_bytes as f64 / 1e6 / self.busy_s.max(1e-9)
    }
    /// Raw bytes / file bytes.
    pub fn ratio(&self) -> f64 {
        self.raw_bytes as f64 / (self.file_bytes as f64).max(1.0)
    }
}

enum Msg {
    Frame(Frame, Option<Verdict>),
    /// No buffer: metadata and verdict only.
    FrameDropped(crate::device::camera::FrameMeta, Option<Verdict>),
    /// A frame read while capture held the sweep back: its verdict only.
    Held(crate::device::camera::FrameMeta),
    Missing {
        sweep: u64,
        band: usize,
    },
    Abandoned {
        sweep: u64,
    },
    Tune(TuneEvent),
    Close,
}

#[derive(Default)]
struct Shared {
    frames_dropped: AtomicU64,
    events_dropped: AtomicU64,
}

/// A running recorder; [`Recorder::finish`] closes the file.
pub struct Recorder {
    tx: Sender<Msg>,
    free: Receiver<Frame>,
    give_back: Sender<Frame>,
    shared: Arc<Shared>,
    thread: Option<std::thread::JoinHandle<Result<RecordStats, RecordError>>>,
}

/// Hands the runner's capture stage to the recorder (see the module header).
pub struct RecordTap {
    tx: Sender<Msg>,
    free: Receiver<Frame>,
    give_back: Sender<Frame>,
    shared: Arc<Shared>,
}

/// A filter whose every command is recorded.
pub struct RecordingTuner<'a> {
    inner: &'a mut dyn BandTuner,
    tx: Sender<Msg>,
    shared: Arc<Shared>,
}

fn mcap_err(path: &Path) -> impl Fn(mcap::McapError) -> RecordError + '_ {
    move |e| RecordError::Mcap {
        path: path.display().to_string(),
        message: e.to_string(),
    }
}

impl Recorder {
    /// Create `path` and start recording: the session and the calibration
    /// (`.ircal` bytes) are written and synced before this returns.
    pub fn create(
        path: &Path,
        session: &Session,
        calibration: &[u8],
        opts: &RecordOptions,
    ) -> Result<Recorder, RecordError> {
        Recorder::create_with_line(path, session, None, calibration, opts)
    }

    /// [`Recorder::create`] for a production line: `line` (the `/irid/line`
    /// message, JSON) is written between the session and the calibration.
    pub fn create_with_line(
        path: &Path,
        session: &Session,
        line: Option<&[u8]>,
        calibration: &[u8],
        opts: &RecordOptions,
    ) -> Result<Recorder, RecordError> {
        let io = |source| RecordError::Io {
            path: path.display().to_string(),
            source,
        };
        let file = File::create(path).map_err(io)?;
        let sync = file.try_clone().map_err(io)?;
        let compression = match opts.compression {
            Compression::None => None,
            Compression::Zstd => Some(mcap::Compression::Zstd),
            Compression::Lz4 => Some(mcap::Compression::Lz4),
        };
        let mut w = mcap::WriteOptions::new()
            .compression(compression)
            .compression_threads(0)
            .chunk_size(Some(4 << 20))
            .profile("irid")
            .library(format!("irid {}", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::with_capacity(1 << 20, file))
            .map_err(mcap_err(path))?;
        for (i, topic) in TOPICS.iter().enumerate() {
            let (schema, encoding) = match *topic {
                TOPIC_FRAME => (0, "irid.frame"),
                TOPIC_CALIBRATION => (0, "irid.ircal"),
                t => {
                    let title = match t {
                        TOPIC_SESSION => "irid.Session",
                        TOPIC_SEQUENCER => "irid.SequencerEvent",
                        TOPIC_FILTER => "irid.FilterEvent",
                        TOPIC_LINE => "irid.LineConfig",
                        _ => "irid.RecorderEvent",
                    };
                    let id = w
                        .add_schema_with_id(
                            i as u16 + 1,
                            title,
                            "jsonschema",
                            json_schema(t).as_bytes(),
                        )
                        .map_err(mcap_err(path))?;
                    (id, "json")
                }
            };
            w.add_channel_with_id(i as u16 + 1, schema, topic, encoding, &BTreeMap::new())
                .map_err(mcap_err(path))?;
        }
        let (sync_tx, sync_rx) = crossbeam_channel::bounded::<()>(1);
        let synced = sync.try_clone().map_err(io)?;
        std::thread::Builder::new()
            .name("irid-record-sync".into())
            .spawn(move || {
                for () in sync_rx.iter() {
                    let _ = synced.sync_data();
                }
            })
            .map_err(io)?;
        let mut out = Out {
            w,
            sync,
            syncer: Some(sync_tx),
            path: path.to_path_buf(),
            sequence: 0,
            stats: RecordStats::default(),
            buf: Vec::new(),
        };
        let session_json = serde_json::to_vec(session).expect("session serialises");
        out.write(TOPIC_SESSION, 0, &session_json)?;
        if let Some(line) = line {
            out.write(TOPIC_LINE, 0, line)?;
        }
        out.write(TOPIC_CALIBRATION, 0, calibration)?;
        out.flush()?;

        let (w, h) = (session.width as usize, session.height as usize);
        let frame_bytes = (w * h * 2).max(1);
        // At least two sweeps, else up to 256 MiB (a slow disk or fsync
        // is ridden out, not dropped), at most 4096 buffers.
        let pool = if opts.frame_pool > 0 {
            opts.frame_pool
        } else {
            ((256usize << 20) / frame_bytes).clamp(2 * session.order.len().max(2), 4096)
        };
        let (free_tx, free) = crossbeam_channel::bounded::<Frame>(pool);
        for _ in 0..pool {
            let _ = free_tx.try_send(Frame::with_size(
                session.width,
                session.height,
                session.format,
            ));
        }
        // Room for every pooled frame plus plenty of small events.
        let (tx, rx) = crossbeam_channel::bounded::<Msg>(pool + 4096);
        let shared = Arc::new(Shared::default());
        let last_band = session.order.last().copied().unwrap_or(0);
        let sh = shared.clone();
        let give_back = free_tx.clone();
        let thread = std::thread::Builder::new()
            .name("irid-record".into())
            .spawn(move || out.run(rx, free_tx, last_band, sh))
            .map_err(io)?;
        Ok(Recorder {
            tx,
            free,
            give_back,
            shared,
            thread: Some(thread),
        })
    }

    /// A tap for [`crate::pipeline::runner::run_tapped`].
    pub fn tap(&self) -> RecordTap {
        RecordTap {
            tx: self.tx.clone(),
            free: self.free.clone(),
            give_back: self.give_back.clone(),
            shared: self.shared.clone(),
        }
    }

    /// Wrap `inner` so that every command is recorded.
    pub fn tuner<'a>(&self, inner: &'a mut dyn BandTuner) -> RecordingTuner<'a> {
        RecordingTuner {
            inner,
            tx: self.tx.clone(),
            shared: self.shared.clone(),
        }
    }

    /// Write what is queued, the summary, and close the file.
    pub fn finish(mut self) -> Result<RecordStats, RecordError> {
        // Blocking here is fine: capture is over.
        let _ = self.tx.send(Msg::Close);
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(r)) => r,
            _ => Err(RecordError::Format {
                path: "recorder".into(),
                message: "the recorder thread panicked".into(),
            }),
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        if let Some(t) = self.thread.take() {
            let _ = self.tx.send(Msg::Close);
            let _ = t.join();
        }
    }
}

fn send_event(tx: &Sender<Msg>, shared: &Shared, m: Msg) {
    if let Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) = tx.try_send(m) {
        shared.events_dropped.fetch_add(1, Ordering::Relaxed);
    }
}

impl CaptureTap for RecordTap {
    fn on_frame(&mut self, frame: &Frame, verdict: Option<Verdict>) {
        if verdict == Some(Verdict::Discard(Discard::Held)) {
            // Read while capture held the sweep back: its pixels were
            // never read, and a replay must not see it as a frame.
            send_event(&self.tx, &self.shared, Msg::Held(frame.meta));
            return;
        }
        let pixels = frame.pixels().ok();
        let buf = match (pixels, self.free.try_recv()) {
            (Some(px), Ok(mut b)) => {
                b.meta = frame.meta;
                // Sized for the session's frames: no allocation.
                b.data.clear();
                b.data.extend_from_slice(px);
                Some(b)
            }
            (_, Ok(b)) => {
                // A malformed frame: its metadata only.
                let _ = self.give_back.try_send(b);
                None
            }
            (_, Err(_)) => None,
        };
        let m = match buf {
            Some(b) => Msg::Frame(b, verdict),
            None => {
                if pixels.is_some() {
                    self.shared.frames_dropped.fetch_add(1, Ordering::Relaxed);
                }
                Msg::FrameDropped(frame.meta, verdict)
            }
        };
        match self.tx.try_send(m) {
            Ok(()) => {}
            Err(TrySendError::Full(m) | TrySendError::Disconnected(m)) => {
                if let Msg::Frame(b, _) = m {
                    self.shared.frames_dropped.fetch_add(1, Ordering::Relaxed);
                    let _ = self.give_back.try_send(b);
                }
                self.shared.events_dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    fn on_missing(&mut self, sweep: u64, band: usize) {
        send_event(&self.tx, &self.shared, Msg::Missing { sweep, band });
    }

    fn on_abandoned(&mut self, sweep: u64) {
        send_event(&self.tx, &self.shared, Msg::Abandoned { sweep });
    }
}

impl BandTuner for RecordingTuner<'_> {
    fn tune(&mut self, nm: f64, now_ns: u64) -> Result<u64, TuneError> {
        let r = self.inner.tune(nm, now_ns);
        let ev = TuneEvent {
            nm,
            now_ns,
            settled_ns: r.as_ref().ok().copied(),
            error: r.as_ref().err().map(|e| match e {
                TuneError::Timeout { .. } => format!("timeout: {e}"),
                TuneError::Refused { .. } => format!("refused: {e}"),
            }),
        };
        send_event(&self.tx, &self.shared, Msg::Tune(ev));
        r
    }

    fn describe(&self) -> String {
        self.inner.describe()
    }
}

/// The recorder thread's state.
struct Out {
    w: mcap::Writer<BufWriter<File>>,
    sync: File,
    /// Requests to the fsync thread.
    syncer: Option<Sender<()>>,
    path: std::path::PathBuf,
    sequence: u32,
    stats: RecordStats,
    buf: Vec<u8>,
}

fn verdict_event(seq: u64, v: Option<Verdict>) -> SeqEvent {
    let (verdict, sweep, band) = match v {
        Some(Verdict::Accept { sweep, band }) => ("accept", Some(sweep), Some(band)),
        Some(Verdict::Discard(d)) => (
            match d {
                Discard::Settling => "settling",
                Discard::Stale => "stale",
                Discard::Abandoned => "abandoned",
                Discard::Bad => "bad",
                Discard::Done => "done",
                Discard::Held => "held",
            },
            None,
            None,
        ),
        None => ("pool_empty", None, None),
    };
    SeqEvent::Frame {
        seq,
        verdict: verdict.into(),
        sweep,
        band,
    }
}

impl Out {
    fn write(&mut self, topic: &str, time_ns: u64, data: &[u8]) -> Result<(), RecordError> {
        let id = TOPICS
            .iter()
            .position(|t| *t == topic)
            .expect("known topic") as u16
            + 1;
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id: id,
            sequence: self.sequence,
            log_time: time_ns,
            publish_time: time_ns,
        };
        self.w
            .write_to_known_channel(&header, data)
            .map_err(mcap_err(&self.path))?;
        self.stats.raw_bytes += data.len() as u64;
        Ok(())
    }

    fn write_json<T: serde::Serialize>(
        &mut self,
        topic: &str,
        time_ns: u64,
        v: &T,
    ) -> Result<(), RecordError> {
        let data = serde_json::to_vec(v).expect("events serialise");
        self.write(topic, time_ns, &data)
    }

    /// Close the chunk and hand it to the OS (what a killed process
    /// keeps), then ask the sync thread to make it durable (what a power
    /// cut keeps): a slow fsync never stalls the recorder.
    fn flush(&mut self) -> Result<(), RecordError> {
        self.w.flush().map_err(mcap_err(&self.path))?;
        if let Some(s) = &self.syncer {
            // One request pending is enough: it syncs everything written.
            let _ = s.try_send(());
        }
        self.stats.flushes += 1;
        Ok(())
    }

    /// Write one message; true when it ends a sweep.
    fn on_msg(
        &mut self,
        m: Msg,
        last_band: usize,
        free: &Sender<Frame>,
    ) -> Result<bool, RecordError> {
        let sweep_end = |v: &Option<Verdict>| matches!(v, Some(Verdict::Accept { band, .. }) if *band == last_band);
        Ok(match m {
            Msg::Frame(f, v) => {
                let mut buf = std::mem::take(&mut self.buf);
                let n = f.meta.len().min(f.data.len());
                encode_frame(&f.meta, &f.data[..n], &mut buf);
                let (t, seq) = (f.meta.timestamp_ns, f.meta.seq);
                let _ = free.try_send(f);
                let r = self.write(TOPIC_FRAME, t, &buf);
                self.buf = buf;
                r?;
                self.stats.frames_written += 1;
                self.write_json(TOPIC_SEQUENCER, t, &verdict_event(seq, v))?;
                sweep_end(&v)
            }
            Msg::FrameDropped(meta, v) => {
                let t = meta.timestamp_ns;
                self.write_json(TOPIC_RECORDER, t, &RecorderEvent::Dropped { seq: meta.seq })?;
                self.write_json(TOPIC_SEQUENCER, t, &verdict_event(meta.seq, v))?;
                sweep_end(&v)
            }
            Msg::Held(meta) => {
                let v = Some(Verdict::Discard(Discard::Held));
                self.write_json(
                    TOPIC_SEQUENCER,
                    meta.timestamp_ns,
                    &verdict_event(meta.seq, v),
                )?;
                false
            }
            Msg::Missing { sweep, band } => {
                self.write_json(TOPIC_SEQUENCER, 0, &SeqEvent::Missing { sweep, band })?;
                band == last_band
            }
            Msg::Abandoned { sweep } => {
                self.write_json(TOPIC_SEQUENCER, 0, &SeqEvent::Abandoned { sweep })?;
                true
            }
            Msg::Tune(ev) => {
                self.write_json(TOPIC_FILTER, ev.now_ns, &ev)?;
                false
            }
            Msg::Close => false,
        })
    }

    /// The thread: write until `Close`, flushing per sweep and per second.
    fn run(
        mut self,
        rx: Receiver<Msg>,
        free: Sender<Frame>,
        last_band: usize,
        shared: Arc<Shared>,
    ) -> Result<RecordStats, RecordError> {
        let start = Instant::now();
        let mut busy = Duration::ZERO;
        let mut last_flush = Instant::now();
        let mut dirty = false;
        loop {
            let m = match rx.recv_timeout(Duration::from_millis(250)) {
                Ok(m) => m,
                Err(crossbeam_channel::RecvTimeoutError::Timeout) => {
                    if dirty && last_flush.elapsed() >= Duration::from_secs(1) {
                        let t = Instant::now();
                        self.flush()?;
                        busy += t.elapsed();
                        (dirty, last_flush) = (false, Instant::now());
                    }
                    continue;
                }
                Err(crossbeam_channel::RecvTimeoutError::Disconnected) => Msg::Close,
            };
            let close = matches!(m, Msg::Close);
            if close {
                break;
            }
            let t = Instant::now();
            let end = self.on_msg(m, last_band, &free)?;
            dirty = true;
            if end || last_flush.elapsed() >= Duration::from_secs(1) {
                self.flush()?;
                (dirty, last_flush) = (false, Instant::now());
            }
            busy += t.elapsed();
        }
        let t = Instant::now();
        // What arrived after Close (nothing, normally) is not waited for.
        while let Ok(m) = rx.try_recv() {
            if !matches!(m, Msg::Close) {
                self.on_msg(m, last_band, &free)?;
            }
        }
        self.stats.frames_dropped = shared.frames_dropped.load(Ordering::Relaxed);
        self.stats.events_dropped = shared.events_dropped.load(Ordering::Relaxed);
        let closed = RecorderEvent::Closed {
            frames_written: self.stats.frames_written,
            frames_dropped: self.stats.frames_dropped,
            events_dropped: self.stats.events_dropped,
        };
        self.write_json(TOPIC_RECORDER, 0, &closed)?;
        self.w.finish().map_err(mcap_err(&self.path))?;
        let path = self.path.clone();
        let io = |source| RecordError::Io {
            path: path.display().to_string(),
            source,
        };
        let mut bw = self.w.into_inner();
        std::io::Write::flush(&mut bw).map_err(io)?;
        drop(self.syncer);
        self.sync.sync_all().map_err(io)?;
        busy += t.elapsed();
        self.stats.file_bytes = std::fs::metadata(&path).map_or(0, |m| m.len());
        self.stats.elapsed_s = start.elapsed().as_secs_f64();
        self.stats.busy_s = busy.as_secs_f64();
        Ok(self.stats)
    }
}
