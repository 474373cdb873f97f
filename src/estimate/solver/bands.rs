//! Band layout: the bands sorted by wavelength, the band range in
//! wavenumber and its interior, and the least-squares parabola [`Window`]
//! around each band that the closed form locates extrema with.

use super::linalg::inv3;
use crate::optics::band::Band;

/// The band layout, worked out once per band set.
#[derive(Clone, Debug)]
pub(super) struct BandTable {
    /// Bands by increasing wavelength: (plane index, λ, wavenumber 1/λ).
    pub(super) sorted: Vec<(usize, f64, f64)>,
    /// Centre of the band range in wavenumber, nm⁻¹.
    pub(super) sigma_center: f64,
    /// The band range in wavenumber, nm⁻¹.
    pub(super) sigma_range: (f64, f64),
    /// That range less 1.5 band spacings at each end, where an extremum
    /// is always found if it exists.
    pub(super) interior: (f64, f64),
    /// The planes are already in increasing wavelength.
    pub(super) sorted_identity: bool,
    /// The least-squares parabola around each sorted band (`None` at the
    /// two end bands or if singular).
    pub(super) parabola: Vec<Option<Window>>,
}

impl BandTable {
    /// The layout of `bands` (cube plane order, at least 4 of them).
    pub(super) fn new(bands: &[Band]) -> BandTable {
        let sorted = {
            let mut v: Vec<(usize, f64, f64)> = bands
                .iter()
                .enumerate()
                .map(|(i, b)| (i, b.center_nm, 1.0 / b.center_nm))
                .collect();
            v.sort_by(|a, b| a.1.total_cmp(&b.1));
            v
        };
        let sorted_identity = sorted.iter().enumerate().all(|(i, b)| b.0 == i);
        let (s_lo, s_hi) = sorted.iter().fold((f64::INFINITY, 0.0f64), |(a, b), x| {
            (a.min(x.2), b.max(x.2))
        });
        let sigma_center = 0.5 * (s_lo + s_hi);
        let sigma_range = (s_lo, s_hi);
        let interior = {
            let sv: Vec<f64> = sorted.iter().map(|b| b.2).collect();
            let k = sv.len();
            // sorted by increasing wavelength: wavenumber decreasing.
            let (hi_step, lo_step) = (sv[0] - sv[1], sv[k - 2] - sv[k - 1]);
            (s_lo + 1.5 * lo_step, s_hi - 1.5 * hi_step)
        };
        let parabola = (0..sorted.len()).map(|i| Window::new(&sorted, i)).collect();
        BandTable {
            sorted,
            sigma_center,
            sigma_range,
            interior,
            sorted_identity,
            parabola,
        }
    }
}

/// The least-squares parabola `v = a u² + b u + c` (u: wavenumber offset
/// from the candidate band, in 1e-4 nm⁻¹ for conditioning) through the
/// samples around one sorted band: five samples inside the band range,
/// four (0–3 or the last four) at the second and second-to-last bands, so
/// an extremum next to either end of the range is still located.
#[derive(Clone, Copy, Debug)]
pub(super) struct Window {
    /// First sorted band of the window.
    pub(super) lo: usize,
    /// Samples in the window (4 or 5).
    pub(super) len: usize,
    /// Their wavenumber offsets (unused slots 0).
    pub(super) u: [f64; 5],
    /// Inverse normal matrix.
    pub(super) minv: [[f64; 3]; 3],
    /// The vertex must lie within this offset range.
    pub(super) vertex: (f64, f64),
    /// Mean sample spacing (offset units).
    pub(super) spacing: f64,
}

impl Window {
    fn new(sorted: &[(usize, f64, f64)], i: usize) -> Option<Window> {
        let nb = sorted.len();
        let (lo, len) = if i >= 2 && i + 2 < nb {
            (i - 2, 5)
        } else if i == 1 && nb >= 4 {
            (0, 4)
        } else if i + 2 == nb && nb >= 4 {
            (nb - 4, 4)
        } else {
            return None;
        };
        let x0 = sorted[i].2;
        let mut u = [0.0; 5];
        let mut m = [[0.0; 3]; 3];
        for k in 0..len {
            u[k] = (sorted[lo + k].2 - x0) * 1e4;
            let row = [u[k] * u[k], u[k], 1.0];
            for r in 0..3 {
                for c in 0..3 {
                    m[r][c] += row[r] * row[c];
                }
            }
        }
        let (u_min, u_max) = u[..len]
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        // The detection (on smoothed data) puts a real extremum within a
        // band of the candidate: the vertex may sit up to 1.5 band spacings
        // from it. A vertex further out is a flat noise parabola's, not an
        // extremum (and would win the merge of two of a kind by being
        // extrapolated). At an end, only within the samples.
        let vertex = if len == 5 {
            (1.5 * u[3], 1.5 * u[1])
        } else {
            (u_min, u_max)
        };
        Some(Window {
            lo,
            len,
            u,
            minv: inv3(m)?,
            vertex,
            spacing: (u_max - u_min) / (len - 1) as f64,
        })
    }
}
