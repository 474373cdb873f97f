//! Per-pixel results as CSV: one row per spectrum (spectrum table) or pixel
//! (cube), in row-major pixel order.
//!
//! Columns ([`HEADER`]): `name,x,y,thickness_nm,sigma_thickness_nm,n_film,
//! theta_deg,sigma_theta_deg,residual_rms,valid,reason,reason_name`. `name`
//! is the spectrum's name, or `x{X}y{Y}` for a cube pixel; `x`, `y` are
//! 0-based; numbers are the maps' f32 values in shortest round-trip form,
//! `nan` where there is none (invalid pixels); `valid` is 1 or 0, `reason`
//! the code and `reason_name` its name (see [`Reason`]). Fields holding a
//! comma, a quote or a line break are quoted as RFC 4180 says.
//!
//! The file appears whole or not at all: it is written to
//! `OUT.tmp-<pid>` in the same directory, flushed to disk, then renamed
//! over `OUT`.
#![forbid(unsafe_code)]

use super::IoError;
use crate::estimate::{ParamMaps, Reason};
use std::io::Write;
use std::path::Path;

/// The header line.
pub const HEADER: &str = "name,x,y,thickness_nm,sigma_thickness_nm,n_film,theta_deg,sigma_theta_deg,residual_rms,valid,reason,reason_name";

/// A number as written: shortest round-trip, `nan` for NaN.
pub fn format_value(v: f32) -> String {
    if v.is_nan() {
        "nan".into()
    } else {
        v.to_string()
    }
}

/// A text field, quoted if it must be.
fn field(s: &str) -> std::borrow::Cow<'_, str> {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\"")).into()
    } else {
        s.into()
    }
}

/// Write `maps` as CSV to `path`, atomically. `names` gives one name per
/// pixel (row-major); without it pixels are named `x{X}y{Y}`.
pub fn write_results(
    path: &Path,
    maps: &ParamMaps,
    names: Option<&[String]>,
) -> Result<(), IoError> {
    write_atomically(path, |w| {
        writeln!(w, "{HEADER}")?;
        for y in 0..maps.height {
            for x in 0..maps.width {
                let i = y * maps.width + x;
                let name = match names.and_then(|n| n.get(i)) {
                    Some(n) => field(n).into_owned(),
                    None => format!("x{x}y{y}"),
                };
                let code = maps.reason[i];
                let reason_name = Reason::from_code(code as u8)
                    .filter(|_| code >= 0.0)
                    .map_or("unknown", Reason::name);
                writeln!(
                    w,
                    "{name},{x},{y},{},{},{},{},{},{},{},{},{}",
                    format_value(maps.thickness_nm[i]),
                    format_value(maps.sigma_thickness_nm[i]),
                    format_value(maps.n_film[i]),
                    format_value(maps.theta_deg[i]),
                    format_value(maps.sigma_theta_deg[i]),
                    format_value(maps.residual_rms[i]),
                    u8::from(maps.valid[i] > 0.5),
                    format_value(code),
                    field(reason_name),
                )?;
            }
        }
        Ok(())
    })
}

/// Write through `body` into a temporary file beside `path`, sync it, and
/// rename it to `path` (see [`super::atomic`]); on any failure `path` is
/// left as it was.
pub fn write_atomically(
    path: &Path,
    body: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<(), IoError> {
    super::atomic::write_atomically(path, super::atomic::Overwrite::Replace, |w| body(w))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_and_values() {
        assert_eq!(field("a b"), "a b");
        assert_eq!(field("a,b"), "\"a,b\"");
        assert_eq!(field("say \"hi\""), "\"say \"\"hi\"\"\"");
        assert_eq!(format_value(f32::NAN), "nan");
        assert_eq!(format_value(300.25), "300.25");
        assert_eq!(format_value(1.0), "1");
    }
}
