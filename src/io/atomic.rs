//! Writing a file so that a crash, a full disk or a read-only folder never
//! leaves a damaged file under its final name.
//!
//! Every file irid writes goes through [`write_atomically`]: the content is
//! written to a hidden temporary file in the same folder (same file system,
//! so the final step is a rename), synced to disk, then renamed over the
//! final name and the folder synced. Until the rename the final name holds
//! what it held before (or nothing); on any error the temporary file is
//! removed and the error names the final path.
//!
//! [`Overwrite::Refuse`] makes the final step a hard link, which fails if
//! the name exists, so an existing output is never replaced unless asked
//! (checked at the moment of writing, not before: no race with another
//! writer). On file systems without hard links it falls back to checking
//! and renaming.

use super::IoError;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// Whether an existing file at the final name may be replaced.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Overwrite {
    /// Replace it (the command was given `--force`, or the file is the
    /// command's own to renew).
    #[default]
    Replace,
    /// Refuse: the error says the file exists.
    Refuse,
}

/// Temporary files made by this process so far (part of their names, so
/// two writers in one process never share one).
static SERIAL: AtomicU64 = AtomicU64::new(0);

/// The hidden temporary file beside `path`: `.NAME.tmp-PID-N`.
fn temp_path(path: &Path) -> Result<PathBuf, IoError> {
    let name = path
        .file_name()
        .ok_or_else(|| IoError::format(path, "not a file name"))?;
    let mut tmp = std::ffi::OsString::from(".");
    tmp.push(name);
    tmp.push(format!(
        ".tmp-{}-{}",
        std::process::id(),
        SERIAL.fetch_add(1, Ordering::Relaxed)
    ));
    Ok(path.with_file_name(tmp))
}

/// The error for an output that exists and may not be replaced.
pub fn exists_error(path: &Path) -> IoError {
    IoError::format(
        path,
        "exists; give --force to replace it, or choose another name",
    )
}

/// Refuse early (before any work) if `path` exists and may not be
/// replaced; [`write_atomically`] checks again when it writes.
pub fn check_new(path: &Path, overwrite: Overwrite) -> Result<(), IoError> {
    if overwrite == Overwrite::Refuse && path.symlink_metadata().is_ok() && !is_special(path) {
        return Err(exists_error(path));
    }
    Ok(())
}

/// Write through `body` into a temporary file beside `path`, sync it, and
/// move it to `path` (replacing it or not, per `overwrite`); on any failure
/// the temporary file is removed and `path` is left as it was.
pub fn write_atomically(
    path: &Path,
    overwrite: Overwrite,
    body: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> Result<(), IoError> {
    // A device or a pipe (`--out /dev/null`, `/dev/stdout`, a FIFO) is
    // written in place: a rename would replace it with a regular file
    // (`/dev/null` became one, and everything that read it since read
    // what had been written there).
    // Nothing is lost there, so it is written with or without `--force`.
    if is_special(path) {
        return write_in_place(path, body).map_err(|e| IoError::os(path, e));
    }
    let tmp = temp_path(path)?;
    let written = (|| {
        let file = File::options().write(true).create_new(true).open(&tmp)?;
        let mut w = BufWriter::new(file);
        body(&mut w)?;
        let file = w.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()
    })();
    let moved = written.and_then(|()| match overwrite {
        Overwrite::Replace => std::fs::rename(&tmp, path).map(|()| true),
        Overwrite::Refuse => match std::fs::hard_link(&tmp, path) {
            Ok(()) => Ok(true),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(false),
            // No hard links here (e.g. some network or FAT file systems).
            Err(_) if path.symlink_metadata().is_err() => {
                std::fs::rename(&tmp, path).map(|()| true)
            }
            Err(_) => Ok(false),
        },
    });
    // After a rename this finds nothing; after a link it drops the extra name.
    let _ = std::fs::remove_file(&tmp);
    match moved {
        Err(e) => return Err(IoError::os(path, e)),
        Ok(false) => return Err(exists_error(path)),
        Ok(true) => {}
    }
    // Make the rename itself durable where the platform allows it.
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
    Ok(())
}

/// Whether `path` names an existing device, pipe or socket (followed
/// through links): a stream, not a file a result is kept in.
fn is_special(path: &Path) -> bool {
    std::fs::metadata(path).is_ok_and(|m| !m.is_file() && !m.is_dir())
}

/// Write through `body` into an existing special file (a device, a pipe).
fn write_in_place(
    path: &Path,
    body: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let file = File::options().write(true).open(path)?;
    let mut w = BufWriter::new(file);
    body(&mut w)?;
    w.flush()
}

/// [`write_atomically`] of a byte buffer.
pub fn write_bytes(path: &Path, overwrite: Overwrite, bytes: &[u8]) -> Result<(), IoError> {
    write_atomically(path, overwrite, |w| w.write_all(bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leftovers(dir: &Path) -> Vec<String> {
        std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains(".tmp-"))
            .collect()
    }

    /// A pipe named as the output is written through, not replaced by a
    /// regular file (as `--out /dev/null --force` once replaced
    /// `/dev/null`), with or without `--force`: a stream holds no result
    /// to lose.
    #[cfg(unix)]
    #[test]
    fn a_pipe_or_device_is_written_in_place_not_replaced() {
        use std::os::unix::fs::FileTypeExt;
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("out.csv");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        if !made.is_ok_and(|s| s.success()) {
            eprintln!("no mkfifo here: skipped");
            return;
        }
        let reader = {
            let fifo = fifo.clone();
            std::thread::spawn(move || std::fs::read(fifo).unwrap())
        };
        write_bytes(&fifo, Overwrite::Replace, b"d,sigma\n").unwrap();
        assert_eq!(reader.join().unwrap(), b"d,sigma\n");
        let kind = std::fs::symlink_metadata(&fifo).unwrap().file_type();
        assert!(kind.is_fifo(), "{kind:?}");
        assert!(leftovers(dir.path()).is_empty());
        check_new(&fifo, Overwrite::Refuse).unwrap();
        let reader = {
            let fifo = fifo.clone();
            std::thread::spawn(move || std::fs::read(fifo).unwrap())
        };
        write_bytes(&fifo, Overwrite::Refuse, b"x").unwrap();
        assert_eq!(reader.join().unwrap(), b"x");
        assert!(std::fs::symlink_metadata(&fifo)
            .unwrap()
            .file_type()
            .is_fifo());
    }

    #[test]
    fn a_failing_body_leaves_the_old_file_and_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.csv");
        write_bytes(&p, Overwrite::Replace, b"old").unwrap();
        let e = write_atomically(&p, Overwrite::Replace, |w| {
            w.write_all(b"half")?;
            Err(std::io::Error::other("disk full"))
        })
        .unwrap_err();
        assert!(e.to_string().contains("a.csv"), "{e}");
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert!(leftovers(dir.path()).is_empty());
    }

    #[test]
    fn refuse_keeps_an_existing_file_and_replace_replaces_it() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.exr");
        write_bytes(&p, Overwrite::Refuse, b"first").unwrap();
        let e = write_bytes(&p, Overwrite::Refuse, b"second").unwrap_err();
        assert!(e.to_string().contains("--force"), "{e}");
        assert!(check_new(&p, Overwrite::Refuse).is_err());
        assert!(check_new(&p, Overwrite::Replace).is_ok());
        assert_eq!(std::fs::read(&p).unwrap(), b"first");
        write_bytes(&p, Overwrite::Replace, b"third").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"third");
        assert!(leftovers(dir.path()).is_empty());
    }
}
