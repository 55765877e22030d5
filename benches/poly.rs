//! Polynomial evaluation per contact (the calibrated force of docs/pipeline.md, step 9)
//! and least-squares fitting at the size of the characterization protocol.
//!
//! Run: `cargo bench --bench poly`

use std::hint::black_box;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use ndarray::{Array1, Array2};
use optical_tactile::calibration::poly::{
    CrossTerms, LeastSquares, PolySpec, Polynomial, VarGroup, fit,
};
use optical_tactile::calibration::{Calibration, SensorSetup};
use optical_tactile::frame::Roi;
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::segment::{Shape, Thresholds};

/// Deterministic pseudo-random numbers in [-1, 1).
fn lcg(state: &mut u64) -> f64 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
}

fn force_spec(a: u32, b: u32, c: u32) -> PolySpec {
    PolySpec::new(
        vec![
            VarGroup::new("displacement", &["dx", "dy", "dz"], a),
            VarGroup::new("location", &["x2d", "y2d"], b),
            VarGroup::new("d_pf", &["d_pf"], c),
        ],
        CrossTerms::MaxOfGroups,
    )
    .unwrap()
}

fn data(n: usize) -> (Array2<f64>, Array1<f64>) {
    let mut s = 1u64;
    let x = Array2::from_shape_fn((n, 6), |_| lcg(&mut s) * 100.0);
    let y = x
        .outer_iter()
        .map(|r| 0.01 * r[2] + 1e-4 * r[0] * r[3] - 2e-5 * r[2] * r[2] + 0.001 * lcg(&mut s))
        .collect();
    (x, y)
}

fn bench(c: &mut Criterion) {
    let (x, y) = data(900);
    let mut g = c.benchmark_group("poly");
    g.warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(2))
        .sample_size(30);
    for (a, b, cc) in [(1, 1, 1), (3, 2, 2), (5, 2, 2)] {
        let spec = force_spec(a, b, cc);
        let (p, _) = fit(&spec, x.view(), y.view(), &LeastSquares::default()).unwrap();
        let id = format!("6var_{a}{b}{cc}_{}terms", p.n_terms());
        let row = [12.0, -3.0, -250.0, 512.4, 101.0, 3.1];
        g.bench_function(BenchmarkId::new("evaluate", &id), |bch| {
            bch.iter(|| p.evaluate(black_box(&row)).unwrap())
        });
        let mut out = vec![0.0; x.nrows()];
        g.bench_function(BenchmarkId::new("evaluate_rows_900", &id), |bch| {
            bch.iter(|| p.evaluate_rows_into(black_box(x.view()), &mut out).unwrap())
        });
        g.bench_function(BenchmarkId::new("fit_900_rows", &id), |bch| {
            bch.iter(|| {
                fit(
                    &spec,
                    black_box(x.view()),
                    y.view(),
                    &LeastSquares::default(),
                )
                .unwrap()
            })
        });
    }

    // A whole contact: location (g1, g2) and force (gx, gy, gz of orders 3, 2, 2).
    let spec = force_spec(3, 2, 2);
    let (f, _) = fit(&spec, x.view(), y.view(), &LeastSquares::default()).unwrap();
    let g1 = Polynomial::raw(
        &["x2d"],
        (0..6).map(|e| vec![e]).collect(),
        vec![-200.0, 0.25, 1e-5, 1e-8, 1e-11, 1e-14],
    )
    .unwrap();
    let g2 = Polynomial::raw(&["y2d"], vec![vec![0], vec![1]], vec![-25.0, 0.25]).unwrap();
    let setup = SensorSetup {
        geometry: SensorGeometry::default(),
        crop: Roi::new(0, 0, 1600, 200),
        thresholds: Thresholds {
            magnitude: 1.5,
            sum: 400.0,
            erode: 5,
            dilate: 9,
            shape: Shape::Rect,
        },
        pipeline: None,
    };
    let cal = Calibration::new(setup, [g1, g2, f.clone(), f.clone(), f], None).unwrap();
    g.bench_function(
        BenchmarkId::new("calibration_contact", "location+force_322"),
        |bch| {
            bch.iter(|| {
                let l = cal.location(black_box(512.4), black_box(101.0)).unwrap();
                let f = cal
                    .force(black_box(12.0), -3.0, -250.0, 512.4, 101.0, 3.1)
                    .unwrap();
                (l, f)
            })
        },
    );
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
