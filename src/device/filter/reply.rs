//! Pure parser for the controller's replies (no I/O, no clock).
//!
//! Promise: every function here takes arbitrary bytes and returns a value or
//! a [`ReplyError`], never panics. Replies are accepted in both the normal
//! (`W 550.00`: letter, right-aligned value) and brief (`550.00`) formats,
//! so the driver works whatever `B` mode a previous client left behind.

use super::ControllerInfo;

/// Why a reply could not be understood.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ReplyError {
    /// The reply line is empty.
    #[error("empty reply")]
    Empty,
    /// Bytes outside printable ASCII.
    #[error("reply contains non-printable bytes")]
    NotPrintable,
    /// A normal-format reply carries another command's letter.
    #[error("reply is for command {got:?}, expected {expected:?}")]
    WrongLetter { expected: char, got: char },
    /// Wrong number of values.
    #[error("expected {expected} value(s), got {got}")]
    FieldCount { expected: usize, got: usize },
    /// A value is not a number.
    #[error("not a number: {0:?}")]
    BadNumber(String),
    /// An immediate command's answer did not start with its echo.
    #[error("immediate reply {got:?} does not start with the echo {expected:?}")]
    BadEcho { expected: char, got: Vec<u8> },
    /// The busy answer is neither `<` nor `>`.
    #[error("busy answer {0:?} is neither '<' nor '>'")]
    BadBusy(char),
    /// The status byte lacks the always-set 0x40 bit.
    #[error("status byte {0:#04x} lacks the always-set 0x40 bit")]
    BadStatus(u8),
}

/// The value fields of a query reply to command `letter`.
pub fn fields(line: &[u8], letter: u8) -> Result<Vec<&str>, ReplyError> {
    if !line.iter().all(|b| (0x20..0x7f).contains(b)) {
        return Err(ReplyError::NotPrintable);
    }
    // Printable ASCII is valid UTF-8.
    let text = std::str::from_utf8(line).map_err(|_| ReplyError::NotPrintable)?;
    let text = text.trim();
    let first = *text.as_bytes().first().ok_or(ReplyError::Empty)?;
    let body = if first.is_ascii_alphabetic() {
        if !first.eq_ignore_ascii_case(&letter) {
            return Err(ReplyError::WrongLetter {
                expected: char::from(letter),
                got: char::from(first),
            });
        }
        &text[1..]
    } else {
        text
    };
    Ok(body.split_ascii_whitespace().collect())
}

fn exactly(line: &[u8], letter: u8, n: usize) -> Result<Vec<&str>, ReplyError> {
    let f = fields(line, letter)?;
    if f.len() == n {
        Ok(f)
    } else {
        Err(ReplyError::FieldCount {
            expected: n,
            got: f.len(),
        })
    }
}

fn number(s: &str) -> Result<f64, ReplyError> {
    // `f64::from_str` also takes "inf"/"NaN"; a controller never sends those.
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && s.bytes().all(|b| b.is_ascii_digit() || b"+-.".contains(&b)) => {
            Ok(v)
        }
        _ => Err(ReplyError::BadNumber(s.to_owned())),
    }
}

/// One numeric value (`R?`, `P?`, `Y?`, ...).
pub fn value(line: &[u8], letter: u8) -> Result<f64, ReplyError> {
    number(exactly(line, letter, 1)?[0])
}

/// `W?`: the wavelength register in nm; `None` for `*` (no valid wavelength).
pub fn wavelength(line: &[u8]) -> Result<Option<f64>, ReplyError> {
    let f = exactly(line, b'W', 1)?;
    if f[0] == "*" {
        Ok(None)
    } else {
        number(f[0]).map(Some)
    }
}

/// `V?`: revision, range and serial number.
pub fn version(line: &[u8]) -> Result<ControllerInfo, ReplyError> {
    let f = exactly(line, b'V', 4)?;
    let serial = f[3]
        .parse::<u32>()
        .map_err(|_| ReplyError::BadNumber(f[3].to_owned()))?;
    Ok(ControllerInfo {
        revision: f[0].to_owned(),
        min_nm: number(f[1])?,
        max_nm: number(f[2])?,
        serial,
    })
}

/// Answer to the immediate `!`: echo then `<` (busy) or `>` (idle).
pub fn busy(answer: &[u8]) -> Result<bool, ReplyError> {
    match answer {
        [b'!', b'<'] => Ok(true),
        [b'!', b'>'] => Ok(false),
        [b'!', other] => Err(ReplyError::BadBusy(char::from(*other))),
        _ => Err(ReplyError::BadEcho {
            expected: '!',
            got: answer.to_vec(),
        }),
    }
}

/// Answer to the immediate `@`: echo then the status byte.
pub fn status_byte(answer: &[u8]) -> Result<u8, ReplyError> {
    match answer {
        [b'@', s] if s & 0x40 != 0 => Ok(*s),
        [b'@', s] => Err(ReplyError::BadStatus(*s)),
        _ => Err(ReplyError::BadEcho {
            expected: '@',
            got: answer.to_vec(),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn both_formats() {
        assert_eq!(wavelength(b"W 550.00"), Ok(Some(550.0)));
        assert_eq!(wavelength(b"550.25"), Ok(Some(550.25)));
        assert_eq!(wavelength(b"W      *"), Ok(None));
        assert_eq!(value(b"R     12", b'R'), Ok(12.0));
        assert_eq!(value(b"r 1", b'R'), Ok(1.0));
        let v = version(b"V   1.00    400    720  10001").unwrap();
        assert_eq!((v.min_nm, v.max_nm, v.serial), (400.0, 720.0, 10001));
        assert_eq!(version(b"1.00 400 720 10001").unwrap().revision, "1.00");
        assert!(matches!(
            wavelength(b"R 12"),
            Err(ReplyError::WrongLetter { .. })
        ));
        assert!(matches!(
            wavelength(b"W inf"),
            Err(ReplyError::BadNumber(_))
        ));
        assert_eq!(busy(b"!<"), Ok(true));
        assert_eq!(busy(b"!>"), Ok(false));
        assert_eq!(status_byte(b"@C"), Ok(0x43));
        assert!(status_byte(b"@\x03").is_err());
    }

    proptest! {
        #[test]
        fn random_bytes_give_errors_not_panics(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let _ = fields(&bytes, b'W');
            let _ = value(&bytes, b'R');
            let _ = wavelength(&bytes);
            let _ = version(&bytes);
            let _ = busy(&bytes);
            let _ = status_byte(&bytes);
        }

        #[test]
        fn printable_noise_is_parsed_or_rejected(s in "[ -~]{0,40}") {
            if let Ok(Some(w)) = wavelength(s.as_bytes()) {
                prop_assert!(w.is_finite());
            }
        }
    }
}
