//! ENVI header text: a header or an error, then its bands.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    if let Ok(h) = irid::io::envi::parse_header(&text, Path::new("x.hdr")) {
        let _ = irid::io::envi::header_bands(&h, Path::new("x.hdr"));
    }
});
