//! What the camera alone does to the pipeline: simulated rest frames with
//! exposure steps and slow drift of gain and offset, through the raw
//! extractor (frames with a patch) and the calibrated sensor (contacts, and
//! contacts not marked out of the calibration's domain),
//! for each exposure compensation; plus the re-referencing policy's quiet
//! statistic (the largest mean `|flow|` over textured tiles) at rest, for
//! several tile sizes. Printed as markdown.
//!
//! ```text
//! cargo run --release -p optical-tactile-tools --bin camera_check -- --frames 1000
//! cargo run --release -p optical-tactile-tools --bin camera_check -- --seeds 1,2,3 --noise-read 1,2 \
//!     --exposure-steps 10,0.03,1,2 --drift 0.05,3,400
//! ```

#[path = "../../../examples/cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use cli_support::{Failure, Numbers, Sink};
use optical_tactile::calibration::Calibration;
use optical_tactile::exposure::ExposureCompensation;
use optical_tactile::flow::FlowField;
use optical_tactile::segment::ThresholdPreset;
use optical_tactile::sensor::{
    ContactExtractor, ExtractorConfig, QUIET_MIN_TEXTURE, TactileSensor, max_tile_mean_where,
    textured_tiles_into,
};
use optical_tactile::track::ReferencePolicy;
use optical_tactile_sim::{ExposureChanges, Press, SimConfig, SyntheticSensor};

const CALIBRATION: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/calibration.json");

/// Rest frames with exposure steps and drift through the extractor and the
/// calibrated sensor, per exposure compensation; the quiet statistic of
/// re-referencing at rest.
#[derive(Parser, Debug)]
#[command(name = "camera_check")]
struct Cli {
    /// Rest frames after the reference, per seed and noise level.
    #[arg(long, value_name = "N", default_value_t = 200)]
    frames: usize,
    /// Simulator seeds.
    #[arg(long, value_name = "a,b,..", default_value_t = Numbers(vec![1.0, 2.0, 3.0]))]
    seeds: Numbers,
    /// Read-noise levels, grey levels.
    #[arg(long, value_name = "a,b,..", default_value_t = Numbers(vec![1.0, 2.0]))]
    noise_read: Numbers,
    /// Exposure steps EVERY,GAIN,OFFSET,LEVELS (as `simulate --exposure-steps`); 0,0,0,1 for none.
    #[arg(long, value_name = "E,G,O,L", allow_hyphen_values = true,
          default_value_t = Numbers(vec![10.0, 0.03, 1.0, 2.0]))]
    exposure_steps: Numbers,
    /// Drift GAIN,OFFSET,PERIOD (as `simulate --drift`); 0,0,1 for none.
    #[arg(long, value_name = "G,O,P", allow_hyphen_values = true,
          default_value_t = Numbers(vec![0.05, 3.0, 400.0]))]
    drift: Numbers,
    /// Calibration (thresholds, flow preset, maps).
    #[arg(long, value_name = "FILE", default_value = CALIBRATION)]
    calibration: PathBuf,
    /// Forces of the light presses (5 mm rod, straight, at -80, 0 and 80 mm)
    /// whose quiet statistic is printed beside the rest frames', N.
    #[arg(long, value_name = "a,b,..", default_value_t = Numbers(vec![0.1, 0.2, 0.3, 0.5]))]
    press_forces: Numbers,
    /// Thresholds of the raw extractor (`low`, `mid`, `high`) [default: the
    /// calibration's].
    #[arg(long, value_name = "PRESET", value_parser = cli_support::threshold_preset())]
    raw_thresholds: Option<ThresholdPreset>,
    /// Exposure compensations to compare (off, offset, gain-offset, auto).
    #[arg(long, value_name = "a,b,..", value_delimiter = ',',
          default_value = "off,offset,gain-offset,auto", value_parser = cli_support::pipeline::exposure)]
    modes: Vec<ExposureCompensation>,
    /// Tile sides of the quiet statistic, full-resolution px.
    #[arg(long, value_name = "a,b,..", default_value_t = Numbers(vec![16.0, 32.0, 64.0]))]
    tiles: Numbers,
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

fn quiet(flow: &FlowField, scale: usize, reference: &ndarray::Array2<f32>, tile_px: usize) -> f64 {
    let tile = (tile_px / scale).max(1);
    let mut mask = Vec::new();
    let tiles_x = textured_tiles_into(reference, tile * scale, QUIET_MIN_TEXTURE, &mut mask);
    max_tile_mean_where(flow, tile, &mask, tiles_x)
}

fn run(cli: &Cli) -> Result<(), Failure> {
    let mut out = Sink::stdout();
    let calibration = Calibration::load(&cli.calibration)?;
    let e = &cli.exposure_steps.0;
    let d = &cli.drift.0;
    if e.len() != 4 || d.len() != 3 {
        return Err("--exposure-steps takes 4 numbers, --drift 3".into());
    }
    let exposure = ExposureChanges {
        step_every: e[0] as u64,
        step_gain: e[1] as f32,
        step_offset: e[2] as f32,
        step_levels: e[3] as u32,
        drift_gain: d[0] as f32,
        drift_offset: d[1] as f32,
        drift_period: d[2],
    };
    writeln!(
        out,
        "{} rest frames per seed and noise level, exposure {exposure:?}, calibration {}\n",
        cli.frames,
        cli.calibration.display()
    )?;
    writeln!(
        out,
        "| seed | read noise | compensation | frames with a patch (raw) | frames with a contact (calibrated), of which with one in domain | |gain-1| max | quiet flow p50 / p99 / max, tiles {} px | ms per frame (extract) |",
        cli.tiles
    )?;
    writeln!(out, "|---|---|---|---|---|---|---|---|")?;
    for &seed in &cli.seeds.0 {
        for &read in &cli.noise_read.0 {
            let mut cfg = SimConfig::default();
            cfg.noise.read = read as f32;
            cfg.noise.exposure = exposure;
            let sim = SyntheticSensor::new(cfg, seed as u64)?;
            let reference = sim.render_indexed(0, &[], false)?.frame;
            let mut runs = Vec::new();
            for &mode in &cli.modes {
                let mut config =
                    ExtractorConfig::from_setup(&calibration.setup)?.with_exposure(mode);
                if let Some(p) = cli.raw_thresholds {
                    config = config.with_thresholds(p);
                }
                let mut ex = ContactExtractor::new(config)?;
                ex.set_reference(&reference)?;
                let mut sensor = TactileSensor::builder(calibration.clone())
                    .rereference(ReferencePolicy::default().with_enabled(false))
                    .configure(|c| {
                        c.extractor.exposure = mode;
                        c.tracker.max_missed = 0;
                    })
                    .build()?;
                sensor.set_reference(&reference)?;
                runs.push((
                    mode,
                    ex,
                    sensor,
                    0usize,
                    (0usize, 0usize),
                    0.0f64,
                    Vec::new(),
                    0.0f64,
                ));
            }
            for k in 1..=cli.frames {
                let frame = sim.render_indexed(k as u64, &[], false)?.frame;
                for (_, ex, sensor, patches, contacts, gain, quiets, busy) in runs.iter_mut() {
                    let t = Instant::now();
                    let n = ex.extract(&frame)?.len();
                    *busy += t.elapsed().as_secs_f64();
                    *patches += usize::from(n > 0);
                    *gain = gain.max((ex.exposure().0 - 1.0).abs());
                    let (flow, scale) = ex.flow();
                    quiets.push(
                        cli.tiles
                            .0
                            .iter()
                            .map(|&t| quiet(flow, scale, &reference, t as usize))
                            .collect::<Vec<f64>>(),
                    );
                    let c = sensor.process(&frame, k as f64 * 0.02)?;
                    contacts.0 += usize::from(!c.is_empty());
                    // Contacts not marked out of the calibration's domain.
                    contacts.1 += usize::from(c.iter().any(|c| !c.out_of_domain));
                }
            }
            // Light presses: the smallest quiet statistic over positions,
            // with the last compensation given.
            let Some((_, ex, ..)) = runs.last_mut() else {
                return Err(Failure::Message(
                    "--modes: give at least one compensation".into(),
                ));
            };
            let mut press_stats = Vec::new();
            for &f in &cli.press_forces.0 {
                let mut worst = vec![f64::INFINITY; cli.tiles.0.len()];
                for (i, x) in [-80.0, 0.0, 80.0].into_iter().enumerate() {
                    let press = Press::rod(x, [0.0, 0.0, -f], 5.0);
                    let frame = sim.render_indexed(5000 + i as u64, &[press], false)?.frame;
                    ex.extract(&frame)?;
                    let (flow, scale) = ex.flow();
                    for (t, w) in cli.tiles.0.iter().zip(worst.iter_mut()) {
                        *w = w.min(quiet(flow, scale, &reference, *t as usize));
                    }
                }
                let w: Vec<String> = worst.iter().map(|v| format!("{v:.3}")).collect();
                press_stats.push(format!("{f} N: {}", w.join(" / ")));
            }
            writeln!(
                out,
                "| {seed} | {read} | quiet statistic of the lightest of 3 presses (5 mm rod), tiles {} px: {} |",
                cli.tiles,
                press_stats.join("; ")
            )?;
            for (mode, _, _, patches, contacts, gain, quiets, busy) in &runs {
                let stats: Vec<String> = (0..cli.tiles.0.len())
                    .map(|t| {
                        let mut v: Vec<f64> = quiets.iter().map(|q| q[t]).collect();
                        format!(
                            "{:.3} / {:.3} / {:.3}",
                            quantile(&mut v, 0.5),
                            quantile(&mut v, 0.99),
                            quantile(&mut v, 1.0)
                        )
                    })
                    .collect();
                writeln!(
                    out,
                    "| {seed} | {read} | {} | {patches} / {} | {} / {}, {} | {gain:.4} | {} | {:.2} |",
                    mode.name(),
                    cli.frames,
                    contacts.0,
                    cli.frames,
                    contacts.1,
                    stats.join("; "),
                    1e3 * busy / cli.frames as f64
                )?;
            }
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    cli_support::finish(run(&Cli::parse()).map(|()| ExitCode::SUCCESS))
}
