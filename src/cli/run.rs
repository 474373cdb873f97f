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
//!
//! The rigs are built by [`crate::device::rig`]; this module turns the
//! flags into its [`DemoOptions`], asks the operator for the references a
//! real camera cannot show itself, reads the clock and prints.

use crate::device::camera::Target;
use crate::device::rig::{demo_rig, hardware_rig, DemoOptions, Rig, StoredCalibration};
use crate::estimate::{Mode, ParamMaps};
use crate::pipeline::calibration::{CalExpect, Calibration, Calibrator};
use crate::pipeline::output::{sweep_path, write_map, SweepSummary};
use crate::pipeline::profile::ProfileLayer;
use crate::pipeline::runner::{self, RunConfig, Setup, SweepSink};
use anyhow::Context;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

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
    /// Replace an existing --record file; with --config, also write into an
    /// output folder that already holds sweep maps, replacing them (the
    /// demo always replaces its own maps).
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

    /// What the demo flags ask of the demo rig.
    pub fn demo_options(&self) -> DemoOptions {
        DemoOptions {
            scene: self.scene.clone(),
            size: self.size.clone(),
            order: self.order.clone(),
            triggered: self.triggered,
            in_process_filter: self.in_process_filter,
            time_scale: self.time_scale,
            paced: !self.unpaced,
            seed: self.seed,
        }
    }
}

/// Seconds since the Unix epoch (the CLI reads the clock; layers below are
/// passed it).
pub fn now_unix_s() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// How the operator is asked to set up a reference a real camera cannot
/// show by itself: a line on stderr, then Enter.
pub(crate) fn ask_operator(target: Target) -> std::io::Result<()> {
    eprintln!(
        "irid: {}; then press Enter",
        if target == Target::Dark {
            "cap the lens (or close the shutter)"
        } else {
            "place the white reference in view"
        }
    );
    let mut s = String::new();
    std::io::stdin().read_line(&mut s)?;
    Ok(())
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
    /// When the mapped sweeps had their last band frame (the finish less
    /// the sweep's latency).
    pub pace: Pace,
}

impl CliSink {
    /// The mean wall time between the mapped sweeps' last band frames, if
    /// two or more were mapped: the pace the rig and the pipeline kept
    /// together, which a saturated machine stretches beyond the filter's
    /// own (a starved capture, or a sweep dropped in between). Taken at
    /// the frames, not at the finished maps: the first sweep also
    /// estimates the film index, the noise and the level, and the sweeps
    /// queued behind it then finish in a burst (the 3-sweep demo read "a
    /// sweep every 4 ms"). From the second sweep on where three or more
    /// were mapped: capture holds the second sweep back until the first
    /// sweep's set-up is done, so the first interval is the set-up's. A
    /// pipeline falling behind shows in the latency.
    pub fn sweep_period(&self) -> Option<std::time::Duration> {
        let p = &self.pace;
        let (from, intervals) = match (p.n, p.first, p.second) {
            (3.., _, Some(second)) => (second, p.n - 2),
            (2, Some(first), _) => (first, 1),
            _ => return None,
        };
        Some((p.last? - from) / intervals as u32)
    }

    /// One more sweep mapped, its last band frame `at`.
    fn note_pace(&mut self, at: std::time::Instant) {
        let p = &mut self.pace;
        match p.n {
            0 => p.first = Some(at),
            1 => p.second = Some(at),
            _ => {}
        }
        p.last = Some(at);
        p.n += 1;
    }
}

/// The mapped sweeps' last band frames: how many, the first two, the last.
#[derive(Clone, Copy, Debug, Default)]
pub struct Pace {
    n: u64,
    first: Option<std::time::Instant>,
    second: Option<std::time::Instant>,
    last: Option<std::time::Instant>,
}

/// When a sweep that finished `now`, `latency_ms` after its last band
/// frame, had that frame (`now` where the latency is not a duration).
fn last_frame_at(now: std::time::Instant, latency_ms: f64) -> std::time::Instant {
    std::time::Duration::try_from_secs_f64(latency_ms / 1e3)
        .ok()
        .and_then(|d| now.checked_sub(d))
        .unwrap_or(now)
}

impl SweepSink for CliSink {
    fn on_sweep(&mut self, s: &SweepSummary, maps: &ParamMaps) -> Result<(), String> {
        self.note_pace(last_frame_at(std::time::Instant::now(), s.latency_ms));
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
            if let Some(why) = &s.relook {
                eprintln!("irid: sweep {}: estimated again: {why}", s.sweep);
            }
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
        None => (demo_rig(&args.demo_options())?, args.mode),
    };
    let calibration = match rig.calibration.clone() {
        Some(StoredCalibration {
            path, max_age_h, ..
        }) => {
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
            rig.capture_calibration(4, 0.99, now_unix_s(), &mut ask_operator)?
        }
    };
    Ok((rig, mode, calibration))
}

/// Run `irid run`.
pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    if let Some(p) = &args.record {
        super::record::refuse_existing(p, args.force)?;
    }
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
        super::line::run(args, &STOP)?;
        if let Some(p) = profile {
            eprint!("{}", p.report());
        }
        return Ok(());
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
        pace: Pace::default(),
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
        // The pace kept, in sweeps and bands per second of wall time.
        let pace = sink.sweep_period().map_or(String::new(), |p| {
            let bands = rig.order.len() as f64 / p.as_secs_f64();
            format!(
                "; a sweep every {:.0} ms ({bands:.1} bands/s)",
                p.as_secs_f64() * 1e3
            )
        });
        let held = if report.frames_held > 0 {
            format!(
                ", {} while the film index, noise and level were estimated",
                report.frames_held
            )
        } else {
            String::new()
        };
        let relooks = match report.relooks {
            0 => String::new(),
            n => {
                format!("; estimated again on {n} sweeps (the calibration moved or poor fits rose)")
            }
        };
        eprintln!(
            "irid: {} sweeps mapped, {} dropped; {} frames read, {} discarded while settling{held}, {} lost or refused{pace}{relooks}{}",
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

#[cfg(test)]
mod tests {
    use super::*;

    fn demo(flags: &[&str]) -> DemoOptions {
        let argv = std::iter::once("irid").chain(flags.iter().copied());
        <DefaultsOnly as clap::Parser>::parse_from(argv)
            .args
            .demo_options()
    }

    #[test]
    fn the_demo_flags_default_to_the_library_defaults() {
        assert_eq!(demo(&[]), DemoOptions::default());
    }

    #[test]
    fn the_demo_camera_is_paced_unless_unpaced() {
        assert!(demo(&[]).paced);
        let fast = demo(&["--unpaced", "--time-scale", "2"]);
        assert!(!fast.paced);
        assert_eq!(fast.time_scale, 2.0);
    }

    /// The pace is taken at the sweeps' last band frames: sweeps acquired
    /// 450 ms apart whose maps finish in a burst (the first estimating the
    /// index, the others queued behind it) read 450 ms, not the burst's
    /// few; a latency that is no duration counts as none. With three or
    /// more, from the second: a first sweep whose set-up held the second
    /// back 1 s does not stretch it; with two, their interval.
    #[test]
    fn the_pace_is_kept_at_the_frames_not_at_the_finished_maps() {
        use std::time::{Duration, Instant};
        let t0 = Instant::now();
        let finish = |ms: u64| t0 + Duration::from_millis(ms);
        let new_sink = || CliSink {
            out: None,
            json: false,
            png: false,
            live: None,
            pace: Pace::default(),
        };
        let mut sink = new_sink();
        assert_eq!(sink.sweep_period(), None);
        // Acquired at 0, 450 and 900 ms; finished at 1 100, 1 104, 1 108.
        for (done, latency) in [(1100, 1100.0), (1104, 654.0), (1108, 208.0)] {
            sink.note_pace(last_frame_at(finish(done), latency));
        }
        let p = sink.sweep_period().expect("three sweeps");
        assert!(
            p.abs_diff(Duration::from_millis(450)) < Duration::from_millis(1),
            "{p:?}"
        );
        let held = |acquired: &[u64]| {
            let mut sink = new_sink();
            for &ms in acquired {
                sink.note_pace(finish(ms));
            }
            sink.sweep_period()
        };
        // Acquired at 0, then (held back 1 s) 1 300, 1 610 and 1 920 ms.
        assert_eq!(
            held(&[0, 1300, 1610, 1920]),
            Some(Duration::from_millis(310))
        );
        assert_eq!(held(&[0, 1300]), Some(Duration::from_millis(1300)));
        assert_eq!(held(&[0]), None);
        for odd in [f64::NAN, -5.0, f64::INFINITY] {
            assert_eq!(last_frame_at(finish(10), odd), finish(10), "{odd}");
        }
    }
}
