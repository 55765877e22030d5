//! The pipeline thread: reads frames (a sequence in a loop, or the camera),
//! rebuilds the pipeline when the page changed a setting, processes, draws
//! the panel and publishes it. It never waits for the page.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use ndarray::Array2;
use optical_tactile::calibration::fit::preset_name;
use optical_tactile::capture::{Frame, FrameSource, SequenceSource};
use optical_tactile::flow::FlowField;
use optical_tactile::flow::dis::DisPreset;
use optical_tactile::frame::Channel;
use optical_tactile::segment::{RestOptions, Thresholds};
use optical_tactile::track::FilterConfig;
use serde_json::{Value, json};

use crate::app::{App, FrameView, PanelView, REST_FRAMES, Rest, Settings};
use crate::cli_support::pipeline::{Found, Pipeline, PipelineArgs};

/// Most bytes of decoded frames a looped sequence keeps in memory (beyond
/// that it is read from disk on every loop).
const CACHE_BYTES: usize = 256 << 20;

/// Where frames come from.
pub enum Source {
    /// A folder of frames, played in a loop.
    Sequence(Looped),
    /// A live camera (or any other endless source).
    #[cfg_attr(not(feature = "v4l"), allow(dead_code))]
    Live(Box<dyn FrameSource>),
}

/// A sequence played in a loop, kept in memory when it fits [`CACHE_BYTES`].
pub struct Looped {
    dir: std::path::PathBuf,
    channel: Channel,
    open: Option<SequenceSource>,
    cache: Vec<Frame>,
    cache_bytes: usize,
    /// The whole sequence is in `cache`.
    cached: bool,
    next: usize,
    /// Added to every frame's time: one more sequence length per loop.
    offset_s: f64,
    last_t: f64,
    period_s: f64,
    readable_in_pass: usize,
}

impl Looped {
    /// Opens `dir` (errors if it is not a readable sequence).
    pub fn open(dir: &std::path::Path, channel: Channel) -> Result<Looped, String> {
        let seq = SequenceSource::open(dir)
            .map_err(|e| format!("cannot open sequence: {e}"))?
            .with_channel(channel);
        if seq.is_empty() {
            return Err(format!("no frame in {}", dir.display()));
        }
        Ok(Looped {
            dir: dir.to_path_buf(),
            channel,
            open: Some(seq),
            cache: Vec::new(),
            cache_bytes: 0,
            cached: false,
            next: 0,
            offset_s: 0.0,
            last_t: 0.0,
            period_s: 0.02,
            readable_in_pass: 0,
        })
    }

    fn next_frame(&mut self) -> Result<Frame, String> {
        loop {
            if self.cached {
                if self.next == self.cache.len() {
                    self.wrap();
                }
                let mut f = self.cache[self.next].clone();
                self.next += 1;
                f.t_s += self.offset_s;
                return Ok(f);
            }
            let seq = match &mut self.open {
                Some(s) => s,
                None => {
                    let s = SequenceSource::open(&self.dir)
                        .map_err(|e| format!("cannot reopen sequence: {e}"))?
                        .with_channel(self.channel);
                    self.open.insert(s)
                }
            };
            match seq.next_frame() {
                Some(Ok(f)) => {
                    self.readable_in_pass += 1;
                    if f.index == 1 {
                        self.period_s = (f.t_s - self.last_t).max(1e-3);
                    }
                    self.last_t = f.t_s;
                    let bytes = f.image.len() * 4;
                    if self.offset_s == 0.0 && self.cache_bytes + bytes <= CACHE_BYTES {
                        self.cache.push(f.clone());
                        self.cache_bytes += bytes;
                    } else {
                        self.cache = Vec::new();
                        self.cache_bytes = usize::MAX / 2;
                    }
                    let mut f = f;
                    f.t_s += self.offset_s;
                    return Ok(f);
                }
                Some(Err(e)) => return Err(format!("unreadable frame: {e}")),
                None => {
                    if self.readable_in_pass == 0 {
                        return Err(format!("no readable frame in {}", self.dir.display()));
                    }
                    self.cached = self.offset_s == 0.0 && self.cache_bytes <= CACHE_BYTES;
                    self.open = None;
                    self.readable_in_pass = 0;
                    self.wrap();
                }
            }
        }
    }

    fn wrap(&mut self) {
        self.next = 0;
        self.offset_s += self.last_t + self.period_s;
    }
}

impl Source {
    fn next_frame(&mut self) -> Result<Frame, String> {
        match self {
            Source::Sequence(s) => s.next_frame(),
            Source::Live(c) => c
                .next_frame()
                .ok_or("the camera stream ended")?
                .map_err(|e| e.to_string()),
        }
    }
}

/// Builds the pipeline `base` describes with the page's settings.
pub fn build(base: &PipelineArgs, s: &Settings) -> Result<Pipeline, String> {
    let mut a = base.clone();
    a.thresholds = None;
    a.magnitude = Some(s.thresholds.magnitude);
    a.sum = Some(s.thresholds.sum);
    a.erode = Some(s.thresholds.erode);
    a.dilate = Some(s.thresholds.dilate);
    a.preset = Some(s.flow);
    a.split = s.split;
    a.build(|c| {
        c.tracker.filter = s.filter.then(FilterConfig::default);
        c.rereference.enabled = s.rereference;
    })
}

/// The settings a freshly built pipeline runs with.
pub fn settings_of(p: &Pipeline, split: bool, filter: bool, rereference: bool) -> Settings {
    let c = p.extractor().config();
    Settings {
        thresholds: c.thresholds,
        flow: DisPreset::parse(&preset_name(c)).unwrap_or(DisPreset::Fine),
        split,
        filter,
        rereference,
    }
}

/// The pipeline thread's state.
pub struct Runner {
    app: Arc<App>,
    base: PipelineArgs,
    pipeline: Pipeline,
    applied: u64,
    source: Source,
    /// The whole camera frame the pipeline's reference was taken from.
    reference: Option<Array2<f32>>,
    /// The last frame processed (re-processed when a setting changes while
    /// paused).
    last: Option<Frame>,
    rest_flows: Vec<FlowField>,
    seq: u64,
    published: VecDeque<Instant>,
    /// A sequence's frame period when it is played at a set rate.
    period: Option<Duration>,
    /// When the next frame of a sequence is due.
    due: Instant,
}

impl Runner {
    /// A runner of `pipeline` (built from `base` and the app's settings) on
    /// `source`.
    pub fn new(
        app: Arc<App>,
        base: PipelineArgs,
        pipeline: Pipeline,
        source: Source,
        play_fps: f64,
    ) -> Runner {
        let applied = app.lock().version;
        let period = (play_fps > 0.0 && matches!(source, Source::Sequence(_)))
            .then(|| Duration::from_secs_f64(1.0 / play_fps));
        Runner {
            period,
            due: Instant::now(),
            app,
            base,
            pipeline,
            applied,
            source,
            reference: None,
            last: None,
            rest_flows: Vec::new(),
            seq: 0,
            published: VecDeque::new(),
        }
    }

    /// Runs until the process ends.
    pub fn run(mut self) {
        loop {
            if let Err(e) = self.turn() {
                self.app.lock().error = Some(e);
                // A failing source (a camera gone): do not spin.
                std::thread::sleep(Duration::from_millis(200));
            }
        }
    }

    /// One turn: settings, then one frame (or a wait while paused).
    fn turn(&mut self) -> Result<(), String> {
        let (settings, version, step, take_reference, rest) = {
            let mut st = self.app.lock();
            while st.paused && st.steps == 0 && st.version == self.applied && !st.take_reference {
                if self.seq > 0 && st.panel.as_ref().is_none_or(|p| p.seq < self.seq) {
                    // Paused on a frame whose panel was skipped: draw it.
                    drop(st);
                    self.publish_panel();
                    st = self.app.lock();
                    continue;
                }
                st = self
                    .app
                    .changed
                    .wait_timeout(st, Duration::from_millis(250))
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
            }
            let step = !st.paused || st.steps > 0;
            st.steps = st.steps.saturating_sub(1);
            let take = std::mem::take(&mut st.take_reference);
            let rest = std::mem::take(&mut st.rest_request);
            (st.settings.clone(), st.version, step, take, rest)
        };
        if rest {
            self.rest_flows.clear();
        }
        if version != self.applied {
            match build(&self.base, &settings) {
                Ok(p) => {
                    self.pipeline = p;
                    self.rest_flows.clear();
                    if let Some(r) = &self.reference {
                        self.pipeline
                            .set_reference(r)
                            .map_err(|e| format!("cannot take the reference again: {e}"))?;
                    }
                }
                Err(e) => self.app.lock().error = Some(format!("settings not applied: {e}")),
            }
            self.applied = version;
            if !step {
                // Paused: show the change on the frame on screen.
                if let Some(f) = self.last.clone() {
                    self.process(&f)?;
                }
                return Ok(());
            }
        }
        if !step && !take_reference {
            return Ok(());
        }
        if let Some(period) = self.period {
            let now = Instant::now();
            if self.due > now {
                std::thread::sleep(self.due - now);
            }
            self.due = self.due.max(now - period) + period;
        }
        let frame = self.source.next_frame()?;
        if take_reference || self.reference.is_none() {
            self.pipeline.set_reference(&frame.image).map_err(|e| {
                format!("frame {}: cannot take it as the reference: {e}", frame.name)
            })?;
            self.reference = Some(frame.image.clone());
            self.last = None;
            return Ok(());
        }
        self.process(&frame)?;
        self.last = Some(frame);
        Ok(())
    }

    fn process(&mut self, frame: &Frame) -> Result<(), String> {
        let t = Instant::now();
        let found = match self.pipeline.process(&frame.image, frame.t_s) {
            Ok(f) => f,
            Err(e) => {
                self.app.lock().error = Some(format!("frame {}: {e}", frame.name));
                return Ok(());
            }
        };
        let process_ms = t.elapsed().as_secs_f64() * 1e3;
        if self.pipeline.rereferenced() {
            self.reference = Some(frame.image.clone());
        }
        let draw = {
            let st = self.app.lock();
            st.panel.is_none() || st.panel_fetched || st.paused
        };
        let t = Instant::now();
        let panel = draw.then(|| self.pipeline.debug_panel());
        let panel_ms = t.elapsed().as_secs_f64() * 1e3;
        let rest = self.collect_rest();
        let info = self.info(frame, &found, process_ms, draw.then_some(panel_ms));
        self.seq += 1;
        let now = Instant::now();
        self.published.push_back(now);
        while self
            .published
            .front()
            .is_some_and(|t| now.duration_since(*t) > Duration::from_secs(5))
        {
            self.published.pop_front();
        }
        let fps = match (self.published.front(), self.published.len()) {
            (Some(first), n) if n > 1 => {
                (n - 1) as f64 / now.duration_since(*first).as_secs_f64().max(1e-6)
            }
            _ => 0.0,
        };
        let mut st = self.app.lock();
        st.frame = Some(Arc::new(FrameView {
            seq: self.seq,
            info,
        }));
        if let Some(canvas) = panel {
            st.panel = Some(Arc::new(PanelView {
                seq: self.seq,
                canvas,
            }));
            st.panel_fetched = false;
        }
        st.fps = fps;
        st.error = None;
        if let Some(rest) = rest {
            match rest {
                Ok(t) => {
                    st.rest = Rest::Done(format!(
                        "from {REST_FRAMES} rest frames: magnitude {} px, sum {}",
                        t.magnitude, t.sum
                    ));
                    st.settings.thresholds = t;
                    st.version += 1;
                }
                Err(e) => st.rest = Rest::Failed(e),
            }
        } else if let Rest::Collecting(_) = st.rest {
            st.rest = Rest::Collecting(self.rest_flows.len());
        }
        drop(st);
        self.app.changed.notify_all();
        Ok(())
    }

    /// Draws the last frame's panel and publishes it.
    fn publish_panel(&mut self) {
        let canvas = self.pipeline.debug_panel();
        let mut st = self.app.lock();
        st.panel = Some(Arc::new(PanelView {
            seq: self.seq,
            canvas,
        }));
        st.panel_fetched = false;
        drop(st);
        self.app.changed.notify_all();
    }

    /// Adds the last flow to the rest flows when they are being collected;
    /// the thresholds once there are enough.
    fn collect_rest(&mut self) -> Option<Result<Thresholds, String>> {
        let collecting = matches!(self.app.lock().rest, Rest::Collecting(_));
        if !collecting {
            return None;
        }
        let (flow, scale) = self.pipeline.extractor().flow();
        self.rest_flows.push(flow.clone());
        if self.rest_flows.len() < REST_FRAMES {
            return None;
        }
        let options = RestOptions {
            scale: scale as f64,
            kernels: self.pipeline.extractor().config().thresholds,
            ..RestOptions::default()
        };
        let result = Thresholds::from_rest(&self.rest_flows, &options).map_err(|e| e.to_string());
        self.rest_flows.clear();
        Some(result)
    }

    fn info(&self, frame: &Frame, found: &Found, process_ms: f64, panel_ms: Option<f64>) -> Value {
        let t = self.pipeline.timings();
        let items: Vec<Value> = match found {
            Found::Contacts(cs) => cs
                .iter()
                .map(|c| {
                    json!({
                        "id": c.id,
                        "location_mm": c.location_mm,
                        "force_n": c.force_n,
                        "force_sigma_n": c.force_sigma_n,
                        "held": c.missed > 0,
                        "fallback": c.fallback,
                        "out_of_domain": c.out_of_domain,
                    })
                })
                .collect(),
            Found::Patches(ps) => ps
                .iter()
                .map(|r| {
                    json!({
                        "x_px": r.x_px,
                        "y_px": r.y_px,
                        "box_px": [r.bbox.x, r.bbox.y, r.bbox.w, r.bbox.h],
                        "strength": r.strength,
                        "ds1": r.ds1,
                        "ds2": r.ds2,
                        "dn": r.dn,
                        "d_pf": r.d_pf,
                    })
                })
                .collect(),
        };
        let ex = self.pipeline.extractor();
        json!({
            "frame": frame.name,
            "index": frame.index,
            "t_s": frame.t_s,
            "patches": ex.patches().len(),
            "contacts": items.len(),
            "splits": ex.segmenter().split_count(),
            "rereferenced": self.pipeline.rereferenced(),
            "items": items,
            "timings_ms": {
                "crop": t.crop_ms,
                "flow": t.flow_ms,
                "segment": t.segment_ms,
                "hhd": t.hhd_ms,
                // The page's "contacts" column: calibration and tracking.
                "contacts": t.contacts_ms + t.tracking_ms,
                "process": process_ms,
                "panel": panel_ms,
            },
        })
    }
}
