//! Synthetic sensor frames with ground truth, written in the formats of docs/formats.md.
//!
//! ```text
//! cargo run --release --example simulate -- <SCENARIO> --out DIR [OPTIONS]
//! cargo run --release --example simulate -- fixtures [--out DIR] [--docs DIR]
//! cargo run --release --example simulate -- --help
//! cargo run --release --example simulate -- <SCENARIO> --help
//! ```
//!
//! Scenarios: `single`, `pair`, `presses`, `shear`, `characterization`, `perches`,
//! `mapping`, `rest` (see `optical_tactile_sim::scenario`), and `fixtures`, which
//! regenerates the repository's fixtures (by default in this crate's
//! `fixtures/`, whatever the working directory) and, with `--docs`, the
//! README pictures. A progress bar with an ETA shows on a terminal (not with
//! `--quiet`).

#[path = "cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand, ValueEnum};
use cli_support::{Failure, Numbers, Sink, Stages};
use ndarray::{Array2, s};
use optical_tactile::Result;
use optical_tactile::viz::{Canvas, Rgb, colormap};
use optical_tactile_sim::scenario::{
    self, Characterization, Common, Mapping, Pair, Perches, Presses, Rest, Scenario, Shear, Single,
    TipPresses,
};
use optical_tactile_sim::{ContactLight, Press, SensorOptions, SimConfig, SyntheticSensor};

/// Where `fixtures` writes by default: this crate's fixtures folder.
const FIXTURES_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures");

/// Synthetic optical tactile sensor frames with ground truth.
#[derive(Parser, Debug)]
#[command(
    name = "simulate",
    after_help = "Each scenario's options and their defaults: simulate <SCENARIO> --help\n\
                  Example: simulate pair --out /tmp/pair --spacing-mm 30 --force-n 2.5"
)]
pub struct Cli {
    /// The scenario to write.
    #[command(subcommand)]
    pub command: Command,
}

/// The scenarios, each with the common options and its own.
#[derive(Subcommand, Debug)]
pub enum Command {
    /// One indenter, force ramp (frame 0 unloaded), optional tilt; with
    /// --sweep-to-mm, one force held while the rod moves along the skin.
    Single {
        /// Common options.
        #[command(flatten)]
        common: CommonArgs,
        /// The scenario's options.
        #[command(flatten)]
        options: SingleArgs,
    },
    /// Two indenters at a given spacing, force ramps (rods across the strip;
    /// with --sensor fingertip, two spheres side by side)
    Pair {
        /// Common options.
        #[command(flatten)]
        common: CommonArgs,
        /// The scenario's options.
        #[command(flatten)]
        options: PairArgs,
    },
    /// Independent presses at random places, forces, tilts and rods, each
    /// frame against frame 0 (accuracy between the protocol's points;
    /// presses.json); with --sensor fingertip, spheres, flat punches and
    /// sheared fingertips anywhere in x and y.
    Presses {
        /// Common options.
        #[command(flatten)]
        common: CommonArgs,
        /// The scenario's options.
        #[command(flatten)]
        options: PressesArgs,
    },
    /// A rod pressing, then shearing (markers.csv: the markers' centres);
    /// with --dot-grid, GelSight-like dot-grid frames with their true flow.
    Shear {
        /// Common options.
        #[command(flatten)]
        common: CommonArgs,
        /// The scenario's options.
        #[command(flatten)]
        options: ShearArgs,
    },
    /// The characterization protocol (tests.csv + frames/), docs/calibration.md;
    /// with --sensor fingertip, the flat sensor's protocol on a 5 x 4 grid
    /// (also geometry.json and indenters.json).
    Characterization {
        /// Common options.
        #[command(flatten)]
        common: CommonArgs,
        /// The scenario's options.
        #[command(flatten)]
        options: CharacterizationArgs,
    },
    /// Two rods of different stiffness under a descending body.
    Perches {
        /// Common options.
        #[command(flatten)]
        common: CommonArgs,
        /// The scenario's options.
        #[command(flatten)]
        options: PerchesArgs,
    },
    /// Touch, move, touch over rods at known world positions (poses.csv,
    /// rods.json).
    Mapping {
        /// Common options.
        #[command(flatten)]
        common: CommonArgs,
        /// The scenario's options.
        #[command(flatten)]
        options: MappingArgs,
    },
    /// The skin at rest (no contact), e.g. with --exposure-steps and --drift
    /// to see what the camera alone does (camera.csv: each frame's gain and
    /// offset).
    Rest {
        /// Common options.
        #[command(flatten)]
        common: CommonArgs,
        /// The scenario's options.
        #[command(flatten)]
        options: RestArgs,
    },
    /// The repository's fixtures (a two-contact press, a characterization
    /// subset and presses on the flat fingertip sensor) and, with --docs,
    /// the README pictures.
    Fixtures(FixturesArgs),
}

/// Options of every scenario.
#[derive(Args, Debug)]
#[command(next_help_heading = "Common options")]
pub struct CommonArgs {
    /// Output folder (created).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Seed for markers, noise and random choices.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub seed: u64,
    /// Write the true dense motion as flow/*.flo [default: on, except for
    /// characterization].
    #[arg(long, overrides_with = "no_flow")]
    pub flow: bool,
    /// Do not write the true dense motion.
    #[arg(long, overrides_with = "flow")]
    pub no_flow: bool,
    /// Frame rate for the time stamps.
    #[arg(long, value_name = "F", default_value_t = 50.0)]
    pub fps: f64,
    /// The simulated sensor: `strip`, the paper's curved strip (1600x200
    /// image, rods across it), or `fingertip`, a flat GelSight-Mini-like
    /// sensor (24 x 18 mm gel, 320x240 image with lens distortion, a grid of
    /// dark dots on a thin stiff gel, round tips pressing it).
    #[arg(long, value_enum, value_name = "SENSOR", default_value_t = Sensor::Strip)]
    pub sensor: Sensor,
    /// With --sensor fingertip: random bright markers on a dark gel instead
    /// of the dot grid (--coverage and --markers then apply).
    #[arg(long, conflicts_with = "dot_grid")]
    pub random_markers: bool,
    /// Render the full 1920x1080 camera frame with the strip inside it (crop
    /// printed, and written as crop.json) instead of the 1600x200 strip.
    #[arg(long)]
    pub full_frame: bool,
    /// Gel Young's modulus, kPa [default: the sensor's, 40 for the strip,
    /// 1000 for the fingertip].
    #[arg(long, value_name = "E")]
    pub youngs_kpa: Option<f64>,
    /// Gel Poisson's ratio [default: 0.47].
    #[arg(long, value_name = "NU")]
    pub poisson: Option<f64>,
    /// Gel layer thickness over the rigid plate, mm [default: the sensor's,
    /// 8 for the strip, 2 for the fingertip].
    #[arg(long, value_name = "T")]
    pub layer_mm: Option<f64>,
    /// Fraction of the image covered by markers.
    #[arg(long, value_name = "C", default_value_t = SimConfig::default().markers.coverage)]
    pub coverage: f64,
    /// Exact number of markers (overrides --coverage).
    #[arg(long, value_name = "N")]
    pub markers: Option<usize>,
    /// Depths of the markers below the skin, mm: the random markers lie
    /// anywhere between MIN and MAX (MIN = MAX: all at one depth, as printed
    /// dots), a dot grid at their mean [default: 0.5,4 on the strip].
    #[arg(long, value_name = "MIN,MAX", allow_hyphen_values = true, value_parser = depth_range)]
    pub marker_depth_mm: Option<(f64, f64)>,
    /// A GelSight-like sensor instead of the strip: a 320x240 image of a
    /// regular grid of dark dots on a bright, lit gel, on a short piece of
    /// the curved strip pressed by rods across it (--coverage and --markers
    /// do not apply; not with --sensor).
    #[arg(long, conflicts_with = "sensor")]
    pub dot_grid: bool,
    /// Dot grid: distance between dot centres, px [default: 30 with
    /// --dot-grid, 22 for the fingertip].
    #[arg(long, value_name = "P")]
    pub pitch_px: Option<f64>,
    /// Dot grid: dot diameter, px [default: 8 with --dot-grid, 7 for the
    /// fingertip].
    #[arg(long, value_name = "D")]
    pub dot_px: Option<f64>,
    /// Dot grid: each dot moved off the grid by up to this, px [default: 0].
    #[arg(long, value_name = "J")]
    pub jitter_px: Option<f64>,
    /// Read-noise standard deviation, grey levels.
    #[arg(long, value_name = "S", default_value_t = SimConfig::default().noise.read)]
    pub noise_read: f32,
    /// Relative per-frame brightness flicker.
    #[arg(long, value_name = "S", default_value_t = SimConfig::default().noise.flicker)]
    pub flicker: f32,
    /// Camera exposure steps: every EVERY frames the gain changes by GAIN
    /// (relative, e.g. 0.02) and the black level by OFFSET grey levels, up or
    /// down at random, at most LEVELS steps from the start [default: off;
    /// OFFSET 0, LEVELS 2].
    #[arg(long, value_name = "EVERY,GAIN[,OFFSET[,LEVELS]]", allow_hyphen_values = true,
          value_parser = exposure_steps)]
    pub exposure_steps: Option<Numbers>,
    /// The gel's light under each contact changes by this fraction at its
    /// centre, over a Gaussian of two thirds of its radius (-0.4: 40%
    /// darker, as a dark object seen through a thin gel; at most 0.9 either
    /// way) [default: 0].
    #[arg(long, value_name = "C", allow_hyphen_values = true, value_parser = light_change)]
    pub contact_light: Option<f32>,
    /// The gel's light under each contact changes by this fraction one
    /// spread either side of its centre along x: brighter on the left,
    /// darker on the right for a positive value (the shading of its slopes
    /// under a light from one side; at most 0.9 either way) [default: 0].
    #[arg(long, value_name = "S", allow_hyphen_values = true, value_parser = light_change)]
    pub contact_shading: Option<f32>,
    /// Slow camera drift: the gain moves by up to GAIN (relative) and the
    /// black level by up to OFFSET grey levels, as a sine of PERIOD frames
    /// [default: off].
    #[arg(long, value_name = "GAIN,OFFSET,PERIOD", allow_hyphen_values = true, value_parser = drift)]
    pub drift: Option<Numbers>,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
}

/// The simulated sensor of `--sensor`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Sensor {
    /// The paper's curved strip (`SimConfig::default`).
    Strip,
    /// A flat fingertip sensor (`SimConfig::fingertip`).
    Fingertip,
}

impl CommonArgs {
    /// Whether the flat fingertip sensor is simulated.
    pub fn is_fingertip(&self) -> bool {
        self.sensor == Sensor::Fingertip
    }

    /// The sensor of the flags.
    pub fn sensor(&self) -> SensorOptions {
        let numbers =
            |n: &Option<Numbers>| n.as_ref().map(|Numbers(v)| v.clone()).unwrap_or_default();
        SensorOptions {
            fingertip: self.is_fingertip(),
            random_markers: self.random_markers,
            dot_grid: self.dot_grid,
            full_frame: self.full_frame,
            youngs_kpa: self.youngs_kpa,
            poisson: self.poisson,
            layer_mm: self.layer_mm,
            coverage: Some(self.coverage),
            markers: self.markers,
            marker_depth_mm: self.marker_depth_mm,
            pitch_px: self.pitch_px,
            dot_px: self.dot_px,
            jitter_px: self.jitter_px,
            noise_read: Some(self.noise_read),
            flicker: Some(self.flicker),
            exposure_steps: numbers(&self.exposure_steps),
            drift: numbers(&self.drift),
            contact_light: ContactLight {
                change: self.contact_light.unwrap_or(0.0),
                sided: self.contact_shading.unwrap_or(0.0),
            },
        }
    }

    /// The scenario's common options; `flow_default` when neither --flow
    /// nor --no-flow is given.
    pub fn common(&self, flow_default: bool) -> Common {
        let mut c = Common::new(&self.out);
        c.seed = self.seed;
        c.fps = self.fps;
        c.flow = if self.no_flow {
            false
        } else {
            self.flow || flow_default
        };
        c.config = self.sensor().config();
        c
    }
}

/// `--contact-light`'s and `--contact-shading`'s value: a finite fraction
/// within [`ContactLight::MAX_CHANGE`] either way.
fn light_change(s: &str) -> std::result::Result<f32, String> {
    let v: f32 = s
        .trim()
        .parse()
        .map_err(|_| format!("expected a number, got {s:?}"))?;
    if !(v.is_finite() && v.abs() <= ContactLight::MAX_CHANGE) {
        return Err(format!(
            "expected a fraction within -{0}..={0}, got {s}",
            ContactLight::MAX_CHANGE
        ));
    }
    Ok(v)
}

/// `--exposure-steps`' value: EVERY,GAIN[,OFFSET[,LEVELS]], EVERY and LEVELS
/// at least 1.
fn exposure_steps(s: &str) -> std::result::Result<Numbers, String> {
    let v = cli_support::number_list(s)?;
    if !(2..=4).contains(&v.len()) || v[0] < 1.0 || v.get(3).is_some_and(|&l| l < 1.0) {
        return Err("expected EVERY,GAIN[,OFFSET[,LEVELS]] with EVERY and LEVELS >= 1".into());
    }
    Ok(Numbers(v))
}

/// `--marker-depth-mm`'s value: MIN,MAX with 0 < MIN <= MAX (the
/// simulator checks MAX against the gel's thickness).
fn depth_range(s: &str) -> std::result::Result<(f64, f64), String> {
    match cli_support::number_list(s)?.as_slice() {
        &[lo, hi] if lo > 0.0 && lo <= hi => Ok((lo, hi)),
        _ => Err(format!("expected MIN,MAX with 0 < MIN <= MAX, got `{s}`")),
    }
}

/// `--drift`'s value: GAIN,OFFSET,PERIOD, PERIOD above 0.
fn drift(s: &str) -> std::result::Result<Numbers, String> {
    let v = cli_support::number_list(s)?;
    if v.len() != 3 || v[2] <= 0.0 {
        return Err("expected GAIN,OFFSET,PERIOD with PERIOD > 0 frames".into());
    }
    Ok(Numbers(v))
}

/// `rest`'s options.
#[derive(Args, Debug)]
#[command(next_help_heading = "Scenario options")]
pub struct RestArgs {
    /// Frames including the reference.
    #[arg(long, value_name = "N", default_value_t = Rest::default().frames)]
    pub frames: usize,
}

/// `single`'s options.
#[derive(Args, Debug)]
#[command(next_help_heading = "Scenario options")]
pub struct SingleArgs {
    /// Chord position, mm.
    #[arg(long, value_name = "X", allow_negative_numbers = true, default_value_t = Single::default().x_mm)]
    pub x_mm: f64,
    /// Peak force magnitude, N.
    #[arg(long, value_name = "F", default_value_t = Single::default().force_n)]
    pub force_n: f64,
    /// Frames including the reference.
    #[arg(long, value_name = "N", default_value_t = Single::default().frames)]
    pub frames: usize,
    /// Rod (with --sensor fingertip, sphere) diameter, mm.
    #[arg(long, value_name = "D", default_value_t = Single::default().indenter_mm)]
    pub indenter_mm: f64,
    /// Force tilt in the x-z plane, deg.
    #[arg(long, value_name = "P", allow_negative_numbers = true, default_value_t = Single::default().pitch_deg)]
    pub pitch_deg: f64,
    /// Force tilt in the y-z plane, deg.
    #[arg(long, value_name = "Y", allow_negative_numbers = true, default_value_t = Single::default().yaw_deg)]
    pub yaw_deg: f64,
    /// A position sweep: every loaded frame holds the peak force, and the
    /// rod moves in equal steps from --x-mm (frame 1) to X (the last frame).
    #[arg(long, value_name = "X", allow_negative_numbers = true)]
    pub sweep_to_mm: Option<f64>,
}

/// `pair`'s options.
#[derive(Args, Debug)]
#[command(next_help_heading = "Scenario options")]
pub struct PairArgs {
    /// Chord position of the midpoint, mm.
    #[arg(long, value_name = "X", allow_negative_numbers = true, default_value_t = Pair::default().x_mm)]
    pub x_mm: f64,
    /// Distance between the rods along the arc (with --sensor fingertip,
    /// between two spheres' centres side by side along x), mm [default: 40;
    /// 8 with --sensor fingertip].
    #[arg(long, value_name = "S")]
    pub spacing_mm: Option<f64>,
    /// Peak force of the left rod, N.
    #[arg(long, value_name = "F", default_value_t = Pair::default().force_n)]
    pub force_n: f64,
    /// Peak force of the right rod, N.
    #[arg(long, value_name = "F", default_value_t = Pair::default().force2_n)]
    pub force2_n: f64,
    /// Frames including the reference.
    #[arg(long, value_name = "N", default_value_t = Pair::default().frames)]
    pub frames: usize,
    /// Rod (with --sensor fingertip, sphere) diameter, mm.
    #[arg(long, value_name = "D", default_value_t = Pair::default().indenter_mm)]
    pub indenter_mm: f64,
}

/// `presses`' options.
#[derive(Args, Debug)]
#[command(next_help_heading = "Scenario options")]
pub struct PressesArgs {
    /// Loaded frames.
    #[arg(long, value_name = "N", default_value_t = Presses::default().presses)]
    pub presses: usize,
    /// Chord positions uniform in [-X, X], mm.
    #[arg(long, value_name = "X", default_value_t = Presses::default().x_max_mm)]
    pub x_max_mm: f64,
    /// Smallest force magnitude, N.
    #[arg(long, value_name = "F", default_value_t = Presses::default().force_min_n)]
    pub force_min_n: f64,
    /// Largest force magnitude, N.
    #[arg(long, value_name = "F", default_value_t = Presses::default().force_max_n)]
    pub force_max_n: f64,
    /// Pitch or yaw (even odds) uniform in [-T, T], deg [default: 15; 20
    /// for the fingertip sensor's spheres and punches].
    #[arg(long, value_name = "T")]
    pub max_tilt_deg: Option<f64>,
    /// Seed of the presses' places, forces, tilts and rods (tips and shears
    /// on the fingertip sensor) [default: --seed]; another value gives other
    /// presses on the same sensor.
    #[arg(long, value_name = "N")]
    pub press_seed: Option<u64>,
    /// Rod diameters drawn from, mm (the strip).
    #[arg(long, value_name = "D,D,...", default_value_t = Numbers(Presses::default().indenters_mm))]
    pub indenters_mm: Numbers,
    /// Fingertip sensor: a fingertip's tangential force up to this fraction
    /// of its normal force, in any direction.
    #[arg(long, value_name = "R", default_value_t = TipPresses::default().max_shear_ratio)]
    pub max_shear_ratio: f64,
    /// Fingertip sensor: the pressed area stays this far inside the gel's
    /// edges, mm.
    #[arg(long, value_name = "M", default_value_t = TipPresses::default().margin_mm)]
    pub margin_mm: f64,
    /// Fingertip sensor: sphere diameters, uniform in [LO, HI], mm.
    #[arg(long, value_name = "LO,HI", value_parser = range_mm,
          default_value_t = Numbers(pair(TipPresses::default().sphere_mm)))]
    pub sphere_mm: Numbers,
    /// Fingertip sensor: flat punch diameters, uniform in [LO, HI], mm.
    #[arg(long, value_name = "LO,HI", value_parser = range_mm,
          default_value_t = Numbers(pair(TipPresses::default().punch_mm)))]
    pub punch_mm: Numbers,
    /// Fingertip sensor: fingertip diameters, uniform in [LO, HI], mm.
    #[arg(long, value_name = "LO,HI", value_parser = range_mm,
          default_value_t = Numbers(pair(TipPresses::default().fingertip_mm)))]
    pub fingertip_mm: Numbers,
}

/// `(lo, hi)` as a list.
fn pair((lo, hi): (f64, f64)) -> Vec<f64> {
    vec![lo, hi]
}

/// A range of diameters: LO,HI with 0 < LO <= HI.
fn range_mm(s: &str) -> std::result::Result<Numbers, String> {
    let v = cli_support::number_list(s)?;
    if v.len() != 2 || v[0] <= 0.0 || v[0] > v[1] {
        return Err("expected LO,HI with 0 < LO <= HI".into());
    }
    Ok(Numbers(v))
}

/// `shear`'s options.
#[derive(Args, Debug)]
#[command(next_help_heading = "Scenario options")]
pub struct ShearArgs {
    /// Chord position of the rod, mm.
    #[arg(long, value_name = "X", allow_negative_numbers = true, default_value_t = Shear::default().x_mm)]
    pub x_mm: f64,
    /// Peak normal force, N.
    #[arg(long, value_name = "F", default_value_t = Shear::default().force_n)]
    pub force_n: f64,
    /// Peak tangential force along x, N.
    #[arg(long, value_name = "F", allow_negative_numbers = true, default_value_t = Shear::default().shear_n[0])]
    pub shear_x_n: f64,
    /// Peak tangential force along y, N.
    #[arg(long, value_name = "F", allow_negative_numbers = true, default_value_t = Shear::default().shear_n[1])]
    pub shear_y_n: f64,
    /// Frames including the reference.
    #[arg(long, value_name = "N", default_value_t = Shear::default().frames)]
    pub frames: usize,
    /// Rod diameter, mm (with --fingertip-y-mm or --sensor fingertip, the
    /// round tip's diameter: 15-20 mm for a fingertip).
    #[arg(long, value_name = "D", default_value_t = Shear::default().indenter_mm)]
    pub indenter_mm: f64,
    /// A round tip (a fingertip) centred at (--x-mm, this) instead of a rod
    /// across the skin, mm [default: a rod; 0 with --sensor fingertip]. With
    /// --dot-grid, give a fingertip sensor's thin gel too, e.g. --youngs-kpa
    /// 600 --layer-mm 3.
    #[arg(long, value_name = "Y", allow_negative_numbers = true)]
    pub fingertip_y_mm: Option<f64>,
}

/// `characterization`'s options.
#[derive(Args, Debug)]
#[command(next_help_heading = "Scenario options")]
pub struct CharacterizationArgs {
    /// A random subset of N tests [default: all: 7200 with 5 repeats on the
    /// strip, 4320 with 2 on the fingertip sensor].
    #[arg(long, value_name = "N")]
    pub subset: Option<usize>,
    /// Repetitions [default: 5 on the strip, 2 on the fingertip sensor].
    #[arg(long, value_name = "R")]
    pub repeats: Option<u32>,
    /// Load-cell noise per axis, N.
    #[arg(long = "load-cell-noise", value_name = "F", default_value_t = Characterization::default().load_cell_noise_n)]
    pub load_cell_noise_n: f64,
    /// Arc-length step of the sweeps written to sweeps.csv, mm; 0: no
    /// sweeps [default: 0.5 for the whole strip protocol; none with
    /// --subset or on the fingertip sensor].
    #[arg(long = "sweep-step-mm", value_name = "MM")]
    pub sweep_step_mm: Option<f64>,
    /// Also sweep the 5 mm rod with its force tilted by +15 and -15 deg
    /// along the strip (two more sweeps: twice the sweeps' images), from
    /// which `calibrate` learns how the readings of a tilted press vary
    /// along the skin.
    #[arg(long = "tilted-sweeps")]
    pub tilted_sweeps: bool,
    /// Spot checks after the tests (split `spot` of tests.csv): presses of
    /// the protocol's indenters at random places, forces and tilts within
    /// the protocol's ranges, from which `calibrate` scores the maps between
    /// the points and fits the force uncertainty; 0: none [default: 300 for
    /// the whole fingertip protocol, about 50 min at a rig; none on the
    /// strip or with --subset].
    #[arg(long = "spot-checks", value_name = "N")]
    pub spot_checks: Option<usize>,
}

/// `perches`' options.
#[derive(Args, Debug)]
#[command(next_help_heading = "Scenario options")]
pub struct PerchesArgs {
    /// Position of the first rod, mm.
    #[arg(long, value_name = "X", allow_negative_numbers = true, default_value_t = Perches::default().x_mm[0])]
    pub x1_mm: f64,
    /// Position of the second rod, mm.
    #[arg(long, value_name = "X", allow_negative_numbers = true, default_value_t = Perches::default().x_mm[1])]
    pub x2_mm: f64,
    /// Stiffness of the first rod, N/mm.
    #[arg(long, value_name = "K", default_value_t = Perches::default().stiffness_n_per_mm[0])]
    pub k1: f64,
    /// Stiffness of the second rod, N/mm.
    #[arg(long, value_name = "K", default_value_t = Perches::default().stiffness_n_per_mm[1])]
    pub k2: f64,
    /// Deepest penetration, mm.
    #[arg(long, value_name = "P", default_value_t = Perches::default().max_penetration_mm)]
    pub penetration_mm: f64,
    /// Frames including the reference.
    #[arg(long, value_name = "N", default_value_t = Perches::default().frames)]
    pub frames: usize,
    /// Rod diameter, mm.
    #[arg(long, value_name = "D", default_value_t = Perches::default().indenter_mm)]
    pub indenter_mm: f64,
}

/// `mapping`'s options.
#[derive(Args, Debug)]
#[command(next_help_heading = "Scenario options")]
pub struct MappingArgs {
    /// World x of the rods, m.
    #[arg(long, value_name = "X,X,...", allow_hyphen_values = true, default_value_t = Numbers(Mapping::default().rods_x_m))]
    pub rods: Numbers,
    /// Height of the rods' tops, m.
    #[arg(long, value_name = "Z", allow_negative_numbers = true, default_value_t = Mapping::default().rods_top_m)]
    pub rods_top_m: f64,
    /// Touches per rod.
    #[arg(long, value_name = "N", default_value_t = Mapping::default().touches)]
    pub touches: usize,
    /// Peak touch force, N.
    #[arg(long, value_name = "F", default_value_t = Mapping::default().force_n)]
    pub force_n: f64,
    /// Rod diameter, mm.
    #[arg(long, value_name = "D", default_value_t = Mapping::default().indenter_mm)]
    pub indenter_mm: f64,
}

/// `fixtures`' options.
#[derive(Args, Debug)]
pub struct FixturesArgs {
    /// Fixtures folder.
    #[arg(long, value_name = "DIR", default_value = FIXTURES_DIR)]
    pub out: PathBuf,
    /// Also write reference_frame.png and press_motion.png there.
    #[arg(long, value_name = "DIR")]
    pub docs: Option<PathBuf>,
    /// Seed for markers, noise and random choices.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub seed: u64,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
}

/// What the command line asks for.
#[derive(Debug, Clone, PartialEq)]
pub enum Job {
    /// Run one scenario (boxed: the options are large).
    Run(Box<(Scenario, Common)>),
    /// Regenerate the fixtures under `out` (and the pictures under `docs`).
    Fixtures {
        /// Fixtures folder.
        out: PathBuf,
        /// Pictures folder, if wanted.
        docs: Option<PathBuf>,
        /// Seed.
        seed: u64,
    },
}

impl Command {
    /// The job, and whether to hide the progress bar.
    pub fn job(self) -> (Job, bool) {
        let run = |s: Scenario, c: &CommonArgs, flow: bool| {
            (Job::Run(Box::new((s, c.common(flow)))), c.quiet)
        };
        match self {
            Command::Single { common, options: o } => run(
                Scenario::Single(Single {
                    x_mm: o.x_mm,
                    force_n: o.force_n,
                    frames: o.frames,
                    indenter_mm: o.indenter_mm,
                    yaw_deg: o.yaw_deg,
                    pitch_deg: o.pitch_deg,
                    sweep_to_mm: o.sweep_to_mm,
                }),
                &common,
                true,
            ),
            Command::Pair { common, options: o } => run(
                Scenario::Pair(Pair {
                    x_mm: o.x_mm,
                    spacing_mm: o.spacing_mm.unwrap_or(if common.is_fingertip() {
                        Pair::fingertip().spacing_mm
                    } else {
                        Pair::default().spacing_mm
                    }),
                    force_n: o.force_n,
                    force2_n: o.force2_n,
                    frames: o.frames,
                    indenter_mm: o.indenter_mm,
                }),
                &common,
                true,
            ),
            Command::Presses { common, options: o } if common.is_fingertip() => run(
                Scenario::TipPresses(TipPresses {
                    presses: o.presses,
                    force_min_n: o.force_min_n,
                    force_max_n: o.force_max_n,
                    max_tilt_deg: o.max_tilt_deg.unwrap_or(TipPresses::default().max_tilt_deg),
                    max_shear_ratio: o.max_shear_ratio,
                    margin_mm: o.margin_mm,
                    sphere_mm: (o.sphere_mm.0[0], o.sphere_mm.0[1]),
                    punch_mm: (o.punch_mm.0[0], o.punch_mm.0[1]),
                    fingertip_mm: (o.fingertip_mm.0[0], o.fingertip_mm.0[1]),
                    press_seed: o.press_seed,
                }),
                &common,
                true,
            ),
            Command::Presses { common, options: o } => run(
                Scenario::Presses(Presses {
                    presses: o.presses,
                    x_max_mm: o.x_max_mm,
                    force_min_n: o.force_min_n,
                    force_max_n: o.force_max_n,
                    max_tilt_deg: o.max_tilt_deg.unwrap_or(Presses::default().max_tilt_deg),
                    indenters_mm: o.indenters_mm.0,
                    press_seed: o.press_seed,
                }),
                &common,
                true,
            ),
            Command::Shear { common, options: o } => run(
                Scenario::Shear(Shear {
                    x_mm: o.x_mm,
                    force_n: o.force_n,
                    shear_n: [o.shear_x_n, o.shear_y_n],
                    frames: o.frames,
                    indenter_mm: o.indenter_mm,
                    // On the fingertip sensor a round tip, at the centre
                    // unless placed.
                    fingertip_y_mm: o.fingertip_y_mm.or(common.is_fingertip().then_some(0.0)),
                }),
                &common,
                true,
            ),
            Command::Characterization { common, options: o } => run(
                Scenario::Characterization(Characterization {
                    subset: o.subset,
                    repeats: o.repeats.unwrap_or(if common.is_fingertip() {
                        Characterization::flat().repeats
                    } else {
                        Characterization::default().repeats
                    }),
                    load_cell_noise_n: o.load_cell_noise_n,
                    sweep_step_mm: o.sweep_step_mm,
                    tilted_sweeps: o.tilted_sweeps,
                    spot_checks: o.spot_checks,
                }),
                &common,
                false,
            ),
            Command::Perches { common, options: o } => run(
                Scenario::Perches(Perches {
                    x_mm: [o.x1_mm, o.x2_mm],
                    stiffness_n_per_mm: [o.k1, o.k2],
                    max_penetration_mm: o.penetration_mm,
                    frames: o.frames,
                    indenter_mm: o.indenter_mm,
                }),
                &common,
                true,
            ),
            Command::Mapping { common, options: o } => run(
                Scenario::Mapping(Mapping {
                    rods_x_m: o.rods.0,
                    rods_top_m: o.rods_top_m,
                    touches: o.touches,
                    force_n: o.force_n,
                    indenter_mm: o.indenter_mm,
                }),
                &common,
                true,
            ),
            Command::Rest { common, options: o } => {
                run(Scenario::Rest(Rest { frames: o.frames }), &common, true)
            }
            Command::Fixtures(f) => (
                Job::Fixtures {
                    out: f.out,
                    docs: f.docs,
                    seed: f.seed,
                },
                f.quiet,
            ),
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    cli_support::finish(run(cli.command).map(|()| ExitCode::SUCCESS))
}

fn run(command: Command) -> std::result::Result<(), Failure> {
    let t0 = Instant::now();
    let (job, quiet) = command.job();
    let mut out = Sink::stdout();
    let stages = Stages::new(quiet);
    let progress = |stage: &str, done: usize, total: usize| stages.update(stage, done, total);
    match job {
        Job::Run(run) => {
            let (sc, common) = *run;
            if common.config.full_frame {
                let (x, y, w, h) = common.config.camera.crop();
                writeln!(
                    out,
                    "full frame; the sensing strip is the crop x={x} y={y} w={w} h={h}"
                )?;
            }
            let sum = scenario::run_with_progress(&sc, &common, &progress);
            stages.finish();
            let sum = sum?;
            writeln!(
                out,
                "wrote {} frames to {} in {:.1} s",
                sum.frames,
                sum.out.display(),
                t0.elapsed().as_secs_f64()
            )?;
        }
        Job::Fixtures {
            out: dir,
            docs,
            seed,
        } => {
            let done = scenario::fixtures_with_progress(&dir, seed, &progress);
            stages.finish();
            done?;
            if let Some(d) = docs {
                pictures(&d, seed)?;
            }
            writeln!(
                out,
                "fixtures written to {} in {:.1} s",
                dir.display(),
                t0.elapsed().as_secs_f64()
            )?;
        }
    }
    Ok(())
}

/// README pictures: an enlarged crop of a reference frame, and the true motion
/// field of a two-rod press (magnitude in colour, arrows exaggerated).
fn pictures(dir: &Path, seed: u64) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| optical_tactile::Error::io(dir, e))?;
    let mut sensor = SyntheticSensor::new(SimConfig::default(), seed)?;
    let (reference, _) = sensor.render(&[])?;
    let crop = reference.slice(s![.., 640..960]).to_owned();
    let scale = 3;
    let mut c = Canvas::new(crop.ncols() * scale, crop.nrows() * scale, Rgb(0, 0, 0));
    c.gray(&crop, 0, 0, scale);
    c.save_png(dir.join("reference_frame.png"))?;

    let contacts = [
        Press::rod(-20.0, [0.0, 0.0, -2.0], 5.0),
        Press::rod(20.0, [0.0, 0.0, -1.5], 5.0),
    ];
    let (_, flow) = sensor.render(&contacts)?;
    let (x0, x1) = (560usize, 1040usize);
    let mag: Array2<f64> = flow.magnitude().slice(s![.., x0..x1]).mapv(|v| v as f64);
    let scale = 2;
    let mut c = Canvas::new(mag.ncols() * scale, mag.nrows() * scale, Rgb(0, 0, 0));
    c.scalar(&mag, 0, 0, scale);
    let exaggerate = 20.0;
    let step = 12;
    for y in (step / 2..flow.height()).step_by(step) {
        for x in (x0 + step / 2..x1).step_by(step) {
            let (u, v) = (flow.u[[y, x]] as f64, flow.v[[y, x]] as f64);
            let (px, py) = (((x - x0) * scale) as f64, (y * scale) as f64);
            c.arrow(
                px,
                py,
                px + exaggerate * u * scale as f64,
                py + exaggerate * v * scale as f64,
                Rgb(255, 255, 255),
            );
        }
    }
    // Contact positions as dots (true x_px).
    for ct in &contacts {
        let r = scenario::truth_record(&sensor, ct);
        let (xp, yp) = (r.x_px.unwrap_or(0.0), r.y_px.unwrap_or(0.0));
        c.dot(
            (xp - x0 as f64) * scale as f64,
            yp * scale as f64,
            4.0,
            colormap(1.0),
        );
    }
    c.save_png(dir.join("press_motion.png"))?;
    Ok(())
}
