//! A line run's configuration as a recording stores it (the `/irid/line`
//! message, JSON), and the [`LineSetup`] and output rebuilt from it.
//!
//! A line recording is replayable without the files it was made from: the
//! session message carries the scene (as JSON), the bands, the capture
//! order and the solver mode; the calibration message the references; and
//! this record the moving-web file's text, the recipe's text and the
//! numbers the runner was given (registration, geometry, nominal speed,
//! warm-up, segments, lanes) — so a replay runs the same line even if the
//! web file has since been edited.

use super::geometry::{LineGeometry, Motion};
use super::recipe::Recipe;
use super::run::LineSetup;
use super::LineError;
use crate::estimate::Mode;
use crate::optics::band::Band;
use crate::pipeline::calibration::Calibrator;
use crate::scene::Scene;

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

    /// The set-up of the recorded run, with `scene`, `bands`, `order`,
    /// `calibrator` and `mode` (the recorded ones, or others to re-judge
    /// the same frames).
    pub fn setup(
        &self,
        scene: Scene,
        bands: Vec<Band>,
        order: Vec<usize>,
        calibrator: Calibrator,
        mode: Mode,
    ) -> LineSetup {
        LineSetup {
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
        }
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
}
