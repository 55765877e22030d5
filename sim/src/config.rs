//! What defines a synthetic sensor ([`SimConfig`]: markers, camera noise,
//! camera model, material) and what rendering produces ([`Rendered`]).

use ndarray::Array2;
use optical_tactile::error::{Error, Result};
use optical_tactile::flow::FlowField;

use super::camera::{CameraModel, Skin};
use super::elastic::Material;

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
}

impl Default for MarkerConfig {
    fn default() -> Self {
        MarkerConfig {
            coverage: 0.3,
            count: None,
            fwhm_px: (2.5, 3.0),
            depth_mm: (0.5, 4.0),
            brightness: (70.0, 200.0),
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
    /// Checks every parameter; the error names the first bad one.
    pub fn validate(&self) -> Result<()> {
        self.skin.validate()?;
        self.camera.validate(&self.skin)?;
        self.material.validate()?;
        let m = &self.markers;
        if let Some(0) = m.count {
            return Err(Error::param(
                "markers.count",
                "zero markers: nothing to see",
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
