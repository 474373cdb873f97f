//! ENVI spectral cubes: a text header (`cube.hdr`) beside a raw binary file.
//!
//! Reading accepts what ENVI and Spectral Python write: the `ENVI` magic on
//! the first line, case-insensitive keys, `;` comments, `{…}` values over
//! several lines; data types 1 (u8), 2 (i16), 3 (i32), 4 (f32), 5 (f64),
//! 12 (u16) and 13 (u32); interleave `bsq`, `bil`, `bip`; either byte order;
//! `header offset`; `wavelength` and `fwhm` in any of the usual units
//! (converted to nm); `reflectance scale factor`; `data ignore value`.
//!
//! The binary file is read once, in one piece, and converted to
//! band-sequential f32 with the header's byte order, whatever the
//! interleave. Every problem with a header or a data file is an
//! [`IoError`] naming the file and the field; no file content can make
//! this module panic.
//!
//! Writing produces a header like Spectral Python's (`wavelength units =
//! Nanometers`, `wavelength`, `fwhm`) and a raw file, f32 little-endian
//! band-sequential unless [`WriteOptions`] say otherwise.

use super::IoError;
use crate::estimate::Cube;
use crate::optics::band::Band;
use std::fmt::Write as _;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

/// Largest header irid reads: a bigger "header" is almost surely the data
/// file passed by mistake.
const MAX_HEADER_BYTES: u64 = 16 << 20;

/// Extensions tried, in order, for the binary file beside `name.hdr` after
/// `name` itself.
const DATA_EXTENSIONS: [&str; 6] = ["img", "raw", "bsq", "bil", "bip", "dat"];

/// ENVI `data type` codes irid reads and writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DataType {
    /// 1: unsigned 8-bit.
    U8,
    /// 2: signed 16-bit.
    I16,
    /// 3: signed 32-bit.
    I32,
    /// 4: 32-bit float.
    F32,
    /// 5: 64-bit float.
    F64,
    /// 12: unsigned 16-bit.
    U16,
    /// 13: unsigned 32-bit.
    U32,
}

impl DataType {
    /// Every supported type.
    pub const ALL: [DataType; 7] = [
        DataType::U8,
        DataType::I16,
        DataType::I32,
        DataType::F32,
        DataType::F64,
        DataType::U16,
        DataType::U32,
    ];

    /// The ENVI code.
    pub fn code(self) -> u32 {
        match self {
            DataType::U8 => 1,
            DataType::I16 => 2,
            DataType::I32 => 3,
            DataType::F32 => 4,
            DataType::F64 => 5,
            DataType::U16 => 12,
            DataType::U32 => 13,
        }
    }

    /// The type with this ENVI code, if irid supports it.
    pub fn from_code(code: u32) -> Option<DataType> {
        DataType::ALL.into_iter().find(|t| t.code() == code)
    }

    /// Bytes per sample.
    pub fn size(self) -> usize {
        match self {
            DataType::U8 => 1,
            DataType::I16 | DataType::U16 => 2,
            DataType::I32 | DataType::U32 | DataType::F32 => 4,
            DataType::F64 => 8,
        }
    }

    /// Whether the type stores integers (written with a scale factor).
    pub fn is_integer(self) -> bool {
        !matches!(self, DataType::F32 | DataType::F64)
    }

    /// Parse a code (`4`) or a name (`f32`, `u16`, …), as on the command line.
    pub fn parse(text: &str) -> Result<DataType, String> {
        let t = text.trim().to_ascii_lowercase();
        let by_name = match t.as_str() {
            "u8" | "byte" => Some(DataType::U8),
            "i16" | "int16" => Some(DataType::I16),
            "i32" | "int32" => Some(DataType::I32),
            "f32" | "float" | "float32" => Some(DataType::F32),
            "f64" | "double" | "float64" => Some(DataType::F64),
            "u16" | "uint16" => Some(DataType::U16),
            "u32" | "uint32" => Some(DataType::U32),
            _ => None,
        };
        by_name
            .or_else(|| t.parse().ok().and_then(DataType::from_code))
            .ok_or_else(|| {
                format!("data type must be one of 1/u8, 2/i16, 3/i32, 4/f32, 5/f64, 12/u16, 13/u32, not {text:?}")
            })
    }
}

/// ENVI `interleave`: the order of samples, lines and bands in the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Interleave {
    /// Band sequential: `[band][line][sample]`.
    Bsq,
    /// Band interleaved by line: `[line][band][sample]`.
    Bil,
    /// Band interleaved by pixel: `[line][sample][band]`.
    Bip,
}

impl Interleave {
    /// Every interleave.
    pub const ALL: [Interleave; 3] = [Interleave::Bsq, Interleave::Bil, Interleave::Bip];

    /// The header spelling.
    pub fn name(self) -> &'static str {
        match self {
            Interleave::Bsq => "bsq",
            Interleave::Bil => "bil",
            Interleave::Bip => "bip",
        }
    }

    /// Parse a header or command-line value (case-insensitive).
    pub fn parse(text: &str) -> Result<Interleave, String> {
        match text.trim().to_ascii_lowercase().as_str() {
            "bsq" => Ok(Interleave::Bsq),
            "bil" => Ok(Interleave::Bil),
            "bip" => Ok(Interleave::Bip),
            _ => Err(format!(
                "unknown value {:?} (expected bsq, bil or bip)",
                text.trim()
            )),
        }
    }

    /// Position in the file of sample `s` of line `l` in band `b`.
    fn index(self, s: usize, l: usize, b: usize, dims: (usize, usize, usize)) -> usize {
        let (samples, lines, bands) = dims;
        match self {
            Interleave::Bsq => (b * lines + l) * samples + s,
            Interleave::Bil => (l * bands + b) * samples + s,
            Interleave::Bip => (l * samples + s) * bands + b,
        }
    }
}

/// ENVI `byte order`: 0 little-endian, 1 big-endian.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ByteOrder {
    /// 0: least significant byte first.
    Little,
    /// 1: most significant byte first.
    Big,
}

/// A parsed ENVI header.
#[derive(Clone, Debug, PartialEq)]
pub struct EnviHeader {
    /// `samples`: pixels per line (image width).
    pub samples: usize,
    /// `lines`: image height.
    pub lines: usize,
    /// `bands`.
    pub bands: usize,
    /// `header offset`: bytes to skip at the start of the data file.
    pub header_offset: u64,
    /// `data type`.
    pub data_type: DataType,
    /// `interleave`.
    pub interleave: Interleave,
    /// `byte order` (little-endian when absent).
    pub byte_order: ByteOrder,
    /// `wavelength`, converted to nm.
    pub wavelengths_nm: Option<Vec<f64>>,
    /// `fwhm`, converted to nm.
    pub fwhm_nm: Option<Vec<f64>>,
    /// `reflectance scale factor`: reflectance = stored value / factor.
    pub reflectance_scale_factor: Option<f64>,
    /// `data ignore value`: samples equal to it read as NaN.
    pub data_ignore_value: Option<f64>,
    /// `description`.
    pub description: Option<String>,
    /// Every field as written, keys lower-cased with single spaces, list
    /// values without their braces.
    pub fields: Vec<(String, String)>,
}

impl EnviHeader {
    /// Number of samples in the data file.
    pub fn sample_count(&self) -> Option<usize> {
        self.samples
            .checked_mul(self.lines)
            .and_then(|n| n.checked_mul(self.bands))
    }

    /// The raw text of a field (lower-case key).
    pub fn get(&self, key: &str) -> Option<&str> {
        self.fields
            .iter()
            .rev()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

/// A whole ENVI image in memory: header and band-sequential values as
/// stored (no scale factor applied; ignored values are NaN).
#[derive(Clone, Debug, PartialEq)]
pub struct EnviImage {
    /// The header.
    pub header: EnviHeader,
    /// The header file.
    pub header_path: PathBuf,
    /// The binary file.
    pub data_path: PathBuf,
    /// `data[b * lines * samples + l * samples + s]`.
    pub data: Vec<f32>,
}

/// Split the header text into `(key, value)` pairs and check the magic.
fn split_fields(text: &str, path: &Path) -> Result<Vec<(String, String)>, IoError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut lines = text.lines().enumerate().peekable();
    let magic = lines
        .by_ref()
        .map(|(_, l)| l.trim())
        .find(|l| !l.is_empty());
    match magic {
        Some(m) if m.eq_ignore_ascii_case("envi") => {}
        _ => {
            return Err(IoError::format(
                path,
                "not an ENVI header (the first line must be `ENVI`)",
            ))
        }
    }
    let mut fields = Vec::new();
    while let Some((no, line)) = lines.next() {
        let line = line.trim();
        if line.is_empty() || line.starts_with(';') {
            continue;
        }
        let Some((key, value)) = line.split_once('=') else {
            return Err(IoError::format(
                path,
                format!(
                    "line {}: expected `key = value`, found {:?}",
                    no + 1,
                    clip(line)
                ),
            ));
        };
        let key = key.split_whitespace().collect::<Vec<_>>().join(" ");
        let key = key.to_ascii_lowercase();
        if key.is_empty() {
            return Err(IoError::format(
                path,
                format!("line {}: a field without a name", no + 1),
            ));
        }
        let mut value = value.trim().to_string();
        if let Some(rest) = value.strip_prefix('{') {
            let mut body = rest.to_string();
            while !body.contains('}') {
                match lines.next() {
                    Some((_, more)) => {
                        body.push('\n');
                        body.push_str(more);
                    }
                    None => return Err(IoError::field(path, &key, "`{` is never closed")),
                }
            }
            let close = body.find('}').unwrap_or(body.len());
            if !body[close + 1..].trim().is_empty() {
                return Err(IoError::field(
                    path,
                    &key,
                    format!(
                        "text after the closing `}}`: {:?}",
                        clip(&body[close + 1..])
                    ),
                ));
            }
            value = body[..close].trim().to_string();
        }
        fields.push((key, value));
    }
    Ok(fields)
}

/// At most 40 characters of `s`, for error messages.
fn clip(s: &str) -> String {
    let s = s.trim();
    if s.chars().count() > 40 {
        let mut c: String = s.chars().take(40).collect();
        c.push('…');
        c
    } else {
        s.to_string()
    }
}

/// Parse an ENVI header's text; `path` names it in errors.
pub fn parse_header(text: &str, path: &Path) -> Result<EnviHeader, IoError> {
    let fields = split_fields(text, path)?;
    let get = |key: &str| {
        fields
            .iter()
            .rev()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    };
    let bad = |key: &str, msg: String| IoError::field(path, key, msg);
    let count = |key: &str| -> Result<usize, IoError> {
        let v = get(key).ok_or_else(|| bad(key, "missing".into()))?;
        match v.trim().parse::<usize>() {
            Ok(n) if n > 0 => Ok(n),
            _ => Err(bad(key, format!("not a positive integer: {:?}", clip(v)))),
        }
    };
    let samples = count("samples")?;
    let lines = count("lines")?;
    let bands = count("bands")?;
    let header_offset = match get("header offset") {
        None => 0,
        Some(v) => v
            .trim()
            .parse::<u64>()
            .map_err(|_| bad("header offset", format!("not a byte count: {:?}", clip(v))))?,
    };
    let data_type = {
        let v = get("data type").ok_or_else(|| bad("data type", "missing".into()))?;
        let code: u32 = v
            .trim()
            .parse()
            .map_err(|_| bad("data type", format!("not a type code: {:?}", clip(v))))?;
        DataType::from_code(code).ok_or_else(|| {
            bad(
                "data type",
                format!("type {code} is not supported (irid reads 1, 2, 3, 4, 5, 12 and 13)"),
            )
        })?
    };
    let interleave = match get("interleave") {
        Some(v) => Interleave::parse(v).map_err(|m| bad("interleave", m))?,
        // With one band every interleave is the same.
        None if bands == 1 => Interleave::Bsq,
        None => return Err(bad("interleave", "missing".into())),
    };
    let byte_order = match get("byte order").map(str::trim) {
        None | Some("0") => ByteOrder::Little,
        Some("1") => ByteOrder::Big,
        Some(v) => {
            return Err(bad(
                "byte order",
                format!("must be 0 or 1, not {:?}", clip(v)),
            ))
        }
    };
    let units = match get("wavelength units") {
        None => None,
        Some(v) => WavelengthUnit::parse(v).map_err(|m| bad("wavelength units", m))?,
    };
    let list = |key: &str| -> Result<Option<Vec<f64>>, IoError> {
        let Some(v) = get(key) else { return Ok(None) };
        let values = parse_list(v).map_err(|m| bad(key, m))?;
        if values.len() != bands {
            return Err(bad(
                key,
                format!("has {} values but `bands` = {bands}", values.len()),
            ));
        }
        Ok(Some(values))
    };
    let raw_wavelengths = list("wavelength")?;
    let unit = units.unwrap_or_else(|| WavelengthUnit::guess(raw_wavelengths.as_deref()));
    let wavelengths_nm = match raw_wavelengths {
        None => None,
        Some(w) => {
            let nm: Vec<f64> = w.iter().map(|&v| unit.to_nm(v)).collect();
            if let Some(i) = nm.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(bad(
                    "wavelength",
                    format!("value {} ({}) is not a positive wavelength", i + 1, w[i]),
                ));
            }
            Some(nm)
        }
    };
    let fwhm_nm = match list("fwhm")? {
        None => None,
        Some(f) => {
            let nm: Vec<f64> = f.iter().map(|&v| unit.width_to_nm(v, 0.0)).collect();
            if let Some(i) = nm.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
                return Err(bad(
                    "fwhm",
                    format!("value {} ({}) is not a width ≥ 0", i + 1, f[i]),
                ));
            }
            // A width in wavenumbers becomes a width in nm at its own band.
            match (&wavelengths_nm, unit) {
                (Some(w), WavelengthUnit::Wavenumber) => Some(
                    f.iter()
                        .zip(w)
                        .map(|(&fw, &c)| unit.width_to_nm(fw, c))
                        .collect(),
                ),
                _ => Some(nm),
            }
        }
    };
    let scalar = |key: &str| -> Result<Option<f64>, IoError> {
        match get(key) {
            None => Ok(None),
            Some(v) => match v.trim().parse::<f64>() {
                Ok(x) if x.is_finite() => Ok(Some(x)),
                _ => Err(bad(key, format!("not a number: {:?}", clip(v)))),
            },
        }
    };
    let reflectance_scale_factor = scalar("reflectance scale factor")?;
    if let Some(f) = reflectance_scale_factor {
        if f <= 0.0 {
            return Err(bad(
                "reflectance scale factor",
                format!("must be positive, not {f}"),
            ));
        }
    }
    let data_ignore_value = scalar("data ignore value")?;
    let description = get("description").map(str::to_string);
    let header = EnviHeader {
        samples,
        lines,
        bands,
        header_offset,
        data_type,
        interleave,
        byte_order,
        wavelengths_nm,
        fwhm_nm,
        reflectance_scale_factor,
        data_ignore_value,
        description,
        fields: fields.clone(),
    };
    if header
        .sample_count()
        .and_then(|n| n.checked_mul(data_type.size()))
        .is_none()
    {
        return Err(bad(
            "samples",
            format!("{samples} × {lines} lines × {bands} bands is too large"),
        ));
    }
    Ok(header)
}

/// Parse a comma-separated list of numbers (the inside of `{…}`).
fn parse_list(v: &str) -> Result<Vec<f64>, String> {
    v.split(',')
        .map(str::trim)
        .enumerate()
        .filter(|(_, s)| !s.is_empty())
        .map(|(i, s)| {
            s.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| format!("value {} is not a number: {:?}", i + 1, clip(s)))
        })
        .collect()
}

/// Units of `wavelength` and `fwhm`.
#[derive(Clone, Copy, Debug, PartialEq)]
enum WavelengthUnit {
    Nanometers,
    Micrometers,
    Millimeters,
    Meters,
    /// cm⁻¹.
    Wavenumber,
}

impl WavelengthUnit {
    fn parse(v: &str) -> Result<Option<WavelengthUnit>, String> {
        let t = v.trim().to_lowercase();
        Ok(Some(match t.as_str() {
            "nanometers" | "nanometer" | "nanometres" | "nanometre" | "nm" => {
                WavelengthUnit::Nanometers
            }
            "micrometers" | "micrometer" | "micrometres" | "micrometre" | "microns"
            | "micron" | "um" | "µm" | "μm" => WavelengthUnit::Micrometers,
            "millimeters" | "millimeter" | "millimetres" | "mm" => WavelengthUnit::Millimeters,
            "meters" | "meter" | "metres" | "m" => WavelengthUnit::Meters,
            "wavenumber" | "wavenumbers" | "cm-1" | "1/cm" => WavelengthUnit::Wavenumber,
            "unknown" | "" => return Ok(None),
            _ => {
                return Err(format!(
                    "unknown value {:?} (irid reads nanometers, micrometers, millimeters, meters, wavenumber)",
                    clip(v)
                ))
            }
        }))
    }

    /// Without (or with `Unknown`) units: values below 30 are taken as µm
    /// (visible/NIR wavelengths in nm are never that small).
    fn guess(values: Option<&[f64]>) -> WavelengthUnit {
        match values {
            Some(v) if !v.is_empty() && v.iter().all(|x| x.abs() < 30.0) => {
                WavelengthUnit::Micrometers
            }
            _ => WavelengthUnit::Nanometers,
        }
    }

    fn to_nm(self, v: f64) -> f64 {
        match self {
            WavelengthUnit::Nanometers => v,
            WavelengthUnit::Micrometers => v * 1e3,
            WavelengthUnit::Millimeters => v * 1e6,
            WavelengthUnit::Meters => v * 1e9,
            WavelengthUnit::Wavenumber => 1e7 / v,
        }
    }

    /// A width at centre `center_nm` (used only for wavenumbers).
    fn width_to_nm(self, w: f64, center_nm: f64) -> f64 {
        match self {
            WavelengthUnit::Wavenumber => w * center_nm * center_nm / 1e7,
            other => other.to_nm(w),
        }
    }
}

/// The header and data files of `path`, which may name either.
///
/// For `x.hdr` the data file is `x` or `x.img` (`.raw`, `.bsq`, `.bil`,
/// `.bip`, `.dat`, any case); for a data file `x.img` the header is
/// `x.hdr` or `x.img.hdr`.
pub fn resolve_paths(path: &Path) -> Result<(PathBuf, PathBuf), IoError> {
    let is_hdr = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("hdr"));
    if is_hdr {
        let stem = path.with_extension("");
        let mut tried = vec![stem.clone()];
        if stem.is_file() {
            return Ok((path.to_path_buf(), stem));
        }
        for ext in DATA_EXTENSIONS {
            for e in [ext.to_string(), ext.to_ascii_uppercase()] {
                let mut p = stem.clone().into_os_string();
                p.push(".");
                p.push(&e);
                let p = PathBuf::from(p);
                if p.is_file() {
                    return Ok((path.to_path_buf(), p));
                }
                tried.push(p);
            }
        }
        if !path.is_file() {
            return Err(IoError::format(path, "no such header file"));
        }
        Err(IoError::format(
            path,
            format!(
                "no data file beside the header (tried {} and .img/.raw/.bsq/.bil/.bip/.dat)",
                stem.display()
            ),
        ))
    } else {
        let mut appended = path.to_path_buf().into_os_string();
        appended.push(".hdr");
        for hdr in [path.with_extension("hdr"), PathBuf::from(appended)] {
            if hdr.is_file() {
                return Ok((hdr, path.to_path_buf()));
            }
        }
        Err(IoError::format(
            path,
            "no ENVI header beside this file (expected a `.hdr`)",
        ))
    }
}

/// Read and parse a header file.
pub fn read_header(path: &Path) -> Result<EnviHeader, IoError> {
    let file = std::fs::File::open(path).map_err(|e| IoError::os(path, e))?;
    let mut bytes = Vec::new();
    file.take(MAX_HEADER_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| IoError::os(path, e))?;
    if bytes.len() as u64 > MAX_HEADER_BYTES {
        return Err(IoError::format(
            path,
            "too large for an ENVI header (is this the data file?)",
        ));
    }
    parse_header(&String::from_utf8_lossy(&bytes), path)
}

/// Read an ENVI image (header and data; `path` may name either).
pub fn read_image(path: &Path) -> Result<EnviImage, IoError> {
    let (hdr, data) = resolve_paths(path)?;
    read_image_from(&hdr, &data)
}

/// Read an ENVI image from an explicit header and data file.
pub fn read_image_from(header_path: &Path, data_path: &Path) -> Result<EnviImage, IoError> {
    let header = read_header(header_path)?;
    let data = read_data(&header, data_path)?;
    Ok(EnviImage {
        header,
        header_path: header_path.to_path_buf(),
        data_path: data_path.to_path_buf(),
        data,
    })
}

/// Read the binary file of `header` into band-sequential f32.
pub fn read_data(header: &EnviHeader, data_path: &Path) -> Result<Vec<f32>, IoError> {
    let count = header.sample_count().unwrap_or(usize::MAX);
    let size = header.data_type.size();
    let need = count.saturating_mul(size) as u64;
    let mut file = std::fs::File::open(data_path).map_err(|e| IoError::os(data_path, e))?;
    let len = file
        .metadata()
        .map_err(|e| IoError::os(data_path, e))?
        .len();
    let end = header.header_offset.saturating_add(need);
    if len < end {
        return Err(IoError::format(
            data_path,
            format!(
                "data file too short: {} × {} × {} samples of type {} after a header offset of {} need {} bytes, the file has {}",
                header.samples,
                header.lines,
                header.bands,
                header.data_type.code(),
                header.header_offset,
                end,
                len
            ),
        ));
    }
    file.seek(SeekFrom::Start(header.header_offset))
        .map_err(|e| IoError::os(data_path, e))?;
    let mut bytes = vec![0u8; need as usize];
    file.read_exact(&mut bytes)
        .map_err(|e| IoError::os(data_path, e))?;
    let mut values = decode(&bytes, header.data_type, header.byte_order);
    if let Some(ignore) = header.data_ignore_value {
        let ignore = ignore as f32;
        for v in &mut values {
            if *v == ignore {
                *v = f32::NAN;
            }
        }
    }
    let dims = (header.samples, header.lines, header.bands);
    Ok(match header.interleave {
        Interleave::Bsq => values,
        il => {
            let mut out = vec![0.0f32; values.len()];
            let mut o = 0;
            for b in 0..header.bands {
                for l in 0..header.lines {
                    for s in 0..header.samples {
                        out[o] = values[il.index(s, l, b, dims)];
                        o += 1;
                    }
                }
            }
            out
        }
    })
}

/// Decode raw samples in file order.
fn decode(bytes: &[u8], t: DataType, order: ByteOrder) -> Vec<f32> {
    macro_rules! conv {
        ($ty:ty, $n:expr) => {
            bytes
                .chunks_exact($n)
                .map(|c| {
                    let a: [u8; $n] = c.try_into().expect("chunks_exact yields $n bytes");
                    (match order {
                        ByteOrder::Little => <$ty>::from_le_bytes(a),
                        ByteOrder::Big => <$ty>::from_be_bytes(a),
                    }) as f32
                })
                .collect()
        };
    }
    match t {
        DataType::U8 => bytes.iter().map(|&b| f32::from(b)).collect(),
        DataType::I16 => conv!(i16, 2),
        DataType::U16 => conv!(u16, 2),
        DataType::I32 => conv!(i32, 4),
        DataType::U32 => conv!(u32, 4),
        DataType::F32 => conv!(f32, 4),
        DataType::F64 => conv!(f64, 8),
    }
}

/// The bands of a header: its wavelengths (required) and widths (0 if absent).
pub fn header_bands(header: &EnviHeader, header_path: &Path) -> Result<Vec<Band>, IoError> {
    let centers = header.wavelengths_nm.as_ref().ok_or_else(|| {
        IoError::field(
            header_path,
            "wavelength",
            "missing (irid needs the band centres)",
        )
    })?;
    // Through `Band::new`, like every other band: a header's bands get the
    // same checks as a scene's.
    centers
        .iter()
        .enumerate()
        .map(|(i, &c)| {
            let fwhm = header
                .fwhm_nm
                .as_ref()
                .and_then(|f| f.get(i).copied())
                .unwrap_or(0.0);
            Band::new(c, fwhm).map_err(|e| {
                IoError::field(header_path, "wavelength", format!("band {}: {e}", i + 1))
            })
        })
        .collect()
}

/// Read a reflectance cube: values divided by the `reflectance scale factor`.
pub fn read_cube(path: &Path) -> Result<Cube, IoError> {
    let img = read_image(path)?;
    image_to_cube(img)
}

/// Turn an image into a reflectance cube (scale factor applied).
pub fn image_to_cube(img: EnviImage) -> Result<Cube, IoError> {
    let bands = header_bands(&img.header, &img.header_path)?;
    let mut data = img.data;
    if let Some(f) = img.header.reflectance_scale_factor {
        // Divide in f64 so that exact stored values give the correctly
        // rounded reflectance.
        data.iter_mut()
            .for_each(|v| *v = (f64::from(*v) / f) as f32);
    }
    Ok(Cube {
        width: img.header.samples,
        height: img.header.lines,
        bands,
        data,
    })
}

/// Read the dark and white reference cubes of the raw-count image `cube`:
/// they must have its size and band count and, where they list
/// wavelengths, its wavelengths. Calibrating is the pipeline's business
/// (`pipeline::calibration::read_calibrated`).
pub fn read_references(
    cube: &EnviImage,
    dark_path: &Path,
    white_path: &Path,
) -> Result<(EnviImage, EnviImage), IoError> {
    let dark = read_image(dark_path)?;
    let white = read_image(white_path)?;
    for refimg in [&dark, &white] {
        check_same_shape(cube, refimg)?;
    }
    Ok((dark, white))
}

fn check_same_shape(cube: &EnviImage, other: &EnviImage) -> Result<(), IoError> {
    let (a, b) = (&cube.header, &other.header);
    let mismatch = |message: String| IoError::Mismatch {
        a: cube.header_path.clone(),
        b: other.header_path.clone(),
        message,
    };
    if (a.samples, a.lines, a.bands) != (b.samples, b.lines, b.bands) {
        return Err(mismatch(format!(
            "sizes differ: {} × {} × {} bands and {} × {} × {} bands",
            a.samples, a.lines, a.bands, b.samples, b.lines, b.bands
        )));
    }
    if let (Some(wa), Some(wb)) = (&a.wavelengths_nm, &b.wavelengths_nm) {
        if let Some(i) = (0..wa.len()).find(|&i| (wa[i] - wb[i]).abs() > 0.5) {
            return Err(mismatch(format!(
                "band {} is at {} nm in one and {} nm in the other",
                i + 1,
                wa[i],
                wb[i]
            )));
        }
    }
    Ok(())
}

/// How [`write_cube`] stores a cube.
#[derive(Clone, Debug, PartialEq)]
pub struct WriteOptions {
    /// Sample type (default f32).
    pub data_type: DataType,
    /// Interleave (default bsq).
    pub interleave: Interleave,
    /// Byte order (default little-endian).
    pub byte_order: ByteOrder,
    /// Zero bytes before the data, recorded as `header offset`.
    pub header_offset: u64,
    /// Stored value = reflectance × factor. Default: 1 (not written) for
    /// float types, 10000 for integer types (255 for u8).
    pub reflectance_scale_factor: Option<f64>,
    /// `description`.
    pub description: Option<String>,
}

impl Default for WriteOptions {
    fn default() -> Self {
        WriteOptions {
            data_type: DataType::F32,
            interleave: Interleave::Bsq,
            byte_order: ByteOrder::Little,
            header_offset: 0,
            reflectance_scale_factor: None,
            description: None,
        }
    }
}

/// Header and data paths for an output `path`: `x.hdr` → (`x.hdr`, `x.img`);
/// `x.img.hdr` → (`x.img.hdr`, `x.img`); anything else `y` → (`y.hdr`, `y.img`)
/// with `y`'s own extension replaced.
pub fn output_paths(path: &Path) -> (PathBuf, PathBuf) {
    let is_hdr = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("hdr"));
    if is_hdr {
        let stem = path.with_extension("");
        let data = if stem.extension().is_some() {
            stem
        } else {
            stem.with_extension("img")
        };
        (path.to_path_buf(), data)
    } else {
        (path.with_extension("hdr"), path.with_extension("img"))
    }
}

/// Write `cube` as an ENVI header and data file; returns their paths.
/// Non-finite values become 0 in integer types; integers are rounded and
/// clamped to the type's range.
pub fn write_cube(
    path: &Path,
    cube: &Cube,
    opts: &WriteOptions,
) -> Result<(PathBuf, PathBuf), IoError> {
    let (hdr_path, data_path) = output_paths(path);
    let (w, h, nb) = (cube.width, cube.height, cube.bands.len());
    if w == 0 || h == 0 || nb == 0 || cube.data.len() != w * h * nb {
        return Err(IoError::format(
            &hdr_path,
            format!(
                "cannot write a cube of {w} × {h} × {nb} bands with {} values",
                cube.data.len()
            ),
        ));
    }
    let scale = opts
        .reflectance_scale_factor
        .unwrap_or(match opts.data_type {
            DataType::U8 => 255.0,
            t if t.is_integer() => 10000.0,
            _ => 1.0,
        });
    let dims = (w, h, nb);
    let mut bytes =
        Vec::with_capacity(opts.header_offset as usize + w * h * nb * opts.data_type.size());
    bytes.resize(opts.header_offset as usize, 0);
    // Walk the file order and fetch from the band-sequential cube.
    let mut file_order = vec![0usize; w * h * nb];
    for b in 0..nb {
        for l in 0..h {
            for s in 0..w {
                file_order[opts.interleave.index(s, l, b, dims)] = (b * h + l) * w + s;
            }
        }
    }
    for &i in &file_order {
        encode(
            f64::from(cube.data[i]) * scale,
            opts.data_type,
            opts.byte_order,
            &mut bytes,
        );
    }
    let mut text = String::from("ENVI\n");
    if let Some(d) = &opts.description {
        // Braces would end the value early; they are the only thing ENVI forbids.
        let d: String = d
            .chars()
            .map(|c| if c == '{' || c == '}' { '(' } else { c })
            .collect();
        let _ = writeln!(text, "description = {{\n{d}}}");
    }
    let _ = writeln!(text, "samples = {w}");
    let _ = writeln!(text, "lines = {h}");
    let _ = writeln!(text, "bands = {nb}");
    let _ = writeln!(text, "header offset = {}", opts.header_offset);
    let _ = writeln!(text, "file type = ENVI Standard");
    let _ = writeln!(text, "data type = {}", opts.data_type.code());
    let _ = writeln!(text, "interleave = {}", opts.interleave.name());
    let _ = writeln!(
        text,
        "byte order = {}",
        match opts.byte_order {
            ByteOrder::Little => 0,
            ByteOrder::Big => 1,
        }
    );
    if scale != 1.0 {
        let _ = writeln!(text, "reflectance scale factor = {scale}");
    }
    let join = |f: &dyn Fn(&Band) -> f64| {
        cube.bands
            .iter()
            .map(|b| format!("{}", f(b)))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let _ = writeln!(text, "wavelength units = Nanometers");
    let _ = writeln!(text, "wavelength = {{{}}}", join(&|b| b.center_nm));
    let _ = writeln!(text, "fwhm = {{{}}}", join(&|b| b.fwhm_nm));
    write_file(&data_path, &bytes)?;
    write_file(&hdr_path, text.as_bytes())?;
    Ok((hdr_path, data_path))
}

/// Data first, then the header, each atomically: a reader never finds a
/// header whose data file is not complete.
fn write_file(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    super::atomic::write_bytes(path, super::atomic::Overwrite::Replace, bytes)
}

fn encode(v: f64, t: DataType, order: ByteOrder, out: &mut Vec<u8>) {
    macro_rules! int {
        ($ty:ty) => {{
            let x = if v.is_finite() {
                v.round().clamp(<$ty>::MIN as f64, <$ty>::MAX as f64) as $ty
            } else {
                0
            };
            match order {
                ByteOrder::Little => out.extend_from_slice(&x.to_le_bytes()),
                ByteOrder::Big => out.extend_from_slice(&x.to_be_bytes()),
            }
        }};
    }
    macro_rules! float {
        ($ty:ty) => {{
            let x = v as $ty;
            match order {
                ByteOrder::Little => out.extend_from_slice(&x.to_le_bytes()),
                ByteOrder::Big => out.extend_from_slice(&x.to_be_bytes()),
            }
        }};
    }
    match t {
        DataType::U8 => int!(u8),
        DataType::I16 => int!(i16),
        DataType::U16 => int!(u16),
        DataType::I32 => int!(i32),
        DataType::U32 => int!(u32),
        DataType::F32 => float!(f32),
        DataType::F64 => float!(f64),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p() -> &'static Path {
        Path::new("t.hdr")
    }

    #[test]
    fn spectral_python_style_header_parses() {
        let text = "ENVI\ndescription = {\n  Created by SPy,\n  on a Tuesday}\nsamples = 3\nLines   = 2\nbands = 4\n\
            ; a comment\nheader offset = 0\nfile type = ENVI Standard\ndata type = 12\ninterleave = BIP\n\
            byte order = 1\nwavelength units = Micrometers\nwavelength = {\n 0.4, 0.5,\n 0.6 , 0.7 }\n\
            fwhm = {0.01,0.01,0.01,0.01}\nreflectance scale factor = 10000\n";
        let h = parse_header(text, p()).unwrap();
        assert_eq!((h.samples, h.lines, h.bands), (3, 2, 4));
        assert_eq!(h.data_type, DataType::U16);
        assert_eq!(h.interleave, Interleave::Bip);
        assert_eq!(h.byte_order, ByteOrder::Big);
        let w = h.wavelengths_nm.unwrap();
        assert!((w[3] - 700.0).abs() < 1e-9, "{w:?}");
        assert!((h.fwhm_nm.unwrap()[0] - 10.0).abs() < 1e-9);
        assert_eq!(h.reflectance_scale_factor, Some(10000.0));
        assert!(h.description.unwrap().contains("Tuesday"));
    }

    #[test]
    fn errors_name_the_field() {
        let base = "ENVI\nsamples = 2\nlines = 2\nbands = 1\ndata type = 4\n";
        let e = parse_header(&format!("{base}interleave = bsx\n"), p()).unwrap_err();
        assert_eq!(
            e.to_string(),
            "t.hdr: field `interleave`: unknown value \"bsx\" (expected bsq, bil or bip)"
        );
        let e = parse_header("ENVI\nsamples = 2\nlines = 2\nbands = 1\n", p()).unwrap_err();
        assert!(e.to_string().contains("field `data type`: missing"), "{e}");
        let e = parse_header(&format!("{base}wavelength = {{1, 2\n"), p()).unwrap_err();
        assert!(e.to_string().contains("`wavelength`"), "{e}");
    }

    #[test]
    fn wavenumber_units_convert() {
        let text = "ENVI\nsamples = 1\nlines = 1\nbands = 2\ndata type = 4\ninterleave = bsq\n\
            wavelength units = Wavenumber\nwavelength = {20000, 25000}\n";
        let h = parse_header(text, p()).unwrap();
        assert_eq!(h.wavelengths_nm.unwrap(), vec![500.0, 400.0]);
    }
}
