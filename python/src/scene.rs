//! `Scene`: a scene file loaded, or a scene built from parts (a density array and the medium's
//! constants, lights and a camera), with its density as an array that can be read and replaced.

use std::path::{Path, PathBuf};

use glam::IVec3;
use numpy::{IntoPyArray, PyArrayDyn};
use pyo3::exceptions::{PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use volgrad::render::scene::{Scene as RustScene, SceneFile, SceneNeeds};
use volgrad::render::scene_file::EmissionFile;
use volgrad::volume::medium::Medium;
use volgrad::volume::transform::IndexTransform;

use crate::arrays::{self, VoxelBox};
use crate::camera::Camera;
use crate::detached;
use crate::errors::{self, check_path, OrRaise};
use crate::grids::{matrix, GridArrays};
use crate::media;
use crate::stand_ins::{StandInViews, StandIns};
use crate::views::{self, Boxes, CameraArg, Sampling};

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
    /// How many times `set_density` has replaced the density: an autograd function that rendered
    /// the scene's own density checks that its backward pass differentiates the same one.
    pub density_changes: u64,
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
                "{argument} has shape {:?} but the scene's density is {:?}: an array of another shape needs its own index_to_world (scene.set_density(array, index_to_world))",
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
        check_path(&path, "path")?;
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
            density_changes: 0,
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
        density_scale: f64,
        albedo: Option<&Bound<'_, PyAny>>,
        phase_g: f64,
        lights: Option<&Bound<'_, PyAny>>,
        camera: Option<Camera>,
        spp: Option<u32>,
        seed: Option<&Bound<'_, PyAny>>,
        max_depth: Option<u32>,
        emission: Option<&Bound<'_, PyAny>>,
        emission_kind: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Scene> {
        let seed = errors::seed(seed)?;
        let transform = arrays::matrix_argument(index_to_world, "index_to_world")?;
        let density =
            arrays::float32_argument::<numpy::Ix3>(density, "density", "of shape (nx, ny, nz)")?;
        // The constants go through the scene file's own reader, so that they are checked and
        // named as a scene file's keys are.
        let density_scale = errors::narrow("density_scale", density_scale)?;
        let phase_g = errors::narrow("phase_g", phase_g)?;
        let medium = PyDict::new(py);
        medium.set_item("density_scale", density_scale)?;
        medium.set_item("phase_g", phase_g)?;
        // An array shaped like the density is a grid; a number or a triple, numpy's included
        // (a 0-d or 1-d array), is the constant albedo a scene file would give.
        let is_grid = |a: &Bound<'_, PyAny>| -> PyResult<bool> {
            Ok(a.hasattr("ndim")? && a.getattr("ndim")?.extract::<usize>()? >= 3)
        };
        let albedo_array = match albedo {
            Some(a) if is_grid(a)? => Some(arrays::float32_argument::<numpy::IxDyn>(
                a,
                "albedo",
                "shaped like the density",
            )?),
            Some(a) if a.hasattr("tolist")? => {
                medium.set_item("albedo", a.call_method0("tolist")?)?;
                None
            }
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
        let json = scene_json(py, spec.as_any(), "albedo and the lights")?;
        let file: SceneFile = serde_json::from_str(&json)
            .map_err(|e| PyValueError::new_err(format!("scene parts: {}", without_position(&e))))?;
        let mut scene =
            RustScene::from_file_as(file, Path::new("<from_parts>"), SceneNeeds::Constants)
                .or_raise()?;
        let has_camera = camera.is_some();
        if let Some(camera) = camera {
            scene.camera = camera.camera;
        }
        if emission.is_none() && emission_kind.is_some() {
            return Err(PyValueError::new_err(
                "emission_kind says what an emission array's values mean: give the array as emission=",
            ));
        }
        let emission = match emission {
            Some(values) => Some((
                arrays::float32_argument::<numpy::Ix3>(
                    values,
                    "emission",
                    "shaped like the density",
                )?,
                emission_file(py, emission_kind)?
                    .emission_kind()
                    .or_raise()?,
            )),
            None => None,
        };
        let values = density.as_array();
        let place = VoxelBox::of_array({
            let (nx, ny, nz) = values.dim();
            [nx, ny, nz]
        });
        let albedo_values = albedo_array.as_ref().map(|a| a.as_array());
        let emission_values = emission.as_ref().map(|(v, kind)| (v.as_array(), kind));
        // The grids are built in parallel: without the GIL, on the process's pool.
        scene.medium = detached::run(py, None, || {
            let grid = media::density_grid(&values, IVec3::ZERO, density_scale, "density")?;
            let mut medium = media::medium_over(&scene, grid, transform, place);
            if let Some(albedo) = &albedo_values {
                medium.albedo = media::albedo_grid(albedo, place, transform, medium.filter)?;
            }
            if let Some((values, kind)) = &emission_values {
                medium.emission = Some(media::emission_grid(
                    values,
                    place,
                    transform,
                    (*kind).clone(),
                    medium.filter,
                )?);
            }
            Ok(medium)
        })?;
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
            density_changes: 0,
        })
    }

    /// The density as (array (nx, ny, nz) float32, 4×4 index_to_world of the array's indices).
    #[getter]
    fn density<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<GridArrays<'py>> {
        let guard = readable(slf)?;
        let this = &*guard;
        let place = this.boxes.density;
        let values = detached::run(py, None, || {
            arrays::from_brickmap(&this.scene.medium.grid, place, "the density")
        })?;
        Ok((
            values.into_pyarray(py),
            matrix(py, this.index_to_world_rows()),
        ))
    }

    /// Replaces the density: an array of the current shape keeps the current index_to_world; with
    /// `index_to_world`, any shape.
    #[pyo3(signature = (density, index_to_world = None))]
    fn set_density(
        slf: &Bound<'_, Self>,
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
        let mut guard = exclusive(slf)?;
        let this = &mut *guard;
        let (medium, place) =
            detached::run(py, None, || this.medium_with(&values, transform, "density"))?;
        this.scene.medium = medium;
        this.boxes.density = place;
        this.density_changes += 1;
        Ok(())
    }

    /// The shape `grad(…, parameter=…)` returns and a stand-in for that grid takes (for
    /// `volgrad.jax`, which checks it while tracing: errors inside its callback lose their type);
    /// a `ValueError` where the scene has no such grid.
    fn _values_shape(&self, parameter: &str) -> PyResult<Vec<usize>> {
        let parameter = views::parameter(parameter).or_raise()?;
        let (place, channels) =
            views::parameter_box(&self.scene, parameter, &self.boxes).or_raise()?;
        Ok(views::values_shape(&place, channels))
    }

    /// How many times `set_density` has replaced the density (for `volgrad.torch`).
    #[getter]
    fn _density_changes(&self) -> u64 {
        self.density_changes
    }

    /// The scene file's camera (or the one `from_parts` was given); None without one.
    #[getter]
    fn camera(slf: &Bound<'_, Self>) -> PyResult<Option<Camera>> {
        Ok(readable(slf)?.own_camera().map(|camera| Camera { camera }))
    }

    /// Renders the scene's camera or one camera (an (H, W, 3) float32 array of linear radiance),
    /// or every camera of a list ((N, H, W, 3); all of one size; view i with seed +
    /// i·0x9E3779B97F4A7C15). `density`, `albedo` and `emission` render other values of those
    /// grids, shaped as `grad` returns them, without changing the scene. spp, seed and max_depth
    /// default to the scene's `[render]` settings. The same bits as `volgrad render` for the same
    /// camera, spp and seed, at any thread count.
    #[pyo3(signature = (cameras = None, spp = None, seed = None, max_depth = None, threads = None, density = None, albedo = None, emission = None))]
    #[allow(clippy::too_many_arguments)]
    fn render<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
        cameras: Option<CameraArg>,
        spp: Option<u32>,
        seed: Option<&Bound<'_, PyAny>>,
        max_depth: Option<u32>,
        threads: Option<usize>,
        density: Option<&Bound<'py, PyAny>>,
        albedo: Option<&Bound<'py, PyAny>>,
        emission: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let stand_ins = StandIns::read(density, albedo, emission)?;
        let mut guard = exclusive(slf)?;
        let this = &mut *guard;
        let seed = errors::seed(seed)?;
        let sampling = Sampling::resolve(&this.scene, spp, seed, max_depth).or_raise()?;
        let (cameras, listed) = views::cameras(this.own_camera(), cameras).or_raise()?;
        let image = this.run_with(py, threads, &stand_ins, |scene, _| {
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
    /// adjoint came from they are still independent of it. `density`, `albedo` and `emission`
    /// stand in for the scene's grids as in `render`.
    #[pyo3(signature = (adjoint, cameras = None, estimator = "joint", parameter = "extinction", spp = None, seed = None, max_depth = None, threads = None, density = None, albedo = None, emission = None))]
    #[allow(clippy::too_many_arguments)]
    fn grad<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
        adjoint: &Bound<'py, PyAny>,
        cameras: Option<CameraArg>,
        estimator: &str,
        parameter: &str,
        spp: Option<u32>,
        seed: Option<&Bound<'_, PyAny>>,
        max_depth: Option<u32>,
        threads: Option<usize>,
        density: Option<&Bound<'py, PyAny>>,
        albedo: Option<&Bound<'py, PyAny>>,
        emission: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let stand_ins = StandIns::read(density, albedo, emission)?;
        let mut guard = exclusive(slf)?;
        let this = &mut *guard;
        let seed = errors::seed(seed)?;
        let sampling = Sampling::resolve(&this.scene, spp, seed, max_depth).or_raise()?;
        let estimator = views::estimator(estimator).or_raise()?;
        let parameter = views::parameter(parameter).or_raise()?;
        let (cameras, listed) = views::cameras(this.own_camera(), cameras).or_raise()?;
        let adjoint =
            arrays::float32_argument::<numpy::IxDyn>(adjoint, "adjoint", "shaped like the images")?;
        let deltas = views::adjoint_images(&adjoint, &cameras, listed).or_raise()?;
        let gradient = this.run_with(py, threads, &stand_ins, |scene, boxes| {
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

    fn __repr__(slf: &Bound<'_, Self>) -> PyResult<String> {
        let this = readable(slf)?;
        let m = &this.scene.medium;
        Ok(format!(
            "Scene('{}', density {:?} at index {:?}, density_scale {}, {} leaves)",
            this.scene.path.display(),
            this.boxes.density.shape,
            this.boxes.density.origin.to_array(),
            m.density_scale,
            m.grid.leaves().len()
        ))
    }
}

/// The scene for a call that changes it, or swaps its grids for the call's length. A Scene runs
/// one call at a time; PyO3's own refusal of a second one says only "Already borrowed".
fn exclusive<'py>(slf: &Bound<'py, Scene>) -> PyResult<PyRefMut<'py, Scene>> {
    slf.try_borrow_mut().map_err(|_| busy())
}

/// The scene for a call that reads it (its density, camera, description).
fn readable<'py>(slf: &Bound<'py, Scene>) -> PyResult<PyRef<'py, Scene>> {
    slf.try_borrow().map_err(|_| busy())
}

fn busy() -> PyErr {
    PyRuntimeError::new_err(
        "this Scene is busy with a call from another thread: a Scene runs one call at a time, so give each thread a Scene of its own (Scene.load or Scene.from_parts again)",
    )
}

impl Scene {
    /// Runs `work` without the GIL on `threads` threads, on the scene with the `stand_ins`
    /// arrays, if any, in place of its own grids for this call only.
    fn run_with<T: Send>(
        &mut self,
        py: Python<'_>,
        threads: Option<usize>,
        stand_ins: &StandIns<'_>,
        work: impl FnOnce(&mut RustScene, &Boxes) -> anyhow::Result<T> + Send,
    ) -> PyResult<T> {
        let arrays = stand_ins.views();
        let boxes = self.boxes;
        detached::run(py, threads, || {
            let medium = self.medium_for(&arrays)?;
            views::with_medium(&mut self.scene, medium, |scene| work(scene, &boxes))
        })
    }

    /// The medium with `arrays` in place of its grids; None when there are none.
    fn medium_for(&self, arrays: &StandInViews<'_>) -> anyhow::Result<Option<Medium>> {
        if !arrays.any() {
            return Ok(None);
        }
        let mut medium = match &arrays.density {
            Some(values) => self.medium_with(values, None, "density")?.0,
            None => self.scene.medium.clone(),
        };
        let own = &self.scene.medium;
        if let Some(values) = &arrays.albedo {
            medium.albedo = media::albedo_over(own, values, self.boxes.albedo)?;
        }
        if let Some(values) = &arrays.emission {
            medium.emission = Some(media::emission_over(own, values, self.boxes.emission)?);
        }
        Ok(Some(medium))
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
    const KEYS: [&str; 3] = ["radiance", "blackbody", "strength"];
    let table = PyDict::new(py);
    table.set_item("grid", "emission")?;
    match kind {
        Some(kind) => {
            for key in kind.keys() {
                let key: String = key.str()?.extract()?;
                if !KEYS.contains(&key.as_str()) {
                    return Err(PyValueError::new_err(format!(
                        "emission_kind: unknown key '{key}' (expected radiance, or blackbody with strength)"
                    )));
                }
            }
            table.update(kind.as_mapping())?
        }
        None => table.set_item("radiance", [1.0, 1.0, 1.0])?,
    }
    let json = scene_json(py, table.as_any(), "emission_kind")?;
    serde_json::from_str(&json)
        .map_err(|e| PyValueError::new_err(format!("emission_kind: {}", without_position(&e))))
}

/// `value` (dicts and lists of numbers) as JSON for the scene file's reader: numpy arrays and
/// scalars as their lists and numbers; a non-finite number or another object refused, naming
/// `what` held it.
fn scene_json(py: Python<'_>, value: &Bound<'_, PyAny>, what: &str) -> PyResult<String> {
    let kwargs = PyDict::new(py);
    kwargs.set_item("allow_nan", false)?;
    let as_list = py
        .import("operator")?
        .call_method1("methodcaller", ("tolist",))?;
    kwargs.set_item("default", as_list)?;
    let json = py
        .import("json")?
        .call_method("dumps", (value,), Some(&kwargs));
    let json = json.map_err(|e| {
        if e.is_instance_of::<PyValueError>(py) {
            PyValueError::new_err(format!("{what}: values must be finite numbers"))
        } else {
            PyTypeError::new_err(format!(
                "{what}: values must be numbers, lists of numbers or numpy arrays ({e})"
            ))
        }
    })?;
    let json: String = json.extract()?;
    // Python's floats are f64: a light of 1e-300 would be dark without a word.
    let value: serde_json::Value =
        serde_json::from_str(&json).map_err(|e| PyValueError::new_err(format!("{what}: {e}")))?;
    volgrad::io::json::within_f32(&value, "")
        .map_err(|e| PyValueError::new_err(format!("{what}: {e}")))?;
    Ok(json)
}

/// A JSON reader's message without "at line 1 column N": the JSON is ours, not the user's.
fn without_position(error: &serde_json::Error) -> String {
    let message = error.to_string();
    match message.rfind(" at line ") {
        Some(at) => message[..at].to_string(),
        None => message,
    }
}
