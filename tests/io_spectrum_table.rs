//! Spectrum tables (`irid::io::spectrum_table`): the formats spectrometers
//! export (CSV with a header, whitespace text without one, µm columns,
//! descending rows, missing values), every malformed file refused with
//! its line named, and the boxcar resampling behind `irid fit --bands`
//! against means computed by hand.

use irid::io::spectrum_table::{parse_table, read_table, SpectrumTable, MAX_ROWS, MAX_SPECTRA};
use irid::io::IoError;
use std::path::Path;

fn parse(text: &str) -> Result<SpectrumTable, IoError> {
    parse_table(text.as_bytes(), Path::new("spectra.csv"))
}

fn centers(t: &SpectrumTable) -> Vec<f64> {
    t.cube.bands.iter().map(|b| b.center_nm).collect()
}

/// Spectrum `x` of the table, in band order.
fn spectrum(t: &SpectrumTable, x: usize) -> Vec<f32> {
    (0..t.rows()).map(|b| t.cube.plane(b)[x]).collect()
}

fn error(text: &str) -> String {
    match parse(text) {
        Ok(t) => panic!("parsed: {t:?}"),
        Err(e) => e.to_string(),
    }
}

fn assert_error(text: &str, fragments: &[&str]) {
    let e = error(text);
    assert!(e.starts_with("spectra.csv: "), "{e}");
    for f in fragments {
        assert!(e.contains(f), "{e:?} lacks {f:?}");
    }
}

/// A spectrometer's own export: a block of metadata above the data
/// (OceanView's layout, tab-separated rows without a column header, its
/// begin and end markers), and a CSV whose metadata end in the header.
#[test]
fn metadata_above_the_data_is_skipped() {
    let t = parse(
        "Data from Sample_Reflection__0__12-00-00-000.txt Node\n\
         \n\
         Date: Tue Mar 05 12:00:00 CET 2024\n\
         User: lab\n\
         Spectrometer: USB4H12345\n\
         Integration Time (sec): 1.000000E-1\n\
         Scans to average: 10\n\
         Number of Pixels in Spectrum: 4\n\
         >>>>>Begin Spectral Data<<<<<\n\
         400.12\t41.5\n\
         400.50\t41.7\n\
         400.88\t41.9\n\
         401.26\t42.0\n\
         >>>>>End Spectral Data<<<<<\n",
    )
    .unwrap();
    assert_eq!(t.names, ["spectrum1"]);
    assert_eq!(centers(&t), [400.12, 400.50, 400.88, 401.26]);
    assert_eq!(spectrum(&t, 0), [41.5, 41.7, 41.9, 42.0]);

    let t = parse(
        "Instrument,F20\n\
         Operator,lab; shift 2\n\
         Date,2024-03-05\n\
         Wavelength (nm),wafer 1,wafer 2\n\
         400,0.30,0.31\n\
         410,0.32,0.33\n\
         420,0.34,0.35\n\
         430,0.36,0.37\n",
    )
    .unwrap();
    assert_eq!(t.names, ["wafer 1", "wafer 2"]);
    assert_eq!(spectrum(&t, 1), [0.31, 0.33, 0.35, 0.37]);
    // The last metadata line without a name per column is no header.
    let t = parse(
        "Instrument: F20\nExported 2024\n400 0.3 0.4\n410 0.3 0.4\n420 0.3 0.4\n430 0.3 0.4\n",
    )
    .unwrap();
    assert_eq!(t.names, ["spectrum1", "spectrum2"]);
}

#[test]
fn csv_with_a_header() {
    let t = parse(
        "# exported by a spectrometer\n\
         Wavelength (nm),sample A,\"sample B\"\n\
         400,0.10,0.20\n\
         \n\
         410,0.11,0.21\r\n\
         420,0.12,0.22\n\
         % another comment\n\
         430,0.13,0.23\n\
         440,0.14,0.24\n",
    )
    .unwrap();
    assert_eq!(t.names, ["sample A", "sample B"]);
    assert_eq!((t.cube.width, t.cube.height), (2, 1));
    assert_eq!(centers(&t), [400.0, 410.0, 420.0, 430.0, 440.0]);
    assert!(t.cube.bands.iter().all(|b| b.fwhm_nm == 0.0));
    assert_eq!(spectrum(&t, 0), [0.10, 0.11, 0.12, 0.13, 0.14]);
    assert_eq!(spectrum(&t, 1), [0.20, 0.21, 0.22, 0.23, 0.24]);
    assert!(!t.micrometers);
}

#[test]
fn semicolon_csv() {
    let t = parse("lambda;r\n500;0,5\n501;0,25\n502;0,125\n503;1\n").unwrap();
    assert_eq!(t.names, ["r"]);
    assert_eq!(spectrum(&t, 0), [0.5, 0.25, 0.125, 1.0]);
}

#[test]
fn whitespace_text_without_a_header() {
    let t = parse(
        "# no header\n\
         500  0.5 0.25  1\n\
           510 0.5 0.25 2\n\
         520 0.5   0.25 3   \n\
         530 0.5 0.25 4\n",
    )
    .unwrap();
    assert_eq!(t.names, ["spectrum1", "spectrum2", "spectrum3"]);
    assert_eq!(centers(&t), [500.0, 510.0, 520.0, 530.0]);
    assert_eq!(spectrum(&t, 2), [1.0, 2.0, 3.0, 4.0]);
}

#[test]
fn tab_separated_with_empty_cells() {
    let t = parse("wl\tsample a\tb\n400\t1\t\n410\t\t2\n420 \t 1\t2\n430\t1\t2\n").unwrap();
    assert_eq!(t.names, ["sample a", "b"]);
    assert!(spectrum(&t, 1)[0].is_nan());
    assert!(spectrum(&t, 0)[1].is_nan());
    assert_eq!(spectrum(&t, 0)[2..], [1.0, 1.0]);
}

#[test]
fn micrometers_are_converted() {
    // No unit: every wavelength below 30 means µm.
    let t = parse("0.40 0.1\n0.45 0.2\n0.50 0.3\n0.55 0.4\n").unwrap();
    assert!(t.micrometers);
    let c = centers(&t);
    for (got, want) in c.iter().zip([400.0, 450.0, 500.0, 550.0]) {
        assert!((got - want).abs() < 1e-9, "{c:?}");
    }
    // Named in the header, in any of the usual spellings.
    for name in ["wavelength (µm)", "wl_um", "Wavelength [microns]", "λ μm"] {
        let t = parse(&format!("{name},r\n1.2,0.1\n1.3,0.2\n1.4,0.3\n1.5,0.4\n")).unwrap();
        assert!(t.micrometers, "{name}");
        assert!((t.cube.bands[0].center_nm - 1200.0).abs() < 1e-9, "{name}");
    }
    // An explicit nm wins over the rule.
    let t = parse("wavelength_nm,r\n10,0.1\n11,0.2\n12,0.3\n13,0.4\n").unwrap();
    assert!(!t.micrometers);
    assert_eq!(centers(&t), [10.0, 11.0, 12.0, 13.0]);
    // A header without a unit keeps the rule.
    let t = parse("wavelength,r\n2.0,0.1\n2.5,0.2\n3.0,0.3\n3.5,0.4\n").unwrap();
    assert_eq!(centers(&t), [2000.0, 2500.0, 3000.0, 3500.0]);
}

#[test]
fn descending_rows_are_reversed() {
    let t = parse("wl,a,b\n700,7,70\n600,6,60\n500,5,50\n400,4,40\n").unwrap();
    assert_eq!(centers(&t), [400.0, 500.0, 600.0, 700.0]);
    assert_eq!(spectrum(&t, 0), [4.0, 5.0, 6.0, 7.0]);
    assert_eq!(spectrum(&t, 1), [40.0, 50.0, 60.0, 70.0]);
}

#[test]
fn nan_cells_are_missing_values() {
    let t = parse("wl,a,b,c\n400,nan,1,1\n410,NaN,1,\n420,1,NAN,1\n430,1,1,1\n").unwrap();
    let nan = |x: usize| -> Vec<bool> { spectrum(&t, x).iter().map(|v| v.is_nan()).collect() };
    assert_eq!(nan(0), [true, true, false, false]);
    assert_eq!(nan(1), [false, false, true, false]);
    assert_eq!(nan(2), [false, true, false, false]);
}

#[test]
fn errors_name_the_line() {
    // Ragged rows.
    assert_error(
        "wl,a,b\n400,1,2\n410,1\n420,1,2\n430,1,2\n",
        &["line 3", "2 cells", "line 1 has 3"],
    );
    assert_error(
        "400 1 2\n410 1 2\n# c\n420 1 2 3\n430 1 2\n",
        &["line 4", "4 cells"],
    );
    // A value that is no number.
    assert_error(
        "wl,a,b\n400,1,2\n410,1,2\n420,1,abc\n430,1,2\n",
        &["line 4", "\"abc\"", "column 3"],
    );
    // A wavelength that is no number (after the header).
    assert_error(
        "wl,a\n400,1\nfoo,1\n420,1\n430,1\n",
        &["line 3", "wavelength \"foo\""],
    );
    assert_error("wl,a\n400,1\n,1\n420,1\n430,1\n", &["line 3", "wavelength"]);
    assert_error(
        "wl,a\n400,1\ninf,1\n420,1\n430,1\n",
        &["line 3", "wavelength"],
    );
    // Repeated and unordered wavelengths.
    assert_error(
        "wl,a\n400,1\n410,1\n410,2\n430,1\n",
        &["line 4", "repeats line 3"],
    );
    assert_error(
        "wl,a\n400,1\n410,1\n405,1\n430,1\n",
        &["line 4", "strictly increasing"],
    );
    assert_error(
        "wl,a\n500,1\n490,1\n495,1\n480,1\n",
        &["line 4", "strictly decreasing"],
    );
    // Wavelengths no band can have.
    assert_error(
        "wl,a\n-1,1\n410,1\n420,1\n430,1\n",
        &["line 2", "band centre"],
    );
    assert_error("0 1\n1 1\n2 1\n3 1\n", &["line 1", "band centre"]);
    // No spectrum column.
    assert_error("wavelength\n400\n410\n", &["line 1", "no spectrum column"]);
    assert_error(
        "# c\n400\n410\n420\n430\n",
        &["line 2", "no spectrum column"],
    );
    // A wavenumber axis.
    assert_error(
        "wavenumber (cm-1),a\n25000,1\n24000,1\n23000,1\n22000,1\n",
        &["line 1", "wavenumbers"],
    );
    // Binary data.
    assert_error("wl,a\n400,1\n41\u{0}0,1\n", &["line 3", "binary"]);
}

#[test]
fn errors_about_the_whole_file() {
    assert_error(
        "wl,a\n400,1\n410,1\n420,1\n",
        &["3 data rows", "at least 4"],
    );
    assert_error("# only comments\n\n", &["no data"]);
    assert_error("", &["no data"]);
    let e = read_table(Path::new("/nonexistent/x.csv"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("/nonexistent/x.csv"), "{e}");
}

#[test]
fn size_limits_refuse_before_allocating() {
    // Too many spectra: refused at the header line.
    let mut header = String::from("wl");
    for i in 0..=MAX_SPECTRA {
        header.push_str(&format!(",s{i}"));
    }
    assert_error(&format!("{header}\n400,1\n"), &["line 1", "too many"]);
    // Too many rows: refused at the first row past the limit.
    let mut text = String::from("wl,a\n");
    for i in 0..=MAX_ROWS {
        text.push_str(&format!("{},1\n", 100 + i));
    }
    assert_error(
        &text,
        &[&format!("line {}", MAX_ROWS + 2), "more than 100000 rows"],
    );
}

/// A table at 400, 401, …, 410 nm with two spectra.
fn fine_table() -> SpectrumTable {
    let mut text = String::from("wl,a,b\n");
    for i in 0..=10 {
        let b = if i == 2 {
            "nan".to_string()
        } else {
            (10 * i).to_string()
        };
        text.push_str(&format!("{},{},{}\n", 400 + i, i * i, b));
    }
    parse(&text).unwrap()
}

#[test]
fn resampling_averages_the_rows_within_half_a_step() {
    let t = fine_table();
    let r = t.resample(&[402.0, 404.0, 409.5, 420.0], 2.0).unwrap();
    assert_eq!(r.names, t.names);
    assert_eq!(centers(&r), [402.0, 404.0, 409.5, 420.0]);
    assert!(r.cube.bands.iter().all(|b| b.fwhm_nm == 2.0));
    let a = spectrum(&r, 0);
    let b = spectrum(&r, 1);
    // 402 ± 1: rows 401, 402, 403 (ends included): a = 1, 4, 9.
    assert_eq!(a[0], (1.0 + 4.0 + 9.0) / 3.0);
    // b at 402 is missing: the mean of the other two, 10 and 30.
    assert_eq!(b[0], 20.0);
    // 404 ± 1: rows 403, 404, 405.
    assert_eq!(a[1], (9.0 + 16.0 + 25.0) / 3.0);
    assert_eq!(b[1], 40.0);
    // 409.5 ± 1: rows 409 and 410.
    assert_eq!(a[2], (81.0 + 100.0) / 2.0);
    assert_eq!(b[2], 95.0);
    // Nothing within 420 ± 1.
    assert!(a[3].is_nan() && b[3].is_nan());
    // A wider band: 405 ± 2.5 takes 403..=407.
    let w = t.resample(&[405.0], 5.0).unwrap();
    assert_eq!(spectrum(&w, 0)[0], (9.0 + 16.0 + 25.0 + 36.0 + 49.0) / 5.0);
    assert!(t.resample(&[405.0], 0.0).is_err());
}

#[test]
fn range_selection_and_empty_bands() {
    let t = fine_table();
    let s = t.select_range(402.5, 406.0);
    assert_eq!(centers(&s), [403.0, 404.0, 405.0, 406.0]);
    assert_eq!(spectrum(&s, 0), [9.0, 16.0, 25.0, 36.0]);
    assert_eq!(s.wavelength_range(), (403.0, 406.0));
    let mut r = t.resample(&[380.0, 402.0, 404.0, 420.0], 2.0).unwrap();
    assert_eq!(r.drop_empty_bands(), 2);
    assert_eq!(centers(&r), [402.0, 404.0]);
    assert_eq!(spectrum(&r, 1), [20.0, 40.0]);
}
