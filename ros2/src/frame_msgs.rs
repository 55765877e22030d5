//! One frame's messages: the contacts, the net wrench and the RViz markers,
//! built from the sensor's output, and the guard that no message with a
//! non-finite float goes out.

use optical_tactile::contact::{Contact, RawContact};
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::viz::Canvas;

use crate::msg::{
    ColorRGBA, Duration, Finite, Header, Image, Marker, MarkerArray, Point, PointCloud2,
    PointField, Pose, TactileContact, TactileContacts, Vector3, Wrench, WrenchStamped,
};

/// Metres per millimetre.
const M_PER_MM: f64 = 1e-3;

/// How the markers look.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerStyle {
    /// Diameter of a contact's sphere, m.
    pub sphere_m: f64,
    /// Length of a force arrow per newton, m/N.
    pub arrow_m_per_n: f64,
    /// How long a marker stays when no later message replaces it, s.
    pub lifetime_s: f64,
}

impl Default for MarkerStyle {
    fn default() -> Self {
        MarkerStyle {
            sphere_m: 0.004,
            arrow_m_per_n: 0.02,
            lifetime_s: 0.5,
        }
    }
}

/// Everything the node publishes for one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameMessages {
    /// The contacts (calibrated), or the patches in pixels (raw mode).
    pub contacts: TactileContacts,
    /// The net wrench about the sensor frame's origin (calibrated only).
    pub wrench: Option<WrenchStamped>,
    /// Every contact with all the sensor says of it, force sigma included
    /// (calibrated only; [`contact_cloud`]).
    pub cloud: Option<PointCloud2>,
    /// The markers: a DELETEALL, then a sphere and a force arrow per contact.
    pub markers: MarkerArray,
    /// The debug panel, when asked for.
    pub image: Option<Image>,
}

/// Why a frame's messages were not published.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NonFinite {
    /// Which message held the non-finite value.
    pub message: &'static str,
}

impl std::fmt::Display for NonFinite {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "the {} message holds a non-finite value", self.message)
    }
}

impl FrameMessages {
    /// Checks every float of every message: `Err` names the first message
    /// that holds a NaN or an infinity (then none of the frame's messages
    /// may be published).
    pub fn check_finite(&self) -> Result<(), NonFinite> {
        let bad = |message| Err(NonFinite { message });
        if !self.contacts.is_finite() {
            return bad("contacts");
        }
        if self.wrench.as_ref().is_some_and(|w| !w.is_finite()) {
            return bad("wrench");
        }
        if self.cloud.as_ref().is_some_and(|c| !c.is_finite()) {
            return bad("contact cloud");
        }
        if !self.markers.is_finite() {
            return bad("markers");
        }
        Ok(())
    }
}

/// The name of a tracked contact in [`TactileContact::name`]: `contact_<id>`.
pub fn contact_name(id: u64) -> String {
    format!("contact_{id}")
}

/// The tracked id in a [`contact_name`], `None` for another name.
pub fn contact_id(name: &str) -> Option<u64> {
    name.strip_prefix("contact_")?.parse().ok()
}

/// The messages of one calibrated frame: every contact the sensor reports
/// (position in metres, force in newtons, both in the sensor frame; the
/// outward skin normal at the contact; no torque: a point contact), the net
/// wrench about the sensor frame's origin (the forces' sum, and the sum of
/// `p x F` with `p` in metres), the contact cloud ([`contact_cloud`], with
/// the force sigmas when `sigma`: a calibration with an uncertainty model)
/// and the markers.
pub fn calibrated(
    header: &Header,
    contacts: &[Contact],
    geometry: &SensorGeometry,
    style: &MarkerStyle,
    sigma: bool,
) -> FrameMessages {
    let mut list = Vec::with_capacity(contacts.len());
    let mut net = Wrench::default();
    for c in contacts {
        let p = c.location_mm.map(|v| v * M_PER_MM);
        let f = c.force_n;
        let normal = geometry.local_to_sensor(c.location_mm[0], [0.0, 0.0, 1.0]);
        list.push(TactileContact {
            header: header.clone(),
            name: contact_name(c.id),
            position: p.into(),
            normal: normal.into(),
            wrench: Wrench {
                force: f.into(),
                torque: Vector3::default(),
            },
        });
        net.force.x += f[0];
        net.force.y += f[1];
        net.force.z += f[2];
        let t = cross(p, f);
        net.torque.x += t[0];
        net.torque.y += t[1];
        net.torque.z += t[2];
    }
    let markers = markers(header, contacts, style);
    FrameMessages {
        contacts: TactileContacts {
            header: header.clone(),
            contacts: list,
        },
        wrench: Some(WrenchStamped {
            header: header.clone(),
            wrench: net,
        }),
        cloud: Some(contact_cloud(header, contacts, sigma)),
        markers,
        image: None,
    }
}

/// The fields of a [`contact_cloud`], in order: name and type.
const CLOUD_FIELDS: [(&str, u8); 10] = [
    ("x", PointField::FLOAT64),
    ("y", PointField::FLOAT64),
    ("z", PointField::FLOAT64),
    ("fx", PointField::FLOAT64),
    ("fy", PointField::FLOAT64),
    ("fz", PointField::FLOAT64),
    ("id", PointField::UINT32),
    ("held_frames", PointField::UINT32),
    ("out_of_domain", PointField::UINT8),
    ("fallback", PointField::UINT8),
];

/// The force sigma fields a [`contact_cloud`] adds with `sigma`.
const SIGMA_FIELDS: [&str; 3] = ["fx_sigma", "fy_sigma", "fz_sigma"];

/// Every contact of a frame as one point of an unordered `PointCloud2`
/// (little-endian, one row): `x`, `y`, `z` (m) and `fx`, `fy`, `fz` (N) in
/// the sensor frame as `float64`; `id` (the tracked id, saturated at
/// `u32::MAX`) and `held_frames` (frames the tracker has held it without a
/// detection) as `uint32`; `out_of_domain` and `fallback` (0 or 1) as
/// `uint8`; with `sigma`, then `fx_sigma`, `fy_sigma`, `fz_sigma` (N, the
/// standard deviation of each force component's error) as `float64`.
///
/// `TactileContacts` has no field for what a robot needs to weigh a
/// reading (its uncertainty, whether the calibration knows such a contact):
/// this message carries all of it in a standard type that ROS tools and
/// `sensor_msgs_py.point_cloud2.read_points` read by field name.
pub fn contact_cloud(header: &Header, contacts: &[Contact], sigma: bool) -> PointCloud2 {
    let mut fields = Vec::with_capacity(CLOUD_FIELDS.len() + SIGMA_FIELDS.len());
    let mut offset = 0;
    let sigmas = SIGMA_FIELDS.iter().filter(|_| sigma);
    let names = (CLOUD_FIELDS.iter().copied()).chain(sigmas.map(|&n| (n, PointField::FLOAT64)));
    for (name, datatype) in names {
        fields.push(PointField {
            name: name.into(),
            offset,
            datatype,
            count: 1,
        });
        offset += PointField::size_of(datatype).unwrap_or(0);
    }
    let point_step = offset;
    let mut data = Vec::with_capacity(point_step as usize * contacts.len());
    for c in contacts {
        for v in c.location_mm.map(|v| v * M_PER_MM).iter().chain(&c.force_n) {
            data.extend_from_slice(&v.to_le_bytes());
        }
        let id = u32::try_from(c.id).unwrap_or(u32::MAX);
        data.extend_from_slice(&id.to_le_bytes());
        data.extend_from_slice(&c.missed.to_le_bytes());
        data.push(u8::from(c.out_of_domain));
        data.push(u8::from(c.fallback));
        if sigma {
            // A contact without a sigma under a calibration that has them
            // cannot happen; NaN would stop the frame at the finiteness check.
            for v in c.force_sigma_n.unwrap_or([f64::NAN; 3]) {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    let width = u32::try_from(contacts.len()).unwrap_or(u32::MAX);
    PointCloud2 {
        header: header.clone(),
        height: 1,
        width,
        fields,
        is_bigendian: false,
        point_step,
        row_step: point_step.saturating_mul(width),
        data,
        is_dense: true,
    }
}

/// The messages of one raw (uncalibrated) frame: each patch as a contact
/// named `patch_<k>` (strongest first) whose position is its contact point
/// in pixels of the cropped image `(x_px, y_px, 0)` and whose force is its
/// raw displacements `(ds1, ds2, dn)` in pixels, in the frame `frame_id`
/// of `header` (the node gives it `<frame_id>_raw_px`): no metre, no
/// newton, so no wrench and no marker but the DELETEALL.
pub fn raw(header: &Header, patches: &[RawContact]) -> FrameMessages {
    let contacts = patches
        .iter()
        .enumerate()
        .map(|(k, r)| TactileContact {
            header: header.clone(),
            name: format!("patch_{k}"),
            position: Point {
                x: r.x_px,
                y: r.y_px,
                z: 0.0,
            },
            normal: Vector3 {
                x: 0.0,
                y: 0.0,
                z: 1.0,
            },
            wrench: Wrench {
                force: [r.ds1, r.ds2, r.dn].into(),
                torque: Vector3::default(),
            },
        })
        .collect();
    FrameMessages {
        contacts: TactileContacts {
            header: header.clone(),
            contacts,
        },
        wrench: None,
        cloud: None,
        markers: MarkerArray {
            markers: vec![delete_all(header)],
        },
        image: None,
    }
}

/// The debug panel as an `rgb8` image.
pub fn image(header: &Header, panel: &Canvas) -> Image {
    let (w, h) = (panel.width(), panel.height());
    Image {
        header: header.clone(),
        height: u32::try_from(h).unwrap_or(u32::MAX),
        width: u32::try_from(w).unwrap_or(u32::MAX),
        encoding: "rgb8".into(),
        is_bigendian: 0,
        step: u32::try_from(3 * w).unwrap_or(u32::MAX),
        data: panel.as_bytes().to_vec(),
    }
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn delete_all(header: &Header) -> Marker {
    Marker {
        header: header.clone(),
        action: Marker::DELETEALL,
        ..Marker::default()
    }
}

/// The marker id of a tracked contact: ids past `i32::MAX` wrap round.
fn marker_id(id: u64) -> i32 {
    (id % (i32::MAX as u64 + 1)) as i32
}

/// A DELETEALL (so contacts that have gone vanish from RViz), then per
/// contact a sphere at its location and an arrow of its force ending at
/// the location (the force the skin receives), `arrow_m_per_n` long per
/// newton. Green: detected in this frame; grey: held (no longer detected);
/// orange: outside what the calibration was fitted on.
fn markers(header: &Header, contacts: &[Contact], style: &MarkerStyle) -> MarkerArray {
    let mut markers = Vec::with_capacity(1 + 2 * contacts.len());
    markers.push(delete_all(header));
    let lifetime = Duration::from_secs_f64(style.lifetime_s);
    for c in contacts {
        let color = if c.missed > 0 {
            ColorRGBA {
                r: 0.6,
                g: 0.6,
                b: 0.6,
                a: 0.8,
            }
        } else if c.out_of_domain {
            ColorRGBA {
                r: 1.0,
                g: 0.55,
                b: 0.0,
                a: 1.0,
            }
        } else {
            ColorRGBA {
                r: 0.1,
                g: 0.85,
                b: 0.2,
                a: 1.0,
            }
        };
        let p: Point = c.location_mm.map(|v| v * M_PER_MM).into();
        let id = marker_id(c.id);
        markers.push(Marker {
            header: header.clone(),
            ns: "contacts".into(),
            id,
            kind: Marker::SPHERE,
            action: Marker::ADD,
            pose: Pose {
                position: p,
                ..Pose::default()
            },
            scale: Vector3 {
                x: style.sphere_m,
                y: style.sphere_m,
                z: style.sphere_m,
            },
            color,
            lifetime,
            ..Marker::default()
        });
        let k = style.arrow_m_per_n;
        let start = Point {
            x: p.x - k * c.force_n[0],
            y: p.y - k * c.force_n[1],
            z: p.z - k * c.force_n[2],
        };
        markers.push(Marker {
            header: header.clone(),
            ns: "forces".into(),
            id,
            kind: Marker::ARROW,
            action: Marker::ADD,
            pose: Pose::default(),
            // Shaft diameter, head diameter, head length.
            scale: Vector3 {
                x: style.sphere_m / 4.0,
                y: style.sphere_m / 2.0,
                z: style.sphere_m / 2.0,
            },
            color,
            lifetime,
            points: vec![start, p],
            ..Marker::default()
        });
    }
    MarkerArray { markers }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::Time;

    fn contact(id: u64, location_mm: [f64; 3], force_n: [f64; 3]) -> Contact {
        Contact {
            id,
            location_mm,
            force_n,
            ..Contact::default()
        }
    }

    fn header() -> Header {
        Header {
            stamp: Time { sec: 5, nanosec: 7 },
            frame_id: "tactile".into(),
        }
    }

    #[test]
    fn contacts_in_metres_and_the_net_wrench_about_the_origin() {
        let g = SensorGeometry::default();
        let cs = [
            contact(3, [10.0, -2.0, 159.0], [0.1, 0.0, -1.0]),
            contact(8, [-20.0, 4.0, 158.0], [0.0, 0.2, -0.5]),
        ];
        let m = calibrated(&header(), &cs, &g, &MarkerStyle::default(), false);
        assert_eq!(m.contacts.contacts.len(), 2);
        let c = &m.contacts.contacts[0];
        assert_eq!(contact_id(&c.name), Some(3));
        assert_eq!(c.header, header());
        assert!((c.position.x - 0.010).abs() < 1e-15);
        assert!((c.position.z - 0.159).abs() < 1e-15);
        assert_eq!(c.wrench.force.z, -1.0);
        // The outward normal at x = 10 mm leans towards +x.
        assert!(c.normal.x > 0.0 && c.normal.z > 0.9);
        let n = (c.normal.x.powi(2) + c.normal.y.powi(2) + c.normal.z.powi(2)).sqrt();
        assert!((n - 1.0).abs() < 1e-12);
        let w = m.wrench.as_ref().unwrap().wrench;
        assert!((w.force.x - 0.1).abs() < 1e-15 && (w.force.z + 1.5).abs() < 1e-15);
        // τx = Σ (y Fz - z Fy)
        let tx = -0.002 * -1.0 - 0.159 * 0.0 + (0.004 * -0.5 - 0.158 * 0.2);
        assert!((w.torque.x - tx).abs() < 1e-15);
        m.check_finite().unwrap();
    }

    #[test]
    fn markers_delete_all_first_then_a_sphere_and_an_arrow_per_contact() {
        let g = SensorGeometry::default();
        let cs = [contact(4, [0.0, 0.0, 160.0], [0.0, 0.0, -2.0])];
        let m = calibrated(&header(), &cs, &g, &MarkerStyle::default(), false).markers;
        assert_eq!(m.markers.len(), 3);
        assert_eq!(m.markers[0].action, Marker::DELETEALL);
        assert_eq!(m.markers[1].kind, Marker::SPHERE);
        assert_eq!(m.markers[1].id, 4);
        assert_eq!(m.markers[2].kind, Marker::ARROW);
        // The arrow ends at the contact and points along the force.
        let [a, b] = [m.markers[2].points[0], m.markers[2].points[1]];
        assert!((b.z - 0.160).abs() < 1e-15 && a.z > b.z);
        assert!(m.markers[1].lifetime.nanosec > 0);

        let empty = calibrated(&header(), &[], &g, &MarkerStyle::default(), false);
        assert!(empty.contacts.contacts.is_empty());
        assert_eq!(empty.markers.markers.len(), 1);
        assert_eq!(empty.wrench.unwrap().wrench, Wrench::default());
    }

    #[test]
    fn a_non_finite_contact_stops_the_frame() {
        let g = SensorGeometry::default();
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let cs = [contact(1, [0.0, 0.0, 160.0], [0.0, bad, -1.0])];
            let m = calibrated(&header(), &cs, &g, &MarkerStyle::default(), false);
            assert_eq!(m.check_finite().unwrap_err().message, "contacts");
            let cs = [contact(1, [bad, 0.0, 160.0], [0.0, 0.0, -1.0])];
            assert!(
                calibrated(&header(), &cs, &g, &MarkerStyle::default(), false)
                    .check_finite()
                    .is_err()
            );
        }
        let style = MarkerStyle {
            sphere_m: f64::NAN,
            ..MarkerStyle::default()
        };
        let cs = [contact(1, [0.0, 0.0, 160.0], [0.0, 0.0, -1.0])];
        let m = calibrated(&header(), &cs, &g, &style, false);
        assert_eq!(m.check_finite().unwrap_err().message, "markers");
    }

    #[test]
    fn the_cloud_holds_every_contact_with_its_sigma_and_flags() {
        let g = SensorGeometry::default();
        let mut a = contact(3, [10.0, -2.0, 159.0], [0.1, 0.0, -1.0]);
        a.force_sigma_n = Some([0.01, 0.002, 0.04]);
        a.out_of_domain = true;
        let mut b = contact(u64::MAX, [-20.0, 4.0, 158.0], [0.0, 0.2, -0.5]);
        b.force_sigma_n = Some([0.02, 0.003, 0.05]);
        b.missed = 2;
        b.fallback = true;
        let m = calibrated(&header(), &[a, b], &g, &MarkerStyle::default(), true);
        m.check_finite().unwrap();
        let c = m.cloud.unwrap();
        assert_eq!(c.header, header());
        assert_eq!((c.height, c.width), (1, 2));
        assert_eq!(c.fields.len(), 13);
        assert_eq!(c.point_step, 9 * 8 + 2 * 4 + 2);
        assert_eq!(c.row_step, 2 * c.point_step);
        assert_eq!(c.data.len(), c.row_step as usize);
        // Offsets follow each other without a gap or an overlap.
        for w in c.fields.windows(2) {
            let size = PointField::size_of(w[0].datatype).unwrap();
            assert_eq!(
                w[1].offset,
                w[0].offset + size,
                "{} -> {}",
                w[0].name,
                w[1].name
            );
        }
        let v = |i, name| c.value(i, name, 0).unwrap();
        assert!((v(0, "x") - 0.010).abs() < 1e-15 && (v(1, "z") - 0.158).abs() < 1e-15);
        assert_eq!((v(0, "fz"), v(1, "fy")), (-1.0, 0.2));
        assert_eq!((v(0, "id"), v(1, "id")), (3.0, u32::MAX as f64));
        assert_eq!((v(0, "held_frames"), v(1, "held_frames")), (0.0, 2.0));
        assert_eq!((v(0, "out_of_domain"), v(1, "out_of_domain")), (1.0, 0.0));
        assert_eq!((v(0, "fallback"), v(1, "fallback")), (0.0, 1.0));
        assert_eq!((v(0, "fz_sigma"), v(1, "fx_sigma")), (0.04, 0.02));
        assert_eq!(c.value(2, "x", 0), None);
        assert_eq!(c.value(0, "torque", 0), None);

        // Without an uncertainty model: no sigma fields.
        let m = calibrated(&header(), &[a], &g, &MarkerStyle::default(), false);
        let c = m.cloud.unwrap();
        assert_eq!(c.fields.len(), 10);
        assert_eq!(c.value(0, "fx_sigma", 0), None);
        assert_eq!(c.value(0, "fz", 0), Some(-1.0));
        // No contact: an empty cloud with the same fields.
        let c = contact_cloud(&header(), &[], true);
        assert_eq!((c.width, c.data.len(), c.fields.len()), (0, 0, 13));
        // Raw frames have none.
        assert!(raw(&header(), &[]).cloud.is_none());
    }

    #[test]
    fn a_contact_without_a_finite_sigma_stops_the_frame() {
        let g = SensorGeometry::default();
        let mut a = contact(1, [0.0, 0.0, 160.0], [0.0, 0.0, -1.0]);
        for bad in [None, Some([0.01, f64::NAN, 0.02]), Some([f64::INFINITY; 3])] {
            a.force_sigma_n = bad;
            let m = calibrated(&header(), &[a], &g, &MarkerStyle::default(), true);
            assert_eq!(m.check_finite().unwrap_err().message, "contact cloud");
        }
    }

    #[test]
    fn raw_patches_keep_their_pixels() {
        let r = RawContact {
            x_px: 120.5,
            y_px: 30.0,
            ds1: 2.0,
            ds2: -1.0,
            dn: 40.0,
            ..RawContact::default()
        };
        let m = raw(&header(), &[r]);
        assert_eq!(m.contacts.contacts[0].name, "patch_0");
        assert_eq!(m.contacts.contacts[0].position.x, 120.5);
        assert_eq!(m.contacts.contacts[0].wrench.force.z, 40.0);
        assert!(m.wrench.is_none());
        assert_eq!(m.markers.markers.len(), 1);
        assert_eq!(contact_id("patch_0"), None);
    }

    #[test]
    fn marker_ids_wrap() {
        assert_eq!(marker_id(5), 5);
        assert_eq!(marker_id(i32::MAX as u64 + 1), 0);
    }
}
