//! The film's colour: a fitted map re-synthesised to spectra with irid's
//! optical model and rendered beside the measured cube (the paper's
//! Fig. 6), the spectral RMSE between the two, and a chart of a film's
//! colour against thickness and angle.
//!
//! Both panels of the comparison are rendered the same way from the same
//! bands (see [`super::colour`]: linear between band centres, held beyond),
//! so a difference in colour is a difference in spectra. The re-synthesis
//! uses each valid pixel's thickness, angle and film index (a film known to
//! the scene as a dispersive material keeps its dispersion), the scene's
//! ambient, substrate and polarisation, and integrates each band's passband
//! as `irid synth` does. It assumes an absolute level (no gain/offset
//! correction of the instrument).

use super::canvas::{font, RgbImage};
use super::colour::{xyz_to_srgb8, Cie};
use super::RenderError;
use crate::estimate::{Cube, ParamMaps};
use crate::optics::{airy, Media, Polarization};
use crate::scene::{FilmKnowledge, Scene};
use num_complex::Complex64;
use plotters::prelude::*;

/// The optical media of a scene at one wavelength, with the film's index
/// given (`n_film`) unless the scene knows its dispersion.
fn media_at(scene: &Scene, lam: f64, n_film: f64) -> Result<Media, RenderError> {
    let bad = |what: &str, e: crate::optics::dispersion::OpticsError| {
        RenderError::input(format!("{what} index at {lam} nm: {e}"))
    };
    let n1 = scene.ambient.index_at(lam).map_err(|e| bad("ambient", e))?;
    let n3 = scene
        .substrate
        .index_at(lam)
        .map_err(|e| bad("substrate", e))?;
    let n2 = match &scene.film {
        FilmKnowledge::Known(d) => d.index_at(lam).map_err(|e| bad("film", e))?,
        FilmKnowledge::Unknown { .. } => Complex64::new(n_film, 0.0),
    };
    Ok(Media { n1, n2, n3 })
}

/// The map's parameters turned back into a reflectance cube on `cube`'s
/// bands (NaN at invalid pixels).
pub fn resynthesise(maps: &ParamMaps, cube: &Cube, scene: &Scene) -> Result<Cube, RenderError> {
    if (maps.width, maps.height) != (cube.width, cube.height) {
        return Err(RenderError::input(format!(
            "the map is {} × {} pixels but the cube {} × {}",
            maps.width, maps.height, cube.width, cube.height
        )));
    }
    let mut out = Cube::zeros(cube.width, cube.height, cube.bands.clone());
    let pol = scene.polarization;
    for (b, band) in cube.bands.iter().enumerate() {
        let nodes: Vec<(f64, f64)> = if band.fwhm_nm > 0.0 {
            band.nodes().to_vec()
        } else {
            vec![(band.center_nm, 1.0)]
        };
        let plane = out.plane_mut(b);
        for (i, o) in plane.iter_mut().enumerate() {
            let (d, th, n) = (
                maps.thickness_nm[i] as f64,
                (maps.theta_deg[i] as f64).to_radians(),
                maps.n_film[i] as f64,
            );
            *o = if maps.valid[i] > 0.5 && d.is_finite() && th.is_finite() {
                let mut r = 0.0;
                for &(lam, w) in &nodes {
                    r += w * airy::reflectance(media_at(scene, lam, n)?, d.max(0.0), th, lam, pol);
                }
                r as f32
            } else {
                f32::NAN
            };
        }
    }
    Ok(out)
}

/// RMS of measured − re-synthesised over every band of every pixel where
/// both are finite, and the number of pixels that counted.
pub fn spectral_rmse(measured: &Cube, synth: &Cube) -> (f64, usize) {
    let n = measured.plane_len();
    let mut sum = 0.0;
    let mut count = 0usize;
    let mut pixels = 0usize;
    let mut a = vec![0.0; measured.bands.len()];
    let mut b = vec![0.0; measured.bands.len()];
    for i in 0..n {
        let (x, y) = (i % measured.width, i / measured.width);
        measured.spectrum_into(x, y, &mut a);
        synth.spectrum_into(x, y, &mut b);
        let before = count;
        for (p, q) in a.iter().zip(&b) {
            if p.is_finite() && q.is_finite() {
                sum += (p - q) * (p - q);
                count += 1;
            }
        }
        pixels += usize::from(count > before);
    }
    let rmse = if count > 0 {
        (sum / count as f64).sqrt()
    } else {
        f64::NAN
    };
    (rmse, pixels)
}

/// Per-pixel XYZ of a cube (None where no band is finite).
pub fn cube_xyz(cube: &Cube) -> Vec<Option<[f64; 3]>> {
    let cie = Cie::get();
    let lams: Vec<f64> = cube.bands.iter().map(|b| b.center_nm).collect();
    let mut s = vec![0.0; lams.len()];
    (0..cube.plane_len())
        .map(|i| {
            cube.spectrum_into(i % cube.width, i / cube.width, &mut s);
            cie.xyz_of_samples(&lams, &s)
        })
        .collect()
}

/// The exposure that brings the 99th-percentile luminance `Y` of `xyz` to
/// 0.9 (films reflect a few per cent: unscaled they would look black).
pub fn auto_exposure(xyz: &[Option<[f64; 3]>]) -> f64 {
    let mut ys: Vec<f64> = xyz
        .iter()
        .flatten()
        .map(|v| v[1])
        .filter(|y| y.is_finite() && *y > 0.0)
        .collect();
    if ys.is_empty() {
        return 1.0;
    }
    ys.sort_by(f64::total_cmp);
    let p99 = ys[((ys.len() - 1) as f64 * 0.99) as usize];
    (0.9 / p99).clamp(1.0, 1000.0)
}

/// Measured and re-synthesised colour side by side.
#[derive(Clone, Debug)]
pub struct Comparison {
    /// The picture.
    pub image: RgbImage,
    /// Spectral RMSE (reflectance) over valid pixels and all bands.
    pub rmse: f64,
    /// Pixels that entered the RMSE.
    pub pixels: usize,
    /// The exposure both panels share.
    pub exposure: f64,
    /// Top-left corners of the measured and re-synthesised panels, and the
    /// picture pixels per map pixel.
    pub panels: [(usize, usize); 2],
    /// Picture pixels per map pixel.
    pub scale: usize,
}

/// Render the comparison picture.
pub fn compare(
    cube: &Cube,
    maps: &ParamMaps,
    scene: &Scene,
    title: &str,
) -> Result<Comparison, RenderError> {
    let synth = resynthesise(maps, cube, scene)?;
    let (rmse, pixels) = spectral_rmse(cube, &synth);
    let meas_xyz = cube_xyz(cube);
    let syn_xyz = cube_xyz(&synth);
    let exposure = auto_exposure(&meas_xyz);
    let (w, h) = (cube.width, cube.height);
    let scale = ((640.0 / w as f64).min(400.0 / h as f64).floor() as usize).max(1);
    let (pw, ph) = (w * scale, h * scale);
    let gap = 20;
    let top = 70;
    let mut img = RgbImage::new((gap + pw) * 2 + gap, top + ph + gap)?;
    let panels = [(gap, top), (2 * gap + pw, top)];
    for (panel, xyz) in panels.iter().zip([&meas_xyz, &syn_xyz]) {
        for (i, v) in xyz.iter().enumerate() {
            // Pixels without a spectrum (invalid fits) in mid grey.
            let c = v.map_or([128, 128, 128], |v| xyz_to_srgb8(v, exposure));
            img.fill(
                panel.0 + (i % w) * scale,
                panel.1 + (i / w) * scale,
                scale,
                scale,
                c,
            );
        }
    }
    img.draw(|root| {
        let e = |e: DrawingAreaErrorKind<_>| e.to_string();
        root.draw(&Text::new(title.to_string(), (gap as i32, 6), font(17.0)))
            .map_err(e)?;
        let sub = format!(
            "sRGB, D65, CIE 1931 2 deg, exposure x{exposure:.2}; spectral RMSE {rmse:.4} over {pixels} pixels"
        );
        root.draw(&Text::new(sub, (gap as i32, 26), font(13.0)))
            .map_err(e)?;
        for (p, label) in panels.iter().zip(["measured", "re-synthesised from the fit"]) {
            root.draw(&Text::new(label, (p.0 as i32, top as i32 - 20), font(14.0)))
                .map_err(e)?;
        }
        Ok(())
    })?;
    Ok(Comparison {
        image: img,
        rmse,
        pixels,
        exposure,
        panels,
        scale,
    })
}

/// A film's colour (the model spectrum over 380–780 nm at 5 nm, with
/// auto exposure) against thickness (x) and angle (y).
pub fn chart(
    scene: &Scene,
    n_film: f64,
    thickness_nm: (f64, f64),
    angle_deg: (f64, f64),
    pol: Polarization,
) -> Result<RgbImage, RenderError> {
    let ok = |(lo, hi): (f64, f64)| lo.is_finite() && hi.is_finite() && lo < hi;
    if !ok(thickness_nm) || thickness_nm.0 < 0.0 || !ok(angle_deg) || angle_deg.1 >= 90.0 {
        return Err(RenderError::input(
            "chart ranges: need 0 ≤ thickness LO < HI and angle LO < HI < 90°",
        ));
    }
    let (nx, ny) = (300usize, 60usize);
    let lams: Vec<f64> = (0..=80).map(|i| 380.0 + 5.0 * i as f64).collect();
    let media: Vec<Media> = lams
        .iter()
        .map(|l| media_at(scene, *l, n_film))
        .collect::<Result<_, _>>()?;
    let cie = Cie::get();
    let mut xyz = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        let th = angle_deg.1 - (angle_deg.1 - angle_deg.0) * (j as f64 + 0.5) / ny as f64;
        for i in 0..nx {
            let d =
                thickness_nm.0 + (thickness_nm.1 - thickness_nm.0) * (i as f64 + 0.5) / nx as f64;
            let r: Vec<f64> = lams
                .iter()
                .zip(&media)
                .map(|(l, m)| airy::reflectance(*m, d, th.to_radians(), *l, pol))
                .collect();
            xyz.push(cie.xyz_of_samples(&lams, &r));
        }
    }
    let exposure = auto_exposure(&xyz);
    let (w, h) = (900u32, 420u32);
    let mut img = RgbImage::new(w as usize, h as usize)?;
    let title = format!(
        "film colour, n = {n_film:.3}: {} (exposure x{exposure:.2})",
        scene.name
    );
    let mut plot_area = (0i32, 0i32, 0i32, 0i32);
    img.draw(|root| {
        let e = |e: DrawingAreaErrorKind<_>| e.to_string();
        let mut ch = ChartBuilder::on(root)
            .caption(title, font(16.0))
            .margin(15)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d(thickness_nm.0..thickness_nm.1, angle_deg.0..angle_deg.1)
            .map_err(e)?;
        ch.configure_mesh()
            .disable_mesh()
            .x_desc("film thickness, nm")
            .y_desc("angle of incidence, degrees")
            .label_style(font(12.0))
            .axis_desc_style(font(13.0))
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| format!("{v:.0}"))
            .draw()
            .map_err(e)?;
        let (xr, yr) = ch.plotting_area().get_pixel_range();
        plot_area = (xr.start, yr.start, xr.end, yr.end);
        Ok(())
    })?;
    let (x0, y0, x1, y1) = plot_area;
    let (pw, ph) = ((x1 - x0).max(1) as usize, (y1 - y0).max(1) as usize);
    for py in 0..ph {
        let j = (py * ny / ph).min(ny - 1);
        for px in 0..pw {
            let i = (px * nx / pw).min(nx - 1);
            let c = xyz[j * nx + i].map_or([128, 128, 128], |v| xyz_to_srgb8(v, exposure));
            img.put(x0 as usize + px, y0 as usize + py, c);
        }
    }
    Ok(img)
}
