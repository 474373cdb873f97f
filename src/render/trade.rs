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

use super::canvas::{RgbImage, FONT_FAMILY};
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

fn cells(line: &str) -> Vec<String> {
    // `\|` inside a cell is an escaped bar, not a separator.
    let l = line.trim().replace("\\|", "\u{1}");
    let l = l.strip_prefix('|').unwrap_or(&l);
    let l = l.strip_suffix('|').unwrap_or(l);
    l.split('|')
        .map(|c| c.replace('\u{1}', "|").trim().to_string())
        .collect()
}

/// A number with an optional SI suffix (`k`, `M`, `G`) and unit.
fn number(s: &str) -> Option<f64> {
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

/// The rows of the first scene-matrix table in `text`.
pub fn parse_table(text: &str) -> Result<Vec<TradeRow>, RenderError> {
    let lines: Vec<&str> = text.lines().collect();
    let start = lines
        .iter()
        .position(|l| {
            let c = cells(l);
            l.trim_start().starts_with('|')
                && ["scene", "angle", "mode", "pixels/s", "efficient"]
                    .iter()
                    .all(|h| c.iter().any(|x| x == h))
        })
        .ok_or_else(|| {
            RenderError::input(
                "no scene-matrix table (a header with scene, angle, mode, pixels/s, mean |Δd|, efficient)",
            )
        })?;
    let head = cells(lines[start]);
    let col = |name: &str| -> Result<usize, RenderError> {
        head.iter()
            .position(|h| h == name)
            .ok_or_else(|| RenderError::input(format!("table has no `{name}` column")))
    };
    let (cs, ca, cm, cp, ce, cf) = (
        col("scene")?,
        col("angle")?,
        col("mode")?,
        col("pixels/s")?,
        col("mean |Δd|")?,
        col("efficient")?,
    );
    let mut rows = Vec::new();
    for (k, line) in lines.iter().enumerate().skip(start + 2) {
        if !line.trim_start().starts_with('|') {
            break;
        }
        let c = cells(line);
        let get = |i: usize| c.get(i).map(String::as_str).unwrap_or("");
        let bad =
            |what: &str| RenderError::input(format!("table line {}: bad {what}: {line:?}", k + 1));
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

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

fn marker<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    at: (i32, i32),
    mode: &str,
    style: ShapeStyle,
) -> Result<(), String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    let (x, y) = at;
    match mode {
        "fast" => root.draw(&TriangleMarker::new((x, y), 7, style)).map_err(e),
        "accurate" => root
            .draw(&Rectangle::new([(x - 5, y - 5), (x + 5, y + 5)], style))
            .map_err(e),
        _ => root.draw(&Circle::new((x, y), 5, style)).map_err(e),
    }
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
    for mode in ["fast", "balanced", "accurate"] {
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

/// Draw the chart to `out`: SVG when it ends in `.svg`, else PNG.
pub fn write_chart(rows: &[TradeRow], title: &str, out: &Path) -> Result<(), RenderError> {
    let svg = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("svg"));
    if svg {
        super::canvas::register_font();
        let mut text = String::new();
        {
            let root = SVGBackend::with_string(&mut text, SIZE).into_drawing_area();
            draw(&root, rows, title).map_err(RenderError::Draw)?;
            root.present()
                .map_err(|e| RenderError::Draw(e.to_string()))?;
        }
        super::canvas::write_atomic(out, text.as_bytes())
    } else {
        let mut img = RgbImage::new(SIZE.0 as usize, SIZE.1 as usize)?;
        img.draw(|root| draw(root, rows, title))?;
        img.write_png(out)
    }
}
