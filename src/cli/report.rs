//! The one-line error report of the `irid` binary.
//!
//! Errors reach `main` as an `anyhow` chain. Some of the typed errors
//! below put their source in their own message *and* expose it as
//! `source()` (thiserror does both for a field named `source`, or a
//! `#[from]` field formatted with `{0}`), so printing the chain with
//! `{:#}` would repeat it. [`error_line`] prints each link of the chain
//! once: a cause whose text its predecessors already show is left out.

/// `e` and its causes on one line, each cause once, separated by `": "`.
pub fn error_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if text.is_empty() || line.contains(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

#[cfg(test)]
mod tests {
    use super::*;
    use anyhow::Context;

    #[test]
    fn a_source_formatted_into_its_message_prints_once() {
        // IoError::Os formats its `source` and exposes it as the source.
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such file");
        let e = crate::io::IoError::os(std::path::Path::new("cube.hdr"), io);
        let e = Err::<(), _>(e).context("reading the cube").unwrap_err();
        let line = error_line(&e);
        assert_eq!(line, "reading the cube: cube.hdr: no such file");
        assert_eq!(format!("{e:#}").matches("no such file").count(), 2, "{e:#}");
    }

    #[test]
    fn a_chain_of_distinct_messages_keeps_every_link() {
        let inner = std::io::Error::other("disk full");
        let e = anyhow::Error::new(inner)
            .context("writing out/sweep-000001.exr")
            .context("sink");
        assert_eq!(
            error_line(&e),
            "sink: writing out/sweep-000001.exr: disk full"
        );
    }

    #[test]
    fn a_from_wrapper_that_repeats_its_source_prints_it_once() {
        use crate::device::camera::CameraError;
        let cam = CameraError::Io(std::io::Error::other("device unplugged"));
        let e = anyhow::Error::new(crate::pipeline::runner::RunError::Camera(cam));
        let line = error_line(&e);
        assert_eq!(line.matches("device unplugged").count(), 1, "{line}");
        assert!(line.starts_with("camera: "), "{line}");
    }
}
