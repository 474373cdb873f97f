//! A real camera over Video4Linux2 (feature `v4l2`, crate `v4l` 0.14).
//!
//! Monochrome formats only: `GREY` (8 bit), `Y10 `, `Y12 ` (10/12 bits in
//! 16-bit little-endian words) and `Y16 `. Packed `Y10P`/`Y10B` are refused
//! with a clear error. Frames arrive by mmap streaming; each one is copied
//! out of the driver's buffer, honouring the stride, into the caller's pooled
//! [`Frame`] before the next dequeue re-queues the buffer, so nothing
//! borrowed from the driver ever crosses a channel.
//!
//! Timestamps are the driver's (CLOCK_MONOTONIC on current kernels), the
//! clock the filter driver's settle times are read on; the sequence number
//! is V4L2's, so a gap is a frame the driver dropped.

use super::{CameraError, CameraInfo, Frame, FrameMeta, FrameSource, PixelFormat};
use std::time::Duration;
use v4l::buffer::Type;
use v4l::control::{Control, Value};
use v4l::io::mmap::Stream;
use v4l::io::traits::CaptureStream;
use v4l::video::Capture;
use v4l::{Device, FourCC};

/// V4L2_CID_EXPOSURE_AUTO (1 = manual).
const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
/// V4L2_CID_EXPOSURE_ABSOLUTE, in units of 100 µs.
const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
/// V4L2_CID_GAIN.
const CID_GAIN: u32 = 0x0098_0913;

/// Requested capture settings.
#[derive(Clone, Debug)]
pub struct V4l2Config {
    /// Device path, e.g. `/dev/video0`.
    pub path: String,
    /// Width (0: keep the device's).
    pub width: u32,
    /// Height (0: keep the device's).
    pub height: u32,
    /// Preferred format.
    pub format: PixelFormat,
    /// Exposure, µs.
    pub exposure_us: u32,
    /// Driver buffers.
    pub buffers: u32,
}

/// A V4L2 camera.
pub struct V4l2Camera {
    dev: Device,
    stream: Option<Stream<'static>>,
    path: String,
    info: CameraInfo,
    stride: usize,
}

fn fourcc_of(f: PixelFormat) -> FourCC {
    FourCC::new(match f {
        PixelFormat::Grey8 => b"GREY",
        PixelFormat::Y10 => b"Y10 ",
        PixelFormat::Y12 => b"Y12 ",
        PixelFormat::Y16 => b"Y16 ",
    })
}

fn format_of(f: FourCC) -> Option<PixelFormat> {
    match &f.repr {
        b"GREY" => Some(PixelFormat::Grey8),
        b"Y10 " => Some(PixelFormat::Y10),
        b"Y12 " => Some(PixelFormat::Y12),
        b"Y16 " => Some(PixelFormat::Y16),
        _ => None,
    }
}

impl V4l2Camera {
    /// Open and configure the device; errors name the device and say what
    /// it offers.
    pub fn open(cfg: &V4l2Config) -> Result<V4l2Camera, CameraError> {
        let path = cfg.path.clone();
        let nodev = |e: std::io::Error| CameraError::NoDevice {
            path: path.clone(),
            message: e.to_string(),
        };
        if !std::path::Path::new(&path).exists() {
            return Err(CameraError::NoDevice {
                path,
                message: "no such device (is the camera plugged in? `v4l2-ctl --list-devices`)"
                    .into(),
            });
        }
        let dev = Device::with_path(&path).map_err(nodev)?;
        let caps = dev.query_caps().map_err(nodev)?;
        let offered: Vec<FourCC> = dev
            .enum_formats()
            .map_err(nodev)?
            .into_iter()
            .map(|d| d.fourcc)
            .collect();
        let offered_s = offered
            .iter()
            .map(|f| f.str().unwrap_or("????").to_string())
            .collect::<Vec<_>>()
            .join(", ");
        let want = fourcc_of(cfg.format);
        let pick = if offered.contains(&want) {
            want
        } else {
            // Fall back to the deepest monochrome format offered.
            [
                PixelFormat::Y16,
                PixelFormat::Y12,
                PixelFormat::Y10,
                PixelFormat::Grey8,
            ]
            .into_iter()
            .map(fourcc_of)
            .find(|f| offered.contains(f))
            .ok_or_else(|| CameraError::UnsupportedFormat {
                path: path.clone(),
                fourcc: want.str().unwrap_or("?").to_string(),
                offered: offered_s.clone(),
            })?
        };
        let mut fmt = dev.format().map_err(nodev)?;
        if cfg.width > 0 && cfg.height > 0 {
            fmt.width = cfg.width;
            fmt.height = cfg.height;
        }
        fmt.fourcc = pick;
        let fmt = dev.set_format(&fmt).map_err(nodev)?;
        let format = format_of(fmt.fourcc).ok_or_else(|| CameraError::UnsupportedFormat {
            path: path.clone(),
            fourcc: fmt.fourcc.str().unwrap_or("?").to_string(),
            offered: offered_s.clone(),
        })?;
        let bpp = if format == PixelFormat::Grey8 { 1 } else { 2 };
        let stride = (fmt.stride as usize).max(fmt.width as usize * bpp);
        let mut stream =
            Stream::with_buffers(&dev, Type::VideoCapture, cfg.buffers.max(2)).map_err(nodev)?;
        stream.set_timeout(Duration::from_secs(2));
        let mut cam = V4l2Camera {
            dev,
            stream: Some(stream),
            info: CameraInfo {
                id: format!("v4l2 {} {} {}", caps.driver, caps.card, caps.bus),
                width: fmt.width,
                height: fmt.height,
                format,
                exposure_us: cfg.exposure_us,
                gain: 1.0,
            },
            path,
            stride,
        };
        cam.set_exposure(cfg.exposure_us)?;
        Ok(cam)
    }

    fn set_int(&self, control: &'static str, id: u32, v: i64) -> Result<(), CameraError> {
        self.dev
            .set_control(Control {
                id,
                value: Value::Integer(v),
            })
            .map_err(|e| CameraError::Control {
                control,
                message: format!("{}: {e}", self.path),
            })
    }
}

impl FrameSource for V4l2Camera {
    fn info(&self) -> CameraInfo {
        self.info.clone()
    }

    fn next_frame(&mut self, out: &mut Frame, timeout: Duration) -> Result<(), CameraError> {
        self.next_frame_if(out, timeout, &mut |_| true).map(|_| ())
    }

    fn next_frame_if(
        &mut self,
        out: &mut Frame,
        timeout: Duration,
        wanted: &mut dyn FnMut(&FrameMeta) -> bool,
    ) -> Result<bool, CameraError> {
        let (w, h) = (self.info.width as usize, self.info.height as usize);
        if out.data.len() < w * h {
            return Err(CameraError::BufferTooSmall {
                have: out.data.len(),
                need: w * h,
            });
        }
        let Some(stream) = self.stream.as_mut() else {
            return Err(CameraError::Unsupported("stream closed".into()));
        };
        stream.set_timeout(timeout);
        let (buf, meta) = match stream.next() {
            Ok(x) => x,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {
                return Err(CameraError::Timeout(timeout))
            }
            Err(e) => return Err(CameraError::Io(e)),
        };
        let used = (meta.bytesused as usize).min(buf.len());
        let data = &buf[..used];
        let seq = u64::from(meta.sequence);
        let bpp = if self.info.format == PixelFormat::Grey8 {
            1
        } else {
            2
        };
        if used < self.stride * (h - 1) + w * bpp {
            return Err(CameraError::BadFrame {
                seq,
                message: format!("{used} bytes, a {w}×{h} frame needs {}", self.stride * h),
            });
        }
        let ts = meta.timestamp;
        out.meta = FrameMeta {
            seq,
            timestamp_ns: (ts.sec as u64).saturating_mul(1_000_000_000) + (ts.usec as u64) * 1000,
            exposure_us: self.info.exposure_us,
            gain: self.info.gain,
            format: self.info.format,
            width: self.info.width,
            height: self.info.height,
            trigger: None,
            encoder: None,
        };
        // A frame no one will look at (exposed while the filter settled)
        // is not copied out of the driver's buffer.
        if !wanted(&out.meta) {
            return Ok(false);
        }
        // Copy out of the driver's buffer now: it is re-queued on the next dequeue.
        for y in 0..h {
            let row = &data[y * self.stride..];
            let dst = &mut out.data[y * w..(y + 1) * w];
            if bpp == 1 {
                for (d, &s) in dst.iter_mut().zip(&row[..w]) {
                    *d = u16::from(s);
                }
            } else {
                for (d, s) in dst.iter_mut().zip(row[..2 * w].chunks_exact(2)) {
                    *d = u16::from_le_bytes([s[0], s[1]]);
                }
            }
        }
        Ok(true)
    }

    fn set_exposure(&mut self, exposure_us: u32) -> Result<u32, CameraError> {
        // Manual exposure first; cameras without the control keep theirs.
        let _ = self.set_int("exposure_auto", CID_EXPOSURE_AUTO, 1);
        let units = i64::from(exposure_us.div_ceil(100).max(1));
        self.set_int("exposure_absolute", CID_EXPOSURE_ABSOLUTE, units)?;
        self.info.exposure_us = (units * 100) as u32;
        Ok(self.info.exposure_us)
    }

    fn set_gain(&mut self, gain: f32) -> Result<f32, CameraError> {
        self.set_int("gain", CID_GAIN, gain.round() as i64)?;
        self.info.gain = gain.round();
        Ok(self.info.gain)
    }
}

impl Drop for V4l2Camera {
    fn drop(&mut self) {
        use v4l::io::traits::Stream as _;
        // The stream's own Drop panics when STREAMOFF fails; stop it here and
        // leak it on failure rather than panic (perhaps while unwinding).
        if let Some(mut s) = self.stream.take() {
            if s.stop().is_ok() {
                drop(s);
            } else {
                std::mem::forget(s);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_device_is_a_clear_error() {
        let e = V4l2Camera::open(&V4l2Config {
            path: "/dev/video-does-not-exist".into(),
            width: 0,
            height: 0,
            format: PixelFormat::Y16,
            exposure_us: 1000,
            buffers: 4,
        })
        .err()
        .expect("no such device");
        assert!(e.to_string().contains("no such device"), "{e}");
    }

    #[test]
    fn formats_round_trip() {
        for f in [
            PixelFormat::Grey8,
            PixelFormat::Y10,
            PixelFormat::Y12,
            PixelFormat::Y16,
        ] {
            assert_eq!(format_of(fourcc_of(f)), Some(f));
        }
        assert_eq!(format_of(FourCC::new(b"Y10P")), None);
    }
}
