//! `line.toml` (the hardware line's configuration).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let _ = toml::from_str::<irid::device::rig::LineConfig>(&text);
});
