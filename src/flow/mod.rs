//! Dense optical flow.
//!
//! [`FlowField`] holds a dense 2-D motion field as two planes `u` (motion along
//! image x, i.e. columns) and `v` (along image y, i.e. rows), each of shape
//! `(height, width)`, in pixels.

pub mod color;
pub mod dis;
mod pyramid;
pub mod refine;

pub(crate) use pyramid::sample_clamped;

use ndarray::{Array2, ArrayView2, Zip};

use crate::error::{Error, Result};

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
