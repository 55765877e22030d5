//! Calibration: the fitted maps from raw contact quantities to millimetres and newtons.
//!
//! A [`Calibration`] holds the five polynomials of the paper (docs/pipeline.md, steps 8-9):
//!
//! - `g1: x2d -> x3D` and `g2: y2d -> y3D` (mm), with `z3D = sqrt(R^2 - x3D^2) - d`
//!   from the [`SensorGeometry`]; on a flat sensor, which locates contacts in
//!   2-D, `g1, g2: (x2d, y2d) -> x3D, y3D` and `z3D = 0`;
//! - `gx, gy, gz: (dx, dy, dz, x2d, y2d, d_pf) -> Fx, Fy, Fz` (N),
//!
//! plus the geometry, the crop and the segmentation thresholds it was fitted
//! with, and the fit report (orders, validation and test MAE). It is saved and
//! loaded as versioned, human-readable JSON (`"version": 1`, see docs/formats.md);
//! loading a malformed or incompatible file gives [`Error::Calibration`] naming
//! the file, never a panic.
//!
//! This module is what a sensor needs at run time: the model, its file
//! format, and evaluating it on a contact. Making one is [`fit`]'s: from a
//! characterization dataset ([`fit::extract_dataset`], [`fit::fit_dataset`])
//! or from already-extracted [`Sample`]s ([`fit::fit`], the paper's order
//! search with a train / validation / test split), so that any front end (the
//! image pipeline, a simulator, recorded quantities) can feed it. [`report`]
//! scores a calibration: errors per split and measuring point, the minimum
//! detectable force, the paper's Table I and Table II.
//!
//! ```
//! use optical_tactile::calibration::poly::Polynomial;
//! use optical_tactile::calibration::{Calibration, SensorSetup};
//! use optical_tactile::frame::Roi;
//! use optical_tactile::geometry::SensorGeometry;
//! use optical_tactile::segment::{Shape, Thresholds};
//!
//! // A hand-made calibration: x = (x2d - 800) / 4 mm, y = 0, F = 0.01 * D.
//! let g1 = Polynomial::raw(&["x2d"], vec![vec![0], vec![1]], vec![-200.0, 0.25])?;
//! let g2 = Polynomial::raw(&["y2d"], vec![vec![0]], vec![0.0])?;
//! let vars = ["dx", "dy", "dz", "x2d", "y2d", "d_pf"];
//! let lin = |k: usize| {
//!     let mut e = vec![0u32; 6];
//!     e[k] = 1;
//!     Polynomial::raw(&vars, vec![e], vec![0.01])
//! };
//! let setup = SensorSetup {
//!     geometry: SensorGeometry::default(),
//!     crop: Roi::new(0, 440, 1600, 200),
//!     thresholds: Thresholds {
//!         magnitude: 1.5, sum: 400.0, erode: 5, dilate: 9, shape: Shape::Rect,
//!     },
//!     pipeline: None,
//! };
//! let cal = Calibration::new(setup, [g1, g2, lin(0)?, lin(1)?, lin(2)?], None)?;
//! assert_eq!(cal.location(800.0, 100.0)?, [0.0, 0.0, 160.0]);
//! assert_eq!(cal.force(10.0, 0.0, -200.0, 800.0, 100.0, 3.0)?, [0.1, 0.0, -2.0]);
//! let back = Calibration::from_json_str(&cal.to_json_string())?;
//! assert_eq!(back, cal);
//! # Ok::<(), optical_tactile::Error>(())
//! ```

pub mod correction;
pub mod fit;
mod format;
pub mod poly;
pub mod report;
pub mod uncertainty;

use serde::{Deserialize, Serialize};

use crate::contact::profile::{ForceMatcher, ProfileModel};
use crate::contact::{Contact, ContactLocator, ContactPointMethod, RawContact};
use crate::error::{Error, Result};
use crate::exposure::ExposureCompensation;
use crate::frame::Roi;
use crate::geometry::SensorGeometry;
use crate::io::{Split, TestRow};
use crate::segment::morphology::Shape;
use crate::segment::{ThresholdPreset, Thresholds};
use correction::ColumnCorrection;
use fit::FitOptions;
use format::thresholds_format;
use poly::{FitReport, Polynomial};
use report::PointTable;
use uncertainty::ForceUncertainty;

/// How far, as a fraction of its width on each side, a force input may leave
/// the [`ForceGuard`]'s training box before the fallback maps take over.
pub const GUARD_BOX_MARGIN: f64 = 0.05;

/// The calibration file format version this library reads and writes.
pub const FORMAT_VERSION: u32 = 1;

/// Variables of `g1` (files from before the shear input have `g1` of
/// [`G1_VARIABLES_LEGACY`], which is still read).
pub const G1_VARIABLES: [&str; 2] = ["x2d", "shear"];
/// Variables of a `g1` without the shear input (older files).
pub const G1_VARIABLES_LEGACY: [&str; 1] = ["x2d"];
/// Variables of `g2` on a sensor that locates along x only (the curved strip).
pub const G2_VARIABLES: [&str; 1] = ["y2d"];
/// Variables of both `g1` and `g2` on a sensor that locates contacts in 2-D
/// ([`SensorGeometry::locates_in_2d`]) without shear inputs: each surface
/// coordinate from the contact point's column and row, which a lens bends
/// into each other.
pub const LOCATION_2D_VARIABLES: [&str; 2] = ["x2d", "y2d"];
/// Variables of `g1` on a sensor that locates in 2-D: column, row and the
/// shear ratio along x ([`RawContact::shear_ratio`]).
pub const G1_2D_VARIABLES: [&str; 3] = ["x2d", "y2d", "shear"];
/// Variables of `g2` on a sensor that locates in 2-D: column, row and the
/// shear ratio across ([`RawContact::shear_ratio_y`]).
pub const G2_2D_VARIABLES: [&str; 3] = ["x2d", "y2d", "shear_y"];
/// Variables of the force maps `gx, gy, gz` in the sensor frame
/// ([`ForceFrame::Sensor`]), in evaluation order.
pub const FORCE_VARIABLES: [&str; 6] = ["dx", "dy", "dz", "x2d", "y2d", "d_pf"];
/// The force inputs ([`FORCE_VARIABLES`] order) that grow with the load:
/// the three displacements and `d_pf` ([`along_the_load`]).
pub const LOAD_INPUTS: [usize; 4] = [0, 1, 2, 5];

/// [`along_the_load`] looks at loads from this fraction of the contact's up
/// to the contact's own: a map is never read at less than half the load.
pub const LOAD_WALK_FROM: f64 = 0.5;
/// Steps of [`along_the_load`]'s walk from [`LOAD_WALK_FROM`] to the full load.
pub const LOAD_WALK_STEPS: usize = 16;
/// [`along_the_load`] stops where the force's rate of change along the
/// load, projected on its mean rate since the walk's start, is less than
/// this fraction of it: an elastic skin's force keeps growing with its
/// deformation, the maps' turns back past their data.
pub const LOAD_WALK_MIN_GROWTH: f64 = 0.5;
/// Variables of the force maps in the local surface frame
/// ([`ForceFrame::Local`]): the raw displacements along the arc, across
/// and along the outward normal (negative for a press), then the contact
/// point and `d_pf`.
pub const LOCAL_FORCE_VARIABLES: [&str; 6] =
    ["d_tangent", "d_across", "d_normal", "x2d", "y2d", "d_pf"];

/// The frame the force maps work in; the maps' variable names say which
/// ([`FORCE_VARIABLES`] or [`LOCAL_FORCE_VARIABLES`]), so a reader that
/// knows only one refuses a file of the other instead of misreading it.
///
/// - `Sensor` (the paper's): the raw displacements are rotated into the
///   sensor frame at the contact's location, and the maps give the sensor
///   frame's force.
/// - `Local`: the maps take the displacements in the local surface frame
///   (tangent, across, outward normal) and give the force in that frame,
///   which is rotated into the sensor frame at the contact's calibrated
///   location. The elastic response is local: a press tilted against the
///   skin's slope and one tilted with it differ in the sensor frame but
///   are alike in the local one, so the maps need less freedom for the same
///   fit.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ForceFrame {
    /// Sensor-frame inputs and outputs.
    #[default]
    Sensor,
    /// Local-frame inputs and outputs, rotated to the sensor frame after.
    Local,
}

impl ForceFrame {
    /// The force maps' variables in this frame.
    pub fn variables(self) -> &'static [&'static str; 6] {
        match self {
            ForceFrame::Sensor => &FORCE_VARIABLES,
            ForceFrame::Local => &LOCAL_FORCE_VARIABLES,
        }
    }

    /// The frame whose variables a force map has, if any.
    pub fn of(map: &Polynomial) -> Option<ForceFrame> {
        [ForceFrame::Sensor, ForceFrame::Local]
            .into_iter()
            .find(|f| {
                map.variables()
                    .iter()
                    .map(String::as_str)
                    .eq(f.variables().iter().copied())
            })
    }

    /// A vector of this frame (a force map's output or displacement inputs)
    /// in the sensor frame, for a contact at chord position `x_mm` of
    /// `geometry`: rotated from the local frame, as it is in the sensor one.
    pub fn to_sensor(self, geometry: &SensorGeometry, x_mm: f64, v: [f64; 3]) -> [f64; 3] {
        match self {
            ForceFrame::Sensor => v,
            ForceFrame::Local => geometry.local_to_sensor(x_mm, v),
        }
    }

    /// The inverse of [`ForceFrame::to_sensor`]: a sensor-frame vector (a
    /// true force) in this frame.
    pub fn from_sensor(self, geometry: &SensorGeometry, x_mm: f64, v: [f64; 3]) -> [f64; 3] {
        match self {
            ForceFrame::Sensor => v,
            ForceFrame::Local => geometry.sensor_to_local(x_mm, v),
        }
    }

    /// The displacement inputs of a patch in this frame: the sensor-frame
    /// rotation (`raw.d_sensor`), or the local ones (the profile-matched
    /// local force when there is one, else `(ds1, ds2, -dn)`).
    pub fn displacements(self, raw: &RawContact) -> [f64; 3] {
        match self {
            ForceFrame::Sensor => raw.d_sensor,
            ForceFrame::Local => raw.local_force.unwrap_or([raw.ds1, raw.ds2, -raw.dn]),
        }
    }
}

/// `maps` (`gx`, `gy`, `gz`) at the inputs `v`.
fn evaluate_maps(maps: [&Polynomial; 3], v: &[f64; 6]) -> Result<[f64; 3]> {
    Ok([
        maps[0].evaluate(v)?,
        maps[1].evaluate(v)?,
        maps[2].evaluate(v)?,
    ])
}

/// The force of `maps` (`gx`, `gy`, `gz`) at the inputs `v`, read along
/// the load: the load-like inputs ([`LOAD_INPUTS`]) are scaled by `s`
/// from [`LOAD_WALK_FROM`] of `scale` up to `scale` in
/// [`LOAD_WALK_STEPS`] steps, and the walk stops at the first step where
/// the force's rate of change along the load, projected on its mean rate
/// since the walk's start, falls under [`LOAD_WALK_MIN_GROWTH`] of that
/// mean rate (a step back or sideways). From the last load before it,
/// `s0`, the force is continued in a straight line to the whole load:
/// `F(s0) + (1 - s0) m`, with `m` the mean rate over the walk. When the
/// walk reaches `scale = 1`, the result is the maps at `v` itself.
///
/// Why: the force maps are polynomials fitted on the characterization, up
/// to its strongest press (3 N by the paper's protocol); past it their
/// highest-order terms take over, and an elastic skin's force grows about
/// in proportion to its deformation while theirs turns back. On the
/// simulated strip a 10 mm rod at x = -80 mm pressed beside a second rod
/// read 2.9 N at 3.7 N and 1.0 N at 4.5 N, its inputs inside the box of
/// all the training data (stronger inputs came from other places) but
/// beyond what was pressed there; a single rod at the same place read
/// 0.8 N at 4.5 N and +8.8 N (a pull) at 6 N. Read along the load from the
/// data's edge: 3.9, 4.5, 4.55 and 5.65 N.
pub fn along_the_load(maps: [&Polynomial; 3], v: &[f64; 6], scale: f64) -> Result<[f64; 3]> {
    let at = |s: f64| -> Result<[f64; 3]> {
        let mut p = *v;
        for &j in &LOAD_INPUTS {
            p[j] *= s;
        }
        evaluate_maps(maps, &p)
    };
    let step = |k: usize| {
        scale * (LOAD_WALK_FROM + (1.0 - LOAD_WALK_FROM) * k as f64 / LOAD_WALK_STEPS as f64)
    };
    let dot = |a: &[f64; 3], b: &[f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (s_start, f_start) = (step(0), at(step(0))?);
    let (mut s0, mut f0) = (s_start, f_start);
    let mut mean = [0.0; 3];
    for k in 1..=LOAD_WALK_STEPS {
        let s = step(k);
        let f = at(s)?;
        let rate: [f64; 3] = std::array::from_fn(|c| (f[c] - f0[c]) / (s - s0));
        // The first step sets the mean rate; later ones are judged by it.
        if k > 1 && dot(&rate, &mean) < LOAD_WALK_MIN_GROWTH * dot(&mean, &mean) {
            break;
        }
        (s0, f0) = (s, f);
        mean = std::array::from_fn(|c| (f0[c] - f_start[c]) / (s0 - s_start));
    }
    if s0 == 1.0 {
        return Ok(f0);
    }
    Ok(std::array::from_fn(|c| f0[c] + (1.0 - s0) * mean[c]))
}

/// The sensor-side settings a calibration belongs to: geometry, crop and
/// segmentation thresholds (not fitted, recorded with the maps).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SensorSetup {
    /// The skin's geometry.
    pub geometry: SensorGeometry,
    /// The crop of the camera frame the pixel coordinates refer to.
    pub crop: Roi,
    /// The segmentation thresholds (written as a preset label and the numbers).
    #[serde(with = "thresholds_format")]
    pub thresholds: Thresholds,
    /// The flow and patch settings the raw quantities were measured with
    /// (optional for files that predate it; a sensor should measure the same way).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pipeline: Option<PipelineSettings>,
}

/// How the raw quantities of a calibration were measured, beyond the thresholds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PipelineSettings {
    /// DIS preset name (`ultrafast`, `fast`, `medium`, `accurate`).
    pub flow_preset: String,
    /// Margin around each patch, full-resolution pixels.
    pub margin_px: usize,
    /// Whether the contact point was refined to sub-pixel precision.
    pub subpixel: bool,
    /// Half-width (full-resolution pixels) of the window of the shear-robust
    /// contact column ([`crate::contact::refine_contact_points`]); 0 when the
    /// column is the argmin of the divergence potential (older files).
    #[serde(default)]
    pub contact_window_px: u32,
    /// How the contact column was measured. Absent in older files, where
    /// `contact_window_px` decides (0: the potential's minimum, otherwise
    /// the energy centroid with that half-window).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contact_point: Option<ContactPointMethod>,
    /// The exposure compensation the frames went through (`off`, `offset`,
    /// `gain-offset`, `auto`). Absent in older files, which were fitted
    /// without compensation ([`PipelineSettings::exposure_compensation`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exposure: Option<ExposureCompensation>,
    /// Whether the dots of a regular marker grid were followed one by one
    /// ([`crate::sensor::ExtractorConfig::dot_tracking`]). Absent (false)
    /// in older files and when off.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub dot_tracking: bool,
    /// Whether, with the dots followed, each contact's displacements came
    /// from a round load's field fitted to its dots
    /// ([`crate::sensor::ExtractorConfig::dot_fit`]). Absent (false) in
    /// older files and when off: the patch's sums.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub dot_fit: bool,
    /// Half-side, full-resolution pixels, of the box of local light the
    /// frames were divided by before the flow
    /// ([`crate::sensor::ExtractorConfig::light_box_px`]). Absent when they
    /// were not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub light_box_px: Option<usize>,
    /// Whether the motion profiles weighed each flow cell by how well the
    /// frame matched the reference there
    /// ([`crate::sensor::ExtractorConfig::weighted_profiles`]). Absent
    /// (false) in older files and when off.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub weighted_profiles: bool,
}

impl SensorSetup {
    /// The crop and the pipeline settings within their bounds
    /// (docs/formats.md): the crop inside the largest frame
    /// ([`crate::frame::MAX_FRAME_SIDE`]), the margin, contact window and
    /// light box at most that (a light box at least 1 px), the contact
    /// point method's parameter within its bound.
    fn check(&self) -> std::result::Result<(), String> {
        let max = crate::frame::MAX_FRAME_SIDE;
        let c = &self.crop;
        let inside = |start: usize, len: usize| start.checked_add(len).is_some_and(|e| e <= max);
        if !(inside(c.x, c.w) && inside(c.y, c.h)) {
            return Err(format!(
                "crop {} reaches beyond the largest frame ({max} px a side)",
                c.to_arg()
            ));
        }
        if let Some(p) = &self.pipeline {
            if p.margin_px > max {
                return Err(format!("pipeline.margin_px {} is above {max}", p.margin_px));
            }
            if p.contact_window_px as usize > max {
                return Err(format!(
                    "pipeline.contact_window_px {} is above {max}",
                    p.contact_window_px
                ));
            }
            if let Some(r) = p.light_box_px
                && !(1..=max).contains(&r)
            {
                return Err(format!("pipeline.light_box_px {r} is not within 1..={max}"));
            }
            p.contact_point_method()
                .validate()
                .map_err(|e| format!("pipeline.contact_point: {e}"))?;
        }
        Ok(())
    }
}

impl PipelineSettings {
    /// The exposure compensation to run with: the recorded one, or `Off` for
    /// a file that predates the record (fitted without compensation).
    pub fn exposure_compensation(&self) -> ExposureCompensation {
        self.exposure.unwrap_or(ExposureCompensation::Off)
    }

    /// How the contact column is measured (see [`PipelineSettings::contact_point`]).
    pub fn contact_point_method(&self) -> ContactPointMethod {
        match (self.contact_point, self.contact_window_px) {
            (Some(m), _) => m,
            (None, 0) => ContactPointMethod::PotentialMinimum,
            (None, w) => ContactPointMethod::EnergyCentroid {
                half_window_px: f64::from(w),
            },
        }
    }
}

/// One characterization test, reduced to the raw quantities of its contact
/// and the truth (docs/pipeline.md, steps 7-9; the `tests.csv` of docs/formats.md).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Train, validation or test.
    pub split: Split,
    /// Measuring point (for per-point tables).
    pub point: u32,
    /// Contact point column, pixels (cropped image).
    pub x2d: f64,
    /// Contact point row, pixels (cropped image).
    pub y2d: f64,
    /// Raw displacement along sensor x (along the arc for a fit in the
    /// local frame, [`ForceFrame::Local`]).
    pub dx: f64,
    /// Raw displacement along sensor y (across, in the local frame).
    pub dy: f64,
    /// Raw displacement along sensor z (along the outward normal, in the
    /// local frame).
    pub dz: f64,
    /// Potential spread `max D - min D`.
    pub d_pf: f64,
    /// Local shear-to-normal ratio `ds1 / dn` ([`RawContact::shear_ratio`]),
    /// an input of `g1`.
    #[serde(default)]
    pub shear: f64,
    /// The shear ratio across, `ds2 / dn` ([`RawContact::shear_ratio_y`]),
    /// an input of a 2-D `g2`.
    #[serde(default)]
    pub shear_y: f64,
    /// True contact x, mm.
    pub x_mm: f64,
    /// True contact y, mm.
    pub y_mm: f64,
    /// True force x, N.
    pub fx: f64,
    /// True force y, N.
    pub fy: f64,
    /// True force z, N.
    pub fz: f64,
    /// Whether the test's motion went beyond what the markers can tell and
    /// no map may be fitted on it ([`crate::calibration::fit::Extraction::fits`]):
    /// a test row or spot check kept so that its error counts.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub untrusted: bool,
}

impl Sample {
    /// The sample of one characterization test: truth, split and point from
    /// its `tests.csv` row, raw quantities from the contact found in its frame.
    pub fn from_test(row: &TestRow, raw: &RawContact) -> Self {
        Self::from_test_in(row, raw, ForceFrame::Sensor)
    }

    /// [`Sample::from_test`] with the displacements of `frame`
    /// ([`ForceFrame::displacements`]); the truth stays in the sensor frame.
    pub fn from_test_in(row: &TestRow, raw: &RawContact, frame: ForceFrame) -> Self {
        let [dx, dy, dz] = frame.displacements(raw);
        Sample {
            split: row.split,
            point: row.point,
            x2d: raw.x_px,
            y2d: raw.y_px,
            dx,
            dy,
            dz,
            d_pf: raw.d_pf,
            shear: raw.shear_ratio(),
            shear_y: raw.shear_ratio_y(),
            x_mm: row.x_mm,
            y_mm: row.y_mm,
            fx: row.fx_n,
            fy: row.fy_n,
            fz: row.fz_n,
            untrusted: false,
        }
    }

    fn fields(&self) -> [(&'static str, f64); 13] {
        [
            ("x2d", self.x2d),
            ("y2d", self.y2d),
            ("dx", self.dx),
            ("dy", self.dy),
            ("dz", self.dz),
            ("d_pf", self.d_pf),
            ("shear", self.shear),
            ("shear_y", self.shear_y),
            ("x_mm", self.x_mm),
            ("y_mm", self.y_mm),
            ("fx", self.fx),
            ("fy", self.fy),
            ("fz", self.fz),
        ]
    }

    /// The force maps' inputs, in [`FORCE_VARIABLES`] order (what
    /// [`Calibration::force_checked`] takes).
    pub fn force_inputs(&self) -> [f64; 6] {
        [self.dx, self.dy, self.dz, self.x2d, self.y2d, self.d_pf]
    }
}

/// A calibrated contact: location (mm) and force (N) in the sensor frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Prediction {
    /// Contact x, mm.
    pub x_mm: f64,
    /// Contact y, mm.
    pub y_mm: f64,
    /// Contact z on the skin, mm.
    pub z_mm: f64,
    /// Force x, N.
    pub fx: f64,
    /// Force y, N.
    pub fy: f64,
    /// Force z, N.
    pub fz: f64,
}

/// The fit reports of the five maps and the test errors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationReport {
    /// The options the maps were fitted with.
    #[serde(default)]
    pub options: FitOptions,
    /// Order search of `g1`.
    pub g1: FitReport,
    /// Order search of `g2`.
    pub g2: FitReport,
    /// Order search of `gx`.
    pub gx: FitReport,
    /// Order search of `gy`.
    pub gy: FitReport,
    /// Order search of `gz`.
    pub gz: FitReport,
    /// Errors of the full calibration on the test split, if it had samples.
    pub test: Option<PointTable>,
    /// Errors of the full calibration on the spot checks (presses between
    /// the protocol's points), if it had any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spot: Option<PointTable>,
}

/// The fitted maps of a sensor, with the setup they belong to.
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    /// Geometry, crop and segmentation thresholds.
    pub setup: SensorSetup,
    g1: Polynomial,
    g2: Polynomial,
    gx: Polynomial,
    gy: Polynomial,
    gz: Polynomial,
    /// How the maps were fitted, if they were (absent for hand-made ones).
    pub report: Option<CalibrationReport>,
    /// Response kernels of the motion profile ([`crate::contact::profile`]); when
    /// present, the force maps take the profile-matched local forces as their
    /// raw displacements instead of the patch sums.
    pub profile: Option<ProfileModel>,
    /// The low-order fallback of the force maps and where they were trained
    /// ([`ForceGuard`]); `None` (hand-made maps, older files): the force maps
    /// are used everywhere.
    pub guard: Option<ForceGuard>,
    /// Smallest profile-matched normal force, N, of a patch reported as a
    /// contact ([`Calibration::is_press`]); `None`: every patch is.
    pub min_normal_n: Option<f64>,
    /// Location offsets and force gains per image column, learned from
    /// sweeps ([`correction`]); `None` (no sweeps, older files): none.
    pub column_correction: Option<ColumnCorrection>,
    /// The spread of the force error per contact ([`uncertainty`]),
    /// fitted on the spot checks or the validation split; `None` (hand-made maps, older
    /// files): contacts carry no force sigma.
    pub uncertainty: Option<ForceUncertainty>,
}

/// The tangential-to-inward-normal ratio `t / -n` of a profile-matched local
/// force (tangential, across, outward normal); `None` unless the normal
/// presses inward and the ratio is finite. See
/// [`RawContact::matched_shear_ratio`].
pub fn shear_ratio_of(local_force: [f64; 3]) -> Option<f64> {
    let [t, _, n] = local_force;
    let r = t / -n;
    (n < 0.0 && r.is_finite()).then_some(r)
}

/// The press test of [`Calibration::is_press`] for a threshold `min_normal_n`
/// and a profile-matched local force (tangential, across, outward normal):
/// passes unless both are given and the inward normal `-local_force[2]` is
/// below the threshold.
pub fn passes_press_test(min_normal_n: Option<f64>, local_force: Option<[f64; 3]>) -> bool {
    match (min_normal_n, local_force) {
        (Some(min), Some(f)) => -f[2] >= min,
        _ => true,
    }
}

/// A safety net for the force maps away from the training data.
///
/// The full force maps are high-order polynomials fitted on a protocol that
/// tilts the force to few levels, so between the levels (or outside the
/// trained inputs) they can swing far off: on the simulator a yaw-tilted
/// 2.9 N press between two training points read -68.7 N. The guard holds
/// maps of the same inputs with the shear displacements capped at a low order
/// ([`fit::GuardOptions::shear_order`]), fitted on the same data, plus the box of
/// training inputs and how far the two map sets disagreed on the training and
/// validation data. [`Calibration::force_checked`] uses the full maps where
/// they are trusted and the fallback maps, for all three components, when the
/// inputs leave the box or the two sets disagree by more than the tolerance on
/// any component: a force inside the box and the envelope then differs from
/// the fallback's by at most the tolerance, and a contact read by the
/// fallback is marked ([`Contact::fallback`]). Its envelope
/// ([`ForceGuard::envelope`]) bounds the load per place: beyond it the maps
/// are read along the load ([`along_the_load`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ForceGuard {
    /// Fallback `gx`, `gy`, `gz` (variables [`FORCE_VARIABLES`]).
    pub maps: [Polynomial; 3],
    /// Smallest training or validation value of each force input.
    pub input_min: [f64; 6],
    /// Largest training or validation value of each force input.
    pub input_max: [f64; 6],
    /// Largest disagreement, N, per component, under which the full maps are
    /// trusted.
    pub tolerance_n: [f64; 3],
    /// Order searches of the fallback maps, if they were fitted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report: Option<Vec<FitReport>>,
    /// The strongest load the training and validation data hold at each
    /// place of the characterization ([`ForceGuard::envelope_at`]); empty
    /// in files from before it (then only the box bounds the inputs).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub envelope: Vec<LoadSite>,
}

/// One place of the characterization and the strongest load pressed there.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoadSite {
    /// Mean contact column of the place's tests, pixels.
    pub x2d: f64,
    /// Mean contact row, pixels.
    pub y2d: f64,
    /// Largest magnitude of the displacement inputs `(d1, d2, d3)` of the
    /// place's tests ([`load_of`]): with a profile model they are the
    /// matched force, in newtons near enough.
    pub load_max: f64,
}

/// The load of force inputs `v` ([`FORCE_VARIABLES`] order) that the
/// guard's envelope bounds: the magnitude of the three displacement inputs.
pub fn load_of(v: &[f64; 6]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// Largest number of [`LoadSite`]s a guard may hold.
pub const MAX_LOAD_SITES: usize = 1 << 16;

impl ForceGuard {
    /// Whether `v` (force inputs, [`FORCE_VARIABLES`] order) lies in the
    /// training box widened by `margin` times its width on each side.
    /// Inputs that none of the fallback maps depends on (`y2d` when it is
    /// kept out of the maps) are not checked.
    pub fn contains(&self, v: &[f64; 6], margin: f64) -> bool {
        v.iter()
            .zip(self.input_min.iter().zip(&self.input_max))
            .enumerate()
            .all(|(j, (&x, (&lo, &hi)))| {
                let pad = margin * (hi - lo);
                (x >= lo - pad && x <= hi + pad) || self.maps.iter().all(|m| m.max_exponent(j) == 0)
            })
    }

    /// The strongest load ([`load_of`]) the characterization pressed near
    /// the contact point `(x2d, y2d)`: the sites' `load_max` weighted by the
    /// inverse square of their distance (a site's own value at the site);
    /// `None` without an envelope.
    pub fn envelope_at(&self, x2d: f64, y2d: f64) -> Option<f64> {
        let (mut num, mut den) = (0.0, 0.0);
        for site in &self.envelope {
            let d2 = (site.x2d - x2d).powi(2) + (site.y2d - y2d).powi(2);
            if d2 < 1e-12 {
                return Some(site.load_max);
            }
            num += site.load_max / d2;
            den += 1.0 / d2;
        }
        (den > 0.0).then(|| num / den)
    }

    /// How much the load of force inputs `v` ([`load_of`]) must shrink to
    /// come within the envelope widened by `margin` of itself: `envelope /
    /// load` when the load is beyond it, else (or without an envelope) 1.
    pub fn load_scale(&self, v: &[f64; 6], margin: f64) -> f64 {
        let load = load_of(v);
        match self.envelope_at(v[3], v[4]) {
            Some(e) if load > e * (1.0 + margin) && e > 0.0 => e * (1.0 + margin) / load,
            _ => 1.0,
        }
    }

    /// Whether force inputs `v` lie where the guard's data do: inside the
    /// box ([`ForceGuard::contains`]) and the load within the envelope
    /// ([`ForceGuard::load_scale`]), both widened by `margin`.
    pub fn knows(&self, v: &[f64; 6], margin: f64) -> bool {
        self.contains(v, margin) && self.load_scale(v, margin) >= 1.0
    }

    fn validate(&self) -> std::result::Result<(), String> {
        let frame = ForceFrame::of(&self.maps[0]).unwrap_or_default();
        for (name, p) in ["gx", "gy", "gz"].iter().zip(&self.maps) {
            check_vars(&format!("guard.{name}"), p, frame.variables())?;
        }
        let finite = |a: &[f64]| a.iter().all(|v| v.is_finite());
        if !finite(&self.input_min) || !finite(&self.input_max) {
            return Err("guard: the input box must be finite".into());
        }
        if self
            .input_min
            .iter()
            .zip(&self.input_max)
            .any(|(lo, hi)| lo > hi)
        {
            return Err("guard: an input's minimum exceeds its maximum".into());
        }
        if self
            .tolerance_n
            .iter()
            .any(|t| !(t.is_finite() && *t >= 0.0))
        {
            return Err("guard: tolerances must be finite and non-negative".into());
        }
        if self.envelope.len() > MAX_LOAD_SITES {
            return Err(format!(
                "guard: {} load sites, at most {MAX_LOAD_SITES}",
                self.envelope.len()
            ));
        }
        if self.envelope.iter().any(|e| {
            !(e.x2d.is_finite() && e.y2d.is_finite() && e.load_max.is_finite() && e.load_max > 0.0)
        }) {
            return Err("guard: a load site must be finite with a positive load_max".into());
        }
        Ok(())
    }
}

/// The error of a calibration built in memory (no file to name) that fails
/// its checks.
fn in_memory(message: String) -> Error {
    Error::Calibration {
        path: None,
        message,
    }
}

/// Checks a polynomial's variables against the expected list.
fn check_vars(name: &str, p: &Polynomial, expected: &[&str]) -> std::result::Result<(), String> {
    if p.variables()
        .iter()
        .map(|s| s.as_str())
        .ne(expected.iter().copied())
    {
        return Err(format!(
            "polynomial `{name}` has variables [{}], expected [{}]",
            p.variables().join(", "),
            expected.join(", ")
        ));
    }
    Ok(())
}

/// Checks a polynomial's variables against the lists its role allows.
fn check_one_of(
    name: &str,
    p: &Polynomial,
    allowed: &[&[&str]],
) -> std::result::Result<(), String> {
    if allowed.iter().any(|a| check_vars(name, p, a).is_ok()) {
        return Ok(());
    }
    let lists: Vec<String> = allowed
        .iter()
        .map(|a| format!("[{}]", a.join(", ")))
        .collect();
    Err(format!(
        "polynomial `{name}` has variables [{}], expected one of {}",
        p.variables().join(", "),
        lists.join(", ")
    ))
}

/// A location map at a contact: its variables (`x2d`, `y2d`, `shear`,
/// `shear_y`, as [`Calibration::check`] allows) take the contact's values.
fn evaluate_location(p: &Polynomial, x2d: f64, y2d: f64, shear: [f64; 2]) -> Result<f64> {
    let pick = |name: &str| match name {
        "x2d" => x2d,
        "y2d" => y2d,
        "shear_y" => shear[1],
        _ => shear[0],
    };
    match p.variables() {
        [a] => p.evaluate(&[pick(a)]),
        [a, b] => p.evaluate(&[pick(a), pick(b)]),
        [a, b, c] => p.evaluate(&[pick(a), pick(b), pick(c)]),
        other => Err(Error::param(
            "location map",
            format!("has {} variables, expected 1 to 3", other.len()),
        )),
    }
}

impl Calibration {
    /// A calibration from its parts. Errors ([`Error::Calibration`]) if a
    /// polynomial does not have the variables its role requires (see
    /// [`G1_VARIABLES`], [`G2_VARIABLES`], [`FORCE_VARIABLES`]) or the setup is
    /// invalid.
    pub fn new(
        setup: SensorSetup,
        maps: [Polynomial; 5],
        report: Option<CalibrationReport>,
    ) -> Result<Self> {
        let [g1, g2, gx, gy, gz] = maps;
        let c = Calibration {
            setup,
            g1,
            g2,
            gx,
            gy,
            gz,
            report,
            profile: None,
            guard: None,
            min_normal_n: None,
            column_correction: None,
            uncertainty: None,
        };
        c.check().map_err(in_memory)?;
        Ok(c)
    }

    fn check(&self) -> std::result::Result<(), String> {
        check_one_of(
            "g1",
            &self.g1,
            &[
                &G1_VARIABLES,
                &G1_VARIABLES_LEGACY,
                &LOCATION_2D_VARIABLES,
                &G1_2D_VARIABLES,
            ],
        )?;
        check_one_of(
            "g2",
            &self.g2,
            &[&G2_VARIABLES, &LOCATION_2D_VARIABLES, &G2_2D_VARIABLES],
        )?;
        // All force maps (and the guard's) in the frame of `gx`.
        let frame = self.force_frame();
        check_vars("gx", &self.gx, frame.variables())?;
        check_vars("gy", &self.gy, frame.variables())?;
        check_vars("gz", &self.gz, frame.variables())?;
        if let Some(g) = &self.guard {
            check_vars("guard.gx", &g.maps[0], frame.variables())?;
        }
        self.setup
            .geometry
            .validate()
            .map_err(|e| format!("geometry: {e}"))?;
        if let Some(p) = &self.profile {
            p.validate().map_err(|e| match e {
                // The file is named by the caller.
                Error::Calibration { message, .. } => message,
                e => e.to_string(),
            })?;
        }
        if let Some(g) = &self.guard {
            g.validate()?;
        }
        if let Some(c) = &self.column_correction {
            if self.setup.geometry.locates_in_2d() {
                return Err("column_correction: only for a sensor that locates along x".into());
            }
            c.validate().map_err(|e| e.to_string())?;
        }
        if let Some(u) = &self.uncertainty {
            u.validate()?;
        }
        if let Some(m) = self.min_normal_n
            && !(m.is_finite() && m >= 0.0)
        {
            return Err(format!(
                "min_normal_n must be finite and non-negative, got {m}"
            ));
        }
        self.setup.check()?;
        self.setup.thresholds.validate().map_err(|e| e.to_string())
    }

    /// `g1` (x2d -> x3D, mm).
    pub fn g1(&self) -> &Polynomial {
        &self.g1
    }
    /// `g2` (y2d -> y3D, mm).
    pub fn g2(&self) -> &Polynomial {
        &self.g2
    }
    /// `gx` (force inputs -> Fx, N).
    pub fn gx(&self) -> &Polynomial {
        &self.gx
    }
    /// `gy` (force inputs -> Fy, N).
    pub fn gy(&self) -> &Polynomial {
        &self.gy
    }
    /// `gz` (force inputs -> Fz, N).
    pub fn gz(&self) -> &Polynomial {
        &self.gz
    }

    /// Contact location `[x, y, z]` in mm from the contact point in pixels,
    /// for a contact without shear: `x = g1(x2d, 0)`, `y = g2(y2d)` (or
    /// `g1(x2d, y2d)` and `g2(x2d, y2d)` on a sensor that locates in 2-D),
    /// `z` the surface's height at `x` (`sqrt(R^2 - x^2) - d` on the strip,
    /// 0 on a flat sensor). See [`Calibration::location_sheared`].
    pub fn location(&self, x2d: f64, y2d: f64) -> Result<[f64; 3]> {
        self.location_sheared(x2d, y2d, 0.0)
    }

    /// Contact location `[x, y, z]` in mm from the contact point in pixels
    /// and the contact's shear-to-normal ratio ([`RawContact::shear_ratio`]):
    /// `x = g1(x2d, shear)` (a legacy `g1` ignores `shear`). On a sensor
    /// that locates in 2-D the ratio across is taken as 0; see
    /// [`Calibration::location_of`] for a patch's own ratios.
    pub fn location_sheared(&self, x2d: f64, y2d: f64, shear: f64) -> Result<[f64; 3]> {
        self.location_with_shear(x2d, y2d, [shear, 0.0])
    }

    /// Contact location `[x, y, z]` in mm from the contact point in pixels
    /// and both shear-to-normal ratios, `[ds1 / dn, ds2 / dn]`
    /// ([`RawContact::shear_ratio`], [`RawContact::shear_ratio_y`]): each map
    /// takes the ones among its variables.
    /// With a [`ColumnCorrection`], its offset at `x2d` is added to `x`.
    /// The correction's tilt layers, if any, are not used: see
    /// [`Calibration::location_of`].
    pub fn location_with_shear(&self, x2d: f64, y2d: f64, shear: [f64; 2]) -> Result<[f64; 3]> {
        self.location_tilted(x2d, y2d, shear, None)
    }

    /// [`Calibration::location_with_shear`], the column correction looked
    /// up at the matched shear ratio `tilt` ([`RawContact::matched_shear_ratio`];
    /// `None`: its straight correction).
    fn location_tilted(
        &self,
        x2d: f64,
        y2d: f64,
        shear: [f64; 2],
        tilt: Option<f64>,
    ) -> Result<[f64; 3]> {
        let mut x = evaluate_location(&self.g1, x2d, y2d, shear)?;
        if let Some(c) = &self.column_correction {
            x += c.location_mm_at(x2d, tilt.unwrap_or(f64::NAN));
        }
        let y = evaluate_location(&self.g2, x2d, y2d, shear)?;
        Ok(self.setup.geometry.point_at(x, y))
    }

    /// Contact location `[x, y, z]` in mm of a patch's raw quantities: its
    /// contact point and both of its shear ratios, and its matched shear
    /// ratio for a column correction with tilt layers.
    pub fn location_of(&self, raw: &RawContact) -> Result<[f64; 3]> {
        self.location_tilted(
            raw.x_px,
            raw.y_px,
            [raw.shear_ratio(), raw.shear_ratio_y()],
            raw.matched_shear_ratio,
        )
    }

    /// The frame the force maps work in (read from `gx`'s variables;
    /// [`ForceFrame::Sensor`] when they are neither set).
    pub fn force_frame(&self) -> ForceFrame {
        ForceFrame::of(&self.gx).unwrap_or_default()
    }

    /// The force maps' inputs of a patch ([`Calibration::force_frame`]'s
    /// displacements, the contact point, `d_pf`): what
    /// [`Calibration::force_checked`] takes.
    pub fn force_inputs(&self, raw: &RawContact) -> [f64; 6] {
        let [a, b, c] = self.force_frame().displacements(raw);
        [a, b, c, raw.x_px, raw.y_px, raw.d_pf]
    }

    /// The force maps' output in N, in their frame
    /// ([`Calibration::force_frame`]: the sensor frame, or the local frame
    /// for local maps), from their displacement inputs, the contact point in
    /// pixels and `d_pf`. [`Calibration::contact`] and
    /// [`Calibration::predict`] give the sensor frame's force in either case.
    /// With a [`ForceGuard`], the fallback maps answer where the full maps
    /// are not trusted (see [`Calibration::force_checked`]).
    pub fn force(
        &self,
        dx: f64,
        dy: f64,
        dz: f64,
        x2d: f64,
        y2d: f64,
        d_pf: f64,
    ) -> Result<[f64; 3]> {
        Ok(self.force_checked(&[dx, dy, dz, x2d, y2d, d_pf])?.0)
    }

    /// Force `[Fx, Fy, Fz]` in N from the force inputs `v` ([`FORCE_VARIABLES`]
    /// order), and whether the [`ForceGuard`]'s fallback maps gave it: they
    /// do when `v` leaves the training box (widened by
    /// [`GUARD_BOX_MARGIN`] of its width) or the full and fallback maps
    /// disagree by more than the guard's tolerance on any component.
    /// Without a guard, always the full maps.
    ///
    /// A load beyond the guard's envelope at the contact's place
    /// ([`ForceGuard::load_scale`]) is read along the load from the
    /// envelope ([`along_the_load`]): past the strongest press of the
    /// characterization the maps turn back.
    pub fn force_checked(&self, v: &[f64; 6]) -> Result<([f64; 3], bool)> {
        let full = [&self.gx, &self.gy, &self.gz];
        let full_at = evaluate_maps(full, v)?;
        let Some(g) = &self.guard else {
            return Ok((full_at, false));
        };
        let fallback = [&g.maps[0], &g.maps[1], &g.maps[2]];
        let fallback_at = evaluate_maps(fallback, v)?;
        let agree = full_at
            .iter()
            .zip(&fallback_at)
            .zip(&g.tolerance_n)
            .all(|((f, s), t)| (f - s).abs() <= *t);
        let trusted = agree && g.contains(v, GUARD_BOX_MARGIN);
        let (maps, at) = if trusted {
            (full, full_at)
        } else {
            (fallback, fallback_at)
        };
        let scale = g.load_scale(v, GUARD_BOX_MARGIN);
        let f = if scale < 1.0 {
            along_the_load(maps, v, scale)?
        } else {
            at
        };
        Ok((f, !trusted))
    }

    /// Half-width of the energy-centroid window this calibration was fitted
    /// with (full-resolution pixels; 0 for the other methods).
    pub fn contact_window_px(&self) -> u32 {
        match self.contact_point_method() {
            ContactPointMethod::EnergyCentroid { half_window_px } => half_window_px.round() as u32,
            _ => 0,
        }
    }

    /// How this calibration measures contact columns (files without pipeline
    /// settings: the potential's minimum).
    pub fn contact_point_method(&self) -> ContactPointMethod {
        self.setup
            .pipeline
            .as_ref()
            .map_or(ContactPointMethod::PotentialMinimum, |p| {
                p.contact_point_method()
            })
    }

    /// Measures the contact points the way this calibration was fitted
    /// ([`Calibration::contact_point_method`], with
    /// [`crate::contact::ContactLocator`]) on the frame's flow (`u` along x,
    /// `v` along y, on a grid of `scale` full-resolution pixels per cell), for a list of
    /// raw contacts of the caller's own. The sensor measures through
    /// [`ContactExtractor::locate`](crate::sensor::ContactExtractor::locate)
    /// with [`Calibration::contact_point_method`] instead, which also counts
    /// the frame's unseen patches as neighbours. Allocates; see
    /// [`Calibration::refine_contacts_with`] for a reusable locator.
    pub fn refine_contacts(
        &self,
        raws: &mut [RawContact],
        u: ndarray::ArrayView2<'_, f32>,
        v: ndarray::ArrayView2<'_, f32>,
        scale: f64,
    ) -> Result<()> {
        self.refine_contacts_with(&mut ContactLocator::new(), raws, u, v, scale)
    }

    /// [`Calibration::refine_contacts`] with the caller's locator, whose
    /// buffers are reused from frame to frame.
    pub fn refine_contacts_with(
        &self,
        locator: &mut ContactLocator,
        raws: &mut [RawContact],
        u: ndarray::ArrayView2<'_, f32>,
        v: ndarray::ArrayView2<'_, f32>,
        scale: f64,
    ) -> Result<()> {
        locator.refine(self.contact_point_method(), raws, u, v, scale)
    }

    /// With a profile model, sets each contact's
    /// [`RawContact::local_force`] from the frame's flow (`u`, `v` on a grid
    /// of `scale` full-resolution pixels per cell), all contacts at once;
    /// without one, does nothing. With an anchored model, a contact whose
    /// motion is clearly elsewhere than its measured point first has its
    /// `x_px` moved there ([`ForceMatcher::relocate_and_measure_contacts_at`]);
    /// with a model that measures shear-free columns, each contact's `x_px`
    /// is then measured again without its tangential motion
    /// ([`ForceMatcher::shear_free_columns`]). Each contact is matched at
    /// [`Calibration::match_column`]; with a [`ColumnCorrection`], its
    /// matched normal force is then multiplied by the correction's gain at
    /// that column ([`ColumnCorrection::correct_local_force`]). With tilt
    /// layers in the correction, each contact's
    /// [`RawContact::matched_shear_ratio`] is taken from that first match and
    /// the profile matched again at the column the tilt's correction gives
    /// (a press the first match passed is kept with it if the second would
    /// drop it). A sensor calls this once the contact columns are measured
    /// the calibration's way.
    pub fn match_forces_with(
        &self,
        matcher: &mut ForceMatcher,
        raws: &mut [RawContact],
        u: ndarray::ArrayView2<'_, f32>,
        v: ndarray::ArrayView2<'_, f32>,
        scale: f64,
    ) -> Result<()> {
        match &self.profile {
            Some(model) if !raws.is_empty() => {
                let column_of = |r: &RawContact| self.match_column(model, r);
                for r in raws.iter_mut() {
                    r.matched_shear_ratio = None;
                }
                if model.anchor.is_some() {
                    matcher
                        .relocate_and_measure_contacts_at(model, raws, u, v, scale, column_of)?;
                    if let Some(sigma_px) = self.shear_free_sigma_px(model) {
                        matcher.shear_free_columns(model, raws, scale, sigma_px, column_of)?;
                    }
                } else {
                    matcher.measure_contacts_at(model, raws, u, v, scale, column_of)?;
                }
                if let Some(c) = &self.column_correction {
                    if !c.layers.is_empty() {
                        // The first match tells how tilted each load is; matched
                        // again at the column the tilt's correction gives.
                        let first: Vec<Option<[f64; 3]>> =
                            raws.iter().map(|r| r.local_force).collect();
                        for r in raws.iter_mut() {
                            r.matched_shear_ratio = r.local_force.and_then(shear_ratio_of);
                        }
                        matcher.measure_contacts_at(model, raws, u, v, scale, column_of)?;
                        // A press the first match read as one stays one: where the
                        // tilt's column loses it, the straight correction holds.
                        for (r, f) in raws.iter_mut().zip(first) {
                            if passes_press_test(self.min_normal_n, f)
                                && !passes_press_test(self.min_normal_n, r.local_force)
                            {
                                r.local_force = f;
                                r.matched_shear_ratio = None;
                            }
                        }
                    }
                    for r in raws.iter_mut() {
                        if let Some(f) = r.local_force {
                            let column = self.match_column(model, r)?;
                            let tilt = r.matched_shear_ratio.unwrap_or(f64::NAN);
                            r.local_force = Some(c.correct_local_force(column, tilt, f));
                        }
                    }
                }
                Ok(())
            }
            _ => Ok(()),
        }
    }

    /// The slope peak's smoothing with which `model` measures shear-free
    /// columns ([`ProfileModel::shear_free_columns`]): `None` unless the
    /// model asks for them and this calibration measures its columns at
    /// the slope peak ([`ContactPointMethod::SlopePeak`]).
    pub fn shear_free_sigma_px(&self, model: &ProfileModel) -> Option<f64> {
        match self.contact_point_method() {
            ContactPointMethod::SlopePeak { sigma_px } if model.shear_free_columns => {
                Some(sigma_px)
            }
            _ => None,
        }
    }

    /// Whether a patch is reported as a contact: with [`Calibration::min_normal_n`]
    /// and a profile-matched local force ([`Calibration::match_forces_with`]),
    /// only if the matched inward normal force reaches it; otherwise always.
    ///
    /// Why: a strong press moves the skin far from it (the tangential load's
    /// far field, and the clamped ends of the strip), by a fraction of a pixel
    /// that the `low` magnitude threshold lets through. Those patches carry
    /// motion but no press: on the simulator their matched normal force is
    /// below 0.2 N, while 99% of the training presses at 0.5 N match at least
    /// 0.37 N (the fitted threshold is half of that).
    pub fn is_press(&self, raw: &RawContact) -> bool {
        passes_press_test(self.min_normal_n, raw.local_force)
    }

    /// The column at which `model` matches a contact's profile: the model's
    /// anchor column ([`crate::contact::profile::ColumnMap`]) of the contact's
    /// calibrated location, or the measured column `x_px` for a model
    /// without one.
    pub fn match_column(&self, model: &ProfileModel, raw: &RawContact) -> Result<f64> {
        match &model.anchor {
            Some(map) => {
                let [x, _, _] = self.location_of(raw)?;
                Ok(map.column(x))
            }
            None => Ok(raw.x_px),
        }
    }

    /// The calibrated contact of a patch's raw quantities (`id` and `missed`
    /// are 0: identity is the tracker's business).
    pub fn contact(&self, raw: &RawContact) -> Result<Contact> {
        let inputs = self.force_inputs(raw);
        let (force_n, fallback) = self.force_checked(&inputs)?;
        let location_mm = self.location_of(raw)?;
        let force_n = self
            .force_frame()
            .to_sensor(&self.setup.geometry, location_mm[0], force_n);
        let outside_training = self
            .guard
            .as_ref()
            .is_some_and(|g| !g.knows(&inputs, GUARD_BOX_MARGIN));
        let off_surface = !self.setup.geometry.contains(location_mm[0], location_mm[1]);
        Ok(Contact {
            id: 0,
            location_mm,
            force_n,
            force_sigma_n: self
                .uncertainty
                .as_ref()
                .map(|u| u.sigma_n(raw.d_pf, force_n)),
            raw: *raw,
            missed: 0,
            fallback,
            out_of_domain: outside_training || off_surface,
        })
    }

    /// Location and force (sensor frame) of a sample's raw quantities.
    pub fn predict(&self, s: &Sample) -> Result<Prediction> {
        let [x_mm, y_mm, z_mm] = self.location_with_shear(s.x2d, s.y2d, [s.shear, s.shear_y])?;
        let f = self.force(s.dx, s.dy, s.dz, s.x2d, s.y2d, s.d_pf)?;
        let [fx, fy, fz] = self.force_frame().to_sensor(&self.setup.geometry, x_mm, f);
        Ok(Prediction {
            x_mm,
            y_mm,
            z_mm,
            fx,
            fy,
            fz,
        })
    }
}
