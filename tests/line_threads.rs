//! The threaded line runner (capture on one thread, solving + statistics on
//! another, segment files and messages on a third) emits exactly what the
//! same run with every stage inline emits: the same rows (bit for bit),
//! the same messages in the same order, the same alarms and the same
//! segment files.

use irid::estimate::Mode;
use irid::io::exr_maps::read_channels;
use irid::line::output::{Collected, LineOutput, OutputConfig, Publisher};
use irid::line::recipe::Recipe;
use irid::line::rig::WebRig;
use irid::line::run::{run_line, CollectRows, LineLimits, LineReport, Threading, WebRowSink};
use irid::line::solve::WebRowOut;
use irid::line::stats::Lanes;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::Duration;

struct Shared(Arc<Mutex<Collected>>);

impl Publisher for Shared {
    fn publish(&mut self, topic: &str, payload: &str) {
        self.0.lock().unwrap().publish(topic, payload);
    }
}

/// Keeps every row and passes it on to the line's output.
struct Tee {
    rows: CollectRows,
    out: LineOutput,
}

impl WebRowSink for Tee {
    fn on_row(&mut self, row: &WebRowOut) -> Result<(), String> {
        self.rows.on_row(row)?;
        self.out.on_row(row)
    }
    fn finish(&mut self) -> Result<(), String> {
        self.out.finish()
    }
}

struct Run {
    rep: LineReport,
    rows: Vec<WebRowOut>,
    messages: Vec<(String, String)>,
    alarms: usize,
    files: Vec<std::path::PathBuf>,
}

fn run(threading: Threading, background_output: bool, dir: &Path) -> Run {
    let rig = WebRig::demo().unwrap();
    let recipe = Recipe::load(&rig.base.join(rig.file.recipe.as_ref().unwrap())).unwrap();
    let built = rig.build(rig.camera_config(), Mode::Balanced).unwrap();
    let (mut cam, mut tuner, mut setup) = (built.camera, built.tuner, built.setup);
    setup.threading = threading;
    let got = Arc::new(Mutex::new(Collected::default()));
    let cfg = OutputConfig {
        // Short segments: many files, some written in the frame that
        // finishes other rows.
        segment_rows: 16,
        lanes: Lanes::equal(rig.file.camera.width as usize, 4),
        out_dir: Some(dir.to_path_buf()),
        topic: "irid/line".into(),
    };
    let pubs: Vec<Box<dyn Publisher + Send>> = vec![Box::new(Shared(got.clone()))];
    let out = if background_output {
        LineOutput::new(cfg, Some(recipe), pubs)
    } else {
        LineOutput::inline(cfg, Some(recipe), pubs)
    };
    let mut tee = Tee {
        rows: CollectRows::default(),
        out,
    };
    let rep = run_line(
        &mut cam,
        &mut tuner,
        setup,
        &LineLimits {
            frames: Some(900),
            frame_timeout: Duration::from_secs(1),
        },
        &mut tee,
        &AtomicBool::new(false),
    )
    .unwrap();
    let messages = got.lock().unwrap().0.clone();
    Run {
        rep,
        rows: tee.rows.rows,
        messages,
        alarms: tee.out.alarm_log.len(),
        files: tee.out.files.clone(),
    }
}

#[test]
fn threaded_runner_emits_what_the_inline_runner_emits() {
    let (d_ref, d_thr) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let reference = run(Threading::Inline, false, d_ref.path());
    let threaded = run(Threading::Split, true, d_thr.path());
    // The demo's run: hundreds of rows, the defect's two alarm events.
    assert!(reference.rows.len() > 300, "{:?}", reference.rep);
    assert_eq!(reference.alarms, 2);
    // Counters (latency and waits aside: they are the wall clock's).
    let strip = |r: &LineReport| LineReport {
        latency_ms_max: 0.0,
        latency_ms_mean: 0.0,
        latency_ms_p99: 0.0,
        capture_waits: 0,
        warmup_wait_rows: 0,
        warmup_wait_ms_max: 0.0,
        ..r.clone()
    };
    assert_eq!(strip(&reference.rep), strip(&threaded.rep));
    // Rows, bit for bit (NaN-free comparison of the estimates' fields).
    assert_eq!(reference.rows.len(), threaded.rows.len());
    for (a, b) in reference.rows.iter().zip(&threaded.rows) {
        assert_eq!(
            format!("{a:?}"),
            format!("{b:?}"),
            "row {} differs",
            a.index
        );
    }
    // Messages in the same order; the file names differ by directory only.
    let norm = |r: &Run, d: &Path| -> Vec<(String, String)> {
        r.messages
            .iter()
            .map(|(t, p)| (t.clone(), p.replace(&d.display().to_string(), "DIR")))
            .collect()
    };
    assert_eq!(
        norm(&reference, d_ref.path()),
        norm(&threaded, d_thr.path())
    );
    assert_eq!(reference.alarms, threaded.alarms);
    // Segment files: the same names, the same channels and header.
    assert!(reference.files.len() > 20);
    assert_eq!(reference.files.len(), threaded.files.len());
    for (a, b) in reference.files.iter().zip(&threaded.files) {
        assert_eq!(a.file_name(), b.file_name());
        let (ca, cb) = (read_channels(a).unwrap(), read_channels(b).unwrap());
        assert_eq!((ca.width, ca.height), (cb.width, cb.height));
        assert_eq!(
            format!("{:?}", ca.attributes),
            format!("{:?}", cb.attributes)
        );
        for (name, va) in &ca.channels {
            let vb = cb.channel(name).unwrap();
            assert!(
                va.iter().zip(vb).all(|(x, y)| x.to_bits() == y.to_bits()),
                "{name} differs in {}",
                a.display()
            );
        }
    }
}

/// Fails on the 40th row.
struct Failing(usize);

impl WebRowSink for Failing {
    fn on_row(&mut self, _row: &WebRowOut) -> Result<(), String> {
        self.0 += 1;
        if self.0 == 40 {
            return Err("disk full".into());
        }
        Ok(())
    }
}

#[test]
fn a_failing_sink_or_segment_write_stops_the_run_with_its_error() {
    for threading in [Threading::Inline, Threading::Split] {
        let rig = WebRig::demo().unwrap();
        let built = rig.build(rig.camera_config(), Mode::Fast).unwrap();
        let (mut cam, mut tuner, mut setup) = (built.camera, built.tuner, built.setup);
        setup.threading = threading;
        let limits = LineLimits {
            frames: Some(400),
            frame_timeout: Duration::from_secs(1),
        };
        let stop = AtomicBool::new(false);
        let err = run_line(&mut cam, &mut tuner, setup, &limits, &mut Failing(0), &stop)
            .unwrap_err()
            .to_string();
        assert!(err.contains("disk full"), "{threading:?}: {err}");
    }
    // A segment directory that does not exist: the output worker's error
    // comes back through the row path and ends the run.
    let rig = WebRig::demo().unwrap();
    let built = rig.build(rig.camera_config(), Mode::Fast).unwrap();
    let (mut cam, mut tuner, setup) = (built.camera, built.tuner, built.setup);
    let cfg = OutputConfig {
        segment_rows: 8,
        lanes: Lanes::equal(rig.file.camera.width as usize, 4),
        out_dir: Some("/nonexistent/irid-line".into()),
        topic: "irid/line".into(),
    };
    let mut out = LineOutput::new(cfg, None, Vec::new());
    let err = run_line(
        &mut cam,
        &mut tuner,
        setup,
        &LineLimits {
            frames: Some(400),
            frame_timeout: Duration::from_secs(1),
        },
        &mut out,
        &AtomicBool::new(false),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("nonexistent"), "{err}");
}
