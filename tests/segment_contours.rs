//! External contours against a flood-fill oracle: each contour's box equals
//! the box of one 8-connected component with its holes filled.

use ndarray::Array2;
use optical_tactile::segment::contours::{BoundingBox, ContourFinder};
use optical_tactile::segment::morphology::Mask;
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};

/// Boxes of the hole-filled 8-connected components, ordered by each
/// component's first pixel in raster order.
fn oracle(m: &Array2<u8>) -> Vec<BoundingBox> {
    let (h, w) = m.dim();
    // Background 4-connected to the outside of the image.
    let mut outside = Array2::<bool>::from_elem((h, w), false);
    let mut stack = Vec::new();
    for y in 0..h {
        for x in 0..w {
            if (x == 0 || y == 0 || x == w - 1 || y == h - 1) && m[[y, x]] == 0 {
                outside[[y, x]] = true;
                stack.push((x, y));
            }
        }
    }
    while let Some((x, y)) = stack.pop() {
        for (dx, dy) in [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)] {
            let (xx, yy) = (x as i64 + dx, y as i64 + dy);
            if xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                continue;
            }
            let (xx, yy) = (xx as usize, yy as usize);
            if m[[yy, xx]] == 0 && !outside[[yy, xx]] {
                outside[[yy, xx]] = true;
                stack.push((xx, yy));
            }
        }
    }
    // 8-connected components of everything not outside.
    let mut seen = Array2::<bool>::from_elem((h, w), false);
    let mut boxes = Vec::new();
    for y in 0..h {
        for x in 0..w {
            if outside[[y, x]] || seen[[y, x]] {
                continue;
            }
            let (mut x0, mut y0, mut x1, mut y1) = (x, y, x, y);
            seen[[y, x]] = true;
            stack.push((x, y));
            while let Some((cx, cy)) = stack.pop() {
                x0 = x0.min(cx);
                x1 = x1.max(cx);
                y0 = y0.min(cy);
                y1 = y1.max(cy);
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let (xx, yy) = (cx as i64 + dx, cy as i64 + dy);
                        if xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                            continue;
                        }
                        let (xx, yy) = (xx as usize, yy as usize);
                        if !outside[[yy, xx]] && !seen[[yy, xx]] {
                            seen[[yy, xx]] = true;
                            stack.push((xx, yy));
                        }
                    }
                }
            }
            boxes.push(BoundingBox::new(x0, y0, x1 - x0 + 1, y1 - y0 + 1));
        }
    }
    boxes
}

fn masks() -> impl Strategy<Value = Array2<u8>> {
    (1usize..140, 1usize..40, 0u32..=100).prop_flat_map(|(w, h, density)| {
        proptest::collection::vec(0u32..100, w * h).prop_map(move |v| {
            Array2::from_shape_vec((h, w), v.into_iter().map(|r| (r < density) as u8).collect())
                .unwrap()
        })
    })
}

/// Masks of a few filled rectangles and rectangular rings (holes, nesting).
fn shapes() -> impl Strategy<Value = Array2<u8>> {
    (
        10usize..130,
        10usize..60,
        proptest::collection::vec(
            (
                0usize..130,
                0usize..60,
                1usize..40,
                1usize..30,
                any::<bool>(),
            ),
            1..12,
        ),
    )
        .prop_map(|(w, h, rects)| {
            let mut m = Array2::<u8>::zeros((h, w));
            for (x, y, rw, rh, ring) in rects {
                for yy in y..(y + rh).min(h) {
                    for xx in x..(x + rw).min(w) {
                        let border = yy == y || xx == x || yy + 1 == y + rh || xx + 1 == x + rw;
                        // Rings toggle so that rings inside rings make islands in holes.
                        m[[yy, xx]] = (!ring || border) as u8;
                    }
                }
            }
            m
        })
}

fn runner(cases: u32) -> TestRunner {
    TestRunner::new_with_rng(
        Config {
            cases,
            failure_persistence: None,
            ..Config::default()
        },
        TestRng::from_seed(RngAlgorithm::ChaCha, &[11u8; 32]),
    )
}

fn check(finder: &mut ContourFinder, m: &Array2<u8>) -> Result<(), TestCaseError> {
    let mk = Mask::from_array(m);
    let mut boxes = Vec::new();
    finder.external_boxes(&mk, &mut boxes);
    prop_assert_eq!(&boxes, &oracle(m));
    // Points: on the mask, consecutive ones 8-adjacent, box = their box.
    for c in finder.external_contours(&mk) {
        prop_assert!(c.points.iter().all(|&(x, y)| mk.get(x, y)));
        for pair in c.points.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            prop_assert!(a.0.abs_diff(b.0) <= 1 && a.1.abs_diff(b.1) <= 1);
        }
        let x0 = c.points.iter().map(|p| p.0).min().unwrap();
        let y0 = c.points.iter().map(|p| p.1).min().unwrap();
        prop_assert_eq!((c.bbox.x, c.bbox.y), (x0, y0));
    }
    Ok(())
}

#[test]
fn random_masks_match_flood_fill() {
    let finder = std::cell::RefCell::new(ContourFinder::new());
    runner(400)
        .run(&masks(), |m| check(&mut finder.borrow_mut(), &m))
        .unwrap();
}

#[test]
fn nested_rings_and_rectangles_match_flood_fill() {
    let finder = std::cell::RefCell::new(ContourFinder::new());
    runner(400)
        .run(&shapes(), |m| check(&mut finder.borrow_mut(), &m))
        .unwrap();
}

#[test]
fn touching_the_border_and_one_pixel_masks() {
    let mut f = ContourFinder::new();
    let mut out = Vec::new();
    let full = Mask::new(70, 5).not();
    f.external_boxes(&full, &mut out);
    assert_eq!(out, vec![BoundingBox::new(0, 0, 70, 5)]);
    let mut one = Mask::new(1, 1);
    f.external_boxes(&one, &mut out);
    assert!(out.is_empty());
    one.set(0, 0, true);
    f.external_boxes(&one, &mut out);
    assert_eq!(out, vec![BoundingBox::new(0, 0, 1, 1)]);
    // A frame around the whole image with an island inside: one contour.
    let framed = Mask::from_fn(66, 9, |x, y| {
        x == 0 || y == 0 || x == 65 || y == 8 || (x == 30 && y == 4)
    });
    f.external_boxes(&framed, &mut out);
    assert_eq!(out, vec![BoundingBox::new(0, 0, 66, 9)]);
}
