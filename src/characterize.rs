//! Calibrating a sensor from a characterization dataset (SPEC.md
//! "Characterization", DATASET.md `tests.csv`).
//!
//! 1. [`extract_dataset`] runs the image pipeline on every test: the test's
//!    own unloaded reference, then its loaded frame, through a
//!    [`ContactExtractor`]; the strongest patch is the test's contact (a test
//!    with no patch is a miss). Tests run in parallel, one extractor per thread.
//! 2. [`fit_dataset`] turns the detections into [`Sample`]s and fits the five
//!    maps with the paper's order search. The raw displacements are rotated
//!    into the sensor frame at the contact's *predicted* chord position (as the
//!    sensor does at run time), so `g1` is fitted first and the force maps after.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use ndarray::Array2;
use rayon::prelude::*;

use crate::calibration::{
    self, Calibration, DetectionLimit, FitOptions, PipelineSettings, PointTable, Sample,
    SegmentationThresholds, SensorSetup,
};
use crate::contact::{RawContact, refine_contact_points, rotate_to_sensor};
use crate::error::{Error, Result};
use crate::geometry::SensorGeometry;
use crate::image::Roi;
use crate::io::{self, Split, TestRow};
use crate::sensor::{ContactExtractor, ExtractorConfig};

/// One test of the dataset and what the pipeline found in it.
#[derive(Debug, Clone, PartialEq)]
pub struct Extraction {
    /// The test's row of `tests.csv`.
    pub row: TestRow,
    /// The strongest patch's raw quantities, `None` if nothing was detected.
    pub raw: Option<RawContact>,
    /// How many patches were found.
    pub patches: usize,
}

/// Reads a dataset's `tests.csv` (errors name the file and line).
pub fn read_dataset(dir: impl AsRef<Path>) -> Result<Vec<TestRow>> {
    let rows = io::read_tests_csv(dir.as_ref().join("tests.csv"))?;
    if rows.is_empty() {
        return Err(Error::format(
            dir.as_ref().join("tests.csv"),
            None,
            "no tests in the file",
        ));
    }
    Ok(rows)
}

fn load(dir: &Path, rel: &str, crop: Option<Roi>) -> Result<Array2<f32>> {
    let path: PathBuf = dir.join(rel);
    let img = io::read_gray(&path)?;
    match crop {
        None => Ok(img),
        Some(r) => r.crop(&img).map(|v| v.to_owned()),
    }
}

/// The default half-width of the contact-column window
/// ([`refine_contact_points`]), full-resolution pixels: wide enough to hold a
/// press's whole motion (about 60 mm of arc on the default strip), so that
/// the centroid is not cut asymmetrically.
pub const DEFAULT_CONTACT_WINDOW_PX: u32 = 400;

/// Runs the pipeline on every test of `rows` (images relative to `dir`),
/// cropping each image to `crop` if given. With `contact_window_px > 0` the
/// contact columns are replaced by the shear-robust estimate of
/// [`refine_contact_points`] with that half-window (0 keeps the argmin of
/// the divergence potential). `progress(done, total)` is called
/// from worker threads as tests finish. The first unreadable image stops the
/// run with an error that names it.
pub fn extract_dataset(
    dir: impl AsRef<Path>,
    rows: &[TestRow],
    config: &ExtractorConfig,
    contact_window_px: u32,
    crop: Option<Roi>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Vec<Extraction>> {
    let dir = dir.as_ref();
    // Checks the configuration once, so that workers cannot fail to build one.
    ContactExtractor::new(config.clone())?;
    let done = AtomicUsize::new(0);
    let total = rows.len();
    rows.par_iter()
        .map_init(
            || ContactExtractor::new(config.clone()).expect("configuration checked above"),
            |ex, row| {
                let reference = load(dir, &row.reference, crop)?;
                let frame = load(dir, &row.frame, crop)?;
                ex.set_reference(&reference)?;
                let mut raws = ex.extract(&frame)?.to_vec();
                if contact_window_px > 0 {
                    let (flow, s) = ex.flow();
                    refine_contact_points(
                        &mut raws,
                        flow.u.view(),
                        s as f64,
                        contact_window_px as f64,
                    )?;
                }
                let out = Extraction {
                    row: row.clone(),
                    raw: raws.first().copied(),
                    patches: raws.len(),
                };
                progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                Ok(out)
            },
        )
        .collect()
}

/// A fitted calibration and how it did.
#[derive(Debug, Clone)]
pub struct DatasetFit {
    /// The calibration.
    pub calibration: Calibration,
    /// Per extraction (same order), its sample if the test was detected.
    pub samples: Vec<Option<Sample>>,
    /// Tests with no detected contact, per split.
    pub misses: [usize; 3],
    /// The minimum detectable force (smallest commanded force from which on
    /// at least 95% of the tests at each force are detected).
    pub min_force: DetectionLimit,
    /// Errors on the test split, total and per point.
    pub test_table: PointTable,
}

fn split_index(s: Split) -> usize {
    match s {
        Split::Train => 0,
        Split::Val => 1,
        Split::Test => 2,
    }
}

/// Per extraction, the sample of a detected test, its raw displacements
/// rotated into the sensor frame at chord position `x_of(raw)`.
fn samples(
    ex: &[Extraction],
    geometry: &SensorGeometry,
    x_of: impl Fn(&RawContact) -> Result<f64>,
) -> Result<Vec<Option<Sample>>> {
    ex.iter()
        .map(|e| {
            e.raw
                .map(|mut raw| {
                    raw.d_sensor = rotate_to_sensor(geometry, x_of(&raw)?, &raw);
                    Ok(Sample::from_test(&e.row, &raw))
                })
                .transpose()
        })
        .collect()
}

fn detected(s: &[Option<Sample>]) -> Vec<Sample> {
    s.iter().flatten().copied().collect()
}

/// Fits a calibration from the extractions (see the module docs).
///
/// `thresholds_name` labels the thresholds in the file (`low`, `mid`, `high`).
pub fn fit_dataset(
    extractions: &[Extraction],
    config: &ExtractorConfig,
    contact_window_px: u32,
    thresholds_name: &str,
    crop: Roi,
    geometry: SensorGeometry,
    options: &FitOptions,
) -> Result<DatasetFit> {
    let t = &config.thresholds;
    let setup = SensorSetup {
        geometry,
        crop,
        thresholds: SegmentationThresholds {
            preset: thresholds_name.to_string(),
            // Through the decimal text, so that 0.2f32 is recorded as 0.2.
            magnitude: f32_to_f64(t.magnitude),
            sum: f32_to_f64(t.sum),
            erode: t.erode as u32,
            dilate: t.dilate as u32,
        },
        pipeline: Some(PipelineSettings {
            flow_preset: preset_name(config),
            margin_px: config.margin_px,
            subpixel: config.subpixel,
            contact_window_px,
        }),
    };
    // Pass 1: the location maps (the rotation does not affect them).
    let first = detected(&samples(extractions, &geometry, |_| Ok(0.0))?);
    let pass1 = calibration::fit(&first, &setup, options)?;
    // Pass 2: rotate at the predicted location, fit everything.
    let second = samples(extractions, &geometry, |r| {
        Ok(pass1.location_sheared(r.x_px, r.y_px, r.shear_ratio())?[0])
    })?;
    let cal = calibration::fit(&detected(&second), &setup, options)?;
    let mut misses = [0usize; 3];
    let mut detections = Vec::with_capacity(extractions.len());
    for e in extractions {
        if e.raw.is_none() {
            misses[split_index(e.row.split)] += 1;
        }
        detections.push((e.row.force_n, e.raw.is_some()));
    }
    let min_force = calibration::min_detectable_force(&detections, 0.95)?;
    let test_table = calibration::evaluate(&cal, &detected(&second), Split::Test)?;
    Ok(DatasetFit {
        calibration: cal,
        samples: second,
        misses,
        min_force,
        test_table,
    })
}

/// An `f32` as the `f64` of its shortest decimal form (0.2f32 -> 0.2).
fn f32_to_f64(x: f32) -> f64 {
    x.to_string().parse().unwrap_or(f64::from(x))
}

/// The DIS preset whose parameters `config.flow` equals, or `custom`.
pub fn preset_name(config: &ExtractorConfig) -> String {
    use crate::flow::dis::{DisParams, DisPreset};
    DisPreset::ALL
        .iter()
        .find(|p| DisParams::preset(**p) == config.flow)
        .map_or_else(|| "custom".to_string(), |p| p.name().to_string())
}
