//! The speed/accuracy trade as a picture: mean thickness error against
//! pixels per second, one point per mode, scene and angle knowledge, with
//! each case's Cramér–Rao limit marked — drawn from the Markdown table
//! `cargo bench --bench scene_matrix` prints (README "Speed and accuracy by
//! scene class"), so the chart is redrawn from data, never by hand.
//!
//! The table is found by its header (`| scene | angle | mode | pixels/s |`
//! … `mean |Δd|` … `efficient` …); columns are looked up by name, so
//! added columns do not break it. Values keep their units as printed
//! (`1.12 M`, `629 k`, `0.683 nm`).

use super::canvas::FONT_FAMILY;
use super::chart::{self, bad_cell, marker, number, Chart, Table, MODES, PALETTE};
use super::RenderError;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;

/// One row of the table.
#[derive(Clone, Debug, PartialEq)]
pub struct TradeRow {
    /// Scene class label.
    pub scene: String,
    /// Whether the angle was known.
    pub angle_known: bool,
    /// Mode name (`fast`, `balanced`, `accurate`).
    pub mode: String,
    /// Per-pixel solve speed.
    pub pixels_per_s: f64,
    /// Mean |Δd|, nm.
    pub mean_err_nm: f64,
    /// Mean |Δd| of an efficient estimator (0.798 σ_CRB), nm.
    pub efficient_nm: f64,
}

/// The rows of the first scene-matrix table in `text`.
pub fn parse_table(text: &str) -> Result<Vec<TradeRow>, RenderError> {
    let table = Table::find(
        text,
        &["scene", "angle", "mode", "pixels/s", "efficient"],
        "scene-matrix",
    )?;
    let (cs, ca, cm, cp, ce, cf) = (
        table.col("scene")?,
        table.col("angle")?,
        table.col("mode")?,
        table.col("pixels/s")?,
        table.col("mean |Δd|")?,
        table.col("efficient")?,
    );
    let mut rows = Vec::new();
    for (k, line, c) in table.rows() {
        let get = |i: usize| c.get(i).map(String::as_str).unwrap_or("");
        let bad = |what: &str| bad_cell(k, what, line);
        rows.push(TradeRow {
            scene: get(cs).to_string(),
            angle_known: get(ca) == "known",
            mode: get(cm).trim_matches('`').to_string(),
            pixels_per_s: number(get(cp)).ok_or_else(|| bad("pixels/s"))?,
            mean_err_nm: number(get(ce)).ok_or_else(|| bad("mean |Δd|"))?,
            efficient_nm: number(get(cf)).ok_or_else(|| bad("efficient"))?,
        });
    }
    if rows.is_empty() {
        return Err(RenderError::input("the scene-matrix table has no rows"));
    }
    Ok(rows)
}

/// Draw the chart on any plotters backend.
pub fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    rows: &[TradeRow],
    title: &str,
) -> Result<(), String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    root.fill(&WHITE).map_err(e)?;
    let (xs, ys): (Vec<f64>, Vec<f64>) = rows
        .iter()
        .flat_map(|r| {
            [
                (r.pixels_per_s, r.mean_err_nm),
                (r.pixels_per_s, r.efficient_nm),
            ]
        })
        .filter(|(x, y)| *x > 0.0 && *y > 0.0)
        .unzip();
    if xs.is_empty() {
        return Err("no positive values to plot".into());
    }
    let (x0, x1) = xs
        .iter()
        .fold((f64::MAX, f64::MIN), |a, v| (a.0.min(*v), a.1.max(*v)));
    let (y0, y1) = ys
        .iter()
        .fold((f64::MAX, f64::MIN), |a, v| (a.0.min(*v), a.1.max(*v)));
    let (area, legend) = root.split_horizontally(root.dim_in_pixel().0 as i32 - 300);
    let mut ch = ChartBuilder::on(&area)
        .caption(title, (FONT_FAMILY, 17))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(
            (x0 / 1.6..x1 * 1.6).log_scale(),
            (y0 / 1.5..y1 * 1.5).log_scale(),
        )
        .map_err(e)?;
    ch.configure_mesh()
        .x_desc("pixels per second (per-pixel solve, 2 cores)")
        .y_desc("mean |thickness error|, nm")
        .label_style((FONT_FAMILY, 12))
        .axis_desc_style((FONT_FAMILY, 13))
        .light_line_style(RGBColor(235, 235, 235))
        .x_label_formatter(&|v| {
            if *v >= 1e6 {
                format!("{:.0} M", v / 1e6)
            } else if *v >= 1e3 {
                format!("{:.0} k", v / 1e3)
            } else {
                format!("{v:.0}")
            }
        })
        .y_label_formatter(&|v| format!("{v}"))
        .draw()
        .map_err(e)?;
    let mut scenes: Vec<&str> = Vec::new();
    for r in rows {
        if !scenes.contains(&r.scene.as_str()) {
            scenes.push(&r.scene);
        }
    }
    for (si, scene) in scenes.iter().enumerate() {
        let colour = PALETTE[si % PALETTE.len()];
        for known in [false, true] {
            let group: Vec<&TradeRow> = rows
                .iter()
                .filter(|r| r.scene == *scene && r.angle_known == known)
                .collect();
            let Some(first) = group.first() else { continue };
            // The limit: a dashed line at the efficient error, across the
            // group's speeds.
            let (gx0, gx1) = group.iter().fold((f64::MAX, f64::MIN), |a, r| {
                (a.0.min(r.pixels_per_s), a.1.max(r.pixels_per_s))
            });
            let lim = first.efficient_nm;
            ch.draw_series(DashedLineSeries::new(
                vec![(gx0 / 1.25, lim), (gx1 * 1.25, lim)],
                4,
                3,
                colour.stroke_width(1),
            ))
            .map_err(e)?;
            for r in &group {
                let at = ch.backend_coord(&(r.pixels_per_s, r.mean_err_nm));
                let style = if known {
                    colour.filled()
                } else {
                    colour.stroke_width(2)
                };
                marker(&area, at, &r.mode, style)?;
            }
        }
    }
    // Legend: scenes by colour, modes by shape, fill by angle knowledge.
    let mut y = 40;
    let text = |s: &str, x: i32, y: i32| Text::new(s.to_string(), (x, y), (FONT_FAMILY, 12));
    for (si, scene) in scenes.iter().enumerate() {
        let colour = PALETTE[si % PALETTE.len()];
        legend
            .draw(&Rectangle::new([(6, y), (18, y + 12)], colour.filled()))
            .map_err(e)?;
        let label: String = scene.chars().take(48).collect();
        legend.draw(&text(&label, 24, y)).map_err(e)?;
        y += 20;
    }
    y += 10;
    for mode in MODES {
        marker(&legend, (12, y + 6), mode, BLACK.stroke_width(2))?;
        legend.draw(&text(mode, 24, y)).map_err(e)?;
        y += 20;
    }
    y += 10;
    legend
        .draw(&Circle::new((12, y + 6), 5, BLACK.filled()))
        .map_err(e)?;
    legend.draw(&text("angle known", 24, y)).map_err(e)?;
    y += 20;
    legend
        .draw(&Circle::new((12, y + 6), 5, BLACK.stroke_width(2)))
        .map_err(e)?;
    legend
        .draw(&text("angle unknown (estimated)", 24, y))
        .map_err(e)?;
    y += 20;
    legend
        .draw(&PathElement::new(vec![(4, y + 6), (20, y + 6)], BLACK))
        .map_err(e)?;
    legend
        .draw(&text("Cramér–Rao limit (efficient mean |Δd|)", 24, y))
        .map_err(e)?;
    Ok(())
}

/// Chart size, pixels.
pub const SIZE: (u32, u32) = (1100, 560);

struct TradeChart<'a> {
    rows: &'a [TradeRow],
    title: &'a str,
}

impl Chart for TradeChart<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String> {
        draw(root, self.rows, self.title)
    }
}

/// Draw the chart to `out`: SVG when it ends in `.svg`, else PNG.
pub fn write_chart(rows: &[TradeRow], title: &str, out: &Path) -> Result<(), RenderError> {
    chart::write(&TradeChart { rows, title }, SIZE, out)
}
