//! The skin's geometry (curved strip, unrolled) and the camera model that maps
//! the unrolled skin to image pixels.
//!
//! Positions on the skin are given in *unrolled* coordinates: arc length `s` (mm)
//! along the centre line measured from the symmetry axis, and `y` (mm) across the
//! width. The camera maps `s` to image x through a mild cubic term (so that the
//! pixel-to-mm map really has to be calibrated, as with the real fisheye camera)
//! and `y` linearly to image y, then, when [`CameraModel::radial`] is not
//! zero, bends both through a radial lens distortion about the image centre
//! (a flat fingertip sensor's short lens), so that both pixel-to-mm maps
//! have to be calibrated.

use optical_tactile::error::{Error, Result};
use optical_tactile::geometry::SensorGeometry;

/// The curved sensing skin: the sensor geometry (the reference design by default)
/// and the length of the sensing area along the arc.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Skin {
    /// Arc radius, frame offset, opening angle and width.
    pub geometry: SensorGeometry,
    /// Length of the sensing skin along the arc, mm (320; at most the arc).
    pub length_mm: f64,
}

impl Default for Skin {
    fn default() -> Self {
        Skin {
            geometry: SensorGeometry::default(),
            length_mm: 320.0,
        }
    }
}

impl Skin {
    /// Checks that the numbers describe a real skin.
    pub fn validate(&self) -> Result<()> {
        self.geometry.validate()?;
        let arc = 2.0 * self.geometry.half_arc_mm();
        if !(self.length_mm.is_finite() && self.length_mm > 0.0 && self.length_mm <= arc + 1e-9) {
            return Err(Error::param(
                "length_mm",
                format!(
                    "must lie in (0, {arc:.1}] (the arc's length), got {}",
                    self.length_mm
                ),
            ));
        }
        Ok(())
    }

    /// Radius of curvature along the length, mm: the strip's arc radius,
    /// infinite for a flat surface.
    pub fn radius_mm(&self) -> f64 {
        self.geometry
            .as_curved_strip()
            .map_or(f64::INFINITY, |g| g.radius_mm)
    }

    /// Width across, mm.
    pub fn width_mm(&self) -> f64 {
        self.geometry.width_mm()
    }

    /// Whether the skin is flat (a fingertip's gel), not the curved strip.
    pub fn is_flat(&self) -> bool {
        matches!(self.geometry, SensorGeometry::Flat(_))
    }

    /// Half the arc length of the sensing area, mm.
    pub fn half_length(&self) -> f64 {
        0.5 * self.length_mm
    }

    /// Arc length of chord position `x_mm`: `s = R asin(x / R)`.
    /// Errors if `x_mm` is not on the sensing area.
    pub fn chord_to_arc(&self, x_mm: f64) -> Result<f64> {
        let max_x = self.arc_to_chord(self.half_length());
        if !x_mm.is_finite() || x_mm.abs() > max_x + 1e-9 {
            return Err(Error::param(
                "x_mm",
                format!("contact at chord {x_mm} mm is off the skin (|x| <= {max_x:.2} mm)"),
            ));
        }
        Ok(self.geometry.chord_to_arc(x_mm))
    }

    /// Chord position of arc length `s_mm`: `x = R sin(s / R)`.
    pub fn arc_to_chord(&self, s_mm: f64) -> f64 {
        self.geometry.arc_to_chord(s_mm)
    }

    /// Height of the skin surface at chord position `x`: `sqrt(R^2 - x^2) - d`.
    pub fn z_at(&self, x_mm: f64) -> f64 {
        self.geometry.z_at(x_mm)
    }

    /// Projects a sensor-frame force onto the local frame at `x_mm`:
    /// `(tangential along +s, across along +y, outward normal)`.
    pub fn force_to_local(&self, x_mm: f64, f: [f64; 3]) -> [f64; 3] {
        self.geometry.sensor_to_local(x_mm, f)
    }
}

/// Camera model: unrolled skin (mm) to pixels of the sensing-strip image, and the
/// strip's place in the full camera frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraModel {
    /// Width of the sensing-strip image, px (1600).
    pub strip_width: usize,
    /// Height of the sensing-strip image, px (200).
    pub strip_height: usize,
    /// Pixels per mm along the arc at the centre (5.0).
    pub px_per_mm_s: f64,
    /// Pixels per mm across the width (4.75).
    pub px_per_mm_y: f64,
    /// Cubic term `k` of `x_px = cx + p (s + k s^3 / h^2)`, `h` = half skin length;
    /// negative compresses the ends (barrel-like). Must lie in (-0.3, 0.3).
    pub cubic: f64,
    /// Radial distortion `k` about the image centre, applied after the maps
    /// along `s` and `y`: a point at distance `r` from the centre moves to
    /// `r (1 + k r^2 / r0^2)`, `r0` the half diagonal of the strip image.
    /// Negative is barrel distortion (the edges pulled in, lines bent
    /// towards the centre). 0 (the strip's) leaves the maps separable and
    /// exactly as without it; otherwise it must lie in (-0.3, 0.3) and keep
    /// the map monotonic over the skin ([`CameraModel::validate`]).
    pub radial: f64,
    /// Full camera frame size, px (1920x1080), used for vignetting and for the
    /// full-frame output option.
    pub frame_size: (usize, usize),
    /// Top-left corner of the strip inside the full frame, px.
    pub strip_origin: (usize, usize),
}

impl Default for CameraModel {
    fn default() -> Self {
        CameraModel {
            strip_width: 1600,
            strip_height: 200,
            px_per_mm_s: 5.0,
            px_per_mm_y: 4.75,
            cubic: -0.04,
            radial: 0.0,
            frame_size: (1920, 1080),
            strip_origin: (160, 440),
        }
    }
}

impl CameraModel {
    /// Checks the camera against the skin: sizes, scales, monotonic mapping, and
    /// that the strip fits in the full frame.
    pub fn validate(&self, skin: &Skin) -> Result<()> {
        if self.strip_width < 16 || self.strip_height < 16 {
            return Err(Error::TooSmall {
                what: "sensing-strip image".into(),
                width: self.strip_width,
                height: self.strip_height,
                min_w: 16,
                min_h: 16,
            });
        }
        for (name, v) in [
            ("px_per_mm_s", self.px_per_mm_s),
            ("px_per_mm_y", self.px_per_mm_y),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::param(
                    name,
                    format!("must be finite and > 0, got {v}"),
                ));
            }
        }
        if !(self.cubic.is_finite() && self.cubic.abs() < 0.3) {
            return Err(Error::param(
                "cubic",
                format!(
                    "must lie in (-0.3, 0.3) to keep the map monotonic, got {}",
                    self.cubic
                ),
            ));
        }
        if !(self.radial.is_finite() && self.radial.abs() < 0.3) {
            return Err(Error::param(
                "radial",
                format!("must lie in (-0.3, 0.3), got {}", self.radial),
            ));
        }
        let (fw, fh) = self.frame_size;
        let (ox, oy) = self.strip_origin;
        if ox + self.strip_width > fw || oy + self.strip_height > fh {
            return Err(Error::CropOutside {
                x: ox,
                y: oy,
                w: self.strip_width,
                h: self.strip_height,
                frame_w: fw,
                frame_h: fh,
            });
        }
        let h = skin.half_length();
        let half_w = 0.5 * skin.width_mm();
        if self.radial != 0.0 {
            // The radial map is monotonic along every ray out to the
            // farthest corner of the undistorted skin: d(r (1 + k r^2)) / dr
            // = 1 + 3 k r^2 stays clearly positive.
            let mut r_max: f64 = 0.0;
            for (s, y) in [(-h, -half_w), (-h, half_w), (h, -half_w), (h, half_w)] {
                let (dx, dy) = self.undistorted_offset(skin, s, y);
                r_max = r_max.max(dx.hypot(dy) / self.radial_scale());
            }
            if 1.0 + 3.0 * self.radial * r_max * r_max < 0.25 {
                return Err(Error::param(
                    "radial",
                    format!(
                        "{} folds the image over itself near the skin's corners \
                         (relative radius {r_max:.2})",
                        self.radial
                    ),
                ));
            }
        }
        // The skin's outline reaches farthest out at its corners or at the
        // middles of its sides (along a side the radial factor changes
        // monotonically).
        let (mut x_start, mut x_end) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut y_top, mut y_bot) = (f64::INFINITY, f64::NEG_INFINITY);
        for (s, y) in [
            (-h, -half_w),
            (-h, 0.0),
            (-h, half_w),
            (0.0, -half_w),
            (0.0, half_w),
            (h, -half_w),
            (h, 0.0),
            (h, half_w),
        ] {
            let (x, yy) = self.skin_to_px(skin, s, y);
            x_start = x_start.min(x);
            x_end = x_end.max(x);
            y_top = y_top.min(yy);
            y_bot = y_bot.max(yy);
        }
        if x_start < 0.0
            || x_end > self.strip_width as f64
            || y_top < 0.0
            || y_bot > self.strip_height as f64
        {
            return Err(Error::param(
                "camera",
                format!(
                    "the skin maps to x {x_start:.1}..{x_end:.1}, y {y_top:.1}..{y_bot:.1} px, \
                     outside the {}x{} strip image",
                    self.strip_width, self.strip_height
                ),
            ));
        }
        Ok(())
    }

    /// Image x (strip pixels, pixel centres at integers) of arc length `s`,
    /// before the radial distortion (the whole map when
    /// [`CameraModel::radial`] is 0; [`CameraModel::skin_to_px`] applies both).
    #[inline]
    pub fn s_to_px(&self, skin: &Skin, s: f64) -> f64 {
        let h = skin.half_length();
        let c = 0.5 * (self.strip_width as f64 - 1.0);
        c + self.px_per_mm_s * (s + self.cubic * s * s * s / (h * h))
    }

    /// Image y (strip pixels) of the across coordinate `y`, before the
    /// radial distortion.
    #[inline]
    pub fn y_to_px(&self, y: f64) -> f64 {
        0.5 * (self.strip_height as f64 - 1.0) + self.px_per_mm_y * y
    }

    /// Arc length of undistorted image x (inverse of [`CameraModel::s_to_px`], by Newton steps;
    /// the map is monotonic because `|cubic| < 0.3`).
    pub fn px_to_s(&self, skin: &Skin, x_px: f64) -> f64 {
        let h = skin.half_length();
        let c = 0.5 * (self.strip_width as f64 - 1.0);
        let target = (x_px - c) / self.px_per_mm_s;
        let mut s = target;
        for _ in 0..30 {
            let f = s + self.cubic * s * s * s / (h * h) - target;
            let df = 1.0 + 3.0 * self.cubic * s * s / (h * h);
            let step = f / df;
            s -= step;
            if step.abs() < 1e-12 {
                break;
            }
        }
        s
    }

    /// Across coordinate of undistorted image y (inverse of
    /// [`CameraModel::y_to_px`]).
    #[inline]
    pub fn px_to_y(&self, y_px: f64) -> f64 {
        (y_px - 0.5 * (self.strip_height as f64 - 1.0)) / self.px_per_mm_y
    }

    /// Image position `(x, y)` (strip pixels) of the skin point at arc
    /// length `s` and across coordinate `y`: [`CameraModel::s_to_px`] and
    /// [`CameraModel::y_to_px`], then the radial distortion. Exactly those
    /// two maps when [`CameraModel::radial`] is 0.
    #[inline]
    pub fn skin_to_px(&self, skin: &Skin, s: f64, y: f64) -> (f64, f64) {
        let (x_u, y_u) = (self.s_to_px(skin, s), self.y_to_px(y));
        if self.radial == 0.0 {
            return (x_u, y_u);
        }
        let (cx, cy) = self.centre();
        let (dx, dy) = (x_u - cx, y_u - cy);
        let f = self.radial_factor((dx * dx + dy * dy) / self.radial_scale().powi(2));
        (cx + dx * f, cy + dy * f)
    }

    /// Skin coordinates `(s, y)` of image position `(x, y)` (strip pixels):
    /// the inverse of [`CameraModel::skin_to_px`] (the radial distortion is
    /// undone by Newton steps on the radius, then [`CameraModel::px_to_s`]
    /// and [`CameraModel::px_to_y`]).
    pub fn px_to_skin(&self, skin: &Skin, x_px: f64, y_px: f64) -> (f64, f64) {
        let (x_u, y_u) = self.undistort(x_px, y_px);
        (self.px_to_s(skin, x_u), self.px_to_y(y_u))
    }

    /// The undistorted image position of distorted image position
    /// `(x, y)`: the inverse of the radial distortion alone.
    pub fn undistort(&self, x_px: f64, y_px: f64) -> (f64, f64) {
        if self.radial == 0.0 {
            return (x_px, y_px);
        }
        let (cx, cy) = self.centre();
        let r0 = self.radial_scale();
        let (dx, dy) = ((x_px - cx) / r0, (y_px - cy) / r0);
        let rd = dx.hypot(dy);
        if rd == 0.0 {
            return (x_px, y_px);
        }
        // Solve r (1 + k r^2) = rd for r.
        let k = self.radial;
        let mut r = rd;
        for _ in 0..50 {
            let f = r * (1.0 + k * r * r) - rd;
            let df = 1.0 + 3.0 * k * r * r;
            let step = f / df.max(1e-6);
            r -= step;
            if step.abs() < 1e-14 {
                break;
            }
        }
        let scale = r / rd;
        (cx + dx * scale * r0, cy + dy * scale * r0)
    }

    /// The image centre the radial distortion is about, strip pixels.
    #[inline]
    fn centre(&self) -> (f64, f64) {
        (
            0.5 * (self.strip_width as f64 - 1.0),
            0.5 * (self.strip_height as f64 - 1.0),
        )
    }

    /// `r0`: the half diagonal of the strip image, px.
    #[inline]
    fn radial_scale(&self) -> f64 {
        0.5 * (self.strip_width as f64).hypot(self.strip_height as f64)
    }

    /// `1 + k r^2` for the squared relative radius `r2`.
    #[inline]
    fn radial_factor(&self, r2: f64) -> f64 {
        1.0 + self.radial * r2
    }

    /// Undistorted image offset from the centre of the skin point `(s, y)`.
    fn undistorted_offset(&self, skin: &Skin, s: f64, y: f64) -> (f64, f64) {
        let (cx, cy) = self.centre();
        (self.s_to_px(skin, s) - cx, self.y_to_px(y) - cy)
    }

    /// The strip's rectangle in the full frame: `(x, y, width, height)`, the
    /// crop that turns a full frame into the strip image.
    pub fn crop(&self) -> (usize, usize, usize, usize) {
        (
            self.strip_origin.0,
            self.strip_origin.1,
            self.strip_width,
            self.strip_height,
        )
    }

    /// Vignetting gain at full-frame pixel `(x, y)`: `1 - v r^2`, `r` the distance
    /// from the frame centre relative to the half diagonal.
    #[inline]
    pub fn vignetting(&self, strength: f32, x_full: f32, y_full: f32) -> f32 {
        let (fw, fh) = (self.frame_size.0 as f32, self.frame_size.1 as f32);
        let dx = x_full - 0.5 * (fw - 1.0);
        let dy = y_full - 0.5 * (fh - 1.0);
        let r2 = (dx * dx + dy * dy) / (0.25 * (fw * fw + fh * fh));
        1.0 - strength * r2
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_2_is_at_minus_114_1() {
        let skin = Skin::default();
        let x = skin.arc_to_chord((2.0 - 8.0) * 20.0);
        assert!((x + 114.1).abs() < 0.05, "{x}");
        let s = skin.chord_to_arc(x).unwrap();
        assert!((s + 120.0).abs() < 1e-9);
        assert!(skin.chord_to_arc(150.0).is_err());
        assert!(skin.chord_to_arc(f64::NAN).is_err());
    }

    #[test]
    fn force_projection_at_point_2() {
        let skin = Skin::default();
        let x = skin.arc_to_chord(-120.0);
        // A vertical press (0, 0, -F) on the sloped skin has a tangential part.
        let l = skin.force_to_local(x, [0.0, 0.0, -1.0]);
        let th = (x / 220.0).asin();
        assert!((l[0] - th.sin()).abs() < 1e-12 && (l[2] + th.cos()).abs() < 1e-12);
        assert!(l[1].abs() < 1e-15);
        assert!(
            Skin {
                length_mm: 400.0,
                ..skin
            }
            .validate()
            .is_err()
        );
    }

    #[test]
    fn camera_maps_the_skin_inside_the_strip_and_inverts() {
        let skin = Skin::default();
        let cam = CameraModel::default();
        cam.validate(&skin).unwrap();
        for s in [-160.0, -77.7, 0.0, 12.5, 160.0] {
            let x = cam.s_to_px(&skin, s);
            assert!((cam.px_to_s(&skin, x) - s).abs() < 1e-9);
        }
        // Non-linear: the local scale at the ends differs from the centre.
        let d0 = cam.s_to_px(&skin, 1.0) - cam.s_to_px(&skin, 0.0);
        let d1 = cam.s_to_px(&skin, 160.0) - cam.s_to_px(&skin, 159.0);
        assert!(d1 < 0.9 * d0);
        let bad = CameraModel { cubic: 0.5, ..cam };
        assert!(bad.validate(&skin).is_err());
        let bad = CameraModel {
            strip_origin: (400, 0),
            ..cam
        };
        assert!(matches!(
            bad.validate(&skin),
            Err(Error::CropOutside { .. })
        ));
    }
}
