//! Python bindings of `optical-tactile`: the extension module
//! `optical_tactile._native`, re-exported by the Python package
//! `optical_tactile` (python/optical_tactile/__init__.py).
//!
//! Frames come in as NumPy arrays and are read in place where their layout
//! allows ([`input`]); every call that processes data releases the GIL
//! ([`errors::detached`]); the library's errors become Python exceptions and
//! a panic never crosses into Python ([`errors`]).

pub mod blocks;
pub mod errors;
pub mod input;
pub mod params;
pub mod sensor;
pub mod sim;

use pyo3::prelude::*;

/// The native module: classes and functions, re-exported by `optical_tactile`.
#[pymodule]
#[pyo3(name = "_native")]
fn native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    errors::register(m)?;
    m.add_class::<sensor::Calibration>()?;
    m.add_class::<sensor::Sensor>()?;
    m.add_class::<sensor::Contact>()?;
    m.add_class::<sensor::RawContact>()?;
    m.add_class::<sensor::Sequence>()?;
    m.add_class::<blocks::Patch>()?;
    m.add_class::<sim::Press>()?;
    m.add_class::<sim::SyntheticSensor>()?;
    m.add_function(wrap_pyfunction!(sensor::read_image, m)?)?;
    m.add_function(wrap_pyfunction!(blocks::dis_flow, m)?)?;
    m.add_function(wrap_pyfunction!(blocks::nhhd, m)?)?;
    m.add_function(wrap_pyfunction!(blocks::segment, m)?)?;
    m.add_function(wrap_pyfunction!(sim::simulate, m)?)?;
    m.add_function(wrap_pyfunction!(sim::calibrate, m)?)?;
    m.add_function(wrap_pyfunction!(sim::evaluate, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
