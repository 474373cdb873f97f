//! The synthetic line: a moving-web description (TOML) turned into a
//! camera, an emulated filter and a [`LineSetup`] — shared by the demo
//! (`irid run --scene web`), the tests and the benchmark.
//!
//! File format (`data/scenes/web.toml`): `scene` (optics and bands, a scene
//! file relative to this one), `recipe` (optional, see
//! [`super::recipe`]), `[camera]` (`width`, `rows_in_view`,
//! `frame_period_ms`, `exposure_ms`, and the incidence angle per sensor
//! row: `angle_deg_per_row` — a slope around the scene's `[angle] deg` —
//! or `angles_deg`, one per sensor row), `[filter]` (`settle_ms`,
//! `settle_jitter_ms`), `[web]` (`speed_fraction` of the highest speed the
//! optics allow, or `speed_rows_per_s`; `rows_per_count`, `jitter_rows`,
//! `seed`), `[film]` ([`WebFilm`]) and `[line]` (`segment_rows`, `lanes`,
//! `mqtt` = `"host:port"`).

use super::geometry::{stepped_band_rate, LineGeometry, Motion};
use super::run::LineSetup;
use super::LineError;
use crate::device::camera::synthetic::{FilterView, SensorModel};
use crate::device::camera::web::{WebCamera, WebCameraConfig, WebFilm};
use crate::estimate::Mode;
use crate::pipeline::calibration::{CalMeta, Calibration, Calibrator};
use crate::pipeline::sequencer::EmulatedTuner;
use crate::scene::{AngleKnowledge, FilmKnowledge, Scene};
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// `[camera]`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// Pixels across the web.
    pub width: u32,
    /// Sensor rows along the web.
    pub rows_in_view: u32,
    /// Frame period, ms.
    pub frame_period_ms: f64,
    /// Exposure, ms.
    pub exposure_ms: f64,
    /// The incidence angle's change per sensor row, degrees: sensor row `s`
    /// sees the web at `θ_c + (s − (rows_in_view − 1)/2) · slope`, θ_c the
    /// scene's `[angle] deg` (default 0: every row at θ_c).
    #[serde(default)]
    pub angle_deg_per_row: Option<f64>,
    /// The incidence angle of each sensor row, degrees (instead of the
    /// slope; exactly `rows_in_view` values).
    #[serde(default)]
    pub angles_deg: Option<Vec<f64>>,
}

impl CameraSpec {
    /// The incidence angle of each sensor row, radians, around the scene's
    /// uniform angle `theta_c` (radians); None: every row at `theta_c`.
    pub fn sensor_angles(&self, theta_c: f64) -> Result<Option<Vec<f64>>, LineError> {
        let n = self.rows_in_view as usize;
        let deg: Vec<f64> = match (&self.angles_deg, self.angle_deg_per_row) {
            (Some(_), Some(_)) => {
                return Err(LineError::Config(
                    "[camera]: give angles_deg or angle_deg_per_row, not both".into(),
                ))
            }
            (Some(list), None) => {
                if list.len() != n {
                    return Err(LineError::Config(format!(
                        "[camera] angles_deg has {} values, rows_in_view is {n}: one angle per sensor row",
                        list.len()
                    )));
                }
                list.clone()
            }
            (None, Some(slope)) if slope != 0.0 => {
                let mid = (n as f64 - 1.0) / 2.0;
                (0..n)
                    .map(|s| theta_c.to_degrees() + (s as f64 - mid) * slope)
                    .collect()
            }
            (None, _) => return Ok(None),
        };
        if let Some((s, a)) = deg
            .iter()
            .enumerate()
            .find(|(_, a)| !(a.is_finite() && (0.0..90.0).contains(*a)))
        {
            return Err(LineError::Config(format!(
                "[camera]: sensor row {s} would see the web at {a}°, outside 0–90°"
            )));
        }
        Ok(Some(deg.iter().map(|a| a.to_radians()).collect()))
    }
}

/// `[filter]`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FilterSpec {
    /// Settle time, ms.
    pub settle_ms: f64,
    /// Extra settle time, up to, ms (uniform).
    #[serde(default)]
    pub settle_jitter_ms: f64,
}

/// `[web]`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebSpec {
    /// Speed as a fraction of the highest the optics allow.
    pub speed_fraction: Option<f64>,
    /// Speed, rows/s (instead of the fraction).
    pub speed_rows_per_s: Option<f64>,
    /// Web rows per encoder count.
    pub rows_per_count: f64,
    /// Position jitter, ± rows.
    #[serde(default)]
    pub jitter_rows: f64,
    /// Seed of the noise and jitter.
    #[serde(default)]
    pub seed: u64,
}

/// `[line]`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LineSpec {
    /// Web rows per EXR segment.
    #[serde(default = "default_segment")]
    pub segment_rows: usize,
    /// Cross-web lanes.
    #[serde(default = "default_lanes")]
    pub lanes: usize,
    /// Publish to this MQTT broker, `host:port` (optional).
    #[serde(default)]
    pub mqtt: Option<String>,
}

fn default_segment() -> usize {
    64
}
fn default_lanes() -> usize {
    4
}

impl Default for LineSpec {
    fn default() -> Self {
        LineSpec {
            segment_rows: default_segment(),
            lanes: default_lanes(),
            mqtt: None,
        }
    }
}

/// A moving-web file as written.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebFile {
    /// The scene (optics, knowledge, bands), relative to this file.
    pub scene: PathBuf,
    /// The recipe, relative to this file.
    pub recipe: Option<PathBuf>,
    /// Camera.
    pub camera: CameraSpec,
    /// Filter.
    pub filter: FilterSpec,
    /// Motion.
    pub web: WebSpec,
    /// Thickness field.
    pub film: WebFilm,
    /// Output.
    #[serde(default)]
    pub line: LineSpec,
}

/// A resolved moving-web description.
#[derive(Clone, Debug)]
pub struct WebRig {
    /// As written.
    pub file: WebFile,
    /// The scene.
    pub scene: Scene,
    /// The directory relative paths start from.
    pub base: PathBuf,
    /// The optics' limit at this band rate.
    pub geometry: LineGeometry,
    /// The speed the web runs at, rows/s.
    pub speed: f64,
    /// The incidence angle of each sensor row, radians (None: every row at
    /// the scene's angle).
    pub sensor_angles: Option<Vec<f64>>,
}

/// What a run needs, built.
pub struct Built {
    /// The camera.
    pub camera: WebCamera,
    /// The emulated filter.
    pub tuner: EmulatedTuner,
    /// The references the set-up's calibrator was built from (what a
    /// recording stores; its creation time is left 0 — the rig reads no
    /// clock).
    pub calibration: Calibration,
    /// The set-up for [`super::run::run_line`].
    pub setup: LineSetup,
}

impl WebRig {
    /// Load `path`.
    pub fn load(path: &Path) -> Result<WebRig, LineError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| LineError::Config(format!("reading {}: {e}", path.display())))?;
        let file: WebFile = toml::from_str(&text)
            .map_err(|e| LineError::Config(format!("{}: {e}", path.display())))?;
        let base = path.parent().unwrap_or(Path::new(".")).to_path_buf();
        WebRig::resolve(file, base)
    }

    /// Resolve a parsed file, paths relative to `base`.
    pub fn resolve(file: WebFile, base: PathBuf) -> Result<WebRig, LineError> {
        let scene_path = base.join(&file.scene);
        let scene = Scene::load(&scene_path).map_err(|e| LineError::Config(e.to_string()))?;
        let bands = scene
            .bands
            .as_ref()
            .ok_or_else(|| LineError::Config(format!("{} has no [bands]", scene_path.display())))?;
        let c = &file.camera;
        let ok = |v: f64| v.is_finite() && v > 0.0;
        if !(ok(c.frame_period_ms) && ok(c.exposure_ms) && c.exposure_ms <= c.frame_period_ms) {
            return Err(LineError::Config(format!(
                "camera: frame period {} ms and exposure {} ms must be positive, exposure within the period",
                c.frame_period_ms, c.exposure_ms
            )));
        }
        let f = &file.filter;
        if !(f.settle_ms >= 0.0 && f.settle_jitter_ms >= 0.0 && f.settle_ms.is_finite()) {
            return Err(LineError::Config("filter: settle times must be ≥ 0".into()));
        }
        let rate = stepped_band_rate(
            (c.frame_period_ms * 1e6) as u64,
            (c.exposure_ms * 1e6) as u64,
            ((f.settle_ms + f.settle_jitter_ms) * 1e6) as u64,
        );
        let geometry = LineGeometry::new(c.rows_in_view as usize, bands.len(), rate)?;
        let speed = match (file.web.speed_fraction, file.web.speed_rows_per_s) {
            (Some(fr), None) => fr * geometry.max_speed(),
            (None, Some(v)) => v,
            _ => {
                return Err(LineError::Config(
                    "[web] needs exactly one of speed_fraction and speed_rows_per_s".into(),
                ))
            }
        };
        let sensor_angles = match (&scene.angle, &file.camera) {
            (AngleKnowledge::Uniform(t), c) => c.sensor_angles(*t)?,
            (_, c) if c.angles_deg.is_none() && c.angle_deg_per_row.is_none() => None,
            _ => {
                return Err(LineError::Config(format!(
                    "[camera] angles per sensor row need a known uniform angle in {} ([angle] deg)",
                    scene_path.display()
                )))
            }
        };
        Ok(WebRig {
            file,
            scene,
            base,
            geometry,
            speed,
            sensor_angles,
        })
    }

    /// The embedded demo.
    pub fn demo() -> Result<WebRig, LineError> {
        WebRig::load(&WebRig::demo_path())
    }

    /// The embedded demo's file.
    pub fn demo_path() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenes/web.toml")
    }

    /// The camera configuration (for tests to add speed changes, jumps).
    pub fn camera_config(&self) -> WebCameraConfig {
        let c = &self.file.camera;
        let sensor = SensorModel {
            exposure_us: (c.exposure_ms * 1e3) as u32,
            frame_period_ns: (c.frame_period_ms * 1e6) as u64,
            // The same light per µs as the default: a white target fills
            // ~80 % of 16 bits at 10 ms through the clearest band.
            counts_per_us: SensorModel::default().counts_per_us * 10.0 / c.exposure_ms.max(1e-3),
            ..SensorModel::default()
        };
        let theta_deg = match &self.scene.angle {
            AngleKnowledge::Uniform(t) => t.to_degrees(),
            _ => 0.0,
        };
        WebCameraConfig {
            width: c.width,
            rows_in_view: c.rows_in_view,
            speed_rows_per_s: self.speed,
            speed_changes: Vec::new(),
            jumps: Vec::new(),
            rows_per_count: self.file.web.rows_per_count,
            jitter_rows: self.file.web.jitter_rows,
            noise_sigma: self.scene.noise_sigma.unwrap_or(0.001),
            sensor,
            theta_deg,
            row_theta_deg: self
                .sensor_angles
                .as_ref()
                .map(|a| a.iter().map(|t| t.to_degrees()).collect())
                .unwrap_or_default(),
            polarization: self.scene.polarization,
            seed: self.file.web.seed,
            realtime_speed: 0.0,
        }
    }

    /// Build the camera (with `cfg`), the filter and the set-up.
    pub fn build(&self, cfg: WebCameraConfig, mode: Mode) -> Result<Built, LineError> {
        if !matches!(self.scene.angle, AngleKnowledge::Uniform(_)) {
            return Err(LineError::Config(
                "the synthetic web needs a known uniform angle ([angle] deg)".into(),
            ));
        }
        let film = match &self.scene.film {
            FilmKnowledge::Known(d) => d.clone(),
            FilmKnowledge::Unknown { .. } => {
                return Err(LineError::Config(
                    "the synthetic web needs a known film ([film] n or material)".into(),
                ))
            }
        };
        let bands = self.scene.bands.clone().unwrap_or_default();
        let view = FilterView::new();
        let rows_per_count = cfg.rows_per_count;
        let camera = WebCamera::new(
            cfg,
            self.file.film.clone(),
            [&self.scene.ambient, &film, &self.scene.substrate],
            &bands,
            view.clone(),
        )
        .map_err(|e| LineError::Config(e.to_string()))?;
        let f = &self.file.filter;
        let tuner = EmulatedTuner::new(
            view,
            Duration::from_secs_f64(f.settle_ms * 1e-3),
            Duration::from_secs_f64(f.settle_jitter_ms * 1e-3),
            self.file.web.seed ^ 0x5eed,
        );
        let (dark, white) = camera.reference_planes();
        let n = self.file.camera.width as usize * self.file.camera.rows_in_view as usize;
        let flags = vec![0u8; dark.len()];
        let exposure_us = (self.file.camera.exposure_ms * 1e3) as u32;
        debug_assert_eq!(dark.len(), n * bands.len());
        let info = crate::device::camera::FrameSource::info(&camera);
        let calibration = Calibration {
            meta: CalMeta {
                version: 1,
                width: info.width,
                height: info.height,
                bands_nm: bands.iter().map(|b| b.center_nm).collect(),
                exposure_us,
                gain: info.gain,
                format: info.format,
                camera_id: info.id,
                created_unix_s: 0,
                white_reflectance: 1.0,
                frames: 1,
                noise: None,
            },
            dark,
            white,
            flags,
        };
        let calibrator = Calibrator::from_calibration(calibration.clone());
        let setup = LineSetup {
            scene: self.scene.clone(),
            order: (0..bands.len()).collect(),
            bands,
            calibrator,
            motion: Motion::Encoder { rows_per_count },
            geometry: self.geometry,
            nominal_speed: self.speed,
            allow_over_speed: false,
            mode,
            warmup_rows: 16,
            threading: super::run::Threading::default(),
            sensor_angles: self.sensor_angles.clone(),
            angle_correction: super::angles::Correction::Auto,
        };
        Ok(Built {
            camera,
            tuner,
            calibration,
            setup,
        })
    }
}
