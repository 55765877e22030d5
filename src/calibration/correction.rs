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
//!
//! **Tilted sweeps.** Under a tilted load the pattern is another one: the
//! contact column of a press tilted along the strip sits on the flank of
//! the tangential response, where the markers pull it otherwise than under
//! a straight press, and the matched normal force follows the column. On
//! the simulator, a 5 mm rod at 2 N pitched by 15 degrees and swept along
//! the skin reads its location 0.2-0.3 mm and its normal force 0.12-0.14 N
//! off with the straight sweeps' correction alone, against 0.05 mm and
//! 0.02 N straight. A dataset may hold sweeps whose forces are tilted
//! along the strip: each tilt then gives one more [`CorrectionLayer`],
//! learned the same way from its own images, with the shear ratio its images
//! were read with per column (tangential over inward normal of their first
//! profile match, [`crate::contact::RawContact::matched_shear_ratio`]). A
//! contact's correction is interpolated between the layers at its own
//! matched shear ratio, linearly, and held at the outermost layers beyond
//! them; a sensor then matches its profile again at the corrected column.
//! Where no image of a tilt is near, that layer holds the straight
//! correction. Measured on the simulator (`docs/results.md`, "Tilted
//! sweeps"): the tilted sweeps' own loads read about 0.05 N in normal force
//! instead of 0.12-0.14 N, random presses gain 8-18% (Fz 0.065 and 0.057 N
//! to 0.060 and 0.047 N on two sets).

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

/// Largest number of [`CorrectionLayer`]s of a [`ColumnCorrection`].
pub const MAX_CORRECTION_LAYERS: usize = 16;

/// Smoothing of the layers' shear ratios along the columns, in units of
/// the correction's own smoothing: a contact's shear ratio is noisy from
/// image to image, and what it depends on (the tilt, the surface's slope)
/// changes slowly along the skin.
pub const SHEAR_RATIO_SMOOTHING: f64 = 12.0;

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
    /// Per sample, the matched shear ratio of the sweep images the offsets
    /// and gains above were learned from; needed with `layers`, `None`
    /// (older files, or straight sweeps alone): the correction holds at every
    /// shear ratio.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shear_ratio: Option<Vec<f64>>,
    /// The corrections learned from sweeps at other tilts (see the module
    /// docs); empty: none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub layers: Vec<CorrectionLayer>,
}

/// The corrections of a [`ColumnCorrection`] learned from the sweeps of one
/// tilt, on the same grid of columns.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CorrectionLayer {
    /// The matched shear ratio of this tilt's sweep images, per sample.
    pub shear_ratio: Vec<f64>,
    /// Added to the calibrated chord position `x`, mm, per sample.
    pub location_mm: Vec<f64>,
    /// Multiplies the profile-matched normal force, per sample.
    pub force_gain: Vec<f64>,
    /// How many sweep images it was fitted on.
    pub images: usize,
}

impl ColumnCorrection {
    /// The location offset (mm) of a contact whose column was measured at
    /// `column_px` ([`crate::contact::RawContact::x_px`]) with the matched
    /// shear ratio `shear` ([`crate::contact::RawContact::matched_shear_ratio`];
    /// it matters only with `layers`; a non-finite one takes the straight
    /// correction).
    pub fn location_mm_at(&self, column_px: f64, shear: f64) -> f64 {
        self.at(column_px, shear, 0.0, |l| l.0)
    }

    /// The force gain of a contact whose profile is matched at `column_px`
    /// ([`crate::calibration::Calibration::match_column`]), with the shear
    /// ratio `shear`.
    pub fn force_gain_at(&self, column_px: f64, shear: f64) -> f64 {
        self.at(column_px, shear, 1.0, |l| l.1)
    }

    /// A profile-matched local force `[tangential, across, normal]`
    /// ([`crate::contact::RawContact::local_force`]) of a contact matched
    /// at `column_px` with the shear ratio `shear`, its normal component
    /// multiplied by the gain there. The tangential response is left
    /// alone: the force maps read it against the normal one.
    pub fn correct_local_force(&self, column_px: f64, shear: f64, local: [f64; 3]) -> [f64; 3] {
        let [t, a, n] = local;
        [t, a, n * self.force_gain_at(column_px, shear)]
    }

    /// One of the corrections at a column and a shear ratio: `pick` chooses
    /// it from a layer's `(location, gain)`; `none` outside the grid. With
    /// layers, linear in the shear ratio between the layers' ratios at the
    /// column, the outermost layer's value beyond them; without, or at a
    /// non-finite `shear`, the base correction's.
    fn at(&self, column_px: f64, shear: f64, none: f64, pick: fn((f64, f64)) -> f64) -> f64 {
        let grid = |v: &[f64]| interpolate(v, self.start_px, self.step_px, column_px);
        let (Some(location), Some(gain)) = (grid(&self.location_mm), grid(&self.force_gain)) else {
            return none;
        };
        let base = pick((location, gain));
        let Some(ratios) = self.shear_ratio.as_deref() else {
            return base;
        };
        if self.layers.is_empty() || !shear.is_finite() {
            return base;
        }
        // (shear ratio, value) of the base and of every layer at this column,
        // on the stack: this runs several times per contact and frame.
        let mut points = [(0.0, 0.0); MAX_CORRECTION_LAYERS + 1];
        points[0] = (grid(ratios).unwrap_or(0.0), base);
        let mut count = 1;
        for l in self.layers.iter().take(MAX_CORRECTION_LAYERS) {
            let (Some(r), Some(loc), Some(g)) = (
                grid(&l.shear_ratio),
                grid(&l.location_mm),
                grid(&l.force_gain),
            ) else {
                continue;
            };
            points[count] = (r, pick((loc, g)));
            count += 1;
        }
        interpolate_in_shear(&mut points[..count], shear)
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
        if self.layers.len() > MAX_CORRECTION_LAYERS {
            return bad(format!(
                "{} layers, at most {MAX_CORRECTION_LAYERS}",
                self.layers.len()
            ));
        }
        if let Some(r) = &self.shear_ratio {
            check_series("shear_ratio", r, n, None)?;
        } else if !self.layers.is_empty() {
            return bad("layers need the base correction's shear_ratio".into());
        }
        for (k, l) in self.layers.iter().enumerate() {
            check_series(&format!("layers[{k}].shear_ratio"), &l.shear_ratio, n, None)?;
            check_series(&format!("layers[{k}].location_mm"), &l.location_mm, n, None)?;
            check_series(
                &format!("layers[{k}].force_gain"),
                &l.force_gain,
                n,
                Some(GAIN_RANGE),
            )?;
        }
        Ok(())
    }
}

/// Checks one series of a [`ColumnCorrection`]: `n` finite values, within
/// `range` if given.
fn check_series(name: &str, values: &[f64], n: usize, range: Option<(f64, f64)>) -> Result<()> {
    let bad = |m: String| Err(Error::param("column_correction", format!("{name}: {m}")));
    if values.len() != n {
        return bad(format!("{} values for {n} columns", values.len()));
    }
    if let Some(v) = values.iter().find(|v| !v.is_finite()) {
        return bad(format!("holds {v}"));
    }
    if let Some((lo, hi)) = range {
        if let Some(v) = values.iter().find(|v| !(**v >= lo && **v <= hi)) {
            return bad(format!("holds {v}, outside [{lo}, {hi}]"));
        }
    }
    Ok(())
}

/// The value at `shear` of the points `(shear ratio, value)`: linear between
/// the two points about it, the outermost point's value beyond them; points
/// at the same ratio count as their mean. `points` is sorted in place; it
/// holds at least one point.
fn interpolate_in_shear(points: &mut [(f64, f64)], shear: f64) -> f64 {
    points.sort_by(|a, b| a.0.total_cmp(&b.0));
    let first = points[0];
    let last = points[points.len() - 1];
    if shear <= first.0 {
        return mean_at(points, first.0);
    }
    if shear >= last.0 {
        return mean_at(points, last.0);
    }
    let i = points.partition_point(|p| p.0 <= shear);
    let (lo, hi) = (points[i - 1], points[i]);
    let (a, b) = (mean_at(points, lo.0), mean_at(points, hi.0));
    let f = (shear - lo.0) / (hi.0 - lo.0);
    a + f * (b - a)
}

/// The mean value of the points at exactly the ratio `r`.
fn mean_at(points: &[(f64, f64)], r: f64) -> f64 {
    let (n, s) = points
        .iter()
        .filter(|p| p.0 == r)
        .fold((0usize, 0.0), |(n, s), p| (n + 1, s + p.1));
    s / n.max(1) as f64
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
            shear_ratio: None,
            layers: Vec::new(),
        }
    }

    /// `corr()` learned straight (shear ratio 0.02 at every column) with two
    /// tilted layers at -0.3 and +0.25.
    fn layered() -> ColumnCorrection {
        let mut c = corr();
        c.shear_ratio = Some(vec![0.02; 3]);
        c.layers = vec![
            CorrectionLayer {
                shear_ratio: vec![0.25, 0.25, 0.25],
                location_mm: vec![0.4, 0.6, 0.0],
                force_gain: vec![1.2, 0.8, 1.0],
                images: 3,
            },
            CorrectionLayer {
                shear_ratio: vec![-0.3, -0.3, -0.3],
                location_mm: vec![-0.5, 0.1, 0.3],
                force_gain: vec![0.9, 1.0, 1.1],
                images: 3,
            },
        ];
        c
    }

    #[test]
    fn corrections_interpolate_inside_and_vanish_outside() {
        let c = corr();
        // Without layers the shear ratio does not matter.
        for shear in [0.0, -0.4, 0.7] {
            assert_eq!(c.location_mm_at(10.0, shear), 0.0);
            assert!((c.location_mm_at(11.0, shear) - 0.1).abs() < 1e-12);
            assert!((c.location_mm_at(14.0, shear) + 0.2).abs() < 1e-12);
            assert!((c.force_gain_at(13.0, shear) - 1.0).abs() < 1e-12);
            assert_eq!(c.location_mm_at(9.9, shear), 0.0);
            assert_eq!(c.location_mm_at(14.1, shear), 0.0);
            assert_eq!(c.force_gain_at(100.0, shear), 1.0);
            assert_eq!(c.force_gain_at(f64::NAN, shear), 1.0);
        }
        c.validate().unwrap();
    }

    #[test]
    fn layers_interpolate_in_the_shear_ratio_and_hold_beyond() {
        let c = layered();
        c.validate().unwrap();
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        // At each layer's own ratio, that layer's values.
        assert!(close(c.location_mm_at(10.0, 0.02), 0.0));
        assert!(close(c.location_mm_at(10.0, 0.25), 0.4));
        assert!(close(c.location_mm_at(10.0, -0.3), -0.5));
        assert!(close(c.force_gain_at(12.0, 0.25), 0.8));
        // Halfway between the base and a layer, halfway between their values.
        assert!(close(c.location_mm_at(12.0, 0.135), 0.5 * (0.2 + 0.6)));
        assert!(close(c.force_gain_at(10.0, -0.14), 0.5 * (1.0 + 0.9)));
        // Beyond the outermost layers, theirs; at a non-finite ratio, the base's.
        assert!(close(c.location_mm_at(14.0, 0.9), 0.0));
        assert!(close(c.location_mm_at(14.0, -2.0), 0.3));
        assert!(close(c.location_mm_at(14.0, f64::NAN), -0.2));
        // Between grid samples, linear in the column too.
        assert!(close(c.location_mm_at(11.0, 0.25), 0.5));
        // Outside the grid, none at any ratio.
        assert_eq!(c.location_mm_at(100.0, 0.25), 0.0);
        assert_eq!(c.force_gain_at(0.0, -0.3), 1.0);
        let f = c.correct_local_force(12.0, 0.25, [0.5, 0.1, -2.0]);
        assert!(close(f[0], 0.5) && close(f[1], 0.1) && close(f[2], -1.6));
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 64, rng_seed: proptest::test_runner::RngSeed::Fixed(11), ..ProptestConfig::default() })]
        #[test]
        fn shear_interpolation_stays_within_the_layers(
            points in proptest::collection::vec((-1.0f64..1.0, -2.0f64..2.0), 1..6),
            shear in -1.5f64..1.5,
        ) {
            let mut p = points.clone();
            let v = interpolate_in_shear(&mut p, shear);
            let lo = points.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
            let hi = points.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
            prop_assert!(v >= lo - 1e-12 && v <= hi + 1e-12, "{} not in [{}, {}]", v, lo, hi);
            // The plain twin: the two points nearest below and above, by a scan.
            let below = points.iter().filter(|p| p.0 <= shear).map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
            let above = points.iter().filter(|p| p.0 >= shear).map(|p| p.0).fold(f64::INFINITY, f64::min);
            let mean = |r: f64| {
                let at: Vec<f64> = points.iter().filter(|p| p.0 == r).map(|p| p.1).collect();
                at.iter().sum::<f64>() / at.len() as f64
            };
            let want = if below == f64::NEG_INFINITY {
                mean(above)
            } else if above == f64::INFINITY || below == above {
                mean(below)
            } else {
                mean(below) + (shear - below) / (above - below) * (mean(above) - mean(below))
            };
            prop_assert!((v - want).abs() < 1e-9, "{} vs {}", v, want);
        }
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
        // Layers: a ratio for the base, series of the grid's length, gains in range.
        let mut c = layered();
        c.shear_ratio = None;
        assert!(c.validate().is_err());
        let mut c = layered();
        c.layers[0].shear_ratio.pop();
        assert!(c.validate().is_err());
        let mut c = layered();
        c.layers[1].force_gain[2] = 0.1;
        assert!(c.validate().is_err());
        let mut c = layered();
        c.layers[1].location_mm[0] = f64::NAN;
        assert!(c.validate().is_err());
        let mut c = layered();
        let extra = c.layers[0].clone();
        c.layers.resize(MAX_CORRECTION_LAYERS + 1, extra);
        assert!(c.validate().is_err());
    }
}
