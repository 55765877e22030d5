//! A flat fingertip sensor end to end: the bundled calibration of the
//! simulated fingertip sensor (fixtures/flat_calibration.json, fitted by
//! `calibrate` on its characterization protocol) on the bundled sequence of
//! presses (fixtures/flat_press: spheres, punches and sheared fingertips
//! anywhere on the gel).

use optical_tactile::capture::{FrameSource, SequenceSource};
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::io::{FrameRecord, read_jsonl};
use optical_tactile::{Calibration, TactileSensor};

const SEQ: &str = "fixtures/flat_press";
const CAL: &str = "fixtures/flat_calibration.json";

#[test]
fn the_flat_calibration_locates_every_bundled_press_in_both_coordinates() {
    let cal = Calibration::load(CAL).unwrap();
    assert!(matches!(cal.setup.geometry, SensorGeometry::Flat(_)));
    assert!(cal.setup.geometry.locates_in_2d());
    // Each frame is pressed against the one reference: no re-referencing,
    // and a contact that moved is a new one, not a held old one.
    let mut sensor = TactileSensor::builder(cal)
        .configure(|c| {
            c.rereference.enabled = false;
            c.tracker.max_missed = 0;
        })
        .build()
        .unwrap();
    let truth: Vec<FrameRecord> = read_jsonl(format!("{SEQ}/truth.jsonl")).unwrap();
    let mut seq = SequenceSource::open(SEQ).unwrap();
    let first = seq.next_frame().unwrap().unwrap();
    sensor.set_reference(&first.image).unwrap();
    let mut pressed = 0;
    while let Some(f) = seq.next_frame() {
        let f = f.unwrap();
        let t = truth.iter().find(|t| t.frame == f.name).unwrap();
        let contacts = sensor.process(&f.image, f.t_s).unwrap();
        assert_eq!(contacts.len(), t.contacts.len(), "{}: {contacts:?}", f.name);
        for (c, want) in contacts.iter().zip(&t.contacts) {
            let [x, y, z] = c.location_mm;
            // Both coordinates within 0.5 mm, on the gel's surface.
            assert!(
                (x - want.x_mm).abs() <= 0.5 && (y - want.y_mm).abs() <= 0.5,
                "{}: ({x:.2}, {y:.2}) mm against ({}, {})",
                f.name,
                want.x_mm,
                want.y_mm
            );
            assert_eq!(z, 0.0);
            // A press: the normal force points into the gel.
            assert!(c.force_n[2] < 0.0, "{}: {:?}", f.name, c.force_n);
        }
        pressed += t.contacts.len();
    }
    assert_eq!(pressed, 11);
}

/// On a regular dot grid, a press that moves the dots by half the grid's
/// pitch or more (a small sphere pressed hard and tilted) is marked out of
/// domain: a dot cannot be told from its neighbour there. A gentle press is
/// not, and random markers (the strip) have no pitch at all.
#[test]
fn motion_beyond_half_the_dot_pitch_is_out_of_domain() {
    use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};
    for (seed, pitch_px) in [(5, 22.0), (6, 18.0)] {
        let mut config = SimConfig::fingertip();
        if let optical_tactile_sim::MarkerLayout::Grid(g) = &mut config.markers.layout {
            g.pitch_px = pitch_px;
        }
        let mut sim = SyntheticSensor::new(config, seed).unwrap();
        let (reference, _) = sim.render(&[]).unwrap();
        let mut sensor = TactileSensor::from_calibration(Calibration::load(CAL).unwrap()).unwrap();
        sensor.set_reference(&reference).unwrap();
        let pitch = sensor.marker_pitch().expect("a dot grid has a pitch");
        assert!(
            (pitch - pitch_px).abs() <= 2.0,
            "pitch {pitch_px}: measured {pitch}"
        );

        let (gentle, _) = sim
            .render(&[Press::sphere(0.0, 0.0, [0.0, 0.0, -0.5], 8.0)])
            .unwrap();
        let c = sensor.process(&gentle, 0.02).unwrap().to_vec();
        assert_eq!(c.len(), 1, "{c:?}");
        assert!(
            c[0].raw.peak_px < 0.5 * pitch && !c[0].out_of_domain,
            "{:?}",
            c[0]
        );

        let t = 20f64.to_radians();
        let hard = Press::sphere(0.0, 0.0, [3.0 * t.sin(), 0.0, -3.0 * t.cos()], 5.0);
        let (img, truth) = sim.render(&[hard]).unwrap();
        let moved = truth
            .u
            .iter()
            .zip(truth.v.iter())
            .map(|(u, v)| u.hypot(*v))
            .fold(0.0f32, f32::max);
        assert!(
            f64::from(moved) > 0.5 * pitch,
            "the press moves the dots {moved} px"
        );
        let c = sensor.process(&img, 0.04).unwrap().to_vec();
        assert!(!c.is_empty());
        let strongest = c
            .iter()
            .max_by(|a, b| a.raw.peak_px.total_cmp(&b.raw.peak_px))
            .unwrap();
        assert!(
            strongest.raw.peak_px >= 0.5 * pitch && strongest.out_of_domain,
            "{strongest:?}"
        );
    }
    // Random markers: no pitch.
    let strip = Calibration::load("fixtures/calibration.json").unwrap();
    let mut sensor = TactileSensor::from_calibration(strip).unwrap();
    let mut seq = SequenceSource::open("fixtures/press").unwrap();
    let first = seq.next_frame().unwrap().unwrap();
    sensor.set_reference(&first.image).unwrap();
    assert_eq!(sensor.marker_pitch(), None);
}
