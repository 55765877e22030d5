//! Direct `O(N^2)` sum: the test oracle.
//!
//! Evaluates `D(m) = dx dy sum_i div(i) G(m - i)` and the same for `R` cell by
//! cell, exactly as the definition reads. **Slow**: `N^2` terms for `N` grid
//! cells (about 0.3 s at 64x64, minutes at 256x256). It exists to check
//! [`NaturalHhd`](super::NaturalHhd), not for use in the pipeline.

use ndarray::{Array2, ArrayView2};

use super::{Decomposition, HhdScalar, fft};
use crate::error::{Error, Result};

/// The potentials `(D, R)` of the divergence `div` and curl `curl` by direct
/// summation over every pair of cells. **Slow** (`O(N^2)`).
///
/// Errors on mismatched shapes, an empty grid or a bad spacing.
pub fn potentials(
    div: ArrayView2<'_, f64>,
    curl: ArrayView2<'_, f64>,
    dx: f64,
    dy: f64,
) -> Result<(Array2<f64>, Array2<f64>)> {
    let (ny, nx) = div.dim();
    if curl.dim() != (ny, nx) {
        return Err(Error::shape(
            "curl (against divergence)",
            (nx, ny),
            (curl.ncols(), curl.nrows()),
        ));
    }
    fft::check_grid(ny, nx, dx, dy)?;
    // G only depends on |offset|: tabulate it once.
    let g = Array2::from_shape_fn((ny, nx), |(oy, ox)| fft::green(oy, ox, dx, dy));
    let mut d = Array2::zeros((ny, nx));
    let mut r = Array2::zeros((ny, nx));
    for my in 0..ny {
        for mx in 0..nx {
            let (mut sd, mut sr) = (0.0, 0.0);
            for iy in 0..ny {
                for ix in 0..nx {
                    let w = g[[my.abs_diff(iy), mx.abs_diff(ix)]];
                    sd += div[[iy, ix]] * w;
                    sr += curl[[iy, ix]] * w;
                }
            }
            d[[my, mx]] = dx * dy * sd;
            r[[my, mx]] = dx * dy * sr;
        }
    }
    Ok((d, r))
}

/// The whole natural HHD with the potentials from [`potentials`]: same
/// stencils, same errors as [`NaturalHhd::decompose`](super::NaturalHhd::decompose).
/// **Slow** (`O(N^2)`).
pub fn decompose<T: HhdScalar>(
    u: ArrayView2<'_, T>,
    v: ArrayView2<'_, T>,
    dx: f64,
    dy: f64,
) -> Result<Decomposition> {
    let mut out = Decomposition::zeros(u.nrows(), u.ncols());
    super::load_input(u, v, dx, dy, &mut out)?;
    let (d, r) = potentials(out.div.view(), out.curl.view(), dx, dy)?;
    out.potential_d = d;
    out.potential_r = r;
    super::finish(&mut out)?;
    Ok(out)
}
