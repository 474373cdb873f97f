//! Pairing frames with bands.
//!
//! The pipeline needs one thing of a filter: "pass this wavelength, and say
//! from when on it is settled" ([`BandTuner`]). Time is the frames' clock,
//! passed in, so the [`Sequencer`] is a pure state machine: replayed
//! metadata gives the same pairing.
//!
//! Two modes:
//! - **stepped** (software): tune a band, then take the first frame whose
//!   exposure *starts* at or after the settled time. Frames exposed while the
//!   filter settles, duplicates and stale (out-of-order) frames are
//!   discarded; a dropped or corrupt frame is simply re-taken by the next one.
//! - **triggered**: the controller cycles its palette and its settled output
//!   triggers the camera, so trigger counts (or frame sequence numbers) give
//!   the pairing: slot `k` is band `order[k mod n]` of sweep `k / n`. A gap
//!   marks the skipped slots' bands missing; a late frame still fills its
//!   slot if it is within one sweep; a duplicate is discarded.
//!
//! Whatever the faults, a frame is never paired with a band other than the
//! one the filter passed while it was exposed.

use crate::device::camera::synthetic::FilterView;
use crate::device::camera::FrameMeta;
use rand::{Rng, SeedableRng};
use std::time::Duration;

/// Filter errors as the pipeline sees them.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TuneError {
    /// The controller did not confirm in time.
    #[error("filter controller did not answer tuning to {nm} nm within {timeout:?}")]
    Timeout {
        /// Requested wavelength.
        nm: f64,
        /// How long we waited.
        timeout: Duration,
    },
    /// The controller answered with an error.
    #[error("filter controller refused {nm} nm: {message}")]
    Refused {
        /// Requested wavelength.
        nm: f64,
        /// What it said.
        message: String,
    },
}

/// What the pipeline needs of a tunable filter.
pub trait BandTuner: Send {
    /// Command `nm` at `now_ns` (the frames' clock); returns the time from
    /// which the filter passes `nm` settled.
    fn tune(&mut self, nm: f64, now_ns: u64) -> Result<u64, TuneError>;

    /// A one-line description for logs and calibration metadata.
    fn describe(&self) -> String;
}

impl<T: BandTuner + ?Sized> BandTuner for Box<T> {
    fn tune(&mut self, nm: f64, now_ns: u64) -> Result<u64, TuneError> {
        (**self).tune(nm, now_ns)
    }
    fn describe(&self) -> String {
        (**self).describe()
    }
}

/// An in-process emulated liquid-crystal filter: settles in a fixed time
/// plus seeded jitter, drives a [`FilterView`] the synthetic camera looks
/// through, and can be told to stop answering.
pub struct EmulatedTuner {
    view: FilterView,
    settle_ns: u64,
    jitter_ns: u64,
    rng: rand_chacha::ChaCha8Rng,
    answer_limit: Option<u64>,
    answered: u64,
    timeout: Duration,
}

impl EmulatedTuner {
    /// A filter settling in `settle` ± `jitter` (uniform), seeded.
    pub fn new(view: FilterView, settle: Duration, jitter: Duration, seed: u64) -> Self {
        EmulatedTuner {
            view,
            settle_ns: settle.as_nanos() as u64,
            jitter_ns: jitter.as_nanos() as u64,
            rng: rand_chacha::ChaCha8Rng::seed_from_u64(seed),
            answer_limit: None,
            answered: 0,
            timeout: Duration::from_millis(500),
        }
    }
}

impl EmulatedTuner {
    /// Answer `n` more commands, then never again (a controller that hung
    /// or was unplugged): every later command times out.
    pub fn stop_answering_after(&mut self, n: u64) {
        self.answer_limit = Some(self.answered + n);
    }
}

impl BandTuner for EmulatedTuner {
    fn tune(&mut self, nm: f64, now_ns: u64) -> Result<u64, TuneError> {
        if self.answer_limit.is_some_and(|l| self.answered >= l) {
            return Err(TuneError::Timeout {
                nm,
                timeout: self.timeout,
            });
        }
        self.answered += 1;
        let jitter = if self.jitter_ns > 0 {
            self.rng.random_range(0..=self.jitter_ns)
        } else {
            0
        };
        let settle = self.settle_ns + jitter;
        self.view.tune(nm, now_ns, settle);
        Ok(now_ns + settle)
    }

    fn describe(&self) -> String {
        format!(
            "emulated LCTF (settle {:.1} ms + up to {:.1} ms jitter)",
            self.settle_ns as f64 / 1e6,
            self.jitter_ns as f64 / 1e6
        )
    }
}

/// Adapts any blocking "tune and wait until settled" call (the VariSpec
/// driver's `FilterController::tune`) to [`BandTuner`]: when the call
/// returns the filter is settled, so the settled time is the host's
/// monotonic clock then — the clock V4L2 timestamps frames on.
pub struct BlockingTuner<F> {
    tune: F,
    label: String,
    clock: fn() -> u64,
}

impl<F: FnMut(f64) -> Result<Duration, TuneError> + Send> BlockingTuner<F> {
    /// Wrap `tune`; `clock` reads the frames' clock in ns.
    pub fn new(label: impl Into<String>, clock: fn() -> u64, tune: F) -> Self {
        BlockingTuner {
            tune,
            label: label.into(),
            clock,
        }
    }
}

impl<F: FnMut(f64) -> Result<Duration, TuneError> + Send> BandTuner for BlockingTuner<F> {
    fn tune(&mut self, nm: f64, _now_ns: u64) -> Result<u64, TuneError> {
        (self.tune)(nm)?;
        Ok((self.clock)())
    }
    fn describe(&self) -> String {
        self.label.clone()
    }
}

/// Drives a real (or emulated, over a pseudo-terminal) VariSpec-protocol
/// controller through [`crate::device::filter::FilterController`], byte for
/// byte, and mirrors what it does into a [`FilterView`] when a synthetic
/// camera looks through it.
///
/// The settled time is `now_ns` plus the settle time the controller
/// reported, converted to device time by `time_scale` (the emulator runs
/// its clock that many times faster than the wall): the synthetic camera's
/// clock is device time.
pub struct ControllerTuner<C> {
    ctrl: C,
    view: Option<FilterView>,
    time_scale: f64,
    timeout: Duration,
    label: String,
}

impl<C: crate::device::filter::FilterController + Send> ControllerTuner<C> {
    /// Wrap `ctrl`; `view` is the synthetic camera's, if any.
    pub fn new(mut ctrl: C, view: Option<FilterView>, time_scale: f64, timeout: Duration) -> Self {
        let label = match ctrl.version() {
            Ok(v) => format!(
                "VariSpec-protocol controller rev {} ({}-{} nm, serial {})",
                v.revision, v.min_nm, v.max_nm, v.serial
            ),
            Err(e) => format!("VariSpec-protocol controller (version unknown: {e})"),
        };
        ControllerTuner {
            ctrl,
            view,
            time_scale: if time_scale > 0.0 { time_scale } else { 1.0 },
            timeout,
            label,
        }
    }

    /// The controller.
    pub fn controller(&mut self) -> &mut C {
        &mut self.ctrl
    }
}

impl<C: crate::device::filter::FilterController + Send> BandTuner for ControllerTuner<C> {
    fn tune(&mut self, nm: f64, now_ns: u64) -> Result<u64, TuneError> {
        use crate::device::filter::FilterError;
        let settle = self.ctrl.tune(nm, self.timeout).map_err(|e| match e {
            FilterError::Timeout { .. } => TuneError::Timeout {
                nm,
                timeout: self.timeout,
            },
            other => TuneError::Refused {
                nm,
                message: other.to_string(),
            },
        })?;
        let settle_ns = (settle.as_secs_f64() * self.time_scale * 1e9) as u64;
        if let Some(v) = &self.view {
            v.tune(nm, now_ns, settle_ns);
        }
        Ok(now_ns + settle_ns)
    }

    fn describe(&self) -> String {
        self.label.clone()
    }
}

/// How frames are paired with bands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SeqMode {
    /// Software-stepped: tune, wait until settled, take the next frame.
    Stepped,
    /// Hardware-triggered: the settled output triggers the camera.
    Triggered,
}

/// Why a frame was not used.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Discard {
    /// Exposed before the filter had settled.
    Settling,
    /// Same or older sequence number than one already used.
    Stale,
    /// Its sweep was abandoned (processing fell behind).
    Abandoned,
    /// The frame was malformed.
    Bad,
    /// Beyond the requested number of sweeps.
    Done,
    /// Read while capture held the next sweep back (the first sweep's
    /// set-up: film index, noise and level; stepped mode).
    Held,
}

/// The sequencer's verdict on one frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Use the frame as band `band` (index into the bands) of sweep `sweep`.
    Accept {
        /// Sweep index.
        sweep: u64,
        /// Band index.
        band: usize,
    },
    /// Do not use it.
    Discard(Discard),
}

/// A band slot given up (triggered mode gap): fill with NaN.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Missing {
    /// Sweep index.
    pub sweep: u64,
    /// Band index.
    pub band: usize,
}

/// Sequencer errors.
#[derive(Debug, thiserror::Error)]
pub enum SequencerError {
    /// The filter failed.
    #[error(transparent)]
    Tune(#[from] TuneError),
    /// Bad configuration.
    #[error("sequencer: {0}")]
    Config(String),
}

/// Pairs frames with bands (see the module header).
pub struct Sequencer {
    mode: SeqMode,
    /// Band centres, nm, by band index.
    bands_nm: Vec<f64>,
    /// Capture order: band indices.
    order: Vec<usize>,
    sweeps: Option<u64>,
    // stepped
    pos: usize,
    sweep: u64,
    settled_at: u64,
    last_seq: Option<u64>,
    // triggered
    slot0: Option<u64>,
    next_slot: u64,
    missing_recent: Vec<u64>,
    abandoned_through: Option<u64>,
    started: bool,
}

impl Sequencer {
    /// A sequencer over `bands_nm` captured in `order` (band indices; every
    /// band exactly once), for `sweeps` sweeps (None: forever).
    pub fn new(
        mode: SeqMode,
        bands_nm: Vec<f64>,
        order: Vec<usize>,
        sweeps: Option<u64>,
    ) -> Result<Sequencer, SequencerError> {
        let n = bands_nm.len();
        let mut seen = vec![false; n];
        if n == 0 || order.len() != n {
            return Err(SequencerError::Config(format!(
                "the band order must list each of the {n} bands once"
            )));
        }
        for &b in &order {
            if b >= n || std::mem::replace(&mut seen[b], true) {
                return Err(SequencerError::Config(format!(
                    "band order entry {b} is out of range or repeated"
                )));
            }
        }
        Ok(Sequencer {
            mode,
            bands_nm,
            order,
            sweeps,
            pos: 0,
            sweep: 0,
            settled_at: u64::MAX,
            last_seq: None,
            slot0: None,
            next_slot: 0,
            missing_recent: Vec::with_capacity(n),
            abandoned_through: None,
            started: false,
        })
    }

    /// Number of bands per sweep.
    pub fn n_bands(&self) -> usize {
        self.order.len()
    }

    /// The mode.
    pub fn mode(&self) -> SeqMode {
        self.mode
    }

    /// Tune the first band (stepped mode). `now_ns` on the frames' clock.
    pub fn start(&mut self, tuner: &mut dyn BandTuner, now_ns: u64) -> Result<(), SequencerError> {
        self.started = true;
        if self.mode == SeqMode::Stepped {
            self.settled_at = tuner.tune(self.bands_nm[self.order[0]], now_ns)?;
        }
        Ok(())
    }

    /// Whether every requested sweep has been paired.
    pub fn finished(&self) -> bool {
        match (self.mode, self.sweeps) {
            (_, None) => false,
            (SeqMode::Stepped, Some(n)) => self.sweep >= n,
            (SeqMode::Triggered, Some(n)) => self.next_slot >= n * self.order.len() as u64,
        }
    }

    /// Whether the next accepted frame would start a sweep after the first
    /// (stepped mode): where capture may hold the sequence back.
    pub fn at_sweep_start(&self) -> bool {
        self.mode == SeqMode::Stepped
            && self.started
            && self.pos == 0
            && self.sweep > 0
            && !self.finished()
    }

    /// Skip the sweep in progress (triggered mode, while the pipeline's
    /// set-up is done): like [`Sequencer::abandon_sweep`], but the sweep
    /// does not count toward the requested number.
    pub fn skip_sweep(
        &mut self,
        tuner: &mut dyn BandTuner,
        now_ns: u64,
    ) -> Result<u64, SequencerError> {
        let s = self.abandon_sweep(tuner, now_ns)?;
        if let Some(n) = self.sweeps.as_mut() {
            *n += 1;
        }
        Ok(s)
    }

    /// Give up the sweep in progress (processing fell behind): its frames
    /// are discarded from now on, and stepped mode restarts at the next
    /// sweep's first band. Returns the abandoned sweep.
    pub fn abandon_sweep(
        &mut self,
        tuner: &mut dyn BandTuner,
        now_ns: u64,
    ) -> Result<u64, SequencerError> {
        match self.mode {
            SeqMode::Stepped => {
                let s = self.sweep;
                self.abandoned_through = Some(s);
                self.sweep += 1;
                self.pos = 0;
                if !self.finished() {
                    self.settled_at = tuner.tune(self.bands_nm[self.order[0]], now_ns)?;
                }
                Ok(s)
            }
            SeqMode::Triggered => {
                let s = self.next_slot / self.order.len() as u64;
                self.abandoned_through = Some(s);
                Ok(s)
            }
        }
    }

    /// Judge one frame. `valid` is false for a frame that failed its size
    /// check. Missing band slots found on the way go to `missing`.
    pub fn on_frame(
        &mut self,
        meta: &FrameMeta,
        valid: bool,
        tuner: &mut dyn BandTuner,
        missing: &mut dyn FnMut(Missing),
    ) -> Result<Verdict, SequencerError> {
        if !valid {
            return Ok(Verdict::Discard(Discard::Bad));
        }
        if self.finished() {
            return Ok(Verdict::Discard(Discard::Done));
        }
        match self.mode {
            SeqMode::Stepped => self.stepped(meta, tuner),
            SeqMode::Triggered => Ok(self.triggered(meta, missing)),
        }
    }

    /// Whether [`Sequencer::on_frame`] would discard a frame with this
    /// metadata as exposed while the filter settled, whatever its pixels: a
    /// pure look ahead, so a source can skip reading (or rendering) pixels
    /// no one will use. Only stepped mode discards for settling; the first
    /// frame (which starts the sequence) and stale frames are not counted.
    pub fn discards_as_settling(&self, meta: &FrameMeta) -> bool {
        self.mode == SeqMode::Stepped
            && self.started
            && !self.finished()
            && self.last_seq.is_none_or(|l| meta.seq > l)
            && meta.timestamp_ns < self.settled_at
    }

    fn stepped(
        &mut self,
        meta: &FrameMeta,
        tuner: &mut dyn BandTuner,
    ) -> Result<Verdict, SequencerError> {
        if !self.started {
            self.start(tuner, meta.timestamp_ns)?;
            return Ok(Verdict::Discard(Discard::Settling));
        }
        if self.last_seq.is_some_and(|l| meta.seq <= l) {
            return Ok(Verdict::Discard(Discard::Stale));
        }
        if meta.timestamp_ns < self.settled_at {
            return Ok(Verdict::Discard(Discard::Settling));
        }
        self.last_seq = Some(meta.seq);
        let v = Verdict::Accept {
            sweep: self.sweep,
            band: self.order[self.pos],
        };
        self.pos += 1;
        if self.pos == self.order.len() {
            self.pos = 0;
            self.sweep += 1;
        }
        if !self.finished() {
            // The command goes out when this exposure ends.
            let now = meta.timestamp_ns + u64::from(meta.exposure_us) * 1000;
            self.settled_at = tuner.tune(self.bands_nm[self.order[self.pos]], now)?;
        }
        Ok(v)
    }

    fn triggered(&mut self, meta: &FrameMeta, missing: &mut dyn FnMut(Missing)) -> Verdict {
        let n = self.order.len() as u64;
        let count = meta.trigger.unwrap_or(meta.seq);
        // A trigger count is the palette position since the controller was
        // armed: the first sweep starts at the next palette start. Without
        // one, the first frame seen is taken as palette entry 0.
        let slot0 = *self.slot0.get_or_insert(match meta.trigger {
            Some(t) => t.div_ceil(n) * n,
            None => count,
        });
        let Some(slot) = count.checked_sub(slot0) else {
            return Verdict::Discard(if self.next_slot == 0 {
                Discard::Settling
            } else {
                Discard::Stale
            });
        };
        let pair = |slot: u64| (slot / n, self.order[(slot % n) as usize]);
        if slot < self.next_slot {
            // Late: only fills a slot given up as missing, within a sweep.
            if let Some(i) = self.missing_recent.iter().position(|&s| s == slot) {
                self.missing_recent.swap_remove(i);
                let (sweep, band) = pair(slot);
                if self.abandoned_through.is_some_and(|a| sweep <= a) {
                    return Verdict::Discard(Discard::Abandoned);
                }
                return Verdict::Accept { sweep, band };
            }
            return Verdict::Discard(Discard::Stale);
        }
        let limit = self.sweeps.map_or(u64::MAX, |s| s * n);
        for gap in self.next_slot..slot.min(limit) {
            let (sweep, band) = pair(gap);
            if self.missing_recent.len() == self.missing_recent.capacity() {
                self.missing_recent.remove(0);
            }
            self.missing_recent.push(gap);
            if self.abandoned_through.is_none_or(|a| sweep > a) {
                missing(Missing { sweep, band });
            }
        }
        self.missing_recent.retain(|&s| s + n > slot);
        self.next_slot = slot + 1;
        if slot >= limit {
            return Verdict::Discard(Discard::Done);
        }
        let (sweep, band) = pair(slot);
        if self.abandoned_through.is_some_and(|a| sweep <= a) {
            return Verdict::Discard(Discard::Abandoned);
        }
        Verdict::Accept { sweep, band }
    }
}

/// Band capture orders.
pub fn order_for(name: &str, n: usize, bands_nm: &[f64]) -> Option<Vec<usize>> {
    let mut asc: Vec<usize> = (0..n).collect();
    asc.sort_by(|&a, &b| bands_nm[a].total_cmp(&bands_nm[b]));
    match name {
        "ascending" => Some(asc),
        "descending" => Some(asc.into_iter().rev().collect()),
        // Every other band up, the rest down: a palette order that keeps
        // steps short (settling is faster for small steps on real units).
        "interleaved" => {
            let up = asc.iter().step_by(2).copied();
            let down: Vec<usize> = asc.iter().skip(1).step_by(2).copied().collect();
            Some(up.chain(down.into_iter().rev()).collect())
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::camera::PixelFormat;

    fn meta(seq: u64, t_ms: u64) -> FrameMeta {
        FrameMeta {
            seq,
            timestamp_ns: t_ms * 1_000_000,
            exposure_us: 5000,
            gain: 1.0,
            format: PixelFormat::Y16,
            width: 1,
            height: 1,
            trigger: None,
            encoder: None,
        }
    }

    #[test]
    fn stepped_discards_settling_stale_and_never_shifts() {
        let view = FilterView::new();
        let mut t = EmulatedTuner::new(view, Duration::from_millis(25), Duration::ZERO, 1);
        let mut s = Sequencer::new(
            SeqMode::Stepped,
            vec![400.0, 500.0, 600.0],
            vec![0, 1, 2],
            Some(1),
        )
        .unwrap();
        s.start(&mut t, 0).unwrap();
        let mut none = |_m: Missing| panic!("no missing in stepped mode");
        let v =
            |s: &mut Sequencer,
             t: &mut EmulatedTuner,
             m: FrameMeta,
             none: &mut dyn FnMut(Missing)| { s.on_frame(&m, true, t, none).unwrap() };
        assert_eq!(
            v(&mut s, &mut t, meta(0, 0), &mut none),
            Verdict::Discard(Discard::Settling)
        );
        assert_eq!(
            v(&mut s, &mut t, meta(3, 30), &mut none),
            Verdict::Accept { sweep: 0, band: 0 }
        );
        // Duplicate and an older frame arriving late.
        assert_eq!(
            v(&mut s, &mut t, meta(3, 30), &mut none),
            Verdict::Discard(Discard::Stale)
        );
        assert_eq!(
            v(&mut s, &mut t, meta(2, 20), &mut none),
            Verdict::Discard(Discard::Stale)
        );
        // Band 1 was commanded at 35 ms, settled at 60 ms.
        assert_eq!(
            v(&mut s, &mut t, meta(4, 40), &mut none),
            Verdict::Discard(Discard::Settling)
        );
        assert_eq!(
            v(&mut s, &mut t, meta(6, 60), &mut none),
            Verdict::Accept { sweep: 0, band: 1 }
        );
        assert_eq!(
            v(&mut s, &mut t, meta(9, 95), &mut none),
            Verdict::Accept { sweep: 0, band: 2 }
        );
        assert!(s.finished());
    }

    /// The look ahead that lets a source skip a frame's pixels agrees with
    /// the verdict the frame then gets, frame by frame, through settling
    /// with jitter, duplicates, late frames and sweep ends; and it never
    /// names a frame that would be accepted (a skipped frame's stale
    /// pixels would land on a band).
    #[test]
    fn the_settling_look_ahead_matches_the_verdict() {
        let view = FilterView::new();
        let mut t = EmulatedTuner::new(
            view,
            Duration::from_millis(40),
            Duration::from_millis(15),
            7,
        );
        let mut s = Sequencer::new(
            SeqMode::Stepped,
            vec![400.0, 450.0, 500.0, 550.0],
            vec![0, 2, 1, 3],
            Some(3),
        )
        .unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let (mut seq, mut settling, mut accepted) = (0u64, 0, 0);
        while !s.finished() {
            // Frames every 10 ms; now and then one repeated or one late.
            let m = match rng.random_range(0..10) {
                0 if seq > 1 => meta(seq - 1, (seq - 1) * 10),
                1 if seq > 2 => meta(seq - 2, (seq - 2) * 10),
                _ => {
                    seq += 1;
                    meta(seq, seq * 10)
                }
            };
            let ahead = s.discards_as_settling(&m);
            let v = s.on_frame(&m, true, &mut t, &mut |_| {}).unwrap();
            let is_settling = v == Verdict::Discard(Discard::Settling);
            // The first frame starts the sequence (settling, not foreseen).
            assert!(
                ahead == is_settling || (!ahead && seq == 1),
                "frame {}: look ahead {ahead}, verdict {v:?}",
                m.seq
            );
            settling += usize::from(ahead);
            accepted += usize::from(matches!(v, Verdict::Accept { .. }));
        }
        assert_eq!(accepted, 12);
        assert!(settling >= 12 * 3, "{settling} frames foreseen as settling");
    }

    #[test]
    fn triggered_marks_gaps_missing_and_fills_late_frames() {
        let mut t = EmulatedTuner::new(FilterView::new(), Duration::ZERO, Duration::ZERO, 1);
        let mut s = Sequencer::new(
            SeqMode::Triggered,
            vec![400.0, 500.0, 600.0],
            vec![2, 1, 0],
            Some(2),
        )
        .unwrap();
        let mut miss = Vec::new();
        let mut go = |s: &mut Sequencer, seq| {
            let mut m = Vec::new();
            let v = s
                .on_frame(&meta(seq, seq), true, &mut t, &mut |x| m.push(x))
                .unwrap();
            (v, m)
        };
        assert_eq!(go(&mut s, 10).0, Verdict::Accept { sweep: 0, band: 2 });
        // 11 is late: 12 arrives first, 11 is marked missing, then fills in.
        let (v, m) = go(&mut s, 12);
        assert_eq!(v, Verdict::Accept { sweep: 0, band: 0 });
        miss.extend(m);
        assert_eq!(miss, vec![Missing { sweep: 0, band: 1 }]);
        assert_eq!(go(&mut s, 11).0, Verdict::Accept { sweep: 0, band: 1 });
        assert_eq!(go(&mut s, 11).0, Verdict::Discard(Discard::Stale));
        // 13 dropped.
        let (v, m) = go(&mut s, 14);
        assert_eq!(v, Verdict::Accept { sweep: 1, band: 1 });
        assert_eq!(m, vec![Missing { sweep: 1, band: 2 }]);
        assert_eq!(go(&mut s, 15).0, Verdict::Accept { sweep: 1, band: 0 });
        assert!(s.finished());
    }

    #[test]
    fn a_silent_controller_is_an_error_not_a_hang() {
        let mut t = EmulatedTuner::new(FilterView::new(), Duration::ZERO, Duration::ZERO, 1);
        t.stop_answering_after(1);
        let mut s = Sequencer::new(
            SeqMode::Stepped,
            vec![400.0, 500.0, 600.0],
            vec![0, 1, 2],
            None,
        )
        .unwrap();
        s.start(&mut t, 0).unwrap();
        let e = s
            .on_frame(&meta(1, 1), true, &mut t, &mut |_| {})
            .unwrap_err();
        assert!(e.to_string().contains("did not answer"), "{e}");
    }

    #[test]
    fn orders_are_permutations() {
        let nm: Vec<f64> = (0..31).map(|i| 400.0 + 10.0 * i as f64).collect();
        for name in ["ascending", "descending", "interleaved"] {
            let mut o = order_for(name, 31, &nm).unwrap();
            o.sort();
            assert_eq!(o, (0..31).collect::<Vec<_>>());
        }
    }
}
