//! Arbitrary text as a calibration; what loads runs through the sensor on
//! the bundled press frames, and every contact it reports must be finite.
//! Seed the corpus with `fixtures/calibration.json`:
//! `mkdir -p corpus/calibration && cp ../fixtures/calibration.json corpus/calibration/`.
#![no_main]

use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use ndarray::Array2;
use optical_tactile::calibration::Calibration;
use optical_tactile::{TactileSensor, io};

fn frames() -> &'static (Array2<f32>, Array2<f32>) {
    static FRAMES: OnceLock<(Array2<f32>, Array2<f32>)> = OnceLock::new();
    FRAMES.get_or_init(|| {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/press");
        let paths = io::list_frames(dir).expect("the bundled press");
        (
            io::read_gray(&paths[0]).expect("frame 0"),
            io::read_gray(&paths[4]).expect("frame 4"),
        )
    })
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(cal) = Calibration::from_json_str(text) else {
        return;
    };
    let Ok(mut sensor) = TactileSensor::from_calibration(cal) else {
        return;
    };
    let (reference, press) = frames();
    if sensor.set_reference(reference).is_err() {
        return;
    }
    if let Ok(contacts) = sensor.process(press, 0.1) {
        for c in contacts {
            assert!(c.location_mm.iter().chain(&c.force_n).all(|x| x.is_finite()));
        }
    }
});
