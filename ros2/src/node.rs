//! The node at run time: a capture thread, a bounded queue, the sensor, and
//! the publishers.
//!
//! ```text
//! capture thread ──(queue of 1-2 frames: a frame that finds it full is dropped)──▶ sensor ─▶ messages ─▶ finite? ─▶ publish
//! ```
//!
//! A sequence replayed with `--rate 0` waits for the queue instead (every
//! frame is processed, as `track` does); paced by `--rate N`, or from a
//! camera, frames that arrive while the sensor is busy are dropped and
//! counted. Everything the node needs from the disk or the device is opened
//! before the ROS 2 participant starts, so that a bad path ends the run
//! with one error line and touches no network.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::thread;
use std::time::{Duration, Instant, SystemTime};

use optical_tactile::calibration::Calibration;
use optical_tactile::capture::{Frame, FrameSource, SequenceSource};
use optical_tactile::flow::dis::DisParams;
use optical_tactile::segment::SplitRule;
use optical_tactile::sensor::{ExtractorConfig, RawSensor, TactileSensor};
use optical_tactile::track::FilterConfig;

use crate::args::NodeArgs;
use crate::frame_msgs::{self, FrameMessages, MarkerStyle};
use crate::msg::{Header, Time};

/// What runs on the frames: the calibrated sensor, or the raw one.
#[derive(Debug)]
pub enum Pipeline {
    /// The calibrated sensor: contacts in metres and newtons.
    Calibrated(Box<TactileSensor>),
    /// No calibration: patches in pixels.
    Raw(Box<RawSensor>),
}

impl Pipeline {
    /// The pipeline `args` ask for: the calibration loaded (an error names
    /// the file) with the flags' overrides, or the raw sensor.
    pub fn build(args: &NodeArgs) -> Result<Pipeline, String> {
        if args.raw {
            let mut config = ExtractorConfig::default()
                .with_exposure(args.exposure.unwrap_or_default())
                .with_split(args.split.then_some(SplitRule::DEFAULT));
            if let Some(p) = args.preset {
                config = config.with_flow(DisParams::preset(p));
            }
            if let Some(t) = args.thresholds {
                config = config.with_thresholds(t);
            }
            let raw = RawSensor::new(config, args.crop).map_err(|e| e.to_string())?;
            return Ok(Pipeline::Raw(Box::new(raw)));
        }
        let path = &args.calibration;
        let calibration = Calibration::load(path)
            .map_err(|e| format!("cannot load calibration {}: {e}", path.display()))?;
        let mut b = TactileSensor::builder(calibration);
        if let Some(crop) = args.crop {
            b = b.crop(crop).force_crop(args.force_crop);
        }
        if let Some(p) = args.preset {
            b = b.flow(DisParams::preset(p));
        }
        if let Some(t) = args.thresholds {
            b = b.thresholds(t);
        }
        let sensor = b
            .configure(|c| {
                if let Some(e) = args.exposure {
                    c.extractor.exposure = e;
                }
                // On: the rule of the calibration's geometry.
                if !args.split {
                    c.extractor.split = None;
                }
                c.tracker.filter = args.filter.then(FilterConfig::default);
                if let Some(h) = args.hold {
                    c.tracker.max_missed = h;
                }
                c.rereference.enabled = args.rereference;
            })
            .build()
            .map_err(|e| e.to_string().replace("set force_crop", "pass --force-crop"))?;
        Ok(Pipeline::Calibrated(Box::new(sensor)))
    }

    /// Takes a whole camera frame as the reference.
    pub fn set_reference(&mut self, frame: &Frame) -> optical_tactile::Result<()> {
        match self {
            Pipeline::Calibrated(s) => s.set_reference(&frame.image),
            Pipeline::Raw(r) => r.set_reference(&frame.image),
        }
    }

    /// Processes a frame and builds its messages (the debug image too when
    /// `debug_image`).
    pub fn process(
        &mut self,
        frame: &Frame,
        header: &Header,
        style: &MarkerStyle,
        debug_image: bool,
    ) -> optical_tactile::Result<FrameMessages> {
        let mut m = match self {
            Pipeline::Calibrated(s) => {
                s.process(&frame.image, frame.t_s)?;
                let cal = s.calibration();
                let sigma = cal.uncertainty.is_some();
                frame_msgs::calibrated(header, s.contacts(), &cal.setup.geometry, style, sigma)
            }
            Pipeline::Raw(r) => {
                let raw_header = Header {
                    stamp: header.stamp,
                    frame_id: format!("{}_raw_px", header.frame_id),
                };
                frame_msgs::raw(&raw_header, r.process(&frame.image)?)
            }
        };
        if debug_image {
            let panel = match self {
                Pipeline::Calibrated(s) => optical_tactile::viz::debug_panel(s),
                Pipeline::Raw(r) => r.debug_panel(),
            };
            m.image = Some(frame_msgs::image(header, &panel));
        }
        Ok(m)
    }

    /// A one-line description for the log.
    pub fn describe(&self) -> String {
        match self {
            Pipeline::Calibrated(s) => {
                let c = s.config();
                format!(
                    "calibrated, crop {}, thresholds |flow| > {} px sum > {}, filter {}, re-referencing {}",
                    s.crop().to_arg(),
                    c.extractor.thresholds.magnitude,
                    c.extractor.thresholds.sum,
                    if c.tracker.filter.is_some() {
                        "on"
                    } else {
                        "off"
                    },
                    if c.rereference.enabled { "on" } else { "off" },
                )
            }
            Pipeline::Raw(r) => format!(
                "raw (no calibration), crop {}",
                r.crop()
                    .map_or_else(|| "whole frame".to_string(), |c| c.to_arg())
            ),
        }
    }
}

/// Where frames come from.
#[derive(Debug, Clone)]
pub enum SourceSpec {
    /// A folder of PNG frames, paced at `rate` frames per second (0: as
    /// fast as they are processed, none dropped).
    Sequence {
        /// The folder.
        dir: std::path::PathBuf,
        /// Frames per second, 0 for unpaced.
        rate: f64,
    },
    /// A V4L2 camera.
    Camera {
        /// Device path.
        device: String,
        /// Requested `(width, height)`.
        size: (u32, u32),
        /// Requested frame rate.
        fps: u32,
        /// Reopen attempts after the camera stops delivering frames.
        reopen: u32,
    },
}

impl SourceSpec {
    /// The source `args` ask for.
    pub fn from_args(args: &NodeArgs) -> SourceSpec {
        match &args.sequence {
            Some(dir) => SourceSpec::Sequence {
                dir: dir.clone(),
                rate: args.rate,
            },
            None => SourceSpec::Camera {
                device: args.device.clone().unwrap_or_else(|| "/dev/video0".into()),
                size: args.size,
                fps: args.fps,
                reopen: args.reopen,
            },
        }
    }

    /// Whether frames are dropped when the queue is full (a camera, or a
    /// paced sequence) rather than waited for.
    pub fn drops(&self) -> bool {
        match self {
            SourceSpec::Sequence { rate, .. } => *rate > 0.0,
            SourceSpec::Camera { .. } => true,
        }
    }
}

/// A frame from the capture thread with its time stamp: the camera's
/// capture time when it gives one, else when the frame was received.
#[derive(Debug)]
pub struct Captured {
    /// The frame.
    pub frame: Frame,
    /// Its time stamp.
    pub stamp: Time,
}

/// What the capture thread sends.
#[derive(Debug)]
enum Event {
    Frame(Captured),
    /// A frame that could not be read; the source goes on.
    Unreadable(String),
    /// The source cannot go on (a camera that is gone).
    #[cfg_attr(not(feature = "v4l"), allow(dead_code))]
    Fatal(String),
}

/// An opened source, in the capture thread.
enum Opened {
    Sequence(SequenceSource),
    #[cfg(feature = "v4l")]
    Camera(optical_tactile::capture::v4l::Camera),
}

impl Opened {
    fn open(
        spec: &SourceSpec,
        channel: optical_tactile::Channel,
    ) -> Result<(Opened, String), String> {
        match spec {
            SourceSpec::Sequence { dir, rate } => {
                let s = SequenceSource::open(dir)
                    .map_err(|e| format!("cannot open sequence {}: {e}", dir.display()))?
                    .with_channel(channel);
                let pace = if *rate > 0.0 {
                    format!("paced at {rate} fps")
                } else {
                    "unpaced".to_string()
                };
                let d = format!("sequence {} ({} frames, {pace})", dir.display(), s.len());
                Ok((Opened::Sequence(s), d))
            }
            #[cfg(feature = "v4l")]
            SourceSpec::Camera {
                device, size, fps, ..
            } => {
                use optical_tactile::capture::v4l::{Camera, CameraConfig};
                let config = CameraConfig {
                    device: device.clone(),
                    width: size.0,
                    height: size.1,
                    fps: *fps,
                    channel,
                    ..CameraConfig::default()
                };
                let cam = Camera::open(config).map_err(|e| format!("cannot open camera: {e}"))?;
                let (w, h) = cam.size();
                Ok((Opened::Camera(cam), format!("camera {device} ({w}x{h})")))
            }
            #[cfg(not(feature = "v4l"))]
            SourceSpec::Camera { device, .. } => Err(format!(
                "no camera support in this build (camera {device}): pass --sequence DIR, or build \
                 with --features v4l"
            )),
        }
    }

    /// The stamp of the frame just read: the camera's capture time on the
    /// system clock when the driver gives one, else now.
    fn stamp(&self) -> Time {
        let now = SystemTime::now();
        match self {
            Opened::Sequence(_) => Time::from_system(now),
            #[cfg(feature = "v4l")]
            Opened::Camera(c) => Time::from_system(capture_on_system_clock(
                c.last_capture_time(),
                monotonic_now(),
                now,
            )),
        }
    }

    fn next(&mut self) -> Option<optical_tactile::Result<Frame>> {
        match self {
            Opened::Sequence(s) => s.next_frame(),
            #[cfg(feature = "v4l")]
            Opened::Camera(c) => c.next_frame(),
        }
    }
}

/// Counts and times of a run, printed at exit.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Report {
    /// Frames the source delivered (the reference included).
    pub received: u64,
    /// Frames processed and published.
    pub published: u64,
    /// Frames dropped because the queue was full.
    pub dropped: u64,
    /// Frames that could not be read or processed (named on stderr).
    pub skipped: u64,
    /// Frames processed whose messages held a non-finite value and were not published.
    pub non_finite: u64,
    /// Milliseconds spent per processed frame (processing, messages, publishing): sum.
    pub busy_ms: f64,
    /// Largest of them.
    pub max_ms: f64,
    /// Seconds from the first frame to the end.
    pub wall_s: f64,
}

impl std::fmt::Display for Report {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let n = self.published + self.non_finite;
        write!(
            f,
            "{} frames received, {} published, {} dropped, {} skipped, {} not published (non-finite)",
            self.received, self.published, self.dropped, self.skipped, self.non_finite
        )?;
        if n > 0 {
            write!(
                f,
                "; {:.1} ms per frame (largest {:.1} ms), {:.1} frames per second over {:.2} s",
                self.busy_ms / n as f64,
                self.max_ms,
                self.published as f64 / self.wall_s.max(1e-9),
                self.wall_s
            )?;
        }
        Ok(())
    }
}

/// Where a frame's messages go.
pub trait Publish {
    /// Publishes one frame's messages (already checked finite).
    fn publish(&mut self, messages: FrameMessages) -> Result<(), String>;
}

/// Collects the messages (tests, and runs without ROS).
impl Publish for Vec<FrameMessages> {
    fn publish(&mut self, messages: FrameMessages) -> Result<(), String> {
        self.push(messages);
        Ok(())
    }
}

/// How the frames are turned into messages.
#[derive(Debug, Clone)]
pub struct Processing {
    /// The sensor frame's tf2 name.
    pub frame_id: String,
    /// The markers' look.
    pub style: MarkerStyle,
    /// Whether to publish the debug image.
    pub debug_image: bool,
    /// Frames in the queue (1 or 2).
    pub queue: usize,
    /// Stop after this many frames from the source.
    pub frames: Option<u64>,
    /// No log line per dropped frame.
    pub quiet: bool,
}

impl Processing {
    /// The processing settings of `args`.
    pub fn from_args(args: &NodeArgs) -> Processing {
        Processing {
            frame_id: args.frame_id.clone(),
            style: MarkerStyle {
                sphere_m: args.sphere_diameter,
                arrow_m_per_n: args.arrow_scale,
                lifetime_s: args.marker_lifetime,
            },
            debug_image: args.debug_image,
            queue: usize::from(args.queue).clamp(1, 2),
            frames: args.frames,
            quiet: args.quiet,
        }
    }
}

/// The capture thread, started but holding its frames until [`Capture::start`].
pub struct Capture {
    events: Receiver<Event>,
    go: Option<SyncSender<()>>,
    dropped: Arc<std::sync::atomic::AtomicU64>,
    handle: Option<thread::JoinHandle<()>>,
    stop: Arc<AtomicBool>,
    /// What was opened, for the log.
    pub description: String,
}

impl Capture {
    /// Opens the source in its own thread (an error if it cannot be
    /// opened); frames flow once [`start`](Self::start) is called, until the
    /// source ends, `stop` is set, or `frames` frames were read.
    pub fn open(
        spec: SourceSpec,
        channel: optical_tactile::Channel,
        p: &Processing,
        stop: Arc<AtomicBool>,
    ) -> Result<Capture, String> {
        let (tx, events) = mpsc::sync_channel(p.queue);
        let (opened_tx, opened_rx) = mpsc::sync_channel(1);
        let (go, go_rx) = mpsc::sync_channel::<()>(1);
        let dropped = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let thread_stop = Arc::clone(&stop);
        let thread_dropped = Arc::clone(&dropped);
        let (limit, quiet) = (p.frames, p.quiet);
        let handle = thread::Builder::new()
            .name("capture".into())
            .spawn(move || {
                let (source, description) = match Opened::open(&spec, channel) {
                    Ok(x) => x,
                    Err(e) => {
                        let _ = opened_tx.send(Err(e));
                        return;
                    }
                };
                let _ = opened_tx.send(Ok(description));
                if go_rx.recv().is_err() {
                    return;
                }
                capture_loop(
                    source,
                    &spec,
                    channel,
                    &tx,
                    &thread_stop,
                    &thread_dropped,
                    limit,
                    quiet,
                );
            })
            .map_err(|e| format!("cannot start the capture thread: {e}"))?;
        let description = opened_rx
            .recv()
            .map_err(|_| "the capture thread ended before opening the source".to_string())??;
        Ok(Capture {
            events,
            go: Some(go),
            dropped,
            handle: Some(handle),
            stop,
            description,
        })
    }

    /// Lets the frames flow.
    pub fn start(&mut self) {
        if let Some(go) = self.go.take() {
            let _ = go.send(());
        }
    }

    /// Frames dropped so far.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

impl Drop for Capture {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.go.take();
        // Unblocks a capture thread waiting on a full queue.
        while self.events.try_recv().is_ok() {}
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn capture_loop(
    mut source: Opened,
    spec: &SourceSpec,
    channel: optical_tactile::Channel,
    tx: &SyncSender<Event>,
    stop: &AtomicBool,
    dropped: &std::sync::atomic::AtomicU64,
    limit: Option<u64>,
    quiet: bool,
) {
    let drops = spec.drops();
    let period = match spec {
        SourceSpec::Sequence { rate, .. } if *rate > 0.0 => {
            Some(Duration::from_secs_f64(1.0 / rate))
        }
        _ => None,
    };
    let mut next_at = Instant::now();
    let mut read = 0u64;
    let mut last_drop_log: Option<Instant> = None;
    // Counted down by the camera's reopen attempts (feature `v4l`).
    #[allow(unused_mut)]
    let mut reopens_left = match spec {
        SourceSpec::Camera { reopen, .. } => *reopen,
        SourceSpec::Sequence { .. } => 0,
    };
    while !stop.load(Ordering::Relaxed) && limit.is_none_or(|n| read < n) {
        if let Some(p) = period {
            let now = Instant::now();
            if next_at > now {
                thread::sleep(next_at - now);
            }
            next_at = next_at.max(now) + p;
        }
        let Some(result) = source.next() else {
            break;
        };
        let event = match result {
            Ok(frame) => {
                read += 1;
                Event::Frame(Captured {
                    frame,
                    stamp: source.stamp(),
                })
            }
            Err(e) => match source {
                Opened::Sequence(_) => Event::Unreadable(e.to_string()),
                #[cfg(feature = "v4l")]
                Opened::Camera(_) => {
                    eprintln!("camera error: {e}");
                    // Closed before it is opened again.
                    drop(source);
                    match reopen(spec, channel, &mut reopens_left, stop) {
                        Some(s) => {
                            source = s;
                            continue;
                        }
                        None => {
                            let _ = tx.send(Event::Fatal(format!(
                                "the camera stopped delivering frames: {e}"
                            )));
                            return;
                        }
                    }
                }
            },
        };
        if drops {
            match tx.try_send(event) {
                Ok(()) => {}
                Err(TrySendError::Full(Event::Frame(c))) => {
                    dropped.fetch_add(1, Ordering::Relaxed);
                    let due = last_drop_log.is_none_or(|t| t.elapsed() >= Duration::from_secs(1));
                    if !quiet && due {
                        eprintln!(
                            "dropped frame {} (processing busy): {} dropped so far",
                            c.frame.name,
                            dropped.load(Ordering::Relaxed)
                        );
                        last_drop_log = Some(Instant::now());
                    }
                }
                Err(TrySendError::Full(other)) => {
                    // An unreadable-frame note: wait for room rather than lose it.
                    if tx.send(other).is_err() {
                        return;
                    }
                }
                Err(TrySendError::Disconnected(_)) => return,
            }
        } else if tx.send(event).is_err() {
            return;
        }
    }
    #[cfg(not(feature = "v4l"))]
    let _ = (reopens_left, channel);
}

/// The system-clock time of a capture at `capture` on the monotonic clock,
/// read at `mono_now` and `now`: `now` less the frame's age. `now` itself
/// without a capture time, or when the age is negative or above a second
/// (a driver whose stamps are not what they claim).
pub fn capture_on_system_clock(
    capture: Option<Duration>,
    mono_now: Option<Duration>,
    now: SystemTime,
) -> SystemTime {
    match (capture, mono_now) {
        (Some(c), Some(m)) => match m.checked_sub(c) {
            Some(age) if age <= Duration::from_secs(1) => now.checked_sub(age).unwrap_or(now),
            _ => now,
        },
        _ => now,
    }
}

/// The monotonic clock (`CLOCK_MONOTONIC`), the clock of V4L2 time stamps.
#[cfg(feature = "v4l")]
fn monotonic_now() -> Option<Duration> {
    let t = nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC).ok()?;
    let (sec, nsec) = (
        u64::try_from(t.tv_sec()).ok()?,
        u32::try_from(t.tv_nsec()).ok()?,
    );
    Some(Duration::new(sec, nsec))
}

#[cfg(feature = "v4l")]
fn reopen(
    spec: &SourceSpec,
    channel: optical_tactile::Channel,
    left: &mut u32,
    stop: &AtomicBool,
) -> Option<Opened> {
    while *left > 0 && !stop.load(Ordering::Relaxed) {
        *left -= 1;
        thread::sleep(Duration::from_secs(1));
        match Opened::open(spec, channel) {
            Ok((s, d)) => {
                eprintln!("reopened {d}");
                return Some(s);
            }
            Err(e) => eprintln!("{e} ({} attempts left)", *left),
        }
    }
    None
}

/// Runs the frames of `capture` through `pipeline` into `sink` until the
/// source ends or `stop` is set. The first readable frame is the
/// reference. A frame that cannot be read or processed (another size than
/// the reference, say) is named on stderr and skipped; a frame whose
/// messages hold a non-finite value is named and not published. Errors on
/// a source that cannot go on, a reference that cannot be taken, or a sink
/// that fails.
pub fn process_frames(
    capture: &mut Capture,
    pipeline: &mut Pipeline,
    sink: &mut dyn Publish,
    p: &Processing,
    stop: &AtomicBool,
) -> Result<Report, String> {
    let mut report = Report::default();
    let mut have_reference = false;
    let mut started: Option<Instant> = None;
    capture.start();
    loop {
        let event = match capture.events.recv_timeout(Duration::from_millis(100)) {
            Ok(e) => e,
            Err(RecvTimeoutError::Timeout) => {
                if stop.load(Ordering::Relaxed) {
                    break;
                }
                continue;
            }
            Err(RecvTimeoutError::Disconnected) => break,
        };
        let c = match event {
            Event::Frame(c) => c,
            Event::Unreadable(e) => {
                eprintln!("skipping unreadable frame: {e}");
                report.skipped += 1;
                continue;
            }
            Event::Fatal(e) => return Err(e),
        };
        report.received += 1;
        started.get_or_insert_with(Instant::now);
        if !have_reference {
            pipeline.set_reference(&c.frame).map_err(|e| {
                format!(
                    "frame {}: cannot take it as the reference: {e}",
                    c.frame.name
                )
            })?;
            have_reference = true;
            continue;
        }
        let t = Instant::now();
        let header = Header {
            stamp: c.stamp,
            frame_id: p.frame_id.clone(),
        };
        let messages = match pipeline.process(&c.frame, &header, &p.style, p.debug_image) {
            Ok(m) => m,
            Err(e) => {
                eprintln!("skipping frame {}: {e}", c.frame.name);
                report.skipped += 1;
                continue;
            }
        };
        if let Err(e) = messages.check_finite() {
            eprintln!("frame {}: not published: {e}", c.frame.name);
            report.non_finite += 1;
        } else {
            sink.publish(messages)?;
            report.published += 1;
        }
        let ms = t.elapsed().as_secs_f64() * 1e3;
        report.busy_ms += ms;
        report.max_ms = report.max_ms.max(ms);
    }
    report.dropped = capture.dropped();
    report.wall_s = started.map_or(0.0, |t| t.elapsed().as_secs_f64());
    if !have_reference && !stop.load(Ordering::Relaxed) {
        return Err("no readable frame: no reference".into());
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn capture_times_move_to_the_system_clock_by_the_frame_age() {
        let now = SystemTime::UNIX_EPOCH + Duration::from_secs(1_000_000);
        let at = |c: u64, m: u64| {
            capture_on_system_clock(
                Some(Duration::from_millis(c)),
                Some(Duration::from_millis(m)),
                now,
            )
        };
        assert_eq!(at(5_000, 5_020), now - Duration::from_millis(20));
        // From the future, or older than a second: the receive time.
        assert_eq!(at(5_030, 5_020), now);
        assert_eq!(at(1_000, 5_020), now);
        assert_eq!(
            capture_on_system_clock(None, Some(Duration::ZERO), now),
            now
        );
        assert_eq!(
            capture_on_system_clock(Some(Duration::ZERO), None, now),
            now
        );
    }
}
