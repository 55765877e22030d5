//! Variational refinement of a flow field (brightness + gradient constancy + smoothness).
//!
//! This is the last step of every DIS pyramid level (Kroeger et al. 2016, section 2.3),
//! with the semantics of OpenCV 5's `VariationalRefinement`: a Brox-style energy
//!
//! ```text
//! E(w) = sum_x  delta * Psi(rho_I)  +  gamma * Psi(rho_grad)  +  alpha * Psi(|grad u|^2 + |grad v|^2)
//! ```
//!
//! where `rho_I = (I_z + I_x du + I_y dv)^2 / (|grad I|^2 + zeta^2)` is the brightness
//! constancy residual normalised by the local gradient, `rho_grad` the same for the
//! two image gradients (constancy of `I_x`, `I_y`), and `Psi(s^2) = sqrt(s^2 + epsilon^2)`
//! the Charbonnier penalty. The energy is linearised once per call around the current
//! image warped by the incoming flow; then `outer_iterations` fixed-point iterations
//! re-evaluate the Charbonnier weights (lagged non-linearity) and solve the resulting
//! linear system (for the flow; equivalently its increment over the incoming flow) with
//! `sor_iterations` red-black SOR sweeps.
//!
//! Image derivatives are taken on the average of the reference and the warped current
//! image; `I_z` is their difference. The derivative kernel is `[-1 0 1]` (OpenCV's, twice
//! the true derivative, so each call moves only about half the residual) or, with
//! [`RefineParams::exact_derivatives`], the correctly scaled `[-1 0 1] / 2`. Second
//! derivatives are the same kernel applied twice; borders are replicated.
//!
//! Everything that depends only on the reference (its derivatives) is computed once in
//! [`VariationalRefiner::set_reference`]; [`VariationalRefiner::refine`] reuses buffers
//! sized for the level and allocates nothing. Work is split over rows with rayon. Each
//! outer iteration is a set of row items (weights, system, SOR half-sweeps) whose
//! dependencies are only between neighbouring rows of consecutive stages, so every
//! schedule that respects them computes exactly the same values: on one thread the
//! items run in a single row sweep (cache-resident), on two threads the two halves
//! sweep towards each other and the band between them follows, on more threads each
//! stage is a parallel pass over rows. The result is bit-identical for any number of
//! threads.
//!
//! Layout: the solver stores every per-pixel quantity split by checkerboard colour
//! ("red" where `row + col` is even, "black" where it is odd), one contiguous padded row
//! per image row and colour, so that a red half-sweep reads contiguous black rows and the
//! inner loops vectorise (see the private `Grid`).

use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// Largest number of outer iterations, and of SOR sweeps per outer iteration,
/// of the variational refinement: 100 each (OpenCV uses 5 and 5; 100 x 100
/// sweeps of a full-HD level already take tens of seconds).
pub const MAX_ITERATIONS: usize = 100;

/// Parameters of the variational refinement (the VR step of DIS).
///
/// The energy weights follow OpenCV's conventions: each of `alpha`, `delta`, `gamma`
/// enters the linear system halved (it multiplies a squared term).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineParams {
    /// Number of fixed-point (outer) iterations, at most [`MAX_ITERATIONS`]: each
    /// re-evaluates the Charbonnier weights around the current increment and solves
    /// the linear system again. `0` makes [`VariationalRefiner::refine`] a no-op
    /// (after checking its input).
    pub outer_iterations: usize,
    /// Number of red-black SOR sweeps per outer iteration (each sweep updates all red
    /// pixels, then all black pixels), at most [`MAX_ITERATIONS`].
    pub sor_iterations: usize,
    /// SOR relaxation factor, in `(0, 2)`; `1` is plain Gauss-Seidel.
    pub omega: f32,
    /// Weight of the smoothness term (flow gradients), in `[0, 1e6]`.
    pub alpha: f32,
    /// Weight of the normalised brightness-constancy term, in `[0, 1e6]`.
    pub delta: f32,
    /// Weight of the normalised gradient-constancy term, in `[0, 1e6]`.
    pub gamma: f32,
    /// Charbonnier epsilon: `Psi(s^2) = sqrt(s^2 + epsilon^2)`, in `[1e-6, 1e3]`. Below
    /// `epsilon` (in the units of the normalised residual, about pixels of motion) the
    /// penalties behave quadratically, above it like L1.
    pub epsilon: f32,
    /// Normalisation regulariser, in `[1e-6, 1e3]`: the data terms are divided by
    /// `|gradient|^2 + zeta^2`, so flat regions (gradient below `zeta`) get little data
    /// weight. `zeta^2` is also added to the diagonal of the system.
    pub zeta: f32,
    /// `false`: derivatives with the kernel `[-1 0 1]` as OpenCV does (twice the true
    /// derivative; a call then corrects only about half the residual motion).
    /// `true`: the correctly scaled central difference `[-1 0 1] / 2`.
    pub exact_derivatives: bool,
}

impl RefineParams {
    /// OpenCV 5's values as DIS uses them in its FAST and MEDIUM presets: 5 outer
    /// iterations, 5 SOR sweeps, omega 1.6, alpha 20, delta 5, gamma 10, epsilon 0.01,
    /// zeta 0.1, OpenCV's un-halved derivatives.
    ///
    /// Note: the OpenCV 5.0 Python wheel's `VariationalRefinement` defaults to
    /// epsilon 0.001 (DIS does not set it). With `epsilon: 0.001` this implementation
    /// reproduces OpenCV's output to a mean of 3e-7 px (see
    /// `examples/refine_vs_opencv.rs`); with 0.01 the two differ by about 0.004 px.
    pub fn opencv() -> Self {
        RefineParams {
            outer_iterations: 5,
            sor_iterations: 5,
            omega: 1.6,
            alpha: 20.0,
            delta: 5.0,
            gamma: 10.0,
            epsilon: 0.01,
            zeta: 0.1,
            exact_derivatives: false,
        }
    }

    /// The most accurate setting measured on synthetic marker images, at the same cost
    /// as [`RefineParams::opencv`]: correctly scaled derivatives (each call then moves
    /// the flow the whole way to the linearised optimum, not half of it) and SOR
    /// over-relaxation `omega = 1.9` (5 sweeps per outer iteration leave the smooth,
    /// patch-sized part of the error far from converged at 1.6).
    ///
    /// Measured by `accuracy_table` in `tests/refine.rs` (480x270 level, Gaussian
    /// markers of sigma 1 and 0.7 px, bump and translation motions, smooth initial
    /// errors of 0.08 and 0.23 px AEPE): mean ratio of AEPE after / before refinement
    /// 0.587 with OpenCV's parameters, 0.385 with exact derivatives alone, 0.231 with
    /// exact derivatives and omega 1.9 (0.226 at omega 1.95, kept at 1.9 for margin
    /// from 2; alpha 10/15/40, delta 10, gamma 0, epsilon 0.001 all measured worse).
    pub fn accurate() -> Self {
        RefineParams {
            exact_derivatives: true,
            omega: 1.9,
            ..Self::opencv()
        }
    }

    /// Checks that every parameter is in its valid range.
    pub fn validate(&self) -> Result<()> {
        // The solver multiplies weights (up to about alpha / epsilon and delta, gamma /
        // epsilon) and forms products of two diagonal entries (at least zeta^2 each)
        // in f32: these bounds keep every intermediate finite and normal.
        let weight = |name: &str, x: f32| {
            if (0.0..=1e6).contains(&x) {
                Ok(())
            } else {
                Err(Error::param(name, format!("must be in [0, 1e6], got {x}")))
            }
        };
        let small = |name: &str, x: f32| {
            if (1e-6..=1e3).contains(&x) {
                Ok(())
            } else {
                Err(Error::param(
                    name,
                    format!("must be in [1e-6, 1e3], got {x}"),
                ))
            }
        };
        for (name, n) in [
            ("outer_iterations", self.outer_iterations),
            ("sor_iterations", self.sor_iterations),
        ] {
            if n > MAX_ITERATIONS {
                return Err(Error::param(
                    name,
                    format!("at most {MAX_ITERATIONS}, got {n}"),
                ));
            }
        }
        if !(self.omega > 0.0 && self.omega < 2.0) {
            return Err(Error::param(
                "omega",
                format!("SOR needs 0 < omega < 2, got {}", self.omega),
            ));
        }
        weight("alpha", self.alpha)?;
        weight("delta", self.delta)?;
        weight("gamma", self.gamma)?;
        small("epsilon", self.epsilon)?;
        small("zeta", self.zeta)?;
        Ok(())
    }
}

impl Default for RefineParams {
    /// [`RefineParams::accurate`].
    fn default() -> Self {
        Self::accurate()
    }
}

// Quantities stored per colour row. Normalised derivatives of the data terms
// (recomputed per call), each multiplied by 1/sqrt of its term's normaliser so that the
// per-iteration work needs no division: brightness (I_x, I_y, I_z) / sqrt(I_x^2 + I_y^2
// + zeta^2); constancy of I_x: (I_xx, I_xy, I_xz) / sqrt(I_xx^2 + I_xy^2 + zeta^2);
// constancy of I_y: (I_xy, I_yy, I_yz) / sqrt(I_xy^2 + I_yy^2 + zeta^2).
const N_DERIV: usize = 9;
// Linear-system coefficients (per outer iteration; the A11 and A22 slots hold
// omega / diagonal) and smoothness weights of the edges to the right and
// down neighbours (0 where there is no neighbour):
const A11: usize = 0;
const A12: usize = 1;
const A22: usize = 2;
const B1: usize = 3;
const B2: usize = 4;
const WR: usize = 5;
const WD: usize = 6;
const N_COEF: usize = 7;
// Flow planes (the incoming flow of the call, and the current flow being solved for):
const U: usize = 0;
const V: usize = 1;
const N_FLOW: usize = 2;

/// Geometry of the checkerboard-split layout.
///
/// Pixel `(i, j)` has colour `c = (i + j) % 2` (0 red, 1 black). In row `i` the pixels
/// of colour `c` sit at `j = 2k + p` with `p = (i + c) % 2`, `k = 0..n(c, i)`. Each
/// colour buffer has `h + 2` padded rows (image row `i` in buffer row `i + 1`); each
/// padded row holds `nq` quantities of `stride` floats, the pixel `k` at offset `k + 1`.
/// Pads stay zero. Then for a pixel `k` of colour `c` in row `i` (padded offsets into the
/// other colour's rows): left neighbour `k + p`, right `k + 1 + p`, up and down `k + 1`
/// in rows `i - 1`, `i + 1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct Grid {
    w: usize,
    h: usize,
    stride: usize,
}

impl Grid {
    fn new(w: usize, h: usize) -> Self {
        Grid {
            w,
            h,
            stride: w.div_ceil(2) + 2,
        }
    }

    /// Offset `p` of colour `c` in row `i`.
    #[inline]
    fn p(c: usize, i: usize) -> usize {
        (i + c) % 2
    }

    /// Number of pixels of colour `c` in row `i`.
    #[inline]
    fn n(&self, c: usize, i: usize) -> usize {
        let p = Self::p(c, i);
        (self.w - p).div_ceil(2)
    }

    fn buf_len(&self, nq: usize) -> usize {
        (self.h + 2) * nq * self.stride
    }
}

/// Data cached from the reference image.
#[derive(Debug, Default)]
struct Reference {
    grid: Grid,
    i0: Vec<f32>,
    gx: Vec<f32>,
    gy: Vec<f32>,
    gxx: Vec<f32>,
    gxy: Vec<f32>,
    gyy: Vec<f32>,
}

/// Per-call working buffers, sized for the reference.
#[derive(Debug, Default)]
struct Work {
    /// Contiguous copy of the current image, used only when the caller's view is not
    /// contiguous.
    i1: Vec<f32>,
    warped: Vec<f32>,
    wx: Vec<f32>,
    wy: Vec<f32>,
    deriv: [Vec<f32>; 2],
    coef: [Vec<f32>; 2],
    base: [Vec<f32>; 2],
    flow: [Vec<f32>; 2],
}

/// Variational refinement planned for one image size (one DIS pyramid level) and one
/// fixed reference image.
///
/// ```
/// use ndarray::Array2;
/// use optical_tactile::flow::refine::{RefineParams, VariationalRefiner};
///
/// let i0 = Array2::from_shape_fn((32, 40), |(y, x)| 128.0 + 60.0 * ((x as f32) * 0.5).sin() * ((y as f32) * 0.4).cos());
/// let mut vr = VariationalRefiner::new(RefineParams::accurate());
/// vr.set_reference(i0.view())?;
/// let (mut u, mut v) = (Array2::zeros((32, 40)), Array2::zeros((32, 40)));
/// vr.refine(i0.view(), &mut u, &mut v)?; // same image: the flow stays zero
/// assert!(u.iter().chain(v.iter()).all(|&x| x == 0.0));
/// # Ok::<(), optical_tactile::Error>(())
/// ```
#[derive(Debug)]
pub struct VariationalRefiner {
    params: RefineParams,
    reference: Option<Reference>,
    work: Work,
}

/// Rows per rayon task: enough pixels that scheduling overhead stays small.
fn rows_per_task(w: usize) -> usize {
    (4096 / w.max(1)).max(1)
}

/// Central difference along x with replicated borders: `s * (f[j+1] - f[j-1])`.
fn deriv_x(src: &[f32], dst: &mut [f32], w: usize, s: f32) {
    let mt = rows_per_task(w);
    dst.par_chunks_mut(w)
        .zip(src.par_chunks(w))
        .with_min_len(mt)
        .for_each(|(d, r)| {
            d[0] = s * (r[1] - r[0]);
            for j in 1..w - 1 {
                d[j] = s * (r[j + 1] - r[j - 1]);
            }
            d[w - 1] = s * (r[w - 1] - r[w - 2]);
        });
}

/// Central difference along y with replicated borders: `s * (f[i+1] - f[i-1])`.
fn deriv_y(src: &[f32], dst: &mut [f32], w: usize, h: usize, s: f32) {
    let mt = rows_per_task(w);
    dst.par_chunks_mut(w)
        .enumerate()
        .with_min_len(mt)
        .for_each(|(i, d)| {
            let up = &src[i.saturating_sub(1) * w..][..w];
            let down = &src[(i + 1).min(h - 1) * w..][..w];
            for j in 0..w {
                d[j] = s * (down[j] - up[j]);
            }
        });
}

fn check_size(what: &str, w: usize, h: usize) -> Result<()> {
    if w < 2 || h < 2 {
        return Err(Error::TooSmall {
            what: what.to_string(),
            width: w,
            height: h,
            min_w: 2,
            min_h: 2,
        });
    }
    Ok(())
}

fn check_finite(what: &str, a: ArrayView2<f32>) -> Result<()> {
    // Fast scan first (contiguous, vectorisable); locate the culprit only on failure.
    let all_finite = match a.as_slice() {
        Some(sl) => sl.iter().fold(true, |ok, x| ok & x.is_finite()),
        None => a.iter().all(|x| x.is_finite()),
    };
    if all_finite {
        return Ok(());
    }
    let ((row, col), _) = a
        .indexed_iter()
        .find(|(_, x)| !x.is_finite())
        .expect("a non-finite value exists");
    Err(Error::NonFinite {
        what: what.to_string(),
        row,
        col,
    })
}

impl VariationalRefiner {
    /// A refiner with the given parameters; call [`set_reference`](Self::set_reference)
    /// before [`refine`](Self::refine).
    pub fn new(params: RefineParams) -> Self {
        VariationalRefiner {
            params,
            reference: None,
            work: Work::default(),
        }
    }

    /// The parameters in use.
    pub fn params(&self) -> &RefineParams {
        &self.params
    }

    /// `(width, height)` of the current reference, if one is set.
    pub fn size(&self) -> Option<(usize, usize)> {
        self.reference.as_ref().map(|r| (r.grid.w, r.grid.h))
    }

    /// Sets the reference image `i0` (shape `(height, width)`, 8-bit scale) and caches
    /// everything that depends only on it: its first and second derivatives, and the
    /// working buffers for its size (re-planned only when the size changes).
    ///
    /// Errors: invalid parameters, an image smaller than 2x2, non-finite values.
    pub fn set_reference(&mut self, i0: ArrayView2<f32>) -> Result<()> {
        self.params.validate()?;
        let (h, w) = i0.dim();
        check_size("variational refinement reference", w, h)?;
        check_finite("variational refinement reference", i0)?;
        let grid = Grid::new(w, h);
        let mut r = self.reference.take().unwrap_or_default();
        if r.grid != grid {
            let n = w * h;
            r = Reference {
                grid,
                i0: vec![0.0; n],
                gx: vec![0.0; n],
                gy: vec![0.0; n],
                gxx: vec![0.0; n],
                gxy: vec![0.0; n],
                gyy: vec![0.0; n],
            };
            self.work = Work {
                i1: Vec::new(),
                warped: vec![0.0; n],
                wx: vec![0.0; n],
                wy: vec![0.0; n],
                deriv: std::array::from_fn(|_| vec![0.0; grid.buf_len(N_DERIV)]),
                coef: std::array::from_fn(|_| vec![0.0; grid.buf_len(N_COEF)]),
                base: std::array::from_fn(|_| vec![0.0; grid.buf_len(N_FLOW)]),
                flow: std::array::from_fn(|_| vec![0.0; grid.buf_len(N_FLOW)]),
            };
        }
        for (d, &x) in r.i0.iter_mut().zip(i0.iter()) {
            *d = x;
        }
        let s = self.deriv_scale();
        deriv_x(&r.i0, &mut r.gx, w, s);
        deriv_y(&r.i0, &mut r.gy, w, h, s);
        deriv_x(&r.gx, &mut r.gxx, w, s);
        deriv_y(&r.gx, &mut r.gxy, w, h, s);
        deriv_y(&r.gy, &mut r.gyy, w, h, s);
        self.reference = Some(r);
        Ok(())
    }

    fn deriv_scale(&self) -> f32 {
        if self.params.exact_derivatives {
            0.5
        } else {
            1.0
        }
    }

    /// Refines the flow `(u, v)` (reference -> current `i1`, in pixels of this level)
    /// in place.
    ///
    /// Errors: no reference set ([`Error::NoReference`]), `i1`, `u` or `v` of another
    /// shape than the reference, non-finite values in them, invalid parameters.
    pub fn refine(
        &mut self,
        i1: ArrayView2<f32>,
        u: &mut Array2<f32>,
        v: &mut Array2<f32>,
    ) -> Result<()> {
        self.params.validate()?;
        let r = self.reference.as_ref().ok_or(Error::NoReference)?;
        let g = r.grid;
        let expected = (g.w, g.h);
        for (what, a) in [
            ("current image against the refinement reference", i1),
            ("flow u against the refinement reference", u.view()),
            ("flow v against the refinement reference", v.view()),
        ] {
            if a.dim() != (g.h, g.w) {
                return Err(Error::shape(what, expected, (a.ncols(), a.nrows())));
            }
        }
        check_finite("current image", i1)?;
        check_finite("flow u", u.view())?;
        check_finite("flow v", v.view())?;
        if self.params.outer_iterations == 0 {
            return Ok(());
        }
        let s = self.deriv_scale();
        let p = self.params;
        let work = &mut self.work;

        // Run the whole call on a rayon worker: called from outside a pool, every
        // parallel pass would otherwise be injected into the pool separately (~70 per
        // call), each paying a cross-thread wake-up.
        rayon::scope(|_| {
            // Current image as a contiguous slice (copy only if the caller's view is not).
            let i1s: &[f32] = match i1.as_slice() {
                Some(sl) => sl,
                None => {
                    work.i1.clear();
                    work.i1.extend(i1.iter().copied());
                    &work.i1
                }
            };
            warp(i1s, u, v, g, &mut work.warped);
            deriv_x(&work.warped, &mut work.wx, g.w, s);
            deriv_y(&work.warped, &mut work.wy, g.w, g.h, s);
            split_derivatives(
                r,
                &work.warped,
                &work.wx,
                &work.wy,
                s,
                p.zeta * p.zeta,
                &mut work.deriv,
            );
            split_flow(u, v, g, &mut work.base);
            // The solver iterates on the total flow, starting from the incoming one.
            for c in 0..2 {
                work.flow[c].copy_from_slice(&work.base[c]);
            }

            let threads = rayon::current_num_threads();
            for _ in 0..p.outer_iterations {
                if threads <= 2 {
                    // The whole outer iteration in cache-friendly row sweeps.
                    outer_wavefront(
                        g,
                        &p,
                        &work.deriv,
                        &work.base,
                        &mut work.coef,
                        &mut work.flow,
                        threads == 2,
                    );
                    continue;
                }
                for c in 0..2 {
                    smoothness_weights(g, c, &p, &work.flow, &mut work.coef);
                }
                for c in 0..2 {
                    assemble(
                        g,
                        c,
                        &p,
                        &work.deriv[c],
                        &work.base,
                        &work.flow[c],
                        &mut work.coef,
                    );
                }
                for _ in 0..p.sor_iterations {
                    for c in 0..2 {
                        sor_half_sweep(g, c, p.omega, &work.coef, &mut work.flow);
                    }
                }
            }
            merge_flow(g, &work.flow, u, v);
        });
        Ok(())
    }
}

/// Bilinear warp of `i1` by the flow (sampling `i1(x + u, y + v)`), borders replicated.
fn warp(i1: &[f32], u: &Array2<f32>, v: &Array2<f32>, g: Grid, out: &mut [f32]) {
    let (w, h) = (g.w, g.h);
    let xmax = (w - 1) as f32;
    let ymax = (h - 1) as f32;
    let mt = rows_per_task(w);
    out.par_chunks_mut(w)
        .enumerate()
        .with_min_len(mt)
        .for_each(|(i, row)| {
            let (ur, vr) = (u.row(i), v.row(i));
            // Rows of standard-layout arrays as slices: no per-element index checks.
            if let (Some(ur), Some(vr)) = (ur.as_slice(), vr.as_slice()) {
                warp_row(i1, w, h, i, ur, vr, row);
                return;
            }
            for j in 0..w {
                // Clamping the sample position is exactly bilinear interpolation of the
                // border-replicated image.
                let x = (j as f32 + ur[j]).clamp(0.0, xmax);
                let y = (i as f32 + vr[j]).clamp(0.0, ymax);
                // x, y >= 0, so truncation is floor (and avoids a libm call: SSE2 has
                // no vector floor).
                let x0 = (x as usize).min(w - 2);
                let y0 = (y as usize).min(h - 2);
                let fx = x - x0 as f32;
                let fy = y - y0 as f32;
                let r0 = &i1[y0 * w + x0..][..2];
                let r1 = &i1[(y0 + 1) * w + x0..][..2];
                // Weighted form (not `a + f * (b - a)`): exact at f = 0 and f = 1, so a
                // zero flow reproduces the image bit for bit.
                let top = (1.0 - fx) * r0[0] + fx * r0[1];
                let bot = (1.0 - fx) * r1[0] + fx * r1[1];
                row[j] = (1.0 - fy) * top + fy * bot;
            }
        });
}

/// [`warp`] of image row `i` from contiguous flow rows (same arithmetic).
///
/// In chunks of [`WARP_CHUNK`] pixels and three passes, so that two of them
/// vectorise: the sample positions, fractions and flat offsets (4 lanes), then
/// the four taps of every pixel gathered one pixel at a time (SSE2 has no
/// gather), then the bilinear blends (4 lanes). The per-pixel form was scalar
/// throughout (~58 instructions per pixel). Same values bit for bit; the
/// per-pixel form is the oracle in the tests.
///
/// Dispatched at run time like [`sor_row`].
#[inline(never)]
fn warp_row(i1: &[f32], w: usize, h: usize, i: usize, ur: &[f32], vr: &[f32], row: &mut [f32]) {
    super::simd_arch().dispatch(WarpOp {
        i1,
        w,
        h,
        i,
        ur,
        vr,
        row,
    });
}

/// [`warp_row_kernel`]'s arguments as a `pulp` operation (see [`SorOp`]).
struct WarpOp<'a> {
    i1: &'a [f32],
    w: usize,
    h: usize,
    i: usize,
    ur: &'a [f32],
    vr: &'a [f32],
    row: &'a mut [f32],
}

impl pulp::WithSimd for WarpOp<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        warp_row_kernel(self.i1, self.w, self.h, self.i, self.ur, self.vr, self.row);
    }
}

/// The body of [`warp_row`].
#[inline(always)]
fn warp_row_kernel(
    i1: &[f32],
    w: usize,
    h: usize,
    i: usize,
    ur: &[f32],
    vr: &[f32],
    row: &mut [f32],
) {
    // Offsets in u32 (a 32-bit multiply vectorises, a 64-bit one does not): a
    // level this large never reaches the refinement, but stay exact anyway.
    if w * h > u32::MAX as usize {
        warp_row_scalar(i1, w, h, i, ur, vr, row);
        return;
    }
    let xmax = (w - 1) as f32;
    let ymax = (h - 1) as f32;
    let (wm2, hm2) = ((w - 2) as i32, (h - 2) as i32);
    let yi = i as f32;
    let w32 = w as u32;
    let n = row.len();
    let (ur, vr) = (&ur[..n], &vr[..n]);
    let mut idx = [0u32; WARP_CHUNK];
    let mut fx = [0.0f32; WARP_CHUNK];
    let mut fy = [0.0f32; WARP_CHUNK];
    let mut taps = [[0.0f32; WARP_CHUNK]; 4];
    for (c, ((out, uc), vc)) in row
        .chunks_mut(WARP_CHUNK)
        .zip(ur.chunks(WARP_CHUNK))
        .zip(vr.chunks(WARP_CHUNK))
        .enumerate()
    {
        let len = out.len();
        let j0 = (c * WARP_CHUNK) as i32;
        let (idx, fx, fy) = (&mut idx[..len], &mut fx[..len], &mut fy[..len]);
        let (uc, vc) = (&uc[..len], &vc[..len]);
        for t in 0..len {
            // 0 <= x, y < 2^31: the i32 conversion is exact (x, y are whole
            // numbers plus a fraction, far below 2^24 here).
            let x = ((j0 + t as i32) as f32 + uc[t]).clamp(0.0, xmax);
            let y = (yi + vc[t]).clamp(0.0, ymax);
            let x0 = (x as i32).min(wm2);
            let y0 = (y as i32).min(hm2);
            fx[t] = x - x0 as f32;
            fy[t] = y - y0 as f32;
            idx[t] = y0 as u32 * w32 + x0 as u32;
        }
        let [t00, t01, t10, t11] = &mut taps;
        let (t00, t01, t10, t11) = (
            &mut t00[..len],
            &mut t01[..len],
            &mut t10[..len],
            &mut t11[..len],
        );
        for t in 0..len {
            // x0 <= w - 2 and y0 <= h - 2, so the 2x2 block is inside.
            let q = &i1[idx[t] as usize..][..w + 2];
            t00[t] = q[0];
            t01[t] = q[1];
            t10[t] = q[w];
            t11[t] = q[w + 1];
        }
        for t in 0..len {
            // Weighted form (not `a + f * (b - a)`): exact at f = 0 and f = 1, so a
            // zero flow reproduces the image bit for bit.
            let top = (1.0 - fx[t]) * t00[t] + fx[t] * t01[t];
            let bot = (1.0 - fx[t]) * t10[t] + fx[t] * t11[t];
            out[t] = (1.0 - fy[t]) * top + fy[t] * bot;
        }
    }
}

/// Pixels per chunk of [`warp_row`] (stack arrays of this many values).
const WARP_CHUNK: usize = 128;

/// [`warp_row`] one pixel at a time: the oracle of its tests, and its fallback
/// for levels with more than 2^32 pixels.
fn warp_row_scalar(
    i1: &[f32],
    w: usize,
    h: usize,
    i: usize,
    ur: &[f32],
    vr: &[f32],
    row: &mut [f32],
) {
    let xmax = (w - 1) as f32;
    let ymax = (h - 1) as f32;
    let (ur, vr) = (&ur[..row.len()], &vr[..row.len()]);
    for (j, ((o, &u), &v)) in row.iter_mut().zip(ur).zip(vr).enumerate() {
        let x = (j as f32 + u).clamp(0.0, xmax);
        let y = (i as f32 + v).clamp(0.0, ymax);
        // 0 <= x, y < 2^31: the i32 conversion is one instruction (usize is not).
        let x0 = (x as i32 as usize).min(w - 2);
        let y0 = (y as i32 as usize).min(h - 2);
        let fx = x - x0 as i32 as f32;
        let fy = y - y0 as i32 as f32;
        let r0 = &i1[y0 * w + x0..][..2];
        let r1 = &i1[(y0 + 1) * w + x0..][..2];
        let top = (1.0 - fx) * r0[0] + fx * r0[1];
        let bot = (1.0 - fx) * r1[0] + fx * r1[1];
        *o = (1.0 - fy) * top + fy * bot;
    }
}

/// Builds the normalised derivatives of the linearised data terms in the split layout
/// (see `N_DERIV`): derivatives of the average of `I0` and the warped `I1` (from the
/// cached reference derivatives plus those of the warped image), `I_z = warped - I0`
/// and its derivatives.
fn split_derivatives(
    r: &Reference,
    warped: &[f32],
    wx: &[f32],
    wy: &[f32],
    s: f32,
    z2: f32,
    deriv: &mut [Vec<f32>; 2],
) {
    let g = r.grid;
    let (w, h, st) = (g.w, g.h, g.stride);
    let rl = N_DERIV * st;
    let [red, black] = deriv;
    let mt = rows_per_task(w);
    red[rl..(h + 1) * rl]
        .par_chunks_mut(rl)
        .zip(black[rl..(h + 1) * rl].par_chunks_mut(rl))
        .enumerate()
        .with_min_len(mt)
        // The nine chunk arrays (9 KiB) are created once per rayon job, not zeroed
        // again for every row: every value read is written first.
        .for_each_init(
            || [[0.0f32; DERIV_CHUNK]; N_DERIV],
            |q, (i, (rrow, brow))| {
                let up = i.saturating_sub(1) * w;
                let dn = (i + 1).min(h - 1) * w;
                let o = i * w;
                fn seg(a: &[f32], off: usize, n: usize) -> &[f32] {
                    &a[off..][..n]
                }
                let row = |a, off| seg(a, off, w);
                let (wxr, wyr) = (row(wx, o), row(wy, o));
                let (wxu, wxd, wyu, wyd) = (row(wx, up), row(wx, dn), row(wy, up), row(wy, dn));
                let (gx, gy, gxx, gxy, gyy) = (
                    row(&r.gx, o),
                    row(&r.gy, o),
                    row(&r.gxx, o),
                    row(&r.gxy, o),
                    row(&r.gyy, o),
                );
                let (i0, wr) = (row(&r.i0, o), row(warped, o));
                // The row in chunks of DERIV_CHUNK pixels (even, so a chunk's
                // colours start at the row's parity): the nine quantities
                // computed and normalised on contiguous stack arrays (loops that
                // vectorise), then dealt out to the two colours. Same arithmetic
                // per pixel as a per-pixel loop, so the same result.
                let mut j0 = 0;
                while j0 < w {
                    let len = DERIV_CHUNK.min(w - j0);
                    let [bx, by, bz, xx, xy, xz, yx, yy, yz] = &mut *q;
                    let sl = |a| seg(a, j0, len);
                    let (cgx, cgy, cwx, cwy) = (sl(gx), sl(gy), sl(wxr), sl(wyr));
                    let (cgxx, cgxy, cgyy) = (sl(gxx), sl(gxy), sl(gyy));
                    let (ci0, cwr) = (sl(i0), sl(wr));
                    let (cxu, cxd, cyu, cyd) = (sl(wxu), sl(wxd), sl(wyu), sl(wyd));
                    for t in 0..len {
                        bx[t] = 0.5 * (cgx[t] + cwx[t]);
                        by[t] = 0.5 * (cgy[t] + cwy[t]);
                        bz[t] = cwr[t] - ci0[t];
                        // wxx is filled below (it needs the row's neighbours).
                        let wxy = s * (cxd[t] - cxu[t]);
                        let wyy = s * (cyd[t] - cyu[t]);
                        let ixy = 0.5 * (cgxy[t] + wxy);
                        xy[t] = ixy;
                        xz[t] = cwx[t] - cgx[t];
                        yx[t] = ixy;
                        yy[t] = 0.5 * (cgyy[t] + wyy);
                        yz[t] = cwy[t] - cgy[t];
                    }
                    // I_xx: central difference of wx along the row, replicated at
                    // the ends (interior first, as contiguous slices).
                    let lo = usize::from(j0 == 0);
                    let hi = if j0 + len == w { len - 1 } else { len };
                    if hi > lo {
                        let n = hi - lo;
                        let right = &wxr[j0 + lo + 1..][..n];
                        let left = &wxr[j0 + lo - 1..][..n];
                        let (cg, out) = (&cgxx[lo..hi], &mut xx[lo..hi]);
                        for t in 0..n {
                            out[t] = 0.5 * (cg[t] + s * (right[t] - left[t]));
                        }
                    }
                    for t in (0..lo).chain(hi..len) {
                        let j = j0 + t;
                        let (jl, jr) = (j.saturating_sub(1), (j + 1).min(w - 1));
                        xx[t] = 0.5 * (cgxx[t] + s * (wxr[jr] - wxr[jl]));
                    }
                    {
                        let [bx, by, bz, xx, xy, xz, yx, yy, yz] =
                            q.each_mut().map(|a| &mut a[..len]);
                        normalise([bx, by, bz], z2);
                        normalise([xx, xy, xz], z2);
                        normalise([yx, yy, yz], z2);
                    }
                    for (c, dst) in [&mut *rrow, &mut *brow].into_iter().enumerate() {
                        let p = Grid::p(c, i);
                        if len <= p {
                            continue;
                        }
                        // Pixels j0 + p, j0 + p + 2, ... are k = j0 / 2, j0 / 2 + 1, ...
                        let cnt = (len - p).div_ceil(2);
                        for (plane, src) in dst.chunks_exact_mut(st).zip(q.iter()) {
                            let out = &mut plane[1 + j0 / 2..][..cnt];
                            for (m, v) in out.iter_mut().enumerate() {
                                *v = src[2 * m + p];
                            }
                        }
                    }
                    j0 += len;
                }
            },
        );
}

/// Pixels per chunk of a row in [`split_derivatives`] (even; nine stack
/// arrays of this many floats).
const DERIV_CHUNK: usize = 256;

/// Divides `(a, b, c)` by `sqrt(a^2 + b^2 + z2)` element-wise, in place.
#[inline(never)]
fn normalise([a, b, c]: [&mut [f32]; 3], z2: f32) {
    let n = a.len();
    let (b, c) = (&mut b[..n], &mut c[..n]);
    for k in 0..n {
        let f = 1.0 / (a[k] * a[k] + b[k] * b[k] + z2).sqrt();
        a[k] *= f;
        b[k] *= f;
        c[k] *= f;
    }
}

/// Copies the incoming flow into the split layout (pads stay zero).
fn split_flow(u: &Array2<f32>, v: &Array2<f32>, g: Grid, base: &mut [Vec<f32>; 2]) {
    let (w, h, st) = (g.w, g.h, g.stride);
    let rl = N_FLOW * st;
    let [red, black] = base;
    red[rl..(h + 1) * rl]
        .par_chunks_mut(rl)
        .zip(black[rl..(h + 1) * rl].par_chunks_mut(rl))
        .enumerate()
        .with_min_len(rows_per_task(w))
        .for_each(|(i, (rrow, brow))| {
            let (ur, vr) = (u.row(i), v.row(i));
            for (c, dst) in [rrow, brow].into_iter().enumerate() {
                let (n, p) = (g.n(c, i), Grid::p(c, i));
                let (du, dv) = dst.split_at_mut(st);
                for k in 0..n {
                    du[k + 1] = ur[2 * k + p];
                    dv[k + 1] = vr[2 * k + p];
                }
            }
        });
}

/// Writes the split flow back into `u`, `v`.
fn merge_flow(g: Grid, flow: &[Vec<f32>; 2], u: &mut Array2<f32>, v: &mut Array2<f32>) {
    let (w, st) = (g.w, g.stride);
    let rl = N_FLOW * st;
    let mt = rows_per_task(w);
    let value = |i: usize, j: usize, q: usize| {
        let c = (i + j) % 2;
        let idx = (i + 1) * rl + q * st + j / 2 + 1;
        flow[c][idx]
    };
    let fill = |out: &mut Array2<f32>, q: usize| {
        if let Some(sl) = out.as_slice_mut() {
            sl.par_chunks_mut(w)
                .enumerate()
                .with_min_len(mt)
                .for_each(|(i, row)| {
                    let off = (i + 1) * rl + q * st + 1;
                    for c in 0..2 {
                        let (n, p) = (g.n(c, i), Grid::p(c, i));
                        let f = &flow[c][off..][..n];
                        for k in 0..n {
                            row[2 * k + p] = f[k];
                        }
                    }
                });
        } else {
            for ((i, j), x) in out.indexed_iter_mut() {
                *x = value(i, j, q);
            }
        }
    };
    fill(u, U);
    fill(v, V);
}

/// Smoothness weights of colour `c`, from the current flow:
/// `alpha/2 / sqrt(|grad u|^2 + |grad v|^2 + epsilon^2)` with forward differences
/// (zero across the right and bottom borders), stored as the weights of the edges to
/// the right (`WR`) and down (`WD`) neighbours; missing edges get weight 0.
fn smoothness_weights(
    g: Grid,
    c: usize,
    p: &RefineParams,
    flow: &[Vec<f32>; 2],
    coef: &mut [Vec<f32>; 2],
) {
    let cl = N_COEF * g.stride;
    coef[c][cl..(g.h + 1) * cl]
        .par_chunks_mut(cl)
        .enumerate()
        .with_min_len(rows_per_task(g.w))
        .for_each(|(i, row)| weights_one_row(g, c, i, p, [&flow[0], &flow[1]], 0, row));
}

/// [`smoothness_weights`] for image row `i`; `row` is that row of colour `c`'s
/// coefficient buffer.
fn weights_one_row(
    g: Grid,
    c: usize,
    i: usize,
    p: &RefineParams,
    flow: [&[f32]; 2],
    off: usize,
    row: &mut [f32],
) {
    let (w, h, st) = (g.w, g.h, g.stride);
    let alpha2 = p.alpha / 2.0;
    let e2 = p.epsilon * p.epsilon;
    let o = 1 - c;
    let fl = N_FLOW * st;
    let n = g.n(c, i);
    let pp = Grid::p(c, i);
    let r = i + 1 - off;
    let of = &flow[c][r * fl..][..fl];
    let nf = &flow[o][r * fl..][..fl];
    // Down neighbour row; in the last row use the pixel itself (difference 0).
    let last_row = i == h - 1;
    let df = if last_row {
        of
    } else {
        &flow[o][(r + 1) * fl..][..fl]
    };
    let (cu, cv) = (at_n(of, U * st + 1, n), at_n(of, V * st + 1, n));
    let (ru, rv) = (at_n(nf, U * st + 1 + pp, n), at_n(nf, V * st + 1 + pp, n));
    let (du, dv) = (at_n(df, U * st + 1, n), at_n(df, V * st + 1, n));
    let (wr_part, wd_part) = row[WR * st..(WD + 1) * st].split_at_mut(st);
    let wr = &mut wr_part[1..][..n];
    let wd = &mut wd_part[1..][..n];
    weights_row(alpha2, e2, [cu, cv], [ru, rv], [du, dv], wr, wd);
    // The pixel in the last column (if of this colour) has no right neighbour.
    if n > 0 && 2 * (n - 1) + pp == w - 1 {
        let k = n - 1;
        let uy = du[k] - cu[k];
        let vy = dv[k] - cv[k];
        let wgt = alpha2 / (uy * uy + vy * vy + e2).sqrt();
        wr[k] = 0.0;
        wd[k] = wgt;
    }
    if last_row {
        wd.fill(0.0);
    }
}

/// Smoothness weights of one colour row from the flow (`[u, v]`) at the pixels, their
/// right and their down neighbours. Separate function
/// so that the outputs are known not to alias the inputs (the loop vectorises).
/// Dispatched at run time like [`sor_row`].
#[inline(never)]
fn weights_row(
    alpha2: f32,
    e2: f32,
    c: [&[f32]; 2],
    r: [&[f32]; 2],
    d: [&[f32]; 2],
    wr: &mut [f32],
    wd: &mut [f32],
) {
    super::simd_arch().dispatch(WeightsOp {
        alpha2,
        e2,
        c,
        r,
        d,
        wr,
        wd,
    });
}

/// [`weights_row_kernel`]'s arguments as a `pulp` operation (see [`SorOp`]).
struct WeightsOp<'a> {
    alpha2: f32,
    e2: f32,
    c: [&'a [f32]; 2],
    r: [&'a [f32]; 2],
    d: [&'a [f32]; 2],
    wr: &'a mut [f32],
    wd: &'a mut [f32],
}

impl pulp::WithSimd for WeightsOp<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        weights_row_kernel(
            self.alpha2,
            self.e2,
            self.c,
            self.r,
            self.d,
            self.wr,
            self.wd,
        );
    }
}

/// The body of [`weights_row`].
#[inline(always)]
fn weights_row_kernel(
    alpha2: f32,
    e2: f32,
    c: [&[f32]; 2],
    r: [&[f32]; 2],
    d: [&[f32]; 2],
    wr: &mut [f32],
    wd: &mut [f32],
) {
    let n = wr.len();
    let wd = &mut wd[..n];
    let [cu, cv] = c.map(|s| &s[..n]);
    let [ru, rv] = r.map(|s| &s[..n]);
    let [du, dv] = d.map(|s| &s[..n]);
    for k in 0..n {
        let ux = ru[k] - cu[k];
        let vx = rv[k] - cv[k];
        let uy = du[k] - cu[k];
        let vy = dv[k] - cv[k];
        let wgt = alpha2 / (ux * ux + vx * vx + uy * uy + vy * vy + e2).sqrt();
        wr[k] = wgt;
        wd[k] = wgt;
    }
}

/// Linear-system coefficients of colour `c` for this outer iteration: the data terms
/// linearised around the current increment (lagged Charbonnier weights) plus the
/// smoothness terms (diagonal and right-hand side from the base flow).
fn assemble(
    g: Grid,
    c: usize,
    p: &RefineParams,
    deriv: &[f32],
    base: &[Vec<f32>; 2],
    flow: &[f32],
    coef: &mut [Vec<f32>; 2],
) {
    let cl = N_COEF * g.stride;
    let k = AssembleConsts::new(p);
    let (own, other) = own_other(coef, c);
    let other: &[f32] = other;
    own[cl..(g.h + 1) * cl]
        .par_chunks_mut(cl)
        .enumerate()
        .with_min_len(rows_per_task(g.w))
        .for_each(|(i, row)| assemble_one_row(g, c, i, &k, deriv, base, flow, 0, row, other));
}

/// [`assemble`] for image row `i`: `deriv` and `flow` are colour `c`'s buffers, `row`
/// is that row of its coefficient buffer, `other` the other colour's coefficients.
fn assemble_one_row(
    g: Grid,
    c: usize,
    i: usize,
    k: &AssembleConsts,
    deriv: &[f32],
    base: &[Vec<f32>; 2],
    flow: &[f32],
    off: usize,
    row: &mut [f32],
    other: &[f32],
) {
    let st = g.stride;
    let (dl, cl, fl) = (N_DERIV * st, N_COEF * st, N_FLOW * st);
    let n = g.n(c, i);
    let pp = Grid::p(c, i);
    // Padded row in the full buffers (`deriv`, `base`) and in the slices that start
    // at padded row `off` (`flow`, `other`).
    let r = i + 1;
    let ro = r - off;
    let dr = &deriv[r * dl..][..dl];
    let d: [&[f32]; N_DERIV] = std::array::from_fn(|x| &dr[x * st + 1..][..n]);
    let od = &flow[ro * fl..][..fl];
    let ob = &base[c][r * fl..][..fl];
    let (sys, wts) = row.split_at_mut(WR * st);
    let (a11s, rest) = sys.split_at_mut(st);
    let (a12s, rest) = rest.split_at_mut(st);
    let (a22s, rest) = rest.split_at_mut(st);
    let (b1s, b2s) = rest.split_at_mut(st);
    let input = AssembleIn {
        d,
        fu: at_n(od, U * st + 1, n),
        fv: at_n(od, V * st + 1, n),
        bu: at_n(ob, U * st + 1, n),
        bv: at_n(ob, V * st + 1, n),
        w: [
            at_n(other, ro * cl + WR * st + pp, n),
            at_n(wts, 1, n),
            at_n(other, (ro - 1) * cl + WD * st + 1, n),
            at_n(wts, st + 1, n),
        ],
    };
    assemble_row(
        k,
        &input,
        &mut a11s[1..][..n],
        &mut a12s[1..][..n],
        &mut a22s[1..][..n],
        &mut b1s[1..][..n],
        &mut b2s[1..][..n],
    );
}

/// Constants of the data and smoothness terms.
struct AssembleConsts {
    z2: f32,
    e2: f32,
    d2: f32,
    g2: f32,
    omega: f32,
}

impl AssembleConsts {
    fn new(p: &RefineParams) -> Self {
        AssembleConsts {
            z2: p.zeta * p.zeta,
            e2: p.epsilon * p.epsilon,
            d2: p.delta / 2.0,
            g2: p.gamma / 2.0,
            omega: p.omega,
        }
    }
}

/// Inputs of one colour row of [`assemble`], each `n` long: normalised derivatives
/// (see `N_DERIV`), current flow, base (incoming) flow and edge weights (left, right,
/// up, down).
struct AssembleIn<'a> {
    d: [&'a [f32]; N_DERIV],
    fu: &'a [f32],
    fv: &'a [f32],
    bu: &'a [f32],
    bv: &'a [f32],
    w: [&'a [f32]; 4],
}

/// The per-pixel system of one colour row. A separate function so that the outputs are
/// distinct `&mut` arguments (no aliasing), which lets the loop vectorise. Stores the
/// `omega / diagonal` (`A11`, `A22` slots) so SOR multiplies instead of
/// dividing.
/// Dispatched at run time like [`sor_row`].
#[inline(never)]
fn assemble_row(
    k: &AssembleConsts,
    x: &AssembleIn,
    inv_a11: &mut [f32],
    a12: &mut [f32],
    inv_a22: &mut [f32],
    b1: &mut [f32],
    b2: &mut [f32],
) {
    super::simd_arch().dispatch(AssembleOp {
        k,
        x,
        out: [inv_a11, a12, inv_a22, b1, b2],
    });
}

/// [`assemble_row_kernel`]'s arguments as a `pulp` operation (see [`SorOp`]).
struct AssembleOp<'a, 'b> {
    k: &'a AssembleConsts,
    x: &'a AssembleIn<'b>,
    out: [&'a mut [f32]; 5],
}

impl pulp::WithSimd for AssembleOp<'_, '_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let [inv_a11, a12, inv_a22, b1, b2] = self.out;
        assemble_row_kernel(self.k, self.x, inv_a11, a12, inv_a22, b1, b2);
    }
}

/// The body of [`assemble_row`].
#[inline(always)]
fn assemble_row_kernel(
    k: &AssembleConsts,
    x: &AssembleIn,
    inv_a11: &mut [f32],
    a12: &mut [f32],
    inv_a22: &mut [f32],
    b1: &mut [f32],
    b2: &mut [f32],
) {
    let n = inv_a11.len();
    let (a12, inv_a22, b1, b2) = (&mut a12[..n], &mut inv_a22[..n], &mut b1[..n], &mut b2[..n]);
    // Sliced without `map` (see `sor_row`).
    let d = &x.d;
    let (bx, by, bz) = (&d[0][..n], &d[1][..n], &d[2][..n]);
    let (xx, xy, xz) = (&d[3][..n], &d[4][..n], &d[5][..n]);
    let (yx, yy, yz) = (&d[6][..n], &d[7][..n], &d[8][..n]);
    let (fu, fv, bu, bv) = (&x.fu[..n], &x.fv[..n], &x.bu[..n], &x.bv[..n]);
    let (wl, wr, wu, wd) = (&x.w[0][..n], &x.w[1][..n], &x.w[2][..n], &x.w[3][..n]);
    let AssembleConsts {
        z2,
        e2,
        d2,
        g2,
        omega,
    } = *k;
    for i in 0..n {
        // Increment over the incoming flow (the data terms are linearised there).
        let (du_i, dv_i) = (fu[i] - bu[i], fv[i] - bv[i]);
        // Normalised brightness constancy, Charbonnier weight lagged at the current
        // increment.
        let (gx, gy, gz) = (bx[i], by[i], bz[i]);
        let res = gz + gx * du_i + gy * dv_i;
        let sb = (res * res + e2).sqrt();
        // Normalised gradient constancy (of I_x and of I_y).
        let (p0, p1, p2) = (xx[i], xy[i], xz[i]);
        let (q0, q1, q2) = (yx[i], yy[i], yz[i]);
        let rx = p2 + p0 * du_i + p1 * dv_i;
        let ry = q2 + q0 * du_i + q1 * dv_i;
        let sg = (rx * rx + ry * ry + e2).sqrt();
        // One division for both Charbonnier weights d2 / sb and g2 / sg.
        let t = 1.0 / (sb * sg);
        let (wb, wg) = (d2 * sg * t, g2 * sb * t);
        let mut s11 = wb * (gx * gx) + z2;
        let mut s12 = wb * (gx * gy);
        let mut s22 = wb * (gy * gy) + z2;
        let mut r1 = -wb * (gz * gx);
        let mut r2 = -wb * (gz * gy);
        s11 += wg * (p0 * p0 + q0 * q0);
        s12 += wg * (p0 * p1 + q0 * q1);
        s22 += wg * (p1 * p1 + q1 * q1);
        r1 -= wg * (p0 * p2 + q0 * q2);
        r2 -= wg * (p1 * p2 + q1 * q2);
        // Solving for the total flow f = base + increment: the data rows become
        // D f = r + D base (D the 2x2 data block), so the smoothness terms need no
        // right-hand side; their weights join the diagonal (left, right, up, down edges,
        // weight 0 where there is none).
        let ws = wl[i] + wr[i] + wu[i] + wd[i];
        r1 += s11 * bu[i] + s12 * bv[i];
        r2 += s12 * bu[i] + s22 * bv[i];
        // One division for both reciprocals of the diagonal, pre-multiplied by omega.
        let (d11, d22) = (s11 + ws, s22 + ws);
        let t = omega / (d11 * d22);
        inv_a11[i] = d22 * t;
        a12[i] = s12;
        inv_a22[i] = d11 * t;
        b1[i] = r1;
        b2[i] = r2;
    }
}

/// Inputs of one colour row of an SOR half-sweep, each `n` long: the system
/// (`omega/A11, A12, omega/A22, B1, B2`), the edge weights (left, right, up, down) and the
/// neighbours' current flow `[left and right, up, down]`: the first slice (`n + 1`
/// long) holds the left neighbours and, one further on, the right ones, so that both
/// are read through one pointer (the loop has ~20 input streams, more than x86-64's
/// 16 registers: each stream fewer is one stack reload fewer per iteration).
struct SorIn<'a> {
    sys: [&'a [f32]; 5],
    w: [&'a [f32]; 4],
    nu: [&'a [f32]; 3],
    nv: [&'a [f32]; 3],
}

/// SOR update of one colour row (separate function: `du`, `dv` are then known not to
/// alias the inputs, so the loop vectorises).
///
/// Dispatched at run time (`pulp`): on a CPU with AVX2 the kernel is compiled 8 lanes
/// wide, otherwise for the baseline target. Same operations in the same order either
/// way (Rust never contracts to FMA), so the result is bit-identical.
#[inline(never)]
fn sor_row(omega: f32, x: &SorIn, du: &mut [f32], dv: &mut [f32]) {
    super::simd_arch().dispatch(SorOp { omega, x, du, dv });
}

/// [`sor_row_kernel`]'s arguments, as a `pulp` operation (a closure's body is not
/// inlined into the AVX2 function `pulp` makes; a `with_simd` method marked
/// `#[inline(always)]` is).
struct SorOp<'a, 'b> {
    omega: f32,
    x: &'a SorIn<'b>,
    du: &'a mut [f32],
    dv: &'a mut [f32],
}

impl pulp::WithSimd for SorOp<'_, '_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        sor_row_kernel(self.omega, self.x, self.du, self.dv);
    }
}

/// The body of [`sor_row`] (inlined into whichever instruction set calls it).
#[inline(always)]
fn sor_row_kernel(omega: f32, x: &SorIn, du: &mut [f32], dv: &mut [f32]) {
    let keep = 1.0 - omega;
    let n = du.len();
    let dv = &mut dv[..n];
    // Every slice cut to its length here, without `map` (a generic call that is
    // inlined or not depending on which codegen unit its instance lands in, which
    // made this loop's code change with edits elsewhere in the crate).
    let (ia11, a12, ia22) = (&x.sys[0][..n], &x.sys[1][..n], &x.sys[2][..n]);
    let (b1, b2) = (&x.sys[3][..n], &x.sys[4][..n]);
    let (wl, wr, wu, wd) = (&x.w[0][..n], &x.w[1][..n], &x.w[2][..n], &x.w[3][..n]);
    let (lru, uu, du_) = (&x.nu[0][..n + 1], &x.nu[1][..n], &x.nu[2][..n]);
    let (lrv, uv, dv_) = (&x.nv[0][..n + 1], &x.nv[1][..n], &x.nv[2][..n]);
    for i in 0..n {
        let su = wl[i] * lru[i] + wr[i] * lru[i + 1] + wu[i] * uu[i] + wd[i] * du_[i];
        let sv = wl[i] * lrv[i] + wr[i] * lrv[i + 1] + wu[i] * uv[i] + wd[i] * dv_[i];
        // du + omega * (gauss_seidel - du), with omega / a11 precomputed.
        let nu = keep * du[i] + (su + b1[i] - a12[i] * dv[i]) * ia11[i];
        let nv = keep * dv[i] + (sv + b2[i] - a12[i] * nu) * ia22[i];
        du[i] = nu;
        dv[i] = nv;
    }
}

/// `n` values of `a` from offset `x`.
#[inline]
fn at_n(a: &[f32], x: usize, n: usize) -> &[f32] {
    &a[x..][..n]
}

/// Splits the two colour buffers into (colour `c` mutable, the other colour).
fn own_other<T>(pair: &mut [T; 2], c: usize) -> (&mut T, &T) {
    let (lo, hi) = pair.split_at_mut(1);
    if c == 0 {
        (&mut lo[0], &hi[0])
    } else {
        (&mut hi[0], &lo[0])
    }
}

/// SOR update of the pixels of colour `c` in image row `i`; `row` is that row of the
/// colour's flow buffer; `coef` and `other` (the other colour's flow) are buffers from
/// padded row `off` on.
fn sor_one_row(
    g: Grid,
    c: usize,
    i: usize,
    omega: f32,
    coef: [&[f32]; 2],
    off: usize,
    row: &mut [f32],
    other: &[f32],
) {
    let st = g.stride;
    let (cl, fl) = (N_COEF * st, N_FLOW * st);
    let (oc, nc) = (coef[c], coef[1 - c]);
    let n = g.n(c, i);
    let pp = Grid::p(c, i);
    let r = i + 1 - off;
    let cr = &oc[r * cl..][..cl];
    let q = |x: usize| &cr[x * st + 1..][..n];
    let (a11, a12, a22, b1, b2, wr, wd) = (q(A11), q(A12), q(A22), q(B1), q(B2), q(WR), q(WD));
    let wl = &nc[r * cl + WR * st + pp..][..n];
    let wu = &nc[(r - 1) * cl + WD * st + 1..][..n];
    let nrow = &other[r * fl..][..fl];
    let urow = &other[(r - 1) * fl..][..fl];
    let drow = &other[(r + 1) * fl..][..fl];
    let input = SorIn {
        sys: [a11, a12, a22, b1, b2],
        w: [wl, wr, wu, wd],
        nu: [
            &nrow[U * st + pp..][..n + 1],
            &urow[U * st + 1..][..n],
            &drow[U * st + 1..][..n],
        ],
        nv: [
            &nrow[V * st + pp..][..n + 1],
            &urow[V * st + 1..][..n],
            &drow[V * st + 1..][..n],
        ],
    };
    let (us, vs) = row.split_at_mut(st);
    sor_row(omega, &input, &mut us[1..][..n], &mut vs[1..][..n]);
}

/// One SOR half-sweep over the pixels of colour `c` (they depend only on the other
/// colour, so rows are independent and the result does not depend on scheduling).
fn sor_half_sweep(g: Grid, c: usize, omega: f32, coef: &[Vec<f32>; 2], flow: &mut [Vec<f32>; 2]) {
    let fl = N_FLOW * g.stride;
    let (own, other) = own_other(flow, c);
    let other: &[f32] = other;
    own[fl..(g.h + 1) * fl]
        .par_chunks_mut(fl)
        .enumerate()
        .with_min_len(rows_per_task(g.w))
        .for_each(|(i, row)| sor_one_row(g, c, i, omega, [&coef[0], &coef[1]], 0, row, other));
}

/// Shared inputs of one outer iteration.
struct OuterCtx<'a> {
    g: Grid,
    p: &'a RefineParams,
    k: AssembleConsts,
    deriv: &'a [Vec<f32>; 2],
    base: &'a [Vec<f32>; 2],
}

/// Runs work items of one outer iteration. Items are in "stage" order `k`: `0` the
/// smoothness weights of a row, `1` its system, `2 + t` SOR half-sweep `t` (red for
/// even `t`). Item `(k, i)` reads only what items `(k - 1, i - 1..=i + 1)` (or earlier)
/// wrote, and whatever overwrites what it reads depends on it, so any order that runs
/// `(k - 1, i')` before `(k, i)` for `|i - i'| <= 1` gives the pass-by-pass result bit
/// for bit.
///
/// `coef` and `flow` are the colours' buffers from padded row `off` on; `range(k)` the
/// inclusive image-row range of stage `k < stages` to run here (empty if `lo > hi`). Rows are
/// swept downwards (item `(k, i)` at step `i + k`) or upwards (at step `k - i`).
fn run_items(
    x: &OuterCtx,
    coef: &mut [&mut [f32]; 2],
    flow: &mut [&mut [f32]; 2],
    off: usize,
    stages: usize,
    range: &(dyn Fn(usize) -> (isize, isize) + Sync),
    downward: bool,
) {
    let (g, st) = (x.g, x.g.stride);
    let (cl, fl) = (N_COEF * st, N_FLOW * st);
    let at = |k: usize, i: isize| {
        if downward {
            i + k as isize
        } else {
            k as isize - i
        }
    };
    let live = || {
        (0..stages)
            .map(|k| (k, range(k)))
            .filter(|(_, r)| r.0 <= r.1)
    };
    let first = live().map(|(k, r)| at(k, r.0).min(at(k, r.1))).min();
    let last = live().map(|(k, r)| at(k, r.0).max(at(k, r.1))).max();
    let (Some(first), Some(last)) = (first, last) else {
        return;
    };
    for step in first..=last {
        for k in 0..stages {
            let (lo, hi) = range(k);
            let i = if downward {
                step - k as isize
            } else {
                k as isize - step
            };
            if i < lo || i > hi {
                continue;
            }
            let i = i as usize;
            let ro = i + 1 - off;
            match k {
                0 => {
                    for c in 0..2 {
                        let row = &mut coef[c][ro * cl..(ro + 1) * cl];
                        weights_one_row(g, c, i, x.p, [&*flow[0], &*flow[1]], off, row);
                    }
                }
                1 => {
                    for c in 0..2 {
                        let (own, other) = own_other(coef, c);
                        let row = &mut own[ro * cl..(ro + 1) * cl];
                        let fc: &[f32] = &*flow[c];
                        assemble_one_row(g, c, i, &x.k, &x.deriv[c], x.base, fc, off, row, other);
                    }
                }
                _ => {
                    let c = (k - 2) % 2;
                    let (own, other) = own_other(flow, c);
                    let row = &mut own[ro * fl..(ro + 1) * fl];
                    sor_one_row(g, c, i, x.p.omega, [&*coef[0], &*coef[1]], off, row, other);
                }
            }
        }
    }
}

/// One whole outer iteration (smoothness weights, system assembly, all red-black SOR
/// sweeps) without separate passes over the level (temporal blocking): each row goes
/// through all stages while it and its neighbours are in cache, instead of every pass
/// streaming the whole level through memory. Bit-identical to the pass-by-pass order
/// (see [`run_items`]).
///
/// One thread: a single downward sweep. Two threads: the top half sweeps down and the
/// bottom half sweeps up at the same time, each doing only the items whose inputs lie
/// in its half; then the band left between them (about `2 * sweeps + 3` rows) is swept
/// on one thread.
fn outer_wavefront(
    g: Grid,
    p: &RefineParams,
    deriv: &[Vec<f32>; 2],
    base: &[Vec<f32>; 2],
    coef: &mut [Vec<f32>; 2],
    flow: &mut [Vec<f32>; 2],
    two_halves: bool,
) {
    let x = OuterCtx {
        g,
        p,
        k: AssembleConsts::new(p),
        deriv,
        base,
    };
    let stages = 2 + 2 * p.sor_iterations;
    let h = g.h as isize;
    let [c0, c1] = coef;
    let [f0, f1] = flow;
    if !two_halves || g.h < 2 * stages + 16 {
        let (mut cs, mut fs) = ([&mut c0[..], &mut c1[..]], [&mut f0[..], &mut f1[..]]);
        run_items(&x, &mut cs, &mut fs, 0, stages, &|_| (0, h - 1), true);
        return;
    }
    let m = h / 2;
    // Top half (image rows < m): weights and systems up to row m - 2, SOR half-sweep t
    // up to row m - 2 - t. Bottom half (rows >= m): weights from row m, systems from
    // m + 1, half-sweep t from m + 2 + t. The band between them comes last.
    let top = |k: usize| (0, m - 2 - (k as isize - 2).max(0));
    let bottom = |k: usize| (m + k as isize, h - 1);
    let band = |k: usize| ((top(k).1 + 1).max(0), (bottom(k).0 - 1).min(h - 1));
    {
        let m = m as usize;
        let (csplit, fsplit) = ((m + 1) * N_COEF * g.stride, (m + 1) * N_FLOW * g.stride);
        let (c0a, c0b) = c0.split_at_mut(csplit);
        let (c1a, c1b) = c1.split_at_mut(csplit);
        let (f0a, f0b) = f0.split_at_mut(fsplit);
        let (f1a, f1b) = f1.split_at_mut(fsplit);
        rayon::join(
            || run_items(&x, &mut [c0a, c1a], &mut [f0a, f1a], 0, stages, &top, true),
            || {
                run_items(
                    &x,
                    &mut [c0b, c1b],
                    &mut [f0b, f1b],
                    m + 1,
                    stages,
                    &bottom,
                    false,
                )
            },
        );
    }
    let (mut cs, mut fs) = ([&mut c0[..], &mut c1[..]], [&mut f0[..], &mut f1[..]]);
    run_items(&x, &mut cs, &mut fs, 0, stages, &band, true);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_counts() {
        let g = Grid::new(5, 3);
        assert_eq!((g.n(0, 0), g.n(1, 0)), (3, 2));
        assert_eq!((g.n(0, 1), g.n(1, 1)), (2, 3));
        let g = Grid::new(4, 3);
        assert_eq!((g.n(0, 0), g.n(1, 0), g.n(0, 1), g.n(1, 1)), (2, 2, 2, 2));
    }

    #[test]
    fn dispatched_sor_row_matches_the_baseline_kernel_bit_for_bit() {
        // The oracle for the runtime SIMD dispatch: `sor_row_kernel` called directly
        // is compiled for the baseline target, `sor_row` runs it in the instruction set
        // `simd_arch` found (AVX2 on most x86-64), `Arch::Scalar` is the fallback.
        // Lengths around the 4- and 8-lane boundaries (remainders on every path).
        let mut rnd = crate::flow::unit_stream(0x2545_f491_4f6c_dd1du64);
        for n in [1usize, 3, 4, 7, 8, 9, 15, 16, 17, 100, 481] {
            let mut v = |scale: f32, len: usize| -> Vec<f32> {
                (0..len).map(|_| scale * (2.0 * rnd() - 1.0)).collect()
            };
            let sys = [v(0.5, n), v(3.0, n), v(0.5, n), v(100.0, n), v(1e-3, n)];
            let w = [v(1.0, n), v(1.0, n), v(1.0, n), v(1.0, n)];
            let nu = [v(5.0, n + 1), v(5.0, n), v(5.0, n)];
            let nv = [v(5.0, n + 1), v(5.0, n), v(5.0, n)];
            let x = SorIn {
                sys: sys.each_ref().map(|a| &a[..]),
                w: w.each_ref().map(|a| &a[..]),
                nu: nu.each_ref().map(|a| &a[..]),
                nv: nv.each_ref().map(|a| &a[..]),
            };
            let (du0, dv0) = (v(2.0, n), v(2.0, n));
            let bits = |a: &[f32]| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            for omega in [1.0f32, 1.6, 1.9] {
                let (mut du1, mut dv1) = (du0.clone(), dv0.clone());
                sor_row_kernel(omega, &x, &mut du1, &mut dv1);
                let (mut du2, mut dv2) = (du0.clone(), dv0.clone());
                sor_row(omega, &x, &mut du2, &mut dv2);
                let (mut du3, mut dv3) = (du0.clone(), dv0.clone());
                pulp::Arch::Scalar.dispatch(SorOp {
                    omega,
                    x: &x,
                    du: &mut du3,
                    dv: &mut dv3,
                });
                assert_eq!((bits(&du2), bits(&dv2)), (bits(&du1), bits(&dv1)));
                assert_eq!((bits(&du3), bits(&dv3)), (bits(&du1), bits(&dv1)));
            }
        }
    }

    #[test]
    fn dispatched_assembly_and_weights_match_the_baseline_kernels_bit_for_bit() {
        // As for the SOR row: `*_kernel` called here is compiled for the baseline,
        // the dispatched function runs in the detected instruction set, and
        // `Arch::Scalar` is the fallback path.
        let mut rnd = crate::flow::unit_stream(0x0123_4567_89ab_cdefu64);
        let bits = |a: &[f32]| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for n in [1usize, 4, 7, 8, 9, 17, 100, 481] {
            let mut v = |scale: f32, len: usize| -> Vec<f32> {
                (0..len).map(|_| scale * (2.0 * rnd() - 1.0)).collect()
            };
            let d: Vec<Vec<f32>> = (0..N_DERIV).map(|k| v(10.0 * (k + 1) as f32, n)).collect();
            let (fu, fv, bu, bv) = (v(3.0, n), v(3.0, n), v(3.0, n), v(3.0, n));
            let wv: Vec<Vec<f32>> = (0..4).map(|_| v(1.0, n)).collect();
            let x = AssembleIn {
                d: std::array::from_fn(|k| &d[k][..]),
                fu: &fu,
                fv: &fv,
                bu: &bu,
                bv: &bv,
                w: std::array::from_fn(|k| &wv[k][..]),
            };
            let k = AssembleConsts {
                z2: 1e-4,
                e2: 1e-6,
                d2: 4.0,
                g2: 10.0,
                omega: 1.6,
            };
            let run = |how: usize| -> Vec<Vec<f32>> {
                let mut o: Vec<Vec<f32>> = (0..5).map(|_| vec![0.0f32; n]).collect();
                let [a, b, c, e, f] = o.get_disjoint_mut([0, 1, 2, 3, 4]).expect("distinct");
                match how {
                    0 => assemble_row_kernel(&k, &x, a, b, c, e, f),
                    1 => assemble_row(&k, &x, a, b, c, e, f),
                    _ => pulp::Arch::Scalar.dispatch(AssembleOp {
                        k: &k,
                        x: &x,
                        out: [a, b, c, e, f],
                    }),
                }
                o
            };
            let want: Vec<_> = run(0).iter().map(|a| bits(a)).collect();
            for how in [1, 2] {
                let got: Vec<_> = run(how).iter().map(|a| bits(a)).collect();
                assert_eq!(got, want, "assembly, n {n}, path {how}");
            }
            let (cu, cv, ru, rv, du, dv) = (
                v(4.0, n),
                v(4.0, n),
                v(4.0, n),
                v(4.0, n),
                v(4.0, n),
                v(4.0, n),
            );
            let wrun = |how: usize| -> (Vec<u32>, Vec<u32>) {
                let (mut wr, mut wd) = (vec![0.0f32; n], vec![0.0f32; n]);
                let (c, r, d) = ([&cu[..], &cv[..]], [&ru[..], &rv[..]], [&du[..], &dv[..]]);
                match how {
                    0 => weights_row_kernel(0.04, 1e-6, c, r, d, &mut wr, &mut wd),
                    1 => weights_row(0.04, 1e-6, c, r, d, &mut wr, &mut wd),
                    _ => pulp::Arch::Scalar.dispatch(WeightsOp {
                        alpha2: 0.04,
                        e2: 1e-6,
                        c,
                        r,
                        d,
                        wr: &mut wr,
                        wd: &mut wd,
                    }),
                }
                (bits(&wr), bits(&wd))
            };
            let want = wrun(0);
            assert_eq!(wrun(1), want, "weights, n {n}");
            assert_eq!(wrun(2), want, "weights, n {n}, scalar arch");
        }
    }

    #[test]
    fn chunked_warp_matches_the_per_pixel_warp_bit_for_bit() {
        // Rows longer than a chunk, flows that leave the image on every side,
        // whole and fractional displacements.
        for (w, h) in [(2usize, 2usize), (7, 5), (300, 9)] {
            let i1: Vec<f32> = (0..w * h)
                .map(|k| ((k * 37 % 101) as f32) * 2.5 + (k % 7) as f32 * 0.13)
                .collect();
            for i in 0..h {
                let ur: Vec<f32> = (0..w)
                    .map(|j| ((j * 13 + i * 7) % 23) as f32 * 0.77 - 8.0)
                    .collect();
                let vr: Vec<f32> = (0..w)
                    .map(|j| ((j * 5 + i * 11) % 19) as f32 * 0.61 - 5.5)
                    .collect();
                let zero = vec![0.0f32; w];
                for (u, v) in [(&ur, &vr), (&zero, &zero)] {
                    let (mut got, mut want) = (vec![0.0f32; w], vec![0.0f32; w]);
                    warp_row(&i1, w, h, i, u, v, &mut got);
                    warp_row_scalar(&i1, w, h, i, u, v, &mut want);
                    let bits = |a: &[f32]| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&got), bits(&want), "{w}x{h} row {i}");
                    // The dispatched warp against its kernel compiled for the baseline.
                    let mut direct = vec![0.0f32; w];
                    warp_row_kernel(&i1, w, h, i, u, v, &mut direct);
                    assert_eq!(bits(&got), bits(&direct), "{w}x{h} row {i}");
                }
                // A zero flow reproduces the image exactly.
                let mut out = vec![0.0f32; w];
                warp_row(&i1, w, h, i, &zero, &zero, &mut out);
                assert_eq!(out, i1[i * w..(i + 1) * w]);
            }
        }
    }

    #[test]
    fn split_merge_round_trip() {
        for (w, h) in [(2, 2), (5, 3), (6, 4), (7, 7)] {
            let g = Grid::new(w, h);
            let u = Array2::from_shape_fn((h, w), |(i, j)| (i * 100 + j) as f32);
            let v = u.mapv(|x| -x);
            let mut base: [Vec<f32>; 2] = std::array::from_fn(|_| vec![0.0; g.buf_len(N_FLOW)]);
            split_flow(&u, &v, g, &mut base);
            let (mut u2, mut v2) = (Array2::zeros((h, w)), Array2::zeros((h, w)));
            merge_flow(g, &base, &mut u2, &mut v2);
            assert_eq!(u, u2);
            assert_eq!(v, v2);
        }
    }
}
