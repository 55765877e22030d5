//! Properties of the natural HHD on analytic and random fields, the FFT path
//! against the direct-sum oracle, and bad input.

use super::{Decomposition, DivergentPart, NaturalHhd, direct, gradient};
use crate::Error;
use ndarray::{Array2, ArrayView2, s};
use proptest::prelude::*;
use proptest::test_runner::RngSeed;

fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        rng_seed: RngSeed::Fixed(0x4848_4400),
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

fn max_abs(a: &Array2<f64>) -> f64 {
    a.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

fn max_diff(a: &Array2<f64>, b: &Array2<f64>) -> f64 {
    assert_eq!(a.dim(), b.dim());
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
}

/// Largest difference between two decompositions, each part relative to the
/// magnitude of its kind (potentials together, vector parts against the
/// input field, div and curl together), as in the reference test.
fn dec_rel_diff(a: &Decomposition, b: &Decomposition, field_scale: f64) -> f64 {
    let pot = max_abs(&b.potential_d)
        .max(max_abs(&b.potential_r))
        .max(f64::MIN_POSITIVE);
    let der = max_abs(&b.div).max(max_abs(&b.curl)).max(f64::MIN_POSITIVE);
    let f = field_scale.max(f64::MIN_POSITIVE);
    [
        max_diff(&a.div, &b.div) / der,
        max_diff(&a.curl, &b.curl) / der,
        max_diff(&a.potential_d, &b.potential_d) / pot,
        max_diff(&a.potential_r, &b.potential_r) / pot,
        max_diff(&a.d.u, &b.d.u) / f,
        max_diff(&a.d.v, &b.d.v) / f,
        max_diff(&a.r.u, &b.r.u) / f,
        max_diff(&a.r.v, &b.r.v) / f,
        max_diff(&a.h.u, &b.h.u) / f,
        max_diff(&a.h.v, &b.h.v) / f,
    ]
    .into_iter()
    .fold(0.0, f64::max)
}

fn field_scale<T: Copy + Into<f64>>(u: ArrayView2<'_, T>, v: ArrayView2<'_, T>) -> f64 {
    u.iter()
        .chain(v.iter())
        .fold(0.0f64, |m, &x| m.max(x.into().abs()))
}

/// A random field of the given size from a proptest-chosen seed (xorshift).
fn random_field(ny: usize, nx: usize, seed: u64) -> (Array2<f32>, Array2<f32>) {
    let mut s = seed | 1;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        ((s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0) as f32
    };
    let u = Array2::from_shape_fn((ny, nx), |_| next());
    let v = Array2::from_shape_fn((ny, nx), |_| next());
    (u, v)
}

proptest! {
    #![proptest_config(config(40))]

    /// The FFT path equals the direct sum, on every shape down to 1x1,
    /// with unequal spacings.
    #[test]
    fn fft_equals_direct_sum(
        ny in 1usize..=12, nx in 1usize..=12,
        dx in 0.2f64..4.0, dy in 0.2f64..4.0, seed in any::<u64>(),
    ) {
        let (u, v) = random_field(ny, nx, seed);
        let mut hhd = NaturalHhd::new();
        let fast = hhd.decompose(u.view(), v.view(), dx, dy).unwrap();
        let slow = direct::decompose(u.view(), v.view(), dx, dy).unwrap();
        let e = dec_rel_diff(&fast, &slow, field_scale(u.view(), v.view()));
        prop_assert!(e < 1e-10, "relative difference {e:e}");
    }

    /// Decomposition is linear in the field.
    #[test]
    fn linear_in_the_field(
        ny in 2usize..=20, nx in 2usize..=20, dx in 0.3f64..3.0, dy in 0.3f64..3.0,
        a in -3.0f64..3.0, b in -3.0f64..3.0, s1 in any::<u64>(), s2 in any::<u64>(),
    ) {
        let (u1, v1) = random_field(ny, nx, s1);
        let (u2, v2) = random_field(ny, nx, s2);
        let (u1, v1, u2, v2) = (u1.mapv(f64::from), v1.mapv(f64::from), u2.mapv(f64::from), v2.mapv(f64::from));
        let u = &u1 * a + &u2 * b;
        let v = &v1 * a + &v2 * b;
        let mut hhd = NaturalHhd::new();
        let d1 = hhd.decompose(u1.view(), v1.view(), dx, dy).unwrap();
        let d2 = hhd.decompose(u2.view(), v2.view(), dx, dy).unwrap();
        let d = hhd.decompose(u.view(), v.view(), dx, dy).unwrap();
        let combo = |f: fn(&Decomposition) -> &Array2<f64>| f(&d1) * a + f(&d2) * b;
        let scale = (a.abs() + b.abs()).max(1e-3);
        let parts: [fn(&Decomposition) -> &Array2<f64>; 8] = [
            |x| &x.potential_d, |x| &x.potential_r, |x| &x.d.u, |x| &x.d.v,
            |x| &x.r.u, |x| &x.r.v, |x| &x.h.u, |x| &x.h.v,
        ];
        for (k, f) in parts.iter().enumerate() {
            let want = combo(*f);
            let norm = max_abs(f(&d1)).max(max_abs(f(&d2))).max(1.0) * scale;
            let e = max_diff(f(&d), &want) / norm;
            prop_assert!(e < 1e-12, "part {k}: {e:e}");
        }
    }

    /// d is curl-free and r divergence-free: with numpy's central stencils
    /// the mixed differences commute, so away from the one-cell border the
    /// discrete curl of d and divergence of r vanish up to rounding.
    #[test]
    fn d_curl_free_and_r_divergence_free(
        ny in 3usize..=24, nx in 3usize..=24, dx in 0.3f64..3.0, dy in 0.3f64..3.0,
        seed in any::<u64>(),
    ) {
        let (u, v) = random_field(ny, nx, seed);
        let dec = NaturalHhd::new().decompose(u.view(), v.view(), dx, dy).unwrap();
        let z = || Array2::<f64>::zeros((ny, nx));
        let (mut dux, mut duy, mut dvx, mut dvy) = (z(), z(), z(), z());
        gradient(&dec.d.u, dx, dy, &mut dux, &mut duy).unwrap();
        gradient(&dec.d.v, dx, dy, &mut dvx, &mut dvy).unwrap();
        let curl_d = &dvx - &duy;
        let (mut rux, mut ruy, mut rvx, mut rvy) = (z(), z(), z(), z());
        gradient(&dec.r.u, dx, dy, &mut rux, &mut ruy).unwrap();
        gradient(&dec.r.v, dx, dy, &mut rvx, &mut rvy).unwrap();
        let div_r = &rux + &rvy;
        let inner = s![1..ny - 1, 1..nx - 1];
        let scale = max_abs(&dec.div).max(max_abs(&dec.curl)).max(1e-30);
        let e1 = curl_d.slice(inner).iter().fold(0.0f64, |m, x| m.max(x.abs())) / scale;
        let e2 = div_r.slice(inner).iter().fold(0.0f64, |m, x| m.max(x.abs())) / scale;
        prop_assert!(e1 < 1e-11 && e2 < 1e-11, "curl d {e1:e}, div r {e2:e}");
    }
}

/// Gradient of a Gaussian potential, rotated gradient of a Gaussian stream
/// function and a linear harmonic field, with their exact parts.
struct Analytic {
    u: Array2<f64>,
    v: Array2<f64>,
    d: (Array2<f64>, Array2<f64>),
    r: (Array2<f64>, Array2<f64>),
    h: (Array2<f64>, Array2<f64>),
}

#[allow(clippy::too_many_arguments)]
fn analytic(
    ny: usize,
    nx: usize,
    dx: f64,
    dy: f64,
    (px, py, ps): (f64, f64, f64),
    (sx, sy, ss): (f64, f64, f64),
    (c0, c1, a, b): (f64, f64, f64, f64),
) -> Analytic {
    let grid = |f: &dyn Fn(f64, f64) -> f64| {
        Array2::from_shape_fn((ny, nx), |(i, j)| f(j as f64 * dx, i as f64 * dy))
    };
    // phi = -exp(-r^2 / 2 ps^2): a dip at (px, py), grad phi points outward.
    let gauss = |x: f64, y: f64, cx: f64, cy: f64, s: f64| {
        (-((x - cx).powi(2) + (y - cy).powi(2)) / (2.0 * s * s)).exp()
    };
    let d_u = grid(&|x, y| (x - px) / (ps * ps) * gauss(x, y, px, py, ps));
    let d_v = grid(&|x, y| (y - py) / (ps * ps) * gauss(x, y, px, py, ps));
    // psi = 0.8 exp(..): r = (-dpsi/dy, dpsi/dx).
    let r_u = grid(&|x, y| 0.8 * (y - sy) / (ss * ss) * gauss(x, y, sx, sy, ss));
    let r_v = grid(&|x, y| -0.8 * (x - sx) / (ss * ss) * gauss(x, y, sx, sy, ss));
    // u = c0 + a x + b y, v = c1 + b x - a y: div = curl = 0.
    let h_u = grid(&|x, y| c0 + a * x + b * y);
    let h_v = grid(&|x, y| c1 + b * x - a * y);
    Analytic {
        u: &d_u + &r_u + &h_u,
        v: &d_v + &r_v + &h_v,
        d: (d_u, d_v),
        r: (r_u, r_v),
        h: (h_u, h_v),
    }
}

/// sqrt(sum |ours - truth|^2 / sum |truth|^2) over both components.
fn rel_l2(ours: (&Array2<f64>, &Array2<f64>), truth: (&Array2<f64>, &Array2<f64>)) -> f64 {
    let num: f64 =
        (ours.0 - truth.0).mapv(|x| x * x).sum() + (ours.1 - truth.1).mapv(|x| x * x).sum();
    let den: f64 = truth.0.mapv(|x| x * x).sum() + truth.1.mapv(|x| x * x).sum();
    (num / den).sqrt()
}

proptest! {
    #![proptest_config(config(8))]

    /// On a 64x80 grid with dx != dy, the parts of a known field come back
    /// within discretization error (O(h^2), a few percent at this size).
    #[test]
    fn recovers_analytic_parts(
        fx in 0.35f64..0.65, fy in 0.35f64..0.65, ps in 5.0f64..8.0,
        gx in 0.35f64..0.65, gy in 0.35f64..0.65, ss in 5.0f64..8.0,
        c0 in -0.5f64..0.5, c1 in -0.5f64..0.5, a in -0.01f64..0.01, b in -0.01f64..0.01,
    ) {
        let (ny, nx, dx, dy) = (64usize, 80usize, 0.8f64, 1.0f64);
        let (w, h) = ((nx - 1) as f64 * dx, (ny - 1) as f64 * dy);
        let f = analytic(ny, nx, dx, dy, (fx * w, fy * h, ps), (gx * w, gy * h, ss), (c0, c1, a, b));
        let dec = NaturalHhd::new().decompose(f.u.view(), f.v.view(), dx, dy).unwrap();
        let ed = rel_l2((&dec.d.u, &dec.d.v), (&f.d.0, &f.d.1));
        let er = rel_l2((&dec.r.u, &dec.r.v), (&f.r.0, &f.r.1));
        // h against the size of the whole field: it is the small rest.
        let eh = rel_l2((&dec.h.u, &dec.h.v), (&f.h.0, &f.h.1))
            * (f.h.0.mapv(|x| x * x).sum() + f.h.1.mapv(|x| x * x).sum()).sqrt()
            / (f.u.mapv(|x| x * x).sum() + f.v.mapv(|x| x * x).sum()).sqrt();
        eprintln!("analytic 64x80: rel L2 d {ed:.4}, r {er:.4}, h {eh:.4}");
        prop_assert!(ed < 0.05 && er < 0.05 && eh < 0.01, "d {ed:.4}, r {er:.4}, h {eh:.4}");
    }

    /// A press (markers pushed radially outward around a point) has its
    /// minimum of D at that point, also with unequal spacings.
    #[test]
    fn press_has_argmin_d_at_the_centre(
        ci in 12usize..28, cj in 15usize..40, s in 3.0f64..6.0,
        dx in 0.5f64..1.5, dy in 0.5f64..1.5, amp in 0.1f64..2.0,
    ) {
        let (ny, nx) = (40usize, 56usize);
        let (cx, cy) = (cj as f64 * dx, ci as f64 * dy);
        let mut u = Array2::<f32>::zeros((ny, nx));
        let mut v = Array2::<f32>::zeros((ny, nx));
        for i in 0..ny {
            for j in 0..nx {
                let (x, y) = (j as f64 * dx - cx, i as f64 * dy - cy);
                let g = amp * (-(x * x + y * y) / (2.0 * s * s)).exp() / s;
                u[[i, j]] = (x * g) as f32;
                v[[i, j]] = (y * g) as f32;
            }
        }
        let dec = NaturalHhd::new().decompose(u.view(), v.view(), dx, dy).unwrap();
        prop_assert_eq!(dec.argmin_d(), (ci, cj));
    }
}

/// The error against the analytic parts falls as O(h^2): halving the
/// spacing over the same domain cuts it about fourfold.
#[test]
fn error_falls_with_the_square_of_the_spacing() {
    let (w, h) = (48.0, 40.0);
    let mut errs = Vec::new();
    for k in [1.0, 2.0] {
        let (dx, dy) = (1.2 / k, 1.0 / k);
        let (nx, ny) = ((w / dx) as usize + 1, (h / dy) as usize + 1);
        let f = analytic(
            ny,
            nx,
            dx,
            dy,
            (20.0, 22.0, 5.0),
            (28.0, 18.0, 6.0),
            (0.1, -0.2, 0.003, 0.001),
        );
        let dec = NaturalHhd::new()
            .decompose(f.u.view(), f.v.view(), dx, dy)
            .unwrap();
        errs.push(rel_l2((&dec.d.u, &dec.d.v), (&f.d.0, &f.d.1)));
    }
    eprintln!("rel L2 error of d: {errs:?}");
    let ratio = errs[0] / errs[1];
    assert!((3.0..5.0).contains(&ratio), "{errs:?}: ratio {ratio}");
}

#[test]
fn spacing_scale_leaves_parts_and_scales_d_range() {
    let (u, v) = random_field(23, 31, 99);
    let mut hhd = NaturalHhd::new();
    let one = hhd.decompose(u.view(), v.view(), 1.0, 1.0).unwrap();
    let fs = field_scale(u.view(), v.view());
    for s in [0.25, 3.0] {
        let dec = hhd.decompose(u.view(), v.view(), s, s).unwrap();
        for (a, b) in [
            (&dec.d.u, &one.d.u),
            (&dec.d.v, &one.d.v),
            (&dec.r.u, &one.r.u),
            (&dec.r.v, &one.r.v),
            (&dec.h.u, &one.h.u),
            (&dec.h.v, &one.h.v),
        ] {
            assert!(max_diff(a, b) / fs < 1e-12);
        }
        // D_s = s D_1 + constant.
        let shift = &dec.potential_d - &(&one.potential_d * s);
        let c = shift[[0, 0]];
        let spread = shift.iter().fold(0.0f64, |m, x| m.max((x - c).abs()));
        assert!(spread < 1e-12 * one.d_range() * s, "{spread:e}");
        assert!((dec.d_range() / one.d_range() - s).abs() < 1e-12 * s);
        assert_eq!(dec.argmin_d(), one.argmin_d());
    }
}

#[test]
fn tiny_grids() {
    let mut hhd = NaturalHhd::new();
    // 1x1: no derivative exists, so everything is harmonic.
    let u = Array2::from_elem((1, 1), 0.5f32);
    let v = Array2::from_elem((1, 1), -2.0f32);
    let dec = hhd.decompose(u.view(), v.view(), 1.0, 1.0).unwrap();
    assert_eq!(dec.potential_d[[0, 0]], 0.0);
    assert_eq!((dec.h.u[[0, 0]], dec.h.v[[0, 0]]), (0.5, -2.0));
    // 1xN and Nx1: derivatives along the single-sample axis are 0.
    let row = Array2::from_shape_vec((1, 4), vec![0.0f32, 1.0, 4.0, 9.0]).unwrap();
    let zero = Array2::<f32>::zeros((1, 4));
    let dec = hhd.decompose(row.view(), zero.view(), 0.5, 2.0).unwrap();
    assert_eq!(
        dec.div.row(0).to_vec(),
        vec![2.0, 4.0, 8.0, 10.0],
        "numpy.gradient([0,1,4,9], 0.5)"
    );
    assert!(dec.curl.iter().all(|&c| c == 0.0));
    let slow = direct::decompose(row.view(), zero.view(), 0.5, 2.0).unwrap();
    assert!(dec_rel_diff(&dec, &slow, 9.0) < 1e-12);
    let col = row.t().to_owned();
    let zc = zero.t().to_owned();
    let dec = hhd.decompose(zc.view(), col.view(), 2.0, 0.5).unwrap();
    assert_eq!(dec.div.column(0).to_vec(), vec![2.0, 4.0, 8.0, 10.0]);
    // 2x2: one-sided differences everywhere.
    let u = Array2::from_shape_vec((2, 2), vec![0.0f32, 1.0, 0.0, 1.0]).unwrap();
    let v = Array2::<f32>::zeros((2, 2));
    let dec = hhd.decompose(u.view(), v.view(), 1.0, 1.0).unwrap();
    assert!(dec.div.iter().all(|&d| d == 1.0));
    let slow = direct::decompose(u.view(), v.view(), 1.0, 1.0).unwrap();
    assert!(dec_rel_diff(&dec, &slow, 1.0) < 1e-12);
}

#[test]
fn larger_unequal_grid_matches_direct_sum() {
    let (u, v) = random_field(41, 57, 7);
    let mut hhd = NaturalHhd::new();
    let fast = hhd.decompose(u.view(), v.view(), 0.3, 1.7).unwrap();
    let slow = direct::decompose(u.view(), v.view(), 0.3, 1.7).unwrap();
    let e = dec_rel_diff(&fast, &slow, field_scale(u.view(), v.view()));
    assert!(e < 1e-10, "{e:e}");
}

#[test]
fn a_torus_split_over_two_threads_matches_direct_sum() {
    // 60x300 pads to 120x600: past PARALLEL_MIN_CELLS, so every FFT pass of
    // this decomposition runs in two halves.
    let (u, v) = random_field(60, 300, 11);
    let mut hhd = NaturalHhd::new();
    let conv = hhd.prepare(60, 300, 2.0, 2.0).unwrap();
    let (py, px) = conv.padded_shape();
    assert!(py * px >= super::fft::PARALLEL_MIN_CELLS);
    let fast = hhd.decompose(u.view(), v.view(), 2.0, 2.0).unwrap();
    let slow = direct::decompose(u.view(), v.view(), 2.0, 2.0).unwrap();
    let e = dec_rel_diff(&fast, &slow, field_scale(u.view(), v.view()));
    assert!(e < 1e-10, "{e:e}");
}

#[test]
fn strided_views_and_reuse_give_the_same_result() {
    let (big_u, big_v) = random_field(60, 90, 3);
    // A strided, offset window such as a segmenter hands over.
    let su = big_u.slice(s![5..45;2, 10..80;3]);
    let sv = big_v.slice(s![5..45;2, 10..80;3]);
    let (ou, ov) = (su.to_owned(), sv.to_owned());
    let mut hhd = NaturalHhd::with_cache_capacity(2).unwrap();
    let want = hhd.decompose(ou.view(), ov.view(), 1.0, 2.0).unwrap();
    let mut out = Decomposition::zeros(3, 3);
    hhd.decompose_into(su, sv, 1.0, 2.0, &mut out).unwrap();
    assert_eq!(out, want);
    // Other sizes in between push the plan out of the cache and back.
    let (a, b) = random_field(17, 9, 4);
    let mut other = Decomposition::zeros(17, 9);
    for dxy in [(1.0, 1.0), (2.0, 1.0), (1.0, 3.0)] {
        hhd.decompose_into(a.view(), b.view(), dxy.0, dxy.1, &mut other)
            .unwrap();
    }
    hhd.decompose_into(su, sv, 1.0, 2.0, &mut out).unwrap();
    assert_eq!(out, want);
    // Transposed (column-major) views too.
    let t = hhd.decompose(ov.t(), ou.t(), 2.0, 1.0).unwrap();
    let want_t = hhd
        .decompose(ov.t().to_owned().view(), ou.t().to_owned().view(), 2.0, 1.0)
        .unwrap();
    assert_eq!(t, want_t);
}

#[test]
fn bad_input_is_a_typed_error() {
    let mut hhd = NaturalHhd::new();
    let z = Array2::<f32>::zeros((4, 5));
    let mut u = z.clone();
    u[[2, 3]] = f32::NAN;
    match hhd.decompose(u.view(), z.view(), 1.0, 1.0) {
        Err(Error::NonFinite { what, row, col }) => {
            assert_eq!((row, col), (2, 3));
            assert!(what.contains('u'), "{what}");
        }
        other => panic!("{other:?}"),
    }
    let mut v = z.clone();
    v[[0, 4]] = f32::NEG_INFINITY;
    match direct::decompose(z.view(), v.view(), 1.0, 1.0) {
        Err(Error::NonFinite { what, row, col }) => {
            assert_eq!((row, col), (0, 4));
            assert!(what.contains('v'), "{what}");
        }
        other => panic!("{other:?}"),
    }
    let w = Array2::<f32>::zeros((5, 4));
    assert!(matches!(
        hhd.decompose(z.view(), w.view(), 1.0, 1.0),
        Err(Error::ShapeMismatch {
            expected_w: 5,
            expected_h: 4,
            got_w: 4,
            got_h: 5,
            ..
        })
    ));
    let e = Array2::<f32>::zeros((0, 5));
    assert!(matches!(
        hhd.decompose(e.view(), e.view(), 1.0, 1.0),
        Err(Error::TooSmall { .. })
    ));
    for (dx, dy, name) in [
        (0.0, 1.0, "dx"),
        (1.0, -1.0, "dy"),
        (f64::NAN, 1.0, "dx"),
        (1.0, f64::INFINITY, "dy"),
    ] {
        match hhd.decompose(z.view(), z.view(), dx, dy) {
            Err(Error::InvalidParameter { name: n, .. }) => assert_eq!(n, name),
            other => panic!("{other:?}"),
        }
        assert!(direct::decompose(z.view(), z.view(), dx, dy).is_err());
    }
    // The planner still works after errors.
    assert!(hhd.decompose(z.view(), z.view(), 1.0, 1.0).is_ok());
}

/// One torus serves every grid up to its max shape: a convolver planned for
/// 60x60 gives the direct sum on a 13x17 grid, and refuses a grid too big.
#[test]
fn a_convolver_serves_smaller_grids_exactly() {
    use super::fft::{FftWorkspace, GreenConvolver};
    use rustfft::FftPlanner;
    let (dx, dy) = (0.7, 1.9);
    let conv = GreenConvolver::new(&mut FftPlanner::new(), 60, 60, dx, dy).unwrap();
    let mut ws = FftWorkspace::new();
    for (ny, nx) in [(13, 17), (60, 1), (1, 60), (60, 60)] {
        let (a, b) = random_field(ny, nx, (ny * 100 + nx) as u64);
        let (div, curl) = (a.mapv(f64::from), b.mapv(f64::from));
        let mut d = Array2::zeros((ny, nx));
        let mut r = Array2::zeros((ny, nx));
        conv.potentials(&mut ws, div.view(), curl.view(), &mut d, &mut r)
            .unwrap();
        let (dd, rr) = direct::potentials(div.view(), curl.view(), dx, dy).unwrap();
        let scale = max_abs(&dd).max(max_abs(&rr));
        let e = max_diff(&d, &dd).max(max_diff(&r, &rr)) / scale;
        assert!(e < 1e-12, "{ny}x{nx}: {e:e}");
    }
    let big = Array2::<f64>::zeros((61, 10));
    let mut o1 = big.clone();
    let mut o2 = big.clone();
    assert!(matches!(
        conv.potentials(&mut ws, big.view(), big.view(), &mut o1, &mut o2),
        Err(Error::ShapeMismatch { .. })
    ));
}

/// A planner can move to a worker thread (one planner per thread, e.g. with
/// rayon's `map_init`), and its results can be sent back.
#[test]
fn planner_and_results_are_send() {
    fn send<T: Send>() {}
    send::<NaturalHhd>();
    send::<Decomposition>();
    let (u, v) = random_field(9, 11, 5);
    let want = NaturalHhd::new()
        .decompose(u.view(), v.view(), 1.0, 1.0)
        .unwrap();
    let got = std::thread::spawn(move || {
        let mut hhd = NaturalHhd::new();
        hhd.decompose(u.view(), v.view(), 1.0, 1.0).unwrap()
    })
    .join()
    .unwrap();
    assert_eq!(got, want);
}

/// Largest difference between a divergent part and a whole decomposition's
/// divergence, `D` and `d`, each relative to the magnitude of its kind.
fn part_rel_diff(part: &DivergentPart, whole: &Decomposition, field_scale: f64) -> f64 {
    let pot = max_abs(&whole.potential_d).max(f64::MIN_POSITIVE);
    let der = max_abs(&whole.div).max(f64::MIN_POSITIVE);
    let f = field_scale.max(f64::MIN_POSITIVE);
    assert_eq!((part.dx, part.dy), (whole.dx, whole.dy));
    [
        max_diff(&part.div, &whole.div) / der,
        max_diff(&part.potential_d, &whole.potential_d) / pot,
        max_diff(&part.d.u, &whole.d.u) / f,
        max_diff(&part.d.v, &whole.d.v) / f,
    ]
    .into_iter()
    .fold(0.0, f64::max)
}

proptest! {
    #![proptest_config(config(60))]

    /// The divergent part alone (two real rows per complex FFT, half the
    /// columns) equals the direct sum's divergence, `D` and `d`, on every
    /// shape down to 1x1 (odd and even row counts, odd and even tori),
    /// with unequal spacings; and the whole FFT decomposition's, to rounding.
    #[test]
    fn divergent_part_equals_direct_sum(
        ny in 1usize..=13, nx in 1usize..=13,
        dx in 0.2f64..4.0, dy in 0.2f64..4.0, seed in any::<u64>(),
    ) {
        let (u, v) = random_field(ny, nx, seed);
        let mut hhd = NaturalHhd::new();
        let mut part = DivergentPart::default();
        hhd.divergent_into(u.view(), v.view(), dx, dy, &mut part).unwrap();
        let scale = field_scale(u.view(), v.view());
        let slow = direct::decompose(u.view(), v.view(), dx, dy).unwrap();
        let e = part_rel_diff(&part, &slow, scale);
        prop_assert!(e < 1e-10, "against the direct sum: {e:e}");
        let whole = hhd.decompose(u.view(), v.view(), dx, dy).unwrap();
        let e = part_rel_diff(&part, &whole, scale);
        prop_assert!(e < 1e-12, "against the whole decomposition: {e:e}");
    }
}

#[test]
fn divergent_part_of_large_and_split_grids_matches_direct_sum() {
    // 41x57: odd rows; 60x300 and 61x301: tori past PARALLEL_MIN_CELLS, so
    // every pass runs in two halves (an even and an odd number of pairs).
    for (ny, nx, dx, dy, seed) in [
        (41, 57, 0.3, 1.7, 7),
        (60, 300, 2.0, 2.0, 11),
        (61, 301, 2.0, 2.0, 12),
    ] {
        let (u, v) = random_field(ny, nx, seed);
        let mut hhd = NaturalHhd::new();
        let mut part = DivergentPart::zeros(2, 3);
        hhd.divergent_into(u.view(), v.view(), dx, dy, &mut part)
            .unwrap();
        let slow = direct::decompose(u.view(), v.view(), dx, dy).unwrap();
        let e = part_rel_diff(&part, &slow, field_scale(u.view(), v.view()));
        assert!(e < 1e-10, "{ny}x{nx}: {e:e}");
    }
}

#[test]
fn divergent_part_reuses_its_storage_and_takes_strided_views() {
    let (big_u, big_v) = random_field(60, 90, 3);
    let su = big_u.slice(s![5..45;2, 10..80;3]);
    let sv = big_v.slice(s![5..45;2, 10..80;3]);
    let (ou, ov) = (su.to_owned(), sv.to_owned());
    let mut hhd = NaturalHhd::with_cache_capacity(2).unwrap();
    let mut want = DivergentPart::default();
    hhd.divergent_into(ou.view(), ov.view(), 1.0, 2.0, &mut want)
        .unwrap();
    // A larger grid, then a smaller one, then this one again, in one part:
    // the same numbers whatever the part held before.
    let mut out = DivergentPart::zeros(1, 1);
    let (a, b) = random_field(37, 41, 4);
    hhd.divergent_into(a.view(), b.view(), 1.0, 1.0, &mut out)
        .unwrap();
    let (c, d) = random_field(3, 5, 5);
    hhd.divergent_into(c.view(), d.view(), 3.0, 1.0, &mut out)
        .unwrap();
    hhd.divergent_into(su, sv, 1.0, 2.0, &mut out).unwrap();
    assert_eq!(out, want);
    assert_eq!(out.shape(), (20, 24));
    // Bad input: the same typed errors as a whole decomposition.
    let z = Array2::<f32>::zeros((4, 5));
    let mut n = z.clone();
    n[[1, 2]] = f32::INFINITY;
    assert!(matches!(
        hhd.divergent_into(z.view(), n.view(), 1.0, 1.0, &mut out),
        Err(Error::NonFinite { row: 1, col: 2, .. })
    ));
    assert!(matches!(
        hhd.divergent_into(z.view(), z.slice(s![..3, ..]), 1.0, 1.0, &mut out),
        Err(Error::ShapeMismatch { .. })
    ));
    assert!(
        hhd.divergent_into(z.view(), z.view(), 0.0, 1.0, &mut out)
            .is_err()
    );
    let e = Array2::<f32>::zeros((0, 5));
    assert!(matches!(
        hhd.divergent_into(e.view(), e.view(), 1.0, 1.0, &mut out),
        Err(Error::TooSmall { .. })
    ));
}
