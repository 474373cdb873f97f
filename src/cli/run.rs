//! `irid run`: live thickness maps.
//!
//! With `--config line.toml`: real hardware (a V4L2 camera, a VariSpec
//! controller on a serial port, a stored calibration). Without: the demo —
//! a synthetic camera looking at the scene (default: the paper's cylinder)
//! through the emulated VariSpec firmware on a pseudo-terminal, calibrated
//! automatically at start (dark: no light; white: a reference target).
//!
//! Per sweep: `OUT/sweep-NNNNNN.exr` and one summary line (`--json`: one
//! JSON object per line). Ctrl-C abandons the sweep in progress, flushes
//! the finished ones and exits 0.

use crate::device::camera::synthetic::{FilterView, SensorModel, SyntheticCamera, SyntheticConfig};
use crate::device::camera::{FrameSource, PixelFormat, Target};
use crate::device::rig::{emulated_varispec, CameraSection, LineConfig};
use crate::estimate::{Mode, ParamMaps};
use crate::optics::band::Band;
use crate::pipeline::calibration::{
    capture_reference, CalExpect, CalMeta, Calibration, CalibrationPolicy, Calibrator, CapturePlan,
};
use crate::pipeline::output::{sweep_path, write_map, SweepSummary};
use crate::pipeline::profile::ProfileLayer;
use crate::pipeline::runner::{self, RunConfig, Setup, SweepSink};
use crate::pipeline::sequencer::{order_for, BandTuner, ControllerTuner, EmulatedTuner, SeqMode};
use crate::scene::{Scene, SceneFile};
use anyhow::{bail, Context};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// Whether `irid run` tracks fringe extrema while bands arrive.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Tracking {
    /// Always.
    On,
    /// Never.
    Off,
    /// Off: measured, the ingest it costs outweighs the solve it saves on
    /// two cores (see README); kept as a choice for machines with spare
    /// ingest CPU.
    Auto,
}

/// Arguments of `irid run`.
#[derive(clap::Args, Debug, Clone)]
pub struct RunArgs {
    /// Line configuration (camera, controller, bands, calibration, scene);
    /// without it, run the demo.
    #[arg(long, value_name = "line.toml")]
    pub config: Option<PathBuf>,
    /// Demo scene (default: the paper's cylinder); `web`: the moving-web
    /// production-line demo (see README "Production line").
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Sweeps to run, then exit (0: until Ctrl-C).
    #[arg(long, default_value_t = 3)]
    pub sweeps: u64,
    /// Output directory of the maps.
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Do not write maps (summaries only).
    #[arg(long)]
    pub no_maps: bool,
    /// One JSON object per sweep on stdout.
    #[arg(long)]
    pub json: bool,
    /// Also write a PNG preview (thickness, colour bar, invalid pixels by
    /// reason) beside each sweep's map.
    #[arg(long, conflicts_with = "no_maps")]
    pub png: bool,
    /// Serve a live page (latest map, trend, valid fraction, drops,
    /// latency) at this address, e.g. 127.0.0.1:8080.
    #[arg(long, value_name = "ADDR")]
    pub serve: Option<String>,
    /// Solver mode.
    #[arg(long, value_enum, default_value_t = Mode::Balanced)]
    pub mode: Mode,
    /// Solver threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Run every stage on one thread (deterministic).
    #[arg(long)]
    pub single_thread: bool,
    /// Track every pixel's fringe-extremum candidates while bands arrive
    /// (local maxima and minima of the smoothed spectrum, decided as soon
    /// as a band's neighbours are in), so that `fast` skips its own
    /// detection pass after the last band: `on`, `off`, or `auto` (= off:
    /// on two cores the ~1.6 ms per 1280×1024 frame it adds to ingest
    /// outweighs the ~5 % of `fast`'s solve it saves).
    #[arg(long, value_enum, default_value_t = Tracking::Auto)]
    pub track_extrema: Tracking,
    /// Demo: image size (the scene's fields stretch to it).
    #[arg(long, value_name = "WxH")]
    pub size: Option<String>,
    /// Band order: ascending, descending, interleaved.
    #[arg(long, default_value = "ascending")]
    pub order: String,
    /// Demo: hardware-triggered pairing (camera triggered by the filter's
    /// settled output) instead of software stepping.
    #[arg(long)]
    pub triggered: bool,
    /// Demo: the emulated filter in-process instead of the VariSpec
    /// firmware on a pseudo-terminal.
    #[arg(long)]
    pub in_process_filter: bool,
    /// Demo: the emulated controller's clock runs this many times faster
    /// than a real unit's.
    #[arg(long, default_value_t = 5.0)]
    pub time_scale: f64,
    /// Demo: let the synthetic camera run as fast as it can instead of at
    /// its frame rate (sped up by --time-scale); the pipeline will then
    /// rightly drop sweeps it cannot keep up with.
    #[arg(long)]
    pub unpaced: bool,
    /// Demo: noise seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Write a Chrome/Perfetto trace (JSON) of every span.
    #[arg(long, value_name = "FILE")]
    pub trace: Option<PathBuf>,
    /// Print per-stage latency percentiles and throughput at exit.
    #[arg(long)]
    pub profile: bool,
    /// With --config: write into an output folder that already holds sweep
    /// maps, replacing them (the demo always replaces its own).
    #[arg(long)]
    pub force: bool,
    /// Record what the line sees (raw frames, pairing, filter events,
    /// calibration, configuration) to this MCAP file while processing.
    #[arg(long, value_name = "FILE.mcap")]
    pub record: Option<PathBuf>,
    /// Chunk compression of the recording.
    #[arg(long, value_enum, default_value_t = super::record::RecordCompression::Lz4)]
    pub record_compression: super::record::RecordCompression,
}

#[derive(clap::Parser)]
struct DefaultsOnly {
    #[command(flatten)]
    args: RunArgs,
}

impl RunArgs {
    /// The defaults (what `irid` with no subcommand runs).
    pub fn defaults() -> RunArgs {
        <DefaultsOnly as clap::Parser>::parse_from(["irid"]).args
    }
}

/// Seconds since the Unix epoch (the CLI reads the clock; layers below are
/// passed it).
pub fn now_unix_s() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// A camera and a filter, ready to run.
pub struct Rig {
    /// The camera.
    pub source: Box<dyn FrameSource>,
    /// The filter.
    pub tuner: Box<dyn BandTuner>,
    /// Scene knowledge.
    pub scene: Scene,
    /// Bands, plane order.
    pub bands: Vec<Band>,
    /// Capture order.
    pub order: Vec<usize>,
    /// Pairing.
    pub seq_mode: SeqMode,
    /// Stored calibration and its limits, for hardware.
    pub calibration: Option<(PathBuf, f64, f64)>,
    /// Keeps the emulated controller's pseudo-terminal alive.
    pub _emulator: Option<lctf_firmware::emu::EmulatorHandle>,
}

fn parse_size(s: &str) -> anyhow::Result<(usize, usize)> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .context("--size wants WxH, e.g. 1280x1024")?;
    let (w, h): (usize, usize) = (w.trim().parse()?, h.trim().parse()?);
    if w == 0 || h == 0 || w * h > 1 << 26 {
        bail!("--size {s}: out of range");
    }
    Ok((w, h))
}

/// The demo rig: synthetic camera + emulated filter.
pub fn demo_rig(args: &RunArgs) -> anyhow::Result<Rig> {
    let (file, base) = demo_scene_file(args)?;
    demo_rig_for(args, &file, &base)
}

/// The demo's scene file (`--scene` or the embedded cylinder, stretched
/// to `--size`) and where its relative paths start.
pub fn demo_scene_file(args: &RunArgs) -> anyhow::Result<(SceneFile, PathBuf)> {
    let (mut file, base): (SceneFile, PathBuf) = match &args.scene {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("cannot read scene {}", p.display()))?;
            let f =
                toml::from_str(&text).map_err(|e| anyhow::anyhow!("scene {}: {e}", p.display()))?;
            (f, p.parent().unwrap_or(Path::new(".")).to_path_buf())
        }
        None => (
            toml::from_str(crate::scene::PAPER_CYLINDER).expect("embedded scene parses"),
            PathBuf::from("."),
        ),
    };
    if let Some(s) = &args.size {
        let (w, h) = parse_size(s)?;
        let t = file
            .truth
            .as_mut()
            .context("the scene has no [truth] to render")?;
        // Fields given per row / column are stretched to the new size.
        use crate::scene::Field;
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

fn demo_rig_for(args: &RunArgs, file: &SceneFile, base: &Path) -> anyhow::Result<Rig> {
    let scene = Scene::resolve(file, base).map_err(|e| anyhow::anyhow!("scene: {e}"))?;
    let bands = scene.bands.clone().context("the scene has no [bands]")?;
    let nm: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    let order = order_for(&args.order, bands.len(), &nm).with_context(|| {
        format!(
            "unknown --order {} (ascending, descending, interleaved)",
            args.order
        )
    })?;
    let view = FilterView::new();
    let big = file_pixels(&scene) > 100_000;
    let mut cfg = SyntheticConfig {
        sensor: SensorModel::default(),
        seed: args.seed,
        // Large images draw their noise from a pool at a fresh offset per
        // frame, so the camera does not limit the line.
        noise_pool: big,
        // At its frame rate (sped up as the emulated controller is), as a
        // real camera: unpaced, frames come as fast as the CPU renders
        // them and the pipeline rightly drops the sweeps it cannot take.
        realtime: !args.unpaced,
        speed: args.time_scale,
        ..Default::default()
    };
    let seq_mode = if args.triggered {
        cfg.trigger_palette = Some(order.clone());
        SeqMode::Triggered
    } else {
        SeqMode::Stepped
    };
    let camera =
        SyntheticCamera::new(&scene, &bands, view.clone(), cfg).context("rendering the scene")?;
    let (tuner, emulator): (Box<dyn BandTuner>, _) = if args.in_process_filter || args.triggered {
        let t = EmulatedTuner::new(
            view,
            Duration::from_millis(50),
            Duration::from_millis(2),
            args.seed,
        );
        (Box::new(t), None)
    } else {
        let (t, h) = emulated_varispec(view, args.time_scale)?;
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

/// The hardware rig of `line.toml`.
pub fn hardware_rig(path: &Path) -> anyhow::Result<(Rig, LineConfig)> {
    let (line, base) = LineConfig::load(path)?;
    let scene = Scene::load(&base.join(&line.scene)).map_err(|e| anyhow::anyhow!("{e}"))?;
    let bands = match &line.bands {
        Some(b) => {
            let mut f = SceneFile::default();
            f.substrate.n = Some(1.5);
            f.bands = b.clone();
            Scene::resolve(&f, &base)
                .map_err(|e| anyhow::anyhow!("{}: [bands]: {e}", path.display()))?
                .bands
                .context("[bands] is empty")?
        }
        None => scene
            .bands
            .clone()
            .context("neither line.toml nor the scene gives [bands]")?,
    };
    let nm: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    let order = order_for(&line.sequence.order, bands.len(), &nm).with_context(|| {
        format!(
            "{}: unknown sequence.order {}",
            path.display(),
            line.sequence.order
        )
    })?;
    let source = open_camera(&line.camera)?;
    let tuner = {
        use crate::device::filter::{FilterController, VariSpec, VariSpecOptions};
        let mut ctrl = VariSpec::open(
            &line.filter.port,
            VariSpecOptions {
                baud: line.filter.baud,
                ..Default::default()
            },
        )
        .with_context(|| format!("opening the filter controller on {}", line.filter.port))?;
        ctrl.ensure_ready(Duration::from_secs(60))
            .context("initialising the filter controller")?;
        if line.sequence.mode == SeqMode::Triggered {
            let seqnm: Vec<f64> = order.iter().map(|&b| nm[b]).collect();
            ctrl.define_sequence(&seqnm)
                .context("loading the band palette")?;
            ctrl.select_palette(0).context("selecting the first band")?;
            ctrl.arm_sync(1).context("arming the sync input")?;
        }
        ControllerTuner::new(
            ctrl,
            None,
            1.0,
            Duration::from_millis(line.filter.settle_timeout_ms),
        )
    };
    let cal = (
        base.join(&line.calibration.file),
        line.calibration.max_age_h,
        line.calibration.white_reflectance,
    );
    Ok((
        Rig {
            source,
            tuner: Box::new(tuner),
            scene,
            bands,
            order,
            seq_mode: line.sequence.mode,
            calibration: Some(cal),
            _emulator: None,
        },
        line,
    ))
}

#[cfg(feature = "v4l2")]
fn open_camera(c: &CameraSection) -> anyhow::Result<Box<dyn FrameSource>> {
    use crate::device::camera::v4l2::{V4l2Camera, V4l2Config};
    let format = PixelFormat::parse(&c.format)
        .with_context(|| format!("camera.format {}: grey8, y10, y12 or y16", c.format))?;
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
fn open_camera(c: &CameraSection) -> anyhow::Result<Box<dyn FrameSource>> {
    let _ = PixelFormat::parse(&c.format);
    bail!(
        "camera {}: this irid was built without V4L2 support; rebuild with `cargo build --release --features v4l2`",
        c.device
    )
}

/// Capture dark and white references with the rig (the synthetic camera
/// switches its own target; a real one needs a person).
pub fn capture_calibration(
    rig: &mut Rig,
    frames: u32,
    white_reflectance: f64,
) -> anyhow::Result<Calibration> {
    let info = rig.source.info();
    let nm: Vec<f64> = rig.bands.iter().map(|b| b.center_nm).collect();
    let mut refs = Vec::new();
    for (name, target) in [
        ("dark", Target::Dark),
        ("white", Target::White(white_reflectance)),
    ] {
        if !rig.source.set_target(target)? {
            eprintln!(
                "irid: {}; then press Enter",
                if name == "dark" {
                    "cap the lens (or close the shutter)"
                } else {
                    "place the white reference in view"
                }
            );
            let mut s = String::new();
            std::io::stdin().read_line(&mut s)?;
        }
        let plan = CapturePlan {
            mode: rig.seq_mode,
            bands_nm: &nm,
            order: &rig.order,
            frames,
            timeout: Duration::from_secs(2),
        };
        let acc = capture_reference(name, rig.source.as_mut(), rig.tuner.as_mut(), &plan)?;
        refs.push(acc);
    }
    rig.source.set_target(Target::Scene)?;
    let meta = CalMeta {
        version: 1,
        width: info.width,
        height: info.height,
        bands_nm: nm,
        exposure_us: info.exposure_us,
        gain: info.gain,
        format: info.format,
        camera_id: info.id,
        created_unix_s: now_unix_s(),
        white_reflectance,
        frames,
        noise: None,
    };
    Ok(Calibration::from_references(
        meta,
        &refs[0],
        &refs[1],
        &CalibrationPolicy::for_format(info.format),
    ))
}

/// Writes each sweep's map and prints its summary line.
pub(crate) struct CliSink {
    /// Where maps go (None: not written).
    pub out: Option<PathBuf>,
    /// JSON summaries.
    pub json: bool,
    /// A PNG preview beside each map.
    pub png: bool,
    /// The live page, fed the latest finished map.
    pub live: Option<super::serve::LiveView>,
}

impl SweepSink for CliSink {
    fn on_sweep(&mut self, s: &SweepSummary, maps: &ParamMaps) -> Result<(), String> {
        let mut s = s.clone();
        if let Some(dir) = &self.out {
            let p = sweep_path(dir, s.sweep);
            write_map(&p, maps).map_err(|e| e.to_string())?;
            if self.png {
                crate::render::map::write_preview(&p, maps).map_err(|e| e.to_string())?;
            }
            s.path = Some(p.display().to_string());
        }
        if let Some(live) = &self.live {
            live.offer(&s, maps);
        }
        if self.json {
            println!("{}", s.json());
        } else {
            println!("{}", s.line());
        }
        Ok(())
    }
}

static STOP: AtomicBool = AtomicBool::new(false);

/// Install the tracing layers `--trace` and `--profile` ask for: the
/// profile layer and the Chrome trace's flush guard (keep it until exit).
pub(crate) fn init_tracing(
    trace: Option<&PathBuf>,
    profile: bool,
) -> anyhow::Result<(Option<ProfileLayer>, Option<tracing_chrome::FlushGuard>)> {
    // Tracing: nothing installed unless asked, so spans cost ~1 ns.
    let profile = profile.then(ProfileLayer::new);
    let mut _chrome_guard = None;
    if trace.is_some() || profile.is_some() {
        use tracing_subscriber::prelude::*;
        let chrome = trace.map(|p| {
            let (layer, guard) = tracing_chrome::ChromeLayerBuilder::new()
                .file(p.clone())
                .include_args(true)
                .build();
            _chrome_guard = Some(guard);
            layer
        });
        tracing_subscriber::registry()
            .with(chrome)
            .with(profile.clone())
            .try_init()
            .context("installing the tracing subscriber")?;
    }
    Ok((profile, _chrome_guard))
}

/// The rig of `irid run` (hardware with `--config`, else the demo), its
/// solver mode and its calibration (loaded and checked, or captured).
pub(crate) fn rig_and_calibration(args: &RunArgs) -> anyhow::Result<(Rig, Mode, Calibration)> {
    let (mut rig, mode) = match &args.config {
        Some(p) => {
            let (rig, line) = hardware_rig(p)?;
            let mode = match (&line.mode, args.mode) {
                (Some(m), Mode::Balanced) => <Mode as clap::ValueEnum>::from_str(m, true)
                    .map_err(|e| anyhow::anyhow!("{}: mode: {e}", p.display()))?,
                _ => args.mode,
            };
            (rig, mode)
        }
        None => (demo_rig(args)?, args.mode),
    };
    let calibration = match rig.calibration.clone() {
        Some((path, max_age_h, _)) => {
            let cal = Calibration::load(&path)?;
            cal.check(
                &path.display().to_string(),
                &CalExpect {
                    camera: rig.source.info(),
                    bands_nm: rig.bands.iter().map(|b| b.center_nm).collect(),
                    now_unix_s: now_unix_s(),
                    max_age_s: (max_age_h * 3600.0) as u64,
                },
            )?;
            cal
        }
        None => {
            if !args.json {
                eprintln!(
                    "irid: demo: {} looking at `{}` through {}; calibrating…",
                    rig.source.info().id,
                    rig.scene.name,
                    rig.tuner.describe()
                );
            }
            capture_calibration(&mut rig, 4, 0.99)?
        }
    };
    Ok((rig, mode, calibration))
}

/// Run `irid run`.
pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    let (profile, _chrome_guard) = init_tracing(args.trace.as_ref(), args.profile)?;
    // The first Ctrl-C stops cleanly; a second ends the process at once,
    // even if a stage is stuck (e.g. waiting on the controller).
    if ctrlc::set_handler(|| {
        if STOP.swap(true, Ordering::SeqCst) {
            eprintln!("irid: interrupted twice: exiting without flushing");
            std::process::exit(130);
        }
    })
    .is_err()
    {
        tracing::warn!("Ctrl-C handler not installed");
    }
    if args.config.is_none() && super::line::wants_web(args) {
        return super::line::run(args, &STOP);
    }

    let (mut rig, mode, calibration) = rig_and_calibration(args)?;
    let recorder = match &args.record {
        Some(p) => Some(super::record::start(p, args, &rig, &calibration, mode)?),
        None => None,
    };
    let calibrator = Calibrator::from_calibration(calibration);
    let out = if args.no_maps {
        None
    } else {
        std::fs::create_dir_all(&args.out)
            .with_context(|| format!("creating {}", args.out.display()))?;
        if args.config.is_some() && !args.force {
            crate::pipeline::output::refuse_earlier_maps(&args.out)?;
        }
        Some(args.out.clone())
    };
    let cfg = RunConfig {
        sweeps: (args.sweeps > 0).then_some(args.sweeps),
        mode,
        threads: args.threads,
        single_thread: args.single_thread,
        track_extrema: match args.track_extrema {
            Tracking::On => true,
            Tracking::Off => false,
            Tracking::Auto => false,
        },
        ..RunConfig::default()
    };
    let mut sink = CliSink {
        out,
        json: args.json,
        png: args.png,
        live: args
            .serve
            .as_deref()
            .map(super::serve::LiveView::start)
            .transpose()?,
    };
    if let Some(l) = &sink.live {
        eprintln!("irid: live view at http://{}/", l.addr);
    }
    let setup = Setup {
        scene: rig.scene.clone(),
        bands: rig.bands.clone(),
        order: rig.order.clone(),
        seq_mode: rig.seq_mode,
        calibrator,
    };
    let stop: &'static AtomicBool = &STOP;
    let report = match &recorder {
        Some(r) => runner::run_tapped(
            rig.source.as_mut(),
            &mut r.tuner(rig.tuner.as_mut()),
            setup,
            &cfg,
            &mut sink,
            &mut runner::NoRows,
            Some(&mut r.tap()),
            stop,
        )?,
        None => runner::run(
            rig.source.as_mut(),
            rig.tuner.as_mut(),
            setup,
            &cfg,
            &mut sink,
            stop,
        )?,
    };
    if let Some(r) = recorder {
        super::record::finish(r, args.record.as_deref(), args.json)?;
    }
    if !args.json {
        eprintln!(
            "irid: {} sweeps mapped, {} dropped; {} frames read, {} discarded while settling, {} lost or refused{}",
            report.sweeps_completed,
            report.sweeps_dropped,
            report.frames_total,
            report.frames_settling,
            report.frames_dropped,
            if report.stopped { "; stopped by Ctrl-C" } else { "" }
        );
    }
    if let Some(p) = profile {
        eprint!("{}", p.report());
    }
    drop(_chrome_guard);
    Ok(())
}
