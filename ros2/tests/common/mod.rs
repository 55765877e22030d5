//! Runs a test in a network namespace of its own, where the only interface
//! is the loopback with multicast on: RustDDS discovery (UDP multicast)
//! then works with no network, and no packet of the test leaves the
//! machine or meets another run's.

#![allow(dead_code)]

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Set in the re-executed test process, inside the namespace.
const INSIDE: &str = "OPTICAL_TACTILE_ROS2_TEST_NETNS";

/// How long a test in a namespace may take before it is killed and fails.
pub const LIMIT: Duration = Duration::from_secs(240);

/// The loopback set up for multicast, then the command `"$@"`.
const SETUP: &str = "ip link set lo up && ip link set lo multicast on && \
                     ip route add 224.0.0.0/4 dev lo && exec \"$@\"";

/// Whether this process is the re-executed test inside its namespace.
pub fn inside() -> bool {
    std::env::var_os(INSIDE).is_some()
}

/// `unshare` arguments that give a new network namespace here: as root, or
/// as a user through a user namespace.
fn unshare_args() -> Vec<&'static str> {
    for args in [&["--net"][..], &["--user", "--map-root-user", "--net"]] {
        let ok = Command::new("unshare")
            .args(args)
            .args(["--", "sh", "-c", "ip link set lo up"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if ok {
            return args.to_vec();
        }
    }
    panic!(
        "these tests need a network namespace of their own (`unshare --net` or `unshare --user \
         --map-root-user --net`, from util-linux, and `ip` from iproute2): neither works here"
    );
}

/// Runs the test `name` of this test binary again inside a new network
/// namespace and fails if it fails there (or takes longer than [`LIMIT`]).
/// Call from the test when not [`inside`].
pub fn run_isolated(name: &str) {
    let exe = std::env::current_exe().expect("the test binary's path");
    let mut child = Command::new("unshare")
        .args(unshare_args())
        .args(["--", "sh", "-c", SETUP, "sh"])
        .arg(exe)
        .args([name, "--exact", "--nocapture", "--test-threads=1"])
        .env(INSIDE, "1")
        .spawn()
        .expect("unshare starts");
    let end = Instant::now() + LIMIT;
    loop {
        match child.try_wait().expect("wait for the test process") {
            Some(status) => {
                assert!(
                    status.success(),
                    "{name} failed in its network namespace: {status}"
                );
                return;
            }
            None if Instant::now() > end => {
                let _ = child.kill();
                let _ = child.wait();
                panic!("{name} took longer than {LIMIT:?} in its network namespace");
            }
            None => std::thread::sleep(Duration::from_millis(50)),
        }
    }
}

/// A ROS domain id for this run (from the process id).
pub fn domain_id() -> u16 {
    1 + (std::process::id() % 200) as u16
}

/// The repository's root.
pub fn root() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}
