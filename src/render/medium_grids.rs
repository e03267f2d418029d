//! The medium's grids besides density, read from their files and checked: an albedo grid (RGB or
//! grey, values in [0, 1]) and an emission grid (temperature or radiance scale). Each comes from
//! the medium's file or its own, with its own transform, into brick maps of its own.

use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::{IVec3, Vec3};

use crate::io::vdb::{self, GridSelector};
use crate::render::scene_check::MAX_LIGHT;
use crate::render::scene_file::{AlbedoFile, EmissionFile};
use crate::volume::albedo::{Albedo, AlbedoGrid};
use crate::volume::brickmap::{BrickMap, Leaf, Tile};
use crate::volume::emission::{Emission, EmissionKind};
use crate::volume::medium::Filter;

/// The file the grid key `key` names: its own `vdb`, relative to the scene file's folder `dir`,
/// or the medium's.
fn grid_file(
    key: &str,
    own: &Option<String>,
    dir: &Path,
    medium_vdb: Option<&Path>,
) -> Result<std::path::PathBuf> {
    match (own, medium_vdb) {
        (Some(v), _) => Ok(dir.join(v)),
        (None, Some(medium)) => Ok(medium.to_path_buf()),
        (None, None) => bail!(
            "medium.{key}: the scene names no medium.vdb, so its grid needs a file of its own (`vdb = …`)"
        ),
    }
}

/// The albedo `file` gives: a constant, or the grid it names (three channels for a vec3 grid,
/// one for a float grid), every value and the background checked to lie in [0, 1].
pub fn load_albedo(
    file: &AlbedoFile,
    dir: &Path,
    medium_vdb: Option<&Path>,
    filter: Filter,
) -> Result<Albedo> {
    let (name, own_vdb) = match file {
        AlbedoFile::Constant(albedo) => return Ok(Albedo::Constant(albedo.rgb())),
        AlbedoFile::Grid { grid, vdb } => (grid, vdb),
    };
    let path = grid_file("albedo", own_vdb, dir, medium_vdb)?;
    let context = || format!("medium.albedo.grid '{name}' (a float or vec3 grid)");
    let components = vdb::read_components(&path, name).with_context(context)?;
    let what = format!("medium.albedo: grid '{name}' in '{}'", path.display());
    let channel_name = |c: usize| match components.len() {
        1 => String::new(),
        _ => format!(" ({})", ["red", "green", "blue"][c]),
    };
    let mut background = Vec3::ZERO;
    let mut channels = Vec::with_capacity(components.len());
    for (c, grid) in components.iter().enumerate() {
        if grid.grid_class == "level set" {
            bail!("{what} is a level set, not an albedo");
        }
        if let Some((voxel, value)) = outside_unit_interval(&grid.bricks) {
            bail!(
                "{what} has value {value} at voxel ({}, {}, {}){}: an albedo must lie in [0, 1]",
                voxel.x,
                voxel.y,
                voxel.z,
                channel_name(c)
            );
        }
        if !(0.0..=1.0).contains(&grid.background) {
            bail!(
                "{what} has background {}{} (its value outside its voxels): an albedo must lie in [0, 1]",
                grid.background,
                channel_name(c)
            );
        }
        background[c] = grid.background;
        channels.push(shifted(&grid.bricks, grid.background));
    }
    if channels.len() == 1 {
        background = Vec3::splat(background.x);
    }
    let first = &components[0];
    Ok(Albedo::Grid(Box::new(AlbedoGrid::new(
        first.name.clone(),
        channels,
        background,
        first.transform,
        filter,
    ))))
}

/// The first stored value outside [0, 1] (every value a lookup can read: a leaf's inactive
/// voxels too), with its voxel (a tile's first).
fn outside_unit_interval(map: &BrickMap) -> Option<(IVec3, f32)> {
    let bad = |v: f32| !(0.0..=1.0).contains(&v);
    for leaf in map.leaves() {
        if let Some(i) = leaf.values.iter().position(|&v| bad(v)) {
            let local = IVec3::new((i >> 6) as i32, ((i >> 3) & 7) as i32, (i & 7) as i32);
            return Some((leaf.origin + local, leaf.values[i]));
        }
    }
    (map.tiles().iter())
        .find(|t| bad(t.value))
        .map(|t| (t.origin, t.value))
}

/// `map` holding value − `background` (see `AlbedoGrid`).
fn shifted(map: &BrickMap, background: f32) -> BrickMap {
    if background == 0.0 {
        return map.clone();
    }
    let leaves = (map.leaves().iter())
        .map(|leaf| Leaf {
            origin: leaf.origin,
            values: leaf.values.map(|v| v - background),
            active: leaf.active,
        })
        .collect();
    let tiles = (map.tiles().iter())
        .map(|t| Tile {
            value: t.value - background,
            ..*t
        })
        .collect();
    BrickMap::new(leaves, tiles)
}

/// The emission grid `file` names, from its own file or the medium's (`medium_vdb`). Its
/// background must be 0, as a density's: the brick map reads 0 outside its voxels, as the
/// density's does, and a background honoured would be emission from all space outside them
/// (where the density is, too). Its largest possible radiance must be within the light cap.
pub fn load_emission(
    file: &EmissionFile,
    dir: &Path,
    medium_vdb: Option<&Path>,
    filter: Filter,
) -> Result<Emission> {
    let kind = file.emission_kind()?;
    let path = grid_file("emission", &file.vdb, dir, medium_vdb)?;
    let grid = vdb::read_zero_outside(
        &path,
        &GridSelector::Name(file.grid.clone()),
        "emission grids",
    )
    .with_context(|| format!("medium.emission.grid '{}'", file.grid))?;
    if matches!(kind, EmissionKind::Radiance(_)) && grid.bricks.min_value() < 0.0 {
        bail!(
            "medium.emission: grid '{}' in '{}' has negative values (min {}), and radiance = [r, g, b] × the grid's value must be ≥ 0",
            grid.name,
            path.display(),
            grid.bricks.min_value()
        );
    }
    let what = format!(
        "medium.emission: grid '{}' in '{}'",
        grid.name,
        path.display()
    );
    let emission = Emission::new(grid.name, grid.bricks, grid.transform, kind, filter);
    check_emission_limit(&emission, &what)?;
    Ok(emission)
}

/// Refuses an emission whose largest possible radiance exceeds the light cap; `what` names it.
pub fn check_emission_limit(emission: &Emission, what: &str) -> Result<()> {
    let (largest, kelvin) = emission.largest_radiance();
    if largest > f64::from(MAX_LIGHT) {
        let how = match emission.kind {
            EmissionKind::Radiance(_) => {
                format!("radiance × its largest value {}", emission.grid.max_value())
            }
            EmissionKind::Blackbody { .. } => {
                format!("strength × the blackbody up to its hottest voxel's {kelvin:.0} K")
            }
        };
        bail!(
            "{what} emits up to {largest:.3e} ({how}); at most {MAX_LIGHT:e}: lower medium.emission.{}",
            match emission.kind {
                EmissionKind::Radiance(_) => "radiance",
                EmissionKind::Blackbody { .. } => "strength",
            }
        );
    }
    Ok(())
}
