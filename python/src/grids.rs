//! `read_grid` and `write_grid`: OpenVDB float grids as dense arrays, without pyopenvdb.

use std::path::PathBuf;

use numpy::{IntoPyArray, PyArray2, PyArray3};
use pyo3::exceptions::{PyFileExistsError, PyIsADirectoryError};
use pyo3::prelude::*;
use volgrad::io::vdb::{self, GridSelector};

use crate::arrays::{self, VoxelBox};
use crate::detached;
use crate::errors::check_path;

/// A grid for Python: its values and the 4×4 map from their indices to world.
pub type GridArrays<'py> = (Bound<'py, PyArray3<f32>>, Bound<'py, PyArray2<f64>>);

/// A 4×4 matrix for Python from its rows.
pub fn matrix<'py>(py: Python<'py>, rows: [f64; 16]) -> Bound<'py, PyArray2<f64>> {
    numpy::ndarray::Array2::from_shape_vec((4, 4), rows.to_vec())
        .expect("16 values make a 4×4 matrix")
        .into_pyarray(py)
}

/// The active box of grid `name` (the file's "density", or its only grid, by default) in `path`:
/// the values as a float32 array a[i, j, k] = voxel (x0 + i, y0 + j, z0 + k), and the 4×4 map
/// from array indices to world (world = M · [i, j, k, 1]; integer indices are voxel centres).
#[pyfunction]
#[pyo3(signature = (path, name = None))]
pub fn read_grid<'py>(
    py: Python<'py>,
    path: PathBuf,
    name: Option<String>,
) -> PyResult<GridArrays<'py>> {
    check_path(&path, "path")?;
    let (values, map) = detached::run(py, None, || {
        let selector = name.map_or(GridSelector::Default, GridSelector::Name);
        if !path.exists() {
            anyhow::bail!("file '{}' does not exist", path.display());
        }
        let grid = vdb::read_grid(&path, &selector)?;
        let place = VoxelBox::active(&grid.bricks);
        let values = arrays::from_brickmap(&grid.bricks, place, &format!("grid '{}'", grid.name))?;
        Ok((
            values,
            arrays::rows_of(place.array_to_world(&grid.transform)),
        ))
    })?;
    Ok((values.into_pyarray(py), matrix(py, map)))
}

/// Writes `array` as float grid `name` of a new VDB file `path`, array index (i, j, k) at index
/// coordinates (i, j, k) with `index_to_world` as its transform. Only the 8³ bricks holding a
/// non-zero value are stored, and the non-zero voxels are active. An existing file is refused
/// unless `overwrite`; `half` stores 16-bit floats.
#[pyfunction]
#[pyo3(signature = (path, array, index_to_world, name = "density".to_string(), overwrite = false, half = false))]
pub fn write_grid(
    py: Python<'_>,
    path: PathBuf,
    array: &Bound<'_, PyAny>,
    index_to_world: &Bound<'_, PyAny>,
    name: String,
    overwrite: bool,
    half: bool,
) -> PyResult<()> {
    check_path(&path, "path")?;
    if path.is_dir() {
        return Err(PyIsADirectoryError::new_err(format!(
            "cannot write '{}': it is a folder",
            path.display()
        )));
    }
    // `symlink_metadata`: a link to a file not yet there is the user's too (`exists` follows it).
    if path.symlink_metadata().is_ok() && !overwrite {
        // The command line's message would say --force.
        return Err(PyFileExistsError::new_err(format!(
            "'{}' already exists: pass overwrite=True to replace it",
            path.display()
        )));
    }
    let transform = arrays::matrix_argument(index_to_world, "index_to_world")?;
    let array = arrays::float32_argument::<numpy::Ix3>(array, "array", "of shape (nx, ny, nz)")?;
    let values = array.as_array();
    detached::run(py, None, || {
        arrays::check_values(&values, "array", true)?;
        let bricks = arrays::to_brickmap(&values, glam::IVec3::ZERO, "array")?;
        let grid_class = if bricks.min_value() < 0.0 {
            "unknown"
        } else {
            "fog volume"
        };
        let grid = vdb::Grid {
            name,
            grid_class: grid_class.into(),
            transform,
            bricks,
            background: 0.0,
            saved_as_half: half,
            metadata: Vec::new(),
        };
        vdb::write_grid_consumed(&path, grid, half, overwrite)
    })
}
