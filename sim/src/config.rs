//! What defines a synthetic sensor ([`SimConfig`]: markers, camera noise,
//! camera model, material) and what rendering produces ([`Rendered`]).

use ndarray::Array2;
use optical_tactile::error::{Error, Result};
use optical_tactile::flow::FlowField;

use super::camera::{CameraModel, Skin};
use super::elastic::Material;
use super::rng::{hash64, mix64};

/// How the markers are scattered and how they look.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerConfig {
    /// Fraction of the skin image covered by spots (0.25-0.35 looks like the real
    /// sensor); sets the marker count unless `count` is given.
    pub coverage: f64,
    /// Explicit marker count (overrides `coverage`).
    pub count: Option<usize>,
    /// Range of spot full widths at half maximum, px.
    pub fwhm_px: (f64, f64),
    /// Range of marker depths below the contact surface, mm.
    pub depth_mm: (f64, f64),
    /// Range of peak spot brightness, 8-bit grey levels.
    pub brightness: (f64, f64),
    /// Where the markers lie and what they look like: random fluorescent
    /// spots (the default; every field above applies) or a regular grid of
    /// dark dots ([`DotGrid`]; only `depth_mm` applies).
    pub layout: MarkerLayout,
}

/// The marker layout of a [`MarkerConfig`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum MarkerLayout {
    /// Bright Gaussian spots scattered uniformly at random over the skin, at
    /// random depths, sizes and brightnesses (the reference design's
    /// fluorescent beads).
    #[default]
    Random,
    /// A regular grid of dark dots (GelSight-like printed markers), one
    /// depth for all: the mean of [`MarkerConfig::depth_mm`]. Meant for a
    /// bright, lit gel ([`SimConfig::dot_grid`]).
    Grid(DotGrid),
}

/// A regular grid of dark dots with soft edges, centred on the skin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DotGrid {
    /// Distance between neighbouring dot centres along both image axes, px.
    pub pitch_px: f64,
    /// Dot diameter (where the edge is half dark), px.
    pub diameter_px: f64,
    /// Width of the dot's soft edge (dark to clear), px; 0 is a hard edge.
    pub edge_px: f64,
    /// Each dot is moved off the grid by up to this many px along each axis
    /// (uniform, from the seed); 0 is a perfect grid.
    pub jitter_px: f64,
    /// Grey levels a dot takes from the lit gel at its centre.
    pub darkness: f64,
}

impl Default for DotGrid {
    /// 8 px dots every 30 px, a 1.5 px edge, no jitter, 140 grey levels dark.
    fn default() -> Self {
        DotGrid {
            pitch_px: 30.0,
            diameter_px: 8.0,
            edge_px: 1.5,
            jitter_px: 0.0,
            darkness: 140.0,
        }
    }
}

impl DotGrid {
    /// Checks the numbers: dots that fit between their neighbours, jitter
    /// included, and a darkness on the 8-bit scale.
    pub fn validate(&self) -> Result<()> {
        let g = self;
        if !(g.pitch_px.is_finite() && (4.0..=1000.0).contains(&g.pitch_px)) {
            return Err(Error::param(
                "markers.grid.pitch_px",
                format!("must lie in 4..=1000 px, got {}", g.pitch_px),
            ));
        }
        if !(g.diameter_px.is_finite() && g.diameter_px >= 1.0) {
            return Err(Error::param(
                "markers.grid.diameter_px",
                format!("must be finite and >= 1 px, got {}", g.diameter_px),
            ));
        }
        if !(g.edge_px.is_finite() && (0.0..=g.diameter_px).contains(&g.edge_px)) {
            return Err(Error::param(
                "markers.grid.edge_px",
                format!("must lie in 0..=diameter_px, got {}", g.edge_px),
            ));
        }
        if !(g.jitter_px.is_finite() && g.jitter_px >= 0.0) {
            return Err(Error::param(
                "markers.grid.jitter_px",
                format!("must be finite and >= 0, got {}", g.jitter_px),
            ));
        }
        let span = g.diameter_px + g.edge_px + 2.0 * g.jitter_px;
        if span >= g.pitch_px {
            return Err(Error::param(
                "markers.grid",
                format!(
                    "dots of {} px with a {} px edge and {} px of jitter touch their \
                     neighbours {} px away",
                    g.diameter_px, g.edge_px, g.jitter_px, g.pitch_px
                ),
            ));
        }
        if !(g.darkness.is_finite() && (0.0..=255.0).contains(&g.darkness)) {
            return Err(Error::param(
                "markers.grid.darkness",
                format!("must lie in 0..=255, got {}", g.darkness),
            ));
        }
        Ok(())
    }
}

impl Default for MarkerConfig {
    fn default() -> Self {
        MarkerConfig {
            coverage: 0.3,
            count: None,
            fwhm_px: (2.5, 3.0),
            depth_mm: (0.5, 4.0),
            brightness: (70.0, 200.0),
            layout: MarkerLayout::Random,
        }
    }
}

/// Camera noise and lighting.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseConfig {
    /// Grey level of the gel between markers (black coating seen through it).
    pub background: f32,
    /// Grey level outside the skin (strip margins, rest of the full frame).
    pub outside: f32,
    /// Shot-noise variance per grey level (variance = `shot * I + read^2`).
    pub shot: f32,
    /// Read-noise standard deviation, grey levels.
    pub read: f32,
    /// Relative standard deviation of the per-frame brightness flicker.
    pub flicker: f32,
    /// Vignetting strength: gain `1 - v r^2` at relative radius `r` in the full frame.
    pub vignetting: f32,
    /// Changes of the camera's gain and black level over time: exposure
    /// steps and slow drift (none by default).
    pub exposure: ExposureChanges,
    /// How the gel's light changes under each contact (none by default).
    pub contact_light: ContactLight,
}

/// How the gel's light changes under a contact, relative to the unloaded
/// gel's: on a real GelSight-class sensor the gel under a contact does not
/// keep its light (its slopes shade it under the lights; a thin clear gel
/// shows the object through it). Each contact scales the light about its
/// centre by `1 + change * g + sided * (dx / s) * g * e^(1/2)`, `g` a
/// Gaussian of spread `s`, two thirds of the contact's radius (of a rod's
/// half-width, along the strip only), `dx` the offset along the image's
/// x. The markers' light is scaled with the gel's. The default (both 0)
/// changes nothing: frames are bit-identical to a sensor without it.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ContactLight {
    /// Relative change of the light at a contact's centre (-0.4: 40%
    /// darker; 0.3: 30% brighter).
    pub change: f32,
    /// Relative change one spread either side of the centre along the
    /// image's x, brighter on the side of smaller x for a positive value,
    /// darker on the other (a gel lit from one side).
    pub sided: f32,
}

impl ContactLight {
    /// Largest relative change of either kind: 0.9 (the light of a spot
    /// never goes below a tenth of the gel's).
    pub const MAX_CHANGE: f32 = 0.9;

    /// Whether it changes anything.
    pub fn is_on(&self) -> bool {
        self.change != 0.0 || self.sided != 0.0
    }

    /// The relative change of the light at offset `(dx, dy)` px from a
    /// contact's centre whose spreads are `(sx, sy)` px (`sy` infinite for
    /// a rod across the image).
    pub fn at(&self, dx: f32, dy: f32, (sx, sy): (f32, f32)) -> f32 {
        let (u, v) = (dx / sx, if sy.is_finite() { dy / sy } else { 0.0 });
        let g = (-0.5 * (u * u + v * v)).exp();
        // e^(1/2): the sided change peaks at one spread from the centre.
        self.change * g - self.sided * u * g * std::f32::consts::E.sqrt()
    }

    fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("noise.contact_light.change", self.change),
            ("noise.contact_light.sided", self.sided),
        ] {
            if !(v.is_finite() && v.abs() <= Self::MAX_CHANGE) {
                return Err(Error::param(
                    name,
                    format!("must lie within -{0}..={0}, got {v}", Self::MAX_CHANGE),
                ));
            }
        }
        Ok(())
    }
}

/// How the camera's gain and black level change over time: the exposure
/// steps of an auto-exposure camera and a slow drift of gain and offset
/// (warm-up, lighting). Applied per frame index on top of the flicker: a
/// pixel is `light * gain + offset` before the noise's rounding, with shot
/// noise following the scaled light. The default (every field 0) changes
/// nothing: frames are bit-identical to a camera without it.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ExposureChanges {
    /// Frames between exposure steps (0: no steps); step `k` happens at
    /// frame `k * step_every`.
    pub step_every: u64,
    /// Relative gain change of one step (0.02: 2% brighter or darker).
    pub step_gain: f32,
    /// Black-level change of one step, grey levels.
    pub step_offset: f32,
    /// How many steps the exposure may wander from where it started: each
    /// step goes up or down at random (from the seed) and turns back at
    /// this bound (at least 1 when steps are on).
    pub step_levels: u32,
    /// Amplitude of the slow gain drift, relative: the gain moves as
    /// `1 + drift_gain * sin(2 pi t / drift_period)`, `t` the frame index.
    pub drift_gain: f32,
    /// Amplitude of the slow offset drift, grey levels (the same sine).
    pub drift_offset: f32,
    /// Period of the slow drift, frames (needed when a drift amplitude is
    /// not 0).
    pub drift_period: f64,
}

impl ExposureChanges {
    /// Whether anything changes at all.
    pub fn is_active(&self) -> bool {
        (self.step_every > 0 && (self.step_gain != 0.0 || self.step_offset != 0.0))
            || self.drift_gain != 0.0
            || self.drift_offset != 0.0
    }

    /// The exposure level (in steps, within `±step_levels`) after the steps
    /// up to frame `index`, the steps' directions drawn from `seed`.
    pub fn level(&self, seed: u64, index: u64) -> i64 {
        if self.step_every == 0 {
            return 0;
        }
        let bound = i64::from(self.step_levels.max(1));
        let mut level = 0i64;
        for k in 1..=index / self.step_every {
            let up = hash64(mix64(seed ^ 0x3C6E_F372_FE94_F82B), k) & 1 == 1;
            let step = if up { 1 } else { -1 };
            level = if (level + step).abs() > bound {
                level - step
            } else {
                level + step
            };
        }
        level
    }

    /// The camera's `(gain, offset)` at frame `index` for a sensor of seed
    /// `seed`: `(1, 0)` when nothing changes.
    pub fn response(&self, seed: u64, index: u64) -> (f32, f32) {
        if !self.is_active() {
            return (1.0, 0.0);
        }
        let level = self.level(seed, index) as f64;
        let phase = if self.drift_period > 0.0 {
            (2.0 * std::f64::consts::PI * index as f64 / self.drift_period).sin()
        } else {
            0.0
        };
        let gain =
            (1.0 + f64::from(self.step_gain) * level) * (1.0 + f64::from(self.drift_gain) * phase);
        let offset = f64::from(self.step_offset) * level + f64::from(self.drift_offset) * phase;
        (gain.max(0.0) as f32, offset as f32)
    }

    fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("noise.exposure.step_gain", self.step_gain),
            ("noise.exposure.step_offset", self.step_offset),
            ("noise.exposure.drift_gain", self.drift_gain),
            ("noise.exposure.drift_offset", self.drift_offset),
        ] {
            if !v.is_finite() {
                return Err(Error::param(name, format!("must be finite, got {v}")));
            }
        }
        let levels = f64::from(self.step_levels.max(1));
        if self.step_every > 0 && f64::from(self.step_gain).abs() * levels >= 0.5 {
            return Err(Error::param(
                "noise.exposure.step_gain",
                format!(
                    "{} per step over {} levels changes the gain by half or more",
                    self.step_gain, levels
                ),
            ));
        }
        if self.drift_gain.abs() >= 0.5 {
            return Err(Error::param(
                "noise.exposure.drift_gain",
                format!("must lie in (-0.5, 0.5), got {}", self.drift_gain),
            ));
        }
        let drifts = self.drift_gain != 0.0 || self.drift_offset != 0.0;
        if drifts && !(self.drift_period.is_finite() && self.drift_period > 0.0) {
            return Err(Error::param(
                "noise.exposure.drift_period",
                format!(
                    "a drift needs a period > 0 frames, got {}",
                    self.drift_period
                ),
            ));
        }
        Ok(())
    }
}

impl Default for NoiseConfig {
    fn default() -> Self {
        NoiseConfig {
            background: 14.0,
            outside: 4.0,
            shot: 0.15,
            read: 1.0,
            flicker: 0.01,
            vignetting: 0.35,
            exposure: ExposureChanges::default(),
            contact_light: ContactLight::default(),
        }
    }
}

/// Everything that defines a synthetic sensor (all with sensible defaults).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SimConfig {
    /// Skin geometry.
    pub skin: Skin,
    /// Camera mapping and image sizes.
    pub camera: CameraModel,
    /// Gel material.
    pub material: Material,
    /// Marker layout and look.
    pub markers: MarkerConfig,
    /// Noise and lighting.
    pub noise: NoiseConfig,
    /// Render the full camera frame (e.g. 1920x1080) with the strip inside it,
    /// instead of the strip alone; [`CameraModel::crop`] gives the strip's rectangle.
    pub full_frame: bool,
}

impl SimConfig {
    /// A small sensor with a regular grid of dark dots on a bright, lit gel,
    /// in the class of a GelSight Mini: a 320x240 image filled by a 31.9 x
    /// 23.9 mm sensing area at 10 px/mm through a distortion-free lens (the
    /// skin the rest of the simulator models, shortened), the default gel
    /// with the dots 0.3 mm under its surface, the gel lit to 180 grey levels
    /// (vignetting over the 320x240 frame) and the default camera noise. Rods
    /// press across its whole width, as on the strip.
    pub fn dot_grid(grid: DotGrid) -> SimConfig {
        let d = SimConfig::default();
        let px_per_mm = 10.0;
        let (w, h) = (320usize, 240usize);
        SimConfig {
            skin: Skin {
                geometry: optical_tactile::geometry::CurvedStrip {
                    width_mm: 23.9,
                    ..Default::default()
                }
                .into(),
                length_mm: 31.9,
            },
            camera: CameraModel {
                strip_width: w,
                strip_height: h,
                px_per_mm_s: px_per_mm,
                px_per_mm_y: px_per_mm,
                cubic: 0.0,
                radial: 0.0,
                frame_size: (w, h),
                strip_origin: (0, 0),
            },
            material: d.material,
            markers: MarkerConfig {
                depth_mm: (0.3, 0.3),
                layout: MarkerLayout::Grid(grid),
                ..d.markers
            },
            noise: NoiseConfig {
                background: 180.0,
                ..d.noise
            },
            full_frame: false,
        }
    }

    /// A flat fingertip sensor in the class of a GelSight Mini: a flat gel
    /// of [`FINGERTIP_LENGTH_MM`] x [`FINGERTIP_WIDTH_MM`] (x along the
    /// image's columns, y along its rows) filling most of a 320x240 image at
    /// 13 px/mm, seen through a short lens with a mild barrel distortion
    /// ([`CameraModel::radial`] -0.06: about 6 px at the middles of the
    /// left and right edges, 11 px at the corners), so that both the
    /// x and the y pixel-to-mm maps have to be calibrated. The gel is thin
    /// and stiff (2 mm of 1 MPa on a rigid window: 0.5-3 N presses of the
    /// flat protocol's indenters move the dots by about 1 to 15 px, less
    /// than the dots' pitch; a softer gel moves a small sphere's dots by
    /// tens of px at 3 N), with a
    /// regular grid of dark dots ([`FINGERTIP_GRID`]: 7 px dots every 22 px,
    /// 0.3 mm under the surface) on the gel lit to 180 grey levels,
    /// vignetting and the default camera noise. The whole 320x240 image is
    /// the sensor's frame (`full_frame` false).
    ///
    /// Round tips press it ([`Press::sphere`](crate::Press::sphere),
    /// [`Press::punch`](crate::Press::punch),
    /// [`Press::fingertip`](crate::Press::fingertip)); random markers instead
    /// of the grid: [`SimConfig::fingertip_with`].
    pub fn fingertip() -> SimConfig {
        SimConfig::fingertip_with(MarkerLayout::Grid(FINGERTIP_GRID))
    }

    /// [`SimConfig::fingertip`] with another marker layout: a
    /// [`MarkerLayout::Grid`] of dark dots on the lit gel, or
    /// [`MarkerLayout::Random`] bright spots (3-4 px, 0.2-1 mm deep, the
    /// default coverage) on a dark gel, as fluorescent beads would look.
    pub fn fingertip_with(layout: MarkerLayout) -> SimConfig {
        let d = SimConfig::default();
        let px_per_mm = 13.0;
        let (w, h) = (320usize, 240usize);
        let (markers, background) = match layout {
            MarkerLayout::Grid(_) => (
                MarkerConfig {
                    depth_mm: (0.3, 0.3),
                    layout,
                    ..d.markers
                },
                180.0,
            ),
            MarkerLayout::Random => (
                MarkerConfig {
                    fwhm_px: (3.0, 4.0),
                    depth_mm: (0.2, 1.0),
                    layout,
                    ..d.markers
                },
                d.noise.background,
            ),
        };
        SimConfig {
            skin: Skin {
                geometry: optical_tactile::geometry::FlatSurface {
                    length_mm: FINGERTIP_LENGTH_MM,
                    width_mm: FINGERTIP_WIDTH_MM,
                }
                .into(),
                length_mm: FINGERTIP_LENGTH_MM,
            },
            camera: CameraModel {
                strip_width: w,
                strip_height: h,
                px_per_mm_s: px_per_mm,
                px_per_mm_y: px_per_mm,
                cubic: 0.0,
                radial: -0.06,
                frame_size: (w, h),
                strip_origin: (0, 0),
            },
            material: Material {
                youngs_kpa: 1000.0,
                poisson: d.material.poisson,
                layer_mm: 2.0,
            },
            markers,
            noise: NoiseConfig {
                background,
                ..d.noise
            },
            full_frame: false,
        }
    }

    /// Checks every parameter; the error names the first bad one.
    pub fn validate(&self) -> Result<()> {
        self.skin.validate()?;
        self.camera.validate(&self.skin)?;
        self.material.validate()?;
        let m = &self.markers;
        if let MarkerLayout::Grid(g) = &m.layout {
            g.validate()?;
        }
        if let Some(0) = m.count {
            return Err(Error::param(
                "markers.count",
                "zero markers: nothing to see",
            ));
        }
        // Each marker is at least a pixel of the image: more cannot be seen,
        // and the bound keeps a count from a flag or a file from asking for
        // more memory than there is.
        let (w, h) = self.image_size();
        if let Some(n) = m.count.filter(|&n| n > w * h) {
            return Err(Error::param(
                "markers.count",
                format!(
                    "{n} markers in a {w}x{h} image: at most one per pixel, {}",
                    w * h
                ),
            ));
        }
        if m.count.is_none() && !(m.coverage.is_finite() && m.coverage > 0.0 && m.coverage < 0.95) {
            return Err(Error::param(
                "markers.coverage",
                format!(
                    "must lie in (0, 0.95), got {} (zero markers: nothing to see)",
                    m.coverage
                ),
            ));
        }
        let range = |name: &str, (lo, hi): (f64, f64), min: f64| -> Result<()> {
            if !(lo.is_finite() && hi.is_finite() && lo >= min && hi >= lo) {
                return Err(Error::param(
                    name,
                    format!("need {min} <= lo <= hi, got ({lo}, {hi})"),
                ));
            }
            Ok(())
        };
        range("markers.fwhm_px", m.fwhm_px, 0.5)?;
        if m.fwhm_px.1 > 20.0 {
            return Err(Error::param(
                "markers.fwhm_px",
                format!(
                    "spots wider than 20 px are not markers, got {}",
                    m.fwhm_px.1
                ),
            ));
        }
        range("markers.depth_mm", m.depth_mm, 1e-3)?;
        range("markers.brightness", m.brightness, 0.0)?;
        if m.depth_mm.1 >= self.material.layer_mm {
            return Err(Error::param(
                "markers.depth_mm",
                format!(
                    "markers down to {} mm do not fit in a {} mm layer",
                    m.depth_mm.1, self.material.layer_mm
                ),
            ));
        }
        let n = &self.noise;
        for (name, v) in [
            ("noise.background", n.background),
            ("noise.outside", n.outside),
            ("noise.shot", n.shot),
            ("noise.read", n.read),
            ("noise.flicker", n.flicker),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Error::param(
                    name,
                    format!("must be finite and >= 0, got {v}"),
                ));
            }
        }
        if !(n.vignetting.is_finite() && (0.0..1.0).contains(&n.vignetting)) {
            return Err(Error::param("noise.vignetting", "must lie in [0, 1)"));
        }
        n.exposure.validate()?;
        n.contact_light.validate()?;
        Ok(())
    }

    /// Image size `(width, height)` of the rendered frames.
    pub fn image_size(&self) -> (usize, usize) {
        if self.full_frame {
            self.camera.frame_size
        } else {
            (self.camera.strip_width, self.camera.strip_height)
        }
    }
}

/// Length (along x, image columns) of [`SimConfig::fingertip`]'s gel, mm.
pub const FINGERTIP_LENGTH_MM: f64 = 24.0;
/// Width (along y, image rows) of [`SimConfig::fingertip`]'s gel, mm.
pub const FINGERTIP_WIDTH_MM: f64 = 18.0;
/// The dot grid of [`SimConfig::fingertip`]: 7 px dots every 22 px (1.7 mm
/// at 13 px/mm), a 1.5 px soft edge, 140 grey levels dark, no jitter.
pub const FINGERTIP_GRID: DotGrid = DotGrid {
    pitch_px: 22.0,
    diameter_px: 7.0,
    edge_px: 1.5,
    jitter_px: 0.0,
    darkness: 140.0,
};

/// Markers as structure of arrays (hot loops read one field at a time).
#[derive(Debug, Clone, Default)]
pub(crate) struct Markers {
    pub s: Vec<f64>,
    pub y: Vec<f64>,
    pub z: Vec<f64>,
    /// Rest position in strip pixels.
    pub px: Vec<f64>,
    pub py: Vec<f64>,
    pub amp: Vec<f32>,
    pub sigma: Vec<f32>,
    /// Dots (grid layout): each marker's radius, px, its soft edge's half
    /// width in `sigma` and a negative `amp`. Empty for Gaussian spots.
    pub radius: Vec<f32>,
}

impl Markers {
    /// How far from its centre marker `i` is drawn, px.
    #[inline]
    pub fn extent(&self, i: usize) -> f32 {
        if self.radius.is_empty() {
            crate::render::SPOT_RADIUS_SIGMAS * self.sigma[i]
        } else {
            self.radius[i] + self.sigma[i] + 1.0
        }
    }
}

/// A frame and its true dense motion.
#[derive(Debug, Clone)]
pub struct Rendered {
    /// The grey image (0..=255, integer-valued like an 8-bit camera frame).
    pub frame: Array2<f32>,
    /// True motion from the unloaded state, px (see [`SyntheticSensor::render`](crate::SyntheticSensor::render));
    /// `None` when not requested.
    pub flow: Option<FlowField>,
}

/// A simulated sensor as the `simulate` command's options describe it: one
/// of the three sensors ([`SimConfig::default`], the curved strip;
/// [`SimConfig::fingertip`]; [`SimConfig::dot_grid`]) with the options
/// given over it, every `None` the sensor's own. [`SensorOptions::config`]
/// builds it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SensorOptions {
    /// The flat fingertip sensor ([`SimConfig::fingertip_with`]) instead of
    /// the strip.
    pub fingertip: bool,
    /// With `fingertip`: random bright markers on a dark gel instead of its
    /// dot grid.
    pub random_markers: bool,
    /// A GelSight-like dot grid on a piece of the strip
    /// ([`SimConfig::dot_grid`]); the fingertip has its own.
    pub dot_grid: bool,
    /// Render the whole camera frame with the strip inside it.
    pub full_frame: bool,
    /// Gel Young's modulus, kPa.
    pub youngs_kpa: Option<f64>,
    /// Gel Poisson's ratio.
    pub poisson: Option<f64>,
    /// Gel layer thickness, mm.
    pub layer_mm: Option<f64>,
    /// Fraction of the image covered by markers.
    pub coverage: Option<f64>,
    /// Exact number of markers (overrides the coverage).
    pub markers: Option<usize>,
    /// Depths of the markers below the skin, mm (min, max).
    pub marker_depth_mm: Option<(f64, f64)>,
    /// Dot grid: distance between dot centres, px.
    pub pitch_px: Option<f64>,
    /// Dot grid: dot diameter, px.
    pub dot_px: Option<f64>,
    /// Dot grid: each dot moved off the grid by up to this, px.
    pub jitter_px: Option<f64>,
    /// Read-noise standard deviation, grey levels.
    pub noise_read: Option<f32>,
    /// Relative per-frame brightness flicker.
    pub flicker: Option<f32>,
    /// Camera exposure steps: every `[0]` frames the gain changes by `[1]`
    /// (relative) and the black level by `[2]` grey levels (default 0), at
    /// most `[3]` steps from the start (default 2); empty: none.
    pub exposure_steps: Vec<f64>,
    /// Slow camera drift: gain `[0]` (relative), black level `[1]` (grey
    /// levels), period `[2]` frames; empty: none.
    pub drift: Vec<f64>,
    /// The gel's light under each contact: change at its centre, and the
    /// sided change of its slopes ([`ContactLight`]).
    pub contact_light: ContactLight,
}

impl SensorOptions {
    /// The sensor these options describe (the fingertip's own dot grid
    /// with `fingertip`, whatever `dot_grid` says; numbers of
    /// `exposure_steps` and `drift` beyond those named are not read).
    /// Not checked: [`SimConfig::validate`] (which every scenario runs)
    /// refuses what does not make a sensor.
    pub fn config(&self) -> SimConfig {
        let grid = |base: DotGrid| DotGrid {
            pitch_px: self.pitch_px.unwrap_or(base.pitch_px),
            diameter_px: self.dot_px.unwrap_or(base.diameter_px),
            jitter_px: self.jitter_px.unwrap_or(base.jitter_px),
            ..base
        };
        let mut cfg = if self.fingertip {
            SimConfig::fingertip_with(if self.random_markers {
                MarkerLayout::Random
            } else {
                MarkerLayout::Grid(grid(FINGERTIP_GRID))
            })
        } else if self.dot_grid {
            SimConfig::dot_grid(grid(DotGrid::default()))
        } else {
            SimConfig::default()
        };
        cfg.full_frame = self.full_frame;
        let m = &mut cfg.material;
        m.youngs_kpa = self.youngs_kpa.unwrap_or(m.youngs_kpa);
        m.poisson = self.poisson.unwrap_or(m.poisson);
        m.layer_mm = self.layer_mm.unwrap_or(m.layer_mm);
        let k = &mut cfg.markers;
        k.coverage = self.coverage.unwrap_or(k.coverage);
        k.count = self.markers.or(k.count);
        k.depth_mm = self.marker_depth_mm.unwrap_or(k.depth_mm);
        let n = &mut cfg.noise;
        n.read = self.noise_read.unwrap_or(n.read);
        n.flicker = self.flicker.unwrap_or(n.flicker);
        let at = |v: &[f64], k: usize, d: f64| v.get(k).copied().unwrap_or(d);
        let (s, d) = (&self.exposure_steps, &self.drift);
        if !s.is_empty() {
            n.exposure.step_every = at(s, 0, 0.0).max(0.0) as u64;
            n.exposure.step_gain = at(s, 1, 0.0) as f32;
            n.exposure.step_offset = at(s, 2, 0.0) as f32;
            n.exposure.step_levels = at(s, 3, 2.0).max(0.0) as u32;
        }
        if !d.is_empty() {
            n.exposure.drift_gain = at(d, 0, 0.0) as f32;
            n.exposure.drift_offset = at(d, 1, 0.0) as f32;
            n.exposure.drift_period = at(d, 2, 0.0);
        }
        n.contact_light = self.contact_light;
        cfg
    }
}
