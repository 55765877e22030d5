//! How good a calibration is: errors per split, per measuring point and per
//! indenter and force, the minimum detectable force, and the paper's Table I
//! and Table II.

use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use super::fit::RestCheck;
use super::poly;
use super::{Calibration, Prediction, Sample};
use crate::error::{Error, Result};
use crate::io::{Split, TestRow};

/// Mean absolute errors of one group of samples.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct QuantityMae {
    /// Number of samples.
    pub n: usize,
    /// MAE of x3D, mm.
    #[serde(deserialize_with = "poly::nullable_f64")]
    pub x_mm: f64,
    /// MAE of y3D, mm.
    #[serde(deserialize_with = "poly::nullable_f64")]
    pub y_mm: f64,
    /// MAE of Fx, N.
    #[serde(deserialize_with = "poly::nullable_f64")]
    pub fx: f64,
    /// MAE of Fy, N.
    #[serde(deserialize_with = "poly::nullable_f64")]
    pub fy: f64,
    /// MAE of Fz, N.
    #[serde(deserialize_with = "poly::nullable_f64")]
    pub fz: f64,
}

/// Errors on a split, in total and per measuring point (the paper's Table II).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointTable {
    /// The split the errors are measured on.
    pub split: Split,
    /// Over all samples of the split.
    pub total: QuantityMae,
    /// Per measuring point, ascending.
    pub per_point: Vec<(u32, QuantityMae)>,
}

/// Running sums of absolute errors of one group of samples.
#[derive(Default)]
struct Acc {
    n: usize,
    s: [f64; 5],
}

impl Acc {
    fn add(&mut self, p: &Prediction, s: &Sample) {
        self.n += 1;
        let e = [
            p.x_mm - s.x_mm,
            p.y_mm - s.y_mm,
            p.fx - s.fx,
            p.fy - s.fy,
            p.fz - s.fz,
        ];
        for (a, e) in self.s.iter_mut().zip(e) {
            *a += e.abs();
        }
    }

    fn mae(&self) -> QuantityMae {
        let n = self.n.max(1) as f64;
        QuantityMae {
            n: self.n,
            x_mm: self.s[0] / n,
            y_mm: self.s[1] / n,
            fx: self.s[2] / n,
            fy: self.s[3] / n,
            fz: self.s[4] / n,
        }
    }
}

/// MAE of the calibration's predictions on the samples of `split` among
/// `items`, in total and per key (in the order `order` sorts the keys).
/// Errors if the split has no sample or a prediction fails.
fn grouped_mae<'a, K: PartialEq + Copy>(
    cal: &Calibration,
    items: impl IntoIterator<Item = (K, &'a Sample)>,
    split: Split,
    order: impl Fn(&K, &K) -> std::cmp::Ordering,
) -> Result<(QuantityMae, Vec<(K, QuantityMae)>)> {
    let mut total = Acc::default();
    let mut per: Vec<(K, Acc)> = Vec::new();
    for (k, s) in items.into_iter().filter(|(_, s)| s.split == split) {
        let p = cal.predict(s)?;
        total.add(&p, s);
        match per.iter_mut().find(|(key, _)| *key == k) {
            Some((_, a)) => a.add(&p, s),
            None => {
                let mut a = Acc::default();
                a.add(&p, s);
                per.push((k, a));
            }
        }
    }
    if total.n == 0 {
        return Err(Error::param(
            "split",
            format!("no `{}` sample to evaluate on", split.as_str()),
        ));
    }
    per.sort_by(|a, b| order(&a.0, &b.0));
    Ok((
        total.mae(),
        per.into_iter().map(|(k, a)| (k, a.mae())).collect(),
    ))
}

/// MAE of the calibration's predictions on the samples of `split`, in total
/// and per measuring point (the paper's Table II). Errors if the split has no
/// sample or a prediction fails.
pub fn evaluate(cal: &Calibration, samples: &[Sample], split: Split) -> Result<PointTable> {
    let (total, per_point) =
        grouped_mae(cal, samples.iter().map(|s| (s.point, s)), split, Ord::cmp)?;
    Ok(PointTable {
        split,
        total,
        per_point,
    })
}

/// One indenter at one commanded force of a characterization protocol.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoadCase {
    /// The indenter's size, mm (`indenter_mm` of `tests.csv`).
    pub indenter_mm: f64,
    /// The commanded force, N (`force_n` of `tests.csv`).
    pub force_n: f64,
}

/// Errors on a split, in total and per indenter and commanded force: where
/// in the protocol's range a calibration is weak.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoadTable {
    /// The split the errors are measured on.
    pub split: Split,
    /// Over all samples of the split.
    pub total: QuantityMae,
    /// Per indenter (ascending), then per commanded force (ascending).
    pub per_load: Vec<(LoadCase, QuantityMae)>,
}

/// MAE of the calibration's predictions on the samples of `split`, in total
/// and per indenter and commanded force, each sample with the test row it
/// came from (as [`crate::calibration::fit::DatasetFit::samples`] pairs with
/// the extractions' rows). Errors if the split has no sample or a
/// prediction fails.
pub fn evaluate_by_load<'a>(
    cal: &Calibration,
    tests: impl IntoIterator<Item = (&'a TestRow, &'a Sample)>,
    split: Split,
) -> Result<LoadTable> {
    let keyed = tests.into_iter().map(|(row, s)| {
        let case = LoadCase {
            indenter_mm: row.indenter_mm,
            force_n: row.force_n,
        };
        (case, s)
    });
    let (total, per_load) = grouped_mae(cal, keyed, split, |a, b| {
        a.indenter_mm
            .total_cmp(&b.indenter_mm)
            .then(a.force_n.total_cmp(&b.force_n))
    })?;
    Ok(LoadTable {
        split,
        total,
        per_load,
    })
}

/// Where the minimum detectable force lies, from the commanded force levels
/// of the characterization (the paper's Table I, row `F_min`): above
/// `above_n` (the largest level not reliably detected, 0 if none) and at most
/// `at_most_n` (the smallest level from which every level is reliably
/// detected; `None` if even the largest is not).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DetectionLimit {
    /// Exclusive lower bound, N.
    pub above_n: f64,
    /// Inclusive upper bound, N.
    pub at_most_n: Option<f64>,
}

impl std::fmt::Display for DetectionLimit {
    /// `(0, 0.5]`, `(0.5, 1]`, or `> 3` when nothing is reliably detected.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.at_most_n {
            Some(hi) => write!(f, "({}, {}]", self.above_n, hi),
            None => write!(f, "> {}", self.above_n),
        }
    }
}

/// The minimum detectable force from per-test detection results
/// `(commanded force N, contact detected)`: a force level counts as reliably
/// detected when at least `min_fraction` of its tests found a contact (1.0:
/// all of them), and the limit is the smallest level from which every level
/// up is reliably detected.
pub fn min_detectable_force(
    detections: &[(f64, bool)],
    min_fraction: f64,
) -> Result<DetectionLimit> {
    if detections.is_empty() {
        return Err(Error::param("detections", "no test results"));
    }
    if !(min_fraction > 0.0 && min_fraction <= 1.0) {
        return Err(Error::param(
            "min_fraction",
            format!("must be in (0, 1], got {min_fraction}"),
        ));
    }
    if let Some(i) = detections
        .iter()
        .position(|d| !(d.0.is_finite() && d.0 > 0.0))
    {
        return Err(Error::param(
            "detections",
            format!(
                "test {i} has commanded force {}, expected > 0",
                detections[i].0
            ),
        ));
    }
    // Per level: (tests, detected). Levels are exact commanded values.
    let mut levels: Vec<(f64, usize, usize)> = Vec::new();
    for &(f, hit) in detections {
        match levels.iter_mut().find(|l| l.0 == f) {
            Some(l) => {
                l.1 += 1;
                l.2 += usize::from(hit);
            }
            None => levels.push((f, 1, usize::from(hit))),
        }
    }
    levels.sort_by(|a, b| a.0.total_cmp(&b.0));
    let ok = |l: &(f64, usize, usize)| l.2 as f64 >= min_fraction * l.1 as f64;
    // The first level of the all-reliable tail.
    let mut start = levels.len();
    while start > 0 && ok(&levels[start - 1]) {
        start -= 1;
    }
    let above_n = if start == 0 { 0.0 } else { levels[start - 1].0 };
    Ok(DetectionLimit {
        above_n,
        at_most_n: levels.get(start).map(|l| l.0),
    })
}

/// The share of a characterization's tests that may give no contact before
/// [`missed_tests_warning`] warns.
pub const MISSED_TESTS_WARNING_FRACTION: f64 = 0.05;

/// A warning for a fit in which more than
/// [`MISSED_TESTS_WARNING_FRACTION`] of the `total` tests gave no contact
/// (`missed` of them); `None` otherwise.
///
/// Why: the segmentation thresholds are flow magnitudes in pixels, and a
/// sensor whose gel moves less (stiffer or thinner, or seen at a lower
/// pixel density) or whose frames are noisier falls below them. The fit
/// then quietly learns only the presses it sees: on a simulated strip with
/// a 70 kPa, 6 mm gel the `high` preset missed 2295 of 7200 tests and
/// detected nothing reliably below 3 N.
pub fn missed_tests_warning(missed: usize, total: usize) -> Option<String> {
    if total == 0 || (missed as f64) <= MISSED_TESTS_WARNING_FRACTION * total as f64 {
        return None;
    }
    Some(format!(
        "{missed} of {total} tests ({:.0}%) gave no contact: the segmentation thresholds are \
         too high for this sensor's motion, and the calibration only knows the presses they \
         let through (the F_min row of Table I says from which force every press is seen). \
         Fit again with lower thresholds (`--thresholds auto` tries the presets in turn and \
         keeps the most sensitive one that finds nothing at rest; below `low`, \
         `--thresholds-custom`), and check the result at rest.",
        100.0 * missed as f64 / total as f64
    ))
}

/// What `calibrate --thresholds auto` makes of one threshold preset, tried
/// from the least sensitive (`high`) to the most (`low`): it keeps the
/// first that sees the protocol ([`ThresholdVerdict::Sees`]), else the most
/// sensitive that stayed quiet at rest.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ThresholdVerdict {
    /// At most [`MISSED_TESTS_WARNING_FRACTION`] of the tests gave no
    /// contact and no rest pair gave one: keep this preset.
    Sees,
    /// Quiet at rest but more of the tests missed: a more sensitive preset
    /// may see them.
    Misses,
    /// A contact on frames with nothing touching: this preset, and every
    /// more sensitive one, reports contacts at rest.
    Noisy,
}

/// The verdict on a preset that missed `missed` of `total` tests and read
/// `rest` ([`super::fit::rest_contacts`]).
pub fn threshold_verdict(missed: usize, total: usize, rest: RestCheck) -> ThresholdVerdict {
    if !rest.quiet() {
        ThresholdVerdict::Noisy
    } else if missed_tests_warning(missed, total).is_none() {
        ThresholdVerdict::Sees
    } else {
        ThresholdVerdict::Misses
    }
}

/// One column of the paper's Table I: a threshold preset, its minimum
/// detectable force and the test errors of the calibration fitted with it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThresholdRow {
    /// Preset name.
    pub preset: String,
    /// Minimum detectable force as text, e.g. a [`DetectionLimit`] printed
    /// (`"(1, 1.5]"`) from the pipeline's detections with
    /// [`min_detectable_force`].
    pub min_force_n: String,
    /// Test MAE.
    pub mae: QuantityMae,
}

/// The paper's Table I in markdown: one column per threshold preset; rows
/// `F_min`, MAE of x (mm), of y (mm) when not all zero, Fx, Fy, Fz (N).
pub fn table_i_markdown(rows: &[ThresholdRow]) -> String {
    let mut s = table_header(rows.iter().map(|r| r.preset.as_str()));
    let _ = write!(s, "| F_min [N] |");
    for r in rows {
        let _ = write!(s, " {} |", r.min_force_n);
    }
    s.push('\n');
    mae_rows(&mut s, rows.iter().map(|r| &r.mae));
    s
}

/// The paper's Table II in markdown: columns Total and one per measuring
/// point; rows MAE of x (mm), of y (mm) when not all zero, Fx, Fy, Fz (N),
/// and the sample count.
pub fn table_ii_markdown(t: &PointTable) -> String {
    let mut cols: Vec<(String, QuantityMae)> = vec![("Total".into(), t.total)];
    cols.extend(t.per_point.iter().map(|(p, m)| (format!("Point {p}"), *m)));
    let mut s = table_header(cols.iter().map(|(name, _)| name.as_str()));
    mae_rows(&mut s, cols.iter().map(|(_, m)| m));
    let _ = write!(s, "| samples |");
    for (_, m) in &cols {
        let _ = write!(s, " {} |", m.n);
    }
    s.push('\n');
    s
}

/// The errors per indenter and commanded force in markdown: one row per
/// load case (and a last row over all), columns indenter (mm), force (N),
/// samples, MAE of x (mm), of y (mm) when not all zero, Fx, Fy, Fz (N).
pub fn table_loads_markdown(t: &LoadTable) -> String {
    let with_y = t.total.y_mm != 0.0 || t.per_load.iter().any(|(_, m)| m.y_mm != 0.0);
    let mut s = String::from("| indenter [mm] | force [N] | samples | MAE x3D [mm] |");
    if with_y {
        s.push_str(" MAE y3D [mm] |");
    }
    s.push_str(" MAE Fx [N] | MAE Fy [N] | MAE Fz [N] |\n|---|---|---|---|");
    s.push_str(if with_y {
        "---|---|---|---|\n"
    } else {
        "---|---|---|\n"
    });
    let mut row = |indenter: &str, force: &str, m: &QuantityMae| {
        let _ = write!(s, "| {indenter} | {force} | {} | {:.2} |", m.n, m.x_mm);
        if with_y {
            let _ = write!(s, " {:.2} |", m.y_mm);
        }
        let _ = writeln!(s, " {:.4} | {:.4} | {:.4} |", m.fx, m.fy, m.fz);
    };
    for (c, m) in &t.per_load {
        row(&c.indenter_mm.to_string(), &c.force_n.to_string(), m);
    }
    row("all", "all", &t.total);
    s
}

/// A markdown header row `| Variable | a | b | ... |` and its separator.
fn table_header<'a>(columns: impl Iterator<Item = &'a str>) -> String {
    let mut s = String::from("| Variable |");
    let mut n = 0;
    for name in columns {
        let _ = write!(s, " {name} |");
        n += 1;
    }
    s.push_str("\n|---|");
    s.push_str(&"---|".repeat(n));
    s.push('\n');
    s
}

/// The MAE rows of x (mm), Fx, Fy, Fz (N) shared by Tables I and II, one
/// column per item of `columns`; with a row of y (mm) after x's when some
/// column's y error is not zero (a sensor that locates contacts in 2-D; on
/// the strip the rods' y is 0 and so is its map's).
fn mae_rows<'a>(s: &mut String, columns: impl Iterator<Item = &'a QuantityMae> + Clone) {
    type Get = fn(&QuantityMae) -> f64;
    let with_y = columns.clone().any(|m| m.y_mm != 0.0);
    let lines: [(&str, Get, usize); 5] = [
        ("MAE x3D [mm]", |m| m.x_mm, 2),
        ("MAE y3D [mm]", |m| m.y_mm, 2),
        ("MAE Fx [N]", |m| m.fx, 4),
        ("MAE Fy [N]", |m| m.fy, 4),
        ("MAE Fz [N]", |m| m.fz, 4),
    ];
    for (name, get, prec) in lines {
        if name.starts_with("MAE y3D") && !with_y {
            continue;
        }
        let _ = write!(s, "| {name} |");
        for m in columns.clone() {
            let _ = write!(s, " {:.*} |", prec, get(m));
        }
        s.push('\n');
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missed_tests_warn_above_five_percent_only() {
        assert_eq!(missed_tests_warning(0, 7200), None);
        // 5% exactly is still quiet; one more test warns.
        assert_eq!(missed_tests_warning(360, 7200), None);
        let w = missed_tests_warning(361, 7200).expect("above 5%");
        assert!(
            w.starts_with("361 of 7200 tests (5%) gave no contact"),
            "{w}"
        );
        let w = missed_tests_warning(2295, 7200).unwrap();
        assert!(w.contains("(32%)") && w.contains("lower thresholds"), "{w}");
        // No test, nothing to say (and no division by zero).
        assert_eq!(missed_tests_warning(0, 0), None);
        assert_eq!(missed_tests_warning(3, 0), None);
    }

    #[test]
    fn a_preset_is_kept_when_it_sees_the_tests_and_stays_quiet_at_rest() {
        let quiet = RestCheck {
            pairs: 32,
            with_contact: 0,
        };
        let noisy = RestCheck {
            pairs: 32,
            with_contact: 1,
        };
        assert_eq!(threshold_verdict(360, 7200, quiet), ThresholdVerdict::Sees);
        assert_eq!(
            threshold_verdict(361, 7200, quiet),
            ThresholdVerdict::Misses
        );
        // A contact at rest outweighs seeing every test.
        assert_eq!(threshold_verdict(0, 7200, noisy), ThresholdVerdict::Noisy);
        assert_eq!(
            threshold_verdict(7200, 7200, noisy),
            ThresholdVerdict::Noisy
        );
        // Without reference pairs nothing was seen at rest.
        let none = RestCheck {
            pairs: 0,
            with_contact: 0,
        };
        assert_eq!(threshold_verdict(10, 7200, none), ThresholdVerdict::Sees);
    }
}
