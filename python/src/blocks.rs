//! The pipeline's stages alone: `dis_flow`, `nhhd`, `segment`.

use ndarray::{Array2, Array3, ArrayView2, Axis, Ix2, Ix3};
use numpy::{
    IntoPyArray, PyArray2, PyArray3, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn,
    PyUntypedArray, PyUntypedArrayMethods,
};
use optical_tactile::flow::FlowField;
use optical_tactile::flow::dis::Dis;
use optical_tactile::hhd::{Field2, NaturalHhd};
use optical_tactile::segment::Segmenter;
use optical_tactile::segment::{SegmenterConfig, Thresholds};
use pyo3::prelude::*;

use crate::errors::{Failure, detached};
use crate::input::{Colour, FrameArg, to_gray};
use crate::params;

/// `(H, W, 2)` from the flow's planes.
fn flow_array(f: &FlowField) -> Array3<f32> {
    let (w, h) = f.size();
    let mut out = Array3::zeros((h, w, 2));
    out.index_axis_mut(Axis(2), 0).assign(&f.u);
    out.index_axis_mut(Axis(2), 1).assign(&f.v);
    out
}

/// Dense optical flow from `reference` to `current` with the library's
/// Dense Inverse Search: a `float32` array `(H, W, 2)` of `(u, v)` per pixel
/// (u along columns), in pixels. Frames as `Sensor.process` takes them.
#[pyfunction]
#[pyo3(signature = (reference, current, *, preset="accurate", channel="green", color_order="rgb"))]
pub fn dis_flow<'py>(
    py: Python<'py>,
    reference: &Bound<'py, PyAny>,
    current: &Bound<'py, PyAny>,
    preset: &str,
    channel: &str,
    color_order: &str,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let setup = || -> Result<_, Failure> {
        Ok((
            FrameArg::extract(reference, "reference")?,
            FrameArg::extract(current, "current")?,
            params::flow(preset)?,
            Colour::parse(channel, color_order)?,
        ))
    };
    let (r, c, params, colour) = setup().map_err(|e| e.into_py(py))?;
    let pixels = || -> Result<_, Failure> { Ok((r.pixels("reference")?, c.pixels("current")?)) };
    let (rp, cp) = pixels().map_err(|e| e.into_py(py))?;
    let flow = detached(py, || {
        let (mut rb, mut cb) = (Array2::zeros((0, 0)), Array2::zeros((0, 0)));
        let ri = to_gray(&rp, colour, &mut rb)?;
        let ci = to_gray(&cp, colour, &mut cb)?;
        let mut dis = Dis::new(params)?;
        dis.set_reference(&ri)?;
        let flow = dis.compute(&ci)?;
        Ok(flow_array(&flow))
    })?;
    Ok(flow.into_pyarray(py))
}

/// A 2-D `float64` or `float32` array argument as `float64`.
fn plane(obj: &Bound<'_, PyAny>, what: &str) -> Result<Array2<f64>, Failure> {
    let Ok(a) = obj.cast::<PyUntypedArray>() else {
        return Err(Failure::Type(format!("{what} must be a numpy.ndarray")));
    };
    let view = |shape: &[usize]| -> Result<(), Failure> {
        if shape.len() != 2 {
            return Err(Failure::Invalid(format!(
                "{what}: expected a 2-D array, got shape {shape:?}"
            )));
        }
        optical_tactile::frame::check_frame_size(what, shape[1], shape[0])?;
        Ok(())
    };
    if let Ok(a) = a.cast::<PyArrayDyn<f64>>() {
        let r: PyReadonlyArrayDyn<'_, f64> = a.try_readonly().map_err(borrowed(what))?;
        view(r.shape())?;
        Ok(r.as_array()
            .into_dimensionality::<Ix2>()
            .map_err(|e| Failure::Invalid(e.to_string()))?
            .to_owned())
    } else if let Ok(a) = a.cast::<PyArrayDyn<f32>>() {
        let r: PyReadonlyArrayDyn<'_, f32> = a.try_readonly().map_err(borrowed(what))?;
        view(r.shape())?;
        Ok(r.as_array()
            .into_dimensionality::<Ix2>()
            .map_err(|e| Failure::Invalid(e.to_string()))?
            .mapv(f64::from))
    } else {
        Err(Failure::Type(format!(
            "{what} must have dtype float64 or float32"
        )))
    }
}

fn borrowed(what: &str) -> impl Fn(numpy::BorrowError) -> Failure + '_ {
    move |e| {
        Failure::Invalid(format!(
            "{what}: the array is borrowed mutably elsewhere ({e})"
        ))
    }
}

fn field_array(f: &Field2) -> Array3<f64> {
    let (ny, nx) = f.u.dim();
    let mut out = Array3::zeros((ny, nx, 2));
    out.index_axis_mut(Axis(2), 0).assign(&f.u);
    out.index_axis_mut(Axis(2), 1).assign(&f.v);
    out
}

/// The result of `nhhd`: three `(ny, nx, 2)` fields and two potentials.
type Hhd<'py> = (
    Bound<'py, PyArray3<f64>>,
    Bound<'py, PyArray3<f64>>,
    Bound<'py, PyArray3<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
);

/// The natural Helmholtz-Hodge decomposition of the field `(u, v)` (2-D
/// arrays of shape `(ny, nx)`, `u` along columns with spacing `dx`, `v`
/// along rows with spacing `dy`): `(d, r, h, D, R)` with `d` curl-free, `r`
/// divergence-free and `h` harmonic, each `(ny, nx, 2)` `float64`, and the
/// potentials `D`, `R` `(ny, nx)`.
#[pyfunction]
#[pyo3(signature = (u, v, dx=1.0, dy=1.0))]
pub fn nhhd<'py>(
    py: Python<'py>,
    u: &Bound<'py, PyAny>,
    v: &Bound<'py, PyAny>,
    dx: f64,
    dy: f64,
) -> PyResult<Hhd<'py>> {
    let planes = || -> Result<_, Failure> { Ok((plane(u, "u")?, plane(v, "v")?)) };
    let (u, v) = planes().map_err(|e| e.into_py(py))?;
    let dec = detached(py, || {
        let mut hhd = NaturalHhd::new();
        Ok(hhd.decompose(u.view(), v.view(), dx, dy)?)
    })?;
    Ok((
        field_array(&dec.d).into_pyarray(py),
        field_array(&dec.r).into_pyarray(py),
        field_array(&dec.h).into_pyarray(py),
        dec.potential_d.into_pyarray(py),
        dec.potential_r.into_pyarray(py),
    ))
}

/// One contact patch of `segment`: a box over the flow.
#[pyclass(module = "optical_tactile", frozen, get_all)]
#[derive(Clone, Debug)]
pub struct Patch {
    /// The patch's box `(x, y, w, h)`: the contour boxes grown by the
    /// margin, clamped, merged (flow pixels).
    pub bbox: (usize, usize, usize, usize),
    /// The union of the contour boxes it came from, before the margin.
    pub core: (usize, usize, usize, usize),
    /// Summed `|flow|` over `bbox`, flow pixels.
    pub flow_sum: f64,
    /// Mask pixels (after erosion and dilation) inside `bbox`.
    pub area: usize,
}

#[pymethods]
impl Patch {
    fn __repr__(&self) -> String {
        format!(
            "Patch(bbox={:?}, core={:?}, flow_sum={:.1}, area={})",
            self.bbox, self.core, self.flow_sum, self.area
        )
    }
}

/// The contact patches of a flow `(H, W, 2)` (`float32`, as `dis_flow`
/// gives it): `|flow|` thresholded, eroded, dilated, external contours' boxes
/// whose summed `|flow|` passes, grown by `margin` and merged. `thresholds`
/// is a preset name or a dict (see `Sensor.from_calibration`); `scale` is
/// the flow's full-resolution pixels per flow pixel.
#[pyfunction]
#[pyo3(signature = (flow, thresholds=None, *, margin=10, scale=1.0))]
pub fn segment<'py>(
    py: Python<'py>,
    flow: &Bound<'py, PyAny>,
    thresholds: Option<&Bound<'py, PyAny>>,
    margin: usize,
    scale: f64,
) -> PyResult<Vec<Patch>> {
    let setup = || -> Result<_, Failure> {
        let Ok(a) = flow.cast::<PyArrayDyn<f32>>() else {
            return Err(Failure::Type(
                "flow must be a numpy.ndarray of dtype float32, shape (H, W, 2)".into(),
            ));
        };
        let r = a.try_readonly().map_err(borrowed("flow"))?;
        let shape = r.shape().to_vec();
        if shape.len() != 3 || shape[2] != 2 {
            return Err(Failure::Invalid(format!(
                "flow: expected shape (H, W, 2), got {shape:?}"
            )));
        }
        optical_tactile::frame::check_frame_size("flow", shape[1], shape[0])?;
        let v = r
            .as_array()
            .into_dimensionality::<Ix3>()
            .map_err(|e| Failure::Invalid(e.to_string()))?;
        let planes = |k: usize| -> Array2<f32> {
            let p: ArrayView2<'_, f32> = v.index_axis(Axis(2), k);
            p.to_owned()
        };
        let field = FlowField::from_planes(planes(0), planes(1))?;
        let t = match thresholds {
            None => Thresholds::HIGH,
            Some(t) => params::thresholds(t, Thresholds::HIGH)?,
        };
        Ok((field, t))
    };
    let (field, t) = setup().map_err(|e| e.into_py(py))?;
    let patches = detached(py, || {
        let mut seg = Segmenter::new(SegmenterConfig {
            thresholds: t,
            margin,
            scale,
        })?;
        Ok(seg.segment(&field)?)
    })?;
    let bb = |b: optical_tactile::segment::contours::BoundingBox| (b.x, b.y, b.width, b.height);
    Ok(patches
        .iter()
        .map(|p| Patch {
            bbox: bb(p.bbox),
            core: bb(p.core),
            flow_sum: p.flow_sum,
            area: p.area,
        })
        .collect())
}
