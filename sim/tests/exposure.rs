//! The camera's exposure changes: off by default (frames bit-identical),
//! steps and drift as specified, bad values refused.

use optical_tactile_sim::{ExposureChanges, SimConfig, SyntheticSensor};

fn steps() -> ExposureChanges {
    ExposureChanges {
        step_every: 10,
        step_gain: 0.03,
        step_offset: 1.0,
        step_levels: 2,
        ..ExposureChanges::default()
    }
}

#[test]
fn no_changes_by_default_and_frames_stay_bit_identical() {
    let e = ExposureChanges::default();
    assert!(!e.is_active());
    assert_eq!(e.response(1, 12345), (1.0, 0.0));
    let mut cfg = SimConfig::default();
    cfg.markers.count = Some(2000);
    let a = SyntheticSensor::new(cfg, 3).unwrap();
    // Steps of zero size change nothing either.
    let mut zero = steps();
    zero.step_gain = 0.0;
    zero.step_offset = 0.0;
    cfg.noise.exposure = zero;
    let b = SyntheticSensor::new(cfg, 3).unwrap();
    for k in [0, 7, 31] {
        let fa = a.render_indexed(k, &[], false).unwrap().frame;
        let fb = b.render_indexed(k, &[], false).unwrap().frame;
        assert_eq!(fa, fb, "frame {k}");
    }
}

#[test]
fn steps_stay_within_their_levels_and_change_only_at_their_frames() {
    let e = steps();
    let levels: Vec<i64> = (0..400).map(|k| e.level(9, k)).collect();
    assert!(levels.iter().all(|l| l.abs() <= 2));
    assert_eq!(levels[0], 0);
    for k in 1..400 {
        if k % 10 != 0 {
            assert_eq!(levels[k], levels[k - 1], "frame {k}");
        } else {
            assert_eq!((levels[k] - levels[k - 1]).abs(), 1, "frame {k}");
        }
    }
    // Both directions happen.
    assert!(levels.iter().any(|&l| l > 0) && levels.iter().any(|&l| l < 0));
    let (g, o) = e.response(9, 125);
    let l = e.level(9, 125) as f32;
    assert!((g - (1.0 + 0.03 * l)).abs() < 1e-6 && (o - l).abs() < 1e-6);
}

#[test]
fn a_brighter_exposure_brightens_the_frame_by_its_gain_and_offset() {
    let mut cfg = SimConfig::default();
    cfg.markers.count = Some(3000);
    cfg.noise.shot = 0.0;
    cfg.noise.read = 0.0;
    cfg.noise.flicker = 0.0;
    let plain = SyntheticSensor::new(cfg, 2).unwrap();
    let e = ExposureChanges {
        drift_gain: 0.1,
        drift_offset: 4.0,
        drift_period: 40.0,
        ..ExposureChanges::default()
    };
    cfg.noise.exposure = e;
    let drifting = SyntheticSensor::new(cfg, 2).unwrap();
    // A quarter period in: gain 1.1, offset 4.
    let (g, o) = e.response(2, 10);
    assert!((g - 1.1).abs() < 1e-6 && (o - 4.0).abs() < 1e-5, "{g} {o}");
    let a = plain.render_indexed(10, &[], false).unwrap().frame;
    let b = drifting.render_indexed(10, &[], false).unwrap().frame;
    let mut worst = 0.0f32;
    for (&x, &y) in a.iter().zip(b.iter()) {
        if x < 200.0 {
            // Both rounded to whole grey levels: within 0.5 + 0.5 g of the
            // exact map.
            worst = worst.max((y - (x * g + o)).abs());
        }
    }
    assert!(worst <= 0.5 + 0.5 * g + 1e-3, "{worst}");
}

#[test]
fn bad_changes_are_refused() {
    let mut cfg = SimConfig::default();
    let mut e = steps();
    e.step_gain = 0.3; // 2 levels: 60%
    cfg.noise.exposure = e;
    assert!(SyntheticSensor::new(cfg, 1).is_err());
    let mut e = ExposureChanges {
        drift_offset: 2.0, // no period
        ..ExposureChanges::default()
    };
    cfg.noise.exposure = e;
    assert!(SyntheticSensor::new(cfg, 1).is_err());
    e.drift_period = 100.0;
    cfg.noise.exposure = e;
    assert!(SyntheticSensor::new(cfg, 1).is_ok());
    e.drift_gain = f32::NAN;
    cfg.noise.exposure = e;
    assert!(SyntheticSensor::new(cfg, 1).is_err());
}
