//! Segmentation experiments on the simulator, printed as markdown:
//!
//! - `rest`: false contacts on rest pairs (reference against another unloaded
//!   frame with fresh noise and flicker), per preset;
//! - `mdf`: minimum detectable force per preset and indenter, over positions
//!   along the skin and the five tilts of the characterization protocol;
//! - `spacing`: two rods pressed at decreasing spacing (with equal forces,
//!   or the second at `--ratio` times the first's); told apart = exactly two
//!   contacts, each within `--tol-mm` of its rod.
//!
//! Frames are rendered with the simulator's library API (no PNGs) and go
//! through the sensor's default DIS flow (`fine`) on the extractor's
//! analysis grid, as in [`ContactExtractor`](optical_tactile::sensor::ContactExtractor).
//!
//! ```text
//! cargo run --release -p optical-tactile-tools --bin sweep -- all
//! cargo run --release -p optical-tactile-tools --bin sweep -- rest --rest 400
//! cargo run --release -p optical-tactile-tools --bin sweep -- mdf --candidate 0.25,900,5,15
//! ```
//!
//! Each sweep shows a progress bar with an ETA on a terminal (`--quiet`
//! hides it); a closed stdout ends the run quietly.
//!
//! With `SWEEP_DEBUG=1` in the environment, the missed presses (from 0.8 N)
//! and every spacing case are printed to stderr with their patches and
//! contour boxes (full-resolution px).

#[path = "../../../examples/cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, ValueEnum};
use cli_support::{Failure, Numbers, Sink, Stages};
use optical_tactile::segment::Thresholds;
use optical_tactile::segment::morphology::Shape;
use optical_tactile::sensor::ExtractorConfig;
use optical_tactile_sim::experiments::{
    DebugLog, INDENTERS_MM, MdfPlan, SpacingPlan, SweepOptions, TILTS_DEG, ThresholdSet, mdf_sweep,
    rest_sweep, spacing_sweep,
};
use optical_tactile_sim::{SimConfig, SyntheticSensor};

/// Segmentation experiments on the simulator (false contacts at rest,
/// minimum detectable force, two-rod spacing), printed as markdown.
#[derive(Parser, Debug)]
#[command(
    name = "sweep",
    after_help = "With SWEEP_DEBUG=1 in the environment, the missed presses (from 0.8 N) and \
                  every spacing case are printed to stderr with their patches and contour boxes."
)]
struct Args {
    /// Which sweep to run.
    #[arg(value_enum, default_value_t = Mode::All)]
    mode: Mode,
    /// Simulator seed (marker layout).
    #[arg(long, value_name = "N", default_value_t = 1)]
    seed: u64,
    /// Rest pairs.
    #[arg(long, value_name = "N", default_value_t = 200)]
    rest: usize,
    /// Arc positions of the single presses, mm from the centre.
    #[arg(long, value_name = "a,b,..", allow_hyphen_values = true,
          default_value_t = Numbers(vec![-120.0, -80.0, -40.0, 0.0, 40.0, 80.0, 120.0]))]
    positions: Numbers,
    /// Force ladder, N.
    #[arg(long, value_name = "a,b,..",
          default_value_t = Numbers((1..=20).map(|k| k as f64 / 10.0).collect()))]
    forces: Numbers,
    /// Two-rod spacings, mm.
    #[arg(long, value_name = "a,b,..",
          default_value_t = Numbers(vec![40.0, 35.0, 30.0, 25.0, 20.0, 17.5, 15.0, 12.5, 10.0, 7.5, 5.0]))]
    spacings: Numbers,
    /// Force of the first (left) rod, N.
    #[arg(long, value_name = "a,b,..", default_value_t = Numbers(vec![1.5, 3.0]))]
    spacing_forces: Numbers,
    /// The second rod's force as a fraction of the first's (1: equal).
    #[arg(long, value_name = "R", default_value_t = 1.0, value_parser = cli_support::positive)]
    ratio: f64,
    /// Arc positions of the pair's midpoint, mm.
    #[arg(long, value_name = "a,b,..", allow_hyphen_values = true,
          default_value_t = Numbers(vec![-60.0, 0.0, 60.0]))]
    spacing_centres: Numbers,
    /// A contact counts for a rod within this distance, mm.
    #[arg(long, value_name = "X", default_value_t = 3.0, value_parser = cli_support::positive)]
    tol_mm: f64,
    /// Patch margin, full-resolution px.
    #[arg(long, value_name = "PX", default_value_t = ExtractorConfig::default().margin_px)]
    margin: usize,
    /// Evaluate these thresholds (magnitude, sum, erode, dilate, kernel
    /// shape rect|cross|ellipse) instead of the presets (repeatable).
    #[arg(long = "candidate", value_name = "m,s,e,d[,shape]", value_parser = candidate)]
    candidates: Vec<ThresholdSet>,
    /// Also keep the presets when candidates are given.
    #[arg(long)]
    with_presets: bool,
    /// No progress bars.
    #[arg(long, short)]
    quiet: bool,
}

/// The sweeps.
#[derive(ValueEnum, Debug, Clone, Copy, PartialEq)]
enum Mode {
    /// Every sweep.
    All,
    /// False contacts on rest pairs.
    Rest,
    /// Minimum detectable force.
    Mdf,
    /// Two rods at decreasing spacing.
    Spacing,
}

impl Args {
    /// The threshold sets to evaluate: the candidates, or the presets (also
    /// with the candidates when asked).
    fn sets(&self) -> Vec<ThresholdSet> {
        let mut sets = if self.candidates.is_empty() || self.with_presets {
            ThresholdSet::presets()
        } else {
            Vec::new()
        };
        sets.extend(self.candidates.iter().cloned());
        sets
    }
}

/// `m,s,e,d[,shape]`.
fn candidate(v: &str) -> Result<ThresholdSet, String> {
    let parts: Vec<&str> = v.split(',').map(str::trim).collect();
    if !(4..=5).contains(&parts.len()) {
        return Err(format!("expected m,s,e,d[,shape], got `{v}`"));
    }
    let shape = match parts.get(4).copied().unwrap_or("rect") {
        "rect" => Shape::Rect,
        "cross" => Shape::Cross,
        "ellipse" => Shape::Ellipse,
        s => return Err(format!("shape `{s}`: expected rect, cross or ellipse")),
    };
    let num = |s: &str| -> Result<f64, String> {
        s.parse::<f64>()
            .ok()
            .filter(|x| x.is_finite() && *x >= 0.0)
            .ok_or_else(|| format!("`{s}`: expected a number >= 0"))
    };
    let t = Thresholds {
        magnitude: num(parts[0])? as f32,
        sum: num(parts[1])? as f32,
        erode: num(parts[2])? as usize,
        dilate: num(parts[3])? as usize,
        shape,
    };
    t.validate().map_err(|e| e.to_string())?;
    Ok(ThresholdSet {
        name: v.to_string(),
        thresholds: t,
    })
}

fn options(args: &Args) -> SweepOptions {
    SweepOptions {
        sets: args.sets(),
        margin_px: args.margin,
        debug: std::env::var_os("SWEEP_DEBUG").map(|_| DebugLog(|l| eprintln!("{l}"))),
    }
}

fn rest(
    out: &mut Sink,
    stages: &Stages,
    args: &Args,
    sensor: &SyntheticSensor,
) -> Result<(), Failure> {
    let t = Instant::now();
    let r = rest_sweep(sensor, &options(args), args.rest, &|s, d, n| {
        stages.update(s, d, n)
    })?;
    stages.finish();
    writeln!(
        out,
        "### False contacts at rest ({} rest pairs, seed {})\n",
        args.rest, args.seed
    )?;
    writeln!(
        out,
        "Peak |flow| per rest pair (full-resolution px): median {:.3}, 99th percentile {:.3}, max {:.3}.\n",
        r.peak_quantile(0.5),
        r.peak_quantile(0.99),
        r.peak_quantile(1.0)
    )?;
    writeln!(
        out,
        "| thresholds | frames with a false contact | false patches | largest contour sum at rest |"
    )?;
    writeln!(out, "|---|---|---|---|")?;
    for (i, set) in args.sets().iter().enumerate() {
        writeln!(
            out,
            "| {} | {} / {} | {} | {:.0} |",
            set.name, r.false_frames[i], args.rest, r.false_patches[i], r.max_contour_sum[i]
        )?;
    }
    eprintln!("rest: {:.1} s", t.elapsed().as_secs_f64());
    writeln!(out)?;
    Ok(())
}

fn mdf(
    out: &mut Sink,
    stages: &Stages,
    args: &Args,
    sensor: &SyntheticSensor,
) -> Result<(), Failure> {
    let t = Instant::now();
    let plan = MdfPlan {
        positions_mm: args.positions.0.clone(),
        forces_n: args.forces.0.clone(),
    };
    let r = mdf_sweep(sensor, &options(args), &plan, &|s, d, n| {
        stages.update(s, d, n)
    })?;
    stages.finish();
    writeln!(
        out,
        "### Minimum detectable force ({} positions x {} tilts per indenter and force, seed {})\n",
        args.positions.0.len(),
        TILTS_DEG.len(),
        args.seed
    )?;
    writeln!(
        out,
        "Smallest force of the ladder from which >= 95% of presses are detected (a patch covering the rod).\n"
    )?;
    writeln!(
        out,
        "| thresholds | 2 mm | 5 mm | 10 mm | all indenters | every press (100%) from | patches away from the rod |"
    )?;
    writeln!(out, "|---|---|---|---|---|---|---|")?;
    let fmt = |v: Option<f64>| v.map_or("> ladder".to_string(), |f| format!("{f:.1} N"));
    for (k, set) in args.sets().iter().enumerate() {
        writeln!(
            out,
            "| {} | {} | {} | {} | **{}** | {} | {} |",
            set.name,
            fmt(r.min_force(k, Some(0), 0.95)),
            fmt(r.min_force(k, Some(1), 0.95)),
            fmt(r.min_force(k, Some(2), 0.95)),
            fmt(r.min_force(k, None, 0.95)),
            fmt(r.min_force(k, None, 1.0)),
            r.stray[k]
        )?;
    }
    writeln!(out, "\nDetection rate per force (all indenters):\n")?;
    write!(out, "| thresholds |")?;
    for f in &args.forces.0 {
        write!(out, " {f:.1} N |")?;
    }
    writeln!(out)?;
    write!(out, "|---|")?;
    for _ in &args.forces.0 {
        write!(out, "---|")?;
    }
    writeln!(out)?;
    for (k, set) in args.sets().iter().enumerate() {
        write!(out, "| {} |", set.name)?;
        for fi in 0..args.forces.0.len() {
            write!(out, " {:.0}% |", 100.0 * r.rate(k, fi))?;
        }
        writeln!(out)?;
    }
    writeln!(out)?;
    eprintln!("mdf: {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn spacing(
    out: &mut Sink,
    stages: &Stages,
    args: &Args,
    sensor: &SyntheticSensor,
) -> Result<(), Failure> {
    let t = Instant::now();
    let plan = SpacingPlan {
        spacings_mm: args.spacings.0.clone(),
        forces_n: args.spacing_forces.0.clone(),
        second_force_ratio: args.ratio,
        centres_mm: args.spacing_centres.0.clone(),
        tol_mm: args.tol_mm,
    };
    let r = spacing_sweep(sensor, &options(args), &plan, &|s, d, n| {
        stages.update(s, d, n)
    })?;
    stages.finish();
    let nc = args.spacing_centres.0.len();
    writeln!(
        out,
        "### Two-rod spacing sweep (straight presses, the second at {} times the first's force, \
         midpoints at {:?} mm, seed {})\n",
        args.ratio, args.spacing_centres.0, args.seed
    )?;
    writeln!(
        out,
        "Told apart = exactly two contacts, each within {} mm of its rod, at every midpoint. \
         Smallest spacing from which every larger spacing of the list is told apart:\n",
        args.tol_mm
    )?;
    let columns = || {
        let mut s = String::new();
        for &d in &INDENTERS_MM {
            for &f in &args.spacing_forces.0 {
                s += &format!(" {d} mm, {f} N |");
            }
        }
        s
    };
    let rule = "---|".repeat(INDENTERS_MM.len() * args.spacing_forces.0.len());
    writeln!(out, "| thresholds |{}", columns())?;
    writeln!(out, "|---|{rule}")?;
    for (k, set) in args.sets().iter().enumerate() {
        write!(out, "| {} |", set.name)?;
        for ii in 0..INDENTERS_MM.len() {
            for fi in 0..args.spacing_forces.0.len() {
                match r.min_spacing(k, ii, Some(fi), None) {
                    Some(s) => write!(out, " {s} mm |")?,
                    None => write!(out, " > {} mm |", args.spacings.0[0])?,
                }
            }
        }
        writeln!(out)?;
    }
    writeln!(
        out,
        "\nPairs told apart per spacing (out of {nc} midpoints), indenter/force in the column order above:\n"
    )?;
    writeln!(out, "| thresholds | spacing |{}", columns())?;
    writeln!(out, "|---|---|{rule}")?;
    for (k, set) in args.sets().iter().enumerate() {
        for (si, sp) in args.spacings.0.iter().enumerate() {
            write!(out, "| {} | {sp} mm |", set.name)?;
            for ii in 0..INDENTERS_MM.len() {
                for fi in 0..args.spacing_forces.0.len() {
                    write!(out, " {} |", r.count(k, ii, fi, si))?;
                }
            }
            writeln!(out)?;
        }
    }
    writeln!(out)?;
    eprintln!("spacing: {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn run(args: &Args) -> Result<(), Failure> {
    let mut out = Sink::stdout();
    let stages = Stages::new(args.quiet);
    let sensor = SyntheticSensor::new(SimConfig::default(), args.seed)?;
    writeln!(
        out,
        "| thresholds | magnitude (px) | sum (px^3) | erode | dilate | shape |"
    )?;
    writeln!(out, "|---|---|---|---|---|---|")?;
    for set in &args.sets() {
        let t = &set.thresholds;
        writeln!(
            out,
            "| {} | {} | {} | {} | {} | {:?} |",
            set.name, t.magnitude, t.sum, t.erode, t.dilate, t.shape
        )?;
    }
    writeln!(out)?;
    let m = args.mode;
    if matches!(m, Mode::All | Mode::Rest) {
        rest(&mut out, &stages, args, &sensor)?;
    }
    if matches!(m, Mode::All | Mode::Mdf) {
        mdf(&mut out, &stages, args, &sensor)?;
    }
    if matches!(m, Mode::All | Mode::Spacing) {
        spacing(&mut out, &stages, args, &sensor)?;
    }
    Ok(())
}

fn main() -> ExitCode {
    cli_support::finish(run(&Args::parse()).map(|()| ExitCode::SUCCESS))
}
