//! Accuracy and time of one DIS parameter set on a synthetic pair, for tuning
//! the speed knobs (`early_stop`, `refine_levels`, ...).
//!
//! ```text
//! cargo run --release --example dis_tune -- DIR [--preset P] [--threads N] [--repeat N] \
//!     [--set name=value]...
//! ```
//! `DIR` holds `ref.png`, `cur.png` and `truth.flo` (as written by
//! `examples/flow synth`). Prints `compute_ms` (median of `--repeat` runs after
//! one warm-up), the average endpoint error and the mean error (bias) with a
//! 16-px border excluded.

use std::path::Path;
use std::time::Instant;

use optical_tactile::error::{Error, Result};
use optical_tactile::flow::FlowField;
use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
use optical_tactile::io::{read_flo, read_gray};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut dir = None;
    let (mut preset, mut threads, mut repeat) = (DisPreset::Fast, 1usize, 5usize);
    let mut p_sets = Vec::new();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        let mut val = || {
            it.next()
                .cloned()
                .ok_or_else(|| Error::param("args", format!("{a} needs a value")))
        };
        match a.as_str() {
            "--preset" => preset = DisPreset::parse(&val()?)?,
            "--threads" => threads = num("threads", &val()?)?,
            "--repeat" => repeat = num::<usize>("repeat", &val()?)?.max(1),
            "--set" => p_sets.push(val()?),
            _ => dir = Some(a.clone()),
        }
    }
    let dir = dir.ok_or_else(|| Error::param("args", "DIR is required"))?;
    let mut p = DisParams::preset(preset);
    for s in &p_sets {
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
            _ => return Err(Error::param("set", format!("unknown parameter `{k}`"))),
        }
    }
    let d = Path::new(&dir);
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
    println!(
        "compute_ms: {ms:.3} aepe: {aepe:.4} bias: {:+.4} {:+.4}",
        bu / n,
        bv / n
    );
    Ok(())
}

fn num<T: std::str::FromStr>(name: &str, s: &str) -> Result<T> {
    s.parse()
        .map_err(|_| Error::param(name, format!("`{s}` is not a number")))
}
