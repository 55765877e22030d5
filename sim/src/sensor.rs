//! [`SyntheticSensor`]: configuration, markers, contacts -> marker motion.

use ndarray::Array2;
use optical_tactile::error::{Error, Result};
use optical_tactile::flow::FlowField;
use rayon::prelude::*;

use super::config::{DotGrid, MarkerLayout, Markers, Rendered, SimConfig};
use super::elastic::{Load, QuadratureCache, RodLoad, RoundLoad, hertz_half_width};
use super::render;
use super::rng::{SplitMix64, mix64};

/// One contact, given in the sensor frame (docs/pipeline.md): a rod lying
/// across the whole width of the skin at chord position `x_mm`, or a round
/// tip (a fingertip, a sphere) centred at `(x_mm, y_mm)` ([`Press::fingertip`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Press {
    /// Chord position of the rod's axis, mm (sensor x).
    pub x_mm: f64,
    /// Force the rod applies on the skin, sensor frame, N: `[Fx, Fy, Fz]`; a
    /// press has `Fz < 0`.
    pub force_n: [f64; 3],
    /// Rod (indenter) diameter, mm (2-10 in the characterization).
    pub diameter_mm: f64,
    /// Width of the pressed area along the skin, mm: `None` takes the
    /// Hertz contact width of the rod on the gel (about 1-8 mm for the
    /// characterization's rods), a number spreads the load over that width
    /// with the same elliptic pressure ([`Press::pad`]). For a round tip, a
    /// number is the contact's diameter instead of the one its force gives.
    pub contact_width_mm: Option<f64>,
    /// Across position of a round tip's centre, mm (sensor y): `None` for a
    /// rod across the whole width. A round tip of diameter `diameter_mm`
    /// loads a thin layer bonded to a rigid base
    /// ([`RoundLoad`](crate::elastic::RoundLoad)), the build of flat fingertip
    /// sensors.
    pub y_mm: Option<f64>,
}

impl Press {
    /// A rod of `diameter_mm` at chord `x_mm` applying `force_n` (sensor frame).
    pub fn rod(x_mm: f64, force_n: [f64; 3], diameter_mm: f64) -> Self {
        Press {
            x_mm,
            force_n,
            diameter_mm,
            contact_width_mm: None,
            y_mm: None,
        }
    }

    /// A broad soft press, like a fingertip's: `force_n` spread over
    /// `width_mm` along the skin (elliptic pressure, e.g. 15-25 mm wide)
    /// and across the skin's whole width, centred at chord `x_mm`.
    pub fn pad(x_mm: f64, force_n: [f64; 3], width_mm: f64) -> Self {
        Press {
            x_mm,
            force_n,
            diameter_mm: width_mm,
            contact_width_mm: Some(width_mm),
            y_mm: None,
        }
    }

    /// A round tip of `diameter_mm` (a fingertip: 15-20 mm; a spherical
    /// indenter) centred at `(x_mm, y_mm)` applying `force_n`, on a thin
    /// gel layer bonded to a rigid base: the gel squeezed from under it
    /// spreads outward, and its contact grows with the force
    /// ([`RoundLoad::sphere_contact_radius`](crate::elastic::RoundLoad::sphere_contact_radius)).
    pub fn fingertip(x_mm: f64, y_mm: f64, force_n: [f64; 3], diameter_mm: f64) -> Self {
        Press {
            x_mm,
            force_n,
            diameter_mm,
            contact_width_mm: None,
            y_mm: Some(y_mm),
        }
    }
}

impl Press {
    /// A spherical tip of `diameter_mm` centred at `(x_mm, y_mm)` applying
    /// `force_n`, on a thin gel layer bonded to a rigid base: the round load
    /// of [`Press::fingertip`] (the same model; "fingertip" names a broad
    /// tip of 15-20 mm, "sphere" a rigid indenter of a few mm). The contact
    /// radius is the thin-layer sphere's
    /// ([`RoundLoad::sphere_contact_radius`](crate::elastic::RoundLoad::sphere_contact_radius)),
    /// growing with the force as `F^(1/6)`. For a tip narrower than the
    /// layer is thick that radius can exceed the tip's own: the layer
    /// spreads a small tip's load over about its thickness, and the
    /// thin-layer limit cannot describe a load concentrated on less, so the
    /// radius is kept as the formula gives it.
    pub fn sphere(x_mm: f64, y_mm: f64, force_n: [f64; 3], diameter_mm: f64) -> Self {
        Press::fingertip(x_mm, y_mm, force_n, diameter_mm)
    }

    /// A flat circular punch of `diameter_mm` centred at `(x_mm, y_mm)`
    /// applying `force_n`. Approximation: the round load of a fixed contact
    /// diameter (the punch's), with the smooth pressure profile
    /// `(1 - r^2/a^2)^2` of [`RoundLoad`](crate::elastic::RoundLoad) rather
    /// than a rigid punch's pressure rising towards its edge. The total force
    /// and the pressed area are the punch's; the motion is smoother at its
    /// rim than a real punch's, and it does not grow with the force as a
    /// sphere's does.
    pub fn punch(x_mm: f64, y_mm: f64, force_n: [f64; 3], diameter_mm: f64) -> Self {
        Press {
            x_mm,
            force_n,
            diameter_mm,
            contact_width_mm: Some(diameter_mm),
            y_mm: Some(y_mm),
        }
    }
}

/// A round indenter of a flat sensor, by kind and diameter (mm): what the
/// flat characterization protocol and the presses on a flat sensor press
/// with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Tip {
    /// A rigid sphere ([`Press::sphere`]), e.g. 3-12 mm.
    Sphere(f64),
    /// A flat circular punch ([`Press::punch`]), e.g. 3-12 mm.
    Punch(f64),
    /// A broad soft tip like a human fingertip ([`Press::fingertip`]),
    /// 15-20 mm.
    Fingertip(f64),
}

impl Tip {
    /// The indenter's diameter, mm.
    pub fn diameter_mm(&self) -> f64 {
        match *self {
            Tip::Sphere(d) | Tip::Punch(d) | Tip::Fingertip(d) => d,
        }
    }

    /// The kind's name in files: `sphere`, `punch` or `fingertip`.
    pub fn kind(&self) -> &'static str {
        match self {
            Tip::Sphere(_) => "sphere",
            Tip::Punch(_) => "punch",
            Tip::Fingertip(_) => "fingertip",
        }
    }

    /// This indenter centred at `(x_mm, y_mm)` applying `force_n` (sensor
    /// frame).
    pub fn press(&self, x_mm: f64, y_mm: f64, force_n: [f64; 3]) -> Press {
        match *self {
            Tip::Sphere(d) => Press::sphere(x_mm, y_mm, force_n, d),
            Tip::Punch(d) => Press::punch(x_mm, y_mm, force_n, d),
            Tip::Fingertip(d) => Press::fingertip(x_mm, y_mm, force_n, d),
        }
    }

    /// Radius (mm) of the pressed area under a normal force `f_n` (N) on a
    /// gel of `mat`: the punch's own radius, a sphere's or a fingertip's
    /// from the thin-layer formula.
    pub fn contact_radius_mm(&self, mat: &crate::Material, f_n: f64) -> f64 {
        match *self {
            Tip::Punch(d) => 0.5 * d,
            Tip::Sphere(d) | Tip::Fingertip(d) => {
                RoundLoad::sphere_contact_radius(mat, 0.5 * d, f_n)
            }
        }
    }
}

/// A synthetic marker-based tactile sensor: build it once from a config and a
/// seed (which fixes the marker layout), then render frames for any contacts.
///
/// ```
/// use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};
/// let mut sensor = SyntheticSensor::new(SimConfig::default(), 42)?;
/// let reference = sensor.render(&[])?.0;
/// let press = Press::rod(-20.0, [0.0, 0.0, -2.0], 5.0);
/// let (frame, truth) = sensor.render(&[press])?;
/// assert_eq!(frame.dim(), reference.dim());
/// assert!(truth.magnitude().iter().cloned().fold(0.0, f32::max) > 0.3);
/// # Ok::<(), optical_tactile::Error>(())
/// ```
#[derive(Debug, Clone)]
pub struct SyntheticSensor {
    config: SimConfig,
    seed: u64,
    markers: Markers,
    /// Which pixels show the skin behind a distorting lens.
    skin_mask: Option<Vec<bool>>,
    quad: QuadratureCache,
    next_index: u64,
}

/// Displacement of the markers in image pixels `(du, dv)`, one per marker.
pub(crate) type PixelMotion = Vec<(f32, f32)>;

impl SyntheticSensor {
    /// Builds the sensor: validates `config` and scatters the markers from `seed`.
    pub fn new(config: SimConfig, seed: u64) -> Result<Self> {
        config.validate()?;
        let markers = scatter_markers(&config, seed);
        Ok(SyntheticSensor {
            config,
            seed,
            markers,
            skin_mask: render::skin_mask(&config),
            quad: QuadratureCache::default(),
            next_index: 0,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &SimConfig {
        &self.config
    }

    /// The seed the sensor was built with.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// Number of markers.
    pub fn marker_count(&self) -> usize {
        self.markers.s.len()
    }

    /// Index of the next frame [`SyntheticSensor::render`] makes (noise and
    /// flicker are drawn per frame index).
    pub fn frame_index(&self) -> u64 {
        self.next_index
    }

    /// Turns contacts into loads on the unrolled skin, checking them.
    pub fn loads(&self, contacts: &[Press]) -> Result<Vec<Load>> {
        let skin = &self.config.skin;
        let mat = &self.config.material;
        contacts
            .iter()
            .map(|c| {
                if !c.force_n.iter().all(|f| f.is_finite()) {
                    return Err(Error::param(
                        "force_n",
                        format!("must be finite, got {:?}", c.force_n),
                    ));
                }
                if !(c.diameter_mm.is_finite() && c.diameter_mm > 0.0) {
                    return Err(Error::param(
                        "diameter_mm",
                        format!("rod diameter must be > 0, got {}", c.diameter_mm),
                    ));
                }
                let s = skin.chord_to_arc(c.x_mm)?;
                let local = skin.force_to_local(c.x_mm, c.force_n);
                let f_in = -local[2];
                if f_in < -1e-12 {
                    return Err(Error::param(
                        "force_n",
                        format!(
                            "the force {:?} at x = {} mm pulls the skin outward (normal component \
                             {:.3} N out of the gel); a rod can only press",
                            c.force_n, c.x_mm, local[2]
                        ),
                    ));
                }
                let w = skin.width_mm();
                if let Some(y) = c.y_mm {
                    if !(y.is_finite() && y.abs() <= 0.5 * w) {
                        return Err(Error::param(
                            "y_mm",
                            format!("must lie on the skin (|y| <= {} mm), got {y}", 0.5 * w),
                        ));
                    }
                    let radius = match c.contact_width_mm {
                        None => RoundLoad::sphere_contact_radius(mat, 0.5 * c.diameter_mm, f_in),
                        Some(width) if width.is_finite() && width > 0.0 => 0.5 * width,
                        Some(width) => {
                            return Err(Error::param(
                                "contact_width_mm",
                                format!("must be finite and > 0, got {width}"),
                            ));
                        }
                    };
                    return Ok(Load::Round(RoundLoad {
                        s_mm: s,
                        y_mm: y,
                        radius,
                        force: [local[0], local[1], f_in],
                    }));
                }
                let b = match c.contact_width_mm {
                    None => hertz_half_width(mat, 0.5 * c.diameter_mm, skin.radius_mm(), f_in / w),
                    Some(width) if width.is_finite() && width > 0.0 => 0.5 * width,
                    Some(width) => {
                        return Err(Error::param(
                            "contact_width_mm",
                            format!("must be finite and > 0, got {width}"),
                        ));
                    }
                };
                Ok(Load::Rod(RodLoad {
                    s_mm: s,
                    y_lo: -0.5 * w,
                    y_hi: 0.5 * w,
                    half_width: b,
                    force: [local[0], local[1], f_in],
                }))
            })
            .collect()
    }

    /// Displacement (mm, local frame `[along s, across, into the gel]`) at a point
    /// of the gel `(s, y, depth)` under `loads`.
    pub fn displacement_at(&self, loads: &[Load], s: f64, y: f64, depth: f64) -> [f64; 3] {
        let mut u = [0.0; 3];
        for l in loads {
            let d = l.layer(&self.config.material, &self.quad, s, y, depth);
            for k in 0..3 {
                u[k] += d[k];
            }
        }
        u
    }

    /// Every marker's displacement (mm, local frame) under `contacts`.
    pub fn marker_displacements(&self, contacts: &[Press]) -> Result<Vec<[f64; 3]>> {
        let loads = self.loads(contacts)?;
        let m = &self.markers;
        Ok((0..m.s.len())
            .into_par_iter()
            .with_min_len(256)
            .map(|i| self.displacement_at(&loads, m.s[i], m.y[i], m.z[i]))
            .collect())
    }

    /// Rest positions of the markers: `(s_mm, y_mm, depth_mm, x_px, y_px)` with
    /// pixel positions in the strip image.
    pub fn marker_positions(&self) -> Vec<(f64, f64, f64, f64, f64)> {
        let m = &self.markers;
        (0..m.s.len())
            .map(|i| (m.s[i], m.y[i], m.z[i], m.px[i], m.py[i]))
            .collect()
    }

    /// Image motion (px) of a point at `(s, y)` displaced by `u` (mm, local).
    #[inline]
    fn to_pixels(&self, s: f64, y: f64, u: [f64; 3]) -> (f32, f32) {
        let cam = &self.config.camera;
        let skin = &self.config.skin;
        if cam.radial == 0.0 {
            let du = cam.s_to_px(skin, s + u[0]) - cam.s_to_px(skin, s);
            let dv = cam.px_per_mm_y * u[1];
            return (du as f32, dv as f32);
        }
        let (x0, y0) = cam.skin_to_px(skin, s, y);
        let (x1, y1) = cam.skin_to_px(skin, s + u[0], y + u[1]);
        ((x1 - x0) as f32, (y1 - y0) as f32)
    }

    pub(crate) fn marker_pixel_motion(&self, loads: &[Load]) -> PixelMotion {
        let m = &self.markers;
        if loads.is_empty() {
            return vec![(0.0, 0.0); m.s.len()];
        }
        (0..m.s.len())
            .into_par_iter()
            .with_min_len(256)
            .map(|i| {
                let u = self.displacement_at(loads, m.s[i], m.y[i], m.z[i]);
                self.to_pixels(m.s[i], m.y[i], u)
            })
            .collect()
    }

    /// The motion field at the markers' mean depth, sampled every `step` strip
    /// pixels along x and y (the truth flow between markers). Returns
    /// `(nx, ny, du, dv)`.
    pub(crate) fn mean_depth_grid(
        &self,
        loads: &[Load],
        step: (usize, usize),
    ) -> (usize, usize, Vec<f32>, Vec<f32>) {
        let cam = &self.config.camera;
        let skin = &self.config.skin;
        let nx = cam.strip_width.div_ceil(step.0) + 1;
        let ny = cam.strip_height.div_ceil(step.1) + 1;
        let depth = 0.5 * (self.config.markers.depth_mm.0 + self.config.markers.depth_mm.1);
        let half_w = 0.5 * skin.width_mm();
        let h = skin.half_length();
        let pts: Vec<(f32, f32)> = (0..nx * ny)
            .into_par_iter()
            .with_min_len(64)
            .map(|k| {
                if loads.is_empty() {
                    return (0.0, 0.0);
                }
                let (gx, gy) = (k % nx, k / nx);
                // Clamp to the skin: outside it the field is that of its edge.
                let (s, y) = cam.px_to_skin(skin, (gx * step.0) as f64, (gy * step.1) as f64);
                let (s, y) = (s.clamp(-h, h), y.clamp(-half_w, half_w));
                self.to_pixels(s, y, self.displacement_at(loads, s, y, depth))
            })
            .collect();
        let (du, dv) = pts.into_iter().unzip();
        (nx, ny, du, dv)
    }

    /// Renders the next frame (frame index advancing by one per call) for
    /// `contacts`, with its true dense motion.
    ///
    /// The truth flow at a pixel is the brightness-weighted mean image motion of
    /// the marker spots covering it, blended smoothly (weight of a faint spot)
    /// with the motion field at the markers' mean depth, which is what remains
    /// between markers. It is the motion from the unloaded skin, i.e. what a
    /// flow from an unloaded reference frame should find.
    pub fn render(&mut self, contacts: &[Press]) -> Result<(Array2<f32>, FlowField)> {
        let r = self.render_indexed(self.next_index, contacts, true)?;
        self.next_index += 1;
        let flow = r.flow.expect("flow requested");
        Ok((r.frame, flow))
    }

    /// Renders frame number `index` (which fixes its noise and flicker) without
    /// touching the frame counter; the flow only when `with_flow`.
    pub fn render_indexed(
        &self,
        index: u64,
        contacts: &[Press],
        with_flow: bool,
    ) -> Result<Rendered> {
        let loads = self.loads(contacts)?;
        let motion = self.marker_pixel_motion(&loads);
        let grid = if with_flow {
            Some(self.mean_depth_grid(&loads, render::GRID_STEP))
        } else {
            None
        };
        let stream = mix64(self.seed ^ 0xA076_1D64_78BD_642F) ^ mix64(index.wrapping_add(1));
        let camera = self.config.noise.exposure.response(self.seed, index);
        let spots = self.light_spots(&loads);
        let scene = render::Scene {
            mask: self.skin_mask.as_deref(),
            spots: &spots,
        };
        Ok(render::render(
            &self.config,
            &self.markers,
            &motion,
            grid.as_ref(),
            scene,
            stream,
            camera,
        ))
    }

    /// Where `loads` change the gel's light
    /// ([`crate::config::NoiseConfig::contact_light`]; none when it is off):
    /// each load's centre in strip pixels, and spreads of two thirds of its
    /// radius (a rod's half-width along the strip; across it, none).
    fn light_spots(&self, loads: &[Load]) -> Vec<render::LightSpot> {
        if !self.config.noise.contact_light.is_on() {
            return Vec::new();
        }
        let (skin, cam) = (&self.config.skin, &self.config.camera);
        loads
            .iter()
            .map(|load| {
                let (s, y, a, across) = match load {
                    Load::Round(r) => (r.s_mm, r.y_mm, r.radius, true),
                    Load::Rod(r) => (r.s_mm, 0.5 * (r.y_lo + r.y_hi), r.half_width, false),
                };
                let spread = (2.0 / 3.0 * a).max(0.05);
                let (x, yp) = cam.skin_to_px(skin, s, y);
                let sx = 0.5 * (cam.s_to_px(skin, s + spread) - cam.s_to_px(skin, s - spread));
                let sy = if across {
                    spread * cam.px_per_mm_y
                } else {
                    f64::INFINITY
                };
                render::LightSpot {
                    x: x as f32,
                    y: yp as f32,
                    sx: (sx as f32).max(0.5),
                    sy: (sy as f32).max(0.5),
                }
            })
            .collect()
    }
}

/// Places the markers: scattered uniformly over the skin (Poisson-like
/// random layout) or on a regular grid of dots.
fn scatter_markers(config: &SimConfig, seed: u64) -> Markers {
    let mc = &config.markers;
    if let MarkerLayout::Grid(g) = &mc.layout {
        return grid_markers(config, g, seed);
    }
    let skin = &config.skin;
    let cam = &config.camera;
    let mut rng = SplitMix64::new(mix64(seed));
    let h = skin.half_length();
    let half_w = 0.5 * skin.width_mm();
    let count = mc.count.unwrap_or_else(|| {
        // Covered fraction of randomly placed discs: 1 - exp(-n a / A).
        let area_px =
            (cam.s_to_px(skin, h) - cam.s_to_px(skin, -h)) * cam.px_per_mm_y * skin.width_mm();
        let mean_d = 0.5 * (mc.fwhm_px.0 + mc.fwhm_px.1);
        let disc = std::f64::consts::PI * 0.25 * mean_d * mean_d;
        ((-(1.0 - mc.coverage).ln()) * area_px / disc)
            .round()
            .max(1.0) as usize
    });
    let mut m = Markers::default();
    for _ in 0..count {
        let s = rng.uniform(-h, h);
        let y = rng.uniform(-half_w, half_w);
        let z = rng.uniform(mc.depth_mm.0, mc.depth_mm.1);
        let fwhm = rng.uniform(mc.fwhm_px.0, mc.fwhm_px.1);
        let amp = rng.uniform(mc.brightness.0, mc.brightness.1);
        m.s.push(s);
        m.y.push(y);
        m.z.push(z);
        let (px, py) = cam.skin_to_px(skin, s, y);
        m.px.push(px);
        m.py.push(py);
        m.amp.push(amp as f32);
        m.sigma.push((fwhm / (8.0 * 2f64.ln()).sqrt()) as f32);
    }
    m
}

/// A regular grid of dots every `pitch_px` over the skin's image, centred on
/// it, each moved by up to `jitter_px` (from the seed), all at the mean depth.
fn grid_markers(config: &SimConfig, g: &DotGrid, seed: u64) -> Markers {
    let skin = &config.skin;
    let cam = &config.camera;
    let mut rng = SplitMix64::new(mix64(seed));
    let h = skin.half_length();
    let half_w = 0.5 * skin.width_mm();
    let (x_lo, x_hi) = (cam.s_to_px(skin, -h), cam.s_to_px(skin, h));
    let (y_lo, y_hi) = (cam.y_to_px(-half_w), cam.y_to_px(half_w));
    let count = |span: f64| ((span / g.pitch_px).floor() as usize).max(1);
    let (nx, ny) = (count(x_hi - x_lo), count(y_hi - y_lo));
    let first = |lo: f64, hi: f64, n: usize| 0.5 * (lo + hi) - 0.5 * (n - 1) as f64 * g.pitch_px;
    let (fx, fy) = (first(x_lo, x_hi, nx), first(y_lo, y_hi, ny));
    let depth = 0.5 * (config.markers.depth_mm.0 + config.markers.depth_mm.1);
    let mut m = Markers::default();
    for row in 0..ny {
        for col in 0..nx {
            let jx = rng.uniform(-g.jitter_px, g.jitter_px);
            let jy = rng.uniform(-g.jitter_px, g.jitter_px);
            let x = (fx + col as f64 * g.pitch_px + jx).clamp(x_lo, x_hi);
            let y = (fy + row as f64 * g.pitch_px + jy).clamp(y_lo, y_hi);
            let s = cam.px_to_s(skin, x).clamp(-h, h);
            let yy = cam.px_to_y(y).clamp(-half_w, half_w);
            m.s.push(s);
            m.y.push(yy);
            m.z.push(depth);
            // Printed on a regular grid in mm; the lens bends it in the image.
            let (px, py) = cam.skin_to_px(skin, s, yy);
            m.px.push(px);
            m.py.push(py);
            m.amp.push(-g.darkness as f32);
            m.sigma.push((0.5 * g.edge_px) as f32);
            m.radius.push((0.5 * g.diameter_px) as f32);
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Slow oracle: every marker summed over the whole image in f64, no bands,
    /// no windows beyond the same spot radius, then the same lighting.
    #[test]
    fn banded_renderer_matches_a_naive_sum() {
        let mut cfg = SimConfig::default();
        cfg.markers.count = Some(3000);
        cfg.noise.shot = 0.0;
        cfg.noise.read = 0.0;
        cfg.noise.flicker = 0.0;
        let s = SyntheticSensor::new(cfg, 5).unwrap();
        let contacts = [Press::rod(10.0, [0.2, 0.0, -2.5], 5.0)];
        let r = s.render_indexed(3, &contacts, true).unwrap();
        let loads = s.loads(&contacts).unwrap();
        let motion = s.marker_pixel_motion(&loads);
        let m = &s.markers;
        let (w, h) = cfg.image_size();
        let mut sig = vec![0.0f64; w * h];
        let mut acc = vec![[0.0f64; 3]; w * h];
        for i in 0..m.s.len() {
            let cx = m.px[i] + motion[i].0 as f64;
            let cy = m.py[i] + motion[i].1 as f64;
            let sg = m.sigma[i] as f64;
            let rad = render::SPOT_RADIUS_SIGMAS as f64 * sg;
            // Every pixel whose centre lies in the spot's radius box (the
            // renderer's window), found by scanning all rows and columns.
            let (x0, x1) = ((cx - rad).floor(), (cx + rad).ceil());
            let (y0, y1) = ((cy - rad).floor(), (cy + rad).ceil());
            for y in (0..h).filter(|&y| y as f64 >= y0 && y as f64 <= y1) {
                for x in (0..w).filter(|&x| x as f64 >= x0 && x as f64 <= x1) {
                    let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                    let g = m.amp[i] as f64 * (-(dx * dx + dy * dy) / (2.0 * sg * sg)).exp();
                    sig[y * w + x] += g;
                    acc[y * w + x][0] += g;
                    acc[y * w + x][1] += g * motion[i].0 as f64;
                    acc[y * w + x][2] += g * motion[i].1 as f64;
                }
            }
        }
        let skin = &cfg.skin;
        let cam = &cfg.camera;
        let hl = skin.half_length();
        let (bx0, bx1) = (cam.s_to_px(skin, -hl) - 0.5, cam.s_to_px(skin, hl) + 0.5);
        let (by0, by1) = (
            cam.y_to_px(-0.5 * skin.width_mm()) - 0.5,
            cam.y_to_px(0.5 * skin.width_mm()) + 0.5,
        );
        let flow = r.flow.unwrap();
        let grid = s.mean_depth_grid(&loads, render::GRID_STEP);
        let w0 = 0.05 * 0.5 * (cfg.markers.brightness.0 + cfg.markers.brightness.1);
        let mut worst = 0.0f64;
        for y in 0..h {
            for x in 0..w {
                let (xf, yf) = (x as f64, y as f64);
                let inside = xf >= bx0 && xf <= bx1 && yf >= by0 && yf <= by1;
                let bg = if inside {
                    cfg.noise.background
                } else {
                    cfg.noise.outside
                } as f64;
                let (ox, oy) = cam.strip_origin;
                let vig =
                    cam.vignetting(cfg.noise.vignetting, (x + ox) as f32, (y + oy) as f32) as f64;
                let want = ((bg + sig[y * w + x]) * vig).clamp(0.0, 255.0);
                let got = r.frame[[y, x]] as f64;
                worst = worst.max((got - want).abs());
                // The flow: brightness-weighted spot motion blended with the
                // mean-depth field.
                let a = acc[y * w + x];
                let (gu, gv) = render::sample_grid(&grid, xf as f32, yf as f32);
                let u = (a[1] + w0 * gu as f64) / (a[0] + w0);
                let v = (a[2] + w0 * gv as f64) / (a[0] + w0);
                assert!((flow.u[[y, x]] as f64 - u).abs() < 1e-4, "u at {x},{y}");
                assert!((flow.v[[y, x]] as f64 - v).abs() < 1e-4, "v at {x},{y}");
            }
        }
        // Rounding to integer grey levels costs 0.5; f32 sums of up to ~255 add
        // a few 1e-3.
        assert!(worst <= 0.5 + 1e-2, "worst pixel error {worst}");
    }

    #[test]
    fn render_advances_the_frame_index() {
        let mut cfg = SimConfig::default();
        cfg.markers.count = Some(500);
        let mut s = SyntheticSensor::new(cfg, 2).unwrap();
        let (a, _) = s.render(&[]).unwrap();
        let (b, _) = s.render(&[]).unwrap();
        assert_eq!(s.frame_index(), 2);
        assert_eq!(a, s.render_indexed(0, &[], false).unwrap().frame);
        assert_eq!(b, s.render_indexed(1, &[], false).unwrap().frame);
        assert_ne!(a, b);
    }
}
