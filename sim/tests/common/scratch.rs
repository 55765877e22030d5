//! Scratch output directories for tests that write scenarios.

use std::path::PathBuf;

/// A path for a scenario's output directory, not yet created, inside a
/// fresh directory named `ot-{name}-` and a unique suffix under the
/// system's temporary directory. The returned guard removes that directory
/// and everything in it when dropped, whether the test passed or failed.
pub fn tmp(name: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::Builder::new()
        .prefix(&format!("ot-{name}-"))
        .tempdir()
        .unwrap();
    let out = dir.path().join("out");
    (dir, out)
}
