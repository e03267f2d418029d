//! The mean of θ over a run's last steps (Polyak–Ruppert averaging, with the later steps weighing
//! more), which is what the run writes and evaluates once it has begun.
//!
//! A budget-bound run ends while Adam's steps still carry the gradient's Monte Carlo noise: θ
//! wanders about the volume the views ask for by an amount the learning rate sets. The mean of
//! the iterates since `average_from` keeps the progress the steps made and averages most of that
//! wander away, without slowing the steps themselves as a lower learning rate would. The mean
//! starts afresh at every upsampling (the coarser iterates lack the new level's detail), so it
//! covers the steps since `average_from` or since the last upsampling, whichever came later.
//!
//! Such a run is still improving when it ends, so an equal weight for every averaged step mixes
//! in iterates it has since improved on. Polynomial-decay averaging (Shamir & Zhang 2013) weighs
//! the k-th averaged step by the rising factorial k·(k+1)·…·(k+η−1):
//! θ̄_n = θ̄_{n−1} + (θ_n − θ̄_{n−1}) · (η + 1)/(n + η), voxel by voxel, where a voxel without a
//! brick counts as θ = 0 (so a brick dropped or created during the average is averaged right).
//! η = 0 is the plain mean.

use glam::IVec3;
use rayon::prelude::*;

use crate::optimize::parameters::{brickmap_of, Parameters};
use crate::volume::brickmap::{BrickMap, BRICK_VOXELS};
use crate::volume::sparse_index::KeyMap;

/// η of polynomial-decay averaging. Two replays of the worked example's 10-minute schedule
/// (`scenes/capture/plume.toml`, seeds 1 and 2), each mean kept beside the plain one over the same
/// steps and scored at the same 1,820 spp: η = 1, 3 and 8 scored +0.06 to +0.13 dB above the
/// plain mean on both the held-out and the relit views, η = 3 the most on average. Where the mean
/// covers few steps it costs a little: −0.06 dB on the Disney cloud's 10-minute run, whose mean
/// covers its last level's 33 steps (docs/reconstruct.md, "The average of the last steps").
const ETA: f32 = 3.0;

/// The running mean θ̄ of θ over `steps` steps, sparse by brick as θ is.
#[derive(Clone, Default)]
pub struct Average {
    steps: u32,
    bricks: KeyMap<Box<[f32; BRICK_VOXELS]>>,
}

impl Average {
    /// Steps averaged so far (0: the average has not begun).
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// Adds θ as the next iterate.
    pub fn add(&mut self, parameters: &Parameters) {
        self.steps += 1;
        let weight = (ETA + 1.0) / (self.steps as f32 + ETA);
        for key in parameters.brick_keys() {
            self.bricks
                .entry(key)
                .or_insert_with(|| Box::new([0.0; BRICK_VOXELS]));
        }
        // Each brick's update reads only its own θ: in parallel, with the same result at any
        // thread count.
        self.bricks.par_iter_mut().for_each(|(key, mean)| {
            let zero = [0.0; BRICK_VOXELS];
            let theta = parameters.brick_theta(*key).unwrap_or(&zero);
            for (m, &t) in mean.iter_mut().zip(theta) {
                *m += (t - *m) * weight;
            }
        });
        self.bricks.retain(|_, mean| mean.iter().any(|&x| x > 0.0));
    }

    /// θ̄ as a brick map (every stored voxel active), as `Parameters::to_brickmap` gives θ.
    pub fn to_brickmap(&self) -> BrickMap {
        brickmap_of(self.sorted().into_iter())
    }

    /// Every brick of θ̄ in key order: what a checkpoint stores.
    pub fn sorted(&self) -> Vec<(IVec3, &[f32; BRICK_VOXELS])> {
        let mut bricks: Vec<_> = self.bricks.iter().map(|(k, v)| (*k, &**v)).collect();
        bricks.sort_by_key(|(k, _)| k.to_array());
        bricks
    }

    /// An average as a checkpoint stored it (clamped to ≥ 0, as restored θ is: a mean of θ ≥ 0).
    pub fn restore(steps: u32, bricks: Vec<(IVec3, [f32; BRICK_VOXELS])>) -> Self {
        let clamped = bricks
            .into_iter()
            .map(|(k, v)| (k, Box::new(v.map(|x| x.max(0.0)))));
        Average {
            steps,
            bricks: clamped.collect(),
        }
    }

    /// Bytes of θ̄.
    pub fn memory_bytes(&self) -> usize {
        self.bricks.len()
            * (std::mem::size_of::<[f32; BRICK_VOXELS]>() + std::mem::size_of::<IVec3>())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Three iterates: a voxel present throughout, one whose brick appears at the second step,
    /// and one whose brick is gone at the third; the mean weighs them by the rising factorial and
    /// counts absent bricks as zeros.
    #[test]
    fn the_mean_counts_absent_bricks_as_zero() {
        let (a, b, c) = (
            IVec3::new(1, 2, 3),
            IVec3::new(40, 0, 0),
            IVec3::new(-9, 0, 0),
        );
        let mut average = Average::default();
        let iterate = |values: &[(IVec3, f32)]| {
            let mut p = Parameters::default();
            for &(v, x) in values {
                p.set(v, x);
            }
            p
        };
        average.add(&iterate(&[(a, 1.0), (c, 0.6)]));
        average.add(&iterate(&[(a, 2.0), (b, 0.9), (c, 0.3)]));
        average.add(&iterate(&[(a, 4.5), (b, 0.3)]));
        let mean = average.to_brickmap();
        assert_eq!(average.steps(), 3);
        // Step k weighs k·(k+1)·(k+2) at η = 3: 6, 24 and 60 of 90.
        let weighed = |x: [f32; 3]| (6.0 * x[0] + 24.0 * x[1] + 60.0 * x[2]) / 90.0;
        for (v, iterates) in [
            (a, [1.0, 2.0, 4.5]),
            (b, [0.0, 0.9, 0.3]),
            (c, [0.6, 0.3, 0.0]),
        ] {
            let expected = weighed(iterates);
            assert!(
                (mean.voxel(v) - expected).abs() < 1e-6,
                "{v}: {} against {expected}",
                mean.voxel(v)
            );
        }
        assert_eq!(mean.voxel(IVec3::new(2, 2, 3)), 0.0);
    }
}
