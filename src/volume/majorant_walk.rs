//! The walk over a `MajorantGrid`: a 3D DDA over its cells (pbrt-v4's `DDAMajorantIterator`), in
//! two levels when the cells live in blocks: a DDA over 8³-cell blocks that skips absent blocks
//! without producing segments and crosses a constant block in one segment, and inside the other
//! blocks a DDA over their cells. A flat grid (a compact medium) is walked by the inner DDA alone.

use glam::{IVec3, Vec3};

use crate::volume::brickmap::floor_ivec3;
use crate::volume::majorant::MajorantGrid;
use crate::volume::majorant_cells::{cell_offset, BLOCK_EDGE, BLOCK_LOG2};
use crate::volume::ray::MajorantSegment;
use crate::volume::sparse_index::NODE_LOG2;

impl MajorantGrid {
    /// Walks the cells the index-space ray `o + t·d` crosses for `t` in `[t0, t1)`, skipping
    /// regions without data (their majorant is 0). Match on the result once per walk (as the
    /// trackers do) to get a loop specialised for the grid's layout.
    #[inline]
    pub fn walk(&self, o: Vec3, d: Vec3, t0: f32, t1: f32) -> Walk<'_> {
        // The ray in cell units: cell c spans [c, c + 1).
        let o_cells = (o - self.origin) * self.inv_cell_size;
        let d_cells = d * self.inv_cell_size;
        let p0 = o_cells + d_cells * t0;
        let step = IVec3::from(d.cmpgt(Vec3::ZERO)) - IVec3::from(d.cmplt(Vec3::ZERO));
        // Edge / |d| rather than 1 / |d_cells|: exact for the global mode's single cell.
        let cell_delta_t = self.cell_size / d.abs();
        if !self.flat.is_empty() {
            // In the flat array's own coordinates: cell c_lo is (0, 0, 0).
            let dims = self.c_hi - self.c_lo + 1;
            let local = p0 - self.c_lo.as_vec3();
            return Walk::Flat(FlatWalk {
                cells: &self.flat,
                dims,
                dda: Dda::new(local, step, cell_delta_t, t0, Some((IVec3::ZERO, dims - 1))),
                t: t0,
                t_end: t1,
            });
        }
        let block = BLOCK_EDGE as f32;
        Walk::Blocks(DdaWalk {
            grid: self,
            o_cells,
            d_cells,
            cell_delta_t,
            t: t0,
            t_end: t1,
            outer: Dda::new(p0 / block, step, cell_delta_t * block, t0, None),
            inner: None,
        })
    }
}

/// A walk over a majorant grid, by layout.
pub enum Walk<'a> {
    Flat(FlatWalk<'a>),
    Blocks(DdaWalk<'a>),
}

impl Iterator for Walk<'_> {
    type Item = MajorantSegment;

    #[inline]
    fn next(&mut self) -> Option<MajorantSegment> {
        match self {
            Walk::Flat(w) => w.next(),
            Walk::Blocks(w) => w.next(),
        }
    }
}

/// The walk over a flat grid: one DDA over its cells, ending where the ray leaves the array.
pub struct FlatWalk<'a> {
    cells: &'a [f32],
    dims: IVec3,
    dda: Dda,
    t: f32,
    t_end: f32,
}

impl Iterator for FlatWalk<'_> {
    type Item = MajorantSegment;

    #[inline]
    fn next(&mut self) -> Option<MajorantSegment> {
        // Not `t >= t_end`: a walk whose bounds are NaN must end too.
        if self.t.partial_cmp(&self.t_end) != Some(std::cmp::Ordering::Less) {
            return None;
        }
        let dda = &mut self.dda;
        let a = dda.exit_axis();
        let t1 = dda.next_t[a].min(self.t_end);
        let segment = MajorantSegment {
            t0: self.t,
            t1,
            sigma_max: self.cells[cell_offset(dda.cell, self.dims)],
        };
        self.t = t1;
        dda.advance(a);
        if dda.cell[a] < 0 || dda.cell[a] >= self.dims[a] {
            self.t_end = t1; // left the grid
        }
        Some(segment)
    }
}

/// A 3D DDA over unit cells: the ray `p(t) = p0 + (t − t0)·d` in cell units.
#[derive(Clone, Copy)]
struct Dda {
    cell: IVec3,
    step: IVec3,
    next_t: Vec3,
    delta_t: Vec3,
}

impl Dda {
    /// Starts in the cell holding `p0` (clamped to `clamp`'s inclusive range: rounding at a
    /// boundary must not leave the block the caller is in). `step` and `delta_t` (t per cell, ∞
    /// on axes the ray does not move along) are the ray's, computed once per walk.
    #[inline]
    fn new(p0: Vec3, step: IVec3, delta_t: Vec3, t0: f32, clamp: Option<(IVec3, IVec3)>) -> Self {
        let mut cell = floor_ivec3(p0);
        if let Some((lo, hi)) = clamp {
            cell = cell.clamp(lo, hi);
        }
        let mut next_t = Vec3::splat(f32::INFINITY);
        for a in 0..3 {
            if step[a] > 0 {
                next_t[a] = t0 + ((cell[a] + 1) as f32 - p0[a]) * delta_t[a];
            } else if step[a] < 0 {
                next_t[a] = t0 + (p0[a] - cell[a] as f32) * delta_t[a];
            }
        }
        Dda {
            cell,
            step,
            next_t,
            delta_t,
        }
    }

    /// The axis whose boundary comes first.
    #[inline]
    fn exit_axis(&self) -> usize {
        if self.next_t.x < self.next_t.y {
            if self.next_t.x < self.next_t.z {
                0
            } else {
                2
            }
        } else if self.next_t.y < self.next_t.z {
            1
        } else {
            2
        }
    }

    /// Where the ray leaves the index node (`NODE_LOG2`-aligned group of cells) it is in.
    #[inline]
    fn node_exit(&self) -> f32 {
        let mask = (1 << NODE_LOG2) - 1;
        (0..3)
            .map(|a| {
                let local = self.cell[a] & mask;
                let remaining = match self.step[a] {
                    1 => mask - local,
                    -1 => local,
                    _ => return f32::INFINITY,
                };
                self.next_t[a] + remaining as f32 * self.delta_t[a]
            })
            .fold(f32::INFINITY, f32::min)
    }

    /// Crosses every boundary at or before `t` (at most a node's worth per axis, so that rounding
    /// can never make this loop long).
    #[inline]
    fn advance_to(&mut self, t: f32) {
        for a in 0..3 {
            for _ in 0..(1 << NODE_LOG2) {
                if self.next_t[a] > t || self.step[a] == 0 {
                    break;
                }
                self.advance(a);
            }
        }
    }

    #[inline]
    fn advance(&mut self, a: usize) {
        self.cell[a] += self.step[a];
        self.next_t[a] += self.delta_t[a];
    }
}

/// The cells of one block the walk is inside.
struct Inner<'a> {
    dda: Dda,
    base: IVec3,
    /// The block's cells inside the medium's box.
    lo: IVec3,
    hi: IVec3,
    dims: IVec3,
    cells: &'a [f32],
    exit: f32,
}

pub struct DdaWalk<'a> {
    grid: &'a MajorantGrid,
    o_cells: Vec3,
    d_cells: Vec3,
    cell_delta_t: Vec3,
    t: f32,
    t_end: f32,
    outer: Dda,
    inner: Option<Inner<'a>>,
}

impl Iterator for DdaWalk<'_> {
    type Item = MajorantSegment;

    #[inline]
    fn next(&mut self) -> Option<MajorantSegment> {
        let grid = self.grid;
        loop {
            // Not `t >= t_end`: a walk whose bounds are NaN must end too.
            if self.t.partial_cmp(&self.t_end) != Some(std::cmp::Ordering::Less) {
                return None;
            }
            if let Some(inner) = &mut self.inner {
                let a = inner.dda.exit_axis();
                // min/max, not clamp: clamp panics on NaN bounds.
                let t1 = inner.dda.next_t[a].min(inner.exit).max(self.t);
                let sigma_max = inner.cells[cell_offset(inner.dda.cell - inner.base, inner.dims)];
                let segment = MajorantSegment {
                    t0: self.t,
                    t1,
                    sigma_max,
                };
                self.t = t1;
                inner.dda.advance(a);
                let c = inner.dda.cell[a];
                if t1 >= inner.exit || c < inner.lo[a] || c > inner.hi[a] {
                    self.inner = None;
                }
                return Some(segment);
            }
            let key = self.outer.cell;
            let Some(handle) = grid.index.get_or_empty_node(key) else {
                // A whole index node (8³ blocks) without data: jump to where the ray leaves it.
                let skip_to = self.outer.node_exit().min(self.t_end).max(self.t);
                self.outer.advance_to(skip_to);
                self.t = skip_to;
                continue;
            };
            let a = self.outer.exit_axis();
            let exit = self.outer.next_t[a].min(self.t_end).max(self.t);
            self.outer.advance(a);
            if handle == 0 {
                self.t = exit; // no data: majorant 0, nothing to sample
                continue;
            }
            let block = &grid.blocks[handle as usize - 1];
            match &block.cells {
                None => {
                    let segment = MajorantSegment {
                        t0: self.t,
                        t1: exit,
                        sigma_max: block.floor,
                    };
                    self.t = exit;
                    return Some(segment);
                }
                Some(cells) => {
                    let base = key << BLOCK_LOG2;
                    let p = self.o_cells + self.d_cells * self.t;
                    let clamp = (base.max(grid.c_lo), (base + 7).min(grid.c_hi));
                    self.inner = Some(Inner {
                        dda: Dda::new(p, self.outer.step, self.cell_delta_t, self.t, Some(clamp)),
                        base,
                        lo: clamp.0,
                        hi: clamp.1,
                        dims: IVec3::splat(BLOCK_EDGE),
                        cells: &cells[..],
                        exit,
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::brickmap::BrickMapBuilder;
    use crate::volume::majorant::Majorant;

    #[test]
    fn majorant_bounds_every_trilinear_lookup() {
        // A hot voxel next to a cell boundary must raise the neighbouring cell too (the apron).
        let mut b = BrickMapBuilder::new();
        for x in 0..24 {
            for y in 0..24 {
                for z in 0..24 {
                    let hot = (x, y, z) == (7, 8, 15) || (x, y, z) == (16, 3, 3);
                    b.set(
                        IVec3::new(x, y, z),
                        if hot {
                            9.0
                        } else {
                            0.1 * ((x * 7 + y * 3 + z) % 5) as f32
                        },
                        true,
                    );
                }
            }
        }
        let m = b.build();
        let bounds = (Vec3::splat(-0.5), Vec3::splat(23.5));
        let flat = MajorantGrid::build_cells(&m, bounds, 2.0, 8, u64::MAX);
        let blocks = MajorantGrid::build_cells(&m, bounds, 2.0, 8, 0);
        assert_eq!((flat.flat.len(), flat.blocks.len()), (27, 0));
        assert_eq!((blocks.flat.len(), blocks.blocks.len()), (0, 1));
        let mut state = 12345u64;
        for k in 0..40000 {
            let grid = if k % 2 == 0 { &flat } else { &blocks };
            let mut r = || {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 40) as f32 / (1u64 << 24) as f32
            };
            let o = Vec3::new(r(), r(), r()) * 24.0 - 0.5;
            let d = (Vec3::new(r(), r(), r()) - 0.5).normalize();
            let exit = (0..3)
                .map(|a| {
                    if d[a] > 0.0 {
                        (23.5 - o[a]) / d[a]
                    } else {
                        (-0.5 - o[a]) / d[a]
                    }
                })
                .fold(f32::INFINITY, f32::min);
            let mut covered = 0.0;
            for seg in grid.walk(o, d, 0.0, exit) {
                assert!(seg.t1 >= seg.t0);
                covered += seg.t1 - seg.t0;
                for k in 0..=4 {
                    let t = seg.t0 + (seg.t1 - seg.t0) * (k as f32 + 0.5) / 5.0;
                    let sigma = 2.0 * m.trilinear(o + d * t);
                    assert!(
                        sigma <= seg.sigma_max + 1e-5,
                        "σ {sigma} > majorant {} at {}",
                        seg.sigma_max,
                        o + d * t
                    );
                }
            }
            assert!(
                (covered - exit).abs() < 1e-3 * exit.max(1.0),
                "segments cover {covered} of {exit}"
            );
        }
    }

    #[test]
    fn global_mode_is_one_cell_with_the_grid_maximum() {
        let mut b = BrickMapBuilder::new();
        b.set(IVec3::new(3, 4, 5), 7.0, true);
        b.set(IVec3::new(30, 4, 5), 1.0, true);
        let m = b.build();
        let grid = MajorantGrid::build(
            &m,
            (Vec3::new(2.5, 3.5, 4.5), Vec3::new(30.5, 4.5, 5.5)),
            0.5,
            Majorant::global(),
        );
        assert_eq!(grid.cell_count(), 1);
        let segs: Vec<_> = grid
            .walk(Vec3::new(2.5, 4.0, 5.0), Vec3::X, 0.0, 28.0)
            .collect();
        assert_eq!(
            segs,
            vec![MajorantSegment {
                t0: 0.0,
                t1: 28.0,
                sigma_max: 3.5
            }]
        );
    }
}
