//! Four-lane helpers shared by the χ² and interpolation kernels
//! (`noise.rs`, `solver/table/kernels.rs`): four bands at a time in
//! `wide::f64x4`, the tail band by band in lane 0 with the same arithmetic,
//! then the lanes summed pairwise. Every function is `inline(always)`, so
//! it is compiled with the calling kernel's vector unit (`multiversion`).

use wide::f64x4;

/// Four consecutive values (the first four of `v`).
#[inline(always)]
pub fn load(v: &[f64]) -> f64x4 {
    f64x4::new([v[0], v[1], v[2], v[3]])
}

/// Four consecutive f32 values widened to f64.
#[inline(always)]
pub fn widen(v: &[f32]) -> f64x4 {
    f64x4::new([v[0], v[1], v[2], v[3]].map(f64::from))
}

/// 1 in each lane whose weight is not 0, else 0 (the mask's bits select 1.0).
#[inline(always)]
pub fn used(w: f64x4) -> f64x4 {
    w.simd_ne(f64x4::ZERO) & f64x4::ONE
}

/// The vector loop's running sums of a weighted χ², four bands a step:
/// `Σ on·w·e²/σ²`, the variances of the bands used and how many.
#[derive(Clone, Copy)]
pub struct Chi2Lanes {
    chi2: f64x4,
    var: f64x4,
    used: f64x4,
}

impl Chi2Lanes {
    /// Nothing summed yet.
    #[inline(always)]
    pub fn new() -> Chi2Lanes {
        Chi2Lanes {
            chi2: f64x4::ZERO,
            var: f64x4::ZERO,
            used: f64x4::ZERO,
        }
    }

    /// Four bands: weights `w`, residuals `e`, variances `var` and their
    /// inverses `inv` (`on · w · e · e · inv`).
    #[inline(always)]
    pub fn add(&mut self, w: f64x4, e: f64x4, var: f64x4, inv: f64x4) {
        let on = used(w);
        self.chi2 += on * w * e * e * inv;
        self.var += on * var;
        self.used += on;
    }

    /// [`Self::add`] dividing by the variance (`on · w · e · e / var`).
    #[inline(always)]
    pub fn add_div(&mut self, w: f64x4, e: f64x4, var: f64x4) {
        let on = used(w);
        self.chi2 += on * w * e * e / var;
        self.var += on * var;
        self.used += on;
    }

    /// The lanes, for the tail's bands and the totals.
    #[inline(always)]
    pub fn sums(self) -> Chi2Sums {
        Chi2Sums {
            chi2: self.chi2.to_array(),
            var: self.var.to_array(),
            used: self.used.to_array(),
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
