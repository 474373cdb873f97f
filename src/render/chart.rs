//! What the benchmark charts share: reading a Markdown table back from a
//! file (README) by its header, numbers as printed with their units, the
//! palette and one marker shape per mode, and writing a chart as SVG or
//! PNG by the output's extension.
//!
//! Tables are found by the names in their header, and columns are looked
//! up by name, so added columns do not break a reader. Nothing here panics
//! on the text: a missing table, column or number is a [`RenderError`].

use super::canvas::RgbImage;
use super::RenderError;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;

/// The cells of one Markdown table line, trimmed; `\|` inside a cell is an
/// escaped bar, not a separator.
pub(crate) fn cells(line: &str) -> Vec<String> {
    let l = line.trim().replace("\\|", "\u{1}");
    let l = l.strip_prefix('|').unwrap_or(&l);
    let l = l.strip_suffix('|').unwrap_or(l);
    l.split('|')
        .map(|c| c.replace('\u{1}', "|").trim().to_string())
        .collect()
}

/// A number with an optional SI suffix (`k`, `M`, `G`) or unit (`nm`, `%`,
/// kept as printed), possibly in backticks.
pub(crate) fn number(s: &str) -> Option<f64> {
    let s = s.trim().trim_matches('`');
    let mut parts = s.split_whitespace();
    let v: f64 = parts.next()?.parse().ok()?;
    let mult = match parts.next() {
        Some("k") => 1e3,
        Some("M") => 1e6,
        Some("G") => 1e9,
        _ => 1.0,
    };
    Some(v * mult).filter(|v| v.is_finite())
}

/// The first Markdown table in a text whose header names every one of a
/// set of columns.
pub(crate) struct Table<'a> {
    lines: Vec<&'a str>,
    start: usize,
    head: Vec<String>,
}

impl<'a> Table<'a> {
    /// The first table in `text` whose header holds all of `columns`;
    /// `what` names it in the error when there is none.
    pub(crate) fn find(text: &'a str, columns: &[&str], what: &str) -> Result<Self, RenderError> {
        let lines: Vec<&str> = text.lines().collect();
        let start = lines
            .iter()
            .position(|l| {
                let c = cells(l);
                l.trim_start().starts_with('|') && columns.iter().all(|h| c.iter().any(|x| x == h))
            })
            .ok_or_else(|| {
                RenderError::input(format!(
                    "no {what} table (a header with {})",
                    columns.join(", ")
                ))
            })?;
        let head = cells(lines[start]);
        Ok(Table { lines, start, head })
    }

    /// The index of the column named `name`.
    pub(crate) fn col(&self, name: &str) -> Result<usize, RenderError> {
        self.head
            .iter()
            .position(|h| h == name)
            .ok_or_else(|| RenderError::input(format!("table has no `{name}` column")))
    }

    /// The body: `(1-based line number, line, cells)` of each row after the
    /// header and its rule, up to the first line that is not a table row.
    pub(crate) fn rows(&self) -> impl Iterator<Item = (usize, &'a str, Vec<String>)> + '_ {
        self.lines
            .iter()
            .enumerate()
            .skip(self.start + 2)
            .take_while(|(_, l)| l.trim_start().starts_with('|'))
            .map(|(k, l)| (k + 1, *l, cells(l)))
    }
}

/// The error for a cell that does not read as what its column holds.
pub(crate) fn bad_cell(line_no: usize, what: &str, line: &str) -> RenderError {
    RenderError::input(format!("table line {line_no}: bad {what}: {line:?}"))
}

/// Colours of the charts' series (matplotlib's "tab10", colour-blind
/// distinguishable in its first three).
pub(crate) const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

/// The solver's modes in the order charts list them.
pub(crate) const MODES: [&str; 3] = ["fast", "balanced", "accurate"];

/// A mode's marker at backend pixel `at`: a triangle for `fast`, a square
/// for `accurate`, a circle otherwise.
pub(crate) fn marker<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    at: (i32, i32),
    mode: &str,
    style: ShapeStyle,
) -> Result<(), String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    let (x, y) = at;
    match mode {
        // plotters fills its triangle marker whatever the style: a hollow
        // one (the angle estimated) is drawn as a closed outline.
        "fast" if !style.filled => {
            let (h, w) = (7, 6);
            let pts = vec![
                (x, y - h),
                (x - w, y + h / 2),
                (x + w, y + h / 2),
                (x, y - h),
            ];
            root.draw(&PathElement::new(pts, style)).map_err(e)
        }
        "fast" => root.draw(&TriangleMarker::new((x, y), 7, style)).map_err(e),
        "accurate" => root
            .draw(&Rectangle::new([(x - 5, y - 5), (x + 5, y + 5)], style))
            .map_err(e),
        _ => root.draw(&Circle::new((x, y), 5, style)).map_err(e),
    }
}

/// A chart that draws itself on any plotters backend.
pub(crate) trait Chart {
    /// Draw on `root` (its whole area).
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String>;
}

/// Draw `chart` at `size` pixels to `out`: SVG when it ends in `.svg`,
/// else PNG; written atomically.
pub(crate) fn write(chart: &impl Chart, size: (u32, u32), out: &Path) -> Result<(), RenderError> {
    let svg = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("svg"));
    if svg {
        super::canvas::register_font();
        let mut text = String::new();
        {
            let root = SVGBackend::with_string(&mut text, size).into_drawing_area();
            chart.draw(&root).map_err(RenderError::Draw)?;
            root.present()
                .map_err(|e| RenderError::Draw(e.to_string()))?;
        }
        super::canvas::write_atomic(out, text.as_bytes())
    } else {
        let mut img = RgbImage::new(size.0 as usize, size.1 as usize)?;
        img.draw(|root| chart.draw(root))?;
        img.write_png(out)
    }
}
