//! Linear-elastic response of the gel layer to surface loads
//! (Boussinesq and Cerruti, integrated over the footprint).
//!
//! Coordinates here are local to the unrolled skin: `x` along the arc (mm), `y`
//! across (mm), `z` depth into the gel (mm, `z > 0`). Loads are
//! `[f_x, f_y, f_n]` in N with `f_n` pressing *into* the gel; displacements are
//! `[u_x, u_y, u_z]` in mm with `u_z` into the gel.
//!
//! A rod contact is a uniform load along `y` (the rod spans the skin's width)
//! times an elliptical (Hertz) profile across it. The integral along the rod is
//! done in closed form (antiderivatives of the Boussinesq and Cerruti kernels in
//! `y`, listed below), which removes the `1/r` peak exactly; the remaining
//! integral across the rod has the elliptical weight `sqrt(1 - t^2)`, which
//! Gauss-Chebyshev quadrature of the second kind integrates without error for
//! the weight itself, with a node count adapted to how close the marker is.
//!
//! With `A = x^2 + z^2`, `r = sqrt(A + y^2)`, the antiderivatives used are
//! - `∫ dy/r = asinh(y/sqrt A)`, `∫ dy/r^3 = y/(A r)`, `∫ y dy/r^3 = -1/r`,
//! - `∫ y dy/(r (r+z)) = ln(r+z)`, `∫ y dy/(r (r+z)^2) = -1/(r+z)`,
//! - `J1 = ∫ dy/(r (r+z)) = (1/x) atan(x y (r-z) / (x^2 r + z y^2))`,
//! - `∫ x^2 dy/(r (r+z)^2) = y/(r+z) - z J1` and `∫ dy/(r+z) = asinh - z J1`,
//! - `∫ y^2 dy/(r (r+z)^2) = -y/(r+z) + ∫ dy/(r+z)` (by parts),
//!
//! so that, e.g., the Cerruti `u_x` term `a (1/(r+z) - x^2/(r (r+z)^2))`
//! integrates to `a (asinh - y/(r+z))`. Each is checked against a brute-force
//! sum of the point solutions in the tests.
//!
//! Layer on a rigid base (thickness `T`): the normal displacement is the
//! half-space one minus its value at depth `T` (Steinbrenner's correction),
//! which cuts off the logarithmic growth of the half-space line solution; the
//! lateral displacements are the half-space ones tapered linearly to zero at
//! the bonded base (see [`RodLoad::layer`] for why not the same subtraction).

use std::f64::consts::PI;

use optical_tactile::error::{Error, Result};

/// Mechanical properties of the gel layer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Young's modulus, kPa (soft silicone gels: tens of kPa; default 40).
    pub youngs_kpa: f64,
    /// Poisson's ratio (nearly incompressible gel: 0.45-0.49).
    pub poisson: f64,
    /// Thickness of the layer above the rigid plate, mm.
    pub layer_mm: f64,
}

impl Default for Material {
    fn default() -> Self {
        Material {
            // Calibrated so that 0.5-3 N on a 40 mm rod moves markers by about
            // 0.3-1.6 px at 5 px/mm, at the soft end of gel moduli.
            youngs_kpa: 40.0,
            poisson: 0.47,
            layer_mm: 8.0,
        }
    }
}

impl Material {
    /// Checks the ranges: `E > 0`, `0 <= nu < 0.5`, `T > 0`.
    pub fn validate(&self) -> Result<()> {
        if !(self.youngs_kpa.is_finite() && self.youngs_kpa > 0.0) {
            return Err(Error::param(
                "youngs_kpa",
                format!("must be > 0, got {}", self.youngs_kpa),
            ));
        }
        if !(self.poisson.is_finite() && (0.0..0.5).contains(&self.poisson)) {
            return Err(Error::param(
                "poisson",
                format!("must lie in [0, 0.5), got {}", self.poisson),
            ));
        }
        if !(self.layer_mm.is_finite() && self.layer_mm > 0.0) {
            return Err(Error::param(
                "layer_mm",
                format!("must be > 0, got {}", self.layer_mm),
            ));
        }
        Ok(())
    }

    /// Shear modulus `G = E / (2 (1 + nu))` in N/mm^2 (1 kPa = 1e-3 N/mm^2).
    pub fn shear_modulus(&self) -> f64 {
        self.youngs_kpa * 1e-3 / (2.0 * (1.0 + self.poisson))
    }

    /// Plane-strain modulus `E* = E / (1 - nu^2)` in N/mm^2.
    pub fn plane_strain_modulus(&self) -> f64 {
        self.youngs_kpa * 1e-3 / (1.0 - self.poisson * self.poisson)
    }
}

/// Half-space displacement at `p = [x, y, z]` (z > 0) due to a point force
/// `f = [f_x, f_y, f_n]` at the surface origin: Boussinesq + Cerruti
/// (the elastic half-space solutions). The slow, obviously-correct oracle of the integrated
/// kernels.
pub fn point_displacement(mat: &Material, f: [f64; 3], p: [f64; 3]) -> [f64; 3] {
    let nu = mat.poisson;
    let a = 1.0 - 2.0 * nu;
    let [x, y, z] = p;
    let r = (x * x + y * y + z * z).sqrt();
    let r3 = r * r * r;
    let rz = r + z;
    let k = 1.0 / (4.0 * PI * mat.shear_modulus());
    // Boussinesq.
    let bn = [
        x * z / r3 - a * x / (r * rz),
        y * z / r3 - a * y / (r * rz),
        z * z / r3 + 2.0 * (1.0 - nu) / r,
    ];
    // Cerruti, force along x.
    let cx = [
        1.0 / r + x * x / r3 + a * (1.0 / rz - x * x / (r * rz * rz)),
        x * y / r3 - a * x * y / (r * rz * rz),
        x * z / r3 + a * x / (r * rz),
    ];
    // Cerruti, force along y (x and y swapped).
    let cy = [
        x * y / r3 - a * x * y / (r * rz * rz),
        1.0 / r + y * y / r3 + a * (1.0 / rz - y * y / (r * rz * rz)),
        y * z / r3 + a * y / (r * rz),
    ];
    let mut u = [0.0; 3];
    for i in 0..3 {
        u[i] = k * (f[0] * cx[i] + f[1] * cy[i] + f[2] * bn[i]);
    }
    u
}

/// `atan(t) / t`, finite at 0.
#[inline]
fn atanc(t: f64) -> f64 {
    if t.abs() < 1e-4 {
        1.0 - t * t / 3.0
    } else {
        t.atan() / t
    }
}

/// Antiderivatives in `y` of the point kernels (without `1/(4 pi G)`), as a
/// matrix `m[load][component]` with loads (f_x, f_y, f_n); see the module docs.
#[inline]
fn primitive(nu: f64, x: f64, y: f64, z: f64) -> [[f64; 3]; 3] {
    let a = 1.0 - 2.0 * nu;
    let aa = x * x + z * z;
    let r = (aa + y * y).sqrt();
    let rz = r + z;
    let l = (y / aa.sqrt()).asinh();
    let ln_rz = rz.ln();
    // J1, written so that it has no cancellation (r - z = (x^2 + y^2)/(r + z)).
    let j1 = {
        let den = x * x * r + z * y * y;
        if den <= 0.0 {
            0.0
        } else {
            let q = y * (x * x + y * y) / rz / den;
            q * atanc(x * q)
        }
    };
    let yar = y / (aa * r);
    let inv_r = 1.0 / r;
    let inv_rz = 1.0 / rz;
    let cross = -x * inv_r + a * x * inv_rz;
    [
        // f_x (Cerruti)
        [
            l + x * x * yar + a * (l - y * inv_rz),
            cross,
            x * z * yar + a * x * j1,
        ],
        // f_y (Cerruti, swapped)
        [
            cross,
            2.0 * l - y * inv_r + a * y * inv_rz,
            -z * inv_r + a * ln_rz,
        ],
        // f_n (Boussinesq)
        [
            x * z * yar - a * x * j1,
            -z * inv_r - a * ln_rz,
            z * z * yar + 2.0 * (1.0 - nu) * l,
        ],
    ]
}

/// Half-space displacement (mm) of a point at depth `z` from a uniform line
/// load of `f = [f_x, f_y, f_n]` N per mm lying on the surface along `y`, with
/// the point at in-plane offset `x` from the line and the load covering the
/// relative coordinate `y' = y_point - eta` from `y1` to `y2`. Closed form: the
/// antiderivatives of the module docs, evaluated at `y2` and `y1`.
#[inline]
pub fn line_segment_displacement(
    mat: &Material,
    f: [f64; 3],
    x: f64,
    y1: f64,
    y2: f64,
    z: f64,
) -> [f64; 3] {
    let p2 = primitive(mat.poisson, x, y2, z);
    let p1 = primitive(mat.poisson, x, y1, z);
    let k = 1.0 / (4.0 * PI * mat.shear_modulus());
    let mut u = [0.0; 3];
    for load in 0..3 {
        if f[load] != 0.0 {
            for c in 0..3 {
                u[c] += k * f[load] * (p2[load][c] - p1[load][c]);
            }
        }
    }
    u
}

/// Gauss-Chebyshev (second kind) nodes and weights on [-1, 1] for the weight
/// `(2/pi) sqrt(1 - t^2)` (weights sum to 1): exact for polynomials of degree
/// `2n - 1` times that weight.
pub fn chebyshev2_rule(n: usize) -> Vec<(f64, f64)> {
    let n = n.max(1);
    let h = PI / (n as f64 + 1.0);
    (1..=n)
        .map(|i| {
            let th = i as f64 * h;
            (th.cos(), 2.0 / PI * h * th.sin().powi(2))
        })
        .collect()
}

/// Hertz half-width `b` (mm) of a rigid cylinder of radius `rod_radius_mm`
/// pressed with line load `line_load` (N/mm) on a convex skin of radius
/// `skin_radius_mm`: `b = sqrt(4 P' R_eff / (pi E*))`, `1/R_eff = 1/R_rod + 1/R_skin`.
pub fn hertz_half_width(
    mat: &Material,
    rod_radius_mm: f64,
    skin_radius_mm: f64,
    line_load: f64,
) -> f64 {
    let r_eff = 1.0 / (1.0 / rod_radius_mm + 1.0 / skin_radius_mm);
    (4.0 * line_load.max(0.0) * r_eff / (PI * mat.plane_strain_modulus())).sqrt()
}

/// A rod load on the unrolled skin, ready to evaluate at markers.
#[derive(Debug, Clone)]
pub struct RodLoad {
    /// Arc position of the rod's axis, mm.
    pub s_mm: f64,
    /// Across extent of the load, mm (`y_lo < y_hi`).
    pub y_lo: f64,
    /// Upper across bound, mm.
    pub y_hi: f64,
    /// Hertz half-width across the rod, mm (0 gives a line load).
    pub half_width: f64,
    /// Total local force `[f_t, f_y, f_n]`, N (`f_n` into the gel).
    pub force: [f64; 3],
}

/// Rules cached by node count, so that evaluation never recomputes cos/sin.
#[derive(Debug, Clone)]
pub struct QuadratureCache {
    rules: Vec<Vec<(f64, f64)>>,
}

/// Largest node count used across a rod.
pub const MAX_NODES: usize = 48;

impl Default for QuadratureCache {
    fn default() -> Self {
        QuadratureCache {
            rules: (0..=MAX_NODES).map(chebyshev2_rule).collect(),
        }
    }
}

impl QuadratureCache {
    /// Node count for a marker at distance `rho` (in the x-z plane) from a rod
    /// of half-width `b`. Far away the footprint acts as a line load: one node
    /// errs by ~`(b/rho)^2`, two (exact to cubic order) by ~`(b/rho)^4`; close
    /// by, enough nodes that their spacing (~ pi b / n) stays below `rho`, the
    /// kernel's scale.
    #[inline]
    pub fn nodes_for(b: f64, rho: f64) -> usize {
        let ratio = b / rho;
        if ratio < 0.05 {
            return 1;
        }
        if ratio < 0.2 {
            return 2;
        }
        let n = (2.0 + 5.0 * ratio).ceil();
        (n as usize).clamp(2, MAX_NODES)
    }

    /// The rule with `n` nodes.
    #[inline]
    pub fn rule(&self, n: usize) -> &[(f64, f64)] {
        &self.rules[n.clamp(1, MAX_NODES)]
    }
}

impl RodLoad {
    /// Half-space displacement (mm) at marker `(s, y, z)`, z > 0.
    #[inline]
    pub fn half_space(
        &self,
        mat: &Material,
        q: &QuadratureCache,
        s: f64,
        y: f64,
        z: f64,
    ) -> [f64; 3] {
        let len = self.y_hi - self.y_lo;
        let f = [
            self.force[0] / len,
            self.force[1] / len,
            self.force[2] / len,
        ];
        let x0 = s - self.s_mm;
        let y1 = y - self.y_hi;
        let y2 = y - self.y_lo;
        let b = self.half_width;
        let rho = (x0 * x0 + z * z).sqrt();
        let n = QuadratureCache::nodes_for(b, rho);
        let mut u = [0.0; 3];
        if b <= 0.0 {
            return line_segment_displacement(mat, f, x0, y1, y2, z);
        }
        for &(t, w) in q.rule(n) {
            let d = line_segment_displacement(mat, f, x0 - b * t, y1, y2, z);
            for c in 0..3 {
                u[c] += w * d[c];
            }
        }
        u
    }

    /// Displacement (mm) of a marker at depth `z` in a layer of thickness
    /// `T = mat.layer_mm` bonded to a rigid base.
    ///
    /// Normal component: half-space at `z` minus half-space at the base
    /// (Steinbrenner's settlement correction), which cuts off the logarithmic
    /// growth of the line-load solution and lets the layer bulge up beside the
    /// contact as an incompressible layer does. Lateral components: the
    /// half-space ones tapered linearly to zero at the bonded base,
    /// `(1 - z/T)`. (Subtracting the base's lateral displacement as well would
    /// be wrong here: in a half-space the sideways motion grows with depth up to
    /// `z ~ |x|`, so the difference would point *inward* beside the contact,
    /// whereas the gel squeezed out of a bonded layer moves outward.)
    #[inline]
    pub fn layer(&self, mat: &Material, q: &QuadratureCache, s: f64, y: f64, z: f64) -> [f64; 3] {
        let top = self.half_space(mat, q, s, y, z);
        let base = self.half_space(mat, q, s, y, mat.layer_mm);
        let taper = (1.0 - z / mat.layer_mm).max(0.0);
        [top[0] * taper, top[1] * taper, top[2] - base[2]]
    }
}

/// A round contact (a fingertip, a spherical tip) on a thin gel layer
/// bonded to a rigid base, the build of flat fingertip sensors (a gel of a
/// few mm on an acrylic window).
///
/// Such a layer, pressed over an area much wider than it is thick, does not
/// behave as a half-space: the nearly incompressible gel cannot move down
/// without flowing sideways, so it is squeezed *outward* from under the
/// contact, and the markers near its surface spread apart. The model is the
/// thin-layer (lubrication) limit of an incompressible layer of thickness
/// `T` and shear modulus `G` (Johnson, *Contact Mechanics*, thin layers):
/// the pressure `p` and the tangential traction `q` are constant through the
/// thickness, and at height `z` above the base
///
/// - lateral: `u(z) = (z^2 - 2 T z) grad p / (2 G) + q z / G`, zero on the
///   base, free of shear from the pressure at the surface;
/// - normal (up): `w(z) = -(z^3 / 3 - T z^2) lap p / (2 G) - z^2 div q / (2 G)`,
///   from the incompressibility `dw/dz = -div u`, so the volume pressed down
///   under the contact bulges up around it (and a shear piles the gel up
///   ahead of the contact).
///
/// A sphere of radius `R` on such a layer takes a pressure `p0 (1 - r^2/a^2)^2`
/// over a contact of radius `a`; the tangential traction is given the same
/// profile (the contact sticks). With that profile every displacement goes
/// smoothly to zero at the contact's edge. Outside the contact the thin-layer
/// limit gives no motion (in a real layer it fades over about `T`).
#[derive(Debug, Clone)]
pub struct RoundLoad {
    /// Arc position of the contact's centre, mm.
    pub s_mm: f64,
    /// Across position of the contact's centre, mm.
    pub y_mm: f64,
    /// Contact radius `a`, mm.
    pub radius: f64,
    /// Total local force `[f_t, f_y, f_n]`, N (`f_n` into the gel).
    pub force: [f64; 3],
}

impl RoundLoad {
    /// Contact radius (mm) of a sphere of radius `tip_radius_mm` pressed
    /// with `f_n` (N) into a thin incompressible layer of `mat`'s thickness
    /// bonded to a rigid base: the indentation of the profile above,
    /// `8 p0 T^3 / (3 G a^2)`, set equal to the sphere's `a^2 / (2 R)`, with
    /// `p0 = 3 f_n / (pi a^2)`, gives `a^6 = 16 f_n T^3 R / (pi G)`.
    pub fn sphere_contact_radius(mat: &Material, tip_radius_mm: f64, f_n: f64) -> f64 {
        let t = mat.layer_mm;
        (16.0 * f_n.max(0.0) * t * t * t * tip_radius_mm / (PI * mat.shear_modulus()))
            .powf(1.0 / 6.0)
    }

    /// Displacement (mm, `[along s, across, into the gel]`) of a marker at
    /// depth `z` below the surface (clamped to the layer), at `(s, y)`.
    pub fn layer(&self, mat: &Material, s: f64, y: f64, z: f64) -> [f64; 3] {
        let a = self.radius;
        if a <= 0.0 {
            return [0.0; 3];
        }
        let (dx, dy) = (s - self.s_mm, y - self.y_mm);
        let rho2 = (dx * dx + dy * dy) / (a * a);
        if rho2 >= 1.0 {
            return [0.0; 3];
        }
        let t = mat.layer_mm;
        let g = mat.shear_modulus();
        // Height above the base.
        let h = (t - z.clamp(0.0, t)).max(0.0);
        let area = PI * a * a;
        let p0 = 3.0 * self.force[2] / area;
        let one = 1.0 - rho2;
        let profile = one * one;
        // grad p = -4 p0 (1 - rho^2) (dx, dy) / a^2; lap p = -8 p0 (1 - 2 rho^2) / a^2.
        let grad = [
            -4.0 * p0 * one * dx / (a * a),
            -4.0 * p0 * one * dy / (a * a),
        ];
        let lap = -8.0 * p0 * (1.0 - 2.0 * rho2) / (a * a);
        let squeeze = (h * h - 2.0 * t * h) / (2.0 * g);
        let shear = 3.0 * profile * h / (area * g);
        // div q, the traction having the pressure's profile.
        let div_q = 3.0 / area * (-4.0 * one / (a * a)) * (self.force[0] * dx + self.force[1] * dy);
        let up = -(h * h * h / 3.0 - t * h * h) * lap / (2.0 * g) - h * h * div_q / (2.0 * g);
        [
            squeeze * grad[0] + shear * self.force[0],
            squeeze * grad[1] + shear * self.force[1],
            -up,
        ]
    }
}

/// One contact's load on the unrolled skin.
#[derive(Debug, Clone)]
pub enum Load {
    /// A rod across the skin's width ([`RodLoad`]).
    Rod(RodLoad),
    /// A round contact on a thin bonded layer ([`RoundLoad`]).
    Round(RoundLoad),
}

impl Load {
    /// Displacement (mm) of a marker at `(s, y)` and depth `z` (see
    /// [`RodLoad::layer`] and [`RoundLoad::layer`]).
    #[inline]
    pub fn layer(&self, mat: &Material, q: &QuadratureCache, s: f64, y: f64, z: f64) -> [f64; 3] {
        match self {
            Load::Rod(l) => l.layer(mat, q, s, y, z),
            Load::Round(l) => l.layer(mat, s, y, z),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mat() -> Material {
        Material::default()
    }

    /// Brute force: midpoint sum of the point solution along y with a sinh
    /// substitution (dense near the peak).
    fn brute_line(mat: &Material, f: [f64; 3], x: f64, y1: f64, y2: f64, z: f64) -> [f64; 3] {
        let c = (x * x + z * z).sqrt();
        let (t1, t2) = ((y1 / c).asinh(), (y2 / c).asinh());
        let n = 20_000;
        let h = (t2 - t1) / n as f64;
        let mut u = [0.0; 3];
        for i in 0..n {
            let t = t1 + (i as f64 + 0.5) * h;
            let y = c * t.sinh();
            let dy = c * t.cosh() * h;
            let p = point_displacement(mat, f, [x, y, z]);
            for k in 0..3 {
                u[k] += p[k] * dy;
            }
        }
        u
    }

    #[test]
    fn closed_form_line_integral_matches_brute_force() {
        let m = mat();
        for &(x, y1, y2, z) in &[
            (0.0, -20.0, 20.0, 1.0),
            (0.7, -3.0, 37.0, 0.5),
            (-2.5, -39.0, 1.0, 2.0),
            (10.0, 5.0, 45.0, 4.0),
            (1e-7, -20.0, 20.0, 0.5),
        ] {
            for f in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] {
                let a = line_segment_displacement(&m, f, x, y1, y2, z);
                let b = brute_line(&m, f, x, y1, y2, z);
                let scale = b.iter().fold(1e-3f64, |s, v| s.max(v.abs()));
                for k in 0..3 {
                    assert!(
                        (a[k] - b[k]).abs() < 1e-5 * scale,
                        "x={x} y=[{y1},{y2}] z={z} f={f:?} k={k}: {} vs {}",
                        a[k],
                        b[k]
                    );
                }
            }
        }
    }

    #[test]
    fn point_solution_symmetries() {
        let m = mat();
        let fz = [0.0, 0.0, 1.0];
        let u = point_displacement(&m, fz, [1.0, 0.5, 2.0]);
        let v = point_displacement(&m, fz, [-1.0, 0.5, 2.0]);
        let w = point_displacement(&m, fz, [0.5, 1.0, 2.0]);
        // Mirror in x flips u_x; rotation by 90 deg swaps x and y.
        assert!(
            (u[0] + v[0]).abs() < 1e-12
                && (u[1] - v[1]).abs() < 1e-12
                && (u[2] - v[2]).abs() < 1e-12
        );
        assert!((u[0] - w[1]).abs() < 1e-12 && (u[2] - w[2]).abs() < 1e-12);
        // Pressing pushes the gel in and, below the surface, outward.
        assert!(u[2] > 0.0 && u[0] > 0.0 && v[0] < 0.0);
    }

    #[test]
    fn rod_footprint_matches_brute_force_2d_sum() {
        let m = mat();
        let q = QuadratureCache::default();
        for (b, s_m, z) in [
            (1.2, 0.3, 0.5),
            (2.2, 1.5, 1.0),
            (0.6, -4.0, 0.5),
            (1.5, 9.0, 3.0),
            (2.0, 0.0, 0.5),
        ] {
            let rod = RodLoad {
                s_mm: 0.0,
                y_lo: -20.0,
                y_hi: 20.0,
                half_width: b,
                force: [0.3, 0.1, 1.0],
            };
            let got = rod.half_space(&m, &q, s_m, 3.0, z);
            // Brute force across the rod: fine midpoint sum of the elliptical
            // pressure (with the sin substitution xi = b sin phi that makes the
            // weight smooth), each strip by the closed-form line integral
            // (checked against the point solution above).
            let n = 4000;
            let mut want = [0.0; 3];
            let len = rod.y_hi - rod.y_lo;
            for i in 0..n {
                let phi = -PI / 2.0 + (i as f64 + 0.5) * PI / n as f64;
                let xi = b * phi.sin();
                let w = 2.0 / PI * phi.cos().powi(2) * PI / n as f64;
                let f = [rod.force[0] / len, rod.force[1] / len, rod.force[2] / len];
                let d = line_segment_displacement(&m, f, s_m - xi, 3.0 - 20.0, 3.0 + 20.0, z);
                for k in 0..3 {
                    want[k] += w * d[k];
                }
            }
            let scale = want.iter().fold(0.0f64, |s, v| s.max(v.abs()));
            for k in 0..3 {
                assert!(
                    (got[k] - want[k]).abs() < 2e-3 * scale,
                    "b={b} s={s_m} z={z} k={k}: {} vs {}",
                    got[k],
                    want[k]
                );
            }
        }
    }

    #[test]
    fn far_field_with_few_nodes_is_accurate() {
        let m = mat();
        let q = QuadratureCache::default();
        let rod = RodLoad {
            s_mm: 0.0,
            y_lo: -20.0,
            y_hi: 20.0,
            half_width: 2.2,
            force: [0.5, 0.0, 3.0],
        };
        for off in [8.0, 12.0, 20.0, 45.0, 100.0] {
            for z in [0.5, 2.0, 8.0] {
                let got = rod.half_space(&m, &q, off, 5.0, z);
                let n = 2000;
                let mut want = [0.0; 3];
                for i in 0..n {
                    let phi = -PI / 2.0 + (i as f64 + 0.5) * PI / n as f64;
                    let w = 2.0 / PI * phi.cos().powi(2) * PI / n as f64;
                    let f = [0.5 / 40.0, 0.0, 3.0 / 40.0];
                    let d = line_segment_displacement(
                        &m,
                        f,
                        off - 2.2 * phi.sin(),
                        5.0 - 20.0,
                        5.0 + 20.0,
                        z,
                    );
                    for k in 0..3 {
                        want[k] += w * d[k];
                    }
                }
                let scale = want.iter().fold(0.0f64, |s, v| s.max(v.abs()));
                for k in 0..3 {
                    assert!(
                        (got[k] - want[k]).abs() < 5e-3 * scale,
                        "off={off} z={z} k={k}"
                    );
                }
            }
        }
    }

    #[test]
    fn hertz_width_grows_with_load_and_radius() {
        let m = mat();
        let b1 = hertz_half_width(&m, 5.0, 220.0, 1.0 / 40.0);
        let b3 = hertz_half_width(&m, 5.0, 220.0, 3.0 / 40.0);
        let b1s = hertz_half_width(&m, 1.0, 220.0, 1.0 / 40.0);
        assert!((b3 / b1 - 3f64.sqrt()).abs() < 1e-12);
        assert!(b1s < b1 && b1 > 0.5 && b1 < 3.0, "{b1}");
    }

    #[test]
    fn material_ranges() {
        assert!(
            Material {
                poisson: 0.5,
                ..mat()
            }
            .validate()
            .is_err()
        );
        assert!(
            Material {
                youngs_kpa: -1.0,
                ..mat()
            }
            .validate()
            .is_err()
        );
        assert!(
            Material {
                layer_mm: 0.0,
                ..mat()
            }
            .validate()
            .is_err()
        );
        mat().validate().unwrap();
    }

    fn thin() -> Material {
        Material {
            youngs_kpa: 150.0,
            poisson: 0.47,
            layer_mm: 2.5,
        }
    }

    fn round(force: [f64; 3]) -> RoundLoad {
        RoundLoad {
            s_mm: 1.0,
            y_mm: -2.0,
            radius: 5.0,
            force,
        }
    }

    /// The closed form against the equations it solves, by finite
    /// differences at points inside the contact: lateral equilibrium
    /// `G d2u/dz2 = grad p`, incompressibility `dw/dz = -div u` (`w` up), a
    /// base that does not move, and a surface whose shear is the traction.
    #[test]
    fn round_load_solves_the_thin_layer_equations() {
        let m = thin();
        let (t, g) = (m.layer_mm, m.shear_modulus());
        let load = round([0.3, -0.2, 1.5]);
        let a = load.radius;
        let area = PI * a * a;
        // The pressure and traction profiles, written out independently.
        let profile = |s: f64, y: f64| {
            let r2 = ((s - load.s_mm).powi(2) + (y - load.y_mm).powi(2)) / (a * a);
            if r2 < 1.0 { (1.0 - r2).powi(2) } else { 0.0 }
        };
        let p = |s: f64, y: f64| 3.0 * load.force[2] / area * profile(s, y);
        // Displacement at height `h` above the base, `w` up.
        let at = |s: f64, y: f64, h: f64| {
            let u = load.layer(&m, s, y, t - h);
            [u[0], u[1], -u[2]]
        };
        let e = 1e-3;
        for &(s, y, h) in &[
            (2.0, -1.0, 1.0),
            (-1.5, -3.0, 2.0),
            (3.5, 0.5, 0.4),
            (1.2, -2.3, 1.7),
        ] {
            let u = at(s, y, h);
            // Equilibrium.
            let (up, um) = (at(s, y, h + e), at(s, y, h - e));
            let dp = [
                (p(s + e, y) - p(s - e, y)) / (2.0 * e),
                (p(s, y + e) - p(s, y - e)) / (2.0 * e),
            ];
            for k in 0..2 {
                let d2 = (up[k] - 2.0 * u[k] + um[k]) / (e * e);
                assert!(
                    (g * d2 - dp[k]).abs() < 1e-4 * dp[k].abs().max(1e-3),
                    "equilibrium {k} at ({s}, {y}, {h}): {} vs {}",
                    g * d2,
                    dp[k]
                );
            }
            // Incompressibility.
            let dw = (up[2] - um[2]) / (2.0 * e);
            let div = (at(s + e, y, h)[0] - at(s - e, y, h)[0]) / (2.0 * e)
                + (at(s, y + e, h)[1] - at(s, y - e, h)[1]) / (2.0 * e);
            assert!(
                (dw + div).abs() < 1e-5,
                "incompressibility at ({s}, {y}, {h}): {dw} vs {}",
                -div
            );
            // The base is bonded.
            assert!(at(s, y, 0.0).iter().all(|v| v.abs() < 1e-15));
            // At the surface the shear stress is the traction.
            // (Second-order one-sided difference: exact for `u`, quadratic in z.)
            let (top, b1, b2) = (at(s, y, t), at(s, y, t - e), at(s, y, t - 2.0 * e));
            for k in 0..2 {
                let shear = g * (3.0 * top[k] - 4.0 * b1[k] + b2[k]) / (2.0 * e);
                let q = 3.0 * load.force[k] / area * profile(s, y);
                assert!(
                    (shear - q).abs() < 2e-3 * q.abs().max(1e-3),
                    "surface shear {k}: {shear} vs {q}"
                );
            }
        }
    }

    /// A normal press spreads the surface outward, the volume it presses
    /// down bulges up around it (none is lost), nothing moves outside the
    /// contact, and a sphere's contact radius makes the indentation at the
    /// centre the sphere's own `a^2 / (2 R)`.
    #[test]
    fn a_round_press_squeezes_the_layer_outward() {
        let m = thin();
        let mut load = round([0.0, 0.0, 2.0]);
        let a = load.radius;
        for &(dx, dy) in &[(1.0, 0.0), (0.0, -2.5), (-3.0, 2.0), (4.0, 1.0)] {
            let u = load.layer(&m, load.s_mm + dx, load.y_mm + dy, 0.0);
            assert!(u[0] * dx + u[1] * dy > 0.0, "inward at ({dx}, {dy}): {u:?}");
            assert!((u[0] * dy - u[1] * dx).abs() < 1e-12, "not radial");
        }
        assert_eq!(
            load.layer(&m, load.s_mm + a * 1.01, load.y_mm, 0.0),
            [0.0; 3]
        );
        // Volume: the surface's normal displacement integrates to zero.
        let n = 400;
        let step = 2.0 * a / n as f64;
        let mut volume = 0.0;
        let mut pressed = 0.0;
        for i in 0..n {
            for j in 0..n {
                let (x, y) = (-a + (i as f64 + 0.5) * step, -a + (j as f64 + 0.5) * step);
                let w = load.layer(&m, load.s_mm + x, load.y_mm + y, 0.0)[2];
                volume += w * step * step;
                pressed += w.max(0.0) * step * step;
            }
        }
        assert!(
            volume.abs() < 1e-3 * pressed,
            "volume {volume} of {pressed} pressed"
        );
        // A sphere of radius 10 mm.
        let r_tip = 10.0;
        load.radius = RoundLoad::sphere_contact_radius(&m, r_tip, load.force[2]);
        let depth = load.layer(&m, load.s_mm, load.y_mm, 0.0)[2];
        let a = load.radius;
        assert!(
            (depth - a * a / (2.0 * r_tip)).abs() < 1e-9 * depth,
            "{depth} vs {}",
            a * a / (2.0 * r_tip)
        );
    }
}
