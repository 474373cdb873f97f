//! Per-sweep outputs: the map as OpenEXR (`DIR/sweep-NNNNNN.exr`, the same
//! f32 channels as `irid fit`) and one summary line (human or JSON).
//!
//! Maps are written by the io layer's EXR writer
//! ([`crate::io::exr_maps::write_maps`]).

use crate::estimate::ParamMaps;
use std::path::{Path, PathBuf};

/// Output errors.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// The map could not be written.
    #[error("writing {path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Cause.
        message: String,
    },
}

/// The summary of one sweep: one line of `irid run` output.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct SweepSummary {
    /// Sweep index (0-based, counting dropped sweeps).
    pub sweep: u64,
    /// Valid pixels / all pixels.
    pub valid_fraction: f64,
    /// Mean thickness of valid pixels, nm (null when none).
    pub thickness_mean_nm: f64,
    /// Standard deviation of the thickness, nm.
    pub thickness_std_nm: f64,
    /// Smallest thickness, nm.
    pub thickness_min_nm: f64,
    /// Largest thickness, nm.
    pub thickness_max_nm: f64,
    /// Film index used.
    pub n_film: f64,
    /// Smallest incidence angle, degrees.
    pub theta_min_deg: f64,
    /// Largest incidence angle, degrees.
    pub theta_max_deg: f64,
    /// Frames lost, refused or discarded for faults since the last map
    /// (not counting frames discarded while the filter settled).
    pub frames_dropped: u64,
    /// Whole sweeps dropped since the last map (processing behind).
    pub sweeps_dropped: u64,
    /// Bands of this sweep given up (NaN planes).
    pub missing_bands: usize,
    /// Wall time from the sweep's last band frame to the finished map, ms.
    pub latency_ms: f64,
    /// The map file, if written.
    pub path: Option<String>,
    /// The reflectance noise σ every fit was judged against (at R = 0.05).
    pub noise_sigma: f64,
    /// Where it came from: `given`, `camera` (measured with the
    /// calibration's references) or `data`.
    pub noise_source: String,
    /// The level in force (`absolute`, `scaled`, …).
    pub level: String,
}

impl SweepSummary {
    /// Statistics of `maps`.
    pub fn from_maps(sweep: u64, maps: &ParamMaps) -> SweepSummary {
        let n = maps.valid.len().max(1);
        let (mut cnt, mut sum, mut sum2) = (0usize, 0.0f64, 0.0f64);
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut tlo, mut thi) = (f64::INFINITY, f64::NEG_INFINITY);
        for i in 0..maps.valid.len() {
            if maps.valid[i] < 0.5 {
                continue;
            }
            let d = f64::from(maps.thickness_nm[i]);
            if d.is_finite() {
                cnt += 1;
                sum += d;
                sum2 += d * d;
                lo = lo.min(d);
                hi = hi.max(d);
            }
            let t = f64::from(maps.theta_deg[i]);
            if t.is_finite() {
                tlo = tlo.min(t);
                thi = thi.max(t);
            }
        }
        let nan_if = |ok: bool, v: f64| if ok { v } else { f64::NAN };
        let quality = |key: &str| {
            maps.meta
                .quality
                .iter()
                .find(|(k, _)| k == key)
                .map(|(_, v)| v.clone())
        };
        let mean = sum / cnt.max(1) as f64;
        SweepSummary {
            sweep,
            valid_fraction: maps.valid_count() as f64 / n as f64,
            thickness_mean_nm: nan_if(cnt > 0, mean),
            thickness_std_nm: nan_if(
                cnt > 0,
                (sum2 / cnt.max(1) as f64 - mean * mean).max(0.0).sqrt(),
            ),
            thickness_min_nm: nan_if(cnt > 0, lo),
            thickness_max_nm: nan_if(cnt > 0, hi),
            n_film: maps.meta.n_film,
            theta_min_deg: nan_if(tlo.is_finite(), tlo),
            theta_max_deg: nan_if(thi.is_finite(), thi),
            noise_sigma: quality("noise_sigma")
                .and_then(|v| v.parse().ok())
                .unwrap_or(f64::NAN),
            noise_source: quality("noise_source").unwrap_or_default(),
            level: quality("level").unwrap_or_default(),
            ..Default::default()
        }
    }

    /// One JSON object (NaN as null).
    pub fn json(&self) -> String {
        serde_json::to_string(self).expect("summary serialises")
    }

    /// One human-readable line.
    pub fn line(&self) -> String {
        format!(
            "sweep {:>6}  valid {:5.1}%  d = {:.1} ± {:.1} nm [{:.1}, {:.1}]  n = {:.4}  θ [{:.1}°, {:.1}°]  dropped {} frames / {} sweeps  missing {}  latency {:.1} ms",
            self.sweep,
            100.0 * self.valid_fraction,
            self.thickness_mean_nm,
            self.thickness_std_nm,
            self.thickness_min_nm,
            self.thickness_max_nm,
            self.n_film,
            self.theta_min_deg,
            self.theta_max_deg,
            self.frames_dropped,
            self.sweeps_dropped,
            self.missing_bands,
            self.latency_ms
        )
    }
}

/// Refuse an output folder that already holds sweep maps (of an earlier
/// run, which this one would overwrite), naming the first found.
pub fn refuse_earlier_maps(dir: &Path) -> Result<(), OutputError> {
    let entries = std::fs::read_dir(dir).map_err(|e| OutputError::Write {
        path: dir.to_path_buf(),
        message: e.to_string(),
    })?;
    let mut earlier: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("sweep-") && n.ends_with(".exr"))
        })
        .collect();
    earlier.sort();
    match earlier.first() {
        None => Ok(()),
        Some(p) => Err(OutputError::Write {
            path: p.clone(),
            message: format!(
                "the output folder holds {} map(s) of an earlier run; give --force to replace them, or another --out",
                earlier.len()
            ),
        }),
    }
}

/// The path of sweep `sweep`'s map under `dir`: a name made of the
/// number alone, so a map is never written outside `dir`.
pub fn sweep_path(dir: &Path, sweep: u64) -> PathBuf {
    dir.join(format!("sweep-{sweep:06}.exr"))
}

/// Write `maps` as an OpenEXR file with the `irid fit` channels and
/// header attributes (the io layer's writer, so `irid fit` and `irid run`
/// maps are the same format).
pub fn write_map(path: &Path, maps: &ParamMaps) -> Result<(), OutputError> {
    crate::io::exr_maps::write_maps(path, maps).map_err(|e| OutputError::Write {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}
