//! Natural HHD by FFT: one decomposition per iteration on a planned size
//! (plans cached, buffers reused), on a rayon pool of one thread (`t1`) and
//! of two (`t2`): tori of `PARALLEL_MIN_CELLS` or more split their FFT
//! passes over both; smaller ones run on one thread either way.
//!
//! `cargo bench --bench hhd` (add `-- 256x256` to run one size).

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use ndarray::Array2;
use optical_tactile::hhd::{Decomposition, NaturalHhd};
use optical_tactile::hhd::{FftWorkspace, GreenConvolver};
use std::hint::black_box;
use std::time::Duration;

fn field(ny: usize, nx: usize) -> (Array2<f32>, Array2<f32>) {
    let (cy, cx) = (ny as f32 / 2.0, nx as f32 / 2.0);
    let s = 0.2 * ny.min(nx) as f32;
    let g = |i: usize, j: usize| {
        let (y, x) = (i as f32 - cy, j as f32 - cx);
        (x, y, (-(x * x + y * y) / (2.0 * s * s)).exp() / s)
    };
    let u = Array2::from_shape_fn((ny, nx), |(i, j)| {
        let (x, y, e) = g(i, j);
        x * e - 0.3 * y * e
    });
    let v = Array2::from_shape_fn((ny, nx), |(i, j)| {
        let (x, y, e) = g(i, j);
        y * e + 0.3 * x * e
    });
    (u, v)
}

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("nhhd_fft");
    group
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2))
        .sample_size(20);
    let shapes = [
        (32, 32),
        (64, 64),
        (128, 128),
        (256, 256),
        (512, 512),
        (1024, 1024),
        (60, 200),
        (50, 400),
        (100, 800),
    ];
    let pools = [1, 2].map(|n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .expect("thread pool")
    });
    for (ny, nx) in shapes {
        let (u, v) = field(ny, nx);
        let mut hhd = NaturalHhd::new();
        let mut out = Decomposition::zeros(ny, nx);
        hhd.decompose_into(u.view(), v.view(), 1.0, 1.0, &mut out)
            .unwrap();
        for pool in &pools {
            let id = format!("{ny}x{nx}_t{}", pool.current_num_threads());
            group.bench_function(BenchmarkId::from_parameter(id), |b| {
                pool.install(|| {
                    b.iter(|| {
                        hhd.decompose_into(
                            black_box(u.view()),
                            black_box(v.view()),
                            1.0,
                            1.0,
                            &mut out,
                        )
                        .unwrap();
                        black_box(&out);
                    })
                })
            });
        }
    }
    group.finish();

    // The convolution alone (FFTs, transposes, spectrum product), to see
    // how much of a decomposition the stencils and copies take.
    let mut group = c.benchmark_group("nhhd_potentials_only");
    group
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2))
        .sample_size(20);
    for (ny, nx) in [(128, 128), (256, 256), (100, 800)] {
        let (u, v) = field(ny, nx);
        let mut hhd = NaturalHhd::new();
        let mut out = Decomposition::zeros(ny, nx);
        hhd.decompose_into(u.view(), v.view(), 1.0, 1.0, &mut out)
            .unwrap();
        let conv = hhd.prepare(ny, nx, 1.0, 1.0).unwrap();
        let mut ws = FftWorkspace::new();
        let (div, curl) = (out.div.clone(), out.curl.clone());
        group.bench_function(BenchmarkId::from_parameter(format!("{ny}x{nx}")), |b| {
            b.iter(|| {
                conv.potentials(
                    &mut ws,
                    div.view(),
                    curl.view(),
                    &mut out.potential_d,
                    &mut out.potential_r,
                )
                .unwrap();
                black_box(&out.potential_d);
            })
        });
    }
    group.finish();

    // Planning a new torus (Green's spectrum; the FFT planner is reused as in
    // NaturalHhd): what a cache miss costs when patch sizes change.
    let mut group = c.benchmark_group("nhhd_plan");
    group
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(2))
        .sample_size(10);
    let mut planner = rustfft::FftPlanner::new();
    // 100x800: a patch as tall and as wide as the strip at the analysis scale.
    for (ny, nx) in [(60, 200), (128, 128), (256, 256), (100, 800)] {
        group.bench_function(BenchmarkId::from_parameter(format!("{ny}x{nx}")), |b| {
            b.iter(|| black_box(GreenConvolver::new(&mut planner, ny, nx, 1.0, 1.0).unwrap()))
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
