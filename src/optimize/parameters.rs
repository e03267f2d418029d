//! The unknown of an inverse rendering: the grid's stored values θ ≥ 0 with Adam's moments beside
//! them, kept in 8³ bricks that exist only where θ > 0 or where the images' gradient arrived in the
//! last step. A brick whose values are all 0 and that received no such gradient is dropped with
//! its moments (`descent`), so the memory of the unknown follows the volume's extent, not its
//! bounding box (DESIGN.md, "Inverse rendering").

use anyhow::{bail, Result};
use glam::IVec3;

use crate::optimize::adam::ScalarMoments;
use crate::optimize::average::Average;
use crate::optimize::exposure::Exposure;
use crate::volume::brickmap::{leaf_offset, BrickMap, Leaf, BRICK_VOXELS};
use crate::volume::sparse_index::KeyMap;

/// The most voxels `from_grid` voxelises from tiles (2^28: 3 GiB of θ and moments).
pub const MAX_VOXELS: u64 = 1 << 28;

/// One brick of the unknown: values and Adam's first and second moments, voxel order as OpenVDB's
/// leaves (`leaf_offset`).
#[derive(Clone)]
pub(super) struct ParameterBrick {
    pub(super) theta: [f32; BRICK_VOXELS],
    pub(super) m: [f32; BRICK_VOXELS],
    pub(super) v: [f32; BRICK_VOXELS],
    /// The moments of the brick's log-scale (`Adam::fit_brick_scales`).
    pub(super) scale: ScalarMoments,
    /// Steps since the images' gradient last reached the brick (`descent`'s keep rule).
    pub(super) idle: u32,
}

impl ParameterBrick {
    fn zero() -> Box<Self> {
        Box::new(ParameterBrick {
            theta: [0.0; BRICK_VOXELS],
            m: [0.0; BRICK_VOXELS],
            v: [0.0; BRICK_VOXELS],
            scale: ScalarMoments::default(),
            idle: 0,
        })
    }

    /// ∂loss/∂u of θ·e^u at u = 0 over this brick: Σ θ·g (in f64, in voxel order).
    pub(super) fn scale_gradient(&self, gradient: &[f32; BRICK_VOXELS]) -> f64 {
        let terms = self.theta.iter().zip(gradient.iter());
        terms.map(|(&t, &g)| f64::from(t) * f64::from(g)).sum()
    }
}

/// A brick's key (voxel >> 3) with its θ, m and v, its log-scale's moments and its idle steps, as
/// a checkpoint stores them.
pub type BrickState<'a> = (
    IVec3,
    &'a [f32; BRICK_VOXELS],
    &'a [f32; BRICK_VOXELS],
    &'a [f32; BRICK_VOXELS],
    ScalarMoments,
    u32,
);

/// The voxel within its brick at `leaf_offset` i.
pub(crate) fn local_of(i: usize) -> IVec3 {
    IVec3::new((i >> 6) as i32, ((i >> 3) & 7) as i32, (i & 7) as i32)
}

/// Bricks of values, given in key order, as a brick map whose every stored voxel is active (each
/// brick a leaf as it is, same voxel order).
pub(super) fn brickmap_of<'a>(
    bricks: impl Iterator<Item = (IVec3, &'a [f32; BRICK_VOXELS])>,
) -> BrickMap {
    let leaves = bricks
        .map(|(key, values)| Leaf {
            origin: key << 3,
            values: *values,
            active: [u64::MAX; BRICK_VOXELS / 64],
        })
        .collect();
    BrickMap::new(leaves, Vec::new())
}

/// The grid's values θ and Adam's state, sparse by brick (keyed by brick coordinate, voxel >> 3).
#[derive(Clone, Default)]
pub struct Parameters {
    pub(super) bricks: KeyMap<Box<ParameterBrick>>,
    /// Adam steps taken (t in the bias corrections).
    pub(super) steps: u32,
    /// The moments of the global log-scale (`Adam::fit_scale`).
    pub(super) scale: ScalarMoments,
    /// Each capture's exposure (`Problem::captures`), when they are fitted (`exposure`; none
    /// otherwise: every factor 1).
    pub exposures: Vec<Exposure>,
    /// The mean of θ over the steps since the average began (`average`; none: not begun). A
    /// level's parameters start without one: the mean starts afresh at every upsampling.
    pub average: Average,
}

impl Parameters {
    /// θ from a grid's voxel values. Tiles are voxelised (every value is a parameter), so a grid
    /// whose tiles hold more than `MAX_VOXELS` voxels is an error naming the count, before any
    /// allocation.
    pub fn from_grid(grid: &BrickMap) -> Result<Self> {
        let tile_voxels = grid
            .tiles()
            .iter()
            .try_fold(0u64, |n, t| n.checked_add((t.size as u64).checked_pow(3)?));
        match tile_voxels {
            Some(n) if n <= MAX_VOXELS => {}
            _ => bail!(
                "the grid's tiles hold {} voxels; as parameters every voxel is stored with its optimiser state, at most {MAX_VOXELS}",
                tile_voxels.map_or("more than 2^64".into(), |n| n.to_string())
            ),
        }
        let mut p = Parameters::default();
        for leaf in grid.leaves() {
            p.brick(leaf.origin >> 3).theta = leaf.values.map(|x| x.max(0.0));
        }
        // Tiles are aligned to bricks (their size is a multiple of 8): fill brick by brick.
        for tile in grid.tiles() {
            let bricks = (tile.size as i32 / 8).max(1);
            for x in 0..bricks {
                for y in 0..bricks {
                    for z in 0..bricks {
                        let key = (tile.origin >> 3) + IVec3::new(x, y, z);
                        p.brick(key).theta = [tile.value.max(0.0); BRICK_VOXELS];
                    }
                }
            }
        }
        p.prune();
        Ok(p)
    }

    pub(super) fn brick(&mut self, brick: IVec3) -> &mut ParameterBrick {
        self.bricks
            .entry(brick)
            .or_insert_with(ParameterBrick::zero)
    }

    /// θ at a voxel (0 where no brick is).
    pub fn get(&self, voxel: IVec3) -> f32 {
        self.state(voxel).0
    }

    /// θ of the brick with key `key` (voxel >> 3), if it is stored.
    pub fn brick_theta(&self, key: IVec3) -> Option<&[f32; BRICK_VOXELS]> {
        self.bricks.get(&key).map(|b| &b.theta)
    }

    /// (θ, m, v) at a voxel (zeros where no brick is).
    pub fn state(&self, voxel: IVec3) -> (f32, f32, f32) {
        self.bricks.get(&(voxel >> 3)).map_or((0.0, 0.0, 0.0), |b| {
            let i = leaf_offset(voxel & 7);
            (b.theta[i], b.m[i], b.v[i])
        })
    }

    /// The brick coordinates (voxel >> 3) that hold parameters.
    pub fn brick_keys(&self) -> impl Iterator<Item = IVec3> + '_ {
        self.bricks.keys().copied()
    }

    /// Sets θ at a voxel (clamped to ≥ 0), creating its brick.
    pub fn set(&mut self, voxel: IVec3, value: f32) {
        self.brick(voxel >> 3).theta[leaf_offset(voxel & 7)] = value.max(0.0);
    }

    pub fn brick_count(&self) -> usize {
        self.bricks.len()
    }

    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// Voxels with θ > 0.
    pub fn active_voxels(&self) -> u64 {
        self.bricks
            .values()
            .map(|b| b.theta.iter().filter(|&&x| x > 0.0).count() as u64)
            .sum()
    }

    /// Bytes of θ, the moments and the average (what a checkpoint reports).
    pub fn memory_bytes(&self) -> usize {
        let brick = std::mem::size_of::<ParameterBrick>() + std::mem::size_of::<IVec3>();
        self.bricks.len() * brick + self.average.memory_bytes()
    }

    /// Adds θ as it is now to the average.
    pub fn add_to_average(&mut self) {
        let mut average = std::mem::take(&mut self.average);
        average.add(self);
        self.average = average;
    }

    /// The run's result: the average once it has begun, θ before.
    pub fn result(&self) -> BrickMap {
        if self.average.steps() > 0 {
            self.average.to_brickmap()
        } else {
            self.to_brickmap()
        }
    }

    /// Drops the bricks whose θ is all 0 and for which `keep` is false.
    pub(super) fn drop_empty(&mut self, keep: impl Fn(&ParameterBrick) -> bool) {
        self.bricks
            .retain(|_, b| keep(b) || b.theta.iter().any(|&x| x > 0.0));
    }

    /// Every stored voxel as (voxel, θ, m, v).
    pub fn voxels(&self) -> impl Iterator<Item = (IVec3, f32, f32, f32)> + '_ {
        self.bricks.iter().flat_map(|(key, b)| {
            (0..BRICK_VOXELS).map(move |i| ((*key << 3) + local_of(i), b.theta[i], b.m[i], b.v[i]))
        })
    }

    /// Sets θ and Adam's moments of a voxel (θ clamped to ≥ 0, v to ≥ 0).
    pub fn set_with_moments(&mut self, voxel: IVec3, theta: f32, m: f32, v: f32) {
        let brick = self.brick(voxel >> 3);
        let i = leaf_offset(voxel & 7);
        brick.theta[i] = theta.max(0.0);
        brick.m[i] = m;
        brick.v[i] = v.max(0.0);
    }

    /// Continues the step count of `other` (Adam's bias corrections) and the global scale's
    /// moments, e.g. after resampling: u is the same parameter at any resolution.
    pub fn continue_steps_of(&mut self, other: &Parameters) {
        self.steps = other.steps;
        self.scale = other.scale;
    }

    /// Gives each brick the log-scale moments of the brick of `coarse` (one level coarser) it
    /// lies in, × `gradient_scale`: brick K's voxels 8K…8K + 7 sit at coarse indices 4K − ¼ …
    /// 4K + 3¼, inside coarse brick K >> 1.
    pub fn inherit_brick_scales(&mut self, coarse: &Parameters, gradient_scale: f32) {
        for (key, brick) in self.bricks.iter_mut() {
            if let Some(parent) = coarse.bricks.get(&(*key >> 1)) {
                brick.scale = parent.scale.scaled(gradient_scale);
            }
        }
    }

    /// Drops the bricks that hold only zeros (after building a grid voxel by voxel).
    pub fn prune(&mut self) {
        self.drop_empty(|_| false);
    }

    /// The brick keys in (x, y, z) order, which does not depend on the hash map's.
    pub(super) fn sorted_keys(&self) -> Vec<IVec3> {
        let mut keys: Vec<IVec3> = self.bricks.keys().copied().collect();
        keys.sort_by_key(|k| k.to_array());
        keys
    }

    /// θ as a brick map (every stored voxel active), e.g. to render or to write as a VDB: each
    /// brick becomes a leaf as it is (same voxel order), in key order.
    pub fn to_brickmap(&self) -> BrickMap {
        let keys = self.sorted_keys();
        brickmap_of(keys.iter().map(|key| (*key, &self.bricks[key].theta)))
    }

    /// Every brick as (key, θ, m, v), in key order: what a checkpoint stores.
    pub fn sorted_bricks(&self) -> Vec<BrickState<'_>> {
        self.sorted_keys()
            .into_iter()
            .map(|key| {
                let b = &self.bricks[&key];
                (key, &b.theta, &b.m, &b.v, b.scale, b.idle)
            })
            .collect()
    }

    /// Restores a brick as `sorted_bricks` gave it (θ clamped to ≥ 0).
    pub fn insert_brick(
        &mut self,
        key: IVec3,
        theta: [f32; BRICK_VOXELS],
        m: [f32; BRICK_VOXELS],
        v: [f32; BRICK_VOXELS],
        scale: ScalarMoments,
        idle: u32,
    ) {
        self.bricks.insert(
            key,
            Box::new(ParameterBrick {
                theta: theta.map(|x| x.max(0.0)),
                m,
                v,
                scale,
                idle,
            }),
        );
    }

    /// The global scale's moments (what a checkpoint stores).
    pub fn scale_moments(&self) -> ScalarMoments {
        self.scale
    }

    /// Restores Adam's step count and the global scale's moments (a checkpoint's).
    pub fn set_steps(&mut self, steps: u32, scale: ScalarMoments) {
        self.steps = steps;
        self.scale = scale;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Tiles become parameters brick by brick; one too large to store is refused, not voxelised.
    #[test]
    fn tiles_are_voxelised_within_a_cap() {
        use crate::volume::brickmap::Tile;
        let tile = |size: u32| Tile {
            origin: IVec3::ZERO,
            size,
            value: 0.5,
        };
        let small = Parameters::from_grid(&BrickMap::new(Vec::new(), vec![tile(16)])).unwrap();
        assert_eq!(small.brick_count(), 8);
        assert_eq!(small.get(IVec3::new(15, 0, 9)), 0.5);
        let huge = Parameters::from_grid(&BrickMap::new(Vec::new(), vec![tile(4096)]));
        let err = huge.err().unwrap().to_string();
        assert!(err.contains("68719476736 voxels"), "{err}");
    }

    #[test]
    fn grids_convert_both_ways() {
        let grid = BrickMap::block(10, |v| (v.x + 2 * v.y) as f32 * 0.1);
        let p = Parameters::from_grid(&grid).unwrap();
        let back = p.to_brickmap();
        for v in [IVec3::ZERO, IVec3::new(9, 9, 9), IVec3::new(3, 7, 1)] {
            assert_eq!(back.voxel(v), grid.voxel(v));
        }
        // The voxel at the origin is 0, in a brick that holds other values: kept.
        assert_eq!(p.get(IVec3::ZERO), 0.0);
        assert_eq!(p.brick_count(), 8);
    }
}
