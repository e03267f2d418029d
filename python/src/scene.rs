//! `Scene`: a scene file loaded, or a scene built from parts (a density array and the medium's
//! constants, lights and a camera), with its density as an array that can be read and replaced.

use std::path::{Path, PathBuf};

use glam::IVec3;
use numpy::{IntoPyArray, PyArrayDyn};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use volgrad::render::scene::{Scene as RustScene, SceneFile, SceneNeeds};
use volgrad::render::scene_file::EmissionFile;
use volgrad::volume::medium::Medium;
use volgrad::volume::transform::IndexTransform;

use crate::arrays::{self, VoxelBox};
use crate::camera::Camera;
use crate::detached;
use crate::errors::OrRaise;
use crate::grids::{matrix, GridArrays};
use crate::media;
use crate::views::{self, Boxes, Sampling};

/// A scene ready to render and differentiate. Its density is the box of voxels `density` returns;
/// gradients with respect to it come back in the same box.
#[pyclass(name = "Scene", module = "volgrad")]
pub struct Scene {
    pub scene: RustScene,
    /// The voxels the density array (and the albedo and emission grids' arrays) cover, in each
    /// grid's index space.
    pub boxes: Boxes,
    /// Whether the scene has a camera of its own (a scene file's, or `from_parts`' `camera`):
    /// without one, every render and gradient names its cameras.
    pub has_camera: bool,
}

impl Scene {
    /// The scene's own camera, if it has one.
    fn own_camera(&self) -> Option<volgrad::render::camera::Camera> {
        self.has_camera.then_some(self.scene.camera)
    }

    /// The medium with `values` in place of the density, over the current box (its shape must
    /// match), or over a new box at index 0 under `index_to_world`.
    pub fn medium_with(
        &self,
        values: &numpy::ndarray::ArrayView3<f32>,
        index_to_world: Option<IndexTransform>,
        argument: &str,
    ) -> anyhow::Result<(Medium, VoxelBox)> {
        let (nx, ny, nz) = values.dim();
        let (place, transform) = match index_to_world {
            Some(transform) => (VoxelBox::of_array([nx, ny, nz]), transform),
            None if [nx, ny, nz] == self.boxes.density.shape => (self.boxes.density, self.scene.medium.transform),
            None => anyhow::bail!(
                "{argument} has shape {:?} but the scene's density is {:?}: give index_to_world with an array of another shape",
                [nx, ny, nz],
                self.boxes.density.shape
            ),
        };
        let grid = media::density_grid(
            values,
            place.origin,
            self.scene.medium.density_scale,
            argument,
        )?;
        Ok((
            media::medium_over(&self.scene, grid, transform, place),
            place,
        ))
    }
}

#[pymethods]
impl Scene {
    /// Reads a scene file (TOML) with its grid and lights, as `volgrad render` does.
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Scene> {
        let scene = detached::run(py, None, || {
            if !path.exists() {
                anyhow::bail!("scene file '{}' does not exist", path.display());
            }
            RustScene::load(&path)
        })?;
        let boxes = Boxes::active(&scene);
        Ok(Scene {
            scene,
            boxes,
            has_camera: true,
        })
    }

    /// A scene from parts: `density` (nx, ny, nz) float32 with `index_to_world` (4×4, array
    /// indices to world), the medium's constants, `lights` as scene-file light tables (dicts), a
    /// `camera`, and the render settings a scene file's `[render]` table holds.
    #[staticmethod]
    #[pyo3(signature = (density, index_to_world, density_scale = 1.0, albedo = None, phase_g = 0.0, lights = None, camera = None, spp = None, seed = None, max_depth = None, emission = None, emission_kind = None))]
    #[allow(clippy::too_many_arguments)]
    fn from_parts(
        py: Python<'_>,
        density: &Bound<'_, PyAny>,
        index_to_world: &Bound<'_, PyAny>,
        density_scale: f32,
        albedo: Option<&Bound<'_, PyAny>>,
        phase_g: f32,
        lights: Option<&Bound<'_, PyAny>>,
        camera: Option<Camera>,
        spp: Option<u32>,
        seed: Option<u64>,
        max_depth: Option<u32>,
        emission: Option<&Bound<'_, PyAny>>,
        emission_kind: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Scene> {
        let transform = arrays::matrix_argument(index_to_world, "index_to_world")?;
        let density =
            arrays::float32_argument::<numpy::Ix3>(density, "density", "of shape (nx, ny, nz)")?;
        // The constants go through the scene file's own reader, so that they are checked and
        // named as a scene file's keys are.
        for (key, value) in [("density_scale", density_scale), ("phase_g", phase_g)] {
            if !value.is_finite() {
                return Err(PyValueError::new_err(format!(
                    "{key} must be a finite number (got {value})"
                )));
            }
        }
        let medium = PyDict::new(py);
        medium.set_item("density_scale", density_scale)?;
        medium.set_item("phase_g", phase_g)?;
        let albedo_array = match albedo {
            Some(a) if a.hasattr("shape")? => Some(arrays::float32_argument::<numpy::IxDyn>(
                a,
                "albedo",
                "shaped like the density",
            )?),
            Some(a) => {
                medium.set_item("albedo", a)?;
                None
            }
            None => None,
        };
        let spec = PyDict::new(py);
        spec.set_item("medium", medium)?;
        spec.set_item(
            "light",
            lights.map_or_else(|| pyo3::types::PyList::empty(py).into_any(), |l| l.clone()),
        )?;
        let render = PyDict::new(py);
        for (key, value) in [
            ("spp", spp.map(u64::from)),
            ("seed", seed),
            ("max_depth", max_depth.map(u64::from)),
        ] {
            if let Some(v) = value {
                render.set_item(key, v)?;
            }
        }
        spec.set_item("render", render)?;
        let kwargs = PyDict::new(py);
        kwargs.set_item("allow_nan", false)?;
        let json: String = (py
            .import("json")?
            .call_method("dumps", (spec,), Some(&kwargs)))
        .map_err(|e| match e.is_instance_of::<PyValueError>(py) {
            true => PyValueError::new_err("albedo and the lights' values must be finite numbers"),
            false => e,
        })?
        .extract()?;
        let file: SceneFile = serde_json::from_str(&json)
            .map_err(|e| PyValueError::new_err(format!("scene parts: {e}")))?;
        let mut scene =
            RustScene::from_file_as(file, Path::new("<from_parts>"), SceneNeeds::Constants)
                .or_raise()?;
        let has_camera = camera.is_some();
        if let Some(camera) = camera {
            scene.camera = camera.camera;
        }
        let values = density.as_array();
        let place = VoxelBox::of_array({
            let (nx, ny, nz) = values.dim();
            [nx, ny, nz]
        });
        let grid =
            media::density_grid(&values, IVec3::ZERO, density_scale, "density").or_raise()?;
        scene.medium = media::medium_over(&scene, grid, transform, place);
        if let Some(albedo) = albedo_array {
            scene.medium.albedo =
                media::albedo_grid(&albedo.as_array(), place, transform, scene.medium.filter)
                    .or_raise()?;
        }
        if let Some(values) = emission {
            let values = arrays::float32_argument::<numpy::Ix3>(
                values,
                "emission",
                "shaped like the density",
            )?;
            let kind = emission_file(py, emission_kind)?
                .emission_kind()
                .or_raise()?;
            scene.medium.emission = Some(
                media::emission_grid(
                    &values.as_array(),
                    place,
                    transform,
                    kind,
                    scene.medium.filter,
                )
                .or_raise()?,
            );
        }
        scene.grid_name = "density".into();
        let boxes = Boxes {
            density: place,
            albedo: place,
            emission: place,
        };
        Ok(Scene {
            scene,
            boxes,
            has_camera,
        })
    }

    /// The density as (array (nx, ny, nz) float32, 4×4 index_to_world of the array's indices).
    #[getter]
    fn density<'py>(&self, py: Python<'py>) -> PyResult<GridArrays<'py>> {
        let place = self.boxes.density;
        let values = detached::run(py, None, || {
            arrays::from_brickmap(&self.scene.medium.grid, place, "the density")
        })?;
        Ok((
            values.into_pyarray(py),
            matrix(py, self.index_to_world_rows()),
        ))
    }

    /// Replaces the density: an array of the current shape keeps the current index_to_world; with
    /// `index_to_world`, any shape.
    #[pyo3(signature = (density, index_to_world = None))]
    fn set_density(
        &mut self,
        py: Python<'_>,
        density: &Bound<'_, PyAny>,
        index_to_world: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<()> {
        let transform = index_to_world
            .map(|m| arrays::matrix_argument(m, "index_to_world"))
            .transpose()?;
        let density =
            arrays::float32_argument::<numpy::Ix3>(density, "density", "of shape (nx, ny, nz)")?;
        let values = density.as_array();
        let (medium, place) =
            detached::run(py, None, || self.medium_with(&values, transform, "density"))?;
        self.scene.medium = medium;
        self.boxes.density = place;
        Ok(())
    }

    /// The scene file's camera (or the one `from_parts` was given); None without one.
    #[getter]
    fn camera(&self) -> Option<Camera> {
        self.own_camera().map(|camera| Camera { camera })
    }

    /// Renders the scene's camera (an (H, W, 3) float32 array of linear radiance) or every camera
    /// of a list ((N, H, W, 3); all of one size; view i with seed + i). `density` renders another
    /// density of the same shape without changing the scene. spp, seed and max_depth default to
    /// the scene's `[render]` settings. The same bits as `volgrad render` for the same camera,
    /// spp and seed, at any thread count.
    #[pyo3(signature = (cameras = None, spp = None, seed = None, max_depth = None, threads = None, density = None))]
    #[allow(clippy::too_many_arguments)]
    fn render<'py>(
        &mut self,
        py: Python<'py>,
        cameras: Option<Vec<Camera>>,
        spp: Option<u32>,
        seed: Option<u64>,
        max_depth: Option<u32>,
        threads: Option<usize>,
        density: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let sampling = Sampling::resolve(&self.scene, spp, seed, max_depth).or_raise()?;
        let listed = cameras.is_some();
        let cameras = views::cameras(self.own_camera(), cameras).or_raise()?;
        let image = self.run_with_density(py, threads, density, |scene, _| {
            views::render_views(scene, &cameras, &sampling)
        })?;
        views::warn_non_finite(py, image.non_finite, image.paths)?;
        views::image_array(py, image, &cameras, listed)
    }

    /// Σ over pixels of adjoint · ∂image/∂θ, the vector-Jacobian product of `render`: θ the
    /// density (`parameter = "extinction"`, shaped like `density`), the albedo grid's values
    /// ("albedo"; (nx, ny, nz) or (nx, ny, nz, 3)) or the emission grid's ("emission").
    /// `adjoint` is (H, W, 3) for the scene's camera or (N, H, W, 3) for a list of cameras, as
    /// `render` returns. The paths use a stream of their own: with the seed of the render the
    /// adjoint came from they are still independent of it.
    #[pyo3(signature = (adjoint, cameras = None, estimator = "joint", parameter = "extinction", spp = None, seed = None, max_depth = None, threads = None, density = None))]
    #[allow(clippy::too_many_arguments)]
    fn grad<'py>(
        &mut self,
        py: Python<'py>,
        adjoint: &Bound<'py, PyAny>,
        cameras: Option<Vec<Camera>>,
        estimator: &str,
        parameter: &str,
        spp: Option<u32>,
        seed: Option<u64>,
        max_depth: Option<u32>,
        threads: Option<usize>,
        density: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let sampling = Sampling::resolve(&self.scene, spp, seed, max_depth).or_raise()?;
        let estimator = views::estimator(estimator).or_raise()?;
        let parameter = views::parameter(parameter).or_raise()?;
        let listed = cameras.is_some();
        let cameras = views::cameras(self.own_camera(), cameras).or_raise()?;
        let adjoint =
            arrays::float32_argument::<numpy::IxDyn>(adjoint, "adjoint", "shaped like the images")?;
        let deltas = views::adjoint_images(&adjoint, &cameras, listed).or_raise()?;
        let gradient = self.run_with_density(py, threads, density, |scene, boxes| {
            views::grad(
                scene, &cameras, &deltas, estimator, parameter, &sampling, boxes,
            )
        })?;
        views::warn_non_finite(py, gradient.non_finite, gradient.paths)?;
        if let Some(v) = gradient.values.iter().find(|v| !v.is_finite()) {
            // Every path's term is finite; their sum went beyond f32's range.
            return Err(PyValueError::new_err(format!(
                "the gradient overflowed float32 (a voxel's sum is {v}): scale the adjoint down (its largest magnitude is {:e})",
                adjoint.as_array().iter().fold(0.0f32, |m, a| m.max(a.abs()))
            )));
        }
        Ok(gradient.values.into_pyarray(py))
    }

    fn __repr__(&self) -> String {
        let m = &self.scene.medium;
        format!(
            "Scene('{}', density {:?} at index {:?}, density_scale {}, {} leaves)",
            self.scene.path.display(),
            self.boxes.density.shape,
            self.boxes.density.origin.to_array(),
            m.density_scale,
            m.grid.leaves().len()
        )
    }
}

impl Scene {
    /// Runs `work` without the GIL on `threads` threads, on the scene with the `density` argument,
    /// if given, in place of its own for this call only.
    fn run_with_density<T: Send>(
        &mut self,
        py: Python<'_>,
        threads: Option<usize>,
        density: Option<&Bound<'_, PyAny>>,
        work: impl FnOnce(&mut RustScene, &Boxes) -> anyhow::Result<T> + Send,
    ) -> PyResult<T> {
        let density = density
            .map(|d| {
                arrays::float32_argument::<numpy::Ix3>(d, "density", "shaped like Scene.density")
            })
            .transpose()?;
        let values = density.as_ref().map(|d| d.as_array());
        let boxes = self.boxes;
        detached::run(py, threads, || {
            let swapped = (values.as_ref())
                .map(|v| self.medium_with(v, None, "density"))
                .transpose()?;
            views::with_medium(&mut self.scene, swapped.map(|m| m.0), |scene| {
                work(scene, &boxes)
            })
        })
    }

    fn index_to_world_rows(&self) -> [f64; 16] {
        arrays::rows_of(
            self.boxes
                .density
                .array_to_world(&self.scene.medium.transform),
        )
    }
}

/// What an emission array's values mean, as a scene file's `medium.emission` table without its
/// grid: `{"radiance": [r, g, b]}` (the default, white) or `{"blackbody": {…}, "strength": s}`.
fn emission_file(py: Python<'_>, kind: Option<&Bound<'_, PyDict>>) -> PyResult<EmissionFile> {
    let table = PyDict::new(py);
    table.set_item("grid", "emission")?;
    match kind {
        Some(kind) => table.update(kind.as_mapping())?,
        None => table.set_item("radiance", [1.0, 1.0, 1.0])?,
    }
    let json: String = py
        .import("json")?
        .call_method1("dumps", (table,))?
        .extract()?;
    serde_json::from_str(&json).map_err(|e| PyValueError::new_err(format!("emission_kind: {e}")))
}
