//! `lctf-emu`: serve the emulated VariSpec-compatible controller on a
//! pseudo-terminal until killed. The pty path is the first line on stdout.

use std::io::Write;
use std::process::ExitCode;
use std::time::Duration;

use lctf_firmware::emu::{spawn_pty, EmuConfig, Faults};
use lctf_firmware::{Config, TimeScale};

const USAGE: &str = "\
usage: lctf-emu [options]
  --time-scale F      device time runs F times faster than real time (default 1)
  --baud N            pace replies at N baud (default: unpaced)
  --nir               emulate a near-infrared unit (650-1100 nm, 150 ms settle)
  --cold-start        power on uninitialised (needs `I`, ~30 s device time)
  --temperature C     liquid-crystal temperature in degrees C (default 25)
  --seed N            jitter and fault PRNG seed (default 1)
  --drop P            drop each byte with probability P
  --garble P          flip a bit in each byte with probability P
  --slow-ms N         hold every reply byte back N ms
  --spurious-error P  leave a spurious error pending after a command with probability P
  -h, --help          this text";

fn parse() -> Result<Option<EmuConfig>, String> {
    let mut cfg = EmuConfig::ready();
    let mut unit_nir = false;
    let mut cold = false;
    let mut temp: Option<f64> = None;
    let mut seed = 1u64;
    let mut faults = Faults::default();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut val = |name: &str| args.next().ok_or_else(|| format!("{name} needs a value"));
        fn num<T: std::str::FromStr>(name: &str, v: String) -> Result<T, String> {
            v.parse().map_err(|_| format!("{name}: bad value {v:?}"))
        }
        match a.as_str() {
            "-h" | "--help" => return Ok(None),
            "--time-scale" => cfg.time_scale = TimeScale::new(num(&a, val(&a)?)?),
            "--baud" => cfg.baud = Some(num(&a, val(&a)?)?),
            "--nir" => unit_nir = true,
            "--cold-start" => cold = true,
            "--temperature" => temp = Some(num(&a, val(&a)?)?),
            "--seed" => seed = num(&a, val(&a)?)?,
            "--drop" => faults.drop_prob = num(&a, val(&a)?)?,
            "--garble" => faults.garble_prob = num(&a, val(&a)?)?,
            "--slow-ms" => faults.slow_reply = Duration::from_millis(num(&a, val(&a)?)?),
            "--spurious-error" => faults.spurious_error_prob = num(&a, val(&a)?)?,
            other => return Err(format!("unknown argument {other:?}")),
        }
    }
    let mut unit = if unit_nir {
        Config::nir()
    } else {
        Config::visible()
    };
    unit.initialised = !cold;
    unit.exercised = !cold;
    unit.seed = seed;
    if let Some(t) = temp {
        unit.temp_centi_c = (t * 100.0).round() as i32;
    }
    cfg.unit = unit;
    cfg.fault_seed = seed;
    cfg.faults = faults;
    Ok(Some(cfg))
}

fn main() -> ExitCode {
    let cfg = match parse() {
        Ok(Some(cfg)) => cfg,
        Ok(None) => {
            println!("{USAGE}");
            return ExitCode::SUCCESS;
        }
        Err(e) => {
            eprintln!("lctf-emu: {e}\n{USAGE}");
            return ExitCode::from(2);
        }
    };
    let handle = match spawn_pty(cfg) {
        Ok(h) => h,
        Err(e) => {
            eprintln!("lctf-emu: cannot open a pseudo-terminal: {e}");
            return ExitCode::FAILURE;
        }
    };
    let mut out = std::io::stdout().lock();
    // The path must be the first line, flushed, so scripts can read it.
    if writeln!(out, "{}", handle.path().display())
        .and_then(|()| out.flush())
        .is_err()
    {
        return ExitCode::FAILURE;
    }
    drop(out);
    eprintln!(
        "lctf-emu: serving {} (time scale {}, faults {:?})",
        handle.path().display(),
        cfg.time_scale.factor(),
        cfg.faults
    );
    loop {
        std::thread::park();
    }
}
