//! Natural Helmholtz-Hodge decomposition (Bhatia et al. 2014) of a flow patch.
//!
//! A 2-D field `V = (u, v)` on a regular grid splits into
//! `V = d + r + h`: a curl-free part `d = grad D`, a divergence-free part
//! `r = J grad R = (-dR/dy, dR/dx)` and a harmonic rest `h`. The *natural*
//! decomposition takes the potentials as free-space convolutions of the
//! divergence and curl with the Green's function of the Laplacian,
//! `D = G * div V`, `R = G * curl V`, so no boundary condition is imposed
//! and whatever enters from outside the patch ends up in `h`.
//!
//! This follows the authors' reference implementation (`pynhhd` 1.1, regular
//! 2-D grids) to the letter, so that results agree with it to ~1e-12:
//! - derivatives use `numpy.gradient`'s stencils: central differences inside,
//!   one-sided first differences at both ends of each axis (along an axis
//!   with a single sample, where numpy refuses, the derivative is taken as 0);
//! - `G(ky, kx) = ln(hypot(ky dy, kx dx)) / (2 pi)` and
//!   `G(0, 0) = ln((dx + dy) / 4) / (2 pi)`;
//! - every cell weighs `dx dy`; no sign flip on `R`.
//!
//! Layout: `u` is the component along columns (x, spacing `dx`), `v` along
//! rows (y, spacing `dy`); arrays have shape `(ny, nx)` = (rows, columns).
//!
//! [`NaturalHhd`] evaluates the convolution by zero-padded FFT in
//! `O(N log N)` ([`GreenConvolver`] is one planned grid size); the tests check
//! it against the `O(N^2)` direct sum of the definition.
//!
//! ```
//! use ndarray::Array2;
//! use optical_tactile::hhd::NaturalHhd;
//!
//! // A source at the centre: flow pointing away from it.
//! let (ny, nx) = (21, 31);
//! let u = Array2::from_shape_fn((ny, nx), |(_, x)| (x as f32 - 15.0) * 0.01);
//! let v = Array2::from_shape_fn((ny, nx), |(y, _)| (y as f32 - 10.0) * 0.01);
//! let mut hhd = NaturalHhd::new();
//! let dec = hhd.decompose(u.view(), v.view(), 1.0, 1.0).unwrap();
//! // Purely divergent: the potential D is lowest at the source.
//! assert_eq!(dec.argmin_d(), (10, 15));
//! assert!(dec.potential_r.iter().all(|r| r.abs() < 1e-12));
//! ```

#[cfg(test)]
mod direct;
mod fft;
#[cfg(test)]
mod tests_oracle;
#[cfg(test)]
mod tests_reference;

pub use fft::{FftWorkspace, GreenConvolver, PARALLEL_MIN_CELLS};

use fft::GreenTable;

use std::sync::Arc;

use ndarray::{Array2, ArrayRef2, ArrayView2};
use rustfft::FftPlanner;

use crate::error::{Error, Result};
use crate::flow::FlowField;

/// A 2-D vector field in f64: `u` along columns (x), `v` along rows (y), each
/// of shape `(ny, nx)`.
#[derive(Debug, Clone, PartialEq)]
pub struct Field2 {
    /// Component along columns (x).
    pub u: Array2<f64>,
    /// Component along rows (y).
    pub v: Array2<f64>,
}

impl Field2 {
    /// A zero field of `ny` rows and `nx` columns.
    pub fn zeros(ny: usize, nx: usize) -> Self {
        Field2 {
            u: Array2::zeros((ny, nx)),
            v: Array2::zeros((ny, nx)),
        }
    }

    fn ensure_shape(&mut self, ny: usize, nx: usize) {
        ensure_shape(&mut self.u, ny, nx);
        ensure_shape(&mut self.v, ny, nx);
    }
}

/// The result of a natural HHD, all in f64, every array of shape `(ny, nx)`.
///
/// `V = d + r + h` holds exactly up to rounding (`h` is defined as the rest).
#[derive(Debug, Clone, PartialEq)]
pub struct Decomposition {
    /// Grid spacing along columns (x) the decomposition was computed with.
    pub dx: f64,
    /// Grid spacing along rows (y).
    pub dy: f64,
    /// Divergence `du/dx + dv/dy` of the input.
    pub div: Array2<f64>,
    /// Curl `dv/dx - du/dy` of the input.
    pub curl: Array2<f64>,
    /// The divergence potential `D` (the paper's D): `d = grad D`. Its minimum
    /// marks a press (a sink of the marker flow).
    pub potential_d: Array2<f64>,
    /// The rotational potential `R`: `r = (-dR/dy, dR/dx)`.
    pub potential_r: Array2<f64>,
    /// Curl-free part `d = grad D`.
    pub d: Field2,
    /// Divergence-free part `r = (-dR/dy, dR/dx)`.
    pub r: Field2,
    /// Harmonic part `h = V - (d + r)`.
    pub h: Field2,
}

impl Decomposition {
    /// An all-zero decomposition of `ny` rows and `nx` columns (spacings 1),
    /// to be filled by [`NaturalHhd::decompose_into`].
    pub fn zeros(ny: usize, nx: usize) -> Self {
        Decomposition {
            dx: 1.0,
            dy: 1.0,
            div: Array2::zeros((ny, nx)),
            curl: Array2::zeros((ny, nx)),
            potential_d: Array2::zeros((ny, nx)),
            potential_r: Array2::zeros((ny, nx)),
            d: Field2::zeros(ny, nx),
            r: Field2::zeros(ny, nx),
            h: Field2::zeros(ny, nx),
        }
    }

    /// `(ny, nx)`: rows and columns.
    pub fn shape(&self) -> (usize, usize) {
        self.potential_d.dim()
    }

    /// `(row, column)` of the smallest `D` (the first one in row-major order
    /// on ties). For a press, this is the contact centre.
    pub fn argmin_d(&self) -> (usize, usize) {
        let mut best = ((0, 0), f64::INFINITY);
        for (idx, &x) in self.potential_d.indexed_iter() {
            if x < best.1 {
                best = (idx, x);
            }
        }
        best.0
    }

    /// `max D - min D`: the spread of the divergence potential (the
    /// pipeline's `d_PF`).
    pub fn d_range(&self) -> f64 {
        let (lo, hi) = self
            .potential_d
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
                (lo.min(x), hi.max(x))
            });
        hi - lo
    }

    /// Reallocates arrays only where their shape or layout does not fit.
    fn ensure_shape(&mut self, ny: usize, nx: usize) {
        for a in [
            &mut self.div,
            &mut self.curl,
            &mut self.potential_d,
            &mut self.potential_r,
        ] {
            ensure_shape(a, ny, nx);
        }
        self.d.ensure_shape(ny, nx);
        self.r.ensure_shape(ny, nx);
        self.h.ensure_shape(ny, nx);
    }
}

/// The divergent half of a natural HHD: the divergence, its potential `D`
/// and the curl-free part `d = grad D`, every array of shape `(ny, nx)`.
/// What the contact pipeline reads (the contact point and `d_PF` from `D`,
/// the normal displacement from `|d|`); [`NaturalHhd::divergent_into`]
/// computes it for about half the work of a whole [`Decomposition`], whose
/// `div`, `potential_d` and `d` it equals up to rounding.
#[derive(Debug, Clone, PartialEq)]
pub struct DivergentPart {
    /// Grid spacing along columns (x) the part was computed with.
    pub dx: f64,
    /// Grid spacing along rows (y).
    pub dy: f64,
    /// Divergence `du/dx + dv/dy` of the input.
    pub div: Array2<f64>,
    /// The divergence potential `D`: `d = grad D`; its minimum marks a press.
    pub potential_d: Array2<f64>,
    /// Curl-free part `d = grad D`.
    pub d: Field2,
}

impl Default for DivergentPart {
    fn default() -> Self {
        Self::zeros(0, 0)
    }
}

impl DivergentPart {
    /// An all-zero part of `ny` rows and `nx` columns (spacings 1), to be
    /// filled by [`NaturalHhd::divergent_into`].
    pub fn zeros(ny: usize, nx: usize) -> Self {
        DivergentPart {
            dx: 1.0,
            dy: 1.0,
            div: Array2::zeros((ny, nx)),
            potential_d: Array2::zeros((ny, nx)),
            d: Field2::zeros(ny, nx),
        }
    }

    /// `(ny, nx)`: rows and columns.
    pub fn shape(&self) -> (usize, usize) {
        self.potential_d.dim()
    }

    /// Reshapes every array to `(ny, nx)`, reusing its storage: patch
    /// sizes change from frame to frame, and fresh zeroed arrays each time
    /// cost more than the arithmetic on small patches.
    fn reshape(&mut self, ny: usize, nx: usize) {
        for a in [
            &mut self.div,
            &mut self.potential_d,
            &mut self.d.u,
            &mut self.d.v,
        ] {
            reshape_reusing(a, ny, nx);
        }
    }
}

/// `a` as a `(ny, nx)` standard-layout array on the same storage (grown
/// when too small); its values are left unspecified.
fn reshape_reusing(a: &mut Array2<f64>, ny: usize, nx: usize) {
    if a.dim() == (ny, nx) && a.is_standard_layout() {
        return;
    }
    let (mut v, offset) = std::mem::take(a).into_raw_vec_and_offset();
    if offset.unwrap_or(0) != 0 {
        v = Vec::new();
    }
    v.resize(ny * nx, 0.0);
    *a = Array2::from_shape_vec((ny, nx), v).expect("ny * nx values");
}

fn ensure_shape(a: &mut Array2<f64>, ny: usize, nx: usize) {
    if a.dim() != (ny, nx) || !a.is_standard_layout() {
        *a = Array2::zeros((ny, nx));
    }
}

/// Input element types the decomposition accepts (f32 flows, or f64).
pub trait HhdScalar: Copy + Into<f64> {}
impl HhdScalar for f32 {}
impl HhdScalar for f64 {}

/// Default number of plans (padded torus and spacing) a [`NaturalHhd`] keeps.
pub const DEFAULT_CACHE: usize = 8;

/// The natural HHD planner: keeps, per grid shape and spacing, the FFT plans
/// and the Green's-function spectrum, plus working buffers, so that repeated
/// decompositions of the same sizes allocate nothing.
///
/// Patch sizes vary from frame to frame, so it caches a few plans at once
/// (least recently used is dropped first; [`DEFAULT_CACHE`] by default), and
/// grids that pad to the same torus (e.g. 58 to 60 rows all pad to 120)
/// share a plan.
/// One planner is not shared between threads; use one per worker thread.
pub struct NaturalHhd {
    planner: FftPlanner<f64>,
    cache: Vec<Arc<GreenConvolver>>,
    capacity: usize,
    workspace: FftWorkspace,
    /// G at the offsets of the largest torus planned so far.
    table: GreenTable,
}

impl Default for NaturalHhd {
    fn default() -> Self {
        Self::new()
    }
}

impl std::fmt::Debug for NaturalHhd {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NaturalHhd")
            .field("cached", &self.cache)
            .field("capacity", &self.capacity)
            .finish()
    }
}

impl NaturalHhd {
    /// A planner caching up to [`DEFAULT_CACHE`] grid sizes.
    pub fn new() -> Self {
        Self::with_cache_capacity(DEFAULT_CACHE).expect("default capacity is positive")
    }

    /// A planner caching up to `capacity` (>= 1) grid sizes.
    pub fn with_cache_capacity(capacity: usize) -> Result<Self> {
        if capacity == 0 {
            return Err(Error::param(
                "capacity",
                "the plan cache must hold at least one size",
            ));
        }
        Ok(NaturalHhd {
            planner: FftPlanner::new(),
            cache: Vec::with_capacity(capacity),
            capacity,
            workspace: FftWorkspace::new(),
            table: GreenTable::default(),
        })
    }

    /// Number of plans (padded torus and spacing) currently cached.
    pub fn cached_sizes(&self) -> usize {
        self.cache.len()
    }

    /// Plans (or finds) the convolution for a `ny x nx` grid with spacings
    /// `dx`, `dy`, so that the first decomposition of that size is nearly as
    /// cheap as the following ones (working buffers grow on first use).
    pub fn prepare(
        &mut self,
        ny: usize,
        nx: usize,
        dx: f64,
        dy: f64,
    ) -> Result<Arc<GreenConvolver>> {
        fft::check_grid(ny, nx, dx, dy)?;
        // Grids that pad to the same torus share one plan.
        let torus = GreenConvolver::torus_for(ny, nx);
        let hit = self.cache.iter().position(|c| {
            let (cdx, cdy) = c.spacing();
            c.padded_shape() == torus
                && cdx.to_bits() == dx.to_bits()
                && cdy.to_bits() == dy.to_bits()
        });
        let conv = match hit {
            Some(i) => {
                // Move to the back: most recently used.
                let c = self.cache.remove(i);
                self.cache.push(c.clone());
                c
            }
            None => {
                let (py, px) = torus;
                self.table.ensure(py / 2 + 1, px / 2 + 1, dx, dy);
                let c = Arc::new(GreenConvolver::with_table(
                    &mut self.planner,
                    Some(&self.table),
                    ny,
                    nx,
                    dx,
                    dy,
                )?);
                if self.cache.len() == self.capacity {
                    self.cache.remove(0);
                }
                self.cache.push(c.clone());
                c
            }
        };
        Ok(conv)
    }

    /// Decomposes `(u, v)` (any strides, e.g. a window of a larger flow) with
    /// spacings `dx` along columns and `dy` along rows.
    ///
    /// Errors: [`Error::ShapeMismatch`] if `v`'s shape differs from `u`'s,
    /// [`Error::TooSmall`] on an empty grid, [`Error::InvalidParameter`] for a
    /// spacing that is not finite and positive, [`Error::NonFinite`] at the
    /// first NaN or infinity (one would spread to all of `D` and `R`).
    pub fn decompose<T: HhdScalar>(
        &mut self,
        u: ArrayView2<'_, T>,
        v: ArrayView2<'_, T>,
        dx: f64,
        dy: f64,
    ) -> Result<Decomposition> {
        let mut out = Decomposition::zeros(u.nrows(), u.ncols());
        self.decompose_into(u, v, dx, dy, &mut out)?;
        Ok(out)
    }

    /// [`decompose`](Self::decompose) for a whole [`FlowField`].
    pub fn decompose_flow(&mut self, flow: &FlowField, dx: f64, dy: f64) -> Result<Decomposition> {
        self.decompose(flow.u.view(), flow.v.view(), dx, dy)
    }

    /// [`decompose`](Self::decompose) into an existing [`Decomposition`],
    /// whose arrays are reused when they already have the right shape: with a
    /// planned size, nothing is allocated. On error `out` is left in an
    /// unspecified (but valid) state.
    pub fn decompose_into<T: HhdScalar>(
        &mut self,
        u: ArrayView2<'_, T>,
        v: ArrayView2<'_, T>,
        dx: f64,
        dy: f64,
        out: &mut Decomposition,
    ) -> Result<()> {
        let (ny, nx) = load_input(u, v, dx, dy, out)?;
        let conv = self.prepare(ny, nx, dx, dy)?;
        conv.potentials(
            &mut self.workspace,
            out.div.view(),
            out.curl.view(),
            &mut out.potential_d,
            &mut out.potential_r,
        )?;
        finish(out)
    }

    /// The divergent part alone of the decomposition of `(u, v)`: the
    /// divergence, its potential `D` and `d = grad D` (see
    /// [`DivergentPart`]), for about half the work of
    /// [`decompose_into`](Self::decompose_into), whose `div`, `potential_d`
    /// and `d` it equals up to rounding. `out`'s storage is reused whatever
    /// its shape; with a planned size, nothing is allocated once `out` has
    /// held a grid as large.
    ///
    /// Errors as [`decompose`](Self::decompose); on error `out` is left in
    /// an unspecified (but valid) state.
    pub fn divergent_into<T: HhdScalar>(
        &mut self,
        u: ArrayView2<'_, T>,
        v: ArrayView2<'_, T>,
        dx: f64,
        dy: f64,
        out: &mut DivergentPart,
    ) -> Result<()> {
        let (ny, nx) = check_input(&u, &v, dx, dy)?;
        out.reshape(ny, nx);
        out.dx = dx;
        out.dy = dy;
        // d and potential_d are free until the potential exists: the input
        // goes there as f64, then du/dx and dv/dy into d.
        copy_finite("HHD input u", u, &mut out.d.u)?;
        copy_finite("HHD input v", v, &mut out.potential_d)?;
        gradient_x(&out.d.u, nx, dx, &mut out.div);
        gradient_y(&out.potential_d, ny, nx, dy, &mut out.d.v);
        // numpy order: div = dudx + dvdy.
        ndarray::Zip::from(&mut out.div)
            .and(&out.d.v)
            .for_each(|div, &dvdy| *div += dvdy);
        let conv = self.prepare(ny, nx, dx, dy)?;
        conv.potential(&mut self.workspace, out.div.view(), &mut out.potential_d)?;
        gradient(&out.potential_d, dx, dy, &mut out.d.u, &mut out.d.v)
    }
}

/// `d f / dx` along rows of the standard-layout `f` (`nx` columns) into
/// `out`, with [`gradient`]'s stencils.
fn gradient_x(f: &Array2<f64>, nx: usize, dx: f64, out: &mut Array2<f64>) {
    let (f, out) = (
        f.as_slice().expect("standard layout"),
        out.as_slice_mut().expect("standard layout"),
    );
    gradient_x_slices(f, nx, dx, out);
}

/// `d f / dy` across the rows of the standard-layout `f` (`ny x nx`) into
/// `out`, with [`gradient`]'s stencils.
fn gradient_y(f: &Array2<f64>, ny: usize, nx: usize, dy: f64, out: &mut Array2<f64>) {
    let (f, out) = (
        f.as_slice().expect("standard layout"),
        out.as_slice_mut().expect("standard layout"),
    );
    gradient_y_slices(f, ny, nx, dy, out);
}

/// `(ny, nx)` of the input: errors if `u` and `v` differ in shape or the
/// grid (size, spacings) is not one the solvers take.
fn check_input<T>(
    u: &ArrayView2<'_, T>,
    v: &ArrayView2<'_, T>,
    dx: f64,
    dy: f64,
) -> Result<(usize, usize)> {
    let (ny, nx) = u.dim();
    if v.dim() != (ny, nx) {
        return Err(Error::shape(
            "HHD input v (against u)",
            (nx, ny),
            (v.ncols(), v.nrows()),
        ));
    }
    fft::check_grid(ny, nx, dx, dy)?;
    Ok((ny, nx))
}

/// `src` as f64 into `dst` (same shape); errors at the first non-finite
/// value, naming it `what`. Row by row over slices when the rows are
/// contiguous (the patches' windows of a flow are): every value is
/// copied, and the first bad one is looked for only when a row holds one.
fn copy_finite<T: HhdScalar>(
    what: &str,
    src: ArrayView2<'_, T>,
    dst: &mut Array2<f64>,
) -> Result<()> {
    let bad = |row: usize, col: usize| Error::NonFinite {
        what: what.into(),
        row,
        col,
    };
    for (r, (s, mut d)) in src.rows().into_iter().zip(dst.rows_mut()).enumerate() {
        match (s.as_slice(), d.as_slice_mut()) {
            (Some(s), Some(d)) => {
                // `0 x` is 0 for a finite value and NaN otherwise: summed,
                // one test per row (no early exit, so the loop vectorises).
                let mut acc = 0.0f64;
                for (o, &x) in d.iter_mut().zip(s) {
                    let x: f64 = x.into();
                    *o = x;
                    acc += 0.0 * x;
                }
                if acc != 0.0 {
                    let c = d.iter().position(|x| !x.is_finite()).unwrap_or(0);
                    return Err(bad(r, c));
                }
            }
            _ => {
                for (c, (o, &x)) in d.iter_mut().zip(s.iter()).enumerate() {
                    let x: f64 = x.into();
                    if !x.is_finite() {
                        return Err(bad(r, c));
                    }
                    *o = x;
                }
            }
        }
    }
    Ok(())
}

/// Validates the input, copies it as f64 into `out.h` (kept there until
/// [`finish`] turns it into the harmonic part) and computes div and curl.
/// Returns `(ny, nx)`.
pub(crate) fn load_input<T: HhdScalar>(
    u: ArrayView2<'_, T>,
    v: ArrayView2<'_, T>,
    dx: f64,
    dy: f64,
    out: &mut Decomposition,
) -> Result<(usize, usize)> {
    let (ny, nx) = check_input(&u, &v, dx, dy)?;
    out.ensure_shape(ny, nx);
    out.dx = dx;
    out.dy = dy;
    copy_finite("HHD input u", u, &mut out.h.u)?;
    copy_finite("HHD input v", v, &mut out.h.v)?;
    // d and r are free until the potentials exist: use them for du, dv.
    gradient(&out.h.u, dx, dy, &mut out.d.u, &mut out.d.v)?;
    gradient(&out.h.v, dx, dy, &mut out.r.u, &mut out.r.v)?;
    // numpy order: div = dudx + dvdy, curl = dvdx - dudy.
    ndarray::Zip::from(&mut out.div)
        .and(&mut out.curl)
        .and(&out.d.u)
        .and(&out.d.v)
        .and(&out.r.u)
        .and(&out.r.v)
        .for_each(|div, curl, &dudx, &dudy, &dvdx, &dvdy| {
            *div = dudx + dvdy;
            *curl = dvdx - dudy;
        });
    Ok((ny, nx))
}

/// From the potentials in `out`, the parts: `d = grad D`, `r = (-dR/dy,
/// dR/dx)`, `h = V - (d + r)` (V is held in `out.h` on entry).
pub(crate) fn finish(out: &mut Decomposition) -> Result<()> {
    let (dx, dy) = (out.dx, out.dy);
    gradient(&out.potential_d, dx, dy, &mut out.d.u, &mut out.d.v)?;
    // r.v = dR/dx and r.u = -dR/dy: a negated spacing flips the sign exactly.
    gradient(&out.potential_r, dx, -dy, &mut out.r.v, &mut out.r.u)?;
    ndarray::Zip::from(&mut out.h.u)
        .and(&mut out.h.v)
        .and(&out.d.u)
        .and(&out.d.v)
        .and(&out.r.u)
        .and(&out.r.v)
        .for_each(|hu, hv, &du, &dv, &ru, &rv| {
            *hu -= du + ru;
            *hv -= dv + rv;
        });
    Ok(())
}

/// `numpy.gradient(f, dy, dx)` with `edge_order=1`: writes `df/dx` (along
/// columns) and `df/dy` (along rows). Central `(f[k+1] - f[k-1]) / (2h)`
/// inside, `(f[1] - f[0]) / h` and `(f[n-1] - f[n-2]) / h` at the ends; along
/// an axis with one sample (numpy refuses those) the derivative is 0.
///
/// The division is done as a multiplication by `1 / (2h)` (resp. `1 / h`),
/// which can differ from numpy in the last bit; it is several times faster.
///
/// Errors with [`Error::ShapeMismatch`] if `dfdx` or `dfdy` does not have
/// `f`'s shape.
pub fn gradient(
    f: &ArrayRef2<f64>,
    dx: f64,
    dy: f64,
    dfdx: &mut ArrayRef2<f64>,
    dfdy: &mut ArrayRef2<f64>,
) -> Result<()> {
    let (ny, nx) = f.dim();
    for (what, d) in [
        ("gradient df/dx", dfdx.dim()),
        ("gradient df/dy", dfdy.dim()),
    ] {
        if d != (ny, nx) {
            return Err(Error::shape(what, (nx, ny), (d.1, d.0)));
        }
    }
    match (f.as_slice(), dfdx.as_slice_mut(), dfdy.as_slice_mut()) {
        (Some(f), Some(gx), Some(gy)) => gradient_slices(f, ny, nx, dx, dy, gx, gy),
        _ => {
            // Any strides: go through contiguous copies.
            let fc = f.as_standard_layout().into_owned();
            let mut gx = Array2::zeros((ny, nx));
            let mut gy = Array2::zeros((ny, nx));
            gradient(&fc, dx, dy, &mut gx, &mut gy)?;
            dfdx.assign(&gx);
            dfdy.assign(&gy);
        }
    }
    Ok(())
}

/// [`gradient`] on row-major slices of `ny * nx` values.
fn gradient_slices(
    f: &[f64],
    ny: usize,
    nx: usize,
    dx: f64,
    dy: f64,
    gx: &mut [f64],
    gy: &mut [f64],
) {
    gradient_x_slices(f, nx, dx, gx);
    gradient_y_slices(f, ny, nx, dy, gy);
}

/// The `df/dx` half of [`gradient_slices`].
fn gradient_x_slices(f: &[f64], nx: usize, dx: f64, gx: &mut [f64]) {
    let (ix, hx) = (1.0 / dx, 1.0 / (2.0 * dx));
    for (fr, out) in f.chunks_exact(nx).zip(gx.chunks_exact_mut(nx)) {
        if nx == 1 {
            out[0] = 0.0;
            continue;
        }
        out[0] = (fr[1] - fr[0]) * ix;
        for (o, w) in out[1..nx - 1].iter_mut().zip(fr.windows(3)) {
            *o = (w[2] - w[0]) * hx;
        }
        out[nx - 1] = (fr[nx - 1] - fr[nx - 2]) * ix;
    }
}

/// The `df/dy` half of [`gradient_slices`].
fn gradient_y_slices(f: &[f64], ny: usize, nx: usize, dy: f64, gy: &mut [f64]) {
    if ny == 1 {
        gy.fill(0.0);
        return;
    }
    let (iy, hy) = (1.0 / dy, 1.0 / (2.0 * dy));
    let row = |y: usize| &f[y * nx..(y + 1) * nx];
    for (y, out) in gy.chunks_exact_mut(nx).enumerate() {
        let (a, b, h) = if y == 0 {
            (row(1), row(0), iy)
        } else if y == ny - 1 {
            (row(ny - 1), row(ny - 2), iy)
        } else {
            (row(y + 1), row(y - 1), hy)
        };
        for ((o, &a), &b) in out.iter_mut().zip(a).zip(b) {
            *o = (a - b) * h;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::array;

    /// The plain twin of [`copy_finite`]: element by element.
    fn copy_finite_plain<T: HhdScalar>(
        what: &str,
        src: ArrayView2<'_, T>,
        dst: &mut Array2<f64>,
    ) -> Result<()> {
        for ((row, col), &x) in src.indexed_iter() {
            let x: f64 = x.into();
            if !x.is_finite() {
                return Err(Error::NonFinite {
                    what: what.into(),
                    row,
                    col,
                });
            }
            dst[[row, col]] = x;
        }
        Ok(())
    }

    #[test]
    fn copy_finite_matches_the_plain_copy() {
        // Contiguous rows (a window of a wider array) and strided ones (a
        // transposed view); all finite, or a NaN or an infinity somewhere
        // (the same first bad value named, the rows before it copied).
        let big =
            Array2::from_shape_fn((9, 13), |(i, j)| (i as f32 - 4.0) * 0.37 + j as f32 * -0.11);
        for bad in [
            None,
            Some((3usize, 5usize, f32::NAN)),
            Some((0, 0, f32::INFINITY)),
            Some((6, 9, f32::NEG_INFINITY)),
        ] {
            let mut src = big.clone();
            if let Some((i, j, x)) = bad {
                src[[i, j]] = x;
                src[[i + 1, 2]] = f32::NAN;
            }
            for view in [
                src.slice(ndarray::s![1..8, 2..12]),
                src.t().slice_move(ndarray::s![.., ..]),
            ] {
                let (mut a, mut b) = (
                    Array2::from_elem(view.dim(), 7.0),
                    Array2::from_elem(view.dim(), 7.0),
                );
                let (ra, rb) = (
                    copy_finite("x", view, &mut a),
                    copy_finite_plain("x", view, &mut b),
                );
                assert_eq!(format!("{ra:?}"), format!("{rb:?}"));
                if ra.is_ok() {
                    assert_eq!(a, b);
                } else {
                    // The rows before the bad value's are copied alike.
                    let Err(Error::NonFinite { row, .. }) = ra else {
                        unreachable!()
                    };
                    assert_eq!(
                        a.slice(ndarray::s![..row, ..]),
                        b.slice(ndarray::s![..row, ..])
                    );
                }
            }
        }
    }

    #[test]
    fn gradient_matches_numpy_on_a_small_example() {
        // numpy.gradient([[1, 2, 4, 7], [2, 5, 9, 20.]], 2.0, 0.5)
        let f = array![[1.0, 2.0, 4.0, 7.0], [2.0, 5.0, 9.0, 20.0]];
        let mut gx = Array2::zeros((2, 4));
        let mut gy = Array2::zeros((2, 4));
        gradient(&f, 0.5, 2.0, &mut gx, &mut gy).unwrap();
        assert_eq!(gx, array![[2.0, 3.0, 5.0, 6.0], [6.0, 7.0, 15.0, 22.0]]);
        assert_eq!(gy, array![[0.5, 1.5, 2.5, 6.5], [0.5, 1.5, 2.5, 6.5]]);
        // Strided views take the general path and agree.
        let ft = f.t().to_owned();
        let (mut gxt, mut gyt) = (Array2::zeros((2, 4)), Array2::zeros((2, 4)));
        gradient(&ft.t(), 0.5, 2.0, &mut gxt.view_mut(), &mut gyt.view_mut()).unwrap();
        assert_eq!((gxt, gyt), (gx, gy));
        let mut bad = Array2::zeros((4, 2));
        assert!(gradient(&f, 1.0, 1.0, &mut bad, &mut Array2::zeros((2, 4))).is_err());
    }

    #[test]
    fn cache_keeps_at_most_capacity_sizes() {
        let mut hhd = NaturalHhd::with_cache_capacity(2).unwrap();
        hhd.prepare(4, 5, 1.0, 1.0).unwrap();
        hhd.prepare(6, 5, 1.0, 1.0).unwrap();
        hhd.prepare(4, 5, 1.0, 1.0).unwrap();
        assert_eq!(hhd.cached_sizes(), 2);
        hhd.prepare(4, 5, 1.0, 2.0).unwrap();
        assert_eq!(hhd.cached_sizes(), 2);
        // (6, 5) was the least recently used and is gone; (4, 5) is still there.
        let shapes: Vec<_> = hhd
            .cache
            .iter()
            .map(|c| (c.padded_shape(), c.spacing()))
            .collect();
        assert_eq!(shapes, vec![((8, 9), (1.0, 1.0)), ((8, 9), (1.0, 2.0))]);
        // 58..=60 rows or columns all pad to 120: one plan for these grids.
        let a = hhd.prepare(58, 60, 1.0, 2.0).unwrap();
        let b = hhd.prepare(60, 59, 1.0, 2.0).unwrap();
        assert!(Arc::ptr_eq(&a, &b));
        assert_eq!(a.padded_shape(), (120, 120));
        assert_eq!(a.max_shape(), (60, 60));
        assert!(NaturalHhd::with_cache_capacity(0).is_err());
    }
}
