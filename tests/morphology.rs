//! Morphology against a naive oracle (direct min/max over the element), and
//! the algebraic properties of erosion and dilation.

use ndarray::Array2;
use optical_tactile::segment::morphology::{
    Mask, Morphology, Shape, StructuringElement, dilate, erode,
};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};

/// Direct min (erosion) / max (dilation) over the element's cells; outside
/// pixels skipped (they never constrain the result).
fn naive(m: &Array2<u8>, se: &StructuringElement, iterations: usize, erode: bool) -> Array2<u8> {
    let (h, w) = m.dim();
    let (ax, ay) = se.anchor();
    let mut cur = m.clone();
    for _ in 0..iterations {
        let mut out = Array2::<u8>::zeros((h, w));
        for y in 0..h {
            for x in 0..w {
                let mut acc = erode;
                for i in 0..se.height {
                    for j in 0..se.width {
                        if !se.contains(i, j) {
                            continue;
                        }
                        let (xx, yy) = (
                            x as i64 + j as i64 - ax as i64,
                            y as i64 + i as i64 - ay as i64,
                        );
                        if xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                            continue;
                        }
                        let v = cur[[yy as usize, xx as usize]] != 0;
                        if erode {
                            acc &= v;
                        } else {
                            acc |= v;
                        }
                    }
                }
                out[[y, x]] = acc as u8;
            }
        }
        cur = out;
    }
    cur
}

fn shape() -> impl Strategy<Value = Shape> {
    prop_oneof![Just(Shape::Rect), Just(Shape::Cross), Just(Shape::Ellipse)]
}

/// A mask with a given density, up to 150 pixels wide (several words per row).
fn mask() -> impl Strategy<Value = Array2<u8>> {
    (1usize..150, 1usize..40, 0u32..=100).prop_flat_map(|(w, h, density)| {
        proptest::collection::vec(0u32..100, w * h).prop_map(move |v| {
            Array2::from_shape_vec((h, w), v.into_iter().map(|r| (r < density) as u8).collect())
                .unwrap()
        })
    })
}

fn runner(cases: u32) -> TestRunner {
    TestRunner::new_with_rng(
        Config {
            cases,
            failure_persistence: None,
            ..Config::default()
        },
        TestRng::from_seed(RngAlgorithm::ChaCha, &[7u8; 32]),
    )
}

#[test]
fn fast_matches_naive_for_every_shape_and_size() {
    // One worker reused across sizes and shapes, as a caller would.
    let worker = std::cell::RefCell::new((Morphology::new(), Mask::default()));
    runner(300)
        .run(
            &(mask(), shape(), 1usize..20, 1usize..20, 1usize..3),
            |(m, shape, kw, kh, it)| {
                let se = StructuringElement::new(shape, kw, kh);
                let mk = Mask::from_array(&m);
                let (morph, out) = &mut *worker.borrow_mut();
                morph.erode(&mk, out, &se, it).unwrap();
                prop_assert_eq!(out.to_array(), naive(&m, &se, it, true), "erode {:?}", se);
                morph.dilate(&mk, out, &se, it).unwrap();
                prop_assert_eq!(out.to_array(), naive(&m, &se, it, false), "dilate {:?}", se);
                Ok(())
            },
        )
        .unwrap();
}

#[test]
fn large_kernels_past_a_word_match_naive() {
    // Kernels wider than 64 pixels exercise the multi-word shifts.
    let m = Array2::from_shape_fn((30, 200), |(y, x)| ((x * 7 + y * 13) % 23 == 0) as u8);
    let mk = Mask::from_array(&m);
    for se in [
        StructuringElement::rect(70, 5),
        StructuringElement::rect(130, 1),
        StructuringElement::ellipse(81, 9),
        StructuringElement::cross(99, 41),
    ] {
        assert_eq!(
            dilate(&mk, &se, 1).unwrap().to_array(),
            naive(&m, &se, 1, false),
            "{se:?}"
        );
        assert_eq!(
            erode(&mk.not(), &se, 1).unwrap().to_array(),
            naive(&mk.not().to_array(), &se, 1, true),
            "{se:?}"
        );
    }
}

#[test]
fn properties_inclusion_and_duality() {
    runner(200)
        .run(
            &(mask(), shape(), 1usize..12, 1usize..12),
            |(m, shape, kw, kh)| {
                let se = StructuringElement::new(shape, kw, kh);
                let mk = Mask::from_array(&m);
                let e = erode(&mk, &se, 1).unwrap();
                let d = dilate(&mk, &se, 1).unwrap();
                for y in 0..mk.height() {
                    for x in 0..mk.width() {
                        // The anchor cell belongs to every element, so erosion
                        // lies inside the mask and the mask inside the dilation.
                        prop_assert!(!e.get(x, y) || mk.get(x, y));
                        prop_assert!(!mk.get(x, y) || d.get(x, y));
                    }
                }
                // Duality with the border convention (outside: 1 for erosion, 0 for dilation).
                prop_assert_eq!(&e, &dilate(&mk.not(), &se, 1).unwrap().not());
                prop_assert_eq!(&d, &erode(&mk.not(), &se, 1).unwrap().not());
                Ok(())
            },
        )
        .unwrap();
}

#[test]
fn one_pixel_empty_and_full_masks() {
    let se = StructuringElement::ellipse(5, 5);
    // One pixel: erosion removes it, dilation stamps the element.
    let mut one = Mask::new(9, 9);
    one.set(4, 4, true);
    assert!(erode(&one, &se, 1).unwrap().is_empty());
    let d = dilate(&one, &se, 1).unwrap().to_array();
    assert_eq!(d.slice(ndarray::s![2..7, 2..7]), se.to_array());
    assert_eq!(d.iter().map(|&v| v as usize).sum::<usize>(), 17);
    // Empty stays empty; a full mask stays full (the outside does not erode it).
    let empty = Mask::new(17, 3);
    assert!(dilate(&empty, &se, 2).unwrap().is_empty());
    let full = empty.not();
    assert_eq!(
        erode(&full, &StructuringElement::rect(31, 31), 3).unwrap(),
        full
    );
    // Zero-sized masks are fine.
    assert_eq!(erode(&Mask::new(0, 5), &se, 1).unwrap().size(), (0, 5));
    assert_eq!(dilate(&Mask::new(5, 0), &se, 1).unwrap().size(), (5, 0));
    // Zero iterations copy.
    assert_eq!(erode(&one, &se, 0).unwrap(), one);
}

#[test]
fn a_ring_touching_the_border() {
    // A square ring that touches the left border: opening it with a 3x3 rect
    // keeps the 3-thick ring, and the border column is not eroded away.
    let m = Mask::from_fn(20, 12, |x, y| {
        let outer = x < 12 && (1..11).contains(&y);
        let hole = (3..9).contains(&x) && (4..8).contains(&y);
        outer && !hole
    });
    let se = StructuringElement::rect(3, 3);
    let opened = dilate(&erode(&m, &se, 1).unwrap(), &se, 1).unwrap();
    assert_eq!(opened, m);
    assert!(erode(&m, &se, 1).unwrap().get(0, 5));
}
