//! Reading and writing float grids through the OpenVDB bridge, as brick maps; and what a grid must
//! be to serve as a density (`read_density`).

use std::path::Path;

use anyhow::{anyhow, bail, Result};
use glam::IVec3;
use rayon::prelude::*;

use crate::io::bridge::{bridge_error, bridge_path, check_grid_name, ffi};
use crate::io::bridge::{FloatGridData, GridSummary, LeafData, MetaEntry};
use crate::io::images::HALF_MAX;
use crate::volume::brickmap::{BrickMap, Leaf, Tile};
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

pub fn list_grids(path: &Path) -> Result<Vec<GridSummary>> {
    ffi::list_grids(bridge_path(path)?).map_err(bridge_error)
}

/// The names of the grids in the file, in file order, without reading the grids.
pub fn list_grid_names(path: &Path) -> Result<Vec<String>> {
    ffi::list_grid_names(bridge_path(path)?).map_err(bridge_error)
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
    zero_outside(&what, "densities", &data)?;
    Grid::from_data(data).map_err(|e| anyhow!("{what}: {e}"))
}

/// Reads a float grid that, as a density, must be 0 outside its voxels (an emission grid): a
/// non-zero background and inactive tiles of another value are refused (`read_density` says
/// why); any class.
pub fn read_zero_outside(path: &Path, selector: &GridSelector, values: &str) -> Result<Grid> {
    let data = read_data(path, selector, false)?;
    let what = format!("grid '{}' in '{}'", data.name, path.display());
    zero_outside(&what, values, &data)?;
    Grid::from_data(data).map_err(|e| anyhow!("{what}: {e}"))
}

/// Refuses a grid (`what`, holding `values`) whose value outside its voxels is not 0: the brick
/// map reads 0 wherever there is no leaf or active tile.
fn zero_outside(what: &str, values: &str, data: &FloatGridData) -> Result<()> {
    if data.background != 0.0 {
        bail!(
            "{what} has background {} (the value of all space outside its voxels): volgrad renders {values} that are 0 outside the grid; rewrite it with background 0",
            data.background
        );
    }
    if data.inactive_tiles_off_background > 0 {
        bail!(
            "{what} has {} inactive tiles whose value is not its background 0: OpenVDB reads their value there, volgrad reads 0; activate them or set them to 0",
            data.inactive_tiles_off_background
        );
    }
    Ok(())
}

/// The threads the bridge copies leaves on: as many as the renderer uses (`--threads`), but no
/// more than the machine has (TBB warns on stderr beyond them, and they would only wait).
fn bridge_threads() -> u32 {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    u32::try_from(rayon::current_num_threads().min(cores)).unwrap_or(u32::MAX)
}

/// A name that several grids of the file share picks none of them: which one was meant is the
/// user's to say, by position (`volgrad info` numbers the grids).
/// An error if several grids of `path` are named `name`; `density` says whether the one wanted
/// is the density, which medium.grid_index can choose by its position.
fn refuse_repeated_name(path: &Path, grids: &[String], name: &str, density: bool) -> Result<()> {
    let at: Vec<usize> = (0..grids.len()).filter(|&i| grids[i] == name).collect();
    if at.len() > 1 {
        let choose = match density {
            true => "choose the density by its position (medium.grid_index), or give the grids names of their own",
            false => "give the grids names of their own",
        };
        bail!(
            "'{}' holds {} grids named '{name}' (positions {at:?} in `volgrad info`): {choose}",
            path.display(),
            at.len()
        );
    }
    Ok(())
}

fn read_data(path: &Path, selector: &GridSelector, to_fog: bool) -> Result<FloatGridData> {
    let p = bridge_path(path)?;
    let threads = bridge_threads();
    match selector {
        GridSelector::Name(name) => {
            refuse_repeated_name(path, &list_grid_names(path)?, name, true)?;
            ffi::read_float_grid(p, name, -1, to_fog, threads)
        }
        GridSelector::Index(i) => match i32::try_from(*i) {
            Ok(i) => ffi::read_float_grid(p, "", i, to_fog, threads),
            Err(_) => bail!("grid index {i} out of range for '{}'", path.display()),
        },
        GridSelector::Default => {
            let grids = list_grid_names(path)?;
            match grids.iter().position(|name| name == "density") {
                Some(i) => {
                    refuse_repeated_name(path, &grids, "density", true)?;
                    ffi::read_float_grid(p, "", i as i32, to_fog, threads)
                }
                None if grids.is_empty() => bail!("'{}' holds no grids", path.display()),
                None if grids.len() == 1 => ffi::read_float_grid(p, "", 0, to_fog, threads),
                None => {
                    bail!(
                        "'{}' has no grid named \"density\" and {} grids ({}): choose one with medium.grid or medium.grid_index",
                        path.display(),
                        grids.len(),
                        grids.join(", ")
                    )
                }
            }
        }
    }
    .map_err(bridge_error)
}

/// Reads the grid named `name` as float components: one for a float grid, three (x, y, z) for a
/// vec3 grid, each as it is stored (any background). A name several grids share is refused, as
/// for the density, rather than the first taken; so are inactive tiles of a value other than
/// the background, which OpenVDB reads as their value and the brick map (holding leaves and
/// active tiles) as the background.
pub fn read_components(path: &Path, name: &str) -> Result<Vec<Grid>> {
    refuse_repeated_name(path, &list_grid_names(path)?, name, false)?;
    let threads = bridge_threads();
    let data =
        ffi::read_grid_components(bridge_path(path)?, name, -1, threads).map_err(bridge_error)?;
    if let Some(d) = data.iter().find(|d| d.inactive_tiles_off_background > 0) {
        let background: Vec<String> = data.iter().map(|d| d.background.to_string()).collect();
        bail!(
            "grid '{name}' in '{}' has {} inactive tiles whose value is not its background {}: OpenVDB reads their value there, volgrad reads the background; activate them or set them to the background",
            path.display(),
            d.inactive_tiles_off_background,
            match background.len() {
                1 => background[0].clone(),
                _ => format!("({})", background.join(", ")),
            }
        );
    }
    data.into_iter()
        .map(|d| Grid::from_data(d).map_err(|e| anyhow!("grid in '{}': {e}", path.display())))
        .collect()
}

/// Writes float grids and vec3 grids (colours, each made of three float components, with the
/// first's name and transform) to `path`, as half floats with `save_half`. Refuses to replace an
/// existing file unless `overwrite`.
pub fn write_grids_with_colours(
    path: &Path,
    grids: &[&Grid],
    colours: &[[&Grid; 3]],
    save_half: bool,
    overwrite: bool,
) -> Result<()> {
    check_write(
        path,
        &[grids, &colours.concat()].concat(),
        save_half,
        overwrite,
    )?;
    let data: Vec<FloatGridData> = grids.iter().map(|g| g.to_data()).collect();
    let colours: Vec<FloatGridData> = colours.iter().flatten().map(|g| g.to_data()).collect();
    ffi::write_grids_with_colours(bridge_path(path)?, &data, &colours, save_half)
        .map_err(bridge_error)
}

/// What every write checks before it begins: the file's name and whether it may be replaced, the
/// grids' names, and their values against half floats' range when saved as halves.
fn check_write(path: &Path, grids: &[&Grid], save_half: bool, overwrite: bool) -> Result<()> {
    check_vdb_name(path)?;
    crate::io::output::refuse_overwrite(path, overwrite)?;
    for g in grids {
        check_grid_name(&g.name)?;
    }
    check_half(grids, save_half)
}

/// Refuses a name that does not end in `.vdb`: every reader of the file (Blender, Houdini,
/// volgrad) goes by it.
fn check_vdb_name(path: &Path) -> Result<()> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    if !ext.eq_ignore_ascii_case("vdb") {
        bail!("'{}': a VDB file's name ends in .vdb", path.display());
    }
    Ok(())
}

/// Refuses grids stored as half floats whose values a half cannot hold (they would be read back
/// as infinite, and refused).
fn check_half(grids: &[&Grid], save_half: bool) -> Result<()> {
    if !save_half {
        return Ok(());
    }
    for g in grids {
        let largest = g.bricks.max_value().max(-g.bricks.min_value());
        if largest > HALF_MAX {
            bail!(
                "grid '{}' holds values up to {largest:e} in magnitude, beyond half floats' largest ({HALF_MAX}): store it as float",
                g.name
            );
        }
    }
    Ok(())
}

/// Writes grids to `path`. Refuses to replace an existing file unless `overwrite`.
pub fn write_grids(path: &Path, grids: &[&Grid], save_half: bool, overwrite: bool) -> Result<()> {
    check_write(path, grids, save_half, overwrite)?;
    let data: Vec<FloatGridData> = grids.iter().map(|g| g.to_data()).collect();
    ffi::write_float_grids(bridge_path(path)?, &data, save_half).map_err(bridge_error)
}

/// As `write_grids` for one grid that the caller no longer needs: its leaves become the bridge's
/// without a copy, so that a large grid is held twice while OpenVDB builds its tree, not three
/// times.
pub fn write_grid_consumed(
    path: &Path,
    grid: Grid,
    save_half: bool,
    overwrite: bool,
) -> Result<()> {
    check_write(path, &[&grid], save_half, overwrite)?;
    let data = grid.into_data();
    ffi::write_float_grids(bridge_path(path)?, &[data], save_half).map_err(bridge_error)
}

impl Grid {
    pub fn from_data(d: FloatGridData) -> Result<Grid> {
        // In parallel: at 100 MiB of leaves each pass over the values is a noticeable part of the
        // load.
        let finite = |values: &[f32]| values.iter().fold(true, |ok, v| ok & v.is_finite());
        if !d.leaves.par_iter().all(|leaf| finite(&leaf.values)) || !finite(&d.tile_values) {
            // A double grid's finite values beyond f32's range (about 3.4e38) arrive infinite too.
            bail!(
                "grid '{}' holds NaN or infinite values (or, stored as double, values beyond a 32-bit float's range, about 3.4e38)",
                d.name
            );
        }
        let tiles = (0..d.tile_values.len())
            .map(|i| Tile {
                origin: IVec3::from_slice(&d.tile_origins[3 * i..3 * i + 3]),
                size: d.tile_sizes[i],
                value: d.tile_values[i],
            })
            .collect();
        Ok(Grid {
            transform: IndexTransform::from_rows(&d.index_to_world)?,
            bricks: BrickMap::new(into_leaves(d.leaves), tiles),
            name: d.name,
            grid_class: d.grid_class,
            background: d.background,
            saved_as_half: d.saved_as_half,
            metadata: d.metadata,
        })
    }

    pub fn to_data(&self) -> FloatGridData {
        let leaves = (self.bricks.leaves().iter())
            .map(|leaf| LeafData {
                origin: leaf.origin.to_array(),
                values: leaf.values,
                active: leaf.active,
            })
            .collect();
        self.data_with(leaves)
    }

    /// As `to_data`, handing the leaves over instead of copying them.
    pub fn into_data(self) -> FloatGridData {
        let mut data = self.data_with(Vec::new());
        data.leaves = from_leaves(self.bricks.into_leaves());
        data
    }

    fn data_with(&self, leaves: Vec<LeafData>) -> FloatGridData {
        let tiles = self.bricks.tiles();
        FloatGridData {
            name: self.name.clone(),
            grid_class: self.grid_class.clone(),
            index_to_world: self.transform.to_rows(),
            background: self.background,
            saved_as_half: self.saved_as_half,
            leaves,
            tile_origins: tiles.iter().flat_map(|t| t.origin.to_array()).collect(),
            tile_sizes: tiles.iter().map(|t| t.size).collect(),
            tile_values: tiles.iter().map(|t| t.value).collect(),
            inactive_tiles_off_background: 0,
            metadata: self.metadata.clone(),
        }
    }
}

// The bridge's leaves and the brick map's are the same bytes: an origin of three i32, 512 f32 and
// 8 u64, in that order, `repr(C)` both.
const _: () = {
    use std::mem::{align_of, offset_of, size_of};
    assert!(size_of::<LeafData>() == size_of::<Leaf>());
    assert!(align_of::<LeafData>() == align_of::<Leaf>());
    assert!(offset_of!(LeafData, origin) == offset_of!(Leaf, origin));
    assert!(offset_of!(LeafData, values) == offset_of!(Leaf, values));
    assert!(offset_of!(LeafData, active) == offset_of!(Leaf, active));
};

/// The leaves the bridge read, as the brick map's, without copying them (100 MiB for a large
/// grid: a copy was a sixth of its load).
fn into_leaves(leaves: Vec<LeafData>) -> Vec<Leaf> {
    // SAFETY: the two leaf types, whose layouts are checked above.
    unsafe { relabel(leaves) }
}

/// A brick map's leaves as the bridge's, without copying them.
fn from_leaves(leaves: Vec<Leaf>) -> Vec<LeafData> {
    // SAFETY: the two leaf types, whose layouts are checked above.
    unsafe { relabel(leaves) }
}

/// `v` as a vector of `B`, the same allocation.
///
/// SAFETY: `A` and `B` must have the same size, alignment and field offsets, with fields of the
/// same types (IVec3 is three i32, `repr(C)`), so that every `A` is a valid `B`: `Leaf` and
/// `LeafData`, either way round. The allocation then changes owner whole, with the layout it was
/// made with.
unsafe fn relabel<A, B>(v: Vec<A>) -> Vec<B> {
    debug_assert!(std::mem::size_of::<A>() == std::mem::size_of::<B>());
    let mut v = std::mem::ManuallyDrop::new(v);
    Vec::from_raw_parts(v.as_mut_ptr().cast::<B>(), v.len(), v.capacity())
}

pub fn meta(name: &str, type_name: &str, value: impl ToString) -> MetaEntry {
    MetaEntry {
        name: name.into(),
        type_name: type_name.into(),
        value: value.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_grid_handed_to_the_bridge_equals_its_copy_and_comes_back_whole() {
        let make = || Grid {
            name: "density".into(),
            grid_class: "fog volume".into(),
            transform: IndexTransform::from_rows(&[
                0.5, 0.0, 0.0, 1.0, 0.0, 0.5, 0.0, 2.0, 0.0, 0.0, 0.5, 3.0, 0.0, 0.0, 0.0, 1.0,
            ])
            .unwrap(),
            bricks: BrickMap::block(19, |v| (v.x + 19 * v.y + 361 * v.z) as f32 / 7000.0),
            background: 0.0,
            saved_as_half: false,
            metadata: vec![meta("author", "string", "test")],
        };
        let grid = make();
        let copied = grid.to_data();
        let handed = make().into_data();
        assert_eq!(handed.leaves.len(), 27);
        assert!(handed.leaves == copied.leaves);
        assert_eq!(
            (
                &handed.tile_origins,
                &handed.tile_sizes,
                &handed.tile_values
            ),
            (
                &copied.tile_origins,
                &copied.tile_sizes,
                &copied.tile_values
            )
        );
        assert_eq!(handed.metadata, copied.metadata);
        // And back: the bridge's leaves become the brick map's as they are.
        let back = Grid::from_data(copied).unwrap();
        for v in [IVec3::ZERO, IVec3::new(18, 3, 11), IVec3::new(7, 8, 9)] {
            assert_eq!(back.bricks.voxel(v), grid.bricks.voxel(v));
            assert!(back.bricks.is_active(v));
        }
        assert_eq!(back.bricks.active_bounds(), grid.bricks.active_bounds());
    }
}
