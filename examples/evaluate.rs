//! Scores predicted contacts against the truth.
//!
//! ```text
//! cargo run --release --example evaluate -- contacts.jsonl truth.jsonl [--gate MM] [--json FILE]
//! ```
//! Prints a markdown table: location and force MAE over matched contacts,
//! misses, false contacts, and per-frame latency if the prediction recorded it.

use std::process::ExitCode;

use optical_tactile::io::{FrameRecord, read_jsonl};
use optical_tactile_sim::evaluate::score;

const USAGE: &str =
    "usage: evaluate CONTACTS.jsonl TRUTH.jsonl [--gate MM (default 10)] [--json FILE]";

fn run() -> Result<(), String> {
    let mut files = Vec::new();
    let mut gate = 10.0;
    let mut json = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(());
            }
            "--gate" => {
                let v = args.next().ok_or("--gate needs a value")?;
                gate = v
                    .parse()
                    .ok()
                    .filter(|g: &f64| g.is_finite() && *g > 0.0)
                    .ok_or(format!("--gate: expected a positive number, got `{v}`"))?;
            }
            "--json" => json = Some(args.next().ok_or("--json needs a file")?),
            _ if a.starts_with("--") => return Err(format!("unknown option {a}\n{USAGE}")),
            _ => files.push(a),
        }
    }
    let [pred, truth] = &files[..] else {
        return Err(USAGE.into());
    };
    let pred: Vec<FrameRecord> = read_jsonl(pred).map_err(|e| e.to_string())?;
    let truth: Vec<FrameRecord> = read_jsonl(truth).map_err(|e| e.to_string())?;
    let e = score(&pred, &truth, gate);
    print!("{}", e.to_markdown());
    if let Some(path) = json {
        let text = serde_json::to_string_pretty(&e).map_err(|e| e.to_string())?;
        std::fs::write(&path, text).map_err(|e| format!("{path}: {e}"))?;
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
