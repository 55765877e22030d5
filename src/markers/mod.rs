//! The marker pattern of a reference frame: the pitch of a regular grid,
//! its dots followed one by one ([`DotTracker`]), and a contact's point
//! where the lines along the followed dots' motion meet ([`centre`]).
//!
//! A regular grid of markers (the dark dots of a GelSight-class sensor) is
//! periodic: seen against one unloaded reference, a dot that moved by a
//! whole pitch looks exactly like its neighbour that did not move, and once
//! neighbouring dots move by half the pitch or more relative to each other,
//! no flow can tell which dot went where. [`grid_pitch`] measures the pitch
//! so that the sensor can mark such motion ([`crate::Contact::out_of_domain`]).
//! A random marker pattern has no pitch: its autocorrelation has no second
//! peak, and [`grid_pitch`] returns `None`.
//!
//! Method: the autocorrelation of the mean-removed image (by FFT, on a
//! central window of at most [`MAX_WINDOW_PX`] a side, zero-padded so that
//! nothing wraps around), normalised by its value at zero shift. Past the
//! central peak (the first shift along either axis where it stops falling
//! or reaches the image's mean), the peaks within a third of the window that
//! reach [`PEAK_FRACTION`] of the highest are lattice vectors, and the
//! shortest one's length is the pitch, when the highest reaches
//! [`MIN_GRID_CORRELATION`] and the correlation falls below half that
//! vector's half-way to it and half a pitch across it (dots apart along two
//! directions, not lines or a band). A grid too coarse for the window (a
//! high-resolution camera's, whose pitch can be 60-200 px) is looked for
//! again on the image averaged over boxes of 2 x 2 pixels, then 4 x 4 (as
//! the flow's pyramid levels are), up to [`MAX_PITCH_SCALE`] times smaller,
//! while the window does not yet cover the whole image.

use ndarray::ArrayRef2;

pub mod centre;
pub mod dots;
pub mod round;
pub use dots::DotTracker;
use rustfft::FftPlanner;
use rustfft::num_complex::Complex64;

/// Largest side, in pixels, of the central window the pitch is measured on:
/// the pattern repeats, so a window of many pitches says as much as the
/// whole frame, at a bounded cost.
pub const MAX_WINDOW_PX: usize = 160;

/// Smallest normalised autocorrelation of the highest lattice peak for the
/// pattern to count as a regular grid. Regular grids score about 0.5-0.9,
/// less with noise, vignetting or dots off their lattice places: on the
/// simulated fingertip sensor 0.27-0.39 with dots moved by up to a fifth
/// of the pitch (`--jitter-px 4` or `5` at 22-30 px). Random markers stay
/// below 0.15 (the fingertip sensor's 0.11-0.13, the strip's 0.07).
pub const MIN_GRID_CORRELATION: f64 = 0.25;

/// A peak of the autocorrelation counts as a lattice vector when it reaches
/// this fraction of the highest peak; the pitch is the shortest of them.
///
/// Why a half: on a grid whose dots sit off their lattice places (hand-made
/// or printed markers; the simulator's `--jitter-px`), the nearest lattice
/// vector correlates less than the longer ones. On the simulated fingertip
/// sensor's references (22 px pitch) it reached 0.94 of the highest peak
/// with 1 px of jitter, 0.85 with 2 px, 0.72 with 3 px and 0.58 with 4 px,
/// where the highest was a vector of 49 px (two pitches along one axis, one
/// along the other); at 85% the pitch read 31 px (the diagonal) from 2 px
/// of jitter on and 49 px from 4 px, and the dots were then followed with
/// the wrong pitch (held-out forces 2-8 times worse). Between lattice
/// vectors a grid's dots do not overlap, so no other peak comes near half.
pub const PEAK_FRACTION: f64 = 0.5;

/// Smallest window side, in pixels, on which a pitch is looked for.
const MIN_WINDOW_PX: usize = 16;

/// Coarsest scale [`grid_pitch`] looks at: the image halved twice, where
/// its window spans 640 px of the image and pitches up to 213 px are found.
pub const MAX_PITCH_SCALE: usize = 4;

/// The pitch, in pixels, of a regular grid of markers in `reference`, or
/// `None` when the image shows no regular grid (random markers, a plain
/// image, a window smaller than 16 px, non-finite pixels). The shortest
/// lattice vector's length, to the nearest pixel of shift at the scale it
/// was found at. A pitch above a third of the window (53 px) is looked for
/// on the image halved, then halved again ([`MAX_PITCH_SCALE`]), as long as
/// the window did not cover the whole image: up to 213 px on an image of at
/// least 640 px a side.
pub fn grid_pitch(reference: &ArrayRef2<f32>) -> Option<f64> {
    let (h, w) = reference.dim();
    let mut scale = 1;
    loop {
        let found = if scale == 1 {
            pitch_in_window(reference.view())
        } else {
            pitch_in_window(box_averaged(reference, scale)?.view())
        };
        if let Some(p) = found {
            return Some(p * scale as f64);
        }
        // The window held the whole image: a coarser scale finds nothing new.
        let (sh, sw) = (h / scale, w / scale);
        if scale >= MAX_PITCH_SCALE || (sh <= MAX_WINDOW_PX && sw <= MAX_WINDOW_PX) {
            return None;
        }
        scale *= 2;
    }
}

/// `reference` averaged over boxes of `factor x factor` pixels (trailing
/// rows and columns dropped), as the flow's pyramid levels are.
fn box_averaged(reference: &ArrayRef2<f32>, factor: usize) -> Option<ndarray::Array2<f32>> {
    let src = reference.as_standard_layout();
    let (h, w) = src.dim();
    let mut dst = ndarray::Array2::zeros((h / factor, w / factor));
    crate::flow::pyramid::downsample_area(src.as_slice()?, w, h, factor, dst.as_slice_mut()?)
        .ok()?;
    Some(dst)
}

/// [`grid_pitch`] at one scale: on the central window of `reference`.
fn pitch_in_window(reference: ndarray::ArrayView2<'_, f32>) -> Option<f64> {
    let (h, w) = reference.dim();
    let (wh, ww) = (h.min(MAX_WINDOW_PX), w.min(MAX_WINDOW_PX));
    if wh < MIN_WINDOW_PX || ww < MIN_WINDOW_PX {
        return None;
    }
    let (y0, x0) = ((h - wh) / 2, (w - ww) / 2);
    let window = reference.slice(ndarray::s![y0..y0 + wh, x0..x0 + ww]);
    if window.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let (ph, pw) = (2 * wh, 2 * ww);
    let buf = raw_autocorrelation(window);
    let zero = buf[0];
    if !(zero > 0.0 && zero.is_finite()) {
        return None; // a plain image
    }
    // Normalised by the number of overlapping pixels at each shift, so
    // that long shifts (few pixels overlap) are not penalised.
    let at = |dy: isize, dx: isize| -> f64 {
        let (iy, ix) = (
            dy.rem_euclid(ph as isize) as usize,
            dx.rem_euclid(pw as isize) as usize,
        );
        let overlap = (wh - dy.unsigned_abs()) * (ww - dx.unsigned_abs());
        buf[iy * pw + ix] / zero * (wh * ww) as f64 / overlap as f64
    };
    let reach = (wh.min(ww) / 3) as isize;
    // The central peak's radius: the first shift along each axis where the
    // correlation stops falling or has fallen to the image's mean (past a
    // dot's own footprint; between the dots of a turned grid it can go on
    // falling slowly beyond the pitch).
    let fall = |step: (isize, isize)| -> isize {
        let mut k = 1;
        while k < reach
            && at(k * step.0, k * step.1) > 0.0
            && at(k * step.0, k * step.1) > at((k + 1) * step.0, (k + 1) * step.1)
        {
            k += 1;
        }
        k
    };
    let r0 = fall((0, 1)).max(fall((1, 0)));
    // Every lattice vector correlates about as well as the shortest (a
    // perfect grid: all equally), so the pitch is the shortest peak whose
    // correlation reaches [`PEAK_FRACTION`] of the highest.
    let mut shifts = Vec::new();
    // Half the shifts suffice (the correlation is symmetric): dy >= 0.
    for dy in 0..=reach {
        for dx in -reach..=reach {
            let d = ((dy * dy + dx * dx) as f64).sqrt();
            if d <= r0 as f64 || d > reach as f64 {
                continue;
            }
            // Only the peaks: a broad peak's inner slope can reach that
            // share of the highest value at a shorter shift than the peak's.
            let c = at(dy, dx);
            let peak = (-1..=1)
                .flat_map(|a| (-1..=1).map(move |b| (a, b)))
                .filter(|&o| o != (0, 0))
                .all(|(a, b)| at(dy + a, dx + b) <= c);
            if peak {
                shifts.push((d, c, dy as f64, dx as f64));
            }
        }
    }
    let best = shifts.iter().map(|s| s.1).fold(f64::NEG_INFINITY, f64::max);
    if best < MIN_GRID_CORRELATION {
        return None;
    }
    let &(pitch, c, dy, dx) = shifts
        .iter()
        .filter(|s| s.1 >= PEAK_FRACTION * best)
        .min_by(|a, b| a.0.total_cmp(&b.0))?;
    // Dots are apart along two directions: half-way to the pitch's vector,
    // and half a pitch across it on either side, the correlation falls
    // below half the peak's (there the shifted grid's dots lie between the
    // grid's). Along lines or a band (a camera's scan lines, a strip of
    // markers across a dark frame) it stays high one way or the other.
    let at_f = |y: f64, x: f64| at(y.round() as isize, x.round() as isize);
    let gaps = [
        at_f(0.5 * dy, 0.5 * dx),
        at_f(dy + 0.5 * dx, dx - 0.5 * dy),
        at_f(dy - 0.5 * dx, dx + 0.5 * dy),
    ];
    gaps.iter().all(|&g| g < PEAK_FRACTION * c).then_some(pitch)
}

/// The autocorrelation of the mean-removed `window` (`h x w`), unnormalised:
/// `sum over (i, j) of a(i, j) a(i + dy, j + dx)` with `a` the window minus
/// its mean and zero outside, at index `(dy mod 2h) * 2w + (dx mod 2w)`. By
/// FFT of the window zero-padded to `2h x 2w`, so that no shift wraps round.
fn raw_autocorrelation(window: ndarray::ArrayView2<'_, f32>) -> Vec<f64> {
    let (wh, ww) = window.dim();
    let mean = window.iter().map(|&v| f64::from(v)).sum::<f64>() / (wh * ww) as f64;
    let (ph, pw) = (2 * wh, 2 * ww);
    let mut buf = vec![Complex64::new(0.0, 0.0); ph * pw];
    for (i, row) in window.rows().into_iter().enumerate() {
        for (j, &v) in row.iter().enumerate() {
            buf[i * pw + j].re = f64::from(v) - mean;
        }
    }
    let mut planner = FftPlanner::<f64>::new();
    fft2(&mut buf, ph, pw, &mut planner, false);
    for z in &mut buf {
        *z = Complex64::new(z.norm_sqr(), 0.0);
    }
    fft2(&mut buf, ph, pw, &mut planner, true);
    let n = (ph * pw) as f64;
    buf.iter().map(|z| z.re / n).collect()
}

/// In-place 2-D FFT of a row-major `h x w` buffer (forward, or inverse
/// without the `1 / (h w)` scale).
fn fft2(buf: &mut [Complex64], h: usize, w: usize, planner: &mut FftPlanner<f64>, inverse: bool) {
    let plan = |n: usize, planner: &mut FftPlanner<f64>| {
        if inverse {
            planner.plan_fft_inverse(n)
        } else {
            planner.plan_fft_forward(n)
        }
    };
    let rows = plan(w, planner);
    for row in buf.chunks_exact_mut(w) {
        rows.process(row);
    }
    let cols = plan(h, planner);
    let mut col = vec![Complex64::new(0.0, 0.0); h];
    for j in 0..w {
        for (i, c) in col.iter_mut().enumerate() {
            *c = buf[i * w + j];
        }
        cols.process(&mut col);
        for (i, c) in col.iter().enumerate() {
            buf[i * w + j] = *c;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    /// A lattice of round dots to paint: `pitch` px apart along two lattice
    /// vectors at `angle` (radians) and `angle + gamma`, dots of `radius`
    /// px, `dark` dots on a bright background or bright on dark, each dot
    /// moved off its lattice place by up to `jitter` px along each axis (a
    /// hash of its lattice index and `seed`).
    #[derive(Clone, Copy)]
    struct Dots {
        pitch: f64,
        angle: f64,
        gamma: f64,
        radius: f64,
        dark: bool,
        jitter: f64,
        seed: u64,
    }

    impl Dots {
        /// Dark dots of `radius` on a square lattice turned by `angle`, on
        /// their places.
        fn square(pitch: f64, angle: f64, radius: f64) -> Self {
            Dots {
                pitch,
                angle,
                gamma: std::f64::consts::FRAC_PI_2,
                radius,
                dark: true,
                jitter: 0.0,
                seed: 0,
            }
        }

        /// The offset of lattice dot `(k, l)` along `axis` (0: x, 1: y).
        fn offset(&self, k: i64, l: i64, axis: u64) -> f64 {
            let mut z = (k as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ (l as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
                ^ self
                    .seed
                    .wrapping_add(axis)
                    .wrapping_mul(0x1656_67B1_9E37_79F9);
            z ^= z >> 31;
            z = z.wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z ^= z >> 29;
            self.jitter * (2.0 * (z >> 11) as f64 / (1u64 << 53) as f64 - 1.0)
        }

        /// A `w` x `h` image of the dots.
        fn paint(&self, w: usize, h: usize) -> Array2<f32> {
            let (p, a, g) = (self.pitch, self.angle, self.angle + self.gamma);
            let (ax, ay, bx, by) = (p * a.cos(), p * a.sin(), p * g.cos(), p * g.sin());
            let det = ax * by - ay * bx;
            Array2::from_shape_fn((h, w), |(i, j)| {
                let (x, y) = (j as f64 + 0.3, i as f64 + 0.7);
                // Lattice coordinates, then the nearest dot among the
                // lattice points about them.
                let s = ((x * by - y * bx) / det).round() as i64;
                let t = ((ax * y - ay * x) / det).round() as i64;
                let mut near = f64::INFINITY;
                for k in s - 1..=s + 1 {
                    for l in t - 1..=t + 1 {
                        let (kf, lf) = (k as f64, l as f64);
                        let px = kf * ax + lf * bx + self.offset(k, l, 0);
                        let py = kf * ay + lf * by + self.offset(k, l, 1);
                        near = near.min((x - px).hypot(y - py));
                    }
                }
                let on = near < self.radius;
                (if on == self.dark { 40.0 } else { 200.0 }) as f32
            })
        }
    }

    #[test]
    fn square_and_hexagonal_grids_give_their_pitch() {
        use std::f64::consts::FRAC_PI_2;
        for (pitch, angle, gamma, dark) in [
            (22.0, 0.0, FRAC_PI_2, true),
            (30.0, 0.3, FRAC_PI_2, true),
            (14.0, 0.0, FRAC_PI_2, false),
            (25.0, 0.1, std::f64::consts::PI / 3.0, true),
        ] {
            let dots = Dots {
                gamma,
                dark,
                ..Dots::square(pitch, angle, 3.5)
            };
            let img = dots.paint(320, 240);
            let p = grid_pitch(&img).expect("a grid");
            assert!((p - pitch).abs() <= 1.0, "pitch {pitch}: measured {p}");
        }
    }

    #[test]
    fn the_fft_autocorrelation_matches_the_direct_sum() {
        let mut state = 7_u64;
        let img = Array2::from_shape_fn((19, 23), |_| {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
            (state >> 40) as f32
        });
        let (h, w) = img.dim();
        let mean = img.iter().map(|&v| f64::from(v)).sum::<f64>() / (h * w) as f64;
        let a = |i: isize, j: isize| -> f64 {
            if (0..h as isize).contains(&i) && (0..w as isize).contains(&j) {
                f64::from(img[[i as usize, j as usize]]) - mean
            } else {
                0.0
            }
        };
        let fast = raw_autocorrelation(img.view());
        for (dy, dx) in [
            (0, 0),
            (0, 1),
            (1, 0),
            (3, -5),
            (-7, 2),
            (18, 22),
            (-18, -22),
        ] {
            let mut direct = 0.0;
            for i in 0..h as isize {
                for j in 0..w as isize {
                    direct += a(i, j) * a(i + dy, j + dx);
                }
            }
            let (iy, ix) = (
                dy.rem_euclid(2 * h as isize) as usize,
                dx.rem_euclid(2 * w as isize) as usize,
            );
            let f = fast[iy * 2 * w + ix];
            assert!(
                (f - direct).abs() <= 1e-6 * direct.abs().max(1.0),
                "({dy}, {dx}): {f} vs {direct}"
            );
        }
    }

    #[test]
    fn random_markers_and_plain_images_have_no_pitch() {
        let mut state = 0x1234_5678_u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as f64 / (1u64 << 31) as f64
        };
        let mut img = Array2::<f32>::from_elem((240, 320), 30.0);
        for _ in 0..900 {
            let (cx, cy) = (next() * 320.0, next() * 240.0);
            for i in 0..240 {
                for j in 0..320 {
                    if (j as f64 - cx).powi(2) + (i as f64 - cy).powi(2) < 4.0 {
                        img[[i, j]] = 220.0;
                    }
                }
            }
        }
        assert_eq!(grid_pitch(&img), None);
        assert_eq!(grid_pitch(&Array2::from_elem((240, 320), 80.0)), None);
        assert_eq!(grid_pitch(&Array2::from_elem((8, 320), 80.0)), None);
        let mut bad = Dots::square(16.0, 0.0, 3.0).paint(64, 64);
        bad[[3, 3]] = f32::NAN;
        assert_eq!(grid_pitch(&bad), None);
    }

    #[test]
    fn a_turned_grid_gives_its_pitch_not_its_diagonal() {
        // Turned by 55 deg, dots a little off their places: along the image
        // axes the correlation went on falling past the pitch, which hid the
        // nearest lattice peaks and read the diagonal (29.4 px).
        // (A case the jittered property found.)
        let pitch = 20.608_353_486_920_358;
        let dots = Dots {
            jitter: 0.045_881_541_743_247_226 * pitch,
            seed: 752,
            ..Dots::square(pitch, 0.953_183_667_662_742_1, pitch / 6.0)
        };
        let p = grid_pitch(&dots.paint(320, 240)).expect("a grid");
        assert!((p - pitch).abs() <= 1.5, "measured {p}");
    }

    #[test]
    fn coarse_grids_are_found_on_the_image_halved() {
        // A high-resolution camera's grid: too coarse for the window at
        // full scale, found halved (within the halved image's pixel).
        for (pitch, w, h, scale) in [
            (84.0, 1280, 720, 2.0),
            (60.0, 320, 240, 2.0),
            (150.0, 1920, 1080, 4.0),
        ] {
            let img = Dots::square(pitch, 0.2, pitch / 5.0).paint(w, h);
            let p = grid_pitch(&img).expect("a grid");
            assert!((p - pitch).abs() <= scale, "pitch {pitch} on {w}x{h}: {p}");
        }
        // Beyond the coarsest scale, or on an image the window already
        // covered: no pitch rather than a wrong one.
        assert_eq!(
            grid_pitch(&Dots::square(90.0, 0.0, 18.0).paint(150, 150)),
            None
        );
    }

    #[test]
    fn random_markers_have_no_pitch_at_any_scale() {
        // Large frames of random markers of 2-8 px: no scale shows a grid.
        for (radius, count, seed) in [(2.0, 6000, 1_u64), (5.0, 1500, 2), (8.0, 600, 3)] {
            let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15);
            let mut next = || {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 33) as f64 / (1u64 << 31) as f64
            };
            let (w, h) = (1280usize, 720usize);
            let mut img = Array2::<f32>::from_elem((h, w), 30.0);
            let r = radius as isize;
            for _ in 0..count {
                let (cx, cy) = (next() * w as f64, next() * h as f64);
                let (i0, j0) = (cy as isize, cx as isize);
                for i in (i0 - r).max(0)..(i0 + r + 1).min(h as isize) {
                    for j in (j0 - r).max(0)..(j0 + r + 1).min(w as isize) {
                        if (j as f64 - cx).powi(2) + (i as f64 - cy).powi(2) < radius * radius {
                            img[[i as usize, j as usize]] = 220.0;
                        }
                    }
                }
            }
            assert_eq!(grid_pitch(&img), None, "markers of {radius} px");
        }
    }

    #[test]
    fn lines_and_bands_are_no_grid() {
        // A camera's scan lines: periodic along y only.
        let lines = Array2::from_shape_fn(
            (480, 640),
            |(i, _)| {
                if i % 6 < 2 { 90.0_f32 } else { 120.0 }
            },
        );
        assert_eq!(grid_pitch(&lines), None);
        // A strip of random markers across a dark full-HD frame (the
        // simulator's full-frame view): halved, the strip is a uniform band.
        let mut state = 99_u64;
        let mut band = Array2::<f32>::from_elem((1080, 1920), 5.0);
        for i in 440..640 {
            for j in 190..1730 {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                band[[i, j]] = if state >> 62 == 0 { 230.0 } else { 40.0 };
            }
        }
        assert_eq!(grid_pitch(&band), None);
    }

    proptest::proptest! {
        #![proptest_config(proptest::test_runner::Config {
            cases: 32,
            rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
            rng_seed: proptest::test_runner::RngSeed::Fixed(11),
            failure_persistence: None,
            ..Default::default()
        })]

        /// Square grids of any pitch a sensor uses, turned by any angle,
        /// with dots of a fifth to a third of the pitch, either polarity,
        /// on frames of various sizes: the pitch within a pixel.
        #[test]
        fn any_square_grid_gives_its_pitch(
            pitch in 10.0f64..45.0,
            angle in 0.0f64..std::f64::consts::FRAC_PI_2,
            dot in 0.2f64..0.33,
            dark in proptest::bool::ANY,
            w in 200usize..400,
            h in 150usize..300,
        ) {
            let img = Dots { dark, ..Dots::square(pitch, angle, dot * pitch) }.paint(w, h);
            let p = grid_pitch(&img);
            proptest::prop_assert!(p.is_some_and(|p| (p - pitch).abs() <= 1.0), "pitch {pitch}: {p:?}");
        }

        /// Square grids whose dots sit off their lattice places by up to a
        /// sixth of the pitch along each axis (dots of a third of it, so
        /// neighbours never touch), turned by any angle: the pitch, not a
        /// diagonal (41% longer) or a longer lattice vector. Within 1.5 px
        /// or 12% of the pitch: with a few dozen dots in the window, each
        /// moved off its place, the lattice peak itself moves (over 2000
        /// such grids the pitch read at most 3.6% off with up to a twelfth
        /// of the pitch of jitter, at most 10.5% off with up to a sixth).
        #[test]
        fn jittered_grids_give_their_pitch(
            pitch in 16.0f64..40.0,
            angle in 0.0f64..std::f64::consts::FRAC_PI_2,
            jitter in 0.0f64..(1.0 / 6.0),
            seed in 0u64..1000,
        ) {
            let dots = Dots { jitter: jitter * pitch, seed, ..Dots::square(pitch, angle, pitch / 6.0) };
            let img = dots.paint(320, 240);
            let p = grid_pitch(&img);
            let tolerance = (0.12 * pitch).max(1.5);
            proptest::prop_assert!(p.is_some_and(|p| (p - pitch).abs() <= tolerance), "pitch {pitch}, jitter {}: {p:?}", jitter * pitch);
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::test_runner::Config {
            cases: 12,
            rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
            rng_seed: proptest::test_runner::RngSeed::Fixed(12),
            failure_persistence: None,
            ..Default::default()
        })]

        /// Square grids coarser than the full-scale window reaches (54 to
        /// 200 px), turned by any angle, dots of a fifth to a third of the
        /// pitch, either polarity, on frames a high-resolution camera
        /// gives: the pitch within the pixel of the scale that can see it
        /// (2 px when halved once, 4 px twice).
        #[test]
        fn any_coarse_grid_gives_its_pitch(
            pitch in 54.0f64..200.0,
            angle in 0.0f64..std::f64::consts::FRAC_PI_2,
            dot in 0.2f64..0.33,
            dark in proptest::bool::ANY,
            wide in proptest::bool::ANY,
        ) {
            let (w, h) = if wide || pitch > 120.0 { (1280, 720) } else { (640, 480) };
            let img = Dots { dark, ..Dots::square(pitch, angle, dot * pitch) }.paint(w, h);
            let p = grid_pitch(&img);
            let tolerance = if pitch <= 106.0 { 2.0 } else { 4.0 };
            proptest::prop_assert!(p.is_some_and(|p| (p - pitch).abs() <= tolerance), "pitch {pitch} on {w}x{h}: {p:?}");
        }
    }
}
