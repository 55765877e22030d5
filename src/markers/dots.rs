//! The dots of a regular marker grid, followed one by one.
//!
//! On a GelSight-class sensor the gel between the dots is plain: the dense
//! optical flow only sees the dots, and fills the gel between them from its
//! coarser levels. What the forces need is each dot's motion, measured
//! precisely. [`DotTracker`] finds the dots of the reference once (the
//! connected regions of strong contrast against the local background, each
//! refined to its contrast-weighted centre; dark dots' contrast relative to
//! the local light, so that uneven lighting does not hide them), and in
//! every frame starts each dot where the flow moved it and moves it to the
//! centre of its contrast there (a mean shift). Under a small indenter pressed hard the flow can
//! lead a dot onto its neighbour or lose it: a dot found where another one
//! is, or moved unlike its neighbours, or not found, is looked for again
//! about its neighbours' median motion, and taken where no neighbour holds
//! a dot. The dots' motion then replaces the flow around them, spread by a
//! Gaussian of [`SPREAD_OF_PITCH`] pitch.
//!
//! Measured on the simulated fingertip sensor (docs/results.md, "A flat
//! fingertip sensor"): the flow at the dots is within a few hundredths of a
//! pixel of the simulator's, but its errors follow the load and the dot's
//! place under the contact, which no map can take out; with the dots
//! followed, the location error halves, and the held-out points' forces
//! come 3 (Fx) and 2 (Fy) times closer than with the flow alone.
//!
//! In every frame a dot's contrast is read against that frame's own local
//! light (its mean over one pitch), so that a contact under which the gel
//! turns darker or brighter (its shading under the lights, or an object
//! seen through a thin gel) does not count the plain gel about a dot as
//! part of it. The frame should still be in the reference's exposure (the
//! extractor compensates it first): dark dots' contrast is scaled to grey
//! levels of the reference's mean light.

use crate::error::{Error, Result};
use crate::exposure::median;
use crate::flow::{FlowField, sample_clamped};
use crate::frame::{Roi, box_mean_into};
use crate::markers::centre::motion_centre;
use ndarray::{Array2, ArrayRef2};

/// Radius, in pitches, of the window over which a dot's centre is taken:
/// its own contrast, not its neighbours' (half a pitch away at the least).
pub const SEARCH_RADIUS_OF_PITCH: f64 = 0.35;

/// Standard deviation, in pitches, of the Gaussian that spreads the dots'
/// motion over the flow grid.
pub const SPREAD_OF_PITCH: f64 = 0.3;

/// A reference pixel belongs to a dot when its contrast reaches this
/// fraction of the reference's strong contrast (its 99.5th percentile).
const DETECT_FRACTION: f32 = 0.5;

/// Contrast below this fraction of the reference's strong contrast weighs
/// nothing in a dot's centre: the camera's noise around the dot would
/// otherwise pull the centre towards the middle of the window.
const FLOOR_FRACTION: f32 = 0.15;

/// Percentile of the reference's contrast taken as its strong contrast.
const STRONG_PERCENTILE: f64 = 0.995;

/// Mean-shift steps per dot at the most, and the step (px) below which the
/// centre has settled.
const MAX_STEPS: usize = 8;
const SETTLED_PX: f64 = 0.01;

/// Dots whose reference centres lie within this many pitches of each other
/// are neighbours: a dot's own row and column and its diagonals.
const NEIGHBOUR_OF_PITCH: f64 = 1.5;

/// Two dots whose centres, followed, come within this many pitches of each
/// other have found the same dot: a neighbour cannot come that close
/// without the gel's strain reaching 75%.
const SAME_DOT_OF_PITCH: f64 = 0.25;

/// A dot whose motion differs from its neighbours' median motion by more
/// than this many pitches may have jumped onto another dot, and is looked
/// for again.
const JUMP_OF_PITCH: f64 = 0.5;

/// A dot looked for again is taken where its motion differs from its
/// neighbours' median motion by at most this many pitches: under a small
/// indenter the motion of neighbouring dots differs by more than half a
/// pitch.
const FOUND_AGAIN_OF_PITCH: f64 = 0.75;

/// Margin, px, beyond a dot's half-contrast radius of the window its centre
/// is settled in: its blurred edge, but not a neighbour that the gel's
/// strain brought close (within the search window, it would pull the
/// centre towards itself).
const EDGE_MARGIN_PX: f64 = 2.0;

/// Passes of looking for strayed dots again at the most: each pass can
/// mend the edge of a region the flow moved by a whole pitch, whose dots
/// agree with each other.
const MEND_PASSES: usize = 4;

/// Starts on a ring about a lost dot's expected place from which it is
/// looked for again.
const RING_STARTS: usize = 8;

/// Below this total weight a flow cell keeps the optical flow's motion.
const MIN_SPREAD_WEIGHT: f64 = 1e-3;

/// Smallest pitch, px, of a grid whose dots are followed: below it a dot
/// spans too few pixels for its centre to mean much.
pub const MIN_PITCH_PX: f64 = 6.0;

/// Largest pitch, px: the background is a box of one pitch a side.
pub const MAX_PITCH_PX: f64 = 200.0;

/// Follows the dots of a regular marker grid from frame to frame
/// ([module docs](self)).
#[derive(Debug, Clone, Default)]
pub struct DotTracker {
    pitch: f64,
    /// How a pixel's contrast against the background is read.
    contrast: Contrast,
    /// The reference's local background (mean over one pitch).
    background: Array2<f32>,
    /// The local background a dot's contrast is read against in the image
    /// being read: the reference's while its dots are found, each frame's
    /// own (the same mean over one pitch) while they are followed.
    light: Array2<f32>,
    /// The running sums `light` is computed with (kept between frames).
    table: Vec<f64>,
    floor: f32,
    /// Radius, px, of the window a dot's centre is settled in at last (its
    /// own contrast only), at most the search window's.
    inner: f64,
    dots: Vec<[f64; 2]>,
    /// Each dot's neighbours (indices into `dots`), within
    /// [`NEIGHBOUR_OF_PITCH`] in the reference.
    neighbours: Vec<Vec<u32>>,
    moved: Vec<Option<[f64; 2]>>,
    /// Per flow cell: sum of weights, of weighted u and of weighted v.
    spread: Vec<[f64; 3]>,
}

impl DotTracker {
    /// A tracker without a reference (it changes no flow).
    pub fn new() -> Self {
        Self::default()
    }

    /// Forgets the reference: [`DotTracker::refine`] then changes nothing.
    pub fn clear(&mut self) {
        self.dots.clear();
        self.neighbours.clear();
        self.moved.clear();
        self.background = Array2::zeros((0, 0));
        self.light = Array2::zeros((0, 0));
    }

    /// Whether a reference with dots is set.
    pub fn is_active(&self) -> bool {
        !self.dots.is_empty()
    }

    /// The dots' centres in the reference, `[x, y]` in pixels.
    pub fn dots(&self) -> &[[f64; 2]] {
        &self.dots
    }

    /// Each dot's motion in the last [`DotTracker::refine`], `[u, v]` in
    /// full-resolution pixels; `None` where the dot was lost (its window
    /// held no contrast, or its centre left the image).
    pub fn displacements(&self) -> &[Option<[f64; 2]>] {
        &self.moved
    }

    /// Whether a dot whose reference centre lies in `region` was lost in
    /// the last [`DotTracker::refine`] (its window held no contrast, or its
    /// centre left the image); false without a reference.
    ///
    /// Why: a dot is lost where the flow led its window astray and it was
    /// not found again, or where dots crowded onto one another; the
    /// others in its region may then have been matched to a neighbour too.
    /// On the characterizations of two simulated fingertip sensors, among
    /// the tests that moved by half a pitch up to two thirds of it, every
    /// test with a dot more than 3 px off its true motion (matched to a
    /// neighbour) also had a dot lost in the contact's box, but for two
    /// tests on the 18 px grid ([`crate::sensor::FOLLOWED_PITCH_FRACTION`]).
    pub fn lost_in(&self, region: Roi) -> bool {
        self.dots
            .iter()
            .zip(&self.moved)
            .any(|(c, m)| m.is_none() && region.holds(*c))
    }

    /// The point where the lines along the dots' last motion meet, for
    /// contact `k` of `starts` (every contact's current point) within
    /// `region` (its box), at most one pitch from `starts[k]`; see
    /// [`crate::markers::centre::motion_centre`]. `None` when the tracker
    /// has no reference or the lines do not give a point.
    pub fn motion_centre(&self, region: Roi, starts: &[[f64; 2]], k: usize) -> Option<[f64; 2]> {
        if !self.is_active() {
            return None;
        }
        motion_centre(&self.dots, &self.moved, region, starts, k, self.pitch)
    }

    /// Finds the dots of `reference`, a grid of `pitch_px` pixels (from
    /// [`crate::markers::grid_pitch`]); returns how many. Dark dots on a
    /// bright gel or bright dots on a dark one, whichever contrasts more. A
    /// dot is kept when its region is at least 3 pixels and at most a
    /// third of a pitch squared, and no other strong region (a neighbour,
    /// the edge of the gel) reaches into its window. Errors on a pitch
    /// outside [`MIN_PITCH_PX`]`..=`[`MAX_PITCH_PX`] or a non-finite pixel;
    /// an image without dots gives 0 and an inactive tracker.
    pub fn set_reference(&mut self, reference: &ArrayRef2<f32>, pitch_px: f64) -> Result<usize> {
        self.clear();
        if !(MIN_PITCH_PX..=MAX_PITCH_PX).contains(&pitch_px) {
            return Err(Error::param(
                "pitch_px",
                format!("{pitch_px}: the dots' pitch must be {MIN_PITCH_PX}-{MAX_PITCH_PX} px"),
            ));
        }
        if reference.iter().any(|v| !v.is_finite()) {
            return Err(Error::param("reference", "non-finite pixel"));
        }
        let (h, w) = reference.dim();
        if h < 3 || w < 3 {
            return Ok(0);
        }
        self.pitch = pitch_px;
        let mut background = Array2::zeros((0, 0));
        box_mean_into(
            reference,
            (pitch_px * 0.5) as usize,
            &mut self.table,
            &mut background,
        );
        self.light.clone_from(&background);
        self.background = background;
        // Polarity: the stronger of the dark and the bright contrast.
        let absolute = |dark| Contrast { dark, light: None };
        let dark = strong(reference, &self.background, absolute(true));
        let bright = strong(reference, &self.background, absolute(false));
        self.contrast = if dark >= bright {
            // Dark dots take a fraction of the light where they sit: read
            // against the local light, they contrast alike under uneven
            // lighting (in grey levels of the mean light).
            let mean = self.background.iter().map(|&v| f64::from(v)).sum::<f64>()
                / self.background.len() as f64;
            Contrast {
                dark: true,
                light: Some(mean as f32),
            }
        } else {
            absolute(false)
        };
        let top = strong(reference, &self.background, self.contrast);
        if top <= 0.0 {
            self.clear();
            return Ok(0);
        }
        let threshold = DETECT_FRACTION * top;
        self.floor = FLOOR_FRACTION * top;
        let contrast =
            |i: usize, j: usize| self.contrast.at(self.background[[i, j]], reference[[i, j]]);
        // Connected regions (4-neighbours) of strong contrast.
        let mut label = Array2::<u32>::zeros((h, w));
        let mut regions: Vec<(usize, f64, f64)> = Vec::new();
        let mut stack = Vec::new();
        for i in 0..h {
            for j in 0..w {
                if label[[i, j]] != 0 || contrast(i, j) <= threshold {
                    continue;
                }
                let id = regions.len() as u32 + 1;
                label[[i, j]] = id;
                stack.push((i, j));
                let (mut n, mut sx, mut sy) = (0usize, 0.0, 0.0);
                while let Some((a, b)) = stack.pop() {
                    n += 1;
                    sx += b as f64;
                    sy += a as f64;
                    let near = [
                        (a.wrapping_sub(1), b),
                        (a + 1, b),
                        (a, b.wrapping_sub(1)),
                        (a, b + 1),
                    ];
                    for (na, nb) in near {
                        if na < h && nb < w && label[[na, nb]] == 0 && contrast(na, nb) > threshold
                        {
                            label[[na, nb]] = id;
                            stack.push((na, nb));
                        }
                    }
                }
                regions.push((n, sx / n as f64, sy / n as f64));
            }
        }
        let radius = SEARCH_RADIUS_OF_PITCH * pitch_px;
        let max_area = pitch_px * pitch_px / 3.0;
        // A dot's own window: its typical half-contrast radius and a margin
        // for its blurred edge.
        let mut sizes: Vec<f64> = regions
            .iter()
            .map(|r| r.0 as f64)
            .filter(|&n| n >= 3.0 && n <= max_area)
            .collect();
        self.inner =
            median(&mut sizes).map_or(0.0, |n| (n / std::f64::consts::PI).sqrt() + EDGE_MARGIN_PX);
        for (k, &(n, x, y)) in regions.iter().enumerate() {
            if n < 3 || n as f64 > max_area {
                continue;
            }
            let Some(c) = self.centre(reference, [x, y], radius) else {
                continue;
            };
            let own = k as u32 + 1;
            let intruded = window(c, radius, h, w).any(|(i, j)| {
                let l = label[[i, j]];
                l != 0 && l != own
            });
            if !intruded {
                self.dots.push(c);
            }
        }
        if self.dots.is_empty() {
            self.clear();
        }
        self.neighbours = within(&self.dots, NEIGHBOUR_OF_PITCH * pitch_px);
        Ok(self.dots.len())
    }

    /// Follows every dot into `frame` (the reference's size and exposure)
    /// from where `flow` moves it, and writes the dots' motion over
    /// `flow`: every cell within three spreads of a followed dot takes the
    /// Gaussian-weighted mean of the dots' motion about it; the others keep
    /// the flow. `flow` is on a grid of `scale` full-resolution pixels per
    /// cell, in its own cells' units (as DIS's native flow). Does nothing
    /// without a reference. Errors on a frame of another size than the
    /// reference or a flow grid that does not cover it at `scale`.
    pub fn refine(
        &mut self,
        frame: &ArrayRef2<f32>,
        flow: &mut FlowField,
        scale: usize,
    ) -> Result<()> {
        if !self.is_active() {
            return Ok(());
        }
        let (h, w) = self.background.dim();
        if frame.dim() != (h, w) {
            return Err(Error::shape(
                "frame against the dots' reference",
                (w, h),
                (frame.dim().1, frame.dim().0),
            ));
        }
        let (fh, fw) = flow.u.dim();
        let s = scale.max(1);
        if flow.v.dim() != (fh, fw) || fh * s < h || fw * s < w || fh == 0 || fw == 0 {
            return Err(Error::param(
                "flow",
                format!("a {fw}x{fh} flow at scale {s} does not cover a {w}x{h} frame"),
            ));
        }
        let radius = SEARCH_RADIUS_OF_PITCH * self.pitch;
        // Each dot's contrast against the frame's own local light: where
        // the gel under a contact turns darker or brighter (its shading, an
        // object seen through it), the reference's light would count the
        // plain gel about a dot as part of it.
        box_mean_into(
            frame,
            (self.pitch * 0.5) as usize,
            &mut self.table,
            &mut self.light,
        );
        let sf = s as f64;
        // The flow's cells in row-major order (a copy only for a flow laid
        // out otherwise).
        let (layout_u, layout_v) = (flow.u.as_standard_layout(), flow.v.as_standard_layout());
        let cells_u = layout_u.as_slice().unwrap_or_default();
        let cells_v = layout_v.as_slice().unwrap_or_default();
        let mut moved = std::mem::take(&mut self.moved);
        moved.clear();
        for &[x0, y0] in &self.dots {
            // The flow's cell coordinates of the dot, and its motion there.
            let (gx, gy) = (
                ((x0 + 0.5) / sf - 0.5) as f32,
                ((y0 + 0.5) / sf - 0.5) as f32,
            );
            let at = |c: &[f32]| f64::from(sample_clamped(c, fw, fh, gx, gy));
            let start = [x0 + sf * at(cells_u), y0 + sf * at(cells_v)];
            // No bound on how far the centre moves from the flow's guess:
            // where the flow lost a dot under strong strain, the dot's own
            // contrast still draws the window onto it (bounding the move by
            // the window's radius lost more than it caught on the
            // simulated fingertip sensor: random presses' Fy 0.116 -> 0.158 N).
            let found = self.centre(frame, start, radius);
            moved.push(found.map(|c| [c[0] - x0, c[1] - y0]));
        }
        self.moved = moved;
        // A region the flow moved by a whole pitch is mended from its edge
        // inwards, a ring of dots per pass.
        for _ in 0..MEND_PASSES {
            if !self.mend_jumps(frame, radius) {
                break;
            }
        }
        // Spread the dots' motion over the flow's cells.
        let sigma = SPREAD_OF_PITCH * self.pitch;
        let reach = 3.0 * sigma;
        self.spread.clear();
        self.spread.resize(fh * fw, [0.0; 3]);
        // The Gaussian is separable: one row of weights per axis per dot.
        let (mut gx, mut gy) = (Vec::new(), Vec::new());
        let offsets = |lo: usize, hi: usize, c: f64, out: &mut Vec<(f64, f64)>| {
            out.clear();
            out.extend((lo..hi).map(|k| {
                let o = (k as f64 + 0.5) * sf - 0.5 - c;
                (o * o, (-0.5 * o * o / (sigma * sigma)).exp())
            }));
        };
        for (&[x0, y0], d) in self.dots.iter().zip(&self.moved) {
            let Some([du, dv]) = *d else { continue };
            let (j0, j1) = cell_range(x0, reach, sf, fw);
            let (i0, i1) = cell_range(y0, reach, sf, fh);
            offsets(j0, j1, x0, &mut gx);
            offsets(i0, i1, y0, &mut gy);
            for (i, &(dy2, wy)) in (i0..i1).zip(&gy) {
                let row = &mut self.spread[i * fw + j0..i * fw + j1];
                for (a, &(dx2, wx)) in row.iter_mut().zip(&gx) {
                    if dx2 + dy2 > reach * reach {
                        continue;
                    }
                    let wt = wx * wy;
                    a[0] += wt;
                    a[1] += wt * du;
                    a[2] += wt * dv;
                }
            }
        }
        for ((a, u), v) in self
            .spread
            .iter()
            .zip(flow.u.iter_mut())
            .zip(flow.v.iter_mut())
        {
            if a[0] >= MIN_SPREAD_WEIGHT {
                *u = (a[1] / a[0] / sf) as f32;
                *v = (a[2] / a[0] / sf) as f32;
            }
        }
        Ok(())
    }

    /// Where the flow led a dot onto another one (two dots at one place, or
    /// a dot moved unlike its neighbours) or lost it, looks for it again
    /// about its neighbours' median motion; a dot that still does not fit
    /// is lost. Returns whether any dot's motion changed.
    fn mend_jumps(&mut self, frame: &ArrayRef2<f32>, radius: f64) -> bool {
        let before = self.moved.clone();
        let n_dots = self.dots.len();
        let same = SAME_DOT_OF_PITCH * self.pitch;
        let mut suspect: Vec<bool> = self.moved.iter().map(Option::is_none).collect();
        for k in 0..n_dots {
            let Some(d) = self.moved[k] else { continue };
            let p = self.at(k, d);
            for &n in &self.neighbours[k] {
                let Some(e) = self.moved[n as usize] else {
                    continue;
                };
                // Of two dots at one place, the one that moved farther is
                // the one that left its own.
                if dist(p, self.at(n as usize, e)) < same && norm(d) >= norm(e) {
                    suspect[k] = true;
                }
            }
            if let Some(m) = self.neighbours_median(k, &suspect)
                && dist(d, m) > JUMP_OF_PITCH * self.pitch
            {
                suspect[k] = true;
            }
        }
        // Where the suspects were first found stays a place to look.
        let first: Vec<Option<[f64; 2]>> = (0..n_dots)
            .map(|k| self.moved[k].filter(|_| suspect[k]))
            .collect();
        for (d, &s) in self.moved.iter_mut().zip(&suspect) {
            if s {
                *d = None;
            }
        }
        // One suspect at a time, each found one trusted by those after it.
        for k in 0..n_dots {
            if !suspect[k] {
                continue;
            }
            let Some(m) = self.neighbours_median(k, &suspect) else {
                continue;
            };
            let [x0, y0] = self.dots[k];
            let guess = [x0 + m[0], y0 + m[1]];
            // From the neighbours' motion, from rest, and from a ring about
            // the neighbours' motion: of the dots found there that no
            // neighbour holds, the one that moved most like its neighbours.
            let ring = (0..RING_STARTS).map(|a| {
                let t = std::f64::consts::TAU * a as f64 / RING_STARTS as f64;
                [guess[0] + radius * t.cos(), guess[1] + radius * t.sin()]
            });
            let starts = [guess, [x0, y0]].into_iter().chain(ring);
            let best = starts
                .filter_map(|start| self.centre(frame, start, radius))
                .map(|c| [c[0] - x0, c[1] - y0])
                .chain(first[k])
                .filter(|&d| {
                    let c = self.at(k, d);
                    !self.neighbours[k].iter().any(|&n| {
                        let n = n as usize;
                        self.moved[n].is_some_and(|e| dist(c, self.at(n, e)) < same)
                    })
                })
                .map(|d| (dist(d, m), d))
                .filter(|&(off, _)| off <= FOUND_AGAIN_OF_PITCH * self.pitch)
                .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((_, d)) = best {
                self.moved[k] = Some(d);
                suspect[k] = false;
            }
        }
        self.moved != before
    }

    /// Where dot `k` is when moved by `d`.
    fn at(&self, k: usize, d: [f64; 2]) -> [f64; 2] {
        [self.dots[k][0] + d[0], self.dots[k][1] + d[1]]
    }

    /// The component-wise median motion of dot `k`'s followed neighbours
    /// that are not `suspect`; `None` without any.
    fn neighbours_median(&self, k: usize, suspect: &[bool]) -> Option<[f64; 2]> {
        let (mut u, mut v): (Vec<f64>, Vec<f64>) = self.neighbours[k]
            .iter()
            .filter(|&&n| !suspect[n as usize])
            .filter_map(|&n| self.moved[n as usize])
            .map(|d| (d[0], d[1]))
            .unzip();
        Some([median(&mut u)?, median(&mut v)?])
    }

    /// The contrast-weighted centre of the dot near `start` in `image`
    /// (mean shift over the dot's own window, or where that holds nothing
    /// over a disc of `radius` first), against the local light of the image
    /// being read (`light`); `None` when no window holds contrast above the
    /// floor or the centre leaves the image.
    fn centre(&self, image: &ArrayRef2<f32>, start: [f64; 2], radius: f64) -> Option<[f64; 2]> {
        if !(self.inner > 0.0 && self.inner < radius) {
            return self.mean_shift(image, start, radius);
        }
        // The dot's own window first; the search window only when that
        // holds nothing, then the dot's own window again.
        self.mean_shift(image, start, self.inner).or_else(|| {
            let c = self.mean_shift(image, start, radius)?;
            self.mean_shift(image, c, self.inner)
        })
    }

    /// Mean shift from `start` over a disc of `radius` to the centre of
    /// the contrast within it ([`DotTracker::centre`]).
    fn mean_shift(&self, image: &ArrayRef2<f32>, start: [f64; 2], radius: f64) -> Option<[f64; 2]> {
        let (h, w) = image.dim();
        let [mut x, mut y] = start;
        for _ in 0..MAX_STEPS {
            if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64) {
                return None;
            }
            let (mut sw, mut sx, mut sy) = (0.0f64, 0.0f64, 0.0f64);
            // The pixels of `window`, in its order, a row at a time.
            let ((i0, i1), (j0, j1)) = window_box([x, y], radius, h, w);
            for i in i0..i1 {
                let dy = i as f64 - y;
                let (bg, im) = (self.light.row(i), image.row(i));
                for j in j0..j1 {
                    let dx = j as f64 - x;
                    if dx * dx + dy * dy > radius * radius {
                        continue;
                    }
                    let c = self.contrast.at(bg[j], im[j]) - self.floor;
                    if c > 0.0 {
                        let c = f64::from(c);
                        sw += c;
                        sx += c * j as f64;
                        sy += c * i as f64;
                    }
                }
            }
            if sw <= 0.0 {
                return None;
            }
            let (nx, ny) = (sx / sw, sy / sw);
            let step = (nx - x).hypot(ny - y);
            (x, y) = (nx, ny);
            if step < SETTLED_PX {
                break;
            }
        }
        Some([x, y])
    }
}

/// The distance between two points (or the difference of two motions).
fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// The length of a motion.
fn norm(d: [f64; 2]) -> f64 {
    d[0].hypot(d[1])
}

/// For each point, the other points within `reach` of it (by buckets of
/// `reach` a side).
fn within(points: &[[f64; 2]], reach: f64) -> Vec<Vec<u32>> {
    let key = |p: [f64; 2]| ((p[0] / reach).floor() as i64, (p[1] / reach).floor() as i64);
    let mut buckets: std::collections::HashMap<(i64, i64), Vec<u32>> = Default::default();
    for (k, &p) in points.iter().enumerate() {
        buckets.entry(key(p)).or_default().push(k as u32);
    }
    points
        .iter()
        .enumerate()
        .map(|(k, &p)| {
            let (bx, by) = key(p);
            let mut near = Vec::new();
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for &n in buckets.get(&(bx + dx, by + dy)).into_iter().flatten() {
                        let q = points[n as usize];
                        if n as usize != k && dist(p, q) <= reach {
                            near.push(n);
                        }
                    }
                }
            }
            near.sort_unstable();
            near
        })
        .collect()
}

/// The rows `i0..i1` and columns `j0..j1` of an `h x w` image whose pixels
/// may lie within `radius` of `c`.
fn window_box(c: [f64; 2], radius: f64, h: usize, w: usize) -> ((usize, usize), (usize, usize)) {
    let i0 = (c[1] - radius).ceil().max(0.0) as usize;
    let i1 = ((c[1] + radius).floor().max(-1.0) + 1.0).min(h as f64) as usize;
    let j0 = (c[0] - radius).ceil().max(0.0) as usize;
    let j1 = ((c[0] + radius).floor().max(-1.0) + 1.0).min(w as f64) as usize;
    ((i0, i1), (j0, j1))
}

/// The pixels `(row, column)` of `image` (`h x w`) within `radius` of `c`.
fn window(c: [f64; 2], radius: f64, h: usize, w: usize) -> impl Iterator<Item = (usize, usize)> {
    let ((i0, i1), (j0, j1)) = window_box(c, radius, h, w);
    (i0..i1).flat_map(move |i| {
        (j0..j1).filter_map(move |j| {
            let (dx, dy) = (j as f64 - c[0], i as f64 - c[1]);
            (dx * dx + dy * dy <= radius * radius).then_some((i, j))
        })
    })
}

/// The cells `lo..hi` (of `n`, `scale` px each) whose centres may lie
/// within `reach` of pixel coordinate `c`.
fn cell_range(c: f64, reach: f64, scale: f64, n: usize) -> (usize, usize) {
    let lo = (((c - reach + 0.5) / scale) - 0.5).floor().max(0.0) as usize;
    let hi = ((((c + reach + 0.5) / scale) - 0.5).ceil() + 1.0).clamp(0.0, n as f64) as usize;
    (lo.min(n), hi)
}

/// How a pixel's contrast against its background is read: darker or
/// brighter than it, in grey levels, or for dark dots relative to the local
/// light (`light`: the mean light, which scales it back to grey levels).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Contrast {
    dark: bool,
    light: Option<f32>,
}

impl Contrast {
    /// The contrast of a pixel of value `v` on background `bg`.
    fn at(self, bg: f32, v: f32) -> f32 {
        match (self.dark, self.light) {
            (true, Some(mean)) => (bg - v) * mean / bg.max(0.1 * mean),
            (true, None) => bg - v,
            (false, _) => v - bg,
        }
    }
}

/// The strong contrast of `image` against `background` read by
/// `contrast`: its [`STRONG_PERCENTILE`] (0 when not positive).
fn strong(image: &ArrayRef2<f32>, background: &Array2<f32>, contrast: Contrast) -> f32 {
    let mut v: Vec<f32> = image
        .iter()
        .zip(background.iter())
        .map(|(i, b)| contrast.at(*b, *i))
        .collect();
    let k = ((v.len() as f64 * STRONG_PERCENTILE) as usize).min(v.len() - 1);
    let (_, x, _) = v.select_nth_unstable_by(k, f32::total_cmp);
    x.max(0.0)
}

#[cfg(test)]
mod tests;
