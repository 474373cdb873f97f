//! Pipeline benchmark (harness = false): prints numbers and the machine.
//!
//! 1. Ingest (calibrate + track) of 1280×1024 16-bit frames, in
//!    pixel-bands/s, beside a plain memcpy of the same bytes in the same
//!    run, on one core; with a disabled tracing span per frame, without
//!    one, and with the `--profile` layer installed (the cost of tracing).
//! 2. Keeps up: the whole threaded pipeline at 1280×1024, 31 bands,
//!    triggered at ≥ 20 bands/s (balanced) and ≥ 100 bands/s (fast): drops,
//!    latency from last band to map, peak RSS.
//!
//! Frame generation is precomputed (rendered planes and a per-band noisy
//! frame cache) and measured apart.
//!
//! Each line of section 1 also gives the bytes moved per pixel-band (read +
//! written, the least the stage must move) and the rate that makes, beside
//! memcpy's (2 + 2 bytes): the memory-bandwidth reference.
//!
//! `cargo bench --bench pipeline [-- quick] [-- ingest]` (`quick`: 640×512,
//! fewer sweeps; `ingest`: section 1 only, without the solver and keeps-up).

use irid::device::camera::synthetic::{
    lctf_transmission, FilterView, SensorModel, SyntheticCamera, SyntheticConfig,
};
use irid::device::camera::{Frame, FrameSource, PixelFormat};
use irid::estimate::{Mode, ParamMaps};
use irid::pipeline::calibration::{CalMeta, Calibration, Calibrator};
use irid::pipeline::output::SweepSummary;
use irid::pipeline::runner::{run, RunConfig, Setup, SweepSink};
use irid::pipeline::sequencer::{order_for, EmulatedTuner, SeqMode};
use irid::pipeline::tracker::Tracker;
use irid::scene::{Field, Scene, SceneFile};
use std::hint::black_box;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    format!("{cpu}, {cores} cores available")
}

fn vm(key: &str) -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(key))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn scene(w: usize, h: usize) -> Scene {
    let mut f: SceneFile = toml::from_str(irid::scene::PAPER_CYLINDER).unwrap();
    let t = f.truth.as_mut().unwrap();
    t.width = w;
    t.height = h;
    // 10° → 42.5° down the image whatever its height.
    t.angle_deg = Some(Field::LinearY([10.0, 42.5]));
    Scene::resolve(&f, std::path::Path::new(".")).unwrap()
}

fn sensor() -> SensorModel {
    SensorModel::default()
}

/// An ideal calibration for the synthetic sensor (dark = offset, white =
/// offset + the R = 0.99 signal), so ingest does real arithmetic.
fn calibration(w: u32, h: u32, nm: &[f64], exposure_us: u32) -> Calibration {
    let s = sensor();
    let n = (w * h) as usize;
    let mut dark = Vec::with_capacity(n * nm.len());
    let mut white = Vec::with_capacity(n * nm.len());
    for &l in nm {
        let k = s.counts_per_us * f64::from(exposure_us) * lctf_transmission(l) * 0.99;
        dark.extend(std::iter::repeat_n(s.dark_offset as f32, n));
        white.extend(std::iter::repeat_n((s.dark_offset + k) as f32, n));
    }
    Calibration {
        meta: CalMeta {
            version: 1,
            width: w,
            height: h,
            bands_nm: nm.to_vec(),
            exposure_us,
            gain: 1.0,
            format: PixelFormat::Y16,
            camera_id: "bench".into(),
            created_unix_s: 0,
            white_reflectance: 0.99,
            frames: 1,
            noise: None,
        },
        flags: vec![0; dark.len()],
        dark,
        white,
    }
}

fn time<F: FnMut()>(reps: usize, mut f: F) -> f64 {
    f(); // warm
    let t = Instant::now();
    for _ in 0..reps {
        f();
    }
    t.elapsed().as_secs_f64() / reps as f64
}

struct Keep {
    latencies: Vec<f64>,
    dropped: u64,
}

impl SweepSink for Keep {
    fn on_sweep(&mut self, s: &SweepSummary, _m: &ParamMaps) -> Result<(), String> {
        self.latencies.push(s.latency_ms);
        self.dropped += s.frames_dropped;
        println!(
            "    sweep {}: valid {:.1}%, d = {:.1} ± {:.1} nm, n = {:.4}, latency {:.0} ms",
            s.sweep,
            100.0 * s.valid_fraction,
            s.thickness_mean_nm,
            s.thickness_std_nm,
            s.n_film,
            s.latency_ms
        );
        Ok(())
    }
}

fn main() {
    let quick = std::env::args().any(|a| a == "quick");
    let ingest_only = std::env::args().any(|a| a == "ingest");
    if let Some(case) = std::env::args().find_map(|a| a.strip_prefix("case=").map(str::to_string)) {
        keeps_up(&case, quick);
        return;
    }
    let (w, h) = if quick {
        (640usize, 512usize)
    } else {
        (1280, 1024)
    };
    println!("irid pipeline benchmark — {}", machine());
    println!("frames {w}×{h} Y16, 31 bands (paper cylinder stretched to the frame)");

    // Frame generation, measured apart.
    let sc = scene(w, h);
    let bands = sc.bands.clone().unwrap();
    let nm: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    let t = Instant::now();
    let view = FilterView::new();
    let mut cam = SyntheticCamera::new(
        &sc,
        &bands,
        view.clone(),
        SyntheticConfig {
            noise_pool: true,
            sensor: sensor(),
            ..Default::default()
        },
    )
    .unwrap();
    println!(
        "frame generation: rendered + noise-cached 31 bands in {:.2} s (once; RSS now {:.0} MiB)",
        t.elapsed().as_secs_f64(),
        vm("VmRSS:")
    );
    let mut frames: Vec<Frame> = Vec::new();
    for (b, &l) in nm.iter().enumerate() {
        view.tune(l, 0, 0);
        let mut f = Frame::with_size(w as u32, h as u32, PixelFormat::Y16);
        cam.next_frame(&mut f, Duration::ZERO).unwrap();
        f.meta.seq = b as u64;
        frames.push(f);
    }
    let t = Instant::now();
    let mut f = Frame::with_size(w as u32, h as u32, PixelFormat::Y16);
    for _ in 0..31 {
        cam.next_frame(&mut f, Duration::ZERO).unwrap();
    }
    println!(
        "  synthetic camera, settled frame from the cache: {:.2} ms/frame",
        t.elapsed().as_secs_f64() / 31.0 * 1e3
    );

    // 1. Ingest vs memcpy, one core.
    let t = Instant::now();
    let cal = Calibrator::new(&calibration(w as u32, h as u32, &nm, sensor().exposure_us));
    println!(
        "calibrator prepared in {:.2} s: {} of 31 bands packed, {:.1} B per pixel-band",
        t.elapsed().as_secs_f64(),
        cal.packed_bands(),
        cal.bytes_per_pixel_band()
    );
    // `irid run`'s default ingest (no candidate tracking), and the one that
    // tracks extremum candidates (`--track-extrema on`).
    let tracker = Tracker::new(w, h, &bands).track_extrema(false);
    let tracking = Tracker::new(w, h, &bands).track_extrema(true);
    let mut buf = tracking.new_sweep_buf();
    let order = order_for("ascending", 31, &nm).unwrap();
    let n = w * h;
    let reps = if quick { 3 } else { 5 };
    let mut dst = vec![0u16; n];
    let t_copy = time(reps, || {
        for f in &frames {
            dst.copy_from_slice(&f.data);
            black_box(&dst);
        }
    }) / 31.0;
    // The same copies into a destination as far out of cache as the sweep
    // cube ingest writes into: a ring of 31 frames (81 MB), pre-faulted.
    let mut ring = vec![1u16; n * frames.len()];
    let t_copy_ring = time(reps, || {
        for (f, d) in frames.iter().zip(ring.chunks_mut(n)) {
            d.copy_from_slice(&f.data);
            black_box(&d[0]);
        }
    }) / 31.0;
    drop(ring);
    let sweep = |span: bool, buf: &mut irid::pipeline::tracker::SweepBuf| {
        tracker.begin(buf, 0);
        for &b in &order {
            let _s = span.then(|| tracing::info_span!("ingest.frame", band = b).entered());
            tracker.ingest(buf, b, &frames[b], &cal).unwrap();
        }
        black_box(&buf.cube.data[0]);
    };
    let t_ingest = time(reps, || sweep(false, &mut buf)) / 31.0;
    let t_tracked = time(reps, || {
        tracking.begin(&mut buf, 0);
        for &b in &order {
            tracking.ingest(&mut buf, b, &frames[b], &cal).unwrap();
        }
        black_box(&buf.cube.data[0]);
    }) / 31.0;
    let t_span = time(reps, || sweep(true, &mut buf)) / 31.0;
    let profile = irid::pipeline::profile::ProfileLayer::new();
    let t_prof = {
        use tracing_subscriber::prelude::*;
        let sub = tracing_subscriber::registry().with(profile.clone());
        tracing::subscriber::with_default(sub, || time(reps, || sweep(true, &mut buf))) / 31.0
    };
    let mut plane = vec![0.0f32; n];
    let t_cal = time(reps, || {
        for &b in &order {
            cal.apply(
                b,
                &frames[b].data,
                u16::MAX,
                sensor().exposure_us,
                &mut plane,
            );
            black_box(&plane);
        }
    }) / 31.0;
    let pbs = |t: f64| n as f64 / t / 1e6;
    // Bytes each stage must move per pixel-band: memcpy reads and writes
    // u16; calibration reads u16 counts and its per-pixel planes and writes
    // f32; candidate tracking (ascending order: each new band completes
    // one candidate's five-band window) reads four f32 planes more.
    let b_copy = 4.0;
    let b_cal = 2.0 + cal.bytes_per_pixel_band() + 4.0;
    let b_ext = b_cal + 16.0;
    let gbs = |bytes: f64, t: f64| bytes * n as f64 / t / 1e9;
    println!(
        "\n1. ingest, one core, per band frame ({} MB of u16); bytes moved per pixel-band, read + written:",
        2 * n / 1_000_000
    );
    println!(
        "  memcpy of the frame        {:7.3} ms  {:8.1} M pixel-bands/s  ({:.1} GB/s)  {:4.1} B  (the reference)",
        t_copy * 1e3,
        pbs(t_copy),
        gbs(b_copy, t_copy),
        b_copy
    );
    println!(
        "  … into a 31-frame ring      {:7.3} ms  {:8.1} M pixel-bands/s  ({:.1} GB/s)  {:4.1} B  (out of cache, as the sweep cube; ingest = {:.2}× this)",
        t_copy_ring * 1e3,
        pbs(t_copy_ring),
        gbs(b_copy, t_copy_ring),
        b_copy,
        t_ingest / t_copy_ring
    );
    for (label, t, b) in [
        ("calibrate only            ", t_cal, b_cal),
        ("ingest (calibrate + track)", t_ingest, b_cal),
        ("… + candidate tracking    ", t_tracked, b_ext),
    ] {
        println!(
            "  {label} {:7.3} ms  {:8.1} M pixel-bands/s  ({:.2}× memcpy)  {b:4.1} B  {:5.1} GB/s ({:.0}% of memcpy's)",
            t * 1e3,
            pbs(t),
            t / t_copy,
            gbs(b, t),
            100.0 * gbs(b, t) / gbs(b_copy, t_copy)
        );
    }
    println!(
        "  … with a span per frame, no subscriber   {:7.3} ms ({:+.2}%)",
        t_span * 1e3,
        100.0 * (t_span / t_ingest - 1.0)
    );
    println!(
        "  … with the --profile layer installed     {:7.3} ms ({:+.2}%)",
        t_prof * 1e3,
        100.0 * (t_prof / t_ingest - 1.0)
    );
    // One tracked sweep again, for its candidates.
    tracking.begin(&mut buf, 0);
    for &b in &order {
        tracking.ingest(&mut buf, b, &frames[b], &cal).unwrap();
    }
    if let Some(cp) = &buf.candidates {
        use irid::estimate::detect::{Candidates, CHUNK};
        let mut c = Candidates::default();
        let mut total = 0u64;
        for y in 0..h {
            for k in 0..w.div_ceil(CHUNK) {
                cp.unpack(y, k, &mut c);
                total += c
                    .maxima
                    .iter()
                    .chain(&c.minima)
                    .map(|m| u64::from(m.count_ones()))
                    .sum::<u64>();
            }
        }
        println!(
            "  (extremum candidates tracked: {:.2} per pixel)",
            total as f64 / n as f64
        );
    }
    if ingest_only {
        return;
    }
    // The solver on the ingested sweep, one thread, for comparison.
    println!("  solver alone on this sweep, one thread (what the pipeline waits for):");
    for (mode, tracked) in [
        (Mode::Fast, false),
        (Mode::Fast, true),
        (Mode::Balanced, false),
    ] {
        let mut solver = irid::estimate::Solver::new(&sc, &bands, mode).unwrap();
        let t = Instant::now();
        let est = solver.estimate_film_index(&buf.cube).unwrap();
        let t_index = t.elapsed().as_secs_f64();
        solver.set_film_index(est).unwrap();
        let rows = if quick { h / 4 } else { h / 16 };
        let mut out =
            vec![irid::estimate::PixelEstimate::invalid(irid::estimate::Reason::Masked); w];
        let mut scratch = irid::estimate::solver::Scratch::default();
        let t = Instant::now();
        for y in 0..rows {
            let pre = if tracked {
                buf.candidates.as_ref()
            } else {
                None
            };
            solver.solve_row_with(&buf.cube, y * (h / rows), &mut out, &mut scratch, pre);
            black_box(&out);
        }
        let px = (rows * w) as f64 / t.elapsed().as_secs_f64();
        println!(
            "    {:<25} {:6.2} M px/s per thread → {:5.2} s per {w}×{h} sweep on one thread (index estimate {:.2} s)",
            if tracked { "fast, tracked candidates" } else { mode.name() },
            px / 1e6,
            n as f64 / px,
            t_index
        );
    }
    drop(buf);
    drop(frames);

    drop(cam);
    // 2. Keeps up, each case in its own process so its peak RSS is its own.
    println!("\n2. keeps up: threaded pipeline, triggered camera (settled frame per band), {w}×{h}, 31 bands, 2 solver threads");
    let exe = std::env::current_exe().unwrap();
    for case in ["balanced", "fast", "fast-tracked"] {
        let mut c = std::process::Command::new(&exe);
        c.arg(format!("case={case}"));
        if quick {
            c.arg("quick");
        }
        let st = c.status().unwrap();
        assert!(st.success());
    }
}

fn keeps_up(case: &str, quick: bool) {
    let (w, h) = if quick {
        (640usize, 512usize)
    } else {
        (1280, 1024)
    };
    let sc = scene(w, h);
    let bands = sc.bands.clone().unwrap();
    let nm: Vec<f64> = bands.iter().map(|b| b.center_nm).collect();
    let order = order_for("ascending", 31, &nm).unwrap();
    let profile = irid::pipeline::profile::ProfileLayer::new();
    {
        use tracing_subscriber::prelude::*;
        tracing_subscriber::registry().with(profile.clone()).init();
    }
    let (mode, rate, sweeps) = match case {
        "balanced" => (Mode::Balanced, 20.0, if quick { 2 } else { 4 }),
        _ => (Mode::Fast, 100.0, if quick { 3 } else { 8 }),
    };
    {
        // 2. Keeps up.

        let palette = order.clone();
        let mut s = sensor();
        s.frame_period_ns = (1e9 / rate) as u64;
        s.exposure_us = s.exposure_us.min((s.frame_period_ns / 1000) as u32 - 500);
        let view = FilterView::new();
        let mut cam = SyntheticCamera::new(
            &sc,
            &bands,
            view.clone(),
            SyntheticConfig {
                noise_pool: true,
                sensor: s.clone(),
                trigger_palette: Some(palette),
                realtime: true,
                ..Default::default()
            },
        )
        .unwrap();
        let mut tuner = EmulatedTuner::new(view, Duration::ZERO, Duration::ZERO, 1);
        let setup = Setup {
            scene: sc.clone(),
            bands: bands.clone(),
            order: order.clone(),
            seq_mode: SeqMode::Triggered,
            calibrator: Calibrator::from_calibration(calibration(
                w as u32,
                h as u32,
                &nm,
                s.exposure_us,
            )),
        };
        let cfg = RunConfig {
            sweeps: Some(sweeps),
            mode,
            threads: Some(2),
            track_extrema: case == "fast-tracked",
            ..RunConfig::default()
        };
        let mut sink = Keep {
            latencies: Vec::new(),
            dropped: 0,
        };
        let period = 31.0 / rate * 1e3;
        println!(
            "  {case} ({}) at {rate} bands/s (sweep period {period:.0} ms), {sweeps} sweeps:",
            mode.name()
        );
        let t = Instant::now();
        let rep = run(
            &mut cam,
            &mut tuner,
            setup,
            &cfg,
            &mut sink,
            &AtomicBool::new(false),
        )
        .unwrap();
        let wall = t.elapsed().as_secs_f64();
        let max_lat = sink.latencies.iter().copied().fold(0.0, f64::max);
        println!(
            "    → {} maps in {wall:.1} s, {} sweeps dropped, {} frames dropped; latency max {max_lat:.0} ms ({} one sweep period); peak RSS {:.0} MiB",
            rep.sweeps_completed,
            rep.sweeps_dropped,
            rep.frames_dropped,
            if max_lat <= period { "≤" } else { "> !" },
            vm("VmHWM:")
        );
    }
    print!("{}", indent(&profile.report()));
}

fn indent(s: &str) -> String {
    s.lines().map(|l| format!("      {l}\n")).collect()
}
