use super::*;
use proptest::prelude::*;

/// The dots of a square grid of `pitch` px offset by `phase`, covering
/// `0..side` px.
fn grid(pitch: f64, phase: [f64; 2], side: f64) -> Vec<[f64; 2]> {
    let n = (side / pitch) as usize;
    let mut dots = Vec::new();
    for i in 0..n {
        for j in 0..n {
            dots.push([phase[0] + j as f64 * pitch, phase[1] + i as f64 * pitch]);
        }
    }
    dots
}

/// A normal press's motion about `c`: outward, `amp * r / sigma *
/// exp(-r^2 / 2 sigma^2)` px at distance `r`, plus `shear` where the press
/// moves the gel (its motion reaches a tenth of its peak).
fn press(
    dots: &[[f64; 2]],
    c: [f64; 2],
    sigma: f64,
    amp: f64,
    shear: [f64; 2],
) -> Vec<Option<[f64; 2]>> {
    dots.iter()
        .map(|p| {
            let s = [p[0] - c[0], p[1] - c[1]];
            let g = (-(s[0] * s[0] + s[1] * s[1]) / (2.0 * sigma * sigma)).exp();
            let t = if g > 0.1 { shear } else { [0.0, 0.0] };
            Some([amp * s[0] / sigma * g + t[0], amp * s[1] / sigma * g + t[1]])
        })
        .collect()
}

/// The box of half-side `half` about `c`, clipped at 0.
fn around(c: [f64; 2], half: f64) -> Roi {
    let (x, y) = ((c[0] - half).max(0.0), (c[1] - half).max(0.0));
    Roi::new(
        x as usize,
        y as usize,
        (2.0 * half) as usize,
        (2.0 * half) as usize,
    )
}

/// The slow twin: the same dots, mean and lines, the point found by
/// minimising the weighted squared distances to the lines over a grid that
/// shrinks about its best node.
fn twin(dots: &[[f64; 2]], moved: &[Option<[f64; 2]>], region: Roi, start: [f64; 2]) -> [f64; 2] {
    let inside = |p: &[f64; 2]| {
        p[0] >= region.x as f64
            && p[0] < (region.x + region.w) as f64
            && p[1] >= region.y as f64
            && p[1] < (region.y + region.h) as f64
    };
    let own: Vec<([f64; 2], [f64; 2])> = dots
        .iter()
        .zip(moved)
        .filter(|(p, _)| inside(p))
        .map(|(p, m)| (*p, m.unwrap()))
        .collect();
    let n = own.len() as f64;
    let mean = [
        own.iter().map(|(_, m)| m[0]).sum::<f64>() / n,
        own.iter().map(|(_, m)| m[1]).sum::<f64>() / n,
    ];
    let largest = own
        .iter()
        .map(|(_, m)| m[0].hypot(m[1]))
        .fold(0.0, f64::max);
    let lines: Vec<([f64; 2], [f64; 2])> = own
        .iter()
        .map(|(p, m)| (*p, [m[0] - mean[0], m[1] - mean[1]]))
        .filter(|(_, r)| r[0].hypot(r[1]) >= LINE_FRACTION * largest)
        .collect();
    // Squared distance from c to the line through p along r, times |r|^2.
    let cost = |c: [f64; 2]| -> f64 {
        lines
            .iter()
            .map(|(p, r)| {
                let cross = (c[0] - p[0]) * r[1] - (c[1] - p[1]) * r[0];
                cross * cross
            })
            .sum()
    };
    let (mut best, mut step) = (start, 4.0);
    for _ in 0..60 {
        let centre = best;
        for i in -10..=10 {
            for j in -10..=10 {
                let c = [centre[0] + i as f64 * step, centre[1] + j as f64 * step];
                if cost(c) < cost(best) {
                    best = c;
                }
            }
        }
        step *= 0.5;
    }
    best
}

#[test]
fn the_lines_meet_where_a_light_press_is_between_four_dots() {
    // A light press between four dots of a 22 px grid, nearer one row than
    // the other: only the four dots around it move.
    let dots = grid(22.0, [5.0, 5.0], 200.0);
    let c = [98.0, 101.5];
    let moved = press(&dots, c, 8.0, 3.0, [0.0, 0.0]);
    let moving = moved
        .iter()
        .filter(|m| m.unwrap()[0].hypot(m.unwrap()[1]) > 0.05)
        .count();
    assert_eq!(moving, 4, "the press moves the four dots about it");
    // Started 4.9 px off, as a slope peak pulled towards a row of dots.
    let got = motion_centre(&dots, &moved, around(c, 60.0), &[[96.0, 97.0]], 0, 22.0).unwrap();
    // Exact but for the region's mean motion, taken out against shear: the
    // four dots' motions do not cancel, so 0.7 px remains.
    assert!((got[0] - c[0]).hypot(got[1] - c[1]) < 1.0, "{got:?}");
}

#[test]
fn each_of_two_contacts_takes_its_own_dots() {
    let dots = grid(20.0, [3.0, 7.0], 300.0);
    let (a, b) = ([90.0, 120.0], [171.0, 126.0]);
    let one = press(&dots, a, 14.0, 2.0, [0.0, 0.0]);
    let two = press(&dots, b, 20.0, 3.0, [0.0, 0.0]);
    let moved: Vec<_> = one
        .iter()
        .zip(&two)
        .map(|(p, q)| Some([p.unwrap()[0] + q.unwrap()[0], p.unwrap()[1] + q.unwrap()[1]]))
        .collect();
    // Both boxes hold both presses.
    let region = Roi::new(30, 60, 210, 130);
    let starts = [[92.0, 118.0], [168.0, 128.0]];
    for (k, truth) in [a, b].into_iter().enumerate() {
        let got = motion_centre(&dots, &moved, region, &starts, k, 20.0).unwrap();
        let off = (got[0] - truth[0]).hypot(got[1] - truth[1]);
        assert!(off < 1.0, "contact {k}: {got:?} against {truth:?}");
    }
    // Taken as one contact, the dots of both pull the point away from each.
    let alone = motion_centre(&dots, &moved, region, &starts[..1], 0, 100.0).unwrap();
    assert!((alone[0] - a[0]).hypot(alone[1] - a[1]) > 3.0, "{alone:?}");
}

#[test]
fn no_point_without_lines_that_cross() {
    let dots = grid(22.0, [5.0, 5.0], 200.0);
    let region = Roi::new(0, 0, 200, 200);
    let start = [[100.0, 100.0]];
    // Nothing moved, or every dot lost.
    let still = vec![Some([0.0, 0.0]); dots.len()];
    assert_eq!(motion_centre(&dots, &still, region, &start, 0, 22.0), None);
    let lost = vec![None; dots.len()];
    assert_eq!(motion_centre(&dots, &lost, region, &start, 0, 22.0), None);
    // The same motion everywhere: nothing is left once the mean is out.
    let slid = vec![Some([1.5, -0.5]); dots.len()];
    assert_eq!(motion_centre(&dots, &slid, region, &start, 0, 22.0), None);
    // Dots moving along one line: the lines run side by side.
    let along: Vec<_> = dots
        .iter()
        .map(|p| {
            Some(if (p[1] - 93.0).abs() < 1.0 {
                [(p[0] - 100.0) * 0.05, 0.0]
            } else {
                [0.0, 0.0]
            })
        })
        .collect();
    assert_eq!(motion_centre(&dots, &along, region, &start, 0, 22.0), None);
    // No contact `k`, a non-finite start, no dots.
    let moved = press(&dots, [100.0, 100.0], 15.0, 2.0, [0.0, 0.0]);
    assert_eq!(motion_centre(&dots, &moved, region, &start, 1, 22.0), None);
    assert_eq!(
        motion_centre(&dots, &moved, region, &[[f64::NAN, 1.0]], 0, 22.0),
        None
    );
    assert_eq!(motion_centre(&[], &[], region, &start, 0, 22.0), None);
    // A point beyond the reach: the current one stands.
    let far = press(&dots, [140.0, 100.0], 15.0, 2.0, [0.0, 0.0]);
    assert_eq!(motion_centre(&dots, &far, region, &start, 0, 22.0), None);
    assert!(motion_centre(&dots, &far, region, &start, 0, 45.0).is_some());
}

#[test]
fn a_non_finite_motion_is_left_out() {
    let dots = grid(22.0, [5.0, 5.0], 200.0);
    let c = [103.0, 95.0];
    let mut moved = press(&dots, c, 15.0, 2.0, [0.0, 0.0]);
    let region = around(c, 70.0);
    let clean = motion_centre(&dots, &moved, region, &[c], 0, 22.0).unwrap();
    // A dot far outside the region, made non-finite, changes nothing.
    moved[0] = Some([f64::NAN, f64::INFINITY]);
    assert_eq!(
        motion_centre(&dots, &moved, region, &[c], 0, 22.0),
        Some(clean)
    );
}

/// A press near the middle of a grid, for the property tests.
struct Case {
    dots: Vec<[f64; 2]>,
    moved: Vec<Option<[f64; 2]>>,
    /// The load's point.
    c: [f64; 2],
    /// Reaching 3 sigma and a pitch about the load.
    region: Roi,
}

/// A press of `sigma_of_pitch` pitches and `amp` px with `shear` on a grid
/// of `pitch` px: its offset `at` from the middle and the grid's `phase`
/// in pitches.
fn case(
    pitch: f64,
    phase: [f64; 2],
    at: [f64; 2],
    sigma_of_pitch: f64,
    amp: f64,
    shear: [f64; 2],
) -> Case {
    let dots = grid(pitch, [phase[0] * pitch, phase[1] * pitch], 260.0);
    let c = [130.0 + at[0] * pitch, 130.0 + at[1] * pitch];
    let sigma = sigma_of_pitch * pitch;
    let moved = press(&dots, c, sigma, amp, shear);
    let region = around(c, 3.0 * sigma + pitch);
    Case {
        dots,
        moved,
        c,
        region,
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// The closed form against its slow twin, on presses of any size and
    /// shear, anywhere against grids of any pitch and phase.
    #[test]
    fn the_closed_form_matches_its_twin(
        pitch in 12.0f64..30.0,
        phase in prop::array::uniform2(0.0f64..1.0),
        at in prop::array::uniform2(-0.5f64..0.5),
        sigma_of_pitch in 0.5f64..1.5,
        amp in 0.5f64..5.0,
        shear in prop::array::uniform2(-1.0f64..1.0),
    ) {
        let Case { dots, moved, c, region } = case(pitch, phase, at, sigma_of_pitch, amp, shear);
        if let Some(got) = motion_centre(&dots, &moved, region, &[c], 0, pitch) {
            let slow = twin(&dots, &moved, region, c);
            prop_assert!((got[0] - slow[0]).hypot(got[1] - slow[1]) < 1e-4 * pitch,
                "{:?} against {:?}", got, slow);
        }
    }

    /// A straight press is found within a tenth of a pitch, whatever the
    /// grid's phase under it (the slope peak's error follows the phase).
    #[test]
    fn a_straight_press_is_found_at_any_phase(
        pitch in 12.0f64..30.0,
        phase in prop::array::uniform2(0.0f64..1.0),
        at in prop::array::uniform2(-0.5f64..0.5),
        sigma_of_pitch in 0.5f64..1.5,
        amp in 0.5f64..5.0,
    ) {
        let Case { dots, moved, c, region } = case(pitch, phase, at, sigma_of_pitch, amp, [0.0, 0.0]);
        let start = [c[0] + 0.3 * pitch, c[1] - 0.2 * pitch];
        let got = motion_centre(&dots, &moved, region, &[start], 0, pitch);
        prop_assert!(got.is_some());
        let got = got.unwrap();
        prop_assert!((got[0] - c[0]).hypot(got[1] - c[1]) < 0.1 * pitch, "{:?} against {:?}", got, c);
    }
}
