//! Rows and whole cubes: each pixel of a row through the per-pixel path
//! (`fast` band-major, 64 pixels at a time), rows in parallel.

use super::closed_form::ExtremaAcc;
use super::{Effort, Scratch, Solver, CLOSED_FORM_RETRY, CLOSED_FORM_SKIP_AFTER};
use crate::estimate::detect::{self, CandidatePlanes};
use crate::estimate::{maps, Cube, EstimateError, Mode, ParamMaps, PixelEstimate, Reason};
use crate::scene::AngleKnowledge;
use multiversion::multiversion;
use rayon::prelude::*;
use std::f64::consts::PI;

/// Pixels whose spectra are gathered from the row's band lines at once: a
/// cache line of `f32`s.
pub(super) const GATHER: usize = 16;

impl Solver {
    /// Solve row `y` of the cube into `out` (length `cube.width`).
    pub fn solve_row(
        &self,
        cube: &Cube,
        y: usize,
        out: &mut [PixelEstimate],
        scratch: &mut Scratch,
    ) {
        self.solve_row_with(cube, y, out, scratch, None);
    }

    /// As [`Solver::solve_row`], with the extremum candidates already found
    /// (by the live tracker, as the bands arrived): `fast` then skips its
    /// detection pass. Planes of another size are ignored.
    pub fn solve_row_with(
        &self,
        cube: &Cube,
        y: usize,
        out: &mut [PixelEstimate],
        scratch: &mut Scratch,
        candidates: Option<&CandidatePlanes>,
    ) {
        // Each row starts afresh: a row's result never depends on which
        // thread solved which row before it.
        scratch.start_afresh();
        let mut pixel = std::mem::take(&mut scratch.pixel);
        pixel.resize(cube.bands.len(), 0.0);
        let mut done = 0;
        // Where the thickness tables serve the known angles, every pixel
        // takes them (no extremum pass needed).
        let tabled = self.prepared.as_ref().is_some_and(|p| !p.tables.is_empty());
        let on_angle = self.row_angle_applies(cube.width);
        if self.mode == Mode::Fast
            && !tabled
            && !on_angle
            && self.level_mode != crate::estimate::level::LevelMode::Free
        {
            let pre = candidates.filter(|c| {
                c.size() == (cube.width, cube.height) && c.bands() == self.table.sorted.len()
            });
            done = self.solve_row_fast(cube, y, out, &mut pixel, scratch, pre);
        }
        let mut fits = std::mem::take(&mut scratch.fits);
        fits.clear();
        fits.extend(out.iter().take(done).map(|o| o.thickness_nm));
        // The row's samples band by band, each band's row copied whole: a
        // pixel's spectrum is then gathered from this (a few cache-resident
        // kilobytes per band) rather than from band planes megabytes apart,
        // one cache line per band per pixel that no prefetcher follows.
        // Each band's row starts one cache line past a multiple of 16
        // floats: at a stride of the row's own width (1280 or 2560 floats,
        // 5 or 10 KiB) a pixel's 31 lines fell into 4 (or 2) of the L1
        // cache's 64 sets, more than their ways hold, and every pixel's
        // gather missed.
        let (w, nb) = (cube.width, cube.bands.len());
        let ws = w.next_multiple_of(16) + 16;
        let mut rows = std::mem::take(&mut scratch.row);
        if done < w {
            rows.clear();
            let n = cube.plane_len();
            if y < cube.height && cube.data.len() >= n * nb {
                for plane in cube.data.chunks_exact(n.max(1)).take(nb) {
                    rows.extend_from_slice(&plane[y * w..(y + 1) * w]);
                    rows.resize(rows.len() + ws - w, f32::NAN);
                }
            }
            // A row outside the cube (or a short cube) reads as missing.
            rows.resize(nb * ws, f32::NAN);
        }
        // Gathered GATHER pixels at a time, band by band: each band's
        // cache line (16 floats) is loaded once for the batch, in a burst
        // of independent loads, instead of once per pixel between solves
        // that have evicted it.
        let mut batch = std::mem::take(&mut scratch.batch);
        batch.resize(GATHER * nb, 0.0);
        let (mut x0, end) = (done, w.min(out.len()));
        // `fast` with the angle free: on the row's estimated angle, where
        // its samples give one (`angle_map`).
        if on_angle
            && end == w
            && self.solve_row_on_angle(&rows, ws, w, out, &mut fits, &mut batch, scratch)
        {
            x0 = end;
        }
        while x0 < end {
            let m = GATHER.min(end - x0);
            gather(&rows, ws, x0, m, nb, &mut batch);
            for i in 0..m {
                let (x, pixel) = (x0 + i, &batch[i * nb..(i + 1) * nb]);
                scratch.last_fit_d = f64::NAN;
                let o = self.solve_pixel(pixel, self.scene.angle.known_at(x, y), scratch);
                scratch.note_fit(&o, &mut fits);
                out[x] = o;
            }
            x0 += m;
        }
        scratch.batch = batch;
        scratch.fits = fits;
        scratch.row = rows;
        // A pixel lost to unusable bands says why, where the calibration
        // tagged them (dark, saturated).
        for (x, o) in out.iter_mut().enumerate().take(cube.width) {
            if matches!(o.reason, Reason::NonFinite | Reason::MissingBands) {
                if let Some(r) = cube.input_reason(x, y) {
                    *o = PixelEstimate::invalid(r);
                }
            }
        }
        scratch.pixel = pixel;
        scratch.warm = None;
        // Every path (`irid fit`, the live runner, the line) widens alike.
        self.widen_for_scale(cube, y, out, scratch);
    }

    /// `fast` on a whole row, band-major: the extremum candidates of 64
    /// pixels at a time come from one branch-free pass over the band planes
    /// (bit masks per pixel), so only the few candidates are visited per
    /// pixel; the fits and closed forms are those of the per-pixel path, and
    /// a pixel they cannot serve takes it. Returns the pixels written (the
    /// whole row, or 0 when this path does not apply).
    fn solve_row_fast(
        &self,
        cube: &Cube,
        y: usize,
        out: &mut [PixelEstimate],
        pixel: &mut [f64],
        scratch: &mut Scratch,
        pre: Option<&CandidatePlanes>,
    ) -> usize {
        let (Some(prep), Some(index)) = (&self.prepared, &self.index) else {
            return 0;
        };
        let nb = self.table.sorted.len();
        let (w, n) = (cube.width, cube.plane_len());
        if !(7..=detect::MAX_DETECT_BANDS).contains(&nb)
            || cube.bands.len() != nb
            || out.len() < w
            || y >= cube.height
        {
            return 0;
        }
        let noise = index.noise_sigma.is_finite().then_some(index.noise_sigma);
        let data = &cube.data;
        let base = y * w;
        // Start of sorted band r's row in the cube.
        let row_of = |r: usize| self.table.sorted[r].0 * n + base;
        const CH: usize = detect::CHUNK;
        const NB: usize = detect::MAX_DETECT_BANDS;
        let mut rows: [&[f32]; NB] = [&[]; NB];
        // The chunk band-major in one block (band r's pixel j at r·CH + j),
        // so a window's samples are read without bounds checks.
        let mut flat = [0f32; CH * NB];
        let mut cand = detect::Candidates::default();
        let mut acc = ExtremaAcc::new(noise);
        let mut x0 = 0;
        while x0 < w {
            let m = (w - x0).min(CH);
            for (r, row) in rows[..nb].iter_mut().enumerate() {
                *row = &data[row_of(r) + x0..row_of(r) + x0 + m];
                flat[r * CH..r * CH + m].copy_from_slice(row);
            }
            match pre {
                Some(p) => p.unpack(y, x0 / CH, &mut cand),
                None => detect::detect(&rows[..nb], &mut cand),
            }
            let detect::Candidates {
                maxima,
                minima,
                bad,
            } = &cand;
            for j in 0..m {
                let x = x0 + j;
                let theta_known = self.scene.angle.known_at(x, y);
                let theta_ok =
                    theta_known.is_none_or(|t| t.is_finite() && (0.0..PI / 2.0).contains(&t));
                let mut est = None;
                // Where the closed form has served no pixel of late, the
                // fitted path (the previous pixel's fit, then the search)
                // without it: looking cost a quarter of the time on a
                // dispersive film whose closed form always misses.
                let misses = scratch.closed_form_misses;
                let look = misses < CLOSED_FORM_SKIP_AFTER || misses % CLOSED_FORM_RETRY == 0;
                if !bad[j] && theta_ok && look {
                    acc.reset();
                    let mut pending = maxima[j] | minima[j];
                    let mut next_free = 1;
                    while pending != 0 && !acc.full() {
                        let i = pending.trailing_zeros() as usize;
                        pending &= pending - 1;
                        if i < next_free {
                            // Next to the previous candidate.
                            continue;
                        }
                        let kind = if maxima[j] >> i & 1 == 1 { 1 } else { -1 };
                        let (lo, len) = self.table.parabola[i]
                            .as_ref()
                            .map_or((0, 0), |w| (w.lo, w.len));
                        let y5 = std::array::from_fn(|k| {
                            let v = f64::from(flat[((lo + k) % NB) * CH + j % CH]);
                            if k < len {
                                v
                            } else {
                                0.0
                            }
                        });
                        self.fit_extremum(i, kind, y5, &mut acc);
                        next_free = i + 2;
                    }
                    est = self.closed_form(prep, &acc, theta_known, noise, Some(index));
                }
                let mut retry_from = None;
                if let (Some(e), true) = (est, self.judging()) {
                    // The closed form must explain the whole spectrum.
                    unflatten(&flat, j, &self.table.sorted, pixel);
                    scratch.ensure(nb);
                    scratch.spectrum.copy_from_slice(pixel);
                    scratch.weight.fill(1.0);
                    match self.judge_closed_form(prep, e, theta_known, nb, scratch) {
                        Ok(e) => est = Some(e),
                        Err(start) => {
                            est = None;
                            retry_from = Some(start);
                        }
                    }
                }
                // Served: judged and kept. A start a step would mend is a
                // miss too: its refinement costs what the previous pixel's
                // fit costs, after the closed form and its judgement (on
                // the thin coating most closed forms were such starts; with
                // them counted as misses its rows solve 13 % faster).
                let served = est.is_some();
                scratch.closed_form_misses = if served { 0 } else { misses + 1 };
                out[x] = match est {
                    Some(mut e) => {
                        if !self.level.share.is_empty() && !self.judging() {
                            // The level's share of σ goes through the
                            // pixel's own fit to these values (already
                            // read where the closed form was judged).
                            unflatten(&flat, j, &self.table.sorted, pixel);
                        }
                        self.with_level(prep, pixel, theta_known.is_none(), &mut e, scratch);
                        e
                    }
                    None if retry_from.is_some() => {
                        // Refined from the closed form (and searched if
                        // that does not fit either), then judged.
                        let effort = Effort::of(Mode::Fast);
                        self.solve_pixel_with(pixel, theta_known, scratch, effort, retry_from)
                    }
                    None => {
                        // The closed form was just tried on these very
                        // samples: straight to the fitted path.
                        unflatten(&flat, j, &self.table.sorted, pixel);
                        let effort = Effort {
                            closed_form: false,
                            ..Effort::of(Mode::Fast)
                        };
                        self.solve_pixel_with(pixel, theta_known, scratch, effort, None)
                    }
                };
                scratch.note_warm(&out[x]);
            }
            x0 += m;
        }
        w
    }

    /// Fit a whole cube: the film index first where unknown, then every
    /// pixel, rows in parallel on the current rayon pool.
    pub fn fit_cube(&mut self, cube: &Cube) -> Result<ParamMaps, EstimateError> {
        self.fit_cube_with_progress(cube, &|_| {})
    }

    /// [`Solver::fit_cube`], calling `row_done(y)` from the solving thread
    /// as each row is finished (in no particular order), so a front end can
    /// show progress.
    pub fn fit_cube_with_progress(
        &mut self,
        cube: &Cube,
        row_done: &(dyn Fn(usize) + Sync),
    ) -> Result<ParamMaps, EstimateError> {
        self.check_cube(cube)?;
        if self
            .index
            .as_ref()
            .is_none_or(|i| !i.noise_sigma.is_finite())
        {
            self.estimate_film_index(cube)?;
        }
        // Every pixel is solved on the data corrected by the level in force.
        let corrected;
        let cube = if self.level.is_identity() {
            cube
        } else {
            let mut c = Cube::zeros(0, 0, Vec::new());
            self.correct_into(cube, &mut c);
            corrected = c;
            &corrected
        };
        let (w, h) = (cube.width, cube.height);
        let mut maps = ParamMaps::for_overwrite(w, h);
        // Rows in parallel, each written straight into its row of the maps
        // by the thread that solved it.
        maps.rows_mut(0..h)
            .into_par_iter()
            .enumerate()
            .for_each_init(
                || {
                    (
                        Scratch::default(),
                        vec![PixelEstimate::invalid(Reason::Masked); w],
                    )
                },
                |(scratch, est), (y, mut row)| {
                    self.solve_row(cube, y, est, scratch);
                    row.set_all(est);
                    row_done(y);
                },
            );
        maps.meta = self.map_meta();
        Ok(maps)
    }

    /// The reflectance scale's share of each valid pixel's σ_d, where a
    /// scale accuracy ε is in force: the pixel fitted again on its spectrum
    /// scaled by 1 ± ε, half the spread of the thicknesses added in
    /// quadrature. A scale error is the same in every band, so the noise
    /// term (ε·R)², independent per band, leaves σ_d too small where the
    /// thickness shows in the level (a film below its first fringe). Two
    /// more fits per valid pixel: spectrum tables (few spectra) take it by
    /// default, cubes only when given an ε.
    #[inline(never)]
    fn widen_for_scale(
        &self,
        cube: &Cube,
        y: usize,
        out: &mut [PixelEstimate],
        scratch: &mut Scratch,
    ) {
        let eps = self.noise.as_ref().map_or(0.0, |n| n.accuracy());
        if eps <= 0.0 {
            return;
        }
        // The row's buffers, reused: no allocation per row.
        let mut pixel = std::mem::take(&mut scratch.pixel);
        let mut scaled = std::mem::take(&mut scratch.scaled);
        pixel.resize(cube.bands.len(), 0.0);
        scaled.resize(cube.bands.len(), 0.0);
        for (x, o) in out.iter_mut().enumerate().take(cube.width) {
            if !o.is_valid() {
                continue;
            }
            cube.spectrum_into(x, y, &mut pixel);
            let theta = self.scene.angle.known_at(x, y);
            let mut ds = [f64::NAN; 2];
            for (d, f) in ds.iter_mut().zip([1.0 + eps, 1.0 - eps]) {
                scaled.iter_mut().zip(&pixel).for_each(|(s, v)| *s = v * f);
                scratch.last_fit_d = f64::NAN;
                // A run past the resolved range left by the row (or by the
                // previous refit) is no start for this valid pixel's fit.
                scratch.end_unresolved_run();
                let e = self.solve_pixel(&scaled, theta, scratch);
                // A scaled spectrum may fail the test; its best fit still
                // says where that scale puts the thickness.
                *d = if e.is_valid() {
                    e.thickness_nm
                } else {
                    scratch.last_fit_d
                };
            }
            if ds.iter().all(|d| d.is_finite()) {
                let spread = 0.5 * (ds[0] - ds[1]).abs();
                o.sigma_thickness_nm = o.sigma_thickness_nm.hypot(spread);
            }
        }
        scratch.pixel = pixel;
        scratch.scaled = scaled;
    }

    /// Metadata for maps produced by this solver.
    pub fn map_meta(&self) -> maps::MapMeta {
        let idx = self.index.clone();
        maps::MapMeta {
            mode: self.mode.name().into(),
            wavelengths_nm: self.nominal_bands.iter().map(|b| b.center_nm).collect(),
            fwhm_nm: self.nominal_bands.iter().map(|b| b.fwhm_nm).collect(),
            n_film: idx.as_ref().map_or(f64::NAN, |i| i.n),
            n_film_sigma: idx.as_ref().map_or(f64::NAN, |i| i.sigma),
            n_film_estimated: idx.as_ref().is_some_and(|i| i.estimated),
            n_film_note: idx.map(|i| i.note).unwrap_or_default(),
            polarization: self.scene.polarization.name(),
            quality: self.quality_meta(),
        }
    }

    /// What the fits were judged against, as (key, value) attributes.
    pub fn quality_meta(&self) -> Vec<(String, String)> {
        let (gain, offset) = self.level.mean();
        let mut q = vec![
            (
                "noise_sigma".to_string(),
                self.noise.as_ref().map_or("unknown".into(), |n| {
                    format!("{:.3e}", n.instrument_sigma(0.05))
                }),
            ),
            (
                "noise_source".into(),
                self.noise
                    .as_ref()
                    .map_or("none (fits not tested)".into(), |n| n.source.name().into()),
            ),
            ("level".into(), self.level_mode.name().into()),
            ("level_gain".into(), format!("{gain:.5}")),
            ("level_offset".into(), format!("{offset:.6}")),
            (
                "thickness_range_nm".into(),
                format!("{:.1}..{:.1}", self.d_min, self.d_max),
            ),
            (
                "optical_thickness_max_nm".into(),
                format!(
                    "{:.0} ({})",
                    self.g_max.0,
                    match self.g_max.1 {
                        crate::estimate::range::RangeLimit::Sampling => "band spacing",
                        crate::estimate::range::RangeLimit::Passband => "passband width",
                    }
                ),
            ),
            (
                "fit_test".into(),
                format!(
                    "chi2 at p = {} against the noise model",
                    crate::estimate::quality::FLAG_PROBABILITY
                ),
            ),
        ];
        if !self.level_note.is_empty() {
            q.push(("level_note".into(), self.level_note.clone()));
        }
        if !self.shift.note.is_empty() {
            q.push(("band_shift".into(), self.shift.note.clone()));
        }
        q
    }

    pub(super) fn check_cube(&self, cube: &Cube) -> Result<(), EstimateError> {
        if cube.bands.len() != self.bands.len() {
            return Err(EstimateError::Shape(format!(
                "the cube has {} bands, the solver {}",
                cube.bands.len(),
                self.bands.len()
            )));
        }
        if cube.data.len() != cube.plane_len() * cube.bands.len() {
            return Err(EstimateError::Shape(
                "cube data length does not match its size".into(),
            ));
        }
        if let AngleKnowledge::Map { width, height, .. } = self.scene.angle {
            if (width, height) != (cube.width, cube.height) {
                return Err(EstimateError::Shape(format!(
                    "the angle map is {width}×{height}, the cube {}×{}",
                    cube.width, cube.height
                )));
            }
        }
        Ok(())
    }
}

/// Pixel `j` of a chunk held band-major in sorted band order (`flat`, band
/// `r`'s pixel `j` at `r·CHUNK + j`) back into the cube's band order: the
/// chunk is already in cache, where the band planes lie megabytes apart.
#[inline]
fn unflatten(flat: &[f32], j: usize, sorted: &[(usize, f64, f64)], pixel: &mut [f64]) {
    for (r, b) in sorted.iter().enumerate() {
        if let (Some(p), Some(&v)) = (pixel.get_mut(b.0), flat.get(r * detect::CHUNK + j)) {
            *p = f64::from(v);
        }
    }
}

/// Pixels `x0..x0 + m` (m ≤ [`GATHER`]) of the row's band lines (`rows[k·ws
/// + x]`) into `batch`, pixel-major (`batch[i·nb + k]`), widened to `f64`:
/// in blocks of four bands by four pixels, each a 4 × 4 transpose the
/// vector unit does in registers (one load per band and one store per
/// pixel, not one of each per value); the edges value by value.
#[multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
pub(super) fn gather(rows: &[f32], ws: usize, x0: usize, m: usize, nb: usize, batch: &mut [f64]) {
    let (k4, i4) = (nb - nb % 4, m - m % 4);
    let batch = &mut batch[..m * nb];
    let line = |k: usize| &rows[k * ws + x0..k * ws + x0 + m];
    for k in (0..k4).step_by(4) {
        let (l0, l1, l2, l3) = (line(k), line(k + 1), line(k + 2), line(k + 3));
        let quads = l0
            .chunks_exact(4)
            .zip(l1.chunks_exact(4))
            .zip(l2.chunks_exact(4).zip(l3.chunks_exact(4)));
        for (q, pixels) in quads.zip(batch.chunks_exact_mut(4 * nb)) {
            let ((c0, c1), (c2, c3)) = q;
            for (p, px) in pixels.chunks_exact_mut(nb).enumerate() {
                let dst: &mut [f64; 4] = (&mut px[k..k + 4]).try_into().expect("four values");
                *dst = [c0[p], c1[p], c2[p], c3[p]].map(f64::from);
            }
        }
        for i in i4..m {
            for j in 0..4 {
                batch[i * nb + k + j] = f64::from(rows[(k + j) * ws + x0 + i]);
            }
        }
    }
    for k in k4..nb {
        for (i, &v) in line(k).iter().enumerate() {
            batch[i * nb + k] = f64::from(v);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blocked gather puts every value where the plain formula does,
    /// at band counts and batch sizes on and off its blocks of four.
    #[test]
    fn gather_is_the_plain_transpose() {
        let ws = 48;
        for nb in [1, 3, 4, 5, 31, 61] {
            let rows: Vec<f32> = (0..nb * ws).map(|v| v as f32 * 0.5 - 3.0).collect();
            for (x0, m) in [(0, 16), (5, 16), (0, 1), (7, 3), (9, 13), (32, 16)] {
                let mut batch = vec![f64::NAN; GATHER * nb];
                gather(&rows, ws, x0, m, nb, &mut batch);
                for i in 0..m {
                    for k in 0..nb {
                        assert_eq!(
                            batch[i * nb + k],
                            f64::from(rows[k * ws + x0 + i]),
                            "nb {nb} x0 {x0} m {m}: pixel {i} band {k}"
                        );
                    }
                }
                assert!(
                    batch[m * nb..].iter().all(|v| v.is_nan()),
                    "wrote past m pixels"
                );
            }
        }
    }
}
