//! Recordings (MCAP): the damage-tolerant reader, the frame decoder and the
//! replay's session parser, on arbitrary bytes.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = std::env::temp_dir().join(format!("irid-fuzz-{}.mcap", std::process::id()));
    if std::fs::write(&path, data).is_err() {
        return;
    }
    if let Ok(mut r) = irid::device::record::reader::RecordReader::open(&path) {
        while let Some(m) = r.next_message() {
            // The decoder checks the length against the frame's size, so
            // the buffer below is bounded by the input.
            if let Ok(meta) = irid::device::record::decode_frame_meta(&m.data) {
                let mut out = vec![0u16; meta.len()];
                irid::device::record::decode_samples(&m.data, &mut out);
            }
        }
    }
    let _ = irid::device::record::replay::Recording::open(&path);
});
