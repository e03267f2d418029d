//! Where a wide medium's data lie: a few disjoint boxes of majorant cells that hold every cell a
//! leaf or a tile reaches, so that a walk crosses the empty space between them in one jump.
//!
//! A medium whose data are in clusters far apart (a plume and a stray wisp a few thousand voxels
//! away, two assets in one file) has a box far larger than its data. One flat array of cells
//! over that box would be too large, and a walk over blocks steps through every empty index node
//! between the clusters. Boxes around the clusters keep the flat arrays (`majorant_cells`) and
//! their walk (`majorant_walk`) at the size of the data.

use glam::{I64Vec3, IVec3};
use std::collections::HashMap;

use crate::volume::brickmap::{BrickMap, BRICK_EDGE};

/// The most boxes a medium is cut into: a walk tests the ray against each of them.
pub const MAX_CLUSTERS: usize = 16;

/// Leaves are first gathered into groups of this many voxels per edge (log2), one box per group:
/// the merging below is quadratic in the boxes, and a group's leaves are close anyway.
const GROUP_LOG2: i32 = 7;

/// Beyond this many groups the data are spread too finely for a few boxes: the blocks serve.
const MAX_GROUPS: usize = 4096;

/// Beyond this many boxes left once neighbours have merged, the data are in too many clusters to
/// merge pair by pair into a few (each merge is quadratic in the boxes): the blocks serve.
const MAX_TO_MERGE: usize = 4 * MAX_CLUSTERS;

/// An inclusive box of cells.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CellBox {
    pub lo: IVec3,
    pub hi: IVec3,
}

impl CellBox {
    /// How many cells it holds (saturating: a box may span the whole i32 range).
    pub fn cells(&self) -> u64 {
        let d = (self.hi.as_i64vec3() - self.lo.as_i64vec3() + 1).max(I64Vec3::ZERO);
        let n = d.x as u128 * d.y as u128 * d.z as u128;
        n.min(u64::MAX as u128) as u64
    }

    fn union(&self, o: &CellBox) -> CellBox {
        CellBox {
            lo: self.lo.min(o.lo),
            hi: self.hi.max(o.hi),
        }
    }

    fn intersects(&self, o: &CellBox) -> bool {
        self.lo.cmple(o.hi).all() && o.lo.cmple(self.hi).all()
    }

    /// Cells the union holds beyond the two boxes' own.
    fn union_waste(&self, o: &CellBox) -> u64 {
        self.union(o)
            .cells()
            .saturating_sub(self.cells().saturating_add(o.cells()))
    }
}

/// Disjoint boxes of cells (edge `s` voxels, clipped to the box `c_lo ..= c_hi`) holding every
/// cell the apron-grown footprint of a leaf or a tile of `bricks` reaches, at most
/// `MAX_CLUSTERS` of them and `budget` cells together; `None` when the data need more.
pub fn find(
    bricks: &BrickMap,
    s: i32,
    c_lo: IVec3,
    c_hi: IVec3,
    budget: u64,
) -> Option<Vec<CellBox>> {
    // A voxel range's trilinear reach in cells (one voxel of apron), in i64: a leaf at the edge
    // of the i32 range must not wrap around.
    let s64 = I64Vec3::splat(s as i64);
    let footprint = |lo: IVec3, hi: IVec3| {
        let lo = (lo.as_i64vec3() - 1).div_euclid(s64).max(c_lo.as_i64vec3());
        let hi = (hi.as_i64vec3() + 1).div_euclid(s64).min(c_hi.as_i64vec3());
        lo.cmple(hi).all().then(|| CellBox {
            lo: lo.as_ivec3(),
            hi: hi.as_ivec3(),
        })
    };
    let mut groups: HashMap<IVec3, CellBox> = HashMap::new();
    for leaf in bricks.leaves() {
        let last = leaf.origin.saturating_add(IVec3::splat(BRICK_EDGE - 1));
        if let Some(b) = footprint(leaf.origin, last) {
            groups
                .entry(leaf.origin >> GROUP_LOG2)
                .and_modify(|g| *g = g.union(&b))
                .or_insert(b);
        }
        if groups.len() > MAX_GROUPS {
            return None;
        }
    }
    let mut boxes: Vec<CellBox> = groups.into_values().collect();
    for tile in bricks.tiles() {
        let last = tile
            .origin
            .saturating_add(IVec3::splat(tile.size as i32 - 1));
        boxes.extend(footprint(tile.origin, last));
    }
    if boxes.len() > MAX_GROUPS {
        return None;
    }
    // The same boxes whatever the hash map's order.
    boxes.sort_unstable_by_key(|b| (b.lo.to_array(), b.hi.to_array()));
    let cells = |boxes: &[CellBox]| {
        boxes
            .iter()
            .fold(0u64, |sum, b| sum.saturating_add(b.cells()))
    };
    loop {
        merge_neighbours(&mut boxes);
        // Disjoint now, and merging only grows them: their cells only add up to more from here.
        if boxes.len() > MAX_TO_MERGE || cells(&boxes) > budget {
            return None;
        }
        if boxes.len() <= MAX_CLUSTERS {
            return Some(boxes);
        }
        merge_cheapest_pair(&mut boxes);
    }
}

/// Merges, until none is left, every pair of boxes that intersect (the result must be disjoint)
/// or whose union holds at most as many empty cells as the two boxes hold together (pieces of one
/// cluster: cheaper walked as one).
fn merge_neighbours(boxes: &mut Vec<CellBox>) {
    let mut merged = true;
    while merged {
        merged = false;
        let mut i = 0;
        while i < boxes.len() {
            let mut j = i + 1;
            while j < boxes.len() {
                let (a, b) = (boxes[i], boxes[j]);
                if a.intersects(&b) || a.union_waste(&b) <= a.cells().saturating_add(b.cells()) {
                    boxes[i] = a.union(&b);
                    boxes.swap_remove(j);
                    merged = true;
                    j = i + 1; // box i grew: test it against the rest again
                } else {
                    j += 1;
                }
            }
            i += 1;
        }
    }
}

/// Merges the two boxes whose union adds the fewest empty cells.
fn merge_cheapest_pair(boxes: &mut Vec<CellBox>) {
    let mut best = (u64::MAX, 0, 1);
    for i in 0..boxes.len() {
        for j in i + 1..boxes.len() {
            let waste = boxes[i].union_waste(&boxes[j]);
            if waste < best.0 {
                best = (waste, i, j);
            }
        }
    }
    let (_, i, j) = best;
    boxes[i] = boxes[i].union(&boxes[j]);
    boxes.swap_remove(j);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::brickmap::{BrickMapBuilder, Tile};

    fn cluster_map(centres: &[IVec3]) -> BrickMap {
        let mut b = BrickMapBuilder::new();
        for &c in centres {
            for k in 0..64 {
                b.set(c + IVec3::new(k % 4, (k / 4) % 4, k / 16) * 5, 1.0, true);
            }
        }
        b.build()
    }

    #[test]
    fn far_clusters_get_boxes_of_their_own_that_hold_every_reached_cell() {
        let centres = [
            IVec3::ZERO,
            IVec3::new(5000, -3000, 40),
            IVec3::new(-70000, 0, 9),
        ];
        let m = cluster_map(&centres);
        let (lo, hi) = m.active_bounds().unwrap();
        let s = 4;
        let c_lo = (lo - 1).div_euclid(IVec3::splat(s));
        let c_hi = (hi + 1).div_euclid(IVec3::splat(s));
        let boxes = find(&m, s, c_lo, c_hi, u64::MAX).unwrap();
        assert_eq!(boxes.len(), 3, "{boxes:?}");
        for (i, a) in boxes.iter().enumerate() {
            assert!(a.cells() < 20 * 20 * 20, "{a:?}");
            assert!(boxes[i + 1..].iter().all(|b| !a.intersects(b)));
        }
        // Every cell a voxel's trilinear reach touches lies in a box.
        for leaf in m.leaves() {
            for corner in [IVec3::ZERO, IVec3::splat(7)] {
                let v = leaf.origin + corner;
                for reach in [v - 1, v + 1] {
                    let cell = reach.div_euclid(IVec3::splat(s));
                    assert!(boxes
                        .iter()
                        .any(|b| b.lo.cmple(cell).all() && cell.cmple(b.hi).all()));
                }
            }
        }
        // The budget is the boxes' cells together.
        let cells: u64 = boxes.iter().map(CellBox::cells).sum();
        assert_eq!(find(&m, s, c_lo, c_hi, cells).map(|b| b.len()), Some(3));
        assert_eq!(find(&m, s, c_lo, c_hi, cells - 1), None);
    }

    #[test]
    fn near_pieces_merge_and_many_clusters_are_capped() {
        // Two pieces of one cluster (a gap of two cells) are walked as one box.
        let m = cluster_map(&[IVec3::ZERO, IVec3::new(24, 0, 0)]);
        let boxes = find(&m, 4, IVec3::splat(-100), IVec3::splat(100), u64::MAX).unwrap();
        assert_eq!(boxes.len(), 1);
        // Forty clusters strewn over a wide box become at most MAX_CLUSTERS disjoint boxes.
        let mut state = 5u32;
        let mut r = || {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            (state >> 8) as i32 % 12000
        };
        let strewn: Vec<IVec3> = (0..40).map(|_| IVec3::new(r(), r(), r()) & !7).collect();
        let m = cluster_map(&strewn);
        let boxes = find(&m, 4, IVec3::splat(-10), IVec3::splat(3000), u64::MAX).unwrap();
        assert!(
            boxes.len() <= MAX_CLUSTERS && boxes.len() > 1,
            "{}",
            boxes.len()
        );
        for (i, a) in boxes.iter().enumerate() {
            assert!(boxes[i + 1..].iter().all(|b| !a.intersects(b)));
        }
        // Thousands of specks far apart are too many clusters: the blocks serve, found at once
        // (milliseconds; the bound below guards against the minutes pairwise merging took, it is no
        // speed target).
        let specks: Vec<IVec3> = (0..4096)
            .map(|k| IVec3::new(k % 16, (k / 16) % 16, k / 256) * 256)
            .collect();
        let mut b = BrickMapBuilder::new();
        specks.iter().for_each(|&v| b.set(v, 1.0, true));
        let m = b.build();
        let start = std::time::Instant::now();
        assert_eq!(
            find(&m, 4, IVec3::splat(-1), IVec3::splat(1024), u64::MAX),
            None
        );
        assert!(start.elapsed().as_secs_f64() < 5.0, "{:?}", start.elapsed());
        // A tile is a box too, and one that reaches across clusters joins them.
        let five: Vec<IVec3> = (0..5).map(|k| IVec3::new(k * 400, 0, 0)).collect();
        let m = cluster_map(&five);
        let (c_lo, c_hi) = (IVec3::splat(-10), IVec3::new(600, 10, 10));
        assert_eq!(find(&m, 4, c_lo, c_hi, u64::MAX).unwrap().len(), 5);
        let tile = Tile {
            origin: IVec3::new(0, 16, 0),
            size: 2048,
            value: 1.0,
        };
        let m = BrickMap::new(m.leaves().to_vec(), vec![tile]);
        assert_eq!(find(&m, 4, c_lo, c_hi, u64::MAX).unwrap().len(), 1);
    }
}
