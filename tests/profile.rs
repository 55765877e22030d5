//! The profile model of the forces: kernels fitted from synthetic samples
//! with known responses, the joint force match against a plain
//! least-squares oracle, and bad input.

use nalgebra::{DMatrix, DVector};
use optical_tactile::Error;
use optical_tactile::contact::profile::{
    ColumnMap, ForceMatcher, ProfileModel, ProfileSample, Relocation, SizeTerm, column_profile_into,
};
use optical_tactile_sim::rng::SplitMix64;

#[path = "common/synthetic.rs"]
mod synthetic;

const N: usize = 400; // profile cells
const SCALE: f64 = 2.0; // full-resolution pixels per cell
const CENTRE: f64 = 399.5;
const SPAN: f64 = 400.0;

/// The true response of channel `ch` to force component `k` of a contact at
/// column `c` (pixels), at offset `t` pixels: smooth shapes whose height
/// changes with the column (degree 1 in the normalised column), below 1e-8
/// beyond 200 px (the kernels' reach in these tests).
fn response(ch: usize, k: usize, c: f64, t: f64) -> f64 {
    let z = (c - CENTRE) / SPAN;
    let w = 30.0 + 5.0 * k as f64 + 3.0 * ch as f64;
    let g = (-(t / w).powi(2)).exp();
    let shape = match k {
        0 => g,                 // tangential: even bump
        1 => g * (1.0 + t / w), // across: lopsided
        _ => t / w * g,         // normal: odd, spreading
    };
    (1.0 + 0.3 * z) * shape * if ch == 0 { 1.0 } else { 0.2 + 0.1 * k as f64 }
}

/// [`response`] plus a far tail, as on a soft, thick gel: the tangential
/// and normal forces also move the skin along the arc, one way, far beyond
/// the kernels' 200 px of reach (e^(-t/300): a fifth of it is left at
/// 480 px).
fn tailed_response(ch: usize, k: usize, c: f64, t: f64) -> f64 {
    let z = (c - CENTRE) / SPAN;
    let far = match (ch, k) {
        (0, 0) => 0.3,
        (0, 2) => -0.2,
        (1, 2) => 0.05,
        _ => 0.0,
    };
    response(ch, k, c, t) + (1.0 + 0.3 * z) * far * (-t.abs() / 300.0).exp()
}

/// The profiles (u, v) of contacts at `cols` with local forces `forces`.
fn profiles(cols: &[f64], forces: &[[f64; 3]]) -> [Vec<f64>; 2] {
    profiles_of(response, cols, forces)
}

/// [`profiles`] with the response `response`.
fn profiles_of(
    response: fn(usize, usize, f64, f64) -> f64,
    cols: &[f64],
    forces: &[[f64; 3]],
) -> [Vec<f64>; 2] {
    synthetic::channel_profiles(N, SCALE, response, cols, forces)
}

/// A training contact: column, local force, profiles (u, v).
type Training = (f64, [f64; 3], [Vec<f64>; 2]);

/// The pixel of cell `j`'s centre.
fn cell(j: usize) -> f64 {
    (j as f64 + 0.5) * SCALE - 0.5
}

/// Training contacts on cell centres, so that the kernels are sampled
/// exactly where the profiles are (no interpolation error).
fn training_set(seed: u64) -> Vec<Training> {
    training_set_of(response, (75, 250), seed)
}

/// [`training_set`] with far tails ([`tailed_response`]), and contacts
/// from one end of the profile to the other, as a protocol's points are
/// (every offset is then reached from several places).
fn tailed_training_set(seed: u64) -> Vec<Training> {
    training_set_of(tailed_response, (10, 380), seed)
}

/// 120 training contacts at random cells of `first..first + span`, with
/// the response `response`.
fn training_set_of(
    response: fn(usize, usize, f64, f64) -> f64,
    (first, span): (usize, usize),
    seed: u64,
) -> Vec<Training> {
    let mut rng = SplitMix64::new(seed);
    (0..120)
        .map(|_| {
            let c = cell(first + (span as f64 * rng.next_f64()) as usize);
            let f = [
                rng.next_f64() - 0.5,
                0.2 * (rng.next_f64() - 0.5),
                -0.5 - 2.5 * rng.next_f64(),
            ];
            let p = profiles_of(response, &[c], &[f]);
            (c, f, p)
        })
        .collect()
}

/// The training contacts as fitting samples, with their own forces or,
/// given `force`, that one for all.
fn samples(set: &[Training], force: Option<[f64; 3]>) -> Vec<ProfileSample<'_>> {
    set.iter()
        .map(|(c, f, p)| ProfileSample {
            column_px: *c,
            profile_u: &p[0],
            profile_v: &p[1],
            scale: SCALE,
            local_force: force.unwrap_or(*f),
            size_mm: None,
        })
        .collect()
}

fn fit(set: &[Training], degree: usize) -> ProfileModel {
    ProfileModel::fit(&samples(set, None), SCALE, 200.0, degree, CENTRE, SPAN).unwrap()
}

#[test]
fn fitted_kernels_reproduce_the_true_responses() {
    let model = fit(&training_set(1), 1);
    assert_eq!(model.half_width, 100);
    // A contact at an unseen column: the model's match of its own profile
    // returns its forces, exactly on a cell centre, and between cells to
    // within the linear interpolation of the kernels and profiles (cells of
    // 2 px against responses some 30 px wide: about 1 % of the force).
    let mut m = ForceMatcher::new();
    let mut out = Vec::new();
    for (c, f, tol) in [
        (cell(166), [0.4, -0.05, -1.7], 1e-9),
        (cell(306), [-0.2, 0.08, -0.6], 1e-9),
        (333.3, [0.4, -0.05, -1.7], 0.01 * 1.7),
        (612.9, [-0.2, 0.08, -0.6], 0.01 * 0.6),
    ] {
        let p = profiles(&[c], &[f]);
        m.measure(&model, &[c], &p[0], &p[1], SCALE, &mut out)
            .unwrap();
        for k in 0..3 {
            assert!((out[0][k] - f[k]).abs() < tol, "{c}: {:?} vs {f:?}", out[0]);
        }
    }
}

#[test]
fn two_close_contacts_share_out_their_overlapping_motion() {
    let model = fit(&training_set(2), 1);
    let cols = [cell(190), cell(220)]; // 60 px apart: their kernels overlap
    let forces = [[0.3, 0.0, -2.0], [-0.1, 0.05, -1.5]];
    let p = profiles(&cols, &forces);
    let mut out = Vec::new();
    ForceMatcher::new()
        .measure(&model, &cols, &p[0], &p[1], SCALE, &mut out)
        .unwrap();
    for (o, f) in out.iter().zip(&forces) {
        for k in 0..3 {
            assert!((o[k] - f[k]).abs() < 1e-9, "{out:?} vs {forces:?}");
        }
    }
    // Each contact alone takes in its neighbour's motion: clearly worse.
    let mut alone = Vec::new();
    ForceMatcher::new()
        .measure(&model, &cols[..1], &p[0], &p[1], SCALE, &mut alone)
        .unwrap();
    assert!((alone[0][2] - forces[0][2]).abs() > 0.05, "{alone:?}");
}

#[test]
fn far_tails_keep_a_distant_contacts_motion_out_of_anothers_force() {
    let set = tailed_training_set(4);
    let s = samples(&set, None);
    let near = ProfileModel::fit(&s, SCALE, 200.0, 1, CENTRE, SPAN).unwrap();
    assert!(near.tail.is_none());
    // Tails sampled on the cells (2 px), out to the profile's length.
    let tailed = near.clone().with_tail(&s, SCALE, 800.0).unwrap();
    let tail = tailed.tail.as_ref().unwrap();
    assert_eq!(tail.half_width, 400);
    assert_eq!(tail.half_width as f64 * tail.step_px, 800.0);
    // 440 px apart: no cell lies within both contacts' 200 px of reach,
    // but each one's equations hold the other's far motion.
    let cols = [cell(80), cell(300)];
    let forces = [[0.1, 0.02, -2.5], [-0.2, 0.0, -1.0]];
    let p = profiles_of(tailed_response, &cols, &forces);
    let mut m = ForceMatcher::new();
    let mut with_tails = Vec::new();
    m.measure(&tailed, &cols, &p[0], &p[1], SCALE, &mut with_tails)
        .unwrap();
    for (o, f) in with_tails.iter().zip(&forces) {
        for k in 0..3 {
            assert!((o[k] - f[k]).abs() < 1e-6, "{with_tails:?} vs {forces:?}");
        }
    }
    // Without them the far motion is read as the other contact's force.
    let mut without = Vec::new();
    m.measure(&near, &cols, &p[0], &p[1], SCALE, &mut without)
        .unwrap();
    let worst = without
        .iter()
        .zip(&forces)
        .flat_map(|(o, f)| (0..3).map(move |k| (o[k] - f[k]).abs()))
        .fold(0.0, f64::max);
    assert!(worst > 0.05, "{without:?} vs {forces:?}");
    // A contact alone is matched exactly as without the tails: its
    // equations lie within its own reach, where the kernels are the same.
    for c in [cell(120), 457.3] {
        let p = profiles_of(tailed_response, &[c], &[forces[0]]);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        m.measure(&near, &[c], &p[0], &p[1], SCALE, &mut a).unwrap();
        m.measure(&tailed, &[c], &p[0], &p[1], SCALE, &mut b)
            .unwrap();
        assert_eq!(a, b);
    }
    // Relocation sees the far contact too: both points stay put.
    let mut moved = cols;
    m.relocate(&tailed, &mut moved, &p[0], &p[1], SCALE)
        .unwrap();
    assert_eq!(moved, cols);
    // A contact alone is relocated as without the tails: its search window
    // reaches past its kernels, and those cells stay unexplained.
    let c = cell(150);
    let p = profiles_of(tailed_response, &[c], &[forces[0]]);
    for at in [c + 24.0, c - 24.0, c + 7.0] {
        let (mut a, mut b) = ([at], [at]);
        m.relocate(&near, &mut a, &p[0], &p[1], SCALE).unwrap();
        m.relocate(&tailed, &mut b, &p[0], &p[1], SCALE).unwrap();
        assert_eq!(a, b);
    }
}

#[test]
fn tails_refuse_bad_parameters_and_broken_files() {
    let set = tailed_training_set(5);
    let s = samples(&set, None);
    let model = ProfileModel::fit(&s, SCALE, 200.0, 1, CENTRE, SPAN).unwrap();
    for (step, reach) in [
        (0.0, 800.0),
        (-2.0, 800.0),
        (f64::NAN, 800.0),
        (2.0, f64::INFINITY),
        (2.0, 200.0), // not beyond the kernels' reach
        (2.0, 100.0),
        (1e9, 800.0),
    ] {
        let e = model.clone().with_tail(&s, step, reach).unwrap_err();
        assert!(
            matches!(e, Error::InvalidParameter { .. }),
            "{step} {reach}: {e}"
        );
    }
    // Offsets no sample reaches keep a zero tail rather than failing.
    let far = model.clone().with_tail(&s, SCALE, 4000.0).unwrap();
    let t = far.tail.as_ref().unwrap();
    assert!(t.kernels[0][0][0] == 0.0 && t.kernels[0][0][2 * t.half_width] == 0.0);
    // A file's tail is checked like its kernels.
    let good = model.with_tail(&s, SCALE, 800.0).unwrap();
    let json = serde_json::to_string(&good).unwrap();
    let back: ProfileModel = serde_json::from_str(&json).unwrap();
    back.validate().unwrap();
    let (a, b) = (back.tail.as_ref().unwrap(), good.tail.as_ref().unwrap());
    assert_eq!((a.step_px, a.half_width), (b.step_px, b.half_width));
    for (x, y) in a
        .kernels
        .iter()
        .flatten()
        .flatten()
        .zip(b.kernels.iter().flatten().flatten())
    {
        assert!((x - y).abs() <= 1e-12 * (1.0 + y.abs()), "{x} vs {y}");
    }
    let mut short = good.clone();
    short.tail.as_mut().unwrap().kernels[1][0].pop();
    let mut nan = good.clone();
    nan.tail.as_mut().unwrap().kernels[0][1][7] = f64::NAN;
    let mut step = good.clone();
    step.tail.as_mut().unwrap().step_px = 0.0;
    let mut wide = good;
    wide.tail.as_mut().unwrap().half_width = usize::MAX;
    for broken in [short, nan, step, wide] {
        let e = broken.validate().unwrap_err();
        assert!(e.to_string().contains("tail"), "{e}");
    }
}

/// The slow, obvious twin of the matcher: build the whole design matrix
/// (every cell within reach of a contact, both channels) and solve it by SVD.
fn oracle(model: &ProfileModel, cols: &[f64], p: &[Vec<f64>; 2]) -> Vec<f64> {
    let reach = model.half_width as f64 * model.step_px;
    let comps = model.kernels[0].len() / (model.degree + 1);
    let mut rows = Vec::new();
    let mut rhs = Vec::new();
    for (ch, prof) in p.iter().enumerate() {
        for (j, &y) in prof.iter().enumerate() {
            let x = (j as f64 + 0.5) * SCALE - 0.5;
            if !cols.iter().any(|c| (x - c).abs() <= reach) {
                continue;
            }
            let mut r = Vec::new();
            for &c in cols {
                for k in 0..comps {
                    r.push(kernel_value(model, ch, c, x - c, k));
                }
            }
            rows.push(r);
            rhs.push(y);
        }
    }
    let a = DMatrix::from_fn(rows.len(), comps * cols.len(), |i, j| rows[i][j]);
    let b = DVector::from_vec(rhs);
    let x = a.svd(true, true).solve(&b, 1e-12).unwrap();
    // The forces of each contact (the size term's unknown, if any, dropped).
    x.as_slice()
        .chunks_exact(comps)
        .flat_map(|c| c[..3].to_vec())
        .collect()
}

/// Kernel value straight from the stored samples (linear between them):
/// within the reach the kernels', beyond it the tail's (0 without one).
fn kernel_value(model: &ProfileModel, ch: usize, c: f64, t: f64, k: usize) -> f64 {
    let reach = model.half_width as f64 * model.step_px;
    let (kernels, step, half) = if t.abs() <= reach {
        (&model.kernels, model.step_px, model.half_width)
    } else if let Some(tail) = &model.tail {
        (&tail.kernels, tail.step_px, tail.half_width)
    } else {
        return 0.0;
    };
    let idx = t / step + half as f64;
    if idx < 0.0 || idx > (2 * half) as f64 {
        return 0.0;
    }
    let i0 = idx.floor() as usize;
    let i1 = (i0 + 1).min(2 * half);
    let a = idx - i0 as f64;
    let z = (c - model.centre_px) / model.span_px;
    (0..=model.degree)
        .map(|m| {
            let kern = &kernels[ch][k * (model.degree + 1) + m];
            z.powi(m as i32) * ((1.0 - a) * kern[i0] + a * kern[i1])
        })
        .sum()
}

proptest::proptest! {
    #![proptest_config(proptest::test_runner::Config {
        cases: 24,
        rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
        rng_seed: proptest::test_runner::RngSeed::Fixed(11),
        failure_persistence: None,
        ..Default::default()
    })]
    #[test]
    fn the_matcher_agrees_with_the_svd_oracle(
        c1 in 100.0f64..700.0,
        gap in 20.0f64..600.0,
        noise in proptest::collection::vec(-1.0f64..1.0, 2 * N),
        sized in proptest::bool::ANY,
        tailed in proptest::bool::ANY,
    ) {
        let set = tailed_training_set(3);
        let mut s = samples(&set, None);
        let model = if sized {
            // The same data with made-up sizes: the size kernels are then
            // mostly noise, but the matcher must still solve the same system.
            for (i, x) in s.iter_mut().enumerate() {
                x.size_mm = Some([2.0, 5.0, 10.0][i % 3]);
            }
            let term = SizeTerm::for_sizes(s.iter().filter_map(|x| x.size_mm)).unwrap();
            ProfileModel::fit_with_size(&s, SCALE, 200.0, 2, CENTRE, SPAN, Some(term)).unwrap()
        } else {
            ProfileModel::fit(&s, SCALE, 200.0, 2, CENTRE, SPAN).unwrap()
        };
        // Tails every 3 px: between the cells, so that the oracle's
        // interpolation of them is exercised too.
        let model = if tailed { model.with_tail(&s, 3.0, 800.0).unwrap() } else { model };
        let cols = [c1, (c1 + gap).min(790.0)];
        let mut p = profiles_of(tailed_response, &cols, &[[0.2, 0.01, -1.0], [0.0, -0.02, -0.7]]);
        for (i, e) in noise.iter().enumerate() {
            p[i / N][i % N] += 0.05 * e;
        }
        let mut out = Vec::new();
        ForceMatcher::new().measure(&model, &cols, &p[0], &p[1], SCALE, &mut out).unwrap();
        let want = oracle(&model, &cols, &p);
        for (g, w) in out.iter().flatten().zip(&want) {
            proptest::prop_assert!((g - w).abs() < 1e-6 * (1.0 + w.abs()), "{out:?} vs {want:?}");
        }
    }
}

#[test]
fn column_profiles_are_scaled_column_sums() {
    let u = ndarray::Array2::from_shape_fn((3, 4), |(i, j)| (i * 4 + j) as f32);
    let mut p = Vec::new();
    column_profile_into(u.view(), 2.0, &mut p);
    assert_eq!(p, vec![24.0, 30.0, 36.0, 42.0]);
}

#[test]
fn bad_input_is_a_clear_error() {
    let model = fit(&training_set(4), 1);
    let p = profiles(&[400.0], &[[0.0, 0.0, -1.0]]);
    let mut m = ForceMatcher::new();
    let mut out = Vec::new();
    // Mismatched profiles.
    let e = m
        .measure(&model, &[400.0], &p[0], &p[1][..10], SCALE, &mut out)
        .unwrap_err();
    assert!(matches!(e, Error::ShapeMismatch { .. }), "{e:?}");
    // A NaN in the profile near the contact.
    let mut bad = p[0].clone();
    bad[200] = f64::NAN;
    let e = m
        .measure(&model, &[400.0], &bad, &p[1], SCALE, &mut out)
        .unwrap_err();
    assert!(matches!(e, Error::NonFinite { .. }), "{e:?}");
    // Two contacts at the same column cannot be told apart: rather than
    // failing the frame, they share the force evenly.
    let mut one = Vec::new();
    m.measure(&model, &[400.0], &p[0], &p[1], SCALE, &mut one)
        .unwrap();
    m.measure(&model, &[400.0, 400.0], &p[0], &p[1], SCALE, &mut out)
        .unwrap();
    for k in 0..3 {
        assert!((out[0][k] - out[1][k]).abs() < 1e-6, "{out:?}");
        assert!(
            (out[0][k] + out[1][k] - one[0][k]).abs() < 1e-6,
            "{out:?} vs {one:?}"
        );
    }
    // A model with no response anywhere: a clear error.
    let mut zero = model.clone();
    zero.kernels
        .iter_mut()
        .flatten()
        .flatten()
        .for_each(|x| *x = 0.0);
    let e = m
        .measure(&zero, &[400.0], &p[0], &p[1], SCALE, &mut out)
        .unwrap_err();
    assert!(matches!(e, Error::Numerical { .. }), "{e:?}");
    // Bad scale, non-finite column.
    assert!(
        m.measure(&model, &[400.0], &p[0], &p[1], 0.0, &mut out)
            .is_err()
    );
    assert!(
        m.measure(&model, &[f64::NAN], &p[0], &p[1], SCALE, &mut out)
            .is_err()
    );
    // No contact: nothing to do.
    m.measure(&model, &[], &p[0], &p[1], SCALE, &mut out)
        .unwrap();
    assert!(out.is_empty());
    // Too few samples, forces that do not vary, bad parameters.
    let set = training_set(5);
    let few = samples(&set[..3], None);
    let e = ProfileModel::fit(&few, SCALE, 120.0, 1, CENTRE, SPAN).unwrap_err();
    assert!(matches!(e, Error::Calibration { .. }), "{e:?}");
    let same = samples(&set, Some([0.0, 0.0, -1.0]));
    let e = ProfileModel::fit(&same, SCALE, 120.0, 1, CENTRE, SPAN).unwrap_err();
    assert!(e.to_string().contains("singular"), "{e}");
    assert!(ProfileModel::fit(&same, 0.0, 120.0, 1, CENTRE, SPAN).is_err());
    assert!(ProfileModel::fit(&same, SCALE, 120.0, 9, CENTRE, SPAN).is_err());
    // A malformed model (kernel of the wrong length) fails validation.
    let mut broken = model.clone();
    broken.kernels[1][2].pop();
    assert!(broken.validate().is_err());
    let mut nan = model;
    nan.kernels[0][0][5] = f64::NAN;
    assert!(nan.validate().is_err());
}

#[test]
fn column_map_recovers_a_polynomial_and_rejects_bad_input() {
    // Columns of a cubic camera-like projection of chord positions.
    let truth = |x: f64| 799.5 + 4.97 * x - 1.6e-4 * x * x + 8.4e-6 * x * x * x;
    let points: Vec<(f64, f64)> = (-11..=11)
        .map(|i| 10.0 * i as f64)
        .map(|x| (x, truth(x)))
        .collect();
    let map = ColumnMap::fit(&points, 3).unwrap();
    for x in [-107.0, -3.3, 0.0, 58.1, 110.0] {
        assert!((map.column(x) - truth(x)).abs() < 1e-6, "{x}");
    }
    map.validate().unwrap();
    // A line cannot follow the cubic's ends.
    let line = ColumnMap::fit(&points, 1).unwrap();
    assert!((line.column(110.0) - truth(110.0)).abs() > 1.0);
    // Bad input: degree, too few points, NaN.
    assert!(ColumnMap::fit(&points, 0).is_err());
    assert!(ColumnMap::fit(&points, 7).is_err());
    let e = ColumnMap::fit(&points[..5], 3).unwrap_err();
    assert!(matches!(e, Error::Calibration { .. }), "{e:?}");
    let mut nan = points.clone();
    nan[4].1 = f64::NAN;
    assert!(matches!(
        ColumnMap::fit(&nan, 3).unwrap_err(),
        Error::InvalidParameter { .. }
    ));
    // All points at one position: no polynomial through them.
    let same = vec![(5.0, 800.0); 20];
    assert!(ColumnMap::fit(&same, 2).is_err());
    // A loaded map with a bad scale or coefficient fails validation, and so
    // does a model that carries it.
    let mut bad = map.clone();
    bad.scale_mm = 0.0;
    assert!(bad.validate().is_err());
    let mut model = fit(&training_set(6), 1);
    model.anchor = Some(ColumnMap {
        scale_mm: 100.0,
        coefficients: vec![1.0, f64::INFINITY],
    });
    assert!(model.validate().is_err());
}

#[test]
fn model_json_keeps_the_anchor_and_older_files_have_none() {
    let mut model = fit(&training_set(7), 1);
    let plain = serde_json::to_string(&model).unwrap();
    assert!(!plain.contains("anchor"), "no anchor, no field");
    assert_eq!(
        serde_json::from_str::<ProfileModel>(&plain).unwrap().anchor,
        None
    );
    model.anchor = Some(ColumnMap {
        scale_mm: 114.0,
        coefficients: vec![799.5, 566.0, -2.1, 12.4],
    });
    let back: ProfileModel = serde_json::from_str(&serde_json::to_string(&model).unwrap()).unwrap();
    // (Kernel samples round-trip to within JSON's float printing.)
    assert_eq!(back.anchor, model.anchor);
}

/// Why kernels are anchored at a smooth map of the true positions: when the
/// measured column moves in step with the tangential force (as the steepest
/// rise of a sheared profile does), kernels fitted at the measured columns
/// mix the normal and tangential responses; fitted at the anchor columns
/// they do not.
#[test]
fn anchored_kernels_are_not_smeared_by_a_shear_dependent_column() {
    let px_per_mm = 5.0;
    let column_of = |x_mm: f64| CENTRE + px_per_mm * x_mm;
    let shift_per_n = 6.0; // measured column moves 6 px per N of tangential force
    let mut rng = SplitMix64::new(11);
    // (true position mm, measured column, local force, profiles)
    type Press = (f64, f64, [f64; 3], [Vec<f64>; 2]);
    let set: Vec<Press> = (0..150)
        .map(|_| {
            let x_mm = -50.0 + 100.0 * rng.next_f64();
            let f = [
                rng.next_f64() - 0.5,
                0.2 * (rng.next_f64() - 0.5),
                -0.5 - 2.5 * rng.next_f64(),
            ];
            let c = column_of(x_mm);
            (x_mm, c + shift_per_n * f[0], f, profiles(&[c], &[f]))
        })
        .collect();
    let points: Vec<(f64, f64)> = set.iter().map(|(x, m, _, _)| (*x, *m)).collect();
    let map = ColumnMap::fit(&points, 1).unwrap();
    let fit_at = |anchored: bool| {
        let samples: Vec<ProfileSample<'_>> = set
            .iter()
            .map(|(x, measured, f, p)| ProfileSample {
                column_px: if anchored { map.column(*x) } else { *measured },
                profile_u: &p[0],
                profile_v: &p[1],
                scale: SCALE,
                local_force: *f,
                size_mm: None,
            })
            .collect();
        ProfileModel::fit(&samples, SCALE, 200.0, 1, CENTRE, SPAN).unwrap()
    };
    let (smeared, anchored) = (fit_at(false), fit_at(true));
    let mut m = ForceMatcher::new();
    let (mut err_smeared, mut err_anchored) = (0.0f64, 0.0f64);
    for (x_mm, f) in [(-31.0, [0.4, 0.05, -2.2]), (12.5, [-0.3, -0.06, -1.1])] {
        let c = column_of(x_mm);
        let p = profiles(&[c], &[f]);
        let mut out = Vec::new();
        m.measure(
            &smeared,
            &[c + shift_per_n * f[0]],
            &p[0],
            &p[1],
            SCALE,
            &mut out,
        )
        .unwrap();
        err_smeared = err_smeared.max((out[0][2] - f[2]).abs());
        m.measure(
            &anchored,
            &[map.column(x_mm)],
            &p[0],
            &p[1],
            SCALE,
            &mut out,
        )
        .unwrap();
        err_anchored = err_anchored.max((out[0][2] - f[2]).abs());
    }
    // The anchor map of zero-mean shifts is the true column to within the
    // spread of the tangential forces' mean; the normal force comes back to
    // a few percent, against a clearly larger error when smeared.
    assert!(
        err_anchored < 0.05,
        "anchored normal force error {err_anchored}"
    );
    assert!(
        err_smeared > 3.0 * err_anchored,
        "smeared {err_smeared} vs anchored {err_anchored}"
    );
}

/// Extra normal response of an indenter of `size_mm` against one of 6 mm:
/// a wider press spreads its motion further out (an odd shape, broader
/// than the normal kernel), linear in the size.
fn widening(ch: usize, size_mm: f64, t: f64) -> f64 {
    let w = 45.0 + 3.0 * ch as f64;
    let g = (-(t / w).powi(2)).exp();
    0.15 * (size_mm - 6.0) * (t / w).powi(3) * g * if ch == 0 { 1.0 } else { 0.4 }
}

/// A training contact pressed by an indenter of known size: column, local
/// force, size (mm), profiles (u, v).
type SizedTraining = (f64, [f64; 3], f64, [Vec<f64>; 2]);

/// Profiles of one contact at `c` with local force `f`, pressed by an
/// indenter of `size_mm`.
fn sized_profiles(c: f64, f: [f64; 3], size_mm: f64) -> [Vec<f64>; 2] {
    let mut p = profiles(&[c], &[f]);
    for (ch, prof) in p.iter_mut().enumerate() {
        for (j, v) in prof.iter_mut().enumerate() {
            *v += f[2] * widening(ch, size_mm, cell(j) - c);
        }
    }
    p
}

/// Why the size term: with indenters of 2, 5 and 10 mm, one normal kernel
/// fits their mean footprint and reads the others' normal force off by
/// several percent; with the size term the match recovers the normal force
/// of any size, one it was not trained on included.
#[test]
fn the_size_term_reads_the_normal_force_of_any_indenter() {
    let mut rng = SplitMix64::new(21);
    let set: Vec<SizedTraining> = (0..150)
        .map(|i| {
            let c = cell(75 + (250.0 * rng.next_f64()) as usize);
            let f = [
                rng.next_f64() - 0.5,
                0.2 * (rng.next_f64() - 0.5),
                -0.5 - 2.5 * rng.next_f64(),
            ];
            let size = [2.0, 5.0, 10.0][i % 3];
            (c, f, size, sized_profiles(c, f, size))
        })
        .collect();
    let samples: Vec<ProfileSample<'_>> = set
        .iter()
        .map(|(c, f, size, p)| ProfileSample {
            column_px: *c,
            profile_u: &p[0],
            profile_v: &p[1],
            scale: SCALE,
            local_force: *f,
            size_mm: Some(*size),
        })
        .collect();
    let term = SizeTerm::for_sizes(set.iter().map(|s| s.2)).unwrap();
    assert!(
        (term.centre_mm - 17.0 / 3.0).abs() < 0.1 && term.scale_mm == 4.0,
        "{term:?}"
    );
    let sized =
        ProfileModel::fit_with_size(&samples, SCALE, 200.0, 1, CENTRE, SPAN, Some(term)).unwrap();
    let plain = ProfileModel::fit(&samples, SCALE, 200.0, 1, CENTRE, SPAN).unwrap();
    assert_eq!(sized.kernels[0].len(), 4 * 2);
    assert_eq!(plain.kernels[0].len(), 3 * 2);
    let mut m = ForceMatcher::new();
    let mut out = Vec::new();
    let (mut worst_sized, mut worst_plain) = (0.0f64, 0.0f64);
    for (c, size) in [
        (cell(140), 2.0),
        (cell(260), 10.0),
        (cell(201), 3.5),
        (cell(177), 8.0),
    ] {
        let f = [0.25, -0.03, -2.4];
        let p = sized_profiles(c, f, size);
        m.measure(&sized, &[c], &p[0], &p[1], SCALE, &mut out)
            .unwrap();
        worst_sized = worst_sized.max((out[0][2] - f[2]).abs());
        m.measure(&plain, &[c], &p[0], &p[1], SCALE, &mut out)
            .unwrap();
        worst_plain = worst_plain.max((out[0][2] - f[2]).abs());
    }
    assert!(
        worst_sized < 1e-6,
        "with the size term: {worst_sized} N off"
    );
    assert!(worst_plain > 0.05, "without it: only {worst_plain} N off");
    // The term survives a file round trip; older files have none.
    let back: ProfileModel = serde_json::from_str(&serde_json::to_string(&sized).unwrap()).unwrap();
    assert_eq!(back.size, Some(term));
    assert!(!serde_json::to_string(&plain).unwrap().contains("size"));
    // A term without its kernels, or with a bad scale, is refused on load.
    let mut broken = plain.clone();
    broken.size = Some(term);
    assert!(broken.validate().is_err());
    let mut bad_scale = sized.clone();
    bad_scale.size = Some(SizeTerm {
        centre_mm: 5.0,
        scale_mm: 0.0,
    });
    assert!(bad_scale.validate().is_err());
}

#[test]
fn the_size_term_needs_sizes_that_vary_and_every_sample_sized() {
    assert_eq!(SizeTerm::for_sizes([5.0, 5.0, 5.0]), None);
    assert_eq!(SizeTerm::for_sizes([]), None);
    assert_eq!(SizeTerm::for_sizes([2.0, f64::NAN]), None);
    assert_eq!(SizeTerm::for_sizes([2.0, -1.0]), None);
    let set = training_set(5);
    let unsized_samples = samples(&set, None);
    let term = SizeTerm {
        centre_mm: 5.0,
        scale_mm: 3.0,
    };
    let err =
        ProfileModel::fit_with_size(&unsized_samples, SCALE, 200.0, 1, CENTRE, SPAN, Some(term))
            .unwrap_err();
    assert!(matches!(err, Error::InvalidParameter { .. }), "{err}");
    assert!(err.to_string().contains("size"), "{err}");
}

/// A contact's match column searched from a misplaced start: where the
/// profile's motion is, to the pixel.
#[test]
fn relocation_puts_back_a_misplaced_point() {
    let model = fit(&training_set(4), 1);
    // Reach 200 px: a search radius of 25 px, moves of 4.2 px or more.
    let radius = optical_tactile::contact::profile::RELOCATE_RADIUS_OF_REACH * model.reach_px();
    assert!((radius - 25.0).abs() < 1e-9);
    let truth = 401.0;
    let force = [0.5, 0.02, -2.0];
    let p = profiles(&[truth], &[force]);
    let mut m = ForceMatcher::new();
    for start in [truth + 20.0, truth - 17.0, truth + 9.0] {
        let mut cols = [start];
        m.relocate(&model, &mut cols, &p[0], &p[1], SCALE).unwrap();
        assert!((cols[0] - truth).abs() <= 1.0, "{start} -> {}", cols[0]);
    }
    // A neighbour at its place stays, while the misplaced one moves.
    let both = [truth, 640.0];
    let p = profiles(&both, &[force, [-0.2, 0.0, -1.2]]);
    let mut cols = [truth + 18.0, 640.0];
    m.relocate(&model, &mut cols, &p[0], &p[1], SCALE).unwrap();
    assert!((cols[0] - truth).abs() <= 1.0, "{cols:?}");
    assert_eq!(cols[1], 640.0);
    // Contacts too far apart for their kernels to meet: each is searched
    // on its own (the other's unknowns have no equation near it).
    let far = [161.0, 641.0];
    let p = profiles(&far, &[force, [-0.2, 0.0, -1.2]]);
    let mut cols = [far[0], far[1] - 19.0];
    m.relocate(&model, &mut cols, &p[0], &p[1], SCALE).unwrap();
    assert_eq!(cols[0], far[0]);
    assert!((cols[1] - far[1]).abs() <= 1.0, "{cols:?}");
}

/// A point at its place, or a few pixels off, is left alone, even on a
/// noisy profile; a point farther off than the radius is not searched for.
#[test]
fn relocation_leaves_a_well_placed_point() {
    let model = fit(&training_set(5), 1);
    let truth = 383.0;
    let mut p = profiles(&[truth], &[[-0.3, 0.0, -1.5]]);
    let mut rng = SplitMix64::new(9);
    for x in p.iter_mut().flatten() {
        *x += 0.02 * (rng.next_f64() - 0.5);
    }
    let mut m = ForceMatcher::new();
    for start in [truth, truth + 3.0, truth - 2.0] {
        let mut cols = [start];
        m.relocate(&model, &mut cols, &p[0], &p[1], SCALE).unwrap();
        assert_eq!(cols[0], start);
    }
    // 60 px off: the right column is beyond the search, and no column
    // within it explains the motion 30% better than the start does.
    let mut cols = [truth + 60.0];
    m.relocate(&model, &mut cols, &p[0], &p[1], SCALE).unwrap();
    assert!((cols[0] - truth).abs() >= 30.0, "{cols:?}");
}

/// The slow twin of the best relocation: the residual sum of squares of a
/// single contact's match at column `c`, over every cell of `window`
/// (both channels), solved by SVD.
fn residual_oracle(model: &ProfileModel, c: f64, p: &[Vec<f64>; 2], window: (f64, f64)) -> f64 {
    let comps = model.kernels[0].len() / (model.degree + 1);
    let mut rows = Vec::new();
    let mut rhs = Vec::new();
    for (ch, prof) in p.iter().enumerate() {
        for (j, &y) in prof.iter().enumerate() {
            let x = cell(j);
            if x < window.0 || x > window.1 {
                continue;
            }
            rows.push(
                (0..comps)
                    .map(|k| kernel_value(model, ch, c, x - c, k))
                    .collect::<Vec<_>>(),
            );
            rhs.push(y);
        }
    }
    let a = DMatrix::from_fn(rows.len(), comps, |i, j| rows[i][j]);
    let b = DVector::from_vec(rhs);
    let x = a.clone().svd(true, true).solve(&b, 1e-12).unwrap();
    (&a * x - b).norm_squared()
}

/// With [`Relocation::Best`] the match column goes where the motion fits
/// best, to a fraction of a pixel, from any start within the search
/// radius, a start a pixel or two off included (which [`Relocation::Clear`]
/// leaves alone); on a noisy profile it lands where a scan of the
/// residual every 0.02 px puts the minimum.
#[test]
fn best_relocation_finds_the_column_to_a_fraction_of_a_pixel() {
    let clear = fit(&training_set(4), 1);
    let best = ProfileModel {
        relocation: Relocation::Best,
        ..clear.clone()
    };
    let radius = optical_tactile::contact::profile::RELOCATE_RADIUS_OF_REACH * best.reach_px();
    let force = [0.4, 0.02, -1.8];
    let mut m = ForceMatcher::new();
    for truth in [401.3, 388.75, 412.5] {
        let p = profiles(&[truth], &[force]);
        for start in [truth + 1.5, truth - 2.4, truth + 11.0, truth - 20.0] {
            let mut cols = [start];
            m.relocate(&best, &mut cols, &p[0], &p[1], SCALE).unwrap();
            assert!(
                (cols[0] - truth).abs() < 0.05,
                "{truth}: {start} -> {}",
                cols[0]
            );
            if (start - truth).abs() < 3.0 {
                let mut cols = [start];
                m.relocate(&clear, &mut cols, &p[0], &p[1], SCALE).unwrap();
                assert_eq!(cols[0], start, "clear moves only a misplaced point");
            }
        }
    }
    // Noise: the minimum of the residual is no longer the truth; the
    // search finds the residual's minimum.
    let truth = 395.6;
    let mut p = profiles(&[truth], &[force]);
    let mut rng = SplitMix64::new(17);
    for x in p.iter_mut().flatten() {
        *x += 0.05 * (rng.next_f64() - 0.5);
    }
    for start in [truth + 6.3, truth - 4.1] {
        let mut cols = [start];
        m.relocate(&best, &mut cols, &p[0], &p[1], SCALE).unwrap();
        let reach = best.reach_px() + radius;
        let window = (start - reach, start + reach);
        let scan = (0..=((2.0 * radius / 0.02) as usize))
            .map(|i| start - radius + 0.02 * i as f64)
            .map(|c| (c, residual_oracle(&best, c, &p, window)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert!(
            (cols[0] - scan.0).abs() < 0.1,
            "from {start}: search {} against the scan's {} (truth {truth})",
            cols[0],
            scan.0
        );
        assert!((cols[0] - start).abs() <= radius);
    }
    // Two contacts, close (kernels overlapping) or far apart (each one's
    // window holding the other's far motion): each found where it is,
    // the other's motion taken out at its own column.
    let set = tailed_training_set(4);
    let tailed = ProfileModel::fit(&samples(&set, None), SCALE, 200.0, 1, CENTRE, SPAN)
        .unwrap()
        .with_tail(&samples(&set, None), SCALE, 800.0)
        .unwrap();
    let tailed_best = ProfileModel {
        relocation: Relocation::Best,
        ..tailed.clone()
    };
    let forces = [[0.3, 0.02, -2.5], [-0.2, 0.0, -1.2]];
    for truths in [[300.3, 470.7], [cell(80) + 0.4, cell(300) + 0.3]] {
        let p = profiles_of(tailed_response, &truths, &forces);
        let start = [truths[0] + 2.5, truths[1] - 3.2];
        let mut cols = start;
        m.relocate(&tailed_best, &mut cols, &p[0], &p[1], SCALE)
            .unwrap();
        for (c, t) in cols.iter().zip(&truths) {
            assert!((c - t).abs() < 0.1, "{truths:?}: {start:?} -> {cols:?}");
        }
        let mut cols = start;
        m.relocate(&tailed, &mut cols, &p[0], &p[1], SCALE).unwrap();
        assert_eq!(cols, start, "clear leaves points a few pixels off");
    }
    // The setting is kept in files; older files (without it) and the
    // default are `Clear`, which is not written.
    let json = serde_json::to_string(&best).unwrap();
    assert!(json.contains(r#""relocation":"best""#), "{json}");
    let back: ProfileModel = serde_json::from_str(&json).unwrap();
    assert_eq!(back.relocation, Relocation::Best);
    let old = serde_json::to_string(&clear).unwrap();
    assert!(!old.contains("relocation"));
    let back: ProfileModel = serde_json::from_str(&old).unwrap();
    assert_eq!(back.relocation, Relocation::Clear);
    let unknown = json.replace(r#""relocation":"best""#, r#""relocation":"sometimes""#);
    assert!(serde_json::from_str::<ProfileModel>(&unknown).is_err());
}

/// `relocate_contacts` moves the patch's measured point by the column's
/// move; the forces matched after it are the contact's.
#[test]
fn relocated_contacts_then_match_their_forces() {
    use ndarray::Array2;
    use optical_tactile::contact::RawContact;
    let model = fit(&training_set(6), 1);
    let truth = 421.0;
    let force = [0.4, 0.0, -1.8];
    let p = profiles(&[truth], &[force]);
    // A one-row flow whose column profiles are `p`.
    let u = Array2::from_shape_fn((1, N), |(_, j)| (p[0][j] / SCALE) as f32);
    let v = Array2::from_shape_fn((1, N), |(_, j)| (p[1][j] / SCALE) as f32);
    let mut raws = [RawContact {
        x_px: truth - 22.0,
        ..Default::default()
    }];
    let mut m = ForceMatcher::new();
    let moved = m
        .relocate_contacts(&model, &mut raws, u.view(), v.view(), SCALE, |r| Ok(r.x_px))
        .unwrap();
    assert_eq!(moved, 1);
    assert!((raws[0].x_px - truth).abs() <= 1.0, "{}", raws[0].x_px);
    m.measure_contacts(&model, &mut raws, u.view(), v.view(), SCALE)
        .unwrap();
    let f = raws[0].local_force.unwrap();
    for k in 0..3 {
        // f32 profiles and a column within a pixel: within 5% of the load.
        assert!((f[k] - force[k]).abs() < 0.05 * 1.8, "{f:?} vs {force:?}");
    }
    // Bad input is an error, not a panic.
    let mut cols = [f64::NAN];
    assert!(m.relocate(&model, &mut cols, &p[0], &p[1], SCALE).is_err());
    let mut cols = [truth];
    assert!(
        m.relocate(&model, &mut cols, &p[0], &p[1][..10], SCALE)
            .is_err()
    );
    assert!(m.relocate(&model, &mut cols, &p[0], &p[1], 0.0).is_err());
    let short = Array2::<f32>::zeros((1, 3));
    assert!(
        m.relocate_contacts(&model, &mut raws, u.view(), short.view(), SCALE, |r| Ok(
            r.x_px
        ))
        .is_err()
    );
}

/// A press as the strip's camera sees it: the normal load (a press is
/// negative) spreads the markers apart about the load line, its slope a
/// wide, flat-topped peak there (a wide rod); the tangential load moves
/// them one way, an even bump narrower than that peak.
fn press_response(ch: usize, k: usize, c: f64, t: f64) -> f64 {
    let z = (c - CENTRE) / SPAN;
    let w = [24.0, 30.0, 45.0][k];
    let g = (-(t / w).powi(2)).exp();
    let shape = match k {
        0 => g,
        1 => g * (1.0 + t / w),
        _ => -t / w * g,
    };
    let gain = if ch == 0 {
        [1.0, 0.1, 1.0]
    } else {
        [0.1, 1.0, 0.1]
    };
    (1.0 + 0.3 * z) * shape * gain[k]
}

/// Why columns are measured again without the tangential motion: the
/// tangential bump's slope rises beside the load line and pulls the slope
/// peak off it (on the simulated strip by up to 26 px under a pitched
/// 10 mm rod); less the bump matched at the contact's match column (here
/// on the load line, as a calibrated location puts it), the slope peaks
/// at the load line again, and the forces are matched there.
#[test]
fn shear_free_columns_put_a_sheared_press_back_on_its_load_line() {
    use optical_tactile::contact::{ContactLocator, RawContact};
    let mut model = fit(&training_set_of(press_response, (75, 250), 12), 1);
    let sigma = 8.0;
    let mut locator = ContactLocator::new();
    let mut m = ForceMatcher::new();
    for (truth, force) in [
        (cell(200), [0.9, 0.0, -2.0]),
        (413.3, [-0.7, 0.05, -1.5]),
        (cell(150), [0.5, 0.0, -0.8]),
    ] {
        let p = profiles_of(press_response, &[truth], &[force]);
        let mut plain = [truth];
        locator.slope_peak_in_profile(&p[0], &mut plain, SCALE, sigma, 1e6);
        assert!((plain[0] - truth).abs() > 8.0, "{truth}: {plain:?}");
        let mut raws = [RawContact {
            x_px: plain[0],
            ..Default::default()
        }];
        let mut run = |model: &ProfileModel, raws: &mut [RawContact]| {
            m.shear_free_columns_of_profiles(model, raws, &p[0], &p[1], SCALE, sigma, |_| Ok(truth))
                .unwrap()
        };
        // Without the flag nothing moves.
        model.shear_free_columns = false;
        assert_eq!(run(&model, &mut raws), 0);
        assert_eq!(raws[0].x_px, plain[0]);
        model.shear_free_columns = true;
        assert_eq!(run(&model, &mut raws), 1);
        assert!(
            (raws[0].x_px - truth).abs() < 0.5,
            "{truth}: {}",
            raws[0].x_px
        );
        let f = raws[0].local_force.unwrap();
        for k in 0..3 {
            assert!((f[k] - force[k]).abs() < 0.02, "{f:?} vs {force:?}");
        }
    }
}
