//! Record and replay (MCAP), through the `irid` binary: a recorded demo run
//! replays to bit-identical maps (one thread and threaded), replays with
//! another mode, survives damage and a kill -9, is read by an independent
//! MCAP reader (the Python `mcap` package), and traces the same spans.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

const IRID: &str = env!("CARGO_BIN_EXE_irid");

/// A small, fast demo: 40×6 pixels, in-process filter, 31 bands.
const DEMO: &[&str] = &["--size", "40x6", "--in-process-filter", "--seed", "3"];

fn irid(args: &[&str]) -> Output {
    let out = Command::new(IRID).args(args).output().expect("irid runs");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "irid {args:?} panicked: {err}");
    out
}

fn ok(args: &[&str]) -> Output {
    let out = irid(args);
    assert!(
        out.status.success(),
        "irid {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 temp path")
}

/// Record a live run of `sweeps` sweeps into `dir/rec.mcap`, maps in
/// `dir/live`.
fn record(dir: &Path, sweeps: u32, extra: &[&str]) -> PathBuf {
    let rec = dir.join("rec.mcap");
    let live = dir.join("live");
    let n = sweeps.to_string();
    let mut args = vec![
        "run",
        "--sweeps",
        &n,
        "--json",
        "--out",
        s(&live),
        "--record",
        s(&rec),
    ];
    args.extend_from_slice(DEMO);
    args.extend_from_slice(extra);
    ok(&args);
    rec
}

/// The finished sweep maps in `dir` (`sweep-*.exr`, sorted); a writer's
/// temporary file left by a killed run (`.sweep-*.exr.tmp-*`) is not one.
fn sweep_files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|d| d.map(|e| e.unwrap().path()).collect())
        .unwrap_or_default();
    v.retain(|p| {
        p.file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.starts_with("sweep-") && n.ends_with(".exr"))
    });
    v.sort();
    v
}

fn json_lines(out: &Output) -> Vec<serde_json::Value> {
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}

fn inspect(rec: &Path) -> serde_json::Value {
    let out = irid(&["inspect", "--json", s(rec)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("inspect --json is JSON")
}

/// Every map of the live run `a` is in the replay `b`, bit for bit.
fn assert_identical(a: &Path, b: &Path) {
    let fa = sweep_files(a);
    assert!(!fa.is_empty(), "no maps in {}", a.display());
    for x in &fa {
        let y = &b.join(x.file_name().unwrap());
        let mx = irid::io::exr_maps::read_channels(x).unwrap();
        let my = irid::io::exr_maps::read_channels(y).unwrap();
        assert_eq!(mx.channels.len(), my.channels.len());
        for ((nx, vx), (ny, vy)) in mx.channels.iter().zip(&my.channels) {
            assert_eq!(nx, ny);
            let bx: Vec<u32> = vx.iter().map(|v| v.to_bits()).collect();
            let by: Vec<u32> = vy.iter().map(|v| v.to_bits()).collect();
            assert!(
                bx == by,
                "{}: channel {nx} differs from the live run's",
                y.display()
            );
        }
    }
}

fn round_trip(threads: &[&str]) {
    let dir = tempfile::tempdir().unwrap();
    let rec = record(dir.path(), 3, threads);
    let replay = dir.path().join("replay");
    let mut args = vec!["replay", s(&rec), "--json", "--out", s(&replay)];
    args.extend_from_slice(threads);
    let out = ok(&args);
    // A threaded live run on a busy machine may drop sweeps for
    // back-pressure (the replay, lossless, does not): every map the live
    // run made must come out of the replay, identical.
    let live = dir.path().join("live");
    assert!(json_lines(&out).len() >= sweep_files(&live).len());
    // The demo camera runs at its frame rate: a 40×6 image keeps up, so a
    // drop is back-pressure on a loaded machine, never most sweeps (an
    // unpaced camera once made every sweep after the first a drop).
    let mapped = sweep_files(&live).len();
    assert!(mapped >= 2, "the live run mapped {mapped} of 3 sweeps");
    assert_identical(&live, &replay);
}

#[test]
fn replay_is_bit_identical_single_thread() {
    round_trip(&["--single-thread"]);
}

#[test]
fn replay_is_bit_identical_threaded() {
    round_trip(&["--threads", "2"]);
}

#[test]
fn an_existing_recording_is_kept_unless_forced() {
    let dir = tempfile::tempdir().unwrap();
    let rec = record(dir.path(), 1, &["--single-thread"]);
    let before = std::fs::read(&rec).unwrap();
    for cmd in [
        vec!["run", "--sweeps", "1", "--no-maps", "--record", s(&rec)],
        vec!["record", s(&rec), "--sweeps", "1"],
    ] {
        let mut args = cmd.clone();
        args.extend_from_slice(DEMO);
        let out = irid(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains("exists") && err.contains("--force"),
            "{err}"
        );
        assert_eq!(
            std::fs::read(&rec).unwrap(),
            before,
            "{cmd:?} touched the recording"
        );
    }
    let mut args = vec!["record", s(&rec), "--sweeps", "1", "--force"];
    args.extend_from_slice(DEMO);
    ok(&args);
    assert_ne!(std::fs::read(&rec).unwrap(), before, "--force replaced it");
}

#[test]
fn replay_writes_png_previews_when_asked() {
    let dir = tempfile::tempdir().unwrap();
    let rec = record(dir.path(), 2, &["--single-thread"]);
    let replay = dir.path().join("replay");
    ok(&[
        "replay",
        s(&rec),
        "--png",
        "--single-thread",
        "--out",
        s(&replay),
    ]);
    let maps = sweep_files(&replay);
    assert!(!maps.is_empty(), "no sweep mapped");
    // A second replay into the same folder keeps the first's maps unless
    // --force.
    let first = std::fs::read(&maps[0]).unwrap();
    let again = irid(&["replay", s(&rec), "--single-thread", "--out", s(&replay)]);
    let err = String::from_utf8_lossy(&again.stderr);
    assert!(!again.status.success() && err.contains("--force"), "{err}");
    assert_eq!(std::fs::read(&maps[0]).unwrap(), first);
    ok(&[
        "replay",
        s(&rec),
        "--png",
        "--single-thread",
        "--force",
        "--out",
        s(&replay),
    ]);
    for map in &maps {
        let png = map.with_extension("png");
        let bytes = std::fs::read(&png)
            .unwrap_or_else(|e| panic!("{}: no preview beside the map: {e}", png.display()));
        let img = irid::render::canvas::decode_png(&bytes).unwrap();
        // The 40×6 map, scaled up, plus a colour bar and a title.
        assert!(
            img.width > 40 && img.height > 6,
            "{}×{}",
            img.width,
            img.height
        );
    }
}

#[test]
fn replay_with_another_mode_and_the_inventory() {
    let dir = tempfile::tempdir().unwrap();
    let rec = record(dir.path(), 2, &["--single-thread"]);
    let inv = inspect(&rec);
    assert_eq!(inv["complete_sweeps"], 2);
    assert_eq!(inv["closed"], true);
    assert_eq!(inv["damage"].as_array().unwrap().len(), 0);
    assert_eq!(inv["verdicts"]["accept"], 62, "31 bands × 2 sweeps");
    assert_eq!(inv["recorder_dropped"], 0);
    let out = ok(&["replay", s(&rec), "--json", "--no-maps", "--mode", "fast"]);
    let live = json_lines(&ok(&["replay", s(&rec), "--json", "--no-maps"]));
    let fast = json_lines(&out);
    assert_eq!(fast.len(), 2);
    for (f, b) in fast.iter().zip(&live) {
        // Same frames, another estimator: the same film to within the
        // spread of the map (the cylinder spans 420–560 nm).
        let (tf, tb) = (
            f["thickness_mean_nm"].as_f64().unwrap(),
            b["thickness_mean_nm"].as_f64().unwrap(),
        );
        assert!((tf - tb).abs() < 5.0, "fast {tf} vs balanced {tb}");
        assert!(f["valid_fraction"].as_f64().unwrap() > 0.8, "{f}");
    }
}

/// Top-level MCAP records: (opcode, offset, total length).
fn records(bytes: &[u8]) -> Vec<(u8, usize, usize)> {
    let mut v = Vec::new();
    let mut at = 8;
    while at + 9 <= bytes.len() {
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        v.push((bytes[at], at, 9 + len));
        if bytes[at] == 0x02 {
            break;
        }
        at += 9 + len;
    }
    v
}

/// Replay a damaged copy: it must replay at least every sweep `inspect`
/// finds intact (a sweep cut by a lost chunk is completed from the next
/// recorded frames of its bands), report damage (where `damaged`), and
/// never panic. Returns (sweeps mapped, sweeps intact, inventory).
fn replay_damaged(
    dir: &Path,
    name: &str,
    bytes: &[u8],
    damaged: bool,
) -> (u64, u64, serde_json::Value) {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    let inv = inspect(&p);
    let out = irid(&["replay", s(&p), "--json", "--no-maps", "--single-thread"]);
    assert!(
        out.status.success(),
        "{name}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mapped = json_lines(&out).len() as u64;
    let intact = inv["complete_sweeps"].as_u64().unwrap();
    assert!(
        mapped >= intact && mapped <= 4,
        "{name}: {mapped} mapped, {inv}"
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.contains("damage"), damaged, "{name}: {err}");
    assert_eq!(
        !inv["damage"].as_array().unwrap().is_empty(),
        damaged,
        "{name}: {inv}"
    );
    (mapped, intact, inv)
}

#[test]
fn damaged_recordings_replay_their_intact_sweeps() {
    let dir = tempfile::tempdir().unwrap();
    let rec = record(dir.path(), 4, &["--single-thread"]);
    let bytes = std::fs::read(&rec).unwrap();
    let recs = records(&bytes);
    let chunks: Vec<_> = recs.iter().filter(|r| r.0 == 0x06).copied().collect();
    assert!(
        chunks.len() >= 5,
        "a chunk per sweep at least: {}",
        chunks.len()
    );
    assert_eq!(inspect(&rec)["complete_sweeps"], 4);
    let data_end = recs.iter().find(|r| r.0 == 0x0F).expect("data end").1;

    // Missing summary: cut where the summary begins.
    let (n, intact, inv) = replay_damaged(dir.path(), "nosummary.mcap", &bytes[..data_end], false);
    assert_eq!((n, intact), (4, 4));
    assert_eq!(inv["closed"], false);

    // Garbage appended after the end.
    let mut g = bytes.clone();
    g.extend((0..5000u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8));
    let (n, intact, _) = replay_damaged(dir.path(), "garbage.mcap", &g, true);
    assert_eq!((n, intact), (4, 4));

    // The chunk holding the middle of the file.
    let mid = chunks
        .iter()
        .copied()
        .find(|c| c.1 + c.2 > bytes.len() / 2)
        .unwrap();

    // Cut in the middle of that chunk: the sweeps before it survive.
    let (n, intact, _) = replay_damaged(dir.path(), "cut.mcap", &bytes[..mid.1 + mid.2 / 2], true);
    assert_eq!(n, intact, "nothing after a cut to complete a sweep with");
    assert!((1..4).contains(&n), "{n}");

    // A flipped byte inside it: CRC (or the decompressor) refuses it; the
    // sweeps on either side replay.
    let mut c = bytes.clone();
    c[mid.1 + mid.2 / 2] ^= 0x55;
    let (n, intact, inv) = replay_damaged(dir.path(), "crc.mcap", &c, true);
    assert!(
        intact < 4 && n >= 2,
        "{n} sweeps from a file with one bad chunk: {inv}"
    );

    // Garbage in the middle: the reader skips to the next sound chunk.
    let mut m = bytes[..mid.1].to_vec();
    m.extend(std::iter::repeat_n(0xAB, 777));
    m.extend_from_slice(&bytes[mid.1..]);
    let (n, intact, _) = replay_damaged(dir.path(), "middle.mcap", &m, true);
    assert_eq!((n, intact), (4, 4), "garbage between chunks loses nothing");

    // Fuzz: cuts and flips anywhere give an answer, never a panic.
    for k in 1..40usize {
        let mut f = bytes.clone();
        let at = k * bytes.len() / 40;
        if k % 2 == 0 {
            f.truncate(at);
        } else {
            f[at] ^= 0xFF;
        }
        let p = dir.path().join("fuzz.mcap");
        std::fs::write(&p, &f).unwrap();
        irid(&["inspect", s(&p)]);
        irid(&["replay", s(&p), "--no-maps", "--single-thread", "--json"]);
    }
}

#[test]
fn kill_9_while_recording_loses_at_most_the_sweep_in_progress() {
    use std::io::BufRead;
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("crash.mcap");
    let live = dir.path().join("live");
    let mut args = vec![
        "run",
        "--sweeps",
        "0",
        "--json",
        "--single-thread",
        "--out",
        s(&live),
        "--record",
        s(&rec),
    ];
    args.extend_from_slice(DEMO);
    let mut child = Command::new(IRID)
        .args(&args)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut lines = std::io::BufReader::new(child.stdout.take().unwrap()).lines();
    // Four maps: sweeps 0–3 were captured. The recorder writes on its own
    // thread (capture never waits for the disk), so at the kill it may
    // still hold the frames of the sweep just mapped; the three before it
    // were synced at their last band.
    for _ in 0..4 {
        lines.next().expect("a sweep line").unwrap();
    }
    // SIGKILL: no chance to close the file.
    child.kill().unwrap();
    child.wait().unwrap();
    let inv = inspect(&rec);
    assert_eq!(inv["closed"], false);
    let complete = inv["complete_sweeps"].as_u64().unwrap();
    // At most the sweep in progress and, with the recorder one sweep
    // behind, the sweep before it are lost.
    assert!(complete >= 3, "{inv}");
    let replay = dir.path().join("replay");
    let out = ok(&[
        "replay",
        s(&rec),
        "--json",
        "--single-thread",
        "--out",
        s(&replay),
    ]);
    assert_eq!(json_lines(&out).len() as u64, complete);
    // The first three replay to the live maps exactly.
    let mut first = sweep_files(&live);
    first.truncate(3);
    for p in &first {
        let q = replay.join(p.file_name().unwrap());
        let (ma, mb) = (
            irid::io::exr_maps::read_channels(p).unwrap(),
            irid::io::exr_maps::read_channels(&q).unwrap(),
        );
        for ((_, x), (_, y)) in ma.channels.iter().zip(&mb.channels) {
            assert!(x.iter().zip(y).all(|(u, v)| u.to_bits() == v.to_bits()));
        }
    }
}

#[test]
fn an_independent_mcap_reader_reads_the_recording() {
    let have = Command::new("python3")
        .args(["-c", "import mcap"])
        .status()
        .is_ok_and(|s| s.success());
    if !have {
        eprintln!("SKIPPED: python3 with the `mcap` package is absent (.ci/run installs it)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let rec = record(dir.path(), 2, &["--single-thread"]);
    let script = r#"
import sys, json, collections
from mcap.reader import make_reader
counts = collections.Counter()
encodings = {}
with open(sys.argv[1], "rb") as f:
    r = make_reader(f)
    for schema, channel, message in r.iter_messages():
        counts[channel.topic] += 1
        encodings[channel.topic] = channel.message_encoding
        if channel.message_encoding == "json":
            json.loads(message.data)
        if channel.topic == "/irid/frame":
            w = int.from_bytes(message.data[24:28], "little")
            h = int.from_bytes(message.data[28:32], "little")
            assert len(message.data) == 44 + 2 * w * h
print(json.dumps({"counts": counts, "encodings": encodings}))
"#;
    let out = Command::new("python3")
        .args(["-c", script, s(&rec)])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let py: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let inv = inspect(&rec);
    assert_eq!(py["counts"], inv["channels"], "python vs irid inspect");
    assert_eq!(py["counts"]["/irid/session"], 1);
    assert_eq!(py["encodings"]["/irid/frame"], "irid.frame");
    assert!(py["counts"]["/irid/frame"].as_u64().unwrap() >= 62);
}

fn span_names(trace: &Path) -> std::collections::BTreeSet<String> {
    let text = std::fs::read_to_string(trace).unwrap();
    let v: serde_json::Value = serde_json::from_str(text.trim_end().trim_end_matches(','))
        .unwrap_or_else(|_| {
            serde_json::from_str(&format!("{}]", text.trim_end().trim_end_matches(','))).unwrap()
        });
    v.as_array()
        .unwrap()
        .iter()
        .filter_map(|e| e["name"].as_str().map(str::to_string))
        .filter(|n| n.contains('.') && !n.contains(' '))
        .collect()
}

#[test]
fn a_replay_traces_the_same_spans_as_the_live_run() {
    let dir = tempfile::tempdir().unwrap();
    let live_trace = dir.path().join("live.json");
    let rec = record(dir.path(), 2, &["--trace", s(&live_trace)]);
    let replay_trace = dir.path().join("replay.json");
    ok(&["replay", s(&rec), "--no-maps", "--trace", s(&replay_trace)]);
    let (a, b) = (span_names(&live_trace), span_names(&replay_trace));
    for want in [
        "capture.frame",
        "ingest.frame",
        "solve.sweep",
        "write.sweep",
    ] {
        assert!(a.contains(want), "live trace lacks {want}: {a:?}");
    }
    assert_eq!(a, b);
}

/// The values of map channel `name`.
fn channel(m: &irid::io::exr_maps::Channels, name: &str) -> Vec<f32> {
    m.channels
        .iter()
        .find(|(n, _)| n == name)
        .unwrap_or_else(|| panic!("no channel {name}"))
        .1
        .clone()
}

/// `irid export --sweep N --envi`: the recorded sweep's calibrated cube,
/// read by Spectral Python (an independent ENVI reader) with the session's
/// wavelengths, and carrying what the live run saw: `irid fit` on it with
/// the demo's scene gives the live sweep map's thickness within its σ.
#[test]
fn a_recorded_sweep_exports_as_an_envi_cube() {
    let dir = tempfile::tempdir().unwrap();
    let rec = record(dir.path(), 2, &[]);
    let hdr = dir.path().join("sweep0.hdr");
    ok(&["export", s(&rec), "--sweep", "0", "--envi", s(&hdr)]);
    // Never over an existing file without --force.
    let again = irid(&["export", s(&rec), "--sweep", "0", "--envi", s(&hdr)]);
    assert!(!again.status.success(), "export replaced an existing cube");
    ok(&[
        "export",
        s(&rec),
        "--sweep",
        "0",
        "--envi",
        s(&hdr),
        "--force",
    ]);
    // A sweep the recording does not hold: a clear error.
    let none = irid(&[
        "export",
        s(&rec),
        "--sweep",
        "99",
        "--envi",
        s(&dir.path().join("x.hdr")),
    ]);
    assert!(!none.status.success());
    assert!(String::from_utf8_lossy(&none.stderr).contains("sweep 99"));

    let inv = inspect(&rec);
    let bands: Vec<f64> = inv["session"]["bands_nm"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let have_spy = Command::new("python3")
        .args(["-c", "import spectral"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if have_spy {
        let script = format!(
            "import spectral, numpy as np\n\
             img = spectral.open_image('{}')\n\
             a = img.load()\n\
             print(a.shape[0], a.shape[1], a.shape[2])\n\
             print(' '.join(str(w) for w in img.bands.centers))\n\
             print(float(np.nanmin(a)), float(np.nanmax(a)), int(np.isnan(a).sum()))\n",
            s(&hdr)
        );
        let out = Command::new("python3")
            .args(["-c", &script])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "Spectral Python failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let text = String::from_utf8_lossy(&out.stdout);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(
            lines[0],
            format!("6 40 {}", bands.len()),
            "rows, columns, bands"
        );
        let centres: Vec<f64> = lines[1].split(' ').map(|v| v.parse().unwrap()).collect();
        assert_eq!(centres.len(), bands.len());
        for (a, b) in centres.iter().zip(&bands) {
            assert!((a - b).abs() < 1e-6, "wavelength {a} for band {b}");
        }
        let stats: Vec<f64> = lines[2].split(' ').map(|v| v.parse().unwrap()).collect();
        // A reflectance (the cylinder's film on its substrate), every band
        // received.
        assert!(
            stats[0] > 0.0 && stats[1] < 1.0,
            "values {} – {}",
            stats[0],
            stats[1]
        );
        assert_eq!(stats[2], 0.0, "NaN samples in a complete sweep");
    } else {
        eprintln!("SKIPPED the Spectral Python read: python3 with `spectral` is absent (.ci/run installs it)");
    }

    // The same information as the live run's sweep 0.
    let scene = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/scenes/paper-cylinder.toml"
    );
    let maps = dir.path().join("fit.exr");
    ok(&["fit", s(&hdr), "--scene", scene, "--out", s(&maps)]);
    let live = sweep_files(&dir.path().join("live"));
    let live = irid::io::exr_maps::read_channels(&live[0]).unwrap();
    let fit = irid::io::exr_maps::read_channels(&maps).unwrap();
    let (dl, sl) = (
        channel(&live, "thickness_nm"),
        channel(&live, "sigma_thickness_nm"),
    );
    let df = channel(&fit, "thickness_nm");
    let mut compared = 0;
    for ((l, s), f) in dl.iter().zip(&sl).zip(&df) {
        if l.is_finite() && f.is_finite() {
            // Each weighs the bands by its own noise model (the camera's
            // calibrated one, the cube's model-free estimate): two
            // consistent fits of the same data, apart by at most
            // √(σ_a² − σ_b²), ~0.7 σ where the weights matter most (the
            // camera's 1.23× loss unweighted); 3σ is over four of those.
            assert!(
                (l - f).abs() <= (3.0 * s).max(0.01),
                "live {l} ± {s}, exported cube {f}"
            );
            compared += 1;
        }
    }
    // `fit` judges against the noise it estimates from the cube, the live
    // run against the camera's calibrated noise: their flags differ at the
    // margin, their numbers only within their statistics.
    assert!(
        compared * 2 >= dl.len(),
        "only {compared} of {} pixels compared",
        dl.len()
    );
}

/// `irid replay CUBE.hdr --scene S`: an ENVI cube from elsewhere goes
/// through the live pipeline as one sweep, and its map agrees with the
/// cube's ground truth as a live sweep's does (σ honest, error small).
#[test]
fn an_envi_cube_replays_as_one_sweep() {
    let dir = tempfile::tempdir().unwrap();
    let cube = dir.path().join("cube.hdr");
    ok(&["synth", "--out", s(&cube)]);
    let scene = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/scenes/paper-cylinder.toml"
    );
    // A cube carries no scene and needs no calibration: both said.
    let no_scene = irid(&["replay", s(&cube), "--out", s(&dir.path().join("x"))]);
    assert!(!no_scene.status.success());
    assert!(String::from_utf8_lossy(&no_scene.stderr).contains("--scene"));
    let out = dir.path().join("rp");
    let run = ok(&[
        "replay",
        s(&cube),
        "--scene",
        scene,
        "--json",
        "--out",
        s(&out),
    ]);
    assert_eq!(json_lines(&run).len(), 1, "one sweep");
    let maps = sweep_files(&out);
    assert_eq!(maps.len(), 1);
    let got = irid::io::exr_maps::read_channels(&maps[0]).unwrap();
    let truth = irid::io::exr_maps::read_channels(&dir.path().join("cube.truth.exr")).unwrap();
    let (d, sd, dt) = (
        channel(&got, "thickness_nm"),
        channel(&got, "sigma_thickness_nm"),
        channel(&truth, "thickness_nm"),
    );
    let valid: Vec<usize> = (0..d.len()).filter(|&i| d[i].is_finite()).collect();
    assert!(
        valid.len() * 10 >= d.len() * 9,
        "{} of {} valid",
        valid.len(),
        d.len()
    );
    let mae = valid.iter().map(|&i| (d[i] - dt[i]).abs()).sum::<f32>() / valid.len() as f32;
    let covered = valid
        .iter()
        .filter(|&&i| (d[i] - dt[i]).abs() <= 2.0 * sd[i])
        .count() as f64
        / valid.len() as f64;
    println!("cube replay: MAE {mae:.3} nm, 2σ coverage {covered:.3}");
    // The paper's cylinder at its noise: sub-nm, and σ neither too small
    // nor too large (2σ coverage of a Gaussian is 0.954).
    assert!(mae < 1.5, "MAE {mae} nm");
    assert!((0.88..=0.995).contains(&covered), "2σ coverage {covered}");
}
