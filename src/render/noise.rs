//! Accuracy against noise as a picture: mean thickness error against the
//! reflectance noise σ, log–log, one line per mode and one panel per scene
//! and angle knowledge, with the Cramér–Rao-efficient error (0.798 σ_CRB at
//! each σ) as a dashed line — drawn from the Markdown table `cargo bench
//! --bench noise_sweep` prints (README "Accuracy against noise").
//!
//! The table's layout lives here, on both sides: [`NoiseRow::markdown`]
//! prints a row (the bench uses it) and [`parse_table`] reads the table
//! back, found by its header (`| scene | angle | mode | noise σ |` …
//! `mean |Δd|` … `efficient` …) with columns looked up by name. Lengths
//! keep four significant digits, so the table reads back within 0.05 %; σ
//! is printed exactly. A measurement with no valid pixel prints `–` and
//! reads back as NaN: not drawn, and the panel says at which σ nothing
//! was valid.

use super::canvas::FONT_FAMILY;
use super::chart::{self, bad_cell, marker, number, Chart, Table, MODES, PALETTE};
use super::RenderError;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;

/// One row of the table: one mode on one scene at one noise level.
#[derive(Clone, Debug, PartialEq)]
pub struct NoiseRow {
    /// Scene class label.
    pub scene: String,
    /// Whether the angle was known.
    pub angle_known: bool,
    /// Mode name (`fast`, `balanced`, `accurate`).
    pub mode: String,
    /// Reflectance noise σ per band the cube was given.
    pub sigma_r: f64,
    /// Fraction of pixels valid, 0..=1.
    pub valid_fraction: f64,
    /// Mean |Δd| over valid pixels, nm.
    pub mean_err_nm: f64,
    /// 99th percentile of |Δd| over valid pixels, nm.
    pub p99_err_nm: f64,
    /// Mean |Δd| of an efficient estimator at this σ (0.798 σ_CRB), nm.
    pub efficient_nm: f64,
    /// Fraction of valid pixels with |Δd| ≤ 2σ_d, 0..=1.
    pub coverage_2sigma: f64,
    /// Fraction of valid pixels with |Δd| > max(3σ_d, 2 nm), 0..=1 (NaN
    /// where a table predates the column).
    pub valid_wrong: f64,
}

/// The table's header and rule, as [`parse_table`] finds it.
pub const HEADER: &str = "| scene | angle | mode | noise σ | valid | mean \\|Δd\\| | p99 \\|Δd\\| | efficient | ratio | \\|Δd\\| ≤ 2σ | valid and wrong |\n|---|---|---|---|---|---|---|---|---|---|---|";

/// `v` with `digits` significant digits; `–` when not finite.
fn sig(v: f64, digits: i32) -> String {
    if !v.is_finite() {
        return "–".into();
    }
    if v == 0.0 {
        return "0".into();
    }
    let mag = v.abs().log10().floor() as i32;
    let dec = (digits - 1 - mag).max(0) as usize;
    format!("{v:.dec$}")
}

/// A length, nm, with four significant digits; `–` when not finite.
fn length(v: f64) -> String {
    if v.is_finite() {
        format!("{} nm", sig(v, 4))
    } else {
        "–".into()
    }
}

/// A fraction as a percentage with one decimal; `–` when not finite.
fn percent(v: f64) -> String {
    if v.is_finite() {
        format!("{:.1} %", 100.0 * v)
    } else {
        "–".into()
    }
}

impl NoiseRow {
    /// Mean |Δd| over the efficient one.
    pub fn ratio(&self) -> f64 {
        self.mean_err_nm / self.efficient_nm
    }

    /// The row as a Markdown table line under [`HEADER`].
    pub fn markdown(&self) -> String {
        format!(
            "| {} | {} | `{}` | {} | {} | {} | {} | {} | {} | {} | {} |",
            self.scene.replace('|', "\\|"),
            if self.angle_known { "known" } else { "unknown" },
            self.mode,
            self.sigma_r,
            percent(self.valid_fraction),
            length(self.mean_err_nm),
            length(self.p99_err_nm),
            length(self.efficient_nm),
            match self.ratio() {
                r if r.is_finite() => format!("{r:.2}"),
                _ => "–".into(),
            },
            percent(self.coverage_2sigma),
            percent(self.valid_wrong),
        )
    }
}

/// A measured value: a number, or `–` (nothing valid) as NaN.
fn measured(cell: &str) -> Option<f64> {
    number(cell).or_else(|| (cell == "–").then_some(f64::NAN))
}

/// The rows of the first noise-sweep table in `text`.
pub fn parse_table(text: &str) -> Result<Vec<NoiseRow>, RenderError> {
    let table = Table::find(
        text,
        &[
            "scene",
            "angle",
            "mode",
            "noise σ",
            "mean |Δd|",
            "efficient",
        ],
        "noise-sweep",
    )?;
    let col = |n: &str| table.col(n);
    let cols = [
        col("scene")?,
        col("angle")?,
        col("mode")?,
        col("noise σ")?,
        col("valid")?,
        col("mean |Δd|")?,
        col("p99 |Δd|")?,
        col("efficient")?,
        col("|Δd| ≤ 2σ")?,
    ];
    // Optional: tables measured before it have no such column.
    let wrong_col = table.col("valid and wrong").ok();
    let mut rows = Vec::new();
    for (k, line, c) in table.rows() {
        let get = |i: usize| c.get(cols[i]).map(String::as_str).unwrap_or("");
        let bad = |what: &str| bad_cell(k, what, line);
        let angle_known = match get(1) {
            "known" => true,
            "unknown" => false,
            _ => return Err(bad("angle (known or unknown)")),
        };
        let mode = get(2).trim_matches('`').to_string();
        if mode.is_empty() {
            return Err(bad("mode"));
        }
        let positive = |v: Option<f64>| v.filter(|v| *v > 0.0);
        rows.push(NoiseRow {
            scene: get(0).to_string(),
            angle_known,
            mode,
            sigma_r: positive(number(get(3))).ok_or_else(|| bad("noise σ"))?,
            valid_fraction: measured(get(4)).ok_or_else(|| bad("valid"))? / 100.0,
            mean_err_nm: measured(get(5)).ok_or_else(|| bad("mean |Δd|"))?,
            p99_err_nm: measured(get(6)).ok_or_else(|| bad("p99 |Δd|"))?,
            efficient_nm: positive(number(get(7))).ok_or_else(|| bad("efficient"))?,
            coverage_2sigma: measured(get(8)).ok_or_else(|| bad("|Δd| ≤ 2σ"))? / 100.0,
            valid_wrong: match wrong_col {
                Some(i) => {
                    let cell = c.get(i).map(String::as_str).unwrap_or("");
                    measured(cell).ok_or_else(|| bad("valid and wrong"))? / 100.0
                }
                None => f64::NAN,
            },
        });
    }
    if rows.is_empty() {
        return Err(RenderError::input("the noise-sweep table has no rows"));
    }
    Ok(rows)
}

/// The modes in `rows`: the known ones in their order, then others as met.
fn modes(rows: &[&NoiseRow]) -> Vec<String> {
    let mut out: Vec<String> = MODES
        .iter()
        .filter(|m| rows.iter().any(|r| r.mode == **m))
        .map(|m| m.to_string())
        .collect();
    for r in rows {
        if !out.contains(&r.mode) {
            out.push(r.mode.clone());
        }
    }
    out
}

/// A mode's colour: the same in every panel and the legend.
fn colour(mode: &str, all: &[String]) -> RGBColor {
    let i = MODES
        .iter()
        .position(|m| *m == mode)
        .unwrap_or_else(|| MODES.len() + all.iter().position(|m| m == mode).unwrap_or(0));
    PALETTE[i % PALETTE.len()]
}

/// A short axis label: two significant digits, no trailing zeros.
fn short(v: f64) -> String {
    let s = sig(v, 2);
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// The range of positive finite values, widened by `pad` on a log scale.
fn log_range(vals: impl Iterator<Item = f64>, pad: f64) -> Option<std::ops::Range<f64>> {
    let (lo, hi) = vals
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::MAX, f64::MIN), |a, v| (a.0.min(v), a.1.max(v)));
    (lo <= hi).then(|| lo / pad..hi * pad)
}

/// What the lines do not show: the noise levels where no mode had a valid
/// pixel (not drawn), and those where some mode had fewer than 90 % valid
/// (its mean is over the valid ones only).
fn validity_notes(rows: &[&NoiseRow]) -> Vec<String> {
    let mut sigmas: Vec<f64> = rows.iter().map(|r| r.sigma_r).collect();
    sigmas.sort_by(f64::total_cmp);
    sigmas.dedup();
    let mut notes = Vec::new();
    for s in sigmas {
        let at: Vec<&&NoiseRow> = rows.iter().filter(|r| r.sigma_r == s).collect();
        if at
            .iter()
            .all(|r| !(r.mean_err_nm.is_finite() && r.mean_err_nm > 0.0))
        {
            notes.push(format!("σ = {s}: no valid pixel (all flagged)"));
        } else if at.iter().any(|r| r.valid_fraction < 0.9) {
            let each: Vec<String> = at
                .iter()
                .map(|r| format!("{} {:.0} %", r.mode, 100.0 * r.valid_fraction))
                .collect();
            notes.push(format!("σ = {s}: valid {}", each.join(", ")));
        }
    }
    notes
}

/// One scene's panel: each mode's mean |Δd| against σ and the efficient
/// error. Markers go on `root` (backend pixels), lines on the panel.
fn draw_panel<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    area: &DrawingArea<DB, Shift>,
    rows: &[&NoiseRow],
    all_modes: &[String],
    caption: &str,
) -> Result<(), String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    let xr = log_range(rows.iter().map(|r| r.sigma_r), 1.4);
    let yr = log_range(
        rows.iter().flat_map(|r| [r.mean_err_nm, r.efficient_nm]),
        1.5,
    );
    let (Some(xr), Some(yr)) = (xr, yr) else {
        return Err(format!("{caption}: no positive values to plot"));
    };
    // Ticks at the measured noise levels.
    let mut sigmas: Vec<f64> = rows.iter().map(|r| r.sigma_r).collect();
    sigmas.sort_by(f64::total_cmp);
    sigmas.dedup();
    let mut ch = ChartBuilder::on(area)
        .caption(caption, (FONT_FAMILY, 13))
        .margin(10)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(xr.log_scale().with_key_points(sigmas), yr.log_scale())
        .map_err(e)?;
    ch.configure_mesh()
        .x_desc("reflectance noise σ per band")
        .y_desc("mean |thickness error|, nm")
        .label_style((FONT_FAMILY, 12))
        .axis_desc_style((FONT_FAMILY, 13))
        .light_line_style(RGBColor(235, 235, 235))
        .x_label_formatter(&|v| short(*v))
        .y_label_formatter(&|v| short(*v))
        .draw()
        .map_err(e)?;
    let by_sigma = |mut pts: Vec<(f64, f64)>| {
        pts.retain(|(x, y)| *x > 0.0 && y.is_finite() && *y > 0.0);
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        pts
    };
    let mut limit = by_sigma(rows.iter().map(|r| (r.sigma_r, r.efficient_nm)).collect());
    limit.dedup_by(|a, b| a.0 == b.0);
    ch.draw_series(DashedLineSeries::new(limit, 6, 4, BLACK.stroke_width(1)))
        .map_err(e)?;
    // Where modes agree their lines coincide: the first mode is drawn last,
    // on top, and the markers' shapes show the ones beneath.
    for mode in modes(rows).into_iter().rev() {
        let c = colour(&mode, all_modes);
        let pts = by_sigma(
            rows.iter()
                .filter(|r| r.mode == mode)
                .map(|r| (r.sigma_r, r.mean_err_nm))
                .collect(),
        );
        ch.draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))
            .map_err(e)?;
        for p in &pts {
            marker(root, ch.backend_coord(p), &mode, c.filled())?;
        }
    }
    for (i, note) in validity_notes(rows).into_iter().enumerate() {
        area.draw(&Text::new(
            note,
            (80, 34 + 16 * i as i32),
            (FONT_FAMILY, 12),
        ))
        .map_err(e)?;
    }
    Ok(())
}

/// The legend: one line and marker per mode, the dashed limit.
fn draw_legend<DB: DrawingBackend>(
    legend: &DrawingArea<DB, Shift>,
    all_modes: &[String],
) -> Result<(), String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    let text = |s: &str, x: i32, y: i32| Text::new(s.to_string(), (x, y), (FONT_FAMILY, 12));
    let mut y = 60;
    for mode in all_modes {
        let c = colour(mode, all_modes);
        legend
            .draw(&PathElement::new(
                vec![(4, y + 6), (36, y + 6)],
                c.stroke_width(2),
            ))
            .map_err(e)?;
        marker(legend, (20, y + 6), mode, c.filled())?;
        legend.draw(&text(mode, 44, y)).map_err(e)?;
        y += 22;
    }
    y += 8;
    for x in [4, 14, 24] {
        legend
            .draw(&PathElement::new(vec![(x, y + 6), (x + 6, y + 6)], BLACK))
            .map_err(e)?;
    }
    legend
        .draw(&text("Cramér–Rao-efficient", 44, y))
        .map_err(e)?;
    legend
        .draw(&text("mean |Δd| (0.798 σ_CRB)", 44, y + 16))
        .map_err(e)?;
    Ok(())
}

/// Draw the chart on any plotters backend.
pub fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    rows: &[NoiseRow],
    title: &str,
) -> Result<(), String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    root.fill(&WHITE).map_err(e)?;
    let mut groups: Vec<(&str, bool)> = Vec::new();
    for r in rows {
        if !groups.contains(&(r.scene.as_str(), r.angle_known)) {
            groups.push((&r.scene, r.angle_known));
        }
    }
    if groups.is_empty() {
        return Err("no rows to plot".into());
    }
    let all: Vec<&NoiseRow> = rows.iter().collect();
    let all_modes = modes(&all);
    let (plots, legend) = root.split_horizontally(root.dim_in_pixel().0 as i32 - 230);
    let plots = plots.titled(title, (FONT_FAMILY, 17)).map_err(e)?;
    let panels = plots.split_evenly((1, groups.len()));
    for (panel, (scene, known)) in panels.iter().zip(&groups) {
        let group: Vec<&NoiseRow> = rows
            .iter()
            .filter(|r| r.scene == *scene && r.angle_known == *known)
            .collect();
        let label: String = scene.chars().take(44).collect();
        let caption = format!(
            "{label}, angle {}",
            if *known { "known" } else { "unknown" }
        );
        draw_panel(root, panel, &group, &all_modes, &caption)?;
    }
    draw_legend(&legend, &all_modes)
}

/// Chart size, pixels.
pub const SIZE: (u32, u32) = (1100, 500);

struct NoiseChart<'a> {
    rows: &'a [NoiseRow],
    title: &'a str,
}

impl Chart for NoiseChart<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String> {
        draw(root, self.rows, self.title)
    }
}

/// Draw the chart to `out`: SVG when it ends in `.svg`, else PNG.
pub fn write_chart(rows: &[NoiseRow], title: &str, out: &Path) -> Result<(), RenderError> {
    chart::write(&NoiseChart { rows, title }, SIZE, out)
}
