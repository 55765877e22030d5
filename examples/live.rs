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
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use cli_support::pipeline::{Found, Pipeline, PipelineArgs, contact_row, patch_row};
use cli_support::{Failure, Sink, TextOut};
use optical_tactile::capture::FrameSource;
use optical_tactile::capture::v4l::{Camera, CameraConfig};

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
    #[command(flatten)]
    pipeline: PipelineArgs,
    /// Stop after N frames [default: run until stopped].
    #[arg(long, value_name = "N")]
    frames: Option<usize>,
    /// Write JSON Lines (one line per frame) to FILE, or to stdout with `-`
    /// (the contacts' lines then go to stderr).
    #[arg(long, value_name = "FILE|-")]
    out: Option<TextOut>,
}

fn run(a: &Cli) -> Result<(), Failure> {
    let frames = a.frames;
    let mut cam = CameraConfig {
        device: a.device.clone(),
        fps: a.fps,
        ..CameraConfig::default()
    };
    (cam.width, cam.height) = (
        u32::try_from(a.size.0).map_err(|_| "--size: width too large")?,
        u32::try_from(a.size.1).map_err(|_| "--size: height too large")?,
    );
    let mut sensor = a.pipeline.build(|_| {})?;
    cam.channel = a.pipeline.channel;
    let mut camera = Camera::open(cam).map_err(|e| e.to_string())?;
    let (w, h) = camera.size();
    let crop = match &sensor {
        Pipeline::Calibrated(s) => s.crop().to_arg(),
        Pipeline::Raw(r) => r
            .crop()
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
