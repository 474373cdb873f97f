//! Cameras behind one small trait, [`FrameSource`].
//!
//! A source fills a caller-owned, pooled [`Frame`]: the caller hands in a
//! buffer sized once, the source copies its pixels into it (out of a driver's
//! mmap buffer, out of a renderer, out of a recording) and stamps the
//! metadata. Nothing crosses a thread boundary borrowed from a device, and
//! nothing in the per-frame path allocates.
//!
//! Every frame carries what a recording needs to reproduce a run exactly:
//! sequence number, exposure start timestamp (ns, on the clock the filter
//! controller's settle times are on), exposure, gain, format and size.
//!
//! Implementations:
//! - [`synthetic::SyntheticCamera`]: renders a scene at the filter's current
//!   band, with sensor noise, dark offset, transmission, saturation, a seed;
//! - [`faults::FaultySource`]: wraps any source and drops, duplicates,
//!   reorders or corrupts frames on a seeded schedule;
//! - `v4l2::V4l2Camera` (feature `v4l2`): a real camera over Video4Linux2.
//!
//! Samples are stored as `u16` whatever the sensor format; the format says
//! how many bits are significant (8, 10, 12 or 16).

pub mod faults;
pub mod synthetic;
#[cfg(feature = "v4l2")]
pub mod v4l2;
pub mod web;

use std::time::Duration;

/// A monochrome pixel format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PixelFormat {
    /// 8 bits per pixel (V4L2 `GREY`).
    Grey8,
    /// 10 significant bits in 16 (V4L2 `Y10 `).
    Y10,
    /// 12 significant bits in 16 (V4L2 `Y12 `).
    Y12,
    /// 16 bits (V4L2 `Y16 `).
    Y16,
}

impl PixelFormat {
    /// Significant bits per sample.
    pub fn bits(self) -> u32 {
        match self {
            PixelFormat::Grey8 => 8,
            PixelFormat::Y10 => 10,
            PixelFormat::Y12 => 12,
            PixelFormat::Y16 => 16,
        }
    }

    /// The largest sample value (the saturation level of the ADC).
    pub fn max_value(self) -> u16 {
        ((1u32 << self.bits()) - 1) as u16
    }

    /// Parse `grey8`, `y10`, `y12`, `y16`.
    pub fn parse(s: &str) -> Option<PixelFormat> {
        match s.to_ascii_lowercase().as_str() {
            "grey8" | "grey" | "gray8" | "y8" => Some(PixelFormat::Grey8),
            "y10" => Some(PixelFormat::Y10),
            "y12" => Some(PixelFormat::Y12),
            "y16" => Some(PixelFormat::Y16),
            _ => None,
        }
    }
}

/// Everything known about one frame besides its pixels.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FrameMeta {
    /// The source's frame counter (V4L2 `sequence`); gaps mean lost frames.
    pub seq: u64,
    /// Start of exposure, ns, on the source's clock.
    pub timestamp_ns: u64,
    /// Exposure time, µs.
    pub exposure_us: u32,
    /// Analogue gain (1 = unity).
    pub gain: f32,
    /// Pixel format.
    pub format: PixelFormat,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// In triggered mode: the trigger count that exposed this frame, if the
    /// source knows it (else the sequencer pairs by `seq`).
    pub trigger: Option<u64>,
    /// The web encoder's count latched at exposure start, when the camera
    /// has one (a production line; see [`crate::line`]).
    #[serde(default)]
    pub encoder: Option<i64>,
}

impl FrameMeta {
    /// Pixels in the frame.
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Whether the frame has no pixels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A frame in a pooled buffer: metadata plus `width × height` samples.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// Metadata.
    pub meta: FrameMeta,
    /// Samples, row-major; `data.len()` is the pool's buffer size, of which
    /// the first `meta.len()` are the frame.
    pub data: Vec<u16>,
}

impl Frame {
    /// A pooled buffer for frames of up to `width × height` pixels. This is
    /// the only allocation a frame ever costs.
    pub fn with_size(width: u32, height: u32, format: PixelFormat) -> Frame {
        Frame {
            meta: FrameMeta {
                seq: 0,
                timestamp_ns: 0,
                exposure_us: 0,
                gain: 1.0,
                format,
                width,
                height,
                trigger: None,
                encoder: None,
            },
            data: vec![0; width as usize * height as usize],
        }
    }

    /// The frame's samples, after checking that the metadata and the buffer
    /// agree: after this check no accessor of the returned slice panics.
    pub fn pixels(&self) -> Result<&[u16], CameraError> {
        let n = self.meta.len();
        self.data.get(..n).ok_or(CameraError::BadFrame {
            seq: self.meta.seq,
            message: format!(
                "{}×{} frame in a buffer of {} samples",
                self.meta.width,
                self.meta.height,
                self.data.len()
            ),
        })
    }
}

/// What a camera is.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraInfo {
    /// An identifier stored with calibrations (driver, card, serial…).
    pub id: String,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Pixel format delivered.
    pub format: PixelFormat,
    /// Current exposure, µs.
    pub exposure_us: u32,
    /// Current gain.
    pub gain: f32,
}

/// What the camera looks at, for calibration. Sources that cannot change it
/// themselves (a real camera) return `Ok(false)` and the operator is asked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Target {
    /// The object being measured.
    Scene,
    /// No light (shutter closed, lens capped).
    Dark,
    /// A white reference of the given reflectance.
    White(f64),
}

/// Camera errors: set-up problems and per-frame trouble.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    /// No frame arrived within the timeout.
    #[error("no frame within {0:?}")]
    Timeout(Duration),
    /// The device does not exist or cannot be opened.
    #[error("camera {path}: {message}")]
    NoDevice {
        /// Device path.
        path: String,
        /// What went wrong.
        message: String,
    },
    /// The device cannot deliver a format irid reads.
    #[error("camera {path}: unsupported pixel format {fourcc} (irid reads GREY, Y10, Y12, Y16; the device offers {offered})")]
    UnsupportedFormat {
        /// Device path.
        path: String,
        /// The format found.
        fourcc: String,
        /// The formats the device offers.
        offered: String,
    },
    /// A control (exposure, gain) could not be set.
    #[error("camera control {control}: {message}")]
    Control {
        /// Which control.
        control: &'static str,
        /// What went wrong.
        message: String,
    },
    /// A frame is malformed (wrong size, short buffer).
    #[error("frame {seq}: {message}")]
    BadFrame {
        /// Its sequence number.
        seq: u64,
        /// What is wrong.
        message: String,
    },
    /// The pooled buffer is too small for the camera's frames.
    #[error("frame buffer holds {have} samples, the camera delivers {need}")]
    BufferTooSmall {
        /// Buffer capacity.
        have: usize,
        /// Frame size.
        need: usize,
    },
    /// The source has no more frames (end of a recording).
    #[error("end of stream")]
    Ended,
    /// An I/O error from the device.
    #[error("camera I/O: {0}")]
    Io(#[from] std::io::Error),
    /// The source cannot do this.
    #[error("{0}")]
    Unsupported(String),
}

/// A camera: fills pooled frames, one at a time, in capture order.
pub trait FrameSource: Send {
    /// What the camera is and delivers.
    fn info(&self) -> CameraInfo;

    /// Fill `out` with the next frame, waiting at most `timeout`.
    ///
    /// `out.data` must hold at least `width × height` samples
    /// ([`CameraError::BufferTooSmall`] otherwise); on error `out` is
    /// unspecified but still a valid buffer to reuse.
    fn next_frame(&mut self, out: &mut Frame, timeout: Duration) -> Result<(), CameraError>;

    /// As [`FrameSource::next_frame`], but asks `wanted` with the frame's
    /// metadata first and fills the pixels only if it says so: frames the
    /// caller will discard unseen (exposed while the filter settled) cost
    /// no copy out of the driver, and no rendering. Returns whether the
    /// pixels were filled; when not, `out.meta` is the frame's and
    /// `out.data` holds stale samples. By default every frame is filled.
    fn next_frame_if(
        &mut self,
        out: &mut Frame,
        timeout: Duration,
        wanted: &mut dyn FnMut(&FrameMeta) -> bool,
    ) -> Result<bool, CameraError> {
        let _ = wanted;
        self.next_frame(out, timeout).map(|()| true)
    }

    /// Set the exposure; returns what the camera accepted.
    fn set_exposure(&mut self, exposure_us: u32) -> Result<u32, CameraError>;

    /// Set the analogue gain; returns what the camera accepted.
    fn set_gain(&mut self, gain: f32) -> Result<f32, CameraError> {
        let _ = gain;
        Err(CameraError::Unsupported(
            "this camera has no gain control".into(),
        ))
    }

    /// Point the camera at a calibration target, if the source can do that
    /// itself; `Ok(false)` means a person must (cap the lens, place the
    /// white reference).
    fn set_target(&mut self, target: Target) -> Result<bool, CameraError> {
        let _ = target;
        Ok(false)
    }
}

impl<S: FrameSource + ?Sized> FrameSource for Box<S> {
    fn info(&self) -> CameraInfo {
        (**self).info()
    }
    fn next_frame(&mut self, out: &mut Frame, timeout: Duration) -> Result<(), CameraError> {
        (**self).next_frame(out, timeout)
    }
    fn next_frame_if(
        &mut self,
        out: &mut Frame,
        timeout: Duration,
        wanted: &mut dyn FnMut(&FrameMeta) -> bool,
    ) -> Result<bool, CameraError> {
        (**self).next_frame_if(out, timeout, wanted)
    }
    fn set_exposure(&mut self, exposure_us: u32) -> Result<u32, CameraError> {
        (**self).set_exposure(exposure_us)
    }
    fn set_gain(&mut self, gain: f32) -> Result<f32, CameraError> {
        (**self).set_gain(gain)
    }
    fn set_target(&mut self, target: Target) -> Result<bool, CameraError> {
        (**self).set_target(target)
    }
}
