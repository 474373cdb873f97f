//! Fuzz-style properties of the firmware core: arbitrary bytes and sync
//! pulses never panic, and always leave the controller in a defined state.

use lctf_firmware::controller::{status, Config, Controller, OUT_CAPACITY};
use lctf_firmware::parser::{parse_line, Line};
use lctf_firmware::ErrorCode;
use proptest::prelude::*;

fn ready() -> Controller {
    Controller::new(Config {
        initialised: true,
        exercised: true,
        ..Config::visible()
    })
}

/// Bytes biased towards the protocol's alphabet so that deep states
/// (palette, modes, sleep, long operations) are reached, not just syntax errors.
fn protocol_byte() -> impl Strategy<Value = u8> {
    prop_oneof![
        4 => proptest::sample::select(b"ABCDEGIJMPRSVWXY0123456789.,?<> \r!@\x1b-".to_vec()),
        1 => any::<u8>(),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn parser_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..48)) {
        let r = parse_line(&bytes);
        if Line::new_checked(&bytes).is_err() {
            prop_assert_eq!(r, Err(ErrorCode::Syntax));
        }
    }

    #[test]
    fn controller_survives_any_byte_stream(
        bytes in proptest::collection::vec(protocol_byte(), 0..400),
        steps in proptest::collection::vec(0u64..20_000_000, 0..400),
        pulses in proptest::collection::vec(any::<bool>(), 0..400),
    ) {
        let mut c = ready();
        let mut now = 0u64;
        let mut sent = 0usize;
        for (i, &b) in bytes.iter().enumerate() {
            now += steps.get(i).copied().unwrap_or(1000);
            c.feed(b, now);
            if pulses.get(i).copied().unwrap_or(false) {
                c.sync_pulse(now);
            }
            while c.pop_output().is_some() {
                sent += 1;
            }
            // Defined state: status byte well-formed, error consistent.
            let s = c.status_byte();
            prop_assert!(s & status::ALWAYS != 0);
            prop_assert_eq!(s & status::ERROR_PENDING != 0, c.error().is_some());
            if let Some(t) = c.target_centi() {
                prop_assert!((40_000..=72_000).contains(&t));
            }
            prop_assert!(c.output_len() <= OUT_CAPACITY);
        }
        // Every byte except LF produces at least its echo.
        let non_lf = bytes.iter().filter(|&&b| b != b'\n').count();
        prop_assert!(sent >= non_lf);
        // Whatever happened, ESC and R 1 bring it back to a quiet, error-free
        // state once the long operations are over.
        for &b in b"\x1bR1\r" {
            c.feed(b, now);
        }
        c.poll(now + 1_000_000_000);
        prop_assert!(!c.is_busy());
        prop_assert_eq!(c.error(), None);
    }
}
