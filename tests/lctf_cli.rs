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

#[test]
fn info_status_and_step_work_without_hardware() {
    irid_lctf(&["info"]).unwrap();
    irid_lctf(&["status", "--json"]).unwrap();
    irid_lctf(&["step", "--bands", "400:440:20", "--time-scale", "10"]).unwrap();
    irid_lctf(&[
        "step",
        "--bands",
        "700:720:20",
        "--nir",
        "--cold-start",
        "--time-scale",
        "1000",
        "--json",
    ])
    .unwrap();
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
