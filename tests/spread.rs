//! The profile model's spread channel: the across motion's first moment
//! about the middle row, against a written-out sum; kernels fitted and
//! matched on three channels; what the channel buys when the match column
//! is a little off; and profiles or files that do not fit the model.

use ndarray::Array2;
use optical_tactile::contact::profile::{
    ForceMatcher, ProfileModel, ProfileSample, SPREAD_WEIGHT, across_profiles_into,
    column_profile_into, spread_profile_into,
};
use optical_tactile_sim::rng::SplitMix64;

#[path = "common/synthetic.rs"]
mod synthetic;

const N: usize = 300; // profile cells
const SCALE: f64 = 2.0; // full-resolution pixels per cell
const CENTRE: f64 = 299.5;
const SPAN: f64 = 300.0;

/// The true response of channel `ch` (0: along x, 1: the across sums, 2:
/// the spread) to force component `k` of a contact at column `c`, at offset
/// `t` pixels. Along x the tangential response is an even bump and the
/// normal one odd, with the bump close to the normal response shifted by a
/// few pixels (as on the strip, where the two are hard to tell apart); the
/// spread answers the normal force alone.
fn response(ch: usize, k: usize, c: f64, t: f64) -> f64 {
    let z = (c - CENTRE) / SPAN;
    let w = 30.0;
    let g = (-(t / w).powi(2)).exp();
    let shape = match (ch, k) {
        (0, 0) => g,
        (0, 1) => 0.05 * g * t / w,
        (0, _) => t / w * g,
        (1, 1) => g,
        (1, _) => 0.0,
        (_, 2) => -0.4 * g,
        _ => 0.0,
    };
    (1.0 + 0.2 * z) * shape
}

/// The profiles of contacts at `cols` with local forces `forces`: along x,
/// and across with (or without) the spread after the sums.
fn profiles(cols: &[f64], forces: &[[f64; 3]], spread: bool) -> [Vec<f64>; 2] {
    let [u, mut v, s] = synthetic::channel_profiles(N, SCALE, response, cols, forces);
    if spread {
        v.extend_from_slice(&s);
    }
    [u, v]
}

/// 100 training contacts on cell centres of cells 60..240.
fn training(seed: u64, spread: bool) -> Vec<(f64, [f64; 3], [Vec<f64>; 2])> {
    let mut rng = SplitMix64::new(seed);
    (0..100)
        .map(|_| {
            let c = (60.0 + (180.0 * rng.next_f64()).floor() + 0.5) * SCALE - 0.5;
            let f = [
                rng.next_f64() - 0.5,
                0.2 * (rng.next_f64() - 0.5),
                -0.5 - 2.5 * rng.next_f64(),
            ];
            (c, f, profiles(&[c], &[f], spread))
        })
        .collect()
}

fn fit(spread: bool) -> ProfileModel {
    let set = training(3, spread);
    let samples: Vec<ProfileSample<'_>> = set
        .iter()
        .map(|(c, f, p)| ProfileSample {
            column_px: *c,
            profile_u: &p[0],
            profile_v: &p[1],
            scale: SCALE,
            local_force: *f,
            size_mm: None,
        })
        .collect();
    ProfileModel::fit(&samples, SCALE, 150.0, 1, CENTRE, SPAN).unwrap()
}

proptest::proptest! {
    #![proptest_config(proptest::test_runner::Config {
        cases: 32,
        rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
        rng_seed: proptest::test_runner::RngSeed::Fixed(5),
        failure_persistence: None,
        ..Default::default()
    })]
    #[test]
    fn the_spread_profile_is_the_written_out_moment(
        h in 1usize..9,
        w in 1usize..7,
        scale in 0.5f64..4.0,
        values in proptest::collection::vec(-5.0f32..5.0, 64),
    ) {
        let v = Array2::from_shape_fn((h, w), |(y, x)| values[(y * w + x) % values.len()]);
        let mut got = Vec::new();
        spread_profile_into(v.view(), scale, &mut got);
        proptest::prop_assert_eq!(got.len(), w);
        for (x, g) in got.iter().enumerate() {
            let mut want = 0.0;
            for y in 0..h {
                let weight = SPREAD_WEIGHT * (y as f64 - (h as f64 - 1.0) / 2.0) / (h as f64 / 2.0);
                want += weight * f64::from(v[[y, x]]) * scale;
            }
            proptest::prop_assert!((g - want).abs() <= 1e-9 * (1.0 + want.abs()), "column {}: {} against {}", x, g, want);
        }
        // The across profiles: the sums, then the moments.
        let (mut sums, mut both) = (Vec::new(), Vec::new());
        column_profile_into(v.view(), scale, &mut sums);
        across_profiles_into(v.view(), scale, true, &mut both);
        proptest::prop_assert_eq!(&both[..w], &sums[..]);
        proptest::prop_assert_eq!(&both[w..], &got[..]);
        across_profiles_into(v.view(), scale, false, &mut both);
        proptest::prop_assert_eq!(&both, &sums);
    }
}

#[test]
fn a_shift_across_has_no_spread_and_a_squeeze_no_sum() {
    // The gel moved across as a whole (a load across the strip): the
    // moment cancels. Squeezed out sideways from the middle row (a press):
    // the sum cancels, the moment does not.
    let (h, w) = (40, 5);
    let shift = Array2::from_elem((h, w), 0.7f32);
    let squeeze = Array2::from_shape_fn((h, w), |(y, _)| 0.05 * (y as f32 - 19.5));
    let (mut sums, mut moments) = (Vec::new(), Vec::new());
    spread_profile_into(shift.view(), 1.0, &mut moments);
    assert!(moments.iter().all(|m| m.abs() < 1e-9), "{moments:?}");
    column_profile_into(squeeze.view(), 1.0, &mut sums);
    spread_profile_into(squeeze.view(), 1.0, &mut moments);
    assert!(sums.iter().all(|s| s.abs() < 1e-6), "{sums:?}");
    assert!(moments.iter().all(|m| *m > 1.0), "{moments:?}");
}

#[test]
fn the_spread_channel_is_fitted_and_matched() {
    let model = fit(true);
    assert!(model.spread);
    assert_eq!(model.channels(), 3);
    assert_eq!(model.kernels.len(), 3);
    // Without the spread in the samples, two channels as before.
    let plain = fit(false);
    assert!(!plain.spread);
    assert_eq!(plain.kernels.len(), 2);
    // A contact at an unseen cell centre reads its own force.
    let (c, f) = ((201.0 + 0.5) * SCALE - 0.5, [0.3, -0.04, -1.9]);
    let p = profiles(&[c], &[f], true);
    let mut out = Vec::new();
    ForceMatcher::new()
        .measure(&model, &[c], &p[0], &p[1], SCALE, &mut out)
        .unwrap();
    for k in 0..3 {
        assert!(
            (out[0][k] - f[k]).abs() < 1e-6,
            "{:?} against {f:?}",
            out[0]
        );
    }
}

#[test]
fn the_spread_holds_the_normal_force_when_the_column_is_off() {
    // Matched 3 px beside the contact, the motion along x alone lets part
    // of a shifted normal response pass for a tangential one; the spread,
    // which the tangential force does not move, holds the normal force
    // closer (here 0.029 N off at 2.5 N against 0.038 N; were the channel
    // not used, the two would be the same).
    let (with, without) = (fit(true), fit(false));
    let mut m = ForceMatcher::new();
    let mut out = Vec::new();
    let (c, f) = ((150.0 + 0.5) * SCALE - 0.5, [0.0, 0.0, -2.5]);
    let p = profiles(&[c], &[f], true);
    m.measure(&with, &[c + 3.0], &p[0], &p[1], SCALE, &mut out)
        .unwrap();
    let err_with = (out[0][2] - f[2]).abs();
    m.measure(&without, &[c + 3.0], &p[0], &p[1][..N], SCALE, &mut out)
        .unwrap();
    let err_without = (out[0][2] - f[2]).abs();
    assert!(
        err_with < 0.9 * err_without,
        "normal force off by {err_with} with the spread, {err_without} without"
    );
}

#[test]
fn a_model_without_the_spread_ignores_it_and_one_with_it_needs_it() {
    let (with, without) = (fit(true), fit(false));
    let (c, f) = (277.0, [0.2, 0.0, -1.2]);
    let p = profiles(&[c], &[f], true);
    let mut m = ForceMatcher::new();
    let (mut a, mut b) = (Vec::new(), Vec::new());
    m.measure(&without, &[c], &p[0], &p[1], SCALE, &mut a)
        .unwrap();
    m.measure(&without, &[c], &p[0], &p[1][..N], SCALE, &mut b)
        .unwrap();
    assert_eq!(a, b);
    // The spread model without the spread profile: an error, no panic.
    let err = m
        .measure(&with, &[c], &p[0], &p[1][..N], SCALE, &mut a)
        .unwrap_err();
    assert!(err.to_string().contains("spread"), "{err}");
    // Nor with an across profile of another length.
    assert!(
        m.measure(&with, &[c], &p[0], &p[1][..N + 3], SCALE, &mut a)
            .is_err()
    );
    let mut col = [c];
    assert!(
        m.relocate(&with, &mut col, &p[0], &p[1][..N], SCALE)
            .is_err()
    );
    assert!(m.relocate(&with, &mut col, &p[0], &p[1], SCALE).is_ok());
}

#[test]
fn a_file_whose_channels_do_not_match_its_spread_flag_is_refused() {
    let plain = fit(false);
    let mut json: serde_json::Value = serde_json::to_value(&plain).unwrap();
    assert!(json.get("spread").is_none(), "written only when set");
    json["spread"] = serde_json::Value::Bool(true);
    let claimed: ProfileModel = serde_json::from_value(json).unwrap();
    let err = claimed.validate().unwrap_err();
    assert!(err.to_string().contains("channels"), "{err}");
    let with = fit(true);
    let mut json = serde_json::to_value(&with).unwrap();
    assert_eq!(json["spread"], serde_json::Value::Bool(true));
    json["spread"] = serde_json::Value::Bool(false);
    let denied: ProfileModel = serde_json::from_value(json).unwrap();
    assert!(denied.validate().is_err());
    // As written, it reads back the same.
    let back: ProfileModel = serde_json::from_str(&serde_json::to_string(&with).unwrap()).unwrap();
    back.validate().unwrap();
    assert_eq!(back, with);
}

#[test]
fn calibrations_of_the_strip_fit_the_spread_channel_by_default() {
    use optical_tactile::calibration::fit::FitOptions;
    use optical_tactile::geometry::SensorGeometry;
    let strip = FitOptions::for_geometry(&SensorGeometry::default());
    assert!(
        strip
            .profile
            .expect("the strip's profile model")
            .spread_channel
    );
    // Options written before the channel read as without it.
    let mut json = serde_json::to_value(strip.profile.unwrap()).unwrap();
    json.as_object_mut().unwrap().remove("spread_channel");
    let old: optical_tactile::calibration::fit::ProfileFitOptions =
        serde_json::from_value(json).unwrap();
    assert!(!old.spread_channel);
}
