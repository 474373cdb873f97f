//! The VariSpec driver against the emulated firmware over a real
//! pseudo-terminal: normal operation, sequences and trigger lines, controller
//! errors, and every injected fault (the driver recovers or reports an
//! error, and never hangs past its time bound).

use std::time::{Duration, Instant};

use irid::device::filter::{FilterController, FilterError, VariSpec, VariSpecOptions};
use lctf_firmware::emu::{spawn_pty, EmuConfig, EmulatorHandle, Faults};
use lctf_firmware::{Config, TimeScale};

fn opts() -> VariSpecOptions {
    VariSpecOptions {
        reply_timeout: Duration::from_millis(150),
        ..VariSpecOptions::default()
    }
}

fn emulator(cfg: EmuConfig) -> EmulatorHandle {
    spawn_pty(cfg).expect("open a pseudo-terminal")
}

fn open(h: &EmulatorHandle) -> VariSpec {
    VariSpec::open(h.path().to_str().unwrap(), opts()).expect("open the emulated controller")
}

#[test]
fn version_and_range() {
    let h = emulator(EmuConfig::ready());
    let mut f = open(&h);
    let v = f.version().unwrap();
    assert_eq!((v.min_nm, v.max_nm, v.serial), (400.0, 720.0, 10001));
    assert_eq!(v.revision, "1.00");
    let st = f.status().unwrap();
    assert!(st.initialised && st.exercised && !st.busy);
    assert_eq!(st.error_code, 0);
    assert_eq!(st.wavelength_nm, None);
    assert_eq!(st.temperature_c, 25.0);
}

#[test]
fn tune_reports_a_real_settle_time() {
    // Real time: a visible unit needs 50 ms (+ up to 2 ms jitter) to settle.
    let h = emulator(EmuConfig::ready());
    let mut f = open(&h);
    for nm in [450.0, 600.0, 525.5] {
        let t = f.tune(nm, Duration::from_secs(2)).unwrap();
        // Lower bound is exact (the emulator cannot settle early); the upper
        // one only guards against hangs on a loaded machine.
        assert!(t >= Duration::from_millis(50), "{t:?}");
        assert!(t < Duration::from_secs(1), "{t:?}");
        assert_eq!(f.status().unwrap().wavelength_nm, Some(nm));
    }
}

#[test]
fn cold_unit_is_initialised_and_slow_when_cold() {
    let h = emulator(EmuConfig {
        unit: Config {
            temp_centi_c: 500,
            ..Config::visible()
        },
        time_scale: TimeScale::new(1000.0),
        ..EmuConfig::default()
    });
    let mut f = open(&h);
    assert!(!f.status().unwrap().initialised);
    assert!(matches!(
        f.set_wavelength(500.0),
        Err(FilterError::Controller { code: 4, .. })
    ));
    f.ensure_ready(Duration::from_secs(5)).unwrap();
    let st = f.status().unwrap();
    assert!(st.initialised && st.exercised);
    assert_eq!(st.temperature_c, 5.0);
    // At 5 °C the liquid crystal is 4x slower: 200 ms device = 0.2 ms wall
    // here, so only check that it settles.
    f.tune(500.0, Duration::from_secs(1)).unwrap();
}

#[test]
fn controller_errors_quote_the_code() {
    let h = emulator(EmuConfig::ready());
    let mut f = open(&h);
    match f.select_palette(5) {
        Err(FilterError::Controller {
            code,
            meaning,
            command,
        }) => {
            assert_eq!(
                (code, meaning, command.as_str()),
                (9, "palette undefined", "P 5")
            );
        }
        other => panic!("{other:?}"),
    }
    // The error was cleared: the next command works.
    f.set_wavelength(500.0).unwrap();
    assert!(matches!(
        f.set_wavelength(900.0),
        Err(FilterError::OutOfRange { .. })
    ));
    assert_eq!(f.status().unwrap().error_code, 0);
}

#[test]
fn sequence_runs_on_sync_and_raises_settled_events() {
    // Scale 2: a visible unit's 50 ms settle is 25 ms of wall time, long
    // enough for the "settled" level to be seen low while the filter moves.
    const SCALE: f64 = 2.0;
    let settle_wall = Duration::from_secs_f64(0.050 / SCALE);
    let mut h = emulator(EmuConfig {
        time_scale: TimeScale::new(SCALE),
        ..EmuConfig::ready()
    });
    let events = h.take_settled_events().unwrap();
    let mut f = open(&h);
    let seq = [450.0, 550.0, 650.0];
    f.define_sequence(&seq).unwrap();
    f.select_palette(0).unwrap();
    f.wait_settled(Duration::from_secs(2)).unwrap();
    let first = events.recv_timeout(Duration::from_secs(2)).unwrap();
    assert_eq!(first.wavelength_nm, 450.0);
    assert!(h.settled(), "settled after wait_settled");
    f.arm_sync(1).unwrap();
    for &nm in seq[1..].iter().chain(&seq[..1]) {
        assert!(h.settled(), "idle before the pulse");
        let pulsed = Instant::now();
        h.pulse_sync();
        // While the filter moves to the next band the level is low ("busy"):
        // watch it until the settled edge arrives.
        let mut saw_busy = false;
        let e = loop {
            saw_busy |= !h.settled();
            match events.try_recv() {
                Ok(e) => break e,
                Err(std::sync::mpsc::TryRecvError::Empty) => {
                    assert!(
                        pulsed.elapsed() < Duration::from_secs(2),
                        "no edge for {nm} nm"
                    );
                    std::thread::yield_now();
                }
                Err(e) => panic!("{e}"),
            }
        };
        assert_eq!(e.wavelength_nm, nm);
        assert!(saw_busy, "the level never went low while tuning to {nm} nm");
        // The edge cannot come before the settle time (50 ms device, the
        // lower bound is exact; jitter only adds).
        assert!(
            e.at.duration_since(pulsed) >= settle_wall,
            "{nm} nm settled after {:?}",
            e.at.duration_since(pulsed)
        );
        // The level follows the edge within the emulator's loop iteration.
        let t = Instant::now();
        while !h.settled() {
            assert!(
                t.elapsed() < Duration::from_secs(1),
                "level stuck low after the edge"
            );
            std::thread::yield_now();
        }
    }
    f.trigger().unwrap();
    f.wait_settled(Duration::from_secs(2)).unwrap();
    assert_eq!(f.status().unwrap().wavelength_nm, Some(550.0));
    let st = f.status().unwrap();
    assert!(st.palette_defined);
}

#[test]
fn reset_clears_and_resynchronises() {
    let h = emulator(EmuConfig::ready());
    let mut f = open(&h);
    let _ = f.select_palette(3);
    f.reset().unwrap();
    assert_eq!(f.status().unwrap().error_code, 0);
    f.tune(500.0, Duration::from_secs(2)).unwrap();
}

/// Run tunes against a faulty line: each call ends (Ok or Err) within its
/// bound, and the driver gets through most of the time.
fn survives(faults: Faults, min_ok: usize) {
    let h = emulator(EmuConfig {
        time_scale: TimeScale::new(10.0),
        faults,
        fault_seed: 42,
        ..EmuConfig::ready()
    });
    let path = h.path().to_str().unwrap().to_owned();
    let mut f = None;
    for _ in 0..5 {
        let t = Instant::now();
        match VariSpec::open(&path, opts()) {
            Ok(v) => {
                f = Some(v);
                break;
            }
            Err(e) => {
                assert!(t.elapsed() < Duration::from_secs(30), "open hung: {e}");
            }
        }
    }
    let mut f = f.expect("the driver opens the port within five tries");
    let bound = f.worst_case_command() + Duration::from_secs(1);
    let settle_timeout = Duration::from_millis(500);
    let mut ok = 0;
    for i in 0..10 {
        let nm = 450.0 + 20.0 * f64::from(i);
        let t = Instant::now();
        let r = f.tune(nm, settle_timeout);
        assert!(
            t.elapsed() < bound + settle_timeout + Duration::from_secs(2),
            "tune took {:?}: {r:?}",
            t.elapsed()
        );
        match r {
            Ok(_) => ok += 1,
            Err(e) => eprintln!("reported: {e}"),
        }
        let t = Instant::now();
        let _ = f.status();
        assert!(t.elapsed() < bound, "status took {:?}", t.elapsed());
    }
    assert!(ok >= min_ok, "only {ok}/10 tunes succeeded with {faults:?}");
}

#[test]
fn fault_dropped_bytes() {
    survives(
        Faults {
            drop_prob: 0.01,
            ..Faults::default()
        },
        5,
    );
}

#[test]
fn fault_garbled_bytes() {
    survives(
        Faults {
            garble_prob: 0.01,
            ..Faults::default()
        },
        5,
    );
}

#[test]
fn fault_slow_replies() {
    survives(
        Faults {
            slow_reply: Duration::from_millis(40),
            ..Faults::default()
        },
        10,
    );
}

#[test]
fn fault_spurious_errors() {
    survives(
        Faults {
            spurious_error_prob: 0.2,
            ..Faults::default()
        },
        8,
    );
}

#[test]
fn too_slow_replies_time_out_instead_of_hanging() {
    let h = emulator(EmuConfig {
        faults: Faults {
            slow_reply: Duration::from_millis(400),
            ..Faults::default()
        },
        ..EmuConfig::ready()
    });
    let t = Instant::now();
    let o = VariSpecOptions {
        reply_timeout: Duration::from_millis(100),
        retries: 1,
        ..VariSpecOptions::default()
    };
    match VariSpec::open(h.path().to_str().unwrap(), o) {
        Err(e) => assert!(matches!(e, FilterError::Timeout { .. }), "{e}"),
        Ok(_) => panic!("replies 400 ms late cannot meet a 100 ms timeout"),
    }
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
}
