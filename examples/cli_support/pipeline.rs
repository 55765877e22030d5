//! The pipeline the `track`, `live` and `tune` tools run: the calibrated
//! sensor or, with `--raw`, the extractor alone; and how they print what
//! they find.

use std::path::PathBuf;

use ndarray::Array2;
use optical_tactile::calibration::Calibration;
use optical_tactile::contact::{Contact, RawContact};
use optical_tactile::exposure::ExposureCompensation;
use optical_tactile::flow::dis::{DisParams, DisPreset};
use optical_tactile::frame::{Channel, Roi};
use optical_tactile::io::FrameRecord;
use optical_tactile::segment::{MAX_KERNEL_PX, SplitRule, ThresholdPreset, Thresholds};
use optical_tactile::sensor::{
    ContactExtractor, ExtractorConfig, RawSensor, SensorConfig, StageTimings, TactileSensor,
};
use optical_tactile::viz;

/// The calibration used unless `--calibration` names another: this crate's.
pub const DEFAULT_CALIBRATION: &str =
    concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/calibration.json");

/// The flags of what runs on the frames, shared by `track`, `live` and `tune`.
#[derive(clap::Args, Debug, Clone)]
pub struct PipelineArgs {
    /// Calibration file.
    #[arg(long, value_name = "FILE", default_value = DEFAULT_CALIBRATION)]
    pub calibration: PathBuf,
    /// No calibration: print and write each frame's patches in pixels with
    /// their raw quantities.
    #[arg(long)]
    pub raw: bool,
    /// Crop of the camera frame [default: the calibration's; with --raw, the whole frame].
    #[arg(long, value_name = "x,y,w,h", value_parser = super::roi)]
    pub crop: Option<Roi>,
    /// Use a --crop that differs from the calibration's (its locations and
    /// forces then no longer hold).
    #[arg(long)]
    pub force_crop: bool,
    /// Segmentation thresholds [default: the calibration's].
    #[arg(long, value_name = "PRESET", value_parser = super::threshold_preset())]
    pub thresholds: Option<ThresholdPreset>,
    /// Per-pixel |flow| above which a pixel belongs to a patch, full-resolution
    /// px [default: that of --thresholds or the calibration].
    #[arg(long, value_name = "PX", value_parser = magnitude)]
    pub magnitude: Option<f32>,
    /// Smallest summed |flow| of a patch [default: that of --thresholds or the
    /// calibration].
    #[arg(long, value_name = "SUM", value_parser = sum)]
    pub sum: Option<f32>,
    /// Erosion kernel, px [default: that of --thresholds or the calibration].
    #[arg(long, value_name = "PX", value_parser = kernel)]
    pub erode: Option<usize>,
    /// Dilation kernel, px [default: that of --thresholds or the calibration].
    #[arg(long, value_name = "PX", value_parser = kernel)]
    pub dilate: Option<usize>,
    /// Cut a patch holding several contacts side by side (the split rule).
    #[arg(long, value_name = "on|off", default_value = "on", action = clap::ArgAction::Set, value_parser = super::on_off)]
    pub split: bool,
    /// DIS flow preset [default: the calibration's].
    #[arg(long, value_name = "PRESET", ignore_case = true, value_parser = super::dis_preset())]
    pub preset: Option<DisPreset>,
    /// Take the camera's exposure changes (gain, black level) out of each
    /// frame against the reference: auto (gain and offset, once the gain
    /// departs by more than 1%: steps and drift), gain-offset (every frame),
    /// offset or off [default: the calibration's; auto with --raw].
    #[arg(long, value_name = "MODE", value_parser = exposure)]
    pub exposure: Option<ExposureCompensation>,
    /// Follow the dots of a regular marker grid one by one and write their
    /// motion over the flow (docs/pipeline.md, step 4) [default: the
    /// calibration's; on with --raw, where the reference shows a regular
    /// grid]. Changes nothing on random markers.
    #[arg(long, value_name = "on|off", action = clap::ArgAction::Set, value_parser = super::on_off)]
    pub dot_tracking: Option<bool>,
    /// With the dots followed, read each contact's shear and normal
    /// displacements from a round load's field fitted to its dots
    /// (docs/pipeline.md, step 7) [default: the calibration's; on with
    /// --raw].
    #[arg(long, value_name = "on|off", action = clap::ArgAction::Set, value_parser = super::on_off)]
    pub dot_fit: Option<bool>,
    /// Which channel of colour frames becomes the grey image.
    #[arg(long, value_name = "green|luma", default_value = "green", value_parser = channel)]
    pub channel: Channel,
}

impl PipelineArgs {
    /// The pipeline these flags ask for: the raw extractor, or the sensor as
    /// the calibration was fitted with the flags' overrides, then `configure`.
    pub fn build(&self, configure: impl FnOnce(&mut SensorConfig)) -> Result<Pipeline, String> {
        if self.raw {
            let exposure = self.exposure.unwrap_or_default();
            let raw = Raw::new(self.crop, self.preset, self.thresholds, exposure)?
                .with_overrides(self)?;
            return Ok(Pipeline::Raw(Box::new(raw)));
        }
        let path = &self.calibration;
        if !path.exists() {
            return Err(format!(
                "calibration file {} not found: fit one with `cargo run --release --example \
                 calibrate -- DATASET_DIR --out {}` (see the README), pass --calibration FILE, \
                 or run with --raw",
                path.display(),
                path.display()
            ));
        }
        let cal = Calibration::load(path).map_err(|e| format!("cannot load calibration: {e}"))?;
        let mut b = TactileSensor::builder(cal);
        if let Some(crop) = self.crop {
            b = b.crop(crop).force_crop(self.force_crop);
        }
        if let Some(p) = self.preset {
            b = b.flow(DisParams::preset(p));
        }
        if let Some(t) = self.thresholds {
            b = b.thresholds(t);
        }
        let exposure = self.exposure;
        let sensor = b
            .configure(|c| {
                if let Some(e) = exposure {
                    c.extractor.exposure = e;
                }
                self.override_extractor(&mut c.extractor);
                configure(c);
            })
            .build()
            .map_err(|e| e.to_string().replace("set force_crop", "pass --force-crop"))?;
        Ok(Pipeline::Calibrated(Box::new(sensor)))
    }
}

impl PipelineArgs {
    /// `thresholds` with the single-value flags (`--magnitude`, `--sum`,
    /// `--erode`, `--dilate`) applied.
    pub fn override_thresholds(&self, mut t: Thresholds) -> Thresholds {
        if let Some(m) = self.magnitude {
            t.magnitude = m;
        }
        if let Some(s) = self.sum {
            t.sum = s;
        }
        if let Some(k) = self.erode {
            t.erode = k;
        }
        if let Some(k) = self.dilate {
            t.dilate = k;
        }
        t
    }

    /// The single-value threshold flags and `--split` applied to `c`.
    fn override_extractor(&self, c: &mut ExtractorConfig) {
        c.thresholds = self.override_thresholds(c.thresholds);
        // On: the rule already set (a calibration's geometry's), else the
        // library's default.
        if !self.split {
            c.split = None;
        } else if c.split.is_none() {
            c.split = Some(SplitRule::DEFAULT);
        }
        if let Some(on) = self.dot_tracking {
            c.dot_tracking = on;
        }
        if let Some(on) = self.dot_fit {
            c.dot_fit = on;
        }
    }
}

/// Parses `--magnitude`: a finite number of pixels in `[0, 100]`.
pub fn magnitude(s: &str) -> Result<f32, String> {
    s.parse::<f32>()
        .ok()
        .filter(|x| (0.0..=100.0).contains(x))
        .ok_or_else(|| format!("expected a number of pixels in [0, 100], got `{s}`"))
}

/// Parses `--sum`: a finite number in `[0, 1e9]`.
pub fn sum(s: &str) -> Result<f32, String> {
    s.parse::<f32>()
        .ok()
        .filter(|x| (0.0..=1e9).contains(x))
        .ok_or_else(|| format!("expected a number in [0, 1e9], got `{s}`"))
}

/// Parses `--erode` and `--dilate`: a kernel side in `1..=255` px.
pub fn kernel(s: &str) -> Result<usize, String> {
    s.parse::<usize>()
        .ok()
        .filter(|k| (1..=MAX_KERNEL_PX).contains(k))
        .ok_or_else(|| format!("expected a kernel side in 1..={MAX_KERNEL_PX} px, got `{s}`"))
}

/// Parses `--exposure`: `auto`, `gain-offset`, `offset` or `off`.
pub fn exposure(s: &str) -> Result<ExposureCompensation, String> {
    ExposureCompensation::parse(s).map_err(|e| e.to_string())
}

/// Parses `--channel`: `green` or `luma`.
pub fn channel(s: &str) -> Result<Channel, String> {
    match s.to_ascii_lowercase().as_str() {
        "green" => Ok(Channel::Green),
        "luma" => Ok(Channel::Luma),
        _ => Err(format!("expected green or luma, got `{s}`")),
    }
}

/// The header of the calibrated table.
pub fn contact_header() -> String {
    format!(
        "{:<14} {:>7} {:>4} {:>8} {:>8} {:>8} {:>7} {:>7} {:>7} {:>8}",
        "frame", "t_s", "id", "x_mm", "y_mm", "z_mm", "fx_n", "fy_n", "fz_n", "ms"
    )
}

/// The header of the raw table.
pub fn patch_header() -> String {
    format!(
        "{:<14} {:>7} {:>3} {:>8} {:>7} {:>18} {:>9} {:>9} {:>9} {:>9} {:>7} {:>8}",
        "frame",
        "t_s",
        "k",
        "x_px",
        "y_px",
        "box x,y,w,h",
        "strength",
        "ds1",
        "ds2",
        "dn",
        "d_pf",
        "ms"
    )
}

/// Without a calibration: the library's [`RawSensor`] on the crop (the
/// whole frame unless one is given), with the library's default flow and
/// thresholds unless given.
pub struct Raw {
    /// The raw pipeline.
    pub sensor: RawSensor,
}

impl Raw {
    /// The raw pipeline with these overrides of the library's defaults.
    pub fn new(
        crop: Option<Roi>,
        preset: Option<DisPreset>,
        thresholds: Option<ThresholdPreset>,
        exposure: ExposureCompensation,
    ) -> Result<Raw, String> {
        let config = Self::config(preset, thresholds, exposure);
        Ok(Raw {
            sensor: RawSensor::new(config, crop).map_err(|e| e.to_string())?,
        })
    }

    fn config(
        preset: Option<DisPreset>,
        thresholds: Option<ThresholdPreset>,
        exposure: ExposureCompensation,
    ) -> ExtractorConfig {
        let mut config = ExtractorConfig::default().with_exposure(exposure);
        if let Some(p) = preset {
            config = config.with_flow(DisParams::preset(p));
        }
        if let Some(t) = thresholds {
            config = config.with_thresholds(t);
        }
        config
    }

    /// The extractor rebuilt with the single-value threshold flags and
    /// `--split` of `args` applied.
    fn with_overrides(mut self, args: &PipelineArgs) -> Result<Raw, String> {
        let mut config = self.sensor.extractor().config().clone();
        args.override_extractor(&mut config);
        self.sensor = RawSensor::new(config, self.sensor.crop()).map_err(|e| e.to_string())?;
        Ok(self)
    }

    /// The crop, `None` for the whole frame.
    pub fn crop(&self) -> Option<Roi> {
        self.sensor.crop()
    }
}

/// What runs on the frames: the calibrated sensor, or the raw extractor.
pub enum Pipeline {
    /// The calibrated sensor.
    Calibrated(Box<TactileSensor>),
    /// The raw extractor.
    Raw(Box<Raw>),
}

/// One frame's findings.
pub enum Found {
    /// Calibrated, tracked contacts.
    Contacts(Vec<Contact>),
    /// Raw patches.
    Patches(Vec<RawContact>),
}

impl Found {
    /// Writes the frame's JSON Lines record (calibrated contacts or raw
    /// patches, in the same per-frame layout).
    pub fn json_line(
        &self,
        w: &mut super::Sink,
        frame: &str,
        t_s: f64,
        latency_ms: f64,
    ) -> Result<(), super::Failure> {
        let (frame, latency_ms) = (frame.to_string(), Some(latency_ms));
        match self {
            Found::Contacts(c) => w.json_line(&FrameRecord {
                frame,
                t_s,
                contacts: c.iter().map(Contact::to_record).collect(),
                latency_ms,
            }),
            Found::Patches(p) => w.json_line(&FrameRecord {
                frame,
                t_s,
                contacts: p.iter().map(RawContact::to_record).collect(),
                latency_ms,
            }),
        }
    }
}

impl Pipeline {
    /// Takes a whole camera frame as the reference.
    pub fn set_reference(&mut self, frame: &Array2<f32>) -> optical_tactile::Result<()> {
        match self {
            Pipeline::Calibrated(s) => s.set_reference(frame),
            Pipeline::Raw(r) => r.sensor.set_reference(frame),
        }
    }

    /// Processes a whole camera frame.
    pub fn process(&mut self, frame: &Array2<f32>, t_s: f64) -> optical_tactile::Result<Found> {
        match self {
            Pipeline::Calibrated(s) => Ok(Found::Contacts(s.process(frame, t_s)?.to_vec())),
            Pipeline::Raw(r) => Ok(Found::Patches(r.sensor.process(frame)?.to_vec())),
        }
    }

    /// The debug panel of the last frame.
    pub fn debug_panel(&self) -> viz::Canvas {
        match self {
            Pipeline::Calibrated(s) => viz::debug_panel(s),
            Pipeline::Raw(r) => r.sensor.debug_panel(),
        }
    }

    /// The extractor (flow, patches, segmentation of the last frame).
    pub fn extractor(&self) -> &ContactExtractor {
        match self {
            Pipeline::Calibrated(s) => s.extractor(),
            Pipeline::Raw(r) => r.sensor.extractor(),
        }
    }

    /// The stage timings of the last frame.
    pub fn timings(&self) -> StageTimings {
        match self {
            Pipeline::Calibrated(s) => *s.timings(),
            Pipeline::Raw(r) => *r.sensor.extractor().timings(),
        }
    }

    /// Whether the last frame became the new reference.
    pub fn rereferenced(&self) -> bool {
        matches!(self, Pipeline::Calibrated(s) if s.rereferenced())
    }
}

/// The calibrated table's row of a contact, with its marks.
pub fn contact_row(name: &str, t_s: f64, c: &Contact, latency_ms: f64) -> String {
    let [x, y, z] = c.location_mm;
    let [fx, fy, fz] = c.force_n;
    let mut marks = String::new();
    for (on, mark) in [
        (c.missed > 0, " (held)"),
        (c.fallback, " (fallback)"),
        (c.out_of_domain, " (out of domain)"),
    ] {
        if on {
            marks.push_str(mark);
        }
    }
    format!(
        "{name:<14} {t_s:>7.3} {:>4} {x:>8.2} {y:>8.2} {z:>8.2} {fx:>7.3} {fy:>7.3} {fz:>7.3} {latency_ms:>8.1}{marks}",
        c.id
    )
}

/// The raw table's row of a patch.
pub fn patch_row(name: &str, t_s: f64, k: usize, r: &RawContact, latency_ms: f64) -> String {
    let b = r.bbox;
    format!(
        "{name:<14} {t_s:>7.3} {k:>3} {:>8.1} {:>7.1} {:>18} {:>9.0} {:>9.1} {:>9.1} {:>9.1} {:>7.2} {latency_ms:>8.1}",
        r.x_px,
        r.y_px,
        format!("{},{},{},{}", b.x, b.y, b.w, b.h),
        r.strength,
        r.ds1,
        r.ds2,
        r.dn,
        r.d_pf,
    )
}
