//! Named materials and a library that loads refractiveindex.info YAML files.
//!
//! A [`Material`] is a name and a [`Dispersion`]. Materials come from
//! refractiveindex.info database files (CC0; format described at
//! <https://github.com/polyanskiy/refractiveindex.info-database>): a `DATA:`
//! list whose entries are `type: formula N` (with `wavelength_range` and
//! `coefficients`) or `type: tabulated nk | tabulated n | tabulated k` (with
//! `data` rows), wavelengths in **µm** (converted here to nm). Supported
//! combinations: one formula or one table for `n` (optionally with `k`), plus
//! optionally one `tabulated k`. Formulas 1–2 map onto [`Dispersion::Sellmeier`],
//! 3–7 onto [`Dispersion::Formula`]; formulas 8–9 are refused.
//!
//! The files in the repository's `data/refractive-index/` are embedded in the
//! binary ([`BUILTIN`]), so a name like `"MgF2-Dodge-o"` resolves from any
//! working directory; [`MaterialLibrary::resolve`] also accepts a path to a
//! `.yml` file, or a name found in an extra directory.
//!
//! Promises: parsing never panics; every error names the file (or
//! `builtin:<name>`) and the field (`DATA[1].coefficients`, `DATA[0].data
//! row 12`), and a material refuses wavelengths outside its file's range.
//! This is the only module of `optics` that touches the file system.

use super::dispersion::{Dispersion, FormulaKind, OpticsError};
use super::Complex64;
use std::path::{Path, PathBuf};
use yaml_rust2::{Yaml, YamlLoader};

/// The materials embedded in the binary: `(name, YAML text)`.
pub const BUILTIN: &[(&str, &str)] = &[
    (
        "Al2O3-Malitson-o",
        include_str!("../../data/refractive-index/Al2O3-Malitson-o.yml"),
    ),
    (
        "H2O-Hale",
        include_str!("../../data/refractive-index/H2O-Hale.yml"),
    ),
    (
        "MgF2-Dodge-o",
        include_str!("../../data/refractive-index/MgF2-Dodge-o.yml"),
    ),
    (
        "PET-Zhang",
        include_str!("../../data/refractive-index/PET-Zhang.yml"),
    ),
    (
        "Si-Green-2008",
        include_str!("../../data/refractive-index/Si-Green-2008.yml"),
    ),
    (
        "Si3N4-Luke",
        include_str!("../../data/refractive-index/Si3N4-Luke.yml"),
    ),
    (
        "SiO2-Malitson",
        include_str!("../../data/refractive-index/SiO2-Malitson.yml"),
    ),
    (
        "TiO2-Devore-o",
        include_str!("../../data/refractive-index/TiO2-Devore-o.yml"),
    ),
];

/// The repository's material directory at compile time.
pub const DATA_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/refractive-index");

/// A named optical material.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    /// Name (file stem for files, e.g. `MgF2-Dodge-o`).
    pub name: String,
    /// Its dispersion model.
    pub dispersion: Dispersion,
}

fn file_err(file: &str, field: impl Into<String>, message: impl Into<String>) -> OpticsError {
    OpticsError::File {
        file: file.to_string(),
        field: field.into(),
        message: message.into(),
    }
}

/// A scalar YAML value as text (`0.2 7.0` is a string, `5.913` a real).
fn scalar_text(y: &Yaml) -> Option<String> {
    match y {
        Yaml::String(s) | Yaml::Real(s) => Some(s.clone()),
        Yaml::Integer(i) => Some(i.to_string()),
        _ => None,
    }
}

fn numbers(text: &str, file: &str, field: &str) -> Result<Vec<f64>, OpticsError> {
    text.split_whitespace()
        .map(|t| {
            t.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| file_err(file, field, format!("{t:?} is not a finite number")))
        })
        .collect()
}

/// Rows of a `data` block: each row `λ[µm] v1 [v2]` with `cols` values after λ.
fn table(
    text: &str,
    cols: usize,
    file: &str,
    field: &str,
) -> Result<(Vec<f64>, Vec<Vec<f64>>), OpticsError> {
    let mut wl = Vec::new();
    let mut vals = vec![Vec::new(); cols];
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let row_field = format!("{field} row {}", i + 1);
        let v = numbers(line, file, &row_field)?;
        if v.len() != cols + 1 {
            return Err(file_err(
                file,
                row_field,
                format!(
                    "expected {} numbers (λ in µm and {cols} values), got {}",
                    cols + 1,
                    v.len()
                ),
            ));
        }
        wl.push(v[0] * 1e3);
        for (c, x) in vals.iter_mut().zip(&v[1..]) {
            c.push(*x);
        }
    }
    Ok((wl, vals))
}

impl Material {
    /// A material with the given model.
    pub fn new(name: impl Into<String>, dispersion: Dispersion) -> Self {
        Material {
            name: name.into(),
            dispersion,
        }
    }

    /// The complex index at `wavelength_nm`; errors name the material.
    pub fn index_at(&self, wavelength_nm: f64) -> Result<Complex64, OpticsError> {
        self.dispersion.index_named(wavelength_nm, &self.name)
    }

    /// Parse a refractiveindex.info YAML text. `name` is used for the
    /// material and, in errors, as the file name.
    pub fn from_yaml_str(name: &str, text: &str) -> Result<Material, OpticsError> {
        let dispersion = parse_yaml(name, text)?;
        Ok(Material::new(name, dispersion))
    }

    /// Load a refractiveindex.info YAML file; the material is named after the
    /// file stem, and errors name the path.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Material, OpticsError> {
        let path = path.as_ref();
        let shown = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|e| file_err(&shown, "-", format!("cannot read: {e}")))?;
        let dispersion = parse_yaml(&shown, &text)?;
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| shown.clone());
        Ok(Material::new(name, dispersion))
    }
}

fn parse_yaml(file: &str, text: &str) -> Result<Dispersion, OpticsError> {
    let docs = YamlLoader::load_from_str(text)
        .map_err(|e| file_err(file, "-", format!("not valid YAML: {e}")))?;
    let doc = docs
        .first()
        .ok_or_else(|| file_err(file, "-", "empty file"))?;
    let data = match &doc["DATA"] {
        Yaml::Array(a) if !a.is_empty() => a,
        Yaml::Array(_) => return Err(file_err(file, "DATA", "empty list")),
        Yaml::BadValue => return Err(file_err(file, "DATA", "missing")),
        _ => return Err(file_err(file, "DATA", "must be a list of entries")),
    };
    let mut n_model: Option<Dispersion> = None;
    let mut k_model: Option<Dispersion> = None;
    for (i, entry) in data.iter().enumerate() {
        let at = |f: &str| format!("DATA[{i}].{f}");
        let kind = scalar_text(&entry["type"])
            .ok_or_else(|| file_err(file, at("type"), "missing or not text"))?;
        let kind = kind.trim();
        let set = |slot: &mut Option<Dispersion>, model: Dispersion, what: &str| {
            if slot.is_some() {
                Err(file_err(
                    file,
                    at("type"),
                    format!("a second source of {what} is not supported"),
                ))
            } else {
                *slot = Some(model);
                Ok(())
            }
        };
        if let Some(num) = kind.strip_prefix("formula") {
            let num: u8 = num
                .trim()
                .parse()
                .map_err(|_| file_err(file, at("type"), format!("unknown type {kind:?}")))?;
            let coef_text = scalar_text(&entry["coefficients"]).ok_or_else(|| {
                file_err(file, at("coefficients"), "missing or not a list of numbers")
            })?;
            let coefs = numbers(&coef_text, file, &at("coefficients"))?;
            let model = match num {
                1 => Dispersion::sellmeier_formula1(&coefs),
                2 => Dispersion::sellmeier_formula2(&coefs),
                3 => Dispersion::formula(FormulaKind::Polynomial, coefs),
                4 => Dispersion::formula(FormulaKind::RefractiveIndexInfo, coefs),
                5 => Dispersion::formula(FormulaKind::Cauchy, coefs),
                6 => Dispersion::formula(FormulaKind::Gases, coefs),
                7 => Dispersion::formula(FormulaKind::Herzberger, coefs),
                _ => {
                    return Err(file_err(
                        file,
                        at("type"),
                        format!("formula {num} is not supported (1–7 are)"),
                    ));
                }
            }
            .map_err(|e| file_err(file, at("coefficients"), e.to_string()))?;
            let range_text = scalar_text(&entry["wavelength_range"]).ok_or_else(|| {
                file_err(
                    file,
                    at("wavelength_range"),
                    "missing (a formula needs its valid range)",
                )
            })?;
            let range = numbers(&range_text, file, &at("wavelength_range"))?;
            let [lo, hi] = range[..] else {
                return Err(file_err(
                    file,
                    at("wavelength_range"),
                    format!("expected two numbers (µm), got {}", range.len()),
                ));
            };
            let model = model
                .with_range(lo * 1e3, hi * 1e3)
                .map_err(|e| file_err(file, at("wavelength_range"), e.to_string()))?;
            set(&mut n_model, model, "n")?;
        } else if let Some(cols) = kind.strip_prefix("tabulated") {
            let data_text = scalar_text(&entry["data"])
                .ok_or_else(|| file_err(file, at("data"), "missing or not a text block"))?;
            let cols = cols.trim();
            let build = |r: Result<Dispersion, OpticsError>| {
                r.map_err(|e| file_err(file, at("data"), e.to_string()))
            };
            match cols {
                "nk" => {
                    let (wl, v) = table(&data_text, 2, file, &at("data"))?;
                    let [n, k] = <[Vec<f64>; 2]>::try_from(v)
                        .map_err(|_| file_err(file, at("data"), "internal column count"))?;
                    set(&mut n_model, build(Dispersion::tabulated(wl, n, k))?, "n")?;
                }
                "n" => {
                    let (wl, mut v) = table(&data_text, 1, file, &at("data"))?;
                    let n = v.pop().unwrap_or_default();
                    set(&mut n_model, build(Dispersion::tabulated_n(wl, n))?, "n")?;
                }
                "k" => {
                    let (wl, mut v) = table(&data_text, 1, file, &at("data"))?;
                    let k = v.pop().unwrap_or_default();
                    set(&mut k_model, build(Dispersion::tabulated_k(wl, k))?, "k")?;
                }
                _ => return Err(file_err(file, at("type"), format!("unknown type {kind:?}"))),
            }
        } else {
            return Err(file_err(file, at("type"), format!("unknown type {kind:?}")));
        }
    }
    match (n_model, k_model) {
        (Some(n), None) => Ok(n),
        (Some(n), Some(k)) => {
            Dispersion::combined(n, k).map_err(|e| file_err(file, "DATA", e.to_string()))
        }
        (None, _) => Err(file_err(file, "DATA", "gives no real index n (only k)")),
    }
}

/// Resolves material names and paths to [`Material`]s: embedded built-ins
/// first, then `<name>.yml` in the library's directories.
#[derive(Clone, Debug)]
pub struct MaterialLibrary {
    dirs: Vec<PathBuf>,
}

impl Default for MaterialLibrary {
    /// The built-ins plus the repository's `data/refractive-index/` (where it
    /// still exists at run time: a development checkout).
    fn default() -> Self {
        MaterialLibrary {
            dirs: vec![PathBuf::from(DATA_DIR)],
        }
    }
}

impl MaterialLibrary {
    /// Only the embedded built-ins.
    pub fn builtin() -> Self {
        MaterialLibrary { dirs: Vec::new() }
    }

    /// Add a directory searched for `<name>.yml` after the built-ins and the
    /// directories already added.
    pub fn with_dir(mut self, dir: impl Into<PathBuf>) -> Self {
        self.dirs.push(dir.into());
        self
    }

    /// Names of the embedded materials.
    pub fn builtin_names() -> impl Iterator<Item = &'static str> {
        BUILTIN.iter().map(|(n, _)| *n)
    }

    /// A material by name: an embedded one (exact name, else ASCII
    /// case-insensitive), else `<name>.yml` / `<name>.yaml` in a directory.
    pub fn get(&self, name: &str) -> Result<Material, OpticsError> {
        let builtin = BUILTIN
            .iter()
            .find(|(n, _)| *n == name)
            .or_else(|| BUILTIN.iter().find(|(n, _)| n.eq_ignore_ascii_case(name)));
        if let Some((n, text)) = builtin {
            let mut m = Material::from_yaml_str(&format!("builtin:{n}"), text)?;
            m.name = (*n).to_string();
            return Ok(m);
        }
        if !name.is_empty() && !name.contains(['/', '\\']) && name != "." && name != ".." {
            for dir in &self.dirs {
                for ext in ["yml", "yaml"] {
                    let p = dir.join(format!("{name}.{ext}"));
                    if p.is_file() {
                        return Material::from_file(&p);
                    }
                }
            }
        }
        let known: Vec<&str> = Self::builtin_names().collect();
        Err(OpticsError::Invalid(format!(
            "unknown material {name:?}: not a built-in ({}) nor a .yml file in {:?}",
            known.join(", "),
            self.dirs
        )))
    }

    /// A built-in or library name, or a path to a refractiveindex.info file
    /// (anything ending in `.yml`/`.yaml` or containing a path separator).
    pub fn resolve(&self, spec: &str) -> Result<Material, OpticsError> {
        let spec = spec.trim();
        let lower = spec.to_ascii_lowercase();
        if lower.ends_with(".yml") || lower.ends_with(".yaml") || spec.contains(['/', '\\']) {
            return Material::from_file(spec);
        }
        self.get(spec)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_builtin_parses_and_evaluates_in_its_range() {
        for (name, _) in BUILTIN {
            let m = MaterialLibrary::builtin().get(name).unwrap();
            let (lo, hi) = m.dispersion.range_nm().unwrap();
            for t in [0.0, 0.37, 1.0] {
                let l = lo + t * (hi - lo);
                let n = m.index_at(l).unwrap();
                assert!(
                    n.re > 1.0 && n.re < 7.0 && n.im >= 0.0,
                    "{name} at {l}: {n}"
                );
            }
            assert!(matches!(
                m.index_at(hi * 1.01),
                Err(OpticsError::OutOfRange { .. })
            ));
        }
    }
}
