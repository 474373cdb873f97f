//! `irid fit --level free` on spectrometer-like normalised intensities that
//! irid's model did not render: free-standing water films (the Airy sum
//! written out by hand, water as a Cauchy formula rather than irid's
//! H2O-Hale table), averaged over a thickness spread in the spot (fringe
//! contrast washes out towards the blue), divided by a lamp spectrum with a
//! bump the model has no term for, on a sloped stray-light baseline, with
//! noise four times larger in the blue than in the red. The thickness must
//! come from the fringe positions: within 10 % for nine spectra in ten,
//! and no valid number off by more.

mod cli_common;
use cli_common::{ok, s};
use std::fmt::Write as _;

/// Water's index, a two-term Cauchy fit (not irid's table).
fn n_water(lam: f64) -> f64 {
    1.324188 + 3102.060378 / (lam * lam)
}

/// Normal-incidence reflectance of a free-standing film (air both sides).
fn airy(d: f64, lam: f64) -> f64 {
    let n = n_water(lam);
    let r = (1.0 - n) / (1.0 + n);
    let f = 4.0 * r * r / (1.0 - r * r).powi(2);
    let s = (2.0 * std::f64::consts::PI * n * d / lam).sin().powi(2);
    f * s / (1.0 + f * s)
}

/// The film seen through a spot whose thickness spreads by `spread`
/// (relative, Gaussian, 15-point quadrature).
fn spotted(d: f64, spread: f64, lam: f64) -> f64 {
    let mut sum = 0.0;
    let mut wsum = 0.0;
    for i in -7..=7 {
        let z = f64::from(i) / 3.0;
        let w = (-0.5 * z * z).exp();
        sum += w * airy(d * (1.0 + spread * z), lam);
        wsum += w;
    }
    sum / wsum
}

/// A deterministic Gaussian-ish noise source (sum of uniforms).
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> f64 {
        let mut acc = 0.0;
        for _ in 0..12 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            acc += (self.0 >> 11) as f64 / (1u64 << 53) as f64;
        }
        acc - 6.0
    }
}

/// One fitted spectrum: the true thickness, the estimate, its σ, whether
/// valid, and the reason's name.
struct Row {
    d: f64,
    got: f64,
    sigma: f64,
    valid: bool,
    reason: String,
}

/// Renders one normalised spectrum per thickness (400–800 nm at 1 nm),
/// each with its own lamp error, spot spread and stray light, and fits
/// them with `irid fit --level free`.
fn fit_water(thick: &[f64], seed: u64) -> Vec<Row> {
    let n_spec = thick.len();
    fit_rendered(thick, seed, |i, d, lam| {
        let k = i as f64 / n_spec as f64;
        let u = (lam - 600.0) / 200.0;
        let lamp = (7.0 + 2.0 * k)
            * (1.0
                + (0.2 - 0.3 * k) * u
                + 0.15 * (-((lam - 520.0 - 80.0 * k) / 50.0).powi(2)).exp());
        let stray = 0.06 + 0.03 * u;
        let sigma = 0.004 * (1.0 + 3.0 * (-(lam - 400.0) / 40.0).exp());
        (stray + lamp * spotted(d, 0.004 + 0.006 * k, lam), sigma)
    })
}

/// Renders spectrum `i` of thickness `d` at 400–800 nm (1 nm) as
/// `render(i, d, λ) = (mean, noise σ)` plus noise, and fits them all with
/// `irid fit --level free`.
fn fit_rendered(
    thick: &[f64],
    seed: u64,
    render: impl Fn(usize, f64, f64) -> (f64, f64),
) -> Vec<Row> {
    let mut noise = Noise(seed);
    let mut text = String::from("wavelength_nm");
    for i in 0..thick.len() {
        write!(text, ",film{i}").unwrap();
    }
    text.push('\n');
    for nm in 400..=800 {
        let lam = f64::from(nm);
        write!(text, "{nm}").unwrap();
        for (i, &d) in thick.iter().enumerate() {
            let (mean, sigma) = render(i, d, lam);
            let v = mean + sigma * noise.next();
            write!(text, ",{v:.6}").unwrap();
        }
        text.push('\n');
    }
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("water.csv");
    std::fs::write(&input, text).unwrap();
    let out = dir.path().join("res.csv");
    ok(&[
        "fit",
        s(&input),
        "--out",
        s(&out),
        "--material2",
        "H2O-Hale",
        "--n1",
        "1",
        "--n3",
        "1",
        "--theta-deg",
        "0",
        "--level",
        "free",
    ]);
    let res = std::fs::read_to_string(&out).unwrap();
    res.lines()
        .skip(1)
        .zip(thick)
        .map(|(line, &d)| {
            let f: Vec<&str> = line.split(',').collect();
            Row {
                d,
                got: f[3].parse().unwrap(),
                sigma: f[4].parse().unwrap(),
                valid: f[9] == "1",
                reason: f[11].to_string(),
            }
        })
        .collect()
}

/// The rows as a table for failure messages.
fn report(rows: &[Row]) -> String {
    let mut out = String::new();
    for r in rows {
        writeln!(
            out,
            "{:7.0} nm → {:8.1} ± {:6.1} valid {} ({})",
            r.d, r.got, r.sigma, r.valid, r.reason
        )
        .unwrap();
    }
    out
}

/// No valid estimate off by more than 10 %, and σ covering the error
/// (the renderer's index differs from the table's by ~1e-3, and the
/// spot's spread biases the fringes): the number of valid rows.
fn check_valid_rows(rows: &[Row]) -> usize {
    let table = report(rows);
    for r in rows.iter().filter(|r| r.valid) {
        assert!(
            (r.got / r.d - 1.0).abs() <= 0.10,
            "valid and wrong:\n{table}"
        );
        assert!(
            (r.got - r.d).abs() <= 3.0 * r.sigma,
            "σ too small:\n{table}"
        );
    }
    rows.iter().filter(|r| r.valid).count()
}

#[test]
fn normalised_water_film_spectra_read_from_their_fringes() {
    // Thicknesses spread geometrically over 250 nm – 4 µm.
    let n_spec: usize = 36;
    let thick: Vec<f64> = (0..n_spec)
        .map(|i| 250.0 * (16f64).powf(i as f64 / (n_spec - 1) as f64))
        .collect();
    let rows = fit_water(&thick, 7);
    let close = check_valid_rows(&rows);
    assert!(
        close * 10 >= 9 * n_spec,
        "{close} of {n_spec} valid:\n{}",
        report(&rows)
    );
}

/// Films with one or two extrema in the band (60–400 nm over 400–800 nm):
/// a single broad hump of the first order moves with the envelope and is
/// flagged; from about one and a half fringes (three extrema, the outer
/// two near the band's ends) the spectrum's shape picks the order, and
/// the estimate is valid and right.
#[test]
fn few_fringe_films_are_read_by_their_shape_or_flagged() {
    let thick: Vec<f64> = (0..18).map(|i| 60.0 + 20.0 * f64::from(i)).collect();
    let rows = fit_water(&thick, 11);
    check_valid_rows(&rows);
    let table = report(&rows);
    println!("{table}");
    // One hump (first order, below ~120 nm): never valid.
    for r in rows.iter().filter(|r| r.d < 120.0) {
        assert!(
            !r.valid,
            "a single first-order hump read as valid:\n{table}"
        );
    }
    // Three extrema or more (from ~280 nm): mostly read.
    let wide: Vec<&Row> = rows.iter().filter(|r| r.d >= 280.0).collect();
    let read = wide.iter().filter(|r| r.valid).count();
    assert!(
        read * 3 >= wide.len() * 2,
        "{read} of {} read:\n{table}",
        wide.len()
    );
}

/// Films too thin for a pair of fringes (50–190 nm: no extremum or one in
/// 400–800 nm), divided by a lamp spectrum with a bump (10–30 %, centred
/// from green to red, 50–90 nm wide), with noise seven times larger in the
/// blue: the bump and the noise can pass for two or three extrema, which
/// a thicker film's fringes would explain — but a film too thin for
/// fringes explains the shape as well (with a straight scale, or one that
/// may curve like the bump), so no thicker answer may stand. Before this
/// was checked, 10 of 270 such spectra came out valid at 0.5–0.9 µm. One
/// case stays beyond what a free level can tell: a 30 % bump centred on a
/// first-order hump narrows it into a third-order one's shape (1 of the
/// 540 here, and of 1 080 over four seeds), so at most one is allowed.
#[test]
fn a_lamp_bump_on_a_film_without_fringes_is_not_read_as_fringes() {
    let mut thick = Vec::new();
    let mut shapes = Vec::new();
    for d in (50..200).step_by(10) {
        for amp in [0.1, 0.2, 0.3] {
            for centre in [520.0, 580.0, 650.0] {
                for width in [50.0, 90.0] {
                    thick.push(f64::from(d));
                    shapes.push((amp, centre, width));
                }
            }
        }
    }
    let mut wrong = Vec::new();
    for seed in [3, 5] {
        let rows = fit_rendered(&thick, seed, |i, d, lam| {
            let (amp, centre, width) = shapes[i];
            let u = (lam - 600.0) / 200.0;
            let lamp = (1.0 + 0.1 * u) * (1.0 + amp * (-((lam - centre) / width).powi(2)).exp());
            let sigma = 0.004 * (1.0 + 6.0 * (-(lam - 400.0) / 40.0).exp());
            (0.03 + 6.0 * airy(d, lam) * lamp, sigma)
        });
        wrong.extend(
            rows.into_iter()
                .filter(|r| r.valid && (r.got / r.d - 1.0).abs() > 0.10),
        );
    }
    assert!(wrong.len() <= 1, "valid and wrong:\n{}", report(&wrong));
}
