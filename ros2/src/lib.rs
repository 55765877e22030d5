//! # optical-tactile-ros2
//!
//! The ROS 2 node of the optical tactile sensor, in pure Rust (the
//! `ros2-client` crate on RustDDS: no ROS installation needed). It reads a
//! V4L2 camera (feature `v4l`) or an image sequence, runs the calibrated
//! [`TactileSensor`](optical_tactile::TactileSensor) (or the raw sensor),
//! and publishes per frame:
//!
//! | topic (default) | type | what |
//! |---|---|---|
//! | `tactile_contacts` | `tactile_msgs/msg/TactileContacts` | every contact: position (m), normal, force (N), in the sensor frame; `name` = `contact_<id>` |
//! | `tactile_wrench` | `geometry_msgs/msg/WrenchStamped` | the net wrench about the sensor frame's origin |
//! | `tactile_contact_cloud` | `sensor_msgs/msg/PointCloud2` | every contact with its force sigma, id and flags, read by field name |
//! | `tactile_markers` | `visualization_msgs/msg/MarkerArray` | DELETEALL, then a sphere and a force arrow per contact |
//! | `tactile_debug_image` | `sensor_msgs/msg/Image` | the debug panel (`--debug-image on`) |
//!
//! The binary `optical_tactile_node` is [`run`] behind a command line
//! ([`args::NodeArgs`]). The repository's `docs/ros2.md` shows how to run
//! it beside the ROS 2 tools.
//!
//! - [`msg`]: the messages, with their finiteness checks.
//! - [`frame_msgs`]: one frame's messages from the sensor's contacts.
//! - [`node`]: capture thread, bounded queue, processing.
//! - [`ros`]: the participant, node and publishers.

pub mod args;
pub mod frame_msgs;
pub mod msg;
pub mod node;
pub mod ros;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use args::NodeArgs;
use node::{Capture, Pipeline, Processing, Report, SourceSpec};
use ros::{RosConfig, RosPublisher};

/// How long the node waits, once every topic has a subscriber, before the
/// first frame: discovery runs both ways, and a subscriber that has not yet
/// seen the node's publishers would miss the first messages.
pub const SETTLE: Duration = Duration::from_secs(1);

/// Runs the node as `args` ask until the sequence ends, `frames` frames were
/// read, or `stop` is set (Ctrl-C): [`Node::start`], then [`Node::run`].
pub fn run(args: &NodeArgs, stop: Arc<AtomicBool>) -> Result<Report, String> {
    Node::start(args, Arc::clone(&stop))?.run(&stop)
}

/// A started node: its source opened, its sensor built, its publishers up;
/// no frame read yet.
pub struct Node {
    pipeline: Pipeline,
    capture: Capture,
    publisher: RosPublisher,
    processing: Processing,
    wait_for_subscribers: f64,
    linger: f64,
}

impl Node {
    /// Builds the sensor (loads the calibration), opens the source, then
    /// starts the ROS 2 participant and the publishers, and says so on
    /// stderr. An error in the first two ends the run before any network
    /// traffic. `stop` also ends the capture.
    pub fn start(args: &NodeArgs, stop: Arc<AtomicBool>) -> Result<Node, String> {
        let pipeline = Pipeline::build(args)?;
        let processing = Processing::from_args(args);
        let capture = Capture::open(SourceSpec::from_args(args), args.channel, &processing, stop)?;
        let ros = RosConfig::from_args(args);
        let publisher = RosPublisher::new(&ros)?;
        eprintln!(
            "{}: {}, {}; publishing on domain {}{} in frame {}",
            ros.node_name,
            capture.description,
            pipeline.describe(),
            ros.domain_id,
            if ros.localhost_only {
                " (loopback only)"
            } else {
                ""
            },
            args.frame_id
        );
        Ok(Node {
            pipeline,
            capture,
            publisher,
            processing,
            wait_for_subscribers: args.wait_for_subscribers,
            linger: args.linger,
        })
    }

    /// The publishers (their subscriber counts).
    pub fn publisher(&self) -> &RosPublisher {
        &self.publisher
    }

    /// Waits for subscribers if asked (then [`SETTLE`]), processes and
    /// publishes every frame until the source ends or `stop` is set, keeps
    /// the node up for the linger time, and returns the counts.
    pub fn run(mut self, stop: &AtomicBool) -> Result<Report, String> {
        if self.wait_for_subscribers > 0.0 {
            let wait = Duration::from_secs_f64(self.wait_for_subscribers);
            if self.publisher.wait_for_subscribers(wait) {
                std::thread::sleep(SETTLE);
            } else {
                eprintln!(
                    "not every topic has a subscriber after {} s (subscribers per topic: {:?}); going on",
                    self.wait_for_subscribers,
                    self.publisher.subscriber_counts()
                );
            }
        }
        let report = node::process_frames(
            &mut self.capture,
            &mut self.pipeline,
            &mut self.publisher,
            &self.processing,
            stop,
        )?;
        let end = Instant::now() + Duration::from_secs_f64(self.linger);
        while Instant::now() < end && !stop.load(Ordering::Relaxed) {
            std::thread::sleep(Duration::from_millis(20));
        }
        Ok(report)
    }
}
