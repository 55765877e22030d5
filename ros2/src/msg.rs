//! The ROS 2 messages the node publishes, as plain structs whose field
//! order is the message definition's: serialized with CDR they are the
//! messages ROS 2 tools read (`ros2 topic echo`, RViz).
//!
//! Only the messages the node needs are here, each with its ROS type name
//! ([`RosMessage::TYPE`]). Every float is checked before publishing
//! ([`Finite`]).

use serde::{Deserialize, Serialize};

/// A message type: its ROS 2 package and name, e.g. `("geometry_msgs", "WrenchStamped")`.
pub trait RosMessage {
    /// `(package, name)` of the message type (`package/msg/name`).
    const TYPE: (&'static str, &'static str);
}

/// Whether every float of a message is finite (no NaN, no infinity).
pub trait Finite {
    /// `true` when every float in the message is finite.
    fn is_finite(&self) -> bool;
}

impl<T: Finite> Finite for [T] {
    fn is_finite(&self) -> bool {
        self.iter().all(Finite::is_finite)
    }
}

impl<T: Finite> Finite for Vec<T> {
    fn is_finite(&self) -> bool {
        self.as_slice().is_finite()
    }
}

/// `builtin_interfaces/Time`: seconds and nanoseconds since the Unix epoch.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Time {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds, `0..1_000_000_000`.
    pub nanosec: u32,
}

impl Time {
    /// The time `t` on the system clock; times before the epoch or past
    /// 2038 (outside `builtin_interfaces/Time`) are clamped to its range.
    pub fn from_system(t: std::time::SystemTime) -> Time {
        match t.duration_since(std::time::UNIX_EPOCH) {
            Ok(d) if d.as_secs() <= i32::MAX as u64 => Time {
                sec: d.as_secs() as i32,
                nanosec: d.subsec_nanos(),
            },
            Ok(_) => Time {
                sec: i32::MAX,
                nanosec: 999_999_999,
            },
            Err(_) => Time::default(),
        }
    }

    /// Seconds since the epoch as a float.
    pub fn as_secs_f64(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }
}

/// `builtin_interfaces/Duration`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Duration {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds, `0..1_000_000_000`.
    pub nanosec: u32,
}

impl Duration {
    /// A duration of `s` seconds (negative, NaN: zero; beyond `i32` seconds: clamped).
    pub fn from_secs_f64(s: f64) -> Duration {
        if s.is_nan() || s <= 0.0 {
            return Duration::default();
        }
        let s = s.min(i32::MAX as f64);
        let sec = s.floor();
        Duration {
            sec: sec as i32,
            nanosec: (((s - sec) * 1e9) as u32).min(999_999_999),
        }
    }
}

/// `std_msgs/Header`: a time stamp and the frame the data is in.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// When the data was captured.
    pub stamp: Time,
    /// The coordinate frame (tf2) of the data.
    pub frame_id: String,
}

/// `geometry_msgs/Point`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/Vector3`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

impl From<[f64; 3]> for Vector3 {
    fn from([x, y, z]: [f64; 3]) -> Self {
        Vector3 { x, y, z }
    }
}

impl From<[f64; 3]> for Point {
    fn from([x, y, z]: [f64; 3]) -> Self {
        Point { x, y, z }
    }
}

impl Finite for Point {
    fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.z.is_finite()
    }
}

impl Finite for Vector3 {
    fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.z.is_finite()
    }
}

/// `geometry_msgs/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

impl Default for Quaternion {
    /// The identity rotation.
    fn default() -> Self {
        Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

impl Finite for Quaternion {
    fn is_finite(&self) -> bool {
        [self.x, self.y, self.z, self.w]
            .iter()
            .all(|v| v.is_finite())
    }
}

/// `geometry_msgs/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position.
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}

impl Finite for Pose {
    fn is_finite(&self) -> bool {
        self.position.is_finite() && self.orientation.is_finite()
    }
}

/// `geometry_msgs/Wrench`: a force (N) and a torque (N m).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Wrench {
    /// Force, N.
    pub force: Vector3,
    /// Torque, N m.
    pub torque: Vector3,
}

impl Finite for Wrench {
    fn is_finite(&self) -> bool {
        self.force.is_finite() && self.torque.is_finite()
    }
}

/// `geometry_msgs/WrenchStamped`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct WrenchStamped {
    /// Stamp and frame.
    pub header: Header,
    /// The wrench.
    pub wrench: Wrench,
}

impl RosMessage for WrenchStamped {
    const TYPE: (&'static str, &'static str) = ("geometry_msgs", "WrenchStamped");
}

impl Finite for WrenchStamped {
    fn is_finite(&self) -> bool {
        self.wrench.is_finite()
    }
}

/// `tactile_msgs/TactileContact`: one contact's location, surface normal
/// and wrench.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TactileContact {
    /// Stamp and frame of the contact.
    pub header: Header,
    /// A unique name of the contact.
    pub name: String,
    /// The contact point.
    pub position: Point,
    /// The surface normal at the contact point.
    pub normal: Vector3,
    /// The wrench applied through the contact point, in the header's frame.
    pub wrench: Wrench,
}

impl Finite for TactileContact {
    fn is_finite(&self) -> bool {
        self.position.is_finite() && self.normal.is_finite() && self.wrench.is_finite()
    }
}

/// `tactile_msgs/TactileContacts`: every contact of one frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TactileContacts {
    /// Stamp and frame of the frame.
    pub header: Header,
    /// The contacts, none when nothing touches.
    pub contacts: Vec<TactileContact>,
}

impl RosMessage for TactileContacts {
    const TYPE: (&'static str, &'static str) = ("tactile_msgs", "TactileContacts");
}

impl Finite for TactileContacts {
    fn is_finite(&self) -> bool {
        self.contacts.is_finite()
    }
}

/// `std_msgs/ColorRGBA`, components in `[0, 1]`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRGBA {
    /// Red.
    pub r: f32,
    /// Green.
    pub g: f32,
    /// Blue.
    pub b: f32,
    /// Opacity.
    pub a: f32,
}

impl Finite for ColorRGBA {
    fn is_finite(&self) -> bool {
        [self.r, self.g, self.b, self.a]
            .iter()
            .all(|v| v.is_finite())
    }
}

/// `sensor_msgs/CompressedImage` (a field of [`Marker`]; the node leaves it empty).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Stamp and frame.
    pub header: Header,
    /// `jpeg` or `png`.
    pub format: String,
    /// The compressed bytes.
    pub data: Vec<u8>,
}

/// `visualization_msgs/UVCoordinate` (a field of [`Marker`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UVCoordinate {
    /// u.
    pub u: f32,
    /// v.
    pub v: f32,
}

impl Finite for UVCoordinate {
    fn is_finite(&self) -> bool {
        self.u.is_finite() && self.v.is_finite()
    }
}

/// `visualization_msgs/MeshFile` (a field of [`Marker`]; the node leaves it empty).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshFile {
    /// File name.
    pub filename: String,
    /// File contents.
    pub data: Vec<u8>,
}

/// `visualization_msgs/Marker` (ROS 2 Humble and later).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    /// Stamp and frame.
    pub header: Header,
    /// Namespace of the marker's id.
    pub ns: String,
    /// Id within the namespace.
    pub id: i32,
    /// Shape ([`Marker::ARROW`], [`Marker::SPHERE`], ...).
    #[serde(rename = "type")]
    pub kind: i32,
    /// [`Marker::ADD`], [`Marker::DELETE`] or [`Marker::DELETEALL`].
    pub action: i32,
    /// Pose of the shape.
    pub pose: Pose,
    /// Size of the shape (for an arrow given by points: shaft and head diameters, head length).
    pub scale: Vector3,
    /// Colour.
    pub color: ColorRGBA,
    /// How long the marker lives, zero for ever.
    pub lifetime: Duration,
    /// Whether the marker moves with its frame.
    pub frame_locked: bool,
    /// Points (an arrow: start and end).
    pub points: Vec<Point>,
    /// Per-point colours.
    pub colors: Vec<ColorRGBA>,
    /// Texture resource URI.
    pub texture_resource: String,
    /// Embedded texture.
    pub texture: CompressedImage,
    /// Texture coordinates.
    pub uv_coordinates: Vec<UVCoordinate>,
    /// Text of a text marker.
    pub text: String,
    /// Mesh resource URI.
    pub mesh_resource: String,
    /// Embedded mesh.
    pub mesh_file: MeshFile,
    /// Whether a mesh uses its own materials.
    pub mesh_use_embedded_materials: bool,
}

impl Marker {
    /// An arrow (from `points[0]` to `points[1]`).
    pub const ARROW: i32 = 0;
    /// A sphere (ellipsoid of diameters `scale`).
    pub const SPHERE: i32 = 2;
    /// Add or replace the marker.
    pub const ADD: i32 = 0;
    /// Delete the marker.
    pub const DELETE: i32 = 2;
    /// Delete every marker of the namespace (every marker, with an empty namespace).
    pub const DELETEALL: i32 = 3;
}

impl Finite for Marker {
    fn is_finite(&self) -> bool {
        self.pose.is_finite()
            && self.scale.is_finite()
            && self.color.is_finite()
            && self.points.is_finite()
            && self.colors.is_finite()
            && self.uv_coordinates.is_finite()
    }
}

/// `visualization_msgs/MarkerArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerArray {
    /// The markers.
    pub markers: Vec<Marker>,
}

impl RosMessage for MarkerArray {
    const TYPE: (&'static str, &'static str) = ("visualization_msgs", "MarkerArray");
}

impl Finite for MarkerArray {
    fn is_finite(&self) -> bool {
        self.markers.is_finite()
    }
}

/// `sensor_msgs/Image`: an uncompressed image.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Stamp and frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding, e.g. `rgb8`.
    pub encoding: String,
    /// Whether multi-byte values are big-endian.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// The pixels, `step * height` bytes.
    pub data: Vec<u8>,
}

impl RosMessage for Image {
    const TYPE: (&'static str, &'static str) = ("sensor_msgs", "Image");
}

impl Finite for Image {
    fn is_finite(&self) -> bool {
        true
    }
}

/// `sensor_msgs/PointField`: one field of a [`PointCloud2`]'s points.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PointField {
    /// The field's name.
    pub name: String,
    /// Byte offset of the field in a point.
    pub offset: u32,
    /// Its type: [`PointField::UINT8`], [`PointField::UINT32`], [`PointField::FLOAT64`], ...
    pub datatype: u8,
    /// How many values of that type the field holds.
    pub count: u32,
}

impl PointField {
    /// An unsigned byte.
    pub const UINT8: u8 = 2;
    /// An unsigned 32-bit integer.
    pub const UINT32: u8 = 6;
    /// A 32-bit float.
    pub const FLOAT32: u8 = 7;
    /// A 64-bit float.
    pub const FLOAT64: u8 = 8;

    /// Bytes of one value of `datatype`, `None` for an unknown type.
    pub fn size_of(datatype: u8) -> Option<u32> {
        match datatype {
            1 | 2 => Some(1),
            3 | 4 => Some(2),
            5..=7 => Some(4),
            8 => Some(8),
            _ => None,
        }
    }
}

/// `sensor_msgs/PointCloud2`: points of named, typed fields packed in bytes.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp and frame.
    pub header: Header,
    /// Rows of points (1 for an unordered cloud).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The fields of every point.
    pub fields: Vec<PointField>,
    /// Whether multi-byte values are big-endian.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points, `row_step * height` bytes.
    pub data: Vec<u8>,
    /// Whether every value is valid (no NaN).
    pub is_dense: bool,
}

impl RosMessage for PointCloud2 {
    const TYPE: (&'static str, &'static str) = ("sensor_msgs", "PointCloud2");
}

impl PointCloud2 {
    /// The `k`-th value (of `count`) of the field `name` of point `i`, read
    /// as a float whatever its type; `None` when there is no such field,
    /// point or value, or the bytes run short.
    pub fn value(&self, i: usize, name: &str, k: usize) -> Option<f64> {
        let f = self.fields.iter().find(|f| f.name == name)?;
        self.read(i, f, k)
    }

    fn read(&self, i: usize, f: &PointField, k: usize) -> Option<f64> {
        if i >= (self.width as usize).saturating_mul(self.height as usize) || k >= f.count as usize
        {
            return None;
        }
        let size = PointField::size_of(f.datatype)? as usize;
        let start = i
            .checked_mul(self.point_step as usize)?
            .checked_add(f.offset as usize)?
            .checked_add(k * size)?;
        let bytes = self.data.get(start..start.checked_add(size)?)?;
        let mut b = [0u8; 8];
        b[..size].copy_from_slice(bytes);
        if self.is_bigendian {
            b[..size].reverse();
        }
        Some(match f.datatype {
            1 => b[0] as i8 as f64,
            2 => b[0] as f64,
            3 => i16::from_le_bytes([b[0], b[1]]) as f64,
            4 => u16::from_le_bytes([b[0], b[1]]) as f64,
            5 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            6 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            7 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            _ => f64::from_le_bytes(b),
        })
    }
}

impl Finite for PointCloud2 {
    /// Every float value of every point is finite, and every value lies
    /// within `data` (a cloud whose bytes run short is not).
    fn is_finite(&self) -> bool {
        let points = (self.width as usize).saturating_mul(self.height as usize);
        self.fields.iter().all(|f| {
            (0..points).all(|i| {
                (0..f.count as usize).all(|k| self.read(i, f, k).is_some_and(f64::is_finite))
            })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_from_the_system_clock() {
        let t = std::time::UNIX_EPOCH + std::time::Duration::new(1_700_000_000, 123_456_789);
        assert_eq!(
            Time::from_system(t),
            Time {
                sec: 1_700_000_000,
                nanosec: 123_456_789
            }
        );
        let before = std::time::UNIX_EPOCH - std::time::Duration::from_secs(1);
        assert_eq!(Time::from_system(before), Time::default());
    }

    #[test]
    fn durations_are_clamped() {
        assert_eq!(
            Duration::from_secs_f64(0.25),
            Duration {
                sec: 0,
                nanosec: 250_000_000
            }
        );
        assert_eq!(Duration::from_secs_f64(f64::NAN), Duration::default());
        assert_eq!(Duration::from_secs_f64(-1.0), Duration::default());
        assert_eq!(Duration::from_secs_f64(f64::INFINITY).sec, i32::MAX);
    }

    #[test]
    fn cloud_values_are_read_in_either_byte_order_and_within_the_data_only() {
        let field = |name: &str, offset, datatype| PointField {
            name: name.into(),
            offset,
            datatype,
            count: 1,
        };
        let mut data = 2.5f64.to_le_bytes().to_vec();
        data.extend_from_slice(&7u32.to_le_bytes());
        let mut c = PointCloud2 {
            height: 1,
            width: 1,
            fields: vec![
                field("a", 0, PointField::FLOAT64),
                field("n", 8, PointField::UINT32),
            ],
            point_step: 12,
            row_step: 12,
            data,
            is_dense: true,
            ..Default::default()
        };
        assert!(c.is_finite());
        assert_eq!(
            (c.value(0, "a", 0), c.value(0, "n", 0)),
            (Some(2.5), Some(7.0))
        );
        assert_eq!(c.value(0, "a", 1), None);
        assert_eq!(c.value(1, "a", 0), None);
        // Big-endian bytes of the same values.
        let mut be = 2.5f64.to_be_bytes().to_vec();
        be.extend_from_slice(&7u32.to_be_bytes());
        let b = PointCloud2 {
            is_bigendian: true,
            data: be,
            ..c.clone()
        };
        assert_eq!(
            (b.value(0, "a", 0), b.value(0, "n", 0)),
            (Some(2.5), Some(7.0))
        );
        // A NaN, bytes that run short, an unknown type, a huge offset.
        c.data[..8].copy_from_slice(&f64::NAN.to_le_bytes());
        assert!(!c.is_finite());
        c.data[..8].copy_from_slice(&1.0f64.to_le_bytes());
        c.data.truncate(10);
        assert!(!c.is_finite());
        c.data.resize(12, 0);
        assert!(c.is_finite());
        c.fields[1].datatype = 99;
        assert!(!c.is_finite());
        c.fields[1] = field("n", u32::MAX, PointField::UINT32);
        assert!(!c.is_finite());
        c.width = u32::MAX;
        c.height = u32::MAX;
        assert_eq!(c.value(usize::MAX, "a", 0), None);
    }

    #[test]
    fn a_non_finite_float_anywhere_is_found() {
        let mut c = TactileContacts {
            contacts: vec![TactileContact::default(); 2],
            ..Default::default()
        };
        assert!(c.is_finite());
        c.contacts[1].wrench.torque.y = f64::NAN;
        assert!(!c.is_finite());
        let mut m = MarkerArray {
            markers: vec![Marker::default()],
        };
        assert!(m.is_finite());
        m.markers[0].points.push(Point {
            x: f64::INFINITY,
            ..Default::default()
        });
        assert!(!m.is_finite());
        let mut m = Marker::default();
        m.color.a = f32::NAN;
        assert!(!m.is_finite());
        let w = WrenchStamped {
            wrench: Wrench {
                force: Vector3 {
                    z: f64::NEG_INFINITY,
                    ..Default::default()
                },
                ..Default::default()
            },
            ..Default::default()
        };
        assert!(!w.is_finite());
    }
}
