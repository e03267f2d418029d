//! The captures' exposures, fitted with the volume: pictures whose absolute brightness nobody
//! wrote down (a photograph's exposure, a render's sun strength known to ±30 %) are compared with
//! the render scaled by one factor k = e^x per capture (`ViewSetFile::capture`), and each x is a
//! parameter like θ.
//!
//! With I′ = k·I the image compared to the targets and δ′ = ∂loss/∂I′ its adjoint:
//! ∂loss/∂θ = Σ δ′·k·∂I/∂θ (the gradient pass runs on k·δ′), and ∂loss/∂x = Σ δ′·(I′ − k·B)
//! over the batch's pixels and channels, B the background a picture with alpha was composited
//! over (the target's part that scales with k too; 0 for opaque pictures): one dot product per
//! iteration, no extra paths. x steps by Adam in log units, so that a factor of 1.3 is as far
//! from 1 as one of 1/1.3.

use crate::optimize::adam::{Adam, AdamStep, ScalarMoments};

/// Adam's step size for x: the most one step moves the factor is e^0.02 (2 %), so that ±30 %
/// is some 15 steps away, slow beside θ's first steps but without overshoot from their noise.
pub const EXPOSURE_STEP: f32 = 0.02;

/// The factor k of capture `capture` among the fitted `exposures` (1 for one never stepped: a run
/// that does not fit exposures has none).
pub fn factor_of(exposures: &[Exposure], capture: usize) -> f32 {
    exposures.get(capture).map_or(1.0, Exposure::factor)
}

/// Every capture's factor, `captures` of them.
pub fn factors(exposures: &[Exposure], captures: usize) -> Vec<f32> {
    (0..captures).map(|c| factor_of(exposures, c)).collect()
}

/// x = ln k and its Adam moments (checkpointed with θ).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Exposure {
    pub log: f32,
    pub moments: ScalarMoments,
}

impl Exposure {
    /// k = e^x: what the render is multiplied by before it meets the targets.
    pub fn factor(&self) -> f32 {
        self.log.exp()
    }

    /// One Adam step of x on its gradient `g` = ∂loss/∂x, at Adam's step count `t` (≥ 1); a
    /// non-finite gradient is skipped, moments unchanged.
    pub fn step(&mut self, adam: &Adam, t: u32, g: f64) {
        if !g.is_finite() {
            return;
        }
        let at = AdamStep::new(
            &Adam {
                lr: EXPOSURE_STEP,
                ..*adam
            },
            t.max(1),
        );
        let (m, v, step) = at.update(self.moments.m, self.moments.v, g as f32);
        self.moments = ScalarMoments { m, v };
        self.log -= step;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Fitting k·I to targets 1.3·I by ∂loss/∂x = Σ δ′·I′ (L2 loss: δ′ = 2(k·I − T)/n) finds
    /// k = 1.3, from above as from below.
    #[test]
    fn the_factor_of_brighter_targets_is_found() {
        let image = [0.2f32, 0.5, 0.05, 0.8];
        for truth in [1.3f32, 1.0 / 1.3] {
            let mut e = Exposure::default();
            for t in 1..=400 {
                let k = e.factor();
                let g: f64 = image
                    .iter()
                    .map(|&i| {
                        let delta = 2.0 * (k * i - truth * i) / image.len() as f32;
                        f64::from(delta * k * i)
                    })
                    .sum();
                e.step(&Adam::default(), t, g);
            }
            assert!((e.factor() / truth - 1.0).abs() < 0.01, "{}", e.factor());
        }
    }
}
