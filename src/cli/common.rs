//! Helpers shared by the subcommands: band lists, scene loading with
//! command-line overrides, a polarisation argument.

use crate::estimate::level::LevelMode;
use crate::scene::{MediumSpec, Scene, SceneFile, PAPER_CYLINDER};
use anyhow::{bail, Context};
use std::path::{Path, PathBuf};

/// Parse a wavelength list: `start:stop:step` (stop inclusive), or
/// comma-separated values, or one value. nm.
pub fn parse_wavelengths(text: &str) -> Result<Vec<f64>, String> {
    let t = text.trim();
    let num = |s: &str| -> Result<f64, String> {
        s.trim()
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("not a number: {:?}", s.trim()))
    };
    let values = if t.contains(':') {
        let parts: Vec<&str> = t.split(':').collect();
        let [a, b, c] = parts[..] else {
            return Err(format!("a range is start:stop:step, not {t:?}"));
        };
        let (start, stop, step) = (num(a)?, num(b)?, num(c)?);
        if !(step > 0.0 && stop >= start) {
            return Err(format!("range {t:?}: need start ≤ stop and step > 0"));
        }
        let n = ((stop - start) / step + 1e-9).floor();
        if n > 100_000.0 {
            return Err(format!("range {t:?} has too many values"));
        }
        (0..=n as usize).map(|i| start + step * i as f64).collect()
    } else {
        t.split(',').map(num).collect::<Result<Vec<_>, _>>()?
    };
    if values.iter().any(|v| *v <= 0.0) {
        return Err("wavelengths must be positive".into());
    }
    Ok(values)
}

/// A parsed scene file and the directory its relative paths start from.
pub struct SceneSource {
    /// The file as parsed (to be edited by overrides).
    pub file: SceneFile,
    /// Base directory of relative paths.
    pub base: PathBuf,
    /// Where it came from, for messages.
    pub origin: String,
}

impl SceneSource {
    /// Parse the scene at `path`.
    pub fn load(path: &Path) -> anyhow::Result<SceneSource> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read scene file {}", path.display()))?;
        let origin = path.display().to_string();
        let file: SceneFile =
            toml::from_str(&text).map_err(|e| anyhow::anyhow!("scene {origin}: {e}"))?;
        Ok(SceneSource {
            file,
            base: path.parent().unwrap_or(Path::new(".")).to_path_buf(),
            origin,
        })
    }

    /// The embedded paper cylinder.
    pub fn paper_cylinder() -> SceneSource {
        SceneSource {
            file: toml::from_str(PAPER_CYLINDER).expect("the embedded scene parses (tested)"),
            base: PathBuf::from("."),
            origin: "<embedded paper-cylinder>".into(),
        }
    }

    /// A scene that knows only the ambient (n = 1): film, angle and
    /// substrate to be given or estimated.
    pub fn empty() -> SceneSource {
        SceneSource {
            file: SceneFile::default(),
            base: PathBuf::from("."),
            origin: "<command line>".into(),
        }
    }

    /// Resolve to a [`Scene`].
    pub fn resolve(&self) -> anyhow::Result<Scene> {
        Scene::resolve(&self.file, &self.base).map_err(|e| anyhow::anyhow!("{}: {e}", self.origin))
    }
}

/// A material named on the command line: a path (`.yml`, or with a
/// separator) is made absolute, because the scene resolves relative paths
/// against its own directory; a built-in name is kept.
fn cli_material(spec: &str) -> String {
    let lower = spec.to_ascii_lowercase();
    let is_path = lower.ends_with(".yml") || lower.ends_with(".yaml") || spec.contains(['/', '\\']);
    match std::path::absolute(spec) {
        Ok(abs) if is_path => abs.display().to_string(),
        _ => spec.to_string(),
    }
}

/// Command-line overrides of a scene. Each given value replaces the
/// scene's; a known value replaces an unknown one (so it is never estimated).
#[derive(Clone, Debug, Default, clap::Args)]
pub struct SceneOverrides {
    /// Ambient index (default: the scene's, else 1).
    #[arg(long, value_name = "N")]
    pub n1: Option<f64>,
    /// Known film index: the film is then never estimated.
    #[arg(long, value_name = "N", conflicts_with = "material2")]
    pub n2: Option<f64>,
    /// Known film material (refractiveindex.info name or .yml path).
    #[arg(long, value_name = "NAME")]
    pub material2: Option<String>,
    /// Substrate index.
    #[arg(long, value_name = "N", conflicts_with = "material3")]
    pub n3: Option<f64>,
    /// Substrate material (refractiveindex.info name or .yml path).
    #[arg(long, value_name = "NAME")]
    pub material3: Option<String>,
    /// Known incidence angle for every pixel, degrees.
    #[arg(long, value_name = "DEG", conflicts_with = "theta_map")]
    pub theta_deg: Option<f64>,
    /// Known per-pixel incidence angle, degrees (single-band EXR or ENVI).
    #[arg(long, value_name = "FILE")]
    pub theta_map: Option<PathBuf>,
    /// Polarisation: s, p, u, or an s weight in [0, 1].
    #[arg(long, value_name = "s|p|u|W")]
    pub pol: Option<String>,
    /// Reflectance noise σ (default: from the calibration, else estimated
    /// from the data without a model).
    #[arg(long, value_name = "SIGMA")]
    pub noise_sigma: Option<f64>,
    /// Accuracy of the reflectance scale, a fraction of R (reference,
    /// focus, lamp drift), added to the noise when fits are judged (default
    /// 0; spectrum tables outside `--level free`: 0.10).
    #[arg(long, value_name = "FRACTION")]
    pub reflectance_accuracy: Option<f64>,
    /// How the instrument's level is modelled: `auto` (absolute unless the
    /// data show a correctable calibration error), `absolute`, `scaled`
    /// (image-wide gain and offset per band), `free` (per-pixel scale,
    /// offset and envelope: normalised intensities).
    #[arg(long, value_enum, value_name = "MODE")]
    pub level: Option<LevelMode>,
    /// The filter's wavelength calibration: `auto` (an image-wide shift of
    /// every band centre, fitted where the data show one), `none`, or the
    /// shift in nm (true centre = nominal + shift).
    #[arg(long, value_name = "auto|none|NM", allow_hyphen_values = true)]
    pub band_shift: Option<String>,
    /// Thinnest film considered, nm (default 0).
    #[arg(long, value_name = "NM")]
    pub min_thickness_nm: Option<f64>,
    /// Thickest film considered, nm (default: what the bands resolve).
    #[arg(long, value_name = "NM")]
    pub max_thickness_nm: Option<f64>,
}

impl SceneOverrides {
    /// Apply the overrides to a parsed scene file.
    pub fn apply(&self, file: &mut SceneFile) -> anyhow::Result<()> {
        if let Some(n) = self.n1 {
            file.ambient = MediumSpec::constant(n);
        }
        if self.n2.is_some() || self.material2.is_some() {
            file.film.n = self.n2;
            file.film.k = None;
            file.film.material = self.material2.as_deref().map(cli_material);
            file.film.search = None;
            file.film.prior = None;
        }
        if let Some(n) = self.n3 {
            file.substrate = MediumSpec::constant(n);
        }
        if let Some(m) = &self.material3 {
            file.substrate = MediumSpec {
                material: Some(cli_material(m)),
                ..Default::default()
            };
        }
        if let Some(d) = self.theta_deg {
            file.angle.deg = Some(d);
            file.angle.map = None;
            file.angle.search_deg = None;
        }
        if let Some(p) = &self.theta_map {
            // The scene resolves map paths against its own directory; a
            // path from the command line is relative to the working one.
            let abs =
                std::path::absolute(p).with_context(|| format!("--theta-map {}", p.display()))?;
            file.angle.map = Some(abs);
            file.angle.deg = None;
            file.angle.search_deg = None;
        }
        if let Some(p) = &self.pol {
            if let Err(m) = crate::optics::Polarization::parse(p) {
                bail!("--pol: {m}");
            }
            file.light.polarization = toml::Value::String(p.clone());
        }
        if let Some(s) = self.noise_sigma {
            file.measurement.noise_sigma = Some(s);
        }
        if let Some(e) = self.reflectance_accuracy {
            file.measurement.reflectance_accuracy = Some(e);
        }
        if let Some(l) = self.level {
            file.measurement.level = Some(l.name().into());
        }
        if let Some(b) = &self.band_shift {
            let spec = crate::scene::BandShiftSpec::Name(b.clone());
            if let Err(m) = spec.resolve() {
                bail!("--band-shift: {m}");
            }
            file.measurement.band_shift = Some(spec);
        }
        if let Some(d) = self.min_thickness_nm {
            file.film.min_thickness_nm = Some(d);
        }
        if let Some(d) = self.max_thickness_nm {
            file.film.max_thickness_nm = Some(d);
        }
        Ok(())
    }
}

/// The overwrite policy of a command's outputs: replace only with `--force`.
pub fn overwrite(force: bool) -> crate::io::atomic::Overwrite {
    if force {
        crate::io::atomic::Overwrite::Replace
    } else {
        crate::io::atomic::Overwrite::Refuse
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{AngleKnowledge, FilmKnowledge};

    #[test]
    fn wavelength_lists() {
        assert_eq!(parse_wavelengths("400:700:10").unwrap().len(), 31);
        assert_eq!(
            parse_wavelengths("400:700:100").unwrap(),
            [400.0, 500.0, 600.0, 700.0]
        );
        assert_eq!(parse_wavelengths("550").unwrap(), [550.0]);
        assert_eq!(parse_wavelengths("500, 510.5").unwrap(), [500.0, 510.5]);
        assert!((parse_wavelengths("0.1:0.3:0.1").unwrap()[2] - 0.3).abs() < 1e-12);
        for bad in [
            "700:400:10",
            "400:700:0",
            "400:700",
            "a",
            "400,,500",
            "-5",
            "1:1e9:1e-3",
        ] {
            assert!(parse_wavelengths(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn overrides_make_values_known() {
        let mut src = SceneSource::paper_cylinder();
        let o = SceneOverrides {
            n2: Some(1.38),
            theta_deg: Some(30.0),
            pol: Some("p".into()),
            n3: Some(1.55),
            ..Default::default()
        };
        o.apply(&mut src.file).unwrap();
        src.file.truth = None;
        let scene = src.resolve().unwrap();
        assert!(matches!(scene.film, FilmKnowledge::Known(_)));
        assert!(
            matches!(scene.angle, AngleKnowledge::Uniform(t) if (t - 30f64.to_radians()).abs() < 1e-12)
        );
        assert_eq!(scene.polarization, crate::optics::Polarization::P);
        assert_eq!(scene.substrate.index_at(500.0).unwrap().re, 1.55);
    }

    #[test]
    fn bad_override_is_named() {
        let mut src = SceneSource::empty();
        let o = SceneOverrides {
            pol: Some("sideways".into()),
            ..Default::default()
        };
        let e = o.apply(&mut src.file).unwrap_err().to_string();
        assert!(e.starts_with("--pol"), "{e}");
    }
}
