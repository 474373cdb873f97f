//! The filter controller's serial replies.
#![no_main]
use irid::device::filter::reply;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = reply::fields(data, b'W');
    let _ = reply::value(data, b'T');
    let _ = reply::wavelength(data);
    let _ = reply::version(data);
    let _ = reply::busy(data);
    let _ = reply::status_byte(data);
});
