//! Rendering: each marker is a Gaussian spot drawn at its moved position (never
//! an image warp), then lighting and camera noise.
//!
//! Work is split into bands of rows rendered in parallel; every marker is
//! listed in each band it touches, in marker order, and all noise comes from a
//! counter-based hash of the pixel index, so the output is identical for any
//! number of threads.

use ndarray::Array2;
use rayon::prelude::*;

use super::config::{MarkerLayout, Markers, Rendered, SimConfig};
use super::rng::{SplitMix64, approx_normal_from_bits, hash64};
use optical_tactile::flow::FlowField;

/// Sampling steps (strip px, along x and y) of the mean-depth motion field used
/// between markers; coarser across, where the field of a rod changes only near
/// its ends.
pub(crate) const GRID_STEP: (usize, usize) = (4, 8);
/// Rows per parallel band.
const BAND_ROWS: usize = 16;
/// Spots are drawn out to this many standard deviations (the tail beyond is
/// below half a grey level for the brightest spots).
pub(crate) const SPOT_RADIUS_SIGMAS: f32 = 3.5;

/// The mean-depth motion grid: `(nx, ny, du, dv)`, node `(i, j)` at strip pixel
/// `(i * GRID_STEP.0, j * GRID_STEP.1)`.
pub(crate) type MotionGrid = (usize, usize, Vec<f32>, Vec<f32>);

struct Frame<'a> {
    cfg: &'a SimConfig,
    markers: &'a Markers,
    motion: &'a [(f32, f32)],
    grid: Option<&'a MotionGrid>,
    buckets: Vec<Vec<u32>>,
    width: usize,
    origin: (f32, f32),
    skin_box: (f32, f32, f32, f32),
    /// Which pixels show the skin, when its outline is curved ([`skin_mask`]).
    mask: Option<&'a [bool]>,
    /// Where the contacts change the gel's light.
    spots: &'a [LightSpot],
    gain: f32,
    /// The camera's black level on top of the light (exposure changes).
    offset: f32,
    stream: u64,
    blend_weight: f32,
}

/// The strip's origin in the rendered image, px.
fn origin(cfg: &SimConfig) -> (f32, f32) {
    if cfg.full_frame {
        (
            cfg.camera.strip_origin.0 as f32,
            cfg.camera.strip_origin.1 as f32,
        )
    } else {
        (0.0, 0.0)
    }
}

/// The skin's box in the rendered image before the lens's radial
/// distortion: `(x0, x1, y0, y1)`, px.
fn skin_box(cfg: &SimConfig, origin: (f32, f32)) -> (f32, f32, f32, f32) {
    let cam = &cfg.camera;
    let skin = &cfg.skin;
    let h = skin.half_length();
    (
        (cam.s_to_px(skin, -h) - 0.5) as f32 + origin.0,
        (cam.s_to_px(skin, h) + 0.5) as f32 + origin.0,
        (cam.y_to_px(-0.5 * skin.width_mm()) - 0.5) as f32 + origin.1,
        (cam.y_to_px(0.5 * skin.width_mm()) + 0.5) as f32 + origin.1,
    )
}

/// Behind a distorting lens the skin's outline is curved: which pixels of
/// the rendered image (row-major) show the skin, i.e. have their
/// undistorted position in the undistorted box. `None` without distortion
/// (the box decides). Made once per sensor.
pub(crate) fn skin_mask(cfg: &SimConfig) -> Option<Vec<bool>> {
    let cam = &cfg.camera;
    if cam.radial == 0.0 {
        return None;
    }
    let (width, height) = cfg.image_size();
    let origin = origin(cfg);
    let (bx0, bx1, by0, by1) = skin_box(cfg, origin);
    let mut mask = Vec::with_capacity(width * height);
    for y in 0..height {
        let yf = y as f32;
        for x in 0..width {
            let xf = x as f32;
            let (xu, yu) = cam.undistort(f64::from(xf - origin.0), f64::from(yf - origin.1));
            let (xu, yu) = (xu as f32 + origin.0, yu as f32 + origin.1);
            mask.push(yu >= by0 && yu <= by1 && xu >= bx0 && xu <= bx1);
        }
    }
    Some(mask)
}

/// Where a contact changes the gel's light
/// ([`crate::config::ContactLight`]): its centre in strip pixels and its
/// spreads along x and y (`sy` infinite for a rod across the strip).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct LightSpot {
    pub x: f32,
    pub y: f32,
    pub sx: f32,
    pub sy: f32,
}

/// The scene a frame shows beyond its markers: the gel's mask and the
/// contacts' changes of its light.
pub(crate) struct Scene<'a> {
    pub mask: Option<&'a [bool]>,
    pub spots: &'a [LightSpot],
}

pub(crate) fn render(
    cfg: &SimConfig,
    markers: &Markers,
    motion: &[(f32, f32)],
    grid: Option<&MotionGrid>,
    scene: Scene<'_>,
    stream: u64,
    camera: (f32, f32),
) -> Rendered {
    let (width, height) = cfg.image_size();
    let origin = origin(cfg);
    let skin_box = skin_box(cfg, origin);
    // Bucket markers by the row bands their spots touch.
    let nbands = height.div_ceil(BAND_ROWS);
    let mut buckets: Vec<Vec<u32>> = vec![Vec::new(); nbands];
    for i in 0..markers.s.len() {
        let cy = markers.py[i] as f32 + motion[i].1 + origin.1;
        let rad = markers.extent(i);
        let y0 = (cy - rad).floor().max(0.0);
        let y1 = (cy + rad).ceil().min(height as f32 - 1.0);
        if y1 < y0 {
            continue;
        }
        for b in (y0 as usize / BAND_ROWS)..=(y1 as usize / BAND_ROWS) {
            buckets[b].push(i as u32);
        }
    }
    let mut flicker = SplitMix64::new(stream ^ 0x5DEE_CE66_D1CE_4E5B);
    let gain = (1.0 + cfg.noise.flicker as f64 * flicker.normal()).max(0.0) as f32;
    // The exposure changes' gain (exactly 1 when there are none).
    let gain = gain * camera.0;
    let mean_amp = match &cfg.markers.layout {
        MarkerLayout::Random => 0.5 * (cfg.markers.brightness.0 + cfg.markers.brightness.1) as f32,
        MarkerLayout::Grid(g) => g.darkness as f32,
    };
    let f = Frame {
        cfg,
        markers,
        motion,
        grid,
        buckets,
        width,
        origin,
        skin_box,
        mask: scene.mask,
        spots: scene.spots,
        gain,
        offset: camera.1,
        stream,
        blend_weight: (0.05 * mean_amp).max(1e-3),
    };
    let mut img = vec![0.0f32; width * height];
    let chunk = BAND_ROWS * width;
    let flow = if grid.is_some() {
        let mut u = vec![0.0f32; width * height];
        let mut v = vec![0.0f32; width * height];
        img.par_chunks_mut(chunk)
            .zip(u.par_chunks_mut(chunk))
            .zip(v.par_chunks_mut(chunk))
            .enumerate()
            .for_each(|(b, ((rows, u), v))| f.band(b, rows, Some((u, v))));
        let u = Array2::from_shape_vec((height, width), u).expect("sized above");
        let v = Array2::from_shape_vec((height, width), v).expect("sized above");
        Some(FlowField { u, v })
    } else {
        img.par_chunks_mut(chunk)
            .enumerate()
            .for_each(|(b, rows)| f.band(b, rows, None));
        None
    };
    Rendered {
        frame: Array2::from_shape_vec((height, width), img).expect("sized above"),
        flow,
    }
}

impl Frame<'_> {
    /// The factor the contacts' light changes scale the light at rendered
    /// pixel `(x, y)` by (exactly 1 without any).
    fn contact_light(&self, x: f32, y: f32) -> f32 {
        if self.spots.is_empty() {
            return 1.0;
        }
        let light = &self.cfg.noise.contact_light;
        let change: f32 = self
            .spots
            .iter()
            .map(|s| {
                light.at(
                    x - self.origin.0 - s.x,
                    y - self.origin.1 - s.y,
                    (s.sx, s.sy),
                )
            })
            .sum();
        (1.0 + change).max(0.0)
    }

    fn band(&self, b: usize, rows: &mut [f32], flow: Option<(&mut [f32], &mut [f32])>) {
        let w = self.width;
        let y_start = b * BAND_ROWS;
        let nrows = rows.len() / w;
        let y_end = y_start + nrows - 1;
        let m = self.markers;
        // Weight sums for the truth flow: sum w, sum w du, sum w dv.
        let mut acc = if flow.is_some() {
            vec![[0.0f32; 3]; rows.len()]
        } else {
            Vec::new()
        };
        let mut ex: Vec<f32> = Vec::with_capacity(32);
        for &i in &self.buckets[b] {
            let i = i as usize;
            let (du, dv) = self.motion[i];
            let cx = m.px[i] as f32 + du + self.origin.0;
            let cy = m.py[i] as f32 + dv + self.origin.1;
            let sigma = m.sigma[i];
            let rad = m.extent(i);
            let x0 = (cx - rad).floor().max(0.0);
            let x1 = (cx + rad).ceil().min(w as f32 - 1.0);
            let y0 = (cy - rad).floor().max(y_start as f32);
            let y1 = (cy + rad).ceil().min(y_end as f32);
            if x1 < x0 || y1 < y0 {
                continue;
            }
            let (x0, x1, y0, y1) = (x0 as usize, x1 as usize, y0 as usize, y1 as usize);
            if !m.radius.is_empty() {
                // A dark dot: `amp` (negative) times its disc profile; the
                // truth weighs its motion by the darkness it adds.
                let (r, e, amp) = (m.radius[i], sigma, m.amp[i]);
                for y in y0..=y1 {
                    let dy = y as f32 - cy;
                    let off = (y - y_start) * w;
                    for x in x0..=x1 {
                        let dx = x as f32 - cx;
                        let p = dot_profile((dx * dx + dy * dy).sqrt(), r, e);
                        rows[off + x] += amp * p;
                        if !acc.is_empty() {
                            let wt = amp.abs() * p;
                            let a = &mut acc[off + x];
                            a[0] += wt;
                            a[1] += wt * du;
                            a[2] += wt * dv;
                        }
                    }
                }
                continue;
            }
            let inv = 1.0 / (2.0 * sigma * sigma);
            ex.clear();
            ex.extend((x0..=x1).map(|x| {
                let d = x as f32 - cx;
                (-d * d * inv).exp()
            }));
            let amp = m.amp[i];
            for y in y0..=y1 {
                let d = y as f32 - cy;
                let ey = amp * (-d * d * inv).exp();
                let off = (y - y_start) * w;
                let row = &mut rows[off + x0..=off + x1];
                for (p, &e) in row.iter_mut().zip(&ex) {
                    *p += ey * e;
                }
                if !acc.is_empty() {
                    let arow = &mut acc[off + x0..=off + x1];
                    for (a, &e) in arow.iter_mut().zip(&ex) {
                        let wt = ey * e;
                        a[0] += wt;
                        a[1] += wt * du;
                        a[2] += wt * dv;
                    }
                }
            }
        }
        // Lighting and noise.
        let cfg = self.cfg;
        let n = &cfg.noise;
        let (bx0, bx1, by0, by1) = self.skin_box;
        let (ox, oy) = if cfg.full_frame {
            (0.0, 0.0)
        } else {
            (
                cfg.camera.strip_origin.0 as f32,
                cfg.camera.strip_origin.1 as f32,
            )
        };
        let read2 = n.read * n.read;
        for r in 0..nrows {
            let y = y_start + r;
            let yf = y as f32;
            let in_y = yf >= by0 && yf <= by1;
            for x in 0..w {
                let xf = x as f32;
                let inside = match self.mask {
                    Some(m) => m[y * w + x],
                    None => in_y && xf >= bx0 && xf <= bx1,
                };
                let bg = if inside { n.background } else { n.outside };
                let k = r * w + x;
                // Overlapping dark dots cannot take away more light than
                // there is.
                let light = ((bg + rows[k]).max(0.0)
                    * cfg.camera.vignetting(n.vignetting, xf + ox, yf + oy)
                    * self.gain
                    * self.contact_light(xf, yf))
                .max(0.0);
                let sd = (n.shot * light + read2).sqrt();
                let z = approx_normal_from_bits(hash64(self.stream, (y * w + x) as u64));
                rows[k] = (light + sd * z + self.offset).round().clamp(0.0, 255.0);
            }
        }
        if let (Some((u, v)), Some(grid)) = (flow, self.grid) {
            let w0 = self.blend_weight;
            let strip_w = cfg.camera.strip_width as f32;
            let strip_h = cfg.camera.strip_height as f32;
            for r in 0..nrows {
                let yf = (y_start + r) as f32 - self.origin.1;
                for x in 0..w {
                    let xf = x as f32 - self.origin.0;
                    let k = r * w + x;
                    if xf < 0.0 || yf < 0.0 || xf > strip_w - 1.0 || yf > strip_h - 1.0 {
                        u[k] = 0.0;
                        v[k] = 0.0;
                        continue;
                    }
                    let (gu, gv) = sample_grid(grid, xf, yf);
                    let a = acc[k];
                    let den = a[0] + w0;
                    u[k] = (a[1] + w0 * gu) / den;
                    v[k] = (a[2] + w0 * gv) / den;
                }
            }
        }
    }
}

/// A dot's darkness profile at distance `d` from its centre: 1 inside,
/// 0 outside, a smoothstep across the edge `r - e ..= r + e` (a hard edge
/// when `e` is 0).
#[inline]
pub(crate) fn dot_profile(d: f32, r: f32, e: f32) -> f32 {
    if e <= 0.0 {
        return if d <= r { 1.0 } else { 0.0 };
    }
    let t = ((r + e - d) / (2.0 * e)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Bilinear sample of the motion grid at strip pixel `(x, y)`.
#[inline]
pub(crate) fn sample_grid(grid: &MotionGrid, x: f32, y: f32) -> (f32, f32) {
    let (nx, ny, du, dv) = grid;
    let gx = (x / GRID_STEP.0 as f32).clamp(0.0, (*nx - 1) as f32);
    let gy = (y / GRID_STEP.1 as f32).clamp(0.0, (*ny - 1) as f32);
    let i0 = (gx as usize).min(nx - 2);
    let j0 = (gy as usize).min(ny - 2);
    let (fx, fy) = (gx - i0 as f32, gy - j0 as f32);
    let at = |f: &Vec<f32>, i: usize, j: usize| f[j * nx + i];
    let bil = |f: &Vec<f32>| {
        (1.0 - fy) * ((1.0 - fx) * at(f, i0, j0) + fx * at(f, i0 + 1, j0))
            + fy * ((1.0 - fx) * at(f, i0, j0 + 1) + fx * at(f, i0 + 1, j0 + 1))
    };
    (bil(du), bil(dv))
}
