//! Dark and white references captured with a rig, per band in its capture
//! order, made into a [`Calibration`]. The synthetic camera switches its
//! own target; for a real one the caller is asked to have a person cap the
//! lens or place the white reference (the front end decides how to ask).
//! The creation time is passed in: this layer does not read the clock.

use super::{Rig, RigError};
use crate::device::camera::Target;
use crate::pipeline::calibration::{
    capture_reference, CalMeta, Calibration, CalibrationPolicy, CapturePlan,
};
use std::time::Duration;

impl Rig {
    /// Capture `frames` dark and `frames` white frames per band and build
    /// the calibration, stamped `created_unix_s`. When the camera cannot
    /// show a reference itself, `ask` is called with it and returns once a
    /// person has set it up. The camera looks at the scene again after.
    pub fn capture_calibration(
        &mut self,
        frames: u32,
        white_reflectance: f64,
        created_unix_s: u64,
        ask: &mut dyn FnMut(Target) -> std::io::Result<()>,
    ) -> Result<Calibration, RigError> {
        let info = self.source.info();
        let nm: Vec<f64> = self.bands.iter().map(|b| b.center_nm).collect();
        let mut refs = Vec::new();
        for (name, target) in [
            ("dark", Target::Dark),
            ("white", Target::White(white_reflectance)),
        ] {
            if !self.source.set_target(target)? {
                ask(target).map_err(RigError::Operator)?;
            }
            let plan = CapturePlan {
                mode: self.seq_mode,
                bands_nm: &nm,
                order: &self.order,
                frames,
                timeout: Duration::from_secs(2),
            };
            let acc = capture_reference(name, self.source.as_mut(), self.tuner.as_mut(), &plan)?;
            refs.push(acc);
        }
        self.source.set_target(Target::Scene)?;
        let meta = CalMeta {
            version: 1,
            width: info.width,
            height: info.height,
            bands_nm: nm,
            exposure_us: info.exposure_us,
            gain: info.gain,
            format: info.format,
            camera_id: info.id,
            created_unix_s,
            white_reflectance,
            frames,
            noise: None,
        };
        Ok(Calibration::from_references(
            meta,
            &refs[0],
            &refs[1],
            &CalibrationPolicy::for_format(info.format),
        ))
    }
}
