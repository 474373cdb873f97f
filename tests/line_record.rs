//! Recording and replaying the production line (`irid run --scene web
//! --record`, `irid record --scene web`, `irid replay`), through the
//! binary: the replay emits the live run's messages and strips exactly,
//! re-judges the same frames with another mode or recipe, survives a
//! kill -9, and the Python `mcap` package reads the recording.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

mod cli_common;

use cli_common::{ok, s};

const IRID: &str = env!("CARGO_BIN_EXE_irid");

/// `irid`, which must not panic whatever it returns.
fn irid(args: &[&str]) -> Output {
    let out = cli_common::irid(args);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "irid {args:?} panicked: {err}");
    out
}

fn messages(stdout: &[u8]) -> Vec<serde_json::Value> {
    String::from_utf8_lossy(stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l:?}: {e}")))
        .collect()
}

/// A message without what legitimately differs between two runs: the
/// segment file's folder (its name stays).
fn comparable(m: &serde_json::Value) -> serde_json::Value {
    let mut m = m.clone();
    if let Some(f) = m.get("file").and_then(|f| f.as_str()) {
        let name = Path::new(f)
            .file_name()
            .unwrap()
            .to_str()
            .unwrap()
            .to_owned();
        m["file"] = serde_json::json!(name);
    }
    m
}

fn segments(msgs: &[serde_json::Value]) -> Vec<&serde_json::Value> {
    msgs.iter().filter(|m| m["type"] == "segment").collect()
}

fn strips(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("strip-") && n.ends_with(".exr"))
        })
        .collect();
    v.sort();
    v
}

fn inspect(rec: &Path) -> serde_json::Value {
    let out = ok(&["inspect", "--json", s(rec)]);
    serde_json::from_slice(&out.stdout).expect("inspect --json is JSON")
}

/// Record one `--sweeps` unit (400 frames) of the web demo, as fast as it
/// goes: returns the live run's stdout messages; strips in `dir/live/line`.
fn record_live(dir: &Path) -> (PathBuf, Vec<serde_json::Value>) {
    let rec = dir.join("web.mcap");
    let out = ok(&[
        "run",
        "--scene",
        "web",
        "--unpaced",
        "--sweeps",
        "1",
        "--out",
        s(&dir.join("live")),
        "--record",
        s(&rec),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("MB/s") && err.contains("ratio"), "{err}");
    (rec, messages(&out.stdout))
}

/// The strips in `a` and `b` hold the same channels, bit for bit, and the
/// same attributes (the EXR writer orders custom attributes as it likes,
/// so the files are compared channel by channel, not byte by byte).
fn assert_same_strips(a: &Path, b: &Path) {
    let (fa, fb) = (strips(a), strips(b));
    assert!(!fa.is_empty());
    let names = |v: &[PathBuf]| -> Vec<String> {
        v.iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect()
    };
    assert_eq!(names(&fa), names(&fb));
    for (x, y) in fa.iter().zip(&fb) {
        let (mx, my) = (
            irid::io::exr_maps::read_channels(x).unwrap(),
            irid::io::exr_maps::read_channels(y).unwrap(),
        );
        assert_eq!((mx.width, mx.height), (my.width, my.height));
        assert_eq!(mx.channels.len(), my.channels.len());
        for ((nx, vx), (ny, vy)) in mx.channels.iter().zip(&my.channels) {
            assert_eq!(nx, ny);
            assert!(
                vx.iter()
                    .map(|v| v.to_bits())
                    .eq(vy.iter().map(|v| v.to_bits())),
                "{}: channel {nx} differs",
                y.display()
            );
        }
        let mut ax = mx.attributes.clone();
        let mut ay = my.attributes.clone();
        ax.sort();
        ay.sort();
        assert_eq!(ax, ay, "{}", y.display());
    }
}

#[test]
fn a_recorded_line_replays_to_identical_messages_and_strips() {
    let dir = tempfile::tempdir().unwrap();
    let (rec, live) = record_live(dir.path());
    assert!(segments(&live).len() >= 2, "{live:?}");
    let inv = inspect(&rec);
    assert_eq!(inv["channels"]["/irid/line"], 1, "{inv}");
    assert_eq!(inv["frames"], 400);
    assert_eq!(inv["recorder_dropped"], 0);
    assert_eq!(inv["closed"], true);
    let line = &inv["line"];
    assert_eq!(line["rows_in_view"], 32);
    assert_eq!(
        line["unregistered_frames"], 0,
        "every frame has its encoder count"
    );
    // The web moved ≈ 46.45 rows/s × 4 s: the frames saw about 186 + 32 rows.
    let seen = line["web_rows"].as_u64().unwrap();
    assert!((200..=240).contains(&seen), "{line}");
    let text = String::from_utf8_lossy(&ok(&["inspect", s(&rec)]).stdout).into_owned();
    assert!(text.contains("production-line recording"), "{text}");

    // Default threads, then one thread (traced and profiled): the same as
    // live both times.
    let trace = dir.path().join("trace.json");
    let traced = ["--single-thread", "--trace", s(&trace), "--profile"];
    for (i, extra) in [&[][..], &traced[..]].iter().enumerate() {
        let out_dir = dir.path().join(format!("replay{i}"));
        let mut args = vec!["replay", s(&rec), "--out", s(&out_dir)];
        args.extend_from_slice(extra);
        let out = ok(&args);
        if i == 1 {
            let err = String::from_utf8_lossy(&out.stderr);
            let frames = err.lines().find(|l| l.starts_with("line.frame"));
            let count = frames.and_then(|l| l.split_whitespace().nth(1));
            assert_eq!(count, Some("400"), "{err}");
        }
        let replayed = messages(&out.stdout);
        assert_eq!(replayed.len(), live.len(), "{replayed:?}");
        for (a, b) in live.iter().zip(&replayed) {
            assert_eq!(comparable(a), comparable(b));
        }
        assert_same_strips(&dir.path().join("live/line"), &out_dir.join("line"));
    }
    // The profile counts the line's frames; the trace holds their reads.
    let t = std::fs::read_to_string(&trace).unwrap();
    assert!(
        t.contains("\"line.read\""),
        "no line.read span in the trace"
    );
    // An existing recording is kept unless --force.
    let again = irid(&[
        "run",
        "--scene",
        "web",
        "--unpaced",
        "--sweeps",
        "1",
        "--no-maps",
        "--record",
        s(&rec),
    ]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("--force"));
    assert_eq!(inspect(&rec)["frames"], 400, "the recording was replaced");
    // The replay's strips are kept unless --force too.
    let kept = irid(&["replay", s(&rec), "--out", s(&dir.path().join("replay0"))]);
    assert!(!kept.status.success());
}

/// Truth of the demo film at pixel `x`, web row `w`.
fn truth_nm(film: &irid::device::camera::web::WebFilm, x: usize, width: usize, w: i64) -> f64 {
    film.thickness_nm(x, width, w)
}

#[test]
fn replay_with_another_mode_and_recipe_rejudges_the_same_rows() {
    let dir = tempfile::tempdir().unwrap();
    let (rec, live) = record_live(dir.path());
    // A recipe with a narrow window around the centre line (lanes 1 and 2
    // average ≈ 321 nm, ± 3 nm of drift): the edge lanes (≈ 327 nm, the
    // parabolic profile 12 nm thicker at the edges) sit above it.
    let recipe = dir.path().join("tight.toml");
    std::fs::write(
        &recipe,
        "name = \"tight\"\ntarget_nm = 321.0\nlower_nm = 316.0\nupper_nm = 326.0\nalarm_rows = 8\n",
    )
    .unwrap();
    // `accurate` (on this film with a known index, `fast` takes the same
    // path as the recorded `balanced` and gives the same maps).
    let out_dir = dir.path().join("accurate");
    let out = ok(&[
        "replay",
        s(&rec),
        "--mode",
        "accurate",
        "--recipe",
        s(&recipe),
        "--out",
        s(&out_dir),
    ]);
    let replayed = messages(&out.stdout);
    // The same rows: every segment of the live run, same first row and
    // length, every row complete.
    let (ls, rs) = (segments(&live), segments(&replayed));
    assert_eq!(ls.len(), rs.len());
    for (a, b) in ls.iter().zip(&rs) {
        assert_eq!(a["first_row"], b["first_row"]);
        assert_eq!(a["rows"], b["rows"]);
        assert_eq!(b["rows_missing_bands"], 0);
        for lane in b["lanes"].as_array().unwrap() {
            assert_eq!(
                lane["target_nm"], 321.0,
                "the recipe given, not the recorded"
            );
        }
    }
    // The live run (recorded recipe, its wide window) raised nothing; the
    // tight recipe alarms on the thick edges.
    assert!(!live.iter().any(|m| m["type"] == "alarm"));
    let raised: Vec<_> = replayed
        .iter()
        .filter(|m| m["type"] == "alarm" && m["event"] == "raised")
        .collect();
    assert!(!raised.is_empty(), "{replayed:?}");
    assert!(
        raised.iter().all(|a| a["lane"] == 0 || a["lane"] == 3),
        "{raised:?}"
    );

    // Accuracy of `accurate` against the film's truth, with the bounds of
    // tests/line_web.rs for every complete row (≥ 95 % valid pixels, mean
    // error ≤ 2 nm: σ is ~0.5 nm per pixel), and the maps are
    // `accurate`'s, not a copy of the live `balanced` ones: each strip
    // names the mode of the solver that wrote it. (Their values may agree
    // to the bit: both modes refine from the previous pixel's fit, and on
    // this film both reach the same minimum by the same steps.)
    let film = irid::line::rig::WebRig::demo().unwrap().file.film;
    let mut strips_seen = 0;
    for (x, y) in strips(&dir.path().join("live/line"))
        .iter()
        .zip(strips(&out_dir.join("line")).iter())
    {
        let (ml, mf) = (
            irid::io::exr_maps::read_channels(x).unwrap(),
            irid::io::exr_maps::read_channels(y).unwrap(),
        );
        let attr = |m: &irid::io::exr_maps::Channels, k: &str| {
            m.attributes
                .iter()
                .find(|(n, _)| n == k)
                .map(|(_, v)| v.clone())
        };
        let first: i64 = attr(&mf, "irid.web_first_row").unwrap().parse().unwrap();
        let ch = |m: &irid::io::exr_maps::Channels, n: &str| {
            m.channels.iter().find(|(c, _)| c == n).unwrap().1.clone()
        };
        let (d, valid, dl) = (
            ch(&mf, "thickness_nm"),
            ch(&mf, "valid"),
            ch(&ml, "thickness_nm"),
        );
        assert_eq!(attr(&mf, "irid.mode").as_deref(), Some("accurate"));
        assert_eq!(attr(&ml, "irid.mode").as_deref(), Some("balanced"));
        assert_eq!(d.len(), dl.len());
        strips_seen += 1;
        let w = mf.width;
        for row in 0..mf.height {
            let (mut err, mut n) = (0.0, 0usize);
            for px in 0..w {
                let i = row * w + px;
                if valid[i] > 0.5 {
                    err += (f64::from(d[i]) - truth_nm(&film, px, w, first + row as i64)).abs();
                    n += 1;
                }
            }
            assert!(
                n as f64 >= 0.95 * w as f64,
                "row {}: {n} valid",
                first + row as i64
            );
            assert!(
                err / n as f64 <= 2.0,
                "row {}: mean error {:.2} nm",
                first + row as i64,
                err / n as f64
            );
        }
    }
    assert!(strips_seen > 0, "no strips written");
    // Re-judging the recording in a mode gives what a live run in that
    // mode gives (same seed, same frames).
    let live_acc = messages(
        &ok(&[
            "run",
            "--scene",
            "web",
            "--unpaced",
            "--sweeps",
            "1",
            "--no-maps",
            "--mode",
            "accurate",
        ])
        .stdout,
    );
    let replay_acc = messages(&ok(&["replay", s(&rec), "--no-maps", "--mode", "accurate"]).stdout);
    // (The messages may equal the live `balanced` run's: on this film both
    // modes reach the same minima; the strips above say which mode wrote
    // them.)
    assert_eq!(live_acc, replay_acc);
}

#[test]
fn record_without_solving_replays_as_the_live_line() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("only.mcap");
    let flags = [
        "--scene",
        "web",
        "--unpaced",
        "--sweeps",
        "1",
        "--seed",
        "4",
    ];
    let mut args = vec!["record", s(&rec)];
    args.extend_from_slice(&flags);
    let out = ok(&args);
    assert!(String::from_utf8_lossy(&out.stderr).contains("ratio"));
    assert_eq!(inspect(&rec)["frames"], 400);
    let mut args = vec!["run", "--no-maps"];
    args.extend_from_slice(&flags);
    let live = messages(&ok(&args).stdout);
    let replayed = messages(&ok(&["replay", s(&rec), "--no-maps"]).stdout);
    assert!(!live.is_empty());
    assert_eq!(live, replayed);
}

#[test]
fn kill_9_while_recording_a_line_replays_every_intact_row() {
    use std::io::BufRead;
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("crash.mcap");
    // Paced (the demo's 5× clock), until killed.
    let mut child = Command::new(IRID)
        .args([
            "run",
            "--scene",
            "web",
            "--sweeps",
            "0",
            "--no-maps",
            "--record",
        ])
        .arg(&rec)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut lines = std::io::BufReader::new(child.stdout.take().unwrap()).lines();
    let mut live = Vec::new();
    while segments(&live).len() < 4 {
        let l = lines.next().expect("a message").unwrap();
        live.push(serde_json::from_str::<serde_json::Value>(&l).unwrap());
    }
    // SIGKILL: no chance to close the file.
    child.kill().unwrap();
    child.wait().unwrap();
    // What the live run printed before it died.
    live.extend(
        lines
            .map_while(Result::ok)
            .filter_map(|l| serde_json::from_str(&l).ok()),
    );
    let inv = inspect(&rec);
    assert_eq!(inv["closed"], false, "{inv}");
    let out = ok(&["replay", s(&rec), "--no-maps"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("not closed properly"), "{err}");
    let replayed = messages(&out.stdout);
    let rs = segments(&replayed);
    // The recorder syncs at every sweep's last band (a sweep is ~29 web
    // rows here), so of the 4 × 64 rows the live run had emitted, at most
    // the sweep in progress is missing: 3 full segments at least.
    assert!(rs.len() > 3, "{} segments replayed", rs.len());
    // Every full segment the replay emitted is the live one, exactly (the
    // last is cut where the recording ends, so only its start is shared).
    let ls = segments(&live);
    for (a, b) in ls.iter().zip(&rs[..rs.len() - 1]) {
        assert_eq!(comparable(a), comparable(b));
    }
    // Every row that left the view before the last intact frame is
    // emitted: rows from the first emitted one up to that frame's first
    // row.
    let last_first = inv["line"]["first_rows"][1].as_i64().unwrap();
    let first = rs[0]["first_row"].as_i64().unwrap();
    let rows: i64 = rs.iter().map(|m| m["rows"].as_i64().unwrap()).sum();
    assert!(rows >= last_first - first, "{rows} rows up to {last_first}");
    assert!(rs.iter().all(|m| m["rows_missing_bands"] == 0));
}

#[test]
fn an_independent_mcap_reader_reads_a_line_recording() {
    let have = Command::new("python3")
        .args(["-c", "import mcap"])
        .status()
        .is_ok_and(|s| s.success());
    if !have {
        eprintln!("SKIPPED: python3 with the `mcap` package is absent (.ci/run installs it)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (rec, _) = record_live(dir.path());
    let script = r#"
import sys, json, collections, tomllib
from mcap.reader import make_reader
counts = collections.Counter()
encoders = []
line = None
with open(sys.argv[1], "rb") as f:
    r = make_reader(f)
    for schema, channel, message in r.iter_messages():
        counts[channel.topic] += 1
        if channel.message_encoding == "json":
            v = json.loads(message.data)
            if channel.topic == "/irid/line":
                assert schema.name == "irid.LineConfig"
                line = v
        if channel.topic == "/irid/frame":
            d = message.data
            w = int.from_bytes(d[24:28], "little")
            h = int.from_bytes(d[28:32], "little")
            assert d[34] == 1, "encoder flag"
            assert len(d) == 52 + 2 * w * h
            encoders.append(int.from_bytes(d[44:52], "little", signed=True))
web = tomllib.loads(line["web_toml"])
print(json.dumps({"counts": counts, "encoders": encoders, "rows_in_view": web["camera"]["rows_in_view"],
                  "rows_per_count": line["motion"]["encoder"]["rows_per_count"]}))
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
    assert_eq!(py["rows_in_view"], 32);
    assert_eq!(py["rows_per_count"], 0.25);
    // The encoder counts, × rows per count, are the web rows irid inspect
    // registered (first and last frame).
    let enc: Vec<i64> = py["encoders"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_i64().unwrap())
        .collect();
    assert_eq!(enc.len(), 400);
    assert!(
        enc.windows(2).all(|p| p[1] >= p[0]),
        "the web moves forward"
    );
    let row = |c: i64| (c as f64 * 0.25).round() as i64;
    assert_eq!(inv["line"]["first_rows"][0], row(enc[0]));
    assert_eq!(inv["line"]["first_rows"][1], row(enc[399]));
}

/// A line whose incidence angle changes across the view: the replay
/// rebuilds the angles per sensor row from the recorded web file (the
/// original file is gone by then) and emits the live run's messages
/// exactly — which it could not with every band at the scene's angle.
#[test]
fn a_replay_models_the_recorded_angles_per_sensor_row() {
    let dir = tempfile::tempdir().unwrap();
    let demo = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes");
    let text = std::fs::read_to_string(demo.join("web.toml")).unwrap();
    let abs = |name: &str| format!("{:?}", demo.join(name).display().to_string());
    let web = text
        .replace("\"web-film.toml\"", &abs("web-film.toml"))
        .replace("\"web-recipe.toml\"", &abs("web-recipe.toml"))
        .replace(
            "exposure_ms = 5.0",
            "exposure_ms = 5.0\nangle_deg_per_row = 0.25",
        );
    assert!(web.contains("angle_deg_per_row"));
    let web_path = dir.path().join("web-angles.toml");
    std::fs::write(&web_path, web).unwrap();
    let rec = dir.path().join("web.mcap");
    let out = ok(&[
        "run",
        "--scene",
        s(&web_path),
        "--unpaced",
        "--sweeps",
        "1",
        "--no-maps",
        "--record",
        s(&rec),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("modelled at their bands' own incidence angles"),
        "{err}"
    );
    let live = messages(&out.stdout);
    assert!(segments(&live).len() >= 2, "{live:?}");
    std::fs::remove_file(&web_path).unwrap();
    let out = ok(&["replay", s(&rec), "--no-maps"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("modelled at their bands' own incidence angles"),
        "{err}"
    );
    let replayed = messages(&out.stdout);
    assert_eq!(replayed.len(), live.len());
    for (a, b) in live.iter().zip(&replayed) {
        assert_eq!(comparable(a), comparable(b));
    }
}
