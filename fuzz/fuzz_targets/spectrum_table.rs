//! Spectrum tables (CSV or whitespace text), then range and resampling.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    if let Ok(t) = irid::io::spectrum_table::parse_table(data, Path::new("t.csv")) {
        let (lo, hi) = t.wavelength_range();
        let _ = t.select_range(lo, hi);
        let _ = t.resample(&[400.0, 410.0, 420.0], 10.0);
    }
});
