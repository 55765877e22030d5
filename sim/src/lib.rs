//! Physics-based synthetic tactile sensor: elastic layer, markers, rendering,
//! scenarios.
//!
//! A [`SyntheticSensor`] is built from a [`SimConfig`] and a seed (which fixes
//! the random marker layout). For any set of rod [`Press`]es given in the
//! sensor frame it computes each marker's displacement from linear elasticity
//! ([`elastic`]: Boussinesq and Cerruti solutions integrated over the rod's
//! Hertz footprint, with a rigid-base correction for the layer), maps it through
//! the camera model ([`camera`]: unrolled skin to pixels, with a mild
//! non-linearity) and re-renders every marker as a Gaussian spot at its moved
//! position (module `render`), with shot and read noise, vignetting and a per-frame
//! brightness flicker. It also returns the true dense motion.
//!
//! [`SimConfig::default`] is the paper's curved strip pressed by rods;
//! [`SimConfig::fingertip`] a flat fingertip sensor (a GelSight-Mini-like
//! dot grid on a thin gel, behind a distorting lens) pressed by round tips
//! ([`Tip`]: spheres, flat punches, fingertips) anywhere in `x` and `y`.
//!
//! [`scenario`] writes whole sequences (frames, `truth.jsonl`, `.flo` truth
//! flow, `tests.csv`, `poses.csv`) in the formats of docs/formats.md; the `simulate`
//! example is its command line.
//!
//! Units and frames: contacts are given in the sensor frame (chord position
//! `x_mm`, force `[Fx, Fy, Fz]` in N, a press has `Fz < 0`); internally the
//! skin is unrolled (arc length `s = R asin(x / R)`, across `y`, depth into the
//! gel) and the force is projected onto the local surface frame at the contact.
//! Images are `Array2<f32>` on the 8-bit scale; flows are in pixels.
//!
//! ```
//! use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};
//! let sensor = SyntheticSensor::new(SimConfig::default(), 1)?;
//! // A 5 mm rod pressing 1.5 N straight down, 30 mm left of centre.
//! let rod = Press::rod(-30.0, [0.0, 0.0, -1.5], 5.0);
//! let loaded = sensor.render_indexed(1, &[rod], true)?;
//! let truth = loaded.flow.expect("asked for the flow");
//! assert_eq!(truth.size(), (1600, 200));
//! # Ok::<(), optical_tactile::Error>(())
//! ```

pub mod camera;
mod config;
pub mod elastic;
pub mod evaluate;
pub mod experiments;
pub mod mapping;
mod render;
pub mod rng;
pub mod scenario;
mod sensor;

pub use camera::{CameraModel, Skin};
pub use config::{
    ContactLight, DotGrid, ExposureChanges, FINGERTIP_GRID, FINGERTIP_LENGTH_MM,
    FINGERTIP_WIDTH_MM, MarkerConfig, MarkerLayout, NoiseConfig, Rendered, SensorOptions,
    SimConfig,
};
pub use elastic::Material;
pub use sensor::{Press, SyntheticSensor, Tip};
