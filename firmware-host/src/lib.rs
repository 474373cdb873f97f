//! VariSpec-compatible liquid-crystal tunable filter (LCTF) controller firmware.
//!
//! The core ([`parser`], [`controller`], [`settle`], [`timing`]) is `no_std`,
//! allocation-free and panic-free on every input byte sequence: buffers are
//! `heapless` with named capacities, and time is always an argument (device
//! microseconds as `u64`), never read from a clock. It speaks the protocol
//! documented in `firmware-host/PROTOCOL.md`.
//!
//! With the `std` feature (default) the [`emu`] module runs the core on a
//! pseudo-terminal so hosts talk to it through a real serial line, byte for
//! byte; the `lctf-emu` binary wraps it.
#![cfg_attr(not(any(test, feature = "std")), no_std)]
#![forbid(unsafe_code)]

pub mod controller;
pub mod parser;
pub mod settle;
pub mod timing;

#[cfg(feature = "std")]
pub mod emu;

pub use controller::{Config, Controller, Event, ReplyMode};
pub use parser::{Command, Line};
pub use settle::SettleParams;
pub use timing::TimeScale;

/// Error codes the controller reports through `R?` (and the 0x20 status
/// bit). Processing continues with the error pending until `R 1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum ErrorCode {
    /// 1: the line is not a valid command (also: line too long, queue full).
    Syntax = 1,
    /// 4: the filter must be initialised (`I`) first.
    NotInitialised = 4,
    /// 9: no palette entry defined at the requested position.
    PaletteUndefined = 9,
    /// 11: palette index outside 0–127.
    PaletteIndex = 11,
    /// 12: wavelength outside the filter's range.
    WavelengthRange = 12,
    /// 14: jump step larger than the filter's range.
    JumpTooLarge = 14,
}

impl ErrorCode {
    /// The numeric code as sent by `R?`.
    pub const fn code(self) -> u8 {
        self as u8
    }

    /// The error for a numeric code, if it is one this firmware knows.
    pub const fn from_code(code: u8) -> Option<Self> {
        Some(match code {
            1 => Self::Syntax,
            4 => Self::NotInitialised,
            9 => Self::PaletteUndefined,
            11 => Self::PaletteIndex,
            12 => Self::WavelengthRange,
            14 => Self::JumpTooLarge,
            _ => return None,
        })
    }

    /// A short English description.
    pub const fn meaning(self) -> &'static str {
        match self {
            Self::Syntax => "syntax error",
            Self::NotInitialised => "not initialised",
            Self::PaletteUndefined => "palette undefined",
            Self::PaletteIndex => "palette index out of range",
            Self::WavelengthRange => "wavelength out of range",
            Self::JumpTooLarge => "jump too large",
        }
    }
}

impl core::fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "error {} ({})", self.code(), self.meaning())
    }
}
