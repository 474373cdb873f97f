//! The per-pixel solver and the global film-index search (placeholder API;
//! the implementation follows).

use super::{Cube, EstimateError, Mode, ParamMaps, PixelEstimate, Reason};
use crate::optics::band::Band;
use crate::scene::Scene;

/// The film index used for a fit: estimated once from the image, or known.
#[derive(Clone, Debug, PartialEq)]
pub struct IndexEstimate {
    /// Index (at the middle band for a dispersive known film).
    pub n: f64,
    /// Standard error (0 when known).
    pub sigma: f64,
    /// Whether it was estimated.
    pub estimated: bool,
    /// The other branch of the n2 ↔ n1·n3/n2 near-symmetry, if one was found.
    pub twin: Option<f64>,
    /// χ² by which the twin fits worse (large: resolved; small: ambiguous).
    pub twin_delta_chi2: f64,
    /// A human-readable note (e.g. "twin not resolved; prior used").
    pub note: String,
}

/// Reusable per-thread working memory of the solver.
#[derive(Clone, Debug, Default)]
pub struct Scratch {
    spectrum: Vec<f64>,
}

/// Solves pixels for the scene's unknowns.
#[derive(Clone, Debug)]
pub struct Solver {
    scene: Scene,
    bands: Vec<Band>,
    mode: Mode,
    index: Option<IndexEstimate>,
}

impl Solver {
    /// A solver for `scene` observed in `bands` (cube plane order).
    pub fn new(scene: &Scene, bands: &[Band], mode: Mode) -> Result<Solver, EstimateError> {
        Ok(Solver {
            scene: scene.clone(),
            bands: bands.to_vec(),
            mode,
            index: None,
        })
    }

    /// The mode.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// The film index in use, once known or estimated.
    pub fn film_index(&self) -> Option<&IndexEstimate> {
        self.index.as_ref()
    }

    /// Use this film index from now on (e.g. one estimated on an earlier sweep).
    pub fn set_film_index(&mut self, est: IndexEstimate) {
        self.index = Some(est);
    }

    /// Estimate the film index from the cube when the scene leaves it
    /// unknown (a no-op returning the known value otherwise).
    pub fn estimate_film_index(&mut self, cube: &Cube) -> Result<IndexEstimate, EstimateError> {
        let _ = cube;
        Err(EstimateError::FilmIndex("not implemented yet".into()))
    }

    /// Solve one pixel. `spectrum` is in band order (NaN marks a missing
    /// band); `theta_known` is the pixel's known angle in radians.
    pub fn solve_pixel(
        &self,
        spectrum: &[f64],
        theta_known: Option<f64>,
        scratch: &mut Scratch,
    ) -> PixelEstimate {
        let _ = (spectrum, theta_known, &scratch.spectrum);
        PixelEstimate::invalid(Reason::PoorFit)
    }

    /// Solve row `y` of the cube into `out` (length `cube.width`).
    pub fn solve_row(
        &self,
        cube: &Cube,
        y: usize,
        out: &mut [PixelEstimate],
        scratch: &mut Scratch,
    ) {
        let mut spec = std::mem::take(&mut scratch.spectrum);
        spec.resize(cube.bands.len(), 0.0);
        for (x, o) in out.iter_mut().enumerate().take(cube.width) {
            cube.spectrum_into(x, y, &mut spec);
            *o = self.solve_pixel(&spec, self.scene.angle.known_at(x, y), scratch);
        }
        scratch.spectrum = spec;
    }

    /// Fit a whole cube: the film index first where unknown, then every
    /// pixel, rows in parallel on the current rayon pool.
    pub fn fit_cube(&mut self, cube: &Cube) -> Result<ParamMaps, EstimateError> {
        let _ = cube;
        Err(EstimateError::FilmIndex("not implemented yet".into()))
    }
}
