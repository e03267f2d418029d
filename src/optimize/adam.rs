//! Adam (Kingma & Ba 2015): its settings, one update of a parameter's moments, and the moments of
//! the log-scales of θ that a step may fit beside the voxels. What the moments belong to (voxels,
//! bricks, the whole grid) is `parameters`' and `descent`'s business.

/// Adam's settings; θ is projected onto 0 ≤ θ ≤ `theta_max` after every step.
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
    /// The largest value a step may leave (`SceneUnits::theta_max`).
    pub theta_max: f32,
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
            theta_max: f32::MAX,
        }
    }
}

/// Adam at step t, with the bias corrections 1 − β1ᵗ and 1 − β2ᵗ computed once for all voxels.
pub struct AdamStep {
    adam: Adam,
    correct1: f32,
    correct2: f32,
}

impl AdamStep {
    pub fn new(adam: &Adam, t: u32) -> Self {
        AdamStep {
            adam: *adam,
            correct1: 1.0 - adam.beta1.powi(t as i32),
            correct2: 1.0 - adam.beta2.powi(t as i32),
        }
    }

    /// One update of a parameter's moments (m, v) by the gradient g; returns the new moments and
    /// the step to subtract: lr · (m / (1 − β1ᵗ)) / (√(v / (1 − β2ᵗ)) + ε).
    #[inline]
    pub fn update(&self, m: f32, v: f32, g: f32) -> (f32, f32, f32) {
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
    pub fn step(&mut self, at: &AdamStep, g: f32, lr_factor: f32) -> f32 {
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
