//! Confidence weights for the motion profiles (docs/pipeline.md, step 8).
//!
//! The along-arc profiles sum the flow over the strip's height, and a rod
//! pressed across the strip moves every row of a column much alike. Under a
//! strong press DIS goes wrong in places, in blocks of a patch or two: the
//! markers deform within a patch, and the contact shades the gel. Where it
//! does, the current frame warped back by the flow no longer matches the
//! reference. [`ProfileWeighting`] measures that mismatch per flow cell
//! (the absolute difference of the reference and the warped frame, summed
//! over a box about the size of a DIS patch), divides it by the
//! reference's texture over the same box (a bright marker's edge leaves a
//! larger difference for the same error than a flat stretch of gel), and
//! turns it into a weight `1 / (1 + (q / (k m))^2)`, where `q` is the
//! texture-normalised mismatch, `m` its median over the frame and `k`
//! [`CONFIDENCE_SCALE_OF_MEDIAN`]. Each column's profile is then the
//! weighted mean of its cells times the column's height
//! ([`ProfileWeighting::reweight_into`]): a cell the flow got wrong gives
//! way to the other rows of its column instead of adding its error. Only
//! the motion along the arc is reweighted: the across force read from the
//! plain sums across the strip reads the protocol's test points as well
//! (0.0037 N against 0.0039 N with both reweighted, on the simulator with
//! the `fine` flow), and everything else alike there (a second, noisier
//! simulated sensor read random presses less badly with both reweighted:
//! docs/results.md).
//!
//! Both the mismatch and the texture scale with the image's contrast, and
//! the median sets the scale of the weights, so they hardly change with the
//! exposure (the texture's floor, [`TEXTURE_FLOOR`], does not scale). A
//! column whose cells all weigh nothing keeps its plain motion.
//!
//! Measured on the simulated strip (docs/results.md, "Confidence-weighted
//! profiles"): DIS's error under a 2.8 N rod averages 0.48 px in the
//! contact's region against 0.11 px over the frame; in the fifth of its
//! boxes that match worst it is 0.83 px, in the rest 0.39 px. A calibration
//! fitted with the weights reads that sensor closer at the protocol's points
//! and between them; on a second simulated sensor with noisier frames only
//! at the points, and presses between them worse, so a calibration uses the
//! weights only when fitted with them
//! ([`crate::sensor::ExtractorConfig::weighted_profiles`]).

use ndarray::{Array2, ArrayView2, Zip};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::flow::FlowField;

/// Half-side of the box the mismatch and the texture are summed over,
/// full-resolution pixels: 4, a 9 x 9 box, about one DIS patch (8 px).
pub const CONFIDENCE_BOX_RADIUS_PX: usize = 4;

/// A cell's weight is `1 / (1 + (q / (k m))^2)` with `k` this, `q` its
/// texture-normalised mismatch and `m` the frame's median of it: a cell
/// matching three times worse than the median one weighs a half.
pub const CONFIDENCE_SCALE_OF_MEDIAN: f32 = 3.0;

/// Added to the texture (the reference's absolute central differences,
/// grey levels, summed over the box) before it divides the mismatch, so
/// that a flat stretch of gel does not divide by zero.
pub const TEXTURE_FLOOR: f32 = 1.0;

/// Per-cell confidence of a flow and the profile flow reweighted by it;
/// keeps the reference, its texture and its buffers from one frame to the
/// next.
#[derive(Debug, Clone, Default)]
pub struct ProfileWeighting {
    reference: Array2<f32>,
    /// The reference's texture summed over each cell's box, at
    /// `texture_scale` (0: not computed for this reference yet).
    texture: Array2<f32>,
    /// The reference at each cell's centre, at `texture_scale`.
    at_cells: Array2<f32>,
    texture_scale: usize,
    mismatch: Array2<f32>,
    /// Scratch of the box sums.
    spare: Array2<f32>,
    weights: Array2<f32>,
    /// Per column: its height over its summed weight (0: kept plain).
    gains: Vec<f64>,
    window: Vec<f32>,
    order: Vec<f32>,
}

impl ProfileWeighting {
    /// An empty weighting, without a reference.
    pub fn new() -> Self {
        Self::default()
    }

    /// The frame the flow is measured against (full resolution, as the
    /// flow saw it).
    pub fn set_reference(&mut self, reference: ArrayView2<'_, f32>) {
        self.reference = reference.as_standard_layout().into_owned();
        self.texture_scale = 0;
    }

    /// The weights of the last [`compute`](Self::compute), one per flow cell.
    pub fn weights(&self) -> ArrayView2<'_, f32> {
        self.weights.view()
    }

    /// The weight of every cell of `flow` (a grid of `scale` full-resolution
    /// pixels per cell, in full-resolution pixel units) from how well
    /// `current` warped back by it matches the reference (full-resolution
    /// frames of one size). A non-finite flow cell weighs nothing. Errors
    /// without a reference, on mismatched shapes, a zero scale or a flow
    /// grid larger than the frames allow.
    pub fn compute(
        &mut self,
        current: ArrayView2<'_, f32>,
        flow: &FlowField,
        scale: usize,
    ) -> Result<()> {
        if self.reference.is_empty() {
            return Err(Error::NoReference);
        }
        check_inputs(self.reference.view(), current, flow, scale)?;
        let (h, w) = flow.u.dim();
        if h == 0 || w == 0 {
            self.weights = Array2::zeros((h, w));
            return Ok(());
        }
        let radius = CONFIDENCE_BOX_RADIUS_PX.div_ceil(scale);
        let reference = Plane::of(&self.reference);
        if self.texture_scale != scale || self.texture.dim() != (h, w) {
            self.texture = Array2::zeros((h, w));
            self.at_cells = Array2::zeros((h, w));
            rows_of(&mut self.texture).for_each(|(i, row)| {
                for (j, t) in row.iter_mut().enumerate() {
                    let (x, y) = cell_centre(i, j, scale);
                    let gx = reference.at(x + 1.0, y) - reference.at(x - 1.0, y);
                    let gy = reference.at(x, y + 1.0) - reference.at(x, y - 1.0);
                    *t = 0.5 * (gx.abs() + gy.abs());
                }
            });
            rows_of(&mut self.at_cells).for_each(|(i, row)| {
                for (j, r) in row.iter_mut().enumerate() {
                    let (x, y) = cell_centre(i, j, scale);
                    *r = reference.at(x, y);
                }
            });
            box_sum_in_place(&mut self.texture, radius, &mut self.spare, &mut self.window);
            self.texture_scale = scale;
        }
        if self.mismatch.dim() != (h, w) {
            self.mismatch = Array2::zeros((h, w));
        }
        let current = current.as_standard_layout();
        let current = current.view();
        let current = Plane::of_view(&current);
        let (fu, fv, at_cells) = (flow.u.view(), flow.v.view(), self.at_cells.view());
        rows_of(&mut self.mismatch).for_each(|(i, row)| {
            let cells = row
                .iter_mut()
                .zip(fu.row(i))
                .zip(fv.row(i))
                .zip(at_cells.row(i));
            for (j, (((m, &u), &v), &r)) in cells.enumerate() {
                let (x, y) = cell_centre(i, j, scale);
                // A non-finite cell adds nothing to its neighbours' boxes
                // and weighs nothing itself (below).
                *m = if u.is_finite() && v.is_finite() {
                    (current.at(x + u, y + v) - r).abs()
                } else {
                    0.0
                };
            }
        });
        box_sum_in_place(
            &mut self.mismatch,
            radius,
            &mut self.spare,
            &mut self.window,
        );
        // The texture-normalised mismatch, then its median over the frame.
        Zip::from(&mut self.mismatch)
            .and(&self.texture)
            .for_each(|m, &t| *m /= t + TEXTURE_FLOOR);
        self.order.clear();
        self.order.extend(self.mismatch.iter().copied());
        let mid = self.order.len() / 2;
        let (_, &mut median, _) = self.order.select_nth_unstable_by(mid, f32::total_cmp);
        let unit = if median.is_finite() && median > 0.0 {
            CONFIDENCE_SCALE_OF_MEDIAN * median
        } else {
            // Nearly every cell matches exactly (or nothing does): the
            // weights cannot tell cells apart.
            f32::INFINITY
        };
        if self.weights.dim() != (h, w) {
            self.weights = Array2::zeros((h, w));
        }
        Zip::from(&mut self.weights)
            .and(&self.mismatch)
            .and(&flow.u)
            .and(&flow.v)
            .for_each(|wt, &q, &u, &v| {
                let r = q / unit;
                *wt = if !(u.is_finite() && v.is_finite()) {
                    0.0
                } else if r.is_finite() {
                    1.0 / (1.0 + r * r)
                } else {
                    1.0
                };
            });
        Ok(())
    }

    /// [`compute`](Self::compute), then `flow` into `out` with each cell's
    /// motion along x (along the arc) times its weight times its column's
    /// height over the column's summed weight: a column's sum over the rows
    /// is then the weighted mean of its cells times the height. A column
    /// whose cells all weigh nothing keeps its plain motion; a cell that
    /// weighs nothing elsewhere moves by 0. The motion along y (across the
    /// strip) is left as it is (module docs).
    pub fn reweight_into(
        &mut self,
        current: ArrayView2<'_, f32>,
        flow: &FlowField,
        scale: usize,
        out: &mut FlowField,
    ) -> Result<()> {
        self.compute(current, flow, scale)?;
        out.u = flow.u.as_standard_layout().into_owned();
        out.v = flow.v.as_standard_layout().into_owned();
        let (h, w) = flow.u.dim();
        // Per column: the height over the summed weight (0: keep the column).
        self.gains.clear();
        self.gains.resize(w, 0.0);
        for row in self.weights.rows() {
            for (t, &x) in self.gains.iter_mut().zip(row) {
                *t += f64::from(x);
            }
        }
        for t in self.gains.iter_mut() {
            *t = if *t > 0.0 { h as f64 / *t } else { 0.0 };
        }
        let (gains, weights) = (&self.gains, self.weights.view());
        rows_of(&mut out.u).for_each(|(i, row)| {
            for ((x, &wt), &g) in row.iter_mut().zip(weights.row(i)).zip(gains) {
                if g > 0.0 {
                    *x = if wt > 0.0 {
                        *x * (f64::from(wt) * g) as f32
                    } else {
                        0.0
                    };
                }
            }
        });
        Ok(())
    }
}

/// The rows of a grid this module allocated (standard layout), with their
/// indices, in parallel.
fn rows_of(a: &mut Array2<f32>) -> impl ParallelIterator<Item = (usize, &mut [f32])> {
    let w = a.ncols().max(1);
    a.as_slice_mut()
        .expect("grids allocated here are in standard layout")
        .par_chunks_mut(w)
        .enumerate()
}

/// The full-resolution pixel at the centre of flow cell `(i, j)` of a grid
/// of `scale` pixels a cell, as `(x, y)`.
fn cell_centre(i: usize, j: usize, scale: usize) -> (f32, f32) {
    let s = scale as f32;
    ((j as f32 + 0.5) * s - 0.5, (i as f32 + 0.5) * s - 0.5)
}

fn check_inputs(
    reference: ArrayView2<'_, f32>,
    current: ArrayView2<'_, f32>,
    flow: &FlowField,
    scale: usize,
) -> Result<()> {
    let wh = |a: ArrayView2<'_, f32>| (a.ncols(), a.nrows());
    if reference.dim() != current.dim() {
        return Err(Error::shape("current frame", wh(reference), wh(current)));
    }
    if flow.u.dim() != flow.v.dim() {
        return Err(Error::shape("flow v", wh(flow.u.view()), wh(flow.v.view())));
    }
    if scale == 0 {
        return Err(Error::param("scale", "must be at least 1"));
    }
    // The flow grid covers the frame at `scale` pixels a cell.
    let (rh, rw) = reference.dim();
    let (fh, fw) = flow.u.dim();
    if fw.saturating_mul(scale) > rw + scale || fh.saturating_mul(scale) > rh + scale {
        return Err(Error::shape(
            "flow grid (cells times scale)",
            (rw, rh),
            (fw.saturating_mul(scale), fh.saturating_mul(scale)),
        ));
    }
    if rw == 0 || rh == 0 {
        return Err(Error::TooSmall {
            what: "reference".into(),
            width: rw,
            height: rh,
            min_w: 1,
            min_h: 1,
        });
    }
    Ok(())
}

/// A standard-layout image as a slice, sampled by bilinear interpolation.
#[derive(Clone, Copy)]
struct Plane<'a> {
    data: &'a [f32],
    w: usize,
    h: usize,
}

impl<'a> Plane<'a> {
    fn of(a: &'a Array2<f32>) -> Self {
        Self::of_view(&a.view())
    }

    /// A standard-layout view (an empty plane otherwise, which samples as 0;
    /// the callers pass standard layouts).
    fn of_view(a: &ArrayView2<'a, f32>) -> Self {
        let (h, w) = a.dim();
        match a.to_slice() {
            Some(data) => Plane { data, w, h },
            None => Plane {
                data: &[],
                w: 0,
                h: 0,
            },
        }
    }

    /// The image at `(x, y)` by bilinear interpolation, the point clamped
    /// into the image (its border continues outwards).
    #[inline]
    fn at(&self, x: f32, y: f32) -> f32 {
        if self.w == 0 || self.h == 0 {
            return 0.0;
        }
        let x = x.clamp(0.0, (self.w - 1) as f32);
        let y = y.clamp(0.0, (self.h - 1) as f32);
        let (x0, y0) = (x as usize, y as usize);
        let (x1, y1) = ((x0 + 1).min(self.w - 1), (y0 + 1).min(self.h - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let (r0, r1) = (y0 * self.w, y1 * self.w);
        let d = self.data;
        let top = d[r0 + x0] * (1.0 - fx) + d[r0 + x1] * fx;
        let bottom = d[r1 + x0] * (1.0 - fx) + d[r1 + x1] * fx;
        top * (1.0 - fy) + bottom * fy
    }
}

/// Replaces every cell of `a` by the sum over the `(2 radius + 1)^2` box
/// about it, cells beyond the border counted as the border's: running
/// sums along each row into `spare`, then a running sum of `spare`'s rows
/// down the columns back into `a` (`window` is scratch).
fn box_sum_in_place(
    a: &mut Array2<f32>,
    radius: usize,
    spare: &mut Array2<f32>,
    window: &mut Vec<f32>,
) {
    let (h, w) = a.dim();
    if h == 0 || w == 0 {
        return;
    }
    if spare.dim() != (h, w) {
        *spare = Array2::zeros((h, w));
    }
    Zip::from(spare.rows_mut())
        .and(a.rows())
        .for_each(|mut out, row| box_sum_lane(row, out.view_mut(), radius));
    // Down the columns: `window` holds the sum of the rows in the box of
    // row i (indices clamped), moved one row at a time.
    let row = |k: i64| spare.row(k.clamp(0, h as i64 - 1) as usize);
    let r = radius as i64;
    window.clear();
    window.resize(w, 0.0);
    for k in -r..=r {
        window.iter_mut().zip(row(k)).for_each(|(s, &x)| *s += x);
    }
    for i in 0..h {
        a.row_mut(i)
            .iter_mut()
            .zip(window.iter())
            .for_each(|(o, &s)| *o = s);
        let (enter, leave) = (row(i as i64 + r + 1), row(i as i64 - r));
        for ((s, &e), &l) in window.iter_mut().zip(enter).zip(leave) {
            *s += e - l;
        }
    }
}

/// One row of [`box_sum_in_place`]: `out[j]` is the sum of `lane` over
/// `j - radius ..= j + radius`, indices clamped, by a running sum.
fn box_sum_lane(
    lane: ndarray::ArrayView1<'_, f32>,
    mut out: ndarray::ArrayViewMut1<'_, f32>,
    radius: usize,
) {
    let n = lane.len();
    if n == 0 {
        return;
    }
    let at = |k: i64| lane[k.clamp(0, n as i64 - 1) as usize];
    let r = radius as i64;
    let mut sum: f32 = (-r..=r).map(at).sum();
    for j in 0..n {
        out[j] = sum;
        let j = j as i64;
        sum += at(j + r + 1) - at(j - r);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The box sum written out: every cell of the box, indices clamped.
    fn box_sum_oracle(a: &Array2<f32>, radius: usize) -> Array2<f32> {
        let (h, w) = a.dim();
        let r = radius as i64;
        Array2::from_shape_fn((h, w), |(i, j)| {
            let mut s = 0.0f64;
            for di in -r..=r {
                for dj in -r..=r {
                    let ii = (i as i64 + di).clamp(0, h as i64 - 1) as usize;
                    let jj = (j as i64 + dj).clamp(0, w as i64 - 1) as usize;
                    s += f64::from(a[[ii, jj]]);
                }
            }
            s as f32
        })
    }

    /// A deterministic texture of bright blobs on a darker gel, 0-255.
    fn texture(h: usize, w: usize) -> Array2<f32> {
        Array2::from_shape_fn((h, w), |(i, j)| {
            let (x, y) = (j as f32, i as f32);
            let a = (0.9 * x + 0.4 * y).sin() * (0.7 * y - 0.3 * x).cos();
            let b = (0.23 * x * x.sqrt() + 0.5 * y).sin();
            120.0 + 60.0 * a + 40.0 * b
        })
    }

    /// `image` moved by whole pixels `(dx, dy)` (the border continues),
    /// plus a small deterministic noise of amplitude `noise`.
    fn moved(image: &Array2<f32>, dx: i64, dy: i64, noise: f32) -> Array2<f32> {
        let (h, w) = image.dim();
        Array2::from_shape_fn((h, w), |(i, j)| {
            let si = (i as i64 - dy).clamp(0, h as i64 - 1) as usize;
            let sj = (j as i64 - dx).clamp(0, w as i64 - 1) as usize;
            let k = (i * 7919 + j * 104_729) % 97;
            image[[si, sj]] + noise * (k as f32 / 48.0 - 1.0)
        })
    }

    fn uniform_flow(h: usize, w: usize, u: f32, v: f32) -> FlowField {
        FlowField {
            u: Array2::from_elem((h, w), u),
            v: Array2::from_elem((h, w), v),
        }
    }

    fn column_sums(a: &Array2<f32>) -> Vec<f64> {
        a.columns()
            .into_iter()
            .map(|c| c.iter().map(|&x| f64::from(x)).sum())
            .collect()
    }

    /// The weights of `flow` from `reference` to `current` (full
    /// resolution) and the flow reweighted by them.
    fn reweighted(
        reference: &Array2<f32>,
        current: &Array2<f32>,
        flow: &FlowField,
    ) -> (ProfileWeighting, FlowField) {
        let mut weighting = ProfileWeighting::new();
        let mut out = FlowField::zeros(0, 0);
        weighting.set_reference(reference.view());
        weighting
            .reweight_into(current.view(), flow, 1, &mut out)
            .unwrap();
        (weighting, out)
    }

    #[test]
    fn an_exact_flow_keeps_every_column_sum() {
        let r = texture(40, 60);
        let c = moved(&r, 3, -2, 0.0);
        let flow = uniform_flow(40, 60, 3.0, -2.0);
        let (weighting, out) = reweighted(&r, &c, &flow);
        assert!(weighting.weights().iter().all(|&w| w > 0.0 && w <= 1.0));
        for (a, b) in column_sums(&out.u).iter().zip(column_sums(&flow.u)) {
            assert!((a - b).abs() < 1e-3, "{a} against {b}");
        }
    }

    /// A block of the flow gone wrong under a press: the plain column sums
    /// carry its whole error, the weighted ones a fifth of it at most, and
    /// the columns it does not touch keep their sums; the motion across is
    /// left as it is.
    #[test]
    fn a_wrong_block_of_flow_gives_way_to_the_rest_of_its_column() {
        let (h, w) = (48, 80);
        let r = texture(h, w);
        let c = moved(&r, 3, 0, 1.5);
        let mut flow = uniform_flow(h, w, 3.0, 0.0);
        for i in 10..22 {
            for j in 30..42 {
                flow.u[[i, j]] = 4.5;
                flow.v[[i, j]] = -1.0;
            }
        }
        let (_, out) = reweighted(&r, &c, &flow);
        assert_eq!(out.v, flow.v, "the motion across is left as it is");
        let truth = 3.0 * h as f64;
        let plain = column_sums(&flow.u);
        let weighted = column_sums(&out.u);
        for j in 32..40 {
            let (p, q) = ((plain[j] - truth).abs(), (weighted[j] - truth).abs());
            assert!(
                p > 17.0 && q < 0.2 * p,
                "column {j}: plain {p}, weighted {q}"
            );
        }
        for j in (0..20).chain(52..w) {
            assert!(
                (weighted[j] - truth).abs() < 0.5,
                "column {j}: {}",
                weighted[j]
            );
        }
    }

    /// Twice the contrast and another black level change the weights
    /// hardly at all: the mismatch and the texture scale alike and the
    /// median sets the weights' scale.
    #[test]
    fn the_weights_hardly_change_with_the_exposure() {
        let (h, w) = (40, 64);
        let r = texture(h, w);
        let c = moved(&r, 2, 1, 2.0);
        let mut flow = uniform_flow(h, w, 2.0, 1.0);
        flow.u[[20, 30]] = 5.0;
        let mut a = ProfileWeighting::new();
        a.set_reference(r.view());
        a.compute(c.view(), &flow, 1).unwrap();
        let (r2, c2) = (r.mapv(|x| 0.5 * x + 10.0), c.mapv(|x| 0.5 * x + 10.0));
        let mut b = ProfileWeighting::new();
        b.set_reference(r2.view());
        b.compute(c2.view(), &flow, 1).unwrap();
        let worst = a
            .weights()
            .iter()
            .zip(b.weights().iter())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 0.05, "{worst}");
    }

    /// A coarser flow grid (2 px a cell) is weighed at its cells' centres.
    #[test]
    fn a_coarse_grid_is_weighed_at_its_cells() {
        let r = texture(40, 64);
        let c = moved(&r, 2, 0, 1.0);
        let mut flow = uniform_flow(20, 32, 2.0, 0.0);
        flow.u[[10, 16]] = 6.0;
        let mut weighting = ProfileWeighting::new();
        weighting.set_reference(r.view());
        weighting.compute(c.view(), &flow, 2).unwrap();
        let wts = weighting.weights();
        assert_eq!(wts.dim(), (20, 32));
        assert!(wts[[10, 16]] < 0.5 * wts[[2, 4]], "{wts:?}");
    }

    #[test]
    fn bad_inputs_are_errors_and_non_finite_cells_weigh_nothing() {
        let r = texture(20, 30);
        let flow = uniform_flow(20, 30, 0.0, 0.0);
        let mut weighting = ProfileWeighting::new();
        let mut out = FlowField::zeros(0, 0);
        // No reference yet.
        assert!(matches!(
            weighting.compute(r.view(), &flow, 1),
            Err(Error::NoReference)
        ));
        weighting.set_reference(r.view());
        let other = texture(20, 31);
        assert!(weighting.compute(other.view(), &flow, 1).is_err());
        assert!(weighting.compute(r.view(), &flow, 0).is_err());
        let big = uniform_flow(40, 30, 0.0, 0.0);
        assert!(weighting.compute(r.view(), &big, 1).is_err());
        let mismatched = FlowField {
            u: Array2::zeros((20, 30)),
            v: Array2::zeros((20, 29)),
        };
        assert!(weighting.compute(r.view(), &mismatched, 1).is_err());
        // An empty flow grid weighs nothing and keeps nothing.
        let none = uniform_flow(0, 0, 0.0, 0.0);
        weighting
            .reweight_into(r.view(), &none, 1, &mut out)
            .unwrap();
        assert_eq!(out.u.dim(), (0, 0));
        // An empty reference is no reference.
        let empty = Array2::<f32>::zeros((0, 0));
        weighting.set_reference(empty.view());
        assert!(weighting.compute(empty.view(), &none, 1).is_err());
        // A non-finite cell weighs nothing and moves by 0; its column's
        // other cells carry the column.
        let c = moved(&r, 1, 0, 1.0);
        let mut flow = uniform_flow(20, 30, 1.0, 0.0);
        flow.u[[5, 7]] = f32::NAN;
        weighting.set_reference(r.view());
        weighting
            .reweight_into(c.view(), &flow, 1, &mut out)
            .unwrap();
        assert_eq!(weighting.weights()[[5, 7]], 0.0);
        assert_eq!(out.u[[5, 7]], 0.0);
        // Its row's other cells keep their weights (but at the right
        // border, where the moved frame has no match for the last column).
        let row: Vec<f32> = weighting.weights().row(5).to_vec();
        assert!(row.iter().filter(|&&w| w > 0.5).count() >= 20, "{row:?}");
        let sum: f32 = out.u.column(7).sum();
        assert!(sum.is_finite() && (sum - 20.0).abs() < 1.0, "{sum}");
    }

    proptest! {
        #![proptest_config(proptest::test_runner::Config {
            cases: 48,
            rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
            rng_seed: proptest::test_runner::RngSeed::Fixed(11),
            failure_persistence: None,
            ..proptest::test_runner::Config::default()
        })]

        #[test]
        fn the_box_sum_matches_its_oracle(
            h in 1usize..14,
            w in 1usize..14,
            radius in 0usize..6,
            seed in any::<u64>(),
        ) {
            let mut state = seed | 1;
            let a = Array2::from_shape_fn((h, w), |_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state % 1000) as f32 / 10.0
            });
            let mut fast = a.clone();
            box_sum_in_place(&mut fast, radius, &mut Array2::zeros((0, 0)), &mut Vec::new());
            let slow = box_sum_oracle(&a, radius);
            for (x, y) in fast.iter().zip(slow.iter()) {
                prop_assert!((x - y).abs() <= 1e-3 * (1.0 + y.abs()), "{x} against {y}");
            }
        }
    }
}
