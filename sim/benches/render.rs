//! Rendering speed of the synthetic sensor: a 1600x200 strip and a full
//! 1920x1080 frame, unloaded and with two rod contacts, with and without the
//! truth flow.

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};
use std::hint::black_box;
use std::time::Duration;

fn bench(c: &mut Criterion) {
    let contacts = [
        Press::rod(-20.0, [0.0, 0.0, -2.0], 5.0),
        Press::rod(20.0, [0.3, 0.0, -1.5], 5.0),
    ];
    let mut g = c.benchmark_group("sim_render");
    g.measurement_time(Duration::from_secs(3))
        .sample_size(20)
        .warm_up_time(Duration::from_millis(500));
    for (label, full) in [("1600x200", false), ("1920x1080", true)] {
        let cfg = SimConfig {
            full_frame: full,
            ..SimConfig::default()
        };
        let sensor = SyntheticSensor::new(cfg, 1).unwrap();
        g.bench_function(BenchmarkId::new("unloaded", label), |b| {
            b.iter(|| black_box(sensor.render_indexed(0, &[], false).unwrap()))
        });
        g.bench_function(BenchmarkId::new("two_rods", label), |b| {
            b.iter(|| black_box(sensor.render_indexed(1, &contacts, false).unwrap()))
        });
        g.bench_function(BenchmarkId::new("two_rods_with_flow", label), |b| {
            b.iter(|| black_box(sensor.render_indexed(1, &contacts, true).unwrap()))
        });
    }
    g.finish();
    let sensor = SyntheticSensor::new(SimConfig::default(), 1).unwrap();
    c.bench_function("sim_marker_motion/two_rods", |b| {
        b.iter(|| black_box(sensor.marker_displacements(&contacts).unwrap()))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
