//! volgrad for Python: OpenVDB grids as numpy arrays (`read_grid`, `write_grid`), pictures
//! decoded to linear radiance (`read_picture`), scenes
//! (`Scene.load`, `Scene.from_parts`), cameras, renders and their vector-Jacobian products
//! (`Scene.render`, `Scene.grad`). A thin layer over the library: every number comes from the
//! same code the command line runs. The package `volgrad` (python/volgrad) wraps this module
//! and adds the PyTorch function.

// Bad input gets an exception, never a panic (see `detached` for the panics that remain possible).
#![deny(clippy::unwrap_used)]

mod arrays;
mod camera;
mod detached;
mod errors;
mod grids;
mod media;
mod pictures;
mod scene;
mod stand_ins;
mod views;

use pyo3::prelude::*;

#[pymodule]
fn _volgrad(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(grids::read_grid, m)?)?;
    m.add_function(wrap_pyfunction!(grids::write_grid, m)?)?;
    m.add_function(wrap_pyfunction!(pictures::read_picture, m)?)?;
    m.add_class::<camera::Camera>()?;
    m.add_class::<scene::Scene>()?;
    Ok(())
}
