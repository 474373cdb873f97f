//! Recordings: what the line saw, in an MCAP file, and a recorded line to
//! replay it through the same pipeline.
//!
//! A recording is a standard MCAP file (chunked, CRC-checked, zstd or lz4
//! compressed; the `mcap` CLI, Foxglove and the Python `mcap` package read
//! it) with these channels (ids fixed, in this order, so a reader that lost
//! a channel record to damage still knows them):
//!
//! | id | topic | encoding | what |
//! |---|---|---|---|
//! | 1 | `/irid/session` | `json` | irid's version, the scene file, bands, capture order, pairing mode, camera, solver mode: one message, first |
//! | 2 | `/irid/calibration` | `irid.ircal` | the calibration in force, the `.ircal` file's bytes: one message |
//! | 3 | `/irid/frame` | `irid.frame` | every frame capture read, raw (layout: [`FRAME_HEADER_LEN`]-byte header, then samples) |
//! | 4 | `/irid/sequencer` | `json` | the sequencer's verdict on each frame, missing bands, abandoned sweeps |
//! | 5 | `/irid/filter` | `json` | each command to the filter: band, time, settled time or error |
//! | 6 | `/irid/recorder` | `json` | frames the recorder itself dropped (disk behind), and its counts at the end |
//! | 7 | `/irid/line` | `json` | a production-line recording only: the moving-web configuration (web file, recipe, registration, geometry, output): one message, between the session and the calibration |
//!
//! The `json` channels carry a JSON Schema (schema encoding `jsonschema`).
//! Log and publish times are the frames' clock (ns).
//!
//! Writing ([`writer`]) happens on the recorder's own thread, fed through
//! a bounded channel: capture never waits, and when the recorder is behind
//! it drops (and counts) frames, never events. A chunk is closed and the
//! file synced at least once per sweep, so a crash loses at most the
//! sweep in progress. Reading ([`reader`]) walks the file record by record
//! and survives damage: a bad chunk is skipped and reported, a truncated
//! tail ends the stream, garbage is skipped to the next valid chunk.
//! [`replay`] turns a recording back into a [`crate::device::camera::FrameSource`]
//! and a [`crate::pipeline::sequencer::BandTuner`]; [`cube_stream`] does the
//! same for an ENVI cube (one sweep).

pub mod cube_stream;
pub mod reader;
pub mod replay;
pub mod writer;

use crate::device::camera::{FrameMeta, PixelFormat};
use crate::pipeline::calibration::Calibration;

/// Recording errors.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// Reading or writing the file failed.
    #[error("{path}: {source}")]
    Io {
        /// The recording.
        path: String,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// The MCAP writer refused.
    #[error("{path}: MCAP: {message}")]
    Mcap {
        /// The recording.
        path: String,
        /// What it said.
        message: String,
    },
    /// The file is not a recording irid can replay.
    #[error("{path}: {message}")]
    Format {
        /// The recording.
        path: String,
        /// What is wrong.
        message: String,
    },
}

/// The channels, in id order (id = index + 1).
pub const TOPICS: [&str; 7] = [
    TOPIC_SESSION,
    TOPIC_CALIBRATION,
    TOPIC_FRAME,
    TOPIC_SEQUENCER,
    TOPIC_FILTER,
    TOPIC_RECORDER,
    TOPIC_LINE,
];
/// Session description.
pub const TOPIC_SESSION: &str = "/irid/session";
/// The calibration in force.
pub const TOPIC_CALIBRATION: &str = "/irid/calibration";
/// Raw frames.
pub const TOPIC_FRAME: &str = "/irid/frame";
/// Sequencer decisions.
pub const TOPIC_SEQUENCER: &str = "/irid/sequencer";
/// Filter controller events.
pub const TOPIC_FILTER: &str = "/irid/filter";
/// The recorder's own drops and counts.
pub const TOPIC_RECORDER: &str = "/irid/recorder";
/// The production line's configuration (line recordings only).
pub const TOPIC_LINE: &str = "/irid/line";

/// Bytes before the samples of a frame message without an encoder count.
///
/// Layout (little-endian): `seq` u64 @0, `timestamp_ns` u64 @8,
/// `exposure_us` u32 @16, `gain` f32 @20, `width` u32 @24, `height` u32 @28,
/// `format` u8 @32 (0 grey8, 1 y10, 2 y12, 3 y16), `has_trigger` u8 @33,
/// `has_encoder` u8 @34, reserved u8 @35, `trigger` u64 @36, then
/// `width × height` u16 samples row-major @44 — or, when `has_encoder` is
/// 1 (a moving web: the count the line registers the frame by), the
/// encoder count i64 @44 and the samples @52 ([`FRAME_HEADER_LEN_ENCODER`]).
/// Recordings made before the encoder was recorded have 0 @34.
pub const FRAME_HEADER_LEN: usize = 44;

/// Bytes before the samples of a frame message with an encoder count.
pub const FRAME_HEADER_LEN_ENCODER: usize = 52;

/// Where a checked frame message's samples start.
fn samples_offset(data: &[u8]) -> usize {
    if data.get(34) == Some(&1) {
        FRAME_HEADER_LEN_ENCODER
    } else {
        FRAME_HEADER_LEN
    }
}

/// What `/irid/session` says (JSON).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Session {
    /// irid's version.
    pub irid_version: String,
    /// Wall-clock start, s since the Unix epoch.
    pub started_unix_s: u64,
    /// `run` (recorded while solving) or `record` (capture only).
    pub command: String,
    /// The scene file as resolved (JSON form of the TOML).
    pub scene: serde_json::Value,
    /// Where the scene's relative paths started.
    pub scene_base: String,
    /// Band centres, nm, plane order.
    pub bands_nm: Vec<f64>,
    /// Band widths (FWHM), nm.
    pub fwhm_nm: Vec<f64>,
    /// Capture order (band indices).
    pub order: Vec<usize>,
    /// `stepped` or `triggered`.
    pub seq_mode: crate::pipeline::sequencer::SeqMode,
    /// Solver mode of the live run.
    pub mode: String,
    /// Camera identifier.
    pub camera_id: String,
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Pixel format.
    pub format: PixelFormat,
    /// Exposure, µs.
    pub exposure_us: u32,
    /// Gain.
    pub gain: f32,
    /// Filter controller description.
    pub filter: String,
    /// Sweeps requested (None: until stopped).
    pub sweeps: Option<u64>,
}

impl Session {
    /// The recorded bands, in plane order (FWHM 0 where none was recorded).
    pub fn bands(&self) -> Vec<crate::optics::band::Band> {
        self.bands_nm
            .iter()
            .zip(self.fwhm_nm.iter().chain(std::iter::repeat(&0.0)))
            .map(|(&center_nm, &fwhm_nm)| crate::optics::band::Band { center_nm, fwhm_nm })
            .collect()
    }
}

/// Encode a frame message into `out` (cleared first).
pub fn encode_frame(meta: &FrameMeta, samples: &[u16], out: &mut Vec<u8>) {
    out.clear();
    out.reserve(FRAME_HEADER_LEN_ENCODER + 2 * samples.len());
    out.extend_from_slice(&meta.seq.to_le_bytes());
    out.extend_from_slice(&meta.timestamp_ns.to_le_bytes());
    out.extend_from_slice(&meta.exposure_us.to_le_bytes());
    out.extend_from_slice(&meta.gain.to_le_bytes());
    out.extend_from_slice(&meta.width.to_le_bytes());
    out.extend_from_slice(&meta.height.to_le_bytes());
    let format = match meta.format {
        PixelFormat::Grey8 => 0u8,
        PixelFormat::Y10 => 1,
        PixelFormat::Y12 => 2,
        PixelFormat::Y16 => 3,
    };
    out.push(format);
    out.push(u8::from(meta.trigger.is_some()));
    out.push(u8::from(meta.encoder.is_some()));
    out.push(0);
    out.extend_from_slice(&meta.trigger.unwrap_or(0).to_le_bytes());
    if let Some(e) = meta.encoder {
        out.extend_from_slice(&e.to_le_bytes());
    }
    for s in samples {
        out.extend_from_slice(&s.to_le_bytes());
    }
}

/// Decode a frame message's header; checks that the samples are all there.
pub fn decode_frame_meta(data: &[u8]) -> Result<FrameMeta, String> {
    if data.len() < FRAME_HEADER_LEN {
        return Err(format!(
            "frame message of {} bytes, shorter than its header",
            data.len()
        ));
    }
    let u64_at = |o: usize| u64::from_le_bytes(data[o..o + 8].try_into().expect("8 bytes"));
    let u32_at = |o: usize| u32::from_le_bytes(data[o..o + 4].try_into().expect("4 bytes"));
    let format = match data[32] {
        0 => PixelFormat::Grey8,
        1 => PixelFormat::Y10,
        2 => PixelFormat::Y12,
        3 => PixelFormat::Y16,
        f => return Err(format!("unknown pixel format code {f}")),
    };
    let header = match data[34] {
        0 => FRAME_HEADER_LEN,
        1 if data.len() >= FRAME_HEADER_LEN_ENCODER => FRAME_HEADER_LEN_ENCODER,
        1 => return Err("frame message too short for its encoder count".into()),
        f => return Err(format!("unknown encoder flag {f}")),
    };
    let meta = FrameMeta {
        seq: u64_at(0),
        timestamp_ns: u64_at(8),
        exposure_us: u32_at(16),
        gain: f32::from_bits(u32_at(20)),
        width: u32_at(24),
        height: u32_at(28),
        format,
        trigger: (data[33] != 0).then(|| u64_at(36)),
        encoder: (header == FRAME_HEADER_LEN_ENCODER).then(|| u64_at(44) as i64),
    };
    let want = (meta.width as u64)
        .saturating_mul(meta.height as u64)
        .saturating_mul(2)
        .saturating_add(header as u64);
    if data.len() as u64 != want {
        return Err(format!(
            "frame {}: {}×{} needs {want} bytes, the message has {}",
            meta.seq,
            meta.width,
            meta.height,
            data.len()
        ));
    }
    Ok(meta)
}

/// Copy a checked frame message's samples into `out` (`decode_frame_meta`
/// first: it guarantees the length).
pub fn decode_samples(data: &[u8], out: &mut [u16]) {
    for (o, c) in out
        .iter_mut()
        .zip(data[samples_offset(data)..].chunks_exact(2))
    {
        *o = u16::from_le_bytes([c[0], c[1]]);
    }
}

/// A calibration as the bytes of its `.ircal` file (what
/// [`Calibration::from_bytes`] reads).
pub fn ircal_bytes(cal: &Calibration) -> Vec<u8> {
    let header = serde_json::to_string(&cal.meta).expect("metadata serialises");
    let mut out = Vec::with_capacity(10 + header.len() + 9 * cal.flags.len());
    out.extend_from_slice(b"IRIDCAL1 ");
    out.extend_from_slice(header.as_bytes());
    out.push(b'\n');
    for v in cal.dark.iter().chain(&cal.white) {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&cal.flags);
    out
}

/// A message on `/irid/sequencer` (JSON, tagged by `kind`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SeqEvent {
    /// The verdict on one frame: `accept` (with sweep and band), or why it
    /// was discarded: `settling`, `stale`, `abandoned`, `bad`, `done`,
    /// `held` (capture held the next sweep back while the first sweep's
    /// film index was estimated), or `pool_empty` (paired, but processing was behind and the sweep was
    /// given up).
    Frame {
        /// Frame sequence number.
        seq: u64,
        /// Verdict.
        verdict: String,
        /// Sweep (accepted frames).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sweep: Option<u64>,
        /// Band index (accepted frames).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        band: Option<usize>,
    },
    /// A band slot given up (triggered mode gap).
    Missing {
        /// Sweep.
        sweep: u64,
        /// Band index.
        band: usize,
    },
    /// A whole sweep given up (processing behind).
    Abandoned {
        /// Sweep.
        sweep: u64,
    },
}

/// A message on `/irid/filter` (JSON): one command to the filter.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TuneEvent {
    /// Wavelength commanded, nm.
    pub nm: f64,
    /// When, ns (frames' clock).
    pub now_ns: u64,
    /// Settled from, ns (None: an error).
    pub settled_ns: Option<u64>,
    /// The error (`timeout: …` or `refused: …`), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// A message on `/irid/recorder` (JSON).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum RecorderEvent {
    /// A frame the recorder had no room for (disk behind).
    Dropped {
        /// Its sequence number.
        seq: u64,
    },
    /// Final counts, written when the recording is closed.
    Closed {
        /// Frames written.
        frames_written: u64,
        /// Frames dropped by the recorder.
        frames_dropped: u64,
        /// Events dropped by the recorder (never expected).
        events_dropped: u64,
    },
}

/// JSON Schemas of the `json` channels, by topic.
pub fn json_schema(topic: &str) -> &'static str {
    match topic {
        TOPIC_SESSION => {
            r#"{"type":"object","title":"irid.Session","required":["irid_version","scene","bands_nm","order","seq_mode","width","height","format"],"properties":{"irid_version":{"type":"string"},"started_unix_s":{"type":"integer"},"command":{"type":"string"},"scene":{"type":"object"},"scene_base":{"type":"string"},"bands_nm":{"type":"array","items":{"type":"number"}},"fwhm_nm":{"type":"array","items":{"type":"number"}},"order":{"type":"array","items":{"type":"integer"}},"seq_mode":{"enum":["stepped","triggered"]},"mode":{"type":"string"},"camera_id":{"type":"string"},"width":{"type":"integer"},"height":{"type":"integer"},"format":{"enum":["grey8","y10","y12","y16"]},"exposure_us":{"type":"integer"},"gain":{"type":"number"},"filter":{"type":"string"},"sweeps":{"type":["integer","null"]}}}"#
        }
        TOPIC_SEQUENCER => {
            r#"{"type":"object","title":"irid.SequencerEvent","required":["kind"],"properties":{"kind":{"enum":["frame","missing","abandoned"]},"seq":{"type":"integer"},"verdict":{"enum":["accept","settling","stale","abandoned","bad","done","held","pool_empty"]},"sweep":{"type":"integer"},"band":{"type":"integer"}}}"#
        }
        TOPIC_LINE => {
            r#"{"type":"object","title":"irid.LineConfig","required":["web_toml","motion","geometry"],"properties":{"web_toml":{"type":"string"},"web_path":{"type":"string"},"recipe_toml":{"type":["string","null"]},"recipe_path":{"type":["string","null"]},"motion":{"type":"object"},"geometry":{"type":"object"},"nominal_speed_rows_per_s":{"type":"number"},"allow_over_speed":{"type":"boolean"},"warmup_rows":{"type":"integer"},"segment_rows":{"type":"integer"},"lanes":{"type":"integer"},"frames_per_sweep_unit":{"type":"integer"}}}"#
        }
        TOPIC_FILTER => {
            r#"{"type":"object","title":"irid.FilterEvent","required":["nm","now_ns"],"properties":{"nm":{"type":"number"},"now_ns":{"type":"integer"},"settled_ns":{"type":["integer","null"]},"error":{"type":"string"}}}"#
        }
        _ => {
            r#"{"type":"object","title":"irid.RecorderEvent","required":["kind"],"properties":{"kind":{"enum":["dropped","closed"]},"seq":{"type":"integer"},"frames_written":{"type":"integer"},"frames_dropped":{"type":"integer"},"events_dropped":{"type":"integer"}}}"#
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_round_trip_and_bad_lengths() {
        let meta = FrameMeta {
            seq: 7,
            timestamp_ns: 123_456_789,
            exposure_us: 1000,
            gain: 1.5,
            format: PixelFormat::Y12,
            width: 3,
            height: 2,
            trigger: Some(42),
            encoder: None,
        };
        let samples = [1u16, 2, 3, 4095, 0, 65535];
        let mut buf = Vec::new();
        encode_frame(&meta, &samples, &mut buf);
        assert_eq!(buf.len(), FRAME_HEADER_LEN + 12);
        assert_eq!(decode_frame_meta(&buf).unwrap(), meta);
        let mut out = [0u16; 6];
        decode_samples(&buf, &mut out);
        assert_eq!(out, samples);
        assert!(decode_frame_meta(&buf[..buf.len() - 1]).is_err());
        assert!(decode_frame_meta(&buf[..10]).is_err());
        buf[32] = 9;
        assert!(decode_frame_meta(&buf).is_err());
    }

    #[test]
    fn an_encoder_count_round_trips_and_old_headers_still_read() {
        let meta = FrameMeta {
            seq: 3,
            timestamp_ns: 99,
            exposure_us: 500,
            gain: 1.0,
            format: PixelFormat::Y16,
            width: 2,
            height: 1,
            trigger: None,
            encoder: Some(-1234567),
        };
        let mut buf = Vec::new();
        encode_frame(&meta, &[10, 20], &mut buf);
        assert_eq!(buf.len(), FRAME_HEADER_LEN_ENCODER + 4);
        assert_eq!(decode_frame_meta(&buf).unwrap(), meta);
        let mut out = [0u16; 2];
        decode_samples(&buf, &mut out);
        assert_eq!(out, [10, 20]);
        // Without the count: the 44-byte header of earlier recordings.
        let plain = FrameMeta {
            encoder: None,
            ..meta
        };
        encode_frame(&plain, &[10, 20], &mut buf);
        assert_eq!(buf.len(), FRAME_HEADER_LEN + 4);
        assert_eq!(decode_frame_meta(&buf).unwrap(), plain);
        buf[34] = 1;
        assert!(decode_frame_meta(&buf).is_err(), "flag without the count");
        buf[34] = 7;
        assert!(decode_frame_meta(&buf).is_err());
    }
}
