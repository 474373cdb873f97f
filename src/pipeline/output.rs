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
    /// Why the film index, noise, level and band shift were estimated
    /// again on this sweep (the level had moved, or poor fits rose), and
    /// what they came to; absent where they were kept.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub relook: Option<String>,
}

/// Over `maps`: how many pixels are valid (as [`ParamMaps::valid_count`]
/// counts them), and over those how many have a finite thickness, its sum
/// and sum of squares, its least and greatest value, and the least and
/// greatest finite angle. One pass in four independent lanes, every test a
/// select (a full camera frame's 1.3 M pixels took ~7 ms band by band on
/// the live runner's critical path, a branch and a dependent sum each).
fn map_stats(maps: &ParamMaps) -> (usize, usize, f64, f64, (f64, f64), (f64, f64)) {
    let n = maps
        .valid
        .len()
        .min(maps.thickness_nm.len())
        .min(maps.theta_deg.len());
    let (valid, d, t) = (
        &maps.valid[..n],
        &maps.thickness_nm[..n],
        &maps.theta_deg[..n],
    );
    let (inf, ninf) = (f64::INFINITY, f64::NEG_INFINITY);
    let (mut valid_n, mut cnt) = ([0f64; 4], [0f64; 4]);
    let (mut sum, mut sum2) = ([0f64; 4], [0f64; 4]);
    let (mut lo, mut hi, mut tlo, mut thi) = ([inf; 4], [ninf; 4], [inf; 4], [ninf; 4]);
    let mut lane = |l: usize, v: f32, d: f32, t: f32| {
        valid_n[l] += if v > 0.5 { 1.0 } else { 0.0 };
        let ok = v >= 0.5;
        let d = f64::from(d);
        let t = f64::from(t);
        let (dk, tk) = (ok && d.is_finite(), ok && t.is_finite());
        cnt[l] += if dk { 1.0 } else { 0.0 };
        let dv = if dk { d } else { 0.0 };
        sum[l] += dv;
        sum2[l] += dv * dv;
        lo[l] = lo[l].min(if dk { d } else { inf });
        hi[l] = hi[l].max(if dk { d } else { ninf });
        tlo[l] = tlo[l].min(if tk { t } else { inf });
        thi[l] = thi[l].max(if tk { t } else { ninf });
    };
    let quads = valid
        .chunks_exact(4)
        .zip(d.chunks_exact(4))
        .zip(t.chunks_exact(4));
    for ((v, d), t) in quads {
        for l in 0..4 {
            lane(l, v[l], d[l], t[l]);
        }
    }
    for i in n - n % 4..n {
        lane(0, valid[i], d[i], t[i]);
    }
    let total = |a: [f64; 4]| (a[0] + a[1]) + (a[2] + a[3]);
    let least = |a: [f64; 4]| a.iter().copied().fold(inf, f64::min);
    let most = |a: [f64; 4]| a.iter().copied().fold(ninf, f64::max);
    (
        total(valid_n) as usize,
        total(cnt) as usize,
        total(sum),
        total(sum2),
        (least(lo), most(hi)),
        (least(tlo), most(thi)),
    )
}

impl SweepSummary {
    /// Statistics of `maps`.
    pub fn from_maps(sweep: u64, maps: &ParamMaps) -> SweepSummary {
        let n = maps.valid.len().max(1);
        let (valid, cnt, sum, sum2, (lo, hi), (tlo, thi)) = map_stats(maps);
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
            valid_fraction: valid as f64 / n as f64,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The four-lane pass against the definition pixel by pixel: valid
    /// pixels only, non-finite thicknesses and angles skipped, on a map
    /// whose length is no multiple of four.
    #[test]
    fn the_summary_counts_the_valid_finite_pixels_as_defined() {
        let (w, h) = (7, 5);
        let mut maps = ParamMaps::new(w, h);
        for i in 0..w * h {
            maps.valid[i] = if i % 3 == 0 { 0.0 } else { 1.0 };
            maps.thickness_nm[i] = if i % 5 == 1 {
                f32::NAN
            } else {
                100.0 + (i * 37 % 23) as f32
            };
            maps.theta_deg[i] = if i % 7 == 2 {
                f32::INFINITY
            } else {
                10.0 + (i * 11 % 17) as f32
            };
        }
        let s = SweepSummary::from_maps(3, &maps);
        let ok = |i: &usize| maps.valid[*i] > 0.5;
        let d: Vec<f64> = (0..w * h)
            .filter(ok)
            .map(|i| f64::from(maps.thickness_nm[i]))
            .filter(|v| v.is_finite())
            .collect();
        let t: Vec<f64> = (0..w * h)
            .filter(ok)
            .map(|i| f64::from(maps.theta_deg[i]))
            .filter(|v| v.is_finite())
            .collect();
        let mean = d.iter().sum::<f64>() / d.len() as f64;
        let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d.len() as f64;
        let valid = (0..w * h).filter(ok).count() as f64 / (w * h) as f64;
        assert_eq!(s.valid_fraction, valid);
        assert!((s.thickness_mean_nm - mean).abs() < 1e-9, "{s:?}");
        assert!(
            (s.thickness_std_nm - var.sqrt()).abs() < 1e-6,
            "{s:?} {}",
            var.sqrt()
        );
        let (lo, hi) = d.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, &v| {
            (a.0.min(v), a.1.max(v))
        });
        let (tlo, thi) = t.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, &v| {
            (a.0.min(v), a.1.max(v))
        });
        assert_eq!((s.thickness_min_nm, s.thickness_max_nm), (lo, hi));
        assert_eq!((s.theta_min_deg, s.theta_max_deg), (tlo, thi));
        // Nothing valid: NaN statistics, not zeros.
        maps.valid.iter_mut().for_each(|v| *v = 0.0);
        let s = SweepSummary::from_maps(4, &maps);
        assert!(
            s.thickness_mean_nm.is_nan() && s.theta_min_deg.is_nan() && s.valid_fraction == 0.0
        );
    }
}
