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
