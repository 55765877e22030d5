//! Binary masks, thresholds, erosion and dilation with structuring elements.
//!
//! A [`Mask`] is a bit-packed binary image (64 pixels per `u64` word), so that
//! morphology runs 64 pixels per instruction. [`Morphology`] is a reusable
//! worker: build it once, call [`Morphology::erode`] / [`Morphology::dilate`]
//! per frame; its scratch buffers are kept and nothing is allocated once they
//! have grown to the frame size.
//!
//! ## Semantics (OpenCV's `erode` / `dilate` with the default border)
//! For a structuring element of `width x height` with its anchor at the centre
//! `(ax, ay) = (width / 2, height / 2)` and cells `(i, j)` (row, column):
//! - `dilate(m)(x, y) = max { m(x + j - ax, y + i - ay) : (i, j) in element }`
//! - `erode(m)(x, y)  = min { m(x + j - ax, y + i - ay) : (i, j) in element }`
//!
//! Pixels outside the image never constrain the result: erosion treats them as
//! 1 and dilation as 0 (OpenCV's `BORDER_CONSTANT` with its "morphology border
//! value"). Hence duality holds exactly: `erode(m) = !dilate(!m)`.
//!
//! ## Cost
//! Rows are dilated 64 pixels per word: a row with few runs of ones (a
//! thresholded flow, or its complement for erosion) by stamping each run
//! grown by the kernel's half-widths, a busy row by bit-parallel doubling
//! (`log2` of the width in word shifts); each row takes the cheaper way.
//! - Rectangle: rows as above, then columns by van Herk/Gil-Werman (three
//!   word operations per 64 pixels whatever the height): cost flat in the
//!   kernel size.
//! - Cross: the union of a one-row and a one-column rectangle.
//! - Ellipse (and any element of more than two rectangles): each distinct row
//!   run dilates the rows once, then every output row ORs one dilated row per
//!   element row: `height` word ORs per 64 pixels, so the cost grows with the
//!   kernel height (with a small constant; see `benches/morphology.rs`).
//!
//! ## Example
//! ```
//! use optical_tactile::segment::morphology::{Mask, StructuringElement, dilate, erode};
//! // A 3x3 square and a lone speck.
//! let m = Mask::from_fn(8, 6, |x, y| (1..4).contains(&x) && (1..4).contains(&y) || (x, y) == (6, 4));
//! let se = StructuringElement::rect(3, 3);
//! // Opening (erode then dilate) removes the speck and restores the square.
//! let opened = dilate(&erode(&m, &se, 1)?, &se, 1)?;
//! assert_eq!(opened.count_ones(), 9);
//! assert!(!opened.get(6, 4));
//! # Ok::<(), optical_tactile::Error>(())
//! ```

use ndarray::{Array2, ArrayRef2};

use crate::error::{Error, Result};
use crate::flow::FlowField;

/// A binary image, bit-packed row by row (bit `x % 64` of word `x / 64`).
///
/// Bits past the width in each row's last word are always 0.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Mask {
    width: usize,
    height: usize,
    words: usize,
    bits: Vec<u64>,
}

impl Mask {
    /// An all-zero mask of `width x height` (either may be 0).
    pub fn new(width: usize, height: usize) -> Self {
        let words = width.div_ceil(64);
        Mask {
            width,
            height,
            words,
            bits: vec![0; words * height],
        }
    }

    /// A mask whose pixel `(x, y)` is `f(x, y)`.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> bool) -> Self {
        let mut m = Mask::new(width, height);
        for y in 0..height {
            for x in 0..width {
                if f(x, y) {
                    m.set(x, y, true);
                }
            }
        }
        m
    }

    /// A mask from a `(height, width)` array: nonzero is 1.
    pub fn from_array(a: &ArrayRef2<u8>) -> Self {
        Mask::from_fn(a.ncols(), a.nrows(), |x, y| a[[y, x]] != 0)
    }

    /// The mask as a `(height, width)` array of 0 and 1.
    pub fn to_array(&self) -> Array2<u8> {
        Array2::from_shape_fn((self.height, self.width), |(y, x)| self.get(x, y) as u8)
    }

    /// Resizes to `width x height` and clears every pixel. Keeps the allocation
    /// when it is large enough.
    pub fn reset(&mut self, width: usize, height: usize) {
        self.width = width;
        self.height = height;
        self.words = width.div_ceil(64);
        self.bits.clear();
        self.bits.resize(self.words * height, 0);
    }

    /// Makes `self` a copy of `src`, reusing `self`'s allocation (the derived
    /// `clone_from` would allocate).
    pub fn copy_from(&mut self, src: &Mask) {
        self.width = src.width;
        self.height = src.height;
        self.words = src.words;
        self.bits.clear();
        self.bits.extend_from_slice(&src.bits);
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// `(width, height)`.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Number of `u64` words per row.
    pub fn words_per_row(&self) -> usize {
        self.words
    }

    /// The packed words of row `y` (bit `x % 64` of word `x / 64` is pixel `x`).
    ///
    /// # Panics
    /// If `y >= height`.
    pub fn row(&self, y: usize) -> &[u64] {
        &self.bits[y * self.words..(y + 1) * self.words]
    }

    /// Pixel `(x, y)`; `false` outside the mask.
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> bool {
        x < self.width
            && y < self.height
            && (self.bits[y * self.words + x / 64] >> (x % 64)) & 1 == 1
    }

    /// Sets pixel `(x, y)`.
    ///
    /// # Panics
    /// If `(x, y)` lies outside the mask.
    pub fn set(&mut self, x: usize, y: usize, value: bool) {
        assert!(
            x < self.width && y < self.height,
            "pixel ({x}, {y}) outside the mask"
        );
        let w = &mut self.bits[y * self.words + x / 64];
        if value {
            *w |= 1 << (x % 64);
        } else {
            *w &= !(1 << (x % 64));
        }
    }

    /// Number of 1 pixels.
    pub fn count_ones(&self) -> usize {
        self.bits.iter().map(|w| w.count_ones() as usize).sum()
    }

    /// Number of 1 pixels in columns `x0..x1` and rows `y0..y1` (clipped to the mask).
    pub fn count_ones_in(&self, x0: usize, y0: usize, x1: usize, y1: usize) -> usize {
        let (x1, y1) = (x1.min(self.width), y1.min(self.height));
        if x0 >= x1 || y0 >= y1 {
            return 0;
        }
        let (k0, k1) = (x0 / 64, (x1 - 1) / 64);
        let mut n = 0usize;
        for y in y0..y1 {
            let row = self.row(y);
            for k in k0..=k1 {
                let mut w = row[k];
                if k == k0 {
                    w &= !0u64 << (x0 % 64);
                }
                if k == k1 && x1 % 64 != 0 {
                    w &= (1u64 << (x1 % 64)) - 1;
                }
                n += w.count_ones() as usize;
            }
        }
        n
    }

    /// `true` if no pixel is set.
    pub fn is_empty(&self) -> bool {
        self.bits.iter().all(|&w| w == 0)
    }

    /// Keeps only the pixels also set in `other` (`self &= other`). Errors
    /// if the sizes differ.
    pub fn and_assign(&mut self, other: &Mask) -> Result<()> {
        if self.size() != other.size() {
            return Err(Error::shape("mask against mask", other.size(), self.size()));
        }
        for (a, b) in self.bits.iter_mut().zip(&other.bits) {
            *a &= b;
        }
        Ok(())
    }

    /// The complement (within the image; pad bits stay 0).
    pub fn not(&self) -> Mask {
        let mut out = self.clone();
        complement_into(self, &mut out);
        out
    }

    /// `values > threshold` for a `(height, width)` array (OpenCV's
    /// `THRESH_BINARY`). Errors with [`Error::NonFinite`] at a NaN or infinite
    /// value, or [`Error::InvalidParameter`] for a NaN threshold.
    pub fn threshold(values: &ArrayRef2<f32>, threshold: f32) -> Result<Mask> {
        let mut m = Mask::default();
        m.threshold_into(values, threshold)?;
        Ok(m)
    }

    /// [`Mask::threshold`] into `self` (resized; the allocation is reused).
    pub fn threshold_into(&mut self, values: &ArrayRef2<f32>, threshold: f32) -> Result<()> {
        if threshold.is_nan() {
            return Err(Error::param("threshold", "is NaN"));
        }
        let (h, w) = values.dim();
        self.reset(w, h);
        for (y, row) in values.rows().into_iter().enumerate() {
            for (x, &v) in row.iter().enumerate() {
                if !v.is_finite() {
                    return Err(Error::NonFinite {
                        what: "thresholded values".into(),
                        row: y,
                        col: x,
                    });
                }
                if v > threshold {
                    self.bits[y * self.words + x / 64] |= 1 << (x % 64);
                }
            }
        }
        Ok(())
    }

    /// `|flow| > threshold` per pixel, into `self` (resized; the allocation is
    /// reused). Compares squared magnitudes, so no square root is taken.
    ///
    /// Errors with [`Error::NonFinite`] at the first NaN or infinite flow value
    /// and [`Error::InvalidParameter`] if `threshold` is negative or not finite.
    pub fn threshold_flow_into(&mut self, flow: &FlowField, threshold: f32) -> Result<()> {
        if !(threshold.is_finite() && threshold >= 0.0) {
            return Err(Error::param(
                "magnitude threshold",
                format!("must be finite and >= 0, got {threshold}"),
            ));
        }
        let (w, h) = flow.size();
        self.reset(w, h);
        let t2 = threshold * threshold;
        let words = self.words;
        for y in 0..h {
            let (ur, vr) = (flow.u.row(y), flow.v.row(y));
            let out = &mut self.bits[y * words..(y + 1) * words];
            // Contiguous rows take the fast path, strided views the general one.
            match (ur.as_slice(), vr.as_slice()) {
                (Some(us), Some(vs)) => {
                    let mut bad = false;
                    for (k, (uc, vc)) in us.chunks(64).zip(vs.chunks(64)).enumerate() {
                        // Compare into bytes (vectorises), then pack 8 at a time.
                        let mut bytes = [0u8; 64];
                        let mut finite = true;
                        for ((b, &u), &v) in bytes.iter_mut().zip(uc).zip(vc) {
                            let m2 = u * u + v * v;
                            // NaN or inf (a bad input or an overflowing square).
                            finite &= m2.is_finite();
                            *b = (m2 > t2) as u8;
                        }
                        bad |= !finite;
                        out[k] = pack_bytes(&bytes);
                    }
                    if bad {
                        flow.check_finite("flow")?;
                        // Finite u, v whose squares overflow: exact test per pixel.
                        for (k, (uc, vc)) in us.chunks(64).zip(vs.chunks(64)).enumerate() {
                            let mut word = 0u64;
                            for (b, (&u, &v)) in uc.iter().zip(vc).enumerate() {
                                word |= ((u.hypot(v) > threshold) as u64) << b;
                            }
                            out[k] = word;
                        }
                    }
                }
                _ => {
                    for x in 0..w {
                        let (u, v) = (ur[x], vr[x]);
                        if !(u.is_finite() && v.is_finite()) {
                            return flow.check_finite("flow");
                        }
                        if u.hypot(v) > threshold {
                            out[x / 64] |= 1 << (x % 64);
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// Mask of the pad bits of the last word of a row (1 where pixels exist).
    fn last_word_mask(&self) -> u64 {
        match self.width % 64 {
            0 => !0,
            r => (1u64 << r) - 1,
        }
    }
}

/// Packs 64 bytes of 0/1 into a word, byte `i` to bit `i`.
#[inline]
fn pack_bytes(bytes: &[u8; 64]) -> u64 {
    let mut w = 0u64;
    for (j, c) in bytes.chunks_exact(8).enumerate() {
        let x = u64::from_le_bytes(c.try_into().expect("8 bytes"));
        // Byte k (0 or 1) lands on bit 56 + k: the partial products
        // 2^(8k + 7i + 7) are all distinct, so nothing carries.
        w |= (x.wrapping_mul(0x0102_0408_1020_4080) >> 56) << (8 * j);
    }
    w
}

/// The shape of a structuring element (OpenCV's `MORPH_RECT`, `MORPH_CROSS`,
/// `MORPH_ELLIPSE`).
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    /// Every cell of the `width x height` box (the default).
    #[default]
    Rect,
    /// The anchor's row and the anchor's column.
    Cross,
    /// The ellipse inscribed in the box, rasterised exactly as OpenCV's
    /// `getStructuringElement(MORPH_ELLIPSE, ...)` does.
    Ellipse,
}

/// A structuring element: a shape in a `width x height` box, anchored at its
/// centre `(width / 2, height / 2)`. Sizes must be at least 1 (checked when used).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct StructuringElement {
    /// The shape.
    pub shape: Shape,
    /// Box width in pixels (columns), >= 1.
    pub width: usize,
    /// Box height in pixels (rows), >= 1.
    pub height: usize,
}

impl StructuringElement {
    /// A `width x height` element of `shape`.
    pub const fn new(shape: Shape, width: usize, height: usize) -> Self {
        StructuringElement {
            shape,
            width,
            height,
        }
    }

    /// A `width x height` rectangle.
    pub const fn rect(width: usize, height: usize) -> Self {
        Self::new(Shape::Rect, width, height)
    }

    /// A `width x height` cross.
    pub const fn cross(width: usize, height: usize) -> Self {
        Self::new(Shape::Cross, width, height)
    }

    /// A `width x height` ellipse.
    pub const fn ellipse(width: usize, height: usize) -> Self {
        Self::new(Shape::Ellipse, width, height)
    }

    /// The anchor `(column, row)` = the centre `(width / 2, height / 2)`.
    pub fn anchor(&self) -> (usize, usize) {
        (self.width / 2, self.height / 2)
    }

    /// Errors unless both sizes are at least 1.
    pub fn validate(&self) -> Result<()> {
        if self.width == 0 || self.height == 0 {
            return Err(Error::param(
                "structuring element",
                format!(
                    "size must be at least 1x1, got {}x{}",
                    self.width, self.height
                ),
            ));
        }
        Ok(())
    }

    /// The cells of row `i` as a half-open column range `j1..j2` (as OpenCV's
    /// `getStructuringElement` computes it).
    pub fn row_run(&self, i: usize) -> (usize, usize) {
        let (w, h) = (self.width as i64, self.height as i64);
        let (ax, ay) = (w / 2, h / 2);
        let i = i as i64;
        match self.shape {
            Shape::Rect => (0, w as usize),
            Shape::Cross if i == ay => (0, w as usize),
            Shape::Cross => (ax as usize, ax as usize + 1),
            Shape::Ellipse => {
                let (r, c) = (h / 2, w / 2);
                let inv_r2 = if r > 0 { 1.0 / (r * r) as f64 } else { 0.0 };
                let dy = i - r;
                if dy.abs() <= r {
                    // cvRound rounds half to even.
                    let dx = (c as f64 * (((r * r - dy * dy) as f64) * inv_r2).sqrt())
                        .round_ties_even() as i64;
                    ((c - dx).max(0) as usize, (c + dx + 1).min(w) as usize)
                } else {
                    (0, 0)
                }
            }
        }
    }

    /// Whether cell `(i, j)` (row, column) belongs to the element.
    pub fn contains(&self, i: usize, j: usize) -> bool {
        let (j1, j2) = self.row_run(i);
        i < self.height && j1 <= j && j < j2
    }

    /// The element as a `(height, width)` array of 0 and 1 (like OpenCV's).
    pub fn to_array(&self) -> Array2<u8> {
        Array2::from_shape_fn((self.height, self.width), |(i, j)| {
            self.contains(i, j) as u8
        })
    }

    /// Decomposes the element into rectangles `[-l, r] x [-t, b]` (offsets
    /// from the anchor) whose union is the element. Every row of our shapes
    /// holds the anchor column, and its left and right extents shrink away from
    /// the anchor row, so the rectangles "rows whose extents reach (l, r)" for
    /// each distinct (l, r) cover it exactly.
    fn rectangles(&self) -> Vec<RectPart> {
        let (ax, ay) = self.anchor();
        let ext: Vec<(usize, usize)> = (0..self.height)
            .map(|i| {
                let (j1, j2) = self.row_run(i);
                debug_assert!(j1 <= ax && ax < j2, "row {i} misses the anchor column");
                (ax - j1, j2 - 1 - ax)
            })
            .collect();
        let mut parts: Vec<RectPart> = Vec::new();
        for &(l, r) in &ext {
            if parts.iter().any(|p| p.l == l && p.r == r) {
                continue;
            }
            let reaches = |i: usize| ext[i].0 >= l && ext[i].1 >= r;
            let mut t = 0;
            while t < ay && reaches(ay - t - 1) {
                t += 1;
            }
            let mut b = 0;
            while ay + b + 1 < self.height && reaches(ay + b + 1) {
                b += 1;
            }
            parts.push(RectPart { l, r, t, b });
        }
        parts
    }
}

/// A rectangle of offsets `[-l, r]` (columns) x `[-t, b]` (rows).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct RectPart {
    l: usize,
    r: usize,
    t: usize,
    b: usize,
}

/// Reusable erosion/dilation worker: holds the scratch buffers.
#[derive(Debug, Default, Clone)]
pub struct Morphology {
    /// Complement of the source (erosion) or iteration ping-pong.
    a: Mask,
    b: Mask,
    /// Result of one rectangle, ORed into the output.
    part: Mask,
    /// Horizontally dilated rows.
    horiz: Mask,
    /// van Herk prefix (`g`) and suffix (`h`) rows.
    g: Vec<u64>,
    h: Vec<u64>,
    row: Vec<u64>,
    /// Ring of horizontally dilated rows, per distinct row run (row-run path).
    planes: Vec<u64>,
    /// Per ring slot: its source row is empty.
    empty: Vec<bool>,
    /// Plans of the last few elements used.
    plans: Vec<(StructuringElement, Plan)>,
}

/// How to dilate by one element.
#[derive(Debug, Clone, Default)]
struct Plan {
    /// Rectangles whose union is the element.
    parts: Vec<RectPart>,
    /// Distinct row runs `(l, r)` (offsets from the anchor column).
    runs: Vec<(usize, usize)>,
    /// For each element row, its index in `runs`.
    row_run: Vec<usize>,
    /// Anchor row.
    ay: usize,
}

impl Plan {
    fn new(se: &StructuringElement) -> Plan {
        let (ax, ay) = se.anchor();
        let mut runs: Vec<(usize, usize)> = Vec::new();
        let row_run = (0..se.height)
            .map(|i| {
                let (j1, j2) = se.row_run(i);
                let lr = (ax - j1, j2 - 1 - ax);
                runs.iter().position(|&x| x == lr).unwrap_or_else(|| {
                    runs.push(lr);
                    runs.len() - 1
                })
            })
            .collect();
        Plan {
            parts: se.rectangles(),
            runs,
            row_run,
            ay,
        }
    }

    /// Rectangles are separable and flat in their size; with more than two,
    /// OR-ing one horizontally dilated row per element row is cheaper than
    /// a vertical pass per rectangle.
    fn by_rows(&self) -> bool {
        self.parts.len() > 2
    }
}

impl Morphology {
    /// A worker with empty buffers (they grow on first use).
    pub fn new() -> Self {
        Self::default()
    }

    /// Erodes `src` by `element`, `iterations` times, into `dst` (resized).
    /// `iterations = 0` copies.
    pub fn erode(
        &mut self,
        src: &Mask,
        dst: &mut Mask,
        element: &StructuringElement,
        iterations: usize,
    ) -> Result<()> {
        self.run(src, dst, element, iterations, true)
    }

    /// Dilates `src` by `element`, `iterations` times, into `dst` (resized).
    /// `iterations = 0` copies.
    pub fn dilate(
        &mut self,
        src: &Mask,
        dst: &mut Mask,
        element: &StructuringElement,
        iterations: usize,
    ) -> Result<()> {
        self.run(src, dst, element, iterations, false)
    }

    fn run(
        &mut self,
        src: &Mask,
        dst: &mut Mask,
        element: &StructuringElement,
        iterations: usize,
        erode: bool,
    ) -> Result<()> {
        element.validate()?;
        // A few plans are kept: a caller alternating erosion and dilation
        // kernels (the segmenter) then builds each plan once.
        let plan = match self.plans.iter().position(|(e, _)| e == element) {
            Some(i) => self.plans.swap_remove(i).1,
            None => Plan::new(element),
        };
        // Erosion is the complement of the dilation of the complement (same
        // offsets): outside pixels, 0 for the dilation, act as 1 for erosion.
        let mut cur = std::mem::take(&mut self.a);
        if erode {
            complement_into(src, &mut cur);
        } else {
            cur.copy_from(src);
        }
        let mut next = std::mem::take(&mut self.b);
        for _ in 0..iterations {
            self.dilate_once(&cur, &mut next, &plan);
            std::mem::swap(&mut cur, &mut next);
        }
        if self.plans.len() >= 4 {
            self.plans.remove(0);
        }
        self.plans.push((*element, plan));
        if erode {
            complement_into(&cur, dst);
        } else {
            dst.copy_from(&cur);
        }
        self.a = cur;
        self.b = next;
        Ok(())
    }

    /// One dilation by the union of `parts` (output resized to `src`).
    fn dilate_once(&mut self, src: &Mask, dst: &mut Mask, plan: &Plan) {
        dst.reset(src.width, src.height);
        if src.width == 0 || src.height == 0 {
            return;
        }
        if plan.by_rows() {
            self.dilate_by_rows(src, dst, plan);
            return;
        }
        let parts = &plan.parts;
        let mut part = std::mem::take(&mut self.part);
        for (n, p) in parts.iter().enumerate() {
            let out: &mut Mask = if n == 0 { dst } else { &mut part };
            self.dilate_rect(src, out, *p);
            if n > 0 {
                for (d, s) in dst.bits.iter_mut().zip(&part.bits) {
                    *d |= *s;
                }
            }
        }
        self.part = part;
    }

    /// Dilation by row runs: each distinct run dilates every row once, then
    /// output row `y` ORs, for each element row `i`, row `y + i - ay` of its
    /// run's dilation. The dilated rows live in a ring of `height` rows (the
    /// window of one output row), which stays in cache. `dst` must be reset
    /// (zero).
    fn dilate_by_rows(&mut self, src: &Mask, dst: &mut Mask, plan: &Plan) {
        let (wds, h) = (src.words, src.height);
        let kh = plan.row_run.len();
        let nk = plan.runs.len();
        let lastmask = src.last_word_mask();
        self.planes.clear();
        self.planes.resize(kh * nk * wds, 0);
        self.row.resize(wds, 0);
        let below = kh - 1 - plan.ay;
        // Per ring slot: whether its source row is empty (its dilations are).
        self.empty.clear();
        self.empty.resize(kh, false);
        let full_row = |o: &[u64]| o[..wds - 1].iter().all(|&w| w == !0) && o[wds - 1] == lastmask;
        let mut next = 0; // next source row to dilate into the ring
        for y in 0..h {
            while next < h && next <= y + below {
                let s = &src.bits[next * wds..(next + 1) * wds];
                let slot = next % kh;
                self.empty[slot] = s.iter().all(|&w| w == 0);
                if !self.empty[slot] {
                    for (k, &(l, r)) in plan.runs.iter().enumerate() {
                        let at = (slot * nk + k) * wds;
                        let d = &mut self.planes[at..at + wds];
                        dilate_row(s, d, &mut self.row, l, r);
                        d[wds - 1] &= lastmask;
                    }
                }
                next += 1;
            }
            let o = &mut dst.bits[y * wds..(y + 1) * wds];
            for (i, &k) in plan.row_run.iter().enumerate() {
                let Some(yy) = (y + i).checked_sub(plan.ay).filter(|&yy| yy < h) else {
                    continue;
                };
                // Sparse masks: empty rows add nothing; dense ones (the
                // complement, when eroding) saturate early.
                if self.empty[yy % kh] {
                    continue;
                }
                let at = ((yy % kh) * nk + k) * wds;
                for (a, b) in o.iter_mut().zip(&self.planes[at..at + wds]) {
                    *a |= *b;
                }
                if i % 4 == 3 && full_row(o) {
                    break;
                }
            }
        }
    }

    /// Dilation by one rectangle: rows by doubling, then columns by van Herk.
    fn dilate_rect(&mut self, src: &Mask, out: &mut Mask, p: RectPart) {
        let (wds, h) = (src.words, src.height);
        let lastmask = src.last_word_mask();
        let mut horiz = std::mem::take(&mut self.horiz);
        let hsrc: &Mask = if p.l == 0 && p.r == 0 {
            src
        } else {
            horiz.reset(src.width, h);
            self.row.resize(wds, 0);
            for y in 0..h {
                let s = &src.bits[y * wds..(y + 1) * wds];
                let d = &mut horiz.bits[y * wds..(y + 1) * wds];
                dilate_row(s, d, &mut self.row, p.l, p.r);
                d[wds - 1] &= lastmask;
            }
            &horiz
        };
        out.reset(src.width, h);
        if p.t == 0 && p.b == 0 {
            out.bits.copy_from_slice(&hsrc.bits);
        } else {
            self.van_herk_columns(hsrc, out, p.t, p.b);
        }
        self.horiz = horiz;
    }

    /// `out[y] = OR of rows y - t ..= y + b` (clipped), by van Herk/Gil-Werman:
    /// in padded row coordinates `q = y' + t` cut into blocks of `n = t + b + 1`
    /// rows, a window `[y, y + n - 1]` is the suffix OR of its first block from
    /// `y` joined with the prefix OR of the next block up to `y + n - 1`.
    fn van_herk_columns(&mut self, src: &Mask, out: &mut Mask, t: usize, b: usize) {
        let (wds, h) = (src.words, src.height);
        let n = t + b + 1;
        let padded = h + n - 1;
        let row = |q: usize| -> Option<&[u64]> {
            (q >= t && q - t < h).then(|| &src.bits[(q - t) * wds..(q - t + 1) * wds])
        };
        // Prefix within blocks, for every padded row q (only q >= n - 1 is read).
        self.g.clear();
        self.g.resize(padded * wds, 0);
        for q in 0..padded {
            let (before, cur) = self.g.split_at_mut(q * wds);
            let cur = &mut cur[..wds];
            match row(q) {
                Some(s) => cur.copy_from_slice(s),
                None => cur.fill(0),
            }
            if q % n != 0 {
                let prev = &before[(q - 1) * wds..];
                for (c, p) in cur.iter_mut().zip(prev) {
                    *c |= *p;
                }
            }
        }
        // Suffix within blocks, for padded rows 0..h (the windows' starts).
        self.h.clear();
        self.h.resize(h * wds, 0);
        let mut carry = vec![0u64; 0];
        std::mem::swap(&mut carry, &mut self.row);
        carry.clear();
        carry.resize(wds, 0);
        // Walk down from the end of the block holding row h - 1.
        let top = ((h - 1) / n + 1) * n; // exclusive end of that block
        for q in (0..top).rev() {
            if q % n == n - 1 {
                carry.fill(0);
            }
            if let Some(s) = row(q) {
                for (c, v) in carry.iter_mut().zip(s) {
                    *c |= *v;
                }
            }
            if q < h {
                self.h[q * wds..(q + 1) * wds].copy_from_slice(&carry);
            }
        }
        self.row = carry;
        for y in 0..h {
            let o = &mut out.bits[y * wds..(y + 1) * wds];
            let hs = &self.h[y * wds..(y + 1) * wds];
            let gs = &self.g[(y + n - 1) * wds..(y + n) * wds];
            for ((o, a), c) in o.iter_mut().zip(hs).zip(gs) {
                *o = a | c;
            }
        }
    }
}

/// `dst[x] = OR of src[x - l ..= x + r]` for one row of words (outside = 0);
/// `tmp` is scratch of the same length. Bits past the row's width may be set
/// in `dst`'s last word (the caller masks them).
///
/// Two ways, the cheaper one per row: a row with few runs of ones (the usual
/// thresholded flow, or its complement) stamps each run grown by `(l, r)`,
/// whatever the kernel size; a busy row grows by bit-parallel doubling, in
/// `log2(l + 1) + log2(r + 1)` word shifts.
fn dilate_row(src: &[u64], dst: &mut [u64], tmp: &mut [u64], l: usize, r: usize) {
    let mut runs = 0usize;
    let mut carry = 0u64;
    for &w in src.iter() {
        runs += (w & !((w << 1) | carry)).count_ones() as usize;
        carry = w >> 63;
    }
    let steps = (usize::BITS - (l + 1).leading_zeros()) as usize
        + (usize::BITS - (r + 1).leading_zeros()) as usize;
    // A run costs a few dozen instructions, a doubling step a few per word.
    if runs * 8 <= src.len() * steps {
        dilate_row_runs(src, dst, l, r);
        return;
    }
    dst.copy_from_slice(src);
    grow(dst, r + 1, or_from_right);
    if l > 0 {
        tmp.copy_from_slice(src);
        grow(tmp, l + 1, or_from_left);
        for (d, t) in dst.iter_mut().zip(tmp.iter()) {
            *d |= *t;
        }
    }
}

/// [`dilate_row`] by stamping each run of ones `[a, b]` as `[a - r, b + l]`
/// (source pixel `a` reaches the outputs `x` with `x - l <= a <= x + r`).
fn dilate_row_runs(src: &[u64], dst: &mut [u64], l: usize, r: usize) {
    dst.fill(0);
    let n = src.len();
    let mut start = 0usize;
    for k in 0..n {
        let w = src[k];
        if w == 0 {
            continue;
        }
        let below = if k > 0 { src[k - 1] >> 63 } else { 0 };
        let above = if k + 1 < n { src[k + 1] << 63 } else { 0 };
        let starts = w & !((w << 1) | below);
        let ends = w & !((w >> 1) | above);
        let mut marks = starts | ends;
        while marks != 0 {
            let b = marks.trailing_zeros();
            marks &= marks - 1;
            let x = k * 64 + b as usize;
            if (starts >> b) & 1 == 1 {
                start = x;
            }
            if (ends >> b) & 1 == 1 {
                fill_bits(dst, start.saturating_sub(r), x + l);
            }
        }
    }
}

/// Sets bits `lo ..= hi` (clipped to the slice).
#[inline]
fn fill_bits(a: &mut [u64], lo: usize, hi: usize) {
    let hi = hi.min(a.len() * 64 - 1);
    let (k0, k1) = (lo / 64, hi / 64);
    let m0 = !0u64 << (lo % 64);
    let m1 = !0u64 >> (63 - hi % 64);
    if k0 == k1 {
        a[k0] |= m0 & m1;
        return;
    }
    a[k0] |= m0;
    for w in &mut a[k0 + 1..k1] {
        *w = !0;
    }
    a[k1] |= m1;
}

/// Turns `a` into the OR of `n` consecutive bits per position by doubling:
/// `step(a, p)` ORs in the copy shifted by `p`.
#[inline]
fn grow(a: &mut [u64], n: usize, step: fn(&mut [u64], usize)) {
    let mut p = 1;
    while 2 * p <= n {
        step(a, p);
        p *= 2;
    }
    if n > p {
        step(a, n - p);
    }
}

/// In place `a[x] |= a[x + s]` (bits past the end read as 0). Safe in
/// increasing order: word `k` reads only words `>= k`, not yet written.
fn or_from_right(a: &mut [u64], s: usize) {
    let (q, r) = (s / 64, s % 64);
    let n = a.len();
    for k in 0..n {
        let lo = if k + q < n { a[k + q] } else { 0 };
        let v = if r == 0 {
            lo
        } else {
            let hi = if k + q + 1 < n { a[k + q + 1] } else { 0 };
            (lo >> r) | (hi << (64 - r))
        };
        a[k] |= v;
    }
}

/// In place `a[x] |= a[x - s]` (bits before the start read as 0). Safe in
/// decreasing order: word `k` reads only words `<= k`, not yet written.
fn or_from_left(a: &mut [u64], s: usize) {
    let (q, r) = (s / 64, s % 64);
    for k in (0..a.len()).rev() {
        let lo = if k >= q { a[k - q] } else { 0 };
        let v = if r == 0 {
            lo
        } else {
            let below = if k > q { a[k - q - 1] } else { 0 };
            (lo << r) | (below >> (64 - r))
        };
        a[k] |= v;
    }
}

/// `dst = !src` inside the image (pad bits 0); `dst` resized to `src`.
fn complement_into(src: &Mask, dst: &mut Mask) {
    dst.reset(src.width, src.height);
    if src.words == 0 {
        return;
    }
    let last = src.last_word_mask();
    for (d, s) in dst
        .bits
        .chunks_exact_mut(src.words)
        .zip(src.bits.chunks_exact(src.words))
    {
        for (dw, sw) in d.iter_mut().zip(s) {
            *dw = !sw;
        }
        *d.last_mut().expect("words > 0") &= last;
    }
}

/// Erodes `src` (allocating convenience for [`Morphology::erode`]).
pub fn erode(src: &Mask, element: &StructuringElement, iterations: usize) -> Result<Mask> {
    let mut out = Mask::default();
    Morphology::new().erode(src, &mut out, element, iterations)?;
    Ok(out)
}

/// Dilates `src` (allocating convenience for [`Morphology::dilate`]).
pub fn dilate(src: &Mask, element: &StructuringElement, iterations: usize) -> Result<Mask> {
    let mut out = Mask::default();
    Morphology::new().dilate(src, &mut out, element, iterations)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::array;

    #[test]
    fn ellipses_match_opencv() {
        let e3 = StructuringElement::ellipse(3, 3).to_array();
        assert_eq!(e3, array![[0, 1, 0], [1, 1, 1], [0, 1, 0]]);
        let e5 = StructuringElement::ellipse(5, 5).to_array();
        assert_eq!(
            e5,
            array![
                [0, 0, 1, 0, 0],
                [1, 1, 1, 1, 1],
                [1, 1, 1, 1, 1],
                [1, 1, 1, 1, 1],
                [0, 0, 1, 0, 0]
            ]
        );
        let e7 = StructuringElement::ellipse(7, 7).to_array();
        assert_eq!(
            e7,
            array![
                [0, 0, 0, 1, 0, 0, 0],
                [0, 1, 1, 1, 1, 1, 0],
                [1, 1, 1, 1, 1, 1, 1],
                [1, 1, 1, 1, 1, 1, 1],
                [1, 1, 1, 1, 1, 1, 1],
                [0, 1, 1, 1, 1, 1, 0],
                [0, 0, 0, 1, 0, 0, 0]
            ]
        );
        let c = StructuringElement::cross(3, 5).to_array();
        assert_eq!(
            c,
            array![[0, 1, 0], [0, 1, 0], [1, 1, 1], [0, 1, 0], [0, 1, 0]]
        );
    }

    #[test]
    fn rectangles_cover_the_element_exactly() {
        for shape in [Shape::Rect, Shape::Cross, Shape::Ellipse] {
            for w in 1..12 {
                for h in 1..12 {
                    let se = StructuringElement::new(shape, w, h);
                    let (ax, ay) = se.anchor();
                    let mut cov = Array2::<u8>::zeros((h, w));
                    for p in se.rectangles() {
                        for i in ay - p.t..=ay + p.b {
                            for j in ax - p.l..=ax + p.r {
                                cov[[i, j]] = 1;
                            }
                        }
                    }
                    assert_eq!(cov, se.to_array(), "{shape:?} {w}x{h}");
                }
            }
        }
    }

    #[test]
    fn both_row_dilations_agree() {
        let mut seed = 99u64;
        for _ in 0..500 {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let n = 1 + (seed >> 60) as usize % 4;
            let (l, r) = ((seed >> 20) as usize % 90, (seed >> 30) as usize % 90);
            let src: Vec<u64> = (0..n)
                .map(|i| {
                    let z = seed.rotate_left(i as u32 * 17) ^ (seed >> 7);
                    if (seed >> 50) & 1 == 1 {
                        z & z.rotate_left(5) & z.rotate_left(11)
                    } else {
                        z
                    }
                })
                .collect();
            let (mut a, mut b, mut t) = (vec![0; n], vec![0; n], vec![0; n]);
            dilate_row_runs(&src, &mut a, l, r);
            b.copy_from_slice(&src);
            grow(&mut b, r + 1, or_from_right);
            t.copy_from_slice(&src);
            grow(&mut t, l + 1, or_from_left);
            for (x, y) in b.iter_mut().zip(&t) {
                *x |= *y;
            }
            assert_eq!(a, b, "l {l} r {r} src {src:x?}");
        }
    }

    #[test]
    fn packing_bytes() {
        let mut b = [0u8; 64];
        for i in [0, 1, 7, 8, 13, 31, 32, 62, 63] {
            b[i] = 1;
        }
        let expect = [0, 1, 7, 8, 13, 31, 32, 62, 63]
            .iter()
            .fold(0u64, |w, &i| w | 1 << i);
        assert_eq!(pack_bytes(&b), expect);
        assert_eq!(pack_bytes(&[1; 64]), !0);
    }

    #[test]
    fn word_shifts() {
        let src = [0x8000_0000_0000_0001u64, 0x1];
        let mut b = src;
        or_from_left(&mut b, 1);
        assert_eq!(b, [0x8000_0000_0000_0003, 0x3]);
        let mut a = src;
        or_from_right(&mut a, 64);
        assert_eq!(a, [0x8000_0000_0000_0001 | 1, 1]);
    }

    #[test]
    fn threshold_counts_strictly_above() {
        let a = array![[0.0f32, 1.0, 2.0], [3.0, 1.0, 0.5]];
        let m = Mask::threshold(&a, 1.0).unwrap();
        assert_eq!(m.to_array(), array![[0u8, 0, 1], [1, 0, 0]]);
        let bad = array![[0.0f32, f32::NAN]];
        assert!(matches!(
            Mask::threshold(&bad, 1.0),
            Err(Error::NonFinite { row: 0, col: 1, .. })
        ));
    }

    #[test]
    fn flow_threshold_and_bad_flows() {
        let mut f = FlowField::zeros(70, 3);
        f.u[[1, 65]] = 3.0;
        f.v[[1, 65]] = 4.0;
        f.u[[2, 0]] = 1.0;
        let mut m = Mask::default();
        m.threshold_flow_into(&f, 4.9).unwrap();
        assert_eq!(m.count_ones(), 1);
        assert!(m.get(65, 1));
        m.threshold_flow_into(&f, 5.0).unwrap();
        assert!(m.is_empty());
        assert!(m.threshold_flow_into(&f, -1.0).is_err());
        assert!(m.threshold_flow_into(&f, f32::NAN).is_err());
        f.v[[2, 69]] = f32::INFINITY;
        assert!(matches!(
            m.threshold_flow_into(&f, 1.0),
            Err(Error::NonFinite {
                row: 2,
                col: 69,
                ..
            })
        ));
        // Finite but with an overflowing square: still exact.
        let mut g = FlowField::zeros(2, 1);
        g.u[[0, 1]] = 1e30;
        m.threshold_flow_into(&g, 1e29).unwrap();
        assert!(m.get(1, 0) && !m.get(0, 0));
    }

    #[test]
    fn zero_sized_element_is_an_error() {
        let m = Mask::new(4, 4);
        assert!(erode(&m, &StructuringElement::rect(0, 3), 1).is_err());
        assert!(dilate(&m, &StructuringElement::ellipse(3, 0), 1).is_err());
    }

    #[test]
    fn count_ones_in_a_window() {
        let m = Mask::from_fn(130, 3, |x, y| (x + y) % 2 == 0);
        let naive = |x0: usize, y0: usize, x1: usize, y1: usize| {
            (y0..y1.min(3))
                .flat_map(|y| (x0..x1.min(130)).map(move |x| (x, y)))
                .filter(|&(x, y)| m.get(x, y))
                .count()
        };
        for (x0, y0, x1, y1) in [
            (0, 0, 130, 3),
            (3, 1, 70, 2),
            (63, 0, 65, 3),
            (64, 0, 128, 3),
            (100, 0, 200, 9),
            (5, 2, 5, 3),
        ] {
            assert_eq!(m.count_ones_in(x0, y0, x1, y1), naive(x0, y0, x1, y1));
        }
    }
}
