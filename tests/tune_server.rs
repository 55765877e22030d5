//! The `tune` example's HTTP server and page routes (examples/tune), built
//! here with their unit tests so that `cargo test` runs them: hostile raw
//! requests, bad controls, saves outside the save directory or over a file.
//! The page itself is tested in a browser by tests/browser/tune.cjs.

#[path = "../examples/cli_support/mod.rs"]
mod cli_support;

#[allow(dead_code)]
#[path = "../examples/tune/app.rs"]
mod app;

#[allow(dead_code)]
#[path = "../examples/tune/http.rs"]
mod http;
