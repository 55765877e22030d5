//! Criterion benches of `flow::Dis` against a fixed reference: every preset
//! at 1920x1080 and on a 1600x200 strip, on 1 and 2 threads, on synthetic
//! marker frames (press-like motion up to ~5 px). `set_reference` is outside
//! the timed loop: a tactile sensor compares every frame with one fixed
//! reference. Also a short sequence of frames against that reference.
//!
//! `cargo bench --bench flow` (short measurement times; on a shared machine
//! compare ratios within one run).

#[path = "../tests/support/mod.rs"]
mod support;

use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use optical_tactile::flow::FlowField;
use optical_tactile::flow::dis::{Dis, DisPreset};

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool")
}

fn bench_presets(c: &mut Criterion) {
    let mut g = c.benchmark_group("dis");
    g.sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2));
    for (w, h, disp) in [(1920usize, 1080usize, 5.0f64), (1600, 200, 4.0)] {
        let motion = support::press_motion(w, h, disp, 3);
        let (r, cur, _) = support::marker_pair(w, h, &motion, 3);
        for preset in DisPreset::ALL {
            for threads in [1usize, 2] {
                let p = pool(threads);
                let mut dis = Dis::with_preset(preset);
                dis.set_reference(&r).expect("reference");
                let mut out = FlowField::zeros(w, h);
                let id = BenchmarkId::new(preset.name(), format!("{w}x{h}_t{threads}"));
                g.bench_function(id, |b| {
                    p.install(|| b.iter(|| dis.compute_into(&cur, &mut out).expect("flow")))
                });
            }
        }
    }
    g.finish();
}

fn bench_sequence(c: &mut Criterion) {
    // Eight frames of a press growing from 0.5 to 4 px, each against the
    // same reference: the sensor's steady state.
    let (w, h) = (1920usize, 1080usize);
    let centres = support::marker_centres(w, h, 4.5, 11);
    let reference = support::render_markers(w, h, &centres, 1.0);
    let frames: Vec<_> = (1..=8)
        .map(|k| {
            let m = support::press_motion(w, h, 0.5 * k as f64, 11);
            let moved: Vec<(f64, f64)> = centres
                .iter()
                .map(|&(x, y)| {
                    let (dx, dy) = m.at(x, y);
                    (x + dx, y + dy)
                })
                .collect();
            support::render_markers(w, h, &moved, 1.0)
        })
        .collect();
    let mut g = c.benchmark_group("dis_sequence");
    g.sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    for preset in [DisPreset::Fast, DisPreset::Accurate] {
        let p = pool(2);
        let mut dis = Dis::with_preset(preset);
        dis.set_reference(&reference).expect("reference");
        let mut out = FlowField::zeros(w, h);
        let id = BenchmarkId::new(preset.name(), format!("{w}x{h}_8frames_t2"));
        g.bench_function(id, |b| {
            p.install(|| {
                b.iter(|| {
                    for f in &frames {
                        dis.compute_into(f, &mut out).expect("flow");
                    }
                })
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench_presets, bench_sequence);
criterion_main!(benches);
