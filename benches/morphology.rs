//! Erosion and dilation of a 1920x1080 mask with rectangles and ellipses of
//! size 3..31: the cost should be (nearly) flat in the kernel size.

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use optical_tactile::segment::morphology::{Mask, Morphology, StructuringElement};
use std::hint::black_box;
use std::time::Duration;

/// A thresholded-flow-like mask: a few large blobs and sparse specks.
fn mask(w: usize, h: usize) -> Mask {
    let blobs = [
        (300.0, 500.0, 80.0),
        (900.0, 300.0, 120.0),
        (1500.0, 700.0, 60.0),
        (1100.0, 900.0, 40.0),
    ];
    let mut s = 0x1234_5678u64;
    Mask::from_fn(w, h, |x, y| {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        let speck = s % 997 == 0;
        speck
            || blobs.iter().any(|&(cx, cy, r): &(f64, f64, f64)| {
                (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2) < r * r
            })
    })
}

fn bench(c: &mut Criterion) {
    let (w, h) = (1920, 1080);
    let m = mask(w, h);
    let mut morph = Morphology::new();
    let mut out = Mask::default();
    let mut g = c.benchmark_group("morphology");
    g.measurement_time(Duration::from_secs(2))
        .warm_up_time(Duration::from_millis(300))
        .sample_size(20);
    for k in [3usize, 5, 9, 15, 21, 31] {
        for (name, se) in [
            ("rect", StructuringElement::rect(k, k)),
            ("ellipse", StructuringElement::ellipse(k, k)),
        ] {
            g.bench_with_input(
                BenchmarkId::new(format!("erode_{name}"), format!("{w}x{h}_k{k}")),
                &se,
                |b, se| b.iter(|| morph.erode(black_box(&m), &mut out, se, 1).unwrap()),
            );
            g.bench_with_input(
                BenchmarkId::new(format!("dilate_{name}"), format!("{w}x{h}_k{k}")),
                &se,
                |b, se| b.iter(|| morph.dilate(black_box(&m), &mut out, se, 1).unwrap()),
            );
        }
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
