//! The multi-contact demo: two rods under the body, both located and both
//! forces measured over time.
//!
//! ```text
//! cargo run --release --example multi_contact -- [SEQ_DIR | --simulate DIR]
//!     [--calibration FILE] [--crop x,y,w,h] [--truth truth.jsonl]
//!     [--json FILE|-] [--png FILE] [--seed N] [--quiet] [--gate-mm G (default 15)]
//! ```
//!
//! Runs the sensor over the sequence and prints, per frame, every live
//! contact (tracked id, x, Fz); with a truth file (`truth.jsonl`, docs/formats.md;
//! default: the one beside the frames, if any) each contact is matched to the
//! nearest true contact in x within the gate, and the table ends with the
//! error per contact. `--png` plots x, Fz and the shear forces over time for
//! every contact (dots), with the truth dashed. `--json` writes
//! `{"frames": [{"frame", "t_s", "contacts": [{"id", "x_mm", "y_mm", "z_mm",
//! "fx_n", "fy_n", "fz_n", "truth": {"x_mm", "fx_n", "fy_n", "fz_n"} | null}]}],
//! "contacts": [{"id", "frames", "truth_index", "mae_x_mm", "mae_fx_n",
//! "mae_fy_n", "mae_fz_n"}], "frames_all_true_detected", "truth_frames"}`.
//!
//! With no sequence (or `--simulate DIR`) it first simulates two 5 mm rods
//! 80 mm apart (arc length), centred, pressing to 2.0 and 1.5 N over 16 frames.

#[path = "cli_support/mod.rs"]
mod cli_support;
#[path = "demo_support/mod.rs"]
mod demo_support;

use std::collections::BTreeMap;
use std::io::Write as _;
use std::process::ExitCode;

use clap::Parser;
use cli_support::Failure;
use demo_support::*;
use optical_tactile::io::FrameRecord;
use optical_tactile_sim::evaluate::match_contacts;
use optical_tactile_sim::scenario::{Pair, Scenario};
use serde::Serialize;

/// Two rods under the body: both located, both forces measured over time,
/// against the truth when there is one.
#[derive(Parser, Debug)]
#[command(name = "multi_contact")]
struct Cli {
    /// The options every demo takes.
    #[command(flatten)]
    demo: DemoArgs,
    /// A measured contact is matched to the nearest true one within this
    /// distance in x, mm.
    #[arg(long, value_name = "G", default_value_t = 15.0, value_parser = cli_support::positive)]
    gate_mm: f64,
}

fn scenario() -> Scenario {
    Scenario::Pair(Pair {
        x_mm: 0.0,
        spacing_mm: 80.0,
        force_n: 2.0,
        force2_n: 1.5,
        frames: 16,
        indenter_mm: 5.0,
    })
}

#[derive(Serialize, Clone, Copy)]
struct TruthOut {
    x_mm: f64,
    fx_n: f64,
    fy_n: f64,
    fz_n: f64,
}

#[derive(Serialize)]
struct ContactOut {
    id: Option<u64>,
    x_mm: f64,
    y_mm: f64,
    z_mm: f64,
    fx_n: f64,
    fy_n: f64,
    fz_n: f64,
    truth: Option<TruthOut>,
}

#[derive(Serialize)]
struct FrameOut {
    frame: String,
    t_s: f64,
    contacts: Vec<ContactOut>,
}

#[derive(Serialize)]
struct TrackOut {
    id: u64,
    frames: usize,
    truth_index: Option<usize>,
    mae_x_mm: Option<f64>,
    mae_fx_n: Option<f64>,
    mae_fy_n: Option<f64>,
    mae_fz_n: Option<f64>,
}

#[derive(Serialize)]
struct Output {
    frames: Vec<FrameOut>,
    contacts: Vec<TrackOut>,
    /// Frames in which every true contact was matched by a measured one.
    frames_all_true_detected: Option<usize>,
    /// Frames of the truth with at least one contact.
    truth_frames: Option<usize>,
}

/// The index of the true contact a measurement was matched to, and its
/// absolute errors in x, Fx, Fy, Fz.
type MatchedErrors = (usize, [f64; 4]);

/// Pairs every measured contact with a true one (nearest in x within the
/// gate) and summarises per tracked id.
fn analyse(frames: &[FrameRecord], truth: Option<&[FrameRecord]>, gate_mm: f64) -> Output {
    let by_name: BTreeMap<&str, &FrameRecord> = truth
        .unwrap_or(&[])
        .iter()
        .map(|f| (f.frame.as_str(), f))
        .collect();
    let mut out_frames = Vec::new();
    // Per id: (truth index, errors x, fx, fy, fz) and frame count.
    let mut per_id: BTreeMap<u64, (usize, Vec<MatchedErrors>)> = BTreeMap::new();
    let (mut all_detected, mut truth_frames) = (0usize, 0usize);
    for f in frames {
        let t = by_name.get(f.frame.as_str()).map(|t| &t.contacts[..]);
        let pairs = t.map(|t| match_contacts(&f.contacts, t, gate_mm));
        if let Some(t) = t.filter(|t| !t.is_empty()) {
            truth_frames += 1;
            if pairs.as_ref().is_some_and(|p| p.len() == t.len()) {
                all_detected += 1;
            }
        }
        let mut contacts = Vec::new();
        for (i, c) in f.contacts.iter().enumerate() {
            let tm = pairs
                .as_ref()
                .and_then(|p| p.iter().find(|(pi, _)| *pi == i))
                .map(|&(_, j)| (j, &t.expect("pairs come from a truth")[j]));
            if let Some(id) = c.id {
                let e = per_id.entry(id).or_default();
                e.0 += 1;
                if let Some((j, tc)) = tm {
                    e.1.push((
                        j,
                        [
                            (c.x_mm - tc.x_mm).abs(),
                            (c.fx_n - tc.fx_n).abs(),
                            (c.fy_n - tc.fy_n).abs(),
                            (c.fz_n - tc.fz_n).abs(),
                        ],
                    ));
                }
            }
            contacts.push(ContactOut {
                id: c.id,
                x_mm: c.x_mm,
                y_mm: c.y_mm,
                z_mm: c.z_mm,
                fx_n: c.fx_n,
                fy_n: c.fy_n,
                fz_n: c.fz_n,
                truth: tm.map(|(_, tc)| TruthOut {
                    x_mm: tc.x_mm,
                    fx_n: tc.fx_n,
                    fy_n: tc.fy_n,
                    fz_n: tc.fz_n,
                }),
            });
        }
        out_frames.push(FrameOut {
            frame: f.frame.clone(),
            t_s: f.t_s,
            contacts,
        });
    }
    let tracks = per_id
        .into_iter()
        .map(|(id, (n, errs))| {
            // The true contact this id was matched to most often.
            let mut votes: BTreeMap<usize, usize> = BTreeMap::new();
            for (j, _) in &errs {
                *votes.entry(*j).or_default() += 1;
            }
            let m = |k: usize| {
                (!errs.is_empty()).then(|| mean(&errs.iter().map(|e| e.1[k]).collect::<Vec<_>>()))
            };
            TrackOut {
                id,
                frames: n,
                truth_index: votes
                    .iter()
                    .max_by_key(|(j, v)| (**v, std::cmp::Reverse(**j)))
                    .map(|(j, _)| *j),
                mae_x_mm: m(0),
                mae_fx_n: m(1),
                mae_fy_n: m(2),
                mae_fz_n: m(3),
            }
        })
        .collect();
    Output {
        frames: out_frames,
        contacts: tracks,
        frames_all_true_detected: truth.map(|_| all_detected),
        truth_frames: truth.map(|_| truth_frames),
    }
}

fn picture(out: &Output, truth: Option<&[FrameRecord]>) -> optical_tactile::viz::Canvas {
    let ids: Vec<u64> = out.contacts.iter().map(|t| t.id).collect();
    let series_of = |k: usize| -> Vec<optical_tactile::viz::Series> {
        let mut s = Vec::new();
        for (n, &id) in ids.iter().enumerate() {
            let color = PALETTE[n % PALETTE.len()];
            let pts: Vec<(f64, f64)> = out
                .frames
                .iter()
                .flat_map(|f| {
                    f.contacts
                        .iter()
                        .filter(|c| c.id == Some(id))
                        .map(move |c| (f.t_s, [c.x_mm, c.fz_n, c.fx_n, c.fy_n][k]))
                })
                .collect();
            let tidx = out.contacts[n].truth_index;
            let tpts = truth.zip(tidx).map(|(t, j)| {
                t.iter()
                    .filter_map(|f| {
                        f.contacts
                            .get(j)
                            .map(|c| (f.t_s, [c.x_mm, c.fz_n, c.fx_n, c.fy_n][k]))
                    })
                    .collect()
            });
            let label = match k {
                2 => format!("FX {id}"),
                3 => format!("FY {id}"),
                _ => format!("ID {id}"),
            };
            s.extend(measured_and_truth(&label, color, pts, tpts));
        }
        s
    };
    let x = time_plot("CONTACT LOCATION X", "X MM", series_of(0)).render(900, 260);
    let fz = time_plot("NORMAL FORCE FZ", "FZ N", series_of(1)).render(900, 260);
    let mut shear = series_of(2);
    // Shear: y components in lighter dots, same colours, no truth repeat.
    for s in series_of(3) {
        if s.style != optical_tactile::viz::Style::Dashed {
            shear.push(optical_tactile::viz::Series {
                style: optical_tactile::viz::Style::Cross(3.0),
                ..s
            });
        }
    }
    let sh = time_plot("SHEAR FORCES FX (DOTS) FY (CROSSES)", "F N", shear).render(900, 260);
    stack(&[x, fz, sh])
}

/// Runs the demo on the command-line arguments `args` (without the program
/// name); `Ok(false)` if some frame had to be skipped.
pub fn run_with(args: &[String]) -> Result<bool, Failure> {
    match cli_support::try_parse::<Cli>("multi_contact", args)? {
        Some(cli) => run(&cli),
        None => Ok(true),
    }
}

fn run(cli: &Cli) -> Result<bool, Failure> {
    let (a, gate) = (&cli.demo, cli.gate_mm);
    let mut report = a.report();
    let (dir, _) = resolve_input(a, "multi_contact", &scenario())?;
    let truth_path = a.truth.clone().or_else(|| {
        let p = dir.join("truth.jsonl");
        p.is_file().then_some(p)
    });
    let truth = truth_path.as_deref().map(read_truth).transpose()?;
    let run = run_sensor(&dir, &a.calibration, a.crop)?;
    let out = analyse(&run.frames, truth.as_deref(), gate);

    writeln!(report, "## multi_contact: {}\n", dir.display())?;
    writeln!(
        report,
        "| frame | t_s | id | x_mm | fx_n | fy_n | fz_n | true x_mm | true fz_n |"
    )?;
    writeln!(report, "|---|---|---|---|---|---|---|---|---|")?;
    for f in &out.frames {
        if f.contacts.is_empty() {
            writeln!(report, "| {} | {:.3} | - | | | | | | |", f.frame, f.t_s)?;
        }
        for c in &f.contacts {
            let (tx, tf) = c
                .truth
                .map(|t| (format!("{:.2}", t.x_mm), format!("{:.3}", t.fz_n)))
                .unwrap_or_default();
            writeln!(
                report,
                "| {} | {:.3} | {} | {:.2} | {:.3} | {:.3} | {:.3} | {tx} | {tf} |",
                f.frame,
                f.t_s,
                c.id.map(|i| i.to_string()).unwrap_or_default(),
                c.x_mm,
                c.fx_n,
                c.fy_n,
                c.fz_n
            )?;
        }
    }
    writeln!(
        report,
        "\n| contact id | frames | true contact | MAE x (mm) | MAE Fx (N) | MAE Fy (N) | MAE Fz (N) |"
    )?;
    writeln!(report, "|---|---|---|---|---|---|---|")?;
    let f = |v: Option<f64>, d: usize| v.map(|v| format!("{v:.d$}")).unwrap_or("-".into());
    for t in &out.contacts {
        writeln!(
            report,
            "| {} | {} | {} | {} | {} | {} | {} |",
            t.id,
            t.frames,
            t.truth_index.map(|j| j.to_string()).unwrap_or("-".into()),
            f(t.mae_x_mm, 2),
            f(t.mae_fx_n, 3),
            f(t.mae_fy_n, 3),
            f(t.mae_fz_n, 3)
        )?;
    }
    if let (Some(d), Some(n)) = (out.frames_all_true_detected, out.truth_frames) {
        writeln!(
            report,
            "\nall true contacts detected in {d} of {n} loaded frames (gate {gate} mm)"
        )?;
    }
    if let Some(p) = &a.png {
        save_png(&picture(&out, truth.as_deref()), p)?;
    }
    if let Some(p) = &a.json {
        p.write_json(&out)?;
    }
    Ok(run.skipped == 0)
}

fn main() -> ExitCode {
    exit_status(run(&Cli::parse()))
}
