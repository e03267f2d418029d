//! Gradient smoothing at the finer levels of the coarse-to-fine schedule: a preconditioner, not a
//! prior.
//!
//! A voxel of the next level is crossed by half the path length of its parent, so its gradient's
//! signal is about 1/8 of the parent's while its Monte Carlo noise falls only by √8: every
//! upsampling costs a factor 2.8 in signal-to-noise, and at the final level Adam's per-voxel steps
//! are mostly noise, which the θ ≥ 0 projection rectifies into haze. Filtering the gradient with
//! the binomial kernel [1 2 1]/4 per axis, once per upsampling done, averages each voxel's gradient
//! over about the start level's voxel again (one pass leaves the noise at 0.23×, two at 0.14×, a
//! parent's 1/√8 and 1/√64 would be 0.35× and 0.125×) while a smooth gradient passes unchanged.
//! A large first level's gradient is mostly noise too: a density's first level with fewer than
//! `optimizer_file::SMOOTHING_PATHS_PER_VOXEL` gradient paths a step per voxel (32,768 pixels at
//! 8 spp over more than about 19,000 voxels) gets a pass of its own by default
//! (`optimizer_file::first_level_smoothing_for`), and every level one more per upsampling.
//!
//! The step is θ ← θ − lr·P·g with P = Bⁿ (n passes), a symmetric filter whose frequency response
//! cos²(ω/2) per axis is ≥ 0, so −P·g is still a descent direction and the fixed points are the
//! stationary points of the loss; what P changes is the path there: coarse structure first, fine
//! detail as the gradient keeps asking for it. The finest detail comes slowly: B's response
//! cos²(ω/2) is near 0 at the level's highest frequency, which is why a first level whose gradient
//! is not mostly noise does better without a pass of its own.

use glam::IVec3;
use rayon::prelude::*;

use super::parameters::local_of;
use crate::optimize::brick_gradient::{BrickGradient, BrickValues};
use crate::volume::brickmap::BRICK_VOXELS;
use crate::volume::sparse_index::KeyMap;

type Bricks = KeyMap<BrickValues>;

/// Stride of one voxel along axis 0, 1, 2 in a brick's voxel order (`leaf_offset`).
const STRIDE: [usize; 3] = [64, 8, 1];
const AXES: [IVec3; 3] = [IVec3::X, IVec3::Y, IVec3::Z];

/// `gradient` filtered with `passes` passes of [1 2 1]/4 along each axis, restricted to the
/// voxels in `lo..=hi` (the level's voxels: the filter must not carry gradient onto voxels the
/// unknown does not have).
pub fn smooth(gradient: BrickGradient, passes: u32, lo: IVec3, hi: IVec3) -> BrickGradient {
    if passes == 0 {
        return gradient;
    }
    let mut bricks: Bricks = gradient.into_bricks().collect();
    for _ in 0..passes {
        for axis in 0..3 {
            bricks = blur_along(&bricks, axis, lo, hi);
        }
    }
    BrickGradient::from_bricks(bricks)
}

/// One pass of out[v] = ¼·in[v − e] + ½·in[v] + ¼·in[v + e] along `axis`, each output brick
/// gathered from its own brick and its two neighbours along the axis.
fn blur_along(bricks: &Bricks, axis: usize, lo: IVec3, hi: IVec3) -> Bricks {
    let e = AXES[axis];
    let mut keys: Vec<IVec3> = bricks.keys().flat_map(|&k| [k - e, k, k + e]).collect();
    keys.sort_unstable_by_key(|k| k.to_array());
    keys.dedup();
    let stride = STRIDE[axis];
    let zero = [0.0; BRICK_VOXELS];
    keys.into_par_iter()
        .filter_map(|key| {
            let at = |k: IVec3| bricks.get(&k).map_or(&zero, |b| &**b);
            let (before, own, after) = (at(key - e), at(key), at(key + e));
            let mut out = Box::new([0.0; BRICK_VOXELS]);
            let mut any = false;
            for (i, slot) in out.iter_mut().enumerate() {
                let local = local_of(i);
                let voxel: IVec3 = (key << 3) + local;
                if voxel.cmplt(lo).any() || voxel.cmpgt(hi).any() {
                    continue;
                }
                // The neighbours' offsets: across the brick's face they are the other brick's
                // voxel at the opposite face (7 strides back or forward).
                let c = local[axis];
                let left = if c > 0 {
                    own[i - stride]
                } else {
                    before[i + 7 * stride]
                };
                let right = if c < 7 {
                    own[i + stride]
                } else {
                    after[i - 7 * stride]
                };
                let g = 0.25 * left + 0.5 * own[i] + 0.25 * right;
                *slot = g;
                any |= g != 0.0;
            }
            any.then_some((key, out))
        })
        .collect::<Vec<_>>()
        .into_iter()
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    /// `smooth` of the voxels `v`, as a map of the non-zero results.
    fn smoothed(
        v: impl IntoIterator<Item = (IVec3, f64)>,
        passes: u32,
        lo: IVec3,
        hi: IVec3,
    ) -> HashMap<IVec3, f64> {
        let out = smooth(BrickGradient::from_voxels(v), passes, lo, hi);
        let voxels: Vec<_> = out.voxels().collect();
        let map: HashMap<_, _> = voxels.iter().copied().collect();
        assert_eq!(map.len(), voxels.len(), "each voxel once");
        map
    }

    #[test]
    fn an_impulse_becomes_the_binomial_kernel_across_brick_faces() {
        // At a brick corner, so that every neighbour lies in another brick.
        let at = IVec3::new(8, 16, 24);
        let big = IVec3::splat(1000);
        let out = smoothed([(at, 64.0)], 1, -big, big);
        assert_eq!(out.len(), 27);
        for (v, g) in &out {
            let d = (*v - at).abs();
            let expected = 64.0 / 2f64.powi(d.x + d.y + d.z) / 8.0;
            assert!((g - expected).abs() < 1e-12, "{v}: {g} vs {expected}");
        }
        // Two passes: [1 4 6 4 1]/16 per axis, the sum kept.
        let out = smoothed([(at, 1.0)], 2, -big, big);
        assert_eq!(out.len(), 125);
        assert!((out.values().sum::<f64>() - 1.0).abs() < 1e-12);
        assert!((out[&at] - (6.0f64 / 16.0).powi(3)).abs() < 1e-12);
        assert!((out[&(at + IVec3::new(2, -1, 0))] - 1.0 * 4.0 * 6.0 / 4096.0).abs() < 1e-12);
    }

    #[test]
    fn a_smooth_gradient_passes_unchanged_and_noise_is_damped() {
        // A linear ramp inside the box is a fixed point of [1 2 1]/4 (away from the box's faces).
        let (lo, hi) = (IVec3::ZERO, IVec3::splat(23));
        let ramp = |v: IVec3| 1.0 + 0.1 * v.x as f64 - 0.05 * v.y as f64 + 0.02 * v.z as f64;
        let voxels: Vec<_> = (0..24 * 24 * 24)
            .map(|i| IVec3::new(i / 576, (i / 24) % 24, i % 24))
            .collect();
        let out = smoothed(voxels.iter().map(|&v| (v, ramp(v))), 1, lo, hi);
        for &v in &voxels {
            if v.cmpgt(lo).all() && v.cmplt(hi).all() {
                assert!((out[&v] - ramp(v)).abs() < 1e-9, "{v}");
            }
        }
        assert!(!out.keys().any(|v| v.cmplt(lo).any() || v.cmpgt(hi).any()));
        // Alternating signs (the highest frequency) vanish inside.
        let checker = |v: IVec3| {
            if (v.x + v.y + v.z) % 2 == 0 {
                1.0
            } else {
                -1.0
            }
        };
        let out = smoothed(voxels.iter().map(|&v| (v, checker(v))), 1, lo, hi);
        assert!(out.keys().all(|v| v.cmple(lo).any() || v.cmpge(hi).any()));
    }
}
