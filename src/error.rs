//! One error type for the whole crate.
//!
//! Every failure that comes from input a user controls (frames, crops, flows,
//! files, parameters, cameras) is returned as an [`Error`] that says what was
//! expected and what came, never as a panic.

use std::path::PathBuf;

/// Result alias used throughout the crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Everything that can go wrong in `optical-tactile`.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Reading or writing a file failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or directory involved.
        path: PathBuf,
        /// The underlying I/O error.
        #[source]
        source: std::io::Error,
    },

    /// An image could not be decoded or encoded.
    #[error("{}: image error: {source}", path.display())]
    Image {
        /// The image file involved.
        path: PathBuf,
        /// The underlying codec error.
        #[source]
        source: ::image::ImageError,
    },

    /// A file's content is malformed (bad magic, wrong header, truncated data,
    /// a bad line in a CSV or JSON Lines file, ...).
    #[error("{}{}: {message}", path.display(), line.map(|l| format!(":{l}")).unwrap_or_default())]
    Format {
        /// The file involved.
        path: PathBuf,
        /// 1-based line number, where the file is line-oriented.
        line: Option<usize>,
        /// What is wrong.
        message: String,
    },

    /// Two things that must have the same shape do not (e.g. a frame of another
    /// size than the reference, u and v planes of different sizes).
    #[error("{what}: expected {expected_w}x{expected_h}, got {got_w}x{got_h}")]
    ShapeMismatch {
        /// What was being compared.
        what: String,
        /// Expected width.
        expected_w: usize,
        /// Expected height.
        expected_h: usize,
        /// Actual width.
        got_w: usize,
        /// Actual height.
        got_h: usize,
    },

    /// An image or field is empty or too small for the operation.
    #[error("{what}: {width}x{height} is too small (need at least {min_w}x{min_h})")]
    TooSmall {
        /// What was too small.
        what: String,
        /// Its width.
        width: usize,
        /// Its height.
        height: usize,
        /// Minimum width required.
        min_w: usize,
        /// Minimum height required.
        min_h: usize,
    },

    /// A region of interest does not lie inside the frame.
    #[error("crop {x},{y},{w}x{h} lies outside the {frame_w}x{frame_h} frame (or is empty)")]
    CropOutside {
        /// Left column of the crop.
        x: usize,
        /// Top row of the crop.
        y: usize,
        /// Crop width.
        w: usize,
        /// Crop height.
        h: usize,
        /// Frame width.
        frame_w: usize,
        /// Frame height.
        frame_h: usize,
    },

    /// A field holds NaN or infinite values where finite ones are required.
    #[error("{what}: non-finite value at row {row}, column {col}")]
    NonFinite {
        /// The field involved.
        what: String,
        /// Row of the first offending value.
        row: usize,
        /// Column of the first offending value.
        col: usize,
    },

    /// A parameter is outside its valid range or makes no sense.
    #[error("invalid parameter `{name}`: {message}")]
    InvalidParameter {
        /// Parameter name, as the user knows it.
        name: String,
        /// Why it is invalid, and what is allowed.
        message: String,
    },

    /// A calibration file cannot be used (wrong version, missing polynomial, ...).
    #[error("calibration {}: {message}", path.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| "(in memory)".into()))]
    Calibration {
        /// The calibration file, if it came from one.
        path: Option<PathBuf>,
        /// What is wrong.
        message: String,
    },

    /// A numerical procedure failed (singular system, too few samples to fit, ...).
    #[error("numerical failure in {what}: {message}")]
    Numerical {
        /// The procedure.
        what: String,
        /// What happened.
        message: String,
    },

    /// The frame source (camera, sequence) failed or stopped.
    #[error("capture: {message}")]
    Capture {
        /// What happened.
        message: String,
    },

    /// No reference frame has been set yet.
    #[error("no reference frame: call set_reference first")]
    NoReference,

    /// Another error, with what was being done when it happened (a
    /// dataset's test and frame, say).
    #[error("{context}: {source}")]
    Context {
        /// What was being done, e.g. `test 12 (frame t012.png)`.
        context: String,
        /// The error itself.
        #[source]
        source: Box<Error>,
    },
}

impl Error {
    /// Shorthand for [`Error::InvalidParameter`].
    pub fn param(name: impl Into<String>, message: impl Into<String>) -> Self {
        Error::InvalidParameter {
            name: name.into(),
            message: message.into(),
        }
    }

    /// Shorthand for [`Error::Format`].
    pub fn format(
        path: impl Into<PathBuf>,
        line: Option<usize>,
        message: impl Into<String>,
    ) -> Self {
        Error::Format {
            path: path.into(),
            line,
            message: message.into(),
        }
    }

    /// Shorthand for [`Error::Io`].
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }

    /// This error inside an [`Error::Context`] saying what was being done.
    pub fn context(self, context: impl Into<String>) -> Self {
        Error::Context {
            context: context.into(),
            source: Box::new(self),
        }
    }

    /// Shorthand for [`Error::ShapeMismatch`] from `(width, height)` pairs.
    pub fn shape(what: impl Into<String>, expected: (usize, usize), got: (usize, usize)) -> Self {
        Error::ShapeMismatch {
            what: what.into(),
            expected_w: expected.0,
            expected_h: expected.1,
            got_w: got.0,
            got_h: got.1,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_carry_the_numbers() {
        let e = Error::shape("frame", (1600, 200), (1920, 1080));
        assert_eq!(e.to_string(), "frame: expected 1600x200, got 1920x1080");
        let e = Error::format("a/tests.csv", Some(3), "missing column `x_mm`");
        assert_eq!(e.to_string(), "a/tests.csv:3: missing column `x_mm`");
        let e = Error::format("f.flo", None, "bad magic");
        assert_eq!(e.to_string(), "f.flo: bad magic");
    }
}
