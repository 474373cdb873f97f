//! `irid fit` on spectrum tables of thin films (10–300 nm) all seen at one
//! angle, the film index and the angle both left unknown: a flat film
//! seen by a spectrometer, the commonest setting there is. At one angle
//! a lossless film's reflectance in s or p light depends on its index
//! only through its two interfaces' Fresnel coefficients, so other
//! indices (the twin that swaps them; in p light also the index of equal
//! admittance; and, the angle free, index–angle pairs that flip both
//! signs) reflect exactly alike, each at its own thickness. No data can
//! tell them apart; irid must say so (the index AMBIGUOUS, every σ
//! spanning the branches) rather than pick one and call every thickness
//! valid — which it did: n = 1.111 ± 0.0001 for a true 1.38 in s light at
//! 45°, n = 1.731 ± 0.0005 in p light at 65°, and 2.23 for 1.46 on silicon,
//! with 39 of 40 thicknesses valid and 20–40 % off in each.
//!
//! The spectra come from the characteristic-matrix method
//! (`optics::tmm`, not the Airy form irid fits with) with seeded noise
//! (ChaCha8, σ = 0.001), 61 bands of 400–700 nm; a spectrum counts as
//! wrong where it is valid and off by more than max(3σ, 2 nm).

mod cli_common;
use cli_common::{ok, s};
use irid::optics::tmm::{self, Layer};
use irid::optics::{Complex64, Polarization};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::path::Path;

const SIGMA: f64 = 0.001;

/// One film per spectrum: thickness (nm) and angle (degrees).
struct Film {
    d: f64,
    theta_deg: f64,
}

/// Forty films of 10–300 nm (a seeded spread), at `angle(i)` degrees.
fn films(angle: impl Fn(usize) -> f64) -> Vec<Film> {
    (0..40)
        .map(|i| Film {
            d: 10.0 + 290.0 * ((i as f64 * 0.618_034) % 1.0),
            theta_deg: angle(i),
        })
        .collect()
}

/// Bands of the tables: 61 of 400–700 nm, or the paper's 31 of 420–560.
const BANDS_61: (f64, f64, usize) = (400.0, 700.0, 61);
const BANDS_31: (f64, f64, usize) = (420.0, 560.0, 31);

/// Write the table of `films` (index `n2` on `n3`, light `pol`) at
/// `bands` (first, last, count).
fn write_table(
    path: &Path,
    films: &[Film],
    (n2, n3): (f64, f64),
    pol: Polarization,
    (first, last, count): (f64, f64, usize),
) {
    let c = |x: f64| Complex64::new(x, 0.0);
    let mut text = String::from("wavelength");
    for (i, f) in films.iter().enumerate() {
        text.push_str(&format!(",s{i:02}_d{:.2}", f.d));
    }
    text.push('\n');
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let noise = Normal::new(0.0, SIGMA).expect("σ is positive");
    for k in 0..count {
        let lam = first + (last - first) * k as f64 / (count - 1) as f64;
        text.push_str(&format!("{lam}"));
        for f in films {
            let th = f.theta_deg.to_radians();
            let r = tmm::reflectance(c(1.0), &[Layer::real(n2, f.d)], c(n3), th, lam, pol);
            text.push_str(&format!(",{}", r + noise.sample(&mut rng)));
        }
        text.push('\n');
    }
    std::fs::write(path, text).unwrap();
}

/// Fit the table, index and angle unknown; returns the JSON summary and
/// the rows (thickness, σ, valid).
fn fit(dir: &Path, n3: f64, pol: &str) -> (serde_json::Value, Vec<(f64, f64, bool)>) {
    let (input, out) = (dir.join("t.csv"), dir.join("r.csv"));
    let n3 = n3.to_string();
    let args = [
        "fit",
        s(&input),
        "--out",
        s(&out),
        "--json",
        "--n3",
        &n3,
        "--pol",
        pol,
        "--reflectance-accuracy",
        "0",
    ];
    let stdout = String::from_utf8(ok(&args).stdout).unwrap();
    let json = stdout
        .lines()
        .find(|l| l.starts_with('{'))
        .map(|l| serde_json::from_str(l).unwrap())
        .expect("a JSON summary");
    let text = std::fs::read_to_string(&out).unwrap();
    let rows = text
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[3].parse().unwrap(), f[4].parse().unwrap(), f[9] == "1")
        })
        .collect();
    (json, rows)
}

/// Valid spectra off by more than max(3σ, 2 nm), and valid spectra.
fn tally(films: &[Film], rows: &[(f64, f64, bool)]) -> (usize, usize) {
    assert_eq!(films.len(), rows.len());
    let (mut wrong, mut valid) = (0, 0);
    for (f, &(d, sigma, ok)) in films.iter().zip(rows) {
        if !ok {
            continue;
        }
        valid += 1;
        if (d - f.d).abs() > (3.0 * sigma).max(2.0) {
            wrong += 1;
            eprintln!("valid and wrong: {:.1} nm read {d:.1} ± {sigma:.1}", f.d);
        }
    }
    (wrong, valid)
}

/// Films at one angle, index and angle unknown: AMBIGUOUS, none valid and
/// wrong, at least half still valid (their σ spans the branches; p light
/// near Brewster's angle leaves some films too faint to see).
fn one_angle_is_ambiguous(n2: f64, n3: f64, deg: f64, pol: Polarization, name: &str) {
    let dir = tempfile::tempdir().unwrap();
    let films = films(|_| deg);
    write_table(&dir.path().join("t.csv"), &films, (n2, n3), pol, BANDS_61);
    let (json, rows) = fit(dir.path(), n3, name);
    let (wrong, valid) = tally(&films, &rows);
    assert_eq!(
        json["n_film_ambiguous"], true,
        "{name} {deg}°, {n2} on {n3}: {}",
        json["n_film_note"]
    );
    assert_eq!(
        wrong, 0,
        "{name} {deg}°: {wrong} of {valid} valid spectra wrong"
    );
    assert!(valid >= 20, "{name} {deg}°: {valid} of 40 valid");
}

#[test]
fn s_light_at_one_angle_leaves_the_twin_open() {
    one_angle_is_ambiguous(1.38, 1.6, 45.0, Polarization::S, "s");
}

/// p light at 65° on 1.38/1.6: the index of equal admittance (1.20 at
/// 65°) and an index–angle pair of flipped signs (1.73 at 47°) reflect as
/// the truth does.
#[test]
fn p_light_at_one_angle_leaves_its_equivalents_open() {
    one_angle_is_ambiguous(1.38, 1.6, 65.0, Polarization::P, "p");
}

/// Films on silicon (a constant 3.88 here) at 45° in s light, the
/// paper's 31 bands, one of them 91.8 nm: a film the search misses at the
/// true index (its lone fit lands at 245 nm and 0°, 10⁵ noise variances
/// off; flagged "poor fit" with the index given). That one residual once
/// chose the index for the other thirty-nine (2.09, every thickness
/// valid and ~40 % thin); its share of the index profile is now capped.
#[test]
fn one_missed_spectrum_does_not_choose_the_index() {
    let dir = tempfile::tempdir().unwrap();
    let mut films = films(|_| 45.0);
    films[5].d = 91.8;
    write_table(
        &dir.path().join("t.csv"),
        &films,
        (1.46, 3.88),
        Polarization::S,
        BANDS_31,
    );
    let (json, rows) = fit(dir.path(), 3.88, "s");
    let (wrong, valid) = tally(&films, &rows);
    assert_eq!(json["n_film_ambiguous"], true, "{}", json["n_film_note"]);
    assert_eq!(wrong, 0, "{wrong} of {valid} valid spectra wrong");
    assert!(valid >= 30, "{valid} of 40 valid");
}

/// The control: the same films seen at angles spread over 20–60° (a
/// curved part) break every equivalence, since each angle's twin index
/// differs. The index is then identified: not ambiguous, within 3σ of
/// the truth, and none valid and wrong.
#[test]
fn spread_angles_identify_the_index() {
    let dir = tempfile::tempdir().unwrap();
    let films = films(|i| 20.0 + 40.0 * ((i as f64 * 0.381_966) % 1.0));
    let bands = BANDS_61;
    write_table(
        &dir.path().join("t.csv"),
        &films,
        (1.38, 1.6),
        Polarization::S,
        bands,
    );
    let (json, rows) = fit(dir.path(), 1.6, "s");
    let (wrong, valid) = tally(&films, &rows);
    assert_eq!(json["n_film_ambiguous"], false, "{}", json["n_film_note"]);
    let (n, sn) = (
        json["n_film"].as_f64().unwrap(),
        json["n_film_sigma"].as_f64().unwrap(),
    );
    assert!((n - 1.38).abs() <= 3.0 * sn.max(1e-4), "n {n} ± {sn}");
    assert_eq!(wrong, 0, "{wrong} of {valid} valid spectra wrong");
    assert!(valid >= 30, "{valid} of 40 valid");
}
