//! `irid run --scene web`: the moving-web demo end to end through the
//! binary — the speed limit printed, JSON lines on stdout, the recipe's
//! alarm firing on the defect, EXR segments on disk.

use std::process::Command;

#[test]
fn web_demo_prints_the_limit_streams_json_and_alarms_on_the_defect() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_irid"))
        .args([
            "run",
            "--scene",
            "web",
            "--unpaced",
            "--sweeps",
            "2",
            "--out",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains(
            "32 rows in view × 50.00 bands/s / 31 bands = highest line speed 51.61 rows/s"
        ),
        "{stderr}"
    );
    let msgs: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l:?}: {e}")))
        .collect();
    let segments = msgs.iter().filter(|m| m["type"] == "segment").count();
    assert!(segments >= 5, "{segments} segments");
    let raised: Vec<_> = msgs
        .iter()
        .filter(|m| m["type"] == "alarm" && m["event"] == "raised")
        .collect();
    assert_eq!(raised.len(), 1, "{raised:?}");
    assert_eq!(raised[0]["lane"], 2);
    let files = std::fs::read_dir(dir.path().join("line")).unwrap().count();
    assert_eq!(files, segments);
}

/// Static-pipeline options the web does not have yet are refused with
/// their names, and nothing is written (not even the recording asked for
/// beside them); `--record` itself is supported (tests/line_record.rs).
#[test]
fn web_mode_refuses_what_it_cannot_do() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("web.mcap");
    let out = Command::new(env!("CARGO_BIN_EXE_irid"))
        .args([
            "run",
            "--scene",
            "web",
            "--sweeps",
            "1",
            "--png",
            "--serve",
            "127.0.0.1:0",
            "--record",
        ])
        .arg(&rec)
        .arg("--out")
        .arg(dir.path().join("out"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("--serve, --png") && stderr.contains("does not support"),
        "{stderr}"
    );
    assert!(!stderr.contains("--record"), "{stderr}");
    assert!(!rec.exists() && !dir.path().join("out").exists());
}

/// `--record` in line mode records: a file irid inspect calls a line
/// recording.
#[test]
fn web_mode_records() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("web.mcap");
    let irid = env!("CARGO_BIN_EXE_irid");
    let out = Command::new(irid)
        .args([
            "run",
            "--scene",
            "web",
            "--unpaced",
            "--sweeps",
            "1",
            "--no-maps",
            "--record",
        ])
        .arg(&rec)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("irid: recorded"), "{stderr}");
    let inv = Command::new(irid)
        .arg("inspect")
        .arg(&rec)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&inv.stdout);
    assert!(text.contains("production-line recording"), "{text}");
}
