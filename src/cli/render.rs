//! `irid render`: pictures from irid's files.
//!
//! - `irid render MAP.exr --out MAP.png [--channel C] [--range LO:HI]`: one
//!   channel as a viridis map with a colour bar; invalid pixels by reason.
//! - `irid render MAP.exr --colour --cube CUBE.hdr --out COLOUR.png`: the
//!   measured cube and the map's re-synthesised spectra side by side in
//!   sRGB (D65, CIE 1931 2°), and the spectral RMSE between them.
//! - `irid render --chart --out CHART.png`: a film's colour against
//!   thickness and angle.
//! - `irid render --trade TABLE.md --out TRADE.svg`: the speed/accuracy
//!   chart from the scene-matrix benchmark's table.
//! - `irid render --noise TABLE.md --out NOISE.svg`: thickness error
//!   against noise from the noise-sweep benchmark's table.

use super::common::SceneOverrides;
use crate::io::{envi, exr_maps};
use crate::render::map::{self, MapStyle};
use crate::render::{film_colour, noise, trade, RenderError};
use crate::scene::{FilmKnowledge, Scene};
use anyhow::{bail, Context};
use std::path::{Path, PathBuf};

/// Arguments of `irid render`.
#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    /// The map file (OpenEXR, as `irid fit` and `irid run` write).
    #[arg(value_name = "MAP.exr")]
    pub map: Option<PathBuf>,
    /// The picture to write (`.png`; the trade and noise charts also `.svg`).
    #[arg(long, value_name = "OUT.png")]
    pub out: PathBuf,
    /// The channel to draw.
    #[arg(long, default_value = "thickness_nm", value_parser = clap::builder::PossibleValuesParser::new(map::CHANNELS))]
    pub channel: String,
    /// Colour range LO:HI (default: the valid pixels' min to max).
    #[arg(long, value_name = "LO:HI", allow_hyphen_values = true)]
    pub range: Option<String>,
    /// Render the measured cube and the map's re-synthesised spectra in
    /// sRGB (D65, CIE 1931 2°) side by side; needs --cube.
    #[arg(long, requires = "cube", requires = "map")]
    pub colour: bool,
    /// The cube the map was fitted from (reflectance ENVI), for --colour.
    #[arg(long, value_name = "CUBE.hdr")]
    pub cube: Option<PathBuf>,
    /// A chart of the film's colour against thickness and angle.
    #[arg(long, conflicts_with_all = ["colour", "trade", "noise"])]
    pub chart: bool,
    /// --chart: thickness range, nm.
    #[arg(long, value_name = "LO:HI", default_value = "0:1500")]
    pub thickness: String,
    /// --chart: angle range, degrees.
    #[arg(long, value_name = "LO:HI", default_value = "0:60")]
    pub angle: String,
    /// Draw the speed/accuracy chart from a Markdown table printed by
    /// `cargo bench --bench scene_matrix` (a file holding it, e.g. README.md).
    #[arg(long, value_name = "TABLE.md", conflicts_with_all = ["colour", "map"])]
    pub trade: Option<PathBuf>,
    /// Draw thickness error against noise from a Markdown table printed by
    /// `cargo bench --bench noise_sweep` (a file holding it, e.g. README.md).
    #[arg(long, value_name = "TABLE.md", conflicts_with_all = ["colour", "map", "trade"])]
    pub noise: Option<PathBuf>,
    /// Scene TOML for --colour and --chart (media, polarisation).
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Replace an existing output picture (without it, an existing one is
    /// an error and is left untouched).
    #[arg(long)]
    pub force: bool,
    /// Scene overrides for --colour and --chart.
    #[command(flatten)]
    pub overrides: SceneOverrides,
}

/// Run `irid render`.
pub fn run(a: &RenderArgs) -> anyhow::Result<()> {
    let overwrite = if a.force {
        crate::io::atomic::Overwrite::Replace
    } else {
        crate::io::atomic::Overwrite::Refuse
    };
    crate::io::atomic::check_new(&a.out, overwrite)?;
    if let Some(table) = &a.trade {
        let title = "irid: thickness error against speed, per mode and scene (scene_matrix bench)";
        return table_chart(table, &a.out, title, trade::parse_table, trade::write_chart);
    }
    if let Some(table) = &a.noise {
        let title = "irid: thickness error against noise, per mode (noise_sweep bench)";
        return table_chart(table, &a.out, title, noise::parse_table, noise::write_chart);
    }
    if a.chart {
        return chart(a);
    }
    let Some(path) = &a.map else {
        bail!("nothing to render: give MAP.exr, --chart, --trade TABLE.md or --noise TABLE.md");
    };
    if a.colour {
        return colour(a, path);
    }
    let c = exr_maps::read_channels(path)?;
    let range = a.range.as_deref().map(map::parse_range).transpose()?;
    let name = file_name(path);
    let style = MapStyle {
        channel: a.channel.clone(),
        range,
        title: format!("{}: {name}", a.channel),
    };
    let pic =
        map::render_map(&c, &style).with_context(|| format!("rendering {}", path.display()))?;
    pic.image.write_png(&a.out)?;
    eprintln!(
        "irid render: {} of {} ({} × {}, {:.1} % valid, range {:.4}..{:.4}) → {}",
        a.channel,
        path.display(),
        c.width,
        c.height,
        100.0 * pic.valid_fraction,
        pic.range.0,
        pic.range.1,
        a.out.display()
    );
    Ok(())
}

/// The scene for --colour and --chart: `--scene` (else one that knows
/// only an ambient of n = 1) with the command-line overrides.
fn scene(a: &RenderArgs) -> anyhow::Result<Scene> {
    super::fit::scene_with_overrides(a.scene.as_deref(), &a.overrides)
}

fn colour(a: &RenderArgs, path: &Path) -> anyhow::Result<()> {
    let scene = scene(a)?;
    let maps = exr_maps::read_maps(path)?;
    let cube_path = a
        .cube
        .as_deref()
        .context("--colour needs --cube CUBE.hdr")?;
    let cube = envi::read_cube(cube_path)?;
    let title = format!(
        "film colour: {} vs the fit {}",
        file_name(cube_path),
        file_name(path)
    );
    let cmp = film_colour::compare(&cube, &maps, &scene, &title)?;
    cmp.image.write_png(&a.out)?;
    println!(
        "spectral RMSE {:.5} (reflectance) over {} valid pixels × {} bands → {}",
        cmp.rmse,
        cmp.pixels,
        cube.bands.len(),
        a.out.display()
    );
    Ok(())
}

fn chart(a: &RenderArgs) -> anyhow::Result<()> {
    let scene = scene(a)?;
    let n_film = match &scene.film {
        FilmKnowledge::Known(d) => d.index_at(550.0).map(|n| n.re).unwrap_or(f64::NAN),
        FilmKnowledge::Unknown { .. } => {
            bail!("--chart needs the film: give --n2 N or --material2 NAME (or a --scene that knows it)")
        }
    };
    let t = map::parse_range(&a.thickness).context("--thickness")?;
    let th = map::parse_range(&a.angle).context("--angle")?;
    let img = film_colour::chart(&scene, n_film, t, th, scene.polarization)?;
    img.write_png(&a.out)?;
    eprintln!("irid render: colour chart → {}", a.out.display());
    Ok(())
}

/// A benchmark chart: the table `parse` finds in the file `table`, drawn
/// by `write` to `out`.
fn table_chart<R>(
    table: &Path,
    out: &Path,
    title: &str,
    parse: fn(&str) -> Result<Vec<R>, RenderError>,
    write: fn(&[R], &str, &Path) -> Result<(), RenderError>,
) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(table)
        .with_context(|| format!("cannot read {}", table.display()))?;
    let rows = parse(&text).with_context(|| table.display().to_string())?;
    write(&rows, title, out)?;
    eprintln!(
        "irid render: {} rows of {} → {}",
        rows.len(),
        table.display(),
        out.display()
    );
    Ok(())
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned())
}
