//! The walk over a `MajorantGrid`: a 3D DDA over its cells (pbrt-v4's `DDAMajorantIterator`), in
//! two levels when the cells live in blocks: a DDA over 8³-cell blocks that skips absent blocks
//! without producing segments and crosses a constant block in one segment, and inside the other
//! blocks a DDA over their cells. A flat grid (a compact medium) is walked by the inner DDA alone;
//! a grid flat in a box per cluster of the data, by that DDA in each box the ray crosses, in order.

use glam::{IVec3, Vec3};

use crate::volume::brickmap::floor_ivec3;
use crate::volume::majorant::MajorantGrid;
use crate::volume::majorant_cells::{cell_offset, FlatCells, BLOCK_EDGE, BLOCK_LOG2};
use crate::volume::majorant_clusters::MAX_CLUSTERS;
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
        let ray = CellRay {
            o_cells,
            d_cells,
            step,
            cell_delta_t,
        };
        match self.flat.as_slice() {
            [] => {}
            // One box over the medium's: the plain flat walk (a box smaller than the medium's, as
            // a medium given wider bounds than its data has, is entered where the ray meets it).
            [cells] if (cells.lo, cells.hi) == (self.c_lo, self.c_hi) => {
                return Walk::Flat(FlatWalk::new(cells, &ray, t0, t1))
            }
            clusters => return Walk::Clusters(ClusterWalk::new(clusters, ray, t0, t1)),
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
    Clusters(ClusterWalk<'a>),
    Blocks(DdaWalk<'a>),
}

impl Iterator for Walk<'_> {
    type Item = MajorantSegment;

    #[inline]
    fn next(&mut self) -> Option<MajorantSegment> {
        match self {
            Walk::Flat(w) => w.next(),
            Walk::Clusters(w) => w.next(),
            Walk::Blocks(w) => w.next(),
        }
    }
}

/// The ray in cell units (cell c spans [c, c + 1)), as every walk starts from it.
struct CellRay {
    o_cells: Vec3,
    d_cells: Vec3,
    step: IVec3,
    cell_delta_t: Vec3,
}

/// The walk over a flat box of cells: one DDA over its cells, ending where the ray leaves it.
pub struct FlatWalk<'a> {
    cells: &'a [f32],
    dims: IVec3,
    dda: Dda,
    t: f32,
    t_end: f32,
}

impl<'a> FlatWalk<'a> {
    #[inline(always)]
    fn new(flat: &'a FlatCells, ray: &CellRay, t0: f32, t1: f32) -> Self {
        // In the box's own coordinates: cell `flat.lo` is (0, 0, 0).
        let dims = flat.dims();
        let local = ray.o_cells + ray.d_cells * t0 - flat.lo.as_vec3();
        FlatWalk {
            cells: &flat.cells,
            dims,
            dda: Dda::new(
                local,
                ray.step,
                ray.cell_delta_t,
                t0,
                Some((IVec3::ZERO, dims - 1)),
            ),
            t: t0,
            t_end: t1,
        }
    }
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
        // max: a start clamped into the box (rounding at its face) must not end before it began.
        let t1 = dda.next_t[a].min(self.t_end).max(self.t);
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

/// The walk over a grid flat in a box per cluster: the stretch of the ray inside each box it
/// crosses, in order along the ray, walked as a flat box. The empty space between the boxes
/// yields no segment, as the cells of majorant 0 in it would yield no tentative collision.
pub struct ClusterWalk<'a> {
    clusters: &'a [FlatCells],
    ray: CellRay,
    /// The boxes the ray crosses on `[t0, t1)`: where it enters and leaves each, and which.
    spans: [(f32, f32, u8); MAX_CLUSTERS],
    count: usize,
    next: usize,
    /// Where the last stretch walked ended.
    walked_to: f32,
    current: Option<FlatWalk<'a>>,
}

impl<'a> ClusterWalk<'a> {
    #[inline]
    fn new(clusters: &'a [FlatCells], ray: CellRay, t0: f32, t1: f32) -> Self {
        let mut walk = ClusterWalk {
            clusters,
            ray,
            spans: [(0.0, 0.0, 0); MAX_CLUSTERS],
            count: 0,
            next: 0,
            walked_to: t0,
            current: None,
        };
        let (o, d) = (walk.ray.o_cells, walk.ray.d_cells);
        let inv_d = d.recip();
        for (i, cluster) in clusters.iter().enumerate().take(MAX_CLUSTERS) {
            let (lo, hi) = (cluster.lo.as_vec3(), cluster.hi.as_vec3() + 1.0);
            let (mut enter, mut leave) = (t0, t1);
            for a in 0..3 {
                if d[a] == 0.0 {
                    if o[a] < lo[a] || o[a] >= hi[a] {
                        leave = f32::NEG_INFINITY;
                    }
                    continue;
                }
                let (near, far) = ((lo[a] - o[a]) * inv_d[a], (hi[a] - o[a]) * inv_d[a]);
                enter = enter.max(near.min(far));
                leave = leave.min(near.max(far));
            }
            if enter < leave {
                // Insertion by entry: the boxes are disjoint, so their stretches are too.
                let mut k = walk.count;
                while k > 0 && walk.spans[k - 1].0 > enter {
                    walk.spans[k] = walk.spans[k - 1];
                    k -= 1;
                }
                walk.spans[k] = (enter, leave, i as u8);
                walk.count += 1;
            }
        }
        walk
    }
}

impl Iterator for ClusterWalk<'_> {
    type Item = MajorantSegment;

    #[inline(always)]
    fn next(&mut self) -> Option<MajorantSegment> {
        loop {
            if let Some(segment) = self.current.as_mut().and_then(|w| w.next()) {
                return Some(segment);
            }
            if self.next == self.count {
                return None;
            }
            let (enter, leave, i) = self.spans[self.next];
            self.next += 1;
            // Boxes that touch: rounding must not let a stretch begin before the last one ended.
            let enter = enter.max(self.walked_to);
            self.walked_to = self.walked_to.max(leave);
            let cluster = &self.clusters[i as usize];
            self.current = Some(FlatWalk::new(cluster, &self.ray, enter, leave));
        }
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
#[path = "majorant_walk_tests.rs"]
mod tests;
