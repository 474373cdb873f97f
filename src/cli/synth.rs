//! `irid synth`: render a scene's ground truth into an ENVI cube (the
//! fixture generator of the tests, and a way to try irid without
//! hardware), with the truth beside it as EXR (`<name>.truth.exr`, channels
//! `thickness_nm`, `theta_deg`, `n_film`).

use super::common::{parse_wavelengths, SceneSource};
use crate::io::envi::{self, ByteOrder, DataType, Interleave, WriteOptions};
use crate::io::exr_maps::{self, Channels, ATTR_PREFIX};
use crate::synth::{scene_bands, Renderer};
use anyhow::Context;
use std::path::{Path, PathBuf};

/// Arguments of `irid synth`.
#[derive(Debug, clap::Args)]
pub struct SynthArgs {
    /// Scene TOML with a [truth] section (default: the paper's cylinder).
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Output header, e.g. `cube.hdr` (data goes to `cube.img`).
    #[arg(long, value_name = "FILE.hdr")]
    pub out: PathBuf,
    /// Replace existing output files (without it, an existing output is an
    /// error and is left untouched).
    #[arg(long)]
    pub force: bool,

    /// Noise seed (default: the scene's).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Gaussian reflectance noise σ (default: the scene's).
    #[arg(long, value_name = "SIGMA")]
    pub noise: Option<f64>,
    /// Band centres, nm: `start:stop:step` or a comma list (default: the scene's).
    #[arg(long, value_name = "LIST")]
    pub bands: Option<String>,
    /// Band FWHM, nm (default: the scene's).
    #[arg(long = "fwhm-nm", value_name = "NM")]
    pub fwhm_nm: Option<f64>,
    /// Sample type: f32 (4), f64 (5), u8 (1), i16 (2), u16 (12), i32 (3), u32 (13).
    #[arg(long, default_value = "f32", value_parser = DataType::parse)]
    pub data_type: DataType,
    /// Interleave: bsq, bil or bip.
    #[arg(long, default_value = "bsq", value_parser = Interleave::parse)]
    pub interleave: Interleave,
    /// Write big-endian samples (`byte order = 1`).
    #[arg(long)]
    pub big_endian: bool,
    /// `reflectance scale factor` (default 1 for floats, 10000 for integers, 255 for u8).
    #[arg(long, value_name = "F")]
    pub scale: Option<f64>,
}

/// `cube.hdr` → `cube.truth.exr`.
pub fn truth_path(out: &Path) -> PathBuf {
    let (hdr, _) = envi::output_paths(out);
    let stem = hdr.with_extension("");
    let stem = if stem.extension().is_some() {
        stem.with_extension("")
    } else {
        stem
    };
    stem.with_extension("truth.exr")
}

/// Run `irid synth`.
pub fn run(a: &SynthArgs) -> anyhow::Result<()> {
    let (hdr, data) = envi::output_paths(&a.out);
    for p in [&hdr, &data, &truth_path(&a.out)] {
        crate::io::atomic::check_new(p, super::common::overwrite(a.force))?;
    }
    let mut src = match &a.scene {
        Some(p) => SceneSource::load(p)?,
        None => SceneSource::paper_cylinder(),
    };
    {
        let truth = src
            .file
            .truth
            .as_mut()
            .with_context(|| format!("{}: no [truth] section to render", src.origin))?;
        if let Some(s) = a.seed {
            truth.seed = s;
        }
        if let Some(n) = a.noise {
            anyhow::ensure!(n.is_finite() && n >= 0.0, "--noise must be ≥ 0, not {n}");
            truth.noise_sigma = n;
        }
    }
    if let Some(list) = &a.bands {
        let centers = parse_wavelengths(list).map_err(|m| anyhow::anyhow!("--bands: {m}"))?;
        let b = &mut src.file.bands;
        b.centers_nm = Some(centers);
        (b.start_nm, b.stop_nm, b.step_nm) = (None, None, None);
    }
    if let Some(f) = a.fwhm_nm {
        src.file.bands.fwhm_nm = Some(f);
    }
    let scene = src.resolve()?;
    let bands = scene_bands(&scene).with_context(|| src.origin.clone())?;
    let renderer = Renderer::new(&scene)?;
    let cube = renderer.render_cube(&bands)?;
    let (noise, seed) = renderer.noise();
    let opts = WriteOptions {
        data_type: a.data_type,
        interleave: a.interleave,
        byte_order: if a.big_endian {
            ByteOrder::Big
        } else {
            ByteOrder::Little
        },
        header_offset: 0,
        reflectance_scale_factor: a.scale,
        description: Some(format!(
            "irid {} synthetic cube: scene {}, noise sigma {noise}, seed {seed}",
            crate::VERSION,
            scene.name
        )),
    };
    let (hdr, data) = envi::write_cube(&a.out, &cube, &opts)?;
    let truth = renderer.truth_maps(&bands);
    let tpath = truth_path(&a.out);
    let n = truth.width * truth.height;
    let attr = |k: &str, v: String| (format!("{ATTR_PREFIX}{k}"), v);
    exr_maps::write_channels(
        &tpath,
        &Channels {
            width: truth.width,
            height: truth.height,
            channels: vec![
                ("thickness_nm".into(), truth.thickness_nm),
                ("theta_deg".into(), truth.theta_deg),
                ("n_film".into(), vec![truth.n_film as f32; n]),
            ],
            attributes: vec![
                attr("version", crate::VERSION.into()),
                attr("scene", scene.name.clone()),
                attr("n_film", format!("{}", truth.n_film)),
                attr("noise_sigma", format!("{noise}")),
                attr("seed", format!("{seed}")),
                attr("units.thickness_nm", "nm".into()),
                attr("units.theta_deg", "degrees".into()),
                attr("units.n_film", "1 (refractive index)".into()),
            ],
        },
    )?;
    eprintln!(
        "irid synth: {} × {} × {} bands → {} + {}, truth {}",
        cube.width,
        cube.height,
        cube.bands.len(),
        hdr.display(),
        data.display(),
        tpath.display()
    );
    Ok(())
}
