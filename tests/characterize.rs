//! Characterization: extraction on the committed 6-test fixture and the
//! errors of bad datasets (missing image, malformed `tests.csv`, too few rows).

#[path = "common/scratch.rs"]
mod scratch;
use scratch::scratch;

use std::path::{Path, PathBuf};

use optical_tactile::Error;
use optical_tactile::calibration::fit::{FitOptions, extract_dataset, fit_dataset, read_dataset};
use optical_tactile::contact::ContactPointMethod;
use optical_tactile::frame::Roi;
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::segment::Thresholds;
use optical_tactile::sensor::ExtractorConfig;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/characterization")
}

/// The thresholds the shipped calibration uses: 0.2 px, sum 600, low kernels.
fn config() -> ExtractorConfig {
    ExtractorConfig::default().with_thresholds(Thresholds {
        magnitude: 0.2,
        sum: 600.0,
        ..Thresholds::LOW
    })
}

/// A fresh directory with an empty `frames/`, removed when the test ends.
fn dataset_dir(name: &str) -> tempfile::TempDir {
    let d = scratch(&format!("characterize-{name}"));
    std::fs::create_dir_all(d.path().join("frames")).unwrap();
    d
}

#[test]
fn extraction_finds_every_fixture_press_near_its_truth() {
    let dir = fixture();
    let rows = read_dataset(&dir).unwrap();
    assert_eq!(rows.len(), 6);
    let ex = extract_dataset(
        &dir,
        &rows,
        &config(),
        ContactPointMethod::DEFAULT,
        None,
        &|_, _| {},
    )
    .unwrap();
    assert_eq!(ex.len(), 6);
    // Pixels per mm of arc on the default strip: 1600 px over the whole arc.
    let g = SensorGeometry::default();
    let px_per_mm = 800.0 / g.half_arc_mm();
    for e in &ex {
        let raw = e
            .raw
            .unwrap_or_else(|| panic!("test {} not detected", e.row.test));
        assert!(e.patches >= 1);
        // The contact column lies within 8 mm of arc of the truth (the
        // calibration does the rest; this checks the measurement is the press).
        let arc = g.chord_to_arc(e.row.x_mm);
        let truth_px = 800.0 + arc * px_per_mm - 0.5;
        assert!(
            (raw.x_px - truth_px).abs() < 8.0 * px_per_mm,
            "test {}: x_px {} vs {truth_px}",
            e.row.test,
            raw.x_px
        );
        assert!(raw.dn > 0.0 && raw.d_pf > 0.0 && raw.area_px > 0);
        assert!(raw.shear_ratio().is_finite());
    }
}

#[test]
fn a_missing_image_is_an_error_naming_the_file() {
    let tmp = dataset_dir("missing");
    let d = tmp.path();
    let src = fixture();
    let text = std::fs::read_to_string(src.join("tests.csv")).unwrap();
    std::fs::write(d.join("tests.csv"), &text).unwrap();
    // Copy every image but the first test's loaded frame.
    let rows = read_dataset(d).unwrap();
    for r in &rows {
        for f in [&r.frame, &r.reference] {
            if *f != rows[0].frame {
                std::fs::copy(src.join(f), d.join(f)).unwrap();
            }
        }
    }
    let err = extract_dataset(
        d,
        &rows,
        &config(),
        ContactPointMethod::DEFAULT,
        None,
        &|_, _| {},
    )
    .unwrap_err();
    let msg = err.to_string();
    assert!(msg.contains(&rows[0].frame), "{msg}");
}

#[test]
fn a_malformed_tests_csv_is_an_error_naming_the_line() {
    let tmp = dataset_dir("malformed");
    let d = tmp.path();
    let text = std::fs::read_to_string(fixture().join("tests.csv")).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    // Line 4 (the third data row): an unknown split.
    lines[3] = lines[3].replacen(",train,", ",trian,", 1);
    std::fs::write(d.join("tests.csv"), lines.join("\n") + "\n").unwrap();
    match read_dataset(d) {
        Err(Error::Format { path, line, .. }) => {
            assert!(path.ends_with("tests.csv"), "{}", path.display());
            assert_eq!(line, Some(4));
        }
        other => panic!("expected a format error, got {other:?}"),
    }
    // An empty file (header only) is an error too.
    std::fs::write(d.join("tests.csv"), format!("{}\n", lines[0])).unwrap();
    assert!(read_dataset(d).is_err());
}

#[test]
fn too_few_rows_to_fit_is_a_clear_error() {
    let dir = fixture();
    let rows = read_dataset(&dir).unwrap();
    let ex = extract_dataset(
        &dir,
        &rows,
        &config(),
        ContactPointMethod::DEFAULT,
        None,
        &|_, _| {},
    )
    .unwrap();
    let err = fit_dataset(
        &ex,
        &config(),
        ContactPointMethod::DEFAULT,
        Roi::full(1600, 200),
        SensorGeometry::default(),
        &FitOptions::default(),
    )
    .unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("train") || msg.contains("sample") || msg.contains("fit"),
        "{msg}"
    );
}

#[test]
fn a_missing_sweep_image_is_an_error_naming_sweeps_csv_and_the_file() {
    use optical_tactile::calibration::fit::{extract_sweeps, read_dataset_sweeps};
    let tmp = dataset_dir("sweeps");
    let d = tmp.path();
    let src = fixture();
    let rows = read_dataset(&src).unwrap();
    for name in [&rows[0].frame, &rows[0].reference] {
        std::fs::copy(src.join(name), d.join(name)).unwrap();
    }
    // No sweeps.csv: no sweeps.
    assert!(read_dataset_sweeps(d).unwrap().is_empty());
    let (f, r) = (&rows[0].frame, &rows[0].reference);
    let text = format!(
        "sweep,frame,reference,indenter_mm,force_n,x_mm,y_mm,fx_n,fy_n,fz_n\n\
         0,{f},{r},10,2,-100,0,0,0,-2\n\
         0,frames/gone.png,{r},10,2,-99.5,0,0,0,-2\n"
    );
    std::fs::write(d.join("sweeps.csv"), text).unwrap();
    let sweeps = read_dataset_sweeps(d).unwrap();
    assert_eq!(sweeps.len(), 2);
    let e = extract_sweeps(
        d,
        &sweeps,
        &config(),
        ContactPointMethod::DEFAULT,
        None,
        &|_, _| {},
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("sweeps.csv") && e.contains("gone.png"), "{e}");
}
