//! Per-contact force uncertainty: how far off a contact's force is likely
//! to be, per axis, so that a robot knows when to trust a reading.
//!
//! The calibration's force error is not the same for every contact. On the
//! simulated strip it grows with the potential's spread `d_pf` (a strong or
//! concentrated press: its absolute error correlates 0.6 with `d_pf`, 0.4
//! with the force's magnitude) and is largest at the ends of the skin and
//! under strong tilts. A [`ForceUncertainty`] models the standard deviation
//! of the error of each force axis (sensor frame) as
//!
//! ```text
//! sigma = base_n + per_d_pf * d_pf + per_newton * |F|
//! ```
//!
//! with non-negative coefficients, fitted on held-out tests the maps were
//! not fitted on (the characterization's spot checks, presses between its
//! points, when it has at least [`MIN_SAMPLES`]; else its validation split):
//! first the shape, by non-negative least squares of the absolute errors on
//! the three terms ([`nnls_abs`]), then the level, scaled so that
//! [`TARGET_COVERAGE`] (68.3%, one standard deviation of a Gaussian) of
//! those tests' errors lie within one sigma.
//!
//! What it is and is not: the spread of the calibration's error over
//! contacts like the characterization's, not a noise level. Most of that
//! error belongs to the place and the load (the marker pattern under the
//! contact, the maps' smoothness), so it does not average out over frames
//! of the same press, and a filter over time does not shrink it. A contact
//! marked out of domain has a sigma extrapolated like its force.

use serde::{Deserialize, Serialize};

use super::{Prediction, Sample};
use crate::contact::profile::solve;
use crate::error::{Error, Result};

/// The fraction of held-out errors within one sigma that the level is
/// fitted to: a Gaussian's one-standard-deviation coverage.
pub const TARGET_COVERAGE: f64 = 0.6827;

/// Fewest held-out samples a [`ForceUncertainty`] is fitted from: fewer
/// cannot pin a 68% quantile.
pub const MIN_SAMPLES: usize = 20;

/// Whether a fit with `detected` spot checks (presses between the
/// protocol's points, `Split::Spot`) fits the uncertainty on them rather
/// than on the validation split: when they are enough to pin a 68%
/// quantile ([`MIN_SAMPLES`]).
pub fn fitted_on_spot_checks(detected: usize) -> bool {
    detected >= MIN_SAMPLES
}

/// Largest coefficient a calibration file may hold (N, N per unit of `d_pf`,
/// N per N): far beyond any sensor's, it bounds what a file can make a
/// contact's sigma.
pub const MAX_COEFFICIENT: f64 = 1e6;

/// The spread model of one force axis: `sigma = base_n + per_d_pf * d_pf +
/// per_newton * |F|`, every coefficient non-negative.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisSpread {
    /// Constant part, N.
    pub base_n: f64,
    /// Part per unit of the contact's potential spread `d_pf`, N.
    pub per_d_pf: f64,
    /// Part per newton of the contact's force magnitude, N/N.
    pub per_newton: f64,
}

impl AxisSpread {
    /// The standard deviation for a contact of spread `d_pf` and force
    /// magnitude `force_n`, N.
    pub fn sigma_n(&self, d_pf: f64, force_n: f64) -> f64 {
        self.base_n + self.per_d_pf * d_pf.max(0.0) + self.per_newton * force_n.max(0.0)
    }

    fn coefficients(&self) -> [f64; 3] {
        [self.base_n, self.per_d_pf, self.per_newton]
    }
}

/// One held-out test for fitting a [`ForceUncertainty`]: the contact's
/// inputs and the calibration's error on it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpreadSample {
    /// The contact's potential spread `d_pf`.
    pub d_pf: f64,
    /// The calibrated force (sensor frame), N.
    pub force_n: [f64; 3],
    /// Calibrated minus true force, per axis, N.
    pub error_n: [f64; 3],
}

impl SpreadSample {
    /// The spread sample of a characterization sample and the calibration's
    /// prediction for it (sensor frame).
    pub fn of(sample: &Sample, prediction: &Prediction) -> Self {
        let p = prediction;
        SpreadSample {
            d_pf: sample.d_pf,
            force_n: [p.fx, p.fy, p.fz],
            error_n: [p.fx - sample.fx, p.fy - sample.fy, p.fz - sample.fz],
        }
    }

    fn features(&self) -> [f64; 3] {
        [1.0, self.d_pf, magnitude(self.force_n)]
    }

    fn is_finite(&self) -> bool {
        self.d_pf.is_finite()
            && self.force_n.iter().all(|v| v.is_finite())
            && self.error_n.iter().all(|v| v.is_finite())
    }
}

fn magnitude(f: [f64; 3]) -> f64 {
    (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt()
}

/// Per force axis (sensor x, y, z), the standard deviation of a contact's
/// force error (see the module docs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ForceUncertainty {
    /// The spread models of Fx, Fy and Fz.
    pub axes: [AxisSpread; 3],
    /// How many held-out tests it was fitted on.
    pub samples: usize,
    /// Fraction of the test split's errors within one sigma, per axis, if
    /// the fit had a test split: what the 68% of the fit came to on tests it
    /// was not fitted on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test_coverage: Option<[f64; 3]>,
}

impl ForceUncertainty {
    /// Fits the model on held-out samples (non-finite ones are skipped).
    /// Errors ([`Error::InvalidParameter`]) with fewer than [`MIN_SAMPLES`]
    /// finite ones.
    pub fn fit(samples: &[SpreadSample]) -> Result<Self> {
        let finite: Vec<&SpreadSample> = samples.iter().filter(|s| s.is_finite()).collect();
        if finite.len() < MIN_SAMPLES {
            return Err(Error::param(
                "samples",
                format!(
                    "a force uncertainty needs at least {MIN_SAMPLES} held-out samples, got {}",
                    finite.len()
                ),
            ));
        }
        let features: Vec<[f64; 3]> = finite.iter().map(|s| s.features()).collect();
        let axes = std::array::from_fn(|a| {
            let y: Vec<f64> = finite.iter().map(|s| s.error_n[a].abs()).collect();
            let c = nnls_abs(&features, &y);
            let k = level(&features, &y, c);
            AxisSpread {
                base_n: c[0] * k,
                per_d_pf: c[1] * k,
                per_newton: c[2] * k,
            }
        });
        Ok(ForceUncertainty {
            axes,
            samples: finite.len(),
            test_coverage: None,
        })
    }

    /// The standard deviation of each force axis's error (sensor x, y, z)
    /// for a contact of potential spread `d_pf` and calibrated force
    /// `force_n`, N.
    pub fn sigma_n(&self, d_pf: f64, force_n: [f64; 3]) -> [f64; 3] {
        let f = magnitude(force_n);
        self.axes.map(|a| a.sigma_n(d_pf, f))
    }

    /// Per axis, the fraction of `samples` (finite ones) whose error lies
    /// within one sigma; `None` without finite samples.
    pub fn coverage(&self, samples: &[SpreadSample]) -> Option<[f64; 3]> {
        let finite: Vec<&SpreadSample> = samples.iter().filter(|s| s.is_finite()).collect();
        if finite.is_empty() {
            return None;
        }
        let mut within = [0usize; 3];
        for s in &finite {
            let sigma = self.sigma_n(s.d_pf, s.force_n);
            for a in 0..3 {
                if s.error_n[a].abs() <= sigma[a] {
                    within[a] += 1;
                }
            }
        }
        Some(within.map(|w| w as f64 / finite.len() as f64))
    }

    /// Checks a loaded model: every coefficient finite, non-negative and at
    /// most [`MAX_COEFFICIENT`]; a test coverage within `[0, 1]`.
    pub fn validate(&self) -> std::result::Result<(), String> {
        for (axis, a) in ["x", "y", "z"].iter().zip(&self.axes) {
            for (name, c) in ["base_n", "per_d_pf", "per_newton"]
                .iter()
                .zip(a.coefficients())
            {
                if !(c.is_finite() && (0.0..=MAX_COEFFICIENT).contains(&c)) {
                    return Err(format!(
                        "force_uncertainty: axis {axis}: {name} must be within [0, {MAX_COEFFICIENT}], got {c}"
                    ));
                }
            }
        }
        if let Some(c) = self.test_coverage
            && c.iter().any(|v| !(0.0..=1.0).contains(v))
        {
            return Err(format!(
                "force_uncertainty: test_coverage must lie within [0, 1], got {c:?}"
            ));
        }
        Ok(())
    }
}

/// The factor that puts [`TARGET_COVERAGE`] of the samples' absolute errors
/// `y` within the shape `features . c`: the target quantile of `y / shape`
/// over samples with a positive shape (1 if none has one: a shape of zero
/// everywhere stays zero).
fn level(features: &[[f64; 3]], y: &[f64], c: [f64; 3]) -> f64 {
    let mut ratios: Vec<f64> = features
        .iter()
        .zip(y)
        .filter_map(|(f, &y)| {
            let s = dot(f, &c);
            (s > 0.0).then_some(y / s)
        })
        .collect();
    if ratios.is_empty() {
        return 1.0;
    }
    ratios.sort_by(f64::total_cmp);
    let i = ((TARGET_COVERAGE * ratios.len() as f64).ceil() as usize).clamp(1, ratios.len()) - 1;
    // A hair above the quantile's ratio: the sigma of the sample that sets
    // it, summed from the scaled coefficients, must not round below its
    // error.
    ratios[i] * (1.0 + 1e-12)
}

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Non-negative least squares of `y` on three features: the `c >= 0`
/// minimising `sum (features . c - y)^2`. With three unknowns every active
/// set can be tried: the unconstrained least squares on each of the seven
/// non-empty subsets of the features, the best one whose coefficients are
/// all non-negative (the problem is convex, so that is the optimum). All
/// zeros if no subset gives one.
pub fn nnls_abs(features: &[[f64; 3]], y: &[f64]) -> [f64; 3] {
    // Column scales, so that features of very different sizes (1, d_pf in
    // the tens, |F| of a few N) meet a well-conditioned system.
    let scale: [f64; 3] = std::array::from_fn(|j| {
        let m = features.iter().map(|f| f[j].abs()).fold(0.0, f64::max);
        if m > 0.0 { m } else { 1.0 }
    });
    let objective = |c: &[f64; 3]| -> f64 {
        features
            .iter()
            .zip(y)
            .map(|(f, &y)| (dot(f, c) - y).powi(2))
            .sum()
    };
    let mut best = ([0.0; 3], objective(&[0.0; 3]));
    for mask in 1u8..8 {
        let cols: Vec<usize> = (0..3).filter(|j| mask & (1 << j) != 0).collect();
        let n = cols.len();
        let mut ata = vec![0.0; n * n];
        let mut atb = vec![0.0; n];
        for (f, &y) in features.iter().zip(y) {
            for (p, &i) in cols.iter().enumerate() {
                let fi = f[i] / scale[i];
                atb[p] += fi * y;
                for (q, &j) in cols.iter().enumerate() {
                    ata[p * n + q] += fi * f[j] / scale[j];
                }
            }
        }
        let Some(sol) = solve(&mut ata, &mut atb, n) else {
            continue;
        };
        if sol.iter().any(|&v| v < 0.0 || !v.is_finite()) {
            continue;
        }
        let mut c = [0.0; 3];
        for (p, &j) in cols.iter().enumerate() {
            c[j] = sol[p] / scale[j];
        }
        let o = objective(&c);
        if o < best.1 {
            best = (c, o);
        }
    }
    best.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A deterministic generator (the tests need no crate for it).
    struct Lcg(u64);
    impl Lcg {
        fn uniform(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 11) as f64) / ((1u64 << 53) as f64)
        }
        fn gaussian(&mut self) -> f64 {
            let (u, v) = (self.uniform().max(1e-300), self.uniform());
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        }
    }

    /// Held-out samples whose errors are Gaussian with the given spread.
    fn draw(rng: &mut Lcg, n: usize, truth: [AxisSpread; 3]) -> Vec<SpreadSample> {
        (0..n)
            .map(|_| {
                let d_pf = 5.0 + 60.0 * rng.uniform();
                let fz = -(0.3 + 2.7 * rng.uniform());
                let force_n = [0.3 * fz * rng.uniform(), 0.1 * fz * rng.uniform(), fz];
                let f = magnitude(force_n);
                let error_n = std::array::from_fn(|a| truth[a].sigma_n(d_pf, f) * rng.gaussian());
                SpreadSample {
                    d_pf,
                    force_n,
                    error_n,
                }
            })
            .collect()
    }

    const TRUTH: [AxisSpread; 3] = [
        AxisSpread {
            base_n: 0.005,
            per_d_pf: 0.0004,
            per_newton: 0.0,
        },
        AxisSpread {
            base_n: 0.002,
            per_d_pf: 0.0,
            per_newton: 0.001,
        },
        AxisSpread {
            base_n: 0.01,
            per_d_pf: 0.001,
            per_newton: 0.005,
        },
    ];

    #[test]
    fn a_fitted_spread_covers_68_percent_of_fresh_errors() {
        let mut rng = Lcg(7);
        let model = ForceUncertainty::fit(&draw(&mut rng, 4000, TRUTH)).unwrap();
        let fresh = draw(&mut rng, 20000, TRUTH);
        let cov = model.coverage(&fresh).unwrap();
        for c in cov {
            assert!((c - TARGET_COVERAGE).abs() < 0.02, "coverage {cov:?}");
        }
        // It follows the spread, not only its level: the wide half of the
        // contacts gets the wider sigmas.
        let (lo, hi): (Vec<_>, Vec<_>) = fresh.iter().partition(|s| s.d_pf < 35.0);
        let mean_sigma = |set: &[&SpreadSample]| {
            set.iter()
                .map(|s| model.sigma_n(s.d_pf, s.force_n)[2])
                .sum::<f64>()
                / set.len() as f64
        };
        assert!(mean_sigma(&hi) > 1.5 * mean_sigma(&lo));
        // Coverage holds within each half, which a constant sigma would miss.
        let owned = |set: &[&SpreadSample]| set.iter().map(|s| **s).collect::<Vec<_>>();
        for half in [owned(&lo), owned(&hi)] {
            let c = model.coverage(&half).unwrap()[2];
            assert!((c - TARGET_COVERAGE).abs() < 0.04, "half coverage {c}");
        }
    }

    #[test]
    fn a_constant_sigma_misses_the_halves() {
        // The check above can fail: a model without the d_pf term covers
        // the narrow half far more than the wide one.
        let mut rng = Lcg(8);
        let fresh = draw(&mut rng, 20000, TRUTH);
        let flat = ForceUncertainty {
            axes: [AxisSpread {
                base_n: 0.05,
                per_d_pf: 0.0,
                per_newton: 0.0,
            }; 3],
            samples: 0,
            test_coverage: None,
        };
        let lo: Vec<_> = fresh.iter().filter(|s| s.d_pf < 35.0).copied().collect();
        let hi: Vec<_> = fresh.iter().filter(|s| s.d_pf >= 35.0).copied().collect();
        let (a, b) = (
            flat.coverage(&lo).unwrap()[2],
            flat.coverage(&hi).unwrap()[2],
        );
        assert!(a - b > 0.1, "{a} vs {b}");
    }

    #[test]
    fn too_few_or_non_finite_samples_are_refused() {
        let mut rng = Lcg(9);
        let mut s = draw(&mut rng, MIN_SAMPLES, TRUTH);
        assert!(ForceUncertainty::fit(&s).is_ok());
        s[3].error_n[1] = f64::NAN;
        s[4].d_pf = f64::INFINITY;
        let e = ForceUncertainty::fit(&s).unwrap_err().to_string();
        assert!(e.contains("at least 20") && e.contains("got 18"), "{e}");
        assert!(ForceUncertainty::fit(&[]).is_err());
        // Coverage skips them too, and says nothing of an empty set.
        let model = ForceUncertainty::fit(&draw(&mut rng, 100, TRUTH)).unwrap();
        assert!(model.coverage(&s).is_some());
        assert!(model.coverage(&s[3..5]).is_none());
    }

    #[test]
    fn errors_of_zero_give_a_sigma_of_zero() {
        let mut rng = Lcg(10);
        let mut s = draw(&mut rng, 50, TRUTH);
        for x in &mut s {
            x.error_n = [0.0; 3];
        }
        let m = ForceUncertainty::fit(&s).unwrap();
        assert_eq!(m.sigma_n(30.0, [0.0, 0.0, -2.0]), [0.0; 3]);
    }

    #[test]
    fn validation_names_the_broken_coefficient() {
        let good = ForceUncertainty {
            axes: TRUTH,
            samples: 10,
            test_coverage: Some([0.6, 0.7, 0.68]),
        };
        assert!(good.validate().is_ok());
        for (axis, k, v) in [
            (0, 0, -0.1),
            (1, 1, f64::NAN),
            (2, 2, 2e6),
            (2, 0, f64::INFINITY),
        ] {
            let mut bad = good.clone();
            let a = &mut bad.axes[axis];
            *[&mut a.base_n, &mut a.per_d_pf, &mut a.per_newton][k] = v;
            let e = bad.validate().unwrap_err();
            let name = ["base_n", "per_d_pf", "per_newton"][k];
            assert!(e.contains(name) && e.contains(["x", "y", "z"][axis]), "{e}");
        }
        let mut bad = good.clone();
        bad.test_coverage = Some([0.5, 1.5, 0.5]);
        assert!(bad.validate().unwrap_err().contains("test_coverage"));
    }

    fn objective(features: &[[f64; 3]], y: &[f64], c: &[f64; 3]) -> f64 {
        features
            .iter()
            .zip(y)
            .map(|(f, &y)| (dot(f, c) - y).powi(2))
            .sum()
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 64, rng_seed: proptest::test_runner::RngSeed::Fixed(19), ..ProptestConfig::default() })]

        /// The fit is the constrained optimum: it satisfies the optimality
        /// (KKT) conditions of non-negative least squares, and no random
        /// non-negative coefficients do better.
        #[test]
        fn nnls_is_the_constrained_optimum(
            rows in proptest::collection::vec((0.0f64..80.0, 0.0f64..4.0, -0.05f64..0.3), 5..60),
            trials in proptest::collection::vec((0.0f64..0.1, 0.0f64..0.01, 0.0f64..0.1), 50),
        ) {
            let features: Vec<[f64; 3]> = rows.iter().map(|r| [1.0, r.0, r.1]).collect();
            let y: Vec<f64> = rows.iter().map(|r| r.2).collect();
            let c = nnls_abs(&features, &y);
            prop_assert!(c.iter().all(|v| *v >= 0.0));
            let best = objective(&features, &y, &c);
            // Gradient of the objective at c (up to a factor 2).
            let mut g = [0.0; 3];
            for (f, &y) in features.iter().zip(&y) {
                let r = dot(f, &c) - y;
                for j in 0..3 {
                    g[j] += f[j] * r;
                }
            }
            for j in 0..3 {
                let size: f64 = features.iter().map(|f| f[j].abs()).sum::<f64>()
                    * y.iter().map(|v| v.abs()).fold(1.0, f64::max);
                let tol = 1e-7 * size.max(1.0);
                if c[j] > 0.0 {
                    prop_assert!(g[j].abs() <= tol, "gradient {g:?} at {c:?}");
                } else {
                    prop_assert!(g[j] >= -tol, "gradient {g:?} at {c:?}");
                }
            }
            for t in &trials {
                let o = objective(&features, &y, &[t.0, t.1, t.2]);
                prop_assert!(o >= best - 1e-12 * best.max(1.0));
            }
        }

        /// On the samples it was fitted on, at least the target fraction of
        /// the errors lies within one sigma (the sample that sets the level
        /// included, however the scaled coefficients round), and at most
        /// one sample more than the target's share plus the ties at the
        /// level.
        #[test]
        fn the_level_covers_its_own_samples(
            seed in 0u64..1_000_000,
            n in MIN_SAMPLES..400,
        ) {
            let mut rng = Lcg(seed);
            let samples = draw(&mut rng, n, TRUTH);
            let u = ForceUncertainty::fit(&samples).unwrap();
            let least = (TARGET_COVERAGE * n as f64).ceil() / n as f64;
            for c in u.coverage(&samples).unwrap() {
                prop_assert!(c >= least - 1e-12 && c >= TARGET_COVERAGE, "{c} of {n}");
                prop_assert!(c <= least + 1.0 / n as f64 + 1e-12, "{c} of {n}");
            }
        }
    }
}
