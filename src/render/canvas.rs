//! An RGB picture in memory, drawn on with `plotters` and written as PNG.
//!
//! The font is DejaVu Sans, compiled in (`assets/fonts/DejaVuSans.ttf`,
//! Bitstream Vera licence beside it) and registered with plotters' pure-Rust
//! `ab_glyph` renderer as "sans-serif", so no system font library is needed.

use super::RenderError;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;
use std::sync::Once;

static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");
static REGISTER: Once = Once::new();

/// The font family name every picture uses.
pub const FONT_FAMILY: &str = "sans-serif";

/// Largest picture side irid draws, pixels (bounds memory on any input).
pub const MAX_SIDE: usize = 8192;

pub(crate) fn register_font() {
    REGISTER.call_once(|| {
        // The bytes are a valid TrueType font compiled in; a failure would
        // only leave text undrawn, never corrupt a picture.
        let _ = plotters::style::register_font(FONT_FAMILY, FontStyle::Normal, FONT);
    });
}

/// An 8-bit sRGB picture, row-major, 3 bytes a pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// `width × height × 3` bytes.
    pub data: Vec<u8>,
}

impl RgbImage {
    /// A white picture. Sides are limited to [`MAX_SIDE`].
    pub fn new(width: usize, height: usize) -> Result<Self, RenderError> {
        if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
            return Err(RenderError::input(format!(
                "picture size {width} × {height} outside 1..={MAX_SIDE}"
            )));
        }
        Ok(RgbImage {
            width,
            height,
            data: vec![255; width * height * 3],
        })
    }

    /// The colour at `(x, y)`, if inside.
    pub fn get(&self, x: usize, y: usize) -> Option<[u8; 3]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = (y * self.width + x) * 3;
        Some([self.data[i], self.data[i + 1], self.data[i + 2]])
    }

    /// Set `(x, y)`; outside is ignored.
    pub fn put(&mut self, x: usize, y: usize, c: [u8; 3]) {
        if x < self.width && y < self.height {
            let i = (y * self.width + x) * 3;
            self.data[i..i + 3].copy_from_slice(&c);
        }
    }

    /// Fill a rectangle (clipped).
    pub fn fill(&mut self, x0: usize, y0: usize, w: usize, h: usize, c: [u8; 3]) {
        for y in y0..(y0 + h).min(self.height) {
            for x in x0..(x0 + w).min(self.width) {
                self.put(x, y, c);
            }
        }
    }

    /// Draw on the picture with plotters (text, lines, shapes).
    pub fn draw<F>(&mut self, f: F) -> Result<(), RenderError>
    where
        F: FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<(), String>,
    {
        register_font();
        let (w, h) = (self.width as u32, self.height as u32);
        let backend = BitMapBackend::with_buffer_and_format(&mut self.data, (w, h))
            .map_err(|e| RenderError::Draw(e.to_string()))?;
        let root = backend.into_drawing_area();
        f(&root).map_err(RenderError::Draw)?;
        root.present().map_err(|e| RenderError::Draw(e.to_string()))
    }

    /// PNG bytes (8-bit RGB).
    pub fn to_png(&self) -> Result<Vec<u8>, RenderError> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, self.width as u32, self.height as u32);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc
                .write_header()
                .map_err(|e| RenderError::Draw(format!("PNG: {e}")))?;
            w.write_image_data(&self.data)
                .map_err(|e| RenderError::Draw(format!("PNG: {e}")))?;
        }
        Ok(out)
    }

    /// Write as a PNG file, atomically (a temporary beside it, renamed).
    pub fn write_png(&self, path: &Path) -> Result<(), RenderError> {
        let bytes = self.to_png()?;
        write_atomic(path, &bytes)
    }
}

/// Write `bytes` to `path` through a temporary file in the same directory,
/// so a reader (the live view, a browser) never sees half a file
/// ([`crate::io::atomic`]: synced, and a device or pipe written in place).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), RenderError> {
    Ok(crate::io::atomic::write_bytes(
        path,
        crate::io::atomic::Overwrite::Replace,
        bytes,
    )?)
}

/// Decode a PNG (8-bit RGB or RGBA) back to an [`RgbImage`] (for tests and
/// the live view's checks).
pub fn decode_png(bytes: &[u8]) -> Result<RgbImage, RenderError> {
    let bad = |e: png::DecodingError| RenderError::input(format!("PNG: {e}"));
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes))
        .read_info()
        .map_err(bad)?;
    let size = dec
        .output_buffer_size()
        .ok_or_else(|| RenderError::input("PNG: too large"))?;
    let mut buf = vec![0; size];
    let info = dec.next_frame(&mut buf).map_err(bad)?;
    let (w, h) = (info.width as usize, info.height as usize);
    let step = match (info.color_type, info.bit_depth) {
        (png::ColorType::Rgb, png::BitDepth::Eight) => 3,
        (png::ColorType::Rgba, png::BitDepth::Eight) => 4,
        other => return Err(RenderError::input(format!("PNG: unsupported {other:?}"))),
    };
    let mut img = RgbImage::new(w, h)?;
    for y in 0..h {
        for x in 0..w {
            let i = y * info.line_size + x * step;
            img.put(x, y, [buf[i], buf[i + 1], buf[i + 2]]);
        }
    }
    Ok(img)
}

/// About `n` round tick values (1, 2 or 5 × 10^k apart) within `[lo, hi]`.
pub fn nice_ticks(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    if !(lo.is_finite() && hi.is_finite()) || hi <= lo || n == 0 {
        return vec![lo];
    }
    let raw = (hi - lo) / n as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let first = (lo / step).ceil() * step;
    (0..=2 * n + 2)
        .map(|i| first + i as f64 * step)
        .take_while(|t| *t <= hi + step * 1e-9)
        .collect()
}

/// A tick label: as few decimals as the step needs.
pub fn tick_label(v: f64, ticks: &[f64]) -> String {
    let step = if ticks.len() > 1 {
        (ticks[1] - ticks[0]).abs()
    } else {
        v.abs().max(1.0)
    };
    let decimals = if step >= 1.0 {
        0
    } else {
        (-step.log10()).ceil() as usize
    };
    format!("{v:.decimals$}")
}

/// A text style in the bundled font.
pub fn font(size: f64) -> TextStyle<'static> {
    (FONT_FAMILY, size).into_font().color(&BLACK)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_and_inside() {
        let t = nice_ticks(0.0, 1.0, 5);
        assert_eq!(t.len(), 6);
        assert!((t[1] - 0.2).abs() < 1e-12);
        let t = nice_ticks(137.0, 1493.0, 8); // raw step 169.5 → 200
        assert!(t.iter().all(|v| (137.0..=1493.0).contains(v)));
        assert!(t.windows(2).all(|w| (w[1] - w[0] - 200.0).abs() < 1e-9));
    }

    #[test]
    fn png_round_trip_keeps_pixels() {
        let mut img = RgbImage::new(7, 5).unwrap();
        img.put(3, 2, [1, 2, 3]);
        let back = decode_png(&img.to_png().unwrap()).unwrap();
        assert_eq!(back, img);
    }

    #[test]
    fn text_is_drawn_with_the_bundled_font() {
        let mut img = RgbImage::new(120, 40).unwrap();
        img.draw(|root| {
            root.draw(&Text::new("irid 123", (5, 10), font(16.0)))
                .map_err(|e| e.to_string())
        })
        .unwrap();
        let dark = img.data.chunks(3).filter(|p| p[0] < 128).count();
        assert!(dark > 30, "only {dark} dark pixels: no glyphs drawn");
    }

    #[test]
    fn oversized_pictures_are_refused() {
        assert!(RgbImage::new(MAX_SIDE + 1, 1).is_err());
        assert!(RgbImage::new(0, 1).is_err());
    }
}
