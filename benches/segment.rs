//! The whole segmentation (threshold, erode, dilate, external contours, sums,
//! margins) of a 1920x1080 flow and of a 480x270 native-level flow, one
//! thread; and its stages at 1080p; a 1080p scene whose one region the
//! split rule cuts in two, with and without the rule; and a fingertip's
//! 320x240 flow with two presses one above the other, with the flat
//! sensor's rule (which cuts them apart along the rows) and the default.

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use optical_tactile::flow::FlowField;
use optical_tactile::segment::contours::ContourFinder;
use optical_tactile::segment::morphology::{Mask, Morphology};
use optical_tactile::segment::{Segmenter, SegmenterConfig, SplitRule, Thresholds};
use std::hint::black_box;
use std::time::Duration;

/// Three presses (Gaussian shear bumps, full-res sigma 40 px, peak 8 px) on
/// low-level noise (about 0.1 px), sampled with `scale` flow pixels per
/// full-resolution pixel (values in flow pixels).
fn flow(w: usize, h: usize, scale: f32) -> FlowField {
    let mut f = FlowField::zeros(w, h);
    let mut s = 0x9E37_79B9u64;
    let bumps = [(400.0f32, 500.0f32), (1000.0, 300.0), (1500.0, 800.0)];
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = (x as f32 / scale, y as f32 / scale);
            let mut u = 0.0;
            for &(cx, cy) in &bumps {
                u += 8.0 * (-((fx - cx).powi(2) + (fy - cy).powi(2)) / (2.0 * 40.0 * 40.0)).exp();
            }
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            let n = ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.3;
            f.u[[y, x]] = (u + n) * scale;
            f.v[[y, x]] = n * scale;
        }
    }
    f
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("segment");
    g.measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_millis(300))
        .sample_size(30);
    for (w, h, sampling) in [(1920usize, 1080usize, 1.0f32), (480, 270, 0.25)] {
        let f = flow(w, h, sampling);
        let scale = 1.0 / sampling as f64;
        let mut seg = Segmenter::new(SegmenterConfig {
            thresholds: Thresholds::HIGH,
            margin: 10,
            scale,
        })
        .unwrap();
        let mut out = Vec::new();
        seg.segment_into(&f, &mut out).unwrap();
        assert_eq!(out.len(), 3, "the bench scene must have three patches");
        g.bench_function(BenchmarkId::new("segment_high", format!("{w}x{h}")), |b| {
            b.iter(|| seg.segment_into(black_box(&f), &mut out).unwrap())
        });
        let mut whole = seg.clone().with_split(None).unwrap();
        g.bench_function(
            BenchmarkId::new("segment_high_nosplit", format!("{w}x{h}")),
            |b| b.iter(|| whole.segment_into(black_box(&f), &mut out).unwrap()),
        );
        // Stages.
        let st = *seg.scaled();
        let mut raw = Mask::default();
        g.bench_function(BenchmarkId::new("threshold", format!("{w}x{h}")), |b| {
            b.iter(|| {
                raw.threshold_flow_into(black_box(&f), st.magnitude)
                    .unwrap()
            })
        });
        let mut morph = Morphology::new();
        let (mut e, mut d) = (Mask::default(), Mask::default());
        g.bench_function(BenchmarkId::new("erode_dilate", format!("{w}x{h}")), |b| {
            b.iter(|| {
                morph.erode(black_box(&raw), &mut e, &st.erode, 1).unwrap();
                morph.dilate(&e, &mut d, &st.dilate, 1).unwrap();
            })
        });
        let mut cf = ContourFinder::new();
        let mut boxes = Vec::new();
        g.bench_function(BenchmarkId::new("contours", format!("{w}x{h}")), |b| {
            b.iter(|| cf.external_boxes(black_box(&d), &mut boxes))
        });
    }
    // Two presses 60 px apart on a strip-like 1920x1080 flow, inside one
    // wide sheared region: one contour that the split rule cuts in two.
    let mut f = flow(1920, 1080, 1.0);
    for y in 0..1080 {
        for x in 0..1920 {
            let shear = 1.5 * (-((x as f32 - 960.0) / 600.0).powi(2)).exp();
            let mut u = shear;
            for c in [930.0f32, 990.0] {
                let d = x as f32 - c;
                u += 0.4 * d * (0.5 - d * d / (2.0 * 144.0)).exp() / 12.0 * 10.0;
            }
            f.u[[y, x]] += u;
        }
    }
    let mut seg = Segmenter::new(SegmenterConfig {
        thresholds: Thresholds::HIGH,
        margin: 10,
        scale: 1.0,
    })
    .unwrap();
    let mut out = Vec::new();
    seg.segment_into(&f, &mut out).unwrap();
    assert!(seg.split_count() >= 1, "the split scene must be cut");
    g.bench_function(BenchmarkId::new("flooded_split", "1920x1080"), |b| {
        b.iter(|| seg.segment_into(black_box(&f), &mut out).unwrap())
    });
    let mut whole = seg.clone().with_split(None).unwrap();
    g.bench_function(BenchmarkId::new("flooded_nosplit", "1920x1080"), |b| {
        b.iter(|| whole.segment_into(black_box(&f), &mut out).unwrap())
    });
    // Two presses (outward flow peaking 3 px on a ring of 12 px) 50 px apart
    // along the rows of a fingertip's 320x240 flow.
    let mut f = FlowField::zeros(320, 240);
    for ((y, x), u) in f.u.indexed_iter_mut() {
        for cy in [95.0f32, 145.0] {
            let (dx, dy) = (x as f32 - 160.0, y as f32 - cy);
            *u += 3.0 / 12.0 * dx * (0.5 - (dx * dx + dy * dy) / 288.0).exp();
        }
    }
    for ((y, x), v) in f.v.indexed_iter_mut() {
        for cy in [95.0f32, 145.0] {
            let (dx, dy) = (x as f32 - 160.0, y as f32 - cy);
            *v += 3.0 / 12.0 * dy * (0.5 - (dx * dx + dy * dy) / 288.0).exp();
        }
    }
    let config = SegmenterConfig {
        thresholds: Thresholds::HIGH,
        margin: 24,
        scale: 1.0,
    };
    for (name, rule) in [
        ("flat_rule", SplitRule::FLAT),
        ("default_rule", SplitRule::DEFAULT),
    ] {
        let mut seg = Segmenter::new(config)
            .unwrap()
            .with_split(Some(rule))
            .unwrap();
        seg.segment_into(&f, &mut out).unwrap();
        let expected = if rule.across { 2 } else { 1 };
        assert_eq!(out.len(), expected, "{name}: {out:?}");
        g.bench_function(BenchmarkId::new(name, "320x240"), |b| {
            b.iter(|| seg.segment_into(black_box(&f), &mut out).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
