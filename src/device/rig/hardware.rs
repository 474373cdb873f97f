//! The rig of a `line.toml`: its scene and bands, a V4L2 camera (feature
//! `v4l2`; without it, an error saying how to rebuild), the VariSpec
//! controller on its serial port — initialised, and for triggered pairing
//! loaded with the band palette and armed — and where its stored
//! calibration lies. Nothing is captured here.

use super::{CameraSection, LineConfig, Rig, RigError, StoredCalibration};
use crate::device::camera::{FrameSource, PixelFormat};
use crate::device::filter::{FilterController, FilterError, VariSpec, VariSpecOptions};
use crate::optics::band::Band;
use crate::pipeline::sequencer::{order_for, ControllerTuner, SeqMode};
use crate::scene::{Scene, SceneFile};
use std::path::Path;
use std::time::Duration;

/// The hardware rig of `line.toml`, and the configuration itself.
pub fn hardware_rig(path: &Path) -> Result<(Rig, LineConfig), RigError> {
    let (line, base) = LineConfig::load(path)?;
    let scene = Scene::load(&base.join(&line.scene)).map_err(RigError::SceneLoad)?;
    let bands = line_bands(path, &line, &base, &scene)?;
    let nm: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    let order = order_for(&line.sequence.order, bands.len(), &nm).ok_or_else(|| {
        RigError::SequenceOrder {
            path: path.display().to_string(),
            order: line.sequence.order.clone(),
        }
    })?;
    let source = open_camera(&line.camera)?;
    let tuner = open_filter(&line, &order, &nm)?;
    let calibration = StoredCalibration {
        path: base.join(&line.calibration.file),
        max_age_h: line.calibration.max_age_h,
        white_reflectance: line.calibration.white_reflectance,
    };
    Ok((
        Rig {
            source,
            tuner: Box::new(tuner),
            scene,
            bands,
            order,
            seq_mode: line.sequence.mode,
            calibration: Some(calibration),
            _emulator: None,
        },
        line,
    ))
}

/// `line.toml`'s `[bands]`, else the scene's.
fn line_bands(
    path: &Path,
    line: &LineConfig,
    base: &Path,
    scene: &Scene,
) -> Result<Vec<Band>, RigError> {
    match &line.bands {
        Some(b) => {
            let mut f = SceneFile::default();
            f.substrate.n = Some(1.5);
            f.bands = b.clone();
            Scene::resolve(&f, base)
                .map_err(|source| RigError::Scene {
                    what: format!("{}: [bands]", path.display()),
                    source,
                })?
                .bands
                .ok_or(RigError::Incomplete("[bands] is empty"))
        }
        None => scene.bands.clone().ok_or(RigError::Incomplete(
            "neither line.toml nor the scene gives [bands]",
        )),
    }
}

/// The controller on `[filter]`'s port, ready; for triggered pairing with
/// the bands loaded as its palette in capture order and the sync armed.
fn open_filter(
    line: &LineConfig,
    order: &[usize],
    nm: &[f64],
) -> Result<ControllerTuner<VariSpec>, RigError> {
    let step = |step: &str| {
        let step = step.to_string();
        move |source: FilterError| RigError::Controller { step, source }
    };
    let mut ctrl = VariSpec::open(
        &line.filter.port,
        VariSpecOptions {
            baud: line.filter.baud,
            ..Default::default()
        },
    )
    .map_err(step(&format!(
        "opening the filter controller on {}",
        line.filter.port
    )))?;
    ctrl.ensure_ready(Duration::from_secs(60))
        .map_err(step("initialising the filter controller"))?;
    if line.sequence.mode == SeqMode::Triggered {
        let seqnm: Vec<f64> = order.iter().map(|&b| nm[b]).collect();
        ctrl.define_sequence(&seqnm)
            .map_err(step("loading the band palette"))?;
        ctrl.select_palette(0)
            .map_err(step("selecting the first band"))?;
        ctrl.arm_sync(1).map_err(step("arming the sync input"))?;
    }
    Ok(ControllerTuner::new(
        ctrl,
        None,
        1.0,
        Duration::from_millis(line.filter.settle_timeout_ms),
    ))
}

#[cfg(feature = "v4l2")]
fn open_camera(c: &CameraSection) -> Result<Box<dyn FrameSource>, RigError> {
    use crate::device::camera::v4l2::{V4l2Camera, V4l2Config};
    let format =
        PixelFormat::parse(&c.format).ok_or_else(|| RigError::CameraFormat(c.format.clone()))?;
    let mut cam = V4l2Camera::open(&V4l2Config {
        path: c.device.clone(),
        width: c.width,
        height: c.height,
        format,
        exposure_us: c.exposure_us,
        buffers: c.buffers,
    })?;
    if let Some(g) = c.gain {
        cam.set_gain(g)?;
    }
    Ok(Box::new(cam))
}

#[cfg(not(feature = "v4l2"))]
fn open_camera(c: &CameraSection) -> Result<Box<dyn FrameSource>, RigError> {
    let _ = PixelFormat::parse(&c.format);
    Err(RigError::NoV4l2(c.device.clone()))
}
