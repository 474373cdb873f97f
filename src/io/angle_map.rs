//! Per-pixel incidence-angle maps in degrees (for a scene's `[angle] map`
//! and `irid fit --theta-map`), from a single-band EXR or ENVI file.
//!
//! An EXR map is its channel named `theta_deg`, or its only channel. An
//! ENVI map must have exactly one band (its `reflectance scale factor`, if
//! any, is not applied: the values are degrees). NaN marks a pixel whose
//! angle is unknown; a finite value outside \[0°, 90°) is an error.

use super::{envi, exr_maps, IoError};
use std::path::Path;

/// Load a single-band angle map in degrees: `(width, height, row-major values)`.
pub fn load_degrees(path: &Path) -> Result<(usize, usize, Vec<f32>), IoError> {
    let is_exr = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    let (w, h, deg) = if is_exr {
        exr_maps::read_single(path, "theta_deg")?
    } else {
        let img = envi::read_image(path)?;
        if img.header.bands != 1 {
            return Err(IoError::field(
                &img.header_path,
                "bands",
                format!("an angle map has one band, not {}", img.header.bands),
            ));
        }
        (img.header.samples, img.header.lines, img.data)
    };
    if let Some(i) = deg
        .iter()
        .position(|d| d.is_finite() && !(0.0..90.0).contains(d))
    {
        return Err(IoError::format(
            path,
            format!(
                "angle {}° at pixel ({}, {}) is outside [0°, 90°)",
                deg[i],
                i % w.max(1),
                i / w.max(1)
            ),
        ));
    }
    Ok((w, h, deg))
}
