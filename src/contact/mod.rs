//! Contacts: the raw quantities of a contact patch (docs/pipeline.md, step 7) and the
//! calibrated contact a user acts on.

pub mod confidence;
pub mod profile;

use ndarray::ArrayView2;
use serde::{Deserialize, Serialize};

use crate::contact::profile::column_profile_into;
use crate::error::{Error, Result};
use crate::frame::Roi;
use crate::geometry::SensorGeometry;
use crate::io::{ContactRecord, RawContactRecord};

/// The raw, uncalibrated quantities of one contact patch (docs/pipeline.md, step 7), all
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
    /// The largest flow magnitude in the patch's box, full-resolution
    /// pixels. On a regular grid of markers, motion of half the grid's
    /// pitch or more cannot be told apart from a neighbouring marker's
    /// ([`crate::markers`]).
    #[serde(default)]
    pub peak_px: f64,
    /// Local force components (tangential, across, outward normal) matched
    /// from the frame's motion profile ([`crate::contact::profile::ForceMatcher`]),
    /// when the calibration has a profile model; they then replace the sums
    /// as the force maps' raw displacements ([`sensor_displacements`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub local_force: Option<[f64; 3]>,
    /// The tangential-to-inward-normal ratio `t / -n` of the contact's first
    /// profile match, before any correction: how tilted the load is along
    /// the strip. A column correction with tilt layers looks them up with it
    /// ([`crate::calibration::correction`]); `None` until such a match.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub matched_shear_ratio: Option<f64>,
    /// The residual ([`crate::markers::round::RoundFit::residual`]) of the
    /// round load's field fitted to the contact's dots, when `ds1`, `ds2`,
    /// `dn` and the point came from that fit
    /// ([`crate::sensor::ExtractorConfig::dot_fit`]); `None` when they did
    /// not (no fit asked for, or none that holds).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dot_fit_residual: Option<f64>,
}

impl RawContact {
    /// The JSON Lines record of a raw run (docs/formats.md).
    pub fn to_record(&self) -> RawContactRecord {
        let b = self.bbox;
        RawContactRecord {
            x_px: self.x_px,
            y_px: self.y_px,
            box_px: [b.x, b.y, b.w, b.h],
            strength: self.strength,
            ds1: self.ds1,
            ds2: self.ds2,
            dn: self.dn,
            d_pf: self.d_pf,
            area_px: self.area_px,
        }
    }

    /// The shear-to-normal ratio across, `ds2 / dn` (0 when `dn` is 0): on
    /// a sensor that locates in 2-D it corrects `y` as
    /// [`RawContact::shear_ratio`] corrects `x`.
    pub fn shear_ratio_y(&self) -> f64 {
        if self.dn > 0.0 && self.ds2.is_finite() {
            self.ds2 / self.dn
        } else {
            0.0
        }
    }

    /// The local shear-to-normal ratio `ds1 / dn` (0 when `dn` is 0): how much
    /// of the load runs along the arc. It tells how far the contact point
    /// estimate is pulled sideways, so the location map takes it as an input.
    pub fn shear_ratio(&self) -> f64 {
        if self.dn > 0.0 && self.ds1.is_finite() {
            self.ds1 / self.dn
        } else {
            0.0
        }
    }
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
    /// Standard deviation of the force's error per axis, N, sensor frame,
    /// from the calibration's
    /// [`ForceUncertainty`](crate::calibration::uncertainty::ForceUncertainty):
    /// about 68% of contacts like the characterization's lie within one
    /// sigma of the true force. `None` when the calibration has no
    /// uncertainty model. It is the calibration's error spread, mostly tied
    /// to the place and the load, so it does not shrink over frames.
    #[serde(default)]
    pub force_sigma_n: Option<[f64; 3]>,
    /// The raw quantities it was computed from.
    pub raw: RawContact,
    /// Frames in a row this contact has been held without a detection (hysteresis).
    pub missed: u32,
    /// Whether the force came from the calibration's low-order fallback maps
    /// because the full maps were not trusted for these inputs
    /// ([`crate::calibration::ForceGuard`]): a contact unlike any of the
    /// training data; its force is the robust estimate, not the finest.
    #[serde(default)]
    pub fallback: bool,
    /// Whether the contact lies outside what its calibration knows: force
    /// inputs outside the box of the training data or a load beyond the
    /// strongest the characterization pressed at that place (beyond the
    /// guard's margin, [`crate::calibration::GUARD_BOX_MARGIN`];
    /// [`crate::calibration::ForceGuard::knows`]), a location off
    /// the sensor's surface ([`crate::geometry::SensorGeometry::contains`]),
    /// or motion beyond what the markers can tell
    /// ([`crate::sensor::ContactExtractor::beyond_markers`]): on a regular
    /// grid of markers, half the grid's pitch or more, where a marker cannot
    /// be told from its neighbour; on random markers, a torn flow (the gel
    /// stretched by a flow patch's side across one patch).
    /// Its location and force are extrapolations: use them with care (a
    /// calibration from another sensor, a crop that is not the calibration's,
    /// a press far stronger than any in the characterization).
    #[serde(default)]
    pub out_of_domain: bool,
}

impl Contact {
    /// Magnitude of the force, N.
    pub fn force_magnitude(&self) -> f64 {
        let [x, y, z] = self.force_n;
        (x * x + y * y + z * z).sqrt()
    }

    /// Whether its location, force and force sigma (if any) are finite
    /// numbers (the sensor never reports a contact that is not).
    pub fn is_finite(&self) -> bool {
        self.location_mm
            .iter()
            .chain(&self.force_n)
            .chain(self.force_sigma_n.iter().flatten())
            .all(|v| v.is_finite())
    }

    /// The JSON Lines record of docs/formats.md.
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
            fallback: Some(self.fallback),
            out_of_domain: Some(self.out_of_domain),
            missed: Some(self.missed),
            fx_sigma_n: self.force_sigma_n.map(|s| s[0]),
            fy_sigma_n: self.force_sigma_n.map(|s| s[1]),
            fz_sigma_n: self.force_sigma_n.map(|s| s[2]),
        }
    }
}

/// Where a patch sits and how its grid relates to the full-resolution image.
///
/// The flow may be computed on a coarser grid than the image (DIS estimates it
/// at a pyramid level, 1/4 resolution for the `fast` preset): grid cell `(i, j)`
/// of the patch covers full-resolution pixels around
/// `((x0 + j + 0.5) * scale - 0.5, (y0 + i + 0.5) * scale - 0.5)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PatchGrid {
    /// Column of the patch's first cell in the (level) grid.
    pub x0: usize,
    /// Row of the patch's first cell in the (level) grid.
    pub y0: usize,
    /// Full-resolution pixels per grid cell (1 at full resolution, 4 at level 2).
    pub scale: f64,
}

/// The decomposition fields [`raw_quantities`] needs, for one patch.
#[derive(Debug, Clone, Copy)]
pub struct PatchFields<'a> {
    /// Flow along x in full-resolution pixels, shape `(h, w)`.
    pub u: ArrayView2<'a, f32>,
    /// Flow along y in full-resolution pixels.
    pub v: ArrayView2<'a, f32>,
    /// Divergence potential `D`, computed with grid spacing `scale`.
    pub potential_d: ArrayView2<'a, f64>,
    /// Curl-free part `d = grad D`, x component.
    pub d_u: ArrayView2<'a, f64>,
    /// Curl-free part, y component.
    pub d_v: ArrayView2<'a, f64>,
}

/// Sub-pixel offset of a minimum from three samples `a, b, c` at -1, 0, +1
/// (vertex of the parabola through them, within +-0.5).
fn parabola_offset(a: f64, b: f64, c: f64) -> f64 {
    let den = a - 2.0 * b + c;
    if den > 0.0 && den.is_finite() {
        (0.5 * (a - c) / den).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// The raw quantities of one patch (docs/pipeline.md, step 7), in full-resolution units.
///
/// - contact point: argmin of `D` (first in row-major order on ties),
///   optionally refined to sub-pixel precision by a parabola through the
///   neighbours along each axis (interior minima only);
/// - `ds1, ds2`: sums of `u` and `v`, times `scale^2` so that they equal the sums
///   over the patch at full resolution;
/// - `dn`: sum of `|d|`, times `scale^2`;
/// - `d_pf`: `max D - min D` (already in full-resolution units when the
///   decomposition used spacing `scale`);
/// - `peak_px`: the largest `|(u, v)|`.
///
/// `area_px`, `bbox` and `strength` are left for the caller (the segmentation
/// knows them). Errors on mismatched shapes or an empty patch.
pub fn raw_quantities(f: &PatchFields<'_>, grid: PatchGrid, subpixel: bool) -> Result<RawContact> {
    let (h, w) = patch_shape(f)?;
    let d = &f.potential_d;
    // One pass over the five fields: the minimum and maximum of D, the
    // largest |(u, v)| and the three sums, each in row-major order as the
    // plain twin (in the tests) takes them one field at a time, so the same
    // values bit for bit; side by side, the five chains of dependent
    // operations overlap. Each sum starts where `Iterator::sum` starts.
    let zero: f64 = std::iter::empty::<f64>().sum();
    let (mut best, mut lo, mut hi) = ((0, 0), f64::INFINITY, f64::NEG_INFINITY);
    let (mut su, mut sv, mut dn) = (zero, zero, zero);
    // The largest squared |(u, v)|: one square root at the end.
    let mut peak2 = 0.0f32;
    for i in 0..h {
        let rows = (d.row(i), f.u.row(i), f.v.row(i), f.d_u.row(i), f.d_v.row(i));
        let slices = (
            rows.0.as_slice(),
            rows.1.as_slice(),
            rows.2.as_slice(),
            rows.3.as_slice(),
            rows.4.as_slice(),
        );
        if let (Some(dr), Some(ur), Some(vr), Some(dur), Some(dvr)) = slices {
            for j in 0..w {
                let x = dr[j];
                if x < lo {
                    lo = x;
                    best = (i, j);
                }
                hi = hi.max(x);
                su += ur[j] as f64;
                sv += vr[j] as f64;
                peak2 = peak2.max(ur[j] * ur[j] + vr[j] * vr[j]);
                let (a, b) = (dur[j], dvr[j]);
                // |d| as sqrt(a^2 + b^2): within an ulp of `hypot`, which
                // guards against overflow that displacements of a few
                // pixels never reach, at several times the cost.
                dn += (a * a + b * b).sqrt();
            }
        } else {
            let (dr, ur, vr, dur, dvr) = rows;
            for j in 0..w {
                let x = dr[j];
                if x < lo {
                    lo = x;
                    best = (i, j);
                }
                hi = hi.max(x);
                su += ur[j] as f64;
                sv += vr[j] as f64;
                peak2 = peak2.max(ur[j] * ur[j] + vr[j] * vr[j]);
                let (a, b) = (dur[j], dvr[j]);
                dn += (a * a + b * b).sqrt();
            }
        }
    }
    let (x_px, y_px) = minimum_point(d, best, (lo, hi), grid, subpixel)?;
    let area = grid.scale * grid.scale;
    Ok(RawContact {
        peak_px: f64::from(peak2.sqrt()),
        x_px,
        y_px,
        ds1: su * area,
        ds2: sv * area,
        dn: dn * area,
        d_pf: hi - lo,
        ..Default::default()
    })
}

/// The common shape `(h, w)` of a patch's fields; errors on mismatched
/// shapes or an empty patch.
fn patch_shape(f: &PatchFields<'_>) -> Result<(usize, usize)> {
    let shape = f.u.dim();
    for (what, dim) in [
        ("v", f.v.dim()),
        ("D", f.potential_d.dim()),
        ("d.u", f.d_u.dim()),
        ("d.v", f.d_v.dim()),
    ] {
        if dim != shape {
            return Err(Error::shape(
                format!("patch field {what} against u"),
                (shape.1, shape.0),
                (dim.1, dim.0),
            ));
        }
    }
    let (h, w) = shape;
    if h == 0 || w == 0 {
        return Err(Error::TooSmall {
            what: "contact patch".into(),
            width: w,
            height: h,
            min_w: 1,
            min_h: 1,
        });
    }
    Ok((h, w))
}

/// The contact point, full-resolution pixels, of the minimum of `d` at cell
/// `best` (refined to sub-pixel by a parabola through its neighbours along
/// each axis when `subpixel`, interior minima only), given D's extremes
/// `(lo, hi)`: an error if they are not finite.
fn minimum_point(
    d: &ArrayView2<'_, f64>,
    best: (usize, usize),
    (lo, hi): (f64, f64),
    grid: PatchGrid,
    subpixel: bool,
) -> Result<(f64, f64)> {
    if !(lo.is_finite() && hi.is_finite()) {
        return Err(Error::NonFinite {
            what: "divergence potential".into(),
            row: best.0,
            col: best.1,
        });
    }
    let (h, w) = d.dim();
    let (i, j) = best;
    let (mut oi, mut oj) = (0.0, 0.0);
    if subpixel {
        if i > 0 && i + 1 < h {
            oi = parabola_offset(d[[i - 1, j]], d[[i, j]], d[[i + 1, j]]);
        }
        if j > 0 && j + 1 < w {
            oj = parabola_offset(d[[i, j - 1]], d[[i, j]], d[[i, j + 1]]);
        }
    }
    let s = grid.scale;
    Ok((
        (grid.x0 as f64 + j as f64 + oj + 0.5) * s - 0.5,
        (grid.y0 as f64 + i as f64 + oi + 0.5) * s - 0.5,
    ))
}

/// Mean-shift centroid of `w` (non-negative weights per grid column) with a
/// hard window of half-width `half` columns, restricted to `[lo, hi)`,
/// starting from the centroid of the whole range. `None` if the weights in
/// the range are all zero.
fn windowed_centroid(w: &[f64], lo: usize, hi: usize, half: f64) -> Option<f64> {
    let centroid = |a: f64, b: f64| {
        let (mut s, mut sx) = (0.0, 0.0);
        for (j, &x) in w.iter().enumerate().take(hi).skip(lo) {
            let jf = j as f64;
            if jf > a && jf < b {
                s += x;
                sx += x * jf;
            }
        }
        (s > 0.0).then(|| sx / s)
    };
    let mut c = centroid(f64::NEG_INFINITY, f64::INFINITY)?;
    // A mean shift with a flat kernel converges in a few steps; a fixed cap
    // keeps the cost bounded when it oscillates between two nearby modes.
    // The window stays symmetric about the estimate: where the region ends
    // (an image edge, or halfway to a neighbouring contact) it shrinks on
    // both sides, since cutting one side only would pull the centroid of a
    // symmetric profile away from the cut.
    let (first, last) = (lo as f64 - 0.5, hi as f64 - 0.5);
    for _ in 0..50 {
        let h = half.min(c - first).min(last - c).max(1.0);
        let next = match centroid(c - h, c + h) {
            Some(n) => n,
            None => break,
        };
        let done = (next - c).abs() < 1e-6;
        c = next;
        if done {
            break;
        }
    }
    Some(c)
}

/// Replaces each contact's column `x_px` by a shear-robust estimate: the
/// centroid of the squared column-summed flow `u` (motion along the arc)
/// within a window of half-width `half_window_px` full-resolution pixels.
///
/// Why: under a line load, the surface motion along the arc is odd about the
/// load point for the normal component and even for the tangential one, so
/// the divergence potential (the integral of the motion) is even plus odd and
/// its minimum slides sideways as soon as the load has any shear (tens of
/// pixels at 15 deg). The energy of the motion, `u^2`, is even about the load
/// point under either load alone, and its centroid moves far less; what
/// remains is corrected by the calibration's `shear` input (see
/// [`RawContact::shear_ratio`]). Column sums over the whole strip height
/// average the noise, and the window keeps a distant contact (or noise far
/// away) out of the centroid.
///
/// `u` is the flow along x on a grid of `scale` full-resolution pixels per
/// cell (cell `j` covers pixel `(j + 0.5) * scale - 0.5`). With several
/// contacts, each one's search range ends halfway to its neighbours' current
/// `x_px`, so that one press does not pull another's centroid. A contact whose
/// range holds no motion keeps its `x_px`. Errors on a non-positive or
/// non-finite window or scale.
pub fn refine_contact_points(
    raws: &mut [RawContact],
    u: ArrayView2<'_, f32>,
    scale: f64,
    half_window_px: f64,
) -> Result<()> {
    ContactLocator::new().refine(
        ContactPointMethod::EnergyCentroid { half_window_px },
        raws,
        u,
        u,
        scale,
    )
}

/// How a contact's column (`x_px`, along the arc) is measured.
///
/// The segmentation gives each contact the argmin of its divergence
/// potential; the other two methods replace it from the frame's flow along
/// the arc, summed over the strip's height into a profile.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "method")]
pub enum ContactPointMethod {
    /// The argmin of the patch's divergence potential D (the paper's method).
    /// Slides sideways under shear: the potential integrates the motion.
    PotentialMinimum,
    /// The mean-shift centroid of the squared profile within a flat window
    /// ([`refine_contact_points`]). Robust to shear, but a close neighbour
    /// cancels part of the motion between two contacts and pulls it outward.
    EnergyCentroid {
        /// Half-width of the window, full-resolution pixels.
        half_window_px: f64,
    },
    /// The steepest rise of the Gaussian-smoothed profile
    /// ([`slope_peak_contact_points`]): a press spreads the markers apart
    /// along the arc, and that spreading (the one-dimensional divergence of
    /// the width-integrated flow) peaks at the load line. Local, so a
    /// neighbour's slowly varying tail hardly moves it.
    SlopePeak {
        /// Standard deviation of the smoothing, full-resolution pixels.
        sigma_px: f64,
    },
    /// The slope peak in both image axes, for sensors that locate contacts
    /// in 2-D (a flat fingertip's round contacts): the column from the flow
    /// along x summed over the rows of the contact's band (its box widened
    /// by 3 sigma), then the row from the flow along y summed over the
    /// columns of its band. Each search stops halfway to the contacts whose
    /// bands across overlap this one's. A contact without a box (zero
    /// width or height) takes the whole image as its band.
    #[serde(rename = "slope_peak_2d")]
    SlopePeak2d {
        /// Standard deviation of the smoothing, full-resolution pixels.
        sigma_px: f64,
    },
    /// Where a normal press's dots point: the point the lines along the
    /// followed dots' motion meet ([`crate::markers::centre`]), found
    /// about each contact's 2-D slope peak
    /// ([`ContactPointMethod::SlopePeak2d`] with the same smoothing). The
    /// slope peak stands where no dots are followed (random markers, dot
    /// tracking off) and where the dots' lines do not meet within a pitch
    /// of it. The extractor ([`crate::sensor::ContactExtractor::locate`])
    /// holds the dots; [`ContactLocator`] alone gives the slope peak.
    MotionLines {
        /// Standard deviation of the slope peak's smoothing, full-resolution
        /// pixels.
        sigma_px: f64,
    },
}

/// Largest smoothing of [`ContactPointMethod::SlopePeak`], full-resolution
/// pixels: 256 (the default is 8; the Gaussian reaches 3 sigma each side, so
/// 256 px already spans 1536 px, about a whole 1600-px strip).
pub const MAX_SLOPE_SIGMA_PX: f64 = 256.0;

/// Largest half-window of [`ContactPointMethod::EnergyCentroid`],
/// full-resolution pixels: the largest frame side,
/// [`crate::frame::MAX_FRAME_SIDE`] (the default is 400).
pub const MAX_CENTROID_HALF_WINDOW_PX: f64 = crate::frame::MAX_FRAME_SIDE as f64;

impl ContactPointMethod {
    /// The default for new calibrations: [`ContactPointMethod::SlopePeak`]
    /// with 8 px of smoothing (on the simulator's protocol it locates
    /// contacts to about 0.25 mm, against 0.65 mm for the energy centroid).
    pub const DEFAULT: Self = Self::SlopePeak { sigma_px: 8.0 };

    /// [`ContactPointMethod::MotionLines`] about the 2-D slope peak of
    /// 16 px: the method of sensors that locate in 2-D
    /// ([`ContactPointMethod::for_geometry`]) and of raw patches where dots
    /// are followed ([`ContactPointMethod::uncalibrated`]).
    pub const MOTION_LINES: Self = Self::MotionLines { sigma_px: 16.0 };

    /// The default for new calibrations of a sensor of `geometry`:
    /// [`ContactPointMethod::DEFAULT`] on the curved strip,
    /// [`ContactPointMethod::MotionLines`] about the 2-D slope peak with
    /// 16 px of smoothing on a sensor that locates contacts in 2-D (without
    /// followed dots, the 2-D slope peak itself). Why 16: such sensors
    /// often carry a sparse grid of dots, and the flow between the dots is
    /// interpolated; a smoothing of about 0.7 dot pitch averages the grid's
    /// phase out. On the simulated fingertip sensor (dots every 22 px, 150
    /// random presses) the raw contact point was 5.9 / 5.2 px off (x / y)
    /// with 8 px, 3.0 / 3.4 px with 16 px and 3.7 / 4.1 px with 24 px. Why
    /// the dots' lines: a light contact moves the few dots about it, and the
    /// slope peak between them falls towards a row of dots (docs/results.md,
    /// "A flat fingertip sensor").
    pub fn for_geometry(geometry: &SensorGeometry) -> Self {
        if geometry.locates_in_2d() {
            Self::MOTION_LINES
        } else {
            Self::DEFAULT
        }
    }

    /// The method for patches measured without a calibration
    /// ([`crate::sensor::RawSensor`], `track --raw`): where the dots of a
    /// regular grid are followed, [`ContactPointMethod::MotionLines`] about
    /// the 2-D slope peak of 16 px (the row as well as the column, where the
    /// dots point); otherwise [`ContactPointMethod::DEFAULT`], the column
    /// as the strip's calibration measures it.
    pub fn uncalibrated(dots_followed: bool) -> Self {
        if dots_followed {
            Self::MOTION_LINES
        } else {
            Self::DEFAULT
        }
    }

    /// Errors ([`Error::InvalidParameter`]) unless the method's parameter is
    /// finite, positive and at most its bound ([`MAX_SLOPE_SIGMA_PX`],
    /// [`MAX_CENTROID_HALF_WINDOW_PX`]).
    pub fn validate(&self) -> Result<()> {
        let (name, x, max) = match *self {
            ContactPointMethod::PotentialMinimum => return Ok(()),
            ContactPointMethod::EnergyCentroid { half_window_px } => (
                "half_window_px",
                half_window_px,
                MAX_CENTROID_HALF_WINDOW_PX,
            ),
            ContactPointMethod::SlopePeak { sigma_px }
            | ContactPointMethod::SlopePeak2d { sigma_px }
            | ContactPointMethod::MotionLines { sigma_px } => {
                ("sigma_px", sigma_px, MAX_SLOPE_SIGMA_PX)
            }
        };
        if x > 0.0 && x <= max {
            Ok(())
        } else {
            Err(Error::param(
                name,
                format!("must be > 0 and at most {max} px, got {x:?}"),
            ))
        }
    }
}

impl Default for ContactPointMethod {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Measures contact columns by a [`ContactPointMethod`], keeping its
/// profile buffers from frame to frame so that a sensor allocates nothing
/// per frame in steady state.
#[derive(Debug, Default, Clone)]
pub struct ContactLocator {
    profile: Vec<f64>,
    slope: Vec<f64>,
    smooth: Vec<f64>,
    kernel: Vec<f64>,
    starts: Vec<f64>,
}

impl ContactLocator {
    /// An empty locator (buffers grow on first use).
    pub fn new() -> Self {
        Self::default()
    }

    /// Replaces each contact's `x_px` (and, for
    /// [`ContactPointMethod::SlopePeak2d`], its `y_px`) as `method` says,
    /// from the frame's flow (`u` along x, `v` along y, on a grid of `scale`
    /// full-resolution pixels per cell).
    /// [`ContactPointMethod::PotentialMinimum`] leaves the contacts as they
    /// are. Errors on a non-positive or non-finite scale, `u` and `v` of
    /// different shapes, or a method parameter out of its range
    /// ([`ContactPointMethod::validate`]).
    pub fn refine(
        &mut self,
        method: ContactPointMethod,
        raws: &mut [RawContact],
        u: ArrayView2<'_, f32>,
        v: ArrayView2<'_, f32>,
        scale: f64,
    ) -> Result<()> {
        method.validate()?;
        if u.dim() != v.dim() {
            return Err(Error::shape(
                "flow v against u",
                (u.ncols(), u.nrows()),
                (v.ncols(), v.nrows()),
            ));
        }
        match method {
            ContactPointMethod::PotentialMinimum => Ok(()),
            ContactPointMethod::EnergyCentroid { half_window_px } => {
                check_positive("scale", scale)?;
                if raws.is_empty() || u.ncols() == 0 {
                    return Ok(());
                }
                column_profile_into(u, 1.0, &mut self.profile);
                for x in &mut self.profile {
                    *x *= *x;
                }
                self.starts.clear();
                self.starts
                    .extend(raws.iter().map(|r| to_grid(r.x_px, scale)));
                let n = self.profile.len();
                for (k, raw) in raws.iter_mut().enumerate() {
                    let Some((lo, hi)) = neighbour_range(&self.starts, k, 0, n) else {
                        continue;
                    };
                    if let Some(c) =
                        windowed_centroid(&self.profile, lo, hi, half_window_px / scale)
                    {
                        raw.x_px = from_grid(c, scale);
                    }
                }
                Ok(())
            }
            ContactPointMethod::SlopePeak { sigma_px } => {
                check_positive("scale", scale)?;
                self.slope_peak(raws, u, scale, sigma_px);
                Ok(())
            }
            ContactPointMethod::SlopePeak2d { sigma_px }
            | ContactPointMethod::MotionLines { sigma_px } => {
                check_positive("scale", scale)?;
                self.slope_peak_2d(raws, u, v, scale, sigma_px);
                Ok(())
            }
        }
    }

    fn slope_peak(
        &mut self,
        raws: &mut [RawContact],
        u: ArrayView2<'_, f32>,
        scale: f64,
        sigma_px: f64,
    ) {
        if raws.is_empty() || u.ncols() < 3 {
            return;
        }
        column_profile_into(u, 1.0, &mut self.profile);
        self.starts.clear();
        self.starts
            .extend(raws.iter().map(|r| to_grid(r.x_px, scale)));
        self.peaks_of_profile(sigma_px / scale, f64::INFINITY, |k, c| {
            raws[k].x_px = from_grid(c, scale);
        });
    }

    /// [`ContactPointMethod::SlopePeak`] on a given along-arc profile
    /// (`profile`, cells of `scale` full-resolution pixels, any units):
    /// each column of `columns_px` moves to the steepest rise of the
    /// profile within `window_px` of it and short of halfway to the others;
    /// a column whose range has no rising slope stays. Used on a profile
    /// less the contacts' modelled tangential motion
    /// ([`crate::contact::profile::ForceMatcher::shear_free_columns`]).
    pub fn slope_peak_in_profile(
        &mut self,
        profile: &[f64],
        columns_px: &mut [f64],
        scale: f64,
        sigma_px: f64,
        window_px: f64,
    ) {
        if columns_px.is_empty() || profile.len() < 3 || !(scale > 0.0 && sigma_px > 0.0) {
            return;
        }
        self.profile.clear();
        self.profile.extend_from_slice(profile);
        self.starts.clear();
        self.starts
            .extend(columns_px.iter().map(|&x| to_grid(x, scale)));
        self.peaks_of_profile(sigma_px / scale, window_px / scale, |k, c| {
            columns_px[k] = from_grid(c, scale);
        });
    }

    /// The slope peak of the loaded profile (smoothing `sigma` cells) for
    /// each start of `self.starts` (cells), within `window` cells of it and
    /// short of halfway to the other starts, handed to `found(k, cell)`; a
    /// start without a rising slope in its range gets nothing.
    fn peaks_of_profile(&mut self, sigma: f64, window: f64, mut found: impl FnMut(usize, f64)) {
        let n = self.profile.len();
        self.smooth_slope(sigma);
        for (k, &me) in self.starts.iter().enumerate() {
            // The search stops short of halfway to the neighbouring
            // contacts. It is not cut to the patch's box: a weak press's box
            // is narrower than its motion and, on the simulator's protocol,
            // cutting there cost 0.36 against 0.24 mm.
            let Some((mut lo, mut hi)) = neighbour_range(&self.starts, k, 0, n) else {
                continue;
            };
            if window.is_finite() {
                lo = lo.max((me - window).ceil().max(0.0) as usize);
                hi = hi.min(((me + window).floor() + 1.0).max(0.0) as usize);
                if lo >= hi {
                    continue;
                }
            }
            if let Some(c) = rising_peak(&self.smooth, lo, hi) {
                found(k, c);
            }
        }
    }

    /// [`ContactPointMethod::SlopePeak2d`]: per contact, the slope peak of
    /// `u` summed over the rows of its band along x, then that of `v`
    /// summed over the columns of its band along y.
    fn slope_peak_2d(
        &mut self,
        raws: &mut [RawContact],
        u: ArrayView2<'_, f32>,
        v: ArrayView2<'_, f32>,
        scale: f64,
        sigma_px: f64,
    ) {
        let (h, w) = u.dim();
        if raws.is_empty() || w < 3 || h < 3 {
            return;
        }
        let pad = 3.0 * sigma_px;
        let bands: Vec<[(usize, usize); 2]> = raws
            .iter()
            .map(|r| {
                let b = r.bbox;
                let band = |start: usize, len: usize, cells: usize| {
                    if len == 0 {
                        return (0, cells);
                    }
                    let lo = to_grid(start as f64 - pad, scale).floor().max(0.0) as usize;
                    let hi = to_grid((start + len) as f64 + pad, scale).ceil().max(0.0) as usize;
                    (lo.min(cells), hi.min(cells).max(lo.min(cells)))
                };
                [band(b.x, b.w, w), band(b.y, b.h, h)]
            })
            .collect();
        let overlap = |a: (usize, usize), b: (usize, usize)| a.0 < b.1 && b.0 < a.1;
        let at: Vec<[f64; 2]> = raws
            .iter()
            .map(|r| [to_grid(r.x_px, scale), to_grid(r.y_px, scale)])
            .collect();
        for (k, raw) in raws.iter_mut().enumerate() {
            for axis in 0..2 {
                // Along x: u summed over the rows of the band across (axis
                // 1); along y: v summed over the columns of the band along x.
                let (across, n) = (bands[k][1 - axis], if axis == 0 { w } else { h });
                if across.0 >= across.1 {
                    continue;
                }
                self.profile.clear();
                self.profile.resize(n, 0.0);
                if axis == 0 {
                    for i in across.0..across.1 {
                        for (o, &x) in self.profile.iter_mut().zip(u.row(i)) {
                            *o += f64::from(x);
                        }
                    }
                } else {
                    for (o, row) in self.profile.iter_mut().zip(v.rows()) {
                        *o = row
                            .iter()
                            .take(across.1)
                            .skip(across.0)
                            .map(|&x| f64::from(x))
                            .sum();
                    }
                }
                self.smooth_slope(sigma_px / scale);
                // Neighbours: the contacts whose bands across overlap this one's.
                self.starts.clear();
                self.starts.push(at[k][axis]);
                self.starts.extend(
                    (0..at.len())
                        .filter(|&m| m != k && overlap(bands[m][1 - axis], across))
                        .map(|m| at[m][axis]),
                );
                let Some((lo, hi)) = neighbour_range(&self.starts, 0, 0, n) else {
                    continue;
                };
                if let Some(c) = rising_peak(&self.smooth, lo, hi) {
                    let px = from_grid(c, scale);
                    if axis == 0 {
                        raw.x_px = px;
                    } else {
                        raw.y_px = px;
                    }
                }
            }
        }
    }

    /// Central differences of `self.profile` (one-sided at the ends) into
    /// `self.slope`, smoothed by a Gaussian of `sigma` cells into
    /// `self.smooth`: truncated at 3 sigma and renormalised where the
    /// profile ends, so that an edge does not drag the slope to zero.
    fn smooth_slope(&mut self, sigma: f64) {
        let p = &self.profile;
        let n = p.len();
        self.slope.clear();
        self.slope.extend((0..n).map(|j| {
            let (a, b) = (j.saturating_sub(1), (j + 1).min(n - 1));
            (p[b] - p[a]) / (b - a) as f64
        }));
        // No sample lies further than the profile's length away, whatever
        // the scale: the kernel need not reach further.
        let radius = (3.0 * sigma).ceil().min(n as f64) as usize;
        self.kernel.clear();
        self.kernel.extend((0..=radius).map(|k| {
            let t = k as f64 / sigma;
            (-0.5 * t * t).exp()
        }));
        self.smooth.clear();
        for j in 0..n {
            let (lo, hi) = (j.saturating_sub(radius), (j + radius).min(n - 1));
            let (mut s, mut w) = (0.0, 0.0);
            for (i, &x) in self.slope.iter().enumerate().take(hi + 1).skip(lo) {
                let g = self.kernel[i.abs_diff(j)];
                s += g * x;
                w += g;
            }
            self.smooth.push(s / w);
        }
    }
}

/// The cell of the largest positive value of `s` in `[lo, hi)`, refined by a
/// parabola through its neighbours; `None` when nothing in range rises.
fn rising_peak(s: &[f64], lo: usize, hi: usize) -> Option<f64> {
    let n = s.len();
    let mut best = lo;
    for j in lo..hi {
        if s[j] > s[best] {
            best = j;
        }
    }
    if s[best] <= 0.0 {
        return None; // no spreading in range: keep the estimate
    }
    let mut off = 0.0;
    if best > 0 && best + 1 < n {
        // A maximum: the vertex of the negated samples' minimum.
        off = parabola_offset(-s[best - 1], -s[best], -s[best + 1]);
    }
    Some(best as f64 + off)
}

fn check_positive(name: &str, x: f64) -> Result<()> {
    if x > 0.0 && x.is_finite() {
        Ok(())
    } else {
        Err(Error::param(name, format!("must be > 0, got {x}")))
    }
}

/// Full-resolution pixel -> flow-grid cell (cell `j` covers pixel `(j + 0.5) * scale - 0.5`).
fn to_grid(px: f64, scale: f64) -> f64 {
    (px + 0.5) / scale - 0.5
}

/// Flow-grid cell -> full-resolution pixel.
fn from_grid(cell: f64, scale: f64) -> f64 {
    (cell + 0.5) * scale - 0.5
}

/// The cells `[lo, hi)` within `[lo0, hi0)` that lie strictly closer to
/// contact `k`'s start than halfway to any other start (ties broken by
/// index), or `None` if that is empty.
fn neighbour_range(starts: &[f64], k: usize, lo0: usize, hi0: usize) -> Option<(usize, usize)> {
    let me = starts[k];
    let (mut a, mut b) = (f64::NEG_INFINITY, f64::INFINITY);
    for (m, &o) in starts.iter().enumerate() {
        if m == k {
            continue;
        }
        let mid = 0.5 * (me + o);
        if o < me || (o == me && m < k) {
            a = a.max(mid);
        } else {
            b = b.min(mid);
        }
    }
    let lo = if a.is_finite() {
        ((a.floor().max(-1.0) + 1.0) as usize).max(lo0)
    } else {
        lo0
    };
    let hi = if b.is_finite() {
        (b.ceil().max(0.0) as usize).min(hi0)
    } else {
        hi0
    };
    (lo < hi).then_some((lo, hi))
}

/// Replaces each contact's column by the steepest rise of the frame's
/// along-arc profile near it ([`ContactPointMethod::SlopePeak`]).
///
/// The profile is the flow along x (`u`, a grid of `scale` full-resolution
/// pixels per cell) summed over all rows; its derivative is smoothed by a
/// Gaussian of standard deviation `sigma_px` full-resolution pixels, and each
/// contact takes the argmax of that slope (refined by a parabola) short of
/// halfway to the other contacts' current `x_px`. Why: a press spreads the markers apart along
/// the arc, so the slope peaks at the load line; a tangential load adds an
/// even bump whose slope is zero there, and a neighbour adds a slowly
/// varying tail, so neither moves the peak much, unlike the argmin of the
/// potential (which integrates the motion) or the energy centroid (which a
/// neighbour's cancelling lobe pulls). A contact whose range has no rising
/// slope keeps its `x_px`. Errors on a non-positive or non-finite `scale` or
/// `sigma_px`. Allocates its buffers; a sensor keeps a [`ContactLocator`].
pub fn slope_peak_contact_points(
    raws: &mut [RawContact],
    u: ArrayView2<'_, f32>,
    scale: f64,
    sigma_px: f64,
) -> Result<()> {
    ContactLocator::new().refine(
        ContactPointMethod::SlopePeak { sigma_px },
        raws,
        u,
        u,
        scale,
    )
}

/// The raw displacements the force maps take, in the sensor frame, for a
/// contact at chord position `x_mm`: the profile-matched local force
/// ([`RawContact::local_force`]) when there is one, else the sums
/// ([`rotate_to_sensor`]).
pub fn sensor_displacements(geometry: &SensorGeometry, x_mm: f64, raw: &RawContact) -> [f64; 3] {
    match raw.local_force {
        Some(f) => geometry.local_to_sensor(x_mm, f),
        None => rotate_to_sensor(geometry, x_mm, raw),
    }
}

/// Rotates a patch's raw displacements from the local surface frame at chord
/// position `x_mm` into the sensor frame (docs/pipeline.md, step 9).
///
/// Locally, `ds1` runs along the tangent (image x follows the arc), `ds2`
/// across (image y follows the width) and the normal component is `-dn`: the
/// markers are pushed into the skin by a press, so `Dz < 0` for a press at
/// the centre, like `Fz`.
pub fn rotate_to_sensor(geometry: &SensorGeometry, x_mm: f64, raw: &RawContact) -> [f64; 3] {
    geometry.local_to_sensor(x_mm, [raw.ds1, raw.ds2, -raw.dn])
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn a_contact_is_finite_only_with_a_finite_location_force_and_sigma() {
        let mut c = Contact {
            location_mm: [1.0, 0.0, 160.0],
            force_n: [0.0, 0.0, -1.0],
            ..Contact::default()
        };
        assert!(c.is_finite());
        c.force_sigma_n = Some([0.01, 0.002, 0.04]);
        assert!(c.is_finite());
        c.force_sigma_n = Some([0.01, f64::NAN, 0.04]);
        assert!(!c.is_finite());
        c.force_sigma_n = None;
        c.force_n[1] = f64::INFINITY;
        assert!(!c.is_finite());
        c.force_n[1] = 0.0;
        c.location_mm[2] = f64::NAN;
        assert!(!c.is_finite());
    }

    /// The plain twin of [`raw_quantities`]: one field at a time.
    fn raw_quantities_plain(
        f: &PatchFields<'_>,
        grid: PatchGrid,
        subpixel: bool,
    ) -> Result<RawContact> {
        patch_shape(f)?;
        let d = &f.potential_d;
        let (mut best, mut lo, mut hi) = ((0, 0), f64::INFINITY, f64::NEG_INFINITY);
        for ((i, j), &x) in d.indexed_iter() {
            if x < lo {
                lo = x;
                best = (i, j);
            }
            hi = hi.max(x);
        }
        let (x_px, y_px) = minimum_point(d, best, (lo, hi), grid, subpixel)?;
        let area = grid.scale * grid.scale;
        let sum = |a: &ArrayView2<'_, f32>| a.iter().map(|&x| x as f64).sum::<f64>() * area;
        // |d| as sqrt(a^2 + b^2): within an ulp of `hypot`, which guards
        // against overflow that displacements of a few pixels never reach, at
        // several times the cost.
        let dn = f
            .d_u
            .iter()
            .zip(f.d_v.iter())
            .map(|(a, b)| (a * a + b * b).sqrt())
            .sum::<f64>()
            * area;
        let peak_px = f64::from(
            f.u.iter()
                .zip(f.v.iter())
                .map(|(&a, &b)| (a * a + b * b).sqrt())
                .fold(0.0f32, f32::max),
        );
        Ok(RawContact {
            peak_px,
            x_px,
            y_px,
            ds1: sum(&f.u),
            ds2: sum(&f.v),
            dn,
            d_pf: hi - lo,
            ..Default::default()
        })
    }

    #[test]
    fn raw_quantities_match_the_plain_twin_bit_for_bit() {
        // Random fields (some exactly -0.0, and u, v as windows of a larger
        // flow, whose rows are not contiguous), both sub-pixel settings,
        // and a NaN and an infinity in D (the same error, or none).
        let mut rnd = crate::flow::unit_stream(0x3c6e_f372_fe94_f82bu64);
        for round in 0..60 {
            let (h, w) = (1 + (12.0 * rnd()) as usize, 1 + (30.0 * rnd()) as usize);
            let mut val = || -> f64 {
                let r = rnd();
                if r < 0.1 {
                    -0.0
                } else {
                    f64::from(8.0 * rnd() - 4.0)
                }
            };
            let big_u = Array2::from_shape_fn((h + 3, w + 5), |_| val() as f32);
            let big_v = Array2::from_shape_fn((h + 3, w + 5), |_| val() as f32);
            let mut pd = Array2::from_shape_fn((h, w), |_| val());
            let du = Array2::from_shape_fn((h, w), |_| val());
            let dv = Array2::from_shape_fn((h, w), |_| val());
            if round % 7 == 3 {
                pd[[h / 2, w / 2]] = f64::NAN;
            }
            if round % 11 == 5 {
                pd[[h - 1, 0]] = f64::NEG_INFINITY;
            }
            let (u, v) = if round % 2 == 0 {
                (
                    big_u.slice(ndarray::s![1..h + 1, 2..w + 2]),
                    big_v.slice(ndarray::s![2..h + 2, 3..w + 3]),
                )
            } else {
                (
                    big_u.slice(ndarray::s![..h;1, ..w;1]),
                    big_v.slice(ndarray::s![..h, ..w]),
                )
            };
            let f = PatchFields {
                u,
                v,
                potential_d: pd.view(),
                d_u: du.view(),
                d_v: dv.view(),
            };
            let grid = PatchGrid {
                x0: 3,
                y0: 1,
                scale: 2.0,
            };
            for subpixel in [false, true] {
                let got = raw_quantities(&f, grid, subpixel);
                let want = raw_quantities_plain(&f, grid, subpixel);
                match (got, want) {
                    (Ok(a), Ok(b)) => {
                        let bits = |r: &RawContact| {
                            [r.x_px, r.y_px, r.ds1, r.ds2, r.dn, r.d_pf].map(f64::to_bits)
                        };
                        assert_eq!(bits(&a), bits(&b), "round {round}");
                    }
                    (Err(a), Err(b)) => assert_eq!(a.to_string(), b.to_string()),
                    (a, b) => panic!("round {round}: {a:?} against {b:?}"),
                }
            }
        }
    }

    #[test]
    fn raw_quantities_read_strided_columns() {
        // A transposed view: no row is contiguous, the general loop runs.
        let pd = Array2::from_shape_fn((5, 4), |(i, j)| {
            ((i as f64) - 2.0).powi(2) + (j as f64 - 1.0).powi(2)
        });
        let t = pd.t().to_owned();
        let du = Array2::from_shape_fn((5, 4), |(i, j)| (i * 5 + j) as f64 * 0.1 - 1.0);
        let dut = du.t().to_owned();
        let u = Array2::from_shape_fn((4, 5), |(i, j)| (i + 2 * j) as f32 * 0.25);
        let f = PatchFields {
            u: u.t(),
            v: u.t(),
            potential_d: t.t(),
            d_u: dut.t(),
            d_v: dut.t(),
        };
        let grid = PatchGrid {
            x0: 0,
            y0: 0,
            scale: 1.0,
        };
        let (a, b) = (
            raw_quantities(&f, grid, true).unwrap(),
            raw_quantities_plain(&f, grid, true).unwrap(),
        );
        assert_eq!(
            [a.x_px, a.y_px, a.ds1, a.ds2, a.dn, a.d_pf],
            [b.x_px, b.y_px, b.ds1, b.ds2, b.dn, b.d_pf]
        );
    }

    #[test]
    fn parabola_vertex_is_exact_for_a_parabola() {
        // f(x) = (x - 0.3)^2 sampled at -1, 0, 1.
        let f = |x: f64| (x - 0.3) * (x - 0.3);
        assert!((parabola_offset(f(-1.0), f(0.0), f(1.0)) - 0.3).abs() < 1e-12);
        assert_eq!(parabola_offset(1.0, 1.0, 1.0), 0.0);
    }

    #[test]
    fn quantities_of_a_radial_bowl() {
        // D = (x - 5.3)^2 + (y - 3)^2 on a 7x11 grid at scale 4, d = grad D.
        let (h, w) = (7, 11);
        let dfun = |y: f64, x: f64| (x - 5.3).powi(2) + (y - 3.0).powi(2);
        let pd = Array2::from_shape_fn((h, w), |(i, j)| dfun(i as f64, j as f64));
        let du = Array2::from_shape_fn((h, w), |(_, j)| 2.0 * (j as f64 - 5.3));
        let dv = Array2::from_shape_fn((h, w), |(i, _)| 2.0 * (i as f64 - 3.0));
        let u = Array2::from_elem((h, w), 0.5f32);
        let v = Array2::from_elem((h, w), -0.25f32);
        let f = PatchFields {
            u: u.view(),
            v: v.view(),
            potential_d: pd.view(),
            d_u: du.view(),
            d_v: dv.view(),
        };
        let grid = PatchGrid {
            x0: 10,
            y0: 2,
            scale: 4.0,
        };
        let r = raw_quantities(&f, grid, true).unwrap();
        assert!(
            (r.x_px - ((10.0 + 5.3 + 0.5) * 4.0 - 0.5)).abs() < 1e-9,
            "{}",
            r.x_px
        );
        assert!((r.y_px - ((2.0 + 3.0 + 0.5) * 4.0 - 0.5)).abs() < 1e-9);
        let coarse = raw_quantities(&f, grid, false).unwrap();
        assert_eq!(coarse.x_px, (10.0 + 5.0 + 0.5) * 4.0 - 0.5);
        assert!((r.ds1 - 0.5 * 77.0 * 16.0).abs() < 1e-9);
        assert!((r.ds2 + 0.25 * 77.0 * 16.0).abs() < 1e-9);
        let max_d = pd.iter().cloned().fold(f64::MIN, f64::max);
        assert!((r.d_pf - (max_d - dfun(3.0, 5.0))).abs() < 1e-12);
        assert!(r.dn > 0.0);
    }

    #[test]
    fn mismatched_or_bad_fields_are_errors() {
        let a = Array2::<f32>::zeros((3, 3));
        let b = Array2::<f64>::zeros((3, 3));
        let c = Array2::<f64>::zeros((3, 4));
        let grid = PatchGrid {
            x0: 0,
            y0: 0,
            scale: 1.0,
        };
        let f = PatchFields {
            u: a.view(),
            v: a.view(),
            potential_d: c.view(),
            d_u: b.view(),
            d_v: b.view(),
        };
        assert!(raw_quantities(&f, grid, true).is_err());
        let mut n = b.clone();
        n[[1, 1]] = f64::NAN;
        n[[0, 0]] = -1.0;
        n[[2, 2]] = f64::INFINITY;
        let f = PatchFields {
            u: a.view(),
            v: a.view(),
            potential_d: n.view(),
            d_u: b.view(),
            d_v: b.view(),
        };
        assert!(matches!(
            raw_quantities(&f, grid, true),
            Err(Error::NonFinite { .. })
        ));
    }

    /// A `(h, w)` flow along x whose every row is `f(column)`.
    fn rows_of(h: usize, w: usize, f: impl Fn(f64) -> f64) -> Array2<f32> {
        Array2::from_shape_fn((h, w), |(_, j)| f(j as f64) as f32)
    }

    fn raw_at(x_px: f64) -> RawContact {
        RawContact {
            x_px,
            ..Default::default()
        }
    }

    /// The slow, obvious version: full-range centroid of the squared column
    /// sums, then a flat-window mean shift until it stops moving.
    fn oracle(u: &Array2<f32>, half: f64) -> f64 {
        let w: Vec<f64> = (0..u.ncols())
            .map(|j| {
                let s: f64 = (0..u.nrows()).map(|i| u[[i, j]] as f64).sum();
                s * s
            })
            .collect();
        let cen = |a: f64, b: f64| {
            let (mut s, mut sx) = (0.0, 0.0);
            for (j, &x) in w.iter().enumerate() {
                if (j as f64) > a && (j as f64) < b {
                    s += x;
                    sx += x * j as f64;
                }
            }
            sx / s
        };
        let mut c = cen(-1e300, 1e300);
        let last = w.len() as f64 - 0.5;
        for _ in 0..50 {
            // Symmetric about the estimate: shrunk where the image ends.
            let h = half.min(c + 0.5).min(last - c).max(1.0);
            let n = cen(c - h, c + h);
            if (n - c).abs() < 1e-6 {
                return n;
            }
            c = n;
        }
        c
    }

    #[test]
    fn a_neighbour_does_not_pull_a_symmetric_profile() {
        // A wide profile at column 40 and a narrow neighbour at 60: the first
        // contact's range is cut halfway, at 50, and its window (30) would
        // reach past that cut on one side only. A one-sided cut put it at
        // 39.42; the symmetric window keeps it at 40.
        let u = Array2::from_shape_fn((1, 100), |(_, j)| {
            let j = j as f32;
            (-(j - 40.0).powi(2) / 128.0).exp() + (-(j - 60.0).powi(2) / 8.0).exp()
        });
        let mut r = [raw_at(41.0), raw_at(59.0)];
        refine_contact_points(&mut r, u.view(), 1.0, 30.0).unwrap();
        assert!((r[0].x_px - 40.0).abs() < 0.05, "{}", r[0].x_px);
        // (The narrow one still feels the wide one's tail inside its own
        // window: leakage, not truncation.)
    }

    #[test]
    fn tangential_and_normal_profiles_give_the_load_point() {
        // Shear: an even bump; press: an odd profile; both about column 61.3.
        let c = 61.3;
        let even = rows_of(7, 160, |j| (-((j - c) / 9.0).powi(2)).exp());
        let odd = rows_of(7, 160, |j| (j - c) / 9.0 * (-((j - c) / 9.0).powi(2)).exp());
        for (name, u) in [("even", &even), ("odd", &odd)] {
            let mut r = [raw_at(70.0)];
            refine_contact_points(&mut r, u.view(), 1.0, 60.0).unwrap();
            assert!((r[0].x_px - c).abs() < 1e-3, "{name}: {}", r[0].x_px);
        }
        // On a grid of 2 pixels per cell, cell 61.3 is pixel (61.3 + 0.5) * 2 - 0.5.
        let mut r = [raw_at(100.0)];
        refine_contact_points(&mut r, even.view(), 2.0, 120.0).unwrap();
        assert!((r[0].x_px - 123.1).abs() < 2e-3, "{}", r[0].x_px);
    }

    #[test]
    fn two_contacts_keep_to_their_own_halves() {
        let g = |j: f64, c: f64| (-((j - c) / 6.0).powi(2)).exp();
        let u = rows_of(4, 300, |j| g(j, 80.0) + 0.5 * g(j, 200.0));
        let mut r = [raw_at(90.0), raw_at(195.0)];
        refine_contact_points(&mut r, u.view(), 1.0, 400.0).unwrap();
        assert!((r[0].x_px - 80.0).abs() < 1e-3, "{}", r[0].x_px);
        assert!((r[1].x_px - 200.0).abs() < 1e-3, "{}", r[1].x_px);
    }

    #[test]
    fn no_motion_keeps_the_contact_point_and_bad_parameters_are_errors() {
        let u = Array2::<f32>::zeros((3, 50));
        let mut r = [raw_at(12.5)];
        refine_contact_points(&mut r, u.view(), 1.0, 10.0).unwrap();
        assert_eq!(r[0].x_px, 12.5);
        for (s, w) in [
            (0.0, 10.0),
            (1.0, 0.0),
            (f64::NAN, 1.0),
            (1.0, f64::INFINITY),
        ] {
            assert!(matches!(
                refine_contact_points(&mut r, u.view(), s, w),
                Err(Error::InvalidParameter { .. })
            ));
        }
        // Nothing to refine: fine.
        refine_contact_points(&mut [], u.view(), 1.0, 10.0).unwrap();
    }

    /// The slow, obvious slope peak: column sums, central differences
    /// (one-sided at the ends), a truncated Gaussian renormalised at the
    /// ends, the argmax over `[lo, hi)`, a parabola through the neighbours.
    fn slope_oracle(u: &Array2<f32>, scale: f64, sigma_px: f64, lo: usize, hi: usize) -> f64 {
        let n = u.ncols();
        let p: Vec<f64> = (0..n)
            .map(|j| (0..u.nrows()).map(|i| u[[i, j]] as f64).sum())
            .collect();
        let d: Vec<f64> = (0..n)
            .map(|j| {
                if j == 0 {
                    p[1] - p[0]
                } else if j == n - 1 {
                    p[n - 1] - p[n - 2]
                } else {
                    (p[j + 1] - p[j - 1]) / 2.0
                }
            })
            .collect();
        let sig = sigma_px / scale;
        let r = (3.0 * sig).ceil() as i64;
        let s: Vec<f64> = (0..n as i64)
            .map(|j| {
                let (mut a, mut w) = (0.0, 0.0);
                for i in (j - r).max(0)..=(j + r).min(n as i64 - 1) {
                    let g = (-0.5 * ((i - j) as f64 / sig).powi(2)).exp();
                    a += g * d[i as usize];
                    w += g;
                }
                a / w
            })
            .collect();
        let mut b = lo;
        for j in lo..hi {
            if s[j] > s[b] {
                b = j;
            }
        }
        let mut off = 0.0;
        if b > 0 && b + 1 < n {
            let den = s[b - 1] - 2.0 * s[b] + s[b + 1];
            if den < 0.0 {
                off = (0.5 * (s[b - 1] - s[b + 1]) / den).clamp(-0.5, 0.5);
            }
        }
        (b as f64 + off + 0.5) * scale - 0.5
    }

    /// A press's motion along the arc about column `c`: odd, spreading
    /// (rising through `c`, steepest there).
    fn press(j: f64, c: f64, w: f64) -> f64 {
        let t = (j - c) / w;
        t * (-t * t).exp()
    }

    #[test]
    fn the_slope_peaks_at_a_press_and_a_far_neighbour_does_not_move_it() {
        let c = 61.3;
        let u = rows_of(5, 200, |j| press(j, c, 8.0) + 0.7 * press(j, 140.0, 8.0));
        let mut r = [raw_at(70.0), raw_at(130.0)];
        slope_peak_contact_points(&mut r, u.view(), 1.0, 2.0).unwrap();
        assert!((r[0].x_px - c).abs() < 0.05, "{}", r[0].x_px);
        assert!((r[1].x_px - 140.0).abs() < 0.05, "{}", r[1].x_px);
        // On a grid of 2 pixels per cell, cell 61.3 is pixel 123.1.
        let mut r = [raw_at(130.0)];
        slope_peak_contact_points(&mut r, u.view(), 2.0, 4.0).unwrap();
        assert!((r[0].x_px - 123.1).abs() < 0.1, "{}", r[0].x_px);
    }

    #[test]
    fn the_slope_peak_stays_put_where_the_centroid_is_pulled() {
        // Two presses 24 cells apart: the lobes between them cancel. The
        // energy centroid slides outward; the slope peak hardly moves.
        let u = rows_of(3, 200, |j| press(j, 88.0, 6.0) + press(j, 112.0, 6.0));
        let mut slope = [raw_at(88.0), raw_at(112.0)];
        slope_peak_contact_points(&mut slope, u.view(), 1.0, 1.5).unwrap();
        let mut centroid = [raw_at(88.0), raw_at(112.0)];
        refine_contact_points(&mut centroid, u.view(), 1.0, 40.0).unwrap();
        let err = |r: &[RawContact; 2]| (r[0].x_px - 88.0).abs().max((r[1].x_px - 112.0).abs());
        assert!(err(&slope) < 0.3, "{:?}", slope.map(|r| r.x_px));
        assert!(
            err(&centroid) > 3.0 * err(&slope),
            "{:?}",
            centroid.map(|r| r.x_px)
        );
    }

    #[test]
    fn the_slope_search_keeps_to_its_side_of_a_neighbour() {
        // A strong rise at 50 and a weaker one at 150: the contact started
        // at 140 keeps to its side of the one started at 60.
        let u = rows_of(2, 200, |j| 2.0 * press(j, 50.0, 5.0) + press(j, 150.0, 5.0));
        let mut r = [raw_at(60.0), raw_at(140.0)];
        slope_peak_contact_points(&mut r, u.view(), 1.0, 1.0).unwrap();
        assert!((r[0].x_px - 50.0).abs() < 0.05, "{}", r[0].x_px);
        assert!((r[1].x_px - 150.0).abs() < 0.05, "{}", r[1].x_px);
        // No rise in range: the estimate is kept.
        let flat = rows_of(2, 50, |_| 1.0);
        let mut r = [raw_at(20.0)];
        slope_peak_contact_points(&mut r, flat.view(), 1.0, 2.0).unwrap();
        assert_eq!(r[0].x_px, 20.0);
        for (s, w) in [(0.0, 1.0), (1.0, -1.0), (1.0, f64::NAN)] {
            assert!(matches!(
                slope_peak_contact_points(&mut r, flat.view(), s, w),
                Err(Error::InvalidParameter { .. })
            ));
        }
    }

    #[test]
    fn old_settings_map_to_their_methods() {
        use crate::calibration::PipelineSettings;
        let mut p = PipelineSettings {
            flow_preset: "accurate".into(),
            margin_px: 0,
            subpixel: true,
            contact_window_px: 0,
            contact_point: None,
            exposure: None,
            dot_tracking: false,
            dot_fit: false,
            light_box_px: None,
            weighted_profiles: false,
        };
        assert_eq!(
            p.contact_point_method(),
            ContactPointMethod::PotentialMinimum
        );
        p.contact_window_px = 400;
        assert_eq!(
            p.contact_point_method(),
            ContactPointMethod::EnergyCentroid {
                half_window_px: 400.0
            }
        );
        p.contact_point = Some(ContactPointMethod::DEFAULT);
        assert_eq!(p.contact_point_method(), ContactPointMethod::DEFAULT);
        let json = serde_json::to_string(&ContactPointMethod::DEFAULT).unwrap();
        assert_eq!(json, r#"{"method":"slope_peak","sigma_px":8.0}"#);
    }

    #[test]
    fn motion_lines_start_at_the_2d_slope_peak() {
        let m = ContactPointMethod::MotionLines { sigma_px: 16.0 };
        let json = serde_json::to_string(&m).unwrap();
        assert_eq!(json, r#"{"method":"motion_lines","sigma_px":16.0}"#);
        assert_eq!(
            serde_json::from_str::<ContactPointMethod>(&json).unwrap(),
            m
        );
        for bad in [0.0, -1.0, f64::NAN, MAX_SLOPE_SIGMA_PX + 1.0] {
            assert!(
                ContactPointMethod::MotionLines { sigma_px: bad }
                    .validate()
                    .is_err()
            );
        }
        // The locator holds no dots: it gives the 2-D slope peak.
        let (h, w) = (20, 40);
        let u = Array2::from_shape_fn((h, w), |(_, j)| (j as f32 - 17.0).tanh());
        let v = Array2::from_shape_fn((h, w), |(i, _)| (i as f32 - 9.0).tanh());
        let start = RawContact {
            x_px: 5.0,
            y_px: 5.0,
            bbox: Roi::new(10, 5, 15, 10),
            ..Default::default()
        };
        let (mut a, mut b) = ([start], [start]);
        let mut locator = ContactLocator::new();
        locator.refine(m, &mut a, u.view(), v.view(), 1.0).unwrap();
        let slope = ContactPointMethod::SlopePeak2d { sigma_px: 16.0 };
        locator
            .refine(slope, &mut b, u.view(), v.view(), 1.0)
            .unwrap();
        assert_eq!(a, b);
        assert_ne!([a[0].x_px, a[0].y_px], [5.0, 5.0]);
    }

    #[test]
    fn shear_ratio_guards_a_zero_normal() {
        let r = RawContact {
            ds1: 3.0,
            dn: 6.0,
            ..Default::default()
        };
        assert_eq!(r.shear_ratio(), 0.5);
        assert_eq!(RawContact::default().shear_ratio(), 0.0);
    }

    proptest::proptest! {
        #![proptest_config(proptest::test_runner::Config {
            cases: 48,
            rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
            rng_seed: proptest::test_runner::RngSeed::Fixed(7),
            failure_persistence: None,
            ..Default::default()
        })]
        #[test]
        fn matches_the_oracle(
            vals in proptest::collection::vec(-3.0f32..3.0, 3 * 40),
            half in 2.0f64..50.0,
        ) {
            let u = Array2::from_shape_vec((3, 40), vals).unwrap();
            let mut r = [raw_at(5.0)];
            refine_contact_points(&mut r, u.view(), 1.0, half).unwrap();
            let want = oracle(&u, half);
            proptest::prop_assert!((r[0].x_px - want).abs() < 1e-6, "{} vs {}", r[0].x_px, want);
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::test_runner::Config {
            cases: 48,
            rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
            rng_seed: proptest::test_runner::RngSeed::Fixed(8),
            failure_persistence: None,
            ..Default::default()
        })]
        #[test]
        fn the_slope_peak_matches_its_oracle(
            vals in proptest::collection::vec(-3.0f32..3.0, 2 * 60),
            sigma in 0.5f64..8.0,
            scale in proptest::sample::select(vec![1.0f64, 2.0, 4.0]),
        ) {
            let u = Array2::from_shape_vec((2, 60), vals).unwrap();
            let mut r = [raw_at(10.0)];
            slope_peak_contact_points(&mut r, u.view(), scale, sigma).unwrap();
            let want = slope_oracle(&u, scale, sigma, 0, 60);
            // Either both found the same peak, or there was no rise at all
            // and the estimate was kept.
            proptest::prop_assert!(
                (r[0].x_px - want).abs() < 1e-9 || r[0].x_px == 10.0,
                "{} vs {}", r[0].x_px, want
            );
        }

        /// The slope peak of a given profile within a window about the
        /// start: the oracle's peak over the window's cells.
        #[test]
        fn the_slope_peak_in_a_window_matches_its_oracle(
            vals in proptest::collection::vec(-3.0f32..3.0, 60),
            sigma in 0.5f64..8.0,
            scale in proptest::sample::select(vec![1.0f64, 2.0, 4.0]),
            start in 0.0f64..59.0,
            window in 0.5f64..30.0,
        ) {
            let u = Array2::from_shape_vec((1, 60), vals).unwrap();
            let profile: Vec<f64> = u.iter().map(|&x| f64::from(x)).collect();
            let first = from_grid(start, scale);
            let mut col = [first];
            ContactLocator::new().slope_peak_in_profile(
                &profile, &mut col, scale, sigma, window * scale,
            );
            let lo = (start - window).ceil().max(0.0) as usize;
            let hi = ((start + window).floor() + 1.0).min(60.0) as usize;
            let want = slope_oracle(&u, scale, sigma, lo, hi);
            proptest::prop_assert!(
                (col[0] - want).abs() < 1e-9 || col[0] == first,
                "{} vs {}", col[0], want
            );
            // Never further than the window and the parabola's half cell.
            proptest::prop_assert!((col[0] - first).abs() <= (window + 0.5) * scale + 1e-9);
        }
    }

    /// A radial press at `(x0, y0)` (grid cells) on an `h x w` grid: the
    /// markers spread outward, `(u, v) = 0.2 (x - x0, y - y0) exp(-r^2 / 2 s^2)`.
    fn radial_press(
        (h, w): (usize, usize),
        (x0, y0): (f64, f64),
        s: f64,
        u: &mut Array2<f32>,
        v: &mut Array2<f32>,
    ) {
        for i in 0..h {
            for j in 0..w {
                let (dx, dy) = (j as f64 - x0, i as f64 - y0);
                let g = (-(dx * dx + dy * dy) / (2.0 * s * s)).exp();
                u[[i, j]] += (0.2 * dx * g) as f32;
                v[[i, j]] += (0.2 * dy * g) as f32;
            }
        }
    }

    #[test]
    fn the_2d_slope_peak_finds_round_presses_in_both_axes() {
        let (h, w, scale) = (60, 80, 2.0);
        let mut u = Array2::<f32>::zeros((h, w));
        let mut v = Array2::<f32>::zeros((h, w));
        // Two presses in the same columns, one above the other.
        radial_press((h, w), (37.3, 14.6), 5.0, &mut u, &mut v);
        radial_press((h, w), (37.8, 44.2), 5.0, &mut u, &mut v);
        let cell_px = |c: f64| (c + 0.5) * scale - 0.5;
        let bbox = |x0: f64, y0: f64| {
            Roi::new(
                (cell_px(x0) - 20.0) as usize,
                (cell_px(y0) - 20.0) as usize,
                40,
                40,
            )
        };
        let mut raws = [
            RawContact {
                x_px: cell_px(35.0),
                y_px: cell_px(17.0),
                bbox: bbox(37.3, 14.6),
                ..Default::default()
            },
            RawContact {
                x_px: cell_px(40.0),
                y_px: cell_px(41.0),
                bbox: bbox(37.8, 44.2),
                ..Default::default()
            },
        ];
        let method = ContactPointMethod::SlopePeak2d { sigma_px: 4.0 };
        ContactLocator::new()
            .refine(method, &mut raws, u.view(), v.view(), scale)
            .unwrap();
        for (r, (x0, y0)) in raws.iter().zip([(37.3, 14.6), (37.8, 44.2)]) {
            assert!(
                (r.x_px - cell_px(x0)).abs() < 0.5,
                "x {} vs {}",
                r.x_px,
                cell_px(x0)
            );
            assert!(
                (r.y_px - cell_px(y0)).abs() < 0.5,
                "y {} vs {}",
                r.y_px,
                cell_px(y0)
            );
        }
        // The 1-D slope peak sums over every row and moves only the columns.
        let mut one = raws;
        one[0].y_px = 1.0;
        ContactLocator::new()
            .refine(
                ContactPointMethod::DEFAULT,
                &mut one[..1],
                u.view(),
                v.view(),
                scale,
            )
            .unwrap();
        assert_eq!(one[0].y_px, 1.0);
        // Mismatched u and v are an error, not a panic.
        let short = Array2::<f32>::zeros((h - 1, w));
        assert!(matches!(
            ContactLocator::new().refine(method, &mut raws, u.view(), short.view(), scale),
            Err(Error::ShapeMismatch { .. })
        ));
    }

    proptest::proptest! {
        #![proptest_config(proptest::test_runner::Config {
            cases: 48,
            rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
            rng_seed: proptest::test_runner::RngSeed::Fixed(9),
            failure_persistence: None,
            ..Default::default()
        })]
        #[test]
        fn the_2d_slope_peak_matches_the_1d_oracle_on_its_bands(
            uv in proptest::collection::vec(-3.0f32..3.0, 2 * 12 * 30),
            sigma in 0.5f64..6.0,
            scale in proptest::sample::select(vec![1.0f64, 2.0]),
            bx in 0usize..20, by in 0usize..8, bw in 1usize..12, bh in 1usize..6,
        ) {
            let (h, w) = (12, 30);
            let u = Array2::from_shape_vec((h, w), uv[..h * w].to_vec()).unwrap();
            let v = Array2::from_shape_vec((h, w), uv[h * w..].to_vec()).unwrap();
            let bbox = Roi::new(bx, by, bw, bh);
            let start = RawContact { x_px: 7.0, y_px: 3.0, bbox, ..Default::default() };
            let mut r = [start];
            let m = ContactPointMethod::SlopePeak2d { sigma_px: sigma };
            ContactLocator::new().refine(m, &mut r, u.view(), v.view(), scale).unwrap();
            // The band: the box widened by 3 sigma, in grid cells.
            let band = |a: usize, len: usize, n: usize| {
                let lo = (((a as f64 - 3.0 * sigma) + 0.5) / scale - 0.5).floor().max(0.0) as usize;
                let hi = ((((a + len) as f64 + 3.0 * sigma) + 0.5) / scale - 0.5).ceil().max(0.0) as usize;
                (lo.min(n), hi.min(n).max(lo.min(n)))
            };
            let rows = band(by, bh, h);
            let cols = band(bx, bw, w);
            if rows.0 < rows.1 {
                let u_band = u.slice(ndarray::s![rows.0..rows.1, ..]).to_owned();
                let want = slope_oracle(&u_band, scale, sigma, 0, w);
                proptest::prop_assert!(
                    (r[0].x_px - want).abs() < 1e-9 || r[0].x_px == 7.0,
                    "x {} vs {}", r[0].x_px, want
                );
            }
            if cols.0 < cols.1 {
                let v_band = v.slice(ndarray::s![.., cols.0..cols.1]).t().to_owned();
                let want = slope_oracle(&v_band, scale, sigma, 0, h);
                proptest::prop_assert!(
                    (r[0].y_px - want).abs() < 1e-9 || r[0].y_px == 3.0,
                    "y {} vs {}", r[0].y_px, want
                );
            }
        }
    }

    #[test]
    fn a_central_press_points_down() {
        let g = SensorGeometry::default();
        let raw = RawContact {
            ds1: 0.0,
            ds2: 0.0,
            dn: 100.0,
            ..Default::default()
        };
        let d = rotate_to_sensor(&g, 0.0, &raw);
        assert_eq!(d, [0.0, 0.0, -100.0]);
        // Off centre the outward normal tilts toward +x for x > 0, so a push into the skin has -x.
        let d = rotate_to_sensor(&g, 100.0, &raw);
        assert!(d[0] < 0.0 && d[2] < 0.0);
    }
}
