//! A production-line recipe (TOML): per-lane targets, limits and alarms.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    if let Ok(r) = irid::line::recipe::Recipe::from_toml(&text, "fuzz") {
        for lane in 0..4 {
            let _ = r.lane(lane);
        }
        let _ = irid::line::recipe::Alarms::new(r, 4);
    }
});
