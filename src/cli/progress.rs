//! Progress bars for long jobs (fitting a large cube, replaying or
//! exporting a recording), on stderr and only
//! when stderr is a terminal: piped or redirected output stays clean.
//!
//! `indicatif` draws at most ~20 times a second whatever the update rate,
//! and its counter is atomic, so solver threads may tick it per row.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::IsTerminal;

/// Jobs shorter than this many steps get no bar (they end before it would
/// be read).
pub const MIN_STEPS: u64 = 64;

/// A bar of `len` steps labelled `what`; hidden unless stderr is a
/// terminal and the job is long enough to watch.
pub fn bar(len: u64, what: &str) -> ProgressBar {
    if len < MIN_STEPS || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
    let style = ProgressStyle::with_template(
        "{msg} [{elapsed_precise}] {wide_bar} {pos}/{len} (eta {eta})",
    )
    .unwrap_or_else(|_| ProgressStyle::default_bar());
    bar.set_style(style);
    bar.set_message(what.to_string());
    bar
}

/// A bar over the bytes of a file of `len` bytes (reading a recording),
/// labelled `what`; hidden unless stderr is a terminal.
pub fn bytes_bar(len: u64, what: &str) -> ProgressBar {
    if !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
    let style = ProgressStyle::with_template(
        "{msg} [{elapsed_precise}] {wide_bar} {bytes}/{total_bytes} (eta {eta})",
    )
    .unwrap_or_else(|_| ProgressStyle::default_bar());
    bar.set_style(style);
    bar.set_message(what.to_string());
    bar
}
