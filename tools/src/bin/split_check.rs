//! The split rule of the segmenter ([`SplitRule`]) on the simulator, printed
//! as markdown, for each preset with and without the rule (or with the rules
//! given by `--split`):
//!
//! - `singles`: single-rod presses over a characterization-like grid
//!   (positions along the skin, the protocol's five tilts, forces 0.5-3 N,
//!   the 2, 5 and 10 mm rods): how many presses the rule cut (each cut is a
//!   spurious split: there is one contact), how many were detected and how
//!   many patches they produced;
//! - `rest`: false contacts on rest pairs;
//! - `spacing`: two straight rods of equal force at decreasing spacing, told
//!   apart when each rod is covered by its own patch (patch level, no nHHD;
//!   `sweep -- spacing` measures the contacts' positions).
//!
//! The flow is the `accurate` DIS at its native resolution (the sensor's
//! default when the split rule was tuned; `sweep` and `experiments` now use
//! the default `fine` flow on the extractor's analysis grid) and the margin
//! the extractor's.
//!
//! ```text
//! cargo run --release -p optical-tactile-tools --bin split_check -- all
//! cargo run --release -p optical-tactile-tools --bin split_check -- singles --split 9,0.25,0.2 --split none
//! ```

#[path = "../../../examples/cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, ValueEnum};
use cli_support::{Failure, Numbers, Sink};
use optical_tactile::Error;
use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
use optical_tactile::segment::{ContactPatch, Segmenter, SegmenterConfig, SplitRule, Thresholds};
use optical_tactile::sensor::ExtractorConfig;
use optical_tactile_sim::scenario::{INDENTERS_MM, TILTS_DEG, tilted_force};
use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};

type Result<T, E = Failure> = std::result::Result<T, E>;

/// The segmenter's split rule on the simulator, per preset with and without
/// the rule (or with the rules given by --split), printed as markdown.
#[derive(Parser, Debug)]
#[command(
    name = "split_check",
    after_help = "SPLIT_DEBUG=1 prints every cut press to stderr; SPLIT_PROFILE=d,f,s1[,s2[,pitch]] \
                  prints the column sums of u and their smoothed derivative for one case instead."
)]
struct Cli {
    /// Which check to run.
    #[arg(value_enum, default_value_t = Mode::All)]
    mode: Mode,
    /// Simulator seed.
    #[arg(long, value_name = "N", default_value_t = 1)]
    seed: u64,
    /// Rest pairs.
    #[arg(long, value_name = "N", default_value_t = 300)]
    rest: usize,
    /// Arc positions of the single presses, mm.
    #[arg(long, value_name = "a,b,..", allow_hyphen_values = true,
          default_value_t = Numbers(vec![-120.0, -80.0, -40.0, 0.0, 40.0, 80.0, 120.0]))]
    positions: Numbers,
    /// Single-press forces, N.
    #[arg(long, value_name = "a,b,..", default_value_t = Numbers(vec![0.5, 1.0, 1.5, 2.0, 3.0]))]
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
    /// Patch margin, full-resolution px.
    #[arg(long, value_name = "PX", default_value_t = ExtractorConfig::default().margin_px)]
    margin: usize,
    /// A split rule to evaluate: smooth px, depth, min_peak[, border px[,
    /// far px (0: off)[, far_min_peak]]], or none (repeatable) [default:
    /// SplitRule::DEFAULT and none].
    #[arg(long = "split", value_name = "s,d,m[,b[,f[,fm]]]|none", value_parser = split_rule)]
    splits: Vec<SplitArg>,
}

/// The checks.
#[derive(ValueEnum, Debug, Clone, Copy, PartialEq)]
enum Mode {
    /// Every check.
    All,
    /// Single-rod presses: spurious splits.
    Singles,
    /// False contacts on rest pairs.
    Rest,
    /// Two rods at decreasing spacing.
    Spacing,
}

/// One `--split`: a rule, or none.
#[derive(Debug, Clone, Copy, PartialEq)]
struct SplitArg(Option<SplitRule>);

/// `s,d,m[,b]` or `none`.
fn split_rule(v: &str) -> Result<SplitArg, String> {
    if v == "none" {
        return Ok(SplitArg(None));
    }
    let p = cli_support::number_list(v)?;
    if !(3..=6).contains(&p.len()) {
        return Err(format!(
            "expected smooth,depth,min_peak[,border[,far[,far_min_peak]]] or none, got `{v}`"
        ));
    }
    let r = SplitRule {
        smooth: p[0] as usize,
        depth: p[1] as f32,
        min_peak: p[2] as f32,
        border: p.get(3).map_or(SplitRule::DEFAULT.border, |&b| b as usize),
        far_px: p.get(4).map_or(SplitRule::DEFAULT.far_px, |&b| b as usize),
        far_min_peak: p
            .get(5)
            .map_or(SplitRule::DEFAULT.far_min_peak, |&m| m as f32),
        across: false,
        press_swing: false,
    };
    r.validate().map_err(|e| e.to_string())?;
    Ok(SplitArg(Some(r)))
}

/// What the command line resolves to.
struct Args {
    mode: Mode,
    seed: u64,
    rest: usize,
    positions: Vec<f64>,
    forces: Vec<f64>,
    spacings: Vec<f64>,
    spacing_forces: Vec<f64>,
    ratio: f64,
    spacing_centres: Vec<f64>,
    splits: Vec<Option<SplitRule>>,
    margin: usize,
}

impl Cli {
    fn resolve(self) -> Args {
        let mut splits: Vec<Option<SplitRule>> = self.splits.iter().map(|s| s.0).collect();
        if splits.is_empty() {
            splits = vec![Some(SplitRule::DEFAULT), None];
        }
        Args {
            mode: self.mode,
            seed: self.seed,
            rest: self.rest,
            positions: self.positions.0,
            forces: self.forces.0,
            spacings: self.spacings.0,
            spacing_forces: self.spacing_forces.0,
            ratio: self.ratio,
            spacing_centres: self.spacing_centres.0,
            splits,
            margin: self.margin,
        }
    }
}

fn split_name(s: &Option<SplitRule>) -> String {
    match s {
        None => "none".into(),
        Some(r) => format!(
            "{},{},{},{},{},{}",
            r.smooth, r.depth, r.min_peak, r.border, r.far_px, r.far_min_peak
        ),
    }
}

/// One DIS and one segmenter per (preset, split rule).
struct Bench {
    dis: Dis,
    names: Vec<String>,
    segs: Vec<Segmenter>,
    patches: Vec<ContactPatch>,
    scale: f64,
}

impl Bench {
    fn new(args: &Args) -> Result<Self> {
        let params = DisParams::preset(DisPreset::Accurate);
        let scale = (1usize << params.finest_scale) as f64;
        let mut names = Vec::new();
        let mut segs = Vec::new();
        for (name, t) in [
            ("LOW", Thresholds::LOW),
            ("MID", Thresholds::MID),
            ("HIGH", Thresholds::HIGH),
        ] {
            for s in &args.splits {
                names.push(format!("{name}, split {}", split_name(s)));
                segs.push(
                    Segmenter::new(SegmenterConfig {
                        thresholds: t,
                        margin: args.margin,
                        scale,
                    })?
                    .with_split(*s)?,
                );
            }
        }
        Ok(Bench {
            dis: Dis::new(params)?,
            names,
            segs,
            patches: Vec::new(),
            scale,
        })
    }

    fn each(
        &mut self,
        frame: &ndarray::Array2<f32>,
        mut f: impl FnMut(usize, &[ContactPatch], usize),
    ) -> Result<()> {
        self.dis.compute_native(frame)?;
        let (flow, _) = self.dis.native_flow().ok_or(Error::NoReference)?;
        for (k, seg) in self.segs.iter_mut().enumerate() {
            seg.segment_into(flow, &mut self.patches)?;
            f(k, &self.patches, seg.split_count());
        }
        Ok(())
    }
}

fn rod_px(sensor: &SyntheticSensor, s: f64) -> f64 {
    let c = sensor.config();
    c.camera.s_to_px(&c.skin, s)
}

/// Index of the first patch covering column `x_px` (full resolution).
fn covering(p: &[ContactPatch], scale: f64, x_px: f64) -> Option<usize> {
    p.iter().position(|p| {
        let x0 = p.bbox.x as f64 * scale;
        let x1 = p.bbox.x_end() as f64 * scale;
        (x0..x1).contains(&x_px)
    })
}

fn singles(out: &mut Sink, args: &Args, sensor: &SyntheticSensor) -> Result<()> {
    let t = Instant::now();
    let mut b = Bench::new(args)?;
    let n = b.segs.len();
    let (mut cut, mut det, mut patches, mut multi) =
        (vec![0; n], vec![0; n], vec![0; n], vec![0; n]);
    let mut total = 0;
    let mut idx = 0u64;
    let debug = std::env::var_os("SPLIT_DEBUG").is_some();
    for &d in &INDENTERS_MM {
        for &s in &args.positions {
            let x = sensor.config().skin.arc_to_chord(s);
            let xp = rod_px(sensor, s);
            for &(yaw, pitch) in &TILTS_DEG {
                let r = sensor.render_indexed(idx, &[], false)?;
                idx += 1;
                b.dis.set_reference(&r.frame)?;
                for &f in &args.forces {
                    let rod = Press::rod(x, tilted_force(f, yaw, pitch), d);
                    let o = sensor.render_indexed(idx, &[rod], false)?;
                    idx += 1;
                    total += 1;
                    let scale = b.scale;
                    let names = b.names.clone();
                    b.each(&o.frame, |k, p, cuts| {
                        if cuts > 0 {
                            cut[k] += 1;
                            if debug {
                                let boxes: Vec<_> = p
                                    .iter()
                                    .map(|p| (p.bbox.x * 2, p.bbox.x_end() * 2))
                                    .collect();
                                eprintln!(
                                    "{}: d {d} s {s} tilt ({yaw},{pitch}) f {f}: rod {xp:.0} cuts {cuts} patches {boxes:?}",
                                    names[k]
                                );
                            }
                        }
                        if covering(p, scale, xp).is_some() {
                            det[k] += 1;
                        }
                        if p.len() > 1 {
                            multi[k] += 1;
                        }
                        patches[k] += p.len();
                    })?;
                }
            }
        }
    }
    writeln!(
        out,
        "### Single presses ({} presses: {} positions x {} tilts x forces {:?} N x 3 rods, seed {})\n",
        total,
        args.positions.len(),
        TILTS_DEG.len(),
        args.forces,
        args.seed
    )?;
    writeln!(
        out,
        "| thresholds | presses cut by the split rule (spurious splits) | detected | presses with > 1 patch | patches |"
    )?;
    writeln!(out, "|---|---|---|---|---|")?;
    for k in 0..n {
        writeln!(
            out,
            "| {} | {} / {total} | {} / {total} | {} | {} |",
            b.names[k], cut[k], det[k], multi[k], patches[k]
        )?;
    }
    writeln!(out)?;
    eprintln!("singles: {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn rest(out: &mut Sink, args: &Args, sensor: &SyntheticSensor) -> Result<()> {
    let mut b = Bench::new(args)?;
    let n = b.segs.len();
    let mut frames = vec![0; n];
    let base = 1_000_000u64;
    for k in 0..args.rest as u64 {
        let r = sensor.render_indexed(base + 2 * k, &[], false)?;
        let o = sensor.render_indexed(base + 2 * k + 1, &[], false)?;
        b.dis.set_reference(&r.frame)?;
        b.each(&o.frame, |i, p, _| {
            if !p.is_empty() {
                frames[i] += 1;
            }
        })?;
    }
    writeln!(
        out,
        "### False contacts at rest ({} rest pairs, seed {})\n",
        args.rest, args.seed
    )?;
    writeln!(out, "| thresholds | frames with a false contact |")?;
    writeln!(out, "|---|---|")?;
    for i in 0..n {
        writeln!(out, "| {} | {} / {} |", b.names[i], frames[i], args.rest)?;
    }
    writeln!(out)?;
    Ok(())
}

fn spacing(out: &mut Sink, args: &Args, sensor: &SyntheticSensor) -> Result<()> {
    let t = Instant::now();
    let mut b = Bench::new(args)?;
    let n = b.segs.len();
    let (nf, ns) = (args.spacing_forces.len(), args.spacings.len());
    let mut apart = vec![vec![vec![vec![0usize; ns]; nf]; 3]; n];
    let mut idx = 2_000_000u64;
    let debug = std::env::var_os("SPLIT_DEBUG").is_some();
    for (ii, &d) in INDENTERS_MM.iter().enumerate() {
        for (fi, &f) in args.spacing_forces.iter().enumerate() {
            for (si, &sp) in args.spacings.iter().enumerate() {
                for &c in &args.spacing_centres {
                    let (s1, s2) = (c - 0.5 * sp, c + 0.5 * sp);
                    let skin = &sensor.config().skin;
                    let rods = [
                        Press::rod(skin.arc_to_chord(s1), [0.0, 0.0, -f], d),
                        Press::rod(skin.arc_to_chord(s2), [0.0, 0.0, -f * args.ratio], d),
                    ];
                    let (p1, p2) = (rod_px(sensor, s1), rod_px(sensor, s2));
                    let r = sensor.render_indexed(idx, &[], false)?;
                    let o = sensor.render_indexed(idx + 1, &rods, false)?;
                    idx += 2;
                    b.dis.set_reference(&r.frame)?;
                    let scale = b.scale;
                    let names = b.names.clone();
                    b.each(&o.frame, |k, p, _| {
                        let (a, c2) = (covering(p, scale, p1), covering(p, scale, p2));
                        let ok = matches!((a, c2), (Some(a), Some(c2)) if a != c2);
                        if ok {
                            apart[k][ii][fi][si] += 1;
                        }
                        if debug {
                            let boxes: Vec<_> = p
                                .iter()
                                .map(|p| (p.bbox.x * 2, p.bbox.x_end() * 2))
                                .collect();
                            eprintln!(
                                "{}: d {d} f {f} sp {sp} c {c}: rods {p1:.0} {p2:.0} ok {ok} patches {boxes:?}",
                                names[k]
                            );
                        }
                    })?;
                }
            }
        }
    }
    let nc = args.spacing_centres.len();
    writeln!(
        out,
        "### Two rods told apart by the patches (each rod covered by its own patch), midpoints {:?} mm, \
         the second rod at {} times the first's force, seed {}\n",
        args.spacing_centres, args.ratio, args.seed
    )?;
    writeln!(
        out,
        "Smallest spacing from which every larger spacing of the list is told apart at every midpoint:\n"
    )?;
    write!(out, "| thresholds |")?;
    for &d in &INDENTERS_MM {
        for &f in &args.spacing_forces {
            write!(out, " {d} mm, {f} N |")?;
        }
    }
    writeln!(out)?;
    write!(out, "|---|")?;
    for _ in 0..3 * nf {
        write!(out, "---|")?;
    }
    writeln!(out)?;
    for k in 0..n {
        write!(out, "| {} |", b.names[k])?;
        for ii in 0..3 {
            for fi in 0..nf {
                let mut best = None;
                for si in 0..ns {
                    if apart[k][ii][fi][si] == nc {
                        best = Some(args.spacings[si]);
                    } else {
                        break;
                    }
                }
                match best {
                    Some(s) => write!(out, " {s} mm |")?,
                    None => write!(out, " > {} mm |", args.spacings[0])?,
                }
            }
        }
        writeln!(out)?;
    }
    writeln!(out)?;
    eprintln!("spacing: {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn run(args: Args) -> Result<()> {
    let mut out = Sink::stdout();
    let sensor = SyntheticSensor::new(SimConfig::default(), args.seed)?;
    if let Ok(spec) = std::env::var("SPLIT_PROFILE") {
        return profile(&mut out, &spec, &sensor);
    }
    let m = args.mode;
    if matches!(m, Mode::All | Mode::Spacing) {
        spacing(&mut out, &args, &sensor)?;
    }
    if matches!(m, Mode::All | Mode::Singles) {
        singles(&mut out, &args, &sensor)?;
    }
    if matches!(m, Mode::All | Mode::Rest) {
        rest(&mut out, &args, &sensor)?;
    }
    Ok(())
}

fn main() -> ExitCode {
    cli_support::finish(run(Cli::parse().resolve()).map(|()| ExitCode::SUCCESS))
}

/// `SPLIT_PROFILE=d,f,s1[,s2[,pitch]]`: prints the column sums of `u` over
/// the whole native flow and their smoothed derivative, for one case.
fn profile(out: &mut Sink, spec: &str, sensor: &SyntheticSensor) -> Result<()> {
    let p = cli_support::number_list(spec).map_err(|e| format!("SPLIT_PROFILE: {e}"))?;
    if !(3..=5).contains(&p.len()) {
        return Err("SPLIT_PROFILE: expected d,f,s1[,s2[,pitch]]".into());
    }
    let (d, f) = (p[0], p[1]);
    let pitch = p.get(4).copied().unwrap_or(0.0);
    let skin = &sensor.config().skin;
    let mut rods = vec![Press::rod(
        skin.arc_to_chord(p[2]),
        tilted_force(f, 0.0, pitch),
        d,
    )];
    if let Some(&s2) = p.get(3) {
        rods.push(Press::rod(
            skin.arc_to_chord(s2),
            tilted_force(f, 0.0, pitch),
            d,
        ));
    }
    let params = DisParams::preset(DisPreset::Accurate);
    let mut dis = Dis::new(params)?;
    dis.set_reference(&sensor.render_indexed(5, &[], false)?.frame)?;
    dis.compute_native(&sensor.render_indexed(6, &rods, false)?.frame)?;
    let (flow, _) = dis.native_flow().ok_or(Error::NoReference)?;
    let prof: Vec<f64> = (0..flow.width())
        .map(|x| flow.u.column(x).iter().map(|&v| v as f64).sum())
        .collect();
    let (mut sm, mut dv) = (Vec::new(), Vec::new());
    optical_tactile::segment::divergence_profile(&prof, 2, &mut sm, &mut dv);
    let rods_px: Vec<f64> = p[2..p.len().min(4)]
        .iter()
        .map(|&s| rod_px(sensor, s) / 2.0)
        .collect();
    writeln!(out, "# rods at native x {rods_px:?}")?;
    for x in (0..prof.len()).step_by(2) {
        writeln!(out, "{x} {:.2} {:.3}", prof[x], dv[x])?;
    }
    Ok(())
}
