//! An in-memory spectral cube of reflectance, band-sequential.
//!
//! Band-sequential (one plane per band) is what a camera behind a tunable
//! filter produces, so the live pipeline fills planes without transposing;
//! the solver gathers one pixel's spectrum from the planes.
//!
//! A band value that calibration could not produce is NaN, and the NaN says
//! why: [`DARK_NAN`] (the pixel is flagged dark or dead in the calibration)
//! and [`SATURATED_NAN`] (the sample, or the white reference, saturated)
//! are quiet NaNs with their own payloads, which every f32 copy keeps
//! (copies move bits; only arithmetic may change a NaN's payload). Any other
//! NaN, or an infinity, is just a missing value. [`Cube::input_reason`]
//! reads the tags back for a pixel, so its map can say "dark" or
//! "saturated" rather than "non-finite input".

use super::maps::Reason;
use crate::optics::band::Band;

/// A band value calibration flagged as too dark to measure (white − dark
/// below the contrast floor, or no response): a quiet NaN, payload 0x0d00.
pub const DARK_NAN: f32 = f32::from_bits(0x7fc0_0d00);

/// A band value that saturated (the frame's sample or the white reference
/// at full scale): a quiet NaN, payload 0x5a00.
pub const SATURATED_NAN: f32 = f32::from_bits(0x7fc0_5a00);

/// The sign bit, which a negation may flip without touching the payload.
const SIGN: u32 = 0x8000_0000;

/// Why the band value `v` is missing: [`Reason::Dark`] or
/// [`Reason::Saturated`] for the tagged NaNs (of either sign), `None` for
/// any other value, a plain NaN included.
pub fn nan_reason(v: f32) -> Option<Reason> {
    let bits = v.to_bits() & !SIGN;
    if bits == SATURATED_NAN.to_bits() {
        Some(Reason::Saturated)
    } else if bits == DARK_NAN.to_bits() {
        Some(Reason::Dark)
    } else {
        None
    }
}

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

    /// The calibration tag on pixel (x, y)'s bands: [`Reason::Saturated`]
    /// if any band holds [`SATURATED_NAN`] (it wins over dark: more light
    /// would not help), else [`Reason::Dark`] if any holds [`DARK_NAN`],
    /// else `None` (also outside the cube).
    pub fn input_reason(&self, x: usize, y: usize) -> Option<Reason> {
        let n = self.plane_len();
        let i = y * self.width + x;
        if n == 0 || x >= self.width || i >= n {
            return None;
        }
        let mut found = None;
        for plane in self.data.chunks_exact(n) {
            match nan_reason(plane[i]) {
                Some(Reason::Saturated) => return Some(Reason::Saturated),
                Some(r) => found = Some(r),
                None => {}
            }
        }
        found
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tags_are_quiet_nans_with_distinct_payloads() {
        for t in [DARK_NAN, SATURATED_NAN] {
            assert!(t.is_nan());
            // Quiet bit set: arithmetic and copies never trap on them.
            assert_ne!(t.to_bits() & 0x0040_0000, 0);
        }
        assert_ne!(DARK_NAN.to_bits(), SATURATED_NAN.to_bits());
        assert_ne!(DARK_NAN.to_bits(), f32::NAN.to_bits());
        assert_eq!(nan_reason(DARK_NAN), Some(Reason::Dark));
        assert_eq!(nan_reason(SATURATED_NAN), Some(Reason::Saturated));
        assert_eq!(nan_reason(-SATURATED_NAN), Some(Reason::Saturated));
        for v in [f32::NAN, -f32::NAN, 0.0, 0.5, f32::INFINITY, f32::MAX] {
            assert_eq!(nan_reason(v), None, "{v}");
        }
    }

    #[test]
    fn copies_keep_the_payload() {
        let src = vec![0.25, DARK_NAN, SATURATED_NAN, f32::NAN];
        let copied = src.clone();
        let mut sliced = vec![0.0f32; 4];
        sliced.copy_from_slice(&src);
        let moved: Vec<f32> = vec![src[0], src[1], src[2], src[3]];
        let via_bytes: Vec<f32> = src
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        for v in [&copied, &sliced, &moved, &via_bytes] {
            let bits: Vec<u32> = v.iter().map(|x| x.to_bits()).collect();
            let want: Vec<u32> = src.iter().map(|x| x.to_bits()).collect();
            assert_eq!(bits, want);
        }
        assert_eq!(nan_reason(sliced[1]), Some(Reason::Dark));
        assert_eq!(nan_reason(moved[2]), Some(Reason::Saturated));
    }

    #[test]
    fn input_reason_scans_the_bands_and_saturated_wins() {
        let bands = (0..3)
            .map(|b| Band {
                center_nm: 500.0 + 10.0 * b as f64,
                fwhm_nm: 0.0,
            })
            .collect();
        let mut c = Cube::zeros(2, 2, bands);
        c.fill_pixel(0, 0, &[0.1, DARK_NAN, 0.2]);
        c.fill_pixel(1, 0, &[DARK_NAN, SATURATED_NAN, DARK_NAN]);
        c.fill_pixel(0, 1, &[f32::NAN, 0.3, f32::INFINITY]);
        c.fill_pixel(1, 1, &[0.1, 0.2, SATURATED_NAN]);
        assert_eq!(c.input_reason(0, 0), Some(Reason::Dark));
        assert_eq!(c.input_reason(1, 0), Some(Reason::Saturated));
        assert_eq!(c.input_reason(0, 1), None);
        assert_eq!(c.input_reason(1, 1), Some(Reason::Saturated));
        assert_eq!(c.input_reason(2, 0), None);
        assert_eq!(c.input_reason(0, 2), None);
    }

    impl Cube {
        fn fill_pixel(&mut self, x: usize, y: usize, v: &[f32]) {
            let i = y * self.width + x;
            for (b, &v) in v.iter().enumerate() {
                self.plane_mut(b)[i] = v;
            }
        }
    }
}
