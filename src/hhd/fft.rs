//! Free-space Green's convolution by zero-padded FFT (Hockney's method).
//!
//! The natural HHD needs the *linear* (aperiodic) convolution of the divergence
//! and the curl with the sampled Green's function `G` of the 2-D Laplacian.
//! A circular convolution equals the linear one on the output window as soon
//! as the torus is at least `(2 ny - 1) x (2 nx - 1)`: every offset that can
//! reach an output cell (`|k| <= n - 1`) then has its own place on the torus
//! and none wraps onto another. We pad to the next 5-smooth size (factors 2,
//! 3, 5 only), for which RustFFT is fastest.
//!
//! `G` is real and even, so its spectrum is real: it is computed once per
//! torus `(py, px)` and spacing `(dx, dy)` and kept in a [`GreenConvolver`].
//! The torus holds `G` at offset `min(k, p - k)` in each axis, which is
//! exact for every offset `|o| <= (p - 1) / 2`: one convolver therefore
//! serves every grid up to `((py + 1) / 2, (px + 1) / 2)`, so patches whose
//! size changes by a pixel or two from frame to frame mostly share a plan. Both real inputs
//! travel in one complex signal `div + i curl`; since `G`'s spectrum is real,
//! the real and imaginary parts never mix, and the output is `D + i R`.
//!
//! Layout of one convolution (`py x px` torus, only `ny` rows hold data):
//! 1. `ny` row FFTs of length `px` (the zero rows need none),
//! 2. transpose into `px` contiguous columns of length `py`,
//! 3. column FFTs, multiply by the spectrum, inverse column FFTs,
//! 4. transpose the first `ny` rows back, `ny` inverse row FFTs, crop.

use std::sync::Arc;

use ndarray::{ArrayRef2, ArrayView2};
use rustfft::num_complex::Complex64;
use rustfft::{Fft, FftPlanner};

use crate::error::{Error, Result};

/// Smallest `n >= min` whose only prime factors are 2, 3 and 5.
///
/// Such lengths run fastest in RustFFT; the padding never needs to be a power
/// of two, only at least `2n - 1`.
pub fn fast_len(min: usize) -> usize {
    let mut n = min.max(1);
    loop {
        let mut m = n;
        for p in [2, 3, 5] {
            while m % p == 0 {
                m /= p;
            }
        }
        if m == 1 {
            return n;
        }
        n += 1;
    }
}

/// The Green's function of the 2-D Laplacian sampled at the grid offset
/// `(oy, ox)` (rows, columns) for spacings `dx` (along columns) and `dy`
/// (along rows): `ln(hypot(oy dy, ox dx)) / (2 pi)`, and at the origin, where
/// the logarithm is singular, the reference's value `ln((dx + dy) / 4) / (2 pi)`
/// (the log of half the mean spacing).
pub fn green(oy: usize, ox: usize, dx: f64, dy: f64) -> f64 {
    let r = if oy == 0 && ox == 0 {
        0.5 * ((dy + dx) / 2.0)
    } else {
        (oy as f64 * dy).hypot(ox as f64 * dx)
    };
    r.ln() * (0.5 / std::f64::consts::PI)
}

/// Working buffers shared by all [`GreenConvolver`]s of one planner: they grow
/// to the largest size seen and are then reused, so a convolution allocates
/// nothing once its size has been met.
#[derive(Default)]
pub struct FftWorkspace {
    rows: Vec<Complex64>,
    cols: Vec<Complex64>,
    scratch: Vec<Complex64>,
}

impl FftWorkspace {
    /// An empty workspace; buffers are sized on first use.
    pub fn new() -> Self {
        Self::default()
    }

    /// Makes sure every buffer can hold what `conv` needs for `ny` rows.
    fn reserve_for(&mut self, conv: &GreenConvolver, ny: usize) {
        let rows = ny * conv.px;
        let cols = conv.px * conv.py;
        if self.rows.len() < rows {
            self.rows.resize(rows, Complex64::default());
        }
        if self.cols.len() < cols {
            self.cols.resize(cols, Complex64::default());
        }
        if self.scratch.len() < conv.scratch_len {
            self.scratch.resize(conv.scratch_len, Complex64::default());
        }
    }
}

/// The planned free-space convolution on one padded torus `(py, px)` with
/// spacing `(dx, dy)`: FFT plans and the (real) spectrum of the Green's
/// function, pre-scaled by the cell area `dx dy` and the FFT's `1 / (py px)`.
/// It convolves any grid of up to [`max_shape`](Self::max_shape).
pub struct GreenConvolver {
    py: usize,
    px: usize,
    dx: f64,
    dy: f64,
    fwd_x: Arc<dyn Fft<f64>>,
    inv_x: Arc<dyn Fft<f64>>,
    fwd_y: Arc<dyn Fft<f64>>,
    inv_y: Arc<dyn Fft<f64>>,
    scratch_len: usize,
    /// Spectrum of G times `dx dy / (py px)`, transposed: index `kx * py + ky`.
    green_hat: Vec<f64>,
}

impl std::fmt::Debug for GreenConvolver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GreenConvolver")
            .field("padded", &(self.py, self.px))
            .field("spacing", &(self.dx, self.dy))
            .finish()
    }
}

impl GreenConvolver {
    /// Padded torus `(py, px)` used for a `ny x nx` grid: the smallest
    /// 5-smooth sizes of at least `2n - 1`.
    pub fn torus_for(ny: usize, nx: usize) -> (usize, usize) {
        (fast_len(2 * ny - 1), fast_len(2 * nx - 1))
    }

    /// Plans the convolution for a `ny x nx` grid (rows x columns) with
    /// spacings `dx` (along columns) and `dy` (along rows), on the torus
    /// [`torus_for`](Self::torus_for)`(ny, nx)`.
    ///
    /// Errors on an empty grid or a spacing that is not finite and positive.
    pub fn new(
        planner: &mut FftPlanner<f64>,
        ny: usize,
        nx: usize,
        dx: f64,
        dy: f64,
    ) -> Result<Self> {
        check_grid(ny, nx, dx, dy)?;
        let (py, px) = Self::torus_for(ny, nx);
        let fwd_x = planner.plan_fft_forward(px);
        let inv_x = planner.plan_fft_inverse(px);
        let fwd_y = planner.plan_fft_forward(py);
        let inv_y = planner.plan_fft_inverse(py);
        let scratch_len = [&fwd_x, &inv_x, &fwd_y, &inv_y]
            .iter()
            .map(|f| f.get_inplace_scratch_len())
            .max()
            .unwrap_or(0);
        let mut conv = GreenConvolver {
            py,
            px,
            dx,
            dy,
            fwd_x,
            inv_x,
            fwd_y,
            inv_y,
            scratch_len,
            green_hat: Vec::new(),
        };
        conv.green_hat = conv.green_spectrum();
        Ok(conv)
    }

    /// Largest grid `(ny, nx)` (rows, columns) this convolver handles
    /// exactly: `2n - 1` must fit on the torus.
    pub fn max_shape(&self) -> (usize, usize) {
        (self.py.div_ceil(2), self.px.div_ceil(2))
    }

    /// Padded torus shape `(py, px)`.
    pub fn padded_shape(&self) -> (usize, usize) {
        (self.py, self.px)
    }

    /// Spacings `(dx, dy)` this convolver was planned for.
    pub fn spacing(&self) -> (f64, f64) {
        (self.dx, self.dy)
    }

    /// Spectrum of G on the torus, real part only, scaled and transposed.
    fn green_spectrum(&self) -> Vec<f64> {
        let (py, px) = (self.py, self.px);
        // Wrap-around order: torus index k holds offset k or p - k, whichever
        // is smaller. Every offset a grid of up to max_shape can produce is
        // then exact, and G stays even on the torus.
        // One quadrant of logarithms, mirrored (planning cost matters when
        // patch sizes change often).
        let (qy, qx) = (py / 2 + 1, px / 2 + 1);
        let mut quad = vec![0.0; qy * qx];
        for oy in 0..qy {
            for ox in 0..qx {
                quad[oy * qx + ox] = green(oy, ox, self.dx, self.dy);
            }
        }
        let mut g = vec![Complex64::default(); py * px];
        for (ky, row) in g.chunks_exact_mut(px).enumerate() {
            let q = &quad[ky.min(py - ky) * qx..][..qx];
            for (kx, z) in row.iter_mut().enumerate() {
                z.re = q[kx.min(px - kx)];
            }
        }
        let mut scratch = vec![Complex64::default(); self.scratch_len];
        self.fwd_x.process_with_scratch(&mut g, &mut scratch);
        let mut t = vec![Complex64::default(); py * px];
        transpose(&g, &mut t, py, px, py);
        self.fwd_y.process_with_scratch(&mut t, &mut scratch);
        // G is even, so its spectrum is real up to rounding; the imaginary
        // part is dropped on purpose.
        let scale = self.dx * self.dy / (py * px) as f64;
        t.iter().map(|c| c.re * scale).collect()
    }

    /// The potentials `D = dx dy sum_i div(i) G(m - i)` and
    /// `R = dx dy sum_i curl(i) G(m - i)` over the whole grid, written into
    /// `d_out` and `r_out` (all four arrays of one shape, at most
    /// [`max_shape`](Self::max_shape)).
    ///
    /// Inputs are not checked for NaN here: one NaN makes every output NaN.
    /// Errors if the shapes differ or exceed `max_shape`.
    pub fn potentials(
        &self,
        ws: &mut FftWorkspace,
        div: ArrayView2<'_, f64>,
        curl: ArrayView2<'_, f64>,
        d_out: &mut ArrayRef2<f64>,
        r_out: &mut ArrayRef2<f64>,
    ) -> Result<()> {
        let (ny, nx) = div.dim();
        let (my, mx) = self.max_shape();
        if ny == 0 || nx == 0 || ny > my || nx > mx {
            return Err(Error::shape(
                format!("grid for a Green's convolver of at most {mx}x{my}"),
                (mx, my),
                (nx, ny),
            ));
        }
        for (what, dim) in [
            ("curl", curl.dim()),
            ("D output", d_out.dim()),
            ("R output", r_out.dim()),
        ] {
            if dim != (ny, nx) {
                return Err(Error::shape(what, (nx, ny), (dim.1, dim.0)));
            }
        }
        ws.reserve_for(self, ny);
        let rows = &mut ws.rows[..ny * self.px];
        for ((row, dr), cr) in rows
            .chunks_exact_mut(self.px)
            .zip(div.rows())
            .zip(curl.rows())
        {
            for ((z, &d), &c) in row.iter_mut().zip(&dr).zip(&cr) {
                *z = Complex64::new(d, c);
            }
            row[nx..].fill(Complex64::default());
        }
        self.convolve_rows(ws, ny);
        let rows = &ws.rows[..ny * self.px];
        for ((row, mut dr), mut rr) in rows
            .chunks_exact(self.px)
            .zip(d_out.rows_mut())
            .zip(r_out.rows_mut())
        {
            for ((z, d), r) in row.iter().zip(&mut dr).zip(&mut rr) {
                *d = z.re;
                *r = z.im;
            }
        }
        Ok(())
    }

    /// In place on `ws.rows[..ny * px]`: rows of `div + i curl` (zero-padded
    /// to `px`) in, rows of `D + i R` out (valid in the first `nx` columns).
    fn convolve_rows(&self, ws: &mut FftWorkspace, ny: usize) {
        let (py, px) = (self.py, self.px);
        let scratch = &mut ws.scratch[..self.scratch_len];
        let rows = &mut ws.rows[..ny * px];
        let cols = &mut ws.cols[..px * py];
        self.fwd_x.process_with_scratch(rows, scratch);
        // Column kx gets the ny data rows, then zeros down to py.
        transpose(rows, cols, ny, px, py);
        // One column at a time, forward, product and inverse while it is in
        // L1: three sweeps over the whole torus would run from memory.
        for (col, g) in cols
            .chunks_exact_mut(py)
            .zip(self.green_hat.chunks_exact(py))
        {
            col[ny..].fill(Complex64::default());
            self.fwd_y.process_with_scratch(col, scratch);
            for (c, &g) in col.iter_mut().zip(g) {
                *c *= g;
            }
            self.inv_y.process_with_scratch(col, scratch);
        }
        // Only the first ny rows of the torus are inside the output window.
        transpose_back(cols, rows, ny, px, py);
        self.inv_x.process_with_scratch(rows, scratch);
    }
}

/// `dst[c * dst_stride + r] = src[r * cols + c]` for `r < nrows`, `c < cols`
/// (row-major `nrows x cols` into column-major with a longer column stride).
fn transpose(
    src: &[Complex64],
    dst: &mut [Complex64],
    nrows: usize,
    cols: usize,
    dst_stride: usize,
) {
    // Blocked so that both sides stay in cache for large grids.
    const B: usize = 16;
    for r0 in (0..nrows).step_by(B) {
        let r1 = (r0 + B).min(nrows);
        for c0 in (0..cols).step_by(B) {
            let c1 = (c0 + B).min(cols);
            for r in r0..r1 {
                let s = &src[r * cols..];
                for c in c0..c1 {
                    dst[c * dst_stride + r] = s[c];
                }
            }
        }
    }
}

/// Inverse of [`transpose`] for the first `nrows` entries of every column:
/// `dst[r * cols + c] = src[c * src_stride + r]`.
fn transpose_back(
    src: &[Complex64],
    dst: &mut [Complex64],
    nrows: usize,
    cols: usize,
    src_stride: usize,
) {
    const B: usize = 16;
    for c0 in (0..cols).step_by(B) {
        let c1 = (c0 + B).min(cols);
        for r0 in (0..nrows).step_by(B) {
            let r1 = (r0 + B).min(nrows);
            for c in c0..c1 {
                let s = &src[c * src_stride..];
                for r in r0..r1 {
                    dst[r * cols + c] = s[r];
                }
            }
        }
    }
}

/// Shared validation of a grid and its spacing.
pub(crate) fn check_grid(ny: usize, nx: usize, dx: f64, dy: f64) -> Result<()> {
    if ny == 0 || nx == 0 {
        return Err(Error::TooSmall {
            what: "HHD grid".into(),
            width: nx,
            height: ny,
            min_w: 1,
            min_h: 1,
        });
    }
    for (name, h) in [("dx", dx), ("dy", dy)] {
        if !(h.is_finite() && h > 0.0) {
            return Err(Error::param(
                name,
                format!("grid spacing must be finite and > 0, got {h}"),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_lengths_are_5_smooth_and_minimal() {
        assert_eq!(fast_len(1), 1);
        assert_eq!(fast_len(7), 8);
        assert_eq!(fast_len(63), 64);
        assert_eq!(fast_len(119), 120);
        assert_eq!(fast_len(399), 400);
        assert_eq!(fast_len(511), 512);
        assert_eq!(fast_len(2047), 2048);
        assert_eq!(fast_len(97), 100);
    }

    #[test]
    fn green_at_origin_uses_half_the_mean_spacing() {
        let g0 = green(0, 0, 0.5, 1.5);
        assert!((g0 - (0.5f64).ln() / (2.0 * std::f64::consts::PI)).abs() < 1e-15);
        let g = green(3, 4, 1.0, 1.0);
        assert!((g - 5f64.ln() / (2.0 * std::f64::consts::PI)).abs() < 1e-15);
        // oy runs along rows, so it is scaled by dy.
        let g = green(1, 0, 2.0, 3.0);
        assert!((g - 3f64.ln() / (2.0 * std::f64::consts::PI)).abs() < 1e-15);
    }

    #[test]
    fn transposes_round_trip() {
        let (nr, nc, stride) = (5, 37, 9);
        let src: Vec<Complex64> = (0..nr * nc)
            .map(|i| Complex64::new(i as f64, -(i as f64)))
            .collect();
        let mut t = vec![Complex64::default(); nc * stride];
        transpose(&src, &mut t, nr, nc, stride);
        assert_eq!(t[3 * stride + 2], src[2 * nc + 3]);
        let mut back = vec![Complex64::default(); nr * nc];
        transpose_back(&t, &mut back, nr, nc, stride);
        assert_eq!(back, src);
    }
}
