//! Integration and property tests of `flow::Dis` on synthetic marker images
//! and smooth textures moved by known analytic flows.

mod support;

use ndarray::Array2;
use optical_tactile::Error;
use optical_tactile::flow::FlowField;
use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
use support::{Motion, marker_pair, mean_error, press_motion, texture_pair};

const W: usize = 256;
const H: usize = 192;
const BORDER: usize = 12;

fn flow_of(preset: DisPreset, r: &Array2<f32>, c: &Array2<f32>) -> FlowField {
    let mut dis = Dis::with_preset(preset);
    dis.set_reference(r).unwrap();
    dis.compute(c).unwrap()
}

fn aepe(preset: DisPreset, pair: &(Array2<f32>, Array2<f32>, FlowField)) -> f64 {
    let e = flow_of(preset, &pair.0, &pair.1)
        .aepe(&pair.2, BORDER)
        .unwrap();
    eprintln!("MEASURE {preset:?} aepe {e:.4}");
    e
}

/// A deterministic proptest runner: fixed seed, few cases.
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

#[test]
fn zero_motion_gives_zero_flow() {
    for preset in DisPreset::ALL {
        let m = marker_pair(W, H, &Motion::Translation(0.0, 0.0), 1);
        let f = flow_of(preset, &m.0, &m.1);
        let max = f.magnitude().iter().cloned().fold(0.0f32, f32::max);
        assert!(
            max < 1e-3,
            "{preset:?}: max |flow| {max} for identical images"
        );
        let t = texture_pair(W, H, &Motion::Translation(0.0, 0.0), 2);
        assert!(aepe(preset, &t) < 1e-3);
    }
}

#[test]
fn translations_of_markers() {
    runner(6)
        .run(
            &(-3.0f64..3.0, -3.0f64..3.0, 0u64..1000),
            |(dx, dy, seed)| {
                let m = marker_pair(W, H, &Motion::Translation(dx, dy), seed);
                let acc = aepe(DisPreset::Accurate, &m);
                prop_assert!(acc < 0.1, "accurate AEPE {acc} for ({dx}, {dy})");
                let bal = aepe(DisPreset::Balanced, &m);
                prop_assert!(bal < 0.1, "balanced AEPE {bal} for ({dx}, {dy})");
                let med = aepe(DisPreset::Medium, &m);
                prop_assert!(med < 0.1, "medium AEPE {med} for ({dx}, {dy})");
                Ok(())
            },
        )
        .unwrap();
}

#[test]
fn translations_of_smooth_textures() {
    runner(6)
        .run(
            &(-4.0f64..4.0, -4.0f64..4.0, 0u64..1000),
            |(dx, dy, seed)| {
                let t = texture_pair(W, H, &Motion::Translation(dx, dy), seed);
                for preset in [DisPreset::Accurate, DisPreset::Medium, DisPreset::Fast] {
                    let e = aepe(preset, &t);
                    prop_assert!(e < 0.1, "{preset:?} AEPE {e} for ({dx}, {dy})");
                }
                Ok(())
            },
        )
        .unwrap();
}

#[test]
fn rotations_and_affine_motions() {
    runner(5)
        .run(
            &(-0.03f64..0.03, -0.02f64..0.02, -0.02f64..0.02, 0u64..1000),
            |(angle, a, b, seed)| {
                let (cx, cy) = (W as f64 / 2.0, H as f64 / 2.0);
                let rot = Motion::Rotation { cx, cy, angle };
                let aff = Motion::Affine {
                    cx,
                    cy,
                    a: [a, b, -b, a],
                    t: [0.7, -0.4],
                };
                for motion in [rot, aff] {
                    let m = marker_pair(W, H, &motion, seed);
                    let e = aepe(DisPreset::Accurate, &m);
                    prop_assert!(e < 0.15, "markers {motion:?}: AEPE {e}");
                    let t = texture_pair(W, H, &motion, seed);
                    let e = aepe(DisPreset::Accurate, &t);
                    // Measured up to ~0.20 px (up to 3.3 px of motion at the
                    // corners of the smooth texture).
                    prop_assert!(e < 0.25, "texture {motion:?}: AEPE {e}");
                }
                Ok(())
            },
        )
        .unwrap();
}

#[test]
fn press_like_bumps() {
    runner(5)
        .run(&(0.3f64..4.0, 0u64..1000), |(max_disp, seed)| {
            let motion = press_motion(W, H, max_disp, seed);
            let m = marker_pair(W, H, &motion, seed);
            let acc = aepe(DisPreset::Accurate, &m);
            prop_assert!(acc < 0.3, "accurate AEPE {acc} at {max_disp} px");
            // On dense 1-px markers the scale-2 presets are aliased; the
            // accurate preset exists for that and must beat them.
            let fast = aepe(DisPreset::Fast, &m);
            prop_assert!(acc < fast, "accurate {acc} not better than fast {fast}");
            let t = texture_pair(W, H, &motion, seed);
            let fast = aepe(DisPreset::Fast, &t);
            prop_assert!(fast < 0.4, "fast AEPE {fast} on a texture at {max_disp} px");
            Ok(())
        })
        .unwrap();
}

/// `dense` is `fine` with overlapping patches: each pixel averages four
/// patches' vectors instead of taking one, so on the same press it is
/// closer to the true motion (measured on 1600x200 marker pairs: 0.028-0.036
/// px against 0.049-0.065 px), not only as close.
#[test]
fn dense_is_closer_than_fine_under_a_press() {
    runner(4)
        .run(&(1.0f64..4.0, 0u64..1000), |(max_disp, seed)| {
            let m = marker_pair(W, H, &press_motion(W, H, max_disp, seed), seed);
            let fine = aepe(DisPreset::Fine, &m);
            let dense = aepe(DisPreset::Dense, &m);
            prop_assert!(
                dense < 0.85 * fine,
                "dense AEPE {dense} against fine's {fine} at {max_disp} px"
            );
            Ok(())
        })
        .unwrap();
}

#[test]
fn subpixel_translation_bias_under_a_hundredth_of_a_pixel() {
    // A larger frame: the bias is a mean over many patches.
    let (w, h) = (480, 320);
    for (k, d) in [0.1, 0.25, 0.5, 1.0, 2.0].into_iter().enumerate() {
        let m = marker_pair(w, h, &Motion::Translation(d, 0.0), 40 + k as u64);
        let f = flow_of(DisPreset::Accurate, &m.0, &m.1);
        let (bu, bv) = mean_error(&f, &m.2, BORDER);
        let fb = flow_of(DisPreset::Balanced, &m.0, &m.1);
        let (pu, pv) = mean_error(&fb, &m.2, BORDER);
        eprintln!("MEASURE balanced bias {d}: {pu:.4} {pv:.4}");
        assert!(
            pu.abs() < 0.01 && pv.abs() < 0.01,
            "balanced bias ({pu}, {pv}) at {d} px"
        );
        eprintln!("MEASURE bias {d}: {bu:.4} {bv:.4}");
        assert!(
            bu.abs() < 0.01 && bv.abs() < 0.01,
            "bias ({bu}, {bv}) at {d} px"
        );
    }
}

#[test]
fn result_does_not_depend_on_thread_count() {
    let motion = press_motion(W, H, 3.0, 5);
    let m = marker_pair(W, H, &motion, 5);
    for preset in DisPreset::ALL {
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut dis = Dis::with_preset(preset);
                dis.set_reference(&m.0).unwrap();
                let f = dis.compute(&m.1).unwrap();
                let native = dis.native_flow().unwrap().0.clone();
                (f, native)
            })
        };
        let (a, b) = (run(1), run(2));
        // Bit-exact: compare the bit patterns, not within a tolerance.
        let bits = |f: &FlowField| -> Vec<u32> {
            f.u.iter().chain(f.v.iter()).map(|x| x.to_bits()).collect()
        };
        assert_eq!(bits(&a.0), bits(&b.0), "{preset:?}");
        assert_eq!(bits(&a.1), bits(&b.1), "{preset:?}");
    }
}

#[test]
fn compute_into_reuses_and_matches_compute() {
    let m = texture_pair(W, H, &Motion::Translation(1.3, -0.6), 9);
    let mut dis = Dis::with_preset(DisPreset::Fast);
    dis.set_reference(&m.0).unwrap();
    let a = dis.compute(&m.1).unwrap();
    let mut out = FlowField::zeros(1, 1);
    dis.compute_into(&m.1, &mut out).unwrap();
    assert_eq!(a, out);
    let ptr = out.u.as_ptr();
    dis.compute_into(&m.1, &mut out).unwrap();
    assert_eq!(
        ptr,
        out.u.as_ptr(),
        "steady state reuses the output buffers"
    );
    // The native flow is the finest level's, at scale 4 for `fast`.
    let (native, scale) = dis.native_flow().unwrap();
    assert_eq!(scale, 4);
    assert_eq!(native.size(), (W / 4, H / 4));
    let mid = native.u[[H / 8, W / 8]] * scale as f32;
    assert!(mid.is_finite(), "{mid}");
    // The full-resolution flow is the native flow upsampled and scaled.
    let (nu, nv) = (native.u[[H / 8, W / 8]], native.v[[H / 8, W / 8]]);
    let (fu, fv) = (a.u[[H / 2 + 1, W / 2 + 1]], a.v[[H / 2 + 1, W / 2 + 1]]);
    assert!((fu - 4.0 * nu).abs() < 0.3 && (fv - 4.0 * nv).abs() < 0.3);
    // Non-contiguous views give the same answer.
    let big_r = Array2::from_shape_fn((H, 2 * W), |(y, x)| m.0[[y, x / 2]]);
    let big_c = Array2::from_shape_fn((H, 2 * W), |(y, x)| m.1[[y, x / 2]]);
    let vr = big_r.slice(ndarray::s![.., ..;2]);
    let vc = big_c.slice(ndarray::s![.., ..;2]);
    let mut dis2 = Dis::with_preset(DisPreset::Fast);
    dis2.set_reference(&vr).unwrap();
    assert_eq!(dis2.compute(&vc).unwrap(), a);
}

#[test]
fn bad_input_gives_typed_errors() {
    let r = Array2::<f32>::from_elem((64, 80), 100.0);
    let mut dis = Dis::with_preset(DisPreset::Fast);
    assert!(matches!(dis.compute(&r), Err(Error::NoReference)));
    dis.set_reference(&r).unwrap();
    let other = Array2::<f32>::zeros((64, 81));
    assert!(matches!(
        dis.compute(&other),
        Err(Error::ShapeMismatch { .. })
    ));
    let empty = Array2::<f32>::zeros((0, 0));
    assert!(matches!(
        Dis::with_preset(DisPreset::Fast).set_reference(&empty),
        Err(Error::TooSmall { .. })
    ));
    // Scale 2 with 8-px patches needs at least 32x32.
    let small = Array2::<f32>::zeros((31, 200));
    assert!(matches!(
        Dis::with_preset(DisPreset::Fast).set_reference(&small),
        Err(Error::TooSmall { min_h: 32, .. })
    ));
    let mut nan = r.clone();
    nan[[10, 20]] = f32::NAN;
    match Dis::with_preset(DisPreset::Fast).set_reference(&nan) {
        Err(Error::NonFinite { row, col, .. }) => assert_eq!((row, col), (10, 20)),
        other => panic!("{other:?}"),
    }
    match dis.compute(&nan) {
        Err(Error::NonFinite { row, col, .. }) => assert_eq!((row, col), (10, 20)),
        other => panic!("{other:?}"),
    }
    // A pixel in the margin the 4x4 boxes do not cover is still checked.
    let r2 = Array2::<f32>::from_elem((66, 83), 100.0);
    let mut dis2 = Dis::with_preset(DisPreset::Fast);
    dis2.set_reference(&r2).unwrap();
    let mut inf = r2.clone();
    inf[[65, 3]] = f32::INFINITY;
    assert!(matches!(
        dis2.compute(&inf),
        Err(Error::NonFinite {
            row: 65,
            col: 3,
            ..
        })
    ));
    let bad = DisParams {
        patch_size: 40,
        ..DisParams::preset(DisPreset::Fast)
    };
    assert!(matches!(Dis::new(bad), Err(Error::InvalidParameter { .. })));
}

/// Two rest frames of a strip whose ends hold no markers, only sensor noise
/// (like the black coating beyond a real skin): the texture gate keeps the
/// flow there at rest, where full Gauss-Newton steps would fit the noise.
#[test]
fn untextured_ends_stay_still_at_rest() {
    let (w, h) = (400, 64);
    let centres = support::marker_centres(w, h, 4.5, 11);
    let base = support::render_markers(w, h, &centres, 1.0);
    let mut rng = support::Rng::new(5);
    let mut frame = |dark: usize| {
        let mut img = base.clone();
        for ((_, x), v) in img.indexed_iter_mut() {
            if x < dark || x >= w - dark {
                *v = 3.0;
            }
            *v += 5.2 * (rng.uniform() - 0.5) as f32;
        }
        img
    };
    let (a, b) = (frame(24), frame(24));
    for preset in [DisPreset::Accurate, DisPreset::Balanced] {
        let mut dis = Dis::new(DisParams::preset(preset)).unwrap();
        dis.set_reference(&a).unwrap();
        let f = dis.compute(&b).unwrap();
        let worst = f.magnitude().iter().cloned().fold(0.0f32, f32::max);
        assert!(worst < 0.5, "{preset:?}: largest flow at rest {worst} px");
    }
}

/// The speed knobs: `early_stop` and `refine_levels` keep the result
/// deterministic across thread counts and accurate; `opencv_semantics`
/// turns both off; bad values are typed errors.
#[test]
fn speed_knobs_stay_accurate_and_deterministic() {
    let motion = press_motion(W, H, 2.5, 11);
    let m = marker_pair(W, H, &motion, 11);
    let t = texture_pair(W, H, &motion, 11);
    let run = |p: &DisParams, pair: &(Array2<f32>, Array2<f32>, FlowField), threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut dis = Dis::new(p.clone()).unwrap();
            dis.set_reference(&pair.0).unwrap();
            dis.compute(&pair.1).unwrap()
        })
    };
    let bits =
        |f: &FlowField| -> Vec<u32> { f.u.iter().chain(f.v.iter()).map(|x| x.to_bits()).collect() };
    for preset in [DisPreset::Fast, DisPreset::Accurate] {
        let opencv = DisParams::preset(preset).opencv_semantics();
        assert_eq!(opencv.early_stop, 0.0);
        assert_eq!(opencv.refine_levels, None);
        for (stop, levels) in [
            (0.0, None),
            (0.02, None),
            (0.0, Some(1)),
            (0.02, Some(1)),
            (0.02, Some(0)),
        ] {
            let p = DisParams {
                early_stop: stop,
                refine_levels: levels,
                ..opencv.clone()
            };
            for pair in [&m, &t] {
                let a = run(&p, pair, 1);
                let b = run(&p, pair, 2);
                assert_eq!(bits(&a), bits(&b), "{preset:?} {stop} {levels:?}");
                let e = a.aepe(&pair.2, BORDER).unwrap();
                let base = run(&opencv, pair, 1).aepe(&pair.2, BORDER).unwrap();
                eprintln!("MEASURE {preset:?} stop {stop} levels {levels:?}: {e:.4} ({base:.4})");
                if levels == Some(0) {
                    // No refinement at all: only determinism is claimed.
                    continue;
                }
                // Within 25 % (+0.02 px) of OpenCV's semantics (on these small
                // frames with few levels; the 1080p figures are in
                // docs/results.md).
                assert!(
                    e <= 1.25 * base + 0.02,
                    "{preset:?} stop {stop} levels {levels:?}: AEPE {e} vs {base}"
                );
            }
        }
    }
    // Refining every level is the same as not limiting the levels.
    let all = DisParams {
        refine_levels: Some(99),
        ..DisParams::preset(DisPreset::Fast).opencv_semantics()
    };
    let none = DisParams::preset(DisPreset::Fast).opencv_semantics();
    assert_eq!(bits(&run(&all, &m, 1)), bits(&run(&none, &m, 1)));
    for bad in [-0.1f32, 1.5, f32::NAN] {
        let p = DisParams {
            early_stop: bad,
            ..DisParams::preset(DisPreset::Fast)
        };
        assert!(matches!(Dis::new(p), Err(Error::InvalidParameter { .. })));
    }
}

/// Large motion on a 1080p marker frame (the pair `examples/flow synth --size
/// 1920x1080 --max-disp 8 --seed 5`, 16.7 px at most). OpenCV's coarsest
/// level (scale 6, 30x16 px) holds aliased dots: searched there, the whole
/// field locks onto a wrong vector that every finer level doubles. `Fast`
/// stops at a level at least 3 patches high (scale 5) and tracks it; the
/// OpenCV rule's failure is pinned too, so a change of it shows here.
#[test]
fn fast_tracks_large_motion_on_1080p_markers() {
    let (w, h) = (1920, 1080);
    let motion = press_motion(w, h, 8.0, 5);
    let pair = marker_pair(w, h, &motion, 5);
    let max = pair.2.magnitude().iter().cloned().fold(0.0f32, f32::max);
    assert!(max > 16.0, "largest motion {max} px");
    let aepe_with = |p: DisParams| {
        let mut dis = Dis::new(p).unwrap();
        dis.set_reference(&pair.0).unwrap();
        dis.compute(&pair.1).unwrap().aepe(&pair.2, 16).unwrap()
    };
    let fast = aepe_with(DisParams::preset(DisPreset::Fast));
    let top6 = aepe_with(DisParams {
        coarsest_min_patches: 1,
        ..DisParams::preset(DisPreset::Fast)
    });
    eprintln!("MEASURE 1080p 16.7 px: fast {fast:.4}, with OpenCV's coarsest level {top6:.2}");
    assert!(fast < 1.0, "fast AEPE {fast} px");
    assert!(
        top6 > 10.0,
        "OpenCV's coarsest level no longer fails: {top6} px"
    );
}

/// The coarsest level rule keeps the finest level even when it is less than
/// `coarsest_min_patches` patches high, and bad values of the new knobs are
/// typed errors.
#[test]
fn stripe_and_coarsest_knobs() {
    // 1600x80 at scale 2 is 400x20: less than 3 patches high, so `Fast`
    // searches that level alone (OpenCV's rule adds the 200x10 scale 3).
    let (w, h) = (1600, 80);
    let pair = marker_pair(w, h, &Motion::Translation(0.6, -0.4), 3);
    let aepe_with = |p: DisParams| {
        let mut dis = Dis::new(p).unwrap();
        dis.set_reference(&pair.0).unwrap();
        dis.compute(&pair.1).unwrap().aepe(&pair.2, 8).unwrap()
    };
    let e = aepe_with(DisParams::preset(DisPreset::Fast));
    let two = aepe_with(DisParams {
        coarsest_min_patches: 1,
        ..DisParams::preset(DisPreset::Fast)
    });
    eprintln!("MEASURE 80-px strip: fast {e:.4}, two levels {two:.4}");
    // A 20-px-high level is mostly border: both are ~0.3 px here (0.3031 and
    // 0.2995 when written); the single level must not be worse than that.
    assert!(e < 0.35, "fast AEPE {e} on an 80-px strip");
    assert!(e <= 1.05 * two + 0.01, "one level {e} vs two {two}");
    for p in [
        DisParams {
            min_stripe_rows: 0,
            ..DisParams::preset(DisPreset::Fast)
        },
        DisParams {
            coarsest_min_patches: 0,
            ..DisParams::preset(DisPreset::Fast)
        },
        DisParams {
            coarsest_min_patches: 65,
            ..DisParams::preset(DisPreset::Fast)
        },
    ] {
        assert!(matches!(Dis::new(p), Err(Error::InvalidParameter { .. })));
    }
    let o = DisParams::preset(DisPreset::Fast).opencv_semantics();
    assert!(o.step_on_stop && o.min_stripe_rows == 1 && o.coarsest_min_patches == 1);
}

/// Endpoint errors of `flow` against `truth` at the markers' reference
/// centres (both sampled bilinearly there): `(mean, max)`.
fn marker_errors(
    flow: &FlowField,
    truth: &FlowField,
    centres: &[(f64, f64, f64, f64, f64)],
) -> (f64, f64) {
    let at = |f: &FlowField, x: f64, y: f64| {
        let (w, h) = f.size();
        let (x, y) = (x.clamp(0.0, (w - 1) as f64), y.clamp(0.0, (h - 1) as f64));
        let (x0, y0) = ((x as usize).min(w - 2), (y as usize).min(h - 2));
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let bil = |a: &Array2<f32>| {
            let top = a[[y0, x0]] * (1.0 - fx) + a[[y0, x0 + 1]] * fx;
            let bot = a[[y0 + 1, x0]] * (1.0 - fx) + a[[y0 + 1, x0 + 1]] * fx;
            top * (1.0 - fy) + bot * fy
        };
        (bil(&f.u), bil(&f.v))
    };
    let (mut sum, mut max) = (0.0f64, 0.0f64);
    for &(_, _, _, x, y) in centres {
        let (fu, fv) = at(flow, x, y);
        let (tu, tv) = at(truth, x, y);
        let e = ((fu - tu) as f64).hypot((fv - tv) as f64);
        sum += e;
        max = max.max(e);
    }
    (sum / centres.len() as f64, max)
}

/// Pixels more than `border` px from the edge whose flow is exactly zero
/// where the true motion is at least `moving` px.
fn exact_zeros(flow: &FlowField, truth: &FlowField, moving: f32, border: usize) -> usize {
    let (w, h) = flow.size();
    let mut n = 0;
    for y in border..h - border {
        for x in border..w - border {
            let t = truth.u[[y, x]].hypot(truth.v[[y, x]]);
            if t >= moving && flow.u[[y, x]] == 0.0 && flow.v[[y, x]] == 0.0 {
                n += 1;
            }
        }
    }
    n
}

/// One dot-grid sequence of `simulate shear --dot-grid`: its options and
/// OpenCV 5 MEDIUM's mean and largest endpoint error at the markers on the
/// press-only frame 4 and the fully sheared frame 8.
struct DotGridCase {
    seed: u64,
    pitch: f64,
    dot: f64,
    jitter: f64,
    shear_x: f64,
    /// A fingertip `(x_mm, y_mm, diameter_mm, shear_y_n)` on a thin, stiff
    /// gel (600 kPa, 3 mm) instead of the default rod on the default gel.
    fingertip: Option<(f64, f64, f64, f64)>,
    medium: [(f64, f64); 2],
}

fn dot_grid_case(c: &DotGridCase, presets: &[DisPreset], check_medium_ratio: bool) {
    use optical_tactile_sim::scenario::Shear;
    use optical_tactile_sim::{DotGrid, SimConfig, SyntheticSensor};
    let mut cfg = SimConfig::dot_grid(DotGrid {
        pitch_px: c.pitch,
        diameter_px: c.dot,
        jitter_px: c.jitter,
        ..DotGrid::default()
    });
    let mut shear = Shear {
        shear_n: [c.shear_x, Shear::default().shear_n[1]],
        ..Shear::default()
    };
    if let Some((x, y, diameter, shear_y)) = c.fingertip {
        cfg.material = optical_tactile_sim::Material {
            youngs_kpa: 600.0,
            poisson: 0.47,
            layer_mm: 3.0,
        };
        shear.x_mm = x;
        shear.fingertip_y_mm = Some(y);
        shear.indenter_mm = diameter;
        shear.shear_n[1] = shear_y;
    }
    let sensor = SyntheticSensor::new(cfg, c.seed).unwrap();
    let centres = sensor.marker_positions();
    let reference = sensor.render_indexed(0, &[], false).unwrap().frame;
    for (k, frame) in [4usize, 8].into_iter().enumerate() {
        let rod = shear.press(frame).unwrap();
        let r = sensor.render_indexed(frame as u64, &[rod], true).unwrap();
        let truth = r.flow.unwrap();
        for &preset in presets {
            let flow = flow_of(preset, &reference, &r.frame);
            let (mean, max) = marker_errors(&flow, &truth, &centres);
            // Exact zeros where the skin moves by 0.3 px or more (on the
            // press-only frame parts of the gel move less than that).
            let zeros = exact_zeros(&flow, &truth, 0.3, 16);
            let (m_mean, m_max) = c.medium[k];
            eprintln!(
                "MEASURE dot grid seed {} pitch {} dot {} frame {frame} {preset:?}: markers mean \
                 {mean:.4} max {max:.4} (MEDIUM {m_mean} / {m_max}), exact zeros {zeros}",
                c.seed, c.pitch, c.dot
            );
            assert_eq!(
                zeros, 0,
                "{preset:?}: {zeros} exact-zero pixels, frame {frame}"
            );
            assert!(
                max < 2.0,
                "{preset:?}: marker error up to {max} px, frame {frame}"
            );
            if preset == DisPreset::Fine && check_medium_ratio {
                assert!(
                    mean <= 1.2 * m_mean,
                    "fine: markers mean {mean} vs MEDIUM {m_mean}, frame {frame}"
                );
            }
        }
    }
}

// OpenCV 5 MEDIUM's figures at the markers, measured on the same frames
// (written by `simulate shear --dot-grid --pitch-px P --dot-px D --jitter-px J
// --shear-x-n S --seed N --out DIR`), per frame F (4, 8), with
// `python3 tools/opencv_dis_baseline.py DIR/000000.png DIR/00000F.png
// --truth DIR/flow/00000F.flo --points DIR/markers.csv --presets medium
// --threads 1 --repeat 1` (pts_mean, pts_max), docs/results.md.
const MEDIUM_A4: (f64, f64) = (0.08680, 0.20026);
const MEDIUM_A8: (f64, f64) = (0.15174, 0.36685);
const MEDIUM_B4: (f64, f64) = (0.07050, 0.26624);
const MEDIUM_B8: (f64, f64) = (0.08312, 0.33933);
const MEDIUM_C4: (f64, f64) = (0.04582, 0.12960);
const MEDIUM_C8: (f64, f64) = (0.07142, 0.26867);
// A fingertip on a thin gel: the same with `--fingertip-y-mm 1.5 --x-mm -2
// --indenter-mm 16 --youngs-kpa 600 --layer-mm 3 --force-n 2 --shear-x-n 0.8
// --shear-y-n 0.3` (seed 1, pitch 30, dots 8).
const MEDIUM_D4: (f64, f64) = (0.09641, 0.33369);
const MEDIUM_D8: (f64, f64) = (0.11250, 0.38396);

/// On a regular grid of dark dots on a lit gel, pressed (by a rod, or by a
/// fingertip on a thin gel) and then strongly sheared, the sensor's flow
/// presets leave no exact-zero holes and no
/// gross error at the markers, and `fine` (the sensor's default) stays
/// within 1.2 times OpenCV MEDIUM's mean error there.
#[test]
fn dot_grids_under_press_and_shear() {
    for c in [
        DotGridCase {
            seed: 4,
            pitch: 30.0,
            dot: 8.0,
            jitter: 0.0,
            shear_x: 0.6,
            fingertip: None,
            medium: [MEDIUM_A4, MEDIUM_A8],
        },
        DotGridCase {
            seed: 2,
            pitch: 24.0,
            dot: 8.0,
            jitter: 2.0,
            shear_x: 0.8,
            fingertip: None,
            medium: [MEDIUM_B4, MEDIUM_B8],
        },
    ] {
        dot_grid_case(&c, &ALL_SENSOR_PRESETS, true);
    }
}

/// The sensor's flow presets with full-resolution or half-resolution
/// patches.
const ALL_SENSOR_PRESETS: [DisPreset; 3] =
    [DisPreset::Fine, DisPreset::Accurate, DisPreset::Balanced];

/// A fingertip (16 mm) on a thin, stiff gel, pressed then sheared across
/// both axes: `fine` and `accurate` leave no hole and `fine` stays within
/// 1.2 times MEDIUM's error at the dots (it is at a third of it). A known
/// limit: `balanced` leaves 5 pixels at exactly zero on the sheared frame
/// (checked by `balanced_leaves_a_few_zeros_under_a_sheared_fingertip`).
#[test]
fn a_fingertip_on_a_dot_grid_under_press_and_shear() {
    dot_grid_case(
        &FINGERTIP_CASE,
        &[DisPreset::Fine, DisPreset::Accurate],
        true,
    );
}

const FINGERTIP_CASE: DotGridCase = DotGridCase {
    seed: 1,
    pitch: 30.0,
    dot: 8.0,
    jitter: 0.0,
    shear_x: 0.8,
    fingertip: Some((-2.0, 1.5, 16.0, 0.3)),
    medium: [MEDIUM_D4, MEDIUM_D8],
};

#[test]
#[ignore = "known limit: balanced leaves 5 exact-zero pixels under a sheared fingertip"]
fn balanced_leaves_a_few_zeros_under_a_sheared_fingertip() {
    dot_grid_case(&FINGERTIP_CASE, &[DisPreset::Balanced], false);
}

/// Dots twice the patch size (16 px every 34 px): the dots' inside is
/// untextured at full resolution and takes the coarser level's flow. A
/// known limit of `fine`: no holes and no gross error, but its mean error at
/// the markers is about 1.7 times MEDIUM's there (0.079 against 0.046 px).
#[test]
#[ignore = "known limit: fine's mean error is 1.7x MEDIUM's on dots twice the patch size"]
fn dot_grid_with_large_dots() {
    dot_grid_case(
        &DotGridCase {
            seed: 9,
            pitch: 34.0,
            dot: 16.0,
            jitter: 1.0,
            shear_x: 0.9,
            fingertip: None,
            medium: [MEDIUM_C4, MEDIUM_C8],
        },
        &ALL_SENSOR_PRESETS,
        true,
    );
}

/// Random fluorescent markers at half the default density (another seed),
/// pressed with shear: filling untextured patches from their neighbours
/// (`fill_untextured`) does not make `fine`'s flow worse than leaving them in
/// the search.
#[test]
fn sparse_random_markers_do_not_regress() {
    use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};
    let mut cfg = SimConfig::default();
    cfg.markers.coverage = 0.15;
    let sensor = SyntheticSensor::new(cfg, 11).unwrap();
    let reference = sensor.render_indexed(0, &[], false).unwrap().frame;
    for (k, rod) in [
        Press::rod(-40.0, [0.0, 0.0, -2.5], 5.0),
        Press::rod(30.0, [0.9, 0.3, -2.5], 10.0),
    ]
    .into_iter()
    .enumerate()
    {
        let r = sensor.render_indexed(k as u64 + 1, &[rod], true).unwrap();
        let truth = r.flow.unwrap();
        let run = |fill: bool| {
            let mut dis = Dis::new(DisParams {
                fill_untextured: fill,
                ..DisParams::preset(DisPreset::Fine)
            })
            .unwrap();
            dis.set_reference(&reference).unwrap();
            dis.compute(&r.frame).unwrap().aepe(&truth, 16).unwrap()
        };
        let (filled, searched) = (run(true), run(false));
        eprintln!(
            "MEASURE sparse markers, press {k}: fine {filled:.5}, without the fill {searched:.5}"
        );
        assert!(
            filled <= searched * 1.01,
            "press {k}: {filled} with the fill, {searched} without"
        );
    }
}

/// Whether a texture is sparse is decided on the reference: for `fine` (the
/// one preset with patches that do not overlap) a regular grid of dark dots
/// is sparse, the simulator's random markers (at the default and at half the
/// density, two seeds) are not, and on them the flow is bit for bit the flow
/// of a search that never treats the texture as sparse. The presets with
/// overlapping patches never treat a texture as sparse.
#[test]
fn sparse_texture_is_decided_on_the_reference() {
    use optical_tactile_sim::{DotGrid, Press, SimConfig, SyntheticSensor};
    for preset in DisPreset::ALL {
        let p = DisParams::preset(preset);
        let overlapping = p.patch_stride < p.patch_size;
        assert_eq!(p.sparse_texture < 1.0, !overlapping, "{preset:?}");
    }
    let gated = [DisPreset::Fine];
    for grid in [
        DotGrid::default(),
        DotGrid {
            pitch_px: 24.0,
            jitter_px: 2.0,
            ..DotGrid::default()
        },
        DotGrid {
            pitch_px: 40.0,
            diameter_px: 10.0,
            darkness: 90.0,
            ..DotGrid::default()
        },
    ] {
        let sensor = SyntheticSensor::new(SimConfig::dot_grid(grid), 5).unwrap();
        let reference = sensor.render_indexed(0, &[], false).unwrap().frame;
        for preset in gated {
            let mut dis = Dis::with_preset(preset);
            dis.set_reference(&reference).unwrap();
            eprintln!(
                "MEASURE dot grid pitch {} {preset:?}: untextured {:.3}",
                grid.pitch_px,
                dis.untextured_fraction()
            );
            assert!(dis.sparse_texture(), "{preset:?} on a dot grid");
        }
    }
    for (seed, coverage) in [(1u64, None), (2, None), (11, Some(0.15))] {
        let mut cfg = SimConfig::default();
        if let Some(c) = coverage {
            cfg.markers.coverage = c;
        }
        let sensor = SyntheticSensor::new(cfg, seed).unwrap();
        let reference = sensor.render_indexed(0, &[], false).unwrap().frame;
        let rod = Press::rod(20.0, [0.6, 0.2, -2.0], 5.0);
        let frame = sensor.render_indexed(1, &[rod], false).unwrap().frame;
        for preset in gated {
            let mut dis = Dis::with_preset(preset);
            dis.set_reference(&reference).unwrap();
            eprintln!(
                "MEASURE strip seed {seed} {preset:?}: untextured {:.3}",
                dis.untextured_fraction()
            );
            assert!(
                !dis.sparse_texture(),
                "{preset:?} on the strip, seed {seed}"
            );
            let dense = Dis::new(DisParams {
                sparse_texture: 1.0,
                ..DisParams::preset(preset)
            });
            let mut dense = dense.unwrap();
            dense.set_reference(&reference).unwrap();
            let (a, b) = (dis.compute(&frame).unwrap(), dense.compute(&frame).unwrap());
            assert!(a.u == b.u && a.v == b.v, "{preset:?}, seed {seed}");
        }
    }
    let bad = DisParams {
        sparse_texture: 1.5,
        ..DisParams::preset(DisPreset::Fine)
    };
    assert!(matches!(Dis::new(bad), Err(Error::InvalidParameter { .. })));
    let nan = DisParams {
        sparse_texture: f32::NAN,
        ..DisParams::preset(DisPreset::Fine)
    };
    assert!(matches!(Dis::new(nan), Err(Error::InvalidParameter { .. })));
}

/// `Dis::textured_coverage_into` on a skin of markers inside a plain, noisy
/// surround (the dark coating past a sensor's skin): every pixel well inside
/// the markers is covered, none well outside them, for any placement of the
/// skin, marker pitch and noise.
#[test]
fn textured_coverage_follows_the_markers() {
    let (w, h) = (160usize, 96usize);
    runner(12)
        .run(
            &(
                (0usize..40, 0usize..30),
                (60usize..120, 40usize..66),
                3.5f64..6.0,
                0.0f64..1.5,
                0u64..1000,
            ),
            |((x0, y0), (sw, sh), pitch, noise, seed)| {
                let (x1, y1) = ((x0 + sw).min(w), (y0 + sh).min(h));
                // Markers (dark, sigma 1 px) whose blobs stay inside the skin.
                let inside = |&(x, y): &(f64, f64)| {
                    x >= x0 as f64 + 4.0
                        && x < x1 as f64 - 4.0
                        && y >= y0 as f64 + 4.0
                        && y < y1 as f64 - 4.0
                };
                let centres: Vec<_> = support::marker_centres(w, h, pitch, seed)
                    .into_iter()
                    .filter(inside)
                    .collect();
                let mut rng = support::Rng::new(seed ^ 0x5eed);
                let mut img = support::render_markers(w, h, &centres, 1.0);
                for v in img.iter_mut() {
                    // About Gaussian, of sd `noise`: a sum of 12 uniforms.
                    let u: f64 = (0..12).map(|_| rng.uniform()).sum::<f64>() - 6.0;
                    *v = (*v + (noise * u) as f32).clamp(0.0, 255.0);
                }
                let mut dis = Dis::with_preset(DisPreset::Fine);
                dis.set_reference(&img).unwrap();
                let mut covered = Vec::new();
                let (cw, ch) = dis.textured_coverage_into(&mut covered);
                prop_assert_eq!((cw, ch), (w, h));
                prop_assert_eq!(covered.len(), w * h);
                // Distance (in pixels, per axis) from the marker blobs' region.
                let (mx0, my0, mx1, my1) = (x0 + 4, y0 + 4, x1 - 4, y1 - 4);
                let patch = dis.params().patch_size;
                // The prefilter and gradient reach 3 px past a blob's 4-sigma
                // extent; a pixel's patch reaches `patch - 1` px beyond it.
                let reach = patch - 1 + 3 + 4;
                for y in 0..h {
                    for x in 0..w {
                        let c = covered[y * w + x];
                        let deep_in = x >= mx0 + patch
                            && x + patch < mx1
                            && y >= my0 + patch
                            && y + patch < my1;
                        let far_out = x + reach < mx0
                            || x >= mx1 + reach
                            || y + reach < my0
                            || y >= my1 + reach;
                        if deep_in {
                            prop_assert!(c, "({x}, {y}) inside the skin is not covered");
                        }
                        if far_out {
                            prop_assert!(!c, "({x}, {y}) outside the skin is covered");
                        }
                    }
                }
                Ok(())
            },
        )
        .unwrap();
}

/// At rest, on dot grids of many pitches, dot sizes and layouts, `fine`
/// finds little motion anywhere, between the dots included (99% of the
/// pixels below 0.6 px, none above 1.5 px): on a sparse texture its
/// untextured patches take the motion of the textured patches around them,
/// not the coarse levels' guesses (which left up to 4 px of bogus motion on
/// the flat gel, 2.7 px at the 99th percentile).
#[test]
fn dot_grids_at_rest_show_no_motion_between_the_dots() {
    use optical_tactile_sim::{DotGrid, SimConfig, SyntheticSensor};
    runner(12)
        .run(
            &(22.0f64..40.0, 6.0f64..12.0, 0.0f64..2.0, 0u64..1000),
            |(pitch, dot, jitter, seed)| {
                let cfg = SimConfig::dot_grid(DotGrid {
                    pitch_px: pitch,
                    diameter_px: dot,
                    jitter_px: jitter,
                    ..DotGrid::default()
                });
                let sim = SyntheticSensor::new(cfg, seed).unwrap();
                let reference = sim.render_indexed(0, &[], false).unwrap().frame;
                let frame = sim.render_indexed(1, &[], false).unwrap().frame;
                let flow = flow_of(DisPreset::Fine, &reference, &frame);
                let (w, h) = flow.size();
                let mut all = Vec::new();
                for y in 16..h - 16 {
                    for x in 16..w - 16 {
                        all.push(flow.u[[y, x]].hypot(flow.v[[y, x]]));
                    }
                }
                all.sort_by(f32::total_cmp);
                let (p99, max) = (all[all.len() * 99 / 100], all[all.len() - 1]);
                eprintln!(
                    "MEASURE rest dot grid pitch {pitch:.1} dot {dot:.1}: |flow| p99 {p99:.3}, max {max:.3}"
                );
                prop_assert!(p99 < 0.6 && max < 1.5, "pitch {pitch}, dot {dot}: p99 {p99}, max {max} px");
                Ok(())
            },
        )
        .unwrap();
}
