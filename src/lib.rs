//! # optical-tactile
//!
//! Turns the camera images of a marker-based optical tactile sensor into every
//! contact's 3D location (mm) and 3D force (N), many contacts at once, in real
//! time; and ships a physics-based synthetic sensor so that all of it can be
//! tried, tested and calibrated without hardware.
//!
//! The pipeline (see the README and `SPEC.md`): crop and green channel →
//! dense optical flow against a fixed reference ([`flow`]) → segmentation into
//! contact patches ([`segment`]) → natural Helmholtz-Hodge decomposition per
//! patch ([`hhd`]) → raw contact quantities → calibrated location and force.
//!
//! ## Conventions
//! - Grayscale images are `ndarray::Array2<f32>` of shape `(height, width)` with
//!   values on the 8-bit scale `0.0..=255.0` (16-bit input is divided by 257).
//! - Flows are [`flow::FlowField`]: `u` along columns (image x), `v` along rows
//!   (image y), in pixels.
//! - Lengths in the sensor frame are in mm, forces in N; the sensor frame is
//!   `x` along the chord, `y` across the width, `z` out of the skin.
//!
//! ## Errors
//! Bad input never panics: every fallible call returns [`Result`] with an
//! [`Error`] that says what was expected and what came.

#![cfg_attr(docsrs, feature(doc_cfg))]

pub mod calibration;
pub mod capture;
pub mod contact;
pub mod error;
pub mod flow;
pub mod frame;
pub mod geometry;
pub mod hhd;
pub mod io;
pub mod segment;
pub mod sensor;
pub mod track;
pub mod viz;

pub use error::{Error, Result};
pub use flow::FlowField;
