//! Dense optical flow between two images with our DIS.
//!
//! ```text
//! cargo run --release --example flow -- REF.png CUR.png [--preset P] [--threads N]
//!     [--repeat N] --out flow.flo [--png flow.png] [--truth truth.flo]
//!     [--set name=value ...]
//! cargo run --release --example flow -- synth OUTDIR [--size WxH] [--max-disp D]
//!     [--translate DX,DY] [--affine A,B,C,D,TX,TY] [--seed S]
//! ```
//!
//! The first form writes the flow (Middlebury .flo), optionally a colour-wheel
//! PNG, and prints `compute_ms: <median>` (flow computation only, median over
//! `--repeat` runs after one warm-up); with `--truth` also the average
//! endpoint error (16 px border excluded) and the mean error (bias).
//! `--set` overrides one `DisParams` field (finest_scale, coarsest_scale,
//! patch_size, patch_stride, iterations, mean_normalization,
//! spatial_propagation, normalized_gradients, prefilter_sigma, backtracking,
//! stripes, zero_candidate, prefilter_all_levels, refine_iterations, sor_iterations, exact_derivatives, alpha,
//! delta, gamma, refine_levels (a number or `all`), early_stop, step_on_stop, min_stripe_rows,
//! coarsest_min_patches); `--affine A,B,C,D,TX,TY` renders the affine motion
//! `d = [[A, B], [C, D]] (p - centre) + (TX, TY)`; `--native` times only the flow at its native level (no
//! final upsampling). The second form renders a synthetic marker pair (ref.png,
//! cur.png, truth.flo) to try it on.

#[path = "../tests/support/mod.rs"]
mod support;

use std::path::Path;
use std::time::Instant;

use optical_tactile::flow::FlowField;
use optical_tactile::flow::color::flow_to_rgb;
use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
use optical_tactile::io::{read_flo, read_gray, write_flo, write_gray_png, write_rgb_png};
use optical_tactile::{Error, Result};

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn usage() -> Error {
    Error::param(
        "arguments",
        "usage: flow REF.png CUR.png [--preset P] [--threads N] [--repeat N] --out flow.flo \
         [--png flow.png] [--truth truth.flo] [--set name=value]... | flow synth OUTDIR \
         [--size WxH] [--max-disp D] [--translate DX,DY] [--affine A,B,C,D,TX,TY] [--seed S]",
    )
}

fn run() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("synth") {
        return synth(&args[1..]);
    }
    let mut pos = Vec::new();
    let mut preset = DisPreset::Accurate;
    let mut threads = 0usize;
    let mut repeat = 5usize;
    let (mut out, mut png, mut truth) = (None, None, None);
    let mut sets = Vec::new();
    let mut native = false;
    let mut it = args.iter();
    while let Some(a) = it.next() {
        let mut val = || it.next().cloned().ok_or_else(usage);
        match a.as_str() {
            "--preset" => preset = DisPreset::parse(&val()?)?,
            "--threads" => threads = parse_num("threads", &val()?)?,
            "--repeat" => repeat = parse_num::<usize>("repeat", &val()?)?.max(1),
            "--out" => out = Some(val()?),
            "--png" => png = Some(val()?),
            "--truth" => truth = Some(val()?),
            "--set" => sets.push(val()?),
            "--native" => native = true,
            _ if a.starts_with("--") => return Err(usage()),
            _ => pos.push(a.clone()),
        }
    }
    let (Some(out), [rp, cp]) = (out, pos.as_slice()) else {
        return Err(usage());
    };
    let mut params = DisParams::preset(preset);
    for s in &sets {
        apply_set(&mut params, s)?;
    }
    let reference = read_gray(Path::new(rp))?;
    let current = read_gray(Path::new(cp))?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::param("threads", e.to_string()))?;
    let (flow, median_ms) = pool.install(|| -> Result<(FlowField, f64)> {
        let mut dis = Dis::new(params)?;
        dis.set_reference(&reference)?;
        let mut flow = FlowField::zeros(1, 1);
        dis.compute_into(&current, &mut flow)?; // warm-up
        let mut times = Vec::with_capacity(repeat);
        for _ in 0..repeat {
            let t = Instant::now();
            if native {
                dis.compute_native(&current)?;
            } else {
                dis.compute_into(&current, &mut flow)?;
            }
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        Ok((flow, times[times.len() / 2]))
    })?;
    println!("compute_ms: {median_ms:.3}");
    write_flo(Path::new(&out), &flow)?;
    if let Some(p) = png {
        let (w, h) = flow.size();
        write_rgb_png(&p, &flow_to_rgb(&flow, None), w, h)?;
    }
    if let Some(t) = truth {
        let truth = read_flo(Path::new(&t))?;
        let aepe = flow.aepe(&truth, 16)?;
        let (bu, bv) = support::mean_error(&flow, &truth, 16);
        println!("aepe: {aepe:.4}");
        println!("bias: {bu:+.4} {bv:+.4}");
    }
    Ok(())
}

fn parse_num<T: std::str::FromStr>(name: &str, s: &str) -> Result<T> {
    s.parse()
        .map_err(|_| Error::param(name, format!("`{s}` is not a number")))
}

fn apply_set(p: &mut DisParams, s: &str) -> Result<()> {
    let (k, v) = s
        .split_once('=')
        .ok_or_else(|| Error::param("set", format!("`{s}` is not name=value")))?;
    let b = |v: &str| matches!(v, "1" | "true" | "on");
    match k {
        "finest_scale" => p.finest_scale = parse_num(k, v)?,
        "coarsest_scale" => p.coarsest_scale = Some(parse_num(k, v)?),
        "patch_size" => p.patch_size = parse_num(k, v)?,
        "patch_stride" => p.patch_stride = parse_num(k, v)?,
        "iterations" => p.gradient_descent_iterations = parse_num(k, v)?,
        "mean_normalization" => p.mean_normalization = b(v),
        "spatial_propagation" => p.spatial_propagation = b(v),
        "normalized_gradients" => p.normalized_gradients = b(v),
        "prefilter_sigma" => p.prefilter_sigma = parse_num(k, v)?,
        "backtracking" => p.backtracking = b(v),
        "stripes" => p.stripes = parse_num(k, v)?,
        "min_texture" => p.min_texture = parse_num(k, v)?,
        "zero_candidate" => p.zero_candidate = b(v),
        "prefilter_all_levels" => p.prefilter_all_levels = b(v),
        "refine_iterations" => p.refinement.outer_iterations = parse_num(k, v)?,
        "refine_levels" => {
            p.refine_levels = if v == "all" {
                None
            } else {
                Some(parse_num(k, v)?)
            }
        }
        "early_stop" => p.early_stop = parse_num(k, v)?,
        "step_on_stop" => p.step_on_stop = b(v),
        "min_stripe_rows" => p.min_stripe_rows = parse_num(k, v)?,
        "coarsest_min_patches" => p.coarsest_min_patches = parse_num(k, v)?,
        "sor_iterations" => p.refinement.sor_iterations = parse_num(k, v)?,
        "exact_derivatives" => p.refinement.exact_derivatives = b(v),
        "alpha" => p.refinement.alpha = parse_num(k, v)?,
        "delta" => p.refinement.delta = parse_num(k, v)?,
        "gamma" => p.refinement.gamma = parse_num(k, v)?,
        _ => return Err(Error::param("set", format!("unknown parameter `{k}`"))),
    }
    Ok(())
}

/// Renders a synthetic marker pair and its true flow into `dir`.
fn synth(args: &[String]) -> Result<()> {
    let dir = args.first().ok_or_else(usage)?;
    let (mut w, mut h, mut max_disp, mut seed) = (1920usize, 1080usize, 5.0f64, 1u64);
    let mut translate = None;
    let mut affine = None;
    let mut it = args[1..].iter();
    while let Some(a) = it.next() {
        let v = it.next().ok_or_else(usage)?;
        match a.as_str() {
            "--size" => {
                let (a, b) = v.split_once('x').ok_or_else(usage)?;
                (w, h) = (parse_num("size", a)?, parse_num("size", b)?);
            }
            "--max-disp" => max_disp = parse_num("max-disp", v)?,
            "--seed" => seed = parse_num("seed", v)?,
            "--translate" => {
                let (a, b) = v.split_once(',').ok_or_else(usage)?;
                translate = Some((parse_num("translate", a)?, parse_num("translate", b)?));
            }
            "--affine" => {
                // a,b,c,d,tx,ty: d = [[a, b], [c, d]] (p - centre) + t.
                let vals = v
                    .split(',')
                    .map(|s| parse_num::<f64>("affine", s))
                    .collect::<Result<Vec<_>>>()?;
                let [a, b, c, d, tx, ty] = vals[..] else {
                    return Err(usage());
                };
                affine = Some(([a, b, c, d], [tx, ty]));
            }
            _ => return Err(usage()),
        }
    }
    let motion = match (translate, affine) {
        (Some((dx, dy)), _) => support::Motion::Translation(dx, dy),
        (None, Some((a, t))) => support::Motion::Affine {
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
            a,
            t,
        },
        (None, None) => support::press_motion(w, h, max_disp, seed),
    };
    let (r, c, t) = support::marker_pair(w, h, &motion, seed);
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let d = Path::new(dir);
    write_gray_png(d.join("ref.png"), &r)?;
    write_gray_png(d.join("cur.png"), &c)?;
    write_flo(d.join("truth.flo"), &t)?;
    let maxm = t.magnitude().iter().cloned().fold(0.0f32, f32::max);
    println!("wrote {dir}: {w}x{h}, max motion {maxm:.2} px");
    Ok(())
}
