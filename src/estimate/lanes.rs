//! Four-lane helpers shared by the χ² and interpolation kernels
//! (`noise.rs`, `solver/judge.rs`, `solver/table/kernels.rs`): four bands
//! at a time in [`F64x4`], the tail band by band in lane 0 with the same
//! arithmetic, then the lanes summed pairwise. Every function is
//! `inline(always)`, so it is compiled with the calling kernel's vector
//! unit (`multiversion`).

use std::ops::{Add, AddAssign, Div, Mul, Sub};

/// Four `f64` lanes: a plain array whose every operation is written lane
/// by lane and `inline(always)`, so that inlined into a `multiversion`
/// kernel the vectoriser compiles it for that kernel's unit (one 256-bit
/// operation under AVX2 or AVX-512). `wide::F64x4`, used here before,
/// chooses its implementation when the crate is compiled: without a
/// global `-C target-feature=+avx` it is two 128-bit halves, and every
/// kernel built on it ran on `xmm` registers alone, in its AVX-512
/// version too (`objdump`: `interval_dots`, `interp_chi2`, `model_chi2`,
/// `flat_chi2`, `judged_sums`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(align(32))]
pub struct F64x4(pub [f64; 4]);

impl F64x4 {
    /// Every lane 0.
    pub const ZERO: F64x4 = F64x4([0.0; 4]);
    /// Every lane 1.
    pub const ONE: F64x4 = F64x4([1.0; 4]);

    /// `x` in every lane.
    #[inline(always)]
    pub fn splat(x: f64) -> F64x4 {
        F64x4([x; 4])
    }

    /// The lanes.
    #[inline(always)]
    pub fn to_array(self) -> [f64; 4] {
        self.0
    }

    /// The lanes of a loop's running sums, once the loop is done, behind
    /// an optimisation barrier. Summed across lanes in view of the loop,
    /// the vectoriser took the sums for a reduction and split every lane
    /// operation into 128-bit halves (rustc 1.95: `vaddpd xmm` pairs and
    /// shuffles); with the barrier it keeps each sum in one 256-bit
    /// register. The barrier costs a store and a load of the lanes per
    /// kernel call.
    #[inline(always)]
    pub fn lanes_done(self) -> [f64; 4] {
        std::hint::black_box(self.0)
    }

    /// Lane by lane the larger, `other`'s where a lane compares false
    /// (NaN): x86's `maxpd` order, so a NaN reflectance clamps to the
    /// floor as it did in `wide`.
    #[inline(always)]
    pub fn max(self, other: F64x4) -> F64x4 {
        let (a, b) = (self.0, other.0);
        F64x4(std::array::from_fn(
            |l| if a[l] > b[l] { a[l] } else { b[l] },
        ))
    }
}

macro_rules! lane_op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl $tr for F64x4 {
            type Output = F64x4;
            #[inline(always)]
            fn $f(self, o: F64x4) -> F64x4 {
                let (a, b) = (self.0, o.0);
                F64x4([a[0] $op b[0], a[1] $op b[1], a[2] $op b[2], a[3] $op b[3]])
            }
        }
    };
}
lane_op!(Add, add, +);
lane_op!(Sub, sub, -);
lane_op!(Mul, mul, *);
lane_op!(Div, div, /);

impl AddAssign for F64x4 {
    #[inline(always)]
    fn add_assign(&mut self, o: F64x4) {
        *self = *self + o;
    }
}

/// Four consecutive values (the first four of `v`).
#[inline(always)]
pub fn load(v: &[f64]) -> F64x4 {
    F64x4([v[0], v[1], v[2], v[3]])
}

/// Four consecutive f32 values widened to f64.
#[inline(always)]
pub fn widen(v: &[f32]) -> F64x4 {
    F64x4([v[0], v[1], v[2], v[3]].map(f64::from))
}

/// 1 in each lane whose weight is not 0, else 0.
#[inline(always)]
pub fn used(w: F64x4) -> F64x4 {
    let w = w.0;
    F64x4(std::array::from_fn(|l| if w[l] != 0.0 { 1.0 } else { 0.0 }))
}

/// The vector loop's running sums of a weighted χ², four bands a step:
/// `Σ on·w·e²/σ²`, the variances of the bands used and how many.
#[derive(Clone, Copy)]
pub struct Chi2Lanes {
    chi2: F64x4,
    var: F64x4,
    used: F64x4,
}

impl Chi2Lanes {
    /// Nothing summed yet.
    #[inline(always)]
    pub fn new() -> Chi2Lanes {
        Chi2Lanes {
            chi2: F64x4::ZERO,
            var: F64x4::ZERO,
            used: F64x4::ZERO,
        }
    }

    /// Four bands: weights `w`, residuals `e`, variances `var` and their
    /// inverses `inv` (`on · w · e · e · inv`).
    #[inline(always)]
    pub fn add(&mut self, w: F64x4, e: F64x4, var: F64x4, inv: F64x4) {
        let on = used(w);
        self.chi2 += on * w * e * e * inv;
        self.var += on * var;
        self.used += on;
    }

    /// [`Self::add`] dividing by the variance (`on · w · e · e / var`).
    #[inline(always)]
    pub fn add_div(&mut self, w: F64x4, e: F64x4, var: F64x4) {
        let on = used(w);
        self.chi2 += on * w * e * e / var;
        self.var += on * var;
        self.used += on;
    }

    /// The lanes, for the tail's bands and the totals.
    #[inline(always)]
    pub fn sums(self) -> Chi2Sums {
        Chi2Sums {
            chi2: self.chi2.lanes_done(),
            var: self.var.lanes_done(),
            used: self.used.lanes_done(),
        }
    }
}

/// The running sums of a weighted χ²: `Σ w e²/σ²`, the variances of the
/// bands used and how many were used, per lane.
#[derive(Clone, Copy)]
pub struct Chi2Sums {
    chi2: [f64; 4],
    var: [f64; 4],
    used: [f64; 4],
}

impl Chi2Sums {
    /// One band of the tail (lane 0): weight `w`, residual `e`, variance
    /// `var` and its inverse `inv` (`on · w · e · e · inv`, as the lanes).
    #[inline(always)]
    pub fn add(&mut self, w: f64, e: f64, var: f64, inv: f64) {
        let on = if w != 0.0 { 1.0 } else { 0.0 };
        self.chi2[0] += on * w * e * e * inv;
        self.var[0] += on * var;
        self.used[0] += on;
    }

    /// [`Self::add`] dividing by the variance (`on · w · e · e / var`).
    #[inline(always)]
    pub fn add_div(&mut self, w: f64, e: f64, var: f64) {
        let on = if w != 0.0 { 1.0 } else { 0.0 };
        self.chi2[0] += on * w * e * e / var;
        self.var[0] += on * var;
        self.used[0] += on;
    }

    /// χ² and the mean variance of the bands used (0 with none).
    #[inline(always)]
    pub fn totals(&self) -> (f64, f64) {
        let sum = |a: [f64; 4]| (a[0] + a[1]) + (a[2] + a[3]);
        let used = sum(self.used);
        let mean = if used > 0.0 {
            sum(self.var) / used
        } else {
            0.0
        };
        (sum(self.chi2), mean)
    }
}

#[cfg(test)]
mod tests {
    use super::{used, F64x4};

    /// Every lane operation is the scalar one, lane by lane, to the bit;
    /// `max` keeps x86's order (the second operand where a lane is NaN).
    #[test]
    fn lanes_compute_as_scalars() {
        let a = [0.3, -1.5, 2.0e-9, f64::NAN];
        let b = [0.7, 4.0, -3.0, 1.0];
        let (x, y) = (F64x4(a), F64x4(b));
        for l in 0..4 {
            let same = |v: f64, w: f64| v.to_bits() == w.to_bits();
            assert!(same((x + y).0[l], a[l] + b[l]));
            assert!(same((x - y).0[l], a[l] - b[l]));
            assert!(same((x * y).0[l], a[l] * b[l]));
            assert!(same((x / y).0[l], a[l] / b[l]));
        }
        assert_eq!(x.max(y).0[..3], [0.7, 4.0, 2.0e-9]);
        assert_eq!(x.max(y).0[3], 1.0);
        assert_eq!(F64x4([f64::NAN; 4]).max(F64x4::ZERO), F64x4::ZERO);
        let mut s = F64x4::splat(1.0);
        s += F64x4::ONE;
        assert_eq!(s.lanes_done(), [2.0; 4]);
        assert_eq!(
            used(F64x4([0.0, -0.0, 3.0, f64::NAN])).0,
            [0.0, 0.0, 1.0, 1.0]
        );
    }
}
