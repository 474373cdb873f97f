//! Scene TOML, resolved, and its bands.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    if let Ok(scene) = irid::scene::Scene::from_toml(&text, "fuzz", Path::new(".")) {
        let _ = irid::synth::scene_bands(&scene);
    }
});
