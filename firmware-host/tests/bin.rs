//! The `lctf-emu` binary prints its pty path as the first stdout line and
//! serves the protocol there until killed.

use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Command, Stdio};
use std::time::Duration;

#[test]
fn prints_path_first_and_serves() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_lctf-emu"))
        .args(["--time-scale", "10", "--seed", "3"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut first = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    let path = first.trim().to_owned();
    assert!(path.starts_with("/dev/"), "{path:?}");
    let mut tty = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&path)
        .unwrap();
    tty.write_all(b"V?\r").unwrap();
    let want = b"V?\rV   1.00    400    720  10001\r";
    let mut got = vec![0u8; want.len()];
    // The emulator answers within milliseconds; a hang would fail the test
    // harness's own timeout rather than this assertion.
    std::thread::sleep(Duration::from_millis(20));
    tty.read_exact(&mut got).unwrap();
    assert_eq!(&got[..], &want[..]);
    child.kill().unwrap();
    child.wait().unwrap();
}
