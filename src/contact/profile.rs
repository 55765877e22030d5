//! Forces from the along-arc motion profile, by matched kernels.
//!
//! The rods and perches this sensor is built for lie across the skin's
//! width, so the flow summed over the strip's height, a profile along the
//! arc, holds what the contacts did. Elastic motion is linear in the load:
//! the profile of a frame is, to a good approximation, the sum over its
//! contacts of each contact's local force components (tangential, across,
//! normal) times a response kernel that depends on where along the arc the
//! contact is. [`ProfileModel`] learns those kernels from a characterization
//! dataset (one contact per test, true forces known); [`ForceMatcher`] then
//! solves, per frame, for the force components of every contact at once by
//! least squares, so that two close contacts share out their overlapping
//! motion instead of each summing the other's.
//!
//! Why not the paper's sums of the patch's flow: a sum over a box mixes the
//! normal and tangential responses, is cut by the box, and takes in a
//! neighbour's motion; the central press of the normal load moves the
//! markers along the arc little, so its sum is a weak, noisy observable.
//! The matched kernel uses the whole shape of the motion, tails included.
//!
//! Profiles are in full-resolution units, whatever the flow's grid: cell `j`
//! of a flow with `scale` pixels per cell lies at pixel `(j + 0.5) * scale -
//! 0.5` and holds `scale` times the sum of its column (the flow integrated
//! over the strip's height), so a model fitted at one flow scale applies at
//! another.

use ndarray::ArrayView2;
use serde::{Deserialize, Serialize};

use crate::contact::RawContact;
use crate::error::{Error, Result};

/// The profile of a flow component: per column, the sum over all rows times
/// `scale` (the component integrated over the height, full-resolution
/// units), into `out`.
pub fn column_profile_into(component: ArrayView2<'_, f32>, scale: f64, out: &mut Vec<f64>) {
    out.clear();
    out.resize(component.ncols(), 0.0);
    add_row_weighted_sums(component, scale, |_| 1.0, out);
}

/// Per column of `component`, the sum over its rows of `weight(row)` times
/// the component, times `scale`, added to `out` (one cell per column).
fn add_row_weighted_sums(
    component: ArrayView2<'_, f32>,
    scale: f64,
    weight: impl Fn(usize) -> f64,
    out: &mut [f64],
) {
    let n = component.ncols();
    if n == 0 || component.nrows() == 0 {
        return;
    }
    // Plain row slices are several times cheaper than the strided iterator
    // (no copy for a standard-layout flow plane, the usual case).
    let component = component.as_standard_layout();
    let rows = component.as_slice().expect("standard layout is contiguous");
    for (y, row) in rows.chunks_exact(n).enumerate() {
        let w = weight(y) * scale;
        for (o, &x) in out.iter_mut().zip(row) {
            *o += w * f64::from(x);
        }
    }
}

/// The weight of the spread profile's equations in a force match against
/// those of the column sums: the spread profile weighs each row by its
/// signed distance from the middle row in units of `1 / SPREAD_WEIGHT` of
/// half the height. Measured on the simulated strip (random presses,
/// calibrations fitted without sweeps): 2 read the normal force closest,
/// 1 and 3 less close, 4 worse than without the channel.
pub const SPREAD_WEIGHT: f64 = 2.0;

/// The spread profile of the across motion `v`: per column, the first
/// moment of `v` about the grid's middle row, each row weighted by its
/// signed distance from it in units of half the height times
/// [`SPREAD_WEIGHT`], times `scale` (full-resolution units, as
/// [`column_profile_into`]), into `out`.
///
/// A press squeezes the gel out sideways, away from the centre line on both
/// sides, which the column sums cancel and the moment keeps (see
/// [`ProfileModel::spread`]).
pub fn spread_profile_into(v: ArrayView2<'_, f32>, scale: f64, out: &mut Vec<f64>) {
    out.clear();
    out.resize(v.ncols(), 0.0);
    spread_profile_of(v, scale, out);
}

/// [`spread_profile_into`] added to `out`, one cell per column of `v`.
fn spread_profile_of(v: ArrayView2<'_, f32>, scale: f64, out: &mut [f64]) {
    let h = v.nrows() as f64;
    let (middle, half) = ((h - 1.0) / 2.0, (h / 2.0).max(0.5));
    add_row_weighted_sums(
        v,
        scale,
        |y| SPREAD_WEIGHT * (y as f64 - middle) / half,
        out,
    );
}

/// The across-motion profiles a [`ProfileModel`] is matched on: the column
/// sums of `v` ([`column_profile_into`]) and, with `spread`, its spread
/// profile ([`spread_profile_into`]) after them, into `out` (twice the
/// columns long then).
pub fn across_profiles_into(v: ArrayView2<'_, f32>, scale: f64, spread: bool, out: &mut Vec<f64>) {
    column_profile_into(v, scale, out);
    if spread {
        let n = out.len();
        out.resize(2 * n, 0.0);
        spread_profile_of(v, scale, &mut out[n..]);
    }
}

/// Whether an across profile of `v_len` cells carries the spread profile
/// after the column sums of a profile along x of `u_len` cells
/// ([`across_profiles_into`]).
fn carries_spread(u_len: usize, v_len: usize) -> bool {
    u_len > 0 && v_len == 2 * u_len
}

/// The channels of a pair of profiles (see [`channels`]).
#[derive(Clone, Copy)]
struct Channels<'a> {
    all: [&'a [f64]; 3],
    len: usize,
}

impl<'a> Channels<'a> {
    fn as_slice(&self) -> &[&'a [f64]] {
        &self.all[..self.len]
    }
}

/// The channels of a pair of profiles: the motion along x, the column sums
/// of the motion along y and, when `profile_v` is twice as long as
/// `profile_u` ([`across_profiles_into`] with the spread), the spread
/// profile. `None` for lengths that are neither.
fn channels<'a>(profile_u: &'a [f64], profile_v: &'a [f64]) -> Option<Channels<'a>> {
    let n = profile_u.len();
    if profile_v.len() == n {
        Some(Channels {
            all: [profile_u, profile_v, &[]],
            len: 2,
        })
    } else if carries_spread(n, profile_v.len()) {
        Some(Channels {
            all: [profile_u, &profile_v[..n], &profile_v[n..]],
            len: 3,
        })
    } else {
        None
    }
}

/// One training contact for [`ProfileModel::fit`].
#[derive(Clone, Copy, Debug)]
pub struct ProfileSample<'a> {
    /// The contact's measured column, full-resolution pixels.
    pub column_px: f64,
    /// Profile of the flow along x ([`column_profile_into`]).
    pub profile_u: &'a [f64],
    /// Profiles of the flow along y ([`across_profiles_into`]): its column
    /// sums, followed by its spread profile when the model is to have the
    /// spread channel ([`ProfileModel::spread`]).
    pub profile_v: &'a [f64],
    /// Flow grid scale of the profiles (full-resolution pixels per cell).
    pub scale: f64,
    /// True force in the local frame at the contact: tangential, across,
    /// normal (outward; a press is negative), N.
    pub local_force: [f64; 3],
    /// Size of the indenter that pressed, mm: needed when the model is
    /// fitted with a [`SizeTerm`], ignored otherwise.
    pub size_mm: Option<f64>,
}

/// The indenter-size term of a [`ProfileModel`]: a fourth response kernel,
/// to the normal force times `(size_mm - centre_mm) / scale_mm`.
///
/// Why: one set of kernels for every indenter fits the mean footprint. A
/// wider indenter spreads its motion wider, and matched against the mean
/// kernel its normal force reads low; by more the harder it presses, as its
/// footprint grows with the load. With the size kernel the match has a
/// second shape to explain the width with, and the normal force no longer
/// depends on which indenter pressed. At run time the size is not known: it
/// is one more unknown per contact, solved with the forces.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SizeTerm {
    /// Size the term is centred on (the training indenters' mean), mm.
    pub centre_mm: f64,
    /// Size scale (half the training indenters' range), mm.
    pub scale_mm: f64,
}

/// Response kernels of the motion profile to a unit local force, as smooth
/// functions of the contact's column (see the module docs).
///
/// The kernel of channel `c` (0: flow along x, 1: along y) and force
/// component `k` (tangential, across, normal) at offset `t` pixels from a
/// contact at column `x` is `sum_m kernels[c][k * (degree + 1) + m][i] *
/// ((x - centre_px) / span_px)^m`, with `t = (i - half_width) * step_px`
/// (linear between samples, zero beyond `half_width` samples).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProfileModel {
    /// Spacing of the kernel samples, full-resolution pixels.
    pub step_px: f64,
    /// Samples on each side of the contact.
    pub half_width: usize,
    /// Column the position polynomial is centred on, pixels.
    pub centre_px: f64,
    /// Column span that the position polynomial's variable is divided by, pixels.
    pub span_px: f64,
    /// Degree of the position polynomial.
    pub degree: usize,
    /// Kernel samples: `kernels[channel][component * (degree + 1) + m]`.
    pub kernels: Vec<Vec<Vec<f64>>>,
    /// Where the kernels are anchored: the column of a contact at a chord
    /// position, as fitted on the training tests. With it, a contact's
    /// profile is matched at the column of its calibrated location
    /// ([`ColumnMap::column`]) instead of at its measured column (see
    /// [`ColumnMap`] for why); `None` (older files): at the measured column.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub anchor: Option<ColumnMap>,
    /// The indenter-size term: with it, `kernels[c]` holds a fourth
    /// component's `degree + 1` kernels after the three forces' ([`SizeTerm`]).
    /// `None` (older files): three components.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size: Option<SizeTerm>,
    /// The kernels' far tails ([`ProfileTail`]): the response beyond
    /// [`ProfileModel::reach_px`], where another contact's equations may
    /// lie. `None` (older files, or fitted without): no response there.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tail: Option<ProfileTail>,
    /// When [`ForceMatcher::relocate_contacts`] moves a contact's match
    /// column ([`Relocation`]). Older files: [`Relocation::Clear`].
    #[serde(default, skip_serializing_if = "Relocation::is_clear")]
    pub relocation: Relocation,
    /// Whether a contact's column is measured again, after a first match,
    /// at the steepest rise of the profile less every contact's modelled
    /// tangential motion ([`ForceMatcher::shear_free_columns`]), before the
    /// location and the force are read. A calibration fitted so measures
    /// its training columns the same way. `false` (older files): the
    /// column stays where the slope peak put it.
    ///
    /// Why: a tangential load adds an even bump to the along-arc motion,
    /// whose slope rises on one side of the contact. Under a wide rod the
    /// normal load's slope peak is flat-topped, and the bump's slope beside
    /// it can match it: the measured column then jumps between the two, by
    /// up to 26 px (5 mm) on the simulated strip for a 10 mm rod pitched 13
    /// degrees, and the normal force read there follows it (1.1 N off at
    /// 2.1 N). Less the modelled bump, the slope peaks at the load line.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub shear_free_columns: bool,
    /// Whether the model has a third channel, the spread profile
    /// ([`spread_profile_into`]): `kernels` and the tail's then hold three
    /// channels, and the across-motion profile a model is matched on must
    /// carry the spread profile after its column sums
    /// ([`across_profiles_into`]). `false` (older files): two channels.
    ///
    /// Why: the motion along the arc alone confuses a normal load with a
    /// tangential one at a slightly other column (the normal response is
    /// odd about the contact, its shift by a pixel or two is an even bump
    /// like the tangential response), so the normal force read there
    /// follows every pixel the column is off. A rod pressed in also
    /// squeezes the gel out sideways, away from the strip's centre line on
    /// both sides; a load along the arc does not. The column sums of the
    /// across motion cancel that spreading; its first moment about the
    /// middle row keeps it, an observable of the normal load alone.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub spread: bool,
}

/// When [`ForceMatcher::relocate_contacts`] moves a contact's match column
/// to the column whose kernel match explains its motion best.
///
/// Why two modes: the measured column (the profile's steepest rise) sticks
/// to the markers under the contact and jumps between them, by up to 3 px
/// (0.6 mm) on the simulated strip as a rod moves along it, and the force
/// matched there reads low by up to 10%. A calibration fitted with sweeps
/// learns those jumps per column ([`crate::calibration::correction`]) and
/// needs the measured column to stay as it was measured; it moves a
/// contact only when the measured point is clearly wrong (`Clear`). Without
/// sweeps nothing corrects the jumps, and the best-fitting column, found to
/// a fraction of a pixel, follows the rod more closely (`Best`: on a rod
/// moved along the simulated strip, 0.7 px of scatter against 1.2 px).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Relocation {
    /// Only when the best column within the search radius leaves a residual
    /// [`RELOCATE_MIN_GAIN`] smaller and lies at least
    /// [`RELOCATE_MIN_SHIFT_OF_RADIUS`] of the radius away: a misplaced
    /// point, not the residual's wobble.
    #[default]
    Clear,
    /// Always to the column of least residual within the search radius,
    /// refined to a fraction of a pixel (every profile cell counts).
    Best,
}

impl Relocation {
    /// Whether this is the default, [`Relocation::Clear`].
    pub fn is_clear(&self) -> bool {
        *self == Relocation::Clear
    }
}

/// The far tails of a [`ProfileModel`]'s kernels, sampled coarser than the
/// kernels themselves.
///
/// Why: on a soft, thick gel a press moves the skin far beyond the reach
/// over which its force is matched (on the simulated strip a straight
/// press still moves the markers by an eighth to a fifth of its peak 500 px
/// away). A contact's
/// equations are the profile cells within the model's reach, and with a
/// single contact nothing else is needed. With two, the cells about one
/// hold the other's far motion; without a kernel for it, the first
/// contact's unknowns take it in (two perches 110 mm apart read 0.1-0.2 N
/// of tangential force that is not there). With the tails, every contact's
/// response is modelled over every equation, and a single contact's match
/// is exactly as without them.
///
/// Sample `i` of a tail kernel lies at offset `(i - half_width) * step_px`,
/// with the same layout and position polynomial as
/// [`ProfileModel::kernels`]; it is used only beyond the model's reach.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProfileTail {
    /// Spacing of the tail samples, full-resolution pixels.
    pub step_px: f64,
    /// Samples on each side of the contact.
    pub half_width: usize,
    /// Tail samples: `kernels[channel][component * (degree + 1) + m]`;
    /// 0 at offsets the training data did not determine.
    pub kernels: Vec<Vec<Vec<f64>>>,
}

/// A smooth map from a contact's chord position (mm) to the image column
/// its kernels are anchored at: a polynomial least-squares fit of the
/// measured columns of the training tests against their true positions.
///
/// Why anchor kernels there rather than at each test's measured column: the
/// measured column moves with the shear (a tilted press shifts the profile's
/// steepest rise by a few pixels) and with the marker pattern under the
/// contact. Kernels fitted at such columns are smeared, and smeared in step
/// with the tangential force, which mixes the normal and tangential
/// responses. At the smooth map of the true positions the training profiles
/// line up; at run time a contact is matched at the map of its calibrated
/// location, which the location map already corrects for shear. On the
/// simulator's protocol this took the normal force's test MAE from 0.145 N
/// to 0.087 N (before the force maps).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ColumnMap {
    /// Chord position scale: the polynomial's variable is `x_mm / scale_mm`.
    pub scale_mm: f64,
    /// Coefficients, constant term first, of the column in pixels.
    pub coefficients: Vec<f64>,
}

impl ColumnMap {
    /// Least-squares polynomial of `degree` (1..=[`MAX_PROFILE_DEGREE`])
    /// through `(x_mm, column_px)` pairs. Errors on too few or non-finite
    /// points or a singular fit.
    pub fn fit(points: &[(f64, f64)], degree: usize) -> Result<Self> {
        if !(1..=MAX_PROFILE_DEGREE).contains(&degree) {
            return Err(Error::param(
                "degree",
                format!("column map degree must be 1..=6, got {degree}"),
            ));
        }
        if let Some(p) = points
            .iter()
            .find(|p| !(p.0.is_finite() && p.1.is_finite()))
        {
            return Err(Error::param(
                "points",
                format!("non-finite column map point {p:?}"),
            ));
        }
        let n = degree + 1;
        if points.len() < 2 * n {
            return Err(calibration_error(format!(
                "column map: {} points for degree {degree}; need at least {}",
                points.len(),
                2 * n
            )));
        }
        let scale_mm = points
            .iter()
            .map(|p| p.0.abs())
            .fold(0.0, f64::max)
            .max(1.0);
        let mut ata = vec![0.0; n * n];
        let mut atb = vec![0.0; n];
        let mut row = vec![0.0; n];
        for &(x, c) in points {
            let z = x / scale_mm;
            let mut p = 1.0;
            for r in row.iter_mut() {
                *r = p;
                p *= z;
            }
            accumulate(&mut ata, &mut atb, &row, c);
        }
        let coefficients = solve(&mut ata, &mut atb, n).ok_or_else(|| {
            calibration_error(format!(
                "column map: the training positions do not determine a degree-{degree} polynomial"
            ))
        })?;
        Ok(ColumnMap {
            scale_mm,
            coefficients,
        })
    }

    /// The anchor column, pixels, of a contact at chord position `x_mm`.
    pub fn column(&self, x_mm: f64) -> f64 {
        let z = x_mm / self.scale_mm;
        self.coefficients
            .iter()
            .rev()
            .fold(0.0, |acc, c| acc * z + c)
    }

    /// Checks the values of a loaded map.
    pub fn validate(&self) -> Result<()> {
        if !(self.scale_mm > 0.0 && self.scale_mm.is_finite())
            || self.coefficients.is_empty()
            || self.coefficients.iter().any(|c| !c.is_finite())
        {
            return Err(calibration_error(
                "profile model: the column map needs scale_mm > 0 and finite coefficients".into(),
            ));
        }
        if self.coefficients.len() > MAX_PROFILE_DEGREE + 1 {
            return Err(calibration_error(format!(
                "profile model: the column map has {} coefficients, at most {} (degree {MAX_PROFILE_DEGREE})",
                self.coefficients.len(),
                MAX_PROFILE_DEGREE + 1
            )));
        }
        Ok(())
    }
}

/// Force components per contact.
const COMPONENTS: usize = 3;

/// Unknowns per contact at most: the three forces and the size term.
const MAX_UNKNOWNS: usize = COMPONENTS + 1;

/// Largest degree of a [`ProfileModel`]'s position polynomial (and of a
/// [`ColumnMap`]): 6.
pub const MAX_PROFILE_DEGREE: usize = 6;

/// Largest number of kernel samples on each side of a contact in a
/// [`ProfileModel`]: 4096 (the default is 300 px at 2 px a sample, 150).
pub const MAX_PROFILE_HALF_WIDTH: usize = 4096;

/// Largest reach and sample spacing of a [`ProfileModel`]'s kernels,
/// full-resolution pixels: the largest frame side,
/// [`crate::frame::MAX_FRAME_SIDE`].
pub const MAX_PROFILE_REACH_PX: f64 = crate::frame::MAX_FRAME_SIDE as f64;

/// How far a contact's match column may be moved by
/// [`ForceMatcher::relocate_contacts`], as a fraction of the kernels' reach
/// (300 px of reach: 37.5 px, about the half-width of the widest rod's
/// footprint on the strip).
pub const RELOCATE_RADIUS_OF_REACH: f64 = 0.125;

/// The least relative drop of the match's residual (sum of squares) for
/// which [`ForceMatcher::relocate_contacts`] moves a contact.
pub const RELOCATE_MIN_GAIN: f64 = 0.3;

/// The least move, as a fraction of the search radius, that
/// [`ForceMatcher::relocate_contacts`] makes: smaller ones are the
/// residual's ordinary wobble, not a misplaced point.
pub const RELOCATE_MIN_SHIFT_OF_RADIUS: f64 = 1.0 / 6.0;

/// Most passes of [`Relocation::Best`] over several contacts (each pass
/// searches every contact with the others' motion, matched at their latest
/// columns, taken out).
const RELOCATE_BEST_PASSES: usize = 3;

/// [`Relocation::Best`] over several contacts stops once no column moved
/// by more than this in a pass, pixels.
const RELOCATE_BEST_SETTLED_PX: f64 = 0.02;

/// The coarse search's step in [`ForceMatcher::relocate_contacts`], pixels.
const RELOCATE_COARSE_STEP: usize = 4;

impl ProfileModel {
    /// Fits the kernels to `samples` by least squares, sample offset by
    /// sample offset (each offset's kernels are a small linear problem in
    /// the samples' forces times the position polynomial).
    ///
    /// `half_width_px` is how far each side of a contact the kernels reach,
    /// `step_px` their spacing, `degree` the position polynomial's degree,
    /// `centre_px` and `span_px` its normalisation (the image's centre column
    /// and half width, say). Errors on bad parameters, on too few samples,
    /// or when the forces do not vary enough to tell the components apart.
    pub fn fit(
        samples: &[ProfileSample<'_>],
        step_px: f64,
        half_width_px: f64,
        degree: usize,
        centre_px: f64,
        span_px: f64,
    ) -> Result<Self> {
        Self::fit_with_size(
            samples,
            step_px,
            half_width_px,
            degree,
            centre_px,
            span_px,
            None,
        )
    }

    /// [`ProfileModel::fit`] with an indenter-size term ([`SizeTerm`]) when
    /// `size` is given: every sample must then carry its finite
    /// [`ProfileSample::size_mm`], and the sizes must vary.
    pub fn fit_with_size(
        samples: &[ProfileSample<'_>],
        step_px: f64,
        half_width_px: f64,
        degree: usize,
        centre_px: f64,
        span_px: f64,
        size: Option<SizeTerm>,
    ) -> Result<Self> {
        if let Some(t) = size {
            t.validate()?;
            require_sizes(samples)?;
        }
        for (name, x) in [
            ("step_px", step_px),
            ("half_width_px", half_width_px),
            ("span_px", span_px),
        ] {
            if !(x > 0.0 && x.is_finite()) {
                return Err(Error::param(name, format!("must be > 0, got {x}")));
            }
        }
        for (name, x) in [("step_px", step_px), ("half_width_px", half_width_px)] {
            if x > MAX_PROFILE_REACH_PX {
                return Err(Error::param(
                    name,
                    format!("at most {MAX_PROFILE_REACH_PX} px, got {x}"),
                ));
            }
        }
        if !centre_px.is_finite() {
            return Err(Error::param("centre_px", "must be finite"));
        }
        if degree > MAX_PROFILE_DEGREE {
            return Err(Error::param(
                "degree",
                format!("at most {MAX_PROFILE_DEGREE}, got {degree}"),
            ));
        }
        let samples_per_side = (half_width_px / step_px).round();
        if samples_per_side > MAX_PROFILE_HALF_WIDTH as f64 {
            return Err(Error::param(
                "step_px",
                format!(
                    "{half_width_px} px at {step_px} px a sample is {samples_per_side} samples a \
                     side, more than {MAX_PROFILE_HALF_WIDTH}"
                ),
            ));
        }
        let half_width = samples_per_side as usize;
        let components = COMPONENTS + usize::from(size.is_some());
        let unknowns = components * (degree + 1);
        if samples.len() < 2 * unknowns {
            return Err(calibration_error(format!(
                "profile model: {} samples for {unknowns} unknowns per offset; need at least {}",
                samples.len(),
                2 * unknowns
            )));
        }
        let mut model = ProfileModel {
            step_px,
            half_width,
            centre_px,
            span_px,
            degree,
            kernels: Vec::new(),
            anchor: None,
            size,
            tail: None,
            relocation: Relocation::Clear,
            shear_free_columns: false,
            // Fitted when every sample carries a spread profile.
            spread: samples
                .iter()
                .all(|s| carries_spread(s.profile_u.len(), s.profile_v.len())),
        };
        model.kernels = model.fit_offsets(samples, step_px, half_width, true)?;
        model.validate()?;
        Ok(model)
    }

    /// The model with far tails ([`ProfileTail`]) fitted to `samples` (the
    /// samples the model was fitted on, at the same columns): every
    /// `step_px` out to `reach_px` each side. Offsets the samples do not
    /// determine (too few, or all at one place) keep a zero tail. Errors on
    /// bad parameters or samples whose sizes the model's size term needs.
    pub fn with_tail(
        mut self,
        samples: &[ProfileSample<'_>],
        step_px: f64,
        reach_px: f64,
    ) -> Result<Self> {
        for (name, x) in [("tail step_px", step_px), ("tail reach_px", reach_px)] {
            if !(x > 0.0 && x <= MAX_PROFILE_REACH_PX) {
                return Err(Error::param(
                    name,
                    format!("must be > 0 and at most {MAX_PROFILE_REACH_PX} px, got {x}"),
                ));
            }
        }
        if reach_px <= self.reach_px() {
            return Err(Error::param(
                "tail reach_px",
                format!(
                    "{reach_px} px does not reach beyond the kernels' {} px",
                    self.reach_px()
                ),
            ));
        }
        if self.size.is_some() {
            require_sizes(samples)?;
        }
        let half_width = ((reach_px / step_px).ceil() as usize).min(MAX_PROFILE_HALF_WIDTH);
        let kernels = self.fit_offsets(samples, step_px, half_width, false)?;
        self.tail = Some(ProfileTail {
            step_px,
            half_width,
            kernels,
        });
        self.validate()?;
        Ok(self)
    }

    /// Kernels fitted at the offsets `(i - half_width) * step_px`, `i` in
    /// `0..=2 * half_width`: `[channel][unknown][i]`. Where too few samples
    /// reach an offset (the image's ends) its kernels stay 0; a singular
    /// system there is an error when `strict`, else its kernels stay 0 too.
    fn fit_offsets(
        &self,
        samples: &[ProfileSample<'_>],
        step_px: f64,
        half_width: usize,
        strict: bool,
    ) -> Result<Vec<Vec<Vec<f64>>>> {
        let components = self.components();
        let unknowns = components * (self.degree + 1);
        // A tail offset is trusted from twice as many samples as unknowns.
        let min_rows = if strict { unknowns } else { 2 * unknowns };
        let mut kernels = vec![vec![vec![0.0; 2 * half_width + 1]; unknowns]; self.channels()];
        let mut design = vec![0.0; unknowns];
        let mut ata = vec![0.0; unknowns * unknowns];
        let mut atb = vec![0.0; unknowns];
        for (ch, kernels) in kernels.iter_mut().enumerate() {
            for i in 0..=2 * half_width {
                let t = (i as f64 - half_width as f64) * step_px;
                ata.fill(0.0);
                atb.fill(0.0);
                let mut rows = 0usize;
                for s in samples {
                    let Some(prof) = channels(s.profile_u, s.profile_v)
                        .and_then(|c| c.as_slice().get(ch).copied())
                    else {
                        continue;
                    };
                    let Some(y) = sample_profile(prof, s.scale, s.column_px + t) else {
                        continue;
                    };
                    let unknowns = self.unknowns(s.local_force, s.size_mm.unwrap_or(0.0));
                    self.design_row(s.column_px, &unknowns[..components], &mut design);
                    accumulate(&mut ata, &mut atb, &design, y);
                    rows += 1;
                }
                if rows < min_rows {
                    // Too close to the image's ends for this offset: no
                    // response known there, the kernel stays 0.
                    continue;
                }
                let Some(k) = solve(&mut ata, &mut atb, unknowns) else {
                    if strict {
                        return Err(calibration_error(
                            "profile model: the training forces do not separate the \
                             tangential, across and normal responses (or the sizes' \
                             from the normal one: singular system)"
                                .into(),
                        ));
                    }
                    continue;
                };
                for (u, &v) in k.iter().enumerate() {
                    kernels[u][i] = v;
                }
            }
        }
        Ok(kernels)
    }

    /// Checks the shapes and values of a loaded model.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(calibration_error(format!("profile model: {m}")));
        if !(self.span_px > 0.0 && self.span_px.is_finite() && self.centre_px.is_finite()) {
            return bad("centre_px and span_px must be finite, span_px > 0".into());
        }
        if self.degree > MAX_PROFILE_DEGREE {
            return bad(format!(
                "degree {} is above {MAX_PROFILE_DEGREE}",
                self.degree
            ));
        }
        if let Some(t) = &self.size {
            t.validate()?;
        }
        let unknowns = self.components() * (self.degree + 1);
        let sampled = |what: &str, step_px: f64, half_width: usize, kernels: &[Vec<Vec<f64>>]| {
            if !(step_px > 0.0 && step_px <= MAX_PROFILE_REACH_PX) {
                return bad(format!(
                    "{what}step_px must be > 0 and at most {MAX_PROFILE_REACH_PX}, got {step_px}"
                ));
            }
            if half_width > MAX_PROFILE_HALF_WIDTH {
                return bad(format!(
                    "{what}half_width {half_width} is above {MAX_PROFILE_HALF_WIDTH} samples"
                ));
            }
            // Cannot overflow: bounded above.
            let n = 2 * half_width + 1;
            if kernels.len() != self.channels()
                || kernels
                    .iter()
                    .any(|c| c.len() != unknowns || c.iter().any(|k| k.len() != n))
            {
                return bad(format!(
                    "expected {} {what}channels of {unknowns} kernels of {n} samples (degree {}, \
                     {what}half_width {half_width}, spread {})",
                    self.channels(),
                    self.degree,
                    self.spread
                ));
            }
            if kernels.iter().flatten().flatten().any(|x| !x.is_finite()) {
                return bad(format!("non-finite {what}kernel sample"));
            }
            Ok(())
        };
        sampled("", self.step_px, self.half_width, &self.kernels)?;
        if let Some(t) = &self.tail {
            sampled("tail ", t.step_px, t.half_width, &t.kernels)?;
        }
        if let Some(a) = &self.anchor {
            a.validate()?;
        }
        Ok(())
    }

    /// Profile channels: along x, across, and the spread with
    /// [`ProfileModel::spread`].
    pub fn channels(&self) -> usize {
        2 + usize::from(self.spread)
    }

    /// Unknowns per contact: 3, or 4 with the size term.
    fn components(&self) -> usize {
        COMPONENTS + usize::from(self.size.is_some())
    }

    /// A contact's unknowns for a local force and indenter size: the force,
    /// then (with the size term) the normal force times the scaled size.
    fn unknowns(&self, force: [f64; 3], size_mm: f64) -> [f64; MAX_UNKNOWNS] {
        let extra = self
            .size
            .map_or(0.0, |t| force[2] * (size_mm - t.centre_mm) / t.scale_mm);
        [force[0], force[1], force[2], extra]
    }

    /// The position polynomial's terms times the unknowns: one design row.
    fn design_row(&self, column_px: f64, unknowns: &[f64], out: &mut [f64]) {
        let z = (column_px - self.centre_px) / self.span_px;
        let mut p = 1.0;
        for m in 0..=self.degree {
            for (k, f) in unknowns.iter().enumerate() {
                out[k * (self.degree + 1) + m] = f * p;
            }
            p *= z;
        }
    }

    /// Kernels of channel `ch` for a contact at `column_px`, at offset `t_px`:
    /// one value per unknown ([`ProfileModel::components`] of them; the rest 0).
    /// Beyond the kernels' reach, the tail's ([`ProfileTail`]) when `tail`
    /// and the model has one.
    fn kernel(
        &self,
        ch: usize,
        column_px: f64,
        t_px: f64,
        tail: bool,
    ) -> Option<[f64; MAX_UNKNOWNS]> {
        let (kernels, step_px, half_width) = if t_px.abs() <= self.reach_px() {
            (&self.kernels, self.step_px, self.half_width)
        } else {
            let t = self.tail.as_ref().filter(|_| tail)?;
            (&t.kernels, t.step_px, t.half_width)
        };
        let kernels = kernels.get(ch)?;
        let idx = t_px / step_px + half_width as f64;
        let last = (2 * half_width) as f64;
        if !(0.0..=last).contains(&idx) {
            return None;
        }
        let i0 = (idx.floor() as usize).min(2 * half_width);
        let i1 = (i0 + 1).min(2 * half_width);
        let a = idx - i0 as f64;
        let z = (column_px - self.centre_px) / self.span_px;
        let mut out = [0.0; MAX_UNKNOWNS];
        for (k, o) in out.iter_mut().take(self.components()).enumerate() {
            let mut p = 1.0;
            for m in 0..=self.degree {
                let kern = &kernels[k * (self.degree + 1) + m];
                *o += p * ((1.0 - a) * kern[i0] + a * kern[i1]);
                p *= z;
            }
        }
        Some(out)
    }

    /// Takes the modelled motion of a contact at `column_px` with
    /// `unknowns` (its local force, then the size term's unknown if the
    /// model has one) out of the profiles `[u, v]` (cells of `scale`
    /// pixels; `v` with its spread profile after its column sums when it is
    /// twice as long as `u`) in the cells whose pixel lies in `window`, far
    /// tails included.
    fn subtract_motion(
        &self,
        column_px: f64,
        unknowns: &[f64],
        scale: f64,
        (lo, hi): (f64, f64),
        [profile_u, profile_v]: [&mut [f64]; 2],
    ) {
        let n = profile_u.len();
        let mut profiles = vec![profile_u];
        if carries_spread(n, profile_v.len()) {
            let (sums, spread) = profile_v.split_at_mut(n);
            profiles.push(sums);
            profiles.push(spread);
        } else {
            profiles.push(profile_v);
        }
        for (ch, prof) in profiles.into_iter().enumerate().take(self.channels()) {
            for (j, p) in prof.iter_mut().enumerate() {
                let x = (j as f64 + 0.5) * scale - 0.5;
                if x < lo || x > hi {
                    continue;
                }
                if let Some(kv) = self.kernel(ch, column_px, x - column_px, true) {
                    *p -= kv.iter().zip(unknowns).map(|(k, f)| k * f).sum::<f64>();
                }
            }
        }
    }

    /// How far each side of a contact the kernels reach, pixels: a
    /// contact's equations are the profile cells within it.
    pub fn reach_px(&self) -> f64 {
        self.half_width as f64 * self.step_px
    }
}

impl SizeTerm {
    /// The term for training indenters of these sizes: centred on their
    /// mean, scaled by half their range. `None` when fewer than two sizes
    /// (the term would not be identifiable) or a size is not finite and > 0.
    pub fn for_sizes(sizes: impl IntoIterator<Item = f64>) -> Option<Self> {
        let (mut lo, mut hi, mut sum, mut n) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0usize);
        for s in sizes {
            if !(s > 0.0 && s.is_finite()) {
                return None;
            }
            lo = lo.min(s);
            hi = hi.max(s);
            sum += s;
            n += 1;
        }
        (n > 0 && hi > lo).then(|| SizeTerm {
            centre_mm: sum / n as f64,
            scale_mm: 0.5 * (hi - lo),
        })
    }

    /// Checks a loaded term: finite centre, scale > 0.
    pub fn validate(&self) -> Result<()> {
        if self.centre_mm.is_finite() && self.scale_mm > 0.0 && self.scale_mm.is_finite() {
            Ok(())
        } else {
            Err(calibration_error(format!(
                "profile model: the size term needs a finite centre_mm and scale_mm > 0, got {} and {}",
                self.centre_mm, self.scale_mm
            )))
        }
    }
}

/// Errors unless every sample carries a finite indenter size (the size
/// term needs them).
fn require_sizes(samples: &[ProfileSample<'_>]) -> Result<()> {
    if samples
        .iter()
        .any(|s| !s.size_mm.is_some_and(|x| x.is_finite()))
    {
        return Err(Error::param(
            "size_mm",
            "every sample needs a finite indenter size for the size term",
        ));
    }
    Ok(())
}

fn calibration_error(message: String) -> Error {
    Error::Calibration {
        path: None,
        message,
    }
}

/// The profile at full-resolution pixel `x_px`, linear between cells; `None`
/// outside the profile.
fn sample_profile(p: &[f64], scale: f64, x_px: f64) -> Option<f64> {
    let c = (x_px + 0.5) / scale - 0.5;
    if p.is_empty() || !(c >= 0.0 && c <= (p.len() - 1) as f64) {
        return None;
    }
    let j = (c.floor() as usize).min(p.len() - 1);
    let k = (j + 1).min(p.len() - 1);
    let a = c - j as f64;
    Some((1.0 - a) * p[j] + a * p[k])
}

/// `ata += r r^T`, `atb += r y` (row-major `ata`).
fn accumulate(ata: &mut [f64], atb: &mut [f64], r: &[f64], y: f64) {
    let n = r.len();
    for i in 0..n {
        if r[i] == 0.0 {
            continue;
        }
        for j in 0..n {
            ata[i * n + j] += r[i] * r[j];
        }
        atb[i] += r[i] * y;
    }
}

/// Solves the symmetric system `ata x = atb` (row-major, `n` x `n`) in place
/// by Gaussian elimination with partial pivoting; the solution is left in
/// `atb`. `None` when singular (relative to the diagonal's scale).
pub(crate) fn solve(ata: &mut [f64], atb: &mut [f64], n: usize) -> Option<Vec<f64>> {
    solve_in_place(ata, atb, n)?;
    Some(atb[..n].to_vec())
}

fn solve_in_place(a: &mut [f64], b: &mut [f64], n: usize) -> Option<()> {
    let scale = (0..n).map(|i| a[i * n + i].abs()).fold(0.0, f64::max);
    if !(scale > 0.0 && scale.is_finite()) {
        return None;
    }
    for col in 0..n {
        let piv =
            (col..n).max_by(|&i, &j| a[i * n + col].abs().total_cmp(&a[j * n + col].abs()))?;
        if a[piv * n + col].abs() <= 1e-12 * scale {
            return None;
        }
        if piv != col {
            for j in 0..n {
                a.swap(piv * n + j, col * n + j);
            }
            b.swap(piv, col);
        }
        let d = a[col * n + col];
        for i in col + 1..n {
            let f = a[i * n + col] / d;
            if f == 0.0 {
                continue;
            }
            for j in col..n {
                a[i * n + j] -= f * a[col * n + j];
            }
            b[i] -= f * b[col];
        }
    }
    for col in (0..n).rev() {
        let mut s = b[col];
        for j in col + 1..n {
            s -= a[col * n + j] * b[j];
        }
        b[col] = s / a[col * n + col];
    }
    b[..n].iter().all(|x| x.is_finite()).then_some(())
}

/// Solves, per frame, for the local force components of every contact at
/// once ([`ProfileModel`]); keeps its buffers from frame to frame.
#[derive(Debug, Default, Clone)]
pub struct ForceMatcher {
    system: NormalEquations,
    profile_u: Vec<f64>,
    profile_v: Vec<f64>,
    forces: Vec<[f64; 3]>,
    columns: Vec<f64>,
    /// The columns before a relocation.
    before: Vec<f64>,
    /// The profile less the contacts' tangential motion, and the slope
    /// peak's buffers ([`ForceMatcher::shear_free_columns`]).
    shear_free: Vec<f64>,
    locator: crate::contact::ContactLocator,
    measured: Vec<f64>,
    tangential: Vec<f64>,
}

/// The least-squares system of one frame's force match, and the copies its
/// solver works on (so that a singular system can be solved again with a
/// ridge).
#[derive(Debug, Default, Clone)]
struct NormalEquations {
    ata: Vec<f64>,
    atb: Vec<f64>,
    row: Vec<f64>,
    work_a: Vec<f64>,
    work_b: Vec<f64>,
}

impl ForceMatcher {
    /// An empty matcher (buffers grow on first use).
    pub fn new() -> Self {
        Self::default()
    }

    /// The local forces `[tangential, across, normal]` of contacts at
    /// `columns_px` that best explain the profiles (grid of `scale`
    /// full-resolution pixels per cell), into `out` (cleared first). Each
    /// profile cell within a kernel's reach of some contact is one equation
    /// per channel. Contacts the profile cannot tell apart (two at one
    /// column) share their force evenly. Errors on mismatched profiles, a
    /// bad scale, a non-finite column or profile value, or a model with no
    /// response at all near the contacts.
    pub fn measure(
        &mut self,
        model: &ProfileModel,
        columns_px: &[f64],
        profile_u: &[f64],
        profile_v: &[f64],
        scale: f64,
        out: &mut Vec<[f64; 3]>,
    ) -> Result<()> {
        self.system
            .solve(model, columns_px, profile_u, profile_v, scale, out)
    }

    /// Sets every contact's [`RawContact::local_force`] from the frame's
    /// flow (`u`, `v` on a grid of `scale` full-resolution pixels per cell),
    /// all contacts solved at once at their current `x_px`.
    pub fn measure_contacts(
        &mut self,
        model: &ProfileModel,
        raws: &mut [RawContact],
        u: ArrayView2<'_, f32>,
        v: ArrayView2<'_, f32>,
        scale: f64,
    ) -> Result<()> {
        self.measure_contacts_at(model, raws, u, v, scale, |r| Ok(r.x_px))
    }

    /// [`ForceMatcher::measure_contacts`] with each contact matched at the
    /// column `column_of(contact)` (a model's anchor column of the contact's
    /// calibrated location, say: [`ColumnMap`]).
    pub fn measure_contacts_at(
        &mut self,
        model: &ProfileModel,
        raws: &mut [RawContact],
        u: ArrayView2<'_, f32>,
        v: ArrayView2<'_, f32>,
        scale: f64,
        column_of: impl FnMut(&RawContact) -> Result<f64>,
    ) -> Result<()> {
        self.load_profiles(model, u, v, scale)?;
        self.solve_loaded(model, raws, scale, column_of)
    }

    /// [`ForceMatcher::relocate_contacts`], then
    /// [`ForceMatcher::measure_contacts_at`] at the moved points, on one
    /// computation of the frame's profiles. Returns how many moved.
    pub fn relocate_and_measure_contacts_at(
        &mut self,
        model: &ProfileModel,
        raws: &mut [RawContact],
        u: ArrayView2<'_, f32>,
        v: ArrayView2<'_, f32>,
        scale: f64,
        mut column_of: impl FnMut(&RawContact) -> Result<f64>,
    ) -> Result<usize> {
        self.load_profiles(model, u, v, scale)?;
        let moved = self.relocate_loaded(model, raws, scale, &mut column_of)?;
        self.solve_loaded(model, raws, scale, column_of)?;
        Ok(moved)
    }

    /// With a model that measures shear-free columns
    /// ([`ProfileModel::shear_free_columns`]), after a first match (each
    /// contact's [`RawContact::local_force`] set at `column_of(contact)`,
    /// by [`ForceMatcher::relocate_and_measure_contacts_at`] or
    /// [`ForceMatcher::measure_contacts_at`] on this frame): every contact's
    /// modelled tangential motion is taken out of the frame's profile along
    /// the arc, each contact's `x_px` moves to the steepest rise of what is
    /// left (the slope peak of smoothing `sigma_px`,
    /// [`crate::contact::ContactLocator::slope_peak_in_profile`]) within
    /// [`RELOCATE_RADIUS_OF_REACH`] of the kernels' reach, and the forces
    /// are matched again at the new `column_of(contact)`. Without the flag,
    /// does nothing. Returns how many contacts moved.
    ///
    /// Once only: repeated (the tangential force matched again at the new
    /// column, the column measured again) the columns drift, on the
    /// simulated strip's random presses from a normal-force error of
    /// 0.036 N to 0.046 N.
    pub fn shear_free_columns(
        &mut self,
        model: &ProfileModel,
        raws: &mut [RawContact],
        scale: f64,
        sigma_px: f64,
        mut column_of: impl FnMut(&RawContact) -> Result<f64>,
    ) -> Result<usize> {
        if !model.shear_free_columns || raws.is_empty() {
            return Ok(0);
        }
        self.load_columns(raws, &mut column_of)?;
        let window = RELOCATE_RADIUS_OF_REACH * model.reach_px();
        self.measured.clear();
        self.measured.extend(raws.iter().map(|r| r.x_px));
        self.tangential.clear();
        self.tangential
            .extend(raws.iter().map(|r| r.local_force.map_or(0.0, |f| f[0])));
        shear_free_profile(
            model,
            &self.profile_u,
            scale,
            &self.columns,
            &self.tangential,
            &mut self.shear_free,
        );
        self.locator.slope_peak_in_profile(
            &self.shear_free,
            &mut self.measured,
            scale,
            sigma_px,
            window,
        );
        let mut moved = 0;
        for (r, &x) in raws.iter_mut().zip(&self.measured) {
            if x != r.x_px {
                r.x_px = x;
                moved += 1;
            }
        }
        self.solve_loaded(model, raws, scale, column_of)?;
        Ok(moved)
    }

    /// [`ForceMatcher::shear_free_columns`] on given profiles along the
    /// arc (`profile_u`, `profile_v`, cells of `scale` pixels, as
    /// [`column_profile_into`] gives them): the first match at
    /// `column_of(contact)`, the columns measured again, the forces matched
    /// again. Errors on profiles of different lengths.
    #[allow(clippy::too_many_arguments)]
    pub fn shear_free_columns_of_profiles(
        &mut self,
        model: &ProfileModel,
        raws: &mut [RawContact],
        profile_u: &[f64],
        profile_v: &[f64],
        scale: f64,
        sigma_px: f64,
        mut column_of: impl FnMut(&RawContact) -> Result<f64>,
    ) -> Result<usize> {
        check_match_inputs(&[], profile_u, profile_v, scale)?;
        self.profile_u.clear();
        self.profile_u.extend_from_slice(profile_u);
        self.profile_v.clear();
        self.profile_v.extend_from_slice(profile_v);
        self.solve_loaded(model, raws, scale, &mut column_of)?;
        self.shear_free_columns(model, raws, scale, sigma_px, column_of)
    }

    /// The frame's column profiles of `u` and `v` (with the spread profile
    /// when `model` has that channel) into the matcher's buffers.
    fn load_profiles(
        &mut self,
        model: &ProfileModel,
        u: ArrayView2<'_, f32>,
        v: ArrayView2<'_, f32>,
        scale: f64,
    ) -> Result<()> {
        if u.dim() != v.dim() {
            return Err(Error::shape(
                "flow v against u",
                (u.ncols(), u.nrows()),
                (v.ncols(), v.nrows()),
            ));
        }
        column_profile_into(u, scale, &mut self.profile_u);
        across_profiles_into(v, scale, model.spread, &mut self.profile_v);
        Ok(())
    }

    /// Each contact's column `column_of(contact)` into the matcher's buffer.
    fn load_columns(
        &mut self,
        raws: &[RawContact],
        mut column_of: impl FnMut(&RawContact) -> Result<f64>,
    ) -> Result<()> {
        self.columns.clear();
        for r in raws {
            self.columns.push(column_of(r)?);
        }
        Ok(())
    }

    /// The force match of the loaded profiles at `column_of(contact)`,
    /// into each contact's [`RawContact::local_force`].
    fn solve_loaded(
        &mut self,
        model: &ProfileModel,
        raws: &mut [RawContact],
        scale: f64,
        column_of: impl FnMut(&RawContact) -> Result<f64>,
    ) -> Result<()> {
        self.load_columns(raws, column_of)?;
        self.system.solve(
            model,
            &self.columns,
            &self.profile_u,
            &self.profile_v,
            scale,
            &mut self.forces,
        )?;
        for (r, f) in raws.iter_mut().zip(&self.forces) {
            r.local_force = Some(*f);
        }
        Ok(())
    }

    /// Puts back contacts whose measured point is far from where their
    /// motion is: each contact's match column (`column_of(contact)`, as for
    /// [`ForceMatcher::measure_contacts_at`]) is searched within
    /// [`RELOCATE_RADIUS_OF_REACH`] of the kernels' reach for the column
    /// whose least-squares match leaves the smallest residual, the other
    /// contacts held at theirs. When that residual is at least
    /// [`RELOCATE_MIN_GAIN`] lower and the column at least
    /// [`RELOCATE_MIN_SHIFT_OF_RADIUS`] of the radius away, the contact's
    /// `x_px` moves by the same number of pixels. Returns how many moved.
    /// The kernels' far tails ([`ProfileTail`]) take no part in the search.
    /// That is [`Relocation::Clear`]; a model with [`Relocation::Best`]
    /// moves every contact to its best column, to a fraction of a pixel,
    /// with the tails (see there).
    ///
    /// Why: the contact point is the steepest rise of a profile. Under a
    /// wide rod pushed at a slant the profile can have two steep flanks,
    /// and the estimate can jump to the wrong one, several millimetres
    /// off; the location map cannot undo a jump, and the kernels matched
    /// there misread the force. The whole shape of the motion still says
    /// where the contact is. On the simulator's random presses this moved
    /// one contact in 150 by 27 px (4.7 mm off before, 0.5 mm after) and
    /// another by 13 px, and none of the rest.
    pub fn relocate_contacts(
        &mut self,
        model: &ProfileModel,
        raws: &mut [RawContact],
        u: ArrayView2<'_, f32>,
        v: ArrayView2<'_, f32>,
        scale: f64,
        column_of: impl FnMut(&RawContact) -> Result<f64>,
    ) -> Result<usize> {
        self.load_profiles(model, u, v, scale)?;
        self.relocate_loaded(model, raws, scale, column_of)
    }

    /// [`ForceMatcher::relocate_contacts`] on the loaded profiles.
    fn relocate_loaded(
        &mut self,
        model: &ProfileModel,
        raws: &mut [RawContact],
        scale: f64,
        column_of: impl FnMut(&RawContact) -> Result<f64>,
    ) -> Result<usize> {
        self.load_columns(raws, column_of)?;
        self.before.clear();
        self.before.extend_from_slice(&self.columns);
        self.system.relocate(
            model,
            &mut self.columns,
            &self.profile_u,
            &self.profile_v,
            scale,
        )?;
        let mut moved = 0;
        for (r, (c, c0)) in raws.iter_mut().zip(self.columns.iter().zip(&self.before)) {
            if c != c0 {
                r.x_px += c - c0;
                moved += 1;
            }
        }
        Ok(moved)
    }

    /// [`ForceMatcher::relocate_contacts`] on columns and profiles given
    /// directly: moves the entries of `columns_px` in place.
    pub fn relocate(
        &mut self,
        model: &ProfileModel,
        columns_px: &mut [f64],
        profile_u: &[f64],
        profile_v: &[f64],
        scale: f64,
    ) -> Result<()> {
        self.system
            .relocate(model, columns_px, profile_u, profile_v, scale)
    }
}

impl NormalEquations {
    /// See [`ForceMatcher::relocate`].
    fn relocate(
        &mut self,
        model: &ProfileModel,
        columns_px: &mut [f64],
        profile_u: &[f64],
        profile_v: &[f64],
        scale: f64,
    ) -> Result<()> {
        check_match_inputs(columns_px, profile_u, profile_v, scale)?;
        model_channels(model, profile_u, profile_v)?;
        if model.relocation == Relocation::Best && columns_px.len() > 1 {
            // The other contacts' motion, matched jointly at their current
            // columns (with the far tails), is taken out of the profiles,
            // and each contact is then searched alone: the same answer as
            // searching it among them with their forces held, at a
            // fraction of the cost of re-solving every contact for every
            // candidate. Repeated while a column still moves, the
            // neighbours' motion taken out at their latest columns.
            let start = columns_px.to_vec();
            let radius = RELOCATE_RADIUS_OF_REACH * model.reach_px();
            // The cells a search from a column can see: its window, with
            // room for the search to move it.
            let window = model.reach_px() + 3.0 * radius;
            let comps = model.components();
            let mut forces = Vec::new();
            let mut solved = false;
            for pass in 0..RELOCATE_BEST_PASSES {
                if self
                    .solve(model, columns_px, profile_u, profile_v, scale, &mut forces)
                    .is_err()
                {
                    break;
                }
                solved = true;
                let unknowns = self.work_b[..comps * columns_px.len()].to_vec();
                let at = columns_px.to_vec();
                let mut own = [0.0];
                for m in 0..at.len() {
                    let (mut u, mut v) = (profile_u.to_vec(), profile_v.to_vec());
                    for (j, &c) in at.iter().enumerate().filter(|&(j, _)| j != m) {
                        model.subtract_motion(
                            c,
                            &unknowns[comps * j..comps * (j + 1)],
                            scale,
                            (at[m] - window, at[m] + window),
                            [&mut u, &mut v],
                        );
                    }
                    own[0] = at[m];
                    self.relocate_each(model, &mut own, &u, &v, scale, pass == 0);
                    columns_px[m] = own[0].clamp(start[m] - radius, start[m] + radius);
                }
                let moved = at
                    .iter()
                    .zip(columns_px.iter())
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                if moved < RELOCATE_BEST_SETTLED_PX {
                    break;
                }
            }
            if solved {
                return Ok(());
            }
        }
        self.relocate_each(model, columns_px, profile_u, profile_v, scale, true);
        Ok(())
    }

    /// [`NormalEquations::relocate`] searching every contact among the
    /// others (each re-solved at every candidate).
    fn relocate_each(
        &mut self,
        model: &ProfileModel,
        columns_px: &mut [f64],
        profile_u: &[f64],
        profile_v: &[f64],
        scale: f64,
        coarse: bool,
    ) {
        let radius = RELOCATE_RADIUS_OF_REACH * model.reach_px();
        let min_shift = RELOCATE_MIN_SHIFT_OF_RADIUS * radius;
        let steps = radius.floor() as i64;
        if steps < 1 {
            return;
        }
        // One window for every candidate, so that their residuals add up
        // the same cells.
        let reach = model.reach_px() + radius;
        // To find a misplaced point the search compares candidate columns by
        // their residual over the window, every second cell (the kernels are
        // smooth over a cell), without the far tails: a far contact's motion
        // weighs alike on every candidate, and with them every contact would
        // enter every search (4 contacts: 2.2 times the time). For the best
        // column to a fraction of a pixel the final steps take every cell,
        // and the tails count: a neighbour's far motion across the window
        // would otherwise pull the column towards it, so every contact takes
        // part, with its tails.
        let best_mode = model.relocation == Relocation::Best;
        let tails = best_mode && model.tail.is_some();
        let rough = (2, tails);
        let fine = if best_mode { (1, tails) } else { rough };
        let steps_px: &[f64] = if best_mode {
            &[2.0, 1.0, 0.5]
        } else {
            &[2.0, 1.0]
        };
        let mut near = Vec::with_capacity(columns_px.len());
        for m in 0..columns_px.len() {
            let c0 = columns_px[m];
            let window = (c0 - reach, c0 + reach);
            // The contacts whose kernels reach into the window (the others'
            // unknowns would have no equation there), or with the tails
            // every contact; this one first.
            near.clear();
            near.push(c0);
            near.extend(
                columns_px
                    .iter()
                    .enumerate()
                    .filter(|&(j, c)| {
                        j != m && (tails || (c - c0).abs() < reach + model.reach_px())
                    })
                    .map(|(_, &c)| c),
            );
            let residual_at = |this: &mut Self, cols: &mut [f64], c: f64, how| {
                cols[0] = c;
                this.residual(model, cols, profile_u, profile_v, scale, window, how)
            };
            let Some(r0) = residual_at(self, &mut near, c0, rough) else {
                continue;
            };
            // Every fourth pixel, then 2 and 1 pixels (and half a pixel for
            // the best column) either side of the best: a misplaced point is a dozen pixels or more off, and the
            // residual's basin about the right column is wider than 4 px.
            let (mut best, mut best_r) = (c0, r0);
            if coarse {
                for k in (-steps..=steps).step_by(RELOCATE_COARSE_STEP) {
                    let c = c0 + k as f64;
                    if let Some(r) = residual_at(self, &mut near, c, rough).filter(|&r| r < best_r)
                    {
                        (best, best_r) = (c, r);
                    }
                }
            }
            if best_mode {
                let Some(r) = residual_at(self, &mut near, best, fine) else {
                    continue;
                };
                best_r = r;
            }
            for &step in steps_px {
                let centre = best;
                for c in [centre - step, centre + step] {
                    if (c - c0).abs() > radius {
                        continue;
                    }
                    if let Some(r) = residual_at(self, &mut near, c, fine).filter(|&r| r < best_r) {
                        (best, best_r) = (c, r);
                    }
                }
            }
            let moves = match model.relocation {
                Relocation::Clear => {
                    best_r < (1.0 - RELOCATE_MIN_GAIN) * r0 && (best - c0).abs() >= min_shift
                }
                Relocation::Best => {
                    // The vertex of the parabola through the best and its
                    // two half-pixel neighbours.
                    let below = residual_at(self, &mut near, best - 0.5, fine);
                    let above = residual_at(self, &mut near, best + 0.5, fine);
                    if let (Some(lo), Some(hi)) = (below, above) {
                        let curvature = lo - 2.0 * best_r + hi;
                        if curvature > 0.0 {
                            best += (0.25 * (lo - hi) / curvature).clamp(-0.25, 0.25);
                        }
                    }
                    best = best.clamp(c0 - radius, c0 + radius);
                    true
                }
            };
            columns_px[m] = if moves { best } else { c0 };
        }
    }

    /// The residual sum of squares of the least-squares match of contacts
    /// at `columns_px`, over every `stride`-th profile cell whose pixel
    /// lies in `window`, with the far tails when `tails`; `None` when the
    /// system is singular there.
    fn residual(
        &mut self,
        model: &ProfileModel,
        columns_px: &[f64],
        profile_u: &[f64],
        profile_v: &[f64],
        scale: f64,
        (lo, hi): (f64, f64),
        (stride, tails): (usize, bool),
    ) -> Option<f64> {
        let chans = model_channels(model, profile_u, profile_v).ok()?;
        let comps = model.components();
        let n = comps * columns_px.len();
        self.ata.clear();
        self.ata.resize(n * n, 0.0);
        self.atb.clear();
        self.atb.resize(n, 0.0);
        self.row.clear();
        self.row.resize(n, 0.0);
        let mut yy = 0.0;
        let first = ((lo + 0.5) / scale - 0.5).ceil().max(0.0) as usize;
        for (ch, &prof) in chans.as_slice().iter().enumerate() {
            for (j, &y) in prof.iter().enumerate().skip(first).step_by(stride) {
                let x = (j as f64 + 0.5) * scale - 0.5;
                if x > hi {
                    break;
                }
                if x < lo {
                    continue;
                }
                for (m, &c) in columns_px.iter().enumerate() {
                    let kv = model
                        .kernel(ch, c, x - c, tails)
                        .unwrap_or([0.0; MAX_UNKNOWNS]);
                    self.row[comps * m..comps * (m + 1)].copy_from_slice(&kv[..comps]);
                }
                accumulate(&mut self.ata, &mut self.atb, &self.row, y);
                yy += y * y;
            }
        }
        if tails {
            // A contact without an equation in the window (a far one whose
            // tail is zero there): the ridge leaves its unknowns at 0.
            self.solve_ridged(n)?;
        } else {
            self.work_a.clear();
            self.work_a.extend_from_slice(&self.ata);
            self.work_b.clear();
            self.work_b.extend_from_slice(&self.atb);
            solve_in_place(&mut self.work_a, &mut self.work_b, n)?;
        }
        let explained: f64 = self.work_b.iter().zip(&self.atb).map(|(x, b)| x * b).sum();
        Some(yy - explained).filter(|r| r.is_finite())
    }

    /// Solves the accumulated system (`ata x = atb`, `n` unknowns) into
    /// `work_b`, `ata` and `atb` kept; when it is singular, again with a
    /// ridge of 1e-9 of the largest diagonal entry, which shares unknowns
    /// the data cannot tell apart out evenly and leaves those without an
    /// equation at 0. `None` if even that fails (an all-zero system).
    fn solve_ridged(&mut self, n: usize) -> Option<()> {
        for ridge in [
            0.0,
            1e-9 * (0..n).map(|i| self.ata[i * n + i]).fold(0.0, f64::max),
        ] {
            self.work_a.clear();
            self.work_a.extend_from_slice(&self.ata);
            for i in 0..n {
                self.work_a[i * n + i] += ridge;
            }
            self.work_b.clear();
            self.work_b.extend_from_slice(&self.atb);
            if solve_in_place(&mut self.work_a, &mut self.work_b, n).is_some() {
                return Some(());
            }
        }
        None
    }

    /// See [`ForceMatcher::measure`].
    fn solve(
        &mut self,
        model: &ProfileModel,
        columns_px: &[f64],
        profile_u: &[f64],
        profile_v: &[f64],
        scale: f64,
        out: &mut Vec<[f64; 3]>,
    ) -> Result<()> {
        out.clear();
        check_match_inputs(columns_px, profile_u, profile_v, scale)?;
        let k = columns_px.len();
        if k == 0 {
            return Ok(());
        }
        let comps = model.components();
        let n = comps * k;
        self.ata.clear();
        self.ata.resize(n * n, 0.0);
        self.atb.clear();
        self.atb.resize(n, 0.0);
        self.row.clear();
        self.row.resize(n, 0.0);
        let reach = model.reach_px();
        let chans = model_channels(model, profile_u, profile_v)?;
        for (ch, &prof) in chans.as_slice().iter().enumerate() {
            for (j, &y) in prof.iter().enumerate() {
                let x = (j as f64 + 0.5) * scale - 0.5;
                if !columns_px.iter().any(|c| (x - c).abs() <= reach) {
                    continue;
                }
                // Every cell here is within some contact's reach: the
                // others' tails model their motion in it.
                for (m, &c) in columns_px.iter().enumerate() {
                    let kv = model
                        .kernel(ch, c, x - c, true)
                        .unwrap_or([0.0; MAX_UNKNOWNS]);
                    self.row[comps * m..comps * (m + 1)].copy_from_slice(&kv[..comps]);
                }
                if !y.is_finite() {
                    return Err(Error::NonFinite {
                        what: "motion profile".into(),
                        row: ch,
                        col: j,
                    });
                }
                accumulate(&mut self.ata, &mut self.atb, &self.row, y);
            }
        }
        // Contacts the profile cannot tell apart (two at one column, say)
        // make the system singular. Rather than fail the frame, a small ridge
        // then shares the force out evenly between them (the minimum-norm
        // answer); the solution is otherwise untouched.
        if self.solve_ridged(n).is_none() {
            return Err(Error::Numerical {
                what: "profile force match".into(),
                message: format!(
                    "no motion near the contacts at columns {columns_px:?} (all-zero system)"
                ),
            });
        }
        out.extend(self.work_b.chunks_exact(comps).map(|c| [c[0], c[1], c[2]]));
        Ok(())
    }
}

/// `profile_u` (cells of `scale` pixels) less the modelled along-arc motion
/// of contacts matched at `columns_px` with tangential forces `tangential`
/// (far tails included), into `out`.
pub fn shear_free_profile(
    model: &ProfileModel,
    profile_u: &[f64],
    scale: f64,
    columns_px: &[f64],
    tangential: &[f64],
    out: &mut Vec<f64>,
) {
    out.clear();
    out.extend_from_slice(profile_u);
    for (&c, &t) in columns_px.iter().zip(tangential) {
        if t == 0.0 || !c.is_finite() {
            continue;
        }
        for (j, p) in out.iter_mut().enumerate() {
            let x = (j as f64 + 0.5) * scale - 0.5;
            if let Some(k) = model.kernel(0, c, x - c, true) {
                *p -= k[0] * t;
            }
        }
    }
}

/// The profile channels `model` is matched on ([`channels`]), or an error
/// when the profiles lack one (the spread of a model with the spread
/// channel, [`ProfileModel::spread`]).
fn model_channels<'a>(
    model: &ProfileModel,
    profile_u: &'a [f64],
    profile_v: &'a [f64],
) -> Result<Channels<'a>> {
    match channels(profile_u, profile_v) {
        Some(mut c) if c.len >= model.channels() => {
            c.len = model.channels();
            Ok(c)
        }
        _ => Err(Error::shape(
            "profile v (a model with the spread channel needs the spread profile after the sums)",
            (profile_u.len() * (model.channels() - 1), 1),
            (profile_v.len(), 1),
        )),
    }
}

/// The checks [`ForceMatcher::measure`] and [`ForceMatcher::relocate`] make
/// of their inputs: a finite scale > 0, an across profile as long as the
/// profile along x (or twice, with the spread profile), finite columns.
fn check_match_inputs(
    columns_px: &[f64],
    profile_u: &[f64],
    profile_v: &[f64],
    scale: f64,
) -> Result<()> {
    if !(scale > 0.0 && scale.is_finite()) {
        return Err(Error::param("scale", format!("must be > 0, got {scale}")));
    }
    if channels(profile_u, profile_v).is_none() {
        return Err(Error::shape(
            "profile v against u (as long, or twice with the spread profile)",
            (profile_u.len(), 1),
            (profile_v.len(), 1),
        ));
    }
    if let Some(c) = columns_px.iter().find(|c| !c.is_finite()) {
        return Err(Error::param("columns_px", format!("non-finite column {c}")));
    }
    Ok(())
}
