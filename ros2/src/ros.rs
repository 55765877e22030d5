//! The ROS 2 side: a participant, a node, one publisher per topic, and the
//! node's spinner (discovery, parameters) on a thread of its own.

use std::net::{IpAddr, Ipv4Addr};
use std::thread;
use std::time::{Duration, Instant};

use ros2_client::rustdds::policy::{Durability, History, Reliability};
use ros2_client::rustdds::{DomainParticipantBuilder, QosPolicies, QosPolicyBuilder};
use ros2_client::{Context, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher};
use serde::Serialize;

use crate::frame_msgs::FrameMessages;
use crate::msg::{Image, MarkerArray, PointCloud2, RosMessage, TactileContacts, WrenchStamped};
use crate::node::Publish;

/// Where and how to publish.
#[derive(Debug, Clone)]
pub struct RosConfig {
    /// ROS domain id.
    pub domain_id: u16,
    /// Only the loopback interface.
    pub localhost_only: bool,
    /// Node name.
    pub node_name: String,
    /// Node namespace.
    pub namespace: String,
    /// Contacts topic.
    pub contacts_topic: String,
    /// Wrench topic.
    pub wrench_topic: String,
    /// Contact cloud topic.
    pub cloud_topic: String,
    /// Markers topic.
    pub markers_topic: String,
    /// Debug image topic, `None` when the image is off.
    pub image_topic: Option<String>,
    /// History depth.
    pub qos_depth: usize,
}

impl RosConfig {
    /// The ROS settings of `args`.
    pub fn from_args(a: &crate::args::NodeArgs) -> RosConfig {
        RosConfig {
            domain_id: a.domain_id,
            localhost_only: a.localhost_only
                || std::env::var("ROS_LOCALHOST_ONLY").is_ok_and(|v| v == "1"),
            node_name: a.node_name.clone(),
            namespace: a.namespace.clone(),
            contacts_topic: a.contacts_topic.clone(),
            wrench_topic: a.wrench_topic.clone(),
            cloud_topic: a.cloud_topic.clone(),
            markers_topic: a.markers_topic.clone(),
            image_topic: a.debug_image.then(|| a.image_topic.clone()),
            qos_depth: a.qos_depth,
        }
    }
}

/// The sensor-data QoS profile: best effort, volatile, keep the last `depth`.
pub fn sensor_data_qos(depth: usize) -> QosPolicies {
    QosPolicyBuilder::new()
        .reliability(Reliability::BestEffort)
        .durability(Durability::Volatile)
        .history(History::KeepLast {
            depth: i32::try_from(depth).unwrap_or(i32::MAX),
        })
        .build()
}

/// A ROS 2 participant for `domain_id`, on every interface or on the
/// loopback only.
pub fn context(domain_id: u16, localhost_only: bool) -> Result<Context, String> {
    let mut b = DomainParticipantBuilder::new(domain_id);
    if localhost_only {
        b = b.with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)]);
    }
    let participant = b
        .build()
        .map_err(|e| format!("cannot start the DDS participant (domain {domain_id}): {e}"))?;
    Context::from_domain_participant(participant)
        .map_err(|e| format!("cannot start the ROS 2 context: {e}"))
}

/// A ROS 2 node named `name` in `namespace` with its spinner running on a
/// thread; [`Spinning::stop`] (or drop) stops it.
pub struct Spinning {
    /// The node.
    pub node: Node,
    handle: Option<thread::JoinHandle<()>>,
}

impl Spinning {
    /// Starts the node and its spinner.
    pub fn new(context: &Context, namespace: &str, name: &str) -> Result<Spinning, String> {
        let node_name = NodeName::new(namespace, name)
            .map_err(|e| format!("bad node name {namespace} {name}: {e:?}"))?;
        let mut node = context
            .new_node(node_name, NodeOptions::new().enable_rosout(false))
            .map_err(|e| format!("cannot create the ROS 2 node: {e:?}"))?;
        let spinner = node
            .spinner()
            .map_err(|e| format!("cannot start the node's spinner: {e}"))?;
        let handle = thread::Builder::new()
            .name("ros2-spinner".into())
            .spawn(move || {
                if let Err(e) = futures::executor::block_on(spinner.spin()) {
                    eprintln!("ROS 2 spinner stopped: {e}");
                }
            })
            .map_err(|e| format!("cannot start the spinner thread: {e}"))?;
        Ok(Spinning {
            node,
            handle: Some(handle),
        })
    }

    /// A topic of message type `M` named `topic` (relative names are in the
    /// node's namespace).
    pub fn topic<M: RosMessage>(
        &mut self,
        topic: &str,
        qos: &QosPolicies,
    ) -> Result<ros2_client::rustdds::Topic, String> {
        let name = Name::parse(topic).map_err(|e| format!("bad topic name `{topic}`: {e:?}"))?;
        let (package, ty) = M::TYPE;
        self.node
            .create_topic(&name, MessageTypeName::new(package, ty), qos)
            .map_err(|e| format!("cannot create topic {topic}: {e}"))
    }

    /// Stops the spinner and waits for its thread.
    pub fn stop(&mut self) {
        if let Some(h) = self.handle.take() {
            self.node.stop_spinner();
            let _ = h.join();
        }
    }
}

impl Drop for Spinning {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The node's publishers.
pub struct RosPublisher {
    contacts: Publisher<TactileContacts>,
    wrench: Publisher<WrenchStamped>,
    cloud: Publisher<PointCloud2>,
    markers: Publisher<MarkerArray>,
    image: Option<Publisher<Image>>,
    // Dropped after the publishers: the node, then the participant.
    node: Spinning,
    _context: Context,
}

fn publisher<M: RosMessage + Serialize>(
    node: &mut Spinning,
    topic: &str,
    qos: &QosPolicies,
) -> Result<Publisher<M>, String> {
    let t = node.topic::<M>(topic, qos)?;
    node.node
        .create_publisher(&t, None)
        .map_err(|e| format!("cannot publish on {topic}: {e}"))
}

impl RosPublisher {
    /// Starts the participant, the node and its publishers.
    pub fn new(c: &RosConfig) -> Result<RosPublisher, String> {
        let context = context(c.domain_id, c.localhost_only)?;
        let mut node = Spinning::new(&context, &c.namespace, &c.node_name)?;
        let qos = sensor_data_qos(c.qos_depth);
        Ok(RosPublisher {
            contacts: publisher(&mut node, &c.contacts_topic, &qos)?,
            wrench: publisher(&mut node, &c.wrench_topic, &qos)?,
            cloud: publisher(&mut node, &c.cloud_topic, &qos)?,
            markers: publisher(&mut node, &c.markers_topic, &qos)?,
            image: c
                .image_topic
                .as_deref()
                .map(|t| publisher(&mut node, t, &qos))
                .transpose()?,
            node,
            _context: context,
        })
    }

    /// How many subscribers each topic has (contacts, wrench, contact
    /// cloud, markers, image).
    pub fn subscriber_counts(&self) -> Vec<usize> {
        let n = &self.node.node;
        let mut v = vec![
            self.contacts.get_subscription_count(n),
            self.wrench.get_subscription_count(n),
            self.cloud.get_subscription_count(n),
            self.markers.get_subscription_count(n),
        ];
        if let Some(i) = &self.image {
            v.push(i.get_subscription_count(n));
        }
        v
    }

    /// Waits up to `timeout` until every topic has a subscriber; `false` if
    /// some has none by then.
    pub fn wait_for_subscribers(&self, timeout: Duration) -> bool {
        let end = Instant::now() + timeout;
        loop {
            if self.subscriber_counts().iter().all(|&n| n > 0) {
                return true;
            }
            if Instant::now() >= end {
                return false;
            }
            thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Publish for RosPublisher {
    fn publish(&mut self, m: FrameMessages) -> Result<(), String> {
        // Best effort: a write does not wait for subscribers.
        self.contacts
            .publish(m.contacts)
            .map_err(|e| format!("cannot publish the contacts: {e}"))?;
        if let Some(w) = m.wrench {
            self.wrench
                .publish(w)
                .map_err(|e| format!("cannot publish the wrench: {e}"))?;
        }
        if let Some(c) = m.cloud {
            self.cloud
                .publish(c)
                .map_err(|e| format!("cannot publish the contact cloud: {e}"))?;
        }
        self.markers
            .publish(m.markers)
            .map_err(|e| format!("cannot publish the markers: {e}"))?;
        if let (Some(p), Some(i)) = (&self.image, m.image) {
            p.publish(i)
                .map_err(|e| format!("cannot publish the debug image: {e}"))?;
        }
        Ok(())
    }
}
