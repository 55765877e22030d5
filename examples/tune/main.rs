//! Tunes the segmentation live in a browser: a local web page shows the
//! debug panel of every frame (flow with the mask's contours; divergent
//! field with each patch's box, contact point and force arrow; potential;
//! grey image), the contacts (or, with `--raw`, the patches in pixels), the
//! counts and the time of each stage, and controls for the thresholds, the
//! kernels, the presets, the flow, the split rule, the filter,
//! re-referencing and pause/step.
//!
//! ```text
//! cargo run --release --example tune -- [SEQ_DIR | --camera DEV] [--calibration FILE | --raw]
//!     [--port 8000] [--bind 127.0.0.1] [--save-dir DIR] [track's pipeline flags]
//! ```
//!
//! Then open the printed address (`http://127.0.0.1:8000/`). The sequence
//! (default: this crate's `fixtures/press`) plays in a loop, its first frame
//! the reference; `--camera` (built with `--features v4l`) runs a live camera,
//! its first frame the reference (start with nothing touching the skin).
//!
//! A change on the page applies from the next frame (while paused, to the
//! frame on screen). The pipeline is rebuilt with the new settings and takes
//! its reference again, so tracked contacts get new ids. The page shows the
//! settings as `track` flags and as the calibration file's `thresholds` and
//! `pipeline` entries, and saves the calibration with the tuned thresholds
//! and flow preset as a new file in `--save-dir` (default: the working
//! directory); it never writes over a file.
//!
//! The server listens on 127.0.0.1 only: other machines cannot reach it.
//! `--bind 0.0.0.0` serves every network interface, to tune from another
//! machine; the page has no authentication, so do that on a network you
//! trust only. Requests are bounded (64 KiB bodies, 16 KiB heads, 32
//! connections); a malformed one gets a 4xx answer. On a loopback address,
//! requests that name another host are refused (a page of another site
//! reaching it through DNS rebinding), and controls must come as JSON (a
//! form of another site cannot send them).
//!
//! `--run-for SECS` stops after that many seconds (for scripts); otherwise
//! the tool runs until stopped (Ctrl-C).

#[path = "../cli_support/mod.rs"]
mod cli_support;

mod app;
mod http;
mod runner;

use std::io::Write as _;
use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::{Arc, Condvar, Mutex, mpsc};
use std::time::Duration;

use clap::{ArgAction, Parser};
use cli_support::Failure;
use cli_support::pipeline::PipelineArgs;

use app::{App, State};
use runner::{Looped, Runner, Source};

/// The sequence run with no argument: this crate's fixture.
const DEFAULT_SEQ: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/press");

/// Longest `--run-for`, seconds (a day).
const MAX_RUN_FOR_S: u64 = 86_400;

/// Tunes the segmentation live: serves a web page with the debug panel of
/// every frame, the contacts, and controls for the thresholds.
#[derive(Parser, Debug)]
#[command(
    name = "tune",
    after_help = "Open the printed address in a browser. The server listens on 127.0.0.1 \
                  unless --bind says otherwise (--bind 0.0.0.0: every interface, no \
                  authentication). Exit status: 0, 1 on an error, 2 on a usage error."
)]
struct Cli {
    /// Folder of frames (PNG, in name order), played in a loop [default:
    /// this crate's fixtures/press].
    #[arg(value_name = "SEQ_DIR", conflicts_with = "camera")]
    seq: Option<PathBuf>,
    /// A V4L2 camera instead of a sequence (needs `--features v4l`).
    #[arg(long, value_name = "DEV")]
    camera: Option<String>,
    /// Camera frame size.
    #[arg(long, value_name = "WxH", default_value = "1920x1080", value_parser = cli_support::size)]
    size: (usize, usize),
    /// Camera frame rate.
    #[arg(long, value_name = "FPS", default_value_t = 50, value_parser = clap::value_parser!(u32).range(1..=1000))]
    fps: u32,
    /// Frames per second a sequence is played at, at most (0: as fast as
    /// the pipeline goes, which leaves the page less of the processor).
    #[arg(long, value_name = "FPS", default_value_t = 20, value_parser = clap::value_parser!(u32).range(0..=1000))]
    play_fps: u32,
    #[command(flatten)]
    pipeline: PipelineArgs,
    /// Kalman filter on the tracked contacts (the page can change it).
    #[arg(long, value_name = "on|off", default_value = "off", action = ArgAction::Set, value_parser = cli_support::on_off)]
    filter: bool,
    /// Take a fresh reference after a quiet spell (the page can change it).
    #[arg(long, value_name = "on|off", default_value = "on", action = ArgAction::Set, value_parser = cli_support::on_off)]
    rereference: bool,
    /// Port to listen on (0: any free port; the address is printed).
    #[arg(long, value_name = "P", default_value_t = 8000)]
    port: u16,
    /// Address to listen on: 127.0.0.1 is this machine only; 0.0.0.0 every
    /// network interface.
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1")]
    bind: IpAddr,
    /// Directory the page saves tuned calibrations to (new files only).
    #[arg(long, value_name = "DIR", default_value = ".")]
    save_dir: PathBuf,
    /// Stop after SECS seconds [default: run until stopped].
    #[arg(long, value_name = "SECS", value_parser = clap::value_parser!(u64).range(1..=MAX_RUN_FOR_S))]
    run_for: Option<u64>,
}

/// The `track` flags that the page does not change.
fn fixed_args(a: &Cli) -> Vec<String> {
    let p = &a.pipeline;
    let mut v = vec![match (&a.seq, &a.camera) {
        (Some(s), _) => s.display().to_string(),
        (None, Some(_)) => "SEQ_DIR".to_string(),
        (None, None) => DEFAULT_SEQ.to_string(),
    }];
    if p.raw {
        v.push("--raw".into());
    } else {
        v.push(format!("--calibration {}", p.calibration.display()));
    }
    if let Some(c) = p.crop {
        v.push(format!("--crop {}", c.to_arg()));
    }
    if p.force_crop {
        v.push("--force-crop".into());
    }
    v.push(format!("--channel {}", channel_name(p.channel)));
    if let Some(e) = p.exposure {
        v.push(format!("--exposure {}", e.name()));
    }
    v
}

fn channel_name(c: optical_tactile::frame::Channel) -> &'static str {
    match c {
        optical_tactile::frame::Channel::Luma => "luma",
        optical_tactile::frame::Channel::Green => "green",
    }
}

/// Opens the frames' source (in the pipeline thread: a camera stays on the
/// thread that opened it).
fn open_source(a: &CameraArgs) -> Result<Source, String> {
    match &a.camera {
        None => Ok(Source::Sequence(Looped::open(&a.seq, a.channel)?)),
        Some(dev) => open_camera(dev, a),
    }
}

/// What the pipeline thread needs to open the source.
#[cfg_attr(not(feature = "v4l"), allow(dead_code))]
struct CameraArgs {
    seq: PathBuf,
    camera: Option<String>,
    size: (usize, usize),
    fps: u32,
    channel: optical_tactile::frame::Channel,
}

#[cfg(feature = "v4l")]
fn open_camera(dev: &str, a: &CameraArgs) -> Result<Source, String> {
    use optical_tactile::capture::v4l::{Camera, CameraConfig};
    let config = CameraConfig {
        device: dev.to_string(),
        width: u32::try_from(a.size.0).map_err(|_| "--size: width too large")?,
        height: u32::try_from(a.size.1).map_err(|_| "--size: height too large")?,
        fps: a.fps,
        channel: a.channel,
        ..CameraConfig::default()
    };
    let cam = Camera::open(config).map_err(|e| e.to_string())?;
    Ok(Source::Live(Box::new(cam)))
}

#[cfg(not(feature = "v4l"))]
fn open_camera(_dev: &str, _a: &CameraArgs) -> Result<Source, String> {
    Err(
        "--camera needs the camera feature: cargo run --release --features v4l \
         --example tune -- --camera DEV"
            .to_string(),
    )
}

fn run(a: Cli) -> Result<ExitCode, Failure> {
    let save_dir = app::save_dir(&a.save_dir)?;
    let pipeline = a.pipeline.build(|c| {
        c.tracker.filter = a.filter.then(optical_tactile::track::FilterConfig::default);
        c.rereference.enabled = a.rereference;
    })?;
    let calibration = match &pipeline {
        cli_support::pipeline::Pipeline::Calibrated(s) => Some(s.calibration().clone()),
        cli_support::pipeline::Pipeline::Raw(_) => None,
    };
    let settings = runner::settings_of(&pipeline, a.pipeline.split, a.filter, a.rereference);
    let app = Arc::new(App {
        state: Mutex::new(State::new(settings)),
        changed: Condvar::new(),
        calibration,
        save_dir,
        fixed_args: fixed_args(&a),
        loopback_only: a.bind.is_loopback(),
    });

    // The pipeline thread: opens the source, says whether it could, then runs.
    let source_args = CameraArgs {
        seq: a.seq.clone().unwrap_or_else(|| PathBuf::from(DEFAULT_SEQ)),
        camera: a.camera.clone(),
        size: a.size,
        fps: a.fps,
        channel: a.pipeline.channel,
    };
    let (ready_tx, ready_rx) = mpsc::channel::<Result<(), String>>();
    let (runner_app, base, play_fps) = (app.clone(), a.pipeline.clone(), a.play_fps);
    std::thread::Builder::new()
        .name("pipeline".into())
        .spawn(move || match open_source(&source_args) {
            Ok(source) => {
                let _ = ready_tx.send(Ok(()));
                Runner::new(runner_app, base, pipeline, source, f64::from(play_fps)).run();
            }
            Err(e) => {
                let _ = ready_tx.send(Err(e));
            }
        })
        .map_err(|e| format!("cannot start the pipeline thread: {e}"))?;
    ready_rx
        .recv()
        .map_err(|_| "the pipeline thread stopped".to_string())??;

    let handler_app = app.clone();
    let addr = SocketAddr::new(a.bind, a.port);
    let server = http::Server::start(&addr.to_string(), http::Limits::default(), move |rq| {
        handler_app.handle(rq)
    })
    .map_err(|e| format!("cannot listen on {addr}: {e}"))?;
    let url = format!("http://{}/", server.addr());
    {
        let mut out = std::io::stdout().lock();
        writeln!(out, "tune: serving {url}")?;
        out.flush()?;
    }
    eprintln!(
        "open {url} in a browser; saving to {}; Ctrl-C stops",
        app.save_dir.display()
    );
    match a.run_for {
        Some(s) => std::thread::sleep(Duration::from_secs(s)),
        None => loop {
            std::thread::park();
        },
    }
    Ok(ExitCode::SUCCESS)
}

fn main() -> ExitCode {
    cli_support::finish(run(Cli::parse()))
}
