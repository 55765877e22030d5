//! `optical_tactile_node`: the ROS 2 node of the optical tactile sensor
//! (`--help` lists its parameters; the repository's docs/ros2.md shows how
//! to run it).

use std::io::Write as _;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use clap::Parser as _;
use optical_tactile_ros2::args::{NodeArgs, translate_ros_args};

fn main() -> ExitCode {
    let argv: Vec<String> = std::env::args().collect();
    let argv = match translate_ros_args(&argv) {
        Ok(a) => a,
        Err(e) => {
            let _ = writeln!(std::io::stderr(), "error: {e}");
            return ExitCode::from(2);
        }
    };
    let args = NodeArgs::parse_from(argv);
    let stop = Arc::new(AtomicBool::new(false));
    let handler_stop = Arc::clone(&stop);
    if let Err(e) = ctrlc::set_handler(move || handler_stop.store(true, Ordering::Relaxed)) {
        let _ = writeln!(std::io::stderr(), "warning: no Ctrl-C handler: {e}");
    }
    match optical_tactile_ros2::run(&args, stop) {
        Ok(report) => {
            let _ = writeln!(std::io::stderr(), "{}: {report}", args.node_name);
            if report.skipped > 0 {
                ExitCode::from(2)
            } else {
                ExitCode::SUCCESS
            }
        }
        Err(e) => {
            let _ = writeln!(std::io::stderr(), "error: {e}");
            ExitCode::FAILURE
        }
    }
}
