//! The medium's grids from arrays: a density (checked, as a brick map, the medium filling the
//! array's box), an albedo grid and an emission grid shaped like it.

use glam::{IVec3, Vec3};
use numpy::ndarray::{ArrayView3, ArrayViewD, Axis, Ix3};
use volgrad::optimize::unknown::medium_like;
use volgrad::render::medium_grids::check_emission_limit;
use volgrad::render::scene::Scene as RustScene;
use volgrad::render::scene_check::MAX_EXTINCTION;
use volgrad::volume::albedo::{Albedo, AlbedoGrid};
use volgrad::volume::brickmap::BrickMap;
use volgrad::volume::emission::{Emission, EmissionKind};
use volgrad::volume::medium::{Filter, Medium};
use volgrad::volume::transform::IndexTransform;

use crate::arrays::{self, VoxelBox};

/// The scene's medium with `grid` (placed as `place` says, under `transform`) as its density: the
/// optical constants, emission and majorant settings kept, the medium filling the box.
pub fn medium_over(
    scene: &RustScene,
    grid: BrickMap,
    transform: IndexTransform,
    place: VoxelBox,
) -> Medium {
    let bounds = match place.is_empty() {
        true => (Vec3::ZERO, Vec3::ZERO),
        false => (place.origin.as_vec3() - 0.5, place.last().as_vec3() + 0.5),
    };
    let mut medium = medium_like(scene, grid, transform, bounds);
    medium.emission = scene.medium.emission.clone();
    medium
}

/// `values` checked as densities of a medium with `density_scale`, as a brick map at `origin`.
pub fn density_grid(
    values: &ArrayView3<f32>,
    origin: IVec3,
    density_scale: f32,
    argument: &str,
) -> anyhow::Result<BrickMap> {
    arrays::check_values(values, argument, false)?;
    let grid = arrays::to_brickmap(values, origin, argument)?;
    let extinction = density_scale as f64 * grid.max_value() as f64;
    if extinction > MAX_EXTINCTION {
        anyhow::bail!("{argument}: density_scale × its largest value is {extinction:.3e}: too large to track (at most {MAX_EXTINCTION:e} per world unit)");
    }
    Ok(grid)
}

/// An emission array shaped like the density as the medium's emission grid: non-negative where
/// it scales a radiance, its brightest voxel within the light cap.
pub fn emission_grid(
    values: &ArrayView3<f32>,
    place: VoxelBox,
    transform: IndexTransform,
    kind: EmissionKind,
    filter: Filter,
) -> anyhow::Result<Emission> {
    let (nx, ny, nz) = values.dim();
    if [nx, ny, nz] != place.shape {
        anyhow::bail!(
            "emission has shape {:?}: it is shaped like the density, {:?}",
            [nx, ny, nz],
            place.shape
        );
    }
    arrays::check_values(
        values,
        "emission",
        matches!(kind, EmissionKind::Blackbody { .. }),
    )?;
    let emission = Emission::new(
        "emission".into(),
        arrays::to_brickmap(values, place.origin, "emission")?,
        transform,
        kind,
        filter,
    );
    check_emission_limit(&emission, "emission")?;
    Ok(emission)
}

/// An albedo array shaped like the density ((nx, ny, nz) grey or (nx, ny, nz, 3)) as the
/// medium's albedo grid, its values checked to lie in [0, 1].
pub fn albedo_grid(
    values: &ArrayViewD<f32>,
    place: VoxelBox,
    transform: IndexTransform,
    filter: Filter,
) -> anyhow::Result<Albedo> {
    let shape = values.shape();
    let channels = match shape {
        [x, y, z] if [*x, *y, *z] == place.shape => 1,
        [x, y, z, 3] if [*x, *y, *z] == place.shape => 3,
        _ => anyhow::bail!("albedo has shape {shape:?}: an array of albedos is shaped like the density, {:?}, or with a last axis of 3 (RGB)", place.shape),
    };
    if values.iter().any(|v| !(0.0..=1.0).contains(v)) {
        anyhow::bail!("albedo: every value must lie in [0, 1]");
    }
    let maps = (0..channels)
        .map(|c| {
            let channel = match channels {
                1 => values.view().into_dimensionality::<Ix3>(),
                _ => values.index_axis(Axis(3), c).into_dimensionality::<Ix3>(),
            }?;
            arrays::to_brickmap(&channel, place.origin, "albedo")
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok(Albedo::Grid(Box::new(AlbedoGrid::new(
        "albedo".into(),
        maps,
        Vec3::ZERO,
        transform,
        filter,
    ))))
}

/// `values` in place of `medium`'s albedo grid, over its box `place` and under its transform;
/// refused where the albedo is a constant, or where the grid's background (its value outside
/// the file's voxels) is not 0, which an array over the box cannot carry.
pub fn albedo_over(
    medium: &Medium,
    values: &ArrayViewD<f32>,
    place: VoxelBox,
) -> anyhow::Result<Albedo> {
    let Some(grid) = medium.albedo.grid() else {
        anyhow::bail!(
            "albedo: the scene's albedo is a constant, not a grid (Scene.from_parts(albedo=array) makes one)"
        );
    };
    if grid.background != Vec3::ZERO {
        anyhow::bail!(
            "albedo: the scene's albedo grid has a background of {} outside its voxels, which an array over its box cannot carry: build the scene with Scene.from_parts(albedo=array)",
            grid.background
        );
    }
    albedo_grid(values, place, grid.transform, grid.filter)
}

/// `values` in place of `medium`'s emission grid, over its box `place`, with its transform and
/// what its values mean; refused where the medium has no emission.
pub fn emission_over(
    medium: &Medium,
    values: &ArrayView3<f32>,
    place: VoxelBox,
) -> anyhow::Result<Emission> {
    let Some(own) = &medium.emission else {
        anyhow::bail!(
            "emission: the scene's medium has no emission (Scene.from_parts(emission=array) makes one)"
        );
    };
    emission_grid(values, place, own.transform, own.kind.clone(), own.filter)
}
