//! Per-web-row state: a ring sized by the field of view, each row gathering
//! its bands in whatever order the sweep delivers them.
//!
//! Promises:
//! - a row is finished as soon as it holds every band (then solved at once)
//!   or when it leaves the view without them (then flagged "missing
//!   bands", never passed off as complete);
//! - rows are finished strictly in web order: a complete row waits behind
//!   an earlier row still in view;
//! - memory is fixed at start: `rows_in_view` slots of `width × bands`
//!   samples, plus the buffers of finished rows handed back with
//!   [`Accumulator::recycle`];
//! - an encoder jump is bounded work: rows skipped beyond
//!   [`Accumulator::max_gap_rows`] are counted, not emitted one by one.
//!
//! The first web row emitted is the one at the last sensor row in the first
//! frame (rows already in view then were partly seen before the run).

/// A finished web row's spectra, handed to the solver; give the buffers
/// back with [`Accumulator::recycle`].
#[derive(Clone, Debug, PartialEq)]
pub struct FinishedRow {
    /// Web row index (0 = sensor row 0 of the first frame).
    pub index: i64,
    /// Reflectance, band-major: band `b` of pixel `x` at `b · width + x`;
    /// bands not seen are NaN.
    pub spectra: Vec<f32>,
    /// The sensor row each band was seen at (`u32::MAX`: not seen).
    pub sensor_rows: Vec<u32>,
    /// Bands seen.
    pub bands_seen: usize,
    /// Timestamp of the frame that brought the last band seen, ns (0: none).
    pub last_ns: u64,
}

impl FinishedRow {
    /// Whether every band was seen.
    pub fn complete(&self) -> bool {
        self.bands_seen == self.sensor_rows.len()
    }
}

#[derive(Clone, Debug)]
struct Slot {
    row: Option<i64>,
    spectra: Vec<f32>,
    sensor_rows: Vec<u32>,
    seen: usize,
    last_ns: u64,
}

/// Counters of what happened to web rows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct RowCounts {
    /// Rows finished with every band.
    pub complete: u64,
    /// Rows finished without some band (emitted flagged).
    pub missing_bands: u64,
    /// Rows skipped by an encoder jump beyond the gap bound (not emitted).
    pub skipped: u64,
    /// Row observations that arrived after their row was finished (the web
    /// moved backwards, or the row had every band already).
    pub late: u64,
}

/// The ring of web rows in view.
pub struct Accumulator {
    width: usize,
    n_bands: usize,
    rows_in_view: usize,
    slots: Vec<Slot>,
    /// Next web row to finish (None before the first frame).
    next: Option<i64>,
    free: Vec<(Vec<f32>, Vec<u32>)>,
    max_gap_rows: usize,
    counts: RowCounts,
}

impl Accumulator {
    /// A ring for a `width`-pixel web seen over `rows_in_view` sensor rows,
    /// `n_bands` bands.
    pub fn new(width: usize, rows_in_view: usize, n_bands: usize) -> Accumulator {
        let slot = || Slot {
            row: None,
            spectra: vec![f32::NAN; width * n_bands],
            sensor_rows: vec![u32::MAX; n_bands],
            seen: 0,
            last_ns: 0,
        };
        Accumulator {
            width,
            n_bands,
            rows_in_view,
            slots: (0..rows_in_view).map(|_| slot()).collect(),
            next: None,
            free: Vec::new(),
            max_gap_rows: 64 * rows_in_view.max(1),
            counts: RowCounts::default(),
        }
    }

    /// Rows of a forward jump emitted (flagged) one by one; beyond this
    /// they are counted as skipped.
    pub fn max_gap_rows(&self) -> usize {
        self.max_gap_rows
    }

    /// Set [`Accumulator::max_gap_rows`].
    pub fn set_max_gap_rows(&mut self, n: usize) {
        self.max_gap_rows = n;
    }

    /// What happened so far.
    pub fn counts(&self) -> RowCounts {
        self.counts
    }

    /// The next web row to be finished.
    pub fn next_row(&self) -> Option<i64> {
        self.next
    }

    /// Give a finished row's buffers back.
    pub fn recycle(&mut self, row: FinishedRow) {
        if self.free.len() < 2 * self.rows_in_view {
            self.free.push((row.spectra, row.sensor_rows));
        }
    }

    fn slot_of(&self, w: i64) -> usize {
        w.rem_euclid(self.rows_in_view as i64) as usize
    }

    /// Take slot `i`'s contents out as a finished row, leaving it empty.
    fn take(&mut self, i: usize, w: i64) -> FinishedRow {
        let (mut s, mut r) = self.free.pop().unwrap_or_else(|| {
            (
                vec![f32::NAN; self.width * self.n_bands],
                vec![u32::MAX; self.n_bands],
            )
        });
        s.fill(f32::NAN);
        r.fill(u32::MAX);
        let slot = &mut self.slots[i];
        std::mem::swap(&mut slot.spectra, &mut s);
        std::mem::swap(&mut slot.sensor_rows, &mut r);
        let row = FinishedRow {
            index: w,
            spectra: s,
            sensor_rows: r,
            bands_seen: slot.seen,
            last_ns: slot.last_ns,
        };
        slot.row = None;
        slot.seen = 0;
        slot.last_ns = 0;
        row
    }

    /// An empty (never seen) row.
    fn unseen(&mut self, w: i64) -> FinishedRow {
        let (mut s, mut r) = self.free.pop().unwrap_or_default();
        s.clear();
        s.resize(self.width * self.n_bands, f32::NAN);
        r.clear();
        r.resize(self.n_bands, u32::MAX);
        FinishedRow {
            index: w,
            spectra: s,
            sensor_rows: r,
            bands_seen: 0,
            last_ns: 0,
        }
    }

    fn finish(&mut self, w: i64, out: &mut dyn FnMut(FinishedRow)) {
        let i = self.slot_of(w);
        let row = if self.slots[i].row == Some(w) {
            self.take(i, w)
        } else {
            self.unseen(w)
        };
        if row.complete() {
            self.counts.complete += 1;
        } else {
            self.counts.missing_bands += 1;
        }
        out(row);
    }

    /// Finish the rows that left the view (below `first`) and every
    /// complete row at the front, in web order.
    fn advance(&mut self, first: i64, out: &mut dyn FnMut(FinishedRow)) {
        let Some(mut next) = self.next else { return };
        // Rows the ring can hold lie below next + rows_in_view.
        let ring_end = next + self.rows_in_view as i64;
        while next < first.min(ring_end) {
            self.finish(next, out);
            next += 1;
        }
        if next < first {
            let gap = (first - next) as u64;
            if gap <= self.max_gap_rows as u64 {
                while next < first {
                    self.finish(next, out);
                    next += 1;
                }
            } else {
                self.counts.skipped += gap;
                next = first;
            }
        }
        loop {
            let i = self.slot_of(next);
            if self.slots[i].row == Some(next) && self.slots[i].seen == self.n_bands {
                self.finish(next, out);
                next += 1;
            } else {
                break;
            }
        }
        self.next = Some(next);
    }

    /// One calibrated frame: band `band`, sensor row 0 on web row `first`,
    /// `rows` = `rows_in_view × width` reflectance values, row-major.
    /// Finished rows go to `out`, in web order.
    pub fn ingest(
        &mut self,
        first: i64,
        band: usize,
        timestamp_ns: u64,
        rows: &[f32],
        out: &mut dyn FnMut(FinishedRow),
    ) {
        if band >= self.n_bands {
            return;
        }
        let h = self.rows_in_view as i64;
        if self.next.is_none() {
            self.next = Some(first + h - 1);
        }
        self.advance(first, out);
        let next = self.next.unwrap_or(first);
        let w = self.width;
        for (y, src) in rows
            .chunks_exact(w.max(1))
            .take(self.rows_in_view)
            .enumerate()
        {
            let wr = first + y as i64;
            if wr < next {
                self.counts.late += 1;
                continue;
            }
            let i = self.slot_of(wr);
            let slot = &mut self.slots[i];
            if slot.row != Some(wr) {
                // Empty, by the ring's invariant (rows in it span fewer
                // than rows_in_view consecutive indices).
                slot.row = Some(wr);
                slot.seen = 0;
                slot.spectra.fill(f32::NAN);
                slot.sensor_rows.fill(u32::MAX);
            }
            if slot.seen == self.n_bands {
                self.counts.late += 1;
                continue;
            }
            if slot.sensor_rows[band] == u32::MAX {
                slot.seen += 1;
            }
            // A band seen twice keeps its latest look.
            slot.sensor_rows[band] = y as u32;
            slot.spectra[band * w..(band + 1) * w].copy_from_slice(src);
            slot.last_ns = timestamp_ns;
        }
        self.advance(first, out);
    }

    /// End of the run: rows still in view are not finished (they are
    /// counted by the caller as run-out).
    pub fn rows_in_ring(&self) -> usize {
        self.slots.iter().filter(|s| s.row.is_some()).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Frame values: web row · 100 + band, so every sample says where it came from.
    fn frame(first: i64, band: usize, h: usize, w: usize) -> Vec<f32> {
        (0..h * w)
            .map(|i| ((first + (i / w) as i64) * 100 + band as i64) as f32)
            .collect()
    }

    fn run(h: usize, n: usize, positions: &[(i64, usize)]) -> (Vec<FinishedRow>, RowCounts) {
        let w = 3;
        let mut acc = Accumulator::new(w, h, n);
        let mut got = Vec::new();
        for (k, &(first, band)) in positions.iter().enumerate() {
            acc.ingest(first, band, k as u64, &frame(first, band, h, w), &mut |r| {
                got.push(r)
            });
        }
        (got, acc.counts())
    }

    #[test]
    fn rows_complete_in_order_with_their_own_samples() {
        // 6 rows in view, 3 bands, 1 row per frame: every row sees 6 frames.
        let pos: Vec<(i64, usize)> = (0..40).map(|k| (k as i64, (k * 2) % 3)).collect();
        let (rows, c) = run(6, 3, &pos);
        assert!(!rows.is_empty());
        for pair in rows.windows(2) {
            assert_eq!(pair[1].index, pair[0].index + 1);
        }
        assert_eq!(rows[0].index, 5);
        for r in &rows {
            assert!(r.complete(), "row {} incomplete", r.index);
            for b in 0..3 {
                for x in 0..3 {
                    assert_eq!(r.spectra[b * 3 + x], (r.index * 100 + b as i64) as f32);
                }
            }
        }
        assert_eq!(c.missing_bands, 0);
        assert_eq!(c.complete as usize, rows.len());
    }

    #[test]
    fn a_dropped_frame_flags_the_rows_that_needed_it() {
        // 3 rows in view, 3 bands, 1 row per frame: each row sees exactly
        // one sweep; dropping frame 20 costs three rows one band each.
        let pos: Vec<(i64, usize)> = (0..40)
            .filter(|&k| k != 20)
            .map(|k| (k as i64, k % 3))
            .collect();
        let (rows, c) = run(3, 3, &pos);
        let bad: Vec<i64> = rows
            .iter()
            .filter(|r| !r.complete())
            .map(|r| r.index)
            .collect();
        assert_eq!(bad, vec![20, 21, 22]);
        assert_eq!(c.missing_bands, 3);
        for r in rows.iter().filter(|r| !r.complete()) {
            assert_eq!(r.bands_seen, 2);
            assert_eq!(r.sensor_rows.iter().filter(|&&s| s == u32::MAX).count(), 1);
        }
        // Web order kept across the flagged rows.
        for pair in rows.windows(2) {
            assert_eq!(pair[1].index, pair[0].index + 1);
        }
    }

    #[test]
    fn encoder_jump_flags_or_skips_with_bounded_work() {
        let mut pos: Vec<(i64, usize)> = (0..20).map(|k| (k as i64, k % 3)).collect();
        pos.extend((0..20).map(|k| (100 + k as i64, (20 + k) % 3)));
        let (rows, c) = run(4, 3, &pos);
        // Every row up to the last finished one, once, in order.
        for pair in rows.windows(2) {
            assert_eq!(pair[1].index, pair[0].index + 1);
        }
        let done: Vec<i64> = rows
            .iter()
            .filter(|r| (21..102).contains(&r.index) && r.complete())
            .map(|r| r.index)
            .collect();
        assert!(done.is_empty(), "{done:?}");
        assert!(c.missing_bands >= 80);
        // A huge jump is counted, not emitted row by row.
        let mut acc = Accumulator::new(2, 4, 3);
        acc.set_max_gap_rows(10);
        let mut n = 0;
        for k in 0..10 {
            acc.ingest(k, (k % 3) as usize, 0, &[0.5; 8], &mut |_| n += 1);
        }
        acc.ingest(1_000_000_000_000, 0, 0, &[0.5; 8], &mut |_| n += 1);
        assert!(n < 20, "{n} rows emitted for a jump");
        assert!(acc.counts().skipped > 999_999_999_000);
    }

    #[test]
    fn backwards_motion_is_late_not_reopened() {
        let mut pos: Vec<(i64, usize)> = (0..20).map(|k| (k as i64, k % 2)).collect();
        pos.push((10, 0));
        pos.extend((20..30).map(|k| (k as i64, k % 2)));
        let (rows, c) = run(4, 2, &pos);
        for pair in rows.windows(2) {
            assert_eq!(pair[1].index, pair[0].index + 1);
        }
        assert!(c.late > 0);
        assert!(rows.iter().all(|r| r.complete()));
    }
}
