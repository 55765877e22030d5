//! Dense Inverse Search (Kroeger et al., ECCV 2016) optical flow.
//!
//! [`Dis`] is a planner: [`Dis::set_reference`] computes everything that
//! depends only on the reference frame (pyramid, Sobel gradients, the patch
//! grid, each patch's mean-normalized structure tensor and its inverse), and
//! [`Dis::compute_into`] then estimates the flow from the reference to a
//! current frame without allocating. The flow maps reference pixels to the
//! current frame: `cur(x + u, y + v) ≈ ref(x, y)`.
//!
//! Per pyramid level, from the coarsest to the finest computed scale:
//! 1. each patch (a `patch_size` square every `patch_stride` pixels) starts
//!    from the coarser level's dense flow at its centre;
//! 2. two passes of inverse-compositional Gauss-Newton descent on the
//!    mean-normalized SSD, with spatial propagation from the already-visited
//!    neighbours (forward: left/up; backward: right/down) inside fixed stripes
//!    of patch rows, so the result never depends on the thread count;
//! 3. densification: every pixel averages the vectors of the patches covering
//!    it, weighted by `1 / max(1, |cur(x + u) - ref(x)|)`;
//! 4. variational refinement of the dense flow
//!    ([`super::refine::VariationalRefiner`], one per level, its reference
//!    data cached in `set_reference`);
//!
//! and the finest level's flow is bilinearly resized to full resolution
//! ([`Dis::compute_into`]) or read at its own level ([`Dis::native_flow`]).
//!
//! The `Ultrafast`, `Fast` and `Medium` presets use OpenCV 5's values; the
//! `Accurate` preset (the default here) and `Balanced` fix what makes OpenCV's
//! DIS weak on marker images (see [`DisPreset::Accurate`]); `Fine`, the tactile
//! sensor's preset, runs the search at full resolution ([`DisPreset::Fine`]),
//! and `Dense` does so with overlapping patches ([`DisPreset::Dense`]).
//!
//! Bad input is an [`Error`]: an empty reference or one too small for a
//! patch at the finest scale ([`Error::TooSmall`]), a current frame of
//! another size ([`Error::ShapeMismatch`]), NaN or infinite pixels
//! ([`Error::NonFinite`], with the first offending pixel), `compute` before
//! `set_reference` ([`Error::NoReference`]), invalid parameters
//! ([`Error::InvalidParameter`]).

use ndarray::{ArrayRef2, ArrayView2};
use rayon::prelude::*;

use super::FlowField;
use super::pyramid::{self, ResizeAxis};
use super::refine::{RefineParams, VariationalRefiner};
use crate::error::{Error, Result};

/// Largest supported patch side (keeps the per-patch scratch on the stack).
pub const MAX_PATCH_SIZE: usize = 32;

/// Largest `gradient_descent_iterations` of [`DisParams`]: 1000 (the presets
/// use 4 to 25).
pub const MAX_DESCENT_ITERATIONS: usize = 1000;

/// Largest `coarsest_scale` of [`DisParams`]: 16 (a level of
/// [`crate::frame::MAX_FRAME_SIDE`] pixels is a single pixel at scale 14).
pub const MAX_SCALE: usize = 16;

/// Largest `stripes` and `min_stripe_rows` of [`DisParams`]: 4096.
pub const MAX_STRIPES: usize = 4096;

/// Named parameter sets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DisPreset {
    /// OpenCV 5 `PRESET_ULTRAFAST`: scale 2, 8/4 patches, 12 descent
    /// iterations, no variational refinement.
    Ultrafast,
    /// OpenCV 5 `PRESET_FAST` (the paper's default): scale 2, 8/4 patches,
    /// 16 descent iterations, 5 refinement iterations, but the refinement
    /// only on the finest level (`refine_levels = Some(1)`: 17 % fewer
    /// instructions at 1080p), OpenCV's step order at the descent's stop
    /// (`step_on_stop`), propagation stripes of at least 3 patch rows
    /// (`min_stripe_rows`) and a coarsest level at least 3 patches high
    /// (`coarsest_min_patches`: OpenCV's 30x16 top level of a 1080p marker
    /// image is aliased noise that made 16.7 px of motion fail). Measured
    /// against OpenCV FAST in docs/results.md.
    /// [`DisParams::opencv_semantics`] restores OpenCV's.
    Fast,
    /// OpenCV 5 `PRESET_MEDIUM`: scale 1, 8/3 patches, 25 descent
    /// iterations, 5 refinement iterations.
    Medium,
    /// Our most accurate marker-image flow (the lowest endpoint error on
    /// our synthetic pairs; the sensor's default until [`DisPreset::Fine`]
    /// matched its forces better): the finest scale
    /// 1 (1-px markers are sub-pixel dots at scale 2), true Gauss-Newton
    /// steps (Sobel normalized to the true derivative, so each step solves
    /// the linearized problem instead of moving 1/8 of the way; 8 iterations
    /// then do more than 16 did), a Gaussian prefilter of 1.5 level px at the
    /// finest level, which removes most of the bilinear "peak locking"
    /// towards whole-pixel shifts (the sub-pixel bias), the zero vector as
    /// an extra candidate (coarse levels of dense marker images are
    /// aliased), and one outer iteration of OpenCV's variational refinement
    /// (needed under strong strain, where rigid patches fail), on every
    /// level: refining the finest level only changed AEPE by at most
    /// 0.0002 px on our synthetic pairs and saved ~10 % of the time, but it
    /// moved the sensor's calibrated contacts (test MAE 0.24 -> 0.29 mm,
    /// Fz 0.118 -> 0.121 N on the simulator's protocol), so it stays off. A second
    /// refinement iteration with a 1-px prefilter lowers the error under
    /// strong strain further but brings the sub-pixel bias back above
    /// 0.01 px (the refinement over-shoots sub-pixel shifts).
    Accurate,
    /// [`DisPreset::Accurate`] without the refinement and with a stronger
    /// prefilter (2 level px): about half the time, as accurate on gentle
    /// motion and with the smallest sub-pixel bias, but much worse under
    /// strong strain (steep presses: rigid patches with no refinement).
    Balanced,
    /// The tactile sensor's preset: [`DisPreset::Balanced`]'s patch search
    /// at full resolution (finest scale 0), 8-px patches on an 8-px stride,
    /// 4 descent iterations, a 1.5 px prefilter, no refinement and a texture
    /// gate of 1 (the full-resolution noise of the black coating beyond the
    /// skin reaches 0.1, [`DisPreset::Accurate`]'s gate, at its edge). Under a
    /// rod the skin's along-arc motion has a near step (the normal load) and
    /// a sharp peak (the tangential load) a few pixels wide; a flow computed
    /// at half resolution blurs them by an amount that depends on the marker
    /// pattern there, and the forces matched to the blurred profile scatter
    /// with the position (docs/results.md). At full resolution
    /// the shape survives, and the coarser stride and fewer iterations keep
    /// it about as fast as [`DisPreset::Accurate`] on the 1600x200 strip.
    Fine,
    /// [`DisPreset::Fine`] with its patches every 4 px instead of 8: each
    /// pixel's flow is then the weighted mean of four overlapping patches
    /// rather than one patch's vector, so under a rod the motion profile
    /// depends less on which markers a patch happens to hold. On the
    /// simulated strip a pitched rod's located column scatters by about
    /// 2 px along a sweep instead of 3.4, and, calibrated with the
    /// characterization's sweeps, single presses are located and read
    /// closer, though not every two-contact sequence (without the sweeps,
    /// worse: docs/results.md), at about 3 times `Fine`'s time
    /// for the flow (1.7-2.3 times per frame). A calibration fitted with it
    /// must run with it: the flow's magnitudes differ (under a light press
    /// it is smoother and lower, so its detection thresholds differ too).
    /// With overlapping patches a texture never counts as sparse
    /// ([`DisParams::sparse_texture`]).
    Dense,
}

impl DisPreset {
    /// Parses `ultrafast`, `fast`, `medium`, `accurate`, `balanced`, `fine`,
    /// `dense` (case-insensitive).
    pub fn parse(name: &str) -> Result<Self> {
        match name.to_ascii_lowercase().as_str() {
            "ultrafast" => Ok(DisPreset::Ultrafast),
            "fast" => Ok(DisPreset::Fast),
            "medium" => Ok(DisPreset::Medium),
            "accurate" => Ok(DisPreset::Accurate),
            "balanced" => Ok(DisPreset::Balanced),
            "fine" => Ok(DisPreset::Fine),
            "dense" => Ok(DisPreset::Dense),
            _ => Err(Error::param(
                "preset",
                format!(
                    "unknown DIS preset `{name}` (ultrafast, fast, medium, accurate, balanced, fine, dense)"
                ),
            )),
        }
    }

    /// Lower-case name, as accepted by [`DisPreset::parse`].
    pub fn name(self) -> &'static str {
        match self {
            DisPreset::Ultrafast => "ultrafast",
            DisPreset::Fast => "fast",
            DisPreset::Medium => "medium",
            DisPreset::Accurate => "accurate",
            DisPreset::Balanced => "balanced",
            DisPreset::Fine => "fine",
            DisPreset::Dense => "dense",
        }
    }

    /// All presets.
    pub const ALL: [DisPreset; 7] = [
        DisPreset::Ultrafast,
        DisPreset::Fast,
        DisPreset::Medium,
        DisPreset::Accurate,
        DisPreset::Balanced,
        DisPreset::Fine,
        DisPreset::Dense,
    ];
}

/// Every DIS parameter. Start from [`DisParams::preset`] and change fields.
#[derive(Debug, Clone, PartialEq)]
pub struct DisParams {
    /// Finest pyramid scale the patches are searched at (0 = full
    /// resolution); the flow is upsampled from there by `2^finest_scale`.
    pub finest_scale: usize,
    /// Coarsest scale; `None` picks OpenCV's
    /// `min(round(log2(max(W,H) / (4 patch))), floor(log2(min(W,H) / patch)))`.
    pub coarsest_scale: Option<usize>,
    /// Patch side in pixels (2..=[`MAX_PATCH_SIZE`]).
    pub patch_size: usize,
    /// Distance between patch corners (1..=patch_size).
    pub patch_stride: usize,
    /// Gradient-descent iterations per patch, split over the two passes.
    pub gradient_descent_iterations: usize,
    /// Subtract the patch mean of the residual (robust to brightness change).
    pub mean_normalization: bool,
    /// Let each patch try its already-visited neighbours' vectors first.
    pub spatial_propagation: bool,
    /// Scale the Sobel gradients to the true derivative (divide by 8), making
    /// each descent step a full Gauss-Newton step. `false` reproduces OpenCV,
    /// whose un-normalized Sobel gives steps of about 1/8 of that.
    pub normalized_gradients: bool,
    /// Gaussian prefilter (standard deviation in level pixels, 0 = off)
    /// applied to both images at every level before the search. Markers of
    /// ~1 px sigma are sub-pixel dots after the area averaging; a light blur
    /// makes the Sobel gradient match the bilinear cost surface, which
    /// removes the sub-pixel bias of un-filtered DIS.
    pub prefilter_sigma: f32,
    /// Apply the prefilter at every level, not only the finest (the coarser
    /// levels are area averages, already smooth).
    pub prefilter_all_levels: bool,
    /// On a cost increase, halve the step back towards the last better
    /// vector and retry (within the iteration budget) instead of stopping.
    /// `false` stops there, as OpenCV does.
    pub backtracking: bool,
    /// Variational refinement run on every level's dense flow
    /// (`outer_iterations == 0` turns it off).
    pub refinement: RefineParams,
    /// Also try the zero vector as a candidate before the first descent.
    /// On marker images the coarse levels are aliased noise and can hand a
    /// patch a wrong vector; zero motion, the most common state of a
    /// tactile sensor's skin, is then a better start. Costs one evaluation
    /// per patch and level.
    pub zero_candidate: bool,
    /// Fixed number of stripes of patch rows that propagation does not cross
    /// (the unit of parallel work; results do not depend on thread count).
    pub stripes: usize,
    /// Texture a patch needs to be searched: the smallest eigenvalue of its
    /// mean-normalized structure tensor per pixel, in (grey levels per pixel)^2
    /// of the true derivative. A patch below it (the black coating beyond the
    /// skin, a saturated spot) holds only sensor noise: a full Gauss-Newton
    /// step would fit that noise into a large bogus vector, so the patch keeps
    /// the vector the coarser level and propagation give it. 0 = off, as in
    /// OpenCV.
    pub min_texture: f32,
    /// Patches below `min_texture` (and edge-only patches) take no part in
    /// the search and no candidate competes for them: after the search each
    /// takes the mean vector of the searched patches nearest to it (those
    /// within the smallest square of 3, 5, 9, 17, ... patches around it that
    /// holds any), or keeps the coarser level's vector when no patch of the
    /// level is searched. Without it such a patch picks among its start, the
    /// zero vector and its neighbours' vectors by a cost that is pure noise,
    /// and on a bright gel with sparse dots many pick zero (at full
    /// resolution, on a stride equal to the patch, whole blocks of the flow
    /// are then exactly zero). `false` (every preset) keeps them in the
    /// search, as OpenCV does: on the simulator's strip the fill did not
    /// keep the calibrated forces' accuracy.
    pub fill_untextured: bool,
    /// Largest fraction of the finest level's patches that may be untextured
    /// (below `min_texture`) in the reference for the texture to count as
    /// dense, in [0, 1]; above it the texture is sparse (1 = never sparse).
    /// On a sparse texture, such as a regular grid of dark dots on a plain,
    /// lit gel, most patches hold only noise: left to pick among their
    /// start, the zero vector and their neighbours' vectors by a cost that
    /// is noise, many pick zero and leave whole blocks of the flow at
    /// exactly zero. On a sparse texture the search therefore (1) lets no
    /// candidate compete for untextured patches: on the coarser levels they
    /// keep the vector the level above gives them, and on the finest level
    /// they take the mean vector of the nearest textured patches (as
    /// `fill_untextured` does), the dots' edges that move with the gel
    /// around them, (2) places the coarser levels' patches at half
    /// the stride, so that their dense flow, which starts the finer level,
    /// averages overlapping patches and has no holes either, and (3) tries
    /// no zero vector at the finest level. On a dense texture (the
    /// simulator's random markers: 3-4% of `fine`'s patches untextured) the
    /// search is unchanged: there the zero vector and the competition clean
    /// the flow where the skin is still, which the calibrated forces rely on
    /// (with (1)-(3) the strip's calibration lost about half its accuracy).
    /// Decided once per reference ([`Dis::sparse_texture`]).
    pub sparse_texture: f32,
    /// Stop a patch's descent once a step moves it by less than this many
    /// level pixels (the step is still applied). 0 = off: every iteration
    /// runs until the cost stops falling, as in OpenCV.
    pub early_stop: f32,
    /// Run the variational refinement only on the `n` finest levels
    /// (`None` = every level, as in OpenCV). The coarse levels' flow is
    /// only a start for the finer patch search, which re-estimates it.
    pub refine_levels: Option<usize>,
    /// When a patch's cost stops falling, still apply the step computed at
    /// that last (worse) vector before stopping, as OpenCV does, instead of
    /// returning to the best vector evaluated. Just past the minimum, the
    /// Gauss-Newton step from there points back towards it, so the final
    /// vector lands nearer the minimum than either evaluated point; with
    /// OpenCV's un-normalized (1/8) steps that is worth 0.005-0.015 px AEPE
    /// on marker pairs (`Fast`; the other presets keep returning to the best
    /// vector, as tuned). Ignored when `backtracking` handles the stop.
    pub step_on_stop: bool,
    /// Least number of patch rows per propagation stripe (1 = `stripes`
    /// alone decides, as in OpenCV). The coarse levels have only a few patch
    /// rows: cut into `stripes` stripes they get no vertical propagation at
    /// all, and a wrong vector of an aliased coarse level is never replaced
    /// by its neighbour's. Still a fixed function of the level size, so
    /// results do not depend on the thread count.
    pub min_stripe_rows: usize,
    /// The coarsest level keeps at least this many patch sides along the
    /// image's shorter side (1 = OpenCV's rule, one patch). At 1920x1080 with
    /// 8-px patches OpenCV's rule picks scale 6, a 30x16 image in which
    /// 1-px markers are aliased noise: a patch search there can lock onto a
    /// wrong vector that every finer level doubles (16.7 px of motion gave
    /// an AEPE of 77 px). 3 patch sides stop at scale 5 (60x33), which still
    /// starts the search within a pixel for motions of ~30 px.
    pub coarsest_min_patches: usize,
}

impl DisParams {
    /// The parameters of a preset.
    pub fn preset(preset: DisPreset) -> Self {
        let base = DisParams {
            finest_scale: 2,
            coarsest_scale: None,
            patch_size: 8,
            patch_stride: 4,
            gradient_descent_iterations: 16,
            mean_normalization: true,
            spatial_propagation: true,
            normalized_gradients: false,
            prefilter_sigma: 0.0,
            prefilter_all_levels: false,
            backtracking: false,
            refinement: RefineParams::opencv(),
            zero_candidate: false,
            stripes: 8,
            min_texture: 0.0,
            fill_untextured: false,
            sparse_texture: 1.0,
            early_stop: 0.0,
            refine_levels: None,
            step_on_stop: false,
            min_stripe_rows: 1,
            coarsest_min_patches: 1,
        };
        match preset {
            DisPreset::Ultrafast => DisParams {
                gradient_descent_iterations: 12,
                refinement: RefineParams {
                    outer_iterations: 0,
                    ..RefineParams::opencv()
                },
                ..base
            },
            // OpenCV's values, except that only the finest level is refined
            // (see `refine_levels`).
            DisPreset::Fast => DisParams {
                refine_levels: Some(1),
                step_on_stop: true,
                min_stripe_rows: 3,
                coarsest_min_patches: 3,
                ..base
            },
            DisPreset::Medium => DisParams {
                finest_scale: 1,
                patch_stride: 3,
                gradient_descent_iterations: 25,
                ..base
            },
            DisPreset::Balanced => DisParams {
                finest_scale: 1,
                patch_stride: 4,
                gradient_descent_iterations: 8,
                normalized_gradients: true,
                prefilter_sigma: 2.0,
                refinement: RefineParams {
                    outer_iterations: 0,
                    ..RefineParams::opencv()
                },
                zero_candidate: true,
                min_texture: 0.1,
                ..base
            },
            DisPreset::Accurate => DisParams {
                prefilter_sigma: 1.5,
                refine_levels: None,
                refinement: RefineParams {
                    outer_iterations: 1,
                    ..RefineParams::opencv()
                },
                ..DisParams::preset(DisPreset::Balanced)
            },
            DisPreset::Fine => DisParams {
                finest_scale: 0,
                patch_stride: 8,
                gradient_descent_iterations: 4,
                prefilter_sigma: 1.5,
                min_texture: 1.0,
                sparse_texture: 0.25,
                ..DisParams::preset(DisPreset::Balanced)
            },
            DisPreset::Dense => DisParams {
                patch_stride: 4,
                sparse_texture: 1.0,
                ..DisParams::preset(DisPreset::Fine)
            },
        }
    }

    /// Whether a reference with this fraction of untextured finest-level
    /// patches counts as a sparse texture (see `sparse_texture`).
    fn is_sparse(&self, untextured: f64) -> bool {
        untextured > self.sparse_texture as f64
    }

    /// The same parameters with OpenCV's iteration semantics: no early stop
    /// of the descent, the refinement on every level, OpenCV's stripes and
    /// coarsest level, and its step at the stop. `Fast` and `Ultrafast` are
    /// then exactly OpenCV 5's presets.
    pub fn opencv_semantics(self) -> Self {
        DisParams {
            early_stop: 0.0,
            refine_levels: None,
            step_on_stop: true,
            min_stripe_rows: 1,
            coarsest_min_patches: 1,
            ..self
        }
    }

    /// Checks every field; [`Error::InvalidParameter`] names the bad one.
    /// Counts have upper bounds ([`MAX_PATCH_SIZE`], [`MAX_DESCENT_ITERATIONS`],
    /// [`MAX_SCALE`], [`MAX_STRIPES`], and the refinement's
    /// [`super::refine::MAX_ITERATIONS`]).
    pub fn validate(&self) -> Result<()> {
        if !(2..=MAX_PATCH_SIZE).contains(&self.patch_size) {
            return Err(Error::param(
                "patch_size",
                format!("{} is outside 2..={MAX_PATCH_SIZE}", self.patch_size),
            ));
        }
        if self.patch_stride == 0 || self.patch_stride > self.patch_size {
            return Err(Error::param(
                "patch_stride",
                format!(
                    "{} must be in 1..=patch_size ({}) so patches cover the image",
                    self.patch_stride, self.patch_size
                ),
            ));
        }
        if self.finest_scale > 12 {
            return Err(Error::param(
                "finest_scale",
                format!("{} is larger than 12", self.finest_scale),
            ));
        }
        if self.gradient_descent_iterations > MAX_DESCENT_ITERATIONS {
            return Err(Error::param(
                "gradient_descent_iterations",
                format!(
                    "{} is larger than {MAX_DESCENT_ITERATIONS}",
                    self.gradient_descent_iterations
                ),
            ));
        }
        if let Some(c) = self.coarsest_scale
            && c > MAX_SCALE
        {
            return Err(Error::param(
                "coarsest_scale",
                format!("{c} is larger than {MAX_SCALE}"),
            ));
        }
        if let Some(c) = self.coarsest_scale
            && c < self.finest_scale
        {
            return Err(Error::param(
                "coarsest_scale",
                format!("{c} is finer than finest_scale {}", self.finest_scale),
            ));
        }
        if !(self.prefilter_sigma.is_finite() && (0.0..=8.0).contains(&self.prefilter_sigma)) {
            return Err(Error::param(
                "prefilter_sigma",
                format!("{} is outside 0..=8 px", self.prefilter_sigma),
            ));
        }
        for (name, n) in [
            ("stripes", self.stripes),
            ("min_stripe_rows", self.min_stripe_rows),
        ] {
            if !(1..=MAX_STRIPES).contains(&n) {
                return Err(Error::param(
                    name,
                    format!("{n} is outside 1..={MAX_STRIPES}"),
                ));
            }
        }
        if !(1..=64).contains(&self.coarsest_min_patches) {
            return Err(Error::param(
                "coarsest_min_patches",
                format!("{} is outside 1..=64", self.coarsest_min_patches),
            ));
        }
        if !(self.min_texture.is_finite() && self.min_texture >= 0.0) {
            return Err(Error::param(
                "min_texture",
                format!("must be finite and >= 0, got {}", self.min_texture),
            ));
        }
        if !(0.0..=1.0).contains(&self.sparse_texture) {
            return Err(Error::param(
                "sparse_texture",
                format!("{} is outside 0..=1", self.sparse_texture),
            ));
        }
        if !(self.early_stop.is_finite() && (0.0..=1.0).contains(&self.early_stop)) {
            return Err(Error::param(
                "early_stop",
                format!("{} is outside 0..=1 px", self.early_stop),
            ));
        }
        self.refinement.validate()?;
        Ok(())
    }
}

impl Default for DisParams {
    /// [`DisPreset::Accurate`], the lowest endpoint error (the tactile
    /// sensor uses [`DisPreset::Fine`]: `ExtractorConfig::default`).
    fn default() -> Self {
        DisParams::preset(DisPreset::Accurate)
    }
}

/// Reference-only data of one patch: the inverse of its (mean-normalized)
/// structure tensor and its gradient sums.
#[derive(Debug, Clone, Copy, Default)]
struct PatchRef {
    ih11: f32,
    ih12: f32,
    ih22: f32,
    sgx: f32,
    sgy: f32,
    /// Whether the patch has a well-defined 2-D step (texture above the
    /// gate); the inverse tensor is zero otherwise.
    textured: bool,
}

/// One pyramid level: reference data (fixed) and per-frame buffers.
#[derive(Debug)]
struct Level {
    w: usize,
    h: usize,
    /// Reference image and its gradients (the gradient planes are left
    /// empty for 8x8 patches, whose search reads `pdata`).
    i0: Vec<f32>,
    gx: Vec<f32>,
    gy: Vec<f32>,
    /// Each 8x8 patch's reference block, in patch order (empty for other
    /// patch sizes).
    pdata: Vec<Patch8>,
    /// Current image at this level (per frame).
    i1: Vec<f32>,
    /// Scratch for the prefilter.
    tmp: Vec<f32>,
    /// Patch grid: corner of patch column `j` / row `i`.
    px: Vec<u32>,
    py: Vec<u32>,
    /// Patch rows covering pixel row `y`: `ilo[y]..=ihi[y]`.
    ilo: Vec<u32>,
    ihi: Vec<u32>,
    /// Per patch column, whether no other patch column covers any of its
    /// pixels (see [`solo_columns`]), and the pixel spans (start, end) the
    /// other columns cover, merged.
    solo: Vec<bool>,
    shared: Vec<(u32, u32)>,
    patches: Vec<PatchRef>,
    /// Patch flow vectors (per frame).
    sx: Vec<f32>,
    sy: Vec<f32>,
    /// Per patch, the evaluation of its vector as the forward pass left it,
    /// when that pass evaluated it (per frame; see [`Known`]).
    known: Vec<Known>,
    /// Dense flow at this level, in this level's pixels.
    flow: FlowField,
    /// Variational refinement with this level's reference cached.
    refiner: VariationalRefiner,
}

impl Level {
    fn ws(&self) -> usize {
        self.px.len()
    }
    fn hs(&self) -> usize {
        self.py.len()
    }
}

/// Corners of patches of side `p` every `s` pixels along an axis of `n`
/// pixels, the last one moved flush with the edge so every pixel is covered.
fn patch_corners(n: usize, p: usize, s: usize) -> Vec<u32> {
    let count = (n - p).div_ceil(s) + 1;
    (0..count).map(|k| (k * s).min(n - p) as u32).collect()
}

/// For each pixel along an axis, the first and last patch covering it.
fn coverage(n: usize, p: usize, corners: &[u32]) -> (Vec<u32>, Vec<u32>) {
    let mut lo = vec![0u32; n];
    let mut hi = vec![0u32; n];
    for x in 0..n {
        let first = corners
            .iter()
            .position(|&c| c as usize + p > x)
            .expect("patches cover the axis");
        let last = corners
            .iter()
            .rposition(|&c| c as usize <= x)
            .expect("patches cover the axis");
        lo[x] = first as u32;
        hi[x] = last as u32;
    }
    (lo, hi)
}

/// Which patch columns of corners `px` (patches of side `p`) are alone on
/// their pixels (no other column's patch covers any of them), and the
/// spans `(start, end)` of the pixels the other columns cover, merged and
/// in order. With a stride equal to the patch (`fine`) every column is
/// alone but the last ones when the width is not a multiple of the patch.
fn solo_columns(px: &[u32], p: usize) -> (Vec<bool>, Vec<(u32, u32)>) {
    let n = px.len();
    let solo: Vec<bool> = (0..n)
        .map(|j| {
            let (x0, x1) = (px[j] as usize, px[j] as usize + p);
            (0..n).all(|k| k == j || px[k] as usize >= x1 || px[k] as usize + p <= x0)
        })
        .collect();
    let mut shared: Vec<(u32, u32)> = Vec::new();
    for j in (0..n).filter(|&j| !solo[j]) {
        let (a, b) = (px[j], px[j] + p as u32);
        match shared.last_mut() {
            Some(last) if a <= last.1 => last.1 = last.1.max(b),
            _ => shared.push((a, b)),
        }
    }
    (solo, shared)
}

/// Dense Inverse Search optical flow against a fixed reference frame.
///
/// ```
/// use ndarray::Array2;
/// use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
///
/// // A smooth texture and the same texture moved by (+1.5, -0.5) px.
/// let tex = |x: f32, y: f32| 128.0 + 60.0 * (0.31 * x).sin() * (0.23 * y).cos()
///     + 40.0 * (0.17 * x + 0.11 * y).sin();
/// let (w, h) = (128, 96);
/// let reference = Array2::from_shape_fn((h, w), |(y, x)| tex(x as f32, y as f32));
/// let current = Array2::from_shape_fn((h, w), |(y, x)| tex(x as f32 - 1.5, y as f32 + 0.5));
///
/// let mut dis = Dis::new(DisParams::preset(DisPreset::Accurate))?;
/// dis.set_reference(&reference)?;
/// let flow = dis.compute(&current)?;
/// assert!((flow.u[[48, 64]] - 1.5).abs() < 0.1);
/// assert!((flow.v[[48, 64]] + 0.5).abs() < 0.1);
/// # Ok::<(), optical_tactile::Error>(())
/// ```
#[derive(Debug)]
pub struct Dis {
    params: DisParams,
    width: usize,
    height: usize,
    /// Levels from finest (`levels[0]`, scale `params.finest_scale`) to coarsest.
    levels: Vec<Level>,
    /// Taps from the finest level to full resolution.
    out_x: ResizeAxis,
    out_y: ResizeAxis,
    /// Scratch for the vertical pass of the final resize.
    out_tmp: Vec<f32>,
    /// Prefilter taps.
    kernel: Vec<f32>,
    /// Fraction of the finest level's patches that are untextured in the
    /// reference.
    untextured: f64,
}

impl Dis {
    /// A planner with the given parameters (checked here).
    pub fn new(params: DisParams) -> Result<Self> {
        params.validate()?;
        Ok(Dis {
            params,
            width: 0,
            height: 0,
            levels: Vec::new(),
            out_x: ResizeAxis::default(),
            out_y: ResizeAxis::default(),
            out_tmp: Vec::new(),
            kernel: Vec::new(),
            untextured: 0.0,
        })
    }

    /// A planner for a preset.
    pub fn with_preset(preset: DisPreset) -> Self {
        Dis::new(DisParams::preset(preset)).expect("presets are valid")
    }

    /// The parameters.
    pub fn params(&self) -> &DisParams {
        &self.params
    }

    /// `(width, height)` of the reference, `(0, 0)` before one is set.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Whether the reference's texture is sparse (see
    /// [`DisParams::sparse_texture`]); `false` before a reference is set.
    pub fn sparse_texture(&self) -> bool {
        self.params.is_sparse(self.untextured)
    }

    /// Fraction of the finest level's patches that are untextured (below
    /// [`DisParams::min_texture`]) in the reference; 0 before a reference
    /// is set or with `min_texture` 0.
    pub fn untextured_fraction(&self) -> f64 {
        self.untextured
    }

    /// Which pixels of the native flow (the finest level: `(width, height)`
    /// of [`native_flow`](Self::native_flow)) lie under at least one
    /// textured patch of the reference (texture at or above
    /// [`DisParams::min_texture`]), row-major into `out`; returns the
    /// level's `(width, height)`, `(0, 0)` before a reference is set. Where
    /// no textured patch reaches, the reference holds only sensor noise
    /// (the black coating beyond the skin, a saturated spot) and the flow
    /// there is not a measurement. With `min_texture` 0 only patches with
    /// no 2-D gradient structure at all fall out.
    pub fn textured_coverage_into(&self, out: &mut Vec<bool>) -> (usize, usize) {
        out.clear();
        let Some(lvl) = self.levels.first() else {
            return (0, 0);
        };
        out.resize(lvl.w * lvl.h, false);
        let psz = self.params.patch_size;
        let ws = lvl.ws();
        for (i, &y0) in lvl.py.iter().enumerate() {
            for (j, &x0) in lvl.px.iter().enumerate() {
                if !lvl.patches[i * ws + j].textured {
                    continue;
                }
                let (x0, y0) = (x0 as usize, y0 as usize);
                for row in out[y0 * lvl.w..(y0 + psz) * lvl.w].chunks_exact_mut(lvl.w) {
                    row[x0..x0 + psz].fill(true);
                }
            }
        }
        (lvl.w, lvl.h)
    }

    /// The coarsest scale OpenCV would choose for this image size.
    pub fn auto_coarsest_scale(width: usize, height: usize, patch_size: usize) -> usize {
        let maxd = width.max(height) as f64;
        let mind = width.min(height) as f64;
        let p = patch_size as f64;
        let a = ((maxd / (4.0 * p)).log2() + 0.5).floor();
        let b = (mind / p).log2().floor();
        a.min(b).max(0.0) as usize
    }

    /// Sets the reference frame and computes everything that depends on it
    /// alone. Errors on empty images, images too small for the patch size at
    /// the finest scale, and non-finite pixels.
    pub fn set_reference(&mut self, reference: &ArrayRef2<f32>) -> Result<()> {
        let (h, w) = reference.dim();
        let p = &self.params;
        let f = 1usize << p.finest_scale;
        let (min_w, min_h) = (p.patch_size * f, p.patch_size * f);
        if w < min_w || h < min_h {
            return Err(Error::TooSmall {
                what: format!(
                    "DIS reference (patch {} at scale {})",
                    p.patch_size, p.finest_scale
                ),
                width: w,
                height: h,
                min_w,
                min_h,
            });
        }
        check_finite(reference, "DIS reference")?;
        let coarsest = p
            .coarsest_scale
            .unwrap_or_else(|| Dis::auto_coarsest_scale(w, h, p.patch_size))
            .max(p.finest_scale);
        // Never go coarser than a level that still holds one patch
        // (`coarsest_min_patches` of them along each side); the finest level
        // is always kept.
        let min_side = p.patch_size * p.coarsest_min_patches;
        let mut scales = Vec::new();
        for s in p.finest_scale..=coarsest {
            let (lw, lh) = pyramid::level_size(w, h, s);
            let small = lw < p.patch_size || lh < p.patch_size;
            if small || (!scales.is_empty() && (lw < min_side || lh < min_side)) {
                break;
            }
            scales.push(s);
        }
        let full = contiguous(reference);
        let grad_scale = if p.normalized_gradients { 0.125 } else { 1.0 };
        let psz = p.patch_size;
        let stride = p.patch_stride;
        let mean_norm = p.mean_normalization;
        // The gate in the units of the stored gradients, summed over a patch.
        let min_eig = p.min_texture as f64 * (psz * psz) as f64 * (8.0 * grad_scale as f64).powi(2);
        let mut levels: Vec<Level> = Vec::with_capacity(scales.len());
        let mut levels_raw: Vec<Vec<f32>> = Vec::with_capacity(scales.len());
        let kernel = pyramid::gaussian_kernel(p.prefilter_sigma);
        let mut untextured = 0.0;
        for (k, &s) in scales.iter().enumerate() {
            let (lw, lh) = pyramid::level_size(w, h, s);
            let mut i0 = vec![0.0f32; lw * lh];
            if k == 0 {
                pyramid::downsample_area(&full, w, h, 1 << s, &mut i0)?;
            } else {
                // Coarser levels average the un-filtered finer level.
                let prev = &levels[k - 1];
                pyramid::downsample_area(&levels_raw[k - 1], prev.w, prev.h, 2, &mut i0)?;
            }
            levels_raw.push(i0.clone());
            if k == 0 || p.prefilter_all_levels {
                pyramid::gaussian_blur(&mut i0, lw, lh, &kernel, &mut vec![0.0; lw * lh])?;
            }
            let mut gx = vec![0.0f32; lw * lh];
            let mut gy = vec![0.0f32; lw * lh];
            pyramid::sobel(&i0, lw, lh, grad_scale, &mut gx, &mut gy)?;
            // Sparse texture (decided on the finest level, built first):
            // overlapping patches on the coarser levels.
            let sparse = p.is_sparse(untextured);
            let stride = if k > 0 && sparse {
                (stride / 2).max(1)
            } else {
                stride
            };
            let px = patch_corners(lw, psz, stride);
            let py = patch_corners(lh, psz, stride);
            let (ilo, ihi) = coverage(lh, psz, &py);
            let (solo, shared) = solo_columns(&px, psz);
            let ws = px.len();
            let patches: Vec<PatchRef> = (0..py.len() * ws)
                .into_par_iter()
                .map(|idx| {
                    let (x0, y0) = (px[idx % ws] as usize, py[idx / ws] as usize);
                    patch_ref(&gx, &gy, lw, x0, y0, psz, mean_norm, min_eig)
                })
                .collect();
            let n = patches.len();
            // 8x8 patches: each patch's reference block stored contiguously,
            // in search order, once per reference.
            let pdata: Vec<Patch8> = if psz == 8 {
                (0..n)
                    .into_par_iter()
                    .map(|idx| {
                        let (x0, y0) = (px[idx % ws] as usize, py[idx / ws] as usize);
                        Patch8::from_planes([&i0, &gx, &gy], lw, x0, y0)
                    })
                    .collect()
            } else {
                Vec::new()
            };
            let (gx, gy) = if psz == 8 {
                (Vec::new(), Vec::new())
            } else {
                (gx, gy)
            };
            if k == 0 {
                untextured = patches.iter().filter(|q| !q.textured).count() as f64 / n as f64;
            }
            let mut refiner = VariationalRefiner::new(p.refinement);
            if p.refinement.outer_iterations > 0 && p.refine_levels.is_none_or(|n| k < n) {
                let view = ArrayView2::from_shape((lh, lw), &i0[..]).expect("level shape");
                refiner.set_reference(view)?;
            }
            levels.push(Level {
                w: lw,
                h: lh,
                i0,
                gx,
                gy,
                pdata,
                i1: vec![0.0; lw * lh],
                tmp: vec![0.0; lw * lh],
                px,
                py,
                ilo,
                ihi,
                solo,
                shared,
                patches,
                sx: vec![0.0; n],
                sy: vec![0.0; n],
                known: vec![Known::NONE; n],
                flow: FlowField::zeros(lw, lh),
                refiner,
            });
        }
        let (fw, fh) = (levels[0].w, levels[0].h);
        self.out_x = ResizeAxis::new(fw, w);
        self.out_y = ResizeAxis::new(fh, h);
        self.out_tmp = vec![0.0; fw * h];
        self.kernel = kernel;
        self.untextured = untextured;
        self.levels = levels;
        self.width = w;
        self.height = h;
        Ok(())
    }

    /// The flow from the reference to `current`, at full resolution.
    pub fn compute(&mut self, current: &ArrayRef2<f32>) -> Result<FlowField> {
        let mut out = FlowField::zeros(self.width, self.height);
        self.compute_into(current, &mut out)?;
        Ok(out)
    }

    /// Like [`Dis::compute`] into a caller-owned flow (resized if its size is
    /// wrong; in steady state nothing is allocated).
    pub fn compute_into(&mut self, current: &ArrayRef2<f32>, out: &mut FlowField) -> Result<()> {
        self.compute_native(current)?;
        if out.size() != (self.width, self.height) {
            *out = FlowField::zeros(self.width, self.height);
        }
        let lvl = &self.levels[0];
        let gain = (1usize << self.params.finest_scale) as f32;
        let (ou, ov) = (
            out.u.as_slice_mut().expect("standard layout"),
            out.v.as_slice_mut().expect("standard layout"),
        );
        let (fu, fv) = (
            lvl.flow.u.as_slice().expect("standard layout"),
            lvl.flow.v.as_slice().expect("standard layout"),
        );
        if (lvl.w, lvl.h) == (self.width, self.height) {
            // The finest level is full resolution (scale 0): the resize's
            // taps would all be whole pixels with weight 0 and gain 1, so
            // the flow is the level's own (up to the sign of a zero).
            ou.copy_from_slice(fu);
            ov.copy_from_slice(fv);
            return Ok(());
        }
        let tmp = &mut self.out_tmp;
        pyramid::resize_bilinear(fu, lvl.w, &self.out_x, &self.out_y, gain, tmp, ou)?;
        pyramid::resize_bilinear(fv, lvl.w, &self.out_x, &self.out_y, gain, tmp, ov)?;
        Ok(())
    }

    /// Computes the flow only at its native (finest computed) level; read it
    /// with [`Dis::native_flow`]. Cheaper than [`Dis::compute_into`] by the
    /// final upsampling.
    pub fn compute_native(&mut self, current: &ArrayRef2<f32>) -> Result<()> {
        if self.levels.is_empty() {
            return Err(Error::NoReference);
        }
        let (h, w) = current.dim();
        if (w, h) != (self.width, self.height) {
            return Err(Error::shape(
                "DIS current frame against the reference",
                (self.width, self.height),
                (w, h),
            ));
        }
        self.build_current_pyramid(current)?;
        let nl = self.levels.len();
        let sparse = self.sparse_texture();
        for k in (0..nl).rev() {
            let (finer, coarser) = self.levels.split_at_mut(k + 1);
            let lvl = &mut finer[k];
            init_patches(lvl, coarser.first(), self.params.patch_size);
            let search = Search {
                keep_untextured: self.params.fill_untextured || sparse,
                zero_candidate: self.params.zero_candidate && !(sparse && k == 0),
            };
            search_level(lvl, &self.params, search);
            // On a sparse texture the finest level's untextured patches take
            // their textured neighbours' motion, not the coarse levels' guess.
            if self.params.fill_untextured || (sparse && k == 0) {
                fill_untextured(lvl);
            }
            densify(lvl, self.params.patch_size);
            let refined = self.params.refine_levels.is_none_or(|n| k < n);
            if self.params.refinement.outer_iterations > 0 && refined {
                let i1 = ArrayView2::from_shape((lvl.h, lvl.w), &lvl.i1[..]).expect("level shape");
                lvl.refiner.refine(i1, &mut lvl.flow.u, &mut lvl.flow.v)?;
            }
        }
        Ok(())
    }

    /// The flow at its native level (the finest computed scale) from the last
    /// compute, in that level's pixels, and the level's scale `2^finest_scale`
    /// (full-resolution pixels per level pixel). `None` before any compute.
    pub fn native_flow(&self) -> Option<(&FlowField, usize)> {
        self.levels
            .first()
            .map(|l| (&l.flow, 1usize << self.params.finest_scale))
    }

    fn build_current_pyramid(&mut self, current: &ArrayRef2<f32>) -> Result<()> {
        let (w, h) = (self.width, self.height);
        let f = 1usize << self.params.finest_scale;
        let full = contiguous(current);
        // At full resolution the finest level's un-filtered image is the
        // frame itself: the prefilter reads it directly (no copy), and the
        // next level averages it.
        let direct = f == 1 && !self.kernel.is_empty();
        {
            let lvl = &mut self.levels[0];
            if direct {
                pyramid::gaussian_blur_into(&full, w, h, &self.kernel, &mut lvl.tmp, &mut lvl.i1)?;
            } else {
                pyramid::downsample_area(&full, w, h, f, &mut lvl.i1)?;
            }
            // The box sums (and the blur's, whose centre tap is positive)
            // carry any NaN/inf of the pixels they cover; the margins a box
            // does not cover are checked directly.
            let bad =
                !pyramid::all_finite(&lvl.i1) || margins_nonfinite(current, lvl.w * f, lvl.h * f);
            if bad {
                check_finite(current, "DIS current frame")?;
            }
        }
        for k in 1..self.levels.len() {
            let (a, b) = self.levels.split_at_mut(k);
            let prev = &a[k - 1];
            let src: &[f32] = if k == 1 && direct { &full } else { &prev.i1 };
            pyramid::downsample_area(src, prev.w, prev.h, 2, &mut b[0].i1)?;
        }
        // Filter after the whole pyramid is built: coarser levels average the
        // un-filtered finer ones, exactly as for the reference.
        if !self.kernel.is_empty() {
            let n = if self.params.prefilter_all_levels {
                self.levels.len()
            } else {
                1
            };
            let first = usize::from(direct);
            for lvl in &mut self.levels[first..n.max(first)] {
                pyramid::gaussian_blur(&mut lvl.i1, lvl.w, lvl.h, &self.kernel, &mut lvl.tmp)?;
            }
        }
        Ok(())
    }
}

/// A contiguous copy-or-borrow of an image as a row-major slice.
fn contiguous(img: &ArrayRef2<f32>) -> std::borrow::Cow<'_, [f32]> {
    match img.as_slice() {
        Some(s) => std::borrow::Cow::Borrowed(s),
        None => std::borrow::Cow::Owned(img.iter().copied().collect()),
    }
}

fn check_finite(img: &ArrayRef2<f32>, what: &str) -> Result<()> {
    let (h, w) = img.dim();
    if w == 0 || h == 0 {
        return Err(Error::TooSmall {
            what: what.to_string(),
            width: w,
            height: h,
            min_w: 1,
            min_h: 1,
        });
    }
    if let Some(((row, col), _)) = img.indexed_iter().find(|(_, v)| !v.is_finite()) {
        return Err(Error::NonFinite {
            what: what.to_string(),
            row,
            col,
        });
    }
    Ok(())
}

/// Whether pixels outside the `cw x ch` top-left block are non-finite.
fn margins_nonfinite(img: &ArrayRef2<f32>, cw: usize, ch: usize) -> bool {
    let (h, w) = img.dim();
    (0..h).any(|y| {
        let xs = if y < ch { cw } else { 0 };
        (xs..w).any(|x| !img[[y, x]].is_finite())
    })
}

fn patch_ref(
    gx: &[f32],
    gy: &[f32],
    w: usize,
    x0: usize,
    y0: usize,
    psz: usize,
    mean_norm: bool,
    min_eig: f64,
) -> PatchRef {
    // Accumulate in f64: sums of 64 squared Sobel values lose digits in f32
    // after the mean is subtracted.
    let (mut xx, mut yy, mut xy, mut sx, mut sy) = (0f64, 0f64, 0f64, 0f64, 0f64);
    for r in 0..psz {
        let o = (y0 + r) * w + x0;
        for c in 0..psz {
            let (a, b) = (gx[o + c] as f64, gy[o + c] as f64);
            xx += a * a;
            yy += b * b;
            xy += a * b;
            sx += a;
            sy += b;
        }
    }
    if mean_norm {
        let n = (psz * psz) as f64;
        xx -= sx * sx / n;
        yy -= sy * sy / n;
        xy -= sx * sy / n;
    }
    let det = xx * yy - xy * xy;
    let tr = xx + yy;
    let smallest = 0.5 * (tr - ((xx - yy) * (xx - yy) + 4.0 * xy * xy).sqrt());
    // A textureless or edge-only patch has no well-defined 2-D step: leave it
    // where propagation and the coarser level put it.
    let textured = tr > 0.0 && det > 1e-6 * tr * tr && smallest >= min_eig;
    let (ih11, ih12, ih22) = if textured {
        (yy / det, -xy / det, xx / det)
    } else {
        (0.0, 0.0, 0.0)
    };
    PatchRef {
        ih11: ih11 as f32,
        ih12: ih12 as f32,
        ih22: ih22 as f32,
        sgx: sx as f32,
        sgy: sy as f32,
        textured,
    }
}

/// Initial patch vectors: the coarser level's dense flow (times 2) at each
/// patch centre, or zero at the coarsest level.
fn init_patches(lvl: &mut Level, coarser: Option<&Level>, psz: usize) {
    let ws = lvl.ws();
    match coarser {
        None => {
            lvl.sx.fill(0.0);
            lvl.sy.fill(0.0);
        }
        Some(c) => {
            let (cu, cv) = (
                c.flow.u.as_slice().expect("standard layout"),
                c.flow.v.as_slice().expect("standard layout"),
            );
            let rx = c.w as f32 / lvl.w as f32;
            let ry = c.h as f32 / lvl.h as f32;
            let (px, py) = (&lvl.px, &lvl.py);
            lvl.sx
                .par_chunks_mut(ws)
                .zip(lvl.sy.par_chunks_mut(ws))
                .enumerate()
                .for_each(|(i, (sxr, syr))| {
                    let cy = (py[i] as usize + psz / 2) as f32;
                    let y = (cy + 0.5) * ry - 0.5;
                    for j in 0..ws {
                        let cx = (px[j] as usize + psz / 2) as f32;
                        let x = (cx + 0.5) * rx - 0.5;
                        sxr[j] = 2.0 * pyramid::sample_clamped(cu, c.w, c.h, x, y);
                        syr[j] = 2.0 * pyramid::sample_clamped(cv, c.w, c.h, x, y);
                    }
                });
        }
    }
}

/// Cost and gradient of one patch at one displacement.
#[derive(Debug, Clone, Copy, Default)]
struct Eval {
    ssd: f32,
    bx: f32,
    by: f32,
}

/// The evaluation of one patch at `(u, v)` in the current frame, kept from
/// the forward pass for the backward pass, which starts from the vector the
/// forward pass left: an evaluation depends on the vector, the patch and the
/// two images alone, so the backward pass reuses it instead of computing the
/// same sums again. `NONE` (NaN, equal to no vector) when the forward pass
/// left an unevaluated vector (a last descent step).
#[derive(Debug, Clone, Copy)]
struct Known {
    u: f32,
    v: f32,
    e: Eval,
}

impl Known {
    const NONE: Known = Known {
        u: f32::NAN,
        v: f32::NAN,
        e: Eval {
            ssd: f32::NAN,
            bx: f32::NAN,
            by: f32::NAN,
        },
    };

    /// The kept evaluation, if it is the one at `(u, v)`. Zeros of either
    /// sign evaluate alike (`x0 + 0.0 == x0 + -0.0`), and a NaN vector is
    /// never known.
    fn at(&self, u: f32, v: f32) -> Option<Eval> {
        (self.u == u && self.v == v).then_some(self.e)
    }
}

/// The candidate vectors of one patch and their evaluations (see
/// [`search_level`]): at most four, each once (vectors equal as floats
/// evaluate alike).
#[derive(Default)]
struct Cands {
    uv: [(f32, f32); 4],
    e: [Eval; 4],
    /// How many of `uv` have their evaluation in `e`.
    done: usize,
    /// How many vectors are listed.
    n: usize,
}

impl Cands {
    fn find(&self, (u, v): (f32, f32)) -> Option<usize> {
        self.uv[..self.n]
            .iter()
            .position(|&(a, b)| a == u && b == v)
    }

    /// Lists `c` with its evaluation `e` (before any [`Cands::want`]).
    fn push_known(&mut self, c: (f32, f32), e: Eval) {
        debug_assert_eq!(self.done, self.n);
        self.uv[self.n] = c;
        self.e[self.n] = e;
        self.n += 1;
        self.done = self.n;
    }

    /// Lists `c` to be evaluated unless it is listed already (or no room
    /// is left: `get` then finds no evaluation for it).
    fn want(&mut self, c: (f32, f32)) {
        if self.n < 4 && self.find(c).is_none() {
            self.uv[self.n] = c;
            self.n += 1;
        }
    }

    /// Evaluates every listed vector without an evaluation.
    fn evaluate(&mut self, view: &LevelView, x0: usize, y0: usize, pr: &PatchRef, pd: &Patch8) {
        let (d, n) = (self.done, self.n);
        view.eval_many(x0, y0, pr, pd, &self.uv[d..n], &mut self.e[d..n]);
        self.done = n;
    }

    /// The evaluation of `c`, if listed and evaluated.
    fn get(&self, c: (f32, f32)) -> Option<Eval> {
        self.find(c).filter(|&q| q < self.done).map(|q| self.e[q])
    }
}

/// Read-only data one patch evaluation needs.
struct LevelView<'a> {
    w: usize,
    h: usize,
    i0: &'a [f32],
    gx: &'a [f32],
    gy: &'a [f32],
    i1: &'a [f32],
    psz: usize,
    mean_norm: bool,
    /// `(w - psz, h - psz)` as f32: the largest window corner (exclusive)
    /// that keeps a `(psz+1)^2` window inside (no usize -> f32 conversions
    /// per evaluation).
    lim: [f32; 2],
    /// `psz * psz` as f32 (the mean's divisor).
    n_px: f32,
}

impl LevelView<'_> {
    /// Mean-normalized SSD between the current image bilinearly sampled at
    /// the patch moved by `(u, v)` and the reference patch, and the
    /// residual-weighted gradient sums `b`. `pd` holds the patch's reference
    /// data contiguously when the patch is 8x8 (see [`Patch8`]).
    #[inline]
    fn eval(&self, x0: usize, y0: usize, pr: &PatchRef, pd: &Patch8, u: f32, v: f32) -> Eval {
        let psz = self.psz;
        let fxp = x0 as f32 + u;
        let fyp = y0 as f32 + v;
        let (ixf, ix) = floor_both(fxp);
        let (iyf, iy) = floor_both(fyp);
        let (ax, ay) = (fxp - ixf, fyp - iyf);
        // Sample window (psz+1)^2 starting at (ix, iy): read in place when
        // inside, else copied with border replication (the rare slow path).
        // `ixf < w - psz` is `ixf + psz < w` exactly: `ixf` is a whole
        // number (exact in f32 below 2^24; beyond, both are false).
        let inside = ixf >= 0.0 && iyf >= 0.0 && ixf < self.lim[0] && iyf < self.lim[1];
        let wts = [ax, ay];
        let (sd, mut sd2, mut bx, mut by) = if inside {
            // In range: both are non-negative and below the image size (and
            // then the integer floors equal the float ones).
            let o = iy as usize * self.w + ix as usize;
            let win = &self.i1[o..];
            if psz == 8 {
                accumulate8(win, self.w, pd, wts)
            } else {
                self.accumulate(win, self.w, x0, y0, wts)
            }
        } else {
            self.accumulate_clamped(ixf, iyf, x0, y0, pd, wts)
        };
        if self.mean_norm {
            let mean = sd / self.n_px;
            bx -= mean * pr.sgx;
            by -= mean * pr.sgy;
            sd2 -= sd * mean;
        }
        Eval { ssd: sd2, bx, by }
    }

    /// [`LevelView::eval`] at each vector of `uv` (at most 4) into `out`,
    /// the same values bit for bit. For 8x8 patches the windows inside the
    /// image go through one kernel together ([`accumulate8_lanes_n`]):
    /// each evaluation is a chain of dependent sums, and independent chains
    /// side by side keep the arithmetic units busy where one alone waits.
    fn eval_many(
        &self,
        x0: usize,
        y0: usize,
        pr: &PatchRef,
        pd: &Patch8,
        uv: &[(f32, f32)],
        out: &mut [Eval],
    ) {
        if self.psz != 8 || uv.len() < 2 {
            for (o, &(u, v)) in out.iter_mut().zip(uv) {
                *o = self.eval(x0, y0, pr, pd, u, v);
            }
            return;
        }
        let mut offs = [0usize; 4];
        let mut wts = [[0.0f32; 2]; 4];
        let mut which = [0usize; 4];
        let mut m = 0;
        for (q, &(u, v)) in uv.iter().enumerate().take(4) {
            // As in `eval`.
            let fxp = x0 as f32 + u;
            let fyp = y0 as f32 + v;
            let (ixf, ix) = floor_both(fxp);
            let (iyf, iy) = floor_both(fyp);
            let inside = ixf >= 0.0 && iyf >= 0.0 && ixf < self.lim[0] && iyf < self.lim[1];
            if inside {
                offs[m] = iy as usize * self.w + ix as usize;
                wts[m] = [fxp - ixf, fyp - iyf];
                which[m] = q;
                m += 1;
            } else {
                out[q] = self.eval(x0, y0, pr, pd, u, v);
            }
        }
        let sums = match m {
            0 => return,
            1 => [accumulate8_lanes(&self.i1[offs[0]..], self.w, pd, wts[0]); 4],
            2 => {
                let wins = [&self.i1[offs[0]..], &self.i1[offs[1]..]];
                let [a, b] = accumulate8_lanes_n::<2>(wins, self.w, pd, [wts[0], wts[1]]);
                [a, b, a, b]
            }
            _ => {
                // A third window fills the fourth slot when there are three.
                let k = if m == 4 { 3 } else { 2 };
                let wins = [
                    &self.i1[offs[0]..],
                    &self.i1[offs[1]..],
                    &self.i1[offs[2]..],
                    &self.i1[offs[k]..],
                ];
                accumulate8_lanes_n::<4>(wins, self.w, pd, [wts[0], wts[1], wts[2], wts[k]])
            }
        };
        for (t, a) in sums.iter().enumerate().take(m) {
            let (sd, mut sd2, mut bx, mut by) = reduce_lanes(*a);
            if self.mean_norm {
                let mean = sd / self.n_px;
                bx -= mean * pr.sgx;
                by -= mean * pr.sgy;
                sd2 -= sd * mean;
            }
            out[which[t]] = Eval { ssd: sd2, bx, by };
        }
    }
}

impl LevelView<'_> {
    /// Sums of `d`, `d^2`, `d gx`, `d gy` over the patch at `(x0, y0)`, where
    /// `d` is the bilinear sample of the window minus the reference. Per-
    /// column accumulators keep the inner loop free of a serial
    /// floating-point dependency (vectorizable, and deterministic).
    #[inline]
    fn accumulate(
        &self,
        win: &[f32],
        stride: usize,
        x0: usize,
        y0: usize,
        [ax, ay]: [f32; 2],
    ) -> (f32, f32, f32, f32) {
        let psz = self.psz;
        let mut acc = [[0.0f32; MAX_PATCH_SIZE]; 4];
        // Bilinear as two lerps: along x per window row, then along y.
        let lerp_row = |r: usize| -> [f32; MAX_PATCH_SIZE] {
            let row = &win[r * stride..][..psz + 1];
            let mut h = [0.0f32; MAX_PATCH_SIZE];
            for c in 0..psz {
                h[c] = row[c] + ax * (row[c + 1] - row[c]);
            }
            h
        };
        let mut top = lerp_row(0);
        for r in 0..psz {
            let bot = lerp_row(r + 1);
            let o = (y0 + r) * self.w + x0;
            let i0r = &self.i0[o..][..psz];
            let gxr = &self.gx[o..][..psz];
            let gyr = &self.gy[o..][..psz];
            for c in 0..psz {
                let d = top[c] + ay * (bot[c] - top[c]) - i0r[c];
                acc[0][c] += d;
                acc[1][c] += d * d;
                acc[2][c] += d * gxr[c];
                acc[3][c] += d * gyr[c];
            }
            top = bot;
        }
        let mut out = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
        for c in 0..psz {
            out.0 += acc[0][c];
            out.1 += acc[1][c];
            out.2 += acc[2][c];
            out.3 += acc[3][c];
        }
        out
    }

    /// [`LevelView::accumulate`] on a window that leaves the image: copied
    /// with border replication into a stack buffer first.
    #[cold]
    #[inline(never)]
    fn accumulate_clamped(
        &self,
        ixf: f32,
        iyf: f32,
        x0: usize,
        y0: usize,
        pd: &Patch8,
        wts: [f32; 2],
    ) -> (f32, f32, f32, f32) {
        let st = self.psz + 1;
        // Clamp in f32 first: a wild vector must not overflow the casts.
        let cl = |v: f32, n: usize| -> usize { v.clamp(0.0, (n - 1) as f32) as usize };
        let fill = |buf: &mut [f32]| {
            // The window's columns, clamped once for all its rows.
            let mut cols = [0usize; MAX_PATCH_SIZE + 1];
            for (c, x) in cols[..st].iter_mut().enumerate() {
                *x = cl(ixf + c as f32, self.w);
            }
            for (r, out) in buf.chunks_exact_mut(st).take(st).enumerate() {
                let row = &self.i1[cl(iyf + r as f32, self.h) * self.w..][..self.w];
                for (o, &x) in out.iter_mut().zip(&cols[..st]) {
                    *o = row[x];
                }
            }
        };
        // The 8x8 patches of every preset need only a 9x9 window: zeroing the
        // largest (33x33) buffer cost more than the copy itself.
        if self.psz == 8 {
            let mut buf = [0.0f32; 81];
            fill(&mut buf);
            accumulate8(&buf, st, pd, wts)
        } else {
            let mut buf = [0.0f32; (MAX_PATCH_SIZE + 1) * (MAX_PATCH_SIZE + 1)];
            fill(&mut buf);
            self.accumulate(&buf, st, x0, y0, wts)
        }
    }
}

/// The reference data of one 8x8 patch, each plane row-major and
/// contiguous: the image and its two gradients. Copied from the level's
/// planes once per reference ([`Dis::set_reference`] stores every patch's
/// block in search order), so the cost kernel reads whole 64-float arrays
/// with no bounds checks or row strides, which the compiler turns into
/// straight vector code, and the search streams through the blocks.
#[derive(Debug, Clone)]
#[repr(C, align(64))]
struct Patch8 {
    i0: [f32; 64],
    gx: [f32; 64],
    gy: [f32; 64],
}

impl Patch8 {
    fn zeroed() -> Self {
        Patch8 {
            i0: [0.0; 64],
            gx: [0.0; 64],
            gy: [0.0; 64],
        }
    }

    /// The 8x8 block at `(x0, y0)` of the reference planes `[i0, gx, gy]`
    /// (`w` columns each).
    fn from_planes([i0, gx, gy]: [&[f32]; 3], w: usize, x0: usize, y0: usize) -> Self {
        let mut p = Patch8::zeroed();
        for r in 0..8 {
            let o = (y0 + r) * w + x0;
            p.i0[r * 8..][..8].copy_from_slice(&i0[o..o + 8]);
            p.gx[r * 8..][..8].copy_from_slice(&gx[o..o + 8]);
            p.gy[r * 8..][..8].copy_from_slice(&gy[o..o + 8]);
        }
        p
    }
}

/// 4-lane partial sums of 64 values: lane `l` takes every 4th value, in a
/// fixed order (deterministic).
#[inline(always)]
fn lanes_sum(a: &[f32; 64]) -> [f32; 4] {
    let mut acc = [0.0f32; 4];
    for k in 0..16 {
        for l in 0..4 {
            acc[l] += a[4 * k + l];
        }
    }
    acc
}

/// 4-lane partial dot products of 64 values, lanes as in [`lanes_sum`].
#[inline(always)]
fn lanes_dot(a: &[f32; 64], b: &[f32; 64]) -> [f32; 4] {
    let mut acc = [0.0f32; 4];
    for k in 0..16 {
        for l in 0..4 {
            acc[l] += a[4 * k + l] * b[4 * k + l];
        }
    }
    acc
}

/// [`LevelView::accumulate`] for 8x8 patches (every preset): the four sums
/// `d`, `d^2`, `d gx`, `d gy`, each as 4 lane partials. Written as
/// whole-array passes (horizontal lerp of the 9 window rows, vertical lerp
/// and difference, then four separate reductions) whose lane partials are
/// returned through memory: with the sums interleaved in one loop, or
/// reduced to scalars here, LLVM's SLP vectorizer packed the four sums of
/// one column into a vector instead (a shuffle per pixel, 2-4x the
/// instructions). Not inlined for the same reason: the stores of the
/// result are what steer the vectorizer to whole-lane vectors.
///
/// Dispatched at run time (`pulp`, see [`super::simd_arch`]): with AVX2 a window row
/// of 8 is one vector. The same operations in the same order on every path, so the
/// sums are bit-identical.
#[inline(never)]
fn accumulate8_lanes(win: &[f32], stride: usize, pd: &Patch8, wts: [f32; 2]) -> [[f32; 4]; 4] {
    super::simd_arch().dispatch(Acc8Op {
        win,
        stride,
        pd,
        wts,
    })
}

/// [`accumulate8_lanes_kernel`]'s arguments as a `pulp` operation (a method marked
/// `#[inline(always)]` is inlined into `pulp`'s AVX2 function; a closure is not).
struct Acc8Op<'a> {
    win: &'a [f32],
    stride: usize,
    pd: &'a Patch8,
    wts: [f32; 2],
}

impl pulp::WithSimd for Acc8Op<'_> {
    type Output = [[f32; 4]; 4];
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) -> [[f32; 4]; 4] {
        accumulate8_lanes_kernel(self.win, self.stride, self.pd, self.wts)
    }
}

/// The body of [`accumulate8_lanes`].
#[inline(always)]
fn accumulate8_lanes_kernel(
    win: &[f32],
    stride: usize,
    pd: &Patch8,
    [ax, ay]: [f32; 2],
) -> [[f32; 4]; 4] {
    let mut hl = [0.0f32; 72];
    // The window rows by stepping a slice (one length test per row, no index
    // products).
    let mut rest = win;
    for r in 0..9 {
        if r > 0 {
            rest = &rest[stride..];
        }
        let row: &[f32; 9] = rest[..9].try_into().expect("9 values");
        for c in 0..8 {
            hl[8 * r + c] = row[c] + ax * (row[c + 1] - row[c]);
        }
    }
    let mut d = [0.0f32; 64];
    for k in 0..64 {
        d[k] = hl[k] + ay * (hl[k + 8] - hl[k]) - pd.i0[k];
    }
    [
        lanes_sum(&d),
        lanes_dot(&d, &d),
        lanes_dot(&d, &pd.gx),
        lanes_dot(&d, &pd.gy),
    ]
}

/// [`accumulate8_lanes`] reduced to the four sums.
#[inline]
fn accumulate8(win: &[f32], stride: usize, pd: &Patch8, wts: [f32; 2]) -> (f32, f32, f32, f32) {
    reduce_lanes(accumulate8_lanes(win, stride, pd, wts))
}

/// The four sums from their lane partials.
#[inline]
fn reduce_lanes(a: [[f32; 4]; 4]) -> (f32, f32, f32, f32) {
    let h = |x: [f32; 4]| (x[0] + x[2]) + (x[1] + x[3]);
    (h(a[0]), h(a[1]), h(a[2]), h(a[3]))
}

/// [`accumulate8_lanes`] of `N` windows of the same patch at once (each
/// window with its own bilinear weights): the same operations in the same
/// order for each, so each result equals [`accumulate8_lanes`]'s bit for
/// bit; the `N` independent reductions are interleaved.
#[inline(never)]
fn accumulate8_lanes_n<const N: usize>(
    wins: [&[f32]; N],
    stride: usize,
    pd: &Patch8,
    wts: [[f32; 2]; N],
) -> [[[f32; 4]; 4]; N] {
    super::simd_arch().dispatch(Acc8NOp {
        wins,
        stride,
        pd,
        wts,
    })
}

/// [`accumulate8_lanes_n`]'s arguments as a `pulp` operation.
struct Acc8NOp<'a, const N: usize> {
    wins: [&'a [f32]; N],
    stride: usize,
    pd: &'a Patch8,
    wts: [[f32; 2]; N],
}

impl<const N: usize> pulp::WithSimd for Acc8NOp<'_, N> {
    type Output = [[[f32; 4]; 4]; N];
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) -> [[[f32; 4]; 4]; N] {
        accumulate8_lanes_n_kernel(self.wins, self.stride, self.pd, self.wts)
    }
}

/// The body of [`accumulate8_lanes_n`]: [`accumulate8_lanes_kernel`]'s
/// differences for each window, then its four lane reductions with the
/// windows' sums side by side.
#[inline(always)]
fn accumulate8_lanes_n_kernel<const N: usize>(
    wins: [&[f32]; N],
    stride: usize,
    pd: &Patch8,
    wts: [[f32; 2]; N],
) -> [[[f32; 4]; 4]; N] {
    let mut d = [[0.0f32; 64]; N];
    for e in 0..N {
        let [ax, ay] = wts[e];
        let mut hl = [0.0f32; 72];
        let mut rest = wins[e];
        for r in 0..9 {
            if r > 0 {
                rest = &rest[stride..];
            }
            let row: &[f32; 9] = rest[..9].try_into().expect("9 values");
            for c in 0..8 {
                hl[8 * r + c] = row[c] + ax * (row[c + 1] - row[c]);
            }
        }
        for k in 0..64 {
            d[e][k] = hl[k] + ay * (hl[k + 8] - hl[k]) - pd.i0[k];
        }
    }
    let mut acc = [[[0.0f32; 4]; 4]; N];
    for k in 0..16 {
        for e in 0..N {
            for l in 0..4 {
                let x = d[e][4 * k + l];
                acc[e][0][l] += x;
                acc[e][1][l] += x * x;
                acc[e][2][l] += x * pd.gx[4 * k + l];
                acc[e][3][l] += x * pd.gy[4 * k + l];
            }
        }
    }
    acc
}

/// [`fast_floor`] and the same floor as an integer (from the one conversion
/// it makes). The integer is the float's value whenever `0 <= x < 2^24`
/// (below -2^31 it wraps; callers use it only for non-negative floors).
#[inline]
fn floor_both(x: f32) -> (f32, i32) {
    let i = x as i32;
    let t = i as f32;
    if t > x {
        (t - 1.0, i.wrapping_sub(1))
    } else {
        (t, i)
    }
}

/// `floor` without the libm call (exact for |x| < 2^31; larger or NaN
/// values only ever reach the clamped path).
#[inline]
fn fast_floor(x: f32) -> f32 {
    let t = x as i32 as f32;
    if t > x { t - 1.0 } else { t }
}

/// How one level's patches are searched.
#[derive(Debug, Clone, Copy)]
struct Search {
    /// Untextured patches are not searched: they keep their start vector
    /// (and are filled afterwards with `fill_untextured`).
    keep_untextured: bool,
    /// The zero vector competes with each patch's start.
    zero_candidate: bool,
}

/// Both propagation passes over all stripes of one level.
fn search_level(lvl: &mut Level, p: &DisParams, search: Search) {
    let ws = lvl.ws();
    let hs = lvl.hs();
    let stripe_rows = hs.div_ceil(p.stripes).max(p.min_stripe_rows);
    let iters = p.gradient_descent_iterations / 2;
    let stop2 = p.early_stop * p.early_stop;
    let view = LevelView {
        w: lvl.w,
        h: lvl.h,
        i0: &lvl.i0,
        gx: &lvl.gx,
        gy: &lvl.gy,
        i1: &lvl.i1,
        psz: p.patch_size,
        mean_norm: p.mean_normalization,
        lim: [(lvl.w - p.patch_size) as f32, (lvl.h - p.patch_size) as f32],
        n_px: (p.patch_size * p.patch_size) as f32,
    };
    let (px, py, patches, pdata) = (&lvl.px, &lvl.py, &lvl.patches, &lvl.pdata);
    lvl.sx
        .par_chunks_mut(stripe_rows * ws)
        .zip(lvl.sy.par_chunks_mut(stripe_rows * ws))
        .zip(lvl.known.par_chunks_mut(stripe_rows * ws))
        .enumerate()
        .for_each(|(k, ((sx, sy), known))| {
            let i_begin = k * stripe_rows;
            let rows = sx.len() / ws;
            // Read by the 8x8 kernels only: other sizes pass this unused block.
            let unused = Patch8::zeroed();
            for forward in [true, false] {
                for ii in 0..rows {
                    let i = if forward { ii } else { rows - 1 - ii };
                    for jj in 0..ws {
                        let j = if forward { jj } else { ws - 1 - jj };
                        let idx = i * ws + j;
                        let gi = i_begin + i;
                        let (x0, y0) = (px[j] as usize, py[gi] as usize);
                        let pr = &patches[gi * ws + j];
                        if search.keep_untextured && !pr.textured {
                            // Keeps its start, or is filled from its
                            // searched neighbours afterwards.
                            continue;
                        }
                        let pd = pdata.get(gi * ws + j).unwrap_or(&unused);
                        let (mut u, mut v) = (sx[idx], sy[idx]);
                        // Every vector the candidate step below may
                        // evaluate: the start (unless the forward pass
                        // left its evaluation), the zero vector and the
                        // visited neighbours' vectors, each once, evaluated
                        // together. The step then reads them from `cands`
                        // in its order (a vector missing there, a NaN,
                        // is evaluated on the spot): the same evaluations,
                        // so the same choice.
                        let neighbours = if !p.spatial_propagation {
                            [None, None]
                        } else if forward {
                            [(j > 0).then(|| idx - 1), (i > 0).then(|| idx - ws)]
                        } else {
                            [
                                (j + 1 < ws).then(|| idx + 1),
                                (i + 1 < rows).then(|| idx + ws),
                            ]
                        };
                        let zero = forward && search.zero_candidate && (u != 0.0 || v != 0.0);
                        let mut cands = Cands::default();
                        if let Some(e) = known[idx].at(u, v).filter(|_| !forward) {
                            cands.push_known((u, v), e);
                        }
                        cands.want((u, v));
                        if zero {
                            cands.want((0.0, 0.0));
                        }
                        for n in neighbours.into_iter().flatten() {
                            cands.want((sx[n], sy[n]));
                        }
                        cands.evaluate(&view, x0, y0, pr, pd);
                        let at = |c: (f32, f32)| {
                            cands
                                .get(c)
                                .unwrap_or_else(|| view.eval(x0, y0, pr, pd, c.0, c.1))
                        };
                        let mut cur = at((u, v));
                        if zero {
                            let e = at((0.0, 0.0));
                            if e.ssd < cur.ssd {
                                (u, v, cur) = (0.0, 0.0, e);
                            }
                        }
                        for n in neighbours.into_iter().flatten() {
                            let (cu, cv) = (sx[n], sy[n]);
                            if cu == u && cv == v {
                                continue;
                            }
                            let e = at((cu, cv));
                            if e.ssd < cur.ssd {
                                (u, v, cur) = (cu, cv, e);
                            }
                        }
                        let (u0, v0, e0) = (u, v, cur);
                        // The evaluation at the final vector, when made.
                        let mut last = Some(cur);
                        // The evaluation at (lu, lv).
                        let mut best = cur;
                        let mut prev = f32::INFINITY;
                        let (mut lu, mut lv) = (u, v);
                        // Whether (u, v) is a halved step not yet evaluated.
                        let mut halved = false;
                        for t in 0..iters {
                            if t > 0 {
                                cur = view.eval(x0, y0, pr, pd, u, v);
                            }
                            // Stop when the cost stops falling; keep the
                            // last vector that lowered it.
                            // (NaN never counts as an improvement.)
                            let improved = cur.ssd < prev;
                            if !improved {
                                if p.backtracking && t > 0 {
                                    u = 0.5 * (u + lu);
                                    v = 0.5 * (v + lv);
                                    halved = true;
                                    last = None;
                                    continue;
                                }
                                if p.step_on_stop && t > 0 {
                                    // OpenCV's order: step, then test.
                                    u -= pr.ih11 * cur.bx + pr.ih12 * cur.by;
                                    v -= pr.ih12 * cur.bx + pr.ih22 * cur.by;
                                    last = None;
                                } else {
                                    (u, v) = (lu, lv);
                                    last = Some(best);
                                }
                                break;
                            }
                            prev = cur.ssd;
                            (lu, lv) = (u, v);
                            best = cur;
                            halved = false;
                            let su = pr.ih11 * cur.bx + pr.ih12 * cur.by;
                            let sv = pr.ih12 * cur.bx + pr.ih22 * cur.by;
                            u -= su;
                            v -= sv;
                            last = None;
                            // Converged: the next evaluation would only
                            // confirm a step this small.
                            if su * su + sv * sv < stop2 {
                                break;
                            }
                        }
                        if halved {
                            (u, v) = (lu, lv);
                            last = Some(best);
                        }
                        // A vector that wandered more than a patch away from
                        // its start is more likely wrong than a large motion.
                        let du = u - u0;
                        let dv = v - v0;
                        let lim = p.patch_size as f32;
                        let within = du * du + dv * dv <= lim * lim;
                        if !within {
                            (u, v) = (u0, v0);
                            last = Some(e0);
                        }
                        sx[idx] = u;
                        sy[idx] = v;
                        if forward {
                            known[idx] = last.map_or(Known::NONE, |e| Known { u, v, e });
                        }
                    }
                }
            }
        });
}

/// Gives every untextured patch the mean vector of the textured patches
/// nearest to it: those in the smallest square of `2r + 1` patches (`r` = 1,
/// 2, 4, ...) around it that holds any, read from summed-area tables of the
/// textured patches' count and vectors (so the cost does not grow with the
/// size of an untextured region). A level without textured patches keeps
/// the coarser level's vectors. Serial and in a fixed order: the result does
/// not depend on the thread count.
fn fill_untextured(lvl: &mut Level) {
    let (ws, hs) = (lvl.ws(), lvl.hs());
    let patches = &lvl.patches;
    if patches.iter().all(|p| p.textured) || !patches.iter().any(|p| p.textured) {
        return;
    }
    // Summed-area tables with a zero first row and column, in f64 so that the
    // differences of large sums stay exact enough.
    let (tw, th) = (ws + 1, hs + 1);
    let mut tables = vec![[0f64; 3]; tw * th];
    for i in 0..hs {
        let mut row = [0f64; 3];
        for j in 0..ws {
            let k = i * ws + j;
            if patches[k].textured {
                row[0] += 1.0;
                row[1] += lvl.sx[k] as f64;
                row[2] += lvl.sy[k] as f64;
            }
            let above = tables[i * tw + j + 1];
            tables[(i + 1) * tw + j + 1] =
                [row[0] + above[0], row[1] + above[1], row[2] + above[2]];
        }
    }
    let rect = |i0: usize, j0: usize, i1: usize, j1: usize| -> [f64; 3] {
        // Sums over patch rows i0..i1 and columns j0..j1 (exclusive ends).
        let (a, b) = (tables[i1 * tw + j1], tables[i0 * tw + j1]);
        let (c, d) = (tables[i1 * tw + j0], tables[i0 * tw + j0]);
        std::array::from_fn(|q| a[q] - b[q] - c[q] + d[q])
    };
    let reach = ws.max(hs);
    for i in 0..hs {
        for j in 0..ws {
            let k = i * ws + j;
            if patches[k].textured {
                continue;
            }
            let mut r = 1;
            loop {
                let (i0, j0) = (i.saturating_sub(r), j.saturating_sub(r));
                let (i1, j1) = ((i + r + 1).min(hs), (j + r + 1).min(ws));
                let [n, su, sv] = rect(i0, j0, i1, j1);
                if n > 0.5 {
                    lvl.sx[k] = (su / n) as f32;
                    lvl.sy[k] = (sv / n) as f32;
                    break;
                }
                if r >= reach {
                    break;
                }
                r *= 2;
            }
        }
    }
}

/// Dense flow: each pixel averages the vectors of the patches covering it,
/// weighted by `1 / max(1, |cur(x + u) - ref(x)|)`.
///
/// Patch-wise per image row: a patch's 8 (psz) pixels of the row share its
/// vector, so the bilinear weights are computed once per patch row and the
/// samples come from two contiguous rows of `cur` (no per-pixel clamping or
/// floor). Each pixel still sums its patches in the same order (patch row,
/// then patch column), and rows are independent, so the result does not
/// depend on the thread count. The weight sums go to `lvl.tmp` (free after
/// the prefilter).
fn densify(lvl: &mut Level, psz: usize) {
    let (w, h, ws) = (lvl.w, lvl.h, lvl.ws());
    let (i0, i1) = (&lvl.i0, &lvl.i1);
    let (sx, sy) = (&lvl.sx, &lvl.sy);
    let (px, ilo, ihi) = (&lvl.px, &lvl.ilo, &lvl.ihi);
    let fu = lvl.flow.u.as_slice_mut().expect("standard layout");
    let fv = lvl.flow.v.as_slice_mut().expect("standard layout");
    let rows = DenseRows {
        w,
        h,
        ws,
        psz,
        i0,
        i1,
        sx,
        sy,
        px,
        ilo,
        ihi,
        solo: &lvl.solo,
        shared: &lvl.shared,
    };
    fu.par_chunks_mut(w)
        .zip(fv.par_chunks_mut(w))
        .zip(lvl.tmp.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, ((ur, vr), swr))| {
            // Dispatched at run time (see `flow::simd_arch`): same values on every path.
            super::simd_arch().dispatch(DensifyRowOp {
                d: &rows,
                y,
                out: [ur, vr, swr],
            });
        });
}

/// What [`densify`] reads, for [`densify_row`].
struct DenseRows<'a> {
    w: usize,
    h: usize,
    ws: usize,
    psz: usize,
    i0: &'a [f32],
    i1: &'a [f32],
    sx: &'a [f32],
    sy: &'a [f32],
    px: &'a [u32],
    ilo: &'a [u32],
    ihi: &'a [u32],
    /// [`solo_columns`] of `px`.
    solo: &'a [bool],
    shared: &'a [(u32, u32)],
}

/// [`densify_row`] as a `pulp` operation (a `with_simd` method marked
/// `#[inline(always)]` is compiled inside `pulp`'s AVX2 function; a closure's body
/// is not).
struct DensifyRowOp<'a, 'b> {
    d: &'a DenseRows<'b>,
    y: usize,
    out: [&'a mut [f32]; 3],
}

impl pulp::WithSimd for DensifyRowOp<'_, '_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        densify_row(self.d, self.y, self.out);
    }
}

/// Row `y` of [`densify`]: the flow `ur`, `vr` ([`densify_row_sums`]'s
/// values bit for bit). A row that one patch row covers (every row of
/// `fine` on a height that is a multiple of the patch) takes each pixel
/// that one patch alone covers straight to its value: that pixel's sums
/// would be `0 + wgt pu`, `0 + wgt pv` and `0 + wgt`, and its flow their
/// quotients, which is what [`densify_solo_row8`] computes, with no sums
/// to clear, add to and divide afterwards. The pixels of the other patch
/// columns (the spans `d.shared`) are summed in `ur`, `vr` and `swr` as
/// [`densify_row_sums`] does.
#[inline(always)]
fn densify_row(d: &DenseRows, y: usize, [ur, vr, swr]: [&mut [f32]; 3]) {
    let i = d.ilo[y] as usize;
    if i != d.ihi[y] as usize {
        densify_row_sums(d, y, [ur, vr, swr]);
        return;
    }
    for &(a, b) in d.shared {
        let span = a as usize..b as usize;
        ur[span.clone()].fill(0.0);
        vr[span.clone()].fill(0.0);
        swr[span].fill(0.0);
    }
    for j in 0..d.ws {
        if d.solo[j] {
            densify_patch_solo(d, y, i, j, [&mut *ur, &mut *vr]);
        } else {
            densify_patch(d, y, i, j, [&mut *ur, &mut *vr, &mut *swr]);
        }
    }
    for &(a, b) in d.shared {
        let span = a as usize..b as usize;
        for ((u, v), s) in ur[span.clone()]
            .iter_mut()
            .zip(vr[span.clone()].iter_mut())
            .zip(&swr[span])
        {
            *u /= s;
            *v /= s;
        }
    }
}

/// Row `y` of [`densify`], every pixel by its sums: the flow sums `ur`, `vr`
/// and the weight sums `swr` over the patches covering it, then the
/// weighted averages (the plain form of [`densify_row`]).
#[inline(always)]
fn densify_row_sums(d: &DenseRows, y: usize, [ur, vr, swr]: [&mut [f32]; 3]) {
    ur.fill(0.0);
    vr.fill(0.0);
    swr.fill(0.0);
    for i in d.ilo[y] as usize..=d.ihi[y] as usize {
        for j in 0..d.ws {
            densify_patch(d, y, i, j, [&mut *ur, &mut *vr, &mut *swr]);
        }
    }
    for ((u, v), s) in ur.iter_mut().zip(vr.iter_mut()).zip(swr.iter()) {
        *u /= s;
        *v /= s;
    }
}

/// The offset in the current image of a patch row's first sample and its
/// bilinear fractions `[ax, ay]`.
type RowWindow = (usize, [f32; 2]);

/// Where patch `(i, j)`'s row `y` samples the current image: its vector,
/// first column, and, when its `psz + 1` samples of rows `iy` and `iy + 1`
/// lie inside, the offset of the first and the bilinear fractions.
#[inline(always)]
fn patch_row_window(
    d: &DenseRows,
    y: usize,
    i: usize,
    j: usize,
) -> ([f32; 2], usize, Option<RowWindow>) {
    let (w, h, psz) = (d.w, d.h, d.psz);
    let (pu, pv) = (d.sx[i * d.ws + j], d.sy[i * d.ws + j]);
    let x0 = d.px[j] as usize;
    let fx = x0 as f32 + pu;
    let fy = y as f32 + pv;
    let (ixf, iyf) = (fast_floor(fx), fast_floor(fy));
    let inside = fx.is_finite()
        && fy.is_finite()
        && ixf >= 0.0
        && iyf >= 0.0
        && ixf + (psz as f32) < w as f32
        && iyf + 1.0 < h as f32;
    let win = inside.then(|| {
        // In range (checked above): the i32 conversion is one
        // instruction, the saturating f32 -> usize one is not.
        let o = iyf as i32 as usize * w + ixf as i32 as usize;
        (o, [fx - ixf, fy - iyf])
    });
    ([pu, pv], x0, win)
}

/// Patch `(i, j)`'s contribution to the sums of row `y`.
#[inline(always)]
fn densify_patch(d: &DenseRows, y: usize, i: usize, j: usize, [ur, vr, swr]: [&mut [f32]; 3]) {
    let (w, h, psz, i1) = (d.w, d.h, d.psz, d.i1);
    let ([pu, pv], x0, win) = patch_row_window(d, y, i, j);
    let ref_row = &d.i0[y * w + x0..][..psz];
    let (u_acc, v_acc) = (&mut ur[x0..][..psz], &mut vr[x0..][..psz]);
    let w_acc = &mut swr[x0..][..psz];
    if let Some((o, wts)) = win {
        let rows = [&i1[o..][..psz + 1], &i1[o + w..][..psz + 1]];
        let acc = [u_acc, v_acc, w_acc];
        if psz == 8 {
            densify_patch_row8(rows, ref_row, wts, [pu, pv], acc);
        } else {
            densify_patch_row(psz, rows, ref_row, wts, [pu, pv], acc);
        }
    } else {
        let fy = y as f32 + pv;
        for c in 0..psz {
            let s = pyramid::sample_clamped(i1, w, h, (x0 + c) as f32 + pu, fy);
            let wgt = 1.0 / (s - ref_row[c]).abs().max(1.0);
            u_acc[c] += wgt * pu;
            v_acc[c] += wgt * pv;
            w_acc[c] += wgt;
        }
    }
}

/// The flow of row `y` on the pixels of patch `(i, j)`, which no other
/// patch covers: [`densify_patch`] into zero sums, then the quotients,
/// in one step (the same operations, so the same values bit for bit).
#[inline(always)]
fn densify_patch_solo(d: &DenseRows, y: usize, i: usize, j: usize, [ur, vr]: [&mut [f32]; 2]) {
    let (w, h, psz, i1) = (d.w, d.h, d.psz, d.i1);
    let ([pu, pv], x0, win) = patch_row_window(d, y, i, j);
    let ref_row = &d.i0[y * w + x0..][..psz];
    let (u_out, v_out) = (&mut ur[x0..][..psz], &mut vr[x0..][..psz]);
    match win {
        Some((o, wts)) if psz == 8 => {
            let rows = [&i1[o..][..9], &i1[o + w..][..9]];
            densify_solo_row8(rows, ref_row, wts, [pu, pv], [u_out, v_out]);
        }
        _ => {
            let fy = y as f32 + pv;
            for c in 0..psz {
                let s = match win {
                    Some((o, [ax, ay])) => {
                        let (top, bot) = (&i1[o..], &i1[o + w..]);
                        let t = top[c] + ax * (top[c + 1] - top[c]);
                        let b = bot[c] + ax * (bot[c + 1] - bot[c]);
                        t + ay * (b - t)
                    }
                    None => pyramid::sample_clamped(i1, w, h, (x0 + c) as f32 + pu, fy),
                };
                let wgt = 1.0 / (s - ref_row[c]).abs().max(1.0);
                let sw = 0.0 + wgt;
                u_out[c] = (0.0 + wgt * pu) / sw;
                v_out[c] = (0.0 + wgt * pv) / sw;
            }
        }
    }
}

/// [`densify_patch_solo`]'s 8-pixel form, vectorised as
/// [`densify_patch_row8`] is: each pixel's flow straight from its one
/// weight, `(0 + wgt pu) / (0 + wgt)` (the sums' first additions kept: `0 +
/// -0.0` is `+0.0`).
#[inline(always)]
fn densify_solo_row8(
    [top, bot]: [&[f32]; 2],
    ref_row: &[f32],
    [ax, ay]: [f32; 2],
    [pu, pv]: [f32; 2],
    [u_out, v_out]: [&mut [f32]; 2],
) {
    let wgt = weights8([top, bot], ref_row, [ax, ay]);
    let sw: [f32; 8] = std::array::from_fn(|c| 0.0 + wgt[c]);
    let u_out: &mut [f32; 8] = (&mut u_out[..8]).try_into().expect("8 values");
    let v_out: &mut [f32; 8] = (&mut v_out[..8]).try_into().expect("8 values");
    quotient8(u_out, &wgt, &sw, pu);
    quotient8(v_out, &wgt, &sw, pv);
}

/// The densification weights of an 8-pixel patch row:
/// `1 / max(1, |warped current - reference|)`, the current image sampled
/// bilinearly at fractions `(ax, ay)` between rows `top` and `bot` (9 values
/// each), computed into an array before anything is written.
#[inline(always)]
fn weights8([top, bot]: [&[f32]; 2], ref_row: &[f32], [ax, ay]: [f32; 2]) -> [f32; 8] {
    let top: &[f32; 9] = top[..9].try_into().expect("9 values");
    let bot: &[f32; 9] = bot[..9].try_into().expect("9 values");
    let ref_row: &[f32; 8] = ref_row[..8].try_into().expect("8 values");
    std::array::from_fn(|c| {
        let t = top[c] + ax * (top[c + 1] - top[c]);
        let b = bot[c] + ax * (bot[c + 1] - bot[c]);
        let s = t + ay * (b - t);
        1.0 / (s - ref_row[c]).abs().max(1.0)
    })
}

/// `out = (0 + s wgt) / sw` element-wise (separate so that each output
/// vectorises as a whole array, as in [`add_scaled8`]).
#[inline(always)]
fn quotient8(out: &mut [f32; 8], wgt: &[f32; 8], sw: &[f32; 8], s: f32) {
    for c in 0..8 {
        out[c] = (0.0 + wgt[c] * s) / sw[c];
    }
}

/// [`densify_patch_row`] for 8-pixel patch rows (every preset), written so
/// that it vectorises: the eight weights are computed first into an array
/// (all reads of the images before any write), then each of the three sums
/// is updated as one 8-value array. In the per-pixel form the compiler
/// could not prove that the sums' writes do not alias the image rows it
/// reads next and left the whole row scalar (~25 instructions per pixel).
/// Same arithmetic per pixel, so the same result bit for bit.
#[inline(always)]
fn densify_patch_row8(
    [top, bot]: [&[f32]; 2],
    ref_row: &[f32],
    [ax, ay]: [f32; 2],
    [pu, pv]: [f32; 2],
    [u_acc, v_acc, w_acc]: [&mut [f32]; 3],
) {
    let wgt = weights8([top, bot], ref_row, [ax, ay]);
    let u_acc: &mut [f32; 8] = (&mut u_acc[..8]).try_into().expect("8 values");
    let v_acc: &mut [f32; 8] = (&mut v_acc[..8]).try_into().expect("8 values");
    let w_acc: &mut [f32; 8] = (&mut w_acc[..8]).try_into().expect("8 values");
    add_scaled8(u_acc, &wgt, pu);
    add_scaled8(v_acc, &wgt, pv);
    for c in 0..8 {
        w_acc[c] += wgt[c];
    }
}

/// `acc += s * wgt` element-wise (separate so the three sums vectorise as
/// whole arrays).
#[inline(always)]
fn add_scaled8(acc: &mut [f32; 8], wgt: &[f32; 8], s: f32) {
    for c in 0..8 {
        acc[c] += wgt[c] * s;
    }
}

/// One patch's contribution to `n` pixels of a row: bilinear samples of the
/// two current-image rows `[top, bot]` at fractions `[ax, ay]`, weighted by
/// `1 / max(1, |sample - ref|)`, added to the `[u, v, weight]` sums.
#[inline(always)]
fn densify_patch_row(
    n: usize,
    [top, bot]: [&[f32]; 2],
    ref_row: &[f32],
    [ax, ay]: [f32; 2],
    [pu, pv]: [f32; 2],
    [u_acc, v_acc, w_acc]: [&mut [f32]; 3],
) {
    let (top, bot, ref_row) = (&top[..n + 1], &bot[..n + 1], &ref_row[..n]);
    let (u_acc, v_acc, w_acc) = (&mut u_acc[..n], &mut v_acc[..n], &mut w_acc[..n]);
    for c in 0..n {
        let t = top[c] + ax * (top[c + 1] - top[c]);
        let b = bot[c] + ax * (bot[c + 1] - bot[c]);
        let s = t + ay * (b - t);
        let wgt = 1.0 / (s - ref_row[c]).abs().max(1.0);
        u_acc[c] += wgt * pu;
        v_acc[c] += wgt * pv;
        w_acc[c] += wgt;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patch_grid_covers_every_pixel() {
        for (n, p, s) in [(33, 8, 4), (32, 8, 4), (8, 8, 4), (50, 8, 3), (9, 4, 4)] {
            let c = patch_corners(n, p, s);
            assert_eq!(*c.last().unwrap() as usize + p, n);
            let (lo, hi) = coverage(n, p, &c);
            for x in 0..n {
                assert!(lo[x] <= hi[x]);
                for k in lo[x]..=hi[x] {
                    let c0 = c[k as usize] as usize;
                    assert!(c0 <= x && x < c0 + p);
                }
            }
        }
    }

    /// The slow, obviously correct patch cost: every pixel sampled on its
    /// own with border replication, sums in f64, mean subtracted explicitly.
    fn naive_eval(v: &LevelView, pr: &PatchRef, x0: usize, y0: usize, u: f32, vv: f32) -> Eval {
        let p = v.psz;
        let mut d = Vec::new();
        for r in 0..p {
            for c in 0..p {
                let (x, y) = (x0 + c, y0 + r);
                let s = pyramid::sample_clamped(v.i1, v.w, v.h, x as f32 + u, y as f32 + vv);
                d.push((s - v.i0[y * v.w + x]) as f64);
            }
        }
        let mean = if v.mean_norm {
            d.iter().sum::<f64>() / d.len() as f64
        } else {
            0.0
        };
        let (mut ssd, mut bx, mut by) = (0.0, 0.0, 0.0);
        for r in 0..p {
            for c in 0..p {
                let k = (y0 + r) * v.w + x0 + c;
                let e = d[r * p + c] - mean;
                ssd += e * e;
                bx += e * v.gx[k] as f64;
                by += e * v.gy[k] as f64;
            }
        }
        let _ = pr;
        Eval {
            ssd: ssd as f32,
            bx: bx as f32,
            by: by as f32,
        }
    }

    #[test]
    fn patch_cost_matches_the_naive_oracle() {
        let (w, h) = (40usize, 30usize);
        let img = |k: u64| -> Vec<f32> {
            (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f32, (i / w) as f32);
                    128.0
                        + 60.0 * (0.5 * x + 0.3 * y + k as f32).sin()
                        + 30.0 * (0.9 * y - 0.2 * x).cos()
                })
                .collect()
        };
        let (i0, i1) = (img(0), img(1));
        let (mut gx, mut gy) = (vec![0.0; w * h], vec![0.0; w * h]);
        pyramid::sobel(&i0, w, h, 0.125, &mut gx, &mut gy).unwrap();
        for psz in [8usize, 6] {
            for mean_norm in [true, false] {
                let view = LevelView {
                    w,
                    h,
                    i0: &i0,
                    gx: &gx,
                    gy: &gy,
                    i1: &i1,
                    psz,
                    mean_norm,
                    lim: [(w - psz) as f32, (h - psz) as f32],
                    n_px: (psz * psz) as f32,
                };
                // Inside, at sub-pixel offsets, and hanging over every edge.
                for &(x0, y0, u, v) in &[
                    (10usize, 8usize, 0.0f32, 0.0f32),
                    (10, 8, 0.37, -1.81),
                    (0, 0, -2.6, -0.4),
                    (w - psz, h - psz, 3.2, 2.9),
                    (5, h - psz, -0.5, 7.5),
                    (12, 4, -1e6, 1e6),
                ] {
                    let pr = patch_ref(&gx, &gy, w, x0, y0, psz, mean_norm, 0.0);
                    let pd = if psz == 8 {
                        Patch8::from_planes([&i0, &gx, &gy], w, x0, y0)
                    } else {
                        Patch8::zeroed()
                    };
                    let got = view.eval(x0, y0, &pr, &pd, u, v);
                    let want = naive_eval(&view, &pr, x0, y0, u, v);
                    let tol = |a: f32| 1e-3 * (1.0 + a.abs());
                    assert!(
                        (got.ssd - want.ssd).abs() < tol(want.ssd),
                        "{psz} {x0},{y0} {u},{v}"
                    );
                    assert!((got.bx - want.bx).abs() < tol(want.bx) * 10.0);
                    assert!((got.by - want.by).abs() < tol(want.by) * 10.0);
                }
            }
        }
    }

    #[test]
    fn floor_both_is_floor_as_float_and_integer() {
        let mut xs = vec![0.0f32, -0.0, 1.0, -1.0, 0.5, -0.5, 2.999_999_8, -2.000_001];
        xs.extend((0..2000).map(|k| (k as f32 - 1000.0) * 0.137));
        xs.extend((0..200).map(|k| k as f32 * 8191.7));
        for x in xs {
            let (f, i) = floor_both(x);
            assert_eq!(f.to_bits(), fast_floor(x).to_bits(), "{x}");
            assert_eq!(f, x.floor(), "{x}");
            assert_eq!(i as f32, f, "{x}");
        }
    }

    #[test]
    fn solo_columns_mark_the_pixels_one_patch_covers() {
        // Stride = patch on an exact width: all alone; on a ragged width the
        // last two columns share pixels; a smaller stride shares them all.
        let (solo, shared) = solo_columns(&patch_corners(32, 8, 8), 8);
        assert!(solo.iter().all(|&s| s) && shared.is_empty());
        let (solo, shared) = solo_columns(&patch_corners(36, 8, 8), 8);
        assert_eq!(solo, [true, true, true, false, false]);
        assert_eq!(shared, [(24, 36)]);
        let (solo, shared) = solo_columns(&patch_corners(36, 8, 4), 8);
        assert!(solo.iter().all(|&s| !s));
        assert_eq!(shared, [(0, 36)]);
        // The oracle: a column is alone when no pixel of it has another.
        for (n, p, s) in [(45, 8, 3), (45, 8, 8), (40, 8, 8), (23, 4, 4), (50, 5, 7)] {
            let px = patch_corners(n, p, s);
            let (solo, shared) = solo_columns(&px, p);
            let count = |x: usize| {
                px.iter()
                    .filter(|&&c| c as usize <= x && x < c as usize + p)
                    .count()
            };
            for (j, &c) in px.iter().enumerate() {
                let alone = (c as usize..c as usize + p).all(|x| count(x) == 1);
                assert_eq!(solo[j], alone, "{n} {p} {s} column {j}");
            }
            for x in 0..n {
                let in_shared = shared
                    .iter()
                    .any(|&(a, b)| a as usize <= x && x < b as usize);
                assert_eq!(
                    in_shared,
                    count(x) > 1
                        || px
                            .iter()
                            .enumerate()
                            .any(|(j, &c)| !solo[j] && c as usize <= x && x < c as usize + p),
                    "{n} {p} {s} pixel {x}"
                );
            }
        }
    }

    #[test]
    fn densify_row_matches_the_summed_row_bit_for_bit() {
        // `densify_row` (pixels of a lone patch straight to their value)
        // against `densify_row_sums`, its plain twin, called directly
        // (compiled for the baseline target), through `simd_arch` (the
        // detected instruction set) and through `Arch::Scalar` (the fallback
        // path). Strides equal to the patch (lone patches, exact and ragged
        // sizes) and smaller (shared pixels); vectors up to +-10 px, patches
        // inside and outside, some exactly zero or -0.0.
        let mut rnd = crate::flow::unit_stream(0x5851_f42d_4c95_7f2du64);
        for (w, h, psz, stride) in [
            (45usize, 23usize, 8usize, 3usize),
            (48, 24, 8, 8),
            (45, 23, 8, 8),
            (37, 21, 5, 5),
            (30, 19, 4, 3),
        ] {
            let px = patch_corners(w, psz, stride);
            let py = patch_corners(h, psz, stride);
            let (ilo, ihi) = coverage(h, psz, &py);
            let (solo, shared) = solo_columns(&px, psz);
            let ws = px.len();
            let i0: Vec<f32> = (0..w * h).map(|_| 255.0 * rnd()).collect();
            let i1: Vec<f32> = (0..w * h).map(|_| 255.0 * rnd()).collect();
            let vector = |r: f32, q: f32| match (4.0 * q) as usize {
                0 => 0.0,
                1 => -0.0,
                _ => 20.0 * r - 10.0,
            };
            let sx: Vec<f32> = (0..ws * py.len()).map(|_| vector(rnd(), rnd())).collect();
            let sy: Vec<f32> = (0..ws * py.len()).map(|_| vector(rnd(), rnd())).collect();
            let d = DenseRows {
                w,
                h,
                ws,
                psz,
                i0: &i0,
                i1: &i1,
                sx: &sx,
                sy: &sy,
                px: &px,
                ilo: &ilo,
                ihi: &ihi,
                solo: &solo,
                shared: &shared,
            };
            let bits = |a: &[f32]| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            for y in 0..h {
                let mut want: Vec<Vec<f32>> = (0..3).map(|_| vec![0.0f32; w]).collect();
                let [a, b, c] = want.get_disjoint_mut([0, 1, 2]).expect("distinct");
                densify_row_sums(&d, y, [a, b, c]);
                assert!(want[2].iter().all(|&s| s > 0.0), "every pixel covered");
                // Garbage in the buffers: the row must not read what it did
                // not write.
                let mut direct: Vec<Vec<f32>> = (0..3).map(|_| vec![f32::NAN; w]).collect();
                let [a, b, c] = direct.get_disjoint_mut([0, 1, 2]).expect("distinct");
                densify_row(&d, y, [a, b, c]);
                for k in 0..2 {
                    assert_eq!(
                        bits(&direct[k]),
                        bits(&want[k]),
                        "{w}x{h} row {y}, plane {k}"
                    );
                }
                for arch in [super::super::simd_arch(), pulp::Arch::Scalar] {
                    let mut got: Vec<Vec<f32>> = (0..3).map(|_| vec![7.0f32; w]).collect();
                    let [a, b, c] = got.get_disjoint_mut([0, 1, 2]).expect("distinct");
                    arch.dispatch(DensifyRowOp {
                        d: &d,
                        y,
                        out: [a, b, c],
                    });
                    for k in 0..2 {
                        assert_eq!(bits(&got[k]), bits(&want[k]), "{w}x{h} row {y}, plane {k}");
                    }
                }
            }
        }
    }

    #[test]
    fn dispatched_patch_kernel_matches_the_baseline_kernel_bit_for_bit() {
        // The oracle for the runtime SIMD dispatch: the kernel called directly here is
        // compiled for the baseline target; `accumulate8_lanes` runs it in the
        // instruction set `simd_arch` found (AVX2 on most x86-64), and the explicit
        // scalar-arch dispatch is the fallback path. Values spanning several orders of
        // magnitude, so that any reordering or FMA contraction would change the bits.
        let mut rnd = crate::flow::unit_stream(0x9e37_79b9_7f4a_7c15u64);
        for stride in [9usize, 13, 40] {
            for _ in 0..100 {
                let win: Vec<f32> = (0..8 * stride + 9)
                    .map(|_| 255.0 * rnd() * if rnd() < 0.1 { 1e3 } else { 1.0 })
                    .collect();
                let mut pd = Patch8::zeroed();
                for k in 0..64 {
                    pd.i0[k] = 255.0 * rnd();
                    pd.gx[k] = 2000.0 * rnd() - 1000.0;
                    pd.gy[k] = 2e-3 * rnd() - 1e-3;
                }
                let wts = [rnd(), rnd()];
                let direct = accumulate8_lanes_kernel(&win, stride, &pd, wts);
                let dispatched = accumulate8_lanes(&win, stride, &pd, wts);
                let op = Acc8Op {
                    win: &win,
                    stride,
                    pd: &pd,
                    wts,
                };
                let scalar = pulp::Arch::Scalar.dispatch(op);
                let bits = |a: [[f32; 4]; 4]| a.map(|l| l.map(f32::to_bits));
                assert_eq!(bits(dispatched), bits(direct));
                assert_eq!(bits(scalar), bits(direct));
            }
        }
    }

    #[test]
    fn batched_patch_kernel_matches_the_single_kernel_bit_for_bit() {
        // `accumulate8_lanes_n` (the candidates of a patch side by side) must
        // give each window exactly what `accumulate8_lanes` gives it alone,
        // on the dispatched and the scalar paths.
        let mut rnd = crate::flow::unit_stream(0x94d0_49bb_1331_11ebu64);
        for stride in [9usize, 17, 40] {
            for _ in 0..50 {
                let win: Vec<f32> = (0..12 * stride + 12)
                    .map(|_| 255.0 * rnd() * if rnd() < 0.1 { 1e3 } else { 1.0 })
                    .collect();
                let mut pd = Patch8::zeroed();
                for k in 0..64 {
                    pd.i0[k] = 255.0 * rnd();
                    pd.gx[k] = 2000.0 * rnd() - 1000.0;
                    pd.gy[k] = 2e-3 * rnd() - 1e-3;
                }
                let wins: [&[f32]; 4] = std::array::from_fn(|e| &win[e + (e % 3) * stride..]);
                let wts: [[f32; 2]; 4] = std::array::from_fn(|_| [rnd(), rnd()]);
                let single: [[[f32; 4]; 4]; 4] =
                    std::array::from_fn(|e| accumulate8_lanes(wins[e], stride, &pd, wts[e]));
                let bits = |a: [[f32; 4]; 4]| a.map(|l| l.map(f32::to_bits));
                let four = accumulate8_lanes_n::<4>(wins, stride, &pd, wts);
                let two =
                    accumulate8_lanes_n::<2>([wins[0], wins[1]], stride, &pd, [wts[0], wts[1]]);
                let op = Acc8NOp {
                    wins,
                    stride,
                    pd: &pd,
                    wts,
                };
                let scalar = pulp::Arch::Scalar.dispatch(op);
                for e in 0..4 {
                    assert_eq!(bits(four[e]), bits(single[e]));
                    assert_eq!(bits(scalar[e]), bits(single[e]));
                }
                for e in 0..2 {
                    assert_eq!(bits(two[e]), bits(single[e]));
                }
            }
        }
    }

    #[test]
    fn batched_evaluation_matches_one_at_a_time() {
        // `LevelView::eval_many` against `LevelView::eval`, windows inside,
        // across the edges and far outside, in groups of 1 to 4.
        let (w, h, psz) = (40usize, 30usize, 8usize);
        let mut rnd = crate::flow::unit_stream(0xd6e8_feb8_6659_fd93u64);
        let i0: Vec<f32> = (0..w * h).map(|_| 255.0 * rnd()).collect();
        let i1: Vec<f32> = (0..w * h).map(|_| 255.0 * rnd()).collect();
        let (mut gx, mut gy) = (vec![0.0; w * h], vec![0.0; w * h]);
        pyramid::sobel(&i0, w, h, 0.125, &mut gx, &mut gy).unwrap();
        for mean_norm in [false, true] {
            let view = LevelView {
                w,
                h,
                i0: &i0,
                gx: &gx,
                gy: &gy,
                i1: &i1,
                psz,
                mean_norm,
                lim: [(w - psz) as f32, (h - psz) as f32],
                n_px: (psz * psz) as f32,
            };
            for &(x0, y0) in &[(0usize, 0usize), (16, 11), (w - psz, h - psz), (3, h - psz)] {
                let pr = patch_ref(&gx, &gy, w, x0, y0, psz, mean_norm, 0.0);
                let pd = Patch8::from_planes([&i0, &gx, &gy], w, x0, y0);
                for _ in 0..40 {
                    let n = 1 + (4.0 * rnd()) as usize % 4;
                    let uv: Vec<(f32, f32)> = (0..n)
                        .map(|_| {
                            let s = if rnd() < 0.2 { 40.0 } else { 4.0 };
                            (s * (2.0 * rnd() - 1.0), s * (2.0 * rnd() - 1.0))
                        })
                        .collect();
                    let mut got = vec![Eval::default(); n];
                    view.eval_many(x0, y0, &pr, &pd, &uv, &mut got);
                    for (g, &(u, v)) in got.iter().zip(&uv) {
                        let want = view.eval(x0, y0, &pr, &pd, u, v);
                        let bits = |e: &Eval| [e.ssd, e.bx, e.by].map(f32::to_bits);
                        assert_eq!(bits(g), bits(&want), "{x0},{y0} {u},{v}");
                    }
                }
            }
        }
    }

    #[test]
    fn vectorised_densify_row_matches_the_per_pixel_row_bit_for_bit() {
        let mut rnd = crate::flow::unit_stream(0x2545_f491_4f6c_dd1du64);
        for _ in 0..200 {
            let top: Vec<f32> = (0..9).map(|_| 255.0 * rnd()).collect();
            let bot: Vec<f32> = (0..9).map(|_| 255.0 * rnd()).collect();
            let reference: Vec<f32> = (0..8).map(|_| 255.0 * rnd()).collect();
            let (ax, ay) = (rnd(), rnd());
            let (pu, pv) = (20.0 * rnd() - 10.0, 20.0 * rnd() - 10.0);
            // Non-zero sums to add to, as in a real row.
            let start: Vec<f32> = (0..8).map(|_| rnd()).collect();
            let (mut u1, mut v1, mut w1) = (start.clone(), start.clone(), start.clone());
            let (mut u2, mut v2, mut w2) = (start.clone(), start.clone(), start.clone());
            densify_patch_row8(
                [&top, &bot],
                &reference,
                [ax, ay],
                [pu, pv],
                [&mut u1, &mut v1, &mut w1],
            );
            densify_patch_row(
                8,
                [&top, &bot],
                &reference,
                [ax, ay],
                [pu, pv],
                [&mut u2, &mut v2, &mut w2],
            );
            let bits = |a: &[f32]| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&u1), bits(&u2));
            assert_eq!(bits(&v1), bits(&v2));
            assert_eq!(bits(&w1), bits(&w2));
        }
    }

    #[test]
    fn densification_matches_the_naive_weighted_average() {
        let mut dis = Dis::with_preset(DisPreset::Ultrafast);
        let (w, h) = (96usize, 64usize);
        let r = ndarray::Array2::from_shape_fn((h, w), |(y, x)| {
            100.0 + 50.0 * (0.2 * x as f32).sin() * (0.3 * y as f32).cos()
        });
        let c = r.mapv(|v| v + 0.5);
        dis.set_reference(&r).unwrap();
        dis.compute_native(&c).unwrap();
        let lvl = &dis.levels[0];
        let ws = lvl.ws();
        for y in 0..lvl.h {
            for x in 0..lvl.w {
                let (mut su, mut sv, mut sw) = (0.0f64, 0.0f64, 0.0f64);
                for (i, &py) in lvl.py.iter().enumerate() {
                    for (j, &px) in lvl.px.iter().enumerate() {
                        let (px, py) = (px as usize, py as usize);
                        if x < px || x >= px + 8 || y < py || y >= py + 8 {
                            continue;
                        }
                        let (pu, pv) = (lvl.sx[i * ws + j], lvl.sy[i * ws + j]);
                        let s = pyramid::sample_clamped(
                            &lvl.i1,
                            lvl.w,
                            lvl.h,
                            x as f32 + pu,
                            y as f32 + pv,
                        );
                        let wt = 1.0 / ((s - lvl.i0[y * lvl.w + x]).abs() as f64).max(1.0);
                        su += wt * pu as f64;
                        sv += wt * pv as f64;
                        sw += wt;
                    }
                }
                assert!((lvl.flow.u[[y, x]] as f64 - su / sw).abs() < 1e-5);
                assert!((lvl.flow.v[[y, x]] as f64 - sv / sw).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn opencv_coarsest_scale() {
        assert_eq!(Dis::auto_coarsest_scale(1920, 1080, 8), 6);
        assert_eq!(Dis::auto_coarsest_scale(1600, 240, 8), 4);
    }

    #[test]
    fn presets_parse_and_validate() {
        for p in DisPreset::ALL {
            assert_eq!(DisPreset::parse(p.name()).unwrap(), p);
            DisParams::preset(p).validate().unwrap();
        }
        assert!(DisPreset::parse("slow").is_err());
        let bad = DisParams {
            patch_stride: 9,
            ..DisParams::preset(DisPreset::Fast)
        };
        assert!(matches!(Dis::new(bad), Err(Error::InvalidParameter { .. })));
    }
}
