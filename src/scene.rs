//! The scene description: what is known about the object, what irid must
//! estimate, and (for synthetic data) the ground truth.
//!
//! One TOML file serves `irid fit`, `irid synth` and `irid run`. Its sections:
//!
//! - `[ambient]`, `[substrate]`: media, each `n`/`k` constants or a `material`
//!   (a built-in refractiveindex.info name or a path to a `.yml` file).
//! - `[film]`: a known index (`n`, `k` or `material`) — then it is never
//!   re-estimated — or, with none of them, unknown: `search = [lo, hi]` bounds
//!   the global index estimate and an optional `prior` breaks the
//!   n2 ↔ n1·n3/n2 twin tie; `min_thickness_nm` / `max_thickness_nm` bound
//!   the thickness search (default: 0 to what the bands resolve).
//! - `[angle]`: known (`deg`, or a per-pixel `map` file in degrees) or unknown
//!   (`search_deg = [lo, hi]`).
//! - `[light]`: `polarization` = `"s"`, `"p"`, `"u"` or an s weight.
//! - `[bands]`: the band set for synthetic cubes and live runs (`irid fit`
//!   takes its bands from the cube header).
//! - `[measurement]`: the instrument — `noise_sigma` (reflectance noise σ),
//!   `reflectance_accuracy` (the reflectance scale's accuracy, a fraction
//!   of R), `level` (`auto`, `absolute`, `scaled`, `free`) and
//!   `band_shift` (`"auto"`, `"none"` or the filter's wavelength error in nm).
//! - `[truth]`: the synthetic ground truth (size, film index, thickness and
//!   angle fields, noise, seed) for `irid synth` and the synthetic camera.
//!
//! Parsing is strict: unknown keys and inconsistent values are errors that
//! name the field.

use crate::estimate::level::LevelMode;
use crate::optics::band::Band;
use crate::optics::dispersion::Dispersion;
use crate::optics::material::MaterialLibrary;
use crate::optics::Polarization;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Errors in a scene description.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file could not be read.
    #[error("cannot read scene file {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The TOML did not parse or did not match the schema.
    #[error("scene {origin}: {message}")]
    Parse {
        /// File name or `<embedded>`.
        origin: String,
        /// What is wrong, with the field.
        message: String,
    },
    /// A value that parses but makes no sense.
    #[error("scene field `{field}`: {message}")]
    Invalid {
        /// The dotted field name.
        field: String,
        /// What is wrong.
        message: String,
    },
}

fn invalid(field: &str, message: impl Into<String>) -> SceneError {
    SceneError::Invalid {
        field: field.to_string(),
        message: message.into(),
    }
}

/// A medium: constant `n`/`k`, or a named material.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MediumSpec {
    /// Real part of the index.
    pub n: Option<f64>,
    /// Extinction coefficient (k ≥ 0); only with `n`.
    pub k: Option<f64>,
    /// A built-in material name (e.g. `"MgF2-Dodge-o"`) or a `.yml` path.
    pub material: Option<String>,
}

impl MediumSpec {
    /// A constant real index.
    pub fn constant(n: f64) -> Self {
        MediumSpec {
            n: Some(n),
            k: None,
            material: None,
        }
    }

    /// Whether the spec names an index at all.
    pub fn is_given(&self) -> bool {
        self.n.is_some() || self.material.is_some()
    }

    /// Resolve to a dispersion model. `field` names the section in errors;
    /// `base` is the directory relative paths are taken from.
    pub fn resolve(&self, field: &str, base: &Path) -> Result<Dispersion, SceneError> {
        match (&self.n, &self.material) {
            (Some(_), Some(_)) => Err(invalid(field, "give either `n` or `material`, not both")),
            (None, None) => Err(invalid(field, "needs `n` or `material`")),
            (Some(n), None) => {
                let k = self.k.unwrap_or(0.0);
                if !(n.is_finite() && *n > 0.0) {
                    return Err(invalid(
                        &format!("{field}.n"),
                        format!("must be a positive number, not {n}"),
                    ));
                }
                if !(k.is_finite() && k >= 0.0) {
                    return Err(invalid(
                        &format!("{field}.k"),
                        format!("must be ≥ 0, not {k}"),
                    ));
                }
                Ok(Dispersion::Constant(crate::optics::Complex64::new(*n, k)))
            }
            (None, Some(name)) => {
                if self.k.is_some() {
                    return Err(invalid(
                        &format!("{field}.k"),
                        "`k` goes with `n`, not with `material`",
                    ));
                }
                let lower = name.to_ascii_lowercase();
                let is_path = lower.ends_with(".yml")
                    || lower.ends_with(".yaml")
                    || name.contains(['/', '\\']);
                let spec = if is_path && Path::new(name).is_relative() {
                    base.join(name).display().to_string()
                } else {
                    name.clone()
                };
                MaterialLibrary::builtin()
                    .with_dir(base)
                    .resolve(&spec)
                    .map(|m| m.dispersion)
                    .map_err(|e| invalid(&format!("{field}.material"), e.to_string()))
            }
        }
    }
}

/// The `[film]` section.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FilmSpec {
    /// Known index (never re-estimated when given).
    pub n: Option<f64>,
    /// Known extinction coefficient, with `n`.
    pub k: Option<f64>,
    /// Known material.
    pub material: Option<String>,
    /// Search range for an unknown index.
    pub search: Option<[f64; 2]>,
    /// Prior guess of an unknown index, used only to break a tie between
    /// indistinguishable twins.
    pub prior: Option<f64>,
    /// Thinnest film the estimator considers, nm (default 0: a bare substrate).
    pub min_thickness_nm: Option<f64>,
    /// Thickest film the estimator considers, nm (default: what the bands
    /// resolve, see `estimate::range`).
    pub max_thickness_nm: Option<f64>,
}

/// The `[measurement]` section: what is known about the instrument.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MeasurementSpec {
    /// Reflectance noise σ (default: measured by the camera's calibration,
    /// or estimated from the data without a model).
    pub noise_sigma: Option<f64>,
    /// Accuracy of the reflectance scale, a fraction of R (default 0 for
    /// cubes, see `irid fit` for spectrum tables): added to the noise in
    /// quadrature when fits are judged.
    pub reflectance_accuracy: Option<f64>,
    /// `auto`, `absolute`, `scaled` or `free` (default `auto`).
    pub level: Option<String>,
    /// The filter's wavelength calibration: `"auto"` (default: an
    /// image-wide shift of every band centre fitted where the data need
    /// it), `"none"`, or the shift in nm (the true centres are the
    /// nominal ones plus it).
    pub band_shift: Option<BandShiftSpec>,
}

/// `[measurement] band_shift` as written: a name or a number of nm.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(untagged)]
pub enum BandShiftSpec {
    /// A shift in nm.
    Nm(f64),
    /// `"auto"` or `"none"`.
    Name(String),
}

/// How the band centres are taken: as given, shifted by a known amount,
/// or with an image-wide shift fitted where the data need it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BandShift {
    /// Fitted where the data show it (`estimate::solver::band_shift`).
    Auto,
    /// Known: every true centre is the nominal one plus this many nm (0:
    /// the centres as given).
    Given(f64),
}

/// The largest band shift a scene may give, nm: past it the header's
/// wavelengths, not the filter's calibration, are wrong.
pub const MAX_BAND_SHIFT_GIVEN_NM: f64 = 50.0;

impl BandShiftSpec {
    /// Resolve a written shift (`field` names it in errors).
    pub fn resolve(&self) -> Result<BandShift, String> {
        match self {
            BandShiftSpec::Name(n) if n == "auto" => Ok(BandShift::Auto),
            BandShiftSpec::Name(n) if n == "none" => Ok(BandShift::Given(0.0)),
            BandShiftSpec::Name(n) => match n.trim().parse::<f64>() {
                Ok(v) => BandShiftSpec::Nm(v).resolve(),
                Err(_) => Err(format!("\"auto\", \"none\" or a shift in nm; not {n:?}")),
            },
            BandShiftSpec::Nm(v) if v.is_finite() && v.abs() <= MAX_BAND_SHIFT_GIVEN_NM => {
                Ok(BandShift::Given(*v))
            }
            BandShiftSpec::Nm(v) => Err(format!(
                "a shift within ±{MAX_BAND_SHIFT_GIVEN_NM} nm, not {v}"
            )),
        }
    }
}

/// The `[angle]` section.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AngleSpec {
    /// Known uniform incidence angle in degrees.
    pub deg: Option<f64>,
    /// Known per-pixel angle map (single-band EXR or ENVI, degrees).
    pub map: Option<PathBuf>,
    /// Search range for an unknown angle, degrees.
    pub search_deg: Option<[f64; 2]>,
}

/// The `[light]` section.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LightSpec {
    /// `s`, `p`, `u` or an s weight in \[0, 1\].
    #[serde(default = "default_pol")]
    pub polarization: toml::Value,
}

fn default_pol() -> toml::Value {
    toml::Value::String("s".into())
}

impl Default for LightSpec {
    fn default() -> Self {
        LightSpec {
            polarization: default_pol(),
        }
    }
}

/// The `[bands]` section: either a regular grid or explicit centres.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct BandsSpec {
    /// First centre, nm.
    pub start_nm: Option<f64>,
    /// Last centre, nm (inclusive).
    pub stop_nm: Option<f64>,
    /// Spacing, nm.
    pub step_nm: Option<f64>,
    /// Explicit centres, nm.
    pub centers_nm: Option<Vec<f64>>,
    /// Full width at half maximum of every band, nm (default: the spacing).
    pub fwhm_nm: Option<f64>,
}

/// A scalar field over the image, for synthetic truth.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Field {
    /// The same value everywhere.
    Constant(f64),
    /// Linear from the first column's value to the last column's.
    LinearX([f64; 2]),
    /// Linear from the first row's value to the last row's.
    LinearY([f64; 2]),
    /// `start + step · row`.
    Rows([f64; 2]),
    /// `start + step · column`.
    Columns([f64; 2]),
}

impl Field {
    /// The value at pixel (x, y) of a `width × height` image.
    pub fn at(&self, x: usize, y: usize, width: usize, height: usize) -> f64 {
        let frac = |i: usize, n: usize| {
            if n > 1 {
                i as f64 / (n - 1) as f64
            } else {
                0.0
            }
        };
        match *self {
            Field::Constant(v) => v,
            Field::LinearX([a, b]) => a + (b - a) * frac(x, width),
            Field::LinearY([a, b]) => a + (b - a) * frac(y, height),
            Field::Rows([a, s]) => a + s * y as f64,
            Field::Columns([a, s]) => a + s * x as f64,
        }
    }
}

/// The `[truth]` section: what a synthetic scene really is.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TruthSpec {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// True film index (when `[film]` leaves it unknown).
    pub film_n: Option<f64>,
    /// True film material (when `[film]` leaves it unknown).
    pub film_material: Option<String>,
    /// Film thickness field, nm.
    pub thickness_nm: Field,
    /// Incidence angle field, degrees (when `[angle]` gives no `deg`).
    pub angle_deg: Option<Field>,
    /// Gaussian reflectance noise σ.
    #[serde(default)]
    pub noise_sigma: f64,
    /// Seed of the noise generator.
    #[serde(default)]
    pub seed: u64,
}

/// A scene file as written.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    /// A label for summaries.
    pub name: Option<String>,
    /// Ambient medium (default air, n = 1).
    #[serde(default)]
    pub ambient: MediumSpec,
    /// Substrate.
    #[serde(default)]
    pub substrate: MediumSpec,
    /// Film.
    #[serde(default)]
    pub film: FilmSpec,
    /// Incidence angle.
    #[serde(default)]
    pub angle: AngleSpec,
    /// Illumination / analyser.
    #[serde(default)]
    pub light: LightSpec,
    /// Bands for synthetic cubes and live runs.
    #[serde(default)]
    pub bands: BandsSpec,
    /// The instrument: noise level and level model.
    #[serde(default)]
    pub measurement: MeasurementSpec,
    /// Synthetic ground truth.
    pub truth: Option<TruthSpec>,
}

/// Largest thickness bound a scene may set, nm.
pub const MAX_THICKNESS_LIMIT_NM: f64 = 100_000.0;

/// The paper's simulated cylinder (the default scene of the demo and the
/// reference scene of the benchmarks).
pub const PAPER_CYLINDER: &str = include_str!("../data/scenes/paper-cylinder.toml");

/// What the estimator may take as known about the film index.
#[derive(Clone, Debug, PartialEq)]
pub enum FilmKnowledge {
    /// Known: never re-estimated.
    Known(Dispersion),
    /// Unknown, constant over the object and over wavelength, in `search`.
    Unknown {
        /// Bounds of the search.
        search: (f64, f64),
        /// Tie-breaker between indistinguishable twins.
        prior: Option<f64>,
    },
}

/// What the estimator may take as known about the incidence angle.
#[derive(Clone, Debug, PartialEq)]
pub enum AngleKnowledge {
    /// One known angle for every pixel, radians.
    Uniform(f64),
    /// A known angle per pixel, degrees, row-major `width × height`.
    Map {
        /// Map width.
        width: usize,
        /// Map height.
        height: usize,
        /// Degrees.
        deg: Vec<f32>,
    },
    /// Unknown: estimated per pixel within `search` (radians).
    Unknown {
        /// Bounds, radians.
        search: (f64, f64),
    },
}

impl AngleKnowledge {
    /// The known angle of pixel (x, y) in radians, if any.
    pub fn known_at(&self, x: usize, y: usize) -> Option<f64> {
        match self {
            AngleKnowledge::Uniform(t) => Some(*t),
            // A NaN entry leaves that pixel's angle unknown.
            AngleKnowledge::Map { width, deg, .. } => deg
                .get(y * width + x)
                .filter(|d| d.is_finite())
                .map(|d| f64::from(*d).to_radians()),
            AngleKnowledge::Unknown { .. } => None,
        }
    }
}

/// A resolved scene: media as dispersion models, knowledge, bands, truth.
#[derive(Clone, Debug)]
pub struct Scene {
    /// Label.
    pub name: String,
    /// Ambient medium.
    pub ambient: Dispersion,
    /// Substrate.
    pub substrate: Dispersion,
    /// Film index knowledge.
    pub film: FilmKnowledge,
    /// Angle knowledge.
    pub angle: AngleKnowledge,
    /// Polarisation.
    pub polarization: Polarization,
    /// Bands of `[bands]`, if given.
    pub bands: Option<Vec<Band>>,
    /// Ground truth, if given.
    pub truth: Option<Truth>,
    /// Thinnest film the estimator considers, nm.
    pub min_thickness_nm: f64,
    /// Thickest film the estimator considers, nm; `None`: what the bands
    /// resolve (`estimate::range`).
    pub max_thickness_nm: Option<f64>,
    /// Reflectance noise σ, when known.
    pub noise_sigma: Option<f64>,
    /// Accuracy of the reflectance scale, a fraction of R (0: exact).
    pub reflectance_accuracy: f64,
    /// How the instrument's level is modelled.
    pub level: LevelMode,
    /// How the band centres are taken (the filter's wavelength calibration).
    pub band_shift: BandShift,
}

/// Resolved synthetic truth.
#[derive(Clone, Debug)]
pub struct Truth {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// The true film index.
    pub film: Dispersion,
    /// Thickness, nm.
    pub thickness_nm: Field,
    /// Angle, degrees.
    pub angle_deg: Field,
    /// Noise σ.
    pub noise_sigma: f64,
    /// Seed.
    pub seed: u64,
}

impl Scene {
    /// Parse and resolve a scene from TOML text; `origin` names it in errors
    /// and `base` is where relative paths start.
    pub fn from_toml(text: &str, origin: &str, base: &Path) -> Result<Scene, SceneError> {
        let file: SceneFile = toml::from_str(text).map_err(|e| SceneError::Parse {
            origin: origin.to_string(),
            message: e.to_string(),
        })?;
        Scene::resolve(&file, base)
    }

    /// Load a scene file.
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let base = path.parent().unwrap_or(Path::new("."));
        Scene::from_toml(&text, &path.display().to_string(), base)
    }

    /// The embedded default scene (the paper's cylinder).
    pub fn paper_cylinder() -> Scene {
        Scene::from_toml(PAPER_CYLINDER, "<embedded paper-cylinder>", Path::new("."))
            .expect("the embedded scene is valid (checked by a test)")
    }

    /// Resolve a parsed scene file.
    pub fn resolve(file: &SceneFile, base: &Path) -> Result<Scene, SceneError> {
        let ambient = if file.ambient.is_given() {
            file.ambient.resolve("ambient", base)?
        } else {
            Dispersion::constant(1.0)
        };
        let substrate = file.substrate.resolve("substrate", base)?;
        let f = &file.film;
        let film_spec = MediumSpec {
            n: f.n,
            k: f.k,
            material: f.material.clone(),
        };
        let film = if film_spec.is_given() {
            if f.search.is_some() {
                return Err(invalid(
                    "film.search",
                    "a known film index needs no search range",
                ));
            }
            FilmKnowledge::Known(film_spec.resolve("film", base)?)
        } else {
            if f.k.is_some() {
                return Err(invalid("film.k", "`k` needs `n`"));
            }
            let (lo, hi) = match f.search {
                Some([lo, hi]) => (lo, hi),
                None => (1.0, 2.5),
            };
            if !(lo.is_finite() && hi.is_finite() && lo >= 1.0 && hi > lo && hi <= 5.0) {
                return Err(invalid(
                    "film.search",
                    format!("must be [lo, hi] with 1 ≤ lo < hi ≤ 5, not [{lo}, {hi}]"),
                ));
            }
            if let Some(p) = f.prior {
                if !(p >= lo && p <= hi) {
                    return Err(invalid(
                        "film.prior",
                        format!("{p} lies outside the search range"),
                    ));
                }
            }
            FilmKnowledge::Unknown {
                search: (lo, hi),
                prior: f.prior,
            }
        };
        let max_thickness_nm = file.film.max_thickness_nm;
        if let Some(m) = max_thickness_nm {
            if !(m.is_finite() && m > 0.0 && m <= MAX_THICKNESS_LIMIT_NM) {
                return Err(invalid(
                    "film.max_thickness_nm",
                    format!("must lie in (0, {MAX_THICKNESS_LIMIT_NM}] nm, not {m}"),
                ));
            }
        }
        let min_thickness_nm = file.film.min_thickness_nm.unwrap_or(0.0);
        if !(min_thickness_nm.is_finite()
            && min_thickness_nm >= 0.0
            && max_thickness_nm.is_none_or(|m| min_thickness_nm < m))
        {
            return Err(invalid(
                "film.min_thickness_nm",
                format!("must be ≥ 0 and below max_thickness_nm, not {min_thickness_nm}"),
            ));
        }
        let noise_sigma = file.measurement.noise_sigma;
        if let Some(s) = noise_sigma {
            if !(s.is_finite() && s > 0.0 && s < 1.0) {
                return Err(invalid(
                    "measurement.noise_sigma",
                    format!("must lie in (0, 1), not {s}"),
                ));
            }
        }
        let reflectance_accuracy = file.measurement.reflectance_accuracy.unwrap_or(0.0);
        if !(reflectance_accuracy.is_finite() && (0.0..0.5).contains(&reflectance_accuracy)) {
            return Err(invalid(
                "measurement.reflectance_accuracy",
                format!("must lie in [0, 0.5), not {reflectance_accuracy}"),
            ));
        }
        let level = match &file.measurement.level {
            None => LevelMode::Auto,
            Some(l) => LevelMode::from_name(l).ok_or_else(|| {
                invalid(
                    "measurement.level",
                    format!("one of auto, absolute, scaled, free; not {l:?}"),
                )
            })?,
        };
        let band_shift = match &file.measurement.band_shift {
            None => BandShift::Auto,
            Some(b) => b
                .resolve()
                .map_err(|m| invalid("measurement.band_shift", m))?,
        };
        let a = &file.angle;
        let angle = match (a.deg, &a.map) {
            (Some(_), Some(_)) => return Err(invalid("angle", "give `deg` or `map`, not both")),
            (Some(deg), None) => {
                if !(0.0..90.0).contains(&deg) {
                    return Err(invalid(
                        "angle.deg",
                        format!("must lie in [0, 90), not {deg}"),
                    ));
                }
                AngleKnowledge::Uniform(deg.to_radians())
            }
            (None, Some(path)) => {
                let path = base.join(path);
                let (width, height, deg) = crate::io::angle_map::load_degrees(&path)
                    .map_err(|e| invalid("angle.map", e.to_string()))?;
                AngleKnowledge::Map { width, height, deg }
            }
            (None, None) => {
                let [lo, hi] = a.search_deg.unwrap_or([0.0, 80.0]);
                if !(lo >= 0.0 && hi > lo && hi < 90.0) {
                    return Err(invalid(
                        "angle.search_deg",
                        format!("must be [lo, hi] with 0 ≤ lo < hi < 90, not [{lo}, {hi}]"),
                    ));
                }
                AngleKnowledge::Unknown {
                    search: (lo.to_radians(), hi.to_radians()),
                }
            }
        };
        let polarization = match &file.light.polarization {
            toml::Value::String(s) => Polarization::parse(s),
            toml::Value::Float(w) => Polarization::parse(&w.to_string()),
            toml::Value::Integer(w) => Polarization::parse(&w.to_string()),
            other => Err(format!("not a polarization: {other}")),
        }
        .map_err(|m| invalid("light.polarization", m))?;
        let bands = resolve_bands(&file.bands)?;
        let truth = match &file.truth {
            None => None,
            Some(t) => Some(resolve_truth(t, &film, &angle, base)?),
        };
        Ok(Scene {
            name: file.name.clone().unwrap_or_else(|| "scene".into()),
            ambient,
            substrate,
            film,
            angle,
            polarization,
            bands,
            truth,
            min_thickness_nm,
            max_thickness_nm,
            noise_sigma,
            reflectance_accuracy,
            level,
            band_shift,
        })
    }
}

fn resolve_bands(b: &BandsSpec) -> Result<Option<Vec<Band>>, SceneError> {
    let centers: Vec<f64> = match (&b.centers_nm, b.start_nm, b.stop_nm, b.step_nm) {
        (None, None, None, None) => return Ok(None),
        (Some(c), None, None, None) => c.clone(),
        (None, Some(start), Some(stop), Some(step)) => {
            if !(step > 0.0 && stop >= start && start > 0.0) || ((stop - start) / step) > 10_000.0 {
                return Err(invalid(
                    "bands",
                    "need 0 < start_nm ≤ stop_nm and step_nm > 0",
                ));
            }
            let n = ((stop - start) / step + 1e-9).floor() as usize + 1;
            (0..n).map(|i| start + step * i as f64).collect()
        }
        _ => {
            return Err(invalid(
                "bands",
                "give either centers_nm or all of start_nm, stop_nm, step_nm",
            ))
        }
    };
    if centers.len() < 3 {
        return Err(invalid("bands", "need at least 3 bands"));
    }
    if centers.iter().any(|c| !(c.is_finite() && *c > 0.0)) {
        return Err(invalid(
            "bands.centers_nm",
            "every centre must be a positive number",
        ));
    }
    let default_fwhm = {
        let mut s: Vec<f64> = centers.clone();
        s.sort_by(f64::total_cmp);
        s.windows(2)
            .map(|w| w[1] - w[0])
            .fold(f64::INFINITY, f64::min)
    };
    let fwhm = b.fwhm_nm.unwrap_or(default_fwhm);
    if !(fwhm.is_finite() && fwhm >= 0.0) {
        return Err(invalid("bands.fwhm_nm", "must be ≥ 0"));
    }
    Ok(Some(
        centers
            .into_iter()
            .map(|c| Band {
                center_nm: c,
                fwhm_nm: fwhm,
            })
            .collect(),
    ))
}

fn resolve_truth(
    t: &TruthSpec,
    film: &FilmKnowledge,
    angle: &AngleKnowledge,
    base: &Path,
) -> Result<Truth, SceneError> {
    if t.width == 0 || t.height == 0 || t.width.saturating_mul(t.height) > 1 << 28 {
        return Err(invalid(
            "truth",
            "width and height must be positive and modest",
        ));
    }
    let film = match (t.film_n, &t.film_material, film) {
        (Some(n), None, _) => MediumSpec::constant(n).resolve("truth.film_n", base)?,
        (None, Some(m), _) => MediumSpec {
            material: Some(m.clone()),
            ..Default::default()
        }
        .resolve("truth.film_material", base)?,
        (None, None, FilmKnowledge::Known(d)) => d.clone(),
        (None, None, FilmKnowledge::Unknown { .. }) => {
            return Err(invalid(
                "truth.film_n",
                "the film index is unknown to the estimator, so the truth must give it",
            ))
        }
        (Some(_), Some(_), _) => {
            return Err(invalid("truth", "give film_n or film_material, not both"))
        }
    };
    let angle_deg = match (&t.angle_deg, angle) {
        (Some(f), _) => f.clone(),
        (None, AngleKnowledge::Uniform(r)) => Field::Constant(r.to_degrees()),
        (None, _) => {
            return Err(invalid(
                "truth.angle_deg",
                "needed unless [angle] gives `deg`",
            ))
        }
    };
    if !(t.noise_sigma.is_finite() && t.noise_sigma >= 0.0) {
        return Err(invalid("truth.noise_sigma", "must be ≥ 0"));
    }
    Ok(Truth {
        width: t.width,
        height: t.height,
        film,
        thickness_nm: t.thickness_nm.clone(),
        angle_deg,
        noise_sigma: t.noise_sigma,
        seed: t.seed,
    })
}
