//! Arbitrary bytes, written to a file, to every reader of the crate: each
//! must return `Ok` or an `Error`, never panic or allocate beyond the
//! formats' bounds (run with `-rss_limit_mb`).
#![no_main]

use libfuzzer_sys::fuzz_target;
use optical_tactile::calibration::Calibration;
use optical_tactile::io::{self, FrameRecord, RawContactRecord};

fuzz_target!(|data: &[u8]| {
    let path = std::env::temp_dir().join(format!("optical-tactile-fuzz-{}", std::process::id()));
    if std::fs::write(&path, data).is_err() {
        return;
    }
    let _ = io::read_gray(&path);
    let _ = io::read_flo(&path);
    let _ = io::read_npy_f64(&path);
    let _ = io::read_jsonl::<FrameRecord>(&path);
    let _ = io::read_jsonl::<FrameRecord<RawContactRecord>>(&path);
    let _ = io::read_tests_csv(&path);
    let _ = io::read_poses_csv(&path);
    let _ = Calibration::load(&path);
});
