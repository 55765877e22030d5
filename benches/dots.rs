//! Criterion bench of following a dot grid's dots (`markers::DotTracker`)
//! on the simulated fingertip sensor (320x240, 7 px dots every 22 px): one
//! frame under a 5 mm sphere at 2 N with 0.6 N of shear, against a fixed
//! reference.
//!
//! - `dots/extract`: `ContactExtractor::extract` (flow, segmentation, nHHD)
//!   with the dots followed and without: the ratio is what following them
//!   costs per frame;
//! - `dots/refine`: `DotTracker::refine` alone on DIS's native flow;
//! - `dots/locate`: `ContactExtractor::locate` of that frame's contact with
//!   the dots followed, by the 2-D slope peak and by the dots' motion lines
//!   about it: the difference is what the lines cost; and by the lines with
//!   the round load's field fitted to the dots (`dot_fit`, the default):
//!   the difference is what the fit costs;
//! - `dots/round fit`: `markers::round::fit_round_field` alone on that
//!   contact's dots.
//!
//! `cargo bench --bench dots` (on a shared machine compare ratios within one
//! run).

use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use optical_tactile::ThresholdPreset;
use optical_tactile::contact::ContactPointMethod;
use optical_tactile::markers::{DotTracker, grid_pitch, round};
use optical_tactile::sensor::{ContactExtractor, ExtractorConfig};
use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};

fn bench(c: &mut Criterion) {
    let mut sensor = SyntheticSensor::new(SimConfig::fingertip(), 1).expect("sensor");
    let (reference, _) = sensor.render(&[]).expect("reference");
    let press = Press::sphere(1.0, -0.5, [0.6, 0.0, -2.0], 5.0);
    let (frame, _) = sensor.render(&[press]).expect("frame");
    let mut group = c.benchmark_group("dots");
    group
        .sample_size(30)
        .measurement_time(Duration::from_secs(4))
        .warm_up_time(Duration::from_secs(1));
    for on in [false, true] {
        let config = ExtractorConfig::default()
            .with_thresholds(ThresholdPreset::Mid)
            .with_dot_tracking(on);
        let mut ex = ContactExtractor::new(config.clone()).expect("extractor");
        ex.set_reference(&reference).expect("reference");
        let name = if on {
            "extract/followed"
        } else {
            "extract/flow alone"
        };
        group.bench_function(name, |b| {
            b.iter(|| ex.extract(&frame).expect("extract").len())
        });
        if on {
            // The frame's contact, measured once (the bench above may be
            // filtered out).
            assert!(!ex.extract(&frame).expect("extract").is_empty());
            let methods = [
                (
                    "locate/slope peak",
                    ContactPointMethod::SlopePeak2d { sigma_px: 16.0 },
                ),
                (
                    "locate/motion lines",
                    ContactPointMethod::MotionLines { sigma_px: 16.0 },
                ),
            ];
            let mut plain = ContactExtractor::new(config.with_dot_fit(false)).expect("extractor");
            plain.set_reference(&reference).expect("reference");
            assert!(!plain.extract(&frame).expect("extract").is_empty());
            for (name, method) in methods {
                group.bench_function(name, |b| {
                    b.iter(|| plain.locate(method).expect("locate").len())
                });
            }
            let lines = ContactPointMethod::MotionLines { sigma_px: 16.0 };
            group.bench_function("locate/motion lines + dot fit", |b| {
                b.iter(|| ex.locate(lines).expect("locate").len())
            });
            let raw = plain.locate(lines).expect("locate")[0];
            let tracker = plain.dot_tracker();
            let pitch = plain.marker_pitch().expect("a dot grid");
            assert!(
                round::fit_round_field(
                    tracker.dots(),
                    tracker.displacements(),
                    &[[raw.x_px, raw.y_px]],
                    0,
                    pitch
                )
                .is_some_and(|f| f.holds())
            );
            group.bench_function("round fit", |b| {
                b.iter(|| {
                    round::fit_round_field(
                        tracker.dots(),
                        tracker.displacements(),
                        &[[raw.x_px, raw.y_px]],
                        0,
                        pitch,
                    )
                })
            });
        }
    }
    let pitch = grid_pitch(&reference).expect("a dot grid");
    let mut tracker = DotTracker::new();
    tracker.set_reference(&reference, pitch).expect("dots");
    let mut dis =
        optical_tactile::flow::dis::Dis::new(ExtractorConfig::default().flow).expect("dis");
    dis.set_reference(&reference).expect("reference");
    dis.compute_native(&frame).expect("flow");
    let (native, scale) = dis.native_flow().expect("native flow");
    let native = native.clone();
    let mut flow = native.clone();
    group.bench_function("refine", |b| {
        b.iter(|| {
            flow.clone_from(&native);
            tracker.refine(&frame, &mut flow, scale).expect("refine");
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
