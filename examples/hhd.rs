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

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use ndarray::Array2;
use optical_tactile::flow::FlowField;
use optical_tactile::hhd::{Decomposition, Field2, NaturalHhd};
use optical_tactile::{Error, Result, io};

const HELP: &str = "\
Natural Helmholtz-Hodge decomposition of a flow field.

USAGE:
    hhd FIELD.flo --out DIR [--dx DX] [--dy DY] [--repeat N]
    hhd --demo WxH [--out DIR] [--dx DX] [--dy DY] [--repeat N]

Writes into DIR:
    d.flo, r.flo, h.flo   curl-free, divergence-free and harmonic parts (f32 .flo)
    D.npy, R.npy          the potentials D and R, float64 (<f8), shape (height, width)

OPTIONS:
    --out DIR      output directory (created if missing)
    --dx DX        grid spacing along columns (x), default 1
    --dy DY        grid spacing along rows (y), default 1
    --demo WxH     decompose a synthetic press of that size instead of a file
    --repeat N     time N decompositions (planned solver): wall-clock min and
                   median, and this thread's CPU time per call (Linux)
    -h, --help     this text
";

struct Args {
    input: Option<PathBuf>,
    demo: Option<(usize, usize)>,
    out: Option<PathBuf>,
    dx: f64,
    dy: f64,
    repeat: usize,
}

fn parse_args() -> Result<Option<Args>> {
    let mut a = Args {
        input: None,
        demo: None,
        out: None,
        dx: 1.0,
        dy: 1.0,
        repeat: 0,
    };
    let mut it = std::env::args().skip(1);
    let value = |it: &mut dyn Iterator<Item = String>, name: &str| {
        it.next().ok_or_else(|| Error::param(name, "needs a value"))
    };
    let number = |s: String, name: &str| -> Result<f64> {
        s.parse()
            .map_err(|_| Error::param(name, format!("not a number: {s}")))
    };
    while let Some(arg) = it.next() {
        match arg.as_str() {
            "-h" | "--help" => return Ok(None),
            "--out" => a.out = Some(value(&mut it, "--out")?.into()),
            "--dx" => a.dx = number(value(&mut it, "--dx")?, "--dx")?,
            "--dy" => a.dy = number(value(&mut it, "--dy")?, "--dy")?,
            "--repeat" => {
                let s = value(&mut it, "--repeat")?;
                a.repeat = s
                    .parse()
                    .map_err(|_| Error::param("--repeat", format!("not a count: {s}")))?;
            }
            "--demo" => {
                let s = value(&mut it, "--demo")?;
                let parsed = s
                    .split_once('x')
                    .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)));
                match parsed {
                    Some((w, h)) if w > 0 && h > 0 => a.demo = Some((w, h)),
                    _ => return Err(Error::param("--demo", format!("expected WxH, got {s}"))),
                }
            }
            s if s.starts_with('-') => {
                return Err(Error::param(s, "unknown option (see --help)"));
            }
            s => {
                if a.input.replace(s.into()).is_some() {
                    return Err(Error::param("FIELD", "only one input file"));
                }
            }
        }
    }
    match (&a.input, &a.demo) {
        (None, None) => Err(Error::param("FIELD", "give a .flo file or --demo WxH")),
        (Some(_), Some(_)) => Err(Error::param("--demo", "give either a file or --demo")),
        (Some(_), None) if a.out.is_none() => Err(Error::param("--out", "is required")),
        _ => Ok(Some(a)),
    }
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

fn run(a: Args) -> Result<()> {
    let flow = match (&a.input, a.demo) {
        (Some(p), _) => io::read_flo(p)?,
        (None, Some((w, h))) => demo_field(w, h),
        (None, None) => unreachable!("checked in parse_args"),
    };
    let (w, h) = flow.size();
    let mut hhd = NaturalHhd::new();
    let mut dec = Decomposition::zeros(h, w);
    let t0 = Instant::now();
    hhd.decompose_into(flow.u.view(), flow.v.view(), a.dx, a.dy, &mut dec)?;
    let first = t0.elapsed();
    let (r, c) = dec.argmin_d();
    println!(
        "{w}x{h}, dx {} dy {}: argmin D at row {r}, column {c}; max D - min D = {:.6}",
        a.dx,
        a.dy,
        dec.d_range()
    );
    println!(
        "first call (plans the size): {:.3} ms",
        first.as_secs_f64() * 1e3
    );
    if a.repeat > 0 {
        let cpu0 = thread_cpu_ns();
        let mut times = Vec::with_capacity(a.repeat);
        for _ in 0..a.repeat {
            let t = Instant::now();
            hhd.decompose_into(flow.u.view(), flow.v.view(), a.dx, a.dy, &mut dec)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        println!(
            "{} planned decompositions: min {:.3} ms, median {:.3} ms",
            a.repeat,
            times[0],
            times[times.len() / 2]
        );
        if let (Some(c0), Some(c1)) = (cpu0, thread_cpu_ns()) {
            // CPU time of this thread: what the call costs on one core, even
            // when other processes share the machine.
            println!(
                "  thread CPU time: {:.3} ms per decomposition (mean)",
                (c1 - c0) as f64 / a.repeat as f64 * 1e-6
            );
        }
    }
    if let Some(out) = &a.out {
        std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
        io::write_flo(out.join("d.flo"), &to_flow(&dec.d))?;
        io::write_flo(out.join("r.flo"), &to_flow(&dec.r))?;
        io::write_flo(out.join("h.flo"), &to_flow(&dec.h))?;
        io::write_npy_f64(out.join("D.npy"), &dec.potential_d)?;
        io::write_npy_f64(out.join("R.npy"), &dec.potential_r)?;
        println!(
            "wrote d.flo r.flo h.flo (f32), D.npy R.npy (f64) to {}",
            out.display()
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    match parse_args() {
        Ok(None) => {
            print!("{HELP}");
            ExitCode::SUCCESS
        }
        Ok(Some(a)) => match run(a) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("error: {e}");
                ExitCode::FAILURE
            }
        },
        Err(e) => {
            eprintln!("error: {e}\n\n{HELP}");
            ExitCode::from(2)
        }
    }
}
