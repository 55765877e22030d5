//! The whole pipeline: frames in, contacts out.
//!
//! - [`ContactExtractor`] runs steps 4-7 of docs/pipeline.md on cropped grayscale frames:
//!   DIS optical flow against a fixed reference, segmentation into patches, a
//!   natural HHD per patch (in parallel), and each patch's raw quantities. It
//!   works at the flow's **native resolution** (DIS's finest computed level:
//!   full resolution for the default `fine`, 1/4 for `fast`): the flow is
//!   never upsampled. Segmentation and the nHHD use a grid of at least 2 px
//!   ([`ANALYSIS_MIN_SCALE`]; a full-resolution flow is averaged 2x2 down to
//!   it) with the grid's spacing, so every quantity comes out in
//!   full-resolution pixels; the contact column and the force profiles read
//!   the native flow ([`ContactExtractor::finest_flow`]). Calibration fitting
//!   uses it directly.
//! - [`TactileSensor`] adds the crop, the calibration (mm and N), tracking
//!   (identity, hysteresis, smoothing) and safe re-referencing.
//! - [`RawSensor`] adds the crop alone: patches in pixels, for a sensor
//!   without a calibration.
//!
//! ```no_run
//! use optical_tactile::calibration::Calibration;
//! use optical_tactile::capture::{FrameSource, SequenceSource};
//! use optical_tactile::sensor::{SensorConfig, TactileSensor};
//!
//! let calibration = Calibration::load("fixtures/calibration.json")?;
//! let mut sensor = TactileSensor::new(SensorConfig::default(), calibration)?;
//! let mut frames = SequenceSource::open("fixtures/press")?;
//! let first = frames.next_frame().expect("a frame")?;
//! sensor.set_reference(&first.image)?;
//! while let Some(frame) = frames.next_frame() {
//!     let frame = frame?;
//!     for c in sensor.process(&frame.image, frame.t_s)? {
//!         println!("contact {} at x = {:.1} mm, Fz = {:.2} N", c.id, c.location_mm[0], c.force_n[2]);
//!     }
//! }
//! # Ok::<(), optical_tactile::Error>(())
//! ```

use std::time::Instant;

use ndarray::{Array2, ArrayRef2, ArrayView2};
use rayon::prelude::*;

use crate::calibration::{Calibration, SensorSetup};
use crate::contact::confidence::ProfileWeighting;
use crate::contact::profile::ForceMatcher;
use crate::contact::{
    Contact, ContactLocator, ContactPointMethod, PatchFields, PatchGrid, RawContact,
    raw_quantities, sensor_displacements,
};
use crate::error::{Error, Result};
use crate::exposure::{ExposureCompensation, ExposureCompensator};
use crate::flow::FlowField;
use crate::flow::dis::{Dis, DisParams, DisPreset};
use crate::frame::Roi;
use crate::geometry::SensorGeometry;
use crate::hhd::{DivergentPart, NaturalHhd};
use crate::markers::{DotTracker, round};
use crate::segment::morphology::Mask;
use crate::segment::{ContactPatch, Segmenter, SegmenterConfig, SplitRule, Thresholds};
use crate::track::{ReferenceMonitor, ReferencePolicy, Tracker, TrackerConfig};

mod raw;
pub use raw::RawSensor;

/// How the extractor cuts and measures patches.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct ExtractorConfig {
    /// Optical flow parameters (default [`DisPreset::Fine`]).
    pub flow: DisParams,
    /// Segmentation thresholds (full-resolution pixels).
    pub thresholds: Thresholds,
    /// Margin around each patch so that it holds the whole deformation,
    /// full-resolution pixels.
    pub margin_px: usize,
    /// Refine the contact point to sub-pixel precision.
    pub subpixel: bool,
    /// Which changes of the camera's exposure (gain, black level) are taken
    /// out of each frame against the reference before the flow (default
    /// [`ExposureCompensation::Auto`]: exposure steps and drift, not flicker;
    /// see [`crate::exposure`]).
    pub exposure: ExposureCompensation,
    /// The rule that cuts one group of contours holding several contacts
    /// side by side (default [`SplitRule::DEFAULT`]); `None` keeps every
    /// group whole.
    pub split: Option<SplitRule>,
    /// Follow the dots of a regular marker grid one by one and let their
    /// motion replace the flow around them ([`crate::markers::DotTracker`]),
    /// when the reference shows a regular grid
    /// ([`crate::markers::grid_pitch`]); on by default, so that a sensor
    /// without a calibration (`track --raw`) follows the dots of a grid as
    /// a calibrated one does (on random markers it changes nothing).
    /// `false`: the flow alone.
    pub dot_tracking: bool,
    /// Where the dots are followed, take each contact's shear and normal
    /// displacements (`ds1`, `ds2`, `dn`) and its point from a round load's
    /// field fitted to its dots ([`crate::markers::round`]) rather than
    /// from the patch's sums, which swing with where the contact sits
    /// against the dots; on by default. Where the fit does not hold (too
    /// few dots, most of their motion unexplained) the displacements are
    /// the dots' plain sums in the same units, the point stays, and the
    /// contact is marked out of domain ([`ContactExtractor::dot_fit_failed`]).
    pub dot_fit: bool,
    /// Divide the reference and each frame by their own local light (the
    /// mean over a box of this half-side, full-resolution pixels) before
    /// the flow ([`crate::frame::divide_by_light_into`]), so that a
    /// contact under which the gel turns darker or brighter is not read as
    /// motion; `None` (the default): the flow reads the frames as they are.
    /// `calibrate` sets it for random markers on a flat sensor
    /// ([`fitting_light_box`]).
    pub light_box_px: Option<usize>,
    /// Weigh each flow cell by how well the frame warped back by the flow
    /// matches the reference there when the motion profiles are summed
    /// over the height ([`crate::contact::confidence`]): the contact's
    /// column and the forces matched to the profiles
    /// ([`ContactExtractor::profile_flow`]). Off by default (`calibrate
    /// --weighted-profiles on` fits with it).
    ///
    /// Why an option: on the simulated strip it reads the protocol's test
    /// points closer on two sensors (Fz 0.028 N against 0.035 N and 0.029
    /// against 0.032 N, with tilted sweeps and the `dense` flow) and random
    /// presses closer on the first (Fz 0.031-0.037 N against 0.035-0.040 N
    /// over four press seeds), but random presses worse on the second (Fz
    /// 0.050 N against 0.042 N), whose frames are noisier (docs/results.md,
    /// "Confidence-weighted profiles").
    pub weighted_profiles: bool,
}

impl Default for ExtractorConfig {
    fn default() -> Self {
        ExtractorConfig {
            flow: DisParams::preset(DisPreset::Fine),
            thresholds: Thresholds::HIGH,
            margin_px: 24,
            subpixel: true,
            exposure: ExposureCompensation::default(),
            split: Some(SplitRule::DEFAULT),
            dot_tracking: true,
            dot_fit: true,
            light_box_px: None,
            weighted_profiles: false,
        }
    }
}

impl ExtractorConfig {
    /// This configuration with other optical flow parameters.
    pub fn with_flow(mut self, flow: DisParams) -> Self {
        self.flow = flow;
        self
    }

    /// This configuration with other segmentation thresholds.
    pub fn with_thresholds(mut self, thresholds: impl Into<Thresholds>) -> Self {
        self.thresholds = thresholds.into();
        self
    }

    /// This configuration with another patch margin, full-resolution pixels.
    pub fn with_margin_px(mut self, margin_px: usize) -> Self {
        self.margin_px = margin_px;
        self
    }

    /// This configuration with sub-pixel contact points on or off.
    pub fn with_subpixel(mut self, subpixel: bool) -> Self {
        self.subpixel = subpixel;
        self
    }

    /// This configuration with another exposure compensation.
    pub fn with_exposure(mut self, exposure: ExposureCompensation) -> Self {
        self.exposure = exposure;
        self
    }

    /// This configuration with the frames divided by their own light over
    /// boxes of half-side `light_box_px` before the flow, or not (`None`).
    pub fn with_light_box_px(mut self, light_box_px: Option<usize>) -> Self {
        self.light_box_px = light_box_px;
        self
    }

    /// This configuration with another split rule (`None`: no split).
    pub fn with_split(mut self, split: Option<SplitRule>) -> Self {
        self.split = split;
        self
    }

    /// This configuration with the dots of a regular grid followed one by
    /// one, or not ([`ExtractorConfig::dot_tracking`]).
    pub fn with_dot_tracking(mut self, on: bool) -> Self {
        self.dot_tracking = on;
        self
    }

    /// This configuration with the contacts' displacements fitted to their
    /// dots, or not ([`ExtractorConfig::dot_fit`]).
    pub fn with_dot_fit(mut self, on: bool) -> Self {
        self.dot_fit = on;
        self
    }

    /// The settings a calibration was fitted with, so that a sensor measures
    /// the raw quantities the same way: the split rule of its geometry
    /// ([`SplitRule::for_geometry`]), the thresholds of `setup.thresholds`
    /// and, when recorded, the flow preset, margin, sub-pixel switch,
    /// exposure compensation, dot tracking, dot fit, light box and profile
    /// weighting of `setup.pipeline` (otherwise the defaults, with the
    /// compensation, dot tracking and dot fit off: such a file predates
    /// them).
    pub fn from_setup(setup: &SensorSetup) -> Result<Self> {
        setup.thresholds.validate()?;
        let mut config = ExtractorConfig {
            thresholds: setup.thresholds,
            split: Some(SplitRule::for_geometry(&setup.geometry)),
            ..ExtractorConfig::default()
        };
        // A file without pipeline settings predates exposure compensation
        // and dot tracking: its maps were fitted on the flow alone.
        config.exposure = ExposureCompensation::Off;
        config.dot_tracking = false;
        config.dot_fit = false;
        if let Some(p) = &setup.pipeline {
            config.flow = DisParams::preset(DisPreset::parse(&p.flow_preset)?);
            config.margin_px = p.margin_px;
            config.subpixel = p.subpixel;
            config.exposure = p.exposure_compensation();
            config.dot_tracking = p.dot_tracking;
            config.dot_fit = p.dot_fit;
            config.light_box_px = p.light_box_px;
            config.weighted_profiles = p.weighted_profiles;
        }
        Ok(config)
    }
}

/// One patch's working set: its planner, the divergent part of its nHHD
/// (all the raw quantities read) and its result.
#[derive(Debug, Default)]
struct Slot {
    hhd: NaturalHhd,
    part: DivergentPart,
    raw: Option<Result<RawContact>>,
}

/// Time spent in each stage of the last frame, ms: wall-clock time read
/// from [`Instant`] at each stage's ends (a few tens of nanoseconds per
/// frame), kept by [`ContactExtractor::timings`] and
/// [`TactileSensor::timings`]. The stages run one after the other, so
/// `crop + flow + segment + hhd + contacts + tracking` is `total` up to the
/// time between them.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimings {
    /// Crop and copy.
    pub crop_ms: f64,
    /// Exposure compensation, optical flow, and its averaging down to the
    /// analysis grid.
    pub flow_ms: f64,
    /// Segmentation.
    pub segment_ms: f64,
    /// nHHD and raw quantities of every patch (patches in parallel).
    pub hhd_ms: f64,
    /// Calibration: contact columns, force profiles, location and force maps.
    pub contacts_ms: f64,
    /// Tracking, the re-referencing check, and taking a new reference when
    /// it says so.
    pub tracking_ms: f64,
    /// The whole call.
    pub total_ms: f64,
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The finest grid, in full-resolution pixels per cell, on which
/// [`ContactExtractor`] segments and decomposes. A full-resolution flow
/// ([`DisPreset::Fine`]) is averaged 2x2 down to it for those stages: at full
/// resolution the nHHD of a patch costs 4-5x more and the patches it finds
/// are the same, while the force profiles, which do need the finest motion,
/// read the native flow ([`ContactExtractor::finest_flow`]).
pub const ANALYSIS_MIN_SCALE: usize = 2;

/// DIS's native flow brought to the analysis grid: in full-resolution pixel
/// units, and averaged down to [`ANALYSIS_MIN_SCALE`] when finer, with the
/// native flow kept beside it. Shared by [`ContactExtractor`] and the
/// simulator's segmentation sweeps, so that both see the same grid.
#[derive(Debug)]
pub struct AnalysisGrid {
    /// Full-resolution pixels per native flow pixel.
    fine_scale: usize,
    /// Full-resolution pixels per analysis-grid pixel.
    scale: usize,
    /// The flow on the analysis grid, full-resolution pixel units.
    flow: FlowField,
    /// The native flow in full-resolution pixel units, when finer than the
    /// analysis grid (empty otherwise: `flow` is the native flow).
    fine: FlowField,
    /// The analysis-grid flow in its own pixel units (the segmenter's
    /// input), when pooled from a finer flow.
    pooled: FlowField,
}

impl AnalysisGrid {
    /// The grid for a DIS flow of finest scale `finest_scale` (a native
    /// pixel is `2^finest_scale` full-resolution pixels).
    pub fn new(finest_scale: usize) -> Self {
        let fine_scale = 1usize << finest_scale;
        AnalysisGrid {
            fine_scale,
            scale: fine_scale.max(ANALYSIS_MIN_SCALE),
            flow: FlowField::zeros(0, 0),
            fine: FlowField::zeros(0, 0),
            pooled: FlowField::zeros(0, 0),
        }
    }

    /// Full-resolution pixels per analysis-grid pixel.
    pub fn scale(&self) -> usize {
        self.scale
    }

    /// Takes a new native flow (in its own pixel units); returns the
    /// analysis-grid flow in the grid's own pixel units (what the segmenter
    /// reads). Errors on a non-finite flow.
    pub fn update<'a>(&'a mut self, native: &'a FlowField) -> Result<&'a FlowField> {
        let factor = self.scale / self.fine_scale;
        if factor == 1 {
            scale_into(native, self.fine_scale as f32, &mut self.flow);
            self.flow.check_finite("optical flow")?;
            Ok(native)
        } else {
            // A finer flow than the analysis grid: kept whole for the force
            // profiles, and averaged down for segmentation and the nHHD.
            scale_into(native, self.fine_scale as f32, &mut self.fine);
            self.fine.check_finite("optical flow")?;
            pool_into(native, factor, &mut self.pooled)?;
            scale_into(&self.pooled, self.scale as f32, &mut self.flow);
            Ok(&self.pooled)
        }
    }

    /// Where a segmentation on this grid may see motion, for `dis`'s
    /// reference (set with [`Segmenter::set_observable`]): `None`
    /// (everywhere) on a sparse texture ([`Dis::sparse_texture`]), whose
    /// untextured patches take the motion of the textured ones around them;
    /// on a dense texture, the grid pixels that a textured patch of the
    /// reference reaches ([`Dis::textured_coverage_into`]). Beyond them (the
    /// dark coating past the skin's markers) the flow holds only the
    /// camera's noise, which a change of exposure turned into false
    /// contacts. `None` as well before `dis` has a reference.
    pub fn observable(&self, dis: &Dis) -> Option<Mask> {
        if dis.sparse_texture() {
            return None;
        }
        let mut covered = Vec::new();
        let (w, h) = dis.textured_coverage_into(&mut covered);
        let factor = self.scale / self.fine_scale;
        let (gw, gh) = (w / factor, h / factor);
        if gw == 0 || gh == 0 {
            return None;
        }
        // A grid pixel averages `factor x factor` native pixels (a partial
        // last row or column is left out, as in the pooling).
        Some(Mask::from_fn(gw, gh, |x, y| {
            (y * factor..(y + 1) * factor)
                .any(|r| covered[r * w + x * factor..r * w + (x + 1) * factor].contains(&true))
        }))
    }

    /// The analysis-grid flow (full-resolution units) and its scale.
    pub fn flow(&self) -> (&FlowField, usize) {
        (&self.flow, self.scale)
    }

    /// The native flow (full-resolution units) and its scale.
    pub fn finest(&self) -> (&FlowField, usize) {
        if self.fine_scale == self.scale {
            (&self.flow, self.scale)
        } else {
            (&self.fine, self.fine_scale)
        }
    }
}

/// `out = flow * gain`, resized to `flow`'s size if needed; the two
/// components in parallel.
fn scale_into(flow: &FlowField, gain: f32, out: &mut FlowField) {
    if out.size() != flow.size() {
        *out = FlowField::zeros(flow.width(), flow.height());
    }
    let scale = |o: &mut Array2<f32>, x: &Array2<f32>| match (o.as_slice_mut(), x.as_slice()) {
        // Both standard layout (the flows here are): a plain loop over the
        // slices, which vectorises.
        (Some(o), Some(x)) => {
            for (o, &x) in o.iter_mut().zip(x) {
                *o = x * gain;
            }
        }
        (None, _) | (_, None) => ndarray::Zip::from(o).and(x).for_each(|o, &x| *o = x * gain),
    };
    rayon::join(|| scale(&mut out.u, &flow.u), || scale(&mut out.v, &flow.v));
}

/// `dst.assign(src)` (same shapes), row by row as slices when `src`'s rows
/// are contiguous (a crop's are) and `dst` is standard layout: `assign`
/// goes element by element through ndarray's `Zip`.
fn copy_rows(src: &ArrayView2<'_, f32>, dst: &mut Array2<f32>) {
    let rows_ok = src.rows().into_iter().all(|r| r.as_slice().is_some());
    if rows_ok && dst.is_standard_layout() {
        for (s, mut d) in src.rows().into_iter().zip(dst.rows_mut()) {
            d.as_slice_mut()
                .expect("standard layout")
                .copy_from_slice(s.to_slice().expect("contiguous row"));
        }
    } else {
        dst.assign(src);
    }
}

/// Averages `flow` over `factor x factor` blocks into `out`, in the pixel
/// units of the coarser grid (so divided by `factor`); a partial last row or
/// column of blocks is left out. Errors if `flow` holds not even one block.
fn pool_into(flow: &FlowField, factor: usize, out: &mut FlowField) -> Result<()> {
    let (w, h) = (flow.width() / factor, flow.height() / factor);
    if w == 0 || h == 0 {
        return Err(Error::TooSmall {
            what: "flow to average down to the analysis grid".into(),
            width: flow.width(),
            height: flow.height(),
            min_w: factor,
            min_h: factor,
        });
    }
    if out.size() != (w, h) {
        *out = FlowField::zeros(w, h);
    }
    let norm = 1.0 / (factor * factor * factor) as f32;
    let sw = flow.width();
    // The two components in parallel.
    let pool = |src: &Array2<f32>, dst: &mut Array2<f32>| {
        // Plain row slices let the inner loops run without per-element
        // index arithmetic (a standard-layout copy only if `flow` is not).
        let src = src.as_standard_layout();
        let src = src.as_slice().expect("standard layout is contiguous");
        // `out` is the grid's own buffer, made by `FlowField::zeros`.
        let dst = dst.as_slice_mut().expect("standard layout is contiguous");
        for (r, drow) in dst.chunks_exact_mut(w).enumerate() {
            drow.fill(0.0);
            for srow in src[r * factor * sw..(r + 1) * factor * sw].chunks_exact(sw) {
                if factor == 2 {
                    // The `fine` flow's case, written out: the same sums
                    // as the general loop, which the compiler does not
                    // vectorize.
                    for (o, b) in drow.iter_mut().zip(srow.chunks_exact(2)) {
                        *o += b[0] + b[1];
                    }
                } else {
                    for (o, block) in drow.iter_mut().zip(srow.chunks_exact(factor)) {
                        *o += block.iter().sum::<f32>();
                    }
                }
            }
            for o in drow.iter_mut() {
                *o *= norm;
            }
        }
    };
    rayon::join(|| pool(&flow.u, &mut out.u), || pool(&flow.v, &mut out.v));
    Ok(())
}

/// The largest motion, as a fraction of a dot grid's pitch, up to which a
/// contact whose dots were all followed counts as such
/// ([`ContactExtractor::dots_followed`]).
///
/// Why two thirds: on the characterizations of two simulated fingertip
/// sensors (pitches of 22 and 18 px), 627 of the 629 tests that moved by
/// half the pitch to two thirds of it and lost no dot in their box had
/// every dot there within 3 px of its true motion (the other two 0.56 of
/// the pitch); from 0.69 of the pitch on, dots were matched to a
/// neighbour with none lost (`docs/results.md`).
pub const FOLLOWED_PITCH_FRACTION: f64 = 2.0 / 3.0;

/// On random markers, the stretch of the flow over one flow patch (the
/// change of motion across a patch's side, over that side) from which a
/// flow cell counts as torn ([`ContactExtractor::beyond_markers`]).
///
/// Why: the flow follows each patch of the reference's texture as one
/// piece. Where the gel's surface stretches so much that the motion changes
/// across a patch by most of the patch's side, the markers of that patch
/// end up spread far apart and the patch no longer matches anything: the
/// flow tears (vectors in every direction, one contact cut in two or three,
/// a contact point at the image's edge). Measured with [`TORN_FRACTION`]
/// on the simulated fingertip sensor with random markers (a thin, stiff
/// gel; `simulate characterization --sensor fingertip --random-markers`,
/// seeds 1 and 5): the 5 mm sphere's tests from 1.5 N on all tear, at
/// 1 N about three in four, at 0.5 N one or two in 240; the 8 mm punch and
/// the 18 mm fingertip never (at most 6% of their moving cells stretched
/// that far, up to 3 N); every test whose contact point landed more than
/// 20 px off had 30% or more. On the paper's strip (a thick, soft gel) no
/// test of its characterizations came near (at most 6%, a 2 mm rod at
/// 3 N). Fitted without the torn tests, the fingertip sensor's other
/// held-out rows read forces within 0.03 N (`docs/results.md`).
pub const TORN_STRAIN: f64 = 0.75;

/// The fraction of a contact's moving flow cells that must stretch by
/// [`TORN_STRAIN`] or more for its flow to count as torn: a tenth, so that
/// a seam of cells where a thin rod's edge cuts sharply into a soft gel
/// (the strip: at most 6%) does not.
pub const TORN_FRACTION: f64 = 0.1;

/// The flow preset to fit a calibration with when none is asked for:
/// [`DisPreset::Dense`] for random markers on a flat sensor (a geometry
/// located in 2-D, [`SensorGeometry::locates_in_2d`], whose reference shows
/// no regular grid: `grid_pitch` `None`, [`crate::markers::grid_pitch`]),
/// [`DisPreset::Fine`] otherwise.
///
/// Why: on a flat sensor with random markers (a thin gel under a small
/// camera image) the denser flow's patches (every half patch instead of
/// every patch: four times as many) follow the small markers' motion more
/// closely, and fewer presses tear it ([`TORN_STRAIN`]). Measured on the simulated fingertip sensor with random
/// markers, two marker seeds (held-out points in domain, Fx / Fy / Fz):
/// 0.029 / 0.023 / 0.042 N with `fine` against 0.020 / 0.017 / 0.034 N with
/// `dense`, and 0.025 / 0.020 / 0.066 N against 0.020 / 0.020 / 0.051 N; on
/// their random presses `dense` also marks fewer contacts out of domain,
/// for about 2.8 ms a 320x240 frame instead of 1.4-1.6 ms (docs/results.md,
/// "Random markers on the fingertip sensor"). A dot grid's dots are followed
/// one by one ([`crate::markers::DotTracker`]), and the strip's calibration
/// without sweeps fits better with `fine`: both keep the sensor's default.
pub fn fitting_flow_preset(geometry: &SensorGeometry, grid_pitch: Option<f64>) -> DisPreset {
    if flat_random_markers(geometry, grid_pitch) {
        DisPreset::Dense
    } else {
        DisPreset::Fine
    }
}

/// Half-side, in flow patches, of the box of local light that frames of
/// random markers on a flat sensor are divided by ([`fitting_light_box`]).
pub const LIGHT_BOX_PATCHES: usize = 2;

/// The light box to fit a calibration with when none is asked for
/// ([`ExtractorConfig::light_box_px`]): [`LIGHT_BOX_PATCHES`] flow patches
/// of `patch_size` px for random markers on a flat sensor (as
/// [`fitting_flow_preset`] tells them), `None` otherwise.
///
/// Why: on random markers the flow reads a change of the gel's light under
/// a contact (its shading, an object seen through a thin gel) in part as
/// motion, and divided by their own light the frames keep the markers and
/// lose it. Measured on the simulated fingertip sensor with random markers
/// (`dense` flow; its random presses, located x / y, Fx / Fy / Fz): with
/// the light 44% darker about each contact 0.102 / 0.111 mm and 0.086 /
/// 0.072 / 0.125 N undivided, 0.076 / 0.068 mm and 0.071 / 0.077 / 0.096 N
/// divided; under the gel's own light the divided frames read closer too
/// (0.069 / 0.058 mm, 0.072 / 0.072 / 0.091 N against 0.090 / 0.079 mm,
/// 0.078 / 0.084 / 0.114 N; markers of another seed 0.067 / 0.083 mm,
/// 0.076 / 0.092 / 0.110 N against 0.079 / 0.114 mm, 0.096 / 0.109 / 0.148
/// N), and the held-out points much as undivided (docs/results.md, "Random
/// markers on the fingertip sensor"). A box of one patch moved the
/// held-out points' x by 0.3 mm; three patches read the presses worse
/// than two. A dot grid's dots are read against each frame's own light
/// already ([`crate::markers::DotTracker`]), and the strip keeps its frames
/// as they are.
pub fn fitting_light_box(
    geometry: &SensorGeometry,
    grid_pitch: Option<f64>,
    patch_size: usize,
) -> Option<usize> {
    flat_random_markers(geometry, grid_pitch).then_some(LIGHT_BOX_PATCHES * patch_size.max(1))
}

/// The largest light box a fit takes from a user, px of half-side
/// ([`FittingChoices::light_box_px`]): four times a 4K camera's width, far
/// beyond any frame.
pub const MAX_LIGHT_BOX_PX: usize = 16384;

/// What a calibration's extraction is told; each `None` is decided from the
/// dataset ([`fitting_extractor`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FittingChoices {
    /// Follow a regular grid's dots one by one
    /// ([`ExtractorConfig::dot_tracking`]); `None`: when the dataset's
    /// reference shows a regular grid.
    pub dot_tracking: Option<bool>,
    /// Fit the contacts' displacements to their followed dots
    /// ([`ExtractorConfig::dot_fit`]; default on).
    pub dot_fit: bool,
    /// The flow preset; `None`: [`fitting_flow_preset`].
    pub flow: Option<DisPreset>,
    /// Half-side of the light box the frames are divided by, px
    /// ([`ExtractorConfig::light_box_px`]; `Some(0)`: none); `None`:
    /// [`fitting_light_box`].
    pub light_box_px: Option<usize>,
    /// Weigh each flow cell of the profiles by how well the frame matches
    /// the reference there ([`ExtractorConfig::weighted_profiles`]).
    pub weighted_profiles: bool,
}

impl Default for FittingChoices {
    fn default() -> Self {
        FittingChoices {
            dot_tracking: None,
            dot_fit: true,
            flow: None,
            light_box_px: None,
            weighted_profiles: false,
        }
    }
}

/// The extraction a characterization dataset is fitted with, and the
/// pitch of the regular grid of markers its `reference` (the first
/// reference image, cropped as the tests will be) shows (`None`: random
/// markers, [`crate::markers::grid_pitch`]): the default configuration
/// with the split rule of `geometry` ([`SplitRule::for_geometry`]) and
/// `choices`, each one not given decided from the geometry and the pitch
/// (dots followed on a grid, [`fitting_flow_preset`],
/// [`fitting_light_box`]). The thresholds are the default's; a fit sets its
/// own ([`ExtractorConfig::with_thresholds`]).
pub fn fitting_extractor(
    geometry: &SensorGeometry,
    reference: &ArrayRef2<f32>,
    choices: &FittingChoices,
) -> (ExtractorConfig, Option<f64>) {
    let pitch = crate::markers::grid_pitch(reference);
    let flow = choices
        .flow
        .unwrap_or_else(|| fitting_flow_preset(geometry, pitch));
    let mut config = ExtractorConfig::default()
        .with_dot_tracking(choices.dot_tracking.unwrap_or(pitch.is_some()))
        .with_dot_fit(choices.dot_fit)
        .with_split(Some(SplitRule::for_geometry(geometry)))
        .with_flow(DisParams::preset(flow));
    config.light_box_px = match choices.light_box_px {
        Some(0) => None,
        Some(r) => Some(r),
        None => fitting_light_box(geometry, pitch, config.flow.patch_size),
    };
    config.weighted_profiles = choices.weighted_profiles;
    (config, pitch)
}

/// Whether a sensor shows random markers on a flat surface: located in 2-D
/// ([`SensorGeometry::locates_in_2d`]), its reference showing no regular
/// grid (`grid_pitch` `None`).
fn flat_random_markers(geometry: &SensorGeometry, grid_pitch: Option<f64>) -> bool {
    geometry.locates_in_2d() && grid_pitch.is_none()
}

/// Flow -> patches -> nHHD -> raw quantities, on cropped grayscale frames
/// (see the module docs). Built once; nothing is allocated per frame once the
/// patch sizes have been seen.
#[derive(Debug)]
pub struct ContactExtractor {
    config: ExtractorConfig,
    dis: Dis,
    exposure: ExposureCompensator,
    /// The last frame brought onto the reference's exposure.
    compensated: Array2<f32>,
    segmenter: Segmenter,
    grid: AnalysisGrid,
    patches: Vec<ContactPatch>,
    slots: Vec<Slot>,
    raws: Vec<RawContact>,
    /// The last frame's patches whose motion lies only where the reference
    /// has no texture ([`ContactPatch::seen`] false): not contacts.
    unseen: Vec<RawContact>,
    locator: ContactLocator,
    timings: StageTimings,
    /// The pitch of the reference's markers when they form a regular grid
    /// ([`crate::markers::grid_pitch`]).
    marker_pitch: Option<f64>,
    /// The dots of a regular grid, followed when the configuration says so.
    dots: DotTracker,
    /// The native flow with the dots' motion written over it.
    dot_flow: FlowField,
    /// Every contact's point before the dots' lines move it
    /// ([`ContactPointMethod::MotionLines`]).
    starts: Vec<[f64; 2]>,
    /// The frames divided by their own light, when the configuration says
    /// so ([`ExtractorConfig::light_box_px`]).
    lit: LightDivision,
    /// The confidence of the last flow's cells, against the reference as
    /// the flow saw it ([`ExtractorConfig::weighted_profiles`]).
    weighting: ProfileWeighting,
    /// The finest flow reweighted by that confidence.
    weighted_flow: FlowField,
}

/// [`ContactExtractor::profile_flow`] from the extractor's fields (so that
/// [`ContactExtractor::locate`] can read it beside its mutable ones): the
/// reweighted flow when `weighted`, else the finest flow; at the finest
/// flow's scale either way.
fn profile_flow_of<'a>(
    weighted: bool,
    grid: &'a AnalysisGrid,
    weighted_flow: &'a FlowField,
) -> (&'a FlowField, usize) {
    let (finest, scale) = grid.finest();
    (if weighted { weighted_flow } else { finest }, scale)
}

/// The working set of [`ExtractorConfig::light_box_px`]: the reference's
/// mean light (the level every divided frame is brought to), the running
/// sums and local light of the last frame, and the divided frame.
#[derive(Debug, Default)]
struct LightDivision {
    level: f32,
    work: Vec<f64>,
    light: Array2<f32>,
    out: Array2<f32>,
}

impl LightDivision {
    /// The last frame [`divide`](Self::divide) gave.
    fn divided(&self) -> &Array2<f32> {
        &self.out
    }

    /// `image` divided by its own light over boxes of half-side `r`, at the
    /// reference's level (`reference`: `image` is the reference, whose mean
    /// sets that level).
    fn divide(&mut self, image: &ArrayRef2<f32>, r: usize, reference: bool) -> &Array2<f32> {
        if reference {
            let n = image.len().max(1) as f64;
            self.level = (image.iter().map(|&v| f64::from(v)).sum::<f64>() / n) as f32;
        }
        crate::frame::divide_by_light_into(
            image,
            r,
            self.level,
            &mut self.work,
            &mut self.light,
            &mut self.out,
        );
        &self.out
    }
}

impl ContactExtractor {
    /// An extractor for `config` (checked here).
    pub fn new(config: ExtractorConfig) -> Result<Self> {
        if let Some(r) = config.light_box_px
            && !(1..=crate::frame::MAX_FRAME_SIDE).contains(&r)
        {
            return Err(Error::param(
                "light_box_px",
                format!("{r}: must lie within 1..={}", crate::frame::MAX_FRAME_SIDE),
            ));
        }
        let dis = Dis::new(config.flow.clone())?;
        let grid = AnalysisGrid::new(config.flow.finest_scale);
        let segmenter = Segmenter::new(SegmenterConfig {
            thresholds: config.thresholds,
            margin: config.margin_px,
            scale: grid.scale() as f64,
        })?
        .with_split(config.split)?;
        Ok(ContactExtractor {
            exposure: ExposureCompensator::new(config.exposure),
            compensated: Array2::zeros((0, 0)),
            config,
            dis,
            segmenter,
            grid,
            patches: Vec::new(),
            slots: Vec::new(),
            raws: Vec::new(),
            unseen: Vec::new(),
            locator: ContactLocator::new(),
            timings: StageTimings::default(),
            marker_pitch: None,
            dots: DotTracker::new(),
            dot_flow: FlowField::zeros(0, 0),
            starts: Vec::new(),
            lit: LightDivision::default(),
            weighting: ProfileWeighting::new(),
            weighted_flow: FlowField::zeros(0, 0),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ExtractorConfig {
        &self.config
    }

    /// Measures the contact column (`x_px`) of every contact of the last
    /// [`extract`](Self::extract) again by `method`, from the finest flow,
    /// and returns them. [`extract`](Self::extract) gives each contact the
    /// argmin of its divergence potential, which shear slides sideways; a
    /// calibrated sensor re-measures with its calibration's method, and
    /// without a calibration [`ContactPointMethod::DEFAULT`] (the slope
    /// peak) is the one to use, as `track --raw` does. With
    /// [`ContactPointMethod::MotionLines`] and the dots of a grid followed,
    /// each contact's point then moves to where its dots' motion lines meet
    /// ([`DotTracker::motion_centre`]), its row as well as its column.
    /// Where the dots are followed and [`ExtractorConfig::dot_fit`] is on,
    /// each contact's displacements (`ds1`, `ds2`, `dn`) then come from a
    /// round load's field fitted to its dots about that point
    /// ([`crate::markers::round`]). Errors on a method parameter out of its
    /// range.
    pub fn locate(&mut self, method: ContactPointMethod) -> Result<&[RawContact]> {
        let (flow, scale) = profile_flow_of(
            self.config.weighted_profiles,
            &self.grid,
            &self.weighted_flow,
        );
        // The unseen patches (motion past the skin's texture only) are not
        // contacts, but they bound each contact's search as any neighbour
        // does: the contacts come out as they would with them.
        let n = self.raws.len();
        self.raws.append(&mut self.unseen);
        let refined = self.locator.refine(
            method,
            &mut self.raws,
            flow.u.view(),
            flow.v.view(),
            scale as f64,
        );
        if refined.is_ok()
            && matches!(method, ContactPointMethod::MotionLines { .. })
            && self.dots.is_active()
        {
            self.starts.clear();
            self.starts
                .extend(self.raws.iter().map(|r| [r.x_px, r.y_px]));
            for (k, raw) in self.raws[..n].iter_mut().enumerate() {
                if let Some([x, y]) = self.dots.motion_centre(raw.bbox, &self.starts, k) {
                    raw.x_px = x;
                    raw.y_px = y;
                }
            }
        }
        if refined.is_ok() && self.config.dot_fit && self.dots.is_active() {
            self.fit_dots(n);
        }
        self.unseen.extend(self.raws.drain(n..));
        refined?;
        Ok(&self.raws)
    }

    /// The displacements and point of the first `n` raw contacts from a
    /// round load's field fitted to their dots ([`ExtractorConfig::dot_fit`]),
    /// about each contact's current point, each on the dots nearer to it
    /// than to the others.
    fn fit_dots(&mut self, n: usize) {
        let Some(pitch) = self.marker_pitch else {
            return;
        };
        self.starts.clear();
        self.starts
            .extend(self.raws[..n].iter().map(|r| [r.x_px, r.y_px]));
        for (k, raw) in self.raws[..n].iter_mut().enumerate() {
            let fit = round::fit_round_field(
                self.dots.dots(),
                self.dots.displacements(),
                &self.starts,
                k,
                pitch,
            );
            raw.dot_fit_residual = None;
            if let Some(f) = fit {
                let holds = f.holds();
                // Where the fit does not hold, the dots' own sums: the same
                // quantities in the same units, swinging with the phase.
                let ([s1, s2], n) = if holds {
                    // The load's centre: the field's own, which shear does
                    // not slide sideways and a neighbour does not pull.
                    raw.x_px = f.centre[0];
                    raw.y_px = f.centre[1];
                    (f.shear, f.normal)
                } else {
                    f.sums
                };
                raw.ds1 = s1;
                raw.ds2 = s2;
                raw.dn = n;
                raw.dot_fit_residual = holds.then_some(f.residual);
            }
        }
    }

    /// Whether a contact's displacements should have come from its dots'
    /// fitted field ([`ExtractorConfig::dot_fit`], the dots followed) but
    /// the fit does not hold ([`round::RoundFit::holds`]) or could not be
    /// made: its displacements are then the dots' plain sums (or, with
    /// fewer than [`round::MIN_DOTS`]
    /// dots, the patch's), which swing with the contact's place against
    /// the dots, and the sensor marks it [`crate::Contact::out_of_domain`].
    pub fn dot_fit_failed(&self, raw: &RawContact) -> bool {
        self.config.dot_fit
            && self.dots.is_active()
            && self.marker_pitch.is_some()
            && raw.dot_fit_residual.is_none()
    }

    /// Sets the reference (unloaded) frame, already cropped.
    pub fn set_reference(&mut self, reference: &ArrayRef2<f32>) -> Result<()> {
        let seen = match self.config.light_box_px {
            Some(r) => self.lit.divide(reference, r, true).view(),
            None => reference.view(),
        };
        self.dis.set_reference(&seen)?;
        if self.config.weighted_profiles {
            self.weighting.set_reference(seen);
        }
        self.exposure.set_reference(reference);
        self.segmenter
            .set_observable(self.grid.observable(&self.dis));
        self.marker_pitch = crate::markers::grid_pitch(reference);
        match self.marker_pitch {
            // A pitch outside the tracker's range: the flow alone.
            Some(p)
                if self.config.dot_tracking && self.dots.set_reference(reference, p).is_ok() => {}
            _ => self.dots.clear(),
        }
        Ok(())
    }

    /// Whether the dots of a regular marker grid are followed one by one:
    /// the configuration asks for it and the reference shows such a grid
    /// ([`ExtractorConfig::dot_tracking`]).
    pub fn follows_dots(&self) -> bool {
        self.dots.is_active()
    }

    /// The pitch, in pixels, of the reference's markers when they form a
    /// regular grid (a pattern whose autocorrelation repeats,
    /// [`crate::markers::grid_pitch`]); `None` for random markers or before
    /// a reference is set.
    pub fn marker_pitch(&self) -> Option<f64> {
        self.marker_pitch
    }

    /// Whether a contact's motion is beyond what the reference's markers can
    /// tell: on a regular grid, a flow of half the pitch or more
    /// ([`RawContact::peak_px`]), where a marker cannot be told from its
    /// neighbour; on random markers, a torn flow: at least [`TORN_FRACTION`]
    /// of the moving cells in the contact's box (motion of the segmentation's
    /// magnitude threshold or more) stretch by [`TORN_STRAIN`] or more over
    /// one flow patch ([`ContactExtractor::flow_strain_fraction`]). Read on
    /// the last frame's flow: call it before the next frame.
    pub fn beyond_markers(&self, raw: &RawContact) -> bool {
        match self.marker_pitch {
            Some(p) => raw.peak_px >= 0.5 * p,
            None => self.flow_strain_fraction(raw.bbox, TORN_STRAIN) >= TORN_FRACTION,
        }
    }

    /// The fraction of the moving cells of the last frame's finest flow
    /// within `bbox` (full-resolution pixels of the cropped image; cells
    /// whose motion reaches the segmentation's magnitude threshold) whose
    /// flow stretches by `strain` or more over one flow patch: the change of
    /// `(u, v)` to the cell one patch side further along x and along y (where
    /// it is inside the image), `sqrt(|du/dx|^2 + |dv/dx|^2 + |du/dy|^2 +
    /// |dv/dy|^2)` with the differences taken over the patch side
    /// ([`FlowField::stretched_fraction`] on the flow's finest level, whose
    /// patch spans `patch_size` cells; cells sampled every half patch side,
    /// a sixteenth of them with 8 px patches: a
    /// strip contact's box of 900 x 200 px takes 17 us, half a percent of the
    /// strip's `fine` flow, `cargo bench --bench flow -- stretched_fraction`).
    /// 0 when no sampled cell moves.
    pub fn flow_strain_fraction(&self, bbox: Roi, strain: f64) -> f64 {
        // The native flow: one cell per pixel of the flow's finest level,
        // where a patch spans `patch_size` cells.
        let (flow, scale) = self.grid.finest();
        let scale = scale.max(1);
        let lag = self.config.flow.patch_size.max(1);
        let (x0, y0) = (bbox.x / scale, bbox.y / scale);
        let cells = Roi {
            x: x0,
            y: y0,
            w: bbox
                .x
                .saturating_add(bbox.w)
                .div_ceil(scale)
                .saturating_sub(x0),
            h: bbox
                .y
                .saturating_add(bbox.h)
                .div_ceil(scale)
                .saturating_sub(y0),
        };
        flow.stretched_fraction(cells, scale, lag, self.config.thresholds.magnitude, strain)
    }

    /// Whether a contact's dots were all followed: the dots of a regular
    /// grid are followed one by one, none whose reference centre lies in
    /// the contact's box was lost in this frame
    /// ([`DotTracker::lost_in`]), and its motion stayed under
    /// [`FOLLOWED_PITCH_FRACTION`] of the pitch. False without followed
    /// dots.
    ///
    /// A contact beyond the markers ([`ContactExtractor::beyond_markers`])
    /// whose dots were all followed is still marked out of domain at run
    /// time, where nothing checks its dots against the truth; a
    /// characterization fits its maps on such tests
    /// ([`crate::calibration::fit::Extraction::dots_followed`]), since on
    /// the simulated sensors their dots moved as the truth did.
    pub fn dots_followed(&self, raw: &RawContact) -> bool {
        self.dots.is_active()
            && self
                .marker_pitch
                .is_some_and(|p| raw.peak_px < FOLLOWED_PITCH_FRACTION * p)
            && !self.dots.lost_in(raw.bbox)
    }

    /// The dots of a regular grid as the extractor follows them: their
    /// reference centres and their motion in the last frame
    /// ([`DotTracker::dots`], [`DotTracker::displacements`]); inactive
    /// unless [`ContactExtractor::follows_dots`].
    pub fn dot_tracker(&self) -> &DotTracker {
        &self.dots
    }

    /// `(width, height)` of the reference, `(0, 0)` before one is set.
    pub fn size(&self) -> (usize, usize) {
        self.dis.size()
    }

    /// Full-resolution pixels per pixel of the native flow.
    pub fn scale(&self) -> usize {
        self.grid.scale()
    }

    /// The raw quantities of every contact patch of `frame` (cropped, same
    /// size as the reference), strongest first.
    pub fn extract(&mut self, frame: &ArrayRef2<f32>) -> Result<&[RawContact]> {
        let t0 = Instant::now();
        let t = t0;
        if self.dis.size() == (0, 0) {
            return Err(Error::NoReference);
        }
        self.exposure
            .compensate_into(frame, &mut self.compensated)?;
        let seen = match self.config.light_box_px {
            Some(r) => self.lit.divide(&self.compensated, r, false).view(),
            None => self.compensated.view(),
        };
        self.dis.compute_native(&seen)?;
        let (native, native_scale) = self.dis.native_flow().ok_or(Error::NoReference)?;
        let seg_input = if self.dots.is_active() {
            self.dot_flow.clone_from(native);
            self.dots
                .refine(&self.compensated, &mut self.dot_flow, native_scale)?;
            self.grid.update(&self.dot_flow)?
        } else {
            self.grid.update(native)?
        };
        self.timings.flow_ms = ms(t);

        let t = Instant::now();
        self.segmenter.segment_into(seg_input, &mut self.patches)?;
        self.timings.segment_ms = ms(t);

        if self.config.weighted_profiles {
            // Counted with the flow: it reweighs the flow's cells.
            let t = Instant::now();
            let (finest, scale) = self.grid.finest();
            let seen = match self.config.light_box_px {
                Some(_) => self.lit.divided().view(),
                None => self.compensated.view(),
            };
            self.weighting
                .reweight_into(seen, finest, scale, &mut self.weighted_flow)?;
            self.timings.flow_ms += ms(t);
        }

        let t = Instant::now();
        let n = self.patches.len();
        if self.slots.len() < n {
            self.slots.resize_with(n, Slot::default);
        }
        let (flow, scale) = self.grid.flow();
        let (s, subpixel) = (scale as f64, self.config.subpixel);
        self.slots[..n]
            .par_iter_mut()
            .zip(self.patches.par_iter())
            .for_each(|(slot, patch)| {
                slot.raw = Some(measure(slot, flow, patch, s, subpixel));
            });
        self.raws.clear();
        self.unseen.clear();
        for (slot, patch) in self.slots[..n].iter_mut().zip(&self.patches) {
            let raw = slot.raw.take().expect("set above")?;
            if patch.seen {
                self.raws.push(raw);
            } else {
                self.unseen.push(raw);
            }
        }
        self.raws.sort_by(|a, b| b.strength.total_cmp(&a.strength));
        self.timings.hhd_ms = ms(t);
        self.timings.total_ms = ms(t0);
        Ok(&self.raws)
    }

    /// The raw contacts of the last [`extract`](Self::extract).
    pub fn raws(&self) -> &[RawContact] {
        &self.raws
    }

    /// The last frame's patches that are not contacts: their motion lies
    /// only where the reference has no texture ([`ContactPatch::seen`]),
    /// such as the dark coating past the skin's markers, where the flow is
    /// the camera's noise. [`locate`](Self::locate) still counts them as
    /// neighbours, and they are measured as contacts are.
    pub fn unseen(&self) -> &[RawContact] {
        &self.unseen
    }

    /// The last flow on the analysis grid (where the patches and their
    /// nHHD live), in full-resolution pixel units, and the grid's scale
    /// (full-resolution pixels per flow pixel). This is DIS's native flow,
    /// or, for a flow finer than [`ANALYSIS_MIN_SCALE`], that flow averaged
    /// down to it.
    pub fn flow(&self) -> (&FlowField, usize) {
        self.grid.flow()
    }

    /// The last flow at DIS's native resolution, in full-resolution pixel
    /// units, and its scale: the finest motion there is, from which the
    /// force profiles and the contact column are measured. The same as
    /// [`flow`](Self::flow) unless the flow is finer than the analysis grid.
    pub fn finest_flow(&self) -> (&FlowField, usize) {
        self.grid.finest()
    }

    /// The flow the motion profiles are summed from (the contact's column
    /// and the forces matched to the profiles), at the scale of
    /// [`finest_flow`](Self::finest_flow): that flow, or with
    /// [`ExtractorConfig::weighted_profiles`] that flow with each cell's
    /// motion reweighted within its column by how well the frame matches
    /// the reference there ([`ProfileWeighting::reweight_into`]), so that a
    /// column's sum is the weighted mean of its cells times its height.
    pub fn profile_flow(&self) -> (&FlowField, usize) {
        profile_flow_of(
            self.config.weighted_profiles,
            &self.grid,
            &self.weighted_flow,
        )
    }

    /// The patches of the last frame (native-resolution boxes), in the order
    /// the segmentation found them.
    pub fn patches(&self) -> &[ContactPatch] {
        &self.patches
    }

    /// The divergent part of the nHHD of the `k`-th patch of the last frame
    /// (same order as [`patches`](Self::patches)): the divergence, its
    /// potential `D` and `d = grad D`, all the raw quantities read. The
    /// rotational and harmonic parts are not computed;
    /// [`NaturalHhd::decompose`] gives them for a patch's flow
    /// ([`ContactPatch::view`] of [`flow`](Self::flow)).
    pub fn divergent_part(&self, k: usize) -> Option<&DivergentPart> {
        (k < self.patches.len()).then(|| &self.slots[k].part)
    }

    /// The segmenter (its mask and contour boxes, for display).
    pub fn segmenter(&self) -> &Segmenter {
        &self.segmenter
    }

    /// The camera's `(gain, offset)` against the reference estimated for
    /// the last frame and taken out before its flow (`(1, 0)` when the
    /// compensation is off).
    pub fn exposure(&self) -> (f64, f64) {
        self.exposure.last()
    }

    /// Stage timings of the last frame (crop, contacts and tracking left at
    /// 0 here; `total` is flow, segmentation and nHHD).
    pub fn timings(&self) -> &StageTimings {
        &self.timings
    }
}

/// nHHD and raw quantities of one patch.
fn measure(
    slot: &mut Slot,
    flow: &FlowField,
    patch: &ContactPatch,
    s: f64,
    subpixel: bool,
) -> Result<RawContact> {
    let b = patch.bbox;
    let (u, v) = patch.view(flow)?;
    let part = &mut slot.part;
    slot.hhd.divergent_into(u, v, s, s, part)?;
    let fields = PatchFields {
        u,
        v,
        potential_d: part.potential_d.view(),
        d_u: part.d.u.view(),
        d_v: part.d.v.view(),
    };
    let mut raw = raw_quantities(
        &fields,
        PatchGrid {
            x0: b.x,
            y0: b.y,
            scale: s,
        },
        subpixel,
    )?;
    let si = s as usize;
    raw.area_px = (patch.area * si * si) as u64;
    raw.bbox = Roi::new(b.x * si, b.y * si, b.width * si, b.height * si);
    // Summed |flow| in full-resolution units: flow pixels x area.
    raw.strength = patch.flow_sum * s * s * s;
    Ok(raw)
}

/// Side of the square tiles (full-resolution pixels) over which the flow
/// magnitude is averaged before the re-referencing policy compares it with
/// its limit.
pub const QUIET_TILE_PX: usize = 16;

/// The largest mean `|flow|` over `tile x tile` tiles of `flow` (the last
/// row and column of tiles may be smaller).
///
/// Why tiles and not the largest pixel: at rest the flow's largest pixel sits
/// on the image border, where DIS is least constrained, and reaches ~0.5-0.6
/// px with the accurate preset on the simulator (the 99.9th percentile stays
/// near 0.2-0.3 px): one noisy pixel would veto re-referencing forever.
/// Averaging over a tile removes that, while a sub-threshold touch, which
/// moves a whole area, still shows.
pub fn max_tile_mean(flow: &FlowField, tile: usize) -> f64 {
    max_tile_mean_where(flow, tile, &[], 0)
}

/// Standard deviation of the reference (grey levels) below which a quiet
/// tile is taken as untextured and left out of the re-referencing check
/// ([`textured_tiles_into`]). Camera noise alone gives about 1-2 grey levels
/// on the simulator's black strip ends; marker texture gives tens.
pub const QUIET_MIN_TEXTURE: f32 = 4.0;

/// Per `tile_px x tile_px` tile of `reference` (row-major, the last row and
/// column of tiles possibly smaller), whether its standard deviation
/// reaches `min_sd`, into `out`; returns the number of tiles per row.
///
/// Why: where the reference has no texture (the black ends of the strip,
/// outside the skin) the optical flow is not measurable and DIS fills it
/// with whatever its coarse levels guessed: between two renders of the
/// unloaded skin the accurate preset put 0.7-0.95 px of mean flow in a
/// corner tile, which vetoed re-referencing for good.
pub fn textured_tiles_into(
    reference: &ArrayRef2<f32>,
    tile_px: usize,
    min_sd: f32,
    out: &mut Vec<bool>,
) -> usize {
    let (h, w) = reference.dim();
    let tile = tile_px.max(1);
    let tiles_x = w.div_ceil(tile);
    out.clear();
    for ty in (0..h).step_by(tile) {
        for tx in (0..w).step_by(tile) {
            let (ye, xe) = ((ty + tile).min(h), (tx + tile).min(w));
            let (mut s, mut s2) = (0.0f64, 0.0f64);
            for y in ty..ye {
                for x in tx..xe {
                    let v = f64::from(reference[[y, x]]);
                    s += v;
                    s2 += v * v;
                }
            }
            let n = ((ye - ty) * (xe - tx)) as f64;
            let var = (s2 / n - (s / n).powi(2)).max(0.0);
            out.push(var.sqrt() >= f64::from(min_sd));
        }
    }
    tiles_x
}

/// [`max_tile_mean`] over the tiles that `mask` (from
/// [`textured_tiles_into`] with tiles of `tile * scale` full-resolution
/// pixels, `tiles_x` per row) marks as textured; tiles outside the mask's
/// range count as textured.
pub fn max_tile_mean_where(flow: &FlowField, tile: usize, mask: &[bool], tiles_x: usize) -> f64 {
    let (w, h) = flow.size();
    let tile = tile.max(1);
    let mut best = 0.0f64;
    for ty in (0..h).step_by(tile) {
        for tx in (0..w).step_by(tile) {
            let k = (ty / tile) * tiles_x + tx / tile;
            if tx / tile < tiles_x && !mask.get(k).copied().unwrap_or(true) {
                continue;
            }
            let (ye, xe) = ((ty + tile).min(h), (tx + tile).min(w));
            let mut sum = 0.0f64;
            for y in ty..ye {
                for x in tx..xe {
                    sum += flow.u[[y, x]].hypot(flow.v[[y, x]]) as f64;
                }
            }
            let mean = sum / ((ye - ty) * (xe - tx)) as f64;
            if mean.is_nan() {
                return f64::NAN;
            }
            best = best.max(mean);
        }
    }
    best
}

/// Everything a [`TactileSensor`] needs besides its calibration.
///
/// Prefer [`SensorConfig::from_calibration`] (or [`TactileSensor::from_calibration`]
/// and [`TactileSensor::builder`]): a calibration's maps hold only for the
/// thresholds, flow preset and crop it was fitted with. `Default` is the
/// library's generic setting (HIGH thresholds, the `fine` flow), which matches a
/// calibration only if it was fitted that way.
#[derive(Debug, Clone, PartialEq, Default)]
#[non_exhaustive]
pub struct SensorConfig {
    /// Crop of the camera frame to the sensing area; `None` takes the
    /// calibration's crop. Another crop than the calibration's is an error
    /// unless `force_crop` is set: the calibration's pixel coordinates refer
    /// to its own crop, so its locations and forces would not hold.
    pub crop: Option<Roi>,
    /// Accept a `crop` that differs from the calibration's (the contacts are
    /// then marked [`Contact::out_of_domain`] wherever they leave what the
    /// calibration knows).
    pub force_crop: bool,
    /// Flow, segmentation and patch settings.
    pub extractor: ExtractorConfig,
    /// Tracking: identity, hysteresis, smoothing.
    pub tracker: TrackerConfig,
    /// When to take a fresh reference.
    pub rereference: ReferencePolicy,
}

/// A calibrated optical tactile sensor: frames in, contacts out (see the module docs).
#[derive(Debug)]
pub struct TactileSensor {
    config: SensorConfig,
    calibration: Calibration,
    crop: Roi,
    frame_size: Option<(usize, usize)>,
    cropped: Array2<f32>,
    extractor: ContactExtractor,
    tracker: Tracker,
    monitor: ReferenceMonitor,
    detections: Vec<Contact>,
    /// The last frame's raw contacts, as the calibration measures them.
    raws: Vec<RawContact>,
    matcher: ForceMatcher,
    /// Per quiet tile of the reference: textured (re-referencing check).
    textured: Vec<bool>,
    textured_x: usize,
    last_t: Option<f64>,
    rereferenced: bool,
    references: u64,
    non_finite: u64,
    timings: StageTimings,
}

impl SensorConfig {
    /// The settings `calibration` was fitted with: its crop, thresholds and
    /// (when recorded) flow preset, patch margin and sub-pixel switch; default
    /// tracking and re-referencing. Errors if the recorded settings are not
    /// valid (an unknown flow preset, say).
    pub fn from_calibration(calibration: &Calibration) -> Result<Self> {
        Ok(SensorConfig {
            crop: Some(calibration.setup.crop),
            force_crop: false,
            extractor: ExtractorConfig::from_setup(&calibration.setup)?,
            tracker: TrackerConfig::default(),
            rereference: ReferencePolicy::default(),
        })
    }
}

/// Builds a [`TactileSensor`] from a calibration, with overrides
/// ([`TactileSensor::builder`]). Every setting starts as the calibration
/// records it ([`SensorConfig::from_calibration`]).
///
/// ```no_run
/// use optical_tactile::flow::dis::{DisParams, DisPreset};
/// use optical_tactile::{Calibration, TactileSensor, ThresholdPreset};
///
/// let calibration = Calibration::load("fixtures/calibration.json")?;
/// // Robust to vibration, at the cost of the weakest presses; a faster flow.
/// let sensor = TactileSensor::builder(calibration)
///     .thresholds(ThresholdPreset::High)
///     .flow(DisParams::preset(DisPreset::Fast))
///     .build()?;
/// # Ok::<(), optical_tactile::Error>(())
/// ```
#[derive(Debug)]
#[must_use = "a builder does nothing until `build` is called"]
pub struct SensorBuilder {
    calibration: Calibration,
    config: Result<SensorConfig>,
}

impl SensorBuilder {
    fn with(mut self, f: impl FnOnce(&mut SensorConfig)) -> Self {
        if let Ok(c) = &mut self.config {
            f(c);
        }
        self
    }

    /// Segmentation thresholds (a [`Thresholds`] or a
    /// [`ThresholdPreset`](crate::segment::ThresholdPreset)). The calibration's
    /// force maps were fitted with its own thresholds: others change the
    /// patches' extent and so the raw quantities the maps read.
    pub fn thresholds(self, thresholds: impl Into<Thresholds>) -> Self {
        let t = thresholds.into();
        self.with(|c| c.extractor.thresholds = t)
    }

    /// Optical flow parameters (a [`DisParams`], e.g. `DisParams::preset(DisPreset::Fast)`).
    pub fn flow(self, params: DisParams) -> Self {
        self.with(|c| c.extractor.flow = params)
    }

    /// Crop of the camera frame. The calibration's pixel coordinates refer
    /// to its own crop: another one is an error at `build` unless
    /// [`SensorBuilder::force_crop`].
    pub fn crop(self, crop: Roi) -> Self {
        self.with(|c| c.crop = Some(crop))
    }

    /// Accept a crop that differs from the calibration's.
    pub fn force_crop(self, force: bool) -> Self {
        self.with(|c| c.force_crop = force)
    }

    /// Tracking: identity, hysteresis and smoothing.
    pub fn tracker(self, tracker: TrackerConfig) -> Self {
        self.with(|c| c.tracker = tracker)
    }

    /// When to take a fresh reference.
    pub fn rereference(self, policy: ReferencePolicy) -> Self {
        self.with(|c| c.rereference = policy)
    }

    /// Any other change to the configuration.
    pub fn configure(self, f: impl FnOnce(&mut SensorConfig)) -> Self {
        self.with(f)
    }

    /// The configuration the sensor will have (`None` if `build` will fail).
    pub fn config(&self) -> Option<&SensorConfig> {
        self.config.as_ref().ok()
    }

    /// The sensor. Errors if the calibration's recorded settings are invalid
    /// or an override is.
    pub fn build(self) -> Result<TactileSensor> {
        TactileSensor::new(self.config?, self.calibration)
    }
}

impl TactileSensor {
    /// A sensor that measures as `calibration` was fitted: crop, thresholds
    /// and flow settings from the calibration, default tracking and
    /// re-referencing. The main way to build one; [`TactileSensor::builder`]
    /// for overrides.
    pub fn from_calibration(calibration: Calibration) -> Result<Self> {
        Self::builder(calibration).build()
    }

    /// A builder starting from the calibration's settings
    /// ([`SensorConfig::from_calibration`]).
    pub fn builder(calibration: Calibration) -> SensorBuilder {
        SensorBuilder {
            config: SensorConfig::from_calibration(&calibration),
            calibration,
        }
    }

    /// A sensor for `config` and `calibration`, for full control. The
    /// thresholds and flow settings of `config` should be the ones the
    /// calibration was fitted with (see [`SensorConfig::from_calibration`]).
    pub fn new(config: SensorConfig, calibration: Calibration) -> Result<Self> {
        let crop = config.crop.unwrap_or(calibration.setup.crop);
        let fitted = calibration.setup.crop;
        if crop != fitted && !config.force_crop {
            return Err(Error::param(
                "crop",
                format!(
                    "{} differs from the calibration's crop {}: its pixel coordinates \
                     refer to that crop, so locations and forces would not hold \
                     (set force_crop to use it anyway)",
                    crop.to_arg(),
                    fitted.to_arg()
                ),
            ));
        }
        Ok(TactileSensor {
            extractor: ContactExtractor::new(config.extractor.clone())?,
            tracker: Tracker::new(config.tracker)?,
            monitor: ReferenceMonitor::new(config.rereference)?,
            config,
            calibration,
            crop,
            frame_size: None,
            cropped: Array2::zeros((0, 0)),
            detections: Vec::new(),
            raws: Vec::new(),
            matcher: ForceMatcher::new(),
            textured: Vec::new(),
            textured_x: 0,
            last_t: None,
            rereferenced: false,
            references: 0,
            non_finite: 0,
            timings: StageTimings::default(),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &SensorConfig {
        &self.config
    }

    /// The calibration.
    pub fn calibration(&self) -> &Calibration {
        &self.calibration
    }

    /// The crop applied to every frame.
    pub fn crop(&self) -> Roi {
        self.crop
    }

    fn crop_into_buffer(&mut self, frame: &ArrayRef2<f32>) -> Result<()> {
        let view = self.crop.crop(frame)?;
        if self.cropped.dim() != view.dim() {
            self.cropped = Array2::zeros(view.dim());
        }
        copy_rows(&view, &mut self.cropped);
        Ok(())
    }

    /// Takes `frame` (a whole camera frame, unloaded) as the reference.
    /// Errors if the crop does not fit it.
    pub fn set_reference(&mut self, frame: &ArrayRef2<f32>) -> Result<()> {
        self.crop_into_buffer(frame)?;
        self.extractor.set_reference(&self.cropped)?;
        self.update_texture();
        self.frame_size = Some((frame.ncols(), frame.nrows()));
        self.tracker.reset();
        self.monitor.reset();
        self.references += 1;
        Ok(())
    }

    /// Processes one frame taken at `t_s` seconds: the contacts in it, each
    /// with a stable id, location (mm) and force (N) in the sensor frame.
    ///
    /// Errors (nothing changes): no reference yet, a frame of another size than
    /// the reference, non-finite pixels.
    pub fn process(&mut self, frame: &ArrayRef2<f32>, t_s: f64) -> Result<&[Contact]> {
        let t0 = Instant::now();
        let size = self.frame_size.ok_or(Error::NoReference)?;
        if (frame.ncols(), frame.nrows()) != size {
            return Err(Error::shape(
                "frame against the reference",
                size,
                (frame.ncols(), frame.nrows()),
            ));
        }
        self.crop_into_buffer(frame)?;
        let crop_ms = ms(t0);
        self.extractor.extract(&self.cropped)?;

        let t = Instant::now();
        self.detections.clear();
        let geometry = self.calibration.setup.geometry;
        // Measure the contact columns the way the calibration was fitted
        // (shear-robust window, if it records one), then locate each contact
        // and rotate its displacements into the sensor frame there.
        // The unseen patches (motion past the skin's texture only) take part
        // as every patch did, then are dropped: not contacts.
        let seen = self
            .extractor
            .locate(self.calibration.contact_point_method())?
            .len();
        self.raws.clear();
        self.raws.extend_from_slice(self.extractor.raws());
        self.raws.extend_from_slice(self.extractor.unseen());
        let (flow, scale) = self.extractor.profile_flow();
        self.calibration.match_forces_with(
            &mut self.matcher,
            &mut self.raws,
            flow.u.view(),
            flow.v.view(),
            scale as f64,
        )?;
        self.raws.truncate(seen);
        // Patches with motion but no press (far-field motion) are dropped.
        let cal = &self.calibration;
        self.raws.retain(|r| cal.is_press(r));
        for raw in &mut self.raws {
            let loc = self.calibration.location_of(raw)?;
            raw.d_sensor = sensor_displacements(&geometry, loc[0], raw);
            let mut contact = self.calibration.contact(raw)?;
            contact.out_of_domain |=
                self.extractor.beyond_markers(raw) || self.extractor.dot_fit_failed(raw);
            // Nothing non-finite leaves the sensor: such a contact (a
            // calibration evaluated far outside its range) is dropped and counted.
            if contact.is_finite() {
                self.detections.push(contact);
            } else {
                self.non_finite += 1;
            }
        }
        let contacts_ms = ms(t);
        let t = Instant::now();
        let dt = self.last_t.map_or(0.0, |p| t_s - p);
        self.last_t = Some(t_s);
        let live = self.tracker.update(&self.detections, dt).len();
        // The quiet flow only where the monitor reads it (re-referencing on,
        // no contact): otherwise its answer does not depend on it.
        let quiet_flow = if self.monitor.reads_flow(live) {
            let (flow, scale) = self.extractor.flow();
            let tile = (QUIET_TILE_PX / scale).max(1);
            max_tile_mean_where(flow, tile, &self.textured, self.textured_x)
        } else {
            f64::NAN
        };
        self.rereferenced = self.monitor.observe(t_s, live, quiet_flow);
        if self.rereferenced {
            // Quiet for long enough: this frame becomes the reference.
            self.extractor.set_reference(&self.cropped)?;
            self.update_texture();
            self.references += 1;
        }
        let mut timings = *self.extractor.timings();
        timings.crop_ms = crop_ms;
        timings.contacts_ms = contacts_ms;
        timings.tracking_ms = ms(t);
        timings.total_ms = ms(t0);
        self.timings = timings;
        Ok(self.contacts())
    }

    /// Which quiet tiles of the new reference have texture (see
    /// [`textured_tiles_into`]).
    fn update_texture(&mut self) {
        let tile_px = (QUIET_TILE_PX / self.extractor.scale()).max(1) * self.extractor.scale();
        self.textured_x = textured_tiles_into(
            &self.cropped,
            tile_px,
            QUIET_MIN_TEXTURE,
            &mut self.textured,
        );
    }

    /// The tracked contacts of the last frame.
    pub fn contacts(&self) -> &[Contact] {
        self.tracker.last()
    }

    /// How many contacts were dropped so far because their location, force
    /// or force sigma was not a finite number.
    pub fn non_finite_dropped(&self) -> u64 {
        self.non_finite
    }

    /// Per-stage timings of the last frame.
    pub fn timings(&self) -> &StageTimings {
        &self.timings
    }

    /// Whether the last frame was taken as a new reference.
    pub fn rereferenced(&self) -> bool {
        self.rereferenced
    }

    /// How many references have been taken (the first included).
    pub fn reference_count(&self) -> u64 {
        self.references
    }

    /// The pitch, in pixels, of the reference's markers when they form a
    /// regular grid ([`ContactExtractor::marker_pitch`]): a contact whose
    /// flow reaches half of it is marked [`Contact::out_of_domain`].
    pub fn marker_pitch(&self) -> Option<f64> {
        self.extractor.marker_pitch()
    }

    /// The extractor (flow, patches, divergent parts of the last frame).
    pub fn extractor(&self) -> &ContactExtractor {
        &self.extractor
    }

    /// The cropped grayscale image of the last frame.
    pub fn cropped(&self) -> &Array2<f32> {
        &self.cropped
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 320x240 reference of bright round markers of radius 2.5 px on a
    /// dark gel: on a square grid of `pitch` px, or at random (`None`).
    fn markers(pitch: Option<f64>) -> Array2<f32> {
        let mut next = crate::flow::unit_stream(0x2545_f491_4f6c_dd1d_u64);
        let centres: Vec<(f64, f64)> = match pitch {
            Some(p) => (0..(240.0 / p) as usize + 1)
                .flat_map(|i| {
                    (0..(320.0 / p) as usize + 1)
                        .map(move |j| (j as f64 * p + 3.0, i as f64 * p + 3.0))
                })
                .collect(),
            None => (0..300)
                .map(|_| (f64::from(next()) * 320.0, f64::from(next()) * 240.0))
                .collect(),
        };
        let mut img = Array2::<f32>::from_elem((240, 320), 30.0);
        for (cx, cy) in centres {
            for ((i, j), v) in img.indexed_iter_mut() {
                if (j as f64 - cx).powi(2) + (i as f64 - cy).powi(2) < 6.25 {
                    *v = 220.0;
                }
            }
        }
        img
    }

    #[test]
    fn a_fit_extracts_as_its_dataset_and_its_choices_say() {
        let flat = SensorGeometry::Flat(crate::geometry::FlatSurface {
            length_mm: 24.0,
            width_mm: 18.0,
        });
        let strip = SensorGeometry::default();
        let (grid, random) = (markers(Some(16.0)), markers(None));
        let fine = DisParams::preset(DisPreset::Fine);
        let dense = DisParams::preset(DisPreset::Dense);
        let auto = FittingChoices::default();
        // A dot grid: its dots followed, the sensor's flow, no light box.
        let (c, pitch) = fitting_extractor(&flat, &grid, &auto);
        assert!(pitch.is_some_and(|p| (p - 16.0).abs() < 1.0), "{pitch:?}");
        assert!(c.dot_tracking && c.dot_fit);
        assert_eq!((c.flow.clone(), c.light_box_px), (fine.clone(), None));
        assert_eq!(c.split, Some(SplitRule::for_geometry(&flat)));
        // Random markers on a flat sensor: the denser flow on frames divided
        // by their own light; on the strip the defaults.
        let (c, pitch) = fitting_extractor(&flat, &random, &auto);
        assert_eq!(pitch, None);
        assert!(!c.dot_tracking);
        assert_eq!(c.flow, dense);
        assert_eq!(c.light_box_px, Some(LIGHT_BOX_PATCHES * dense.patch_size));
        let (c, _) = fitting_extractor(&strip, &random, &auto);
        assert_eq!((c.flow.clone(), c.light_box_px), (fine.clone(), None));
        assert_eq!(c.split, Some(SplitRule::for_geometry(&strip)));
        // What is asked is kept: the box then follows the asked flow's
        // patches unless it is asked too (0: none).
        let asked = FittingChoices {
            dot_tracking: Some(false),
            dot_fit: false,
            flow: Some(DisPreset::Fine),
            light_box_px: None,
            weighted_profiles: true,
        };
        let (c, _) = fitting_extractor(&flat, &grid, &asked);
        assert!(!c.dot_tracking && !c.dot_fit && c.weighted_profiles);
        let (c, _) = fitting_extractor(&flat, &random, &asked);
        assert_eq!(c.flow, fine);
        assert_eq!(c.light_box_px, Some(LIGHT_BOX_PATCHES * fine.patch_size));
        for (box_px, expected) in [(0, None), (24, Some(24))] {
            let choices = FittingChoices {
                light_box_px: Some(box_px),
                ..auto
            };
            assert_eq!(
                fitting_extractor(&flat, &random, &choices).0.light_box_px,
                expected
            );
        }
    }

    #[test]
    fn copy_rows_copies_crops_and_strided_views() {
        let big = Array2::from_shape_fn((9, 14), |(y, x)| (y * 14 + x) as f32 * 0.5 - 7.0);
        for view in [
            big.slice(ndarray::s![1..8, 2..13]),
            big.t().slice_move(ndarray::s![..10, ..]),
            big.view(),
        ] {
            let mut dst = Array2::from_elem(view.dim(), f32::NAN);
            copy_rows(&view, &mut dst);
            assert_eq!(dst, view);
        }
    }

    #[test]
    fn scale_into_multiplies_every_value() {
        // Against the plain product per element: the slice loop (standard
        // layout) and the resize of a wrong-sized output.
        let mut rnd = crate::flow::unit_stream(0x6a09_e667_f3bc_c908u64);
        let mut flow = FlowField::zeros(37, 11);
        for x in flow.u.iter_mut().chain(flow.v.iter_mut()) {
            *x = if rnd() < 0.1 {
                -0.0
            } else {
                40.0 * rnd() - 20.0
            };
        }
        for gain in [1.0f32, 2.0, 0.37] {
            let mut out = FlowField::zeros(3, 2);
            scale_into(&flow, gain, &mut out);
            let bits = |a: &Array2<f32>| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&out.u), bits(&flow.u.mapv(|x| x * gain)));
            assert_eq!(bits(&out.v), bits(&flow.v.mapv(|x| x * gain)));
        }
    }

    /// The obvious twin of `pool_into`: each output cell averages its block
    /// one value at a time.
    fn pool_naive(flow: &FlowField, f: usize) -> FlowField {
        let (w, h) = (flow.width() / f, flow.height() / f);
        let mut out = FlowField::zeros(w, h);
        for r in 0..h {
            for c in 0..w {
                let (mut su, mut sv) = (0.0f64, 0.0f64);
                for i in 0..f {
                    for j in 0..f {
                        su += f64::from(flow.u[[r * f + i, c * f + j]]);
                        sv += f64::from(flow.v[[r * f + i, c * f + j]]);
                    }
                }
                let n = (f * f * f) as f64;
                out.u[[r, c]] = (su / n) as f32;
                out.v[[r, c]] = (sv / n) as f32;
            }
        }
        out
    }

    #[test]
    fn pooling_matches_the_block_mean_and_drops_partial_blocks() {
        for (w, h, f) in [(16, 8, 2), (17, 9, 2), (30, 13, 4), (2, 2, 2)] {
            let mut flow = FlowField::zeros(w, h);
            for r in 0..h {
                for c in 0..w {
                    flow.u[[r, c]] = ((r * 31 + c * 17) % 23) as f32 * 0.1 - 1.0;
                    flow.v[[r, c]] = ((r * 7 + c * 13) % 19) as f32 * -0.05;
                }
            }
            let mut out = FlowField::zeros(0, 0);
            pool_into(&flow, f, &mut out).unwrap();
            let want = pool_naive(&flow, f);
            assert_eq!(out.size(), want.size());
            for (a, b) in out
                .u
                .iter()
                .chain(out.v.iter())
                .zip(want.u.iter().chain(want.v.iter()))
            {
                assert!((a - b).abs() < 1e-6, "{a} vs {b}");
            }
        }
    }

    #[test]
    fn pooling_by_two_is_bit_identical_to_the_general_block_sums() {
        let (w, h) = (37, 12);
        let mut flow = FlowField::zeros(w, h);
        for r in 0..h {
            for c in 0..w {
                // Signed zeros, tiny and large values among them.
                let x = ((r * 31 + c * 17) % 23) as f32 * 0.37 - 4.0;
                flow.u[[r, c]] = if (r + c) % 7 == 0 { -0.0 } else { x * 1e-3 };
                flow.v[[r, c]] = if (r * c) % 5 == 0 { -0.0 } else { x * 1e4 };
            }
        }
        let mut out = FlowField::zeros(0, 0);
        pool_into(&flow, 2, &mut out).unwrap();
        let norm = 1.0 / 8.0f32;
        for (src, got) in [(&flow.u, &out.u), (&flow.v, &out.v)] {
            for r in 0..h / 2 {
                for c in 0..w / 2 {
                    let mut o = 0.0f32;
                    for i in 0..2 {
                        let block = [src[[2 * r + i, 2 * c]], src[[2 * r + i, 2 * c + 1]]];
                        o += block.iter().sum::<f32>();
                    }
                    assert_eq!((o * norm).to_bits(), got[[r, c]].to_bits(), "({r}, {c})");
                }
            }
        }
    }

    #[test]
    fn pooling_a_flow_smaller_than_one_block_is_an_error() {
        let mut out = FlowField::zeros(0, 0);
        let err = pool_into(&FlowField::zeros(1, 5), 2, &mut out).unwrap_err();
        assert!(matches!(err, Error::TooSmall { .. }), "{err}");
    }

    #[test]
    fn the_split_rule_is_a_setting_of_the_extractor() {
        let on = ContactExtractor::new(ExtractorConfig::default()).unwrap();
        assert_eq!(on.segmenter().split(), Some(&SplitRule::DEFAULT));
        let off = ContactExtractor::new(ExtractorConfig::default().with_split(None)).unwrap();
        assert_eq!(off.segmenter().split(), None);
        let bad = SplitRule {
            depth: -1.0,
            ..SplitRule::DEFAULT
        };
        assert!(ContactExtractor::new(ExtractorConfig::default().with_split(Some(bad))).is_err());
    }

    #[test]
    fn the_analysis_grid_is_never_finer_than_two_pixels() {
        assert_eq!(AnalysisGrid::new(0).scale(), 2);
        assert_eq!(AnalysisGrid::new(1).scale(), 2);
        assert_eq!(AnalysisGrid::new(2).scale(), 4);
        let mut g = AnalysisGrid::new(1);
        let mut native = FlowField::zeros(4, 2);
        native.u[[1, 3]] = f32::NAN;
        assert!(matches!(g.update(&native), Err(Error::NonFinite { .. })));
    }
}
