//! What every command-line tool shares (the examples and the developer
//! tools in `tools/`): how a run ends, `-` for stdout, quiet broken pipes and
//! progress bars. Included with `#[path]`, so each tool uses only part of it.
//!
//! - Arguments are parsed by clap (`Parser::parse`): `--help` prints the
//!   usage with every default and exits 0; an unknown or malformed flag
//!   prints one error line (and the usage) and exits 2.
//! - A run returns `Result<ExitCode, Failure>`; [`finish`] prints a
//!   [`Failure::Message`] as one line `error: ...` on stderr and exits 1.
//! - Everything written to stdout goes through `writeln!` on a [`Sink`]: when
//!   the reader goes away (`track | head -3`) the write fails with a broken
//!   pipe, which becomes [`Failure::BrokenPipe`] and ends the run quietly
//!   with status 0.
//! - A flag that writes a text stream (JSON Lines, JSON, CSV) takes a
//!   [`TextOut`]: a file, or `-` for stdout. A flag that writes binary data
//!   (PNG, `.flo`, `.npy`) parses with [`binary_path`], which refuses `-`.
//! - Long jobs show a [`progress_bar`] (or [`Stages`] of them) with an ETA on
//!   stderr, hidden when stderr is not a terminal or with `--quiet`.
#![allow(dead_code)]

pub mod pipeline;

use std::fmt;
use std::io::{self, IsTerminal, Write};
use std::path::PathBuf;
use std::process::ExitCode;
use std::str::FromStr;
use std::sync::Mutex;
use std::time::Duration;

use clap::builder::{PossibleValuesParser, TypedValueParser};
use indicatif::{ProgressBar, ProgressStyle};
use optical_tactile::flow::dis::DisPreset;
use optical_tactile::frame::Roi;
use optical_tactile::segment::ThresholdPreset;
use serde::Serialize;

/// Why a run stopped early.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Failure {
    /// The reader of stdout went away (a closed pipe): not an error, the
    /// run ends quietly with status 0.
    BrokenPipe,
    /// An error, printed as one line `error: ...`; exit status 1.
    Message(String),
}

impl Failure {
    /// The message as one line: the lines of a multi-line message joined.
    pub fn one_line(&self) -> String {
        match self {
            Failure::BrokenPipe => "broken pipe".to_string(),
            Failure::Message(m) => m
                .lines()
                .map(str::trim)
                .filter(|l| !l.is_empty())
                .collect::<Vec<_>>()
                .join(" "),
        }
    }

    /// Whether the message contains `s` (for tests).
    pub fn contains(&self, s: &str) -> bool {
        self.one_line().contains(s)
    }
}

impl fmt::Display for Failure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.one_line())
    }
}

impl From<String> for Failure {
    fn from(m: String) -> Self {
        Failure::Message(m)
    }
}

impl From<&str> for Failure {
    fn from(m: &str) -> Self {
        Failure::Message(m.to_string())
    }
}

impl From<io::Error> for Failure {
    fn from(e: io::Error) -> Self {
        if e.kind() == io::ErrorKind::BrokenPipe {
            Failure::BrokenPipe
        } else {
            Failure::Message(e.to_string())
        }
    }
}

impl From<optical_tactile::Error> for Failure {
    fn from(e: optical_tactile::Error) -> Self {
        Failure::Message(e.to_string())
    }
}

impl From<serde_json::Error> for Failure {
    fn from(e: serde_json::Error) -> Self {
        Failure::Message(e.to_string())
    }
}

/// The exit status of a run: its own on success, 0 after a broken pipe, 1
/// after an error (printed as one line on stderr).
pub fn finish(result: Result<ExitCode, Failure>) -> ExitCode {
    match result {
        Ok(code) => code,
        Err(Failure::BrokenPipe) => ExitCode::SUCCESS,
        Err(e) => {
            let _ = writeln!(io::stderr(), "error: {}", e.one_line());
            ExitCode::FAILURE
        }
    }
}

/// Parses `args` (without the program name) as `T`, for tests and callers
/// that run a tool in-process. `Ok(None)` after `--help` (printed to
/// stdout); a usage error is a [`Failure::Message`] with clap's first line.
pub fn try_parse<T: clap::Parser>(name: &str, args: &[String]) -> Result<Option<T>, Failure> {
    match T::try_parse_from(std::iter::once(name.to_string()).chain(args.iter().cloned())) {
        Ok(t) => Ok(Some(t)),
        Err(e) if !e.use_stderr() => {
            // --help or --version.
            write!(io::stdout().lock(), "{}", e.render())?;
            Ok(None)
        }
        Err(e) => {
            let text = e.render().to_string();
            let first = text.lines().next().unwrap_or("invalid arguments");
            Err(Failure::Message(
                first.strip_prefix("error: ").unwrap_or(first).to_string(),
            ))
        }
    }
}

/// A text output named on the command line: a file, or stdout for `-`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TextOut {
    /// `-`: standard output.
    Stdout,
    /// A file (created or truncated).
    File(PathBuf),
}

impl FromStr for TextOut {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "" => Err("expected a file name, or - for stdout".to_string()),
            "-" => Ok(TextOut::Stdout),
            _ => Ok(TextOut::File(PathBuf::from(s))),
        }
    }
}

impl fmt::Display for TextOut {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TextOut::Stdout => f.write_str("stdout"),
            TextOut::File(p) => write!(f, "{}", p.display()),
        }
    }
}

impl TextOut {
    /// Whether this is stdout.
    pub fn is_stdout(&self) -> bool {
        *self == TextOut::Stdout
    }

    /// Opens it for writing.
    pub fn create(&self) -> Result<Sink, Failure> {
        match self {
            TextOut::Stdout => Ok(Sink::stdout()),
            TextOut::File(p) => {
                let f = std::fs::File::create(p)
                    .map_err(|e| format!("cannot create {}: {e}", p.display()))?;
                Ok(Sink {
                    name: p.display().to_string(),
                    out: Box::new(io::BufWriter::new(f)),
                })
            }
        }
    }

    /// Writes `value` as pretty JSON (and a newline); says so on stderr when
    /// it went to a file. A NaN or infinite number is refused (JSON has none)
    /// and nothing is written.
    pub fn write_json<T: Serialize>(&self, value: &T) -> Result<(), Failure> {
        let name = match self {
            TextOut::File(p) => p.clone(),
            TextOut::Stdout => PathBuf::from("stdout"),
        };
        optical_tactile::io::check_finite(value, name)?;
        let text = serde_json::to_string_pretty(value)?;
        let mut s = self.create()?;
        writeln!(s, "{text}")?;
        s.flush()?;
        if let TextOut::File(p) = self {
            let _ = writeln!(io::stderr(), "wrote {}", p.display());
        }
        Ok(())
    }
}

/// A place text goes: stdout, stderr or a file. Its write errors name it,
/// and keep their kind (a broken pipe stays one).
pub struct Sink {
    name: String,
    out: Box<dyn Write>,
}

impl Sink {
    /// Standard output (locked).
    pub fn stdout() -> Sink {
        Sink {
            name: "stdout".to_string(),
            out: Box::new(io::stdout().lock()),
        }
    }

    /// Standard error.
    pub fn stderr() -> Sink {
        Sink {
            name: "stderr".to_string(),
            out: Box::new(io::stderr()),
        }
    }

    /// The report of a tool: stdout, or stderr when a data stream already
    /// goes to stdout (so that stdout stays pure data).
    pub fn report(data_on_stdout: bool) -> Sink {
        if data_on_stdout {
            Sink::stderr()
        } else {
            Sink::stdout()
        }
    }

    /// Writes `record` as one line of JSON and flushes, so that nothing
    /// already written is lost if the run stops.
    pub fn json_line<T: Serialize>(&mut self, record: &T) -> Result<(), Failure> {
        let line = serde_json::to_string(record)?;
        writeln!(self, "{line}")?;
        self.flush()?;
        Ok(())
    }

    fn named(&self, e: io::Error) -> io::Error {
        if e.kind() == io::ErrorKind::BrokenPipe {
            e
        } else {
            io::Error::new(e.kind(), format!("cannot write {}: {e}", self.name))
        }
    }
}

impl Write for Sink {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.out.write(buf).map_err(|e| self.named(e))
    }

    fn flush(&mut self) -> io::Result<()> {
        self.out.flush().map_err(|e| self.named(e))
    }
}

/// Parses a binary output's file name (PNG, `.flo`, `.npy`): `-` (stdout)
/// is refused, as such data does not belong on a terminal or in a text
/// stream.
pub fn binary_path(s: &str) -> Result<PathBuf, String> {
    match s {
        "" => Err("expected a file name".to_string()),
        "-" => Err("binary output cannot go to stdout (-): give a file name".to_string()),
        _ => Ok(PathBuf::from(s)),
    }
}

/// `--preset`: a DIS flow preset by name, the names listed in `--help`.
pub fn dis_preset() -> impl TypedValueParser<Value = DisPreset> {
    PossibleValuesParser::new(DisPreset::ALL.map(DisPreset::name))
        .map(|s| DisPreset::parse(&s).expect("a listed preset name"))
}

/// `--thresholds`: a segmentation threshold preset by name (`low`, `mid`,
/// `high`), the names listed in `--help`.
pub fn threshold_preset() -> impl TypedValueParser<Value = ThresholdPreset> {
    PossibleValuesParser::new(ThresholdPreset::ALL.map(ThresholdPreset::name))
        .map(|s| s.parse().expect("a listed preset name"))
}

/// `--crop x,y,w,h`.
pub fn roi(s: &str) -> Result<Roi, String> {
    Roi::parse(s).map_err(|e| e.to_string())
}

/// `on` or `off` (also `true`/`false`, `1`/`0`), for switches that take a
/// value.
pub fn on_off(s: &str) -> Result<bool, String> {
    match s {
        "on" | "true" | "1" => Ok(true),
        "off" | "false" | "0" => Ok(false),
        _ => Err(format!("expected on or off, got `{s}`")),
    }
}

/// A comma-separated list of numbers as one option value (`--rods
/// 0.4,0.9,1.35`); shown the same way as a default in `--help`.
#[derive(Debug, Clone, PartialEq)]
pub struct Numbers(pub Vec<f64>);

impl FromStr for Numbers {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        number_list(s).map(Numbers)
    }
}

impl fmt::Display for Numbers {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let parts: Vec<String> = self.0.iter().map(f64::to_string).collect();
        f.write_str(&parts.join(","))
    }
}

/// A comma-separated list of numbers.
pub fn number_list(s: &str) -> Result<Vec<f64>, String> {
    s.split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| format!("expected numbers separated by commas, got `{t}`"))
        })
        .collect()
}

/// A positive, finite number.
pub fn positive(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|x| x.is_finite() && *x > 0.0)
        .ok_or_else(|| format!("expected a positive number, got `{s}`"))
}

/// A finite number.
pub fn finite(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|x| x.is_finite())
        .ok_or_else(|| format!("expected a number, got `{s}`"))
}

/// `WxH` with both sides positive.
pub fn size(s: &str) -> Result<(usize, usize), String> {
    s.split_once('x')
        .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
        .filter(|&(w, h)| w > 0 && h > 0)
        .ok_or_else(|| format!("expected WxH (positive whole numbers), got `{s}`"))
}

/// Whether progress bars are drawn: stderr is a terminal and not `--quiet`.
pub fn show_progress(quiet: bool) -> bool {
    !quiet && io::stderr().is_terminal()
}

/// A progress bar with an ETA on stderr for `total` steps, labelled `label`;
/// hidden when stderr is not a terminal or with `quiet`.
pub fn progress_bar(label: &str, total: u64, quiet: bool) -> ProgressBar {
    if !show_progress(quiet) {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(total);
    bar.set_style(
        ProgressStyle::with_template(
            "{prefix:>27} [{bar:30}] {pos}/{len} {elapsed:>4} elapsed, ETA {eta:>4}",
        )
        .expect("a valid template")
        .progress_chars("=> "),
    );
    bar.set_prefix(label.to_string());
    bar.enable_steady_tick(Duration::from_millis(500));
    bar
}

/// Progress bars for a job of stages reporting `(stage, done, total)` from
/// any thread (the simulator's and the sweeps' progress callbacks): a new
/// stage name finishes the previous bar and starts the next.
pub struct Stages {
    quiet: bool,
    current: Mutex<Option<(String, ProgressBar)>>,
}

impl Stages {
    /// No bar yet; every bar hidden with `quiet` or off a terminal.
    pub fn new(quiet: bool) -> Stages {
        Stages {
            quiet,
            current: Mutex::new(None),
        }
    }

    /// Reports `done` of `total` steps of `stage`.
    pub fn update(&self, stage: &str, done: usize, total: usize) {
        let mut cur = self.current.lock().unwrap_or_else(|e| e.into_inner());
        if cur.as_ref().is_none_or(|(s, _)| s != stage) {
            if let Some((_, bar)) = cur.take() {
                bar.finish();
            }
            *cur = Some((
                stage.to_string(),
                progress_bar(stage, total as u64, self.quiet),
            ));
        }
        let (_, bar) = cur.as_ref().expect("just set");
        bar.set_length(total as u64);
        // Workers report out of order: never move back.
        bar.set_position((done as u64).max(bar.position()));
    }

    /// Finishes the current bar (left on screen).
    pub fn finish(&self) {
        let mut cur = self.current.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, bar)) = cur.take() {
            bar.finish();
        }
    }
}
