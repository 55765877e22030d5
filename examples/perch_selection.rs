//! The compliance demo: the body presses two perches of different stiffness
//! by the same depth; the one pushing back harder is stiffer. Reports which,
//! where it is, and the sideways move that puts the body over it.
//!
//! ```text
//! cargo run --release --example perch_selection -- [SEQ_DIR | --simulate DIR]
//!     [--calibration FILE] [--crop x,y,w,h] [--truth truth.jsonl]
//!     [--json FILE|-] [--png FILE] [--seed N] [--quiet] [--min-force F (default 0.5)]
//! ```
//!
//! Contacts lighter than `--min-force` N are left out everywhere: with the
//! shipped calibration a faint ghost patch (~0.3 N) sometimes appears ~45 mm
//! outboard of a real press and would count as a third, soft "perch". The
//! perches are the contacts of the **press frame**: the frame with the
//! most live contacts (at least two), ties broken by the largest summed force
//! (the deepest press, where forces are largest and the ranking most
//! reliable). Their force magnitudes are ranked (rank 1 = stiffest = largest
//! force); the move is the stiffest perch's x (sensor frame, body frame = sensor
//! frame along x). With a truth file (`truth.jsonl`, docs/formats.md; default: the
//! one beside the frames, if any) the table adds each perch's true location
//! and force in the press frame and whether the true ranking agrees.
//!
//! `--json` writes `{"perches": [{"x_mm", "force_n", "stiffness_rank"}, ...],
//! "stiffer": {"x_mm", "force_n"}, "move_mm"}` (sensor frame, perches in
//! ascending x). `--png` plots x and |F| of every contact over time (truth
//! dashed) and marks the press frame.
//!
//! With no sequence (or `--simulate DIR`) it first simulates the simulator's
//! `perches` scenario: 10 mm rods at x = -60 and +50 mm with stiffness 1 and
//! 2 N/mm, pressed to 1.5 mm over 12 frames.

#[path = "cli_support/mod.rs"]
mod cli_support;
#[path = "demo_support/mod.rs"]
mod demo_support;

use std::io::Write as _;
use std::process::ExitCode;

use clap::Parser;
use cli_support::Failure;
use demo_support::*;
use optical_tactile::io::FrameRecord;
use optical_tactile::viz::{Rgb, Series, Style};
use optical_tactile_sim::evaluate::match_contacts;
use optical_tactile_sim::mapping::{PerchReading, rank_perches};
use optical_tactile_sim::scenario::{Perches, Scenario};
use serde::Serialize;

/// Two perches of different stiffness pressed by the same depth: which is
/// stiffer, where it is, and the move that puts the body over it.
#[derive(Parser, Debug)]
#[command(name = "perch_selection")]
struct Cli {
    /// The options every demo takes.
    #[command(flatten)]
    demo: DemoArgs,
    /// Contacts lighter than this are left out, N.
    #[arg(long, value_name = "F", default_value_t = 0.5, allow_negative_numbers = true, value_parser = cli_support::finite)]
    min_force: f64,
}

#[derive(Serialize, Clone, Copy)]
struct PerchOut {
    x_mm: f64,
    force_n: f64,
    stiffness_rank: usize,
}

#[derive(Serialize)]
struct Stiffer {
    x_mm: f64,
    force_n: f64,
}

#[derive(Serialize)]
struct Output {
    perches: Vec<PerchOut>,
    stiffer: Stiffer,
    move_mm: f64,
}

/// The press frame's index in `frames` (see the module docs), or an error
/// when no frame shows two contacts.
fn press_frame(frames: &[FrameRecord]) -> Result<usize, String> {
    let best = frames
        .iter()
        .enumerate()
        .max_by(|(_, a), (_, b)| {
            let sum = |f: &FrameRecord| f.contacts.iter().map(force_magnitude).sum::<f64>();
            a.contacts
                .len()
                .cmp(&b.contacts.len())
                .then(sum(a).total_cmp(&sum(b)))
        })
        .map(|(i, _)| i)
        .ok_or("no frame processed")?;
    let n = frames[best].contacts.len();
    if n < 2 {
        return Err(format!(
            "no frame shows two perches at once (at most {n} contact): nothing to compare"
        ));
    }
    Ok(best)
}

/// Runs the demo on the command-line arguments `args` (without the program
/// name); `Ok(false)` if some frame had to be skipped.
pub fn run_with(args: &[String]) -> Result<bool, Failure> {
    match cli_support::try_parse::<Cli>("perch_selection", args)? {
        Some(cli) => run(&cli),
        None => Ok(true),
    }
}

fn run(cli: &Cli) -> Result<bool, Failure> {
    let (a, min_force) = (&cli.demo, cli.min_force);
    let mut report = a.report();
    let (dir, _) = resolve_input(a, "perch_selection", &Scenario::Perches(Perches::default()))?;
    let truth_path = a.truth.clone().or_else(|| {
        let p = dir.join("truth.jsonl");
        p.is_file().then_some(p)
    });
    let truth = truth_path.as_deref().map(read_truth).transpose()?;
    let mut run = run_sensor(&dir, &a.calibration, a.crop)?;
    for f in &mut run.frames {
        f.contacts.retain(|c| force_magnitude(c) >= min_force);
    }
    let k = press_frame(&run.frames)?;
    let press = &run.frames[k];
    let mut contacts = press.contacts.clone();
    contacts.sort_by(|a, b| a.x_mm.total_cmp(&b.x_mm));
    let readings: Vec<PerchReading> = contacts
        .iter()
        .map(|c| PerchReading {
            x_mm: c.x_mm,
            force_n: force_magnitude(c),
        })
        .collect();
    let ranking = rank_perches(&readings).map_err(|e| e.to_string())?;
    let out = Output {
        perches: readings
            .iter()
            .zip(&ranking.ranks)
            .map(|(r, &rank)| PerchOut {
                x_mm: r.x_mm,
                force_n: r.force_n,
                stiffness_rank: rank,
            })
            .collect(),
        stiffer: Stiffer {
            x_mm: readings[ranking.stiffest].x_mm,
            force_n: readings[ranking.stiffest].force_n,
        },
        move_mm: ranking.move_mm,
    };

    // The truth of the press frame, matched by x (gate 15 mm).
    let true_press = truth
        .as_ref()
        .and_then(|t| t.iter().find(|f| f.frame == press.frame));
    let matched: Vec<Option<(f64, f64)>> = match true_press {
        Some(tf) => {
            let pairs = match_contacts(&contacts, &tf.contacts, 15.0);
            (0..contacts.len())
                .map(|i| {
                    pairs
                        .iter()
                        .find(|p| p.0 == i)
                        .map(|&(_, j)| (tf.contacts[j].x_mm, force_magnitude(&tf.contacts[j])))
                })
                .collect()
        }
        None => vec![None; contacts.len()],
    };
    let true_ranks = if matched.iter().all(|m| m.is_some()) && true_press.is_some() {
        let r: Vec<PerchReading> = matched
            .iter()
            .map(|m| {
                let (x_mm, force_n) = m.expect("all matched");
                PerchReading { x_mm, force_n }
            })
            .collect();
        Some(rank_perches(&r).map_err(|e| e.to_string())?)
    } else {
        None
    };

    writeln!(
        report,
        "## perch_selection: {} (press frame {}, t = {:.3} s)\n",
        dir.display(),
        press.frame,
        press.t_s
    )?;
    writeln!(
        report,
        "| perch | x_mm | force_n | stiffness rank | true x_mm | true force_n | true rank |"
    )?;
    writeln!(report, "|---|---|---|---|---|---|---|")?;
    for (i, p) in out.perches.iter().enumerate() {
        let (tx, tf) = matched[i]
            .map(|(x, f)| (format!("{x:.2}"), format!("{f:.3}")))
            .unwrap_or(("-".into(), "-".into()));
        let tr = true_ranks
            .as_ref()
            .map(|r| r.ranks[i].to_string())
            .unwrap_or("-".into());
        writeln!(
            report,
            "| {} | {:.2} | {:.3} | {} | {tx} | {tf} | {tr} |",
            i + 1,
            p.x_mm,
            p.force_n,
            p.stiffness_rank
        )?;
    }
    writeln!(
        report,
        "\nstiffer perch at x = {:.2} mm ({:.3} N): move the body {:+.2} mm along x to be over it",
        out.stiffer.x_mm, out.stiffer.force_n, out.move_mm
    )?;
    if let Some(r) = &true_ranks {
        let agree = r.ranks == ranking.ranks;
        let tx = matched[r.stiffest].expect("ranked").0;
        writeln!(
            report,
            "truth: stiffer perch at x = {tx:.2} mm; ranking {}; move error {:.2} mm",
            if agree { "agrees" } else { "DISAGREES" },
            (out.move_mm - tx).abs()
        )?;
    }

    if let Some(p) = &a.png {
        let xs = id_series(&run.frames, |c| c.x_mm);
        let fs = id_series(&run.frames, force_magnitude);
        let (mut sx, mut sf) = (Vec::new(), Vec::new());
        for (n, ((id, x), (_, f))) in xs.into_iter().zip(fs).enumerate() {
            let color = PALETTE[n % PALETTE.len()];
            // Its true contact: nearest in mean x.
            let mx = mean(&x.iter().map(|p| p.1).collect::<Vec<_>>());
            let j = true_press.and_then(|tf| {
                (0..tf.contacts.len()).min_by(|&a, &b| {
                    (tf.contacts[a].x_mm - mx)
                        .abs()
                        .total_cmp(&(tf.contacts[b].x_mm - mx).abs())
                })
            });
            let tt = |v: fn(&optical_tactile::io::ContactRecord) -> f64| {
                truth.as_deref().zip(j).map(|(t, j)| truth_series(t, j, v))
            };
            sx.extend(measured_and_truth(
                &format!("ID {id}"),
                color,
                x,
                tt(|c| c.x_mm),
            ));
            sf.extend(measured_and_truth(
                &format!("ID {id}"),
                color,
                f,
                tt(force_magnitude),
            ));
        }
        let mark = |lo: f64, hi: f64| Series {
            label: "PRESS FRAME".into(),
            points: vec![(press.t_s, lo), (press.t_s, hi)],
            color: Rgb(120, 120, 120),
            style: Style::Line,
        };
        sx.push(mark(-160.0, 160.0));
        let fmax = sf
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.1))
            .fold(0.0f64, f64::max);
        sf.push(mark(0.0, fmax));
        let mut px = time_plot("PERCH LOCATIONS X", "X MM", sx);
        px.y_range = Some((-165.0, 165.0));
        let title = format!(
            "FORCE MAGNITUDE: STIFFER PERCH AT X = {:.1} MM, MOVE {:+.1} MM",
            out.stiffer.x_mm, out.move_mm
        );
        let pf = time_plot(&title, "F N", sf);
        save_png(&stack(&[px.render(900, 260), pf.render(900, 300)]), p)?;
    }
    if let Some(p) = &a.json {
        p.write_json(&out)?;
    }
    Ok(run.skipped == 0)
}

fn main() -> ExitCode {
    exit_status(run(&Cli::parse()))
}
