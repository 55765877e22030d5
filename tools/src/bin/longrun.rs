//! A long run: many frames through `TactileSensor::process`, reporting the
//! process's resident memory (VmRSS) and its peak (VmHWM) from
//! `/proc/self/status` along the way, to show memory stays flat after warm-up.
//!
//! ```text
//! cargo run --release -p optical-tactile-tools --bin longrun -- [--frames 10000] [--preset fast|accurate|...]
//!     [--full-frame] [--every 1000]
//! ```
//!
//! A few simulated frames are rendered once and reused cyclically, in cycles
//! of 200 frames (50 Hz time stamps): 150 frames at rest (each of 3 rest
//! renders with their own noise: after 2 s of quiet the sensor re-references),
//! then 50 frames of a two-rod press ramping through 4 force levels, so that
//! contacts start, are tracked, end, and new ids are taken all run long.
//! Linux only (reads `/proc/self/status`).

#[path = "../../../examples/cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use cli_support::{Failure, Sink};

use ndarray::Array2;
use optical_tactile::calibration::poly::Polynomial;
use optical_tactile::calibration::{Calibration, SensorSetup};
use optical_tactile::flow::dis::{DisParams, DisPreset};
use optical_tactile::frame::Roi;
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::segment::{Shape, Thresholds};
use optical_tactile::sensor::{ExtractorConfig, SensorConfig, TactileSensor};
use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};

/// `VmRSS` and `VmHWM` in kB.
fn memory_kb() -> Result<(u64, u64), String> {
    let s = std::fs::read_to_string("/proc/self/status")
        .map_err(|e| format!("cannot read /proc/self/status: {e}"))?;
    let field = |name: &str| -> Result<u64, String> {
        s.lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next()?.parse().ok())
            .ok_or(format!("no {name} in /proc/self/status"))
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?))
}

/// A linear calibration (x = (x_px - 799.5) / 5 mm, F = 1e-4 D): memory and
/// time do not depend on the maps' accuracy.
fn calibration(crop: Roi) -> Result<Calibration, String> {
    let e = |e: optical_tactile::Error| e.to_string();
    let g1 =
        Polynomial::raw(&["x2d"], vec![vec![0], vec![1]], vec![-799.5 / 5.0, 0.2]).map_err(e)?;
    let g2 = Polynomial::raw(&["y2d"], vec![vec![0]], vec![0.0]).map_err(e)?;
    let vars = ["dx", "dy", "dz", "x2d", "y2d", "d_pf"];
    let lin = |k: usize| {
        let mut ex = vec![0u32; 6];
        ex[k] = 1;
        Polynomial::raw(&vars, vec![ex], vec![1e-4]).map_err(e)
    };
    let setup = SensorSetup {
        geometry: SensorGeometry::default(),
        crop,
        thresholds: Thresholds {
            magnitude: 0.5,
            sum: 600.0,
            erode: 5,
            dilate: 15,
            shape: Shape::Rect,
        },
        pipeline: None,
    };
    Calibration::new(setup, [g1, g2, lin(0)?, lin(1)?, lin(2)?], None).map_err(e)
}

/// Many frames through TactileSensor::process, reporting the resident
/// memory (VmRSS) and its peak (VmHWM) along the way (Linux).
#[derive(Parser, Debug)]
#[command(name = "longrun")]
struct Cli {
    /// Frames to process.
    #[arg(long, value_name = "N", default_value_t = 10_000)]
    frames: usize,
    /// Report every N frames.
    #[arg(long, value_name = "N", default_value_t = 1_000)]
    every: usize,
    /// DIS flow preset.
    #[arg(long, value_name = "PRESET", default_value = "fast", ignore_case = true,
          value_parser = cli_support::dis_preset())]
    preset: DisPreset,
    /// Render the full 1920x1080 camera frame (the sensor crops the strip).
    #[arg(long)]
    full_frame: bool,
}

fn run(cli: &Cli) -> Result<(), Failure> {
    let mut out = Sink::stdout();
    let (frames, every, preset, full_frame) = (cli.frames, cli.every, cli.preset, cli.full_frame);
    let every = every.max(1);
    let (rss0, _) = memory_kb()?;

    let config = SimConfig {
        full_frame,
        ..SimConfig::default()
    };
    let (x, y, w, h) = config.camera.crop();
    let crop = if full_frame {
        Roi::new(x, y, w, h)
    } else {
        Roi::new(0, 0, w, h)
    };
    let mut sim = SyntheticSensor::new(config, 1).map_err(|e| e.to_string())?;
    let render = |sim: &mut SyntheticSensor, c: &[Press]| -> Result<Array2<f32>, String> {
        Ok(sim.render(c).map_err(|e| e.to_string())?.0)
    };
    let reference = render(&mut sim, &[])?;
    let rest: Vec<Array2<f32>> = (0..3)
        .map(|_| render(&mut sim, &[]))
        .collect::<Result<_, _>>()?;
    let press: Vec<Array2<f32>> = (1..=4)
        .map(|k| {
            let f = 0.5 * k as f64;
            render(
                &mut sim,
                &[
                    Press::rod(-20.0, [0.0, 0.0, -f], 5.0),
                    Press::rod(20.0, [0.0, 0.0, -0.75 * f], 5.0),
                ],
            )
        })
        .collect::<Result<_, _>>()?;

    let mut sensor_config = SensorConfig::default();
    sensor_config.crop = Some(crop);
    sensor_config.extractor = ExtractorConfig::default()
        .with_flow(DisParams::preset(preset))
        .with_thresholds(Thresholds {
            magnitude: 0.5,
            sum: 600.0,
            ..Thresholds::LOW
        });
    let mut sensor =
        TactileSensor::new(sensor_config, calibration(crop)?).map_err(|e| e.to_string())?;
    sensor
        .set_reference(&reference)
        .map_err(|e| e.to_string())?;
    let (rss_ready, _) = memory_kb()?;
    writeln!(
        out,
        "{} frames of {}x{} (crop {w}x{h}), preset {}; RSS {} kB at start, {} kB with frames rendered and the sensor built",
        frames,
        reference.ncols(),
        reference.nrows(),
        preset.name(),
        rss0,
        rss_ready
    )?;
    writeln!(
        out,
        "{:>7} {:>10} {:>10} {:>9} {:>8} {:>11} {:>8}",
        "frames", "VmRSS_kB", "VmHWM_kB", "contacts", "max_id", "references", "ms/frame"
    )?;
    let (mut contacts, mut max_id) = (0usize, 0u64);
    let mut busy = 0.0f64;
    let start = Instant::now();
    for n in 1..=frames {
        let phase = n % 200;
        let frame = if phase < 150 {
            &rest[phase % 3]
        } else {
            &press[((phase - 150) / 4).min(3)]
        };
        let t = Instant::now();
        let cs = sensor
            .process(frame, n as f64 * 0.02)
            .map_err(|e| format!("frame {n}: {e}"))?;
        busy += t.elapsed().as_secs_f64();
        contacts += cs.len();
        max_id = cs.iter().map(|c| c.id).fold(max_id, u64::max);
        if n % every == 0 || n == frames {
            let (rss, hwm) = memory_kb()?;
            writeln!(
                out,
                "{n:>7} {rss:>10} {hwm:>10} {contacts:>9} {max_id:>8} {:>11} {:>8.2}",
                sensor.reference_count(),
                1e3 * busy / n as f64
            )?;
        }
    }
    writeln!(
        out,
        "{} frames in {:.1} s ({:.1} fps in process())",
        frames,
        start.elapsed().as_secs_f64(),
        frames as f64 / busy
    )?;
    Ok(())
}

fn main() -> ExitCode {
    cli_support::finish(run(&Cli::parse()).map(|()| ExitCode::SUCCESS))
}
