//! Times `VariationalRefiner::refine` on a synthetic marker pair, for profiling and for
//! CPU-time measurements on a shared machine (wrap it in `perf stat -e task-clock`).
//!
//! `cargo run --release -p optical-tactile-tools --bin refine_probe -- W H CALLS [opencv|accurate]`
//! prints the median wall time per call. Thread count: `RAYON_NUM_THREADS`.

#[path = "../../../examples/cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, ValueEnum};
use cli_support::{Failure, Sink};
use ndarray::Array2;
use optical_tactile::flow::refine::{RefineParams, VariationalRefiner};

/// Times VariationalRefiner::refine on a synthetic marker pair (median wall
/// time per call; threads: RAYON_NUM_THREADS).
#[derive(Parser, Debug)]
#[command(name = "refine_probe")]
struct Cli {
    /// Image width, px.
    #[arg(value_name = "W", value_parser = clap::value_parser!(u64).range(1..))]
    width: u64,
    /// Image height, px.
    #[arg(value_name = "H", value_parser = clap::value_parser!(u64).range(1..))]
    height: u64,
    /// Timed calls.
    #[arg(value_name = "CALLS", value_parser = clap::value_parser!(u64).range(1..))]
    calls: u64,
    /// Refinement parameters.
    #[arg(value_enum, default_value_t = Params::Accurate)]
    params: Params,
}

/// The parameter sets.
#[derive(ValueEnum, Debug, Clone, Copy, PartialEq)]
enum Params {
    /// `RefineParams::opencv()`.
    Opencv,
    /// `RefineParams::accurate()`.
    Accurate,
}

fn markers(w: usize, h: usize, dx: f32, dy: f32) -> Array2<f32> {
    let mut img = Array2::from_elem((h, w), 200.0f32);
    let mut y = 3.0f32;
    while y < h as f32 {
        let mut x = 3.0f32;
        while x < w as f32 {
            let (cx, cy) = (x + dx, y + dy);
            for py in (cy as isize - 4).max(0)..(cy as isize + 5).min(h as isize) {
                for px in (cx as isize - 4).max(0)..(cx as isize + 5).min(w as isize) {
                    let r2 = (px as f32 - cx).powi(2) + (py as f32 - cy).powi(2);
                    img[[py as usize, px as usize]] -= 150.0 * (-r2 / 2.0).exp();
                }
            }
            x += 6.0;
        }
        y += 6.0;
    }
    img
}

fn main() -> ExitCode {
    cli_support::finish(run(&Cli::parse()).map(|()| ExitCode::SUCCESS))
}

fn run(cli: &Cli) -> Result<(), Failure> {
    let (w, h, calls) = (cli.width as usize, cli.height as usize, cli.calls as usize);
    let params = match cli.params {
        Params::Opencv => RefineParams::opencv(),
        Params::Accurate => RefineParams::accurate(),
    };
    let i0 = markers(w, h, 0.0, 0.0);
    let i1 = markers(w, h, 0.3, -0.2);
    let mut vr = VariationalRefiner::new(params);
    vr.set_reference(i0.view())?;
    let (mut u, mut v) = (Array2::zeros((h, w)), Array2::zeros((h, w)));
    let mut times = Vec::with_capacity(calls);
    for _ in 0..calls {
        u.fill(0.2);
        v.fill(-0.1);
        let t = Instant::now();
        vr.refine(i1.view(), &mut u, &mut v)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    writeln!(
        Sink::stdout(),
        "{w}x{h}: median {:.3} ms per call over {calls} calls (u at centre {:.4})",
        times[calls / 2],
        u[[h / 2, w / 2]]
    )?;
    Ok(())
}
