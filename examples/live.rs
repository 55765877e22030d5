//! Contacts from a live V4L2 camera (Linux, `--features v4l`).
//!
//! ```text
//! cargo run --release --features v4l --example live -- [--device /dev/video0]
//!     [--size 1920x1080] [--fps 50] [--calibration fixtures/calibration.json]
//!     [--crop x,y,w,h] [--frames N] [--out contacts.jsonl|-]
//! ```
//!
//! The first frame is the reference: start with nothing touching the skin.
//! Every later frame's contacts are printed (id, location mm, force N). The
//! flow and segmentation settings come from the calibration (as in the
//! `track` example). A camera that vanishes ends the run with an error (the
//! capture times out instead of hanging); lines already written to `--out`
//! are kept. `--out -` writes the JSON Lines to stdout and the contacts'
//! lines to stderr; a closed stdout ends the run quietly. The default
//! calibration is this crate's `fixtures/calibration.json`.

#[path = "cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use cli_support::{Failure, Sink, TextOut};
use optical_tactile::calibration::Calibration;
use optical_tactile::capture::FrameSource;
use optical_tactile::capture::v4l::{Camera, CameraConfig};
use optical_tactile::frame::Roi;
use optical_tactile::io::FrameRecord;
use optical_tactile::sensor::TactileSensor;

/// The calibration used unless `--calibration` names another: this crate's.
const DEFAULT_CALIBRATION: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/calibration.json");

/// Contacts from a live V4L2 camera. The first frame is the reference: start
/// with nothing touching the skin.
#[derive(Parser, Debug)]
#[command(name = "live")]
struct Cli {
    /// Camera device.
    #[arg(long, value_name = "PATH", default_value_t = CameraConfig::default().device)]
    device: String,
    /// Requested frame size.
    #[arg(long, value_name = "WxH", default_value = "1920x1080", value_parser = cli_support::size)]
    size: (usize, usize),
    /// Requested frame rate.
    #[arg(long, value_name = "FPS", default_value_t = CameraConfig::default().fps)]
    fps: u32,
    /// Calibration file.
    #[arg(long, value_name = "FILE", default_value = DEFAULT_CALIBRATION)]
    calibration: PathBuf,
    /// Crop of the camera frame [default: the calibration's].
    #[arg(long, value_name = "x,y,w,h", value_parser = cli_support::roi)]
    crop: Option<Roi>,
    /// Stop after N frames [default: run until stopped].
    #[arg(long, value_name = "N")]
    frames: Option<usize>,
    /// Write JSON Lines (one line per frame) to FILE, or to stdout with `-`
    /// (the contacts' lines then go to stderr).
    #[arg(long, value_name = "FILE|-")]
    out: Option<TextOut>,
}

fn run(a: &Cli) -> Result<(), Failure> {
    let (calibration, frames) = (&a.calibration, a.frames);
    let mut cam = CameraConfig {
        device: a.device.clone(),
        fps: a.fps,
        ..CameraConfig::default()
    };
    (cam.width, cam.height) = (
        u32::try_from(a.size.0).map_err(|_| "--size: width too large")?,
        u32::try_from(a.size.1).map_err(|_| "--size: height too large")?,
    );
    if !calibration.is_file() {
        return Err(format!(
            "calibration file {} not found (fit one with the `calibrate` example, or pass --calibration FILE)",
            calibration.display()
        )
        .into());
    }
    let cal = Calibration::load(calibration).map_err(|e| e.to_string())?;
    let mut builder = TactileSensor::builder(cal);
    if let Some(crop) = a.crop {
        builder = builder.crop(crop);
    }
    let mut sensor = builder.build().map_err(|e| e.to_string())?;
    let mut camera = Camera::open(cam).map_err(|e| e.to_string())?;
    let (w, h) = camera.size();
    let crop = sensor.crop();
    eprintln!(
        "camera {w}x{h}, crop {},{},{},{}",
        crop.x, crop.y, crop.w, crop.h
    );
    let mut writer = a.out.as_ref().map(TextOut::create).transpose()?;
    let mut report = Sink::report(a.out.as_ref().is_some_and(TextOut::is_stdout));

    let first = camera
        .next_frame()
        .ok_or("the camera gave no frame")?
        .map_err(|e| e.to_string())?;
    sensor
        .set_reference(&first.image)
        .map_err(|e| e.to_string())?;
    eprintln!("reference taken (frame {})", first.name);

    let mut n = 0usize;
    let start = Instant::now();
    while frames.is_none_or(|max| n < max) {
        let frame = camera
            .next_frame()
            .ok_or("the camera stream ended")?
            .map_err(|e| e.to_string())?;
        let t = Instant::now();
        let contacts = sensor
            .process(&frame.image, frame.t_s)
            .map_err(|e| format!("frame {}: {e}", frame.name))?
            .to_vec();
        let latency_ms = t.elapsed().as_secs_f64() * 1e3;
        n += 1;
        for c in &contacts {
            let [x, y, z] = c.location_mm;
            let [fx, fy, fz] = c.force_n;
            writeln!(
                report,
                "{} t={:.3}s id {} at ({x:.1}, {y:.1}, {z:.1}) mm, F = ({fx:.2}, {fy:.2}, {fz:.2}) N ({latency_ms:.1} ms)",
                frame.name, frame.t_s, c.id
            )?;
        }
        if sensor.rereferenced() {
            eprintln!("{}: new reference (quiet, small flow)", frame.name);
        }
        if let Some(wr) = &mut writer {
            wr.json_line(&FrameRecord {
                frame: frame.name.clone(),
                t_s: frame.t_s,
                contacts: contacts.iter().map(|c| c.to_record()).collect(),
                latency_ms: Some(latency_ms),
            })?;
        }
        if n % 250 == 0 {
            eprintln!(
                "{n} frames, {:.1} fps",
                n as f64 / start.elapsed().as_secs_f64()
            );
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    cli_support::finish(run(&Cli::parse()).map(|()| ExitCode::SUCCESS))
}
