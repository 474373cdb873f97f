//! A synthetic camera: the scene's truth seen through the tunable filter by
//! a noisy 10–16-bit sensor.
//!
//! Noise-free reflectance planes are rendered once per band
//! ([`crate::synth::Renderer::render_band`]); each frame converts them to
//! counts: `dark + k·exposure·T(band)·R`, shot noise (Gaussian with variance
//! ∝ signal), read noise, quantisation, clipping at full scale. The RNG is
//! seeded, and frame timestamps run on a virtual clock (`seq · period`), so a
//! run is bit-reproducible.
//!
//! The camera sees whatever the filter passes *during the exposure*: it reads
//! a shared [`FilterView`] that the (emulated) controller updates, and a
//! frame exposed while the filter settles is a blend of the old and the new
//! band. That is what makes the sequencer's discard rule testable.
//!
//! In triggered mode the camera stands for the pair "controller cycling its
//! palette on sync + camera triggered by its settled output": frame `k` is
//! exposed, settled, at palette entry `k mod n`.

use super::{CameraError, CameraInfo, Frame, FrameSource, PixelFormat, Target};
use crate::optics::band::Band;
use crate::scene::Scene;
use crate::synth::{Renderer, SynthError};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// What the filter passes over time: a transition from one wavelength to
/// another that completes `settle_ns` after `start_ns`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FilterTransition {
    /// Wavelength before the change (None: nothing tuned yet).
    pub from_nm: Option<f64>,
    /// Wavelength being tuned to.
    pub to_nm: Option<f64>,
    /// When the change was commanded, ns (the camera's clock).
    pub start_ns: u64,
    /// How long the liquid crystal takes to settle, ns.
    pub settle_ns: u64,
}

impl FilterTransition {
    /// Fraction of the way to `to_nm` at time `t_ns` (0 … 1).
    pub fn progress(&self, t_ns: u64) -> f64 {
        if t_ns <= self.start_ns {
            return 0.0;
        }
        if self.settle_ns == 0 {
            return 1.0;
        }
        ((t_ns - self.start_ns) as f64 / self.settle_ns as f64).min(1.0)
    }
}

/// A shared view of the filter's optical state: the emulated controller
/// writes it, the synthetic camera reads it.
#[derive(Clone, Debug, Default)]
pub struct FilterView(Arc<Mutex<FilterTransition>>);

impl FilterView {
    /// A filter with nothing tuned.
    pub fn new() -> FilterView {
        FilterView::default()
    }

    /// Command a change to `nm` at `at_ns`, settling in `settle_ns`.
    pub fn tune(&self, nm: f64, at_ns: u64, settle_ns: u64) {
        let mut t = self.0.lock().unwrap_or_else(|p| p.into_inner());
        // Mid-transition, the crystal is closer to whichever end it is nearer.
        let from = if t.progress(at_ns) >= 0.5 {
            t.to_nm
        } else {
            t.from_nm
        };
        *t = FilterTransition {
            from_nm: from,
            to_nm: Some(nm),
            start_ns: at_ns,
            settle_ns,
        };
    }

    /// The current transition.
    pub fn get(&self) -> FilterTransition {
        *self.0.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The sensor and light model.
#[derive(Clone, Debug, PartialEq)]
pub struct SensorModel {
    /// Output format (bits).
    pub format: PixelFormat,
    /// Dark offset, counts.
    pub dark_offset: f64,
    /// Counts per µs of exposure for a white (R = 1) target through a fully
    /// transmitting filter.
    pub counts_per_us: f64,
    /// Read noise, counts RMS.
    pub read_noise: f64,
    /// Counts per photo-electron (shot noise variance = signal · this).
    pub counts_per_electron: f64,
    /// Exposure, µs.
    pub exposure_us: u32,
    /// Frame period, ns (the virtual clock advances by this per frame).
    pub frame_period_ns: u64,
}

impl Default for SensorModel {
    fn default() -> Self {
        // A white target through the most transmissive band fills ~80% of a
        // 16-bit range at 10 ms.
        SensorModel {
            format: PixelFormat::Y16,
            dark_offset: 800.0,
            counts_per_us: 0.8 * 65535.0 / 10_000.0 / 0.5,
            read_noise: 6.0,
            counts_per_electron: 0.25,
            exposure_us: 10_000,
            frame_period_ns: 12_500_000,
        }
    }
}

/// The LCTF's transmission at `nm`: liquid-crystal filters pass far less in
/// the blue than in the red (polariser stack); a smooth 0.1 → 0.5 ramp.
pub fn lctf_transmission(nm: f64) -> f64 {
    let t = ((nm - 400.0) / 300.0).clamp(0.0, 1.0);
    0.1 + 0.4 * t * t * (3.0 - 2.0 * t)
}

/// Options of the synthetic camera.
#[derive(Clone, Debug)]
pub struct SyntheticConfig {
    /// Sensor and light.
    pub sensor: SensorModel,
    /// Seed of the noise.
    pub seed: u64,
    /// Triggered mode: the palette (indices into the bands) the controller
    /// cycles through, one settled trigger per frame. `None`: free-running,
    /// seeing whatever the [`FilterView`] says.
    pub trigger_palette: Option<Vec<usize>>,
    /// Draw each frame's noise from a pool of standard normals twice a
    /// frame long, at a fresh random offset per frame: every frame gets new
    /// noise (a pixel sees independent samples from frame to frame) for
    /// about the cost of a copy, so the camera never limits a large live
    /// run. `false`: a fresh draw per pixel (bit-exact per seed either way).
    pub noise_pool: bool,
    /// Pace frames to the wall clock at `frame_period_ns`.
    pub realtime: bool,
    /// When pacing, run the clock this many times faster than the wall
    /// (to match an emulated controller running faster than a real unit).
    pub speed: f64,
}

impl Default for SyntheticConfig {
    fn default() -> Self {
        SyntheticConfig {
            sensor: SensorModel::default(),
            seed: 1,
            trigger_palette: None,
            noise_pool: false,
            realtime: false,
            speed: 1.0,
        }
    }
}

/// The synthetic camera.
pub struct SyntheticCamera {
    bands: Vec<Band>,
    /// Noise-free reflectance per band, row-major.
    planes: Vec<Vec<f32>>,
    /// Standard normals for [`SyntheticConfig::noise_pool`] (empty: none).
    pool: Vec<f32>,
    /// One frame's fresh draws where there is no pool.
    draw: Vec<f32>,
    width: u32,
    height: u32,
    cfg: SyntheticConfig,
    filter: FilterView,
    target: Target,
    rng: ChaCha8Rng,
    seq: u64,
    /// Wall time and virtual time of the first paced frame.
    started: Option<(std::time::Instant, u64)>,
}

impl SyntheticCamera {
    /// A camera looking at `scene` (which needs `[truth]`), through a filter
    /// with these bands. Renders every band's plane now.
    pub fn new(
        scene: &Scene,
        bands: &[Band],
        filter: FilterView,
        cfg: SyntheticConfig,
    ) -> Result<SyntheticCamera, SynthError> {
        let r = Renderer::new(scene)?;
        let n = r.width() * r.height();
        let mut planes = Vec::with_capacity(bands.len());
        for b in bands {
            let mut p = vec![0.0f32; n];
            r.render_band(b, &mut p)?;
            planes.push(p);
        }
        let mut cam = SyntheticCamera {
            bands: bands.to_vec(),
            planes,
            pool: Vec::new(),
            draw: Vec::new(),
            width: r.width() as u32,
            height: r.height() as u32,
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            cfg,
            filter,
            target: Target::Scene,
            seq: 0,
            started: None,
        };
        if cam.cfg.noise_pool {
            cam.pool = (0..2 * n)
                .map(|_| StandardNormal.sample(&mut cam.rng))
                .collect();
        }
        Ok(cam)
    }

    /// The shared filter view this camera looks through.
    pub fn filter_view(&self) -> FilterView {
        self.filter.clone()
    }

    /// Pace frames to the wall clock (or not).
    pub fn set_realtime(&mut self, on: bool) {
        self.cfg.realtime = on;
        self.started = None;
    }

    /// When pacing, run the clock `speed` times faster than the wall
    /// (non-positive: real time).
    pub fn set_speed(&mut self, speed: f64) {
        self.cfg.speed = speed;
        self.started = None;
    }

    /// The bands the camera knows how to render.
    pub fn bands(&self) -> &[Band] {
        &self.bands
    }

    fn band_of(&self, nm: Option<f64>) -> Option<usize> {
        let nm = nm?;
        self.bands
            .iter()
            .enumerate()
            .min_by(|a, b| {
                (a.1.center_nm - nm)
                    .abs()
                    .total_cmp(&(b.1.center_nm - nm).abs())
            })
            .filter(|(_, b)| (b.center_nm - nm).abs() < 0.5)
            .map(|(i, _)| i)
    }

    /// Counts for a blend of band `a` (weight 1 − α) and band `b` (α).
    fn render_counts(&mut self, a: Option<usize>, b: Option<usize>, alpha: f64, out: &mut [u16]) {
        let s = &self.cfg.sensor;
        let k = s.counts_per_us * f64::from(s.exposure_us);
        let gain_of = |band: Option<usize>| {
            band.map_or(0.0, |i| k * lctf_transmission(self.bands[i].center_nm))
        };
        let (ga, gb) = (gain_of(a) * (1.0 - alpha), gain_of(b) * alpha);
        let max = f64::from(s.format.max_value());
        let (dark, read2, cpe) = (
            s.dark_offset,
            s.read_noise * s.read_noise,
            s.counts_per_electron,
        );
        let white = match self.target {
            Target::Scene => None,
            Target::Dark => Some(0.0),
            Target::White(r) => Some(r),
        };
        let n = out.len();
        let p = Counts {
            dark: dark as f32,
            read2: read2 as f32,
            cpe: cpe as f32,
            max: max as f32,
        };
        // A missing band contributes nothing (its gain is zero), so the
        // other band's plane stands in for it.
        let plane = |band: Option<usize>| band.map(|i| &self.planes[i][..n]);
        let planes = match (white, plane(a).or(plane(b)), plane(b).or(plane(a))) {
            (None, Some(pa), Some(pb)) => Ok((pa, pb)),
            (w, _, _) => Err(w.map_or(0.0, |w| ga * w + gb * w)),
        };
        // The frame's noise: a window of the pool at a fresh offset, or a
        // fresh draw per pixel (drawn first, so the pixel loop carries no
        // branches and vectorises).
        if self.pool.len() >= 2 * n && n > 0 {
            let off = self.rng.random_range(0..=self.pool.len() - n);
            p.frame(planes, (ga, gb), &self.pool[off..off + n], out);
        } else {
            self.draw.clear();
            let rng = &mut self.rng;
            self.draw.extend((0..n).map(|_| {
                let z: f64 = StandardNormal.sample(&mut *rng);
                z as f32
            }));
            p.frame(planes, (ga, gb), &self.draw, out);
        }
    }
}

/// The sensor's response: dark offset, read and shot noise, clipping.
/// In f32: counts are integers below 2¹⁶, which f32 holds exactly, and the
/// noise needs no more than its 24 bits; eight pixels per AVX2 vector.
#[derive(Clone, Copy)]
struct Counts {
    dark: f32,
    read2: f32,
    cpe: f32,
    max: f32,
}

impl Counts {
    /// One frame: the two bands' planes blended by `gains` (or a uniform
    /// signal), the standard normal draws `z`, into `out`.
    fn frame(
        &self,
        planes: Result<(&[f32], &[f32]), f64>,
        (ga, gb): (f64, f64),
        z: &[f32],
        out: &mut [u16],
    ) {
        frame_counts(*self, planes, (ga as f32, gb as f32), z, out);
    }

    /// The count for an expected `signal` (counts above dark) and a
    /// standard normal draw `z`.
    #[inline(always)]
    fn count(&self, signal: f32, z: f32) -> u16 {
        let signal = signal.max(0.0);
        let v = self.dark + signal + z * (self.read2 + signal * self.cpe).sqrt();
        // Round half up by truncation after clamping (non-negative):
        // `round` is a libm call in this per-pixel loop.
        (v.clamp(0.0, self.max) + 0.5).min(self.max) as i32 as u16
    }
}

/// [`Counts::frame`]'s loops, compiled for the best vector unit.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1", "aarch64+neon"))]
fn frame_counts(
    p: Counts,
    planes: Result<(&[f32], &[f32]), f64>,
    (ga, gb): (f32, f32),
    z: &[f32],
    out: &mut [u16],
) {
    match planes {
        Ok((pa, pb)) => {
            for (((o, &z), &ra), &rb) in out.iter_mut().zip(z).zip(pa).zip(pb) {
                *o = p.count(ga * ra + gb * rb, z);
            }
        }
        Err(signal) => {
            let signal = signal as f32;
            for (o, &z) in out.iter_mut().zip(z) {
                *o = p.count(signal, z);
            }
        }
    }
}

impl FrameSource for SyntheticCamera {
    fn info(&self) -> CameraInfo {
        CameraInfo {
            id: format!("synthetic seed={}", self.cfg.seed),
            width: self.width,
            height: self.height,
            format: self.cfg.sensor.format,
            exposure_us: self.cfg.sensor.exposure_us,
            gain: 1.0,
        }
    }

    fn next_frame(&mut self, out: &mut Frame, _timeout: Duration) -> Result<(), CameraError> {
        let n = self.width as usize * self.height as usize;
        if out.data.len() < n {
            return Err(CameraError::BufferTooSmall {
                have: out.data.len(),
                need: n,
            });
        }
        let seq = self.seq;
        self.seq += 1;
        let s = &self.cfg.sensor;
        let t0 = seq * s.frame_period_ns;
        if self.cfg.realtime {
            let (start, v0) = *self
                .started
                .get_or_insert_with(|| (std::time::Instant::now(), t0));
            let speed = if self.cfg.speed > 0.0 {
                self.cfg.speed
            } else {
                1.0
            };
            let due = start + Duration::from_secs_f64((t0 - v0) as f64 / 1e9 / speed);
            let now = std::time::Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
        let exposure_ns = u64::from(s.exposure_us) * 1000;
        let mut trigger = None;
        if let Some(palette) = &self.cfg.trigger_palette {
            if !palette.is_empty() {
                let b = palette[(seq % palette.len() as u64) as usize];
                let nm = self.bands.get(b).map_or(0.0, |b| b.center_nm);
                self.filter.tune(nm, t0, 0);
                trigger = Some(seq);
            }
        }
        let tr = self.filter.get();
        // The camera integrates over the exposure; the blend at mid-exposure
        // is a fair stand-in for the integral of a smooth transition.
        let alpha = tr.progress(t0 + exposure_ns / 2);
        let (a, b) = (self.band_of(tr.from_nm), self.band_of(tr.to_nm));
        let dst = &mut out.data[..n];
        self.render_counts(a, b, alpha, dst);
        let s = &self.cfg.sensor;
        out.meta = super::FrameMeta {
            seq,
            timestamp_ns: t0,
            exposure_us: s.exposure_us,
            gain: 1.0,
            format: s.format,
            width: self.width,
            height: self.height,
            trigger,
            encoder: None,
        };
        Ok(())
    }

    fn set_exposure(&mut self, exposure_us: u32) -> Result<u32, CameraError> {
        let max_us = (self.cfg.sensor.frame_period_ns / 1000) as u32;
        let e = exposure_us.clamp(1, max_us.max(1));
        if e != self.cfg.sensor.exposure_us {
            self.cfg.sensor.exposure_us = e;
        }
        Ok(e)
    }

    fn set_target(&mut self, target: Target) -> Result<bool, CameraError> {
        self.target = target;
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(cfg: SyntheticConfig) -> SyntheticCamera {
        let scene = Scene::paper_cylinder();
        let bands = scene.bands.clone().unwrap();
        SyntheticCamera::new(&scene, &bands, FilterView::new(), cfg).unwrap()
    }

    #[test]
    fn frames_are_reproducible_and_settling_frames_are_blends() {
        let mut a = cam(SyntheticConfig::default());
        let mut b = cam(SyntheticConfig::default());
        let view = a.filter_view();
        let info = a.info();
        let mut fa = Frame::with_size(info.width, info.height, info.format);
        let mut fb = fa.clone();
        view.tune(400.0, 0, 0);
        b.filter_view().tune(400.0, 0, 0);
        a.next_frame(&mut fa, Duration::ZERO).unwrap();
        b.next_frame(&mut fb, Duration::ZERO).unwrap();
        assert_eq!(fa, fb);
        let settled_400 = fa.data.clone();
        // Change to 700 nm right at the next frame's start with a settle time
        // of one frame: that frame is half-way, the one after is clean.
        let period = a.cfg.sensor.frame_period_ns;
        view.tune(700.0, period, period);
        a.next_frame(&mut fa, Duration::ZERO).unwrap();
        let blend = fa.data.clone();
        a.next_frame(&mut fa, Duration::ZERO).unwrap();
        let mean = |v: &[u16]| v.iter().map(|&x| f64::from(x)).sum::<f64>() / v.len() as f64;
        let (m400, mb, m700) = (mean(&settled_400), mean(&blend), mean(&fa.data));
        assert!(
            (m400 < mb && mb < m700) || (m400 > mb && mb > m700),
            "{m400} {mb} {m700}"
        );
    }

    /// Every frame gets fresh noise, pooled or drawn per pixel: two settled
    /// frames of one band differ by noise of twice the sensor's variance
    /// (read noise plus shot noise at the pixel's signal), within the
    /// sampling error of the estimate (~2.5 % for 2 000 pixels: 5σ bound).
    #[test]
    fn every_frame_gets_fresh_noise_of_the_sensors_variance() {
        for pool in [false, true] {
            let mut c = cam(SyntheticConfig {
                noise_pool: pool,
                ..Default::default()
            });
            let view = c.filter_view();
            let info = c.info();
            view.tune(c.bands()[10].center_nm, 0, 0);
            let mut f1 = Frame::with_size(info.width, info.height, info.format);
            let mut f2 = f1.clone();
            c.next_frame(&mut f1, Duration::ZERO).unwrap();
            c.next_frame(&mut f2, Duration::ZERO).unwrap();
            let s = c.cfg.sensor.clone();
            let (mut num, mut want, mut n) = (0.0, 0.0, 0.0f64);
            for (a, b) in f1.data.iter().zip(&f2.data) {
                let d = f64::from(*a) - f64::from(*b);
                num += d * d;
                let signal = 0.5 * (f64::from(*a) + f64::from(*b)) - s.dark_offset;
                want += 2.0
                    * (s.read_noise * s.read_noise + signal.max(0.0) * s.counts_per_electron)
                    + 2.0 / 12.0;
                n += 1.0;
            }
            let ratio = num / want;
            let tol = 5.0 * (2.0 / n).sqrt();
            assert!(
                (ratio - 1.0).abs() < tol,
                "pool {pool}: variance ratio {ratio} (±{tol})"
            );
        }
    }
}
