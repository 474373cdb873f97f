//! How many quadrature nodes each band's passband takes: the fewest whose
//! model agrees with the 9-point one where they differ most.
//!
//! The 9-point Gauss–Hermite rule integrates a passband within 1.5e-5 of
//! the fringe for periods down to 1.33 FWHM (`optics::band`), but most
//! scenes need far less: 10 nm passbands on a film within a 31-band
//! camera's range are resolved by 5 nodes. Each node is one evaluation of
//! the film's reflectance per pixel and per fit step, so the node count
//! is the model's cost. No closed-form bound serves here: a film's
//! reflectance carries harmonics of its fringe (`k` times faster, of
//! relative size `|r12 r23|^{k−1}`) and a phase curved in wavelength, each
//! integrated worse than a pure fringe. So each rule of fewer nodes is
//! compared with the 9-point model on probes where the error peaks — a
//! fringe period at the thickest film, densely, and the range coarsely, at
//! the range's ends and middle in angle — and a band keeps the fewest nodes
//! within half the tolerance there (the other half spares what the probes
//! miss between them).

use super::super::model::{FilmModel, ModelOut};
use super::EstimateError;
use crate::optics::band::{N_NODES, RULES};

/// Probes over one fringe period at the thickest film (its error peaks
/// where the fringe is fastest and the passband widest against it).
const TOP_PROBES: usize = 48;
/// Probes over the whole thickness range.
const RANGE_PROBES: usize = 32;

/// Where to compare the models: thickness `d_range` (nm), angles
/// `theta_range` (rad), and the fringe's period in thickness at the
/// thickest film (nm).
pub(super) struct Probes {
    pub d_range: (f64, f64),
    pub theta_range: (f64, f64),
    pub period_nm: f64,
}

impl Probes {
    fn points(&self) -> Vec<(f64, f64)> {
        let (d0, d1) = self.d_range;
        let (t0, t1) = self.theta_range;
        let thetas: Vec<f64> = if t1 > t0 {
            vec![t0, 0.5 * (t0 + t1), t1]
        } else {
            vec![t0]
        };
        let top0 = (d1 - self.period_nm.max(0.0)).max(d0);
        let ds = (0..TOP_PROBES)
            .map(|i| top0 + (d1 - top0) * (i as f64 + 0.5) / TOP_PROBES as f64)
            .chain((0..=RANGE_PROBES).map(|i| d0 + (d1 - d0) * i as f64 / RANGE_PROBES as f64));
        ds.flat_map(|d| thetas.iter().map(move |&t| (d, t)))
            .filter(|&(d, t)| d.is_finite() && t.is_finite())
            .collect()
    }
}

/// The node count of each band: 1 where `integrated[k]` is false, else
/// the fewest of [`RULES`] whose model (built by `model_with`) stays within
/// `tolerance / 2` of `full` (every integrated band on 9 nodes) on the
/// probes, else 9.
pub(super) fn fewest_nodes(
    full: &FilmModel,
    integrated: &[bool],
    probes: &Probes,
    tolerance: f64,
    model_with: impl Fn(&[usize]) -> Result<FilmModel, EstimateError>,
) -> Result<Vec<usize>, EstimateError> {
    let nb = integrated.len();
    let mut nodes: Vec<usize> = integrated
        .iter()
        .map(|&i| if i { N_NODES } else { 1 })
        .collect();
    let points = probes.points();
    if points.is_empty() {
        return Ok(nodes);
    }
    let (mut want, mut got) = (ModelOut::new(nb), ModelOut::new(nb));
    let reference: Vec<Vec<f64>> = points
        .iter()
        .map(|&(d, t)| {
            full.eval(d, t, &mut want, false);
            want.r.clone()
        })
        .collect();
    // Bands still on 9 nodes, tried on the next rule up.
    let mut open: Vec<bool> = integrated.to_vec();
    for n in RULES.into_iter().filter(|&n| n < N_NODES) {
        if !open.iter().any(|&o| o) {
            break;
        }
        let trial: Vec<usize> = (0..nb).map(|k| if open[k] { n } else { 1 }).collect();
        let model = model_with(&trial)?;
        let mut worst = vec![0.0f64; nb];
        for (&(d, t), r) in points.iter().zip(&reference) {
            model.eval(d, t, &mut got, false);
            for k in (0..nb).filter(|&k| open[k]) {
                let e = (got.r[k] - r[k]).abs();
                // NaN (a probe the model cannot evaluate) keeps 9 nodes.
                worst[k] = if e.is_nan() {
                    f64::INFINITY
                } else {
                    worst[k].max(e)
                };
            }
        }
        for k in 0..nb {
            if open[k] && worst[k] <= 0.5 * tolerance {
                nodes[k] = n;
                open[k] = false;
            }
        }
    }
    Ok(nodes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::band::Band;
    use crate::optics::dispersion::Dispersion;
    use crate::optics::Polarization;

    fn film(bands: &[Band], n2: f64, n3: f64, nodes: &[usize]) -> FilmModel {
        FilmModel::with_nodes(
            bands,
            &Dispersion::constant(1.0),
            &Dispersion::constant(n2),
            &Dispersion::constant(n3),
            Polarization::Unpolarized,
            nodes,
        )
        .unwrap()
    }

    /// The fewest nodes agree with the 9-point model within the tolerance
    /// off the probes too (1 000 thicknesses and 7 angles between them),
    /// on a weak film (the paper's 1.37 on 1.6) and on one whose fringe
    /// carries strong harmonics (2.4 on 1.5, |r12 r23| ≈ 0.17), with 10 nm
    /// passbands; and they are fewer than 9 on most bands (the point of
    /// choosing), more on the blue bands, where the fringe runs fastest,
    /// than on the red.
    #[test]
    fn the_fewest_nodes_hold_the_tolerance_between_the_probes() {
        let bands: Vec<Band> = (0..31)
            .map(|k| Band::new(400.0 + 10.0 * k as f64, 10.0).unwrap())
            .collect();
        let tol = 1e-5;
        // The weak film takes at most 7 nodes a band on average; the strong
        // one more (its harmonics), but still fewer than 9 everywhere.
        for (n2, n3, d_max, most) in [(1.37, 1.6, 2400.0, 7), (2.4, 1.5, 1300.0, 8)] {
            let nine = vec![N_NODES; bands.len()];
            let full = film(&bands, n2, n3, &nine);
            let probes = Probes {
                d_range: (0.0, d_max),
                theta_range: (0.0, 60f64.to_radians()),
                period_nm: 400.0 / (2.0 * n2),
            };
            let nodes = fewest_nodes(&full, &vec![true; bands.len()], &probes, tol, |n| {
                Ok(film(&bands, n2, n3, n))
            })
            .unwrap();
            let total: usize = nodes.iter().sum();
            assert!(total <= most * bands.len(), "{n2}: {nodes:?}");
            assert!(nodes[0] >= nodes[30], "{n2}: {nodes:?}");
            let fewer = film(&bands, n2, n3, &nodes);
            let (mut a, mut b) = (ModelOut::new(31), ModelOut::new(31));
            let mut worst = 0.0f64;
            for i in 0..1000 {
                let d = d_max * (i as f64 + 0.37) / 1000.0;
                for j in 0..7 {
                    let t = (3.0 + 8.0 * j as f64).to_radians();
                    full.eval(d, t, &mut a, false);
                    fewer.eval(d, t, &mut b, false);
                    for k in 0..31 {
                        worst = worst.max((a.r[k] - b.r[k]).abs());
                    }
                }
            }
            assert!(worst <= tol, "{n2} on {n3}: {worst:.2e} with {nodes:?}");
        }
    }
}
