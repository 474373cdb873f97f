//! Files: ENVI spectral cubes, OpenEXR parameter maps, angle maps.
//!
//! - [`envi`]: ENVI cubes (`.hdr` + raw binary) in and out, and the
//!   dark/white calibration of raw counts to reflectance.
//! - [`exr_maps`]: parameter maps, synthetic truth and angle maps as f32
//!   OpenEXR channels with text attributes.
//! - [`angle_map`]: a per-pixel incidence-angle map in degrees from a
//!   single-band EXR or ENVI file.
//! - [`spectrum_table`]: spectrometer files and single spectra (CSV or
//!   whitespace-separated text, one column per spectrum) as a one-row cube.
//! - [`results_csv`]: per-pixel (per-spectrum) results as CSV.
//! - [`atomic`]: how every file is written (temporary name, sync, rename;
//!   an existing output kept unless replacing it was asked for).
//!
//! Promise: malformed, inconsistent or truncated files give an [`IoError`]
//! that names the file and, for headers, the field (for text tables, the
//! line). Nothing in this layer
//! panics on file contents.

pub mod angle_map;
pub mod atomic;
pub mod envi;
pub mod exr_maps;
pub mod results_csv;
pub mod spectrum_table;

use std::path::{Path, PathBuf};

/// Errors of the file layer. Every variant names the file it is about.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The operating system refused to read or write the file.
    #[error("{}: {source}", path.display())]
    Os {
        /// The file.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// A header field is missing, malformed or inconsistent.
    #[error("{}: field `{field}`: {message}", path.display())]
    Field {
        /// The header file.
        path: PathBuf,
        /// The (lower-case) field name.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// The file as a whole is unusable (not the expected format, too short,
    /// missing channels).
    #[error("{}: {message}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A line of a text file (spectrum table) is malformed.
    #[error("{}: line {line}: {message}", path.display())]
    Line {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// Two files that must agree (cube and reference, cube and angle map) do not.
    #[error("{} and {}: {message}", a.display(), b.display())]
    Mismatch {
        /// First file.
        a: PathBuf,
        /// Second file.
        b: PathBuf,
        /// What differs.
        message: String,
    },
}

impl IoError {
    pub(crate) fn os(path: &Path, source: std::io::Error) -> Self {
        IoError::Os {
            path: path.to_path_buf(),
            source,
        }
    }

    pub(crate) fn field(path: &Path, field: &str, message: impl Into<String>) -> Self {
        IoError::Field {
            path: path.to_path_buf(),
            field: field.to_string(),
            message: message.into(),
        }
    }

    pub(crate) fn line(path: &Path, line: usize, message: impl Into<String>) -> Self {
        IoError::Line {
            path: path.to_path_buf(),
            line,
            message: message.into(),
        }
    }

    pub(crate) fn format(path: &Path, message: impl Into<String>) -> Self {
        IoError::Format {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}
