//! `Calibration`, `Sensor`, `Contact`, `RawContact`, `Sequence`, `read_image`.

use std::path::PathBuf;
use std::sync::Mutex;
use std::time::Instant;

use ndarray::{Array2, ArrayRef2};
use numpy::{IntoPyArray, PyArray2};
use optical_tactile::capture::{FrameSource, SequenceSource};
use optical_tactile::contact::{Contact as LibContact, ContactPointMethod, RawContact as LibRaw};
use optical_tactile::frame::Roi;
use optical_tactile::io::{ContactRecord, read_gray_channel};
use optical_tactile::sensor::{ContactExtractor, ExtractorConfig};
use optical_tactile::track::FilterConfig;
use optical_tactile::{Calibration as LibCalibration, TactileSensor};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::{Failure, detached, invalid, lib};
use crate::input::{Colour, FrameArg, to_gray_within};
use crate::params;

/// A sensor's calibration: the fitted maps from raw quantities to
/// millimetres and newtons, with the crop, thresholds and flow settings they
/// were fitted with.
#[pyclass(module = "optical_tactile", frozen)]
#[derive(Clone)]
pub struct Calibration {
    pub(crate) inner: LibCalibration,
}

#[pymethods]
impl Calibration {
    /// Loads a calibration JSON file (docs/formats.md).
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Calibration> {
        detached(py, || Ok(LibCalibration::load(&path)?)).map(|inner| Calibration { inner })
    }

    /// Reads a calibration from its JSON text.
    #[staticmethod]
    fn from_json(py: Python<'_>, text: &str) -> PyResult<Calibration> {
        LibCalibration::from_json_str(text)
            .map(|inner| Calibration { inner })
            .map_err(|e| lib(py, e))
    }

    /// The calibration as JSON text (the file format).
    fn to_json(&self) -> String {
        self.inner.to_json_string()
    }

    /// Writes the calibration to a JSON file.
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        detached(py, || Ok(self.inner.save(&path)?))
    }

    /// The crop of the camera frame the calibration's pixels refer to, `(x, y, w, h)`.
    #[getter]
    fn crop(&self) -> (usize, usize, usize, usize) {
        params::roi_tuple(self.inner.setup.crop)
    }

    /// The segmentation thresholds it was fitted with (dict).
    #[getter]
    fn thresholds<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        params::thresholds_dict(py, &self.inner.setup.thresholds)
    }

    /// The flow preset it was fitted with, if recorded.
    #[getter]
    fn flow_preset(&self) -> Option<String> {
        self.inner
            .setup
            .pipeline
            .as_ref()
            .map(|p| p.flow_preset.clone())
    }

    /// The test split's mean absolute errors recorded by the fit (`n`,
    /// `x_mm`, `y_mm`, `fx`, `fy`, `fz`), if any.
    #[getter]
    fn test_mae<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(t) = self.inner.report.as_ref().and_then(|r| r.test.as_ref()) else {
            return Ok(None);
        };
        let d = PyDict::new(py);
        d.set_item("n", t.total.n)?;
        d.set_item("x_mm", t.total.x_mm)?;
        d.set_item("y_mm", t.total.y_mm)?;
        d.set_item("fx", t.total.fx)?;
        d.set_item("fy", t.total.fy)?;
        d.set_item("fz", t.total.fz)?;
        Ok(Some(d))
    }

    fn __repr__(&self) -> String {
        let c = self.inner.setup.crop;
        format!(
            "Calibration(crop=({}, {}, {}, {}), flow_preset={:?})",
            c.x,
            c.y,
            c.w,
            c.h,
            self.flow_preset()
        )
    }
}

/// The raw, uncalibrated quantities of one contact patch, in the pixels of
/// the cropped image.
#[pyclass(module = "optical_tactile", frozen, get_all)]
#[derive(Clone, Debug)]
pub struct RawContact {
    /// Contact point column, px (cropped image).
    pub x_px: f64,
    /// Contact point row, px.
    pub y_px: f64,
    /// Shear raw displacement along image x (sum of the patch's flow u).
    pub ds1: f64,
    /// Shear raw displacement along image y (sum of the patch's flow v).
    pub ds2: f64,
    /// Normal raw displacement (sum of |d| over the patch).
    pub dn: f64,
    /// Spread of the divergence potential, `max D - min D`.
    pub d_pf: f64,
    /// Raw displacements in the sensor frame `(Dx, Dy, Dz)`.
    pub d_sensor: (f64, f64, f64),
    /// Pixels of the patch's mask.
    pub area_px: u64,
    /// The patch's box `(x, y, w, h)`, px of the cropped image.
    pub box_px: (usize, usize, usize, usize),
    /// Summed flow magnitude of the patch (the detection strength).
    pub strength: f64,
    /// Profile-matched local force components, when the calibration has a
    /// profile model.
    pub local_force: Option<(f64, f64, f64)>,
}

impl From<&LibRaw> for RawContact {
    fn from(r: &LibRaw) -> Self {
        let [a, b, c] = r.d_sensor;
        RawContact {
            x_px: r.x_px,
            y_px: r.y_px,
            ds1: r.ds1,
            ds2: r.ds2,
            dn: r.dn,
            d_pf: r.d_pf,
            d_sensor: (a, b, c),
            area_px: r.area_px,
            box_px: params::roi_tuple(r.bbox),
            strength: r.strength,
            local_force: r.local_force.map(|[x, y, z]| (x, y, z)),
        }
    }
}

#[pymethods]
impl RawContact {
    fn __repr__(&self) -> String {
        format!(
            "RawContact(x_px={:.2}, y_px={:.2}, ds1={:.1}, ds2={:.1}, dn={:.1}, d_pf={:.3}, box_px={:?})",
            self.x_px, self.y_px, self.ds1, self.ds2, self.dn, self.d_pf, self.box_px
        )
    }
}

/// One contact: where (mm) and how hard (N), in the sensor frame, with the
/// raw quantities it came from. A raw sensor (`Sensor.raw`) has no
/// calibration: its contacts' `location_mm` and `force_n` are `None` and
/// `id` is the patch's index in the frame.
#[pyclass(module = "optical_tactile", frozen, get_all)]
#[derive(Clone, Debug)]
pub struct Contact {
    /// Identity, stable from frame to frame while the contact lasts.
    pub id: u64,
    /// Location `(x, y, z)`, mm, sensor frame (`None` without calibration).
    pub location_mm: Option<(f64, f64, f64)>,
    /// Force `(Fx, Fy, Fz)`, N, sensor frame; a press has `Fz < 0` (`None`
    /// without calibration).
    pub force_n: Option<(f64, f64, f64)>,
    /// Standard deviation of the force's error `(Fx, Fy, Fz)`, N: about
    /// 68% of contacts lie within one sigma of the true force (`None`
    /// without calibration, or with one that has no uncertainty model).
    pub force_sigma_n: Option<(f64, f64, f64)>,
    /// Contact point column, px of the cropped image.
    pub x_px: f64,
    /// Contact point row, px of the cropped image.
    pub y_px: f64,
    /// Frames in a row this contact has been held without a detection.
    pub missed: u32,
    /// Whether the force came from the calibration's fallback maps.
    pub fallback: bool,
    /// Whether the contact lies outside what the calibration knows.
    pub out_of_domain: bool,
    /// The raw quantities.
    pub raw: RawContact,
}

impl Contact {
    /// The contact as a contacts-file record (docs/formats.md), `None`
    /// without calibration (no location or force).
    pub fn record(&self) -> Option<ContactRecord> {
        let ((x_mm, y_mm, z_mm), (fx_n, fy_n, fz_n)) = (self.location_mm?, self.force_n?);
        let sigma = self.force_sigma_n;
        Some(ContactRecord {
            id: Some(self.id),
            x_mm,
            y_mm,
            z_mm,
            fx_n,
            fy_n,
            fz_n,
            x_px: Some(self.x_px),
            y_px: Some(self.y_px),
            d_pf: Some(self.raw.d_pf),
            fallback: Some(self.fallback),
            out_of_domain: Some(self.out_of_domain),
            missed: Some(self.missed),
            fx_sigma_n: sigma.map(|s| s.0),
            fy_sigma_n: sigma.map(|s| s.1),
            fz_sigma_n: sigma.map(|s| s.2),
            ..ContactRecord::default()
        })
    }

    fn calibrated(c: &LibContact) -> Self {
        let [x, y, z] = c.location_mm;
        let [fx, fy, fz] = c.force_n;
        Contact {
            id: c.id,
            location_mm: Some((x, y, z)),
            force_n: Some((fx, fy, fz)),
            force_sigma_n: c.force_sigma_n.map(|[x, y, z]| (x, y, z)),
            x_px: c.raw.x_px,
            y_px: c.raw.y_px,
            missed: c.missed,
            fallback: c.fallback,
            out_of_domain: c.out_of_domain,
            raw: RawContact::from(&c.raw),
        }
    }

    fn raw_patch(k: usize, r: &LibRaw) -> Self {
        Contact {
            id: k as u64,
            location_mm: None,
            force_n: None,
            force_sigma_n: None,
            x_px: r.x_px,
            y_px: r.y_px,
            missed: 0,
            fallback: false,
            out_of_domain: false,
            raw: RawContact::from(r),
        }
    }
}

#[pymethods]
impl Contact {
    /// Magnitude of the force, N (`None` without calibration).
    #[getter]
    fn force_magnitude(&self) -> Option<f64> {
        self.force_n.map(|(x, y, z)| (x * x + y * y + z * z).sqrt())
    }

    fn __repr__(&self) -> String {
        match (self.location_mm, self.force_n) {
            (Some((x, y, z)), Some((fx, fy, fz))) => format!(
                "Contact(id={}, location_mm=({x:.2}, {y:.2}, {z:.2}), force_n=({fx:.3}, {fy:.3}, {fz:.3}), \
                 x_px={:.1}, y_px={:.1}{}{}{})",
                self.id,
                self.x_px,
                self.y_px,
                if self.missed > 0 { ", held" } else { "" },
                if self.fallback { ", fallback" } else { "" },
                if self.out_of_domain {
                    ", out_of_domain"
                } else {
                    ""
                },
            ),
            _ => format!(
                "Contact(id={}, raw, x_px={:.1}, y_px={:.1}, strength={:.0})",
                self.id, self.x_px, self.y_px, self.raw.strength
            ),
        }
    }
}

/// What runs on the frames.
enum Pipeline {
    Calibrated(Box<TactileSensor>),
    Raw {
        extractor: Box<ContactExtractor>,
        crop: Option<Roi>,
        has_reference: bool,
    },
}

struct State {
    pipeline: Pipeline,
    /// Conversion buffer of integer or luma frames (reused).
    buf: Array2<f32>,
    /// The converted crop, before it goes into `buf` (reused).
    scratch: Array2<f32>,
    /// The library's `process()` time of the last frame, ms.
    last_ms: f64,
}

impl Pipeline {
    /// The part of a frame the pipeline reads, if not all of it.
    fn crop(&self) -> Option<Roi> {
        match self {
            Pipeline::Calibrated(s) => Some(s.crop()),
            Pipeline::Raw { crop, .. } => *crop,
        }
    }

    fn set_reference(&mut self, img: &ArrayRef2<f32>) -> optical_tactile::Result<()> {
        match self {
            Pipeline::Calibrated(s) => s.set_reference(img),
            Pipeline::Raw {
                extractor,
                crop,
                has_reference,
            } => {
                let roi = crop.unwrap_or_else(|| Roi::full(img.ncols(), img.nrows()));
                extractor.set_reference(&roi.crop(img)?)?;
                *has_reference = true;
                Ok(())
            }
        }
    }

    fn process(&mut self, img: &ArrayRef2<f32>, t_s: f64) -> optical_tactile::Result<Vec<Contact>> {
        match self {
            Pipeline::Calibrated(s) => Ok(s
                .process(img, t_s)?
                .iter()
                .map(Contact::calibrated)
                .collect()),
            Pipeline::Raw {
                extractor,
                crop,
                has_reference,
            } => {
                if !*has_reference {
                    return Err(optical_tactile::Error::NoReference);
                }
                let roi = crop.unwrap_or_else(|| Roi::full(img.ncols(), img.nrows()));
                let view = roi.crop(img)?;
                extractor.extract(&view)?;
                // The contact point as `track --raw` measures it: the column
                // as a calibration measures it by default, or both
                // coordinates where followed dots point.
                let method = ContactPointMethod::uncalibrated(extractor.follows_dots());
                Ok(extractor
                    .locate(method)?
                    .iter()
                    .enumerate()
                    .map(|(k, r)| Contact::raw_patch(k, r))
                    .collect())
            }
        }
    }
}

/// The tactile sensor: give it an unloaded reference frame, then frames;
/// each `process` call returns the frame's contacts.
///
/// Frames are NumPy arrays of `uint8`, `uint16` or `float32` (on the 8-bit
/// scale, 0-255), grey `(H, W)` or colour `(H, W, 3)`; the whole camera
/// frame, which the sensor crops. The GIL is released while a frame is
/// processed. One sensor may be shared by threads: its calls then run one
/// at a time.
#[pyclass(module = "optical_tactile", frozen)]
pub struct Sensor {
    state: Mutex<State>,
    colour: Colour,
    calibrated: bool,
}

fn new_sensor(pipeline: Pipeline, colour: Colour) -> Sensor {
    let calibrated = matches!(pipeline, Pipeline::Calibrated(_));
    Sensor {
        state: Mutex::new(State {
            pipeline,
            buf: Array2::zeros((0, 0)),
            scratch: Array2::zeros((0, 0)),
            last_ms: f64::NAN,
        }),
        colour,
        calibrated,
    }
}

impl Sensor {
    /// Reads `frame` as the pipeline's grey image (within its crop) and
    /// hands the pipeline, the image and the last `process()` time to `f`,
    /// with the GIL released and the sensor's state locked.
    fn with_frame<T: Send>(
        &self,
        py: Python<'_>,
        frame: &Bound<'_, PyAny>,
        f: impl FnOnce(&mut Pipeline, &ArrayRef2<f32>, &mut f64) -> Result<T, Failure> + Send,
    ) -> PyResult<T> {
        let arg = FrameArg::extract(frame, "frame").map_err(|e| e.into_py(py))?;
        let colour = self.colour;
        let px = arg.pixels("frame").map_err(|e| e.into_py(py))?;
        detached(py, || {
            let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
            let State {
                pipeline,
                buf,
                scratch,
                last_ms,
            } = &mut *st;
            let img = to_gray_within(&px, colour, pipeline.crop(), buf, scratch)?;
            f(pipeline, &img, last_ms)
        })
    }
}

#[pymethods]
impl Sensor {
    /// A calibrated sensor. Crop, thresholds, flow preset and exposure
    /// compensation come from the calibration; the keywords override them.
    #[staticmethod]
    #[pyo3(signature = (
        calibration, *, thresholds=None, preset=None, crop=None, force_crop=false,
        exposure=None, filter=false, hold=None, rereference=true, channel="green",
        color_order="rgb", dot_tracking=None, dot_fit=None
    ))]
    #[allow(clippy::too_many_arguments)]
    fn from_calibration(
        py: Python<'_>,
        calibration: &Calibration,
        thresholds: Option<&Bound<'_, PyAny>>,
        preset: Option<&str>,
        crop: Option<(usize, usize, usize, usize)>,
        force_crop: bool,
        exposure: Option<&str>,
        filter: bool,
        hold: Option<u32>,
        rereference: bool,
        channel: &str,
        color_order: &str,
        dot_tracking: Option<bool>,
        dot_fit: Option<bool>,
    ) -> PyResult<Sensor> {
        let build = || -> Result<Sensor, Failure> {
            let colour = Colour::parse(channel, color_order)?;
            let cal = calibration.inner.clone();
            let base = cal.setup.thresholds;
            let mut b = TactileSensor::builder(cal);
            if let Some(t) = thresholds {
                b = b.thresholds(params::thresholds(t, base)?);
            }
            if let Some(p) = preset {
                b = b.flow(params::flow(p)?);
            }
            if let Some(c) = crop {
                b = b.crop(params::crop(c)).force_crop(force_crop);
            }
            let exposure = exposure.map(params::exposure).transpose()?;
            let sensor = b
                .configure(|c| {
                    if let Some(e) = exposure {
                        c.extractor.exposure = e;
                    }
                    if let Some(on) = dot_tracking {
                        c.extractor.dot_tracking = on;
                    }
                    if let Some(on) = dot_fit {
                        c.extractor.dot_fit = on;
                    }
                    c.tracker.filter = filter.then(FilterConfig::default);
                    if let Some(h) = hold {
                        c.tracker.max_missed = h;
                    }
                    c.rereference.enabled = rereference;
                })
                .build()?;
            Ok(new_sensor(Pipeline::Calibrated(Box::new(sensor)), colour))
        };
        build().map_err(|e| e.into_py(py))
    }

    /// A sensor without calibration: every frame's patches with their raw
    /// quantities in pixels (`Contact.location_mm` and `force_n` are
    /// `None`). The crop defaults to the whole frame, the flow preset and
    /// thresholds to the library's defaults.
    #[staticmethod]
    #[pyo3(signature = (
        *, crop=None, thresholds=None, preset=None, exposure="auto", channel="green",
        color_order="rgb", dot_tracking=true, dot_fit=true
    ))]
    #[allow(clippy::too_many_arguments)]
    fn raw(
        py: Python<'_>,
        crop: Option<(usize, usize, usize, usize)>,
        thresholds: Option<&Bound<'_, PyAny>>,
        preset: Option<&str>,
        exposure: &str,
        channel: &str,
        color_order: &str,
        dot_tracking: bool,
        dot_fit: bool,
    ) -> PyResult<Sensor> {
        let build = || -> Result<Sensor, Failure> {
            let colour = Colour::parse(channel, color_order)?;
            let mut config = ExtractorConfig::default()
                .with_exposure(params::exposure(exposure)?)
                .with_dot_tracking(dot_tracking)
                .with_dot_fit(dot_fit);
            if let Some(p) = preset {
                config = config.with_flow(params::flow(p)?);
            }
            if let Some(t) = thresholds {
                let base = config.thresholds;
                config = config.with_thresholds(params::thresholds(t, base)?);
            }
            let extractor = ContactExtractor::new(config)?;
            Ok(new_sensor(
                Pipeline::Raw {
                    extractor: Box::new(extractor),
                    crop: crop.map(params::crop),
                    has_reference: false,
                },
                colour,
            ))
        };
        build().map_err(|e| e.into_py(py))
    }

    /// Takes `frame` (unloaded: nothing touches the skin) as the reference.
    fn set_reference(&self, py: Python<'_>, frame: &Bound<'_, PyAny>) -> PyResult<()> {
        self.with_frame(py, frame, |pipeline, img, _| {
            Ok(pipeline.set_reference(img)?)
        })
    }

    /// Processes `frame`, taken at `t_s` seconds: the contacts in it.
    fn process(
        &self,
        py: Python<'_>,
        frame: &Bound<'_, PyAny>,
        t_s: f64,
    ) -> PyResult<Vec<Contact>> {
        finite(py, "t_s", t_s)?;
        self.with_frame(py, frame, |pipeline, img, last_ms| {
            let t = Instant::now();
            let out = pipeline.process(img, t_s);
            *last_ms = t.elapsed().as_secs_f64() * 1e3;
            Ok(out?)
        })
    }

    /// Whether the sensor has a calibration (`Sensor.from_calibration`).
    #[getter]
    fn calibrated(&self) -> bool {
        self.calibrated
    }

    /// The crop of the camera frame the sensor processes, `(x, y, w, h)`
    /// (`None` for a raw sensor on whole frames).
    #[getter]
    fn crop(&self) -> Option<(usize, usize, usize, usize)> {
        let st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        match &st.pipeline {
            Pipeline::Calibrated(s) => Some(params::roi_tuple(s.crop())),
            Pipeline::Raw { crop, .. } => crop.map(params::roi_tuple),
        }
    }

    /// Whether the last frame became the new reference (quiet, small flow).
    #[getter]
    fn rereferenced(&self) -> bool {
        let st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        matches!(&st.pipeline, Pipeline::Calibrated(s) if s.rereferenced())
    }

    /// Time the library's `process()` took on the last frame, ms (the
    /// conversion of the NumPy frame and the Python call are not in it).
    #[getter]
    fn last_process_ms(&self) -> f64 {
        self.state.lock().unwrap_or_else(|e| e.into_inner()).last_ms
    }

    /// Time spent in each stage of the last frame, ms (dict: crop, flow,
    /// segment, hhd, contacts (calibration), tracking, total).
    fn timings<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let t = match &st.pipeline {
            Pipeline::Calibrated(s) => *s.timings(),
            Pipeline::Raw { extractor, .. } => *extractor.timings(),
        };
        let d = PyDict::new(py);
        d.set_item("crop", t.crop_ms)?;
        d.set_item("flow", t.flow_ms)?;
        d.set_item("segment", t.segment_ms)?;
        d.set_item("hhd", t.hhd_ms)?;
        d.set_item("contacts", t.contacts_ms)?;
        d.set_item("tracking", t.tracking_ms)?;
        d.set_item("total", t.total_ms)?;
        Ok(d)
    }

    fn __repr__(&self) -> String {
        match self.crop() {
            Some((x, y, w, h)) => format!(
                "Sensor(calibrated={}, crop=({x}, {y}, {w}, {h}))",
                if self.calibrated { "True" } else { "False" }
            ),
            None => "Sensor(calibrated=False, crop=None)".into(),
        }
    }
}

/// Reads an image file (PNG) as the library does: a `float32` grey image
/// `(H, W)` on the 8-bit scale (16-bit images divided by 257; colour images'
/// green channel, or luma).
#[pyfunction]
#[pyo3(signature = (path, *, channel="green"))]
pub fn read_image<'py>(
    py: Python<'py>,
    path: PathBuf,
    channel: &str,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let colour = Colour::parse(channel, "rgb").map_err(|e| e.into_py(py))?;
    let img = detached(py, || Ok(read_gray_channel(&path, colour.channel)?))?;
    Ok(img.into_pyarray(py))
}

/// The frames of a directory of PNG images, in name order, as
/// `(name, t_s, image)` with `image` as `read_image` gives it and `t_s` from
/// a `poses.csv` beside the frames, else the frame's index / `fps`.
#[pyclass(module = "optical_tactile")]
pub struct Sequence {
    source: SequenceSource,
}

/// One frame of a [`Sequence`]: name, time stamp, grey image.
type SequenceItem<'py> = (String, f64, Bound<'py, PyArray2<f32>>);

#[pymethods]
impl Sequence {
    /// Opens the directory `path`.
    #[new]
    #[pyo3(signature = (path, *, channel="green", fps=50.0))]
    fn new(py: Python<'_>, path: PathBuf, channel: &str, fps: f64) -> PyResult<Sequence> {
        let colour = Colour::parse(channel, "rgb").map_err(|e| e.into_py(py))?;
        let source = SequenceSource::open(&path)
            .and_then(|s| s.with_fps(fps))
            .map_err(|e| lib(py, e))?
            .with_channel(colour.channel);
        Ok(Sequence { source })
    }

    fn __len__(&self) -> usize {
        self.source.len()
    }

    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__<'py>(&mut self, py: Python<'py>) -> PyResult<Option<SequenceItem<'py>>> {
        let source = &mut self.source;
        let next = detached(py, || Ok(source.next_frame().transpose()?))?;
        Ok(next.map(|f| (f.name, f.t_s, f.image.into_pyarray(py))))
    }

    /// The frame files, in order.
    #[getter]
    fn paths(&self) -> Vec<PathBuf> {
        self.source.paths().to_vec()
    }
}

/// Errors unless `t` is finite.
pub fn finite(py: Python<'_>, name: &str, t: f64) -> PyResult<()> {
    if t.is_finite() {
        Ok(())
    } else {
        Err(invalid(
            py,
            format!("invalid parameter `{name}`: must be finite, got {t}"),
        ))
    }
}
