//! Sparse voxel storage that mirrors an OpenVDB float tree: 8³ bricks (VDB leaves) and constant
//! active tiles, found through a `SparseIndex` of brick slots (8³-brick nodes under a top level that
//! is dense for compact grids), so that memory follows the active data whatever the bounding box
//! and a lookup in a compact grid is three array reads and no hashing.
//!
//! Conventions are OpenVDB's: voxel centres at integer index coordinates, leaf values in the order
//! `x*64 + y*8 + z`, and the value 0 wherever there is no leaf or tile (fog volumes' background).

use std::collections::HashMap;

use glam::{IVec3, Vec3};
use rayon::prelude::*;

use crate::volume::sparse_index::SparseIndex;

pub const BRICK_EDGE: i32 = 8;
pub const BRICK_VOXELS: usize = 512;

/// One 8³ leaf: every value of its buffer (inactive voxels included, as OpenVDB keeps them) and its
/// active mask. `repr(C)`: the bridge's `LeafData` has the same layout, so that a grid read from a
/// file becomes a brick map without copying its leaves.
#[derive(Clone)]
#[repr(C)]
pub struct Leaf {
    pub origin: IVec3,
    pub values: [f32; BRICK_VOXELS],
    pub active: [u64; 8],
}

/// A constant active region of `size`³ voxels (a multiple of 8) starting at `origin`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tile {
    pub origin: IVec3,
    pub size: u32,
    pub value: f32,
}

/// Slot encoding: 0 = empty, `TILE_BIT | j` = tile j, otherwise leaf `slot - 1`.
const EMPTY: u32 = 0;
const TILE_BIT: u32 = 1 << 31;

#[inline]
pub fn leaf_offset(local: IVec3) -> usize {
    ((local.x << 6) | (local.y << 3) | local.z) as usize
}

#[derive(Clone)]
pub struct BrickMap {
    leaves: Vec<Leaf>,
    tiles: Vec<Tile>,
    /// Brick coordinates (index >> 3) → slot, for the bricks lookups can reach.
    slots: SparseIndex,
    /// Inclusive bounding box of the active voxels; `None` for an empty grid.
    active_bounds: Option<(IVec3, IVec3)>,
    /// The smallest and largest stored value, each with 0 (an empty grid's range is (0, 0)).
    value_range: (f32, f32),
}

/// What a brick slot holds, resolved once so that neighbouring lookups can reuse it.
#[derive(Clone, Copy)]
enum Brick<'a> {
    Empty,
    Constant(f32),
    Leaf(&'a [f32; BRICK_VOXELS]),
}

impl Brick<'_> {
    /// The value of voxel `v`, which lies in this brick.
    #[inline(always)]
    fn value(self, v: IVec3) -> f32 {
        match self {
            Brick::Empty => 0.0,
            Brick::Constant(c) => c,
            Brick::Leaf(values) => values[leaf_offset(v & 7)],
        }
    }
}

impl BrickMap {
    /// Builds the map from leaves and tiles. The slot table covers the active bounding box plus a
    /// one-voxel apron (trilinear lookups at the medium's edge read one voxel beyond the active box);
    /// leaves entirely outside it are unreachable and dropped.
    pub fn new(leaves: Vec<Leaf>, tiles: Vec<Tile>) -> Self {
        let active_bounds = active_bounds(&leaves, &tiles);
        let (lo, hi) = match active_bounds {
            // i64: the apron of a voxel at the edge of the i32 range must not wrap around.
            Some((lo, hi)) => (
                brick_of_i64(lo.as_i64vec3() - 1),
                brick_of_i64(hi.as_i64vec3() + 1),
            ),
            None => (IVec3::ZERO, IVec3::splat(-1)),
        };
        let flat_budget = flat_slot_budget(&leaves, &tiles);
        let mut map = BrickMap {
            leaves: Vec::new(),
            tiles,
            slots: SparseIndex::with_flat_budget(lo, hi, flat_budget),
            active_bounds,
            value_range: (0.0, 0.0),
        };
        for (j, tile) in map.tiles.iter().enumerate() {
            let b0: IVec3 = tile.origin >> 3;
            let n = (tile.size as i32 / BRICK_EDGE).max(1);
            let handle = TILE_BIT | j as u32;
            // A later tile wins where tiles overlap (they do not in a valid VDB tree).
            let last = b0.saturating_add(IVec3::splat(n - 1));
            map.slots.fill(b0, last, handle, |slot| *slot = handle);
        }
        // Leaves after tiles: a leaf overrides the tile around it (see `with_added`). They are
        // kept in place (a second vector would hold a large grid twice while it fills).
        let mut leaves = leaves;
        let mut handle = 0u32;
        leaves.retain(|leaf| match map.slots.slot_mut(leaf.origin >> 3) {
            Some(slot) => {
                handle += 1;
                *slot = handle;
                true
            }
            None => false,
        });
        map.value_range = value_range(&leaves, &map.tiles);
        map.leaves = leaves;
        map
    }

    /// The `n`³ block of active voxels 0..n with values `f(voxel)`: test and example grids.
    pub fn block(n: i32, f: impl Fn(IVec3) -> f32) -> BrickMap {
        let mut b = BrickMapBuilder::new();
        for x in 0..n {
            for y in 0..n {
                for z in 0..n {
                    let v = IVec3::new(x, y, z);
                    b.set(v, f(v), true);
                }
            }
        }
        b.build()
    }

    pub fn leaves(&self) -> &[Leaf] {
        &self.leaves
    }

    /// The leaves, handed over (the map is consumed).
    pub fn into_leaves(self) -> Vec<Leaf> {
        self.leaves
    }

    pub fn tiles(&self) -> &[Tile] {
        &self.tiles
    }

    pub fn active_bounds(&self) -> Option<(IVec3, IVec3)> {
        self.active_bounds
    }

    /// Bytes held by the map (leaf buffers and masks, tiles, the slot table).
    pub fn memory_bytes(&self) -> usize {
        self.leaves.len() * std::mem::size_of::<Leaf>()
            + self.tiles.len() * std::mem::size_of::<Tile>()
            + self.slots.memory_bytes()
            + std::mem::size_of::<Self>()
    }

    #[inline(always)]
    fn brick(&self, brick: IVec3) -> Brick<'_> {
        match self.slots.get(brick) {
            EMPTY => Brick::Empty,
            s if s & TILE_BIT != 0 => Brick::Constant(self.tiles[(s & !TILE_BIT) as usize].value),
            s => Brick::Leaf(&self.leaves[(s - 1) as usize].values),
        }
    }

    /// The value stored for voxel `v` (0 where there is no data).
    #[inline]
    pub fn voxel(&self, v: IVec3) -> f32 {
        self.brick(v >> 3).value(v)
    }

    /// Whether voxel `v` is active (in a leaf's mask or inside an active tile).
    pub fn is_active(&self, v: IVec3) -> bool {
        match self.slots.get(v >> 3) {
            EMPTY => false,
            s if s & TILE_BIT != 0 => true,
            s => {
                let o = leaf_offset(v & 7);
                self.leaves[(s - 1) as usize].active[o >> 6] & (1u64 << (o & 63)) != 0
            }
        }
    }

    /// Value of the voxel whose cell contains `p` (index space).
    #[inline]
    pub fn nearest(&self, p: Vec3) -> f32 {
        self.voxel(floor_ivec3(p + 0.5))
    }

    /// Trilinear interpolation between voxel centres (OpenVDB's BoxSampler).
    #[inline(always)]
    pub fn trilinear(&self, p: Vec3) -> f32 {
        let v0 = floor_ivec3(p);
        let local = v0 & 7;
        if local.cmplt(IVec3::splat(7)).all() {
            // All eight corners in one brick: resolve it once; empty and constant bricks need
            // no interpolation.
            return match self.brick(v0 >> 3) {
                Brick::Empty => 0.0,
                Brick::Constant(value) => value,
                Brick::Leaf(values) => interpolate(&leaf_corners(values, local), p - v0.as_vec3()),
            };
        }
        interpolate(&self.straddling_corners(v0), p - v0.as_vec3())
    }

    /// The values at the eight corners of the trilinear cell between voxel centres `v0` and
    /// `v0 + 1`, corner k at `v0 + corner(k)`.
    #[inline(always)]
    pub fn cell_corners(&self, v0: IVec3) -> [f32; 8] {
        let local = v0 & 7;
        if local.cmplt(IVec3::splat(7)).all() {
            return match self.brick(v0 >> 3) {
                Brick::Empty => [0.0; 8],
                Brick::Constant(value) => [value; 8],
                Brick::Leaf(values) => leaf_corners(values, local),
            };
        }
        self.straddling_corners(v0)
    }

    /// `cell_corners` of a cell that straddles bricks (a third of all lookups): the bricks it
    /// touches (two, four or eight: one per subset of the axes it crosses) are resolved once each
    /// instead of once per corner.
    #[inline(always)]
    fn straddling_corners(&self, v0: IVec3) -> [f32; 8] {
        let carry = IVec3::from((v0 & 7).cmpeq(IVec3::splat(7)));
        let crossed = ((carry.x << 2) | (carry.y << 1) | carry.z) as usize;
        let mut bricks = [Brick::Empty; 8];
        for (which, brick) in bricks.iter_mut().enumerate() {
            if which & !crossed == 0 {
                *brick = self.brick((v0 >> 3) + corner(which));
            }
        }
        std::array::from_fn(|k| bricks[k & crossed].value(v0 + corner(k)))
    }

    /// A copy with `delta` added to the given voxels (finite differences). Voxels inside tiles get
    /// their brick voxelised; active flags and the active bounds are kept; voxels beyond the slot
    /// table (unreachable by lookups) are ignored.
    pub fn with_added(&self, deltas: &[(IVec3, f32)]) -> BrickMap {
        let mut leaves: HashMap<IVec3, Leaf> =
            self.leaves.iter().map(|l| (l.origin, l.clone())).collect();
        for &(v, delta) in deltas {
            if !self.slots.contains_key(v >> 3) {
                continue;
            }
            let origin = v & !7;
            let leaf = leaves
                .entry(origin)
                .or_insert_with(|| match self.brick(v >> 3) {
                    Brick::Constant(c) => Leaf {
                        origin,
                        values: [c; BRICK_VOXELS],
                        active: [u64::MAX; 8],
                    },
                    _ => Leaf {
                        origin,
                        values: [0.0; BRICK_VOXELS],
                        active: [0; 8],
                    },
                });
            leaf.values[leaf_offset(v & 7)] += delta;
        }
        let mut leaves: Vec<Leaf> = leaves.into_values().collect();
        leaves.sort_by_key(|l| (l.origin.x, l.origin.y, l.origin.z));
        BrickMap::new(leaves, self.tiles.clone())
    }

    /// Largest stored value (0 for an empty grid).
    pub fn max_value(&self) -> f32 {
        self.value_range.1
    }

    /// Smallest stored value (0 for an empty grid).
    pub fn min_value(&self) -> f32 {
        self.value_range.0
    }

    pub fn active_voxel_count(&self) -> u64 {
        let in_leaves: u64 = self
            .leaves
            .iter()
            .map(|l| l.active.iter().map(|w| w.count_ones() as u64).sum::<u64>())
            .sum();
        in_leaves
            + self
                .tiles
                .iter()
                .map(|t| (t.size as u64).pow(3))
                .sum::<u64>()
    }
}

/// Bricks a flat slot table may cover: 16 per leaf or tile (64 bytes next to a leaf's 2 KiB, 3 %),
/// or 2¹² (16 KiB) for tiny grids. Beyond it the table is a sparse index.
fn flat_slot_budget(leaves: &[Leaf], tiles: &[Tile]) -> u64 {
    (16 * (leaves.len() + tiles.len()) as u64).max(1 << 12)
}

/// The brick holding voxel `v`, for voxel coordinates one step beyond the i32 range (an apron).
fn brick_of_i64(v: glam::I64Vec3) -> IVec3 {
    (v >> 3i64).as_ivec3()
}

/// ⌊p⌋ per axis without a libm call (x86-64 without SSE4.1 has no floor instruction); index
/// coordinates are far inside the i32 range.
#[inline]
pub fn floor_ivec3(p: Vec3) -> IVec3 {
    let i = p.as_ivec3(); // truncates toward zero
    i - IVec3::from(p.cmplt(i.as_vec3()))
}

/// Corner k of a trilinear cell: bit 2 → +x, bit 1 → +y, bit 0 → +z.
#[inline]
pub fn corner(k: usize) -> IVec3 {
    IVec3::new((k >> 2) as i32 & 1, (k >> 1) as i32 & 1, k as i32 & 1)
}

/// The trilinear field of a cell's corner values `c` (from `cell_corners`) at fractions `f`:
/// along z, then y, then x (corner k has bits x = 4, y = 2, z = 1).
#[inline(always)]
pub fn interpolate(c: &[f32; 8], f: Vec3) -> f32 {
    let z00 = c[0] + (c[1] - c[0]) * f.z;
    let z01 = c[2] + (c[3] - c[2]) * f.z;
    let z10 = c[4] + (c[5] - c[4]) * f.z;
    let z11 = c[6] + (c[7] - c[6]) * f.z;
    let y0 = z00 + (z01 - z00) * f.y;
    let y1 = z10 + (z11 - z10) * f.y;
    y0 + (y1 - y0) * f.x
}

/// The eight corner values of the trilinear cell at leaf coordinate `local` (all inside the leaf).
#[inline(always)]
fn leaf_corners(values: &[f32; BRICK_VOXELS], local: IVec3) -> [f32; 8] {
    let o = leaf_offset(local);
    std::array::from_fn(|k| values[o + CORNER_OFFSETS[k]])
}

/// Leaf offsets of the eight corners of a trilinear cell, relative to its base voxel.
pub const CORNER_OFFSETS: [usize; 8] = [0, 1, 8, 9, 64, 65, 72, 73];

/// The smallest and largest of the values and 0. Once, at construction: a load checks both, and
/// a fold over every value is a chain of dependent min/max (≈ 25 ms per 100 MiB), so the leaves
/// are scanned in parallel, each in eight independent lanes.
fn value_range(leaves: &[Leaf], tiles: &[Tile]) -> (f32, f32) {
    let widen = |a: (f32, f32), b: (f32, f32)| (a.0.min(b.0), a.1.max(b.1));
    let in_leaves = leaves
        .par_iter()
        .map(|leaf| {
            let (mut lo, mut hi) = ([0.0f32; 8], [0.0f32; 8]);
            for lane in leaf.values.chunks_exact(8) {
                for ((l, h), &v) in lo.iter_mut().zip(&mut hi).zip(lane) {
                    *l = l.min(v);
                    *h = h.max(v);
                }
            }
            lo.iter()
                .zip(&hi)
                .fold((0.0, 0.0), |r, (&l, &h)| widen(r, (l, h)))
        })
        .reduce(|| (0.0, 0.0), widen);
    tiles
        .iter()
        .fold(in_leaves, |r, t| widen(r, (t.value, t.value)))
}

/// The inclusive box of the active voxels of the leaves and tiles. In parallel, and per leaf from
/// its mask words (word x holds row x, bit y·8 + z): testing each voxel's bit was a third of a
/// large grid's load.
fn active_bounds(leaves: &[Leaf], tiles: &[Tile]) -> Option<(IVec3, IVec3)> {
    let widen = |a: (IVec3, IVec3), b: (IVec3, IVec3)| (a.0.min(b.0), a.1.max(b.1));
    let empty = (IVec3::splat(i32::MAX), IVec3::splat(i32::MIN));
    let in_leaves = leaves
        .par_iter()
        .filter_map(leaf_active_box)
        .reduce(|| empty, widen);
    let (lo, hi) = tiles.iter().fold(in_leaves, |r, t| {
        widen(r, (t.origin, t.origin + IVec3::splat(t.size as i32 - 1)))
    });
    (lo.cmple(hi).all()).then_some((lo, hi))
}

/// The inclusive box of `leaf`'s active voxels, `None` if it has none.
fn leaf_active_box(leaf: &Leaf) -> Option<(IVec3, IVec3)> {
    let x0 = leaf.active.iter().position(|&w| w != 0)? as i32;
    let x1 = leaf.active.iter().rposition(|&w| w != 0)? as i32;
    let rows = leaf.active.iter().fold(0u64, |a, &w| a | w); // bit y·8 + z: some x has (y, z)
    let (y0, y1) = (rows.trailing_zeros() / 8, (63 - rows.leading_zeros()) / 8);
    let mut columns = rows; // bit z of the low byte: some (x, y) has z
    columns |= columns >> 32;
    columns |= columns >> 16;
    columns |= columns >> 8;
    let columns = columns as u8;
    let (z0, z1) = (columns.trailing_zeros(), 7 - columns.leading_zeros());
    Some((
        leaf.origin + IVec3::new(x0, y0 as i32, z0 as i32),
        leaf.origin + IVec3::new(x1, y1 as i32, z1 as i32),
    ))
}

/// Collects voxels one at a time (grid generators, gradient export) and produces a `BrickMap`.
/// Not for hot loops: it hashes.
#[derive(Default, Clone)]
pub struct BrickMapBuilder {
    leaves: HashMap<IVec3, Leaf>,
}

impl BrickMapBuilder {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn set(&mut self, v: IVec3, value: f32, active: bool) {
        let origin = v & !7;
        let leaf = self.leaves.entry(origin).or_insert_with(|| Leaf {
            origin,
            values: [0.0; BRICK_VOXELS],
            active: [0; 8],
        });
        let o = leaf_offset(v & 7);
        leaf.values[o] = value;
        if active {
            leaf.active[o >> 6] |= 1u64 << (o & 63);
        } else {
            leaf.active[o >> 6] &= !(1u64 << (o & 63));
        }
    }

    pub fn build(self) -> BrickMap {
        let mut leaves: Vec<Leaf> = self.leaves.into_values().collect();
        leaves.sort_by_key(|l| (l.origin.x, l.origin.y, l.origin.z));
        BrickMap::new(leaves, Vec::new())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp() -> BrickMap {
        // value = x + 10 y + 100 z over a 20³ block, crossing brick boundaries.
        let mut b = BrickMapBuilder::new();
        for x in -4..16 {
            for y in -4..16 {
                for z in -4..16 {
                    b.set(IVec3::new(x, y, z), (x + 10 * y + 100 * z) as f32, true);
                }
            }
        }
        b.build()
    }

    #[test]
    fn trilinear_reproduces_linear_fields_across_bricks() {
        let m = ramp();
        for p in [
            Vec3::new(0.25, 0.5, 0.75),
            Vec3::new(7.3, 7.9, 6.5),
            Vec3::new(-0.5, 3.2, 7.99),
            Vec3::new(12.0, 1.0, 2.0),
        ] {
            let expect = p.x + 10.0 * p.y + 100.0 * p.z;
            assert!(
                (m.trilinear(p) - expect).abs() < 1e-3,
                "{p}: {} vs {expect}",
                m.trilinear(p)
            );
        }
    }

    #[test]
    fn nearest_picks_the_voxel_whose_cell_contains_the_point() {
        let m = ramp();
        assert_eq!(m.nearest(Vec3::new(2.49, 3.51, -0.49)), (2 + 40) as f32);
        assert_eq!(m.nearest(Vec3::new(7.6, 0.0, 0.0)), 8.0);
    }

    #[test]
    fn the_value_range_spans_leaves_tiles_and_zero() {
        // The ramp x + 10 y + 100 z over -4..16 in each axis.
        let m = ramp();
        assert_eq!((m.min_value(), m.max_value()), (-444.0, 1665.0));
        let mut leaf = m.leaves()[0].clone();
        leaf.values = [0.5; BRICK_VOXELS];
        leaf.values[77] = 3.0;
        let tile = Tile {
            origin: IVec3::new(64, 0, 0),
            size: 16,
            value: 2.0,
        };
        let m = BrickMap::new(vec![leaf.clone()], vec![tile]);
        assert_eq!((m.min_value(), m.max_value()), (0.0, 3.0));
        let tile = Tile {
            value: -7.0,
            ..tile
        };
        let m = BrickMap::new(vec![leaf], vec![tile]);
        assert_eq!((m.min_value(), m.max_value()), (-7.0, 3.0));
        assert_eq!(BrickMap::new(Vec::new(), Vec::new()).max_value(), 0.0);
    }

    #[test]
    fn tiles_are_constant_and_outside_is_zero() {
        let tile = Tile {
            origin: IVec3::new(128, 0, 0),
            size: 128,
            value: 2.5,
        };
        let m = BrickMap::new(Vec::new(), vec![tile]);
        assert_eq!(m.voxel(IVec3::new(200, 5, 127)), 2.5);
        assert_eq!(m.trilinear(Vec3::new(150.5, 60.2, 3.3)), 2.5);
        assert!(m.is_active(IVec3::new(255, 127, 127)));
        assert_eq!(m.voxel(IVec3::new(256, 5, 5)), 0.0);
        assert_eq!(m.voxel(IVec3::new(-100000, 5, 5)), 0.0);
        assert_eq!(
            m.active_bounds(),
            Some((IVec3::new(128, 0, 0), IVec3::new(255, 127, 127)))
        );
        // Constant tiles are not voxelised.
        assert!(m.memory_bytes() < 4 * 20 * 20 * 20 + 1024);
    }

    #[test]
    fn leaf_offsets_follow_openvdb() {
        assert_eq!(leaf_offset(IVec3::new(1, 2, 3)), 64 + 16 + 3);
        let mut b = BrickMapBuilder::new();
        b.set(IVec3::new(-1, 9, 17), 4.0, true);
        let m = b.build();
        assert_eq!(m.leaves()[0].origin, IVec3::new(-8, 8, 16));
        assert_eq!(m.leaves()[0].values[leaf_offset(IVec3::new(7, 1, 1))], 4.0);
        assert_eq!(m.active_voxel_count(), 1);
    }

    #[test]
    fn a_leafs_active_box_is_read_from_its_mask_words() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::SmallRng::seed_from_u64(7);
        for case in 0..200 {
            // A few active voxels (one, for the edge cases at the corners, every 50th case).
            let mut leaf = Leaf {
                origin: IVec3::new(-16, 8, 24),
                values: [0.0; BRICK_VOXELS],
                active: [0; 8],
            };
            let count = if case % 50 == 0 {
                1
            } else {
                rng.gen_range(1..6)
            };
            for _ in 0..count {
                let o = rng.gen_range(0..BRICK_VOXELS);
                leaf.active[o >> 6] |= 1 << (o & 63);
            }
            let (mut lo, mut hi) = (IVec3::splat(i32::MAX), IVec3::splat(i32::MIN));
            for o in 0..BRICK_VOXELS {
                if leaf.active[o >> 6] >> (o & 63) & 1 == 1 {
                    let v = leaf.origin
                        + IVec3::new((o >> 6) as i32, ((o >> 3) & 7) as i32, (o & 7) as i32);
                    (lo, hi) = (lo.min(v), hi.max(v));
                }
            }
            assert_eq!(leaf_active_box(&leaf), Some((lo, hi)), "case {case}");
        }
        let none = Leaf {
            origin: IVec3::ZERO,
            values: [1.0; BRICK_VOXELS],
            active: [0; 8],
        };
        assert_eq!(leaf_active_box(&none), None);
    }
}
