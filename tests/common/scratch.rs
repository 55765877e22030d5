//! Scratch directories for tests that write files.

/// A fresh, empty directory named `optical-tactile-{name}-` and a unique
/// suffix under the system's temporary directory, removed when the
/// returned guard is dropped, whether the test passed or failed.
pub fn scratch(name: &str) -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix(&format!("optical-tactile-{name}-"))
        .tempdir()
        .unwrap()
}
