//! A long run: ≥ 500 sweeps of small frames in `fast` mode through the
//! whole pipeline (synthetic camera, emulated filter, calibration,
//! tracking, solve, sink), checking that the process's resident memory
//! stays flat after warm-up and that every sweep is mapped.
//!
//! One test in its own binary: RSS is process-wide, so no other test may
//! run beside it.

mod pipeline_common;

use irid::device::camera::synthetic::{FilterView, SensorModel, SyntheticCamera, SyntheticConfig};
use irid::estimate::{Mode, ParamMaps};
use irid::pipeline::calibration::Calibrator;
use irid::pipeline::output::SweepSummary;
use irid::pipeline::runner::{run, RunConfig, Setup, SweepSink};
use irid::pipeline::sequencer::{order_for, EmulatedTuner, SeqMode};
use irid::scene::{Scene, SceneFile};
use pipeline_common::calibrate;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

/// Sweeps before memory is measured: the first sweep estimates the film
/// index and noise; the allocator settles over the next few.
const WARM_UP: usize = 20;

/// Growth of resident memory allowed from the end of warm-up to the end of
/// the run. Nothing on the per-frame path allocates and per-sweep
/// allocations (summaries, map metadata) are freed each sweep, so the
/// expected growth is zero; the bound leaves room for the allocator's
/// arenas and page-granular RSS (a few MB), and is far below what a leak of
/// one 32 × 8 × 31-band sweep buffer (32 kB) per sweep would add over 500
/// sweeps (16 MB).
const MAX_GROWTH_KB: u64 = 6 * 1024;

fn rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .expect("VmRSS in /proc/self/status")
}

struct Watch {
    rss_kb: Vec<u64>,
    valid: Vec<f64>,
}

impl SweepSink for Watch {
    fn on_sweep(&mut self, s: &SweepSummary, _: &ParamMaps) -> Result<(), String> {
        self.rss_kb.push(rss_kb());
        self.valid.push(s.valid_fraction);
        Ok(())
    }
}

fn small_scene() -> Scene {
    let mut f: SceneFile = toml::from_str(irid::scene::PAPER_CYLINDER).unwrap();
    let t = f.truth.as_mut().unwrap();
    t.width = 32;
    t.height = 8;
    Scene::resolve(&f, std::path::Path::new(".")).unwrap()
}

#[test]
fn five_hundred_sweeps_in_flat_memory() {
    let sweeps = 500;
    let scene = small_scene();
    let bands = scene.bands.clone().unwrap();
    let nm: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    let order = order_for("ascending", bands.len(), &nm).unwrap();
    let view = FilterView::new();
    let cfg = SyntheticConfig {
        seed: 5,
        sensor: SensorModel::default(),
        ..Default::default()
    };
    let mut cam = SyntheticCamera::new(&scene, &bands, view.clone(), cfg).unwrap();
    // The filter on a virtual clock: settling costs frames, not wall time.
    let mut tuner = EmulatedTuner::new(
        view,
        Duration::from_millis(5),
        Duration::from_micros(400),
        5,
    );
    let cal = calibrate(&mut cam, &mut tuner, SeqMode::Stepped, &nm, &order, 2);
    let setup = Setup {
        scene: scene.clone(),
        bands: bands.clone(),
        order,
        seq_mode: SeqMode::Stepped,
        calibrator: Calibrator::new(&cal),
    };
    let run_cfg = RunConfig {
        sweeps: Some(sweeps),
        mode: Mode::Fast,
        single_thread: true,
        ..RunConfig::default()
    };
    let mut watch = Watch {
        rss_kb: Vec::new(),
        valid: Vec::new(),
    };
    let rep = run(
        &mut cam,
        &mut tuner,
        setup,
        &run_cfg,
        &mut watch,
        &AtomicBool::new(false),
    )
    .unwrap();
    assert_eq!(rep.sweeps_completed, sweeps);
    assert_eq!(rep.sweeps_dropped, 0);
    assert!(
        watch.valid.iter().all(|&v| v > 0.9),
        "every sweep still maps the film"
    );
    let base = watch.rss_kb[WARM_UP];
    let last = *watch.rss_kb.last().unwrap();
    let peak = *watch.rss_kb[WARM_UP..].iter().max().unwrap();
    eprintln!("RSS after {WARM_UP} sweeps {base} kB, after {sweeps} {last} kB, peak {peak} kB");
    assert!(
        peak.saturating_sub(base) <= MAX_GROWTH_KB,
        "resident memory grew by {} kB over {} sweeps",
        peak - base,
        sweeps as usize - WARM_UP
    );
}
