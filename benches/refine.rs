//! Criterion bench of the variational refinement (one call of `refine`, i.e. one DIS
//! pyramid level) at the level sizes that matter: 480x270 (a 1920x1080 frame at
//! scale 2, DIS FAST's finest level), 960x540 (scale 1, MEDIUM) and a 400x50 strip
//! level; 1 and 2 threads; OpenCV's parameters against the accurate ones.
//!
//! Input: Gaussian markers (sigma 1 px) moved by a smooth bump, the refinement started
//! from the true flow plus a smooth error, as DIS would hand it over. Each iteration
//! also copies the initial flow back (two plane copies, small next to the refinement).
//!
//! Run: `cargo bench --bench refine`.

use std::hint::black_box;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use ndarray::Array2;
use optical_tactile::flow::refine::{RefineParams, VariationalRefiner};

fn markers(w: usize, h: usize, shift: impl Fn(f32, f32) -> (f32, f32)) -> Array2<f32> {
    let mut img = Array2::from_elem((h, w), 200.0f32);
    let spacing = 6.0f32;
    let mut k = 0u32;
    let mut y = 3.0f32;
    while y < h as f32 {
        let mut x = 3.0f32;
        while x < w as f32 {
            k = k.wrapping_mul(1_103_515_245).wrapping_add(12_345);
            let jx = ((k >> 8) % 100) as f32 / 100.0 - 0.5;
            let jy = ((k >> 16) % 100) as f32 / 100.0 - 0.5;
            let (dx, dy) = shift(x + jx, y + jy);
            let (cx, cy) = (x + jx + dx, y + jy + dy);
            for py in (cy as isize - 4).max(0)..(cy as isize + 5).min(h as isize) {
                for px in (cx as isize - 4).max(0)..(cx as isize + 5).min(w as isize) {
                    let r2 = (px as f32 - cx).powi(2) + (py as f32 - cy).powi(2);
                    img[[py as usize, px as usize]] -= 150.0 * (-r2 / 2.0).exp();
                }
            }
            x += spacing;
        }
        y += spacing;
    }
    img
}

struct Case {
    name: String,
    i0: Array2<f32>,
    i1: Array2<f32>,
    u0: Array2<f32>,
    v0: Array2<f32>,
}

fn case(w: usize, h: usize) -> Case {
    let (cx, cy, r) = (w as f32 / 2.0, h as f32 / 2.0, (h as f32 / 4.0).max(8.0));
    let motion = move |x: f32, y: f32| {
        let (dx, dy) = ((x - cx) / r, (y - cy) / r);
        let g = 1.5 * (-(dx * dx + dy * dy) / 2.0).exp();
        (0.3 + g * dx, -0.2 + g * dy)
    };
    let i0 = markers(w, h, |_, _| (0.0, 0.0));
    let i1 = markers(w, h, motion);
    let u0 = Array2::from_shape_fn((h, w), |(y, x)| {
        motion(x as f32, y as f32).0 + 0.1 * (x as f32 / 7.0).sin()
    });
    let v0 = Array2::from_shape_fn((h, w), |(y, x)| {
        motion(x as f32, y as f32).1 + 0.1 * (y as f32 / 5.0).cos()
    });
    Case {
        name: format!("{w}x{h}"),
        i0,
        i1,
        u0,
        v0,
    }
}

fn bench(c: &mut Criterion) {
    let pools: Vec<(usize, rayon::ThreadPool)> = [1, 2]
        .into_iter()
        .map(|n| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap();
            (n, pool)
        })
        .collect();
    for (w, h) in [(480, 270), (960, 540), (400, 50)] {
        let cs = case(w, h);
        let mut group = c.benchmark_group("refine");
        group
            .sample_size(10)
            .warm_up_time(Duration::from_millis(300))
            .measurement_time(Duration::from_secs(2));
        for (pname, params) in [
            ("opencv", RefineParams::opencv()),
            ("accurate", RefineParams::accurate()),
        ] {
            for (threads, pool) in &pools {
                let mut vr = VariationalRefiner::new(params);
                vr.set_reference(cs.i0.view()).unwrap();
                let (mut u, mut v) = (cs.u0.clone(), cs.v0.clone());
                let id = BenchmarkId::new(format!("{pname}_{threads}t"), &cs.name);
                // `install` per call (a few microseconds): criterion's group cannot
                // move into the pool.
                group.bench_function(id, |b| {
                    b.iter(|| {
                        pool.install(|| {
                            u.assign(&cs.u0);
                            v.assign(&cs.v0);
                            vr.refine(cs.i1.view(), &mut u, &mut v).unwrap();
                            black_box(&u);
                        })
                    })
                });
            }
        }
        group.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
