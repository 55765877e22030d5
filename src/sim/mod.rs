//! Physics-based synthetic tactile sensor: elastic layer, markers, rendering, scenarios.

pub mod camera;
pub mod elastic;
pub mod rng;
