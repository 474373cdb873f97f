//! One channel of an irid map file as a picture: viridis over the valid
//! pixels, a colour bar with the channel's unit, a title, and invalid
//! pixels in fixed colours by reason with a legend of the reasons present.
//!
//! Promise: a valid pixel's colour is exactly `viridis((v − lo)/(hi − lo))`
//! (clamped to the range) and an invalid one exactly [`reason_colour`] of
//! its reason, at every picture pixel the map pixel covers
//! ([`MapPicture::map_pixel`] says where), so a picture can be checked by
//! reading it back.

use super::canvas::{font, nice_ticks, tick_label, RgbImage, MAX_SIDE};
use super::RenderError;
use crate::estimate::Reason;
use crate::io::exr_maps::{Channels, MAP_UNITS};
use plotters::prelude::*;

/// The channels `irid render --channel` accepts.
pub const CHANNELS: [&str; 7] = [
    "thickness_nm",
    "sigma_thickness_nm",
    "theta_deg",
    "sigma_theta_deg",
    "n_film",
    "residual_rms",
    "reason",
];

/// What to draw.
#[derive(Clone, Debug)]
pub struct MapStyle {
    /// The channel.
    pub channel: String,
    /// Colour range; `None`: the valid pixels' minimum to maximum.
    pub range: Option<(f64, f64)>,
    /// Title line (the channel and the file, typically).
    pub title: String,
}

/// A rendered map and where the map sits in it.
#[derive(Clone, Debug)]
pub struct MapPicture {
    /// The picture.
    pub image: RgbImage,
    /// Top-left corner of the map in the picture.
    pub origin: (usize, usize),
    /// Picture pixels per map pixel along each axis (below 1: the map is
    /// shown subsampled).
    pub scale: f64,
    /// The colour range used.
    pub range: (f64, f64),
    /// Valid pixels / all pixels.
    pub valid_fraction: f64,
}

impl MapPicture {
    /// The picture pixel at the centre of map pixel `(x, y)`.
    pub fn map_pixel(&self, x: usize, y: usize) -> (usize, usize) {
        let c = |i: usize| ((i as f64 + 0.5) * self.scale) as usize;
        (self.origin.0 + c(x), self.origin.1 + c(y))
    }
}

/// The colour of a value at fraction `t` of the range (clamped).
pub fn viridis(t: f64) -> [u8; 3] {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let c = colorous::VIRIDIS.eval_continuous(t);
    [c.r, c.g, c.b]
}

/// The fixed colour of an invalid pixel's reason: greys, warm and purple
/// tones that viridis (blue–green–yellow) never produces.
pub fn reason_colour(code: u8) -> [u8; 3] {
    match code {
        1 => [0, 0, 0],        // non-finite input
        2 => [70, 70, 70],     // dark
        3 => [255, 255, 255],  // saturated
        4 => [150, 150, 150],  // missing bands
        5 => [255, 127, 14],   // no fringe
        6 => [214, 39, 40],    // ambiguous order
        7 => [227, 119, 194],  // poor fit
        8 => [23, 190, 207],   // angle not identifiable (reason map only)
        9 => [140, 86, 75],    // out of model
        10 => [205, 205, 205], // masked
        11 => [148, 103, 189], // unresolved
        12 => [255, 0, 255],   // at bound
        0 => [44, 160, 44],    // ok (reason map only)
        _ => [255, 255, 0],    // unknown code
    }
}

fn reason_name(code: u8) -> String {
    match Reason::from_code(code) {
        Some(r) => format!("{code} {}", r.name()),
        None => format!("{code} unknown code"),
    }
}

/// The unit of a channel, from the file or irid's table.
fn unit_of(c: &Channels, channel: &str) -> String {
    c.attribute(&format!("irid.units.{channel}"))
        .map(str::to_string)
        .or_else(|| {
            MAP_UNITS
                .iter()
                .find(|(n, _)| *n == channel)
                .map(|(_, u)| u.to_string())
        })
        .unwrap_or_default()
}

/// Per pixel: `Ok(value)` to colour by value, `Err(code)` to colour by
/// reason.
fn classify(c: &Channels, channel: &str) -> Result<Vec<Result<f64, u8>>, RenderError> {
    let values = c
        .channel(channel)
        .ok_or_else(|| RenderError::input(format!("no channel `{channel}` in the map file")))?;
    let n = c.width * c.height;
    if values.len() != n {
        return Err(RenderError::input(format!(
            "channel `{channel}` has the wrong length"
        )));
    }
    let reason = c.channel("reason");
    let valid = c.channel("valid");
    let code_at = |i: usize| -> u8 {
        reason
            .and_then(|r| r.get(i))
            .filter(|v| v.is_finite() && **v >= 0.0 && **v < 255.0)
            .map_or(255, |v| *v as u8)
    };
    Ok((0..n)
        .map(|i| {
            if channel == "reason" {
                return Err(code_at(i));
            }
            let ok = valid.and_then(|v| v.get(i)).is_none_or(|v| *v > 0.5);
            let v = values[i] as f64;
            if ok && v.is_finite() {
                Ok(v)
            } else {
                // A valid pixel with a non-finite value (σ_θ of a known
                // angle) still needs a colour: call it non-finite.
                Err(if ok { 1 } else { code_at(i) })
            }
        })
        .collect())
}

fn auto_range(px: &[Result<f64, u8>]) -> Option<(f64, f64)> {
    let (lo, hi) = px
        .iter()
        .filter_map(|p| p.as_ref().ok())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(*v), b.max(*v))
        });
    if !lo.is_finite() {
        return None;
    }
    if hi > lo {
        Some((lo, hi))
    } else {
        let pad = lo.abs().max(1.0) * 1e-3;
        Some((lo - pad, hi + pad))
    }
}

const MARGIN: usize = 20;
const TITLE_H: usize = 44;
const BAR_W: usize = 22;
const BAR_LABEL_W: usize = 110;
const LEGEND_ROW: usize = 20;

/// Render one channel of a map file.
pub fn render_map(c: &Channels, style: &MapStyle) -> Result<MapPicture, RenderError> {
    if c.width == 0 || c.height == 0 {
        return Err(RenderError::input("empty map"));
    }
    let px = classify(c, &style.channel)?;
    let categorical = style.channel == "reason";
    let range = match style.range {
        Some((lo, hi)) if lo.is_finite() && hi.is_finite() && hi > lo => (lo, hi),
        Some((lo, hi)) => {
            return Err(RenderError::input(format!(
                "range {lo}:{hi}: need finite LO < HI"
            )))
        }
        None => auto_range(&px).unwrap_or((0.0, 1.0)),
    };
    // Picture pixels per map pixel: enlarge small maps to ~700 px across,
    // shrink large ones to at most 1600.
    let fit = (700.0 / c.width as f64).min(500.0 / c.height as f64);
    let scale = if fit >= 1.0 {
        fit.floor()
    } else {
        (1600.0 / c.width as f64)
            .min(1200.0 / c.height as f64)
            .min(1.0)
    };
    let (dw, dh) = (
        ((c.width as f64 * scale).round() as usize).max(1),
        ((c.height as f64 * scale).round() as usize).max(1),
    );
    let mut counts = [0usize; 256];
    for p in &px {
        if let Err(code) = p {
            counts[*code as usize] += 1;
        }
    }
    let present: Vec<u8> = (0..=255u8).filter(|c| counts[*c as usize] > 0).collect();
    let bar_h = dh.max(200);
    let width = (MARGIN + dw + MARGIN + BAR_W + BAR_LABEL_W).max(520);
    let legend_h = if present.is_empty() {
        0
    } else {
        MARGIN + LEGEND_ROW * present.len()
    };
    let height = TITLE_H + bar_h.max(dh) + legend_h + MARGIN;
    if width > MAX_SIDE || height > MAX_SIDE {
        return Err(RenderError::input("map too large to draw"));
    }
    let mut img = RgbImage::new(width, height)?;
    let origin = (MARGIN, TITLE_H);
    // The map itself, nearest-neighbour.
    for y in 0..dh {
        let sy = ((y as f64 + 0.5) / scale) as usize;
        for x in 0..dw {
            let sx = ((x as f64 + 0.5) / scale) as usize;
            let i = sy.min(c.height - 1) * c.width + sx.min(c.width - 1);
            let col = match px[i] {
                Ok(v) => viridis((v - range.0) / (range.1 - range.0)),
                Err(code) => reason_colour(code),
            };
            img.put(origin.0 + x, origin.1 + y, col);
        }
    }
    let bar_x = MARGIN + dw + MARGIN;
    if !categorical {
        for y in 0..bar_h {
            let t = 1.0 - (y as f64 + 0.5) / bar_h as f64;
            img.fill(bar_x, TITLE_H + y, BAR_W, 1, viridis(t));
        }
    }
    let valid = match c.channel("valid") {
        Some(v) => v.iter().filter(|v| **v > 0.5).count(),
        None => px.iter().filter(|p| p.is_ok()).count(),
    };
    let valid_fraction = valid as f64 / px.len() as f64;
    let unit = unit_of(c, &style.channel);
    let legend_y = TITLE_H + bar_h.max(dh) + MARGIN;
    img.draw(|root| {
        let e = |e: DrawingAreaErrorKind<_>| e.to_string();
        root.draw(&Text::new(
            style.title.clone(),
            (MARGIN as i32, 6),
            font(17.0),
        ))
        .map_err(e)?;
        let sub = if categorical {
            format!("reason codes; {:.1} % valid", 100.0 * valid_fraction)
        } else {
            format!(
                "{} [{}]; {:.1} % valid; range {:.4} to {:.4}",
                style.channel,
                unit,
                100.0 * valid_fraction,
                range.0,
                range.1
            )
        };
        root.draw(&Text::new(sub, (MARGIN as i32, 26), font(13.0)))
            .map_err(e)?;
        if !categorical {
            let ticks = nice_ticks(range.0, range.1, 6);
            for t in &ticks {
                let f = (t - range.0) / (range.1 - range.0);
                let y = (TITLE_H as f64 + (1.0 - f) * bar_h as f64) as i32;
                let x = (bar_x + BAR_W) as i32;
                root.draw(&PathElement::new(vec![(x, y), (x + 5, y)], BLACK))
                    .map_err(e)?;
                root.draw(&Text::new(
                    tick_label(*t, &ticks),
                    (x + 8, y - 7),
                    font(12.0),
                ))
                .map_err(e)?;
            }
            let u: String = unit.chars().take(14).collect();
            let ux = (bar_x + BAR_W + 8) as i32;
            root.draw(&Text::new(
                u,
                (ux, (TITLE_H + bar_h) as i32 - 14),
                font(12.0),
            ))
            .map_err(e)?;
        }
        for (k, code) in present.iter().enumerate() {
            let y = (legend_y + k * LEGEND_ROW) as i32;
            let col = reason_colour(*code);
            let rgb = RGBColor(col[0], col[1], col[2]);
            let x = MARGIN as i32;
            root.draw(&Rectangle::new([(x, y), (x + 14, y + 14)], rgb.filled()))
                .map_err(e)?;
            root.draw(&Rectangle::new([(x, y), (x + 14, y + 14)], BLACK))
                .map_err(e)?;
            let n = counts[*code as usize];
            let label = format!("{}: {n} px", reason_name(*code));
            root.draw(&Text::new(label, (x + 22, y), font(13.0)))
                .map_err(e)?;
        }
        Ok(())
    })?;
    Ok(MapPicture {
        image: img,
        origin,
        scale,
        range,
        valid_fraction,
    })
}

/// Parse `LO:HI`.
pub fn parse_range(s: &str) -> Result<(f64, f64), RenderError> {
    let bad = || RenderError::input(format!("range {s:?}: expected LO:HI with LO < HI"));
    let (a, b) = s.split_once(':').ok_or_else(bad)?;
    let lo: f64 = a.trim().parse().map_err(|_| bad())?;
    let hi: f64 = b.trim().parse().map_err(|_| bad())?;
    if lo.is_finite() && hi.is_finite() && lo < hi {
        Ok((lo, hi))
    } else {
        Err(bad())
    }
}

/// The preview of a map file: `thickness_nm`, titled with the file's name,
/// written beside it as `NAME.png`. Returns the PNG's path.
pub fn write_preview(
    exr_path: &std::path::Path,
    maps: &crate::estimate::ParamMaps,
) -> Result<std::path::PathBuf, RenderError> {
    let c = Channels::from_maps(maps);
    let name = exr_path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let style = MapStyle {
        channel: "thickness_nm".into(),
        range: None,
        title: format!("film thickness: {name}"),
    };
    let png = exr_path.with_extension("png");
    render_map(&c, &style)?.image.write_png(&png)?;
    Ok(png)
}
