//! Spectrum tables: spectrometer exports and single spectra as text, one
//! row per wavelength and one column per spectrum.
//!
//! ```text
//! # comment (also `%`); blank lines are ignored
//! wavelength_nm,sample A,sample B        <- optional header
//! 400,0.0412,0.0398
//! 401,0.0415,nan                          <- nan, NaN or an empty cell: missing
//! ```
//!
//! - Separators: `;` if the first data row has one, else `,`, else
//!   a tab (spaces around cells ignored), else runs of spaces and tabs. In `;` files a decimal comma (`0,0412`) is
//!   read as a decimal point. Cells may be wrapped in double quotes (no
//!   separator inside them); one trailing separator per line is ignored.
//! - Header: the line above the first data row, when its first cell is not
//!   a number; its first cell names the wavelength column, the others the
//!   spectra (without a header they are `spectrum1`, `spectrum2`, …). A
//!   spectrometer's metadata may stand above it (lines whose first cell is
//!   not a number, and `>>>`-markers such as OceanView's "Begin Spectral
//!   Data"): then the last of them is the header only if it has a cell per
//!   column. The first data row fixes the separator.
//! - Units: nm. A first header cell with a `um`, `µm`, `micron(s)` or
//!   `micrometer(s)` word means µm, with `nm` or `nanometer(s)` nm;
//!   otherwise, if every wavelength is below 30, µm (the ENVI rule).
//!   Wavenumber columns are refused. A spectrum whose header cell has a
//!   `%` or the word `percent` ("R (%)", "%R") is in percent: the caller
//!   divides it by 100 ([`SpectrumTable::percent_to_fraction`]).
//! - Order: wavelengths strictly increasing or strictly decreasing (the
//!   latter are reversed); a repeated wavelength or a change of direction
//!   is an error naming the line.
//!
//! The result is a [`Cube`] one pixel high with one pixel per spectrum and
//! one band (FWHM 0) per row, in increasing wavelength, plus the spectrum
//! names. [`SpectrumTable::select_range`] and [`SpectrumTable::resample`]
//! (boxcar bands) prepare a finely sampled spectrometer file for the
//! solver, which takes at most
//! [`MAX_BANDS`](crate::estimate::solver::MAX_BANDS) bands.
//!
//! Every problem is an [`IoError`] naming the file and, for a bad row, the
//! line. The file is read line by line; its size is bounded before
//! anything big is allocated ([`MAX_ROWS`], [`MAX_SPECTRA`],
//! [`MAX_VALUES`], [`MAX_LINE_BYTES`]). No file content makes this module
//! panic.
#![forbid(unsafe_code)]

use super::IoError;
use crate::estimate::Cube;
use crate::optics::band::Band;
use std::io::{BufRead, Read};
use std::path::Path;

/// Most data rows (wavelengths) a table may have.
pub const MAX_ROWS: usize = 100_000;
/// Most spectra (columns after the wavelength) a table may have.
pub const MAX_SPECTRA: usize = 100_000;
/// Most values (rows × spectra) a table may have (200 MB as f32).
pub const MAX_VALUES: usize = 50_000_000;
/// Longest line read.
pub const MAX_LINE_BYTES: usize = 16 << 20;
/// Fewest rows: the solver needs at least 4 bands.
pub const MIN_ROWS: usize = 4;

/// Wavelengths all below this (and without a unit in the header) are µm.
const MICROMETER_BELOW: f64 = 30.0;

/// A spectrum table as read.
#[derive(Clone, Debug, PartialEq)]
pub struct SpectrumTable {
    /// `width` = number of spectra, `height` = 1, one band per row in
    /// increasing wavelength (nm).
    pub cube: Cube,
    /// One name per spectrum (pixel `x` of the cube).
    pub names: Vec<String>,
    /// Whether the file's wavelengths were µm (converted to nm).
    pub micrometers: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Separator {
    Semicolon,
    Comma,
    Tab,
    Whitespace,
}

impl Separator {
    fn detect(line: &str) -> Separator {
        if line.contains(';') {
            Separator::Semicolon
        } else if line.contains(',') {
            Separator::Comma
        } else if line.contains('\t') {
            Separator::Tab
        } else {
            Separator::Whitespace
        }
    }

    fn split(self, line: &str) -> Vec<&str> {
        fn unquote(c: &str) -> &str {
            let c = c.trim();
            c.strip_prefix('"')
                .and_then(|c| c.strip_suffix('"'))
                .map_or(c, str::trim)
        }
        match self {
            Separator::Semicolon => line.split(';').map(unquote).collect(),
            Separator::Comma => line.split(',').map(unquote).collect(),
            Separator::Tab => line.split('\t').map(unquote).collect(),
            Separator::Whitespace => line.split_whitespace().map(unquote).collect(),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Unit {
    Nanometers,
    Micrometers,
}

/// The unit named by the wavelength column's header cell, if any.
fn header_unit(name: &str) -> Result<Option<Unit>, String> {
    let lower = name.to_lowercase();
    let mut unit = None;
    for word in lower.split(|c: char| !c.is_alphanumeric()) {
        let u = match word {
            "nm" | "nanometer" | "nanometers" | "nanometre" | "nanometres" => Unit::Nanometers,
            "um" | "µm" | "μm" | "micron" | "microns" | "micrometer" | "micrometers"
            | "micrometre" | "micrometres" => Unit::Micrometers,
            "wavenumber" | "wavenumbers" | "cm" => {
                return Err(format!(
                    "wavelength column {name:?}: wavenumbers are not supported (give nm or µm)"
                ))
            }
            _ => continue,
        };
        unit = Some(u);
    }
    Ok(unit)
}

/// A value cell: a number, or NaN for `nan` (any case) and empty cells.
fn parse_value(cell: &str, decimal_comma: bool) -> Option<f64> {
    if cell.is_empty() || cell.eq_ignore_ascii_case("nan") {
        return Some(f64::NAN);
    }
    parse_number(cell, decimal_comma)
}

fn parse_number(cell: &str, decimal_comma: bool) -> Option<f64> {
    if decimal_comma && cell.contains(',') && !cell.contains('.') {
        cell.replace(',', ".").parse().ok()
    } else {
        cell.parse().ok()
    }
}

/// Show at most 40 characters of a cell in a message.
fn clip(s: &str) -> String {
    if s.chars().count() > 40 {
        format!("{}…", s.chars().take(40).collect::<String>())
    } else {
        s.to_string()
    }
}

/// Read a spectrum table from a file.
pub fn read_table(path: &Path) -> Result<SpectrumTable, IoError> {
    let file = std::fs::File::open(path).map_err(|e| IoError::os(path, e))?;
    parse_table(std::io::BufReader::new(file), path)
}

/// Parse a spectrum table from text; `path` names it in errors.
pub fn parse_table(mut reader: impl BufRead, path: &Path) -> Result<SpectrumTable, IoError> {
    let mut buf = Vec::new();
    let mut line_no = 0usize;
    let mut sep: Option<Separator> = None;
    // The last non-numeric line before the first data row, and how many
    // there were.
    let mut pending: Option<(String, usize)> = None;
    let mut preamble = 0usize;
    // Cells per row (wavelength included), and the line that fixed it.
    let mut columns: Option<(usize, usize)> = None;
    let mut header: Option<Vec<String>> = None;
    let mut unit = None;
    // Raw wavelength and line number of each row; values row-major.
    let mut rows: Vec<(f64, usize)> = Vec::new();
    let mut values: Vec<f32> = Vec::new();
    // Whether the last column ever held a non-empty cell.
    let mut last_column_used = false;
    loop {
        buf.clear();
        let n = reader
            .by_ref()
            .take(MAX_LINE_BYTES as u64 + 1)
            .read_until(b'\n', &mut buf)
            .map_err(|e| IoError::os(path, e))?;
        if n == 0 {
            break;
        }
        line_no += 1;
        if buf.len() > MAX_LINE_BYTES {
            return Err(IoError::line(
                path,
                line_no,
                format!("longer than {MAX_LINE_BYTES} bytes (not a spectrum table?)"),
            ));
        }
        if buf.contains(&0) {
            return Err(IoError::line(
                path,
                line_no,
                "binary data (a NUL byte): not a text spectrum table",
            ));
        }
        let text = String::from_utf8_lossy(&buf);
        let t = text.trim_start_matches('\u{feff}').trim();
        // Comments, blank lines, and a spectrometer's data markers
        // (OceanView's ">>>>>Begin Spectral Data<<<<<").
        if t.is_empty() || t.starts_with('#') || t.starts_with('%') || t.starts_with(">>>") {
            continue;
        }
        // Trailing tabs are separators (empty cells), not blank space.
        let t = text
            .trim_start_matches('\u{feff}')
            .trim_start()
            .trim_end_matches([' ', '\r', '\n']);
        if columns.is_none() {
            let line_sep = Separator::detect(t);
            let first = line_sep.split(t);
            if parse_number(first[0], line_sep == Separator::Semicolon).is_none() {
                // Before the first data row: the header, or a
                // spectrometer's metadata above it (the last such line is
                // taken for the header where it has a name per column).
                pending = Some((t.to_string(), line_no));
                preamble += 1;
                continue;
            }
            // The first data row fixes the separator.
            sep = Some(line_sep);
            if let Some((h, h_line)) = pending.take() {
                let n = first.len();
                let split = |sep: Separator| {
                    let mut c = sep.split(&h);
                    while c.len() > 1 && c.last().is_some_and(|c| c.is_empty()) {
                        c.pop();
                    }
                    c
                };
                let fit = |c: &Vec<&str>| {
                    c.len() == n || (c.len() + 1 == n && first.last().is_some_and(|c| c.is_empty()))
                };
                // Split as the data are, or as the header itself reads (a
                // space-separated header over tab-separated rows).
                let own = split(Separator::detect(&h));
                let (hcells, fits) = match split(line_sep) {
                    c if fit(&c) => (c, true),
                    _ if fit(&own) => (own, true),
                    _ => (own, false),
                };
                // A lone line above the data is the header, checked as
                // one; after metadata, only a line that fits the columns.
                if preamble == 1 || fits {
                    if hcells.len() < 2 {
                        return Err(IoError::line(
                            path,
                            h_line,
                            "no spectrum column (the header names only the wavelength column)",
                        ));
                    }
                    check_spectra(path, h_line, hcells.len() - 1)?;
                    unit = header_unit(hcells[0]).map_err(|m| IoError::line(path, h_line, m))?;
                    header = Some(hcells[1..].iter().map(|c| c.to_string()).collect());
                    columns = Some((hcells.len(), h_line));
                }
            }
        }
        // Set by the first data row above.
        let sep = *sep.get_or_insert_with(|| Separator::detect(t));
        let decimal_comma = sep == Separator::Semicolon;
        let mut cells = sep.split(t);
        // Without a header, the first data row fixes the columns.
        let (ncols, first_line) = match columns {
            Some(c) => c,
            None => {
                if cells.len() < 2 {
                    return Err(IoError::line(
                        path,
                        line_no,
                        "no spectrum column (a row holds only a wavelength)",
                    ));
                }
                check_spectra(path, line_no, cells.len() - 1)?;
                *columns.insert((cells.len(), line_no))
            }
        };
        if cells.len() == ncols + 1 && cells.last().is_some_and(|c| c.is_empty()) {
            cells.pop();
        }
        if cells.len() != ncols {
            return Err(IoError::line(
                path,
                line_no,
                format!(
                    "{} cells, but line {first_line} has {ncols} (wavelength + {} spectra)",
                    cells.len(),
                    ncols - 1
                ),
            ));
        }
        if rows.len() >= MAX_ROWS {
            return Err(IoError::line(
                path,
                line_no,
                format!("more than {MAX_ROWS} rows: too large for a spectrum table"),
            ));
        }
        if (rows.len() + 1).saturating_mul(ncols - 1) > MAX_VALUES {
            return Err(IoError::line(
                path,
                line_no,
                format!("more than {MAX_VALUES} values: too large for a spectrum table"),
            ));
        }
        push_row(
            path,
            line_no,
            &cells,
            decimal_comma,
            &mut rows,
            &mut values,
            &mut last_column_used,
        )?;
    }
    let Some((ncols, _)) = columns else {
        return Err(IoError::format(path, "no data: an empty spectrum table"));
    };
    if rows.len() < MIN_ROWS {
        return Err(IoError::format(
            path,
            format!(
                "{} data rows; irid needs at least {MIN_ROWS} wavelengths",
                rows.len()
            ),
        ));
    }
    let mut width = ncols - 1;
    // A trailing separator on every row of a table without a header is an
    // empty, unnamed last column: drop it.
    if header.is_none() && !last_column_used {
        if width == 1 {
            return Err(IoError::format(
                path,
                "no spectrum column (the only value column is empty)",
            ));
        }
        values = values
            .chunks_exact(width)
            .flat_map(|r| r[..width - 1].iter().copied())
            .collect();
        width -= 1;
    }
    let unit = unit.unwrap_or(if rows.iter().all(|(w, _)| w.abs() < MICROMETER_BELOW) {
        Unit::Micrometers
    } else {
        Unit::Nanometers
    });
    let scale = match unit {
        Unit::Nanometers => 1.0,
        Unit::Micrometers => 1e3,
    };
    let mut bands = Vec::with_capacity(rows.len());
    for &(w, line) in &rows {
        let band =
            Band::new(w * scale, 0.0).map_err(|e| IoError::line(path, line, e.to_string()))?;
        bands.push(band);
    }
    let increasing = rows[1].0 > rows[0].0;
    for i in 1..rows.len() {
        let ((a, la), (b, lb)) = (rows[i - 1], rows[i]);
        if a == b {
            return Err(IoError::line(
                path,
                lb,
                format!("wavelength {b} repeats line {la}'s"),
            ));
        }
        if (b > a) != increasing {
            return Err(IoError::line(
                path,
                lb,
                format!(
                    "wavelength {b} after {a} (line {la}): rows must be strictly {}",
                    if increasing {
                        "increasing"
                    } else {
                        "decreasing"
                    }
                ),
            ));
        }
    }
    if !increasing {
        bands.reverse();
        values = values
            .chunks_exact(width)
            .rev()
            .flatten()
            .copied()
            .collect();
    }
    let names = match header {
        Some(h) => h
            .into_iter()
            .take(width)
            .enumerate()
            .map(|(i, n)| {
                if n.is_empty() {
                    format!("spectrum{}", i + 1)
                } else {
                    n
                }
            })
            .collect(),
        None => (1..=width).map(|i| format!("spectrum{i}")).collect(),
    };
    Ok(SpectrumTable {
        cube: Cube {
            width,
            height: 1,
            bands,
            data: values,
        },
        names,
        micrometers: unit == Unit::Micrometers,
    })
}

fn check_spectra(path: &Path, line: usize, n: usize) -> Result<(), IoError> {
    if n > MAX_SPECTRA {
        return Err(IoError::line(
            path,
            line,
            format!("{n} spectra: more than {MAX_SPECTRA}, too many for a spectrum table"),
        ));
    }
    Ok(())
}

fn push_row(
    path: &Path,
    line: usize,
    cells: &[&str],
    decimal_comma: bool,
    rows: &mut Vec<(f64, usize)>,
    values: &mut Vec<f32>,
    last_column_used: &mut bool,
) -> Result<(), IoError> {
    let w = parse_number(cells[0], decimal_comma)
        .filter(|w| w.is_finite())
        .ok_or_else(|| {
            IoError::line(
                path,
                line,
                format!("wavelength {:?} is not a finite number", clip(cells[0])),
            )
        })?;
    for (j, cell) in cells[1..].iter().enumerate() {
        let v = parse_value(cell, decimal_comma).ok_or_else(|| {
            IoError::line(
                path,
                line,
                format!(
                    "value {:?} in column {} is not a number (nan or an empty cell mark a missing value)",
                    clip(cell),
                    j + 2
                ),
            )
        })?;
        values.push(v as f32);
    }
    *last_column_used |= cells.last().is_some_and(|c| !c.is_empty());
    rows.push((w, line));
    Ok(())
}

/// Fewest rows for [`SpectrumTable::repair_spikes`] to look for spikes:
/// a densely sampled spectrometer file, not a band set.
pub const SPIKE_MIN_ROWS: usize = 100;

/// How far (in robust σ of the local departures) a spike stands out.
pub const SPIKE_SIGMAS: f64 = 10.0;

impl SpectrumTable {
    /// Number of spectra.
    pub fn spectra(&self) -> usize {
        self.cube.width
    }

    /// Number of rows (bands).
    pub fn rows(&self) -> usize {
        self.cube.bands.len()
    }

    /// Shortest and longest wavelength, nm (NaN for an empty table).
    pub fn wavelength_range(&self) -> (f64, f64) {
        match (self.cube.bands.first(), self.cube.bands.last()) {
            (Some(a), Some(b)) => (a.center_nm, b.center_nm),
            _ => (f64::NAN, f64::NAN),
        }
    }

    /// Only the rows with `lo_nm ≤ λ ≤ hi_nm`.
    pub fn select_range(&self, lo_nm: f64, hi_nm: f64) -> SpectrumTable {
        let w = self.cube.width;
        let keep: Vec<usize> = (0..self.rows())
            .filter(|&b| (lo_nm..=hi_nm).contains(&self.cube.bands[b].center_nm))
            .collect();
        let bands = keep.iter().map(|&b| self.cube.bands[b]).collect();
        let data = keep
            .iter()
            .flat_map(|&b| self.cube.data[b * w..(b + 1) * w].iter().copied())
            .collect();
        SpectrumTable {
            cube: Cube {
                width: w,
                height: 1,
                bands,
                data,
            },
            names: self.names.clone(),
            micrometers: self.micrometers,
        }
    }

    /// Boxcar bands: for each centre, per spectrum, the mean of the finite
    /// table values whose wavelength lies within ±`width_nm`/2 of it (both
    /// ends included, to 1e-9 relative, so 1 nm samples and a 2 nm step
    /// average three samples centred on the band), NaN where there is none.
    /// The bands get FWHM `width_nm`.
    pub fn resample(&self, centers_nm: &[f64], width_nm: f64) -> Result<SpectrumTable, String> {
        if !(width_nm.is_finite() && width_nm > 0.0) {
            return Err(format!("band width must be > 0 nm, not {width_nm}"));
        }
        let w = self.cube.width;
        let n = centers_nm
            .len()
            .checked_mul(w)
            .filter(|n| *n <= MAX_VALUES)
            .ok_or_else(|| format!("{} bands × {w} spectra: too many values", centers_nm.len()))?;
        let mut bands = Vec::with_capacity(centers_nm.len());
        let mut data = vec![f32::NAN; n];
        let mut sum = vec![0f64; w];
        let mut count = vec![0u32; w];
        for (k, &c) in centers_nm.iter().enumerate() {
            bands.push(Band::new(c, width_nm).map_err(|e| e.to_string())?);
            let half = width_nm / 2.0;
            let tol = 1e-9 * c.abs().max(width_nm);
            let (lo, hi) = (c - half - tol, c + half + tol);
            let b0 = self.cube.bands.partition_point(|b| b.center_nm < lo);
            let b1 = self.cube.bands.partition_point(|b| b.center_nm <= hi);
            sum.fill(0.0);
            count.fill(0);
            for b in b0..b1 {
                for (x, &v) in self.cube.data[b * w..(b + 1) * w].iter().enumerate() {
                    if v.is_finite() {
                        sum[x] += f64::from(v);
                        count[x] += 1;
                    }
                }
            }
            for x in 0..w {
                if count[x] > 0 {
                    data[k * w + x] = (sum[x] / f64::from(count[x])) as f32;
                }
            }
        }
        Ok(SpectrumTable {
            cube: Cube {
                width: w,
                height: 1,
                bands,
                data,
            },
            names: self.names.clone(),
            micrometers: self.micrometers,
        })
    }

    /// Spectra whose header names them in percent (a `%` in the name, or
    /// the word `percent`) divided by 100 to fractions; their names.
    pub fn percent_to_fraction(&mut self) -> Vec<String> {
        let w = self.cube.width;
        let mut done = Vec::new();
        for (x, name) in self.names.iter().enumerate() {
            let lower = name.to_lowercase();
            if !(lower.contains('%')
                || lower
                    .split(|c: char| !c.is_alphanumeric())
                    .any(|t| t == "percent"))
            {
                continue;
            }
            for v in self.cube.data.iter_mut().skip(x).step_by(w) {
                *v *= 0.01;
            }
            done.push(name.clone());
        }
        done
    }

    /// Replace isolated spikes by the median of their neighbours; returns
    /// the wavelengths (nm) replaced, per spectrum in order.
    ///
    /// A spectrometer's file can hold single samples no spectrum of a film
    /// makes: a cosmic ray on the detector, a dead pixel, a zero written at
    /// the end of the range. On a densely sampled table (at least
    /// [`SPIKE_MIN_ROWS`] rows) a film's spectrum changes little from one row
    /// to the next, so a sample is a spike when it departs from the median of
    /// its six nearest neighbours (each carried to it along the local
    /// slope) by more than [`SPIKE_SIGMAS`] times the
    /// robust scatter of such departures over the 50 rows around it, and by
    /// more than the spread of those neighbours themselves (less their
    /// extremes, one of which may be a spike's partner). Only up to two
    /// adjacent samples qualify: a longer run is structure, left to the fit.
    pub fn repair_spikes(&mut self) -> Vec<f64> {
        let (w, nb) = (self.cube.width, self.rows());
        let mut replaced = Vec::new();
        if nb < SPIKE_MIN_ROWS {
            return replaced;
        }
        let mut y = vec![0.0f64; nb];
        let mut dev = vec![0.0f64; nb];
        let mut med = vec![0.0f64; nb];
        let mut spread = vec![0.0f64; nb];
        let mut nbh: Vec<f64> = Vec::with_capacity(6);
        let mut win: Vec<f64> = Vec::with_capacity(51);
        for x in 0..w {
            for (k, v) in y.iter_mut().enumerate() {
                *v = f64::from(self.cube.data[k * w + x]);
            }
            if y.iter().any(|v| !v.is_finite()) {
                continue;
            }
            for i in 0..nb {
                // The six nearest rows, shifted inwards at the ends.
                let a = i.saturating_sub(3).min(nb - 7);
                // The local slope (median step between neighbours), so a
                // row at the range's end, seen from one side, is not taken
                // for a spike of the slope's size.
                nbh.clear();
                nbh.extend(
                    (a..a + 6)
                        .filter(|&j| j != i && j + 1 != i)
                        .map(|j| y[j + 1] - y[j]),
                );
                nbh.sort_by(f64::total_cmp);
                let slope = nbh[nbh.len() / 2];
                nbh.clear();
                nbh.extend(
                    (a..a + 7)
                        .filter(|&j| j != i)
                        .map(|j| y[j] + slope * (i as f64 - j as f64)),
                );
                nbh.sort_by(f64::total_cmp);
                med[i] = 0.5 * (nbh[2] + nbh[3]);
                spread[i] = nbh[4] - nbh[1];
                dev[i] = y[i] - med[i];
            }
            let mut spikes = Vec::new();
            for i in 0..nb {
                let a = i.saturating_sub(25).min(nb.saturating_sub(51));
                let z = (a + 51).min(nb);
                win.clear();
                win.extend(dev[a..z].iter().map(|d| d.abs()));
                let m = win.len() / 2;
                let (_, mid, _) = win.select_nth_unstable_by(m, f64::total_cmp);
                let scale = 1.4826 * *mid;
                if dev[i].abs() > SPIKE_SIGMAS * scale && dev[i].abs() > spread[i] {
                    spikes.push(i);
                }
            }
            // Runs of at most two.
            let mut j = 0;
            while j < spikes.len() {
                let mut e = j;
                while e + 1 < spikes.len() && spikes[e + 1] == spikes[e] + 1 {
                    e += 1;
                }
                if e - j < 2 {
                    for &i in &spikes[j..=e] {
                        self.cube.data[i * w + x] = med[i] as f32;
                        replaced.push(self.cube.bands[i].center_nm);
                    }
                }
                j = e + 1;
            }
        }
        replaced
    }

    /// Drop the bands that are NaN in every spectrum; returns how many.
    pub fn drop_empty_bands(&mut self) -> usize {
        let w = self.cube.width;
        let keep: Vec<usize> = (0..self.rows())
            .filter(|&b| {
                self.cube.data[b * w..(b + 1) * w]
                    .iter()
                    .any(|v| !v.is_nan())
            })
            .collect();
        let dropped = self.rows() - keep.len();
        if dropped > 0 {
            self.cube.bands = keep.iter().map(|&b| self.cube.bands[b]).collect();
            self.cube.data = keep
                .iter()
                .flat_map(|&b| self.cube.data[b * w..(b + 1) * w].iter().copied())
                .collect();
        }
        dropped
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<SpectrumTable, IoError> {
        parse_table(text.as_bytes(), Path::new("t.csv"))
    }

    #[test]
    fn separators_and_units() {
        assert_eq!(Separator::detect("a;b,c"), Separator::Semicolon);
        assert_eq!(Separator::detect("a,b"), Separator::Comma);
        assert_eq!(Separator::detect("a\tb c"), Separator::Tab);
        assert_eq!(Separator::detect("a  b"), Separator::Whitespace);
        assert_eq!(header_unit("Wavelength (µm)"), Ok(Some(Unit::Micrometers)));
        assert_eq!(header_unit("wl_um"), Ok(Some(Unit::Micrometers)));
        assert_eq!(header_unit("lambda [nm]"), Ok(Some(Unit::Nanometers)));
        assert_eq!(header_unit("wavelength"), Ok(None));
        assert!(header_unit("Wavenumber (cm-1)").is_err());
    }

    #[test]
    fn semicolon_files_take_decimal_commas() {
        let t = parse("wl;a\n400;0,5\n410;0,25\n420;\"1,5\"\n430;nan\n").unwrap();
        assert_eq!(t.cube.data[..3], [0.5, 0.25, 1.5]);
        assert!(t.cube.data[3].is_nan());
    }

    /// A dense fringe spectrum with noise: a zero at the last row, a
    /// cosmic ray in the middle and a two-sample glitch are replaced; the
    /// clean table and a three-sample step are left alone.
    #[test]
    fn isolated_spikes_are_repaired_and_structure_is_not() {
        let rows = 400;
        let mut text = String::from("wl,a\n");
        let mut noise = 0x2545_f491_4f6c_dd1du64;
        let mut truth = Vec::new();
        for i in 0..rows {
            let lam = 400.0 + i as f64;
            noise ^= noise << 13;
            noise ^= noise >> 7;
            noise ^= noise << 17;
            let e = ((noise >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 1e-3;
            let r = 0.2 + 0.15 * (4.0 * std::f64::consts::PI * 1.5 * 600.0 / lam).cos();
            truth.push(r);
            text.push_str(&format!("{lam},{}\n", r + e));
        }
        let clean = parse(&text).unwrap();
        let mut t = clean.clone();
        let none = t.repair_spikes();
        assert!(none.is_empty(), "a clean spectrum has no spike: {none:?}");
        let mut bad = clean.clone();
        bad.cube.data[rows - 1] = 0.0;
        bad.cube.data[150] += 0.08;
        bad.cube.data[250] -= 0.05;
        bad.cube.data[251] -= 0.05;
        let mut fixed = bad.clone();
        let got = fixed.repair_spikes();
        assert_eq!(got, [550.0, 650.0, 651.0, 799.0]);
        for i in [150, 250, 251, rows - 1] {
            let e = (f64::from(fixed.cube.data[i]) - truth[i]).abs();
            assert!(e < 3e-3, "row {i}: {e}");
        }
        let mut step = clean.clone();
        for i in 300..303 {
            step.cube.data[i] += 0.05;
        }
        assert!(
            step.repair_spikes().is_empty(),
            "three samples are structure"
        );
    }

    #[test]
    fn percent_columns_are_scaled_and_others_not() {
        let mut t = parse("nm,R (%),sample,Percent reflectance\n400,50,0.5,25\n410,40,0.4,20\n420,30,0.3,10\n430,20,0.2,5\n")
            .unwrap();
        let done = t.percent_to_fraction();
        assert_eq!(
            done,
            vec!["R (%)".to_string(), "Percent reflectance".to_string()]
        );
        // Band-major: each band's three spectra.
        let want = [0.5, 0.5, 0.25, 0.4, 0.4, 0.2, 0.3, 0.3, 0.1, 0.2, 0.2, 0.05];
        for (g, w) in t.cube.data.iter().zip(want) {
            assert!((f64::from(*g) - w).abs() < 1e-7, "{:?}", t.cube.data);
        }
    }

    #[test]
    fn trailing_separators_are_ignored() {
        let t = parse("400,1,2,\n410,1,2,\n420,1,2,\n430,1,2,\n").unwrap();
        assert_eq!(t.names, ["spectrum1", "spectrum2"]);
        let t = parse("wl,a,\n400,1,\n410,1,\n420,1\n430,1\n").unwrap();
        assert_eq!(t.names, ["a"]);
        assert_eq!(t.cube.data, [1.0; 4]);
    }
}
