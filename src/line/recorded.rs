//! A line run's configuration as a recording stores it (the `/irid/line`
//! message, JSON), and the [`LineSetup`] and output rebuilt from it.
//!
//! A line recording is replayable without the files it was made from: the
//! session message carries the scene (as JSON), the bands, the capture
//! order and the solver mode; the calibration message the references; and
//! this record the moving-web file's text, the recipe's text and the
//! numbers the runner was given (registration, geometry, nominal speed,
//! warm-up, segments, lanes) — so a replay runs the same line even if the
//! web file has since been edited. The incidence angle per sensor row is
//! rebuilt from the recorded web file's `[camera]` (around the replay's
//! scene angle: a replay with `--scene` of another angle moves a slope
//! with it; an explicit `angles_deg` list stays as recorded).

use super::geometry::{LineGeometry, Motion};
use super::recipe::Recipe;
use super::rig::WebFile;
use super::run::LineSetup;
use super::LineError;
use crate::estimate::Mode;
use crate::optics::band::Band;
use crate::pipeline::calibration::Calibrator;
use crate::scene::{AngleKnowledge, Scene};

/// The `/irid/line` message.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LineRecord {
    /// The moving-web file, as written (TOML text).
    pub web_toml: String,
    /// Where it was read from (for people; nothing is read from it).
    pub web_path: String,
    /// The recipe in force, as written (TOML text); None: no recipe.
    pub recipe_toml: Option<String>,
    /// Where the recipe was read from.
    pub recipe_path: Option<String>,
    /// How frames were registered to the web.
    pub motion: Motion,
    /// Rows in view, bands, band rate (the speed check).
    pub geometry: LineGeometry,
    /// The nominal web speed, rows/s.
    pub nominal_speed_rows_per_s: f64,
    /// Whether the run was allowed above the optics' limit.
    pub allow_over_speed: bool,
    /// Complete rows that taught the estimator the noise level first.
    pub warmup_rows: usize,
    /// Web rows per EXR strip segment.
    pub segment_rows: usize,
    /// Cross-web lanes.
    pub lanes: usize,
    /// Frames per `--sweeps` unit of the command line.
    pub frames_per_sweep_unit: u64,
}

impl LineRecord {
    /// Parse and check a recorded `/irid/line` message.
    pub fn from_json(bytes: &[u8]) -> Result<LineRecord, LineError> {
        let r: LineRecord = serde_json::from_slice(bytes)
            .map_err(|e| LineError::Config(format!("recorded line configuration: {e}")))?;
        let g = r.geometry;
        LineGeometry::new(g.rows_in_view, g.n_bands, g.band_rate_hz)?;
        if r.segment_rows == 0 || r.lanes == 0 || r.frames_per_sweep_unit == 0 {
            return Err(LineError::Config(format!(
                "recorded line configuration: {} rows per segment, {} lanes, {} frames per sweep unit (all must be positive)",
                r.segment_rows, r.lanes, r.frames_per_sweep_unit
            )));
        }
        Ok(r)
    }

    /// The recorded recipe, parsed and checked (None: the run had none).
    pub fn recipe(&self) -> Result<Option<Recipe>, LineError> {
        self.recipe_toml
            .as_deref()
            .map(|t| Recipe::from_toml(t, "(recorded)"))
            .transpose()
    }

    /// The incidence angle of each sensor row, radians, from the recorded
    /// web file's `[camera]` around `scene`'s uniform angle (None: every
    /// row at the scene's angle).
    pub fn sensor_angles(&self, scene: &Scene) -> Result<Option<Vec<f64>>, LineError> {
        let file: WebFile = toml::from_str(&self.web_toml)
            .map_err(|e| LineError::Config(format!("recorded web file {}: {e}", self.web_path)))?;
        let c = &file.camera;
        if c.angles_deg.is_none() && c.angle_deg_per_row.is_none() {
            return Ok(None);
        }
        let AngleKnowledge::Uniform(theta_c) = scene.angle else {
            return Err(LineError::Config(format!(
                "recorded web file {}: angles per sensor row need a known uniform angle ([angle] deg)",
                self.web_path
            )));
        };
        let angles = c.sensor_angles(theta_c)?;
        if let Some(a) = &angles {
            if a.len() != self.geometry.rows_in_view {
                return Err(LineError::Config(format!(
                    "recorded web file {}: {} angles per sensor row, {} rows in view",
                    self.web_path,
                    a.len(),
                    self.geometry.rows_in_view
                )));
            }
        }
        Ok(angles)
    }

    /// The set-up of the recorded run, with `scene`, `bands`, `order`,
    /// `calibrator` and `mode` (the recorded ones, or others to re-judge
    /// the same frames); the incidence angle per sensor row is rebuilt from
    /// the recorded web file around `scene`'s angle.
    pub fn setup(
        &self,
        scene: Scene,
        bands: Vec<Band>,
        order: Vec<usize>,
        calibrator: Calibrator,
        mode: Mode,
    ) -> Result<LineSetup, LineError> {
        let sensor_angles = self.sensor_angles(&scene)?;
        Ok(LineSetup {
            scene,
            bands,
            order,
            calibrator,
            motion: self.motion,
            geometry: self.geometry,
            nominal_speed: self.nominal_speed_rows_per_s,
            allow_over_speed: self.allow_over_speed,
            mode,
            warmup_rows: self.warmup_rows,
            threading: super::run::Threading::default(),
            sensor_angles,
            angle_correction: super::angles::Correction::Auto,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record() -> LineRecord {
        LineRecord {
            web_toml: "scene = \"x.toml\"\n".into(),
            web_path: "web.toml".into(),
            recipe_toml: Some(
                "target_nm = 500.0\nlower_nm = 480.0\nupper_nm = 520.0\nalarm_rows = 10\n".into(),
            ),
            recipe_path: Some("r.toml".into()),
            motion: Motion::Encoder {
                rows_per_count: 0.25,
            },
            geometry: LineGeometry::new(32, 31, 50.0).unwrap(),
            nominal_speed_rows_per_s: 40.0,
            allow_over_speed: false,
            warmup_rows: 16,
            segment_rows: 64,
            lanes: 4,
            frames_per_sweep_unit: 400,
        }
    }

    #[test]
    fn round_trips_and_refuses_nonsense() {
        let r = record();
        let bytes = serde_json::to_vec(&r).unwrap();
        assert_eq!(LineRecord::from_json(&bytes).unwrap(), r);
        assert_eq!(r.recipe().unwrap().unwrap().target_nm, 500.0);
        let mut bad = r.clone();
        bad.geometry.band_rate_hz = -1.0;
        let e = LineRecord::from_json(&serde_json::to_vec(&bad).unwrap()).unwrap_err();
        assert!(e.to_string().contains("band rate"), "{e}");
        bad = r.clone();
        bad.lanes = 0;
        assert!(LineRecord::from_json(&serde_json::to_vec(&bad).unwrap()).is_err());
        assert!(LineRecord::from_json(b"{\"web_toml\": 3}").is_err());
        bad = r;
        bad.recipe_toml = Some("target_nm = \"x\"".into());
        assert!(bad.recipe().is_err());
    }

    /// A replay rebuilds the angles per sensor row from the recorded web
    /// file, exactly as the live rig resolved them, around the replay's
    /// scene angle; a recording without them (older, or none set) has none.
    #[test]
    fn the_angles_per_sensor_row_come_back_from_the_recorded_web_file() {
        use super::super::rig::WebRig;
        let demo = WebRig::demo_path();
        let text = std::fs::read_to_string(&demo).unwrap();
        let with = text.replace(
            "exposure_ms = 5.0",
            "exposure_ms = 5.0\nangle_deg_per_row = 0.25",
        );
        assert_ne!(with, text);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("web.toml");
        let scene = demo.parent().unwrap().join("web-film.toml");
        let with = with.replace(
            "scene = \"web-film.toml\"",
            &format!("scene = {:?}", scene.display().to_string()),
        );
        let with = with.replace("recipe = \"web-recipe.toml\"\n", "");
        std::fs::write(&path, &with).unwrap();
        let live = WebRig::load(&path).unwrap();
        let want = live.sensor_angles.clone().unwrap();
        assert_eq!(want.len(), 32);
        let mut r = record();
        r.web_toml = with;
        r.geometry = live.geometry;
        let cal = crate::pipeline::calibration::Calibrator::from_calibration(
            live.build(live.camera_config(), Mode::Fast)
                .unwrap()
                .calibration,
        );
        let bands = live.scene.bands.clone().unwrap();
        let order: Vec<usize> = (0..bands.len()).collect();
        let setup = r
            .setup(
                live.scene.clone(),
                bands.clone(),
                order.clone(),
                cal.clone(),
                Mode::Fast,
            )
            .unwrap();
        assert_eq!(setup.sensor_angles.as_deref(), Some(&want[..]));
        // Re-judged at another scene angle: the slope moves with it.
        let mut other = live.scene.clone();
        other.angle = AngleKnowledge::Uniform(35f64.to_radians());
        let moved = r
            .setup(other, bands.clone(), order.clone(), cal.clone(), Mode::Fast)
            .unwrap()
            .sensor_angles
            .unwrap();
        for (m, w) in moved.iter().zip(&want) {
            assert!((m - w - 5f64.to_radians()).abs() < 1e-12);
        }
        // The demo's own file: no angles.
        r.web_toml = text;
        let none = r
            .setup(live.scene.clone(), bands, order, cal, Mode::Fast)
            .unwrap();
        assert!(none.sensor_angles.is_none());
    }
}
