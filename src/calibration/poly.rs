//! Multivariate polynomials: terms, evaluation, least-squares fitting, order search.
//!
//! The calibration maps of the paper (docs/pipeline.md, steps 8-9) are polynomials of a
//! few named variables whose orders are chosen per *group* of variables: the
//! force maps `gx, gy, gz` take the displacements `{dx, dy, dz}` up to one order,
//! the image location `{x2d, y2d}` up to another and `{d_pf}` up to a third.
//!
//! - [`PolySpec`] says which terms a polynomial has: its [`VarGroup`]s, each with
//!   a maximum order (the total degree of a term in that group's variables), and
//!   a [`CrossTerms`] rule limiting terms that mix groups.
//! - [`Polynomial`] holds the variables, the exponent list, the coefficients and
//!   the input normalization it was fitted with, so evaluating it needs nothing
//!   else. Evaluation precomputes the powers of each input on the stack: no
//!   allocation per call.
//! - [`fit`] solves the least-squares problem in f64 (inputs normalized to
//!   `[-1, 1]`, columns scaled to unit norm, SVD) and reports the numerical rank.
//! - [`search_orders`] fits every combination of group orders `1..=max` on the
//!   training data, keeps the one with the lowest validation MAE and reports the
//!   test MAE (the paper's characterization protocol), in parallel with rayon.
//!
//! ```
//! use ndarray::array;
//! use optical_tactile::calibration::poly::{fit, CrossTerms, LeastSquares, PolySpec, VarGroup};
//!
//! // y = 1 + 2x - 3x^2, fitted with a single group of order 2.
//! let spec = PolySpec::new(vec![VarGroup::new("x", &["x"], 2)], CrossTerms::MaxOfGroups)?;
//! let x = array![[-1.0], [0.0], [0.5], [1.0], [2.0]];
//! let y = x.column(0).mapv(|x| 1.0 + 2.0 * x - 3.0 * x * x);
//! let (p, stats) = fit(&spec, x.view(), y.view(), &LeastSquares::default())?;
//! assert_eq!(stats.rank, 3);
//! assert!((p.evaluate(&[3.0])? - (1.0 + 6.0 - 27.0)).abs() < 1e-9);
//! # Ok::<(), optical_tactile::Error>(())
//! ```

use std::fmt::Write as _;

use nalgebra::DMatrix;
use ndarray::{Array1, ArrayView1, ArrayView2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Largest order a group may have. Calibration maps use orders up to ~6; this
/// bound only keeps term counts and power tables small.
pub const MAX_ORDER: u32 = 16;

/// Largest number of variables of one polynomial.
pub const MAX_VARIABLES: usize = 16;

/// Largest number of terms a [`PolySpec`] may generate.
pub const MAX_TERMS: usize = 5000;

/// Size of the stack power table used by evaluation: the sum over variables of
/// (highest exponent + 1) must not exceed it. With [`MAX_VARIABLES`] variables
/// of exponent up to [`MAX_ORDER`] that is 16 * 17 = 272.
const POW_TABLE: usize = MAX_VARIABLES * (MAX_ORDER as usize + 1);

/// A group of variables sharing one maximum order.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct VarGroup {
    /// Name of the group (e.g. `"displacement"`), used in reports.
    pub name: String,
    /// Names of the variables in the group, in the order they are passed to
    /// evaluation (after the variables of the groups before this one).
    pub variables: Vec<String>,
    /// Maximum total degree of a term in this group's variables. In an order
    /// search it is the largest candidate; `0` keeps the group out of every
    /// term (only the constant in these variables).
    pub max_order: u32,
    /// Whether an order search ([`candidate_orders`]) also tries leaving the
    /// group out (order 0) besides `1..=max_order`. `false` (older files):
    /// `1..=max_order` only.
    ///
    /// Why: for a refinement that not every dataset supports. On the strip
    /// the shear ratio in `g1` takes out the pull of a tangential load on
    /// the contact column; on a sensor whose patches are wide and noisy
    /// (a stiff, thin gel seen with the `low` thresholds) the ratio itself
    /// is noise, and with it the location map read the test points 2.62 mm
    /// off against 0.59 mm without it.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub optional: bool,
}

impl VarGroup {
    /// A group named `name` over `variables` with maximum order `max_order`.
    pub fn new(name: &str, variables: &[&str], max_order: u32) -> Self {
        VarGroup {
            name: name.to_string(),
            variables: variables.iter().map(|v| v.to_string()).collect(),
            max_order,
            optional: false,
        }
    }

    /// The group, which an order search may also leave out
    /// ([`VarGroup::optional`]).
    pub fn or_none(mut self) -> Self {
        self.optional = true;
        self
    }
}

/// How terms that mix variables of different groups are limited.
///
/// Within a group, a term's degree in that group's variables never exceeds the
/// group's order. This rule adds a limit on the term's *total* degree.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CrossTerms {
    /// No cross terms: every term involves the variables of one group only.
    None,
    /// A term's total degree is at most the largest order among the groups it
    /// involves (e.g. displacement order 3, location order 1: `dx^2 * x2d` is
    /// allowed, `dx^3 * x2d` is not). The default: it keeps cross terms but
    /// grows the term count like a single polynomial of the largest order.
    MaxOfGroups,
    /// A term's total degree is at most this number.
    Total(u32),
    /// Only the per-group limits: the full tensor product of the groups'
    /// polynomial spaces (the largest basis, grows fastest).
    Full,
    /// Terms within one group are limited by that group's order only; terms
    /// mixing groups have a total degree of at most this number. For a map
    /// that is mainly a function of one variable with small corrections in
    /// another (`g1(x2d, shear)`: `x2d^5` but only `shear * x2d`), where
    /// `MaxOfGroups` would add `shear * x2d^4` and overfit.
    Mixed(u32),
}

/// Which terms a polynomial has: its variable groups and the cross-term rule.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PolySpec {
    /// The groups, in variable order.
    pub groups: Vec<VarGroup>,
    /// How terms mixing groups are limited.
    pub cross: CrossTerms,
}

impl PolySpec {
    /// A checked spec: at least one group, every group with at least one
    /// variable, variable names unique and non-empty, orders at most
    /// [`MAX_ORDER`], at most [`MAX_VARIABLES`] variables and [`MAX_TERMS`] terms.
    pub fn new(groups: Vec<VarGroup>, cross: CrossTerms) -> Result<Self> {
        let spec = PolySpec { groups, cross };
        spec.validate()?;
        Ok(spec)
    }

    /// A spec with a single variable `name` of maximum order `order`.
    pub fn single(name: &str, order: u32) -> Result<Self> {
        PolySpec::new(
            vec![VarGroup::new(name, &[name], order)],
            CrossTerms::MaxOfGroups,
        )
    }

    fn validate(&self) -> Result<()> {
        if self.groups.is_empty() {
            return Err(Error::param(
                "groups",
                "a polynomial needs at least one group",
            ));
        }
        let mut names: Vec<&str> = Vec::new();
        for g in &self.groups {
            if g.variables.is_empty() {
                return Err(Error::param(
                    "groups",
                    format!("group `{}` has no variable", g.name),
                ));
            }
            if g.max_order > MAX_ORDER {
                return Err(Error::param(
                    "max_order",
                    format!(
                        "group `{}` has order {}, at most {MAX_ORDER} is supported",
                        g.name, g.max_order
                    ),
                ));
            }
            for v in &g.variables {
                if v.is_empty() {
                    return Err(Error::param("variables", "a variable name is empty"));
                }
                if names.contains(&v.as_str()) {
                    return Err(Error::param(
                        "variables",
                        format!("variable `{v}` appears twice"),
                    ));
                }
                names.push(v);
            }
        }
        if names.len() > MAX_VARIABLES {
            return Err(Error::param(
                "variables",
                format!(
                    "{} variables, at most {MAX_VARIABLES} are supported",
                    names.len()
                ),
            ));
        }
        if let CrossTerms::Total(n) | CrossTerms::Mixed(n) = self.cross
            && n > MAX_ORDER
        {
            return Err(Error::param(
                "cross",
                format!("total order {n}, at most {MAX_ORDER} is supported"),
            ));
        }
        // Counting walks every combination of group degrees: bound it first.
        let combos = self
            .groups
            .iter()
            .fold(1u64, |a, g| a.saturating_mul(u64::from(g.max_order) + 1));
        if combos > 1_000_000 {
            return Err(Error::param(
                "orders",
                format!("{combos} combinations of group degrees; use fewer groups or lower orders"),
            ));
        }
        let n = self.count_terms();
        if n > MAX_TERMS {
            return Err(Error::param(
                "orders",
                format!("the spec generates {n} terms, at most {MAX_TERMS} are supported"),
            ));
        }
        Ok(())
    }

    /// All variable names, group after group.
    pub fn variables(&self) -> Vec<String> {
        self.groups
            .iter()
            .flat_map(|g| g.variables.iter().cloned())
            .collect()
    }

    /// Number of variables.
    pub fn n_variables(&self) -> usize {
        self.groups.iter().map(|g| g.variables.len()).sum()
    }

    /// The maximum order of every group, in group order.
    pub fn orders(&self) -> Vec<u32> {
        self.groups.iter().map(|g| g.max_order).collect()
    }

    /// The same groups with other orders (one per group).
    pub fn with_orders(&self, orders: &[u32]) -> Result<Self> {
        if orders.len() != self.groups.len() {
            return Err(Error::param(
                "orders",
                format!(
                    "{} orders given for {} groups",
                    orders.len(),
                    self.groups.len()
                ),
            ));
        }
        let mut s = self.clone();
        for (g, &o) in s.groups.iter_mut().zip(orders) {
            g.max_order = o;
        }
        s.validate()?;
        Ok(s)
    }

    /// Whether a term whose degree in each group is `group_deg` is allowed.
    fn allows(&self, group_deg: &[u32]) -> bool {
        let total: u32 = group_deg.iter().sum();
        let involved = || {
            self.groups
                .iter()
                .zip(group_deg)
                .filter(|&(_, &d)| d > 0)
                .map(|(g, _)| g.max_order)
        };
        if self
            .groups
            .iter()
            .zip(group_deg)
            .any(|(g, &d)| d > g.max_order)
        {
            return false;
        }
        match self.cross {
            CrossTerms::None => group_deg.iter().filter(|&&d| d > 0).count() <= 1,
            CrossTerms::MaxOfGroups => total <= involved().max().unwrap_or(0),
            CrossTerms::Total(n) => total <= n,
            CrossTerms::Full => true,
            CrossTerms::Mixed(n) => group_deg.iter().filter(|&&d| d > 0).count() <= 1 || total <= n,
        }
    }

    /// Counts the terms without materializing them (cheap guard against
    /// explosive specs).
    fn count_terms(&self) -> usize {
        // Number of monomials of degree exactly d in k variables: C(d+k-1, k-1).
        fn exact(d: u32, k: usize) -> usize {
            let (mut num, mut den) = (1u128, 1u128);
            for i in 1..k as u128 {
                num *= d as u128 + i;
                den *= i;
            }
            (num / den).min(usize::MAX as u128) as usize
        }
        let mut degs = vec![0u32; self.groups.len()];
        let mut count = 0usize;
        loop {
            if self.allows(&degs) {
                let mut c = 1usize;
                for (g, &d) in self.groups.iter().zip(&degs) {
                    c = c.saturating_mul(exact(d, g.variables.len()));
                }
                count = count.saturating_add(c);
            }
            // Odometer over group degrees 0..=max_order.
            let mut i = 0;
            loop {
                if i == degs.len() {
                    return count;
                }
                if degs[i] < self.groups[i].max_order {
                    degs[i] += 1;
                    break;
                }
                degs[i] = 0;
                i += 1;
            }
        }
    }

    /// The exponent rows of the spec's terms, one row per term with one
    /// exponent per variable. Order: ascending total degree, then descending
    /// lexicographic on the exponents (constant, `x1`, `x2`, ..., `x1^2`,
    /// `x1 x2`, ...), so the list is deterministic. Errors if the spec is
    /// invalid (see [`PolySpec::new`]; the fields are public, so a spec may
    /// have been built without it).
    pub fn terms(&self) -> Result<Vec<Vec<u32>>> {
        self.validate()?;
        // Per group: every exponent tuple of total degree <= max_order.
        fn tuples(k: usize, max: u32) -> Vec<Vec<u32>> {
            let mut out = Vec::new();
            let mut cur = vec![0u32; k];
            fn rec(i: usize, left: u32, cur: &mut Vec<u32>, out: &mut Vec<Vec<u32>>) {
                if i == cur.len() {
                    out.push(cur.clone());
                    return;
                }
                for e in 0..=left {
                    cur[i] = e;
                    rec(i + 1, left - e, cur, out);
                }
                cur[i] = 0;
            }
            rec(0, max, &mut cur, &mut out);
            out
        }
        let per_group: Vec<Vec<Vec<u32>>> = self
            .groups
            .iter()
            .map(|g| tuples(g.variables.len(), g.max_order))
            .collect();
        let mut out: Vec<Vec<u32>> = vec![Vec::new()];
        let mut degs_out: Vec<Vec<u32>> = vec![Vec::new()];
        for tuples in &per_group {
            let mut next = Vec::with_capacity(out.len() * tuples.len());
            let mut next_degs = Vec::with_capacity(out.len() * tuples.len());
            for (row, degs) in out.iter().zip(&degs_out) {
                for t in tuples {
                    let mut r = row.clone();
                    r.extend_from_slice(t);
                    let mut d = degs.clone();
                    d.push(t.iter().sum());
                    next.push(r);
                    next_degs.push(d);
                }
            }
            out = next;
            degs_out = next_degs;
        }
        let mut terms: Vec<Vec<u32>> = out
            .into_iter()
            .zip(degs_out)
            .filter(|(_, d)| {
                // Pad the degree vector conceptually: all groups are present.
                self.allows(d)
            })
            .map(|(r, _)| r)
            .collect();
        terms.sort_by(|a, b| {
            let da: u32 = a.iter().sum();
            let db: u32 = b.iter().sum();
            da.cmp(&db).then_with(|| b.cmp(a))
        });
        Ok(terms)
    }

    /// Number of terms (errors like [`PolySpec::terms`]).
    pub fn n_terms(&self) -> Result<usize> {
        self.validate()?;
        Ok(self.count_terms())
    }
}

/// A multivariate polynomial over named variables, with the input
/// normalization it was fitted with:
///
/// `p(x) = sum_k c_k * prod_j t_j^e_kj`, with `t_j = (x_j - shift_j) / scale_j`.
///
/// Built by [`fit`] or [`Polynomial::new`]; serialized (serde) as its
/// variables, `input_shift`, `input_scale`, `exponents` (one row per term) and
/// `coefficients`. Floating-point numbers are written as strings holding the
/// shortest decimal that reads back to the same `f64`, so a JSON round trip is
/// bit-exact; plain JSON numbers are accepted when reading.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "PolynomialRepr", into = "PolynomialRepr")]
pub struct Polynomial {
    variables: Vec<String>,
    /// Row-major, `n_terms x n_variables`.
    exponents: Vec<u32>,
    coefficients: Vec<f64>,
    shift: Vec<f64>,
    scale: Vec<f64>,
    /// Derived: start of each variable's powers in the power table.
    pow_offset: Vec<usize>,
    /// Derived: highest exponent of each variable.
    max_exp: Vec<u32>,
    /// Derived: used length of the power table.
    pow_len: usize,
    /// Derived: for every term, the power-table indices of its non-zero
    /// factors, `width` per term, padded with index 0 (which always holds
    /// `t_0^0 = 1`, so padding multiplies by exactly 1 and changes no bit).
    /// A fixed width lets evaluation run a branch-free loop per term.
    factors: Vec<u16>,
    /// Derived: factors per term (at least 1).
    width: usize,
}

impl Polynomial {
    /// A polynomial from its parts. `exponents` has one row per term with one
    /// exponent per variable; `shift` and `scale` are the input normalization
    /// (use [`Polynomial::raw`] for none). Errors if the shapes disagree, a
    /// number is not finite, a scale is not positive, or an exponent exceeds
    /// [`MAX_ORDER`].
    pub fn new(
        variables: Vec<String>,
        exponents: Vec<Vec<u32>>,
        coefficients: Vec<f64>,
        shift: Vec<f64>,
        scale: Vec<f64>,
    ) -> Result<Self> {
        Self::build(variables, exponents, coefficients, shift, scale)
            .map_err(|m| Error::param("polynomial", m))
    }

    /// A polynomial in the raw variables (shift 0, scale 1).
    pub fn raw(
        variables: &[&str],
        exponents: Vec<Vec<u32>>,
        coefficients: Vec<f64>,
    ) -> Result<Self> {
        let n = variables.len();
        Self::new(
            variables.iter().map(|s| s.to_string()).collect(),
            exponents,
            coefficients,
            vec![0.0; n],
            vec![1.0; n],
        )
    }

    /// Shared validation of [`Polynomial::new`] and deserialization; the error
    /// is a plain message so that serde can attach the file position.
    fn build(
        variables: Vec<String>,
        exponents: Vec<Vec<u32>>,
        coefficients: Vec<f64>,
        shift: Vec<f64>,
        scale: Vec<f64>,
    ) -> std::result::Result<Self, String> {
        let nv = variables.len();
        if nv == 0 {
            return Err("a polynomial needs at least one variable".into());
        }
        if nv > MAX_VARIABLES {
            return Err(format!(
                "{nv} variables, at most {MAX_VARIABLES} are supported"
            ));
        }
        for (i, v) in variables.iter().enumerate() {
            if variables[..i].contains(v) {
                return Err(format!("variable `{v}` appears twice"));
            }
        }
        if exponents.len() != coefficients.len() {
            return Err(format!(
                "{} exponent rows but {} coefficients",
                exponents.len(),
                coefficients.len()
            ));
        }
        if shift.len() != nv || scale.len() != nv {
            return Err(format!(
                "{nv} variables but {} input_shift and {} input_scale values",
                shift.len(),
                scale.len()
            ));
        }
        for (k, row) in exponents.iter().enumerate() {
            if row.len() != nv {
                return Err(format!(
                    "exponent row {k} has {} entries but there are {nv} variables",
                    row.len()
                ));
            }
            if let Some(&e) = row.iter().find(|&&e| e > MAX_ORDER) {
                return Err(format!(
                    "exponent row {k} has exponent {e}, at most {MAX_ORDER} is supported"
                ));
            }
        }
        if let Some(k) = coefficients.iter().position(|c| !c.is_finite()) {
            return Err(format!("coefficient {k} is not finite"));
        }
        if let Some(j) = shift.iter().position(|c| !c.is_finite()) {
            return Err(format!("input_shift of `{}` is not finite", variables[j]));
        }
        if let Some(j) = scale.iter().position(|c| !(c.is_finite() && *c > 0.0)) {
            return Err(format!(
                "input_scale of `{}` must be finite and positive, got {}",
                variables[j], scale[j]
            ));
        }
        let mut max_exp = vec![0u32; nv];
        for row in &exponents {
            for (m, &e) in max_exp.iter_mut().zip(row) {
                *m = (*m).max(e);
            }
        }
        let mut pow_offset = Vec::with_capacity(nv);
        let mut off = 0usize;
        for &m in &max_exp {
            pow_offset.push(off);
            off += m as usize + 1;
        }
        debug_assert!(off <= POW_TABLE);
        let width = exponents
            .iter()
            .map(|row| row.iter().filter(|&&e| e > 0).count())
            .max()
            .unwrap_or(0)
            .max(1);
        let mut factors = Vec::with_capacity(exponents.len() * width);
        for row in &exponents {
            let start = factors.len();
            for (j, &e) in row.iter().enumerate() {
                if e > 0 {
                    factors.push((pow_offset[j] + e as usize) as u16);
                }
            }
            factors.resize(start + width, 0);
        }
        Ok(Polynomial {
            variables,
            exponents: exponents.into_iter().flatten().collect(),
            coefficients,
            shift,
            scale,
            pow_offset,
            max_exp,
            pow_len: off,
            factors,
            width,
        })
    }

    /// The variable names, in evaluation order.
    pub fn variables(&self) -> &[String] {
        &self.variables
    }

    /// Number of variables.
    pub fn n_variables(&self) -> usize {
        self.variables.len()
    }

    /// Number of terms.
    pub fn n_terms(&self) -> usize {
        self.coefficients.len()
    }

    /// The exponents of term `k` (one per variable).
    pub fn exponents(&self, k: usize) -> &[u32] {
        let n = self.variables.len();
        &self.exponents[k * n..(k + 1) * n]
    }

    /// The largest exponent of variable `j` over the terms (0: the
    /// polynomial does not depend on it). Panics if `j` is not a variable
    /// index, like slice indexing.
    pub fn max_exponent(&self, j: usize) -> u32 {
        self.max_exp[j]
    }

    /// The coefficients, in the normalized variables `t_j`.
    pub fn coefficients(&self) -> &[f64] {
        &self.coefficients
    }

    /// The input shifts (`t_j = (x_j - shift_j) / scale_j`).
    pub fn input_shift(&self) -> &[f64] {
        &self.shift
    }

    /// The input scales (`t_j = (x_j - shift_j) / scale_j`).
    pub fn input_scale(&self) -> &[f64] {
        &self.scale
    }

    /// Highest total degree of a term.
    pub fn degree(&self) -> u32 {
        (0..self.n_terms())
            .map(|k| self.exponents(k).iter().sum())
            .max()
            .unwrap_or(0)
    }

    /// Fills the power table: `pow[off_j + e] = t_j^e`.
    #[inline]
    fn powers(&self, x: &[f64], pow: &mut [f64]) {
        for j in 0..x.len() {
            let t = (x[j] - self.shift[j]) / self.scale[j];
            let base = self.pow_offset[j];
            pow[base] = 1.0;
            let mut acc = 1.0;
            for e in 1..=self.max_exp[j] as usize {
                acc *= t;
                pow[base + e] = acc;
            }
        }
    }

    /// Sum of the terms, powers already in the table. Dispatches to a loop
    /// specialized for the factor width (the calibration maps have 1-3).
    #[inline]
    fn sum_terms(&self, pow: &[f64]) -> f64 {
        match self.width {
            1 => self.sum_fixed::<1>(pow),
            2 => self.sum_fixed::<2>(pow),
            3 => self.sum_fixed::<3>(pow),
            4 => self.sum_fixed::<4>(pow),
            w => {
                let mut sum = 0.0;
                for (&c, f) in self.coefficients.iter().zip(self.factors.chunks_exact(w)) {
                    let mut p = c;
                    for &i in f {
                        p *= pow[i as usize];
                    }
                    sum += p;
                }
                sum
            }
        }
    }

    #[inline]
    fn sum_fixed<const W: usize>(&self, pow: &[f64]) -> f64 {
        let mut sum = 0.0;
        for (&c, f) in self.coefficients.iter().zip(self.factors.chunks_exact(W)) {
            let mut p = c;
            for &i in f {
                p *= pow[i as usize];
            }
            sum += p;
        }
        sum
    }

    /// Checks one input row: right length, finite values.
    fn check_input(&self, x: &[f64], row: usize) -> Result<()> {
        if x.len() != self.variables.len() {
            return Err(Error::param(
                "polynomial input",
                format!(
                    "{} values given, the polynomial has {} variables ({})",
                    x.len(),
                    self.variables.len(),
                    self.variables.join(", ")
                ),
            ));
        }
        if let Some(col) = x.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                what: format!("polynomial input `{}`", self.variables[col]),
                row,
                col,
            });
        }
        Ok(())
    }

    /// The value at `x` (one value per variable, in [`Polynomial::variables`]
    /// order). Allocation-free. Errors on a wrong length or non-finite input.
    #[inline]
    pub fn evaluate(&self, x: &[f64]) -> Result<f64> {
        self.check_input(x, 0)?;
        // The table lives on the stack; its size is picked so that the common
        // small maps do not pay for zeroing the largest possible table.
        Ok(match self.pow_len {
            0..=32 => self.eval_with::<32>(x),
            33..=96 => self.eval_with::<96>(x),
            _ => self.eval_with::<POW_TABLE>(x),
        })
    }

    #[inline]
    fn eval_with<const N: usize>(&self, x: &[f64]) -> f64 {
        let mut pow = [0.0f64; N];
        self.powers(x, &mut pow);
        self.sum_terms(&pow)
    }

    /// Evaluates every row of `x` (`rows x n_variables`) into `out`.
    pub fn evaluate_rows_into(&self, x: ArrayView2<f64>, out: &mut [f64]) -> Result<()> {
        let (rows, cols) = x.dim();
        if cols != self.variables.len() {
            return Err(Error::shape(
                "polynomial inputs (variables x rows)",
                (self.variables.len(), rows),
                (cols, rows),
            ));
        }
        if out.len() != rows {
            return Err(Error::shape("polynomial output", (1, rows), (1, out.len())));
        }
        let mut pow = [0.0f64; POW_TABLE];
        let mut buf = [0.0f64; MAX_VARIABLES];
        for (i, (row, o)) in x.outer_iter().zip(out.iter_mut()).enumerate() {
            for (b, &v) in buf.iter_mut().zip(row.iter()) {
                *b = v;
            }
            let xr = &buf[..cols];
            self.check_input(xr, i)?;
            self.powers(xr, &mut pow);
            *o = self.sum_terms(&pow);
        }
        Ok(())
    }

    /// Evaluates every row of `x` (`rows x n_variables`).
    pub fn evaluate_rows(&self, x: ArrayView2<f64>) -> Result<Array1<f64>> {
        let mut out = Array1::zeros(x.nrows());
        self.evaluate_rows_into(x, out.as_slice_mut().expect("a fresh Array1 is contiguous"))?;
        Ok(out)
    }

    /// A readable form, e.g. `1.5 + 2*t(x) - 0.25*t(x)^2` where `t(x)` is the
    /// normalized variable (see the type's docs).
    pub fn to_formula(&self) -> String {
        let mut s = String::new();
        for k in 0..self.n_terms() {
            let c = self.coefficients[k];
            if k == 0 {
                let _ = write!(s, "{c}");
            } else if c < 0.0 {
                let _ = write!(s, " - {}", -c);
            } else {
                let _ = write!(s, " + {c}");
            }
            for (j, &e) in self.exponents(k).iter().enumerate() {
                match e {
                    0 => {}
                    1 => {
                        let _ = write!(s, "*t({})", self.variables[j]);
                    }
                    _ => {
                        let _ = write!(s, "*t({})^{e}", self.variables[j]);
                    }
                }
            }
        }
        s
    }
}

/// The serialized form of a [`Polynomial`].
#[derive(Serialize, Deserialize)]
struct PolynomialRepr {
    variables: Vec<String>,
    #[serde(with = "exact_f64")]
    input_shift: Vec<f64>,
    #[serde(with = "exact_f64")]
    input_scale: Vec<f64>,
    exponents: Vec<Vec<u32>>,
    #[serde(with = "exact_f64")]
    coefficients: Vec<f64>,
}

impl TryFrom<PolynomialRepr> for Polynomial {
    type Error = String;
    fn try_from(r: PolynomialRepr) -> std::result::Result<Self, String> {
        Polynomial::build(
            r.variables,
            r.exponents,
            r.coefficients,
            r.input_shift,
            r.input_scale,
        )
    }
}

impl From<Polynomial> for PolynomialRepr {
    fn from(p: Polynomial) -> Self {
        let n = p.variables.len();
        PolynomialRepr {
            exponents: p.exponents.chunks(n).map(|c| c.to_vec()).collect(),
            variables: p.variables,
            input_shift: p.shift,
            input_scale: p.scale,
            coefficients: p.coefficients,
        }
    }
}

/// `f64` lists written as strings of the shortest round-tripping decimal.
///
/// Why: serde_json without its `float_roundtrip` feature parses some decimals
/// one ulp off, so numbers would not survive a save/load bit-exactly; Rust's own
/// `str::parse::<f64>` is correctly rounded. Reading accepts numbers too, for
/// hand-written files.
pub(crate) mod exact_f64 {
    use serde::de::{self, SeqAccess, Visitor};
    use serde::ser::SerializeSeq;
    use serde::{Deserializer, Serializer};
    use std::fmt;

    /// Shortest decimal that parses back to `x` (plain for moderate magnitudes,
    /// scientific otherwise so tiny values do not print hundreds of zeros).
    pub(crate) fn to_text(x: f64) -> String {
        let a = x.abs();
        if x == 0.0 || (1e-5..1e16).contains(&a) {
            format!("{x:?}")
        } else {
            format!("{x:e}")
        }
    }

    pub(crate) fn serialize<S: Serializer>(v: &[f64], s: S) -> Result<S::Ok, S::Error> {
        let mut seq = s.serialize_seq(Some(v.len()))?;
        for &x in v {
            seq.serialize_element(&to_text(x))?;
        }
        seq.end()
    }

    struct Num(f64);
    impl<'de> de::Deserialize<'de> for Num {
        fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
            struct V;
            impl Visitor<'_> for V {
                type Value = Num;
                fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                    f.write_str("a number or a string holding a decimal number")
                }
                fn visit_f64<E: de::Error>(self, v: f64) -> Result<Num, E> {
                    Ok(Num(v))
                }
                fn visit_i64<E: de::Error>(self, v: i64) -> Result<Num, E> {
                    Ok(Num(v as f64))
                }
                fn visit_u64<E: de::Error>(self, v: u64) -> Result<Num, E> {
                    Ok(Num(v as f64))
                }
                fn visit_str<E: de::Error>(self, v: &str) -> Result<Num, E> {
                    let x: f64 = v
                        .trim()
                        .parse()
                        .map_err(|_| E::custom(format!("`{v}` is not a decimal number")))?;
                    if !x.is_finite() {
                        return Err(E::custom(format!("`{v}` is not a finite number")));
                    }
                    Ok(Num(x))
                }
            }
            d.deserialize_any(V)
        }
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Vec<f64>;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a list of numbers")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut a: A) -> Result<Vec<f64>, A::Error> {
                let mut out = Vec::with_capacity(a.size_hint().unwrap_or(0));
                while let Some(Num(x)) = a.next_element()? {
                    out.push(x);
                }
                Ok(out)
            }
        }
        d.deserialize_seq(V)
    }
}

/// Options of [`fit`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LeastSquares {
    /// Normalize every input to `[-1, 1]` over the training data (stored in
    /// the polynomial). On by default: it keeps high powers of large pixel
    /// coordinates from ruining the conditioning. Off: coefficients are in the
    /// raw variables.
    pub normalize: bool,
    /// Singular values below `rcond * largest` count as zero (numerical rank).
    pub rcond: f64,
    /// Accept a rank-deficient design (e.g. a variable that is constant in the
    /// data) and return the minimum-norm solution; if false it is an error.
    pub allow_rank_deficient: bool,
    /// Robust fitting: `Some(k)` down-weights residuals beyond `k` robust
    /// standard deviations (Huber loss, iteratively reweighted least squares;
    /// 1.345 is the classic choice). `None` (default): plain least squares, as
    /// the paper. Helps when a few samples are gross outliers (a mis-detected
    /// contact), at the cost of one SVD per iteration.
    #[serde(default)]
    pub huber: Option<f64>,
    /// Largest number of reweighting iterations of the robust fit.
    #[serde(default = "default_irls_iterations")]
    pub irls_iterations: u32,
}

fn default_irls_iterations() -> u32 {
    30
}

impl Default for LeastSquares {
    fn default() -> Self {
        LeastSquares {
            normalize: true,
            rcond: 1e-10,
            allow_rank_deficient: false,
            huber: None,
            irls_iterations: default_irls_iterations(),
        }
    }
}

/// What one least-squares fit reached.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitStats {
    /// Number of data rows.
    pub n_rows: usize,
    /// Number of terms (unknowns).
    pub n_terms: usize,
    /// Numerical rank of the (column-scaled) design matrix.
    pub rank: usize,
    /// Ratio of the largest to the smallest kept singular value.
    pub condition: f64,
    /// Mean absolute residual on the fitted data.
    pub train_mae: f64,
    /// Root-mean-square residual on the fitted data.
    pub train_rmse: f64,
}

/// Checks that `x` has `n_vars` columns, as many rows as `y`, and only finite
/// values.
fn check_data(x: ArrayView2<f64>, y: ArrayView1<f64>, n_vars: usize, what: &str) -> Result<()> {
    let (rows, cols) = x.dim();
    if cols != n_vars {
        return Err(Error::shape(
            format!("{what} inputs (variables x rows)"),
            (n_vars, rows),
            (cols, rows),
        ));
    }
    if y.len() != rows {
        return Err(Error::shape(
            format!("{what} targets (1 x rows)"),
            (1, rows),
            (1, y.len()),
        ));
    }
    for ((row, col), v) in x.indexed_iter() {
        if !v.is_finite() {
            return Err(Error::NonFinite {
                what: format!("{what} inputs"),
                row,
                col,
            });
        }
    }
    if let Some(row) = y.iter().position(|v| !v.is_finite()) {
        return Err(Error::NonFinite {
            what: format!("{what} targets"),
            row,
            col: 0,
        });
    }
    Ok(())
}

/// Fits the polynomial of `spec` to `y ≈ p(x)` by least squares.
///
/// `x` has one row per sample and one column per variable (in
/// [`PolySpec::variables`] order). Inputs are normalized (see
/// [`LeastSquares::normalize`]), the design matrix's columns scaled to unit
/// norm and the problem solved by SVD in f64.
///
/// Errors: fewer rows than terms ([`Error::Numerical`], saying how many are
/// needed), mismatched shapes, non-finite data, a rank-deficient design unless
/// allowed (the rank is always in [`FitStats::rank`]).
pub fn fit(
    spec: &PolySpec,
    x: ArrayView2<f64>,
    y: ArrayView1<f64>,
    options: &LeastSquares,
) -> Result<(Polynomial, FitStats)> {
    spec.validate()?;
    if let Some(k) = options.huber
        && !(k.is_finite() && k > 0.0)
    {
        return Err(Error::param(
            "huber",
            format!("must be finite and > 0, got {k}"),
        ));
    }
    if !(options.rcond.is_finite() && options.rcond >= 0.0 && options.rcond < 1.0) {
        return Err(Error::param(
            "rcond",
            format!("must be in [0, 1), got {}", options.rcond),
        ));
    }
    let nv = spec.n_variables();
    check_data(x, y, nv, "fit")?;
    let terms = spec.terms()?;
    let (n, m) = (x.nrows(), terms.len());
    if n < m {
        return Err(Error::Numerical {
            what: "polynomial fit".into(),
            message: format!(
                "{m} terms (orders {:?}) need at least {m} samples, got {n}",
                spec.orders()
            ),
        });
    }
    // Normalization to [-1, 1]; a constant variable keeps scale 1 so its
    // normalized value is 0 and its columns vanish (reported as rank loss).
    let mut shift = vec![0.0; nv];
    let mut scale = vec![1.0; nv];
    if options.normalize {
        for j in 0..nv {
            let col = x.column(j);
            let lo = col.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = col.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            shift[j] = 0.5 * (lo + hi);
            let half = 0.5 * (hi - lo);
            scale[j] = if half > 0.0 && half.is_finite() {
                half
            } else {
                1.0
            };
        }
    }
    let unit = Polynomial::build(
        spec.variables(),
        terms.clone(),
        vec![1.0; m],
        shift.clone(),
        scale.clone(),
    )
    .map_err(|msg| Error::param("spec", msg))?;

    // Design matrix, from the same power table the evaluation uses so that fit
    // and evaluation see identical monomials.
    let mut a = DMatrix::<f64>::zeros(n, m);
    let mut pow = [0.0f64; POW_TABLE];
    let mut buf = [0.0f64; MAX_VARIABLES];
    for (i, row) in x.outer_iter().enumerate() {
        for (b, &v) in buf.iter_mut().zip(row.iter()) {
            *b = v;
        }
        unit.powers(&buf[..nv], &mut pow);
        for (k, f) in unit.factors.chunks_exact(unit.width).enumerate() {
            let mut p = 1.0;
            for &idx in f {
                p *= pow[idx as usize];
            }
            a[(i, k)] = p;
        }
    }
    let mut col_norm = vec![1.0; m];
    for k in 0..m {
        let nk = a.column(k).norm();
        if nk > 0.0 && nk.is_finite() {
            col_norm[k] = nk;
            a.column_mut(k).scale_mut(1.0 / nk);
        }
    }
    let b = nalgebra::DVector::from_iterator(n, y.iter().copied());
    let rank_error = |rank: usize| Error::Numerical {
        what: "polynomial fit".into(),
        message: format!(
            "rank-deficient design: rank {rank} for {m} terms (orders {:?}); a variable is \
             (nearly) constant or the samples do not vary enough for this order",
            spec.orders()
        ),
    };
    let mut sol = solve_scaled(&a, &b, options.rcond)?;
    if sol.rank < m && !options.allow_rank_deficient {
        return Err(rank_error(sol.rank));
    }
    if let Some(k) = options.huber {
        // Iteratively reweighted least squares with Huber weights: residuals
        // beyond k robust standard deviations (1.4826 * median |r|) get weight
        // k * sigma / |r|, so a few gross outliers cannot drag the fit.
        let mut z_prev = sol.z.clone();
        for _ in 0..options.irls_iterations {
            let r = &b - &a * &sol.z;
            let mut abs: Vec<f64> = r.iter().map(|v| v.abs()).collect();
            abs.sort_by(f64::total_cmp);
            let sigma = 1.4826 * abs[abs.len() / 2];
            if sigma <= f64::EPSILON * b.amax().max(1.0) {
                break; // (nearly) exact fit: nothing to down-weight
            }
            let w: Vec<f64> = r
                .iter()
                .map(|v| {
                    let t = v.abs() / (k * sigma);
                    if t <= 1.0 { 1.0 } else { (1.0 / t).sqrt() }
                })
                .collect();
            let mut aw = a.clone();
            for (i, wi) in w.iter().enumerate() {
                aw.row_mut(i).scale_mut(*wi);
            }
            let bw = nalgebra::DVector::from_iterator(n, b.iter().zip(&w).map(|(v, wi)| v * wi));
            sol = solve_scaled(&aw, &bw, options.rcond)?;
            if sol.rank < m && !options.allow_rank_deficient {
                return Err(rank_error(sol.rank));
            }
            let step = (&sol.z - &z_prev).amax();
            z_prev = sol.z.clone();
            if step <= 1e-12 * sol.z.amax().max(1e-300) {
                break;
            }
        }
    }
    let (z, rank, smax, smin_kept) = (sol.z, sol.rank, sol.smax, sol.smin_kept);
    let coefficients: Vec<f64> = (0..m).map(|k| z[k] / col_norm[k]).collect();
    if let Some(k) = coefficients.iter().position(|c| !c.is_finite()) {
        return Err(Error::Numerical {
            what: "polynomial fit".into(),
            message: format!("coefficient {k} came out non-finite"),
        });
    }
    let poly =
        Polynomial::build(spec.variables(), terms, coefficients, shift, scale).map_err(|msg| {
            Error::Numerical {
                what: "polynomial fit".into(),
                message: msg,
            }
        })?;
    let pred = poly.evaluate_rows(x)?;
    let (mut sa, mut sq) = (0.0, 0.0);
    for (p, t) in pred.iter().zip(y.iter()) {
        let r = p - t;
        sa += r.abs();
        sq += r * r;
    }
    let stats = FitStats {
        n_rows: n,
        n_terms: m,
        rank,
        condition: if rank > 0 {
            smax / smin_kept
        } else {
            f64::INFINITY
        },
        train_mae: sa / n as f64,
        train_rmse: (sq / n as f64).sqrt(),
    };
    Ok((poly, stats))
}

/// Solution of a column-scaled least-squares problem.
struct Solution {
    z: nalgebra::DVector<f64>,
    rank: usize,
    smax: f64,
    smin_kept: f64,
}

/// Minimum-norm least squares `a z ≈ b` by SVD, singular values below
/// `rcond * largest` dropped, plus one step of iterative refinement on the
/// residual (recovers the digits the SVD's rounding lost: exact data is then
/// fitted to ~1e-15).
fn solve_scaled(a: &DMatrix<f64>, b: &nalgebra::DVector<f64>, rcond: f64) -> Result<Solution> {
    let m = a.ncols();
    let svd =
        nalgebra::SVD::try_new(a.clone(), true, true, f64::EPSILON, 10_000).ok_or_else(|| {
            Error::Numerical {
                what: "polynomial fit".into(),
                message: "the SVD did not converge".into(),
            }
        })?;
    let s = &svd.singular_values;
    let smax = s.iter().copied().fold(0.0, f64::max);
    let tol = rcond * smax;
    let kept = |v: f64| v > tol && v > 0.0;
    let rank = s.iter().filter(|&&v| kept(v)).count();
    let smin_kept = s
        .iter()
        .copied()
        .filter(|&v| kept(v))
        .fold(f64::INFINITY, f64::min);
    let u = svd.u.as_ref().expect("U was requested");
    let v_t = svd.v_t.as_ref().expect("V^T was requested");
    let solve = |rhs: &nalgebra::DVector<f64>| {
        let utb = u.transpose() * rhs;
        let mut z = nalgebra::DVector::<f64>::zeros(m);
        for (i, &sv) in s.iter().enumerate() {
            if kept(sv) {
                z += v_t.row(i).transpose() * (utb[i] / sv);
            }
        }
        z
    };
    let mut z = solve(b);
    let r = b - a * &z;
    z += solve(&r);
    Ok(Solution {
        z,
        rank,
        smax,
        smin_kept,
    })
}

/// Mean absolute error of `p` on `(x, y)`.
pub fn mae(p: &Polynomial, x: ArrayView2<f64>, y: ArrayView1<f64>) -> Result<f64> {
    check_data(x, y, p.n_variables(), "evaluation")?;
    if y.is_empty() {
        return Err(Error::param("data", "no samples to measure an error on"));
    }
    let pred = p.evaluate_rows(x)?;
    Ok(pred.iter().zip(y).map(|(a, b)| (a - b).abs()).sum::<f64>() / y.len() as f64)
}

/// Inputs and targets of one data split.
#[derive(Clone, Copy, Debug)]
pub struct FitData<'a> {
    /// One row per sample, one column per variable.
    pub x: ArrayView2<'a, f64>,
    /// One target per sample.
    pub y: ArrayView1<'a, f64>,
}

impl<'a> FitData<'a> {
    /// Pairs inputs with targets (checked when used).
    pub fn new(x: ArrayView2<'a, f64>, y: ArrayView1<'a, f64>) -> Self {
        FitData { x, y }
    }
}

/// One candidate of an order search.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    /// The order of every group.
    pub orders: Vec<u32>,
    /// Number of terms.
    pub n_terms: usize,
    /// Numerical rank reached (absent if the fit failed).
    pub rank: Option<usize>,
    /// Training MAE (absent if the fit failed).
    pub train_mae: Option<f64>,
    /// Validation MAE (absent if the fit failed).
    pub val_mae: Option<f64>,
    /// Why the fit failed, if it did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// Result of an order search: the chosen orders and their errors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitReport {
    /// Group names, in order.
    pub groups: Vec<String>,
    /// Chosen order of every group.
    pub orders: Vec<u32>,
    /// Cross-term rule used.
    pub cross: CrossTerms,
    /// Number of terms of the chosen polynomial.
    pub n_terms: usize,
    /// Its numerical rank.
    pub rank: usize,
    /// Number of training samples.
    pub n_train: usize,
    /// Number of validation samples.
    pub n_val: usize,
    /// Number of test samples (0 without a test set).
    pub n_test: usize,
    /// Training MAE of the chosen polynomial.
    #[serde(deserialize_with = "nullable_f64")]
    pub train_mae: f64,
    /// Validation MAE (the selection criterion).
    #[serde(deserialize_with = "nullable_f64")]
    pub val_mae: f64,
    /// Test MAE, if a test set was given.
    pub test_mae: Option<f64>,
    /// Every candidate tried, in search order.
    pub candidates: Vec<Candidate>,
}

/// Reads an `f64` that may have been written as `null` (serde_json writes
/// NaN and infinities as `null`), so a saved report always loads back.
pub(crate) fn nullable_f64<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> std::result::Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// Every combination of group orders `1..=max_order` (`0..=max_order` for
/// an [optional](VarGroup::optional) group; a group of max order 0 stays at
/// 0), first group varying slowest.
pub fn candidate_orders(spec: &PolySpec) -> Vec<Vec<u32>> {
    let mut out: Vec<Vec<u32>> = vec![Vec::new()];
    for g in &spec.groups {
        let range: Vec<u32> = if g.max_order == 0 {
            vec![0]
        } else {
            (u32::from(!g.optional)..=g.max_order).collect()
        };
        out = out
            .iter()
            .flat_map(|p| {
                range.iter().map(move |&o| {
                    let mut q = p.clone();
                    q.push(o);
                    q
                })
            })
            .collect();
    }
    out
}

/// Relative tolerance under which two validation MAEs count as equal in
/// [`search_orders`] (relative to the mean |target| of the validation set).
pub const TIE_TOLERANCE: f64 = 1e-9;

/// The paper's order search: fits `spec` with every combination of group
/// orders ([`candidate_orders`]) on `train`, keeps the one with the lowest MAE on
/// `val` and reports its MAE on `test`. Ties (MAEs within [`TIE_TOLERANCE`]
/// times the mean |validation target|, i.e. equal up to rounding) go to the
/// candidate with fewer terms, then to the lower MAE, then to search order.
///
/// Candidates that cannot be fitted (too few samples, rank deficiency when not
/// allowed) are recorded in the report and skipped; if none can be fitted the
/// error of the smallest candidate is returned. Runs the candidates in
/// parallel; the result does not depend on the thread count.
pub fn search_orders(
    spec: &PolySpec,
    train: FitData,
    val: FitData,
    test: Option<FitData>,
    options: &LeastSquares,
) -> Result<(Polynomial, FitReport)> {
    spec.validate()?;
    let nv = spec.n_variables();
    check_data(train.x, train.y, nv, "training")?;
    check_data(val.x, val.y, nv, "validation")?;
    if val.y.is_empty() {
        return Err(Error::param(
            "validation",
            "the order search needs at least one validation sample",
        ));
    }
    if let Some(t) = test {
        check_data(t.x, t.y, nv, "test")?;
    }
    let orders = candidate_orders(spec);
    let results: Vec<(Candidate, Option<Polynomial>)> = orders
        .par_iter()
        .map(|o| {
            let s = match spec.with_orders(o) {
                Ok(s) => s,
                Err(e) => {
                    return (
                        Candidate {
                            orders: o.clone(),
                            n_terms: 0,
                            rank: None,
                            train_mae: None,
                            val_mae: None,
                            error: Some(e.to_string()),
                        },
                        None,
                    );
                }
            };
            let n_terms = s.count_terms();
            match fit(&s, train.x, train.y, options)
                .and_then(|(p, st)| Ok((mae(&p, val.x, val.y)?, p, st)))
            {
                Ok((v, p, st)) => (
                    Candidate {
                        orders: o.clone(),
                        n_terms,
                        rank: Some(st.rank),
                        train_mae: Some(st.train_mae),
                        val_mae: Some(v),
                        error: None,
                    },
                    Some(p),
                ),
                Err(e) => (
                    Candidate {
                        orders: o.clone(),
                        n_terms,
                        rank: None,
                        train_mae: None,
                        val_mae: None,
                        error: Some(e.to_string()),
                    },
                    None,
                ),
            }
        })
        .collect();
    let fitted: Vec<(usize, f64, usize)> = results
        .iter()
        .enumerate()
        .filter_map(|(i, (c, p))| p.as_ref().and(c.val_mae).map(|v| (i, v, c.n_terms)))
        .filter(|(_, v, _)| v.is_finite())
        .collect();
    // Validation MAEs that differ only by rounding (exactly representable
    // data: every order at or above the true one fits to ~1e-13) are ties,
    // resolved towards fewer terms; real data differ by far more.
    let y_scale = val.y.iter().map(|v| v.abs()).sum::<f64>() / val.y.len() as f64;
    let min_val = fitted.iter().map(|f| f.1).fold(f64::INFINITY, f64::min);
    let tie = min_val + TIE_TOLERANCE * y_scale.max(min_val);
    let best = fitted
        .into_iter()
        .filter(|f| f.1 <= tie)
        .min_by(|a, b| a.2.cmp(&b.2).then(a.1.total_cmp(&b.1)).then(a.0.cmp(&b.0)));
    let Some((bi, val_mae, _)) = best else {
        let first = results
            .iter()
            .min_by_key(|(c, _)| c.n_terms)
            .and_then(|(c, _)| c.error.clone())
            .unwrap_or_else(|| "no candidate".into());
        return Err(Error::Numerical {
            what: "order search".into(),
            message: format!("no candidate order could be fitted; smallest: {first}"),
        });
    };
    let poly = results[bi].1.clone().expect("best has a polynomial");
    let chosen = results[bi].0.clone();
    let test_mae = match test {
        Some(t) if !t.y.is_empty() => Some(mae(&poly, t.x, t.y)?),
        _ => None,
    };
    let report = FitReport {
        groups: spec.groups.iter().map(|g| g.name.clone()).collect(),
        orders: chosen.orders.clone(),
        cross: spec.cross,
        n_terms: chosen.n_terms,
        rank: chosen.rank.unwrap_or(0),
        n_train: train.y.len(),
        n_val: val.y.len(),
        n_test: test.map(|t| t.y.len()).unwrap_or(0),
        train_mae: chosen.train_mae.unwrap_or(f64::NAN),
        val_mae,
        test_mae,
        candidates: results.into_iter().map(|(c, _)| c).collect(),
    };
    Ok((poly, report))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn term_counts_match_enumeration() {
        let spec = PolySpec::new(
            vec![
                VarGroup::new("d", &["dx", "dy", "dz"], 3),
                VarGroup::new("loc", &["x", "y"], 2),
                VarGroup::new("p", &["pf"], 1),
            ],
            CrossTerms::MaxOfGroups,
        )
        .unwrap();
        for cross in [
            CrossTerms::None,
            CrossTerms::MaxOfGroups,
            CrossTerms::Total(2),
            CrossTerms::Full,
            CrossTerms::Mixed(2),
        ] {
            let s = PolySpec {
                cross,
                ..spec.clone()
            };
            assert_eq!(s.terms().unwrap().len(), s.n_terms().unwrap(), "{cross:?}");
        }
        // Full tensor product: C(6,3) * C(4,2) * C(2,1) = 20 * 6 * 2.
        let s = PolySpec {
            cross: CrossTerms::Full,
            ..spec.clone()
        };
        assert_eq!(s.n_terms().unwrap(), 240);
        // No cross terms: 1 + (20-1) + (6-1) + (2-1).
        let s = PolySpec {
            cross: CrossTerms::None,
            ..spec
        };
        assert_eq!(s.n_terms().unwrap(), 26);
    }

    #[test]
    fn exact_text_round_trips() {
        for x in [
            0.0,
            -0.0,
            1.0,
            0.1,
            1e-300,
            -2.5e-7,
            1e20,
            f64::MAX,
            f64::MIN_POSITIVE,
        ] {
            let t = exact_f64::to_text(x);
            assert_eq!(t.parse::<f64>().unwrap().to_bits(), x.to_bits(), "{t}");
        }
    }
}
