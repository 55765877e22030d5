//! The split rule ([`SplitRule`]): oracles for its two building blocks (the
//! smoothed derivative of a profile, the cuts on a derivative) and
//! properties on synthetic flows: two presses at a known separation are cut
//! at the valley between them, one bump however stretched, sheared or noisy
//! is never cut.

use optical_tactile::flow::FlowField;
use optical_tactile::segment::morphology::Shape;
use optical_tactile::segment::{
    Segmenter, SegmenterConfig, SplitRule, Thresholds, divergence_profile, find_cuts,
};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};

fn runner(cases: u32) -> TestRunner {
    TestRunner::new_with_rng(
        Config {
            cases,
            failure_persistence: None,
            ..Config::default()
        },
        TestRng::from_seed(RngAlgorithm::ChaCha, &[7; 32]),
    )
}

/// Naive smoothed derivative: each box-filter output is the mean of the
/// samples inside its (clipped) window, computed by a loop; twice; then
/// central differences.
fn naive_divergence(p: &[f64], r: usize) -> Vec<f64> {
    let n = p.len();
    let mut s = p.to_vec();
    for _ in 0..2 {
        let prev = s.clone();
        for (i, v) in s.iter_mut().enumerate() {
            let lo = i.saturating_sub(r);
            let hi = (i + r).min(n - 1);
            *v = prev[lo..=hi].iter().sum::<f64>() / (hi - lo + 1) as f64;
        }
    }
    (0..n)
        .map(|i| {
            if n == 1 {
                0.0
            } else if i == 0 {
                s[1] - s[0]
            } else if i == n - 1 {
                s[n - 1] - s[n - 2]
            } else {
                (s[i + 1] - s[i - 1]) / 2.0
            }
        })
        .collect()
}

/// Naive cuts: every index that is the largest of its run of positive values
/// (searched by walking both ways) and high enough is a peak; consecutive
/// peaks are compared one pair at a time, the group's height being the
/// highest peak since the last cut.
fn naive_cuts(d: &[f64], rule: &SplitRule, valid: std::ops::Range<usize>) -> Vec<usize> {
    let top = d[valid.clone()].iter().copied().fold(0.0, f64::max);
    if top <= 0.0 {
        return vec![];
    }
    let run_max = |i: usize| {
        let (mut a, mut b) = (i, i);
        while a > 0 && d[a - 1] > 0.0 {
            a -= 1;
        }
        while b + 1 < d.len() && d[b + 1] > 0.0 {
            b += 1;
        }
        // The first index holding the run's maximum.
        let m = d[a..=b].iter().copied().fold(f64::MIN, f64::max);
        (a..=b).find(|&k| d[k] == m).unwrap() == i
    };
    // With the far rule, a weaker peak counts far from every strong one.
    let level = rule.min_peak as f64 * top;
    let low = if rule.far_px > 0 {
        rule.far_min_peak.min(rule.min_peak) as f64 * top
    } else {
        level
    };
    let candidates: Vec<usize> = (0..d.len())
        .filter(|&i| d[i] > 0.0 && run_max(i))
        .filter(|&i| d[i] >= low && valid.contains(&i))
        .collect();
    let inset = rule.far_px / 2;
    let peaks: Vec<usize> = candidates
        .iter()
        .copied()
        .filter(|&i| {
            d[i] >= level
                || (i >= valid.start + inset
                    && i + inset < valid.end
                    && candidates
                        .iter()
                        .filter(|&&o| d[o] >= level)
                        .all(|&o| o.abs_diff(i) >= rule.far_px))
        })
        .collect();
    let mut cuts = vec![];
    let mut group = f64::NAN;
    for w in 0..peaks.len() {
        if w == 0 {
            group = d[peaks[0]];
            continue;
        }
        let (a, b) = (peaks[w - 1], peaks[w]);
        let mut at = a + 1;
        for k in a + 1..b {
            if d[k] < d[at] {
                at = k;
            }
        }
        let p = d[b];
        let far = rule.far_px > 0 && b - a >= rule.far_px && d[at] < 0.0;
        if d[at] <= -(rule.depth as f64) * group.min(p) || far {
            cuts.push(at);
            group = p;
        } else {
            group = group.max(p);
        }
    }
    cuts
}

#[test]
fn divergence_profile_matches_the_naive_filter() {
    let strategy = (proptest::collection::vec(-50.0f64..50.0, 1..80), 0usize..9);
    runner(200)
        .run(&strategy, |(p, r)| {
            let (mut s, mut d) = (Vec::new(), Vec::new());
            divergence_profile(&p, r, &mut s, &mut d);
            let want = naive_divergence(&p, r);
            prop_assert_eq!(d.len(), p.len());
            for (a, b) in d.iter().zip(&want) {
                prop_assert!((a - b).abs() < 1e-9, "{} vs {}", a, b);
            }
            Ok(())
        })
        .unwrap();
}

#[test]
fn find_cuts_matches_the_naive_rule() {
    // Smoothed random walks: several lobes of both signs.
    let strategy = (
        proptest::collection::vec(-3.0f64..3.0, 2..120),
        0.02f32..1.0,
        0.0f32..1.0,
        0usize..10,
        0usize..10,
        0usize..60,
        0.0f32..1.0,
    );
    runner(400)
        .run(
            &strategy,
            |(steps, depth, min_peak, lo, hi, far_px, far_min_peak)| {
                let (mut s, mut d) = (Vec::new(), Vec::new());
                let walk: Vec<f64> = steps
                    .iter()
                    .scan(0.0, |a, &x| {
                        *a += x;
                        Some(*a)
                    })
                    .collect();
                divergence_profile(&walk, 1, &mut s, &mut d);
                let n = d.len();
                let valid = lo.min(n)..n.saturating_sub(hi).max(lo.min(n));
                let rule = SplitRule {
                    depth,
                    min_peak,
                    far_px,
                    far_min_peak,
                    ..SplitRule::DEFAULT
                };
                let mut cuts = vec![99];
                find_cuts(&d, &rule, valid.clone(), &mut cuts);
                prop_assert_eq!(&cuts, &naive_cuts(&d, &rule, valid));
                // Cuts are strictly inside and increasing, at negative values.
                for w in cuts.windows(2) {
                    prop_assert!(w[0] < w[1]);
                }
                for &c in &cuts {
                    prop_assert!(c > 0 && c < n && d[c] < 0.0);
                }
                Ok(())
            },
        )
        .unwrap();
}

#[test]
fn find_cuts_by_hand() {
    let rule = SplitRule {
        depth: 0.5,
        min_peak: 0.3,
        far_px: 0,
        ..SplitRule::DEFAULT
    };
    let mut cuts = vec![];
    // Two peaks (4 and 3), valley -2 at index 4: -2 <= -0.5 * 3.
    let d = [0.0, 1.0, 4.0, 0.5, -2.0, -1.0, 3.0, 0.0];
    find_cuts(&d, &rule, 0..d.len(), &mut cuts);
    assert_eq!(cuts, [4]);
    // Valley -1 is not deep enough: one group.
    let d = [0.0, 1.0, 4.0, 0.5, -1.0, -1.0, 3.0, 0.0];
    find_cuts(&d, &rule, 0..d.len(), &mut cuts);
    assert!(cuts.is_empty());
    // A zero valley (the middle of a flat punch) never cuts.
    let d = [0.0, 4.0, 0.0, 0.0, 0.0, 4.0, 0.0];
    find_cuts(&d, &rule, 0..d.len(), &mut cuts);
    assert!(cuts.is_empty());
    // The second peak is below 0.3 of the first: ignored.
    let d = [0.0, 1.0, 4.0, 0.5, -3.0, -1.0, 1.0, 0.0];
    find_cuts(&d, &rule, 0..d.len(), &mut cuts);
    assert!(cuts.is_empty());
    // Outside the valid range a peak does not count.
    let d = [0.0, 1.0, 4.0, 0.5, -2.0, -1.0, 3.0, 0.0];
    find_cuts(&d, &rule, 0..5, &mut cuts);
    assert!(cuts.is_empty());
    // Three peaks, two deep valleys.
    let d = [2.0, -2.0, 2.0, -2.0, 2.0];
    find_cuts(&d, &rule, 0..5, &mut cuts);
    assert_eq!(cuts, [1, 3]);
    // Far apart, a shallow valley is enough, but still a valley: peaks
    // 6 cells apart with a dip to -0.2 are cut with far_px 6, not with 7
    // (nor without the far rule, above), and never where the profile only
    // touches zero.
    let d = [0.0, 4.0, 0.5, 0.1, -0.2, 0.1, 0.2, 3.0, 0.0];
    find_cuts(&d, &rule, 0..d.len(), &mut cuts);
    assert!(cuts.is_empty());
    let far = |far_px| SplitRule { far_px, ..rule };
    find_cuts(&d, &far(6), 0..d.len(), &mut cuts);
    assert_eq!(cuts, [4]);
    find_cuts(&d, &far(7), 0..d.len(), &mut cuts);
    assert!(cuts.is_empty());
    let flat = [0.0, 4.0, 0.5, 0.0, 0.0, 0.0, 0.2, 3.0, 0.0];
    find_cuts(&flat, &far(1), 0..flat.len(), &mut cuts);
    assert!(cuts.is_empty());
    // A peak under min_peak counts from far_min_peak, only far from every
    // peak above min_peak and half that inside the range: 1.0 (a quarter
    // of 4) is 6 cells from the 4, and the 0.9 next to the 4 is no peak of
    // its own.
    let d = [0.0, 4.0, 0.5, -0.4, 0.9, -0.3, 0.2, 1.0, 0.0, 0.0, 0.0, 0.0];
    let weak = |far_px, far_min_peak| SplitRule {
        far_px,
        far_min_peak,
        ..rule
    };
    find_cuts(&d, &weak(6, 0.2), 0..d.len(), &mut cuts);
    assert_eq!(cuts, [3]);
    find_cuts(&d, &weak(6, 0.3), 0..d.len(), &mut cuts);
    assert!(cuts.is_empty());
    find_cuts(&d, &weak(7, 0.2), 0..d.len(), &mut cuts);
    assert!(cuts.is_empty());
    find_cuts(&d, &weak(2, 0.2), 0..d.len(), &mut cuts);
    assert_eq!(cuts, [3, 5]);
    // Within 3 cells of the range's end, the weak peak does not count.
    find_cuts(&d, &weak(6, 0.2), 0..9, &mut cuts);
    assert!(cuts.is_empty());
    // Empty and all-negative profiles.
    find_cuts(&[], &rule, 0..0, &mut cuts);
    assert!(cuts.is_empty());
    find_cuts(&[-1.0, -2.0], &rule, 0..2, &mut cuts);
    assert!(cuts.is_empty());
}

#[test]
fn invalid_rules_are_errors() {
    let seg = || Segmenter::new(SegmenterConfig::default()).unwrap();
    for bad in [
        SplitRule {
            smooth: 0,
            ..SplitRule::DEFAULT
        },
        SplitRule {
            depth: 0.0,
            ..SplitRule::DEFAULT
        },
        SplitRule {
            depth: f32::NAN,
            ..SplitRule::DEFAULT
        },
        SplitRule {
            min_peak: 1.5,
            ..SplitRule::DEFAULT
        },
        SplitRule {
            min_peak: -0.1,
            ..SplitRule::DEFAULT
        },
        SplitRule {
            far_min_peak: 1.5,
            ..SplitRule::DEFAULT
        },
        SplitRule {
            far_min_peak: f32::NAN,
            ..SplitRule::DEFAULT
        },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
        assert!(seg().with_split(Some(bad)).is_err(), "{bad:?}");
    }
    assert!(SplitRule::DEFAULT.validate().is_ok());
    let s = seg();
    assert_eq!(s.split(), Some(&SplitRule::DEFAULT));
    assert_eq!(s.with_split(None).unwrap().split(), None);
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

fn segmenter(margin: usize) -> Segmenter {
    Segmenter::new(SegmenterConfig {
        thresholds: thresholds(),
        margin,
        scale: 1.0,
    })
    .unwrap()
}

/// A press: radial outward flow, peak `amp` on the ring `r = sigma`.
fn add_press(f: &mut FlowField, cx: f32, cy: f32, amp: f32, sigma: f32) {
    for ((y, x), u) in f.u.indexed_iter_mut() {
        let (dx, dy) = (x as f32 - cx, y as f32 - cy);
        *u += amp / sigma * dx * (0.5 - (dx * dx + dy * dy) / (2.0 * sigma * sigma)).exp();
    }
    for ((y, x), v) in f.v.indexed_iter_mut() {
        let (dx, dy) = (x as f32 - cx, y as f32 - cy);
        *v += amp / sigma * dy * (0.5 - (dx * dx + dy * dy) / (2.0 * sigma * sigma)).exp();
    }
}

/// A shear bump of direction `angle`, widths `sx`, `sy` along axes rotated
/// by `tilt`.
#[allow(clippy::too_many_arguments)]
fn add_shear(
    f: &mut FlowField,
    cx: f32,
    cy: f32,
    amp: f32,
    sx: f32,
    sy: f32,
    tilt: f32,
    angle: f32,
) {
    let (st, ct) = tilt.sin_cos();
    let (sa, ca) = angle.sin_cos();
    let (h, w) = f.u.dim();
    for y in 0..h {
        for x in 0..w {
            let (dx, dy) = (x as f32 - cx, y as f32 - cy);
            let (a, b) = (ct * dx + st * dy, -st * dx + ct * dy);
            let g = amp * (-(a * a) / (2.0 * sx * sx) - (b * b) / (2.0 * sy * sy)).exp();
            f.u[[y, x]] += ca * g;
            f.v[[y, x]] += sa * g;
        }
    }
}

fn add_noise(f: &mut FlowField, seed: u64, amp: f32) {
    let mut s = seed | 1;
    for v in f.u.iter_mut().chain(f.v.iter_mut()) {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        *v += ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 2.0 * amp;
    }
}

#[test]
fn two_presses_are_cut_at_the_valley_between_them() {
    // Equal presses, sigma 12: the masks join below ~4 sigma, the margins
    // overlap above; cut at the midpoint (the symmetric valley) either way.
    // The default rule smooths over 21 px (twice): its resolution is about
    // twice that, so separations start at 40 px.
    assert_eq!(SplitRule::DEFAULT.smooth, 21);
    // Margins of 24-40 px make the grown boxes overlap at every separation
    // drawn (the masks are <= ~46 px wide), so the rule decides.
    let strategy = (
        40.0f32..80.0,
        0.0f32..1.0,
        2.0f32..5.0,
        24usize..40,
        any::<u64>(),
    );
    runner(40)
        .run(&strategy, |(sep, off, amp, margin, seed)| {
            let mut f = FlowField::zeros(400, 100);
            let c1 = 120.0 + 40.0 * off;
            let c2 = c1 + sep;
            add_press(&mut f, c1, 50.0, amp, 12.0);
            add_press(&mut f, c2, 50.0, amp, 12.0);
            add_noise(&mut f, seed, 0.05);
            let mut seg = segmenter(margin);
            let p = seg.segment(&f).unwrap();
            prop_assert_eq!(p.len(), 2, "sep {} {:?}", sep, p);
            prop_assert_eq!(seg.split_count(), 1);
            let mid = 0.5 * (c1 + c2);
            let cut = p[1].bbox.x as f32;
            prop_assert_eq!(p[0].bbox.x_end(), p[1].bbox.x, "the patches touch");
            // Each press's outward core (|x - c| < sigma) is in its own
            // patch; while the two convergence lobes (at c +- sqrt(3) sigma)
            // overlap, the valley is single and the cut at the midpoint;
            // farther apart the cut is at the deeper of the two lobes.
            prop_assert!(cut >= c1 + 12.0 && cut <= c2 - 12.0, "cut {}", cut);
            if sep <= 50.0 {
                prop_assert!((cut - mid).abs() <= 3.0, "cut {} mid {}", cut, mid);
            }
            prop_assert!(p[0].bbox.contains(c1 as usize, 50));
            prop_assert!(p[1].bbox.contains(c2 as usize, 50));
            // Without the rule the same scene is one merged patch.
            let whole = segmenter(margin)
                .with_split(None)
                .unwrap()
                .segment(&f)
                .unwrap();
            prop_assert_eq!(whole.len(), 1);
            Ok(())
        })
        .unwrap();
}

#[test]
fn one_bump_is_never_cut_however_stretched_sheared_or_noisy() {
    let strategy = (
        (6.0f32..40.0, 6.0f32..40.0, 0.0f32..3.2, 0.0f32..6.3),
        (2.0f32..8.0, 0.0f32..1.5),
        (0usize..30, any::<u64>(), 0.0f32..0.15),
    );
    runner(80)
        .run(
            &strategy,
            |((sx, sy, tilt, angle), (amp, press), (margin, seed, noise))| {
                let mut f = FlowField::zeros(400, 120);
                add_shear(&mut f, 200.0, 60.0, amp, sx, sy, tilt, angle);
                // A press at the same place (a sheared press), or none.
                if press > 0.3 {
                    add_press(&mut f, 200.0, 60.0, press * amp, 0.5 * sx.min(sy) + 4.0);
                }
                add_noise(&mut f, seed, noise);
                let mut seg = segmenter(margin);
                let p = seg.segment(&f).unwrap();
                prop_assert_eq!(seg.split_count(), 0, "{:?}", p);
                prop_assert_eq!(p.len(), 1, "{:?}", p);
                prop_assert!(p[0].bbox.contains(200, 60));
                Ok(())
            },
        )
        .unwrap();
}

#[test]
fn a_press_and_its_two_lobes_are_one_patch() {
    // A wide flat press: outward flow only outside |x - c| > 20 (the skin
    // held under the punch), two lobes of |flow| on either side that the
    // mask keeps apart, joined by the margin: divergence positive at both
    // edges, zero between: one patch.
    let mut f = FlowField::zeros(400, 100);
    for ((_, x), u) in f.u.indexed_iter_mut() {
        let d = x as f32 - 200.0;
        let out = (d.abs() - 20.0).max(0.0);
        *u = d.signum() * 5.0 * (out / 8.0) * (1.0 - out / 8.0).exp();
    }
    let mut seg = segmenter(20);
    let p = seg.segment(&f).unwrap();
    assert_eq!(seg.contour_boxes().len(), 2, "two lobes in the mask");
    assert_eq!(p.len(), 1, "{p:?}");
    assert_eq!(seg.split_count(), 0);
}

/// Noise in 8x8 blocks (a flow whose patches do not overlap errs patch by
/// patch): each block gets one random vector of up to `amp` per component.
fn add_block_noise(f: &mut FlowField, seed: u64, amp: f32) {
    let mut s = seed | 1;
    let (h, w) = f.u.dim();
    for by in (0..h).step_by(8) {
        for bx in (0..w).step_by(8) {
            let mut draw = || {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 2.0 * amp
            };
            let (du, dv) = (draw(), draw());
            for y in by..(by + 8).min(h) {
                for x in bx..(bx + 8).min(w) {
                    f.u[[y, x]] += du;
                    f.v[[y, x]] += dv;
                }
            }
        }
    }
}

/// A fingertip on a small flat sensor (a 320x240 image): one broad press
/// (outward flow peaking on a ring of radius 20-60 px), with or without a
/// shear of the same size, anywhere in the middle of the image, with
/// patch-sized noise of up to 10% of the motion on top, is one patch.
#[test]
fn a_fingertip_on_a_small_sensor_is_one_patch() {
    let strategy = (
        (20.0f32..60.0, 1.5f32..6.0, 0.0f32..1.2, 0.0f32..6.3),
        (130.0f32..190.0, 100.0f32..140.0),
        (0.0f32..0.1, any::<u64>(), 16usize..32),
    );
    runner(80)
        .run(
            &strategy,
            |((radius, amp, shear, angle), (cx, cy), (noise, seed, margin))| {
                let mut f = FlowField::zeros(320, 240);
                add_press(&mut f, cx, cy, amp, radius);
                if shear > 0.2 {
                    let s = 1.5 * radius;
                    add_shear(&mut f, cx, cy, shear * amp, s, s, 0.0, angle);
                }
                add_block_noise(&mut f, seed, noise * amp);
                // The default rule, and the flat sensor's, which also cuts
                // along the rows and looks for a press's swing in each piece.
                for rule in [SplitRule::DEFAULT, SplitRule::FLAT] {
                    let mut seg = segmenter(margin).with_split(Some(rule)).unwrap();
                    let p = seg.segment(&f).unwrap();
                    prop_assert_eq!(seg.split_count(), 0, "{:?}", p);
                    prop_assert_eq!(p.len(), 1, "{:?}", p);
                    prop_assert!(p[0].bbox.contains(cx as usize, cy as usize));
                }
                Ok(())
            },
        )
        .unwrap();
}

/// A fingertip on the simulated flat sensor (a grid of dark dots on a thin
/// gel bonded to its window, 320x240 px at 10 px/mm): pressed anywhere in
/// the middle with 0.5-3 N, sheared by up to half that in any direction, on
/// grids of several pitches, dot sizes and seeds, the default extractor
/// (`fine` flow, high thresholds: what `track --raw` runs) finds one patch,
/// around the fingertip, and none at rest.
#[test]
fn a_simulated_fingertip_on_a_dot_grid_is_one_patch() {
    use optical_tactile::sensor::{ContactExtractor, ExtractorConfig};
    use optical_tactile_sim::{DotGrid, Material, Press, SimConfig, SyntheticSensor};
    let strategy = (
        (-5.0f64..5.0, -3.0f64..3.0, 15.0f64..20.0),
        (0.5f64..3.0, 0.0f64..0.8, 0.0f64..6.3),
        (22.0f64..36.0, 6.0f64..10.0, 0u64..1000),
    );
    runner(64)
        .run(
            &strategy,
            |((x, y, tip), (fz, shear, angle), (pitch, dot, seed))| {
                let mut cfg = SimConfig::dot_grid(DotGrid {
                    pitch_px: pitch,
                    diameter_px: dot,
                    jitter_px: 1.0,
                    ..DotGrid::default()
                });
                cfg.material = Material {
                    youngs_kpa: 600.0,
                    poisson: 0.47,
                    layer_mm: 3.0,
                };
                let sim = SyntheticSensor::new(cfg, seed).unwrap();
                let reference = sim.render_indexed(0, &[], false).unwrap().frame;
                let f = [shear * fz * angle.cos(), shear * fz * angle.sin(), -fz];
                let press = Press::fingertip(x, y, f, tip);
                let frame = sim.render_indexed(1, &[press], false).unwrap().frame;
                let mut ex = ContactExtractor::new(ExtractorConfig::default()).unwrap();
                ex.set_reference(&reference).unwrap();
                // At rest first: nothing.
                let rest = sim.render_indexed(2, &[], false).unwrap().frame;
                let at_rest = ex.extract(&rest).unwrap().len();
                prop_assert_eq!(at_rest, 0, "patches at rest");
                let n = ex.extract(&frame).unwrap().len();
                let scale = ex.scale() as f64;
                let boxes: Vec<_> = ex.patches().iter().map(|p| p.bbox).collect();
                // The fingertip's centre in pixels (the image's centre is the
                // skin's).
                let (cx, cy) = (160.0 + 10.0 * x, 120.0 + 10.0 * y);
                prop_assert_eq!(n, 1, "{:?}", boxes);
                let b = boxes[0];
                let inside = (b.x as f64 * scale..=(b.x + b.width) as f64 * scale).contains(&cx)
                    && (b.y as f64 * scale..=(b.y + b.height) as f64 * scale).contains(&cy);
                prop_assert!(inside, "{:?} misses ({cx}, {cy})", b);
                Ok(())
            },
        )
        .unwrap();
}

/// Two presses one above the other on a small flat sensor's image (320x240:
/// the default rule cuts along its longer side, x, only), 40-80 px apart
/// along the rows, the second at half to all of the first's strength,
/// a little off to either side: the flat sensor's rule cuts them apart
/// along y, each press in its own patch; the default rule leaves one patch.
#[test]
fn two_presses_along_the_shorter_side_are_cut_by_the_flat_rule() {
    let strategy = (
        (40.0f32..80.0, -10.0f32..10.0, 0.5f32..1.0),
        (3.0f32..5.0, 140.0f32..180.0, 80.0f32..100.0),
        (any::<u64>(), 24usize..40),
    );
    runner(40)
        .run(
            &strategy,
            |((sep, dx, ratio), (amp, cx, cy), (seed, margin))| {
                let mut f = FlowField::zeros(320, 240);
                let (c1, c2) = ((cx, cy), (cx + dx, cy + sep));
                add_press(&mut f, c1.0, c1.1, amp, 12.0);
                add_press(&mut f, c2.0, c2.1, ratio * amp, 12.0);
                add_noise(&mut f, seed, 0.05);
                let mut seg = segmenter(margin).with_split(Some(SplitRule::FLAT)).unwrap();
                let p = seg.segment(&f).unwrap();
                prop_assert_eq!(p.len(), 2, "sep {} ratio {} {:?}", sep, ratio, p);
                for c in [c1, c2] {
                    let holding = p
                        .iter()
                        .filter(|q| q.bbox.contains(c.0 as usize, c.1 as usize))
                        .count();
                    prop_assert_eq!(holding, 1, "{:?} in {:?}", c, p);
                }
                prop_assert!(!p[0].bbox.intersects(&p[1].bbox), "{:?}", p);
                let default = segmenter(margin).segment(&f).unwrap();
                prop_assert_eq!(default.len(), 1, "{:?}", default);
                Ok(())
            },
        )
        .unwrap();
}

/// A press with a shear along the rows beside it whose far edge turns back
/// (the gel squeezed ahead of a sheared press, then a positive lobe of
/// divergence where the motion returns towards zero): a valley and a
/// second lobe along y, but the motion beyond the valley never swings
/// from below zero to above it as a press's does, so the flat rule keeps
/// one patch; a true second press there is cut off.
#[test]
fn a_shear_lobe_is_not_a_second_press() {
    let strategy = (2.0f32..5.0, 0.6f32..1.2, any::<u64>());
    runner(40)
        .run(&strategy, |(amp, shear, seed)| {
            let (cx, cy) = (160.0f32, 90.0f32);
            let mut f = FlowField::zeros(320, 240);
            add_press(&mut f, cx, cy, amp, 12.0);
            // Motion along +y ahead of the press, overshooting below zero
            // beyond it and returning: v = s(y) with a negative tail.
            for ((y, x), v) in f.v.indexed_iter_mut() {
                let (dx, dy) = (x as f32 - cx, y as f32 - cy);
                let across = (-dx * dx / (2.0 * 30.0 * 30.0)).exp();
                let ahead = (dy - 25.0) / 14.0;
                *v -= shear * amp * across * ahead * (-0.5 * ahead * ahead).exp();
            }
            add_noise(&mut f, seed, 0.05);
            let mut seg = segmenter(30).with_split(Some(SplitRule::FLAT)).unwrap();
            let p = seg.segment(&f).unwrap();
            prop_assert_eq!(p.len(), 1, "{:?}", p);
            Ok(())
        })
        .unwrap();
}
