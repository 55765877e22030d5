//! Natural Helmholtz-Hodge decomposition of a flow file.
//!
//! ```text
//! cargo run --release --example hhd -- FIELD.flo --out DIR [--dx 1 --dy 1] [--repeat N]
//! cargo run --release --example hhd -- --demo 256x256 [--out DIR] [--repeat N]
//! ```
//!
//! Reads a Middlebury `.flo` (u along columns, v along rows, pixels) and
//! writes into DIR: `d.flo` (curl-free part), `r.flo` (divergence-free
//! part), `h.flo` (harmonic part), all f32 as the format requires, and
//! `D.npy`, `R.npy`: the two potentials as **float64** (`<f8`) arrays of shape
//! (height, width). `--dx`/`--dy` are the grid spacings along columns/rows
//! (default 1). `--demo WxH` decomposes a synthetic press (outward flow
//! with a twist) instead of a file. `--repeat N` times N decompositions with
//! the planned solver and prints the wall-clock minimum and median and the
//! thread's CPU time per call (which stays meaningful on a loaded machine).

#[path = "cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use cli_support::{Failure, Sink};
use ndarray::Array2;
use optical_tactile::flow::FlowField;
use optical_tactile::hhd::{Decomposition, Field2, NaturalHhd};
use optical_tactile::{Error, io};

/// Natural Helmholtz-Hodge decomposition of a flow field. Writes into DIR:
/// d.flo, r.flo, h.flo (curl-free, divergence-free and harmonic parts, f32
/// .flo) and D.npy, R.npy (the potentials D and R, float64 <f8, shape
/// (height, width)).
#[derive(Parser, Debug)]
#[command(name = "hhd")]
struct Args {
    /// Flow field to decompose (Middlebury .flo: u along columns, v along
    /// rows, pixels).
    #[arg(
        value_name = "FIELD.flo",
        required_unless_present = "demo",
        conflicts_with = "demo"
    )]
    input: Option<PathBuf>,
    /// Decompose a synthetic press of that size (outward flow with a twist)
    /// instead of a file.
    #[arg(long, value_name = "WxH", value_parser = cli_support::size)]
    demo: Option<(usize, usize)>,
    /// Output directory (created if missing; required with a file).
    #[arg(long, value_name = "DIR", required_unless_present = "demo")]
    out: Option<PathBuf>,
    /// Grid spacing along columns (x).
    #[arg(long, value_name = "DX", default_value_t = 1.0, value_parser = cli_support::finite)]
    dx: f64,
    /// Grid spacing along rows (y).
    #[arg(long, value_name = "DY", default_value_t = 1.0, value_parser = cli_support::finite)]
    dy: f64,
    /// Time N decompositions (planned solver): wall-clock min and median,
    /// and this thread's CPU time per call (Linux).
    #[arg(long, value_name = "N", default_value_t = 0)]
    repeat: usize,
}

/// Outward flow around the centre with a small twist: a press with shear.
fn demo_field(w: usize, h: usize) -> FlowField {
    let (cx, cy) = (w as f32 / 2.0, h as f32 / 2.0);
    let s = 0.2 * w.min(h) as f32;
    let e = |i: usize, j: usize| {
        let (x, y) = (j as f32 - cx, i as f32 - cy);
        (x, y, 2.0 * (-(x * x + y * y) / (2.0 * s * s)).exp() / s)
    };
    let u = Array2::from_shape_fn((h, w), |(i, j)| {
        let (x, y, g) = e(i, j);
        (x - 0.2 * y) * g
    });
    let v = Array2::from_shape_fn((h, w), |(i, j)| {
        let (x, y, g) = e(i, j);
        (y + 0.2 * x) * g
    });
    FlowField { u, v }
}

/// CPU time this thread has run, in ns (Linux `/proc/thread-self/schedstat`).
fn thread_cpu_ns() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

fn to_flow(f: &Field2) -> FlowField {
    FlowField {
        u: f.u.mapv(|x| x as f32),
        v: f.v.mapv(|x| x as f32),
    }
}

fn run(a: Args) -> Result<(), Failure> {
    let mut out = Sink::stdout();
    let flow = match (&a.input, a.demo) {
        (Some(p), _) => io::read_flo(p)?,
        (None, Some((w, h))) => demo_field(w, h),
        (None, None) => unreachable!("clap requires a file or --demo"),
    };
    let (w, h) = flow.size();
    let mut hhd = NaturalHhd::new();
    let mut dec = Decomposition::zeros(h, w);
    let t0 = Instant::now();
    hhd.decompose_into(flow.u.view(), flow.v.view(), a.dx, a.dy, &mut dec)?;
    let first = t0.elapsed();
    let (r, c) = dec.argmin_d();
    writeln!(
        out,
        "{w}x{h}, dx {} dy {}: argmin D at row {r}, column {c}; max D - min D = {:.6}",
        a.dx,
        a.dy,
        dec.d_range()
    )?;
    writeln!(
        out,
        "first call (plans the size): {:.3} ms",
        first.as_secs_f64() * 1e3
    )?;
    if a.repeat > 0 {
        let cpu0 = thread_cpu_ns();
        let mut times = Vec::with_capacity(a.repeat);
        for _ in 0..a.repeat {
            let t = Instant::now();
            hhd.decompose_into(flow.u.view(), flow.v.view(), a.dx, a.dy, &mut dec)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        writeln!(
            out,
            "{} planned decompositions: min {:.3} ms, median {:.3} ms",
            a.repeat,
            times[0],
            times[times.len() / 2]
        )?;
        if let (Some(c0), Some(c1)) = (cpu0, thread_cpu_ns()) {
            // CPU time of this thread: what the call costs on one core, even
            // when other processes share the machine.
            writeln!(
                out,
                "  thread CPU time: {:.3} ms per decomposition (mean)",
                (c1 - c0) as f64 / a.repeat as f64 * 1e-6
            )?;
        }
    }
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        io::write_flo(dir.join("d.flo"), &to_flow(&dec.d))?;
        io::write_flo(dir.join("r.flo"), &to_flow(&dec.r))?;
        io::write_flo(dir.join("h.flo"), &to_flow(&dec.h))?;
        io::write_npy_f64(dir.join("D.npy"), &dec.potential_d)?;
        io::write_npy_f64(dir.join("R.npy"), &dec.potential_r)?;
        writeln!(
            out,
            "wrote d.flo r.flo h.flo (f32), D.npy R.npy (f64) to {}",
            dir.display()
        )?;
    }
    Ok(())
}

fn main() -> ExitCode {
    cli_support::finish(run(Args::parse()).map(|()| ExitCode::SUCCESS))
}
