//! Helpers shared by the estimation tests: the truth's angle as a known
//! per-pixel map, two solves of one pixel compared, and the scene's known
//! film as a model (for the Cramér–Rao bounds the tests compute).

#![allow(dead_code)] // each test crate uses some of these

use irid::estimate::model::FilmModel;
use irid::estimate::solver::Scratch;
use irid::estimate::{Cube, PixelEstimate, Reason, Solver};
use irid::optics::band::Band;
use irid::scene::{AngleKnowledge, FilmKnowledge, Scene};

/// Assert that two solves of the same pixel (`row`, from a row path, and
/// `lone`, the pixel solved alone) judge it alike — the same reason — and,
/// where valid, agree on thickness and σ within 0.05 σ. Returns whether
/// the thickness is identical (`None` for a flagged pixel).
pub fn assert_agree(at: &str, row: &PixelEstimate, lone: &PixelEstimate) -> Option<bool> {
    assert_agree_within(at, row, lone, 0.05)
}

/// [`assert_agree`] with the thicknesses within `k` σ: `fast` stops a
/// refinement within √0.1 = 0.32 σ of its minimum, so two of its fits of
/// one minimum from different starts lie within 0.64 σ of each other.
pub fn assert_agree_within(
    at: &str,
    row: &PixelEstimate,
    lone: &PixelEstimate,
    k: f64,
) -> Option<bool> {
    assert_eq!(row.reason, lone.reason, "{at}: {row:?} vs {lone:?}");
    if !row.is_valid() {
        return None;
    }
    let dd = (row.thickness_nm - lone.thickness_nm).abs();
    assert!(dd < k * row.sigma_thickness_nm, "{at}: {row:?} vs {lone:?}");
    assert!(
        (row.sigma_thickness_nm - lone.sigma_thickness_nm).abs() < 0.05 * row.sigma_thickness_nm,
        "{at}: {row:?} vs {lone:?}"
    );
    Some(dd < 1e-9)
}

/// `s` with its synthetic truth's angles given as a known angle map.
pub fn with_known_angle(mut s: Scene) -> Scene {
    let t = s.truth.clone().expect("a synthetic scene");
    let deg = (0..t.height)
        .flat_map(|y| (0..t.width).map(move |x| (x, y)))
        .map(|(x, y)| t.angle_deg.at(x, y, t.width, t.height) as f32)
        .collect();
    s.angle = AngleKnowledge::Map {
        width: t.width,
        height: t.height,
        deg,
    };
    s
}

/// Whether a valid estimate is wrong: farther than max(3σ, 2 nm) from the
/// truth.
pub fn valid_and_wrong(est: &PixelEstimate, truth_nm: f32) -> bool {
    let e = (est.thickness_nm - f64::from(truth_nm)).abs();
    est.is_valid() && e > (3.0 * est.sigma_thickness_nm).max(2.0)
}

/// A row path's tally: not passed by flagging everything (over 90 % of the
/// pixels valid), nor by agreeing on wrong numbers (at most 1 % of the
/// valid pixels wrong).
pub fn assert_rows_trustworthy(label: &str, valid: usize, total: usize, wrong: usize) {
    assert!(
        valid as f64 > 0.9 * total as f64,
        "{label}: {valid} of {total} valid"
    );
    assert!(
        wrong as f64 <= 0.01 * valid as f64,
        "{label}: {wrong} valid and wrong"
    );
}

/// The scene's known film seen in `bands`, every band point-sampled: the
/// model whose Jacobian at the truth gives a test's Cramér–Rao bound.
pub fn point_model(scene: &Scene, bands: &[Band]) -> FilmModel {
    let FilmKnowledge::Known(film) = &scene.film else {
        panic!("the film's material is known")
    };
    FilmModel::new(
        bands,
        &scene.ambient,
        film,
        &scene.substrate,
        scene.polarization,
        &vec![false; bands.len()],
    )
    .expect("the scene's model")
}

/// A thin production coating: 60–400 nm of silica across the image on PET,
/// the angle 20–40° down it, unpolarised, 31 bands at 10 nm; `angle` the
/// scene's `[angle]` section, the truth rendered with noise σ
/// `truth_sigma` from `seed`, and `given_sigma` the `[measurement]` σ
/// (none: the noise is the test's to set).
pub fn thin_coating(
    angle: &str,
    (width, height): (usize, usize),
    truth_sigma: f64,
    seed: u64,
    given_sigma: Option<f64>,
) -> Scene {
    let measurement = given_sigma.map_or(String::new(), |s| {
        format!("[measurement]\nnoise_sigma = {s}\n")
    });
    let text = format!(
        r#"
[ambient]
n = 1.0
[substrate]
material = "PET-Zhang"
[film]
material = "SiO2-Malitson"
{angle}
[light]
polarization = "u"
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
{measurement}[truth]
width = {width}
height = {height}
thickness_nm = {{ linear_x = [60.0, 400.0] }}
angle_deg = {{ linear_y = [20.0, 40.0] }}
noise_sigma = {truth_sigma}
seed = {seed}
"#
    );
    Scene::from_toml(&text, "<test>", std::path::Path::new(".")).expect("test scene parses")
}

/// A ripple no film makes (0.03·sin(2πk/7) on band k, 30× a σ of 0.001)
/// added to columns `cols` of every row of `cube`.
pub fn add_ripple(cube: &mut Cube, cols: std::ops::Range<usize>) {
    let (w, h) = (cube.width, cube.height);
    for (k, plane) in cube.data.chunks_exact_mut(w * h).enumerate() {
        let ripple = 0.03 * (std::f64::consts::TAU * k as f64 / 7.0).sin();
        for y in 0..h {
            for x in cols.clone() {
                plane[y * w + x] += ripple as f32;
            }
        }
    }
}

/// Every row of `cube` solved as a row solver does (one scratch through
/// the rows, each row starting afresh) and every pixel alone (a fresh
/// scratch: no previous pixel, the whole search), both handed to
/// `each(x, y, row, lone, scratch)` with the rows' scratch as its row
/// left it; returns that scratch (its counters).
pub fn rows_against_lone(
    solver: &Solver,
    cube: &Cube,
    mut each: impl FnMut(usize, usize, &PixelEstimate, &PixelEstimate, &Scratch),
) -> Scratch {
    let mut scratch = Scratch::default();
    let mut row = vec![PixelEstimate::invalid(Reason::Masked); cube.width];
    let mut spec = vec![0.0; cube.bands.len()];
    for y in 0..cube.height {
        solver.solve_row(cube, y, &mut row, &mut scratch);
        for (x, r) in row.iter().enumerate() {
            cube.spectrum_into(x, y, &mut spec);
            let mut lone = Scratch::default();
            let p = solver.solve_pixel(&spec, solver.scene_angle().known_at(x, y), &mut lone);
            each(x, y, r, &p, &scratch);
        }
    }
    scratch
}
