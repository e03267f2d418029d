//! The unknown of an inverse rendering: the grid's stored values θ ≥ 0 with Adam's moments beside
//! them, kept in 8³ bricks that exist only where θ > 0 or where gradient arrived in the last step.
//! A brick whose values are all 0 and that received no gradient is dropped with its moments, so the
//! memory of the unknown follows the volume's extent, not its bounding box (DESIGN.md, "Inverse
//! rendering").

use anyhow::{bail, Result};
use glam::IVec3;

use crate::volume::brickmap::{leaf_offset, BrickMap, Leaf, BRICK_VOXELS};
use crate::volume::sparse_index::KeyMap;

/// The most voxels `from_grid` voxelises from tiles (2^28: 3 GiB of θ and moments).
pub const MAX_VOXELS: u64 = 1 << 28;

/// Adam's settings (Kingma & Ba 2015); θ is projected onto θ ≥ 0 after every step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Adam {
    pub lr: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
}

impl Default for Adam {
    fn default() -> Self {
        Adam {
            lr: 0.01,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
        }
    }
}

/// One brick of the unknown: values and Adam's first and second moments, voxel order as OpenVDB's
/// leaves (`leaf_offset`).
#[derive(Clone)]
struct ParameterBrick {
    theta: [f32; BRICK_VOXELS],
    m: [f32; BRICK_VOXELS],
    v: [f32; BRICK_VOXELS],
}

impl ParameterBrick {
    fn zero() -> Box<Self> {
        Box::new(ParameterBrick {
            theta: [0.0; BRICK_VOXELS],
            m: [0.0; BRICK_VOXELS],
            v: [0.0; BRICK_VOXELS],
        })
    }
}

/// A brick's key (voxel >> 3) with its θ, m and v, as a checkpoint stores them.
pub type BrickState<'a> = (
    IVec3,
    &'a [f32; BRICK_VOXELS],
    &'a [f32; BRICK_VOXELS],
    &'a [f32; BRICK_VOXELS],
);

/// The voxel within its brick at `leaf_offset` i.
pub(crate) fn local_of(i: usize) -> IVec3 {
    IVec3::new((i >> 6) as i32, ((i >> 3) & 7) as i32, (i & 7) as i32)
}

/// The grid's values θ and Adam's state, sparse by brick (keyed by brick coordinate, voxel >> 3).
#[derive(Clone, Default)]
pub struct Parameters {
    bricks: KeyMap<Box<ParameterBrick>>,
    /// Adam steps taken (t in the bias corrections).
    steps: u32,
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

    fn brick(&mut self, brick: IVec3) -> &mut ParameterBrick {
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

    /// Bytes of θ and the moments (what a checkpoint reports).
    pub fn memory_bytes(&self) -> usize {
        self.bricks.len() * (std::mem::size_of::<ParameterBrick>() + std::mem::size_of::<IVec3>())
    }

    /// One Adam step with the gradient `gradient` (∂loss/∂θ per voxel; voxels not listed have
    /// gradient 0), then the projection θ ← max(θ, 0); bricks that hold only zeros and got no
    /// gradient are dropped with their moments.
    ///
    /// m ← β1·m + (1 − β1)·g,  v ← β2·v + (1 − β2)·g²,
    /// θ ← max(0, θ − lr · (m / (1 − β1ᵗ)) / (√(v / (1 − β2ᵗ)) + ε)).
    pub fn adam_step(&mut self, adam: &Adam, gradient: impl IntoIterator<Item = (IVec3, f64)>) {
        self.steps += 1;
        // Gradients arrive brick by brick (the gradient grid's and the prior's order), so the
        // brick of the previous voxel is remembered instead of hashing every voxel's key.
        let mut touched: KeyMap<Box<[f32; BRICK_VOXELS]>> = KeyMap::default();
        let mut current: Option<(IVec3, Box<[f32; BRICK_VOXELS]>)> = None;
        for (voxel, g) in gradient {
            let g = g as f32;
            if g != 0.0 && g.is_finite() {
                let key = voxel >> 3;
                if current.as_ref().is_none_or(|(k, _)| *k != key) {
                    if let Some((k, brick)) = current.take() {
                        touched.insert(k, brick);
                    }
                    let brick = touched
                        .remove(&key)
                        .unwrap_or_else(|| Box::new([0.0; BRICK_VOXELS]));
                    current = Some((key, brick));
                }
                if let Some((_, brick)) = &mut current {
                    brick[leaf_offset(voxel & 7)] += g;
                }
            }
        }
        if let Some((k, brick)) = current {
            touched.insert(k, brick);
        }
        for &key in touched.keys() {
            self.brick(key);
        }
        let t = self.steps as i32;
        let correct1 = 1.0 - adam.beta1.powi(t);
        let correct2 = 1.0 - adam.beta2.powi(t);
        let zero = [0.0f32; BRICK_VOXELS];
        for (key, brick) in self.bricks.iter_mut() {
            let grads = touched.get(key).map_or(&zero, |g| &**g);
            for (i, &g) in grads.iter().enumerate() {
                let m = adam.beta1 * brick.m[i] + (1.0 - adam.beta1) * g;
                let v = adam.beta2 * brick.v[i] + (1.0 - adam.beta2) * g * g;
                brick.m[i] = m;
                brick.v[i] = v;
                let step = adam.lr * (m / correct1) / ((v / correct2).sqrt() + adam.epsilon);
                brick.theta[i] = (brick.theta[i] - step).max(0.0);
            }
        }
        self.drop_empty(&touched);
    }

    /// Drops the bricks whose θ is all 0 and which are not in `keep`.
    fn drop_empty<T>(&mut self, keep: &KeyMap<T>) {
        self.bricks
            .retain(|key, b| keep.contains_key(key) || b.theta.iter().any(|&x| x > 0.0));
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

    /// Continues the step count of `other` (Adam's bias corrections), e.g. after resampling.
    pub fn continue_steps_of(&mut self, other: &Parameters) {
        self.steps = other.steps;
    }

    /// Drops the bricks that hold only zeros (after building a grid voxel by voxel).
    pub fn prune(&mut self) {
        self.drop_empty(&KeyMap::<()>::default());
    }

    /// The brick keys in (x, y, z) order, which does not depend on the hash map's.
    fn sorted_keys(&self) -> Vec<IVec3> {
        let mut keys: Vec<IVec3> = self.bricks.keys().copied().collect();
        keys.sort_by_key(|k| k.to_array());
        keys
    }

    /// θ as a brick map (every stored voxel active), e.g. to render or to write as a VDB: each
    /// brick becomes a leaf as it is (same voxel order), in key order.
    pub fn to_brickmap(&self) -> BrickMap {
        let leaves = self
            .sorted_keys()
            .into_iter()
            .map(|key| Leaf {
                origin: key << 3,
                values: self.bricks[&key].theta,
                active: [u64::MAX; BRICK_VOXELS / 64],
            })
            .collect();
        BrickMap::new(leaves, Vec::new())
    }

    /// Every brick as (key, θ, m, v), in key order: what a checkpoint stores.
    pub fn sorted_bricks(&self) -> Vec<BrickState<'_>> {
        self.sorted_keys()
            .into_iter()
            .map(|key| {
                let b = &self.bricks[&key];
                (key, &b.theta, &b.m, &b.v)
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
    ) {
        self.bricks.insert(
            key,
            Box::new(ParameterBrick {
                theta: theta.map(|x| x.max(0.0)),
                m,
                v,
            }),
        );
    }

    /// Restores Adam's step count (a checkpoint's).
    pub fn set_steps(&mut self, steps: u32) {
        self.steps = steps;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Adam's update written out by hand for two steps of one voxel.
    #[test]
    fn adam_matches_hand_computed_steps() {
        let adam = Adam {
            lr: 0.1,
            beta1: 0.9,
            beta2: 0.99,
            epsilon: 1e-8,
        };
        let v = IVec3::new(3, -2, 9);
        let mut p = Parameters::default();
        p.set(v, 1.0);
        p.adam_step(&adam, [(v, 2.0)]);
        // t = 1: m = 0.2, v = 0.04, m̂ = 2, v̂ = 4, step = 0.1 · 2 / 2 = 0.1.
        assert!((p.get(v) - 0.9).abs() < 1e-6, "{}", p.get(v));
        p.adam_step(&adam, [(v, -1.0)]);
        // t = 2: m = 0.18 − 0.1 = 0.08, v = 0.0396 + 0.01 = 0.0496,
        // m̂ = 0.08 / 0.19, v̂ = 0.0496 / 0.0199, step = 0.1 · m̂ / √v̂.
        let expected = 0.9 - 0.1 * (0.08 / 0.19) / (0.0496f64 / 0.0199).sqrt();
        assert!(
            (p.get(v) as f64 - expected).abs() < 1e-6,
            "{} vs {expected}",
            p.get(v)
        );
        assert_eq!(p.steps(), 2);
    }

    #[test]
    fn projection_keeps_theta_non_negative_and_empty_bricks_are_dropped() {
        let adam = Adam {
            lr: 0.5,
            ..Adam::default()
        };
        let (a, far) = (IVec3::new(1, 1, 1), IVec3::new(1000, 0, 0));
        let mut p = Parameters::default();
        p.set(a, 0.2);
        // A large positive gradient pushes θ below 0: the projection stops it at 0.
        p.adam_step(&adam, [(a, 10.0)]);
        assert_eq!(p.get(a), 0.0);
        // That brick got gradient this step, so it stays (with its moments) for one more step…
        assert_eq!(p.brick_count(), 1);
        // …and is dropped once a step passes without gradient while it holds only zeros.
        p.adam_step(&adam, []);
        assert_eq!(p.brick_count(), 0);
        // Gradient arriving in empty space creates a brick there, and a negative gradient grows θ.
        p.adam_step(&adam, [(far, -1.0)]);
        assert_eq!(p.brick_count(), 1);
        assert!(p.get(far) > 0.0);
        assert!(p.memory_bytes() >= 3 * BRICK_VOXELS * 4);
    }

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
