//! The synthetic sensor (`optical-tactile-sim`) and calibration fitting.

use std::path::PathBuf;
use std::sync::Mutex;

use numpy::{IntoPyArray, PyArray2, PyArray3};
use optical_tactile::calibration::fit::{
    AutoThresholds, FitOptions, MAX_REST_PAIRS, ProfileChoices, extract_dataset, extract_sweeps,
    fit_dataset_with_sweeps, read_dataset, read_dataset_geometry, read_dataset_sweeps,
    rest_contacts, rest_pairs,
};
use optical_tactile::contact::ContactPointMethod;
use optical_tactile::flow::dis::DisPreset;
use optical_tactile::frame::Roi;
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::io::{FrameRecord, read_gray, read_jsonl};
use optical_tactile::segment::Thresholds;
use optical_tactile::sensor::{FittingChoices, fitting_extractor};
use optical_tactile_sim::evaluate::{MAX_WORST, ScoreOptions, score_with};
use optical_tactile_sim::scenario::{self, Common, Scenario};
use optical_tactile_sim::{
    Press as SimPress, SensorOptions, SimConfig, SyntheticSensor as SimSensor,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::{Failure, detached};
use crate::params;
use crate::sensor::{Calibration, Contact};

/// Sets the fields named in `kw` on `$s`; an unknown name is an error that
/// lists the known ones.
macro_rules! set_fields {
    ($kw:expr, $s:expr, $scenario:expr, $($f:ident),+ $(,)?) => {
        if let Some(kw) = $kw {
            for (k, v) in kw.iter() {
                let key: String = k
                    .extract()
                    .map_err(|_| Failure::Type("option names must be strings".into()))?;
                match key.as_str() {
                    $(stringify!($f) => {
                        $s.$f = v
                            .extract()
                            .map_err(|e| Failure::Type(format!("option `{key}`: {e}")))?
                    })+
                    _ => {
                        return Err(Failure::Invalid(format!(
                            "invalid parameter `{key}`: not an option of the `{}` scenario ({}) \
                             nor of the sensor ({})",
                            $scenario,
                            [$(stringify!($f)),+].join(", "),
                            SENSOR_KEYS.join(", ")
                        )))
                    }
                }
            }
        }
    };
}

/// Largest number of frames (or presses) one `simulate` call writes: a
/// count past it is refused before anything is written, rather than filling
/// the disk (the longest shipped scenario writes 7200 tests).
pub const MAX_SIM_FRAMES: usize = 100_000;

/// Errors if the count option `name` is above `max`.
fn at_most(name: &str, value: usize, max: usize) -> Result<(), Failure> {
    if value > max {
        return Err(Failure::Invalid(format!(
            "invalid parameter `{name}`: {value} is above {max}, the most one simulate call \
             writes"
        )));
    }
    Ok(())
}

/// The simulated sensors: the paper's curved strip, or a flat fingertip
/// sensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sensor {
    Strip,
    Fingertip,
}

impl Sensor {
    fn parse(name: &str) -> Result<Self, Failure> {
        match name {
            "strip" => Ok(Sensor::Strip),
            "fingertip" => Ok(Sensor::Fingertip),
            _ => Err(Failure::Invalid(format!(
                "invalid parameter `sensor`: unknown sensor {name:?} (strip, fingertip)"
            ))),
        }
    }
}

fn scenario(
    name: &str,
    sensor: Sensor,
    kw: Option<&Bound<'_, PyDict>>,
) -> Result<Scenario, Failure> {
    let sc = scenario_options(name, sensor, kw)?;
    match &sc {
        Scenario::Single(s) => at_most("frames", s.frames, MAX_SIM_FRAMES)?,
        Scenario::Pair(s) => at_most("frames", s.frames, MAX_SIM_FRAMES)?,
        Scenario::Presses(s) => at_most("presses", s.presses, MAX_SIM_FRAMES)?,
        Scenario::TipPresses(s) => at_most("presses", s.presses, MAX_SIM_FRAMES)?,
        Scenario::Shear(s) => at_most("frames", s.frames, MAX_SIM_FRAMES)?,
        Scenario::Characterization(s) => {
            at_most("subset", s.subset.unwrap_or(0), MAX_SIM_FRAMES)?;
            at_most("repeats", s.repeats as usize, 100)?;
        }
        Scenario::Perches(s) => at_most("frames", s.frames, MAX_SIM_FRAMES)?,
        Scenario::Mapping(s) => {
            at_most("touches", s.touches, 1000)?;
            at_most("rods_x_m", s.rods_x_m.len(), 1000)?;
        }
        Scenario::Rest(s) => at_most("frames", s.frames, MAX_SIM_FRAMES)?,
    }
    Ok(sc)
}

fn scenario_options(
    name: &str,
    sensor: Sensor,
    kw: Option<&Bound<'_, PyDict>>,
) -> Result<Scenario, Failure> {
    let fingertip = sensor == Sensor::Fingertip;
    Ok(match name {
        "single" => {
            let mut s = scenario::Single::default();
            set_fields!(
                kw,
                s,
                name,
                x_mm,
                force_n,
                frames,
                indenter_mm,
                yaw_deg,
                pitch_deg,
                sweep_to_mm
            );
            Scenario::Single(s)
        }
        "pair" => {
            let mut s = if fingertip {
                scenario::Pair::fingertip()
            } else {
                scenario::Pair::default()
            };
            set_fields!(
                kw,
                s,
                name,
                x_mm,
                spacing_mm,
                force_n,
                force2_n,
                frames,
                indenter_mm
            );
            Scenario::Pair(s)
        }
        "presses" if fingertip => {
            let mut s = scenario::TipPresses::default();
            set_fields!(
                kw,
                s,
                name,
                presses,
                force_min_n,
                force_max_n,
                max_tilt_deg,
                max_shear_ratio,
                margin_mm,
                sphere_mm,
                punch_mm,
                fingertip_mm,
                press_seed
            );
            Scenario::TipPresses(s)
        }
        "presses" => {
            let mut s = scenario::Presses::default();
            set_fields!(
                kw,
                s,
                name,
                presses,
                x_max_mm,
                force_min_n,
                force_max_n,
                max_tilt_deg,
                indenters_mm,
                press_seed
            );
            Scenario::Presses(s)
        }
        "shear" => {
            // On the fingertip sensor a round tip, at the centre unless placed.
            let mut s = scenario::Shear {
                fingertip_y_mm: fingertip.then_some(0.0),
                ..scenario::Shear::default()
            };
            set_fields!(
                kw,
                s,
                name,
                x_mm,
                force_n,
                shear_n,
                frames,
                indenter_mm,
                fingertip_y_mm
            );
            Scenario::Shear(s)
        }
        "characterization" => {
            let mut s = if fingertip {
                scenario::Characterization::flat()
            } else {
                scenario::Characterization::default()
            };
            set_fields!(
                kw,
                s,
                name,
                subset,
                repeats,
                load_cell_noise_n,
                sweep_step_mm,
                tilted_sweeps,
                spot_checks
            );
            Scenario::Characterization(s)
        }
        "perches" => {
            let mut s = scenario::Perches::default();
            set_fields!(
                kw,
                s,
                name,
                x_mm,
                stiffness_n_per_mm,
                max_penetration_mm,
                frames,
                indenter_mm
            );
            Scenario::Perches(s)
        }
        "mapping" => {
            let mut s = scenario::Mapping::default();
            set_fields!(
                kw,
                s,
                name,
                rods_x_m,
                rods_top_m,
                touches,
                force_n,
                indenter_mm
            );
            Scenario::Mapping(s)
        }
        "rest" => {
            let mut s = scenario::Rest::default();
            set_fields!(kw, s, name, frames);
            Scenario::Rest(s)
        }
        _ => {
            return Err(Failure::Invalid(format!(
                "invalid parameter `scenario`: unknown scenario {name:?} (single, pair, presses, \
                 shear, characterization, perches, mapping, rest)"
            )));
        }
    })
}

/// The keywords of [`simulate`] that describe the sensor rather than the
/// scenario (those of `simulate`'s command-line sensor flags).
const SENSOR_KEYS: [&str; 17] = [
    "random_markers",
    "dot_grid",
    "youngs_kpa",
    "poisson",
    "layer_mm",
    "coverage",
    "markers",
    "marker_depth_mm",
    "pitch_px",
    "dot_px",
    "jitter_px",
    "noise_read",
    "flicker",
    "exposure_steps",
    "drift",
    "contact_light",
    "contact_shading",
];

/// The sensor [`simulate`]'s keywords describe ([`SENSOR_KEYS`]), and the
/// other keywords (the scenario's). Errors, as the command line does, on
/// a dot grid or random markers asked of the wrong sensor and on
/// `exposure_steps` (EVERY, GAIN[, OFFSET[, LEVELS]]) or `drift` (GAIN,
/// OFFSET, PERIOD) of another length; the values themselves are checked by
/// the simulator.
fn sensor_options<'py>(
    py: Python<'py>,
    sensor: Sensor,
    full_frame: bool,
    kw: Option<&Bound<'py, PyDict>>,
) -> Result<(SensorOptions, Option<Bound<'py, PyDict>>), Failure> {
    let mut o = SensorOptions {
        fingertip: sensor == Sensor::Fingertip,
        full_frame,
        ..SensorOptions::default()
    };
    let Some(kw) = kw else {
        return Ok((o, None));
    };
    let rest = PyDict::new(py);
    for (k, v) in kw.iter() {
        let key: String = k
            .extract()
            .map_err(|_| Failure::Type("option names must be strings".into()))?;
        let bad = |e: PyErr| Failure::Type(format!("option `{key}`: {e}"));
        match key.as_str() {
            "random_markers" => o.random_markers = v.extract().map_err(bad)?,
            "dot_grid" => o.dot_grid = v.extract().map_err(bad)?,
            "youngs_kpa" => o.youngs_kpa = v.extract().map_err(bad)?,
            "poisson" => o.poisson = v.extract().map_err(bad)?,
            "layer_mm" => o.layer_mm = v.extract().map_err(bad)?,
            "coverage" => o.coverage = v.extract().map_err(bad)?,
            "markers" => o.markers = v.extract().map_err(bad)?,
            "marker_depth_mm" => o.marker_depth_mm = v.extract().map_err(bad)?,
            "pitch_px" => o.pitch_px = v.extract().map_err(bad)?,
            "dot_px" => o.dot_px = v.extract().map_err(bad)?,
            "jitter_px" => o.jitter_px = v.extract().map_err(bad)?,
            "noise_read" => o.noise_read = v.extract().map_err(bad)?,
            "flicker" => o.flicker = v.extract().map_err(bad)?,
            "exposure_steps" => o.exposure_steps = v.extract().map_err(bad)?,
            "drift" => o.drift = v.extract().map_err(bad)?,
            "contact_light" => o.contact_light.change = v.extract().map_err(bad)?,
            "contact_shading" => o.contact_light.sided = v.extract().map_err(bad)?,
            _ => rest
                .set_item(k, v)
                .map_err(|e| Failure::Type(e.to_string()))?,
        }
    }
    let invalid = |what: &str| Err(Failure::Invalid(what.into()));
    if o.dot_grid && o.fingertip {
        return invalid("dot_grid: the fingertip sensor has a dot grid of its own");
    }
    if o.random_markers && !o.fingertip {
        return invalid(
            "random_markers: for sensor=\"fingertip\" (the strip's markers are random)",
        );
    }
    let steps = &o.exposure_steps;
    if !steps.is_empty()
        && (!(2..=4).contains(&steps.len())
            || steps[0].is_nan()
            || steps[0] < 1.0
            || steps.get(3).is_some_and(|&l| l.is_nan() || l < 1.0))
    {
        return invalid(
            "exposure_steps: (EVERY, GAIN[, OFFSET[, LEVELS]]) with EVERY and LEVELS >= 1",
        );
    }
    if !o.drift.is_empty() && (o.drift.len() != 3 || o.drift[2].is_nan() || o.drift[2] <= 0.0) {
        return invalid("drift: (GAIN, OFFSET, PERIOD) with PERIOD > 0 frames");
    }
    Ok((o, Some(rest)))
}

/// Writes a synthetic recording of `scenario` (`"single"`, `"pair"`,
/// `"presses"`, `"shear"`, `"characterization"`, `"perches"`, `"mapping"`,
/// `"rest"`) into the directory `out`, in the formats of docs/formats.md:
/// frames `000000.png, ...` (frame 0 unloaded) and `truth.jsonl`, or for
/// `characterization` a dataset (`tests.csv`, `frames/`) for `calibrate`.
/// The scenario's options are keywords (e.g. `force_n=2.0, frames=8` for
/// `single`; `subset=400` for `characterization`); `flow` also writes the
/// true dense motion (`.flo`), `full_frame` renders the whole camera frame.
/// `sensor` is `"strip"` (the paper's curved strip, rods across it) or
/// `"fingertip"` (a flat GelSight-Mini-like sensor: a 24 x 18 mm gel with a
/// grid of dark dots filmed at 320x240; `presses` then draws spheres, flat
/// punches and sheared fingertips anywhere in x and y, and
/// `characterization` writes the flat protocol with its `geometry.json`).
/// The sensor's own keywords are those of the command line's sensor flags
/// (`random_markers` (fingertip), `dot_grid` (strip),
/// `youngs_kpa`, `poisson`, `layer_mm`, `coverage`, `markers`,
/// `marker_depth_mm=(min, max)`, `pitch_px`, `dot_px`, `jitter_px`,
/// `noise_read`, `flicker`, `exposure_steps=(every, gain[, offset[,
/// levels]])`, `drift=(gain, offset, period)`, `contact_light`,
/// `contact_shading`): the same options make the same frames.
/// Returns the number of frames written.
#[pyfunction]
#[pyo3(signature = (scenario, out, *, seed=1, flow=false, fps=50.0, full_frame=false, sensor="strip", **options))]
#[allow(clippy::too_many_arguments)]
pub fn simulate(
    py: Python<'_>,
    scenario: &str,
    out: PathBuf,
    seed: u64,
    flow: bool,
    fps: f64,
    full_frame: bool,
    sensor: &str,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<usize> {
    let sensor = Sensor::parse(sensor).map_err(|e| e.into_py(py))?;
    let (sensor_options, options) =
        sensor_options(py, sensor, full_frame, options).map_err(|e| e.into_py(py))?;
    let sc = self::scenario(scenario, sensor, options.as_ref()).map_err(|e| e.into_py(py))?;
    let mut common = Common::new(out);
    common.config = sensor_options.config();
    common.seed = seed;
    common.flow = flow;
    common.fps = fps;
    let summary = detached(py, || Ok(scenario::run(&sc, &common)?))?;
    Ok(summary.frames)
}

/// One rod pressing on the synthetic sensor.
#[pyclass(module = "optical_tactile", frozen, get_all)]
#[derive(Clone, Debug)]
pub struct Press {
    /// Chord position of the rod's axis, mm.
    pub x_mm: f64,
    /// Force on the skin `(Fx, Fy, Fz)`, N, sensor frame (a press has `Fz < 0`).
    pub force_n: (f64, f64, f64),
    /// Rod diameter, mm.
    pub diameter_mm: f64,
    /// Width of the pressed area, mm (`None`: the rod's Hertz width).
    pub contact_width_mm: Option<f64>,
}

#[pymethods]
impl Press {
    /// A rod of `diameter_mm` at chord `x_mm` applying `force_n`.
    #[new]
    #[pyo3(signature = (x_mm, force_n, diameter_mm=5.0))]
    fn new(x_mm: f64, force_n: (f64, f64, f64), diameter_mm: f64) -> Self {
        Press {
            x_mm,
            force_n,
            diameter_mm,
            contact_width_mm: None,
        }
    }

    /// A broad soft press (a fingertip's): `force_n` spread over `width_mm`.
    #[staticmethod]
    fn pad(x_mm: f64, force_n: (f64, f64, f64), width_mm: f64) -> Self {
        Press {
            x_mm,
            force_n,
            diameter_mm: width_mm,
            contact_width_mm: Some(width_mm),
        }
    }

    fn __repr__(&self) -> String {
        format!(
            "Press(x_mm={}, force_n={:?}, diameter_mm={})",
            self.x_mm, self.force_n, self.diameter_mm
        )
    }
}

impl Press {
    fn lib(&self) -> SimPress {
        let (a, b, c) = self.force_n;
        SimPress {
            x_mm: self.x_mm,
            force_n: [a, b, c],
            diameter_mm: self.diameter_mm,
            contact_width_mm: self.contact_width_mm,
            y_mm: None,
        }
    }
}

/// A physics-based synthetic marker sensor (the 1600x200 strip, or the
/// whole 1920x1080 camera frame with `full_frame`): frames for any presses.
#[pyclass(module = "optical_tactile", frozen)]
pub struct SyntheticSensor {
    inner: SimSensor,
}

/// A rendered frame, with the true flow when asked for.
type Rendered<'py> = (Bound<'py, PyArray2<f32>>, Option<Bound<'py, PyArray3<f32>>>);

#[pymethods]
impl SyntheticSensor {
    /// The default synthetic sensor; `seed` fixes the marker layout.
    #[new]
    #[pyo3(signature = (*, seed=1, full_frame=false))]
    fn new(py: Python<'_>, seed: u64, full_frame: bool) -> PyResult<Self> {
        let config = SimConfig {
            full_frame,
            ..SimConfig::default()
        };
        detached(py, || Ok(SimSensor::new(config, seed)?)).map(|inner| SyntheticSensor { inner })
    }

    /// The sensing strip's rectangle in the rendered frame, `(x, y, w, h)`.
    #[getter]
    fn crop(&self) -> (usize, usize, usize, usize) {
        let c = self.inner.config();
        if c.full_frame {
            c.camera.crop()
        } else {
            let (w, h) = c.image_size();
            (0, 0, w, h)
        }
    }

    /// Renders frame number `index` (which fixes its noise) under
    /// `presses`: a `float32` grey image `(H, W)` (integer-valued, 0-255)
    /// and, with `flow=True`, the true motion `(H, W, 2)` from the unloaded
    /// skin, else `None`.
    #[pyo3(signature = (presses=Vec::new(), *, index=0, flow=false))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        presses: Vec<PyRef<'py, Press>>,
        index: u64,
        flow: bool,
    ) -> PyResult<Rendered<'py>> {
        let presses: Vec<SimPress> = presses.iter().map(|p| p.lib()).collect();
        let r = detached(py, || {
            let r = self.inner.render_indexed(index, &presses, flow)?;
            let f = r.flow.map(|f| {
                let (w, h) = f.size();
                let mut out = ndarray::Array3::zeros((h, w, 2));
                out.index_axis_mut(ndarray::Axis(2), 0).assign(&f.u);
                out.index_axis_mut(ndarray::Axis(2), 1).assign(&f.v);
                out
            });
            Ok((r.frame, f))
        })?;
        Ok((r.0.into_pyarray(py), r.1.map(|f| f.into_pyarray(py))))
    }
}

/// Fits a calibration from a characterization dataset (`tests.csv` and its
/// frames, docs/formats.md; `simulate("characterization", ...)` makes one):
/// runs the pipeline on every test (on all cores, the GIL released), then
/// fits the location and force maps with the library's order search, as
/// `calibrate` does with the same options.
/// `thresholds`: a preset name or a dict, or `"auto"` (the default): the
/// presets `high`, `mid`, `low` in turn, keeping the first that gives a
/// contact on all but 5% of the tests, else the most sensitive one that
/// finds no contact on pairs of the dataset's reference images, as
/// `calibrate --thresholds auto` does; `preset`: the flow preset (default:
/// decided from the dataset, as `calibrate` does: `dense` for random
/// markers on a flat sensor, else the library's); `crop`: `(x, y, w, h)` of
/// the frames (default: the whole frame). The sensor's geometry is
/// `geometry` (`"strip"` or `"flat:LENGTHxWIDTH"`, mm), else the dataset's
/// `geometry.json` (a flat sensor's: contacts located in 2-D), else the
/// curved strip. With a `sweeps.csv` beside `tests.csv` (the
/// strip), the calibration also learns per-column location offsets and
/// force gains from the sweeps (docs/calibration.md); `sweeps=False`
/// ignores it. The other options are `calibrate`'s flags of the same names
/// (docs/calibration.md): `measured_columns`, `relocation` (`"clear"` or
/// `"best"`; default: clear with sweeps, best without),
/// `shear_free_columns`, `spread_channel`, `weighted_profiles`,
/// `dot_tracking` (`None`: when the reference shows a regular grid),
/// `dot_fit`, `light_box` (px, 0: none; `None`: decided from the dataset).
/// `progress`, if given, is called as `progress(stage, done, total)` about
/// every percent of each stage (`"tests"` once per thresholds preset tried,
/// `"sweeps"`, `"fit"`), from the worker threads, one call at a time; an
/// exception it raises is raised once the fit is done.
/// The result's `test_mae` has the test split's errors.
#[pyfunction]
#[pyo3(signature = (
    dataset_dir, *, thresholds=None, preset=None, crop=None, sweeps=true,
    measured_columns=false, relocation=None, shear_free_columns=false,
    spread_channel=true, weighted_profiles=false, dot_tracking=None, dot_fit=true,
    light_box=None, geometry=None, progress=None,
))]
#[allow(clippy::too_many_arguments)]
pub fn calibrate(
    py: Python<'_>,
    dataset_dir: PathBuf,
    thresholds: Option<&Bound<'_, PyAny>>,
    preset: Option<&str>,
    crop: Option<(usize, usize, usize, usize)>,
    sweeps: bool,
    measured_columns: bool,
    relocation: Option<&str>,
    shear_free_columns: bool,
    spread_channel: bool,
    weighted_profiles: bool,
    dot_tracking: Option<bool>,
    dot_fit: bool,
    light_box: Option<usize>,
    geometry: Option<&str>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Calibration> {
    // `None` (or "auto"): the presets in turn, as `calibrate --thresholds auto`.
    let auto = match thresholds {
        None => true,
        Some(t) => t.extract::<String>().is_ok_and(|s| s == "auto"),
    };
    let parsed = || -> Result<_, Failure> {
        let asked = match (auto, thresholds) {
            (false, Some(t)) => Some(params::thresholds(t, Thresholds::HIGH)?),
            _ => None,
        };
        let flow = preset.map(DisPreset::parse).transpose()?;
        let relocation = relocation.map(params::relocation).transpose()?;
        let light_box = light_box.map(params::light_box).transpose()?;
        let geometry = geometry.map(SensorGeometry::parse).transpose()?;
        Ok((asked, flow, relocation, light_box, geometry))
    };
    let (asked, flow, relocation, light_box, geometry) = parsed().map_err(|e| e.into_py(py))?;
    let choices = FittingChoices {
        dot_tracking,
        dot_fit,
        flow,
        light_box_px: light_box,
        weighted_profiles,
    };
    let crop = crop.map(params::crop);
    // The progress callback, called from the workers with the GIL taken,
    // one call at a time, about every percent; its first error is raised
    // once the fit is done (the work cannot be stopped half-way).
    let failed: Mutex<Option<PyErr>> = Mutex::new(None);
    let report = |stage: &str, done: usize, total: usize| {
        let Some(callback) = &progress else {
            return;
        };
        if done % (total / 100).max(1) != 0 && done != total {
            return;
        }
        let mut slot = failed.lock().unwrap_or_else(|e| e.into_inner());
        if slot.is_none() {
            let called = Python::attach(|py| callback.call1(py, (stage, done, total)).map(drop));
            *slot = called.err();
        }
    };
    let inner = detached(py, || {
        let rows = read_dataset(&dataset_dir)?;
        let first = read_gray(dataset_dir.join(&rows[0].reference))?;
        let full = crop.unwrap_or_else(|| Roi::full(first.ncols(), first.nrows()));
        // The dataset's geometry.json says which sensor it is (the curved
        // strip without one), and that chooses the contact point and the
        // force maps' inputs as `calibrate` does; its first reference
        // whether the dots are followed, the flow and the light box.
        let geometry = match geometry {
            Some(g) => g,
            None => read_dataset_geometry(&dataset_dir)?.unwrap_or_default(),
        };
        let point = ContactPointMethod::for_geometry(&geometry);
        let (mut config, _) =
            fitting_extractor(&geometry, &full.crop(&first)?.to_owned(), &choices);
        let ex = match asked {
            Some(t) => {
                config = config.with_thresholds(t);
                let tick = |done, total| report("tests", done, total);
                extract_dataset(&dataset_dir, &rows, &config, point, crop, &tick)?
            }
            None => {
                let pairs = rest_pairs(&rows, MAX_REST_PAIRS);
                let mut search = AutoThresholds::new();
                while let Some(p) = search.next_preset() {
                    let c = config.clone().with_thresholds(p);
                    let tick = |done, total| report("tests", done, total);
                    let ex = extract_dataset(&dataset_dir, &rows, &c, point, crop, &tick)?;
                    let rest = rest_contacts(&dataset_dir, &pairs, &c, crop)?;
                    search.record(ex, rest)?;
                }
                let (p, ex) = search.finish().ok_or_else(|| {
                    optical_tactile::Error::param("thresholds", "no preset tried")
                })?;
                config = config.with_thresholds(p);
                ex
            }
        };
        // The dataset's sweeps.csv, if any and not declined, gives the
        // per-column corrections.
        let sweeps = if sweeps {
            read_dataset_sweeps(&dataset_dir)?
        } else {
            Vec::new()
        };
        let tick = |done, total| report("sweeps", done, total);
        let swept = extract_sweeps(&dataset_dir, &sweeps, &config, point, crop, &tick)?;
        let base = FitOptions::for_geometry(&geometry);
        let options = FitOptions {
            profile: base.profile.map(|p| {
                p.with_choices(&ProfileChoices {
                    measured_columns,
                    relocation,
                    shear_free_columns,
                    spread_channel,
                    ..ProfileChoices::default()
                })
            }),
            ..base
        };
        report("fit", 0, 1);
        let fit = fit_dataset_with_sweeps(&ex, &swept, &config, point, full, geometry, &options)?;
        report("fit", 1, 1);
        Ok(fit.calibration)
    })?;
    if let Some(e) = failed.into_inner().unwrap_or_else(|e| e.into_inner()) {
        return Err(e);
    }
    Ok(Calibration { inner })
}

/// Scores predicted contacts against the truth as the `evaluate` example
/// does, and returns its scores as a dict (the JSON of `evaluate --json`:
/// `frames`, `matched`, `misses`, `false_contacts`, `mae_x_mm` ...
/// `mae_fz_n`, `mean_force_error_n`, `beyond`, `worst`, `sigma_coverage`,
/// `bands`, ...). `predictions` is a contacts file (JSON Lines, as `track
/// --out` writes) or the frames' `(name, contacts)` pairs, `contacts` the
/// list a calibrated `Sensor.process` returned for the frame of that name;
/// `truth` a `truth.jsonl` (as `simulate` writes). A prediction matches a
/// true contact within `gate_mm`; `beyond_n` is the bar of `beyond`;
/// `worst` how many contacts of largest 3-D force error are listed;
/// `band_mm` scores the contacts apart per band of that width along the
/// true x. Nothing to score (no frame named in both, or no contact
/// matched) is an error, as it is for the command.
#[pyfunction]
#[pyo3(signature = (predictions, truth, *, gate_mm=10.0, beyond_n=0.3, worst=5, band_mm=None))]
pub fn evaluate<'py>(
    py: Python<'py>,
    predictions: &Bound<'py, PyAny>,
    truth: PathBuf,
    gate_mm: f64,
    beyond_n: f64,
    worst: usize,
    band_mm: Option<f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let checked = || -> Result<(Option<PathBuf>, Vec<FrameRecord>), Failure> {
        for (name, v) in [("gate_mm", gate_mm), ("beyond_n", beyond_n)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Failure::Invalid(format!(
                    "{name} must be finite and > 0, got {v}"
                )));
            }
        }
        if band_mm.is_some_and(|b| !(b.is_finite() && b > 0.0)) {
            return Err(Failure::Invalid(format!(
                "band_mm must be finite and > 0, got {band_mm:?}"
            )));
        }
        if worst > MAX_WORST {
            return Err(Failure::Invalid(format!(
                "worst must be at most {MAX_WORST}, got {worst}"
            )));
        }
        if let Ok(path) = predictions.extract::<PathBuf>() {
            return Ok((Some(path), Vec::new()));
        }
        let mut frames = Vec::new();
        for item in predictions
            .try_iter()
            .map_err(|_| Failure::Type("predictions: a path or (name, contacts) pairs".into()))?
        {
            let (frame, contacts): (String, Vec<Bound<'py, Contact>>) = item
                .and_then(|i| i.extract())
                .map_err(|e| Failure::Type(format!("predictions: (name, contacts) pairs: {e}")))?;
            let contacts = contacts
                .iter()
                .map(|c| {
                    c.get().record().ok_or_else(|| {
                        Failure::Invalid(format!(
                            "predictions: a contact of {frame} has no location or force \
                             (a raw sensor's patch: only a calibrated sensor's contacts are scored)"
                        ))
                    })
                })
                .collect::<Result<_, _>>()?;
            frames.push(FrameRecord {
                frame,
                t_s: 0.0,
                contacts,
                latency_ms: None,
            });
        }
        Ok((None, frames))
    };
    let (path, frames) = checked().map_err(|e| e.into_py(py))?;
    let json = detached(py, || {
        let pred = match path {
            Some(p) => read_jsonl(p)?,
            None => frames,
        };
        let truth: Vec<FrameRecord> = read_jsonl(&truth)?;
        let options = ScoreOptions {
            gate_mm,
            beyond_n,
            worst,
            band_mm,
        };
        let e = score_with(&pred, &truth, &options);
        if e.frames == 0 || e.matched == 0 {
            return Err(Failure::Invalid(format!(
                "nothing to score: {} frames named in both, {} contacts matched within {gate_mm} \
                 mm ({} misses, {} false contacts)",
                e.frames, e.matched, e.misses, e.false_contacts
            )));
        }
        serde_json::to_string(&e).map_err(|e| Failure::Invalid(e.to_string()))
    })?;
    py.import("json")?.call_method1("loads", (json,))
}
