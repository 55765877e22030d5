//! The flat fingertip sensor: its preset, the lens distortion, round
//! indenters, the flat characterization protocol, presses in x and y, and
//! what bad input gives.

use optical_tactile::Error;
use optical_tactile::geometry::{FlatSurface, SensorGeometry};
use optical_tactile::io::{self, FrameRecord, Split};
use optical_tactile_sim::scenario::{
    self, Characterization, Common, FLAT_HELD_OUT_POINTS, Scenario, TipPresses, tilted_force,
};
use optical_tactile_sim::{
    CameraModel, FINGERTIP_LENGTH_MM, FINGERTIP_WIDTH_MM, MarkerLayout, Press, SimConfig, Skin,
    SyntheticSensor, Tip,
};
use proptest::prelude::*;

#[path = "common/scratch.rs"]
mod scratch;
use scratch::tmp;

fn fingertip() -> SyntheticSensor {
    SyntheticSensor::new(SimConfig::fingertip(), 3).unwrap()
}

#[test]
fn the_preset_is_a_flat_gelsight_mini_class_sensor() {
    let cfg = SimConfig::fingertip();
    cfg.validate().unwrap();
    assert_eq!(
        cfg.skin.geometry,
        SensorGeometry::Flat(FlatSurface {
            length_mm: FINGERTIP_LENGTH_MM,
            width_mm: FINGERTIP_WIDTH_MM,
        })
    );
    assert_eq!(cfg.image_size(), (320, 240));
    assert!(!cfg.full_frame);
    assert!(cfg.skin.radius_mm().is_infinite());
    let cam = &cfg.camera;
    assert!((12.0..=14.0).contains(&cam.px_per_mm_s) && cam.px_per_mm_s == cam.px_per_mm_y);
    assert!(cam.radial != 0.0);
    assert!(matches!(cfg.markers.layout, MarkerLayout::Grid(_)));
    // The dots are dark on a lit gel: the reference frame is bright with
    // dark spots, and darker outside the gel (the corners).
    let s = fingertip();
    let frame = s.render_indexed(0, &[], false).unwrap().frame;
    let centre = frame[[120, 160]].max(frame[[120, 171]]);
    assert!(centre > 150.0, "{centre}");
    let darkest = frame.iter().cloned().fold(255.0f32, f32::min);
    assert!(darkest < 80.0, "{darkest}");
    assert!(frame[[0, 0]] < 20.0, "corner {}", frame[[0, 0]]);
    assert!(
        (100..=200).contains(&s.marker_count()),
        "{}",
        s.marker_count()
    );
    // Random markers instead: bright spots on a dark gel.
    let random = SimConfig::fingertip_with(MarkerLayout::Random);
    let r = SyntheticSensor::new(random, 3).unwrap();
    let f = r.render_indexed(0, &[], false).unwrap().frame;
    let mean = f.iter().map(|&v| v as f64).sum::<f64>() / f.len() as f64;
    assert!(mean < 120.0 && r.marker_count() > 1000, "{mean}");
}

#[test]
fn the_distortion_bends_both_axes_and_vanishes_at_zero() {
    let cfg = SimConfig::fingertip();
    let (skin, cam) = (&cfg.skin, &cfg.camera);
    // A line of constant y (a row of dots) is bent: its image y changes
    // along x; a line of constant x is bent too.
    let (_, y_mid) = cam.skin_to_px(skin, 0.0, 8.0);
    let (_, y_end) = cam.skin_to_px(skin, 11.0, 8.0);
    assert!((y_mid - y_end).abs() > 2.0, "{y_mid} {y_end}");
    let (x_mid, _) = cam.skin_to_px(skin, 11.0, 0.0);
    let (x_end, _) = cam.skin_to_px(skin, 11.0, 8.5);
    assert!((x_mid - x_end).abs() > 2.0, "{x_mid} {x_end}");
    // Barrel: the edges are pulled in towards the centre.
    assert!(x_mid < cam.s_to_px(skin, 11.0));
    // Without the radial term the map is the separable one, bit for bit.
    let plain = CameraModel {
        radial: 0.0,
        ..*cam
    };
    for (s, y) in [(-11.3, 4.1), (0.0, 0.0), (7.77, -8.9)] {
        assert_eq!(
            plain.skin_to_px(skin, s, y),
            (plain.s_to_px(skin, s), plain.y_to_px(y))
        );
        assert_eq!(plain.undistort(s, y), (s, y));
    }
    // The strip's camera has none.
    assert_eq!(CameraModel::default().radial, 0.0);
    // Out of range, or folding the image over itself: refused.
    for k in [0.3, -0.3, f64::NAN, f64::INFINITY] {
        let bad = CameraModel { radial: k, ..*cam };
        assert!(bad.validate(skin).is_err(), "{k}");
    }
    // A distortion that pushes the gel out of the image: refused.
    let bad = CameraModel {
        radial: 0.2,
        ..*cam
    };
    assert!(bad.validate(skin).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, rng_seed: proptest::test_runner::RngSeed::Fixed(5), failure_persistence: None, ..ProptestConfig::default() })]

    /// The lens map inverts, and is monotonic along both axes and along
    /// every ray from the centre, over the whole gel, for any distortion
    /// the validation accepts.
    #[test]
    fn the_distortion_inverts_and_is_monotonic(
        s in -12.0f64..12.0, y in -9.0f64..9.0, k in -0.12f64..0.04,
        ds in 0.001f64..2.0, dy in 0.001f64..2.0, grow in 1.0001f64..1.2,
    ) {
        let mut cfg = SimConfig::fingertip();
        cfg.camera.radial = k;
        prop_assume!(cfg.validate().is_ok());
        let (skin, cam) = (&cfg.skin, &cfg.camera);
        let (x, yp) = cam.skin_to_px(skin, s, y);
        let (s2, y2) = cam.px_to_skin(skin, x, yp);
        prop_assert!((s2 - s).abs() < 1e-9 && (y2 - y).abs() < 1e-9, "{s2} {y2}");
        // Along x at fixed y, along y at fixed x.
        let s_next = (s + ds).min(12.0);
        let y_next = (y + dy).min(9.0);
        if s_next > s {
            prop_assert!(cam.skin_to_px(skin, s_next, y).0 > x);
        }
        if y_next > y {
            prop_assert!(cam.skin_to_px(skin, s, y_next).1 > yp);
        }
        // Along the ray from the image centre through this point.
        let (cx, cy) = (159.5, 119.5);
        let (xu, yu) = (cam.s_to_px(skin, s), cam.y_to_px(y));
        let (xo, yo) = (cx + (xu - cx) * grow, cy + (yu - cy) * grow);
        let (x_out, y_out) = cam.skin_to_px(skin, cam.px_to_s(skin, xo), cam.px_to_y(yo));
        let r_in = (x - cx).hypot(yp - cy);
        let r_out = (x_out - cx).hypot(y_out - cy);
        prop_assert!(r_out > r_in || r_in < 1e-9, "{r_in} {r_out}");
    }
}

/// The centroid of the true motion's magnitude (pixels moving by more than
/// a tenth of the largest motion), its peak, and the largest motion.
fn motion_centre(flow: &optical_tactile::flow::FlowField) -> ((f64, f64), (f64, f64), f64) {
    let mag = flow.magnitude();
    let max = mag.iter().cloned().fold(0.0f32, f32::max) as f64;
    let (mut w, mut sx, mut sy) = (0.0, 0.0, 0.0);
    let mut peak = (0.0, 0.0);
    for ((y, x), &m) in mag.indexed_iter() {
        let m = m as f64;
        if m >= max {
            peak = (x as f64, y as f64);
        }
        if m > 0.1 * max {
            w += m;
            sx += m * x as f64;
            sy += m * y as f64;
        }
    }
    ((sx / w, sy / w), peak, max)
}

/// A sphere, a flat punch and a sheared fingertip, each off the centre in
/// both x and y: the dots move where the press is, by a few px, and the
/// truth puts the press at the right pixel.
#[test]
fn presses_move_the_dots_where_they_press() {
    let s = fingertip();
    let px_per_mm = s.config().camera.px_per_mm_s;
    let mat = s.config().material;
    let cases = [
        (Tip::Sphere(5.0), -6.0, 3.5, [0.0, 0.0, -2.0]),
        (Tip::Punch(8.0), 5.0, -3.0, [0.0, 0.0, -2.5]),
        (Tip::Fingertip(18.0), 3.0, 2.5, [1.2, -0.8, -2.0]),
        (Tip::Sphere(10.0), -7.0, -4.0, [0.0, 0.4, -1.0]),
    ];
    for (tip, x, y, f) in cases {
        let press = tip.press(x, y, f);
        let truth = scenario::truth_record(&s, &press);
        assert_eq!((truth.x_mm, truth.y_mm, truth.z_mm), (x, y, 0.0));
        let (tx, ty) = (truth.x_px.unwrap(), truth.y_px.unwrap());
        // The truth's pixel is the lens's image of the point.
        let cam = &s.config().camera;
        assert_eq!((tx, ty), cam.skin_to_px(&s.config().skin, x, y));
        let r = s.render_indexed(1, &[press], true).unwrap();
        let flow = r.flow.unwrap();
        let (centre, peak, max) = motion_centre(&flow);
        let radius_px = tip.contact_radius_mm(&mat, -f[2]) * px_per_mm;
        let off = (centre.0 - tx).hypot(centre.1 - ty);
        assert!(
            off < 0.2 * radius_px,
            "{tip:?}: motion centred at {centre:?}, press at ({tx:.1}, {ty:.1}), \
             contact radius {radius_px:.1} px"
        );
        assert!((centre.0 - tx).abs() < 0.2 * radius_px && (centre.1 - ty).abs() < 0.2 * radius_px);
        let peak_off = (peak.0 - tx).hypot(peak.1 - ty);
        assert!(
            peak_off < radius_px,
            "{tip:?}: peak {peak:?} {peak_off:.1} px off"
        );
        assert!((1.0..=20.0).contains(&max), "{tip:?}: {max} px");
        // Nothing moves far from the press.
        let mag = flow.magnitude();
        for ((py, px), &m) in mag.indexed_iter() {
            let d = (px as f64 - tx).hypot(py as f64 - ty);
            if d > 1.5 * radius_px + 10.0 {
                assert!(m < 0.05, "{tip:?}: {m} px at ({px}, {py})");
            }
        }
    }
}

/// A fingertip sheared along +x moves the dots along +x, one sheared along
/// +y along +y (image rows): the axes are not swapped.
#[test]
fn shear_moves_the_dots_along_the_force() {
    let s = fingertip();
    for (f, along_x) in [([1.6, 0.0, -2.0], true), ([0.0, 1.6, -2.0], false)] {
        let press = Press::fingertip(0.0, 0.0, f, 18.0);
        let flow = s.render_indexed(1, &[press], true).unwrap().flow.unwrap();
        let (mut su, mut sv) = (0.0f64, 0.0f64);
        for (u, v) in flow.u.iter().zip(flow.v.iter()) {
            su += *u as f64;
            sv += *v as f64;
        }
        if along_x {
            assert!(su > 10.0 * sv.abs(), "{su} {sv}");
        } else {
            assert!(sv > 10.0 * su.abs(), "{su} {sv}");
        }
    }
}

#[test]
fn the_flat_protocol_writes_a_dataset_on_its_grid() {
    let (_out_dir, out) = tmp("char");
    let mut c = Common::new(&out);
    c.flow = false;
    c.config = SimConfig::fingertip();
    let o = Characterization {
        subset: Some(90),
        ..Characterization::flat()
    };
    scenario::run(&Scenario::Characterization(o), &c).unwrap();
    let rows = io::read_tests_csv(out.join("tests.csv")).unwrap();
    assert_eq!(rows.len(), 90);
    // The geometry for calibrate, and the indenters' kinds.
    let g: SensorGeometry =
        serde_json::from_str(&std::fs::read_to_string(out.join("geometry.json")).unwrap()).unwrap();
    assert_eq!(g, c.config.skin.geometry);
    let kinds: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("indenters.json")).unwrap())
            .unwrap();
    assert_eq!(kinds.as_array().unwrap().len(), 3);
    let xs = [-7.0, -3.5, 0.0, 3.5, 7.0];
    let ys = [-4.0, -4.0 / 3.0, 4.0 / 3.0, 4.0];
    let mut splits = [0usize; 3];
    for r in &rows {
        assert!(out.join(&r.frame).exists() && out.join(&r.reference).exists());
        assert!((1..=20).contains(&r.point));
        let (col, row) = ((r.point - 1) % 5, (r.point - 1) / 5);
        assert!((r.x_mm - xs[col as usize]).abs() < 1e-9, "{r:?}");
        assert!((r.y_mm - ys[row as usize]).abs() < 1e-9, "{r:?}");
        assert!([5.0, 8.0, 18.0].contains(&r.indenter_mm));
        let held_out = FLAT_HELD_OUT_POINTS.contains(&r.point);
        assert_eq!(r.split == Split::Train, !held_out);
        splits[match r.split {
            Split::Train => 0,
            Split::Val => 1,
            Split::Test => 2,
            Split::Spot => panic!("no spot checks with a subset: {r:?}"),
        }] += 1;
        let f = tilted_force(r.force_n, r.yaw_deg, r.pitch_deg);
        let err =
            ((r.fx_n - f[0]).powi(2) + (r.fy_n - f[1]).powi(2) + (r.fz_n - f[2]).powi(2)).sqrt();
        assert!(err > 0.0 && err < 0.05, "{err}");
    }
    assert!(splits.iter().all(|&n| n > 0), "{splits:?}");
    // The held-out points are spread: a corner, the centre, sides.
    let held: Vec<(u32, u32)> = FLAT_HELD_OUT_POINTS
        .iter()
        .map(|p| ((p - 1) % 5, (p - 1) / 5))
        .collect();
    assert!(held.contains(&(0, 0)));
    assert!(held.iter().any(|&(c, _)| c == 2));
    assert!(held.iter().any(|&(c, _)| c == 4));
    assert!(held.iter().any(|&(_, r)| r == 3));
}

/// The rows of a characterization with `spots` spot checks after a
/// subset of `subset` tests, on `config`.
fn with_spot_checks(
    out: &std::path::Path,
    config: SimConfig,
    subset: usize,
    spots: usize,
) -> Vec<io::TestRow> {
    let mut c = Common::new(out);
    c.flow = false;
    c.config = config;
    let o = Characterization {
        subset: Some(subset),
        spot_checks: Some(spots),
        ..Characterization::flat()
    };
    scenario::run(&Scenario::Characterization(o), &c).unwrap();
    io::read_tests_csv(out.join("tests.csv")).unwrap()
}

#[test]
fn spot_checks_press_the_protocols_tips_between_its_points() {
    let (_dir, out) = tmp("spots");
    let rows = with_spot_checks(&out, SimConfig::fingertip(), 10, 80);
    assert_eq!(rows.len(), 90);
    assert!(rows[..10].iter().all(|r| r.split != Split::Spot));
    let spots = &rows[10..];
    let grid = |r: &io::TestRow| {
        let xs = [-7.0, -3.5, 0.0, 3.5, 7.0];
        let ys = [-4.0, -4.0 / 3.0, 4.0 / 3.0, 4.0];
        xs.iter()
            .flat_map(|x| ys.iter().map(move |y| (r.x_mm - x).hypot(r.y_mm - y)))
            .fold(f64::INFINITY, f64::min)
    };
    let mut frames = std::collections::HashSet::new();
    let (mut yawed, mut pitched, mut off_grid) = (0, 0, 0);
    let (mut x_range, mut y_range) = ((f64::MAX, f64::MIN), (f64::MAX, f64::MIN));
    for r in spots {
        assert_eq!((r.split, r.point, r.repeat), (Split::Spot, 0, 1), "{r:?}");
        assert!(out.join(&r.frame).exists() && out.join(&r.reference).exists());
        assert!(frames.insert(r.frame.clone()), "{r:?}");
        assert!([5.0, 8.0, 18.0].contains(&r.indenter_mm), "{r:?}");
        // Within the protocol's ranges: its points' extent, its force
        // ladder, its largest tilt about one axis.
        assert!(r.x_mm.abs() <= 7.0 && r.y_mm.abs() <= 4.0, "{r:?}");
        assert!((0.5..=3.0).contains(&r.force_n), "{r:?}");
        assert!(r.yaw_deg == 0.0 || r.pitch_deg == 0.0, "{r:?}");
        assert!(
            r.yaw_deg.abs() <= 20.0 && r.pitch_deg.abs() <= 20.0,
            "{r:?}"
        );
        yawed += usize::from(r.yaw_deg != 0.0);
        pitched += usize::from(r.pitch_deg != 0.0);
        off_grid += usize::from(grid(r) > 0.5);
        x_range = (x_range.0.min(r.x_mm), x_range.1.max(r.x_mm));
        y_range = (y_range.0.min(r.y_mm), y_range.1.max(r.y_mm));
        let f = tilted_force(r.force_n, r.yaw_deg, r.pitch_deg);
        let err =
            ((r.fx_n - f[0]).powi(2) + (r.fy_n - f[1]).powi(2) + (r.fz_n - f[2]).powi(2)).sqrt();
        assert!(err > 0.0 && err < 0.05, "{err}");
    }
    // Spread over the gel between the points, both tilt axes.
    assert!(yawed > 20 && pitched > 20, "{yawed} {pitched}");
    assert!(off_grid > 60, "{off_grid} of 80 within 0.5 mm of a point");
    assert!(
        x_range.1 - x_range.0 > 11.0 && y_range.1 - y_range.0 > 6.0,
        "{x_range:?} {y_range:?}"
    );
    // The same seed draws the same checks.
    let (_again_dir, again) = tmp("spots_again");
    assert_eq!(
        with_spot_checks(&again, SimConfig::fingertip(), 10, 80),
        rows
    );
}

#[test]
fn spot_checks_on_the_strip_press_its_rods_between_the_points() {
    let (_dir, out) = tmp("strip_spots");
    let rows = with_spot_checks(&out, SimConfig::default(), 2, 12);
    let spots: Vec<&io::TestRow> = rows.iter().filter(|r| r.split == Split::Spot).collect();
    assert_eq!(spots.len(), 12);
    let skin = SimConfig::default().skin;
    let end = skin.arc_to_chord(120.0);
    for r in spots {
        assert!([2.0, 5.0, 10.0].contains(&r.indenter_mm), "{r:?}");
        assert!(r.x_mm.abs() <= end && r.y_mm == 0.0, "{r:?}");
        assert!(
            r.yaw_deg.abs() <= 15.0 && r.pitch_deg.abs() <= 15.0,
            "{r:?}"
        );
        assert!(out.join(&r.frame).exists());
    }
}

#[test]
fn too_many_spot_checks_are_refused_before_anything_is_written() {
    let (_dir, out) = tmp("spots_huge");
    let mut c = Common::new(&out);
    c.config = SimConfig::fingertip();
    let o = Characterization {
        spot_checks: Some(scenario::MAX_SPOT_CHECKS + 1),
        ..Characterization::flat()
    };
    let e = scenario::run(&Scenario::Characterization(o), &c).unwrap_err();
    assert!(e.to_string().contains("spot_checks"), "{e}");
    assert!(!out.exists());
}

#[test]
fn tip_presses_land_anywhere_on_the_gel() {
    let (_out_dir, out) = tmp("presses");
    let mut c = Common::new(&out);
    c.flow = false;
    c.config = SimConfig::fingertip();
    let o = TipPresses {
        presses: 30,
        ..TipPresses::default()
    };
    let sum = scenario::run(&Scenario::TipPresses(o.clone()), &c).unwrap();
    assert_eq!(sum.frames, 31);
    let truth: Vec<FrameRecord> = io::read_jsonl(out.join("truth.jsonl")).unwrap();
    assert!(truth[0].contacts.is_empty());
    let info: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(out.join("presses.json")).unwrap()).unwrap();
    assert_eq!(info.len(), 30);
    let (mut xs, mut ys) = (vec![], vec![]);
    let mut kinds = std::collections::BTreeSet::new();
    for (t, i) in truth[1..].iter().zip(&info) {
        let ct = &t.contacts[0];
        assert_eq!(i["frame"].as_str().unwrap(), t.frame);
        assert_eq!(ct.z_mm, 0.0);
        let contact = i["contact_mm"].as_f64().unwrap();
        assert!(ct.x_mm.abs() + 0.5 * contact <= 12.0 && ct.y_mm.abs() + 0.5 * contact <= 9.0);
        let f = [ct.fx_n, ct.fy_n, ct.fz_n];
        let mag = (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt();
        assert!((0.5 - 1e-9..=3.0 + 1e-9).contains(&mag), "{mag}");
        let kind = i["indenter"].as_str().unwrap().to_string();
        let ratio = f[0].hypot(f[1]) / -f[2];
        assert!((ratio - i["shear_ratio"].as_f64().unwrap()).abs() < 1e-9);
        if kind == "fingertip" {
            assert!(ratio <= 0.8 + 1e-9);
        } else {
            assert!(ratio <= 20f64.to_radians().tan() + 1e-9);
        }
        kinds.insert(kind);
        xs.push(ct.x_mm);
        ys.push(ct.y_mm);
    }
    assert_eq!(kinds.len(), 3, "{kinds:?}");
    let spread = |v: &[f64]| {
        v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min)
    };
    assert!(spread(&xs) > 8.0 && spread(&ys) > 5.0, "{xs:?} {ys:?}");
    // The press seed stated as the sensor's seed draws the same presses;
    // another one other presses on the same sensor (the same reference).
    let run_with = |name: &str, press_seed: Option<u64>| {
        let (dir, out) = tmp(name);
        let mut c2 = c.clone();
        c2.out = out.clone();
        let o2 = TipPresses {
            press_seed,
            ..o.clone()
        };
        scenario::run(&Scenario::TipPresses(o2), &c2).unwrap();
        let t: Vec<FrameRecord> = io::read_jsonl(out.join("truth.jsonl")).unwrap();
        let reference = std::fs::read(out.join(&t[0].frame)).unwrap();
        (dir, t, reference)
    };
    let (_same_dir, same, _) = run_with("presses-same", Some(c.seed));
    assert_eq!(same, truth);
    let (_other_dir, other, other_ref) = run_with("presses-other", Some(c.seed + 1));
    assert_eq!(other.len(), truth.len());
    assert_ne!(other[1..], truth[1..]);
    assert_eq!(other_ref, std::fs::read(out.join(&truth[0].frame)).unwrap());
}

#[test]
fn hostile_presses_are_errors() {
    let s = fingertip();
    let bad = [
        Press::sphere(12.5, 0.0, [0.0, 0.0, -1.0], 5.0), // off the gel in x
        Press::punch(0.0, 9.5, [0.0, 0.0, -1.0], 8.0),   // off the gel in y
        Press::sphere(f64::NAN, 0.0, [0.0, 0.0, -1.0], 5.0),
        Press::sphere(0.0, f64::INFINITY, [0.0, 0.0, -1.0], 5.0),
        Press::sphere(0.0, 0.0, [0.0, 0.0, f64::NAN], 5.0),
        Press::fingertip(0.0, 0.0, [f64::INFINITY, 0.0, -1.0], 18.0),
        Press::sphere(0.0, 0.0, [0.0, 0.0, 1.0], 5.0), // pulls
        Press::punch(0.0, 0.0, [0.0, 0.0, -1.0], 0.0),
        Press::punch(0.0, 0.0, [0.0, 0.0, -1.0], f64::NAN),
        Press::sphere(0.0, 0.0, [0.0, 0.0, -1.0], -5.0),
    ];
    for p in bad {
        assert!(
            matches!(s.loads(&[p]), Err(Error::InvalidParameter { .. })),
            "{p:?}"
        );
        assert!(s.render_indexed(1, &[p], true).is_err(), "{p:?}");
    }
    // Options of the presses and the protocol that cannot work: errors
    // before anything is written.
    let (_out_dir, out) = tmp("hostile");
    let mut c = Common::new(&out);
    c.config = SimConfig::fingertip();
    for o in [
        TipPresses {
            presses: 0,
            ..TipPresses::default()
        },
        TipPresses {
            force_max_n: f64::NAN,
            ..TipPresses::default()
        },
        TipPresses {
            force_min_n: 2.0,
            force_max_n: 1.0,
            ..TipPresses::default()
        },
        TipPresses {
            max_shear_ratio: -0.1,
            ..TipPresses::default()
        },
        TipPresses {
            sphere_mm: (5.0, 3.0),
            ..TipPresses::default()
        },
        TipPresses {
            punch_mm: (f64::NAN, 3.0),
            ..TipPresses::default()
        },
        // No press of this size fits on the gel.
        TipPresses {
            margin_mm: 8.0,
            ..TipPresses::default()
        },
    ] {
        assert!(
            scenario::run(&Scenario::TipPresses(o.clone()), &c).is_err(),
            "{o:?}"
        );
    }
    // A gel so soft that the protocol's contacts do not fit on it.
    c.config.material.youngs_kpa = 0.001;
    let e = scenario::run(&Scenario::Characterization(Characterization::flat()), &c);
    assert!(e.is_err());
    assert!(!out.join("tests.csv").exists());
    // A distortion with NaN, or a flat skin longer than its geometry.
    let mut cfg = SimConfig::fingertip();
    cfg.camera.radial = f64::NAN;
    assert!(SyntheticSensor::new(cfg, 1).is_err());
    let mut cfg = SimConfig::fingertip();
    cfg.skin = Skin {
        length_mm: 30.0,
        ..cfg.skin
    };
    assert!(SyntheticSensor::new(cfg, 1).is_err());
}

/// The gel's light under a contact (`NoiseConfig::contact_light`): off by
/// default; on, a press scales the light at its centre by `1 + change` and
/// one spread either side along x by `1 + sided` and `1 - sided`, and
/// leaves it far from the contact; the frame without contacts is the same
/// either way. Out-of-range changes are errors.
#[test]
fn a_contact_changes_the_gels_light_about_it() {
    use optical_tactile_sim::{ContactLight, NoiseConfig};
    let quiet = |light: ContactLight| {
        let mut c = SimConfig::fingertip();
        // No dots: the gel's light alone.
        if let MarkerLayout::Grid(g) = &mut c.markers.layout {
            g.darkness = 0.0;
        }
        c.noise = NoiseConfig {
            shot: 0.0,
            read: 0.0,
            flicker: 0.0,
            vignetting: 0.0,
            contact_light: light,
            ..c.noise
        };
        SyntheticSensor::new(c, 5).unwrap()
    };
    // A punch of known radius: 4 mm, its light's spread 8/3 mm.
    let press = Press::punch(-2.0, 1.0, [0.0, 0.0, -1.5], 8.0);
    let (x0, y0) =
        SimConfig::fingertip()
            .camera
            .skin_to_px(&SimConfig::fingertip().skin, -2.0, 1.0);
    let spread_px = 8.0 / 3.0 * SimConfig::fingertip().camera.px_per_mm_y;
    let at = |img: &ndarray::Array2<f32>, dx: f64| {
        f64::from(img[[y0.round() as usize, (x0 + dx).round() as usize]])
    };
    let (plain, _) = quiet(ContactLight::default()).render(&[press]).unwrap();
    for (change, sided) in [(-0.4, 0.0), (0.3, 0.0), (0.0, 0.25)] {
        let light = ContactLight { change, sided };
        let mut sim = quiet(light);
        let (rest, _) = sim.render(&[]).unwrap();
        assert_eq!(rest, quiet(ContactLight::default()).render(&[]).unwrap().0);
        let (lit, _) = sim.render(&[press]).unwrap();
        let ratio = |dx: f64| at(&lit, dx) / at(&plain, dx);
        // Grey levels are whole numbers: within one of 180.
        let tol = 1.5 / 180.0;
        assert!(
            (ratio(0.0) - (1.0 + f64::from(change))).abs() < tol,
            "{light:?}: {}",
            ratio(0.0)
        );
        let side = f64::from(sided);
        assert!(
            (ratio(-spread_px) - (1.0 + side) - f64::from(change) * (-0.5f64).exp()).abs() < 0.02,
            "{light:?}: left {}",
            ratio(-spread_px)
        );
        assert!(
            (ratio(spread_px) - (1.0 - side) - f64::from(change) * (-0.5f64).exp()).abs() < 0.02,
            "{light:?}: right {}",
            ratio(spread_px)
        );
        assert!(
            (ratio(6.0 * spread_px.min(20.0)) - 1.0).abs() < tol,
            "{light:?}: far {}",
            ratio(6.0 * spread_px.min(20.0))
        );
    }
    for (change, sided) in [(0.95, 0.0), (0.0, -1.0), (f32::NAN, 0.0)] {
        let mut c = SimConfig::fingertip();
        c.noise.contact_light = ContactLight { change, sided };
        let err = SyntheticSensor::new(c, 5).unwrap_err();
        assert!(err.to_string().contains("contact_light"), "{err}");
    }
}

/// On the flat sensor `single` and `pair` press spheres on the centre line
/// (their rods' diameters), the flat sensor's dots moving under them; the
/// strip's rod scenarios under a drone (perches, mapping, presses of rods)
/// and a pair too wide for the gel are refused before anything is written.
#[test]
fn single_and_pair_press_spheres_and_the_strip_scenarios_are_refused() {
    use optical_tactile_sim::scenario::{Mapping, Pair, Perches, Presses, Single};
    let (_dir, out) = tmp("flat_scenarios");
    let mut c = Common::new(&out);
    c.flow = false;
    c.config = SimConfig::fingertip();
    for (sc, at) in [
        (
            Scenario::Single(Single {
                x_mm: 3.0,
                frames: 3,
                ..Single::default()
            }),
            vec![3.0],
        ),
        (
            Scenario::Pair(Pair {
                frames: 3,
                ..Pair::fingertip()
            }),
            vec![-4.0, 4.0],
        ),
    ] {
        scenario::run(&sc, &c).unwrap();
        let truth: Vec<FrameRecord> = io::read_jsonl(out.join("truth.jsonl")).unwrap();
        let last = truth.last().unwrap();
        let xs: Vec<f64> = last.contacts.iter().map(|p| p.x_mm).collect();
        assert_eq!(xs, at, "{sc:?}");
        assert!(last.contacts.iter().all(|p| p.y_mm == 0.0));
        std::fs::remove_dir_all(&out).unwrap();
    }
    for sc in [
        Scenario::Perches(Perches::default()),
        Scenario::Mapping(Mapping::default()),
        Scenario::Presses(Presses::default()),
        Scenario::Pair(Pair {
            spacing_mm: 30.0,
            ..Pair::fingertip()
        }),
    ] {
        let e = scenario::run(&sc, &c).unwrap_err();
        assert!(matches!(e, Error::InvalidParameter { .. }), "{sc:?}: {e}");
        assert!(!out.exists(), "{sc:?}");
    }
}
