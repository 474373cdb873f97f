//! The operating limits README states, computed here (`cargo test --test
//! operating_limits -- --nocapture` prints the table) for the default band
//! sets, 400–700 nm at 10 and 5 nm, on the paper's media (film n = 1.37 on
//! a substrate of n = 1.60, in air):
//!
//! - **thickest film**: the optical thickness the bands resolve
//!   (`estimate::range::max_optical_thickness`: a phase step of 0.8 π
//!   between the two bluest bands) over n2·cos θ2. Noise does not move it:
//!   past it the fringe aliases onto a thinner film.
//! - **thinnest film**: the smallest d whose Cramér–Rao σ_d (the exact
//!   model's Jacobian; irid's fits reach it with the angle known, see the
//!   scene matrix) is at most 10 % of d. Near d = 0 reflectance is even in
//!   d, so σ_d grows as d → 0; the limit moves with the square root of the
//!   noise or faster.
//! - **identifiable angle**: the angles at which the joint (d, θ) bound
//!   σ_θ stays within 0.25° (irid's "angle not identifiable" threshold),
//!   at d = 500 nm, for s, p and unpolarised light.
//!
//! The assertions check the physics the numbers rest on, with tolerances
//! from the definitions (not copied from a run).

use irid::estimate::model::{FilmModel, ModelOut};
use irid::estimate::range::max_optical_thickness;
use irid::optics::band::Band;
use irid::optics::dispersion::Dispersion;
use irid::optics::Polarization;

const N1: f64 = 1.0;
const N2: f64 = 1.37;
const N3: f64 = 1.60;
const ANGLE_LIMIT_DEG: f64 = 0.25;

fn bands(step: f64) -> Vec<Band> {
    let n = (300.0 / step).round() as usize + 1;
    (0..n)
        .map(|i| Band::new(400.0 + step * i as f64, 0.0).unwrap())
        .collect()
}

fn model(b: &[Band], pol: Polarization) -> FilmModel {
    FilmModel::new(
        b,
        &Dispersion::constant(N1),
        &Dispersion::constant(N2),
        &Dispersion::constant(N3),
        pol,
        &vec![false; b.len()],
    )
    .unwrap()
}

/// Fisher sums (d·d, d·θ, θ·θ) of the model at (d, θ).
fn fisher(m: &FilmModel, nb: usize, d: f64, theta: f64) -> (f64, f64, f64) {
    let mut out = ModelOut::new(nb);
    m.eval(d, theta, &mut out, true);
    let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
    for k in 0..nb {
        a += out.dr_dd[k] * out.dr_dd[k];
        b += out.dr_dd[k] * out.dr_dth[k];
        c += out.dr_dth[k] * out.dr_dth[k];
    }
    (a, b, c)
}

/// σ_d with the angle known.
fn sigma_d(m: &FilmModel, nb: usize, d: f64, theta: f64, sigma_r: f64) -> f64 {
    sigma_r / fisher(m, nb, d, theta).0.sqrt()
}

/// σ_θ (degrees) with d and θ both unknown.
fn sigma_theta_deg(m: &FilmModel, nb: usize, d: f64, theta: f64, sigma_r: f64) -> f64 {
    let (a, b, c) = fisher(m, nb, d, theta);
    (sigma_r * (a / (a * c - b * b)).sqrt()).to_degrees()
}

/// Smallest d (1 nm grid) with σ_d ≤ 10 % of d.
fn thinnest(m: &FilmModel, nb: usize, theta: f64, sigma_r: f64) -> f64 {
    (1..3000)
        .map(f64::from)
        .find(|&d| sigma_d(m, nb, d, theta, sigma_r) <= 0.1 * d)
        .unwrap_or(f64::NAN)
}

/// The angle ranges (0.5° grid, 0–80°) where σ_θ ≤ the limit.
fn identifiable(m: &FilmModel, nb: usize, d: f64, sigma_r: f64) -> Vec<(f64, f64)> {
    let mut ranges: Vec<(f64, f64)> = Vec::new();
    let mut open: Option<f64> = None;
    for i in 0..=160 {
        let t = 0.5 * f64::from(i);
        let ok = sigma_theta_deg(m, nb, d, t.to_radians(), sigma_r) <= ANGLE_LIMIT_DEG;
        match (ok, open) {
            (true, None) => open = Some(t),
            (false, Some(s)) => {
                ranges.push((s, t - 0.5));
                open = None;
            }
            _ => {}
        }
    }
    if let Some(s) = open {
        ranges.push((s, 80.0));
    }
    ranges
}

fn show(r: &[(f64, f64)]) -> String {
    if r.is_empty() {
        return "none".into();
    }
    r.iter()
        .map(|(a, b)| format!("{a:.1}–{b:.1}°"))
        .collect::<Vec<_>>()
        .join(", ")
}

#[test]
fn operating_limits_of_the_default_band_sets() {
    let noise = [1e-4, 1e-3, 1e-2];
    println!("| bands | thickest d (θ = 0) | σ_R | thinnest d, θ = 30° known | angle identifiable at d = 500 nm: s | p | unpolarised |");
    println!("|---|---|---|---|---|---|---|");
    for step in [10.0, 5.0] {
        let b = bands(step);
        let nb = b.len();
        let (g, _) = max_optical_thickness(&b);
        let thickest = g / N2;
        let ms = model(&b, Polarization::S);
        let mp = model(&b, Polarization::P);
        let mu = model(&b, Polarization::Unpolarized);
        let mut last_thin = 0.0;
        for &s in &noise {
            let thin = thinnest(&mu, nb, 30f64.to_radians(), s);
            println!(
                "| 400–700 nm / {step} nm ({nb}) | {thickest:.0} nm | {s:.0e} | {thin:.0} nm | {} | {} | {} |",
                show(&identifiable(&ms, nb, 500.0, s)),
                show(&identifiable(&mp, nb, 500.0, s)),
                show(&identifiable(&mu, nb, 500.0, s)),
            );
            // More noise never makes a thinner film measurable.
            assert!(thin >= last_thin, "{thin} < {last_thin}");
            last_thin = thin;
        }
        // σ_d scales linearly with σ_R at fixed d (the bound is linear).
        let r = sigma_d(&mu, nb, 300.0, 0.5, 1e-2) / sigma_d(&mu, nb, 300.0, 0.5, 1e-3);
        assert!((r - 10.0).abs() < 1e-9, "{r}");
        // Halving the step doubles the resolved optical thickness (to the
        // 2 % a sampling limit set by 1/λ differences allows).
        if step == 5.0 {
            let (g10, _) = max_optical_thickness(&bands(10.0));
            assert!((g / g10 - 2.0).abs() < 0.03, "{}", g / g10);
        }
        // At normal incidence the angle is never identifiable (R is even
        // in θ there), and in p light at Brewster's angle of the substrate
        // interface (~58° for 1.6) the fringe contrast collapses.
        let at = |m: &FilmModel, t: f64| sigma_theta_deg(m, nb, 500.0, t.to_radians(), 1e-3);
        assert!(at(&ms, 0.0) > ANGLE_LIMIT_DEG || at(&ms, 0.0).is_nan());
        assert!(at(&mp, 53.9) > at(&mp, 40.0), "p near Brewster");
    }
}
