//! The mapping-by-touch demo: touch, move, touch again; every contact is
//! taken into the world frame with the body pose of its frame, and repeated
//! touches are clustered into obstacle estimates.
//!
//! ```text
//! cargo run --release --example touch_mapping -- [SEQ_DIR | --simulate DIR]
//!     [--calibration FILE] [--crop x,y,w,h] [--truth rods.json]
//!     [--json FILE|-] [--png FILE] [--seed N] [--quiet] [--radius-mm R (default 50)]
//!     [--min-force F (default 0.5)] [--gate-mm G (default 100)]
//!     [--mounting default|identity] [--min-count N (default 1)]
//! ```
//!
//! The sequence needs `poses.csv` (docs/formats.md) with a row for every frame
//! that has contacts. The sensor mounting defaults to the simulator's (skin
//! facing down under the body: sensor x = body x, y = -y, z = -z); a truth
//! file's `sensor_in_body_rotation` / `sensor_in_body_offset_m` replace it,
//! and `--mounting identity` makes the sensor frame the body frame.
//! Contacts lighter than `--min-force` N are left out: with the shipped
//! calibration a faint ghost patch (~0.25 N) sometimes appears ~35 mm beside a
//! real 1 N touch and would pull its cluster (the paper's drone filtered with
//! thresholds above 1 N for the same reason). Touches are clustered
//! by single linkage with `--radius-mm` (see `optical_tactile_sim::mapping`);
//! clusters of fewer than `--min-count` touches are dropped (a real obstacle
//! is pressed over several frames; a ghost patch seldom is).
//!
//! With a truth file (the simulator's `rods.json`: rods along world y;
//! default: the one beside the frames, if any) each rod is matched to a
//! cluster (closest first, within `--gate-mm`) and the error per rod is the
//! distance from the cluster's centre to the rod's top line (the line the
//! skin touches).
//!
//! Prints the clusters and the errors as markdown; `--json` writes exactly
//! `{"clusters": [{"x_m", "y_m", "z_m", "count", "spread_m"}]}` (world
//! frame); `--png` draws the world x-z map (touches, clusters, true rods) and
//! a zoom around each rod in mm.
//!
//! With no sequence (or `--simulate DIR`) it first simulates the simulator's
//! `mapping` scenario: five 10 mm rods at world x = 0.4, 0.9, 1.35, 1.9,
//! 2.5 m with tops at 1.0 m, touched twice each at random places on the skin
//! with a 1.5 N press in three steps.

#[path = "cli_support/mod.rs"]
mod cli_support;
#[path = "demo_support/mod.rs"]
mod demo_support;

use std::io::Write as _;
use std::process::ExitCode;

use clap::{Parser, ValueEnum};
use cli_support::Failure;
use demo_support::*;
use optical_tactile::io;
use optical_tactile::viz::{Plot, Rgb, Series, Style};
use optical_tactile_sim::mapping::{
    Cluster, ClusterSummary, MapOptions, Mounting, RodsTruth, TouchMap, map_touches, match_rods,
    poses_by_frame, read_rods_json,
};
use optical_tactile_sim::scenario::{Mapping, Scenario};
use serde::Serialize;

/// Touch, move, touch again: contacts into the world frame with the body
/// pose of their frame, repeated touches clustered into obstacles.
#[derive(Parser, Debug)]
#[command(name = "touch_mapping")]
struct Cli {
    /// The options every demo takes.
    #[command(flatten)]
    demo: DemoArgs,
    /// Touches closer than this are one obstacle (single linkage), mm.
    #[arg(long, value_name = "R", default_value_t = MapOptions::default().radius_m * 1e3, value_parser = cli_support::finite)]
    radius_mm: f64,
    /// Contacts lighter than this are left out, N.
    #[arg(long, value_name = "F", default_value_t = MapOptions::default().min_force_n, allow_negative_numbers = true, value_parser = cli_support::finite)]
    min_force: f64,
    /// A rod is matched to a cluster within this distance, mm.
    #[arg(long, value_name = "G", default_value_t = 100.0, value_parser = cli_support::finite)]
    gate_mm: f64,
    /// The sensor's mounting on the body [default: the truth file's, else
    /// the simulator's].
    #[arg(long, value_enum)]
    mounting: Option<MountingArg>,
    /// Clusters of fewer touches are dropped.
    #[arg(long, value_name = "N", default_value_t = MapOptions::default().min_count as u64, value_parser = clap::value_parser!(u64).range(1..))]
    min_count: u64,
}

/// `--mounting`.
#[derive(ValueEnum, Debug, Clone, Copy, PartialEq)]
enum MountingArg {
    /// The simulator's: skin facing down under the body (x = x, y = -y, z = -z).
    Default,
    /// The sensor frame is the body frame.
    Identity,
}

#[derive(Serialize)]
struct Output {
    clusters: Vec<ClusterSummary>,
}

/// Runs the demo on the command-line arguments `args` (without the program
/// name); `Ok(false)` if some frame had to be skipped.
pub fn run_with(args: &[String]) -> Result<bool, Failure> {
    match cli_support::try_parse::<Cli>("touch_mapping", args)? {
        Some(cli) => run(&cli),
        None => Ok(true),
    }
}

fn run(cli: &Cli) -> Result<bool, Failure> {
    let a = &cli.demo;
    let mut report = a.report();
    let options = MapOptions {
        radius_m: cli.radius_mm * 1e-3,
        min_force_n: cli.min_force,
        min_count: cli.min_count as usize,
    };
    let gate_m = cli.gate_mm * 1e-3;
    let (dir, _) = resolve_input(a, "touch_mapping", &Scenario::Mapping(Mapping::default()))?;
    let poses_path = dir.join("poses.csv");
    if !poses_path.is_file() {
        return Err(format!(
            "no poses.csv in {}: mapping needs the body pose of every frame with contacts \
             (docs/formats.md: frame,t_s,x_m,y_m,z_m,qw,qx,qy,qz)",
            dir.display()
        )
        .into());
    }
    let rows = io::read_poses_csv(&poses_path).map_err(|e| format!("cannot read poses: {e}"))?;
    let poses = poses_by_frame(&rows, &poses_path).map_err(|e| e.to_string())?;
    let truth_path = a.truth.clone().or_else(|| {
        let p = dir.join("rods.json");
        p.is_file().then_some(p)
    });
    let truth: Option<RodsTruth> = truth_path
        .as_deref()
        .map(|p| {
            if !p.exists() {
                return Err(format!("truth file {} not found", p.display()));
            }
            read_rods_json(p).map_err(|e| format!("cannot read truth: {e}"))
        })
        .transpose()?;
    let mounting = match cli.mounting {
        None => truth.as_ref().map(|t| t.mounting).unwrap_or_default(),
        Some(MountingArg::Default) => Mounting::default(),
        Some(MountingArg::Identity) => Mounting::identity(),
    };

    let run = run_sensor(&dir, &a.calibration, a.crop)?;
    let TouchMap { touches, clusters } =
        map_touches(&run.frames, &poses, &mounting, &options, &poses_path)
            .map_err(|e| e.to_string())?;
    let points: Vec<[f64; 3]> = touches.iter().map(|t| t.position_m).collect();
    let matches = truth
        .as_ref()
        .map(|t| match_rods(&clusters, &t.rods, gate_m))
        .transpose()
        .map_err(|e| e.to_string())?;

    writeln!(
        report,
        "## touch_mapping: {} ({} contacts in {} frames, {} clusters)\n",
        dir.display(),
        touches.len(),
        run.frames.len(),
        clusters.len()
    )?;
    writeln!(
        report,
        "| cluster | x_m | y_m | z_m | count | spread_mm | rod | error_mm |"
    )?;
    writeln!(report, "|---|---|---|---|---|---|---|---|")?;
    for (k, c) in clusters.iter().enumerate() {
        let m = matches
            .as_ref()
            .and_then(|m| m.iter().find(|r| r.cluster == Some(k)));
        writeln!(
            report,
            "| {} | {:.4} | {:.4} | {:.4} | {} | {:.2} | {} | {} |",
            k + 1,
            c.position_m[0],
            c.position_m[1],
            c.position_m[2],
            c.count,
            c.spread_m * 1e3,
            m.map(|r| (r.rod + 1).to_string()).unwrap_or("-".into()),
            m.and_then(|r| r.error_m)
                .map(|e| format!("{:.2}", e * 1e3))
                .unwrap_or("-".into())
        )?;
    }
    if let (Some(t), Some(m)) = (&truth, &matches) {
        writeln!(
            report,
            "\n| rod | x_m | top_m | cluster | dx_mm | dz_mm | error_mm |"
        )?;
        writeln!(report, "|---|---|---|---|---|---|---|")?;
        let mut errs = Vec::new();
        for r in m {
            let rod = &t.rods[r.rod];
            let (c, dx, dz, e) = match r.cluster {
                Some(k) => {
                    let p = clusters[k].position_m;
                    errs.push(r.error_m.expect("matched"));
                    (
                        (k + 1).to_string(),
                        format!("{:+.2}", (p[0] - rod.point_m[0]) * 1e3),
                        format!("{:+.2}", (p[2] - rod.point_m[2]) * 1e3),
                        format!("{:.2}", r.error_m.expect("matched") * 1e3),
                    )
                }
                None => ("missed".into(), "-".into(), "-".into(), "-".into()),
            };
            writeln!(
                report,
                "| {} | {:.4} | {:.4} | {c} | {dx} | {dz} | {e} |",
                r.rod + 1,
                rod.point_m[0],
                rod.point_m[2]
            )?;
        }
        let missed = m.iter().filter(|r| r.cluster.is_none()).count();
        let false_clusters = clusters.len() - errs.len();
        if errs.is_empty() {
            writeln!(
                report,
                "\nno rod found ({missed} missed, {false_clusters} false clusters)"
            )?;
        } else {
            writeln!(
                report,
                "\nerror per rod: mean {:.2} mm, worst {:.2} mm over {} rods; {missed} missed, \
                 {false_clusters} false clusters (target: worst <= 2 mm; paper < 40 mm)",
                mean(&errs) * 1e3,
                errs.iter().fold(0.0f64, |a, &b| a.max(b)) * 1e3,
                errs.len()
            )?;
        }
    }

    if let Some(p) = &a.png {
        let grey = Rgb(150, 150, 150);
        let mut series = vec![Series {
            label: "TOUCHES".into(),
            points: points.iter().map(|p| (p[0], p[2])).collect(),
            color: grey,
            style: Style::Dots(2.0),
        }];
        series.push(Series {
            label: "CLUSTERS".into(),
            points: clusters
                .iter()
                .map(|c| (c.position_m[0], c.position_m[2]))
                .collect(),
            color: PALETTE[0],
            style: Style::Circle(0.0),
        });
        if let Some(t) = &truth {
            series.push(Series {
                label: "TRUE RODS".into(),
                points: t
                    .rods
                    .iter()
                    .map(|r| (r.point_m[0], r.point_m[2]))
                    .collect(),
                color: PALETTE[1],
                style: Style::Cross(5.0),
            });
        }
        // At least 0.2 m of z, so that the map is not a mm-scale scatter
        // (the zooms below show the mm).
        let zs = series.iter().flat_map(|s| s.points.iter().map(|p| p.1));
        let (zlo, zhi) = zs.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), z| {
            (a.min(z), b.max(z))
        });
        let zmid = if zlo.is_finite() {
            0.5 * (zlo + zhi)
        } else {
            0.0
        };
        let half = (0.5 * (zhi - zlo) + 0.02).max(0.1);
        let overview = Plot {
            title: "TOUCH MAP, WORLD X-Z (ZOOMS BELOW: CIRCLE = 2 MM TARGET)".into(),
            y_range: Some((zmid - half, zmid + half)),
            x_label: "X M".into(),
            y_label: "Z M".into(),
            series,
            ..Plot::default()
        }
        .render(1100, 260);
        let mut panels = vec![overview];
        // A zoom around each rod (or each cluster without truth), in mm.
        let centres: Vec<(String, [f64; 3])> = match &truth {
            Some(t) => t
                .rods
                .iter()
                .enumerate()
                .map(|(k, r)| (format!("ROD {}", k + 1), r.point_m))
                .collect(),
            None => clusters
                .iter()
                .enumerate()
                .map(|(k, c)| (format!("CLUSTER {}", k + 1), c.position_m))
                .collect(),
        };
        let zooms: Vec<_> = centres
            .iter()
            .take(6)
            .map(|(name, c)| {
                let rel = |p: [f64; 3]| ((p[0] - c[0]) * 1e3, (p[2] - c[2]) * 1e3);
                let near = |p: &[f64; 3]| (p[0] - c[0]).abs() < 0.02 && (p[2] - c[2]).abs() < 0.02;
                let mut s = vec![Series {
                    label: String::new(),
                    points: points.iter().filter(|p| near(p)).map(|&p| rel(p)).collect(),
                    color: grey,
                    style: Style::Dots(3.0),
                }];
                s.push(Series {
                    label: String::new(),
                    points: clusters
                        .iter()
                        .filter(|k| near(&k.position_m))
                        .map(|k| rel(k.position_m))
                        .collect(),
                    color: PALETTE[0],
                    style: Style::Cross(6.0),
                });
                if truth.is_some() {
                    s.push(Series {
                        label: String::new(),
                        points: vec![(0.0, 0.0)],
                        color: PALETTE[1],
                        style: Style::Circle(2.0),
                    });
                }
                Plot {
                    title: name.clone(),
                    x_label: "DX MM".into(),
                    y_label: "DZ MM".into(),
                    x_range: Some((-6.0, 6.0)),
                    y_range: Some((-6.0, 6.0)),
                    equal_aspect: true,
                    series: s,
                }
                .render(214, 214)
            })
            .collect();
        if !zooms.is_empty() {
            panels.push(row(&zooms));
        }
        save_png(&stack(&panels), p)?;
    }
    if let Some(p) = &a.json {
        let out = Output {
            clusters: clusters.iter().map(Cluster::summary).collect(),
        };
        p.write_json(&out)?;
    }
    Ok(run.skipped == 0)
}

fn main() -> ExitCode {
    exit_status(run(&Cli::parse()))
}
