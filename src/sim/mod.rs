//! Physics-based synthetic tactile sensor: elastic layer, markers, rendering,
//! scenarios.
//!
//! A [`SyntheticSensor`] is built from a [`SimConfig`] and a seed (which fixes
//! the random marker layout). For any set of rod [`Contact`]s given in the
//! sensor frame it computes each marker's displacement from linear elasticity
//! ([`elastic`]: Boussinesq and Cerruti solutions integrated over the rod's
//! Hertz footprint, with a rigid-base correction for the layer), maps it through
//! the camera model ([`camera`]: unrolled skin to pixels, with a mild
//! non-linearity) and re-renders every marker as a Gaussian spot at its moved
//! position ([`render`]), with shot and read noise, vignetting and a per-frame
//! brightness flicker. It also returns the true dense motion.

pub mod camera;
pub mod cli;
pub mod elastic;
mod render;
pub mod rng;
pub mod scenario;
mod sensor;

pub use camera::{Camera, Skin};
pub use elastic::Material;
pub use sensor::{Contact, MarkerConfig, NoiseConfig, Rendered, SimConfig, SyntheticSensor};
