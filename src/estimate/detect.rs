//! Fringe-extremum candidates of many pixels at once, band-major.
//!
//! A candidate is a local maximum or minimum of the spectrum smoothed by
//! `[1 2 1] / 4` along the bands in increasing wavelength (the end samples
//! reflected, so the second and second-to-last bands can hold one). The
//! smoothing only decides *where* to fit: the parabola fits that locate
//! the extremum use the raw samples.
//!
//! [`detect`] scans up to [`CHUNK`] pixels of one image row through every
//! band in one branch-free pass over contiguous band rows (vectorised,
//! with an AVX2 or NEON version chosen at run time), and leaves per pixel
//! two bit masks (bit `r`: sorted band `r` is a candidate maximum /
//! minimum) and a flag for samples outside the reflectance range the model
//! accepts. [`smooth`] is the same arithmetic for one pixel, so the
//! per-pixel path takes the same decisions.
#![forbid(unsafe_code)]

use multiversion::multiversion;

/// Pixels per [`detect`] call.
pub const CHUNK: usize = 64;

/// Most bands [`detect`] handles (bits of the masks).
pub const MAX_DETECT_BANDS: usize = 64;

/// Reflectance outside this range is outside the model (`bad`).
pub const VALID_RANGE: (f32, f32) = (-0.2, 1.2);

/// Candidates of one chunk of pixels.
#[derive(Clone, Debug)]
pub struct Candidates {
    /// Bit `r` of pixel `j`: sorted band `r` is a candidate maximum.
    pub maxima: [u64; CHUNK],
    /// Bit `r` of pixel `j`: sorted band `r` is a candidate minimum.
    pub minima: [u64; CHUNK],
    /// Pixel `j` has a sample that is NaN or outside [`VALID_RANGE`].
    pub bad: [bool; CHUNK],
}

impl Default for Candidates {
    fn default() -> Self {
        Candidates {
            maxima: [0; CHUNK],
            minima: [0; CHUNK],
            bad: [false; CHUNK],
        }
    }
}

/// `[1 2 1] / 4` of three neighbouring samples, in the f32 arithmetic of
/// [`detect`] (the per-pixel path uses it to take the same decisions).
#[inline(always)]
pub fn smooth3(a: f32, b: f32, c: f32) -> f32 {
    0.25 * a + 0.5 * b + 0.25 * c
}

/// Scan `rows` (one slice per band, by increasing wavelength, each the
/// same `m ≤ CHUNK` pixels) into `out`. Fewer than 3 or more than
/// [`MAX_DETECT_BANDS`] bands give no candidates (every pixel `bad`).
pub fn detect(rows: &[&[f32]], out: &mut Candidates) {
    let nb = rows.len();
    let m = rows.first().map_or(0, |r| r.len().min(CHUNK));
    if !(3..=MAX_DETECT_BANDS).contains(&nb) || rows.iter().any(|r| r.len() < m) {
        *out = Candidates::default();
        out.bad = [true; CHUNK];
        return;
    }
    let mut lo = [[0u32; CHUNK]; 2];
    let mut hi = [[0u32; CHUNK]; 2];
    let mut bad = [0u32; CHUNK];
    detect_impl(rows, m, &mut lo, &mut hi, &mut bad);
    for j in 0..CHUNK {
        out.maxima[j] = u64::from(lo[0][j]) | u64::from(hi[0][j]) << 32;
        out.minima[j] = u64::from(lo[1][j]) | u64::from(hi[1][j]) << 32;
        out.bad[j] = bad[j] != 0;
    }
}

/// The vectorised body: masks in 32-bit halves (bands 0–31 in `lo`, 32–63
/// in `hi`) so the lanes match the f32 samples.
#[multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1", "aarch64+neon"))]
fn detect_impl(
    rows: &[&[f32]],
    m: usize,
    lo: &mut [[u32; CHUNK]; 2],
    hi: &mut [[u32; CHUNK]; 2],
    bad: &mut [u32; CHUNK],
) {
    let nb = rows.len();
    let (vmin, vmax) = VALID_RANGE;
    for row in rows {
        for (b, &v) in bad[..m].iter_mut().zip(&row[..m]) {
            *b |= u32::from(!((v >= vmin) & (v <= vmax)));
        }
    }
    let (mut prev, mut cur, mut next) = ([0f32; CHUNK], [0f32; CHUNK], [0f32; CHUNK]);
    smooth_row(rows, 0, m, &mut prev);
    smooth_row(rows, 1, m, &mut cur);
    for r in 1..nb - 1 {
        smooth_row(rows, r + 1, m, &mut next);
        let (masks, shift) = if r < 32 {
            (&mut *lo, r as u32)
        } else {
            (&mut *hi, r as u32 - 32)
        };
        let [max, min] = masks;
        for ((((mx, mn), &a), &b), &c) in max[..m]
            .iter_mut()
            .zip(min[..m].iter_mut())
            .zip(&prev[..m])
            .zip(&cur[..m])
            .zip(&next[..m])
        {
            *mx |= u32::from((b > a) & (b >= c)) << shift;
            *mn |= u32::from((b < a) & (b <= c)) << shift;
        }
        std::mem::swap(&mut prev, &mut cur);
        std::mem::swap(&mut cur, &mut next);
    }
}

/// Smoothed band `r` of the chunk into `dst` (ends reflected); inlined
/// into each version of [`detect_impl`].
#[inline(always)]
fn smooth_row(rows: &[&[f32]], r: usize, m: usize, dst: &mut [f32; CHUNK]) {
    let nb = rows.len();
    let (ya, yb, yc) = (
        &rows[r.saturating_sub(1)][..m],
        &rows[r][..m],
        &rows[(r + 1).min(nb - 1)][..m],
    );
    for (((d, &a), &b), &c) in dst[..m].iter_mut().zip(ya).zip(yb).zip(yc) {
        *d = smooth3(a, b, c);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The masks are the per-pixel definition, bit for bit, for random
    /// spectra of every band count (including more than 32 bands), chunk
    /// widths below [`CHUNK`], and bad samples.
    #[test]
    fn masks_match_the_per_pixel_definition() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for nb in [3usize, 5, 7, 31, 33, 40, 64] {
            for m in [1usize, 17, 64] {
                let mut planes = vec![vec![0f32; m]; nb];
                for p in planes.iter_mut() {
                    for v in p.iter_mut() {
                        // Few distinct levels, so ties occur.
                        *v = f32::from(rng.random_range(0u8..6)) * 0.01;
                    }
                }
                planes[nb / 2][m / 2] = f32::NAN;
                planes[0][0] = 1.5;
                let rows: Vec<&[f32]> = planes.iter().map(|p| &p[..]).collect();
                let mut c = Candidates::default();
                detect(&rows, &mut c);
                for j in 0..m {
                    let ys: Vec<f32> = planes.iter().map(|p| p[j]).collect();
                    let smooth = |ys: &[f32], i: usize| {
                        smooth3(ys[i.saturating_sub(1)], ys[i], ys[(i + 1).min(nb - 1)])
                    };
                    let (mut mx, mut mn) = (0u64, 0u64);
                    for r in 1..nb - 1 {
                        let (a, b, d) = (smooth(&ys, r - 1), smooth(&ys, r), smooth(&ys, r + 1));
                        mx |= u64::from(b > a && b >= d) << r;
                        mn |= u64::from(b < a && b <= d) << r;
                    }
                    let bad = ys.iter().any(|v| !(-0.2..=1.2).contains(v));
                    assert_eq!(c.maxima[j], mx, "nb {nb} m {m} pixel {j}");
                    assert_eq!(c.minima[j], mn, "nb {nb} m {m} pixel {j}");
                    assert_eq!(c.bad[j], bad, "nb {nb} m {m} pixel {j}");
                }
            }
        }
    }

    #[test]
    fn a_clean_fringe_has_its_extrema_and_nothing_else() {
        // cos over 31 bands: maxima at 0, 10, 20, 30; minima at 5, 15, 25.
        let planes: Vec<Vec<f32>> = (0..31)
            .map(|r| vec![(0.05 + 0.03 * (std::f64::consts::PI * r as f64 / 5.0).cos()) as f32])
            .collect();
        let rows: Vec<&[f32]> = planes.iter().map(|p| &p[..]).collect();
        let mut c = Candidates::default();
        detect(&rows, &mut c);
        assert_eq!(c.maxima[0], 1 << 10 | 1 << 20);
        assert_eq!(c.minima[0], 1 << 5 | 1 << 15 | 1 << 25);
        assert!(!c.bad[0]);
    }

    #[test]
    fn unusable_band_counts_flag_every_pixel() {
        let p = [0.1f32; 4];
        let mut c = Candidates::default();
        detect(&[&p, &p], &mut c);
        assert!(c.bad.iter().all(|&b| b));
        let many: Vec<&[f32]> = (0..65).map(|_| &p[..]).collect();
        detect(&many, &mut c);
        assert!(c.bad.iter().all(|&b| b));
    }
}
