//! The coarse majorant grid of a medium: its settings, its cells' layout and bounds as the walk
//! and the hot spots read them, and the hot spots it holds.
//!
//! Cell `c` of a grid with cell edge `S` voxels covers the continuous index range
//! `[c·S − ½, c·S + S − ½)`; its majorant bounds every lookup in it (`majorant_cells` builds the
//! bounds). `--majorant global` is one cell that spans the whole medium. The walk over the cells,
//! a two-level DDA, is `majorant_walk`, above this module.

use glam::{IVec3, Vec3};

use crate::volume::brickmap::BrickMap;
use crate::volume::hot_spots::{HotSpots, MajorantCells};
use crate::volume::majorant_cells::{
    cell_offset, flat_cell_budget, Block, Builder, FlatCells, BLOCK_CELLS, BLOCK_EDGE, BLOCK_LOG2,
};
use crate::volume::sparse_index::SparseIndex;

#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    clap::ValueEnum,
    serde::Deserialize,
    serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum MajorantMode {
    /// One majorant per coarse cell of the grid (fast; the default).
    #[default]
    Grid,
    /// One majorant for the whole medium (the baseline for speed comparisons).
    Global,
}

crate::display_as_value_enum!(MajorantMode);

/// How a medium is tracked: the majorant mode and, for the grid, its cell edge in voxels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Majorant {
    pub mode: MajorantMode,
    pub cell_voxels: u32,
}

impl Majorant {
    pub const fn grid(cell_voxels: u32) -> Self {
        Majorant {
            mode: MajorantMode::Grid,
            cell_voxels,
        }
    }

    pub const fn global() -> Self {
        Majorant {
            mode: MajorantMode::Global,
            cell_voxels: 0,
        }
    }
}

#[derive(Clone)]
pub struct MajorantGrid {
    /// Index-space corner of cell (0, 0, 0) and the cell edges: cell c spans
    /// `origin + c·cell_size .. origin + (c + 1)·cell_size`. The global mode is one flat cell over
    /// the medium's box.
    pub(super) origin: Vec3,
    pub(super) cell_size: Vec3,
    pub(super) inv_cell_size: Vec3,
    /// Cells of the medium's box (inclusive); a walk that starts on its faces starts inside.
    pub(super) c_lo: IVec3,
    pub(super) c_hi: IVec3,
    /// Flat mode: one majorant per cell, x-major, walked by a single-level DDA, in one box over
    /// `c_lo ..= c_hi` (a compact medium) or in a box per cluster of the data (a wide medium whose
    /// data lie in a few clusters; the walk jumps between them). Empty in block mode.
    pub(super) flat: Vec<FlatCells>,
    /// Block mode: block coordinates → index + 1 into `blocks`.
    pub(super) index: SparseIndex,
    pub(super) blocks: Vec<Block>,
    /// Whether walks refine loose cells along the ray (`volume::refine`): the grid mode does; the
    /// global mode is the plain one-majorant baseline that speed comparisons measure against.
    pub refine: bool,
    /// Cell edge in voxels (0 in the global mode).
    pub(super) cell_voxels: i32,
    /// Cells whose few hot voxels make their majorant loose (see `with_hot_spots`).
    pub(super) hot_spots: HotSpots,
}

impl MajorantGrid {
    /// `bounds` is the medium's continuous index box; values are multiplied by `density_scale`.
    pub fn build(
        bricks: &BrickMap,
        bounds: (Vec3, Vec3),
        density_scale: f32,
        majorant: Majorant,
    ) -> Self {
        match majorant.mode {
            MajorantMode::Global => MajorantGrid {
                origin: bounds.0,
                cell_size: (bounds.1 - bounds.0).max(Vec3::splat(1e-6)),
                inv_cell_size: (bounds.1 - bounds.0).max(Vec3::splat(1e-6)).recip(),
                c_lo: IVec3::ZERO,
                c_hi: IVec3::ZERO,
                flat: vec![FlatCells {
                    lo: IVec3::ZERO,
                    hi: IVec3::ZERO,
                    cells: vec![bricks.max_value().max(0.0) * density_scale],
                }],
                index: SparseIndex::new(IVec3::ZERO, IVec3::splat(-1)),
                blocks: Vec::new(),
                refine: true,
                cell_voxels: 0,
                hot_spots: HotSpots::default(),
            },
            MajorantMode::Grid => Self::build_cells(
                bricks,
                bounds,
                density_scale,
                majorant.cell_voxels.clamp(1, 1 << 20) as i32,
                flat_cell_budget(bricks),
            ),
        }
    }

    /// The grid mode's grid, cells of `s` voxels: flat when the box (or the boxes of the data's
    /// clusters) has at most `flat_budget` cells, in blocks otherwise (the tests pick the layout
    /// this way).
    pub(super) fn build_cells(
        bricks: &BrickMap,
        bounds: (Vec3, Vec3),
        density_scale: f32,
        s: i32,
        flat_budget: u64,
    ) -> Self {
        let cells = Builder::build(bricks, bounds, density_scale, s, flat_budget);
        MajorantGrid {
            // Cell c covers voxels c·S ..= c·S + S − 1: it starts half a voxel below c·S.
            origin: Vec3::splat(-0.5),
            cell_size: Vec3::splat(s as f32),
            inv_cell_size: Vec3::splat(1.0 / s as f32),
            c_lo: cells.c_lo,
            c_hi: cells.c_hi,
            flat: cells.flats,
            index: cells.index,
            blocks: cells.blocks,
            refine: true,
            cell_voxels: s,
            hot_spots: HotSpots::default(),
        }
    }

    /// This majorant with the hot spots of `bricks` (the grid it was built from) found, for a
    /// medium in which no segment inside a voxel is longer than `voxel_diagonal` (world units):
    /// walks then split a hot cell's stretch at the reach of its hot voxels
    /// (`volume::hot_spots`).
    pub fn with_hot_spots(mut self, bricks: &BrickMap, voxel_diagonal: f32) -> Self {
        self.hot_spots = HotSpots::find(bricks, &self, voxel_diagonal);
        self
    }

    /// Cells with hot spots.
    pub fn hot_spot_count(&self) -> usize {
        self.hot_spots.len()
    }

    /// Cells with their own majorant (constant blocks count as one cell).
    pub fn cell_count(&self) -> usize {
        if !self.flat.is_empty() {
            return self.flat.iter().map(|f| f.cells.len()).sum();
        }
        self.blocks
            .iter()
            .map(|b| if b.cells.is_some() { BLOCK_CELLS } else { 1 })
            .sum()
    }

    /// The flat boxes the cells are in: one over the medium, one per cluster of its data, or
    /// none (blocks).
    pub fn flat_boxes(&self) -> usize {
        self.flat.len()
    }

    pub fn memory_bytes(&self) -> usize {
        let cells: usize = self.blocks.iter().filter(|b| b.cells.is_some()).count()
            * std::mem::size_of::<[f32; BLOCK_CELLS]>();
        cells
            + self.flat.iter().map(|f| f.cells.len()).sum::<usize>() * std::mem::size_of::<f32>()
            + self.blocks.len() * std::mem::size_of::<Block>()
            + self.index.memory_bytes()
            + self.hot_spots.memory_bytes()
            + std::mem::size_of::<Self>()
    }
}

impl MajorantCells for MajorantGrid {
    fn cell_geometry(&self) -> (Vec3, Vec3) {
        (self.origin, self.inv_cell_size)
    }

    fn cell_voxels(&self) -> Option<i32> {
        (self.cell_voxels > 0).then_some(self.cell_voxels)
    }

    fn cell_range(&self) -> (IVec3, IVec3) {
        (self.c_lo, self.c_hi)
    }

    fn cell_majorant(&self, c: IVec3) -> f32 {
        if c.cmplt(self.c_lo).any() || c.cmpgt(self.c_hi).any() {
            return 0.0;
        }
        if !self.flat.is_empty() {
            return self.flat.iter().find_map(|f| f.get(c)).unwrap_or(0.0);
        }
        match self.index.get(c >> BLOCK_LOG2) {
            0 => 0.0,
            handle => {
                let block = &self.blocks[handle as usize - 1];
                match &block.cells {
                    None => block.floor,
                    Some(cells) => {
                        cells[cell_offset(c & (BLOCK_EDGE - 1), IVec3::splat(BLOCK_EDGE))]
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::brickmap::BrickMapBuilder;

    #[test]
    fn leaves_at_the_edge_of_the_index_range_build_small_majorants() {
        // A voxel's apron reaches one cell below i32::MIN with 1-voxel cells: the per-leaf table
        // must be sized in 64-bit arithmetic and clipped to the medium's box, not wrap around.
        for v in [IVec3::splat(i32::MIN), IVec3::splat(i32::MAX)] {
            let mut b = BrickMapBuilder::new();
            b.set(v, 2.0, true);
            let m = b.build();
            let (lo, hi) = m.active_bounds().unwrap();
            let bounds = (lo.as_vec3() - 0.5, hi.as_vec3() + 0.5);
            for cell in [1, 4] {
                let g = MajorantGrid::build_cells(&m, bounds, 1.0, cell, 0);
                assert!(g.memory_bytes() < 64 * 1024, "{} bytes", g.memory_bytes());
                assert!(g.blocks.iter().any(|b| b.floor >= 2.0
                    || b.cells
                        .as_ref()
                        .is_some_and(|c| c.iter().any(|&x| x >= 2.0))));
            }
        }
    }
}
