//! Host emulator: the firmware core served on a pseudo-terminal.
//!
//! [`spawn_pty`] opens a pty pair in raw mode and runs a [`Controller`] on a
//! thread, feeding it the bytes written to the slave side with timestamps
//! from a real monotonic clock converted through a [`TimeScale`]. Any serial
//! client (the irid driver, pyserial, micro-manager) opens
//! [`EmulatorHandle::path`] as it would a USB serial port.
//!
//! The trigger lines are host-side: [`EmulatorHandle::pulse_sync`] pulses
//! the sync input, and the "settled" output is both a level
//! ([`EmulatorHandle::settled`]) and an event channel
//! ([`EmulatorHandle::take_settled_events`]) a synthetic camera can trigger
//! from. Faults ([`Faults`]) are injected between the line and the core.
//! The thread stops, and the pty closes, when the handle is dropped.

use std::collections::VecDeque;
use std::io;
use std::os::fd::{AsFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use nix::errno::Errno;
use nix::fcntl::{fcntl, FcntlArg, OFlag};
use nix::poll::{poll, PollFd, PollFlags};
use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};

use crate::controller::{Config, Controller, Event};
use crate::settle::Prng;
use crate::timing::TimeScale;
use crate::ErrorCode;

/// Bytes read from the pty per system call.
const READ_CHUNK: usize = 256;
/// Longest the service loop sleeps waiting for input; bounds the latency of
/// busy→idle transitions and settled events.
const TICK: Duration = Duration::from_micros(500);

/// Faults injected on the serial line. Probabilities are per byte (drop,
/// garble; applied independently to each direction) or per line command
/// (spurious error).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Faults {
    /// Probability that a byte is lost.
    pub drop_prob: f64,
    /// Probability that a byte has one bit flipped.
    pub garble_prob: f64,
    /// Every reply byte is held back this long before it is sent.
    pub slow_reply: Duration,
    /// Probability that a line command leaves a spurious error pending
    /// (as if the unit had failed it), in addition to its normal effect.
    pub spurious_error_prob: f64,
}

impl Faults {
    /// Whether any fault is enabled.
    pub fn any(&self) -> bool {
        self.drop_prob > 0.0
            || self.garble_prob > 0.0
            || !self.slow_reply.is_zero()
            || self.spurious_error_prob > 0.0
    }
}

/// Emulator configuration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EmuConfig {
    /// The emulated unit.
    pub unit: Config,
    /// Device time per wall time (100 = a hundred times faster than a real unit).
    pub time_scale: TimeScale,
    /// Pace replies at this baud rate (10 bits per byte); `None` sends as
    /// fast as the pty takes them.
    pub baud: Option<u32>,
    /// Injected faults.
    pub faults: Faults,
    /// Seed of the fault PRNG (the unit's jitter has its own seed).
    pub fault_seed: u64,
}

impl Default for EmuConfig {
    fn default() -> Self {
        Self {
            unit: Config::visible(),
            time_scale: TimeScale::REAL,
            baud: None,
            faults: Faults::default(),
            fault_seed: 1,
        }
    }
}

impl EmuConfig {
    /// A visible-range unit that is already initialised and exercised (as it
    /// is after an earlier session), so it can be tuned at once.
    pub fn ready() -> Self {
        Self {
            unit: Config {
                initialised: true,
                exercised: true,
                ..Config::visible()
            },
            ..Self::default()
        }
    }
}

/// The "settled" output went high.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SettledEvent {
    /// The wavelength the filter settled at, nm.
    pub wavelength_nm: f64,
    /// Device time of the edge, µs since the emulator started.
    pub device_us: u64,
    /// Wall-clock time the emulator noticed the edge.
    pub at: Instant,
}

#[derive(Debug)]
enum Control {
    Sync,
    Temperature(i32),
}

/// A running emulator. Dropping it stops the thread and closes the pty.
#[derive(Debug)]
pub struct EmulatorHandle {
    path: PathBuf,
    stop: Arc<AtomicBool>,
    settled: Arc<AtomicBool>,
    control: mpsc::Sender<Control>,
    events: Option<mpsc::Receiver<SettledEvent>>,
    thread: Option<JoinHandle<()>>,
}

impl EmulatorHandle {
    /// Path of the pty's slave side: open it as a serial port.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Pulse the sync (trigger) input once.
    pub fn pulse_sync(&self) {
        let _ = self.control.send(Control::Sync);
    }

    /// Change the liquid-crystal temperature (°C); later tunings use it.
    pub fn set_temperature(&self, celsius: f64) {
        let _ = self
            .control
            .send(Control::Temperature((celsius * 100.0).round() as i32));
    }

    /// Level of the "settled" output (high when the filter is not moving).
    pub fn settled(&self) -> bool {
        self.settled.load(Ordering::Acquire)
    }

    /// The stream of "settled" edges; `None` after the first call. Events
    /// are kept until read, so take it only if you will drain it.
    pub fn take_settled_events(&mut self) -> Option<mpsc::Receiver<SettledEvent>> {
        self.events.take()
    }
}

impl Drop for EmulatorHandle {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Open a pty and serve the controller on it until the handle is dropped.
pub fn spawn_pty(config: EmuConfig) -> io::Result<EmulatorHandle> {
    let pty = nix::pty::openpty(None, None).map_err(io::Error::from)?;
    // Raw mode: the line discipline must neither echo nor translate CR, or
    // the client would see bytes the firmware never sent.
    let mut t = tcgetattr(pty.slave.as_fd()).map_err(io::Error::from)?;
    cfmakeraw(&mut t);
    tcsetattr(pty.slave.as_fd(), SetArg::TCSANOW, &t).map_err(io::Error::from)?;
    fcntl(pty.master.as_fd(), FcntlArg::F_SETFL(OFlag::O_NONBLOCK)).map_err(io::Error::from)?;
    let path = nix::unistd::ttyname(pty.slave.as_fd()).map_err(io::Error::from)?;

    let stop = Arc::new(AtomicBool::new(false));
    let settled = Arc::new(AtomicBool::new(true));
    let (control, control_rx) = mpsc::channel();
    let (events_tx, events) = mpsc::channel();
    let service = Service {
        master: pty.master,
        _slave: pty.slave,
        ctl: Controller::new(config.unit),
        config,
        rng: Prng::new(config.fault_seed),
        start: Instant::now(),
        pending: VecDeque::new(),
        next_tx: Instant::now(),
        stop: stop.clone(),
        settled: settled.clone(),
        control: control_rx,
        events: events_tx,
    };
    let thread = std::thread::Builder::new()
        .name("lctf-emu".into())
        .spawn(move || service.run())?;
    Ok(EmulatorHandle {
        path,
        stop,
        settled,
        control,
        events: Some(events),
        thread: Some(thread),
    })
}

struct Service {
    master: OwnedFd,
    // Held open so reads on the master never fail with EIO between clients.
    _slave: OwnedFd,
    ctl: Controller,
    config: EmuConfig,
    rng: Prng,
    start: Instant,
    /// Reply bytes with the wall time they may be sent.
    pending: VecDeque<(Instant, u8)>,
    next_tx: Instant,
    stop: Arc<AtomicBool>,
    settled: Arc<AtomicBool>,
    control: mpsc::Receiver<Control>,
    events: mpsc::Sender<SettledEvent>,
}

impl Service {
    fn run(mut self) {
        let mut buf = [0u8; READ_CHUNK];
        while !self.stop.load(Ordering::Acquire) {
            let mut fds = [PollFd::new(self.master.as_fd(), PollFlags::POLLIN)];
            let tick_ms = u8::try_from(TICK.as_millis()).unwrap_or(1).max(1);
            let readable = match poll(&mut fds, tick_ms) {
                Ok(n) => n > 0,
                Err(Errno::EINTR) => false,
                Err(_) => {
                    std::thread::sleep(TICK);
                    false
                }
            };
            if readable {
                match nix::unistd::read(self.master.as_fd(), &mut buf) {
                    Ok(n) => {
                        // Stamped after the read: the bytes were sent before
                        // it, so a host timing from its send never sees a
                        // settle shorter than the model's.
                        let t = self.device_now();
                        for &b in &buf[..n] {
                            self.receive(b, t);
                        }
                    }
                    Err(Errno::EAGAIN | Errno::EINTR) => {}
                    // EIO: no client has the slave open; keep serving.
                    Err(_) => std::thread::sleep(TICK),
                }
            }
            let now = self.device_now();
            while let Ok(c) = self.control.try_recv() {
                match c {
                    Control::Sync => self.ctl.sync_pulse(now),
                    Control::Temperature(t) => self.ctl.set_temperature(t),
                }
            }
            self.ctl.poll(now);
            while let Some(Event::Settled { at_us, centi_nm }) = self.ctl.pop_event() {
                let _ = self.events.send(SettledEvent {
                    wavelength_nm: f64::from(centi_nm) / 100.0,
                    device_us: at_us,
                    at: Instant::now(),
                });
            }
            self.settled.store(self.ctl.settled(), Ordering::Release);
            self.transmit();
        }
    }

    fn device_now(&self) -> u64 {
        self.config.time_scale.device_us(self.start.elapsed())
    }

    fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && (self.rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64 <= p
    }

    /// One byte from the client, through the fault model.
    fn receive(&mut self, b: u8, now: u64) {
        let f = self.config.faults;
        if self.chance(f.drop_prob) {
            return;
        }
        let b = if self.chance(f.garble_prob) {
            b ^ (1 << (self.rng.next_u64() % 7))
        } else {
            b
        };
        self.ctl.feed(b, now);
        if b == b'\r' && self.chance(f.spurious_error_prob) {
            const CODES: [ErrorCode; 4] = [
                ErrorCode::Syntax,
                ErrorCode::PaletteUndefined,
                ErrorCode::WavelengthRange,
                ErrorCode::JumpTooLarge,
            ];
            let e = CODES[(self.rng.next_u64() % CODES.len() as u64) as usize];
            self.ctl.inject_error(e);
        }
    }

    /// Move controller output through the fault model onto the pty.
    fn transmit(&mut self) {
        let f = self.config.faults;
        let release = Instant::now() + f.slow_reply;
        while let Some(b) = self.ctl.pop_output() {
            if self.chance(f.drop_prob) {
                continue;
            }
            let b = if self.chance(f.garble_prob) {
                b ^ (1 << (self.rng.next_u64() % 7))
            } else {
                b
            };
            self.pending.push_back((release, b));
        }
        let now = Instant::now();
        let byte_time = self
            .config
            .baud
            .filter(|&b| b > 0)
            .map(|b| Duration::from_secs_f64(10.0 / f64::from(b)));
        // Pacing: a byte may leave once the previous one has; no credit is
        // saved up beyond two ticks of idle line.
        let start = self.next_tx.max(now.checked_sub(TICK * 2).unwrap_or(now));
        let mut t = start;
        let mut out = Vec::new();
        for &(ready, b) in &self.pending {
            if ready > now || t > now {
                break;
            }
            if let Some(bt) = byte_time {
                t += bt;
            }
            out.push(b);
        }
        if out.is_empty() {
            return;
        }
        match nix::unistd::write(self.master.as_fd(), &out) {
            Ok(n) => {
                self.pending.drain(..n);
                if let Some(bt) = byte_time {
                    self.next_tx = start + bt * u32::try_from(n).unwrap_or(u32::MAX);
                }
            }
            Err(_) => std::thread::sleep(TICK),
        }
    }
}
