//! Sparse accumulation of per-voxel gradients: bricks appear where gradient arrives. The brick
//! table covers the medium's slot range (the active box plus the trilinear apron), so every voxel a
//! lookup can weight has a place; accumulation is two array reads plus, the first time a brick is
//! touched, one allocation.

use glam::IVec3;

use crate::volume::brickmap::{
    corner, leaf_offset, BrickMap, BrickMapBuilder, BRICK_VOXELS, CORNER_OFFSETS,
};

#[derive(Clone)]
pub struct GradientGrid {
    slot_origin: IVec3,
    slot_dims: IVec3,
    /// 0 = no brick yet, otherwise index + 1 into `bricks`.
    slots: Vec<u32>,
    bricks: Vec<(IVec3, Box<[f64; BRICK_VOXELS]>)>,
}

impl GradientGrid {
    /// An empty accumulator covering the voxels from `lo` to `hi` (inclusive).
    pub fn new(lo: IVec3, hi: IVec3) -> Self {
        let (a, b) = (lo >> 3i32, hi >> 3i32);
        let slot_dims = (b - a + 1).max(IVec3::ZERO);
        GradientGrid {
            slot_origin: a,
            slot_dims,
            slots: vec![0; (slot_dims.x * slot_dims.y * slot_dims.z) as usize],
            bricks: Vec::new(),
        }
    }

    /// Covers every voxel a lookup in `grid`'s medium can weight.
    pub fn for_grid(grid: &BrickMap) -> Self {
        match grid.active_bounds() {
            Some((lo, hi)) => Self::new(lo - 1, hi + 1),
            None => Self::new(IVec3::ZERO, IVec3::splat(-1)),
        }
    }

    /// An empty accumulator of the same extent.
    pub fn empty_like(&self) -> Self {
        GradientGrid {
            slot_origin: self.slot_origin,
            slot_dims: self.slot_dims,
            slots: vec![0; self.slots.len()],
            bricks: Vec::new(),
        }
    }

    #[inline]
    fn slot(&self, brick: IVec3) -> Option<usize> {
        let b = brick - self.slot_origin;
        if b.cmplt(IVec3::ZERO).any() || b.cmpge(self.slot_dims).any() {
            return None;
        }
        Some(((b.x * self.slot_dims.y + b.y) * self.slot_dims.z + b.z) as usize)
    }

    /// Adds `value` to voxel `v`; voxels outside the extent are ignored (no lookup reaches them).
    #[inline]
    pub fn add(&mut self, v: IVec3, value: f64) {
        let Some(slot) = self.slot(v >> 3) else {
            return;
        };
        if self.slots[slot] == 0 {
            self.bricks.push((v & !7, Box::new([0.0; BRICK_VOXELS])));
            self.slots[slot] = self.bricks.len() as u32;
        }
        self.bricks[self.slots[slot] as usize - 1].1[leaf_offset(v & 7)] += value;
    }

    /// Adds `weights[k] · value` to corner k of the trilinear cell at `base`, resolving the brick
    /// once when the cell does not straddle bricks.
    #[inline]
    pub fn add_cell(&mut self, base: IVec3, weights: &[f32; 8], value: f64) {
        if (base & 7).cmplt(IVec3::splat(7)).all() {
            let Some(slot) = self.slot(base >> 3) else {
                return;
            };
            if self.slots[slot] == 0 {
                self.bricks.push((base & !7, Box::new([0.0; BRICK_VOXELS])));
                self.slots[slot] = self.bricks.len() as u32;
            }
            let values = &mut self.bricks[self.slots[slot] as usize - 1].1;
            let o = leaf_offset(base & 7);
            for (k, &w) in weights.iter().enumerate() {
                values[o + CORNER_OFFSETS[k]] += w as f64 * value;
            }
        } else {
            for (k, &w) in weights.iter().enumerate() {
                if w > 0.0 {
                    self.add(base + corner(k), w as f64 * value);
                }
            }
        }
    }

    pub fn get(&self, v: IVec3) -> f64 {
        match self.slot(v >> 3).map(|s| self.slots[s]) {
            Some(i) if i > 0 => self.bricks[i as usize - 1].1[leaf_offset(v & 7)],
            _ => 0.0,
        }
    }

    /// `self += weight · other` (same extent), brick by brick.
    pub fn merge(&mut self, other: &GradientGrid, weight: f64) {
        assert_eq!(
            self.slot_dims, other.slot_dims,
            "gradient grids of different extents"
        );
        for (origin, values) in &other.bricks {
            let slot = self.slot(*origin >> 3).expect("same extent");
            if self.slots[slot] == 0 {
                self.bricks.push((*origin, Box::new([0.0; BRICK_VOXELS])));
                self.slots[slot] = self.bricks.len() as u32;
            }
            let mine = &mut self.bricks[self.slots[slot] as usize - 1].1;
            for (m, v) in mine.iter_mut().zip(values.iter()) {
                *m += weight * v;
            }
        }
    }

    pub fn scale(&mut self, factor: f64) {
        for (_, values) in &mut self.bricks {
            for v in values.iter_mut() {
                *v *= factor;
            }
        }
    }

    /// Every voxel with a stored (possibly zero) value.
    pub fn voxels(&self) -> impl Iterator<Item = (IVec3, f64)> + '_ {
        self.bricks.iter().flat_map(|(origin, values)| {
            values
                .iter()
                .enumerate()
                .map(move |(o, &v)| (*origin + offset_voxel(o), v))
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

    pub fn brick_count(&self) -> usize {
        self.bricks.len()
    }

    /// As a brick map of f32 values for export: voxels that received a non-zero gradient are
    /// active.
    pub fn to_brickmap(&self) -> BrickMap {
        let mut b = BrickMapBuilder::new();
        for (v, g) in self.voxels() {
            if g != 0.0 {
                b.set(v, g as f32, true);
            }
        }
        b.build()
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
