//! Criterion bench of the whole `TactileSensor::process` call (crop, flow,
//! segmentation, nHHD of every patch, calibration, tracking), on
//!
//! - a 1920x1080 simulated camera frame whose 1600x200 sensing strip is
//!   cropped (the simulator's `--full-frame` layout), and
//! - the 1600x200 strip alone,
//!
//! with the `fast` and `accurate` (default) DIS presets, on 2 threads, for a
//! two-rod press (2.0 N and 1.5 N: two patches per frame) against a fixed
//! reference. Frames per second = 1000 / (median ms per call).
//!
//! `sensor_heavy_press`: the strip with one 10 mm rod pressing 2.9 N with
//! 0.8 N of shear at the centre, `fine` preset, the shipped calibration's 0.2 px threshold: the
//! motion spreads along most of the strip and so does its one patch, the
//! nHHD's largest case.
//!
//! `sensor_large_presses`: the strip with 1, 2 and 4 large presses (10 mm
//! rods at 2.5-3 N with 0.3-0.8 N of shear, 70 mm apart), `fine` preset,
//! the LOW thresholds (0.15 px): each press's patch spreads 60-130 mm along
//! the strip, the case where the time per frame grows with the contacts.
//! After each case it prints the medians of the sensor's own stage timings
//! (`StageTimings`) over 41 further calls, ms.
//!
//! `cargo bench --bench sensor` (short measurement times; on a shared machine
//! compare ratios within one run).

use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use ndarray::Array2;
use optical_tactile::calibration::poly::Polynomial;
use optical_tactile::calibration::{Calibration, SensorSetup};
use optical_tactile::flow::dis::{DisParams, DisPreset};
use optical_tactile::frame::Roi;
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::segment::{Shape, Thresholds};
use optical_tactile::sensor::{ExtractorConfig, SensorConfig, StageTimings, TactileSensor};
use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};

/// A linear calibration for the strip `crop` (x = (x_px - 799.5) / 5 mm,
/// F = 1e-4 D): the maps' cost is what matters here, not their accuracy.
fn calibration(crop: Roi) -> Calibration {
    let g1 =
        Polynomial::raw(&["x2d"], vec![vec![0], vec![1]], vec![-799.5 / 5.0, 0.2]).expect("g1");
    let g2 = Polynomial::raw(&["y2d"], vec![vec![0]], vec![0.0]).expect("g2");
    let vars = ["dx", "dy", "dz", "x2d", "y2d", "d_pf"];
    let lin = |k: usize| {
        let mut e = vec![0u32; 6];
        e[k] = 1;
        Polynomial::raw(&vars, vec![e], vec![1e-4]).expect("force map")
    };
    let setup = SensorSetup {
        geometry: SensorGeometry::default(),
        crop,
        thresholds: Thresholds {
            magnitude: 0.5,
            sum: 600.0,
            erode: 5,
            dilate: 15,
            shape: Shape::Rect,
        },
        pipeline: None,
    };
    Calibration::new(setup, [g1, g2, lin(0), lin(1), lin(2)], None).expect("calibration")
}

/// Reference and pressed frame, and the strip's crop in them.
fn frames(full_frame: bool) -> (Array2<f32>, Array2<f32>, Roi) {
    frames_of(
        full_frame,
        &[
            Press::rod(-20.0, [0.0, 0.0, -2.0], 5.0),
            Press::rod(20.0, [0.0, 0.0, -1.5], 5.0),
        ],
    )
}

/// Reference and a frame pressed by `press`, and the strip's crop in them.
fn frames_of(full_frame: bool, press: &[Press]) -> (Array2<f32>, Array2<f32>, Roi) {
    let config = SimConfig {
        full_frame,
        ..SimConfig::default()
    };
    let crop = if full_frame {
        let (x, y, w, h) = config.camera.crop();
        Roi::new(x, y, w, h)
    } else {
        Roi::new(0, 0, config.camera.strip_width, config.camera.strip_height)
    };
    let mut sim = SyntheticSensor::new(config, 1).expect("simulator");
    let (reference, _) = sim.render(&[]).expect("reference");
    let (pressed, _) = sim.render(press).expect("press");
    (reference, pressed, crop)
}

fn bench_process(c: &mut Criterion) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .expect("thread pool");
    let mut g = c.benchmark_group("sensor_process");
    g.sample_size(20)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    for full_frame in [true, false] {
        let (reference, pressed, crop) = frames(full_frame);
        let size = format!("{}x{}", reference.ncols(), reference.nrows());
        for preset in [DisPreset::Fast, DisPreset::Accurate, DisPreset::Fine] {
            let mut sensor = ready(preset, threshold(0.5), crop, &reference, &pressed, &size);
            let mut t = 0.02;
            g.bench_function(BenchmarkId::new(preset.name(), &size), |b| {
                pool.install(|| {
                    b.iter(|| {
                        t += 0.02;
                        sensor.process(&pressed, t).expect("process").len()
                    })
                })
            });
        }
    }
    g.finish();

    let mut g = c.benchmark_group("sensor_heavy_press");
    g.sample_size(20)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    let (reference, pressed, crop) = frames_of(false, &[Press::rod(0.0, [0.8, 0.0, -2.9], 10.0)]);
    let size = format!("{}x{}", reference.ncols(), reference.nrows());
    // The shipped calibration's 0.2 px threshold, at which such a press's
    // patch spreads along most of the strip.
    let mut sensor = ready(
        DisPreset::Fine,
        threshold(0.2),
        crop,
        &reference,
        &pressed,
        &size,
    );
    let mut t = 0.02;
    let b = sensor.extractor().patches()[0].bbox;
    eprintln!(
        "heavy press: largest patch {}x{} flow px",
        b.width, b.height
    );
    g.bench_function(BenchmarkId::new("fine", &size), |bch| {
        pool.install(|| {
            bch.iter(|| {
                t += 0.02;
                sensor.process(&pressed, t).expect("process").len()
            })
        })
    });
    g.finish();

    let mut g = c.benchmark_group("sensor_large_presses");
    g.sample_size(20)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    let presses = [
        Press::rod(-105.0, [0.8, 0.0, -2.9], 10.0),
        Press::rod(35.0, [-0.5, 0.0, -2.5], 10.0),
        Press::rod(-35.0, [0.3, 0.0, -3.0], 10.0),
        Press::rod(105.0, [-0.6, 0.0, -2.7], 10.0),
    ];
    for n in [1, 2, 4] {
        let (reference, pressed, crop) = frames_of(false, &presses[..n]);
        let mut sensor = ready(
            DisPreset::Fine,
            Thresholds::LOW,
            crop,
            &reference,
            &pressed,
            &format!("{n} presses"),
        );
        let patches = sensor.extractor().patches();
        let cells: Vec<String> = patches
            .iter()
            .map(|p| format!("{}x{}", p.bbox.width, p.bbox.height))
            .collect();
        eprintln!(
            "{n} large presses: {} patches of {} cells",
            patches.len(),
            cells.join(", ")
        );
        let mut t = 0.02;
        g.bench_function(BenchmarkId::new("fine_low", n), |b| {
            pool.install(|| {
                b.iter(|| {
                    t += 0.02;
                    sensor.process(&pressed, t).expect("process").len()
                })
            })
        });
        let stages: Vec<StageTimings> = pool.install(|| {
            (0..41)
                .map(|_| {
                    t += 0.02;
                    sensor.process(&pressed, t).expect("process");
                    *sensor.timings()
                })
                .collect()
        });
        let median = |f: fn(&StageTimings) -> f64| {
            let mut v: Vec<f64> = stages.iter().map(f).collect();
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        eprintln!(
            "{n} large presses, stage medians (ms): flow {:.2}, segment {:.2}, nhhd {:.2}, \
             crop + calibration + tracking {:.2}, total {:.2}",
            median(|s| s.flow_ms),
            median(|s| s.segment_ms),
            median(|s| s.hhd_ms),
            median(|s| s.total_ms - s.flow_ms - s.segment_ms - s.hhd_ms),
            median(|s| s.total_ms),
        );
    }
    g.finish();
}

/// The low kernels with a flow threshold of `magnitude` px and a sum of 600.
fn threshold(magnitude: f32) -> Thresholds {
    Thresholds {
        magnitude,
        sum: 600.0,
        ..Thresholds::LOW
    }
}

/// A sensor with `preset` and `thresholds` on `crop`,
/// its reference set and `pressed` processed once at t = 0.02 s (the press
/// must be seen).
fn ready(
    preset: DisPreset,
    thresholds: Thresholds,
    crop: Roi,
    reference: &Array2<f32>,
    pressed: &Array2<f32>,
    size: &str,
) -> TactileSensor {
    let mut config = SensorConfig::default();
    config.crop = Some(crop);
    config.extractor = ExtractorConfig::default()
        .with_flow(DisParams::preset(preset))
        .with_thresholds(thresholds);
    let mut sensor = TactileSensor::new(config, calibration(crop)).expect("sensor");
    sensor.set_reference(reference).expect("reference");
    let n = sensor.process(pressed, 0.02).expect("process").len();
    assert!(n >= 1, "{size} {}: the press should be seen", preset.name());
    sensor
}

criterion_group!(benches, bench_process);
criterion_main!(benches);
