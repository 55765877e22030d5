//! # optical-tactile
//!
//! Every contact's 3D location (mm) and 3D force (N), many contacts at once,
//! in real time, from the camera images of a marker-based optical tactile
//! sensor: a camera films markers inside a soft skin, a press moves them, and
//! this crate turns that motion into contacts.
//!
//! ## Where to start
//! Load the [`Calibration`] of your sensor, build a [`TactileSensor`] from it
//! with [`TactileSensor::from_calibration`] (crop, thresholds and flow
//! settings come from the calibration; [`TactileSensor::builder`] overrides
//! them), give it an unloaded reference frame, then feed it frames:
//!
//! ```
//! use optical_tactile::{Calibration, SequenceSource, TactileSensor};
//!
//! let calibration = Calibration::load("fixtures/calibration.json")?;
//! let mut sensor = TactileSensor::from_calibration(calibration)?;
//! let mut frames = SequenceSource::open("fixtures/press")?;
//! let reference = frames.next().expect("a first frame")?;
//! sensor.set_reference(&reference.image)?;
//! for frame in frames {
//!     let frame = frame?;
//!     for c in sensor.process(&frame.image, frame.t_s)? {
//!         println!(
//!             "{}: contact {} at x = {:.1} mm, F = ({:.2}, {:.2}, {:.2}) N",
//!             frame.name, c.id, c.location_mm[0], c.force_n[0], c.force_n[1], c.force_n[2]
//!         );
//!     }
//! }
//! # Ok::<(), optical_tactile::Error>(())
//! ```
//!
//! Frames are `ndarray::Array2<f32>` grayscale images; [`frame`] converts
//! `image` crate buffers and raw camera buffers (gray, RGB, BGR, YUYV; 8 or 16
//! bit) into them, with `_into` variants that reuse a buffer. A
//! [`SequenceSource`] reads a directory of PNG frames; `capture::v4l`
//! (feature `v4l`) a V4L2 camera. Without a calibration,
//! [`sensor::ContactExtractor`] gives each patch's raw quantities in pixels.
//!
//! ## The pipeline, one module per stage
//! ```text
//! frame ─▶ capture ─▶ frame (crop, green) ─▶ flow::Dis ─▶ segment ─▶ hhd::NaturalHhd ─▶ contact ─▶ calibration ─▶ track ─▶ Contact
//! ```
//! 1. [`capture`]: frames from a directory or a camera; [`frame`]: crop to the
//!    sensing area, green channel (or luma) as f32.
//! 2. [`flow`]: dense optical flow against the reference frame (our own Dense
//!    Inverse Search, OpenCV's presets plus finer ones).
//! 3. [`segment`]: the flow's magnitude thresholded, eroded, dilated; external
//!    contours; one box per contact patch.
//! 4. [`hhd`]: the natural Helmholtz-Hodge decomposition of each patch's flow
//!    (FFT, plans cached).
//! 5. [`contact`]: each patch's raw quantities (contact point, shear and normal
//!    displacement, potential range) and the contact's location.
//! 6. [`calibration`]: the fitted maps to millimetres and newtons, and
//!    [`calibration::fit`], which fits them from a characterization dataset.
//! 7. [`track`]: identity over time, hysteresis, smoothing, safe re-referencing.
//! 8. [`sensor`]: [`TactileSensor`] composes all of it; every stage is also
//!    usable alone.
//!
//! Beside them: [`io`] reads and writes the file formats (image sequences,
//! `.flo`, `.npy`, JSON Lines contacts, characterization `tests.csv`,
//! `poses.csv`), [`geometry`] describes the skin, [`viz`] draws debug pictures.
//! The repository's `docs/` folder describes the pipeline step by step
//! (`docs/pipeline.md`), every file format (`docs/formats.md`) and how to
//! calibrate your own sensor (`docs/calibration.md`). A physics-based
//! synthetic sensor to try all of it without hardware is the companion crate
//! `optical-tactile-sim`.
//!
//! ## Conventions
//! - Grayscale images are `ndarray::Array2<f32>` of shape `(height, width)` with
//!   values on the 8-bit scale `0.0..=255.0` (16-bit input is divided by 257).
//! - Flows are [`FlowField`]: `u` along columns (image x), `v` along rows
//!   (image y), in pixels.
//! - Lengths in the sensor frame are in mm, forces in N; the sensor frame is
//!   `x` along the chord, `y` across the width, `z` out of the skin; a press
//!   into the skin has `Fz < 0`.
//!
//! ## Errors
//! Bad input never panics: every fallible call returns [`Result`] with an
//! [`Error`] that says what was expected and what came.
//!
//! ## Features
//! | feature | what |
//! |---|---|
//! | `v4l` | `capture::v4l`: frames from a V4L2 camera (Linux; needs libclang to build) |

#![cfg_attr(docsrs, feature(doc_cfg))]

// The stages, in the order the data flows.
pub mod capture;
pub mod frame;

pub mod exposure;

pub mod flow;

pub mod segment;

pub mod hhd;

pub mod contact;

pub mod calibration;

pub mod track;

pub mod sensor;

// Beside the stages.
pub mod error;
pub mod geometry;
pub mod io;
pub mod markers;
pub mod viz;

pub use calibration::Calibration;
pub use capture::{Frame, FrameSource, SequenceSource};
pub use contact::Contact;
pub use error::{Error, Result};
pub use flow::FlowField;
pub use frame::{Channel, Roi};
pub use segment::{ThresholdPreset, Thresholds};
pub use sensor::{SensorBuilder, SensorConfig, TactileSensor};

/// The README's code blocks, run as doctests so that the documented main
/// path is checked by `cargo test`.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
