//! Bad conditions: a calibration or sequence that is missing or malformed,
//! a camera that is not there, a frame of another size, an unreadable
//! frame, a non-finite value: one clear error line and a non-zero status,
//! or the frame named and skipped; never a panic, never a non-finite
//! message published. None of these starts a ROS 2 participant.

mod common;
#[path = "../../tests/common/scratch.rs"]
mod scratch;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use clap::Parser as _;
use optical_tactile::viz::{Canvas, Rgb};
use optical_tactile_ros2::args::NodeArgs;
use optical_tactile_ros2::frame_msgs::FrameMessages;
use optical_tactile_ros2::node::{self, Capture, Pipeline, Processing, Report, SourceSpec};
use scratch::scratch;

const NODE: &str = env!("CARGO_BIN_EXE_optical_tactile_node");

/// Runs the binary; `(status, stderr)`.
fn node(args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(NODE)
        .args(args)
        .output()
        .expect("the node runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn assert_one_error_line(stderr: &str, names: &str) {
    let errors: Vec<_> = stderr
        .lines()
        .filter(|l| l.starts_with("error: "))
        .collect();
    assert_eq!(errors.len(), 1, "one error line:\n{stderr}");
    assert!(
        errors[0].contains(names),
        "the error names {names}:\n{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// A fresh, empty directory named `optical-tactile-ros2-{tag}-` and a unique
/// suffix, removed when the guard is dropped, whether the test passed or not.
fn temp_dir(tag: &str) -> tempfile::TempDir {
    scratch(&format!("ros2-{tag}"))
}

fn press() -> PathBuf {
    common::root().join("fixtures/press")
}

fn calibration() -> PathBuf {
    common::root().join("fixtures/calibration.json")
}

#[test]
fn a_missing_or_malformed_calibration_is_one_error_line_and_status_1() {
    let guard = temp_dir("cal");
    let dir = guard.path();
    let missing = dir.join("none.json");
    let seq = press();
    let (code, err) = node(&[
        "--sequence",
        seq.to_str().unwrap(),
        "--calibration",
        missing.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert_one_error_line(&err, "none.json");

    let bad = dir.join("bad.json");
    std::fs::write(&bad, "{\"version\": ").unwrap();
    let (code, err) = node(&[
        "--sequence",
        seq.to_str().unwrap(),
        "--calibration",
        bad.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert_one_error_line(&err, "bad.json");
}

#[test]
fn a_missing_sequence_or_camera_is_one_error_line_and_status_1() {
    let (code, err) = node(&["--sequence", "/nonexistent/frames"]);
    assert_eq!(code, Some(1), "{err}");
    assert_one_error_line(&err, "/nonexistent/frames");

    // With the v4l feature the device does not open; without it there is
    // no camera support: either way an error naming the device.
    let (code, err) = node(&["--device", "/dev/optical-tactile-no-such-camera"]);
    assert_eq!(code, Some(1), "{err}");
    assert_one_error_line(&err, "/dev/optical-tactile-no-such-camera");
}

#[test]
fn usage_errors_are_status_2() {
    let (code, err) = node(&["--no-such-flag"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--no-such-flag"));
    let (code, err) = node(&["--ros-args", "--params-file", "p.yaml"]);
    assert_eq!(code, Some(2), "{err}");
    assert_one_error_line(&err, "--params-file");
    let (code, err) = node(&["--ros-args", "-p", "qos_depth:=1000"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("1000"), "{err}");
}

/// Runs the frames of `seq` through the calibrated sensor into a list, with
/// `configure` applied to the processing settings: no ROS 2.
fn run_in_memory(
    seq: &Path,
    configure: impl FnOnce(&mut Processing),
) -> (Result<Report, String>, Vec<FrameMessages>) {
    let args = NodeArgs::try_parse_from([
        "n",
        "--sequence",
        seq.to_str().unwrap(),
        "--calibration",
        calibration().to_str().unwrap(),
    ])
    .unwrap();
    let mut pipeline = Pipeline::build(&args).unwrap();
    let mut p = Processing::from_args(&args);
    configure(&mut p);
    let stop = Arc::new(AtomicBool::new(false));
    let mut capture = Capture::open(
        SourceSpec::from_args(&args),
        args.channel,
        &p,
        Arc::clone(&stop),
    )
    .unwrap();
    let mut sink = Vec::new();
    let report = node::process_frames(&mut capture, &mut pipeline, &mut sink, &p, &stop);
    (report, sink)
}

/// The press with frame `k` replaced by `bytes` (written as its PNG).
fn press_with(tag: &str, k: usize, write: impl FnOnce(&Path)) -> tempfile::TempDir {
    let guard = temp_dir(tag);
    let dir = guard.path();
    for entry in std::fs::read_dir(press()).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "png") {
            std::fs::copy(&path, dir.join(path.file_name().unwrap())).unwrap();
        }
    }
    write(&dir.join(format!("{k:06}.png")));
    guard
}

#[test]
fn a_frame_of_another_size_is_skipped_and_the_rest_published() {
    let seq = press_with("size", 4, |p| {
        Canvas::new(320, 40, Rgb(0, 90, 0)).save_png(p).unwrap();
    });
    let (report, sent) = run_in_memory(seq.path(), |_| {});
    let report = report.expect("the run goes on past the frame");
    assert_eq!(report.skipped, 1, "{report}");
    assert_eq!(report.published, 6, "{report}");
    assert_eq!(sent.len(), 6);
    assert!(sent.iter().all(|m| m.check_finite().is_ok()));
}

#[test]
fn an_unreadable_frame_is_skipped() {
    let seq = press_with("unreadable", 3, |p| {
        std::fs::write(p, b"\x89PNG\r\n\x1a\nnot a png").unwrap();
    });
    let (report, sent) = run_in_memory(seq.path(), |_| {});
    let report = report.unwrap();
    assert_eq!((report.skipped, report.published), (1, 6), "{report}");
    assert_eq!(sent.len(), 6);
}

#[test]
fn no_message_with_a_non_finite_value_is_published() {
    // A non-finite marker size makes every frame with a contact non-finite.
    let (report, sent) = run_in_memory(&press(), |p| p.style.sphere_m = f64::NAN);
    let report = report.unwrap();
    assert!(report.non_finite > 0, "{report}");
    assert_eq!(report.non_finite + report.published, 7, "{report}");
    assert_eq!(sent.len() as u64, report.published);
    for m in &sent {
        assert!(m.check_finite().is_ok());
        assert!(
            m.contacts.contacts.is_empty(),
            "only frames without a contact go out"
        );
    }
}

#[test]
fn a_paced_replay_accounts_for_every_frame() {
    // Paced faster than the processing goes: a frame that finds the queue
    // full is dropped and counted; every frame is published or dropped.
    let args = NodeArgs::try_parse_from([
        "n",
        "--sequence",
        press().to_str().unwrap(),
        "--calibration",
        calibration().to_str().unwrap(),
        "--rate",
        "1000",
        "--quiet",
    ])
    .unwrap();
    let mut pipeline = Pipeline::build(&args).unwrap();
    let p = Processing::from_args(&args);
    let stop = Arc::new(AtomicBool::new(false));
    let mut capture = Capture::open(
        SourceSpec::from_args(&args),
        args.channel,
        &p,
        Arc::clone(&stop),
    )
    .unwrap();
    let mut sink = Vec::new();
    let r = node::process_frames(&mut capture, &mut pipeline, &mut sink, &p, &stop).unwrap();
    assert_eq!(r.received + r.dropped, 8, "{r}");
    assert_eq!(r.published + 1, r.received, "{r}");
}
