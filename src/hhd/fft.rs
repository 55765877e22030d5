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
//! `G` is real and even, so its spectrum is real (and even): it is computed
//! once per torus `(py, px)` and spacing `(dx, dy)` and kept in a
//! [`GreenConvolver`], from a quarter of the torus and two real transforms
//! per complex FFT (about a fifth of the time of one full 2-D FFT, which
//! matters because a press of a new size needs a new spectrum).
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
//!
//! On a torus of [`PARALLEL_MIN_CELLS`] cells or more (a patch of about 60 x
//! 300 flow pixels), each pass is cut in two halves run by `rayon::join`, so
//! one large patch uses both cores; the numbers do not change, since every
//! 1-D transform is still done whole by one thread.

use std::sync::Arc;

use ndarray::{ArrayRef2, ArrayView2};
use rayon::prelude::*;
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
///
/// Away from the origin it is evaluated as `ln(r^2) / (4 pi)`: the same
/// value up to the last bit or two, without `hypot`, which costs more than
/// the logarithm (planning a new torus evaluates this a quarter-torus of
/// times).
pub fn green(oy: usize, ox: usize, dx: f64, dy: f64) -> f64 {
    if oy == 0 && ox == 0 {
        return (0.5 * ((dy + dx) / 2.0)).ln() * (0.5 / std::f64::consts::PI);
    }
    let (y, x) = (oy as f64 * dy, ox as f64 * dx);
    (y * y + x * x).ln() * (0.25 / std::f64::consts::PI)
}

/// [`green`] tabulated for offsets `(oy, ox)` below `(rows, cols)` at one
/// spacing: planning a new torus then reads G instead of evaluating a
/// logarithm per offset, which is most of a new spectrum's cost. Grows to
/// the largest torus seen (for a 1600x200 strip on a 2 px grid, 101 x 801
/// values).
#[derive(Debug, Default)]
pub(crate) struct GreenTable {
    dx: f64,
    dy: f64,
    rows: usize,
    cols: usize,
    g: Vec<f64>,
}

impl GreenTable {
    /// Whether the table holds every offset below `(rows, cols)` at `(dx, dy)`.
    fn holds(&self, rows: usize, cols: usize, dx: f64, dy: f64) -> bool {
        rows <= self.rows
            && cols <= self.cols
            && self.dx.to_bits() == dx.to_bits()
            && self.dy.to_bits() == dy.to_bits()
    }

    /// Makes the table hold every offset below `(rows, cols)` at `(dx, dy)`:
    /// grown (to at least the size it had, at the same spacing) or made
    /// anew for another spacing.
    pub(crate) fn ensure(&mut self, rows: usize, cols: usize, dx: f64, dy: f64) {
        if self.holds(rows, cols, dx, dy) {
            return;
        }
        let same = self.dx.to_bits() == dx.to_bits() && self.dy.to_bits() == dy.to_bits();
        let (rows, cols) = if same {
            (rows.max(self.rows), cols.max(self.cols))
        } else {
            (rows, cols)
        };
        self.g.clear();
        self.g.resize(rows * cols, 0.0);
        let fill = |(oy, row): (usize, &mut [f64])| {
            for (ox, v) in row.iter_mut().enumerate() {
                *v = green(oy, ox, dx, dy);
            }
        };
        if rows * cols >= PARALLEL_MIN_CELLS / 4 {
            self.g.par_chunks_mut(cols).enumerate().for_each(fill);
        } else {
            self.g.chunks_mut(cols).enumerate().for_each(fill);
        }
        (self.dx, self.dy, self.rows, self.cols) = (dx, dy, rows, cols);
    }

    fn get(&self, oy: usize, ox: usize) -> f64 {
        self.g[oy * self.cols + ox]
    }
}

/// Working buffers shared by all [`GreenConvolver`]s of one planner: they grow
/// to the largest size seen and are then reused, so a convolution allocates
/// nothing once its size has been met.
#[derive(Default)]
pub struct FftWorkspace {
    rows: Vec<Complex64>,
    cols: Vec<Complex64>,
    scratch: Vec<Complex64>,
    /// The second half's scratch when a pass is split over two threads.
    scratch2: Vec<Complex64>,
    /// Half spectra (`px / 2 + 1` bins) of the rows of a real input
    /// ([`GreenConvolver::potential`]).
    half: Vec<Complex64>,
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
        if self.scratch2.len() < conv.scratch_len {
            self.scratch2.resize(conv.scratch_len, Complex64::default());
        }
    }

    /// Makes sure every buffer can hold what [`GreenConvolver::potential`]
    /// needs for `ny` rows of a real input.
    fn reserve_real(&mut self, conv: &GreenConvolver, ny: usize) {
        let qx = conv.px / 2 + 1;
        let grow = |v: &mut Vec<Complex64>, n: usize| {
            if v.len() < n {
                v.resize(n, Complex64::default());
            }
        };
        grow(&mut self.rows, ny.div_ceil(2) * conv.px);
        grow(&mut self.half, 2 * ny.div_ceil(2) * qx);
        grow(&mut self.cols, qx * conv.py);
        grow(&mut self.scratch, conv.scratch_len);
        grow(&mut self.scratch2, conv.scratch_len);
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
    /// Spectrum of G times `dx dy / (py px)`, transposed (index
    /// `kx * py + ky`), for `kx <= px / 2`; column `kx > px / 2` is column
    /// `px - kx`.
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
        Self::with_table(planner, None, ny, nx, dx, dy)
    }

    /// [`new`](Self::new), reading G from `table` when it holds the offsets
    /// and spacing needed (the same values, without their logarithms).
    pub(crate) fn with_table(
        planner: &mut FftPlanner<f64>,
        table: Option<&GreenTable>,
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
        let (qy, qx) = (py / 2 + 1, px / 2 + 1);
        let table = table.filter(|t| t.holds(qy, qx, dx, dy));
        conv.green_hat = conv.green_spectrum(table);
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

    /// Spectrum of G on the torus, scaled and transposed, for the columns
    /// `kx <= px / 2` only (index `kx * py + ky`): the rest mirror them.
    ///
    /// G is real and even on the torus, so every 1-D transform along the way
    /// is of a real, even sequence and has a real, even spectrum. That gives
    /// three savings over one complex 2-D FFT of the whole torus:
    /// - only the `py / 2 + 1` distinct rows (offsets `0..=py/2`) are
    ///   transformed, and only the first `px / 2 + 1` bins of each are kept;
    /// - two real even sequences share one complex FFT: with `z = a + i b`,
    ///   `FFT(z) = A + i B` where `A` and `B` are real, so they come back as
    ///   the real and imaginary parts;
    /// - the columns are then transformed in the same pairs.
    ///
    /// About a quarter of the full transform's work, which matters because a
    /// new patch size means a new spectrum.
    fn green_spectrum(&self, table: Option<&GreenTable>) -> Vec<f64> {
        let g = |oy: usize, ox: usize| match table {
            Some(t) => t.get(oy, ox),
            None => green(oy, ox, self.dx, self.dy),
        };
        let (py, px) = (self.py, self.px);
        let (qy, qx) = (py / 2 + 1, px / 2 + 1);
        // A large torus (a new size of a large patch) shares the work with
        // rayon's pool: every 1-D transform is still done whole by one
        // thread, so the spectrum is the same to the bit.
        let par = py * px >= PARALLEL_MIN_CELLS;
        let work = || {
            (
                vec![Complex64::default(); self.scratch_len],
                vec![Complex64::default(); px.max(py)],
            )
        };
        // Stage 1: rows oy = 0..qy, a pair per FFT, bins kx < qx kept:
        // rows[oy * qx + kx]. Torus index k holds offset min(k, p - k):
        // every offset a grid of up to max_shape can produce is then
        // exact, and G stays even.
        let mut rows = vec![0.0; qy.next_multiple_of(2) * qx];
        let stage1 = |(scratch, buf): &mut (Vec<Complex64>, Vec<Complex64>),
                      (pair, out): (usize, &mut [f64])| {
            let oy = 2 * pair;
            let buf = &mut buf[..px];
            let has_b = oy + 1 < qy;
            for (ox, z) in buf[..qx].iter_mut().enumerate() {
                let b = if has_b { g(oy + 1, ox) } else { 0.0 };
                *z = Complex64::new(g(oy, ox), b);
            }
            for kx in qx..px {
                buf[kx] = buf[px - kx];
            }
            self.fwd_x.process_with_scratch(buf, scratch);
            let (a, b) = out.split_at_mut(qx);
            for ((a, b), z) in a.iter_mut().zip(b).zip(&buf[..qx]) {
                *a = z.re;
                *b = z.im;
            }
        };
        chunk_halves(&mut rows, 2 * qx, par, work, stage1);
        // Stage 2: columns kx = 0..qx over the whole torus height (row ky
        // holds offset min(ky, py - ky)), a pair per FFT.
        let scale = self.dx * self.dy / (py * px) as f64;
        let mut hat = vec![0.0; qx.next_multiple_of(2) * py];
        let rows = &rows;
        let stage2 = |(scratch, buf): &mut (Vec<Complex64>, Vec<Complex64>),
                      (pair, out): (usize, &mut [f64])| {
            let kx = 2 * pair;
            let buf = &mut buf[..py];
            let has_b = kx + 1 < qx;
            for (ky, z) in buf.iter_mut().enumerate() {
                let oy = ky.min(py - ky);
                let b = if has_b { rows[oy * qx + kx + 1] } else { 0.0 };
                *z = Complex64::new(rows[oy * qx + kx], b);
            }
            self.fwd_y.process_with_scratch(buf, scratch);
            // The spectra are real up to rounding: the parts that should
            // vanish are dropped on purpose.
            let (a, b) = out.split_at_mut(py);
            for ((a, b), z) in a.iter_mut().zip(b).zip(buf.iter()) {
                *a = z.re * scale;
                *b = z.im * scale;
            }
        };
        chunk_halves(&mut hat, 2 * py, par, work, stage2);
        hat.truncate(qx * py);
        hat
    }

    /// The potentials `D = dx dy sum_i div(i) G(m - i)` and
    /// `R = dx dy sum_i curl(i) G(m - i)` over the whole grid, written into
    /// `d_out` and `r_out` (all four arrays of one shape, at most
    /// [`max_shape`](Self::max_shape)).
    ///
    /// On a torus of at least [`PARALLEL_MIN_CELLS`] cells the FFT passes
    /// run in two halves on rayon's pool (bit-identical to one thread).
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
        let par = self.py * self.px >= PARALLEL_MIN_CELLS;
        self.convolve_rows(ws, ny, par);
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

    /// The potential `D = dx dy sum_i div(i) G(m - i)` of one real field
    /// alone, written into `d_out` (both arrays of one shape, at most
    /// [`max_shape`](Self::max_shape)): what [`potentials`](Self::potentials)
    /// computes as its real part, for about half the work.
    ///
    /// Two real rows travel in one complex FFT (`a + i b`), whose spectrum
    /// splits into the two rows' half spectra by Hermitian symmetry; only
    /// the `px / 2 + 1` columns of non-negative frequencies are transformed
    /// (the others mirror them); two rows come back from one inverse FFT the
    /// same way. The result equals `potentials`' real part up to rounding
    /// (the tests check both against the direct sum).
    ///
    /// On a torus of at least [`PARALLEL_MIN_CELLS`] cells the FFT passes
    /// run in two halves on rayon's pool (bit-identical to one thread).
    ///
    /// Inputs are not checked for NaN here: one NaN makes every output NaN.
    /// Errors if the shapes differ or exceed `max_shape`.
    pub fn potential(
        &self,
        ws: &mut FftWorkspace,
        div: ArrayView2<'_, f64>,
        d_out: &mut ArrayRef2<f64>,
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
        if d_out.dim() != (ny, nx) {
            let dim = d_out.dim();
            return Err(Error::shape("D output", (nx, ny), (dim.1, dim.0)));
        }
        ws.reserve_real(self, ny);
        let px = self.px;
        let pairs = ny.div_ceil(2);
        let rows = &mut ws.rows[..pairs * px];
        for (p, row) in rows.chunks_exact_mut(px).enumerate() {
            let a = div.row(2 * p);
            if 2 * p + 1 < ny {
                let b = div.row(2 * p + 1);
                for ((z, &a), &b) in row.iter_mut().zip(&a).zip(&b) {
                    *z = Complex64::new(a, b);
                }
            } else {
                for (z, &a) in row.iter_mut().zip(&a) {
                    *z = Complex64::new(a, 0.0);
                }
            }
            row[nx..].fill(Complex64::default());
        }
        let par = self.py * self.px >= PARALLEL_MIN_CELLS;
        self.convolve_real(ws, ny, par);
        let rows = &ws.rows[..pairs * px];
        for (p, row) in rows.chunks_exact(px).enumerate() {
            for (d, z) in d_out.row_mut(2 * p).iter_mut().zip(row) {
                *d = z.re;
            }
            if 2 * p + 1 < ny {
                for (d, z) in d_out.row_mut(2 * p + 1).iter_mut().zip(row) {
                    *d = z.im;
                }
            }
        }
        Ok(())
    }

    /// In place on `ws.rows[..ny.div_ceil(2) * px]`: pairs of real rows
    /// packed as `a + i b` (zero-padded to `px`) in, the pairs' potentials
    /// packed the same way out (valid in the first `nx` columns). See
    /// [`potential`](Self::potential); `par` as in
    /// [`convolve_rows`](Self::convolve_rows).
    fn convolve_real(&self, ws: &mut FftWorkspace, ny: usize, par: bool) {
        let (py, px) = (self.py, self.px);
        let qx = px / 2 + 1;
        let pairs = ny.div_ceil(2);
        let FftWorkspace {
            rows,
            cols,
            scratch,
            scratch2,
            half,
        } = ws;
        let s1 = &mut scratch[..self.scratch_len];
        let s2 = &mut scratch2[..self.scratch_len];
        let rows = &mut rows[..pairs * px];
        let half = &mut half[..2 * pairs * qx];
        let cols = &mut cols[..qx * py];
        // Pairs 0..cut on one thread, the rest on the other.
        let cut = if par { pairs / 2 } else { 0 };
        // Rows: forward FFT of each pair, split into the two half spectra.
        // (An odd last row has no partner: its pair's second spectrum is
        // zero and stays unused.)
        pair_halves(rows, half, cut, px, qx, s1, s2, |z, h, _, s| {
            self.fwd_x.process_with_scratch(z, s);
            for (zp, hp) in z.chunks_exact(px).zip(h.chunks_exact_mut(2 * qx)) {
                let (ha, hb) = hp.split_at_mut(qx);
                split_pair(zp, ha);
                unsplit_second(zp, hb);
            }
        });
        // Columns kx = 0..qx: forward, product, inverse while in cache.
        let col_cut = if par { qx / 2 * py } else { 0 };
        let data = &*half;
        halves(cols, col_cut, s1, s2, |part, start, s| {
            let first = start / py;
            transpose(data, part, ny, qx, first, py);
            for (k, col) in part.chunks_exact_mut(py).enumerate() {
                let g = &self.green_hat[(first + k) * py..][..py];
                col[ny..].fill(Complex64::default());
                self.fwd_y.process_with_scratch(col, s);
                for (c, &g) in col.iter_mut().zip(g) {
                    *c *= g;
                }
                self.inv_y.process_with_scratch(col, s);
            }
        });
        // Rows back: the two half spectra of a pair joined, one inverse FFT.
        let spectra = &*cols;
        transpose_back(spectra, &mut half[..ny * qx], 0, qx, py);
        pair_halves(rows, half, cut, px, qx, s1, s2, |z, h, _, s| {
            for (zp, hp) in z.chunks_exact_mut(px).zip(h.chunks_exact(2 * qx)) {
                let (ha, hb) = hp.split_at(qx);
                join_pair(ha, hb, zp);
            }
            self.inv_x.process_with_scratch(z, s);
        });
    }

    /// In place on `ws.rows[..ny * px]`: rows of `div + i curl` (zero-padded
    /// to `px`) in, rows of `D + i R` out (valid in the first `nx` columns).
    ///
    /// With `par` (a torus of at least [`PARALLEL_MIN_CELLS`] cells) each FFT
    /// pass is cut in two halves (rows, then columns) run by `rayon::join`, each with
    /// its own scratch: a single large patch then uses both cores, and the
    /// result is the same to the bit since every 1-D transform is done alone.
    fn convolve_rows(&self, ws: &mut FftWorkspace, ny: usize, par: bool) {
        let (py, px) = (self.py, self.px);
        let FftWorkspace {
            rows,
            cols,
            scratch,
            scratch2,
            ..
        } = ws;
        let s1 = &mut scratch[..self.scratch_len];
        let s2 = &mut scratch2[..self.scratch_len];
        let rows = &mut rows[..ny * px];
        let cols = &mut cols[..px * py];
        let row_cut = if par { ny / 2 * px } else { 0 };
        halves(rows, row_cut, s1, s2, |part, _, s| {
            self.fwd_x.process_with_scratch(part, s)
        });
        // Column kx gets the ny data rows, then zeros down to py; forward,
        // product and inverse while the column is in L1 (three sweeps over
        // the whole torus would run from memory).
        let col_cut = if par { px / 2 * py } else { 0 };
        let data = &*rows;
        halves(cols, col_cut, s1, s2, |part, start, s| {
            let first = start / py;
            transpose(data, part, ny, px, first, py);
            for (k, col) in part.chunks_exact_mut(py).enumerate() {
                // Column kx's spectrum equals column px - kx's (G is even).
                let kx = first + k;
                let g = &self.green_hat[kx.min(px - kx) * py..][..py];
                col[ny..].fill(Complex64::default());
                self.fwd_y.process_with_scratch(col, s);
                for (c, &g) in col.iter_mut().zip(g) {
                    *c *= g;
                }
                self.inv_y.process_with_scratch(col, s);
            }
        });
        // Only the first ny rows of the torus are inside the output window.
        let spectra = &*cols;
        halves(rows, row_cut, s1, s2, |part, start, s| {
            transpose_back(spectra, part, start / px, px, py);
            self.inv_x.process_with_scratch(part, s)
        });
    }
}

/// Smallest padded torus (cells) whose FFT passes are split over two threads
/// (see [`GreenConvolver::potentials`]); below it the work is too short to
/// be worth handing over.
pub const PARALLEL_MIN_CELLS: usize = 1 << 16;

/// Runs `f(part, start, scratch)` on `data[..cut]` and `data[cut..]` in
/// parallel, each with one of the two scratch buffers, or on the whole of
/// `data` with the first when `cut` leaves one side empty.
fn halves(
    data: &mut [Complex64],
    cut: usize,
    s1: &mut [Complex64],
    s2: &mut [Complex64],
    f: impl Fn(&mut [Complex64], usize, &mut [Complex64]) + Sync,
) {
    if cut == 0 || cut >= data.len() {
        f(data, 0, s1);
        return;
    }
    let (a, b) = data.split_at_mut(cut);
    rayon::join(|| f(a, 0, s1), || f(b, cut, s2));
}

/// Runs `f(state, (k, chunk))` on every `len`-long chunk `k` of `data`
/// (the last one possibly shorter), with a `state` from `init`: with `par`,
/// the first half of the chunks on one thread and the rest on another
/// (`rayon::join`), each with its own state.
fn chunk_halves<S>(
    data: &mut [f64],
    len: usize,
    par: bool,
    init: impl Fn() -> S + Sync,
    f: impl Fn(&mut S, (usize, &mut [f64])) + Sync,
) {
    let run = |part: &mut [f64], first: usize| {
        let mut state = init();
        for (k, chunk) in part.chunks_mut(len).enumerate() {
            f(&mut state, (first + k, chunk));
        }
    };
    let n = data.len().div_ceil(len);
    if !par || n < 2 {
        run(data, 0);
        return;
    }
    let (a, b) = data.split_at_mut(n / 2 * len);
    rayon::join(|| run(a, 0), || run(b, n / 2));
}

/// [`halves`] for the row passes of [`GreenConvolver::potential`]: `rows`
/// holds pairs of rows (`px` each), `half` the two half spectra (`qx` bins
/// each) of every pair; pairs `..cut` and `cut..` go to the two threads,
/// each with its pairs' half spectra. `f(pairs, half_spectra, first, scratch)`
/// gets the index of its first pair.
fn pair_halves(
    rows: &mut [Complex64],
    half: &mut [Complex64],
    cut: usize,
    px: usize,
    qx: usize,
    s1: &mut [Complex64],
    s2: &mut [Complex64],
    f: impl Fn(&mut [Complex64], &mut [Complex64], usize, &mut [Complex64]) + Sync,
) {
    let pairs = rows.len() / px;
    if cut == 0 || cut >= pairs {
        f(rows, half, 0, s1);
        return;
    }
    let (ra, rb) = rows.split_at_mut(cut * px);
    let (ha, hb) = half.split_at_mut(2 * cut * qx);
    rayon::join(|| f(ra, ha, 0, s1), || f(rb, hb, cut, s2));
}

/// The half spectrum (`h.len()` bins) of the real part `a` of a signal
/// `z = a + i b` from `z`'s spectrum: `A[k] = (Z[k] + conj Z[-k]) / 2`.
/// Bin 0 (and bin `p / 2` for an even length `p`) is real exactly.
fn split_pair(z: &[Complex64], h: &mut [Complex64]) {
    let p = z.len();
    for (k, out) in h.iter_mut().enumerate() {
        let (a, b) = (z[k], z[(p - k) % p].conj());
        *out = (a + b) * 0.5;
    }
    real_ends(h, p);
}

/// The half spectrum of the imaginary part `b` of `z = a + i b` from `z`'s
/// spectrum: `B[k] = (Z[k] - conj Z[-k]) / (2 i)`.
fn unsplit_second(z: &[Complex64], h: &mut [Complex64]) {
    let p = z.len();
    for (k, out) in h.iter_mut().enumerate() {
        let d = z[k] - z[(p - k) % p].conj();
        // d / (2 i) = (d.im - i d.re) / 2
        *out = Complex64::new(d.im * 0.5, -d.re * 0.5);
    }
    real_ends(h, p);
}

/// The spectrum of a real signal is real at bin 0 and, for an even length
/// `p`, at bin `p / 2`: drops what rounding left there.
fn real_ends(h: &mut [Complex64], p: usize) {
    h[0].im = 0.0;
    if p % 2 == 0 {
        h[p / 2].im = 0.0;
    }
}

/// The spectrum `Z = A + i B` of `a + i b` from the half spectra of the two
/// real signals, both extended by Hermitian symmetry (`A[-k] = conj A[k]`).
fn join_pair(a: &[Complex64], b: &[Complex64], z: &mut [Complex64]) {
    let p = z.len();
    let q = a.len();
    for (k, out) in z.iter_mut().enumerate() {
        let (ak, bk) = if k < q {
            (a[k], b[k])
        } else {
            (a[p - k].conj(), b[p - k].conj())
        };
        // ak + i bk
        *out = Complex64::new(ak.re - bk.im, ak.im + bk.re);
    }
}

/// Columns `first..` of the row-major `nrows x cols` array `src` into
/// `dst`, which holds as many columns of length `dst_stride` as fit:
/// `dst[(c - first) * dst_stride + r] = src[r * cols + c]` for `r < nrows`.
fn transpose(
    src: &[Complex64],
    dst: &mut [Complex64],
    nrows: usize,
    cols: usize,
    first: usize,
    dst_stride: usize,
) {
    let end = (first + dst.len() / dst_stride).min(cols);
    // Blocked so that both sides stay in cache for large grids.
    const B: usize = 16;
    for r0 in (0..nrows).step_by(B) {
        let r1 = (r0 + B).min(nrows);
        for c0 in (first..end).step_by(B) {
            let c1 = (c0 + B).min(end);
            for r in r0..r1 {
                let s = &src[r * cols..];
                for c in c0..c1 {
                    dst[(c - first) * dst_stride + r] = s[c];
                }
            }
        }
    }
}

/// Inverse of [`transpose`] for rows `first..` (as many rows of `cols` as
/// `dst` holds): `dst[(r - first) * cols + c] = src[c * src_stride + r]`.
fn transpose_back(
    src: &[Complex64],
    dst: &mut [Complex64],
    first: usize,
    cols: usize,
    src_stride: usize,
) {
    let end = first + dst.len() / cols;
    const B: usize = 16;
    for c0 in (0..cols).step_by(B) {
        let c1 = (c0 + B).min(cols);
        for r0 in (first..end).step_by(B) {
            let r1 = (r0 + B).min(end);
            for c in c0..c1 {
                let s = &src[c * src_stride..];
                for r in r0..r1 {
                    dst[(r - first) * cols + c] = s[r];
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
        transpose(&src, &mut t, nr, nc, 0, stride);
        assert_eq!(t[3 * stride + 2], src[2 * nc + 3]);
        let mut back = vec![Complex64::default(); nr * nc];
        transpose_back(&t, &mut back, 0, nc, stride);
        assert_eq!(back, src);
        // A block of columns, then a block of rows, as the two halves do.
        let mut part = vec![Complex64::default(); 10 * stride];
        transpose(&src, &mut part, nr, nc, 20, stride);
        assert_eq!(part[..], t[20 * stride..30 * stride]);
        let mut rows = vec![Complex64::default(); 2 * nc];
        transpose_back(&t, &mut rows, 3, nc, stride);
        assert_eq!(rows[..], src[3 * nc..]);
    }

    /// The slow twin of `green_spectrum`: G laid out on the whole torus, one
    /// complex 2-D FFT, real part kept.
    fn full_spectrum(py: usize, px: usize, dx: f64, dy: f64) -> Vec<Vec<f64>> {
        let mut planner = FftPlanner::new();
        let (fx, fy) = (planner.plan_fft_forward(px), planner.plan_fft_forward(py));
        let mut g: Vec<Vec<Complex64>> = (0..py)
            .map(|ky| {
                (0..px)
                    .map(|kx| Complex64::new(green(ky.min(py - ky), kx.min(px - kx), dx, dy), 0.0))
                    .collect()
            })
            .collect();
        for row in &mut g {
            fx.process(row);
        }
        for kx in 0..px {
            let mut col: Vec<Complex64> = (0..py).map(|ky| g[ky][kx]).collect();
            fy.process(&mut col);
            for (ky, c) in col.into_iter().enumerate() {
                g[ky][kx] = c;
            }
        }
        let scale = dx * dy / (py * px) as f64;
        g.iter()
            .map(|r| r.iter().map(|c| c.re * scale).collect())
            .collect()
    }

    #[test]
    fn green_spectrum_matches_the_full_torus_transform() {
        let mut planner = FftPlanner::new();
        // Odd and even tori, single rows and columns, unequal spacings.
        for (ny, nx, dx, dy) in [
            (1, 1, 1.0, 1.0),
            (1, 7, 0.5, 2.0),
            (6, 1, 1.0, 1.0),
            (2, 3, 1.5, 0.7),
            (5, 8, 1.0, 3.0),
            (13, 28, 2.0, 2.0),
            (40, 33, 0.3, 1.1),
            // Past PARALLEL_MIN_CELLS: the spectrum is shared with the pool.
            (130, 260, 2.0, 2.0),
        ] {
            let conv = GreenConvolver::new(&mut planner, ny, nx, dx, dy).unwrap();
            let (py, px) = conv.padded_shape();
            let want = full_spectrum(py, px, dx, dy);
            let top = want.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
            for (ky, row) in want.iter().enumerate() {
                for (kx, &w) in row.iter().enumerate() {
                    let got = conv.green_hat[kx.min(px - kx) * py + ky];
                    assert!(
                        (got - w).abs() <= 1e-13 * top,
                        "{ny}x{nx} torus {py}x{px} at ({ky}, {kx}): {got} vs {w}"
                    );
                }
            }
        }
    }

    #[test]
    fn split_real_passes_are_bit_identical_to_one_thread() {
        let mut planner = FftPlanner::new();
        // Odd and even row counts: an odd number of pairs, and a lone row.
        for (ny, nx) in [(9, 23), (8, 16), (7, 5)] {
            let conv = GreenConvolver::new(&mut planner, ny, nx, 1.0, 2.0).unwrap();
            let px = conv.padded_shape().1;
            let pairs = ny.div_ceil(2);
            let input: Vec<Complex64> = (0..pairs * px)
                .map(|i| {
                    let (p, c) = (i / px, i % px);
                    let im = if 2 * p + 1 < ny {
                        ((p + c * 5) % 7) as f64
                    } else {
                        0.0
                    };
                    if c < nx {
                        Complex64::new(((p * 7 + c * 3) % 11) as f64, im)
                    } else {
                        Complex64::default()
                    }
                })
                .collect();
            let mut out = Vec::new();
            for par in [false, true] {
                let mut ws = FftWorkspace::new();
                ws.reserve_real(&conv, ny);
                ws.rows[..pairs * px].copy_from_slice(&input);
                conv.convolve_real(&mut ws, ny, par);
                out.push(ws.rows[..pairs * px].to_vec());
            }
            assert_eq!(out[0], out[1], "{ny}x{nx}");
            assert_ne!(out[0], input);
        }
    }

    #[test]
    fn a_tabulated_green_gives_the_same_spectrum_to_the_bit() {
        let mut planner = FftPlanner::new();
        let mut table = GreenTable::default();
        // The table grows with the tori, and is made anew for a spacing.
        for (ny, nx, dx, dy) in [
            (5, 8, 1.0, 3.0),
            (40, 33, 1.0, 3.0),
            (13, 28, 1.0, 3.0),
            (13, 28, 2.0, 2.0),
            (130, 260, 2.0, 2.0),
        ] {
            let (py, px) = GreenConvolver::torus_for(ny, nx);
            table.ensure(py / 2 + 1, px / 2 + 1, dx, dy);
            let want = GreenConvolver::new(&mut planner, ny, nx, dx, dy).unwrap();
            let got =
                GreenConvolver::with_table(&mut planner, Some(&table), ny, nx, dx, dy).unwrap();
            assert_eq!(got.green_hat, want.green_hat, "{ny}x{nx}");
        }
        // The largest torus, 270 x 540 for 130 x 260.
        assert_eq!((table.rows, table.cols), (136, 271));
        // A table that does not hold the offsets is not read.
        let small = GreenTable::default();
        let got = GreenConvolver::with_table(&mut planner, Some(&small), 9, 9, 1.0, 1.0).unwrap();
        let want = GreenConvolver::new(&mut planner, 9, 9, 1.0, 1.0).unwrap();
        assert_eq!(got.green_hat, want.green_hat);
    }

    #[test]
    fn split_passes_are_bit_identical_to_one_thread() {
        let (ny, nx) = (9, 23);
        let mut planner = FftPlanner::new();
        let conv = GreenConvolver::new(&mut planner, ny, nx, 1.0, 2.0).unwrap();
        let px = conv.padded_shape().1;
        let input: Vec<Complex64> = (0..ny * px)
            .map(|i| {
                let (r, c) = (i / px, i % px);
                if c < nx {
                    Complex64::new(((r * 7 + c * 3) % 11) as f64, ((r + c * 5) % 7) as f64)
                } else {
                    Complex64::default()
                }
            })
            .collect();
        let mut out = Vec::new();
        for par in [false, true] {
            let mut ws = FftWorkspace::new();
            ws.reserve_for(&conv, ny);
            ws.rows[..ny * px].copy_from_slice(&input);
            conv.convolve_rows(&mut ws, ny, par);
            out.push(ws.rows[..ny * px].to_vec());
        }
        assert_eq!(out[0], out[1]);
        assert_ne!(out[0], input);
    }
}
