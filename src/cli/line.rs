//! `irid run --scene web`: the moving-web demo — the synthetic web through
//! the emulated filter, mapped row by row, with lane statistics, the
//! recipe's alarms, EXR strip segments and JSON lines on stdout (and MQTT
//! when the web file names a broker).

use super::run::RunArgs;
use crate::line::mqtt::{MqttConfig, MqttPublisher};
use crate::line::output::{JsonLines, LineOutput, OutputConfig, Publisher};
use crate::line::recipe::Recipe;
use crate::line::rig::WebRig;
use crate::line::run::{run_line, LineLimits};
use crate::line::stats::Lanes;
use anyhow::Context;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

/// Frames per `--sweeps` unit: 4 s of the demo's 10 ms frames.
const FRAMES_PER_UNIT: u64 = 400;

/// Whether `--scene` asks for the moving web (`web`, or a web file).
pub fn wants_web(args: &RunArgs) -> bool {
    args.scene.as_deref().is_some_and(|s| {
        s == Path::new("web")
            || std::fs::read_to_string(s).is_ok_and(|t| t.contains("[web]") && t.contains("[film]"))
    })
}

/// Run the moving-web demo.
pub fn run(args: &RunArgs, stop: &AtomicBool) -> anyhow::Result<()> {
    // Options of the static pipeline the moving web does not have yet:
    // refused, never silently ignored (a recording asked for and not made
    // is lost data).
    let missing: Vec<&str> = [
        (args.record.is_some(), "--record"),
        (args.serve.is_some(), "--serve"),
        (args.png, "--png"),
    ]
    .into_iter()
    .filter_map(|(asked, name)| asked.then_some(name))
    .collect();
    if !missing.is_empty() {
        anyhow::bail!(
            "the moving web (--scene web) does not support {} yet; the static scene does",
            missing.join(", ")
        );
    }
    let rig = match args.scene.as_deref() {
        Some(p) if p != Path::new("web") => WebRig::load(p)?,
        _ => WebRig::demo()?,
    };
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
    let built = rig.build(cfg, args.mode)?;
    let (mut cam, mut tuner, setup) = (built.camera, built.tuner, built.setup);
    let recipe = match &rig.file.recipe {
        Some(r) => Some(Recipe::load(&rig.base.join(r))?),
        None => None,
    };
    let out_dir = (!args.no_maps).then(|| args.out.join("line"));
    if let Some(d) = &out_dir {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    let mut pubs: Vec<Box<dyn Publisher + Send>> = vec![Box::new(JsonLines(std::io::stdout()))];
    if let Some(addr) = &rig.file.line.mqtt {
        let (host, port) = addr
            .rsplit_once(':')
            .and_then(|(h, p)| Some((h, p.parse::<u16>().ok()?)))
            .with_context(|| format!("mqtt = {addr:?}: expected host:port"))?;
        pubs.push(Box::new(MqttPublisher::start(MqttConfig::new(host, port))));
    }
    let width = rig.file.camera.width as usize;
    let out_cfg = OutputConfig {
        segment_rows: rig.file.line.segment_rows,
        lanes: Lanes::equal(width, rig.file.line.lanes),
        out_dir,
        topic: "irid/line".into(),
    };
    let mut out = LineOutput::new(out_cfg, recipe, pubs);
    let frames = (args.sweeps > 0).then(|| args.sweeps * FRAMES_PER_UNIT);
    let limits = LineLimits {
        frames,
        frame_timeout: Duration::from_secs(2),
    };
    let rep = run_line(&mut cam, &mut tuner, setup, &limits, &mut out, stop)?;
    eprintln!(
        "irid line: {} rows emitted ({} complete, {} missing bands, {} skipped), {} segments, {} alarm events; \
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
    if rep.capture_waits > 0 || out.output_waits() > 0 {
        eprintln!(
            "irid line: capture waited for the solver {} times, rows for the output worker {} times (the CPU or the disk fell behind)",
            rep.capture_waits,
            out.output_waits()
        );
    }
    Ok(())
}
