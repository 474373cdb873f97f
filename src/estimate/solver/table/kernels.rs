//! The tables' vector kernels: a fit's interval sums, the interpolant's
//! values and χ² (four f64 lanes, `wide::F64x4`: indexed lanes compiled to
//! scalar code), and the scan of every grid point (eight f32 lanes), each
//! compiled per vector unit (`multiversion`). The arithmetic is written so
//! that each lane repeats the scalar tail's, to the bit.

use super::SCAN_STRIDE;
use crate::estimate::lanes::{load, widen, Chi2Lanes, F64x4};
use crate::estimate::noise::{NoiseModel, SIGMA_FLOOR};
use multiversion::multiversion;

/// `[Σe², Σe·c1, Σe·c2, Σe·c3]` over the bands of one grid interval,
/// `e = y − centre − A` (see [`IntervalCubic`]): values `r` and slopes
/// `dr` at the interval's two ends. The `c`'s are linear in `B − A`, `P`
/// and `Q`, so so are their sums: per band only `e` and `B − A` are
/// formed and four products summed (`Σe²`, `Σe(B − A)`, `ΣeP`, `ΣeQ`),
/// the `c`'s sums follow once. Four independent lanes per sum (a single
/// f64 chain would not vectorise), the tail band by band.
#[allow(clippy::needless_range_loop)] // four lanes, indexed alike
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn interval_dots(
    r: [&[f32]; 2],
    dr: [&[f32]; 2],
    y: &[f64],
    centre: &[f64],
    h: f64,
) -> [f64; 4] {
    let nb = y.len();
    let (ra, rb, da, db, centre) = (
        &r[0][..nb],
        &r[1][..nb],
        &dr[0][..nb],
        &dr[1][..nb],
        &centre[..nb],
    );
    // Written out, not as a closure: a closure is not compiled with the
    // enclosing function's target features, and here it was called (not
    // inlined) once per band from the AVX2 version. Chunks of four zipped
    // (not indexed: the bounds checks of `k0 + l` kept the loop scalar).
    let (mut s0, mut s1, mut s2, mut s3) = (F64x4::ZERO, F64x4::ZERO, F64x4::ZERO, F64x4::ZERO);
    let quads = ra
        .chunks_exact(4)
        .zip(rb.chunks_exact(4))
        .zip(da.chunks_exact(4).zip(db.chunks_exact(4)))
        .zip(y.chunks_exact(4).zip(centre.chunks_exact(4)));
    for (((ra, rb), (da, db)), (y, centre)) in quads {
        let a = widen(ra);
        let e = load(y) - load(centre) - a;
        s0 += e * e;
        s1 += e * (widen(rb) - a);
        s2 += e * widen(da);
        s3 += e * widen(db);
    }
    let mut acc = [s0, s1, s2, s3].map(F64x4::lanes_done);
    for k in nb - nb % 4..nb {
        let a = f64::from(ra[k]);
        let e = y[k] - centre[k] - a;
        acc[0][0] += e * e;
        acc[1][0] += e * (f64::from(rb[k]) - a);
        acc[2][0] += e * f64::from(da[k]);
        acc[3][0] += e * f64::from(db[k]);
    }
    let [ee, ed, ep, eq] = acc.map(|s| (s[0] + s[1]) + (s[2] + s[3]));
    let (ep, eq) = (ep * h, eq * h);
    // IntervalCubic::coefficients, summed: c1 = P·h,
    // c2 = 3(B − A) − (2P + Q)·h, c3 = 2(A − B) + (P + Q)·h.
    [ee, ep, 3.0 * ed - 2.0 * ep - eq, -2.0 * ed + ep + eq]
}

/// [`ThicknessTable::values`]: `centre + h00·A + h10·P + h01·B + h11·Q`
/// per band, four bands at a time in `F64x4` lanes (the arithmetic of
/// [`interp_chi2`]).
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn interp_values(
    r: [&[f32]; 2],
    dr: [&[f32]; 2],
    centre: &[f64],
    [h00, h10, h01, h11]: [f64; 4],
    out: &mut [f64],
) {
    let n = centre.len().min(out.len());
    let (ra, rb, da, db) = (&r[0][..n], &r[1][..n], &dr[0][..n], &dr[1][..n]);
    let (centre, out) = (&centre[..n], &mut out[..n]);
    let g = [h00, h10, h01, h11].map(F64x4::splat);
    for (q, out) in end_quads([ra, rb, da, db], centre).zip(out.chunks_exact_mut(4)) {
        out.copy_from_slice(&hermite_quad(q, g).to_array());
    }
    let tail = n - n % 4;
    for (k, o) in out.iter_mut().enumerate().skip(tail) {
        *o = hermite_at([ra, rb, da, db], centre, [h00, h10, h01, h11], k);
    }
}

/// [`ThicknessTable::chi2_flat`]: per band the interpolant's value
/// `centre + h00·A + h10·P + h01·B + h11·Q` and `flat_chi2`'s sums over
/// it, in the same four lanes.
#[allow(clippy::needless_range_loop, clippy::too_many_arguments)] // four lanes, indexed alike
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn interp_chi2(
    r: [&[f32]; 2],
    dr: [&[f32]; 2],
    centre: &[f64],
    [h00, h10, h01, h11]: [f64; 4],
    y: &[f64],
    w: &[f64],
    var: &[f64],
    inv: &[f64],
) -> (f64, f64) {
    let n = centre
        .len()
        .min(y.len())
        .min(w.len())
        .min(var.len())
        .min(inv.len());
    let (ra, rb, da, db) = (&r[0][..n], &r[1][..n], &dr[0][..n], &dr[1][..n]);
    let (centre, y, w, var, inv) = (&centre[..n], &y[..n], &w[..n], &var[..n], &inv[..n]);
    // Four bands at a time in `F64x4` lanes (see `interval_dots`), the
    // tail band by band, with the same arithmetic.
    let mut lanes = Chi2Lanes::new();
    let g = [h00, h10, h01, h11].map(F64x4::splat);
    let quads = end_quads([ra, rb, da, db], centre)
        .zip(y.chunks_exact(4))
        .zip(
            w.chunks_exact(4)
                .zip(var.chunks_exact(4))
                .zip(inv.chunks_exact(4)),
        );
    for ((q, y), ((w, var), inv)) in quads {
        let rk = hermite_quad(q, g);
        lanes.add(load(w), load(y) - rk, load(var), load(inv));
    }
    let mut sums = lanes.sums();
    for k in n - n % 4..n {
        let rk = hermite_at([ra, rb, da, db], centre, [h00, h10, h01, h11], k);
        sums.add(w[k], y[k] - rk, var[k], inv[k]);
    }
    sums.totals()
}

/// [`ThicknessTable::chi2_model`]: per band the interpolant's value and
/// its χ² term under the reflectance-dependent noise (the variance at
/// that value, as `noise::band_var` forms it), eight bands a step in
/// `f32` lanes: the values never leave the registers, and an `f32`
/// division costs a third of an `f64` one per lane (this pass had taken
/// 15 % of a live pixel's time; 8 % since).
///
/// Precision: the residual `y − R` is formed in `f32` from values of
/// order 1, so it carries ~1e-8 of absolute rounding against a noise σ of
/// at least `SIGMA_FLOOR` = 1e-4: χ² to ~1e-4 relative at that floor and
/// ~1e-5 at a camera's 1e-3, against the ±25 % that χ² itself scatters
/// by over 31 bands — a test decision moves only for a pixel within that
/// sliver of its threshold. The sums are `f64` across the lanes.
#[allow(clippy::needless_range_loop, clippy::too_many_arguments)] // eight lanes, indexed alike
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn interp_model_chi2(
    r: [&[f32]; 2],
    dr: [&[f32]; 2],
    centre: &[f64],
    hm: [f64; 4],
    y: &[f64],
    w: &[f64],
    noise: &NoiseModel,
) -> (f64, f64) {
    let (var0, shot) = (&noise.var0[..], &noise.shot[..]);
    let n = centre
        .len()
        .min(y.len())
        .min(w.len())
        .min(var0.len())
        .min(shot.len())
        .min(r[0].len())
        .min(r[1].len())
        .min(dr[0].len())
        .min(dr[1].len());
    let [h00, h10, h01, h11] = hm.map(|h| h as f32);
    let rel2 = noise.rel2 as f32;
    let floor = (SIGMA_FLOOR * SIGMA_FLOOR) as f32;
    let mut acc = Lanes8::default();
    let whole = n - n % 8;
    let mut k0 = 0;
    while k0 < whole {
        let b = Chunk8 {
            ra: eight(&r[0][k0..]),
            rb: eight(&r[1][k0..]),
            da: eight(&dr[0][k0..]),
            db: eight(&dr[1][k0..]),
            centre: eight(&centre[k0..]).map(|v| v as f32),
            y: eight(&y[k0..]).map(|v| v as f32),
            w: eight(&w[k0..]).map(|v| v as f32),
            var0: eight(&var0[k0..]).map(|v| v as f32),
            shot: eight(&shot[k0..]).map(|v| v as f32),
        };
        acc.add(&b, [h00, h10, h01, h11], rel2, floor);
        k0 += 8;
    }
    if whole < n {
        // The rest padded into one more chunk (a padded band weighs 0 and
        // its variance is 1: it adds nothing).
        let mut b = Chunk8::PADDING;
        for (l, k) in (whole..n).enumerate() {
            b.ra[l] = r[0][k];
            b.rb[l] = r[1][k];
            b.da[l] = dr[0][k];
            b.db[l] = dr[1][k];
            b.centre[l] = centre[k] as f32;
            b.y[l] = y[k] as f32;
            b.w[l] = w[k] as f32;
            b.var0[l] = var0[k] as f32;
            b.shot[l] = shot[k] as f32;
        }
        acc.add(&b, [h00, h10, h01, h11], rel2, floor);
    }
    acc.totals()
}

/// Eight bands' inputs of [`interp_model_chi2`] in `f32` (fixed-size
/// arrays: the lane loop carries no bounds checks and vectorises).
#[derive(Clone, Copy)]
struct Chunk8 {
    ra: [f32; 8],
    rb: [f32; 8],
    da: [f32; 8],
    db: [f32; 8],
    centre: [f32; 8],
    y: [f32; 8],
    w: [f32; 8],
    var0: [f32; 8],
    shot: [f32; 8],
}

impl Chunk8 {
    /// Bands that add nothing: weight 0, variance 1.
    const PADDING: Chunk8 = Chunk8 {
        ra: [0.0; 8],
        rb: [0.0; 8],
        da: [0.0; 8],
        db: [0.0; 8],
        centre: [0.0; 8],
        y: [0.0; 8],
        w: [0.0; 8],
        var0: [1.0; 8],
        shot: [0.0; 8],
    };
}

/// Eight lanes of χ², variance and count sums.
#[derive(Default)]
struct Lanes8 {
    chi2: [f32; 8],
    var: [f32; 8],
    used: [f32; 8],
}

/// The first eight values of `v` (which holds at least eight).
#[inline(always)]
fn eight<T: Copy + Default>(v: &[T]) -> [T; 8] {
    let mut out = [T::default(); 8];
    out.copy_from_slice(&v[..8]);
    out
}

impl Lanes8 {
    /// One chunk's terms: the interpolant's value (Hermite weights `h`),
    /// its variance, and `on · w · e² / var` into each lane.
    #[inline(always)]
    fn add(&mut self, b: &Chunk8, [h00, h10, h01, h11]: [f32; 4], rel2: f32, floor: f32) {
        for l in 0..8 {
            let rv = b.centre[l] + h00 * b.ra[l] + h10 * b.da[l] + h01 * b.rb[l] + h11 * b.db[l];
            let rp = rv.max(0.0);
            let var = (b.var0[l] + b.shot[l] * rp + rel2 * rp * rp).max(floor);
            let e = b.y[l] - rv;
            let on = if b.w[l] != 0.0 { 1.0 } else { 0.0 };
            self.chi2[l] += on * b.w[l] * e * e / var;
            self.var[l] += on * var;
            self.used[l] += on;
        }
    }

    /// χ² and the mean variance of the bands used (0 with none), summed
    /// across the lanes in `f64`.
    fn totals(&self) -> (f64, f64) {
        let sum = |a: &[f32; 8]| a.iter().map(|&v| f64::from(v)).sum::<f64>();
        let used = sum(&self.used);
        let mean = if used > 0.0 {
            sum(&self.var) / used
        } else {
            0.0
        };
        (sum(&self.chi2), mean)
    }
}

/// Four bands of a grid interval's ends and the bands' centres: `A`,
/// `B` (values), `P`, `Q` (slopes) and `centre`, a chunk each.
type EndQuad<'a> = ([&'a [f32]; 4], &'a [f64]);

/// The interval's ends ([`EndQuad`]) four bands a step (no closure: a
/// closure is not compiled with the calling kernel's target features).
#[inline(always)]
fn end_quads<'a>(
    [ra, rb, da, db]: [&'a [f32]; 4],
    centre: &'a [f64],
) -> impl Iterator<Item = EndQuad<'a>> {
    ra.chunks_exact(4)
        .zip(rb.chunks_exact(4))
        .zip(da.chunks_exact(4).zip(db.chunks_exact(4)))
        .zip(centre.chunks_exact(4))
        .map(quad)
}

/// [`end_quads`]' item from the zipped chunks (a plain function, so it is
/// inlined into the kernel's target features like the rest).
#[inline(always)]
#[allow(clippy::type_complexity)]
fn quad<'a>(
    (((ra, rb), (da, db)), centre): (((&'a [f32], &'a [f32]), (&'a [f32], &'a [f32])), &'a [f64]),
) -> EndQuad<'a> {
    ([ra, rb, da, db], centre)
}

/// Four bands' values of the interpolant, `centre + h00·A + h10·P +
/// h01·B + h11·Q` (the tail's arithmetic, [`hermite_at`]), with the
/// Hermite weights `g = [h00, h10, h01, h11]` in every lane.
#[inline(always)]
fn hermite_quad(
    ([ra, rb, da, db], centre): EndQuad<'_>,
    [g00, g10, g01, g11]: [F64x4; 4],
) -> F64x4 {
    load(centre) + g00 * widen(ra) + g10 * widen(da) + g01 * widen(rb) + g11 * widen(db)
}

/// One band's value of the interpolant, `centre + h00·A + h10·P + h01·B +
/// h11·Q` (the lanes' arithmetic), from the ends' values `A`, `B` and
/// slopes `P`, `Q`.
#[inline(always)]
fn hermite_at(
    [ra, rb, da, db]: [&[f32]; 4],
    centre: &[f64],
    [h00, h10, h01, h11]: [f64; 4],
    k: usize,
) -> f64 {
    let (a, b, p, q) = (
        f64::from(ra[k]),
        f64::from(rb[k]),
        f64::from(da[k]),
        f64::from(db[k]),
    );
    centre[k] + h00 * a + h10 * p + h01 * b + h11 * q
}

/// The residual at every scanned grid point of a complete spectrum,
/// `Σy² − 2 y·R + ΣR²`, eight grid points per vector: the table's scanned
/// rows are transposed in blocks of eight ([`ThicknessTable::coarse`]),
/// so each band is one broadcast multiply–add into eight sums and no sum
/// is reduced across lanes; four blocks a pass share each band's
/// broadcast and keep four independent chains of fused multiply–adds
/// (one block with separate multiplies and adds, as before, scanned the
/// thick hard coat's 731-point table in ~1 µs; fused and grouped, its
/// angle-known `fast` runs 1.1–1.2× faster). f32 keeps 1e-7 of `Σy²`, far
/// below a residual of `nb σ²` at any usable noise level.
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn scan_blocked(coarse: &[f32], rr: &[f32], y: &[f32], yy: f32, sse: &mut [f32]) {
    // A fused multiply–add where the vector unit has one (Rust never
    // contracts `a * b + c` itself; without FMA `mul_add` would be a
    // library call).
    if multiversion::target::target_cfg_f!(target_feature = "fma") {
        scan_blocks::<true>(coarse, rr, y, yy, sse);
    } else {
        scan_blocks::<false>(coarse, rr, y, yy, sse);
    }
}

/// `a · b + c`, fused where `FMA`.
#[inline(always)]
fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// Blocks scanned together: each band's `y` is loaded once for all of
/// them, and their sums are independent chains (the multiply–adds of one
/// block's sum wait on each other).
const SCAN_GROUP: usize = 4;

/// [`scan_blocked`]'s loops (inlined into each of its vector units):
/// [`SCAN_GROUP`] blocks a pass over the bands, then the rest one by one
/// with four partial sums.
#[allow(clippy::needless_range_loop)] // eight lanes, indexed alike
#[inline(always)]
fn scan_blocks<const FMA: bool>(coarse: &[f32], rr: &[f32], y: &[f32], yy: f32, sse: &mut [f32]) {
    let nb = y.len();
    let blocks = (sse.len() / 8)
        .min(rr.len() / 8)
        .min(coarse.len() / (nb * 8).max(1));
    let finish = |dot: [f32; 8], rr: &[f32], out: &mut [f32]| {
        for l in 0..8 {
            out[l] = yy - 2.0 * dot[l] + rr[l];
        }
    };
    let mut b = 0;
    while b + SCAN_GROUP <= blocks {
        let group = &coarse[b * nb * 8..(b + SCAN_GROUP) * nb * 8];
        let mut acc = [[0f32; 8]; SCAN_GROUP];
        for (k, &yk) in y.iter().enumerate() {
            for (i, a) in acc.iter_mut().enumerate() {
                let row = &group[(i * nb + k) * 8..(i * nb + k) * 8 + 8];
                for l in 0..8 {
                    a[l] = madd::<FMA>(yk, row[l], a[l]);
                }
            }
        }
        for (i, a) in acc.iter().enumerate() {
            let at = (b + i) * 8;
            finish(*a, &rr[at..at + 8], &mut sse[at..at + 8]);
        }
        b += SCAN_GROUP;
    }
    let whole = nb - nb % 4;
    for b in b..blocks {
        let blk = &coarse[b * nb * 8..(b + 1) * nb * 8];
        let mut acc = [[0f32; 8]; 4];
        for k0 in (0..whole).step_by(4) {
            for (p, a) in acc.iter_mut().enumerate() {
                let k = k0 + p;
                let row = &blk[k * 8..k * 8 + 8];
                for l in 0..8 {
                    a[l] = madd::<FMA>(y[k], row[l], a[l]);
                }
            }
        }
        for k in whole..nb {
            let row = &blk[k * 8..k * 8 + 8];
            for l in 0..8 {
                acc[0][l] = madd::<FMA>(y[k], row[l], acc[0][l]);
            }
        }
        let mut dot = [0f32; 8];
        for l in 0..8 {
            dot[l] = (acc[0][l] + acc[1][l]) + (acc[2][l] + acc[3][l]);
        }
        finish(dot, &rr[b * 8..b * 8 + 8], &mut sse[b * 8..b * 8 + 8]);
    }
}

/// Each point's ranking key: the lowest value of the parabola through it
/// and its neighbours where it is a local minimum (`≤` its left, `<` its
/// right; the ends compare with +∞), +∞ elsewhere and at NaN.
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn minimum_keys(sse: &[f32], keys: &mut [f32]) {
    let n = sse.len();
    // Branch-free (selects only), so the loop vectorises; the same
    // arithmetic as `parabola_min`.
    let key = |l: f32, c: f32, r: f32| {
        let a = 0.5 * (l + r) - c;
        let b = 0.5 * (r - l);
        let v = (c - b * b / (4.0 * a)).max(0.0);
        let pm = if a > 0.0 && a < f32::INFINITY { v } else { c };
        if c <= l && c < r {
            pm
        } else {
            f32::INFINITY
        }
    };
    if n == 0 {
        return;
    }
    if n == 1 {
        keys[0] = key(f32::INFINITY, sse[0], f32::INFINITY);
        return;
    }
    keys[0] = key(f32::INFINITY, sse[0], sse[1]);
    for (k, w) in keys[1..n - 1].iter_mut().zip(sse.windows(3)) {
        *k = key(w[0], w[1], w[2]);
    }
    keys[n - 1] = key(sse[n - 2], sse[n - 1], f32::INFINITY);
}

/// `Σ w (y − R)²` at every grid point (spectra with missing bands).
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn scan_weighted(r: &[f32], y: &[f32], w: &[f32], sse: &mut [f32]) {
    let nbp = y.len();
    for (row, out) in r.chunks_exact(nbp).step_by(SCAN_STRIDE).zip(sse.iter_mut()) {
        let mut acc = [0f32; 8];
        for ((rv, yv), wv) in row
            .chunks_exact(8)
            .zip(y.chunks_exact(8))
            .zip(w.chunks_exact(8))
        {
            for i in 0..8 {
                let e = yv[i] - rv[i];
                acc[i] += wv[i] * e * e;
            }
        }
        *out = acc.iter().sum();
    }
}
