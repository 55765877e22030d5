//! A V4L2 camera (Linux), YUYV at the requested size and rate (feature `v4l`).

use std::time::{Duration, Instant};

use ::v4l::buffer::Type;
use ::v4l::io::mmap::Stream;
use ::v4l::io::traits::CaptureStream;
use ::v4l::video::Capture;
use ::v4l::{Device, FourCC};

use super::{Frame, FrameSource};
use crate::error::{Error, Result};
use crate::frame::{Channel, PixelLayout, gray_from_u8};

/// What to ask the camera for.
#[derive(Debug, Clone)]
pub struct CameraConfig {
    /// Device path, e.g. `/dev/video0`.
    pub device: String,
    /// Requested width in pixels (the reference camera: 1920).
    pub width: u32,
    /// Requested height in pixels (the reference camera: 1080).
    pub height: u32,
    /// Requested frame rate (the reference camera: ~50).
    pub fps: u32,
    /// Green (computed from YUV) or luma (the Y samples as they are).
    pub channel: Channel,
    /// How long to wait for a frame before reporting the camera as stalled.
    pub timeout: Duration,
}

impl Default for CameraConfig {
    fn default() -> Self {
        CameraConfig {
            device: "/dev/video0".into(),
            width: 1920,
            height: 1080,
            fps: 50,
            channel: Channel::Green,
            timeout: Duration::from_secs(2),
        }
    }
}

/// A V4L2 camera streaming YUYV frames through memory-mapped buffers.
///
/// A camera that is unplugged or stalls yields [`Error::Capture`] within the
/// configured timeout instead of blocking forever; after such an error the
/// stream keeps returning errors.
pub struct Camera {
    stream: Stream<'static>,
    config: CameraConfig,
    width: usize,
    height: usize,
    stride: usize,
    index: usize,
    start: Instant,
    failed: bool,
    capture_time: Option<Duration>,
}

fn cap(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Capture {
        message: format!("{what}: {e}"),
    }
}

impl Camera {
    /// Opens the device and starts streaming YUYV at the requested size and rate.
    /// Errors if the device is missing or does not deliver YUYV.
    pub fn open(config: CameraConfig) -> Result<Self> {
        let dev = Device::with_path(&config.device).map_err(|e| cap(&config.device, e))?;
        let mut fmt = dev.format().map_err(|e| cap("query format", e))?;
        fmt.width = config.width;
        fmt.height = config.height;
        fmt.fourcc = FourCC::new(b"YUYV");
        let fmt = dev.set_format(&fmt).map_err(|e| cap("set format", e))?;
        if fmt.fourcc != FourCC::new(b"YUYV") {
            return Err(cap(
                &config.device,
                format!("camera refuses YUYV (offers {})", fmt.fourcc),
            ));
        }
        if config.fps > 0 {
            dev.set_params(&::v4l::video::capture::Parameters::with_fps(config.fps))
                .map_err(|e| cap("set frame rate", e))?;
        }
        let mut stream = Stream::with_buffers(&dev, Type::VideoCapture, 4)
            .map_err(|e| cap("start stream", e))?;
        stream.set_timeout(config.timeout);
        Ok(Camera {
            stream,
            width: fmt.width as usize,
            height: fmt.height as usize,
            stride: fmt.stride as usize,
            config,
            index: 0,
            start: Instant::now(),
            failed: false,
            capture_time: None,
        })
    }

    /// The size the camera actually delivers (it may differ from the request).
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// When the last frame was captured, by the driver's time stamp on the
    /// system's monotonic clock (`CLOCK_MONOTONIC`, time since boot), if the
    /// driver gives one; `None` before the first frame or when the driver's
    /// time stamps are of another clock or missing. A frame's `t_s` is
    /// instead the time it was received, from the opening of the camera.
    pub fn last_capture_time(&self) -> Option<Duration> {
        self.capture_time
    }
}

impl FrameSource for Camera {
    fn next_frame(&mut self) -> Option<Result<Frame>> {
        if self.failed {
            return Some(Err(cap(&self.config.device, "camera stopped earlier")));
        }
        let (buf, meta) = match self.stream.next() {
            Ok(x) => x,
            Err(e) => {
                self.failed = true;
                return Some(Err(cap(&self.config.device, e)));
            }
        };
        self.capture_time = monotonic_time(meta);
        let stride = self.stride.max(2 * self.width);
        let image = gray_from_u8(
            buf,
            self.width,
            self.height,
            stride,
            PixelLayout::Yuyv,
            self.config.channel,
        );
        let index = self.index;
        self.index += 1;
        Some(image.map(|image| Frame {
            image,
            name: format!("{index:06}"),
            index,
            t_s: self.start.elapsed().as_secs_f64(),
        }))
    }
}

/// The buffer's capture time when the driver stamps it on the monotonic clock.
fn monotonic_time(meta: &::v4l::buffer::Metadata) -> Option<Duration> {
    use ::v4l::buffer::Flags;
    let clock = meta.flags & Flags::TIMESTAMP_MASK;
    let (sec, usec) = (meta.timestamp.sec, meta.timestamp.usec);
    let valid = clock == Flags::TIMESTAMP_MONOTONIC
        && sec >= 0
        && (0..1_000_000).contains(&usec)
        && (sec, usec) != (0, 0);
    valid.then(|| Duration::new(sec as u64, 1000 * usec as u32))
}
