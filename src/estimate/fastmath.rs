//! Branch-free `sin`/`cos` for the solver's inner loops.
//!
//! The model evaluates one `sin_cos` per band per iteration, so the libm
//! call (with its slow paths for huge arguments) dominates a fit. Phases
//! here are bounded (|Δ| below ~10⁴ rad for any film the solver considers),
//! so a two-constant Cody–Waite reduction by π/2 and the fdlibm kernel
//! polynomials on [−π/4, π/4] give |error| ≤ 2e-16 with no branches the
//! compiler cannot turn into selects (so loops over bands vectorise).

const PIO2_HI: f64 = 1.570_796_326_734_125_6;
const PIO2_LO: f64 = 6.077_100_506_506_192e-11;
const FRAC_2_PI: f64 = std::f64::consts::FRAC_2_PI;

const S1: f64 = -1.666_666_666_666_663_2e-1;
const S2: f64 = 8.333_333_333_322_49e-3;
const S3: f64 = -1.984_126_982_985_795e-4;
const S4: f64 = 2.755_731_370_707_007e-6;
const S5: f64 = -2.505_076_025_340_686e-8;
const S6: f64 = 1.589_690_995_211_55e-10;

const C1: f64 = 4.166_666_666_666_66e-2;
const C2: f64 = -1.388_888_888_887_411e-3;
const C3: f64 = 2.480_158_728_947_673e-5;
const C4: f64 = -2.755_731_435_139_066e-7;
const C5: f64 = 2.087_572_321_298_175e-9;
const C6: f64 = -1.135_964_755_778_819_5e-11;

/// 1.5·2⁵²: adding and subtracting it rounds a double to the nearest
/// integer (ties to even) for |x| < 2⁵¹.
const SHIFT: f64 = 6_755_399_441_055_744.0;

/// Round to nearest for |x| < 2⁵¹ without a libm call (`f64::round` is one
/// on baseline x86-64); larger values are returned as they are.
#[inline(always)]
pub fn round(x: f64) -> f64 {
    if x.abs() < 2_251_799_813_685_248.0 {
        (x + SHIFT) - SHIFT
    } else {
        x
    }
}

/// `(sin x, cos x)` for |x| ≤ 1e5; larger or non-finite arguments fall back
/// to the standard library.
#[inline(always)]
pub fn sin_cos(x: f64) -> (f64, f64) {
    if x.is_nan() || x.abs() > 1e5 {
        return x.sin_cos();
    }
    sin_cos_bounded(x)
}

/// `(sin x, cos x)` without the range check: callers guarantee |x| ≤ 1e5
/// (beyond it the result degrades gracefully but is never NaN for finite x).
/// Branch-free, so loops over it vectorise.
#[inline(always)]
pub fn sin_cos_bounded(x: f64) -> (f64, f64) {
    let (r, q) = reduce_quadrant(x);
    let z = r * r;
    let s = r + r * z * (S1 + z * (S2 + z * (S3 + z * (S4 + z * (S5 + z * S6)))));
    let c = 1.0 - 0.5 * z + z * z * (C1 + z * (C2 + z * (C3 + z * (C4 + z * (C5 + z * C6)))));
    // Quadrant fix-up with bit operations only (swap on odd k, sign flips
    // by XOR), so it vectorises even without SSE4.1.
    let swap = 0u64.wrapping_sub(q & 1);
    let (sb, cb) = (s.to_bits(), c.to_bits());
    let sin_b = (cb & swap) | (sb & !swap);
    let cos_b = (sb & swap) | (cb & !swap);
    let sin = f64::from_bits(sin_b ^ ((q & 2) << 62));
    let cos = f64::from_bits(cos_b ^ ((q.wrapping_add(1) & 2) << 62));
    (sin, cos)
}

/// `x` reduced by the nearest multiple k of π/2 (|x| ≤ 1e5: a
/// two-constant Cody–Waite reduction), and bits whose lowest two hold
/// k mod 4. Branch-free.
#[inline(always)]
pub fn reduce_quadrant(x: f64) -> (f64, u64) {
    // Round to nearest by the 1.5·2⁵² trick (see [`round`]); the low
    // mantissa bits of `t` then hold k mod 4.
    let t = x * FRAC_2_PI + SHIFT;
    let k = t - SHIFT;
    ((x - k * PIO2_HI) - k * PIO2_LO, t.to_bits())
}

/// `(sin, cos)` in `f32` of `r` in [−π/4, π/4] (the Cephes minimax
/// polynomials, ~1 ulp), with the quadrant `q` (its lowest two bits k mod
/// 4) applied as [`sin_cos_bounded`] does: `x` = `r` + k·π/2 from
/// [`reduce_quadrant`]. Branch-free, so eight lanes vectorise.
#[inline(always)]
pub fn sin_cos_reduced_f32(r: f32, q: u32) -> (f32, f32) {
    let z = r * r;
    let s = r + r * z * (-1.666_665_5e-1 + z * (8.332_161e-3 + z * -1.951_529_6e-4));
    let c = 1.0 - 0.5 * z + z * z * (4.166_664_6e-2 + z * (-1.388_731_6e-3 + z * 2.443_315_7e-5));
    let swap = 0u32.wrapping_sub(q & 1);
    let (sb, cb) = (s.to_bits(), c.to_bits());
    let sin_b = (cb & swap) | (sb & !swap);
    let cos_b = (sb & swap) | (cb & !swap);
    let sin = f32::from_bits(sin_b ^ ((q & 2) << 30));
    let cos = f32::from_bits(cos_b ^ ((q.wrapping_add(1) & 2) << 30));
    (sin, cos)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn agrees_with_libm_over_the_solver_range() {
        let mut worst: f64 = 0.0;
        let mut x = -2000.0;
        while x < 2000.0 {
            let (s, c) = sin_cos(x);
            worst = worst.max((s - x.sin()).abs()).max((c - x.cos()).abs());
            x += 0.001_234_567;
        }
        // A few ulps of the reduction error k·|PIO2 − π/2| ~ 1e-19 · 1300.
        assert!(worst < 1e-14, "{worst}");
        // Exact-ish identities at the quadrant boundaries.
        let (s, c) = sin_cos(std::f64::consts::FRAC_PI_2);
        assert!((s - 1.0).abs() < 1e-16 && c.abs() < 1e-16);
        assert!(sin_cos(f64::NAN).0.is_nan());
    }
}
