//! `irid render` of a map: the picture read back pixel by pixel (a valid
//! pixel is the colormap at its value, an invalid one its reason's colour),
//! its size, the legend present only for reasons present; `irid fit --png`
//! writes the preview; bad input is an error, not a panic.

mod cli_common;
use cli_common::{fails_with, ok, s};
use irid::io::exr_maps::{write_channels, Channels};
use irid::render::canvas::decode_png;
use irid::render::map::{reason_colour, render_map, viridis, MapStyle};

/// A 40 × 6 map: thickness 100 + 10·x nm; pixel (5, 2) poor fit, (7, 3)
/// no fringe, both invalid with NaN values.
fn map() -> Channels {
    let (w, h) = (40, 6);
    let mut t = Vec::new();
    let mut valid = Vec::new();
    let mut reason = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let bad = match (x, y) {
                (5, 2) => Some(7.0),
                (7, 3) => Some(5.0),
                _ => None,
            };
            t.push(if bad.is_some() {
                f32::NAN
            } else {
                100.0 + 10.0 * x as f32
            });
            valid.push(if bad.is_some() { 0.0 } else { 1.0 });
            reason.push(bad.unwrap_or(0.0));
        }
    }
    Channels {
        width: w,
        height: h,
        channels: vec![
            ("thickness_nm".into(), t),
            ("valid".into(), valid),
            ("reason".into(), reason),
        ],
        attributes: vec![("irid.units.thickness_nm".into(), "nm".into())],
    }
}

fn style(range: Option<(f64, f64)>) -> MapStyle {
    MapStyle {
        channel: "thickness_nm".into(),
        range,
        title: "test".into(),
    }
}

#[test]
fn valid_pixels_follow_viridis_and_invalid_ones_their_reason() {
    let pic = render_map(&map(), &style(None)).unwrap();
    // The automatic range is the valid values' extent: 100..490 nm.
    assert_eq!(pic.range, (100.0, 490.0));
    for (x, y) in [(0, 0), (13, 4), (39, 5), (20, 1)] {
        let (px, py) = pic.map_pixel(x, y);
        let t = (10.0 * x as f64) / 390.0;
        assert_eq!(
            pic.image.get(px, py),
            Some(viridis(t)),
            "map pixel ({x}, {y})"
        );
    }
    let (px, py) = pic.map_pixel(5, 2);
    assert_eq!(pic.image.get(px, py), Some(reason_colour(7)));
    let (px, py) = pic.map_pixel(7, 3);
    assert_eq!(pic.image.get(px, py), Some(reason_colour(5)));
    assert!((pic.valid_fraction - 238.0 / 240.0).abs() < 1e-12);
    // Viridis ends: dark purple at the low end, yellow at the high end.
    assert_eq!(viridis(0.0), [68, 1, 84]);
    assert_eq!(viridis(1.0), [253, 231, 37]);
}

#[test]
fn a_given_range_clamps_and_the_reason_colours_never_occur_in_viridis() {
    let pic = render_map(&map(), &style(Some((200.0, 300.0)))).unwrap();
    let at = |x, y| {
        let (px, py) = pic.map_pixel(x, y);
        pic.image.get(px, py).unwrap()
    };
    assert_eq!(at(0, 0), viridis(0.0), "100 nm is below the range");
    assert_eq!(at(39, 0), viridis(1.0), "490 nm is above it");
    assert_eq!(at(15, 0), viridis(0.5), "250 nm is the middle");
    // Every reason colour is far from every viridis colour, so an invalid
    // pixel is never mistaken for a value.
    for code in 1..=12u8 {
        let c = reason_colour(code);
        let nearest = (0..=1000)
            .map(|i| {
                let v = viridis(i as f64 / 1000.0);
                (0..3)
                    .map(|k| (c[k] as i32 - v[k] as i32).abs())
                    .sum::<i32>()
            })
            .min()
            .unwrap();
        assert!(
            nearest > 40,
            "reason {code} colour {c:?} is {nearest} from viridis"
        );
    }
}

#[test]
fn the_picture_has_a_colour_bar_and_a_legend_for_the_reasons_present() {
    let pic = render_map(&map(), &style(None)).unwrap();
    let img = &pic.image;
    // The map is enlarged by a whole factor: 40 px → 17 × 40 = 680 px.
    assert_eq!(pic.scale, 17.0);
    // The colour bar: right of the map, yellow at its top, purple at its foot.
    let bar_x = pic.origin.0 + 680 + 20 + 10;
    let top = img.get(bar_x, pic.origin.1).unwrap();
    let foot_y = (pic.origin.1..img.height)
        .rev()
        .find(|y| img.get(bar_x, *y).unwrap() != [255, 255, 255])
        .unwrap();
    let foot = img.get(bar_x, foot_y).unwrap();
    assert!(top[0] > 240 && top[1] > 220, "bar top {top:?}");
    assert!(foot[0] < 80 && foot[2] > 70, "bar foot {foot:?}");
    // Two legend swatches, below the map, in the two reasons' colours.
    let below = pic.origin.1 + (6.0 * pic.scale) as usize;
    let swatch_rows: Vec<[u8; 3]> = (below..img.height)
        .filter_map(|y| img.get(pic.origin.0 + 7, y))
        .filter(|c| *c == reason_colour(7) || *c == reason_colour(5))
        .collect();
    assert!(swatch_rows.contains(&reason_colour(5)) && swatch_rows.contains(&reason_colour(7)));
    // Text was drawn (title, ticks, legend): dark anti-aliased pixels
    // outside the map.
    let dark_above = (0..pic.origin.1)
        .flat_map(|y| (0..img.width).map(move |x| (x, y)))
        .filter(|(x, y)| img.get(*x, *y).unwrap().iter().all(|v| *v < 100))
        .count();
    assert!(dark_above > 50, "title: {dark_above} dark pixels");
}

#[test]
fn the_reason_channel_is_categorical() {
    let mut st = style(None);
    st.channel = "reason".into();
    let pic = render_map(&map(), &st).unwrap();
    let at = |x, y| {
        let (px, py) = pic.map_pixel(x, y);
        pic.image.get(px, py).unwrap()
    };
    assert_eq!(at(0, 0), reason_colour(0));
    assert_eq!(at(5, 2), reason_colour(7));
}

#[test]
fn cli_renders_an_exr_to_a_png_of_the_right_size() {
    let dir = tempfile::tempdir().unwrap();
    let exr = dir.path().join("m.exr");
    write_channels(&exr, &map()).unwrap();
    let png = dir.path().join("m.png");
    ok(&["render", s(&exr), "--out", s(&png), "--range", "100:490"]);
    let img = decode_png(&std::fs::read(&png).unwrap()).unwrap();
    let direct = render_map(&map(), &style(Some((100.0, 490.0)))).unwrap();
    assert_eq!(
        (img.width, img.height),
        (direct.image.width, direct.image.height)
    );
    let (px, py) = direct.map_pixel(13, 4);
    assert_eq!(img.get(px, py), Some(viridis(130.0 / 390.0)));
}

#[test]
fn cli_bad_input_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let exr = dir.path().join("m.exr");
    write_channels(&exr, &map()).unwrap();
    let png = dir.path().join("m.png");
    fails_with(
        &["render", s(&exr), "--out", s(&png), "--channel", "n_film"],
        &["no channel `n_film`"],
    );
    fails_with(
        &["render", s(&exr), "--out", s(&png), "--range", "5:1"],
        &["range", "LO < HI"],
    );
    let junk = dir.path().join("junk.exr");
    std::fs::write(&junk, b"not an exr").unwrap();
    fails_with(&["render", s(&junk), "--out", s(&png)], &["junk.exr"]);
    assert!(!png.exists());
}

#[test]
fn fit_png_writes_the_preview_beside_the_map_and_no_progress_bar_when_piped() {
    let dir = tempfile::tempdir().unwrap();
    let cube = dir.path().join("cube.hdr");
    let exr = dir.path().join("maps.exr");
    let scene =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes/paper-cylinder.toml");
    ok(&["synth", "--out", s(&cube)]);
    let out = ok(&[
        "fit",
        s(&cube),
        "--out",
        s(&exr),
        "--scene",
        s(&scene),
        "--png",
    ]);
    // stderr is a pipe here: the summary only, no bar (no carriage
    // returns or escape sequences).
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains('\r') && !err.contains('\u{1b}'), "{err:?}");
    let png = dir.path().join("maps.png");
    let got = decode_png(&std::fs::read(&png).unwrap()).unwrap();
    // The preview is `irid render`'s thickness picture of that file.
    let c = irid::io::exr_maps::read_channels(&exr).unwrap();
    let want = render_map(
        &c,
        &MapStyle {
            channel: "thickness_nm".into(),
            range: None,
            title: "film thickness: maps.exr".into(),
        },
    )
    .unwrap();
    assert_eq!(got, want.image);
    let csv = dir.path().join("r.csv");
    fails_with(
        &[
            "fit",
            s(&cube),
            "--out",
            s(&csv),
            "--scene",
            s(&scene),
            "--png",
        ],
        &["--png", "OpenEXR"],
    );
}
