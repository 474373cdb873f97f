//! The Airy summation (`optics::airy`) against the independent
//! characteristic-matrix method (`optics::tmm`), plus the physical limits
//! both must obey.
//!
//! Tolerances: both formulations evaluate O(1) expressions of O(1) complex
//! numbers, so they agree to a few ulps (1e-15) when well conditioned. The
//! worst conditioning in the sweep is the multiple-reflection denominator
//! `1 + r12 r23 e^{iΔ}` near grazing incidence, where `|r12 r23| → 1`; 1e-12
//! leaves three orders of magnitude for that amplification and still catches
//! any real error (a wrong sign, branch or conjugation changes `r` at O(0.01–1)).

use irid::optics::tmm::{self, Layer};
use irid::optics::{airy, Complex64, Media, Polarization};
use proptest::prelude::*;

const TOL: f64 = 1e-12;

fn c(re: f64, im: f64) -> Complex64 {
    Complex64::new(re, im)
}

fn deg(x: f64) -> f64 {
    x.to_radians()
}

/// Ambient, film and substrate indices of the sweep: lossless, the paper's
/// twin pair, a dielectric denser than the ambient, absorbing films and
/// substrates (Si near 500 nm from Green 2008: 4.29 + 0.045i; a silver-like
/// metal 0.13 + 3.0i), and films optically thinner than the ambient (TIR).
fn sweep_media() -> Vec<Media> {
    let ambients = [c(1.0, 0.0), c(1.33, 0.0), c(1.5, 0.0)];
    let films = [
        c(1.0, 0.0),
        c(1.17, 0.0),
        c(1.37, 0.0),
        c(2.3, 0.0),
        c(2.0, 0.3),
        c(4.29, 0.045),
        c(0.13, 3.0),
    ];
    let substrates = [
        c(1.0, 0.0),
        c(1.6, 0.0),
        c(4.29, 0.045),
        c(1.5, 1e-3),
        c(0.13, 3.0),
    ];
    let mut out = Vec::new();
    for &n1 in &ambients {
        for &n2 in &films {
            for &n3 in &substrates {
                out.push(Media { n1, n2, n3 });
            }
        }
    }
    out
}

const ANGLES_DEG: [f64; 11] = [
    0.0, 5.0, 10.0, 30.0, 42.5, 45.0, 60.0, 75.0, 85.0, 89.0, 89.9,
];
const THICKNESSES_NM: [f64; 8] = [0.0, 1.0, 50.0, 137.0, 420.0, 560.0, 1000.0, 2000.0];
const WAVELENGTHS_NM: [f64; 3] = [400.0, 551.3, 700.0];

#[test]
fn airy_and_tmm_amplitudes_agree_over_the_sweep() {
    let mut worst = 0.0f64;
    let mut count = 0usize;
    for m in sweep_media() {
        for &a in &ANGLES_DEG {
            for &d in &THICKNESSES_NM {
                for &lam in &WAVELENGTHS_NM {
                    let th = deg(a);
                    let (rs_a, rp_a) = airy::amplitude(m, d, th, lam);
                    let t = tmm::film_response(m, d, th, lam);
                    let err = (rs_a - t.r_s).norm().max((rp_a - t.r_p).norm());
                    assert!(
                        err <= TOL,
                        "r differs by {err:e} for {m:?}, d = {d} nm, θ = {a}°, λ = {lam} nm: airy ({rs_a}, {rp_a}) tmm ({}, {})",
                        t.r_s,
                        t.r_p
                    );
                    for pol in [
                        Polarization::S,
                        Polarization::P,
                        Polarization::Unpolarized,
                        Polarization::Mixed { s_weight: 0.3 },
                    ] {
                        let ra = airy::reflectance(m, d, th, lam, pol);
                        let rt = tmm::reflectance(m.n1, &[Layer::new(m.n2, d)], m.n3, th, lam, pol);
                        assert!(
                            (ra - rt).abs() <= TOL,
                            "{pol:?}: {ra} vs {rt} for {m:?} d = {d} θ = {a}"
                        );
                    }
                    worst = worst.max(err);
                    count += 1;
                }
            }
        }
    }
    assert!(count > 10_000);
    eprintln!("{count} cases, worst amplitude difference {worst:e}");
}

/// Textbook Fresnel reflectances of the bare n1/n3 interface for real indices
/// below the critical angle, written with angles (Snell), not with q.
fn textbook_bare(n1: f64, n3: f64, theta1: f64) -> (f64, f64) {
    let theta3 = (n1 * theta1.sin() / n3).asin();
    let (c1, c3) = (theta1.cos(), theta3.cos());
    let rs = (n1 * c1 - n3 * c3) / (n1 * c1 + n3 * c3);
    let rp = (n3 * c1 - n1 * c3) / (n3 * c1 + n1 * c3);
    (rs * rs, rp * rp)
}

#[test]
fn vanishing_film_gives_the_bare_interface() {
    for (n1, n2, n3) in [(1.0, 1.37, 1.6), (1.0, 2.3, 1.5), (1.33, 1.1, 1.52)] {
        for a in [0.0, 20.0, 45.0, 70.0, 89.0] {
            let th = deg(a);
            let (bs, bp) = textbook_bare(n1, n3, th);
            // The textbook form goes through cos θ1, whose relative rounding
            // error grows like tan θ1 ulps (57 at 89°): 1e-13 covers it.
            let close = |(rs, rp): (f64, f64), what: &str| {
                assert!(
                    (rs - bs).abs() < 1e-13 && (rp - bp).abs() < 1e-13,
                    "{what} at {a}°: ({rs}, {rp}) vs ({bs}, {bp})"
                );
            };
            let stack = |n2: f64, d: f64| (c(n1, 0.0), [Layer::real(n2, d)], c(n3, 0.0));
            for lam in [400.0, 650.0] {
                // d = 0, any film.
                close(
                    airy::reflectance_sp(Media::real(n1, n2, n3), 0.0, th, lam),
                    "airy d = 0",
                );
                let (a1, l, a3) = stack(n2, 0.0);
                close(tmm::reflectance_sp(a1, &l, a3, th, lam), "tmm d = 0");
                // n2 = n3 and n2 = n1, any thickness.
                for d in [10.0, 480.0, 1999.0] {
                    close(
                        airy::reflectance_sp(Media::real(n1, n3, n3), d, th, lam),
                        "airy n2 = n3",
                    );
                    close(
                        airy::reflectance_sp(Media::real(n1, n1, n3), d, th, lam),
                        "airy n2 = n1",
                    );
                    let (a1, l, a3) = stack(n3, d);
                    close(tmm::reflectance_sp(a1, &l, a3, th, lam), "tmm n2 = n3");
                    let (a1, l, a3) = stack(n1, d);
                    close(tmm::reflectance_sp(a1, &l, a3, th, lam), "tmm n2 = n1");
                }
            }
        }
    }
}

#[test]
fn grazing_incidence_reflects_everything() {
    // As θ1 → 90°, q1 = n1 cos θ1 → 0 and r → −1 for any stack:
    // r = (η0 − Y)/(η0 + Y) with Y the stack's input admittance, so
    // 1 − R = 4 η0 Re Y / |η0 + Y|² ∝ cos θ1 to first order while Y stays
    // finite: shrinking cos θ1 tenfold shrinks 1 − R tenfold, up to relative
    // corrections O(η0/|Y|) ~ 1e-4 here (10% slack is generous). (Y itself
    // vanishes when the substrate has the ambient's index; then 1 − R ∝ cos² θ1,
    // so the TIR case below uses a denser substrate.)
    for m in [
        Media::real(1.0, 1.37, 1.6),
        Media {
            n1: c(1.0, 0.0),
            n2: c(4.29, 0.045),
            n3: c(1.6, 0.0),
        },
        Media::real(1.5, 1.0, 1.6),
        Media {
            n1: c(1.0, 0.0),
            n2: c(1.37, 0.0),
            n3: c(4.29, 0.045),
        },
    ] {
        for pol in [Polarization::S, Polarization::P] {
            let loss = |eps: f64| {
                let th = std::f64::consts::FRAC_PI_2 - eps;
                let ra = 1.0 - airy::reflectance(m, 480.0, th, 550.0, pol);
                let rt =
                    1.0 - tmm::reflectance(m.n1, &[Layer::new(m.n2, 480.0)], m.n3, th, 550.0, pol);
                assert!((ra - rt).abs() < TOL);
                ra
            };
            let (l1, l2) = (loss(1e-4), loss(1e-5));
            assert!(l1 > 0.0 && l1 < 1e-2, "{m:?} {pol:?}: 1 − R = {l1}");
            let ratio = l2 / l1;
            assert!((ratio - 0.1).abs() < 0.01, "{m:?} {pol:?}: ratio {ratio}");
            // Exactly grazing: R = 1.
            let r = airy::reflectance(m, 480.0, std::f64::consts::FRAC_PI_2, 550.0, pol);
            assert!((r - 1.0).abs() < 1e-12, "{r}");
        }
    }
}

#[test]
fn energy_is_conserved_for_lossless_stacks() {
    // R + T = 1 with lossless ambient and layers, including multilayers,
    // frustrated total internal reflection (thin gap, T > 0) and TIR at the
    // substrate (T = 0).
    let stacks: Vec<(f64, Vec<Layer>, f64)> = vec![
        (1.0, vec![Layer::real(1.37, 480.0)], 1.6),
        (
            1.0,
            vec![
                Layer::real(2.3, 60.0),
                Layer::real(1.38, 100.0),
                Layer::real(2.3, 60.0),
            ],
            1.52,
        ),
        (1.5, vec![Layer::real(1.0, 150.0)], 1.5),
        (1.5, vec![Layer::real(1.0, 150.0)], 1.0),
        (1.0, vec![], 1.5),
    ];
    for (n1, layers, n3) in &stacks {
        for a in [0.0, 15.0, 41.0, 42.5, 60.0, 80.0, 89.9] {
            for lam in [400.0, 550.0, 700.0] {
                let r = tmm::response(c(*n1, 0.0), layers, c(*n3, 0.0), deg(a), lam);
                for (big_r, big_t) in [
                    (r.reflectance_s, r.transmittance_s),
                    (r.reflectance_p, r.transmittance_p),
                ] {
                    assert!(
                        (big_r + big_t - 1.0).abs() < 1e-13,
                        "{n1} {layers:?} {n3} {a}°: R {big_r} T {big_t}"
                    );
                    assert!(big_t >= 0.0);
                }
            }
        }
    }
    // Frustrated TIR really transmits, and a thicker gap transmits less.
    let thin = tmm::transmittance_sp(
        c(1.5, 0.0),
        &[Layer::real(1.0, 50.0)],
        c(1.5, 0.0),
        deg(60.0),
        500.0,
    );
    let thick = tmm::transmittance_sp(
        c(1.5, 0.0),
        &[Layer::real(1.0, 300.0)],
        c(1.5, 0.0),
        deg(60.0),
        500.0,
    );
    assert!(thin.0 > thick.0 && thick.0 > 0.0 && thin.1 > thick.1 && thick.1 > 0.0);
}

#[test]
fn transmittance_normalisation_holds_into_an_absorbing_substrate() {
    // T is the flux just inside the substrate, so with a lossless film
    // R + T = 1 even when the substrate absorbs. For p this only holds with
    // the n² factors of the TM impedance: a check of the power normalisation.
    let si = c(4.29, 0.045);
    let metal = c(0.13, 3.0);
    for n3 in [si, metal] {
        for a in [0.0, 30.0, 60.0, 75.0, 89.0] {
            let r = tmm::response(c(1.0, 0.0), &[Layer::real(1.46, 300.0)], n3, deg(a), 550.0);
            assert!(
                (r.reflectance_s + r.transmittance_s - 1.0).abs() < 1e-13,
                "{r:?}"
            );
            assert!(
                (r.reflectance_p + r.transmittance_p - 1.0).abs() < 1e-13,
                "{r:?}"
            );
        }
    }
    // An absorbing film takes its share: A = 1 − R − T > 0.
    let r = tmm::response(
        c(1.0, 0.0),
        &[Layer::new(si, 300.0)],
        c(1.5, 0.0),
        deg(30.0),
        450.0,
    );
    assert!(1.0 - r.reflectance_s - r.transmittance_s > 1e-3);
    assert!(1.0 - r.reflectance_p - r.transmittance_p > 1e-3);
}

#[test]
fn s_equals_p_at_normal_incidence() {
    // Exact in theory; the s and p paths are different algebra (p carries
    // n² factors), so they agree to rounding, O(100 ulps) near R ≈ 1 of a metal.
    for m in sweep_media() {
        for d in [0.0, 137.0, 560.0] {
            let (rs, rp) = airy::reflectance_sp(m, d, 0.0, 500.0);
            assert!((rs - rp).abs() < 1e-13, "{m:?}");
            let (ts, tp) = tmm::reflectance_sp(m.n1, &[Layer::new(m.n2, d)], m.n3, 0.0, 500.0);
            assert!((ts - tp).abs() < 1e-13, "{m:?}");
        }
    }
}

#[test]
fn twin_film_is_exact_at_normal_incidence() {
    // n2 → n1 n3 / n2 with n2 d kept swaps r12 and r23; R is symmetric in
    // them, so the spectra coincide to rounding. The phase Δ (up to ~60 rad
    // here) is computed from different products n·d, so it carries ~60 ε of
    // absolute rounding; |dR/dΔ| < 1 makes 1e-13 a safe bound.
    for (n1, n2, n3) in [(1.0, 1.37, 1.6), (1.0, 2.0, 1.5), (1.33, 1.45, 1.52)] {
        let twin = n1 * n3 / n2;
        for d in [100.0, 420.0, 560.0, 1500.0] {
            let d_twin = n2 * d / twin;
            for lam in (0..=30).map(|i| 400.0 + 10.0 * i as f64) {
                let a = airy::reflectance(Media::real(n1, n2, n3), d, 0.0, lam, Polarization::S);
                let b =
                    airy::reflectance(Media::real(n1, twin, n3), d_twin, 0.0, lam, Polarization::S);
                assert!((a - b).abs() < 1e-13, "{n2} vs {twin} at {lam}: {a} {b}");
                let t = tmm::reflectance(
                    c(n1, 0.0),
                    &[Layer::real(twin, d_twin)],
                    c(n3, 0.0),
                    0.0,
                    lam,
                    Polarization::S,
                );
                assert!((a - t).abs() < 1e-13);
            }
        }
    }
}

#[test]
fn brewster_angle_extinguishes_p() {
    for (n1, n3) in [(1.0f64, 1.5f64), (1.0, 1.6), (1.33, 1.0)] {
        let th_b = (n3 / n1).atan();
        let (rs, rp) = airy::reflectance_sp(Media::real(n1, n1, n3), 0.0, th_b, 550.0);
        let (_, rp_t) = tmm::reflectance_sp(c(n1, 0.0), &[], c(n3, 0.0), th_b, 550.0);
        // r_p is a difference of O(1) terms that cancel: |r_p| ~ 1e-16.
        assert!(rp < 1e-28 && rp_t < 1e-28, "{rp} {rp_t}");
        assert!(rs > 1e-3);
    }
}

#[test]
fn sublayers_and_ambient_layers_change_nothing() {
    // Splitting a film in two of the same index is the same film; a layer of
    // the ambient's own index on top only shifts the phase of r.
    let (n1, n2, n3) = (c(1.0, 0.0), c(2.0, 0.3), c(1.6, 0.0));
    for a in [0.0, 40.0, 80.0] {
        let one = tmm::response(n1, &[Layer::new(n2, 500.0)], n3, deg(a), 600.0);
        let two = tmm::response(
            n1,
            &[Layer::new(n2, 180.0), Layer::new(n2, 320.0)],
            n3,
            deg(a),
            600.0,
        );
        assert!((one.r_s - two.r_s).norm() < 1e-13 && (one.r_p - two.r_p).norm() < 1e-13);
        assert!((one.t_s - two.t_s).norm() < 1e-13 && (one.t_p - two.t_p).norm() < 1e-13);
        let top = tmm::response(
            n1,
            &[Layer::new(n1, 250.0), Layer::new(n2, 500.0)],
            n3,
            deg(a),
            600.0,
        );
        assert!((one.reflectance_s - top.reflectance_s).abs() < 1e-13);
        assert!((one.reflectance_p - top.reflectance_p).abs() < 1e-13);
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// Every output finite and physical, and the two formulations agree,
    /// over a wide physical range (absorbing, TIR, grazing, thick films).
    #[test]
    fn outputs_are_finite_and_formulations_agree(
        n1 in 1.0f64..2.0,
        n2 in 0.05f64..5.0, k2 in 0.0f64..5.0,
        n3 in 0.05f64..5.0, k3 in 0.0f64..5.0,
        absorbing in proptest::bool::ANY,
        theta_deg in 0.0f64..90.0,
        d in 0.0f64..20_000.0,
        lam in 200.0f64..2000.0,
    ) {
        let (k2, k3) = if absorbing { (k2, k3) } else { (0.0, 0.0) };
        let (n2, n3) = if absorbing { (n2, n3) } else { (n2.max(1.0), n3.max(1.0)) };
        let m = Media { n1: c(n1, 0.0), n2: c(n2, k2), n3: c(n3, k3) };
        let th = deg(theta_deg);
        let (rs, rp) = airy::reflectance_sp(m, d, th, lam);
        let t = tmm::film_response(m, d, th, lam);
        for x in [rs, rp, t.reflectance_s, t.reflectance_p, t.transmittance_s, t.transmittance_p] {
            prop_assert!(x.is_finite());
            prop_assert!((-1e-12..=1.0 + 1e-12).contains(&x), "{x}");
        }
        prop_assert!(t.reflectance_s + t.transmittance_s <= 1.0 + 1e-12);
        prop_assert!(t.reflectance_p + t.transmittance_p <= 1.0 + 1e-12);
        if !absorbing {
            prop_assert!((t.reflectance_s + t.transmittance_s - 1.0).abs() < 1e-12);
            prop_assert!((t.reflectance_p + t.transmittance_p - 1.0).abs() < 1e-12);
        }
        prop_assert!((rs - t.reflectance_s).abs() < TOL, "s: {} vs {}", rs, t.reflectance_s);
        prop_assert!((rp - t.reflectance_p).abs() < TOL, "p: {} vs {}", rp, t.reflectance_p);
    }
}
