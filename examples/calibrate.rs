//! Calibrates a sensor from a characterization dataset (DATASET.md).
//!
//! ```text
//! cargo run --release --example calibrate -- DATASET_DIR [--thresholds low|mid|high|all]
//!     [--thresholds-custom MAGNITUDE,SUM] [--contact-point slope[:SIGMA]|centroid[:HALF]|argmin]
//!     [--shear-order N]
//!     [--preset fast|accurate|...] [--crop x,y,w,h] [--predictions FILE] --out calibration.json
//! ```
//!
//! Runs the pipeline on every test (each frame against its own reference) on
//! all cores, fits the five polynomial maps with the paper's order search and
//! prints, in markdown, Table I (per threshold preset: minimum detectable force,
//! test MAE of x, Fx, Fy, Fz) and Table II (test MAE per point), and between
//! them the load cell's floor: how much the recorded force scatters between
//! repetitions of a test, and the MAE a sensor reading the applied force
//! exactly would score against it (`characterize::load_cell_spread`). With
//! `--thresholds all` the presets are fitted in turn; `--out` gets the `high`
//! one (the paper's flight setting) and the others are written beside it as
//! `NAME.low.json` and `NAME.mid.json`. `--thresholds-custom M,S` fits with
//! flow magnitude `M` px and patch sum `S` (full-resolution units) and the
//! `low` kernels, labelled `custom`. `--contact-point` chooses how a contact's
//! column is measured: `slope` (default, the steepest rise of the along-arc
//! profile smoothed by a Gaussian of SIGMA px, default 8), `centroid` (the
//! energy centroid in a window of half-width HALF px, default 400) or
//! `argmin` (argmin of D, the paper's); `--contact-window PX` is the older
//! spelling of `centroid:PX` (0 = argmin). `--shear-order N` the largest order of the shear ratio in `g1`
//! (default 2; 0 = the paper's `g1(x2d)`). `y2d` stays out of the force maps
//! unless `--force-y2d` is given (the rods span the width: it only carries noise).
//! `--force-order N` is the force maps' largest displacement order (default 5),
//! `--dpf-order N` their largest `d_pf` order (default 2, 0 leaves it out) and
//! `--shear-order-force N` caps the shear displacements `dx, dy` at order N
//! inside that (default 0: no cap; see `FitOptions::shear_max_order`).
//! `--guard-shear-order N` is the shear order of the fallback force maps that
//! take over where the full maps are not trusted (default 2; 0 fits no guard;
//! see `calibration::ForceGuard`).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use optical_tactile::calibration::fit::{
    extract_dataset, fit_dataset, load_cell_spread, read_dataset,
};
use optical_tactile::calibration::{self, FitOptions, GuardOptions, ThresholdRow};
use optical_tactile::contact::ContactPointMethod;
use optical_tactile::flow::dis::{DisParams, DisPreset};
use optical_tactile::frame::Roi;
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::io::{self, FrameRecord, JsonlWriter, Split};
use optical_tactile::segment::Thresholds;
use optical_tactile::sensor::ExtractorConfig;

const USAGE: &str = "usage: calibrate DATASET_DIR --out calibration.json [--thresholds low|mid|high|all (default high)] \
[--thresholds-custom MAGNITUDE,SUM] [--contact-point slope[:SIGMA]|centroid[:HALF]|argmin (default slope:8)] [--contact-window PX] [--shear-order N (default 2)] [--force-order N (default 5)] [--dpf-order N (default 2)] [--shear-order-force N (default 0: one displacement group)] [--guard-shear-order N (default 2, 0: no guard)] [--force-y2d] \
[--preset ultrafast|fast|medium|accurate|balanced|fine (default fine, the sensor's)] [--crop x,y,w,h] [--predictions FILE]";

struct Args {
    dir: PathBuf,
    out: PathBuf,
    presets: Vec<&'static str>,
    custom: Option<(f32, f32)>,
    contact_point: ContactPointMethod,
    shear_order: u32,
    force_order: u32,
    dpf_order: u32,
    shear_force_order: Option<u32>,
    guard: Option<GuardOptions>,
    force_y2d: bool,
    /// `--preset`; `None`: the sensor's default (`ExtractorConfig::default`).
    flow: Option<DisPreset>,
    crop: Option<Roi>,
    predictions: Option<PathBuf>,
}

/// `slope[:SIGMA]`, `centroid[:HALF]` or `argmin`.
fn parse_contact_point(v: &str) -> Result<ContactPointMethod, String> {
    let (name, num) = match v.split_once(':') {
        Some((n, x)) => (n, Some(x)),
        None => (v, None),
    };
    let given = num.is_some();
    let num = |default: f64| -> Result<f64, String> {
        match num {
            None => Ok(default),
            Some(x) => x
                .parse::<f64>()
                .ok()
                .filter(|x| *x > 0.0 && x.is_finite())
                .ok_or(format!(
                    "--contact-point: expected a positive number after `:`, got `{x}`"
                )),
        }
    };
    match name {
        "slope" => Ok(ContactPointMethod::SlopePeak {
            sigma_px: num(8.0)?,
        }),
        "centroid" => Ok(ContactPointMethod::EnergyCentroid {
            half_window_px: num(400.0)?,
        }),
        "argmin" if !given => Ok(ContactPointMethod::PotentialMinimum),
        _ => Err(format!(
            "--contact-point: expected slope[:SIGMA], centroid[:HALF] or argmin, got `{v}`"
        )),
    }
}

/// A polynomial order option's value, within `range`.
fn order(name: &str, v: &str, range: std::ops::RangeInclusive<u32>) -> Result<u32, String> {
    v.parse().ok().filter(|n| range.contains(n)).ok_or(format!(
        "{name}: expected {}..={}, got `{v}`",
        range.start(),
        range.end()
    ))
}

fn parse() -> Result<Option<Args>, String> {
    let mut dir = None;
    let mut out = None;
    let mut presets = vec!["high"];
    let mut flow = None;
    let mut crop = None;
    let mut predictions = None;
    let mut custom = None;
    let mut contact_point = ContactPointMethod::DEFAULT;
    let mut shear_order = FitOptions::default().location_shear_order;
    let mut force_order = FitOptions::default().displacement_max_order;
    let mut dpf_order = FitOptions::default().d_pf_max_order;
    let mut shear_force_order = FitOptions::default().shear_max_order;
    let mut guard = FitOptions::default().guard;
    // The characterization rods span the skin's width, so y2d carries only
    // noise into the force maps (measured: Fx 0.082 -> 0.063 N, Fz 0.30 ->
    // 0.24 N test MAE without it): off unless asked for.
    let mut force_y2d = false;
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        let mut val = |name: &str| it.next().ok_or(format!("{name} needs a value"));
        match a.as_str() {
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(None);
            }
            "--out" => out = Some(PathBuf::from(val("--out")?)),
            "--thresholds" => {
                presets = match val("--thresholds")?.as_str() {
                    "low" => vec!["low"],
                    "mid" => vec!["mid"],
                    "high" => vec!["high"],
                    "all" => vec!["high", "mid", "low"],
                    v => {
                        return Err(format!(
                            "--thresholds: expected low, mid, high or all, got `{v}`"
                        ));
                    }
                }
            }
            "--thresholds-custom" => {
                let v = val("--thresholds-custom")?;
                let parts: Vec<Result<f32, _>> = v.split(',').map(|p| p.trim().parse()).collect();
                match parts.as_slice() {
                    [Ok(m), Ok(s)] if *m > 0.0 && *s >= 0.0 => {
                        custom = Some((*m, *s));
                        presets = vec!["custom"];
                    }
                    _ => {
                        return Err(format!(
                            "--thresholds-custom: expected MAGNITUDE,SUM (positive numbers), got `{v}`"
                        ));
                    }
                }
            }
            "--force-y2d" => force_y2d = true,
            "--contact-window" => {
                let v = val("--contact-window")?;
                let w: u32 = v
                    .parse()
                    .map_err(|_| format!("--contact-window: expected pixels >= 0, got `{v}`"))?;
                contact_point = match w {
                    0 => ContactPointMethod::PotentialMinimum,
                    w => ContactPointMethod::EnergyCentroid {
                        half_window_px: f64::from(w),
                    },
                };
            }
            "--contact-point" => contact_point = parse_contact_point(&val("--contact-point")?)?,
            "--shear-order" => shear_order = order("--shear-order", &val("--shear-order")?, 0..=5)?,
            "--force-order" => force_order = order("--force-order", &val("--force-order")?, 1..=6)?,
            "--dpf-order" => dpf_order = order("--dpf-order", &val("--dpf-order")?, 0..=4)?,
            "--shear-order-force" => {
                let n = order("--shear-order-force", &val("--shear-order-force")?, 0..=6)?;
                shear_force_order = (n > 0).then_some(n);
            }
            "--guard-shear-order" => {
                let n = order("--guard-shear-order", &val("--guard-shear-order")?, 0..=6)?;
                guard = (n > 0).then(|| GuardOptions {
                    shear_order: n,
                    ..GuardOptions::default()
                });
            }
            "--preset" => {
                flow = Some(DisPreset::parse(&val("--preset")?).map_err(|e| e.to_string())?)
            }
            "--crop" => crop = Some(Roi::parse(&val("--crop")?).map_err(|e| e.to_string())?),
            "--predictions" => predictions = Some(PathBuf::from(val("--predictions")?)),
            _ if a.starts_with("--") => return Err(format!("unknown option {a}\n{USAGE}")),
            _ if dir.is_none() => dir = Some(PathBuf::from(a)),
            _ => return Err(format!("unexpected argument `{a}`\n{USAGE}")),
        }
    }
    Ok(Some(Args {
        dir: dir.ok_or(USAGE)?,
        out: out.ok_or(format!("--out is required\n{USAGE}"))?,
        presets,
        custom,
        contact_point,
        shear_order,
        force_order,
        dpf_order,
        shear_force_order,
        guard,
        force_y2d,
        flow,
        crop,
        predictions,
    }))
}

fn thresholds(name: &str, custom: Option<(f32, f32)>) -> Thresholds {
    match name {
        "custom" => {
            let (magnitude, sum) =
                custom.unwrap_or((Thresholds::LOW.magnitude, Thresholds::LOW.sum));
            Thresholds {
                magnitude,
                sum,
                ..Thresholds::LOW
            }
        }
        "low" => Thresholds::LOW,
        "mid" => Thresholds::MID,
        _ => Thresholds::HIGH,
    }
}

fn sibling(out: &Path, preset: &str) -> PathBuf {
    let stem = out
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    out.with_file_name(format!("{stem}.{preset}.json"))
}

fn run() -> Result<(), String> {
    let Some(args) = parse()? else { return Ok(()) };
    let err = |e: optical_tactile::Error| e.to_string();
    let rows = read_dataset(&args.dir).map_err(err)?;
    // The crop the pixel coordinates refer to: given, or the whole image.
    let crop = match args.crop {
        Some(c) => c,
        None => {
            let img = io::read_gray(args.dir.join(&rows[0].reference)).map_err(err)?;
            Roi::full(img.ncols(), img.nrows())
        }
    };
    let threads = rayon::current_num_threads();
    eprintln!(
        "{} tests in {}, {} threads",
        rows.len(),
        args.dir.display(),
        threads
    );
    let mut table_i = Vec::new();
    let mut table_ii = Vec::new();
    for (k, preset) in args.presets.iter().enumerate() {
        let mut config = ExtractorConfig {
            thresholds: thresholds(preset, args.custom),
            ..ExtractorConfig::default()
        };
        if let Some(p) = args.flow {
            config.flow = DisParams::preset(p);
        }
        let t0 = Instant::now();
        let step = (rows.len() / 20).max(1);
        let progress = |done: usize, total: usize| {
            if done % step == 0 || done == total {
                eprint!(
                    "\r[{preset}] {done}/{total} tests, {:.0} s  ",
                    t0.elapsed().as_secs_f64()
                );
                let _ = std::io::stderr().flush();
            }
        };
        let ex = extract_dataset(
            &args.dir,
            &rows,
            &config,
            args.contact_point,
            args.crop,
            &progress,
        )
        .map_err(err)?;
        eprintln!();
        let options = FitOptions {
            location_shear_order: args.shear_order,
            displacement_max_order: args.force_order,
            d_pf_max_order: args.dpf_order,
            shear_max_order: args.shear_force_order,
            guard: args.guard,
            force_use_y2d: args.force_y2d,
            ..FitOptions::default()
        };
        let fit = fit_dataset(
            &ex,
            &config,
            args.contact_point,
            crop,
            SensorGeometry::default(),
            &options,
        )
        .map_err(err)?;
        eprintln!(
            "[{preset}] fitted in {:.1} s; misses train/val/test: {}/{}/{}",
            t0.elapsed().as_secs_f64(),
            fit.misses[0],
            fit.misses[1],
            fit.misses[2]
        );
        if let Some(g) = &fit.calibration.guard {
            let test: Vec<_> = fit
                .samples
                .iter()
                .flatten()
                .filter(|s| s.split == Split::Test)
                .collect();
            let mut fallback = 0;
            for s in &test {
                let v = s.force_inputs();
                fallback += usize::from(fit.calibration.force_checked(&v).map_err(err)?.1);
            }
            let [tx, ty, tz] = g.tolerance_n;
            eprintln!(
                "[{preset}] force guard: tolerance Fx {tx:.3}, Fy {ty:.3}, Fz {tz:.3} N; \
                 {fallback} of {} test rows read by the fallback maps",
                test.len()
            );
        }
        let path = if k == 0 {
            args.out.clone()
        } else {
            sibling(&args.out, preset)
        };
        fit.calibration.save(&path).map_err(err)?;
        eprintln!("[{preset}] wrote {}", path.display());
        if k == 0 {
            if let Some(pred) = &args.predictions {
                let mut w = JsonlWriter::create(pred).map_err(err)?;
                for (e, s) in ex
                    .iter()
                    .zip(&fit.samples)
                    .filter(|(e, _)| e.row.split == Split::Test)
                {
                    let mut contacts = Vec::new();
                    if let Some(s) = s {
                        let p = fit.calibration.predict(s).map_err(err)?;
                        contacts.push(io::ContactRecord {
                            x_mm: p.x_mm,
                            y_mm: p.y_mm,
                            z_mm: p.z_mm,
                            fx_n: p.fx,
                            fy_n: p.fy,
                            fz_n: p.fz,
                            x_px: Some(s.x2d),
                            y_px: Some(s.y2d),
                            d_pf: Some(s.d_pf),
                            dx: Some(s.dx),
                            dy: Some(s.dy),
                            dz: Some(s.dz),
                            ..Default::default()
                        });
                    }
                    w.write(&FrameRecord {
                        frame: e.row.frame.clone(),
                        t_s: 0.0,
                        contacts,
                        latency_ms: None,
                    })
                    .map_err(err)?;
                }
            }
        }
        table_i.push(ThresholdRow {
            preset: preset.to_string(),
            min_force_n: fit.min_force.to_string(),
            mae: fit.test_table.total,
        });
        table_ii.push((preset.to_string(), fit.test_table));
    }
    println!("## Table I: test-set errors per threshold preset\n");
    println!("{}", calibration::table_i_markdown(&table_i));
    if let Some(s) = load_cell_spread(&rows) {
        let [sx, sy, sz] = s.sigma_n;
        let [mx, my, mz] = s.mae_floor_n();
        println!(
            "Load cell: its readings scatter by Fx {sx:.4}, Fy {sy:.4}, Fz {sz:.4} N (standard \
             deviation) between repetitions of the same test ({} groups). A sensor that read the \
             applied force exactly would score about Fx {mx:.4}, Fy {my:.4}, Fz {mz:.4} N MAE \
             against these recordings: the floor under the force columns above.\n",
            s.groups
        );
    }
    for (preset, t) in &table_ii {
        println!("## Table II: test-set errors per point ({preset} thresholds)\n");
        println!("{}", calibration::table_ii_markdown(t));
    }
    Ok(())
}

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
