//! Mapping by touch: transforms, clustering (against a brute-force oracle),
//! rod matching, perch ranking and bad input.

use std::collections::HashMap;
use std::path::Path;

use optical_tactile::Error;
use optical_tactile::io::{ContactRecord, FrameRecord, PoseRow};
use optical_tactile_sim::mapping::{
    Cluster, MapOptions, Mounting, PerchReading, Pose, Rod, cluster, map_touches, match_rods,
    poses_by_frame, rank_perches, read_rods_json, sensor_to_world, world_contacts,
};
use proptest::prelude::*;
use proptest::test_runner::RngSeed;

#[path = "common/scratch.rs"]
mod scratch;

fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        rng_seed: RngSeed::Fixed(0x4D41_5050),
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

fn d(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// The oracle: connected components of the "within radius" graph by
/// repeated relabelling until nothing changes (O(n^3), obviously right).
fn brute_clusters(points: &[[f64; 3]], r: f64) -> Vec<Vec<usize>> {
    let n = points.len();
    let mut label: Vec<usize> = (0..n).collect();
    loop {
        let mut changed = false;
        for i in 0..n {
            for j in 0..n {
                if d(points[i], points[j]) <= r && label[j] < label[i] {
                    label[i] = label[j];
                    changed = true;
                }
            }
        }
        if !changed {
            break;
        }
    }
    let mut groups: Vec<Vec<usize>> = Vec::new();
    let mut seen: Vec<usize> = Vec::new();
    for i in 0..n {
        match seen.iter().position(|&l| l == label[i]) {
            Some(g) => groups[g].push(i),
            None => {
                seen.push(label[i]);
                groups.push(vec![i]);
            }
        }
    }
    groups
}

fn members(c: &[Cluster]) -> Vec<Vec<usize>> {
    c.iter().map(|c| c.members.clone()).collect()
}

fn points_strategy(max: usize) -> impl Strategy<Value = Vec<[f64; 3]>> {
    proptest::collection::vec(
        (0.0..1.0f64, 0.0..0.3f64, 0.0..0.3f64).prop_map(|(x, y, z)| [x, y, z]),
        0..max,
    )
}

proptest! {
    #![proptest_config(config(64))]

    #[test]
    fn clustering_matches_the_oracle(points in points_strategy(40), r in 0.01..0.3f64) {
        let got = cluster(&points, r).unwrap();
        prop_assert_eq!(members(&got), brute_clusters(&points, r));
        // Summaries: mean, count, RMS spread.
        for c in &got {
            prop_assert_eq!(c.count, c.members.len());
            for k in 0..3 {
                let m = c.members.iter().map(|&i| points[i][k]).sum::<f64>() / c.count as f64;
                prop_assert!((m - c.position_m[k]).abs() < 1e-12);
            }
            let rms = (c.members.iter().map(|&i| d(points[i], c.position_m).powi(2)).sum::<f64>()
                / c.count as f64).sqrt();
            prop_assert!((rms - c.spread_m).abs() < 1e-12);
        }
    }

    #[test]
    fn clustering_ignores_input_order(points in points_strategy(30), r in 0.01..0.3f64, seed in 0u64..1000) {
        // A deterministic shuffle, then map member indices back.
        let n = points.len();
        let mut perm: Vec<usize> = (0..n).collect();
        let mut s = seed;
        for i in (1..n).rev() {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            perm.swap(i, (s >> 33) as usize % (i + 1));
        }
        let shuffled: Vec<[f64; 3]> = perm.iter().map(|&i| points[i]).collect();
        let mut a: Vec<Vec<usize>> = members(&cluster(&points, r).unwrap());
        let mut b: Vec<Vec<usize>> = cluster(&shuffled, r)
            .unwrap()
            .iter()
            .map(|c| {
                let mut m: Vec<usize> = c.members.iter().map(|&k| perm[k]).collect();
                m.sort_unstable();
                m
            })
            .collect();
        a.sort();
        b.sort();
        prop_assert_eq!(a, b);
    }

    #[test]
    fn rigid_transforms_preserve_distances(
        p in (-200.0..200.0f64, -20.0..20.0f64, 0.0..160.0f64),
        q in (-200.0..200.0f64, -20.0..20.0f64, 0.0..160.0f64),
        t in (-5.0..5.0f64, -5.0..5.0f64, 0.0..3.0f64),
        quat in (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64),
    ) {
        prop_assume!(quat.0.abs() + quat.1.abs() + quat.2.abs() + quat.3.abs() > 0.1);
        let pose = Pose::new([t.0, t.1, t.2], [quat.0, quat.1, quat.2, quat.3]).unwrap();
        let m = Mounting::default();
        let (p, q) = ([p.0, p.1, p.2], [q.0, q.1, q.2]);
        let (wp, wq) = (sensor_to_world(p, &pose, &m), sensor_to_world(q, &pose, &m));
        prop_assert!((d(wp, wq) - 1e-3 * d(p, q)).abs() < 1e-9);
        // The quaternion is normalised and the rotation keeps handedness:
        // (a x b) . c is preserved.
        let n = pose.quaternion().iter().map(|v| v * v).sum::<f64>();
        prop_assert!((n - 1.0).abs() < 1e-12);
        let o = sensor_to_world([0.0; 3], &pose, &m);
        let e = |v: [f64; 3]| {
            let w = sensor_to_world(v, &pose, &m);
            [(w[0] - o[0]) * 1e3, (w[1] - o[1]) * 1e3, (w[2] - o[2]) * 1e3]
        };
        let (a, b, c) = (e([1.0, 0.0, 0.0]), e([0.0, 1.0, 0.0]), e([0.0, 0.0, 1.0]));
        let cross = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
        let triple = cross[0] * c[0] + cross[1] * c[1] + cross[2] * c[2];
        prop_assert!((triple - 1.0).abs() < 1e-9);
    }

    #[test]
    fn identity_pose_and_mounting_only_scale(p in (-200.0..200.0f64, -20.0..20.0f64, -50.0..160.0f64)) {
        let w = sensor_to_world([p.0, p.1, p.2], &Pose::identity(), &Mounting::identity());
        prop_assert!((w[0] - p.0 * 1e-3).abs() < 1e-15);
        prop_assert!((w[1] - p.1 * 1e-3).abs() < 1e-15);
        prop_assert!((w[2] - p.2 * 1e-3).abs() < 1e-15);
    }
}

#[test]
fn one_point_is_one_cluster_with_no_spread() {
    let c = cluster(&[[0.3, -0.1, 1.0]], 0.01).unwrap();
    assert_eq!(c.len(), 1);
    assert_eq!(c[0].count, 1);
    assert_eq!(c[0].position_m, [0.3, -0.1, 1.0]);
    assert_eq!(c[0].spread_m, 0.0);
    assert!(cluster(&[], 0.01).unwrap().is_empty());
}

#[test]
fn chains_join_and_the_radius_is_inclusive() {
    // 0 - 1 - 2 chain (0.04 apart), 3 alone; 0 and 2 are 0.08 apart.
    let p = [
        [0.0, 0.0, 0.0],
        [0.04, 0.0, 0.0],
        [0.08, 0.0, 0.0],
        [0.2, 0.0, 0.0],
    ];
    let c = cluster(&p, 0.04 + 1e-12).unwrap();
    assert_eq!(members(&c), vec![vec![0, 1, 2], vec![3]]);
    let c = cluster(&p, 0.039).unwrap();
    assert_eq!(c.len(), 4);
}

#[test]
fn bad_cluster_input_is_an_error() {
    for r in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        assert!(matches!(
            cluster(&[[0.0; 3]], r),
            Err(Error::InvalidParameter { .. })
        ));
    }
    let e = cluster(&[[0.0; 3], [f64::NAN, 0.0, 0.0]], 0.1).unwrap_err();
    assert!(e.to_string().contains("point 1"), "{e}");
}

#[test]
fn the_mapping_scenario_geometry_lands_on_the_rod() {
    // The simulator's mapping scenario: body at x = rod - x_mm/1000, level;
    // the skin point z_mm below the body touches the rod's top.
    let (rod_x, top) = (0.9, 1.0);
    for x_mm in [-100.0, -20.0, 0.0, 45.0, 110.0] {
        let z_mm = (220.0f64 * 220.0 - x_mm * x_mm).sqrt() - 60.0;
        let pose = Pose::new(
            [rod_x - x_mm * 1e-3, 0.0, top + z_mm * 1e-3],
            [1.0, 0.0, 0.0, 0.0],
        )
        .unwrap();
        let w = sensor_to_world([x_mm, 0.0, z_mm], &pose, &Mounting::default());
        assert!(Rod::along_y(rod_x, top).distance(w) < 1e-12, "{w:?}");
    }
}

#[test]
fn rod_distance_is_perpendicular() {
    let r = Rod::along_y(1.0, 2.0);
    assert!((r.distance([1.003, 55.0, 1.996]) - 0.005).abs() < 1e-12);
    let p = Rod::point([1.0, 2.0, 3.0]);
    assert!((p.distance([1.0, 2.0, 4.0]) - 1.0).abs() < 1e-12);
}

fn at(p: [f64; 3]) -> Cluster {
    Cluster {
        position_m: p,
        count: 1,
        spread_m: 0.0,
        members: vec![0],
    }
}

/// Brute force: the one-to-one assignment within the gate that matches the
/// most rods, then the smallest total error.
fn brute_match(clusters: &[Cluster], rods: &[Rod], gate: f64) -> (usize, f64) {
    fn rec(r: usize, used: &mut Vec<bool>, c: &[Cluster], rods: &[Rod], gate: f64) -> (usize, f64) {
        if r == rods.len() {
            return (0, 0.0);
        }
        let mut best = rec(r + 1, used, c, rods, gate);
        for k in 0..c.len() {
            let e = rods[r].distance(c[k].position_m);
            if !used[k] && e <= gate {
                used[k] = true;
                let (n, s) = rec(r + 1, used, c, rods, gate);
                used[k] = false;
                if n + 1 > best.0 || (n + 1 == best.0 && s + e < best.1) {
                    best = (n + 1, s + e);
                }
            }
        }
        best
    }
    rec(0, &mut vec![false; clusters.len()], clusters, rods, gate)
}

proptest! {
    #![proptest_config(config(64))]

    /// When rods are far apart compared with the clusters' errors, greedy
    /// matching is the best assignment.
    #[test]
    fn matching_agrees_with_brute_force_on_separated_rods(
        errs in proptest::collection::vec((-0.02..0.02f64, -0.02..0.02f64), 1..5),
        extra in 0usize..2,
    ) {
        let rods: Vec<Rod> = (0..errs.len()).map(|k| Rod::along_y(0.5 * k as f64, 1.0)).collect();
        let mut clusters: Vec<Cluster> = errs
            .iter()
            .enumerate()
            .rev()
            .map(|(k, e)| at([0.5 * k as f64 + e.0, 0.3, 1.0 + e.1]))
            .collect();
        for j in 0..extra {
            clusters.push(at([10.0 + j as f64, 0.0, 1.0]));
        }
        let m = match_rods(&clusters, &rods, 0.1).unwrap();
        let (n, total) = brute_match(&clusters, &rods, 0.1);
        let got_n = m.iter().filter(|x| x.cluster.is_some()).count();
        let got_total: f64 = m.iter().filter_map(|x| x.error_m).sum();
        prop_assert_eq!(got_n, n);
        prop_assert!((got_total - total).abs() < 1e-12);
        for x in &m {
            let e = errs[x.rod];
            prop_assert!((x.error_m.unwrap() - (e.0 * e.0 + e.1 * e.1).sqrt()).abs() < 1e-12);
        }
    }
}

#[test]
fn matching_is_one_to_one_and_gated() {
    let rods = [
        Rod::along_y(0.0, 1.0),
        Rod::along_y(0.01, 1.0),
        Rod::along_y(5.0, 1.0),
    ];
    let clusters = [at([0.004, 0.0, 1.0])];
    let m = match_rods(&clusters, &rods, 0.05).unwrap();
    // Rod 0 (4 mm away) takes the cluster; rod 1 (6 mm) is left without one.
    assert_eq!(m[0].cluster, Some(0));
    assert_eq!(m[1].cluster, None);
    assert_eq!(m[2].cluster, None);
    assert!(match_rods(&clusters, &rods, 0.0).is_err());
}

fn rec(frame: &str, contacts: &[(f64, f64)]) -> FrameRecord {
    FrameRecord {
        frame: frame.into(),
        t_s: 0.0,
        contacts: contacts
            .iter()
            .map(|&(x, fz)| ContactRecord {
                x_mm: x,
                z_mm: 150.0,
                fz_n: fz,
                ..Default::default()
            })
            .collect(),
        latency_ms: None,
    }
}

fn pose_row(frame: &str, x: f64, q: [f64; 4]) -> PoseRow {
    PoseRow {
        frame: frame.into(),
        t_s: 0.0,
        x_m: x,
        y_m: 0.0,
        z_m: 1.2,
        qw: q[0],
        qx: q[1],
        qy: q[2],
        qz: q[3],
    }
}

#[test]
fn world_contacts_use_each_frames_pose() {
    let path = Path::new("poses.csv");
    let rows = [
        pose_row("000000.png", 0.0, [1.0, 0.0, 0.0, 0.0]),
        pose_row("000001.png", 0.5, [1.0, 0.0, 0.0, 0.0]),
    ];
    let poses = poses_by_frame(&rows, path).unwrap();
    let frames = [
        rec("000000.png", &[]),
        rec("000001.png", &[(10.0, -1.0), (20.0, -0.1)]),
        rec("000002.png", &[]), // no pose, no contact: fine
    ];
    let w = world_contacts(&frames, &poses, &Mounting::default(), 0.5, path).unwrap();
    assert_eq!(w.len(), 1, "the 0.1 N touch is below min_force");
    assert!((w[0].position_m[0] - 0.51).abs() < 1e-12);
    assert!((w[0].position_m[2] - 1.05).abs() < 1e-12);
    assert_eq!(w[0].force_n, 1.0);
}

#[test]
fn frames_without_poses_and_bad_rows_are_errors() {
    let path = Path::new("seq/poses.csv");
    let poses: HashMap<String, Pose> = HashMap::new();
    let frames = [rec("000003.png", &[(10.0, -1.0)])];
    let e = world_contacts(&frames, &poses, &Mounting::default(), 0.0, path).unwrap_err();
    let s = e.to_string();
    assert!(
        s.contains("000003.png") && s.contains("seq/poses.csv"),
        "{s}"
    );

    let dup = [
        pose_row("a.png", 0.0, [1.0, 0.0, 0.0, 0.0]),
        pose_row("a.png", 0.0, [1.0, 0.0, 0.0, 0.0]),
    ];
    let e = poses_by_frame(&dup, path).unwrap_err();
    assert!(matches!(e, Error::Format { line: Some(3), .. }), "{e}");
    let zero = [pose_row("a.png", 0.0, [0.0; 4])];
    assert!(matches!(
        poses_by_frame(&zero, path),
        Err(Error::Format { line: Some(2), .. })
    ));
    let nan = [pose_row("a.png", f64::NAN, [1.0, 0.0, 0.0, 0.0])];
    assert!(poses_by_frame(&nan, path).is_err());
}

#[test]
fn rods_json_reads_and_rejects_bad_files() {
    let (_dir_guard, dir) = scratch::tmp("mapping");
    std::fs::create_dir_all(&dir).unwrap();
    let good = dir.join("rods.json");
    std::fs::write(
        &good,
        r#"{"rods":[{"x_m":0.4,"top_m":1.0,"diameter_mm":10.0},{"x_m":0.9,"top_m":1.0,"diameter_mm":5.0}],
            "sensor_in_body_rotation":[[1,0,0],[0,-1,0],[0,0,-1]],"sensor_in_body_offset_m":[0,0,0],"note":"x"}"#,
    )
    .unwrap();
    let t = read_rods_json(&good).unwrap();
    assert_eq!(t.rods, vec![Rod::along_y(0.4, 1.0), Rod::along_y(0.9, 1.0)]);
    assert_eq!(t.diameters_mm, vec![10.0, 5.0]);
    assert_eq!(t.mounting, Mounting::default());

    let bad = dir.join("bad.json");
    std::fs::write(&bad, r#"{"rods":[{"x_m":0.4}]}"#).unwrap();
    assert!(matches!(read_rods_json(&bad), Err(Error::Format { .. })));
    std::fs::write(
        &bad,
        r#"{"rods":[],"sensor_in_body_rotation":[[1,0,0],[0,1,0],[0,0,-1]],"sensor_in_body_offset_m":[0,0,0]}"#,
    )
    .unwrap();
    assert!(
        matches!(read_rods_json(&bad), Err(Error::Format { .. })),
        "a reflection is no mounting"
    );
    assert!(matches!(
        read_rods_json(dir.join("missing.json")),
        Err(Error::Io { .. })
    ));
}

#[test]
fn perch_ranking() {
    let p = [
        PerchReading {
            x_mm: -60.0,
            force_n: 1.5,
        },
        PerchReading {
            x_mm: 50.0,
            force_n: 3.0,
        },
        PerchReading {
            x_mm: 0.0,
            force_n: 2.0,
        },
    ];
    let r = rank_perches(&p).unwrap();
    assert_eq!(r.ranks, vec![3, 1, 2]);
    assert_eq!((r.stiffest, r.move_mm), (1, 50.0));
    let tie = rank_perches(&[
        PerchReading {
            x_mm: 1.0,
            force_n: 2.0,
        },
        PerchReading {
            x_mm: 2.0,
            force_n: 2.0,
        },
    ])
    .unwrap();
    assert_eq!(tie.ranks, vec![1, 2]);
    assert!(
        rank_perches(&[PerchReading {
            x_mm: f64::NAN,
            force_n: 1.0
        }])
        .is_err()
    );
}

#[test]
fn map_touches_filters_and_clusters() {
    let path = Path::new("poses.csv");
    let rows = [
        pose_row("a.png", 0.0, [1.0, 0.0, 0.0, 0.0]),
        pose_row("b.png", 0.001, [1.0, 0.0, 0.0, 0.0]),
        pose_row("c.png", 1.0, [1.0, 0.0, 0.0, 0.0]),
    ];
    let poses = poses_by_frame(&rows, path).unwrap();
    // Two touches 1 mm apart, one far away, one too light.
    let frames = [
        rec("a.png", &[(0.0, -1.0)]),
        rec("b.png", &[(0.0, -1.0), (60.0, -0.2)]),
        rec("c.png", &[(0.0, -1.0)]),
    ];
    let m = Mounting::default();
    let opts = MapOptions::default();
    let map = map_touches(&frames, &poses, &m, &opts, path).unwrap();
    assert_eq!(map.touches.len(), 3);
    assert_eq!(members(&map.clusters), vec![vec![0, 1], vec![2]]);
    let two = MapOptions {
        min_count: 2,
        ..opts
    };
    let map = map_touches(&frames, &poses, &m, &two, path).unwrap();
    assert_eq!(members(&map.clusters), vec![vec![0, 1]]);
    let all = MapOptions {
        min_force_n: 0.0,
        ..opts
    };
    assert_eq!(
        map_touches(&frames, &poses, &m, &all, path)
            .unwrap()
            .touches
            .len(),
        4
    );
    for bad in [
        MapOptions {
            min_count: 0,
            ..opts
        },
        MapOptions {
            min_force_n: f64::NAN,
            ..opts
        },
        MapOptions {
            radius_m: 0.0,
            ..opts
        },
    ] {
        assert!(matches!(
            map_touches(&frames, &poses, &m, &bad, path),
            Err(Error::InvalidParameter { .. })
        ));
    }
}
