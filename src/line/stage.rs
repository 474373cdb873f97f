//! The row stage: finished web rows → solved rows → the row sink, with the
//! latency of every row measured from the read of the frame that finished
//! it to the moment the sink returned from it.
//!
//! The same stage runs inline (in the capture loop) or on its own thread
//! behind a bounded channel ([`super::run::Threading`]); it sees the same
//! rows in the same order either way, so the emitted rows are identical.
//! On its thread it takes every batch waiting at once and solves their
//! rows together in parallel (each row by one thread, results in web
//! order), which is how it catches up after a slow moment.

use super::accumulate::FinishedRow;
use super::run::WebRowSink;
use super::solve::RowSolver;
use std::time::Instant;

/// The rows one frame finished, with the moment that frame was read.
pub(super) struct Batch {
    /// Finished rows, in web order.
    pub rows: Vec<FinishedRow>,
    /// When the frame that finished them was read from the camera.
    pub t_read: Instant,
}

/// Row latencies in 1 ms bins (the last bin: 2 s and more): percentiles
/// of a run of any length in fixed memory.
#[derive(Clone, Debug)]
pub(super) struct Histogram(Vec<u64>);

impl Default for Histogram {
    fn default() -> Self {
        Histogram(vec![0; 2001])
    }
}

impl Histogram {
    fn add(&mut self, ms: f64) {
        let i = (ms.max(0.0) as usize).min(self.0.len() - 1);
        self.0[i] += 1;
    }

    /// The upper edge of the bin holding the `q` quantile, ms (0: empty).
    pub fn quantile(&self, q: f64) -> f64 {
        let n: u64 = self.0.iter().sum();
        if n == 0 {
            return 0.0;
        }
        let want = ((q * n as f64).ceil() as u64).clamp(1, n);
        let mut seen = 0;
        for (i, c) in self.0.iter().enumerate() {
            seen += c;
            if seen >= want {
                return (i + 1) as f64;
            }
        }
        self.0.len() as f64
    }
}

/// What the row stage did.
#[derive(Clone, Debug, Default)]
pub(super) struct StageReport {
    /// Rows handed to the sink.
    pub rows_emitted: u64,
    /// Of those, rows whose bands were modelled at their own angles.
    pub rows_angle_corrected: u64,
    /// Sum, count and largest of the row latencies, ms.
    pub latency_sum_ms: f64,
    /// Rows whose latency was measured (complete rows after the warm-up).
    pub latency_n: u64,
    /// Largest latency, ms.
    pub latency_max_ms: f64,
    /// Their distribution.
    pub latency_hist: Histogram,
    /// Complete rows whose last frame was read while the warm-up was being
    /// solved (they waited for it; not in the latency above).
    pub warmup_wait_rows: u64,
    /// Largest latency among them, ms.
    pub warmup_wait_max_ms: f64,
    /// Looks after the warm-up that estimated the calibration again.
    pub relooks: u64,
    /// Looks that found the calibration unsettled (see
    /// [`super::run::LineReport::unsettled_looks`]).
    pub unsettled_looks: u64,
}

/// Solves rows and hands them to the sink.
pub(super) struct RowStage<'s> {
    solver: RowSolver,
    sink: &'s mut (dyn WebRowSink + Send),
    report: StageReport,
    rows: Vec<FinishedRow>,
    reads: Vec<Instant>,
    /// When the rows waiting for the warm-up had been solved.
    ready_at: Option<Instant>,
    /// The sink has the estimator's map metadata.
    meta_sent: bool,
}

impl<'s> RowStage<'s> {
    pub fn new(solver: RowSolver, sink: &'s mut (dyn WebRowSink + Send)) -> RowStage<'s> {
        RowStage {
            solver,
            sink,
            report: StageReport::default(),
            rows: Vec::new(),
            reads: Vec::new(),
            ready_at: None,
            meta_sent: false,
        }
    }

    /// Solve and emit the rows of `batches` (in order); finished rows'
    /// buffers go to `recycle`.
    pub fn push(
        &mut self,
        batches: &mut Vec<Batch>,
        recycle: &mut dyn FnMut(FinishedRow),
    ) -> Result<(), String> {
        for b in batches.drain(..) {
            self.reads
                .extend(std::iter::repeat_n(b.t_read, b.rows.len()));
            self.rows.extend(b.rows);
        }
        if self.rows.is_empty() {
            return Ok(());
        }
        // Before the noise level is known, rows wait (warm-up) and come out
        // later, not one for one: their latency is not measured.
        let was_ready = self.solver.ready();
        let mut solved = Vec::with_capacity(self.rows.len());
        self.solver.push_all(&mut self.rows, &mut |out, buf| {
            solved.push(out);
            recycle(buf);
        });
        if !was_ready && self.solver.ready() {
            self.ready_at = Some(Instant::now());
        }
        self.send_meta(!solved.is_empty());
        let mut reads = std::mem::take(&mut self.reads).into_iter();
        for row in solved {
            let t_read = reads.next();
            self.sink.on_row(&row)?;
            self.report.rows_emitted += 1;
            self.report.rows_angle_corrected += u64::from(row.angle_corrected);
            let Some(t) = t_read.filter(|_| was_ready && row.complete) else {
                continue;
            };
            let l = t.elapsed().as_secs_f64() * 1e3;
            if self.ready_at.is_some_and(|r| t < r) {
                // Read while the warm-up was being solved: it waited for
                // the warm-up, a start-up delay reported apart.
                self.report.warmup_wait_rows += 1;
                self.report.warmup_wait_max_ms = self.report.warmup_wait_max_ms.max(l);
                continue;
            }
            self.report.latency_sum_ms += l;
            self.report.latency_n += 1;
            self.report.latency_max_ms = self.report.latency_max_ms.max(l);
            self.report.latency_hist.add(l);
        }
        Ok(())
    }

    /// The estimator's map metadata to the sink, once, before the first
    /// row it emits.
    fn send_meta(&mut self, rows: bool) {
        if rows && !self.meta_sent {
            self.sink.set_map_meta(self.solver.solver().map_meta());
            self.meta_sent = true;
        }
    }

    /// The run ended: solve the rows still waiting for the warm-up, emit
    /// them, finish the sink.
    pub fn finish(mut self) -> Result<StageReport, String> {
        let mut solved = Vec::new();
        self.solver.flush(&mut |out, _| solved.push(out));
        self.send_meta(!solved.is_empty());
        for row in solved {
            self.sink.on_row(&row)?;
            self.report.rows_emitted += 1;
            self.report.rows_angle_corrected += u64::from(row.angle_corrected);
        }
        self.sink.finish()?;
        self.report.relooks = self.solver.relooks();
        self.report.unsettled_looks = self.solver.unsettled_looks();
        Ok(self.report)
    }
}

#[cfg(test)]
mod tests {
    use super::Histogram;

    #[test]
    fn quantiles_are_the_upper_edge_of_their_bin() {
        let mut h = Histogram::default();
        assert_eq!(h.quantile(0.99), 0.0);
        for i in 0..100 {
            h.add(f64::from(i) + 0.5);
        }
        assert_eq!(h.quantile(0.5), 50.0);
        assert_eq!(h.quantile(0.99), 99.0);
        assert_eq!(h.quantile(1.0), 100.0);
        h.add(1e9);
        assert_eq!(h.quantile(1.0), 2001.0);
    }
}
