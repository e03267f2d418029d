//! The per-cell bounds of a grid-mode majorant: the maximum σt every lookup in a cell can see,
//! gathered from the leaves and tiles of a brick map into flat or block storage.
//!
//! Cell `c` of a grid with cell edge `S` voxels covers the voxels `c·S .. c·S+S-1`, i.e. the
//! continuous index range `[c·S − ½, c·S + S − ½)`. A trilinear lookup anywhere in it reads voxels
//! `c·S − 1 ..= c·S + S` (the one-voxel apron), so the cell's majorant is the maximum σt over that
//! range; a nearest lookup reads a subset.
//!
//! Memory follows the data: a compact medium's cells are one flat array; a wide one's are one flat
//! array per cluster of its data (`majorant_clusters`) where a few boxes hold them, and otherwise
//! grouped in blocks of 8³, a block existing only where a brick or a tile raises it (a
//! `SparseIndex` finds it). A block inside a tile is one shared constant, not 512 cells. Kept apart from the
//! grid that holds the result (`majorant`) and the walk over it (`majorant_walk`): building is the
//! one part that reads voxels.

use glam::{IVec3, Vec3};
use rayon::prelude::*;

use crate::volume::brickmap::{BrickMap, Leaf, BRICK_EDGE as BRICK_EDGE_VOXELS};
use crate::volume::majorant_clusters::{self, CellBox};
use crate::volume::sparse_index::SparseIndex;

/// Cells per block edge (log2) and cells per block.
pub(super) const BLOCK_LOG2: i32 = 3;
pub(super) const BLOCK_CELLS: usize = 1 << (3 * BLOCK_LOG2);
pub(super) const BLOCK_EDGE: i32 = 1 << BLOCK_LOG2;
/// Ranges at least this many blocks wide are raised block by block, not cell by cell.
const WIDE_RANGE_BLOCKS: i32 = 16;

/// A block of 8³ cells: one majorant for all of them, or one per cell.
#[derive(Clone)]
pub(super) struct Block {
    /// Majorant of every cell without its own value (and a lower bound of those that have one).
    pub(super) floor: f32,
    pub(super) cells: Option<Box<[f32; BLOCK_CELLS]>>,
    /// Referenced by many index entries (a tile's interior): copied before a single cell changes.
    pub(super) shared: bool,
}

/// Offset of cell `local` in an x-major array of `dims` cells.
#[inline]
pub(super) fn cell_offset(local: IVec3, dims: IVec3) -> usize {
    (local.x as usize * dims.y as usize + local.y as usize) * dims.z as usize + local.z as usize
}

/// A box of cells `lo ..= hi`, one majorant each, x-major.
#[derive(Clone)]
pub(super) struct FlatCells {
    pub(super) lo: IVec3,
    pub(super) hi: IVec3,
    pub(super) cells: Vec<f32>,
}

impl FlatCells {
    fn zeros(b: CellBox) -> Self {
        FlatCells {
            lo: b.lo,
            hi: b.hi,
            cells: vec![0.0; b.cells() as usize],
        }
    }

    pub(super) fn dims(&self) -> IVec3 {
        self.hi - self.lo + 1
    }

    /// The majorant of cell `c`, if the box holds it.
    #[inline]
    pub(super) fn get(&self, c: IVec3) -> Option<f32> {
        (c.cmpge(self.lo).all() && c.cmple(self.hi).all())
            .then(|| self.cells[cell_offset(c - self.lo, self.dims())])
    }
}

/// The most cells a flat majorant may have: 2048 per leaf or tile (8 KiB next to a leaf's 2 KiB, so
/// that a compact grid keeps the fastest walk even with 1³ cells: the cloud's are 2.6 × its leaf
/// data, as before), or 2¹² for tiny grids. Beyond it (wide grids) cells live in a box per cluster
/// of the data, or in blocks.
pub(super) fn flat_cell_budget(bricks: &BrickMap) -> u64 {
    (2048 * (bricks.leaves().len() + bricks.tiles().len()) as u64).max(1 << 12)
}

/// The cells of a grid-mode majorant, built by `Builder::build` and then moved into the grid.
pub(super) struct Builder {
    /// Flat mode's cells: one box over the medium's or one per cluster of its data (empty in
    /// block mode).
    pub(super) flats: Vec<FlatCells>,
    pub(super) index: SparseIndex,
    pub(super) blocks: Vec<Block>,
    /// Cells of the medium's box (inclusive): cells beyond it are never walked.
    pub(super) c_lo: IVec3,
    pub(super) c_hi: IVec3,
}

impl Builder {
    /// The majorants of the cells of edge `s` voxels over the continuous index box `bounds`,
    /// values multiplied by `density_scale`: one flat array when the box has at most
    /// `flat_budget` cells, one per cluster when the clusters' boxes have, blocks otherwise.
    pub(super) fn build(
        bricks: &BrickMap,
        bounds: (Vec3, Vec3),
        density_scale: f32,
        s: i32,
        flat_budget: u64,
    ) -> Self {
        // Voxel centres inside the box run from ceil(lo) to floor(hi); their cells span the box.
        let first_voxel = bounds.0.ceil().as_ivec3();
        let last_voxel = bounds.1.floor().as_ivec3();
        let c_lo = first_voxel.div_euclid(IVec3::splat(s));
        let c_hi = last_voxel.div_euclid(IVec3::splat(s)).max(c_lo);
        let whole = CellBox { lo: c_lo, hi: c_hi };
        let boxes = if whole.cells() <= flat_budget {
            vec![whole]
        } else {
            majorant_clusters::find(bricks, s, c_lo, c_hi, flat_budget).unwrap_or_default()
        };
        let mut builder = Builder {
            flats: boxes.into_iter().map(FlatCells::zeros).collect(),
            index: SparseIndex::new(c_lo >> BLOCK_LOG2, c_hi >> BLOCK_LOG2),
            blocks: Vec::new(),
            c_lo,
            c_hi,
        };
        // Voxel v lies in the apron-grown footprint of cells ceil((v − S)/S) ..= floor((v + 1)/S).
        let footprint = |v_lo: IVec3, v_hi: IVec3| {
            // i64: the apron of a voxel at the edge of the i32 range must not wrap around.
            let s = glam::I64Vec3::splat(s as i64);
            let lo = (v_lo.as_i64vec3() - 1).div_euclid(s);
            let hi = (v_hi.as_i64vec3() + 1).div_euclid(s);
            (lo.as_ivec3(), hi.as_ivec3())
        };
        // Per leaf, the maxima over each cell's share of it are gathered in a small local table
        // first and each cell is raised once: raising the footprint of every voxel (512 per leaf)
        // made this build most of the load time of a large grid. The tables are independent, so
        // they are gathered in parallel; raising stays in leaf order.
        let (box_lo, box_hi) = (builder.c_lo.as_i64vec3(), builder.c_hi.as_i64vec3());
        let tables: Vec<_> = bricks
            .leaves()
            .par_iter()
            .filter_map(|leaf| leaf_cell_maxima(leaf, s, box_lo, box_hi))
            .collect();
        for (first_cell, dims, local) in tables {
            builder.raise_table(first_cell, dims, &local, density_scale);
        }
        for tile in bricks.tiles() {
            if tile.value > 0.0 {
                let last = tile
                    .origin
                    .saturating_add(IVec3::splat(tile.size as i32 - 1));
                let (lo, hi) = footprint(tile.origin, last);
                builder.raise(lo, hi, tile.value * density_scale);
            }
        }
        builder
    }

    /// The block behind `slot`, created (or unshared) so that it can be changed alone.
    fn own(blocks: &mut Vec<Block>, slot: &mut u32) -> usize {
        if *slot == 0 {
            blocks.push(Block {
                floor: 0.0,
                cells: None,
                shared: false,
            });
            *slot = blocks.len() as u32;
        } else if blocks[*slot as usize - 1].shared {
            let mut copy = blocks[*slot as usize - 1].clone();
            copy.shared = false;
            blocks.push(copy);
            *slot = blocks.len() as u32;
        }
        *slot as usize - 1
    }

    fn raise_floor(block: &mut Block, sigma: f32) {
        block.floor = block.floor.max(sigma);
        if let Some(cells) = &mut block.cells {
            cells.iter_mut().for_each(|c| *c = c.max(sigma));
        }
    }

    /// Raises each cell `first + (x, y, z)` of a table of `dims` cells (x-major) whose value is
    /// positive to at least value × `scale`, as `raise` cell by cell would. A flat majorant takes
    /// the table row by row: three million calls of `raise` were a third of a large grid's build.
    fn raise_table(&mut self, first: IVec3, dims: IVec3, table: &[f32], scale: f32) {
        let at = |c: IVec3| table[cell_offset(c - first, dims)];
        if self.flats.is_empty() {
            for k in 0..table.len() as i32 {
                let cell =
                    first + IVec3::new(k / (dims.y * dims.z), (k / dims.z) % dims.y, k % dims.z);
                if at(cell) > 0.0 {
                    self.raise(cell, cell, at(cell) * scale);
                }
            }
            return;
        }
        for flat in &mut self.flats {
            let (lo, hi) = (first.max(flat.lo), (first + dims - 1).min(flat.hi));
            if lo.cmpgt(hi).any() {
                continue;
            }
            let flat_dims = flat.dims();
            for x in lo.x..=hi.x {
                for y in lo.y..=hi.y {
                    let row = cell_offset(IVec3::new(x, y, lo.z) - flat.lo, flat_dims);
                    for z in lo.z..=hi.z {
                        let value = at(IVec3::new(x, y, z));
                        if value > 0.0 {
                            let c = &mut flat.cells[row + (z - lo.z) as usize];
                            *c = c.max(value * scale);
                        }
                    }
                }
            }
        }
    }

    /// Raises the majorant of every cell in the inclusive range `[lo, hi]` to at least `sigma`.
    fn raise(&mut self, lo: IVec3, hi: IVec3, sigma: f32) {
        let (lo, hi) = (lo.max(self.c_lo), hi.min(self.c_hi));
        if lo.cmpgt(hi).any() {
            return;
        }
        if !self.flats.is_empty() {
            for flat in &mut self.flats {
                let (lo, hi) = (lo.max(flat.lo), hi.min(flat.hi));
                let dims = flat.dims();
                for x in lo.x..=hi.x {
                    for y in lo.y..=hi.y {
                        for z in lo.z..=hi.z {
                            let c =
                                &mut flat.cells[cell_offset(IVec3::new(x, y, z) - flat.lo, dims)];
                            *c = c.max(sigma);
                        }
                    }
                }
            }
            return;
        }
        let (b_lo, b_hi) = (lo >> BLOCK_LOG2, hi >> BLOCK_LOG2);
        // Blocks entirely inside the range share one constant block (a tile's interior). A range
        // many blocks wide (a large tile) gives its partly covered blocks the constant too: a
        // looser bound one block thick around it, so that its cost grows with its surface in
        // index nodes and not in cells (a 4096³ tile's apron would otherwise be 10⁵ cell arrays).
        let wide = (b_hi - b_lo).max_element() >= WIDE_RANGE_BLOCKS;
        let (fill_lo, fill_hi) = if wide {
            (b_lo, b_hi)
        } else {
            (
                (lo + (1 << BLOCK_LOG2) - 1) >> BLOCK_LOG2,
                ((hi + 1) >> BLOCK_LOG2) - 1,
            )
        };
        if fill_lo.cmple(fill_hi).all() {
            self.blocks.push(Block {
                floor: sigma,
                cells: None,
                shared: true,
            });
            let handle = self.blocks.len() as u32;
            let blocks = &mut self.blocks;
            self.index.fill(fill_lo, fill_hi, handle, |slot| {
                let b = Self::own(blocks, slot);
                Self::raise_floor(&mut blocks[b], sigma);
            });
        }
        if wide {
            return;
        }
        let (full_lo, full_hi) = (fill_lo, fill_hi);
        for bx in b_lo.x..=b_hi.x {
            for by in b_lo.y..=b_hi.y {
                for bz in b_lo.z..=b_hi.z {
                    let key = IVec3::new(bx, by, bz);
                    if key.cmpge(full_lo).all() && key.cmple(full_hi).all() {
                        continue;
                    }
                    let Some(slot) = self.index.slot_mut(key) else {
                        continue;
                    };
                    let b = Self::own(&mut self.blocks, slot);
                    let block = &mut self.blocks[b];
                    let floor = block.floor;
                    let cells = block
                        .cells
                        .get_or_insert_with(|| Box::new([floor; BLOCK_CELLS]));
                    let base = key << BLOCK_LOG2;
                    let (a, z) = (lo.max(base) - base, hi.min(base + 7) - base);
                    for x in a.x..=z.x {
                        for y in a.y..=z.y {
                            for zz in a.z..=z.z {
                                let c = &mut cells
                                    [cell_offset(IVec3::new(x, y, zz), IVec3::splat(BLOCK_EDGE))];
                                *c = c.max(sigma);
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The most cells a leaf's apron-grown footprint spans per axis ((8 + 2) voxels, one cell each).
const MAX_LEAF_CELLS: usize = 12;

/// The maxima of `leaf`'s values over each majorant cell's apron-grown share of it (cells of `s`³
/// voxels inside the box `box_lo..=box_hi`, at most 12 per axis): the first cell, the table's
/// dimensions and the table, x-major. `None` when the leaf reaches no cell of the box.
/// 64-bit arithmetic: a leaf at the edge of the i32 range must not wrap around.
fn leaf_cell_maxima(
    leaf: &Leaf,
    s: i32,
    box_lo: glam::I64Vec3,
    box_hi: glam::I64Vec3,
) -> Option<(IVec3, IVec3, Vec<f32>)> {
    let s64 = s as i64;
    let origin = leaf.origin.as_i64vec3();
    let first_cell = ((origin - 1).div_euclid(glam::I64Vec3::splat(s64))).max(box_lo);
    let last_cell =
        ((origin + BRICK_EDGE_VOXELS as i64).div_euclid(glam::I64Vec3::splat(s64))).min(box_hi);
    if first_cell.cmpgt(last_cell).any() {
        return None;
    }
    let dims = (last_cell - first_cell + 1).as_ivec3();
    let (dx, dy, dz) = (dims.x as usize, dims.y as usize, dims.z as usize);
    // Per axis, the local cells a voxel at leaf coordinate i reaches (an empty range where they
    // all lie outside the box).
    let reach: [[std::ops::Range<usize>; 8]; 3] = std::array::from_fn(|a| {
        std::array::from_fn(|i| {
            let v = origin[a] + i as i64;
            let lo = ((v - 1).div_euclid(s64) - first_cell[a]).max(0);
            let end = ((v + 1).div_euclid(s64) - first_cell[a] + 1).min(dims[a] as i64);
            lo as usize..end.max(lo) as usize
        })
    });
    // A cell's maximum is separable. Reduce x first, whole (y, z) slabs of 64 values at a time,
    // then y, rows of 8 z at a time, then z: the first two passes are element-wise maxima of
    // contiguous arrays, which vectorise (reducing z first, a scalar pass over every voxel, took
    // 1.8 times as long).
    let mut along_x = [[0.0f32; 64]; MAX_LEAF_CELLS];
    for (x, slab) in leaf.values.chunks_exact(64).enumerate() {
        for cx in reach[0][x].clone() {
            for (o, &v) in along_x[cx].iter_mut().zip(slab) {
                *o = o.max(v);
            }
        }
    }
    let mut along_xy = [[0.0f32; 8]; MAX_LEAF_CELLS * MAX_LEAF_CELLS];
    for (cx, slab) in along_x[..dx].iter().enumerate() {
        for (y, row) in slab.chunks_exact(8).enumerate() {
            for cy in reach[1][y].clone() {
                for (o, &v) in along_xy[cx * dy + cy].iter_mut().zip(row) {
                    *o = o.max(v);
                }
            }
        }
    }
    let mut local = vec![0.0f32; dx * dy * dz];
    for (out, row) in local.chunks_exact_mut(dz).zip(&along_xy[..dx * dy]) {
        for (z, &v) in row.iter().enumerate() {
            for cz in reach[2][z].clone() {
                out[cz] = out[cz].max(v);
            }
        }
    }
    Some((first_cell.as_ivec3(), dims, local))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::brickmap::BRICK_VOXELS;

    #[test]
    fn a_leaf_cell_maximum_is_the_max_over_the_cells_apron() {
        // The separable reduction against the definition: cell c (edge s) takes the largest value
        // of the leaf's voxels v with c·s − 1 ≤ v ≤ c·s + s per axis, and 0 when none is > 0.
        let mut state = 99u64;
        let mut r = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        for s in [1, 2, 3, 4, 8] {
            for origin in [IVec3::ZERO, IVec3::new(-8, 16, 40), IVec3::new(8, -24, 0)] {
                let mut leaf = Leaf {
                    origin,
                    values: [0.0; BRICK_VOXELS],
                    active: [u64::MAX; 8],
                };
                for v in leaf.values.iter_mut() {
                    let x = r();
                    *v = if x < 0.3 { 0.0 } else { 4.0 * x - 1.5 };
                }
                // A box that cuts the leaf's cells on some sides.
                let box_lo = (origin.as_i64vec3() / s as i64) - glam::I64Vec3::new(1, 0, 1);
                let box_hi = (origin.as_i64vec3() / s as i64) + glam::I64Vec3::new(9, 1, 9);
                let (first, dims, table) = leaf_cell_maxima(&leaf, s, box_lo, box_hi).unwrap();
                for (k, &got) in table.iter().enumerate() {
                    let k = k as i32;
                    let cell = first
                        + IVec3::new(k / (dims.y * dims.z), (k / dims.z) % dims.y, k % dims.z);
                    let (lo, hi) = (cell * s - 1, cell * s + s);
                    let mut expected = 0.0f32;
                    for (i, &v) in leaf.values.iter().enumerate() {
                        let voxel = origin
                            + IVec3::new((i >> 6) as i32, ((i >> 3) & 7) as i32, (i & 7) as i32);
                        if voxel.cmpge(lo).all() && voxel.cmple(hi).all() {
                            expected = expected.max(v);
                        }
                    }
                    assert_eq!(got, expected, "cell {cell} (edge {s}, leaf at {origin})");
                }
                // The table covers exactly the cells the leaf reaches inside the box.
                let reach_lo = (origin.as_i64vec3() - 1).div_euclid(glam::I64Vec3::splat(s as i64));
                assert_eq!(first.as_i64vec3(), reach_lo.max(box_lo));
            }
        }
    }
}
