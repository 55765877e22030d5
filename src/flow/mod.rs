//! Dense optical flow.
//!
//! [`FlowField`] holds a dense 2-D motion field as two planes `u` (motion along
//! image x, i.e. columns) and `v` (along image y, i.e. rows), each of shape
//! `(height, width)`, in pixels.

pub mod color;
pub mod dis;
pub(crate) mod pyramid;
pub mod refine;

pub(crate) use pyramid::sample_clamped;

use ndarray::{Array2, ArrayView2, Zip};

use crate::error::{Error, Result};
use crate::frame::Roi;

/// The instruction set the hot loops are dispatched to, detected once per process.
///
/// `pulp` compiles the `with_simd` method of an operation passed to `Arch::dispatch`
/// with AVX2 (+FMA) enabled when the CPU has it, so the plain loops inside run 8 lanes
/// wide instead of the baseline target's 4, without `unsafe` in this crate and without
/// a build flag. Each hot loop is a small `pulp::WithSimd` struct whose `with_simd`
/// and kernel are `#[inline(always)]`, so that the kernel is compiled inside that
/// method; a closure passed to `dispatch` is not (its body stays baseline code).
pub(crate) fn simd_arch() -> pulp::Arch {
    static ARCH: std::sync::OnceLock<pulp::Arch> = std::sync::OnceLock::new();
    *ARCH.get_or_init(pulp::Arch::new)
}

/// A dense 2-D flow field: `u` along columns (x), `v` along rows (y), in pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowField {
    /// Horizontal component (along image x), shape `(height, width)`.
    pub u: Array2<f32>,
    /// Vertical component (along image y), shape `(height, width)`.
    pub v: Array2<f32>,
}

impl FlowField {
    /// A zero flow of the given size.
    pub fn zeros(width: usize, height: usize) -> Self {
        FlowField {
            u: Array2::zeros((height, width)),
            v: Array2::zeros((height, width)),
        }
    }

    /// Builds a flow from its two planes; they must have the same shape.
    pub fn from_planes(u: Array2<f32>, v: Array2<f32>) -> Result<Self> {
        if u.dim() != v.dim() {
            return Err(Error::shape(
                "flow planes (v against u)",
                (u.ncols(), u.nrows()),
                (v.ncols(), v.nrows()),
            ));
        }
        Ok(FlowField { u, v })
    }

    /// Width in pixels (number of columns).
    pub fn width(&self) -> usize {
        self.u.ncols()
    }

    /// Height in pixels (number of rows).
    pub fn height(&self) -> usize {
        self.u.nrows()
    }

    /// `(width, height)`.
    pub fn size(&self) -> (usize, usize) {
        (self.width(), self.height())
    }

    /// Per-pixel magnitude `sqrt(u^2 + v^2)`.
    pub fn magnitude(&self) -> Array2<f32> {
        let mut m = Array2::zeros(self.u.dim());
        self.magnitude_into(&mut m);
        m
    }

    /// Per-pixel magnitude written into `out` (reshaped if needed).
    pub fn magnitude_into(&self, out: &mut Array2<f32>) {
        if out.dim() != self.u.dim() {
            *out = Array2::zeros(self.u.dim());
        }
        Zip::from(out)
            .and(&self.u)
            .and(&self.v)
            .for_each(|m, &u, &v| *m = u.hypot(v));
    }

    /// Errors with [`Error::NonFinite`] at the first NaN or infinite value.
    pub fn check_finite(&self, what: &str) -> Result<()> {
        for plane in [&self.u, &self.v] {
            // The common case, all finite, as a vectorised pass over the
            // slice; the indexed search only runs to name a bad value.
            if plane.as_slice().is_some_and(pyramid::all_finite) {
                continue;
            }
            if let Some(((row, col), _)) = plane.indexed_iter().find(|(_, x)| !x.is_finite()) {
                return Err(Error::NonFinite {
                    what: what.to_string(),
                    row,
                    col,
                });
            }
        }
        Ok(())
    }

    /// A view of the sub-field `x0..x0+w`, `y0..y0+h` (columns, rows).
    ///
    /// Errors with [`Error::CropOutside`] if the window does not fit.
    pub fn window(
        &self,
        x0: usize,
        y0: usize,
        w: usize,
        h: usize,
    ) -> Result<(ArrayView2<'_, f32>, ArrayView2<'_, f32>)> {
        if w == 0 || h == 0 || x0 + w > self.width() || y0 + h > self.height() {
            return Err(Error::CropOutside {
                x: x0,
                y: y0,
                w,
                h,
                frame_w: self.width(),
                frame_h: self.height(),
            });
        }
        let s = ndarray::s![y0..y0 + h, x0..x0 + w];
        Ok((self.u.slice(s), self.v.slice(s)))
    }

    /// The fraction of the moving cells of `cells` (a box of this field's
    /// cells, clipped to it; moving: `|(u, v)|` of `moving_px` or more) whose
    /// flow stretches by `strain` or more over `lag` cells: with `(du, dv)`
    /// the change of the flow to the cell `lag` further along x and
    /// `(du', dv')` to the one `lag` further along y (each where it lies in
    /// the field), the stretch is `sqrt(du^2 + dv^2 + du'^2 + dv'^2)` over
    /// the lag in full-resolution pixels (`lag * scale`; the flow is in
    /// full-resolution pixels, one cell spans `scale` of them). The cells are
    /// sampled every `lag / 2` cells along both axes (every cell for a lag of
    /// 1). 0 when no sampled cell moves or the box is empty.
    ///
    /// What it tells: a dense-texture flow follows each patch of the
    /// reference as one piece, so where the motion changes across a patch by
    /// a good part of its side the patch no longer matches and the flow
    /// tears ([`crate::sensor::ContactExtractor::beyond_markers`]).
    pub fn stretched_fraction(
        &self,
        cells: Roi,
        scale: usize,
        lag: usize,
        moving_px: f32,
        strain: f64,
    ) -> f64 {
        let (w, h) = self.size();
        let lag = lag.max(1);
        let step = (lag / 2).max(1);
        let (x0, y0) = (cells.x.min(w), cells.y.min(h));
        let x1 = cells.x.saturating_add(cells.w).min(w);
        let y1 = cells.y.saturating_add(cells.h).min(h);
        let moving = moving_px * moving_px;
        // Compared squared, over the lag in full-resolution pixels.
        let limit = (strain * lag as f64 * scale.max(1) as f64).powi(2) as f32;
        let (u, v) = (self.u.as_standard_layout(), self.v.as_standard_layout());
        let (u, v) = (
            u.as_slice().expect("standard layout"),
            v.as_slice().expect("standard layout"),
        );
        let (mut sampled, mut stretched) = (0usize, 0usize);
        for i in (y0..y1).step_by(step) {
            for j in (x0..x1).step_by(step) {
                let k = i * w + j;
                let (a, b) = (u[k], v[k]);
                if a * a + b * b < moving {
                    continue;
                }
                sampled += 1;
                let mut d2 = 0.0f32;
                // `w - j > lag`: `j + lag < w` without overflow at any lag.
                if w - j > lag {
                    d2 += (u[k + lag] - a).powi(2) + (v[k + lag] - b).powi(2);
                }
                if h - i > lag {
                    let k2 = k + lag * w;
                    d2 += (u[k2] - a).powi(2) + (v[k2] - b).powi(2);
                }
                if d2 >= limit {
                    stretched += 1;
                }
            }
        }
        if sampled == 0 {
            0.0
        } else {
            stretched as f64 / sampled as f64
        }
    }

    /// Average endpoint error against `truth`, ignoring a `border` of pixels on
    /// every side. Errors if the sizes differ or nothing is left inside the border.
    pub fn aepe(&self, truth: &FlowField, border: usize) -> Result<f64> {
        if self.size() != truth.size() {
            return Err(Error::shape(
                "flow against truth",
                truth.size(),
                self.size(),
            ));
        }
        let (w, h) = self.size();
        if w <= 2 * border || h <= 2 * border {
            return Err(Error::TooSmall {
                what: "flow inside the evaluation border".into(),
                width: w,
                height: h,
                min_w: 2 * border + 1,
                min_h: 2 * border + 1,
            });
        }
        let mut sum = 0.0f64;
        for y in border..h - border {
            for x in border..w - border {
                let du = (self.u[[y, x]] - truth.u[[y, x]]) as f64;
                let dv = (self.v[[y, x]] - truth.v[[y, x]]) as f64;
                sum += du.hypot(dv);
            }
        }
        Ok(sum / ((w - 2 * border) * (h - 2 * border)) as f64)
    }
}

/// A seeded xorshift64 stream of values uniform in `[0, 1)` (24-bit), for
/// the flow kernels' bit-for-bit tests: cheap, reproducible, no dependency.
#[cfg(test)]
pub(crate) fn unit_stream(seed: u64) -> impl FnMut() -> f32 {
    let mut state = seed;
    move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn planes_must_match() {
        let e = FlowField::from_planes(Array2::zeros((2, 3)), Array2::zeros((3, 2)));
        assert!(matches!(e, Err(Error::ShapeMismatch { .. })));
    }

    #[test]
    fn aepe_of_a_constant_offset() {
        let a = FlowField::zeros(10, 8);
        let mut b = FlowField::zeros(10, 8);
        b.u.fill(3.0);
        b.v.fill(4.0);
        assert!((a.aepe(&b, 2).unwrap() - 5.0).abs() < 1e-12);
        assert!(a.aepe(&b, 4).is_err());
    }

    /// The plain twin of [`FlowField::stretched_fraction`]: every sampled
    /// cell's stretch in f64 by indexing, one axis at a time.
    fn stretched_fraction_plain(
        f: &FlowField,
        cells: Roi,
        scale: usize,
        lag: usize,
        moving_px: f32,
        strain: f64,
    ) -> f64 {
        let (w, h) = f.size();
        let lag = lag.max(1);
        let step = (lag / 2).max(1);
        let at = |i: usize, j: usize| (f64::from(f.u[[i, j]]), f64::from(f.v[[i, j]]));
        let (mut n, mut k) = (0, 0);
        let mut i = cells.y;
        while i < (cells.y + cells.h).min(h) {
            let mut j = cells.x;
            while j < (cells.x + cells.w).min(w) {
                let (a, b) = at(i, j);
                if a.hypot(b) >= f64::from(moving_px) {
                    n += 1;
                    let mut d2 = 0.0;
                    if j + lag < w {
                        let (c, d) = at(i, j + lag);
                        d2 += (c - a).powi(2) + (d - b).powi(2);
                    }
                    if i + lag < h {
                        let (c, d) = at(i + lag, j);
                        d2 += (c - a).powi(2) + (d - b).powi(2);
                    }
                    if d2.sqrt() / (lag * scale) as f64 >= strain {
                        k += 1;
                    }
                }
                j += step;
            }
            i += step;
        }
        if n == 0 { 0.0 } else { k as f64 / n as f64 }
    }

    /// A field of `w x h` cells from a function of the cell's (x, y).
    fn field(w: usize, h: usize, f: impl Fn(f64, f64) -> (f64, f64)) -> FlowField {
        let u = Array2::from_shape_fn((h, w), |(i, j)| f(j as f64, i as f64).0 as f32);
        let v = Array2::from_shape_fn((h, w), |(i, j)| f(j as f64, i as f64).1 as f32);
        FlowField { u, v }
    }

    #[test]
    fn stretched_fraction_matches_its_plain_twin_on_random_fields() {
        let mut r = unit_stream(0x5EED_0F10);
        for (w, h, amp) in [(40, 30, 0.5f32), (64, 48, 4.0), (33, 17, 12.0)] {
            let mut f = FlowField::zeros(w, h);
            for x in f.u.iter_mut().chain(f.v.iter_mut()) {
                *x = amp * (2.0 * r() - 1.0);
            }
            for (cells, scale, lag) in [
                (Roi::full(w, h), 1, 8),
                (
                    Roi {
                        x: 3,
                        y: 2,
                        w: 20,
                        h: 11,
                    },
                    2,
                    4,
                ),
                (
                    Roi {
                        x: w - 5,
                        y: h - 4,
                        w: 50,
                        h: 50,
                    },
                    1,
                    1,
                ),
                (
                    Roi {
                        x: 1,
                        y: 1,
                        w: 9,
                        h: 7,
                    },
                    4,
                    3,
                ),
            ] {
                for (moving, strain) in [(0.0, 0.1), (0.5, 0.75), (2.0, 1.5)] {
                    let fast = f.stretched_fraction(cells, scale, lag, moving, strain);
                    let plain = stretched_fraction_plain(&f, cells, scale, lag, moving, strain);
                    assert_eq!(fast, plain, "{w}x{h} {cells:?} scale {scale} lag {lag}");
                }
            }
        }
    }

    #[test]
    fn stretched_fraction_of_degenerate_boxes_is_zero() {
        let f = field(20, 10, |x, _| (x, 0.0));
        let nothing = Roi {
            x: 0,
            y: 0,
            w: 0,
            h: 0,
        };
        assert_eq!(f.stretched_fraction(nothing, 1, 8, 0.0, 0.1), 0.0);
        let beyond = Roi {
            x: 30,
            y: 30,
            w: usize::MAX,
            h: usize::MAX,
        };
        assert_eq!(f.stretched_fraction(beyond, 1, 8, 0.0, 0.1), 0.0);
        // Nothing moves enough.
        assert_eq!(
            f.stretched_fraction(Roi::full(20, 10), 1, 8, 100.0, 0.1),
            0.0
        );
        // A lag of 0 counts as 1; an empty field.
        assert!(f.stretched_fraction(Roi::full(20, 10), 1, 0, 0.0, 0.5) > 0.9);
        let empty = FlowField::zeros(0, 0);
        assert_eq!(
            empty.stretched_fraction(Roi::full(5, 5), 1, 8, 0.0, 0.1),
            0.0
        );
        // Lags and scales of any size: no neighbour in the field, nothing
        // stretched, no overflow.
        for (scale, lag) in [(1, usize::MAX), (usize::MAX, 8), (usize::MAX, usize::MAX)] {
            let all = Roi::full(20, 10);
            assert_eq!(f.stretched_fraction(all, scale, lag, 0.0, 0.1), 0.0);
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::test_runner::Config {
            cases: 64,
            rng_seed: proptest::test_runner::RngSeed::Fixed(0x5743_7C4E),
            failure_persistence: None,
            ..proptest::test_runner::Config::default()
        })]

        /// A uniform translation never stretches; a uniform stretch `e`
        /// along x (`u = e x`, in full-resolution pixels) or a rotation by
        /// `e` (stretch `e sqrt 2`) stretches every cell whose neighbour
        /// one lag along x (and along y) is in the field when `e` is above
        /// the bar, none when it is below.
        #[test]
        fn stretched_fraction_of_analytic_fields(
            e in 0.05f64..3.0,
            t in -20.0f64..20.0,
            scale in 1usize..4,
            lag in 1usize..10,
            w in 12usize..60,
            h in 12usize..60,
        ) {
            let all = Roi::full(w, h);
            let shift = field(w, h, |_, _| (t, -0.5 * t));
            proptest::prop_assert_eq!(shift.stretched_fraction(all, scale, lag, 0.0, 0.01), 0.0);
            let s = scale as f64;
            let stretch = field(w, h, |x, _| (e * x * s, 0.0));
            let rotation = field(w, h, |x, y| (-e * y * s, e * x * s));
            let step = (lag / 2).max(1);
            let sampled = |n: usize| n.div_ceil(step);
            // Sampled cells with their neighbour one lag along x (and y) inside.
            let inside = |n: usize| (0..n).step_by(step).filter(|&k| k + lag < n).count();
            let total = (sampled(w) * sampled(h)) as f64;
            for (f, stretch_of, want) in [
                (&stretch, e, (inside(w) * sampled(h)) as f64 / total),
                (&rotation, e * 2f64.sqrt(), (inside(w) * inside(h)) as f64 / total),
            ] {
                let below = f.stretched_fraction(all, scale, lag, 0.0, stretch_of * 1.01);
                let above = f.stretched_fraction(all, scale, lag, 0.0, stretch_of * 0.99);
                // Cells with only one neighbour in the field stretch by less
                // than the bar (the rotation's: e, against e sqrt 2), except
                // the rotation's x-only cells, which reach e and count when
                // the bar is within e.
                proptest::prop_assert_eq!(below, 0.0);
                proptest::prop_assert!(above >= want - 1e-12, "{} < {}", above, want);
            }
        }
    }

    #[test]
    fn nan_is_found() {
        let mut f = FlowField::zeros(4, 4);
        f.v[[2, 1]] = f32::NAN;
        match f.check_finite("flow") {
            Err(Error::NonFinite { row, col, .. }) => assert_eq!((row, col), (2, 1)),
            other => panic!("{other:?}"),
        }
    }
}
