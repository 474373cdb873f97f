//! `.ircal` calibration files.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = irid::pipeline::calibration::Calibration::from_bytes(data);
});
