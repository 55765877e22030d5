//! Parameters given from Python: thresholds, flow presets, crops.

use optical_tactile::contact::profile::Relocation;
use optical_tactile::exposure::ExposureCompensation;
use optical_tactile::flow::dis::{DisParams, DisPreset};
use optical_tactile::frame::Roi;
use optical_tactile::segment::{Shape, ThresholdPreset, Thresholds};
use optical_tactile::sensor::MAX_LIGHT_BOX_PX;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyString};

use crate::errors::Failure;

/// Thresholds from a preset name (`"low"`, `"mid"`, `"high"`) or a dict with
/// some of `magnitude`, `sum`, `erode`, `dilate`, `shape` (`"rect"`,
/// `"cross"`, `"ellipse"`); missing keys come from `base`.
pub fn thresholds(obj: &Bound<'_, PyAny>, base: Thresholds) -> Result<Thresholds, Failure> {
    if let Ok(s) = obj.cast::<PyString>() {
        let name = s.to_string();
        let preset: ThresholdPreset = name.parse()?;
        return Ok(preset.into());
    }
    let Ok(d) = obj.cast::<PyDict>() else {
        return Err(Failure::Type(
            "thresholds must be \"low\", \"mid\", \"high\" or a dict of magnitude, sum, erode, \
             dilate, shape"
                .into(),
        ));
    };
    let mut t = base;
    for (k, v) in d.iter() {
        let key: String = k
            .extract()
            .map_err(|_| Failure::Type("threshold keys must be strings".into()))?;
        let bad = |e: PyErr| Failure::Type(format!("thresholds[{key:?}]: {e}"));
        match key.as_str() {
            "magnitude" => t.magnitude = v.extract().map_err(bad)?,
            "sum" => t.sum = v.extract().map_err(bad)?,
            "erode" => t.erode = v.extract().map_err(bad)?,
            "dilate" => t.dilate = v.extract().map_err(bad)?,
            "shape" => {
                let s: String = v.extract().map_err(bad)?;
                t.shape = match s.to_ascii_lowercase().as_str() {
                    "rect" => Shape::Rect,
                    "cross" => Shape::Cross,
                    "ellipse" => Shape::Ellipse,
                    _ => {
                        return Err(Failure::Invalid(format!(
                            "invalid parameter `thresholds.shape`: expected rect, cross or \
                             ellipse, got {s:?}"
                        )));
                    }
                }
            }
            _ => {
                return Err(Failure::Invalid(format!(
                    "invalid parameter `thresholds`: unknown key {key:?} (magnitude, sum, \
                     erode, dilate, shape)"
                )));
            }
        }
    }
    t.validate()?;
    Ok(t)
}

/// The flow parameters of a preset name.
pub fn flow(preset: &str) -> Result<DisParams, Failure> {
    Ok(DisParams::preset(DisPreset::parse(preset)?))
}

/// An exposure compensation name (`"auto"`, `"gain-offset"`, `"offset"`, `"off"`).
pub fn exposure(name: &str) -> Result<ExposureCompensation, Failure> {
    Ok(ExposureCompensation::parse(name)?)
}

/// A relocation name (`"clear"`, `"best"`).
pub fn relocation(name: &str) -> Result<Relocation, Failure> {
    match name {
        "clear" => Ok(Relocation::Clear),
        "best" => Ok(Relocation::Best),
        _ => Err(Failure::Invalid(format!(
            "relocation must be \"clear\" or \"best\", got {name:?}"
        ))),
    }
}

/// A light box's half-side, px (0: none), at most [`MAX_LIGHT_BOX_PX`].
pub fn light_box(px: usize) -> Result<usize, Failure> {
    if px > MAX_LIGHT_BOX_PX {
        return Err(Failure::Invalid(format!(
            "light_box must be at most {MAX_LIGHT_BOX_PX} px, got {px}"
        )));
    }
    Ok(px)
}

/// A crop `(x, y, w, h)`.
pub fn crop(c: (usize, usize, usize, usize)) -> Roi {
    Roi::new(c.0, c.1, c.2, c.3)
}

/// A crop as `(x, y, w, h)`.
pub fn roi_tuple(r: Roi) -> (usize, usize, usize, usize) {
    (r.x, r.y, r.w, r.h)
}

/// Thresholds as a dict.
pub fn thresholds_dict<'py>(py: Python<'py>, t: &Thresholds) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("magnitude", t.magnitude)?;
    d.set_item("sum", t.sum)?;
    d.set_item("erode", t.erode)?;
    d.set_item("dilate", t.dilate)?;
    d.set_item(
        "shape",
        match t.shape {
            Shape::Rect => "rect",
            Shape::Cross => "cross",
            Shape::Ellipse => "ellipse",
        },
    )?;
    Ok(d)
}
