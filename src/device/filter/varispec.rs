//! VariSpec-protocol driver over a serial port.
//!
//! Promises: every method returns within a bound set by
//! [`VariSpecOptions`] (each attempt waits at most `reply_timeout` per
//! reply; idempotent commands are retried at most `retries` times after a
//! resynchronisation); echoes are checked byte for byte; after every set
//! command the status byte is checked and a pending error is read (`R?`),
//! cleared (`R 1`) and reported with the controller's code. Line commands
//! are sent in normal reply mode (`B 0`, set when the port is opened).

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::time::{Duration, Instant};

use serialport::{ClearBuffer, SerialPort};

use super::reply::{self, ReplyError};
use super::{error_meaning, ControllerInfo, FilterController, FilterError, Status};

/// Status-byte bits (see `firmware-host/PROTOCOL.md`).
const ST_INITIALISED: u8 = 0x01;
const ST_EXERCISED: u8 = 0x02;
const ST_PALETTE: u8 = 0x04;
const ST_ERROR: u8 = 0x20;
const ESC: u8 = 0x1b;
/// Palette entries the protocol provides.
pub const PALETTE_CAPACITY: usize = 128;
/// A quiet line for this long means no stale bytes are still coming.
const QUIET: Duration = Duration::from_millis(15);

/// Longest reply line kept waiting for its line end: the longest real one
/// (the version string) is ~40 bytes.
const MAX_LINE: usize = 512;
/// Bytes of unexpected input quoted in an error.
const QUOTED: usize = 64;

/// `got`, as text, cut to its first [`QUOTED`] bytes.
fn quote(got: &[u8]) -> String {
    let mut s = String::from_utf8_lossy(&got[..got.len().min(QUOTED)]).into_owned();
    if got.len() > QUOTED {
        s.push_str(&format!("… ({} bytes)", got.len()));
    }
    s
}

/// Serial and retry settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VariSpecOptions {
    /// Baud rate (9600 on most units, 115200 on some).
    pub baud: u32,
    /// Longest wait for any one reply (echo line, value line, immediate answer).
    pub reply_timeout: Duration,
    /// Extra attempts for idempotent commands after a transient failure.
    pub retries: u32,
    /// Pause between busy polls in [`FilterController::wait_settled`].
    pub poll_interval: Duration,
}

impl Default for VariSpecOptions {
    fn default() -> Self {
        Self {
            baud: 9600,
            reply_timeout: Duration::from_millis(500),
            retries: 3,
            poll_interval: Duration::from_micros(500),
        }
    }
}

/// A VariSpec-protocol controller on a serial port.
pub struct VariSpec {
    port: Box<dyn SerialPort>,
    opts: VariSpecOptions,
    rx: VecDeque<u8>,
    info: Option<ControllerInfo>,
    tuned_at: Option<Instant>,
}

impl std::fmt::Debug for VariSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VariSpec")
            .field("port", &self.port.name())
            .field("opts", &self.opts)
            .field("info", &self.info)
            .finish()
    }
}

impl VariSpec {
    /// Open `path`, resynchronise, select normal replies and read the version.
    pub fn open(path: &str, opts: VariSpecOptions) -> Result<Self, FilterError> {
        let port = serialport::new(path, opts.baud)
            .timeout(opts.reply_timeout)
            .open()
            .map_err(|source| FilterError::Open {
                port: path.to_owned(),
                source,
            })?;
        let mut v = Self {
            port,
            opts,
            rx: VecDeque::new(),
            info: None,
            tuned_at: None,
        };
        v.resync(false)?;
        v.retrying(|v| v.command("B0"))?;
        let info = v.version()?;
        v.info = Some(info);
        Ok(v)
    }

    /// The options in use.
    pub fn options(&self) -> &VariSpecOptions {
        &self.opts
    }

    /// Upper bound on one retried set command or query: per attempt at most
    /// five reply waits (echo, status, `R?` echo and value, `R 1`) plus a
    /// resynchronisation (two reply timeouts).
    pub fn worst_case_command(&self) -> Duration {
        (self.opts.reply_timeout * 7 + QUIET) * (self.opts.retries + 1)
    }

    fn write_all(&mut self, bytes: &[u8]) -> Result<(), FilterError> {
        self.port.write_all(bytes)?;
        self.port.flush()?;
        Ok(())
    }

    /// Read at least one more byte into `rx`, or time out at `deadline`.
    fn fill(&mut self, deadline: Instant) -> Result<bool, FilterError> {
        let now = Instant::now();
        if now >= deadline {
            return Ok(false);
        }
        self.port
            .set_timeout(deadline - now)
            .map_err(std::io::Error::from)?;
        let mut buf = [0u8; 256];
        match self.port.read(&mut buf) {
            Ok(0) => Ok(false),
            Ok(n) => {
                self.rx.extend(&buf[..n]);
                Ok(true)
            }
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => Ok(false),
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => Ok(true),
            Err(e) => Err(e.into()),
        }
    }

    fn timeout(&self, what: &str, started: Instant, got: &[u8]) -> FilterError {
        FilterError::Timeout {
            what: what.to_owned(),
            waited: started.elapsed(),
            got: quote(got),
        }
    }

    /// Next `\r`-terminated line (without the `\r`).
    fn read_line(&mut self, what: &str, deadline: Instant) -> Result<Vec<u8>, FilterError> {
        let started = Instant::now();
        loop {
            if let Some(i) = self.rx.iter().position(|&b| b == b'\r') {
                let line: Vec<u8> = self.rx.drain(..=i).take(i).collect();
                return Ok(line);
            }
            if self.rx.len() > MAX_LINE {
                // A flood without line ends never becomes a reply: stop
                // before it costs memory (the next command resynchronises).
                let head: Vec<u8> = self.rx.iter().copied().take(QUOTED).collect();
                self.rx.clear();
                return Err(FilterError::LineTooLong {
                    what: what.to_owned(),
                    limit: MAX_LINE,
                    head: String::from_utf8_lossy(&head).into_owned(),
                });
            }
            if !self.fill(deadline)? {
                let got: Vec<u8> = self.rx.iter().copied().collect();
                return Err(self.timeout(what, started, &got));
            }
        }
    }

    /// Send an immediate single-byte command and read its two-byte answer.
    fn immediate(&mut self, cmd: u8) -> Result<[u8; 2], FilterError> {
        self.write_all(&[cmd])?;
        let started = Instant::now();
        let deadline = started + self.opts.reply_timeout;
        loop {
            // Stale answers of an earlier, timed-out query may precede ours:
            // skip to our echo.
            while self.rx.front().is_some_and(|&b| b != cmd) {
                self.rx.pop_front();
            }
            if self.rx.len() >= 2 {
                let a = [self.rx[0], self.rx[1]];
                self.rx.drain(..2);
                return Ok(a);
            }
            if !self.fill(deadline)? {
                let got: Vec<u8> = self.rx.iter().copied().collect();
                return Err(self.timeout(
                    &format!("answer to {:?}", char::from(cmd)),
                    started,
                    &got,
                ));
            }
        }
    }

    /// Drop stale input until the line is quiet. With `escape`, first send
    /// ESC (abort, flush the controller's partial line) and `R 1`.
    fn resync(&mut self, escape: bool) -> Result<(), FilterError> {
        if escape {
            self.write_all(b"\x1bR1\r")?;
        }
        let limit = Instant::now() + self.opts.reply_timeout * 2;
        loop {
            self.rx.clear();
            let quiet_until = (Instant::now() + QUIET).min(limit);
            if !self.fill(quiet_until)? || Instant::now() >= limit {
                break;
            }
        }
        self.rx.clear();
        let _ = self.port.clear(ClearBuffer::Input);
        Ok(())
    }

    /// Send a line command, check its echo, and return `reply_lines` lines.
    fn transact(&mut self, cmd: &str, reply_lines: usize) -> Result<Vec<Vec<u8>>, FilterError> {
        let mut bytes = cmd.as_bytes().to_vec();
        bytes.push(b'\r');
        self.write_all(&bytes)?;
        let deadline = Instant::now() + self.opts.reply_timeout;
        let echo = self.read_line(&format!("echo of {cmd:?}"), deadline)?;
        // A leading ESC echo from a resync may precede the line.
        let trimmed: &[u8] = {
            let start = echo.iter().position(|&b| b != ESC).unwrap_or(echo.len());
            &echo[start..]
        };
        if trimmed != cmd.as_bytes() {
            return Err(FilterError::Echo {
                sent: cmd.to_owned(),
                echoed: String::from_utf8_lossy(&echo).into_owned(),
            });
        }
        let mut lines = Vec::with_capacity(reply_lines);
        for _ in 0..reply_lines {
            let deadline = Instant::now() + self.opts.reply_timeout;
            lines.push(self.read_line(&format!("reply to {cmd:?}"), deadline)?);
        }
        Ok(lines)
    }

    fn status_raw(&mut self) -> Result<u8, FilterError> {
        let a = self.immediate(b'@')?;
        reply::status_byte(&a).map_err(|why| reply_err("@", &a, why))
    }

    /// Read, clear and report a pending error, if any.
    fn check_error(&mut self, cmd: &str) -> Result<(), FilterError> {
        if self.status_raw()? & ST_ERROR == 0 {
            return Ok(());
        }
        let code = self.query("R?", b'R')?;
        self.transact("R1", 0)?;
        let code = code.round().clamp(0.0, 255.0) as u8;
        Err(FilterError::Controller {
            command: cmd.to_owned(),
            code,
            meaning: error_meaning(code),
        })
    }

    /// A set command: echo, then check the error status.
    fn command(&mut self, cmd: &str) -> Result<(), FilterError> {
        self.transact(cmd, 0)?;
        self.check_error(cmd)
    }

    /// A query with one numeric value.
    fn query(&mut self, cmd: &str, letter: u8) -> Result<f64, FilterError> {
        let lines = self.transact(cmd, 1)?;
        reply::value(&lines[0], letter).map_err(|why| reply_err(cmd, &lines[0], why))
    }

    /// Run `f`, retrying transient failures after a resynchronisation. Only
    /// for idempotent operations.
    fn retrying<T>(
        &mut self,
        mut f: impl FnMut(&mut Self) -> Result<T, FilterError>,
    ) -> Result<T, FilterError> {
        let mut attempt = 0;
        loop {
            match f(self) {
                Ok(v) => return Ok(v),
                Err(e) if e.is_transient() && attempt < self.opts.retries => {
                    tracing::debug!(error = %e, attempt, "lctf: retrying after resync");
                    attempt += 1;
                    self.resync(true)?;
                }
                Err(e) => return Err(e),
            }
        }
    }

    fn check_range(&self, nm: f64) -> Result<(), FilterError> {
        if let Some(i) = &self.info {
            if !(nm.is_finite() && nm >= i.min_nm && nm <= i.max_nm) {
                return Err(FilterError::OutOfRange {
                    nm,
                    min_nm: i.min_nm,
                    max_nm: i.max_nm,
                });
            }
        }
        Ok(())
    }

    /// Wait until `!` answers idle, polling; without touching the
    /// controller's state (no ESC), so it is safe during `I`/`E`.
    fn wait_idle(&mut self, timeout: Duration) -> Result<(), FilterError> {
        let deadline = Instant::now() + timeout;
        loop {
            match self
                .immediate(b'!')
                .and_then(|a| reply::busy(&a).map_err(|why| reply_err("!", &a, why)))
            {
                Ok(false) => return Ok(()),
                Ok(true) => {}
                Err(e) if e.is_transient() => {
                    tracing::debug!(error = %e, "lctf: busy poll failed");
                    self.resync(false)?;
                }
                Err(e) => return Err(e),
            }
            if Instant::now() >= deadline {
                return Err(FilterError::NotSettled(timeout));
            }
            std::thread::sleep(self.opts.poll_interval);
        }
    }
}

fn reply_err(cmd: &str, reply: &[u8], why: ReplyError) -> FilterError {
    FilterError::Reply {
        command: cmd.to_owned(),
        reply: String::from_utf8_lossy(reply).into_owned(),
        why,
    }
}

impl FilterController for VariSpec {
    fn version(&mut self) -> Result<ControllerInfo, FilterError> {
        let info = self.retrying(|v| {
            let lines = v.transact("V?", 1)?;
            reply::version(&lines[0]).map_err(|why| reply_err("V?", &lines[0], why))
        })?;
        self.info = Some(info.clone());
        Ok(info)
    }

    fn set_wavelength(&mut self, nm: f64) -> Result<(), FilterError> {
        self.check_range(nm)?;
        let cmd = format!("W {nm:.2}");
        // Re-sending W is safe: it retargets the same wavelength. The settle
        // time counts from the (last) send: the unit cannot start earlier.
        self.retrying(|v| {
            v.tuned_at = Some(Instant::now());
            v.command(&cmd)
        })
    }

    fn wait_settled(&mut self, timeout: Duration) -> Result<Duration, FilterError> {
        let since = self.tuned_at.unwrap_or_else(Instant::now);
        self.wait_idle(timeout)?;
        Ok(since.elapsed())
    }

    fn define_sequence(&mut self, wavelengths_nm: &[f64]) -> Result<(), FilterError> {
        if wavelengths_nm.is_empty() || wavelengths_nm.len() > PALETTE_CAPACITY {
            return Err(FilterError::Sequence {
                len: wavelengths_nm.len(),
                max: PALETTE_CAPACITY,
            });
        }
        for &nm in wavelengths_nm {
            self.check_range(nm)?;
        }
        self.retrying(|v| v.command("C1"))?;
        for (i, &nm) in wavelengths_nm.iter().enumerate() {
            let cmd = format!("D {nm:.2},{i}");
            self.retrying(|v| v.command(&cmd))?;
        }
        self.retrying(|v| v.command("M0"))
    }

    fn select_palette(&mut self, idx: usize) -> Result<(), FilterError> {
        if idx >= PALETTE_CAPACITY {
            return Err(FilterError::Sequence {
                len: idx + 1,
                max: PALETTE_CAPACITY,
            });
        }
        let cmd = format!("P {idx}");
        self.retrying(|v| {
            v.tuned_at = Some(Instant::now());
            v.command(&cmd)
        })
    }

    fn arm_sync(&mut self, every_nth: u16) -> Result<(), FilterError> {
        let cmd = format!("G {every_nth}");
        self.retrying(|v| v.command(&cmd))
    }

    fn trigger(&mut self) -> Result<(), FilterError> {
        // Not idempotent (each X advances): a failed X is reported, not resent.
        self.tuned_at = Some(Instant::now());
        let r = self.command("X");
        if r.as_ref().is_err_and(FilterError::is_transient) {
            self.resync(true)?;
        }
        r
    }

    fn status(&mut self) -> Result<Status, FilterError> {
        self.retrying(|v| {
            let raw = v.status_raw()?;
            let a = v.immediate(b'!')?;
            let busy = reply::busy(&a).map_err(|why| reply_err("!", &a, why))?;
            let code = v.query("R?", b'R')?;
            let lines = v.transact("W?", 1)?;
            let wavelength_nm =
                reply::wavelength(&lines[0]).map_err(|why| reply_err("W?", &lines[0], why))?;
            let temperature_c = v.query("Y?", b'Y')?;
            Ok(Status {
                raw,
                initialised: raw & ST_INITIALISED != 0,
                exercised: raw & ST_EXERCISED != 0,
                palette_defined: raw & ST_PALETTE != 0,
                busy,
                error_code: code.round().clamp(0.0, 255.0) as u8,
                wavelength_nm,
                temperature_c,
            })
        })
    }

    fn ensure_ready(&mut self, timeout: Duration) -> Result<(), FilterError> {
        let deadline = Instant::now() + timeout;
        let raw = self.retrying(|v| v.status_raw())?;
        if raw & ST_INITIALISED == 0 {
            tracing::info!("lctf: initialising the filter");
            self.retrying(|v| v.command("I1"))?;
            self.wait_idle(deadline.saturating_duration_since(Instant::now()))?;
        }
        if raw & ST_EXERCISED == 0 {
            tracing::info!("lctf: exercising the liquid crystal");
            self.retrying(|v| v.command("E1"))?;
            self.wait_idle(deadline.saturating_duration_since(Instant::now()))?;
        }
        Ok(())
    }

    fn reset(&mut self) -> Result<(), FilterError> {
        self.resync(true)?;
        self.retrying(|v| v.command("B0"))
    }
}
