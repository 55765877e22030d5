//! The node's parameters: command-line flags (clap), also given the ROS way
//! as `--ros-args -p name:=value` ([`translate_ros_args`]).

use std::path::PathBuf;

use clap::builder::{PossibleValuesParser, TypedValueParser};
use clap::{ArgAction, Parser};
use optical_tactile::exposure::ExposureCompensation;
use optical_tactile::flow::dis::DisPreset;
use optical_tactile::frame::{Channel, Roi};
use optical_tactile::segment::ThresholdPreset;

/// The calibration used unless `--calibration` names another: the
/// repository's, of the simulated reference sensor.
pub const DEFAULT_CALIBRATION: &str =
    concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/calibration.json");

/// Largest `--qos-depth`.
pub const MAX_QOS_DEPTH: usize = 100;
/// Largest `--rate` and `--fps`, frames per second.
pub const MAX_RATE: f64 = 1000.0;
/// Largest wait, linger or lifetime, seconds.
pub const MAX_WAIT_S: f64 = 3600.0;
/// Largest ROS domain id (the ports of higher ids do not fit the UDP range).
pub const MAX_DOMAIN_ID: u16 = 232;

/// The ROS 2 node of the optical tactile sensor: reads a V4L2 camera or an
/// image sequence, runs the tactile sensor, and publishes per frame the
/// contacts (tactile_msgs/TactileContacts), the net wrench
/// (geometry_msgs/WrenchStamped), RViz markers (visualization_msgs/MarkerArray)
/// and optionally the debug image (sensor_msgs/Image).
#[derive(Parser, Debug, Clone)]
#[command(
    name = "optical_tactile_node",
    after_help = "Every flag is also a ROS parameter: `--ros-args -p frame_id:=tactile -p \
                  filter:=true` (underscores for dashes; `-r __node:=NAME`, `-r __ns:=/NS` and \
                  `-r TOPIC:=NEW` remap the node and its topics). The first frame is the \
                  unloaded reference. Exit status: 0; 1 on an error (a calibration that does \
                  not load, a camera that is gone); 2 on a usage error or if some frame was \
                  skipped (named on stderr)."
)]
pub struct NodeArgs {
    // --- where frames come from
    /// Read frames from this folder of PNG images (in name order) instead of a camera.
    #[arg(long, value_name = "DIR", conflicts_with = "device")]
    pub sequence: Option<PathBuf>,
    /// Pace the sequence at N frames per second, as a camera would deliver
    /// it (frames the processing cannot keep up with are dropped); 0: every
    /// frame, as fast as the processing goes.
    #[arg(long, value_name = "FPS", default_value_t = 0.0, value_parser = rate)]
    pub rate: f64,
    /// V4L2 camera device (needs the `v4l` feature) [default: /dev/video0 without --sequence].
    #[arg(long, value_name = "PATH")]
    pub device: Option<String>,
    /// Requested camera frame size.
    #[arg(long, value_name = "WxH", default_value = "1920x1080", value_parser = size)]
    pub size: (u32, u32),
    /// Requested camera frame rate.
    #[arg(long, value_name = "FPS", default_value_t = 50, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub fps: u32,
    /// How often to reopen a camera that stopped delivering frames (1 s
    /// apart) before giving up with an error.
    #[arg(long, value_name = "N", default_value_t = 3, value_parser = clap::value_parser!(u32).range(0..=1000))]
    pub reopen: u32,
    /// Frames waiting between capture and processing (1 or 2); a frame
    /// arriving while they are full is dropped.
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=2))]
    pub queue: u8,
    /// Stop after N frames [default: the end of the sequence, or never for a camera].
    #[arg(long, value_name = "N")]
    pub frames: Option<u64>,

    // --- what runs on them
    /// Calibration file.
    #[arg(long, value_name = "FILE", default_value = DEFAULT_CALIBRATION)]
    pub calibration: PathBuf,
    /// No calibration: publish each frame's patches in pixels with their raw
    /// displacements (frame `<frame_id>_raw_px`), no wrench, no marker.
    #[arg(long)]
    pub raw: bool,
    /// Crop of the camera frame [default: the calibration's; with --raw, the whole frame].
    #[arg(long, value_name = "x,y,w,h", value_parser = roi)]
    pub crop: Option<Roi>,
    /// Use a --crop that differs from the calibration's.
    #[arg(long)]
    pub force_crop: bool,
    /// Segmentation thresholds preset [default: the calibration's].
    #[arg(long, value_name = "PRESET", value_parser = threshold_preset())]
    pub thresholds: Option<ThresholdPreset>,
    /// DIS flow preset [default: the calibration's].
    #[arg(long, value_name = "PRESET", ignore_case = true, value_parser = dis_preset())]
    pub preset: Option<DisPreset>,
    /// Cut a patch holding several contacts side by side.
    #[arg(long, value_name = "on|off", default_value = "on", action = ArgAction::Set, value_parser = on_off)]
    pub split: bool,
    /// Camera exposure compensation: auto, gain-offset, offset or off
    /// [default: the calibration's; auto with --raw].
    #[arg(long, value_name = "MODE", value_parser = exposure)]
    pub exposure: Option<ExposureCompensation>,
    /// Which channel of colour frames becomes the grey image.
    #[arg(long, value_name = "green|luma", default_value = "green", value_parser = channel)]
    pub channel: Channel,
    /// Kalman filter on the tracked contacts.
    #[arg(long, value_name = "on|off", default_value = "off", action = ArgAction::Set, value_parser = on_off)]
    pub filter: bool,
    /// Take a fresh reference after a quiet spell with small flow.
    #[arg(long, value_name = "on|off", default_value = "on", action = ArgAction::Set, value_parser = on_off)]
    pub rereference: bool,
    /// Frames a contact no longer detected is still reported with its last
    /// estimate [default: 2, the tracker's].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(0..=1000))]
    pub hold: Option<u32>,

    // --- ROS 2
    /// Node name.
    #[arg(long, value_name = "NAME", default_value = "optical_tactile")]
    pub node_name: String,
    /// Node namespace (relative topic names are in it).
    #[arg(long, value_name = "NS", default_value = "/")]
    pub namespace: String,
    /// ROS domain id.
    #[arg(long, value_name = "ID", env = "ROS_DOMAIN_ID", default_value_t = 0, value_parser = clap::value_parser!(u16).range(0..=MAX_DOMAIN_ID as i64))]
    pub domain_id: u16,
    /// Use the loopback interface only (127.0.0.1; it must have the
    /// MULTICAST flag for discovery: `ip link set lo multicast on`).
    #[arg(long)]
    pub localhost_only: bool,
    /// The tf2 frame of every message: the sensor frame.
    #[arg(long, value_name = "FRAME", default_value = "tactile_sensor")]
    pub frame_id: String,
    /// Topic of the contacts (tactile_msgs/msg/TactileContacts).
    #[arg(long, value_name = "TOPIC", default_value = "tactile_contacts")]
    pub contacts_topic: String,
    /// Topic of the net wrench (geometry_msgs/msg/WrenchStamped).
    #[arg(long, value_name = "TOPIC", default_value = "tactile_wrench")]
    pub wrench_topic: String,
    /// Topic of the contact cloud (sensor_msgs/msg/PointCloud2): every
    /// contact's position, force, force sigma, id and flags.
    #[arg(long, value_name = "TOPIC", default_value = "tactile_contact_cloud")]
    pub cloud_topic: String,
    /// Topic of the RViz markers (visualization_msgs/msg/MarkerArray).
    #[arg(long, value_name = "TOPIC", default_value = "tactile_markers")]
    pub markers_topic: String,
    /// Topic of the debug image (sensor_msgs/msg/Image).
    #[arg(long, value_name = "TOPIC", default_value = "tactile_debug_image")]
    pub image_topic: String,
    /// Publish the debug panel (flow with the patch contours, divergent
    /// field, potential, image) as an rgb8 image.
    #[arg(long, value_name = "on|off", default_value = "off", action = ArgAction::Set, value_parser = on_off)]
    pub debug_image: bool,
    /// History depth of the publishers (sensor-data QoS: best effort, volatile, keep last N).
    #[arg(long, value_name = "N", default_value_t = 5, value_parser = depth)]
    pub qos_depth: usize,
    /// Before the first frame, wait up to S seconds until every topic has a subscriber.
    #[arg(long, value_name = "S", default_value_t = 0.0, value_parser = seconds)]
    pub wait_for_subscribers: f64,
    /// After the last frame, keep the node up S seconds so that the last
    /// messages reach their subscribers.
    #[arg(long, value_name = "S", default_value_t = 0.5, value_parser = seconds)]
    pub linger: f64,
    /// Diameter of a contact's sphere marker, m.
    #[arg(long, value_name = "M", default_value_t = 0.004, value_parser = marker_size)]
    pub sphere_diameter: f64,
    /// Length of a force arrow per newton, m/N.
    #[arg(long, value_name = "M_PER_N", default_value_t = 0.02, value_parser = marker_size)]
    pub arrow_scale: f64,
    /// Lifetime of a marker, s (a DELETEALL also clears them every frame).
    #[arg(long, value_name = "S", default_value_t = 0.5, value_parser = seconds)]
    pub marker_lifetime: f64,
    /// No log line per dropped frame (the counts are still printed at exit).
    #[arg(long, short)]
    pub quiet: bool,
}

fn parse_f64_in(s: &str, lo: f64, hi: f64, what: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|x| (lo..=hi).contains(x))
        .ok_or_else(|| format!("expected {what} in [{lo}, {hi}], got `{s}`"))
}

fn rate(s: &str) -> Result<f64, String> {
    parse_f64_in(s, 0.0, MAX_RATE, "frames per second")
}

fn seconds(s: &str) -> Result<f64, String> {
    parse_f64_in(s, 0.0, MAX_WAIT_S, "seconds")
}

fn marker_size(s: &str) -> Result<f64, String> {
    parse_f64_in(s, 0.0, 10.0, "a length")
}

fn depth(s: &str) -> Result<usize, String> {
    s.parse::<usize>()
        .ok()
        .filter(|d| (1..=MAX_QOS_DEPTH).contains(d))
        .ok_or_else(|| format!("expected a depth in 1..={MAX_QOS_DEPTH}, got `{s}`"))
}

fn size(s: &str) -> Result<(u32, u32), String> {
    s.split_once('x')
        .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
        .filter(|&(w, h): &(u32, u32)| (1..=16384).contains(&w) && (1..=16384).contains(&h))
        .ok_or_else(|| format!("expected WxH (whole numbers in 1..=16384), got `{s}`"))
}

fn roi(s: &str) -> Result<Roi, String> {
    Roi::parse(s).map_err(|e| e.to_string())
}

fn on_off(s: &str) -> Result<bool, String> {
    match s {
        "on" | "true" | "True" | "1" => Ok(true),
        "off" | "false" | "False" | "0" => Ok(false),
        _ => Err(format!("expected on or off, got `{s}`")),
    }
}

fn exposure(s: &str) -> Result<ExposureCompensation, String> {
    ExposureCompensation::parse(s).map_err(|e| e.to_string())
}

fn channel(s: &str) -> Result<Channel, String> {
    match s.to_ascii_lowercase().as_str() {
        "green" => Ok(Channel::Green),
        "luma" => Ok(Channel::Luma),
        _ => Err(format!("expected green or luma, got `{s}`")),
    }
}

fn threshold_preset() -> impl TypedValueParser<Value = ThresholdPreset> {
    PossibleValuesParser::new(ThresholdPreset::ALL.map(ThresholdPreset::name))
        .try_map(|s| s.parse::<ThresholdPreset>().map_err(|e| e.to_string()))
}

fn dis_preset() -> impl TypedValueParser<Value = DisPreset> {
    PossibleValuesParser::new(DisPreset::ALL.map(DisPreset::name))
        .try_map(|s| DisPreset::parse(&s).map_err(|e| e.to_string()))
}

/// The switches that take no value on the command line: as ROS parameters
/// they take `true` (the flag given) or `false` (left out).
const SWITCHES: [&str; 4] = ["raw", "force_crop", "localhost_only", "quiet"];

/// The topic flags, by the default topic name a `-r FROM:=TO` remaps.
const TOPICS: [(&str, &str); 5] = [
    ("tactile_contacts", "--contacts-topic"),
    ("tactile_wrench", "--wrench-topic"),
    ("tactile_contact_cloud", "--cloud-topic"),
    ("tactile_markers", "--markers-topic"),
    ("tactile_debug_image", "--image-topic"),
];

/// The command line with its `--ros-args ... [--]` sections turned into
/// flags: `-p name:=value` (or `--param`) becomes `--name value` (with
/// dashes for underscores; a switch becomes `--name` for `true` and
/// nothing for `false`), `-r __node:=NAME` `--node-name NAME`, `-r
/// __ns:=/NS` `--namespace /NS`, and `-r TOPIC:=NEW` for one of the
/// node's default topic names the matching topic flag. Errors name an
/// argument of a ROS section the node does not take (a parameters file,
/// a log level, ...). `args` includes the program name.
pub fn translate_ros_args(args: &[String]) -> Result<Vec<String>, String> {
    let mut out = Vec::with_capacity(args.len());
    let mut it = args.iter();
    while let Some(a) = it.next() {
        if a != "--ros-args" {
            out.push(a.clone());
            continue;
        }
        while let Some(a) = it.next() {
            match a.as_str() {
                "--" => break,
                "--ros-args" => continue,
                "-p" | "--param" => {
                    let p = it
                        .next()
                        .ok_or_else(|| format!("--ros-args: {a} needs name:=value"))?;
                    let (name, value) = p.split_once(":=").ok_or_else(|| {
                        format!("--ros-args: expected name:=value after {a}, got `{p}`")
                    })?;
                    let flag = format!("--{}", name.replace('_', "-"));
                    if SWITCHES.contains(&name) {
                        if on_off(value).map_err(|e| format!("--ros-args -p {name}: {e}"))? {
                            out.push(flag);
                        }
                    } else {
                        out.push(flag);
                        out.push(value.to_string());
                    }
                }
                "-r" | "--remap" => {
                    let r = it
                        .next()
                        .ok_or_else(|| format!("--ros-args: {a} needs from:=to"))?;
                    let (from, to) = r.split_once(":=").ok_or_else(|| {
                        format!("--ros-args: expected from:=to after {a}, got `{r}`")
                    })?;
                    let flag = match from {
                        "__node" | "__name" => "--node-name",
                        "__ns" => "--namespace",
                        _ => TOPICS
                            .iter()
                            .find(|(t, _)| *t == from.trim_start_matches("~/"))
                            .map(|(_, f)| *f)
                            .ok_or_else(|| {
                                format!("--ros-args: cannot remap `{from}` (not one of the node's topics)")
                            })?,
                    };
                    out.push(flag.to_string());
                    out.push(to.to_string());
                }
                other => {
                    return Err(format!(
                        "--ros-args: `{other}` is not supported (only -p name:=value and -r from:=to)"
                    ));
                }
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(v: &[&str]) -> Vec<String> {
        v.iter().map(|x| x.to_string()).collect()
    }

    #[test]
    fn ros_parameters_become_flags() {
        let got = translate_ros_args(&s(&[
            "node",
            "--sequence",
            "seq",
            "--ros-args",
            "-p",
            "frame_id:=arm_skin",
            "-p",
            "filter:=true",
            "--param",
            "raw:=true",
            "-p",
            "force_crop:=false",
            "-r",
            "__node:=skin",
            "-r",
            "tactile_wrench:=/arm/wrench",
            "--",
            "--quiet",
        ]))
        .unwrap();
        assert_eq!(
            got,
            s(&[
                "node",
                "--sequence",
                "seq",
                "--frame-id",
                "arm_skin",
                "--filter",
                "true",
                "--raw",
                "--node-name",
                "skin",
                "--wrench-topic",
                "/arm/wrench",
                "--quiet",
            ])
        );
        let a = NodeArgs::try_parse_from(&got).unwrap();
        assert_eq!(a.frame_id, "arm_skin");
        assert!(a.filter && a.raw && a.quiet);
        assert_eq!(a.wrench_topic, "/arm/wrench");
    }

    #[test]
    fn unsupported_ros_arguments_are_named() {
        for bad in [
            &["n", "--ros-args", "--params-file", "p.yaml"][..],
            &["n", "--ros-args", "-p", "frame_id"],
            &["n", "--ros-args", "-p"],
            &["n", "--ros-args", "-r", "chatter:=x"],
            &["n", "--ros-args", "-p", "raw:=maybe"],
        ] {
            let e = translate_ros_args(&s(bad)).unwrap_err();
            assert!(e.starts_with("--ros-args"), "{e}");
        }
    }

    #[test]
    fn defaults_and_bounds() {
        let a = NodeArgs::try_parse_from(["n"]).unwrap();
        assert_eq!(a.qos_depth, 5);
        assert_eq!(a.queue, 1);
        assert!(!a.debug_image && !a.filter && a.rereference && a.split);
        for bad in [
            &["n", "--qos-depth", "0"][..],
            &["n", "--qos-depth", "101"],
            &["n", "--rate", "-1"],
            &["n", "--rate", "NaN"],
            &["n", "--queue", "3"],
            &["n", "--domain-id", "233"],
            &["n", "--size", "0x10"],
            &["n", "--linger", "inf"],
            &["n", "--sequence", "a", "--device", "b"],
        ] {
            assert!(NodeArgs::try_parse_from(bad).is_err(), "{bad:?}");
        }
    }
}
