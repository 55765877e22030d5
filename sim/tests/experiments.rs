//! The library side of the experiments (`sim::experiments`) on tiny inputs:
//! the sweeps' parallel bookkeeping against a sequential oracle, their
//! summaries on hand-built results, properties of the measured figures that
//! could fail (a pair 60 mm apart is told apart, a pair at 0 mm is not; the
//! minimum detectable force rises from LOW to HIGH), and bad input.
//!
//! The full measurements are `cargo run --release --example experiments`
//! (docs/results.md).

use optical_tactile::Error;
use optical_tactile::segment::Thresholds;
use optical_tactile::sensor::{ContactExtractor, ExtractorConfig};
use optical_tactile_sim::experiments::{
    INDENTERS_MM, MdfPlan, MdfResult, SpacingPlan, SpacingResult, SweepOptions, ThresholdSet,
    mdf_sweep, no_progress, pair_told_apart, rest_sweep, spacing_sweep,
};
use optical_tactile_sim::{SimConfig, SyntheticSensor};

#[path = "common/scratch.rs"]
mod scratch;

fn sensor(seed: u64) -> SyntheticSensor {
    SyntheticSensor::new(SimConfig::default(), seed).unwrap()
}

fn extractor(t: Thresholds) -> ContactExtractor {
    ContactExtractor::new(ExtractorConfig::default().with_thresholds(t)).unwrap()
}

fn only(name: &str, t: Thresholds) -> SweepOptions {
    SweepOptions {
        sets: vec![ThresholdSet {
            name: name.into(),
            thresholds: t,
        }],
        ..SweepOptions::default()
    }
}

#[test]
fn a_pair_60_mm_apart_is_told_apart_and_one_at_0_mm_is_not() {
    let s = sensor(5);
    for (name, t) in [("mid", Thresholds::MID), ("high", Thresholds::HIGH)] {
        let mut ex = extractor(t);
        for d in [2.0, 10.0] {
            assert!(
                pair_told_apart(&s, &mut ex, d, [2.0, 2.0], 60.0, 0.0, 3.0, 10, None).unwrap(),
                "{name}, {d} mm rods 60 mm apart"
            );
            assert!(
                !pair_told_apart(&s, &mut ex, d, [2.0, 2.0], 0.0, 0.0, 3.0, 12, None).unwrap(),
                "{name}, {d} mm rods at the same place"
            );
        }
    }
}

#[test]
fn a_pair_is_not_told_apart_when_the_tolerance_excludes_the_contacts() {
    // The same frames as above, judged with a tolerance far below the
    // contact location's scatter: the criterion really looks at positions.
    let s = sensor(5);
    let mut ex = extractor(Thresholds::MID);
    assert!(pair_told_apart(&s, &mut ex, 10.0, [2.0, 2.0], 60.0, 0.0, 3.0, 10, None).unwrap());
    assert!(!pair_told_apart(&s, &mut ex, 10.0, [2.0, 2.0], 60.0, 0.0, 1e-6, 10, None).unwrap());
}

#[test]
fn spacing_sweep_matches_sequential_calls() {
    let s = sensor(2);
    let o = SweepOptions::default();
    let plan = SpacingPlan {
        spacings_mm: vec![50.0, 12.0],
        forces_n: vec![2.0],
        second_force_ratio: 1.0,
        centres_mm: vec![0.0],
        tol_mm: 3.0,
    };
    let r = spacing_sweep(&s, &o, &plan, &no_progress).unwrap();
    assert_eq!(r.apart.len(), 3);
    // Oracle: the same cases one by one, with the frame indices the sweep
    // documents (2 000 000 + 2 x case, cases in indenter, force, spacing,
    // midpoint order).
    let mut far_apart = 0;
    for (k, set) in o.sets.iter().enumerate() {
        let mut ex = extractor(set.thresholds);
        for (ii, &d) in INDENTERS_MM.iter().enumerate() {
            for (si, &sp) in plan.spacings_mm.iter().enumerate() {
                let case = (ii * plan.spacings_mm.len() + si) as u64;
                let want = pair_told_apart(
                    &s,
                    &mut ex,
                    d,
                    [2.0, 2.0],
                    sp,
                    0.0,
                    3.0,
                    2_000_000 + 2 * case,
                    None,
                )
                .unwrap();
                assert_eq!(r.apart[k][ii][0][si][0], want, "{} d {d} sp {sp}", set.name);
                far_apart += usize::from(si == 0 && want);
            }
        }
    }
    // 50 mm apart at the centre: told apart by at least MID and HIGH.
    assert!(far_apart >= 2 * INDENTERS_MM.len(), "{far_apart}");
}

#[test]
fn min_spacing_needs_every_larger_spacing_force_and_midpoint() {
    let plan = SpacingPlan {
        spacings_mm: vec![40.0, 30.0, 20.0, 10.0],
        forces_n: vec![1.5, 3.0],
        second_force_ratio: 1.0,
        centres_mm: vec![-60.0, 0.0],
        tol_mm: 3.0,
    };
    // apart[spacing] per (force, centre); one indenter used, the others false.
    let mut apart = vec![vec![vec![vec![false; 2]; 4]; 2]; INDENTERS_MM.len()];
    let set = |apart: &mut Vec<Vec<Vec<Vec<bool>>>>, f: usize, c: usize, v: [bool; 4]| {
        for (si, b) in v.into_iter().enumerate() {
            apart[0][f][si][c] = b;
        }
    };
    set(&mut apart, 0, 0, [true, true, false, true]); // 10 mm after a gap
    set(&mut apart, 0, 1, [true, true, true, true]);
    set(&mut apart, 1, 0, [true, true, true, false]);
    set(&mut apart, 1, 1, [true, false, true, true]);
    let r = SpacingResult {
        sets: ThresholdSet::presets()[..1].to_vec(),
        plan,
        apart: vec![apart],
    };
    assert_eq!(r.min_spacing(0, 0, Some(0), Some(1)), Some(10.0));
    assert_eq!(r.min_spacing(0, 0, Some(0), Some(0)), Some(30.0));
    assert_eq!(r.min_spacing(0, 0, Some(1), Some(0)), Some(20.0));
    assert_eq!(r.min_spacing(0, 0, Some(1), Some(1)), Some(40.0));
    assert_eq!(r.min_spacing(0, 0, None, Some(1)), Some(40.0));
    assert_eq!(r.min_spacing(0, 0, Some(0), None), Some(30.0));
    assert_eq!(r.min_spacing(0, 0, None, None), Some(40.0));
    assert_eq!(r.min_spacing(0, 1, None, None), None);
    assert_eq!(r.count(0, 0, 1, 1), 1);
}

#[test]
fn mdf_min_force_is_the_start_of_the_detected_tail() {
    let forces = vec![0.5, 1.0, 1.5, 2.0];
    let r = MdfResult {
        sets: ThresholdSet::presets()[..1].to_vec(),
        plan: MdfPlan {
            positions_mm: vec![0.0, 40.0, 80.0, 120.0],
            forces_n: forces,
        },
        per: 20,
        // A detection at 0.5 N, a dip at 1.0 N: only the tail from 1.5 N counts.
        hits: vec![vec![
            vec![20, 18, 19, 20],
            vec![0, 20, 20, 20],
            vec![0, 0, 5, 19],
        ]],
        stray: vec![0],
    };
    assert_eq!(r.min_force(0, Some(0), 0.95), Some(1.5));
    assert_eq!(r.min_force(0, Some(0), 0.9), Some(0.5));
    assert_eq!(r.min_force(0, Some(1), 1.0), Some(1.0));
    assert_eq!(r.min_force(0, Some(2), 0.95), Some(2.0));
    assert_eq!(r.min_force(0, Some(2), 1.0), None);
    // Over every indenter: the largest, or none if one never gets there.
    assert_eq!(r.min_force(0, None, 0.95), Some(2.0));
    assert_eq!(r.min_force(0, None, 1.0), None);
    assert!((r.rate(0, 2) - 44.0 / 60.0).abs() < 1e-12);
}

#[test]
fn minimum_detectable_force_rises_from_low_to_high() {
    let s = sensor(4);
    let plan = MdfPlan {
        positions_mm: vec![80.0],
        forces_n: vec![0.25, 0.5, 1.0, 1.5, 2.0, 3.0],
    };
    let r = mdf_sweep(&s, &SweepOptions::default(), &plan, &no_progress).unwrap();
    assert_eq!(r.per, 5);
    let m: Vec<f64> = (0..3)
        .map(|k| r.min_force(k, None, 1.0).expect("every preset detects 3 N"))
        .collect();
    assert!(m[0] <= m[1] && m[1] <= m[2], "LOW, MID, HIGH: {m:?}");
    assert!(m[0] < m[2], "LOW must see less than HIGH: {m:?}");
    // The low preset sees 0.5 N presses (its minimum detectable force is below 0.5 N).
    assert!(m[0] <= 0.5, "{m:?}");
    // Detection never falls as the thresholds fall, press by press.
    for ii in 0..INDENTERS_MM.len() {
        for fi in 0..plan.forces_n.len() {
            assert!(r.hits[0][ii][fi] >= r.hits[2][ii][fi]);
        }
    }
}

#[test]
fn rest_pairs_give_no_false_contact_and_sorted_peaks() {
    let s = sensor(9);
    let r = rest_sweep(&s, &SweepOptions::default(), 4, &no_progress).unwrap();
    assert_eq!(r.false_frames, vec![0, 0, 0]);
    assert_eq!(r.false_patches, vec![0, 0, 0]);
    assert_eq!(r.peaks_px.len(), 4);
    assert!(r.peaks_px.windows(2).all(|w| w[0] <= w[1]));
    // Noise moves the flow a little, never like a press.
    assert!(
        r.peak_quantile(0.0) > 0.0 && r.peak_quantile(1.0) < 1.0,
        "{:?}",
        r.peaks_px
    );
    // The noise stays below every preset's sum threshold.
    for (k, set) in r.sets.iter().enumerate() {
        assert!(r.max_contour_sum[k] < set.thresholds.sum as f64);
    }
}

#[test]
fn bad_input_is_a_parameter_error() {
    let s = sensor(1);
    let o = SweepOptions::default();
    let no_sets = SweepOptions {
        sets: vec![],
        ..SweepOptions::default()
    };
    let is_param = |e: Error| matches!(e, Error::InvalidParameter { .. });
    assert!(is_param(rest_sweep(&s, &o, 0, &no_progress).unwrap_err()));
    assert!(is_param(
        rest_sweep(&s, &no_sets, 2, &no_progress).unwrap_err()
    ));
    let bad_t = only(
        "bad",
        Thresholds {
            magnitude: f32::NAN,
            ..Thresholds::MID
        },
    );
    assert!(rest_sweep(&s, &bad_t, 2, &no_progress).is_err());
    for plan in [
        MdfPlan {
            positions_mm: vec![0.0],
            forces_n: vec![1.0, 0.5],
        },
        MdfPlan {
            positions_mm: vec![0.0],
            forces_n: vec![],
        },
        MdfPlan {
            positions_mm: vec![1000.0],
            forces_n: vec![1.0],
        },
        MdfPlan {
            positions_mm: vec![0.0],
            forces_n: vec![f64::NAN],
        },
    ] {
        assert!(
            is_param(mdf_sweep(&s, &o, &plan, &no_progress).unwrap_err()),
            "{plan:?}"
        );
    }
    let empty = SpacingPlan {
        spacings_mm: vec![],
        ..SpacingPlan::default()
    };
    assert!(is_param(
        spacing_sweep(&s, &o, &empty, &no_progress).unwrap_err()
    ));
    let off = SpacingPlan {
        spacings_mm: vec![40.0],
        forces_n: vec![1.0],
        second_force_ratio: 1.0,
        centres_mm: vec![150.0],
        tol_mm: 3.0,
    };
    assert!(is_param(
        spacing_sweep(&s, &o, &off, &no_progress).unwrap_err()
    ));
    let mut ex = extractor(Thresholds::MID);
    assert!(is_param(
        pair_told_apart(&s, &mut ex, 5.0, [1.0, 1.0], f64::NAN, 0.0, 3.0, 0, None).unwrap_err()
    ));
    assert!(is_param(
        pair_told_apart(&s, &mut ex, 5.0, [1.0, 1.0], 20.0, 0.0, 0.0, 0, None).unwrap_err()
    ));
}

#[test]
fn touch_mapping_finds_each_rod_within_a_few_mm() {
    use optical_tactile::calibration::Calibration;
    use optical_tactile_sim::experiments::{MappingOptions, mapping_run};
    use optical_tactile_sim::scenario::Mapping;
    let cal = Calibration::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../fixtures/calibration.json"
    ))
    .unwrap();
    let (_dir_guard, dir) = scratch::tmp("experiments-mapping");
    let o = MappingOptions {
        scenario: Mapping {
            rods_x_m: vec![0.4, 0.9],
            touches: 2,
            ..Mapping::default()
        },
        ..MappingOptions::default()
    };
    let run = mapping_run(&cal, 3, &dir, &o).unwrap();
    // Two rods, two clusters, nothing else: a contact held by the tracker
    // after the body lifted off (this frame's pose, an old estimate) would
    // land 5 cm above a rod or beside it and make a false cluster.
    assert_eq!(run.clusters.len(), 2, "{run:?}");
    assert_eq!(run.false_clusters, 0);
    assert!(run.contacts >= 4, "{run:?}");
    let worst = run.worst_m().expect("both rods found");
    assert!(worst < 0.005, "{run:?}");
    assert!(run.mean_m() <= worst);
    for c in &run.clusters {
        assert!(c.spread_m < 0.005 && c.count >= 2, "{c:?}");
    }
}
