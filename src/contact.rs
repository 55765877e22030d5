//! Contacts: the raw quantities of a contact patch (SPEC.md step 7) and the
//! calibrated contact a user acts on.

use ndarray::ArrayView2;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::geometry::SensorGeometry;
use crate::image::Roi;
use crate::io::ContactRecord;

/// The raw, uncalibrated quantities of one contact patch (SPEC.md step 7), all
/// in the pixels of the cropped full-resolution image.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct RawContact {
    /// Contact point column: argmin of the divergence potential D.
    pub x_px: f64,
    /// Contact point row.
    pub y_px: f64,
    /// Shear raw displacement along image x: sum of the patch's flow u.
    pub ds1: f64,
    /// Shear raw displacement along image y: sum of the patch's flow v.
    pub ds2: f64,
    /// Normal raw displacement: sum of |d| (the curl-free part) over the patch.
    pub dn: f64,
    /// Spread of the divergence potential, `max D - min D`.
    pub d_pf: f64,
    /// Raw displacements rotated into the sensor frame `(Dx, Dy, Dz)`.
    pub d_sensor: [f64; 3],
    /// Number of pixels of the patch's mask (full-resolution pixels).
    pub area_px: u64,
    /// The patch's bounding box (full-resolution pixels of the cropped image).
    pub bbox: Roi,
    /// Summed flow magnitude of the patch: the detection strength.
    pub strength: f64,
}

impl RawContact {
    /// The local shear-to-normal ratio `ds1 / dn` (0 when `dn` is 0): how much
    /// of the load runs along the arc. It tells how far the contact point
    /// estimate is pulled sideways, so the location map takes it as an input.
    pub fn shear_ratio(&self) -> f64 {
        if self.dn > 0.0 && self.ds1.is_finite() {
            self.ds1 / self.dn
        } else {
            0.0
        }
    }
}

/// One contact: where (mm) and how hard (N), in the sensor frame.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Contact {
    /// Identity, stable from frame to frame while the contact lasts (0 until tracked).
    pub id: u64,
    /// Location `(x, y, z)` in mm, sensor frame.
    pub location_mm: [f64; 3],
    /// Force `(Fx, Fy, Fz)` in N, sensor frame (a press has `Fz < 0`).
    pub force_n: [f64; 3],
    /// The raw quantities it was computed from.
    pub raw: RawContact,
    /// Frames in a row this contact has been held without a detection (hysteresis).
    pub missed: u32,
}

impl Contact {
    /// Magnitude of the force, N.
    pub fn force_magnitude(&self) -> f64 {
        let [x, y, z] = self.force_n;
        (x * x + y * y + z * z).sqrt()
    }

    /// The JSON Lines record of DATASET.md.
    pub fn to_record(&self) -> ContactRecord {
        let r = &self.raw;
        ContactRecord {
            id: Some(self.id),
            x_mm: self.location_mm[0],
            y_mm: self.location_mm[1],
            z_mm: self.location_mm[2],
            fx_n: self.force_n[0],
            fy_n: self.force_n[1],
            fz_n: self.force_n[2],
            x_px: Some(r.x_px),
            y_px: Some(r.y_px),
            d_pf: Some(r.d_pf),
            dx: Some(r.d_sensor[0]),
            dy: Some(r.d_sensor[1]),
            dz: Some(r.d_sensor[2]),
            area_px: Some(r.area_px),
        }
    }
}

/// Where a patch sits and how its grid relates to the full-resolution image.
///
/// The flow may be computed on a coarser grid than the image (DIS estimates it
/// at a pyramid level, 1/4 resolution for the `fast` preset): grid cell `(i, j)`
/// of the patch covers full-resolution pixels around
/// `((x0 + j + 0.5) * scale - 0.5, (y0 + i + 0.5) * scale - 0.5)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PatchGrid {
    /// Column of the patch's first cell in the (level) grid.
    pub x0: usize,
    /// Row of the patch's first cell in the (level) grid.
    pub y0: usize,
    /// Full-resolution pixels per grid cell (1 at full resolution, 4 at level 2).
    pub scale: f64,
}

/// The decomposition fields [`raw_quantities`] needs, for one patch.
#[derive(Debug, Clone, Copy)]
pub struct PatchFields<'a> {
    /// Flow along x in full-resolution pixels, shape `(h, w)`.
    pub u: ArrayView2<'a, f32>,
    /// Flow along y in full-resolution pixels.
    pub v: ArrayView2<'a, f32>,
    /// Divergence potential `D`, computed with grid spacing `scale`.
    pub potential_d: ArrayView2<'a, f64>,
    /// Curl-free part `d = grad D`, x component.
    pub d_u: ArrayView2<'a, f64>,
    /// Curl-free part, y component.
    pub d_v: ArrayView2<'a, f64>,
}

/// Sub-pixel offset of a minimum from three samples `a, b, c` at -1, 0, +1
/// (vertex of the parabola through them, within +-0.5).
fn parabola_offset(a: f64, b: f64, c: f64) -> f64 {
    let den = a - 2.0 * b + c;
    if den > 0.0 && den.is_finite() {
        (0.5 * (a - c) / den).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// The raw quantities of one patch (SPEC.md step 7), in full-resolution units.
///
/// - contact point: argmin of `D` (first in row-major order on ties),
///   optionally refined to sub-pixel precision by a parabola through the
///   neighbours along each axis (interior minima only);
/// - `ds1, ds2`: sums of `u` and `v`, times `scale^2` so that they equal the sums
///   over the patch at full resolution;
/// - `dn`: sum of `|d|`, times `scale^2`;
/// - `d_pf`: `max D - min D` (already in full-resolution units when the
///   decomposition used spacing `scale`).
///
/// `area_px`, `bbox` and `strength` are left for the caller (the segmentation
/// knows them). Errors on mismatched shapes or an empty patch.
pub fn raw_quantities(f: &PatchFields<'_>, grid: PatchGrid, subpixel: bool) -> Result<RawContact> {
    let shape = f.u.dim();
    for (what, dim) in [
        ("v", f.v.dim()),
        ("D", f.potential_d.dim()),
        ("d.u", f.d_u.dim()),
        ("d.v", f.d_v.dim()),
    ] {
        if dim != shape {
            return Err(Error::shape(
                format!("patch field {what} against u"),
                (shape.1, shape.0),
                (dim.1, dim.0),
            ));
        }
    }
    let (h, w) = shape;
    if h == 0 || w == 0 {
        return Err(Error::TooSmall {
            what: "contact patch".into(),
            width: w,
            height: h,
            min_w: 1,
            min_h: 1,
        });
    }
    let d = &f.potential_d;
    let (mut best, mut lo, mut hi) = ((0, 0), f64::INFINITY, f64::NEG_INFINITY);
    for ((i, j), &x) in d.indexed_iter() {
        if x < lo {
            lo = x;
            best = (i, j);
        }
        hi = hi.max(x);
    }
    if !(lo.is_finite() && hi.is_finite()) {
        return Err(Error::NonFinite {
            what: "divergence potential".into(),
            row: best.0,
            col: best.1,
        });
    }
    let (i, j) = best;
    let (mut oi, mut oj) = (0.0, 0.0);
    if subpixel {
        if i > 0 && i + 1 < h {
            oi = parabola_offset(d[[i - 1, j]], d[[i, j]], d[[i + 1, j]]);
        }
        if j > 0 && j + 1 < w {
            oj = parabola_offset(d[[i, j - 1]], d[[i, j]], d[[i, j + 1]]);
        }
    }
    let s = grid.scale;
    let area = s * s;
    let sum = |a: &ArrayView2<'_, f32>| a.iter().map(|&x| x as f64).sum::<f64>() * area;
    let dn = f
        .d_u
        .iter()
        .zip(f.d_v.iter())
        .map(|(a, b)| a.hypot(*b))
        .sum::<f64>()
        * area;
    Ok(RawContact {
        x_px: (grid.x0 as f64 + j as f64 + oj + 0.5) * s - 0.5,
        y_px: (grid.y0 as f64 + i as f64 + oi + 0.5) * s - 0.5,
        ds1: sum(&f.u),
        ds2: sum(&f.v),
        dn,
        d_pf: hi - lo,
        ..Default::default()
    })
}

/// Column sums of a flow component over all rows: the profile along the
/// arc that the centroid of [`refine_contact_points`] works on.
fn column_sums(u: ArrayView2<'_, f32>) -> Vec<f64> {
    let mut out = vec![0.0f64; u.ncols()];
    for row in u.rows() {
        for (o, &x) in out.iter_mut().zip(row.iter()) {
            *o += x as f64;
        }
    }
    out
}

/// Mean-shift centroid of `w` (non-negative weights per grid column) with a
/// hard window of half-width `half` columns, restricted to `[lo, hi)`,
/// starting from the centroid of the whole range. `None` if the weights in
/// the range are all zero.
fn windowed_centroid(w: &[f64], lo: usize, hi: usize, half: f64) -> Option<f64> {
    let centroid = |a: f64, b: f64| {
        let (mut s, mut sx) = (0.0, 0.0);
        for (j, &x) in w.iter().enumerate().take(hi).skip(lo) {
            let jf = j as f64;
            if jf > a && jf < b {
                s += x;
                sx += x * jf;
            }
        }
        (s > 0.0).then(|| sx / s)
    };
    let mut c = centroid(f64::NEG_INFINITY, f64::INFINITY)?;
    // A mean shift with a flat kernel converges in a few steps; a fixed cap
    // keeps the cost bounded when it oscillates between two nearby modes.
    // The window stays symmetric about the estimate: where the region ends
    // (an image edge, or halfway to a neighbouring contact) it shrinks on
    // both sides, since cutting one side only would pull the centroid of a
    // symmetric profile away from the cut.
    let (first, last) = (lo as f64 - 0.5, hi as f64 - 0.5);
    for _ in 0..50 {
        let h = half.min(c - first).min(last - c).max(1.0);
        let next = match centroid(c - h, c + h) {
            Some(n) => n,
            None => break,
        };
        let done = (next - c).abs() < 1e-6;
        c = next;
        if done {
            break;
        }
    }
    Some(c)
}

/// Replaces each contact's column `x_px` by a shear-robust estimate: the
/// centroid of the squared column-summed flow `u` (motion along the arc)
/// within a window of half-width `half_window_px` full-resolution pixels.
///
/// Why: under a line load, the surface motion along the arc is odd about the
/// load point for the normal component and even for the tangential one, so
/// the divergence potential (the integral of the motion) is even plus odd and
/// its minimum slides sideways as soon as the load has any shear (tens of
/// pixels at 15 deg). The energy of the motion, `u^2`, is even about the load
/// point under either load alone, and its centroid moves far less; what
/// remains is corrected by the calibration's `shear` input (see
/// [`RawContact::shear_ratio`]). Column sums over the whole strip height
/// average the noise, and the window keeps a distant contact (or noise far
/// away) out of the centroid.
///
/// `u` is the flow along x on a grid of `scale` full-resolution pixels per
/// cell (cell `j` covers pixel `(j + 0.5) * scale - 0.5`). With several
/// contacts, each one's search range ends halfway to its neighbours' current
/// `x_px`, so that one press does not pull another's centroid. A contact whose
/// range holds no motion keeps its `x_px`. Errors on a non-positive or
/// non-finite window or scale.
pub fn refine_contact_points(
    raws: &mut [RawContact],
    u: ArrayView2<'_, f32>,
    scale: f64,
    half_window_px: f64,
) -> Result<()> {
    if !(scale > 0.0 && scale.is_finite()) {
        return Err(Error::param("scale", format!("must be > 0, got {scale}")));
    }
    if !(half_window_px > 0.0 && half_window_px.is_finite()) {
        return Err(Error::param(
            "half_window_px",
            format!("must be > 0, got {half_window_px}"),
        ));
    }
    if raws.is_empty() || u.ncols() == 0 {
        return Ok(());
    }
    let w: Vec<f64> = column_sums(u).into_iter().map(|x| x * x).collect();
    let to_grid = |px: f64| (px + 0.5) / scale - 0.5;
    let starts: Vec<f64> = raws.iter().map(|r| to_grid(r.x_px)).collect();
    let n = w.len();
    for (k, raw) in raws.iter_mut().enumerate() {
        let me = starts[k];
        let (mut a, mut b) = (f64::NEG_INFINITY, f64::INFINITY);
        for (m, &o) in starts.iter().enumerate() {
            if m == k {
                continue;
            }
            let mid = 0.5 * (me + o);
            if o < me || (o == me && m < k) {
                a = a.max(mid);
            } else {
                b = b.min(mid);
            }
        }
        let lo = if a.is_finite() {
            (a.floor().max(-1.0) + 1.0) as usize
        } else {
            0
        };
        let hi = if b.is_finite() {
            (b.ceil().max(0.0) as usize).min(n)
        } else {
            n
        };
        if lo >= hi {
            continue;
        }
        if let Some(c) = windowed_centroid(&w, lo, hi, half_window_px / scale) {
            raw.x_px = (c + 0.5) * scale - 0.5;
        }
    }
    Ok(())
}

/// Rotates a patch's raw displacements from the local surface frame at chord
/// position `x_mm` into the sensor frame (SPEC.md step 9).
///
/// Locally, `ds1` runs along the tangent (image x follows the arc), `ds2`
/// across (image y follows the width) and the normal component is `-dn`: the
/// markers are pushed into the skin by a press, so `Dz < 0` for a press at
/// the centre, like `Fz`.
pub fn rotate_to_sensor(geometry: &SensorGeometry, x_mm: f64, raw: &RawContact) -> [f64; 3] {
    geometry.local_to_sensor(x_mm, [raw.ds1, raw.ds2, -raw.dn])
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn parabola_vertex_is_exact_for_a_parabola() {
        // f(x) = (x - 0.3)^2 sampled at -1, 0, 1.
        let f = |x: f64| (x - 0.3) * (x - 0.3);
        assert!((parabola_offset(f(-1.0), f(0.0), f(1.0)) - 0.3).abs() < 1e-12);
        assert_eq!(parabola_offset(1.0, 1.0, 1.0), 0.0);
    }

    #[test]
    fn quantities_of_a_radial_bowl() {
        // D = (x - 5.3)^2 + (y - 3)^2 on a 7x11 grid at scale 4, d = grad D.
        let (h, w) = (7, 11);
        let dfun = |y: f64, x: f64| (x - 5.3).powi(2) + (y - 3.0).powi(2);
        let pd = Array2::from_shape_fn((h, w), |(i, j)| dfun(i as f64, j as f64));
        let du = Array2::from_shape_fn((h, w), |(_, j)| 2.0 * (j as f64 - 5.3));
        let dv = Array2::from_shape_fn((h, w), |(i, _)| 2.0 * (i as f64 - 3.0));
        let u = Array2::from_elem((h, w), 0.5f32);
        let v = Array2::from_elem((h, w), -0.25f32);
        let f = PatchFields {
            u: u.view(),
            v: v.view(),
            potential_d: pd.view(),
            d_u: du.view(),
            d_v: dv.view(),
        };
        let grid = PatchGrid {
            x0: 10,
            y0: 2,
            scale: 4.0,
        };
        let r = raw_quantities(&f, grid, true).unwrap();
        assert!(
            (r.x_px - ((10.0 + 5.3 + 0.5) * 4.0 - 0.5)).abs() < 1e-9,
            "{}",
            r.x_px
        );
        assert!((r.y_px - ((2.0 + 3.0 + 0.5) * 4.0 - 0.5)).abs() < 1e-9);
        let coarse = raw_quantities(&f, grid, false).unwrap();
        assert_eq!(coarse.x_px, (10.0 + 5.0 + 0.5) * 4.0 - 0.5);
        assert!((r.ds1 - 0.5 * 77.0 * 16.0).abs() < 1e-9);
        assert!((r.ds2 + 0.25 * 77.0 * 16.0).abs() < 1e-9);
        let max_d = pd.iter().cloned().fold(f64::MIN, f64::max);
        assert!((r.d_pf - (max_d - dfun(3.0, 5.0))).abs() < 1e-12);
        assert!(r.dn > 0.0);
    }

    #[test]
    fn mismatched_or_bad_fields_are_errors() {
        let a = Array2::<f32>::zeros((3, 3));
        let b = Array2::<f64>::zeros((3, 3));
        let c = Array2::<f64>::zeros((3, 4));
        let grid = PatchGrid {
            x0: 0,
            y0: 0,
            scale: 1.0,
        };
        let f = PatchFields {
            u: a.view(),
            v: a.view(),
            potential_d: c.view(),
            d_u: b.view(),
            d_v: b.view(),
        };
        assert!(raw_quantities(&f, grid, true).is_err());
        let mut n = b.clone();
        n[[1, 1]] = f64::NAN;
        n[[0, 0]] = -1.0;
        n[[2, 2]] = f64::INFINITY;
        let f = PatchFields {
            u: a.view(),
            v: a.view(),
            potential_d: n.view(),
            d_u: b.view(),
            d_v: b.view(),
        };
        assert!(matches!(
            raw_quantities(&f, grid, true),
            Err(Error::NonFinite { .. })
        ));
    }

    /// A `(h, w)` flow along x whose every row is `f(column)`.
    fn rows_of(h: usize, w: usize, f: impl Fn(f64) -> f64) -> Array2<f32> {
        Array2::from_shape_fn((h, w), |(_, j)| f(j as f64) as f32)
    }

    fn raw_at(x_px: f64) -> RawContact {
        RawContact {
            x_px,
            ..Default::default()
        }
    }

    /// The slow, obvious version: full-range centroid of the squared column
    /// sums, then a flat-window mean shift until it stops moving.
    fn oracle(u: &Array2<f32>, half: f64) -> f64 {
        let w: Vec<f64> = (0..u.ncols())
            .map(|j| {
                let s: f64 = (0..u.nrows()).map(|i| u[[i, j]] as f64).sum();
                s * s
            })
            .collect();
        let cen = |a: f64, b: f64| {
            let (mut s, mut sx) = (0.0, 0.0);
            for (j, &x) in w.iter().enumerate() {
                if (j as f64) > a && (j as f64) < b {
                    s += x;
                    sx += x * j as f64;
                }
            }
            sx / s
        };
        let mut c = cen(-1e300, 1e300);
        let last = w.len() as f64 - 0.5;
        for _ in 0..50 {
            // Symmetric about the estimate: shrunk where the image ends.
            let h = half.min(c + 0.5).min(last - c).max(1.0);
            let n = cen(c - h, c + h);
            if (n - c).abs() < 1e-6 {
                return n;
            }
            c = n;
        }
        c
    }

    #[test]
    fn a_neighbour_does_not_pull_a_symmetric_profile() {
        // A wide profile at column 40 and a narrow neighbour at 60: the first
        // contact's range is cut halfway, at 50, and its window (30) would
        // reach past that cut on one side only. A one-sided cut put it at
        // 39.42; the symmetric window keeps it at 40.
        let u = Array2::from_shape_fn((1, 100), |(_, j)| {
            let j = j as f32;
            (-(j - 40.0).powi(2) / 128.0).exp() + (-(j - 60.0).powi(2) / 8.0).exp()
        });
        let mut r = [raw_at(41.0), raw_at(59.0)];
        refine_contact_points(&mut r, u.view(), 1.0, 30.0).unwrap();
        assert!((r[0].x_px - 40.0).abs() < 0.05, "{}", r[0].x_px);
        // (The narrow one still feels the wide one's tail inside its own
        // window: leakage, not truncation.)
    }

    #[test]
    fn tangential_and_normal_profiles_give_the_load_point() {
        // Shear: an even bump; press: an odd profile; both about column 61.3.
        let c = 61.3;
        let even = rows_of(7, 160, |j| (-((j - c) / 9.0).powi(2)).exp());
        let odd = rows_of(7, 160, |j| (j - c) / 9.0 * (-((j - c) / 9.0).powi(2)).exp());
        for (name, u) in [("even", &even), ("odd", &odd)] {
            let mut r = [raw_at(70.0)];
            refine_contact_points(&mut r, u.view(), 1.0, 60.0).unwrap();
            assert!((r[0].x_px - c).abs() < 1e-3, "{name}: {}", r[0].x_px);
        }
        // On a grid of 2 pixels per cell, cell 61.3 is pixel (61.3 + 0.5) * 2 - 0.5.
        let mut r = [raw_at(100.0)];
        refine_contact_points(&mut r, even.view(), 2.0, 120.0).unwrap();
        assert!((r[0].x_px - 123.1).abs() < 2e-3, "{}", r[0].x_px);
    }

    #[test]
    fn two_contacts_keep_to_their_own_halves() {
        let g = |j: f64, c: f64| (-((j - c) / 6.0).powi(2)).exp();
        let u = rows_of(4, 300, |j| g(j, 80.0) + 0.5 * g(j, 200.0));
        let mut r = [raw_at(90.0), raw_at(195.0)];
        refine_contact_points(&mut r, u.view(), 1.0, 400.0).unwrap();
        assert!((r[0].x_px - 80.0).abs() < 1e-3, "{}", r[0].x_px);
        assert!((r[1].x_px - 200.0).abs() < 1e-3, "{}", r[1].x_px);
    }

    #[test]
    fn no_motion_keeps_the_contact_point_and_bad_parameters_are_errors() {
        let u = Array2::<f32>::zeros((3, 50));
        let mut r = [raw_at(12.5)];
        refine_contact_points(&mut r, u.view(), 1.0, 10.0).unwrap();
        assert_eq!(r[0].x_px, 12.5);
        for (s, w) in [
            (0.0, 10.0),
            (1.0, 0.0),
            (f64::NAN, 1.0),
            (1.0, f64::INFINITY),
        ] {
            assert!(matches!(
                refine_contact_points(&mut r, u.view(), s, w),
                Err(Error::InvalidParameter { .. })
            ));
        }
        // Nothing to refine: fine.
        refine_contact_points(&mut [], u.view(), 1.0, 10.0).unwrap();
    }

    #[test]
    fn shear_ratio_guards_a_zero_normal() {
        let r = RawContact {
            ds1: 3.0,
            dn: 6.0,
            ..Default::default()
        };
        assert_eq!(r.shear_ratio(), 0.5);
        assert_eq!(RawContact::default().shear_ratio(), 0.0);
    }

    proptest::proptest! {
        #![proptest_config(proptest::test_runner::Config {
            cases: 48,
            rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
            rng_seed: proptest::test_runner::RngSeed::Fixed(7),
            failure_persistence: None,
            ..Default::default()
        })]
        #[test]
        fn matches_the_oracle(
            vals in proptest::collection::vec(-3.0f32..3.0, 3 * 40),
            half in 2.0f64..50.0,
        ) {
            let u = Array2::from_shape_vec((3, 40), vals).unwrap();
            let mut r = [raw_at(5.0)];
            refine_contact_points(&mut r, u.view(), 1.0, half).unwrap();
            let want = oracle(&u, half);
            proptest::prop_assert!((r[0].x_px - want).abs() < 1e-6, "{} vs {}", r[0].x_px, want);
        }
    }

    #[test]
    fn a_central_press_points_down() {
        let g = SensorGeometry::default();
        let raw = RawContact {
            ds1: 0.0,
            ds2: 0.0,
            dn: 100.0,
            ..Default::default()
        };
        let d = rotate_to_sensor(&g, 0.0, &raw);
        assert_eq!(d, [0.0, 0.0, -100.0]);
        // Off centre the outward normal tilts toward +x for x > 0, so a push into the skin has -x.
        let d = rotate_to_sensor(&g, 100.0, &raw);
        assert!(d[0] < 0.0 && d[2] < 0.0);
    }
}
