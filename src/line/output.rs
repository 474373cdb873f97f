//! What the line gets: per-row lane statistics feeding the trend, the
//! capability windows and the recipe's alarms; the strip as EXR segments
//! of N web rows written atomically; per-segment statistics and alarms as
//! JSON messages to every [`Publisher`] (JSON lines on stdout, MQTT).
//!
//! Messages (one JSON object each; NaN is `null`):
//! - topic `…/segment`: `{"type":"segment","segment":k,"first_row":…,
//!   "rows":N,"t_first_ns":…,"t_last_ns":…,"rows_missing_bands":…,
//!   "file":…,"lanes":[{"lane":i,"mean_nm","sigma_nm","min_nm","max_nm",
//!   "valid_fraction","nonuniformity_pct","md_mean_nm",
//!   "md_slope_nm_per_krow","cp","cpk","target_nm","lower_nm","upper_nm",
//!   "alarm"}]}`;
//! - topic `…/alarm`: `{"type":"alarm","event":"raised"|"cleared",
//!   "lane","side":"high"|"low","from_row","at_row","rows","mean_nm","spec"}`,
//!   sent as soon as the row that raises or clears it is emitted.
//!
//! A segment file is written to a temporary name in the same directory and
//! renamed: a reader never sees half a segment. Files and messages are
//! written by the output worker ([`super::writer`]), on its own thread by
//! default, in the order the rows produced them: a row handed to this
//! sink never waits for a file write.

use super::recipe::{Alarm, Alarms, Recipe};
use super::run::WebRowSink;
use super::solve::WebRowOut;
use super::stats::{lane_stats, row_stats, LaneTracker, Lanes};
use super::writer::{Job, Writer};
use serde_json::json;
use std::path::PathBuf;

/// Where messages go.
pub trait Publisher {
    /// Send one message (never blocks the line: a publisher that cannot
    /// deliver now queues or drops and counts).
    fn publish(&mut self, topic: &str, payload: &str);
    /// Wait (bounded) for queued messages to go out, at the end of a run.
    fn flush(&mut self) {}
}

/// JSON lines to any writer (stdout in the CLI): one message per line.
pub struct JsonLines<W: std::io::Write>(pub W);

impl<W: std::io::Write> Publisher for JsonLines<W> {
    fn publish(&mut self, _topic: &str, payload: &str) {
        // A closed stdout must not stop the line.
        let _ = writeln!(self.0, "{payload}");
    }
    fn flush(&mut self) {
        let _ = self.0.flush();
    }
}

/// Messages kept in memory (tests).
#[derive(Default)]
pub struct Collected(pub Vec<(String, String)>);

impl Publisher for Collected {
    fn publish(&mut self, topic: &str, payload: &str) {
        self.0.push((topic.to_string(), payload.to_string()));
    }
}

/// How the output is organised.
#[derive(Clone, Debug)]
pub struct OutputConfig {
    /// Web rows per segment.
    pub segment_rows: usize,
    /// Cross-web lanes.
    pub lanes: Lanes,
    /// Where EXR segments go (None: not written).
    pub out_dir: Option<PathBuf>,
    /// Topic prefix (`irid/line` → `irid/line/segment`, `irid/line/alarm`).
    pub topic: String,
}

/// The line's output sink.
pub struct LineOutput {
    cfg: OutputConfig,
    recipe: Option<Recipe>,
    alarms: Option<Alarms>,
    tracker: LaneTracker,
    seg: Vec<WebRowOut>,
    seg_index: u64,
    events: Vec<Alarm>,
    active: Vec<bool>,
    writer: Writer,
    /// Every alarm event so far.
    pub alarm_log: Vec<Alarm>,
    /// Segments finished.
    pub segments: u64,
    /// Segment files written (known once the run has finished).
    pub files: Vec<PathBuf>,
}

impl LineOutput {
    /// An output; `recipe` gives limits and alarms (without: statistics
    /// only). Files and messages are written by a worker thread.
    pub fn new(
        cfg: OutputConfig,
        recipe: Option<Recipe>,
        publishers: Vec<Box<dyn Publisher + Send>>,
    ) -> LineOutput {
        Self::with_writer(cfg, recipe, publishers, true)
    }

    /// As [`LineOutput::new`], files and messages written inline, in the
    /// row path (the reference the threaded output is checked against).
    pub fn inline(
        cfg: OutputConfig,
        recipe: Option<Recipe>,
        publishers: Vec<Box<dyn Publisher + Send>>,
    ) -> LineOutput {
        Self::with_writer(cfg, recipe, publishers, false)
    }

    fn with_writer(
        cfg: OutputConfig,
        recipe: Option<Recipe>,
        publishers: Vec<Box<dyn Publisher + Send>>,
        background: bool,
    ) -> LineOutput {
        let n = cfg.lanes.len();
        let (cap_rows, trend_rows) = recipe
            .as_ref()
            .map_or((512, 256), |r| (r.capability_rows, r.trend_rows));
        LineOutput {
            alarms: recipe.clone().map(|r| Alarms::new(r, n)),
            recipe,
            tracker: LaneTracker::new(n, cap_rows, trend_rows),
            seg: Vec::with_capacity(cfg.segment_rows.max(1)),
            seg_index: 0,
            events: Vec::new(),
            active: vec![false; n],
            writer: Writer::new(cfg.out_dir.clone(), publishers, background),
            alarm_log: Vec::new(),
            segments: 0,
            files: Vec::new(),
            cfg,
        }
    }

    /// Segment jobs and messages that found the output worker's queue
    /// full and waited (the disk or a publisher fell behind).
    pub fn output_waits(&self) -> u64 {
        self.writer.waits()
    }

    fn topic(&self, kind: &str) -> String {
        format!("{}/{kind}", self.cfg.topic)
    }

    fn end_segment(&mut self) -> Result<(), String> {
        if self.seg.is_empty() {
            return Ok(());
        }
        let lanes: Vec<serde_json::Value> = self
            .cfg
            .lanes
            .0
            .iter()
            .enumerate()
            .map(|(i, &(a, b))| {
                let s = lane_stats(
                    self.seg.iter().flat_map(|r| {
                        r.estimates[a..b]
                            .iter()
                            .filter(|e| e.is_valid())
                            .map(|e| e.thickness_nm)
                    }),
                    (b - a) * self.seg.len(),
                );
                let tr = self.tracker.trend(i);
                let spec = self.recipe.as_ref().map(|r| r.lane(i));
                let cap = spec.and_then(|s| self.tracker.capability(i, s.lower_nm, s.upper_nm));
                json!({
                    "lane": i,
                    "mean_nm": s.mean_nm, "sigma_nm": s.sigma_nm,
                    "min_nm": s.min_nm, "max_nm": s.max_nm,
                    "valid_fraction": s.valid_fraction,
                    "nonuniformity_pct": s.nonuniformity_pct,
                    "md_mean_nm": tr.map(|t| t.mean_nm),
                    "md_slope_nm_per_krow": tr.map(|t| t.slope_nm_per_krow),
                    "cp": cap.map(|c| c.cp), "cpk": cap.map(|c| c.cpk),
                    "target_nm": spec.map(|s| s.target_nm),
                    "lower_nm": spec.map(|s| s.lower_nm),
                    "upper_nm": spec.map(|s| s.upper_nm),
                    "alarm": self.active.get(i).copied().unwrap_or(false),
                })
            })
            .collect();
        let (first, last) = (&self.seg[0], &self.seg[self.seg.len() - 1]);
        let msg = json!({
            "type": "segment",
            "segment": self.seg_index,
            "first_row": first.index,
            "rows": self.seg.len(),
            "t_first_ns": first.time_ns,
            "t_last_ns": last.time_ns,
            "rows_missing_bands": self.seg.iter().filter(|r| !r.complete).count(),
            // Filled in by the worker once the file is written.
            "file": null,
            "lanes": lanes,
        });
        let rows = std::mem::replace(
            &mut self.seg,
            Vec::with_capacity(self.cfg.segment_rows.max(1)),
        );
        let topic = self.topic("segment");
        self.writer.submit(Job::Segment {
            index: self.seg_index,
            rows,
            topic,
            msg,
        })?;
        self.seg_index += 1;
        self.segments += 1;
        Ok(())
    }
}

impl WebRowSink for LineOutput {
    fn set_map_meta(&mut self, meta: crate::estimate::maps::MapMeta) {
        self.writer.set_map_meta(meta);
    }

    fn on_row(&mut self, row: &WebRowOut) -> Result<(), String> {
        let stats = row_stats(row, &self.cfg.lanes);
        if row.complete {
            self.tracker.push(row, &self.cfg.lanes, &stats);
        }
        if let Some(a) = &mut self.alarms {
            a.push(row.index, row.complete, &stats, &mut self.events);
        }
        for e in std::mem::take(&mut self.events) {
            if let Some(s) = self.active.get_mut(e.lane) {
                *s = e.event == "raised";
            }
            let mut v = serde_json::to_value(&e).map_err(|e| e.to_string())?;
            v["type"] = json!("alarm");
            let topic = self.topic("alarm");
            self.writer.submit(Job::Publish {
                topic,
                payload: v.to_string(),
            })?;
            self.alarm_log.push(e);
        }
        self.seg.push(row.clone());
        if self.seg.len() >= self.cfg.segment_rows.max(1) {
            self.end_segment()?;
        }
        Ok(())
    }

    fn finish(&mut self) -> Result<(), String> {
        self.end_segment()?;
        self.files = self.writer.finish()?;
        Ok(())
    }
}
