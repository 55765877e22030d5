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
//! through the default (accurate) DIS flow at its native resolution, as in
//! [`ContactExtractor`].
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

use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
use optical_tactile::morphology::Shape;
use optical_tactile::segment::{ContactPatch, Segmenter, SegmenterConfig, Thresholds};
use optical_tactile::sensor::{ContactExtractor, ExtractorConfig};
use optical_tactile::sim::scenario::tilted_force;
use optical_tactile::sim::{Contact, SimConfig, SyntheticSensor};
use optical_tactile::{Error, Result};

const INDENTERS_MM: [f64; 3] = [2.0, 5.0, 10.0];
/// The characterization protocol's tilts `(yaw, pitch)`, degrees.
const TILTS_DEG: [(f64, f64); 5] = [
    (0.0, 0.0),
    (0.0, 15.0),
    (0.0, -15.0),
    (15.0, 0.0),
    (-15.0, 0.0),
];

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
    sets: Vec<(String, Thresholds)>,
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
    let presets = vec![
        ("LOW".to_string(), Thresholds::LOW),
        ("MID".to_string(), Thresholds::MID),
        ("HIGH".to_string(), Thresholds::HIGH),
    ];
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
                a.sets.push((v.clone(), t));
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

/// Image column (full-resolution strip pixels) of a rod at arc position `s`.
fn rod_px(sensor: &SyntheticSensor, s: f64) -> f64 {
    let c = sensor.config();
    c.camera.s_to_px(&c.skin, s)
}

/// Does a patch (native-resolution box) cover column `x_px` (full resolution)?
fn covers(p: &ContactPatch, scale: f64, x_px: f64) -> bool {
    let x0 = p.bbox.x as f64 * scale;
    let x1 = (p.bbox.x + p.bbox.width) as f64 * scale;
    (x0..=x1).contains(&x_px)
}

/// One DIS (accurate preset) and one segmenter per threshold set, run on the
/// same native flow.
struct Bench {
    dis: Dis,
    segs: Vec<Segmenter>,
    patches: Vec<ContactPatch>,
    scale: f64,
}

impl Bench {
    fn new(args: &Args) -> Result<Self> {
        let params = DisParams::preset(DisPreset::Accurate);
        let scale = (1usize << params.finest_scale) as f64;
        let segs = args
            .sets
            .iter()
            .map(|(_, t)| {
                Segmenter::new(SegmenterConfig {
                    thresholds: *t,
                    margin: args.margin,
                    scale,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Bench {
            dis: Dis::new(params)?,
            segs,
            patches: Vec::new(),
            scale,
        })
    }

    /// Computes the flow of `frame` against the current reference, then calls
    /// `f(set index, patches)` for every threshold set.
    fn each(
        &mut self,
        frame: &ndarray::Array2<f32>,
        mut f: impl FnMut(usize, &[ContactPatch]),
    ) -> Result<()> {
        self.dis.compute_native(frame)?;
        let (flow, _) = self.dis.native_flow().ok_or(Error::NoReference)?;
        for (k, seg) in self.segs.iter_mut().enumerate() {
            seg.segment_into(flow, &mut self.patches)?;
            f(k, &self.patches);
        }
        Ok(())
    }

    /// Largest `|flow|` of the last frame, full-resolution pixels.
    fn peak(&self) -> f64 {
        let (flow, _) = self.dis.native_flow().expect("computed");
        flow.u
            .iter()
            .zip(flow.v.iter())
            .map(|(u, v)| u.hypot(*v) as f64)
            .fold(0.0, f64::max)
            * self.scale
    }
}

fn rest(args: &Args, sensor: &SyntheticSensor) -> Result<()> {
    let t = Instant::now();
    let mut bench = Bench::new(args)?;
    let n = args.sets.len();
    let mut false_frames = vec![0usize; n];
    let mut false_patches = vec![0usize; n];
    let mut peaks = Vec::with_capacity(args.rest);
    let mut sums = vec![0.0f64; n];
    // Frame indices far from the other modes' so the noise is fresh.
    let base = 1_000_000u64;
    for k in 0..args.rest as u64 {
        let r = sensor.render_indexed(base + 2 * k, &[], false)?;
        let o = sensor.render_indexed(base + 2 * k + 1, &[], false)?;
        bench.dis.set_reference(&r.frame)?;
        let mut segs_max = vec![0.0f64; n];
        bench.each(&o.frame, |i, p| {
            if !p.is_empty() {
                false_frames[i] += 1;
                false_patches[i] += p.len();
            }
            segs_max[i] = 0.0;
        })?;
        for (i, seg) in bench.segs.iter().enumerate() {
            let s3 = bench.scale.powi(3);
            let m = seg.contour_sums().iter().copied().fold(0.0, f64::max) * s3;
            segs_max[i] = m;
            sums[i] = sums[i].max(m);
        }
        peaks.push(bench.peak());
    }
    peaks.sort_by(f64::total_cmp);
    let q = |p: f64| peaks[((p * peaks.len() as f64) as usize).min(peaks.len() - 1)];
    println!(
        "### False contacts at rest ({} rest pairs, seed {})\n",
        args.rest, args.seed
    );
    println!(
        "Peak |flow| per rest pair (full-resolution px): median {:.3}, 99th percentile {:.3}, max {:.3}.\n",
        q(0.5),
        q(0.99),
        peaks[peaks.len() - 1]
    );
    println!(
        "| thresholds | frames with a false contact | false patches | largest contour sum at rest |"
    );
    println!("|---|---|---|---|");
    for (i, (name, _)) in args.sets.iter().enumerate() {
        println!(
            "| {name} | {} / {} | {} | {:.0} |",
            false_frames[i], args.rest, false_patches[i], sums[i]
        );
    }
    eprintln!("rest: {:.1} s", t.elapsed().as_secs_f64());
    println!();
    Ok(())
}

fn mdf(args: &Args, sensor: &SyntheticSensor) -> Result<()> {
    let t = Instant::now();
    let mut bench = Bench::new(args)?;
    let (n, nf) = (args.sets.len(), args.forces.len());
    // hit[set][indenter][force], out of `per` presses each.
    let mut hit = vec![vec![vec![0usize; nf]; 3]; n];
    let mut stray = vec![0usize; n];
    let per = args.positions.len() * TILTS_DEG.len();
    let mut idx = 0u64;
    let debug = std::env::var_os("SWEEP_DEBUG").is_some();
    for (ii, &d) in INDENTERS_MM.iter().enumerate() {
        for &s in &args.positions {
            let x = sensor.config().skin.arc_to_chord(s);
            let xp = rod_px(sensor, s);
            for &(yaw, pitch) in &TILTS_DEG {
                // One fresh reference per condition, a fresh frame per force.
                let r = sensor.render_indexed(idx, &[], false)?;
                idx += 1;
                bench.dis.set_reference(&r.frame)?;
                for (fi, &f) in args.forces.iter().enumerate() {
                    let rod = Contact::rod(x, tilted_force(f, yaw, pitch), d);
                    let o = sensor.render_indexed(idx, &[rod], false)?;
                    idx += 1;
                    let scale = bench.scale;
                    bench.each(&o.frame, |k, p| {
                        if p.iter().any(|p| covers(p, scale, xp)) {
                            hit[k][ii][fi] += 1;
                        }
                        if debug && f >= 0.8 && p.iter().any(|p| !covers(p, scale, xp)) {
                            let boxes: Vec<_> = p
                                .iter()
                                .map(|p| (p.bbox.x as f64 * scale, p.bbox.x_end() as f64 * scale))
                                .collect();
                            eprintln!(
                                "miss set {k} d {d} s {s} tilt ({yaw},{pitch}) f {f}: rod {xp:.0} boxes {boxes:?}"
                            );
                        }
                        stray[k] += p.iter().filter(|p| !covers(p, scale, xp)).count();
                    })?;
                }
            }
        }
    }
    let min_force_at = |h: &[usize], rate: f64| -> Option<f64> {
        // Smallest ladder force from which every larger one is detected in >= rate.
        let mut best = None;
        for fi in (0..nf).rev() {
            if h[fi] as f64 >= rate * per as f64 - 1e-9 {
                best = Some(args.forces[fi]);
            } else {
                break;
            }
        }
        best
    };
    println!(
        "### Minimum detectable force ({} positions x {} tilts per indenter and force, seed {})\n",
        args.positions.len(),
        TILTS_DEG.len(),
        args.seed
    );
    println!(
        "Smallest force of the ladder from which >= 95% of presses are detected (a patch covering the rod).\n"
    );
    let min_force = |h: &[usize]| min_force_at(h, 0.95);
    println!(
        "| thresholds | 2 mm | 5 mm | 10 mm | all indenters | every press (100%) from | patches away from the rod |"
    );
    println!("|---|---|---|---|---|---|---|");
    let fmt = |v: Option<f64>| v.map_or("> ladder".to_string(), |f| format!("{f:.1} N"));
    for (k, (name, _)) in args.sets.iter().enumerate() {
        let each: Vec<Option<f64>> = (0..3).map(|i| min_force(&hit[k][i])).collect();
        let all = each.iter().try_fold(0.0f64, |m, v| v.map(|v| m.max(v)));
        let every = (0..3)
            .map(|i| min_force_at(&hit[k][i], 1.0))
            .try_fold(0.0f64, |m, v| v.map(|v| m.max(v)));
        println!(
            "| {name} | {} | {} | {} | **{}** | {} | {} |",
            fmt(each[0]),
            fmt(each[1]),
            fmt(each[2]),
            fmt(all),
            fmt(every),
            stray[k]
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
    for (k, (name, _)) in args.sets.iter().enumerate() {
        print!("| {name} |");
        for fi in 0..nf {
            let h: usize = (0..3).map(|i| hit[k][i][fi]).sum();
            print!(" {:.0}% |", 100.0 * h as f64 / (3 * per) as f64);
        }
        println!();
    }
    println!();
    eprintln!("mdf: {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn spacing(args: &Args, sensor: &SyntheticSensor) -> Result<()> {
    let t = Instant::now();
    let mut extractors = args
        .sets
        .iter()
        .map(|(_, th)| {
            ContactExtractor::new(ExtractorConfig {
                thresholds: *th,
                margin_px: args.margin,
                ..ExtractorConfig::default()
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let px_per_mm = sensor.config().camera.px_per_mm_s;
    let tol = args.tol_mm * px_per_mm;
    let (n, ns) = (args.sets.len(), args.spacings.len());
    // apart[set][indenter][force][spacing]: pairs told apart (out of the centres).
    let mut apart = vec![vec![vec![vec![0usize; ns]; args.spacing_forces.len()]; 3]; n];
    let mut idx = 2_000_000u64;
    let debug = std::env::var_os("SWEEP_DEBUG").is_some();
    for (ii, &d) in INDENTERS_MM.iter().enumerate() {
        for (fi, &f) in args.spacing_forces.iter().enumerate() {
            for (si, &sp) in args.spacings.iter().enumerate() {
                for &c in &args.spacing_centres {
                    let (s1, s2) = (c - 0.5 * sp, c + 0.5 * sp);
                    let skin = &sensor.config().skin;
                    let rods = [
                        Contact::rod(skin.arc_to_chord(s1), [0.0, 0.0, -f], d),
                        Contact::rod(skin.arc_to_chord(s2), [0.0, 0.0, -f], d),
                    ];
                    let (p1, p2) = (rod_px(sensor, s1), rod_px(sensor, s2));
                    let r = sensor.render_indexed(idx, &[], false)?;
                    let o = sensor.render_indexed(idx + 1, &rods, false)?;
                    idx += 2;
                    for (k, ex) in extractors.iter_mut().enumerate() {
                        ex.set_reference(&r.frame)?;
                        let raws = ex.extract(&o.frame)?.to_vec();
                        if debug {
                            let got: Vec<_> = raws
                                .iter()
                                .map(|r| (r.x_px.round(), r.bbox.x, r.bbox.x + r.bbox.w))
                                .collect();
                            let cores: Vec<_> = ex
                                .segmenter()
                                .contour_boxes()
                                .iter()
                                .map(|b| (b.x * 2, b.x_end() * 2))
                                .collect();
                            eprintln!(
                                "set {k} d {d} f {f} sp {sp} c {c}: rods {p1:.0} {p2:.0} got {got:?} contours {cores:?}"
                            );
                        }
                        if raws.len() == 2 {
                            let mut xs = [raws[0].x_px, raws[1].x_px];
                            xs.sort_by(f64::total_cmp);
                            if (xs[0] - p1).abs() <= tol && (xs[1] - p2).abs() <= tol {
                                apart[k][ii][fi][si] += 1;
                            }
                        }
                    }
                }
            }
        }
    }
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
    print!("| thresholds |");
    for &d in &INDENTERS_MM {
        for &f in &args.spacing_forces {
            print!(" {d} mm, {f} N |");
        }
    }
    println!();
    print!("|---|");
    for _ in 0..3 * args.spacing_forces.len() {
        print!("---|");
    }
    println!();
    for (k, (name, _)) in args.sets.iter().enumerate() {
        print!("| {name} |");
        for ii in 0..3 {
            for fi in 0..args.spacing_forces.len() {
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
    println!(
        "\nPairs told apart per spacing (out of {nc} midpoints), indenter/force in the column order above:\n"
    );
    print!("| thresholds | spacing |");
    for &d in &INDENTERS_MM {
        for &f in &args.spacing_forces {
            print!(" {d} mm, {f} N |");
        }
    }
    println!();
    print!("|---|---|");
    for _ in 0..3 * args.spacing_forces.len() {
        print!("---|");
    }
    println!();
    for (k, (name, _)) in args.sets.iter().enumerate() {
        for (si, sp) in args.spacings.iter().enumerate() {
            print!("| {name} | {sp} mm |");
            for ii in 0..3 {
                for fi in 0..args.spacing_forces.len() {
                    print!(" {} |", apart[k][ii][fi][si]);
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
    for (name, t) in &args.sets {
        println!(
            "| {name} | {} | {} | {} | {} | {:?} |",
            t.magnitude, t.sum, t.erode, t.dilate, t.shape
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
