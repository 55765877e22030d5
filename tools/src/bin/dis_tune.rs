//! Accuracy and time of one DIS parameter set on a synthetic pair, for tuning
//! the speed knobs (`early_stop`, `refine_levels`, ...).
//!
//! ```text
//! cargo run --release -p optical-tactile-tools --bin dis_tune -- DIR [--preset P] [--threads N] \
//!     [--repeat N] [--set name=value]...
//! ```
//! `DIR` holds `ref.png`, `cur.png` and `truth.flo` (as written by
//! `examples/flow synth`). Prints `compute_ms` (median of `--repeat` runs after
//! one warm-up), the average endpoint error and the mean error (bias) with a
//! 16-px border excluded.

#[path = "../../../examples/cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use cli_support::{Failure, Sink};
use optical_tactile::error::{Error, Result};
use optical_tactile::flow::FlowField;
use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
use optical_tactile::io::{read_flo, read_gray};

/// Accuracy and time of one DIS parameter set on a synthetic pair.
#[derive(Parser, Debug)]
#[command(name = "dis_tune")]
struct Cli {
    /// Folder with ref.png, cur.png and truth.flo (`flow synth` writes them).
    #[arg(value_name = "DIR")]
    dir: PathBuf,
    /// DIS preset to start from.
    #[arg(long, value_name = "PRESET", default_value = "fast", ignore_case = true,
          value_parser = cli_support::dis_preset())]
    preset: DisPreset,
    /// Worker threads (0: one per core).
    #[arg(long, value_name = "N", default_value_t = 1)]
    threads: usize,
    /// Timed runs after one warm-up (the median is printed).
    #[arg(long, value_name = "N", default_value_t = 5, value_parser = clap::value_parser!(u64).range(1..))]
    repeat: u64,
    /// Override one parameter (repeatable): early_stop, refine_levels,
    /// iterations, refine_iterations, sor_iterations, normalized_gradients,
    /// step_on_stop, min_stripe_rows, coarsest_min_patches.
    #[arg(long = "set", value_name = "NAME=VALUE")]
    sets: Vec<String>,
}

fn main() -> ExitCode {
    cli_support::finish(run(&Cli::parse()).map(|()| ExitCode::SUCCESS))
}

fn run(cli: &Cli) -> std::result::Result<(), Failure> {
    let (preset, threads, repeat) = (cli.preset, cli.threads, cli.repeat as usize);
    let mut p = DisParams::preset(preset);
    for s in &cli.sets {
        let (k, v) = s
            .split_once('=')
            .ok_or_else(|| Error::param("set", format!("`{s}` is not name=value")))?;
        match k {
            "early_stop" => p.early_stop = num(k, v)?,
            "refine_levels" => p.refine_levels = Some(num(k, v)?),
            "iterations" => p.gradient_descent_iterations = num(k, v)?,
            "refine_iterations" => p.refinement.outer_iterations = num(k, v)?,
            "sor_iterations" => p.refinement.sor_iterations = num(k, v)?,
            "normalized_gradients" => p.normalized_gradients = v == "1",
            "step_on_stop" => p.step_on_stop = v == "1",
            "min_stripe_rows" => p.min_stripe_rows = num(k, v)?,
            "coarsest_min_patches" => p.coarsest_min_patches = num(k, v)?,
            _ => return Err(Error::param("set", format!("unknown parameter `{k}`")).into()),
        }
    }
    let d = Path::new(&cli.dir);
    let reference = read_gray(d.join("ref.png"))?;
    let current = read_gray(d.join("cur.png"))?;
    let truth = read_flo(d.join("truth.flo"))?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::param("threads", e.to_string()))?;
    let (flow, ms) = pool.install(|| -> Result<(FlowField, f64)> {
        let mut dis = Dis::new(p)?;
        dis.set_reference(&reference)?;
        let mut flow = FlowField::zeros(1, 1);
        dis.compute_into(&current, &mut flow)?;
        let mut times = Vec::with_capacity(repeat);
        for _ in 0..repeat {
            let t = Instant::now();
            dis.compute_into(&current, &mut flow)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        Ok((flow, times[times.len() / 2]))
    })?;
    let aepe = flow.aepe(&truth, 16)?;
    let (h, w) = truth.u.dim();
    let (mut bu, mut bv, mut n) = (0.0f64, 0.0f64, 0usize);
    for y in 16..h.saturating_sub(16) {
        for x in 16..w.saturating_sub(16) {
            bu += (flow.u[[y, x]] - truth.u[[y, x]]) as f64;
            bv += (flow.v[[y, x]] - truth.v[[y, x]]) as f64;
            n += 1;
        }
    }
    let n = n.max(1) as f64;
    writeln!(
        Sink::stdout(),
        "compute_ms: {ms:.3} aepe: {aepe:.4} bias: {:+.4} {:+.4}",
        bu / n,
        bv / n
    )?;
    Ok(())
}

fn num<T: std::str::FromStr>(name: &str, s: &str) -> Result<T> {
    s.parse()
        .map_err(|_| Error::param(name, format!("`{s}` is not a number")))
}
