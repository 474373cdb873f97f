//! Material library (placeholder until the optics branch lands).
use super::dispersion::{Dispersion, OpticsError};
use std::path::Path;

/// A named material.
pub struct Material {
    /// Name.
    pub name: String,
    /// Its index.
    pub dispersion: Dispersion,
}

/// Resolves material names.
pub struct MaterialLibrary;

impl MaterialLibrary {
    /// The built-in library.
    pub fn builtin() -> Self {
        MaterialLibrary
    }
    /// Resolve a name or a path relative to `base`.
    pub fn resolve_relative(&self, name: &str, base: &Path) -> Result<Material, OpticsError> {
        let _ = base;
        Err(OpticsError::Invalid(format!("unknown material {name}")))
    }
}
