//! Criterion benches of `flow::Dis` against a fixed reference: every preset
//! at 1920x1080 and on a 1600x200 strip, on 1 and 2 threads, on synthetic
//! marker frames (press-like motion up to ~5 px). `set_reference` is outside
//! the timed loop: a tactile sensor compares every frame with one fixed
//! reference. Also a short sequence of frames against that reference, and
//! the torn-flow check (`FlowField::stretched_fraction`) over a strip
//! contact's box of 900x200 px beside the `fine` flow of the whole strip it
//! is read from (the ratio is what it adds to a frame's flow).
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

fn bench_stretch(c: &mut Criterion) {
    use optical_tactile::frame::Roi;
    let (w, h) = (1600usize, 200usize);
    let motion = support::press_motion(w, h, 4.0, 5);
    let (r, cur, _) = support::marker_pair(w, h, &motion, 5);
    let mut dis = Dis::with_preset(DisPreset::Fine);
    dis.set_reference(&r).expect("reference");
    let mut out = FlowField::zeros(w, h);
    dis.compute_into(&cur, &mut out).expect("flow");
    let mut g = c.benchmark_group("stretched_fraction");
    g.sample_size(20)
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(2));
    let p = pool(1);
    g.bench_function("fine_flow_1600x200_t1", |b| {
        p.install(|| b.iter(|| dis.compute_into(&cur, &mut out).expect("flow")))
    });
    let cells = Roi::new(350, 0, 900, 200);
    g.bench_function("box_900x200_lag8", |b| {
        b.iter(|| std::hint::black_box(out.stretched_fraction(cells, 1, 8, 0.2, 0.75)))
    });
    g.finish();
}

criterion_group!(benches, bench_presets, bench_sequence, bench_stretch);
criterion_main!(benches);
