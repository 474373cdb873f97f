//! Shared rig for the pipeline tests: the paper cylinder seen by the
//! synthetic camera through an emulated filter, calibrated like a real line.
#![allow(dead_code)]

use irid::device::camera::synthetic::{FilterView, SensorModel, SyntheticCamera, SyntheticConfig};
use irid::device::camera::{FrameSource, Target};
use irid::estimate::ParamMaps;
use irid::optics::band::Band;
use irid::pipeline::calibration::{
    capture_reference, CalMeta, Calibration, CalibrationPolicy, Calibrator, CapturePlan,
};
use irid::pipeline::runner::{run, RunConfig, RunError, RunReport, Setup, SweepSink};
use irid::pipeline::sequencer::{order_for, BandTuner, EmulatedTuner, SeqMode};
use irid::scene::Scene;
use irid::synth::{Renderer, TruthMaps};
use std::sync::atomic::AtomicBool;
use std::time::Duration;

pub struct Rig {
    pub cam: SyntheticCamera,
    pub tuner: EmulatedTuner,
    pub view: FilterView,
    pub scene: Scene,
    pub bands: Vec<Band>,
    pub order: Vec<usize>,
    pub cal: Calibration,
    pub truth: TruthMaps,
}

pub fn scene() -> Scene {
    Scene::paper_cylinder()
}

pub fn rig(seed: u64, order: &str, triggered: bool) -> Rig {
    let scene = scene();
    let bands = scene.bands.clone().unwrap();
    let nm: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    let order = order_for(order, bands.len(), &nm).unwrap();
    let view = FilterView::new();
    // A fast camera (2 ms frames, 1 ms exposure, same light per frame as
    // the default 10 ms one) so paced threaded runs take a fraction of a
    // second per sweep.
    let d = SensorModel::default();
    let sensor = SensorModel {
        exposure_us: 1000,
        frame_period_ns: 2_000_000,
        counts_per_us: d.counts_per_us * f64::from(d.exposure_us) / 1000.0,
        ..d
    };
    let cfg = SyntheticConfig {
        seed,
        sensor,
        trigger_palette: triggered.then(|| order.clone()),
        // Half a second of frames in the driver's queue: a test machine
        // busy with other tests may keep capture off its core for longer
        // than eight 2 ms frames, and these tests check pairing and
        // dropping, not a camera that loses frames (`irid run`'s keeps 8).
        queue_frames: 250,
        ..Default::default()
    };
    let mut cam = SyntheticCamera::new(&scene, &bands, view.clone(), cfg).unwrap();
    // The filter settles in 5 ms + up to 0.4 ms: two or three 2 ms frames
    // are exposed while it moves and must be discarded.
    let mut tuner = EmulatedTuner::new(
        view.clone(),
        Duration::from_millis(5),
        Duration::from_micros(400),
        seed,
    );
    let mode = if triggered {
        SeqMode::Triggered
    } else {
        SeqMode::Stepped
    };
    let cal = calibrate(&mut cam, &mut tuner, mode, &nm, &order, 4);
    let truth = Renderer::new(&scene).unwrap().truth_maps(&bands);
    Rig {
        cam,
        tuner,
        view,
        scene,
        bands,
        order,
        cal,
        truth,
    }
}

pub fn calibrate(
    cam: &mut dyn FrameSource,
    tuner: &mut dyn BandTuner,
    mode: SeqMode,
    nm: &[f64],
    order: &[usize],
    frames: u32,
) -> Calibration {
    let info = cam.info();
    let plan = CapturePlan {
        mode,
        bands_nm: nm,
        order,
        frames,
        timeout: Duration::from_secs(1),
    };
    cam.set_target(Target::Dark).unwrap();
    let dark = capture_reference("dark", cam, tuner, &plan).unwrap();
    cam.set_target(Target::White(0.99)).unwrap();
    let white = capture_reference("white", cam, tuner, &plan).unwrap();
    cam.set_target(Target::Scene).unwrap();
    let meta = CalMeta {
        version: 1,
        width: info.width,
        height: info.height,
        bands_nm: nm.to_vec(),
        exposure_us: info.exposure_us,
        gain: info.gain,
        format: info.format,
        camera_id: info.id,
        created_unix_s: 1_700_000_000,
        white_reflectance: 0.99,
        frames,
        noise: None,
    };
    Calibration::from_references(
        meta,
        &dark,
        &white,
        &CalibrationPolicy::for_format(info.format),
    )
}

impl Rig {
    /// Run `sweeps` sweeps; threaded runs pace the camera to the wall clock
    /// (an unpaced camera delivers frames infinitely fast, and the pipeline
    /// rightly drops sweeps).
    pub fn go(
        &mut self,
        triggered: bool,
        cfg: &RunConfig,
        sink: &mut dyn SweepSink,
        stop: &AtomicBool,
    ) -> Result<RunReport, RunError> {
        self.cam.set_realtime(!cfg.single_thread);
        let setup = self.setup(triggered);
        run(&mut self.cam, &mut self.tuner, setup, cfg, sink, stop)
    }

    pub fn setup(&self, triggered: bool) -> Setup {
        Setup {
            scene: self.scene.clone(),
            bands: self.bands.clone(),
            order: self.order.clone(),
            seq_mode: if triggered {
                SeqMode::Triggered
            } else {
                SeqMode::Stepped
            },
            calibrator: Calibrator::new(&self.cal),
        }
    }
}

pub fn config(sweeps: u64, single_thread: bool) -> RunConfig {
    RunConfig {
        sweeps: Some(sweeps),
        single_thread,
        threads: Some(2),
        ..RunConfig::default()
    }
}

/// Thickness error statistics of valid pixels: (mean |err|, max |err|, valid fraction).
pub fn thickness_error(maps: &ParamMaps, truth: &TruthMaps) -> (f64, f64, f64) {
    let (mut n, mut sum, mut max) = (0usize, 0.0f64, 0.0f64);
    for i in 0..maps.valid.len() {
        if maps.valid[i] > 0.5 {
            let e = (f64::from(maps.thickness_nm[i]) - f64::from(truth.thickness_nm[i])).abs();
            n += 1;
            sum += e;
            max = max.max(e);
        }
    }
    (
        sum / n.max(1) as f64,
        max,
        n as f64 / maps.valid.len() as f64,
    )
}

/// Valid pixels of `maps`, and those of them farther than max(3σ, 2 nm)
/// from the truth (a valid pixel must be right).
pub fn valid_and_wrong(maps: &ParamMaps, truth: &TruthMaps) -> (usize, usize) {
    let (mut valid, mut wrong) = (0usize, 0usize);
    for p in 0..maps.width * maps.height {
        if maps.valid[p] > 0.5 {
            valid += 1;
            let e = f64::from((maps.thickness_nm[p] - truth.thickness_nm[p]).abs());
            if e > (3.0 * f64::from(maps.sigma_thickness_nm[p])).max(2.0) {
                wrong += 1;
            }
        }
    }
    (valid, wrong)
}

/// Maps compared bit for bit (NaN payloads included).
pub fn bits(maps: &ParamMaps) -> Vec<u32> {
    maps.channels()
        .iter()
        .flat_map(|(_, v)| v.iter().map(|x| x.to_bits()))
        .collect()
}
