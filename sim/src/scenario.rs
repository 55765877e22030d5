//! Scenarios: sequences of frames with ground truth, written to a folder in the
//! file formats of docs/formats.md.
//!
//! Every scenario writes its frames as 8-bit grey PNG. Sequences (`single`,
//! `pair`, `presses`, `perches`, `mapping`, `rest`) write `000000.png, 000001.png, ...` (frame 0
//! is the unloaded reference), `truth.jsonl` (one line per frame with the true
//! contacts) and, unless disabled, the true dense motion of each frame as
//! `flow/000000.flo`. `characterization` writes `tests.csv` and
//! `frames/tNNNN.png` + `frames/tNNNN_ref.png` per test (and, with `flow`,
//! `flow/tNNNN.flo`); on a flat sensor ([`SimConfig::fingertip`]) it runs the
//! flat protocol ([`FLAT_TIPS`] on a grid of points) and also writes
//! `geometry.json` (the [`SensorGeometry`](optical_tactile::geometry::SensorGeometry)
//! as JSON) and `indenters.json`. With the full-frame option every scenario also writes
//! `crop.json`, the strip's rectangle `{x, y, width, height}` in the frame.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use serde::Serialize;

use super::config::SimConfig;
use super::rng::{SplitMix64, mix64};
use super::sensor::{Press, SyntheticSensor, Tip};
use optical_tactile::error::{Error, Result};
use optical_tactile::io::{self, ContactRecord, FrameRecord, PoseRow, Split, TestRow};

/// Options shared by every scenario.
#[derive(Debug, Clone, PartialEq)]
pub struct Common {
    /// Output folder (created if missing).
    pub out: PathBuf,
    /// Seed: fixes the marker layout, the noise and every random choice.
    pub seed: u64,
    /// Write the true dense motion (`.flo`) of every frame.
    pub flow: bool,
    /// Frame rate for the `t_s` time stamps.
    pub fps: f64,
    /// The synthetic sensor's configuration.
    pub config: SimConfig,
}

impl Common {
    /// Defaults for `out`: seed 1, flow on, 50 fps, default sensor.
    pub fn new(out: impl Into<PathBuf>) -> Self {
        Common {
            out: out.into(),
            seed: 1,
            flow: true,
            fps: 50.0,
            config: SimConfig::default(),
        }
    }
}

/// One indenter pressing with a force ramp: a rod across the strip, or on a
/// flat sensor a sphere of the rod's diameter on its centre line (`y = 0`).
#[derive(Debug, Clone, PartialEq)]
pub struct Single {
    /// Chord position, mm.
    pub x_mm: f64,
    /// Peak force magnitude, N.
    pub force_n: f64,
    /// Number of frames including the unloaded reference (frame 0).
    pub frames: usize,
    /// Rod diameter, mm.
    pub indenter_mm: f64,
    /// Tilt of the force in the y-z plane, degrees.
    pub yaw_deg: f64,
    /// Tilt of the force in the x-z plane, degrees.
    pub pitch_deg: f64,
    /// A position sweep: `Some(x_to)` holds the peak force on every loaded
    /// frame and moves the rod from `x_mm` (frame 1) to `x_to` (the last
    /// frame) in equal steps, each frame against the unloaded frame 0. It
    /// shows how a calibration's readings change with the position of one
    /// load, between the protocol's points and across the marker pattern.
    pub sweep_to_mm: Option<f64>,
}

impl Single {
    /// The rod of frame `k` (`None` for the reference, frame 0).
    pub fn press(&self, k: usize) -> Option<Press> {
        if k == 0 {
            return None;
        }
        let f = tilted_force(1.0, self.yaw_deg, self.pitch_deg);
        match self.sweep_to_mm {
            None => Some(Press::rod(
                self.x_mm,
                f.map(|v| v * (self.force_n * ramp(k, self.frames))),
                self.indenter_mm,
            )),
            Some(to) => {
                let t = if self.frames > 2 {
                    (k - 1) as f64 / (self.frames - 2) as f64
                } else {
                    0.0
                };
                Some(Press::rod(
                    self.x_mm + t * (to - self.x_mm),
                    f.map(|v| v * self.force_n),
                    self.indenter_mm,
                ))
            }
        }
    }
}

impl Default for Single {
    fn default() -> Self {
        Single {
            x_mm: 0.0,
            force_n: 2.0,
            frames: 10,
            indenter_mm: 5.0,
            yaw_deg: 0.0,
            pitch_deg: 0.0,
            sweep_to_mm: None,
        }
    }
}

/// Two indenters at a given spacing, pressing together with force ramps:
/// rods across the strip or, on a flat sensor, two spheres side by side
/// along x on its centre line (`y = 0`).
#[derive(Debug, Clone, PartialEq)]
pub struct Pair {
    /// Chord position of the midpoint between the rods, mm.
    pub x_mm: f64,
    /// Distance between the rods along the arc (between the spheres' centres
    /// on a flat sensor), mm.
    pub spacing_mm: f64,
    /// Peak force of the first (left) rod, N.
    pub force_n: f64,
    /// Peak force of the second (right) rod, N.
    pub force2_n: f64,
    /// Number of frames including the reference.
    pub frames: usize,
    /// Rod (or sphere) diameter, mm.
    pub indenter_mm: f64,
}

impl Default for Pair {
    fn default() -> Self {
        Pair {
            x_mm: 0.0,
            spacing_mm: 40.0,
            force_n: 2.0,
            force2_n: 1.5,
            frames: 10,
            indenter_mm: 5.0,
        }
    }
}

impl Pair {
    /// The pair on a flat fingertip sensor: two 5 mm spheres 8 mm apart (a
    /// gap of 3 mm between them on its 24 mm gel), the rest as
    /// [`Pair::default`].
    pub fn fingertip() -> Self {
        Pair {
            spacing_mm: 8.0,
            ..Pair::default()
        }
    }
}

/// The characterization protocol (docs/calibration.md): the strip's (13
/// points on the centre line, rods) or, when the sensor's geometry is flat,
/// the flat protocol (a 5 x 4 grid of points, [`flat_point_mm`]; the
/// indenters [`FLAT_TIPS`]; the tilts [`FLAT_TILTS_DEG`]; the held-out
/// points [`FLAT_HELD_OUT_POINTS`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Characterization {
    /// Only a random subset of this many tests (all when `None`).
    pub subset: Option<usize>,
    /// Repetitions per (point, indenter, tilt, force): 5 by default (the
    /// strip's protocol); the flat protocol's default is
    /// [`FLAT_REPEATS`] ([`Characterization::flat`]).
    pub repeats: u32,
    /// Load-cell noise, N (standard deviation per axis). The default, 3 mN,
    /// is the resolution class of a small 6-axis F/T sensor (an ATI Nano17
    /// resolves 1/320 N); see [`LOAD_CELL_NOISE_N`].
    pub load_cell_noise_n: f64,
    /// Arc-length step of the sweeps ([`SWEEPS`]) written beside the
    /// tests (`sweeps.csv`), mm; `None`: [`SWEEP_STEP_MM`] for the whole
    /// strip protocol, no sweeps with a `subset` or on a flat sensor;
    /// `Some(0.0)`: no sweeps; a negative or non-finite step is an error.
    pub sweep_step_mm: Option<f64>,
    /// Also write the [`TILTED_SWEEPS`] after the straight ones (twice the
    /// sweeps' images and rig time).
    pub tilted_sweeps: bool,
    /// Spot checks written after the tests (`spot` split): presses of the
    /// protocol's indenters at places, forces and tilts drawn at random
    /// within the protocol's ranges (one of its indenters, a force uniform
    /// over its ladder's span, tilted about one axis up to its largest
    /// tilt, anywhere in its points' extent); `None`:
    /// [`FLAT_SPOT_CHECKS`] on a flat sensor's whole protocol, none on the
    /// strip or with a `subset`. At most [`MAX_SPOT_CHECKS`].
    pub spot_checks: Option<usize>,
}

/// The flat protocol's default number of spot checks: 300 presses, about
/// 50 minutes at a rig (10 s a press), from which `calibrate` scores the
/// maps between the protocol's points and fits the force uncertainty.
pub const FLAT_SPOT_CHECKS: usize = 300;
/// Largest number of spot checks of one characterization.
pub const MAX_SPOT_CHECKS: usize = 100_000;

/// The sweeps of the strip's protocol, `(indenter_mm, force_n)`: each
/// presses the rod straight down with this force at every
/// [`SWEEP_STEP_MM`] of arc between the outermost training points, one
/// image per position against one unloaded reference per sweep. They
/// sample the skin densely, which the 13 marked points cannot: how the
/// readings vary with the marker pattern under the contact
/// (`optical_tactile::calibration::correction`).
pub const SWEEPS: [(f64, f64); 2] = [(10.0, 2.0), (5.0, 2.0)];
/// The optional tilted sweeps (`Characterization::tilted_sweeps`),
/// `(indenter_mm, force_n, pitch_deg)`: the 5 mm rod of [`SWEEPS`] with its
/// force turned by 15 degrees either way along the strip, the protocol's
/// largest pitch. Under a tilted load the contact column and the matched
/// force follow the marker pattern otherwise than under a straight one;
/// these sweeps let `calibrate` learn that too (corrections that depend on
/// the contact's shear ratio, `optical_tactile::calibration::correction`).
pub const TILTED_SWEEPS: [(f64, f64, f64); 2] = [(5.0, 2.0, 15.0), (5.0, 2.0, -15.0)];
/// Default arc-length step of the sweeps, mm (457 images per sweep on
/// the default strip).
pub const SWEEP_STEP_MM: f64 = 0.5;
/// Largest number of images of one sweep (a step too small for the skin
/// is an error, not a huge dataset).
pub const MAX_SWEEP_FRAMES: usize = 20_000;

/// Default load-cell noise of the characterization protocol, N (standard
/// deviation per axis): a good rig's load cell, about 1/320 N.
///
/// It sets a floor under every force MAE scored against the recorded force:
/// an exact sensor scores `sqrt(2 / pi) = 0.8` times it
/// ([`optical_tactile::calibration::fit::load_cell_spread`] measures it from a dataset's
/// repetitions). A 10 mN cell (`--load-cell-noise 0.01`, this simulator's
/// earlier default) puts that floor at 8 mN: above the 5 mN Fy the project
/// aims at, and equal to the Fy the paper's method reached in Python on
/// synthetic data of this kind, whose load cell must have been quieter.
pub const LOAD_CELL_NOISE_N: f64 = 0.003;

impl Default for Characterization {
    fn default() -> Self {
        Characterization {
            subset: None,
            repeats: 5,
            load_cell_noise_n: LOAD_CELL_NOISE_N,
            sweep_step_mm: None,
            tilted_sweeps: false,
            spot_checks: None,
        }
    }
}

impl Characterization {
    /// The flat protocol's defaults: every test, [`FLAT_REPEATS`]
    /// repetitions, the default load cell.
    pub fn flat() -> Self {
        Characterization {
            repeats: FLAT_REPEATS,
            ..Characterization::default()
        }
    }
}

/// Independent single presses anywhere on the skin, each frame against the
/// one unloaded reference (frame 0): position, force, tilt and rod drawn at
/// random. The characterization protocol presses on 13 marked points only;
/// this scenario measures what a calibration does between them, where a
/// user's contacts land. Also writes `presses.json` (per loaded frame: the
/// rod's diameter and the tilt).
#[derive(Debug, Clone, PartialEq)]
pub struct Presses {
    /// Number of loaded frames (one press each).
    pub presses: usize,
    /// Presses land uniformly in `[-x_max_mm, x_max_mm]` along the chord, mm.
    pub x_max_mm: f64,
    /// Smallest force magnitude, N.
    pub force_min_n: f64,
    /// Largest force magnitude, N.
    pub force_max_n: f64,
    /// Largest tilt, degrees: each press tilts about one axis (pitch or
    /// yaw, even odds, as the protocol does), uniformly within +-this.
    pub max_tilt_deg: f64,
    /// Rod diameters drawn from, mm (even odds).
    pub indenters_mm: Vec<f64>,
    /// Seed of the draws (places, forces, tilts, rods); `None`: the
    /// sensor's seed ([`Common::seed`]). Another press seed gives other
    /// presses on the same sensor (same markers), so that a calibration can
    /// be checked on several sets of presses.
    pub press_seed: Option<u64>,
}

impl Default for Presses {
    fn default() -> Self {
        Presses {
            presses: 150,
            x_max_mm: 110.0,
            force_min_n: 0.5,
            force_max_n: 3.0,
            max_tilt_deg: 15.0,
            indenters_mm: vec![2.0, 5.0, 10.0],
            press_seed: None,
        }
    }
}

/// Independent presses of round tips anywhere on a flat sensor (or on the
/// strip), each frame against the one unloaded reference (frame 0): the
/// flat counterpart of [`Presses`]. Each press draws its indenter's kind
/// (sphere, flat punch or fingertip, even odds) and diameter (uniform in
/// the kind's range), its force magnitude, and its direction: spheres and
/// punches tilt about one axis (pitch or yaw, even odds) within
/// `max_tilt_deg`, as the protocol's rig does; fingertips shear in any
/// direction with a tangential force up to `max_shear_ratio` times the
/// normal force. The centre lands uniformly where the pressed area (its
/// radius under the drawn force, [`Tip::contact_radius_mm`]) stays
/// `margin_mm` inside the gel's edges. Also writes `presses.json` (per
/// loaded frame: the indenter, its contact diameter, the tilt or shear).
#[derive(Debug, Clone, PartialEq)]
pub struct TipPresses {
    /// Number of loaded frames (one press each).
    pub presses: usize,
    /// Smallest force magnitude, N.
    pub force_min_n: f64,
    /// Largest force magnitude, N.
    pub force_max_n: f64,
    /// Largest tilt of sphere and punch presses, degrees.
    pub max_tilt_deg: f64,
    /// Largest tangential force of a fingertip, as a fraction of its normal
    /// force (0.8: a firm, rubbery grip).
    pub max_shear_ratio: f64,
    /// Distance kept between the pressed area and the gel's edges, mm.
    pub margin_mm: f64,
    /// Sphere diameters, mm: `(smallest, largest)`.
    pub sphere_mm: (f64, f64),
    /// Flat punch diameters, mm. (Not below 6 mm by default: a narrower
    /// punch at 3 N presses the gel harder than its modulus, beyond the
    /// linear thin-layer model, and moves the dots by tens of px.)
    pub punch_mm: (f64, f64),
    /// Fingertip diameters, mm.
    pub fingertip_mm: (f64, f64),
    /// Seed of the draws (tips, places, forces, tilts, shears); `None`: the
    /// sensor's seed ([`Common::seed`]). Another press seed gives other
    /// presses on the same sensor (same dots or markers).
    pub press_seed: Option<u64>,
}

impl Default for TipPresses {
    fn default() -> Self {
        TipPresses {
            presses: 150,
            force_min_n: 0.5,
            force_max_n: 3.0,
            max_tilt_deg: 20.0,
            max_shear_ratio: 0.8,
            margin_mm: 0.5,
            sphere_mm: (3.0, 12.0),
            punch_mm: (6.0, 12.0),
            fingertip_mm: (15.0, 20.0),
            press_seed: None,
        }
    }
}

/// A rod pressing, then shearing: the normal force ramps up over the first
/// half of the loaded frames, then, held, the tangential force ramps up over
/// the second half. Also writes `markers.csv` (`x_px,y_px`: every marker's
/// centre in the reference frame, image pixels), for scoring a flow at the
/// markers. With [`SimConfig::dot_grid`] it makes dot-grid frames of a
/// GelSight-like sensor with their true flow.
#[derive(Debug, Clone, PartialEq)]
pub struct Shear {
    /// Chord position of the rod, mm.
    pub x_mm: f64,
    /// Peak normal force, N (pressing: applied as `Fz = -force_n`).
    pub force_n: f64,
    /// Peak tangential force `[Fx, Fy]`, N.
    pub shear_n: [f64; 2],
    /// Number of frames including the unloaded reference (at least 3).
    pub frames: usize,
    /// Rod diameter, mm (the tip's diameter for a fingertip).
    pub indenter_mm: f64,
    /// `Some(y_mm)`: a round tip (a fingertip, [`Press::fingertip`]) centred
    /// at `(x_mm, y_mm)` instead of a rod across the skin.
    pub fingertip_y_mm: Option<f64>,
}

impl Default for Shear {
    fn default() -> Self {
        Shear {
            x_mm: 0.0,
            force_n: 2.0,
            shear_n: [0.6, 0.2],
            frames: 9,
            indenter_mm: 5.0,
            fingertip_y_mm: None,
        }
    }
}

/// Two perches of different stiffness under a descending body.
#[derive(Debug, Clone, PartialEq)]
pub struct Perches {
    /// Chord positions of the two rods, mm.
    pub x_mm: [f64; 2],
    /// Stiffness of the two rods, N/mm (force = stiffness x penetration).
    pub stiffness_n_per_mm: [f64; 2],
    /// Deepest penetration of the skin, mm.
    pub max_penetration_mm: f64,
    /// Number of frames including the reference.
    pub frames: usize,
    /// Rod diameter, mm.
    pub indenter_mm: f64,
}

impl Default for Perches {
    fn default() -> Self {
        Perches {
            x_mm: [-60.0, 50.0],
            stiffness_n_per_mm: [1.0, 2.0],
            max_penetration_mm: 1.5,
            frames: 12,
            indenter_mm: 10.0,
        }
    }
}

/// Touch, move, touch along a trajectory over rods at known world positions.
#[derive(Debug, Clone, PartialEq)]
pub struct Mapping {
    /// World x of each rod's axis, m (rods lie along world y).
    pub rods_x_m: Vec<f64>,
    /// Height of the rods' tops, m.
    pub rods_top_m: f64,
    /// Touches per rod (each at a new random place on the skin).
    pub touches: usize,
    /// Peak force of a touch, N.
    pub force_n: f64,
    /// Rod diameter, mm.
    pub indenter_mm: f64,
}

impl Default for Mapping {
    fn default() -> Self {
        Mapping {
            rods_x_m: vec![0.4, 0.9, 1.35, 1.9, 2.5],
            rods_top_m: 1.0,
            touches: 2,
            force_n: 1.5,
            indenter_mm: 10.0,
        }
    }
}

/// Unloaded frames only: the skin at rest for `frames` frames (frame 0 the
/// reference), to see what the camera alone does to the pipeline. With the
/// noise model's exposure changes ([`crate::ExposureChanges`]) the frames
/// carry exposure steps and slow drift; the scenario then also writes
/// `camera.csv`, each frame's gain and black-level offset
/// (`frame,level,gain,offset`).
#[derive(Debug, Clone, PartialEq)]
pub struct Rest {
    /// Number of frames including the reference.
    pub frames: usize,
}

impl Default for Rest {
    fn default() -> Self {
        Rest { frames: 200 }
    }
}

/// A scenario and its options.
#[derive(Debug, Clone, PartialEq)]
pub enum Scenario {
    /// One indenter, force ramp, optional tilt; or a position sweep at one
    /// force.
    Single(Single),
    /// Two indenters at a given spacing.
    Pair(Pair),
    /// Independent presses at random places, forces and tilts.
    Presses(Presses),
    /// Independent presses of round tips (spheres, punches, fingertips) at
    /// random places in x and y, forces, tilts and shears.
    TipPresses(TipPresses),
    /// A press, then shear, with the markers' centres.
    Shear(Shear),
    /// The characterization protocol in the `tests.csv` format.
    Characterization(Characterization),
    /// Two perches of different stiffness.
    Perches(Perches),
    /// Touch mapping with poses.
    Mapping(Mapping),
    /// The skin at rest, optionally with exposure steps and drift.
    Rest(Rest),
}

/// Progress callback: `(stage, done, total)`, called from worker threads as
/// work completes (a scenario's stage is its name, its steps the frames or
/// tests written). The library prints nothing: the caller shows progress.
pub type Progress<'a> = &'a (dyn Fn(&str, usize, usize) + Sync);

/// A progress callback that does nothing.
pub fn no_progress(_: &str, _: usize, _: usize) {}

/// What a scenario wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// The output folder.
    pub out: PathBuf,
    /// Number of PNG frames written.
    pub frames: usize,
}

/// The force of magnitude `f` pressing along the world vertical on a sensor
/// tilted by `(yaw, pitch)` degrees, in the sensor frame: pitch turns it in the
/// x-z plane (positive pitch gives positive `Fx`), yaw in the y-z plane.
pub fn tilted_force(f: f64, yaw_deg: f64, pitch_deg: f64) -> [f64; 3] {
    let (sy, cy) = yaw_deg.to_radians().sin_cos();
    let (sp, cp) = pitch_deg.to_radians().sin_cos();
    [f * sp * cy, f * sy, -f * cp * cy]
}

fn check_force(name: &str, f: f64) -> Result<()> {
    if !(f.is_finite() && f >= 0.0) {
        return Err(Error::param(
            name,
            format!("force magnitude must be finite and >= 0, got {f}"),
        ));
    }
    Ok(())
}

fn check_frames(n: usize) -> Result<()> {
    if n < 2 {
        return Err(Error::param(
            "frames",
            format!("need at least 2 (reference + one loaded), got {n}"),
        ));
    }
    Ok(())
}

/// The strip's rectangle in a full frame, written as `crop.json` beside
/// full-frame output so that a user (or the pipeline) can crop it.
#[derive(Serialize)]
struct Crop {
    x: usize,
    y: usize,
    width: usize,
    height: usize,
}

fn write_crop(c: &Common) -> Result<()> {
    if c.config.full_frame {
        let (x, y, width, height) = c.config.camera.crop();
        write_json(
            &c.out.join("crop.json"),
            &Crop {
                x,
                y,
                width,
                height,
            },
        )?;
    }
    Ok(())
}

fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    // Creating succeeds on an existing read-only folder: probe that we can write.
    let probe = dir.join(".write-probe");
    std::fs::write(&probe, b"").map_err(|e| Error::io(dir, e))?;
    std::fs::remove_file(&probe).map_err(|e| Error::io(&probe, e))
}

/// Writes frames + truth of a contact sequence of `total` frames, reporting
/// each frame written to `progress` under `stage`.
struct SequenceWriter<'p> {
    out: PathBuf,
    flow: bool,
    fps: f64,
    truth: io::JsonlWriter,
    n: usize,
    stage: &'static str,
    total: usize,
    progress: Progress<'p>,
}

impl<'p> SequenceWriter<'p> {
    fn new(c: &Common, stage: &'static str, total: usize, progress: Progress<'p>) -> Result<Self> {
        create_dir(&c.out)?;
        if c.flow {
            create_dir(&c.out.join("flow"))?;
        }
        write_crop(c)?;
        Ok(SequenceWriter {
            out: c.out.clone(),
            flow: c.flow,
            fps: c.fps,
            truth: io::JsonlWriter::create(c.out.join("truth.jsonl"))?,
            n: 0,
            stage,
            total,
            progress,
        })
    }

    fn name(&self) -> String {
        format!("{:06}.png", self.n)
    }

    fn frame(&mut self, sensor: &SyntheticSensor, contacts: &[Press]) -> Result<String> {
        let name = self.name();
        let r = sensor.render_indexed(self.n as u64, contacts, self.flow)?;
        io::write_gray_png(self.out.join(&name), &r.frame)?;
        if let Some(flow) = &r.flow {
            io::write_flo(
                self.out.join("flow").join(format!("{:06}.flo", self.n)),
                flow,
            )?;
        }
        let rec = FrameRecord {
            frame: name.clone(),
            t_s: self.n as f64 / self.fps,
            contacts: contacts.iter().map(|c| truth_record(sensor, c)).collect(),
            latency_ms: None,
        };
        self.truth.write(&rec)?;
        self.n += 1;
        (self.progress)(self.stage, self.n, self.total);
        Ok(name)
    }
}

/// The JSON Lines record (docs/formats.md) of a true contact (pixel position in the strip image).
pub fn truth_record(sensor: &SyntheticSensor, c: &Press) -> ContactRecord {
    let cfg = sensor.config();
    let s = cfg.skin.geometry.chord_to_arc(c.x_mm);
    // A rod lies across the whole skin: its point is on the centre line.
    let y = c.y_mm.unwrap_or(0.0);
    ContactRecord {
        x_mm: c.x_mm,
        y_mm: y,
        z_mm: cfg.skin.z_at(c.x_mm),
        fx_n: c.force_n[0],
        fy_n: c.force_n[1],
        fz_n: c.force_n[2],
        x_px: Some(cfg.camera.skin_to_px(&cfg.skin, s, y).0),
        y_px: Some(cfg.camera.skin_to_px(&cfg.skin, s, y).1),
        ..Default::default()
    }
}

/// Runs a scenario, writing everything into `common.out`.
pub fn run(scenario: &Scenario, common: &Common) -> Result<Summary> {
    run_with_progress(scenario, common, &no_progress)
}

/// [`run`], reporting every frame (or characterization test) written to
/// `progress` as `(scenario name, done, total)`.
pub fn run_with_progress(
    scenario: &Scenario,
    common: &Common,
    progress: Progress<'_>,
) -> Result<Summary> {
    if !(common.fps.is_finite() && common.fps > 0.0) {
        return Err(Error::param(
            "fps",
            format!("must be > 0, got {}", common.fps),
        ));
    }
    // Check every option before touching the disk.
    match scenario {
        Scenario::Single(o) => {
            check_force("force_n", o.force_n)?;
            check_frames(o.frames)?;
            if let Some(to) = o.sweep_to_mm
                && !to.is_finite()
            {
                return Err(Error::param(
                    "sweep_to_mm",
                    format!("must be finite, got {to}"),
                ));
            }
        }
        Scenario::Pair(o) => {
            check_force("force_n", o.force_n)?;
            check_force("force2_n", o.force2_n)?;
            check_frames(o.frames)?;
            if !(o.spacing_mm.is_finite() && o.spacing_mm > 0.0) {
                return Err(Error::param(
                    "spacing_mm",
                    format!("must be > 0, got {}", o.spacing_mm),
                ));
            }
        }
        Scenario::Presses(o) => {
            check_random_presses(o.presses, (o.force_min_n, o.force_max_n), o.max_tilt_deg)?;
            if !(o.x_max_mm.is_finite() && o.x_max_mm >= 0.0) {
                return Err(Error::param("x_max_mm", "must be finite and >= 0"));
            }
            if o.indenters_mm.is_empty() {
                return Err(Error::param("indenters_mm", "need at least one rod"));
            }
        }
        Scenario::TipPresses(o) => check_tip_presses(o)?,
        Scenario::Shear(o) => {
            check_force("force_n", o.force_n)?;
            if o.frames < 3 {
                return Err(Error::param(
                    "frames",
                    format!(
                        "need at least 3 (reference, press, shear), got {}",
                        o.frames
                    ),
                ));
            }
            if o.shear_n.iter().any(|f| !f.is_finite()) {
                return Err(Error::param("shear_n", "must be finite"));
            }
        }
        Scenario::Characterization(o) => {
            if o.repeats == 0 {
                return Err(Error::param("repeats", "need at least 1"));
            }
            if o.subset == Some(0) {
                return Err(Error::param("subset", "need at least 1 test"));
            }
            check_force("load_cell_noise_n", o.load_cell_noise_n)?;
        }
        Scenario::Perches(o) => {
            check_frames(o.frames)?;
            for k in o.stiffness_n_per_mm {
                if !(k.is_finite() && k > 0.0) {
                    return Err(Error::param(
                        "stiffness_n_per_mm",
                        format!("must be > 0, got {k}"),
                    ));
                }
            }
            if !(o.max_penetration_mm.is_finite() && o.max_penetration_mm >= 0.0) {
                return Err(Error::param("max_penetration_mm", "must be >= 0"));
            }
        }
        Scenario::Mapping(o) => {
            check_force("force_n", o.force_n)?;
            if o.rods_x_m.is_empty() || o.touches == 0 {
                return Err(Error::param(
                    "rods_x_m",
                    "need at least one rod and one touch",
                ));
            }
            if o.rods_x_m.iter().any(|x| !x.is_finite()) || !o.rods_top_m.is_finite() {
                return Err(Error::param("rods_x_m", "rod positions must be finite"));
            }
        }
        Scenario::Rest(o) => check_frames(o.frames)?,
    }
    // Rods under a drone's body, on a flat fingertip's gel: refused, not
    // written as frames nothing can be seen in.
    if common.config.skin.is_flat() {
        let strip_only = match scenario {
            Scenario::Perches(_) => Some("perches"),
            Scenario::Mapping(_) => Some("mapping"),
            Scenario::Presses(_) => Some("presses of rods"),
            _ => None,
        };
        if let Some(name) = strip_only {
            return Err(Error::param(
                "sensor",
                format!(
                    "{name} is a scenario of the curved strip (rods across it); on a flat \
                     sensor use single, pair, shear, rest, characterization or the presses of \
                     round tips"
                ),
            ));
        }
    }
    let sensor = SyntheticSensor::new(common.config, common.seed)?;
    match scenario {
        Scenario::Single(o) => single(&sensor, common, o, progress),
        Scenario::Pair(o) => pair(&sensor, common, o, progress),
        Scenario::Presses(o) => presses(&sensor, common, o, progress),
        Scenario::TipPresses(o) => tip_presses(&sensor, common, o, progress),
        Scenario::Shear(o) => shear(&sensor, common, o, progress),
        Scenario::Characterization(o) => characterization(&sensor, common, o, progress),
        Scenario::Perches(o) => perches(&sensor, common, o, progress),
        Scenario::Mapping(o) => mapping(&sensor, common, o, progress),
        Scenario::Rest(o) => rest(&sensor, common, o, progress),
    }
}

/// Ramp fraction for frame `k` of `n` (frame 0 unloaded, last frame full).
fn ramp(k: usize, n: usize) -> f64 {
    k as f64 / (n - 1) as f64
}

/// `rod` as the skin takes it: on the strip as it is, on a flat sensor a
/// sphere of its diameter at its x on the centre line (a rod across a
/// fingertip's gel is too light a load to see).
fn on_skin(skin: &crate::Skin, rod: Press) -> Press {
    if skin.is_flat() {
        Press::sphere(rod.x_mm, 0.0, rod.force_n, rod.diameter_mm)
    } else {
        rod
    }
}

fn single(
    sensor: &SyntheticSensor,
    c: &Common,
    o: &Single,
    progress: Progress<'_>,
) -> Result<Summary> {
    let tip = |p: Press| on_skin(&c.config.skin, p);
    // Reject a bad contact (at either end of a sweep) before writing anything.
    let f = tilted_force(1.0, o.yaw_deg, o.pitch_deg);
    for x in [Some(o.x_mm), o.sweep_to_mm].into_iter().flatten() {
        sensor.loads(&[tip(Press::rod(x, f, o.indenter_mm))])?;
    }
    let mut w = SequenceWriter::new(c, "single", o.frames, progress)?;
    for k in 0..o.frames {
        w.frame(sensor, o.press(k).map(tip).as_slice())?;
    }
    Ok(Summary {
        out: c.out.clone(),
        frames: w.n,
    })
}

impl Shear {
    /// The rod of frame `k` (`None` for the reference, frame 0).
    pub fn press(&self, k: usize) -> Option<Press> {
        shear_press(self, k)
    }
}

fn shear_press(o: &Shear, k: usize) -> Option<Press> {
    if k == 0 {
        return None;
    }
    let loaded = o.frames - 1;
    let press_frames = loaded.div_ceil(2);
    let normal = (k as f64 / press_frames as f64).min(1.0);
    let shear = if k > press_frames {
        (k - press_frames) as f64 / (loaded - press_frames) as f64
    } else {
        0.0
    };
    let f = [
        o.shear_n[0] * shear,
        o.shear_n[1] * shear,
        -o.force_n * normal,
    ];
    Some(match o.fingertip_y_mm {
        Some(y) => Press::fingertip(o.x_mm, y, f, o.indenter_mm),
        None => Press::rod(o.x_mm, f, o.indenter_mm),
    })
}

fn shear(
    sensor: &SyntheticSensor,
    c: &Common,
    o: &Shear,
    progress: Progress<'_>,
) -> Result<Summary> {
    let rods: Vec<Option<Press>> = (0..o.frames).map(|k| shear_press(o, k)).collect();
    for rod in rods.iter().flatten() {
        sensor.loads(std::slice::from_ref(rod))?;
    }
    let mut w = SequenceWriter::new(c, "shear", o.frames, progress)?;
    let origin = if c.config.full_frame {
        c.config.camera.strip_origin
    } else {
        (0, 0)
    };
    let mut csv = String::from("x_px,y_px\n");
    for (_, _, _, x, y) in sensor.marker_positions() {
        csv += &format!("{:.4},{:.4}\n", x + origin.0 as f64, y + origin.1 as f64);
    }
    let path = c.out.join("markers.csv");
    std::fs::write(&path, csv).map_err(|e| Error::io(&path, e))?;
    for rod in &rods {
        w.frame(sensor, rod.as_slice())?;
    }
    Ok(Summary {
        out: c.out.clone(),
        frames: w.n,
    })
}

/// What `presses.json` records of one loaded frame.
#[derive(Serialize)]
struct PressInfo {
    frame: String,
    indenter_mm: f64,
    yaw_deg: f64,
    pitch_deg: f64,
}

fn presses(
    sensor: &SyntheticSensor,
    c: &Common,
    o: &Presses,
    progress: Progress<'_>,
) -> Result<Summary> {
    // All draws first, from their own stream, so that the presses depend on
    // the seed alone; every rod is checked before anything is written.
    let seed = o.press_seed.unwrap_or(c.seed);
    let mut rng = SplitMix64::new(mix64(seed ^ 0x7072_6573_7365_7321));
    let mut plan = Vec::with_capacity(o.presses);
    for _ in 0..o.presses {
        let x = rng.uniform(-o.x_max_mm, o.x_max_mm);
        let f = rng.uniform(o.force_min_n, o.force_max_n);
        let tilt = rng.uniform(-o.max_tilt_deg, o.max_tilt_deg);
        let (yaw, pitch) = if rng.below(2) == 0 {
            (0.0, tilt)
        } else {
            (tilt, 0.0)
        };
        let d = o.indenters_mm[rng.below(o.indenters_mm.len() as u64) as usize];
        let contact = Press::rod(x, tilted_force(f, yaw, pitch), d);
        sensor.loads(std::slice::from_ref(&contact))?;
        plan.push((contact, d, yaw, pitch));
    }
    let mut w = SequenceWriter::new(c, "presses", 1 + o.presses, progress)?;
    w.frame(sensor, &[])?;
    let mut info = Vec::with_capacity(plan.len());
    for (contact, d, yaw, pitch) in plan {
        let frame = w.frame(sensor, std::slice::from_ref(&contact))?;
        info.push(PressInfo {
            frame,
            indenter_mm: d,
            yaw_deg: yaw,
            pitch_deg: pitch,
        });
    }
    write_json(&c.out.join("presses.json"), &info)?;
    Ok(Summary {
        out: c.out.clone(),
        frames: w.n,
    })
}

/// The options random presses share: a count, a force range and a largest tilt.
fn check_random_presses(presses: usize, (lo, hi): (f64, f64), max_tilt_deg: f64) -> Result<()> {
    if presses == 0 {
        return Err(Error::param("presses", "need at least 1"));
    }
    check_force("force_min_n", lo)?;
    check_force("force_max_n", hi)?;
    if lo > hi {
        return Err(Error::param(
            "force_min_n",
            format!("{lo} is above force_max_n {hi}"),
        ));
    }
    if !(max_tilt_deg.is_finite() && (0.0..=60.0).contains(&max_tilt_deg)) {
        return Err(Error::param("max_tilt_deg", "must be within 0..=60"));
    }
    Ok(())
}

fn check_tip_presses(o: &TipPresses) -> Result<()> {
    check_random_presses(o.presses, (o.force_min_n, o.force_max_n), o.max_tilt_deg)?;
    if !(o.max_shear_ratio.is_finite() && (0.0..=2.0).contains(&o.max_shear_ratio)) {
        return Err(Error::param("max_shear_ratio", "must be within 0..=2"));
    }
    if !(o.margin_mm.is_finite() && o.margin_mm >= 0.0) {
        return Err(Error::param("margin_mm", "must be finite and >= 0"));
    }
    for (name, (lo, hi)) in [
        ("sphere_mm", o.sphere_mm),
        ("punch_mm", o.punch_mm),
        ("fingertip_mm", o.fingertip_mm),
    ] {
        if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && lo <= hi && hi <= 100.0) {
            return Err(Error::param(
                name,
                format!("need 0 < smallest <= largest <= 100 mm, got ({lo}, {hi})"),
            ));
        }
    }
    Ok(())
}

/// What `presses.json` records of one loaded frame of [`TipPresses`] (and
/// of the `flat_press` fixture).
#[derive(Serialize)]
struct TipPressInfo {
    frame: String,
    /// `sphere`, `punch` or `fingertip`.
    indenter: &'static str,
    indenter_mm: f64,
    /// Diameter of the pressed area, mm.
    contact_mm: f64,
    yaw_deg: f64,
    pitch_deg: f64,
    /// Tangential over normal force.
    shear_ratio: f64,
}

/// The largest centre offsets `(|x|, |y|)` at which a pressed area of
/// radius `radius_mm` stays `margin_mm` inside the skin.
fn centre_range(skin: &crate::Skin, radius_mm: f64, margin_mm: f64) -> Result<(f64, f64)> {
    let inset = radius_mm + margin_mm;
    let x = skin.arc_to_chord(skin.half_length() - inset);
    let y = 0.5 * skin.width_mm() - inset;
    if !(inset < skin.half_length() && y >= 0.0) {
        return Err(Error::param(
            "margin_mm",
            format!(
                "a pressed area of {radius_mm:.2} mm radius, {margin_mm} mm from the edges, \
                 does not fit on the skin"
            ),
        ));
    }
    Ok((x, y))
}

fn tip_presses(
    sensor: &SyntheticSensor,
    c: &Common,
    o: &TipPresses,
    progress: Progress<'_>,
) -> Result<Summary> {
    // All draws first, from their own stream; every press is checked before
    // anything is written.
    let mat = c.config.material;
    let seed = o.press_seed.unwrap_or(c.seed);
    let mut rng = SplitMix64::new(mix64(seed ^ 0x7469_7070_7265_7373));
    let mut plan = Vec::with_capacity(o.presses);
    for _ in 0..o.presses {
        let tip = match rng.below(3) {
            0 => Tip::Sphere(rng.uniform(o.sphere_mm.0, o.sphere_mm.1)),
            1 => Tip::Punch(rng.uniform(o.punch_mm.0, o.punch_mm.1)),
            _ => Tip::Fingertip(rng.uniform(o.fingertip_mm.0, o.fingertip_mm.1)),
        };
        let f = rng.uniform(o.force_min_n, o.force_max_n);
        let (mut yaw, mut pitch) = (0.0, 0.0);
        let ratio;
        let force = if let Tip::Fingertip(_) = tip {
            ratio = rng.uniform(0.0, o.max_shear_ratio);
            let angle = rng.uniform(-std::f64::consts::PI, std::f64::consts::PI);
            let normal = f / (1.0 + ratio * ratio).sqrt();
            [
                ratio * normal * angle.cos(),
                ratio * normal * angle.sin(),
                -normal,
            ]
        } else {
            let tilt = rng.uniform(-o.max_tilt_deg, o.max_tilt_deg);
            if rng.below(2) == 0 {
                pitch = tilt;
            } else {
                yaw = tilt;
            }
            ratio = tilt.to_radians().tan().abs();
            tilted_force(f, yaw, pitch)
        };
        let radius = tip.contact_radius_mm(&mat, -force[2]);
        let (x_max, y_max) = centre_range(&c.config.skin, radius, o.margin_mm)?;
        let x = rng.uniform(-x_max, x_max);
        let y = rng.uniform(-y_max, y_max);
        let contact = tip.press(x, y, force);
        sensor.loads(std::slice::from_ref(&contact))?;
        plan.push((
            contact,
            TipPressInfo {
                frame: String::new(),
                indenter: tip.kind(),
                indenter_mm: tip.diameter_mm(),
                contact_mm: 2.0 * radius,
                yaw_deg: yaw,
                pitch_deg: pitch,
                shear_ratio: ratio,
            },
        ));
    }
    write_tip_presses(sensor, c, "presses", plan, progress)
}

/// Writes the reference and one frame per press, `truth.jsonl` and
/// `presses.json`.
fn write_tip_presses(
    sensor: &SyntheticSensor,
    c: &Common,
    stage: &'static str,
    plan: Vec<(Press, TipPressInfo)>,
    progress: Progress<'_>,
) -> Result<Summary> {
    let mut w = SequenceWriter::new(c, stage, 1 + plan.len(), progress)?;
    w.frame(sensor, &[])?;
    let mut info = Vec::with_capacity(plan.len());
    for (contact, mut i) in plan {
        i.frame = w.frame(sensor, std::slice::from_ref(&contact))?;
        info.push(i);
    }
    write_json(&c.out.join("presses.json"), &info)?;
    Ok(Summary {
        out: c.out.clone(),
        frames: w.n,
    })
}

fn pair(sensor: &SyntheticSensor, c: &Common, o: &Pair, progress: Progress<'_>) -> Result<Summary> {
    let skin = &c.config.skin;
    let s_mid = skin.chord_to_arc(o.x_mm)?;
    let xs = [
        skin.arc_to_chord(s_mid - 0.5 * o.spacing_mm),
        skin.arc_to_chord(s_mid + 0.5 * o.spacing_mm),
    ];
    let peaks = [o.force_n, o.force2_n];
    let flat = skin.is_flat();
    // Both rods must really be on the skin (arc_to_chord never fails), and
    // on a flat sensor both spheres wholly on its gel: said of the spacing
    // before any load is checked.
    let inset = if flat { 0.5 * o.indenter_mm } else { 0.0 };
    for s in [s_mid - 0.5 * o.spacing_mm, s_mid + 0.5 * o.spacing_mm] {
        if s.abs() + inset > skin.half_length() {
            let what = if flat {
                "a sphere's centre"
            } else {
                "a rod at arc length"
            };
            return Err(Error::param(
                "spacing_mm",
                format!(
                    "{what} {s:.1} mm is off the skin (|x| <= {:.1} mm)",
                    skin.half_length() - inset
                ),
            ));
        }
    }
    let at = |k: usize| -> Vec<Press> {
        if k == 0 {
            return vec![];
        }
        (0..2)
            .map(|i| {
                let f = [0.0, 0.0, -peaks[i] * ramp(k, o.frames)];
                on_skin(skin, Press::rod(xs[i], f, o.indenter_mm))
            })
            .collect()
    };
    sensor.loads(&at(o.frames - 1))?;
    let mut w = SequenceWriter::new(c, "pair", o.frames, progress)?;
    for k in 0..o.frames {
        w.frame(sensor, &at(k))?;
    }
    Ok(Summary {
        out: c.out.clone(),
        frames: w.n,
    })
}

/// Measuring points and their split (docs/pipeline.md): points 2-14; 5, 8, 11 are
/// validation; the test split repeats points 5, 8, 11.
const TRAIN_POINTS: [u32; 10] = [2, 3, 4, 6, 7, 9, 10, 12, 13, 14];
const HELD_OUT_POINTS: [u32; 3] = [5, 8, 11];
/// The characterization protocol's indenter diameters, mm.
pub const INDENTERS_MM: [f64; 3] = [2.0, 5.0, 10.0];
/// The characterization protocol's tilts `(yaw, pitch)`, degrees.
pub const TILTS_DEG: [(f64, f64); 5] = [
    (0.0, 0.0),
    (0.0, 15.0),
    (0.0, -15.0),
    (15.0, 0.0),
    (-15.0, 0.0),
];
const FORCES_N: [f64; 6] = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0];

/// The flat protocol's indenters: a 5 mm sphere, an 8 mm flat punch and an
/// 18 mm fingertip (their diameters differ, so `indenter_mm` names each).
pub const FLAT_TIPS: [Tip; 3] = [Tip::Sphere(5.0), Tip::Punch(8.0), Tip::Fingertip(18.0)];
/// The flat protocol's tilts `(yaw, pitch)`, degrees: shear along y (yaw)
/// and along x (pitch) of `tan 20 deg` = 0.36 times the normal force.
pub const FLAT_TILTS_DEG: [(f64, f64); 5] = [
    (0.0, 0.0),
    (0.0, 20.0),
    (0.0, -20.0),
    (20.0, 0.0),
    (-20.0, 0.0),
];
/// The flat protocol's grid of measuring points: columns along x, rows
/// along y. Points are numbered from 1 row by row, from the point at
/// the smallest x and y.
pub const FLAT_GRID: (u32, u32) = (5, 4);
/// The flat protocol's held-out points (validation, and the separately
/// recorded test split): a corner (1), the point nearest the centre (8), a
/// side (15) and another side (17) of the 5 x 4 grid.
pub const FLAT_HELD_OUT_POINTS: [u32; 4] = [1, 8, 15, 17];
/// The flat protocol's default repetitions.
pub const FLAT_REPEATS: u32 = 2;
/// Margin between the largest pressed area of the flat protocol and the
/// gel's edges, mm.
pub const FLAT_MARGIN_MM: f64 = 1.0;

/// The distance (mm) of the flat protocol's outer points from the gel's
/// edges on a gel of `mat`: the largest contact radius of [`FLAT_TIPS`] at
/// the top of the force ladder, plus [`FLAT_MARGIN_MM`].
pub fn flat_inset_mm(mat: &crate::Material) -> f64 {
    let top = FORCES_N[FORCES_N.len() - 1];
    FLAT_TIPS
        .iter()
        .map(|t| t.contact_radius_mm(mat, top))
        .fold(0.0, f64::max)
        + FLAT_MARGIN_MM
}

/// The sensor-frame position `(x_mm, y_mm)` of the flat protocol's point
/// `point` (1 to 20) on `skin` with a gel of `mat`: a 5 x 4 grid spread
/// evenly over the gel inset by [`flat_inset_mm`].
pub fn flat_point_mm(skin: &crate::Skin, mat: &crate::Material, point: u32) -> Result<(f64, f64)> {
    let (nx, ny) = FLAT_GRID;
    if !(1..=nx * ny).contains(&point) {
        return Err(Error::param(
            "point",
            format!(
                "the flat protocol's points are 1 to {}, got {point}",
                nx * ny
            ),
        ));
    }
    let inset = flat_inset_mm(mat);
    let (x_max, y_max) = centre_range(skin, inset, 0.0).map_err(|_| {
        Error::param(
            "material",
            format!(
                "the flat protocol's points lie {inset:.2} mm inside the gel's edges (its \
                 largest pressed area at 3 N plus {FLAT_MARGIN_MM} mm): no room on a \
                 {:.1} x {:.1} mm gel; a stiffer or thinner gel presses smaller areas",
                2.0 * skin.half_length(),
                skin.width_mm()
            ),
        )
    })?;
    let (col, row) = ((point - 1) % nx, (point - 1) / nx);
    let at = |k: u32, n: u32, max: f64| -max + 2.0 * max * k as f64 / (n - 1) as f64;
    Ok((at(col, nx, x_max), at(row, ny, y_max)))
}

/// One planned characterization test.
#[derive(Debug, Clone, Copy)]
struct Planned {
    /// The protocol's point; 0 for a spot check, pressed at `at`.
    point: u32,
    /// A spot check's place `(x_mm, y_mm)` (on the strip, `x` is the arc
    /// length and `y` is 0).
    at: Option<(f64, f64)>,
    indenter: f64,
    /// The flat protocol's round indenter; `None`: a rod of `indenter` mm.
    tip: Option<Tip>,
    tilt: (f64, f64),
    repeat: u32,
    force: f64,
    split: Split,
}

fn protocol(repeats: u32) -> Vec<Planned> {
    let mut v = Vec::new();
    let groups: [(&[u32], Split); 3] = [
        (&TRAIN_POINTS, Split::Train),
        (&HELD_OUT_POINTS, Split::Val),
        (&HELD_OUT_POINTS, Split::Test),
    ];
    for (points, split) in groups {
        for &point in points {
            for &indenter in &INDENTERS_MM {
                for &tilt in &TILTS_DEG {
                    for repeat in 1..=repeats {
                        for &force in &FORCES_N {
                            v.push(Planned {
                                point,
                                at: None,
                                indenter,
                                tip: None,
                                tilt,
                                repeat,
                                force,
                                split,
                            });
                        }
                    }
                }
            }
        }
    }
    v
}

/// The flat protocol: the grid's 16 training points, the 4 held-out points
/// as `val`, then again as `test`; each with every indenter, tilt,
/// repetition and force.
fn flat_protocol(repeats: u32) -> Vec<Planned> {
    let (nx, ny) = FLAT_GRID;
    let train: Vec<u32> = (1..=nx * ny)
        .filter(|p| !FLAT_HELD_OUT_POINTS.contains(p))
        .collect();
    let groups: [(&[u32], Split); 3] = [
        (&train, Split::Train),
        (&FLAT_HELD_OUT_POINTS, Split::Val),
        (&FLAT_HELD_OUT_POINTS, Split::Test),
    ];
    let mut v = Vec::new();
    for (points, split) in groups {
        for &point in points {
            for tip in FLAT_TIPS {
                for &tilt in &FLAT_TILTS_DEG {
                    for repeat in 1..=repeats {
                        for &force in &FORCES_N {
                            v.push(Planned {
                                point,
                                at: None,
                                indenter: tip.diameter_mm(),
                                tip: Some(tip),
                                tilt,
                                repeat,
                                force,
                                split,
                            });
                        }
                    }
                }
            }
        }
    }
    v
}

/// The largest tilt of the protocol's tests, degrees: 20 on a flat
/// sensor ([`FLAT_TILTS_DEG`]), 15 on the strip ([`TILTS_DEG`]).
fn largest_tilt_deg(flat: bool) -> f64 {
    let tilts: &[(f64, f64)] = if flat { &FLAT_TILTS_DEG } else { &TILTS_DEG };
    tilts
        .iter()
        .map(|&(y, p)| y.abs().max(p.abs()))
        .fold(0.0, f64::max)
}

/// `n` spot checks ([`Characterization::spot_checks`]): each one of the
/// protocol's indenters (a round tip of [`FLAT_TIPS`] on a flat sensor, a
/// rod of [`INDENTERS_MM`] on the strip), a force magnitude uniform over
/// the protocol's force ladder, tilted about one axis (yaw or pitch, even
/// odds) uniformly within the protocol's largest tilt, at a place uniform
/// over the protocol's points' extent: the rectangle of the flat grid
/// (`extent`: its largest `|x|` and `|y|`), or the arc between the strip's
/// outermost training points. Drawn from `seed`'s own stream.
fn spot_checks(n: usize, flat: bool, extent: (f64, f64), seed: u64) -> Vec<Planned> {
    let mut rng = SplitMix64::new(mix64(seed ^ 0x5B07_C4EC_0000_0001));
    let max_tilt = largest_tilt_deg(flat);
    let (lo, hi) = (FORCES_N[0], FORCES_N[FORCES_N.len() - 1]);
    let (first, last) = (TRAIN_POINTS[0], TRAIN_POINTS[TRAIN_POINTS.len() - 1]);
    let arc = ((first as f64 - 8.0) * 20.0, (last as f64 - 8.0) * 20.0);
    (0..n)
        .map(|_| {
            let (tip, indenter) = if flat {
                let tip = FLAT_TIPS[rng.below(FLAT_TIPS.len() as u64) as usize];
                (Some(tip), tip.diameter_mm())
            } else {
                (
                    None,
                    INDENTERS_MM[rng.below(INDENTERS_MM.len() as u64) as usize],
                )
            };
            let force = rng.uniform(lo, hi);
            let angle = rng.uniform(-max_tilt, max_tilt);
            let tilt = if rng.below(2) == 0 {
                (angle, 0.0)
            } else {
                (0.0, angle)
            };
            let at = if flat {
                (
                    rng.uniform(-extent.0, extent.0),
                    rng.uniform(-extent.1, extent.1),
                )
            } else {
                (rng.uniform(arc.0, arc.1), 0.0)
            };
            Planned {
                point: 0,
                at: Some(at),
                indenter,
                tip,
                tilt,
                repeat: 1,
                force,
                split: Split::Spot,
            }
        })
        .collect()
}

/// What `indenters.json` says of each indenter of a flat protocol.
#[derive(Serialize)]
struct IndenterInfo {
    indenter_mm: f64,
    kind: &'static str,
}

fn characterization(
    sensor: &SyntheticSensor,
    c: &Common,
    o: &Characterization,
    progress: Progress<'_>,
) -> Result<Summary> {
    let flat = c.config.skin.is_flat();
    let mut all = if flat {
        flat_protocol(o.repeats)
    } else {
        protocol(o.repeats)
    };
    let spots = match o.spot_checks {
        Some(n) => n,
        None if flat && o.subset.is_none() => FLAT_SPOT_CHECKS,
        None => 0,
    };
    if spots > MAX_SPOT_CHECKS {
        return Err(Error::param(
            "spot_checks",
            format!("at most {MAX_SPOT_CHECKS}, got {spots}"),
        ));
    }
    // The flat protocol's points, checked before anything is written.
    let (nx, ny) = FLAT_GRID;
    let points: Vec<(f64, f64)> = if flat {
        (1..=nx * ny)
            .map(|p| flat_point_mm(&c.config.skin, &c.config.material, p))
            .collect::<Result<_>>()?
    } else {
        Vec::new()
    };
    let mut ids: Vec<usize> = (0..all.len()).collect();
    if let Some(n) = o.subset {
        // Partial Fisher-Yates with its own stream, then back to protocol order.
        let mut rng = SplitMix64::new(mix64(c.seed ^ 0x5EB5_E7C0_FFEE_0001));
        let n = n.min(ids.len());
        for i in 0..n {
            let j = i + rng.below((ids.len() - i) as u64) as usize;
            ids.swap(i, j);
        }
        ids.truncate(n);
        ids.sort_unstable();
    }
    // The spot checks after the tests, over the protocol points' extent.
    let extent = points.iter().fold((0.0, 0.0), |(x, y): (f64, f64), p| {
        (x.max(p.0.abs()), y.max(p.1.abs()))
    });
    let first_spot = all.len();
    all.extend(spot_checks(spots, flat, extent, c.seed));
    ids.extend(first_spot..all.len());
    create_dir(&c.out)?;
    create_dir(&c.out.join("frames"))?;
    if c.flow {
        create_dir(&c.out.join("flow"))?;
    }
    write_crop(c)?;
    if flat {
        let path = c.out.join("geometry.json");
        let json = serde_json::to_string(&c.config.skin.geometry)
            .map_err(|e| Error::format(&path, None, e.to_string()))?;
        std::fs::write(&path, json + "\n").map_err(|e| Error::io(&path, e))?;
        let info: Vec<IndenterInfo> = FLAT_TIPS
            .iter()
            .map(|t| IndenterInfo {
                indenter_mm: t.diameter_mm(),
                kind: t.kind(),
            })
            .collect();
        write_json(&c.out.join("indenters.json"), &info)?;
    }
    let skin = &c.config.skin;
    // Tests are independent (each has its own frame indices and noise), so they
    // are made in parallel; PNG encoding would otherwise leave a core idle.
    // The rows come back in protocol order whatever the thread count.
    let done = AtomicUsize::new(0);
    let rows: Vec<TestRow> = ids
        .par_iter()
        .map(|&id| -> Result<TestRow> {
            let p = all[id];
            let f = tilted_force(p.force, p.tilt.0, p.tilt.1);
            let (x, y, contact) = match p.tip {
                Some(tip) => {
                    let (x, y) = p.at.unwrap_or_else(|| points[p.point as usize - 1]);
                    (x, y, tip.press(x, y, f))
                }
                None => {
                    let arc = p.at.map_or((p.point as f64 - 8.0) * 20.0, |a| a.0);
                    let x = skin.arc_to_chord(arc);
                    (x, 0.0, Press::rod(x, f, p.indenter))
                }
            };
            // Fresh noise and flicker for each image: frame indices from the test id.
            let reference = sensor.render_indexed(2 * id as u64, &[], false)?;
            let loaded = sensor.render_indexed(2 * id as u64 + 1, &[contact], c.flow)?;
            let frame = format!("frames/t{id:04}.png");
            let refname = format!("frames/t{id:04}_ref.png");
            io::write_gray_png(c.out.join(&refname), &reference.frame)?;
            io::write_gray_png(c.out.join(&frame), &loaded.frame)?;
            if let Some(flow) = &loaded.flow {
                io::write_flo(c.out.join(format!("flow/t{id:04}.flo")), flow)?;
            }
            // The load cell reads the true force plus a little noise.
            let mut cell = SplitMix64::new(mix64(c.seed ^ mix64(id as u64 ^ 0x10AD_CE11)));
            let noisy = f.map(|v| v + o.load_cell_noise_n * cell.normal());
            let k = done.fetch_add(1, Ordering::Relaxed) + 1;
            progress("characterization", k, ids.len());
            Ok(TestRow {
                test: id,
                frame,
                reference: refname,
                point: p.point,
                indenter_mm: p.indenter,
                yaw_deg: p.tilt.0,
                pitch_deg: p.tilt.1,
                repeat: p.repeat,
                force_n: p.force,
                split: p.split,
                x_mm: x,
                y_mm: y,
                fx_n: noisy[0],
                fy_n: noisy[1],
                fz_n: noisy[2],
            })
        })
        .collect::<Result<_>>()?;
    io::write_tests_csv(c.out.join("tests.csv"), &rows)?;
    let step = match o.sweep_step_mm {
        Some(s) => s,
        None if flat || o.subset.is_some() => 0.0,
        None => SWEEP_STEP_MM,
    };
    let swept = if flat || step == 0.0 {
        0
    } else {
        sweeps(sensor, c, o, step, all.len(), progress)?
    };
    Ok(Summary {
        out: c.out.clone(),
        frames: 2 * rows.len() + swept,
    })
}

/// Writes the strip protocol's sweeps ([`SWEEPS`], then [`TILTED_SWEEPS`]
/// if asked) and `sweeps.csv`; frame
/// indices start after the tests' (`first_id`), so that every image has
/// its own noise. Returns the number of images written.
fn sweeps(
    sensor: &SyntheticSensor,
    c: &Common,
    o: &Characterization,
    step_mm: f64,
    first_id: usize,
    progress: Progress<'_>,
) -> Result<usize> {
    if !(step_mm.is_finite() && step_mm > 0.0) {
        return Err(Error::param(
            "sweep_step_mm",
            format!("must be > 0 and finite, got {step_mm}"),
        ));
    }
    let skin = &c.config.skin;
    let (first, last) = (TRAIN_POINTS[0], TRAIN_POINTS[TRAIN_POINTS.len() - 1]);
    let (s0, s1) = ((first as f64 - 8.0) * 20.0, (last as f64 - 8.0) * 20.0);
    let n = ((s1 - s0) / step_mm).floor() as usize + 1;
    if n > MAX_SWEEP_FRAMES {
        return Err(Error::param(
            "sweep_step_mm",
            format!("{step_mm} mm makes {n} images per sweep, more than {MAX_SWEEP_FRAMES}"),
        ));
    }
    create_dir(&c.out.join("sweeps"))?;
    let straight = SWEEPS.iter().map(|&(d, f)| (d, f, 0.0));
    let tilted = TILTED_SWEEPS.iter().copied().filter(|_| o.tilted_sweeps);
    let plan: Vec<(f64, f64, f64)> = straight.chain(tilted).collect();
    let mut rows = Vec::with_capacity(n * plan.len());
    let mut id = 2 * first_id;
    let total = n * plan.len();
    let done = AtomicUsize::new(0);
    for (k, &(indenter, force, pitch)) in plan.iter().enumerate() {
        let refname = format!("sweeps/s{k}_ref.png");
        let reference = sensor.render_indexed(id as u64, &[], false)?;
        io::write_gray_png(c.out.join(&refname), &reference.frame)?;
        id += 1;
        let f = tilted_force(force, 0.0, pitch);
        let part: Vec<io::SweepRow> = (0..n)
            .into_par_iter()
            .map(|i| -> Result<io::SweepRow> {
                let x = skin.arc_to_chord(s0 + i as f64 * step_mm);
                let index = (id + i) as u64;
                let loaded = sensor.render_indexed(index, &[Press::rod(x, f, indenter)], false)?;
                let frame = format!("sweeps/s{k}_{i:05}.png");
                io::write_gray_png(c.out.join(&frame), &loaded.frame)?;
                let mut cell = SplitMix64::new(mix64(c.seed ^ mix64(index ^ 0x5EEE_70AD)));
                let noisy = f.map(|v| v + o.load_cell_noise_n * cell.normal());
                let done = done.fetch_add(1, Ordering::Relaxed) + 1;
                progress("sweeps", done, total);
                Ok(io::SweepRow {
                    sweep: k as u32,
                    frame,
                    reference: refname.clone(),
                    indenter_mm: indenter,
                    force_n: force,
                    x_mm: x,
                    y_mm: 0.0,
                    fx_n: noisy[0],
                    fy_n: noisy[1],
                    fz_n: noisy[2],
                })
            })
            .collect::<Result<_>>()?;
        id += n;
        rows.extend(part);
    }
    io::write_sweeps_csv(c.out.join("sweeps.csv"), &rows)?;
    Ok(rows.len() + plan.len())
}

#[derive(Serialize)]
struct PerchInfo {
    x_mm: f64,
    stiffness_n_per_mm: f64,
    diameter_mm: f64,
}

fn perches(
    sensor: &SyntheticSensor,
    c: &Common,
    o: &Perches,
    progress: Progress<'_>,
) -> Result<Summary> {
    let at = |k: usize| -> Vec<Press> {
        let pen = o.max_penetration_mm * ramp(k, o.frames);
        (0..2)
            .filter(|_| k > 0)
            .map(|i| {
                Press::rod(
                    o.x_mm[i],
                    [0.0, 0.0, -o.stiffness_n_per_mm[i] * pen],
                    o.indenter_mm,
                )
            })
            .collect()
    };
    sensor.loads(&at(o.frames - 1))?;
    let mut w = SequenceWriter::new(c, "perches", o.frames, progress)?;
    for k in 0..o.frames {
        w.frame(sensor, &at(k))?;
    }
    let info: Vec<PerchInfo> = (0..2)
        .map(|i| PerchInfo {
            x_mm: o.x_mm[i],
            stiffness_n_per_mm: o.stiffness_n_per_mm[i],
            diameter_mm: o.indenter_mm,
        })
        .collect();
    write_json(&c.out.join("perches.json"), &info)?;
    Ok(Summary {
        out: c.out.clone(),
        frames: w.n,
    })
}

fn rest(sensor: &SyntheticSensor, c: &Common, o: &Rest, progress: Progress<'_>) -> Result<Summary> {
    let mut w = SequenceWriter::new(c, "rest", o.frames, progress)?;
    let exposure = c.config.noise.exposure;
    let mut csv = String::from("frame,level,gain,offset\n");
    for k in 0..o.frames {
        let name = w.frame(sensor, &[])?;
        let (gain, offset) = exposure.response(c.seed, k as u64);
        let level = exposure.level(c.seed, k as u64);
        csv.push_str(&format!("{name},{level},{gain},{offset}\n"));
    }
    if exposure.is_active() {
        let path = c.out.join("camera.csv");
        std::fs::write(&path, csv).map_err(|e| Error::io(&path, e))?;
    }
    Ok(Summary {
        out: c.out.clone(),
        frames: w.n,
    })
}

fn write_json<T: Serialize>(path: &Path, v: &T) -> Result<()> {
    let s =
        serde_json::to_string_pretty(v).map_err(|e| Error::format(path, None, e.to_string()))?;
    std::fs::write(path, s + "\n").map_err(|e| Error::io(path, e))
}

#[derive(Serialize)]
struct RodInfo {
    x_m: f64,
    top_m: f64,
    diameter_mm: f64,
}

#[derive(Serialize)]
struct WorldInfo {
    /// Rods lie along the world y axis.
    rods: Vec<RodInfo>,
    /// Rotation of the sensor frame in the body frame (rows), and its offset, m.
    sensor_in_body_rotation: [[f64; 3]; 3],
    sensor_in_body_offset_m: [f64; 3],
    note: &'static str,
}

/// The sensor hangs under the body with its skin facing down: sensor x = body
/// x, sensor y = -body y, sensor z = -body z (180 deg about x).
const SENSOR_IN_BODY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]];

fn mapping(
    sensor: &SyntheticSensor,
    c: &Common,
    o: &Mapping,
    progress: Progress<'_>,
) -> Result<Summary> {
    let skin = &c.config.skin;
    let mut rng = SplitMix64::new(mix64(c.seed ^ 0x3A99_1F6E));
    // The reference, then per touch: approach, three press steps, leave.
    let total = 1 + 5 * o.rods_x_m.len() * o.touches;
    let mut w = SequenceWriter::new(c, "mapping", total, progress)?;
    let mut poses = Vec::new();
    let hover = 0.05; // m above the touching height while travelling
    let mut push = |w: &mut SequenceWriter, pose: [f64; 3], contacts: &[Press]| -> Result<()> {
        let name = w.frame(sensor, contacts)?;
        poses.push(PoseRow {
            frame: name,
            t_s: (w.n - 1) as f64 / w.fps,
            x_m: pose[0],
            y_m: pose[1],
            z_m: pose[2],
            qw: 1.0,
            qx: 0.0,
            qy: 0.0,
            qz: 0.0,
        });
        Ok(())
    };
    // Reference: hovering before the first rod.
    let first = o.rods_x_m[0];
    push(&mut w, [first - 0.2, 0.0, o.rods_top_m + 0.3], &[])?;
    let reach = 0.8 * skin.arc_to_chord(skin.half_length()); // mm of chord used
    for &rod in &o.rods_x_m {
        for _ in 0..o.touches {
            let x_mm = rng.uniform(-reach, reach);
            let px = rod - x_mm * 1e-3;
            // Skin touches the rod's top when the body is this high.
            let touch_z = o.rods_top_m + skin.z_at(x_mm) * 1e-3;
            push(&mut w, [px, 0.0, touch_z + hover], &[])?;
            for (k, frac) in [0.33, 0.67, 1.0].into_iter().enumerate() {
                let f = o.force_n * frac;
                // Deeper press, deeper body (1 mm per N of the skin's response).
                let z = touch_z - (k as f64 + 1.0) * 0.3e-3;
                push(
                    &mut w,
                    [px, 0.0, z],
                    &[Press::rod(x_mm, [0.0, 0.0, -f], o.indenter_mm)],
                )?;
            }
            push(&mut w, [px, 0.0, touch_z + hover], &[])?;
        }
    }
    io::write_poses_csv(c.out.join("poses.csv"), &poses)?;
    let info = WorldInfo {
        rods: o
            .rods_x_m
            .iter()
            .map(|&x| RodInfo {
                x_m: x,
                top_m: o.rods_top_m,
                diameter_mm: o.indenter_mm,
            })
            .collect(),
        sensor_in_body_rotation: SENSOR_IN_BODY,
        sensor_in_body_offset_m: [0.0, 0.0, 0.0],
        note: "rods lie along world y; a contact at sensor (x_mm, y_mm, z_mm) is at world \
               p + R_body * (S * [x, y, z] / 1000) with S = sensor_in_body_rotation",
    };
    write_json(&c.out.join("rods.json"), &info)?;
    Ok(Summary {
        out: c.out.clone(),
        frames: w.n,
    })
}

/// The presses of the `flat_press` fixture: `(indenter, x_mm, y_mm,
/// [Fx, Fy, Fz])` on [`SimConfig::fingertip`], one per loaded frame: the
/// three kinds of indenter at the centre, the corners and the sides, straight
/// down, tilted, and a fingertip sheared along x and along y.
pub const FLAT_PRESS_FIXTURE: [(Tip, f64, f64, [f64; 3]); 11] = [
    (Tip::Sphere(5.0), 0.0, 0.0, [0.0, 0.0, -1.5]),
    (Tip::Sphere(5.0), -7.0, -4.0, [0.0, 0.0, -2.0]),
    (Tip::Sphere(8.0), 7.0, 4.0, [0.3, 0.0, -1.0]),
    (Tip::Punch(8.0), -6.5, 4.0, [0.0, 0.0, -2.5]),
    (Tip::Punch(6.0), 6.0, -4.5, [0.0, -0.4, -1.5]),
    (Tip::Punch(10.0), 2.0, 1.0, [0.0, 0.0, -3.0]),
    (Tip::Fingertip(18.0), 0.0, 0.0, [0.0, 0.0, -2.0]),
    (Tip::Fingertip(18.0), -3.0, 2.0, [1.6, 0.0, -2.0]),
    (Tip::Fingertip(16.0), 4.0, -2.0, [0.0, -1.2, -1.5]),
    (Tip::Sphere(3.0), -2.5, -5.5, [0.0, 0.0, -0.8]),
    (Tip::Sphere(12.0), 8.0, -1.0, [-0.5, 0.5, -2.5]),
];

/// The repository's fixtures under `out`: `press/` (two 5 mm rods 40 mm apart
/// ramping to 2.0 and 1.5 N over 8 frames, no flow), `characterization/`
/// (a 6-test subset of the protocol, no flow) and `flat_press/` (the flat
/// fingertip sensor, [`SimConfig::fingertip`]: its reference and one frame
/// per press of [`FLAT_PRESS_FIXTURE`], with `truth.jsonl` and
/// `presses.json`, no flow). See `fixtures/README.md`.
pub fn fixtures(out: &Path, seed: u64) -> Result<()> {
    fixtures_with_progress(out, seed, &no_progress)
}

/// [`fixtures`], reporting progress as [`run_with_progress`] does (stages
/// `pair`, `characterization`, then `flat_press`).
pub fn fixtures_with_progress(out: &Path, seed: u64, progress: Progress<'_>) -> Result<()> {
    let mut press = Common::new(out.join("press"));
    press.seed = seed;
    press.flow = false;
    let pair = Pair {
        x_mm: 0.0,
        spacing_mm: 40.0,
        force_n: 2.0,
        force2_n: 1.5,
        frames: 8,
        indenter_mm: 5.0,
    };
    run_with_progress(&Scenario::Pair(pair), &press, progress)?;
    let mut ch = Common::new(out.join("characterization"));
    ch.seed = seed;
    ch.flow = false;
    let c = Characterization {
        subset: Some(6),
        ..Default::default()
    };
    run_with_progress(&Scenario::Characterization(c), &ch, progress)?;
    let mut flat = Common::new(out.join("flat_press"));
    flat.seed = seed;
    flat.flow = false;
    flat.config = SimConfig::fingertip();
    flat_press_fixture(&flat, progress)?;
    Ok(())
}

/// Writes the presses of [`FLAT_PRESS_FIXTURE`] as a sequence.
fn flat_press_fixture(c: &Common, progress: Progress<'_>) -> Result<Summary> {
    let sensor = SyntheticSensor::new(c.config, c.seed)?;
    let mat = c.config.material;
    let plan = FLAT_PRESS_FIXTURE
        .iter()
        .map(|&(tip, x, y, f)| {
            let contact = tip.press(x, y, f);
            sensor.loads(std::slice::from_ref(&contact))?;
            let shear = f[0].hypot(f[1]);
            Ok((
                contact,
                TipPressInfo {
                    frame: String::new(),
                    indenter: tip.kind(),
                    indenter_mm: tip.diameter_mm(),
                    contact_mm: 2.0 * tip.contact_radius_mm(&mat, -f[2]),
                    // The tilts that turn a vertical push into this force
                    // (exactly so when it leans about one axis).
                    yaw_deg: f[1].atan2(-f[2]).to_degrees(),
                    pitch_deg: f[0].atan2(-f[2]).to_degrees(),
                    shear_ratio: shear / -f[2],
                },
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    write_tip_presses(&sensor, c, "flat_press", plan, progress)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dataset_example_row_force() {
        let f = tilted_force(1.5, 0.0, 15.0);
        assert!((f[0] - 0.39).abs() < 0.005 && f[1].abs() < 1e-12 && (f[2] + 1.45).abs() < 0.005);
        let g = tilted_force(2.0, -15.0, 0.0);
        assert!(g[0].abs() < 1e-12 && g[1] < 0.0);
        assert!(((g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt() - 2.0).abs() < 1e-12);
    }

    #[test]
    fn protocol_counts() {
        let p = protocol(5);
        // (10 train + 3 val + 3 test points) x 3 indenters x 5 tilts x 5 repeats x 6 forces
        assert_eq!(p.len(), 16 * 3 * 5 * 5 * 6);
        assert_eq!(p.iter().filter(|t| t.split == Split::Train).count(), 4500);
        assert!(
            p.iter()
                .filter(|t| t.split != Split::Train)
                .all(|t| [5, 8, 11].contains(&t.point))
        );
    }
}
