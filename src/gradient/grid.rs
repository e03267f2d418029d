//! Sparse accumulation of per-voxel gradients: bricks appear where gradient arrives. The brick
//! index (a `SparseIndex`, memory proportional to the bricks touched, whatever the bounding box)
//! accepts the medium's brick range (the active box plus the trilinear apron), so every voxel a
//! lookup can weight has a place; accumulation is a few array reads plus, the first time a brick is
//! touched, one allocation.
//!
//! The value type is a parameter: a pass splats into per-band f32 grids (half the memory traffic of
//! the scattered adds that dominate its bookkeeping, and half the memory per band) and reduces them
//! into an f64 grid, where sums over many bands and runs keep their precision.

use std::ops::{AddAssign, Mul};

use glam::IVec3;

use crate::volume::brickmap::{
    corner, floor_ivec3, leaf_offset, BrickMap, Leaf, BRICK_VOXELS, CORNER_OFFSETS,
};
use crate::volume::medium::Medium;
use crate::volume::sparse_index::SparseIndex;

/// A value a gradient grid accumulates: f32 for a pass's splats, f64 for results.
pub trait Accumulator:
    Copy + Default + PartialEq + AddAssign + Mul<Output = Self> + Send + Sync + 'static
{
    fn from_f32(v: f32) -> Self;
    fn from_f64(v: f64) -> Self;
    fn to_f64(self) -> f64;
}

impl Accumulator for f32 {
    fn from_f32(v: f32) -> Self {
        v
    }
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
}

impl Accumulator for f64 {
    fn from_f32(v: f32) -> Self {
        v as f64
    }
    fn from_f64(v: f64) -> Self {
        v
    }
    fn to_f64(self) -> f64 {
        self
    }
}

#[derive(Clone)]
pub struct GradientGrid<T: Accumulator = f64> {
    /// Inclusive brick range accepted (voxels beyond it are never weighted by a lookup).
    brick_lo: IVec3,
    brick_hi: IVec3,
    /// Brick coordinates → index + 1 into `bricks` (0 = no brick yet).
    slots: SparseIndex,
    bricks: Vec<(IVec3, Box<[T; BRICK_VOXELS]>)>,
}

impl<T: Accumulator> GradientGrid<T> {
    /// An empty accumulator covering the voxels from `lo` to `hi` (inclusive).
    pub fn new(lo: IVec3, hi: IVec3) -> Self {
        Self::with_flat_budget(lo, hi, 1 << 12)
    }

    /// As `new`; the brick index is one flat table when the box holds at most `flat_budget`
    /// bricks (one array read per lookup), a sparse index otherwise.
    fn with_flat_budget(lo: IVec3, hi: IVec3, flat_budget: u64) -> Self {
        let (brick_lo, brick_hi) = (lo >> 3i32, hi >> 3i32);
        GradientGrid {
            brick_lo,
            brick_hi,
            slots: SparseIndex::with_flat_budget(brick_lo, brick_hi, flat_budget),
            bricks: Vec::new(),
        }
    }

    /// Covers every voxel a lookup in `grid`'s medium can weight.
    pub fn for_grid(grid: &BrickMap) -> Self {
        match grid.active_bounds() {
            // The brick map's flat-table rule: at most 16 slots per leaf.
            Some((lo, hi)) => Self::with_flat_budget(
                lo.saturating_sub(IVec3::ONE),
                hi.saturating_add(IVec3::ONE),
                (16 * grid.leaves().len() as u64).max(1 << 12),
            ),
            None => Self::new(IVec3::ZERO, IVec3::splat(-1)),
        }
    }

    /// Covers every voxel a lookup inside `medium`'s bounds can weight (the same as `for_grid` for
    /// a medium that ends at its active voxels; an optimisation's fixed domain otherwise).
    pub fn for_medium(medium: &Medium) -> Self {
        let (lo, hi) = medium.bounds;
        if !(lo.cmplt(hi).all()) {
            return Self::new(IVec3::ZERO, IVec3::splat(-1));
        }
        // A trilinear lookup at p weights the voxels floor(p) and floor(p) + 1 (voxel centres sit
        // at integer indices).
        let first = floor_ivec3(lo);
        let last = floor_ivec3(hi).saturating_add(IVec3::ONE);
        Self::with_flat_budget(
            first,
            last,
            (16 * medium.grid.leaves().len() as u64).max(1 << 12),
        )
    }

    /// An empty accumulator of the same extent.
    pub fn empty_like(&self) -> Self {
        GradientGrid {
            brick_lo: self.brick_lo,
            brick_hi: self.brick_hi,
            slots: self.slots.empty_like(),
            bricks: Vec::new(),
        }
    }

    /// The values of the brick holding voxel `v`, created on first touch; `None` outside the
    /// extent.
    #[inline]
    fn brick_mut(&mut self, v: IVec3) -> Option<&mut [T; BRICK_VOXELS]> {
        let slot = self.slots.slot_mut(v >> 3)?;
        if *slot == 0 {
            self.bricks
                .push((v & !7, Box::new([T::default(); BRICK_VOXELS])));
            *slot = self.bricks.len() as u32;
        }
        let index = *slot as usize - 1;
        Some(&mut self.bricks[index].1)
    }

    /// Adds `value` to voxel `v`; voxels outside the extent are ignored (no lookup reaches them).
    #[inline]
    pub fn add(&mut self, v: IVec3, value: T) {
        if let Some(values) = self.brick_mut(v) {
            values[leaf_offset(v & 7)] += value;
        }
    }

    /// Adds `weights[k] · value` to corner k of the trilinear cell at `base`, resolving the brick
    /// once when the cell does not straddle bricks.
    #[inline]
    pub fn add_cell(&mut self, base: IVec3, weights: &[f32; 8], value: T) {
        if (base & 7).cmplt(IVec3::splat(7)).all() {
            let Some(values) = self.brick_mut(base) else {
                return;
            };
            let o = leaf_offset(base & 7);
            for (k, &w) in weights.iter().enumerate() {
                values[o + CORNER_OFFSETS[k]] += T::from_f32(w) * value;
            }
        } else {
            for (k, &w) in weights.iter().enumerate() {
                if w > 0.0 {
                    self.add(base + corner(k), T::from_f32(w) * value);
                }
            }
        }
    }

    pub fn get(&self, v: IVec3) -> f64 {
        match self.slots.get(v >> 3) {
            0 => 0.0,
            i => self.bricks[i as usize - 1].1[leaf_offset(v & 7)].to_f64(),
        }
    }

    pub fn brick_count(&self) -> usize {
        self.bricks.len()
    }

    /// Bytes held: the bricks' values and the brick index.
    pub fn memory_bytes(&self) -> usize {
        self.bricks.len()
            * (std::mem::size_of::<(IVec3, Box<[T; BRICK_VOXELS]>)>()
                + std::mem::size_of::<[T; BRICK_VOXELS]>())
            + self.slots.memory_bytes()
    }

    /// `self += weight · other` (same extent), brick by brick, computed in f64.
    pub fn merge<U: Accumulator>(&mut self, other: &GradientGrid<U>, weight: f64) {
        assert_eq!(
            (self.brick_lo, self.brick_hi),
            (other.brick_lo, other.brick_hi),
            "gradient grids of different extents"
        );
        for (origin, values) in &other.bricks {
            let mine = self.brick_mut(*origin).expect("same extent");
            for (m, v) in mine.iter_mut().zip(values.iter()) {
                *m = T::from_f64(m.to_f64() + weight * v.to_f64());
            }
        }
    }

    pub fn scale(&mut self, factor: f64) {
        for (_, values) in &mut self.bricks {
            for v in values.iter_mut() {
                *v = T::from_f64(v.to_f64() * factor);
            }
        }
    }

    /// Every voxel with a stored (possibly zero) value.
    pub fn voxels(&self) -> impl Iterator<Item = (IVec3, f64)> + '_ {
        self.bricks.iter().flat_map(|(origin, values)| {
            values
                .iter()
                .enumerate()
                .map(move |(o, &v)| (*origin + offset_voxel(o), v.to_f64()))
        })
    }

    /// ⟨g, 1⟩ over the voxels inside the inclusive box `[lo, hi]`.
    pub fn sum_in_box(&self, lo: IVec3, hi: IVec3) -> f64 {
        self.voxels()
            .filter(|(v, _)| v.cmpge(lo).all() && v.cmple(hi).all())
            .map(|(_, g)| g)
            .sum()
    }

    pub fn sum(&self) -> f64 {
        self.voxels().map(|(_, g)| g).sum()
    }

    /// As a brick map of f32 values for export: voxels that received a non-zero gradient are
    /// active. Built brick by brick (no per-voxel map): the export of a large gradient must not
    /// hold it twice over.
    pub fn to_brickmap(&self) -> BrickMap {
        let mut leaves = Vec::with_capacity(self.bricks.len());
        leaves.extend(self.bricks.iter().filter_map(|(origin, values)| {
            let mut leaf = Leaf {
                origin: *origin,
                values: [0.0; BRICK_VOXELS],
                active: [0; 8],
            };
            for (o, v) in values.iter().enumerate() {
                let g = v.to_f64() as f32;
                if g != 0.0 {
                    leaf.values[o] = g;
                    leaf.active[o >> 6] |= 1 << (o & 63);
                }
            }
            leaf.active.iter().any(|&w| w != 0).then_some(leaf)
        }));
        BrickMap::new(leaves, Vec::new())
    }
}

#[inline]
fn offset_voxel(o: usize) -> IVec3 {
    IVec3::new((o >> 6) as i32, ((o >> 3) & 7) as i32, (o & 7) as i32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accumulates_sparsely_and_merges() {
        let mut g = GradientGrid::new(IVec3::splat(-10), IVec3::splat(30));
        g.add(IVec3::new(-9, 0, 3), 1.5);
        g.add(IVec3::new(-9, 0, 3), 1.0);
        g.add(IVec3::new(29, 29, 29), -2.0);
        g.add(IVec3::new(500, 0, 0), 7.0); // outside: ignored
        assert_eq!(g.brick_count(), 2);
        assert_eq!(g.get(IVec3::new(-9, 0, 3)), 2.5);
        let mut h = g.empty_like();
        h.merge(&g, 0.5);
        h.merge(&g, 0.5);
        assert_eq!(h.get(IVec3::new(29, 29, 29)), -2.0);
        // A cell inside one brick and one straddling bricks give the same per-corner sums.
        let weights = [0.1, 0.2, 0.05, 0.15, 0.1, 0.1, 0.2, 0.1];
        for base in [IVec3::new(1, 2, 3), IVec3::new(7, 7, 7)] {
            let mut a = g.empty_like();
            a.add_cell(base, &weights, 2.0);
            for (k, &w) in weights.iter().enumerate() {
                assert!((a.get(base + corner(k)) - 2.0 * w as f64).abs() < 1e-7);
            }
        }
        assert_eq!(h.sum(), 0.5);
        assert_eq!(h.sum_in_box(IVec3::splat(0), IVec3::splat(29)), -2.0);
        let map = h.to_brickmap();
        assert_eq!(map.active_voxel_count(), 2);
        assert_eq!(map.voxel(IVec3::new(-9, 0, 3)), 2.5);
    }
}
