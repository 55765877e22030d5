//! The library's errors as Python exceptions, and the guard that keeps a
//! panic from reaching Python.
//!
//! Every exception the package raises for the library's errors derives from
//! [`OpticalTactileError`]; the ones about bad input also derive from
//! `ValueError`, a missing file from `FileNotFoundError`, another file
//! problem from `OSError`, so that both `except OpticalTactileError` and the
//! built-in families catch them. The message is the library's own.

use std::panic::{AssertUnwindSafe, catch_unwind};

use optical_tactile::Error;
use pyo3::exceptions::{PyException, PyFileNotFoundError, PyOSError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyDict, PyTuple, PyType};

pyo3::create_exception!(
    optical_tactile,
    OpticalTactileError,
    PyException,
    "Base class of every error the library raises (a numerical failure, no \
     reference frame yet, an internal error; the subclasses say more)."
);

/// The package's exception classes that derive from two bases (created once
/// per interpreter, at module import).
struct Classes {
    invalid_input: Py<PyType>,
    format: Py<PyType>,
    missing_file: Py<PyType>,
    file: Py<PyType>,
}

static CLASSES: PyOnceLock<Classes> = PyOnceLock::new();

/// `type(name, (OpticalTactileError, other), {...})`.
fn subclass(
    py: Python<'_>,
    name: &str,
    other: Bound<'_, PyType>,
    doc: &str,
) -> PyResult<Py<PyType>> {
    let bases = PyTuple::new(
        py,
        [
            py.get_type::<OpticalTactileError>().into_any(),
            other.into_any(),
        ],
    )?;
    let dict = PyDict::new(py);
    dict.set_item("__doc__", doc)?;
    dict.set_item("__module__", "optical_tactile")?;
    let class = py
        .get_type::<PyType>()
        .call1((name, bases, dict))?
        .cast_into::<PyType>()?;
    Ok(class.unbind())
}

fn classes(py: Python<'_>) -> PyResult<&Classes> {
    CLASSES.get_or_try_init(py, || {
        Ok(Classes {
            invalid_input: subclass(
                py,
                "InvalidInputError",
                py.get_type::<PyValueError>(),
                "Bad input: a frame of the wrong shape, size or dtype layout, NaN, a \
                 parameter out of range, a crop outside the frame.",
            )?,
            format: subclass(
                py,
                "FormatError",
                py.get_type::<PyValueError>(),
                "A file's content is malformed or unusable (an image that does not \
                 decode, a bad line in a CSV or JSON file, an unusable calibration).",
            )?,
            missing_file: subclass(
                py,
                "MissingFileError",
                py.get_type::<PyFileNotFoundError>(),
                "A file or directory the call needs does not exist.",
            )?,
            file: subclass(
                py,
                "FileError",
                py.get_type::<PyOSError>(),
                "Reading or writing a file failed (other than it missing).",
            )?,
        })
    })
}

/// Adds the exception classes to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("OpticalTactileError", py.get_type::<OpticalTactileError>())?;
    let c = classes(py)?;
    m.add("InvalidInputError", c.invalid_input.bind(py))?;
    m.add("FormatError", c.format.bind(py))?;
    m.add("MissingFileError", c.missing_file.bind(py))?;
    m.add("FileError", c.file.bind(py))?;
    Ok(())
}

/// Which of the package's exceptions an error is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Invalid,
    Format,
    Missing,
    File,
    Base,
}

fn kind(e: &Error) -> Kind {
    match e {
        Error::Context { source, .. } => kind(source),
        Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => Kind::Missing,
        Error::Io { .. } => Kind::File,
        Error::Image { .. } | Error::Format { .. } | Error::Calibration { .. } => Kind::Format,
        Error::ShapeMismatch { .. }
        | Error::TooSmall { .. }
        | Error::CropOutside { .. }
        | Error::NonFinite { .. }
        | Error::InvalidParameter { .. } => Kind::Invalid,
        _ => Kind::Base,
    }
}

fn raise(py: Python<'_>, class: &Py<PyType>, message: String) -> PyErr {
    match class.bind(py).call1((message.clone(),)) {
        Ok(instance) => PyErr::from_value(instance),
        Err(_) => OpticalTactileError::new_err(message),
    }
}

/// A failure inside a call: the library's error, a bad argument found by the
/// bindings, or a panic caught before it could reach Python.
#[derive(Debug)]
pub enum Failure {
    /// The library's error.
    Lib(Error),
    /// Bad input found by the bindings (raised as `InvalidInputError`).
    Invalid(String),
    /// A wrong type of argument (raised as `TypeError`).
    Type(String),
    /// A panic: a bug, raised as `OpticalTactileError` with its message.
    Panic(String),
}

impl From<Error> for Failure {
    fn from(e: Error) -> Self {
        Failure::Lib(e)
    }
}

impl Failure {
    /// The Python exception.
    pub fn into_py(self, py: Python<'_>) -> PyErr {
        let c = match classes(py) {
            Ok(c) => c,
            Err(e) => return e,
        };
        match self {
            Failure::Lib(e) => {
                let message = e.to_string();
                match kind(&e) {
                    Kind::Invalid => raise(py, &c.invalid_input, message),
                    Kind::Format => raise(py, &c.format, message),
                    Kind::Missing => raise(py, &c.missing_file, message),
                    Kind::File => raise(py, &c.file, message),
                    Kind::Base => OpticalTactileError::new_err(message),
                }
            }
            Failure::Invalid(message) => raise(py, &c.invalid_input, message),
            Failure::Type(message) => PyTypeError::new_err(message),
            Failure::Panic(message) => OpticalTactileError::new_err(format!(
                "internal error (a bug in optical-tactile, please report it): {message}"
            )),
        }
    }
}

/// Bad input found by the bindings, as a Python exception.
pub fn invalid(py: Python<'_>, message: impl Into<String>) -> PyErr {
    Failure::Invalid(message.into()).into_py(py)
}

/// The library's error as a Python exception.
pub fn lib(py: Python<'_>, e: Error) -> PyErr {
    Failure::Lib(e).into_py(py)
}

/// Runs `f`, turning a panic into [`Failure::Panic`].
pub fn guard<T>(f: impl FnOnce() -> Result<T, Failure>) -> Result<T, Failure> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a panic".to_string());
            Err(Failure::Panic(message))
        }
    }
}

/// Runs `f` with the GIL released (other Python threads run meanwhile) and
/// a panic caught; the failure becomes the Python exception.
pub fn detached<T: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> Result<T, Failure> + Send,
) -> PyResult<T> {
    py.detach(|| guard(f)).map_err(|e| e.into_py(py))
}
