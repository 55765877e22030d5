//! Area-averaged image pyramids, Sobel gradients and bilinear resampling.
//!
//! All kernels work on contiguous row-major `f32` slices (`width * height`),
//! run rows in parallel with rayon, and write into caller-owned buffers so a
//! planner can reuse them frame after frame. Each output pixel is computed
//! from its inputs alone, so results do not depend on the thread count.

use rayon::prelude::*;

use crate::error::{Error, Result};

/// Errors unless `buf` holds exactly `w * h` values.
fn check_len(what: &str, buf: &[f32], w: usize, h: usize) -> Result<()> {
    if buf.len() == w * h {
        Ok(())
    } else {
        Err(Error::param(
            what,
            format!("buffer of {} values for a {w}x{h} image", buf.len()),
        ))
    }
}

/// Size of pyramid level `scale` for a `(width, height)` image: integer
/// division by `2^scale`, as OpenCV's DIS does.
pub fn level_size(width: usize, height: usize, scale: usize) -> (usize, usize) {
    (width >> scale, height >> scale)
}

/// Box-averages `src` (`sw x sh`) by a `factor x factor` area into `dst`
/// (`sw / factor x sh / factor`, integer division: trailing rows and columns
/// that do not fill a whole box are dropped, as in OpenCV's `INTER_AREA` at
/// integer ratios). `factor == 1` is a copy. Errors if `factor` is 0 or a
/// buffer has the wrong length.
///
/// Levels stay in `f32` (no 8-bit rounding), so sub-grey-level detail of small
/// markers survives into the coarse levels.
pub fn downsample_area(
    src: &[f32],
    sw: usize,
    sh: usize,
    factor: usize,
    dst: &mut [f32],
) -> Result<()> {
    if factor == 0 {
        return Err(Error::param(
            "factor",
            "the averaging factor must be at least 1",
        ));
    }
    let (dw, dh) = (sw / factor, sh / factor);
    check_len("src", src, sw, sh)?;
    check_len("dst", dst, dw, dh)?;
    if dw == 0 || dh == 0 {
        return Ok(());
    }
    if factor == 1 {
        dst.par_chunks_mut(dw)
            .zip(src.par_chunks(sw))
            .for_each(|(d, s)| d.copy_from_slice(&s[..dw]));
        return Ok(());
    }
    let norm = 1.0 / (factor * factor) as f32;
    dst.par_chunks_mut(dw).enumerate().for_each(|(y, drow)| {
        let rows = &src[y * factor * sw..(y + 1) * factor * sw];
        if factor == 2 {
            let (r0, r1) = rows.split_at(sw);
            // Dispatched at run time (see `flow::simd_arch`): same values on every path.
            super::simd_arch().dispatch(Half2Op { r0, r1, out: drow });
        } else if factor <= 64 {
            // Sum the `factor` rows column by column first (contiguous, vectorises),
            // then each group of `factor` columns, through a stack buffer of a few
            // hundred columns (no allocation). Integer-valued (8-bit) pixels sum
            // exactly in any order, so this equals the box sum.
            const BUF: usize = 512;
            let mut buf = [0.0f32; BUF];
            let per = BUF / factor;
            for (ci, dchunk) in drow.chunks_mut(per).enumerate() {
                let c0 = ci * per * factor;
                let n = dchunk.len() * factor;
                let col = &mut buf[..n];
                col.copy_from_slice(&rows[c0..c0 + n]);
                for r in rows.chunks_exact(sw).skip(1) {
                    for (a, b) in col.iter_mut().zip(&r[c0..c0 + n]) {
                        *a += b;
                    }
                }
                for (d, g) in dchunk.iter_mut().zip(col.chunks_exact(factor)) {
                    *d = g.iter().sum::<f32>() * norm;
                }
            }
        } else {
            drow.fill(0.0);
            for r in rows.chunks_exact(sw) {
                for (x, d) in drow.iter_mut().enumerate() {
                    let c = x * factor;
                    *d += r[c..c + factor].iter().sum::<f32>();
                }
            }
            for d in drow.iter_mut() {
                *d *= norm;
            }
        }
    });
    Ok(())
}

/// One output row of a 2x2 box average as a `pulp` operation (see
/// [`BlendRowOp`]): `out[x]` averages columns `2x, 2x + 1` of rows `r0`, `r1`.
struct Half2Op<'a> {
    r0: &'a [f32],
    r1: &'a [f32],
    out: &'a mut [f32],
}

impl pulp::WithSimd for Half2Op<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let n = self.out.len();
        let (r0, r1) = (&self.r0[..2 * n], &self.r1[..2 * n]);
        for (x, d) in self.out.iter_mut().enumerate() {
            let c = 2 * x;
            *d = (r0[c] + r0[c + 1] + r1[c] + r1[c + 1]) * 0.25;
        }
    }
}

/// 3x3 Sobel gradients of `img` (`w x h`) into `gx`, `gy`, scaled by `scale`
/// (`1.0` gives OpenCV's un-normalized Sobel where a unit ramp gives 8;
/// `0.125` gives the true derivative). Borders are reflected without
/// repeating the edge pixel (OpenCV's `BORDER_REFLECT_101`). Errors if a
/// buffer has the wrong length.
pub fn sobel(
    img: &[f32],
    w: usize,
    h: usize,
    scale: f32,
    gx: &mut [f32],
    gy: &mut [f32],
) -> Result<()> {
    check_len("img", img, w, h)?;
    check_len("gx", gx, w, h)?;
    check_len("gy", gy, w, h)?;
    if w == 0 || h == 0 {
        return Ok(());
    }
    let refl = |i: isize, n: usize| -> usize {
        let n = n as isize;
        if n == 1 {
            return 0;
        }
        let r = if i < 0 {
            -i
        } else if i >= n {
            2 * n - 2 - i
        } else {
            i
        };
        r as usize
    };
    gx.par_chunks_mut(w)
        .zip(gy.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (gxr, gyr))| {
            let up = &img[refl(y as isize - 1, h) * w..][..w];
            let mid = &img[y * w..][..w];
            let dn = &img[refl(y as isize + 1, h) * w..][..w];
            for x in 0..w {
                let l = refl(x as isize - 1, w);
                let r = refl(x as isize + 1, w);
                let dx = (up[r] - up[l]) + 2.0 * (mid[r] - mid[l]) + (dn[r] - dn[l]);
                let dy = (dn[l] - up[l]) + 2.0 * (dn[x] - up[x]) + (dn[r] - up[r]);
                gxr[x] = dx * scale;
                gyr[x] = dy * scale;
            }
        });
    Ok(())
}

/// Normalized Gaussian taps of standard deviation `sigma` px, radius
/// `ceil(3 sigma)`; empty for `sigma <= 0` (no filtering).
pub fn gaussian_kernel(sigma: f32) -> Vec<f32> {
    if sigma <= 0.0 {
        return Vec::new();
    }
    let rad = (3.0 * sigma).ceil() as isize;
    let mut k: Vec<f32> = (-rad..=rad)
        .map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let sum: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    k
}

/// Separable convolution of `img` (`w x h`) in place with the symmetric
/// taps `k` (odd length, e.g. from [`gaussian_kernel`]; empty does nothing),
/// reflect-101 borders, using `tmp` (same size) as scratch. Errors if a
/// buffer has the wrong length or `k` has an even length.
pub fn gaussian_blur(
    img: &mut [f32],
    w: usize,
    h: usize,
    k: &[f32],
    tmp: &mut [f32],
) -> Result<()> {
    check_len("img", img, w, h)?;
    check_len("tmp", tmp, w, h)?;
    check_taps(k)?;
    if k.is_empty() || w == 0 || h == 0 {
        return Ok(());
    }
    blur_rows(img, w, k, tmp);
    blur_cols(tmp, w, h, k, img);
    Ok(())
}

/// [`gaussian_blur`] of `src` into `dst` (both `w x h`), `src` unchanged;
/// an empty `k` copies. The same values as blurring a copy in place.
pub fn gaussian_blur_into(
    src: &[f32],
    w: usize,
    h: usize,
    k: &[f32],
    tmp: &mut [f32],
    dst: &mut [f32],
) -> Result<()> {
    check_len("src", src, w, h)?;
    check_len("tmp", tmp, w, h)?;
    check_len("dst", dst, w, h)?;
    check_taps(k)?;
    if k.is_empty() {
        dst.copy_from_slice(src);
        return Ok(());
    }
    if w == 0 || h == 0 {
        return Ok(());
    }
    blur_rows(src, w, k, tmp);
    blur_cols(tmp, w, h, k, dst);
    Ok(())
}

fn check_taps(k: &[f32]) -> Result<()> {
    if k.len() % 2 == 0 && !k.is_empty() {
        return Err(Error::param("kernel", "needs an odd number of taps"));
    }
    Ok(())
}

/// Index `i` reflected into `0..n` without repeating the edge (reflect-101),
/// reflecting again until inside (a radius may exceed a tiny size).
fn reflect101(i: isize, n: usize) -> usize {
    let n = n as isize;
    if n == 1 {
        return 0;
    }
    let mut i = i;
    loop {
        if i < 0 {
            i = -i;
        } else if i >= n {
            i = 2 * n - 2 - i;
        } else {
            return i as usize;
        }
    }
}

/// Most taps the vertical pass keeps its row offsets for on the stack
/// (a prefilter of up to 8 px has 49); longer kernels take the per-tap loop.
const MAX_TAPS: usize = 64;

/// The horizontal pass of the blur: each row of `src` (`w` columns) into the
/// same row of `out`. Every output sums its taps in order from 0.0, in `f32`
/// (`((0 + k0 a0) + k1 a1) + ...`), on every path and instruction set.
fn blur_rows(src: &[f32], w: usize, k: &[f32], out: &mut [f32]) {
    out.par_chunks_mut(w)
        .zip(src.par_chunks(w))
        .for_each(|(orow, row)| {
            // Dispatched at run time (see `flow::simd_arch`): same values on every path.
            super::simd_arch().dispatch(BlurRowOp { row, k, out: orow });
        });
}

/// The vertical pass of the blur: each row of `out` (`w x h`) from the rows
/// of `src` its taps reach, summed as in [`blur_rows`].
fn blur_cols(src: &[f32], w: usize, h: usize, k: &[f32], out: &mut [f32]) {
    let rad = (k.len() / 2) as isize;
    out.par_chunks_mut(w).enumerate().for_each(|(y, orow)| {
        let row_of = |t: usize| reflect101(y as isize + t as isize - rad, h) * w;
        if k.len() <= MAX_TAPS {
            let mut offsets = [0usize; MAX_TAPS];
            for (t, o) in offsets[..k.len()].iter_mut().enumerate() {
                *o = row_of(t);
            }
            // Dispatched at run time (see `flow::simd_arch`): same values on every path.
            super::simd_arch().dispatch(BlurColsOp {
                src,
                offsets: &offsets[..k.len()],
                k,
                out: orow,
            });
        } else {
            orow.fill(0.0);
            for (t, &kv) in k.iter().enumerate() {
                let s = &src[row_of(t)..][..w];
                for (o, &v) in orow.iter_mut().zip(s) {
                    *o += kv * v;
                }
            }
        }
    });
}

/// [`blur_row`] as a `pulp` operation (see [`BlendRowOp`]).
struct BlurRowOp<'a> {
    row: &'a [f32],
    k: &'a [f32],
    out: &'a mut [f32],
}

impl pulp::WithSimd for BlurRowOp<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        blur_row(self.row, self.k, self.out);
    }
}

/// One row of the horizontal pass: the interior eight outputs at a time,
/// each group's eight sums held in registers across the taps; the reflected
/// borders (and a last group of fewer than eight) one output at a time.
#[inline(always)]
fn blur_row(row: &[f32], k: &[f32], out: &mut [f32]) {
    let w = row.len();
    let rad = k.len() / 2;
    let out = &mut out[..w];
    let border = |x: usize| -> f32 {
        let mut acc = 0.0f32;
        for (t, &kv) in k.iter().enumerate() {
            acc += kv * row[reflect101(x as isize + t as isize - rad as isize, w)];
        }
        acc
    };
    if w <= 2 * rad {
        for (x, o) in out.iter_mut().enumerate() {
            *o = border(x);
        }
        return;
    }
    // Output `rad + x` reads `row[x..x + k.len()]`.
    let n = w - 2 * rad;
    let groups = n / 8;
    for (g, o) in out[rad..][..groups * 8].chunks_exact_mut(8).enumerate() {
        let x = 8 * g;
        let mut acc = [0.0f32; 8];
        for (t, &kv) in k.iter().enumerate() {
            let s: &[f32; 8] = row[x + t..][..8].try_into().expect("8 values");
            for l in 0..8 {
                acc[l] += kv * s[l];
            }
        }
        o.copy_from_slice(&acc);
    }
    for x in groups * 8..n {
        let mut acc = 0.0f32;
        for (t, &kv) in k.iter().enumerate() {
            acc += kv * row[x + t];
        }
        out[rad + x] = acc;
    }
    for x in (0..rad).chain(w - rad..w) {
        out[x] = border(x);
    }
}

/// [`blur_cols_row`] as a `pulp` operation (see [`BlendRowOp`]).
struct BlurColsOp<'a> {
    src: &'a [f32],
    offsets: &'a [usize],
    k: &'a [f32],
    out: &'a mut [f32],
}

impl pulp::WithSimd for BlurColsOp<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        blur_cols_row(self.src, self.offsets, self.k, self.out);
    }
}

/// One output row of the vertical pass: tap `t` reads the row of `src`
/// starting at `offsets[t]`; eight outputs at a time, their sums held in
/// registers across the taps, then the last few one at a time.
#[inline(always)]
fn blur_cols_row(src: &[f32], offsets: &[usize], k: &[f32], out: &mut [f32]) {
    let w = out.len();
    let rows_end = offsets.iter().map(|&o| o + w).max().unwrap_or(0);
    let src = &src[..rows_end];
    let groups = w / 8;
    for (g, o) in out[..groups * 8].chunks_exact_mut(8).enumerate() {
        let x = 8 * g;
        let mut acc = [0.0f32; 8];
        for (&off, &kv) in offsets.iter().zip(k) {
            let s: &[f32; 8] = src[off + x..][..8].try_into().expect("8 values");
            for l in 0..8 {
                acc[l] += kv * s[l];
            }
        }
        o.copy_from_slice(&acc);
    }
    for x in groups * 8..w {
        let mut acc = 0.0f32;
        for (&off, &kv) in offsets.iter().zip(k) {
            acc += kv * src[off + x];
        }
        out[x] = acc;
    }
}

/// Whether every value of `buf` is finite (neither NaN nor infinite).
pub fn all_finite(buf: &[f32]) -> bool {
    buf.par_chunks(4096).all(|c| {
        // Dispatched at run time (see `flow::simd_arch`).
        super::simd_arch().dispatch(FiniteOp { buf: c })
    })
}

/// [`all_finite`] on one chunk as a `pulp` operation (see [`BlendRowOp`]).
struct FiniteOp<'a> {
    buf: &'a [f32],
}

impl pulp::WithSimd for FiniteOp<'_> {
    type Output = bool;
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) -> bool {
        // `0 v` is zero for a finite value and NaN otherwise, and a NaN stays
        // in a sum whatever the order: eight lane sums, no early exit, so the
        // loop vectorises.
        let mut acc = [0.0f32; 8];
        let mut chunks = self.buf.chunks_exact(8);
        for c in &mut chunks {
            for l in 0..8 {
                acc[l] += 0.0 * c[l];
            }
        }
        let tail = chunks.remainder().iter().all(|v| v.is_finite());
        tail && acc.iter().all(|a| *a == 0.0)
    }
}

/// Precomputed bilinear taps for resizing one axis from `src_n` to `dst_n`
/// samples with OpenCV's half-pixel-centre convention
/// (`src = (dst + 0.5) * src_n / dst_n - 0.5`, clamped to the edge).
#[derive(Debug, Clone, Default)]
pub struct ResizeAxis {
    /// Lower source index of each destination sample.
    pub i0: Vec<u32>,
    /// Upper source index (equal to `i0` at the clamped edges).
    pub i1: Vec<u32>,
    /// Weight of `i1` (the weight of `i0` is `1 - w`).
    pub w: Vec<f32>,
}

impl ResizeAxis {
    /// Taps for `src_n -> dst_n`; empty (no taps) if either is zero.
    pub fn new(src_n: usize, dst_n: usize) -> Self {
        if src_n == 0 || dst_n == 0 {
            return ResizeAxis::default();
        }
        let ratio = src_n as f64 / dst_n as f64;
        let mut a = ResizeAxis {
            i0: Vec::with_capacity(dst_n),
            i1: Vec::with_capacity(dst_n),
            w: Vec::with_capacity(dst_n),
        };
        for d in 0..dst_n {
            let s = ((d as f64 + 0.5) * ratio - 0.5).clamp(0.0, (src_n - 1) as f64);
            let f = s.floor();
            let i0 = f as usize;
            let i1 = (i0 + 1).min(src_n - 1);
            a.i0.push(i0 as u32);
            a.i1.push(i1 as u32);
            a.w.push((s - f) as f32);
        }
        a
    }
}

/// Bilinear resize of `src` (`sw` columns) into `dst` (`dw` columns) with
/// precomputed taps, multiplying every value by `gain` (the flow rescaling
/// when moving between pyramid levels). `tmp` (`sw * dh` values) holds the
/// vertical pass: rows are blended first at the source width (contiguous,
/// vectorizable), then each output row gathers from one blended row.
/// Errors if a buffer length or a tap does not fit the sizes.
pub fn resize_bilinear(
    src: &[f32],
    sw: usize,
    xs: &ResizeAxis,
    ys: &ResizeAxis,
    gain: f32,
    tmp: &mut [f32],
    dst: &mut [f32],
) -> Result<()> {
    let dw = xs.w.len();
    let dh = ys.w.len();
    check_len("dst", dst, dw, dh)?;
    check_len("tmp", tmp, sw, dh)?;
    let sh = src.len().checked_div(sw).unwrap_or(0);
    check_len("src", src, sw, sh)?;
    let fits = |a: &ResizeAxis, n: usize| a.i1.iter().chain(&a.i0).all(|&i| (i as usize) < n);
    if !fits(xs, sw) || !fits(ys, sh) {
        return Err(Error::param(
            "taps",
            format!("resize taps reach outside the {sw}x{sh} source"),
        ));
    }
    tmp.par_chunks_mut(sw).enumerate().for_each(|(y, trow)| {
        let r0 = &src[ys.i0[y] as usize * sw..][..sw];
        let r1 = &src[ys.i1[y] as usize * sw..][..sw];
        let wy = ys.w[y];
        super::simd_arch().dispatch(BlendRowOp {
            r0,
            r1,
            wy,
            gain,
            out: trow,
        });
    });
    let tmp = &*tmp;
    let exact = |f: usize| dw == sw * f;
    dst.par_chunks_mut(dw).enumerate().for_each(|(y, drow)| {
        let t = &tmp[y * sw..][..sw];
        // Integer power-of-two ratios (the pyramid's case) use fixed
        // weights instead of per-column taps: the same values bit for bit
        // (the weights are dyadic, exact in f32), without the gathers.
        // Dispatched at run time (see `flow::simd_arch`): same values on every path.
        let arch = super::simd_arch();
        if exact(2) {
            arch.dispatch(UpsampleOp::<2> { t, out: drow });
        } else if exact(4) {
            arch.dispatch(UpsampleOp::<4> { t, out: drow });
        } else if exact(8) {
            arch.dispatch(UpsampleOp::<8> { t, out: drow });
        } else {
            for x in 0..dw {
                let (a, b, wx) = (xs.i0[x] as usize, xs.i1[x] as usize, xs.w[x]);
                drow[x] = t[a] + wx * (t[b] - t[a]);
            }
        }
    });
    Ok(())
}

/// The vertical pass of [`resize_bilinear`] on one row, as a `pulp` operation (a
/// `with_simd` method marked `#[inline(always)]` is compiled inside `pulp`'s AVX2
/// function; a closure's body is not).
struct BlendRowOp<'a> {
    r0: &'a [f32],
    r1: &'a [f32],
    wy: f32,
    gain: f32,
    out: &'a mut [f32],
}

impl pulp::WithSimd for BlendRowOp<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        blend_row(self.r0, self.r1, self.wy, self.gain, self.out);
    }
}

/// `out = gain * (r0 + wy * (r1 - r0))`, elementwise.
#[inline(always)]
fn blend_row(r0: &[f32], r1: &[f32], wy: f32, gain: f32, out: &mut [f32]) {
    let n = out.len();
    let (r0, r1) = (&r0[..n], &r1[..n]);
    for x in 0..n {
        out[x] = gain * (r0[x] + wy * (r1[x] - r0[x]));
    }
}

/// [`upsample_row`] as a `pulp` operation (see [`BlendRowOp`]).
struct UpsampleOp<'a, const F: usize> {
    t: &'a [f32],
    out: &'a mut [f32],
}

impl<const F: usize> pulp::WithSimd for UpsampleOp<'_, F> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        upsample_row::<F>(self.t, self.out);
    }
}

/// One row of an exact `F`x bilinear upsampling with half-pixel centres:
/// output `F k + m` lies at source `k + (m + 0.5) / F - 0.5`, i.e. between
/// `k - 1` and `k` for `m < F/2` and between `k` and `k + 1` otherwise.
///
/// Written per source interval: the `F` outputs from `F k + F/2` to
/// `F k + F + F/2 - 1` all interpolate `t[k]` -> `t[k + 1]` with weights
/// `(j + 0.5) / F`, one broadcast and one `F`-wide multiply-add per interval
/// (vectorises) instead of `F` scalar blends. The weights and the formula
/// `a + c (b - a)` are those of the per-output form (exact for powers of two),
/// so the values are identical; the `F/2` outputs at each end, beyond the first
/// and last centre, are the edge value (border replication).
#[inline(always)]
fn upsample_row<const F: usize>(t: &[f32], out: &mut [f32]) {
    let n = t.len();
    if n == 0 {
        return;
    }
    let half = F / 2;
    let c: [f32; F] = std::array::from_fn(|j| (j as f32 + 0.5) / F as f32);
    let out = &mut out[..F * n];
    let (head, rest) = out.split_at_mut(half);
    head.fill(t[0]);
    let mut chunks = rest.chunks_exact_mut(F);
    for (o, ab) in (&mut chunks).zip(t.windows(2)) {
        let (a, d) = (ab[0], ab[1] - ab[0]);
        for (o, &cj) in o.iter_mut().zip(&c) {
            *o = a + cj * d;
        }
    }
    chunks.into_remainder().fill(t[n - 1]);
}

/// Bilinear sample of `img` (`w x h`) at `(x, y)`, clamping to the edge
/// (border replication). Used where one sample at a time is needed.
/// `img` must hold `w * h > 0` values; otherwise the result is NaN.
#[inline]
pub fn sample_clamped(img: &[f32], w: usize, h: usize, x: f32, y: f32) -> f32 {
    if w == 0 || h == 0 || img.len() < w * h {
        return f32::NAN;
    }
    let xc = x.clamp(0.0, (w - 1) as f32);
    let yc = y.clamp(0.0, (h - 1) as f32);
    // Non-negative after the clamp, so truncation is the floor.
    let (x0, y0) = (xc as usize, yc as usize);
    let (fx, fy) = (xc - x0 as f32, yc - y0 as f32);
    let x1 = (x0 + 1).min(w - 1);
    let y1 = (y0 + 1).min(h - 1);
    let top = img[y0 * w + x0] + fx * (img[y0 * w + x1] - img[y0 * w + x0]);
    let bot = img[y1 * w + x0] + fx * (img[y1 * w + x1] - img[y1 * w + x0]);
    top + fy * (bot - top)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dispatched_resize_rows_match_the_baseline_kernels_bit_for_bit() {
        // The oracle for the runtime SIMD dispatch: the kernels called directly are
        // compiled for the baseline target; through `simd_arch` they run in the
        // detected instruction set (AVX2 on most x86-64), through `Arch::Scalar` on
        // the fallback path.
        let arch = crate::flow::simd_arch();
        let bits = |a: &[f32]| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for n in [1usize, 3, 8, 9, 17, 480] {
            let t: Vec<f32> = (0..n)
                .map(|k| ((k * 37 % 101) as f32) * 2.5 - (k % 7) as f32 * 13.1)
                .collect();
            let r1: Vec<f32> = t.iter().map(|x| 0.3 * x + 1.7).collect();
            let mut want = vec![0.0f32; n];
            blend_row(&t, &r1, 0.3125, -2.0, &mut want);
            for a in [arch, pulp::Arch::Scalar] {
                let mut got = vec![0.0f32; n];
                let (r0, r1, out) = (&t[..], &r1[..], &mut got[..]);
                a.dispatch(BlendRowOp {
                    r0,
                    r1,
                    wy: 0.3125,
                    gain: -2.0,
                    out,
                });
                assert_eq!(bits(&got), bits(&want));
            }
            let mut want = vec![0.0f32; 4 * n];
            upsample_row::<4>(&t, &mut want);
            for a in [arch, pulp::Arch::Scalar] {
                let mut got = vec![0.0f32; 4 * n];
                a.dispatch(UpsampleOp::<4> {
                    t: &t,
                    out: &mut got,
                });
                assert_eq!(bits(&got), bits(&want));
            }
            let mut want = vec![0.0f32; 2 * n];
            upsample_row::<2>(&t, &mut want);
            let mut got = vec![0.0f32; 2 * n];
            arch.dispatch(UpsampleOp::<2> {
                t: &t,
                out: &mut got,
            });
            assert_eq!(bits(&got), bits(&want));
            // The 2x2 box average of rows `t` and `r1` (half as many outputs).
            let want: Vec<f32> = (0..n / 2)
                .map(|x| (t[2 * x] + t[2 * x + 1] + r1[2 * x] + r1[2 * x + 1]) * 0.25)
                .collect();
            for a in [arch, pulp::Arch::Scalar] {
                let mut got = vec![0.0f32; n / 2];
                a.dispatch(Half2Op {
                    r0: &t,
                    r1: &r1,
                    out: &mut got,
                });
                assert_eq!(bits(&got), bits(&want));
            }
        }
    }

    /// The oracle: the plain mean of the `f x f` box of output pixel `(x, y)`.
    fn naive_box(src: &[f32], w: usize, f: usize, x: usize, y: usize) -> f64 {
        let mut s = 0.0f64;
        for yy in 0..f {
            for xx in 0..f {
                s += src[(y * f + yy) * w + x * f + xx] as f64;
            }
        }
        s / (f * f) as f64
    }

    #[test]
    fn area_average_matches_naive_boxes() {
        let (w, h) = (13, 9);
        let src: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 101) as f32).collect();
        for f in 1..=4 {
            let (dw, dh) = (w / f, h / f);
            let mut dst = vec![0.0; dw * dh];
            downsample_area(&src, w, h, f, &mut dst).unwrap();
            for y in 0..dh {
                for x in 0..dw {
                    let want = naive_box(&src, w, f, x, y);
                    assert!((dst[y * dw + x] as f64 - want).abs() < 1e-3, "f={f}");
                }
            }
        }
    }

    #[test]
    fn area_average_of_wide_rows_spans_several_column_chunks() {
        // Wider than the 512-column stack buffer of the factor > 2 path, with a
        // width that is not a multiple of the factor and non-integer pixels.
        let (w, h) = (1203, 9);
        let src: Vec<f32> = (0..w * h)
            .map(|i| ((i * 7919) % 2551) as f32 * 0.1)
            .collect();
        for f in [3usize, 4, 5, 8] {
            let (dw, dh) = (w / f, h / f);
            let mut dst = vec![0.0; dw * dh];
            downsample_area(&src, w, h, f, &mut dst).unwrap();
            for y in 0..dh {
                for x in 0..dw {
                    let want = naive_box(&src, w, f, x, y);
                    let got = dst[y * dw + x] as f64;
                    assert!((got - want).abs() < 1e-4 * want.max(1.0), "f={f} {x},{y}");
                }
            }
        }
    }

    /// The blur as two plain passes, tap by tap over whole rows: the oracle
    /// of the register-blocked passes, which must give the same bits.
    fn blur_two_pass(img: &mut [f32], w: usize, h: usize, k: &[f32]) {
        let rad = (k.len() / 2) as isize;
        let mut tmp = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0f32;
                for (t, &kv) in k.iter().enumerate() {
                    acc += kv * img[y * w + reflect101(x as isize + t as isize - rad, w)];
                }
                tmp[y * w + x] = acc;
            }
        }
        for (y, orow) in img.chunks_mut(w).enumerate() {
            orow.fill(0.0);
            for (t, &kv) in k.iter().enumerate() {
                let yy = reflect101(y as isize + t as isize - rad, h);
                for x in 0..w {
                    orow[x] += kv * tmp[yy * w + x];
                }
            }
        }
    }

    #[test]
    fn blur_matches_the_two_pass_oracle_bit_for_bit() {
        let mut rnd = crate::flow::unit_stream(0x5851_f42d_4c95_7f2du64);
        for &(w, h) in &[
            (1, 1),
            (3, 2),
            (7, 5),
            (11, 9),
            (24, 17),
            (61, 13),
            (200, 40),
        ] {
            for sigma in [0.4f32, 1.5, 2.0, 3.3, 8.0, 11.0] {
                let k = gaussian_kernel(sigma);
                let img: Vec<f32> = (0..w * h)
                    .map(|_| 255.0 * rnd() * if rnd() < 0.1 { 1e3 } else { 1.0 })
                    .collect();
                let mut want = img.clone();
                blur_two_pass(&mut want, w, h, &k);
                let mut tmp = vec![0.0; w * h];
                let mut got = img.clone();
                gaussian_blur(&mut got, w, h, &k, &mut tmp).unwrap();
                let mut into = vec![0.0; w * h];
                gaussian_blur_into(&img, w, h, &k, &mut tmp, &mut into).unwrap();
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got), bits(&want), "{w}x{h}, sigma {sigma}");
                assert_eq!(bits(&into), bits(&want), "{w}x{h}, sigma {sigma}");
            }
        }
    }

    #[test]
    fn all_finite_finds_any_nan_or_infinity() {
        for n in [0usize, 1, 7, 8, 9, 4095, 4096, 4097, 10_000] {
            let mut v = vec![1.5f32; n];
            assert!(all_finite(&v));
            for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
                for at in [0, n / 2, n.saturating_sub(1)] {
                    if n == 0 {
                        continue;
                    }
                    v[at] = bad;
                    assert!(!all_finite(&v), "{n} {at} {bad}");
                    v[at] = 1.5;
                }
            }
        }
    }

    #[test]
    fn blur_matches_naive_convolution_and_keeps_constants() {
        let (w, h) = (11, 9);
        let img: Vec<f32> = (0..w * h).map(|i| ((i * 29) % 53) as f32).collect();
        let mut out = img.clone();
        let mut tmp = vec![0.0; w * h];
        let sigma = 0.8f32;
        gaussian_blur(&mut out, w, h, &gaussian_kernel(sigma), &mut tmp).unwrap();
        let rad = 3i64;
        let kern = |i: i64| (-(i * i) as f64 / (2.0 * (sigma as f64).powi(2))).exp();
        let ksum: f64 = (-rad..=rad).map(kern).sum();
        let refl = |i: i64, n: i64| {
            if i < 0 {
                -i
            } else if i >= n {
                2 * n - 2 - i
            } else {
                i
            }
        };
        for y in 0..h as i64 {
            for x in 0..w as i64 {
                let mut s = 0.0f64;
                for dy in -rad..=rad {
                    for dx in -rad..=rad {
                        let (yy, xx) = (refl(y + dy, h as i64), refl(x + dx, w as i64));
                        s += kern(dx) * kern(dy) * img[(yy * w as i64 + xx) as usize] as f64;
                    }
                }
                let want = s / (ksum * ksum);
                assert!((out[(y * w as i64 + x) as usize] as f64 - want).abs() < 1e-3);
            }
        }
        let mut c = vec![7.0f32; w * h];
        gaussian_blur(&mut c, w, h, &gaussian_kernel(1.5), &mut tmp).unwrap();
        assert!(c.iter().all(|v| (v - 7.0).abs() < 1e-4));
    }

    #[test]
    fn wrong_buffers_are_errors_not_panics() {
        let img = vec![1.0f32; 12];
        let mut small = vec![0.0f32; 5];
        let mut ok = vec![0.0f32; 12];
        assert!(downsample_area(&img, 4, 3, 0, &mut small).is_err());
        assert!(downsample_area(&img, 4, 3, 2, &mut small).is_err());
        assert!(sobel(&img, 4, 3, 1.0, &mut small, &mut ok.clone()).is_err());
        let k = gaussian_kernel(1.0);
        assert!(gaussian_blur(&mut ok, 4, 3, &k, &mut small).is_err());
        assert!(gaussian_blur(&mut ok, 4, 3, &[0.5, 0.5], &mut [0.0; 12]).is_err());
        let (xs, ys) = (ResizeAxis::new(4, 8), ResizeAxis::new(3, 6));
        assert!(resize_bilinear(&img, 4, &xs, &ys, 1.0, &mut small, &mut ok).is_err());
        let (bx, by) = (ResizeAxis::new(9, 8), ResizeAxis::new(3, 6));
        let (mut t, mut d) = (vec![0.0; 4 * 6], vec![0.0; 48]);
        assert!(resize_bilinear(&img, 4, &bx, &by, 1.0, &mut t, &mut d).is_err());
        assert!(sample_clamped(&[], 0, 0, 0.5, 0.5).is_nan());
        assert!(ResizeAxis::new(0, 5).w.is_empty());
    }

    #[test]
    fn sobel_of_a_ramp() {
        let (w, h) = (7, 5);
        let img: Vec<f32> = (0..w * h).map(|i| (i % w) as f32 * 2.0).collect();
        let (mut gx, mut gy) = (vec![0.0; w * h], vec![0.0; w * h]);
        sobel(&img, w, h, 0.125, &mut gx, &mut gy).unwrap();
        for y in 0..h {
            for x in 1..w - 1 {
                assert!((gx[y * w + x] - 2.0).abs() < 1e-6);
                assert!(gy[y * w + x].abs() < 1e-6);
            }
            // Reflect-101 makes the edge derivative zero.
            assert_eq!(gx[y * w], 0.0);
        }
        sobel(&img, w, h, 1.0, &mut gx, &mut gy).unwrap();
        assert!((gx[2 * w + 3] - 16.0).abs() < 1e-5);
    }

    #[test]
    fn exact_upsampling_matches_the_general_taps() {
        let (sw, sh) = (9, 5);
        let src: Vec<f32> = (0..sw * sh)
            .map(|i| ((i * 7919) % 97) as f32 * 0.37)
            .collect();
        for f in [2usize, 4, 8] {
            let (dw, dh) = (sw * f, sh * f);
            let (xs, ys) = (ResizeAxis::new(sw, dw), ResizeAxis::new(sh, dh));
            let mut tmp = vec![0.0; sw * dh];
            let mut fast = vec![0.0; dw * dh];
            resize_bilinear(&src, sw, &xs, &ys, 1.5, &mut tmp, &mut fast).unwrap();
            for y in 0..dh {
                for x in 0..dw {
                    let t = &tmp[y * sw..];
                    let (a, b, w) = (xs.i0[x] as usize, xs.i1[x] as usize, xs.w[x]);
                    let want = t[a] + w * (t[b] - t[a]);
                    assert_eq!(fast[y * dw + x].to_bits(), want.to_bits(), "f={f} x={x}");
                }
            }
        }
    }

    #[test]
    fn exact_factor_upsampling_matches_the_generic_taps() {
        // The specialised x2/x4/x8 rows against the per-output tap formula.
        for (sw, sh) in [(1usize, 2usize), (2, 1), (7, 3), (33, 5)] {
            let src: Vec<f32> = (0..sw * sh)
                .map(|i| ((i * 7919) % 257) as f32 * 0.37 - 40.0)
                .collect();
            for f in [2usize, 4, 8] {
                let (dw, dh) = (sw * f, sh * f);
                let (xs, ys) = (ResizeAxis::new(sw, dw), ResizeAxis::new(sh, dh));
                let mut tmp = vec![0.0; sw * dh];
                let mut dst = vec![0.0; dw * dh];
                resize_bilinear(&src, sw, &xs, &ys, 2.0, &mut tmp, &mut dst).unwrap();
                for y in 0..dh {
                    let (r0, r1, wy) = (ys.i0[y] as usize, ys.i1[y] as usize, ys.w[y]);
                    let col = |x: usize| {
                        let (a, b) = (src[r0 * sw + x], src[r1 * sw + x]);
                        2.0 * (a + wy * (b - a))
                    };
                    for x in 0..dw {
                        let (a, b, wx) = (xs.i0[x] as usize, xs.i1[x] as usize, xs.w[x]);
                        let want = col(a) + wx * (col(b) - col(a));
                        let got = dst[y * dw + x];
                        assert!((got - want).abs() < 1e-4, "{sw}x{sh} f={f} {x},{y}");
                    }
                }
            }
        }
    }

    #[test]
    fn resize_reproduces_linear_functions_inside() {
        let (sw, sh) = (10, 6);
        let src: Vec<f32> = (0..sw * sh)
            .map(|i| (i % sw) as f32 + 3.0 * (i / sw) as f32)
            .collect();
        let (dw, dh) = (20, 12);
        let xs = ResizeAxis::new(sw, dw);
        let ys = ResizeAxis::new(sh, dh);
        let mut dst = vec![0.0; dw * dh];
        let mut tmp = vec![0.0; sw * dh];
        resize_bilinear(&src, sw, &xs, &ys, 2.0, &mut tmp, &mut dst).unwrap();
        for y in 1..dh - 1 {
            for x in 1..dw - 1 {
                let sx = (x as f32 + 0.5) / 2.0 - 0.5;
                let sy = (y as f32 + 0.5) / 2.0 - 0.5;
                let want = 2.0 * (sx + 3.0 * sy);
                assert!((dst[y * dw + x] - want).abs() < 1e-4);
                let s = sample_clamped(&src, sw, sh, sx, sy);
                assert!((2.0 * s - want).abs() < 1e-4);
            }
        }
    }
}
