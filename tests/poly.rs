//! Polynomials: term generation, evaluation against a naive oracle, least
//! squares against exact polynomials and the normal equations, order search,
//! errors, serde.

use ndarray::{Array1, Array2, ArrayView2};
use optical_tactile::Error;
use optical_tactile::calibration::poly::{
    CrossTerms, FitData, LeastSquares, PolySpec, Polynomial, VarGroup, candidate_orders, fit, mae,
    search_orders,
};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, RngSeed};

/// Deterministic generator (splitmix64): reproducible data without a `rand`
/// dependency.
struct Rng(u64);
impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [lo, hi).
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }
    /// Standard normal (Box-Muller).
    fn normal(&mut self) -> f64 {
        let u1 = self.uniform(1e-12, 1.0);
        let u2 = self.uniform(0.0, 1.0);
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

/// The obviously correct evaluation: sum of c_k * prod ((x_j - shift_j) / scale_j)^e_kj.
fn naive_eval(p: &Polynomial, x: &[f64]) -> f64 {
    let mut s = 0.0;
    for k in 0..p.n_terms() {
        let mut term = p.coefficients()[k];
        for (j, &e) in p.exponents(k).iter().enumerate() {
            let t = (x[j] - p.input_shift()[j]) / p.input_scale()[j];
            term *= t.powi(e as i32);
        }
        s += term;
    }
    s
}

fn spec3(a: u32, b: u32, c: u32, cross: CrossTerms) -> PolySpec {
    PolySpec::new(
        vec![
            VarGroup::new("disp", &["dx", "dy", "dz"], a),
            VarGroup::new("loc", &["x2d", "y2d"], b),
            VarGroup::new("pf", &["d_pf"], c),
        ],
        cross,
    )
    .unwrap()
}

fn proptest_config(cases: u32) -> Config {
    Config {
        cases,
        rng_algorithm: RngAlgorithm::ChaCha,
        rng_seed: RngSeed::Fixed(0x5eed_0006),
        failure_persistence: None,
        ..Config::default()
    }
}

#[test]
fn cross_term_rules_on_a_small_example() {
    // Group a (order 2) and b (order 1); exponents are [a, b].
    let groups = vec![VarGroup::new("A", &["a"], 2), VarGroup::new("B", &["b"], 1)];
    let terms = |cross| {
        PolySpec::new(groups.clone(), cross)
            .unwrap()
            .terms()
            .unwrap()
    };
    assert_eq!(
        terms(CrossTerms::MaxOfGroups),
        vec![vec![0, 0], vec![1, 0], vec![0, 1], vec![2, 0], vec![1, 1]]
    );
    assert_eq!(
        terms(CrossTerms::None),
        vec![vec![0, 0], vec![1, 0], vec![0, 1], vec![2, 0]]
    );
    assert_eq!(
        terms(CrossTerms::Full),
        vec![
            vec![0, 0],
            vec![1, 0],
            vec![0, 1],
            vec![2, 0],
            vec![1, 1],
            vec![2, 1]
        ]
    );
    assert_eq!(
        terms(CrossTerms::Total(1)),
        vec![vec![0, 0], vec![1, 0], vec![0, 1]]
    );
}

#[test]
fn within_a_group_the_order_limits_the_total_degree() {
    let s = PolySpec::new(vec![VarGroup::new("g", &["u", "v"], 2)], CrossTerms::None).unwrap();
    // 1, u, v, u^2, uv, v^2
    assert_eq!(s.n_terms().unwrap(), 6);
    for t in s.terms().unwrap() {
        assert!(t.iter().sum::<u32>() <= 2);
    }
    // MaxOfGroups: no term of the 6-variable spec exceeds the largest involved order.
    let s = spec3(3, 1, 2, CrossTerms::MaxOfGroups);
    for t in s.terms().unwrap() {
        let (d, l, p) = (t[0] + t[1] + t[2], t[3] + t[4], t[5]);
        assert!(d <= 3 && l <= 1 && p <= 2, "{t:?}");
        let max_involved = [(d, 3), (l, 1), (p, 2)]
            .iter()
            .filter(|(g, _)| *g > 0)
            .map(|(_, o)| *o)
            .max()
            .unwrap_or(0);
        assert!(d + l + p <= max_involved, "{t:?}");
    }
    assert_eq!(s.terms().unwrap().len(), s.n_terms().unwrap());
}

#[test]
fn exact_polynomial_coefficients_are_recovered() {
    // Raw variables (no normalization): the fitted coefficients are the true ones.
    let spec = spec3(2, 1, 1, CrossTerms::MaxOfGroups);
    let terms = spec.terms().unwrap();
    let mut rng = Rng(7);
    let truth: Vec<f64> = (0..terms.len()).map(|_| rng.uniform(-2.0, 2.0)).collect();
    let p_true = Polynomial::raw(
        &["dx", "dy", "dz", "x2d", "y2d", "d_pf"],
        terms.clone(),
        truth.clone(),
    )
    .unwrap();
    let n = 200;
    let x = Array2::from_shape_fn((n, 6), |_| rng.uniform(-1.5, 1.5));
    let y: Array1<f64> = x
        .outer_iter()
        .map(|r| naive_eval(&p_true, r.as_slice().unwrap()))
        .collect();
    let opts = LeastSquares {
        normalize: false,
        ..LeastSquares::default()
    };
    let (p, stats) = fit(&spec, x.view(), y.view(), &opts).unwrap();
    assert_eq!(stats.rank, terms.len());
    assert_eq!(stats.n_terms, terms.len());
    for (k, (a, b)) in p.coefficients().iter().zip(&truth).enumerate() {
        assert!((a - b).abs() < 1e-9, "term {k} {:?}: {a} vs {b}", terms[k]);
    }
    assert!(stats.train_mae < 1e-12, "train MAE {}", stats.train_mae);

    // Normalized fit of the same data: other coefficients, same function.
    let (q, _) = fit(&spec, x.view(), y.view(), &LeastSquares::default()).unwrap();
    for _ in 0..50 {
        let pt: Vec<f64> = (0..6).map(|_| rng.uniform(-1.5, 1.5)).collect();
        let (a, b) = (q.evaluate(&pt).unwrap(), naive_eval(&p_true, &pt));
        assert!((a - b).abs() < 1e-9 * (1.0 + b.abs()), "{a} vs {b}");
    }
}

#[test]
fn large_pixel_coordinates_are_handled_by_normalization() {
    // x in pixels around 800 with a 5th-order map: raw monomials span 1e15.
    let mut rng = Rng(11);
    let f = |x: f64| {
        let t = (x - 800.0) / 700.0;
        -150.0 + 160.0 * t - 3.0 * t * t + 2.0 * t.powi(3) - 0.5 * t.powi(5)
    };
    let x = Array2::from_shape_fn((120, 1), |_| rng.uniform(100.0, 1500.0));
    let y: Array1<f64> = x.column(0).mapv(f);
    let (p, st) = fit(
        &PolySpec::single("x2d", 5).unwrap(),
        x.view(),
        y.view(),
        &LeastSquares::default(),
    )
    .unwrap();
    assert_eq!(st.rank, 6);
    for xi in [100.0, 333.3, 800.0, 1499.0] {
        assert!((p.evaluate(&[xi]).unwrap() - f(xi)).abs() < 1e-8);
    }
}

/// Normal equations solved by Gaussian elimination: the textbook oracle for a
/// well-conditioned least-squares problem.
fn normal_equations(a: &Array2<f64>, y: &Array1<f64>) -> Vec<f64> {
    let m = a.ncols();
    let mut g = vec![vec![0.0; m + 1]; m];
    for i in 0..m {
        for j in 0..m {
            g[i][j] = a.column(i).dot(&a.column(j));
        }
        g[i][m] = a.column(i).dot(y);
    }
    for c in 0..m {
        let piv = (c..m)
            .max_by(|&p, &q| g[p][c].abs().total_cmp(&g[q][c].abs()))
            .unwrap();
        g.swap(c, piv);
        for r in 0..m {
            if r != c {
                let f = g[r][c] / g[c][c];
                for k in c..=m {
                    g[r][k] -= f * g[c][k];
                }
            }
        }
    }
    (0..m).map(|i| g[i][m] / g[i][i]).collect()
}

#[test]
fn noisy_fit_matches_the_normal_equations() {
    let spec = PolySpec::new(
        vec![
            VarGroup::new("a", &["u", "v"], 2),
            VarGroup::new("b", &["w"], 1),
        ],
        CrossTerms::MaxOfGroups,
    )
    .unwrap();
    let terms = spec.terms().unwrap();
    let mut rng = Rng(3);
    let n = 80;
    let x = Array2::from_shape_fn((n, 3), |_| rng.uniform(-1.0, 1.0));
    let y: Array1<f64> = x
        .outer_iter()
        .map(|r| 1.0 + r[0] - 2.0 * r[1] * r[2] + 0.5 * r[0].powi(3) + 0.1 * rng.normal())
        .collect();
    let a = Array2::from_shape_fn((n, terms.len()), |(i, k)| {
        (0..3)
            .map(|j| x[(i, j)].powi(terms[k][j] as i32))
            .product::<f64>()
    });
    let oracle = normal_equations(&a, &y);
    let opts = LeastSquares {
        normalize: false,
        ..LeastSquares::default()
    };
    let (p, _) = fit(&spec, x.view(), y.view(), &opts).unwrap();
    for (a, b) in p.coefficients().iter().zip(&oracle) {
        assert!((a - b).abs() < 1e-9, "{a} vs {b}");
    }
}

/// Noisy samples of a 6-variable polynomial with known group orders.
fn noisy_force_data(n: usize, rng: &mut Rng, noise: f64) -> (Array2<f64>, Array1<f64>) {
    let x = Array2::from_shape_fn((n, 6), |_| rng.uniform(-1.0, 1.0));
    // Displacement order 2 (dz^2, dx*dy), location order 1, d_pf order 1.
    let y = x
        .outer_iter()
        .map(|r| {
            0.3 + 1.5 * r[2] - 0.8 * r[2] * r[2] + 0.6 * r[0] * r[1] + 0.4 * r[3] - 0.3 * r[5]
                + 0.2 * r[2] * r[3]
                + noise * rng.normal()
        })
        .collect();
    (x, y)
}

#[test]
fn order_search_picks_the_true_orders_on_noisy_data() {
    let mut rng = Rng(2026);
    let (xt, yt) = noisy_force_data(600, &mut rng, 0.02);
    let (xv, yv) = noisy_force_data(300, &mut rng, 0.02);
    let (xs, ys) = noisy_force_data(300, &mut rng, 0.02);
    let spec = spec3(4, 3, 3, CrossTerms::MaxOfGroups);
    let (p, rep) = search_orders(
        &spec,
        FitData::new(xt.view(), yt.view()),
        FitData::new(xv.view(), yv.view()),
        Some(FitData::new(xs.view(), ys.view())),
        &LeastSquares::default(),
    )
    .unwrap();
    assert_eq!(
        rep.orders,
        vec![2, 1, 1],
        "candidates: {:#?}",
        rep.candidates
    );
    assert_eq!(rep.candidates.len(), 4 * 3 * 3);
    assert_eq!(rep.n_terms, p.n_terms());
    // With noise sigma 0.02, MAE of the right model is about 0.8 * sigma.
    let test_mae = rep.test_mae.unwrap();
    assert!(test_mae < 0.02, "test MAE {test_mae}");
    assert!((test_mae - mae(&p, xs.view(), ys.view()).unwrap()).abs() < 1e-15);
    // The chosen candidate has the lowest validation MAE of all.
    for c in &rep.candidates {
        if let Some(v) = c.val_mae {
            assert!(v >= rep.val_mae);
        }
    }
}

#[test]
fn order_search_single_variable_true_order() {
    let mut rng = Rng(99);
    let f = |x: f64| 2.0 - x + 0.7 * x.powi(3);
    let mk = |n, rng: &mut Rng| {
        let x = Array2::from_shape_fn((n, 1), |_| rng.uniform(-2.0, 2.0));
        let y: Array1<f64> = x
            .column(0)
            .iter()
            .map(|&v| f(v) + 0.05 * rng.normal())
            .collect();
        (x, y)
    };
    let (xt, yt) = mk(300, &mut rng);
    let (xv, yv) = mk(200, &mut rng);
    let (_, rep) = search_orders(
        &PolySpec::single("x", 8).unwrap(),
        FitData::new(xt.view(), yt.view()),
        FitData::new(xv.view(), yv.view()),
        None,
        &LeastSquares::default(),
    )
    .unwrap();
    assert_eq!(rep.orders, vec![3]);
    assert_eq!(rep.test_mae, None);
}

#[test]
fn order_search_is_deterministic() {
    let mut rng = Rng(5);
    let (xt, yt) = noisy_force_data(200, &mut rng, 0.05);
    let (xv, yv) = noisy_force_data(100, &mut rng, 0.05);
    let spec = spec3(3, 2, 2, CrossTerms::MaxOfGroups);
    let run = || {
        search_orders(
            &spec,
            FitData::new(xt.view(), yt.view()),
            FitData::new(xv.view(), yv.view()),
            None,
            &LeastSquares::default(),
        )
        .unwrap()
    };
    let (p1, r1) = run();
    let (p2, r2) = run();
    assert_eq!(p1, p2);
    assert_eq!(r1, r2);
    let single = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let (p3, r3) = single.install(run);
    assert_eq!(p1, p3);
    assert_eq!(r1, r3);
}

#[test]
fn candidates_too_big_for_the_data_are_skipped_and_reported() {
    let mut rng = Rng(8);
    // 30 training rows: disp order 3 with loc 2 and pf 2 has 84 terms: unfit.
    let (xt, yt) = noisy_force_data(30, &mut rng, 0.01);
    let (xv, yv) = noisy_force_data(30, &mut rng, 0.01);
    let (_, rep) = search_orders(
        &spec3(3, 2, 2, CrossTerms::MaxOfGroups),
        FitData::new(xt.view(), yt.view()),
        FitData::new(xv.view(), yv.view()),
        None,
        &LeastSquares::default(),
    )
    .unwrap();
    let skipped: Vec<_> = rep
        .candidates
        .iter()
        .filter(|c| c.error.is_some())
        .collect();
    assert!(!skipped.is_empty());
    for c in skipped {
        assert!(c.n_terms > 30);
        assert!(
            c.error.as_ref().unwrap().contains("at least"),
            "{:?}",
            c.error
        );
    }
    assert!(rep.n_terms <= 30);
}

#[test]
fn too_few_rows_says_how_many_are_needed() {
    let spec = spec3(2, 1, 1, CrossTerms::MaxOfGroups);
    let m = spec.n_terms().unwrap();
    let x = Array2::<f64>::zeros((m - 1, 6));
    let y = Array1::<f64>::zeros(m - 1);
    let e = fit(&spec, x.view(), y.view(), &LeastSquares::default()).unwrap_err();
    assert!(matches!(e, Error::Numerical { .. }), "{e}");
    let msg = e.to_string();
    assert!(msg.contains(&format!("at least {m} samples")), "{msg}");
    assert!(msg.contains(&format!("got {}", m - 1)), "{msg}");
    // The search reports the smallest candidate's error when nothing fits.
    let e = search_orders(
        &spec,
        FitData::new(x.view(), y.view()),
        FitData::new(x.view(), y.view()),
        None,
        &LeastSquares::default(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("no candidate"), "{e}");
}

#[test]
fn bad_data_is_a_typed_error() {
    let spec = PolySpec::single("x", 2).unwrap();
    let x = Array2::from_shape_fn((10, 1), |(i, _)| i as f64);
    let y = Array1::from_shape_fn(10, |i| i as f64);
    // Mismatched variable count.
    let x2 = Array2::<f64>::zeros((10, 2));
    let e = fit(&spec, x2.view(), y.view(), &LeastSquares::default()).unwrap_err();
    assert!(matches!(e, Error::ShapeMismatch { .. }), "{e}");
    // Mismatched row count.
    let e = fit(
        &spec,
        x.view(),
        y.slice(ndarray::s![..9]),
        &LeastSquares::default(),
    )
    .unwrap_err();
    assert!(matches!(e, Error::ShapeMismatch { .. }), "{e}");
    // Non-finite input and target, with their positions.
    let mut xn = x.clone();
    xn[(4, 0)] = f64::NAN;
    match fit(&spec, xn.view(), y.view(), &LeastSquares::default()).unwrap_err() {
        Error::NonFinite { row, col, .. } => assert_eq!((row, col), (4, 0)),
        e => panic!("{e}"),
    }
    let mut yn = y.clone();
    yn[7] = f64::INFINITY;
    match fit(&spec, x.view(), yn.view(), &LeastSquares::default()).unwrap_err() {
        Error::NonFinite { row, .. } => assert_eq!(row, 7),
        e => panic!("{e}"),
    }
    // Bad rcond.
    let opts = LeastSquares {
        rcond: f64::NAN,
        ..LeastSquares::default()
    };
    assert!(matches!(
        fit(&spec, x.view(), y.view(), &opts).unwrap_err(),
        Error::InvalidParameter { .. }
    ));
}

#[test]
fn rank_deficiency_is_reported() {
    // v is a copy of u: the u and v columns are collinear.
    let spec = PolySpec::new(vec![VarGroup::new("g", &["u", "v"], 1)], CrossTerms::None).unwrap();
    let x = Array2::from_shape_fn((20, 2), |(i, _)| i as f64);
    let y = Array1::from_shape_fn(20, |i| 3.0 + 2.0 * i as f64);
    let e = fit(&spec, x.view(), y.view(), &LeastSquares::default()).unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains("rank 2 for 3 terms"), "{msg}");
    // Allowed: minimum-norm solution, rank in the stats, still exact.
    let opts = LeastSquares {
        allow_rank_deficient: true,
        ..LeastSquares::default()
    };
    let (p, st) = fit(&spec, x.view(), y.view(), &opts).unwrap();
    assert_eq!(st.rank, 2);
    assert!((p.evaluate(&[30.0, 30.0]).unwrap() - 63.0).abs() < 1e-9);
    // A constant variable: rank loss too.
    let xc = Array2::from_shape_fn((20, 1), |_| 5.0);
    let e = fit(
        &PolySpec::single("c", 1).unwrap(),
        xc.view(),
        y.view(),
        &LeastSquares::default(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("rank 1 for 2 terms"), "{e}");
}

#[test]
fn bad_specs_and_inputs_are_rejected() {
    assert!(PolySpec::new(vec![], CrossTerms::None).is_err());
    assert!(PolySpec::new(vec![VarGroup::new("g", &[], 1)], CrossTerms::None).is_err());
    assert!(
        PolySpec::new(
            vec![VarGroup::new("a", &["x"], 1), VarGroup::new("b", &["x"], 1)],
            CrossTerms::None
        )
        .is_err()
    );
    assert!(PolySpec::single("x", 99).is_err());
    // A spec built from its public fields is checked when used.
    let raw = PolySpec {
        groups: vec![VarGroup::new("g", &["a", "a"], 1)],
        cross: CrossTerms::Full,
    };
    assert!(raw.terms().is_err());
    let huge = PolySpec {
        groups: vec![VarGroup::new("g", &["a"], u32::MAX)],
        cross: CrossTerms::Full,
    };
    assert!(huge.n_terms().is_err());
    // Sixteen one-variable groups of order 16: refused before counting (17^16 combinations).
    let names: Vec<String> = (0..16).map(|i| format!("w{i}")).collect();
    let groups = names
        .iter()
        .map(|n| VarGroup::new(n, &[n.as_str()], 16))
        .collect();
    assert!(PolySpec::new(groups, CrossTerms::Total(2)).is_err());
    let many: Vec<String> = (0..16).map(|i| format!("v{i}")).collect();
    let many: Vec<&str> = many.iter().map(|s| s.as_str()).collect();
    let e = PolySpec::new(vec![VarGroup::new("g", &many, 8)], CrossTerms::Full).unwrap_err();
    assert!(e.to_string().contains("terms"), "{e}");
    let spec = spec3(1, 1, 1, CrossTerms::None);
    assert!(spec.with_orders(&[1, 2]).is_err());
    // Evaluation: wrong length and non-finite input.
    let p = Polynomial::raw(&["a", "b"], vec![vec![0, 0], vec![1, 1]], vec![1.0, 2.0]).unwrap();
    assert!(matches!(
        p.evaluate(&[1.0]),
        Err(Error::InvalidParameter { .. })
    ));
    assert!(matches!(
        p.evaluate(&[1.0, f64::NAN]),
        Err(Error::NonFinite { col: 1, .. })
    ));
    let x = Array2::<f64>::zeros((3, 3));
    assert!(matches!(
        p.evaluate_rows(x.view()),
        Err(Error::ShapeMismatch { .. })
    ));
    // Construction: mismatched exponent rows / coefficients, bad scale.
    assert!(Polynomial::raw(&["a"], vec![vec![0, 1]], vec![1.0]).is_err());
    assert!(Polynomial::raw(&["a"], vec![vec![0], vec![1]], vec![1.0]).is_err());
    assert!(
        Polynomial::new(
            vec!["a".into()],
            vec![vec![1]],
            vec![1.0],
            vec![0.0],
            vec![0.0]
        )
        .is_err()
    );
    assert!(Polynomial::raw(&["a"], vec![vec![1]], vec![f64::NAN]).is_err());
}

#[test]
fn serde_round_trip_is_bit_exact_and_validated() {
    let mut rng = Rng(42);
    let spec = spec3(2, 1, 1, CrossTerms::MaxOfGroups);
    let (x, y) = noisy_force_data(100, &mut rng, 0.1);
    let (p, _) = fit(&spec, x.view(), y.view(), &LeastSquares::default()).unwrap();
    let json = serde_json::to_string_pretty(&p).unwrap();
    let q: Polynomial = serde_json::from_str(&json).unwrap();
    assert_eq!(p, q);
    for (a, b) in p.coefficients().iter().zip(q.coefficients()) {
        assert_eq!(a.to_bits(), b.to_bits());
    }
    for (a, b) in p.input_scale().iter().zip(q.input_scale()) {
        assert_eq!(a.to_bits(), b.to_bits());
    }
    // Hand-written files may use plain numbers.
    let q: Polynomial = serde_json::from_str(
        r#"{"variables":["x"],"input_shift":[0],"input_scale":[1.0],"exponents":[[0],[2]],"coefficients":[1.5,"-2"]}"#,
    )
    .unwrap();
    assert_eq!(q.evaluate(&[3.0]).unwrap(), 1.5 - 18.0);
    assert_eq!(q.to_formula(), "1.5 - 2*t(x)^2");
    assert_eq!(q.degree(), 2);
    // Exponent row of the wrong width: an error with a position.
    let e = serde_json::from_str::<Polynomial>(
        r#"{"variables":["x","y"],"input_shift":[0,0],"input_scale":[1,1],"exponents":[[0,0],[1]],"coefficients":[1,2]}"#,
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("exponent row 1 has 1 entries"),
        "{e}"
    );
    let e = serde_json::from_str::<Polynomial>(
        r#"{"variables":["x"],"input_shift":[0],"input_scale":[1],"exponents":[[0]],"coefficients":[1,2]}"#,
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("1 exponent rows but 2 coefficients"),
        "{e}"
    );
    let e = serde_json::from_str::<Polynomial>(
        r#"{"variables":["x"],"input_shift":[0],"input_scale":[1],"exponents":[[0]],"coefficients":["NaN"]}"#,
    )
    .unwrap_err();
    assert!(e.to_string().contains("not a finite"), "{e}");
}

#[test]
fn candidate_orders_cover_the_grid() {
    let c = candidate_orders(&spec3(2, 3, 0, CrossTerms::None));
    assert_eq!(c.len(), 6);
    assert_eq!(c[0], vec![1, 1, 0]);
    assert_eq!(c[5], vec![2, 3, 0]);
}

fn batch_matches_naive(p: &Polynomial, x: ArrayView2<f64>) {
    let fast = p.evaluate_rows(x).unwrap();
    for (r, f) in x.outer_iter().zip(fast.iter()) {
        let row = r.to_vec();
        let n = naive_eval(p, &row);
        let single = p.evaluate(&row).unwrap();
        assert!((f - n).abs() <= 1e-12 * (1.0 + n.abs()), "{f} vs {n}");
        assert_eq!(f.to_bits(), single.to_bits());
    }
}

proptest! {
    #![proptest_config(proptest_config(48))]

    /// Fast (power table) evaluation agrees with the naive formula for random
    /// polynomials, normalizations and points.
    #[test]
    fn fast_evaluation_matches_naive(
        a in 0u32..4, b in 0u32..3, c in 0u32..3,
        cross in prop_oneof![Just(CrossTerms::None), Just(CrossTerms::MaxOfGroups), Just(CrossTerms::Full)],
        seed in any::<u64>(),
    ) {
        let spec = spec3(a, b, c, cross);
        let mut rng = Rng(seed);
        let terms = spec.terms().unwrap();
        let coef: Vec<f64> = (0..terms.len()).map(|_| rng.uniform(-3.0, 3.0)).collect();
        let shift: Vec<f64> = (0..6).map(|_| rng.uniform(-100.0, 100.0)).collect();
        let scale: Vec<f64> = (0..6).map(|_| rng.uniform(0.5, 200.0)).collect();
        let p = Polynomial::new(spec.variables(), terms, coef, shift.clone(), scale.clone()).unwrap();
        let x = Array2::from_shape_fn((8, 6), |(_, j)| shift[j] + scale[j] * rng.uniform(-1.2, 1.2));
        batch_matches_naive(&p, x.view());
    }

    /// Any exactly representable polynomial is recovered (as a function) by
    /// the normalized fit.
    #[test]
    fn exact_polynomials_are_refitted(order in 1u32..5, seed in any::<u64>()) {
        let mut rng = Rng(seed);
        let spec = PolySpec::new(
            vec![VarGroup::new("loc", &["x", "y"], order)],
            CrossTerms::MaxOfGroups,
        ).unwrap();
        let terms = spec.terms().unwrap();
        let coef: Vec<f64> = (0..terms.len()).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let p = Polynomial::new(spec.variables(), terms.clone(), coef, vec![500.0, 100.0], vec![400.0, 80.0]).unwrap();
        let n = 3 * terms.len() + 5;
        let x = Array2::from_shape_fn((n, 2), |(_, j)| if j == 0 { rng.uniform(100.0, 900.0) } else { rng.uniform(20.0, 180.0) });
        let y = p.evaluate_rows(x.view()).unwrap();
        let (q, st) = fit(&spec, x.view(), y.view(), &LeastSquares::default()).unwrap();
        prop_assert_eq!(st.rank, terms.len());
        for _ in 0..10 {
            let pt = [rng.uniform(100.0, 900.0), rng.uniform(20.0, 180.0)];
            let (a, b) = (q.evaluate(&pt).unwrap(), p.evaluate(&pt).unwrap());
            prop_assert!((a - b).abs() < 1e-9 * (1.0 + b.abs()), "{} vs {}", a, b);
        }
    }

    /// serde round trip is bit-exact for arbitrary finite coefficients.
    #[test]
    fn json_round_trip_is_bit_exact(coef in prop::collection::vec(prop::num::f64::NORMAL | prop::num::f64::SUBNORMAL | prop::num::f64::ZERO, 1..6)) {
        let terms: Vec<Vec<u32>> = (0..coef.len() as u32).map(|k| vec![k]).collect();
        let p = Polynomial::raw(&["x"], terms, coef).unwrap();
        let q: Polynomial = serde_json::from_str(&serde_json::to_string(&p).unwrap()).unwrap();
        for (a, b) in p.coefficients().iter().zip(q.coefficients()) {
            prop_assert_eq!(a.to_bits(), b.to_bits());
        }
    }
}

#[test]
fn huber_fit_resists_gross_outliers() {
    let mut rng = Rng(31);
    let n = 400;
    let x = Array2::from_shape_fn((n, 1), |_| rng.uniform(-1.0, 1.0));
    let truth = [1.0, 2.0, -1.0];
    let mut y: Array1<f64> = x
        .column(0)
        .iter()
        .map(|&v| truth[0] + truth[1] * v + truth[2] * v * v + 0.01 * rng.normal())
        .collect();
    // 5 % gross outliers, all on one side (a biased mis-detection).
    for i in (0..n).step_by(20) {
        y[i] += rng.uniform(5.0, 10.0);
    }
    let spec = PolySpec::single("x", 2).unwrap();
    let plain = LeastSquares {
        normalize: false,
        ..LeastSquares::default()
    };
    let robust = LeastSquares {
        huber: Some(1.345),
        ..plain.clone()
    };
    let (p_ls, _) = fit(&spec, x.view(), y.view(), &plain).unwrap();
    let (p_h, _) = fit(&spec, x.view(), y.view(), &robust).unwrap();
    let err = |p: &Polynomial| {
        p.coefficients()
            .iter()
            .zip(truth)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max)
    };
    assert!(err(&p_ls) > 0.2, "plain LS error {}", err(&p_ls));
    assert!(err(&p_h) < 0.01, "Huber error {}", err(&p_h));
    // On exact data the robust fit is the plain one.
    let ye: Array1<f64> = x.column(0).mapv(|v| 1.0 + 2.0 * v - v * v);
    let (q, _) = fit(&spec, x.view(), ye.view(), &robust).unwrap();
    assert!(err(&q) < 1e-12);
    // Bad parameter.
    let bad = LeastSquares {
        huber: Some(-1.0),
        ..plain
    };
    assert!(matches!(
        fit(&spec, x.view(), y.view(), &bad),
        Err(Error::InvalidParameter { .. })
    ));
}

#[test]
fn an_optional_group_may_be_left_out_by_the_search() {
    // Candidates: the optional group also at order 0.
    let spec = |optional: bool| {
        let shear = VarGroup::new("s", &["s"], 2);
        PolySpec::new(
            vec![
                VarGroup::new("x", &["x"], 2),
                if optional { shear.or_none() } else { shear },
            ],
            CrossTerms::MaxOfGroups,
        )
        .unwrap()
    };
    assert_eq!(
        candidate_orders(&spec(true)),
        vec![
            vec![1, 0],
            vec![1, 1],
            vec![1, 2],
            vec![2, 0],
            vec![2, 1],
            vec![2, 2]
        ]
    );
    assert!(candidate_orders(&spec(false)).iter().all(|o| o[1] >= 1));

    // y depends on x alone; s is noise of a few samples' range, so a fit
    // with s overfits the training set and reads the validation set worse.
    let mut rng = Rng(7);
    let mk = |n, rng: &mut Rng| {
        let x = Array2::from_shape_fn((n, 2), |(_, j)| {
            if j == 0 {
                rng.uniform(-1.0, 1.0)
            } else {
                rng.normal()
            }
        });
        let y: Array1<f64> = x
            .rows()
            .into_iter()
            .map(|r| 1.0 + 2.0 * r[0] - r[0] * r[0] + 0.05 * rng.normal())
            .collect();
        (x, y)
    };
    let (xt, yt) = mk(12, &mut rng);
    let (xv, yv) = mk(200, &mut rng);
    let search = |optional| {
        search_orders(
            &spec(optional),
            FitData::new(xt.view(), yt.view()),
            FitData::new(xv.view(), yv.view()),
            None,
            &LeastSquares::default(),
        )
        .unwrap()
        .1
    };
    let (with, without) = (search(true), search(false));
    assert_eq!(with.orders, vec![2, 0]);
    assert!(without.orders[1] >= 1);
    assert!(
        with.val_mae < without.val_mae,
        "{} against {}",
        with.val_mae,
        without.val_mae
    );

    // Where s does carry the target, the search keeps it.
    let mk = |n, rng: &mut Rng| {
        let x = Array2::from_shape_fn((n, 2), |_| rng.uniform(-1.0, 1.0));
        let y: Array1<f64> = x
            .rows()
            .into_iter()
            .map(|r| r[0] + 0.8 * r[1] + 0.01 * rng.normal())
            .collect();
        (x, y)
    };
    let (xt, yt) = mk(100, &mut rng);
    let (xv, yv) = mk(100, &mut rng);
    let (_, rep) = search_orders(
        &spec(true),
        FitData::new(xt.view(), yt.view()),
        FitData::new(xv.view(), yv.view()),
        None,
        &LeastSquares::default(),
    )
    .unwrap();
    assert!(rep.orders[1] >= 1, "{:?}", rep.orders);
}
