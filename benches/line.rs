//! The highest line speed the processor sustains when the filter is not the
//! limit: a 1280-pixel web, 31 bands, `ROWS` rows in view, the filter
//! settling instantly (one band per frame), frames as fast as the CPU takes
//! them. The camera's own rendering time is measured and left out (a real
//! camera renders nothing).
//!
//! The rows go to the line's real output (lane statistics, alarms, EXR
//! segments of 64 rows written to a temporary directory): the latency is
//! that of a production run.
//!
//! `cargo bench --bench line [-- FRAMES [ROWS [split|inline [RATE]]]]`
//! (default 1500 frames, 64 rows, split: capture and solving on separate
//! threads, files on the output worker; inline: everything in the capture
//! loop). Without RATE the camera delivers frames as fast as they are
//! taken (the sustained band rate); with RATE it delivers RATE frames per
//! second of wall time, as a camera behind a filter stepping RATE bands/s
//! does (the row latency at that band rate). `spread=DEG` anywhere in the
//! arguments makes the incidence angle run ±DEG across the view (around
//! the scene's 30°), each band then modelled at its own angle where the
//! rule asks for it; `correction=off|always` overrides the rule.

use irid::device::camera::{CameraError, CameraInfo, Frame, FrameSource};
use irid::estimate::Mode;
use irid::line::angles::Correction;
use irid::line::output::{LineOutput, OutputConfig};
use irid::line::rig::WebRig;
use irid::line::run::{run_line, LineLimits, Threading};
use irid::line::stats::Lanes;
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
    let all: Vec<String> = std::env::args().skip(1).collect();
    let keyed = |k: &str| {
        all.iter()
            .find_map(|a| a.strip_prefix(k).map(str::to_owned))
    };
    let spread: f64 = keyed("spread=").and_then(|v| v.parse().ok()).unwrap_or(0.0);
    let correction = match keyed("correction=").as_deref() {
        Some("off") => Correction::Off,
        Some("always") => Correction::Always,
        _ => Correction::Auto,
    };
    let args: Vec<String> = all
        .iter()
        .filter(|a| !a.starts_with('-') && !a.contains('='))
        .cloned()
        .collect();
    let frames: u64 = args.first().and_then(|a| a.parse().ok()).unwrap_or(1500);
    let rows: u32 = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(64);
    let inline = args.get(2).is_some_and(|a| a == "inline");
    let rate: f64 = args.get(3).and_then(|a| a.parse().ok()).unwrap_or(0.0);
    let mut rig = WebRig::demo().expect("demo web");
    rig.file.camera.width = 1280;
    rig.file.camera.rows_in_view = rows;
    rig.file.camera.frame_period_ms = 1.0;
    rig.file.camera.exposure_ms = 0.5;
    rig.file.filter.settle_ms = 0.0;
    rig.file.filter.settle_jitter_ms = 0.0;
    rig.file.web.speed_fraction = Some(0.95);
    if spread > 0.0 {
        rig.file.camera.angle_deg_per_row = Some(2.0 * spread / (f64::from(rows) - 1.0));
    }
    let rig = WebRig::resolve(rig.file, rig.base).expect("resolves");
    let mut cam_cfg = rig.camera_config();
    // 1 ms frames, one band each: RATE bands/s is 1000/RATE times slower.
    cam_cfg.realtime_speed = rate / 1000.0;
    let built = rig.build(cam_cfg, Mode::Balanced).expect("builds");
    let (cam, mut tuner, mut setup) = (built.camera, built.tuner, built.setup);
    setup.angle_correction = correction;
    setup.threading = if inline {
        Threading::Inline
    } else {
        Threading::Split
    };
    let dir = tempfile::tempdir().expect("temporary directory");
    let cfg = OutputConfig {
        segment_rows: 64,
        lanes: Lanes::equal(1280, 4),
        out_dir: Some(dir.path().to_path_buf()),
        topic: "irid/line".into(),
    };
    let mut sink = if inline {
        LineOutput::inline(cfg, None, Vec::new())
    } else {
        LineOutput::new(cfg, None, Vec::new())
    };
    let mut cam = Timed {
        inner: cam,
        spent: Duration::ZERO,
    };
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
    let n = rig.geometry.n_bands as f64;
    println!(
        "line: 1280 px × {rows} rows in view × {} bands, {} frames ({} accepted), {} rows emitted ({} missing bands)",
        n, rep.frames_total, rep.frames_accepted, rep.rows_emitted, rep.rows.missing_bands
    );
    if rate > 0.0 {
        println!("line: camera paced at {rate} frames/s of wall time");
    } else if inline {
        // One thread: the processing time is the wall time less the
        // camera's rendering.
        let proc_s = wall - cam.spent.as_secs_f64();
        let bands_per_s = rep.frames_accepted as f64 / proc_s;
        println!(
            "line: processing {proc_s:.2} s (camera rendering {:.2} s left out): {bands_per_s:.1} bands/s sustained \
             → highest line speed {:.1} rows/s ({:.1} web rows solved per second)",
            cam.spent.as_secs_f64(),
            rows as f64 * bands_per_s / n,
            rep.rows_emitted as f64 / proc_s
        );
    } else {
        // Threads overlap the camera's rendering with solving: the wall
        // clock's rate, rendering included (a floor).
        let bands_per_s = rep.frames_accepted as f64 / wall;
        println!(
            "line: {wall:.2} s of wall time, camera rendering ({:.2} s) included: {bands_per_s:.1} bands/s \
             → highest line speed {:.1} rows/s",
            cam.spent.as_secs_f64(),
            rows as f64 * bands_per_s / n
        );
    }
    println!(
        "line ({}): row latency after its last band: mean {:.2} ms, 99 % ≤ {:.0} ms, max {:.2} ms; \
         {} segments written; capture waited for the solver {} times, rows for the output worker {} times; \
         {} rows read during the warm-up's solving waited up to {:.0} ms",
        if inline { "inline" } else { "split" },
        rep.latency_ms_mean,
        rep.latency_ms_p99,
        rep.latency_ms_max,
        sink.files.len(),
        rep.capture_waits,
        sink.output_waits(),
        rep.warmup_wait_rows,
        rep.warmup_wait_ms_max
    );
    println!(
        "line: incidence angle ±{spread}° across the view ({correction:?}): {} of {} rows modelled at their bands' own angles",
        rep.rows_angle_corrected, rep.rows.complete
    );
}
