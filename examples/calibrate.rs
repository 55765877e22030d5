//! Calibrates a sensor from a characterization dataset (docs/formats.md).
//!
//! ```text
//! cargo run --release --example calibrate -- DATASET_DIR [--thresholds low|mid|high|all]
//!     [--thresholds-custom MAGNITUDE,SUM]
//!     [--contact-point slope[:SIGMA]|slope2d[:SIGMA]|lines[:SIGMA]|centroid[:HALF]|argmin]
//!     [--geometry strip|flat:LENGTHxWIDTH] [--shear-order N]
//!     [--preset fast|accurate|...] [--crop x,y,w,h] [--predictions FILE] --out calibration.json
//! ```
//!
//! Runs the pipeline on every test (each frame against its own reference) on
//! all cores, fits the five polynomial maps with the paper's order search and
//! prints, in markdown, Table I (per threshold preset: minimum detectable force,
//! test MAE of x, Fx, Fy, Fz), Table II (test MAE per point) and the test MAE
//! per indenter and commanded force, and between Tables I and II the load
//! cell's floor: how much the recorded force scatters between
//! repetitions of a test, and the MAE a sensor reading the applied force
//! exactly would score against it (`characterize::load_cell_spread`). With
//! `--thresholds all` the presets are fitted in turn; `--out` gets the `high`
//! one (the paper's flight setting) and the others are written beside it as
//! `NAME.low.json` and `NAME.mid.json`. `--thresholds-custom M,S` fits with
//! flow magnitude `M` px and patch sum `S` (full-resolution units) and the
//! `low` kernels, labelled `custom`. `--geometry` is the sensor's surface: the
//! dataset's `geometry.json` when it has one, else the paper's curved strip
//! (`strip`); `flat:24x18` is a flat gel 24 mm along x (image columns) by
//! 18 mm along y. On a flat sensor contacts are located in 2-D: both location
//! maps take `(x2d, y2d)`, `y2d` enters the force maps and the contact point
//! defaults to `lines:16`. `--contact-point` chooses how a contact's
//! column is measured: `slope` (default on the strip, the steepest rise of the along-arc
//! profile smoothed by a Gaussian of SIGMA px, default 8), `slope2d` (the same
//! along both image axes), `lines` (where the lines along the followed dots'
//! motion meet, about the `slope2d` point of SIGMA px, default 16; the
//! default on a flat sensor; without followed dots it is `slope2d`), `centroid` (the
//! energy centroid in a window of half-width HALF px, default 400) or
//! `argmin` (argmin of D, the paper's); `--contact-window PX` is the older
//! spelling of `centroid:PX` (0 = argmin). `--shear-order N` the largest order of the shear ratio in `g1`
//! (default 2; 0 = the paper's `g1(x2d)`). `y2d` stays out of the force maps
//! unless `--force-y2d` is given (the rods span the width: it only carries noise).
//! `--force-order N` is the force maps' largest displacement order (default 4
//! on the strip, 5 on a flat sensor), `--dpf-order N` their largest `d_pf`
//! order (default 2, 0 leaves it out) and `--shear-order-force N` caps the
//! shear displacements `dx, dy` at order N inside that (default 2 on the
//! strip, no cap on a flat sensor; 0: no cap; see
//! `FitOptions::shear_max_order`). `--force-frame local|sensor` is the frame
//! the force maps work in (default `local` on the strip: the local surface
//! frame, rotated to the sensor frame after; `sensor` is the paper's).
//! `--guard-shear-order N` is the shear order of the fallback force maps that
//! take over where the full maps are not trusted (default 2; 0 fits no guard;
//! see `calibration::ForceGuard`).
//!
//! A strip's dataset may hold sweeps (`sweeps.csv`: one rod pressed every
//! 0.5-2 mm along the skin), from which the location and the force learn
//! what the marker pattern does between the protocol's points
//! (docs/calibration.md, "Sweeps"); without them `calibrate` prints a note
//! on what that costs, and `--no-sweeps` ignores them. Without sweeps a
//! contact's match column is moved to where the profile model fits its
//! motion best, to a fraction of a pixel (`--relocation best`); with them
//! only a clearly misplaced one is (`--relocation clear`, see
//! `contact::profile::Relocation`). `--shear-free-columns` measures each
//! contact's column again without its matched tangential motion
//! (`contact::profile::ProfileModel::shear_free_columns`).
//! `--spread-channel off` fits the profile model without its spread
//! channel (`contact::profile::ProfileModel::spread`).
//!
//! When the first reference shows a regular grid of markers (a dot grid on
//! a plain gel), the dots are followed one by one and their motion written
//! over the flow (`markers::DotTracker`); the calibration records it, so
//! that a sensor does the same. `--dot-tracking off` leaves the flow alone,
//! `on` asks for it whatever the reference shows.
//!
//! The calibration also gets a per-contact force uncertainty, fitted on the
//! validation split (`calibration::uncertainty`): one line prints its
//! coefficients and the fraction of the test split's errors within one
//! sigma (the aim is 68%). A dataset with spot checks (split `spot`:
//! presses at places of their own, between the protocol's points) gets
//! their errors printed beside the test split's, and the uncertainty is
//! fitted on them once at least 20 are detected.
//!
//! `--out -` writes the calibration to stdout and the tables to stderr (not
//! with `--thresholds all`, which writes one file per preset);
//! `--predictions -` writes the test set's predictions (JSON Lines) to
//! stdout. The extraction shows a progress bar with an ETA on a terminal
//! (`--quiet` hides it).

#[path = "cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, ValueEnum};
use cli_support::{Failure, Sink, TextOut};
use optical_tactile::calibration::correction::ColumnCorrection;
use optical_tactile::calibration::fit::{
    AutoThresholds, DatasetFit, Extraction, MAX_REST_PAIRS, RestCheck, extract_dataset,
    extract_sweeps, fit_dataset_with_sweeps, load_cell_spread, read_dataset, read_dataset_geometry,
    read_dataset_sweeps, rest_contacts, rest_pairs,
};
use optical_tactile::calibration::fit::{FitOptions, GuardOptions, ProfileChoices};
use optical_tactile::calibration::report::{self, ThresholdRow};
use optical_tactile::calibration::uncertainty::ForceUncertainty;
use optical_tactile::calibration::{ForceFrame, Sample};
use optical_tactile::contact::ContactPointMethod;
use optical_tactile::contact::profile::Relocation;
use optical_tactile::flow::dis::DisPreset;
use optical_tactile::frame::Roi;
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::io::{self, FrameRecord, Split};
use optical_tactile::segment::Thresholds;
use optical_tactile::sensor::{
    ExtractorConfig, FittingChoices, MAX_LIGHT_BOX_PX, fitting_extractor, fitting_flow_preset,
};

/// Calibrates a sensor from a characterization dataset: runs the pipeline on
/// every test, fits the polynomial maps and prints the paper's Tables I and
/// II and the errors per indenter and force (test set) in markdown.
#[derive(Parser, Debug)]
#[command(name = "calibrate")]
struct Cli {
    /// Characterization dataset folder (tests.csv and its frames, docs/formats.md).
    #[arg(value_name = "DATASET_DIR")]
    dir: PathBuf,
    /// Write the calibration (JSON) to FILE, or to stdout with `-` (the
    /// tables then go to stderr).
    #[arg(long, value_name = "FILE|-")]
    out: TextOut,
    /// Threshold preset to fit; `auto` tries `high`, `mid`, `low` in turn and
    /// keeps the first that sees all but 5% of the tests, else the most
    /// sensitive one that finds no contact between the dataset's reference
    /// images; `all` fits the three, --out gets `high` and the others go
    /// beside it as NAME.low.json and NAME.mid.json.
    #[arg(long, value_enum, default_value_t = PresetArg::Auto)]
    thresholds: PresetArg,
    /// Fit with flow magnitude MAGNITUDE px and patch sum SUM (full
    /// resolution) and the `low` kernels, labelled `custom` (instead of
    /// --thresholds).
    #[arg(long, value_name = "MAGNITUDE,SUM", value_parser = parse_custom)]
    thresholds_custom: Option<(f32, f32)>,
    /// How a contact's point is measured: the steepest rise of the profile
    /// smoothed by a Gaussian of SIGMA px (along x, or along both axes with
    /// slope2d), where the lines along the followed dots' motion meet about
    /// the slope2d point (lines), the energy centroid in a window of
    /// half-width HALF px (default 400), or argmin of D (the paper's)
    /// [default: slope:8 on the strip, lines:16 on a flat sensor].
    #[arg(long, value_name = "slope[:SIGMA]|slope2d[:SIGMA]|lines[:SIGMA]|centroid[:HALF]|argmin",
          value_parser = parse_contact_point, overrides_with = "contact_window")]
    contact_point: Option<ContactPointMethod>,
    /// The sensor's surface: the paper's curved strip, or a flat gel
    /// LENGTH mm along x by WIDTH mm along y [default: the dataset's
    /// geometry.json, else strip].
    #[arg(long, value_name = "strip|flat:LENGTHxWIDTH", value_parser = parse_geometry)]
    geometry: Option<SensorGeometry>,
    /// The older spelling of --contact-point centroid:PX (0: argmin).
    #[arg(long, value_name = "PX", overrides_with = "contact_point")]
    contact_window: Option<u32>,
    /// Largest order of the shear ratio in g1 (0: the paper's g1(x2d)).
    #[arg(long, value_name = "N", default_value_t = FitOptions::default().location_shear_order,
          value_parser = clap::value_parser!(u32).range(0..=5))]
    shear_order: u32,
    /// The force maps' largest displacement order [default: 4 on the strip,
    /// 5 on a flat sensor].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=6))]
    force_order: Option<u32>,
    /// The force maps' largest d_pf order (0 leaves it out).
    #[arg(long, value_name = "N", default_value_t = FitOptions::default().d_pf_max_order,
          value_parser = clap::value_parser!(u32).range(0..=4))]
    dpf_order: u32,
    /// Caps the shear displacements dx, dy at order N inside the force maps
    /// (0: no cap, one displacement group) [default: 2 on the strip, 0 on a
    /// flat sensor].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(0..=6))]
    shear_order_force: Option<u32>,
    /// The frame the force maps work in: `local` (the surface's tangent,
    /// across and normal; rotated to the sensor frame after) or `sensor`
    /// (the paper's) [default: local on the strip, sensor on a flat sensor,
    /// where the two are the same].
    #[arg(long, value_name = "FRAME", value_parser = parse_force_frame)]
    force_frame: Option<ForceFrame>,
    /// Shear order of the fallback force maps that take over where the full
    /// maps are not trusted (0: no guard).
    #[arg(long, value_name = "N",
          default_value_t = FitOptions::default().guard.map_or(0, |g| g.shear_order),
          value_parser = clap::value_parser!(u32).range(0..=6))]
    guard_shear_order: u32,
    /// Let y2d into the force maps (the rods span the width: it only
    /// carries noise).
    #[arg(long)]
    force_y2d: bool,
    /// Ignore the dataset's sweeps.csv (fit without the per-column
    /// corrections it gives).
    #[arg(long)]
    no_sweeps: bool,
    /// Fit the profile model without its indenter-size kernels (one normal
    /// kernel for every indenter; docs/calibration.md).
    #[arg(long)]
    no_size_term: bool,
    /// Fit the profile model without its kernels' far tails (then a
    /// contact's far motion is not modelled where another contact's force
    /// is matched; docs/pipeline.md).
    #[arg(long)]
    no_profile_tail: bool,
    /// Match every contact at its measured column, never at the anchor
    /// map of its location. For markers on one layer (printed dots, one
    /// sprayed layer), where the measured columns may read between the
    /// protocol's points closer than the validation points can tell
    /// (docs/calibration.md, "Which columns"): fit with and without it and
    /// compare.
    #[arg(long)]
    measured_columns: bool,
    /// When a contact's match column moves to where its motion fits the
    /// profile model best: `clear` only for a clearly misplaced point,
    /// `best` always, to a fraction of a pixel [default: clear with sweeps,
    /// best without].
    #[arg(long, value_enum, value_name = "WHEN")]
    relocation: Option<RelocationArg>,
    /// Measure each contact's column again without its matched tangential
    /// motion, in the fit and at run time (strip, slope-peak columns):
    /// puts the column of a wide rod pressed at a tilt back on its load
    /// line (docs/calibration.md, "Shear-free columns").
    #[arg(long)]
    shear_free_columns: bool,
    /// Follow the dots of a regular marker grid one by one and let their
    /// motion replace the flow around them: `auto` when the first
    /// reference shows a regular grid (docs/pipeline.md, step 4).
    #[arg(long, value_enum, value_name = "WHEN", default_value = "auto")]
    dot_tracking: DotTrackingArg,
    /// With the dots followed, read each contact's shear and normal
    /// displacements from a round load's field fitted to its dots rather
    /// than from the patch's sums (docs/pipeline.md, step 7).
    #[arg(long, value_name = "on|off", default_value = "on", action = clap::ArgAction::Set, value_parser = cli_support::on_off)]
    dot_fit: bool,
    /// DIS flow preset [default: dense for random markers on a flat sensor
    /// (no regular grid in the first reference), otherwise fine, the
    /// sensor's].
    #[arg(long, value_name = "PRESET", ignore_case = true, value_parser = cli_support::dis_preset())]
    preset: Option<DisPreset>,
    /// Divide the frames by their own local light, a box of this half-side
    /// (px), before the flow; 0: not [default: two flow patches (16 px)
    /// for random markers on a flat sensor, otherwise 0].
    #[arg(long, value_name = "PX", value_parser = clap::value_parser!(u32).range(0..=MAX_LIGHT_BOX_PX as i64))]
    light_box: Option<u32>,
    /// Weigh each flow cell by how well the frame warped back by the flow
    /// matches the reference there when the motion profiles along the arc
    /// are summed (docs/pipeline.md, step 8; the curved strip). On the
    /// simulator it reads one sensor closer and another's presses worse:
    /// fit with and without it and compare.
    #[arg(long, value_name = "on|off", default_value = "off", action = clap::ArgAction::Set, value_parser = cli_support::on_off)]
    weighted_profiles: bool,
    /// Match the forces on the across motion's first moment about the
    /// strip's centre line too, the gel squeezed out sideways by a press
    /// (docs/pipeline.md, step 9; the curved strip).
    #[arg(long, value_name = "on|off", default_value = "on", action = clap::ArgAction::Set, value_parser = cli_support::on_off)]
    spread_channel: bool,
    /// Crop of the frames [default: the whole image].
    #[arg(long, value_name = "x,y,w,h", value_parser = cli_support::roi)]
    crop: Option<Roi>,
    /// Write the test set's predictions (JSON Lines) to FILE, or to stdout
    /// with `-`.
    #[arg(long, value_name = "FILE|-")]
    predictions: Option<TextOut>,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
}

/// `--thresholds`.
#[derive(ValueEnum, Debug, Clone, Copy, PartialEq)]
enum PresetArg {
    Auto,
    Low,
    Mid,
    High,
    All,
}

/// `--dot-tracking`.
#[derive(ValueEnum, Debug, Clone, Copy, PartialEq)]
enum DotTrackingArg {
    Auto,
    On,
    Off,
}

/// `--relocation`.
#[derive(ValueEnum, Debug, Clone, Copy, PartialEq)]
enum RelocationArg {
    Clear,
    Best,
}

impl From<RelocationArg> for Relocation {
    fn from(r: RelocationArg) -> Self {
        match r {
            RelocationArg::Clear => Relocation::Clear,
            RelocationArg::Best => Relocation::Best,
        }
    }
}

/// What the command line resolves to.
struct Args {
    dir: PathBuf,
    out: TextOut,
    presets: Vec<&'static str>,
    custom: Option<(f32, f32)>,
    contact_point: Option<ContactPointMethod>,
    geometry: Option<SensorGeometry>,
    shear_order: u32,
    /// `--force-order`; `None`: the geometry's default.
    force_order: Option<u32>,
    dpf_order: u32,
    /// `--shear-order-force`; `None`: the geometry's default, `Some(0)`: no cap.
    shear_force_order: Option<u32>,
    /// `--force-frame`; `None`: the geometry's default.
    force_frame: Option<ForceFrame>,
    guard: Option<GuardOptions>,
    force_y2d: bool,
    no_sweeps: bool,
    no_size_term: bool,
    no_profile_tail: bool,
    measured_columns: bool,
    relocation: Option<Relocation>,
    shear_free_columns: bool,
    dot_tracking: DotTrackingArg,
    /// `--dot-fit`.
    dot_fit: bool,
    /// `--preset`; `None`: the sensor's default (`ExtractorConfig::default`).
    flow: Option<DisPreset>,
    /// `--light-box`; `None`: as [`fitting_light_box`] says.
    light_box: Option<usize>,
    /// `--weighted-profiles`.
    weighted_profiles: bool,
    /// `--spread-channel`.
    spread_channel: bool,
    crop: Option<Roi>,
    predictions: Option<TextOut>,
    quiet: bool,
}

/// Runs one extraction pass over `n` images (`run` with its progress
/// callback) behind a progress bar labelled `label`.
fn extract_with_bar(
    label: &str,
    n: usize,
    quiet: bool,
    run: impl FnOnce(&(dyn Fn(usize, usize) + Sync)) -> optical_tactile::Result<Vec<Extraction>>,
) -> Result<Vec<Extraction>, String> {
    let bar = cli_support::progress_bar(label, n as u64, quiet);
    let progress = |done: usize, _total: usize| {
        bar.set_position((done as u64).max(bar.position()));
    };
    let out = run(&progress);
    bar.finish();
    out.map_err(|e| e.to_string())
}

/// Printed when a strip's dataset has no `sweeps.csv` (and `--no-sweeps`
/// was not given): without sweeps the maps know the skin only at the
/// protocol's points (docs/calibration.md, "Sweeps").
const NO_SWEEPS_NOTE: &str = "note: no sweeps.csv beside tests.csv. Between the protocol's points, \
where most contacts land, forces will read further off than with sweeps (simulated strip: \
presses anywhere Fz 0.088 N against 0.065 N, two perches 0.051 N against 0.017 N per contact); \
one rod swept every 1-2 mm (120-240 images) brings nearly all of it back (docs/calibration.md, \
\"Sweeps\"). --no-sweeps fits without them and says nothing.";

/// One line on a fitted column correction: how many sweep images, how large
/// its location offsets and how far its force gains stray from 1, over the
/// columns the sweeps reached.
fn correction_summary(c: &ColumnCorrection, images: usize, misses: usize) -> String {
    let rms = |values: &[f64], gains: &[f64]| {
        let reached: Vec<usize> = (0..values.len())
            .filter(|&i| values[i] != 0.0 || gains[i] != 1.0)
            .collect();
        let rms = |v: &mut dyn Iterator<Item = f64>| {
            let (n, s) = v.fold((0usize, 0.0), |(n, s), x| (n + 1, s + x * x));
            (s / n.max(1) as f64).sqrt()
        };
        let loc = rms(&mut reached.iter().map(|&i| values[i]));
        let gain = rms(&mut reached.iter().map(|&i| gains[i] - 1.0));
        (reached.len(), loc, gain)
    };
    let (reached, loc, gain) = rms(&c.location_mm, &c.force_gain);
    let mut line = format!(
        "sweeps: {images} images ({misses} not read as a press); corrections over {reached} columns: \
         location offset {loc:.3} mm rms, force gain {:.1}% rms",
        100.0 * gain
    );
    for l in &c.layers {
        let (_, loc, gain) = rms(&l.location_mm, &l.force_gain);
        let mut ratios = l.shear_ratio.clone();
        ratios.sort_by(f64::total_cmp);
        let median = ratios.get(ratios.len() / 2).copied().unwrap_or(0.0);
        line.push_str(&format!(
            "; tilted layer at shear ratio {median:+.2} ({} images): {loc:.3} mm, {:.1}% rms",
            l.images,
            100.0 * gain
        ));
    }
    line
}

/// The spot checks' errors beside the test split's: how much of the
/// protocol's accuracy holds between its points.
fn spot_markdown(test: &report::QuantityMae, spot: &report::QuantityMae) -> String {
    let mut s = String::from(
        "| rows | samples | MAE x3D [mm] | MAE y3D [mm] | MAE Fx [N] | MAE Fy [N] | MAE Fz [N] |\n\
         |---|---|---|---|---|---|---|\n",
    );
    for (name, m) in [
        ("test split (the protocol's points)", test),
        ("spot checks", spot),
    ] {
        s.push_str(&format!(
            "| {name} | {} | {:.2} | {:.2} | {:.4} | {:.4} | {:.4} |\n",
            m.n, m.x_mm, m.y_mm, m.fx, m.fy, m.fz
        ));
    }
    s
}

/// One line on the fitted force uncertainty: sigma per axis as
/// `base + per d_pf + per newton`, what it was fitted on (the spot checks
/// `spot` if it was, else the validation split), and the test split's
/// coverage.
fn uncertainty_summary(u: &ForceUncertainty, spot: Option<&report::PointTable>) -> String {
    let axes: Vec<String> = ["Fx", "Fy", "Fz"]
        .iter()
        .zip(&u.axes)
        .map(|(name, a)| {
            format!(
                "{name} {:.4} + {:.5} d_pf + {:.4} |F|",
                a.base_n, a.per_d_pf, a.per_newton
            )
        })
        .collect();
    let coverage = u.test_coverage.map_or_else(
        || "no test split".to_string(),
        |c| {
            format!(
                "test errors within one sigma: {:.0}% / {:.0}% / {:.0}% (aim 68%)",
                100.0 * c[0],
                100.0 * c[1],
                100.0 * c[2]
            )
        },
    );
    let on_spots = spot.is_some_and(|t| {
        optical_tactile::calibration::uncertainty::fitted_on_spot_checks(t.total.n)
    });
    let (what, note) = if on_spots {
        (
            "spot checks",
            " (its level is set to 68% on the spot checks, presses between the protocol's \
             points: the points' own errors may lie within it more or less often)",
        )
    } else {
        ("validation tests", "")
    };
    format!(
        "force uncertainty (sigma, N; fitted on {} {what}): {}; {coverage}{note}",
        u.samples,
        axes.join(", ")
    )
}

/// `local` or `sensor`.
fn parse_force_frame(v: &str) -> Result<ForceFrame, String> {
    match v {
        "local" => Ok(ForceFrame::Local),
        "sensor" => Ok(ForceFrame::Sensor),
        _ => Err(format!("expected `local` or `sensor`, got `{v}`")),
    }
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
                .ok_or(format!("expected a positive number after `:`, got `{x}`")),
        }
    };
    let method = match name {
        "slope" => ContactPointMethod::SlopePeak {
            sigma_px: num(8.0)?,
        },
        "slope2d" => ContactPointMethod::SlopePeak2d {
            sigma_px: num(8.0)?,
        },
        "lines" => ContactPointMethod::MotionLines {
            sigma_px: num(16.0)?,
        },
        "centroid" => ContactPointMethod::EnergyCentroid {
            half_window_px: num(400.0)?,
        },
        "argmin" if !given => ContactPointMethod::PotentialMinimum,
        _ => {
            return Err(format!(
                "expected slope[:SIGMA], slope2d[:SIGMA], lines[:SIGMA], centroid[:HALF] or argmin, got `{v}`"
            ));
        }
    };
    method.validate().map_err(|e| e.to_string())?;
    Ok(method)
}

/// `strip` or `flat:LENGTHxWIDTH` (mm).
fn parse_geometry(v: &str) -> Result<SensorGeometry, String> {
    SensorGeometry::parse(v).map_err(|e| e.to_string())
}

/// `MAGNITUDE,SUM`: a positive flow magnitude and a patch sum >= 0.
fn parse_custom(v: &str) -> Result<(f32, f32), String> {
    let parts: Vec<Result<f32, _>> = v.split(',').map(|p| p.trim().parse()).collect();
    match parts.as_slice() {
        [Ok(m), Ok(s)] if *m > 0.0 && *s >= 0.0 && m.is_finite() && s.is_finite() => Ok((*m, *s)),
        _ => Err(format!(
            "expected MAGNITUDE,SUM (positive numbers), got `{v}`"
        )),
    }
}

impl Cli {
    fn resolve(self) -> Result<Args, String> {
        let presets = match (self.thresholds_custom, self.thresholds) {
            (Some(_), _) => vec!["custom"],
            (None, PresetArg::Auto) => vec!["auto"],
            (None, PresetArg::Low) => vec!["low"],
            (None, PresetArg::Mid) => vec!["mid"],
            (None, PresetArg::High) => vec!["high"],
            (None, PresetArg::All) => vec!["high", "mid", "low"],
        };
        if self.out.is_stdout() && presets.len() > 1 {
            return Err(
                "--thresholds all writes one calibration file per preset: give --out a file name"
                    .into(),
            );
        }
        if self.out.is_stdout() && self.predictions.as_ref().is_some_and(TextOut::is_stdout) {
            return Err("--out and --predictions cannot both go to stdout (-)".into());
        }
        let contact_point = match self.contact_window {
            Some(0) => Some(ContactPointMethod::PotentialMinimum),
            Some(w) => Some(ContactPointMethod::EnergyCentroid {
                half_window_px: f64::from(w),
            }),
            None => self.contact_point,
        };
        Ok(Args {
            dir: self.dir,
            out: self.out,
            presets,
            custom: self.thresholds_custom,
            contact_point,
            geometry: self.geometry,
            shear_order: self.shear_order,
            force_order: self.force_order,
            dpf_order: self.dpf_order,
            shear_force_order: self.shear_order_force,
            force_frame: self.force_frame,
            guard: (self.guard_shear_order > 0).then(|| GuardOptions {
                shear_order: self.guard_shear_order,
                ..GuardOptions::default()
            }),
            force_y2d: self.force_y2d,
            no_sweeps: self.no_sweeps,
            no_size_term: self.no_size_term,
            no_profile_tail: self.no_profile_tail,
            measured_columns: self.measured_columns,
            relocation: self.relocation.map(Relocation::from),
            shear_free_columns: self.shear_free_columns,
            dot_tracking: self.dot_tracking,
            dot_fit: self.dot_fit,
            flow: self.preset,
            light_box: self.light_box.map(|r| r as usize),
            weighted_profiles: self.weighted_profiles,
            spread_channel: self.spread_channel,
            crop: self.crop,
            predictions: self.predictions,
            quiet: self.quiet,
        })
    }
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

fn run(args: Args) -> Result<(), Failure> {
    let err = |e: optical_tactile::Error| e.to_string();
    let data_on_stdout =
        args.out.is_stdout() || args.predictions.as_ref().is_some_and(TextOut::is_stdout);
    let mut out = Sink::report(data_on_stdout);
    let rows = read_dataset(&args.dir).map_err(err)?;
    let geometry = match args.geometry {
        Some(g) => g,
        None => read_dataset_geometry(&args.dir)
            .map_err(err)?
            .unwrap_or_default(),
    };
    let two_d = geometry.locates_in_2d();
    let contact_point = args
        .contact_point
        .unwrap_or(ContactPointMethod::for_geometry(&geometry));
    // The crop the pixel coordinates refer to: given, or the whole image.
    let first = io::read_gray(args.dir.join(&rows[0].reference)).map_err(err)?;
    let crop = args
        .crop
        .unwrap_or_else(|| Roi::full(first.ncols(), first.nrows()));
    // A regular grid's pitch: what tells a motion beyond the markers (half
    // of it, against a torn flow on random markers) and whether the dots
    // can be followed; with it the flow and the light box not asked for.
    let reference = crop.crop(&first).map_err(err)?.to_owned();
    let choices = FittingChoices {
        dot_tracking: match args.dot_tracking {
            DotTrackingArg::On => Some(true),
            DotTrackingArg::Off => Some(false),
            DotTrackingArg::Auto => None,
        },
        dot_fit: args.dot_fit,
        flow: args.flow,
        light_box_px: args.light_box,
        weighted_profiles: args.weighted_profiles,
    };
    let (fitting, pitch) = fitting_extractor(&geometry, &reference, &choices);
    if let (Some(p), DotTrackingArg::Auto) = (pitch, args.dot_tracking) {
        eprintln!(
            "the references show a regular grid of markers ({p:.0} px apart): \
             its dots are followed one by one (--dot-tracking off: the flow alone)"
        );
    }
    let preset = fitting_flow_preset(&geometry, pitch);
    if args.flow.is_none() && preset != DisPreset::Fine {
        eprintln!(
            "the references show random markers on a flat sensor: fitted with the `{}` flow \
             (--preset fine: the sensor's default, half the time per frame), the frames \
             divided by their own light (--light-box 0: as they are)",
            preset.name()
        );
    }
    let sweeps = if args.no_sweeps {
        Vec::new()
    } else {
        read_dataset_sweeps(&args.dir).map_err(err)?
    };
    let threads = rayon::current_num_threads();
    eprintln!(
        "{} tests and {} sweep images in {}, {} threads, {} geometry",
        rows.len(),
        sweeps.len(),
        args.dir.display(),
        threads,
        geometry.kind()
    );
    if sweeps.is_empty() && !args.no_sweeps && !geometry.locates_in_2d() {
        eprintln!("{}", NO_SWEEPS_NOTE);
    }
    let mut table_i = Vec::new();
    let mut table_ii = Vec::new();
    let mut spot_tables = Vec::new();
    let spots = rows.iter().filter(|r| r.split == Split::Spot).count();
    let config_for = |preset: &str| {
        fitting
            .clone()
            .with_thresholds(thresholds(preset, args.custom))
    };
    let extract_tests = |preset: &str, config: &ExtractorConfig| {
        extract_with_bar(&format!("[{preset}] tests"), rows.len(), args.quiet, |p| {
            extract_dataset(&args.dir, &rows, config, contact_point, args.crop, p)
        })
    };
    // Pairs of reference images: frames with nothing touching, on which
    // every preset is checked for contacts at rest.
    let pairs = rest_pairs(&rows, MAX_REST_PAIRS);
    let at_rest = |config: &ExtractorConfig| -> Result<(RestCheck, String), Failure> {
        let rest = rest_contacts(&args.dir, &pairs, config, args.crop).map_err(err)?;
        let said = if rest.pairs == 0 {
            "no two reference images to look at rest with".to_string()
        } else {
            format!(
                "{} of {} pairs of reference images a contact",
                rest.with_contact, rest.pairs
            )
        };
        Ok((rest, said))
    };
    for (k, &asked) in args.presets.iter().enumerate() {
        let t0 = Instant::now();
        let (preset, config, ex) = if asked == "auto" {
            let mut auto = AutoThresholds::new();
            while let Some(preset) = auto.next_preset() {
                let config = config_for(preset.name());
                let ex = extract_tests(preset.name(), &config)?;
                let (rest, said) = at_rest(&config)?;
                let t = auto.record(ex, rest).map_err(err)?;
                eprintln!(
                    "[auto] {preset}: {} of {} tests gave no contact, {said}",
                    t.missed, t.tests
                );
            }
            let (preset, ex) = auto.finish().expect("the search tried a preset");
            eprintln!("[auto] fitting with `{preset}` (--thresholds low|mid|high to choose)");
            (preset.name(), config_for(preset.name()), ex)
        } else {
            let config = config_for(asked);
            let ex = extract_tests(asked, &config)?;
            let (rest, said) = at_rest(&config)?;
            eprintln!("[{asked}] at rest: {said}");
            if !rest.quiet() {
                eprintln!(
                    "[{asked}] warning: these thresholds find contacts with nothing touching the \
                     skin; a sensor fitted with them will too (try less sensitive thresholds)"
                );
            }
            (asked, config, ex)
        };
        let swept = if sweeps.is_empty() {
            Vec::new()
        } else {
            extract_with_bar(
                &format!("[{preset}] sweeps"),
                sweeps.len(),
                args.quiet,
                |p| extract_sweeps(&args.dir, &sweeps, &config, contact_point, args.crop, p),
            )?
        };
        let base = FitOptions::for_geometry(&geometry);
        let options = FitOptions {
            location_shear_order: args.shear_order,
            displacement_max_order: args.force_order.unwrap_or(base.displacement_max_order),
            d_pf_max_order: args.dpf_order,
            shear_max_order: match args.shear_force_order {
                None => base.shear_max_order,
                Some(0) => None,
                Some(n) => Some(n),
            },
            guard: args.guard,
            force_frame: args.force_frame.unwrap_or(base.force_frame),
            force_use_y2d: args.force_y2d || two_d,
            profile: base.profile.map(|p| {
                p.with_choices(&ProfileChoices {
                    measured_columns: args.measured_columns,
                    relocation: args.relocation,
                    shear_free_columns: args.shear_free_columns,
                    spread_channel: args.spread_channel,
                    size_term: !args.no_size_term,
                    profile_tail: !args.no_profile_tail,
                })
            }),
            ..base
        };
        let fit = fit_dataset_with_sweeps(
            &ex,
            &swept,
            &config,
            contact_point,
            crop,
            geometry,
            &options,
        )
        .map_err(err)?;
        eprintln!(
            "[{preset}] fitted in {:.1} s; misses train/val/test{}: {}/{}/{}{}",
            t0.elapsed().as_secs_f64(),
            if spots > 0 { "/spot" } else { "" },
            fit.misses[0],
            fit.misses[1],
            fit.misses[2],
            if spots > 0 {
                format!("/{}", fit.misses[3])
            } else {
                String::new()
            }
        );
        if let Some(w) = report::missed_tests_warning(fit.misses.iter().sum(), ex.len()) {
            eprintln!("[{preset}] warning: {w}");
        }
        if let Some(c) = &fit.calibration.column_correction {
            eprintln!(
                "[{preset}] {}",
                correction_summary(c, swept.len(), fit.sweep_misses)
            );
        }
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
        match &fit.calibration.uncertainty {
            Some(u) => eprintln!(
                "[{preset}] {}",
                uncertainty_summary(u, fit.spot_table.as_ref())
            ),
            None => eprintln!(
                "[{preset}] force uncertainty: not fitted (fewer than {} validation tests or spot checks detected)",
                optical_tactile::calibration::uncertainty::MIN_SAMPLES
            ),
        }
        match &args.out {
            TextOut::Stdout => {
                let mut stdout = Sink::stdout();
                stdout.write_all(fit.calibration.to_json_string().as_bytes())?;
                stdout.flush()?;
            }
            TextOut::File(p) => {
                let path = if k == 0 {
                    p.clone()
                } else {
                    sibling(p, preset)
                };
                fit.calibration.save(&path).map_err(err)?;
                eprintln!("[{preset}] wrote {}", path.display());
            }
        }
        if k == 0 {
            if let Some(pred) = &args.predictions {
                let mut w = pred.create()?;
                for (e, s) in ex
                    .iter()
                    .zip(&fit.samples)
                    .filter(|(e, _)| e.row.split == Split::Test)
                {
                    let mut contacts = Vec::new();
                    if let Some(s) = s {
                        let p = fit.calibration.predict(s).map_err(err)?;
                        // The record's displacements are in the sensor frame.
                        let d = fit.calibration.force_frame().to_sensor(
                            &fit.calibration.setup.geometry,
                            p.x_mm,
                            [s.dx, s.dy, s.dz],
                        );
                        let sigma = fit
                            .calibration
                            .uncertainty
                            .as_ref()
                            .map(|u| u.sigma_n(s.d_pf, [p.fx, p.fy, p.fz]));
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
                            dx: Some(d[0]),
                            dy: Some(d[1]),
                            dz: Some(d[2]),
                            fx_sigma_n: sigma.map(|s| s[0]),
                            fy_sigma_n: sigma.map(|s| s[1]),
                            fz_sigma_n: sigma.map(|s| s[2]),
                            ..Default::default()
                        });
                    }
                    w.json_line(&FrameRecord {
                        frame: e.row.frame.clone(),
                        t_s: 0.0,
                        contacts,
                        latency_ms: None,
                    })?;
                }
            }
        }
        table_i.push(ThresholdRow {
            preset: preset.to_string(),
            min_force_n: fit.min_force.to_string(),
            mae: fit.test_table.total,
        });
        let by_load = report::evaluate_by_load(
            &fit.calibration,
            ex.iter()
                .zip(&fit.samples)
                .filter_map(|(e, s)| s.as_ref().map(|s| (&e.row, s))),
            Split::Test,
        )
        .map_err(err)?;
        let beyond = beyond_markers_note(&ex, &fit, pitch.is_some()).map_err(err)?;
        if let Some(spot) = &fit.spot_table {
            spot_tables.push((preset.to_string(), fit.test_table.total, spot.total));
        }
        table_ii.push((preset.to_string(), fit.test_table, (by_load, beyond)));
    }
    writeln!(out, "## Table I: test-set errors per threshold preset\n")?;
    writeln!(out, "{}", report::table_i_markdown(&table_i))?;
    if let Some(s) = load_cell_spread(&rows) {
        let [sx, sy, sz] = s.sigma_n;
        let [mx, my, mz] = s.mae_floor_n();
        writeln!(
            out,
            "Load cell: its readings scatter by Fx {sx:.4}, Fy {sy:.4}, Fz {sz:.4} N (standard \
             deviation) between repetitions of the same test ({} groups). A sensor that read the \
             applied force exactly would score about Fx {mx:.4}, Fy {my:.4}, Fz {mz:.4} N MAE \
             against these recordings: the floor under the force columns above.\n",
            s.groups
        )?;
    }
    for (preset, t, _) in &table_ii {
        writeln!(
            out,
            "## Table II: test-set errors per point ({preset} thresholds)\n"
        )?;
        writeln!(out, "{}", report::table_ii_markdown(t))?;
    }
    for (preset, test, spot) in &spot_tables {
        writeln!(
            out,
            "## Spot checks: presses between the points ({preset} thresholds)\n"
        )?;
        writeln!(out, "{}", spot_markdown(test, spot))?;
    }
    for (preset, _, (by_load, beyond)) in &table_ii {
        writeln!(
            out,
            "## Test-set errors per indenter and force ({preset} thresholds)\n"
        )?;
        writeln!(out, "{}", report::table_loads_markdown(by_load))?;
        if let Some(note) = beyond {
            writeln!(out, "{note}\n")?;
        }
    }
    Ok(())
}

/// How many detected test rows moved beyond what the markers can tell
/// (marked out of domain at run time): on a regular grid (`grid`), by half
/// its pitch or more; on random markers, with a torn flow
/// ([`optical_tactile::sensor::TORN_STRAIN`]). Then the test errors of the
/// others, and how many training and validation rows that far the maps were
/// fitted on (on a grid, those whose dots were all followed; on random
/// markers none). `None` when no test row moved that far.
fn beyond_markers_note(
    ex: &[Extraction],
    fit: &DatasetFit,
    grid: bool,
) -> optical_tactile::Result<Option<String>> {
    let test = |e: &&Extraction| e.row.split == Split::Test && e.raw.is_some();
    let detected = ex.iter().filter(test).count();
    let beyond = ex.iter().filter(test).filter(|e| e.beyond_markers).count();
    if beyond == 0 {
        return Ok(None);
    }
    let fitting = |e: &&Extraction| e.row.split != Split::Test && e.raw.is_some();
    let far = ex.iter().filter(fitting).filter(|e| e.beyond_markers);
    let (far_n, far_fitted) = far.fold((0, 0), |(n, k), e| (n + 1, k + usize::from(e.fits())));
    let inside: Vec<Sample> = ex
        .iter()
        .zip(&fit.samples)
        .filter(|(e, _)| !e.beyond_markers)
        .filter_map(|(_, s)| *s)
        .collect();
    let m = report::evaluate(&fit.calibration, &inside, Split::Test)?.total;
    let others = format!(
        "The other {}: MAE x {:.2} mm, y {:.2} mm, Fx {:.4}, Fy {:.4}, Fz {:.4} N.",
        m.n, m.x_mm, m.y_mm, m.fx, m.fy, m.fz
    );
    Ok(Some(if grid {
        format!(
            "Motion beyond the markers: {beyond} of {detected} detected test rows moved by half \
             the dot grid's pitch or more, where a dot cannot be told from its neighbour; the \
             sensor marks such contacts out of domain. {others} Of the {far_n} training and \
             validation rows that moved that far, the maps were fitted on the {far_fitted} whose \
             dots were all followed (none lost in the contact's box, motion under two thirds of \
             the pitch)."
        )
    } else {
        format!(
            "Motion beyond the markers: {beyond} of {detected} detected test rows tore the flow \
             ({:.0}% of the contact's moving flow or more stretched by {:.0}% or more across \
             one flow patch, where the random markers no longer match the reference); the \
             sensor marks such contacts out of domain. {others} The maps were fitted without \
             the {far_n} training and validation rows that tore it.",
            100.0 * optical_tactile::sensor::TORN_FRACTION,
            100.0 * optical_tactile::sensor::TORN_STRAIN
        )
    }))
}

fn main() -> ExitCode {
    let args = Cli::parse().resolve();
    cli_support::finish(
        args.map_err(Failure::from)
            .and_then(run)
            .map(|()| ExitCode::SUCCESS),
    )
}
