use super::*;
use nalgebra::{DMatrix, DVector};
use proptest::prelude::*;
use proptest::test_runner::{Config as ProptestConfig, RngSeed};

/// A field of the model's kind: the squeeze `alpha grad S` and the shear
/// `beta S` of `profile`, radius `a`, centred at `c`; `power` replaces the
/// profile's exponent by any real one (a shape outside the fit's family).
fn field(p: [f64; 2], c: [f64; 2], a: f64, power: f64, alpha: f64, beta: [f64; 2]) -> [f64; 2] {
    let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
    let one = 1.0 - (dx * dx + dy * dy) / (a * a);
    if one <= 0.0 {
        return [0.0; 2];
    }
    let s = one.powf(power);
    let k = -2.0 * power * one.powf(power - 1.0) / (a * a);
    [alpha * k * dx + beta[0] * s, alpha * k * dy + beta[1] * s]
}

/// A square grid of dots of `pitch`, `n` a side, its first dot at `origin`.
fn grid(pitch: f64, n: usize, origin: [f64; 2]) -> Vec<[f64; 2]> {
    (0..n * n)
        .map(|k| {
            let (i, j) = ((k / n) as f64, (k % n) as f64);
            [origin[0] + j * pitch, origin[1] + i * pitch]
        })
        .collect()
}

fn moved(dots: &[[f64; 2]], mut f: impl FnMut([f64; 2]) -> [f64; 2]) -> Vec<Option<[f64; 2]>> {
    dots.iter().map(|&p| Some(f(p))).collect()
}

/// The slow twin of `solve`: the design matrix written out, solved by SVD.
fn solve_slow(s: &Samples, profile: Profile, c: [f64; 2], a: f64) -> (f64, f64, [f64; 2]) {
    let n = s.at.len();
    let mut m = DMatrix::zeros(2 * n, 3);
    let mut b = DVector::zeros(2 * n);
    for (k, (p, d)) in s.at.iter().zip(&s.motion).enumerate() {
        let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
        let (v, g) = profile.value(dx * dx + dy * dy, a);
        m[(2 * k, 0)] = g * dx;
        m[(2 * k + 1, 0)] = g * dy;
        m[(2 * k, 1)] = v;
        m[(2 * k + 1, 2)] = v;
        b[2 * k] = d[0];
        b[2 * k + 1] = d[1];
    }
    let x = m.clone().svd(true, true).solve(&b, 1e-12).unwrap();
    let r = &b - &m * &x;
    (r.norm_squared(), x[0], [x[1], x[2]])
}

fn samples(dots: &[[f64; 2]], motion: &[Option<[f64; 2]>]) -> Samples {
    let motion: Vec<[f64; 2]> = motion.iter().map(|m| m.unwrap()).collect();
    let norm2 = motion.iter().map(|m| m[0] * m[0] + m[1] * m[1]).sum();
    Samples {
        at: dots.to_vec(),
        motion,
        norm2,
    }
}

#[test]
fn the_normal_equations_match_the_written_out_least_squares() {
    let dots = grid(20.0, 9, [10.0, 12.0]);
    let c = [93.0, 88.5];
    let motion = moved(&dots, |p| {
        let f = field(p, c, 47.0, 2.0, -300.0, [2.5, -1.5]);
        // Motion the model cannot explain, so that the residual is not 0.
        [
            f[0] + 0.3 * (p[1] * 0.37).sin(),
            f[1] + 0.2 * (p[0] * 0.23).cos(),
        ]
    });
    let s = samples(&dots, &motion);
    for profile in Profile::ALL {
        for (cc, a) in [(c, 47.0), ([90.0, 91.0], 35.0), ([100.0, 80.0], 70.0)] {
            let fast = solve(&s, profile, cc, a);
            let slow = solve_slow(&s, profile, cc, a);
            let scale = s.norm2;
            assert!(
                (fast.0 - slow.0).abs() <= 1e-9 * scale,
                "{profile:?} {fast:?} {slow:?}"
            );
            assert!((fast.1 - slow.1).abs() <= 1e-7 * (1.0 + slow.1.abs()));
            for k in 0..2 {
                assert!((fast.2[k] - slow.2[k]).abs() <= 1e-7 * (1.0 + slow.2[k].abs()));
            }
        }
    }
}

#[test]
fn the_search_ends_no_worse_than_a_fine_grid_of_centres_and_radii() {
    // The slow twin of the compass search: every centre within a pitch on
    // a grid of a tenth of a pitch, every radius on a grid of 1 px.
    let pitch = 20.0;
    let dots = grid(pitch, 11, [0.0, 0.0]);
    let c = [103.0, 96.0];
    let motion = moved(&dots, |p| field(p, c, 43.0, 2.0, -250.0, [1.0, 2.0]));
    let start = [100.0, 100.0];
    let fit = fit_round_field(&dots, &motion, &[start], 0, pitch).unwrap();
    let s = samples(&dots, &motion);
    let mut brute = f64::INFINITY;
    for i in -10..=10 {
        for j in -10..=10 {
            let cc = [start[0] + 2.0 * f64::from(j), start[1] + 2.0 * f64::from(i)];
            for a in 20..=80 {
                brute = brute.min(solve(&s, Profile::Compact(4), cc, f64::from(a)).0);
            }
        }
    }
    let found = fit.residual * fit.residual * s.norm2;
    assert!(
        found <= brute + 1e-9 * s.norm2,
        "search {found}, grid {brute}"
    );
    assert_eq!(fit.profile, Profile::Compact(4));
    assert!((fit.centre[0] - c[0]).abs() < 0.05 && (fit.centre[1] - c[1]).abs() < 0.05);
    assert!((fit.radius_px - 43.0).abs() < 0.1, "{}", fit.radius_px);
}

#[test]
fn a_field_of_the_family_gives_its_integrals_where_the_sums_swing() {
    // A radial squeeze twice the shear, on a contact two pitches wide,
    // moved across one pitch: the fitted integrals stay, the sums swing.
    let pitch = 22.0;
    let dots = grid(pitch, 13, [0.0, 0.0]);
    let (a, alpha, beta) = (38.0, -400.0, [0.0, 3.0]);
    let integral = Profile::Compact(4).integral(a);
    let (mut fitted, mut sums) = (Vec::new(), Vec::new());
    for k in 0..11 {
        let c = [132.0 + 0.3 * f64::from(k), 132.0 + 2.0 * f64::from(k)];
        let motion = moved(&dots, |p| field(p, c, a, 2.0, alpha, beta));
        let fit = fit_round_field(&dots, &motion, &[[c[0] + 3.0, c[1] - 4.0]], 0, pitch).unwrap();
        assert!(fit.holds());
        assert!(
            (fit.shear[1] / (beta[1] * integral) - 1.0).abs() < 0.01,
            "{fit:?}"
        );
        assert!(
            (fit.normal / (-alpha * integral) - 1.0).abs() < 0.01,
            "{fit:?}"
        );
        assert!(fit.shear[0].abs() < 0.01 * beta[1] * integral);
        fitted.push(fit.shear[1]);
        sums.push(fit.sums.0[1]);
    }
    let spread = |v: &[f64]| {
        let (lo, hi) = v
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &x| {
                (l.min(x), h.max(x))
            });
        (hi - lo) / (0.5 * (hi + lo))
    };
    assert!(spread(&fitted) < 0.01, "fitted {fitted:?}");
    assert!(spread(&sums) > 0.1, "the sums should swing: {sums:?}");
}

#[test]
fn hostile_input_gives_none_or_a_fit_that_does_not_hold_never_a_panic() {
    let dots = grid(20.0, 9, [0.0, 0.0]);
    let still = vec![Some([0.0, 0.0]); dots.len()];
    let some = moved(&dots, |p| {
        field(p, [80.0, 80.0], 40.0, 2.0, -100.0, [1.0, 0.0])
    });
    // Nothing, nothing moving, no pitch, no start.
    assert!(fit_round_field(&[], &[], &[[0.0, 0.0]], 0, 20.0).is_none());
    assert!(fit_round_field(&dots, &still, &[[80.0, 80.0]], 0, 20.0).is_none());
    for pitch in [0.0, -3.0, f64::NAN, f64::INFINITY] {
        assert!(fit_round_field(&dots, &some, &[[80.0, 80.0]], 0, pitch).is_none());
    }
    assert!(fit_round_field(&dots, &some, &[[f64::NAN, 80.0]], 0, 20.0).is_none());
    // Contact out of range; too few dots: other contacts all about it,
    // lost dots, fewer motions than dots.
    assert!(fit_round_field(&dots, &some, &[[80.0, 80.0]], 1, 20.0).is_none());
    let crowded = [
        [80.0, 80.0],
        [81.0, 80.0],
        [79.0, 80.0],
        [80.0, 81.0],
        [80.0, 79.0],
    ];
    assert!(fit_round_field(&dots, &some, &crowded, 0, 20.0).is_none());
    let lost = vec![None; dots.len()];
    assert!(fit_round_field(&dots, &lost, &[[80.0, 80.0]], 0, 20.0).is_none());
    assert!(fit_round_field(&dots, &some[..5], &[[80.0, 80.0]], 0, 20.0).is_none());
    // Non-finite motions are skipped; the rest still fits.
    let mut bad = some.clone();
    bad[3] = Some([f64::NAN, 1.0]);
    bad[4] = Some([f64::INFINITY, 0.0]);
    let fit = fit_round_field(&dots, &bad, &[[80.0, 80.0]], 0, 20.0).unwrap();
    assert!(fit.holds() && fit.shear.iter().all(|v| v.is_finite()));
    // Noise alone: a fit, but one that does not hold.
    let mut state = 7u64;
    let noise = moved(&dots, |_| {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
        let u = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
        [u, -u * 0.7]
    });
    let fit = fit_round_field(&dots, &noise, &[[80.0, 80.0]], 0, 20.0);
    assert!(fit.is_none_or(|f| !f.holds()), "{fit:?}");
    // Huge motions stay finite.
    let huge = moved(&dots, |p| {
        field(p, [80.0, 80.0], 40.0, 2.0, -1e12, [1e9, 0.0])
    });
    let fit = fit_round_field(&dots, &huge, &[[80.0, 80.0]], 0, 20.0).unwrap();
    assert!(fit.shear.iter().chain([&fit.normal]).all(|v| v.is_finite()));
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 48,
        rng_seed: RngSeed::Fixed(0x0A0D_F17E),
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    /// Any pitch, contact size (a profile's standard deviation of 0.6 to
    /// 1.1 pitches), place against the dots, squeeze and shear, with a
    /// profile of the family: the shear and the normal within 2% of the
    /// field's integrals, the fit holding.
    #[test]
    fn round_fields_give_their_integrals_wherever_they_sit(
        pitch in 12.0f64..40.0,
        size in 0.6f64..1.1,
        phase in (0.0f64..1.0, 0.0f64..1.0),
        power in prop_oneof![Just(2.0), Just(2.5), Just(3.0), Just(3.5), Just(4.0)],
        squeeze in 0.0f64..3.0,
        shear in (-1.0f64..1.0, -1.0f64..1.0),
    ) {
        check_integrals(pitch, size, phase, power, squeeze, shear, 0.02)?;
    }

    /// The same with a profile between the family's members (exponents 2
    /// to 4): within 5% (measured: at most 4%, a profile between the
    /// exponents 2 and 2.5 under a strong squeeze). Narrower than about half
    /// a pitch, a field is not pinned by the samples: with one dot under its
    /// middle, a profile of another width and height fits it as well.
    #[test]
    fn profiles_between_the_family_give_their_integrals_too(
        pitch in 12.0f64..40.0,
        size in 0.6f64..1.1,
        phase in (0.0f64..1.0, 0.0f64..1.0),
        power in 2.0f64..4.0,
        squeeze in 0.0f64..3.0,
        shear in (-1.0f64..1.0, -1.0f64..1.0),
    ) {
        check_integrals(pitch, size, phase, power, squeeze, shear, 0.05)?;
    }
}

/// The fit of one analytic field on a square grid (see the properties):
/// its shear and normal within `tolerance` of the field's integrals.
fn check_integrals(
    pitch: f64,
    size: f64,
    phase: (f64, f64),
    power: f64,
    squeeze: f64,
    shear: (f64, f64),
    tolerance: f64,
) -> Result<(), TestCaseError> {
    prop_assume!(squeeze + shear.0.abs() + shear.1.abs() > 0.2);
    // `size`: the profile's standard deviation along an axis, in pitches;
    // for `(1 - r^2/a^2)^n` it is `a / sqrt(2 (n + 2))`.
    let a = size * pitch * (2.0 * (power + 2.0)).sqrt();
    let dots = grid(pitch, 15, [0.0, 0.0]);
    let c = [7.0 * pitch + phase.0 * pitch, 7.0 * pitch + phase.1 * pitch];
    // Amplitudes in pixels of peak motion: shear up to a third of the
    // pitch, squeeze up to three times the shear's scale.
    let beta = [shear.0 * pitch / 3.0, shear.1 * pitch / 3.0];
    let alpha = -squeeze * a * pitch / 12.0;
    let motion = moved(&dots, |p| field(p, c, a, power, alpha, beta));
    let start = [c[0] + 0.2 * pitch, c[1] - 0.2 * pitch];
    // The grid must hold the whole field.
    let dots_span = 14.0 * pitch;
    prop_assume!(c[0] - a > 0.0 && c[0] + a < dots_span);
    let fit = fit_round_field(&dots, &motion, &[start], 0, pitch).expect("a fit");
    prop_assert!(fit.holds(), "{:?}", fit);
    // The field's own integrals: the profile integrates to pi a^2 / (power + 1).
    let integral = std::f64::consts::PI * a * a / (power + 1.0);
    let scale = (beta[0].hypot(beta[1]) + alpha.abs() / a) * integral;
    for k in 0..2 {
        prop_assert!(
            (fit.shear[k] - beta[k] * integral).abs() <= tolerance * scale,
            "shear {:?} vs {:?}",
            fit.shear,
            [beta[0] * integral, beta[1] * integral]
        );
    }
    // The normal is a length times a motion: its scale is the shear's
    // times the radius.
    prop_assert!(
        (fit.normal + alpha * integral).abs() <= tolerance * scale * a,
        "normal {} vs {}",
        fit.normal,
        -alpha * integral
    );
    Ok(())
}
