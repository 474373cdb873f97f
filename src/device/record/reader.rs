//! Reading a recording record by record, through damage.
//!
//! The file is walked linearly (the summary is never needed): each chunk
//! is read whole (bounded by [`MAX_RECORD`]), decompressed and CRC-checked
//! by the `mcap` crate, and its messages are handed out only if the whole
//! chunk is sound. What goes wrong is reported in [`RecordReader::damage`],
//! never as a panic:
//!
//! - a chunk that fails to decompress or whose CRC does not match is
//!   skipped;
//! - a record that claims more bytes than the file holds, or an unknown
//!   record, makes the reader scan forward to the next sound chunk (garbage
//!   in the middle, a cut chunk at the end);
//! - bytes after the end magic are reported as appended garbage;
//! - a file without footer (not closed: a crash) is readable up to its last
//!   complete chunk and says so.

use super::{RecordError, TOPICS};
use std::collections::{HashMap, VecDeque};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

/// Largest record the reader accepts (a chunk of a few frames is far
/// below).
pub const MAX_RECORD: u64 = 1 << 30;

const OP_HEADER: u8 = 0x01;
const OP_FOOTER: u8 = 0x02;
const OP_SCHEMA: u8 = 0x03;
const OP_CHANNEL: u8 = 0x04;
const OP_MESSAGE: u8 = 0x05;
const OP_CHUNK: u8 = 0x06;
const OP_DATA_END: u8 = 0x0F;

/// Something wrong with the file.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Damage {
    /// Byte offset where it was found.
    pub offset: u64,
    /// What.
    pub message: String,
}

/// One message.
#[derive(Clone, Debug)]
pub struct RawMsg {
    /// Its topic (one of [`TOPICS`] for irid's channels).
    pub topic: String,
    /// Log time, ns.
    pub log_time: u64,
    /// Payload.
    pub data: Vec<u8>,
}

/// A damage-tolerant linear reader (see the module header).
pub struct RecordReader {
    file: BufReader<File>,
    path: String,
    pos: u64,
    len: u64,
    channels: HashMap<u16, String>,
    pending: VecDeque<RawMsg>,
    damage: Vec<Damage>,
    done: bool,
    closed: bool,
    chunks: u64,
}

impl RecordReader {
    /// Open `path`; it must start with the MCAP magic.
    pub fn open(path: &Path) -> Result<RecordReader, RecordError> {
        let name = path.display().to_string();
        let io = |source| RecordError::Io {
            path: name.clone(),
            source,
        };
        let f = File::open(path).map_err(io)?;
        let len = f.metadata().map_err(io)?.len();
        let mut file = BufReader::with_capacity(1 << 20, f);
        let mut magic = [0u8; 8];
        if len < 8 || file.read_exact(&mut magic).is_err() || magic != *mcap::MAGIC {
            return Err(RecordError::Format {
                path: name,
                message: "not an MCAP file (no MCAP magic at the start)".into(),
            });
        }
        Ok(RecordReader {
            file,
            path: name,
            pos: 8,
            len,
            channels: HashMap::new(),
            pending: VecDeque::new(),
            damage: Vec::new(),
            done: false,
            closed: false,
            chunks: 0,
        })
    }

    /// The file's name.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// What was found wrong so far.
    pub fn damage(&self) -> &[Damage] {
        &self.damage
    }

    /// Whether the file ended with a footer and the end magic.
    pub fn closed(&self) -> bool {
        self.closed
    }

    /// Bytes read so far and the file size (progress).
    pub fn progress(&self) -> (u64, u64) {
        (self.pos, self.len)
    }

    /// Sound chunks read so far.
    pub fn chunks(&self) -> u64 {
        self.chunks
    }

    /// The next message, or None at the end of what can be read.
    pub fn next_message(&mut self) -> Option<RawMsg> {
        loop {
            if let Some(m) = self.pending.pop_front() {
                return Some(m);
            }
            if self.done {
                return None;
            }
            self.step();
        }
    }

    fn note(&mut self, offset: u64, message: String) {
        // Bounded: a hopeless file does not grow the list without end.
        if self.damage.len() < 1000 {
            self.damage.push(Damage { offset, message });
        }
    }

    fn read_at(&mut self, offset: u64, n: usize) -> std::io::Result<Vec<u8>> {
        self.file.seek(SeekFrom::Start(offset))?;
        let mut v = vec![0u8; n];
        self.file.read_exact(&mut v)?;
        Ok(v)
    }

    /// Read one top-level record at `self.pos`.
    fn step(&mut self) {
        let at = self.pos;
        let left = self.len - at;
        if left == 0 {
            // No footer: not closed (a crash), which `closed()` says; not
            // damage in itself.
            self.done = true;
            return;
        }
        let head = match self.read_at(at, 9.min(left as usize)) {
            Ok(h) if h.len() == 9 => h,
            _ => {
                self.note(at, format!("{left} stray bytes at the end: truncated"));
                self.done = true;
                return;
            }
        };
        let op = head[0];
        let rlen = u64::from_le_bytes(head[1..9].try_into().expect("8 bytes"));
        let known = matches!(op, 0x01..=0x0F) || op >= 0x80;
        if !known || rlen > left - 9 || rlen > MAX_RECORD {
            let why = if known {
                format!(
                    "record (opcode 0x{op:02x}) claims {rlen} bytes, {} left: cut or damaged",
                    left - 9
                )
            } else {
                format!("unknown record opcode 0x{op:02x}: garbage")
            };
            self.note(at, why);
            self.resync(at + 1);
            return;
        }
        let body = match self.read_at(at + 9, rlen as usize) {
            Ok(b) => b,
            Err(e) => {
                self.note(at, format!("reading: {e}"));
                self.done = true;
                return;
            }
        };
        self.pos = at + 9 + rlen;
        match op {
            OP_CHUNK => self.chunk(at, &body),
            OP_SCHEMA | OP_CHANNEL | OP_MESSAGE => match parse_checked(op, &body) {
                Ok(r) => self.take(r),
                Err(e) => self.note(at, format!("record 0x{op:02x}: {e}")),
            },
            OP_FOOTER => self.after_footer(),
            OP_HEADER | OP_DATA_END => {}
            _ => {} // indexes, statistics, attachments, metadata: not needed
        }
    }

    fn after_footer(&mut self) {
        self.done = true;
        let at = self.pos;
        let left = self.len - at;
        match self.read_at(at, 8.min(left as usize)) {
            Ok(m) if m == *mcap::MAGIC => {
                self.closed = true;
                if left > 8 {
                    self.note(
                        at + 8,
                        format!(
                            "{} bytes after the end of the file: garbage appended",
                            left - 8
                        ),
                    );
                }
            }
            _ => self.note(at, "footer not followed by the end magic".into()),
        }
    }

    fn take(&mut self, r: mcap::records::Record<'static>) {
        use mcap::records::Record;
        match r {
            Record::Channel(c) => {
                self.channels.insert(c.id, c.topic);
            }
            Record::Message { header, data } => {
                let topic = match self.channels.get(&header.channel_id) {
                    Some(t) => t.clone(),
                    // The channel record was lost: irid's ids are fixed.
                    None => match TOPICS.get(usize::from(header.channel_id).wrapping_sub(1)) {
                        Some(t) => (*t).to_string(),
                        None => format!("channel {}", header.channel_id),
                    },
                };
                self.pending.push_back(RawMsg {
                    topic,
                    log_time: header.log_time,
                    data: data.into_owned(),
                });
            }
            _ => {}
        }
    }

    /// Parse a chunk; its messages are taken only if all of it is sound.
    fn chunk(&mut self, at: u64, body: &[u8]) {
        match parse_chunk(body) {
            Ok(records) => {
                self.chunks += 1;
                for r in records {
                    self.take(r);
                }
            }
            Err(e) => self.note(at, format!("chunk skipped: {e}")),
        }
    }

    /// Scan forward from `from` for the next sound chunk and continue
    /// there; the end if there is none.
    fn resync(&mut self, from: u64) {
        const WINDOW: usize = 1 << 20;
        let mut start = from;
        while start + 9 < self.len {
            let n = (WINDOW as u64).min(self.len - start) as usize;
            let Ok(win) = self.read_at(start, n) else {
                break;
            };
            for i in 0..n {
                if win[i] != OP_CHUNK {
                    continue;
                }
                let at = start + i as u64;
                let Some(rlen) = win
                    .get(i + 1..i + 9)
                    .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
                else {
                    // Straddles the window: looked at again in the next.
                    break;
                };
                if !(36..=MAX_RECORD).contains(&rlen) || at + 9 + rlen > self.len {
                    continue;
                }
                let Ok(body) = self.read_at(at + 9, rlen as usize) else {
                    continue;
                };
                if let Ok(records) = parse_chunk(&body) {
                    self.note(
                        from - 1,
                        format!("{} bytes skipped to the next sound chunk", at - (from - 1)),
                    );
                    self.chunks += 1;
                    for r in records {
                        self.take(r);
                    }
                    self.pos = at + 9 + rlen;
                    return;
                }
            }
            if n < WINDOW {
                break;
            }
            start += (WINDOW - 8) as u64;
        }
        self.done = true;
    }
}

/// Decompress and check one chunk body, all or nothing.
fn parse_chunk(body: &[u8]) -> Result<Vec<mcap::records::Record<'static>>, String> {
    use mcap::records::Record;
    let (header, data) = match parse_checked(OP_CHUNK, body)? {
        Record::Chunk { header, data } => (header, data),
        _ => return Err("not a chunk".into()),
    };
    if !matches!(header.compression.as_str(), "" | "zstd" | "lz4") {
        return Err(format!("unknown compression {:?}", header.compression));
    }
    if header.uncompressed_size > MAX_RECORD {
        return Err(format!("implausible size {}", header.uncompressed_size));
    }
    // Decompressed through a reader capped at the claimed size, into a
    // buffer that grows with the data: a damaged size field costs nothing
    // (mcap's own chunk reader allocates the claim up front — a mutated
    // 35 kB file once asked for 1.7 GB).
    let claimed = header.uncompressed_size;
    let raw = match header.compression.as_str() {
        "zstd" => read_capped(
            zstd::stream::read::Decoder::new(&data[..]).map_err(|e| e.to_string())?,
            claimed,
        )?,
        "lz4" => read_capped(
            lz4::Decoder::new(&data[..]).map_err(|e| e.to_string())?,
            claimed,
        )?,
        _ => read_capped(&data[..], claimed)?,
    };
    if raw.len() as u64 != claimed {
        return Err(format!(
            "chunk holds {} bytes, its header says {claimed}",
            raw.len()
        ));
    }
    if header.uncompressed_crc != 0 && crc32fast::hash(&raw) != header.uncompressed_crc {
        return Err("chunk CRC mismatch".into());
    }
    let mut out = Vec::new();
    let mut at = 0usize;
    while at < raw.len() {
        let head = raw
            .get(at..at + 9)
            .ok_or_else(|| format!("record header cut at byte {at} of the chunk"))?;
        let len = u64::from_le_bytes(head[1..9].try_into().expect("8 bytes"));
        let end = usize::try_from(len)
            .ok()
            .and_then(|l| (at + 9).checked_add(l))
            .filter(|&e| e <= raw.len())
            .ok_or_else(|| format!("record at byte {at} runs past the chunk"))?;
        // A chunk holds schemas, channels and messages; anything else is
        // not needed (and not parsed).
        if matches!(head[0], OP_SCHEMA | OP_CHANNEL | OP_MESSAGE) {
            out.push(parse_checked(head[0], &raw[at + 9..end])?);
        }
        at = end;
    }
    Ok(out)
}

/// `mcap`'s parser for one record body, called only once every
/// length-prefixed field of the record is seen to fit in the body: the
/// parser reserves what a prefix claims before reading it, so a damaged
/// prefix in a few kB once asked for 1.9 GB and aborted the process.
fn parse_checked(op: u8, body: &[u8]) -> Result<mcap::records::Record<'static>, String> {
    if !prefixes_fit(op, body) {
        return Err(format!(
            "a field's length runs past the record's {} bytes",
            body.len()
        ));
    }
    mcap::read::parse_record(op, body)
        .map(|r| r.into_owned())
        .map_err(|e| e.to_string())
}

/// Whether the length-prefixed fields of a schema, channel or chunk record
/// (MCAP's layouts) each fit in what is left of `body`.
fn prefixes_fit(op: u8, body: &[u8]) -> bool {
    let mut at = 0usize;
    // Skip `n` fixed bytes.
    let fixed = |at: &mut usize, n: usize| -> bool {
        *at = at.saturating_add(n);
        *at <= body.len()
    };
    // A `u32` (or `u64`) length, then that many bytes.
    let prefixed = |at: &mut usize, width: usize| -> bool {
        let Some(raw) = body.get(*at..at.saturating_add(width)) else {
            return false;
        };
        let mut le = [0u8; 8];
        le[..width].copy_from_slice(raw);
        let n = u64::from_le_bytes(le);
        match usize::try_from(n)
            .ok()
            .and_then(|n| (*at + width).checked_add(n))
        {
            Some(end) if end <= body.len() => {
                *at = end;
                true
            }
            _ => false,
        }
    };
    match op {
        // id, name, encoding, data
        OP_SCHEMA => {
            fixed(&mut at, 2)
                && prefixed(&mut at, 4)
                && prefixed(&mut at, 4)
                && prefixed(&mut at, 4)
        }
        // id, schema id, topic, message encoding, metadata map (u32 bytes
        // of string pairs)
        OP_CHANNEL => {
            if !(fixed(&mut at, 4) && prefixed(&mut at, 4) && prefixed(&mut at, 4)) {
                return false;
            }
            let map_start = at + 4;
            if !prefixed(&mut at, 4) {
                return false;
            }
            let map_end = at;
            let mut p = map_start;
            while p < map_end {
                if !(prefixed(&mut p, 4) && prefixed(&mut p, 4)) || p > map_end {
                    return false;
                }
            }
            true
        }
        // start, end, uncompressed size, CRC, compression, records (u64)
        OP_CHUNK => fixed(&mut at, 28) && prefixed(&mut at, 4) && prefixed(&mut at, 8),
        _ => true,
    }
}

/// Everything `r` yields, up to one byte past `claimed` (so a longer
/// stream is seen as one), the buffer growing with what arrives.
fn read_capped(r: impl std::io::Read, claimed: u64) -> Result<Vec<u8>, String> {
    use std::io::Read as _;
    let mut out = Vec::new();
    r.take(claimed.saturating_add(1))
        .read_to_end(&mut out)
        .map_err(|e| format!("decompressing: {e}"))?;
    Ok(out)
}
