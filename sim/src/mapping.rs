//! Mapping by touch and perch selection: the geometry of the paper's demos.
//!
//! - [`Pose`] (body pose in the world: unit quaternion + translation, one
//!   `poses.csv` row) and [`Mounting`] (the sensor frame in the body frame)
//!   take a contact from the sensor frame (mm) to the world frame (m):
//!   [`sensor_to_world`], or every contact of a sequence at once with
//!   [`world_contacts`]; [`map_touches`] does that and the clustering in one
//!   call, with the `touch_mapping` example's defaults ([`MapOptions`]).
//! - [`cluster`] groups repeated touches of the same obstacle: single-linkage
//!   clustering with a distance threshold (two points are in the same cluster
//!   when a chain of points, each within `radius_m` of the next, joins them).
//!   The result does not depend on the order of the points. Each [`Cluster`]
//!   holds its mean position, count and spread.
//! - [`Rod`] is a true obstacle (a line in the world); [`match_rods`] pairs
//!   clusters with rods one to one and gives the error per rod (distance from
//!   the cluster's centre to the rod's line).
//! - [`rank_perches`] is the compliance demo's decision: of perches pressed by
//!   the same depth, the one pushing back harder is stiffer.
//!
//! ```
//! use optical_tactile_sim::mapping::{cluster, sensor_to_world, Mounting, Pose, Rod};
//! // The body 1.2 m above the world origin, level; the sensor hangs under it
//! // (the default mounting: skin facing down).
//! let pose = Pose::new([0.5, 0.0, 1.2], [1.0, 0.0, 0.0, 0.0])?;
//! let w = sensor_to_world([20.0, 0.0, 150.0], &pose, &Mounting::default());
//! assert!((w[0] - 0.52).abs() < 1e-12 && (w[2] - 1.05).abs() < 1e-12);
//! let clusters = cluster(&[w, [0.521, 0.0, 1.05], [0.9, 0.0, 1.05]], 0.05)?;
//! assert_eq!(clusters.len(), 2);
//! assert_eq!(clusters[0].count, 2);
//! let rod = Rod::along_y(0.52, 1.05);
//! assert!(rod.distance(clusters[0].position_m) < 1e-3);
//! # Ok::<(), optical_tactile::Error>(())
//! ```

use std::collections::HashMap;
use std::path::Path;

use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use optical_tactile::error::{Error, Result};
use optical_tactile::io::{FrameRecord, PoseRow};

/// A body pose in the world frame: the body frame's origin (m) and its
/// orientation (a unit quaternion taking body vectors to world vectors).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Position of the body origin in the world, m.
    pub translation_m: [f64; 3],
    rotation: UnitQuaternion<f64>,
}

impl Pose {
    /// The identity pose (body frame = world frame).
    pub fn identity() -> Self {
        Pose {
            translation_m: [0.0; 3],
            rotation: UnitQuaternion::identity(),
        }
    }

    /// A pose from a translation (m) and a quaternion `[w, x, y, z]`, which is
    /// normalised. Errors on a non-finite value or a (near-)zero quaternion.
    pub fn new(translation_m: [f64; 3], q: [f64; 4]) -> Result<Self> {
        if translation_m.iter().chain(q.iter()).any(|v| !v.is_finite()) {
            return Err(Error::param(
                "pose",
                format!("non-finite value in translation {translation_m:?} / quaternion {q:?}"),
            ));
        }
        let quat = Quaternion::new(q[0], q[1], q[2], q[3]);
        let n = quat.norm();
        if n < 1e-9 {
            return Err(Error::param(
                "pose",
                format!("quaternion {q:?} has zero length: no orientation"),
            ));
        }
        Ok(Pose {
            translation_m,
            rotation: UnitQuaternion::new_unchecked(quat / n),
        })
    }

    /// The pose of one `poses.csv` row.
    pub fn from_row(row: &PoseRow) -> Result<Self> {
        Pose::new(
            [row.x_m, row.y_m, row.z_m],
            [row.qw, row.qx, row.qy, row.qz],
        )
        .map_err(|e| Error::param("pose", format!("frame {}: {e}", row.frame)))
    }

    /// The unit quaternion `[w, x, y, z]`.
    pub fn quaternion(&self) -> [f64; 4] {
        let q = self.rotation.quaternion();
        [q.w, q.i, q.j, q.k]
    }

    /// A body-frame point (m) in the world frame (m).
    pub fn transform_point(&self, p: [f64; 3]) -> [f64; 3] {
        let v = self.rotation * Vector3::from(p) + Vector3::from(self.translation_m);
        [v.x, v.y, v.z]
    }
}

/// Where the sensor sits on the body: `body = rotation * sensor + offset`
/// (points in m).
///
/// The default is what the simulator's `mapping` scenario assumes
/// (`rods.json`'s `sensor_in_body_rotation`): the sensor hangs under the body
/// with its skin facing down, sensor x = body x, sensor y = -body y, sensor z
/// = -body z (180 deg about x), no offset.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mounting {
    rotation: Matrix3<f64>,
    offset_m: [f64; 3],
}

impl Default for Mounting {
    fn default() -> Self {
        Mounting {
            rotation: Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0),
            offset_m: [0.0; 3],
        }
    }
}

impl Mounting {
    /// Sensor frame = body frame.
    pub fn identity() -> Self {
        Mounting {
            rotation: Matrix3::identity(),
            offset_m: [0.0; 3],
        }
    }

    /// A mounting from a rotation matrix given by rows (`body = R * sensor +
    /// offset`) and an offset in m. Errors unless `R` is a proper rotation
    /// (orthonormal within 1e-6, determinant +1) and everything is finite.
    pub fn new(rotation_rows: [[f64; 3]; 3], offset_m: [f64; 3]) -> Result<Self> {
        let flat: Vec<f64> = rotation_rows.iter().flatten().copied().collect();
        if flat.iter().chain(offset_m.iter()).any(|v| !v.is_finite()) {
            return Err(Error::param("mounting", "non-finite rotation or offset"));
        }
        let r = Matrix3::from_row_slice(&flat);
        let err = (r.transpose() * r - Matrix3::identity()).abs().max();
        if err > 1e-6 || r.determinant() < 0.0 {
            return Err(Error::param(
                "mounting",
                format!(
                    "rotation {rotation_rows:?} is not a proper rotation (|R^T R - I| = {err:.2e}, det = {:.3})",
                    r.determinant()
                ),
            ));
        }
        Ok(Mounting {
            rotation: r,
            offset_m,
        })
    }

    /// A sensor-frame point in m in the body frame, m.
    pub fn to_body(&self, p_m: [f64; 3]) -> [f64; 3] {
        let v = self.rotation * Vector3::from(p_m) + Vector3::from(self.offset_m);
        [v.x, v.y, v.z]
    }
}

/// A contact location in the sensor frame (mm) in the world frame (m), with
/// the body pose of its frame.
pub fn sensor_to_world(contact_mm: [f64; 3], pose: &Pose, mounting: &Mounting) -> [f64; 3] {
    pose.transform_point(mounting.to_body(contact_mm.map(|v| v * 1e-3)))
}

/// One contact of a sequence, in the world frame.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldContact {
    /// Frame file name.
    pub frame: String,
    /// Time stamp of the frame, s.
    pub t_s: f64,
    /// Contact identity (when the record has one).
    pub id: Option<u64>,
    /// Location in the world frame, m.
    pub position_m: [f64; 3],
    /// Force magnitude, N.
    pub force_n: f64,
}

/// The poses of `poses.csv` rows by frame name. Errors (naming `path`, the
/// file the rows came from, and the 1-based line) on a duplicate frame or an
/// invalid pose.
pub fn poses_by_frame(rows: &[PoseRow], path: &Path) -> Result<HashMap<String, Pose>> {
    let mut out = HashMap::with_capacity(rows.len());
    for (k, row) in rows.iter().enumerate() {
        let line = Some(k + 2); // after the header
        let pose = Pose::from_row(row).map_err(|e| Error::format(path, line, e.to_string()))?;
        if out.insert(row.frame.clone(), pose).is_some() {
            return Err(Error::format(
                path,
                line,
                format!("frame {} has a second pose row", row.frame),
            ));
        }
    }
    Ok(out)
}

/// Every contact of `frames` in the world frame, in order, each with the
/// pose of its frame. Contacts whose force magnitude is below `min_force_n`
/// are left out (light touches are located less well). A frame with
/// contacts but no pose is an error naming `poses_path` and the frame;
/// frames without contacts need no pose.
pub fn world_contacts(
    frames: &[FrameRecord],
    poses: &HashMap<String, Pose>,
    mounting: &Mounting,
    min_force_n: f64,
    poses_path: &Path,
) -> Result<Vec<WorldContact>> {
    let mut out = Vec::new();
    for f in frames {
        if f.contacts.is_empty() {
            continue;
        }
        let pose = poses.get(&f.frame).ok_or_else(|| {
            Error::format(
                poses_path,
                None,
                format!("no pose row for frame {} (which has contacts)", f.frame),
            )
        })?;
        for c in &f.contacts {
            let p = [c.x_mm, c.y_mm, c.z_mm];
            if p.iter().any(|v| !v.is_finite()) {
                return Err(Error::param(
                    "contacts",
                    format!("frame {}: non-finite contact location {p:?}", f.frame),
                ));
            }
            let force = (c.fx_n * c.fx_n + c.fy_n * c.fy_n + c.fz_n * c.fz_n).sqrt();
            if force < min_force_n {
                continue;
            }
            out.push(WorldContact {
                frame: f.frame.clone(),
                t_s: f.t_s,
                id: c.id,
                position_m: sensor_to_world(p, pose, mounting),
                force_n: force,
            });
        }
    }
    Ok(out)
}

/// Repeated touches of one obstacle.
#[derive(Debug, Clone, PartialEq)]
pub struct Cluster {
    /// Mean position of the members, m.
    pub position_m: [f64; 3],
    /// Number of members.
    pub count: usize,
    /// Root-mean-square distance of the members from the mean, m.
    pub spread_m: f64,
    /// Indices of the members in the input, ascending.
    pub members: Vec<usize>,
}

/// One obstacle estimate as the demos and experiments report it (world
/// frame; the JSON shape of the `touch_mapping` example).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ClusterSummary {
    /// Mean position of the touches, x, m.
    pub x_m: f64,
    /// Mean position of the touches, y, m.
    pub y_m: f64,
    /// Mean position of the touches, z, m.
    pub z_m: f64,
    /// Number of contacts (one per frame they were seen in).
    pub count: usize,
    /// RMS distance of the contacts from the mean, m.
    pub spread_m: f64,
}

impl Cluster {
    /// The cluster without its member list.
    pub fn summary(&self) -> ClusterSummary {
        let [x_m, y_m, z_m] = self.position_m;
        ClusterSummary {
            x_m,
            y_m,
            z_m,
            count: self.count,
            spread_m: self.spread_m,
        }
    }
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn find(parent: &mut [usize], mut i: usize) -> usize {
    while parent[i] != i {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    i
}

/// Single-linkage clusters of `points` (m): two points share a cluster when
/// a chain of points, each at most `radius_m` from the next, joins them.
/// Clusters come in the order of their first member (for a time-ordered
/// input: the order the obstacles were first touched). Errors on a
/// non-finite point or a radius that is not finite and > 0.
///
/// Sweeps the points sorted by x, so only pairs closer than `radius_m` in x
/// are compared: O(n log n) for sparse obstacles.
pub fn cluster(points: &[[f64; 3]], radius_m: f64) -> Result<Vec<Cluster>> {
    if !(radius_m.is_finite() && radius_m > 0.0) {
        return Err(Error::param(
            "radius_m",
            format!("must be finite and > 0, got {radius_m}"),
        ));
    }
    if let Some((i, p)) = points
        .iter()
        .enumerate()
        .find(|(_, p)| p.iter().any(|v| !v.is_finite()))
    {
        return Err(Error::param(
            "points",
            format!("point {i} is not finite: {p:?}"),
        ));
    }
    let n = points.len();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| points[a][0].total_cmp(&points[b][0]));
    let mut parent: Vec<usize> = (0..n).collect();
    for (k, &i) in order.iter().enumerate() {
        for &j in &order[k + 1..] {
            if points[j][0] - points[i][0] > radius_m {
                break;
            }
            if dist(points[i], points[j]) <= radius_m {
                let (a, b) = (find(&mut parent, i), find(&mut parent, j));
                if a != b {
                    parent[a.max(b)] = a.min(b);
                }
            }
        }
    }
    let mut index: HashMap<usize, usize> = HashMap::new();
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for i in 0..n {
        let r = find(&mut parent, i);
        let g = *index.entry(r).or_insert_with(|| {
            groups.push(Vec::new());
            groups.len() - 1
        });
        groups[g].push(i);
    }
    Ok(groups
        .into_iter()
        .map(|members| summarize(points, members))
        .collect())
}

/// The [`Cluster`] of the given members of `points`.
fn summarize(points: &[[f64; 3]], members: Vec<usize>) -> Cluster {
    let count = members.len();
    let mut c = [0.0; 3];
    for &i in &members {
        for (a, v) in c.iter_mut().zip(points[i]) {
            *a += v;
        }
    }
    let c = c.map(|v| v / count as f64);
    let ss: f64 = members.iter().map(|&i| dist(points[i], c).powi(2)).sum();
    Cluster {
        position_m: c,
        count,
        spread_m: (ss / count as f64).sqrt(),
        members,
    }
}

/// Options of [`map_touches`]. The defaults are those of the
/// `touch_mapping` example.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapOptions {
    /// Single-linkage radius, m (default 0.05: touches of one rod fall within
    /// a few mm; rods are tens of cm apart).
    pub radius_m: f64,
    /// Contacts lighter than this are left out, N (default 0.5: drops faint
    /// ghost patches that can appear beside a real press).
    pub min_force_n: f64,
    /// Clusters with fewer touches are dropped (default 1: none).
    pub min_count: usize,
}

impl Default for MapOptions {
    fn default() -> Self {
        MapOptions {
            radius_m: 0.05,
            min_force_n: 0.5,
            min_count: 1,
        }
    }
}

/// The result of [`map_touches`].
#[derive(Debug, Clone, PartialEq)]
pub struct TouchMap {
    /// Every kept contact in the world frame, in sequence order.
    pub touches: Vec<WorldContact>,
    /// The obstacle estimates; `members` index `touches`.
    pub clusters: Vec<Cluster>,
}

/// The whole mapping step: [`world_contacts`] then [`cluster`], dropping
/// clusters of fewer than `options.min_count` touches. Errors as those
/// functions do, and on options out of range.
pub fn map_touches(
    frames: &[FrameRecord],
    poses: &HashMap<String, Pose>,
    mounting: &Mounting,
    options: &MapOptions,
    poses_path: &Path,
) -> Result<TouchMap> {
    if !(options.min_force_n.is_finite() && options.min_force_n >= 0.0) {
        return Err(Error::param(
            "min_force_n",
            format!("must be finite and >= 0, got {}", options.min_force_n),
        ));
    }
    if options.min_count == 0 {
        return Err(Error::param("min_count", "must be >= 1"));
    }
    let touches = world_contacts(frames, poses, mounting, options.min_force_n, poses_path)?;
    let points: Vec<[f64; 3]> = touches.iter().map(|t| t.position_m).collect();
    let mut clusters = cluster(&points, options.radius_m)?;
    clusters.retain(|c| c.count >= options.min_count);
    Ok(TouchMap { touches, clusters })
}

/// A true obstacle: a straight rod, as a line through `point_m` along
/// `direction` (a point obstacle is any line of zero length: use
/// [`Rod::point`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rod {
    /// A point on the rod's touched line, m (for a rod touched from above:
    /// on its top).
    pub point_m: [f64; 3],
    /// Unit direction of the rod, or zero for a point obstacle.
    pub direction: [f64; 3],
}

impl Rod {
    /// A rod lying along the world y axis with its top at world `(x_m, *,
    /// top_m)`, as in the simulator's `mapping` scenario.
    pub fn along_y(x_m: f64, top_m: f64) -> Self {
        Rod {
            point_m: [x_m, 0.0, top_m],
            direction: [0.0, 1.0, 0.0],
        }
    }

    /// A point obstacle.
    pub fn point(p_m: [f64; 3]) -> Self {
        Rod {
            point_m: p_m,
            direction: [0.0; 3],
        }
    }

    /// Distance of `p` (m) from the rod's line (or point), m.
    pub fn distance(&self, p: [f64; 3]) -> f64 {
        let d = Vector3::from(self.direction);
        let v = Vector3::from(p) - Vector3::from(self.point_m);
        let n = d.norm();
        if n < 1e-12 {
            return v.norm();
        }
        let d = d / n;
        (v - d * v.dot(&d)).norm()
    }
}

/// A true rod and the cluster matched to it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RodMatch {
    /// Index of the rod.
    pub rod: usize,
    /// Index of its cluster, `None` if no cluster lies within the gate.
    pub cluster: Option<usize>,
    /// Distance from the cluster's centre to the rod, m.
    pub error_m: Option<f64>,
}

/// Pairs clusters with rods one to one: repeatedly takes the closest
/// remaining (rod, cluster) pair within `gate_m` (ties by rod then cluster
/// index). Returns one entry per rod, in rod order; clusters not named in any
/// entry are false obstacles.
pub fn match_rods(clusters: &[Cluster], rods: &[Rod], gate_m: f64) -> Result<Vec<RodMatch>> {
    if !(gate_m.is_finite() && gate_m > 0.0) {
        return Err(Error::param(
            "gate_m",
            format!("must be finite and > 0, got {gate_m}"),
        ));
    }
    let mut pairs = Vec::new();
    for (r, rod) in rods.iter().enumerate() {
        for (c, cl) in clusters.iter().enumerate() {
            let d = rod.distance(cl.position_m);
            if d <= gate_m {
                pairs.push((d, r, c));
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut out: Vec<RodMatch> = (0..rods.len())
        .map(|rod| RodMatch {
            rod,
            cluster: None,
            error_m: None,
        })
        .collect();
    let mut used = vec![false; clusters.len()];
    for (d, r, c) in pairs {
        if out[r].cluster.is_none() && !used[c] {
            out[r].cluster = Some(c);
            out[r].error_m = Some(d);
            used[c] = true;
        }
    }
    Ok(out)
}

/// The true rods of a simulator `rods.json` (written by the `mapping`
/// scenario) and the mounting it assumes.
#[derive(Debug, Clone, PartialEq)]
pub struct RodsTruth {
    /// The rods, in file order.
    pub rods: Vec<Rod>,
    /// Rod diameters, mm.
    pub diameters_mm: Vec<f64>,
    /// The sensor mounting the file states.
    pub mounting: Mounting,
}

#[derive(Deserialize)]
struct RodsFile {
    rods: Vec<RodEntry>,
    sensor_in_body_rotation: [[f64; 3]; 3],
    sensor_in_body_offset_m: [f64; 3],
}

#[derive(Deserialize)]
struct RodEntry {
    x_m: f64,
    top_m: f64,
    diameter_mm: f64,
}

/// Reads a `rods.json` (rods along world y at `x_m` with their top at
/// `top_m`, and the sensor mounting). Missing or malformed files are errors.
pub fn read_rods_json(path: impl AsRef<Path>) -> Result<RodsTruth> {
    let path = path.as_ref();
    let s = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let f: RodsFile =
        serde_json::from_str(&s).map_err(|e| Error::format(path, Some(e.line()), e.to_string()))?;
    if f.rods
        .iter()
        .any(|r| !(r.x_m.is_finite() && r.top_m.is_finite() && r.diameter_mm.is_finite()))
    {
        return Err(Error::format(path, None, "non-finite rod position"));
    }
    let mounting = Mounting::new(f.sensor_in_body_rotation, f.sensor_in_body_offset_m)
        .map_err(|e| Error::format(path, None, e.to_string()))?;
    Ok(RodsTruth {
        rods: f
            .rods
            .iter()
            .map(|r| Rod::along_y(r.x_m, r.top_m))
            .collect(),
        diameters_mm: f.rods.iter().map(|r| r.diameter_mm).collect(),
        mounting,
    })
}

/// One perch as the sensor measured it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PerchReading {
    /// Chord position, mm (sensor frame).
    pub x_mm: f64,
    /// Force magnitude at the common press depth, N.
    pub force_n: f64,
}

/// The compliance decision over perches pressed by the same depth.
#[derive(Debug, Clone, PartialEq)]
pub struct PerchRanking {
    /// Stiffness rank of each input perch, in input order: 1 = stiffest
    /// (largest force); ranks are distinct, equal forces ranked in input
    /// order.
    pub ranks: Vec<usize>,
    /// Index of the stiffest perch.
    pub stiffest: usize,
    /// Sideways move (mm, along sensor x) that puts the sensor origin over
    /// the stiffest perch.
    pub move_mm: f64,
}

/// Ranks perches by stiffness: pressed by the same depth, the one pushing
/// back harder is stiffer (force = stiffness x depth). Errors on no perch or
/// a non-finite reading.
pub fn rank_perches(perches: &[PerchReading]) -> Result<PerchRanking> {
    if perches.is_empty() {
        return Err(Error::param("perches", "no perch to rank"));
    }
    if let Some(p) = perches
        .iter()
        .find(|p| !(p.x_mm.is_finite() && p.force_n.is_finite()))
    {
        return Err(Error::param("perches", format!("non-finite reading {p:?}")));
    }
    let mut order: Vec<usize> = (0..perches.len()).collect();
    // Largest force first; stable, so ties keep input order.
    order.sort_by(|&a, &b| perches[b].force_n.total_cmp(&perches[a].force_n));
    let mut ranks = vec![0; perches.len()];
    for (r, &i) in order.iter().enumerate() {
        ranks[i] = r + 1;
    }
    let stiffest = order[0];
    Ok(PerchRanking {
        ranks,
        stiffest,
        move_mm: perches[stiffest].x_mm,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_mounting_flips_y_and_z() {
        let m = Mounting::default();
        assert_eq!(m.to_body([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0]);
        assert!(
            Mounting::new(
                [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]],
                [0.0; 3]
            )
            .is_err()
        );
        assert!(
            Mounting::new(
                [[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                [0.0; 3]
            )
            .is_err()
        );
    }

    #[test]
    fn quarter_turn_about_z() {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let p = Pose::new([1.0, 0.0, 0.0], [h, 0.0, 0.0, h]).unwrap();
        let w = p.transform_point([1.0, 0.0, 0.0]);
        assert!((w[0] - 1.0).abs() < 1e-12 && (w[1] - 1.0).abs() < 1e-12 && w[2].abs() < 1e-12);
        assert!(Pose::new([0.0; 3], [0.0; 4]).is_err());
        assert!(Pose::new([f64::NAN, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]).is_err());
    }

    #[test]
    fn ranks_by_force() {
        let r = rank_perches(&[
            PerchReading {
                x_mm: -60.0,
                force_n: 1.4,
            },
            PerchReading {
                x_mm: 50.0,
                force_n: 2.9,
            },
        ])
        .unwrap();
        assert_eq!(r.ranks, vec![2, 1]);
        assert_eq!(r.stiffest, 1);
        assert_eq!(r.move_mm, 50.0);
        assert!(rank_perches(&[]).is_err());
    }
}
