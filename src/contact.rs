//! Contacts: the raw quantities of a contact patch (SPEC.md step 7) and the
//! calibrated contact a user acts on.

use serde::{Deserialize, Serialize};

use crate::image::Roi;
use crate::io::ContactRecord;

/// The raw, uncalibrated quantities of one contact patch (SPEC.md step 7), all
/// in the pixels of the cropped full-resolution image.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct RawContact {
    /// Contact point column: argmin of the divergence potential D.
    pub x_px: f64,
    /// Contact point row.
    pub y_px: f64,
    /// Shear raw displacement along image x: sum of the patch's flow u.
    pub ds1: f64,
    /// Shear raw displacement along image y: sum of the patch's flow v.
    pub ds2: f64,
    /// Normal raw displacement: sum of |d| (the curl-free part) over the patch.
    pub dn: f64,
    /// Spread of the divergence potential, `max D - min D`.
    pub d_pf: f64,
    /// Raw displacements rotated into the sensor frame `(Dx, Dy, Dz)`.
    pub d_sensor: [f64; 3],
    /// Number of pixels of the patch's mask (full-resolution pixels).
    pub area_px: u64,
    /// The patch's bounding box (full-resolution pixels of the cropped image).
    pub bbox: Roi,
    /// Summed flow magnitude of the patch: the detection strength.
    pub strength: f64,
}

/// One contact: where (mm) and how hard (N), in the sensor frame.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Contact {
    /// Identity, stable from frame to frame while the contact lasts (0 until tracked).
    pub id: u64,
    /// Location `(x, y, z)` in mm, sensor frame.
    pub location_mm: [f64; 3],
    /// Force `(Fx, Fy, Fz)` in N, sensor frame (a press has `Fz < 0`).
    pub force_n: [f64; 3],
    /// The raw quantities it was computed from.
    pub raw: RawContact,
    /// Frames in a row this contact has been held without a detection (hysteresis).
    pub missed: u32,
}

impl Contact {
    /// Magnitude of the force, N.
    pub fn force_magnitude(&self) -> f64 {
        let [x, y, z] = self.force_n;
        (x * x + y * y + z * z).sqrt()
    }

    /// The JSON Lines record of DATASET.md.
    pub fn to_record(&self) -> ContactRecord {
        let r = &self.raw;
        ContactRecord {
            id: Some(self.id),
            x_mm: self.location_mm[0],
            y_mm: self.location_mm[1],
            z_mm: self.location_mm[2],
            fx_n: self.force_n[0],
            fy_n: self.force_n[1],
            fz_n: self.force_n[2],
            x_px: Some(r.x_px),
            y_px: Some(r.y_px),
            d_pf: Some(r.d_pf),
            dx: Some(r.d_sensor[0]),
            dy: Some(r.d_sensor[1]),
            dz: Some(r.d_sensor[2]),
            area_px: Some(r.area_px),
        }
    }
}
