//! A synthetic moving web: a film with a known thickness field passing
//! under the camera at a configured speed, seen through the tunable filter.
//!
//! The film's thickness at cross-web pixel `x` of web row `w` is
//! [`WebFilm::thickness_nm`]: a base, a parabolic cross-web profile, streaks
//! (narrow bands of constant offset running along the web), a slow sinusoidal
//! drift along the web and a rectangular defect. The film is constant within
//! a web row, and each sensor row is rendered at the web row the encoder
//! registers it to (so the truth of a row is exact, to the encoder's
//! resolution; a real line blurs sharp edges by up to half a count).
//!
//! Motion: the web advances `speed · frame_period` rows per frame plus a
//! seeded position jitter (uniform within ±`jitter_rows`), with scheduled
//! speed changes and jumps (a web that lurches, an encoder that slips with
//! it); each frame's metadata carries the latched encoder count
//! (`round(position / rows_per_count)`).
//!
//! Like [`super::synthetic::SyntheticCamera`] the camera reads the filter's
//! state from a shared [`FilterView`] (a frame exposed while the filter
//! settles is a blend of two bands; its pass bands can drift mid-run,
//! [`WebCamera::drift_filter`]), converts reflectance to counts
//! (`dark + k·exposure·T(band)·R`), adds Gaussian noise of a given
//! *reflectance* σ, quantises and clips. Reflectance comes from a table per
//! band and distinct incidence angle over the film's thickness range (0.05
//! nm steps, linear interpolation: < 1e-7 in reflectance) of the exact Airy
//! formula. Where the angle depends on the sensor row
//! ([`WebCameraConfig::row_theta_deg`]) each row is rendered at its own
//! angle: `distinct angles × bands × thickness samples` f32s (32 rows × 31
//! bands × ~2000 samples for the demo's film = 8 MB), built once, in
//! parallel. Seeded and on a virtual clock: bit-reproducible.

use super::synthetic::{lctf_transmission, FilterView, LampChange, SensorModel};
use super::{CameraError, CameraInfo, Frame, FrameMeta, FrameSource};
use crate::optics::airy;
use crate::optics::band::Band;
use crate::optics::dispersion::Dispersion;
use crate::optics::{Media, Polarization};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::time::Duration;

/// A streak: a narrow band along the web with its own thickness offset.
#[derive(Clone, Debug, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct Streak {
    /// Centre, as a fraction of the width (0 … 1).
    pub x_frac: f64,
    /// Width, pixels.
    pub width_px: f64,
    /// Thickness offset, nm.
    pub delta_nm: f64,
}

/// A rectangular defect.
#[derive(Clone, Debug, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct Defect {
    /// Cross-web extent, fractions of the width.
    pub x_frac: [f64; 2],
    /// First web row.
    pub row: i64,
    /// Length, web rows.
    pub rows: i64,
    /// Thickness offset, nm.
    pub delta_nm: f64,
}

/// The film's thickness field.
#[derive(Clone, Debug, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct WebFilm {
    /// Thickness at the web's centre line, nm.
    pub base_nm: f64,
    /// Extra thickness at the edges (parabolic cross-web profile), nm.
    #[serde(default)]
    pub edge_nm: f64,
    /// Streaks.
    #[serde(default)]
    pub streaks: Vec<Streak>,
    /// Amplitude of the slow drift along the web, nm.
    #[serde(default)]
    pub drift_nm: f64,
    /// Period of the drift, web rows.
    #[serde(default = "default_period")]
    pub drift_period_rows: f64,
    /// A defect.
    #[serde(default)]
    pub defect: Option<Defect>,
}

fn default_period() -> f64 {
    2000.0
}

impl WebFilm {
    /// Thickness, nm, at pixel `x` of a `width`-pixel web, web row `w`.
    pub fn thickness_nm(&self, x: usize, width: usize, w: i64) -> f64 {
        let u = if width > 1 {
            2.0 * x as f64 / (width - 1) as f64 - 1.0
        } else {
            0.0
        };
        let mut d = self.base_nm + self.edge_nm * u * u;
        for s in &self.streaks {
            if (x as f64 - s.x_frac * width as f64).abs() <= s.width_px / 2.0 {
                d += s.delta_nm;
            }
        }
        if self.drift_period_rows > 0.0 {
            d += self.drift_nm * (std::f64::consts::TAU * w as f64 / self.drift_period_rows).sin();
        }
        if let Some(f) = &self.defect {
            let xf = x as f64 / width.max(1) as f64;
            if w >= f.row && w < f.row + f.rows && xf >= f.x_frac[0] && xf < f.x_frac[1] {
                d += f.delta_nm;
            }
        }
        d
    }

    /// The thinnest and thickest film anywhere, nm (for tables).
    pub fn range_nm(&self) -> (f64, f64) {
        let streak: f64 = self.streaks.iter().map(|s| s.delta_nm.abs()).sum();
        let defect = self.defect.as_ref().map_or(0.0, |d| d.delta_nm.abs());
        let spread = self.edge_nm.abs() + streak + self.drift_nm.abs() + defect;
        ((self.base_nm - spread).max(0.0), self.base_nm + spread)
    }
}

/// How the web moves and how the camera sees it.
#[derive(Clone, Debug)]
pub struct WebCameraConfig {
    /// Pixels across the web.
    pub width: u32,
    /// Sensor rows along the web.
    pub rows_in_view: u32,
    /// Web speed, rows/s.
    pub speed_rows_per_s: f64,
    /// Speed changes: from frame `seq` on, this speed (rows/s).
    pub speed_changes: Vec<(u64, f64)>,
    /// Jumps: before frame `seq`, the web lurches this many rows.
    pub jumps: Vec<(u64, f64)>,
    /// Web rows per encoder count.
    pub rows_per_count: f64,
    /// Position jitter, ± web rows (uniform).
    pub jitter_rows: f64,
    /// Reflectance noise σ.
    pub noise_sigma: f64,
    /// Sensor (format, dark, gain, exposure, frame period).
    pub sensor: SensorModel,
    /// Incidence angle, degrees.
    pub theta_deg: f64,
    /// Incidence angle of each sensor row, degrees (empty: every row at
    /// `theta_deg`).
    pub row_theta_deg: Vec<f64>,
    /// Polarisation.
    pub polarization: Polarization,
    /// Seed.
    pub seed: u64,
    /// Pace frames to the wall clock, this many times faster (0: no pacing).
    pub realtime_speed: f64,
}

/// Errors building the camera.
#[derive(Debug, thiserror::Error)]
pub enum WebCameraError {
    /// A medium cannot be evaluated.
    #[error("{medium} at {wavelength_nm} nm: {message}")]
    Optics {
        /// Which medium.
        medium: &'static str,
        /// Where.
        wavelength_nm: f64,
        /// What went wrong.
        message: String,
    },
    /// A bad setting.
    #[error("web camera: {0}")]
    Config(String),
}

/// Reflectance against thickness for one band.
struct Table {
    d0: f64,
    inv_step: f64,
    r: Vec<f32>,
}

impl Table {
    fn at(&self, d: f64) -> f32 {
        let t = ((d - self.d0) * self.inv_step).max(0.0);
        let i = (t as usize).min(self.r.len().saturating_sub(2));
        let f = (t - i as f64).clamp(0.0, 1.0) as f32;
        self.r[i] * (1.0 - f) + self.r[i + 1] * f
    }
}

/// The moving-web camera.
pub struct WebCamera {
    cfg: WebCameraConfig,
    film: WebFilm,
    bands: Vec<Band>,
    /// Per distinct angle, per band: `tables[a · bands + b]`.
    tables: Vec<Table>,
    /// The same through a drifted filter, and the frame from which on
    /// ([`WebCamera::drift_filter`]).
    drifted: Option<(u64, Vec<Table>)>,
    /// Ambient, film and substrate, and the distinct angles, degrees (the
    /// tables are built again for a drifted filter).
    media: [Dispersion; 3],
    angles: Vec<f64>,
    /// Each sensor row's angle (index into the distinct angles).
    row_angle: Vec<usize>,
    filter: FilterView,
    rng: ChaCha8Rng,
    seq: u64,
    /// True web position (rows) without jitter.
    pos: f64,
    /// Thickness of the rows in view, per frame (scratch).
    thick: Vec<f64>,
    started: Option<(std::time::Instant, u64)>,
    /// A change of the light, and the frame it was set at.
    lamp: Option<(u64, LampChange)>,
}

const TABLE_STEP_NM: f64 = 0.05;

impl WebCamera {
    /// A camera over `film` (media `ambient`, `film_index`, `substrate`) in
    /// these bands, looking through `filter`.
    pub fn new(
        cfg: WebCameraConfig,
        film: WebFilm,
        media: [&Dispersion; 3],
        bands: &[Band],
        filter: FilterView,
    ) -> Result<WebCamera, WebCameraError> {
        if cfg.width == 0 || cfg.rows_in_view == 0 {
            return Err(WebCameraError::Config("empty frame".into()));
        }
        if !(cfg.rows_per_count.is_finite() && cfg.rows_per_count > 0.0) {
            return Err(WebCameraError::Config(format!(
                "rows per count must be positive, got {}",
                cfg.rows_per_count
            )));
        }
        let (lo, hi) = film.range_nm();
        let n = ((hi - lo) / TABLE_STEP_NM).ceil() as usize + 2;
        if n > 2_000_000 {
            return Err(WebCameraError::Config(format!(
                "film thickness range {lo:.0}–{hi:.0} nm is too wide to tabulate"
            )));
        }
        let h = cfg.rows_in_view as usize;
        if !(cfg.row_theta_deg.is_empty() || cfg.row_theta_deg.len() == h) {
            return Err(WebCameraError::Config(format!(
                "{} incidence angles for {h} sensor rows",
                cfg.row_theta_deg.len()
            )));
        }
        // Distinct angles (bit for bit), each row pointing at its own.
        let row_deg: Vec<f64> = if cfg.row_theta_deg.is_empty() {
            vec![cfg.theta_deg; h]
        } else {
            cfg.row_theta_deg.clone()
        };
        let mut angles: Vec<f64> = Vec::new();
        let row_angle: Vec<usize> = row_deg
            .iter()
            .map(
                |&t| match angles.iter().position(|a| a.to_bits() == t.to_bits()) {
                    Some(i) => i,
                    None => {
                        angles.push(t);
                        angles.len() - 1
                    }
                },
            )
            .collect();
        let media = [media[0].clone(), media[1].clone(), media[2].clone()];
        let tables = tabulate(bands, &media, &angles, (lo, n), cfg.polarization)?;
        let px = cfg.width as usize * cfg.rows_in_view as usize;
        Ok(WebCamera {
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            cfg,
            film,
            bands: bands.to_vec(),
            tables,
            drifted: None,
            media,
            angles,
            row_angle,
            filter,
            seq: 0,
            pos: 0.0,
            thick: vec![0.0; px],
            started: None,
            lamp: None,
        })
    }

    /// Change the light from the next frame on, after the line's
    /// calibration (None: the light stays as it is now).
    pub fn set_lamp(&mut self, change: Option<LampChange>) {
        self.lamp = change.map(|c| (self.seq, c));
    }

    /// The filter's pass bands drift (with temperature, say) by `shift_nm`
    /// from `after_frames` frames on: each band's frames are rendered at
    /// its centre plus the shift, while the controller and the metadata
    /// still name the nominal one.
    pub fn drift_filter(&mut self, after_frames: u64, shift_nm: f64) -> Result<(), WebCameraError> {
        let moved: Vec<Band> = self
            .bands
            .iter()
            .map(|b| Band {
                center_nm: b.center_nm + shift_nm,
                ..*b
            })
            .collect();
        let lo = self.tables.first().map_or(0.0, |t| t.d0);
        let n = self.tables.first().map_or(2, |t| t.r.len());
        let tables = tabulate(
            &moved,
            &self.media,
            &self.angles,
            (lo, n),
            self.cfg.polarization,
        )?;
        self.drifted = Some((self.seq + after_frames, tables));
        Ok(())
    }

    /// The film.
    pub fn film(&self) -> &WebFilm {
        &self.film
    }

    /// The true thickness of web row `w` (encoder count × rows per count,
    /// rounded), nm.
    pub fn truth_row(&self, w: i64, out: &mut Vec<f64>) {
        let width = self.cfg.width as usize;
        out.clear();
        out.extend((0..width).map(|x| self.film.thickness_nm(x, width, w)));
    }

    /// Dark and white (R = 1) reference planes, band-sequential, without
    /// noise: the calibration that turns this camera's counts into
    /// reflectance exactly.
    pub fn reference_planes(&self) -> (Vec<f32>, Vec<f32>) {
        let n = self.cfg.width as usize * self.cfg.rows_in_view as usize;
        let s = &self.cfg.sensor;
        let k = s.counts_per_us * f64::from(s.exposure_us);
        let mut dark = Vec::with_capacity(n * self.bands.len());
        let mut white = Vec::with_capacity(n * self.bands.len());
        for b in &self.bands {
            dark.extend(std::iter::repeat_n(s.dark_offset as f32, n));
            let wv = s.dark_offset + k * lctf_transmission(b.center_nm);
            white.extend(std::iter::repeat_n(wv as f32, n));
        }
        (dark, white)
    }

    fn band_of(&self, nm: Option<f64>) -> Option<usize> {
        let nm = nm?;
        self.bands
            .iter()
            .position(|b| (b.center_nm - nm).abs() < 0.5)
    }

    fn speed_at(&self, seq: u64) -> f64 {
        self.cfg
            .speed_changes
            .iter()
            .filter(|(s, _)| *s <= seq)
            .max_by_key(|(s, _)| *s)
            .map_or(self.cfg.speed_rows_per_s, |&(_, v)| v)
    }

    fn pace(&mut self, t0: u64) {
        if self.cfg.realtime_speed <= 0.0 {
            return;
        }
        let (start, v0) = *self
            .started
            .get_or_insert_with(|| (std::time::Instant::now(), t0));
        let due = start + Duration::from_secs_f64((t0 - v0) as f64 / 1e9 / self.cfg.realtime_speed);
        let now = std::time::Instant::now();
        if due > now {
            std::thread::sleep(due - now);
        }
    }
}

/// Each band's reflectance over `n` thickness samples from `lo` nm (steps
/// of [`TABLE_STEP_NM`]), per distinct angle (degrees): `[a · bands + b]`.
fn tabulate(
    bands: &[Band],
    media: &[Dispersion; 3],
    angles: &[f64],
    (lo, n): (f64, usize),
    pol: Polarization,
) -> Result<Vec<Table>, WebCameraError> {
    let mut band_nodes = Vec::with_capacity(bands.len());
    for b in bands {
        let points: Vec<(f64, f64)> = if b.fwhm_nm > 0.0 {
            b.nodes().to_vec()
        } else {
            vec![(b.center_nm, 1.0)]
        };
        let mut nodes = Vec::with_capacity(points.len());
        for (lam, wgt) in points {
            let get = |d: &Dispersion, medium| {
                d.index_in_passband(lam, b.center_nm)
                    .map_err(|e| WebCameraError::Optics {
                        medium,
                        wavelength_nm: lam,
                        message: e.to_string(),
                    })
            };
            let m = Media {
                n1: get(&media[0], "ambient")?,
                n2: get(&media[1], "film")?,
                n3: get(&media[2], "substrate")?,
            };
            nodes.push((lam, wgt, m));
        }
        band_nodes.push(nodes);
    }
    let nb = bands.len();
    // Each table on its own: the same values whatever the threads.
    use rayon::prelude::*;
    Ok((0..angles.len() * nb)
        .into_par_iter()
        .map(|i| {
            let theta = angles[i / nb].to_radians();
            let nodes = &band_nodes[i % nb];
            let r = (0..n)
                .map(|j| {
                    let d = lo + j as f64 * TABLE_STEP_NM;
                    nodes
                        .iter()
                        .map(|&(lam, wgt, m)| wgt * airy::reflectance(m, d, theta, lam, pol))
                        .sum::<f64>() as f32
                })
                .collect();
            Table {
                d0: lo,
                inv_step: 1.0 / TABLE_STEP_NM,
                r,
            }
        })
        .collect())
}

impl FrameSource for WebCamera {
    fn info(&self) -> CameraInfo {
        CameraInfo {
            id: format!("synthetic web seed={}", self.cfg.seed),
            width: self.cfg.width,
            height: self.cfg.rows_in_view,
            format: self.cfg.sensor.format,
            exposure_us: self.cfg.sensor.exposure_us,
            gain: 1.0,
        }
    }

    fn next_frame(&mut self, out: &mut Frame, _timeout: Duration) -> Result<(), CameraError> {
        let (w, h) = (self.cfg.width as usize, self.cfg.rows_in_view as usize);
        let n = w * h;
        if out.data.len() < n {
            return Err(CameraError::BufferTooSmall {
                have: out.data.len(),
                need: n,
            });
        }
        let seq = self.seq;
        self.seq += 1;
        let period = self.cfg.sensor.frame_period_ns;
        let t0 = seq * period;
        self.pace(t0);
        if seq > 0 {
            self.pos += self.speed_at(seq) * period as f64 * 1e-9;
        }
        for &(s, rows) in &self.cfg.jumps {
            if s == seq {
                self.pos += rows;
            }
        }
        let j = self.cfg.jitter_rows;
        let jitter = if j > 0.0 {
            self.rng.random_range(-j..=j)
        } else {
            0.0
        };
        let rpc = self.cfg.rows_per_count;
        let count = ((self.pos + jitter) / rpc).round() as i64;
        let first = (count as f64 * rpc).round() as i64;
        for y in 0..h {
            for x in 0..w {
                self.thick[y * w + x] = self.film.thickness_nm(x, w, first + y as i64);
            }
        }
        let s = &self.cfg.sensor;
        let exposure_ns = u64::from(s.exposure_us) * 1000;
        let tr = self.filter.get();
        let alpha = tr.progress(t0 + exposure_ns / 2);
        let (a, b) = (self.band_of(tr.from_nm), self.band_of(tr.to_nm));
        let light = self
            .lamp
            .map_or(1.0, |(set, c)| c.light_at(seq.saturating_sub(set)));
        let k = light * s.counts_per_us * f64::from(s.exposure_us);
        let gain =
            |i: Option<usize>| i.map_or(0.0, |i| k * lctf_transmission(self.bands[i].center_nm));
        let (ga, gb) = (gain(a) * (1.0 - alpha), gain(b) * alpha);
        let sigma_counts = self.cfg.noise_sigma * (ga + gb);
        let max = f64::from(s.format.max_value());
        let dark = s.dark_offset;
        let nb = self.bands.len();
        let tables = match &self.drifted {
            Some((from, t)) if seq >= *from => t,
            _ => &self.tables,
        };
        for (y, (orow, drow)) in out.data[..n]
            .chunks_exact_mut(w)
            .zip(self.thick.chunks_exact(w))
            .enumerate()
        {
            let base = self.row_angle[y] * nb;
            let (ta, tb) = (a.map(|i| &tables[base + i]), b.map(|i| &tables[base + i]));
            for (o, &d) in orow.iter_mut().zip(drow) {
                let ra = ta.map_or(0.0, |t| f64::from(t.at(d)));
                let rb = tb.map_or(0.0, |t| f64::from(t.at(d)));
                let z: f64 = StandardNormal.sample(&mut self.rng);
                let v = dark + ga * ra + gb * rb + z * sigma_counts;
                *o = (v.clamp(0.0, max) + 0.5).min(max) as u16;
            }
        }
        out.meta = FrameMeta {
            seq,
            timestamp_ns: t0,
            exposure_us: s.exposure_us,
            gain: 1.0,
            format: s.format,
            width: self.cfg.width,
            height: self.cfg.rows_in_view,
            trigger: None,
            encoder: Some(count),
        };
        Ok(())
    }

    fn set_exposure(&mut self, exposure_us: u32) -> Result<u32, CameraError> {
        let max_us = (self.cfg.sensor.frame_period_ns / 1000) as u32;
        self.cfg.sensor.exposure_us = exposure_us.clamp(1, max_us.max(1));
        Ok(self.cfg.sensor.exposure_us)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn film_field_has_its_features() {
        let f = WebFilm {
            base_nm: 300.0,
            edge_nm: 20.0,
            streaks: vec![Streak {
                x_frac: 0.25,
                width_px: 3.0,
                delta_nm: 5.0,
            }],
            drift_nm: 4.0,
            drift_period_rows: 400.0,
            defect: Some(Defect {
                x_frac: [0.5, 0.6],
                row: 100,
                rows: 10,
                delta_nm: 30.0,
            }),
        };
        let w = 101;
        assert!((f.thickness_nm(50, w, 0) - 300.0).abs() < 1e-9);
        assert!((f.thickness_nm(0, w, 0) - 320.0).abs() < 1e-9);
        assert!((f.thickness_nm(25, w, 0) - (300.0 + 20.0 * 0.25 + 5.0)).abs() < 1e-9);
        assert!(
            (f.thickness_nm(50, w, 100)
                - (300.0 + 4.0 * (std::f64::consts::TAU / 4.0).sin() + 0.0))
                .abs()
                < 1e-9
        );
        assert!((f.thickness_nm(55, w, 105) - f.thickness_nm(55, w, 95) - 30.0).abs() < 0.5);
        let (lo, hi) = f.range_nm();
        assert!(lo <= 296.0 && hi >= 354.0);
    }

    #[test]
    fn table_matches_the_model() {
        let film = WebFilm {
            base_nm: 400.0,
            edge_nm: 50.0,
            streaks: vec![],
            drift_nm: 0.0,
            drift_period_rows: 1000.0,
            defect: None,
        };
        let air = Dispersion::constant(1.0);
        let f = Dispersion::constant(1.45);
        let sub = Dispersion::constant(1.6);
        let bands = vec![Band::new(500.0, 0.0).unwrap()];
        let cfg = WebCameraConfig {
            width: 8,
            rows_in_view: 4,
            speed_rows_per_s: 10.0,
            speed_changes: vec![],
            jumps: vec![],
            rows_per_count: 0.5,
            jitter_rows: 0.0,
            noise_sigma: 0.0,
            sensor: SensorModel::default(),
            theta_deg: 20.0,
            row_theta_deg: vec![],
            polarization: Polarization::S,
            seed: 1,
            realtime_speed: 0.0,
        };
        let cam = WebCamera::new(cfg, film, [&air, &f, &sub], &bands, FilterView::new()).unwrap();
        let m = Media::real(1.0, 1.45, 1.6);
        for d in [400.0, 412.3456, 449.99] {
            let want = airy::reflectance(m, d, 20f64.to_radians(), 500.0, Polarization::S);
            assert!((f64::from(cam.tables[0].at(d)) - want).abs() < 2e-7, "{d}");
        }
    }

    #[test]
    fn each_sensor_row_is_rendered_at_its_own_angle() {
        let film = WebFilm {
            base_nm: 300.0,
            edge_nm: 0.0,
            streaks: vec![],
            drift_nm: 0.0,
            drift_period_rows: 1000.0,
            defect: None,
        };
        let air = Dispersion::constant(1.0);
        let f = Dispersion::constant(1.45);
        let sub = Dispersion::constant(1.6);
        let bands = vec![
            Band::new(450.0, 0.0).unwrap(),
            Band::new(600.0, 0.0).unwrap(),
        ];
        let rows = vec![20.0, 25.0, 20.0, 35.0];
        let cfg = WebCameraConfig {
            width: 2,
            rows_in_view: 4,
            speed_rows_per_s: 0.0,
            speed_changes: vec![],
            jumps: vec![],
            rows_per_count: 1.0,
            jitter_rows: 0.0,
            noise_sigma: 0.0,
            sensor: SensorModel::default(),
            theta_deg: 30.0,
            row_theta_deg: rows.clone(),
            polarization: Polarization::Unpolarized,
            seed: 1,
            realtime_speed: 0.0,
        };
        let cam = WebCamera::new(
            cfg.clone(),
            film.clone(),
            [&air, &f, &sub],
            &bands,
            FilterView::new(),
        )
        .unwrap();
        // Rows at the same angle share a table.
        assert_eq!(cam.tables.len(), 3 * bands.len());
        let m = Media::real(1.0, 1.45, 1.6);
        for (y, &deg) in rows.iter().enumerate() {
            for (b, band) in bands.iter().enumerate() {
                let t = &cam.tables[cam.row_angle[y] * bands.len() + b];
                let want = airy::reflectance(
                    m,
                    300.0,
                    deg.to_radians(),
                    band.center_nm,
                    Polarization::Unpolarized,
                );
                assert!(
                    (f64::from(t.at(300.0)) - want).abs() < 2e-7,
                    "row {y} band {b}"
                );
            }
        }
        // A list of the wrong length is refused.
        let mut bad = cfg;
        bad.row_theta_deg = vec![20.0; 3];
        let e = WebCamera::new(bad, film, [&air, &f, &sub], &bands, FilterView::new())
            .err()
            .unwrap();
        assert!(
            e.to_string()
                .contains("3 incidence angles for 4 sensor rows"),
            "{e}"
        );
    }
}
