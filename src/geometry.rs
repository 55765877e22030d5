//! Sensor geometry: the sensing surface, its local frames, rotations.
//!
//! Two surfaces are described ([`SensorGeometry`]): the paper's **curved
//! strip** ([`CurvedStrip`]) and a **flat** rectangle ([`FlatSurface`], the
//! build of fingertip sensors of the GelSight, DIGIT and GelSlim class).
//! Every method that depends on the position on the surface takes the
//! position's sensor-frame `x` (both surfaces, and a cylinder's, bend along
//! one axis at most).
//!
//! **Curved strip.** The skin is an arc of a circle of radius `R` (220 mm),
//! opening angle 86 deg, 40 mm wide. The **sensor frame** has `x` along the
//! chord, `y` across the width and `z` along the arc's symmetry axis pointing
//! out of the skin; its origin lies on that axis at distance `d` (60 mm) from
//! the circle's centre. A point of the skin at chord position `x` therefore
//! sits at `z = sqrt(R^2 - x^2) - d`, at the polar angle `theta = asin(x / R)`
//! from the axis, and at the (signed) arc length `s = R * theta` from the
//! centre line.
//!
//! **Flat surface.** A rectangle `length_mm` along `x` by `width_mm` along
//! `y`; the sensor frame's origin is the rectangle's centre on the gel's
//! outer surface and `z` points out of the gel, so every surface point has
//! `z = 0`, the arc length is `x` and the local frame is the sensor frame.
//!
//! The **local surface frame** at a skin point has the unit vectors
//! `t` (tangent along the arc, towards +x), `w` (across, = +y) and `n` (outward
//! normal). In sensor coordinates (`theta = 0` everywhere on a flat surface):
//!
//! ```text
//! t = ( cos θ, 0, -sin θ)
//! w = ( 0,     1,  0    )
//! n = ( sin θ, 0,  cos θ)
//! ```
//!
//! ```
//! use optical_tactile::geometry::{FlatSurface, SensorGeometry};
//! let g = SensorGeometry::default();
//! // Point 2 of the characterization protocol lies 120 mm of arc left of centre.
//! let x = g.arc_to_chord(-120.0);
//! assert!((x + 114.1).abs() < 0.1);
//! assert!((g.z_at(0.0) - 160.0).abs() < 1e-12);
//! // A flat 24 x 18 mm gel: contacts are located in x and y.
//! let flat = SensorGeometry::Flat(FlatSurface { length_mm: 24.0, width_mm: 18.0 });
//! assert!(flat.locates_in_2d() && flat.contains(11.9, -8.9));
//! assert_eq!(flat.point_at(3.0, -2.0), [3.0, -2.0, 0.0]);
//! ```

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Largest length or width of a sensing surface a geometry may describe,
/// mm (10 m): bounds what a file may ask for.
pub const MAX_SURFACE_MM: f64 = 10_000.0;

fn check_positive(name: &str, v: f64) -> Result<()> {
    if v.is_finite() && v > 0.0 && v <= MAX_SURFACE_MM {
        Ok(())
    } else {
        Err(Error::param(
            name,
            format!("must be finite, > 0 and at most {MAX_SURFACE_MM} mm, got {v}"),
        ))
    }
}

/// The shape of a sensor's sensing surface, and the sensor frame it
/// defines (module docs). Stored in calibration files with a `kind`
/// (`curved_strip` or `flat`; a file without `kind` is a curved strip).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "GeometryRepr", into = "GeometryRepr")]
pub enum SensorGeometry {
    /// The paper's curved strip: an arc of a circle, pressed by rods across
    /// its width; contacts are located along the arc.
    CurvedStrip(CurvedStrip),
    /// A flat rectangle: contacts are located in both surface coordinates.
    Flat(FlatSurface),
}

impl Default for SensorGeometry {
    /// The reference sensor of the paper ([`CurvedStrip::default`]).
    fn default() -> Self {
        SensorGeometry::CurvedStrip(CurvedStrip::default())
    }
}

impl From<CurvedStrip> for SensorGeometry {
    fn from(g: CurvedStrip) -> Self {
        SensorGeometry::CurvedStrip(g)
    }
}

impl From<FlatSurface> for SensorGeometry {
    fn from(g: FlatSurface) -> Self {
        SensorGeometry::Flat(g)
    }
}

/// A flat rectangular sensing surface (all lengths in mm), centred on the
/// sensor frame's origin with its outward normal along `+z`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FlatSurface {
    /// Extent along `x`, mm.
    pub length_mm: f64,
    /// Extent along `y`, mm.
    pub width_mm: f64,
}

impl FlatSurface {
    /// Checks that both sides are finite, positive and at most
    /// [`MAX_SURFACE_MM`].
    pub fn validate(&self) -> Result<()> {
        check_positive("length_mm", self.length_mm)?;
        check_positive("width_mm", self.width_mm)
    }
}

impl SensorGeometry {
    /// Checks that every dimension is finite and makes sense.
    pub fn validate(&self) -> Result<()> {
        match self {
            SensorGeometry::CurvedStrip(g) => g.validate(),
            SensorGeometry::Flat(g) => g.validate(),
        }
    }

    /// A surface named as on the command line: `strip` (the default curved
    /// strip) or `flat:LENGTHxWIDTH` (mm, e.g. `flat:24x18`); anything else,
    /// or a dimension [`SensorGeometry::validate`] refuses, is
    /// [`Error::InvalidParameter`].
    pub fn parse(text: &str) -> Result<Self> {
        let bad = || {
            Error::param(
                "geometry",
                format!("expected strip or flat:LENGTHxWIDTH (mm, e.g. flat:24x18), got `{text}`"),
            )
        };
        let g = match text.split_once(':') {
            None if text == "strip" => SensorGeometry::default(),
            Some(("flat", dims)) => {
                let (l, w) = dims.split_once('x').ok_or_else(bad)?;
                let num = |x: &str| x.trim().parse::<f64>().map_err(|_| bad());
                SensorGeometry::Flat(FlatSurface {
                    length_mm: num(l)?,
                    width_mm: num(w)?,
                })
            }
            _ => return Err(bad()),
        };
        g.validate()?;
        Ok(g)
    }

    /// The surface's name in files and messages: `curved_strip` or `flat`.
    pub fn kind(&self) -> &'static str {
        match self {
            SensorGeometry::CurvedStrip(_) => "curved_strip",
            SensorGeometry::Flat(_) => "flat",
        }
    }

    /// The curved strip, if this is one.
    pub fn as_curved_strip(&self) -> Option<&CurvedStrip> {
        match self {
            SensorGeometry::CurvedStrip(g) => Some(g),
            SensorGeometry::Flat(_) => None,
        }
    }

    /// Whether contacts are located in both surface coordinates: `true` for
    /// a flat surface (its calibration maps `x` and `y` from the contact
    /// point in 2-D), `false` for the curved strip (pressed by rods across
    /// its width: `x` along the arc, `y` as the calibration's `g2` says).
    pub fn locates_in_2d(&self) -> bool {
        matches!(self, SensorGeometry::Flat(_))
    }

    /// Width of the surface across (along `y`), mm.
    pub fn width_mm(&self) -> f64 {
        match self {
            SensorGeometry::CurvedStrip(g) => g.width_mm,
            SensorGeometry::Flat(g) => g.width_mm,
        }
    }

    /// The largest `|x|` on the surface (half the chord; half the length of a
    /// flat surface).
    pub fn half_chord_mm(&self) -> f64 {
        match self {
            SensorGeometry::CurvedStrip(g) => g.half_chord_mm(),
            SensorGeometry::Flat(g) => 0.5 * g.length_mm,
        }
    }

    /// Half the surface's length along `x`, measured on the surface (half
    /// the arc; half the length of a flat surface).
    pub fn half_arc_mm(&self) -> f64 {
        match self {
            SensorGeometry::CurvedStrip(g) => g.half_arc_mm(),
            SensorGeometry::Flat(g) => 0.5 * g.length_mm,
        }
    }

    /// Angle (radians) between the outward normal at `x` and `+z` (0
    /// everywhere on a flat surface).
    pub fn angle_at(&self, x_mm: f64) -> f64 {
        match self {
            SensorGeometry::CurvedStrip(g) => g.angle_at(x_mm),
            SensorGeometry::Flat(_) => 0.0,
        }
    }

    /// Signed length along the surface from `x = 0` to `x` (the arc length;
    /// `x` itself on a flat surface).
    pub fn chord_to_arc(&self, x_mm: f64) -> f64 {
        match self {
            SensorGeometry::CurvedStrip(g) => g.chord_to_arc(x_mm),
            SensorGeometry::Flat(_) => x_mm,
        }
    }

    /// Inverse of [`SensorGeometry::chord_to_arc`].
    pub fn arc_to_chord(&self, s_mm: f64) -> f64 {
        match self {
            SensorGeometry::CurvedStrip(g) => g.arc_to_chord(s_mm),
            SensorGeometry::Flat(_) => s_mm,
        }
    }

    /// Height `z` of the surface at `x` (`sqrt(R^2 - x^2) - d` on the strip,
    /// 0 on a flat surface).
    pub fn z_at(&self, x_mm: f64) -> f64 {
        match self {
            SensorGeometry::CurvedStrip(g) => g.z_at(x_mm),
            SensorGeometry::Flat(_) => 0.0,
        }
    }

    /// Whether the point (`x`, `y`) lies on the surface.
    pub fn contains(&self, x_mm: f64, y_mm: f64) -> bool {
        x_mm.is_finite()
            && y_mm.is_finite()
            && x_mm.abs() <= self.half_chord_mm()
            && y_mm.abs() <= self.width_mm() / 2.0
    }

    /// The local surface frame at `x`, as a rotation matrix whose columns
    /// are `t`, `w`, `n` in sensor coordinates. It maps local components
    /// `(tangent, across, normal)` to sensor components `(x, y, z)`.
    pub fn local_frame(&self, x_mm: f64) -> Matrix3<f64> {
        let (s, c) = self.angle_at(x_mm).sin_cos();
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

    /// The outward unit normal at `x`, sensor frame.
    pub fn normal_at(&self, x_mm: f64) -> [f64; 3] {
        self.local_to_sensor(x_mm, [0.0, 0.0, 1.0])
    }

    /// The surface point at `(x, y)`, in the sensor frame.
    pub fn point_at(&self, x_mm: f64, y_mm: f64) -> [f64; 3] {
        [x_mm, y_mm, self.z_at(x_mm)]
    }
}

/// How a geometry is written in a file: a `kind` and the fields of that
/// kind (docs/formats.md). A file without `kind` is a curved strip.
#[derive(Serialize, Deserialize)]
struct GeometryRepr {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    kind: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    radius_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    d_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    opening_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    length_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    width_mm: Option<f64>,
}

impl From<SensorGeometry> for GeometryRepr {
    fn from(g: SensorGeometry) -> Self {
        let kind = Some(g.kind().to_string());
        match g {
            SensorGeometry::CurvedStrip(c) => GeometryRepr {
                kind,
                radius_mm: Some(c.radius_mm),
                d_mm: Some(c.d_mm),
                opening_deg: Some(c.opening_deg),
                length_mm: None,
                width_mm: Some(c.width_mm),
            },
            SensorGeometry::Flat(f) => GeometryRepr {
                kind,
                radius_mm: None,
                d_mm: None,
                opening_deg: None,
                length_mm: Some(f.length_mm),
                width_mm: Some(f.width_mm),
            },
        }
    }
}

impl TryFrom<GeometryRepr> for SensorGeometry {
    type Error = String;

    fn try_from(r: GeometryRepr) -> std::result::Result<Self, String> {
        let kind = r.kind.as_deref().unwrap_or("curved_strip");
        let need = |name: &str, v: Option<f64>| {
            v.ok_or_else(|| format!("a {kind} geometry needs `{name}`"))
        };
        let refuse = |name: &str, v: Option<f64>| match v {
            Some(_) => Err(format!("`{name}` does not apply to a {kind} geometry")),
            None => Ok(()),
        };
        match kind {
            "curved_strip" => {
                refuse("length_mm", r.length_mm)?;
                Ok(SensorGeometry::CurvedStrip(CurvedStrip {
                    radius_mm: need("radius_mm", r.radius_mm)?,
                    d_mm: need("d_mm", r.d_mm)?,
                    opening_deg: need("opening_deg", r.opening_deg)?,
                    width_mm: need("width_mm", r.width_mm)?,
                }))
            }
            "flat" => {
                refuse("radius_mm", r.radius_mm)?;
                refuse("d_mm", r.d_mm)?;
                refuse("opening_deg", r.opening_deg)?;
                Ok(SensorGeometry::Flat(FlatSurface {
                    length_mm: need("length_mm", r.length_mm)?,
                    width_mm: need("width_mm", r.width_mm)?,
                }))
            }
            other => Err(format!(
                "unknown geometry kind `{other}` (curved_strip, flat)"
            )),
        }
    }
}

/// The geometry of a curved sensing skin (all lengths in mm).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CurvedStrip {
    /// Radius `R` of the skin's arc.
    pub radius_mm: f64,
    /// Distance `d` from the circle's centre to the sensor frame's origin.
    pub d_mm: f64,
    /// Opening angle of the arc, in degrees.
    pub opening_deg: f64,
    /// Width of the skin across the arc (along `y`).
    pub width_mm: f64,
}

impl Default for CurvedStrip {
    /// The reference sensor of the paper: R = 220 mm, d = 60 mm, 86 deg, 40 mm wide.
    fn default() -> Self {
        CurvedStrip {
            radius_mm: 220.0,
            d_mm: 60.0,
            opening_deg: 86.0,
            width_mm: 40.0,
        }
    }
}

impl CurvedStrip {
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
        check_positive("radius_mm", self.radius_mm)?;
        check_positive("width_mm", self.width_mm)?;
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn surfaces_parse_from_their_command_line_names() {
        assert_eq!(
            SensorGeometry::parse("strip").unwrap(),
            SensorGeometry::default()
        );
        let flat = SensorGeometry::parse("flat:24x18").unwrap();
        assert_eq!(
            flat,
            SensorGeometry::Flat(FlatSurface {
                length_mm: 24.0,
                width_mm: 18.0
            })
        );
        assert_eq!(
            SensorGeometry::parse("flat: 30 x 20.5").unwrap().kind(),
            "flat"
        );
        for bad in [
            "",
            "curved",
            "flat",
            "flat:24",
            "flat:24x",
            "flat:ax18",
            "flat:0x18",
            "flat:-24x18",
            "flat:24x1e9",
            "flat:NaNx18",
            "strip:1",
            "flat:24x18x3",
        ] {
            let e = SensorGeometry::parse(bad).unwrap_err();
            assert!(matches!(e, Error::InvalidParameter { .. }), "{bad:?}: {e}");
        }
    }
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
            let c = g.as_curved_strip().unwrap();
            let z = g.z_at(x) + c.d_mm;
            assert_relative_eq!((x * x + z * z).sqrt(), c.radius_mm, epsilon = 1e-9);
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
            let c = CurvedStrip::default();
            let p = Vector3::new(x, 0.0, g.z_at(x) + c.d_mm) / c.radius_mm;
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
        let c = CurvedStrip::default();
        let bad = SensorGeometry::from(CurvedStrip {
            radius_mm: -1.0,
            ..c
        });
        assert!(bad.validate().is_err());
        let bad = SensorGeometry::from(CurvedStrip {
            opening_deg: 200.0,
            ..c
        });
        assert!(bad.validate().is_err());
        let bad = SensorGeometry::from(CurvedStrip {
            radius_mm: 1e9,
            ..c
        });
        assert!(bad.validate().is_err());
    }

    #[test]
    fn a_flat_surface_is_its_own_local_frame() {
        let g = SensorGeometry::from(FlatSurface {
            length_mm: 24.0,
            width_mm: 18.0,
        });
        g.validate().unwrap();
        assert!(g.locates_in_2d() && !SensorGeometry::default().locates_in_2d());
        for x in [-12.0, -3.3, 0.0, 7.5, 12.0] {
            assert_eq!(g.local_frame(x), Matrix3::identity());
            assert_eq!(g.chord_to_arc(x), x);
            assert_eq!(g.arc_to_chord(x), x);
            assert_eq!(g.z_at(x), 0.0);
            assert_eq!(g.normal_at(x), [0.0, 0.0, 1.0]);
        }
        assert_eq!(g.half_chord_mm(), 12.0);
        assert!(g.contains(12.0, 9.0) && !g.contains(12.01, 0.0) && !g.contains(0.0, -9.01));
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 2e4] {
            let f = FlatSurface {
                length_mm: bad,
                width_mm: 18.0,
            };
            assert!(SensorGeometry::from(f).validate().is_err(), "{bad}");
        }
    }

    #[test]
    fn geometries_round_trip_through_json_and_old_files_read_as_strips() {
        for g in [
            SensorGeometry::default(),
            SensorGeometry::from(FlatSurface {
                length_mm: 24.0,
                width_mm: 18.0,
            }),
        ] {
            let text = serde_json::to_string(&g).unwrap();
            assert!(
                text.contains(&format!("\"kind\":\"{}\"", g.kind())),
                "{text}"
            );
            let back: SensorGeometry = serde_json::from_str(&text).unwrap();
            assert_eq!(back, g);
        }
        let old = r#"{"radius_mm": 220.0, "d_mm": 60.0, "opening_deg": 86.0, "width_mm": 40.0}"#;
        let g: SensorGeometry = serde_json::from_str(old).unwrap();
        assert_eq!(g, SensorGeometry::default());
        for (bad, says) in [
            (
                r#"{"kind": "dome", "width_mm": 4}"#,
                "unknown geometry kind `dome`",
            ),
            (r#"{"kind": "flat", "width_mm": 4}"#, "needs `length_mm`"),
            (
                r#"{"kind": "flat", "length_mm": 4, "width_mm": 4, "radius_mm": 9}"#,
                "`radius_mm` does not apply",
            ),
            (
                r#"{"radius_mm": 220.0, "d_mm": 60.0, "width_mm": 40.0}"#,
                "needs `opening_deg`",
            ),
            (r#"{"kind": 3}"#, "invalid type"),
        ] {
            let e = serde_json::from_str::<SensorGeometry>(bad).unwrap_err();
            assert!(e.to_string().contains(says), "{bad}: {e}");
        }
    }
}
