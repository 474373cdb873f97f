//! The emulator speaks the raw protocol byte for byte, as a pyserial client
//! (or micro-manager's adapter) sees it: echo, then the reply, CR-terminated;
//! immediate commands answer with echo + one byte.

use std::time::Duration;

use lctf_firmware::emu::{spawn_pty, EmuConfig};

fn exchange(port: &mut dyn serialport::SerialPort, send: &[u8], expect: &[u8]) {
    port.write_all(send).unwrap();
    let mut got = vec![0u8; expect.len()];
    port.read_exact(&mut got).unwrap();
    assert_eq!(
        String::from_utf8_lossy(&got),
        String::from_utf8_lossy(expect),
        "after sending {:?}",
        String::from_utf8_lossy(send)
    );
}

#[test]
fn raw_bytes_on_the_line() {
    let h = spawn_pty(EmuConfig::ready()).unwrap();
    let mut p = serialport::new(h.path().to_str().unwrap(), 9600)
        .timeout(Duration::from_secs(2))
        .open()
        .unwrap();
    let p = p.as_mut();
    exchange(p, b"V?\r", b"V?\rV   1.00    400    720  10001\r");
    exchange(p, b"@", b"@C");
    exchange(p, b"!", b"!>");
    exchange(p, b"W 550.000\r", b"W 550.000\r");
    exchange(p, b"!", b"!<");
    exchange(p, b"W?\r", b"W?\rW 550.00\r");
    exchange(p, b"B1\r", b"B1\r");
    exchange(p, b"@", b"@K");
    exchange(p, b"W?\r", b"W?\r550.00\r");
    exchange(p, b"V ?\r", b"V ?\r1.00 400 720 10001\r");
    exchange(p, b"B2\r", b"B2\rb      2\r");
    exchange(p, b"D 500,0\r", b"D 500,0\rd 500.00\r");
    exchange(p, b"B0\r", b"B0\r");
    exchange(p, b"W 9000\r", b"W 9000\r");
    // 0x40 | error 0x20 | palette 0x04 | exercised 0x02 | initialised 0x01
    exchange(p, b"@", b"@g");
    exchange(p, b"R?\r", b"R?\rR     12\r");
    exchange(p, b"R1\r", b"R1\r");
    exchange(p, b"W?\r", b"W?\rW      *\r");
    // LF is ignored, so "\r\n" line endings work too.
    exchange(p, b"P?\r\n", b"P?\rP      0\r");
    exchange(p, b"Y?\r", b"Y?\rY  25.00\r");
    exchange(p, b"W 5\x1b", b"W 5\x1b");
    exchange(p, b"\r", b"\r");
    exchange(p, b"@", b"@G");
}

/// A device that floods the line without ever ending one (wrong baud, a
/// different instrument, noise): the driver gives up with a short error
/// quoting the start, in bounded time and memory — never a giant reply.
#[test]
fn a_flood_without_line_ends_is_a_short_error() {
    use irid::device::filter::varispec::{VariSpec, VariSpecOptions};
    use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};
    use std::io::Write;
    use std::os::fd::AsFd;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;

    let pty = nix::pty::openpty(None, None).unwrap();
    let mut t = tcgetattr(pty.slave.as_fd()).unwrap();
    cfmakeraw(&mut t);
    tcsetattr(pty.slave.as_fd(), SetArg::TCSANOW, &t).unwrap();
    let path = nix::unistd::ttyname(pty.slave.as_fd()).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let flood = {
        let stop = stop.clone();
        // Non-blocking: once the driver has given up nobody reads, the
        // pty's buffer fills, and a blocking write would never return to
        // see `stop` (closing the slave does not wake it on every kernel:
        // this test once hung CI).
        let flags = nix::fcntl::fcntl(pty.master.as_fd(), nix::fcntl::FcntlArg::F_GETFL).unwrap();
        let flags = nix::fcntl::OFlag::from_bits_truncate(flags) | nix::fcntl::OFlag::O_NONBLOCK;
        nix::fcntl::fcntl(pty.master.as_fd(), nix::fcntl::FcntlArg::F_SETFL(flags)).unwrap();
        let mut master = std::fs::File::from(pty.master);
        std::thread::spawn(move || {
            let junk = [b'A'; 4096];
            while !stop.load(Ordering::Relaxed) {
                match master.write(&junk) {
                    Ok(_) => {}
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        std::thread::sleep(Duration::from_millis(1));
                    }
                    Err(_) => break,
                }
            }
        })
    };
    let opts = VariSpecOptions {
        reply_timeout: Duration::from_millis(200),
        retries: 1,
        ..VariSpecOptions::default()
    };
    let started = std::time::Instant::now();
    let err = VariSpec::open(path.to_str().unwrap(), opts).unwrap_err();
    let took = started.elapsed();
    stop.store(true, Ordering::Relaxed);
    drop(pty.slave);
    let _ = flood.join();
    let msg = err.to_string();
    assert!(msg.contains("without a line end"), "{msg}");
    assert!(msg.len() < 400, "error of {} bytes: {msg}", msg.len());
    // Resync (2 reply timeouts) + at most 2 attempts, each well under a
    // second: bounded, not a hang.
    assert!(took < Duration::from_secs(5), "took {took:?}");
}
