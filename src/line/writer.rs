//! The line's output worker: EXR strip segments and published messages,
//! off the row path.
//!
//! [`super::output::LineOutput`] computes statistics and alarms as each row
//! arrives and hands the worker jobs — a message to publish, or a finished
//! segment (its rows and its message, whose `file` the worker fills in once
//! the file is written). The worker runs the jobs in order, so messages go
//! out in the same order as when everything ran on one thread, and a
//! segment's message is sent only after its file exists.
//!
//! In the background (the default) the worker has its own thread fed by a
//! bounded channel of [`JOB_QUEUE`] jobs: a row never waits for a file
//! write unless the disk falls that far behind, in which case the row path
//! waits (counted in [`Writer::waits`]) rather than hold unbounded memory
//! or lose a segment. Inline, the jobs run at once (the reference).

use super::output::Publisher;
use super::solve::WebRowOut;
use crate::estimate::maps::MapMeta;
use crate::estimate::ParamMaps;
use crate::io::exr_maps::{map_attributes, write_channels, Channels};
use crossbeam_channel::{Sender, TrySendError};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

/// Jobs the background worker may have waiting (segments and messages).
pub const JOB_QUEUE: usize = 64;

/// One thing for the worker to do.
pub(super) enum Job {
    /// Publish `payload` on `topic`.
    Publish { topic: String, payload: String },
    /// Write segment `index` (its rows) and publish its message on
    /// `topic`, with `"file"` set to the file written.
    Segment {
        index: u64,
        rows: Vec<WebRowOut>,
        topic: String,
        msg: serde_json::Value,
    },
    /// The map metadata for the segments that follow.
    Meta(Box<MapMeta>),
}

/// What does the jobs.
pub(super) struct Worker {
    out_dir: Option<PathBuf>,
    publishers: Vec<Box<dyn Publisher + Send>>,
    files: Vec<PathBuf>,
    /// The estimator's map metadata, written with each segment.
    meta: MapMeta,
}

impl Worker {
    fn run(&mut self, job: Job) -> Result<(), String> {
        match job {
            Job::Publish { topic, payload } => self.publish(&topic, &payload),
            Job::Meta(meta) => self.meta = *meta,
            Job::Segment {
                index,
                rows,
                topic,
                mut msg,
            } => {
                let file = match &self.out_dir {
                    Some(dir) => Some(write_segment(dir, index, &rows, &self.meta)?),
                    None => None,
                };
                msg["file"] = serde_json::json!(file.as_ref().map(|f| f.display().to_string()));
                self.files.extend(file);
                self.publish(&topic, &msg.to_string());
            }
        }
        Ok(())
    }

    fn publish(&mut self, topic: &str, payload: &str) {
        for p in &mut self.publishers {
            p.publish(topic, payload);
        }
    }

    fn flush(&mut self) {
        for p in &mut self.publishers {
            p.flush();
        }
    }
}

/// The worker, inline or on its thread.
pub(super) enum Writer {
    /// Jobs run at once.
    Inline(Worker),
    /// Jobs go to the worker's thread.
    Background {
        tx: Option<Sender<Job>>,
        thread: Option<JoinHandle<Option<Worker>>>,
        /// The first error the worker met (it stops there).
        failed: Arc<Mutex<Option<String>>>,
        /// Jobs that found the queue full and waited.
        waits: u64,
    },
}

impl Writer {
    /// A writer of segments to `out_dir` (None: no files) and messages to
    /// `publishers`.
    pub fn new(
        out_dir: Option<PathBuf>,
        publishers: Vec<Box<dyn Publisher + Send>>,
        background: bool,
    ) -> Writer {
        let worker = Worker {
            out_dir,
            publishers,
            files: Vec::new(),
            meta: MapMeta::default(),
        };
        if !background {
            return Writer::Inline(worker);
        }
        let (tx, rx) = crossbeam_channel::bounded::<Job>(JOB_QUEUE);
        // The worker goes over once the thread runs: if no thread can be
        // started it is still here, and the jobs run inline.
        let (give, take) = crossbeam_channel::bounded::<Worker>(1);
        let failed = Arc::new(Mutex::new(None));
        let f = failed.clone();
        let thread = std::thread::Builder::new()
            .name("irid-line-output".into())
            .spawn(move || {
                let mut worker = take.recv().ok()?;
                for job in rx {
                    if let Err(e) = worker.run(job) {
                        *f.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
                        break;
                    }
                }
                worker.flush();
                Some(worker)
            });
        let worker = match thread {
            Ok(t) => match give.send(worker) {
                Ok(()) => {
                    return Writer::Background {
                        tx: Some(tx),
                        thread: Some(t),
                        failed,
                        waits: 0,
                    }
                }
                Err(back) => back.0,
            },
            Err(e) => {
                tracing::warn!(%e, "no output thread; segments are written inline");
                worker
            }
        };
        Writer::Inline(worker)
    }

    /// The map metadata for the segments that follow (queued in order
    /// with them). A worker that has failed reports it at the next
    /// segment's `submit`.
    pub fn set_map_meta(&mut self, meta: MapMeta) {
        let _ = self.submit(Job::Meta(Box::new(meta)));
    }

    /// Do `job` (inline) or queue it; an error the worker met earlier is
    /// returned here.
    pub fn submit(&mut self, job: Job) -> Result<(), String> {
        match self {
            Writer::Inline(w) => w.run(job),
            Writer::Background {
                tx, failed, waits, ..
            } => {
                if let Some(e) = failed.lock().unwrap_or_else(|p| p.into_inner()).take() {
                    return Err(e);
                }
                let Some(tx) = tx else {
                    return Err("the output has finished".into());
                };
                let sent = match tx.try_send(job) {
                    Ok(()) => Ok(()),
                    Err(TrySendError::Full(job)) => {
                        *waits += 1;
                        tx.send(job).map_err(|_| ())
                    }
                    Err(TrySendError::Disconnected(_)) => Err(()),
                };
                sent.map_err(|()| Self::stopped(failed))
            }
        }
    }

    fn stopped(failed: &Mutex<Option<String>>) -> String {
        failed
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take()
            .unwrap_or_else(|| "the output thread stopped".into())
    }

    /// Run every job left, flush the publishers; the files written.
    pub fn finish(&mut self) -> Result<Vec<PathBuf>, String> {
        match self {
            Writer::Inline(w) => {
                w.flush();
                Ok(std::mem::take(&mut w.files))
            }
            Writer::Background {
                tx, thread, failed, ..
            } => {
                drop(tx.take());
                let worker = match thread.take() {
                    Some(t) => t
                        .join()
                        .map_err(|_| "the output thread panicked".to_string())?
                        .map(|w| w.files)
                        .unwrap_or_default(),
                    None => return Ok(Vec::new()),
                };
                if let Some(e) = failed.lock().unwrap_or_else(|p| p.into_inner()).take() {
                    return Err(e);
                }
                Ok(worker)
            }
        }
    }

    /// Jobs that waited for a full queue.
    pub fn waits(&self) -> u64 {
        match self {
            Writer::Inline(_) => 0,
            Writer::Background { waits, .. } => *waits,
        }
    }
}

impl Drop for Writer {
    fn drop(&mut self) {
        if let Writer::Background { tx, thread, .. } = self {
            drop(tx.take());
            if let Some(t) = thread.take() {
                let _ = t.join();
            }
        }
    }
}

/// Write one segment, atomically (temporary name, renamed).
fn write_segment(
    dir: &Path,
    index: u64,
    rows: &[WebRowOut],
    meta: &MapMeta,
) -> Result<PathBuf, String> {
    let (w, h) = (rows[0].estimates.len(), rows.len());
    let mut maps = ParamMaps::new(w, h);
    maps.meta = meta.clone();
    for (y, r) in rows.iter().enumerate() {
        for (x, e) in r.estimates.iter().enumerate() {
            maps.set(x, y, e);
        }
    }
    let (first, last) = (&rows[0], &rows[h - 1]);
    let mut attributes = map_attributes(&maps.meta);
    attributes.extend([
        ("irid.segment".to_string(), index.to_string()),
        ("irid.web_first_row".to_string(), first.index.to_string()),
        ("irid.web_rows".to_string(), h.to_string()),
        ("irid.time_first_ns".to_string(), first.time_ns.to_string()),
        ("irid.time_last_ns".to_string(), last.time_ns.to_string()),
    ]);
    let data = Channels {
        width: w,
        height: h,
        channels: maps
            .channels()
            .iter()
            .map(|(n, v)| (n.to_string(), v.to_vec()))
            .collect(),
        attributes,
    };
    let name = format!("strip-{index:06}.exr");
    let tmp = dir.join(format!(".{name}.tmp"));
    let path = dir.join(name);
    write_channels(&tmp, &data).map_err(|e| e.to_string())?;
    std::fs::rename(&tmp, &path)
        .map_err(|e| format!("renaming {} to {}: {e}", tmp.display(), path.display()))?;
    Ok(path)
}
