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
//! cargo run --release --example split_check -- all
//! cargo run --release --example split_check -- singles --split 9,0.25,0.2 --split none
//! ```

use std::time::Instant;

use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
use optical_tactile::segment::{ContactPatch, Segmenter, SegmenterConfig, SplitRule, Thresholds};
use optical_tactile::sensor::ExtractorConfig;
use optical_tactile::{Error, Result};
use optical_tactile_sim::scenario::{INDENTERS_MM, TILTS_DEG, tilted_force};
use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};

struct Args {
    mode: String,
    seed: u64,
    rest: usize,
    positions: Vec<f64>,
    forces: Vec<f64>,
    spacings: Vec<f64>,
    spacing_forces: Vec<f64>,
    spacing_centres: Vec<f64>,
    splits: Vec<Option<SplitRule>>,
    margin: usize,
}

const HELP: &str = "usage: split_check [all|singles|rest|spacing] [options]
  --seed N              simulator seed, default 1
  --rest N              rest pairs, default 300
  --positions a,b,..    arc positions of single presses, mm (default -120,-80,-40,0,40,80,120)
  --forces a,b,..       single-press forces, N (default 0.5,1,1.5,2,3)
  --spacings a,b,..     two-rod spacings, mm (default 40,35,30,25,20,17.5,15,12.5,10,7.5,5)
  --spacing-forces      equal force of both rods, N (default 1.5,3)
  --spacing-centres     arc positions of the pair's midpoint, mm (default -60,0,60)
  --margin PX           patch margin, full-resolution px (default: the extractor's)
  --split s,d,m[,b]|none  split rule (smooth px, depth, min_peak, border px) to evaluate (repeatable;
                        default: SplitRule::DEFAULT and none)";

fn list(s: &str) -> Result<Vec<f64>> {
    s.split(',').map(num).collect()
}

fn num(s: &str) -> Result<f64> {
    s.trim()
        .parse::<f64>()
        .map_err(|e| Error::param("number", format!("`{s}`: {e}")))
}

fn parse_args() -> Result<Args> {
    let mut a = Args {
        mode: "all".into(),
        seed: 1,
        rest: 300,
        positions: vec![-120.0, -80.0, -40.0, 0.0, 40.0, 80.0, 120.0],
        forces: vec![0.5, 1.0, 1.5, 2.0, 3.0],
        spacings: vec![
            40.0, 35.0, 30.0, 25.0, 20.0, 17.5, 15.0, 12.5, 10.0, 7.5, 5.0,
        ],
        spacing_forces: vec![1.5, 3.0],
        spacing_centres: vec![-60.0, 0.0, 60.0],
        splits: Vec::new(),
        margin: ExtractorConfig::default().margin_px,
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut val = |name: &str| it.next().ok_or_else(|| Error::param(name, "missing value"));
        match arg.as_str() {
            "-h" | "--help" => {
                println!("{HELP}");
                std::process::exit(0);
            }
            "all" | "singles" | "rest" | "spacing" => a.mode = arg.clone(),
            "--seed" => a.seed = num(&val("--seed")?)? as u64,
            "--rest" => a.rest = num(&val("--rest")?)? as usize,
            "--positions" => a.positions = list(&val("--positions")?)?,
            "--forces" => a.forces = list(&val("--forces")?)?,
            "--spacings" => a.spacings = list(&val("--spacings")?)?,
            "--spacing-forces" => a.spacing_forces = list(&val("--spacing-forces")?)?,
            "--spacing-centres" => a.spacing_centres = list(&val("--spacing-centres")?)?,
            "--margin" => a.margin = num(&val("--margin")?)? as usize,
            "--split" => {
                let v = val("--split")?;
                if v == "none" {
                    a.splits.push(None);
                } else {
                    let p = list(&v)?;
                    if p.len() < 3 {
                        return Err(Error::param(
                            "--split",
                            "need smooth,depth,min_peak[,border]",
                        ));
                    }
                    let r = SplitRule {
                        smooth: p[0] as usize,
                        depth: p[1] as f32,
                        min_peak: p[2] as f32,
                        border: p.get(3).map_or(SplitRule::DEFAULT.border, |&b| b as usize),
                    };
                    r.validate()?;
                    a.splits.push(Some(r));
                }
            }
            _ => return Err(Error::param("argument", format!("unknown `{arg}`\n{HELP}"))),
        }
    }
    if a.splits.is_empty() {
        a.splits = vec![Some(SplitRule::DEFAULT), None];
    }
    Ok(a)
}

fn split_name(s: &Option<SplitRule>) -> String {
    match s {
        None => "none".into(),
        Some(r) => format!("{},{},{},{}", r.smooth, r.depth, r.min_peak, r.border),
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

fn singles(args: &Args, sensor: &SyntheticSensor) -> Result<()> {
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
    println!(
        "### Single presses ({} presses: {} positions x {} tilts x forces {:?} N x 3 rods, seed {})\n",
        total,
        args.positions.len(),
        TILTS_DEG.len(),
        args.forces,
        args.seed
    );
    println!(
        "| thresholds | presses cut by the split rule (spurious splits) | detected | presses with > 1 patch | patches |"
    );
    println!("|---|---|---|---|---|");
    for k in 0..n {
        println!(
            "| {} | {} / {total} | {} / {total} | {} | {} |",
            b.names[k], cut[k], det[k], multi[k], patches[k]
        );
    }
    println!();
    eprintln!("singles: {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn rest(args: &Args, sensor: &SyntheticSensor) -> Result<()> {
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
    println!(
        "### False contacts at rest ({} rest pairs, seed {})\n",
        args.rest, args.seed
    );
    println!("| thresholds | frames with a false contact |");
    println!("|---|---|");
    for i in 0..n {
        println!("| {} | {} / {} |", b.names[i], frames[i], args.rest);
    }
    println!();
    Ok(())
}

fn spacing(args: &Args, sensor: &SyntheticSensor) -> Result<()> {
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
                        Press::rod(skin.arc_to_chord(s2), [0.0, 0.0, -f], d),
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
    println!(
        "### Two rods told apart by the patches (each rod covered by its own patch), midpoints {:?} mm, seed {}\n",
        args.spacing_centres, args.seed
    );
    println!(
        "Smallest spacing from which every larger spacing of the list is told apart at every midpoint:\n"
    );
    print!("| thresholds |");
    for &d in &INDENTERS_MM {
        for &f in &args.spacing_forces {
            print!(" {d} mm, {f} N |");
        }
    }
    println!();
    print!("|---|");
    for _ in 0..3 * nf {
        print!("---|");
    }
    println!();
    for k in 0..n {
        print!("| {} |", b.names[k]);
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
                    Some(s) => print!(" {s} mm |"),
                    None => print!(" > {} mm |", args.spacings[0]),
                }
            }
        }
        println!();
    }
    println!();
    eprintln!("spacing: {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn main() -> Result<()> {
    let args = parse_args()?;
    let sensor = SyntheticSensor::new(SimConfig::default(), args.seed)?;
    if let Ok(spec) = std::env::var("SPLIT_PROFILE") {
        return profile(&spec, &sensor);
    }
    let m = args.mode.as_str();
    if m == "all" || m == "spacing" {
        spacing(&args, &sensor)?;
    }
    if m == "all" || m == "singles" {
        singles(&args, &sensor)?;
    }
    if m == "all" || m == "rest" {
        rest(&args, &sensor)?;
    }
    Ok(())
}

/// `SPLIT_PROFILE=d,f,s1[,s2[,pitch]]`: prints the column sums of `u` over
/// the whole native flow and their smoothed derivative, for one case.
fn profile(spec: &str, sensor: &SyntheticSensor) -> Result<()> {
    let p = list(spec)?;
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
    println!("# rods at native x {rods_px:?}");
    for x in (0..prof.len()).step_by(2) {
        println!("{x} {:.2} {:.3}", prof[x], dv[x]);
    }
    Ok(())
}
