//! Contacts from a live V4L2 camera (Linux, `--features v4l`).
//!
//! ```text
//! cargo run --release --features v4l --example live -- [--device /dev/video0]
//!     [--size 1920x1080] [--fps 50] [--calibration fixtures/calibration.json]
//!     [--crop x,y,w,h] [--frames N] [--out contacts.jsonl]
//! ```
//!
//! The first frame is the reference: start with nothing touching the skin.
//! Every later frame's contacts are printed (id, location mm, force N). The
//! flow and segmentation settings come from the calibration (as in the
//! `track` example). A camera that vanishes ends the run with an error (the
//! capture times out instead of hanging); lines already written to `--out`
//! are kept.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use optical_tactile::calibration::Calibration;
use optical_tactile::capture::FrameSource;
use optical_tactile::capture::v4l::{Camera, CameraConfig};
use optical_tactile::frame::Roi;
use optical_tactile::io::{FrameRecord, JsonlWriter};
use optical_tactile::sensor::{ExtractorConfig, SensorConfig, TactileSensor};

const USAGE: &str = "usage: live [--device /dev/video0] [--size WxH (default 1920x1080)] [--fps 50] \
[--calibration FILE (default fixtures/calibration.json)] [--crop x,y,w,h] [--frames N (default: until stopped)] \
[--out contacts.jsonl]";

fn run() -> Result<(), String> {
    let mut cam = CameraConfig::default();
    let mut calibration = PathBuf::from("fixtures/calibration.json");
    let mut crop = None;
    let mut frames: Option<usize> = None;
    let mut out = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut val = |name: &str| args.next().ok_or(format!("{name} needs a value\n{USAGE}"));
        match a.as_str() {
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(());
            }
            "--device" => cam.device = val("--device")?,
            "--size" => {
                let v = val("--size")?;
                let (w, h) = v
                    .split_once('x')
                    .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
                    .ok_or(format!("--size: expected WxH, got `{v}`"))?;
                cam.width = w;
                cam.height = h;
            }
            "--fps" => {
                let v = val("--fps")?;
                cam.fps = v
                    .parse()
                    .map_err(|_| format!("--fps: not a number: `{v}`"))?;
            }
            "--calibration" => calibration = PathBuf::from(val("--calibration")?),
            "--crop" => crop = Some(Roi::parse(&val("--crop")?).map_err(|e| e.to_string())?),
            "--frames" => {
                let v = val("--frames")?;
                frames = Some(
                    v.parse()
                        .map_err(|_| format!("--frames: not a number: `{v}`"))?,
                );
            }
            "--out" => out = Some(PathBuf::from(val("--out")?)),
            _ => return Err(format!("unknown argument {a}\n{USAGE}")),
        }
    }
    if !calibration.is_file() {
        return Err(format!(
            "calibration file {} not found (fit one with the `calibrate` example, or pass --calibration FILE)",
            calibration.display()
        ));
    }
    let cal = Calibration::load(&calibration).map_err(|e| e.to_string())?;
    let config = SensorConfig {
        crop,
        extractor: ExtractorConfig::from_setup(&cal.setup).map_err(|e| e.to_string())?,
        ..SensorConfig::default()
    };
    let mut sensor = TactileSensor::new(config, cal).map_err(|e| e.to_string())?;
    let mut camera = Camera::open(cam).map_err(|e| e.to_string())?;
    let (w, h) = camera.size();
    eprintln!("camera {w}x{h}, crop {:?}", sensor.crop());
    let mut writer = match &out {
        Some(p) => Some(JsonlWriter::create(p).map_err(|e| e.to_string())?),
        None => None,
    };

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
            println!(
                "{} t={:.3}s id {} at ({x:.1}, {y:.1}, {z:.1}) mm, F = ({fx:.2}, {fy:.2}, {fz:.2}) N ({latency_ms:.1} ms)",
                frame.name, frame.t_s, c.id
            );
        }
        if sensor.rereferenced() {
            eprintln!("{}: new reference (quiet, small flow)", frame.name);
        }
        if let Some(wr) = &mut writer {
            wr.write(&FrameRecord {
                frame: frame.name.clone(),
                t_s: frame.t_s,
                contacts: contacts.iter().map(|c| c.to_record()).collect(),
                latency_ms: Some(latency_ms),
            })
            .map_err(|e| e.to_string())?;
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
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
