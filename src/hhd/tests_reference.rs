//! Agreement with reference outputs of the natural HHD (fixtures/hhd/).
//!
//! The fixtures come from `tools/nhhd_reference.py`: a numpy/scipy
//! transcription of the reference definition (numpy.gradient stencils,
//! scipy.signal.fftconvolve for the potentials, checked there against a
//! direct sum). The authors' pynhhd 1.1 itself was not installable here.

use std::path::{Path, PathBuf};

use super::{Decomposition, NaturalHhd, direct};
use ndarray::Array2;

/// Minimal reader for the .npy files numpy writes for a C-ordered 2-D `<f8`
/// array (all the fixtures are such).
fn read_npy_f64(path: &Path) -> Array2<f64> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(&bytes[..6], b"\x93NUMPY", "{}: not a .npy", path.display());
    let (hlen, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        _ => (
            u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize,
            12,
        ),
    };
    let header = std::str::from_utf8(&bytes[start..start + hlen]).unwrap();
    assert!(header.contains("'descr': '<f8'"), "{header}");
    assert!(header.contains("'fortran_order': False"), "{header}");
    let shape = header
        .split("'shape': (")
        .nth(1)
        .unwrap()
        .split(')')
        .next()
        .unwrap();
    let dims: Vec<usize> = shape
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| s.trim().parse().unwrap())
        .collect();
    assert_eq!(dims.len(), 2, "{header}");
    let data: Vec<f64> = bytes[start + hlen..]
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
        .collect();
    Array2::from_shape_vec((dims[0], dims[1]), data).unwrap()
}

fn fixture_dir(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures/hhd")
        .join(name)
}

fn max_abs(a: &Array2<f64>) -> f64 {
    a.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

/// max |ours - ref| / scale.
fn rel_err(ours: &Array2<f64>, reference: &Array2<f64>, scale: f64) -> f64 {
    assert_eq!(ours.dim(), reference.dim());
    let err = ours
        .iter()
        .zip(reference)
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    err / scale.max(f64::MIN_POSITIVE)
}

fn compare(dec: &Decomposition, dir: &Path, tol: f64) -> Vec<(String, f64)> {
    let parts: [(&str, &Array2<f64>); 10] = [
        ("div", &dec.div),
        ("curl", &dec.curl),
        ("D", &dec.potential_d),
        ("R", &dec.potential_r),
        ("d_u", &dec.d.u),
        ("d_v", &dec.d.v),
        ("r_u", &dec.r.u),
        ("r_v", &dec.r.v),
        ("h_u", &dec.h.u),
        ("h_v", &dec.h.v),
    ];
    let load = |name: &str| read_npy_f64(&dir.join(format!("{name}.npy")));
    // Errors are relative to the magnitude of the quantity's kind (the
    // potentials together, the vector fields against the input): a part
    // that is nearly zero (R of a curl-free press) has no scale of its own.
    let field_scale = max_abs(&load("u")).max(max_abs(&load("v")));
    let pot_scale = max_abs(&load("D")).max(max_abs(&load("R")));
    let deriv_scale = max_abs(&load("div")).max(max_abs(&load("curl")));
    let mut errs = Vec::new();
    for (name, ours) in parts {
        let reference = load(name);
        let scale = match name {
            "div" | "curl" => deriv_scale,
            "D" | "R" => pot_scale,
            _ => field_scale,
        };
        let e = rel_err(ours, &reference, scale);
        assert!(
            e <= tol,
            "{}: {name} differs by {e:e} (relative)",
            dir.display()
        );
        errs.push((name.to_string(), e));
    }
    errs
}

fn run_case(name: &str) {
    let dir = fixture_dir(name);
    let spacing = std::fs::read_to_string(dir.join("spacing.txt")).unwrap();
    let sp: Vec<f64> = spacing
        .split_whitespace()
        .map(|s| s.parse().unwrap())
        .collect();
    let (dx, dy) = (sp[0], sp[1]);
    let u64_ = read_npy_f64(&dir.join("u.npy"));
    let v64 = read_npy_f64(&dir.join("v.npy"));
    // The fixture inputs are f32 values stored as f64: the f32 API sees
    // exactly the reference's input.
    let u32_ = u64_.mapv(|x| x as f32);
    let v32 = v64.mapv(|x| x as f32);
    assert!(u32_.iter().zip(&u64_).all(|(&a, &b)| a as f64 == b));
    let mut hhd = NaturalHhd::new();
    let dec = hhd.decompose(u32_.view(), v32.view(), dx, dy).unwrap();
    let errs = compare(&dec, &dir, 1e-12);
    eprintln!("{name}: FFT vs reference {errs:?}");
    let dec64 = hhd.decompose(u64_.view(), v64.view(), dx, dy).unwrap();
    assert_eq!(dec64, dec);
    let oracle = direct::decompose(u32_.view(), v32.view(), dx, dy).unwrap();
    let errs = compare(&oracle, &dir, 1e-12);
    eprintln!("{name}: direct vs reference {errs:?}");
}

#[test]
fn analytic_17x23_unequal_spacing() {
    run_case("analytic_17x23");
}

#[test]
fn press_32x32() {
    run_case("press_32x32");
    // A press spreads markers outward: D is lowest at the centre.
    let d = read_npy_f64(&fixture_dir("press_32x32").join("D.npy"));
    let mut best = ((0, 0), f64::INFINITY);
    for (i, &x) in d.indexed_iter() {
        if x < best.1 {
            best = (i, x);
        }
    }
    let (r, c) = best.0;
    assert!(
        (15..=16).contains(&r) && (15..=16).contains(&c),
        "{:?}",
        best.0
    );
}

#[test]
fn random_12x40_wide_spacing_ratio() {
    run_case("random_12x40");
}
