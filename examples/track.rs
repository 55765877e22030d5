//! Runs the tactile sensor over an image sequence: contacts per frame.
//!
//! ```text
//! cargo run --release --example track -- [SEQ_DIR] [--calibration FILE] [--crop x,y,w,h]
//!     [--thresholds low|mid|high] [--preset fast|accurate|...] [--filter on|off]
//!     [--rereference on|off] [--hold N] [--out contacts.jsonl] [--debug DIR]
//! ```
//!
//! With no arguments it runs on `fixtures/press` with
//! `fixtures/calibration.json`. The first readable frame is the reference
//! (unloaded); every later frame is processed and printed as a table of its
//! contacts (id, location in mm, force in N, latency), then the frame rate.
//!
//! The flow preset, patch margin and sub-pixel switch come from the
//! calibration's `setup.pipeline` when it records them, the segmentation
//! thresholds from its `setup.thresholds`: the sensor then measures the raw
//! quantities exactly as the calibration was fitted. `--preset` and
//! `--thresholds` override them (the calibration's accuracy no longer holds).
//!
//! `--hold N` is how many frames a contact that is no longer detected is
//! still reported with its last estimate (default 2; 0 for sequences whose
//! frames are independent presses, such as `simulate presses`).
//!
//! `--out` writes JSON Lines per DATASET.md (one line per processed frame,
//! with `latency_ms`), flushed line by line. `--debug DIR` writes the debug
//! panel (flow, divergent field, potential, image) of every frame as
//! `DIR/<frame>.png`.
//!
//! Errors: a missing calibration or sequence stops the run before anything is
//! written. An unreadable frame, or one that cannot be processed (another size
//! than the reference, NaN), is named on stderr and skipped: the run goes on,
//! and the exit status is 2 at the end if any frame was skipped.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use optical_tactile::calibration::Calibration;
use optical_tactile::calibration::fit::preset_name;
use optical_tactile::capture::{FrameSource, SequenceSource};
use optical_tactile::flow::dis::{DisParams, DisPreset};
use optical_tactile::frame::Roi;
use optical_tactile::io::{FrameRecord, JsonlWriter};
use optical_tactile::segment::{ThresholdPreset, Thresholds};
use optical_tactile::sensor::{ExtractorConfig, SensorConfig, TactileSensor};
use optical_tactile::track::{FilterConfig, ReferencePolicy};
use optical_tactile::viz;

const USAGE: &str = "usage: track [SEQ_DIR (default fixtures/press)] [--calibration FILE (default fixtures/calibration.json)] \
[--crop x,y,w,h] [--thresholds low|mid|high] [--preset ultrafast|fast|medium|accurate|balanced|fine] \
[--filter on|off (default off)] [--rereference on|off (default on)] [--hold N (default 2)] [--out contacts.jsonl] [--debug DIR] [--quiet]";

struct Args {
    seq: PathBuf,
    calibration: PathBuf,
    crop: Option<Roi>,
    thresholds: Option<Thresholds>,
    preset: Option<DisPreset>,
    filter: bool,
    rereference: bool,
    hold: Option<u32>,
    out: Option<PathBuf>,
    debug: Option<PathBuf>,
    quiet: bool,
}

fn on_off(name: &str, v: &str) -> Result<bool, String> {
    match v {
        "on" | "true" | "1" => Ok(true),
        "off" | "false" | "0" => Ok(false),
        _ => Err(format!("{name}: expected on or off, got `{v}`")),
    }
}

fn parse() -> Result<Option<Args>, String> {
    let mut a = Args {
        seq: PathBuf::from("fixtures/press"),
        calibration: PathBuf::from("fixtures/calibration.json"),
        crop: None,
        thresholds: None,
        preset: None,
        filter: false,
        rereference: true,
        hold: None,
        out: None,
        debug: None,
        quiet: false,
    };
    let mut seq = None;
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut val = |name: &str| args.next().ok_or(format!("{name} needs a value\n{USAGE}"));
        match arg.as_str() {
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(None);
            }
            "--calibration" => a.calibration = PathBuf::from(val("--calibration")?),
            "--crop" => a.crop = Some(Roi::parse(&val("--crop")?).map_err(|e| e.to_string())?),
            "--thresholds" => {
                a.thresholds = Some(
                    val("--thresholds")?
                        .parse::<ThresholdPreset>()
                        .map_err(|e| e.to_string())?
                        .thresholds(),
                )
            }
            "--preset" => {
                a.preset = Some(DisPreset::parse(&val("--preset")?).map_err(|e| e.to_string())?)
            }
            "--filter" => a.filter = on_off("--filter", &val("--filter")?)?,
            "--rereference" => a.rereference = on_off("--rereference", &val("--rereference")?)?,
            "--hold" => {
                let v = val("--hold")?;
                a.hold = Some(
                    v.parse()
                        .map_err(|_| format!("--hold: expected a number of frames, got `{v}`"))?,
                )
            }
            "--out" => a.out = Some(PathBuf::from(val("--out")?)),
            "--debug" => a.debug = Some(PathBuf::from(val("--debug")?)),
            "--quiet" => a.quiet = true,
            _ if arg.starts_with("--") => return Err(format!("unknown option {arg}\n{USAGE}")),
            _ if seq.is_none() => seq = Some(PathBuf::from(arg)),
            _ => return Err(format!("unexpected argument `{arg}`\n{USAGE}")),
        }
    }
    if let Some(s) = seq {
        a.seq = s;
    }
    Ok(Some(a))
}

fn load_calibration(path: &Path) -> Result<Calibration, String> {
    if !path.is_file() {
        return Err(format!(
            "calibration file {} not found: fit one with `cargo run --release --example calibrate -- \
             DATASET_DIR --out {}` (see the README), or pass --calibration FILE",
            path.display(),
            path.display()
        ));
    }
    Calibration::load(path).map_err(|e| format!("cannot load calibration: {e}"))
}

fn sensor_config(a: &Args, cal: &Calibration) -> Result<SensorConfig, String> {
    let mut extractor = ExtractorConfig::from_setup(&cal.setup).map_err(|e| e.to_string())?;
    if let Some(p) = a.preset {
        extractor.flow = DisParams::preset(p);
    }
    if let Some(t) = a.thresholds {
        extractor.thresholds = t;
    }
    let mut config = SensorConfig {
        crop: a.crop,
        extractor,
        ..SensorConfig::default()
    };
    config.tracker.filter = a.filter.then(FilterConfig::default);
    if let Some(h) = a.hold {
        config.tracker.max_missed = h;
    }
    config.rereference = ReferencePolicy {
        enabled: a.rereference,
        ..ReferencePolicy::default()
    };
    Ok(config)
}

fn run() -> Result<bool, String> {
    let Some(a) = parse()? else {
        return Ok(true);
    };
    let cal = load_calibration(&a.calibration)?;
    let config = sensor_config(&a, &cal)?;
    let mut seq = SequenceSource::open(&a.seq).map_err(|e| format!("cannot open sequence: {e}"))?;
    let mut sensor = TactileSensor::new(config, cal).map_err(|e| e.to_string())?;
    let mut out = match &a.out {
        Some(p) => Some(JsonlWriter::create(p).map_err(|e| e.to_string())?),
        None => None,
    };
    if let Some(d) = &a.debug {
        std::fs::create_dir_all(d)
            .map_err(|e| format!("cannot create debug directory {}: {e}", d.display()))?;
    }
    let c = sensor.config();
    eprintln!(
        "sequence {} ({} frames), calibration {}, crop {:?}, flow preset {}, thresholds |flow| > {} px sum > {}, \
         filter {}, re-referencing {}",
        a.seq.display(),
        seq.len(),
        a.calibration.display(),
        sensor.crop(),
        preset_name(&c.extractor),
        c.extractor.thresholds.magnitude,
        c.extractor.thresholds.sum,
        if a.filter { "on" } else { "off" },
        if a.rereference { "on" } else { "off" },
    );

    let mut skipped = 0usize;
    let mut have_reference = false;
    let (mut processed, mut busy_ms) = (0usize, 0.0f64);
    let wall = Instant::now();
    if !a.quiet {
        println!(
            "{:<14} {:>7} {:>4} {:>8} {:>8} {:>8} {:>7} {:>7} {:>7} {:>8}",
            "frame", "t_s", "id", "x_mm", "y_mm", "z_mm", "fx_n", "fy_n", "fz_n", "ms"
        );
    }
    while let Some(frame) = seq.next_frame() {
        let frame = match frame {
            Ok(f) => f,
            Err(e) => {
                eprintln!("skipping unreadable frame: {e}");
                skipped += 1;
                continue;
            }
        };
        if !have_reference {
            match sensor.set_reference(&frame.image) {
                Ok(()) => {
                    have_reference = true;
                    if !a.quiet {
                        println!("{:<14} {:>7.3} reference", frame.name, frame.t_s);
                    }
                }
                Err(e) => {
                    return Err(format!(
                        "frame {}: cannot take it as the reference: {e}",
                        frame.name
                    ));
                }
            }
            continue;
        }
        let t = Instant::now();
        let contacts = match sensor.process(&frame.image, frame.t_s) {
            Ok(c) => c.to_vec(),
            Err(e) => {
                eprintln!("skipping frame {}: {e}", frame.name);
                skipped += 1;
                continue;
            }
        };
        let latency_ms = t.elapsed().as_secs_f64() * 1e3;
        processed += 1;
        busy_ms += latency_ms;
        if !a.quiet {
            if contacts.is_empty() {
                println!(
                    "{:<14} {:>7.3} {:>4} {:>60.1}",
                    frame.name, frame.t_s, "-", latency_ms
                );
            }
            for (k, c) in contacts.iter().enumerate() {
                let name = if k == 0 { frame.name.as_str() } else { "" };
                let [x, y, z] = c.location_mm;
                let [fx, fy, fz] = c.force_n;
                println!(
                    "{name:<14} {:>7.3} {:>4} {x:>8.2} {y:>8.2} {z:>8.2} {fx:>7.3} {fy:>7.3} {fz:>7.3} {:>8.1}{}",
                    frame.t_s,
                    c.id,
                    latency_ms,
                    if c.missed > 0 { " (held)" } else { "" }
                );
            }
            if sensor.rereferenced() {
                println!(
                    "{:<14} {:>7.3} new reference (quiet, small flow)",
                    "", frame.t_s
                );
            }
        }
        if let Some(w) = &mut out {
            let rec = FrameRecord {
                frame: frame.name.clone(),
                t_s: frame.t_s,
                contacts: contacts.iter().map(|c| c.to_record()).collect(),
                latency_ms: Some(latency_ms),
            };
            w.write(&rec).map_err(|e| e.to_string())?;
        }
        if let Some(d) = &a.debug {
            let stem = Path::new(&frame.name)
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| format!("{:06}", frame.index));
            let path = d.join(format!("{stem}.png"));
            viz::debug_panel(&sensor)
                .save_png(&path)
                .map_err(|e| e.to_string())?;
        }
    }
    if !have_reference {
        return Err(format!("no readable frame in {}", a.seq.display()));
    }
    let wall_s = wall.elapsed().as_secs_f64();
    if processed > 0 {
        println!(
            "{processed} frames processed ({skipped} skipped), {:.1} ms per frame in process(): {:.1} fps \
             ({:.1} fps with reading{})",
            busy_ms / processed as f64,
            1e3 * processed as f64 / busy_ms,
            processed as f64 / wall_s,
            if a.debug.is_some() {
                " and debug panels"
            } else {
                ""
            }
        );
    } else {
        println!("no frame processed ({skipped} skipped)");
    }
    Ok(skipped == 0)
}

fn main() -> ExitCode {
    match run() {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(2),
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
