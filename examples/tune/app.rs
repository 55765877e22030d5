//! What the page and the pipeline thread share, and the page's routes:
//! the settings the page may change (checked here, all or nothing), the
//! last frame's findings and panel, and the tuned calibration's file.

use std::fs::OpenOptions;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use image::ImageEncoder as _;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use optical_tactile::calibration::Calibration;
use optical_tactile::flow::dis::DisPreset;
use optical_tactile::segment::{MAX_KERNEL_PX, ThresholdPreset, Thresholds};
use optical_tactile::viz::Canvas;
use serde::Deserialize;
use serde_json::{Value, json};

use crate::http::{Request, Response};

/// The page, its script and style, embedded in the binary.
const PAGE_HTML: &str = include_str!("page.html");
const PAGE_JS: &str = include_str!("page.js");
const PAGE_CSS: &str = include_str!("page.css");

/// Largest `--magnitude` the page accepts, full-resolution px.
pub const MAX_MAGNITUDE: f32 = 100.0;
/// Largest `--sum` the page accepts.
pub const MAX_SUM: f32 = 1e9;
/// Rest frames collected for the automatic thresholds (at the default
/// false-contact rate of 1%, the fewest the estimate accepts).
pub const REST_FRAMES: usize = 100;
/// Longest wait of `GET /state?after=N` for a newer frame.
pub const LONG_POLL: Duration = Duration::from_secs(1);
/// Longest file name the page may save to, bytes.
pub const MAX_NAME_BYTES: usize = 128;

/// What the page may change; applied by the pipeline thread from the next
/// frame on.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Segmentation thresholds and kernels.
    pub thresholds: Thresholds,
    /// DIS flow preset.
    pub flow: DisPreset,
    /// The split rule on or off.
    pub split: bool,
    /// Kalman filter on the tracked contacts (calibrated mode).
    pub filter: bool,
    /// Re-referencing after a quiet spell (calibrated mode).
    pub rereference: bool,
}

impl Settings {
    /// As JSON for the page.
    pub fn to_json(&self) -> Value {
        let t = &self.thresholds;
        json!({
            "magnitude": decimal(t.magnitude),
            "sum": decimal(t.sum),
            "erode": t.erode,
            "dilate": t.dilate,
            "preset": t.as_preset().map_or("custom", ThresholdPreset::name),
            "flow": self.flow.name(),
            "split": self.split,
            "filter": self.filter,
            "rereference": self.rereference,
        })
    }
}

/// `x` as the f64 its shortest decimal form names (0.2f32 is 0.2, not
/// 0.20000000298023224), for JSON.
pub fn decimal(x: f32) -> f64 {
    x.to_string().parse().unwrap_or(f64::from(x))
}

/// The automatic thresholds from rest frames.
#[derive(Debug, Clone, PartialEq)]
pub enum Rest {
    /// Not asked for.
    Idle,
    /// Collecting flows: how many so far.
    Collecting(usize),
    /// Done: what was set.
    Done(String),
    /// Failed: why.
    Failed(String),
}

/// The last processed frame's findings.
pub struct FrameView {
    /// Increases with every published frame.
    pub seq: u64,
    /// Findings, counts and timings, as sent to the page.
    pub info: Value,
}

/// The debug panel (four rows) of a frame.
pub struct PanelView {
    /// The frame's [`FrameView::seq`].
    pub seq: u64,
    /// The panel.
    pub canvas: Canvas,
}

/// Everything the page and the pipeline thread share (behind a mutex).
pub struct State {
    /// The latest frame.
    pub frame: Option<Arc<FrameView>>,
    /// The latest panel drawn. The pipeline draws one only once the page
    /// has fetched the previous one (`panel_fetched`): a page slower than
    /// the pipeline costs it no drawing it will not show, and no page none.
    pub panel: Option<Arc<PanelView>>,
    /// The latest panel was fetched: the pipeline draws the next.
    pub panel_fetched: bool,
    /// The PNG of a panel: `(seq, bytes)`.
    pub png: Option<(u64, Arc<Vec<u8>>)>,
    /// How long the last PNG took to encode, ms.
    pub encode_ms: f64,
    /// The settings asked for.
    pub settings: Settings,
    /// Bumped on every settings change.
    pub version: u64,
    /// The settings the pipeline started with (the "calibration" preset).
    pub initial: Settings,
    /// Paused: no frame is processed unless stepped.
    pub paused: bool,
    /// Frames to process while paused.
    pub steps: u32,
    /// Take the next frame as the reference.
    pub take_reference: bool,
    /// Collect rest flows for the automatic thresholds.
    pub rest_request: bool,
    /// The automatic thresholds' progress.
    pub rest: Rest,
    /// The pipeline's last error (a frame it could not process).
    pub error: Option<String>,
    /// Frames per second the pipeline thread publishes.
    pub fps: f64,
}

impl State {
    /// The state at start: `settings` asked for and started with, playing,
    /// nothing seen yet.
    pub fn new(settings: Settings) -> State {
        State {
            frame: None,
            panel: None,
            panel_fetched: false,
            png: None,
            encode_ms: 0.0,
            settings: settings.clone(),
            version: 0,
            initial: settings,
            paused: false,
            steps: 0,
            take_reference: false,
            rest_request: false,
            rest: Rest::Idle,
            error: None,
            fps: 0.0,
        }
    }
}

/// The fixed facts of the run and the shared state.
pub struct App {
    /// The shared state.
    pub state: Mutex<State>,
    /// Signalled on every new frame and every control.
    pub changed: Condvar,
    /// The calibration loaded (`None` with `--raw`).
    pub calibration: Option<Calibration>,
    /// Where tuned calibrations are saved.
    pub save_dir: PathBuf,
    /// The `track` flags that do not change (input, calibration, crop, ...).
    pub fixed_args: Vec<String>,
    /// Served on a loopback address only: requests must name it (or
    /// `localhost`) as their host.
    pub loopback_only: bool,
}

/// Whether a `Host` header names a loopback address or `localhost` (any
/// port).
pub fn is_loopback_host(host: &str) -> bool {
    let name = match host.strip_prefix('[') {
        Some(rest) => rest.split(']').next().unwrap_or(""),
        None => host.rsplit_once(':').map_or(host, |(n, _)| n),
    };
    name.eq_ignore_ascii_case("localhost")
        || name
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

impl App {
    /// Locks the state (a poisoned lock is taken over: the state stays valid
    /// between statements).
    pub fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Answers one request.
    pub fn handle(&self, rq: &Request) -> Response {
        // A page of another site must not drive this one: through a name
        // that resolves to this machine (DNS rebinding), or with a form's
        // plain-text POST (JSON needs a preflight, which is not answered).
        if self.loopback_only
            && let Some(host) = &rq.host
            && !is_loopback_host(host)
        {
            return Response::error(421, format!("host {host}: use 127.0.0.1 or localhost"));
        }
        if rq.method == "POST"
            && rq
                .content_type
                .as_deref()
                .is_none_or(|t| !t.trim_start().starts_with("application/json"))
        {
            return Response::error(415, "send the body as Content-Type: application/json");
        }
        match (rq.method.as_str(), rq.path.as_str()) {
            ("GET", "/") | ("GET", "/index.html") => {
                Response::new(200, "text/html; charset=utf-8", PAGE_HTML)
            }
            ("GET", "/app.js") => Response::new(200, "text/javascript; charset=utf-8", PAGE_JS),
            ("GET", "/app.css") => Response::new(200, "text/css; charset=utf-8", PAGE_CSS),
            ("GET", "/state") => self.get_state(rq),
            ("GET", "/frame.png") => self.get_png(rq),
            ("POST", "/control") => match parse_body::<Control>(rq) {
                Ok(c) => match self.apply(&c) {
                    Ok(()) => Response::json(200, &self.state_json(&self.lock())),
                    Err(m) => Response::error(400, m),
                },
                Err(r) => r,
            },
            ("POST", "/save") => match parse_body::<Save>(rq) {
                Ok(s) => self.save(&s.name),
                Err(r) => r,
            },
            (_, "/" | "/index.html" | "/app.js" | "/app.css" | "/state" | "/frame.png") => {
                Response::error(405, "method not allowed: use GET")
            }
            (_, "/control" | "/save") => Response::error(405, "method not allowed: use POST"),
            _ => Response::error(404, format!("no such page: {}", rq.path)),
        }
    }

    fn get_state(&self, rq: &Request) -> Response {
        let after = match rq.query_value("after").map(str::parse::<u64>) {
            None => None,
            Some(Ok(n)) => Some(n),
            Some(Err(_)) => return Response::error(400, "after: expected a frame number"),
        };
        let deadline = Instant::now() + LONG_POLL;
        let mut st = self.lock();
        if let Some(after) = after {
            // Long poll: wait for a frame newer than `after`, at most LONG_POLL.
            while st.frame.as_ref().is_none_or(|f| f.seq <= after) {
                let now = Instant::now();
                if now >= deadline {
                    break;
                }
                st = self
                    .changed
                    .wait_timeout(st, deadline - now)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
            }
        }
        Response::json(200, &self.state_json(&st))
    }

    /// The state as the page reads it.
    pub fn state_json(&self, st: &State) -> Value {
        let (seq, frame) = match &st.frame {
            Some(f) => (f.seq, f.info.clone()),
            None => (0, Value::Null),
        };
        let panel_seq = st.panel.as_ref().map_or(0, |p| p.seq);
        let rest = match &st.rest {
            Rest::Idle => json!({ "state": "idle" }),
            Rest::Collecting(n) => json!({ "state": "collecting", "frames": n, "of": REST_FRAMES }),
            Rest::Done(m) => json!({ "state": "done", "message": m }),
            Rest::Failed(m) => json!({ "state": "failed", "message": m }),
        };
        json!({
            "seq": seq,
            "panel_seq": panel_seq,
            "frame": frame,
            "settings": st.settings.to_json(),
            "paused": st.paused,
            "rest": rest,
            "error": st.error,
            "fps": st.fps,
            "encode_ms": st.encode_ms,
            "mode": if self.calibration.is_some() { "calibrated" } else { "raw" },
            "can_save": self.calibration.is_some(),
            "save_dir": self.save_dir.display().to_string(),
            "flow_presets": DisPreset::ALL.map(DisPreset::name),
            "command_line": self.command_line(&st.settings),
            "calibration_snippet": self.snippet(&st.settings),
        })
    }

    /// The latest panel as PNG, its frame number in `X-Panel-Seq`; with
    /// `?after=N`, waits up to [`LONG_POLL`] for a panel newer than `N`
    /// (`204` if none came).
    fn get_png(&self, rq: &Request) -> Response {
        let after = match rq.query_value("after").map(str::parse::<u64>) {
            None => None,
            Some(Ok(n)) => Some(n),
            Some(Err(_)) => return Response::error(400, "after: expected a frame number"),
        };
        let frame = {
            let deadline = Instant::now() + LONG_POLL;
            let mut st = self.lock();
            if let Some(after) = after {
                while st.panel.as_ref().is_none_or(|p| p.seq <= after) {
                    let now = Instant::now();
                    if now >= deadline {
                        return Response::new(204, "image/png", Vec::new());
                    }
                    st = self
                        .changed
                        .wait_timeout(st, deadline - now)
                        .unwrap_or_else(|e| e.into_inner())
                        .0;
                }
            }
            let Some(frame) = st.panel.clone() else {
                return Response::error(404, "no frame yet");
            };
            st.panel_fetched = true;
            if let Some((seq, png)) = &st.png
                && *seq == frame.seq
            {
                return Response::new(200, "image/png", png.as_slice())
                    .with_header("X-Panel-Seq", seq.to_string());
            }
            frame
        };
        let t = Instant::now();
        let png = match encode_png(&frame.canvas) {
            Ok(p) => Arc::new(p),
            Err(e) => return Response::error(500, format!("cannot encode the panel: {e}")),
        };
        let mut st = self.lock();
        st.encode_ms = t.elapsed().as_secs_f64() * 1e3;
        if st.png.as_ref().is_none_or(|(s, _)| *s < frame.seq) {
            st.png = Some((frame.seq, png.clone()));
        }
        Response::new(200, "image/png", png.as_slice())
            .with_header("X-Panel-Seq", frame.seq.to_string())
    }

    /// Applies a control (all of it, or nothing on an error).
    pub fn apply(&self, c: &Control) -> Result<(), String> {
        let mut st = self.lock();
        let mut s = st.settings.clone();
        if let Some(p) = &c.preset {
            s.thresholds = match p.as_str() {
                "calibration" | "initial" => st.initial.thresholds,
                name => name
                    .parse::<ThresholdPreset>()
                    .map_err(|e| format!("preset: {e}"))?
                    .thresholds(),
            };
        }
        if let Some(m) = c.magnitude {
            if !(m.is_finite() && (0.0..=f64::from(MAX_MAGNITUDE)).contains(&m)) {
                return Err(format!(
                    "magnitude: expected 0 to {MAX_MAGNITUDE} px, got {m}"
                ));
            }
            s.thresholds.magnitude = m as f32;
        }
        if let Some(v) = c.sum {
            if !(v.is_finite() && (0.0..=f64::from(MAX_SUM)).contains(&v)) {
                return Err(format!("sum: expected 0 to {MAX_SUM}, got {v}"));
            }
            s.thresholds.sum = v as f32;
        }
        for (name, k, slot) in [
            ("erode", c.erode, &mut s.thresholds.erode),
            ("dilate", c.dilate, &mut s.thresholds.dilate),
        ] {
            if let Some(k) = k {
                if !(1..=MAX_KERNEL_PX as u64).contains(&k) {
                    return Err(format!(
                        "{name}: expected a kernel side of 1 to {MAX_KERNEL_PX} px, got {k}"
                    ));
                }
                *slot = k as usize;
            }
        }
        if let Some(f) = &c.flow {
            s.flow = DisPreset::parse(f).map_err(|e| format!("flow: {e}"))?;
        }
        if let Some(v) = c.split {
            s.split = v;
        }
        if let Some(v) = c.filter {
            s.filter = v;
        }
        if let Some(v) = c.rereference {
            s.rereference = v;
        }
        s.thresholds.validate().map_err(|e| e.to_string())?;
        if s != st.settings {
            st.settings = s;
            st.version += 1;
        }
        if let Some(p) = c.paused {
            st.paused = p;
        }
        if c.step == Some(true) {
            st.steps = st.steps.saturating_add(1).min(100);
        }
        if c.reference == Some(true) {
            st.take_reference = true;
        }
        if c.rest_estimate == Some(true) {
            st.rest_request = true;
            st.rest = Rest::Collecting(0);
        }
        drop(st);
        self.changed.notify_all();
        Ok(())
    }

    /// The `track` command line with these settings.
    pub fn command_line(&self, s: &Settings) -> String {
        let t = &s.thresholds;
        let mut args = vec![
            "cargo run --release --example track --".to_string(),
            self.fixed_args.join(" "),
        ];
        if let Some(p) = t.as_preset() {
            args.push(format!("--thresholds {p}"));
        } else {
            args.push(format!(
                "--magnitude {} --sum {} --erode {} --dilate {}",
                t.magnitude, t.sum, t.erode, t.dilate
            ));
        }
        args.push(format!("--preset {}", s.flow.name()));
        if !s.split {
            args.push("--split off".to_string());
        }
        if self.calibration.is_some() {
            args.push(format!("--filter {}", on_off(s.filter)));
            args.push(format!("--rereference {}", on_off(s.rereference)));
        }
        args.retain(|a| !a.is_empty());
        args.join(" ")
    }

    /// The calibration with the tuned thresholds and flow preset, if there
    /// is one.
    pub fn tuned(&self, s: &Settings) -> Option<Calibration> {
        let mut cal = self.calibration.clone()?;
        cal.setup.thresholds = s.thresholds;
        if let Some(p) = &mut cal.setup.pipeline {
            p.flow_preset = s.flow.name().to_string();
        }
        Some(cal)
    }

    /// The calibration file's `thresholds` (and `pipeline`) entries with
    /// these settings, as JSON text.
    pub fn snippet(&self, s: &Settings) -> String {
        let t = &s.thresholds;
        let value = match self.tuned(s).map(|c| c.to_json_string()) {
            Some(text) => match serde_json::from_str::<Value>(&text) {
                Ok(v) => json!({ "thresholds": v["thresholds"], "pipeline": v["pipeline"] }),
                Err(e) => json!({ "error": e.to_string() }),
            },
            None => json!({ "thresholds": {
                "preset": t.as_preset().map_or("custom", ThresholdPreset::name),
                "magnitude": decimal(t.magnitude),
                "sum": decimal(t.sum),
                "erode": t.erode,
                "dilate": t.dilate,
            }}),
        };
        serde_json::to_string_pretty(&value).unwrap_or_default()
    }

    /// Saves the tuned calibration as `name` in the save directory: a new
    /// file only, a plain name ending in `.json`.
    pub fn save(&self, name: &str) -> Response {
        let settings = self.lock().settings.clone();
        let Some(cal) = self.tuned(&settings) else {
            return Response::error(409, "no calibration to save in --raw mode");
        };
        if let Err(m) = check_name(name) {
            return Response::error(400, m);
        }
        let path = self.save_dir.join(name);
        let text = cal.to_json_string();
        // What is written must load back.
        if let Err(e) = Calibration::from_json_str(&text) {
            return Response::error(500, format!("the tuned calibration does not load: {e}"));
        }
        let file = OpenOptions::new().write(true).create_new(true).open(&path);
        let mut file = match file {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                return Response::error(
                    409,
                    format!("{} exists: choose a new name", path.display()),
                );
            }
            Err(e) => {
                return Response::error(500, format!("cannot create {}: {e}", path.display()));
            }
        };
        if let Err(e) = file
            .write_all(text.as_bytes())
            .and_then(|()| file.sync_all())
        {
            return Response::error(500, format!("cannot write {}: {e}", path.display()));
        }
        Response::json(201, &json!({ "path": path.display().to_string() }))
    }
}

/// A control from the page: any subset of the fields; any other field is an
/// error.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Control {
    /// `--magnitude`, px.
    pub magnitude: Option<f64>,
    /// `--sum`.
    pub sum: Option<f64>,
    /// `--erode`, px.
    pub erode: Option<u64>,
    /// `--dilate`, px.
    pub dilate: Option<u64>,
    /// A threshold preset: `low`, `mid`, `high` or `calibration` (the
    /// thresholds the run started with).
    pub preset: Option<String>,
    /// The flow preset by name.
    pub flow: Option<String>,
    /// The split rule on or off.
    pub split: Option<bool>,
    /// The Kalman filter on or off.
    pub filter: Option<bool>,
    /// Re-referencing on or off.
    pub rereference: Option<bool>,
    /// Pause or play.
    pub paused: Option<bool>,
    /// Process one frame while paused.
    pub step: Option<bool>,
    /// Take the next frame as the reference.
    pub reference: Option<bool>,
    /// Estimate the thresholds from the next rest frames.
    pub rest_estimate: Option<bool>,
}

/// `POST /save`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Save {
    name: String,
}

fn parse_body<T: serde::de::DeserializeOwned>(rq: &Request) -> Result<T, Response> {
    let text = std::str::from_utf8(&rq.body)
        .map_err(|_| Response::error(400, "the body is not UTF-8 text"))?;
    serde_json::from_str(text).map_err(|e| Response::error(400, format!("bad JSON: {e}")))
}

/// A plain file name ending in `.json`: letters, digits, `.`, `-`, `_`,
/// not starting with `.`, at most [`MAX_NAME_BYTES`].
pub fn check_name(name: &str) -> Result<(), String> {
    let ok_chars = name
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_'));
    if name.len() > MAX_NAME_BYTES
        || !ok_chars
        || name.starts_with('.')
        || !name.ends_with(".json")
        || name.len() <= ".json".len()
    {
        return Err(format!(
            "`{}`: expected a plain file name ending in .json (letters, digits, . - _; \
             at most {MAX_NAME_BYTES} bytes), saved in the save directory",
            name.chars().take(MAX_NAME_BYTES).collect::<String>()
        ));
    }
    Ok(())
}

fn on_off(b: bool) -> &'static str {
    if b { "on" } else { "off" }
}

/// The panel as PNG, fast compression (the page reloads it every frame).
pub fn encode_png(canvas: &Canvas) -> image::ImageResult<Vec<u8>> {
    let mut out = Vec::with_capacity(canvas.as_bytes().len() / 4);
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Sub).write_image(
        canvas.as_bytes(),
        canvas.width() as u32,
        canvas.height() as u32,
        image::ExtendedColorType::Rgb8,
    )?;
    Ok(out)
}

/// The save directory as given, checked to be one.
pub fn save_dir(dir: &Path) -> Result<PathBuf, String> {
    let meta = std::fs::metadata(dir).map_err(|e| format!("--save-dir {}: {e}", dir.display()))?;
    if !meta.is_dir() {
        return Err(format!("--save-dir {}: not a directory", dir.display()));
    }
    Ok(dir.to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;
    use optical_tactile::segment::Thresholds;

    fn app(calibration: Option<Calibration>, dir: &Path) -> App {
        let settings = Settings {
            thresholds: Thresholds::MID,
            flow: DisPreset::Fine,
            split: true,
            filter: false,
            rereference: true,
        };
        App {
            state: Mutex::new(State::new(settings)),
            changed: Condvar::new(),
            calibration,
            save_dir: dir.to_path_buf(),
            fixed_args: vec!["SEQ".into()],
            loopback_only: true,
        }
    }

    fn request(method: &str, path: &str, query: &str, body: &[u8]) -> Request {
        Request {
            method: method.into(),
            path: path.into(),
            query: query.into(),
            body: body.to_vec(),
            content_type: (method == "POST").then(|| "application/json".to_string()),
            host: Some("127.0.0.1:8000".into()),
        }
    }

    fn post(app: &App, path: &str, body: &str) -> Response {
        app.handle(&request("POST", path, "", body.as_bytes()))
    }

    fn get(app: &App, path: &str, query: &str) -> Response {
        app.handle(&request("GET", path, query, b""))
    }

    fn temp_dir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("tune-test-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn controls_change_the_settings_and_the_command_line() {
        let a = app(None, &std::env::temp_dir());
        let r = post(
            &a,
            "/control",
            r#"{"magnitude": 0.3, "sum": 700, "erode": 7}"#,
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let st = a.lock();
        assert_eq!(st.version, 1);
        assert_eq!(st.settings.thresholds.magnitude, 0.3);
        assert_eq!(st.settings.thresholds.sum, 700.0);
        assert_eq!(st.settings.thresholds.erode, 7);
        let line = a.command_line(&st.settings);
        assert!(
            line.contains("--magnitude 0.3 --sum 700 --erode 7 --dilate 21"),
            "{line}"
        );
        assert!(!line.contains("--filter"), "raw mode: {line}");
        drop(st);
        assert_eq!(post(&a, "/control", r#"{"preset": "low"}"#).status, 200);
        let line = a.command_line(&a.lock().settings);
        assert!(line.contains("--thresholds low"), "{line}");
        assert_eq!(
            post(&a, "/control", r#"{"preset": "calibration"}"#).status,
            200
        );
        assert_eq!(a.lock().settings.thresholds, Thresholds::MID);
    }

    #[test]
    fn bad_controls_are_refused_with_400_and_change_nothing() {
        let a = app(None, &std::env::temp_dir());
        for body in [
            "",
            "{",
            "[1, 2]",
            "\"magnitude\"",
            r#"{"magnitud": 0.3}"#,
            r#"{"magnitude": -0.1}"#,
            r#"{"magnitude": 1e300}"#,
            r#"{"magnitude": "0.3"}"#,
            r#"{"sum": -1}"#,
            r#"{"sum": 2e9}"#,
            r#"{"erode": 0}"#,
            r#"{"erode": 256}"#,
            r#"{"dilate": 2.5}"#,
            r#"{"dilate": -3}"#,
            r#"{"erode": 18446744073709551616}"#,
            r#"{"preset": "medium-rare"}"#,
            r#"{"flow": "warp"}"#,
            r#"{"split": "yes"}"#,
            r#"{"magnitude": 0.3, "erode": 999}"#,
        ] {
            let r = post(&a, "/control", body);
            assert_eq!(
                r.status,
                400,
                "{body}: {}",
                String::from_utf8_lossy(&r.body)
            );
            assert!(String::from_utf8_lossy(&r.body).contains("error"));
        }
        let r = a.handle(&request("POST", "/control", "", &[0xff, 0xfe, b'{']));
        assert_eq!(r.status, 400);
        // Another site's form (plain text) or a rebound host name.
        let mut form = request("POST", "/control", "", br#"{"magnitude": 0.3}"#);
        form.content_type = Some("text/plain".into());
        assert_eq!(a.handle(&form).status, 415);
        form.content_type = None;
        assert_eq!(a.handle(&form).status, 415);
        let mut rebound = request("POST", "/control", "", br#"{"magnitude": 0.3}"#);
        rebound.host = Some("evil.example:8000".into());
        assert_eq!(a.handle(&rebound).status, 421);
        let st = a.lock();
        assert_eq!(st.version, 0, "a refused control changed the settings");
        assert_eq!(st.settings.thresholds, Thresholds::MID);
    }

    #[test]
    fn loopback_hosts() {
        for h in [
            "127.0.0.1:8000",
            "localhost:1",
            "LOCALHOST",
            "[::1]:8000",
            "127.1.2.3",
        ] {
            assert!(is_loopback_host(h), "{h}");
        }
        for h in [
            "evil.example:8000",
            "10.0.0.1:8000",
            "[2001:db8::1]:80",
            "",
            "localhost.evil",
        ] {
            assert!(!is_loopback_host(h), "{h}");
        }
    }

    #[test]
    fn routes_and_methods() {
        let a = app(None, &std::env::temp_dir());
        assert_eq!(get(&a, "/", "").status, 200);
        assert_eq!(get(&a, "/app.js", "").status, 200);
        assert_eq!(get(&a, "/nope", "").status, 404);
        assert_eq!(get(&a, "/control", "").status, 405);
        assert_eq!(post(&a, "/state", "{}").status, 405);
        assert_eq!(get(&a, "/frame.png", "").status, 404, "no frame yet");
        assert_eq!(get(&a, "/frame.png", "after=-1").status, 400);
        assert_eq!(get(&a, "/frame.png", "after=0").status, 204, "none came");
        a.lock().panel = Some(Arc::new(PanelView {
            seq: 3,
            canvas: Canvas::new(4, 2, optical_tactile::viz::Rgb(1, 2, 3)),
        }));
        let r = get(&a, "/frame.png", "after=2");
        assert_eq!((r.status, r.content_type), (200, "image/png"));
        assert_eq!(r.headers, vec![("X-Panel-Seq", "3".to_string())]);
        assert!(r.body.starts_with(b"\x89PNG"));
        assert!(a.lock().panel_fetched);
        assert_eq!(get(&a, "/frame.png", "after=3").status, 204);
        assert_eq!(get(&a, "/state", "after=x").status, 400);
        let t = Instant::now();
        let r = get(&a, "/state", "after=0");
        assert_eq!(r.status, 200);
        assert!(t.elapsed() < LONG_POLL + Duration::from_millis(500));
        let v: Value = serde_json::from_slice(&r.body).unwrap();
        assert_eq!(v["settings"]["magnitude"], json!(0.35));
    }

    #[test]
    fn save_writes_a_new_file_only_and_it_loads_back() {
        let dir = temp_dir("save");
        let cal = Calibration::load(crate::cli_support::pipeline::DEFAULT_CALIBRATION).unwrap();
        let a = app(Some(cal), &dir);
        assert_eq!(
            post(&a, "/control", r#"{"magnitude": 0.25, "sum": 900}"#).status,
            200
        );
        let r = post(&a, "/save", r#"{"name": "tuned.json"}"#);
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        let back = Calibration::load(dir.join("tuned.json")).unwrap();
        assert_eq!(back.setup.thresholds.magnitude, 0.25);
        assert_eq!(back.setup.thresholds.sum, 900.0);
        // Never over an existing file.
        let r = post(&a, "/save", r#"{"name": "tuned.json"}"#);
        assert_eq!(r.status, 409);
        for name in [
            "../escape.json",
            "/tmp/abs.json",
            "sub/dir.json",
            ".hidden.json",
            "notjson.txt",
            ".json",
            "",
            "a\u{0}.json",
            "caf\u{e9}.json",
        ] {
            let body = json!({ "name": name }).to_string();
            let r = post(&a, "/save", &body);
            assert_eq!(
                r.status,
                400,
                "{name:?}: {}",
                String::from_utf8_lossy(&r.body)
            );
        }
        let long = format!("{}.json", "a".repeat(200));
        assert_eq!(
            post(&a, "/save", &json!({ "name": long }).to_string()).status,
            400
        );
        assert_eq!(post(&a, "/save", r#"{"name": 3}"#).status, 400);
        assert_eq!(
            post(&a, "/save", r#"{"name": "x.json", "over": 1}"#).status,
            400
        );
        let files: Vec<_> = std::fs::read_dir(&dir).unwrap().collect();
        assert_eq!(files.len(), 1, "only tuned.json was written");
        let _ = std::fs::remove_dir_all(&dir);
        // Raw mode has nothing to save.
        let raw = app(None, &std::env::temp_dir());
        assert_eq!(post(&raw, "/save", r#"{"name": "x.json"}"#).status, 409);
    }

    #[test]
    fn the_snippet_is_the_calibration_files_entry() {
        let cal = Calibration::load(crate::cli_support::pipeline::DEFAULT_CALIBRATION).unwrap();
        let a = app(Some(cal), &std::env::temp_dir());
        assert_eq!(
            post(&a, "/control", r#"{"preset": "high", "flow": "fast"}"#).status,
            200
        );
        let s = a.snippet(&a.lock().settings);
        let v: Value = serde_json::from_str(&s).unwrap();
        assert_eq!(v["thresholds"]["preset"], "high");
        assert_eq!(v["thresholds"]["sum"], json!(3000.0));
        assert_eq!(v["pipeline"]["flow_preset"], "fast");
    }
}
