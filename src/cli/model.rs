//! `irid model`: the model reflectance of one film for given parameters, one
//! `wavelength_nm reflectance` pair per line, for cross-checks against
//! other codes. Numbers are printed with Rust's shortest round-trip
//! formatting, so they carry full f64 precision.

use super::common::parse_wavelengths;
use crate::optics::band::Band;
use crate::optics::dispersion::Dispersion;
use crate::optics::material::MaterialLibrary;
use crate::optics::{airy, Complex64, Media, Polarization};
use anyhow::Context;
use std::io::Write;

/// Arguments of `irid model`.
#[derive(Debug, clap::Args)]
pub struct ModelArgs {
    /// Ambient index.
    #[arg(long, default_value_t = 1.0)]
    pub n1: f64,
    /// Ambient extinction coefficient.
    #[arg(long, default_value_t = 0.0)]
    pub k1: f64,
    /// Film index.
    #[arg(
        long,
        required_unless_present = "material2",
        conflicts_with = "material2"
    )]
    pub n2: Option<f64>,
    /// Film extinction coefficient.
    #[arg(long, default_value_t = 0.0)]
    pub k2: f64,
    /// Film material (refractiveindex.info name or .yml path) instead of --n2.
    #[arg(long, value_name = "NAME")]
    pub material2: Option<String>,
    /// Substrate index.
    #[arg(
        long,
        required_unless_present = "material3",
        conflicts_with = "material3"
    )]
    pub n3: Option<f64>,
    /// Substrate extinction coefficient.
    #[arg(long, default_value_t = 0.0)]
    pub k3: f64,
    /// Substrate material instead of --n3.
    #[arg(long, value_name = "NAME")]
    pub material3: Option<String>,
    /// Film thickness, nm.
    #[arg(long = "d-nm", value_name = "NM")]
    pub d_nm: f64,
    /// Incidence angle in the ambient, degrees.
    #[arg(long, value_name = "DEG", default_value_t = 0.0)]
    pub theta_deg: f64,
    /// Polarisation: s, p, u, or an s weight in [0, 1].
    #[arg(long, default_value = "s")]
    pub pol: String,
    /// Wavelengths, nm: `start:stop:step` (inclusive) or a comma list.
    #[arg(long, value_name = "LIST")]
    pub wavelengths: String,
    /// Band FWHM, nm: integrate the model over a Gaussian passband (0: point samples).
    #[arg(long = "fwhm-nm", value_name = "NM", default_value_t = 0.0)]
    pub fwhm_nm: f64,
}

fn medium(
    name: &str,
    n: Option<f64>,
    k: f64,
    material: &Option<String>,
) -> anyhow::Result<Dispersion> {
    match (n, material) {
        (_, Some(m)) => MaterialLibrary::builtin()
            .resolve(m)
            .map(|m| m.dispersion)
            .with_context(|| format!("{name} material {m:?}")),
        (Some(n), None) => {
            anyhow::ensure!(
                n.is_finite() && n > 0.0 && k.is_finite() && k >= 0.0,
                "{name}: need n > 0 and k ≥ 0, not n = {n}, k = {k}"
            );
            Ok(Dispersion::Constant(Complex64::new(n, k)))
        }
        (None, None) => anyhow::bail!("{name}: give an index or a material"),
    }
}

/// Compute the model reflectance at each wavelength: `(λ nm, R)`.
pub fn evaluate(a: &ModelArgs) -> anyhow::Result<Vec<(f64, f64)>> {
    let ambient = medium("ambient", Some(a.n1), a.k1, &None)?;
    let film = medium("film", a.n2, a.k2, &a.material2)?;
    let substrate = medium("substrate", a.n3, a.k3, &a.material3)?;
    let pol = Polarization::parse(&a.pol).map_err(|m| anyhow::anyhow!("--pol: {m}"))?;
    anyhow::ensure!(
        a.d_nm.is_finite() && a.d_nm >= 0.0,
        "--d-nm must be ≥ 0, not {}",
        a.d_nm
    );
    anyhow::ensure!(
        (0.0..90.0).contains(&a.theta_deg),
        "--theta-deg must lie in [0, 90), not {}",
        a.theta_deg
    );
    anyhow::ensure!(
        a.fwhm_nm.is_finite() && a.fwhm_nm >= 0.0,
        "--fwhm-nm must be ≥ 0"
    );
    let lams =
        parse_wavelengths(&a.wavelengths).map_err(|m| anyhow::anyhow!("--wavelengths: {m}"))?;
    let theta = a.theta_deg.to_radians();
    let mut out = Vec::with_capacity(lams.len());
    for lam in lams {
        let band = Band {
            center_nm: lam,
            fwhm_nm: a.fwhm_nm,
        };
        let err = std::cell::RefCell::new(None);
        let r = band.integrate(|l| {
            let media = (|| {
                Ok::<_, crate::optics::dispersion::OpticsError>(Media {
                    n1: ambient.index_at(l)?,
                    n2: film.index_at(l)?,
                    n3: substrate.index_at(l)?,
                })
            })();
            match media {
                Ok(m) => airy::reflectance(m, a.d_nm, theta, l, pol),
                Err(e) => {
                    err.borrow_mut().get_or_insert(e);
                    f64::NAN
                }
            }
        });
        if let Some(e) = err.into_inner() {
            return Err(e).with_context(|| format!("at {lam} nm"));
        }
        out.push((lam, r));
    }
    Ok(out)
}

/// Run `irid model`.
pub fn run(a: &ModelArgs) -> anyhow::Result<()> {
    let rows = evaluate(a)?;
    let mut text = String::with_capacity(rows.len() * 32);
    for (lam, r) in rows {
        text.push_str(&format!("{lam} {r}\n"));
    }
    std::io::stdout().lock().write_all(text.as_bytes())?;
    Ok(())
}
