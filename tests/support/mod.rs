//! Deterministic synthetic test images for the optical-flow tests, benches
//! and example: Gaussian marker patterns re-rendered after a known analytic
//! motion, and smooth random textures warped by it.
//!
//! Until the physics-based simulator lands this is the flow code's own
//! stand-in for marker images: ~1 px-sigma dark Gaussian dots on a bright
//! background on a jittered grid, covering about 30 % of the pixels.

#![allow(dead_code)]

use ndarray::Array2;
use optical_tactile::flow::FlowField;

/// Small deterministic PRNG (SplitMix64), so images never depend on a crate.
pub struct Rng(u64);

impl Rng {
    /// Seeded generator.
    pub fn new(seed: u64) -> Self {
        Rng(seed ^ 0x9E37_79B9_7F4A_7C15)
    }
    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in `[0, 1)`.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform in `[a, b)`.
    pub fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.uniform()
    }
}

/// A press-like bump: radial (divergent) displacement `amp * r/sigma *
/// exp(-r^2 / (2 sigma^2))` around `(cx, cy)`, plus a lateral shear
/// `(sx, sy) * exp(-r^2 / (2 sigma^2))`.
#[derive(Debug, Clone, Copy)]
pub struct Bump {
    pub cx: f64,
    pub cy: f64,
    pub sigma: f64,
    pub amp: f64,
    pub sx: f64,
    pub sy: f64,
}

/// An analytic motion field: where the material point at `(x, y)` moves.
#[derive(Debug, Clone)]
pub enum Motion {
    /// Rigid translation.
    Translation(f64, f64),
    /// Rotation by `angle` radians about `(cx, cy)`.
    Rotation { cx: f64, cy: f64, angle: f64 },
    /// `d = A (p - c) + t`, `A = [[a, b], [c, d]]` about the centre `(cx, cy)`.
    Affine {
        cx: f64,
        cy: f64,
        a: [f64; 4],
        t: [f64; 2],
    },
    /// Sum of bumps.
    Bumps(Vec<Bump>),
}

impl Motion {
    /// Displacement of the point `(x, y)`.
    pub fn at(&self, x: f64, y: f64) -> (f64, f64) {
        match self {
            Motion::Translation(dx, dy) => (*dx, *dy),
            Motion::Rotation { cx, cy, angle } => {
                let (s, c) = angle.sin_cos();
                let (rx, ry) = (x - cx, y - cy);
                (c * rx - s * ry - rx, s * rx + c * ry - ry)
            }
            Motion::Affine { cx, cy, a, t } => {
                let (rx, ry) = (x - cx, y - cy);
                (a[0] * rx + a[1] * ry + t[0], a[2] * rx + a[3] * ry + t[1])
            }
            Motion::Bumps(bs) => {
                let (mut dx, mut dy) = (0.0, 0.0);
                for b in bs {
                    let (rx, ry) = (x - b.cx, y - b.cy);
                    let g = (-(rx * rx + ry * ry) / (2.0 * b.sigma * b.sigma)).exp();
                    dx += b.amp * rx / b.sigma * g + b.sx * g;
                    dy += b.amp * ry / b.sigma * g + b.sy * g;
                }
                (dx, dy)
            }
        }
    }

    /// The true flow on the pixel grid: displacement of each reference pixel.
    pub fn truth(&self, w: usize, h: usize) -> FlowField {
        let mut f = FlowField::zeros(w, h);
        for y in 0..h {
            for x in 0..w {
                let (u, v) = self.at(x as f64, y as f64);
                f.u[[y, x]] = u as f32;
                f.v[[y, x]] = v as f32;
            }
        }
        f
    }

    /// The reference point that moves to `(x, y)` (fixed-point inversion;
    /// the motions used here have gradients well below 1).
    pub fn inverse(&self, x: f64, y: f64) -> (f64, f64) {
        let (mut px, mut py) = (x, y);
        for _ in 0..30 {
            let (dx, dy) = self.at(px, py);
            px = x - dx;
            py = y - dy;
        }
        (px, py)
    }
}

/// Marker centres on a jittered grid of `pitch` px covering the image plus a
/// margin (so markers can move in from outside).
pub fn marker_centres(w: usize, h: usize, pitch: f64, seed: u64) -> Vec<(f64, f64)> {
    let mut rng = Rng::new(seed);
    let margin = 12.0;
    let mut pts = Vec::new();
    let mut y = -margin;
    while y < h as f64 + margin {
        let mut x = -margin;
        while x < w as f64 + margin {
            let j = 0.3 * pitch;
            pts.push((x + rng.range(-j, j), y + rng.range(-j, j)));
            x += pitch;
        }
        y += pitch;
    }
    pts
}

/// Renders dark Gaussian markers of `sigma` px on a bright background
/// (200 grey levels, markers 150 deep, summed where they overlap, clamped
/// at 0).
pub fn render_markers(w: usize, h: usize, centres: &[(f64, f64)], sigma: f64) -> Array2<f32> {
    let mut acc = Array2::<f64>::zeros((h, w));
    let rad = (4.0 * sigma).ceil() as i64;
    let k = 1.0 / (2.0 * sigma * sigma);
    for &(cx, cy) in centres {
        let (ix, iy) = (cx.round() as i64, cy.round() as i64);
        for y in (iy - rad).max(0)..=(iy + rad).min(h as i64 - 1) {
            for x in (ix - rad).max(0)..=(ix + rad).min(w as i64 - 1) {
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                acc[[y as usize, x as usize]] += (-(dx * dx + dy * dy) * k).exp();
            }
        }
    }
    acc.mapv(|a| (200.0 - 150.0 * a).max(0.0) as f32)
}

/// A reference marker image and the image after `motion`, with the truth.
pub fn marker_pair(
    w: usize,
    h: usize,
    motion: &Motion,
    seed: u64,
) -> (Array2<f32>, Array2<f32>, FlowField) {
    let c0 = marker_centres(w, h, 4.5, seed);
    let c1: Vec<(f64, f64)> = c0
        .iter()
        .map(|&(x, y)| {
            let (dx, dy) = motion.at(x, y);
            (x + dx, y + dy)
        })
        .collect();
    (
        render_markers(w, h, &c0, 1.0),
        render_markers(w, h, &c1, 1.0),
        motion.truth(w, h),
    )
}

/// A smooth random texture: a sum of `n` random plane waves with
/// wavelengths of 16..48 px, around grey level 128.
pub struct Texture {
    waves: Vec<(f64, f64, f64, f64)>, // kx, ky, phase, amplitude
}

impl Texture {
    /// Random waves from `seed`.
    pub fn new(seed: u64, n: usize) -> Self {
        let mut rng = Rng::new(seed);
        let waves = (0..n)
            .map(|_| {
                let lambda = rng.range(16.0, 48.0);
                let th = rng.range(0.0, std::f64::consts::TAU);
                let k = std::f64::consts::TAU / lambda;
                (
                    k * th.cos(),
                    k * th.sin(),
                    rng.range(0.0, std::f64::consts::TAU),
                    rng.range(10.0, 30.0),
                )
            })
            .collect();
        Texture { waves }
    }
    /// Value at a point.
    pub fn at(&self, x: f64, y: f64) -> f64 {
        128.0
            + self
                .waves
                .iter()
                .map(|&(kx, ky, ph, a)| a * (kx * x + ky * y + ph).sin())
                .sum::<f64>()
    }
}

/// A smooth-texture pair: reference `T(x)`, current `T(motion^-1(x))`.
pub fn texture_pair(
    w: usize,
    h: usize,
    motion: &Motion,
    seed: u64,
) -> (Array2<f32>, Array2<f32>, FlowField) {
    let t = Texture::new(seed, 8);
    let r = Array2::from_shape_fn((h, w), |(y, x)| t.at(x as f64, y as f64) as f32);
    let c = Array2::from_shape_fn((h, w), |(y, x)| {
        let (px, py) = motion.inverse(x as f64, y as f64);
        t.at(px, py) as f32
    });
    (r, c, motion.truth(w, h))
}

/// Bumps like a few fingertip presses, scaled so the largest displacement is
/// about `max_disp` px.
pub fn press_motion(w: usize, h: usize, max_disp: f64, seed: u64) -> Motion {
    let mut rng = Rng::new(seed);
    let n = 3;
    let s = (w.min(h) as f64) / 4.0;
    let bumps = (0..n)
        .map(|_| Bump {
            cx: rng.range(0.2, 0.8) * w as f64,
            cy: rng.range(0.2, 0.8) * h as f64,
            sigma: s * rng.range(0.7, 1.3),
            amp: max_disp * 0.8 / 0.6065,
            sx: rng.range(-0.4, 0.4) * max_disp,
            sy: rng.range(-0.4, 0.4) * max_disp,
        })
        .collect();
    Motion::Bumps(bumps)
}

/// Mean of `(flow - truth)` over the interior (the bias), per component.
pub fn mean_error(flow: &FlowField, truth: &FlowField, border: usize) -> (f64, f64) {
    let (w, h) = flow.size();
    let (mut su, mut sv, mut n) = (0.0, 0.0, 0.0);
    for y in border..h - border {
        for x in border..w - border {
            su += (flow.u[[y, x]] - truth.u[[y, x]]) as f64;
            sv += (flow.v[[y, x]] - truth.v[[y, x]]) as f64;
            n += 1.0;
        }
    }
    (su / n, sv / n)
}
