//! `irid lctf` end to end against the in-process emulated controller.

use clap::Parser;
use irid::cli::lctf::{parse_bands, run, LctfArgs};

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    lctf: LctfArgs,
}

fn irid_lctf(args: &[&str]) -> anyhow::Result<()> {
    let cli = Cli::try_parse_from(std::iter::once("lctf").chain(args.iter().copied()))?;
    run(&cli.lctf)
}

/// Run the `irid` binary; its stdout, or a panic with its stderr.
fn irid_out(args: &[&str]) -> String {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_irid"))
        .args(args)
        .output()
        .expect("run irid");
    assert!(
        out.status.success(),
        "irid {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("UTF-8 output")
}

/// The text after `key:` on the line that starts with it.
fn field<'a>(text: &'a str, key: &str) -> &'a str {
    text.lines()
        .find_map(|l| l.strip_prefix(key).and_then(|r| r.strip_prefix(':')))
        .unwrap_or_else(|| panic!("no `{key}:` line in\n{text}"))
        .trim()
}

/// Settle times in ms: device time (50 ms visible, 150 ms near-IR, plus up
/// to 2 ms of jitter) over the time scale is an exact lower bound on the
/// wall time the driver measures; the upper bound only guards against a
/// hang or a unit of the wrong kind on a loaded machine.
fn check_settle(ms: f64, device_ms: f64, scale: f64) {
    assert!(
        ms >= device_ms / scale,
        "{ms} ms < {device_ms} ms / {scale}"
    );
    assert!(ms < device_ms / scale + 500.0, "{ms} ms");
}

#[test]
fn info_status_and_step_work_without_hardware() {
    // Info: the emulated visible unit (firmware-host `Config::visible`).
    let info = irid_out(&["lctf", "info"]);
    assert_eq!(
        field(&info, "controller"),
        "VariSpec protocol (emulated on a pseudo-terminal)"
    );
    assert_eq!(field(&info, "revision"), "1.00");
    assert_eq!(field(&info, "range"), "400 - 720 nm");
    assert_eq!(field(&info, "serial"), "10001");
    // Initialised and exercised by `connect`, idle, no error, not tuned.
    let status = field(&info, "status");
    for want in [
        "initialised=true",
        "exercised=true",
        "palette=false",
        "busy=false",
        "error=0",
    ] {
        assert!(status.contains(want), "{status}");
    }
    assert_eq!(field(&info, "wavelength"), "none");
    assert_eq!(field(&info, "temperature"), "25.00 °C");

    // The near-IR unit, as JSON.
    let nir: serde_json::Value =
        serde_json::from_str(irid_out(&["lctf", "info", "--nir", "--json"]).trim()).unwrap();
    assert_eq!(nir["min_nm"], 650.0);
    assert_eq!(nir["max_nm"], 1100.0);
    assert_eq!(nir["serial"], 10002);
    assert_eq!(nir["revision"], "1.00");
    assert_eq!(nir["emulated"], true);

    // Status: every field, with its type.
    let out = irid_out(&["lctf", "status", "--json", "--temperature", "31.5"]);
    assert_eq!(out.lines().count(), 1, "{out}");
    let st: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    let obj = st.as_object().unwrap();
    let mut keys: Vec<&str> = obj.keys().map(String::as_str).collect();
    keys.sort_unstable();
    assert_eq!(
        keys,
        [
            "busy",
            "error_code",
            "exercised",
            "initialised",
            "palette_defined",
            "raw",
            "temperature_c",
            "wavelength_nm"
        ]
    );
    assert!(st["raw"].as_u64().is_some_and(|r| r <= 0xff), "{st}");
    assert_eq!(st["initialised"], true);
    assert_eq!(st["exercised"], true);
    assert_eq!(st["palette_defined"], false);
    assert_eq!(st["busy"], false);
    assert_eq!(st["error_code"], 0);
    assert!(st["wavelength_nm"].is_null(), "{st}");
    assert_eq!(st["temperature_c"].as_f64(), Some(31.5));

    // Step, text: one line per band, in order, then a summary.
    let out = irid_out(&[
        "lctf",
        "step",
        "--bands",
        "400:440:20",
        "--time-scale",
        "10",
    ]);
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines.len(), 3 + 1, "{out}");
    let mut times = vec![];
    for (line, nm) in lines.iter().zip(["400.00", "420.00", "440.00"]) {
        let w: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(w.len(), 6, "{line}");
        assert_eq!(
            (w[0], w[1], w[2], w[3], w[5]),
            (nm, "nm", "settled", "in", "ms"),
            "{line}"
        );
        let ms: f64 = w[4].parse().unwrap();
        check_settle(ms, 50.0, 10.0);
        times.push(ms);
    }
    let summary = lines[3];
    assert!(summary.starts_with("3 bands: settle mean "), "{summary}");
    assert!(
        summary.contains("emulator 10x faster than real time"),
        "{summary}"
    );
    let min = times.iter().copied().fold(f64::INFINITY, f64::min);
    assert!(summary.contains(&format!("min {min:.2} ms")), "{summary}");

    // Step, JSON: a cold-started near-IR unit, 1000× real time.
    let out = irid_out(&[
        "lctf",
        "step",
        "--bands",
        "700:720:20",
        "--nir",
        "--cold-start",
        "--time-scale",
        "1000",
        "--json",
    ]);
    let lines: Vec<serde_json::Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 2 + 1, "{out}");
    for (l, nm) in lines.iter().zip([700.0, 720.0]) {
        assert_eq!(l["band_nm"], nm);
        check_settle(l["settle_ms"].as_f64().unwrap(), 150.0, 1000.0);
    }
    let s = &lines[2];
    assert_eq!(s["bands"], 2);
    assert_eq!(s["time_scale"], 1000.0);
    assert_eq!(s["emulated"], true);
    let (min, mean, max) = (
        s["min_ms"].as_f64().unwrap(),
        s["mean_ms"].as_f64().unwrap(),
        s["max_ms"].as_f64().unwrap(),
    );
    assert!(min <= mean && mean <= max, "{s}");
    let t: Vec<f64> = lines[..2]
        .iter()
        .map(|l| l["settle_ms"].as_f64().unwrap())
        .collect();
    assert_eq!((min, max), (t[0].min(t[1]), t[0].max(t[1])));
}

#[test]
fn bad_bands_and_ports_are_errors() {
    assert!(
        irid_lctf(&["step", "--bands", "300:400:10"]).is_err(),
        "below the range"
    );
    assert!(irid_lctf(&["info", "--port", "/nonexistent/tty"]).is_err());
    assert_eq!(
        parse_bands("400:700:100").unwrap(),
        vec![400.0, 500.0, 600.0, 700.0]
    );
}
