//! `[optimizer]` of a run file: Adam's settings and schedule, the loss, the batch and samples per
//! view, the priors and the optional fits beside the voxels. Every key has a default; every check
//! names its key.

use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};

use crate::gradient::loss::Loss;
use crate::optimize::adam::Adam;
use crate::optimize::prior::{Prior, PriorKind};
use crate::optimize::scene_units::{self, SceneUnits};

/// `[optimizer]`: every key may be left out (`Default`). The keys that would be grid values are
/// optical depths and weights relative to the images (`scene_units`), so the defaults carry over
/// from scene to scene; `Problem::load` resolves them and `OUT/settings.toml` shows the result.
/// Pixels per iteration by default: the sample-matching paper's recipe (32,768 pixels over all
/// views), which is also 8 whole views of 64², the cloud study's batch.
pub const BATCH_PIXELS: u32 = 32_768;

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct OptimizerFile {
    /// The learning rate as the optical depth along the unknown box's longest edge that one
    /// Adam step may change (each voxel moves by about lr = τ·u in grid values; default
    /// `STEP_OPTICAL_DEPTH`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub step_optical_depth: Option<f32>,
    /// The learning rate in grid values, instead of `step_optical_depth` (settings.toml writes
    /// the one a run used, as `lr`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lr: Option<f32>,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
    /// The learning rate at the end of the budget, as a fraction of the first (exponential decay
    /// in between); 1 keeps it constant.
    pub lr_decay: f32,
    /// The learning rate is multiplied by this at each upsampling (see "One rule per level" in
    /// `reconstruct`).
    pub level_lr: f32,
    pub loss: Loss,
    /// Views per iteration: a random batch, reshuffled each epoch (default: 8, or every view
    /// when there are fewer, as long as they hold at most `BATCH_PIXELS`; larger views are
    /// batched by pixels instead).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub batch: Option<u32>,
    /// Pixels per iteration instead of whole views: drawn across every training view (a uniform
    /// view, then a uniform pixel of it), so that the cost of an iteration does not follow the
    /// views' size or number, and ranks split pixels, not views.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub batch_pixels: Option<u32>,
    /// Samples per pixel of each view's gradient pass.
    pub spp: u32,
    /// Samples per pixel of the primal render whose residual against the target is the adjoint
    /// image (default: 2 × spp). Near convergence a low-spp residual is mostly Monte Carlo noise,
    /// which the gradient pass multiplies into every voxel; a primal sample costs about 1/5 of a
    /// gradient one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub primal_spp: Option<u32>,
    /// The gradient pass's paths go to each pixel in proportion to its adjoint |δ| (the
    /// residual's weight there), as many in all as `spp` uniform paths would cost
    /// (`gradient::pixel_samples`); false: `spp` through every pixel.
    pub samples_follow_adjoint: bool,
    /// Suffix paths per camera path of the gradient pass (K, `grad --suffix-paths`): fewer make an
    /// iteration cheaper and its gradient noisier; on the worked example 1, 3 and 4 end within the
    /// seeds' spread of 2 in the same 10 minutes.
    pub suffix_paths: u32,
    /// Iterations when the command line gives neither --iterations nor --budget.
    pub iterations: u32,
    /// One prior (`prior = { kind = …, weight = … }`) or several, summed (`prior = [{ … }, { … }]`);
    /// `prior = []` for none. Weights are relative to the images' power, the log prior's `scale`
    /// is an optical depth (`scene_units`).
    #[serde(deserialize_with = "one_or_many")]
    pub prior: Vec<PriorFile>,
    /// Filter the gradient with [1 2 1]/4 per axis (`smoothing`): `first_level_smoothing` passes
    /// at the first level, one more per upsampling done.
    pub smooth_gradient: bool,
    /// Smoothing passes at the first level; by default one where a step's paths are few for the
    /// first level's voxels, none where they are many (`first_level_smoothing_for`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub first_level_smoothing: Option<u32>,
    /// From this fraction of the run on, the result is a mean of θ over the steps since (or
    /// since the last upsampling, if later), the later steps weighing more: `average`. 1: θ as
    /// the last step left it.
    pub average_from: f32,
    /// Fit a global log-scale of θ beside the voxels (`Adam::fit_scale`).
    pub fit_scale: bool,
    /// Fit a log-scale of θ per brick beside the voxels (`Adam::fit_brick_scales`).
    pub fit_brick_scales: bool,
    /// The brick log-scales' learning rate as a multiple of lr (`Adam::brick_scale_lr`).
    pub brick_scale_lr: f32,
    /// Fit the capture's exposure: one factor the renders are scaled by before they meet the
    /// targets, for pictures whose absolute brightness is not known (`exposure`).
    pub fit_exposure: bool,
    /// The weight of the alpha loss beside the colour's: alpha (1 − the camera ray's
    /// transmittance) counts as this many colour channels. Default: `ALPHA_WEIGHT` when every
    /// training image has alpha, 0 otherwise; above 0, views rendered from a truth get alpha
    /// targets too.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub alpha_weight: Option<f32>,
}

impl Default for OptimizerFile {
    fn default() -> Self {
        let prior = |kind, weight, scale| PriorFile {
            kind,
            weight,
            scale,
        };
        OptimizerFile {
            step_optical_depth: None,
            lr: None,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            lr_decay: scene_units::LR_DECAY,
            level_lr: 0.5,
            loss: Loss::L2,
            batch: None,
            batch_pixels: None,
            spp: 8,
            primal_spp: None,
            samples_follow_adjoint: true,
            suffix_paths: crate::gradient::adjoint::DEFAULT_SUFFIX_PATHS,
            iterations: 100,
            prior: vec![
                prior(PriorKind::Tv, scene_units::DEFAULT_TV_WEIGHT, None),
                prior(
                    PriorKind::Log,
                    scene_units::DEFAULT_LOG_WEIGHT,
                    Some(scene_units::DEFAULT_LOG_SCALE),
                ),
            ],
            smooth_gradient: true,
            first_level_smoothing: None,
            average_from: AVERAGE_FROM,
            fit_scale: true,
            fit_brick_scales: true,
            fit_exposure: false,
            alpha_weight: None,
            brick_scale_lr: 3.0,
        }
    }
}

/// `alpha_weight` when every training image has alpha: alpha counts as much as one colour
/// channel.
pub const ALPHA_WEIGHT: f32 = 1.0;

/// Below this many gradient paths per step per first-level voxel, a density's first level gets a
/// smoothing pass of its own by default (`first_level_smoothing_for`). Measured, not derived: in
/// the runs of docs/reconstruct.md ("One rule per level") the pass raised the held-out PSNR of the
/// worked example (3.8 paths per voxel, +0.13 dB) and of the cloud (10.0, +0.47 dB) and lowered it
/// for the quick ball (19.0, −0.23 dB over six seeds) and the smoke (47.8, −1.6 dB); 14 is the
/// geometric mean of the two neighbours across the change.
pub const SMOOTHING_PATHS_PER_VOXEL: f64 = 14.0;
/// Where the average of θ begins by default, as a fraction of the run. Measured against the last
/// iterate of the same 10-minute run (docs/reconstruct.md, "The average of the last steps"): on
/// the worked example the mean from 0.6 on scored +0.11 dB held-out and +0.20 dB relit, from 0.75
/// or 0.9 on less; on the cloud, whose last level is its last 5 %, +0.02 dB.
pub const AVERAGE_FROM: f32 = 0.6;

/// The most smoothing passes at the first level (n passes blur by σ = √(n/2) voxels).
pub const MAX_FIRST_LEVEL_SMOOTHING: u32 = 8;

/// The most suffix paths per camera path (as `grad --suffix-paths`).
pub const MAX_SUFFIX_PATHS: u32 = 64;

/// The most pixels one iteration may draw (2²⁴: 512 times the sample-matching paper's 32,768).
pub const MAX_BATCH_PIXELS: u32 = 1 << 24;

/// The most samples per pixel of an iteration's passes (`spp`, `primal_spp`): 2²⁰, far past any
/// use, so that the default primal_spp = 2 × spp cannot wrap.
pub const MAX_SPP: u32 = 1 << 20;

/// The largest `alpha_weight`: alpha counting as a million colour channels is colour not fitted
/// at all, and far beyond it the loss's squared gradients overflow f32 (at 10²² a run empties its
/// grid without a word).
pub const MAX_ALPHA_WEIGHT: f32 = 1e6;

/// The first level's smoothing passes by default. For a density, one where a step's `paths` are
/// fewer than `SMOOTHING_PATHS_PER_VOXEL` per first-level voxel, so that each voxel's gradient is
/// mostly Monte Carlo noise, which the pass averages over its neighbours; none where they are
/// more: there the gradient already says what the level can resolve, and the pass, whose response
/// cos²(ω/2) per axis is near 0 at the level's finest detail, only holds the level back from it.
/// For an emission grid (`extinction` false) none: on both flames, at 8 and 41 paths per voxel,
/// the pass left the held-out PSNR where it was or lowered it and raised the volume error by a
/// third or more, the blur spreading light into voxels the flame leaves dark (docs/reconstruct.md,
/// "One rule per level").
pub fn first_level_smoothing_for(paths: f64, first_level_voxels: u64, extinction: bool) -> u32 {
    u32::from(extinction && paths < SMOOTHING_PATHS_PER_VOXEL * first_level_voxels as f64)
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct PriorFile {
    pub kind: PriorKind,
    pub weight: f32,
    /// δ of the log prior, required by it and refused by the others.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scale: Option<f32>,
}

/// A table or an array of tables, each read as a `T` (its errors, e.g. an unknown kind, kept as
/// they are: an untagged enum would replace them with "did not match any variant").
pub(super) fn one_or_many<'de, D, T>(d: D) -> Result<Vec<T>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: serde::de::DeserializeOwned,
{
    let items = match toml::Value::deserialize(d)? {
        toml::Value::Array(items) => items,
        one => vec![one],
    };
    items
        .into_iter()
        .map(|item| T::deserialize(item).map_err(serde::de::Error::custom))
        .collect()
}

/// The largest prior weight per unit of θ: a voxel's pull from it (a few times this for total
/// variation's six neighbours) squared stays far inside f32.
const MAX_PRIOR_WEIGHT: f32 = 1e18;

impl OptimizerFile {
    pub fn validate(&self) -> Result<()> {
        if self.step_optical_depth.is_some() && self.lr.is_some() {
            bail!("optimizer.step_optical_depth and optimizer.lr both set the learning rate: give one");
        }
        for (key, value) in [
            ("step_optical_depth", self.step_optical_depth),
            ("lr", self.lr),
        ] {
            match value {
                Some(v) if !(v > 0.0 && v.is_finite()) => {
                    bail!("optimizer.{key} must be a positive number (got {v})")
                }
                _ => {}
            }
        }
        for (key, beta) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&beta) {
                bail!("optimizer.{key} must be in [0, 1) (got {beta})");
            }
        }
        if !(self.epsilon > 0.0 && self.epsilon.is_finite()) {
            bail!(
                "optimizer.epsilon must be a positive number (got {})",
                self.epsilon
            );
        }
        if !(self.lr_decay > 0.0 && self.lr_decay <= 1.0) {
            bail!(
                "optimizer.lr_decay must be in (0, 1] (got {})",
                self.lr_decay
            );
        }
        if !(self.level_lr > 0.0 && self.level_lr <= 1.0) {
            bail!(
                "optimizer.level_lr must be in (0, 1] (got {})",
                self.level_lr
            );
        }
        if !(self.brick_scale_lr > 0.0 && self.brick_scale_lr.is_finite()) {
            bail!(
                "optimizer.brick_scale_lr must be a positive number (got {})",
                self.brick_scale_lr
            );
        }
        if let Some(n) = self
            .first_level_smoothing
            .filter(|&n| n > MAX_FIRST_LEVEL_SMOOTHING)
        {
            bail!("optimizer.first_level_smoothing must be at most {MAX_FIRST_LEVEL_SMOOTHING} (got {n})");
        }
        if !(0.0..=1.0).contains(&self.average_from) {
            bail!(
                "optimizer.average_from must be a fraction of the run in [0, 1] (got {})",
                self.average_from
            );
        }
        if let Some(w) = self
            .alpha_weight
            .filter(|w| !(0.0..=MAX_ALPHA_WEIGHT).contains(w))
        {
            bail!(
                "optimizer.alpha_weight must be a number from 0 to {MAX_ALPHA_WEIGHT:e} (got {w})"
            );
        }
        if self.loss == Loss::Mean {
            bail!("optimizer.loss must compare against the targets: l2, l1 or relative-l2");
        }
        if self.batch.is_some() && self.batch_pixels.is_some() {
            bail!("optimizer.batch (views) and optimizer.batch_pixels (pixels) exclude each other: give one");
        }
        if let Some(n) = self.batch_pixels.filter(|&n| n > MAX_BATCH_PIXELS) {
            bail!(
                "optimizer.batch_pixels is {n}, more than {MAX_BATCH_PIXELS} pixels per iteration"
            );
        }
        for (key, n) in [
            ("batch", self.batch.unwrap_or(1)),
            ("batch_pixels", self.batch_pixels.unwrap_or(1)),
            ("spp", self.spp),
            ("primal_spp", self.primal_spp.unwrap_or(self.spp)),
            ("suffix_paths", self.suffix_paths),
            ("iterations", self.iterations),
        ] {
            if n == 0 {
                bail!("optimizer.{key} must be at least 1");
            }
        }
        for (key, n) in [
            ("spp", self.spp),
            ("primal_spp", self.primal_spp.unwrap_or(1)),
        ] {
            if n > MAX_SPP {
                bail!("optimizer.{key} is {n}, more than {MAX_SPP} samples per pixel");
            }
        }
        if self.suffix_paths > MAX_SUFFIX_PATHS {
            bail!(
                "optimizer.suffix_paths is {}, more than {MAX_SUFFIX_PATHS}",
                self.suffix_paths
            );
        }
        for p in &self.prior {
            if !(p.weight >= 0.0 && p.weight.is_finite()) {
                bail!(
                    "optimizer.prior.weight must be a number ≥ 0 (got {})",
                    p.weight
                );
            }
            match (p.kind, p.scale) {
                // The prior's pull at θ = 0 is weight/δ: a δ near f32's smallest numbers makes it
                // overflow in the optimiser's squared gradients, a NaN loss steps later.
                (PriorKind::Log, Some(d)) if (1e-12..=f32::MAX).contains(&d) => {}
                (PriorKind::Log, d) => bail!(
                    "optimizer.prior.scale must be a number from 1e-12 up for kind \"log\" (got {})",
                    d.map_or("nothing".into(), |d| d.to_string())
                ),
                (_, Some(_)) => bail!("optimizer.prior.scale is only for kind \"log\""),
                (_, None) => {}
            }
        }
        Ok(())
    }

    /// Fills in what the scene decides: the learning rate (from `step_optical_depth`), the batch,
    /// `primal_spp` (2 × spp) and the first level's smoothing. The batch, unless given: 8 whole
    /// views (or every view, when there are fewer) if they hold at most `BATCH_PIXELS`, else
    /// `BATCH_PIXELS` pixels drawn across the views, so that an iteration costs the same on 64²
    /// views and on 800² ones. `view_pixels` are the training views' sizes, `first_level_voxels`
    /// the unknown's voxels at its first level; `extinction`: the unknown is the density.
    pub fn resolve(
        &mut self,
        units: &SceneUnits,
        view_pixels: &[u64],
        first_level_voxels: u64,
        extinction: bool,
    ) -> Result<()> {
        let lr = self.learning_rate(units);
        if !(lr > 0.0 && lr.is_finite()) {
            // Checked as given, a step_optical_depth can still give a rate beyond f32 (or 0)
            // over the scene's units: a run at it would fly to the clamp (or stand still).
            bail!(
                "optimizer.step_optical_depth = {} gives a learning rate of {lr} grid units, which is no step: give a smaller (or larger) one, or lr",
                self.step_optical_depth.unwrap_or(scene_units::STEP_OPTICAL_DEPTH)
            );
        }
        // settings.toml gives the learning rate as `lr` alone: with both, it would not load.
        self.lr = Some(lr);
        self.step_optical_depth = None;
        if self.batch.is_none() && self.batch_pixels.is_none() {
            let views = view_pixels.len().min(8);
            // The largest views: what a batch of whole views may cost.
            let mut sizes = view_pixels.to_vec();
            sizes.sort_unstable_by(|a, b| b.cmp(a));
            if sizes[..views].iter().sum::<u64>() > u64::from(BATCH_PIXELS) {
                self.batch_pixels = Some(BATCH_PIXELS);
            } else {
                self.batch = Some(views as u32);
            }
        }
        self.primal_spp = Some(self.primal_spp.unwrap_or(2 * self.spp));
        let paths = self.paths_per_step(view_pixels);
        self.first_level_smoothing =
            Some(self.first_level_smoothing.unwrap_or_else(|| {
                first_level_smoothing_for(paths, first_level_voxels, extinction)
            }));
        Ok(())
    }

    /// The gradient pass's paths in one step once the batch is resolved: its pixels (a batch of
    /// views takes their mean size) times `spp`.
    pub fn paths_per_step(&self, view_pixels: &[u64]) -> f64 {
        let pixels = match (self.batch_pixels, self.batch) {
            (Some(pixels), _) => f64::from(pixels),
            (None, batch) => {
                let mean = view_pixels.iter().sum::<u64>() as f64 / view_pixels.len().max(1) as f64;
                f64::from(batch.unwrap_or(1)) * mean
            }
        };
        pixels * f64::from(self.spp)
    }

    /// Fills in `alpha_weight` once the views are known: `with_alpha` of the `views` training
    /// views have an alpha target; `extinction`: the unknown is the density (alpha depends on
    /// nothing else).
    pub fn resolve_alpha(
        &mut self,
        with_alpha: usize,
        views: usize,
        extinction: bool,
    ) -> Result<()> {
        let weight = match self.alpha_weight {
            Some(w) if w > 0.0 && !extinction => bail!(
                "optimizer.alpha_weight is {w}, but alpha (1 − transmittance) does not depend on the emission grid: set it to 0"
            ),
            Some(w) if w > 0.0 && with_alpha == 0 => bail!(
                "optimizer.alpha_weight is {w}, but no training view has an alpha target: their images have no alpha channel and there is no truth to render one from"
            ),
            Some(w) => w,
            None if extinction && with_alpha == views && views > 0 => ALPHA_WEIGHT,
            None => 0.0,
        };
        self.alpha_weight = Some(weight);
        Ok(())
    }

    /// The learning rate in grid values: `lr`, or `step_optical_depth` along the box.
    fn learning_rate(&self, units: &SceneUnits) -> f32 {
        let step = self
            .step_optical_depth
            .unwrap_or(scene_units::STEP_OPTICAL_DEPTH);
        self.lr.unwrap_or_else(|| units.theta(step))
    }

    /// Adam's settings once `resolve` has run.
    pub fn adam(&self, units: &SceneUnits) -> Adam {
        Adam {
            lr: self.learning_rate(units),
            beta1: self.beta1,
            beta2: self.beta2,
            epsilon: self.epsilon,
            fit_scale: self.fit_scale,
            fit_brick_scales: self.fit_brick_scales,
            brick_scale_lr: self.brick_scale_lr,
            theta_max: units.theta_max,
        }
    }

    /// The priors in grid units; an error if a weight is too large to be one there: its pull on
    /// a voxel beyond `MAX_PRIOR_WEIGHT`, whose square Adam's second moment would not hold (every
    /// step then 0: the run stood still), or its penalty infinite.
    pub fn priors(&self, units: &SceneUnits) -> Result<Vec<Prior>> {
        let prior = |(i, p): (usize, &PriorFile)| {
            let prior = units.prior(p.kind, p.weight, p.scale);
            if !prior.weight.is_finite() || prior.weight > MAX_PRIOR_WEIGHT {
                bail!(
                    "optimizer.prior[{i}].weight {:e} is too large: relative to these images and this box it is {:e} per unit of θ, above {MAX_PRIOR_WEIGHT:e}, whose square the optimiser holds",
                    p.weight,
                    f64::from(p.weight) * units.image_power / units.theta_per_optical_depth
                );
            }
            Ok(prior)
        };
        self.prior.iter().enumerate().map(prior).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Whole views while 8 of them cost at most the recipe's 32,768 pixels (the cloud's 64²
    /// views), pixel batches of that size above it; a batch the file gives is kept.
    #[test]
    fn the_default_batch_follows_the_views_size() {
        let units = SceneUnits::new(0.1, 500.0, 0.04);
        let resolved = |views: &[u64], batch: Option<u32>| {
            let mut o = OptimizerFile {
                batch,
                ..OptimizerFile::default()
            };
            o.resolve(&units, views, 1, true).unwrap();
            (o.batch, o.batch_pixels)
        };
        assert_eq!(resolved(&[64 * 64; 20], None), (Some(8), None));
        assert_eq!(resolved(&[32 * 32; 3], None), (Some(3), None));
        assert_eq!(resolved(&[96 * 96; 24], None), (None, Some(BATCH_PIXELS)));
        assert_eq!(resolved(&[800 * 800; 2], None), (None, Some(BATCH_PIXELS)));
        // One large view among small ones counts: a batch may draw it.
        let mut mixed = vec![64 * 64; 10];
        mixed[3] = 256 * 256;
        assert_eq!(resolved(&mixed, None), (None, Some(BATCH_PIXELS)));
        assert_eq!(resolved(&[96 * 96; 24], Some(8)), (Some(8), None));
    }

    /// The first level's smoothing by default: one pass for a density whose step has fewer than
    /// `SMOOTHING_PATHS_PER_VOXEL` paths per first-level voxel (8 views of 64² at 8 spp, or
    /// 32,768 pixels of larger views, are 262,144 paths: 14 per voxel at 18,724.6 voxels), none
    /// above it or for an emission grid; a value the file gives is kept.
    #[test]
    fn the_first_level_smoothing_follows_the_paths_per_voxel() {
        let units = SceneUnits::new(0.1, 500.0, 0.04);
        let resolved = |views: &[u64], voxels, extinction, given| {
            let mut o = OptimizerFile {
                first_level_smoothing: given,
                ..OptimizerFile::default()
            };
            o.resolve(&units, views, voxels, extinction).unwrap();
            o.first_level_smoothing
        };
        for views in [&[64 * 64; 16][..], &[96 * 96; 24][..]] {
            assert_eq!(resolved(views, 26_208, true, None), Some(1));
            assert_eq!(resolved(views, 18_725, true, None), Some(1));
            assert_eq!(resolved(views, 18_724, true, None), Some(0));
            assert_eq!(resolved(views, 5_488, true, None), Some(0));
            assert_eq!(resolved(views, 26_208, false, None), Some(0));
            assert_eq!(resolved(views, 5_488, true, Some(2)), Some(2));
        }
    }

    /// Alpha is fitted by default only when every training view has an alpha target and the
    /// unknown is the density; asked for without alpha targets, or for an emission grid, it is
    /// refused naming the key.
    #[test]
    fn the_alpha_weight_follows_the_targets() {
        let resolved = |weight: Option<f32>, with_alpha, views, extinction| {
            let mut o = OptimizerFile {
                alpha_weight: weight,
                ..OptimizerFile::default()
            };
            o.resolve_alpha(with_alpha, views, extinction)
                .map(|_| o.alpha_weight.unwrap())
                .map_err(|e| e.to_string())
        };
        assert_eq!(resolved(None, 24, 24, true), Ok(ALPHA_WEIGHT));
        assert_eq!(resolved(None, 23, 24, true), Ok(0.0));
        assert_eq!(resolved(None, 24, 24, false), Ok(0.0));
        assert_eq!(resolved(Some(0.5), 3, 24, true), Ok(0.5));
        assert_eq!(resolved(Some(0.0), 24, 24, false), Ok(0.0));
        for (with_alpha, extinction, needle) in
            [(0, true, "no training view"), (24, false, "emission")]
        {
            let error = resolved(Some(1.0), with_alpha, 24, extinction).unwrap_err();
            assert!(
                error.contains("optimizer.alpha_weight") && error.contains(needle),
                "{error}"
            );
        }
    }
}
