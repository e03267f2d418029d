//! `read_picture`: a picture from elsewhere decoded as a run file's view set decodes it, so that a
//! Python loop fits the same linear radiance `optimize` would (an 8-bit PNG read as its stored
//! values would be fitted several times too bright).

use std::path::PathBuf;

use numpy::ndarray::{Array2, Array3};
use numpy::{IntoPyArray, PyArray2, PyArray3};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use volgrad::io::images::{self, ColorSpace};

use crate::detached;
use crate::errors::check_path;

/// A picture for Python: linear colour (H, W, 3), premultiplied by alpha, and alpha (H, W) when
/// the file has it.
pub type PictureArrays<'py> = (Bound<'py, PyArray3<f32>>, Option<Bound<'py, PyArray2<f32>>>);

/// The picture at `path` as linear radiance: decoded by the colour space the file declares, else
/// sRGB for 8- and 16-bit files and linear for float ones (`color_space` "linear" or "srgb"
/// overrides both); colour premultiplied by alpha (a transparent film's picture of the medium
/// alone) and alpha, or `None` without an alpha channel.
#[pyfunction]
#[pyo3(signature = (path, color_space = None))]
pub fn read_picture<'py>(
    py: Python<'py>,
    path: PathBuf,
    color_space: Option<String>,
) -> PyResult<PictureArrays<'py>> {
    check_path(&path, "path")?;
    let space = match color_space.as_deref() {
        None => None,
        Some("linear") => Some(ColorSpace::Linear),
        Some("srgb") => Some(ColorSpace::Srgb),
        Some(other) => {
            return Err(PyValueError::new_err(format!(
                "color_space must be \"linear\" or \"srgb\" (got \"{other}\")"
            )))
        }
    };
    let picture = detached::run(py, None, || {
        if !path.exists() {
            anyhow::bail!("file '{}' does not exist", path.display());
        }
        images::read_picture(&path, space)
    })?;
    let (width, height) = (picture.color.width as usize, picture.color.height as usize);
    let shape_error =
        |e: numpy::ndarray::ShapeError| PyValueError::new_err(format!("'{}': {e}", path.display()));
    let colour = picture.color.pixels.iter().flat_map(|p| p.to_array());
    let colour =
        Array3::from_shape_vec((height, width, 3), colour.collect()).map_err(shape_error)?;
    let alpha = match picture.alpha {
        Some(a) => Some(
            Array2::from_shape_vec((height, width), a)
                .map_err(shape_error)?
                .into_pyarray(py),
        ),
        None => None,
    };
    Ok((colour.into_pyarray(py), alpha))
}
