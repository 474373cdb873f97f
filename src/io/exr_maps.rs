//! OpenEXR files of per-pixel f32 channels: the parameter maps of `irid fit`,
//! the ground truth of `irid synth`, angle maps.
//!
//! One single-part scan-line file, ZIP-compressed (lossless), every channel
//! f32, with irid's metadata as text attributes named `irid.*`. Attribute
//! text is kept to ASCII (OpenEXR text is Latin-1 and the `exr` crate
//! panics beyond U+00FF), so notes are transliterated before writing.
//!
//! Readers look channels up by name: files come back with channels sorted
//! alphabetically, and files written by other tools may hold extra ones.

use super::IoError;
use crate::estimate::maps::MapMeta;
use crate::estimate::{ParamMaps, Reason};
use exr::prelude::*;
// The prelude's `Result` alias would shadow std's.
use std::path::Path;
use std::result::Result;

/// Attribute-name prefix of irid's metadata.
pub const ATTR_PREFIX: &str = "irid.";

/// The unit of each [`ParamMaps`] channel, as written to `irid.units.<channel>`.
pub const MAP_UNITS: [(&str, &str); 8] = [
    ("thickness_nm", "nm"),
    ("n_film", "1 (refractive index)"),
    ("theta_deg", "degrees"),
    ("sigma_thickness_nm", "nm (1 sigma)"),
    ("sigma_theta_deg", "degrees (1 sigma)"),
    ("residual_rms", "reflectance (RMS)"),
    ("valid", "1 valid, 0 invalid"),
    ("reason", "code, see irid.reason_codes"),
];

/// A set of named f32 channels of one size, with text attributes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Channels {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// `(name, row-major values)`.
    pub channels: Vec<(String, Vec<f32>)>,
    /// Text attributes `(name, value)`; other attribute types are read as
    /// their debug text.
    pub attributes: Vec<(String, String)>,
}

impl Channels {
    /// A solver's maps as channels ([`ParamMaps::channels`], metadata as
    /// `irid.*` attributes).
    pub fn from_maps(maps: &ParamMaps) -> Channels {
        Channels {
            width: maps.width,
            height: maps.height,
            channels: maps
                .channels()
                .iter()
                .map(|(n, v)| (n.to_string(), v.to_vec()))
                .collect(),
            attributes: map_attributes(&maps.meta),
        }
    }

    /// The channel called `name`.
    pub fn channel(&self, name: &str) -> Option<&[f32]> {
        self.channels
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_slice())
    }

    /// The text attribute called `name`.
    pub fn attribute(&self, name: &str) -> Option<&str> {
        self.attributes
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }
}

/// ASCII rendering of `s`: the few non-ASCII symbols irid's own messages use
/// are spelled out, anything else becomes `?`.
pub fn to_ascii(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            c if c.is_ascii() => out.push(c),
            'σ' => out.push_str("sigma"),
            'θ' => out.push_str("theta"),
            'λ' => out.push_str("lambda"),
            'χ' => out.push_str("chi"),
            'Δ' => out.push_str("Delta "),
            '²' => out.push_str("^2"),
            '±' => out.push_str("+-"),
            'µ' | 'μ' => out.push('u'),
            '°' => out.push_str(" deg"),
            '≥' => out.push_str(">="),
            '≤' => out.push_str("<="),
            '≈' => out.push('~'),
            '↔' => out.push_str("<->"),
            '→' => out.push_str("->"),
            '·' | '×' => out.push('*'),
            '−' | '–' | '—' => out.push('-'),
            '…' => out.push_str("..."),
            _ => out.push('?'),
        }
    }
    out
}

/// Write channels to an EXR file. Every channel must hold `width × height`
/// values; names and attribute values are made ASCII.
pub fn write_channels(path: &Path, data: &Channels) -> Result<(), IoError> {
    let (w, h) = (data.width, data.height);
    if w == 0 || h == 0 {
        return Err(IoError::format(
            path,
            format!("cannot write an empty {w} × {h} image"),
        ));
    }
    if data.channels.is_empty() {
        return Err(IoError::format(path, "no channels to write"));
    }
    let mut list: SmallVec<[AnyChannel<FlatSamples>; 4]> = SmallVec::new();
    for (name, values) in &data.channels {
        if values.len() != w * h {
            return Err(IoError::format(
                path,
                format!(
                    "channel `{name}` has {} values for a {w} × {h} image",
                    values.len()
                ),
            ));
        }
        let text = Text::new_or_none(to_ascii(name))
            .ok_or_else(|| IoError::format(path, format!("channel name {name:?}")))?;
        list.push(AnyChannel::new(text, FlatSamples::F32(values.clone())));
    }
    let mut attrs = LayerAttributes::default();
    for (name, value) in &data.attributes {
        let (Some(k), Some(v)) = (
            Text::new_or_none(to_ascii(name)),
            Text::new_or_none(to_ascii(value)),
        ) else {
            // to_ascii leaves only ASCII, which Text always accepts.
            continue;
        };
        attrs.other.insert(k, AttributeValue::Text(v));
    }
    let encoding = Encoding {
        compression: Compression::ZIP16,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    let layer = Layer::new((w, h), attrs, encoding, AnyChannels::sort(list));
    // Through a temporary file (see `io::atomic`): a crash mid-write never
    // leaves a truncated map under the final name.
    let image = Image::from_layer(layer);
    let mut exr_failure = None;
    let written = super::atomic::write_atomically(path, super::atomic::Overwrite::Replace, |w| {
        image.write().to_buffered(w).map_err(|e| match e {
            exr::error::Error::Io(io) => io,
            other => {
                let message = other.to_string();
                exr_failure = Some(other);
                std::io::Error::other(message)
            }
        })
    });
    match (written, exr_failure) {
        (Err(_), Some(e)) => Err(exr_error(path, e)),
        (r, _) => r,
    }
}

fn exr_error(path: &Path, e: exr::error::Error) -> IoError {
    match e {
        exr::error::Error::Io(io) => IoError::os(path, io),
        other => IoError::format(path, format!("OpenEXR: {other}")),
    }
}

/// Read every channel of the first layer of an EXR file as f32.
pub fn read_channels(path: &Path) -> Result<Channels, IoError> {
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(|e| exr_error(path, e))?;
    let layer = &image.layer_data;
    let (w, h) = (layer.size.width(), layer.size.height());
    let channels = layer
        .channel_data
        .list
        .iter()
        .map(|c| {
            (
                c.name.to_string(),
                c.sample_data.values_as_f32().collect::<Vec<f32>>(),
            )
        })
        .collect();
    let mut attributes: Vec<(String, String)> = layer
        .attributes
        .other
        .iter()
        .chain(image.attributes.other.iter())
        .map(|(k, v)| {
            let value = match v {
                AttributeValue::Text(t) => t.to_string(),
                other => format!("{other:?}"),
            };
            (k.to_string(), value)
        })
        .collect();
    attributes.sort();
    Ok(Channels {
        width: w,
        height: h,
        channels,
        attributes,
    })
}

/// The `irid.reason_codes` legend: `0=ok; 1=non-finite input; …`.
pub fn reason_legend() -> String {
    Reason::ALL
        .iter()
        .map(|r| format!("{}={}", *r as u8, r.name()))
        .collect::<Vec<_>>()
        .join("; ")
}

fn join_nm(v: &[f64]) -> String {
    v.iter()
        .map(|x| format!("{x}"))
        .collect::<Vec<_>>()
        .join(",")
}

/// The attributes written with parameter maps.
pub fn map_attributes(meta: &MapMeta) -> Vec<(String, String)> {
    let a = |k: &str, v: String| (format!("{ATTR_PREFIX}{k}"), v);
    let mut out = vec![
        a("version", crate::VERSION.to_string()),
        a("mode", meta.mode.clone()),
        a("wavelengths_nm", join_nm(&meta.wavelengths_nm)),
        a("fwhm_nm", join_nm(&meta.fwhm_nm)),
        a("n_film", format!("{}", meta.n_film)),
        a("n_film_sigma", format!("{}", meta.n_film_sigma)),
        a("n_film_estimated", format!("{}", meta.n_film_estimated)),
        a("n_film_note", meta.n_film_note.clone()),
        a("polarization", meta.polarization.clone()),
        a("reason_codes", reason_legend()),
    ];
    for (k, v) in &meta.quality {
        out.push(a(k, v.clone()));
    }
    for (ch, unit) in MAP_UNITS {
        out.push(a(&format!("units.{ch}"), unit.to_string()));
    }
    out
}

/// Write parameter maps to one EXR file (channels named as in
/// [`ParamMaps::channels`], metadata as `irid.*` attributes).
pub fn write_maps(path: &Path, maps: &ParamMaps) -> Result<(), IoError> {
    let data = Channels::from_maps(maps);
    write_channels(path, &data)
}

fn parse_nm_list(path: &Path, field: &str, v: Option<&str>) -> Result<Vec<f64>, IoError> {
    match v.map(str::trim) {
        None | Some("") => Ok(Vec::new()),
        Some(v) => v
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| IoError::field(path, field, "not a comma-separated list of numbers")),
    }
}

/// Read parameter maps written by [`write_maps`] (or any EXR holding the
/// eight channels). Missing metadata attributes read as defaults.
pub fn read_maps(path: &Path) -> Result<ParamMaps, IoError> {
    let c = read_channels(path)?;
    let mut maps = ParamMaps::new(c.width, c.height);
    let get = |name: &str| -> Result<Vec<f32>, IoError> {
        c.channel(name).map(<[f32]>::to_vec).ok_or_else(|| {
            IoError::format(path, format!("no channel `{name}` (not an irid map file?)"))
        })
    };
    maps.thickness_nm = get("thickness_nm")?;
    maps.n_film = get("n_film")?;
    maps.theta_deg = get("theta_deg")?;
    maps.sigma_thickness_nm = get("sigma_thickness_nm")?;
    maps.sigma_theta_deg = get("sigma_theta_deg")?;
    maps.residual_rms = get("residual_rms")?;
    maps.valid = get("valid")?;
    maps.reason = get("reason")?;
    let attr = |k: &str| c.attribute(&format!("{ATTR_PREFIX}{k}"));
    let num = |k: &str| -> Result<f64, IoError> {
        match attr(k) {
            None => Ok(f64::NAN),
            Some(v) => v.trim().parse().map_err(|_| {
                IoError::field(
                    path,
                    &format!("{ATTR_PREFIX}{k}"),
                    format!("not a number: {v:?}"),
                )
            }),
        }
    };
    maps.meta = MapMeta {
        mode: attr("mode").unwrap_or_default().to_string(),
        wavelengths_nm: parse_nm_list(path, "irid.wavelengths_nm", attr("wavelengths_nm"))?,
        fwhm_nm: parse_nm_list(path, "irid.fwhm_nm", attr("fwhm_nm"))?,
        n_film: num("n_film")?,
        n_film_sigma: num("n_film_sigma")?,
        n_film_estimated: attr("n_film_estimated") == Some("true"),
        n_film_note: attr("n_film_note").unwrap_or_default().to_string(),
        polarization: attr("polarization").unwrap_or_default().to_string(),
        quality: crate::estimate::maps::QUALITY_KEYS
            .iter()
            .chain(&crate::estimate::maps::QUALITY_OPTIONAL_KEYS)
            .filter_map(|k| attr(k).map(|v| (k.to_string(), v.to_string())))
            .collect(),
    };
    Ok(maps)
}

/// Write one f32 channel (an angle map, a truth field).
pub fn write_single(
    path: &Path,
    name: &str,
    width: usize,
    height: usize,
    values: &[f32],
) -> Result<(), IoError> {
    write_channels(
        path,
        &Channels {
            width,
            height,
            channels: vec![(name.to_string(), values.to_vec())],
            attributes: vec![(format!("{ATTR_PREFIX}version"), crate::VERSION.to_string())],
        },
    )
}

/// Read one channel: the one called `preferred` if present, else the only
/// channel of the file. `(width, height, values)`.
pub fn read_single(path: &Path, preferred: &str) -> Result<(usize, usize, Vec<f32>), IoError> {
    let mut c = read_channels(path)?;
    let i = match c.channels.iter().position(|(n, _)| n == preferred) {
        Some(i) => i,
        None if c.channels.len() == 1 => 0,
        None => {
            let names: Vec<&str> = c.channels.iter().map(|(n, _)| n.as_str()).collect();
            return Err(IoError::format(
                path,
                format!(
                    "{} channels ({}) and none called `{preferred}`",
                    names.len(),
                    names.join(", ")
                ),
            ));
        }
    };
    let (_, values) = c.channels.swap_remove(i);
    Ok((c.width, c.height, values))
}
