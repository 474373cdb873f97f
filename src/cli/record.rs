//! Recordings from the command line: `irid run --record FILE.mcap` (the
//! hook [`start`] / [`finish`]), `irid replay` and `irid inspect`.
//!
//! A replay is the recording as a camera and a filter fed through the same
//! runner as a live run (`lossless`: it waits rather than drops), with the
//! recorded scene, mode and calibration unless others are given.

use super::run::{init_tracing, CliSink, RunArgs};
use crate::device::record::reader::RecordReader;
use crate::device::record::replay::Recording;
use crate::device::record::writer::{Compression, RecordOptions, RecordStats, Recorder};
use crate::device::record::{
    ircal_bytes, RecorderEvent, SeqEvent, Session, TOPIC_FRAME, TOPIC_LINE, TOPIC_RECORDER,
    TOPIC_SEQUENCER, TOPIC_SESSION,
};
use crate::device::rig::{demo_scene_file, LineConfig, Rig};
use crate::estimate::Mode;
use crate::pipeline::calibration::{Calibration, Calibrator};
use crate::pipeline::runner::{self, RunConfig, Setup};
use crate::scene::{Scene, SceneFile};
use anyhow::Context;
use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

/// Chunk compression of a recording.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum RecordCompression {
    /// LZ4: fast, keeps up with the camera (see README).
    Lz4,
    /// zstd: smaller, slower.
    Zstd,
    /// None.
    None,
}

fn mode_name(m: Mode) -> String {
    format!("{m:?}").to_ascii_lowercase()
}

/// The scene file of a run and where its relative paths start.
fn scene_file_of(args: &RunArgs) -> anyhow::Result<(SceneFile, PathBuf)> {
    match &args.config {
        None => Ok(demo_scene_file(&args.demo_options())?),
        Some(p) => {
            let (line, base) = LineConfig::load(p)?;
            let path = base.join(&line.scene);
            let text = std::fs::read_to_string(&path)
                .with_context(|| format!("cannot read scene {}", path.display()))?;
            let f = toml::from_str(&text)
                .map_err(|e| anyhow::anyhow!("scene {}: {e}", path.display()))?;
            Ok((f, path.parent().unwrap_or(Path::new(".")).to_path_buf()))
        }
    }
}

/// Start recording `irid run` to `path` (after calibration).
/// Refuse (before any capture) to replace an existing recording unless
/// `force`: a recording of the line is not made again.
pub(crate) fn refuse_existing(path: &Path, force: bool) -> anyhow::Result<()> {
    let overwrite = if force {
        crate::io::atomic::Overwrite::Replace
    } else {
        crate::io::atomic::Overwrite::Refuse
    };
    crate::io::atomic::check_new(path, overwrite)?;
    Ok(())
}

pub(crate) fn start(
    path: &Path,
    args: &RunArgs,
    rig: &Rig,
    cal: &Calibration,
    mode: Mode,
) -> anyhow::Result<Recorder> {
    let (file, base) = scene_file_of(args)?;
    let base = std::path::absolute(&base).unwrap_or(base);
    let info = rig.source.info();
    let session = Session {
        irid_version: env!("CARGO_PKG_VERSION").into(),
        started_unix_s: super::run::now_unix_s(),
        command: "run".into(),
        scene: serde_json::to_value(&file).context("serialising the scene")?,
        scene_base: base.display().to_string(),
        bands_nm: rig.bands.iter().map(|b| b.center_nm).collect(),
        fwhm_nm: rig.bands.iter().map(|b| b.fwhm_nm).collect(),
        order: rig.order.clone(),
        seq_mode: rig.seq_mode,
        mode: mode_name(mode),
        camera_id: info.id,
        width: info.width,
        height: info.height,
        format: info.format,
        exposure_us: info.exposure_us,
        gain: info.gain,
        filter: rig.tuner.describe(),
        sweeps: (args.sweeps > 0).then_some(args.sweeps),
    };
    let opts = record_options(args.record_compression);
    Ok(Recorder::create(path, &session, &ircal_bytes(cal), &opts)?)
}

/// The recorder's options for `--record-compression`.
pub(crate) fn record_options(c: RecordCompression) -> RecordOptions {
    RecordOptions {
        compression: match c {
            RecordCompression::Lz4 => Compression::Lz4,
            RecordCompression::Zstd => Compression::Zstd,
            RecordCompression::None => Compression::None,
        },
        ..Default::default()
    }
}

/// Close the recording and say what it cost.
pub(crate) fn finish(r: Recorder, path: Option<&Path>, json: bool) -> anyhow::Result<()> {
    let s: RecordStats = r.finish()?;
    let name = path.map_or(String::new(), |p| p.display().to_string());
    let line = format!(
        "irid: recorded {name}: {} frames, {:.1} MB raw at {:.2} MB/s, file {:.1} MB (ratio {:.2}), recorder busy {:.0} % (takes up to {:.0} MB/s){}",
        s.frames_written,
        s.raw_bytes as f64 / 1e6,
        s.mb_per_s(),
        s.file_bytes as f64 / 1e6,
        s.ratio(),
        100.0 * s.busy_s / s.elapsed_s.max(1e-9),
        s.capacity_mb_per_s(),
        if s.frames_dropped > 0 {
            format!("; the disk could not keep up: {} frames dropped from the recording", s.frames_dropped)
        } else {
            String::new()
        }
    );
    if json {
        println!(
            "{}",
            serde_json::json!({
                "recording": name, "frames": s.frames_written, "frames_dropped": s.frames_dropped,
                "raw_bytes": s.raw_bytes, "file_bytes": s.file_bytes, "mb_per_s": s.mb_per_s(),
                "ratio": s.ratio(), "busy_s": s.busy_s, "elapsed_s": s.elapsed_s,
            })
        );
    } else {
        eprintln!("{line}");
    }
    Ok(())
}

/// Arguments of `irid replay`.
#[derive(clap::Args, Debug, Clone)]
pub struct ReplayArgs {
    /// The recording (`irid run --record`), or an ENVI cube (`.hdr`),
    /// replayed as one sweep (needs `--scene`).
    pub file: PathBuf,
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
    /// Write into an output folder that already holds sweep maps,
    /// replacing them.
    #[arg(long)]
    pub force: bool,
    /// Solver mode (default: the recorded run's).
    #[arg(long, value_enum)]
    pub mode: Option<Mode>,
    /// Scene (default: the recorded one).
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Calibration `.ircal` (default: the recorded one).
    #[arg(long, value_name = "FILE")]
    pub calibration: Option<PathBuf>,
    /// A line recording: judge the rows against this recipe instead of the
    /// recorded one.
    #[arg(long, value_name = "FILE")]
    pub recipe: Option<PathBuf>,
    /// Pace frames by their recorded timestamps (real time).
    #[arg(long, conflicts_with = "speed")]
    pub realtime: bool,
    /// Pace frames at this many times real time.
    #[arg(long, value_name = "X")]
    pub speed: Option<f64>,
    /// Stop after this many sweeps (default: the whole recording; a line
    /// recording: this many units of `irid run --sweeps`).
    #[arg(long)]
    pub sweeps: Option<u64>,
    /// Solver threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Run every stage on one thread.
    #[arg(long)]
    pub single_thread: bool,
    /// Write a Chrome/Perfetto trace (JSON) of every span.
    #[arg(long, value_name = "FILE")]
    pub trace: Option<PathBuf>,
    /// Print per-stage latency percentiles and throughput at exit.
    #[arg(long)]
    pub profile: bool,
}

static STOP: AtomicBool = AtomicBool::new(false);

pub(crate) fn progress_bar(file: &Path) -> crate::device::record::replay::Progress {
    let len = std::fs::metadata(file).map_or(0, |m| m.len());
    let bar = super::progress::bytes_bar(len, &format!("replay {}", file.display()));
    Box::new(move |pos, len| {
        bar.set_length(len);
        bar.set_position(pos);
        if pos >= len {
            bar.finish_and_clear();
        }
    })
}

/// The calibration a replay or export uses: `given`, or the one recorded
/// in `rec` (`file`); either must fit the recording's frames and bands.
pub(crate) fn calibration_for(
    rec: &Recording,
    file: &Path,
    given: Option<&Path>,
) -> anyhow::Result<Calibration> {
    let s = &rec.session;
    let cal = match given {
        Some(p) => Calibration::load(p)?,
        None => Calibration::from_bytes(&rec.calibration)
            .map_err(|e| anyhow::anyhow!("{}: recorded calibration: {e}", file.display()))?,
    };
    if (cal.meta.width, cal.meta.height) != (s.width, s.height) || cal.meta.bands_nm != s.bands_nm {
        anyhow::bail!(
            "the calibration is for {}×{} with {} bands, the recording has {}×{} with {} bands",
            cal.meta.width,
            cal.meta.height,
            cal.meta.bands_nm.len(),
            s.width,
            s.height,
            s.bands_nm.len()
        );
    }
    Ok(cal)
}

/// A replay's sink: maps in `--out` (created) unless `--no-maps`.
fn replay_sink(args: &ReplayArgs) -> anyhow::Result<CliSink> {
    let out = if args.no_maps {
        None
    } else {
        std::fs::create_dir_all(&args.out)
            .with_context(|| format!("creating {}", args.out.display()))?;
        if !args.force {
            crate::pipeline::output::refuse_earlier_maps(&args.out)?;
        }
        Some(args.out.clone())
    };
    Ok(CliSink {
        out,
        json: args.json,
        png: args.png,
        live: None,
        pace: super::run::Pace::default(),
    })
}

/// Run `irid replay`.
pub fn replay(args: &ReplayArgs) -> anyhow::Result<()> {
    let (profile, _chrome_guard) = init_tracing(args.trace.as_ref(), args.profile)?;
    if ctrlc::set_handler(|| STOP.store(true, Ordering::Relaxed)).is_err() {
        tracing::warn!("Ctrl-C handler not installed");
    }
    if is_envi(&args.file) {
        return replay_cube(args);
    }
    let rec = Recording::open(&args.file)?;
    if rec.line.is_some() {
        super::line::replay(args, rec, &STOP)?;
        if let Some(p) = profile {
            eprint!("{}", p.report());
        }
        return Ok(());
    }
    if args.recipe.is_some() {
        anyhow::bail!(
            "{}: --recipe applies to a production-line recording (irid run --scene web --record); this one is of a static scene",
            args.file.display()
        );
    }
    let s = rec.session.clone();
    let scene = recorded_scene(args, &s)?;
    let cal = calibration_for(&rec, &args.file, args.calibration.as_deref())?;
    let mode = match args.mode {
        Some(m) => m,
        None => <Mode as clap::ValueEnum>::from_str(&s.mode, true)
            .map_err(|e| anyhow::anyhow!("{}: recorded mode: {e}", args.file.display()))?,
    };
    let bands = s.bands();
    let cfg = RunConfig {
        sweeps: args.sweeps,
        mode,
        threads: args.threads,
        single_thread: args.single_thread,
        lossless: true,
        ..RunConfig::default()
    };
    let setup = Setup {
        scene,
        bands,
        order: s.order.clone(),
        seq_mode: s.seq_mode,
        calibrator: Calibrator::from_calibration(cal),
    };
    let speed = if args.realtime { Some(1.0) } else { args.speed };
    let mut source = rec.source(speed);
    let bar = std::io::stderr().is_terminal() && !args.json;
    if bar {
        source = source.with_progress(progress_bar(&args.file));
    }
    let mut tuner = rec.tuner();
    let mut sink = replay_sink(args)?;
    let started = std::time::Instant::now();
    let report = runner::run(&mut source, &mut tuner, setup, &cfg, &mut sink, &STOP)?;
    if bar {
        eprintln!();
    }
    let st = rec.stats();
    let secs = started.elapsed().as_secs_f64();
    if !args.json {
        eprintln!(
            "irid: replayed {}: {} sweeps mapped, {} dropped; {} frames in {secs:.2} s ({:.0} frames/s){}",
            args.file.display(),
            report.sweeps_completed,
            report.sweeps_dropped,
            st.frames,
            st.frames as f64 / secs.max(1e-9),
            if st.diverged > 0 {
                format!("; {} filter commands not as recorded (the live run dropped sweeps or the recorder frames)", st.diverged)
            } else {
                String::new()
            }
        );
    }
    report_damage(&args.file, &st);
    if let Some(p) = profile {
        eprint!("{}", p.report());
    }
    drop(_chrome_guard);
    Ok(())
}

/// The scene of a replay: `--scene`, or the one recorded in the session.
pub(crate) fn recorded_scene(args: &ReplayArgs, s: &Session) -> anyhow::Result<Scene> {
    Ok(match &args.scene {
        Some(p) => Scene::load(p)?,
        None => {
            let f: SceneFile = serde_json::from_value(s.scene.clone())
                .with_context(|| format!("{}: recorded scene", args.file.display()))?;
            Scene::resolve(&f, Path::new(&s.scene_base))
                .map_err(|e| anyhow::anyhow!("{}: recorded scene: {e}", args.file.display()))?
        }
    })
}

/// Say on stderr that a replayed file was not closed, and where it is
/// damaged.
pub(crate) fn report_damage(file: &Path, st: &crate::device::record::replay::ReplayStats) {
    if !st.closed {
        eprintln!(
            "irid: {}: not closed properly (crash or cut)",
            file.display()
        );
    }
    for d in &st.damage {
        eprintln!(
            "irid: {}: damage at byte {}: {}",
            file.display(),
            d.offset,
            d.message
        );
    }
}

/// An ENVI header (by its extension or its first line) rather than a
/// recording.
fn is_envi(path: &Path) -> bool {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("hdr"))
    {
        return true;
    }
    let mut head = [0u8; 4];
    std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .is_ok_and(|()| &head == b"ENVI")
}

/// `irid replay CUBE.hdr`: an ENVI reflectance cube through the live
/// pipeline as a one-sweep stream ([`CubeStream`]): the scene must be
/// given (a cube carries none), the calibration is the cube's own.
fn replay_cube(args: &ReplayArgs) -> anyhow::Result<()> {
    use crate::device::record::cube_stream::{CubeStream, InstantTuner};
    let Some(scene_path) = &args.scene else {
        anyhow::bail!(
            "{}: an ENVI cube carries no scene: give --scene FILE",
            args.file.display()
        );
    };
    if args.calibration.is_some() {
        anyhow::bail!(
            "{}: an ENVI cube is already reflectance: --calibration does not apply",
            args.file.display()
        );
    }
    let (profile, _chrome_guard) = init_tracing(args.trace.as_ref(), args.profile)?;
    let scene = Scene::load(scene_path)?;
    let cube = crate::io::envi::read_cube(&args.file)?;
    let label = args.file.display().to_string();
    let mut source = CubeStream::new(cube, &label);
    let bands = source.bands().to_vec();
    let setup = Setup {
        scene,
        order: (0..bands.len()).collect(),
        bands,
        seq_mode: crate::pipeline::sequencer::SeqMode::Stepped,
        calibrator: source.calibrator(),
    };
    let cfg = RunConfig {
        sweeps: Some(1),
        mode: args.mode.unwrap_or(Mode::Balanced),
        threads: args.threads,
        single_thread: args.single_thread,
        lossless: true,
        ..RunConfig::default()
    };
    let mut sink = replay_sink(args)?;
    let started = std::time::Instant::now();
    let report = runner::run(
        &mut source,
        &mut InstantTuner,
        setup,
        &cfg,
        &mut sink,
        &STOP,
    )?;
    if !args.json {
        eprintln!(
            "irid: replayed {label} as one sweep: {} mapped in {:.2} s",
            report.sweeps_completed,
            started.elapsed().as_secs_f64()
        );
    }
    if let Some(p) = profile {
        eprint!("{}", p.report());
    }
    drop(_chrome_guard);
    Ok(())
}

/// Arguments of `irid inspect`.
#[derive(clap::Args, Debug, Clone)]
pub struct InspectArgs {
    /// The recording.
    pub file: PathBuf,
    /// One JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// What `irid inspect` finds.
#[derive(Debug, Default, serde::Serialize)]
pub struct Inventory {
    /// Messages per topic.
    pub channels: BTreeMap<String, u64>,
    /// The session, if found.
    pub session: Option<Session>,
    /// Frames recorded with pixels.
    pub frames: u64,
    /// First and last frame timestamps, ns.
    pub time_range_ns: Option<(u64, u64)>,
    /// Gaps in the camera's frame counter (frames lost before capture).
    pub seq_gaps: u64,
    /// Sweeps with every band accepted or marked missing.
    pub complete_sweeps: u64,
    /// Sweeps begun but not complete (cut, abandoned, damaged).
    pub incomplete_sweeps: Vec<u64>,
    /// Band slots marked missing (triggered gaps).
    pub missing_bands: u64,
    /// Sweeps abandoned live (processing behind).
    pub abandoned_sweeps: Vec<u64>,
    /// Verdicts by kind.
    pub verdicts: BTreeMap<String, u64>,
    /// Frames the recorder dropped (disk behind).
    pub recorder_dropped: u64,
    /// Whether the file was closed properly.
    pub closed: bool,
    /// Sound chunks.
    pub chunks: u64,
    /// Damage found.
    pub damage: Vec<crate::device::record::reader::Damage>,
    /// A production-line recording: the web it saw (None: a static scene).
    pub line: Option<super::line::LineInventory>,
}

/// Read a whole recording and list what is in it.
pub fn inventory(path: &Path) -> anyhow::Result<Inventory> {
    let mut r = RecordReader::open(path)?;
    let mut inv = Inventory::default();
    let mut last_seq: Option<u64> = None;
    let mut bands: BTreeMap<u64, usize> = BTreeMap::new();
    let mut census: Option<super::line::LineCensus> = None;
    let mut line_recording = false;
    while let Some(m) = r.next_message() {
        *inv.channels.entry(m.topic.clone()).or_default() += 1;
        match m.topic.as_str() {
            TOPIC_SESSION => inv.session = serde_json::from_slice(&m.data).ok(),
            TOPIC_LINE => {
                line_recording = true;
                census = super::line::LineCensus::new(&m.data);
            }
            TOPIC_FRAME => {
                if let Ok(meta) = crate::device::record::decode_frame_meta(&m.data) {
                    if let Some(c) = census.as_mut() {
                        c.frame(&meta);
                    }
                    inv.frames += 1;
                    if let Some(l) = last_seq.filter(|&l| meta.seq > l.saturating_add(1)) {
                        inv.seq_gaps = inv.seq_gaps.saturating_add(meta.seq - l - 1);
                    }
                    last_seq = Some(last_seq.map_or(meta.seq, |l| l.max(meta.seq)));
                    let t = meta.timestamp_ns;
                    inv.time_range_ns = Some(
                        inv.time_range_ns
                            .map_or((t, t), |(a, b)| (a.min(t), b.max(t))),
                    );
                }
            }
            TOPIC_SEQUENCER => match serde_json::from_slice::<SeqEvent>(&m.data) {
                Ok(SeqEvent::Frame { verdict, sweep, .. }) => {
                    if let (true, Some(s)) = (verdict == "accept", sweep) {
                        *bands.entry(s).or_default() += 1;
                    }
                    *inv.verdicts.entry(verdict).or_default() += 1;
                }
                Ok(SeqEvent::Missing { sweep, .. }) => {
                    inv.missing_bands += 1;
                    *bands.entry(sweep).or_default() += 1;
                }
                Ok(SeqEvent::Abandoned { sweep }) => inv.abandoned_sweeps.push(sweep),
                Err(_) => {}
            },
            TOPIC_RECORDER => {
                if let Ok(RecorderEvent::Dropped { .. }) = serde_json::from_slice(&m.data) {
                    inv.recorder_dropped += 1;
                }
            }
            _ => {}
        }
    }
    let n = inv.session.as_ref().map_or(0, |s| s.order.len());
    for (&s, &k) in &bands {
        if k >= n && n > 0 {
            inv.complete_sweeps += 1;
        } else {
            inv.incomplete_sweeps.push(s);
        }
    }
    inv.line = match census {
        Some(c) => Some(c.finish()),
        None if line_recording => Some(super::line::LineInventory::default()),
        None => None,
    };
    inv.closed = r.closed();
    inv.chunks = r.chunks();
    inv.damage = r.damage().to_vec();
    Ok(inv)
}

/// Run `irid inspect`.
pub fn inspect(args: &InspectArgs) -> anyhow::Result<()> {
    let inv = inventory(&args.file)?;
    if args.json {
        println!("{}", serde_json::to_string(&inv)?);
        return Ok(());
    }
    println!("{}", args.file.display());
    if let Some(s) = &inv.session {
        println!(
            "  irid {} `{}`: {}×{} {:?}, {} bands {:.0}–{:.0} nm, {:?} pairing, mode {}, filter: {}",
            s.irid_version,
            s.command,
            s.width,
            s.height,
            s.format,
            s.bands_nm.len(),
            s.bands_nm.first().copied().unwrap_or(f64::NAN),
            s.bands_nm.last().copied().unwrap_or(f64::NAN),
            s.seq_mode,
            s.mode,
            s.filter
        );
    }
    if let Some(l) = &inv.line {
        println!(
            "  a production-line recording (moving web): {} rows in view, {} bands, nominal {:.2} rows/s{}",
            l.rows_in_view,
            l.bands,
            l.nominal_speed_rows_per_s,
            if l.recipe { ", with its recipe" } else { "" }
        );
        match l.first_rows {
            Some((a, b)) => println!(
                "  web: rows {a}..{} seen ({} web rows), {} frames not registrable",
                b + l.rows_in_view as i64,
                l.web_rows,
                l.unregistered_frames
            ),
            None => println!("  web: no frame registered"),
        }
    }
    println!("  channels:");
    for (t, k) in &inv.channels {
        println!("    {t:<20} {k} messages");
    }
    let dur = inv.time_range_ns.map_or(0.0, |(a, b)| (b - a) as f64 / 1e9);
    println!(
        "  frames: {} over {dur:.2} s; {} lost before capture (counter gaps); {} dropped by the recorder",
        inv.frames, inv.seq_gaps, inv.recorder_dropped
    );
    println!(
        "  sweeps: {} complete; incomplete: {:?}; abandoned live: {:?}; missing bands: {}",
        inv.complete_sweeps, inv.incomplete_sweeps, inv.abandoned_sweeps, inv.missing_bands
    );
    println!("  verdicts: {:?}", inv.verdicts);
    println!(
        "  {} chunks; {}",
        inv.chunks,
        if inv.closed {
            "closed properly"
        } else {
            "NOT closed (crash or cut)"
        }
    );
    if inv.damage.is_empty() {
        println!("  no damage");
    }
    for d in &inv.damage {
        println!("  damage at byte {}: {}", d.offset, d.message);
    }
    Ok(())
}

/// Arguments of `irid record`.
#[derive(clap::Args, Debug, Clone)]
pub struct RecordArgs {
    /// The recording to write.
    #[arg(value_name = "FILE.mcap")]
    pub file: PathBuf,
    /// The line or demo options of `irid run` (`--sweeps`, `--config`,
    /// `--scene`, `--size`, …; the solver options are ignored).
    #[command(flatten)]
    pub run: RunArgs,
}

/// Run `irid record`: capture and pair frames, record them, solve nothing.
pub fn record_only(args: &RecordArgs) -> anyhow::Result<()> {
    use crate::device::camera::{CameraError, Frame};
    use crate::pipeline::runner::CaptureTap;
    use crate::pipeline::sequencer::{Sequencer, Verdict};
    if ctrlc::set_handler(|| STOP.store(true, Ordering::Relaxed)).is_err() {
        tracing::warn!("Ctrl-C handler not installed");
    }
    let run = &args.run;
    refuse_existing(&args.file, run.force)?;
    if run.config.is_none() && super::line::wants_web(run) {
        return super::line::record_only(&args.file, run, &STOP);
    }
    let (mut rig, mode, cal) = super::run::rig_and_calibration(run)?;
    let recorder = start(&args.file, run, &rig, &cal, mode)?;
    let info = rig.source.info();
    let nm: Vec<f64> = rig.bands.iter().map(|b| b.center_nm).collect();
    let sweeps = (run.sweeps > 0).then_some(run.sweeps);
    let mut seq = Sequencer::new(rig.seq_mode, nm, rig.order.clone(), sweeps)?;
    let last_band = rig.order.last().copied().unwrap_or(0);
    let mut frame = Frame::with_size(info.width, info.height, info.format);
    let mut tap = recorder.tap();
    let result = (|| -> anyhow::Result<u64> {
        let mut tuner = recorder.tuner(rig.tuner.as_mut());
        let mut done = 0u64;
        while !seq.finished() && !STOP.load(Ordering::Relaxed) {
            match rig
                .source
                .next_frame(&mut frame, std::time::Duration::from_secs(2))
            {
                Ok(()) => {}
                Err(CameraError::BadFrame { seq, message }) => {
                    tracing::warn!(seq, %message, "bad frame");
                    continue;
                }
                Err(CameraError::Ended) => break,
                Err(e) => return Err(e.into()),
            }
            let valid = frame.pixels().is_ok()
                && (frame.meta.width, frame.meta.height) == (info.width, info.height);
            let v = seq.on_frame(&frame.meta, valid, &mut tuner, &mut |m| {
                tap.on_missing(m.sweep, m.band)
            })?;
            tap.on_frame(&frame, Some(v));
            if let Verdict::Accept { sweep, band } = v {
                if band == last_band {
                    done += 1;
                    if !run.json {
                        eprintln!("irid: sweep {sweep} recorded");
                    }
                }
            }
        }
        Ok(done)
    })();
    drop(tap);
    finish(recorder, Some(&args.file), run.json)?;
    let n = result?;
    if !run.json {
        eprintln!("irid: {n} sweeps recorded to {}", args.file.display());
    }
    Ok(())
}
