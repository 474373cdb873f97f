//! Running the `irid` binary from integration tests: success, failure
//! with the expected words in the message, paths as arguments.
#![allow(dead_code)] // each test crate uses its own share

use std::path::Path;
use std::process::{Command, Output};

/// Run `irid` with `args`.
pub fn irid(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_irid"))
        .args(args)
        .output()
        .expect("run irid")
}

/// Run `irid`, which must succeed.
pub fn ok(args: &[&str]) -> Output {
    let out = irid(args);
    assert!(
        out.status.success(),
        "irid {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Run `irid`, which must fail (no panic) with each fragment in its message.
pub fn fails_with(args: &[&str], fragments: &[&str]) {
    let out = irid(args);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "irid {args:?} succeeded");
    assert!(!err.contains("panicked"), "irid {args:?} panicked: {err}");
    for f in fragments {
        assert!(err.contains(f), "irid {args:?}: {err:?} lacks {f:?}");
    }
}

/// A path as an argument.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}
