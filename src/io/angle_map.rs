//! Per-pixel incidence-angle maps (placeholder until the io branch lands).
use std::path::Path;

/// Load a single-band angle map in degrees: `(width, height, row-major values)`.
pub fn load_degrees(path: &Path) -> Result<(usize, usize, Vec<f32>), String> {
    Err(format!(
        "{}: angle maps are not supported yet",
        path.display()
    ))
}
