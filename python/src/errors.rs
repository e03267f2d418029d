//! volgrad's errors as Python exceptions, with the command line's messages: a missing file is
//! `FileNotFoundError`, another failure to read or write one `OSError`, the rest (bad values, bad
//! scenes, a file whose contents are not what it should hold) `ValueError`.

use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyBool;
use pyo3::PyErr;

/// The exception for `error`, its message the whole chain ("reading x: cause: ...") as the
/// command line prints it.
pub fn to_py(error: anyhow::Error) -> PyErr {
    let message = format!("{error:#}");
    let io_kind = error
        .chain()
        .find_map(|cause| cause.downcast_ref::<std::io::Error>())
        .map(|e| e.kind());
    match io_kind {
        Some(std::io::ErrorKind::NotFound) => PyFileNotFoundError::new_err(message),
        // The file was read, and its contents are wrong (a scene file that is not UTF-8).
        Some(std::io::ErrorKind::InvalidData) => PyValueError::new_err(message),
        Some(_) => PyOSError::new_err(message),
        // The scene and grid readers check a file's existence themselves, with a message that
        // names the key it came from.
        None if message.contains("does not exist") => PyFileNotFoundError::new_err(message),
        None => PyValueError::new_err(message),
    }
}

/// `Result<T, anyhow::Error>` as a Python result.
pub trait OrRaise<T> {
    fn or_raise(self) -> pyo3::PyResult<T>;
}

impl<T> OrRaise<T> for anyhow::Result<T> {
    fn or_raise(self) -> pyo3::PyResult<T> {
        self.map_err(to_py)
    }
}

/// A path argument the operating system can take: Python strings may hold a NUL, at which the
/// system's calls would cut the path short (`b\0.vdb` would write `b`, past the checks made on
/// the whole string).
pub fn check_path(path: &std::path::Path, argument: &str) -> pyo3::PyResult<()> {
    if path.as_os_str().as_encoded_bytes().contains(&0) {
        return Err(PyValueError::new_err(format!(
            "{argument}: a path cannot hold a NUL character ({})",
            path.display()
        )));
    }
    Ok(())
}

/// A number argument as the f32 volgrad computes in. Python's float is an f64: a non-zero value
/// beyond f32's range would become 0 or infinity without a word (a `density_scale` of 1e-46, an
/// empty medium), so it is refused by name, as is a NaN or an infinity.
pub fn narrow(argument: &str, value: f64) -> PyResult<f32> {
    // The library's range rule (the one scene and run files are held to), with Python's wording.
    if !value.is_finite() || volgrad::io::exact::float_within_f32(argument, value).is_err() {
        return Err(PyValueError::new_err(format!(
            "{argument} must be a finite number within a 32-bit float's range, about 1e-45 to 3e38 in magnitude (got {value:e})"
        )));
    }
    Ok(value as f32)
}

/// A seed argument: none, or a whole number in [0, 2⁶⁴) (a Python or numpy integer, not a
/// bool); anything else a `ValueError` naming the range, as `volgrad.torch` and `volgrad.jax`
/// raise (PyO3's own conversion raises `OverflowError` or `TypeError`).
pub fn seed(value: Option<&Bound<'_, PyAny>>) -> PyResult<Option<u64>> {
    let Some(value) = value.filter(|v| !v.is_none()) else {
        return Ok(None);
    };
    match value.is_instance_of::<PyBool>() {
        false => value.extract::<u64>().ok(),
        true => None,
    }
    .map(Some)
    .ok_or_else(|| {
        let given = value.repr().map_or_else(|_| "?".into(), |r| r.to_string());
        PyValueError::new_err(format!(
            "seed must be a whole number in [0, 2**64) (got {given})"
        ))
    })
}
