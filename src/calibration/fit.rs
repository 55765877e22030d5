//! Calibrating a sensor from a characterization dataset (docs/calibration.md;
//! the `tests.csv` of docs/formats.md).
//!
//! 1. [`extract_dataset`] runs the image pipeline on every test: the test's
//!    own unloaded reference, then its loaded frame, through a
//!    [`ContactExtractor`]; the strongest patch is the test's contact (a test
//!    with no patch is a miss). Tests run in parallel, one extractor per thread.
//! 2. [`fit_dataset`] turns the detections into [`Sample`]s and fits the five
//!    maps with the paper's order search. The raw displacements are rotated
//!    into the sensor frame at the contact's *predicted* chord position (as the
//!    sensor does at run time), so `g1` is fitted first and the force maps after.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use ndarray::{Array1, Array2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::correction::{
    ColumnCorrection, CorrectionLayer, DEFAULT_SMOOTHING_PX, GAIN_RANGE, MAX_CORRECTION_LAYERS,
    SHEAR_RATIO_SMOOTHING, smooth_on_grid,
};
use super::poly::{self, CrossTerms, FitData, FitReport, PolySpec, Polynomial, VarGroup};
use super::report::{self, DetectionLimit, PointTable, ThresholdVerdict, evaluate};
use super::uncertainty::{ForceUncertainty, SpreadSample};
use super::{
    Calibration, CalibrationReport, ForceFrame, ForceGuard, G1_2D_VARIABLES, G2_2D_VARIABLES,
    LoadSite, PipelineSettings, Sample, SensorSetup, in_memory, shear_ratio_of,
};
use crate::contact::profile::{
    ColumnMap, ForceMatcher, MAX_PROFILE_REACH_PX, ProfileModel, ProfileSample, Relocation,
    SizeTerm, across_profiles_into, column_profile_into,
};
use crate::contact::{ContactPointMethod, RawContact, sensor_displacements};
use crate::error::{Error, Result};
use crate::frame::Roi;
use crate::geometry::SensorGeometry;
use crate::io::{self, Split, TestRow};
use crate::segment::ThresholdPreset;
use crate::sensor::{ContactExtractor, ExtractorConfig};

/// Options of [`fit`]: the largest order tried per map and variable group.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitOptions {
    /// Largest order of `g1` and `g2` (orders `1..=max` are tried).
    pub location_max_order: u32,
    /// Largest order of the shear ratio in `g1` (orders `0..=max` are tried
    /// on the strip, `1..=max` on a flat sensor; 0 leaves it out, the
    /// paper's `g1(x2d)`). Cross terms with `x2d` up to the order of `x2d`.
    #[serde(default)]
    pub location_shear_order: u32,
    /// Cross-term rule of `g1` between `x2d` and the shear ratio. The
    /// default, `Mixed(2)`, keeps `shear * x2d` but no higher cross terms:
    /// on the simulator's protocol `MaxOfGroups` (`shear * x2d^4`, ...)
    /// fitted the training points better and the unseen test points worse
    /// (0.63 against 0.25 mm). Older files, which lack it, used `MaxOfGroups`.
    #[serde(default = "max_of_groups")]
    pub location_cross: CrossTerms,
    /// Largest order of the displacement group `{dx, dy, dz}` in the force
    /// maps. Default 5: the profile-matched forces bend away from the true
    /// force as the indenter's footprint widens with the load, and on the
    /// simulator's full protocol the order search picked the largest order
    /// offered up to 5 (test Fz MAE 0.057 N with at most 3, 0.045 with 5).
    pub displacement_max_order: u32,
    /// Largest order of the shear displacements `{dx, dy}` in the force
    /// maps, when below [`FitOptions::displacement_max_order`]: the
    /// displacement group is then split into `shear {dx, dy}` of this order
    /// and `normal {dz}` of `displacement_max_order`. Why: the protocol tilts
    /// the force to three levels per axis only (-15, 0, +15 degrees), which
    /// pins a polynomial in the shear down to order 2; higher shear orders are
    /// free between the levels. Measured on the simulator (fitted on the
    /// 2500-test subset, scored on 150 random presses of `simulate presses`):
    /// without the cap, 11 presses read more than 1 N off in Fz (the worst
    /// 66 N, at yaw -15 deg between two training points); with order 2 none
    /// did (worst 0.73 N off) and the presses' Fz MAE fell from 0.75 to 0.14 N,
    /// but the protocol's own test MAE rose (Fz 0.053 -> 0.059 N, Fx 0.014 ->
    /// 0.019 N); so the default is `None`, one displacement group. On the
    /// strip, with the profile model's matched forces as inputs,
    /// [`FitOptions::for_geometry`] caps it at [`STRIP_SHEAR_ORDER`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shear_max_order: Option<u32>,
    /// Largest order of the location group `{x2d, y2d}` in the force maps.
    pub force_location_max_order: u32,
    /// Largest order of `{d_pf}` in the force maps (0 leaves it out). On a
    /// 2500-test subset of the simulator's protocol leaving it out lowered the
    /// test Fz MAE (0.053 -> 0.046 N), but on the full protocol it raised it
    /// (0.045 -> 0.059 N): the default keeps the paper's d_pf.
    pub d_pf_max_order: u32,
    /// Whether `y2d` enters the force maps (the paper's choice, the default).
    /// When every characterization indenter spans the skin's width, `y2d` only
    /// carries noise: turning this off keeps it out (its exponents stay 0, the
    /// maps keep their six variables), so a contact off the centre line later
    /// does not extrapolate the fitted noise.
    pub force_use_y2d: bool,
    /// Cross-term rule of the force maps.
    pub cross: CrossTerms,
    /// The profile model fitted for the forces ([`crate::contact::profile`]); `None`
    /// keeps the paper's patch sums as the force maps' raw displacements.
    #[serde(default)]
    pub profile: Option<ProfileFitOptions>,
    /// The fallback force maps fitted beside the full ones ([`ForceGuard`]);
    /// `None` fits none. Older files, which lack it, had none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub guard: Option<GuardOptions>,
    /// The frame of the force maps ([`ForceFrame`]; the sensor frame by
    /// default and in older reports).
    #[serde(default)]
    pub force_frame: ForceFrame,
    /// Least-squares options. Rank deficiency is allowed by default: a
    /// variable that does not vary in the dataset (y2d under an indenter that
    /// spans the width) then gets a minimum-norm (zero) coefficient, and the
    /// rank is in the report.
    pub least_squares: poly::LeastSquares,
}

impl FitOptions {
    /// The options `calibrate` fits a sensor of `geometry` with: the
    /// defaults, with `y2d` in the force maps only where contacts are
    /// located in 2-D (on the strip every characterization rod spans the
    /// width, so `y2d` only carries noise; on a flat sensor contacts land
    /// anywhere in `y`), and there without the profile model.
    ///
    /// On the strip, where the profile model's matched forces (with its
    /// size kernel) are already close to the true forces, the force maps
    /// are kept smooth between the protocol's tilts and forces:
    /// displacement order 4 and the shear capped at order 2
    /// ([`STRIP_DISPLACEMENT_ORDER`], [`STRIP_SHEAR_ORDER`]), and they work
    /// in the local surface frame ([`ForceFrame::Local`]; on a flat sensor
    /// the two frames are the same).
    pub fn for_geometry(geometry: &SensorGeometry) -> Self {
        let two_d = geometry.locates_in_2d();
        let defaults = FitOptions::default();
        FitOptions {
            displacement_max_order: if two_d {
                defaults.displacement_max_order
            } else {
                STRIP_DISPLACEMENT_ORDER
            },
            shear_max_order: if two_d {
                defaults.shear_max_order
            } else {
                Some(STRIP_SHEAR_ORDER)
            },
            force_use_y2d: two_d,
            force_frame: if two_d {
                ForceFrame::Sensor
            } else {
                ForceFrame::Local
            },
            // The profile model's kernels run along the strip's arc and sum
            // the flow over its height; a 2-D sensor's forces come from the
            // patch sums.
            profile: if two_d {
                None
            } else {
                FitOptions::default().profile
            },
            ..FitOptions::default()
        }
    }
}

/// The force maps' displacement order on the strip
/// ([`FitOptions::for_geometry`]). Measured on three simulated sensors
/// (their protocols and 150 random presses each, with the sweeps and the
/// size kernel): with order 5 and no shear cap the protocol's test Fz MAE
/// was 0.042 / 0.052 / 0.048 N and the random presses' 0.107 / 0.072 /
/// 0.074 N; with order 4 and the shear at order 2, 0.059 / 0.065 / 0.053 N
/// and 0.065 / 0.061 / 0.062 N (sensor-frame maps; in the local frame
/// 0.060 / 0.068 / 0.059 N and 0.063 / 0.059 / 0.053 N). The higher orders
/// fit the protocol's five
/// tilts and six force levels and swing between them, where a robot
/// presses.
pub const STRIP_DISPLACEMENT_ORDER: u32 = 4;

/// The force maps' shear order on the strip ([`FitOptions::for_geometry`]):
/// the protocol's three tilt levels per axis pin down order 2.
pub const STRIP_SHEAR_ORDER: u32 = 2;

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            location_max_order: 5,
            location_shear_order: 2,
            location_cross: CrossTerms::Mixed(2),
            displacement_max_order: 5,
            shear_max_order: None,
            force_location_max_order: 2,
            d_pf_max_order: 2,
            force_use_y2d: true,
            cross: CrossTerms::MaxOfGroups,
            profile: Some(ProfileFitOptions::default()),
            guard: Some(GuardOptions::default()),
            force_frame: ForceFrame::Sensor,
            least_squares: poly::LeastSquares {
                allow_rank_deficient: true,
                ..poly::LeastSquares::default()
            },
        }
    }
}

/// How the [`ForceGuard`] is fitted.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GuardOptions {
    /// Largest order of the shear displacements `{dx, dy}` in the fallback
    /// maps (the protocol's three tilt levels per axis pin down order 2).
    pub shear_order: u32,
    /// The tolerance per component is [`GuardOptions::tolerance_factor`]
    /// times this quantile (in (0, 1]; 1 is the largest) of the
    /// disagreements of the full and fallback maps on the training and
    /// validation data ...
    pub quantile: f64,
    /// ... times this factor ...
    pub tolerance_factor: f64,
    /// ... but at least this, N.
    pub tolerance_floor_n: f64,
}

impl GuardOptions {
    /// Errors ([`Error::InvalidParameter`] named `guard`) unless the factor
    /// and floor are finite and non-negative and the quantile is in (0, 1].
    pub fn validate(&self) -> Result<()> {
        let non_negative = |v: f64| v.is_finite() && v >= 0.0;
        if non_negative(self.tolerance_factor)
            && non_negative(self.tolerance_floor_n)
            && self.quantile > 0.0
            && self.quantile <= 1.0
        {
            Ok(())
        } else {
            Err(Error::param(
                "guard",
                "the tolerance factor and floor must be finite and non-negative, the quantile in (0, 1]",
            ))
        }
    }
}

impl Default for GuardOptions {
    /// Shear order 2, tolerance 1.5 times the 99th percentile, at least
    /// 0.05 N. Measured on the simulator (full protocol; 150 random presses
    /// of `simulate presses`): the presses' Fz MAE fell from 0.72 N without a
    /// guard to 0.17 N with 1.5 times the largest disagreement (tolerance Fz
    /// 1.06 N) and to 0.14 N with this rule, while the protocol's test Fz
    /// MAE rose from 0.0446 to 0.0451 N (1% of its test rows fall back).
    fn default() -> Self {
        GuardOptions {
            shear_order: 2,
            quantile: 0.99,
            tolerance_factor: 1.5,
            tolerance_floor_n: 0.05,
        }
    }
}

fn max_of_groups() -> CrossTerms {
    CrossTerms::MaxOfGroups
}

/// How the profile model of the forces is fitted ([`crate::contact::profile::ProfileModel::fit`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProfileFitOptions {
    /// How far each side of a contact the kernels reach, full-resolution pixels.
    pub half_width_px: f64,
    /// Degree of the kernels' polynomial in the contact's column.
    pub degree: usize,
    /// Largest degree of the kernels' anchor map
    /// ([`crate::contact::profile::ColumnMap`]): of the degrees `1..=max`
    /// whose map predicts a left-out training point's column about as well
    /// as the best degree's (leave one point out), the fit keeps the one
    /// whose matched forces have the lowest validation MAE; the measured
    /// columns instead only when they read the tests of every validation
    /// point clearly closer (a paired test per point), or when no anchor
    /// map can be fitted. 0: measured columns only (files from before the
    /// anchor map).
    #[serde(default)]
    pub anchor_max_degree: usize,
    /// Fit the indenter-size term
    /// ([`crate::contact::profile::SizeTerm`]) when the training tests
    /// were pressed by indenters of more than one size. Off in files from
    /// before the term.
    #[serde(default)]
    pub size_term: bool,
    /// How far each side of a contact the kernels' far tails reach
    /// ([`crate::contact::profile::ProfileTail`]), full-resolution pixels,
    /// at most the profile's length; 0 fits no tail (files from before
    /// the tails).
    #[serde(default)]
    pub tail_px: f64,
    /// Spacing of the tail samples, full-resolution pixels.
    #[serde(default = "default_tail_step_px")]
    pub tail_step_px: f64,
    /// When a contact's match column is moved to where its motion fits
    /// best ([`Relocation`]); `None` (the default): [`Relocation::Clear`]
    /// with sweeps, whose corrections are learned at the measured columns,
    /// and [`Relocation::Best`] without them.
    #[serde(default)]
    pub relocation: Option<Relocation>,
    /// Measure every column again without the contacts' tangential motion
    /// ([`ProfileModel::shear_free_columns`]) when the columns are measured
    /// at the slope peak ([`ContactPointMethod::SlopePeak`]); otherwise it
    /// does nothing. Off by default: on the simulated strip it puts a wide
    /// rod pressed at a tilt back on its load line but reads a few presses
    /// near the strip's ends worse, and on a second simulated sensor most
    /// figures worse (docs/results.md, "Shear-free columns").
    #[serde(default)]
    pub shear_free_columns: bool,
    /// Fit the spread channel ([`ProfileModel::spread`]): the response of
    /// the across motion's first moment about the strip's centre line. On
    /// by default; off in files from before it.
    #[serde(default)]
    pub spread_channel: bool,
}

fn default_tail_step_px() -> f64 {
    8.0
}

impl Default for ProfileFitOptions {
    /// 300 px (about 60 mm of arc on the default strip, where most of a
    /// press's motion has died out) and degree 2 (measured on the simulator's
    /// protocol: degree 2 predicted the unseen test points best, 4 and 6
    /// overfitted), anchor maps up to degree 5 (the camera's projection of
    /// the arc is close to a cubic); tails over the whole image (an eighth
    /// to a fifth of the peak motion is still there 500 px away), every 8 px (they are
    /// smooth).
    fn default() -> Self {
        ProfileFitOptions {
            half_width_px: 300.0,
            degree: 2,
            anchor_max_degree: 5,
            size_term: true,
            tail_px: MAX_PROFILE_REACH_PX,
            tail_step_px: default_tail_step_px(),
            relocation: None,
            shear_free_columns: false,
            spread_channel: true,
        }
    }
}

/// What a fit is told about its profile model, over the sensor's defaults
/// ([`ProfileFitOptions::with_choices`]): the `calibrate` command's flags
/// of the same names (docs/calibration.md). The default changes nothing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ProfileChoices {
    /// Match every contact at its measured column, never at an anchor map
    /// ([`ProfileFitOptions::anchor_max_degree`] 0).
    pub measured_columns: bool,
    /// The relocation ([`ProfileFitOptions::relocation`]); `None`: the
    /// defaults'.
    pub relocation: Option<Relocation>,
    /// Measure the columns again without the tangential motion
    /// ([`ProfileFitOptions::shear_free_columns`]).
    pub shear_free_columns: bool,
    /// Keep the spread channel where the defaults fit it
    /// ([`ProfileFitOptions::spread_channel`]).
    pub spread_channel: bool,
    /// Keep the indenter-size kernels where the defaults fit them
    /// ([`ProfileFitOptions::size_term`]).
    pub size_term: bool,
    /// Keep the kernels' far tails ([`ProfileFitOptions::tail_px`]; off:
    /// none).
    pub profile_tail: bool,
}

impl Default for ProfileChoices {
    fn default() -> Self {
        ProfileChoices {
            measured_columns: false,
            relocation: None,
            shear_free_columns: false,
            spread_channel: true,
            size_term: true,
            profile_tail: true,
        }
    }
}

impl ProfileFitOptions {
    /// These options with `choices` over them: a choice can turn off what
    /// these fit (the spread channel, the size kernels, the tails, the
    /// anchor maps) and turn on the shear-free columns, and a relocation
    /// asked for replaces theirs.
    pub fn with_choices(self, choices: &ProfileChoices) -> Self {
        ProfileFitOptions {
            size_term: self.size_term && choices.size_term,
            tail_px: if choices.profile_tail {
                self.tail_px
            } else {
                0.0
            },
            anchor_max_degree: if choices.measured_columns {
                0
            } else {
                self.anchor_max_degree
            },
            relocation: choices.relocation.or(self.relocation),
            shear_free_columns: self.shear_free_columns || choices.shear_free_columns,
            spread_channel: self.spread_channel && choices.spread_channel,
            ..self
        }
    }
}

/// The spec of the force maps for these options.
///
/// Groups, in variable order: `displacement {dx, dy, dz}` (or `shear {dx,
/// dy}` and `normal {dz}`, see [`FitOptions::shear_max_order`]), `location
/// {x2d, y2d}`, `d_pf {d_pf}`; without [`FitOptions::force_use_y2d`] the location
/// group is `{x2d}` and `y2d` sits alone in a group of order 0 (unused).
pub fn force_spec(options: &FitOptions) -> Result<PolySpec> {
    let v = options.force_frame.variables();
    let mut groups = match options.shear_max_order {
        Some(k) if k < options.displacement_max_order => vec![
            VarGroup::new("shear", &v[..2], k),
            VarGroup::new("normal", &v[2..3], options.displacement_max_order),
        ],
        _ => vec![VarGroup::new(
            "displacement",
            &v[..3],
            options.displacement_max_order,
        )],
    };
    if options.force_use_y2d {
        groups.push(VarGroup::new(
            "location",
            &v[3..5],
            options.force_location_max_order,
        ));
    } else {
        groups.push(VarGroup::new(
            "location",
            &v[3..4],
            options.force_location_max_order,
        ));
        groups.push(VarGroup::new("unused", &v[4..5], 0));
    }
    groups.push(VarGroup::new("d_pf", &v[5..], options.d_pf_max_order));
    PolySpec::new(groups, options.cross)
}

/// Fits the five maps from samples with the paper's order search: each
/// polynomial's orders are chosen among `1..=max` by validation MAE; test
/// errors are reported.
///
/// Errors: no samples, a non-finite field ([`Error::NonFinite`] with the
/// sample index as `row`), no training or validation sample, or no candidate
/// order that can be fitted (e.g. fewer training samples than terms).
pub fn fit(samples: &[Sample], setup: &SensorSetup, options: &FitOptions) -> Result<Calibration> {
    if samples.is_empty() {
        return Err(Error::param("samples", "no samples to fit"));
    }
    setup
        .geometry
        .validate()
        .map_err(|e| Error::param("geometry", e.to_string()))?;
    setup.thresholds.validate()?;
    if let Some(g) = &options.guard {
        g.validate()?;
    }
    for (row, s) in samples.iter().enumerate() {
        if let Some(col) = s.fields().iter().position(|(_, v)| !v.is_finite()) {
            return Err(Error::NonFinite {
                what: format!("sample field `{}`", s.fields()[col].0),
                row,
                col,
            });
        }
    }
    let pick =
        |split: Split| -> Vec<&Sample> { samples.iter().filter(|s| s.split == split).collect() };
    let (train, val, test) = (pick(Split::Train), pick(Split::Val), pick(Split::Test));
    let spot = pick(Split::Spot);
    if train.is_empty() || val.is_empty() {
        return Err(Error::param(
            "samples",
            format!(
                "fitting needs training and validation samples, got {} train, {} val, {} test",
                train.len(),
                val.len(),
                test.len()
            ),
        ));
    }
    // Column arrays per split: g1 input, g2 input, force inputs, and targets.
    // On a sensor that locates in 2-D, both location maps take (x2d, y2d).
    let two_d = setup.geometry.locates_in_2d();
    struct Cols {
        g1_in: Array2<f64>,
        g2_in: Array2<f64>,
        force: Array2<f64>,
        x_mm: Array1<f64>,
        y_mm: Array1<f64>,
        f: [Array1<f64>; 3],
    }
    let cols = |set: &[&Sample]| {
        let n = set.len();
        let with = |k: usize, shear: fn(&Sample) -> f64| {
            Array2::from_shape_fn((n, k), |(i, j)| {
                let s = set[i];
                [s.x2d, s.y2d, shear(s)][j + 3 - k]
            })
        };
        Cols {
            g1_in: if two_d {
                with(3, |s| s.shear)
            } else {
                Array2::from_shape_fn((n, 2), |(i, j)| [set[i].x2d, set[i].shear][j])
            },
            g2_in: if two_d {
                with(3, |s| s.shear_y)
            } else {
                Array2::from_shape_fn((n, 1), |(i, _)| set[i].y2d)
            },
            force: Array2::from_shape_fn((n, 6), |(i, j)| set[i].force_inputs()[j]),
            x_mm: set.iter().map(|s| s.x_mm).collect(),
            y_mm: set.iter().map(|s| s.y_mm).collect(),
            f: {
                // The maps' targets: the true force in their frame, rotated
                // at the true location for local maps.
                let target: Vec<[f64; 3]> = set
                    .iter()
                    .map(|s| {
                        let f = [s.fx, s.fy, s.fz];
                        options.force_frame.from_sensor(&setup.geometry, s.x_mm, f)
                    })
                    .collect();
                std::array::from_fn(|k| target.iter().map(|t| t[k]).collect())
            },
        }
    };
    let (tr, va, te) = (cols(&train), cols(&val), cols(&test));
    let has_test = !test.is_empty();
    let ls = &options.least_squares;
    let named = |what: &'static str| move |e: Error| prefix_error(what, e);

    let (g1_spec, g2_spec) = if two_d {
        // One location group: every monomial of x2d and y2d up to the
        // order, as a lens's distortion mixes the two; and the shear ratio
        // along the map's own axis, which pulls the slope peak sideways, as
        // on the strip.
        let spec = |vars: &[&str; 3]| {
            PolySpec::new(
                vec![
                    VarGroup::new("location", &vars[..2], options.location_max_order),
                    VarGroup::new("shear", &vars[2..], options.location_shear_order),
                ],
                options.location_cross,
            )
        };
        (spec(&G1_2D_VARIABLES)?, spec(&G2_2D_VARIABLES)?)
    } else {
        // g1 always has the shear input (order 0 = unused, then the paper's
        // map); the search may leave it out where the validation points read
        // closer without it.
        let g1 = PolySpec::new(
            vec![
                VarGroup::new("x2d", &["x2d"], options.location_max_order),
                VarGroup::new("shear", &["shear"], options.location_shear_order).or_none(),
            ],
            options.location_cross,
        )?;
        let g2 = PolySpec::new(
            vec![VarGroup::new("y2d", &["y2d"], options.location_max_order)],
            CrossTerms::MaxOfGroups,
        )?;
        (g1, g2)
    };
    // On a sensor that locates in 2-D, the validation points share the
    // training points' rows and columns, so they cannot see a map swing
    // between them (an order that bends through every column of points),
    // and reward it: where enough spot checks within what the markers can
    // tell were recorded, every map's orders are chosen on them instead.
    let sound_spots: Vec<&Sample> = spot.iter().copied().filter(|s| !s.untrusted).collect();
    let steer = if two_d && super::uncertainty::fitted_on_spot_checks(sound_spots.len()) {
        cols(&sound_spots)
    } else {
        cols(&val)
    };
    let (g1, r1) = poly::search_orders(
        &g1_spec,
        FitData::new(tr.g1_in.view(), tr.x_mm.view()),
        FitData::new(steer.g1_in.view(), steer.x_mm.view()),
        has_test.then(|| FitData::new(te.g1_in.view(), te.x_mm.view())),
        ls,
    )
    .map_err(named("g1"))?;
    let (g2, r2) = poly::search_orders(
        &g2_spec,
        FitData::new(tr.g2_in.view(), tr.y_mm.view()),
        FitData::new(steer.g2_in.view(), steer.y_mm.view()),
        has_test.then(|| FitData::new(te.g2_in.view(), te.y_mm.view())),
        ls,
    )
    .map_err(named("g2"))?;
    let force_maps = |spec: &PolySpec, prefix: &str| -> Result<[(Polynomial, FitReport); 3]> {
        let mut maps = Vec::with_capacity(3);
        for (k, name) in ["gx", "gy", "gz"].into_iter().enumerate() {
            let r = poly::search_orders(
                spec,
                FitData::new(tr.force.view(), tr.f[k].view()),
                FitData::new(steer.force.view(), steer.f[k].view()),
                has_test.then(|| FitData::new(te.force.view(), te.f[k].view())),
                ls,
            )
            .map_err(|e| prefix_error(&format!("{prefix}{name}"), e))?;
            maps.push(r);
        }
        Ok(maps.try_into().expect("three force maps were fitted"))
    };
    let [(gx, rx), (gy, ry), (gz, rz)] = force_maps(&force_spec(options)?, "")?;
    let guard = match options.guard {
        None => None,
        Some(g) => {
            let spec = force_spec(&FitOptions {
                shear_max_order: Some(g.shear_order),
                ..options.clone()
            })?;
            let [(fx, rfx), (fy, rfy), (fz, rfz)] = force_maps(&spec, "guard.")?;
            let mut guard = fit_guard(
                [&gx, &gy, &gz],
                [fx, fy, fz],
                vec![rfx, rfy, rfz],
                [&tr.force, &va.force],
                &g,
            )?;
            guard.envelope = load_envelope(
                samples
                    .iter()
                    .filter(|s| matches!(s.split, Split::Train | Split::Val)),
            );
            Some(guard)
        }
    };
    let mut cal = Calibration::new(
        setup.clone(),
        [g1, g2, gx, gy, gz],
        Some(CalibrationReport {
            options: options.clone(),
            g1: r1,
            g2: r2,
            gx: rx,
            gy: ry,
            gz: rz,
            test: None,
            spot: None,
        }),
    )?;
    // `new` checked the rest; only the guard is new here.
    if let Some(g) = &guard {
        g.validate().map_err(in_memory)?;
    }
    cal.guard = guard;
    let fitted_on = if super::uncertainty::fitted_on_spot_checks(spot.len()) {
        &spot
    } else {
        &val
    };
    cal.uncertainty = fit_uncertainty(&cal, fitted_on, &test)?;
    if has_test {
        let table = evaluate(&cal, samples, Split::Test)?;
        if let Some(r) = cal.report.as_mut() {
            r.test = Some(table);
        }
    }
    if !spot.is_empty() {
        let table = evaluate(&cal, samples, Split::Spot)?;
        if let Some(r) = cal.report.as_mut() {
            r.spot = Some(table);
        }
    }
    Ok(cal)
}

/// The per-contact force uncertainty of `cal` ([`super::uncertainty`]),
/// fitted on its errors on the held-out samples `held_out` (the spot checks
/// when there are at least [`super::uncertainty::MIN_SAMPLES`] of them, as
/// they sample the places between the protocol's points; else the
/// validation split) and scored on the test samples; `None` with fewer than
/// [`super::uncertainty::MIN_SAMPLES`] held-out samples.
fn fit_uncertainty(
    cal: &Calibration,
    held_out: &[&Sample],
    test: &[&Sample],
) -> Result<Option<ForceUncertainty>> {
    let spread = |set: &[&Sample]| -> Result<Vec<SpreadSample>> {
        set.iter()
            .map(|s| Ok(SpreadSample::of(s, &cal.predict(s)?)))
            .collect()
    };
    let held_out = spread(held_out)?;
    if held_out.len() < super::uncertainty::MIN_SAMPLES {
        return Ok(None);
    }
    let mut model = ForceUncertainty::fit(&held_out)?;
    model.test_coverage = model.coverage(&spread(test)?);
    Ok(Some(model))
}

/// The guard of the full force maps `full` with fallback maps `safe`: the box
/// of the inputs `sets` (rows of force inputs) and, per component, the
/// tolerance `max(floor, factor * quantile of |full - safe| over the sets)`
/// (`options` already checked by [`fit`]).
fn fit_guard(
    full: [&Polynomial; 3],
    safe: [Polynomial; 3],
    report: Vec<FitReport>,
    sets: [&Array2<f64>; 2],
    options: &GuardOptions,
) -> Result<ForceGuard> {
    let mut lo = [f64::INFINITY; 6];
    let mut hi = [f64::NEG_INFINITY; 6];
    let mut gaps: [Vec<f64>; 3] = Default::default();
    for m in sets {
        for (j, col) in m.columns().into_iter().enumerate() {
            lo[j] = col.fold(lo[j], |a, &x| a.min(x));
            hi[j] = col.fold(hi[j], |a, &x| a.max(x));
        }
        for (k, g) in gaps.iter_mut().enumerate() {
            let d = full[k].evaluate_rows(m.view())? - safe[k].evaluate_rows(m.view())?;
            g.extend(d.iter().map(|x| x.abs()));
        }
    }
    let tolerance_n = gaps.map(|mut g| {
        g.sort_by(f64::total_cmp);
        // The smallest value with at least `quantile` of the data at or below it.
        let i = ((options.quantile * g.len() as f64).ceil() as usize).clamp(1, g.len().max(1)) - 1;
        let q = g.get(i).copied().unwrap_or(0.0);
        (options.tolerance_factor * q).max(options.tolerance_floor_n)
    });
    Ok(ForceGuard {
        maps: safe,
        input_min: lo,
        input_max: hi,
        tolerance_n,
        report: Some(report),
        envelope: Vec::new(),
    })
}

/// The guard's load envelope ([`ForceGuard::envelope_at`]): per
/// characterization point of `samples`, its mean contact point and largest
/// load ([`super::load_of`]), in the order of the points' numbers (at most
/// [`super::MAX_LOAD_SITES`] points, the first ones).
fn load_envelope<'a>(samples: impl Iterator<Item = &'a Sample>) -> Vec<LoadSite> {
    let mut sites: std::collections::BTreeMap<u32, (f64, f64, f64, usize)> = Default::default();
    for s in samples {
        let load = super::load_of(&s.force_inputs());
        if !(s.x2d.is_finite() && s.y2d.is_finite() && load.is_finite()) {
            continue;
        }
        let e = sites.entry(s.point).or_insert((0.0, 0.0, 0.0, 0));
        e.0 += s.x2d;
        e.1 += s.y2d;
        e.2 = e.2.max(load);
        e.3 += 1;
    }
    sites
        .into_values()
        .filter(|&(_, _, d, _)| d > 0.0)
        .take(super::MAX_LOAD_SITES)
        .map(|(x, y, d, n)| LoadSite {
            x2d: x / n as f64,
            y2d: y / n as f64,
            load_max: d,
        })
        .collect()
}

/// Puts the map's name in front of an error's message.
fn prefix_error(what: &str, e: Error) -> Error {
    match e {
        Error::Numerical { what: w, message } => Error::Numerical {
            what: format!("{w} of `{what}`"),
            message,
        },
        Error::InvalidParameter { name, message } => Error::InvalidParameter {
            name,
            message: format!("fitting `{what}`: {message}"),
        },
        other => other,
    }
}

/// One test of the dataset and what the pipeline found in it.
#[derive(Debug, Clone, PartialEq)]
pub struct Extraction {
    /// The test's row of `tests.csv`.
    pub row: TestRow,
    /// The strongest patch's raw quantities, `None` if nothing was detected.
    pub raw: Option<RawContact>,
    /// How many patches were found.
    pub patches: usize,
    /// The frame's motion profiles: along x
    /// ([`crate::contact::profile::column_profile_into`]) and across, its
    /// column sums followed by its spread profile
    /// ([`crate::contact::profile::across_profiles_into`]); empty if nothing
    /// was detected.
    pub profiles: [Vec<f64>; 2],
    /// The flow grid's scale (full-resolution pixels per cell).
    pub scale: f64,
    /// Whether the strongest patch moved beyond what the reference's
    /// markers can tell ([`ContactExtractor::beyond_markers`]: half the
    /// pitch of a regular grid or more, or a torn flow on random markers);
    /// such a contact is marked out of domain at run time.
    pub beyond_markers: bool,
    /// Whether the strongest patch's dots were all followed
    /// ([`ContactExtractor::dots_followed`]: none lost in its box, motion
    /// under two thirds of the pitch); a training or validation test
    /// beyond the markers is fitted on only then ([`Extraction::fits`]).
    pub dots_followed: bool,
    /// Whether the strongest patch's displacements should have come from
    /// its dots' fitted field but the fit failed
    /// ([`ContactExtractor::dot_fit_failed`]): never fitted on, marked out
    /// of domain at run time.
    pub dot_fit_failed: bool,
}

impl Extraction {
    /// Whether the maps may be fitted on this test's motion: it stayed
    /// within what the markers can tell, or its dots were all followed.
    /// Why the second: under a small indenter pressed hard, most tests
    /// beyond half the pitch have every dot where it truly moved, and
    /// leaving them out left the maps to extrapolate to the strongest
    /// presses. On the simulated fingertip sensor, fitted with them the
    /// held-out rows score Fx / Fy / Fz 0.020 / 0.034 / 0.035 N, without
    /// them 0.025 / 0.042 / 0.047 N (`docs/results.md`).
    pub fn fits(&self) -> bool {
        (!self.beyond_markers || self.dots_followed) && !self.dot_fit_failed
    }
}

/// Largest `geometry.json` read: 64 KiB (a geometry is a few fields).
pub const MAX_GEOMETRY_BYTES: u64 = 64 << 10;

/// The name of the file beside `tests.csv` that describes the sensor's
/// surface (docs/formats.md).
pub const GEOMETRY_FILE: &str = "geometry.json";

/// Reads a dataset's `geometry.json` ([`SensorGeometry`] as JSON), `None`
/// when the dataset has none (the sensor is then whatever the caller says,
/// by default the curved strip). Errors ([`Error::Format`] naming the file)
/// on a file larger than [`MAX_GEOMETRY_BYTES`], not JSON, of an unknown
/// kind or with a dimension out of range; a path that exists but is not a
/// regular file is [`Error::Io`].
pub fn read_dataset_geometry(dir: impl AsRef<Path>) -> Result<Option<SensorGeometry>> {
    let path = dir.as_ref().join(GEOMETRY_FILE);
    if !path.exists() {
        return Ok(None);
    }
    let bytes = io::read_capped(&path, MAX_GEOMETRY_BYTES)?;
    let g: SensorGeometry = serde_json::from_slice(&bytes)
        .map_err(|e| Error::format(&path, Some(e.line()), e.to_string()))?;
    g.validate()
        .map_err(|e| Error::format(&path, None, e.to_string()))?;
    Ok(Some(g))
}

/// Reads a dataset's `tests.csv` (errors name the file and line).
pub fn read_dataset(dir: impl AsRef<Path>) -> Result<Vec<TestRow>> {
    let rows = io::read_tests_csv(dir.as_ref().join("tests.csv"))?;
    if rows.is_empty() {
        return Err(Error::format(
            dir.as_ref().join("tests.csv"),
            None,
            "no tests in the file",
        ));
    }
    Ok(rows)
}

fn load(dir: &Path, rel: &str, crop: Option<Roi>) -> Result<Array2<f32>> {
    let path: PathBuf = dir.join(rel);
    let img = io::read_gray(&path)?;
    match crop {
        None => Ok(img),
        Some(r) => r.crop(&img).map(|v| v.to_owned()),
    }
}

/// The default half-width of the energy-centroid window
/// ([`ContactPointMethod::EnergyCentroid`]), full-resolution pixels: wide
/// enough to hold a press's whole motion (about 60 mm of arc on the default
/// strip), so that the centroid is not cut asymmetrically.
pub const DEFAULT_CONTACT_WINDOW_PX: u32 = 400;

/// Runs the pipeline on every test of `rows` (images relative to `dir`),
/// cropping each image to `crop` if given, and measures each contact's
/// column by `contact_point` ([`ContactExtractor::locate`]).
/// `progress(done, total)` is called
/// from worker threads as tests finish. The first test that cannot be read
/// or processed stops the run with an error ([`Error::Context`]) that names
/// the test and its frames.
pub fn extract_dataset(
    dir: impl AsRef<Path>,
    rows: &[TestRow],
    config: &ExtractorConfig,
    contact_point: ContactPointMethod,
    crop: Option<Roi>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Vec<Extraction>> {
    let dir = dir.as_ref();
    // Checks the configuration once, so that workers cannot fail to build one.
    ContactExtractor::new(config.clone())?;
    contact_point.validate()?;
    let done = AtomicUsize::new(0);
    let total = rows.len();
    rows.par_iter()
        .map_init(
            || ContactExtractor::new(config.clone()).expect("configuration checked above"),
            |ex, row| {
                let mut one = || -> Result<Extraction> {
                    let reference = load(dir, &row.reference, crop)?;
                    let frame = load(dir, &row.frame, crop)?;
                    ex.set_reference(&reference)?;
                    ex.extract(&frame)?;
                    let raws = ex.locate(contact_point)?.to_vec();
                    let (flow, s) = ex.profile_flow();
                    let s = s as f64;
                    let mut profiles = [Vec::new(), Vec::new()];
                    if !raws.is_empty() {
                        column_profile_into(flow.u.view(), s, &mut profiles[0]);
                        across_profiles_into(flow.v.view(), s, true, &mut profiles[1]);
                    }
                    let beyond_markers = raws.first().is_some_and(|r| ex.beyond_markers(r));
                    let dots_followed = raws.first().is_some_and(|r| ex.dots_followed(r));
                    let dot_fit_failed = raws.first().is_some_and(|r| ex.dot_fit_failed(r));
                    Ok(Extraction {
                        row: row.clone(),
                        beyond_markers,
                        dots_followed,
                        dot_fit_failed,
                        raw: raws.first().copied(),
                        patches: raws.len(),
                        profiles,
                        scale: s,
                    })
                };
                let out = one().map_err(|e| {
                    e.context(format!(
                        "test {} (frame {}, reference {})",
                        row.test, row.frame, row.reference
                    ))
                })?;
                progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                Ok(out)
            },
        )
        .collect()
}

/// The most pairs of reference images [`rest_pairs`] returns: enough to
/// see a false-contact rate of a few percent, a second's work.
pub const MAX_REST_PAIRS: usize = 32;

/// Pairs of distinct reference images of `rows` (the unloaded skin of
/// different tests, recorded apart): frames with nothing touching, for
/// [`rest_contacts`]. The references are sorted by name and the `k`-th is
/// paired with the one half the list further on; at most `max` pairs,
/// spread evenly over the list. Empty when the tests share fewer than two
/// reference images.
pub fn rest_pairs(rows: &[TestRow], max: usize) -> Vec<(String, String)> {
    let mut refs: Vec<&str> = rows.iter().map(|r| r.reference.as_str()).collect();
    refs.sort_unstable();
    refs.dedup();
    let half = refs.len() / 2;
    let n = half.min(max);
    (0..n)
        .map(|i| {
            let k = i * half / n;
            (refs[k].to_string(), refs[k + half].to_string())
        })
        .collect()
}

/// What the segmentation reports on frames with nothing touching
/// ([`rest_contacts`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RestCheck {
    /// Pairs of reference images read.
    pub pairs: usize,
    /// Pairs on which at least one contact was found.
    pub with_contact: usize,
}

impl RestCheck {
    /// Whether no pair gave a contact (true, vacuously, without pairs).
    pub fn quiet(&self) -> bool {
        self.with_contact == 0
    }
}

/// Runs the pipeline on each pair `(reference, frame)` of images (paths
/// relative to `dir`, cropped to `crop` if given; [`rest_pairs`]), the
/// first as the reference, and counts the pairs on which it finds a contact:
/// with both images of the unloaded skin, each one is a false contact at
/// rest. Errors name the pair whose images cannot be read or processed.
pub fn rest_contacts(
    dir: impl AsRef<Path>,
    pairs: &[(String, String)],
    config: &ExtractorConfig,
    crop: Option<Roi>,
) -> Result<RestCheck> {
    let dir = dir.as_ref();
    ContactExtractor::new(config.clone())?;
    let found: Vec<bool> = pairs
        .par_iter()
        .map_init(
            || ContactExtractor::new(config.clone()).expect("configuration checked above"),
            |ex, (a, b)| {
                let mut one = || -> Result<bool> {
                    ex.set_reference(&load(dir, a, crop)?)?;
                    Ok(!ex.extract(&load(dir, b, crop)?)?.is_empty())
                };
                one().map_err(|e| e.context(format!("rest pair (reference {a}, frame {b})")))
            },
        )
        .collect::<Result<_>>()?;
    Ok(RestCheck {
        pairs: pairs.len(),
        with_contact: found.iter().filter(|&&f| f).count(),
    })
}

/// One threshold preset tried by [`AutoThresholds`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ThresholdTry {
    /// The preset.
    pub preset: ThresholdPreset,
    /// Tests that gave no contact with it.
    pub missed: usize,
    /// Tests run.
    pub tests: usize,
    /// What it found at rest ([`rest_contacts`]).
    pub rest: RestCheck,
    /// What that makes of it.
    pub verdict: ThresholdVerdict,
}

/// Chooses a characterization's segmentation thresholds among the presets
/// from what each does on the dataset itself: `high`, `mid`, `low` in turn
/// ([`AutoThresholds::ORDER`]), keeping the first that gives a contact on
/// all but [`report::MISSED_TESTS_WARNING_FRACTION`] of the tests, else the
/// most sensitive one that found no contact at rest; a preset that finds
/// one at rest ends the search (a more sensitive one would too), and if
/// even `high` does it is kept, as nothing less sensitive is offered.
///
/// The caller runs the pipeline: while [`next_preset`](Self::next_preset)
/// names one, extract the tests with its thresholds ([`extract_dataset`]),
/// read the rest pairs ([`rest_contacts`]) and [`record`](Self::record)
/// them; then [`finish`](Self::finish).
#[derive(Debug, Default)]
pub struct AutoThresholds {
    tried: Vec<ThresholdTry>,
    kept: Option<(ThresholdPreset, Vec<Extraction>)>,
}

impl AutoThresholds {
    /// The order the presets are tried in: the paper's robust choice first.
    pub const ORDER: [ThresholdPreset; 3] = [
        ThresholdPreset::High,
        ThresholdPreset::Mid,
        ThresholdPreset::Low,
    ];

    /// A search that has tried nothing.
    pub fn new() -> Self {
        Self::default()
    }

    /// The preset to try next, `None` once the search is over (the last
    /// preset tried saw the tests or fired at rest, or none is left).
    pub fn next_preset(&self) -> Option<ThresholdPreset> {
        match self.tried.last() {
            Some(t) if t.verdict != ThresholdVerdict::Misses => None,
            _ => Self::ORDER.get(self.tried.len()).copied(),
        }
    }

    /// Records what [`next_preset`](Self::next_preset) did: its tests'
    /// extractions and its rest check. Errors if the search is over.
    pub fn record(
        &mut self,
        extractions: Vec<Extraction>,
        rest: RestCheck,
    ) -> Result<ThresholdTry> {
        let preset = self
            .next_preset()
            .ok_or_else(|| Error::param("thresholds", "the preset search is over"))?;
        let missed = extractions.iter().filter(|e| e.raw.is_none()).count();
        let verdict = report::threshold_verdict(missed, extractions.len(), rest);
        let t = ThresholdTry {
            preset,
            missed,
            tests: extractions.len(),
            rest,
            verdict,
        };
        self.tried.push(t);
        // A preset that fires at rest is kept only when it is the first.
        if verdict != ThresholdVerdict::Noisy || self.kept.is_none() {
            self.kept = Some((preset, extractions));
        }
        Ok(t)
    }

    /// Every preset tried, in order.
    pub fn tried(&self) -> &[ThresholdTry] {
        &self.tried
    }

    /// The preset kept and its tests' extractions; `None` if nothing was
    /// recorded.
    pub fn finish(self) -> Option<(ThresholdPreset, Vec<Extraction>)> {
        self.kept
    }
}

/// A fitted calibration and how it did.
#[derive(Debug, Clone)]
pub struct DatasetFit {
    /// The calibration.
    pub calibration: Calibration,
    /// Per extraction (same order), its sample if the test was detected.
    pub samples: Vec<Option<Sample>>,
    /// Tests with no detected contact, per split: train, val, test, spot.
    pub misses: [usize; 4],
    /// Sweep images not read as a press (no contact, or one that failed
    /// the press test); 0 without sweeps.
    pub sweep_misses: usize,
    /// The minimum detectable force (smallest commanded force from which on
    /// at least 95% of the tests at each force are detected; the spot
    /// checks, at forces off the protocol's ladder, left out).
    pub min_force: DetectionLimit,
    /// Errors on the test split, total and per point.
    pub test_table: PointTable,
    /// Errors on the spot checks, if the dataset has any.
    pub spot_table: Option<PointTable>,
}

fn split_index(s: Split) -> usize {
    match s {
        Split::Train => 0,
        Split::Val => 1,
        Split::Test => 2,
        Split::Spot => 3,
    }
}

/// Per extraction, the sample of a detected test, its raw displacements
/// in `frame`: rotated into the sensor frame at chord position
/// `x_of(extraction, raw)`, or the local ones; with `local[i]` given,
/// extraction `i`'s profile-matched local force is taken as its raw
/// displacements ([`sensor_displacements`], [`ForceFrame::displacements`]).
fn samples(
    ex: &[Extraction],
    geometry: &SensorGeometry,
    frame: ForceFrame,
    local: &[Option<[f64; 3]>],
    x_of: impl Fn(&Extraction, &RawContact) -> Result<f64>,
) -> Result<Vec<Option<Sample>>> {
    ex.iter()
        .enumerate()
        .map(|(i, e)| {
            e.raw
                .map(|mut raw| {
                    if let Some(f) = local.get(i).copied().flatten() {
                        raw.local_force = Some(f);
                    }
                    raw.d_sensor = sensor_displacements(geometry, x_of(e, &raw)?, &raw);
                    Ok(Sample::from_test_in(&e.row, &raw, frame))
                })
                .transpose()
        })
        .collect()
}

/// The tests with no detected contact per split (train, val, test, spot),
/// and each protocol test's commanded force and whether it was detected,
/// for the detection limit: per level of the protocol's force ladder, so
/// the spot checks, each at a force of its own, are left out of it.
fn detections(ex: &[Extraction], s: &[Option<Sample>]) -> ([usize; 4], Vec<(f64, bool)>) {
    let mut misses = [0usize; 4];
    let mut found = Vec::with_capacity(ex.len());
    for (e, s) in ex.iter().zip(s) {
        if s.is_none() {
            misses[split_index(e.row.split)] += 1;
        }
        if e.row.split != Split::Spot {
            found.push((e.row.force_n, s.is_some()));
        }
    }
    (misses, found)
}

fn detected(s: &[Option<Sample>]) -> Vec<Sample> {
    s.iter().flatten().copied().collect()
}

/// The detected samples the maps are fitted on: every test row, but no
/// training or validation row whose motion went beyond what the markers can
/// tell ([`Extraction::beyond_markers`]) unless its dots were all followed
/// ([`Extraction::fits`]): otherwise its flow may have matched each dot to a
/// neighbour, or torn apart on random markers, and a map fitted on it would
/// be wrong for every other contact. The sensor marks contacts beyond the markers out of domain; the
/// test split and the spot checks keep them, so that their errors count them.
fn trusted(ex: &[Extraction], s: &[Option<Sample>]) -> Vec<Sample> {
    ex.iter()
        .zip(s)
        .filter(|(e, _)| e.fits() || matches!(e.row.split, Split::Test | Split::Spot))
        .filter_map(|(e, s)| {
            s.map(|s| Sample {
                untrusted: !e.fits(),
                ..s
            })
        })
        .collect()
}

/// Fits a calibration from the extractions (see the module docs), without
/// sweeps: [`fit_dataset_with_sweeps`] with none.
pub fn fit_dataset(
    extractions: &[Extraction],
    config: &ExtractorConfig,
    contact_point: ContactPointMethod,
    crop: Roi,
    geometry: SensorGeometry,
    options: &FitOptions,
) -> Result<DatasetFit> {
    fit_dataset_with_sweeps(
        extractions,
        &[],
        config,
        contact_point,
        crop,
        geometry,
        options,
    )
}

/// Fits a calibration from the tests' extractions and, when there are
/// sweeps ([`extract_sweeps`]), the [`ColumnCorrection`] of the sweeps'
/// images ([`super::correction`]):
///
/// - the location offsets once the location maps are fitted (the first
///   pass), so that the profile model is matched at the corrected
///   locations, as a sensor will match it; with sweeps at several tilts,
///   one layer of offsets per tilt, looked up by each contact's matched
///   shear ratio ([`super::correction`]);
/// - the gains of the matched normal force once the profile model is
///   fitted: per sweep, the true normal force over the matched one,
///   divided by the sweep's median. Every test's matched force is
///   corrected by them before the force maps are fitted.
///
/// Sweeps need a sensor that locates along x (the strip): on one that
/// locates in 2-D they are an error.
pub fn fit_dataset_with_sweeps(
    extractions: &[Extraction],
    sweeps: &[Extraction],
    config: &ExtractorConfig,
    contact_point: ContactPointMethod,
    crop: Roi,
    geometry: SensorGeometry,
    options: &FitOptions,
) -> Result<DatasetFit> {
    fit_columns_as_measured(
        extractions,
        sweeps,
        config,
        contact_point,
        crop,
        geometry,
        options,
        false,
    )
}

/// [`fit_dataset_with_sweeps`] on extractions whose columns are
/// `shear_free` (measured again, [`shear_free_extractions`]) or not yet.
/// A fit that asks for shear-free columns and has not measured them fits
/// its first profile model, measures every test's and sweep's column
/// again with it, as a sensor will, and fits everything again on those.
#[allow(clippy::too_many_arguments)]
fn fit_columns_as_measured(
    extractions: &[Extraction],
    sweeps: &[Extraction],
    config: &ExtractorConfig,
    contact_point: ContactPointMethod,
    crop: Roi,
    geometry: SensorGeometry,
    options: &FitOptions,
    shear_free: bool,
) -> Result<DatasetFit> {
    if !sweeps.is_empty() && geometry.locates_in_2d() {
        return Err(Error::param(
            "sweeps",
            "sweeps correct the location along x only: not for a sensor that locates in 2-D",
        ));
    }
    let setup = SensorSetup {
        geometry,
        crop,
        thresholds: config.thresholds,
        pipeline: Some(PipelineSettings {
            flow_preset: preset_name(config),
            margin_px: config.margin_px,
            subpixel: config.subpixel,
            contact_window_px: match contact_point {
                ContactPointMethod::EnergyCentroid { half_window_px } => {
                    half_window_px.round() as u32
                }
                _ => 0,
            },
            contact_point: Some(contact_point),
            exposure: Some(config.exposure),
            dot_tracking: config.dot_tracking,
            dot_fit: config.dot_tracking && config.dot_fit,
            light_box_px: config.light_box_px,
            weighted_profiles: config.weighted_profiles,
        }),
    };
    // Pass 1: the location maps (the rotation does not affect them).
    let first = trusted(
        extractions,
        &samples(extractions, &geometry, options.force_frame, &[], |_, _| {
            Ok(0.0)
        })?,
    );
    let mut pass1 = fit(&first, &setup, options)?;
    let groups = tilt_groups(sweeps);
    let mut location_fix = location_correction(sweeps, &groups, &pass1, crop)?;
    pass1.column_correction = location_fix.clone();
    // The profile model (forces by matched kernels), fitted on the training
    // split with the true forces in the local frame at the true location;
    // then every detected test's local force is matched with it.
    // A test whose measured point the model finds clearly elsewhere is
    // moved there, as a sensor moves it (`Calibration::match_forces_with`).
    let mut relocated = None;
    let (profile, local) = match options.profile {
        None => (None, Vec::new()),
        Some(p) => {
            let mut model = fit_profile(extractions, &geometry, &setup.crop, p, &pass1)?;
            model.relocation = relocation_for(p.relocation, !sweeps.is_empty());
            let sigma_px = match contact_point {
                ContactPointMethod::SlopePeak { sigma_px }
                    if p.shear_free_columns && model.anchor.is_some() =>
                {
                    Some(sigma_px)
                }
                _ => None,
            };
            if let (Some(sigma_px), false) = (sigma_px, shear_free) {
                let again =
                    |set: &[Extraction]| shear_free_extractions(&model, set, &pass1, sigma_px);
                return fit_columns_as_measured(
                    &again(extractions)?,
                    &again(sweeps)?,
                    config,
                    contact_point,
                    crop,
                    geometry,
                    options,
                    true,
                );
            }
            model.shear_free_columns = sigma_px.is_some();
            if let Some(fix) = matched_layer_ratios(&model, sweeps, &groups, &pass1)? {
                location_fix = Some(fix.clone());
                pass1.column_correction = Some(fix);
            }
            // Shear-free columns were measured after a sensor's relocation
            // (`shear_free_extractions`); a sensor does not relocate again.
            if !model.shear_free_columns {
                relocated = relocate(&model, extractions, &pass1)?;
            }
            let moved = relocated.as_deref().unwrap_or(extractions);
            if let Some(tilted) = with_matched_ratios(&model, moved, &pass1)? {
                relocated = Some(tilted);
            }
            let moved = relocated.as_deref().unwrap_or(extractions);
            let local = match_forces(&model, moved, |e, raw| {
                Ok(match_position(&model, e, raw, &pass1)?.1)
            })?;
            (Some(model), local)
        }
    };
    let extractions = relocated.as_deref().unwrap_or(extractions);
    // The force gains of the sweeps, on the profile-matched normal force:
    // applied to every test's matched force, so that the force maps are
    // fitted on corrected inputs, as a sensor will give them.
    let mut local = local;
    let (correction, sweep_local) = match (location_fix, &profile) {
        (Some(fix), Some(model)) => {
            let (fix, sweep_local) = normal_gain(sweeps, &groups, &pass1, model, fix)?;
            for (e, f) in extractions.iter().zip(local.iter_mut()) {
                if let (Some(raw), Some(f)) = (&e.raw, f.as_mut()) {
                    let column = match_position(model, e, raw, &pass1)?.1;
                    let tilt = raw.matched_shear_ratio.unwrap_or(f64::NAN);
                    *f = fix.correct_local_force(column, tilt, *f);
                }
            }
            (Some(fix), sweep_local)
        }
        (fix, _) => (fix, Vec::new()),
    };
    // Pass 2: rotate at the predicted location (the true one for the
    // training tests of an anchored profile model, see `match_position`),
    // fit everything.
    let mut second = samples(
        extractions,
        &geometry,
        options.force_frame,
        &local,
        |e, raw| match &profile {
            Some(model) => Ok(match_position(model, e, raw, &pass1)?.0),
            None => Ok(pass1.location_of(raw)?[0]),
        },
    )?;
    // The press test a sensor applies (`Calibration::is_press`): a test
    // whose strongest patch fails it counts as a miss, as it would at run time.
    // Without a profile model nothing was matched (`local` is empty), so
    // there is no threshold.
    let min_normal_n = press_threshold(extractions, &local);
    for (i, s) in second.iter_mut().enumerate() {
        if !super::passes_press_test(min_normal_n, local.get(i).copied().flatten()) {
            *s = None;
        }
    }
    let mut cal = fit(&trusted(extractions, &second), &setup, options)?;
    cal.profile = profile;
    cal.min_normal_n = min_normal_n;
    cal.column_correction = correction;
    let sweep_misses = sweeps
        .iter()
        .zip(sweep_local.iter().chain(std::iter::repeat(&None)))
        .filter(|(e, f)| e.raw.is_none() || !super::passes_press_test(min_normal_n, **f))
        .count();
    let (misses, detections) = detections(extractions, &second);
    let min_force = report::min_detectable_force(&detections, 0.95)?;
    let found = detected(&second);
    let test_table = report::evaluate(&cal, &found, Split::Test)?;
    let spot_table = if found.iter().any(|s| s.split == Split::Spot) {
        Some(report::evaluate(&cal, &found, Split::Spot)?)
    } else {
        None
    };
    // The report's errors were taken before the column correction was set.
    if let Some(r) = cal.report.as_mut() {
        r.test = Some(test_table.clone());
        r.spot = spot_table.clone();
    }
    Ok(DatasetFit {
        calibration: cal,
        samples: second,
        misses,
        sweep_misses,
        min_force,
        test_table,
        spot_table,
    })
}

/// The relocation a profile model is fitted with: the one asked for, else
/// [`Relocation::Clear`] with sweeps (their corrections are learned at the
/// measured columns) and [`Relocation::Best`] without.
fn relocation_for(asked: Option<Relocation>, sweeps: bool) -> Relocation {
    asked.unwrap_or(if sweeps {
        Relocation::Clear
    } else {
        Relocation::Best
    })
}

/// Sweeps whose loads' median tilts along the strip (sensor frame,
/// `atan2(fx, -fz)`) lie within this many degrees of each other share one
/// layer of the correction.
const TILT_GROUP_DEG: f64 = 3.0;

/// The sweeps' images grouped by tilt ([`tilt_groups`]).
struct TiltGroups {
    /// The group of each sweep image, in the sweeps' order.
    of_image: Vec<usize>,
    /// Each group's mean tilt along the strip, degrees.
    tilts_deg: Vec<f64>,
}

/// The tilt group of each sweep image: its sweep's median tilt along the
/// strip ([`TILT_GROUP_DEG`]), group 0 the one nearest to straight, the others
/// by increasing tilt. Also the groups' mean tilts, degrees. The sweep
/// number is the rows' `repeat` ([`io::SweepRow::as_test`]).
fn tilt_groups(sweeps: &[Extraction]) -> TiltGroups {
    let mut per_sweep: std::collections::BTreeMap<u32, Vec<f64>> = Default::default();
    for e in sweeps {
        let r = &e.row;
        let tilt = r.fx_n.atan2(-r.fz_n).to_degrees();
        if tilt.is_finite() {
            per_sweep.entry(r.repeat).or_default().push(tilt);
        }
    }
    let mut medians: Vec<(u32, f64)> = per_sweep
        .into_iter()
        .filter_map(|(k, t)| Some((k, upper_median(t)?)))
        .collect();
    medians.sort_by(|a, b| a.1.total_cmp(&b.1));
    // Clusters of consecutive tilts.
    let mut clusters: Vec<Vec<(u32, f64)>> = Vec::new();
    for m in medians {
        match clusters.last_mut() {
            Some(c) if m.1 - c[c.len() - 1].1 <= TILT_GROUP_DEG => c.push(m),
            _ => clusters.push(vec![m]),
        }
    }
    let mean = |c: &[(u32, f64)]| c.iter().map(|m| m.1).sum::<f64>() / c.len() as f64;
    let straightest = (0..clusters.len())
        .min_by(|&a, &b| {
            mean(&clusters[a])
                .abs()
                .total_cmp(&mean(&clusters[b]).abs())
        })
        .unwrap_or(0);
    if !clusters.is_empty() {
        let first = clusters.remove(straightest);
        clusters.insert(0, first);
    }
    let tilts: Vec<f64> = clusters.iter().map(|c| mean(c)).collect();
    let group_of = |sweep: u32| {
        clusters
            .iter()
            .position(|c| c.iter().any(|m| m.0 == sweep))
            .unwrap_or(0)
    };
    TiltGroups {
        of_image: sweeps.iter().map(|e| group_of(e.row.repeat)).collect(),
        tilts_deg: tilts,
    }
}

/// The location half of the sweeps' [`ColumnCorrection`] for `cal` (gains
/// all 1): at each detected sweep image's measured column, the true chord
/// position minus `cal`'s; one layer per tilt beyond the straightest
/// ([`tilt_groups`]), each with its images' true shear ratios in the local
/// frame (replaced by their matched ones once the profile model is fitted,
/// [`matched_layer_ratios`]). `None`
/// without sweeps; an error if no image of a tilt was detected, or if the
/// sweeps hold more tilts than a correction may have layers.
fn location_correction(
    sweeps: &[Extraction],
    groups: &TiltGroups,
    cal: &Calibration,
    crop: Roi,
) -> Result<Option<ColumnCorrection>> {
    if sweeps.is_empty() {
        return Ok(None);
    }
    let tilts = &groups.tilts_deg;
    if tilts.len() > MAX_CORRECTION_LAYERS + 1 {
        return Err(Error::param(
            "sweeps",
            format!(
                "{} tilts of the sweeps' loads, at most {}",
                tilts.len(),
                MAX_CORRECTION_LAYERS + 1
            ),
        ));
    }
    // Per group: columns, location offsets and shear ratios of its images.
    let geometry = cal.setup.geometry;
    let mut per_group = vec![(Vec::new(), Vec::new(), Vec::new()); tilts.len().max(1)];
    for (e, &g) in sweeps.iter().zip(&groups.of_image) {
        if let Some(raw) = &e.raw {
            let r = &e.row;
            let (columns, offsets, ratios) = &mut per_group[g];
            columns.push(raw.x_px);
            offsets.push(r.x_mm - cal.location_of(raw)?[0]);
            let truth = geometry.sensor_to_local(r.x_mm, [r.fx_n, r.fy_n, r.fz_n]);
            ratios.push(shear_ratio_of(truth).unwrap_or(f64::NAN));
        }
    }
    for (g, (columns, _, _)) in per_group.iter().enumerate() {
        if columns.is_empty() {
            let which = if tilts.len() > 1 {
                format!(" tilted by {:.1} deg", tilts.get(g).copied().unwrap_or(0.0))
            } else {
                String::new()
            };
            return Err(Error::param(
                "sweeps",
                format!("no contact found in any sweep image{which}"),
            ));
        }
    }
    let sigma = smoothing_for(&per_group[0].0);
    let n = crop.w;
    let smooth = |columns: &[f64], values: &[f64], prior: f64, sigma: f64| {
        smooth_on_grid(columns, values, prior, sigma, 0.0, 1.0, n)
    };
    let ratios_of =
        |columns: &[f64], ratios: &[f64]| smoothed_ratios(columns, ratios, (sigma, 0.0, 1.0, n));
    let (columns, offsets, ratios) = &per_group[0];
    let location_mm = smooth(columns, offsets, 0.0, sigma)?;
    let mut fix = ColumnCorrection {
        start_px: 0.0,
        step_px: 1.0,
        force_gain: vec![1.0; location_mm.len()],
        location_mm,
        smoothing_px: sigma,
        images: per_group.iter().map(|g| g.0.len()).sum(),
        shear_ratio: None,
        layers: Vec::new(),
    };
    if per_group.len() == 1 {
        return Ok(Some(fix));
    }
    for (columns, offsets, ratios) in &per_group[1..] {
        // Learned as a change from the straight offsets, so that where no
        // image of this tilt is near, the straight offsets hold.
        let mut change: Vec<f64> = columns
            .iter()
            .zip(offsets)
            .map(|(&c, &o)| o - fix.location_mm_at(c, f64::NAN))
            .collect();
        clip_outliers(&mut change, LAYER_LOCATION_FLOOR_MM);
        let mut location = smooth(columns, &change, 0.0, sigma)?;
        for (l, base) in location.iter_mut().zip(&fix.location_mm) {
            *l += base;
        }
        fix.layers.push(CorrectionLayer {
            shear_ratio: ratios_of(columns, ratios)?,
            location_mm: location,
            force_gain: vec![1.0; n],
            images: columns.len(),
        });
    }
    fix.shear_ratio = Some(ratios_of(columns, ratios)?);
    Ok(Some(fix))
}

/// The upper median of the finite `values` (the middle one of an odd
/// count, the upper of the middle two of an even one); `None` when none is
/// finite.
fn upper_median(values: impl IntoIterator<Item = f64>) -> Option<f64> {
    let mut v: Vec<f64> = values.into_iter().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    let n = v.len();
    let (_, &mut m, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    Some(m)
}

/// How many robust standard deviations (1.4826 times the median absolute
/// deviation) a tilt layer's change at one image may lie from the median
/// change before it is clipped ([`clip_outliers`]).
const LAYER_CLIP_SIGMAS: f64 = 3.0;

/// The least half-width of the band [`clip_outliers`] keeps a tilt layer's
/// location changes in, mm.
const LAYER_LOCATION_FLOOR_MM: f64 = 0.1;

/// The least half-width of the band [`clip_outliers`] keeps a tilt layer's
/// gain factors in.
const LAYER_GAIN_FLOOR: f64 = 0.05;

/// Clips each value to the median plus or minus [`LAYER_CLIP_SIGMAS`]
/// robust standard deviations (at least `floor`); NaN values stay NaN.
///
/// Why: a tilted rod's raw column does not follow its place smoothly but
/// jumps with the marker pattern (a few images read several millimetres
/// off where their neighbours do not), and smoothed as they are, those few
/// images made a layer that moved a nearly straight press by over a
/// millimetre. The clip bounds what a handful of images can teach a layer
/// while the place-to-place pattern within the band is kept.
fn clip_outliers(values: &mut [f64], floor: f64) {
    let Some(median) = upper_median(values.iter().copied()) else {
        return;
    };
    let mad = upper_median(values.iter().map(|v| (v - median).abs())).unwrap_or(0.0);
    let band = (LAYER_CLIP_SIGMAS * 1.4826 * mad).max(floor);
    for v in values.iter_mut().filter(|v| v.is_finite()) {
        *v = v.clamp(median - band, median + band);
    }
}

/// The smoothing of a correction fitted at `columns`: [`DEFAULT_SMOOTHING_PX`],
/// or half the median spacing of the columns if that is wider. Sweeps in coarse
/// steps then give a correction that varies smoothly between their images
/// instead of one that is back at none halfway between them. Columns less
/// than a pixel apart (several sweeps over the same positions) count once.
fn smoothing_for(columns: &[f64]) -> f64 {
    let mut sorted: Vec<f64> = columns.iter().copied().filter(|c| c.is_finite()).collect();
    sorted.sort_by(f64::total_cmp);
    let mut gaps: Vec<f64> = sorted
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|gap| *gap >= 1.0)
        .collect();
    gaps.sort_by(f64::total_cmp);
    let spacing = gaps.get(gaps.len() / 2).copied().unwrap_or(0.0);
    (0.5 * spacing).max(DEFAULT_SMOOTHING_PX)
}

/// The smallest commanded force of a sweep image whose gain is measured,
/// N: the ratio of two small forces is mostly noise.
const MIN_GAIN_FORCE_N: f64 = 0.3;

/// `fix` with its force gains, and each sweep image's matched local force
/// with the gain applied. Each detected sweep image is matched by `model`
/// as a sensor matches it (at `cal`'s column, `cal` holding the location
/// offsets of `fix`); its gain, at that column, is its true normal force
/// in the local frame over the matched one, divided by the median of its
/// sweep; each tilt's gains go to its own layer ([`tilt_groups`]). Images
/// whose ratio leaves [`GAIN_RANGE`] or whose commanded force is below
/// [`MIN_GAIN_FORCE_N`] are left out.
fn normal_gain(
    sweeps: &[Extraction],
    groups: &TiltGroups,
    cal: &Calibration,
    model: &ProfileModel,
    fix: ColumnCorrection,
) -> Result<(ColumnCorrection, Vec<Option<[f64; 3]>>)> {
    let geometry = cal.setup.geometry;
    let tilted = with_matched_ratios(model, sweeps, cal)?;
    let sweeps = tilted.as_deref().unwrap_or(sweeps);
    let mut local = match_forces(model, sweeps, |_, raw| cal.match_column(model, raw))?;
    let columns_of = sweeps
        .iter()
        .map(|e| e.raw.map(|raw| cal.match_column(model, &raw)).transpose())
        .collect::<Result<Vec<_>>>()?;
    // Per sweep: (group, match column, ratio) of each usable image.
    let mut per_sweep: std::collections::BTreeMap<u32, Vec<(usize, f64, f64)>> = Default::default();
    let (lo, hi) = GAIN_RANGE;
    for (((e, f), column), &g) in sweeps
        .iter()
        .zip(&local)
        .zip(&columns_of)
        .zip(&groups.of_image)
    {
        let (Some(f), Some(column)) = (f, column) else {
            continue;
        };
        let r = &e.row;
        let truth = geometry.sensor_to_local(r.x_mm, [r.fx_n, r.fy_n, r.fz_n]);
        let ratio = truth[2] / f[2];
        if r.force_n >= MIN_GAIN_FORCE_N && ratio.is_finite() && (lo..=hi).contains(&ratio) {
            per_sweep
                .entry(r.repeat)
                .or_default()
                .push((g, *column, ratio));
        }
    }
    // Per group: the columns and gains of its sweeps' images.
    let mut per_group = vec![(Vec::new(), Vec::new()); fix.layers.len() + 1];
    for images in per_sweep.values() {
        let Some(median) = upper_median(images.iter().map(|i| i.2)) else {
            continue;
        };
        for &(g, c, r) in images {
            if let Some((columns, gains)) = per_group.get_mut(g) {
                columns.push(c);
                gains.push(r / median);
            }
        }
    }
    let (sigma, start, step, n) = (
        fix.smoothing_px,
        fix.start_px,
        fix.step_px,
        fix.location_mm.len(),
    );
    let smooth = |(columns, gains): &(Vec<f64>, Vec<f64>)| -> Result<Vec<f64>> {
        let mut g = smooth_on_grid(columns, gains, 1.0, sigma, start, step, n)?;
        for g in &mut g {
            *g = g.clamp(lo, hi);
        }
        Ok(g)
    };
    let mut fix = fix;
    fix.force_gain = smooth(&per_group[0])?;
    let mut layer_gains = Vec::with_capacity(fix.layers.len());
    for (columns, gains) in &per_group[1..] {
        // As a factor on the straight gains, which hold where no image of
        // this tilt is near.
        let mut change: Vec<f64> = columns
            .iter()
            .zip(gains)
            .map(|(&c, &g)| g / fix.force_gain_at(c, f64::NAN))
            .collect();
        clip_outliers(&mut change, LAYER_GAIN_FLOOR);
        let factor = smooth(&(columns.clone(), change))?;
        layer_gains.push(
            factor
                .iter()
                .zip(&fix.force_gain)
                .map(|(f, base)| (f * base).clamp(lo, hi))
                .collect(),
        );
    }
    for (layer, gains) in fix.layers.iter_mut().zip(layer_gains) {
        layer.force_gain = gains;
    }
    for ((f, column), e) in local.iter_mut().zip(&columns_of).zip(sweeps) {
        if let (Some(f), Some(column), Some(raw)) = (f.as_mut(), column, &e.raw) {
            let tilt = raw.matched_shear_ratio.unwrap_or(f64::NAN);
            *f = fix.correct_local_force(*column, tilt, *f);
        }
    }
    Ok((fix, local))
}

/// The name of the optional file beside `tests.csv` that lists the sweeps
/// (docs/formats.md).
pub const SWEEPS_FILE: &str = "sweeps.csv";

/// Reads a dataset's `sweeps.csv`: empty when the dataset has none.
pub fn read_dataset_sweeps(dir: impl AsRef<Path>) -> Result<Vec<io::SweepRow>> {
    let path = dir.as_ref().join(SWEEPS_FILE);
    if !path.exists() {
        return Ok(Vec::new());
    }
    io::read_sweeps_csv(path)
}

/// Runs the pipeline on every sweep image, as [`extract_dataset`] does on
/// tests (each row as [`io::SweepRow::as_test`]: the sweep number is the
/// test's `repeat`). An image that cannot be read stops the run with an
/// error naming `sweeps.csv`, the row (as `test N`, from 0) and its frames.
pub fn extract_sweeps(
    dir: impl AsRef<Path>,
    sweeps: &[io::SweepRow],
    config: &ExtractorConfig,
    contact_point: ContactPointMethod,
    crop: Option<Roi>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Vec<Extraction>> {
    let rows: Vec<TestRow> = sweeps
        .iter()
        .enumerate()
        .map(|(i, r)| r.as_test(i))
        .collect();
    extract_dataset(dir, &rows, config, contact_point, crop, progress)
        .map_err(|e| e.context(format!("{SWEEPS_FILE}, rows counted from 0")))
}

/// Fraction of the weakest training presses' matched normal force below
/// which a patch is not a press ([`Calibration::min_normal_n`]).
pub const PRESS_FRACTION: f64 = 0.5;

/// The press threshold of a dataset: [`PRESS_FRACTION`] of the 1st percentile
/// of the matched inward normal force over the detected training tests at
/// the smallest commanded force; `None` if there is no such test or that
/// percentile is not positive.
fn press_threshold(extractions: &[Extraction], local: &[Option<[f64; 3]>]) -> Option<f64> {
    let tests: Vec<(f64, f64)> = extractions
        .iter()
        .zip(local)
        .filter(|(e, _)| e.row.split == Split::Train)
        .filter_map(|(e, f)| f.map(|f| (e.row.force_n, -f[2])))
        .collect();
    weakest_press_threshold(&tests)
}

/// [`press_threshold`] of `(commanded force, matched inward normal force)`
/// pairs.
fn weakest_press_threshold(tests: &[(f64, f64)]) -> Option<f64> {
    let lowest = tests.iter().map(|t| t.0).min_by(f64::total_cmp)?;
    let mut normals: Vec<f64> = tests
        .iter()
        .filter(|t| t.0 <= lowest * (1.0 + 1e-9))
        .map(|t| t.1)
        .collect();
    normals.sort_by(f64::total_cmp);
    let q = *normals.get(normals.len() / 100)?;
    (q.is_finite() && q > 0.0).then_some(PRESS_FRACTION * q)
}

/// Where a detected test's force is matched and rotated: its chord position
/// (mm) and the column its profile is matched at. Test and validation
/// tests, like a sensor at run time, use `cal`'s location and
/// [`Calibration::match_column`]. Training tests of an anchored model use
/// their true position and its anchor column, as the kernels were fitted:
/// the force maps then learn what the kernels get wrong, not the location
/// map's errors (which are largest at the outer training points, and would
/// otherwise teach the force maps corrections that do not hold elsewhere).
fn match_position(
    model: &ProfileModel,
    e: &Extraction,
    raw: &RawContact,
    cal: &Calibration,
) -> Result<(f64, f64)> {
    match &model.anchor {
        Some(map) if e.row.split == Split::Train => Ok((e.row.x_mm, map.column(e.row.x_mm))),
        _ => Ok((cal.location_of(raw)?[0], cal.match_column(model, raw)?)),
    }
}

/// The extractions of `split` in which a contact was detected.
/// The detected tests of a split that the profile model is fitted and
/// checked on (those that [`Extraction::fits`], as in [`trusted`]).
fn detected_in(extractions: &[Extraction], split: Split) -> Vec<&Extraction> {
    extractions
        .iter()
        .filter(|e| e.row.split == split && e.raw.is_some() && e.fits())
        .collect()
}

/// The extractions with every detected test's point moved as a sensor
/// moves it ([`ForceMatcher::relocate`] at `cal`'s match column); `None`
/// when none moves (the model has no anchor, say).
fn relocate(
    model: &ProfileModel,
    extractions: &[Extraction],
    cal: &Calibration,
) -> Result<Option<Vec<Extraction>>> {
    if model.anchor.is_none() {
        return Ok(None);
    }
    let mut matcher = ForceMatcher::new();
    let mut moves = Vec::new();
    for (i, e) in extractions.iter().enumerate() {
        if let Some(raw) = &e.raw {
            let before = cal.match_column(model, raw)?;
            let mut column = [before];
            matcher.relocate(model, &mut column, &e.profiles[0], &e.profiles[1], e.scale)?;
            if column[0] != before {
                moves.push((i, column[0] - before));
            }
        }
    }
    if moves.is_empty() {
        return Ok(None);
    }
    let mut out = extractions.to_vec();
    for (i, shift) in moves {
        if let Some(raw) = out[i].raw.as_mut() {
            raw.x_px += shift;
        }
    }
    Ok(Some(out))
}

/// The extractions with every detected column measured as a sensor with a
/// model of shear-free columns measures it
/// ([`Calibration::match_forces_with`]): moved where `cal`'s match
/// column is clearly misplaced ([`ForceMatcher::relocate`]), matched at
/// `cal`'s match column, then moved to the slope peak (smoothing
/// `sigma_px`) of the profile less its modelled tangential motion
/// ([`ForceMatcher::shear_free_columns`]).
fn shear_free_extractions(
    model: &ProfileModel,
    extractions: &[Extraction],
    cal: &Calibration,
    sigma_px: f64,
) -> Result<Vec<Extraction>> {
    let model = ProfileModel {
        shear_free_columns: true,
        ..model.clone()
    };
    let mut matcher = ForceMatcher::new();
    let mut out = extractions.to_vec();
    for e in &mut out {
        let Some(raw) = e.raw.as_mut() else {
            continue;
        };
        let (pu, pv) = (&e.profiles[0], &e.profiles[1]);
        let before = cal.match_column(&model, raw)?;
        let mut column = [before];
        matcher.relocate(&model, &mut column, pu, pv, e.scale)?;
        raw.x_px += column[0] - before;
        let mut one = [*raw];
        matcher.shear_free_columns_of_profiles(
            &model,
            &mut one,
            pu,
            pv,
            e.scale,
            sigma_px,
            |r| cal.match_column(&model, r),
        )?;
        raw.x_px = one[0].x_px;
    }
    Ok(out)
}

/// Each detected test's local force matched by `model` at the column
/// `column_of(extraction, raw)`.
fn match_forces<'a>(
    model: &ProfileModel,
    extractions: impl IntoIterator<Item = &'a Extraction>,
    column_of: impl Fn(&Extraction, &RawContact) -> Result<f64>,
) -> Result<Vec<Option<[f64; 3]>>> {
    let mut matcher = ForceMatcher::new();
    let mut forces = Vec::new();
    extractions
        .into_iter()
        .map(|e| {
            e.raw
                .map(|raw| {
                    let column = column_of(e, &raw)?;
                    matcher.measure(
                        model,
                        &[column],
                        &e.profiles[0],
                        &e.profiles[1],
                        e.scale,
                        &mut forces,
                    )?;
                    Ok(forces[0])
                })
                .transpose()
        })
        .collect()
}

/// `cal`'s column correction with the shear ratios of its straight part and
/// of its tilt layers taken from the sweep images' own first matches
/// ([`with_matched_ratios`], at `cal`'s straight-corrected columns), as a
/// sensor will measure them, instead of their true ratios: what the profile
/// match reads of a tilt before the force maps is not exactly the tilt, and
/// the layers are then looked up on the scale they will be looked up with.
/// `None` (nothing to change) without tilt layers.
fn matched_layer_ratios(
    model: &ProfileModel,
    sweeps: &[Extraction],
    groups: &TiltGroups,
    cal: &Calibration,
) -> Result<Option<ColumnCorrection>> {
    let Some(matched) = with_matched_ratios(model, sweeps, cal)? else {
        return Ok(None);
    };
    let Some(mut fix) = cal.column_correction.clone() else {
        return Ok(None);
    };
    let mut per_group = vec![(Vec::new(), Vec::new()); fix.layers.len() + 1];
    for (e, &g) in matched.iter().zip(&groups.of_image) {
        if let (Some(raw), Some(slot)) = (&e.raw, per_group.get_mut(g)) {
            if let Some(r) = raw.matched_shear_ratio {
                slot.0.push(raw.x_px);
                slot.1.push(r);
            }
        }
    }
    let grid = (
        fix.smoothing_px,
        fix.start_px,
        fix.step_px,
        fix.location_mm.len(),
    );
    fix.shear_ratio = Some(smoothed_ratios(&per_group[0].0, &per_group[0].1, grid)?);
    for (layer, (columns, ratios)) in fix.layers.iter_mut().zip(&per_group[1..]) {
        layer.shear_ratio = smoothed_ratios(columns, ratios, grid)?;
    }
    Ok(Some(fix))
}

/// A correction layer's shear ratios on the grid `(smoothing, start, step,
/// samples)`: the images' `ratios` at their `columns`, smoothed along the
/// columns [`SHEAR_RATIO_SMOOTHING`] times as widely as the offsets, their
/// median where no image is near.
fn smoothed_ratios(
    columns: &[f64],
    ratios: &[f64],
    (sigma, start, step, n): (f64, f64, f64, usize),
) -> Result<Vec<f64>> {
    let median = upper_median(ratios.iter().copied()).unwrap_or(0.0);
    smooth_on_grid(
        columns,
        ratios,
        median,
        SHEAR_RATIO_SMOOTHING * sigma,
        start,
        step,
        n,
    )
}

/// With a column correction that has tilt layers, `extractions` with each
/// detected contact's [`RawContact::matched_shear_ratio`] set from a first
/// match at `cal`'s straight-corrected column, as a sensor sets it
/// ([`Calibration::match_forces_with`]); `None` (nothing to set) without.
fn with_matched_ratios(
    model: &ProfileModel,
    extractions: &[Extraction],
    cal: &Calibration,
) -> Result<Option<Vec<Extraction>>> {
    if cal
        .column_correction
        .as_ref()
        .is_none_or(|c| c.layers.is_empty())
    {
        return Ok(None);
    }
    let mut out = extractions.to_vec();
    for e in &mut out {
        if let Some(raw) = e.raw.as_mut() {
            raw.matched_shear_ratio = None;
        }
    }
    let first = match_forces(model, &out, |_, raw| cal.match_column(model, raw))?;
    for (e, f) in out.iter_mut().zip(first) {
        if let Some(raw) = e.raw.as_mut() {
            raw.matched_shear_ratio = f.and_then(shear_ratio_of);
        }
    }
    Ok(Some(out))
}

/// Fits the profile model on the detected training tests once at their
/// measured columns and once per anchor map degree that
/// [`anchor_degrees`] keeps ([`ColumnMap`]), and keeps the anchored model
/// whose matched forces, rotated into the sensor frame at `cal`'s
/// locations, have the lowest validation MAE (summed over Fx, Fy, Fz),
/// unless the measured columns read the tests of every validation point
/// clearly closer ([`clearly_lower_at_every_point`]), or no anchor map can
/// be fitted.
fn fit_profile(
    extractions: &[Extraction],
    geometry: &SensorGeometry,
    crop: &Roi,
    options: ProfileFitOptions,
    cal: &Calibration,
) -> Result<ProfileModel> {
    let train = detected_in(extractions, Split::Train);
    // The anchor maps' points: each training test's protocol point, true
    // position and measured column.
    let located: Vec<(u32, (f64, f64))> = train
        .iter()
        .filter_map(|e| e.raw.map(|r| (e.row.point, (e.row.x_mm, r.x_px))))
        .collect();
    let points: Vec<(f64, f64)> = located.iter().map(|&(_, p)| p).collect();
    let degrees = anchor_degrees(&located, options.anchor_max_degree);
    let anchors = std::iter::once(None).chain(degrees.into_iter().map(Some));
    // The best anchored model (validation MAE, its per-test errors) and the
    // model at the measured columns with its per-test errors.
    let mut best: Option<(f64, Vec<Option<f64>>, ProfileModel)> = None;
    let mut measured: Option<(Vec<Option<f64>>, ProfileModel)> = None;
    let mut last_error = None;
    for degree in anchors {
        let anchor = match degree {
            None => None,
            Some(d) => match ColumnMap::fit(&points, d) {
                Ok(m) => Some(m),
                Err(e) => {
                    last_error = Some(e);
                    continue;
                }
            },
        };
        let model = match fit_profile_at(&train, geometry, crop, options, anchor) {
            Ok(m) => m,
            Err(e) => {
                last_error = Some(e);
                continue;
            }
        };
        let errors = validation_force_errors(&model, extractions, geometry, cal)?;
        if degree.is_none() {
            measured = Some((errors, model));
            continue;
        }
        let score = mean_of_known(&errors);
        if best.as_ref().is_none_or(|(b, _, _)| score < *b) {
            best = Some((score, errors, model));
        }
    }
    let model = match (best, measured, last_error) {
        (Some((_, anchored, model)), Some((at_measured, other)), _) => {
            let val_points: Vec<u32> = detected_in(extractions, Split::Val)
                .iter()
                .map(|e| e.row.point)
                .collect();
            if clearly_lower_at_every_point(&at_measured, &anchored, &val_points) {
                other
            } else {
                model
            }
        }
        (Some((_, _, model)), None, _) | (None, Some((_, model)), _) => model,
        (None, None, Some(e)) => return Err(e),
        (None, None, None) => {
            return Err(Error::param("profile", "no profile model candidate"));
        }
    };
    // The tails leave a single contact's match as it is, so the choice
    // above is the same with them; they are fitted once, for the model kept.
    let longest = train
        .iter()
        .map(|e| e.profiles[0].len() as f64 * e.scale)
        .fold(0.0, f64::max);
    let tail_px = options.tail_px.min(longest);
    if tail_px <= model.reach_px() {
        return Ok(model);
    }
    let samples = profile_samples(&train, geometry, model.anchor.as_ref(), model.spread);
    model.with_tail(&samples, options.tail_step_px, tail_px)
}

/// The profile samples of the training tests, each at its anchor column of
/// the true position (or at its measured column without an anchor map),
/// with their spread profiles when `spread` (the model then fits the
/// spread channel), else with the across motion's column sums alone.
fn profile_samples<'a>(
    train: &[&'a Extraction],
    geometry: &SensorGeometry,
    anchor: Option<&ColumnMap>,
    spread: bool,
) -> Vec<ProfileSample<'a>> {
    train
        .iter()
        .filter_map(|e| {
            let raw = e.raw.as_ref()?;
            let r = &e.row;
            Some(ProfileSample {
                column_px: anchor.map_or(raw.x_px, |a| a.column(r.x_mm)),
                profile_u: &e.profiles[0],
                profile_v: if spread {
                    &e.profiles[1]
                } else {
                    &e.profiles[1][..e.profiles[1].len().min(e.profiles[0].len())]
                },
                scale: e.scale,
                local_force: geometry.sensor_to_local(r.x_mm, [r.fx_n, r.fy_n, r.fz_n]),
                size_mm: Some(r.indenter_mm),
            })
        })
        .collect()
}

/// Fits the profile model on `train` with its kernels anchored by `anchor`
/// at the true positions (or at the measured columns without one).
fn fit_profile_at(
    train: &[&Extraction],
    geometry: &SensorGeometry,
    crop: &Roi,
    options: ProfileFitOptions,
    anchor: Option<ColumnMap>,
) -> Result<ProfileModel> {
    let samples = profile_samples(train, geometry, anchor.as_ref(), options.spread_channel);
    let size = if options.size_term {
        SizeTerm::for_sizes(samples.iter().filter_map(|s| s.size_mm))
    } else {
        None
    };
    // The position polynomial's variable runs over -1..1 across the crop.
    let half = 0.5 * crop.w as f64;
    let mut model = ProfileModel::fit_with_size(
        &samples,
        train.first().map_or(1.0, |e| e.scale),
        options.half_width_px,
        options.degree,
        half - 0.5,
        half.max(1.0),
        size,
    )?;
    model.anchor = anchor;
    Ok(model)
}

/// Per detected validation test (in order), the absolute error of
/// `model`'s matched force in the sensor frame summed over the three axes;
/// `None` where it matched none.
fn validation_force_errors(
    model: &ProfileModel,
    extractions: &[Extraction],
    geometry: &SensorGeometry,
    cal: &Calibration,
) -> Result<Vec<Option<f64>>> {
    let val = detected_in(extractions, Split::Val);
    let forces = match_forces(model, val.iter().copied(), |_, raw| {
        cal.match_column(model, raw)
    })?;
    val.iter()
        .zip(&forces)
        .map(|(e, f)| {
            let (Some(raw), Some(f)) = (e.raw, f) else {
                return Ok(None);
            };
            let x = cal.location_of(&raw)?[0];
            let f = geometry.local_to_sensor(x, *f);
            let r = &e.row;
            Ok(Some(
                (f[0] - r.fx_n).abs() + (f[1] - r.fy_n).abs() + (f[2] - r.fz_n).abs(),
            ))
        })
        .collect()
}

/// The mean of the known values (infinite without one).
fn mean_of_known(values: &[Option<f64>]) -> f64 {
    let known: Vec<f64> = values.iter().flatten().copied().collect();
    if known.is_empty() {
        f64::INFINITY
    } else {
        known.iter().sum::<f64>() / known.len() as f64
    }
}

/// How many times the best degree's root-mean-square miss of a left-out
/// point a column map's may be for [`anchor_degrees`] to keep it.
const ANCHOR_MISS_FACTOR: f64 = 2.0;

/// The degrees `1..=max_degree` of the column map ([`ColumnMap`]) through
/// the training tests' `(point, (x_mm, column_px))` worth trying: those
/// whose map, fitted without one protocol point, misses that point's mean
/// column by at most [`ANCHOR_MISS_FACTOR`] times the best degree's miss
/// (root mean square over the points, leave one point out). Every degree
/// with fewer than three points; a degree that cannot be fitted without
/// one of them is left out.
///
/// Why: the validation tests' forces, which choose among these, lie at
/// three of the protocol's points, and the force error there is mostly the
/// marker pattern under those three places. On a protocol-sized random
/// subset of the simulated strip's dataset (1065 tests, no sweeps) they
/// picked the straight map, which misses a left-out point's column by 4.0
/// px where the cubic misses it by 1.0 px (the camera's projection of the
/// arc is close to a cubic); random presses between the points read
/// 0.30-0.32 mm and Fz 0.085-0.103 N off with it, 0.21-0.22 mm and
/// 0.065-0.080 N with the cubic. On every simulated dataset measured the
/// straight and quadratic maps miss by 2.1-6.9 times the best degree's
/// root-mean-square miss (the closest call, 2.1, the straight map on a
/// second simulated sensor, whose best degree misses by 2.0 px).
fn anchor_degrees(located: &[(u32, (f64, f64))], max_degree: usize) -> Vec<usize> {
    let mut ids: Vec<u32> = located.iter().map(|&(p, _)| p).collect();
    ids.sort_unstable();
    ids.dedup();
    if ids.len() < 3 {
        return (1..=max_degree).collect();
    }
    let mut misses: Vec<(usize, f64)> = Vec::new();
    'degrees: for degree in 1..=max_degree {
        let mut sum_sq = 0.0;
        for &id in &ids {
            let others: Vec<(f64, f64)> = located
                .iter()
                .filter(|&&(p, _)| p != id)
                .map(|&(_, xy)| xy)
                .collect();
            let Ok(map) = ColumnMap::fit(&others, degree) else {
                continue 'degrees;
            };
            let held: Vec<f64> = located
                .iter()
                .filter(|&&(p, _)| p == id)
                .map(|&(_, (x, c))| map.column(x) - c)
                .collect();
            let mean = held.iter().sum::<f64>() / held.len() as f64;
            sum_sq += mean * mean;
        }
        let rms = (sum_sq / ids.len() as f64).sqrt();
        if rms.is_finite() {
            misses.push((degree, rms));
        }
    }
    let best = misses.iter().map(|m| m.1).fold(f64::INFINITY, f64::min);
    misses
        .iter()
        .filter(|m| m.1 <= ANCHOR_MISS_FACTOR * best)
        .map(|m| m.0)
        .collect()
}

/// How many standard errors below the other the mean of a paired
/// difference must lie for [`clearly_lower`].
const CLEARLY_LOWER_T: f64 = 2.0;

/// Whether the errors `a` are [`clearly_lower`] than `b` on the tests of
/// every point in `points` (the protocol point of each test, in the order
/// of the errors), each point tested on its own: false without a point.
///
/// Why per point: most of a force error belongs to the place (the marker
/// pattern under it), so the validation tests of one point are not
/// independent samples, and one point that reads much closer can carry a
/// test over all of them. On a protocol-sized random subset of the
/// simulated strip's dataset the measured columns read two of the three
/// validation points clearly closer than the cubic anchor map and the
/// third alike (t over all tests above 2), but put random presses between
/// the points 0.53-0.56 mm and Fz 0.085-0.106 N off against 0.20-0.22 mm
/// and 0.063-0.080 N with the anchor map kept. What it costs: with the markers
/// at one depth the measured columns read two validation points clearly
/// closer and the third (the middle one) not, so the anchor map is kept
/// there too, where the measured columns read random presses closer (Fz
/// 0.020 N against 0.031-0.033 N; two perches 0.012-0.022 N per contact
/// against 0.019-0.054 N).
fn clearly_lower_at_every_point(a: &[Option<f64>], b: &[Option<f64>], points: &[u32]) -> bool {
    // Per point, its tests' errors in their order.
    type Pairs = (Vec<Option<f64>>, Vec<Option<f64>>);
    let mut per_point: std::collections::BTreeMap<u32, Pairs> = Default::default();
    for ((x, y), &p) in a.iter().zip(b).zip(points) {
        let (xs, ys) = per_point.entry(p).or_default();
        xs.push(*x);
        ys.push(*y);
    }
    !per_point.is_empty() && per_point.values().all(|(xs, ys)| clearly_lower(xs, ys))
}

/// Whether the errors `a` are lower than `b` on the same tests (pairs where
/// both are known) by more than [`CLEARLY_LOWER_T`] standard errors of the
/// mean difference: a paired test, false with fewer than two pairs.
///
/// Used per validation point ([`clearly_lower_at_every_point`]).
fn clearly_lower(a: &[Option<f64>], b: &[Option<f64>]) -> bool {
    let d: Vec<f64> = a
        .iter()
        .zip(b)
        .filter_map(|(a, b)| Some(a.as_ref()? - b.as_ref()?))
        .collect();
    let n = d.len() as f64;
    if d.len() < 2 {
        return false;
    }
    let mean = d.iter().sum::<f64>() / n;
    let var = d.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1.0);
    let se = (var / n).sqrt();
    mean < 0.0 && -mean > CLEARLY_LOWER_T * se
}

/// How much the load cell's readings scatter between repetitions of the same
/// test, and what that costs any sensor scored against them.
///
/// The protocol repeats every test (same point, indenter, tilt and commanded
/// force) several times. Whatever the recorded force does between those
/// repetitions, the images cannot follow if the press itself was the same:
/// on the simulator it is the load cell's noise alone; on a real rig it also
/// holds the rig's own repeatability, so it is then an upper bound on the
/// noise. A sensor that read the applied force exactly would still score a
/// test MAE of about [`LoadCellSpread::mae_floor_n`] against the recordings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoadCellSpread {
    /// Pooled standard deviation of the recorded force within repetition
    /// groups, per axis (x, y, z), N.
    pub sigma_n: [f64; 3],
    /// Repetition groups with at least two tests.
    pub groups: usize,
    /// Degrees of freedom of the pooled estimate (tests minus groups).
    pub dof: usize,
}

impl LoadCellSpread {
    /// The expected absolute error of an exact sensor against the recorded
    /// force, per axis: `sigma * sqrt(2 / pi)` (Gaussian noise), N.
    pub fn mae_floor_n(&self) -> [f64; 3] {
        let k = (2.0 / std::f64::consts::PI).sqrt();
        self.sigma_n.map(|s| s * k)
    }
}

/// The [`LoadCellSpread`] of a dataset's rows: tests are grouped by split,
/// point, indenter, yaw, pitch and commanded force, and the recorded force's
/// variance within each group is pooled. `None` if no group holds two tests
/// (a dataset without repetitions says nothing about its load cell). Rows
/// with a non-finite recorded force are left out.
pub fn load_cell_spread(rows: &[TestRow]) -> Option<LoadCellSpread> {
    use std::collections::BTreeMap;
    // Exact keys: the values of one protocol come from one writer, so the
    // repetitions of a test carry the same decimal text.
    type Key = (usize, u32, u64, u64, u64, u64);
    let mut groups: BTreeMap<Key, Vec<[f64; 3]>> = BTreeMap::new();
    for r in rows {
        let f = [r.fx_n, r.fy_n, r.fz_n];
        if f.iter().any(|v| !v.is_finite()) {
            continue;
        }
        let key = (
            split_index(r.split),
            r.point,
            r.indenter_mm.to_bits(),
            r.yaw_deg.to_bits(),
            r.pitch_deg.to_bits(),
            r.force_n.to_bits(),
        );
        groups.entry(key).or_default().push(f);
    }
    let (mut sum_sq, mut n_groups, mut dof) = ([0.0f64; 3], 0usize, 0usize);
    for g in groups.values().filter(|g| g.len() >= 2) {
        let n = g.len() as f64;
        for (a, s) in sum_sq.iter_mut().enumerate() {
            let mean = g.iter().map(|f| f[a]).sum::<f64>() / n;
            *s += g.iter().map(|f| (f[a] - mean).powi(2)).sum::<f64>();
        }
        n_groups += 1;
        dof += g.len() - 1;
    }
    (dof > 0).then(|| LoadCellSpread {
        sigma_n: sum_sq.map(|s| (s / dof as f64).sqrt()),
        groups: n_groups,
        dof,
    })
}

/// The DIS preset whose parameters `config.flow` equals, or `custom`.
pub fn preset_name(config: &ExtractorConfig) -> String {
    use crate::flow::dis::{DisParams, DisPreset};
    DisPreset::ALL
        .iter()
        .find(|p| DisParams::preset(**p) == config.flow)
        .map_or_else(|| "custom".to_string(), |p| p.name().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::segment::{Shape, Thresholds};

    /// A calibration whose location is `x = (x2d - 800) / 5` mm, with no shear input.
    fn linear_location() -> Calibration {
        let g1 = Polynomial::raw(&["x2d"], vec![vec![0], vec![1]], vec![-160.0, 0.2]).unwrap();
        let g2 = Polynomial::raw(&["y2d"], vec![vec![0]], vec![0.0]).unwrap();
        let f = || {
            Polynomial::raw(
                &crate::calibration::FORCE_VARIABLES,
                vec![vec![0, 0, 1, 0, 0, 0]],
                vec![1.0],
            )
            .unwrap()
        };
        let setup = SensorSetup {
            geometry: SensorGeometry::default(),
            crop: Roi::new(0, 0, 1600, 200),
            thresholds: Thresholds {
                magnitude: 1.5,
                sum: 400.0,
                erode: 5,
                dilate: 9,
                shape: Shape::Rect,
            },
            pipeline: None,
        };
        Calibration::new(setup, [g1, g2, f(), f(), f()], None).unwrap()
    }

    /// A sweep image at the true chord position `x_mm` whose contact
    /// column was measured at `x_px` (or not at all).
    fn sweep_image(x_mm: f64, x_px: Option<f64>) -> Extraction {
        let row = io::SweepRow {
            sweep: 0,
            frame: String::new(),
            reference: String::new(),
            indenter_mm: 5.0,
            force_n: 2.0,
            x_mm,
            y_mm: 0.0,
            fx_n: 0.0,
            fy_n: 0.0,
            fz_n: -2.0,
        };
        Extraction {
            row: row.as_test(0),
            raw: x_px.map(|x_px| RawContact {
                x_px,
                y_px: 100.0,
                dn: 1.0,
                ..Default::default()
            }),
            patches: usize::from(x_px.is_some()),
            profiles: [Vec::new(), Vec::new()],
            scale: 1.0,
            beyond_markers: false,
            dots_followed: false,
            dot_fit_failed: false,
        }
    }

    /// A sweep image as [`sweep_image`], of sweep `sweep` whose load is
    /// tilted by `pitch_deg` along the strip (sensor frame).
    fn tilted_sweep_image(sweep: u32, pitch_deg: f64, x_mm: f64, x_px: Option<f64>) -> Extraction {
        let mut e = sweep_image(x_mm, x_px);
        let (s, c) = pitch_deg.to_radians().sin_cos();
        e.row.repeat = sweep;
        e.row.fx_n = 2.0 * s;
        e.row.fz_n = -2.0 * c;
        e
    }

    #[test]
    fn rest_pairs_pair_distinct_references_half_the_list_apart() {
        let row = |reference: &str| {
            let mut row = sweep_image(0.0, None).row;
            row.reference = reference.to_string();
            row
        };
        // Six distinct references, one shared by two tests.
        let rows: Vec<TestRow> = ["r5", "r0", "r3", "r1", "r4", "r2", "r3"]
            .into_iter()
            .map(row)
            .collect();
        let pairs = rest_pairs(&rows, 32);
        let want = |v: &[(&str, &str)]| -> Vec<(String, String)> {
            v.iter()
                .map(|(a, b)| (a.to_string(), b.to_string()))
                .collect()
        };
        assert_eq!(pairs, want(&[("r0", "r3"), ("r1", "r4"), ("r2", "r5")]));
        // At most `max`, spread over the list; none without two references.
        assert_eq!(rest_pairs(&rows, 2), want(&[("r0", "r3"), ("r1", "r4")]));
        assert_eq!(rest_pairs(&rows, 1), want(&[("r0", "r3")]));
        assert!(rest_pairs(&rows, 0).is_empty());
        assert!(rest_pairs(&[row("a"), row("a")], 32).is_empty());
        assert!(rest_pairs(&[], 32).is_empty());
        let many: Vec<TestRow> = (0..1000).map(|i| row(&format!("r{i:04}"))).collect();
        let pairs = rest_pairs(&many, MAX_REST_PAIRS);
        assert_eq!(pairs.len(), MAX_REST_PAIRS);
        assert!(pairs.iter().all(|(a, b)| a < b));
        assert_eq!(pairs[0], ("r0000".to_string(), "r0500".to_string()));
    }

    #[test]
    fn the_threshold_search_keeps_the_first_preset_that_sees_the_tests() {
        // `n` tests, the first `missed` without a contact.
        let tests = |n: usize, missed: usize| -> Vec<Extraction> {
            (0..n)
                .map(|i| sweep_image(0.0, (i >= missed).then_some(100.0)))
                .collect()
        };
        let rest = |with_contact| RestCheck {
            pairs: 8,
            with_contact,
        };
        let run = |tries: &[(usize, usize)]| {
            let mut auto = AutoThresholds::new();
            for &(missed, at_rest) in tries {
                assert!(auto.next_preset().is_some());
                auto.record(tests(100, missed), rest(at_rest)).unwrap();
            }
            assert_eq!(auto.next_preset(), None, "{tries:?}");
            let verdicts: Vec<_> = auto.tried().iter().map(|t| t.verdict).collect();
            let (kept, ex) = auto.finish().unwrap();
            (
                kept,
                ex.iter().filter(|e| e.raw.is_none()).count(),
                verdicts,
            )
        };
        use ThresholdPreset::{High, Low, Mid};
        use ThresholdVerdict::{Misses, Noisy, Sees};
        // `high` sees all but 5%: kept, nothing else tried.
        assert_eq!(run(&[(5, 0)]), (High, 5, vec![Sees]));
        // `high` misses 10%, `mid` 3%: `mid`.
        assert_eq!(run(&[(10, 0), (3, 0)]), (Mid, 3, vec![Misses, Sees]));
        // Each misses more than 5%: the most sensitive, `low`.
        assert_eq!(
            run(&[(40, 0), (20, 0), (8, 0)]),
            (Low, 8, vec![Misses, Misses, Misses])
        );
        // `mid` fires at rest: the search stops and keeps `high`.
        assert_eq!(run(&[(10, 0), (0, 1)]), (High, 10, vec![Misses, Noisy]));
        // Even `high` fires at rest: nothing less sensitive is offered.
        assert_eq!(run(&[(0, 2)]), (High, 0, vec![Noisy]));
        // Recording after the search is over is an error.
        let mut auto = AutoThresholds::new();
        auto.record(tests(10, 0), rest(0)).unwrap();
        assert!(auto.record(tests(10, 0), rest(0)).is_err());
        assert!(AutoThresholds::new().finish().is_none());
    }

    /// Training tests at ten protocol points 25 mm apart, five a point,
    /// each at `column(x)` plus a fixed pseudo-random scatter of up to
    /// `scatter_px` (the marker pattern under the place).
    fn located_tests(column: impl Fn(f64) -> f64, scatter_px: f64) -> Vec<(u32, (f64, f64))> {
        let mut out = Vec::new();
        for p in 0..10u32 {
            let x = -112.5 + 25.0 * f64::from(p);
            let place = scatter_px * ((f64::from(p) * 2.39).sin());
            for k in 0..5 {
                let test = 0.2 * ((f64::from(p * 5 + k) * 0.77).cos());
                out.push((p + 2, (x, column(x) + place + test)));
            }
        }
        out
    }

    #[test]
    fn anchor_degrees_leave_out_the_maps_that_miss_a_left_out_point() {
        // A cubic projection of the arc: the straight and quadratic maps
        // miss a left-out point by far more than the cubic; they go.
        let cubic = |x: f64| {
            let z = x / 114.0;
            800.0 + 570.0 * z - z * z + 15.0 * z * z * z
        };
        let kept = anchor_degrees(&located_tests(cubic, 0.5), 5);
        assert!(kept.contains(&3), "{kept:?}");
        assert!(!kept.contains(&1) && !kept.contains(&2), "{kept:?}");
        // A straight projection: the straight map is among those kept.
        let kept = anchor_degrees(&located_tests(|x| 800.0 + 5.0 * x, 0.5), 5);
        assert!(kept.contains(&1), "{kept:?}");
        // Fewer than three points: every degree is tried.
        let two: Vec<_> = located_tests(cubic, 0.5)
            .into_iter()
            .filter(|t| t.0 < 4)
            .collect();
        assert_eq!(anchor_degrees(&two, 5), vec![1, 2, 3, 4, 5]);
        // Four points: without one of them three positions are left, which
        // no map of degree 3 or more is determined by; those degrees go.
        let four: Vec<_> = located_tests(cubic, 0.5)
            .into_iter()
            .filter(|t| t.0 < 6)
            .collect();
        assert!(anchor_degrees(&four, 5).iter().all(|&d| d <= 2));
    }

    #[test]
    fn profile_choices_turn_off_what_the_defaults_fit_and_ask_the_rest() {
        let base = ProfileFitOptions::default();
        assert_eq!(base.with_choices(&ProfileChoices::default()), base);
        let all = ProfileChoices {
            measured_columns: true,
            relocation: Some(Relocation::Best),
            shear_free_columns: true,
            spread_channel: false,
            size_term: false,
            profile_tail: false,
        };
        let got = base.with_choices(&all);
        assert_eq!(got.anchor_max_degree, 0);
        assert_eq!(got.relocation, Some(Relocation::Best));
        assert!(got.shear_free_columns && !got.spread_channel && !got.size_term);
        assert_eq!(got.tail_px, 0.0);
        assert_eq!(
            (got.half_width_px, got.degree),
            (base.half_width_px, base.degree)
        );
        // What the defaults leave off, a choice to keep does not turn on.
        let bare = ProfileFitOptions {
            spread_channel: false,
            size_term: false,
            relocation: Some(Relocation::Clear),
            ..base
        };
        let kept = bare.with_choices(&ProfileChoices::default());
        assert!(!kept.spread_channel && !kept.size_term);
        assert_eq!(kept.relocation, Some(Relocation::Clear));
    }

    #[test]
    fn clearly_lower_at_every_point_tests_each_point_on_its_own() {
        let known = |v: &[f64]| v.iter().map(|&x| Some(x)).collect::<Vec<_>>();
        let points = [5, 5, 5, 5, 8, 8, 8, 8];
        let b = known(&[0.10, 0.20, 0.30, 0.40, 0.10, 0.20, 0.30, 0.40]);
        // Lower by 0.01 at both points: clearly lower.
        let a = known(&[0.09, 0.19, 0.29, 0.39, 0.09, 0.19, 0.29, 0.39]);
        assert!(clearly_lower_at_every_point(&a, &b, &points));
        // Far lower at point 5, no closer at point 8: not at every point,
        // though the test over all eight says clearly lower.
        let one = known(&[0.00, 0.10, 0.20, 0.30, 0.11, 0.19, 0.31, 0.39]);
        assert!(clearly_lower(&one, &b));
        assert!(!clearly_lower_at_every_point(&one, &b, &points));
        // No point: never.
        assert!(!clearly_lower_at_every_point(&[], &[], &[]));
    }

    #[test]
    fn clearly_lower_is_a_paired_test_of_the_known_pairs() {
        let known = |v: &[f64]| v.iter().map(|&x| Some(x)).collect::<Vec<_>>();
        let b = known(&[0.10, 0.20, 0.30, 0.40, 0.50, 0.60]);
        // Lower by 0.01 on every test: no spread, clearly lower.
        let a = known(&[0.09, 0.19, 0.29, 0.39, 0.49, 0.59]);
        assert!(clearly_lower(&a, &b));
        assert!(!clearly_lower(&b, &a));
        assert!(!clearly_lower(&b, &b));
        // Lower on average, but by less than two standard errors.
        let noisy = known(&[0.00, 0.30, 0.20, 0.45, 0.40, 0.62]);
        assert!(mean_of_known(&noisy) < mean_of_known(&b));
        assert!(!clearly_lower(&noisy, &b));
        // Only pairs with both errors count; fewer than two: never.
        let mut gaps = a.clone();
        for g in gaps.iter_mut().take(5) {
            *g = None;
        }
        assert!(!clearly_lower(&gaps, &b));
        assert!(!clearly_lower(&[], &[]));
        assert!(clearly_lower(&a[..2], &b[..2]));
        assert_eq!(mean_of_known(&[Some(1.0), None, Some(3.0)]), 2.0);
        assert_eq!(mean_of_known(&[None]), f64::INFINITY);
    }

    #[test]
    fn the_upper_median_skips_what_is_not_finite() {
        assert_eq!(upper_median([3.0, 1.0, 2.0]), Some(2.0));
        // Even counts: the upper of the middle two, as a sorted slice's
        // `len / 2`-th element.
        assert_eq!(upper_median([4.0, 1.0, 3.0, 2.0]), Some(3.0));
        assert_eq!(upper_median([f64::NAN, 5.0, f64::INFINITY, 1.0]), Some(5.0));
        assert_eq!(upper_median([f64::NAN]), None);
        assert_eq!(upper_median(std::iter::empty()), None);
    }

    #[test]
    fn a_layers_few_wild_images_are_clipped_and_the_rest_kept() {
        // A smooth place-to-place pattern, three images read 3 mm off, one NaN.
        let mut values: Vec<f64> = (0..200).map(|i| 0.2 * (i as f64 * 0.1).sin()).collect();
        let pattern = values.clone();
        for i in [50, 51, 52] {
            values[i] = -3.0;
        }
        values[100] = f64::NAN;
        clip_outliers(&mut values, LAYER_LOCATION_FLOOR_MM);
        // The band: median +- 3 robust sigmas of a sine of amplitude 0.2
        // (MAD about 0.14), so about 0.6 mm; the wild images end at its edge.
        for i in [50, 51, 52] {
            assert!(values[i] > -0.8 && values[i] < -0.3, "{}", values[i]);
        }
        assert!(values[100].is_nan());
        for (i, (v, p)) in values.iter().zip(&pattern).enumerate() {
            if ![50, 51, 52, 100].contains(&i) {
                assert_eq!(v, p, "image {i} moved");
            }
        }
        // Values all alike: the floor keeps the band open, nothing moves
        // within it, a value beyond it is clipped to it.
        let mut flat = vec![1.0; 20];
        flat[3] = 1.05;
        flat[4] = 2.0;
        clip_outliers(&mut flat, LAYER_GAIN_FLOOR);
        assert_eq!(flat[3], 1.05);
        assert!((flat[4] - (1.0 + LAYER_GAIN_FLOOR)).abs() < 1e-12);
        // Nothing finite: nothing to do, no panic.
        let mut none = vec![f64::NAN; 3];
        clip_outliers(&mut none, 0.1);
        assert!(none.iter().all(|v| v.is_nan()));
        clip_outliers(&mut [], 0.1);
    }

    #[test]
    fn sweeps_are_grouped_by_their_tilt() {
        let sweeps = vec![
            tilted_sweep_image(0, 0.0, 0.0, Some(800.0)),
            tilted_sweep_image(1, 15.0, 0.0, Some(800.0)),
            tilted_sweep_image(2, 0.4, 0.0, Some(800.0)),
            tilted_sweep_image(3, -15.0, 0.0, Some(800.0)),
            tilted_sweep_image(1, 15.0, 1.0, None),
            tilted_sweep_image(4, 14.0, 0.0, Some(800.0)),
        ];
        let TiltGroups {
            of_image: groups,
            tilts_deg: tilts,
        } = tilt_groups(&sweeps);
        // The straight sweeps share group 0; the others by increasing tilt;
        // tilts within a few degrees share a group.
        assert_eq!(groups, vec![0, 2, 0, 1, 2, 2]);
        assert_eq!(tilts.len(), 3);
        assert!(tilts[0].abs() < 0.5 && (tilts[1] + 15.0).abs() < 1e-9);
        assert!((tilts[2] - 14.5).abs() < 1e-9);
        assert_eq!(tilt_groups(&[]).tilts_deg.len(), 0);
    }

    #[test]
    fn tilted_sweeps_teach_the_location_of_a_tilted_press() {
        let mut cal = linear_location();
        // The measured column lags the truth by one pattern under a straight
        // load and by another under a tilted one.
        let straight_lag = |x_px: f64| 4.0 * (x_px / 9.0).sin();
        let tilted_lag = |x_px: f64| 4.0 * (x_px / 7.0).cos();
        let truth_px = |x_mm: f64| 800.0 + 5.0 * x_mm;
        let mut sweeps = Vec::new();
        for i in 0..=160 {
            let x = -40.0 + 0.5 * i as f64;
            let px = truth_px(x);
            sweeps.push(tilted_sweep_image(0, 0.0, x, Some(px + straight_lag(px))));
            sweeps.push(tilted_sweep_image(1, 15.0, x, Some(px + tilted_lag(px))));
        }
        let fix = location_correction(&sweeps, &tilt_groups(&sweeps), &cal, cal.setup.crop)
            .unwrap()
            .unwrap();
        fix.validate().unwrap();
        assert_eq!(fix.layers.len(), 1);
        assert_eq!(fix.layers[0].images, 161);
        // The layers' ratios: the loads' true shear ratios in the local frame.
        let geometry = cal.setup.geometry;
        let ratio_at = |x_mm: f64, pitch: f64| {
            let (s, c) = f64::to_radians(pitch).sin_cos();
            shear_ratio_of(geometry.sensor_to_local(x_mm, [2.0 * s, 0.0, -2.0 * c])).unwrap()
        };
        let layer = &fix.layers[0];
        let base = fix.shear_ratio.as_ref().unwrap();
        for x in [-30.0, 0.0, 25.0] {
            let col = truth_px(x) as usize;
            assert!((layer.shear_ratio[col] - ratio_at(x, 15.0)).abs() < 0.01);
            assert!((base[col] - ratio_at(x, 0.0)).abs() < 0.01);
        }
        cal.column_correction = Some(fix);
        // Between the images, each load's location is corrected by its own
        // tilt's offsets when the contact carries its matched shear ratio.
        let error = |lag: &dyn Fn(f64) -> f64, pitch: f64, tilt: bool| {
            let errors: Vec<f64> = (0..100)
                .map(|i| {
                    let x = -35.0 + 0.7 * i as f64 + 0.13;
                    let px = truth_px(x);
                    let raw = RawContact {
                        x_px: px + lag(px),
                        y_px: 100.0,
                        dn: 1.0,
                        matched_shear_ratio: tilt.then(|| ratio_at(x, pitch)),
                        ..Default::default()
                    };
                    (cal.location_of(&raw).unwrap()[0] - x).abs()
                })
                .collect();
            errors.iter().sum::<f64>() / errors.len() as f64
        };
        let tilted_plain = error(&tilted_lag, 15.0, false);
        let tilted = error(&tilted_lag, 15.0, true);
        let straight = error(&straight_lag, 0.0, true);
        assert!(tilted_plain > 0.4, "{tilted_plain}");
        assert!(tilted < tilted_plain / 3.0, "{tilted_plain} -> {tilted}");
        assert!(straight < 0.15, "{straight}");
        // A tilt with no detected image is an error, as for straight sweeps.
        let mut blind = sweeps.clone();
        for e in blind.iter_mut().filter(|e| e.row.repeat == 1) {
            e.raw = None;
        }
        assert!(
            location_correction(
                &blind,
                &tilt_groups(&blind),
                &linear_location(),
                cal.setup.crop
            )
            .is_err()
        );
    }

    #[test]
    fn sweeps_teach_the_location_what_the_marker_pattern_does() {
        let mut cal = linear_location();
        // The measured column lags the truth by a pattern that changes every
        // ~30 px (6 mm), as the flow's steepest rise sticks to the markers.
        let lag = |x_px: f64| 4.0 * (x_px / 9.0).sin();
        let truth_px = |x_mm: f64| 800.0 + 5.0 * x_mm;
        // One sweep image every 0.5 mm from -40 to 40 mm, and a few misses.
        let sweeps: Vec<Extraction> = (0..=160)
            .map(|i| {
                let x = -40.0 + 0.5 * i as f64;
                let seen = i % 37 != 5;
                sweep_image(x, seen.then(|| truth_px(x) + lag(truth_px(x))))
            })
            .collect();
        let before: Vec<f64> = (0..100)
            .map(|i| {
                let x = -35.0 + 0.7 * i as f64 + 0.13;
                (cal.location(truth_px(x) + lag(truth_px(x)), 100.0).unwrap()[0] - x).abs()
            })
            .collect();
        let fix = location_correction(&sweeps, &tilt_groups(&sweeps), &cal, cal.setup.crop)
            .unwrap()
            .unwrap();
        assert_eq!(fix.images, 161 - 5);
        assert_eq!(fix.smoothing_px, DEFAULT_SMOOTHING_PX);
        assert!(fix.force_gain.iter().all(|g| *g == 1.0));
        // No sweep near column 100 (x = -140 mm): no offset there.
        assert_eq!(fix.location_mm_at(100.0, 0.0), 0.0);
        cal.column_correction = Some(fix);
        // At positions between the sweep's images, the location error falls
        // to a small part of what it was.
        let after: Vec<f64> = (0..100)
            .map(|i| {
                let x = -35.0 + 0.7 * i as f64 + 0.13;
                (cal.location(truth_px(x) + lag(truth_px(x)), 100.0).unwrap()[0] - x).abs()
            })
            .collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        assert!(mean(&before) > 0.4, "{}", mean(&before));
        assert!(
            mean(&after) < mean(&before) / 3.0,
            "{} -> {}",
            mean(&before),
            mean(&after)
        );
        // Coarse sweeps (two over the same positions every 5 mm, 25 px) are
        // smoothed over their spacing: between their images the correction
        // is not back at zero.
        let coarse: Vec<Extraction> = (0..=33)
            .map(|i| {
                let i = i % 17;
                let x = -40.0 + 5.0 * i as f64;
                sweep_image(x, Some(truth_px(x) + lag(truth_px(x))))
            })
            .collect();
        let wide = location_correction(
            &coarse,
            &tilt_groups(&coarse),
            &linear_location(),
            cal.setup.crop,
        )
        .unwrap()
        .unwrap();
        assert!(wide.smoothing_px > 10.0, "{}", wide.smoothing_px);
        let between = truth_px(2.5);
        assert!(
            wide.location_mm_at(between, 0.0).abs()
                > 0.1 * wide.location_mm_at(truth_px(0.0), 0.0).abs()
        );
        // Without sweeps nothing is fitted; with no detected image it is an error.
        assert!(
            location_correction(&[], &tilt_groups(&[]), &cal, cal.setup.crop)
                .unwrap()
                .is_none()
        );
        let blind = vec![sweep_image(0.0, None); 3];
        assert!(location_correction(&blind, &tilt_groups(&blind), &cal, cal.setup.crop).is_err());
    }

    #[test]
    fn without_sweeps_contacts_go_where_their_motion_fits_best() {
        assert_eq!(relocation_for(None, false), Relocation::Best);
        assert_eq!(relocation_for(None, true), Relocation::Clear);
        for asked in [Relocation::Clear, Relocation::Best] {
            for sweeps in [false, true] {
                assert_eq!(relocation_for(Some(asked), sweeps), asked);
            }
        }
        // Option files from before the setting ask for nothing.
        let old: ProfileFitOptions = serde_json::from_str(
            r#"{"half_width_px": 300.0, "degree": 2, "anchor_max_degree": 5, "size_term": true}"#,
        )
        .unwrap();
        assert_eq!(old.relocation, None);
    }

    #[test]
    fn the_strip_gets_smooth_force_maps_and_a_flat_sensor_the_defaults() {
        let strip = FitOptions::for_geometry(&SensorGeometry::default());
        assert_eq!(strip.displacement_max_order, STRIP_DISPLACEMENT_ORDER);
        assert_eq!(strip.shear_max_order, Some(STRIP_SHEAR_ORDER));
        assert!(!strip.force_use_y2d);
        assert!(strip.profile.is_some_and(|p| p.size_term));
        let flat = FitOptions::for_geometry(&SensorGeometry::Flat(crate::geometry::FlatSurface {
            length_mm: 24.0,
            width_mm: 18.0,
        }));
        let defaults = FitOptions::default();
        assert_eq!(flat.displacement_max_order, defaults.displacement_max_order);
        assert_eq!(flat.shear_max_order, defaults.shear_max_order);
        assert!(flat.force_use_y2d);
        assert_eq!(flat.profile, None);
    }

    #[test]
    fn sweeps_on_a_sensor_that_locates_in_2d_are_an_error() {
        let flat = SensorGeometry::Flat(crate::geometry::FlatSurface {
            length_mm: 24.0,
            width_mm: 18.0,
        });
        let e = fit_dataset_with_sweeps(
            &[],
            &[sweep_image(0.0, Some(800.0))],
            &ExtractorConfig::default(),
            ContactPointMethod::DEFAULT,
            Roi::new(0, 0, 320, 240),
            flat,
            &FitOptions::default(),
        )
        .unwrap_err();
        assert!(e.to_string().contains("2-D"), "{e}");
    }

    #[test]
    fn tests_beyond_the_markers_are_fitted_on_only_with_their_dots_followed() {
        // Every combination of split, beyond the markers and dots followed,
        // each test's sample marked by its index.
        let mut ex = Vec::new();
        let mut samples = Vec::new();
        for split in [Split::Train, Split::Val, Split::Test] {
            for (beyond_markers, dots_followed) in
                [(false, false), (false, true), (true, false), (true, true)]
            {
                let mut e = sweep_image(0.0, Some(800.0));
                e.row.test = ex.len();
                e.row.split = split;
                e.beyond_markers = beyond_markers;
                e.dots_followed = dots_followed;
                let mut s = Sample::from_test(&e.row, e.raw.as_ref().unwrap());
                s.x_mm = ex.len() as f64;
                samples.push(Some(s));
                ex.push(e);
            }
        }
        // One undetected test: no sample, nothing fitted.
        ex.push(sweep_image(0.0, None));
        samples.push(None);
        let fitted: Vec<usize> = trusted(&ex, &samples)
            .iter()
            .map(|s| s.x_mm as usize)
            .collect();
        // Train and validation: all but the one beyond the markers whose
        // dots were not all followed; the test split keeps every test.
        assert_eq!(fitted, vec![0, 1, 3, 4, 5, 7, 8, 9, 10, 11]);
        assert!(ex[2].beyond_markers && !ex[2].dots_followed && !ex[2].fits());
        assert!(ex[3].fits() && ex[1].fits() && ex[0].fits());
        let checked: Vec<usize> = detected_in(&ex, Split::Val)
            .iter()
            .map(|e| e.row.test)
            .collect();
        assert_eq!(checked, vec![4, 5, 7]);
    }

    #[test]
    fn spot_checks_count_their_misses_but_not_in_the_detection_limit() {
        // Every split, one test detected and one missed each; the spot
        // checks at forces of their own.
        let mut ex = Vec::new();
        let mut samples = Vec::new();
        for (split, force) in [
            (Split::Train, 1.0),
            (Split::Val, 1.0),
            (Split::Test, 1.5),
            (Split::Spot, 0.73),
        ] {
            for found in [true, false] {
                let mut e = sweep_image(0.0, found.then_some(800.0));
                e.row.split = split;
                e.row.force_n = force;
                samples.push(e.raw.as_ref().map(|r| Sample::from_test(&e.row, r)));
                ex.push(e);
            }
        }
        let (misses, found) = detections(&ex, &samples);
        assert_eq!(misses, [1, 1, 1, 1]);
        assert_eq!(
            found,
            vec![
                (1.0, true),
                (1.0, false),
                (1.0, true),
                (1.0, false),
                (1.5, true),
                (1.5, false)
            ]
        );
    }

    #[test]
    fn the_press_threshold_is_half_the_weakest_presses_normal() {
        // 200 presses at 0.5 N matching 0.40..0.60 N, and stronger ones.
        let mut t: Vec<(f64, f64)> = (0..200).map(|i| (0.5, 0.40 + 0.001 * i as f64)).collect();
        t.extend((0..50).map(|i| (1.0, 0.9 + 0.001 * i as f64)));
        // 1st percentile of the 0.5 N ones: the 3rd smallest, 0.402.
        let th = weakest_press_threshold(&t).unwrap();
        assert!((th - 0.5 * 0.402).abs() < 1e-12, "{th}");
        // Nothing to go on, or a non-positive normal: no threshold.
        assert_eq!(weakest_press_threshold(&[]), None);
        assert_eq!(weakest_press_threshold(&[(0.5, -0.1)]), None);
        assert_eq!(weakest_press_threshold(&[(0.5, f64::NAN)]), None);
    }
}
