//! The whole pipeline on the bundled two-rod press sequence.

mod common;
use common::linear_calibration;

use optical_tactile::Error;
use optical_tactile::capture::{FrameSource, SequenceSource};
use optical_tactile::flow::dis::{DisParams, DisPreset};
use optical_tactile::frame::Roi;
use optical_tactile::io::{FrameRecord, read_jsonl};
use optical_tactile::segment::Thresholds;
use optical_tactile::sensor::{ContactExtractor, ExtractorConfig, SensorConfig, TactileSensor};

const SEQ: &str = "fixtures/press";

/// Thresholds low enough for the simulator's sub-pixel motion at ~0.6 N and
/// above the accurate preset's rest noise (at most ~0.14 px).
fn sensitive() -> ExtractorConfig {
    ExtractorConfig::default()
        .with_flow(DisParams::preset(DisPreset::Accurate))
        .with_thresholds(Thresholds {
            magnitude: 0.2,
            sum: 600.0,
            ..Thresholds::LOW
        })
}

fn frames() -> Vec<optical_tactile::capture::Frame> {
    let mut seq = SequenceSource::open(SEQ).unwrap();
    std::iter::from_fn(|| seq.next_frame())
        .map(|f| f.unwrap())
        .collect()
}

#[test]
fn both_rods_are_found_where_they_press() {
    let truth: Vec<FrameRecord> = read_jsonl(format!("{SEQ}/truth.jsonl")).unwrap();
    let frames = frames();
    let mut ex = ContactExtractor::new(sensitive()).unwrap();
    ex.set_reference(&frames[0].image).unwrap();
    // The lightest presses (0.29 N and 0.21 N) are below these thresholds.
    assert!(ex.extract(&frames[1].image).unwrap().is_empty());
    // The last frame (2.0 N and 1.5 N): two contacts, each within 10 px (2 mm) of its rod.
    let raws = ex.extract(&frames[7].image).unwrap().to_vec();
    assert_eq!(raws.len(), 2, "{raws:?}");
    let mut xs: Vec<f64> = raws.iter().map(|r| r.x_px).collect();
    xs.sort_by(f64::total_cmp);
    let want: Vec<f64> = truth[7].contacts.iter().map(|c| c.x_px.unwrap()).collect();
    for (x, w) in xs.iter().zip(&want) {
        assert!((x - w).abs() < 10.0, "contact at {x}, rod at {w}");
    }
    // The stronger press (left, 2 N) comes first.
    assert!(raws[0].x_px < raws[1].x_px && raws[0].strength > raws[1].strength);
    for r in &raws {
        assert!(r.dn > 0.0 && r.d_pf > 0.0 && r.area_px > 0);
        assert!(r.bbox.x as f64 <= r.x_px && r.x_px <= (r.bbox.x + r.bbox.w) as f64);
    }
}

/// With the full-resolution `fine` flow, segmentation and the nHHD run on
/// the 2-px analysis grid (the 2x2 mean of the native flow), while
/// `finest_flow` keeps the native flow for the force profiles; both rods are
/// still found where they press.
#[test]
fn fine_flow_is_analysed_on_the_two_pixel_grid() {
    let truth: Vec<FrameRecord> = read_jsonl(format!("{SEQ}/truth.jsonl")).unwrap();
    let frames = frames();
    let config = sensitive().with_flow(DisParams::preset(DisPreset::Fine));
    let mut ex = ContactExtractor::new(config).unwrap();
    assert_eq!(ex.scale(), 2);
    ex.set_reference(&frames[0].image).unwrap();
    let raws = ex.extract(&frames[7].image).unwrap().to_vec();
    let (fine, fs) = ex.finest_flow();
    let (grid, gs) = ex.flow();
    assert_eq!((fs, gs), (1, 2));
    let (w, h) = (frames[7].image.ncols(), frames[7].image.nrows());
    assert_eq!(fine.size(), (w, h));
    assert_eq!(grid.size(), (w / 2, h / 2));
    // Every analysis cell is the mean of its 2x2 block, in the same units.
    for (r, c) in [(0, 0), (37, 350), (50, 450), (99, 799)] {
        for (g, f) in [(&grid.u, &fine.u), (&grid.v, &fine.v)] {
            let mean = (f[[2 * r, 2 * c]]
                + f[[2 * r, 2 * c + 1]]
                + f[[2 * r + 1, 2 * c]]
                + f[[2 * r + 1, 2 * c + 1]])
                / 4.0;
            assert!(
                (g[[r, c]] - mean).abs() < 1e-5,
                "({r}, {c}): {} vs {mean}",
                g[[r, c]]
            );
        }
    }
    assert_eq!(raws.len(), 2, "{raws:?}");
    let mut xs: Vec<f64> = raws.iter().map(|r| r.x_px).collect();
    xs.sort_by(f64::total_cmp);
    for (x, c) in xs.iter().zip(&truth[7].contacts) {
        let want = c.x_px.unwrap();
        assert!((x - want).abs() < 10.0, "contact at {x}, rod at {want}");
    }
}

fn sensor() -> TactileSensor {
    let mut config = SensorConfig::default();
    config.extractor = sensitive();
    TactileSensor::new(config, linear_calibration(Roi::new(0, 0, 1600, 200), None)).unwrap()
}

#[test]
fn contacts_keep_their_ids_and_press_down() {
    let frames = frames();
    let mut s = sensor();
    assert!(matches!(
        s.process(&frames[1].image, 0.02),
        Err(Error::NoReference)
    ));
    s.set_reference(&frames[0].image).unwrap();
    let mut ids = Vec::new();
    for f in &frames[1..] {
        let contacts = s.process(&f.image, f.t_s).unwrap().to_vec();
        if f.index == 7 {
            assert_eq!(contacts.len(), 2, "{contacts:#?}");
            for c in &contacts {
                // Pixel 699.6 and 899.4 map to -20 and +20 mm with this calibration.
                assert!((c.location_mm[0].abs() - 20.0).abs() < 2.0, "{c:?}");
                assert!(c.force_n[2] < 0.0, "a press points down: {c:?}");
                assert!(c.location_mm[2] > 150.0);
            }
        }
        ids.push(contacts.iter().map(|c| c.id).collect::<Vec<_>>());
    }
    // Once both rods are seen, their ids do not change.
    let last = ids.last().unwrap().clone();
    assert_eq!(last.len(), 2);
    let first_full = ids.iter().position(|v| v.len() == 2).unwrap();
    assert!(ids[first_full..].iter().all(|v| *v == last), "{ids:?}");
    let t = s.timings();
    assert!(t.total_ms >= t.flow_ms && t.flow_ms > 0.0);
}

#[test]
fn bad_frames_are_errors_and_change_nothing() {
    let frames = frames();
    let mut s = sensor();
    s.set_reference(&frames[0].image).unwrap();
    let before = s.process(&frames[7].image, 0.14).unwrap().to_vec();
    let small = frames[7].image.slice(ndarray::s![..100, ..]).to_owned();
    assert!(matches!(
        s.process(&small, 0.16),
        Err(Error::ShapeMismatch { .. })
    ));
    let mut nan = frames[7].image.clone();
    nan[[10, 10]] = f32::NAN;
    assert!(s.process(&nan, 0.16).is_err());
    assert_eq!(s.contacts(), &before[..]);
    // A crop outside the frame (forced: it is not the calibration's either).
    let mut config = SensorConfig::default();
    config.crop = Some(Roi::new(100, 0, 1600, 200));
    config.force_crop = true;
    config.extractor = sensitive();
    let mut s =
        TactileSensor::new(config, linear_calibration(Roi::new(0, 0, 1600, 200), None)).unwrap();
    assert!(matches!(
        s.set_reference(&frames[0].image),
        Err(Error::CropOutside { .. })
    ));
}

/// The re-referencing check leaves out tiles where the reference has no
/// texture (the flow is not measurable there).
#[test]
fn the_quiet_check_skips_untextured_tiles() {
    use optical_tactile::FlowField;
    use optical_tactile::sensor::{max_tile_mean, max_tile_mean_where, textured_tiles_into};
    // 40 x 20 reference: a flat left part (x < 16), a checkerboard elsewhere.
    let reference = ndarray::Array2::from_shape_fn((20, 40), |(y, x)| {
        if x < 16 {
            10.0
        } else if (x + y) % 2 == 0 {
            200.0
        } else {
            0.0
        }
    });
    let mut mask = Vec::new();
    let tiles_x = textured_tiles_into(&reference, 8, 4.0, &mut mask);
    // Tiles of 8 px: 5 per row (the last one 8 wide), 3 rows (the last 4 high).
    assert_eq!((tiles_x, mask.len()), (5, 15));
    for (k, &t) in mask.iter().enumerate() {
        assert_eq!(t, k % 5 >= 2, "tile {k}");
    }
    // Flow on a grid of 2 px per cell (20 x 10), tiles of 4 cells: 1.5 px in
    // the flat part, 0.2 px elsewhere.
    let mut flow = FlowField::zeros(20, 10);
    flow.u
        .indexed_iter_mut()
        .for_each(|((_, x), u)| *u = if x < 8 { 1.5 } else { 0.2 });
    assert!((max_tile_mean(&flow, 4) - 1.5).abs() < 1e-6);
    assert!((max_tile_mean_where(&flow, 4, &mask, tiles_x) - 0.2).abs() < 1e-6);
    // No mask: every tile counts.
    assert_eq!(
        max_tile_mean_where(&flow, 4, &[], 0),
        max_tile_mean(&flow, 4)
    );
}

/// A sensor on the bundled calibration, by the main path.
fn bundled(
    builder: impl FnOnce(optical_tactile::SensorBuilder) -> optical_tactile::SensorBuilder,
) -> optical_tactile::Result<TactileSensor> {
    let cal = optical_tactile::Calibration::load("fixtures/calibration.json")?;
    builder(TactileSensor::builder(cal)).build()
}

#[test]
fn a_crop_other_than_the_calibrations_is_an_error_unless_forced() {
    // The calibration's crop is the whole 1600x200 strip image.
    let other = Roi::new(690, 0, 20, 200);
    match bundled(|b| b.crop(other)) {
        Err(Error::InvalidParameter { name, message }) => {
            assert_eq!(name, "crop");
            assert!(
                message.contains("690,0,20,200") && message.contains("0,0,1600,200"),
                "{message}"
            );
        }
        other => panic!("expected a crop error, got {other:?}"),
    }
    // The calibration's own crop, given explicitly, is fine; forced, another one too.
    assert!(bundled(|b| b.crop(Roi::new(0, 0, 1600, 200))).is_ok());
    let mut sensor = bundled(|b| b.crop(Roi::new(100, 0, 1500, 200)).force_crop(true)).unwrap();
    let frames = frames();
    sensor.set_reference(&frames[0].image).unwrap();
    for f in &frames[1..] {
        for c in sensor.process(&f.image, f.t_s).unwrap() {
            assert!(c.is_finite(), "{c:?}");
        }
    }
}

#[test]
fn contacts_say_when_they_leave_the_calibrations_domain() {
    let crop = Roi::new(0, 0, 1600, 200);
    let cal = linear_calibration(crop, None);
    let raw = |x_px: f64| optical_tactile::contact::RawContact {
        x_px,
        y_px: 100.0,
        dn: 100.0,
        d_pf: 2.0,
        d_sensor: [1.0, 0.0, -200.0],
        ..Default::default()
    };
    // x = (x_px - 799.5) / 5 mm: the skin's half chord is 150 mm (x_px 1549.5).
    assert!(!cal.contact(&raw(800.0)).unwrap().out_of_domain);
    assert!(!cal.contact(&raw(1500.0)).unwrap().out_of_domain);
    let off = cal.contact(&raw(1590.0)).unwrap();
    assert!(off.out_of_domain && off.location_mm[0] > 150.0, "{off:?}");
    // The mark and the fallback flag are written to JSON Lines.
    let rec = serde_json::to_value(off.to_record()).unwrap();
    assert_eq!(rec["out_of_domain"], true);
    assert_eq!(rec["fallback"], false);
    // The bundled calibration has a guard: inputs far outside its training box are marked.
    let bundled_cal = optical_tactile::Calibration::load("fixtures/calibration.json").unwrap();
    let mut strong = raw(800.0);
    strong.d_sensor = [0.0, 0.0, -1e6];
    strong.dn = 1e6;
    assert!(bundled_cal.contact(&strong).unwrap().out_of_domain);
}

#[test]
fn non_finite_contacts_never_leave_the_sensor() {
    use optical_tactile::calibration::poly::Polynomial;
    // A calibration whose Fz map overflows on any press: F = 1e308 * dz.
    let crop = Roi::new(0, 0, 1600, 200);
    let base = linear_calibration(crop, None);
    let vars = ["dx", "dy", "dz", "x2d", "y2d", "d_pf"];
    let map = |k: usize, c: f64| {
        let mut e = vec![0u32; 6];
        e[k] = 1;
        Polynomial::raw(&vars, vec![e], vec![c]).unwrap()
    };
    let cal = optical_tactile::Calibration::new(
        base.setup.clone(),
        [
            base.g1().clone(),
            base.g2().clone(),
            map(0, 1e-4),
            map(1, 1e-4),
            map(2, 1e308),
        ],
        None,
    )
    .unwrap();
    let mut config = SensorConfig::from_calibration(&cal).unwrap();
    config.extractor = sensitive();
    let mut sensor = TactileSensor::new(config, cal).unwrap();
    let frames = frames();
    sensor.set_reference(&frames[0].image).unwrap();
    for f in &frames[1..] {
        let contacts = sensor.process(&f.image, f.t_s).unwrap();
        assert!(contacts.iter().all(|c| c.is_finite()), "{contacts:?}");
    }
    assert!(sensor.non_finite_dropped() > 0);
}

/// Without a calibration, `locate` measures the contact column as a new
/// calibration would: on a dot grid pressed by a rod at the middle and then
/// sheared, the slope peak stays near the rod where the divergence
/// potential's minimum (what `extract` gives) slides away under the shear;
/// `PotentialMinimum` leaves the columns as `extract` gave them.
#[test]
fn locate_keeps_the_raw_contact_column_at_the_rod_under_shear() {
    use optical_tactile::contact::ContactPointMethod;
    use optical_tactile_sim::scenario::Shear;
    use optical_tactile_sim::{DotGrid, SimConfig, SyntheticSensor};
    let sim = SyntheticSensor::new(SimConfig::dot_grid(DotGrid::default()), 4).unwrap();
    let shear = Shear {
        shear_n: [0.6, Shear::default().shear_n[1]],
        ..Shear::default()
    };
    let reference = sim.render_indexed(0, &[], false).unwrap().frame;
    // The flow alone: the slope peak of DIS's flow, as the strip measures it.
    let config = ExtractorConfig::default().with_dot_tracking(false);
    let mut ex = ContactExtractor::new(config).unwrap();
    ex.set_reference(&reference).unwrap();
    let rod_px = 0.5 * reference.ncols() as f64; // the rod at x = 0, the middle
    let mut worst = (0.0f64, 0.0f64);
    for frame in 2..=7 {
        let press = shear.press(frame).unwrap();
        let img = sim
            .render_indexed(frame as u64, &[press], false)
            .unwrap()
            .frame;
        let raws = ex.extract(&img).unwrap().to_vec();
        assert_eq!(raws.len(), 1, "frame {frame}: one patch");
        let same = ex.locate(ContactPointMethod::PotentialMinimum).unwrap();
        assert_eq!(same[0].x_px, raws[0].x_px);
        let located = ex.locate(ContactPointMethod::DEFAULT).unwrap()[0].x_px;
        eprintln!(
            "MEASURE frame {frame}: potential minimum {:.1} px, slope peak {located:.1} px, rod {rod_px}",
            raws[0].x_px
        );
        worst.0 = worst.0.max((raws[0].x_px - rod_px).abs());
        worst.1 = worst.1.max((located - rod_px).abs());
    }
    assert!(worst.1 <= 15.0, "slope peak up to {} px off", worst.1);
    assert!(worst.0 > 2.0 * worst.1, "{worst:?}");
}

/// The dark coating past the skin's markers holds only the camera's noise:
/// however that noise changes, the extractor reports no contact there; a
/// segmentation of the same flow that looks everywhere finds patches (so the
/// check is not vacuous), which the extractor sets apart as unseen. On a dot
/// grid (a sparse texture) the whole image stays observable.
#[test]
fn the_dark_border_past_the_skin_is_not_read_as_motion() {
    use optical_tactile::FlowField;
    use optical_tactile::segment::{Segmenter, SegmenterConfig};
    use optical_tactile_sim::{DotGrid, SimConfig, SyntheticSensor};
    let thresholds = Thresholds {
        magnitude: 0.2,
        sum: 600.0,
        ..Thresholds::LOW
    };
    let (mut unmasked_patches, mut unseen) = (0, 0);
    for seed in [6u64, 7] {
        let sim = SyntheticSensor::new(SimConfig::default(), seed).unwrap();
        let reference = sim.render_indexed(0, &[], false).unwrap().frame;
        let mut ex =
            ContactExtractor::new(ExtractorConfig::default().with_thresholds(thresholds)).unwrap();
        ex.set_reference(&reference).unwrap();
        let observable = ex.segmenter().observable().expect("a dense texture");
        let (gw, gh) = observable.size();
        // The strip's dark ends (about 30 px at each end) are not observable,
        // its middle is.
        assert!(!observable.get(2, gh / 2) && !observable.get(gw - 3, gh / 2));
        assert!(observable.get(gw / 2, gh / 2));
        // A rest frame whose dark ends got a brighter, noisier black level
        // (the markers and everything else unchanged).
        let mut rng = 0x9e37_79b9_7f4a_7c15u64 ^ seed;
        let mut frame = reference.clone();
        for ((_, x), v) in frame.indexed_iter_mut() {
            if !(32..reference.ncols() - 32).contains(&x) {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                *v += 4.0 + 8.0 * (rng >> 40) as f32 / (1u64 << 24) as f32;
            }
        }
        assert!(ex.extract(&frame).unwrap().is_empty(), "seed {seed}");
        unseen += ex.unseen().len();
        // The same flow, segmented everywhere, in the grid's own units.
        let (flow, scale) = ex.flow();
        let grid_units = FlowField::from_planes(
            flow.u.mapv(|u| u / scale as f32),
            flow.v.mapv(|v| v / scale as f32),
        )
        .unwrap();
        let mut plain = Segmenter::new(SegmenterConfig {
            thresholds,
            margin: 24,
            scale: scale as f64,
        })
        .unwrap();
        let mut patches = Vec::new();
        plain.segment_into(&grid_units, &mut patches).unwrap();
        unmasked_patches += patches.len();
    }
    assert!(
        unmasked_patches > 0,
        "the border noise gave no patch at all"
    );
    // The extractor found those patches too, and set them apart.
    assert_eq!(unseen, unmasked_patches);

    let sim = SyntheticSensor::new(SimConfig::dot_grid(DotGrid::default()), 2).unwrap();
    let mut ex = ContactExtractor::new(ExtractorConfig::default()).unwrap();
    ex.set_reference(&sim.render_indexed(0, &[], false).unwrap().frame)
        .unwrap();
    assert!(ex.segmenter().observable().is_none());
}

/// The extractor's raw quantities come from the divergent part of the nHHD
/// alone (`NaturalHhd::divergent_into`, half the FFT work) and `|d|` as
/// `sqrt(a^2 + b^2)`: its slow twin, the whole decomposition of every patch
/// and `hypot`, gives the same contact points, displacements and `d_PF` to
/// 1e-12 (relative), on the bundled press with the calibration's settings
/// (`fine` flow, 0.2 px threshold) and on a press spanning most of the strip.
#[test]
fn raw_quantities_equal_the_whole_decomposition_path() {
    use optical_tactile::contact::{PatchFields, PatchGrid, raw_quantities};
    use optical_tactile::hhd::NaturalHhd;
    use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};

    let config = ExtractorConfig::default().with_thresholds(Thresholds {
        magnitude: 0.2,
        sum: 600.0,
        ..Thresholds::LOW
    });
    let frames = frames();
    let mut sim = SyntheticSensor::new(SimConfig::default(), 1).unwrap();
    let (rest, _) = sim.render(&[]).unwrap();
    let (heavy, _) = sim
        .render(&[Press::rod(0.0, [0.8, 0.0, -2.9], 10.0)])
        .unwrap();
    let cases = [
        (&frames[0].image, &frames[5].image),
        (&frames[0].image, &frames[7].image),
        (&rest, &heavy),
    ];
    let mut checked = 0;
    for (reference, frame) in cases {
        let mut ex = ContactExtractor::new(config.clone()).unwrap();
        ex.set_reference(reference).unwrap();
        ex.extract(frame).unwrap();
        let (flow, scale) = ex.flow();
        let s = scale as f64;
        let mut hhd = NaturalHhd::new();
        for patch in ex.patches() {
            let (u, v) = patch.view(flow).unwrap();
            let dec = hhd.decompose(u, v, s, s).unwrap();
            let b = patch.bbox;
            let grid = PatchGrid {
                x0: b.x,
                y0: b.y,
                scale: s,
            };
            let fields = PatchFields {
                u,
                v,
                potential_d: dec.potential_d.view(),
                d_u: dec.d.u.view(),
                d_v: dec.d.v.view(),
            };
            let mut want = raw_quantities(&fields, grid, true).unwrap();
            want.dn = dec
                .d
                .u
                .iter()
                .zip(dec.d.v.iter())
                .map(|(a, b)| a.hypot(*b))
                .sum::<f64>()
                * s
                * s;
            // The extractor's raw contact of this patch: the same box.
            let got = ex
                .raws()
                .iter()
                .find(|r| r.bbox.x == b.x * scale && r.bbox.w == b.width * scale)
                .expect("a raw contact per patch");
            let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1.0);
            for (what, a, b) in [
                ("x_px", got.x_px, want.x_px),
                ("y_px", got.y_px, want.y_px),
                ("ds1", got.ds1, want.ds1),
                ("ds2", got.ds2, want.ds2),
                ("dn", got.dn, want.dn),
                ("d_pf", got.d_pf, want.d_pf),
            ] {
                assert!(close(a, b), "{what}: {a} vs {b}");
            }
            checked += 1;
        }
    }
    // Two rods in each press frame, one patch for the heavy press.
    assert!(checked >= 5, "{checked} patches checked");
}

#[test]
fn the_sensor_applies_the_calibrations_column_correction() {
    let plain = optical_tactile::Calibration::load("fixtures/calibration.json").unwrap();
    // The bundled calibration's gains, times 1.25 everywhere.
    let mut gained = plain.clone();
    let c = gained
        .column_correction
        .as_mut()
        .expect("a column correction");
    for g in &mut c.force_gain {
        *g *= 1.25;
    }
    let run = |cal: optical_tactile::Calibration| {
        let mut s = TactileSensor::from_calibration(cal).unwrap();
        let frames = frames();
        s.set_reference(&frames[0].image).unwrap();
        let mut out = Vec::new();
        for f in &frames[1..] {
            out.extend(s.process(&f.image, f.t_s).unwrap().iter().map(|c| c.raw));
        }
        out
    };
    let (a, b) = (run(plain), run(gained));
    assert!(!a.is_empty());
    assert_eq!(a.len(), b.len());
    for (a, b) in a.iter().zip(&b) {
        let (fa, fb) = (a.local_force.unwrap(), b.local_force.unwrap());
        assert_eq!(a.x_px, b.x_px);
        assert_eq!(fa[0], fb[0]);
        assert_eq!(fa[1], fb[1]);
        assert!(
            (fb[2] - 1.25 * fa[2]).abs() <= 1e-12 * fa[2].abs(),
            "{fa:?} {fb:?}"
        );
    }
}

/// The strip's random markers on its thick, soft gel: even its hardest
/// presses (a 2 mm rod at 3 N, pitched 15 deg either way, at the ends and
/// in the middle; a 10 mm rod at 3 N) stretch the flow far less than a torn
/// flow does, so none is beyond the markers, with the bundled calibration's
/// settings and the dense flow, on other seeds.
#[test]
fn the_strips_hardest_presses_do_not_tear_the_flow() {
    use optical_tactile::contact::ContactPointMethod;
    use optical_tactile::sensor::{TORN_FRACTION, TORN_STRAIN};
    use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};
    let thresholds = Thresholds {
        magnitude: 0.2,
        sum: 600.0,
        ..Thresholds::LOW
    };
    for (seed, preset) in [(71, DisPreset::Fine), (72, DisPreset::Dense)] {
        let mut sim = SyntheticSensor::new(SimConfig::default(), seed).unwrap();
        let (reference, _) = sim.render(&[]).unwrap();
        let mut ex = ContactExtractor::new(
            ExtractorConfig::default()
                .with_flow(DisParams::preset(preset))
                .with_thresholds(thresholds),
        )
        .unwrap();
        ex.set_reference(&reference).unwrap();
        assert_eq!(ex.marker_pitch(), None);
        let mut worst = 0.0f64;
        for x in [-112.0, -60.0, 0.0, 75.0, 112.0] {
            for (d, pitch) in [(2.0, 15.0), (2.0, -15.0), (10.0, 0.0)] {
                let t = f64::to_radians(pitch);
                let press = Press::rod(x, [3.0 * t.sin(), 0.0, -3.0 * t.cos()], d);
                let (frame, _) = sim.render(&[press]).unwrap();
                ex.extract(&frame).unwrap();
                let raws = ex.locate(ContactPointMethod::DEFAULT).unwrap().to_vec();
                assert!(!raws.is_empty(), "seed {seed}: {press:?} not found");
                for r in &raws {
                    assert!(!ex.beyond_markers(r), "seed {seed}: {press:?} said torn");
                    worst = worst.max(ex.flow_strain_fraction(r.bbox, TORN_STRAIN));
                }
            }
        }
        // A box of any size reads the field it overlaps, without overflow.
        let huge = Roi::new(usize::MAX - 3, usize::MAX - 3, usize::MAX, usize::MAX);
        assert_eq!(ex.flow_strain_fraction(huge, TORN_STRAIN), 0.0);
        // Well below the bar, not just under it.
        assert!(worst < 0.5 * TORN_FRACTION, "seed {seed}: {worst}");
    }
}

/// A high-resolution camera's view of a coarse grid of bright dots (84 px
/// apart over the middle of a 1280x720 frame, on a gel lit unevenly and
/// crossed by a camera's scan lines), pressed at two places: without a
/// calibration the grid is recognised, its dots are followed, and the
/// contact point is where they point.
#[test]
fn a_coarse_grid_of_a_high_resolution_camera_is_followed_without_a_calibration() {
    use ndarray::Array2;
    use optical_tactile::contact::ContactPointMethod;
    const PITCH: f64 = 84.0;
    // The unloaded gel at (x, y), and a pixel's noise from its index.
    let gel = |x: f64, y: f64| -> f32 {
        let mut v = 90.0 + 25.0 * x / 1280.0;
        if (y.floor() as i64).rem_euclid(6) < 2 {
            v -= 12.0;
        }
        let (gx, gy) = ((x - 262.0) / PITCH, (y - 52.0) / PITCH);
        let (kx, ky) = (gx.round(), gy.round());
        let inside = (0.0..=9.0).contains(&kx) && (0.0..=7.0).contains(&ky);
        if inside && (gx - kx).hypot(gy - ky) * PITCH < 11.0 {
            v = 225.0;
        }
        v as f32
    };
    let noise = |i: usize, j: usize, k: u64| -> f32 {
        let mut z = (i as u64 * 1280 + j as u64) ^ k.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z ^= z >> 27;
        (z % 5) as f32 - 2.0
    };
    // Pressed at (cx, cy): the gel moved outward by a bump of 6 px at one
    // spread (60 px) from the centre, each pixel showing where it came from.
    let frame = |press: Option<(f64, f64)>, k: u64| {
        Array2::from_shape_fn((720, 1280), |(i, j)| {
            let (x, y) = (j as f64, i as f64);
            let (mut sx, mut sy) = (x, y);
            if let Some((cx, cy)) = press {
                let (dx, dy) = ((x - cx) / 60.0, (y - cy) / 60.0);
                let bump = 6.0 * (-0.5 * (dx * dx + dy * dy)).exp();
                sx -= bump * dx;
                sy -= bump * dy;
            }
            gel(sx, sy) + noise(i, j, k)
        })
    };
    let mut ex = ContactExtractor::new(ExtractorConfig::default()).unwrap();
    ex.set_reference(&frame(None, 0)).unwrap();
    let pitch = ex.marker_pitch().expect("the grid is recognised");
    assert!((pitch - PITCH).abs() <= 2.0, "pitch {pitch}");
    assert!(ex.follows_dots());
    for (k, at) in [(500.0, 300.0), (650.0, 200.0)].into_iter().enumerate() {
        let raws = ex.extract(&frame(Some(at), k as u64 + 1)).unwrap().to_vec();
        assert_eq!(raws.len(), 1, "one patch at {at:?}");
        let p = ex.locate(ContactPointMethod::uncalibrated(true)).unwrap()[0];
        let off = (p.x_px - at.0).hypot(p.y_px - at.1);
        eprintln!(
            "MEASURE press at {at:?}: point {:.1}, {:.1} ({off:.2} px off)",
            p.x_px, p.y_px
        );
        assert!(
            off <= 3.0,
            "press at {at:?}: point ({}, {})",
            p.x_px,
            p.y_px
        );
    }
}
