//! `irid lctf`: talk to the tunable-filter controller from the command line.
//!
//! `info`, `status` and `step` open a VariSpec-protocol controller on
//! `--port`, or — when no port is given — spawn irid's emulated controller
//! on a pseudo-terminal in-process and talk to it through that real serial
//! line, so the commands work on a machine without hardware.

use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use lctf_firmware::emu::{spawn_pty, EmuConfig, EmulatorHandle};
use lctf_firmware::timing::{EXERCISE_CYCLE_US, INITIALISE_US};
use lctf_firmware::{Config, TimeScale};

use crate::device::filter::{FilterController, VariSpec, VariSpecOptions};

/// Arguments of `irid lctf`.
#[derive(clap::Args, Debug)]
pub struct LctfArgs {
    #[command(subcommand)]
    pub command: LctfCommand,
}

/// The `irid lctf` subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum LctfCommand {
    /// Version, tuning range, serial number and status.
    Info(Connection),
    /// Status flags, busy, pending error, wavelength, temperature.
    Status(Connection),
    /// Step through a band sequence and report each settle time.
    Step(StepArgs),
}

/// How to reach the controller.
#[derive(clap::Args, Debug, Clone)]
pub struct Connection {
    /// Serial port of the controller; omitted: use the emulated controller.
    #[arg(long)]
    pub port: Option<String>,
    /// Baud rate.
    #[arg(long, default_value_t = 9600)]
    pub baud: u32,
    /// Longest wait for one reply, ms.
    #[arg(long, default_value_t = 500)]
    pub reply_timeout_ms: u64,
    /// Emulator: device time runs this many times faster than real time.
    #[arg(long, default_value_t = 1.0)]
    pub time_scale: f64,
    /// Emulator: a near-infrared unit (650-1100 nm, ~150 ms settle).
    #[arg(long)]
    pub nir: bool,
    /// Emulator: power on uninitialised (runs `I`, 30 s of device time).
    #[arg(long)]
    pub cold_start: bool,
    /// Emulator: liquid-crystal temperature, °C.
    #[arg(long, default_value_t = 25.0)]
    pub temperature: f64,
    /// Print JSON lines instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `irid lctf step`.
#[derive(clap::Args, Debug)]
pub struct StepArgs {
    #[command(flatten)]
    pub conn: Connection,
    /// Bands as start:stop:step in nm (inclusive), e.g. 400:700:10.
    #[arg(long, default_value = "400:700:10")]
    pub bands: String,
    /// Longest wait for one band to settle, ms.
    #[arg(long, default_value_t = 2000)]
    pub settle_timeout_ms: u64,
}

/// An open controller; keeps the emulator (if any) alive.
struct Session {
    filter: VariSpec,
    _emu: Option<EmulatorHandle>,
    emulated: bool,
    scale: f64,
}

fn connect(c: &Connection) -> anyhow::Result<Session> {
    let opts = VariSpecOptions {
        baud: c.baud,
        reply_timeout: Duration::from_millis(c.reply_timeout_ms),
        ..VariSpecOptions::default()
    };
    let scale = TimeScale::new(c.time_scale);
    let (path, emu) = match &c.port {
        Some(p) => (p.clone(), None),
        None => {
            let mut unit = if c.nir {
                Config::nir()
            } else {
                Config::visible()
            };
            unit.initialised = !c.cold_start;
            unit.exercised = !c.cold_start;
            unit.temp_centi_c = (c.temperature * 100.0).round() as i32;
            let h = spawn_pty(EmuConfig {
                unit,
                time_scale: scale,
                ..EmuConfig::default()
            })
            .context("spawning the emulated controller")?;
            (h.path().display().to_string(), Some(h))
        }
    };
    let mut filter =
        VariSpec::open(&path, opts).with_context(|| format!("opening the controller on {path}"))?;
    // Initialisation and one exercise cycle, plus margin for the line.
    let ready = scale.wall(INITIALISE_US + EXERCISE_CYCLE_US) + Duration::from_secs(5);
    filter
        .ensure_ready(ready)
        .context("initialising the controller")?;
    Ok(Session {
        filter,
        emulated: emu.is_some(),
        _emu: emu,
        scale: scale.factor(),
    })
}

/// Parse `start:stop:step` (nm, inclusive of `stop` when on the grid).
pub fn parse_bands(s: &str) -> anyhow::Result<Vec<f64>> {
    let parts: Vec<f64> = s
        .split(':')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("bands {s:?}: expected start:stop:step in nm"))?;
    let [start, stop, step] = parts[..] else {
        bail!("bands {s:?}: expected start:stop:step in nm");
    };
    if !(start.is_finite() && stop.is_finite() && step.is_finite() && step > 0.0 && stop >= start) {
        bail!("bands {s:?}: need start <= stop and step > 0");
    }
    let n = ((stop - start) / step + 1e-9).floor() as usize + 1;
    if n > 10_000 {
        bail!("bands {s:?}: {n} bands is too many");
    }
    Ok((0..n).map(|i| start + step * i as f64).collect())
}

/// Entry point of `irid lctf`.
pub fn run(args: &LctfArgs) -> anyhow::Result<()> {
    match &args.command {
        LctfCommand::Info(c) => info(c),
        LctfCommand::Status(c) => status(c),
        LctfCommand::Step(s) => step(s),
    }
}

fn info(c: &Connection) -> anyhow::Result<()> {
    let mut s = connect(c)?;
    let v = s.filter.version()?;
    let st = s.filter.status()?;
    if c.json {
        println!(
            "{}",
            serde_json::json!({
                "revision": v.revision, "min_nm": v.min_nm, "max_nm": v.max_nm,
                "serial": v.serial, "emulated": s.emulated,
                "status": status_json(&st),
            })
        );
    } else {
        println!(
            "controller: VariSpec protocol{}",
            if s.emulated {
                " (emulated on a pseudo-terminal)"
            } else {
                ""
            }
        );
        println!("revision:   {}", v.revision);
        println!("range:      {} - {} nm", v.min_nm, v.max_nm);
        println!("serial:     {}", v.serial);
        print_status(&st);
    }
    Ok(())
}

fn status(c: &Connection) -> anyhow::Result<()> {
    let mut s = connect(c)?;
    let st = s.filter.status()?;
    if c.json {
        println!("{}", status_json(&st));
    } else {
        print_status(&st);
    }
    Ok(())
}

fn status_json(st: &crate::device::filter::Status) -> serde_json::Value {
    serde_json::json!({
        "raw": st.raw, "initialised": st.initialised, "exercised": st.exercised,
        "palette_defined": st.palette_defined, "busy": st.busy,
        "error_code": st.error_code, "wavelength_nm": st.wavelength_nm,
        "temperature_c": st.temperature_c,
    })
}

fn print_status(st: &crate::device::filter::Status) {
    let wl = st
        .wavelength_nm
        .map_or_else(|| "none".to_owned(), |w| format!("{w:.2} nm"));
    println!(
        "status:     0x{:02x} initialised={} exercised={} palette={} busy={} error={}",
        st.raw, st.initialised, st.exercised, st.palette_defined, st.busy, st.error_code
    );
    println!("wavelength: {wl}");
    println!("temperature: {:.2} °C", st.temperature_c);
}

fn step(a: &StepArgs) -> anyhow::Result<()> {
    let bands = parse_bands(&a.bands)?;
    let mut s = connect(&a.conn)?;
    let timeout = Duration::from_millis(a.settle_timeout_ms);
    let mut times = Vec::with_capacity(bands.len());
    let started = Instant::now();
    for &nm in &bands {
        let t = s
            .filter
            .tune(nm, timeout)
            .with_context(|| format!("tuning to {nm} nm"))?;
        let ms = t.as_secs_f64() * 1e3;
        if a.conn.json {
            println!("{}", serde_json::json!({"band_nm": nm, "settle_ms": ms}));
        } else {
            println!("{nm:8.2} nm  settled in {ms:7.2} ms");
        }
        times.push(ms);
    }
    let n = times.len() as f64;
    let mean = times.iter().sum::<f64>() / n;
    let max = times.iter().copied().fold(0.0, f64::max);
    let min = times.iter().copied().fold(f64::INFINITY, f64::min);
    if a.conn.json {
        println!(
            "{}",
            serde_json::json!({"bands": times.len(), "mean_ms": mean, "min_ms": min,
                "max_ms": max, "total_s": started.elapsed().as_secs_f64(),
                "time_scale": s.scale, "emulated": s.emulated})
        );
    } else {
        println!(
            "{} bands: settle mean {mean:.2} ms, min {min:.2} ms, max {max:.2} ms (wall clock{}); total {:.2} s",
            times.len(),
            if s.emulated && s.scale != 1.0 {
                format!(", emulator {}x faster than real time", s.scale)
            } else {
                String::new()
            },
            started.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bands_parse_inclusive() {
        let b = parse_bands("400:700:10").unwrap();
        assert_eq!(b.len(), 31);
        assert_eq!(b[30], 700.0);
        assert_eq!(parse_bands("500:500:1").unwrap(), vec![500.0]);
        assert!(parse_bands("700:400:10").is_err());
        assert!(parse_bands("400:700").is_err());
        assert!(parse_bands("400:700:0").is_err());
        assert!(parse_bands("a:b:c").is_err());
    }
}
