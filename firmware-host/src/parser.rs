//! Command parser: one received line (without its carriage return) → [`Command`].
//!
//! Two stages, kept apart like smoltcp's wire layer: [`Line::new_checked`]
//! only proves that the bytes are a well-formed line (length, printable ASCII,
//! a command letter), and [`Command::parse`] turns a checked line into a typed
//! command. Neither stage allocates, and every byte sequence yields either a
//! command or an [`ErrorCode`] — never a panic.

use crate::ErrorCode;

/// Longest command line accepted, in bytes, without the terminator. Real
/// commands are at most ~20 bytes (`D 1100.00,127`); longer lines are syntax
/// errors.
pub const LINE_CAPACITY: usize = 32;

/// Number of palette entries (`D wl,idx` with idx 0–127).
pub const PALETTE_CAPACITY: usize = 128;

/// Largest numeric argument magnitude accepted, in hundredths. Keeps every
/// later arithmetic step far from overflow.
const MAX_CENTI: i64 = 100_000_000;

/// A line whose bytes have been checked: 1..=[`LINE_CAPACITY`] printable
/// ASCII bytes starting with a letter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Line<'a> {
    bytes: &'a [u8],
}

impl<'a> Line<'a> {
    /// Check `bytes` (a line without its terminator).
    pub fn new_checked(bytes: &'a [u8]) -> Result<Self, ErrorCode> {
        if bytes.is_empty() || bytes.len() > LINE_CAPACITY {
            return Err(ErrorCode::Syntax);
        }
        if !bytes.iter().all(|b| (0x20..0x7f).contains(b)) {
            return Err(ErrorCode::Syntax);
        }
        if !bytes[0].is_ascii_alphabetic() {
            return Err(ErrorCode::Syntax);
        }
        Ok(Self { bytes })
    }

    /// The command letter, upper-cased (irid's choice: letters are
    /// case-insensitive).
    pub fn letter(&self) -> u8 {
        self.bytes[0].to_ascii_uppercase()
    }

    /// The argument text after the letter, with surrounding spaces removed.
    pub fn arg(&self) -> &'a [u8] {
        trim(&self.bytes[1..])
    }

    /// The raw bytes of the line.
    pub fn as_bytes(&self) -> &'a [u8] {
        self.bytes
    }
}

/// Direction argument of `P` and `W`: an explicit value or a step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step<T> {
    /// Go to this value.
    To(T),
    /// `>`: one step forward.
    Next,
    /// `<`: one step back.
    Prev,
}

/// A parsed command. Wavelengths are in hundredths of a nanometre
/// ("centi-nm"), the controller's resolution.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// `X?`: query register `X` (the letter, upper-case).
    Query(u8),
    /// `A [serial]`: awaken.
    Awaken(Option<u32>),
    /// `B n`: reply mode 0 normal, 1 brief, 2 auto-confirm.
    Brief(u8),
    /// `C [1]`: clear the palette.
    ClearPalette,
    /// `D wl,idx`: define a palette entry.
    Define { centi_nm: u32, index: u8 },
    /// `E [n]`: exercise the liquid crystal n times (default 1).
    Exercise(u16),
    /// `G n`: advance on every n-th sync pulse, 0 = sync ignored.
    SyncDivider(u16),
    /// `I [1]`: initialise.
    Initialise,
    /// `J step`: jump step for `W>`/`W<` and mode 4, in centi-nm.
    Jump(i32),
    /// `M n`: sequence mode (0 palette cycle, 4 step by J).
    Mode(u8),
    /// `P idx|>|<`: select a palette entry.
    Palette(Step<u8>),
    /// `R [1]`: reset (clear) the pending error.
    ResetError,
    /// `S [serial]`: sleep.
    Sleep(Option<u32>),
    /// `W wl|>|<`: tune.
    Wavelength(Step<u32>),
    /// `X`: simulated trigger (one sync advance, ignoring the divider).
    Trigger,
}

impl Command {
    /// Parse a checked line.
    pub fn parse(line: &Line<'_>) -> Result<Self, ErrorCode> {
        let letter = line.letter();
        let arg = line.arg();
        if arg == b"?" {
            return match letter {
                b'B' | b'C' | b'D' | b'E' | b'G' | b'I' | b'J' | b'M' | b'P' | b'R' | b'S'
                | b'V' | b'W' | b'Y' => Ok(Command::Query(letter)),
                _ => Err(ErrorCode::Syntax),
            };
        }
        match letter {
            b'A' => Ok(Command::Awaken(opt_u32(arg)?)),
            b'B' => match parse_uint(arg)? {
                n @ 0..=2 => Ok(Command::Brief(n as u8)),
                _ => Err(ErrorCode::Syntax),
            },
            b'C' => one_or_empty(arg).map(|_| Command::ClearPalette),
            b'D' => {
                let comma = arg
                    .iter()
                    .position(|&b| b == b',')
                    .ok_or(ErrorCode::Syntax)?;
                let wl = parse_centi(trim(&arg[..comma]))?;
                let idx = parse_uint(trim(&arg[comma + 1..]))?;
                if wl <= 0 {
                    return Err(ErrorCode::WavelengthRange);
                }
                if idx >= PALETTE_CAPACITY as i64 {
                    return Err(ErrorCode::PaletteIndex);
                }
                Ok(Command::Define {
                    centi_nm: wl as u32,
                    index: idx as u8,
                })
            }
            b'E' => {
                if arg.is_empty() {
                    Ok(Command::Exercise(1))
                } else {
                    match parse_uint(arg)? {
                        n @ 1..=100 => Ok(Command::Exercise(n as u16)),
                        _ => Err(ErrorCode::Syntax),
                    }
                }
            }
            b'G' => match parse_uint(arg)? {
                n @ 0..=9999 => Ok(Command::SyncDivider(n as u16)),
                _ => Err(ErrorCode::Syntax),
            },
            b'I' => one_or_empty(arg).map(|_| Command::Initialise),
            b'J' => Ok(Command::Jump(parse_centi(arg)? as i32)),
            b'M' => match parse_uint(arg)? {
                n @ (0 | 4) => Ok(Command::Mode(n as u8)),
                _ => Err(ErrorCode::Syntax),
            },
            b'P' => match arg {
                b">" => Ok(Command::Palette(Step::Next)),
                b"<" => Ok(Command::Palette(Step::Prev)),
                _ => {
                    let idx = parse_uint(arg)?;
                    if idx >= PALETTE_CAPACITY as i64 {
                        Err(ErrorCode::PaletteIndex)
                    } else {
                        Ok(Command::Palette(Step::To(idx as u8)))
                    }
                }
            },
            b'R' => one_or_empty(arg).map(|_| Command::ResetError),
            b'S' => Ok(Command::Sleep(opt_u32(arg)?)),
            b'W' => match arg {
                b">" => Ok(Command::Wavelength(Step::Next)),
                b"<" => Ok(Command::Wavelength(Step::Prev)),
                _ => {
                    let wl = parse_centi(arg)?;
                    if wl <= 0 {
                        return Err(ErrorCode::WavelengthRange);
                    }
                    Ok(Command::Wavelength(Step::To(wl as u32)))
                }
            },
            b'X' => {
                if arg.is_empty() {
                    Ok(Command::Trigger)
                } else {
                    Err(ErrorCode::Syntax)
                }
            }
            _ => Err(ErrorCode::Syntax),
        }
    }
}

/// Parse a complete line: check, then parse.
pub fn parse_line(bytes: &[u8]) -> Result<Command, ErrorCode> {
    Command::parse(&Line::new_checked(bytes)?)
}

fn trim(mut s: &[u8]) -> &[u8] {
    while let [b' ', rest @ ..] = s {
        s = rest;
    }
    while let [rest @ .., b' '] = s {
        s = rest;
    }
    s
}

fn one_or_empty(arg: &[u8]) -> Result<(), ErrorCode> {
    if arg.is_empty() || arg == b"1" {
        Ok(())
    } else {
        Err(ErrorCode::Syntax)
    }
}

fn opt_u32(arg: &[u8]) -> Result<Option<u32>, ErrorCode> {
    if arg.is_empty() {
        Ok(None)
    } else {
        let v = parse_uint(arg)?;
        u32::try_from(v).map(Some).map_err(|_| ErrorCode::Syntax)
    }
}

/// Unsigned decimal integer, at most 9 digits.
fn parse_uint(s: &[u8]) -> Result<i64, ErrorCode> {
    if s.is_empty() || s.len() > 9 || !s.iter().all(u8::is_ascii_digit) {
        return Err(ErrorCode::Syntax);
    }
    Ok(s.iter()
        .fold(0i64, |acc, &d| acc * 10 + i64::from(d - b'0')))
}

/// Signed decimal with an optional fraction, in hundredths, rounded half up
/// on the third decimal (micro-manager sends three decimals).
pub fn parse_centi(s: &[u8]) -> Result<i64, ErrorCode> {
    let (neg, s) = match s {
        [b'-', rest @ ..] => (true, rest),
        [b'+', rest @ ..] => (false, rest),
        _ => (false, s),
    };
    let dot = s.iter().position(|&b| b == b'.');
    let (int, frac) = match dot {
        Some(i) => (&s[..i], &s[i + 1..]),
        None => (s, &s[s.len()..]),
    };
    if int.is_empty() && frac.is_empty() {
        return Err(ErrorCode::Syntax);
    }
    if int.len() > 9 || frac.len() > 9 {
        return Err(ErrorCode::Syntax);
    }
    if !int.iter().chain(frac.iter()).all(u8::is_ascii_digit) {
        return Err(ErrorCode::Syntax);
    }
    let whole = int.iter().fold(0i64, |a, &d| a * 10 + i64::from(d - b'0'));
    let digit = |i: usize| frac.get(i).map_or(0, |&d| i64::from(d - b'0'));
    let mut v = whole * 100 + digit(0) * 10 + digit(1);
    if digit(2) >= 5 {
        v += 1;
    }
    if v > MAX_CENTI {
        return Err(ErrorCode::Syntax);
    }
    Ok(if neg { -v } else { v })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_documented_forms() {
        assert_eq!(
            parse_line(b"W 550.00"),
            Ok(Command::Wavelength(Step::To(55000)))
        );
        assert_eq!(
            parse_line(b"W550.125"),
            Ok(Command::Wavelength(Step::To(55013)))
        );
        assert_eq!(parse_line(b"w>"), Ok(Command::Wavelength(Step::Next)));
        assert_eq!(parse_line(b"V ?"), Ok(Command::Query(b'V')));
        assert_eq!(parse_line(b"V?"), Ok(Command::Query(b'V')));
        assert_eq!(
            parse_line(b"D 550.5, 3"),
            Ok(Command::Define {
                centi_nm: 55050,
                index: 3
            })
        );
        assert_eq!(parse_line(b"D550,128"), Err(ErrorCode::PaletteIndex));
        assert_eq!(parse_line(b"P 127"), Ok(Command::Palette(Step::To(127))));
        assert_eq!(parse_line(b"P 128"), Err(ErrorCode::PaletteIndex));
        assert_eq!(parse_line(b"J -2.5"), Ok(Command::Jump(-250)));
        assert_eq!(parse_line(b"R1"), Ok(Command::ResetError));
        assert_eq!(parse_line(b"R 1"), Ok(Command::ResetError));
        assert_eq!(parse_line(b"I1"), Ok(Command::Initialise));
        assert_eq!(parse_line(b"A 12345"), Ok(Command::Awaken(Some(12345))));
        assert_eq!(parse_line(b"M 4"), Ok(Command::Mode(4)));
        assert_eq!(parse_line(b"B2"), Ok(Command::Brief(2)));
    }

    #[test]
    fn rejects_malformed_lines() {
        for bad in [
            &b""[..],
            b"?",
            b"1W",
            b"W",
            b"W abc",
            b"W 5.5.5",
            b"W .",
            b"Q 1",
            b"B 3",
            b"M 2",
            b"X 1",
            b"D 550",
            b"W 9999999999",
            b"W\x01",
            b"W 550.00 and then some more text...",
        ] {
            assert_eq!(parse_line(bad), Err(ErrorCode::Syntax), "{bad:?}");
        }
        assert_eq!(parse_line(b"W 0"), Err(ErrorCode::WavelengthRange));
        assert_eq!(parse_line(b"W -5"), Err(ErrorCode::WavelengthRange));
    }
}
