//! The sensor over time: re-referencing under a simulated slow drift (and
//! never while touched), a sequence with broken frames in the middle (named,
//! skipped, nothing already written lost), the debug panel, and the
//! calibration-driven configuration.

mod common;
#[path = "common/scratch.rs"]
mod scratch;
use common::linear_calibration;
use scratch::scratch;

use ndarray::{Array2, s};
use optical_tactile::Error;
use optical_tactile::calibration::{Calibration, PipelineSettings};
use optical_tactile::capture::{FrameSource, SequenceSource};
use optical_tactile::flow::dis::{DisParams, DisPreset};
use optical_tactile::frame::Roi;
use optical_tactile::io::{self, FrameRecord, JsonlWriter, read_jsonl};
use optical_tactile::segment::Thresholds;
use optical_tactile::sensor::{ExtractorConfig, SensorConfig, TactileSensor};
use optical_tactile::track::ReferencePolicy;
use optical_tactile::viz::{self, Rgb};
use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};

/// The fast preset (cheap enough for hundreds of frames in a test) with
/// thresholds above its rest noise.
fn fast_sensor(crop: Roi, policy: ReferencePolicy) -> TactileSensor {
    let mut config = SensorConfig::default();
    config.crop = Some(crop);
    config.extractor = ExtractorConfig::default()
        .with_flow(DisParams::preset(DisPreset::Fast))
        .with_thresholds(Thresholds {
            magnitude: 0.5,
            sum: 600.0,
            ..Thresholds::LOW
        });
    config.rereference = policy;
    TactileSensor::new(config, linear_calibration(crop, None)).unwrap()
}

/// `img` moved right by `dx` px (bilinear; the first column repeats).
fn shift_x(img: &Array2<f32>, dx: f64) -> Array2<f32> {
    let (h, w) = img.dim();
    let k = dx.floor();
    let a = (dx - k) as f32;
    let k = k as i64;
    Array2::from_shape_fn((h, w), |(y, x)| {
        let at = |xx: i64| img[[y, xx.clamp(0, w as i64 - 1) as usize]];
        let x0 = x as i64 - k;
        (1.0 - a) * at(x0) + a * at(x0 - 1)
    })
}

/// Rest renders (each with its own noise) and a two-rod press (3 N and
/// 2.5 N: both well above the fast preset's detection limit), strip only.
fn renders() -> (Array2<f32>, Vec<Array2<f32>>, Array2<f32>) {
    let mut sim = SyntheticSensor::new(SimConfig::default(), 5).unwrap();
    let reference = sim.render(&[]).unwrap().0;
    let rest = (0..3).map(|_| sim.render(&[]).unwrap().0).collect();
    let press = sim
        .render(&[
            Press::rod(-20.0, [0.0, 0.0, -3.0], 5.0),
            Press::rod(20.0, [0.0, 0.0, -2.5], 5.0),
        ])
        .unwrap()
        .0;
    (reference, rest, press)
}

/// The middle of the strip, where the rods press (x_px 700 and 900).
const CROP: Roi = Roi {
    x: 400,
    y: 0,
    w: 800,
    h: 200,
};

/// Runs a slow global drift of the markers (0.01 px per frame along x, 50
/// Hz, 3 s: 1.5 px in all, three times the segmentation threshold) with no
/// contact; returns (frames with any contact, references taken).
fn drift(policy: ReferencePolicy) -> (usize, u64) {
    let (reference, rest, _) = renders();
    let mut s = fast_sensor(CROP, policy);
    s.set_reference(&reference).unwrap();
    let mut touched = 0;
    for n in 1..=150 {
        let frame = shift_x(&rest[n % 3], 0.01 * n as f64);
        let cs = s.process(&frame, n as f64 * 0.02).unwrap();
        touched += usize::from(!cs.is_empty());
    }
    (touched, s.reference_count())
}

#[test]
fn slow_drift_is_absorbed_by_re_referencing() {
    let policy = ReferencePolicy::default()
        .with_enabled(true)
        .with_quiet_s(0.5)
        .with_max_flow_px(0.5);
    let (touched, refs) = drift(policy);
    assert_eq!(touched, 0, "drift reported as contact");
    // 1.5 px of drift, at most ~0.5 px + 0.5 s of drift (0.25 px) between references.
    assert!(refs >= 3, "only {refs} references");
}

#[test]
fn without_re_referencing_the_same_drift_piles_up_into_false_contacts() {
    // The control for the test above: the drift is large enough to matter.
    let policy = ReferencePolicy::default().with_enabled(false);
    let (touched, refs) = drift(policy);
    assert_eq!(refs, 1);
    assert!(touched > 0, "drift of 1.5 px never crossed the threshold");
}

#[test]
fn never_re_references_while_touched() {
    let (reference, rest, press) = renders();
    let policy = ReferencePolicy::default()
        .with_enabled(true)
        .with_quiet_s(0.2)
        .with_max_flow_px(0.5);
    let mut s = fast_sensor(CROP, policy);
    s.set_reference(&reference).unwrap();
    // 1.5 s of a steady press (the flow is steady too: only the touch is there).
    for n in 1..=75 {
        let cs = s.process(&press, n as f64 * 0.02).unwrap();
        assert_eq!(cs.len(), 2, "frame {n}");
        assert!(!s.rereferenced());
    }
    assert_eq!(s.reference_count(), 1);
    let ids: Vec<u64> = s.contacts().iter().map(|c| c.id).collect();
    // Release: held contacts end after max_missed frames, then 0.2 s of quiet.
    let mut first_new = None;
    for n in 76..=110 {
        s.process(&rest[n % 3], n as f64 * 0.02).unwrap();
        if s.rereferenced() && first_new.is_none() {
            first_new = Some(n);
            assert!(s.contacts().is_empty());
        }
    }
    let n = first_new.expect("re-referenced after the release");
    assert!((86..=100).contains(&n), "re-referenced at frame {n}");
    // Touching again after the new reference: new identities, forces back.
    let cs = s.process(&press, 2.3).unwrap();
    assert_eq!(cs.len(), 2);
    assert!(cs.iter().all(|c| !ids.contains(&c.id)));
}

#[test]
fn broken_frames_in_the_middle_are_named_skipped_and_nothing_written_is_lost() {
    let tmp = scratch("broken-seq");
    let dir = tmp.path();
    for f in io::list_frames("fixtures/press").unwrap() {
        std::fs::copy(&f, dir.join(f.file_name().unwrap())).unwrap();
    }
    // Frame 3 is not a PNG; frame 5 is a PNG of another size.
    std::fs::write(dir.join("000003.png"), b"not a png").unwrap();
    let small = io::read_gray("fixtures/press/000005.png")
        .unwrap()
        .slice(s![..100, ..])
        .to_owned();
    io::write_gray_png(dir.join("000005.png"), &small).unwrap();

    let out = dir.join("contacts.jsonl");
    let mut seq = SequenceSource::open(dir).unwrap();
    let crop = Roi::new(0, 0, 1600, 200);
    let mut config = SensorConfig::default();
    config.extractor = ExtractorConfig::default().with_thresholds(Thresholds {
        magnitude: 0.2,
        sum: 600.0,
        ..Thresholds::LOW
    });
    let mut sensor = TactileSensor::new(config, linear_calibration(crop, None)).unwrap();
    let first = seq.next_frame().unwrap().unwrap();
    sensor.set_reference(&first.image).unwrap();
    let mut skipped = Vec::new();
    {
        let mut w = JsonlWriter::create(&out).unwrap();
        while let Some(frame) = seq.next_frame() {
            let frame = match frame {
                Ok(f) => f,
                Err(e) => {
                    skipped.push(e.to_string());
                    continue;
                }
            };
            match sensor.process(&frame.image, frame.t_s) {
                Ok(cs) => {
                    let rec = FrameRecord {
                        frame: frame.name.clone(),
                        t_s: frame.t_s,
                        contacts: cs.iter().map(|c| c.to_record()).collect(),
                        latency_ms: Some(1.0),
                    };
                    w.write(&rec).unwrap();
                }
                Err(e) => {
                    assert!(matches!(e, Error::ShapeMismatch { .. }), "{e}");
                    skipped.push(format!("{}: {e}", frame.name));
                }
            }
            if frame.index == 4 {
                // Mid-run, everything so far is already on disk (flushed per line).
                let so_far: Vec<FrameRecord> = read_jsonl(&out).unwrap();
                assert_eq!(so_far.len(), 3);
            }
        }
        // The writer is dropped here without any explicit flush or close.
        std::mem::forget(w);
    }
    assert_eq!(skipped.len(), 2, "{skipped:?}");
    assert!(skipped[0].contains("000003.png"), "{}", skipped[0]);
    assert!(skipped[1].contains("000005.png"), "{}", skipped[1]);
    let recs: Vec<FrameRecord> = read_jsonl(&out).unwrap();
    let names: Vec<&str> = recs.iter().map(|r| r.frame.as_str()).collect();
    assert_eq!(
        names,
        [
            "000001.png",
            "000002.png",
            "000004.png",
            "000006.png",
            "000007.png"
        ]
    );
    // The run went on past the broken frames: both rods in the last frame.
    assert_eq!(recs[4].contacts.len(), 2, "{:?}", recs[4]);
}

#[test]
fn a_missing_calibration_is_an_io_error_naming_the_file() {
    let e = Calibration::load("no/such/calibration.json").unwrap_err();
    assert!(matches!(e, Error::Io { .. }), "{e:?}");
    assert!(e.to_string().contains("no/such/calibration.json"), "{e}");
}

#[test]
fn extractor_settings_come_from_the_calibration() {
    let crop = Roi::new(0, 0, 1600, 200);
    let cal = linear_calibration(
        crop,
        Some(PipelineSettings {
            flow_preset: "fast".into(),
            margin_px: 16,
            subpixel: false,
            contact_window_px: 400,
            contact_point: None,
            exposure: Some(optical_tactile::exposure::ExposureCompensation::GainOffset),
            dot_tracking: true,
            dot_fit: true,
            light_box_px: Some(16),
            weighted_profiles: true,
        }),
    );
    let c = ExtractorConfig::from_setup(&cal.setup).unwrap();
    assert!(c.dot_tracking && c.dot_fit && c.weighted_profiles);
    assert_eq!(c.light_box_px, Some(16));
    assert_eq!(c.flow, DisParams::preset(DisPreset::Fast));
    assert_eq!((c.margin_px, c.subpixel), (16, false));
    assert_eq!(
        c.exposure,
        optical_tactile::exposure::ExposureCompensation::GainOffset
    );
    assert_eq!(c.thresholds.magnitude, 0.2);
    assert_eq!(
        (c.thresholds.sum, c.thresholds.erode, c.thresholds.dilate),
        (600.0, 5, 15)
    );
    // Without pipeline settings: the defaults, with the calibration's thresholds.
    let c = ExtractorConfig::from_setup(&linear_calibration(crop, None).setup).unwrap();
    let d = ExtractorConfig::default();
    assert_eq!(
        (c.flow, c.margin_px, c.subpixel, c.dot_tracking, c.dot_fit),
        (d.flow, d.margin_px, d.subpixel, false, false)
    );
    // A file written before the dots' field was fitted reads the sums.
    let mut older = cal.setup.clone();
    older.pipeline.as_mut().unwrap().dot_fit = false;
    let text = serde_json::to_string(&older.pipeline).unwrap();
    assert!(!text.contains("dot_fit"), "{text}");
    assert!(!ExtractorConfig::from_setup(&older).unwrap().dot_fit);
    // Bad settings are typed errors.
    let mut setup = cal.setup.clone();
    setup.pipeline.as_mut().unwrap().flow_preset = "turbo".into();
    assert!(matches!(
        ExtractorConfig::from_setup(&setup),
        Err(Error::InvalidParameter { .. })
    ));
    let mut setup = cal.setup.clone();
    setup.thresholds.erode = 0;
    assert!(matches!(
        ExtractorConfig::from_setup(&setup),
        Err(Error::InvalidParameter { .. })
    ));
}

#[test]
fn debug_panel_shows_the_fields_the_contacts_and_the_image() {
    let (reference, _, press) = renders();
    let crop = Roi::new(0, 0, 1600, 200);
    let mut s = fast_sensor(crop, ReferencePolicy::default());
    // Before any frame: an empty panel, no panic.
    let empty = viz::debug_panel(&s);
    assert_eq!(empty.width(), 0);
    s.set_reference(&reference).unwrap();
    let cs = s.process(&press, 0.02).unwrap().to_vec();
    assert_eq!(cs.len(), 2);
    let p = viz::debug_panel(&s);
    let (w, h) = (1600usize, 200usize);
    assert_eq!((p.width(), p.height()), (w, 4 * h + 12));
    let row = h + 4;
    for c in &cs {
        let (x, y) = (c.raw.x_px.round() as usize, c.raw.y_px.round() as usize);
        // The contact dot on the divergent field and on the potential.
        assert_eq!(p.get(x, row + y), Some(Rgb::RED));
        assert_eq!(p.get(x, 2 * row + y), Some(Rgb::RED));
        // The patch box.
        let b = c.raw.bbox;
        assert_eq!(p.get(b.x + b.w / 2, row + b.y), Some(Rgb::GREEN));
    }
    // Far from the contacts the field views are black (no patch there), the
    // flow view is not.
    assert_eq!(p.get(100, row + 100), Some(Rgb::BLACK));
    assert_ne!(p.get(100, 100), Some(Rgb::BLACK));
    // The bottom view is the cropped image itself.
    for (x, y) in [(0usize, 0usize), (123, 45), (1599, 199)] {
        let g = reference.dim(); // same size as the crop
        assert!(y < g.0 && x < g.1);
        let v = s.cropped()[[y, x]].round() as u8;
        assert_eq!(p.get(x, 3 * row + y), Some(Rgb(v, v, v)));
    }
    // The gaps are grey.
    assert_eq!(p.get(10, h + 1), Some(Rgb(40, 40, 40)));
}

#[test]
fn quiet_flow_is_a_tile_mean_not_one_pixel() {
    use optical_tactile::flow::FlowField;
    use optical_tactile::sensor::max_tile_mean;
    let mut f = FlowField::zeros(40, 20);
    // One noisy border pixel of 8 px: diluted over its 16x16 tile.
    f.u[[0, 0]] = 8.0;
    assert!((max_tile_mean(&f, 16) - 8.0 / 256.0).abs() < 1e-9);
    assert_eq!(max_tile_mean(&f, 1), 8.0);
    // A uniform drift is seen at its full size; the short last tiles count too.
    f.u.fill(0.0);
    f.v.fill(0.3);
    assert!((max_tile_mean(&f, 16) - 0.3).abs() < 1e-6);
    let mut g = FlowField::zeros(40, 20);
    g.v[[19, 39]] = 1.0; // alone in a 8x4 corner tile
    assert!((max_tile_mean(&g, 16) - 1.0 / 32.0).abs() < 1e-9);
    // Against the obvious per-tile loop on a random-ish field.
    let h = FlowField {
        u: Array2::from_shape_fn((20, 40), |(y, x)| ((x * 7 + y * 13) % 11) as f32 * 0.1),
        v: Array2::from_shape_fn((20, 40), |(y, x)| ((x * 3 + y * 5) % 7) as f32 * -0.1),
    };
    let mut want = 0.0f64;
    for ty in [0usize, 16] {
        for tx in [0usize, 16, 32] {
            let t = h.u.slice(s![ty..(ty + 16).min(20), tx..(tx + 16).min(40)]);
            let t2 = h.v.slice(s![ty..(ty + 16).min(20), tx..(tx + 16).min(40)]);
            let m: f64 = t
                .iter()
                .zip(t2.iter())
                .map(|(a, b)| a.hypot(*b) as f64)
                .sum::<f64>()
                / t.len() as f64;
            want = want.max(m);
        }
    }
    assert!((max_tile_mean(&h, 16) - want).abs() < 1e-9);
    g.u[[3, 3]] = f32::NAN;
    assert!(max_tile_mean(&g, 16).is_nan());
}

#[test]
fn the_accurate_preset_re_references_at_rest_too() {
    // Its rest flow has single border pixels at ~0.5 px: the tile mean
    // keeps them from vetoing re-referencing.
    let (reference, rest, _) = renders();
    let mut config = SensorConfig::default();
    config.crop = Some(CROP);
    config.extractor = ExtractorConfig::default().with_thresholds(Thresholds {
        magnitude: 0.2,
        sum: 600.0,
        ..Thresholds::LOW
    });
    config.rereference = ReferencePolicy::default()
        .with_enabled(true)
        .with_quiet_s(0.2)
        .with_max_flow_px(0.5);
    let mut s = TactileSensor::new(config, linear_calibration(CROP, None)).unwrap();
    s.set_reference(&reference).unwrap();
    for n in 1..=24 {
        assert!(s.process(&rest[n % 3], n as f64 * 0.02).unwrap().is_empty());
    }
    assert!(s.reference_count() >= 2, "{}", s.reference_count());
}

#[test]
fn held_contacts_say_so_in_their_records() {
    // Two rods, then rest: the tracker holds both for `max_missed` (2)
    // frames, repeating their last reading, and each record counts the
    // frames held.
    let (reference, rest, press) = renders();
    let mut s = fast_sensor(CROP, ReferencePolicy::default().with_enabled(false));
    s.set_reference(&reference).unwrap();
    let pressed = s.process(&press, 0.02).unwrap().to_vec();
    assert_eq!(pressed.len(), 2, "{pressed:?}");
    let records = |cs: &[optical_tactile::Contact]| -> Vec<serde_json::Value> {
        cs.iter()
            .map(|c| serde_json::to_value(c.to_record()).unwrap())
            .collect()
    };
    for r in records(&pressed) {
        assert_eq!(r["missed"], 0, "{r}");
    }
    for k in 1..=2u32 {
        let held = s
            .process(&rest[k as usize], 0.02 * (k + 1) as f64)
            .unwrap()
            .to_vec();
        assert_eq!(held.len(), 2, "frame {k} at rest: {held:?}");
        for (c, r) in held.iter().zip(records(&held)) {
            assert_eq!(r["missed"], k, "{r}");
            let before = pressed.iter().find(|p| p.id == c.id).unwrap();
            assert_eq!(c.force_n, before.force_n);
            assert_eq!(r["fz_n"], before.force_n[2]);
        }
    }
    assert!(s.process(&rest[0], 0.08).unwrap().is_empty());
    // Read back, the count survives; a record without the key reads as None.
    let line = serde_json::to_string(&pressed[0].to_record()).unwrap();
    assert!(line.contains(r#""missed":0"#), "{line}");
    let back: io::ContactRecord = serde_json::from_str(&line).unwrap();
    assert_eq!(back.missed, Some(0));
    let old: io::ContactRecord = serde_json::from_str(
        r#"{"x_mm":1.0,"y_mm":0.0,"z_mm":0.0,"fx_n":0.0,"fy_n":0.0,"fz_n":-2.0}"#,
    )
    .unwrap();
    assert_eq!(old.missed, None);
}
