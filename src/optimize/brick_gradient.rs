//! A gradient over the unknown, ∂loss/∂θ per voxel, sparse by the unknown's own 8³ bricks (keyed
//! voxel >> 3, values in `leaf_offset` order): what the gradient pass's voxels are bucketed into
//! once, then smoothed (`smoothing`), and what Adam's step reads brick by brick (`parameters`).

use glam::IVec3;

use crate::optimize::parameters::local_of;
use crate::volume::brickmap::{leaf_offset, BRICK_VOXELS};
use crate::volume::sparse_index::KeyMap;

pub type BrickValues = Box<[f64; BRICK_VOXELS]>;

#[derive(Clone, Default)]
pub struct BrickGradient {
    bricks: KeyMap<BrickValues>,
}

impl BrickGradient {
    /// Voxels' gradients summed into bricks; zero and non-finite values are left out (a non-finite
    /// sample was already counted as dropped by the pass that made it). Voxels arrive brick by
    /// brick (a gradient grid's order), so the current brick is kept aside instead of hashing every
    /// voxel's key.
    pub fn from_voxels(voxels: impl IntoIterator<Item = (IVec3, f64)>) -> Self {
        let mut out = BrickGradient::default();
        let mut current: Option<(IVec3, BrickValues)> = None;
        for (voxel, g) in voxels {
            if g == 0.0 || !g.is_finite() {
                continue;
            }
            let key = voxel >> 3;
            if current.as_ref().is_none_or(|(k, _)| *k != key) {
                if let Some((k, values)) = current.take() {
                    out.bricks.insert(k, values);
                }
                let values = out.bricks.remove(&key).unwrap_or_else(zero);
                current = Some((key, values));
            }
            if let Some((_, values)) = &mut current {
                values[leaf_offset(voxel & 7)] += g;
            }
        }
        if let Some((k, values)) = current {
            out.bricks.insert(k, values);
        }
        out
    }

    /// Builds from whole bricks (each key at most once).
    pub fn from_bricks(bricks: impl IntoIterator<Item = (IVec3, BrickValues)>) -> Self {
        BrickGradient {
            bricks: bricks.into_iter().collect(),
        }
    }

    /// The bricks, taken out.
    pub fn into_bricks(self) -> impl Iterator<Item = (IVec3, BrickValues)> {
        self.bricks.into_iter()
    }

    pub fn get(&self, key: IVec3) -> Option<&[f64; BRICK_VOXELS]> {
        self.bricks.get(&key).map(|b| &**b)
    }

    /// The gradient at one voxel (0 where no brick holds it).
    pub fn at(&self, voxel: IVec3) -> f64 {
        self.get(voxel >> 3)
            .map_or(0.0, |values| values[leaf_offset(voxel & 7)])
    }

    /// Adds `other` brick by brick.
    pub fn add(&mut self, other: BrickGradient) {
        for (key, values) in other.bricks {
            match self.bricks.get_mut(&key) {
                Some(sum) => sum.iter_mut().zip(values.iter()).for_each(|(s, v)| *s += v),
                None => {
                    self.bricks.insert(key, values);
                }
            }
        }
    }

    /// The brick keys that hold gradient.
    pub fn keys(&self) -> impl Iterator<Item = IVec3> + '_ {
        self.bricks.keys().copied()
    }

    pub fn brick_count(&self) -> usize {
        self.bricks.len()
    }

    /// Every non-zero voxel gradient (in the map's order).
    pub fn voxels(&self) -> impl Iterator<Item = (IVec3, f64)> + '_ {
        self.bricks.iter().flat_map(|(key, values)| {
            let origin = *key << 3;
            values
                .iter()
                .enumerate()
                .filter(|(_, &g)| g != 0.0)
                .map(move |(i, &g)| (origin + local_of(i), g))
        })
    }
}

fn zero() -> BrickValues {
    Box::new([0.0; BRICK_VOXELS])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn voxels_are_summed_into_their_bricks() {
        let (a, b) = (IVec3::new(-1, 0, 7), IVec3::new(8, 0, 0));
        let g = BrickGradient::from_voxels([(a, 1.0), (b, 2.0), (a, 0.5), (b, f64::NAN), (b, 0.0)]);
        assert_eq!(g.brick_count(), 2);
        let mut voxels: Vec<_> = g.voxels().collect();
        voxels.sort_by_key(|(v, _)| v.to_array());
        assert_eq!(voxels, vec![(a, 1.5), (b, 2.0)]);
        assert_eq!(g.get(a >> 3).unwrap()[leaf_offset(a & 7)], 1.5);
    }

    #[test]
    fn gradients_add_brick_by_brick() {
        let (a, b, c) = (
            IVec3::new(1, 2, 3),
            IVec3::new(6, 2, 3),
            IVec3::new(-9, 0, 0),
        );
        let mut g = BrickGradient::from_voxels([(a, 1.0), (b, -2.0)]);
        g.add(BrickGradient::from_voxels([(a, 0.25), (c, 4.0)]));
        assert_eq!(g.brick_count(), 2);
        assert_eq!((g.at(a), g.at(b), g.at(c)), (1.25, -2.0, 4.0));
        assert_eq!(g.at(IVec3::new(5, 5, 5)), 0.0);
    }
}
