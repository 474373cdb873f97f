//! Soak benchmark (harness = false): a long threaded run — small frames,
//! `fast` mode, the VariSpec firmware emulator on a pseudo-terminal with
//! its clock sped up — printing resident memory and the latency from last
//! band to map, window by window, and their trend over the run. Flat lines
//! are the result wanted: no leak, no growing queue.
//!
//! `cargo bench --bench soak [-- --sweeps N] [--every K] [--time-scale S]
//! [--in-process [--speed X]]` (defaults: 10 000 sweeps, a line every 500,
//! S = 100; in-process: the emulated filter on the camera's clock, paced
//! at X = 10× real time).

use irid::device::camera::synthetic::{FilterView, SensorModel, SyntheticCamera, SyntheticConfig};
use irid::device::camera::{FrameSource, Target};
use irid::estimate::{Mode, ParamMaps};
use irid::pipeline::calibration::{
    capture_reference, CalMeta, Calibration, CalibrationPolicy, Calibrator, CapturePlan,
};
use irid::pipeline::output::SweepSummary;
use irid::pipeline::runner::{run, RunConfig, Setup, SweepSink};
use irid::pipeline::sequencer::{order_for, EmulatedTuner, SeqMode};
use irid::scene::{Scene, SceneFile};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

fn rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}

fn arg(name: &str, default: f64) -> f64 {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// One window of sweeps: its memory and latencies.
struct Window {
    first: u64,
    rss_kb: u64,
    p50_ms: f64,
    p99_ms: f64,
    frames_dropped: u64,
    sweeps_dropped: u64,
}

struct Soak {
    every: usize,
    started: Instant,
    latencies: Vec<f64>,
    frames_dropped: u64,
    sweeps_dropped: u64,
    first: u64,
    windows: Vec<Window>,
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(((v.len() as f64 - 1.0) * q).round() as usize)
        .copied()
        .unwrap_or(f64::NAN)
}

impl SweepSink for Soak {
    fn on_sweep(&mut self, s: &SweepSummary, _: &ParamMaps) -> Result<(), String> {
        if self.latencies.is_empty() {
            self.first = s.sweep;
        }
        self.latencies.push(s.latency_ms);
        self.frames_dropped += s.frames_dropped;
        self.sweeps_dropped += s.sweeps_dropped;
        if self.latencies.len() == self.every {
            let w = Window {
                first: self.first,
                rss_kb: rss_kb(),
                p50_ms: quantile(&mut self.latencies, 0.5),
                p99_ms: quantile(&mut self.latencies, 0.99),
                frames_dropped: self.frames_dropped,
                sweeps_dropped: self.sweeps_dropped,
            };
            println!(
                "sweeps {:>6}–{:<6} {:>7.1} s  RSS {:>7} kB  latency p50 {:>7.2} ms  p99 {:>7.2} ms  dropped {} frames / {} sweeps",
                w.first,
                s.sweep,
                self.started.elapsed().as_secs_f64(),
                w.rss_kb,
                w.p50_ms,
                w.p99_ms,
                w.frames_dropped,
                w.sweeps_dropped
            );
            self.windows.push(w);
            self.latencies.clear();
            (self.frames_dropped, self.sweeps_dropped) = (0, 0);
        }
        Ok(())
    }
}

/// Least-squares slope of `y` over the window index.
fn slope(y: &[f64]) -> f64 {
    let n = y.len() as f64;
    let mx = (n - 1.0) / 2.0;
    let my = y.iter().sum::<f64>() / n;
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for (i, v) in y.iter().enumerate() {
        let dx = i as f64 - mx;
        sxy += dx * (v - my);
        sxx += dx * dx;
    }
    if sxx > 0.0 {
        sxy / sxx
    } else {
        0.0
    }
}

fn main() {
    let sweeps = arg("--sweeps", 10_000.0) as u64;
    let every = (arg("--every", 500.0) as usize).max(1);
    let time_scale = arg("--time-scale", 100.0);
    let mut f: SceneFile = toml::from_str(irid::scene::PAPER_CYLINDER).unwrap();
    let t = f.truth.as_mut().unwrap();
    (t.width, t.height) = (32, 8);
    let scene = Scene::resolve(&f, std::path::Path::new(".")).unwrap();
    let bands = scene.bands.clone().unwrap();
    let nm: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    let order = order_for("ascending", bands.len(), &nm).unwrap();
    let view = FilterView::new();
    // A 1 kHz camera (0.5 ms exposure, the default's light per frame).
    let d = SensorModel::default();
    let sensor = SensorModel {
        exposure_us: 500,
        frame_period_ns: 1_000_000,
        counts_per_us: d.counts_per_us * f64::from(d.exposure_us) / 500.0,
        ..d
    };
    let cfg = SyntheticConfig {
        seed: 9,
        sensor,
        ..Default::default()
    };
    let mut cam = SyntheticCamera::new(&scene, &bands, view.clone(), cfg).unwrap();
    // Calibrated through the in-process filter on the camera's virtual
    // clock (as the pipeline tests do); the run then goes through the
    // firmware emulator in real time.
    let mut cal_tuner = EmulatedTuner::new(
        view.clone(),
        Duration::from_millis(5),
        Duration::from_micros(400),
        9,
    );
    let plan = CapturePlan {
        mode: SeqMode::Stepped,
        bands_nm: &nm,
        order: &order,
        frames: 2,
        timeout: Duration::from_secs(2),
    };
    cam.set_target(Target::Dark).unwrap();
    let dark = capture_reference("dark", &mut cam, &mut cal_tuner, &plan).unwrap();
    cam.set_target(Target::White(0.99)).unwrap();
    let white = capture_reference("white", &mut cam, &mut cal_tuner, &plan).unwrap();
    cam.set_target(Target::Scene).unwrap();
    cam.set_realtime(true);
    // The firmware emulator on a pseudo-terminal (each band waits on the
    // serial round trip: ~5 s a sweep), or with --in-process the emulated
    // filter on the camera's clock, paced at --speed × real time: the
    // 10 000-sweep soak in minutes.
    let in_process = std::env::args().any(|a| a == "--in-process");
    let (mut tuner, _emu): (Box<dyn irid::pipeline::sequencer::BandTuner>, _) = if in_process {
        cam.set_speed(arg("--speed", 10.0));
        let t = EmulatedTuner::new(
            view.clone(),
            Duration::from_millis(5),
            Duration::from_micros(400),
            9,
        );
        (Box::new(t), None)
    } else {
        let (t, h) = irid::device::rig::emulated_varispec(view, time_scale).unwrap();
        (Box::new(t), Some(h))
    };
    let info = cam.info();
    let meta = CalMeta {
        version: 1,
        width: info.width,
        height: info.height,
        bands_nm: nm.clone(),
        exposure_us: info.exposure_us,
        gain: info.gain,
        format: info.format,
        camera_id: info.id,
        created_unix_s: 0,
        white_reflectance: 0.99,
        frames: 2,
        noise: None,
    };
    let policy = CalibrationPolicy::for_format(info.format);
    let cal = Calibration::from_references(meta, &dark, &white, &policy);
    println!(
        "soak: {sweeps} sweeps of 32 × 8 px, 31 bands, fast, threaded, {} ({})",
        if in_process {
            format!(
                "in-process filter, camera paced at {}×",
                arg("--speed", 10.0)
            )
        } else {
            format!("VariSpec emulator at {time_scale}×")
        },
        irid::pipeline::sequencer::BandTuner::describe(&tuner)
    );
    let setup = Setup {
        scene,
        bands,
        order,
        seq_mode: SeqMode::Stepped,
        calibrator: Calibrator::new(&cal),
    };
    let run_cfg = RunConfig {
        sweeps: Some(sweeps),
        mode: Mode::Fast,
        threads: Some(1),
        ..RunConfig::default()
    };
    let mut soak = Soak {
        every,
        started: Instant::now(),
        latencies: Vec::new(),
        frames_dropped: 0,
        sweeps_dropped: 0,
        first: 0,
        windows: Vec::new(),
    };
    let rep = run(
        &mut cam,
        &mut tuner,
        setup,
        &run_cfg,
        &mut soak,
        &AtomicBool::new(false),
    )
    .unwrap();
    println!(
        "done: {} sweeps mapped, {} dropped, {} frames ({} lost, {} settling, {} lost while tuning) in {:.1} s",
        rep.sweeps_completed,
        rep.sweeps_dropped,
        rep.frames_total,
        rep.frames_dropped,
        rep.frames_settling,
        rep.frames_lost_tuning,
        soak.started.elapsed().as_secs_f64()
    );
    // The trend after the first window (warm-up: index estimate, allocator).
    let w = soak.windows.get(1..).unwrap_or_default();
    if w.len() >= 2 {
        let per = |f: &dyn Fn(&Window) -> f64| {
            slope(&w.iter().map(f).collect::<Vec<_>>()) * 1000.0 / every as f64
        };
        println!(
            "trend per 1000 sweeps after warm-up: RSS {:+.1} kB, latency p50 {:+.3} ms, p99 {:+.3} ms",
            per(&|x| x.rss_kb as f64),
            per(&|x| x.p50_ms),
            per(&|x| x.p99_ms)
        );
    } else {
        println!("(too few windows for a trend: raise --sweeps or lower --every)");
    }
}
