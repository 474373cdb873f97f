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

/// The candidates of a whole image kept band-major as bit planes, so they
/// can be found incrementally as bands arrive (the live tracker) and
/// handed to the fast solver, which then skips its own [`detect`] pass.
///
/// For each row, chunk of [`CHUNK`] pixels and sorted band: a word of
/// candidate maxima and one of minima (bit `j`: pixel `x0 + j`); per row
/// and chunk a word of `bad` pixels. A candidate band's words are final
/// once its five samples (the smoothing's three neighbours either side,
/// clipped at the ends) have all arrived; [`CandidatePlanes::unpack`]
/// then gives exactly what [`detect`] gives on the same data.
#[derive(Clone, Debug)]
pub struct CandidatePlanes {
    width: usize,
    height: usize,
    bands: usize,
    chunks: usize,
    /// `[(row · chunks + chunk) · bands + band] · 2 + {0: max, 1: min}`.
    bits: Vec<u64>,
    /// `row · chunks + chunk`.
    bad: Vec<u64>,
    /// [`CandidatePlanes::set_candidate`]'s maxima then minima of a row as
    /// 0/1 bytes, padded to whole chunks (the padding stays 0).
    scratch: Vec<u8>,
}

impl CandidatePlanes {
    /// Planes for `width × height` pixels and `bands` sorted bands (at
    /// most [`MAX_DETECT_BANDS`]); `None` beyond that.
    pub fn new(width: usize, height: usize, bands: usize) -> Option<CandidatePlanes> {
        if !(3..=MAX_DETECT_BANDS).contains(&bands) {
            return None;
        }
        let chunks = width.div_ceil(CHUNK);
        Some(CandidatePlanes {
            width,
            height,
            bands,
            chunks,
            bits: vec![0; height * chunks * bands * 2],
            bad: vec![0; height * chunks],
            scratch: vec![0; 2 * chunks * CHUNK],
        })
    }

    /// Sorted bands.
    pub fn bands(&self) -> usize {
        self.bands
    }

    /// Image size.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Forget everything (a new sweep).
    pub fn clear(&mut self) {
        self.bits.fill(0);
        self.bad.fill(0);
    }

    /// The sorted bands whose samples decide candidate band `c`.
    pub fn window(&self, c: usize) -> std::ops::RangeInclusive<usize> {
        c.saturating_sub(2)..=(c + 2).min(self.bands - 1)
    }

    /// Fold row `y` of a band that arrived (`row`, `width` samples) into the
    /// row's bad pixels.
    pub fn add_row(&mut self, y: usize, row: &[f32]) {
        if y >= self.height {
            return;
        }
        let (vmin, vmax) = VALID_RANGE;
        for (k, px) in row.chunks(CHUNK).take(self.chunks).enumerate() {
            let mut bytes = [0u8; CHUNK];
            for (b, &v) in bytes.iter_mut().zip(px) {
                *b = u8::from(!((v >= vmin) & (v <= vmax)));
            }
            self.bad[y * self.chunks + k] |= pack64(&bytes);
        }
    }

    /// Decide candidate band `c` (1 ≤ c < bands − 1) of row `y` from
    /// `rows`, that row of sorted bands `window(c)` in order. Branch-free
    /// and vectorised over the row; no allocation (the scratch rows are
    /// the planes' own).
    pub fn set_candidate(&mut self, y: usize, c: usize, rows: &[&[f32]]) {
        let (nb, w) = (self.bands, self.width);
        let lo = c.saturating_sub(2);
        if c == 0 || c + 1 >= nb || y >= self.height || rows.len() != self.window(c).count() {
            return;
        }
        if rows.iter().any(|r| r.len() < w) {
            return;
        }
        // Raw row of sorted band b, reflected at the ends.
        let at = |b: isize| rows[(b.clamp(0, nb as isize - 1) as usize) - lo];
        let ci = c as isize;
        let cmp = &mut self.scratch;
        cmp.resize(2 * w.div_ceil(CHUNK) * CHUNK, 0);
        let (cmax, cmin) = cmp.split_at_mut(w.div_ceil(CHUNK) * CHUNK);
        let five = [at(ci - 2), at(ci - 1), at(ci), at(ci + 1), at(ci + 2)];
        compare_rows(five, &mut cmax[..w], &mut cmin[..w]);
        for k in 0..self.chunks {
            let i = ((y * self.chunks + k) * nb + c) * 2;
            self.bits[i] = pack64(&cmax[k * CHUNK..(k + 1) * CHUNK]);
            self.bits[i + 1] = pack64(&cmin[k * CHUNK..(k + 1) * CHUNK]);
        }
    }

    /// Chunk `k` of row `y` as per-pixel masks, as [`detect`] leaves them.
    pub fn unpack(&self, y: usize, k: usize, out: &mut Candidates) {
        out.maxima = [0; CHUNK];
        out.minima = [0; CHUNK];
        let base = (y * self.chunks + k) * self.bands;
        for r in 0..self.bands {
            for (kind, masks) in [&mut out.maxima, &mut out.minima].into_iter().enumerate() {
                let mut w = self.bits.get((base + r) * 2 + kind).copied().unwrap_or(0);
                while w != 0 {
                    let j = w.trailing_zeros() as usize;
                    w &= w - 1;
                    masks[j] |= 1 << r;
                }
            }
        }
        let bad = self
            .bad
            .get(y * self.chunks + k)
            .copied()
            .unwrap_or(u64::MAX);
        for (j, b) in out.bad.iter_mut().enumerate() {
            *b = bad >> j & 1 == 1;
        }
    }
}

/// Candidate maxima and minima of the middle of five rows (sorted bands
/// c − 2 … c + 2, ends already reflected) as 0/1 bytes: the three smoothed
/// values and their comparison in one pass.
#[multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1", "aarch64+neon"))]
fn compare_rows(rows: [&[f32]; 5], cmax: &mut [u8], cmin: &mut [u8]) {
    let n = cmax.len().min(cmin.len());
    let [r0, r1, r2, r3, r4] = rows.map(|r| &r[..n.min(r.len())]);
    let n = r0
        .len()
        .min(r1.len())
        .min(r2.len())
        .min(r3.len())
        .min(r4.len());
    for x in 0..n {
        let a = smooth3(r0[x], r1[x], r2[x]);
        let b = smooth3(r1[x], r2[x], r3[x]);
        let c = smooth3(r2[x], r3[x], r4[x]);
        cmax[x] = u8::from((b > a) & (b >= c));
        cmin[x] = u8::from((b < a) & (b <= c));
    }
}

/// 64 bytes of 0 or 1 (fewer: the rest 0) as the bits of a word, byte `j`
/// to bit `j`: eight bytes at a time by one multiplication that gathers
/// their low bits into the top byte.
#[inline]
fn pack64(bytes: &[u8]) -> u64 {
    let mut w = 0u64;
    for (k, ch) in bytes.chunks(8).take(8).enumerate() {
        let mut b = [0u8; 8];
        b[..ch.len()].copy_from_slice(ch);
        let byte = u64::from_le_bytes(b).wrapping_mul(0x0102_0408_1020_4080) >> 56;
        w |= byte << (8 * k);
    }
    w
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

    /// Planes filled band by band, in any order, unpack to what `detect`
    /// finds on the whole cube.
    #[test]
    fn planes_filled_in_any_order_match_detect() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (w, h) = (150, 3);
        for nb in [5usize, 31, 40] {
            let planes: Vec<Vec<f32>> = (0..nb)
                .map(|_| {
                    (0..w * h)
                        .map(|_| f32::from(rng.random_range(0u8..6)) * 0.01)
                        .collect()
                })
                .collect();
            let mut order: Vec<usize> = (0..nb).collect();
            for i in (1..nb).rev() {
                order.swap(i, rng.random_range(0..=i));
            }
            let mut cp = CandidatePlanes::new(w, h, nb).unwrap();
            let mut arrived = vec![false; nb];
            for &b in &order {
                arrived[b] = true;
                for y in 0..h {
                    cp.add_row(y, &planes[b][y * w..(y + 1) * w]);
                }
                for c in b.saturating_sub(2)..=(b + 2).min(nb - 1) {
                    if cp.window(c).all(|r| arrived[r]) {
                        for y in 0..h {
                            let rows: Vec<&[f32]> = cp
                                .window(c)
                                .map(|r| &planes[r][y * w..(y + 1) * w])
                                .collect();
                            cp.set_candidate(y, c, &rows);
                        }
                    }
                }
            }
            for y in 0..h {
                for k in 0..w.div_ceil(CHUNK) {
                    let x0 = k * CHUNK;
                    let m = (w - x0).min(CHUNK);
                    let rows: Vec<&[f32]> = planes
                        .iter()
                        .map(|p| &p[y * w + x0..y * w + x0 + m])
                        .collect();
                    let (mut a, mut b) = (Candidates::default(), Candidates::default());
                    detect(&rows, &mut a);
                    cp.unpack(y, k, &mut b);
                    assert_eq!(a.maxima[..m], b.maxima[..m], "nb {nb} row {y} chunk {k}");
                    assert_eq!(a.minima[..m], b.minima[..m], "nb {nb} row {y} chunk {k}");
                    assert_eq!(a.bad[..m], b.bad[..m], "nb {nb} row {y} chunk {k}");
                }
            }
        }
    }

    #[test]
    fn pack64_puts_byte_j_at_bit_j() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for len in [0usize, 1, 7, 8, 9, 63, 64] {
            let bytes: Vec<u8> = (0..len).map(|_| rng.random_range(0u8..2)).collect();
            let want = bytes
                .iter()
                .enumerate()
                .fold(0u64, |w, (j, &b)| w | u64::from(b) << j);
            assert_eq!(pack64(&bytes), want, "{bytes:?}");
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
