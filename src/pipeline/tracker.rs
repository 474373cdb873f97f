//! Per-pixel state of a sweep in progress, updated incrementally with each
//! band frame, so that when a pixel's last band arrives only the solve
//! remains.
//!
//! A [`SweepBuf`] holds a sweep: the band-sequential reflectance [`Cube`]
//! the solver reads, which bands have arrived (or were given up as
//! missing: NaN planes, which the solver treats as missing bands), the
//! metadata of every frame used (enough for a recording to replay the run),
//! and each pixel's fringe-extremum candidates
//! ([`crate::estimate::detect::CandidatePlanes`]: local maxima and minima
//! of the smoothed spectrum, as bit planes), decided as soon as a band and
//! the neighbours its smoothing needs have all arrived. Bands may arrive in
//! any order: each candidate band is decided once, when the last of its
//! window arrives. The `fast` solver takes the candidates from here and
//! skips its own detection pass, so when the last band arrives only the
//! fits and closed forms remain.
//!
//! Buffers are sized once ([`Tracker::new_sweep_buf`]) and reused sweep
//! after sweep: nothing in the per-frame path allocates.
//!
//! State is keyed by *scene row* (`scene_row(sensor_row)`, the identity for a
//! static object). Following a moving web, where a stretch of film collects
//! its bands at different camera rows, is a change of that mapping and of
//! when a row counts as complete, not of the state.

use super::calibration::Calibrator;
use crate::device::camera::{Frame, FrameMeta};
use crate::estimate::detect::CandidatePlanes;
use crate::estimate::Cube;
use crate::optics::band::Band;

/// Tracking errors (per frame; the frame is refused, the run goes on).
#[derive(Debug, thiserror::Error)]
pub enum TrackError {
    /// The frame's size is not the tracker's.
    #[error("frame {seq}: {got_w}×{got_h}, expected {want_w}×{want_h}")]
    FrameSize {
        /// Sequence number.
        seq: u64,
        /// Frame width.
        got_w: u32,
        /// Frame height.
        got_h: u32,
        /// Expected width.
        want_w: usize,
        /// Expected height.
        want_h: usize,
    },
    /// The band index is out of range.
    #[error("band {0} out of range")]
    Band(usize),
}

/// Whether a band of the sweep has arrived.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BandState {
    /// Not yet.
    Empty,
    /// Filled from a frame.
    Present,
    /// Given up: the plane is NaN.
    Missing,
}

/// A sweep being filled, or filled.
#[derive(Clone, Debug)]
pub struct SweepBuf {
    /// Sweep index.
    pub sweep: u64,
    /// Reflectance, band-sequential, scene rows.
    pub cube: Cube,
    /// Per band.
    pub state: Vec<BandState>,
    /// Metadata of the frame used per band.
    pub frames: Vec<Option<FrameMeta>>,
    /// Bands present or missing.
    pub done: usize,
    /// Extremum candidates, when tracked (and at most
    /// [`crate::estimate::detect::MAX_DETECT_BANDS`] bands).
    pub candidates: Option<CandidatePlanes>,
    /// Frames lost or refused while this sweep was filled.
    pub frames_dropped: u64,
}

impl SweepBuf {
    /// Whether every band has arrived or been given up.
    pub fn complete(&self) -> bool {
        self.done == self.state.len()
    }

    /// Bands given up.
    pub fn missing(&self) -> usize {
        self.state
            .iter()
            .filter(|s| **s == BandState::Missing)
            .count()
    }
}

/// Per-sweep incremental tracking (see the module header).
#[derive(Clone, Debug)]
pub struct Tracker {
    width: usize,
    height: usize,
    bands: Vec<Band>,
    /// Band indices in ascending wavelength.
    sorted: Vec<usize>,
    /// Position of each band in `sorted`.
    rank: Vec<usize>,
    /// Whether to track extremum candidates.
    candidates: bool,
}

impl Tracker {
    /// A tracker for `width × height` frames in `bands`.
    pub fn new(width: usize, height: usize, bands: &[Band]) -> Tracker {
        let mut sorted: Vec<usize> = (0..bands.len()).collect();
        sorted.sort_by(|&a, &b| bands[a].center_nm.total_cmp(&bands[b].center_nm));
        let mut rank = vec![0; bands.len()];
        for (p, &b) in sorted.iter().enumerate() {
            rank[b] = p;
        }
        Tracker {
            width,
            height,
            bands: bands.to_vec(),
            sorted,
            rank,
            candidates: true,
        }
    }

    /// Turn the tracking of extremum candidates on or off.
    pub fn track_extrema(mut self, on: bool) -> Tracker {
        self.candidates = on;
        self
    }

    /// The bands, in plane order.
    pub fn bands(&self) -> &[Band] {
        &self.bands
    }

    /// Frame size.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// The scene row a sensor row's pixels belong to (identity for a static
    /// object; a moving web shifts it by the travel since the sweep began).
    #[inline]
    pub fn scene_row(&self, sensor_row: usize) -> usize {
        sensor_row
    }

    /// A sweep buffer of the right size: the one allocation per buffer.
    pub fn new_sweep_buf(&self) -> SweepBuf {
        // Filled (NaN: nothing arrived yet) rather than calloc'ed, so every
        // page is touched here, once, and not faulted in on the frame path.
        let mut cube = Cube::zeros(self.width, self.height, self.bands.clone());
        cube.data.fill(f32::NAN);
        SweepBuf {
            sweep: 0,
            cube,
            state: vec![BandState::Empty; self.bands.len()],
            frames: vec![None; self.bands.len()],
            done: 0,
            candidates: if self.candidates {
                CandidatePlanes::new(self.width, self.height, self.bands.len())
            } else {
                None
            },
            frames_dropped: 0,
        }
    }

    /// Reset `buf` for sweep `sweep` (no allocation).
    pub fn begin(&self, buf: &mut SweepBuf, sweep: u64) {
        buf.sweep = sweep;
        buf.state.fill(BandState::Empty);
        buf.frames.fill(None);
        buf.done = 0;
        if let Some(c) = &mut buf.candidates {
            c.clear();
        }
        buf.frames_dropped = 0;
    }

    /// Calibrate `frame` into band `band`'s plane and update the extrema.
    /// Returns whether the sweep is now complete. A band already filled is
    /// overwritten only if it was missing (a late frame).
    pub fn ingest(
        &self,
        buf: &mut SweepBuf,
        band: usize,
        frame: &Frame,
        cal: &Calibrator,
    ) -> Result<bool, TrackError> {
        let m = &frame.meta;
        let px = match frame.pixels() {
            Ok(px) if (m.width as usize, m.height as usize) == (self.width, self.height) => px,
            _ => {
                return Err(TrackError::FrameSize {
                    seq: m.seq,
                    got_w: m.width,
                    got_h: m.height,
                    want_w: self.width,
                    want_h: self.height,
                })
            }
        };
        let state = *buf.state.get(band).ok_or(TrackError::Band(band))?;
        if state == BandState::Present {
            return Ok(buf.complete());
        }
        let sat = m.format.max_value();
        let w = self.width;
        buf.state[band] = BandState::Present;
        let decide = self.newly_decided(buf, band);
        let SweepBuf {
            cube, candidates, ..
        } = buf;
        // Row by row: calibrate, then (the new row still in cache) decide
        // the candidate bands whose window this band completed.
        for y in 0..self.height {
            let row = self.scene_row(y);
            cal.apply_row(
                band,
                y * w,
                &px[y * w..(y + 1) * w],
                sat,
                m.exposure_us,
                &mut cube.plane_mut(band)[row * w..(row + 1) * w],
            );
            if let Some(cp) = candidates.as_mut().filter(|_| self.candidates) {
                self.candidates_row(cube, cp, band, row, &decide);
            }
        }
        buf.frames[band] = Some(*m);
        if state == BandState::Empty {
            buf.done += 1;
        }
        Ok(buf.complete())
    }

    /// The sorted candidate bands (up to five) whose window `band`'s
    /// arrival completes; `band` is already marked arrived.
    fn newly_decided(&self, buf: &SweepBuf, band: usize) -> [Option<usize>; 5] {
        let mut out = [None; 5];
        let Some(cp) = buf.candidates.as_ref().filter(|_| self.candidates) else {
            return out;
        };
        let (nb, r) = (self.sorted.len(), self.rank[band]);
        for (slot, c) in out
            .iter_mut()
            .zip(r.saturating_sub(2)..=(r + 2).min(nb - 1))
        {
            if c >= 1
                && c + 1 < nb
                && cp
                    .window(c)
                    .all(|p| buf.state[self.sorted[p]] != BandState::Empty)
            {
                *slot = Some(c);
            }
        }
        out
    }

    /// Row `row` of the candidate planes after `band`'s row arrived.
    fn candidates_row(
        &self,
        cube: &Cube,
        cp: &mut CandidatePlanes,
        band: usize,
        row: usize,
        decide: &[Option<usize>; 5],
    ) {
        let w = self.width;
        let row_of = |b: usize| &cube.plane(b)[row * w..(row + 1) * w];
        cp.add_row(row, row_of(band));
        for c in decide.iter().flatten() {
            let mut rows: [&[f32]; 5] = [&[]; 5];
            let win = cp.window(*c);
            let k = win.clone().count();
            for (slot, p) in rows.iter_mut().zip(win) {
                *slot = row_of(self.sorted[p]);
            }
            cp.set_candidate(row, *c, &rows[..k]);
        }
    }

    /// Give band `band` up for this sweep: its plane becomes NaN.
    pub fn mark_missing(&self, buf: &mut SweepBuf, band: usize) -> Result<bool, TrackError> {
        let state = *buf.state.get(band).ok_or(TrackError::Band(band))?;
        if state == BandState::Empty {
            buf.cube.plane_mut(band).fill(f32::NAN);
            buf.state[band] = BandState::Missing;
            buf.done += 1;
            // A missing band's NaN samples flag its pixels, as the solver's
            // own detection would.
            let decide = self.newly_decided(buf, band);
            let SweepBuf {
                cube, candidates, ..
            } = buf;
            if let Some(cp) = candidates.as_mut().filter(|_| self.candidates) {
                for row in 0..self.height {
                    self.candidates_row(cube, cp, band, row, &decide);
                }
            }
        }
        Ok(buf.complete())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::camera::PixelFormat;

    fn bands() -> Vec<Band> {
        (0..7)
            .map(|i| Band {
                center_nm: 400.0 + 50.0 * i as f64,
                fwhm_nm: 0.0,
            })
            .collect()
    }

    /// A 1×1 "spectrum" with a peak exactly at 1/x = 1/(1/550): values from
    /// a parabola in wavenumber.
    fn value(nm: f64) -> u16 {
        let x = 1.0 / nm - 1.0 / 560.0;
        (60000.0 - 2.0e10 * x * x) as u16
    }

    /// Ingest a `w × h` sweep in `order`, band `missing` given up, and
    /// return the buffer.
    fn run(w: usize, h: usize, order: &[usize], missing: Option<usize>) -> SweepBuf {
        let b = bands();
        let t = Tracker::new(w, h, &b);
        let cal = Calibrator::identity(w as u32, h as u32, b.len(), PixelFormat::Y16, 1000);
        let mut buf = t.new_sweep_buf();
        t.begin(&mut buf, 0);
        let mut f = Frame::with_size(w as u32, h as u32, PixelFormat::Y16);
        f.meta.exposure_us = 1000;
        for (k, &i) in order.iter().enumerate() {
            let done = if Some(i) == missing {
                t.mark_missing(&mut buf, i).unwrap()
            } else {
                for (p, v) in f.data.iter_mut().enumerate() {
                    // A peak near 560 nm, tilted and varied per pixel, and
                    // one saturated (NaN) sample.
                    *v = value(b[i].center_nm).saturating_sub((p * 37 % 11) as u16 * 300);
                    if p == 5 && i == 2 {
                        *v = u16::MAX;
                    }
                }
                t.ingest(&mut buf, i, &f, &cal).unwrap()
            };
            assert_eq!(done, k + 1 == order.len());
        }
        buf
    }

    /// The candidates tracked band by band, in any order and with a band
    /// missing, are those the solver's own detection finds on the complete
    /// cube; the peak is at the 550 nm band.
    #[test]
    fn candidates_tracked_in_any_order_match_detection_on_the_cube() {
        use crate::estimate::detect::{detect, Candidates, CHUNK};
        let (w, h) = (70, 2);
        for (order, missing) in [
            (vec![0, 1, 2, 3, 4, 5, 6], None),
            (vec![6, 5, 4, 3, 2, 1, 0], None),
            (vec![3, 0, 6, 1, 5, 2, 4], None),
            (vec![3, 0, 6, 1, 5, 2, 4], Some(5)),
        ] {
            let buf = run(w, h, &order, missing);
            let cp = buf.candidates.as_ref().unwrap();
            for y in 0..h {
                for k in 0..w.div_ceil(CHUNK) {
                    let (x0, m) = (k * CHUNK, (w - k * CHUNK).min(CHUNK));
                    let rows: Vec<&[f32]> = (0..7)
                        .map(|b| &buf.cube.plane(b)[y * w + x0..y * w + x0 + m])
                        .collect();
                    let (mut want, mut got) = (Candidates::default(), Candidates::default());
                    detect(&rows, &mut want);
                    cp.unpack(y, k, &mut got);
                    assert_eq!(want.maxima[..m], got.maxima[..m], "{order:?} {missing:?}");
                    assert_eq!(want.minima[..m], got.minima[..m], "{order:?} {missing:?}");
                    assert_eq!(want.bad[..m], got.bad[..m], "{order:?} {missing:?}");
                    if missing.is_none() && y == 0 && k == 0 {
                        assert_eq!(got.maxima[0], 1 << 3, "{order:?}");
                        assert!(got.bad[5] && !got.bad[0]);
                    }
                }
            }
        }
    }

    #[test]
    fn wrong_size_frame_is_refused_and_missing_bands_are_nan() {
        let b = bands();
        let t = Tracker::new(2, 2, &b);
        let cal = Calibrator::identity(2, 2, b.len(), PixelFormat::Y16, 1000);
        let mut buf = t.new_sweep_buf();
        t.begin(&mut buf, 0);
        let mut f = Frame::with_size(2, 2, PixelFormat::Y16);
        f.meta.height = 4;
        assert!(t.ingest(&mut buf, 0, &f, &cal).is_err());
        f.meta.height = 2;
        assert!(t.ingest(&mut buf, 99, &f, &cal).is_err());
        t.mark_missing(&mut buf, 3).unwrap();
        assert!(buf.cube.plane(3).iter().all(|v| v.is_nan()));
        assert_eq!(buf.missing(), 1);
    }

    #[test]
    fn calibration_tags_reach_the_sweep_cube() {
        use crate::estimate::Reason;
        use crate::pipeline::calibration::{flag, Calibrator};
        let b = bands();
        let n = 4;
        let t = Tracker::new(2, 2, &b);
        // Pixel 1 dark in band 2, pixel 2 saturated in the white of band 4;
        // pixel 3's sample saturates in band 5 (and is dark in band 1).
        let mut flags = vec![0u8; n * b.len()];
        flags[2 * n + 1] = flag::DARK;
        flags[4 * n + 2] = flag::SATURATED | flag::DEAD;
        flags[n + 3] = flag::DEAD;
        let dark = vec![100.0; n * b.len()];
        let white = vec![20000.0; n * b.len()];
        let cal = Calibrator::from_planes(n, dark, white, &flags, 0.9, 1000);
        let mut buf = t.new_sweep_buf();
        t.begin(&mut buf, 0);
        for band in 0..b.len() {
            let mut f = Frame::with_size(2, 2, PixelFormat::Y16);
            f.meta.exposure_us = 1000;
            f.data.copy_from_slice(&[5000, 5000, 5000, 5000]);
            if band == 5 {
                f.data[3] = u16::MAX;
            }
            t.ingest(&mut buf, band, &f, &cal).unwrap();
        }
        let c = &buf.cube;
        assert_eq!(c.input_reason(0, 0), None);
        assert!(c.plane(2)[0].is_finite());
        assert_eq!(c.input_reason(1, 0), Some(Reason::Dark));
        assert_eq!(c.input_reason(0, 1), Some(Reason::Saturated));
        assert_eq!(c.input_reason(1, 1), Some(Reason::Saturated));
    }
}
