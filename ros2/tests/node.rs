//! The node end to end: started in-process on the bundled press with the
//! bundled calibration, a subscriber in the same test receives its
//! contacts, wrenches, contact clouds and markers over the loopback (in a network namespace
//! of the test's own), and they match what the library gives on the same
//! frames, computed the way the `track` example does.

mod common;

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use clap::Parser as _;
use optical_tactile::capture::SequenceSource;
use optical_tactile::contact::Contact;
use optical_tactile::segment::SplitRule;
use optical_tactile::{Calibration, TactileSensor};
use optical_tactile_ros2::Node;
use optical_tactile_ros2::args::NodeArgs;
use optical_tactile_ros2::frame_msgs::contact_id;
use optical_tactile_ros2::msg::{
    Marker, MarkerArray, PointCloud2, RosMessage, TactileContacts, WrenchStamped,
};
use optical_tactile_ros2::ros::{self, Spinning};
use ros2_client::Subscription;
use serde::de::DeserializeOwned;

/// Within these the published values must equal the library's.
const POSITION_TOL_M: f64 = 1e-6;
const FORCE_TOL_N: f64 = 1e-6;

/// Every processed frame's contacts, as `track` computes them with its
/// default flags: the calibration's settings, split on, no filter,
/// re-referencing on, the first frame the reference.
fn expected() -> Vec<Vec<Contact>> {
    let root = common::root();
    let calibration = Calibration::load(root.join("fixtures/calibration.json")).unwrap();
    let mut sensor = TactileSensor::builder(calibration)
        .configure(|c| {
            c.extractor.split = Some(SplitRule::DEFAULT);
            c.tracker.filter = None;
            c.rereference.enabled = true;
        })
        .build()
        .unwrap();
    let mut frames = SequenceSource::open(root.join("fixtures/press")).unwrap();
    sensor
        .set_reference(&frames.next().unwrap().unwrap().image)
        .unwrap();
    frames
        .map(|f| {
            let f = f.unwrap();
            sensor.process(&f.image, f.t_s).unwrap().to_vec()
        })
        .collect()
}

fn subscribe<M: RosMessage + DeserializeOwned + 'static>(
    node: &mut Spinning,
    topic: &str,
) -> Subscription<M> {
    let qos = ros::sensor_data_qos(10);
    let t = node.topic::<M>(topic, &qos).unwrap();
    node.node.create_subscription::<M>(&t, None).unwrap()
}

fn take_all<M: DeserializeOwned + 'static>(s: &Subscription<M>, into: &mut Vec<M>) {
    while let Some((m, _info)) = s.take().expect("a readable sample") {
        into.push(m);
    }
}

#[test]
fn publishes_what_track_computes() {
    if !common::inside() {
        common::run_isolated("publishes_what_track_computes");
        return;
    }
    let want = expected();
    assert_eq!(want.len(), 7);
    assert!(want.iter().any(|c| c.len() >= 2), "the press has two rods");
    assert!(want.iter().any(Vec::is_empty), "and frames with no contact");

    let domain = common::domain_id().to_string();
    let root = common::root();
    let seq = root.join("fixtures/press");
    let cal = root.join("fixtures/calibration.json");
    let args = NodeArgs::try_parse_from([
        "optical_tactile_node",
        "--sequence",
        seq.to_str().unwrap(),
        "--calibration",
        cal.to_str().unwrap(),
        "--domain-id",
        &domain,
        "--frame-id",
        "skin",
        "--linger",
        "1",
    ])
    .unwrap();

    // The subscriber first, so that the node finds it.
    let context = ros::context(args.domain_id, false).unwrap();
    let mut listener = Spinning::new(&context, "/", "test_listener").unwrap();
    let contacts_sub = subscribe::<TactileContacts>(&mut listener, &args.contacts_topic);
    let wrench_sub = subscribe::<WrenchStamped>(&mut listener, &args.wrench_topic);
    let cloud_sub = subscribe::<PointCloud2>(&mut listener, &args.cloud_topic);
    let markers_sub = subscribe::<MarkerArray>(&mut listener, &args.markers_topic);

    // The node started, then its first frame only once the subscriber has
    // matched every publisher (and the node every subscription): no
    // message is lost to discovery still under way.
    let stop = Arc::new(AtomicBool::new(false));
    let node = Node::start(&args, Arc::clone(&stop)).expect("the node starts");
    let matched = Instant::now() + Duration::from_secs(60);
    loop {
        let seen = [
            contacts_sub.get_publisher_count(&listener.node),
            wrench_sub.get_publisher_count(&listener.node),
            cloud_sub.get_publisher_count(&listener.node),
            markers_sub.get_publisher_count(&listener.node),
        ];
        let counts = node.publisher().subscriber_counts();
        if seen.iter().chain(&counts).all(|&n| n > 0) {
            break;
        }
        assert!(
            Instant::now() < matched,
            "discovery: subscriber sees {seen:?} publishers, node {counts:?} subscribers"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    let (done_tx, done_rx) = mpsc::channel();
    let runner = std::thread::spawn(move || {
        let _ = done_tx.send(node.run(&stop));
    });

    let (mut contacts, mut wrenches, mut markers) = (Vec::new(), Vec::new(), Vec::new());
    let mut clouds = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut report = None;
    while Instant::now() < deadline {
        take_all(&contacts_sub, &mut contacts);
        take_all(&wrench_sub, &mut wrenches);
        take_all(&cloud_sub, &mut clouds);
        take_all(&markers_sub, &mut markers);
        if report.is_none() {
            if let Ok(r) = done_rx.try_recv() {
                report = Some(r.expect("the node runs"));
            }
        }
        let all = [contacts.len(), wrenches.len(), clouds.len(), markers.len()]
            .iter()
            .all(|&n| n >= want.len());
        if all && report.is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    eprintln!(
        "received {} contacts, {} wrench, {} cloud, {} markers messages",
        contacts.len(),
        wrenches.len(),
        clouds.len(),
        markers.len()
    );
    let report = report.expect("the node ends within the time limit");
    runner.join().unwrap();
    assert_eq!(report.published, 7, "{report}");
    assert_eq!(
        (report.skipped, report.dropped, report.non_finite),
        (0, 0, 0)
    );
    assert_eq!(contacts.len(), want.len(), "contacts messages received");
    assert_eq!(wrenches.len(), want.len(), "wrench messages received");
    assert_eq!(markers.len(), want.len(), "marker messages received");
    assert_eq!(clouds.len(), want.len(), "contact cloud messages received");

    let mut last_stamp = None;
    for (k, want) in want.iter().enumerate() {
        let got = &contacts[k];
        assert_eq!(got.header.frame_id, "skin");
        assert!(got.header.stamp.sec > 0);
        assert!(last_stamp <= Some(got.header.stamp), "stamps in order");
        last_stamp = Some(got.header.stamp);
        assert_eq!(got.contacts.len(), want.len(), "frame {k}: contacts");
        let mut net = [0.0; 3];
        for (g, w) in got.contacts.iter().zip(want) {
            assert_eq!(contact_id(&g.name), Some(w.id), "frame {k}: id");
            assert_eq!(g.header, got.header);
            let p = [g.position.x, g.position.y, g.position.z];
            for i in 0..3 {
                assert!(
                    (p[i] - w.location_mm[i] * 1e-3).abs() <= POSITION_TOL_M,
                    "frame {k} contact {}: position {p:?} m, library {:?} mm",
                    w.id,
                    w.location_mm
                );
            }
            let f = [g.wrench.force.x, g.wrench.force.y, g.wrench.force.z];
            for i in 0..3 {
                assert!(
                    (f[i] - w.force_n[i]).abs() <= FORCE_TOL_N,
                    "frame {k} contact {}: force {f:?} N, library {:?} N",
                    w.id,
                    w.force_n
                );
                net[i] += w.force_n[i];
            }
        }
        let ws = &wrenches[k];
        assert_eq!(ws.header, got.header);
        let f = ws.wrench.force;
        for (g, w) in [f.x, f.y, f.z].iter().zip(net) {
            assert!(
                (g - w).abs() <= FORCE_TOL_N,
                "frame {k}: net force {f:?}, library {net:?}"
            );
        }

        // The cloud: one point per contact, in the same order, with the
        // force sigma of the bundled calibration's uncertainty model.
        let cloud = &clouds[k];
        assert_eq!(cloud.header, got.header);
        assert_eq!(cloud.width as usize, want.len(), "frame {k}: cloud points");
        for (i, w) in want.iter().enumerate() {
            let v = |name| cloud.value(i, name, 0).expect(name);
            assert_eq!(v("id") as u64, w.id);
            assert_eq!(v("held_frames") as u32, w.missed);
            assert_eq!(v("out_of_domain") != 0.0, w.out_of_domain);
            assert_eq!(v("fallback") != 0.0, w.fallback);
            for (j, name) in ["x", "y", "z"].into_iter().enumerate() {
                assert!((v(name) - w.location_mm[j] * 1e-3).abs() <= POSITION_TOL_M);
            }
            let sigma = w.force_sigma_n.expect("the bundled calibration has sigmas");
            for (j, (f, s)) in [("fx", "fx_sigma"), ("fy", "fy_sigma"), ("fz", "fz_sigma")]
                .into_iter()
                .enumerate()
            {
                assert!((v(f) - w.force_n[j]).abs() <= FORCE_TOL_N);
                assert!(v(s) > 0.0 && (v(s) - sigma[j]).abs() <= FORCE_TOL_N);
            }
        }

        let m = &markers[k].markers;
        assert_eq!(m.len(), 1 + 2 * want.len(), "frame {k}: markers");
        assert_eq!(m[0].action, Marker::DELETEALL);
        let added = |kind| {
            m.iter()
                .filter(|m| m.action == Marker::ADD && m.kind == kind)
                .collect::<Vec<_>>()
        };
        let (spheres, arrows) = (added(Marker::SPHERE), added(Marker::ARROW));
        assert_eq!((spheres.len(), arrows.len()), (want.len(), want.len()));
        for (s, w) in spheres.iter().zip(want) {
            assert_eq!(s.id as u64, w.id);
            assert!((s.pose.position.x - w.location_mm[0] * 1e-3).abs() <= POSITION_TOL_M);
        }
    }
}
