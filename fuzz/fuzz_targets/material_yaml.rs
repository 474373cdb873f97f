//! refractiveindex.info YAML, evaluated across the spectrum.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    if let Ok(m) = irid::optics::material::Material::from_yaml_str("fuzz", &text) {
        for nm in [250.0, 400.0, 550.0, 1000.0, 1e5] {
            let _ = m.index_at(nm);
        }
    }
});
