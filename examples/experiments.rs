//! The paper's "Sensor Performance" section on the simulator, in one
//! command, printed as markdown with the paper's figures and our targets
//! (docs/results.md) side by side:
//!
//! - Table I (per threshold preset low/mid/high: minimum detectable force and
//!   test MAE of x, Fx, Fy, Fz) and Table II (per test point), from a
//!   simulated characterization run written to `--out DIR` and fitted with
//!   `characterize::{extract_dataset, fit_dataset}` as `calibrate` does;
//! - the minimum spacing at which two contacts are told apart, per indenter
//!   and preset (`sim::experiments::spacing_sweep`);
//! - the minimum detectable force per preset over a finer force ladder, and
//!   false contacts on rest frames (`mdf_sweep`, `rest_sweep`);
//! - the touch-mapping error per rod over 5 runs with different seeds
//!   (`mapping_run`: the `mapping` scenario, a `TactileSensor` with the
//!   `high` calibration fitted here, `optical_tactile_sim::mapping`'s clustering).
//!
//! ```text
//! cargo run --release --example experiments -- [--out DIR] [--quick] [--json FILE]
//!     [--seed N] [--subset N] [--quiet]
//! ```
//!
//! `--quick` uses small subsets (about 1-2 minutes); the full run takes
//! about 10-20 minutes on 2 cores. A progress bar per stage, with an ETA,
//! shows on a terminal (`--quiet` hides it). `--json -` writes the report as
//! JSON to stdout and the markdown to stderr.

#[path = "cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use cli_support::{Failure, Sink, Stages, TextOut};
use serde::Serialize;

use optical_tactile::calibration::Calibration;
use optical_tactile::calibration::fit::FitOptions;
use optical_tactile::calibration::fit::{
    LoadCellSpread, extract_dataset, fit_dataset, load_cell_spread, read_dataset,
};
use optical_tactile::calibration::report::{DetectionLimit, PointTable, QuantityMae};
use optical_tactile::contact::ContactPointMethod;
use optical_tactile::frame::Roi;
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::io;
use optical_tactile::segment::Thresholds;
use optical_tactile::sensor::ExtractorConfig;
use optical_tactile_sim::experiments::{
    INDENTERS_MM, MappingOptions, MappingRun, MdfPlan, MdfResult, RestResult, SpacingPlan,
    SpacingResult, SweepOptions, TILTS_DEG, mapping_run, mdf_sweep, rest_sweep, spacing_sweep,
};
use optical_tactile_sim::scenario::{self, Characterization, Common, Scenario};
use optical_tactile_sim::{SimConfig, SyntheticSensor};

/// The paper's "Sensor Performance" section on the simulator, printed as
/// markdown beside the paper's figures and our targets: Tables I and II from
/// a simulated characterization, the minimum spacing of two contacts, the
/// minimum detectable force, false contacts at rest, and the touch-mapping
/// error.
#[derive(Parser, Debug)]
#[command(name = "experiments")]
struct Args {
    /// Folder for the simulated data.
    #[arg(long, value_name = "DIR", default_value_os_t = std::env::temp_dir().join("optical-tactile-experiments"))]
    out: PathBuf,
    /// Small subsets (about 1-2 minutes instead of 10-20 on 2 cores).
    #[arg(long)]
    quick: bool,
    /// Write the report as JSON to FILE, or to stdout with `-` (the markdown
    /// then goes to stderr).
    #[arg(long, value_name = "FILE|-")]
    json: Option<TextOut>,
    /// Simulator seed (the mapping runs take this one and the next four).
    #[arg(long, value_name = "N", default_value_t = 1)]
    seed: u64,
    /// Characterization tests [default: 2500, 300 with --quick].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(50..))]
    subset: Option<u64>,
    /// No progress bars.
    #[arg(long, short)]
    quiet: bool,
}

/// What the run measures, by mode.
struct Plan {
    subset: usize,
    rest_pairs: usize,
    mdf: MdfPlan,
    spacing: SpacingPlan,
}

impl Plan {
    fn new(a: &Args) -> Plan {
        if a.quick {
            Plan {
                subset: a.subset.map_or(300, |n| n as usize),
                rest_pairs: 60,
                mdf: MdfPlan {
                    positions_mm: vec![-80.0, 0.0, 80.0],
                    forces_n: (1..=10).map(|k| k as f64 / 5.0).collect(),
                },
                spacing: SpacingPlan {
                    spacings_mm: vec![40.0, 30.0, 25.0, 20.0, 15.0, 10.0],
                    forces_n: vec![1.5],
                    second_force_ratio: 1.0,
                    centres_mm: vec![0.0],
                    tol_mm: 3.0,
                },
            }
        } else {
            Plan {
                subset: a.subset.map_or(2500, |n| n as usize),
                rest_pairs: 1500,
                mdf: MdfPlan::default(),
                spacing: SpacingPlan::default(),
            }
        }
    }
}

/// The paper's figures (real sensor) and the aim (docs/results.md).
mod bar {
    /// Table I per preset low/mid/high: F_min text, x mm, Fx, Fy, Fz N.
    pub const TABLE_I: [(&str, [f64; 4]); 3] = [
        ("(0, 0.5)", [1.4, 0.071, 0.024, 0.169]),
        ("[0.5, 1)", [1.5, 0.074, 0.024, 0.166]),
        ("[1, 1.5)", [1.5, 0.070, 0.026, 0.172]),
    ];
    /// The paper's F_min ranges per preset, N: `[lo, hi)`.
    pub const FMIN_RANGE: [(f64, f64); 3] = [(0.0, 0.5), (0.5, 1.0), (1.0, 1.5)];
    /// Table II (high thresholds): Total, point 5, 8, 11; rows x, Fx, Fy, Fz.
    pub const TABLE_II: [[f64; 4]; 4] = [
        [1.5, 1.8, 1.0, 1.6],
        [0.070, 0.059, 0.074, 0.078],
        [0.026, 0.026, 0.024, 0.029],
        [0.172, 0.103, 0.196, 0.230],
    ];
    /// Our aim: x mm, Fx, Fy, Fz N.
    pub const TARGET: [f64; 4] = [0.5, 0.02, 0.005, 0.05];
    /// Aim for the minimum detectable force with the low preset, N.
    pub const TARGET_MDF_LOW: f64 = 0.3;
    /// Aim for the spacing at which two contacts are told apart, mm.
    pub const TARGET_SPACING: f64 = 15.0;
    /// Aim for the worst mapping error per obstacle, m.
    pub const TARGET_MAPPING_M: f64 = 0.002;
    /// The paper's minimum spacing per indenter (2, 5, 10 mm).
    pub const SPACING: [f64; 3] = [20.0, 40.0, 40.0];
}

/// Touch-mapping runs, seeds `--seed` .. `--seed + 4`.
const MAPPING_RUNS: u64 = 5;

const PRESETS: [(&str, Thresholds); 3] = [
    ("low", Thresholds::LOW),
    ("mid", Thresholds::MID),
    ("high", Thresholds::HIGH),
];
const VARS: [&str; 4] = ["MAE x3D [mm]", "MAE Fx [N]", "MAE Fy [N]", "MAE Fz [N]"];

fn maes(m: &QuantityMae) -> [f64; 4] {
    [m.x_mm, m.fx, m.fy, m.fz]
}

fn met(ok: bool) -> &'static str {
    if ok { "met" } else { "**NOT met**" }
}

/// One preset's characterization fit.
#[derive(Serialize)]
struct PresetFit {
    preset: String,
    thresholds: Thresholds,
    /// From the characterization's force levels (0.5..3 N).
    min_force: DetectionLimit,
    /// Tests without a detected contact, train/val/test.
    misses: [usize; 4],
    test: PointTable,
    seconds: f64,
    #[serde(skip)]
    calibration: Calibration,
}

#[derive(Serialize)]
struct Report {
    quick: bool,
    seed: u64,
    characterization_tests: usize,
    characterization: Vec<PresetFit>,
    /// The load cell's scatter between repetitions of a test (`None`: no
    /// repetitions in the subset).
    load_cell: Option<LoadCellSpread>,
    rest: RestResult,
    mdf: MdfResult,
    spacing: SpacingResult,
    mapping: Vec<MappingRun>,
    wall_s: f64,
}

fn characterization(
    a: &Args,
    plan: &Plan,
    stages: &Stages,
) -> optical_tactile::Result<(usize, Vec<PresetFit>, Option<LoadCellSpread>)> {
    let dir = a.out.join("characterization");
    let mut common = Common::new(&dir);
    common.seed = a.seed;
    common.flow = false;
    eprintln!(
        "[characterization] rendering {} tests into {}",
        plan.subset,
        dir.display()
    );
    scenario::run_with_progress(
        &Scenario::Characterization(Characterization {
            subset: Some(plan.subset),
            ..Default::default()
        }),
        &common,
        &|_, d, n| stages.update("characterization, rendering", d, n),
    )?;
    let rows = read_dataset(&dir)?;
    let img = io::read_gray(dir.join(&rows[0].reference))?;
    let crop = Roi::full(img.ncols(), img.nrows());
    let mut fits = Vec::new();
    for (name, thresholds) in PRESETS {
        let t = Instant::now();
        let config = ExtractorConfig::default().with_thresholds(thresholds);
        let stage = format!("characterization, {name}");
        let ex = extract_dataset(
            &dir,
            &rows,
            &config,
            ContactPointMethod::DEFAULT,
            None,
            &|d, n| stages.update(&stage, d, n),
        )?;
        // As `calibrate` does by default on the strip.
        let options = FitOptions::for_geometry(&SensorGeometry::default());
        let fit = fit_dataset(
            &ex,
            &config,
            ContactPointMethod::DEFAULT,
            crop,
            SensorGeometry::default(),
            &options,
        )?;
        fits.push(PresetFit {
            preset: name.to_string(),
            thresholds,
            min_force: fit.min_force,
            misses: fit.misses,
            test: fit.test_table,
            calibration: fit.calibration,
            seconds: t.elapsed().as_secs_f64(),
        });
    }
    Ok((rows.len(), fits, load_cell_spread(&rows)))
}

fn print_table_i(out: &mut Sink, fits: &[PresetFit], tests: usize) -> std::io::Result<()> {
    writeln!(out, "## Table I: test-set errors per threshold preset\n")?;
    writeln!(
        out,
        "Simulated characterization, {tests} tests (a random subset of the protocol's 7200), \
         each preset's own calibration fitted on its detections. Paper = real sensor (Table I); \
         target = our aim (docs/results.md).\n"
    )?;
    write!(out, "| Variable |")?;
    for f in fits {
        write!(out, " {} (ours) | {} (paper) |", f.preset, f.preset)?;
    }
    writeln!(out, " target |")?;
    writeln!(out, "|---|{}---|", "---|---|".repeat(fits.len()))?;
    write!(out, "| F_min [N] |")?;
    for (k, f) in fits.iter().enumerate() {
        write!(out, " {} | {} |", f.min_force, bar::TABLE_I[k].0)?;
    }
    writeln!(out, " <= 0.3 (low) |")?;
    for (v, name) in VARS.iter().enumerate() {
        write!(out, "| {name} |")?;
        for (k, f) in fits.iter().enumerate() {
            let ours = maes(&f.test.total)[v];
            write!(
                out,
                " {} ({}) | {} |",
                fmt4(ours),
                met(ours <= bar::TARGET[v]),
                paper_fmt(v, bar::TABLE_I[k].1[v])
            )?;
        }
        writeln!(out, " <= {} |", bar::TARGET[v])?;
    }
    write!(out, "| test samples (misses) |")?;
    for f in fits {
        write!(out, " {} ({}) | |", f.test.total.n, f.misses[2])?;
    }
    writeln!(out, " |\n")?;
    writeln!(
        out,
        "F_min here is on the protocol's force levels (0.5, 1, ..., 3 N): the smallest \
         level from which >= 95% of the tests at each level are detected. The finer ladder \
         below measures it to 0.1-0.2 N.\n"
    )?;
    Ok(())
}

/// A paper figure as the paper prints it: x in mm to 0.1, forces to 0.001 N.
fn paper_fmt(var: usize, x: f64) -> String {
    if var == 0 {
        format!("{x:.1}")
    } else {
        format!("{x:.3}")
    }
}

fn fmt4(x: f64) -> String {
    if x >= 0.1 {
        format!("{x:.2}")
    } else {
        format!("{x:.4}")
    }
}

fn print_table_ii(out: &mut Sink, f: &PresetFit) -> std::io::Result<()> {
    writeln!(
        out,
        "## Table II: test-set errors per point ({} thresholds, the paper's flight setting)\n",
        f.preset
    )?;
    let mut cols: Vec<(String, &QuantityMae)> = vec![("Total".into(), &f.test.total)];
    cols.extend(
        f.test
            .per_point
            .iter()
            .map(|(p, m)| (format!("Point {p}"), m)),
    );
    write!(out, "| Variable |")?;
    for (name, _) in &cols {
        write!(out, " {name} ours | paper |")?;
    }
    writeln!(out)?;
    writeln!(out, "|---|{}", "---|---|".repeat(cols.len()))?;
    for (v, name) in VARS.iter().enumerate() {
        write!(out, "| {name} |")?;
        for (c, (_, m)) in cols.iter().enumerate() {
            let paper = bar::TABLE_II[v]
                .get(c)
                .map_or("-".to_string(), |&p| paper_fmt(v, p));
            write!(out, " {} | {paper} |", fmt4(maes(m)[v]))?;
        }
        writeln!(out)?;
    }
    write!(out, "| samples |")?;
    for (_, m) in &cols {
        write!(out, " {} | |", m.n)?;
    }
    writeln!(out, "\n")?;
    Ok(())
}

fn print_rest_mdf(out: &mut Sink, rest: &RestResult, mdf: &MdfResult) -> std::io::Result<()> {
    writeln!(
        out,
        "## Minimum detectable force and false contacts at rest\n"
    )?;
    writeln!(
        out,
        "Single rods at {} arc positions ({:?} mm) x the protocol's {} tilts per indenter, \
         force ladder {:.1}..{:.1} N; MDF = smallest ladder force from which >= 95% of \
         the presses of every indenter are detected (a patch covering the rod). Rest: {} \
         pairs of unloaded frames with fresh noise and flicker; any patch is a false contact.\n",
        mdf.plan.positions_mm.len(),
        mdf.plan.positions_mm,
        TILTS_DEG.len(),
        mdf.plan.forces_n[0],
        mdf.plan.forces_n[mdf.plan.forces_n.len() - 1],
        rest.pairs
    )?;
    writeln!(
        out,
        "| preset | MDF ours (>= 95%) | every press from | paper | in the paper's range | false contacts at rest | target |"
    )?;
    writeln!(out, "|---|---|---|---|---|---|---|")?;
    let fmt = |v: Option<f64>| v.map_or("> ladder".to_string(), |f| format!("{f:.1} N"));
    for (k, set) in mdf.sets.iter().enumerate() {
        let m = mdf.min_force(k, None, 0.95);
        let (lo, hi) = bar::FMIN_RANGE[k.min(2)];
        let in_range = m.is_some_and(|m| m >= lo && m < hi);
        let target = if k == 0 {
            format!(
                "<= {} N, no false contact: {}",
                bar::TARGET_MDF_LOW,
                met(m.is_some_and(|m| m <= bar::TARGET_MDF_LOW) && rest.false_frames[k] == 0)
            )
        } else {
            format!("no false contact: {}", met(rest.false_frames[k] == 0))
        };
        writeln!(
            out,
            "| {} | {} | {} | {} | {} | {} / {} | {target} |",
            set.name,
            fmt(m),
            fmt(mdf.min_force(k, None, 1.0)),
            bar::TABLE_I[k.min(2)].0,
            if in_range { "yes" } else { "no" },
            rest.false_frames[k],
            rest.pairs
        )?;
    }
    writeln!(
        out,
        "\nPeak |flow| of a rest pair (full-resolution px): median {:.3}, 99th percentile {:.3}, max {:.3}; \
         largest contour sum at rest per preset: {}.\n",
        rest.peak_quantile(0.5),
        rest.peak_quantile(0.99),
        rest.peak_quantile(1.0),
        mdf.sets
            .iter()
            .zip(&rest.max_contour_sum)
            .map(|(s, v)| format!("{} {v:.0}", s.name))
            .collect::<Vec<_>>()
            .join(", ")
    )?;
    write!(
        out,
        "Detection rate per force (all indenters):\n\n| preset |"
    )?;
    for f in &mdf.plan.forces_n {
        write!(out, " {f:.1} N |")?;
    }
    writeln!(out, "\n|---|{}", "---|".repeat(mdf.plan.forces_n.len()))?;
    for (k, set) in mdf.sets.iter().enumerate() {
        write!(out, "| {} |", set.name)?;
        for fi in 0..mdf.plan.forces_n.len() {
            write!(out, " {:.0}% |", 100.0 * mdf.rate(k, fi))?;
        }
        writeln!(out)?;
    }
    writeln!(out)?;
    Ok(())
}

fn print_spacing(out: &mut Sink, sp: &SpacingResult) -> std::io::Result<()> {
    let p = &sp.plan;
    writeln!(out, "## Two contacts: minimum spacing\n")?;
    writeln!(
        out,
        "Two straight rods of equal force ({:?} N) at spacings {:?} mm around midpoints {:?} mm; \
         told apart = exactly two contacts, each within {} mm of its rod. Minimum spacing = \
         smallest spacing of the list from which every larger one is told apart at every force \
         and midpoint (`> {}` = not even the largest).\n",
        p.forces_n, p.spacings_mm, p.centres_mm, p.tol_mm, p.spacings_mm[0]
    )?;
    let centre = p.centres_mm.iter().position(|&c| c == 0.0);
    let fmt =
        |v: Option<f64>| v.map_or(format!("> {} mm", p.spacings_mm[0]), |s| format!("{s} mm"));
    write!(out, "| preset |")?;
    for d in INDENTERS_MM {
        write!(out, " {d} mm indenter |")?;
        if centre.is_some() && p.centres_mm.len() > 1 {
            write!(out, " {d} mm, midpoint 0 only |")?;
        }
    }
    writeln!(out)?;
    let per = if centre.is_some() && p.centres_mm.len() > 1 {
        2
    } else {
        1
    };
    writeln!(out, "|---|{}", "---|".repeat(per * INDENTERS_MM.len()))?;
    for (k, set) in sp.sets.iter().enumerate() {
        write!(out, "| {} |", set.name)?;
        for ii in 0..INDENTERS_MM.len() {
            let all = sp.min_spacing(k, ii, None, None);
            write!(
                out,
                " {} ({}) |",
                fmt(all),
                met(all.is_some_and(|s| s <= bar::TARGET_SPACING))
            )?;
            if per == 2 {
                write!(out, " {} |", fmt(sp.min_spacing(k, ii, None, centre)))?;
            }
        }
        writeln!(out)?;
    }
    write!(out, "| paper (real sensor) |")?;
    for ii in 0..INDENTERS_MM.len() {
        write!(out, " {} mm |", bar::SPACING[ii])?;
        if per == 2 {
            write!(out, " |")?;
        }
    }
    writeln!(out)?;
    writeln!(
        out,
        "\nTarget: <= {} mm for every indenter; the paper's method reproduced in Python: \
         30-40 mm (high).\n",
        bar::TARGET_SPACING
    )?;
    Ok(())
}

fn print_summary(
    out: &mut Sink,
    fits: &[PresetFit],
    load_cell: Option<&LoadCellSpread>,
    rest: &RestResult,
    mdf: &MdfResult,
    sp: &SpacingResult,
    mapping: &[MappingRun],
) -> std::io::Result<()> {
    writeln!(out, "## Summary: the bar the paper sets\n")?;
    writeln!(
        out,
        "| quantity | paper (real sensor) | paper's method in Python | our aim | ours | |"
    )?;
    writeln!(out, "|---|---|---|---|---|---|")?;
    if let Some(high) = fits.iter().find(|f| f.preset == "high") {
        let m = maes(&high.test.total);
        writeln!(
            out,
            "| contact location MAE (high) | 1.5 mm | 1.55 mm | <= 0.5 mm | {:.2} mm | {} |",
            m[0],
            met(m[0] <= bar::TARGET[0])
        )?;
        writeln!(
            out,
            "| Fx / Fy / Fz MAE (high) | 0.070 / 0.026 / 0.172 N | 0.038 / 0.008 / 0.121 N | <= 0.02 / 0.005 / 0.05 N | {} / {} / {} N | {} |",
            fmt4(m[1]),
            fmt4(m[2]),
            fmt4(m[3]),
            ["Fx", "Fy", "Fz"]
                .iter()
                .enumerate()
                .map(|(i, n)| format!("{n} {}", met(m[i + 1] <= bar::TARGET[i + 1])))
                .collect::<Vec<_>>()
                .join(", ")
        )?;
    }
    if let Some(s) = load_cell {
        let [x, y, z] = s.mae_floor_n();
        writeln!(
            out,
            "| the load cell's floor: an exact sensor's Fx / Fy / Fz MAE against its readings | | | | {} / {} / {} N | |",
            fmt4(x),
            fmt4(y),
            fmt4(z)
        )?;
    }
    let low = mdf.min_force(0, None, 0.95);
    writeln!(
        out,
        "| minimum detectable force (low) | < 0.5 N | 0.4 N | <= 0.3 N, no false contact at rest | {}, {} / {} rest pairs with a false contact | {} |",
        low.map_or("> ladder".into(), |f| format!("{f:.1} N")),
        rest.false_frames[0],
        rest.pairs,
        met(low.is_some_and(|f| f <= bar::TARGET_MDF_LOW) && rest.false_frames[0] == 0)
    )?;
    if let Some(high) = mdf.sets.iter().position(|s| s.name == "HIGH") {
        let h = mdf.min_force(high, None, 0.95);
        writeln!(
            out,
            "| minimum detectable force (high) | 1-1.5 N | 1.2-1.4 N | 1-1.5 N | {} | {} |",
            h.map_or("> ladder".into(), |f| format!("{f:.1} N")),
            met(h.is_some_and(|f| (1.0..1.5).contains(&f)))
        )?;
    }
    // Per indenter, the best preset at every force and midpoint, and (if the
    // plan has it) at the skin's centre only.
    let centre = sp.plan.centres_mm.iter().position(|&c| c == 0.0);
    let best = |ii: usize, c: Option<usize>| -> (Option<f64>, String) {
        let all: Vec<Option<f64>> = (0..sp.sets.len())
            .map(|k| sp.min_spacing(k, ii, None, c))
            .collect();
        let b = all.iter().copied().flatten().min_by(f64::total_cmp);
        let names: Vec<&str> = (0..sp.sets.len())
            .filter(|&k| b.is_some() && all[k] == b)
            .map(|k| sp.sets[k].name.as_str())
            .collect();
        (
            b,
            if b.is_some() {
                names.join(", ")
            } else {
                "every preset".into()
            },
        )
    };
    let over = |s: Option<f64>| {
        s.map_or(format!("> {} mm", sp.plan.spacings_mm[0]), |s| {
            format!("{s} mm")
        })
    };
    let mut cells = Vec::new();
    let mut ok = true;
    for (ii, d) in INDENTERS_MM.iter().enumerate() {
        let (b, who) = best(ii, None);
        ok &= b.is_some_and(|s| s <= bar::TARGET_SPACING);
        let mut cell = format!("{d} mm: {} ({who})", over(b));
        if let Some(c) = centre.filter(|_| sp.plan.centres_mm.len() > 1) {
            let (bc, whoc) = best(ii, Some(c));
            cell += &format!(", at the centre only {} ({whoc})", over(bc));
        }
        cells.push(cell);
    }
    writeln!(
        out,
        "| two contacts told apart at (best preset, every midpoint {:?} mm) | 20 / 40 / 40 mm | 30-40 mm | <= 15 mm | {} | {} |",
        sp.plan.centres_mm,
        cells.join("; "),
        met(ok)
    )?;
    let (mean, worst) = mapping_summary(mapping);
    writeln!(
        out,
        "| mapping by touch, error per obstacle ({} runs) | < 40 mm | mean 0.8 mm, worst 9 mm | worst <= 2 mm | mean {}, worst {} | {} |",
        mapping.len(),
        mean.map_or("-".into(), |m| format!("{:.1} mm", m * 1e3)),
        worst.map_or("a rod missed".into(), |w| format!("{:.1} mm", w * 1e3)),
        met(worst.is_some_and(|w| w <= bar::TARGET_MAPPING_M))
    )?;
    writeln!(out)?;
    Ok(())
}

fn print_mapping(out: &mut Sink, runs: &[MappingRun], o: &MappingOptions) -> std::io::Result<()> {
    writeln!(
        out,
        "## Mapping by touch: error per obstacle over {} runs\n",
        runs.len()
    )?;
    writeln!(
        out,
        "The simulator's `mapping` scenario (rods along world y at x = {:?} m, {} touches per rod at \
         random places on the skin, up to {} N, {} mm rods), one seed per run; the `high` calibration \
         fitted above in a `TactileSensor` (frame 0 as reference); the contacts detected in each \
         frame (not those the tracker holds), from {} N, into the world frame with the frame's pose, \
         single-linkage clusters of radius {} m (`mapping::map_touches`, the `touch_mapping` \
         example's defaults), matched one to one with the true rods within {} m \
         (`mapping::match_rods`). Error = distance of a cluster's centre from its rod's line.\n",
        o.scenario.rods_x_m,
        o.scenario.touches,
        o.scenario.force_n,
        o.scenario.indenter_mm,
        o.map.min_force_n,
        o.map.radius_m,
        o.gate_m
    )?;
    write!(out, "| seed | contacts | clusters | false clusters |")?;
    for k in 0..o.scenario.rods_x_m.len() {
        write!(out, " rod {} [mm] |", k + 1)?;
    }
    writeln!(out, " worst [mm] |")?;
    writeln!(
        out,
        "|---|---|---|---|{}---|",
        "---|".repeat(o.scenario.rods_x_m.len())
    )?;
    let mm = |e: Option<f64>| e.map_or("missed".to_string(), |e| format!("{:.1}", e * 1e3));
    let mm_unit =
        |e: Option<f64>| e.map_or("a rod missed".to_string(), |e| format!("{:.1} mm", e * 1e3));
    for r in runs {
        write!(
            out,
            "| {} | {} | {} | {} |",
            r.seed,
            r.contacts,
            r.clusters.len(),
            r.false_clusters
        )?;
        for e in &r.errors_m {
            write!(out, " {} |", mm(*e))?;
        }
        writeln!(out, " {} |", mm(r.worst_m()))?;
    }
    let (mean, worst) = mapping_summary(runs);
    writeln!(
        out,
        "\nOver all runs: mean {}, worst {} (paper: < 40 mm; the paper's method in Python: mean 0.8 mm, \
         worst 9 mm; our aim: worst <= 2 mm: {}).\n",
        mean.map_or("-".into(), |m| format!("{:.1} mm", m * 1e3)),
        mm_unit(worst),
        met(worst.is_some_and(|w| w <= bar::TARGET_MAPPING_M))
    )?;
    Ok(())
}

/// Mean over every found rod of every run, and the worst (`None` if a rod
/// was missed in some run).
fn mapping_summary(runs: &[MappingRun]) -> (Option<f64>, Option<f64>) {
    let all: Vec<Option<f64>> = runs.iter().flat_map(|r| r.errors_m.clone()).collect();
    let found: Vec<f64> = all.iter().flatten().copied().collect();
    let mean = (!found.is_empty()).then(|| found.iter().sum::<f64>() / found.len() as f64);
    let worst = all.iter().try_fold(0.0f64, |m, e| e.map(|e| m.max(e)));
    (mean, worst)
}

fn run(a: &Args) -> Result<(), Failure> {
    let err = |e: optical_tactile::Error| e.to_string();
    let mut out = Sink::report(a.json.as_ref().is_some_and(TextOut::is_stdout));
    let stages = Stages::new(a.quiet);
    let t0 = Instant::now();
    let plan = Plan::new(a);
    eprintln!(
        "experiments: {} mode, seed {}, {} threads, output in {}",
        if a.quick { "quick" } else { "full" },
        a.seed,
        rayon::current_num_threads(),
        a.out.display()
    );
    let (tests, fits, load_cell) = characterization(a, &plan, &stages).map_err(err)?;
    stages.finish();
    let sensor = SyntheticSensor::new(SimConfig::default(), a.seed).map_err(err)?;
    let o = SweepOptions::default();
    let progress = |stage: &str, d: usize, n: usize| stages.update(stage, d, n);
    // Each stage's bar is finished before the next starts (and left on
    // screen); on an error the bars are dropped, which leaves them too.
    let rest = rest_sweep(&sensor, &o, plan.rest_pairs, &progress).map_err(err)?;
    stages.finish();
    let mdf = mdf_sweep(&sensor, &o, &plan.mdf, &progress).map_err(err)?;
    stages.finish();
    let spacing = spacing_sweep(&sensor, &o, &plan.spacing, &progress).map_err(err)?;
    stages.finish();
    let mapping_options = MappingOptions::default();
    let high = fits
        .iter()
        .find(|f| f.preset == "high")
        .ok_or("no high calibration")?;
    let mut mapping = Vec::new();
    for k in 0..MAPPING_RUNS {
        let seed = a.seed + k;
        let dir = a.out.join(format!("mapping/seed{seed}"));
        mapping.push(mapping_run(&high.calibration, seed, &dir, &mapping_options).map_err(err)?);
        progress("mapping", k as usize + 1, MAPPING_RUNS as usize);
    }
    stages.finish();
    let wall = t0.elapsed().as_secs_f64();

    writeln!(
        out,
        "# Sensor performance on the simulator ({} run, seed {})\n",
        if a.quick { "quick" } else { "full" },
        a.seed
    )?;
    writeln!(
        out,
        "Simulator defaults (1600 x 200 px strip, 5 px/mm), `{}` DIS flow (the sensor's default), \
         extractor margin {} px. Wall time {:.0} s on {} threads.\n",
        optical_tactile::calibration::fit::preset_name(&ExtractorConfig::default()),
        o.margin_px,
        wall,
        rayon::current_num_threads()
    )?;
    print_summary(
        &mut out,
        &fits,
        load_cell.as_ref(),
        &rest,
        &mdf,
        &spacing,
        &mapping,
    )?;
    print_table_i(&mut out, &fits, tests)?;
    if let Some(high) = fits.iter().find(|f| f.preset == "high") {
        print_table_ii(&mut out, high)?;
    }
    print_rest_mdf(&mut out, &rest, &mdf)?;
    print_spacing(&mut out, &spacing)?;
    print_mapping(&mut out, &mapping, &mapping_options)?;
    writeln!(
        out,
        "### Presets\n\n| preset | magnitude (px) | sum (px^3) | erode | dilate |\n|---|---|---|---|---|"
    )?;
    for s in &o.sets {
        let t = &s.thresholds;
        writeln!(
            out,
            "| {} | {} | {} | {} | {} |",
            s.name, t.magnitude, t.sum, t.erode, t.dilate
        )?;
    }
    writeln!(out)?;
    if let Some(json) = &a.json {
        let report = Report {
            quick: a.quick,
            seed: a.seed,
            characterization_tests: tests,
            characterization: fits,
            load_cell,
            rest,
            mdf,
            spacing,
            mapping,
            wall_s: wall,
        };
        json.write_json(&report)?;
    }
    Ok(())
}

fn main() -> ExitCode {
    cli_support::finish(run(&Args::parse()).map(|()| ExitCode::SUCCESS))
}
