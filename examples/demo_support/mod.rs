//! What the three demo examples (`multi_contact`, `perch_selection`,
//! `touch_mapping`) share: the command line, running the sensor over a
//! sequence, reading truth, writing JSON and plots. Included with `#[path]`
//! by each example and by `tests/demos.rs`, so each uses only part of it.
//! It uses the tools' shared `cli_support`, which the including file
//! declares beside it.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Args;
use optical_tactile::calibration::Calibration;
use optical_tactile::capture::{FrameSource, SequenceSource};
use optical_tactile::frame::Roi;
use optical_tactile::io::{self, FrameRecord};
use optical_tactile::sensor::TactileSensor;
use optical_tactile::viz::{Canvas, Plot, Rgb, Series, Style};
use optical_tactile_sim::scenario::{self, Common, Scenario};

use super::cli_support::{self, Failure, Stages, TextOut};

/// The calibration used unless `--calibration` names another: this crate's.
pub const DEFAULT_CALIBRATION: &str =
    concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/calibration.json");

/// The options every demo takes.
#[derive(Args, Debug, Clone, PartialEq)]
pub struct DemoArgs {
    /// A recorded sequence: a folder of frames (docs/formats.md) [default:
    /// simulate the demo's scenario first].
    #[arg(value_name = "SEQ_DIR", conflicts_with = "simulate")]
    pub input: Option<PathBuf>,
    /// Simulate the demo's scenario into DIR first [default: a folder under
    /// the system's temp dir named after the demo].
    #[arg(long, value_name = "DIR")]
    pub simulate: Option<PathBuf>,
    /// Calibration file.
    #[arg(long, value_name = "FILE", default_value = DEFAULT_CALIBRATION)]
    pub calibration: PathBuf,
    /// Crop of the camera frame [default: the calibration's].
    #[arg(long, value_name = "x,y,w,h", value_parser = cli_support::roi)]
    pub crop: Option<Roi>,
    /// Ground truth file [default: the one beside the frames, if any].
    #[arg(long, value_name = "FILE")]
    pub truth: Option<PathBuf>,
    /// Write the result as JSON to FILE, or to stdout with `-` (the tables
    /// then go to stderr).
    #[arg(long, value_name = "FILE|-")]
    pub json: Option<TextOut>,
    /// Write the picture (PNG) to FILE.
    #[arg(long, value_name = "FILE", value_parser = cli_support::binary_path)]
    pub png: Option<PathBuf>,
    /// Simulator seed.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub seed: u64,
    /// No progress bar while simulating.
    #[arg(long, short)]
    pub quiet: bool,
}

impl DemoArgs {
    /// Where the printed tables go: stdout, or stderr when the JSON does.
    pub fn report(&self) -> cli_support::Sink {
        cli_support::Sink::report(self.json.as_ref().is_some_and(TextOut::is_stdout))
    }
}

/// The sequence to run: the given folder, or a scenario simulated into
/// `--simulate DIR` (default: a folder under the system's temp dir named
/// after the demo). Returns the folder and whether it was simulated.
pub fn resolve_input(
    a: &DemoArgs,
    demo: &str,
    scenario: &Scenario,
) -> Result<(PathBuf, bool), String> {
    // Check the calibration before any long work (simulation, reading).
    if !a.calibration.is_file() {
        load_calibration(&a.calibration)?;
    }
    if let Some(dir) = &a.input {
        if !dir.is_dir() {
            return Err(format!(
                "sequence folder {} not found (or not a folder)",
                dir.display()
            ));
        }
        return Ok((dir.clone(), false));
    }
    let dir = a
        .simulate
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join(format!("optical-tactile-{demo}")));
    simulate(scenario, &dir, a.seed, a.quiet)?;
    Ok((dir, true))
}

/// Simulates `scenario` into `dir` (no true flow: not needed, and large),
/// with a progress bar on a terminal unless `quiet`.
pub fn simulate(scenario: &Scenario, dir: &Path, seed: u64, quiet: bool) -> Result<(), String> {
    let mut common = Common::new(dir);
    common.seed = seed;
    common.flow = false;
    eprintln!("simulating into {} (seed {seed}) ...", dir.display());
    let stages = Stages::new(quiet);
    let s = scenario::run_with_progress(scenario, &common, &|stage, done, total| {
        stages.update(stage, done, total)
    });
    stages.finish();
    let s = s.map_err(|e| format!("simulation failed: {e}"))?;
    eprintln!("  {} frames", s.frames);
    Ok(())
}

/// Loads the calibration with a clear message when it is missing.
pub fn load_calibration(path: &Path) -> Result<Calibration, String> {
    if !path.exists() {
        return Err(format!(
            "calibration file {} not found: pass --calibration FILE (fit one with the \
             `calibrate` example)",
            path.display()
        ));
    }
    Calibration::load(path).map_err(|e| format!("cannot load calibration {}: {e}", path.display()))
}

/// The contacts of every frame of a sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorRun {
    /// One record per frame, in order, the reference (first readable frame)
    /// included with no contacts. Only live contacts are kept: a contact the
    /// tracker holds through a missed detection repeats an old measurement.
    pub frames: Vec<FrameRecord>,
    /// Frames that could not be read or processed (named on stderr).
    pub skipped: usize,
}

/// Runs the tactile sensor over the sequence in `dir` with the calibration
/// (its recorded pipeline settings and thresholds) and an optional crop.
pub fn run_sensor(dir: &Path, calibration: &Path, crop: Option<Roi>) -> Result<SensorRun, String> {
    let cal = load_calibration(calibration)?;
    let mut builder = TactileSensor::builder(cal);
    if let Some(crop) = crop {
        builder = builder.crop(crop);
    }
    let mut seq = SequenceSource::open(dir)
        .map_err(|e| format!("cannot open sequence {}: {e}", dir.display()))?;
    if seq.len() < 2 {
        return Err(format!(
            "sequence {} has {} frame(s): need a reference and at least one more",
            dir.display(),
            seq.len()
        ));
    }
    let mut sensor = builder.build().map_err(|e| e.to_string())?;
    let mut out = SensorRun {
        frames: Vec::new(),
        skipped: 0,
    };
    let mut have_reference = false;
    while let Some(frame) = seq.next_frame() {
        let frame = match frame {
            Ok(f) => f,
            Err(e) => {
                eprintln!("skipping unreadable frame: {e}");
                out.skipped += 1;
                continue;
            }
        };
        if !have_reference {
            sensor
                .set_reference(&frame.image)
                .map_err(|e| format!("frame {}: cannot be the reference: {e}", frame.name))?;
            have_reference = true;
            out.frames.push(FrameRecord {
                frame: frame.name,
                t_s: frame.t_s,
                contacts: vec![],
                latency_ms: None,
            });
            continue;
        }
        match sensor.process(&frame.image, frame.t_s) {
            Ok(cs) => out.frames.push(FrameRecord {
                frame: frame.name,
                t_s: frame.t_s,
                contacts: cs
                    .iter()
                    .filter(|c| c.missed == 0)
                    .map(|c| c.to_record())
                    .collect(),
                latency_ms: None,
            }),
            Err(e) => {
                eprintln!("skipping frame {}: {e}", frame.name);
                out.skipped += 1;
            }
        }
    }
    if !have_reference {
        return Err(format!("no readable frame in {}", dir.display()));
    }
    Ok(out)
}

/// Reads a `truth.jsonl` with a clear message.
pub fn read_truth(path: &Path) -> Result<Vec<FrameRecord>, String> {
    if !path.exists() {
        return Err(format!("truth file {} not found", path.display()));
    }
    io::read_jsonl(path).map_err(|e| format!("cannot read truth: {e}"))
}

/// Writes a picture as PNG and says so on stderr.
pub fn save_png(picture: &Canvas, path: &Path) -> Result<(), String> {
    picture.save_png(path).map_err(|e| e.to_string())?;
    eprintln!("wrote {}", path.display());
    Ok(())
}

/// The exit status every demo documents: 0 when all frames were read, 2
/// when some were skipped (each named on stderr), 1 on an error (one line
/// on stderr), 0 when stdout was closed early.
pub fn exit_status(outcome: Result<bool, Failure>) -> ExitCode {
    cli_support::finish(outcome.map(|all| {
        if all {
            ExitCode::SUCCESS
        } else {
            ExitCode::from(2)
        }
    }))
}

/// Colours for contacts 0, 1, 2, ...
pub const PALETTE: [Rgb; 6] = [
    Rgb(30, 100, 220),
    Rgb(220, 70, 30),
    Rgb(40, 160, 60),
    Rgb(150, 60, 190),
    Rgb(200, 150, 0),
    Rgb(0, 160, 170),
];

/// A measured series (dots) and, when given, its truth (dashed line).
pub fn measured_and_truth(
    label: &str,
    color: Rgb,
    measured: Vec<(f64, f64)>,
    truth: Option<Vec<(f64, f64)>>,
) -> Vec<Series> {
    let mut v = vec![Series {
        label: label.to_string(),
        points: measured,
        color,
        style: Style::Dots(3.0),
    }];
    if let Some(t) = truth {
        v.push(Series {
            label: format!("{label} TRUE"),
            points: t,
            color,
            style: Style::Dashed,
        });
    }
    v
}

/// Stacks canvases top to bottom (white background, 6 px gaps).
pub fn stack(panels: &[Canvas]) -> Canvas {
    let w = panels.iter().map(|c| c.width()).max().unwrap_or(1);
    let h = panels.iter().map(|c| c.height() + 6).sum::<usize>().max(1);
    let mut out = Canvas::new(w, h, Rgb::WHITE);
    let mut y = 0;
    for p in panels {
        out.blit(p, 0, y as i64);
        y += p.height() + 6;
    }
    out
}

/// Places canvases left to right (white background, 6 px gaps).
pub fn row(panels: &[Canvas]) -> Canvas {
    let h = panels.iter().map(|c| c.height()).max().unwrap_or(1);
    let w = panels.iter().map(|c| c.width() + 6).sum::<usize>().max(1);
    let mut out = Canvas::new(w, h, Rgb::WHITE);
    let mut x = 0;
    for p in panels {
        out.blit(p, x as i64, 0);
        x += p.width() + 6;
    }
    out
}

/// A plot over time with the given series.
pub fn time_plot(title: &str, y_label: &str, series: Vec<Series>) -> Plot {
    Plot {
        title: title.to_string(),
        x_label: "T S".into(),
        y_label: y_label.to_string(),
        series,
        ..Plot::default()
    }
}

/// The force magnitude of a record, N.
pub fn force_magnitude(c: &io::ContactRecord) -> f64 {
    (c.fx_n * c.fx_n + c.fy_n * c.fy_n + c.fz_n * c.fz_n).sqrt()
}

/// Mean of a slice (NaN when empty).
pub fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

/// The values of every tracked contact over time: `(id, [(t_s, value)])`,
/// ids in order of first appearance.
pub fn id_series(
    frames: &[FrameRecord],
    value: impl Fn(&io::ContactRecord) -> f64,
) -> Vec<(u64, Vec<(f64, f64)>)> {
    let mut out: Vec<(u64, Vec<(f64, f64)>)> = Vec::new();
    for f in frames {
        for c in &f.contacts {
            let Some(id) = c.id else { continue };
            let p = (f.t_s, value(c));
            match out.iter_mut().find(|(i, _)| *i == id) {
                Some((_, v)) => v.push(p),
                None => out.push((id, vec![p])),
            }
        }
    }
    out
}

/// The values of the `j`-th true contact of every truth frame over time.
pub fn truth_series(
    truth: &[FrameRecord],
    j: usize,
    value: impl Fn(&io::ContactRecord) -> f64,
) -> Vec<(f64, f64)> {
    truth
        .iter()
        .filter_map(|f| f.contacts.get(j).map(|c| (f.t_s, value(c))))
        .collect()
}
