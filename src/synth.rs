//! Synthetic spectral data from a scene's ground truth: the fixture
//! generator of the tests, the renderer behind the synthetic camera and
//! `irid synth`.
//!
//! Rendering is deterministic: the same scene and seed give the same bits.
//! Noise-free planes can be rendered once per band and reused (the synthetic
//! camera does), so generation never limits a benchmark of what consumes it.

use crate::estimate::Cube;
use crate::optics::airy;
use crate::optics::band::Band;
use crate::optics::dispersion::OpticsError;
use crate::optics::Media;
use crate::scene::{Scene, Truth};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

/// Errors of synthesis.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// The scene has no `[truth]` section.
    #[error("the scene has no [truth] section to render")]
    NoTruth,
    /// The scene has no `[bands]` and none were given.
    #[error("the scene has no [bands] section and no bands were given")]
    NoBands,
    /// A medium cannot be evaluated at a band.
    #[error("{medium} at {wavelength_nm} nm: {source}")]
    Optics {
        /// Which medium.
        medium: &'static str,
        /// Where.
        wavelength_nm: f64,
        /// Cause.
        source: OpticsError,
    },
}

/// The true per-pixel parameters of a synthetic scene.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthMaps {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// Thickness, nm, row-major.
    pub thickness_nm: Vec<f32>,
    /// Angle, degrees, row-major.
    pub theta_deg: Vec<f32>,
    /// Film index at the middle band.
    pub n_film: f64,
}

/// Renders noise-free reflectance planes of a scene's truth.
#[derive(Clone, Debug)]
pub struct Renderer {
    scene: Scene,
    truth: Truth,
}

impl Renderer {
    /// A renderer for `scene`, which must have a `[truth]` section.
    pub fn new(scene: &Scene) -> Result<Renderer, SynthError> {
        let truth = scene.truth.clone().ok_or(SynthError::NoTruth)?;
        Ok(Renderer {
            scene: scene.clone(),
            truth,
        })
    }

    /// Image width.
    pub fn width(&self) -> usize {
        self.truth.width
    }

    /// Image height.
    pub fn height(&self) -> usize {
        self.truth.height
    }

    /// The truth's noise σ and seed.
    pub fn noise(&self) -> (f64, u64) {
        (self.truth.noise_sigma, self.truth.seed)
    }

    /// The true parameter maps.
    pub fn truth_maps(&self, bands: &[Band]) -> TruthMaps {
        let (w, h) = (self.truth.width, self.truth.height);
        let mut thickness_nm = Vec::with_capacity(w * h);
        let mut theta_deg = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                thickness_nm.push(self.truth.thickness_nm.at(x, y, w, h) as f32);
                theta_deg.push(self.truth.angle_deg.at(x, y, w, h) as f32);
            }
        }
        let mid = bands
            .get(bands.len() / 2)
            .map(|b| b.center_nm)
            .unwrap_or(550.0);
        let n_film = self
            .truth
            .film
            .index_at(mid)
            .map(|n| n.re)
            .unwrap_or(f64::NAN);
        TruthMaps {
            width: w,
            height: h,
            thickness_nm,
            theta_deg,
            n_film,
        }
    }

    fn media_at(&self, wavelength_nm: f64, center_nm: f64) -> Result<Media, SynthError> {
        let get = |d: &crate::optics::dispersion::Dispersion, medium| {
            d.index_in_passband(wavelength_nm, center_nm)
                .map_err(|source| SynthError::Optics {
                    medium,
                    wavelength_nm,
                    source,
                })
        };
        Ok(Media {
            n1: get(&self.scene.ambient, "ambient")?,
            n2: get(&self.truth.film, "film")?,
            n3: get(&self.scene.substrate, "substrate")?,
        })
    }

    /// Render the noise-free reflectance plane of one band into `out`
    /// (row-major, `width × height`). The passband is integrated when the
    /// band has a width.
    pub fn render_band(&self, band: &Band, out: &mut [f32]) -> Result<(), SynthError> {
        use rayon::prelude::*;
        let (w, h) = (self.truth.width, self.truth.height);
        // The media at the band's quadrature nodes, once per band (the same
        // nodes `Band::integrate` uses), not per pixel.
        let points: Vec<(f64, f64)> = if band.fwhm_nm > 0.0 {
            band.nodes().to_vec()
        } else {
            vec![(band.center_nm, 1.0)]
        };
        let mut nodes = Vec::with_capacity(points.len());
        for (lam, wgt) in points {
            nodes.push((lam, wgt, self.media_at(lam, band.center_nm)?));
        }
        let pol = self.scene.polarization;
        out[..w * h]
            .par_chunks_mut(w.max(1))
            .enumerate()
            .for_each(|(y, row)| {
                for (x, o) in row.iter_mut().enumerate() {
                    let d = self.truth.thickness_nm.at(x, y, w, h).max(0.0);
                    let th = self.truth.angle_deg.at(x, y, w, h).to_radians();
                    let r: f64 = nodes
                        .iter()
                        .map(|&(lam, wgt, m)| wgt * airy::reflectance(m, d, th, lam, pol))
                        .sum();
                    *o = r as f32;
                }
            });
        Ok(())
    }

    /// Render a whole noisy cube (noise σ and seed from the truth).
    pub fn render_cube(&self, bands: &[Band]) -> Result<Cube, SynthError> {
        let mut cube = Cube::zeros(self.truth.width, self.truth.height, bands.to_vec());
        for (b, band) in bands.iter().enumerate() {
            self.render_band(band, cube.plane_mut(b))?;
        }
        add_noise(&mut cube.data, self.truth.noise_sigma, self.truth.seed);
        Ok(cube)
    }
}

/// Add Gaussian noise of σ `sigma` to `data`, reproducibly from `seed`.
pub fn add_noise(data: &mut [f32], sigma: f64, seed: u64) {
    if sigma <= 0.0 || !sigma.is_finite() {
        return;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let normal = Normal::new(0.0, sigma).expect("σ is positive and finite");
    for v in data {
        *v = (f64::from(*v) + normal.sample(&mut rng)) as f32;
    }
}

/// The bands of a scene, or an error when it has none.
pub fn scene_bands(scene: &Scene) -> Result<Vec<Band>, SynthError> {
    scene.bands.clone().ok_or(SynthError::NoBands)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_cylinder_renders_finite_reflectance_with_substrate_peaks() {
        let scene = Scene::paper_cylinder();
        let bands = scene_bands(&scene).unwrap();
        assert_eq!(bands.len(), 31);
        let r = Renderer::new(&scene).unwrap();
        let mut plane = vec![0.0f32; r.width() * r.height()];
        r.render_band(&bands[0], &mut plane).unwrap();
        // For n1 < n2 < n3 the film never reflects more than the bare
        // substrate (peaks touch it), nor less than the quarter-wave value.
        let bare = airy::bare_reflectance(
            crate::optics::Complex64::new(1.0, 0.0),
            crate::optics::Complex64::new(1.6, 0.0),
            10f64.to_radians(),
            crate::optics::Polarization::S,
        );
        let v = plane[0] as f64;
        assert!(
            v.is_finite() && v > 0.0 && v <= bare + 1e-6,
            "{v} vs {bare}"
        );
    }
}

/// Accuracy of fitted maps against the truth.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Accuracy {
    /// Pixels compared.
    pub pixels: usize,
    /// Fraction of pixels valid.
    pub valid_fraction: f64,
    /// Mean absolute thickness error over valid pixels, nm.
    pub thickness_mae_nm: f64,
    /// 99th percentile of the absolute thickness error, nm.
    pub thickness_p99_nm: f64,
    /// Largest absolute thickness error, nm.
    pub thickness_max_nm: f64,
    /// Mean absolute angle error over valid pixels with θ ≥ 20°, degrees.
    pub theta_mae_ge20_deg: f64,
    /// Largest absolute angle error over valid pixels with θ < 20° that
    /// were not flagged "angle not identifiable", degrees.
    pub theta_max_lt20_unflagged_deg: f64,
    /// Fraction of valid pixels with |thickness error| ≤ 2σ.
    pub coverage_2sigma: f64,
    /// Fraction of valid pixels that are wrong: |thickness error| above
    /// max(3σ, 2 nm) (a valid pixel must be right).
    pub valid_wrong_fraction: f64,
}

/// Compare fitted maps with the truth.
pub fn compare(maps: &crate::estimate::ParamMaps, truth: &TruthMaps) -> Accuracy {
    use crate::estimate::Reason;
    let n = maps.width * maps.height;
    let mut errs = Vec::with_capacity(n);
    let (mut th_sum, mut th_n, mut th_max_lt20, mut covered) = (0.0, 0usize, 0.0f64, 0usize);
    let mut wrong = 0usize;
    for i in 0..n {
        if maps.valid[i] < 0.5 {
            continue;
        }
        let e = (f64::from(maps.thickness_nm[i]) - f64::from(truth.thickness_nm[i])).abs();
        errs.push(e);
        let sigma = f64::from(maps.sigma_thickness_nm[i]);
        if e <= 2.0 * sigma {
            covered += 1;
        }
        // Not `!(e <= …)`: a NaN σ on a valid pixel is no claim of
        // precision, and the finite-outputs tests catch it.
        if e > (3.0 * sigma).max(2.0) {
            wrong += 1;
        }
        let t = f64::from(truth.theta_deg[i]);
        let te = (f64::from(maps.theta_deg[i]) - t).abs();
        if t >= 20.0 {
            th_sum += te;
            th_n += 1;
        } else if maps.reason[i] as u8 != Reason::AngleNotIdentifiable as u8 {
            th_max_lt20 = th_max_lt20.max(te);
        }
    }
    let valid = errs.len();
    errs.sort_by(f64::total_cmp);
    let pct = |p: f64| {
        if errs.is_empty() {
            f64::NAN
        } else {
            errs[((errs.len() - 1) as f64 * p).round() as usize]
        }
    };
    Accuracy {
        pixels: n,
        valid_fraction: valid as f64 / n.max(1) as f64,
        thickness_mae_nm: errs.iter().sum::<f64>() / valid.max(1) as f64,
        thickness_p99_nm: pct(0.99),
        thickness_max_nm: errs.last().copied().unwrap_or(f64::NAN),
        theta_mae_ge20_deg: if th_n > 0 {
            th_sum / th_n as f64
        } else {
            f64::NAN
        },
        theta_max_lt20_unflagged_deg: th_max_lt20,
        coverage_2sigma: covered as f64 / valid.max(1) as f64,
        valid_wrong_fraction: wrong as f64 / valid.max(1) as f64,
    }
}
