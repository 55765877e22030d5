//! The segmenter on synthetic flows: Gaussian bumps (shear) and radial
//! presses, one patch per contact, weak bumps dropped by the sum threshold,
//! close bumps cut at the valley between them (merged without one), borders
//! clamped, scales consistent; thresholds from rest recordings of synthetic
//! noise.

use optical_tactile::Error;
use optical_tactile::flow::FlowField;
use optical_tactile::segment::contours::BoundingBox;
use optical_tactile::segment::morphology::{Mask, Shape, StructuringElement};
use optical_tactile::segment::{RestOptions, Segmenter, SegmenterConfig, Thresholds};

/// A shear bump: `u = amp exp(-r^2 / 2 sigma^2)`; coordinates in full-res
/// pixels, sampled with `scale` flow pixels per full-res pixel (values in
/// flow pixels too).
fn add_shear(f: &mut FlowField, scale: f32, cx: f32, cy: f32, amp: f32, sigma: f32) {
    for ((y, x), u) in f.u.indexed_iter_mut() {
        let (fx, fy) = (
            (x as f32 + 0.5) / scale - 0.5,
            (y as f32 + 0.5) / scale - 0.5,
        );
        let r2 = (fx - cx).powi(2) + (fy - cy).powi(2);
        *u += scale * amp * (-r2 / (2.0 * sigma * sigma)).exp();
    }
}

/// A press: radial outward flow `amp (r / sigma) exp(1/2 - r^2 / 2 sigma^2)`
/// (peak `amp` on the ring `r = sigma`, zero at the centre).
fn add_press(f: &mut FlowField, cx: f32, cy: f32, amp: f32, sigma: f32) {
    let (h, w) = f.u.dim();
    for y in 0..h {
        for x in 0..w {
            let (dx, dy) = (x as f32 - cx, y as f32 - cy);
            let g = amp / sigma * (0.5 - (dx * dx + dy * dy) / (2.0 * sigma * sigma)).exp();
            f.u[[y, x]] += g * dx;
            f.v[[y, x]] += g * dy;
        }
    }
}

fn thresholds() -> Thresholds {
    Thresholds {
        magnitude: 1.0,
        sum: 1000.0,
        erode: 5,
        dilate: 11,
        shape: Shape::Rect,
    }
}

fn segmenter(margin: usize, scale: f64) -> Segmenter {
    Segmenter::new(SegmenterConfig {
        thresholds: thresholds(),
        margin,
        scale,
    })
    .unwrap()
}

fn contains(b: &BoundingBox, x0: f32, y0: f32, x1: f32, y1: f32) -> bool {
    b.x as f32 <= x0 && b.y as f32 <= y0 && b.x_end() as f32 > x1 && b.y_end() as f32 > y1
}

#[test]
fn one_patch_per_bump_containing_it() {
    let mut f = FlowField::zeros(400, 120);
    let centres = [(60.0, 60.0), (200.0, 50.0), (340.0, 70.0)];
    for &(cx, cy) in &centres {
        add_shear(&mut f, 1.0, cx, cy, 6.0, 10.0);
    }
    let mut seg = segmenter(4, 1.0);
    let p = seg.segment(&f).unwrap();
    assert_eq!(p.len(), 3, "{p:?}");
    let mut by_x = p.clone();
    by_x.sort_by_key(|p| p.bbox.x);
    for (patch, &(cx, cy)) in by_x.iter().zip(&centres) {
        // Everything above the threshold: r < sigma sqrt(2 ln 6) = 18.9.
        assert!(
            contains(&patch.core, cx - 18.0, cy - 18.0, cx + 18.0, cy + 18.0),
            "{patch:?}"
        );
        assert!(
            contains(&patch.bbox, cx - 22.0, cy - 22.0, cx + 22.0, cy + 22.0),
            "{patch:?}"
        );
        assert!(patch.bbox.width < 70 && patch.bbox.height < 70, "{patch:?}");
        // The sum of a 2-D Gaussian is 2 pi sigma^2 amp = 3770: most of it is in.
        assert!(
            patch.flow_sum > 3000.0 && patch.flow_sum < 3771.0,
            "{}",
            patch.flow_sum
        );
        assert!(patch.area > 1000 && patch.area <= patch.bbox.area());
        let (u, v) = patch.view(&f).unwrap();
        let b = patch.bbox;
        assert_eq!(u, f.u.slice(ndarray::s![b.y..b.y_end(), b.x..b.x_end()]));
        assert_eq!(v.dim(), (b.height, b.width));
        assert_eq!(patch.sub_flow(&f).unwrap().u, u);
    }
}

#[test]
fn a_weak_bump_is_dropped_by_the_sum_threshold() {
    let mut f = FlowField::zeros(300, 100);
    add_shear(&mut f, 1.0, 70.0, 50.0, 6.0, 10.0);
    // Above the magnitude threshold over a disk of radius 5.8 (survives the
    // 5x5 erosion) but sums to 2 pi 36 1.6 = 362 < 1000.
    add_shear(&mut f, 1.0, 220.0, 50.0, 1.6, 6.0);
    let mut seg = segmenter(0, 1.0);
    let p = seg.segment(&f).unwrap();
    assert_eq!(seg.contour_boxes().len(), 2);
    assert!(seg.contour_sums()[1] < 1000.0 && seg.contour_sums()[1] > 100.0);
    assert_eq!(p.len(), 1);
    assert!(p[0].bbox.contains(70, 50));
}

#[test]
fn close_bumps_are_cut_between_them_and_merge_only_without_a_valley() {
    // Overlapping masks (one contour), but two bumps with a valley of
    // convergence between them: the split rule cuts the contour in two
    // patches that touch and do not overlap.
    let mut f = FlowField::zeros(300, 100);
    add_shear(&mut f, 1.0, 110.0, 50.0, 12.0, 10.0);
    add_shear(&mut f, 1.0, 160.0, 50.0, 12.0, 10.0);
    let mut seg = segmenter(0, 1.0);
    let p = seg.segment(&f).unwrap();
    assert_eq!(seg.contour_boxes().len(), 1, "one contour");
    assert_eq!(p.len(), 2, "{p:?}");
    assert_eq!(p[0].bbox.x_end(), p[1].bbox.x);
    assert!(p[0].bbox.contains(110, 50) && p[1].bbox.contains(160, 50));
    // The pieces stay inside the contour's box (their outer sides trimmed
    // around their own peak), with its full height.
    let c = seg.contour_boxes()[0];
    for q in &p {
        assert_eq!((q.core.y, q.core.height), (c.y, c.height));
        assert!(
            q.core.x >= c.x && q.core.x_end() <= c.x_end(),
            "{q:?} {c:?}"
        );
    }
    // Without the rule: one patch, as before the rule existed.
    let whole = segmenter(0, 1.0)
        .with_split(None)
        .unwrap()
        .segment(&f)
        .unwrap();
    assert_eq!(whole.len(), 1);
    assert!(contains(&whole[0].bbox, 95.0, 40.0, 175.0, 60.0));

    // Separate contours whose boxes overlap once grown by the margin: cut at
    // the valley between them (not merged), so no flow is counted twice;
    // each patch keeps the margin on its outer side.
    let mut f = FlowField::zeros(300, 100);
    add_shear(&mut f, 1.0, 100.0, 50.0, 6.0, 10.0);
    add_shear(&mut f, 1.0, 148.0, 50.0, 6.0, 10.0);
    let apart = segmenter(0, 1.0).segment(&f).unwrap();
    assert_eq!(apart.len(), 2, "{apart:?}");
    let gap = apart[1].bbox.x - apart[0].bbox.x_end();
    assert!(gap > 0 && gap < 12, "gap {gap}");
    let mut seg = segmenter(gap, 1.0);
    let cut = seg.segment(&f).unwrap();
    assert_eq!(cut.len(), 2, "{cut:?}");
    assert_eq!(seg.split_count(), 1);
    assert_eq!(
        cut[0].bbox.x_end(),
        cut[1].bbox.x,
        "touching, not overlapping"
    );
    // The cut is where the skin converges most: for shear bumps that is
    // past the first bump's centre (its trailing lobe), not the middle of
    // the gap between the contours; each bump stays in its own patch.
    assert!(cut[0].bbox.contains(100, 50) && cut[1].bbox.contains(148, 50));
    // Outer sides: within the grown boxes (trimmed around each peak).
    assert!(cut[0].bbox.x >= apart[0].bbox.x - gap);
    assert!(cut[1].bbox.x_end() <= apart[1].bbox.x_end() + gap);
    let total = cut[0].flow_sum + cut[1].flow_sum;
    let union = cut[0].bbox.union(&cut[1].bbox);
    let merged = segmenter(gap, 1.0)
        .with_split(None)
        .unwrap()
        .segment(&f)
        .unwrap();
    assert_eq!(merged.len(), 1);
    assert_eq!(merged[0].bbox.union(&union), merged[0].bbox);
    // Disjoint pieces inside the merged box: no flow counted twice.
    assert!(total <= merged[0].flow_sum * (1.0 + 1e-9));

    // Two bumps so close that there is no valley (one wider bump): merged.
    let mut f = FlowField::zeros(300, 100);
    add_shear(&mut f, 1.0, 140.0, 50.0, 6.0, 10.0);
    add_shear(&mut f, 1.0, 152.0, 50.0, 6.0, 10.0);
    let mut seg = segmenter(10, 1.0);
    assert_eq!(seg.segment(&f).unwrap().len(), 1);
    assert_eq!(seg.split_count(), 0);
}

#[test]
fn a_press_ring_is_one_patch_and_the_border_clamps() {
    let mut f = FlowField::zeros(300, 100);
    // Magnitude zero at the centre: the mask is a ring, its hole is ignored.
    add_press(&mut f, 150.0, 50.0, 1.3, 16.0);
    // A bump cut by the left border.
    add_shear(&mut f, 1.0, 2.0, 30.0, 6.0, 10.0);
    let mut seg = segmenter(20, 1.0);
    let p = seg.segment(&f).unwrap();
    assert_eq!(p.len(), 2, "{p:?}");
    let ring = p.iter().find(|p| p.bbox.contains(150, 50)).unwrap();
    assert!(!seg.mask().get(150, 50), "the centre is a hole of the mask");
    assert!(contains(&ring.core, 135.0, 35.0, 165.0, 65.0));
    let edge = p.iter().find(|p| p.bbox.contains(2, 30)).unwrap();
    assert_eq!((edge.bbox.x, edge.bbox.y), (0, 0));
    assert!(edge.bbox.x_end() < 100);
}

#[test]
fn the_same_scene_at_quarter_scale() {
    let mut full = FlowField::zeros(480, 160);
    let mut quarter = FlowField::zeros(120, 40);
    for (cx, cy) in [(100.0, 80.0), (330.0, 70.0)] {
        add_shear(&mut full, 1.0, cx, cy, 6.0, 14.0);
        add_shear(&mut quarter, 0.25, cx, cy, 6.0, 14.0);
    }
    let a = segmenter(8, 1.0).segment(&full).unwrap();
    let b = segmenter(8, 4.0).segment(&quarter).unwrap();
    assert_eq!(a.len(), 2);
    assert_eq!(b.len(), 2);
    for (pa, pb) in a.iter().zip(&b) {
        for (va, vb) in [
            (pa.bbox.x, pb.bbox.x),
            (pa.bbox.y, pb.bbox.y),
            (pa.bbox.x_end(), pb.bbox.x_end()),
            (pa.bbox.y_end(), pb.bbox.y_end()),
        ] {
            assert!((va as f32 / 4.0 - vb as f32).abs() <= 2.0, "{pa:?} {pb:?}");
        }
        // Sums scale as s^3.
        let r = pb.flow_sum * 64.0 / pa.flow_sum;
        assert!((0.8..1.25).contains(&r), "{r}");
    }
}

#[test]
fn bad_flows_are_errors() {
    let mut seg = segmenter(0, 1.0);
    assert!(matches!(
        seg.segment(&FlowField::zeros(0, 5)),
        Err(Error::TooSmall { .. })
    ));
    let mut f = FlowField::zeros(10, 10);
    f.v[[3, 4]] = f32::NAN;
    assert!(matches!(
        seg.segment(&f),
        Err(Error::NonFinite { row: 3, col: 4, .. })
    ));
    let f = FlowField {
        u: ndarray::Array2::zeros((3, 4)),
        v: ndarray::Array2::zeros((4, 3)),
    };
    assert!(matches!(seg.segment(&f), Err(Error::ShapeMismatch { .. })));
    // A flow of one pixel, and a zero flow: no patch, no error.
    assert!(seg.segment(&FlowField::zeros(1, 1)).unwrap().is_empty());
    assert!(seg.segment(&FlowField::zeros(64, 9)).unwrap().is_empty());
    let cfg = SegmenterConfig {
        scale: -1.0,
        ..Default::default()
    };
    assert!(Segmenter::new(cfg).is_err());
}

/// Direct threshold, erosion and dilation on bytes.
fn naive_mask(f: &FlowField, t: f32, e: &StructuringElement, d: &StructuringElement) -> Mask {
    let m = Mask::from_fn(f.width(), f.height(), |x, y| {
        f.u[[y, x]].hypot(f.v[[y, x]]) > t
    });
    let morph = |m: &Mask, se: &StructuringElement, erode: bool| {
        let (ax, ay) = se.anchor();
        Mask::from_fn(m.width(), m.height(), |x, y| {
            let mut acc = erode;
            for i in 0..se.height {
                for j in 0..se.width {
                    let (xx, yy) = (
                        x as i64 + j as i64 - ax as i64,
                        y as i64 + i as i64 - ay as i64,
                    );
                    if !se.contains(i, j)
                        || xx < 0
                        || yy < 0
                        || xx >= m.width() as i64
                        || yy >= m.height() as i64
                    {
                        continue;
                    }
                    let v = m.get(xx as usize, yy as usize);
                    acc = if erode { acc && v } else { acc || v };
                }
            }
            acc
        })
    };
    morph(&morph(&m, e, true), d, false)
}

#[test]
fn the_mask_matches_the_naive_pipeline_on_noisy_bumps() {
    let mut rng = Rng(3);
    let mut seg = segmenter(0, 1.0);
    for _ in 0..5 {
        let mut f = noise(&mut rng, 150, 50, 0.5);
        for _ in 0..3 {
            let (cx, cy) = (rng.uniform() * 150.0, rng.uniform() * 50.0);
            add_shear(
                &mut f,
                1.0,
                cx,
                cy,
                2.0 + 4.0 * rng.uniform(),
                3.0 + 8.0 * rng.uniform(),
            );
        }
        seg.segment(&f).unwrap();
        let st = seg.scaled();
        assert_eq!(
            seg.mask(),
            &naive_mask(&f, st.magnitude, &st.erode, &st.dilate)
        );
    }
}

/// splitmix64 with Box-Muller normals: a fixed, dependency-free RNG.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self) -> f32 {
        ((self.next() >> 40) as f32 + 0.5) / (1u64 << 24) as f32
    }
    fn normal(&mut self) -> f32 {
        let (a, b) = (self.uniform(), self.uniform());
        (-2.0 * a.ln()).sqrt() * (std::f32::consts::TAU * b).cos()
    }
}

/// Spatially correlated noise like a flow estimator's at rest: i.i.d.
/// normals smoothed by a 3x3 box, rescaled to per-component deviation `sigma`.
fn noise(rng: &mut Rng, w: usize, h: usize, sigma: f32) -> FlowField {
    let mut f = FlowField::zeros(w, h);
    for plane in [&mut f.u, &mut f.v] {
        let raw = ndarray::Array2::from_shape_fn((h + 2, w + 2), |_| rng.normal());
        for y in 0..h {
            for x in 0..w {
                let s: f32 = raw.slice(ndarray::s![y..y + 3, x..x + 3]).sum();
                plane[[y, x]] = s / 3.0 * sigma;
            }
        }
    }
    f
}

#[test]
fn thresholds_from_rest_noise() {
    let mut rng = Rng(42);
    // Flows at DIS's level 2: 4 full-resolution pixels per flow pixel.
    let (w, h, scale) = (120, 40, 4.0);
    let opts = RestOptions {
        false_contact_rate: 0.05,
        scale,
        ..Default::default()
    };
    let rest: Vec<FlowField> = (0..40).map(|_| noise(&mut rng, w, h, 0.1)).collect();
    let t = Thresholds::from_rest(&rest, &opts).unwrap();
    // The magnitude threshold sits in the noise's tail (Rayleigh, sigma 0.1
    // level pixels: the 0.999 quantile is 0.37, times 1.25), in full-res pixels.
    assert!(t.magnitude > 0.3 * 4.0 && t.magnitude < 0.7 * 4.0, "{t:?}");
    assert!(t.sum > 0.0);
    // Twice the noise: twice the thresholds.
    let loud: Vec<FlowField> = (0..40).map(|_| noise(&mut rng, w, h, 0.2)).collect();
    let t2 = Thresholds::from_rest(&loud, &opts).unwrap();
    let r = t2.magnitude / t.magnitude;
    assert!((1.7..2.3).contains(&r), "{r}");
    // Fresh rest frames: false contacts at most at the chosen rate.
    let cfg = SegmenterConfig {
        thresholds: t,
        margin: 0,
        scale,
    };
    let mut seg = Segmenter::new(cfg).unwrap();
    let n = 200;
    let false_frames = (0..n)
        .filter(|_| !seg.segment(&noise(&mut rng, w, h, 0.1)).unwrap().is_empty())
        .count();
    assert!(
        false_frames <= n / 20,
        "{false_frames} of {n} rest frames had a contact"
    );
    // A real contact (peak 3 level pixels = 30 sigma) is found.
    let mut f = noise(&mut rng, w, h, 0.1);
    add_shear(&mut f, 0.25, 200.0, 80.0, 12.0, 20.0);
    let p = seg.segment(&f).unwrap();
    assert_eq!(p.len(), 1, "{p:?}");
    assert!(p[0].bbox.contains(50, 20));
}

#[test]
fn from_rest_rejects_bad_input() {
    let opts = RestOptions {
        false_contact_rate: 0.1,
        ..Default::default()
    };
    let ok: Vec<FlowField> = (0..10).map(|_| FlowField::zeros(20, 20)).collect();
    assert!(Thresholds::from_rest(&ok, &opts).is_ok());
    assert!(
        Thresholds::from_rest(&ok[..9], &opts).is_err(),
        "too few for a 0.1 rate"
    );
    assert!(Thresholds::from_rest(&[], &opts).is_err());
    let mut mixed = ok.clone();
    mixed[3] = FlowField::zeros(21, 20);
    assert!(matches!(
        Thresholds::from_rest(&mixed, &opts),
        Err(Error::ShapeMismatch { .. })
    ));
    let mut nan = ok.clone();
    nan[2].u[[1, 1]] = f32::NAN;
    assert!(matches!(
        Thresholds::from_rest(&nan, &opts),
        Err(Error::NonFinite { .. })
    ));
    for bad in [
        RestOptions {
            false_contact_rate: 0.0,
            ..opts
        },
        RestOptions {
            pixel_quantile: 1.0,
            ..opts
        },
        RestOptions {
            headroom: 0.5,
            ..opts
        },
        RestOptions { scale: 0.0, ..opts },
    ] {
        assert!(Thresholds::from_rest(&ok, &bad).is_err(), "{bad:?}");
    }
}

#[test]
fn property_patches_cover_every_bump_and_never_overlap() {
    use proptest::prelude::*;
    use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
    let bumps = proptest::collection::vec(
        (0.0f32..200.0, 0.0f32..80.0, 3.0f32..8.0, 5.0f32..10.0),
        1..5,
    );
    let mut runner = TestRunner::new_with_rng(
        Config {
            cases: 40,
            failure_persistence: None,
            ..Config::default()
        },
        TestRng::from_seed(RngAlgorithm::ChaCha, &[5u8; 32]),
    );
    runner
        .run(&(bumps, 0usize..12), |(bumps, margin)| {
            let mut f = FlowField::zeros(200, 80);
            for &(cx, cy, a, s) in &bumps {
                add_shear(&mut f, 1.0, cx, cy, a, s);
            }
            let th = Thresholds {
                sum: 100.0,
                ..thresholds()
            };
            let mut seg = Segmenter::new(SegmenterConfig {
                thresholds: th,
                margin,
                scale: 1.0,
            })
            .unwrap();
            let p = seg.segment(&f).unwrap();
            for (i, a) in p.iter().enumerate() {
                for b in &p[i + 1..] {
                    prop_assert!(!a.bbox.intersects(&b.bbox), "{:?} {:?}", a, b);
                }
                prop_assert!(a.bbox.x_end() <= 200 && a.bbox.y_end() <= 80);
                let holds_one = bumps.iter().any(|&(cx, cy, _, _)| {
                    a.bbox.contains(
                        (cx.round() as usize).min(199),
                        (cy.round() as usize).min(79),
                    )
                });
                prop_assert!(holds_one, "{:?} holds no bump of {:?}", a, bumps);
            }
            // Each bump is above the threshold over a disk of radius >= 7.4
            // (amp >= 3, sigma >= 5): it survives the 5x5 erosion.
            for &(cx, cy, _, _) in &bumps {
                let (x, y) = (
                    (cx.round() as usize).min(199),
                    (cy.round() as usize).min(79),
                );
                prop_assert!(
                    p.iter().any(|q| q.core.contains(x, y)),
                    "bump at ({}, {}) lost: {:?}",
                    cx,
                    cy,
                    p
                );
            }
            Ok(())
        })
        .unwrap();
}
