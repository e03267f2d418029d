//! Reading and writing float grids through the OpenVDB bridge, as brick maps; and what a grid must
//! be to serve as a density (`read_density`).

use std::path::Path;

use anyhow::{anyhow, bail, Result};
use glam::IVec3;
use rayon::prelude::*;

use crate::io::bridge::ffi;
use crate::io::bridge::{FloatGridData, GridSummary, MetaEntry};
use crate::volume::brickmap::{BrickMap, Leaf, Tile, BRICK_VOXELS};
use crate::volume::transform::IndexTransform;

/// Which grid of a file to read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum GridSelector {
    Name(String),
    /// Position in file order (names may repeat).
    Index(usize),
    /// "density" if there is one, else the file's only grid.
    Default,
}

/// What to do with a grid of class "level set" read as a density.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LevelSet {
    /// Refuse it: its values are signed distances, not densities.
    #[default]
    Refuse,
    /// Convert it with OpenVDB's `tools::sdfToFogVolume`: 0 outside, a 0 → 1 ramp across the
    /// interior half of the narrow band, 1 inside.
    Fog,
}

/// A float grid in memory.
pub struct Grid {
    pub name: String,
    pub grid_class: String,
    pub transform: IndexTransform,
    pub bricks: BrickMap,
    /// OpenVDB's value outside every leaf and tile. The brick map reads 0 there, so only a grid
    /// with background 0 is read as a density (`read_density`); the rest keep it to write it back.
    pub background: f32,
    pub saved_as_half: bool,
    pub metadata: Vec<MetaEntry>,
}

fn path_str(path: &Path) -> Result<&str> {
    path.to_str()
        .ok_or_else(|| anyhow!("path '{}' is not valid UTF-8", path.display()))
}

pub fn list_grids(path: &Path) -> Result<Vec<GridSummary>> {
    ffi::list_grids(path_str(path)?).map_err(|e| anyhow!("{}", e.what()))
}

/// Reads a float grid as it is stored (any class, any background).
pub fn read_grid(path: &Path, selector: &GridSelector) -> Result<Grid> {
    let data = read_data(path, selector, false)?;
    Grid::from_data(data).map_err(|e| anyhow!("grid in '{}': {e}", path.display()))
}

/// Reads a float grid to render as a density: a level set is converted or refused (`level_set`),
/// a non-zero background refused, and so are inactive tiles of another value. OpenVDB's
/// background is the value of all space outside the tree, so a non-zero one would be an infinite
/// medium, while volgrad's medium ends at the active voxels' bounds and reads 0 wherever there is
/// no leaf or active tile.
pub fn read_density(path: &Path, selector: &GridSelector, level_set: LevelSet) -> Result<Grid> {
    let data = read_data(path, selector, level_set == LevelSet::Fog)?;
    let what = format!("grid '{}' in '{}'", data.name, path.display());
    if data.grid_class == "level set" {
        bail!(
            "{what} is a level set (signed distances, not densities): set medium.levelset = \"fog\" to convert it with OpenVDB's sdfToFogVolume, or give a fog volume"
        );
    }
    if data.background != 0.0 {
        bail!(
            "{what} has background {} (the value of all space outside its voxels): volgrad renders densities that are 0 outside the grid; rewrite it with background 0",
            data.background
        );
    }
    if data.inactive_tiles_off_background > 0 {
        bail!(
            "{what} has {} inactive tiles whose value is not its background 0: OpenVDB reads their value there, volgrad reads 0; activate them or set them to 0",
            data.inactive_tiles_off_background
        );
    }
    Grid::from_data(data).map_err(|e| anyhow!("{what}: {e}"))
}

fn read_data(path: &Path, selector: &GridSelector, to_fog: bool) -> Result<FloatGridData> {
    let p = path_str(path)?;
    // The bridge copies leaves on as many threads as the renderer uses (`--threads`).
    let threads = u32::try_from(rayon::current_num_threads()).unwrap_or(u32::MAX);
    match selector {
        GridSelector::Name(name) => ffi::read_float_grid(p, name, -1, to_fog, threads),
        GridSelector::Index(i) => match i32::try_from(*i) {
            Ok(i) => ffi::read_float_grid(p, "", i, to_fog, threads),
            Err(_) => bail!("grid index {i} out of range for '{}'", path.display()),
        },
        GridSelector::Default => {
            let grids = list_grids(path)?;
            match grids.iter().position(|g| g.name == "density") {
                Some(i) => ffi::read_float_grid(p, "", i as i32, to_fog, threads),
                None if grids.is_empty() => bail!("'{}' holds no grids", path.display()),
                None if grids.len() == 1 => ffi::read_float_grid(p, "", 0, to_fog, threads),
                None => {
                    let names: Vec<_> = grids.iter().map(|g| g.name.as_str()).collect();
                    bail!(
                        "'{}' has no grid named \"density\" and {} grids ({}): choose one with medium.grid or medium.grid_index",
                        path.display(),
                        grids.len(),
                        names.join(", ")
                    )
                }
            }
        }
    }
    .map_err(|e| anyhow!("{}", e.what()))
}

/// Writes grids to `path`. Refuses to replace an existing file unless `overwrite`.
pub fn write_grids(path: &Path, grids: &[&Grid], save_half: bool, overwrite: bool) -> Result<()> {
    crate::io::output::refuse_overwrite(path, overwrite)?;
    let data: Vec<FloatGridData> = grids.iter().map(|g| g.to_data()).collect();
    ffi::write_float_grids(path_str(path)?, &data, save_half).map_err(|e| anyhow!("{}", e.what()))
}

/// As `write_grids` for one grid that the caller no longer needs: it is freed once its values are
/// in the bridge's arrays, so that a large grid is held twice while OpenVDB builds its tree, not
/// three times.
pub fn write_grid_consumed(
    path: &Path,
    grid: Grid,
    save_half: bool,
    overwrite: bool,
) -> Result<()> {
    crate::io::output::refuse_overwrite(path, overwrite)?;
    let data = grid.to_data();
    drop(grid);
    ffi::write_float_grids(path_str(path)?, &[data], save_half).map_err(|e| anyhow!("{}", e.what()))
}

impl Grid {
    pub fn from_data(d: FloatGridData) -> Result<Grid> {
        let n = d.leaf_origins.len() / 3;
        if d.leaf_values.len() != n * BRICK_VOXELS || d.leaf_active.len() != n * 8 {
            bail!("inconsistent leaf arrays from the bridge");
        }
        // In parallel: at 100 MiB of leaves each pass over the values is a noticeable part of the
        // load. The check is a pass of its own, so that the copy is an indexed collect, written
        // straight into the leaves' vector.
        let finite = |values: &[f32]| values.iter().fold(true, |ok, v| ok & v.is_finite());
        if !d.leaf_values.par_chunks(1 << 16).all(finite) || !finite(&d.tile_values) {
            bail!("grid '{}' holds NaN or infinite values", d.name);
        }
        // The lengths were checked above, so every chunk has exactly a leaf's worth.
        let leaves: Vec<Leaf> = d
            .leaf_origins
            .par_chunks_exact(3)
            .zip(d.leaf_values.par_chunks_exact(BRICK_VOXELS))
            .zip(d.leaf_active.par_chunks_exact(8))
            .map(|((origin, values), active)| Leaf {
                origin: IVec3::from_slice(origin),
                values: values.try_into().expect("chunks_exact gives whole leaves"),
                active: active.try_into().expect("chunks_exact gives whole masks"),
            })
            .collect();
        let tiles = (0..d.tile_values.len())
            .map(|i| Tile {
                origin: IVec3::from_slice(&d.tile_origins[3 * i..3 * i + 3]),
                size: d.tile_sizes[i],
                value: d.tile_values[i],
            })
            .collect();
        Ok(Grid {
            transform: IndexTransform::from_rows(&d.index_to_world)?,
            bricks: BrickMap::new(leaves, tiles),
            name: d.name,
            grid_class: d.grid_class,
            background: d.background,
            saved_as_half: d.saved_as_half,
            metadata: d.metadata,
        })
    }

    pub fn to_data(&self) -> FloatGridData {
        let leaves = self.bricks.leaves();
        let tiles = self.bricks.tiles();
        // Sized up front: a grown vector of a large grid's values would hold up to twice them.
        let mut leaf_values = Vec::with_capacity(leaves.len() * BRICK_VOXELS);
        let mut leaf_active = Vec::with_capacity(leaves.len() * 8);
        for leaf in leaves {
            leaf_values.extend_from_slice(&leaf.values);
            leaf_active.extend_from_slice(&leaf.active);
        }
        FloatGridData {
            name: self.name.clone(),
            grid_class: self.grid_class.clone(),
            index_to_world: self.transform.to_rows(),
            background: self.background,
            saved_as_half: self.saved_as_half,
            leaf_origins: leaves.iter().flat_map(|l| l.origin.to_array()).collect(),
            leaf_values,
            leaf_active,
            tile_origins: tiles.iter().flat_map(|t| t.origin.to_array()).collect(),
            tile_sizes: tiles.iter().map(|t| t.size).collect(),
            tile_values: tiles.iter().map(|t| t.value).collect(),
            inactive_tiles_off_background: 0,
            metadata: self.metadata.clone(),
        }
    }
}

pub fn meta(name: &str, type_name: &str, value: impl ToString) -> MetaEntry {
    MetaEntry {
        name: name.into(),
        type_name: type_name.into(),
        value: value.to_string(),
    }
}
