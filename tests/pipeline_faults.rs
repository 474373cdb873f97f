//! Faults: dropped, duplicated, out-of-order and corrupted frames, a filter
//! controller that stops answering, bad calibrations. Each fault is one
//! line: a `FaultySource` around the synthetic camera.

mod pipeline_common;

use irid::device::camera::faults::{FaultConfig, FaultySource};
use irid::device::camera::CameraInfo;
use irid::pipeline::calibration::{CalExpect, Calibration, CalibrationPolicy, Calibrator};
use irid::pipeline::runner::{run, CollectSink, RunReport};
use pipeline_common::*;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

const MEAN_ERR_NM: f64 = 1.5;

fn faulty(faults: FaultConfig, triggered: bool, single: bool) -> (RunReport, CollectSink, Rig) {
    let mut r = rig(21, "ascending", triggered);
    let setup = r.setup(triggered);
    let cam = std::mem::replace(
        &mut r.cam,
        irid::device::camera::synthetic::SyntheticCamera::new(
            &r.scene,
            &r.bands,
            r.view.clone(),
            Default::default(),
        )
        .unwrap(),
    );
    let mut cam = cam;
    cam.set_realtime(!single);
    let mut src = FaultySource::new(cam, faults);
    let mut sink = CollectSink::default();
    let rep = run(
        &mut src,
        &mut r.tuner,
        setup,
        &config(3, single),
        &mut sink,
        &AtomicBool::new(false),
    )
    .unwrap();
    (rep, sink, r)
}

fn assert_accurate(sink: &CollectSink, r: &Rig, min_valid: f64) {
    assert!(!sink.maps.is_empty());
    for m in &sink.maps {
        let (mean, _, valid) = thickness_error(m, &r.truth);
        assert!(valid >= min_valid, "valid {valid}");
        assert!(
            mean < MEAN_ERR_NM,
            "a band shifted? mean thickness error {mean} nm"
        );
    }
}

#[test]
fn stepped_dropped_frames_are_retaken() {
    let (rep, sink, r) = faulty(FaultConfig::drops(0.2, 1), false, true);
    assert!(rep.frames_dropped > 0);
    assert_eq!(rep.sweeps_completed, 3);
    assert!(sink.summaries.iter().all(|s| s.missing_bands == 0));
    assert_accurate(&sink, &r, 0.95);
}

#[test]
fn stepped_duplicates_are_discarded() {
    let (rep, sink, r) = faulty(FaultConfig::duplicates(0.3, 2), false, true);
    assert!(rep.frames_dropped > 0);
    assert_accurate(&sink, &r, 0.95);
}

#[test]
fn stepped_out_of_order_frames_never_shift_bands() {
    let (rep, sink, r) = faulty(FaultConfig::reorders(0.3, 3), false, false);
    assert!(rep.frames_dropped > 0);
    assert_accurate(&sink, &r, 0.95);
}

#[test]
fn corrupted_frames_are_refused_not_panicked_on() {
    let (rep, sink, r) = faulty(FaultConfig::corrupts(0.2, 4), false, true);
    assert!(rep.frames_dropped > 0);
    assert_accurate(&sink, &r, 0.95);
}

#[test]
fn triggered_gaps_become_missing_bands_and_the_solver_copes() {
    // The film index is estimated on a sweep with complete spectra (the
    // solver's rule), then reused: the first sweep passes clean.
    let faults = FaultConfig {
        after: 40,
        ..FaultConfig::drops(0.05, 5)
    };
    let (rep, sink, r) = faulty(faults, true, true);
    assert!(rep.frames_dropped > 0);
    let missing: usize = sink.summaries.iter().map(|s| s.missing_bands).sum();
    assert!(missing > 0, "{:?}", sink.summaries);
    // Missing bands are NaN planes, never another band's frame.
    assert_accurate(&sink, &r, 0.8);
}

#[test]
fn triggered_duplicates_and_reorders_never_shift_bands() {
    let (_, sink, r) = faulty(
        FaultConfig {
            duplicate: 0.1,
            reorder: 0.1,
            seed: 6,
            ..Default::default()
        },
        true,
        false,
    );
    assert_accurate(&sink, &r, 0.8);
}

#[test]
fn a_controller_that_stops_answering_is_a_clear_error_without_a_hang() {
    for single in [true, false] {
        let mut r = rig(8, "ascending", false);
        r.tuner.stop_answering_after(40);
        let t0 = Instant::now();
        let mut sink = CollectSink::default();
        let e = r
            .go(
                false,
                &config(5, single),
                &mut sink,
                &AtomicBool::new(false),
            )
            .unwrap_err();
        assert!(e.to_string().contains("did not answer"), "{e}");
        assert!(t0.elapsed() < Duration::from_secs(30));
        // The sweep completed before the controller fell silent was delivered.
        assert_eq!(sink.maps.len(), 1);
    }
}

#[test]
fn a_mismatched_or_stale_calibration_is_refused_with_a_message() {
    let r = rig(9, "ascending", false);
    let info: CameraInfo = irid::device::camera::FrameSource::info(&r.cam);
    let nm: Vec<f64> = r.bands.iter().map(|b| b.center_nm).collect();
    let expect = |info: CameraInfo, nm: Vec<f64>, now: u64| CalExpect {
        camera: info,
        bands_nm: nm,
        now_unix_s: now,
        max_age_s: 24 * 3600,
    };
    let now = r.cal.meta.created_unix_s + 10;
    r.cal
        .check("cal", &expect(info.clone(), nm.clone(), now))
        .unwrap();
    let mut other = info.clone();
    other.width += 1;
    let e = r
        .cal
        .check("cal", &expect(other, nm.clone(), now))
        .unwrap_err()
        .to_string();
    assert!(e.contains("141×14") && e.contains("irid calibrate"), "{e}");
    let e = r
        .cal
        .check("cal", &expect(info.clone(), nm[1..].to_vec(), now))
        .unwrap_err()
        .to_string();
    assert!(e.contains("bands"), "{e}");
    let mut slow = info.clone();
    slow.exposure_us *= 2;
    assert!(r
        .cal
        .check("cal", &expect(slow, nm.clone(), now))
        .unwrap_err()
        .to_string()
        .contains("exposure"));
    let e = r
        .cal
        .check("cal", &expect(info, nm, now + 48 * 3600))
        .unwrap_err()
        .to_string();
    assert!(e.contains("old"), "{e}");
    // A damaged file.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("c.ircal");
    r.cal.save(&p).unwrap();
    let mut bytes = std::fs::read(&p).unwrap();
    bytes.truncate(bytes.len() - 7);
    std::fs::write(&p, &bytes).unwrap();
    let e = Calibration::load(&p).unwrap_err().to_string();
    assert!(e.contains("c.ircal") && e.contains("body"), "{e}");
}

#[test]
fn a_calibration_with_dark_brighter_than_white_flags_pixels_and_never_panics() {
    let mut r = rig(10, "ascending", false);
    // Dark and white swapped: every pixel is flagged, every estimate invalid.
    let nb = r.bands.len();
    let cal = Calibration::from_references(
        r.cal.meta.clone(),
        &acc(&r.cal.white, nb),
        &acc(&r.cal.dark, nb),
        &CalibrationPolicy::for_format(r.cal.meta.format),
    );
    assert!(cal.flags.iter().all(|&f| f != 0));
    let mut setup = r.setup(false);
    setup.calibrator = Calibrator::new(&cal);
    let mut sink = CollectSink::default();
    run(
        &mut r.cam,
        &mut r.tuner,
        setup,
        &config(1, true),
        &mut sink,
        &AtomicBool::new(false),
    )
    .unwrap();
    assert_eq!(sink.maps[0].valid_count(), 0);
    assert!(sink.maps[0].thickness_nm.iter().all(|v| v.is_nan()));
}

/// An accumulator holding `planes` as one frame each.
fn acc(planes: &[f32], bands: usize) -> irid::pipeline::calibration::Accumulator {
    use irid::device::camera::{Frame, PixelFormat};
    let n = planes.len() / bands;
    let mut a = irid::pipeline::calibration::Accumulator::new(n, bands);
    let mut f = Frame::with_size(n as u32, 1, PixelFormat::Y16);
    for b in 0..bands {
        for i in 0..n {
            f.data[i] = planes[b * n + i].round() as u16;
        }
        a.add(b, &f).unwrap();
    }
    a
}
