//! `irid run --scene web`: the moving-web demo — the synthetic web through
//! the emulated filter, mapped row by row, with lane statistics, the
//! recipe's alarms, EXR strip segments and JSON lines on stdout (and MQTT
//! when the web file names a broker).
//!
//! Recording and replay of a line: `--record F.mcap` taps the line runner
//! (every frame read with its verdict, every filter command) and writes
//! the line's configuration ([`LineRecord`]) beside the session and the
//! calibration; `irid record --scene web` records without solving; `irid
//! replay F.mcap` of a line recording runs the same line runner with the
//! recording as its camera and filter.

use super::record::{calibration_for, recorded_scene, ReplayArgs};
use super::run::RunArgs;
use crate::device::camera::{CameraError, Frame, FrameSource};
use crate::device::record::replay::Recording;
use crate::device::record::writer::Recorder;
use crate::device::record::Session;
use crate::estimate::Mode;
use crate::line::geometry::first_row;
use crate::line::mqtt::{MqttConfig, MqttPublisher};
use crate::line::output::{JsonLines, LineOutput, OutputConfig, Publisher};
use crate::line::recipe::Recipe;
use crate::line::recorded::LineRecord;
use crate::line::rig::{Built, WebRig};
use crate::line::run::{run_line, run_line_tapped, LineLimits, LineReport, LineSetup};
use crate::line::stats::Lanes;
use crate::pipeline::calibration::Calibrator;
use crate::pipeline::runner::CaptureTap;
use crate::pipeline::sequencer::{BandTuner, SeqMode, Sequencer, Verdict};
use crate::scene::SceneFile;
use anyhow::Context;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// Frames per `--sweeps` unit: 4 s of the demo's 10 ms frames.
const FRAMES_PER_UNIT: u64 = 400;

/// A frame source seen by `--trace` and `--profile`: a `line.read` span
/// around each read and a `line.frame` span from a frame's delivery to
/// the next read — everything the line runner does with that frame
/// (calibrate, register, accumulate, solve the rows it finishes, emit) —
/// so the line runner itself needs no spans. Live and replay show the same.
struct Spanned<'a> {
    inner: &'a mut dyn FrameSource,
    frame: Option<tracing::Span>,
}

impl<'a> Spanned<'a> {
    fn new(inner: &'a mut dyn FrameSource) -> Self {
        Spanned { inner, frame: None }
    }
}

impl FrameSource for Spanned<'_> {
    fn info(&self) -> crate::device::camera::CameraInfo {
        self.inner.info()
    }

    fn next_frame(&mut self, out: &mut Frame, timeout: Duration) -> Result<(), CameraError> {
        self.frame = None;
        let r = tracing::info_span!("line.read").in_scope(|| self.inner.next_frame(out, timeout));
        if r.is_ok() {
            self.frame = Some(tracing::info_span!("line.frame", seq = out.meta.seq));
        }
        r
    }

    fn set_exposure(&mut self, exposure_us: u32) -> Result<u32, CameraError> {
        self.inner.set_exposure(exposure_us)
    }

    fn set_gain(&mut self, gain: f32) -> Result<f32, CameraError> {
        self.inner.set_gain(gain)
    }

    fn set_target(&mut self, target: crate::device::camera::Target) -> Result<bool, CameraError> {
        self.inner.set_target(target)
    }
}

/// Whether `--scene` asks for the moving web (`web`, or a web file).
pub fn wants_web(args: &RunArgs) -> bool {
    args.scene.as_deref().is_some_and(|s| {
        s == Path::new("web")
            || std::fs::read_to_string(s).is_ok_and(|t| t.contains("[web]") && t.contains("[film]"))
    })
}

/// The web file `--scene` names (the demo's for `web`), loaded.
fn load_rig(args: &RunArgs) -> anyhow::Result<(WebRig, PathBuf)> {
    let path = match args.scene.as_deref() {
        Some(p) if p != Path::new("web") => p.to_path_buf(),
        _ => WebRig::demo_path(),
    };
    Ok((WebRig::load(&path)?, path))
}

/// The rig built for `args` (seed, pacing), the limit printed, and the
/// recipe with its path and text.
struct Line {
    rig: WebRig,
    web_path: PathBuf,
    built: Built,
    recipe: Option<(PathBuf, String, Recipe)>,
}

fn build_line(args: &RunArgs) -> anyhow::Result<Line> {
    let (rig, web_path) = load_rig(args)?;
    eprintln!("irid line: {}", rig.geometry.describe());
    eprintln!(
        "irid line: web at {:.2} rows/s ({:.0} % of the highest)",
        rig.speed,
        100.0 * rig.speed / rig.geometry.max_speed()
    );
    let mut cfg = rig.camera_config();
    cfg.seed = args.seed;
    if !args.unpaced {
        cfg.realtime_speed = args.time_scale;
    }
    let mut built = rig.build(cfg, args.mode)?;
    built.calibration.meta.created_unix_s = super::run::now_unix_s();
    let recipe = match &rig.file.recipe {
        Some(r) => {
            let p = rig.base.join(r);
            let text = std::fs::read_to_string(&p)
                .with_context(|| format!("reading recipe {}", p.display()))?;
            let recipe = Recipe::from_toml(&text, &p.display().to_string())?;
            Some((p, text, recipe))
        }
        None => None,
    };
    Ok(Line {
        rig,
        web_path,
        built,
        recipe,
    })
}

/// Start recording a line run (`command`: `run` or `record`): the session
/// (scene, bands, camera), the line configuration and the calibration.
fn start_recorder(
    path: &Path,
    args: &RunArgs,
    command: &str,
    line: &Line,
) -> anyhow::Result<Recorder> {
    let (rig, setup) = (&line.rig, &line.built.setup);
    let scene_path = rig.base.join(&rig.file.scene);
    let text = std::fs::read_to_string(&scene_path)
        .with_context(|| format!("reading scene {}", scene_path.display()))?;
    let scene: SceneFile = toml::from_str(&text)
        .map_err(|e| anyhow::anyhow!("scene {}: {e}", scene_path.display()))?;
    let base = scene_path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let base = std::path::absolute(&base).unwrap_or(base);
    let info = line.built.camera.info();
    let session = Session {
        irid_version: env!("CARGO_PKG_VERSION").into(),
        started_unix_s: super::run::now_unix_s(),
        command: command.into(),
        scene: serde_json::to_value(&scene).context("serialising the scene")?,
        scene_base: base.display().to_string(),
        bands_nm: setup.bands.iter().map(|b| b.center_nm).collect(),
        fwhm_nm: setup.bands.iter().map(|b| b.fwhm_nm).collect(),
        order: setup.order.clone(),
        seq_mode: SeqMode::Stepped,
        mode: setup.mode.name().to_string(),
        camera_id: info.id,
        width: info.width,
        height: info.height,
        format: info.format,
        exposure_us: info.exposure_us,
        gain: info.gain,
        filter: line.built.tuner.describe(),
        sweeps: (args.sweeps > 0).then_some(args.sweeps),
    };
    let web_toml = std::fs::read_to_string(&line.web_path)
        .with_context(|| format!("reading {}", line.web_path.display()))?;
    let record = LineRecord {
        web_toml,
        web_path: line.web_path.display().to_string(),
        recipe_toml: line.recipe.as_ref().map(|(_, t, _)| t.clone()),
        recipe_path: line
            .recipe
            .as_ref()
            .map(|(p, _, _)| p.display().to_string()),
        motion: setup.motion,
        geometry: setup.geometry,
        nominal_speed_rows_per_s: setup.nominal_speed,
        allow_over_speed: setup.allow_over_speed,
        warmup_rows: setup.warmup_rows,
        segment_rows: rig.file.line.segment_rows,
        lanes: rig.file.line.lanes,
        frames_per_sweep_unit: FRAMES_PER_UNIT,
    };
    let json = serde_json::to_vec(&record).context("serialising the line configuration")?;
    let cal = crate::device::record::ircal_bytes(&line.built.calibration);
    let opts = super::record::record_options(args.record_compression);
    Ok(Recorder::create_with_line(
        path,
        &session,
        Some(&json),
        &cal,
        &opts,
    )?)
}

/// The line's sink: JSON lines on stdout (plus `extra` publishers), EXR
/// strips in `out_dir` (created) unless None.
fn line_output(
    out_dir: Option<PathBuf>,
    width: usize,
    segment_rows: usize,
    lanes: usize,
    recipe: Option<Recipe>,
    extra: Vec<Box<dyn Publisher + Send>>,
) -> anyhow::Result<LineOutput> {
    if let Some(d) = &out_dir {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    let mut pubs: Vec<Box<dyn Publisher + Send>> = vec![Box::new(JsonLines(std::io::stdout()))];
    pubs.extend(extra);
    let cfg = OutputConfig {
        segment_rows,
        lanes: Lanes::equal(width, lanes),
        out_dir,
        topic: "irid/line".into(),
    };
    Ok(LineOutput::new(cfg, recipe, pubs))
}

fn print_report(what: &str, rep: &LineReport, out: &LineOutput) {
    eprintln!(
        "irid line: {what}{} rows emitted ({} complete, {} missing bands, {} skipped), {} segments, {} alarm events; \
         band rate {:.1}/s, web {:.1} rows/s; row latency after its last band: mean {:.2} ms, 99 % ≤ {:.0} ms, max {:.2} ms",
        rep.rows_emitted,
        rep.rows.complete,
        rep.rows.missing_bands,
        rep.rows.skipped,
        out.segments,
        out.alarm_log.len(),
        rep.band_rate_hz,
        rep.speed_rows_per_s,
        rep.latency_ms_mean,
        rep.latency_ms_p99,
        rep.latency_ms_max
    );
    if rep.rows_angle_corrected > 0 {
        eprintln!(
            "irid line: {} rows modelled at their bands' own incidence angles (the spread across the view mattered)",
            rep.rows_angle_corrected
        );
    }
    if rep.relooks > 0 {
        eprintln!(
            "irid line: the calibration moved during the run and was estimated again {} times (see the log)",
            rep.relooks
        );
    }
    if rep.unsettled_looks > 0 {
        eprintln!(
            "irid line: the calibration kept moving (a flickering lamp, a filter that will not hold?): at {} looks it had moved {} or more looks in a row, and the rows were flagged until it was steady",
            rep.unsettled_looks,
            crate::line::solve::UNSETTLED_LOOKS
        );
    }
    if rep.capture_waits > 0 || out.output_waits() > 0 {
        eprintln!(
            "irid line: capture waited for the solver {} times, rows for the output worker {} times (the CPU or the disk fell behind)",
            rep.capture_waits,
            out.output_waits()
        );
    }
}

/// Run the moving-web demo (recording it with `--record`).
pub fn run(args: &RunArgs, stop: &AtomicBool) -> anyhow::Result<()> {
    // Options of the static pipeline the moving web does not have yet:
    // refused, never silently ignored.
    let missing: Vec<&str> = [(args.serve.is_some(), "--serve"), (args.png, "--png")]
        .into_iter()
        .filter_map(|(asked, name)| asked.then_some(name))
        .collect();
    if !missing.is_empty() {
        anyhow::bail!(
            "the moving web (--scene web) does not support {} yet; the static scene does",
            missing.join(", ")
        );
    }
    let mut line = build_line(args)?;
    let recorder = match &args.record {
        Some(p) => Some(start_recorder(p, args, "run", &line)?),
        None => None,
    };
    let mut extra: Vec<Box<dyn Publisher + Send>> = Vec::new();
    if let Some(addr) = &line.rig.file.line.mqtt {
        let (host, port) = addr
            .rsplit_once(':')
            .and_then(|(h, p)| Some((h, p.parse::<u16>().ok()?)))
            .with_context(|| format!("mqtt = {addr:?}: expected host:port"))?;
        extra.push(Box::new(MqttPublisher::start(MqttConfig::new(host, port))));
    }
    let mut out = line_output(
        (!args.no_maps).then(|| args.out.join("line")),
        line.rig.file.camera.width as usize,
        line.rig.file.line.segment_rows,
        line.rig.file.line.lanes,
        line.recipe.take().map(|(_, _, r)| r),
        extra,
    )?;
    let limits = LineLimits {
        frames: (args.sweeps > 0).then(|| args.sweeps * FRAMES_PER_UNIT),
        frame_timeout: Duration::from_secs(2),
    };
    let Built {
        mut camera,
        mut tuner,
        setup,
        ..
    } = line.built;
    let mut camera = Spanned::new(&mut camera);
    let rep = match &recorder {
        Some(r) => run_line_tapped(
            &mut camera,
            &mut r.tuner(&mut tuner),
            setup,
            &limits,
            &mut out,
            Some(&mut r.tap()),
            stop,
        ),
        None => run_line(&mut camera, &mut tuner, setup, &limits, &mut out, stop),
    };
    // The recording is closed (and its cost printed) even when the run
    // failed: it is what shows why.
    if let Some(r) = recorder {
        super::record::finish(r, args.record.as_deref(), false)?;
    }
    print_report("", &rep?, &out);
    Ok(())
}

/// `irid record --scene web`: capture and pair the line's frames and record
/// them, solving nothing.
pub fn record_only(file: &Path, args: &RunArgs, stop: &AtomicBool) -> anyhow::Result<()> {
    let line = build_line(args)?;
    let recorder = start_recorder(file, args, "record", &line)?;
    let Built {
        mut camera,
        mut tuner,
        setup,
        ..
    } = line.built;
    let info = camera.info();
    let nm: Vec<f64> = setup.bands.iter().map(|b| b.center_nm).collect();
    let mut seq = Sequencer::new(SeqMode::Stepped, nm, setup.order.clone(), None)?;
    let frames = (args.sweeps > 0).then(|| args.sweeps * FRAMES_PER_UNIT);
    let mut frame = Frame::with_size(info.width, info.height, info.format);
    let mut tap = recorder.tap();
    let result = (|| -> anyhow::Result<(u64, u64)> {
        let mut tuner = recorder.tuner(&mut tuner);
        let (mut read, mut accepted) = (0u64, 0u64);
        while !stop.load(Ordering::Relaxed) && frames.is_none_or(|n| read < n) {
            match camera.next_frame(&mut frame, Duration::from_secs(2)) {
                Ok(()) => {}
                Err(CameraError::BadFrame { seq, message }) => {
                    tracing::warn!(seq, %message, "bad frame");
                    read += 1;
                    continue;
                }
                Err(CameraError::Ended) => break,
                Err(e) => return Err(e.into()),
            }
            read += 1;
            let valid = frame.pixels().is_ok()
                && (frame.meta.width, frame.meta.height) == (info.width, info.height);
            let v = seq.on_frame(&frame.meta, valid, &mut tuner, &mut |m| {
                tap.on_missing(m.sweep, m.band)
            })?;
            tap.on_frame(&frame, Some(v));
            accepted += u64::from(matches!(v, Verdict::Accept { .. }));
        }
        Ok((read, accepted))
    })();
    drop(tap);
    super::record::finish(recorder, Some(file), args.json)?;
    let (read, accepted) = result?;
    if !args.json {
        eprintln!(
            "irid line: {read} frames read, {accepted} paired with a band, recorded to {}",
            file.display()
        );
    }
    Ok(())
}

/// Refuse to mix a replay's strips with an earlier run's unless `force`.
fn refuse_earlier_strips(dir: &Path, force: bool) -> anyhow::Result<()> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(());
    };
    let earlier = entries
        .filter_map(Result::ok)
        .filter(|e| {
            e.file_name()
                .to_str()
                .is_some_and(|n| n.starts_with("strip-") && n.ends_with(".exr"))
        })
        .count();
    if earlier > 0 && !force {
        anyhow::bail!(
            "{}: holds {earlier} strip segment(s) of an earlier run; give --force to replace them, or another --out",
            dir.display()
        );
    }
    Ok(())
}

/// The set-up and output of a line replay: the recorded line, re-judged
/// with `--mode`, `--scene`, `--calibration`, `--recipe` when given.
fn replay_setup(
    args: &ReplayArgs,
    rec: &Recording,
    line: &LineRecord,
) -> anyhow::Result<(LineSetup, LineOutput)> {
    let s = &rec.session;
    let scene = recorded_scene(args, s)?;
    let cal = calibration_for(rec, &args.file, args.calibration.as_deref())?;
    let mode = match args.mode {
        Some(m) => m,
        None => <Mode as clap::ValueEnum>::from_str(&s.mode, true)
            .map_err(|e| anyhow::anyhow!("{}: recorded mode: {e}", args.file.display()))?,
    };
    let recipe = match &args.recipe {
        Some(p) => Some(Recipe::load(p)?),
        None => line
            .recipe()
            .with_context(|| format!("{}: recorded recipe", args.file.display()))?,
    };
    let setup = line
        .setup(
            scene,
            s.bands(),
            s.order.clone(),
            Calibrator::from_calibration(cal),
            mode,
        )
        .with_context(|| args.file.display().to_string())?;
    let out_dir = (!args.no_maps).then(|| args.out.join("line"));
    if let Some(d) = &out_dir {
        refuse_earlier_strips(d, args.force)?;
    }
    // Never the recorded MQTT broker: a replay must not publish into the
    // production line's topics.
    let out = line_output(
        out_dir,
        s.width as usize,
        line.segment_rows,
        line.lanes,
        recipe,
        Vec::new(),
    )?;
    Ok((setup, out))
}

/// `irid replay` of a line recording: the recording as the line runner's
/// camera and filter; JSON lines on stdout and EXR strips in `--out`/line,
/// as the live run.
pub fn replay(args: &ReplayArgs, rec: Recording, stop: &AtomicBool) -> anyhow::Result<()> {
    if args.png {
        anyhow::bail!("the moving web (a line recording) does not support --png yet");
    }
    let threads = if args.single_thread {
        Some(1)
    } else {
        args.threads
    };
    if let Some(n) = threads {
        // Before anything uses the pool. The rows a frame finishes are
        // solved each by one thread, so the result does not depend on
        // this (the runner's own guarantee).
        rayon::ThreadPoolBuilder::new()
            .num_threads(n.max(1))
            .build_global()
            .context("setting the solver's thread count")?;
    }
    let raw = rec.line.as_deref().unwrap_or_default();
    let line = LineRecord::from_json(raw).with_context(|| args.file.display().to_string())?;
    let (setup, mut out) = replay_setup(args, &rec, &line)?;
    let speed = if args.realtime { Some(1.0) } else { args.speed };
    let mut source = rec.source(speed);
    if std::io::stderr().is_terminal() {
        source = source.with_progress(super::record::progress_bar(&args.file));
    }
    let mut tuner = rec.tuner();
    let limits = LineLimits {
        frames: args.sweeps.map(|n| n * line.frames_per_sweep_unit),
        frame_timeout: Duration::from_secs(2),
    };
    let started = std::time::Instant::now();
    let rep = run_line(
        &mut Spanned::new(&mut source),
        &mut tuner,
        setup,
        &limits,
        &mut out,
        stop,
    )?;
    let st = rec.stats();
    let secs = started.elapsed().as_secs_f64();
    print_report(&format!("replayed {}: ", args.file.display()), &rep, &out);
    eprintln!(
        "irid line: {} frames in {secs:.2} s ({:.0} frames/s), {} refused{}",
        st.frames,
        st.frames as f64 / secs.max(1e-9),
        st.bad_frames,
        if st.diverged > 0 {
            format!("; {} filter commands not as recorded", st.diverged)
        } else {
            String::new()
        }
    );
    super::record::report_damage(&args.file, &st);
    Ok(())
}

/// What `irid inspect` says about a line recording.
#[derive(Debug, Default, serde::Serialize)]
pub struct LineInventory {
    /// Sensor rows that see the web.
    pub rows_in_view: usize,
    /// Bands per sweep.
    pub bands: usize,
    /// Nominal web speed, rows/s.
    pub nominal_speed_rows_per_s: f64,
    /// The web row under sensor row 0 in the first and the last frame
    /// recorded (None: no frame could be registered).
    pub first_rows: Option<(i64, i64)>,
    /// Web rows the recorded frames saw (first frame's first row to the
    /// last frame's last row).
    pub web_rows: u64,
    /// Frames that could not be registered (no encoder count).
    pub unregistered_frames: u64,
    /// Whether a recipe was recorded.
    pub recipe: bool,
}

/// Follows the frames of a line recording through the inventory.
pub struct LineCensus {
    inv: LineInventory,
    reg: Option<crate::line::geometry::Registration>,
}

impl LineCensus {
    /// From the recorded `/irid/line` message (None: not a line recording
    /// or the message is unreadable).
    pub fn new(raw: &[u8]) -> Option<LineCensus> {
        let l = LineRecord::from_json(raw).ok()?;
        Some(LineCensus {
            inv: LineInventory {
                rows_in_view: l.geometry.rows_in_view,
                bands: l.geometry.n_bands,
                nominal_speed_rows_per_s: l.nominal_speed_rows_per_s,
                recipe: l.recipe_toml.is_some(),
                ..LineInventory::default()
            },
            reg: crate::line::geometry::Registration::new(l.motion).ok(),
        })
    }

    /// One recorded frame.
    pub fn frame(&mut self, meta: &crate::device::camera::FrameMeta) {
        let pos = self
            .reg
            .as_mut()
            .and_then(|r| r.position(meta.encoder, meta.timestamp_ns).ok());
        let Some(p) = pos else {
            self.inv.unregistered_frames += 1;
            return;
        };
        let r = first_row(p);
        self.inv.first_rows = Some(self.inv.first_rows.map_or((r, r), |(a, _)| (a, r)));
    }

    /// The totals.
    pub fn finish(mut self) -> LineInventory {
        if let Some((a, b)) = self.inv.first_rows {
            self.inv.web_rows = (b - a).unsigned_abs() + self.inv.rows_in_view as u64;
        }
        self.inv
    }
}
