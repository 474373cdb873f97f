//! Seeded mutation tests of every parser irid exposes to files or devices:
//! ENVI headers and data, spectrum tables, scene, recipe and line TOML, MCAP
//! recordings, `.ircal` calibrations, refractiveindex.info YAML and the
//! filter controller's serial replies. Valid inputs are mutated (bytes
//! flipped, inserted, deleted, duplicated, truncated, numbers replaced by
//! hostile ones) by a seeded generator, so every run sees the same cases.
//!
//! Each case must give a value or an error — no panic (caught and
//! reported with the input) — finish (each parser's batch runs on a thread
//! with a deadline), and allocate at most [`ALLOC_LIMIT`] bytes at its peak
//! (counted per thread by the allocator below): a header claiming 10¹²
//! pixels, or bands that would need gigabytes of tables, must be refused
//! before allocating. `cargo fuzz` targets of the same parsers are in
//! `fuzz/`.

use irid::pipeline::calibration::{CalMeta, Calibration};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;
use std::time::Duration;

/// Peak heap a single parse may take. The inputs are at most a few kB;
/// the largest legitimate structure they describe here (a 140 × 14 × 31
/// cube, a 512-band table) is well under a megabyte, so 64 MB is out of
/// proportion by design and far below what the bugs this guards against
/// asked for (12 GB).
const ALLOC_LIMIT: usize = 64 << 20;

/// Cases per parser (each is a handful of microseconds to a millisecond).
const CASES: u64 = 3000;

/// How long one parser's batch may take before it counts as a hang.
const DEADLINE: Duration = Duration::from_secs(120);

struct Counting;

thread_local! {
    static CURRENT: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

fn note_alloc(n: usize) {
    let _ = CURRENT.try_with(|c| {
        let v = c.get().saturating_add(n);
        c.set(v);
        let _ = PEAK.try_with(|p| p.set(p.get().max(v)));
    });
}

fn note_free(n: usize) {
    let _ = CURRENT.try_with(|c| c.set(c.get().saturating_sub(n)));
}

// SAFETY: forwards to the system allocator unchanged; the counters are
// const-initialised thread-locals without destructors (no allocation).
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        note_alloc(l.size());
        System.alloc(l)
    }
    unsafe fn alloc_zeroed(&self, l: Layout) -> *mut u8 {
        note_alloc(l.size());
        System.alloc_zeroed(l)
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        note_free(l.size());
        System.dealloc(p, l)
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        note_free(l.size());
        note_alloc(new);
        System.realloc(p, l, new)
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Heap in use on this thread now.
fn current() -> usize {
    CURRENT.with(Cell::get)
}

/// Run `f` on the heap counters of this thread: its peak above the start.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = current();
    PEAK.with(|p| p.set(base));
    let out = f();
    (out, PEAK.with(Cell::get) - base)
}

/// Numbers a careless parser trips on.
const HOSTILE: &[&str] = &[
    "0",
    "-1",
    "1e300",
    "-1e300",
    "1e-300",
    "NaN",
    "nan",
    "inf",
    "-inf",
    "4294967296",
    "18446744073709551616",
    "1000000000000",
    "99999999999999999999999",
    "0.001",
    "-0",
    "1e6",
    "",
    " ",
    "{",
    "}",
    "[",
    "]",
    "=",
    ",",
    "\"",
    "\n",
    "\r",
    "\0",
    "é",
    "λ",
    "0x10",
    "1_0",
];

/// One mutant of `seed`: 1–4 mutations.
fn mutate(seed: &[u8], rng: &mut ChaCha8Rng) -> Vec<u8> {
    let mut v = seed.to_vec();
    for _ in 0..rng.random_range(1..=4) {
        let len = v.len();
        let at = if len == 0 {
            0
        } else {
            rng.random_range(0..=len)
        };
        match rng.random_range(0..7) {
            // Flip a bit.
            0 if len > 0 => {
                let i = rng.random_range(0..len);
                v[i] ^= 1 << rng.random_range(0..8);
            }
            // Random byte in.
            1 => v.insert(at, rng.random()),
            // Delete a span.
            2 if len > 0 => {
                let n = rng.random_range(1..=len.min(16));
                let i = rng.random_range(0..=len - n);
                v.drain(i..i + n);
            }
            // Duplicate a span.
            3 if len > 0 => {
                let n = rng.random_range(1..=len.min(64));
                let i = rng.random_range(0..=len - n);
                let span = v[i..i + n].to_vec();
                v.splice(at..at, span);
            }
            // Truncate.
            4 => v.truncate(at),
            // Replace a number (a run of digits) by a hostile one.
            _ => {
                let digits: Vec<usize> = (0..len).filter(|&i| v[i].is_ascii_digit()).collect();
                let word = HOSTILE[rng.random_range(0..HOSTILE.len())].as_bytes();
                if digits.is_empty() {
                    v.splice(at..at, word.iter().copied());
                } else {
                    let s = digits[rng.random_range(0..digits.len())];
                    let mut e = s;
                    while e < len && (v[e].is_ascii_digit() || v[e] == b'.') {
                        e += 1;
                    }
                    v.splice(s..e, word.iter().copied());
                }
            }
        }
    }
    v
}

/// Run `check` on `CASES` mutants of each seed on a thread with a deadline;
/// a panic, a hang or a peak allocation over the limit fails, naming the
/// parser, the seed and the input.
fn fuzz(name: &'static str, seeds: Vec<Vec<u8>>, check: fn(&[u8])) {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name(format!("fuzz-{name}"))
        .spawn(move || {
            let mut rng = ChaCha8Rng::seed_from_u64(0x1d1d ^ name.len() as u64);
            let mut worst = 0usize;
            for case in 0..CASES {
                let seed = &seeds[(case as usize) % seeds.len()];
                // Every seed once as it is, then mutants.
                let input = if case < seeds.len() as u64 {
                    seed.clone()
                } else {
                    mutate(seed, &mut rng)
                };
                let (r, peak) = peak_of(|| {
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| check(&input)))
                });
                let shown = String::from_utf8_lossy(&input[..input.len().min(400)]).into_owned();
                // IRID_FUZZ_DUMP=DIR keeps the whole failing input.
                if r.is_err() || peak > ALLOC_LIMIT {
                    if let Some(dir) = std::env::var_os("IRID_FUZZ_DUMP") {
                        let file = Path::new(&dir).join(format!("{name}-{case}"));
                        let _ = std::fs::write(file, &input);
                    }
                }
                if r.is_err() {
                    let _ = tx.send(Err(format!("{name}: case {case} panicked on {shown:?}")));
                    return;
                }
                if peak > ALLOC_LIMIT {
                    let _ = tx.send(Err(format!(
                        "{name}: case {case} allocated {peak} bytes for {} input bytes: {shown:?}",
                        input.len()
                    )));
                    return;
                }
                worst = worst.max(peak);
            }
            let _ = tx.send(Ok(worst));
        })
        .unwrap();
    match rx.recv_timeout(DEADLINE) {
        Ok(Ok(worst)) => eprintln!("{name}: {CASES} cases, peak heap {worst} bytes"),
        Ok(Err(e)) => panic!("{e}"),
        Err(_) => panic!("{name}: no answer within {DEADLINE:?} (a hang?)"),
    }
}

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn files(dir: &str, ext: &str) -> Vec<Vec<u8>> {
    let mut v: Vec<_> = std::fs::read_dir(root().join(dir))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == ext))
        .collect();
    v.sort();
    v.iter().map(|p| std::fs::read(p).unwrap()).collect()
}

#[test]
fn envi_headers() {
    fuzz(
        "envi header",
        files("tests/fixtures/envi/valid", "hdr"),
        |b| {
            let text = String::from_utf8_lossy(b);
            if let Ok(h) = irid::io::envi::parse_header(&text, Path::new("x.hdr")) {
                // A header that parses describes a whole image, and its
                // bands (where it names them) are one per band.
                assert!(h.samples > 0 && h.lines > 0 && h.bands > 0);
                if let Ok(b) = irid::io::envi::header_bands(&h, Path::new("x.hdr")) {
                    assert_eq!(b.len(), h.bands);
                }
            }
        },
    );
}

#[test]
fn envi_header_and_data_from_disk() {
    // The header mutated, with a data file of 0–4 kB beside it: the reader
    // must check sizes against the file before allocating.
    fuzz(
        "envi cube",
        files("tests/fixtures/envi/valid", "hdr"),
        |b| {
            let dir = tempfile::tempdir().unwrap();
            let hdr = dir.path().join("c.hdr");
            std::fs::write(&hdr, b).unwrap();
            let n = b.iter().map(|&x| x as usize).sum::<usize>() % 4096;
            std::fs::write(dir.path().join("c.img"), vec![0x41u8; n]).unwrap();
            if let Ok(img) = irid::io::envi::read_image(&hdr) {
                // Every value read came from the file (at least a byte
                // each), and the cube holds them all.
                let h = &img.header;
                let values = h.samples * h.lines * h.bands;
                assert_eq!(img.data.len(), values);
                assert!(values <= n, "{values} values from {n} bytes");
                if let Ok(cube) = irid::io::envi::image_to_cube(img) {
                    assert_eq!(cube.data.len(), values);
                }
            }
        },
    );
}

const TABLE: &str = "wavelength_nm,a,b\n400,0.05,0.06\n410,0.051,0.061\n420,0.052,0.062\n\
                     430,0.053,0.063\n440,0.054,0.064\n";
const TEXT_TABLE: &str = "# scan\n400 0.05\n401 0.051\n402 0.049\n403 0.05\n404 0.052\n";

#[test]
fn spectrum_tables() {
    let seeds = vec![TABLE.into(), TEXT_TABLE.into()];
    fuzz("spectrum table", seeds, |b| {
        if let Ok(t) = irid::io::spectrum_table::parse_table(b, Path::new("t.csv")) {
            // A table that parses is one: a name per spectrum, its rows in
            // increasing finite wavelength, every row kept by its own range.
            let (lo, hi) = t.wavelength_range();
            assert!(t.rows() > 0 && lo.is_finite() && lo <= hi, "{lo}–{hi} nm");
            assert_eq!(t.names.len(), t.cube.width);
            let bands = &t.cube.bands;
            assert!(bands.windows(2).all(|p| p[0].center_nm < p[1].center_nm));
            assert_eq!(t.select_range(lo, hi).rows(), t.rows());
            if let Ok(r) = t.resample(&[400.0, 410.0, 420.0], 10.0) {
                assert_eq!((r.rows(), r.cube.width), (3, t.cube.width));
            }
        }
    });
}

#[test]
fn scene_toml() {
    fuzz("scene toml", files("data/scenes", "toml"), |b| {
        let text = String::from_utf8_lossy(b);
        if let Ok(scene) = irid::scene::Scene::from_toml(&text, "t", &root().join("data/scenes")) {
            let _ = irid::synth::scene_bands(&scene);
        }
    });
}

#[test]
fn recipe_toml() {
    let seeds = vec![std::fs::read(root().join("data/scenes/web-recipe.toml")).unwrap()];
    fuzz("recipe toml", seeds, |b| {
        let text = String::from_utf8_lossy(b);
        if let Ok(r) = irid::line::recipe::Recipe::from_toml(&text, "t") {
            for lane in 0..4 {
                let _ = r.lane(lane);
            }
            let _ = irid::line::recipe::Alarms::new(r, 4);
        }
    });
}

#[test]
fn recordings() {
    // Real recordings (one sweep of an 8×4 demo image, lz4 and zstd
    // chunks) as seeds: the mutants break chunks, CRCs, lengths and
    // records; the damage-tolerant reader, the frame decoder and the
    // session parser must report, never panic or allocate out of
    // proportion (a size field once made the chunk reader ask for 1.7 GB).
    let seeds = files("tests/fixtures/recording", "mcap");
    assert_eq!(seeds.len(), 2);
    fuzz("recording", seeds, |b| {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.mcap");
        std::fs::write(&path, b).unwrap();
        if let Ok(mut r) = irid::device::record::reader::RecordReader::open(&path) {
            while let Some(m) = r.next_message() {
                if let Ok(meta) = irid::device::record::decode_frame_meta(&m.data) {
                    let mut px = vec![0u16; meta.len()];
                    irid::device::record::decode_samples(&m.data, &mut px);
                }
            }
        }
        let _ = irid::device::record::replay::Recording::open(&path);
    });
}

#[test]
fn line_toml() {
    let seeds = vec![std::fs::read(root().join("tools/line.example.toml")).unwrap()];
    fuzz("line toml", seeds, |b| {
        let text = String::from_utf8_lossy(b);
        let _ = toml::from_str::<irid::device::rig::LineConfig>(&text);
    });
}

fn ircal() -> Vec<u8> {
    let meta = CalMeta {
        version: 1,
        width: 3,
        height: 2,
        bands_nm: vec![400.0, 410.0],
        exposure_us: 1000,
        gain: 1.0,
        format: irid::device::camera::PixelFormat::Y16,
        camera_id: "synthetic".into(),
        created_unix_s: 1_700_000_000,
        white_reflectance: 0.99,
        frames: 4,
        noise: None,
    };
    let mut b = b"IRIDCAL1 ".to_vec();
    b.extend(serde_json::to_vec(&meta).unwrap());
    b.push(b'\n');
    for i in 0..12 {
        b.extend((100.0f32 + i as f32).to_le_bytes());
    }
    for i in 0..12 {
        b.extend((9000.0f32 + i as f32).to_le_bytes());
    }
    b.extend([0u8; 12]);
    assert!(Calibration::from_bytes(&b).is_ok(), "the seed is valid");
    b
}

#[test]
fn ircal_files() {
    fuzz("ircal", vec![ircal()], |b| {
        let _ = Calibration::from_bytes(b);
    });
}

#[test]
fn refractiveindex_yaml() {
    fuzz(
        "material yaml",
        files("data/refractive-index", "yml"),
        |b| {
            let text = String::from_utf8_lossy(b);
            if let Ok(m) = irid::optics::material::Material::from_yaml_str("m", &text) {
                for nm in [250.0, 400.0, 550.0, 1000.0, 1e5] {
                    if let Ok(i) = m.index_at(nm) {
                        assert!(i.re.is_finite() && i.re > 0.0 && i.im.is_finite() && i.im >= 0.0);
                    }
                }
            }
        },
    );
}

#[test]
fn controller_replies() {
    use irid::device::filter::reply;
    let seeds: Vec<Vec<u8>> = [
        "W 550.00",
        "550.00",
        "V   1.00    400    720  10001",
        "<",
        ">",
        "!>",
        "T  23.5",
        "E   0",
    ]
    .iter()
    .map(|s| s.as_bytes().to_vec())
    .collect();
    fuzz("controller reply", seeds, |b| {
        let _ = reply::fields(b, b'W');
        let _ = reply::value(b, b'T');
        let _ = reply::wavelength(b);
        let _ = reply::version(b);
        let _ = reply::busy(b);
        let _ = reply::status_byte(b);
    });
}
