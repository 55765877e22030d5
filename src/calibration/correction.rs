//! Corrections along the image columns, learned from sweeps.
//!
//! The location and force maps are smooth in position: they are fitted on
//! the protocol's marked points, 20 mm of arc apart. Between those points
//! the readings also depend on the marker pattern under the contact, which
//! changes every millimetre: where the markers are sparse the flow reads a
//! press a few per cent weaker and its steepest rise, where the contact
//! column is measured, stays on the last markers for a few millimetres.
//! On the simulator this variation is a property of the place, not of the
//! load: along a sweep of the skin, the relative error of the matched
//! normal force correlates 0.94-0.98 between rods of 2, 5 and 10 mm and
//! forces of 1.5-3 N, and the column error 0.92-0.98.
//!
//! A **sweep** (`sweeps.csv`, docs/formats.md) presses one rod with a
//! constant force at closely spaced positions along the skin. From the
//! sweeps of a dataset, [`crate::calibration::fit`] learns a
//! [`ColumnCorrection`]: per image column, what the calibrated location
//! of a contact measured there misses (mm, added to `x`) and by what
//! factor the normal force of a contact matched there
//! (the force maps' input) reads low or high there, relative to the
//! sweep's own median (the force maps keep the level; the gain only takes
//! out the place-to-place variation, and the maps are fitted on corrected
//! inputs). Both are
//! Gaussian-weighted means of the sweep images around each column
//! ([`smooth_on_grid`]), pulled towards no correction where no sweep image
//! is near.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Largest number of grid columns of a [`ColumnCorrection`] (a crop is at
/// most a few thousand pixels wide).
pub const MAX_CORRECTION_COLUMNS: usize = 1 << 16;

/// Default smoothing of a [`ColumnCorrection`], full-resolution pixels (the
/// standard deviation of the Gaussian weights): about one sweep step of
/// 0.5 mm on the default strip, narrower than the marker pattern's
/// variation.
pub const DEFAULT_SMOOTHING_PX: f64 = 2.0;

/// How many sweep images' worth of weight the "no correction" prior has in
/// [`smooth_on_grid`]: small against the weight of a sweep's images near a
/// column (about 2 for one sweep in steps of 2.5 px), so that it hardly
/// biases a swept column, but it takes over where the nearest image is
/// more than about 2.5 standard deviations away.
pub const PRIOR_WEIGHT: f64 = 0.05;

/// The force gains a [`ColumnCorrection`] may hold: outside this range a
/// sweep image is no evidence of the marker pattern (a miss, a neighbour's
/// patch) and the file is refused.
pub const GAIN_RANGE: (f64, f64) = (0.5, 2.0);

/// Per image column: a location offset and a force gain (see the module docs).
///
/// Sample `i` lies at column `start_px + i * step_px`; between samples the
/// values are linear, outside the grid there is no correction (offset 0,
/// gain 1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ColumnCorrection {
    /// Column of the first sample, full-resolution pixels of the crop.
    pub start_px: f64,
    /// Spacing of the samples, pixels.
    pub step_px: f64,
    /// Added to the calibrated chord position `x`, mm, per sample.
    pub location_mm: Vec<f64>,
    /// Multiplies the profile-matched normal force (the force maps' input)
    /// of a contact matched at the sample's column, per sample.
    pub force_gain: Vec<f64>,
    /// The Gaussian smoothing it was fitted with, pixels.
    pub smoothing_px: f64,
    /// How many sweep images it was fitted on.
    pub images: usize,
}

impl ColumnCorrection {
    /// The location offset (mm) of a contact whose column was measured at
    /// `column_px` ([`crate::contact::RawContact::x_px`]).
    pub fn location_mm_at(&self, column_px: f64) -> f64 {
        interpolate(&self.location_mm, self.start_px, self.step_px, column_px).unwrap_or(0.0)
    }

    /// The force gain of a contact whose profile is matched at `column_px`
    /// ([`crate::calibration::Calibration::match_column`]).
    pub fn force_gain_at(&self, column_px: f64) -> f64 {
        interpolate(&self.force_gain, self.start_px, self.step_px, column_px).unwrap_or(1.0)
    }

    /// A profile-matched local force `[tangential, across, normal]`
    /// ([`crate::contact::RawContact::local_force`]) of a contact matched
    /// at `column_px`, its normal component multiplied by the gain there. The
    /// sweeps press straight down, so they say nothing of the tangential
    /// response, which is left alone.
    pub fn correct_local_force(&self, column_px: f64, local: [f64; 3]) -> [f64; 3] {
        let [t, a, n] = local;
        [t, a, n * self.force_gain_at(column_px)]
    }

    /// Checks the grid and the values: a positive, finite step; two
    /// non-empty series of equal length of at most
    /// [`MAX_CORRECTION_COLUMNS`]; finite offsets; gains within
    /// [`GAIN_RANGE`].
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::param("column_correction", m));
        if !(self.start_px.is_finite() && self.step_px.is_finite() && self.step_px > 0.0) {
            return bad(format!(
                "start_px {} and step_px {} must be finite, step_px > 0",
                self.start_px, self.step_px
            ));
        }
        let n = self.location_mm.len();
        if n == 0 || n > MAX_CORRECTION_COLUMNS || self.force_gain.len() != n {
            return bad(format!(
                "location_mm ({n}) and force_gain ({}) must have the same length, 1 to {MAX_CORRECTION_COLUMNS}",
                self.force_gain.len()
            ));
        }
        if let Some(v) = self.location_mm.iter().find(|v| !v.is_finite()) {
            return bad(format!("location_mm holds {v}"));
        }
        let (lo, hi) = GAIN_RANGE;
        if let Some(g) = self.force_gain.iter().find(|g| !(**g >= lo && **g <= hi)) {
            return bad(format!("force_gain holds {g}, outside [{lo}, {hi}]"));
        }
        if !(self.smoothing_px.is_finite() && self.smoothing_px >= 0.0) {
            return bad(format!(
                "smoothing_px {} must be finite, >= 0",
                self.smoothing_px
            ));
        }
        Ok(())
    }
}

/// `values` sampled at `start + i * step`, linear between samples; `None`
/// outside the grid or at a non-finite `x`.
fn interpolate(values: &[f64], start: f64, step: f64, x: f64) -> Option<f64> {
    let t = (x - start) / step;
    let last = values.len().checked_sub(1)?;
    if !(t >= 0.0 && t <= last as f64) {
        return None;
    }
    let i = (t.floor() as usize).min(last.saturating_sub(1));
    let f = t - i as f64;
    match values.get(i + 1) {
        Some(next) => Some(values[i] * (1.0 - f) + next * f),
        None => Some(values[i]),
    }
}

/// At each of `n` grid columns `start + i * step`, the Gaussian-weighted
/// mean (standard deviation `sigma_px`, cut at 4 sigma) of the `values`
/// measured at `columns`, with the `prior` counted as [`PRIOR_WEIGHT`]
/// samples at every column: where no sample is near, the prior. Samples at
/// non-finite columns or with non-finite values are skipped. Errors on
/// mismatched lengths, a grid of more than [`MAX_CORRECTION_COLUMNS`] or a
/// non-positive or non-finite `sigma_px` or `step`.
pub fn smooth_on_grid(
    columns: &[f64],
    values: &[f64],
    prior: f64,
    sigma_px: f64,
    start: f64,
    step: f64,
    n: usize,
) -> Result<Vec<f64>> {
    if columns.len() != values.len() {
        return Err(Error::shape(
            "sweep values against columns",
            (columns.len(), 1),
            (values.len(), 1),
        ));
    }
    if !(sigma_px.is_finite() && sigma_px > 0.0 && step.is_finite() && step > 0.0) {
        return Err(Error::param(
            "smoothing",
            format!("sigma {sigma_px} px and step {step} px must be finite and > 0"),
        ));
    }
    if n > MAX_CORRECTION_COLUMNS || !start.is_finite() {
        return Err(Error::param(
            "smoothing",
            format!("{n} columns from {start}: at most {MAX_CORRECTION_COLUMNS}, finite start"),
        ));
    }
    let mut samples: Vec<(f64, f64)> = columns
        .iter()
        .zip(values)
        .filter(|(c, v)| c.is_finite() && v.is_finite())
        .map(|(c, v)| (*c, *v))
        .collect();
    samples.sort_by(|a, b| a.0.total_cmp(&b.0));
    let reach = 4.0 * sigma_px;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let g = start + i as f64 * step;
        let first = samples.partition_point(|s| s.0 < g - reach);
        let (mut sw, mut swv) = (PRIOR_WEIGHT, PRIOR_WEIGHT * prior);
        for &(c, v) in samples[first..].iter().take_while(|s| s.0 <= g + reach) {
            let z = (c - g) / sigma_px;
            let w = (-0.5 * z * z).exp();
            sw += w;
            swv += w * v;
        }
        out.push(swv / sw);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The plain twin of [`smooth_on_grid`]: every sample against every
    /// column, in input order.
    fn smooth_plain(
        columns: &[f64],
        values: &[f64],
        prior: f64,
        sigma: f64,
        start: f64,
        step: f64,
        n: usize,
    ) -> Vec<f64> {
        (0..n)
            .map(|i| {
                let g = start + i as f64 * step;
                let (mut sw, mut swv) = (PRIOR_WEIGHT, PRIOR_WEIGHT * prior);
                for (c, v) in columns.iter().zip(values) {
                    if !(c.is_finite() && v.is_finite()) || (c - g).abs() > 4.0 * sigma {
                        continue;
                    }
                    let w = (-0.5 * ((c - g) / sigma).powi(2)).exp();
                    sw += w;
                    swv += w * v;
                }
                swv / sw
            })
            .collect()
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 64, rng_seed: proptest::test_runner::RngSeed::Fixed(7), ..ProptestConfig::default() })]
        #[test]
        fn smoothing_matches_its_plain_twin(
            samples in proptest::collection::vec((0.0f64..200.0, -3.0f64..3.0), 0..120),
            sigma in 0.3f64..8.0,
            start in -20.0f64..20.0,
            step in 0.25f64..4.0,
            n in 0usize..150,
            prior in -1.0f64..1.0,
        ) {
            let (c, v): (Vec<f64>, Vec<f64>) = samples.into_iter().unzip();
            let fast = smooth_on_grid(&c, &v, prior, sigma, start, step, n).unwrap();
            let plain = smooth_plain(&c, &v, prior, sigma, start, step, n);
            prop_assert_eq!(fast.len(), n);
            for (a, b) in fast.iter().zip(&plain) {
                prop_assert!((a - b).abs() <= 1e-9 * (1.0 + b.abs()), "{} vs {}", a, b);
            }
        }
    }

    #[test]
    fn smoothing_recovers_a_slow_field_and_falls_back_to_the_prior() {
        // Samples every 2.5 px of a field that varies over ~30 px.
        let c: Vec<f64> = (0..200).map(|i| 100.0 + 2.5 * i as f64).collect();
        let f = |x: f64| 0.3 * (x / 30.0).sin();
        let v: Vec<f64> = c.iter().map(|&x| f(x)).collect();
        let out = smooth_on_grid(&c, &v, 0.0, 2.0, 0.0, 1.0, 800).unwrap();
        for x in (120..580).step_by(7) {
            assert!(
                (out[x] - f(x as f64)).abs() < 0.01,
                "at {x}: {} vs {}",
                out[x],
                f(x as f64)
            );
        }
        // Far from every sample: the prior exactly.
        assert_eq!(out[10], 0.0);
        assert_eq!(out[700], 0.0);
        // NaN samples are skipped, not spread.
        let mut v2 = v.clone();
        v2[50] = f64::NAN;
        let out2 = smooth_on_grid(&c, &v2, 0.0, 2.0, 0.0, 1.0, 800).unwrap();
        assert!(out2.iter().all(|x| x.is_finite()));
    }

    #[test]
    fn bad_smoothing_arguments_are_errors() {
        assert!(smooth_on_grid(&[1.0], &[], 0.0, 2.0, 0.0, 1.0, 4).is_err());
        assert!(smooth_on_grid(&[1.0], &[1.0], 0.0, 0.0, 0.0, 1.0, 4).is_err());
        assert!(smooth_on_grid(&[1.0], &[1.0], 0.0, f64::NAN, 0.0, 1.0, 4).is_err());
        assert!(smooth_on_grid(&[1.0], &[1.0], 0.0, 2.0, 0.0, -1.0, 4).is_err());
        assert!(
            smooth_on_grid(
                &[1.0],
                &[1.0],
                0.0,
                2.0,
                0.0,
                1.0,
                MAX_CORRECTION_COLUMNS + 1
            )
            .is_err()
        );
    }

    fn corr() -> ColumnCorrection {
        ColumnCorrection {
            start_px: 10.0,
            step_px: 2.0,
            location_mm: vec![0.0, 0.2, -0.2],
            force_gain: vec![1.0, 1.1, 0.9],
            smoothing_px: 2.0,
            images: 3,
        }
    }

    #[test]
    fn corrections_interpolate_inside_and_vanish_outside() {
        let c = corr();
        assert_eq!(c.location_mm_at(10.0), 0.0);
        assert!((c.location_mm_at(11.0) - 0.1).abs() < 1e-12);
        assert!((c.location_mm_at(14.0) + 0.2).abs() < 1e-12);
        assert!((c.force_gain_at(13.0) - 1.0).abs() < 1e-12);
        assert_eq!(c.location_mm_at(9.9), 0.0);
        assert_eq!(c.location_mm_at(14.1), 0.0);
        assert_eq!(c.force_gain_at(100.0), 1.0);
        assert_eq!(c.force_gain_at(f64::NAN), 1.0);
        c.validate().unwrap();
    }

    #[test]
    fn invalid_corrections_are_refused() {
        let mut c = corr();
        c.force_gain[1] = 3.0;
        assert!(c.validate().is_err());
        let mut c = corr();
        c.force_gain[1] = f64::NAN;
        assert!(c.validate().is_err());
        let mut c = corr();
        c.location_mm.pop();
        assert!(c.validate().is_err());
        let mut c = corr();
        c.step_px = 0.0;
        assert!(c.validate().is_err());
        let mut c = corr();
        c.location_mm[0] = f64::INFINITY;
        assert!(c.validate().is_err());
        let mut c = corr();
        c.location_mm.clear();
        c.force_gain.clear();
        assert!(c.validate().is_err());
    }
}
