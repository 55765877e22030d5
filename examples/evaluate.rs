//! Scores predicted contacts against the truth.
//!
//! ```text
//! cargo run --release --example evaluate -- contacts.jsonl truth.jsonl [--gate MM] \
//!     [--beyond N] [--worst K] [--bands MM] [--json FILE|-]
//! ```
//! Prints a markdown table: location and force MAE over matched contacts,
//! misses, false contacts, how many contacts are off by more than `--beyond`
//! newtons on each axis (0.3 by default), and per-frame latency if the
//! prediction recorded it; then the `--worst` contacts of largest 3-D force
//! error (5 by default, 0 for none), with their frames, so that the tail
//! behind a mean can be looked at. `--bands MM` adds the errors per band of
//! MM along the true x (where on the sensor the errors are).
//! `--json -` writes the scores to stdout and the table to stderr. With no
//! frame in common or no matched contact there is nothing to score: the
//! table is printed, no scores are written and the exit status is 1.

#[path = "cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use cli_support::{Failure, Sink, TextOut};
use optical_tactile::io::{FrameRecord, read_jsonl};
use optical_tactile_sim::evaluate::{MAX_WORST, ScoreOptions, score_with};

/// Scores predicted contacts (JSON Lines, docs/formats.md) against the truth:
/// location and force MAE over matched contacts, misses, false contacts and
/// latency, as a markdown table.
#[derive(Parser, Debug)]
#[command(name = "evaluate")]
struct Cli {
    /// Predicted contacts (JSON Lines, one record per frame).
    #[arg(value_name = "CONTACTS.jsonl")]
    contacts: PathBuf,
    /// True contacts (JSON Lines, one record per frame).
    #[arg(value_name = "TRUTH.jsonl")]
    truth: PathBuf,
    /// A prediction matches a true contact within this distance, mm.
    #[arg(long, value_name = "MM", default_value_t = 10.0, value_parser = cli_support::positive)]
    gate: f64,
    /// Count the contacts whose error on an axis exceeds this, N.
    #[arg(long, value_name = "N", default_value_t = ScoreOptions::default().beyond_n,
          value_parser = cli_support::positive)]
    beyond: f64,
    /// List this many contacts of largest 3-D force error (0: none).
    #[arg(long, value_name = "K", default_value_t = ScoreOptions::default().worst as u32,
          value_parser = clap::value_parser!(u32).range(0..=MAX_WORST as i64))]
    worst: u32,
    /// Score the contacts apart per band of this width along the true x, mm
    /// (a table after the others; `bands` in the JSON).
    #[arg(long, value_name = "MM", value_parser = cli_support::positive)]
    bands: Option<f64>,
    /// Write the scores as JSON to FILE, or to stdout with `-` (the table
    /// then goes to stderr).
    #[arg(long, value_name = "FILE|-")]
    json: Option<TextOut>,
}

fn run(a: &Cli) -> Result<(), Failure> {
    let pred: Vec<FrameRecord> = read_jsonl(&a.contacts)?;
    let truth: Vec<FrameRecord> = read_jsonl(&a.truth)?;
    let options = ScoreOptions {
        gate_mm: a.gate,
        beyond_n: a.beyond,
        worst: a.worst as usize,
        band_mm: a.bands,
    };
    let e = score_with(&pred, &truth, &options);
    let mut report = Sink::report(a.json.as_ref().is_some_and(TextOut::is_stdout));
    write!(report, "{}", e.to_markdown())?;
    // Errors over no pair would read as perfect scores: nothing to score is
    // a failure, and no scores are written.
    if e.frames == 0 {
        return Err(format!(
            "nothing to score: no frame of {} is named in {}",
            a.contacts.display(),
            a.truth.display()
        )
        .into());
    }
    if e.matched == 0 {
        return Err(format!(
            "nothing to score: no predicted contact lies within {} mm of a true one \
             ({} frames, {} misses, {} false contacts)",
            a.gate, e.frames, e.misses, e.false_contacts
        )
        .into());
    }
    if let Some(out) = &a.json {
        out.write_json(&e)?;
    }
    Ok(())
}

/// Runs `evaluate` on the command-line arguments `args` (without the
/// program name), for tests.
pub fn run_with(args: &[String]) -> Result<(), Failure> {
    match cli_support::try_parse::<Cli>("evaluate", args)? {
        Some(cli) => run(&cli),
        None => Ok(()),
    }
}

fn main() -> ExitCode {
    cli_support::finish(run(&Cli::parse()).map(|()| ExitCode::SUCCESS))
}
