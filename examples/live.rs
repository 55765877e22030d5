//! Contacts from a live V4L2 camera (Linux, `--features v4l`).
//!
//! ```text
//! cargo run --release --features v4l --example live -- [--device /dev/video0]
//!     [--size 1920x1080] [--fps 50] [--channel green|luma]
//!     [--calibration fixtures/calibration.json | --raw] [--crop x,y,w,h] [--force-crop]
//!     [--thresholds low|mid|high] [--preset PRESET] [--frames N] [--out contacts.jsonl|-]
//! ```
//!
//! The first frame is the reference: start with nothing touching the skin.
//! Every later frame's contacts are printed (id, location mm, force N). The
//! flow and segmentation settings come from the calibration (as in the
//! `track` example). A camera that vanishes ends the run with an error (the
//! capture times out instead of hanging); lines already written to `--out`
//! are kept. `--out -` writes the JSON Lines to stdout and the contacts'
//! lines to stderr; a closed stdout ends the run quietly. The default
//! calibration is this crate's `fixtures/calibration.json`. `--raw` needs no
//! calibration and reports each frame's patches in pixels with their raw
//! quantities, as `track --raw` does.

#[path = "cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use cli_support::pipeline::{Found, Pipeline, Raw, contact_row, patch_row};
use cli_support::{Failure, Sink, TextOut};
use optical_tactile::calibration::Calibration;
use optical_tactile::capture::FrameSource;
use optical_tactile::capture::v4l::{Camera, CameraConfig};
use optical_tactile::exposure::ExposureCompensation;
use optical_tactile::flow::dis::{DisParams, DisPreset};
use optical_tactile::frame::{Channel, Roi};
use optical_tactile::segment::ThresholdPreset;
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
    /// Take the camera's exposure changes (gain, black level) out of each
    /// frame against the reference: off, offset or gain-offset. Costs some
    /// accuracy on a steady camera; fit the calibration the same way.
    #[arg(long, value_name = "MODE", default_value = "off", value_parser = cli_support::pipeline::exposure)]
    exposure: ExposureCompensation,
    /// Which channel of colour frames becomes the grey image.
    #[arg(long, value_name = "green|luma", default_value = "green", value_parser = cli_support::pipeline::channel)]
    channel: Channel,
    /// Calibration file.
    #[arg(long, value_name = "FILE", default_value = DEFAULT_CALIBRATION)]
    calibration: PathBuf,
    /// No calibration: report each frame's patches in pixels with their raw quantities.
    #[arg(long)]
    raw: bool,
    /// Crop of the camera frame [default: the calibration's; with --raw, the whole frame].
    #[arg(long, value_name = "x,y,w,h", value_parser = cli_support::roi)]
    crop: Option<Roi>,
    /// Use a --crop that differs from the calibration's.
    #[arg(long)]
    force_crop: bool,
    /// Segmentation thresholds [default: the calibration's].
    #[arg(long, value_name = "PRESET", value_parser = cli_support::threshold_preset())]
    thresholds: Option<ThresholdPreset>,
    /// DIS flow preset [default: the calibration's].
    #[arg(long, value_name = "PRESET", ignore_case = true, value_parser = cli_support::dis_preset())]
    preset: Option<DisPreset>,
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
    let mut sensor = if a.raw {
        Pipeline::Raw(Box::new(Raw::new(
            a.crop,
            a.preset,
            a.thresholds,
            a.exposure,
        )?))
    } else {
        if !calibration.exists() {
            return Err(format!(
                "calibration file {} not found (fit one with the `calibrate` example, pass \
                 --calibration FILE, or run with --raw)",
                calibration.display()
            )
            .into());
        }
        let cal = Calibration::load(calibration).map_err(|e| e.to_string())?;
        let mut builder = TactileSensor::builder(cal);
        if let Some(crop) = a.crop {
            builder = builder.crop(crop).force_crop(a.force_crop);
        }
        if let Some(p) = a.preset {
            builder = builder.flow(DisParams::preset(p));
        }
        if let Some(t) = a.thresholds {
            builder = builder.thresholds(t);
        }
        let exposure = a.exposure;
        let sensor = builder
            .configure(|c| c.extractor.exposure = exposure)
            .build()
            .map_err(|e| e.to_string().replace("set force_crop", "pass --force-crop"))?;
        Pipeline::Calibrated(Box::new(sensor))
    };
    cam.channel = a.channel;
    let mut camera = Camera::open(cam).map_err(|e| e.to_string())?;
    let (w, h) = camera.size();
    let crop = match &sensor {
        Pipeline::Calibrated(s) => s.crop().to_arg(),
        Pipeline::Raw(r) => r
            .crop
            .map_or_else(|| "whole frame".to_string(), |c| c.to_arg()),
    };
    eprintln!("camera {w}x{h}, crop {crop}");
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
        let found = sensor
            .process(&frame.image, frame.t_s)
            .map_err(|e| format!("frame {}: {e}", frame.name))?;
        let latency_ms = t.elapsed().as_secs_f64() * 1e3;
        n += 1;
        match &found {
            Found::Contacts(contacts) => {
                for c in contacts {
                    writeln!(
                        report,
                        "{}",
                        contact_row(&frame.name, frame.t_s, c, latency_ms)
                    )?;
                }
            }
            Found::Patches(patches) => {
                for (k, r) in patches.iter().enumerate() {
                    writeln!(
                        report,
                        "{}",
                        patch_row(&frame.name, frame.t_s, k, r, latency_ms)
                    )?;
                }
            }
        }
        if sensor.rereferenced() {
            eprintln!("{}: new reference (quiet, small flow)", frame.name);
        }
        if let Some(wr) = &mut writer {
            found.json_line(wr, &frame.name, frame.t_s, latency_ms)?;
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
