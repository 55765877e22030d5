//! Criterion bench of the profile model's per-frame work on the strip: the
//! joint force match of a frame's contacts (`ForceMatcher::measure`) and
//! the relocation search that runs before it (`ForceMatcher::relocate`),
//! the shear-free columns' second measurement and match after it
//! (`ForceMatcher::shear_free_columns`; the bench includes the first match),
//! with the shipped calibration's model (`fixtures/calibration.json`: 300 px
//! of reach, degree 2, the size term, far tails), the same model without
//! its tails and with the best relocation (`Relocation::Best`, as fitted
//! without sweeps), on a 1600-cell profile (the `fine` flow's full-resolution
//! grid) holding 1 and 4 contacts.
//!
//! The profiles are smooth made-up motion (a spreading press and a shear
//! bump per contact): the cost does not depend on the values, and the
//! relocation searches every candidate column whatever it finds.
//!
//! `profile/weights`: the confidence weights of a 1600x200 flow
//! (`ProfileWeighting::reweight_into`, the profiles of a calibration with
//! `weighted_profiles`) against the plain column sums of the same flow
//! (`column_profile_into`, u and v), and those sums with the spread
//! profile of v after them (`across_profiles_into`, the profiles of a model
//! with the spread channel), on a textured frame moved by a smooth press.
//!
//! `cargo bench --bench profile` (on a shared machine compare the two
//! functions' ratio within one run).

use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use optical_tactile::calibration::Calibration;
use optical_tactile::contact::RawContact;
use optical_tactile::contact::profile::{ForceMatcher, ProfileModel, Relocation};

const CELLS: usize = 1600;

/// Profiles (u, v) of contacts at `columns`: a spreading press (odd in the
/// offset) plus a shear bump along u, a small bump along v.
fn profiles(columns: &[f64]) -> (Vec<f64>, Vec<f64>) {
    let mut u = vec![0.0; CELLS];
    let mut v = vec![0.0; CELLS];
    for (j, (pu, pv)) in u.iter_mut().zip(v.iter_mut()).enumerate() {
        let x = j as f64;
        for &c in columns {
            let t = (x - c) / 40.0;
            let g = (-t * t).exp();
            *pu += 300.0 * t * g + 80.0 * g;
            *pv += 10.0 * g;
        }
    }
    (u, v)
}

fn bench_profile(c: &mut Criterion) {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/calibration.json");
    let cal = Calibration::load(path).expect("the shipped calibration");
    let model = cal
        .profile
        .expect("the shipped calibration has a profile model");
    let mut g = c.benchmark_group("profile");
    g.measurement_time(Duration::from_secs(3));
    g.warm_up_time(Duration::from_millis(500));
    // The same model without its far tails: what they cost; and with the
    // best relocation (a calibration fitted without sweeps).
    let mut untailed = model.clone();
    untailed.tail = None;
    let best = ProfileModel {
        relocation: Relocation::Best,
        ..model.clone()
    };
    for columns in [vec![799.5], vec![300.0, 650.0, 1000.0, 1350.0]] {
        let (pu, pv) = profiles(&columns);
        let n = columns.len();
        let mut matcher = ForceMatcher::new();
        let mut out = Vec::new();
        // The columns measured again without the tangential motion, after
        // the first match (`ForceMatcher::shear_free_columns`, a model fitted
        // with `calibrate --shear-free-columns`): its cost beside `measure`.
        let free = ProfileModel {
            shear_free_columns: true,
            ..model.clone()
        };
        let mut raws: Vec<RawContact> = columns
            .iter()
            .map(|&x_px| RawContact {
                x_px,
                ..Default::default()
            })
            .collect();
        g.bench_function(BenchmarkId::new("shear_free", format!("{n}, tails")), |b| {
            b.iter(|| {
                for (r, &c) in raws.iter_mut().zip(&columns) {
                    r.x_px = c;
                }
                matcher
                    .shear_free_columns_of_profiles(&free, &mut raws, &pu, &pv, 1.0, 8.0, |r| {
                        Ok(r.x_px)
                    })
                    .expect("shear-free columns")
            })
        });
        for (model, what) in [
            (&model, "tails"),
            (&untailed, "no tails"),
            (&best, "tails, best"),
        ] {
            let id = format!("{n}, {what}");
            g.bench_function(BenchmarkId::new("measure", &id), |b| {
                b.iter(|| {
                    matcher
                        .measure(model, &columns, &pu, &pv, 1.0, &mut out)
                        .expect("match")
                })
            });
            let mut moved = columns.clone();
            g.bench_function(BenchmarkId::new("relocate", &id), |b| {
                b.iter(|| {
                    moved.copy_from_slice(&columns);
                    matcher
                        .relocate(model, &mut moved, &pu, &pv, 1.0)
                        .expect("relocate")
                })
            });
        }
    }
    g.finish();
}

fn bench_weights(c: &mut Criterion) {
    use ndarray::Array2;
    use optical_tactile::contact::confidence::ProfileWeighting;
    use optical_tactile::contact::profile::column_profile_into;
    use optical_tactile::flow::FlowField;
    let (h, w) = (200, CELLS);
    let reference = Array2::from_shape_fn((h, w), |(i, j)| {
        let (x, y) = (j as f32, i as f32);
        120.0 + 60.0 * (0.9 * x + 0.4 * y).sin() * (0.7 * y - 0.3 * x).cos()
    });
    let press = |j: usize| {
        let t = (j as f32 - 800.0) / 40.0;
        -3.0 * t * (-t * t).exp()
    };
    let flow = FlowField {
        u: Array2::from_shape_fn((h, w), |(_, j)| press(j)),
        v: Array2::from_shape_fn((h, w), |(_, j)| 0.2 * press(j)),
    };
    // The frame the flow explains (to the nearest pixel).
    let current = Array2::from_shape_fn((h, w), |(i, j)| {
        let src = (j as f32 - press(j)).round().clamp(0.0, (w - 1) as f32) as usize;
        reference[[i, src]]
    });
    let mut g = c.benchmark_group("profile/weights");
    g.measurement_time(Duration::from_secs(3));
    g.warm_up_time(Duration::from_millis(500));
    let mut weighting = ProfileWeighting::new();
    weighting.set_reference(reference.view());
    let mut out = FlowField::zeros(0, 0);
    g.bench_function("reweight", |b| {
        b.iter(|| {
            weighting
                .reweight_into(current.view(), &flow, 1, &mut out)
                .expect("weights")
        })
    });
    let (mut pu, mut pv) = (Vec::new(), Vec::new());
    g.bench_function("plain column sums", |b| {
        b.iter(|| {
            column_profile_into(flow.u.view(), 1.0, &mut pu);
            column_profile_into(flow.v.view(), 1.0, &mut pv);
        })
    });
    g.bench_function("column sums and spread", |b| {
        b.iter(|| {
            column_profile_into(flow.u.view(), 1.0, &mut pu);
            optical_tactile::contact::profile::across_profiles_into(
                flow.v.view(),
                1.0,
                true,
                &mut pv,
            );
        })
    });
    g.finish();
}

criterion_group!(benches, bench_profile, bench_weights);
criterion_main!(benches);
