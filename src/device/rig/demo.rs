//! The demo rig: a synthetic camera looking at a scene (default: the
//! paper's cylinder, stretched to the size asked for) through an emulated
//! filter — the VariSpec firmware on a pseudo-terminal driven by the real
//! serial driver, or the in-process emulation. The camera runs at its frame
//! rate (sped up as the emulated controller is) unless asked not to.

use super::{Rig, RigError};
use crate::device::camera::synthetic::{FilterView, SensorModel, SyntheticCamera, SyntheticConfig};
use crate::device::filter::FilterError;
use crate::pipeline::sequencer::{order_for, BandTuner, ControllerTuner, EmulatedTuner, SeqMode};
use crate::scene::{Field, Scene, SceneFile};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// What the demo rig is built from (the demo flags of `irid run`).
#[derive(Debug, Clone, PartialEq)]
pub struct DemoOptions {
    /// Scene file (`None`: the paper's cylinder).
    pub scene: Option<PathBuf>,
    /// Image size, `WxH` (the scene's fields stretch to it; `None`: the
    /// scene's own).
    pub size: Option<String>,
    /// Band order: `ascending`, `descending`, `interleaved`.
    pub order: String,
    /// Hardware-triggered pairing (camera triggered by the filter's
    /// settled output) instead of software stepping; implies the
    /// in-process filter.
    pub triggered: bool,
    /// The emulated filter in-process instead of the VariSpec firmware on
    /// a pseudo-terminal.
    pub in_process_filter: bool,
    /// The emulated controller's clock runs this many times faster than a
    /// real unit's; the camera's frame rate is sped up alike.
    pub time_scale: f64,
    /// The camera delivers frames at its frame rate, as a real one does
    /// (`false`: as fast as the CPU renders them, and the pipeline rightly
    /// drops the sweeps it cannot take).
    pub paced: bool,
    /// Noise seed (also the in-process filter's jitter).
    pub seed: u64,
}

impl Default for DemoOptions {
    fn default() -> Self {
        DemoOptions {
            scene: None,
            size: None,
            order: "ascending".into(),
            triggered: false,
            in_process_filter: false,
            time_scale: 5.0,
            paced: true,
            seed: 1,
        }
    }
}

/// The demo rig: synthetic camera + emulated filter.
pub fn demo_rig(opts: &DemoOptions) -> Result<Rig, RigError> {
    let (file, base) = demo_scene_file(opts)?;
    demo_rig_for(opts, &file, &base)
}

/// The demo's scene file (`opts.scene` or the embedded cylinder, stretched
/// to `opts.size`) and where its relative paths start.
pub fn demo_scene_file(opts: &DemoOptions) -> Result<(SceneFile, PathBuf), RigError> {
    let (mut file, base): (SceneFile, PathBuf) = match &opts.scene {
        Some(p) => {
            let path = p.display().to_string();
            let text = std::fs::read_to_string(p).map_err(|source| RigError::SceneRead {
                path: path.clone(),
                source,
            })?;
            let f = toml::from_str(&text).map_err(|e| RigError::SceneParse {
                path,
                message: e.to_string(),
            })?;
            (f, p.parent().unwrap_or(Path::new(".")).to_path_buf())
        }
        None => (
            toml::from_str(crate::scene::PAPER_CYLINDER).expect("embedded scene parses"),
            PathBuf::from("."),
        ),
    };
    if let Some(s) = &opts.size {
        let (w, h) = parse_size(s)?;
        let t = file
            .truth
            .as_mut()
            .ok_or(RigError::Incomplete("the scene has no [truth] to render"))?;
        // Fields given per row / column are stretched to the new size.
        let (ow, oh) = (t.width as f64, t.height as f64);
        let stretch = |f: &mut Field| match f {
            Field::Rows([_, s]) => *s *= (oh - 1.0).max(1.0) / (h as f64 - 1.0).max(1.0),
            Field::Columns([_, s]) => *s *= (ow - 1.0).max(1.0) / (w as f64 - 1.0).max(1.0),
            _ => {}
        };
        stretch(&mut t.thickness_nm);
        if let Some(a) = t.angle_deg.as_mut() {
            stretch(a);
        }
        t.width = w;
        t.height = h;
    }
    Ok((file, base))
}

/// `WxH`, each at least 1, at most 2²⁶ pixels in all.
fn parse_size(s: &str) -> Result<(usize, usize), RigError> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| RigError::Size("--size wants WxH, e.g. 1280x1024".into()))?;
    let num = |v: &str| {
        v.trim()
            .parse::<usize>()
            .map_err(|e| RigError::Size(format!("--size {s}: {e}")))
    };
    let (w, h) = (num(w)?, num(h)?);
    if w == 0 || h == 0 || w.checked_mul(h).is_none_or(|n| n > 1 << 26) {
        return Err(RigError::Size(format!("--size {s}: out of range")));
    }
    Ok((w, h))
}

fn demo_rig_for(opts: &DemoOptions, file: &SceneFile, base: &Path) -> Result<Rig, RigError> {
    let scene = Scene::resolve(file, base).map_err(|source| RigError::Scene {
        what: "scene".into(),
        source,
    })?;
    let bands = scene
        .bands
        .clone()
        .ok_or(RigError::Incomplete("the scene has no [bands]"))?;
    let nm: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    let order = order_for(&opts.order, bands.len(), &nm)
        .ok_or_else(|| RigError::Order(opts.order.clone()))?;
    let view = FilterView::new();
    let big = file_pixels(&scene) > 100_000;
    let mut cfg = SyntheticConfig {
        sensor: SensorModel::default(),
        seed: opts.seed,
        // Large images draw their noise from a pool at a fresh offset per
        // frame, so the camera does not limit the line.
        noise_pool: big,
        // At its frame rate (sped up as the emulated controller is), as a
        // real camera: unpaced, frames come as fast as the CPU renders
        // them and the pipeline rightly drops the sweeps it cannot take.
        realtime: opts.paced,
        speed: opts.time_scale,
        ..Default::default()
    };
    let seq_mode = if opts.triggered {
        cfg.trigger_palette = Some(order.clone());
        SeqMode::Triggered
    } else {
        SeqMode::Stepped
    };
    let camera =
        SyntheticCamera::new(&scene, &bands, view.clone(), cfg).map_err(RigError::Render)?;
    let (tuner, emulator): (Box<dyn BandTuner>, _) = if opts.in_process_filter || opts.triggered {
        let t = EmulatedTuner::new(
            view,
            Duration::from_millis(50),
            Duration::from_millis(2),
            opts.seed,
        );
        (Box::new(t), None)
    } else {
        let (t, h) = emulated_varispec(view, opts.time_scale)?;
        (Box::new(t), Some(h))
    };
    Ok(Rig {
        source: Box::new(camera),
        tuner,
        scene,
        bands,
        order,
        seq_mode,
        calibration: None,
        _emulator: emulator,
    })
}

fn file_pixels(scene: &Scene) -> usize {
    scene.truth.as_ref().map_or(0, |t| t.width * t.height)
}

/// The VariSpec firmware emulated on a pseudo-terminal, driven by the
/// serial driver, mirrored into `view`.
pub fn emulated_varispec(
    view: FilterView,
    time_scale: f64,
) -> Result<
    (
        ControllerTuner<crate::device::filter::VariSpec>,
        lctf_firmware::emu::EmulatorHandle,
    ),
    FilterError,
> {
    use crate::device::filter::{FilterController, VariSpec, VariSpecOptions};
    use lctf_firmware::emu::{spawn_pty, EmuConfig};
    let scale = lctf_firmware::TimeScale::new(time_scale);
    let h = spawn_pty(EmuConfig {
        time_scale: scale,
        ..EmuConfig::ready()
    })
    .map_err(|e| {
        FilterError::Io(std::io::Error::new(
            e.kind(),
            format!("spawning the emulated filter controller: {e}"),
        ))
    })?;
    let path = h.path().display().to_string();
    let mut ctrl = VariSpec::open(&path, VariSpecOptions::default())?;
    ctrl.ensure_ready(Duration::from_secs(10))?;
    Ok((
        ControllerTuner::new(ctrl, Some(view), time_scale, Duration::from_secs(2)),
        h,
    ))
}

#[cfg(test)]
mod tests {
    use super::parse_size;

    #[test]
    fn sizes_are_bounded_without_overflow() {
        assert_eq!(parse_size("1280x1024").unwrap(), (1280, 1024));
        assert_eq!(parse_size("8192X8192").unwrap(), (8192, 8192));
        // 2²⁶ + 1 pixels, and a product that overflows usize: both refused.
        assert!(parse_size("8193x8192").is_err());
        assert!(parse_size("4294967296x4294967296").is_err());
        let e = parse_size("4x").unwrap_err().to_string();
        assert!(e.contains("--size 4x"), "{e}");
        assert!(parse_size("0x5").is_err());
    }
}
