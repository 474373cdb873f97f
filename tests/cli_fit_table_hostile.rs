//! `irid fit` on spectrum tables holding what no film reflects, as a user's
//! files do: dark (all-zero) spectra among real ones, and raw counts under
//! `--level free`. The spectra are rendered by a normal-incidence Airy sum
//! written out here (not irid's model), with seeded noise (ChaCha8, as `irid synth`).

mod cli_common;
use cli_common::{ok, s};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::f64::consts::PI;
use std::path::Path;

/// Film and substrate indices, and the noise σ of every sample.
const N2: f64 = 1.46;
const N3: f64 = 2.0;
const SIGMA: f64 = 0.001;

/// Reflectance of a film of `d` nm on the substrate in air at normal
/// incidence (s and p alike): |r12 + r23 e^{-iδ}|² / |1 + r12 r23 e^{-iδ}|²
/// with δ = 4π n2 d / λ, the cosine form of the modulus.
fn reflectance(d: f64, lam: f64) -> f64 {
    let (r12, r23) = ((1.0 - N2) / (1.0 + N2), (N2 - N3) / (N2 + N3));
    let c = (4.0 * PI * N2 * d / lam).cos();
    let num = r12 * r12 + r23 * r23 + 2.0 * r12 * r23 * c;
    let den = 1.0 + r12 * r12 * r23 * r23 + 2.0 * r12 * r23 * c;
    num / den
}

/// Thirty films of 100–2 420 nm at 61 bands (400–700 nm), each sample
/// `f(R, λ)` of its noisy reflectance; the spectra whose index `dark`
/// picks are all zero. Returns the true thicknesses (None: dark).
fn write_table(
    path: &Path,
    f: impl Fn(f64, f64) -> f64,
    dark: impl Fn(usize) -> bool,
) -> Vec<Option<f64>> {
    let films: Vec<Option<f64>> = (0..30)
        .map(|i| (!dark(i)).then_some(100.0 + 80.0 * i as f64))
        .collect();
    let mut text = String::from("wavelength");
    for (i, d) in films.iter().enumerate() {
        text.push_str(&format!(",s{i:02}_d{}", d.unwrap_or(0.0)));
    }
    text.push('\n');
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let noise = Normal::new(0.0, SIGMA).expect("σ is positive");
    for k in 0..61 {
        let lam = 400.0 + 5.0 * k as f64;
        text.push_str(&format!("{lam}"));
        for d in &films {
            let v = match d {
                Some(d) => f(reflectance(*d, lam) + noise.sample(&mut rng), lam),
                None => 0.0,
            };
            text.push_str(&format!(",{v}"));
        }
        text.push('\n');
    }
    std::fs::write(path, text).unwrap();
    films
}

/// The result CSV's rows: (thickness, σ, valid).
fn results(path: &Path) -> Vec<(f64, f64, bool)> {
    let text = std::fs::read_to_string(path).unwrap();
    text.lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[3].parse().unwrap(), f[4].parse().unwrap(), f[9] == "1")
        })
        .collect()
}

/// Valid spectra off by more than max(3σ, 2 nm), and valid spectra.
fn tally(films: &[Option<f64>], rows: &[(f64, f64, bool)]) -> (usize, usize) {
    assert_eq!(films.len(), rows.len());
    let (mut wrong, mut valid) = (0, 0);
    for (truth, &(d, sigma, ok)) in films.iter().zip(rows) {
        if !ok {
            continue;
        }
        let truth = truth.expect("a dark spectrum is never valid");
        valid += 1;
        if (d - truth).abs() > (3.0 * sigma).max(2.0) {
            wrong += 1;
            eprintln!("valid and wrong: {truth} nm read {d} ± {sigma}");
        }
    }
    (wrong, valid)
}

/// Six all-zero spectra (a closed shutter) among thirty, index and angle
/// unknown: they were taken into the index sample, where they fit best at
/// the index that reflects least (√(n1·n3) ≈ 1.41), and pulled the rest
/// to n = 1.44 at 48°: 24 of 24 spectra valid and ~20 % off. Left out of
/// the sample now, none is valid and wrong, and the real spectra stay
/// valid (the angle not identifiable at normal incidence, σ spanning it).
#[test]
fn dark_spectra_do_not_pull_the_index_of_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let (input, out) = (dir.path().join("t.csv"), dir.path().join("r.csv"));
    let films = write_table(&input, |r, _| r, |i| i % 5 == 0);
    ok(&[
        "fit",
        s(&input),
        "--out",
        s(&out),
        "--n3",
        "2.0",
        "--pol",
        "u",
    ]);
    let rows = results(&out);
    let (wrong, valid) = tally(&films, &rows);
    assert_eq!(wrong, 0, "{wrong} of {valid} valid spectra wrong");
    assert!(valid >= 20, "{valid} of 24 real spectra valid");
}

/// Raw counts of a lamp that peaks at 600 nm over a dark level of 1 000
/// counts: `--level free` (its own scale and offset per spectrum) is what
/// the refusal of such a table recommends, and it once refused them too
/// (the index sample kept only values a reflectance takes). With the film
/// and angle given, the thickness comes from the fringes: every valid one
/// within 10 % (the free level's bound) and most valid.
#[test]
fn raw_counts_fit_under_the_free_level() {
    let dir = tempfile::tempdir().unwrap();
    let (input, out) = (dir.path().join("t.csv"), dir.path().join("r.csv"));
    let lamp = |lam: f64| (-((lam - 600.0) / 180.0).powi(2)).exp();
    let films = write_table(
        &input,
        |r, lam| (r * 40_000.0 * lamp(lam) + 1_000.0).round(),
        |_| false,
    );
    let common = [
        "--n3",
        "2.0",
        "--pol",
        "u",
        "--n2",
        "1.46",
        "--theta-deg",
        "0",
    ];
    let mut args = vec!["fit", s(&input), "--out", s(&out)];
    args.extend_from_slice(&common);
    args.extend_from_slice(&["--level", "free"]);
    ok(&args);
    let rows = results(&out);
    let mut valid = 0;
    for (truth, &(d, _, ok)) in films.iter().zip(&rows) {
        let truth = truth.unwrap();
        if ok {
            valid += 1;
            assert!((d - truth).abs() <= 0.1 * truth, "{truth} nm read {d}");
        }
    }
    assert!(valid >= 20, "{valid} of 30 valid");
}
