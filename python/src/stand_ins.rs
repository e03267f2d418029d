//! Arrays that stand in for a scene's grids for one call (`render` and `grad`'s `density=`,
//! `albedo=` and `emission=`): the call sees a medium with them in place of its own grids, and
//! the scene is not changed.

use numpy::ndarray::{ArrayView3, ArrayViewD};
use numpy::{PyReadonlyArray3, PyReadonlyArrayDyn};
use pyo3::prelude::*;

use crate::arrays;

/// A call's stand-in arrays, read while the GIL is held.
pub struct StandIns<'py> {
    density: Option<PyReadonlyArray3<'py, f32>>,
    albedo: Option<PyReadonlyArrayDyn<'py, f32>>,
    emission: Option<PyReadonlyArray3<'py, f32>>,
}

/// The same arrays as views, for the work done without the GIL.
pub struct StandInViews<'a> {
    pub density: Option<ArrayView3<'a, f32>>,
    pub albedo: Option<ArrayViewD<'a, f32>>,
    pub emission: Option<ArrayView3<'a, f32>>,
}

impl<'py> StandIns<'py> {
    /// Each argument given, as a float32 array of its parameter's shape.
    pub fn read(
        density: Option<&Bound<'py, PyAny>>,
        albedo: Option<&Bound<'py, PyAny>>,
        emission: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Self> {
        let grid = |value: &Bound<'py, PyAny>, name: &str| {
            arrays::float32_argument::<numpy::Ix3>(value, name, "shaped like the scene's grid")
        };
        Ok(StandIns {
            density: density.map(|d| grid(d, "density")).transpose()?,
            albedo: (albedo.map(|a| {
                arrays::float32_argument::<numpy::IxDyn>(a, "albedo", "shaped like the albedo grid")
            }))
            .transpose()?,
            emission: emission.map(|e| grid(e, "emission")).transpose()?,
        })
    }

    pub fn views(&self) -> StandInViews<'_> {
        StandInViews {
            density: self.density.as_ref().map(|a| a.as_array()),
            albedo: self.albedo.as_ref().map(|a| a.as_array()),
            emission: self.emission.as_ref().map(|a| a.as_array()),
        }
    }
}

impl StandInViews<'_> {
    pub fn any(&self) -> bool {
        self.density.is_some() || self.albedo.is_some() || self.emission.is_some()
    }
}
