//! The synthetic sensor: mechanics, rendering, determinism, scenarios, errors.

use std::path::PathBuf;

use optical_tactile::Error;
use optical_tactile::io::{self, FrameRecord};
use optical_tactile_sim::elastic::{
    QuadratureCache, RodLoad, line_segment_displacement, point_displacement,
};
use optical_tactile_sim::scenario::{
    self, Common, Mapping, Perches, Presses, Scenario, Single, tilted_force,
};
use optical_tactile_sim::{
    DotGrid, FINGERTIP_GRID, MarkerConfig, MarkerLayout, Material, NoiseConfig, Press,
    SensorOptions, SimConfig, SyntheticSensor,
};
use proptest::prelude::*;

#[path = "common/scratch.rs"]
mod scratch;
use scratch::tmp;

fn sensor() -> SyntheticSensor {
    SyntheticSensor::new(SimConfig::default(), 7).unwrap()
}

fn press(x: f64, f: f64) -> Press {
    Press::rod(x, [0.0, 0.0, -f], 5.0)
}

fn norm(u: [f64; 3]) -> f64 {
    (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt()
}

#[test]
fn normal_press_at_the_centre_is_symmetric() {
    let s = sensor();
    let loads = s.loads(&[press(0.0, 2.0)]).unwrap();
    for &(x, y, z) in &[(1.0, 3.0, 0.5), (4.0, -12.0, 2.0), (9.0, 18.0, 3.5)] {
        let a = s.displacement_at(&loads, x, y, z);
        let b = s.displacement_at(&loads, -x, y, z);
        let c = s.displacement_at(&loads, x, -y, z);
        let tol = 1e-9 * norm(a).max(1e-9);
        assert!(
            (a[0] + b[0]).abs() < tol && (a[1] - b[1]).abs() < tol && (a[2] - b[2]).abs() < tol
        );
        assert!(
            (a[0] - c[0]).abs() < tol && (a[1] + c[1]).abs() < tol && (a[2] - c[2]).abs() < tol
        );
    }
}

#[test]
fn motion_decays_with_distance() {
    let s = sensor();
    let loads = s.loads(&[press(0.0, 2.0)]).unwrap();
    let mags: Vec<f64> = [3.0, 6.0, 12.0, 24.0, 48.0]
        .iter()
        .map(|&d| s.displacement_at(&loads, d, 0.0, 2.0)[0].abs())
        .collect();
    for w in mags.windows(2) {
        assert!(w[1] < w[0], "{mags:?}");
    }
    assert!(mags[4] < 0.05 * mags[0], "{mags:?}");
}

#[test]
fn linear_in_force_at_a_fixed_footprint() {
    let m = Material::default();
    let q = QuadratureCache::default();
    let rod = |k: f64| RodLoad {
        s_mm: 3.0,
        y_lo: -20.0,
        y_hi: 20.0,
        half_width: 1.3,
        force: [0.4 * k, -0.1 * k, 1.7 * k],
    };
    for &(x, y, z) in &[(3.5, 0.0, 0.5), (-2.0, 15.0, 2.0), (20.0, -19.0, 4.0)] {
        let a = rod(1.0).layer(&m, &q, x, y, z);
        let b = rod(-2.5).layer(&m, &q, x, y, z);
        for k in 0..3 {
            assert!((b[k] + 2.5 * a[k]).abs() < 1e-12 * norm(a).max(1e-12) * 10.0);
        }
    }
}

#[test]
fn contacts_superpose() {
    let s = sensor();
    let (a, b) = (press(-30.0, 1.5), Press::rod(10.0, [0.3, -0.2, -2.0], 10.0));
    let la = s.loads(&[a]).unwrap();
    let lb = s.loads(&[b]).unwrap();
    let lab = s.loads(&[a, b]).unwrap();
    for &(x, y, z) in &[(-25.0, 1.0, 1.0), (0.0, -5.0, 2.0), (12.0, 19.0, 0.7)] {
        let ua = s.displacement_at(&la, x, y, z);
        let ub = s.displacement_at(&lb, x, y, z);
        let uab = s.displacement_at(&lab, x, y, z);
        for k in 0..3 {
            assert!((uab[k] - ua[k] - ub[k]).abs() < 1e-12);
        }
    }
}

#[test]
fn markers_spread_outward_below_a_normal_press() {
    let s = sensor();
    let x_c = -40.0;
    let s_c = SimConfig::default().skin.chord_to_arc(x_c).unwrap();
    // Press along the local normal (a vertical press here would add shear).
    let th = (x_c / 220.0f64).asin();
    let normal = Press::rod(x_c, [-2.0 * th.sin(), 0.0, -2.0 * th.cos()], 5.0);
    let d = s.marker_displacements(&[normal]).unwrap();
    let mut checked = 0;
    for (p, u) in s.marker_positions().iter().zip(&d) {
        let off = p.0 - s_c;
        // Below the rod: away from its ends (where the load stops) and its
        // centre line, within a cone of the marker's depth. Further out, the
        // shallowest markers of a slightly compressible gel drift back toward
        // the load (the (1 - 2 nu) surface term of Boussinesq).
        if off.abs() > 0.5 && off.abs() < (8.0 * p.2).min(15.0) && p.1.abs() < 15.0 {
            assert!(
                u[0] * off > 0.0,
                "marker at offset {off} depth {} moved {:?}",
                p.2,
                u
            );
            if off.abs() < 1.0 {
                assert!(u[2] > 0.0, "pressed in under the rod");
            }
            checked += 1;
        }
    }
    assert!(checked > 500, "{checked}");
}

fn max_marker_px(s: &SyntheticSensor, c: Press) -> f64 {
    let cfg = s.config();
    let d = s.marker_displacements(&[c]).unwrap();
    s.marker_positions()
        .iter()
        .zip(&d)
        .map(|(p, u)| {
            let du = cfg.camera.s_to_px(&cfg.skin, p.0 + u[0]) - p.3;
            du.hypot(cfg.camera.px_per_mm_y * u[1])
        })
        .fold(0.0, f64::max)
}

#[test]
fn press_magnitudes_match_the_reference_range() {
    // 0.5-3 N on a 40 mm rod moves markers ~0.3-2 px at ~5 px/mm.
    let s = sensor();
    let lo = max_marker_px(&s, press(0.0, 0.5));
    let hi = max_marker_px(&s, press(0.0, 3.0));
    assert!((0.15..0.6).contains(&lo), "0.5 N: {lo} px");
    assert!((0.9..2.5).contains(&hi), "3 N: {hi} px");
    // A 15 deg tilt adds a larger, translation-like shear.
    let tilted = Press::rod(0.0, scenario::tilted_force(1.5, 0.0, 15.0), 5.0);
    let straight = max_marker_px(&s, press(0.0, 1.5));
    let t = max_marker_px(&s, tilted);
    println!(
        "max marker motion: 0.5 N {lo:.3} px, 3 N {hi:.3} px, 1.5 N {straight:.3} px, 1.5 N at 15 deg {t:.3} px"
    );
    assert!(t > 1.3 * straight, "tilted {t} vs straight {straight}");
}

#[test]
fn shear_moves_markers_along_the_force() {
    // Sensor x is image x and sensor y is image y; a tangential force drags
    // the gel (and the markers) its way.
    let s = sensor();
    for (yaw, pitch, axis, sign) in [
        (0.0, 15.0, 0, 1.0),
        (0.0, -15.0, 0, -1.0),
        (15.0, 0.0, 1, 1.0),
        (-15.0, 0.0, 1, -1.0),
    ] {
        let c = Press::rod(0.0, scenario::tilted_force(2.0, yaw, pitch), 5.0);
        let d = s.marker_displacements(&[c]).unwrap();
        let near: Vec<f64> = s
            .marker_positions()
            .iter()
            .zip(&d)
            .filter(|(p, _)| p.0.abs() < 5.0 && p.1.abs() < 15.0)
            .map(|(_, u)| u[axis])
            .collect();
        let mean = near.iter().sum::<f64>() / near.len() as f64;
        assert!(
            mean * sign > 0.02,
            "yaw {yaw} pitch {pitch}: mean {mean} mm"
        );
    }
}

#[test]
fn identical_output_for_any_thread_count() {
    let s = sensor();
    let c = [press(-20.0, 2.0), Press::rod(30.0, [0.2, 0.1, -1.0], 2.0)];
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let three = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap();
    let a = one.install(|| s.render_indexed(5, &c, true).unwrap());
    let b = three.install(|| s.render_indexed(5, &c, true).unwrap());
    assert_eq!(a.frame, b.frame);
    assert_eq!(a.flow, b.flow);
    // Same seed, new sensor: same frame. Other index: other noise, same markers.
    let again = SyntheticSensor::new(SimConfig::default(), 7).unwrap();
    assert_eq!(again.render_indexed(5, &c, false).unwrap().frame, a.frame);
    let other = s.render_indexed(6, &c, false).unwrap().frame;
    assert_ne!(other, a.frame);
    let mad = (&other - &a.frame).mapv(f32::abs).mean().unwrap();
    assert!(
        mad < 6.0,
        "frames of the same scene differ by {mad} on average"
    );
}

fn noiseless() -> SimConfig {
    SimConfig {
        noise: NoiseConfig {
            shot: 0.0,
            read: 0.0,
            flicker: 0.0,
            ..NoiseConfig::default()
        },
        ..SimConfig::default()
    }
}

fn bilinear(img: &ndarray::Array2<f32>, x: f32, y: f32) -> f32 {
    let (h, w) = img.dim();
    let x = x.clamp(0.0, (w - 1) as f32 - 1e-3);
    let y = y.clamp(0.0, (h - 1) as f32 - 1e-3);
    let (i, j) = (x as usize, y as usize);
    let (fx, fy) = (x - i as f32, y - j as f32);
    (1.0 - fy) * ((1.0 - fx) * img[[j, i]] + fx * img[[j, i + 1]])
        + fy * ((1.0 - fx) * img[[j + 1, i]] + fx * img[[j + 1, i + 1]])
}

#[test]
fn truth_flow_explains_the_rendered_motion() {
    // Markers are re-rendered, never warped; still, warping the reference by the
    // truth flow must reproduce the loaded frame far better than no motion.
    let s = SyntheticSensor::new(noiseless(), 3).unwrap();
    let r0 = s.render_indexed(0, &[], false).unwrap().frame;
    let r1 = s
        .render_indexed(
            1,
            &[Press::rod(0.0, scenario::tilted_force(3.0, 0.0, 15.0), 5.0)],
            true,
        )
        .unwrap();
    let flow = r1.flow.unwrap();
    let (mut e_static, mut e_warp, mut n) = (0.0f64, 0.0f64, 0);
    for y in 20..180 {
        for x in 700..900 {
            let (u, v) = (flow.u[[y, x]], flow.v[[y, x]]);
            let cur = r1.frame[[y, x]];
            e_static += (cur - r0[[y, x]]).abs() as f64;
            e_warp += (cur - bilinear(&r0, x as f32 - u, y as f32 - v)).abs() as f64;
            n += 1;
        }
    }
    let (e_static, e_warp) = (e_static / n as f64, e_warp / n as f64);
    assert!(
        e_warp < 0.5 * e_static,
        "warped {e_warp} vs static {e_static}"
    );
    let peak = flow.magnitude().iter().cloned().fold(0.0f32, f32::max);
    assert!(peak > 1.0, "{peak}");
}

#[test]
fn reference_frame_looks_like_the_sensor() {
    let s = sensor();
    let f = s.render_indexed(0, &[], false).unwrap().frame;
    assert_eq!(f.dim(), (200, 1600));
    assert!(
        f.iter()
            .all(|v| (0.0..=255.0).contains(v) && v.fract() == 0.0)
    );
    // Covered fraction as defined (discs of the spots' FWHM, mean 2.75 px):
    // rasterise the discs at the rest positions over the skin's image area.
    let (mut covered, mut total) = (0usize, 0usize);
    let mut mask = ndarray::Array2::<bool>::default((200, 1600));
    for p in s.marker_positions() {
        let (cx, cy) = (p.3, p.4);
        for y in (cy - 2.0).floor() as i64..=(cy + 2.0).ceil() as i64 {
            for x in (cx - 2.0).floor() as i64..=(cx + 2.0).ceil() as i64 {
                if (0..200).contains(&y)
                    && (0..1600).contains(&x)
                    && (x as f64 - cx).hypot(y as f64 - cy) <= 1.375
                {
                    mask[[y as usize, x as usize]] = true;
                }
            }
        }
    }
    for y in 10..190 {
        for x in 60..1540 {
            total += 1;
            covered += mask[[y, x]] as usize;
        }
    }
    let cov = covered as f64 / total as f64;
    assert!((0.25..0.35).contains(&cov), "coverage {cov}");
    // And the picture: dark gel between spots, most of it brighter than the
    // coating because spot tails overlap.
    let inner = f.slice(ndarray::s![10..190, 60..1540]);
    let dark = inner.iter().filter(|&&v| v < 25.0).count() as f64 / inner.len() as f64;
    assert!((0.1..0.6).contains(&dark), "dark fraction {dark}");
    assert!(s.marker_count() > 10_000);
}

#[test]
fn full_frame_holds_the_strip_at_its_crop() {
    let cfg = SimConfig {
        full_frame: true,
        ..SimConfig::default()
    };
    let s = SyntheticSensor::new(cfg, 7).unwrap();
    let r = s.render_indexed(0, &[press(0.0, 2.0)], true).unwrap();
    assert_eq!(r.frame.dim(), (1080, 1920));
    let (x, y, w, h) = cfg.camera.crop();
    let strip = r.frame.slice(ndarray::s![y..y + h, x..x + w]);
    let mean_in = strip.mean().unwrap();
    let mean_out = r.frame.slice(ndarray::s![0..y, ..]).mean().unwrap();
    assert!(mean_in > 3.0 * mean_out, "{mean_in} vs {mean_out}");
    let flow = r.flow.unwrap();
    assert_eq!(flow.u[[10, 10]], 0.0);
    // The strip of the full frame is the strip image's content (same markers).
    let alone = sensor()
        .render_indexed(0, &[press(0.0, 2.0)], true)
        .unwrap();
    let fa = alone.flow.unwrap();
    // (equal up to f32 rounding of the shifted spot centres)
    let d = (flow.u[[y + 100, x + 800 + 15]] - fa.u[[100, 815]]).abs();
    assert!(d < 1e-4, "{d}");
}

#[test]
fn nonsense_parameters_are_errors() {
    let s = sensor();
    let bad = |c: Press| {
        assert!(
            matches!(s.loads(&[c]), Err(Error::InvalidParameter { .. })),
            "{c:?}"
        )
    };
    bad(press(150.0, 1.0)); // off the skin
    bad(press(f64::NAN, 1.0));
    bad(Press::rod(0.0, [0.0, 0.0, 1.0], 5.0)); // pulls the skin
    bad(Press::rod(0.0, [0.0, f64::INFINITY, -1.0], 5.0));
    bad(Press::rod(0.0, [0.0, 0.0, -1.0], 0.0));
    assert!(s.render_indexed(0, &[press(200.0, 1.0)], true).is_err());
    let with = |m: MarkerConfig| SimConfig {
        markers: m,
        ..SimConfig::default()
    };
    for m in [
        MarkerConfig {
            count: Some(0),
            ..MarkerConfig::default()
        },
        // More markers than the image has pixels: refused before any
        // memory is asked for them (a count of 1e11 would abort the
        // allocation).
        MarkerConfig {
            count: Some(1600 * 200 + 1),
            ..MarkerConfig::default()
        },
        MarkerConfig {
            count: Some(100_000_000_000),
            ..MarkerConfig::default()
        },
        MarkerConfig {
            coverage: 0.0,
            ..MarkerConfig::default()
        },
        MarkerConfig {
            depth_mm: (0.5, 9.0),
            ..MarkerConfig::default()
        },
        MarkerConfig {
            fwhm_px: (3.0, 2.0),
            ..MarkerConfig::default()
        },
    ] {
        assert!(SyntheticSensor::new(with(m), 1).is_err(), "{m:?}");
    }
    let soft = SimConfig {
        material: Material {
            youngs_kpa: 0.0,
            ..Material::default()
        },
        ..SimConfig::default()
    };
    assert!(SyntheticSensor::new(soft, 1).is_err());
}

#[test]
fn scenario_errors_and_unwritable_output() {
    let (_out_dir, out) = tmp("errors");
    let neg = Scenario::Single(Single {
        force_n: -1.0,
        ..Single::default()
    });
    assert!(matches!(
        scenario::run(&neg, &Common::new(&out)),
        Err(Error::InvalidParameter { .. })
    ));
    let off = Scenario::Single(Single {
        x_mm: -160.0,
        ..Single::default()
    });
    assert!(scenario::run(&off, &Common::new(&out)).is_err());
    assert!(!out.exists(), "nothing written for bad parameters");
    // An output path below a regular file cannot be created.
    std::fs::create_dir_all(&out).unwrap();
    let file = out.join("plain-file");
    std::fs::write(&file, b"x").unwrap();
    let ok = Scenario::Single(Single {
        frames: 2,
        ..Single::default()
    });
    assert!(matches!(
        scenario::run(&ok, &Common::new(file.join("sub"))),
        Err(Error::Io { .. })
    ));
}

#[test]
fn single_scenario_writes_frames_truth_and_flow() {
    let (_out_dir, out) = tmp("single");
    let o = Single {
        frames: 3,
        pitch_deg: 15.0,
        force_n: 1.5,
        x_mm: -30.0,
        ..Single::default()
    };
    let sum = scenario::run(&Scenario::Single(o), &Common::new(&out)).unwrap();
    assert_eq!(sum.frames, 3);
    let frames = io::list_frames(&out).unwrap();
    assert_eq!(frames.len(), 3);
    let truth: Vec<FrameRecord> = io::read_jsonl(out.join("truth.jsonl")).unwrap();
    assert_eq!(truth.len(), 3);
    assert!(truth[0].contacts.is_empty());
    let c = &truth[2].contacts[0];
    assert!((c.fx_n - 0.388).abs() < 0.001 && (c.fz_n + 1.449).abs() < 0.001 && c.y_mm == 0.0);
    assert!((c.z_mm - (220f64.powi(2) - 900.0).sqrt() + 60.0).abs() < 1e-9);
    let img = io::read_gray(&frames[2]).unwrap();
    assert_eq!(img.dim(), (200, 1600));
    let flow = io::read_flo(out.join("flow/000002.flo")).unwrap();
    assert!(flow.magnitude().iter().cloned().fold(0.0f32, f32::max) > 0.3);
    assert_eq!(
        io::read_flo(out.join("flow/000000.flo")).unwrap().u.sum(),
        0.0
    );
}

#[test]
fn characterization_subset_follows_the_protocol() {
    let (_out_dir, out) = tmp("char");
    let mut c = Common::new(&out);
    c.flow = false;
    let o = scenario::Characterization {
        subset: Some(4),
        ..Default::default()
    };
    scenario::run(&Scenario::Characterization(o.clone()), &c).unwrap();
    let rows = io::read_tests_csv(out.join("tests.csv")).unwrap();
    assert_eq!(rows.len(), 4);
    for r in &rows {
        assert!(out.join(&r.frame).exists() && out.join(&r.reference).exists());
        let s = (r.point as f64 - 8.0) * 20.0;
        assert!((r.x_mm - 220.0 * (s / 220.0).sin()).abs() < 1e-9);
        let f = scenario::tilted_force(r.force_n, r.yaw_deg, r.pitch_deg);
        // Load-cell noise is small but present.
        let err =
            ((r.fx_n - f[0]).powi(2) + (r.fy_n - f[1]).powi(2) + (r.fz_n - f[2]).powi(2)).sqrt();
        assert!(err > 0.0 && err < 0.08, "{err}");
        assert_eq!(r.split == io::Split::Train, ![5, 8, 11].contains(&r.point));
    }
    // The same seed picks the same tests.
    let (_out2_dir, out2) = tmp("char2");
    c.out = out2.clone();
    scenario::run(&Scenario::Characterization(o), &c).unwrap();
    let rows2 = io::read_tests_csv(out2.join("tests.csv")).unwrap();
    assert_eq!(rows, rows2);
}

#[test]
fn characterization_writes_sweeps_along_the_training_points() {
    let (_out_dir, out) = tmp("char_sweeps");
    let mut c = Common::new(&out);
    c.flow = false;
    let o = scenario::Characterization {
        subset: Some(2),
        sweep_step_mm: Some(40.0),
        ..Default::default()
    };
    let summary = scenario::run(&Scenario::Characterization(o), &c).unwrap();
    let rows = io::read_sweeps_csv(out.join("sweeps.csv")).unwrap();
    // Arc -120..120 mm every 40 mm: 7 images per sweep, and one reference each.
    assert_eq!(rows.len(), 7 * scenario::SWEEPS.len());
    assert_eq!(summary.frames, 2 * 2 + rows.len() + scenario::SWEEPS.len());
    for (k, &(indenter, force)) in scenario::SWEEPS.iter().enumerate() {
        let sweep: Vec<_> = rows.iter().filter(|r| r.sweep == k as u32).collect();
        assert_eq!(sweep.len(), 7);
        for (i, r) in sweep.iter().enumerate() {
            let s = -120.0 + 40.0 * i as f64;
            assert!((r.x_mm - 220.0 * (s / 220.0).sin()).abs() < 1e-9);
            assert_eq!((r.indenter_mm, r.force_n, r.y_mm), (indenter, force, 0.0));
            // Straight down, with the load cell's noise.
            assert!(
                (r.fz_n + force).abs() < 0.02 && r.fx_n.abs() < 0.02,
                "{r:?}"
            );
            assert!(out.join(&r.frame).exists() && out.join(&r.reference).exists());
        }
    }
    // With the tilted sweeps: the same straight sweeps, then the 5 mm rod's
    // force turned by each tilt along the strip.
    let (_tilted_dir, tilted) = tmp("char_tilted_sweeps");
    c.out = tilted.clone();
    let o = scenario::Characterization {
        subset: Some(2),
        sweep_step_mm: Some(40.0),
        tilted_sweeps: true,
        ..Default::default()
    };
    let summary = scenario::run(&Scenario::Characterization(o), &c).unwrap();
    let all = io::read_sweeps_csv(tilted.join("sweeps.csv")).unwrap();
    let sweeps = scenario::SWEEPS.len() + scenario::TILTED_SWEEPS.len();
    assert_eq!(all.len(), 7 * sweeps);
    assert_eq!(summary.frames, 2 * 2 + all.len() + sweeps);
    for (k, &(indenter, force, pitch)) in scenario::TILTED_SWEEPS.iter().enumerate() {
        let k = (scenario::SWEEPS.len() + k) as u32;
        let sweep: Vec<_> = all.iter().filter(|r| r.sweep == k).collect();
        assert_eq!(sweep.len(), 7);
        let f = scenario::tilted_force(force, 0.0, pitch);
        for r in sweep {
            assert_eq!((r.indenter_mm, r.force_n), (indenter, force));
            assert!(
                (r.fx_n - f[0]).abs() < 0.02 && (r.fz_n - f[2]).abs() < 0.02 && f[0].abs() > 0.5,
                "{r:?}"
            );
        }
    }
    // The straight sweeps come first, as without the tilted ones.
    assert_eq!(&all[..rows.len()], &rows[..]);
    // A subset alone writes none; a step of 0 none either; a tiny step is refused.
    let (_bare_dir, bare) = tmp("char_no_sweeps");
    c.out = bare.clone();
    let o = scenario::Characterization {
        subset: Some(2),
        ..Default::default()
    };
    scenario::run(&Scenario::Characterization(o), &c).unwrap();
    assert!(!bare.join("sweeps.csv").exists());
    let (_tiny_dir, tiny) = tmp("char_tiny_sweeps");
    c.out = tiny.clone();
    let o = scenario::Characterization {
        subset: Some(1),
        sweep_step_mm: Some(1e-6),
        ..Default::default()
    };
    let e = scenario::run(&Scenario::Characterization(o), &c).unwrap_err();
    assert!(e.to_string().contains("sweep_step_mm"), "{e}");
}

#[test]
fn presses_land_anywhere_in_range_each_against_the_reference() {
    let (_out_dir, out) = tmp("presses");
    let mut c = Common::new(&out);
    c.flow = false;
    let o = Presses {
        presses: 6,
        x_max_mm: 90.0,
        force_min_n: 1.0,
        force_max_n: 2.0,
        max_tilt_deg: 10.0,
        indenters_mm: vec![2.0, 10.0],
        press_seed: None,
    };
    let sum = scenario::run(&Scenario::Presses(o.clone()), &c).unwrap();
    assert_eq!(sum.frames, 7);
    let truth: Vec<FrameRecord> = io::read_jsonl(out.join("truth.jsonl")).unwrap();
    assert_eq!(truth.len(), 7);
    assert!(truth[0].contacts.is_empty());
    let info: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(out.join("presses.json")).unwrap()).unwrap();
    assert_eq!(info.len(), 6);
    let mut xs = vec![];
    for (t, i) in truth[1..].iter().zip(&info) {
        assert_eq!(t.contacts.len(), 1);
        assert_eq!(i["frame"].as_str().unwrap(), t.frame);
        let ct = &t.contacts[0];
        assert!(ct.x_mm.abs() <= 90.0, "{}", ct.x_mm);
        let f = [ct.fx_n, ct.fy_n, ct.fz_n];
        assert!((1.0..=2.0).contains(&norm(f)), "{f:?}");
        // One tilt axis at a time, within the range, and the force is the
        // tilted force that the record says.
        let (yaw, pitch) = (
            i["yaw_deg"].as_f64().unwrap(),
            i["pitch_deg"].as_f64().unwrap(),
        );
        assert!(yaw == 0.0 || pitch == 0.0);
        assert!(yaw.abs() <= 10.0 && pitch.abs() <= 10.0);
        let want = tilted_force(norm(f), yaw, pitch);
        assert!(f.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-9));
        assert!([2.0, 10.0].contains(&i["indenter_mm"].as_f64().unwrap()));
        xs.push(ct.x_mm);
    }
    // Spread out, not one place.
    let spread =
        xs.iter().cloned().fold(f64::MIN, f64::max) - xs.iter().cloned().fold(f64::MAX, f64::min);
    assert!(spread > 20.0, "{xs:?}");
    // The same seed draws the same presses.
    let (_again_dir, again) = tmp("presses2");
    c.out = again.clone();
    scenario::run(&Scenario::Presses(o.clone()), &c).unwrap();
    let truth2: Vec<FrameRecord> = io::read_jsonl(again.join("truth.jsonl")).unwrap();
    assert_eq!(truth, truth2);
    // Another press seed: other presses on the same sensor (the same
    // reference frame, so the same markers).
    let (_other_dir, other) = tmp("presses3");
    c.out = other.clone();
    let o3 = Presses {
        press_seed: Some(c.seed + 1),
        ..o.clone()
    };
    scenario::run(&Scenario::Presses(o3), &c).unwrap();
    let truth3: Vec<FrameRecord> = io::read_jsonl(other.join("truth.jsonl")).unwrap();
    assert_eq!(truth3.len(), 7);
    assert_ne!(truth3[1..], truth[1..]);
    let reference = |d: &std::path::Path| std::fs::read(d.join(&truth[0].frame)).unwrap();
    assert_eq!(reference(&out), reference(&other));
    // Bad options fail before anything is written.
    let (_bad_dir, bad) = tmp("presses-bad");
    c.out = bad.clone();
    for o in [
        Presses {
            presses: 0,
            ..Presses::default()
        },
        Presses {
            force_min_n: 3.0,
            force_max_n: 1.0,
            ..Presses::default()
        },
        Presses {
            x_max_mm: f64::NAN,
            ..Presses::default()
        },
        Presses {
            max_tilt_deg: 90.0,
            ..Presses::default()
        },
        Presses {
            indenters_mm: vec![],
            ..Presses::default()
        },
        // Off the skin.
        Presses {
            x_max_mm: 400.0,
            ..Presses::default()
        },
    ] {
        assert!(scenario::run(&Scenario::Presses(o), &c).is_err());
        assert!(!bad.join("truth.jsonl").exists());
    }
}

#[test]
fn perches_and_mapping_write_their_extras() {
    let (_out_dir, out) = tmp("perch");
    let mut c = Common::new(&out);
    c.flow = false;
    let p = Perches {
        frames: 3,
        ..Perches::default()
    };
    scenario::run(&Scenario::Perches(p.clone()), &c).unwrap();
    let truth: Vec<FrameRecord> = io::read_jsonl(out.join("truth.jsonl")).unwrap();
    let last = &truth[2].contacts;
    // Equal penetration: the stiffer perch pushes back harder.
    assert!(
        (last[1].fz_n / last[0].fz_n - p.stiffness_n_per_mm[1] / p.stiffness_n_per_mm[0]).abs()
            < 1e-9
    );
    assert!(out.join("perches.json").exists());

    let (_out_dir, out) = tmp("map");
    c.out = out.clone();
    let m = Mapping {
        rods_x_m: vec![0.5, 1.0],
        touches: 1,
        ..Mapping::default()
    };
    let sum = scenario::run(&Scenario::Mapping(m.clone()), &c).unwrap();
    let poses = io::read_poses_csv(out.join("poses.csv")).unwrap();
    let truth: Vec<FrameRecord> = io::read_jsonl(out.join("truth.jsonl")).unwrap();
    assert_eq!(poses.len(), sum.frames);
    assert_eq!(truth.len(), sum.frames);
    let mut touched = vec![];
    for (p, t) in poses.iter().zip(&truth) {
        assert_eq!(p.frame, t.frame);
        for ct in &t.contacts {
            // Sensor x = body x: the contact's world x is the rod's.
            let wx = p.x_m + ct.x_mm * 1e-3;
            assert!(m.rods_x_m.iter().any(|r| (r - wx).abs() < 1e-9), "{wx}");
            // The skin point touches the rod's top (sensor z = -body z).
            let wz = p.z_m - ct.z_mm * 1e-3;
            assert!(
                wz <= m.rods_top_m + 1e-12 && wz > m.rods_top_m - 2e-3,
                "{wz}"
            );
            touched.push(wx);
        }
    }
    assert!(touched.len() >= 2);
    assert!(out.join("rods.json").exists());
}

#[test]
fn committed_fixtures_are_what_the_simulator_makes() {
    // If this fails, the simulator changed: regenerate the fixtures with the
    // command in fixtures/README.md.
    let (_out_dir, out) = tmp("fixtures");
    scenario::fixtures(&out, 1).unwrap();
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fixtures");
    for f in [
        "press/truth.jsonl",
        "characterization/tests.csv",
        "flat_press/truth.jsonl",
        "flat_press/presses.json",
    ] {
        let a = std::fs::read_to_string(out.join(f)).unwrap();
        let b = std::fs::read_to_string(repo.join(f)).unwrap();
        assert_eq!(a, b, "{f}");
    }
    let mut n = 0;
    for dir in ["press", "characterization/frames", "flat_press"] {
        for p in io::list_frames(out.join(dir)).unwrap() {
            let name = p.strip_prefix(&out).unwrap();
            let a = io::read_gray(&p).unwrap();
            let b = io::read_gray(repo.join(name)).unwrap();
            assert!(
                a == b,
                "{} differs from the committed fixture",
                name.display()
            );
            n += 1;
        }
    }
    assert_eq!(n, 8 + 12 + 12);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, rng_seed: proptest::test_runner::RngSeed::Fixed(11), failure_persistence: None, ..ProptestConfig::default() })]

    /// The closed-form integral along the rod equals a brute-force sum of the
    /// point solutions (sinh-spaced midpoints, dense at the 1/r peak).
    #[test]
    fn line_integral_equals_sum_of_point_loads(
        x in -15.0f64..15.0, ya in -30.0f64..30.0, len in 0.5f64..45.0,
        z in 0.3f64..5.0, fx in -1.0f64..1.0, fy in -1.0f64..1.0, fn_ in 0.0f64..2.0,
    ) {
        let m = Material::default();
        let f = [fx, fy, fn_];
        let (y1, y2) = (ya, ya + len);
        let got = line_segment_displacement(&m, f, x, y1, y2, z);
        let c = (x * x + z * z).sqrt();
        let (t1, t2) = ((y1 / c).asinh(), (y2 / c).asinh());
        let n = 6000;
        let h = (t2 - t1) / n as f64;
        let mut want = [0.0; 3];
        for i in 0..n {
            let t = t1 + (i as f64 + 0.5) * h;
            let p = point_displacement(&m, f, [x, c * t.sinh(), z]);
            for k in 0..3 { want[k] += p[k] * c * t.cosh() * h; }
        }
        let scale = norm(want).max(1e-6);
        for k in 0..3 {
            prop_assert!((got[k] - want[k]).abs() < 1e-5 * scale, "{k}: {} vs {}", got[k], want[k]);
        }
    }

    /// Gauss-Chebyshev across the Hertz footprint equals a fine brute-force sum.
    #[test]
    fn footprint_quadrature_equals_brute_force(
        b in 0.2f64..2.5, off in -8.0f64..8.0, y in -19.0f64..19.0, z in 0.5f64..4.0,
    ) {
        let m = Material::default();
        let q = QuadratureCache::default();
        let rod = RodLoad { s_mm: 0.0, y_lo: -20.0, y_hi: 20.0, half_width: b, force: [0.5, 0.2, 1.0] };
        let got = rod.half_space(&m, &q, off, y, z);
        let n = 3000;
        let mut want = [0.0; 3];
        let f = [0.5 / 40.0, 0.2 / 40.0, 1.0 / 40.0];
        for i in 0..n {
            let phi = -std::f64::consts::FRAC_PI_2 + (i as f64 + 0.5) * std::f64::consts::PI / n as f64;
            let w = 2.0 * phi.cos().powi(2) / n as f64;
            let d = line_segment_displacement(&m, f, off - b * phi.sin(), y - 20.0, y + 20.0, z);
            for k in 0..3 { want[k] += w * d[k]; }
        }
        let scale = norm(want).max(1e-9);
        for k in 0..3 {
            prop_assert!((got[k] - want[k]).abs() < 3e-3 * scale, "{k}: {} vs {}", got[k], want[k]);
        }
    }
}

#[test]
fn single_sweep_moves_one_load_along_the_skin() {
    let (_out_dir, out) = tmp("sweep");
    let mut c = Common::new(&out);
    c.flow = false;
    let o = Single {
        frames: 5,
        force_n: 2.0,
        pitch_deg: 15.0,
        x_mm: 10.0,
        sweep_to_mm: Some(13.0),
        ..Single::default()
    };
    // Frames 1..=4 at 10, 11, 12, 13 mm, each at the full force.
    let want_x = [10.0, 11.0, 12.0, 13.0];
    for (k, x) in want_x.iter().enumerate() {
        let p = o.press(k + 1).unwrap();
        assert!((p.x_mm - x).abs() < 1e-12, "frame {}: {}", k + 1, p.x_mm);
    }
    assert!(o.press(0).is_none());
    scenario::run(&Scenario::Single(o.clone()), &c).unwrap();
    let truth: Vec<FrameRecord> = io::read_jsonl(out.join("truth.jsonl")).unwrap();
    assert_eq!(truth.len(), 5);
    assert!(truth[0].contacts.is_empty());
    let f = tilted_force(2.0, 0.0, 15.0);
    let mut last_x = f64::NEG_INFINITY;
    for r in &truth[1..] {
        let t = &r.contacts[0];
        assert!((t.fx_n - f[0]).abs() < 1e-9 && (t.fz_n - f[2]).abs() < 1e-9);
        assert!(t.x_mm > last_x, "the chord position grows along the sweep");
        last_x = t.x_mm;
    }
    std::fs::remove_dir_all(&out).unwrap();
    // An end off the skin or a non-finite end: an error, nothing written.
    for to in [400.0, f64::NAN] {
        let bad = Single {
            sweep_to_mm: Some(to),
            ..o.clone()
        };
        assert!(scenario::run(&Scenario::Single(bad), &c).is_err(), "{to}");
        assert!(!out.exists());
    }
}

/// The command line's sensor options: none given is the sensor itself; each
/// given lands in its field, over the sensor asked for.
#[test]
fn sensor_options_over_the_three_sensors() {
    let none = SensorOptions::default();
    assert_eq!(none.config(), SimConfig::default());
    let tip = SensorOptions {
        fingertip: true,
        ..none.clone()
    };
    assert_eq!(tip.config(), SimConfig::fingertip());
    let grid = SensorOptions {
        dot_grid: true,
        ..none.clone()
    };
    assert_eq!(grid.config(), SimConfig::dot_grid(DotGrid::default()));
    let asked = SensorOptions {
        fingertip: true,
        pitch_px: Some(26.0),
        youngs_kpa: Some(800.0),
        markers: Some(900),
        marker_depth_mm: Some((0.4, 0.6)),
        noise_read: Some(2.5),
        exposure_steps: vec![5.0, 0.02],
        drift: vec![0.05, 3.0, 40.0],
        ..none.clone()
    };
    let c = asked.config();
    let MarkerLayout::Grid(g) = c.markers.layout else {
        panic!("{:?}", c.markers.layout)
    };
    assert_eq!(
        (g.pitch_px, g.diameter_px),
        (26.0, FINGERTIP_GRID.diameter_px)
    );
    assert_eq!(c.material.youngs_kpa, 800.0);
    assert_eq!(
        c.material.layer_mm,
        SimConfig::fingertip().material.layer_mm
    );
    assert_eq!(
        (c.markers.count, c.markers.depth_mm),
        (Some(900), (0.4, 0.6))
    );
    assert_eq!(c.noise.read, 2.5);
    let e = c.noise.exposure;
    assert_eq!(
        (e.step_every, e.step_gain, e.step_offset, e.step_levels),
        (5, 0.02, 0.0, 2)
    );
    assert_eq!(
        (e.drift_gain, e.drift_offset, e.drift_period),
        (0.05, 3.0, 40.0)
    );
    assert!(c.validate().is_ok());
    let beads = SensorOptions {
        random_markers: true,
        ..tip
    };
    assert_eq!(
        beads.config(),
        SimConfig::fingertip_with(MarkerLayout::Random)
    );
}
