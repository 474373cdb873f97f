//! An in-memory spectral cube of reflectance, band-sequential.
//!
//! Band-sequential (one plane per band) is what a camera behind a tunable
//! filter produces, so the live pipeline fills planes without transposing;
//! the solver gathers one pixel's spectrum from the planes.

use crate::optics::band::Band;

/// Reflectance cube: `data[b * width * height + y * width + x]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Cube {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// The bands, in plane order (not necessarily sorted).
    pub bands: Vec<Band>,
    /// Reflectance values, band-sequential.
    pub data: Vec<f32>,
}

impl Cube {
    /// A cube of zeros.
    pub fn zeros(width: usize, height: usize, bands: Vec<Band>) -> Cube {
        let n = width * height * bands.len();
        Cube {
            width,
            height,
            bands,
            data: vec![0.0; n],
        }
    }

    /// Pixels per plane.
    pub fn plane_len(&self) -> usize {
        self.width * self.height
    }

    /// One band's plane.
    pub fn plane(&self, band: usize) -> &[f32] {
        let n = self.plane_len();
        &self.data[band * n..(band + 1) * n]
    }

    /// One band's plane, mutable.
    pub fn plane_mut(&mut self, band: usize) -> &mut [f32] {
        let n = self.plane_len();
        &mut self.data[band * n..(band + 1) * n]
    }

    /// Copy pixel (x, y)'s spectrum, in plane order, into `out`.
    pub fn spectrum_into(&self, x: usize, y: usize, out: &mut [f64]) {
        let n = self.plane_len();
        let i = y * self.width + x;
        if n == 0 || i >= n {
            return;
        }
        for (o, plane) in out.iter_mut().zip(self.data.chunks_exact(n)) {
            *o = f64::from(plane[i]);
        }
    }
}
