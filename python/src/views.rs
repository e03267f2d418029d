//! What `Scene.render` and `Scene.grad` do once their arguments are checked: the views one after
//! another through the library's image loops and gradient passes, their gradients summed as quanta
//! of one quantum (so the sum is the same bits at any thread count).

use anyhow::{bail, Context, Result};
use glam::Vec3;
use numpy::ndarray::{ArrayD, IxDyn};
use numpy::{IntoPyArray, PyArrayDyn, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::PyRuntimeWarning;
use pyo3::prelude::*;
use volgrad::gradient::adjoint::Estimator;
use volgrad::gradient::passes::{
    add_gradient_of, gradient_grid_for, sample_scale, BandedGradient, GradOptions, Parameter,
    QuantumBands,
};
use volgrad::gradient::pixel_samples::PixelSamples;
use volgrad::render::camera::Camera as RustCamera;
use volgrad::render::image::{self as image_loop, RenderOptions};
use volgrad::render::pixel_set::PixelSet;
use volgrad::render::scene::Scene as RustScene;
use volgrad::volume::medium::Medium;

use crate::arrays::{self, VoxelBox};
use crate::camera::Camera;

/// spp, seed and max_depth: given, or the scene's `[render]` settings.
pub struct Sampling {
    pub spp: u32,
    pub seed: u64,
    pub max_depth: u32,
}

impl Sampling {
    pub fn resolve(
        scene: &RustScene,
        spp: Option<u32>,
        seed: Option<u64>,
        max_depth: Option<u32>,
    ) -> Result<Self> {
        let spp = spp.unwrap_or(scene.settings.spp);
        if spp == 0 {
            bail!("spp must be at least 1");
        }
        Ok(Sampling {
            spp,
            seed: seed.unwrap_or(scene.settings.seed),
            max_depth: max_depth.unwrap_or(scene.settings.max_depth),
        })
    }

    /// View i's seed: seed + i·φ (mod 2⁶⁴), φ = 2⁶⁴ / the golden ratio. The views of one call
    /// are independent of each other, and so are the calls of a training loop that passes the
    /// iteration as the seed: with seed + i, the view at position i + 1 of one iteration would
    /// redraw the paths it drew at position i of the one before. View 0 keeps the seed itself,
    /// as a render of the scene's camera does.
    fn seed_of(&self, view: usize) -> u64 {
        const VIEW_STRIDE: u64 = 0x9E37_79B9_7F4A_7C15;
        self.seed
            .wrapping_add((view as u64).wrapping_mul(VIEW_STRIDE))
    }
}

/// A call's `cameras` argument: one camera (its image is (H, W, 3), as the scene's own camera's)
/// or a list of them ((N, H, W, 3)).
#[derive(FromPyObject)]
pub enum CameraArg {
    One(Camera),
    List(Vec<Camera>),
}

/// The cameras of a call, and whether they came as a list: the list given (non-empty, all of
/// one size), the one camera given, or the scene's own.
pub fn cameras(
    own: Option<RustCamera>,
    cameras: Option<CameraArg>,
) -> Result<(Vec<RustCamera>, bool)> {
    let cameras = match cameras {
        None => {
            let own = own.context(
                "the scene has no camera of its own (Scene.from_parts without camera=): give cameras=[…]",
            )?;
            return Ok((vec![own], false));
        }
        Some(CameraArg::One(camera)) => return Ok((vec![camera.camera], false)),
        Some(CameraArg::List(cameras)) => cameras,
    };
    let Some(first) = cameras.first() else {
        bail!("cameras: the list is empty (give None for the scene's own camera)");
    };
    let size = (first.camera.width, first.camera.height);
    if let Some((i, c)) = cameras
        .iter()
        .enumerate()
        .find(|(_, c)| (c.camera.width, c.camera.height) != size)
    {
        bail!(
            "cameras: every camera of a call has one size (camera 0 is {}×{}, camera {i} is {}×{}); render the others in a call of their own",
            size.0,
            size.1,
            c.camera.width,
            c.camera.height
        );
    }
    Ok((cameras.into_iter().map(|c| c.camera).collect(), true))
}

pub fn estimator(name: &str) -> Result<Estimator> {
    Ok(match name {
        "joint" => Estimator::Joint,
        "drt" => Estimator::Drt,
        "naive" => Estimator::Naive,
        _ => bail!("estimator must be \"joint\", \"drt\" or \"naive\" (got \"{name}\")"),
    })
}

pub fn parameter(name: &str) -> Result<Parameter> {
    Ok(match name {
        "extinction" => Parameter::Extinction,
        "albedo" => Parameter::Albedo,
        "emission" => Parameter::Emission,
        _ => bail!("parameter must be \"extinction\", \"albedo\" or \"emission\" (got \"{name}\")"),
    })
}

/// Runs `work` on the scene with `medium` in place of its own, if given, and puts its own back.
pub fn with_medium<T>(
    scene: &mut RustScene,
    medium: Option<Medium>,
    work: impl FnOnce(&mut RustScene) -> Result<T>,
) -> Result<T> {
    let own = medium.map(|m| std::mem::replace(&mut scene.medium, m));
    let camera = scene.camera;
    let result = work(scene);
    scene.camera = camera;
    if let Some(own) = own {
        scene.medium = own;
    }
    result
}

/// Values computed over the views, with the samples dropped as non-finite.
pub struct Computed<T> {
    pub values: T,
    pub paths: u64,
    pub non_finite: u64,
}

/// Every camera's image, one after another (each through every thread).
pub fn render_views(
    scene: &mut RustScene,
    cameras: &[RustCamera],
    sampling: &Sampling,
) -> Result<Computed<Vec<f32>>> {
    let mut values = Vec::new();
    let (mut paths, mut non_finite) = (0, 0);
    for (i, camera) in cameras.iter().enumerate() {
        scene.camera = *camera;
        let options = RenderOptions {
            spp: sampling.spp,
            seed: sampling.seed_of(i),
            max_depth: sampling.max_depth,
            progress: false,
        };
        let (image, stats) = image_loop::render(scene, &options);
        values.extend(image.pixels.iter().flat_map(|p| p.to_array()));
        paths += stats.paths;
        non_finite += stats.non_finite;
    }
    Ok(Computed {
        values,
        paths,
        non_finite,
    })
}

/// Images as an (H, W, 3) array, or (N, H, W, 3) when the cameras were `listed`.
pub fn image_array<'py>(
    py: Python<'py>,
    values: Computed<Vec<f32>>,
    cameras: &[RustCamera],
    listed: bool,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let (w, h) = (cameras[0].width as usize, cameras[0].height as usize);
    let shape = match listed {
        true => vec![cameras.len(), h, w, 3],
        false => vec![h, w, 3],
    };
    let array = ArrayD::from_shape_vec(IxDyn(&shape), values.values).map_err(|e| {
        pyo3::exceptions::PyRuntimeError::new_err(format!("image of the wrong size: {e}"))
    })?;
    Ok(array.into_pyarray(py))
}

/// The adjoint images of the views: (H, W, 3) for the scene's camera, (N, H, W, 3) for a list.
pub fn adjoint_images(
    adjoint: &PyReadonlyArrayDyn<f32>,
    cameras: &[RustCamera],
    listed: bool,
) -> Result<Vec<Vec<Vec3>>> {
    let (w, h) = (cameras[0].width as usize, cameras[0].height as usize);
    let expected = match listed {
        true => vec![cameras.len(), h, w, 3],
        false => vec![h, w, 3],
    };
    if adjoint.shape() != expected.as_slice() {
        bail!(
            "adjoint has shape {:?}; the images of these cameras are {:?}",
            adjoint.shape(),
            expected
        );
    }
    let view = adjoint.as_array();
    let flat: Vec<f32> = view.iter().copied().collect();
    if let Some(bad) = flat.iter().find(|v| !v.is_finite()) {
        bail!(
            "adjoint holds non-finite values ({bad}): an adjoint image must be finite everywhere"
        );
    }
    Ok(flat
        .chunks(w * h * 3)
        .map(|image| image.chunks(3).map(Vec3::from_slice).collect())
        .collect())
}

/// The boxes of voxels a scene's grids are arrays over: what `Scene.density` returns and what
/// each parameter's gradient comes back in.
#[derive(Debug, Clone, Copy)]
pub struct Boxes {
    pub density: VoxelBox,
    pub albedo: VoxelBox,
    pub emission: VoxelBox,
}

impl Boxes {
    /// A loaded scene's: each grid's active voxels.
    pub fn active(scene: &RustScene) -> Self {
        let m = &scene.medium;
        let albedo = m.albedo.grid().map(|a| &a.channels[0]);
        Boxes {
            density: VoxelBox::active(&m.grid),
            albedo: albedo.map_or(VoxelBox::EMPTY, VoxelBox::active),
            emission: m
                .emission
                .as_ref()
                .map_or(VoxelBox::EMPTY, |e| VoxelBox::active(&e.grid)),
        }
    }
}

/// The box of values a parameter's gradient comes back in (and the passes' domain, so that voxels
/// at 0 get theirs too) and its number of colour channels; refused where the scene has no such
/// grid.
pub fn parameter_box(
    scene: &RustScene,
    parameter: Parameter,
    boxes: &Boxes,
) -> Result<(VoxelBox, usize)> {
    let medium = &scene.medium;
    Ok(match parameter {
        Parameter::Extinction => (boxes.density, 1),
        Parameter::Emission => match &medium.emission {
            Some(_) => (boxes.emission, 1),
            None => bail!(
                "parameter \"emission\": the scene's medium has no emission (medium.emission)"
            ),
        },
        Parameter::Albedo => match medium.albedo.grid() {
            Some(a) => (boxes.albedo, a.channels.len()),
            None => bail!("parameter \"albedo\": the scene's albedo is a constant, not a grid"),
        },
    })
}

/// The shape of a parameter's values over `place`: a last axis for a colour grid's channels.
pub fn values_shape(place: &VoxelBox, channels: usize) -> Vec<usize> {
    let mut shape = place.shape.to_vec();
    if channels > 1 {
        shape.push(channels);
    }
    shape
}

/// Σ over the views' pixels of δ · ∂image/∂θ, dense over the parameter's box (a last axis of 3
/// for an RGB albedo grid, one pass per channel with the same paths, as `volgrad grad` does).
pub fn grad(
    scene: &mut RustScene,
    cameras: &[RustCamera],
    deltas: &[Vec<Vec3>],
    estimator: Estimator,
    parameter: Parameter,
    sampling: &Sampling,
    boxes: &Boxes,
) -> Result<Computed<ArrayD<f32>>> {
    let (place, channels) = parameter_box(scene, parameter, boxes)?;
    // Before any path is traced: the result is a dense array of this box.
    place.checked_len("the gradient")?;
    if place.is_empty() {
        return Ok(Computed {
            values: ArrayD::zeros(IxDyn(&values_shape(&place, channels))),
            paths: 0,
            non_finite: 0,
        });
    }
    let scale = sample_scale(scene, parameter);
    let bands = QuantumBands::of(
        deltas
            .iter()
            .map(|d| (&d[..], scale, PixelSamples::Uniform)),
        sampling.spp,
    );
    // `volgrad grad`'s defaults: per-path suffixes, radiance.
    let pass = GradOptions {
        parameter,
        domain: Some((place.origin, place.last())),
        ..GradOptions::new(estimator, sampling.spp, sampling.seed, sampling.max_depth)
    };
    let (mut paths, mut non_finite) = (0, 0);
    let mut planes = Vec::with_capacity(channels);
    for c in 0..channels {
        let channel = (channels > 1).then_some(c);
        let grid = gradient_grid_for(scene, &GradOptions { channel, ..pass });
        let mut total = BandedGradient::new(bands.clone(), grid);
        for (i, (camera, delta)) in cameras.iter().zip(deltas).enumerate() {
            scene.camera = *camera;
            let options = GradOptions {
                seed: sampling.seed_of(i),
                channel,
                ..pass
            };
            let every_pixel = PixelSet::All(camera.width * camera.height);
            let (_, stats) =
                add_gradient_of(scene, (delta, scale), &options, &every_pixel, &mut total);
            paths += stats.paths;
            non_finite += stats.non_finite;
        }
        planes.push(arrays::gradient_in(&total.values(), place)?);
    }
    let values = match channels {
        1 => planes.pop().expect("one channel").into_dyn(),
        _ => {
            let views: Vec<_> = planes.iter().map(|p| p.view()).collect();
            numpy::ndarray::stack(numpy::ndarray::Axis(3), &views)?.into_dyn()
        }
    };
    Ok(Computed {
        values,
        paths,
        non_finite,
    })
}

/// A Python warning when paths came out NaN or infinite (they count as 0), as the command line
/// warns on stderr.
pub fn warn_non_finite(py: Python<'_>, non_finite: u64, paths: u64) -> PyResult<()> {
    if non_finite == 0 {
        return Ok(());
    }
    let message =
        format!("{non_finite} non-finite samples were dropped (counted as 0) out of {paths} paths");
    let message = std::ffi::CString::new(message).expect("the message holds no NUL");
    PyErr::warn(py, &py.get_type::<PyRuntimeWarning>(), &message, 1)
}
