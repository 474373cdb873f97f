//! The line's output: lane statistics, the recipe's alarm firing on the
//! demo's defect, EXR strip segments written atomically and read back.

use irid::estimate::Mode;
use irid::io::exr_maps::read_channels;
use irid::line::output::{Collected, LineOutput, OutputConfig, Publisher};
use irid::line::recipe::Recipe;
use irid::line::rig::WebRig;
use irid::line::run::{run_line, LineLimits};
use irid::line::stats::Lanes;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Shares what a publisher got with the test.
struct Shared(Arc<Mutex<Collected>>);

impl Publisher for Shared {
    fn publish(&mut self, topic: &str, payload: &str) {
        self.0.lock().unwrap().publish(topic, payload);
    }
}

#[test]
fn demo_recipe_alarms_on_the_defect_and_segments_round_trip() {
    let rig = WebRig::demo().unwrap();
    let recipe = Recipe::load(&rig.base.join(rig.file.recipe.as_ref().unwrap())).unwrap();
    let built = rig.build(rig.camera_config(), Mode::Balanced).unwrap();
    let (mut cam, mut tuner, setup) = (built.camera, built.tuner, built.setup);
    let dir = tempfile::tempdir().unwrap();
    let got = Arc::new(Mutex::new(Collected::default()));
    let width = rig.file.camera.width as usize;
    let cfg = OutputConfig {
        segment_rows: 64,
        lanes: Lanes::equal(width, 4),
        out_dir: Some(dir.path().to_path_buf()),
        topic: "irid/line".into(),
    };
    let mut out = LineOutput::new(cfg, Some(recipe), vec![Box::new(Shared(got.clone()))]);
    let rep = run_line(
        &mut cam,
        &mut tuner,
        setup,
        &LineLimits {
            frames: Some(900),
            frame_timeout: Duration::from_secs(1),
        },
        &mut out,
        &AtomicBool::new(false),
    )
    .unwrap();
    assert_eq!(rep.rows.missing_bands, 0, "{rep:?}");
    // The defect: rows 200..240, x in [0.5, 0.62) of the width, 38 of
    // lane 2's 80 pixels: +12 nm on its mean, out of its ±7 nm window
    // (the drift adds at most 3 nm). The alarm rises once the excursion
    // passes 10 rows and clears when the defect ends.
    let raised: Vec<_> = out
        .alarm_log
        .iter()
        .filter(|a| a.event == "raised")
        .collect();
    assert_eq!(raised.len(), 1, "{:?}", out.alarm_log);
    let a = raised[0];
    assert_eq!((a.lane, a.side), (2, "high"));
    assert_eq!(a.from_row, 200);
    assert_eq!(a.at_row, 210);
    let cleared: Vec<_> = out
        .alarm_log
        .iter()
        .filter(|a| a.event == "cleared")
        .collect();
    assert_eq!(cleared.len(), 1);
    assert_eq!(cleared[0].at_row, 240);
    // Messages: every segment, in order, and the two alarm events.
    let msgs = got.lock().unwrap();
    let segs: Vec<serde_json::Value> = msgs
        .0
        .iter()
        .filter(|(t, _)| t == "irid/line/segment")
        .map(|(_, p)| serde_json::from_str(p).unwrap())
        .collect();
    assert_eq!(segs.len() as u64, out.segments);
    assert_eq!(
        msgs.0
            .iter()
            .filter(|(t, _)| t == "irid/line/alarm")
            .count(),
        2
    );
    let mut next_row = segs[0]["first_row"].as_i64().unwrap();
    let mut rows_total = 0;
    for (k, s) in segs.iter().enumerate() {
        assert_eq!(s["segment"].as_u64().unwrap(), k as u64);
        assert_eq!(s["first_row"].as_i64().unwrap(), next_row);
        let n = s["rows"].as_i64().unwrap();
        next_row += n;
        rows_total += n as u64;
        let lanes = s["lanes"].as_array().unwrap();
        assert_eq!(lanes.len(), 4);
        for l in lanes {
            // Complete rows: lane means near the film's profile, nearly
            // every pixel valid, capability figures present.
            let m = l["mean_nm"].as_f64().unwrap();
            assert!((315.0..345.0).contains(&m), "{l}");
            assert!(l["valid_fraction"].as_f64().unwrap() > 0.97, "{l}");
            assert!(l["cpk"].as_f64().is_some(), "{l}");
        }
    }
    assert_eq!(rows_total, rep.rows_emitted);
    // Segment files: one per segment, no temporary left, the header says
    // where on the web they are, the thickness matches the messages.
    assert_eq!(out.files.len() as u64, out.segments);
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        names
            .iter()
            .all(|n| n.starts_with("strip-") && n.ends_with(".exr")),
        "{names:?}"
    );
    for (k, f) in out.files.iter().enumerate() {
        let c = read_channels(f).unwrap();
        let s = &segs[k];
        assert_eq!(
            c.attribute("irid.web_first_row").unwrap(),
            s["first_row"].to_string()
        );
        assert_eq!(c.height as i64, s["rows"].as_i64().unwrap());
        assert_eq!(c.width, width);
        let t = c.channel("thickness_nm").unwrap();
        let lane0: Vec<f64> = (0..c.height)
            .flat_map(|y| (0..width / 4).map(move |x| (x, y)))
            .map(|(x, y)| f64::from(t[y * width + x]))
            .filter(|v| v.is_finite())
            .collect();
        let mean = lane0.iter().sum::<f64>() / lane0.len() as f64;
        let want = s["lanes"][0]["mean_nm"].as_f64().unwrap();
        // f32 storage: 320 nm to ~3e-5 nm.
        assert!((mean - want).abs() < 1e-3, "{mean} vs {want}");
        assert!(c.attribute("irid.time_last_ns").is_some());
    }
}
