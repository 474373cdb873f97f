//! Per-pixel state of a sweep in progress, updated incrementally with each
//! band frame, so that when a pixel's last band arrives only the solve
//! remains.
//!
//! A [`SweepBuf`] holds a sweep: the band-sequential reflectance [`Cube`]
//! the solver reads, which bands have arrived (or were given up as
//! missing: NaN planes, which the solver treats as missing bands), the
//! metadata of every frame used (enough for a recording to replay the run),
//! and per-pixel fringe extrema (peaks and valleys with sub-band positions,
//! from a parabola in wavenumber through three neighbouring bands), found as
//! soon as a band and its two spectral neighbours have all arrived. Bands may
//! arrive in any order: each triple of spectral neighbours is examined once,
//! when its last member arrives.
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
use crate::estimate::Cube;
use crate::optics::band::Band;

/// Most extrema kept per pixel (31 bands over 400–700 nm show at most 3–4
/// fringes for the films irid is for; extra ones are counted, not kept).
pub const MAX_EXTREMA: usize = 4;

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

/// One fringe extremum of a pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Extremum {
    /// Sub-band position, nm.
    pub nm: f32,
    /// Interpolated reflectance at the extremum.
    pub value: f32,
    /// Peak (true) or valley.
    pub peak: bool,
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
    /// Extrema per pixel: count (may exceed [`MAX_EXTREMA`]).
    pub n_extrema: Vec<u8>,
    /// Extrema slots, `MAX_EXTREMA` per pixel: position (nm, negative for a
    /// valley) and value.
    pub extrema: Vec<(f32, f32)>,
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

    /// Pixel `i`'s extrema (at most [`MAX_EXTREMA`]), in arrival order.
    pub fn extrema_of(&self, i: usize) -> impl Iterator<Item = Extremum> + '_ {
        let k = self
            .n_extrema
            .get(i)
            .map_or(0, |&k| usize::from(k).min(MAX_EXTREMA));
        // Empty when extrema are not tracked (no slots were allocated).
        self.extrema
            .get(i * MAX_EXTREMA..i * MAX_EXTREMA + k)
            .unwrap_or(&[])
            .iter()
            .map(|&(p, v)| Extremum {
                nm: p.abs(),
                value: v,
                peak: p > 0.0,
            })
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
    /// Whether to track extrema (the solver finds its own; tracking them
    /// here is what a moving-web mode or an extrema-fed fast path needs).
    extrema: bool,
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
            extrema: true,
        }
    }

    /// Turn extrema tracking on or off.
    pub fn track_extrema(mut self, on: bool) -> Tracker {
        self.extrema = on;
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
        let n = self.width * self.height;
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
            n_extrema: vec![0; n],
            extrema: if self.extrema {
                vec![(f32::NAN, f32::NAN); n * MAX_EXTREMA]
            } else {
                Vec::new()
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
        buf.n_extrema.fill(0);
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
        let plane = buf.cube.plane_mut(band);
        for y in 0..self.height {
            let row = self.scene_row(y);
            cal.apply_row(
                band,
                y * w,
                &px[y * w..(y + 1) * w],
                sat,
                m.exposure_us,
                &mut plane[row * w..(row + 1) * w],
            );
        }
        buf.frames[band] = Some(*m);
        if state == BandState::Empty {
            buf.done += 1;
        }
        buf.state[band] = BandState::Present;
        if self.extrema {
            self.update_extrema(buf, band);
        }
        Ok(buf.complete())
    }

    /// Give band `band` up for this sweep: its plane becomes NaN.
    pub fn mark_missing(&self, buf: &mut SweepBuf, band: usize) -> Result<bool, TrackError> {
        let state = *buf.state.get(band).ok_or(TrackError::Band(band))?;
        if state == BandState::Empty {
            buf.cube.plane_mut(band).fill(f32::NAN);
            buf.state[band] = BandState::Missing;
            buf.done += 1;
        }
        Ok(buf.complete())
    }

    fn update_extrema(&self, buf: &mut SweepBuf, band: usize) {
        let nb = self.sorted.len();
        let r = self.rank[band];
        for p in r.saturating_sub(1)..=(r + 1).min(nb.saturating_sub(1)) {
            if p == 0 || p + 1 >= nb {
                continue;
            }
            let (a, b, c) = (self.sorted[p - 1], self.sorted[p], self.sorted[p + 1]);
            if [a, b, c]
                .iter()
                .any(|&i| buf.state[i] != BandState::Present)
            {
                continue;
            }
            let x = [
                1.0 / self.bands[a].center_nm as f32,
                1.0 / self.bands[b].center_nm as f32,
                1.0 / self.bands[c].center_nm as f32,
            ];
            let n = self.width * self.height;
            let (data, counts, slots) = (&buf.cube.data, &mut buf.n_extrema, &mut buf.extrema);
            let (pa, pb, pc) = (
                &data[a * n..(a + 1) * n],
                &data[b * n..(b + 1) * n],
                &data[c * n..(c + 1) * n],
            );
            // Two passes per block of 64 pixels: a branch-free, vectorisable
            // scan for extrema into a bit mask, then the (rare) sub-band fits.
            for base in (0..n).step_by(64) {
                let end = (base + 64).min(n);
                let (qa, qb, qc) = (&pa[base..end], &pb[base..end], &pc[base..end]);
                let mut mask = 0u64;
                for j in 0..qa.len() {
                    let (y0, y1, y2) = (qa[j], qb[j], qc[j]);
                    let e = (y1 > y0) & (y1 >= y2) | (y1 < y0) & (y1 <= y2);
                    mask |= u64::from(e) << j;
                }
                while mask != 0 {
                    let j = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    let i = base + j;
                    let (y0, y1, y2) = (qa[j], qb[j], qc[j]);
                    let (nm, v) = vertex(x, [y0, y1, y2]);
                    let k = usize::from(counts[i]);
                    if k < MAX_EXTREMA {
                        slots[i * MAX_EXTREMA + k] = (if y1 > y0 { nm } else { -nm }, v);
                    }
                    counts[i] = counts[i].saturating_add(1);
                }
            }
        }
    }
}

/// Vertex of the parabola through three points in wavenumber, as (nm,
/// value); falls back to the middle sample if the fit degenerates.
#[inline]
fn vertex(x: [f32; 3], y: [f32; 3]) -> (f32, f32) {
    let (d0, d2) = (x[1] - x[0], x[1] - x[2]);
    let (e0, e2) = (y[1] - y[0], y[1] - y[2]);
    let den = d0 * e2 - d2 * e0;
    if den == 0.0 || !den.is_finite() {
        return (1.0 / x[1], y[1]);
    }
    let xv = x[1] - 0.5 * (d0 * d0 * e2 - d2 * d2 * e0) / den;
    let xv = xv.clamp(x[0].min(x[2]), x[0].max(x[2]));
    // Value from the Lagrange form at xv.
    let l0 = (xv - x[1]) * (xv - x[2]) / ((x[0] - x[1]) * (x[0] - x[2]));
    let l1 = (xv - x[0]) * (xv - x[2]) / ((x[1] - x[0]) * (x[1] - x[2]));
    let l2 = (xv - x[0]) * (xv - x[1]) / ((x[2] - x[0]) * (x[2] - x[1]));
    (1.0 / xv, l0 * y[0] + l1 * y[1] + l2 * y[2])
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

    fn run(order: &[usize]) -> Vec<Extremum> {
        let b = bands();
        let t = Tracker::new(1, 1, &b);
        let cal = Calibrator::identity(1, 1, b.len(), PixelFormat::Y16, 1000);
        let mut buf = t.new_sweep_buf();
        t.begin(&mut buf, 0);
        let mut f = Frame::with_size(1, 1, PixelFormat::Y16);
        f.meta.exposure_us = 1000;
        for (k, &i) in order.iter().enumerate() {
            f.data[0] = value(b[i].center_nm);
            let done = t.ingest(&mut buf, i, &f, &cal).unwrap();
            assert_eq!(done, k + 1 == order.len());
        }
        buf.extrema_of(0).collect()
    }

    #[test]
    fn peak_found_sub_band_in_any_order() {
        for order in [
            vec![0, 1, 2, 3, 4, 5, 6],
            vec![6, 5, 4, 3, 2, 1, 0],
            vec![3, 0, 6, 1, 5, 2, 4],
        ] {
            let e = run(&order);
            assert_eq!(e.len(), 1, "{order:?}");
            assert!(e[0].peak);
            assert!((e[0].nm - 560.0).abs() < 1.0, "{:?}", e[0]);
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
}
