//! Hostile files a new user could feed `irid fit`: each is refused with an
//! error naming what is wrong, before anything out of proportion to the
//! file is allocated — never an abort or a panic — and every error prints
//! its cause once.

mod cli_common;
use cli_common::{fails_with, irid, s};
use std::path::{Path, PathBuf};

fn cube(dir: &Path, name: &str, dims: (u64, u64), wavelengths: &[f64], data: usize) -> PathBuf {
    let w: Vec<String> = wavelengths.iter().map(|x| format!("{x}")).collect();
    let text = format!(
        "ENVI\nsamples = {}\nlines = {}\nbands = {}\nheader offset = 0\ndata type = 4\n\
         interleave = bsq\nbyte order = 0\nwavelength units = Nanometers\nwavelength = {{{}}}\n",
        dims.0,
        dims.1,
        w.len(),
        w.join(", ")
    );
    let hdr = dir.join(format!("{name}.hdr"));
    std::fs::write(&hdr, text).unwrap();
    std::fs::write(dir.join(format!("{name}.img")), vec![0u8; data]).unwrap();
    hdr
}

fn fit(hdr: &Path, fragments: &[&str]) {
    let out = hdr.with_extension("exr");
    fails_with(&["fit", s(hdr), "--out", s(&out), "--n3", "1.6"], fragments);
}

#[test]
fn sub_nanometre_wavelengths_are_refused() {
    // The cube: 4 × 3, wavelengths 0.001–0.031 "nm" (µm values
    // under a nm unit). It used to abort allocating 12 GB.
    let dir = tempfile::tempdir().unwrap();
    let w: Vec<f64> = (0..31).map(|i| 0.001 + 0.001 * f64::from(i)).collect();
    let hdr = cube(dir.path(), "tiny", (4, 3), &w, 4 * 3 * 31 * 4);
    fit(&hdr, &["band centre 0.001 nm", "wavelength units"]);
}

#[test]
fn bands_that_would_need_gigabytes_of_grid_are_refused_before_allocating() {
    // 31 bands all at 12 nm: no spacing bounds the thickness, and so short
    // a wavelength makes the fringe-search grid step tiny (~2 GB of grid).
    let dir = tempfile::tempdir().unwrap();
    let hdr = cube(dir.path(), "same", (4, 3), &[12.0; 31], 4 * 3 * 31 * 4);
    fit(&hdr, &["fringe-search grid", "at most 64 MB"]);
}

#[test]
fn a_header_claiming_a_terapixel_is_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let w: Vec<f64> = (0..31).map(|i| 400.0 + 10.0 * f64::from(i)).collect();
    let hdr = cube(dir.path(), "tera", (1_000_000, 1_000_000), &w, 1024);
    fit(&hdr, &["data file too short", "1024"]);
}

#[test]
fn an_error_prints_its_cause_once() {
    // SceneError::Io formats its io::Error and exposes it as its source.
    let dir = tempfile::tempdir().unwrap();
    let w: Vec<f64> = (0..31).map(|i| 400.0 + 10.0 * f64::from(i)).collect();
    let hdr = cube(dir.path(), "c", (4, 3), &w, 4 * 3 * 31 * 4);
    let missing = dir.path().join("missing.toml");
    let m = dir.path().join("m.exr");
    let out = irid(&["fit", s(&hdr), "--out", s(&m), "--scene", s(&missing)]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert_eq!(err.matches("No such file or directory").count(), 1, "{err}");
}
