//! Segmentation experiments on the simulator (issue 5), printed as markdown:
//!
//! - `rest`: false contacts on rest pairs (reference against another unloaded
//!   frame with fresh noise and flicker), per preset;
//! - `mdf`: minimum detectable force per preset and indenter, over positions
//!   along the skin and the five tilts of the characterization protocol;
//! - `spacing`: two rods pressed with equal force at decreasing spacing; told
//!   apart = exactly two contacts, each within `--tol-mm` of its rod.
//!
//! Frames are rendered with the simulator's library API (no PNGs) and go
//! through the sensor's default DIS flow (`fine`) on the extractor's
//! analysis grid, as in [`ContactExtractor`].
//!
//! ```text
//! cargo run --release --example sweep -- all
//! cargo run --release --example sweep -- rest --rest 400
//! cargo run --release --example sweep -- mdf --candidate 0.25,900,5,15
//! ```
//!
//! With `SWEEP_DEBUG=1` in the environment, the missed presses (from 0.8 N)
//! and every spacing case are printed to stderr with their patches and
//! contour boxes (full-resolution px).

use std::time::Instant;

use optical_tactile::segment::Thresholds;
use optical_tactile::segment::morphology::Shape;
use optical_tactile::sensor::ExtractorConfig;
use optical_tactile::{Error, Result};
use optical_tactile_sim::experiments::{
    DebugLog, INDENTERS_MM, MdfPlan, SpacingPlan, SweepOptions, TILTS_DEG, ThresholdSet, mdf_sweep,
    no_progress, rest_sweep, spacing_sweep,
};
use optical_tactile_sim::{SimConfig, SyntheticSensor};

struct Args {
    mode: String,
    seed: u64,
    rest: usize,
    /// Arc positions of the presses, mm from the centre.
    positions: Vec<f64>,
    forces: Vec<f64>,
    spacings: Vec<f64>,
    spacing_forces: Vec<f64>,
    spacing_centres: Vec<f64>,
    tol_mm: f64,
    margin: usize,
    /// Named threshold sets to evaluate (the presets unless `--candidate`).
    sets: Vec<ThresholdSet>,
}

const HELP: &str = "usage: sweep [all|rest|mdf|spacing] [options]
  --seed N            simulator seed (marker layout), default 1
  --rest N            rest pairs, default 200
  --positions a,b,..  arc positions of single presses, mm (default -120,-80,-40,0,40,80,120)
  --forces a,b,..     force ladder, N (default 0.1,0.2,..,2.0)
  --spacings a,b,..   two-rod spacings, mm (default 40,35,30,25,20,17.5,15,12.5,10,7.5,5)
  --spacing-forces    equal force of both rods, N (default 1.5,3)
  --spacing-centres   arc positions of the pair's midpoint, mm (default -60,0,60)
  --tol-mm X          a contact counts for a rod within X mm (default 3)
  --margin PX         patch margin, full-resolution px (default: ExtractorConfig's)
  --candidate m,s,e,d[,shape]  evaluate these thresholds instead of the presets (repeatable)
  --with-presets      also keep the presets when candidates are given";

fn list(s: &str) -> Result<Vec<f64>> {
    s.split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .map_err(|e| Error::param("list", format!("`{t}`: {e}")))
        })
        .collect()
}

fn parse_args() -> Result<Args> {
    let presets = ThresholdSet::presets();
    let mut a = Args {
        mode: "all".into(),
        seed: 1,
        rest: 200,
        positions: vec![-120.0, -80.0, -40.0, 0.0, 40.0, 80.0, 120.0],
        forces: (1..=20).map(|k| k as f64 / 10.0).collect(),
        spacings: vec![
            40.0, 35.0, 30.0, 25.0, 20.0, 17.5, 15.0, 12.5, 10.0, 7.5, 5.0,
        ],
        spacing_forces: vec![1.5, 3.0],
        spacing_centres: vec![-60.0, 0.0, 60.0],
        tol_mm: 3.0,
        margin: ExtractorConfig::default().margin_px,
        sets: Vec::new(),
    };
    let mut with_presets = false;
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut val = |name: &str| it.next().ok_or_else(|| Error::param(name, "missing value"));
        match arg.as_str() {
            "-h" | "--help" => {
                println!("{HELP}");
                std::process::exit(0);
            }
            "all" | "rest" | "mdf" | "spacing" => a.mode = arg.clone(),
            "--seed" => a.seed = num(&val("--seed")?)? as u64,
            "--rest" => a.rest = num(&val("--rest")?)? as usize,
            "--positions" => a.positions = list(&val("--positions")?)?,
            "--forces" => a.forces = list(&val("--forces")?)?,
            "--spacings" => a.spacings = list(&val("--spacings")?)?,
            "--spacing-forces" => a.spacing_forces = list(&val("--spacing-forces")?)?,
            "--spacing-centres" => a.spacing_centres = list(&val("--spacing-centres")?)?,
            "--tol-mm" => a.tol_mm = num(&val("--tol-mm")?)?,
            "--margin" => a.margin = num(&val("--margin")?)? as usize,
            "--with-presets" => with_presets = true,
            "--candidate" => {
                let v = val("--candidate")?;
                let parts: Vec<&str> = v.split(',').collect();
                if parts.len() < 4 {
                    return Err(Error::param("--candidate", "need m,s,e,d[,shape]"));
                }
                let shape = match parts.get(4).copied().unwrap_or("rect") {
                    "rect" => Shape::Rect,
                    "cross" => Shape::Cross,
                    "ellipse" => Shape::Ellipse,
                    s => return Err(Error::param("--candidate", format!("shape `{s}`"))),
                };
                let t = Thresholds {
                    magnitude: num(parts[0])? as f32,
                    sum: num(parts[1])? as f32,
                    erode: num(parts[2])? as usize,
                    dilate: num(parts[3])? as usize,
                    shape,
                };
                t.validate()?;
                a.sets.push(ThresholdSet {
                    name: v.clone(),
                    thresholds: t,
                });
            }
            _ => return Err(Error::param("argument", format!("unknown `{arg}`\n{HELP}"))),
        }
    }
    if a.sets.is_empty() || with_presets {
        let mut sets = presets;
        sets.append(&mut a.sets);
        a.sets = sets;
    }
    Ok(a)
}

fn num(s: &str) -> Result<f64> {
    s.parse::<f64>()
        .map_err(|e| Error::param("number", format!("`{s}`: {e}")))
}

fn options(args: &Args) -> SweepOptions {
    SweepOptions {
        sets: args.sets.clone(),
        margin_px: args.margin,
        debug: std::env::var_os("SWEEP_DEBUG").map(|_| DebugLog(|l| eprintln!("{l}"))),
    }
}

fn rest(args: &Args, sensor: &SyntheticSensor) -> Result<()> {
    let t = Instant::now();
    let r = rest_sweep(sensor, &options(args), args.rest, &no_progress)?;
    println!(
        "### False contacts at rest ({} rest pairs, seed {})\n",
        args.rest, args.seed
    );
    println!(
        "Peak |flow| per rest pair (full-resolution px): median {:.3}, 99th percentile {:.3}, max {:.3}.\n",
        r.peak_quantile(0.5),
        r.peak_quantile(0.99),
        r.peak_quantile(1.0)
    );
    println!(
        "| thresholds | frames with a false contact | false patches | largest contour sum at rest |"
    );
    println!("|---|---|---|---|");
    for (i, set) in args.sets.iter().enumerate() {
        println!(
            "| {} | {} / {} | {} | {:.0} |",
            set.name, r.false_frames[i], args.rest, r.false_patches[i], r.max_contour_sum[i]
        );
    }
    eprintln!("rest: {:.1} s", t.elapsed().as_secs_f64());
    println!();
    Ok(())
}

fn mdf(args: &Args, sensor: &SyntheticSensor) -> Result<()> {
    let t = Instant::now();
    let plan = MdfPlan {
        positions_mm: args.positions.clone(),
        forces_n: args.forces.clone(),
    };
    let r = mdf_sweep(sensor, &options(args), &plan, &no_progress)?;
    println!(
        "### Minimum detectable force ({} positions x {} tilts per indenter and force, seed {})\n",
        args.positions.len(),
        TILTS_DEG.len(),
        args.seed
    );
    println!(
        "Smallest force of the ladder from which >= 95% of presses are detected (a patch covering the rod).\n"
    );
    println!(
        "| thresholds | 2 mm | 5 mm | 10 mm | all indenters | every press (100%) from | patches away from the rod |"
    );
    println!("|---|---|---|---|---|---|---|");
    let fmt = |v: Option<f64>| v.map_or("> ladder".to_string(), |f| format!("{f:.1} N"));
    for (k, set) in args.sets.iter().enumerate() {
        println!(
            "| {} | {} | {} | {} | **{}** | {} | {} |",
            set.name,
            fmt(r.min_force(k, Some(0), 0.95)),
            fmt(r.min_force(k, Some(1), 0.95)),
            fmt(r.min_force(k, Some(2), 0.95)),
            fmt(r.min_force(k, None, 0.95)),
            fmt(r.min_force(k, None, 1.0)),
            r.stray[k]
        );
    }
    println!("\nDetection rate per force (all indenters):\n");
    print!("| thresholds |");
    for f in &args.forces {
        print!(" {f:.1} N |");
    }
    println!();
    print!("|---|");
    for _ in &args.forces {
        print!("---|");
    }
    println!();
    for (k, set) in args.sets.iter().enumerate() {
        print!("| {} |", set.name);
        for fi in 0..args.forces.len() {
            print!(" {:.0}% |", 100.0 * r.rate(k, fi));
        }
        println!();
    }
    println!();
    eprintln!("mdf: {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn spacing(args: &Args, sensor: &SyntheticSensor) -> Result<()> {
    let t = Instant::now();
    let plan = SpacingPlan {
        spacings_mm: args.spacings.clone(),
        forces_n: args.spacing_forces.clone(),
        centres_mm: args.spacing_centres.clone(),
        tol_mm: args.tol_mm,
    };
    let r = spacing_sweep(sensor, &options(args), &plan, &no_progress)?;
    let nc = args.spacing_centres.len();
    println!(
        "### Two-rod spacing sweep (equal straight presses, midpoints at {:?} mm, seed {})\n",
        args.spacing_centres, args.seed
    );
    println!(
        "Told apart = exactly two contacts, each within {} mm of its rod, at every midpoint. \
         Smallest spacing from which every larger spacing of the list is told apart:\n",
        args.tol_mm
    );
    let columns = || {
        let mut s = String::new();
        for &d in &INDENTERS_MM {
            for &f in &args.spacing_forces {
                s += &format!(" {d} mm, {f} N |");
            }
        }
        s
    };
    let rule = "---|".repeat(INDENTERS_MM.len() * args.spacing_forces.len());
    println!("| thresholds |{}", columns());
    println!("|---|{rule}");
    for (k, set) in args.sets.iter().enumerate() {
        print!("| {} |", set.name);
        for ii in 0..INDENTERS_MM.len() {
            for fi in 0..args.spacing_forces.len() {
                match r.min_spacing(k, ii, Some(fi), None) {
                    Some(s) => print!(" {s} mm |"),
                    None => print!(" > {} mm |", args.spacings[0]),
                }
            }
        }
        println!();
    }
    println!(
        "\nPairs told apart per spacing (out of {nc} midpoints), indenter/force in the column order above:\n"
    );
    println!("| thresholds | spacing |{}", columns());
    println!("|---|---|{rule}");
    for (k, set) in args.sets.iter().enumerate() {
        for (si, sp) in args.spacings.iter().enumerate() {
            print!("| {} | {sp} mm |", set.name);
            for ii in 0..INDENTERS_MM.len() {
                for fi in 0..args.spacing_forces.len() {
                    print!(" {} |", r.count(k, ii, fi, si));
                }
            }
            println!();
        }
    }
    println!();
    eprintln!("spacing: {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn main() -> Result<()> {
    let args = parse_args()?;
    let sensor = SyntheticSensor::new(SimConfig::default(), args.seed)?;
    println!("| thresholds | magnitude (px) | sum (px^3) | erode | dilate | shape |");
    println!("|---|---|---|---|---|---|");
    for set in &args.sets {
        let t = &set.thresholds;
        println!(
            "| {} | {} | {} | {} | {} | {:?} |",
            set.name, t.magnitude, t.sum, t.erode, t.dilate, t.shape
        );
    }
    println!();
    let m = args.mode.as_str();
    if m == "all" || m == "rest" {
        rest(&args, &sensor)?;
    }
    if m == "all" || m == "mdf" {
        mdf(&args, &sensor)?;
    }
    if m == "all" || m == "spacing" {
        spacing(&args, &sensor)?;
    }
    Ok(())
}
