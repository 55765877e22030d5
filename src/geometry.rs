//! Sensor geometry: the curved skin, local surface frames, rotations.
//!
//! The reference sensor's skin is an arc of a circle of radius `R` (220 mm),
//! opening angle 86 deg, 40 mm wide. The **sensor frame** has `x` along the
//! chord, `y` across the width and `z` along the arc's symmetry axis pointing
//! out of the skin; its origin lies on that axis at distance `d` (60 mm) from
//! the circle's centre. A point of the skin at chord position `x` therefore
//! sits at `z = sqrt(R^2 - x^2) - d`, at the polar angle `theta = asin(x / R)`
//! from the axis, and at the (signed) arc length `s = R * theta` from the
//! centre line.
//!
//! The **local surface frame** at a skin point has the unit vectors
//! `t` (tangent along the arc, towards +x), `w` (across, = +y) and `n` (outward
//! normal). In sensor coordinates:
//!
//! ```text
//! t = ( cos θ, 0, -sin θ)
//! w = ( 0,     1,  0    )
//! n = ( sin θ, 0,  cos θ)
//! ```
//!
//! ```
//! use optical_tactile::geometry::SensorGeometry;
//! let g = SensorGeometry::default();
//! // Point 2 of the characterization protocol lies 120 mm of arc left of centre.
//! let x = g.arc_to_chord(-120.0);
//! assert!((x + 114.1).abs() < 0.1);
//! assert!((g.z_at(0.0) - 160.0).abs() < 1e-12);
//! ```

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// The geometry of a curved sensing skin (all lengths in mm).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SensorGeometry {
    /// Radius `R` of the skin's arc.
    pub radius_mm: f64,
    /// Distance `d` from the circle's centre to the sensor frame's origin.
    pub d_mm: f64,
    /// Opening angle of the arc, in degrees.
    pub opening_deg: f64,
    /// Width of the skin across the arc (along `y`).
    pub width_mm: f64,
}

impl Default for SensorGeometry {
    /// The reference sensor of the paper: R = 220 mm, d = 60 mm, 86 deg, 40 mm wide.
    fn default() -> Self {
        SensorGeometry {
            radius_mm: 220.0,
            d_mm: 60.0,
            opening_deg: 86.0,
            width_mm: 40.0,
        }
    }
}

impl SensorGeometry {
    /// Checks that every dimension is finite and makes sense.
    pub fn validate(&self) -> Result<()> {
        let pos = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(Error::param(
                    name,
                    format!("must be finite and > 0, got {v}"),
                ))
            }
        };
        pos("radius_mm", self.radius_mm)?;
        pos("width_mm", self.width_mm)?;
        pos("opening_deg", self.opening_deg)?;
        if self.opening_deg >= 180.0 {
            return Err(Error::param(
                "opening_deg",
                format!("must be below 180, got {}", self.opening_deg),
            ));
        }
        if !self.d_mm.is_finite() {
            return Err(Error::param("d_mm", "must be finite"));
        }
        Ok(())
    }

    /// Half the opening angle, in radians.
    pub fn half_angle(&self) -> f64 {
        self.opening_deg.to_radians() / 2.0
    }

    /// Half the chord: the largest `|x|` on the skin.
    pub fn half_chord_mm(&self) -> f64 {
        self.radius_mm * self.half_angle().sin()
    }

    /// Half the arc length: the largest `|s|` on the skin.
    pub fn half_arc_mm(&self) -> f64 {
        self.radius_mm * self.half_angle()
    }

    /// Polar angle `theta = asin(x / R)` (radians) of the skin point at chord position `x`.
    pub fn angle_at(&self, x_mm: f64) -> f64 {
        (x_mm / self.radius_mm).clamp(-1.0, 1.0).asin()
    }

    /// Signed arc length from the centre line to chord position `x`.
    pub fn chord_to_arc(&self, x_mm: f64) -> f64 {
        self.radius_mm * self.angle_at(x_mm)
    }

    /// Chord position of the skin point at signed arc length `s`.
    pub fn arc_to_chord(&self, s_mm: f64) -> f64 {
        self.radius_mm * (s_mm / self.radius_mm).sin()
    }

    /// Height `z = sqrt(R^2 - x^2) - d` of the skin at chord position `x`.
    pub fn z_at(&self, x_mm: f64) -> f64 {
        (self.radius_mm * self.radius_mm - x_mm * x_mm)
            .max(0.0)
            .sqrt()
            - self.d_mm
    }

    /// Whether the point (`x` along the chord, `y` across) lies on the skin.
    pub fn contains(&self, x_mm: f64, y_mm: f64) -> bool {
        x_mm.is_finite()
            && y_mm.is_finite()
            && x_mm.abs() <= self.half_chord_mm()
            && y_mm.abs() <= self.width_mm / 2.0
    }

    /// The local surface frame at chord position `x`, as a rotation matrix whose
    /// columns are `t`, `w`, `n` in sensor coordinates. It maps local
    /// components `(tangent, across, normal)` to sensor components `(x, y, z)`.
    pub fn local_frame(&self, x_mm: f64) -> Matrix3<f64> {
        let th = self.angle_at(x_mm);
        let (s, c) = th.sin_cos();
        Matrix3::new(
            c, 0.0, s, //
            0.0, 1.0, 0.0, //
            -s, 0.0, c,
        )
    }

    /// Rotates a vector given in the local frame at `x` (tangent, across,
    /// normal) into the sensor frame.
    pub fn local_to_sensor(&self, x_mm: f64, local: [f64; 3]) -> [f64; 3] {
        let v = self.local_frame(x_mm) * Vector3::from(local);
        [v.x, v.y, v.z]
    }

    /// Rotates a vector given in the sensor frame into the local frame at `x`
    /// (tangent, across, normal).
    pub fn sensor_to_local(&self, x_mm: f64, sensor: [f64; 3]) -> [f64; 3] {
        let v = self.local_frame(x_mm).transpose() * Vector3::from(sensor);
        [v.x, v.y, v.z]
    }

    /// The skin point at chord position `x` and width position `y`, in the sensor frame.
    pub fn point_at(&self, x_mm: f64, y_mm: f64) -> [f64; 3] {
        [x_mm, y_mm, self.z_at(x_mm)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn arc_and_chord_are_inverse() {
        let g = SensorGeometry::default();
        for s in [-150.0, -120.0, -3.0, 0.0, 17.5, 140.0] {
            assert_relative_eq!(g.chord_to_arc(g.arc_to_chord(s)), s, epsilon = 1e-9);
        }
        // Point 2 of the protocol (docs/formats.md: point 2 is near -114 mm).
        assert_relative_eq!(g.arc_to_chord(-120.0), -114.1, epsilon = 0.05);
    }

    #[test]
    fn skin_point_lies_on_the_circle() {
        let g = SensorGeometry::default();
        for x in [-140.0, -50.0, 0.0, 90.0] {
            let z = g.z_at(x) + g.d_mm;
            assert_relative_eq!((x * x + z * z).sqrt(), g.radius_mm, epsilon = 1e-9);
        }
    }

    #[test]
    fn normal_is_radial_and_frame_is_orthonormal() {
        let g = SensorGeometry::default();
        for x in [-120.0, -10.0, 0.0, 77.0] {
            let m = g.local_frame(x);
            assert_relative_eq!(m.transpose() * m, Matrix3::identity(), epsilon = 1e-12);
            assert_relative_eq!(m.determinant(), 1.0, epsilon = 1e-12);
            // The outward normal points from the circle's centre through the point.
            let p = Vector3::new(x, 0.0, g.z_at(x) + g.d_mm) / g.radius_mm;
            assert_relative_eq!(m.column(2).into_owned(), p, epsilon = 1e-12);
            // The tangent is the derivative of the point along increasing x.
            let h = 1e-5;
            let dp = Vector3::new(2.0 * h, 0.0, g.z_at(x + h) - g.z_at(x - h)).normalize();
            assert_relative_eq!(m.column(0).into_owned(), dp, epsilon = 1e-6);
        }
    }

    #[test]
    fn rotations_round_trip() {
        let g = SensorGeometry::default();
        let v = [0.3, -0.2, -1.7];
        let back = g.local_to_sensor(-60.0, g.sensor_to_local(-60.0, v));
        for k in 0..3 {
            assert_relative_eq!(back[k], v[k], epsilon = 1e-12);
        }
        // At the centre the local frame is the sensor frame.
        assert_eq!(g.local_to_sensor(0.0, v), v);
    }

    #[test]
    fn bounds_and_validation() {
        let g = SensorGeometry::default();
        assert!(g.contains(150.0, 20.0));
        assert!(!g.contains(151.0, 0.0));
        assert!(!g.contains(0.0, 20.1));
        assert!(!g.contains(f64::NAN, 0.0));
        assert!(g.validate().is_ok());
        let bad = SensorGeometry {
            radius_mm: -1.0,
            ..g
        };
        assert!(bad.validate().is_err());
        let bad = SensorGeometry {
            opening_deg: 200.0,
            ..g
        };
        assert!(bad.validate().is_err());
    }
}
