//! The passband criterion against the actual difference between point
//! sampling and integrating a real film spectrum.
//!
//! The spectrum is the paper's film (1.37 on 1.60, s, 30°), evaluated with the
//! Airy model; the passband integral is taken as a reference by a dense
//! Simpson rule over ±8σ, independent of the band's Gauss–Hermite nodes.

use irid::optics::airy;
use irid::optics::band::Band;
use std::f64::consts::PI;

const N1: f64 = 1.0;
const N2: f64 = 1.37;
const N3: f64 = 1.6;

/// Reflectance of a film with optical thickness `g = n2 d cos θ2` at λ.
fn spectrum(g: f64, theta: f64) -> impl Fn(f64) -> f64 {
    let (s, _) = airy::real_film(N1, N2, N3, theta.sin()).expect("lossless, below critical");
    move |lam: f64| s.reflectance((4.0 * PI * g / lam).cos())
}

/// Reference passband integral: composite Simpson over ±8σ, 4000 intervals
/// (the integrand is smooth; h⁴ error ≪ 1e-12 for fringe periods ≥ 5 nm).
fn reference(band: Band, f: &dyn Fn(f64) -> f64) -> f64 {
    let s = band.sigma_nm();
    let (lo, hi, n) = (band.center_nm - 8.0 * s, band.center_nm + 8.0 * s, 4000);
    let h = (hi - lo) / n as f64;
    let gauss =
        |l: f64| (-(l - band.center_nm).powi(2) / (2.0 * s * s)).exp() / (s * (2.0 * PI).sqrt());
    let mut acc = 0.0;
    for i in 0..=n {
        let l = lo + h * i as f64;
        let w = if i == 0 || i == n {
            1.0
        } else if i % 2 == 1 {
            4.0
        } else {
            2.0
        };
        acc += w * f(l) * gauss(l);
    }
    acc * h / 3.0
}

#[test]
fn quadrature_matches_reference_on_a_film_spectrum() {
    // Fringe periods λ²/(2g) ≥ 1.5 FWHM here (u ≤ 1.8): GH-9 error
    // ≤ u¹⁸/1.76e10 ≈ 2e-6 of the amplitude (≈ 0.03), so 1e-7 absolute.
    let theta = 30f64.to_radians();
    for (center, fwhm) in [(400.0, 7.0), (550.0, 10.0), (700.0, 20.0)] {
        let band = Band::new(center, fwhm).unwrap();
        for g in [0.0, 150.0, 420.0, 700.0, 1000.0] {
            let p = center * center / (2.0 * g);
            if p < 1.5 * fwhm {
                continue;
            }
            let f = spectrum(g, theta);
            let got = band.integrate(&f);
            let want = reference(band, &f);
            assert!(
                (got - want).abs() < 1e-7,
                "{center}/{fwhm} g = {g}: {got} vs {want}"
            );
        }
    }
}

/// First-harmonic point-sampling error, exactly for a phase quadratic in λ:
/// for x ~ N(0, σ²), E[e^{i(αx + βx²)}] = (1 − 2iβσ²)^{−1/2} exp(−α²σ²/(2(1 − 2iβσ²))).
fn first_harmonic_error(g: f64, center: f64, sigma: f64) -> f64 {
    use irid::optics::Complex64;
    let alpha = -4.0 * PI * g / (center * center); // Δ'
    let beta = 4.0 * PI * g / center.powi(3); // Δ''/2
    let one = Complex64::new(1.0, 0.0);
    let z = one - Complex64::new(0.0, 2.0 * beta * sigma * sigma);
    let avg = z.powf(-0.5) * (-(alpha * alpha * sigma * sigma) / (2.0 * z)).exp();
    let dc = 4.0 * PI * g / center;
    let integrated = (Complex64::new(0.0, dc).exp() * avg).re;
    (dc.cos() - integrated).abs()
}

#[test]
fn criterion_predicts_the_point_sampling_error() {
    // Against the exact first-harmonic result for a quadratic phase, the
    // actual error differs by what the first harmonic leaves out: the second
    // harmonic, of relative size ≈ ρ = |r12 r23| and suffering at most about
    // four times the first harmonic's error (phase 2Δ: loss 1 − A⁴ ≤ 4(1 − A),
    // shift 2φ), and the cubic phase term, relative size ≈ 3|Δ' Δ'''/6| σ⁴.
    let theta = 30f64.to_radians();
    let (s, _) = airy::real_film(N1, N2, N3, theta.sin()).unwrap();
    let a = (s.half_wave() - s.quarter_wave()).abs() / 2.0;
    let rho = (s.r12 * s.r23).abs();
    for (center, fwhm) in [(400.0, 7.0), (450.0, 10.0), (600.0, 15.0)] {
        let band = Band::new(center, fwhm).unwrap();
        let sigma = band.sigma_nm();
        for i in 0..200 {
            let g = 5.0 * i as f64;
            if center * center / (2.0 * g) < 1.5 * fwhm {
                break;
            }
            let f = spectrum(g, theta);
            let actual = (f(center) - reference(band, &f)).abs();
            let first = a * first_harmonic_error(g, center, sigma);
            let bound = band.point_sampling_error(g, a);
            let cubic = 3.0 * (4.0 * PI * g).powi(2) * sigma.powi(4) / center.powi(6);
            let slack = 4.0 * rho * bound + a * cubic + 1e-12;
            assert!(
                (actual - first).abs() <= slack,
                "{center}/{fwhm} g = {g}: actual {actual:e}, first harmonic {first:e}, slack {slack:e}"
            );
            // The criterion's bound is never exceeded by more than the slack.
            assert!(
                actual <= bound + slack,
                "{center}/{fwhm} g = {g}: {actual:e} > {bound:e}"
            );
        }
    }
}

#[test]
fn criterion_decisions_are_consistent_with_the_actual_error() {
    // With the noise of the paper's simulation (σ_R = 0.001) and a tolerance
    // of a third of it: whenever the criterion says "point sampling is fine",
    // the actual error is within the tolerance (up to the neglected terms);
    // at fringe extrema, where it says "integrate", the error really exceeds it.
    let theta = 30f64.to_radians();
    let (s, _) = airy::real_film(N1, N2, N3, theta.sin()).unwrap();
    let a = (s.half_wave() - s.quarter_wave()).abs() / 2.0;
    let tol = 0.001 / 3.0;
    let band = Band::new(450.0, 10.0).unwrap();
    let (mut said_fine, mut said_integrate) = (0, 0);
    for m in 1..40 {
        // Extrema: 4π g/λc = mπ.
        let g = m as f64 * band.center_nm / 4.0;
        let f = spectrum(g, theta);
        let actual = (f(band.center_nm) - reference(band, &f)).abs();
        if band.needs_integration_for(g, a, tol) {
            said_integrate += 1;
            assert!(
                actual > 0.8 * tol,
                "g = {g}: actual {actual:e} but integration demanded"
            );
        } else {
            said_fine += 1;
            assert!(
                actual < 1.2 * tol,
                "g = {g}: actual {actual:e} but point sampling allowed"
            );
        }
        // The worst-case form is conservative.
        if !band.needs_integration(g, tol) {
            assert!(!band.needs_integration_for(g, a, tol));
        }
    }
    assert!(
        said_fine > 3 && said_integrate > 3,
        "{said_fine} {said_integrate}"
    );
}
