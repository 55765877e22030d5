//! The camera alone never makes a contact: simulated rest frames with
//! exposure steps and slow drift of gain and black level give no patch
//! (raw extractor, the most sensitive preset) and no contact (the bundled
//! calibration), across seeds and read noise up to 2 grey levels; and the default flow at
//! rest lets the sensor re-reference. docs/results.md gives the same check
//! on 1,000 frames per case (`camera_check`).

use ndarray::Array2;
use optical_tactile::Calibration;
use optical_tactile::exposure::ExposureCompensation;
use optical_tactile::segment::Thresholds;
use optical_tactile::sensor::{ContactExtractor, ExtractorConfig, TactileSensor};
use optical_tactile::track::ReferencePolicy;
use optical_tactile_sim::{ExposureChanges, SimConfig, SyntheticSensor};

const CALIBRATION: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/calibration.json");

/// Exposure steps of 3% and 1 grey level every 10 frames (up to 2 steps
/// away), and a drift of 5% and 3 grey levels over 400 frames.
fn changes() -> ExposureChanges {
    ExposureChanges {
        step_every: 10,
        step_gain: 0.03,
        step_offset: 1.0,
        step_levels: 2,
        drift_gain: 0.05,
        drift_offset: 3.0,
        drift_period: 400.0,
    }
}

fn simulator(seed: u64, read: f32, exposure: ExposureChanges) -> SyntheticSensor {
    let mut cfg = SimConfig::default();
    cfg.noise.read = read;
    cfg.noise.exposure = exposure;
    SyntheticSensor::new(cfg, seed).unwrap()
}

fn rest(sim: &SyntheticSensor, k: u64) -> Array2<f32> {
    sim.render_indexed(k, &[], false).unwrap().frame
}

/// Frames with a raw patch (low thresholds) and frames with a calibrated
/// contact, over `frames` rest frames of `sim` with `mode`.
fn false_contacts(
    sim: &SyntheticSensor,
    frames: u64,
    mode: ExposureCompensation,
) -> (usize, usize) {
    let reference = rest(sim, 0);
    let mut raw = ContactExtractor::new(
        ExtractorConfig::default()
            .with_thresholds(Thresholds::LOW)
            .with_exposure(mode),
    )
    .unwrap();
    raw.set_reference(&reference).unwrap();
    let calibration = Calibration::load(CALIBRATION).unwrap();
    let mut sensor = TactileSensor::builder(calibration)
        .rereference(ReferencePolicy::default().with_enabled(false))
        .configure(|c| c.extractor.exposure = mode)
        .build()
        .unwrap();
    sensor.set_reference(&reference).unwrap();
    let (mut patches, mut contacts) = (0, 0);
    for k in 1..=frames {
        let frame = rest(sim, k);
        patches += usize::from(!raw.extract(&frame).unwrap().is_empty());
        contacts += usize::from(!sensor.process(&frame, k as f64 * 0.02).unwrap().is_empty());
    }
    (patches, contacts)
}

/// The default (`Auto`) is what the sensor runs with.
#[test]
fn auto_is_the_default() {
    assert_eq!(
        ExtractorConfig::default().exposure,
        ExposureCompensation::Auto
    );
}

#[test]
fn exposure_steps_and_drift_at_rest_make_no_contact() {
    // Five skins (marker layouts) and read noise from 1 to 2 grey levels.
    for (seed, read) in [(1, 1.0), (2, 2.0), (3, 1.5), (4, 1.0), (5, 2.0)] {
        let sim = simulator(seed, read, changes());
        for mode in [ExposureCompensation::GainOffset, ExposureCompensation::Auto] {
            let got = false_contacts(&sim, 80, mode);
            assert_eq!(
                got,
                (0, 0),
                "seed {seed}, read noise {read}, {mode:?}: frames with a patch, with a contact"
            );
        }
    }
}

#[test]
fn without_compensation_the_same_changes_make_patches() {
    // The check above is not vacuous: the same frames, uncompensated, do.
    let sim = simulator(1, 1.0, changes());
    let (patches, _) = false_contacts(&sim, 80, ExposureCompensation::Off);
    assert!(patches > 0, "no patch without compensation");
}

#[test]
fn the_compensation_finds_the_simulated_gain_and_offset() {
    let exposure = changes();
    let sim = simulator(4, 1.0, exposure);
    let mut ex = ContactExtractor::new(
        ExtractorConfig::default().with_exposure(ExposureCompensation::GainOffset),
    )
    .unwrap();
    ex.set_reference(&rest(&sim, 0)).unwrap();
    for k in [15u64, 33, 57, 95] {
        ex.extract(&rest(&sim, k)).unwrap();
        let (gain, offset) = ex.exposure();
        let (g, o) = exposure.response(4, k);
        // The simulator's own per-frame flicker (1%) comes on top.
        assert!(
            (gain / f64::from(g) - 1.0).abs() < 0.04,
            "frame {k}: {gain} vs {g}"
        );
        assert!(
            (offset - f64::from(o)).abs() < 3.0,
            "frame {k}: {offset} vs {o}"
        );
    }
}

#[test]
fn the_sensor_re_references_at_rest_with_the_default_flow() {
    use ExposureCompensation::{GainOffset, Off};
    for (seed, read, exposure, mode) in [
        (1, 1.0, ExposureChanges::default(), Off),
        (2, 1.5, ExposureChanges::default(), Off),
        // Exposure changes need the compensation (off by default).
        (1, 1.0, changes(), GainOffset),
        // Rest noise above the former 0.5 px limit (0.96 px at most). This
        // camera's 1% per-frame flicker with 2 grey levels of read noise gives
        // false contacts at rest without the compensation (docs/results.md).
        (3, 2.0, ExposureChanges::default(), GainOffset),
    ] {
        let sim = simulator(seed, read, exposure);
        let calibration = Calibration::load(CALIBRATION).unwrap();
        assert_eq!(
            calibration.setup.pipeline.as_ref().unwrap().flow_preset,
            "fine"
        );
        let mut sensor = TactileSensor::builder(calibration)
            .configure(|c| c.extractor.exposure = mode)
            .build()
            .unwrap();
        sensor.set_reference(&rest(&sim, 0)).unwrap();
        // 2.4 s at 50 Hz: the default policy needs 2 s of quiet.
        let mut fired = 0;
        for k in 1..=120u64 {
            let contacts = sensor.process(&rest(&sim, k), k as f64 * 0.02).unwrap();
            assert!(contacts.is_empty(), "seed {seed}, frame {k}");
            fired += usize::from(sensor.rereferenced());
        }
        assert_eq!(fired, 1, "seed {seed}, read noise {read}: re-references");
    }
}

/// On a flat dot-grid sensor (320x240, dark dots on a lit gel) the same
/// exposure steps and drift make no patch with the raw mode's default (high)
/// thresholds nor with the mid ones, over grids of several pitches and dot
/// sizes, read noise 1 and 2.
#[test]
fn exposure_changes_on_a_dot_grid_make_no_patch() {
    use optical_tactile_sim::DotGrid;
    for (seed, read) in [(1u64, 1.0f32), (2, 2.0), (3, 1.0)] {
        let mut cfg = SimConfig::dot_grid(DotGrid {
            pitch_px: 24.0 + 3.0 * seed as f64,
            diameter_px: 6.0 + seed as f64,
            jitter_px: 1.0,
            ..DotGrid::default()
        });
        cfg.noise.read = read;
        cfg.noise.exposure = changes();
        let sim = SyntheticSensor::new(cfg, seed).unwrap();
        let reference = rest(&sim, 0);
        for thresholds in [Thresholds::HIGH, Thresholds::MID] {
            let mut ex =
                ContactExtractor::new(ExtractorConfig::default().with_thresholds(thresholds))
                    .unwrap();
            ex.set_reference(&reference).unwrap();
            let with_patch = (1..=80)
                .filter(|&k| !ex.extract(&rest(&sim, k)).unwrap().is_empty())
                .count();
            assert_eq!(
                with_patch, 0,
                "seed {seed}, read noise {read}, {thresholds:?}"
            );
        }
    }
}
