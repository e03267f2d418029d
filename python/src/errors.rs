//! volgrad's errors as Python exceptions, with the command line's messages: a missing file is
//! `FileNotFoundError`, another failure to read or write one `OSError`, the rest (bad values, bad
//! scenes, a file whose contents are not what it should hold) `ValueError`.

use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyValueError};
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
