//! One descent step of the unknown: Adam on the images' gradient and the priors', with θ ≥ 0 kept
//! by projection, and the bricks that hold only zeros and got none of the images' gradient
//! dropped.
//!
//! Only the images' gradient keeps a brick. A sparsity prior (l1, log) has a non-zero gradient
//! at θ = 0 in every stored voxel, so if its gradient kept bricks, no brick would ever be dropped
//! and the unknown's memory would follow its box instead of the volume; at θ = 0 its pull only
//! meets the projection, so dropping such a brick changes nothing but the memory.
//!
//! A brick is dropped only after `KEEP_IDLE_STEPS` steps without the images' gradient. Rays reach
//! a brick of empty space now and then, not every step; dropped at once, it would come back with
//! fresh moments, and Adam's first step with a small v̂ (bias-corrected with the run's step count,
//! not the brick's) moves every voxel by several learning rates whatever its gradient: a random
//! walk that the θ ≥ 0 projection turns into haze. The moments outlive about one first-moment
//! horizon, 1/(1 − β1) = 10 steps.

use glam::IVec3;
use rayon::prelude::*;

use crate::optimize::adam::{Adam, AdamStep};
use crate::optimize::brick_gradient::BrickGradient;
use crate::optimize::parameters::Parameters;
use crate::optimize::prior::Prior;
use crate::volume::brickmap::BRICK_VOXELS;

/// Steps without the images' gradient after which a brick that holds only zeros is dropped.
pub const KEEP_IDLE_STEPS: u32 = 10;

impl Parameters {
    /// One step on the images' gradient `data` and the priors', each R = weight × the mean over
    /// the level's `level_voxels` voxels (`Prior::evaluate`); returns Σ R.
    pub fn descend(
        &mut self,
        adam: &Adam,
        data: &BrickGradient,
        priors: &[Prior],
        level_voxels: u64,
    ) -> f64 {
        let mut prior_gradient = BrickGradient::default();
        let mut value = 0.0;
        for prior in priors {
            let (v, gradient) = prior.evaluate(self, level_voxels);
            value += v;
            prior_gradient.add(gradient);
        }
        self.adam_step(adam, data, &prior_gradient);
        value
    }

    /// One Adam step with the gradient `data + prior` (∂loss/∂θ per voxel; voxels in neither
    /// have gradient 0), then the projection θ ← max(θ, 0); bricks that hold only zeros and got
    /// none of `data` for `KEEP_IDLE_STEPS` steps are dropped with their moments.
    ///
    /// m ← β1·m + (1 − β1)·g,  v ← β2·v + (1 − β2)·g²,
    /// θ ← max(0, θ·e^(Δu + Δu_b) − lr · (m / (1 − β1ᵗ)) / (√(v / (1 − β2ᵗ)) + ε)),
    /// where Δu is the same Adam step of the global log-scale u, whose gradient is Σ θ·g over
    /// every voxel, when `adam.fit_scale`, and Δu_b that of the brick's log-scale u_b, on Σ θ·g
    /// over the brick, when `adam.fit_brick_scales` (each 0 otherwise).
    pub fn adam_step(&mut self, adam: &Adam, data: &BrickGradient, prior: &BrickGradient) {
        self.steps += 1;
        for key in data.keys() {
            self.brick(key);
        }
        let gradient_of = |key: IVec3| -> [f32; BRICK_VOXELS] {
            let zero = [0.0; BRICK_VOXELS];
            let (d, p) = (
                data.get(key).unwrap_or(&zero),
                prior.get(key).unwrap_or(&zero),
            );
            std::array::from_fn(|i| (d[i] + p[i]) as f32)
        };
        let at = AdamStep::new(adam, self.steps);
        let global = if adam.fit_scale {
            // Σ θ·g in f64 and in key order, so that it does not depend on the hash map's order.
            let sum: f64 = self
                .sorted_keys()
                .iter()
                .map(|key| self.bricks[key].scale_gradient(&gradient_of(*key)))
                .sum();
            self.scale.step(&at, sum as f32, 1.0)
        } else {
            1.0
        };
        // Each brick's step reads only its own state and gradient: in parallel, with the same
        // result at any thread count.
        self.bricks.par_iter_mut().for_each(|(key, brick)| {
            let grads = gradient_of(*key);
            let scale = if adam.fit_brick_scales {
                let g = brick.scale_gradient(&grads) as f32;
                global * brick.scale.step(&at, g, adam.brick_scale_lr)
            } else {
                global
            };
            for (i, &g) in grads.iter().enumerate() {
                let (m, v, step) = at.update(brick.m[i], brick.v[i], g);
                brick.m[i] = m;
                brick.v[i] = v;
                brick.theta[i] = (brick.theta[i] * scale - step).max(0.0).min(adam.theta_max);
            }
            brick.idle = if data.get(*key).is_some() {
                0
            } else {
                brick.idle.saturating_add(1)
            };
        });
        self.drop_empty(|brick| brick.idle < KEEP_IDLE_STEPS);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optimize::adam::ScalarMoments;
    use crate::optimize::prior::PriorKind;

    /// One Adam step on the images' gradient `voxels`, no prior.
    fn step(p: &mut Parameters, adam: &Adam, voxels: impl IntoIterator<Item = (IVec3, f64)>) {
        p.adam_step(
            adam,
            &BrickGradient::from_voxels(voxels),
            &BrickGradient::default(),
        );
    }

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
        step(&mut p, &adam, [(v, 2.0)]);
        // t = 1: m = 0.2, v = 0.04, m̂ = 2, v̂ = 4, step = 0.1 · 2 / 2 = 0.1.
        assert!((p.get(v) - 0.9).abs() < 1e-6, "{}", p.get(v));
        step(&mut p, &adam, [(v, -1.0)]);
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
        step(&mut p, &adam, [(v, 0.5)]);
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
        step(&mut p, &adam, [(v, -0.5)]);
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
        step(&mut p, &adam, [(v, 1e30)]);
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
            step(&mut p, &adam, gradient);
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
        step(&mut p, &adam, [(a, 0.5), (b, -0.25)]);
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
        step(&mut p, &adam, [(a, 10.0)]);
        assert_eq!(p.get(a), 0.0);
        // That brick got gradient this step, so it stays (with its moments) while it is idle…
        for _ in 1..KEEP_IDLE_STEPS {
            step(&mut p, &adam, []);
            assert_eq!(p.brick_count(), 1);
        }
        // …and is dropped at its KEEP_IDLE_STEPS-th step without gradient, holding only zeros.
        step(&mut p, &adam, []);
        assert_eq!(p.brick_count(), 0);
        // Gradient arriving in empty space creates a brick there, and a negative gradient grows θ.
        step(&mut p, &adam, [(far, -1.0)]);
        assert_eq!(p.brick_count(), 1);
        assert!(p.get(far) > 0.0);
        assert!(p.memory_bytes() >= 3 * BRICK_VOXELS * 4);
    }

    /// A sparsity prior's gradient is non-zero at θ = 0 (l1: 1; log: δ/(δ + θ) = 1), but only the
    /// images' gradient keeps a brick: a brick the images never reach is pulled to 0 (5 steps)
    /// and dropped `KEEP_IDLE_STEPS` later, and one they reach stays.
    #[test]
    fn a_brick_without_the_images_gradient_is_dropped_with_a_sparsity_prior() {
        for kind in [PriorKind::L1, PriorKind::Log] {
            let prior = Prior {
                kind,
                weight: 1.0,
                scale: 0.01,
                tv_epsilon: 1e-3,
            };
            let adam = Adam {
                lr: 0.01,
                ..Adam::default()
            };
            let (seen, unseen) = (IVec3::new(1, 2, 3), IVec3::new(100, 0, 0));
            let mut p = Parameters::default();
            p.set(seen, 0.5);
            p.set(unseen, 0.05);
            for i in 0..30 {
                // The images ask the seen voxel to stay (a gradient alternating in sign).
                let g = if i % 2 == 0 { 1e-3 } else { -1e-3 };
                let data = BrickGradient::from_voxels([(seen, g)]);
                p.descend(&adam, &data, &[prior], 1000);
            }
            assert_eq!(p.get(unseen), 0.0, "{kind:?}");
            let keys: Vec<IVec3> = p.brick_keys().collect();
            assert_eq!(
                keys,
                vec![seen >> 3],
                "{kind:?}: the unseen brick is dropped"
            );
            assert!(p.get(seen) > 0.1, "{kind:?}: {}", p.get(seen));
        }
    }
}
