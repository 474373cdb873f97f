//! Spectra to colour: CIE 1931 XYZ under illuminant D65 with the 2°
//! standard observer, then sRGB (IEC 61966-2-1).
//!
//! The tables are compiled in from `data/cie/` (1 nm steps; sources and
//! checks in `data/cie/SOURCE.md`). A reflectance spectrum sampled at a few
//! band centres is interpolated linearly between them and held at its end
//! values beyond them, over 360–830 nm; XYZ is normalised so that a perfect
//! white (R = 1 everywhere) has Y = 1, and therefore renders as sRGB white.
//! Pure numerics: no I/O, no clock.

#![forbid(unsafe_code)]

use std::sync::OnceLock;

static CMF_CSV: &str = include_str!("../../data/cie/cie1931_2deg_cmf.csv");
static D65_CSV: &str = include_str!("../../data/cie/d65.csv");

/// First and last wavelength of the colour integral, nm (the observer's
/// table).
pub const LAMBDA_RANGE: (u32, u32) = (360, 830);

/// The CIE tables on a common 1 nm grid over [`LAMBDA_RANGE`]:
/// `S(λ)·x̄(λ)`, `S(λ)·ȳ(λ)`, `S(λ)·z̄(λ)`, divided by `Σ S(λ)·ȳ(λ)`.
#[derive(Debug)]
pub struct Cie {
    /// `(λ nm, [weights for X, Y, Z])`.
    pub weights: Vec<(f64, [f64; 3])>,
}

fn parse(csv: &str, cols: usize) -> Vec<(u32, Vec<f64>)> {
    csv.lines()
        .skip(1)
        .filter_map(|l| {
            let mut it = l.split(',').map(|v| v.trim().parse::<f64>());
            let lam = it.next()?.ok()?;
            let vals: Vec<f64> = it.take(cols).collect::<Result<_, _>>().ok()?;
            (vals.len() == cols).then_some((lam as u32, vals))
        })
        .collect()
}

/// The CIE 1931 2° observer as tabulated: `(λ nm, [x̄, ȳ, z̄])`, 1 nm.
pub fn observer() -> Vec<(f64, [f64; 3])> {
    parse(CMF_CSV, 3)
        .into_iter()
        .map(|(l, v)| (l as f64, [v[0], v[1], v[2]]))
        .collect()
}

impl Cie {
    /// The tables (parsed once).
    pub fn get() -> &'static Cie {
        static CIE: OnceLock<Cie> = OnceLock::new();
        CIE.get_or_init(|| {
            let cmf = parse(CMF_CSV, 3);
            let d65 = parse(D65_CSV, 1);
            let mut weights = Vec::new();
            for (lam, xyz) in &cmf {
                if let Some((_, s)) = d65.iter().find(|(l, _)| l == lam) {
                    let s = s[0];
                    weights.push((*lam as f64, [s * xyz[0], s * xyz[1], s * xyz[2]]));
                }
            }
            let norm: f64 = weights.iter().map(|(_, w)| w[1]).sum();
            for (_, w) in &mut weights {
                for v in w.iter_mut() {
                    *v /= norm;
                }
            }
            Cie { weights }
        })
    }

    /// XYZ of a reflectance spectrum given as `reflectance(λ nm)`.
    pub fn xyz_of(&self, reflectance: impl Fn(f64) -> f64) -> [f64; 3] {
        let mut xyz = [0.0; 3];
        for (lam, w) in &self.weights {
            let r = reflectance(*lam);
            for k in 0..3 {
                xyz[k] += r * w[k];
            }
        }
        xyz
    }

    /// XYZ of a spectrum sampled at `wavelengths_nm` (any order; NaN
    /// samples skipped), interpolated linearly and held at its ends.
    /// `None` when no sample is finite.
    pub fn xyz_of_samples(&self, wavelengths_nm: &[f64], r: &[f64]) -> Option<[f64; 3]> {
        let mut pts: Vec<(f64, f64)> = wavelengths_nm
            .iter()
            .zip(r)
            .filter(|(l, v)| l.is_finite() && v.is_finite())
            .map(|(l, v)| (*l, *v))
            .collect();
        if pts.is_empty() {
            return None;
        }
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        Some(self.xyz_of(|lam| interpolate(&pts, lam)))
    }
}

/// Linear interpolation in sorted `pts`, held at the ends.
pub fn interpolate(pts: &[(f64, f64)], x: f64) -> f64 {
    let i = pts.partition_point(|p| p.0 < x);
    if i == 0 {
        return pts[0].1;
    }
    if i >= pts.len() {
        return pts[pts.len() - 1].1;
    }
    let (a, b) = (pts[i - 1], pts[i]);
    if b.0 <= a.0 {
        return b.1;
    }
    a.1 + (b.1 - a.1) * (x - a.0) / (b.0 - a.0)
}

/// XYZ (Y = 1 for white) to linear sRGB (IEC 61966-2-1 matrix).
pub fn xyz_to_linear_srgb(xyz: [f64; 3]) -> [f64; 3] {
    let [x, y, z] = xyz;
    [
        3.2406 * x - 1.5372 * y - 0.4986 * z,
        -0.9689 * x + 1.8758 * y + 0.0415 * z,
        0.0557 * x - 0.2040 * y + 1.0570 * z,
    ]
}

/// The sRGB transfer function of a linear value, clipped to [0, 1].
pub fn srgb_encode(v: f64) -> f64 {
    let v = if v.is_finite() {
        v.clamp(0.0, 1.0)
    } else {
        0.0
    };
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// XYZ to 8-bit sRGB. `exposure` scales XYZ first (1: a perfect white is
/// 255, 255, 255; films reflect little, so pictures brighten them).
pub fn xyz_to_srgb8(xyz: [f64; 3], exposure: f64) -> [u8; 3] {
    let lin = xyz_to_linear_srgb(xyz.map(|v| v * exposure));
    lin.map(|v| (srgb_encode(v) * 255.0).round() as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tables_parse_completely() {
        let cie = Cie::get();
        assert_eq!(cie.weights.len(), 471, "360–830 nm at 1 nm");
        assert_eq!(cie.weights[0].0, 360.0);
    }

    #[test]
    fn interpolation_holds_the_ends() {
        let pts = [(400.0, 0.0), (500.0, 1.0)];
        assert_eq!(interpolate(&pts, 300.0), 0.0);
        assert_eq!(interpolate(&pts, 450.0), 0.5);
        assert_eq!(interpolate(&pts, 900.0), 1.0);
    }
}
