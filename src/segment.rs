//! Cutting a flow into contact patches (SPEC.md step 5, the paper's
//! "Thresholds" section).
//!
//! [`Segmenter::segment`]: `|flow|` → threshold → binary mask → erode (drops
//! specks smaller than the kernel) → dilate (restores the region, joins what
//! erosion split) → **external** contours only → one bounding box per contour
//! → discard boxes whose summed `|flow|` is below a second threshold → grow the
//! boxes by a margin, clamp them to the image, merge the ones that overlap →
//! [`ContactPatch`]es, each a box over the **unmodified** flow.
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
//! - Boxes that share at least one pixel after the margin are merged into
//!   their union box, repeatedly until no two overlap: one patch per group.
//!   The nHHD of a patch assumes one contact in it, and two overlapping boxes
//!   would count the shared flow twice. Boxes that only touch stay apart.
//! - The summed `|flow|` test is made on each contour's own box (before the
//!   margin), as in the paper; a merged patch reports the sum over its final box.

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

use ndarray::ArrayView2;

use crate::contact::PatchGrid;
use crate::contours::{BoundingBox, ContourFinder};
use crate::error::{Error, Result};
use crate::flow::FlowField;
use crate::image::Roi;
use crate::morphology::{Mask, Morphology, Shape, StructuringElement};

/// Segmentation thresholds and kernels, in **full-resolution** pixels (see
/// the module docs for how they scale).
///
/// The presets [`Thresholds::LOW`], [`Thresholds::MID`] and
/// [`Thresholds::HIGH`] were chosen on the simulator (default 1600 x 200 px
/// strip, 5 px/mm) through [`ContactExtractor`](crate::sensor::ContactExtractor)
/// with the default (accurate) DIS flow at its native resolution (scale 2).
/// Measured with `cargo run --release --example sweep` (seed 1; tables in
/// docs/results/segmentation.md):
///
/// | preset | min. detectable force (>= 95%) | every press from | false contacts at rest |
/// |---|---|---|---|
/// | LOW  | 0.4 N (target < 0.5 N; wish <= 0.3 N not met: 89% at 0.3 N) | 0.6 N | 0 / 1500 pairs |
/// | MID  | 0.8 N (target 0.5-1 N) | 1.2 N | 0 / 1500 pairs |
/// | HIGH | 1.2 N (target 1-1.5 N) | 1.8 N | 0 / 1500 pairs |
///
/// Minimum detectable force: smallest force of a 0.1 N ladder from which at
/// least 95% of single presses are detected (a patch covering the rod), over
/// 7 positions along the skin (-120..120 mm), the 2, 5 and 10 mm rods and the
/// protocol's 5 tilts; the limit is set by purely normal presses (centre,
/// straight, or a tilt that cancels the skin's slope), which move markers
/// least. Rest pairs: a reference against another unloaded frame with fresh
/// noise and flicker; the largest summed `|flow|` of any rest contour was
/// 1390 (LOW's kernels), 960 (MID's and HIGH's), below every preset's `sum`.
///
/// Two rods are not told apart as closely as the target (15 mm) with the
/// extractor's 24 px margin: a pair of straight presses at the skin's centre
/// is two patches from 20 mm (MID, 1.5 N) to 40 mm (LOW, 3 N), mostly
/// because the margins merge two separate contours (without margin: 10-17.5
/// mm under MID); off centre, where the skin's slope turns part of the load
/// into shear, 3 N moves the whole strip above the magnitude threshold and
/// both rods fall in one patch (see docs/results/segmentation.md).
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
    /// on the simulator (target below 0.5 N); just above the accurate flow's
    /// rest noise (typically ~0.14 px), so the sum test (1500, above the
    /// largest rest contour's 1390) is what rejects noise: little headroom
    /// for a noisier camera.
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

    /// The preset named `low`, `mid` or `high` (any case).
    pub fn preset(name: &str) -> Result<Thresholds> {
        match name.to_ascii_lowercase().as_str() {
            "low" => Ok(Thresholds::LOW),
            "mid" => Ok(Thresholds::MID),
            "high" => Ok(Thresholds::HIGH),
            _ => Err(Error::param(
                "thresholds",
                format!("unknown preset `{name}` (expected low, mid or high)"),
            )),
        }
    }

    /// Errors unless the thresholds are finite and non-negative and the
    /// kernels at least 1.
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
            if k == 0 {
                return Err(Error::param(
                    format!("thresholds.{name}"),
                    "kernel size must be >= 1",
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
}

impl Segmenter {
    /// A segmenter for `config`. Errors on invalid thresholds or scale.
    pub fn new(config: SegmenterConfig) -> Result<Self> {
        let scaled = config.thresholds.at_scale(config.scale)?;
        Ok(Segmenter {
            config,
            scaled,
            margin: (config.margin as f64 / config.scale).round() as usize,
            morph: Morphology::new(),
            contours: ContourFinder::new(),
            raw: Mask::default(),
            eroded: Mask::default(),
            mask: Mask::default(),
            boxes: Vec::new(),
            contour_sums: Vec::new(),
            merged: Vec::new(),
        })
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
        for &(bbox, core) in &self.merged {
            out.push(ContactPatch {
                bbox,
                core,
                flow_sum: box_sum(flow, &bbox),
                area: self
                    .mask
                    .count_ones_in(bbox.x, bbox.y, bbox.x_end(), bbox.y_end()),
            });
        }
        Ok(())
    }
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
        assert_eq!(Thresholds::preset("HIGH").unwrap(), Thresholds::HIGH);
        assert_eq!(Thresholds::preset("low").unwrap(), Thresholds::LOW);
        assert!(Thresholds::preset("extreme").is_err());
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
