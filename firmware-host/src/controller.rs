//! The controller state machine: bytes in, bytes and trigger events out.
//!
//! Promises: [`Controller::feed`] accepts any byte at any time and never
//! panics; every byte except LF is echoed at once; line commands run on the
//! carriage return; immediate commands (`ESC`, `!`, `@`) are answered at
//! once, even while busy. Replies go to a bounded output queue the caller
//! drains ([`Controller::pop_output`]); "settled" edges of the trigger output
//! go to a bounded event queue ([`Controller::pop_event`]). Time is passed in
//! as device microseconds and may not run backwards (earlier stamps are
//! treated as "no time passed").

use core::fmt::Write;

use heapless::{Deque, String, Vec};

use crate::parser::{parse_line, Command, Step, LINE_CAPACITY, PALETTE_CAPACITY};
use crate::settle::{Motion, Prng, SettleParams};
use crate::timing::{EXERCISE_CYCLE_US, INITIALISE_US};
use crate::ErrorCode;

/// Bytes of replies that can wait to be sent. Sized for the longest reply,
/// the full `D?` listing (128 entries × 16 bytes) plus slack.
pub const OUT_CAPACITY: usize = 2560;
/// Line commands that can wait while an `I`/`E` runs.
pub const QUEUE_CAPACITY: usize = 8;
/// Trigger events kept until the caller collects them (oldest dropped first).
pub const EVENT_CAPACITY: usize = 32;
/// Width of the right-aligned value field in normal replies.
pub const NORMAL_FIELD: usize = 7;

/// Immediate command: abort the running `I`/`E`, flush the queue and the
/// partial line.
pub const ESC: u8 = 0x1b;
/// Immediate command: busy query, answered `<` (busy) or `>` (idle).
pub const BUSY_QUERY: u8 = b'!';
/// Immediate command: status query, answered with the status byte.
pub const STATUS_QUERY: u8 = b'@';

/// Bits of the status byte sent after `@`.
pub mod status {
    /// Filter initialised (`I` completed).
    pub const INITIALISED: u8 = 0x01;
    /// Liquid crystal exercised (`E` completed).
    pub const EXERCISED: u8 = 0x02;
    /// At least one palette entry defined.
    pub const PALETTE_DEFINED: u8 = 0x04;
    /// Brief reply mode (`B 1`).
    pub const BRIEF: u8 = 0x08;
    /// An error is pending (read it with `R?`, clear with `R 1`).
    pub const ERROR_PENDING: u8 = 0x20;
    /// Always set, so the status byte is a printable character.
    pub const ALWAYS: u8 = 0x40;
}

/// Reply format selected with `B`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReplyMode {
    /// `B 0`: letter, then each value right-aligned in a 7-character field.
    Normal = 0,
    /// `B 1`: values only, separated by single spaces.
    Brief = 1,
    /// `B 2`: as normal, plus a confirmation line after every set command.
    AutoConfirm = 2,
}

/// Unit description and power-on state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Config {
    /// Firmware revision reported by `V?`.
    pub revision: &'static str,
    /// Shortest tunable wavelength, centi-nm.
    pub min_centi_nm: u32,
    /// Longest tunable wavelength, centi-nm.
    pub max_centi_nm: u32,
    /// Serial number (5 digits on real units).
    pub serial: u32,
    /// Settling model.
    pub settle: SettleParams,
    /// Liquid-crystal temperature, centi-°C.
    pub temp_centi_c: i32,
    /// Seed of the jitter PRNG.
    pub seed: u64,
    /// Start already initialised (as after an earlier session).
    pub initialised: bool,
    /// Start already exercised.
    pub exercised: bool,
}

impl Config {
    /// A visible-range unit, 400–720 nm, cold-started (needs `I`).
    pub const fn visible() -> Self {
        Self {
            revision: "1.00",
            min_centi_nm: 40_000,
            max_centi_nm: 72_000,
            serial: 10_001,
            settle: SettleParams::VISIBLE,
            temp_centi_c: 2500,
            seed: 1,
            initialised: false,
            exercised: false,
        }
    }

    /// A near-infrared unit, 650–1100 nm, cold-started.
    pub const fn nir() -> Self {
        Self {
            min_centi_nm: 65_000,
            max_centi_nm: 110_000,
            serial: 10_002,
            settle: SettleParams::NIR,
            ..Self::visible()
        }
    }
}

impl Default for Config {
    fn default() -> Self {
        Self::visible()
    }
}

/// Trigger-output events.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event {
    /// The "settled" output went high: the passband reached 95 % of the step
    /// to `centi_nm` at device time `at_us`.
    Settled { at_us: u64, centi_nm: u32 },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum LongOp {
    Initialise,
    Exercise,
}

/// A single value in a reply.
#[derive(Debug, Clone, Copy)]
enum Val {
    Int(i64),
    Centi(i64),
    Star,
    Text(&'static str),
}

/// The controller.
#[derive(Debug, Clone)]
pub struct Controller {
    cfg: Config,
    line: Vec<u8, LINE_CAPACITY>,
    line_overflow: bool,
    out: Deque<u8, OUT_CAPACITY>,
    out_dropped: u32,
    queue: Deque<Command, QUEUE_CAPACITY>,
    events: Deque<Event, EVENT_CAPACITY>,
    mode: ReplyMode,
    initialised: bool,
    exercised: bool,
    asleep: bool,
    error: Option<ErrorCode>,
    palette: [Option<u32>; PALETTE_CAPACITY],
    palette_pos: u8,
    seq_mode: u8,
    divider: u16,
    pulses: u16,
    jump: i32,
    target: Option<u32>,
    motion: Motion,
    moving: bool,
    long_op: Option<(LongOp, u64)>,
    rng: Prng,
    temp_centi_c: i32,
    now: u64,
}

impl Controller {
    /// A controller in its power-on state.
    pub fn new(cfg: Config) -> Self {
        Self {
            cfg,
            line: Vec::new(),
            line_overflow: false,
            out: Deque::new(),
            out_dropped: 0,
            queue: Deque::new(),
            events: Deque::new(),
            mode: ReplyMode::Normal,
            initialised: cfg.initialised,
            exercised: cfg.exercised,
            asleep: false,
            error: None,
            palette: [None; PALETTE_CAPACITY],
            palette_pos: 0,
            seq_mode: 0,
            divider: 0,
            pulses: 0,
            jump: 0,
            target: None,
            motion: Motion::resting(cfg.min_centi_nm),
            moving: false,
            long_op: None,
            rng: Prng::new(cfg.seed),
            temp_centi_c: cfg.temp_centi_c,
            now: 0,
        }
    }

    /// The unit description.
    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// Receive one byte at device time `now_us`.
    pub fn feed(&mut self, byte: u8, now_us: u64) {
        self.poll(now_us);
        match byte {
            ESC => {
                self.push(ESC);
                self.long_op = None;
                self.queue.clear();
                self.line.clear();
                self.line_overflow = false;
            }
            BUSY_QUERY => {
                self.push(BUSY_QUERY);
                let b = if self.is_busy() { b'<' } else { b'>' };
                self.push(b);
            }
            STATUS_QUERY => {
                self.push(STATUS_QUERY);
                let s = self.status_byte();
                self.push(s);
            }
            // irid's choice: LF is ignored (not echoed) so "\r\n" clients work.
            b'\n' => {}
            b'\r' => {
                self.push(b'\r');
                let overflow = core::mem::replace(&mut self.line_overflow, false);
                let line = core::mem::take(&mut self.line);
                if overflow {
                    self.error = Some(ErrorCode::Syntax);
                } else if !line.is_empty() {
                    match parse_line(&line) {
                        Ok(cmd) => self.submit(cmd),
                        Err(e) => self.error = Some(e),
                    }
                }
            }
            other => {
                self.push(other);
                if self.line.push(other).is_err() {
                    self.line_overflow = true;
                }
            }
        }
    }

    /// Advance device time to `now_us`: finish `I`/`E`, run queued commands,
    /// raise "settled" events. Call it regularly (the emulator does every
    /// millisecond) and before reading [`Controller::is_busy`].
    pub fn poll(&mut self, now_us: u64) {
        self.now = self.now.max(now_us);
        loop {
            if let Some((op, until)) = self.long_op {
                if self.now < until {
                    break;
                }
                self.long_op = None;
                match op {
                    LongOp::Initialise => self.initialised = true,
                    LongOp::Exercise => self.exercised = true,
                }
            }
            match self.queue.pop_front() {
                Some(cmd) => self.run(cmd),
                None => break,
            }
        }
        if self.moving && self.motion.is_settled(self.now) {
            self.moving = false;
            self.emit(Event::Settled {
                at_us: self.motion.settled_at(),
                centi_nm: self.motion.target(),
            });
        }
    }

    /// A pulse on the sync input at `now_us`: every `G`-th pulse advances the
    /// sequence (palette in mode 0, `J` step in mode 4).
    pub fn sync_pulse(&mut self, now_us: u64) {
        self.poll(now_us);
        if self.divider == 0 || self.long_op.is_some() {
            return;
        }
        self.pulses = self.pulses.saturating_add(1);
        if self.pulses >= self.divider {
            self.pulses = 0;
            if let Err(e) = self.advance() {
                self.error = Some(e);
            }
        }
    }

    /// Level of the "settled" trigger output: high when nothing is moving or
    /// running.
    pub fn settled(&self) -> bool {
        !self.is_busy()
    }

    /// Whether `!` would answer busy (as of the last `feed`/`poll`).
    pub fn is_busy(&self) -> bool {
        self.long_op.is_some() || (self.moving && !self.motion.is_settled(self.now))
    }

    /// Device time when the current motion settles, if one is under way.
    pub fn settles_at(&self) -> Option<u64> {
        self.moving.then(|| self.motion.settled_at())
    }

    /// Passband centre now, centi-nm (for a synthetic camera).
    pub fn position_centi(&self) -> f64 {
        self.motion.position_centi(self.now)
    }

    /// The wavelength register (`None` prints as `*`).
    pub fn target_centi(&self) -> Option<u32> {
        self.target
    }

    /// The pending error, if any.
    pub fn error(&self) -> Option<ErrorCode> {
        self.error
    }

    /// Raise an error as if a command had failed (fault injection).
    pub fn inject_error(&mut self, e: ErrorCode) {
        self.error = Some(e);
    }

    /// Current reply mode.
    pub fn reply_mode(&self) -> ReplyMode {
        self.mode
    }

    /// Change the liquid-crystal temperature (affects later motions).
    pub fn set_temperature(&mut self, temp_centi_c: i32) {
        self.temp_centi_c = temp_centi_c;
    }

    /// The status byte answered to `@`.
    pub fn status_byte(&self) -> u8 {
        let mut s = status::ALWAYS;
        if self.initialised {
            s |= status::INITIALISED;
        }
        if self.exercised {
            s |= status::EXERCISED;
        }
        if self.palette.iter().any(Option::is_some) {
            s |= status::PALETTE_DEFINED;
        }
        if self.mode == ReplyMode::Brief {
            s |= status::BRIEF;
        }
        if self.error.is_some() {
            s |= status::ERROR_PENDING;
        }
        s
    }

    /// Next byte to transmit.
    pub fn pop_output(&mut self) -> Option<u8> {
        self.out.pop_front()
    }

    /// Bytes waiting to be transmitted.
    pub fn output_len(&self) -> usize {
        self.out.len()
    }

    /// Reply bytes lost because the output queue was full.
    pub fn output_dropped(&self) -> u32 {
        self.out_dropped
    }

    /// Next trigger event.
    pub fn pop_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    fn emit(&mut self, e: Event) {
        if self.events.is_full() {
            self.events.pop_front();
        }
        let _ = self.events.push_back(e);
    }

    fn push(&mut self, b: u8) {
        if self.out.push_back(b).is_err() {
            self.out_dropped = self.out_dropped.saturating_add(1);
        }
    }

    fn push_str(&mut self, s: &str) {
        for b in s.bytes() {
            self.push(b);
        }
    }

    /// Run now, or queue behind a running `I`/`E` (the unit is deaf to line
    /// commands while it drives the liquid crystal through its range).
    fn submit(&mut self, cmd: Command) {
        if self.long_op.is_some() {
            if self.queue.push_back(cmd).is_err() {
                self.error = Some(ErrorCode::Syntax);
            }
        } else {
            self.run(cmd);
        }
    }

    fn run(&mut self, cmd: Command) {
        match self.execute(cmd) {
            Ok(Some((letter, val))) => {
                if self.mode == ReplyMode::AutoConfirm {
                    self.reply(letter.to_ascii_lowercase(), &[val]);
                }
            }
            Ok(None) => {}
            Err(e) => self.error = Some(e),
        }
    }

    /// Execute one command; `Ok(Some(..))` is the confirmation value of a set
    /// command (sent in auto-confirm mode).
    fn execute(&mut self, cmd: Command) -> Result<Option<(u8, Val)>, ErrorCode> {
        let zero = Val::Int(0);
        Ok(Some(match cmd {
            Command::Query(letter) => {
                self.answer(letter);
                return Ok(None);
            }
            Command::Awaken(serial) => {
                if self.addressed(serial) && self.asleep {
                    self.asleep = false;
                    if let Some(t) = self.target {
                        self.start_motion(t);
                    }
                }
                (b'A', zero)
            }
            Command::Brief(n) => {
                self.mode = match n {
                    1 => ReplyMode::Brief,
                    2 => ReplyMode::AutoConfirm,
                    _ => ReplyMode::Normal,
                };
                (b'B', Val::Int(i64::from(n)))
            }
            Command::ClearPalette => {
                self.palette = [None; PALETTE_CAPACITY];
                self.palette_pos = 0;
                (b'C', zero)
            }
            Command::Define { centi_nm, index } => {
                self.check_range(centi_nm)?;
                if let Some(slot) = self.palette.get_mut(usize::from(index)) {
                    *slot = Some(centi_nm);
                }
                (b'D', Val::Centi(i64::from(centi_nm)))
            }
            Command::Exercise(n) => {
                let d = EXERCISE_CYCLE_US.saturating_mul(u64::from(n));
                self.exercised = false;
                self.long_op = Some((LongOp::Exercise, self.now.saturating_add(d)));
                (b'E', Val::Int(i64::from(n)))
            }
            Command::SyncDivider(n) => {
                self.divider = n;
                self.pulses = 0;
                (b'G', Val::Int(i64::from(n)))
            }
            Command::Initialise => {
                self.initialised = false;
                self.long_op = Some((LongOp::Initialise, self.now.saturating_add(INITIALISE_US)));
                (b'I', zero)
            }
            Command::Jump(j) => {
                let span = i64::from(self.cfg.max_centi_nm) - i64::from(self.cfg.min_centi_nm);
                if i64::from(j).abs() > span {
                    return Err(ErrorCode::JumpTooLarge);
                }
                self.jump = j;
                (b'J', Val::Centi(i64::from(j)))
            }
            Command::Mode(m) => {
                self.seq_mode = m;
                (b'M', Val::Int(i64::from(m)))
            }
            Command::Palette(step) => {
                self.select_palette(step)?;
                (b'P', Val::Int(i64::from(self.palette_pos)))
            }
            Command::ResetError => {
                self.error = None;
                (b'R', zero)
            }
            Command::Sleep(serial) => {
                if self.addressed(serial) {
                    self.asleep = true;
                    self.moving = false;
                }
                (b'S', zero)
            }
            Command::Wavelength(step) => {
                self.step_wavelength(step)?;
                (
                    b'W',
                    self.target.map_or(Val::Star, |t| Val::Centi(i64::from(t))),
                )
            }
            Command::Trigger => {
                self.advance()?;
                (b'X', zero)
            }
        }))
    }

    /// irid's choice: `A`/`S` with another unit's serial are ignored, as on a
    /// shared line they address that unit.
    fn addressed(&self, serial: Option<u32>) -> bool {
        serial.is_none_or(|s| s == self.cfg.serial)
    }

    fn check_range(&self, centi: u32) -> Result<(), ErrorCode> {
        if (self.cfg.min_centi_nm..=self.cfg.max_centi_nm).contains(&centi) {
            Ok(())
        } else {
            Err(ErrorCode::WavelengthRange)
        }
    }

    fn step_wavelength(&mut self, step: Step<u32>) -> Result<(), ErrorCode> {
        if !self.initialised {
            return Err(ErrorCode::NotInitialised);
        }
        let wl = match step {
            Step::To(wl) => {
                if let Err(e) = self.check_range(wl) {
                    // As micro-manager's adapter expects: `W?` then reads `*`.
                    self.target = None;
                    return Err(e);
                }
                wl
            }
            Step::Next | Step::Prev => {
                let base = self.target.ok_or(ErrorCode::WavelengthRange)?;
                let j = if step == Step::Next {
                    self.jump
                } else {
                    -self.jump
                };
                let wl = i64::from(base) + i64::from(j);
                let wl = u32::try_from(wl).map_err(|_| ErrorCode::WavelengthRange)?;
                self.check_range(wl)?;
                wl
            }
        };
        self.tune(wl);
        Ok(())
    }

    fn select_palette(&mut self, step: Step<u8>) -> Result<(), ErrorCode> {
        if !self.initialised {
            return Err(ErrorCode::NotInitialised);
        }
        let n = PALETTE_CAPACITY;
        let idx = match step {
            Step::To(i) => usize::from(i),
            Step::Next | Step::Prev => {
                let cur = usize::from(self.palette_pos);
                // Walk to the next defined entry, wrapping (irid's choice).
                (1..=n)
                    .map(|k| {
                        if step == Step::Next {
                            (cur + k) % n
                        } else {
                            (cur + n - k) % n
                        }
                    })
                    .find(|&i| self.palette.get(i).copied().flatten().is_some())
                    .ok_or(ErrorCode::PaletteUndefined)?
            }
        };
        let wl = self
            .palette
            .get(idx)
            .copied()
            .flatten()
            .ok_or(ErrorCode::PaletteUndefined)?;
        self.palette_pos = idx as u8;
        self.tune(wl);
        Ok(())
    }

    /// One sequence step (sync pulse or `X`).
    fn advance(&mut self) -> Result<(), ErrorCode> {
        match self.seq_mode {
            4 => self.step_wavelength(Step::Next),
            _ => self.select_palette(Step::Next),
        }
    }

    fn tune(&mut self, wl: u32) {
        self.target = Some(wl);
        if !self.asleep {
            self.start_motion(wl);
        }
    }

    fn start_motion(&mut self, wl: u32) {
        self.motion = self.motion.retarget(
            wl,
            self.now,
            &self.cfg.settle,
            self.temp_centi_c,
            &mut self.rng,
        );
        self.moving = true;
    }

    fn answer(&mut self, letter: u8) {
        let b = |v: bool| Val::Int(i64::from(v));
        match letter {
            b'B' => self.reply(letter, &[Val::Int(self.mode as i64)]),
            b'C' => self.reply(letter, &[Val::Int(0)]),
            b'D' => {
                let count = self.palette.iter().filter(|e| e.is_some()).count();
                self.reply(letter, &[Val::Int(count as i64)]);
                for i in 0..PALETTE_CAPACITY {
                    if let Some(wl) = self.palette[i] {
                        self.reply(letter, &[Val::Int(i as i64), Val::Centi(i64::from(wl))]);
                    }
                }
            }
            b'E' => self.reply(letter, &[b(self.exercised)]),
            b'G' => self.reply(letter, &[Val::Int(i64::from(self.divider))]),
            b'I' => self.reply(letter, &[b(self.initialised)]),
            b'J' => self.reply(letter, &[Val::Centi(i64::from(self.jump))]),
            b'M' => self.reply(letter, &[Val::Int(i64::from(self.seq_mode))]),
            b'P' => self.reply(letter, &[Val::Int(i64::from(self.palette_pos))]),
            b'R' => self.reply(
                letter,
                &[Val::Int(self.error.map_or(0, |e| i64::from(e.code())))],
            ),
            b'S' => self.reply(letter, &[b(self.asleep)]),
            b'V' => {
                let nm = |c: u32| {
                    if c.is_multiple_of(100) {
                        Val::Int(i64::from(c / 100))
                    } else {
                        Val::Centi(i64::from(c))
                    }
                };
                self.reply(
                    letter,
                    &[
                        Val::Text(self.cfg.revision),
                        nm(self.cfg.min_centi_nm),
                        nm(self.cfg.max_centi_nm),
                        Val::Int(i64::from(self.cfg.serial)),
                    ],
                );
            }
            b'W' => {
                let v = self.target.map_or(Val::Star, |t| Val::Centi(i64::from(t)));
                self.reply(letter, &[v]);
            }
            b'Y' => self.reply(letter, &[Val::Centi(i64::from(self.temp_centi_c))]),
            // The parser only lets the letters above through.
            _ => self.error = Some(ErrorCode::Syntax),
        }
    }

    /// One reply line in the current mode; `letter` is omitted in brief mode.
    fn reply(&mut self, letter: u8, vals: &[Val]) {
        let brief = self.mode == ReplyMode::Brief;
        if !brief {
            self.push(letter);
        }
        for (i, v) in vals.iter().enumerate() {
            let mut s: String<24> = String::new();
            // A 24-byte buffer fits every value we format (i64 is ≤ 20 chars);
            // a failure would only truncate, never panic.
            let _ = match *v {
                Val::Int(n) => write!(s, "{n}"),
                Val::Centi(c) => {
                    let sign = if c < 0 { "-" } else { "" };
                    let a = c.unsigned_abs();
                    write!(s, "{sign}{}.{:02}", a / 100, a % 100)
                }
                Val::Star => s.push_str("*").map_err(|_| core::fmt::Error),
                Val::Text(t) => s.push_str(t).map_err(|_| core::fmt::Error),
            };
            if brief {
                if i > 0 {
                    self.push(b' ');
                }
            } else {
                let pad = NORMAL_FIELD.saturating_sub(s.len()).max(1);
                for _ in 0..pad {
                    self.push(b' ');
                }
            }
            self.push_str(&s);
        }
        self.push(b'\r');
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ready() -> Controller {
        Controller::new(Config {
            initialised: true,
            exercised: true,
            ..Config::visible()
        })
    }

    /// Send `s` at `now` and return everything the controller transmitted.
    fn send(c: &mut Controller, s: &[u8], now: u64) -> std::string::String {
        for &b in s {
            c.feed(b, now);
        }
        let mut out = std::vec::Vec::new();
        while let Some(b) = c.pop_output() {
            out.push(b);
        }
        std::string::String::from_utf8_lossy(&out).into_owned()
    }

    #[test]
    fn echoes_and_replies_in_each_mode() {
        let mut c = ready();
        assert_eq!(send(&mut c, b"W 550\r", 0), "W 550\r");
        assert_eq!(send(&mut c, b"W?\r", 0), "W?\rW 550.00\r");
        assert_eq!(
            send(&mut c, b"V?\r", 0),
            "V?\rV   1.00    400    720  10001\r"
        );
        assert_eq!(send(&mut c, b"B1\r", 0), "B1\r");
        assert_eq!(send(&mut c, b"W?\r", 0), "W?\r550.00\r");
        assert_eq!(send(&mut c, b"V ?\r", 0), "V ?\r1.00 400 720 10001\r");
        assert_eq!(send(&mut c, b"B2\r", 0), "B2\rb      2\r");
        assert_eq!(send(&mut c, b"W 600.5\r", 0), "W 600.5\rw 600.50\r");
        assert_eq!(send(&mut c, b"W?\r", 0), "W?\rW 600.50\r");
        assert_eq!(send(&mut c, b"B0\r", 0), "B0\r");
    }

    #[test]
    fn immediate_commands_answer_at_once() {
        let mut c = ready();
        assert_eq!(send(&mut c, b"!", 0), "!>");
        assert_eq!(send(&mut c, b"@", 0), "@C");
        send(&mut c, b"W 500\r", 1_000);
        assert_eq!(send(&mut c, b"!", 2_000), "!<");
        // Immediate commands inside a partial line do not disturb it.
        assert_eq!(send(&mut c, b"W?", 2_000), "W?");
        assert_eq!(send(&mut c, b"!", 2_000), "!<");
        assert_eq!(send(&mut c, b"\r", 2_000), "\rW 500.00\r");
        assert_eq!(send(&mut c, b"!", 60_000), "!>");
    }

    #[test]
    fn busy_until_settled_then_event() {
        let mut c = ready();
        send(&mut c, b"W 500\r", 10_000);
        let at = c.settles_at().unwrap();
        assert!((60_000..=62_000).contains(&at), "{at}");
        c.poll(at - 1);
        assert!(c.is_busy());
        assert_eq!(c.pop_event(), None);
        c.poll(at + 500);
        assert!(c.settled());
        assert_eq!(
            c.pop_event(),
            Some(Event::Settled {
                at_us: at,
                centi_nm: 50_000
            })
        );
    }

    #[test]
    fn errors_are_pending_until_reset() {
        let mut c = ready();
        assert_eq!(send(&mut c, b"W 900\r", 0), "W 900\r");
        assert_eq!(
            c.status_byte() & status::ERROR_PENDING,
            status::ERROR_PENDING
        );
        assert_eq!(send(&mut c, b"R?\r", 0), "R?\rR     12\r");
        assert_eq!(send(&mut c, b"W?\r", 0), "W?\rW      *\r");
        // Processing continues with the error pending.
        assert_eq!(send(&mut c, b"W 450\r", 0), "W 450\r");
        assert_eq!(send(&mut c, b"R 1\r", 0), "R 1\r");
        assert_eq!(send(&mut c, b"R?\r", 0), "R?\rR      0\r");
        assert_eq!(send(&mut c, b"bogus\r", 0), "bogus\r");
        assert_eq!(c.error(), Some(ErrorCode::Syntax));
        send(&mut c, b"R1\r", 0);
        send(&mut c, b"P 5\r", 0);
        assert_eq!(c.error(), Some(ErrorCode::PaletteUndefined));
        send(&mut c, b"J 400\r", 0);
        assert_eq!(c.error(), Some(ErrorCode::JumpTooLarge));
        let long = [b'W'; 40];
        send(&mut c, b"R1\r", 0);
        send(&mut c, &long, 0);
        send(&mut c, b"\r", 0);
        assert_eq!(c.error(), Some(ErrorCode::Syntax));
    }

    #[test]
    fn cold_start_needs_initialise_which_queues_commands() {
        let mut c = Controller::new(Config::visible());
        assert_eq!(send(&mut c, b"@", 0), "@@");
        send(&mut c, b"W 500\r", 0);
        assert_eq!(c.error(), Some(ErrorCode::NotInitialised));
        send(&mut c, b"R1\r", 0);
        assert_eq!(send(&mut c, b"I1\r", 0), "I1\r");
        assert_eq!(send(&mut c, b"!", 1_000_000), "!<");
        // Queued: echoed now, answered when the initialisation completes.
        assert_eq!(send(&mut c, b"W?\r", 1_000_000), "W?\r");
        c.poll(INITIALISE_US);
        assert_eq!(send(&mut c, b"", INITIALISE_US), "W      *\r");
        assert_eq!(send(&mut c, b"@", INITIALISE_US), "@A");
    }

    #[test]
    fn escape_aborts_initialise_and_flushes() {
        let mut c = Controller::new(Config::visible());
        send(&mut c, b"I\rW?\rW 5", 0);
        assert_eq!(send(&mut c, b"\x1b", 10), "\x1b");
        assert_eq!(send(&mut c, b"!", 20), "!>");
        c.poll(INITIALISE_US * 2);
        assert_eq!(send(&mut c, b"", INITIALISE_US * 2), "");
        assert_eq!(c.status_byte() & status::INITIALISED, 0);
    }

    #[test]
    fn palette_cycles_on_sync_with_divider() {
        let mut c = ready();
        send(&mut c, b"C1\rD 500,0\rD 600,1\rD 700,2\rM0\rG2\rP0\r", 0);
        assert_eq!(c.error(), None);
        assert_eq!(c.target_centi(), Some(50_000));
        c.sync_pulse(100_000);
        assert_eq!(c.target_centi(), Some(50_000));
        c.sync_pulse(200_000);
        assert_eq!(c.target_centi(), Some(60_000));
        c.sync_pulse(300_000);
        c.sync_pulse(400_000);
        c.sync_pulse(500_000);
        c.sync_pulse(600_000);
        assert_eq!(c.target_centi(), Some(50_000), "wraps");
        assert_eq!(
            send(&mut c, b"D?\r", 600_000),
            "D?\rD      3\rD      0 500.00\rD      1 600.00\rD      2 700.00\r"
        );
        send(&mut c, b"X\r", 700_000);
        assert_eq!(c.target_centi(), Some(60_000));
    }

    #[test]
    fn mode_4_steps_by_jump() {
        let mut c = ready();
        send(&mut c, b"W 500\rJ 10\rM4\rG1\r", 0);
        c.sync_pulse(1);
        c.sync_pulse(2);
        assert_eq!(c.target_centi(), Some(52_000));
        send(&mut c, b"W<\r", 3);
        assert_eq!(c.target_centi(), Some(51_000));
        send(&mut c, b"W 715\r", 4);
        c.sync_pulse(5);
        assert_eq!(c.error(), Some(ErrorCode::WavelengthRange));
        assert_eq!(c.target_centi(), Some(71_500));
    }

    #[test]
    fn sleep_defers_tuning_until_awake() {
        let mut c = ready();
        send(&mut c, b"S\rW 600\r", 0);
        assert!(!c.is_busy());
        send(&mut c, b"A 99\r", 10);
        assert!(!c.is_busy(), "other unit's serial is ignored");
        send(&mut c, b"A 10001\r", 20);
        assert!(c.is_busy());
    }

    #[test]
    fn time_going_backwards_is_harmless() {
        let mut c = ready();
        send(&mut c, b"W 500\r", 1_000_000);
        c.poll(0);
        assert!(c.is_busy());
        c.poll(2_000_000);
        assert!(!c.is_busy());
    }
}
