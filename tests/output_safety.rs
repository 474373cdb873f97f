//! Outputs under hostile conditions: a full disk and a read-only folder
//! are reported with the file named, and never damage an output written
//! before; no temporary file is left behind; an existing output is kept
//! unless `--force` is given.
//!
//! The full-disk and read-only cases use a 64 kB tmpfs (root can write
//! into a read-only *directory*, so permissions alone prove nothing as
//! root); where mounting is not permitted, the read-only case falls back
//! to a directory without write permission (as a normal user) and the
//! full-disk case is skipped with a message.

mod cli_common;
use cli_common::{fails_with, ok, s};
use irid::estimate::ParamMaps;
use irid::io::exr_maps::{read_maps, write_maps};
use irid::io::results_csv::write_results;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A tmpfs of `size` mounted on a fresh directory, unmounted on drop.
struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    fn mount(size: &str) -> Option<Tmpfs> {
        let dir = tempfile::tempdir().ok()?;
        let ok = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir.path())
            .output()
            .is_ok_and(|o| o.status.success());
        ok.then_some(Tmpfs { dir })
    }
    fn path(&self) -> &Path {
        self.dir.path()
    }
    fn remount_read_only(&self) -> bool {
        Command::new("mount")
            .args(["-o", "remount,ro"])
            .arg(self.path())
            .status()
            .is_ok_and(|s| s.success())
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(self.dir.path()).status();
    }
}

/// Maps of incompressible values (so their size is what we ask for).
fn maps(w: usize, h: usize, seed: u32) -> ParamMaps {
    let mut m = ParamMaps::new(w, h);
    let mut x = seed.wrapping_mul(2_654_435_761).max(1);
    for v in m.thickness_nm.iter_mut().chain(m.theta_deg.iter_mut()) {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        *v = f32::from_bits(0x4000_0000 | (x >> 9));
    }
    m
}

fn temporaries(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.to_string_lossy().contains(".tmp-"))
        .collect()
}

#[test]
fn a_full_disk_is_reported_and_earlier_outputs_survive() {
    let Some(fs) = Tmpfs::mount("64k") else {
        eprintln!("SKIPPED: mounting a tmpfs is not permitted here (needs root)");
        return;
    };
    let first = fs.path().join("sweep-000000.exr");
    let small = maps(8, 8, 1);
    write_maps(&first, &small).unwrap();
    let before = std::fs::read(&first).unwrap();
    // 128 × 128 × 2 incompressible channels ≈ 128 kB: more than the disk.
    let big = maps(128, 128, 2);
    let second = fs.path().join("sweep-000001.exr");
    let e = write_maps(&second, &big).unwrap_err().to_string();
    assert!(e.contains("sweep-000001.exr"), "{e}");
    assert!(e.contains("No space left on device"), "{e}");
    // Replacing the first map with the big one fails too, and keeps it.
    assert!(write_maps(&first, &big).is_err());
    assert_eq!(
        std::fs::read(&first).unwrap(),
        before,
        "earlier map damaged"
    );
    assert_eq!(read_maps(&first).unwrap().thickness_nm, small.thickness_nm);
    assert!(!second.exists(), "no partial map under the final name");
    let csv = fs.path().join("res.csv");
    assert!(write_results(&csv, &big, None).is_err());
    assert!(!csv.exists());
    assert!(
        temporaries(fs.path()).is_empty(),
        "{:?}",
        temporaries(fs.path())
    );
}

#[test]
fn a_read_only_folder_is_reported_and_earlier_outputs_survive() {
    let small = maps(8, 8, 3);
    let check = |dir: &Path| {
        let first = dir.join("maps.exr");
        let before = std::fs::read(&first).unwrap();
        let e = write_maps(&first, &maps(8, 8, 4)).unwrap_err().to_string();
        assert!(e.contains("maps.exr"), "{e}");
        assert!(
            e.contains("Read-only file system") || e.contains("Permission denied"),
            "{e}"
        );
        assert_eq!(std::fs::read(&first).unwrap(), before);
        assert!(write_results(&dir.join("r.csv"), &small, None).is_err());
        assert!(temporaries(dir).is_empty());
    };
    if let Some(fs) = Tmpfs::mount("64k") {
        write_maps(&fs.path().join("maps.exr"), &small).unwrap();
        assert!(fs.remount_read_only(), "remount read-only");
        check(fs.path());
        return;
    }
    // Not root: a folder without write permission does the same.
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    write_maps(&dir.path().join("maps.exr"), &small).unwrap();
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o555)).unwrap();
    check(dir.path());
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
}

#[test]
fn existing_outputs_are_kept_unless_forced() {
    let dir = tempfile::tempdir().unwrap();
    let cube = dir.path().join("cube.hdr");
    ok(&["synth", "--out", s(&cube), "--seed", "1"]);
    let img = std::fs::read(dir.path().join("cube.img")).unwrap();
    fails_with(
        &["synth", "--out", s(&cube), "--seed", "2"],
        &["cube.hdr", "exists", "--force"],
    );
    assert_eq!(std::fs::read(dir.path().join("cube.img")).unwrap(), img);
    ok(&["synth", "--out", s(&cube), "--seed", "2", "--force"]);
    assert_ne!(std::fs::read(dir.path().join("cube.img")).unwrap(), img);

    let out = dir.path().join("maps.csv");
    std::fs::write(&out, "keep me").unwrap();
    let args = [
        "fit",
        s(&cube),
        "--out",
        s(&out),
        "--n3",
        "1.6",
        "--mode",
        "fast",
    ];
    fails_with(&args, &["maps.csv", "exists", "--force"]);
    assert_eq!(std::fs::read_to_string(&out).unwrap(), "keep me");
    let mut forced = args.to_vec();
    forced.push("--force");
    ok(&forced);
    assert!(std::fs::read_to_string(&out).unwrap().starts_with("name,"));
    assert!(temporaries(dir.path()).is_empty());
}

#[test]
fn a_run_refuses_a_folder_holding_maps_of_an_earlier_run() {
    let dir = tempfile::tempdir().unwrap();
    assert!(irid::pipeline::output::refuse_earlier_maps(dir.path()).is_ok());
    std::fs::write(dir.path().join("notes.txt"), "x").unwrap();
    assert!(irid::pipeline::output::refuse_earlier_maps(dir.path()).is_ok());
    std::fs::write(dir.path().join("sweep-000003.exr"), "x").unwrap();
    let e = irid::pipeline::output::refuse_earlier_maps(dir.path())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("sweep-000003.exr") && e.contains("--force"),
        "{e}"
    );
}
