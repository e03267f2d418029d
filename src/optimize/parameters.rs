//! The unknown of an inverse rendering: the grid's stored values θ ≥ 0 with Adam's moments beside
//! them, kept in 8³ bricks that exist only where θ > 0 or where gradient arrived in the last step.
//! A brick whose values are all 0 and that received no gradient is dropped with its moments, so the
//! memory of the unknown follows the volume's extent, not its bounding box (DESIGN.md, "Inverse
//! rendering").

use anyhow::{bail, Result};
use glam::IVec3;
use rayon::prelude::*;

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
    /// Also fit one global log-scale u of θ (θ ← θ·e^Δu with its own Adam moments) in every step.
    /// Its gradient ∂loss/∂u = Σ θ·g sums every voxel's, so it is nearly noise-free where each
    /// voxel's is mostly noise: the overall density of an optically thick medium, which per-voxel
    /// steps find slowly (each voxel's share of that signal is below its noise), comes at once.
    pub fit_scale: bool,
    /// Also fit a log-scale u_b per brick (θ ← θ·e^(Δu + Δu_b)), each on its own brick's
    /// Σ θ·g: the same idea for modes that differ across the volume (a cloud's hidden interior
    /// too thin while its surface, which the views pin down, is right), which one global scale
    /// cannot move and per-voxel steps move slowly.
    pub fit_brick_scales: bool,
    /// The brick log-scales' learning rate as a multiple of `lr`: each brick's Σ θ·g sums fewer
    /// voxels than the global one's, so it is noisier, but the interior it moves has no other
    /// fast mode.
    pub brick_scale_lr: f32,
}

impl Default for Adam {
    fn default() -> Self {
        Adam {
            lr: 0.01,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            fit_scale: false,
            fit_brick_scales: false,
            brick_scale_lr: 1.0,
        }
    }
}

/// Adam at step t, with the bias corrections 1 − β1ᵗ and 1 − β2ᵗ computed once for all voxels.
struct AdamStep {
    adam: Adam,
    correct1: f32,
    correct2: f32,
}

impl AdamStep {
    fn new(adam: &Adam, t: u32) -> Self {
        AdamStep {
            adam: *adam,
            correct1: 1.0 - adam.beta1.powi(t as i32),
            correct2: 1.0 - adam.beta2.powi(t as i32),
        }
    }

    /// One update of a parameter's moments (m, v) by the gradient g; returns the new moments and
    /// the step to subtract: lr · (m / (1 − β1ᵗ)) / (√(v / (1 − β2ᵗ)) + ε).
    fn update(&self, m: f32, v: f32, g: f32) -> (f32, f32, f32) {
        let a = &self.adam;
        let m = a.beta1 * m + (1.0 - a.beta1) * g;
        let v = a.beta2 * v + (1.0 - a.beta2) * g * g;
        (
            m,
            v,
            a.lr * (m / self.correct1) / ((v / self.correct2).sqrt() + a.epsilon),
        )
    }
}

/// Adam's moments of one scalar parameter: a log-scale of θ (global or per brick).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ScalarMoments {
    pub m: f32,
    pub v: f32,
}

impl ScalarMoments {
    /// Adam's step of a log-scale u whose gradient is `g`, at `lr_factor` × Adam's learning
    /// rate; returns the factor e^Δu it applies to θ. A step whose factor is not finite (a Σ θ·g
    /// beyond f32 makes it inf/inf; a learning rate so large that e^Δu overflows) is skipped,
    /// moments unchanged, like a non-finite voxel gradient: θ·inf would leave θ infinite.
    fn step(&mut self, at: &AdamStep, g: f32, lr_factor: f32) -> f32 {
        let (m, v, step) = at.update(self.m, self.v, g);
        let factor = (-step * lr_factor).exp();
        if !factor.is_finite() {
            return 1.0;
        }
        *self = ScalarMoments { m, v };
        factor
    }

    /// The moments of a log-scale whose gradient becomes `factor` times what it was (after an
    /// upsampling: a child brick's Σ θ·g is 1/8 of its parent's).
    pub fn scaled(self, factor: f32) -> Self {
        ScalarMoments {
            m: self.m * factor,
            v: self.v * factor * factor,
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
    /// The moments of the brick's log-scale (`Adam::fit_brick_scales`).
    scale: ScalarMoments,
}

impl ParameterBrick {
    fn zero() -> Box<Self> {
        Box::new(ParameterBrick {
            theta: [0.0; BRICK_VOXELS],
            m: [0.0; BRICK_VOXELS],
            v: [0.0; BRICK_VOXELS],
            scale: ScalarMoments::default(),
        })
    }

    /// ∂loss/∂u of θ·e^u at u = 0 over this brick: Σ θ·g (in f64, in voxel order).
    fn scale_gradient(&self, gradient: &[f32; BRICK_VOXELS]) -> f64 {
        let terms = self.theta.iter().zip(gradient.iter());
        terms.map(|(&t, &g)| f64::from(t) * f64::from(g)).sum()
    }
}

/// A brick's key (voxel >> 3) with its θ, m and v and its log-scale's moments, as a checkpoint
/// stores them.
pub type BrickState<'a> = (
    IVec3,
    &'a [f32; BRICK_VOXELS],
    &'a [f32; BRICK_VOXELS],
    &'a [f32; BRICK_VOXELS],
    ScalarMoments,
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
    /// The moments of the global log-scale (`Adam::fit_scale`).
    scale: ScalarMoments,
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
    /// θ ← max(0, θ·e^(Δu + Δu_b) − lr · (m / (1 − β1ᵗ)) / (√(v / (1 − β2ᵗ)) + ε)),
    /// where Δu is the same Adam step of the global log-scale u, whose gradient is Σ θ·g over
    /// every voxel, when `adam.fit_scale`, and Δu_b that of the brick's log-scale u_b, on Σ θ·g
    /// over the brick, when `adam.fit_brick_scales` (each 0 otherwise).
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
        let at = AdamStep::new(adam, self.steps);
        let global = if adam.fit_scale {
            let g = self.scale_gradient(&touched);
            self.scale.step(&at, g, 1.0)
        } else {
            1.0
        };
        let zero = [0.0f32; BRICK_VOXELS];
        // Each brick's step reads only its own state and gradient: in parallel, with the same
        // result at any thread count.
        self.bricks.par_iter_mut().for_each(|(key, brick)| {
            let grads = touched.get(key).map_or(&zero, |g| &**g);
            let scale = if adam.fit_brick_scales {
                let g = brick.scale_gradient(grads) as f32;
                global * brick.scale.step(&at, g, adam.brick_scale_lr)
            } else {
                global
            };
            for (i, &g) in grads.iter().enumerate() {
                let (m, v, step) = at.update(brick.m[i], brick.v[i], g);
                brick.m[i] = m;
                brick.v[i] = v;
                brick.theta[i] = (brick.theta[i] * scale - step).max(0.0);
            }
        });
        self.drop_empty(&touched);
    }

    /// ∂loss/∂u of θ·e^u at u = 0: Σ θ·g over the voxels that got gradient (summed in f64, in
    /// key order, so that it does not depend on the hash map's order).
    fn scale_gradient(&self, gradient: &KeyMap<Box<[f32; BRICK_VOXELS]>>) -> f32 {
        let mut keys: Vec<&IVec3> = gradient.keys().collect();
        keys.sort_by_key(|k| k.to_array());
        let sum: f64 = keys
            .into_iter()
            .filter_map(|key| Some(self.bricks.get(key)?.scale_gradient(&gradient[key])))
            .sum();
        sum as f32
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
                (key, &b.theta, &b.m, &b.v, b.scale)
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
    ) {
        self.bricks.insert(
            key,
            Box::new(ParameterBrick {
                theta: theta.map(|x| x.max(0.0)),
                m,
                v,
                scale,
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

    /// Adam's update written out by hand for two steps of one voxel.
    #[test]
    fn adam_matches_hand_computed_steps() {
        let adam = Adam {
            lr: 0.1,
            beta1: 0.9,
            beta2: 0.99,
            epsilon: 1e-8,
            ..Adam::default()
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

    /// One Adam step (lr 0.1, β 0.9 / 0.99) of one voxel θ = 2 with gradient 0.5, so its
    /// brick's and the grid's ∂loss/∂u = θ·g = 1; at t = 1 every m̂ = g and v̂ = g², so each
    /// log-scale steps by its lr and the voxel by 0.1.
    fn one_voxel_step(adam: Adam) -> (f32, Parameters) {
        let adam = Adam {
            lr: 0.1,
            beta1: 0.9,
            beta2: 0.99,
            epsilon: 1e-8,
            ..adam
        };
        let v = IVec3::new(0, 5, 1);
        let mut p = Parameters::default();
        p.set(v, 2.0);
        p.adam_step(&adam, [(v, 0.5)]);
        (p.get(v), p)
    }

    #[test]
    fn the_global_scale_matches_a_hand_computed_step() {
        let (theta, p) = one_voxel_step(Adam {
            fit_scale: true,
            ..Adam::default()
        });
        let expected = 2.0 * (-0.1f64).exp() - 0.1;
        assert!((theta as f64 - expected).abs() < 1e-6, "{theta}");
        let ScalarMoments { m, v } = p.scale_moments();
        assert!((m - 0.1).abs() < 1e-6 && (v - 0.01).abs() < 1e-6, "{m} {v}");
    }

    /// A brick's scale at `brick_scale_lr` = 3: three times the global one's step above, with
    /// the same moments (they are the gradient's, whatever the learning rate).
    #[test]
    fn a_brick_scale_steps_at_its_own_learning_rate() {
        let (theta, p) = one_voxel_step(Adam {
            fit_brick_scales: true,
            brick_scale_lr: 3.0,
            ..Adam::default()
        });
        let expected = 2.0 * (-0.3f64).exp() - 0.1;
        assert!((theta as f64 - expected).abs() < 1e-6, "{theta}");
        let ScalarMoments { m, v } = p.sorted_bricks()[0].4;
        assert!((m - 0.1).abs() < 1e-6 && (v - 0.01).abs() < 1e-6, "{m} {v}");
    }

    /// A learning rate whose log-scale step overflows e^Δu (Δu ≈ +3e29: the gradient −0.5 asks
    /// for more density): the scale's step is skipped and θ stays finite.
    #[test]
    fn a_scale_step_beyond_f32_is_skipped() {
        let adam = Adam {
            lr: 0.1,
            fit_brick_scales: true,
            brick_scale_lr: 3e30,
            ..Adam::default()
        };
        let v = IVec3::new(0, 5, 1);
        let mut p = Parameters::default();
        p.set(v, 2.0);
        p.adam_step(&adam, [(v, -0.5)]);
        // Only the voxel's own step, −lr·sign(g): θ = 2.1.
        assert!((p.get(v) - 2.1).abs() < 1e-6, "{}", p.get(v));
        assert_eq!(p.sorted_bricks()[0].4, ScalarMoments::default());
    }

    /// Huge values and gradients whose Σ θ·g overflows f32: the scales' steps are skipped, θ
    /// stays.
    #[test]
    fn the_scales_skip_a_sum_beyond_f32() {
        let adam = Adam {
            fit_scale: true,
            fit_brick_scales: true,
            ..Adam::default()
        };
        let v = IVec3::new(2, 2, 2);
        let mut p = Parameters::default();
        p.set(v, 1e30);
        p.adam_step(&adam, [(v, 1e30)]);
        // The voxel's own step is lr · m̂ / √v̂ with v̂ = inf in f32: 0.
        assert_eq!(p.get(v), 1e30);
        assert_eq!(p.scale_moments(), ScalarMoments::default());
        assert_eq!(p.sorted_bricks()[0].4, ScalarMoments::default());
    }

    /// The 16³ voxels (8 bricks) of the noisy-optimisation tests below, and their true values.
    fn noisy_voxels() -> Vec<(IVec3, f32)> {
        (0..4096)
            .map(|i| {
                let v = IVec3::new(i & 15, (i >> 4) & 15, i >> 8);
                (v, 0.5 + 0.25 * (i as f32 * 0.37).sin())
            })
            .collect()
    }

    /// 300 Adam steps from θ = truth × `start(voxel)` on the gradient of ½·0.01·(θ − truth)²
    /// per voxel plus noise of standard deviation 0.1, 10× the signal's size (fixed seed).
    fn optimise_under_noise(
        voxels: &[(IVec3, f32)],
        adam: Adam,
        start: impl Fn(IVec3) -> f32,
        seed: u64,
    ) -> Parameters {
        use rand::{Rng, SeedableRng};
        let mut p = Parameters::default();
        for &(v, truth) in voxels {
            p.set(v, truth * start(v));
        }
        let mut rng = rand::rngs::SmallRng::seed_from_u64(seed);
        for _ in 0..300 {
            let gradient: Vec<(IVec3, f64)> = voxels
                .iter()
                .map(|&(v, truth)| {
                    let signal = 0.01 * (p.get(v) - truth);
                    let noise = 0.1 * (rng.gen::<f32>() - 0.5) * 3.46; // unit variance × 0.1
                    (v, f64::from(signal + noise))
                })
                .collect();
            p.adam_step(&adam, gradient);
        }
        p
    }

    /// |Σ θ − Σ truth| / Σ truth over the voxels `select` picks.
    fn relative_mass_error(
        p: &Parameters,
        voxels: &[(IVec3, f32)],
        select: impl Fn(IVec3) -> bool,
    ) -> f32 {
        let (sum, truth_sum) = voxels
            .iter()
            .filter(|(v, _)| select(*v))
            .fold((0.0, 0.0), |(s, t), &(v, truth)| (s + p.get(v), t + truth));
        ((sum - truth_sum) / truth_sum).abs()
    }

    /// What the global scale is for: a medium whose every voxel is 2.5× too thin, each voxel's
    /// gradient 10× noisier than its signal. Per-voxel steps alone barely move the mean; with the
    /// scale (whose gradient sums the signal of all voxels) it reaches the truth's.
    #[test]
    fn the_global_scale_finds_the_overall_density_under_per_voxel_noise() {
        let voxels = noisy_voxels();
        let mean_error = |fit_scale: bool| {
            let adam = Adam {
                lr: 0.01,
                fit_scale,
                ..Adam::default()
            };
            let p = optimise_under_noise(&voxels, adam, |_| 1.0 / 2.5, 7);
            relative_mass_error(&p, &voxels, |_| true)
        };
        let (with, without) = (mean_error(true), mean_error(false));
        assert!(with < 0.1, "with the scale: the mean is off by {with}");
        assert!(without > 0.3, "without: the mean is off by {without}");
    }

    /// The brick scales by hand: two bricks, each with one voxel θ = 2; gradients 0.5 and −0.25,
    /// so each brick's ∂loss/∂u_b = θ·g is 1 and −0.5, and Adam's first step is ∓lr in either.
    #[test]
    fn brick_scales_match_hand_computed_steps() {
        let adam = Adam {
            lr: 0.1,
            beta1: 0.9,
            beta2: 0.99,
            epsilon: 1e-8,
            fit_brick_scales: true,
            ..Adam::default()
        };
        let (a, b) = (IVec3::new(1, 1, 1), IVec3::new(9, 1, 1));
        let mut p = Parameters::default();
        p.set(a, 2.0);
        p.set(b, 2.0);
        p.adam_step(&adam, [(a, 0.5), (b, -0.25)]);
        // a: Δu_b = −0.1, the voxel's own step 0.1; b: Δu_b = +0.1, its own step −0.1.
        let expected_a = 2.0 * (-0.1f64).exp() - 0.1;
        let expected_b = 2.0 * 0.1f64.exp() + 0.1;
        assert!((p.get(a) as f64 - expected_a).abs() < 1e-6, "{}", p.get(a));
        assert!((p.get(b) as f64 - expected_b).abs() < 1e-6, "{}", p.get(b));
        // The global scale was not asked for.
        assert_eq!(p.scale_moments(), ScalarMoments::default());
    }

    /// What the brick scales are for: half of a medium 2.5× too thin, the other half 1.5× too
    /// dense, each voxel's gradient 10× noisier than its signal. One global scale cannot fix
    /// both halves (it settles between them) and per-voxel steps barely move (each leaves a half
    /// over 35 % off); a scale per brick brings both halves' means within 15 % of the truth's
    /// (11 % and 4 %: at a constant lr the brick scales' own noise is what is left).
    #[test]
    fn brick_scales_find_densities_that_differ_across_the_volume() {
        // Two bricks across x, so x < 8 and x ≥ 8 are four bricks each.
        let voxels = noisy_voxels();
        let start = |v: IVec3| if v.x < 8 { 1.0 / 2.5 } else { 1.5 };
        let worst_half = |adam: Adam| {
            let p = optimise_under_noise(&voxels, adam, start, 11);
            let left = relative_mass_error(&p, &voxels, |v| v.x < 8);
            left.max(relative_mass_error(&p, &voxels, |v| v.x >= 8))
        };
        let adam = Adam {
            lr: 0.01,
            ..Adam::default()
        };
        let bricks = worst_half(Adam {
            fit_brick_scales: true,
            ..adam
        });
        let global = worst_half(Adam {
            fit_scale: true,
            ..adam
        });
        let voxels_only = worst_half(adam);
        assert!(
            bricks < 0.15,
            "with brick scales: a half's mean is off by {bricks}"
        );
        assert!(
            global > 0.35,
            "with the global scale: a half's mean is off by {global}"
        );
        assert!(
            voxels_only > 0.35,
            "per-voxel steps alone: a half's mean is off by {voxels_only}"
        );
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
