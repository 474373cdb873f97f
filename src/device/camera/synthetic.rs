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
    /// When pacing, the frames the driver keeps for a reader that is late
    /// (a V4L2 queue of buffers): an older frame is lost, as a real camera
    /// loses it, and shows as a gap in the frame counter. 0 keeps every
    /// frame (an unbounded queue: a reader that fell behind — during the
    /// calibration, say — then reads seconds-old frames, and the rig seems
    /// to step faster than its filter settles while it catches up).
    pub queue_frames: u32,
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
            queue_frames: 8,
        }
    }
}

/// The light changing during a run, after the calibration's references
/// were taken (a lamp dimming as it ages or warms, a lamp replaced): from
/// `after_frames` frames after it is set ([`SyntheticCamera::set_lamp`])
/// the light moves linearly, over `over_frames` frames (0: at once), to
/// `factor` times what it was, and stays there.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LampChange {
    /// Frames before the change begins.
    pub after_frames: u64,
    /// Frames it takes.
    pub over_frames: u64,
    /// The light after it, relative to before.
    pub factor: f64,
}

impl LampChange {
    /// The light `frames` frames after the change was set.
    pub fn light_at(&self, frames: u64) -> f64 {
        let Some(into) = frames.checked_sub(self.after_frames) else {
            return 1.0;
        };
        if into >= self.over_frames {
            return self.factor;
        }
        1.0 + (self.factor - 1.0) * into as f64 / self.over_frames as f64
    }
}

/// How a frame sees the scene: the light relative to the calibration's
/// ([`LampChange`]), and whether through the drifted filter
/// ([`SyntheticCamera::drift_filter`]).
#[derive(Clone, Copy)]
struct Lit {
    light: f64,
    drifted: bool,
}

/// The synthetic camera.
pub struct SyntheticCamera {
    bands: Vec<Band>,
    /// Noise-free reflectance per band, row-major.
    planes: Vec<Vec<f32>>,
    /// Standard normals for [`SyntheticConfig::noise_pool`] (empty: none),
    /// quantised ([`POOL_SCALE`]).
    pool: Vec<i16>,
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
    /// A change of the light, and the frame it was set at.
    lamp: Option<(u64, LampChange)>,
    /// The scene, to render the bands again where the filter drifts.
    scene: Scene,
    /// Planes rendered at the filter's drifted centres, and the first
    /// frame that sees them.
    drifted: Option<(u64, Vec<Vec<f32>>)>,
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
            lamp: None,
            scene: scene.clone(),
            drifted: None,
        };
        if cam.cfg.noise_pool {
            cam.pool = normal_pool(&mut cam.rng, 2 * n);
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

    /// Change the light from the next frame on (None: the light stays as
    /// it is now).
    pub fn set_lamp(&mut self, change: Option<LampChange>) {
        self.lamp = change.map(|c| (self.seq, c));
    }

    /// The filter's pass bands drift (with temperature, say) by `shift_nm`
    /// from `after_frames` frames on: each band's frames are rendered at
    /// its centre plus the shift, while the controller and the headers
    /// still name the nominal one.
    pub fn drift_filter(&mut self, after_frames: u64, shift_nm: f64) -> Result<(), SynthError> {
        let r = Renderer::new(&self.scene)?;
        let n = r.width() * r.height();
        let mut planes = Vec::with_capacity(self.bands.len());
        for b in &self.bands {
            let moved = Band {
                center_nm: b.center_nm + shift_nm,
                ..*b
            };
            let mut p = vec![0.0f32; n];
            r.render_band(&moved, &mut p)?;
            planes.push(p);
        }
        self.drifted = Some((self.seq + after_frames, planes));
        Ok(())
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
    /// Frame `seq` into `out` (its first `n` samples rendered only where
    /// `wanted` says so): the trigger's filter command, the metadata, and
    /// the noise stream advanced as if rendered.
    fn produce(
        &mut self,
        seq: u64,
        out: &mut Frame,
        n: usize,
        wanted: &mut dyn FnMut(&super::FrameMeta) -> bool,
    ) -> bool {
        let s = &self.cfg.sensor;
        let t0 = seq * s.frame_period_ns;
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
        let want = wanted(&out.meta);
        // The noise stream advances as if the frame were rendered, so
        // skipping one changes no other frame.
        let light = self
            .lamp
            .map_or(1.0, |(set, c)| c.light_at(seq.saturating_sub(set)));
        let drifted = self.drifted.as_ref().is_some_and(|(from, _)| seq >= *from);
        let scene = Lit { light, drifted };
        self.render_counts(a, b, alpha, scene, &mut out.data[..n], want);
        want
    }

    fn render_counts(
        &mut self,
        a: Option<usize>,
        b: Option<usize>,
        alpha: f64,
        Lit { light, drifted }: Lit,
        out: &mut [u16],
        render: bool,
    ) {
        let s = &self.cfg.sensor;
        let k = light * s.counts_per_us * f64::from(s.exposure_us);
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
        let set = match &self.drifted {
            Some((_, planes)) if drifted => planes,
            _ => &self.planes,
        };
        let plane = |band: Option<usize>| band.map(|i| &set[i][..n]);
        let planes = match (white, plane(a).or(plane(b)), plane(b).or(plane(a))) {
            (None, Some(pa), Some(pb)) => Ok((pa, pb)),
            (w, _, _) => Err(w.map_or(0.0, |w| ga * w + gb * w)),
        };
        // The frame's noise: a window of the pool at a fresh offset, or a
        // fresh draw per pixel (drawn first, so the pixel loop carries no
        // branches and vectorises).
        if self.pool.len() >= 2 * n && n > 0 {
            let off = self.rng.random_range(0..=self.pool.len() - n);
            if render {
                let z = Draws::Pool(&self.pool[off..off + n]);
                frame_counts(p, Signal::of(planes, (ga, gb)), z, out);
            }
        } else {
            self.draw.clear();
            let rng = &mut self.rng;
            self.draw.extend((0..n).map(|_| {
                let z: f64 = StandardNormal.sample(&mut *rng);
                z as f32
            }));
            if render {
                let z = Draws::Fresh(&self.draw);
                frame_counts(p, Signal::of(planes, (ga, gb)), z, out);
            }
        }
    }
}

/// The pool's standard normals are stored as `i16` in units of
/// `1 / POOL_SCALE` (±8 σ; a step of 2.4e-4 σ): half the bytes of `f32`
/// to stream per frame, where a 1280 × 1024 frame is memory-bound.
const POOL_SCALE: f32 = 4096.0;

/// A pool of `len` standard normals, quantised as [`POOL_SCALE`] says.
fn normal_pool(rng: &mut ChaCha8Rng, len: usize) -> Vec<i16> {
    (0..len)
        .map(|_| {
            let z: f64 = StandardNormal.sample(&mut *rng);
            (z * f64::from(POOL_SCALE)).round().clamp(-32767.0, 32767.0) as i16
        })
        .collect()
}

/// A frame's expected signal (counts above dark) per pixel.
#[derive(Clone, Copy)]
enum Signal<'a> {
    /// Two bands' planes blended (the filter in transit).
    Blend(&'a [f32], &'a [f32], f32, f32),
    /// One band's plane (the filter settled: the other's weight is zero).
    One(&'a [f32], f32),
    /// The same signal everywhere (a calibration target).
    Uniform(f32),
}

impl<'a> Signal<'a> {
    /// The planes and gains of [`SyntheticCamera::render_counts`]: a
    /// blend whose one weight is zero reads the other plane alone (the
    /// same numbers: `0·a + g·b = g·b`).
    fn of(planes: Result<(&'a [f32], &'a [f32]), f64>, (ga, gb): (f64, f64)) -> Signal<'a> {
        let (ga, gb) = (ga as f32, gb as f32);
        match planes {
            Ok((_, pb)) if ga == 0.0 => Signal::One(pb, gb),
            Ok((pa, _)) if gb == 0.0 => Signal::One(pa, ga),
            Ok((pa, pb)) => Signal::Blend(pa, pb, ga, gb),
            Err(signal) => Signal::Uniform(signal as f32),
        }
    }
}

/// A frame's standard normal draws, one per pixel.
#[derive(Clone, Copy)]
enum Draws<'a> {
    /// Drawn for this frame.
    Fresh(&'a [f32]),
    /// A window of the quantised pool.
    Pool(&'a [i16]),
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
    /// The count for an expected `signal` (counts above dark) and a
    /// standard normal draw `z`.
    #[inline(always)]
    fn count(&self, signal: f32, z: f32) -> u16 {
        let signal = signal.max(0.0);
        let v = self.dark + signal + z * (self.read2 + signal * self.cpe).sqrt();
        // Rounded to the nearest count by adding 2²³, where an f32's unit
        // in the last place is 1, and reading the low mantissa bits:
        // branch-free and vectorised (`round` is a libm call here, and a
        // saturating `as` cast compiled to lane-by-lane checks). `max`
        // first maps a NaN to 0.
        let v = v.max(0.0).min(self.max);
        ((v + 8_388_608.0).to_bits() & 0xFFFF) as u16
    }

    /// Every pixel of `out` from its signal and draw (inlined into each
    /// of [`frame_counts`]' loops, so each vectorises on its own).
    #[inline(always)]
    fn fill(
        self,
        out: &mut [u16],
        signal: impl Iterator<Item = f32>,
        z: impl Iterator<Item = f32>,
    ) {
        for ((o, s), z) in out.iter_mut().zip(signal).zip(z) {
            *o = self.count(s, z);
        }
    }
}

/// One frame into `out`, compiled for the best vector unit: one loop per
/// kind of signal and of draws.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1", "aarch64+neon"))]
fn frame_counts(p: Counts, signal: Signal, z: Draws, out: &mut [u16]) {
    macro_rules! with_draws {
        ($signal:expr) => {
            match z {
                Draws::Fresh(z) => p.fill(out, $signal, z.iter().copied()),
                Draws::Pool(z) => {
                    let scale = 1.0 / POOL_SCALE;
                    p.fill(out, $signal, z.iter().map(|&q| f32::from(q) * scale))
                }
            }
        };
    }
    match signal {
        Signal::Blend(pa, pb, ga, gb) => {
            with_draws!(pa.iter().zip(pb).map(|(&ra, &rb)| ga * ra + gb * rb))
        }
        Signal::One(pa, ga) => with_draws!(pa.iter().map(|&r| ga * r)),
        Signal::Uniform(s) => with_draws!(std::iter::repeat(s)),
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

    fn next_frame(&mut self, out: &mut Frame, timeout: Duration) -> Result<(), CameraError> {
        self.next_frame_if(out, timeout, &mut |_| true).map(|_| ())
    }

    fn next_frame_if(
        &mut self,
        out: &mut Frame,
        _timeout: Duration,
        wanted: &mut dyn FnMut(&super::FrameMeta) -> bool,
    ) -> Result<bool, CameraError> {
        let n = self.width as usize * self.height as usize;
        if out.data.len() < n {
            return Err(CameraError::BufferTooSmall {
                have: out.data.len(),
                need: n,
            });
        }
        let mut seq = self.seq;
        if self.cfg.realtime {
            let period = self.cfg.sensor.frame_period_ns.max(1);
            let (start, v0) = *self
                .started
                .get_or_insert_with(|| (std::time::Instant::now(), seq * period));
            let speed = if self.cfg.speed > 0.0 {
                self.cfg.speed
            } else {
                1.0
            };
            // Frames older than the driver's queue are lost.
            let q = u64::from(self.cfg.queue_frames);
            if q > 0 {
                let device_ns = (start.elapsed().as_secs_f64() * speed * 1e9) as u64;
                let newest = (v0 + device_ns) / period;
                while seq + q <= newest {
                    self.seq = seq + 1;
                    self.produce(seq, out, n, &mut |_| false);
                    seq += 1;
                }
            }
            let due = start + Duration::from_secs_f64((seq * period - v0) as f64 / 1e9 / speed);
            let now = std::time::Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
        self.seq = seq + 1;
        Ok(self.produce(seq, out, n, wanted))
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

    /// A frame skipped (its pixels not wanted) changes no other frame: the
    /// noise stream advances as if it had been rendered, pooled or not.
    /// Its metadata is still the frame's.
    #[test]
    fn skipping_a_frame_changes_no_other_frame() {
        for pool in [false, true] {
            let cfg = SyntheticConfig {
                noise_pool: pool,
                ..Default::default()
            };
            let (mut all, mut some) = (cam(cfg.clone()), cam(cfg));
            let nm = all.bands()[7].center_nm;
            all.filter_view().tune(nm, 0, 0);
            some.filter_view().tune(nm, 0, 0);
            let info = all.info();
            let mut fa = Frame::with_size(info.width, info.height, info.format);
            let mut fs = fa.clone();
            for k in 0..5u64 {
                all.next_frame(&mut fa, Duration::ZERO).unwrap();
                let skip = k == 1 || k == 2;
                let filled = some
                    .next_frame_if(&mut fs, Duration::ZERO, &mut |m| {
                        assert_eq!(m.seq, k);
                        !skip
                    })
                    .unwrap();
                assert_eq!(filled, !skip);
                assert_eq!(fs.meta, fa.meta);
                if !skip {
                    assert_eq!(fs.data, fa.data, "pool {pool}, frame {k}");
                }
            }
        }
    }

    /// A reader late by more than the driver's queue loses the older
    /// frames, as a real camera does: the next frame read is one of the
    /// newest `queue_frames`, the counter shows the gap, and that frame is
    /// the very frame a reader that took every one got (the noise stream
    /// advances over the lost ones). With no bound (0), nothing is lost.
    #[test]
    fn a_late_reader_loses_the_frames_past_the_queue() {
        for (queue, pool) in [(4u32, true), (4, false), (0, true)] {
            let sensor = SensorModel {
                exposure_us: 500,
                frame_period_ns: 1_000_000,
                ..SensorModel::default()
            };
            let cfg = SyntheticConfig {
                sensor,
                noise_pool: pool,
                queue_frames: queue,
                ..Default::default()
            };
            let mut live = cam(SyntheticConfig {
                realtime: true,
                ..cfg.clone()
            });
            let mut all = cam(cfg);
            let nm = live.bands()[3].center_nm;
            live.filter_view().tune(nm, 0, 0);
            all.filter_view().tune(nm, 0, 0);
            let info = live.info();
            let mut f = Frame::with_size(info.width, info.height, info.format);
            let mut g = f.clone();
            live.next_frame(&mut f, Duration::ZERO).unwrap();
            assert_eq!(f.meta.seq, 0);
            // 40 frame periods late.
            std::thread::sleep(Duration::from_millis(40));
            live.next_frame(&mut f, Duration::ZERO).unwrap();
            let seq = f.meta.seq;
            if queue == 0 {
                assert_eq!(seq, 1);
            } else {
                // Due at 40 ms or later: within the newest four of them
                // (a slow machine may read later still, never earlier).
                assert!(seq >= 40 - u64::from(queue), "seq {seq}");
            }
            for _ in 0..=seq {
                all.next_frame(&mut g, Duration::ZERO).unwrap();
            }
            assert_eq!(g.meta, f.meta);
            assert_eq!(g.data, f.data, "queue {queue}, pool {pool}");
        }
    }

    /// The branch-free rounding gives the nearest count, as `f64::round`
    /// does (away from exact halves, which noise never hits), clipped to
    /// the ADC's range, and a NaN maps to 0.
    #[test]
    fn counts_round_to_the_nearest_and_clip() {
        let p = Counts {
            dark: 800.0,
            read2: 36.0,
            cpe: 0.25,
            max: 65535.0,
        };
        let mut checked = 0;
        for i in 0..20_000 {
            let signal = i as f32 * 3.3137;
            for z in [-9.0f32, -2.71, -0.013, 0.0, 0.37, 1.5, 6.2] {
                let v = f64::from(p.dark + signal + z * (p.read2 + signal * p.cpe).sqrt());
                if (v.fract().abs() - 0.5).abs() < 1e-3 {
                    continue;
                }
                let want = v.round().clamp(0.0, 65535.0) as u16;
                assert_eq!(p.count(signal, z), want, "signal {signal}, z {z}");
                checked += 1;
            }
        }
        assert!(checked > 130_000);
        assert_eq!(p.count(1e9, 0.0), 65535);
        assert_eq!(p.count(0.0, -1e6), 0);
        assert_eq!(p.count(f32::NAN, 0.0), 800);
    }
}
