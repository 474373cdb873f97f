//! Pictures: parameter maps rendered to PNG with a colour bar and a legend,
//! the film's colour (CIE 1931, D65, sRGB), and charts.
//!
//! - [`canvas`]: an RGB image, the bundled font, PNG encoding, and nice
//!   axis ticks.
//! - [`map`]: one channel of an irid map file as a perceptual (viridis)
//!   picture; invalid pixels coloured apart by reason, with a legend.
//! - [`colour`]: spectra to CIE XYZ and sRGB (pure numerics, tables
//!   compiled in from `data/cie/`).
//! - [`film_colour`]: a map's fitted parameters re-synthesised to spectra
//!   and rendered beside the measured cube; the colour-vs-thickness chart.
//! - `chart` (internal): what the benchmark charts share (Markdown tables read
//!   back, palette, mode markers, SVG or PNG output).
//! - [`trade`]: the speed/accuracy chart from the scene-matrix table.
//! - [`noise`]: the accuracy-against-noise chart from the noise-sweep
//!   table, whose rows it also prints.
//!
//! Text is drawn with DejaVu Sans compiled into the binary
//! (`assets/fonts/`), so rendering needs no system font library. Nothing
//! here panics on file contents: bad input is a [`RenderError`].

pub mod canvas;
mod chart;
pub mod colour;
pub mod film_colour;
pub mod map;
pub mod noise;
pub mod trade;

use std::path::PathBuf;

/// Errors of the picture layer.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// Reading an input file failed.
    #[error(transparent)]
    Io(#[from] crate::io::IoError),
    /// Writing the picture failed.
    #[error("{}: {message}", path.display())]
    Write {
        /// The output file.
        path: PathBuf,
        /// What went wrong (with its cause).
        message: String,
    },
    /// The input cannot be drawn (no such channel, nothing finite, a bad
    /// range, a malformed table).
    #[error("{0}")]
    Input(String),
    /// The drawing library failed.
    #[error("drawing: {0}")]
    Draw(String),
}

impl RenderError {
    pub(crate) fn input(message: impl Into<String>) -> Self {
        RenderError::Input(message.into())
    }
}
