//! Cutting a flow into contact patches (docs/pipeline.md, step 5, the paper's
//! "Thresholds" section).
//!
//! [`Segmenter::segment`]: `|flow|` → threshold → binary mask → erode (drops
//! specks smaller than the kernel) → dilate (restores the region, joins what
//! erosion split) → **external** contours only → one bounding box per contour
//! → discard boxes whose summed `|flow|` is below a second threshold → grow the
//! boxes by a margin, clamp them to the image, group the ones that overlap →
//! split each group that holds several contacts ([`SplitRule`], beyond the
//! paper) → [`ContactPatch`]es, each a box over the **unmodified** flow.
//!
//! ## Units and scale
//! [`Thresholds`] are stated for the **full-resolution** image (pixels of the
//! cropped camera frame), so one preset serves any pyramid level. `scale` is
//! the number of full-resolution pixels per flow pixel, as
//! `flow::dis::Dis::native_flow` reports it and
//! [`PatchGrid`] takes it: 1 at full resolution, 4
//! for DIS's native level 2, whose flow is in its own (level) pixels. With
//! `s = 1 / scale`, on such a flow:
//! - the magnitude threshold is `magnitude * s` (displacements shrink by `s`);
//! - the summed threshold is `sum * s^3` (`s` for each displacement, `s^2` for
//!   the number of pixels summed);
//! - kernel sizes and the margin are `size * s`, rounded to the nearest odd
//!   size (kernels, at least 1) or integer (margin).
//!
//! ## Boxes that overlap, and the image border
//! - A box grown by the margin is clamped to the image: a contact at the edge
//!   yields a smaller patch, never an error.
//! - Boxes that share at least one pixel after the margin are grouped
//!   (repeatedly, until no two groups overlap); boxes that only touch stay
//!   apart. A group's core is the union of its contour boxes, its box the
//!   union of their grown boxes.
//! - Each group is then cut by the [`SplitRule`] (on by default): where the
//!   smoothed divergence along the image's longer side shows two contacts
//!   with the skin squeezed between them, the group's box is cut across at
//!   that valley. Pieces touch and never overlap, so no flow is counted
//!   twice (the nHHD of a patch assumes one contact in it). The two outer
//!   pieces are trimmed on their outer side to as far from their
//!   divergence peak as their cut is, plus the margin, so that a contact
//!   in a wide (sheared) region sits in the middle of its patch. This separates
//!   both contours whose margins overlap and one contour (one mask region)
//!   that holds two contacts. A group the rule does not cut is one patch,
//!   as when boxes were simply merged ([`Segmenter::set_split`] with `None`
//!   restores that behaviour).
//! - The summed `|flow|` test is made on each contour's own box (before the
//!   margin), as in the paper, and again on each piece of a cut group (a
//!   weaker piece is given back to its neighbour); a patch reports the sum
//!   over its final box.
//!
//! ## Example
//! ```
//! use optical_tactile::FlowField;
//! use optical_tactile::segment::{Segmenter, SegmenterConfig, Thresholds};
//! // A 4-pixel shift over a 40x30 block of a 200x100 full-resolution flow.
//! let mut flow = FlowField::zeros(200, 100);
//! flow.u.slice_mut(ndarray::s![30..60, 50..90]).fill(4.0);
//! let config = SegmenterConfig { thresholds: Thresholds::MID, margin: 5, scale: 1.0 };
//! let mut segmenter = Segmenter::new(config)?;
//! let patches = segmenter.segment(&flow)?;
//! assert_eq!(patches.len(), 1);
//! // Eroding by 9 then dilating by 21 grows the block by 6 px per side,
//! // then the margin adds 5.
//! let c = patches[0].core;
//! assert_eq!((c.x, c.y, c.width, c.height), (44, 24, 52, 42));
//! let b = patches[0].bbox;
//! assert_eq!((b.x, b.y, b.width, b.height), (39, 19, 62, 52));
//! let (u, _v) = patches[0].view(&flow)?;
//! assert_eq!(u.sum(), 4.0 * 40.0 * 30.0);
//! # Ok::<(), optical_tactile::Error>(())
//! ```

pub mod contours;
pub mod morphology;

use ndarray::ArrayView2;

use crate::contact::PatchGrid;
use crate::error::{Error, Result};
use crate::flow::FlowField;
use crate::frame::Roi;
use crate::segment::contours::{BoundingBox, ContourFinder};
pub use crate::segment::morphology::Shape;
use crate::segment::morphology::{Mask, Morphology, StructuringElement};

/// A named set of segmentation thresholds: the paper's presets, from the most
/// sensitive to the most robust to vibration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ThresholdPreset {
    /// [`Thresholds::LOW`]: the smallest forces, little headroom for noise.
    Low,
    /// [`Thresholds::MID`].
    Mid,
    /// [`Thresholds::HIGH`]: the paper's choice in flight.
    High,
}

impl ThresholdPreset {
    /// Every preset, from the most sensitive.
    pub const ALL: [ThresholdPreset; 3] = [
        ThresholdPreset::Low,
        ThresholdPreset::Mid,
        ThresholdPreset::High,
    ];

    /// The preset's name as written in files and on command lines: `low`,
    /// `mid` or `high`.
    pub const fn name(self) -> &'static str {
        match self {
            ThresholdPreset::Low => "low",
            ThresholdPreset::Mid => "mid",
            ThresholdPreset::High => "high",
        }
    }

    /// The preset's thresholds.
    pub const fn thresholds(self) -> Thresholds {
        Thresholds::preset(self)
    }
}

impl std::fmt::Display for ThresholdPreset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for ThresholdPreset {
    type Err = Error;

    /// `low`, `mid` or `high`, in any case.
    fn from_str(name: &str) -> Result<Self> {
        ThresholdPreset::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(name))
            .ok_or_else(|| {
                Error::param(
                    "thresholds",
                    format!("unknown preset `{name}` (expected low, mid or high)"),
                )
            })
    }
}

impl From<ThresholdPreset> for Thresholds {
    fn from(preset: ThresholdPreset) -> Self {
        Thresholds::preset(preset)
    }
}

/// Largest erosion or dilation kernel side, full-resolution pixels: 255
/// (the presets use 5 to 21; a kernel wider than a contact's patch erases
/// it). The morphology's memory and time grow with the kernel.
pub const MAX_KERNEL_PX: usize = 255;

/// Segmentation thresholds and kernels, in **full-resolution** pixels (see
/// the module docs for how they scale).
///
/// The presets [`Thresholds::LOW`], [`Thresholds::MID`] and
/// [`Thresholds::HIGH`] were chosen on the simulator (default 1600 x 200 px
/// strip, 5 px/mm) through [`ContactExtractor`](crate::sensor::ContactExtractor)
/// with the default (`fine`) DIS flow, segmented on the analysis grid
/// (scale 2). Measured with `cargo run --release -p optical-tactile-tools
/// --bin sweep -- all --rest 1500` (seed 1; tables in docs/results.md):
///
/// | preset | min. detectable force (>= 95%) | every press from | false contacts at rest |
/// |---|---|---|---|
/// | LOW  | 0.4 N (target < 0.5 N; 95% at 0.3 N, 86% at 0.2 N) | 0.4 N | 0 / 1500 pairs |
/// | MID  | 0.8 N (target 0.5-1 N) | 1.3 N | 0 / 1500 pairs |
/// | HIGH | 1.2 N (target 1-1.5 N) | 2.0 N | 0 / 1500 pairs |
///
/// Minimum detectable force: smallest force of a 0.1 N ladder from which at
/// least 95% of single presses are detected (a patch covering the rod), over
/// 7 positions along the skin (-120..120 mm), the 2, 5 and 10 mm rods and the
/// protocol's 5 tilts; the limit is set by purely normal presses (centre,
/// straight, or a tilt that cancels the skin's slope), which move markers
/// least. Rest pairs: a reference against another unloaded frame with fresh
/// noise and flicker; the largest summed `|flow|` of any rest contour was
/// 256 (LOW's kernels) and 0 (MID's and HIGH's: no pixel left after
/// erosion), far below every preset's `sum`.
///
/// With the [`SplitRule`], two straight rods of equal force are two
/// contacts, each within 3 mm of its rod, at every spacing from 40 mm down
/// to 10 mm (LOW and MID at 1.5 and 3 N, HIGH at 3 N; 2, 5 and 10 mm rods;
/// midpoints -60, 0 and 60 mm); none at 7.5 mm. HIGH at 1.5 N does not
/// detect a centred pair at all below 30 mm (see docs/results.md).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Thresholds {
    /// Per-pixel `|flow|` above which a pixel belongs to the mask, in
    /// full-resolution pixels.
    pub magnitude: f32,
    /// Minimum summed `|flow|` over a contour's box for it to count as a
    /// contact, in full-resolution pixels (displacement) summed over
    /// full-resolution pixels.
    pub sum: f32,
    /// Erosion kernel size (square), full-resolution pixels.
    pub erode: usize,
    /// Dilation kernel size (square), full-resolution pixels.
    pub dilate: usize,
    /// Kernel shape for both.
    pub shape: Shape,
}

impl Thresholds {
    /// Low thresholds: the most sensitive. Minimum detectable force 0.4 N
    /// on the simulator (target below 0.5 N). Its magnitude is below the
    /// `fine` flow's rest noise (peak 0.23 px per frame, median), so the sum
    /// test is what rejects noise: 1500 against 256 for the largest contour
    /// seen at rest.
    pub const LOW: Thresholds = Thresholds {
        magnitude: 0.15,
        sum: 1500.0,
        erode: 5,
        dilate: 15,
        shape: Shape::Rect,
    };

    /// Mid thresholds: minimum detectable force 0.8 N on the simulator
    /// (target 0.5-1 N).
    pub const MID: Thresholds = Thresholds {
        magnitude: 0.35,
        sum: 2000.0,
        erode: 9,
        dilate: 21,
        shape: Shape::Rect,
    };

    /// High thresholds, the paper's choice in flight (robust to vibration):
    /// minimum detectable force 1.2 N on the simulator (target 1-1.5 N).
    pub const HIGH: Thresholds = Thresholds {
        magnitude: 0.55,
        sum: 3000.0,
        erode: 9,
        dilate: 21,
        shape: Shape::Rect,
    };

    /// The thresholds of a preset.
    pub const fn preset(preset: ThresholdPreset) -> Thresholds {
        match preset {
            ThresholdPreset::Low => Thresholds::LOW,
            ThresholdPreset::Mid => Thresholds::MID,
            ThresholdPreset::High => Thresholds::HIGH,
        }
    }

    /// The preset these thresholds equal, if any.
    pub fn as_preset(&self) -> Option<ThresholdPreset> {
        ThresholdPreset::ALL
            .into_iter()
            .find(|&p| Thresholds::preset(p) == *self)
    }

    /// Errors unless the thresholds are finite and non-negative and the
    /// kernels in `1..=`[`MAX_KERNEL_PX`].
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [("magnitude", self.magnitude), ("sum", self.sum)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Error::param(
                    format!("thresholds.{name}"),
                    format!("must be finite and >= 0, got {v}"),
                ));
            }
        }
        for (name, k) in [("erode", self.erode), ("dilate", self.dilate)] {
            if !(1..=MAX_KERNEL_PX).contains(&k) {
                return Err(Error::param(
                    format!("thresholds.{name}"),
                    format!("kernel size must be in 1..={MAX_KERNEL_PX} px, got {k}"),
                ));
            }
        }
        Ok(())
    }

    /// The thresholds for a flow at `scale` (full-resolution pixels per flow
    /// pixel), in that flow's pixels.
    pub fn at_scale(&self, scale: f64) -> Result<ScaledThresholds> {
        self.validate()?;
        check_scale(scale)?;
        let s = 1.0 / scale;
        Ok(ScaledThresholds {
            magnitude: (self.magnitude as f64 * s) as f32,
            sum: self.sum as f64 * s * s * s,
            erode: StructuringElement::new(self.shape, odd(self.erode, s), odd(self.erode, s)),
            dilate: StructuringElement::new(self.shape, odd(self.dilate, s), odd(self.dilate, s)),
        })
    }

    /// Thresholds derived from the noise floor of flows recorded **without
    /// contact** (beyond the paper).
    ///
    /// `flows` are rest flows at `options.scale`; kernels and shape come from
    /// `options.kernels`. Method:
    /// 1. `magnitude` = the `pixel_quantile` quantile of all per-pixel
    ///    `|flow|`, times `headroom`: a fraction `1 - pixel_quantile` of noise
    ///    pixels pass, and the erosion removes those specks.
    /// 2. For each frame, the statistic a false contact would have to beat:
    ///    the larger of (a) the largest summed `|flow|` of any box the
    ///    segmentation finds with that magnitude threshold and no sum
    ///    threshold, and (b) the largest summed `|flow|` of any window of the
    ///    dilation kernel's size (the smallest box a surviving blob can
    ///    have), so that the sum threshold also guards frames noisier than the
    ///    ones recorded.
    /// 3. `sum` = the `k`-th smallest of those per-frame statistics with
    ///    `k = ceil((1 - false_contact_rate) n)`, times `headroom`: on frames
    ///    like the recorded ones, at most a fraction `false_contact_rate`
    ///    exceeds it.
    ///
    /// Errors: no flows, flows of different sizes or with non-finite values,
    /// parameters out of range, or fewer than `ceil(1 / false_contact_rate)`
    /// flows (too few to estimate that rate).
    pub fn from_rest(flows: &[FlowField], options: &RestOptions) -> Result<Thresholds> {
        let rate = options.false_contact_rate;
        if !(rate > 0.0 && rate < 1.0) {
            return Err(Error::param(
                "false_contact_rate",
                format!("must be in (0, 1), got {rate}"),
            ));
        }
        let q = options.pixel_quantile;
        if !(q > 0.0 && q < 1.0) {
            return Err(Error::param(
                "pixel_quantile",
                format!("must be in (0, 1), got {q}"),
            ));
        }
        if !(options.headroom.is_finite() && options.headroom >= 1.0) {
            return Err(Error::param(
                "headroom",
                format!("must be finite and >= 1, got {}", options.headroom),
            ));
        }
        let mut base = options.kernels;
        base.magnitude = 0.0;
        base.sum = 0.0;
        let scaled = base.at_scale(options.scale)?;
        let needed = (1.0 / rate).ceil() as usize;
        if flows.len() < needed {
            return Err(Error::param(
                "false_contact_rate",
                format!(
                    "a rate of {rate} needs at least {needed} rest flows, got {}",
                    flows.len()
                ),
            ));
        }
        let size = flows[0].size();
        for f in flows {
            check_flow(f)?;
            if f.size() != size {
                return Err(Error::shape("rest flow", size, f.size()));
            }
        }
        // 1. Per-pixel quantile.
        let mag_level = magnitude_quantile(flows, q) * options.headroom;
        // 2. Per-frame statistics.
        let s = 1.0 / options.scale;
        let mut seg = Segmenter::new(SegmenterConfig {
            thresholds: Thresholds {
                magnitude: (mag_level as f64 / s) as f32,
                sum: 0.0,
                ..base
            },
            margin: 0,
            scale: options.scale,
        })?;
        let win = scaled.dilate.width.min(size.0).min(size.1).max(1);
        let mut integral = Vec::new();
        let mut stats = Vec::with_capacity(flows.len());
        let mut patches = Vec::new();
        for f in flows {
            seg.segment_into(f, &mut patches)?;
            let boxes = seg.contour_sums.iter().copied().fold(0.0f64, f64::max);
            let windows = max_window_sum(f, win, &mut integral);
            stats.push(boxes.max(windows));
        }
        // 3. Order statistic.
        stats.sort_by(f64::total_cmp);
        let k = (((1.0 - rate) * stats.len() as f64).ceil() as usize).clamp(1, stats.len()) - 1;
        let sum_level = stats[k] * options.headroom as f64;
        Ok(Thresholds {
            magnitude: (mag_level as f64 / s) as f32,
            sum: (sum_level / (s * s * s)) as f32,
            ..base
        })
    }
}

/// Options of [`Thresholds::from_rest`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RestOptions {
    /// Accepted fraction of rest frames with a false contact, in (0, 1).
    pub false_contact_rate: f64,
    /// Quantile of the per-pixel `|flow|` used as the magnitude threshold, in
    /// (0, 1).
    pub pixel_quantile: f64,
    /// Factor (>= 1) applied to both measured thresholds, for rest frames
    /// noisier than the recorded ones.
    pub headroom: f32,
    /// Scale of the given flows: full-resolution pixels per flow pixel.
    pub scale: f64,
    /// Kernels and shape to use (its `magnitude` and `sum` are ignored).
    pub kernels: Thresholds,
}

impl Default for RestOptions {
    fn default() -> Self {
        RestOptions {
            false_contact_rate: 0.01,
            pixel_quantile: 0.999,
            headroom: 1.25,
            scale: 1.0,
            kernels: Thresholds::MID,
        }
    }
}

/// [`Thresholds`] converted to one flow scale, in that flow's pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScaledThresholds {
    /// Per-pixel `|flow|` threshold.
    pub magnitude: f32,
    /// Summed `|flow|` threshold.
    pub sum: f64,
    /// Erosion element.
    pub erode: StructuringElement,
    /// Dilation element.
    pub dilate: StructuringElement,
}

/// Configuration of a [`Segmenter`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SegmenterConfig {
    /// Thresholds and kernels (full-resolution pixels).
    pub thresholds: Thresholds,
    /// Margin added around each box so that a patch holds its whole
    /// deformation, full-resolution pixels (scaled like the kernels).
    pub margin: usize,
    /// Scale of the flows to segment: full-resolution pixels per flow pixel
    /// (1 at full resolution, 4 for DIS's level-2 native flow).
    pub scale: f64,
}

impl Default for SegmenterConfig {
    /// [`Thresholds::HIGH`] (the paper's flight setting), a 10 px margin,
    /// full resolution.
    fn default() -> Self {
        SegmenterConfig {
            thresholds: Thresholds::HIGH,
            margin: 10,
            scale: 1.0,
        }
    }
}

/// One contact patch: a box over the unmodified flow.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactPatch {
    /// The patch: contour box(es) grown by the margin, clamped, merged.
    pub bbox: BoundingBox,
    /// Union of the contour boxes it came from (before the margin).
    pub core: BoundingBox,
    /// Whether its motion is seen where the reference has texture (see
    /// [`Segmenter::set_observable`]); always `true` without that mask.
    pub seen: bool,
    /// Summed `|flow|` over `bbox`, in the flow's pixels.
    pub flow_sum: f64,
    /// Number of mask pixels (after erosion and dilation) inside `bbox`.
    pub area: usize,
}

impl ContactPatch {
    /// Views `(u, v)` of the patch's sub-flow in `flow` (the flow it was cut
    /// from, unmodified). Errors if the box does not fit `flow`.
    pub fn view<'a>(
        &self,
        flow: &'a FlowField,
    ) -> Result<(ArrayView2<'a, f32>, ArrayView2<'a, f32>)> {
        let b = self.bbox;
        flow.window(b.x, b.y, b.width, b.height)
    }

    /// Where the patch sits in the flow's grid, for
    /// [`contact::raw_quantities`](crate::contact::raw_quantities); `scale` is
    /// full-resolution pixels per flow pixel (the segmenter's).
    pub fn grid(&self, scale: f64) -> PatchGrid {
        PatchGrid {
            x0: self.bbox.x,
            y0: self.bbox.y,
            scale,
        }
    }

    /// The patch's box in full-resolution pixels (each flow pixel covers
    /// `scale x scale` of them; `scale` rounded to a whole number of pixels).
    pub fn full_res_roi(&self, scale: f64) -> Roi {
        let k = scale.round().max(1.0) as usize;
        let b = self.bbox;
        Roi {
            x: b.x * k,
            y: b.y * k,
            w: b.width * k,
            h: b.height * k,
        }
    }

    /// The patch's sub-flow as an owned [`FlowField`].
    pub fn sub_flow(&self, flow: &FlowField) -> Result<FlowField> {
        let (u, v) = self.view(flow)?;
        Ok(FlowField {
            u: u.to_owned(),
            v: v.to_owned(),
        })
    }
}

/// Reusable segmenter: built once for a configuration, called per flow; its
/// buffers are kept so that nothing but the output list is allocated per
/// frame once they have grown.
#[derive(Debug, Clone)]
pub struct Segmenter {
    config: SegmenterConfig,
    scaled: ScaledThresholds,
    margin: usize,
    morph: Morphology,
    contours: ContourFinder,
    raw: Mask,
    eroded: Mask,
    mask: Mask,
    boxes: Vec<BoundingBox>,
    /// Summed |flow| of every contour box of the last call (before the sum test).
    contour_sums: Vec<f64>,
    merged: Vec<(BoundingBox, BoundingBox)>,
    split: Option<SplitRule>,
    /// Smoothing radius of the split profile, flow pixels.
    split_radius: usize,
    profile: Vec<f64>,
    mag_profile: Vec<f64>,
    mag_prefix: Vec<f64>,
    acc_u: Vec<f32>,
    acc_m: Vec<f32>,
    smoothed: Vec<f64>,
    divergence: Vec<f64>,
    cuts: Vec<usize>,
    /// The pieces `(grown box, core)` of the last call.
    pieces: Vec<(BoundingBox, BoundingBox)>,
    /// The pieces along the first side, before the cuts across.
    across_pieces: Vec<(BoundingBox, BoundingBox)>,
    /// Number of cuts the split rule made in the last call.
    split_count: usize,
    /// Where motion can be seen at all (see [`Segmenter::set_observable`]);
    /// `None`: everywhere.
    observable: Option<Mask>,
    /// The thresholded mask within `observable`.
    masked: Mask,
    /// Boxes of the observable contours that pass the sum test.
    seen: Vec<BoundingBox>,
}

impl Segmenter {
    /// A segmenter for `config`. Errors on invalid thresholds or scale, or a
    /// margin above [`crate::frame::MAX_FRAME_SIDE`].
    pub fn new(config: SegmenterConfig) -> Result<Self> {
        let scaled = config.thresholds.at_scale(config.scale)?;
        if config.margin > crate::frame::MAX_FRAME_SIDE {
            return Err(Error::param(
                "margin",
                format!(
                    "{} px is above the largest frame side, {}",
                    config.margin,
                    crate::frame::MAX_FRAME_SIDE
                ),
            ));
        }
        Ok(Segmenter {
            config,
            scaled,
            // A margin past every frame side grows any box to the whole
            // image, as the largest side does: clamped there, it cannot
            // overflow whatever the scale.
            margin: (config.margin as f64 / config.scale)
                .round()
                .min(crate::frame::MAX_FRAME_SIDE as f64) as usize,
            morph: Morphology::new(),
            contours: ContourFinder::new(),
            raw: Mask::default(),
            eroded: Mask::default(),
            mask: Mask::default(),
            boxes: Vec::new(),
            contour_sums: Vec::new(),
            merged: Vec::new(),
            split: Some(SplitRule::DEFAULT),
            split_radius: SplitRule::DEFAULT.radius(config.scale),
            profile: Vec::new(),
            mag_profile: Vec::new(),
            mag_prefix: Vec::new(),
            acc_u: Vec::new(),
            acc_m: Vec::new(),
            smoothed: Vec::new(),
            divergence: Vec::new(),
            cuts: Vec::new(),
            pieces: Vec::new(),
            across_pieces: Vec::new(),
            split_count: 0,
            observable: None,
            masked: Mask::default(),
            seen: Vec::new(),
        })
    }

    /// Tells which patches are seen where motion can be seen: with a `mask`
    /// (the flow's size; checked at each call), a patch is
    /// [`seen`](ContactPatch::seen) only if its contours meet a contour of
    /// the thresholded flow's part within the mask that passes the sum test
    /// on its own; every patch keeps the box it has without the mask.
    /// `None` lifts the restriction. Where a frame has no
    /// texture (the dark coating beyond the skin's markers) the flow holds
    /// only the camera's noise, which the magnitude test would otherwise read
    /// as motion, while a press near the skin's end moves the flow on both
    /// sides of it.
    pub fn set_observable(&mut self, mask: Option<Mask>) {
        self.observable = mask;
    }

    /// The mask of [`set_observable`](Self::set_observable), if any.
    pub fn observable(&self) -> Option<&Mask> {
        self.observable.as_ref()
    }

    /// Sets the rule that splits one group of contours holding several
    /// contacts ([`SplitRule::DEFAULT`] after [`Segmenter::new`]); `None`
    /// keeps every group whole (the behaviour before the rule existed).
    /// Errors if the rule is invalid.
    pub fn set_split(&mut self, split: Option<SplitRule>) -> Result<()> {
        if let Some(rule) = &split {
            rule.validate()?;
            self.split_radius = rule.radius(self.config.scale);
        }
        self.split = split;
        Ok(())
    }

    /// [`Segmenter::set_split`] by value, for building.
    pub fn with_split(mut self, split: Option<SplitRule>) -> Result<Self> {
        self.set_split(split)?;
        Ok(self)
    }

    /// The split rule in use, if any.
    pub fn split(&self) -> Option<&SplitRule> {
        self.split.as_ref()
    }

    /// How many cuts the split rule made in the last call (0 when every
    /// group stayed whole).
    pub fn split_count(&self) -> usize {
        self.split_count
    }

    /// The configuration.
    pub fn config(&self) -> &SegmenterConfig {
        &self.config
    }

    /// The thresholds in the flow's pixels.
    pub fn scaled(&self) -> &ScaledThresholds {
        &self.scaled
    }

    /// The mask of the last call after erosion and dilation (for display).
    pub fn mask(&self) -> &Mask {
        &self.mask
    }

    /// The external contours' boxes of the last call, before the sum test.
    pub fn contour_boxes(&self) -> &[BoundingBox] {
        &self.boxes
    }

    /// The summed `|flow|` of each of [`Segmenter::contour_boxes`].
    pub fn contour_sums(&self) -> &[f64] {
        &self.contour_sums
    }

    /// The contact patches of `flow` (see the module docs).
    ///
    /// Errors: an empty flow ([`Error::TooSmall`]), planes of different
    /// shapes ([`Error::ShapeMismatch`]), NaN or infinite values
    /// ([`Error::NonFinite`]).
    pub fn segment(&mut self, flow: &FlowField) -> Result<Vec<ContactPatch>> {
        let mut out = Vec::new();
        self.segment_into(flow, &mut out)?;
        Ok(out)
    }

    /// [`Segmenter::segment`] into `out` (cleared first), reusing its allocation.
    pub fn segment_into(&mut self, flow: &FlowField, out: &mut Vec<ContactPatch>) -> Result<()> {
        out.clear();
        check_flow(flow)?;
        let (w, h) = flow.size();
        let st = self.scaled;
        self.raw.threshold_flow_into(flow, st.magnitude)?;
        // Where motion can be seen: the contours of the observable part of
        // the mask that pass the sum test. A patch is `seen` if its contours
        // meet one of them; its box is cut from the whole mask as without
        // the restriction, so a contact whose motion spills past the skin's
        // texture is measured whole.
        self.seen.clear();
        if let Some(observable) = &self.observable {
            self.masked.copy_from(&self.raw);
            self.masked.and_assign(observable)?;
            self.morph
                .erode(&self.masked, &mut self.eroded, &st.erode, 1)?;
            self.morph
                .dilate(&self.eroded, &mut self.mask, &st.dilate, 1)?;
            self.contours.external_boxes(&self.mask, &mut self.boxes);
            for b in &self.boxes {
                if box_sum_where_reaches(flow, b, observable, st.sum) {
                    self.seen.push(*b);
                }
            }
        }
        self.morph
            .erode(&self.raw, &mut self.eroded, &st.erode, 1)?;
        self.morph
            .dilate(&self.eroded, &mut self.mask, &st.dilate, 1)?;
        self.contours.external_boxes(&self.mask, &mut self.boxes);
        self.contour_sums.clear();
        self.merged.clear();
        for b in &self.boxes {
            let s = box_sum(flow, b);
            self.contour_sums.push(s);
            if s >= st.sum {
                self.merged.push((b.expand(self.margin, w, h), *b));
            }
        }
        // Merge overlapping grown boxes until none overlap (few boxes: O(n^2)
        // per pass is cheap).
        let mut changed = true;
        while changed {
            changed = false;
            'outer: for i in 0..self.merged.len() {
                for j in i + 1..self.merged.len() {
                    if self.merged[i].0.intersects(&self.merged[j].0) {
                        let (bj, cj) = self.merged.swap_remove(j);
                        let (bi, ci) = self.merged[i];
                        self.merged[i] = (bi.union(&bj), ci.union(&cj));
                        changed = true;
                        break 'outer;
                    }
                }
            }
        }
        self.merged.sort_by_key(|(b, _)| (b.y, b.x));
        self.split_count = 0;
        // Along the image's longer side, then, with a rule that cuts across
        // too, each piece along the other side (see `SplitRule`).
        let along_x = w >= h;
        let mut pieces = std::mem::take(&mut self.pieces);
        pieces.clear();
        for gi in 0..self.merged.len() {
            let (grown, core) = self.merged[gi];
            self.cut_group(flow, grown, core, along_x, &mut pieces);
        }
        if self.split.is_some_and(|r| r.across) {
            let mut along = std::mem::take(&mut self.across_pieces);
            along.clear();
            along.append(&mut pieces);
            for &(grown, core) in &along {
                self.cut_group(flow, grown, core, !along_x, &mut pieces);
            }
            self.across_pieces = along;
        }
        for &(bbox, piece) in &pieces {
            let seen = self.observable.is_none() || self.seen.iter().any(|o| o.intersects(&piece));
            out.push(ContactPatch {
                bbox,
                core: piece,
                seen,
                flow_sum: box_sum(flow, &bbox),
                area: self
                    .mask
                    .count_ones_in(bbox.x, bbox.y, bbox.x_end(), bbox.y_end()),
            });
        }
        self.pieces = pieces;
        Ok(())
    }

    /// The pieces `(grown box, core)` of one group (its grown box and the
    /// union of its contour boxes `core`) after the split rule's cuts along
    /// x (along y when `!along_x`), pushed onto `pieces`; the group whole
    /// without a rule or a cut.
    fn cut_group(
        &mut self,
        flow: &FlowField,
        grown: BoundingBox,
        core: BoundingBox,
        along_x: bool,
        pieces: &mut Vec<(BoundingBox, BoundingBox)>,
    ) {
        self.cuts.clear();
        if let Some(rule) = self.split {
            self.group_cuts(flow, &core, along_x, &rule);
        }
        self.split_count += self.cuts.len();
        let (origin, core_end, grown_lo, grown_hi) = if along_x {
            (core.x, core.x_end(), grown.x, grown.x_end())
        } else {
            (core.y, core.y_end(), grown.y, grown.y_end())
        };
        let nc = self.cuts.len();
        for k in 0..=nc {
            let (mut bbox, mut piece) = (grown, core);
            let start = if k == 0 { None } else { Some(self.cuts[k - 1]) };
            let end = self.cuts.get(k).copied();
            set_range(&mut piece, along_x, start, end);
            set_range(&mut bbox, along_x, start, end);
            // The outer piece of a cut group is trimmed on its outer
            // side to as far from its peak as the cut is (plus the
            // margin): the contact sits in the middle of its patch, and
            // the rest of a flooded (sheared) region, which would pull
            // the nHHD potential's minimum to the patch's far end, is
            // left out.
            if nc > 0 && (k == 0 || k == nc) {
                let (lo, hi) = (start.unwrap_or(origin), end.unwrap_or(core_end));
                let peak = origin
                    + (lo - origin..hi - origin)
                        .max_by(|&a, &b| self.divergence[a].total_cmp(&self.divergence[b]))
                        .unwrap_or(0);
                if k == 0 {
                    let half = hi - peak;
                    let new_lo = peak.saturating_sub(half).max(origin);
                    set_range(&mut piece, along_x, Some(new_lo), end);
                    let g = new_lo.saturating_sub(self.margin).max(grown_lo);
                    set_range(&mut bbox, along_x, Some(g), end);
                } else {
                    let new_hi = (peak + (peak - lo) + 1).min(core_end);
                    set_range(&mut piece, along_x, start, Some(new_hi));
                    let g = (new_hi + self.margin).min(grown_hi);
                    set_range(&mut bbox, along_x, start, Some(g));
                }
            }
            pieces.push((bbox, piece));
        }
    }

    /// The cuts (absolute flow coordinates along x, or y when `!along_x`) that
    /// split the group whose contour boxes' union is `core`, into
    /// `self.cuts`: the split rule on the divergence profile, then cuts
    /// removed until every piece passes the sum threshold.
    fn group_cuts(
        &mut self,
        flow: &FlowField,
        core: &BoundingBox,
        along_x: bool,
        rule: &SplitRule,
    ) {
        let n = if along_x { core.width } else { core.height };
        self.column_profiles(flow, core, along_x);
        divergence_profile(
            &self.profile,
            self.split_radius,
            &mut self.smoothed,
            &mut self.divergence,
        );
        let origin = if along_x { core.x } else { core.y };
        let len = if along_x { flow.width() } else { flow.height() };
        let border = (rule.border as f64 / self.config.scale).round() as usize;
        let valid = border.saturating_sub(origin)..(len.saturating_sub(border + origin)).min(n);
        let scaled = SplitRule {
            far_px: ((rule.far_px as f64 / self.config.scale).round() as usize)
                .max(usize::from(rule.far_px > 0)),
            ..*rule
        };
        find_cuts(&self.divergence, &scaled, valid, &mut self.cuts);
        for c in &mut self.cuts {
            *c += origin;
        }
        // A piece too weak to be a contact on its own goes back to its
        // neighbour: drop the cut on its left (or its right for the first).
        // Summed |flow| of a piece from the prefix sums of the |flow|
        // profile (the same sum as `box_sum` over the piece).
        self.mag_prefix.clear();
        self.mag_prefix.push(0.0);
        let mut acc = 0.0;
        for &m in &self.mag_profile {
            acc += m;
            self.mag_prefix.push(acc);
        }
        while !self.cuts.is_empty() {
            let (cuts, prefix) = (&self.cuts, &self.mag_prefix);
            let weak = (0..=cuts.len()).find(|&k| {
                let lo = if k == 0 { origin } else { cuts[k - 1] };
                let hi = cuts.get(k).copied().unwrap_or(origin + n);
                prefix[hi - origin] - prefix[lo - origin] < self.scaled.sum
                    || rule.press_swing
                        && !has_press_swing(
                            &self.smoothed[lo - origin..hi - origin],
                            &self.divergence[lo - origin..hi - origin],
                        )
            });
            match weak {
                Some(k) => {
                    self.cuts.remove(k.saturating_sub(1));
                }
                None => break,
            }
        }
    }
}

/// Whether a piece's smoothed motion profile `p` (the flow along the cut
/// axis, summed across) swings from below zero to above it about the
/// piece's divergence peak (`divergence`, the same cells): a press pushes
/// the gel away from it on both sides ([`SplitRule::press_swing`]).
fn has_press_swing(p: &[f64], divergence: &[f64]) -> bool {
    let Some(peak) = (0..divergence.len()).max_by(|&a, &b| divergence[a].total_cmp(&divergence[b]))
    else {
        return false;
    };
    let before = p[..=peak].iter().copied().fold(f64::INFINITY, f64::min);
    let after = p[peak..].iter().copied().fold(f64::NEG_INFINITY, f64::max);
    before < 0.0 && after > 0.0
}

impl Segmenter {
    /// Into `profile` and `mag_profile`: for each column of `core` (rows
    /// when `!along_x`), the sum of `u` (`v`) and of `|flow|` over the
    /// box's rows (columns). Rows are added in f32 (vectorises), flushed to
    /// f64 every 64 rows.
    fn column_profiles(&mut self, flow: &FlowField, core: &BoundingBox, along_x: bool) {
        let n = if along_x { core.width } else { core.height };
        self.profile.clear();
        self.profile.resize(n, 0.0);
        self.mag_profile.clear();
        self.mag_profile.resize(n, 0.0);
        let (x0, x1) = (core.x, core.x_end());
        if !along_x {
            for y in core.y..core.y_end() {
                let (ur, vr) = (flow.u.row(y), flow.v.row(y));
                let (mut sv, mut sm) = (0.0f64, 0.0f64);
                for x in x0..x1 {
                    sv += vr[x] as f64;
                    sm += (ur[x] as f64).hypot(vr[x] as f64);
                }
                self.profile[y - core.y] = sv;
                self.mag_profile[y - core.y] = sm;
            }
            return;
        }
        self.acc_u.clear();
        self.acc_u.resize(n, 0.0);
        self.acc_m.clear();
        self.acc_m.resize(n, 0.0);
        let flush = |acc: &mut [f32], out: &mut [f64]| {
            for (o, a) in out.iter_mut().zip(acc.iter_mut()) {
                *o += *a as f64;
                *a = 0.0;
            }
        };
        for (i, y) in (core.y..core.y_end()).enumerate() {
            let (ur, vr) = (flow.u.row(y), flow.v.row(y));
            match (ur.as_slice(), vr.as_slice()) {
                (Some(u), Some(v)) => {
                    let (u, v) = (&u[x0..x1], &v[x0..x1]);
                    for (a, &b) in self.acc_u.iter_mut().zip(u) {
                        *a += b;
                    }
                    for ((a, &b), &c) in self.acc_m.iter_mut().zip(u).zip(v) {
                        *a += (b * b + c * c).sqrt();
                    }
                }
                _ => {
                    for (k, x) in (x0..x1).enumerate() {
                        self.acc_u[k] += ur[x];
                        self.acc_m[k] += ur[x].hypot(vr[x]);
                    }
                }
            }
            if i % 64 == 63 {
                flush(&mut self.acc_u, &mut self.profile);
                flush(&mut self.acc_m, &mut self.mag_profile);
            }
        }
        flush(&mut self.acc_u, &mut self.profile);
        flush(&mut self.acc_m, &mut self.mag_profile);
    }
}

/// Restricts `b` along x (or y) to `[start, end)`, each bound kept when `None`.
fn set_range(b: &mut BoundingBox, along_x: bool, start: Option<usize>, end: Option<usize>) {
    let (lo, len) = if along_x {
        (&mut b.x, &mut b.width)
    } else {
        (&mut b.y, &mut b.height)
    };
    let hi = end.unwrap_or(*lo + *len);
    let lo2 = start.unwrap_or(*lo);
    *lo = lo2;
    *len = hi - lo2;
}

/// Rule that splits one group of contours (a connected mask region, or
/// contours whose margins overlap) that holds several contacts.
///
/// Physics: a press pushes the skin **outward** from the contact (positive
/// divergence of the marker flow, the nHHD potential's minimum), and the
/// skin between two presses is squeezed from both sides (negative
/// divergence). Shear adds a one-signed displacement whose divergence is
/// positive on one flank and negative on the other, one lobe each. So the
/// column (or row) sums of the displacement along x (or y), smoothed and differentiated, show one positive lobe per
/// contact; the group is cut between two positive lobes of heights `p1` and
/// `p2` (each at least `min_peak` times the group's highest) when the
/// profile between them falls to `-depth * min(p1, p2)` or below, at that
/// minimum (the point where the skin is squeezed most). A flat 10 mm punch
/// that holds the skin under it still has a zero, not a negative,
/// divergence between its two edges, so it stays one patch.
///
/// The profile runs along the image's longer side: x (column sums of `u`)
/// when the flow is at least as wide as tall, else y (row sums of `v`). For
/// a strip-shaped skin that is its length, along which contacts lie; across
/// it the flow of a rod is mostly noise (and a yawed press adds a shear
/// whose noise-sized structure there would split it). With `across` (a
/// sensor that locates contacts in 2-D, [`SplitRule::for_geometry`]), each
/// piece is then cut the same way along the other side too, from the
/// profile of the flow along that side: on a fingertip's gel contacts lie
/// anywhere.
///
/// Peaks closer than `border` to the image's ends are not contacts: the
/// flow is least constrained there and a single press shows a spurious
/// divergence peak at the strip's end (simulator, accurate DIS).
///
/// Limits: only contacts side by side along that direction (or, with
/// `across`, along either image side) are separated, and only if the
/// weaker one's peak is at least `min_peak` times the stronger's (the
/// simulator's strip and the paper's rods); a piece whose summed `|flow|`
/// is below [`Thresholds::sum`] (or, with `press_swing`, that shows no
/// press's swing) is given back to its neighbour, so a press sheared
/// strongly enough that its motion along the axis never falls below zero
/// stays joined to a neighbour.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SplitRule {
    /// Width of the box filter applied twice to the profile before
    /// differentiating, full-resolution pixels (scaled like the kernels).
    pub smooth: usize,
    /// Valley depth as a fraction of the lower of the two peaks (> 0).
    pub depth: f32,
    /// Smallest peak that may be a contact, as a fraction of the group's
    /// highest peak, in [0, 1].
    pub min_peak: f32,
    /// Peaks closer than this to either end of the image (along the
    /// profile) are ignored, full-resolution pixels (scaled like the
    /// margin).
    pub border: usize,
    /// Two peaks at least this far apart, full-resolution pixels (scaled
    /// like the margin), are cut wherever the profile between them goes
    /// below zero, however shallow the valley; 0 turns this off (rules
    /// from before it).
    #[serde(default)]
    pub far_px: usize,
    /// With `far_px`, a peak at least `far_px` from every peak of
    /// `min_peak` or more, and half of `far_px` inside the range where
    /// peaks count, counts from this fraction of the highest peak, in [0,
    /// 1] (at most `min_peak` is used). With `far_px` 0, as in rules from
    /// before the far rules, only `min_peak` counts.
    #[serde(default)]
    pub far_min_peak: f32,
    /// Each piece is also cut along the image's shorter side (the
    /// profile of the flow along that side, summed across it). Absent
    /// (false) in rules from before it.
    #[serde(default)]
    pub across: bool,
    /// Each piece must show a press's swing: the motion along the cut axis
    /// (summed across) below zero before the piece's divergence peak and
    /// above zero after it, as a press pushes the gel away from it both
    /// ways. Beside a press sheared along that axis the gel is squeezed
    /// ahead of it and a positive lobe of divergence follows, which with
    /// the valley looks like a second press; there the motion only returns
    /// towards zero. Absent (false) in rules from before it.
    #[serde(default)]
    pub press_swing: bool,
}

impl SplitRule {
    /// The rule used by [`Segmenter::new`]: smoothing 21 px, depth 0.1,
    /// min_peak 0.4, border 32 px, far 250 px from 0.3 of the highest peak.
    /// Chosen on the simulator
    /// (`tools/src/bin/split_check.rs`, seeds 1 to 4 with the far rules,
    /// 1 and 2 before them): 0 of 525 single presses (7 positions, 5 tilts,
    /// 0.5-3 N, 2/5/10 mm rods) cut, for every preset; 0 false contacts on
    /// 1500 rest pairs (see docs/results.md).
    ///
    /// Why the far rule: on a curved skin a press also moves the markers
    /// one way along the arc, far out (the camera sees the inward push
    /// slanted), and the sign of that motion flips from one half of the
    /// skin to the other. Two presses on either side of the middle then
    /// fill each other's valley: a 3 N and a 1.5 N rod 110 mm apart leave
    /// a valley of 3% of the higher peak between lobes of 100% and 60%,
    /// and one of them was lost; a 1 N rod 60 mm from a 3 N one makes a
    /// lobe of 31-39%, under `min_peak`. A single press's own lobes lie
    /// closer together than 250 px (a 0.5 N press's weak far lobes reach
    /// 200 px).
    pub const DEFAULT: SplitRule = SplitRule {
        smooth: 21,
        depth: 0.1,
        min_peak: 0.4,
        border: 32,
        far_px: 250,
        far_min_peak: 0.3,
        across: false,
        press_swing: false,
    };

    /// The rule for a sensor that locates contacts in 2-D (a flat
    /// fingertip's gel): cuts along both image sides (`across`), from
    /// peaks of 0.2 of the highest (a flat punch's divergence spreads along
    /// its rim: an 8 mm punch at 1.5 N peaks at a third of a 5 mm sphere's
    /// at 2 N beside it), without the far rules (they answer the strip's
    /// far motion along its arc; a fingertip's image is a few hundred
    /// pixels across). The rest as [`SplitRule::DEFAULT`].
    pub const FLAT: SplitRule = SplitRule {
        min_peak: 0.2,
        far_px: 0,
        far_min_peak: 0.0,
        across: true,
        press_swing: true,
        ..SplitRule::DEFAULT
    };

    /// The rule for `geometry`: [`SplitRule::FLAT`] where contacts are
    /// located in 2-D, else [`SplitRule::DEFAULT`].
    pub fn for_geometry(geometry: &crate::geometry::SensorGeometry) -> SplitRule {
        if geometry.locates_in_2d() {
            SplitRule::FLAT
        } else {
            SplitRule::DEFAULT
        }
    }

    /// Errors unless `smooth >= 1`, `depth` finite and > 0 and `min_peak`
    /// and `far_min_peak` in [0, 1].
    pub fn validate(&self) -> Result<()> {
        if self.smooth == 0 {
            return Err(Error::param("split.smooth", "must be >= 1"));
        }
        if !(self.depth.is_finite() && self.depth > 0.0) {
            return Err(Error::param(
                "split.depth",
                format!("must be finite and > 0, got {}", self.depth),
            ));
        }
        if !(0.0..=1.0).contains(&self.min_peak) {
            return Err(Error::param(
                "split.min_peak",
                format!("must be in [0, 1], got {}", self.min_peak),
            ));
        }
        if !(0.0..=1.0).contains(&self.far_min_peak) {
            return Err(Error::param(
                "split.far_min_peak",
                format!("must be in [0, 1], got {}", self.far_min_peak),
            ));
        }
        Ok(())
    }

    /// Smoothing radius (half the odd filter width) in the pixels of a flow
    /// at `scale`.
    pub fn radius(&self, scale: f64) -> usize {
        (odd(self.smooth, 1.0 / scale) - 1) / 2
    }
}

/// The smoothed derivative of `profile`: `profile` box-filtered twice with
/// width `2 radius + 1` (windows clipped at the ends, means over what is
/// inside) into `smoothed`, then central differences (one-sided at the ends)
/// into `divergence`. Both outputs have `profile`'s length.
pub fn divergence_profile(
    profile: &[f64],
    radius: usize,
    smoothed: &mut Vec<f64>,
    divergence: &mut Vec<f64>,
) {
    let n = profile.len();
    smoothed.clear();
    smoothed.extend_from_slice(profile);
    // `divergence` holds the prefix sums meanwhile (no allocation per call
    // once the buffers have grown).
    for _ in 0..2 {
        let prefix = &mut *divergence;
        prefix.clear();
        prefix.push(0.0);
        let mut acc = 0.0;
        for &p in smoothed.iter() {
            acc += p;
            prefix.push(acc);
        }
        for (i, s) in smoothed.iter_mut().enumerate() {
            let (a, b) = (i.saturating_sub(radius), (i + radius + 1).min(n));
            *s = (prefix[b] - prefix[a]) / (b - a) as f64;
        }
    }
    divergence.clear();
    divergence.extend((0..n).map(|i| {
        let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
        if b > a {
            (smoothed[b] - smoothed[a]) / (b - a) as f64
        } else {
            0.0
        }
    }));
}

/// The split rule on a divergence profile: the indices where it cuts, in
/// increasing order, into `cuts` (cleared first). A cut at `c` separates
/// `[.., c)` from `[c, ..)`; see [`SplitRule`].
///
/// Only peaks at indices in `peaks_in` count (the caller leaves out the
/// image's ends, see [`SplitRule::border`]). [`SplitRule::far_px`] is read
/// in the profile's cells: the caller scales it to the flow's grid.
pub fn find_cuts(
    divergence: &[f64],
    rule: &SplitRule,
    peaks_in: std::ops::Range<usize>,
    cuts: &mut Vec<usize>,
) {
    cuts.clear();
    let top = divergence
        .get(peaks_in.clone())
        .unwrap_or(&[])
        .iter()
        .copied()
        .fold(0.0f64, f64::max);
    if top <= 0.0 {
        return;
    }
    let level = rule.min_peak as f64 * top;
    let far_on = rule.far_px > 0;
    let low = if far_on {
        (rule.far_min_peak.min(rule.min_peak)) as f64 * top
    } else {
        level
    };
    // Candidate peaks, the maximum of each run of positive values at least
    // `low` high, into `cuts` (it holds the peaks until the cuts replace
    // them: the cut after peak k is written at index k - 1 or before).
    let n = divergence.len();
    let mut i = 0;
    while i < n {
        if divergence[i] <= 0.0 {
            i += 1;
            continue;
        }
        let (mut best, mut at) = (divergence[i], i);
        while i < n && divergence[i] > 0.0 {
            if divergence[i] > best {
                (best, at) = (divergence[i], i);
            }
            i += 1;
        }
        if best >= low && peaks_in.contains(&at) {
            cuts.push(at);
        }
    }
    // A peak under `level` counts only far (`far_px`) from every peak above
    // it, where a strong press's own lobes do not reach, and at least half
    // of that inside the range where peaks count, away from the spurious
    // lobes at the ends of the flow.
    let strong = |k: usize| divergence[k] >= level;
    let inset = rule.far_px / 2;
    let weak_in = peaks_in.start.saturating_add(inset)..peaks_in.end.saturating_sub(inset);
    let mut kept = 0;
    for j in 0..cuts.len() {
        let at = cuts[j];
        let keep = strong(at)
            || weak_in.contains(&at)
                && cuts
                    .iter()
                    .all(|&o| !strong(o) || o.abs_diff(at) >= rule.far_px);
        if keep {
            cuts[kept] = at;
            kept += 1;
        }
    }
    cuts.truncate(kept);
    // The cuts: between consecutive peaks, at the valley's minimum when it
    // is deep enough (or, far apart, below zero).
    let mut written = 0;
    let (mut g, mut last) = (0.0, 0usize); // highest peak of the group, last peak
    for k in 0..cuts.len() {
        let (at, best) = (cuts[k], divergence[cuts[k]]);
        if k == 0 {
            (g, last) = (best, at);
            continue;
        }
        let (mut v, mut v_at) = (f64::INFINITY, last);
        for (j, &d) in divergence.iter().enumerate().take(at).skip(last + 1) {
            if d < v {
                (v, v_at) = (d, j);
            }
        }
        let far = far_on && at - last >= rule.far_px;
        if v <= -(rule.depth as f64) * g.min(best) || (far && v < 0.0) {
            cuts[written] = v_at;
            written += 1;
            g = best;
        } else {
            g = g.max(best);
        }
        last = at;
    }
    cuts.truncate(written);
}

/// Nearest odd size to `size * s`, at least 1.
fn odd(size: usize, s: f64) -> usize {
    let v = size as f64 * s;
    ((((v - 1.0) / 2.0).round().max(0.0)) as usize) * 2 + 1
}

fn check_scale(scale: f64) -> Result<()> {
    if !(scale.is_finite() && scale > 0.0) {
        return Err(Error::param(
            "scale",
            format!("must be finite and > 0, got {scale}"),
        ));
    }
    Ok(())
}

fn check_flow(flow: &FlowField) -> Result<()> {
    if flow.u.dim() != flow.v.dim() {
        return Err(Error::shape(
            "flow planes (v against u)",
            (flow.u.ncols(), flow.u.nrows()),
            (flow.v.ncols(), flow.v.nrows()),
        ));
    }
    let (w, h) = flow.size();
    if w == 0 || h == 0 {
        return Err(Error::TooSmall {
            what: "flow to segment".into(),
            width: w,
            height: h,
            min_w: 1,
            min_h: 1,
        });
    }
    Ok(())
}

/// Sum of `|flow|` over a box: per row in f32 with eight lanes (vectorises),
/// rows accumulated in f64. A row whose f32 squares overflow is redone in f64.
/// Whether [`box_sum_where`] of `b` reaches `limit` (`>=`): the same sum
/// in the same order, stopped at the end of the first row where it has
/// reached it. Every term is non-negative, and adding a non-negative
/// number never lowers a floating-point sum, so the whole sum would reach
/// it too: the same answer, and a large patch stops after a few rows.
fn box_sum_where_reaches(flow: &FlowField, b: &BoundingBox, mask: &Mask, limit: f64) -> bool {
    let mut sum = 0.0f64;
    if sum >= limit {
        return true;
    }
    for y in b.y..b.y_end() {
        for x in b.x..b.x_end() {
            if mask.get(x, y) {
                sum += f64::from(flow.u[[y, x]]).hypot(f64::from(flow.v[[y, x]]));
            }
        }
        if sum >= limit {
            return true;
        }
    }
    false
}

/// Summed `|flow|` over the pixels of box `b` set in `mask` (the slow,
/// plain sum: it runs only on the few contours of the observable part).
#[cfg(test)]
fn box_sum_where(flow: &FlowField, b: &BoundingBox, mask: &Mask) -> f64 {
    let mut sum = 0.0f64;
    for y in b.y..b.y_end() {
        for x in b.x..b.x_end() {
            if mask.get(x, y) {
                sum += f64::from(flow.u[[y, x]]).hypot(f64::from(flow.v[[y, x]]));
            }
        }
    }
    sum
}

fn box_sum(flow: &FlowField, b: &BoundingBox) -> f64 {
    let exact = |u: &[f32], v: &[f32]| -> f64 {
        u.iter()
            .zip(v)
            .map(|(&a, &c)| ((a as f64).powi(2) + (c as f64).powi(2)).sqrt())
            .sum()
    };
    let mut s = 0.0f64;
    for y in b.y..b.y_end() {
        let (ur, vr) = (flow.u.row(y), flow.v.row(y));
        s += match (ur.as_slice(), vr.as_slice()) {
            (Some(u), Some(v)) => {
                let (u, v) = (&u[b.x..b.x_end()], &v[b.x..b.x_end()]);
                let mut acc = [0.0f32; 8];
                let (uc, vc) = (u.chunks_exact(8), v.chunks_exact(8));
                let (ut, vt) = (uc.remainder(), vc.remainder());
                for (a, c) in uc.zip(vc) {
                    for i in 0..8 {
                        acc[i] += (a[i] * a[i] + c[i] * c[i]).sqrt();
                    }
                }
                let row = acc.iter().map(|&x| x as f64).sum::<f64>() + exact(ut, vt);
                if row.is_finite() { row } else { exact(u, v) }
            }
            _ => (b.x..b.x_end())
                .map(|x| ((ur[x] as f64).powi(2) + (vr[x] as f64).powi(2)).sqrt())
                .sum::<f64>(),
        };
    }
    s
}

/// The exact `q` quantile of `|flow|` over all pixels of all `flows` (the
/// value of rank `ceil(q n)`), in bounded memory: a histogram over
/// `[0, max]` finds the bin holding that rank, then only that bin's values
/// are kept and selected.
fn magnitude_quantile(flows: &[FlowField], q: f64) -> f32 {
    const BINS: usize = 1 << 16;
    let mags = || {
        flows
            .iter()
            .flat_map(|f| f.u.iter().zip(f.v.iter()).map(|(u, v)| u.hypot(*v)))
    };
    let n: usize = flows.iter().map(|f| f.u.len()).sum();
    let max = mags().fold(0.0f32, f32::max);
    if n == 0 || max == 0.0 {
        return 0.0;
    }
    let bin = |m: f32| (((m / max) as f64 * BINS as f64) as usize).min(BINS - 1);
    let mut hist = vec![0usize; BINS];
    for m in mags() {
        hist[bin(m)] += 1;
    }
    let rank = ((q * n as f64).ceil() as usize).clamp(1, n) - 1;
    let mut before = 0;
    let mut b = 0;
    while before + hist[b] <= rank {
        before += hist[b];
        b += 1;
    }
    let mut inside: Vec<f32> = mags().filter(|&m| bin(m) == b).collect();
    let (_, &mut v, _) = inside.select_nth_unstable_by(rank - before, f32::total_cmp);
    v
}

/// Largest sum of `|flow|` over any `k x k` window (integral image).
fn max_window_sum(flow: &FlowField, k: usize, integral: &mut Vec<f64>) -> f64 {
    let (w, h) = flow.size();
    let k = k.min(w).min(h);
    let iw = w + 1;
    integral.clear();
    integral.resize(iw * (h + 1), 0.0);
    for y in 0..h {
        let mut row = 0.0f64;
        for x in 0..w {
            row += flow.u[[y, x]].hypot(flow.v[[y, x]]) as f64;
            integral[(y + 1) * iw + x + 1] = integral[y * iw + x + 1] + row;
        }
    }
    let mut best = 0.0f64;
    for y in 0..=h - k {
        for x in 0..=w - k {
            let s = integral[(y + k) * iw + x + k]
                - integral[y * iw + x + k]
                - integral[(y + k) * iw + x]
                + integral[y * iw + x];
            best = best.max(s);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_stopped_masked_sum_answers_as_the_whole_sum() {
        // Random flows, masks and boxes; limits at the whole sum, one ulp
        // either side of it, at a partial row sum, 0, negative and NaN.
        let mut rnd = crate::flow::unit_stream(0x1f83_d9ab_fb41_bd6bu64);
        for round in 0..80 {
            let (w, h) = (3 + (20.0 * rnd()) as usize, 2 + (12.0 * rnd()) as usize);
            let mut f = FlowField::zeros(w, h);
            for y in 0..h {
                for x in 0..w {
                    f.u[[y, x]] = 4.0 * rnd() - 2.0;
                    f.v[[y, x]] = if rnd() < 0.1 { -0.0 } else { 4.0 * rnd() - 2.0 };
                }
            }
            let density = rnd();
            let mask = Mask::from_fn(w, h, |_, _| rnd() < density);
            let (x0, y0) = ((w as f32 * rnd()) as usize, (h as f32 * rnd()) as usize);
            let b = BoundingBox::new(
                x0,
                y0,
                1 + ((w - x0 - 1) as f32 * rnd()) as usize,
                1 + ((h - y0 - 1) as f32 * rnd()) as usize,
            );
            let whole = box_sum_where(&f, &b, &mask);
            let first_row = box_sum_where(&f, &BoundingBox::new(b.x, b.y, b.width, 1), &mask);
            let limits = [
                whole,
                f64::from_bits(whole.to_bits() + 1),
                if whole > 0.0 {
                    f64::from_bits(whole.to_bits() - 1)
                } else {
                    -1.0
                },
                first_row,
                0.0,
                -3.0,
                f64::NAN,
                whole * 0.5,
            ];
            for limit in limits {
                assert_eq!(
                    box_sum_where_reaches(&f, &b, &mask, limit),
                    whole >= limit,
                    "round {round}, limit {limit}, sum {whole}"
                );
            }
        }
    }

    #[test]
    fn odd_sizes() {
        assert_eq!(odd(13, 0.25), 3);
        assert_eq!(odd(5, 0.25), 1);
        assert_eq!(odd(25, 0.25), 7);
        assert_eq!(odd(21, 1.0), 21);
        assert_eq!(odd(1, 0.01), 1);
    }

    #[test]
    fn scaling_of_the_thresholds() {
        let t = Thresholds::HIGH.at_scale(4.0).unwrap();
        assert!((t.magnitude - 0.55 / 4.0).abs() < 1e-6);
        assert!((t.sum - 3000.0 / 64.0).abs() < 1e-9);
        assert_eq!(t.erode, StructuringElement::rect(3, 3));
        assert!(Thresholds::HIGH.at_scale(0.0).is_err());
        assert!(Thresholds::HIGH.at_scale(f64::NAN).is_err());
        let bad = Thresholds {
            sum: -1.0,
            ..Thresholds::LOW
        };
        assert!(bad.validate().is_err());
        let bad = Thresholds {
            erode: 0,
            ..Thresholds::LOW
        };
        assert!(
            Segmenter::new(SegmenterConfig {
                thresholds: bad,
                ..Default::default()
            })
            .is_err()
        );
    }

    #[test]
    fn patch_in_full_resolution() {
        let p = ContactPatch {
            bbox: BoundingBox::new(3, 5, 10, 4),
            core: BoundingBox::new(4, 6, 8, 2),
            seen: true,
            flow_sum: 1.0,
            area: 16,
        };
        assert_eq!(
            p.full_res_roi(4.0),
            Roi {
                x: 12,
                y: 20,
                w: 40,
                h: 16
            }
        );
        assert_eq!(
            p.full_res_roi(1.0),
            Roi {
                x: 3,
                y: 5,
                w: 10,
                h: 4
            }
        );
        let g = p.grid(4.0);
        assert_eq!((g.x0, g.y0, g.scale), (3, 5, 4.0));
    }

    #[test]
    fn presets_by_name_and_json() {
        assert_eq!(
            "HIGH".parse::<ThresholdPreset>().unwrap(),
            ThresholdPreset::High
        );
        assert_eq!(
            "low".parse::<ThresholdPreset>().unwrap(),
            ThresholdPreset::Low
        );
        assert!("extreme".parse::<ThresholdPreset>().is_err());
        for p in ThresholdPreset::ALL {
            assert_eq!(p.to_string().parse::<ThresholdPreset>().unwrap(), p);
            assert_eq!(Thresholds::preset(p).as_preset(), Some(p));
        }
        let custom = Thresholds {
            magnitude: 0.2,
            ..Thresholds::LOW
        };
        assert_eq!(custom.as_preset(), None);
        let json = serde_json::to_string(&SegmenterConfig::default()).unwrap();
        assert!(json.contains("\"shape\":\"rect\""), "{json}");
        let back: SegmenterConfig = serde_json::from_str(&json).unwrap();
        assert_eq!(back, SegmenterConfig::default());
    }

    #[test]
    fn presets_are_ordered() {
        for (a, b) in [
            (Thresholds::LOW, Thresholds::MID),
            (Thresholds::MID, Thresholds::HIGH),
        ] {
            assert!(a.magnitude < b.magnitude && a.sum < b.sum && a.erode <= b.erode);
        }
    }

    #[test]
    fn quantile_matches_sorting() {
        let mut seed = 7u64;
        let flows: Vec<FlowField> = (0..3)
            .map(|_| {
                let mut f = FlowField::zeros(13, 7);
                for (u, v) in f.u.iter_mut().zip(f.v.iter_mut()) {
                    seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
                    *u = ((seed >> 40) % 1000) as f32 / 100.0;
                    *v = ((seed >> 20) % 7) as f32 - 3.0;
                }
                f
            })
            .collect();
        let mut all: Vec<f32> = flows
            .iter()
            .flat_map(|f| f.u.iter().zip(f.v.iter()).map(|(u, v)| u.hypot(*v)))
            .collect();
        all.sort_by(f32::total_cmp);
        for q in [0.001, 0.1, 0.5, 0.9, 0.99, 0.999999] {
            let rank = ((q * all.len() as f64).ceil() as usize).clamp(1, all.len()) - 1;
            assert_eq!(magnitude_quantile(&flows, q), all[rank], "q {q}");
        }
        assert_eq!(magnitude_quantile(&[FlowField::zeros(3, 3)], 0.9), 0.0);
    }

    #[test]
    fn box_sum_is_accurate_and_survives_overflowing_squares() {
        let mut f = FlowField::zeros(37, 3);
        f.u.fill(3.0);
        f.v.fill(4.0);
        let b = BoundingBox::new(2, 0, 33, 3);
        assert!((box_sum(&f, &b) - 5.0 * 99.0).abs() < 1e-9);
        f.u[[1, 10]] = 1e30;
        let s = box_sum(&f, &b);
        assert!(((s - 1e30) / 1e30).abs() < 1e-6, "{s}");
    }

    #[test]
    fn window_sum_matches_brute_force() {
        let mut f = FlowField::zeros(7, 5);
        for y in 0..5 {
            for x in 0..7 {
                f.u[[y, x]] = ((x * 3 + y * 5) % 7) as f32;
                f.v[[y, x]] = ((x + y) % 3) as f32 - 1.0;
            }
        }
        let mut buf = Vec::new();
        for k in 1..=5 {
            let mut best = 0.0f64;
            for y in 0..=5 - k {
                for x in 0..=7 - k {
                    best = best.max(box_sum(&f, &BoundingBox::new(x, y, k, k)));
                }
            }
            assert!(
                (max_window_sum(&f, k, &mut buf) - best).abs() < 1e-4,
                "k {k}"
            );
        }
    }
}
