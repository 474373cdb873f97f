//! The highest line speed the processor sustains when the filter is not the
//! limit: a 1280-pixel web, 31 bands, `ROWS` rows in view, the filter
//! settling instantly (one band per frame), frames as fast as the CPU takes
//! them. The camera's own rendering time is measured and left out (a real
//! camera renders nothing).
//!
//! `cargo bench --bench line [-- FRAMES [ROWS]]` (default 1500 frames, 64 rows)

use irid::device::camera::{CameraError, CameraInfo, Frame, FrameSource};
use irid::estimate::Mode;
use irid::line::rig::WebRig;
use irid::line::run::{run_line, CollectRows, LineLimits};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

/// Times the wrapped camera.
struct Timed<S> {
    inner: S,
    spent: Duration,
}

impl<S: FrameSource> FrameSource for Timed<S> {
    fn info(&self) -> CameraInfo {
        self.inner.info()
    }
    fn next_frame(&mut self, out: &mut Frame, t: Duration) -> Result<(), CameraError> {
        let t0 = Instant::now();
        let r = self.inner.next_frame(out, t);
        self.spent += t0.elapsed();
        r
    }
    fn set_exposure(&mut self, e: u32) -> Result<u32, CameraError> {
        self.inner.set_exposure(e)
    }
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let frames: u64 = args.first().and_then(|a| a.parse().ok()).unwrap_or(1500);
    let rows: u32 = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(64);
    let mut rig = WebRig::demo().expect("demo web");
    rig.file.camera.width = 1280;
    rig.file.camera.rows_in_view = rows;
    rig.file.camera.frame_period_ms = 1.0;
    rig.file.camera.exposure_ms = 0.5;
    rig.file.filter.settle_ms = 0.0;
    rig.file.filter.settle_jitter_ms = 0.0;
    rig.file.web.speed_fraction = Some(0.95);
    let rig = WebRig::resolve(rig.file, rig.base).expect("resolves");
    let built = rig
        .build(rig.camera_config(), Mode::Balanced)
        .expect("builds");
    let (cam, mut tuner, setup) = (built.camera, built.tuner, built.setup);
    let mut cam = Timed {
        inner: cam,
        spent: Duration::ZERO,
    };
    let mut sink = CollectRows::default();
    let t0 = Instant::now();
    let rep = run_line(
        &mut cam,
        &mut tuner,
        setup,
        &LineLimits {
            frames: Some(frames),
            frame_timeout: Duration::from_secs(1),
        },
        &mut sink,
        &AtomicBool::new(false),
    )
    .expect("runs");
    let wall = t0.elapsed().as_secs_f64();
    let proc_s = wall - cam.spent.as_secs_f64();
    let bands_per_s = rep.frames_accepted as f64 / proc_s;
    let n = rig.geometry.n_bands as f64;
    let speed = rows as f64 * bands_per_s / n;
    println!(
        "line: 1280 px × {rows} rows in view × {} bands, {} frames ({} accepted), {} rows emitted ({} missing bands)",
        n, rep.frames_total, rep.frames_accepted, rep.rows_emitted, rep.rows.missing_bands
    );
    println!(
        "line: processing {proc_s:.2} s (camera rendering {:.2} s left out): {bands_per_s:.1} bands/s sustained \
         → highest line speed {speed:.1} rows/s ({:.1} web rows solved per second of CPU)",
        cam.spent.as_secs_f64(),
        rep.rows_emitted as f64 / proc_s
    );
    println!(
        "line: row latency after its last band: mean {:.2} ms, max {:.2} ms",
        rep.latency_ms_mean, rep.latency_ms_max
    );
}
