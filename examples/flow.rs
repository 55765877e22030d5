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
//! stripes, zero_candidate, fill_untextured, sparse_texture, prefilter_all_levels, refine_iterations, sor_iterations, exact_derivatives, alpha,
//! delta, gamma, refine_levels (a number or `all`), early_stop, step_on_stop, min_stripe_rows,
//! coarsest_min_patches); `--affine A,B,C,D,TX,TY` renders the affine motion
//! `d = [[A, B], [C, D]] (p - centre) + (TX, TY)`; `--native` times only the flow at its native level (no
//! final upsampling). The second form renders a synthetic marker pair (ref.png,
//! cur.png, truth.flo) to try it on.

#[path = "cli_support/mod.rs"]
mod cli_support;
#[path = "../tests/support/mod.rs"]
mod support;

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, Subcommand};
use cli_support::{Failure, Sink};
use optical_tactile::flow::FlowField;
use optical_tactile::flow::color::flow_to_rgb;
use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
use optical_tactile::io::{read_flo, read_gray, write_flo, write_gray_png, write_rgb_png};
use optical_tactile::{Error, Result};

/// Dense optical flow between two images with our DIS: writes it as .flo,
/// prints the median computation time and, against a true flow, the error.
#[derive(Parser, Debug)]
#[command(
    name = "flow",
    args_conflicts_with_subcommands = true,
    subcommand_negates_reqs = true
)]
struct Cli {
    /// Render a synthetic pair instead.
    #[command(subcommand)]
    command: Option<Synth>,
    /// Reference image.
    #[arg(value_name = "REF.png", required = true)]
    reference: Option<PathBuf>,
    /// Current image.
    #[arg(value_name = "CUR.png", required = true)]
    current: Option<PathBuf>,
    /// DIS preset (the sensor's default, `fine`, unless given).
    #[arg(long, value_name = "PRESET", default_value = "fine", ignore_case = true,
          value_parser = cli_support::dis_preset())]
    preset: DisPreset,
    /// Worker threads (0: one per core).
    #[arg(long, value_name = "N", default_value_t = 0)]
    threads: usize,
    /// Timed runs after one warm-up (the median is printed).
    #[arg(long, value_name = "N", default_value_t = 5, value_parser = clap::value_parser!(u64).range(1..))]
    repeat: u64,
    /// Write the flow (Middlebury .flo) here.
    #[arg(long, value_name = "FILE", required = true, value_parser = cli_support::binary_path)]
    out: Option<PathBuf>,
    /// Write a colour-wheel picture of the flow (PNG) here.
    #[arg(long, value_name = "FILE", value_parser = cli_support::binary_path)]
    png: Option<PathBuf>,
    /// True flow (.flo): print the average endpoint error and the bias
    /// (16 px border excluded).
    #[arg(long, value_name = "FILE")]
    truth: Option<PathBuf>,
    /// Override one DisParams field, e.g. --set patch_size=12 (repeatable;
    /// finest_scale, coarsest_scale, patch_size, patch_stride, iterations,
    /// mean_normalization, spatial_propagation, normalized_gradients,
    /// prefilter_sigma, backtracking, stripes, min_texture, zero_candidate,
    /// fill_untextured, sparse_texture, prefilter_all_levels, refine_iterations, sor_iterations,
    /// exact_derivatives, alpha, delta, gamma, refine_levels (a number or
    /// `all`), early_stop, step_on_stop, min_stripe_rows,
    /// coarsest_min_patches).
    #[arg(long = "set", value_name = "NAME=VALUE")]
    sets: Vec<String>,
    /// Time only the flow at its native level (no final upsampling).
    #[arg(long)]
    native: bool,
}

#[derive(Subcommand, Debug)]
enum Synth {
    /// Renders a synthetic marker pair (ref.png, cur.png, truth.flo) into
    /// OUTDIR to try the flow on.
    Synth {
        /// Output folder (created).
        #[arg(value_name = "OUTDIR")]
        dir: PathBuf,
        /// Image size.
        #[arg(long, value_name = "WxH", default_value = "1920x1080", value_parser = cli_support::size)]
        size: (usize, usize),
        /// Largest displacement of the synthetic press, px.
        #[arg(long, value_name = "D", default_value_t = 5.0)]
        max_disp: f64,
        /// A uniform translation instead of the press.
        #[arg(long, value_name = "DX,DY", allow_hyphen_values = true, value_parser = pair)]
        translate: Option<(f64, f64)>,
        /// The affine motion d = [[A, B], [C, D]] (p - centre) + (TX, TY)
        /// instead of the press.
        #[arg(long, value_name = "A,B,C,D,TX,TY", allow_hyphen_values = true, value_parser = affine)]
        affine: Option<([f64; 4], [f64; 2])>,
        /// Seed of the markers and the press.
        #[arg(long, value_name = "S", default_value_t = 1)]
        seed: u64,
    },
}

/// `DX,DY`.
fn pair(s: &str) -> std::result::Result<(f64, f64), String> {
    match cli_support::number_list(s)?[..] {
        [a, b] => Ok((a, b)),
        _ => Err(format!("expected two numbers DX,DY, got `{s}`")),
    }
}

/// `A,B,C,D,TX,TY`.
fn affine(s: &str) -> std::result::Result<([f64; 4], [f64; 2]), String> {
    match cli_support::number_list(s)?[..] {
        [a, b, c, d, tx, ty] => Ok(([a, b, c, d], [tx, ty])),
        _ => Err(format!("expected six numbers A,B,C,D,TX,TY, got `{s}`")),
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    cli_support::finish(run(cli).map(|()| ExitCode::SUCCESS))
}

fn run(cli: Cli) -> std::result::Result<(), Failure> {
    let mut out = Sink::stdout();
    if let Some(Synth::Synth {
        dir,
        size: (w, h),
        max_disp,
        translate,
        affine,
        seed,
    }) = cli.command
    {
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
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        write_gray_png(dir.join("ref.png"), &r)?;
        write_gray_png(dir.join("cur.png"), &c)?;
        write_flo(dir.join("truth.flo"), &t)?;
        let maxm = t.magnitude().iter().cloned().fold(0.0f32, f32::max);
        writeln!(
            out,
            "wrote {}: {w}x{h}, max motion {maxm:.2} px",
            dir.display()
        )?;
        return Ok(());
    }
    let (Some(rp), Some(cp), Some(flo)) = (&cli.reference, &cli.current, &cli.out) else {
        unreachable!("clap requires REF, CUR and --out without a subcommand");
    };
    let repeat = cli.repeat as usize;
    let mut params = DisParams::preset(cli.preset);
    for s in &cli.sets {
        apply_set(&mut params, s)?;
    }
    let reference = read_gray(rp)?;
    let current = read_gray(cp)?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(cli.threads)
        .build()
        .map_err(|e| Error::param("threads", e.to_string()))?;
    let native = cli.native;
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
    writeln!(out, "compute_ms: {median_ms:.3}")?;
    write_flo(flo, &flow)?;
    if let Some(p) = &cli.png {
        let (w, h) = flow.size();
        write_rgb_png(p, &flow_to_rgb(&flow, None), w, h)?;
    }
    if let Some(t) = &cli.truth {
        let truth = read_flo(t)?;
        let aepe = flow.aepe(&truth, 16)?;
        let (bu, bv) = support::mean_error(&flow, &truth, 16);
        writeln!(out, "aepe: {aepe:.4}")?;
        writeln!(out, "bias: {bu:+.4} {bv:+.4}")?;
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
        "fill_untextured" => p.fill_untextured = b(v),
        "sparse_texture" => p.sparse_texture = parse_num(k, v)?,
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
