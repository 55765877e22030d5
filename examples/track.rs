//! Runs the tactile sensor over an image sequence: contacts per frame.
//!
//! ```text
//! cargo run --release --example track -- [SEQ_DIR] [--calibration FILE | --raw] [--crop x,y,w,h]
//!     [--force-crop] [--channel green|luma] [--thresholds low|mid|high] [--preset fast|accurate|...]
//!     [--magnitude PX] [--sum SUM] [--erode PX] [--dilate PX] [--split on|off]
//!     [--filter on|off] [--rereference on|off] [--hold N] [--out contacts.jsonl|-] [--debug DIR] [--quiet]
//!     [--timings]
//! ```
//!
//! With no arguments it runs on this crate's `fixtures/press` with
//! `fixtures/calibration.json` (found from any working directory). The first
//! readable frame is the reference (unloaded); every later frame is processed
//! and printed as a table of its contacts (id, location in mm, force in N,
//! latency), then the frame rate.
//!
//! The flow preset, patch margin and sub-pixel switch come from the
//! calibration's `setup.pipeline` when it records them, the segmentation
//! thresholds from its `setup.thresholds`: the sensor then measures the raw
//! quantities exactly as the calibration was fitted. `--preset` and
//! `--thresholds` override them (the calibration's accuracy no longer holds),
//! and `--magnitude`, `--sum`, `--erode` and `--dilate` override one value
//! each (the `tune` example prints the flags of the thresholds tuned on its
//! page). `--split off` keeps a patch holding several contacts side by side
//! whole.
//!
//! `--raw` needs no calibration: the crop defaults to the whole frame, the
//! flow and thresholds to the library's defaults (or `--preset`,
//! `--thresholds`), and every frame's patches are printed and written with
//! their contact point and box in pixels, strength, shear and normal raw
//! displacements (`ds1`, `ds2`, `dn`) and `d_pf`, in the same per-frame
//! JSON Lines layout as calibrated contacts (docs/formats.md). With
//! `--dot-tracking on` on a sensor with a regular grid of dots, the
//! contact point is where the dots' motion lines meet, in both axes, and
//! with `--dot-fit on` (the default) the centre of the round load's field
//! fitted to the dots, whose shear and squeeze give `ds1`, `ds2`, `dn`.
//!
//! A contact whose force came from the calibration's fallback maps is marked
//! `(fallback)`, one outside what the calibration was fitted on
//! `(out of domain)`; both marks are written to the JSON Lines. A `--crop`
//! other than the calibration's is refused unless `--force-crop`.
//!
//! `--hold N` is how many frames a contact that is no longer detected is
//! still reported with its last estimate (default 2; 0 for sequences whose
//! frames are independent presses, such as `simulate presses`).
//!
//! `--out` writes JSON Lines per docs/formats.md (one line per processed frame,
//! with `latency_ms`), flushed line by line; `--out -` writes them to stdout
//! and the table to stderr. `--debug DIR` writes the debug panel (flow,
//! divergent field, potential, image) of every frame as `DIR/<frame>.png`.
//! A closed stdout (`track | head`) ends the run quietly.
//!
//! `--timings` ends the run with the time per stage (reading the PNG,
//! crop, flow, segmentation, nHHD, calibration, tracking, the whole
//! `process` call and the frame with reading): median, 90th percentile and
//! largest over the processed frames, and the slowest frame's stages and
//! patches (`StageTimings`, docs/results.md#latency-budget).
//!
//! Errors: a missing calibration or sequence stops the run before anything is
//! written. An unreadable frame, or one that cannot be processed (another size
//! than the reference, NaN), is named on stderr and skipped: the run goes on,
//! and the exit status is 2 at the end if any frame was skipped.

#[path = "cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{ArgAction, Parser};
use cli_support::pipeline::{
    Found, Pipeline, PipelineArgs, contact_header, contact_row, patch_header, patch_row,
};
use cli_support::{Failure, Sink, TextOut};
use optical_tactile::calibration::fit::preset_name;
use optical_tactile::capture::{FrameSource, SequenceSource};
use optical_tactile::sensor::StageTimings;
use optical_tactile::track::FilterConfig;

/// The sequence run with no argument: this crate's fixture.
const DEFAULT_SEQ: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/press");

/// Runs the tactile sensor over an image sequence and prints the contacts
/// of every frame (id, location in mm, force in N, latency).
#[derive(Parser, Debug)]
#[command(
    name = "track",
    after_help = "The first readable frame is the unloaded reference. Exit status: 0, 1 on an \
                  error, 2 if some frame was skipped (named on stderr) or on a usage error."
)]
struct Cli {
    /// Folder of frames (PNG, in name order).
    #[arg(value_name = "SEQ_DIR", default_value = DEFAULT_SEQ)]
    seq: PathBuf,
    #[command(flatten)]
    pipeline: PipelineArgs,
    /// Kalman filter on the tracked contacts.
    #[arg(long, value_name = "on|off", default_value = "off", action = ArgAction::Set, value_parser = cli_support::on_off)]
    filter: bool,
    /// Take a fresh reference after a quiet spell with small flow.
    #[arg(long, value_name = "on|off", default_value = "on", action = ArgAction::Set, value_parser = cli_support::on_off)]
    rereference: bool,
    /// Frames a contact no longer detected is still reported with its last
    /// estimate [default: 2, the tracker's].
    #[arg(long, value_name = "N")]
    hold: Option<u32>,
    /// Write JSON Lines (one line per processed frame) to FILE, or to stdout
    /// with `-` (the table then goes to stderr).
    #[arg(long, value_name = "FILE|-")]
    out: Option<TextOut>,
    /// Write every frame's debug panel as DIR/<frame>.png.
    #[arg(long, value_name = "DIR")]
    debug: Option<PathBuf>,
    /// No per-frame table.
    #[arg(long, short)]
    quiet: bool,
    /// At the end, the time per stage over the processed frames (median,
    /// 90th percentile, largest) and the slowest frame's stages.
    #[arg(long)]
    timings: bool,
}

/// One processed frame's times, ms, and its patches.
struct FrameTimes {
    name: String,
    read_ms: f64,
    stages: StageTimings,
    process_ms: f64,
    /// Patches and the largest one's cells on the analysis grid.
    patches: usize,
    largest: (usize, usize),
}

impl FrameTimes {
    /// The columns of the table: name and time, ms.
    fn columns(&self) -> [(&'static str, f64); 9] {
        let s = &self.stages;
        [
            ("read", self.read_ms),
            ("crop", s.crop_ms),
            ("flow", s.flow_ms),
            ("segment", s.segment_ms),
            ("nhhd", s.hhd_ms),
            ("calibrate", s.contacts_ms),
            ("track", s.tracking_ms),
            ("process", self.process_ms),
            ("frame", self.read_ms + self.process_ms),
        ]
    }
}

/// The `q`-quantile (nearest rank) of `v`, which it sorts.
fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// The `--timings` table: per stage, median / p90 / max; then the slowest
/// frame (by the whole frame, reading included).
fn timings_table(times: &[FrameTimes], report: &mut Sink) -> Result<(), Failure> {
    if times.is_empty() {
        return Ok(());
    }
    let names = times[0].columns().map(|(n, _)| n);
    let mut line = format!("{:<10}", "ms");
    for n in names {
        line += &format!(" {n:>9}");
    }
    writeln!(report, "{line}")?;
    for (label, q) in [("median", 0.5), ("p90", 0.9), ("max", 1.0)] {
        let mut line = format!("{label:<10}");
        for k in 0..names.len() {
            let mut v: Vec<f64> = times.iter().map(|t| t.columns()[k].1).collect();
            line += &format!(" {:>9.2}", quantile(&mut v, q));
        }
        writeln!(report, "{line}")?;
    }
    let worst = times
        .iter()
        .max_by(|a, b| a.columns()[8].1.total_cmp(&b.columns()[8].1))
        .expect("not empty");
    let mut line = format!("{:<10}", "slowest");
    for (_, v) in worst.columns() {
        line += &format!(" {v:>9.2}");
    }
    writeln!(report, "{line}")?;
    writeln!(
        report,
        "slowest frame: {}, {} patches, the largest {}x{} cells on the analysis grid",
        worst.name, worst.patches, worst.largest.1, worst.largest.0
    )?;
    Ok(())
}

/// Runs the sensor as `a` asks; `Ok(false)` if some frame was skipped.
fn run(a: &Cli) -> Result<bool, Failure> {
    let mut seq = SequenceSource::open(&a.seq)
        .map_err(|e| format!("cannot open sequence: {e}"))?
        .with_channel(a.pipeline.channel);
    let mut sensor = a.pipeline.build(|c| {
        c.tracker.filter = a.filter.then(FilterConfig::default);
        if let Some(h) = a.hold {
            c.tracker.max_missed = h;
        }
        c.rereference.enabled = a.rereference;
    })?;
    let mut out = a.out.as_ref().map(TextOut::create).transpose()?;
    let mut report = Sink::report(a.out.as_ref().is_some_and(TextOut::is_stdout));
    if let Some(d) = &a.debug {
        std::fs::create_dir_all(d)
            .map_err(|e| format!("cannot create debug directory {}: {e}", d.display()))?;
    }
    match &sensor {
        Pipeline::Calibrated(s) => {
            let (c, crop) = (s.config(), s.crop());
            eprintln!(
                "sequence {} ({} frames), calibration {}, crop {}, flow preset {}, thresholds |flow| > {} px sum > {}, \
                 filter {}, re-referencing {}",
                a.seq.display(),
                seq.len(),
                a.pipeline.calibration.display(),
                crop.to_arg(),
                preset_name(&c.extractor),
                c.extractor.thresholds.magnitude,
                c.extractor.thresholds.sum,
                if a.filter { "on" } else { "off" },
                if a.rereference { "on" } else { "off" },
            );
        }
        Pipeline::Raw(r) => {
            let c = r.sensor.extractor().config();
            eprintln!(
                "sequence {} ({} frames), raw (no calibration), crop {}, flow preset {}, thresholds |flow| > {} px sum > {}",
                a.seq.display(),
                seq.len(),
                r.crop()
                    .map_or_else(|| "whole frame".to_string(), |c| c.to_arg()),
                preset_name(c),
                c.thresholds.magnitude,
                c.thresholds.sum,
            );
        }
    }

    let mut skipped = 0usize;
    let mut have_reference = false;
    let (mut processed, mut busy_ms) = (0usize, 0.0f64);
    let wall = Instant::now();
    let mut times: Vec<FrameTimes> = Vec::new();
    if !a.quiet {
        let header = if a.pipeline.raw {
            patch_header()
        } else {
            contact_header()
        };
        writeln!(report, "{header}")?;
    }
    loop {
        let t_read = Instant::now();
        let Some(frame) = seq.next_frame() else {
            break;
        };
        let read_ms = t_read.elapsed().as_secs_f64() * 1e3;
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
                    eprintln!("{}", markers_note(sensor.extractor()));
                    if !a.quiet {
                        writeln!(report, "{:<14} {:>7.3} reference", frame.name, frame.t_s)?;
                    }
                }
                Err(e) => {
                    return Err(format!(
                        "frame {}: cannot take it as the reference: {e}",
                        frame.name
                    )
                    .into());
                }
            }
            continue;
        }
        let t = Instant::now();
        let found = match sensor.process(&frame.image, frame.t_s) {
            Ok(f) => f,
            Err(e) => {
                eprintln!("skipping frame {}: {e}", frame.name);
                skipped += 1;
                continue;
            }
        };
        let latency_ms = t.elapsed().as_secs_f64() * 1e3;
        processed += 1;
        if a.timings {
            let patches = sensor.extractor().patches();
            times.push(FrameTimes {
                name: frame.name.clone(),
                read_ms,
                stages: sensor.timings(),
                process_ms: latency_ms,
                patches: patches.len(),
                largest: patches
                    .iter()
                    .map(|p| (p.bbox.height, p.bbox.width))
                    .max_by_key(|&(h, w)| h * w)
                    .unwrap_or((0, 0)),
            });
        }
        busy_ms += latency_ms;
        let empty = match &found {
            Found::Contacts(c) => c.is_empty(),
            Found::Patches(p) => p.is_empty(),
        };
        if !a.quiet {
            if empty {
                writeln!(
                    report,
                    "{:<14} {:>7.3} {:>4} {:>60.1}",
                    frame.name, frame.t_s, "-", latency_ms
                )?;
            }
            let name = |k: usize| if k == 0 { frame.name.as_str() } else { "" };
            match &found {
                Found::Contacts(contacts) => {
                    for (k, c) in contacts.iter().enumerate() {
                        writeln!(report, "{}", contact_row(name(k), frame.t_s, c, latency_ms))?;
                    }
                }
                Found::Patches(patches) => {
                    for (k, r) in patches.iter().enumerate() {
                        writeln!(
                            report,
                            "{}",
                            patch_row(name(k), frame.t_s, k, r, latency_ms)
                        )?;
                    }
                }
            }
            if sensor.rereferenced() {
                writeln!(
                    report,
                    "{:<14} {:>7.3} new reference (quiet, small flow)",
                    "", frame.t_s
                )?;
            }
        }
        if let Some(w) = &mut out {
            found.json_line(w, &frame.name, frame.t_s, latency_ms)?;
        }
        if let Some(d) = &a.debug {
            let stem = Path::new(&frame.name)
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| format!("{:06}", frame.index));
            let path = d.join(format!("{stem}.png"));
            sensor
                .debug_panel()
                .save_png(&path)
                .map_err(|e| e.to_string())?;
        }
    }
    if !have_reference {
        return Err(format!("no readable frame in {}", a.seq.display()).into());
    }
    let wall_s = wall.elapsed().as_secs_f64();
    if processed > 0 {
        writeln!(
            report,
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
        )?;
    } else {
        writeln!(report, "no frame processed ({skipped} skipped)")?;
    }
    timings_table(&times, &mut report)?;
    Ok(skipped == 0)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    cli_support::finish(run(&cli).map(|ok| {
        if ok {
            ExitCode::SUCCESS
        } else {
            ExitCode::from(2)
        }
    }))
}

/// What the reference shows of the markers, and whether their dots are
/// followed: so that a user of another sensor sees whether its grid was
/// recognised.
fn markers_note(ex: &optical_tactile::sensor::ContactExtractor) -> String {
    match (ex.marker_pitch(), ex.follows_dots()) {
        (Some(p), true) if ex.config().dot_fit => format!(
            "markers: a regular grid, {p:.0} px apart, its dots followed one by one \
             and each contact's field fitted to them"
        ),
        (Some(p), true) => {
            format!("markers: a regular grid, {p:.0} px apart, its dots followed one by one")
        }
        (Some(p), false) => format!(
            "markers: a regular grid, {p:.0} px apart, read by the flow alone \
             (--dot-tracking on follows its dots)"
        ),
        (None, _) => "markers: no regular grid (random markers or none): the flow alone".into(),
    }
}
