//! The dot tracker on rendered dot grids: the dots found, followed under
//! known motion, the spread flow against a direct sum, and bad input.

use super::*;
use proptest::prelude::*;
use proptest::test_runner::RngSeed;

/// A deterministic standard normal stream (sum of uniforms).
struct Noise(u64);

impl Noise {
    fn normal(&mut self) -> f32 {
        let mut s = 0.0;
        for _ in 0..12 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            s += (self.0 >> 11) as f64 / (1u64 << 53) as f64;
        }
        (s - 6.0) as f32
    }
}

/// A `w x h` image of round dots at `centres` (radius `r`, a soft edge of
/// 1.5 px): `dark` dots taking 2/3 of the light of a gel lit to 180, or
/// bright dots adding 120 grey levels to a gel at 40, with the light
/// falling off by 15% towards the edges; camera noise of `noise` grey
/// levels.
fn render(
    w: usize,
    h: usize,
    centres: &[[f64; 2]],
    r: f64,
    dark: bool,
    noise: f32,
    seed: u64,
) -> Array2<f32> {
    render_lit(w, h, centres, (r, dark), noise, seed, 0.15)
}

/// [`render`] with the light falling off by `falloff` (a fraction of the
/// centre's) towards the middle of each edge (twice that in the corners),
/// the dots' contrast with it.
fn render_lit(
    w: usize,
    h: usize,
    centres: &[[f64; 2]],
    (r, dark): (f64, bool),
    noise: f32,
    seed: u64,
    falloff: f64,
) -> Array2<f32> {
    let mut n = Noise(seed);
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let light = |i: usize, j: usize| {
        (1.0 - falloff * (((j as f64 - cx) / cx).powi(2) + ((i as f64 - cy) / cy).powi(2))) as f32
    };
    let mut cover = Array2::<f32>::zeros((h, w));
    let e = 1.5;
    for c in centres {
        let reach = (r + e + 1.0).ceil() as isize;
        let (ci, cj) = (c[1].round() as isize, c[0].round() as isize);
        for i in ci - reach..=ci + reach {
            for j in cj - reach..=cj + reach {
                if i < 0 || j < 0 || i >= h as isize || j >= w as isize {
                    continue;
                }
                let d = ((j as f64 - c[0]).powi(2) + (i as f64 - c[1]).powi(2)).sqrt();
                let t = ((r + e - d) / (2.0 * e)).clamp(0.0, 1.0);
                cover[[i as usize, j as usize]] += (t * t * (3.0 - 2.0 * t)) as f32;
            }
        }
    }
    Array2::from_shape_fn((h, w), |(i, j)| {
        let p = cover[[i, j]].min(1.0);
        let v = if dark {
            180.0 * light(i, j) * (1.0 - 2.0 / 3.0 * p)
        } else {
            light(i, j) * (40.0 + 120.0 * p)
        };
        (v + noise * n.normal()).clamp(0.0, 255.0)
    })
}

/// The centres of a square grid of `pitch` px offset by `(ox, oy)`,
/// every dot whole inside `w x h`.
fn grid(w: usize, h: usize, pitch: f64, ox: f64, oy: f64) -> Vec<[f64; 2]> {
    let mut v = Vec::new();
    let mut y = oy;
    while y < h as f64 - 6.0 {
        let mut x = ox;
        while x < w as f64 - 6.0 {
            if x > 6.0 && y > 6.0 {
                v.push([x, y]);
            }
            x += pitch;
        }
        y += pitch;
    }
    v
}

/// A smooth bump of motion: radial, `amp` px at most, about `(x0, y0)`.
fn bump(amp: f64, x0: f64, y0: f64, width: f64) -> impl Fn([f64; 2]) -> [f64; 2] {
    move |[x, y]| {
        let (dx, dy) = (x - x0, y - y0);
        let g = amp * (-(dx * dx + dy * dy) / (2.0 * width * width)).exp() / width;
        [g * dx, g * dy]
    }
}

/// `centres`, each moved by `field`.
fn displaced(centres: &[[f64; 2]], field: &dyn Fn([f64; 2]) -> [f64; 2]) -> Vec<[f64; 2]> {
    centres
        .iter()
        .map(|&c| {
            let d = field(c);
            [c[0] + d[0], c[1] + d[1]]
        })
        .collect()
}

/// The nearest true centre's distance to `c`.
fn nearest(truth: &[[f64; 2]], c: [f64; 2]) -> (usize, f64) {
    truth
        .iter()
        .enumerate()
        .map(|(k, t)| (k, (t[0] - c[0]).hypot(t[1] - c[1])))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("centres")
}

/// Asserts that every dot of `t` was followed to within `tol` px of the
/// motion `field` gives its true centre (the nearest of `truth`).
fn every_dot_followed(
    t: &DotTracker,
    truth: &[[f64; 2]],
    field: &dyn Fn([f64; 2]) -> [f64; 2],
    tol: f64,
    case: &str,
) {
    for (&c, d) in t.dots().iter().zip(t.displacements()) {
        let (k, _) = nearest(truth, c);
        let d = d.unwrap_or_else(|| panic!("{case}: dot {c:?} lost"));
        let off = dist(d, field(truth[k]));
        assert!(off < tol, "{case}: dot {c:?} {off} px off ({d:?})");
    }
}

/// A native flow at `scale` px per cell holding `field` (full-resolution
/// px) plus a constant error, in its cells' units.
fn flow_of(
    w: usize,
    h: usize,
    scale: usize,
    field: &dyn Fn([f64; 2]) -> [f64; 2],
    error: [f64; 2],
) -> FlowField {
    let (fw, fh) = (w.div_ceil(scale), h.div_ceil(scale));
    let s = scale as f64;
    let mut f = FlowField::zeros(fw, fh);
    for i in 0..fh {
        for j in 0..fw {
            let p = [(j as f64 + 0.5) * s - 0.5, (i as f64 + 0.5) * s - 0.5];
            let d = field(p);
            f.u[[i, j]] = ((d[0] + error[0]) / s) as f32;
            f.v[[i, j]] = ((d[1] + error[1]) / s) as f32;
        }
    }
    f
}

#[test]
fn finds_the_dots_of_grids_of_several_pitches_and_either_polarity() {
    for (pitch, r, dark, ox, oy) in [
        (22.0, 3.5, true, 11.3, 10.7),
        (16.0, 2.5, true, 8.6, 9.2),
        (30.0, 5.0, false, 14.1, 15.5),
    ] {
        let truth = grid(320, 240, pitch, ox, oy);
        let img = render(320, 240, &truth, r, dark, 1.5, 3);
        let mut t = DotTracker::new();
        let n = t.set_reference(&img, pitch).unwrap();
        assert!(
            n as f64 >= 0.9 * truth.len() as f64,
            "pitch {pitch}: {n} of {} dots",
            truth.len()
        );
        let worst = t
            .dots()
            .iter()
            .map(|&c| nearest(&truth, c).1)
            .fold(0.0, f64::max);
        assert!(worst < 0.1, "pitch {pitch}: a centre {worst} px off");
    }
}

#[test]
fn finds_every_dot_under_strongly_uneven_light() {
    // The light falls to 40% at the edges' middles and to nothing in the
    // corners' reach: the dots' contrast falls with it.
    let truth = grid(320, 240, 22.0, 11.3, 10.7);
    let img = render_lit(320, 240, &truth, (3.5, true), 1.5, 4, 0.6);
    let mut t = DotTracker::new();
    let n = t.set_reference(&img, 22.0).unwrap();
    let inner: Vec<_> = truth
        .iter()
        .filter(|c| ((c[0] - 160.0) / 160.0).powi(2) + ((c[1] - 120.0) / 120.0).powi(2) < 1.0)
        .collect();
    let found = inner
        .iter()
        .filter(|c| {
            t.dots()
                .iter()
                .any(|d| (d[0] - c[0]).hypot(d[1] - c[1]) < 0.2)
        })
        .count();
    assert!(
        found == inner.len(),
        "{found} of the {} dots within the lit ellipse found ({n} in all)",
        inner.len()
    );
}

#[test]
fn follows_dots_moved_by_a_smooth_field_from_an_imprecise_flow() {
    let (w, h, pitch) = (320, 240, 22.0);
    let truth = grid(w, h, pitch, 11.3, 10.7);
    let reference = render(w, h, &truth, 3.5, true, 1.5, 5);
    let field = bump(7.0, 150.0, 110.0, 25.0);
    let moved = displaced(&truth, &field);
    let largest = truth
        .iter()
        .map(|&c| {
            let d = field(c);
            d[0].hypot(d[1])
        })
        .fold(0.0, f64::max);
    assert!(
        largest > 3.0 && largest < 6.0,
        "the bump moves dots by {largest} px"
    );
    let frame = render(w, h, &moved, 3.5, true, 1.5, 6);
    let mut t = DotTracker::new();
    t.set_reference(&reference, pitch).unwrap();
    for scale in [1, 2, 4] {
        let mut flow = flow_of(w, h, scale, &field, [1.2, -0.8]);
        t.refine(&frame, &mut flow, scale).unwrap();
        let mut errors = Vec::new();
        for (&c, d) in t.dots().iter().zip(t.displacements()) {
            let d = d.expect("every dot followed");
            let (k, _) = nearest(&truth, c);
            let want = field(truth[k]);
            errors.push((d[0] - want[0]).hypot(d[1] - want[1]));
        }
        let mean = errors.iter().sum::<f64>() / errors.len() as f64;
        let worst = errors.iter().copied().fold(0.0, f64::max);
        assert!(
            mean < 0.03 && worst < 0.12,
            "scale {scale}: mean {mean}, worst {worst} px"
        );
    }
}

/// The centres of a hexagonal grid of `pitch` px between neighbours (rows
/// `pitch * sqrt(3) / 2` apart, every other one shifted by half a pitch),
/// every dot whole inside `w x h`.
fn hex_grid(w: usize, h: usize, pitch: f64) -> Vec<[f64; 2]> {
    let row = pitch * 3f64.sqrt() / 2.0;
    let mut v = Vec::new();
    let mut k = 0;
    while 9.0 + k as f64 * row < h as f64 - 8.0 {
        let y = 9.0 + k as f64 * row;
        let mut x = 9.3 + if k % 2 == 1 { 0.5 * pitch } else { 0.0 };
        while x < w as f64 - 8.0 {
            v.push([x, y]);
            x += pitch;
        }
        k += 1;
    }
    v
}

/// Under a small indenter the flow can lead a dot onto its neighbour (one
/// dot, a row of them each onto the next, or a whole block of them, which
/// agree with each other) or onto the plain gel between dots: each such dot
/// is found again where its neighbours' motion says.
/// Square and hexagonal grids, dark and bright dots.
#[test]
fn dots_the_flow_led_astray_are_found_again() {
    let (w, h) = (320, 240);
    let layouts = [
        ("square", grid(w, h, 22.0, 11.3, 10.7), 22.0, true),
        ("hexagonal", hex_grid(w, h, 26.0), 26.0, false),
    ];
    for (name, truth, pitch, dark) in layouts {
        let reference = render(w, h, &truth, 3.5, dark, 1.5, 7);
        // Dots near the middle move by up to 0.45 pitch.
        let field = bump(16.0 / 22.0 * pitch, 160.0, 120.0, 25.0 / 22.0 * pitch);
        let largest = truth.iter().map(|&c| norm(field(c))).fold(0.0, f64::max);
        assert!(
            largest > 0.4 * pitch && largest < 0.5 * pitch,
            "{name}: the bump moves dots by {largest} px"
        );
        let frame = render(w, h, &displaced(&truth, &field), 3.5, dark, 1.5, 8);
        // The dots the flow misleads, and how: the three nearest the
        // bump's middle each onto its right neighbour (a row of them), one
        // below a pitch upwards, one to the left onto the plain gel.
        let by_distance = |x: f64, y: f64| nearest(&truth, [x, y]).0;
        let mut astray: Vec<(usize, [f64; 2])> = Vec::new();
        for dx in [-1.0, 0.0, 1.0] {
            astray.push((by_distance(160.0 + dx * pitch, 120.0), [pitch, 0.0]));
        }
        astray.push((by_distance(160.0, 120.0 + pitch), [0.0, -pitch]));
        astray.push((
            by_distance(160.0 - 2.0 * pitch, 120.0 - pitch),
            [0.5 * pitch; 2],
        ));
        // A block of dots (a dot and every neighbour about it) a pitch left.
        let block = truth[by_distance(70.0, 175.0)];
        for (k, &c) in truth.iter().enumerate() {
            if dist(c, block) < 1.5 * pitch {
                astray.push((k, [-pitch, 0.0]));
            }
        }
        let misled = |p: [f64; 2]| {
            let d = field(p);
            let off = astray
                .iter()
                .find(|(k, _)| dist(truth[*k], p) < 0.3 * pitch)
                .map_or([0.0, 0.0], |(_, e)| *e);
            [d[0] + off[0], d[1] + off[1]]
        };
        let mut t = DotTracker::new();
        assert!(t.set_reference(&reference, pitch).unwrap() * 10 >= truth.len() * 9);
        for scale in [1, 2] {
            let mut flow = flow_of(w, h, scale, &misled, [0.0, 0.0]);
            t.refine(&frame, &mut flow, scale).unwrap();
            every_dot_followed(&t, &truth, &field, 0.15, &format!("{name}, scale {scale}"));
        }
    }
}

/// A dot pushed within half a pitch of a neighbour that did not move (the
/// gel squeezed by more than half) neither pulls that neighbour's centre
/// towards itself nor is taken for it.
#[test]
fn a_dot_squeezed_against_a_still_one_leaves_it_still() {
    let (w, h, pitch) = (320, 240, 22.0);
    let truth = grid(w, h, pitch, 11.3, 10.7);
    let reference = render(w, h, &truth, 3.5, true, 1.0, 9);
    let (pushed, still) = (
        nearest(&truth, [150.0, 120.0]).0,
        nearest(&truth, [172.0, 120.0]).0,
    );
    assert!(dist(truth[still], [truth[pushed][0] + pitch, truth[pushed][1]]) < 1e-9);
    let field = |p: [f64; 2]| {
        if dist(p, truth[pushed]) < 0.3 * pitch {
            [0.55 * pitch, 0.0]
        } else {
            [0.0, 0.0]
        }
    };
    let frame = render(w, h, &displaced(&truth, &field), 3.5, true, 1.0, 10);
    let mut t = DotTracker::new();
    t.set_reference(&reference, pitch).unwrap();
    let mut flow = flow_of(w, h, 1, &field, [0.0, 0.0]);
    t.refine(&frame, &mut flow, 1).unwrap();
    every_dot_followed(&t, &truth, &field, 0.1, "squeezed");
}

#[test]
fn the_spread_flow_matches_a_direct_sum_over_every_dot() {
    let (w, h, pitch) = (200, 150, 22.0);
    let truth = grid(w, h, pitch, 11.3, 10.7);
    let reference = render(w, h, &truth, 3.5, true, 1.0, 8);
    let field = bump(6.0, 90.0, 70.0, 20.0);
    let moved = displaced(&truth, &field);
    let frame = render(w, h, &moved, 3.5, true, 1.0, 9);
    let mut t = DotTracker::new();
    t.set_reference(&reference, pitch).unwrap();
    for scale in [1, 2, 3] {
        let before = flow_of(w, h, scale, &|_| [0.5, 0.25], [0.0, 0.0]);
        let mut flow = before.clone();
        t.refine(&frame, &mut flow, scale).unwrap();
        let s = scale as f64;
        let sigma = SPREAD_OF_PITCH * pitch;
        let (fh, fw) = flow.u.dim();
        for i in 0..fh {
            for j in 0..fw {
                let p = [(j as f64 + 0.5) * s - 0.5, (i as f64 + 0.5) * s - 0.5];
                let (mut sw, mut su, mut sv) = (0.0, 0.0, 0.0);
                for (c, d) in t.dots().iter().zip(t.displacements()) {
                    let Some(d) = d else { continue };
                    let r2 = (p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2);
                    if r2 <= (3.0 * sigma).powi(2) {
                        let wt = (-0.5 * r2 / (sigma * sigma)).exp();
                        sw += wt;
                        su += wt * d[0];
                        sv += wt * d[1];
                    }
                }
                let (u, v) = if sw >= MIN_SPREAD_WEIGHT {
                    (su / sw / s, sv / sw / s)
                } else {
                    (f64::from(before.u[[i, j]]), f64::from(before.v[[i, j]]))
                };
                assert!(
                    (f64::from(flow.u[[i, j]]) - u).abs() < 1e-4,
                    "scale {scale} cell {i},{j}"
                );
                assert!(
                    (f64::from(flow.v[[i, j]]) - v).abs() < 1e-4,
                    "scale {scale} cell {i},{j}"
                );
            }
        }
    }
}

#[test]
fn an_image_without_dots_changes_no_flow() {
    let plain = Array2::from_elem((120, 160), 128.0f32);
    let mut t = DotTracker::new();
    assert_eq!(t.set_reference(&plain, 22.0).unwrap(), 0);
    assert!(!t.is_active());
    let before = flow_of(160, 120, 2, &|p| [p[0] * 0.01, 0.3], [0.0, 0.0]);
    let mut flow = before.clone();
    t.refine(&plain, &mut flow, 2).unwrap();
    assert_eq!(flow, before);
}

#[test]
fn dots_that_vanish_are_lost_and_leave_the_flow_alone() {
    let truth = grid(160, 120, 22.0, 11.3, 10.7);
    let reference = render(160, 120, &truth, 3.5, true, 1.0, 2);
    let mut t = DotTracker::new();
    assert!(t.set_reference(&reference, 22.0).unwrap() > 10);
    let blank = Array2::from_elem((120, 160), 180.0f32);
    let before = flow_of(160, 120, 2, &|_| [0.7, -0.2], [0.0, 0.0]);
    let mut flow = before.clone();
    t.refine(&blank, &mut flow, 2).unwrap();
    assert!(t.displacements().iter().all(Option::is_none));
    assert_eq!(flow, before);
}

#[test]
fn a_lost_dot_is_found_only_in_the_region_that_holds_it() {
    let truth = grid(160, 120, 22.0, 11.3, 10.7);
    let reference = render(160, 120, &truth, 3.5, true, 1.0, 2);
    let mut t = DotTracker::new();
    let whole = Roi::new(0, 0, 160, 120);
    assert!(!t.lost_in(whole), "no reference, nothing lost");
    assert!(t.set_reference(&reference, 22.0).unwrap() > 10);
    // Every dot followed: nothing lost anywhere.
    let same = flow_of(160, 120, 2, &|_| [0.0, 0.0], [0.0, 0.0]);
    let mut flow = same.clone();
    t.refine(&reference, &mut flow, 2).unwrap();
    assert!(t.displacements().iter().all(Option::is_some));
    assert!(!t.lost_in(whole));
    // One dot blotted out of the frame: lost, and only a region holding
    // its reference centre says so.
    let (k, _) = nearest(t.dots(), [77.0, 54.0]);
    let gone = t.dots()[k];
    let mut frame = reference.clone();
    for ((i, j), v) in frame.indexed_iter_mut() {
        if (j as f64 - gone[0]).hypot(i as f64 - gone[1]) < 8.0 {
            *v = 180.0;
        }
    }
    let mut flow = same.clone();
    t.refine(&frame, &mut flow, 2).unwrap();
    let lost: Vec<usize> = (0..t.dots().len())
        .filter(|&i| t.displacements()[i].is_none())
        .collect();
    assert_eq!(lost, vec![k], "only the blotted dot is lost");
    let (x, y) = (gone[0] as usize, gone[1] as usize);
    assert!(t.lost_in(whole));
    assert!(t.lost_in(Roi::new(x - 5, y - 5, 11, 11)));
    assert!(
        !t.lost_in(Roi::new(x + 6, y - 5, 20, 11)),
        "a region beside it"
    );
    assert!(
        !t.lost_in(Roi::new(x - 5, y + 6, 11, 20)),
        "a region below it"
    );
    assert!(!t.lost_in(Roi::new(x, y, 0, 0)), "an empty region");
}

#[test]
fn bad_input_is_an_error() {
    let truth = grid(160, 120, 22.0, 11.3, 10.7);
    let reference = render(160, 120, &truth, 3.5, true, 1.0, 2);
    let mut t = DotTracker::new();
    for pitch in [f64::NAN, 0.0, 3.0, 1e9, f64::INFINITY] {
        assert!(t.set_reference(&reference, pitch).is_err(), "pitch {pitch}");
        assert!(!t.is_active());
    }
    let mut bad = reference.clone();
    bad[[5, 5]] = f32::NAN;
    assert!(t.set_reference(&bad, 22.0).is_err());
    t.set_reference(&reference, 22.0).unwrap();
    let mut flow = flow_of(160, 120, 2, &|_| [0.0, 0.0], [0.0, 0.0]);
    let small = Array2::from_elem((60, 80), 180.0f32);
    assert!(t.refine(&small, &mut flow, 2).is_err());
    let mut short = flow_of(80, 60, 1, &|_| [0.0, 0.0], [0.0, 0.0]);
    assert!(t.refine(&reference, &mut short, 1).is_err());
    // A tiny image has no dots, and no error.
    let tiny = Array2::from_elem((2, 2), 10.0f32);
    assert_eq!(t.set_reference(&tiny, 22.0).unwrap(), 0);
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 24,
        rng_seed: RngSeed::Fixed(0x0D07_5EED),
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    /// A grid shifted as a whole is followed to a few hundredths of a
    /// pixel, from a flow off by up to 1.5 px.
    #[test]
    fn a_shifted_grid_is_followed(
        dx in -4.0f64..4.0, dy in -4.0f64..4.0,
        ex in -1.5f64..1.5, ey in -1.5f64..1.5,
        ox in 8.0f64..14.0, oy in 8.0f64..14.0,
        seed in 0u64..1000,
    ) {
        let truth = grid(160, 120, 22.0, ox, oy);
        let reference = render(160, 120, &truth, 3.5, true, 1.5, seed);
        let moved: Vec<[f64; 2]> = truth.iter().map(|c| [c[0] + dx, c[1] + dy]).collect();
        let frame = render(160, 120, &moved, 3.5, true, 1.5, seed + 1);
        let mut t = DotTracker::new();
        t.set_reference(&reference, 22.0).unwrap();
        let mut flow = flow_of(160, 120, 2, &|_| [dx, dy], [ex, ey]);
        t.refine(&frame, &mut flow, 2).unwrap();
        let got: Vec<[f64; 2]> = t.displacements().iter().flatten().copied().collect();
        prop_assert!(got.len() as f64 >= 0.8 * t.dots().len() as f64);
        let mean = got.iter().map(|d| (d[0] - dx).hypot(d[1] - dy)).sum::<f64>() / got.len() as f64;
        prop_assert!(mean < 0.05, "mean error {} px", mean);
    }
}

/// `image` with its light scaled by `1 + amp * g` about `(x0, y0)`, `g` a
/// Gaussian of `width` px (negative `amp`: darker), or by `1 + amp * g *
/// (x - x0) / width` with `dipole` (a gel lit from one side, its slopes
/// brighter on one side of a contact and darker on the other).
fn shaded(
    image: &Array2<f32>,
    amp: f64,
    (x0, y0): (f64, f64),
    width: f64,
    dipole: bool,
) -> Array2<f32> {
    Array2::from_shape_fn(image.dim(), |(i, j)| {
        let (dx, dy) = (j as f64 - x0, i as f64 - y0);
        let mut g = (-(dx * dx + dy * dy) / (2.0 * width * width)).exp();
        if dipole {
            g *= dx / width;
        }
        (f64::from(image[[i, j]]) * (1.0 + amp * g)).clamp(0.0, 255.0) as f32
    })
}

/// The gel under a contact turns darker or brighter in the frame (its
/// shading under the camera's lights, or an object seen through a thin
/// gel) while the reference stays as it was: the dots are still followed
/// to their own centres, their contrast read against the frame's own
/// light. Against the reference's light the plain gel about a darkened
/// dot would weigh as part of it.
#[test]
fn dots_under_a_darker_or_brighter_contact_are_followed() {
    let (w, h, pitch) = (320, 240, 22.0);
    // Dark dots' contrast is read relative to the local light, bright
    // dots' in grey levels: the light's slope across a bright dot still
    // weighs one side of it more (0.02-0.05 px; against the reference's
    // light 0.03-0.085 px, and 0.03-0.20 px for dark dots).
    for (dark, seed, tolerance) in [(true, 31, (0.025, 0.05)), (false, 32, (0.06, 0.1))] {
        let truth = grid(w, h, pitch, 11.3, 10.7);
        let reference = render(w, h, &truth, 3.5, dark, 1.0, seed);
        let field = bump(7.0, 150.0, 110.0, 25.0);
        let moved = displaced(&truth, &field);
        let frame = render(w, h, &moved, 3.5, dark, 1.0, seed + 10);
        for (amp, dipole) in [(-0.4, false), (0.3, false), (0.35, true)] {
            let lit = shaded(&frame, amp, (150.0, 110.0), 30.0, dipole);
            let mut t = DotTracker::new();
            t.set_reference(&reference, pitch).unwrap();
            let mut flow = flow_of(w, h, 2, &field, [0.6, -0.4]);
            t.refine(&lit, &mut flow, 2).unwrap();
            let mut errors = Vec::new();
            for (&c, d) in t.dots().iter().zip(t.displacements()) {
                // The dots the light changed by a tenth or more.
                if (c[0] - 150.0).hypot(c[1] - 110.0) > 45.0 {
                    continue;
                }
                let d = d.expect("every dot followed");
                let (k, _) = nearest(&truth, c);
                errors.push(dist(d, field(truth[k])));
            }
            let mean = errors.iter().sum::<f64>() / errors.len() as f64;
            let worst = errors.iter().copied().fold(0.0, f64::max);
            assert!(
                errors.len() >= 12,
                "{} dots in the light's reach",
                errors.len()
            );
            assert!(
                mean < tolerance.0 && worst < tolerance.1,
                "dark {dark}, light x(1 {amp:+}{}): mean {mean}, worst {worst} px over {} dots",
                if dipole { " dipole" } else { "" },
                errors.len()
            );
        }
    }
}
