//! Run files (TOML): what an inverse rendering knows (a scene file's lights, medium constants and
//! render settings), what it sees (views with target images, or orbits rendered from a true grid),
//! what it solves for (the unknown grid's box, resolution, start and levels) and how (Adam, loss,
//! batch, prior). Same conventions as scene files: unknown keys are errors, paths are relative to
//! the run file, every check names its key.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::Deserialize;

use crate::gradient::loss::Loss;
use crate::optimize::parameters::Adam;
use crate::optimize::prior::{Prior, PriorKind};
use crate::optimize::resample::Moments;
use crate::optimize::views::Orbit;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunFile {
    /// The scene file: lights, medium constants (density_scale, albedo, phase_g, filter) and
    /// render settings. Its grid is not used: the unknown replaces it.
    pub scene: String,
    /// The true grid of a synthetic study: targets are rendered from it, and the volume error is
    /// measured against it.
    pub truth: Option<String>,
    /// The truth's grid name (default: "density", or the file's only grid).
    pub truth_grid: Option<String>,
    #[serde(default = "default_target_spp")]
    pub target_spp: u32,
    /// Samples per pixel of the held-out renders (fixed seed), far above the training spp so that
    /// evaluation noise stays below the error measured.
    #[serde(default = "default_eval_spp")]
    pub eval_spp: u32,
    /// Held-out evaluation every this many iterations (and at the end).
    #[serde(default = "default_eval_every")]
    pub eval_every: u32,
    /// A checkpoint every this many iterations (and at the end).
    #[serde(default = "default_checkpoint_every")]
    pub checkpoint_every: u32,
    #[serde(default = "default_seed")]
    pub seed: u64,
    #[serde(default)]
    pub view: Vec<ViewFile>,
    #[serde(default)]
    pub views: ViewSetFile,
    #[serde(default)]
    pub holdout: Vec<ViewFile>,
    #[serde(default)]
    pub holdouts: ViewSetFile,
    pub unknown: UnknownFile,
    #[serde(default)]
    pub optimizer: OptimizerFile,
}

fn default_target_spp() -> u32 {
    1024
}
fn default_eval_spp() -> u32 {
    256
}
fn default_eval_every() -> u32 {
    10
}
fn default_checkpoint_every() -> u32 {
    100
}
fn default_seed() -> u64 {
    1
}

/// A camera as in a scene file, with the image it sees.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewFile {
    pub position: [f32; 3],
    pub target: [f32; 3],
    #[serde(default = "crate::render::scene::default_up")]
    pub up: [f32; 3],
    pub fov_deg: f32,
    pub width: u32,
    pub height: u32,
    /// The target image (linear; any format OpenImageIO reads). Without it the view's target is
    /// rendered from `truth`.
    pub image: Option<String>,
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewSetFile {
    pub orbit: Option<OrbitFile>,
}

/// Cameras on a Fibonacci spiral around the unknown's box, targets rendered from `truth`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OrbitFile {
    pub count: u32,
    pub elevation_deg: [f32; 2],
    pub distance: f32,
    pub fov_deg: f32,
    pub width: u32,
    pub height: u32,
    /// Turns the whole spiral about +y, e.g. to put held-out views between the training views.
    #[serde(default)]
    pub azimuth_offset_deg: f32,
}

impl OrbitFile {
    pub fn orbit(&self) -> Orbit {
        Orbit {
            count: self.count,
            elevation_deg: (self.elevation_deg[0], self.elevation_deg[1]),
            distance: self.distance,
            fov_deg: self.fov_deg,
            width: self.width,
            height: self.height,
            azimuth_offset_deg: self.azimuth_offset_deg,
        }
    }
}

/// The unknown grid.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnknownFile {
    /// "truth" (the truth's active box and transform), "start" (the start VDB's), or
    /// `{ min = [x, y, z], max = [x, y, z] }`, a world box.
    pub bounds: BoundsFile,
    /// The final voxel size (world units) of a world box; with "truth" or "start" the grid's own.
    pub voxel_size: Option<f32>,
    /// The voxel size of the first level, if given: it must be the final one × 2^(levels).
    pub start_voxel_size: Option<f32>,
    /// A constant, or a VDB whose (trilinear) field is sampled at the first level's voxels.
    pub start: StartFile,
    /// Fractions of the budget at which the grid is upsampled ×2 per axis, increasing in (0, 1).
    #[serde(default)]
    pub levels: Vec<f32>,
    /// Adam's moments after an upsampling: "reset" or "resample".
    #[serde(default = "default_moments")]
    pub moments: Moments,
}

fn default_moments() -> Moments {
    Moments::Resample
}

#[derive(Debug, Clone, Deserialize)]
#[serde(untagged)]
pub enum BoundsFile {
    Named(String),
    Box { min: [f32; 3], max: [f32; 3] },
}

#[derive(Debug, Clone, Deserialize)]
#[serde(untagged)]
pub enum StartFile {
    Constant(f32),
    Vdb(String),
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OptimizerFile {
    #[serde(default = "default_lr")]
    pub lr: f32,
    #[serde(default = "default_beta1")]
    pub beta1: f32,
    #[serde(default = "default_beta2")]
    pub beta2: f32,
    #[serde(default = "default_epsilon")]
    pub epsilon: f32,
    /// The learning rate at the end of the budget, as a fraction of `lr` (exponential decay in
    /// between); 1 keeps it constant.
    #[serde(default = "default_lr_decay")]
    pub lr_decay: f32,
    /// The learning rate is multiplied by this at each upsampling: a finer voxel is crossed by
    /// half the path length, so the same change in θ moves the image half as much, while its
    /// gradient is noisier; 0.5 keeps the change of optical depth per step and voxel what it was.
    #[serde(default = "default_level_lr")]
    pub level_lr: f32,
    #[serde(default = "default_loss")]
    pub loss: Loss,
    /// Views per iteration: a random batch, reshuffled each epoch.
    #[serde(default = "default_batch")]
    pub batch: u32,
    /// Samples per pixel of each view's gradient pass (and of its primal render, unless
    /// `primal_spp` is given).
    #[serde(default = "default_spp")]
    pub spp: u32,
    /// Samples per pixel of the primal render whose residual against the target is the adjoint
    /// image. Near convergence an 8-spp residual is mostly Monte Carlo noise, which the gradient
    /// pass multiplies into every voxel; the primal costs less per sample than the gradient pass.
    #[serde(default)]
    pub primal_spp: Option<u32>,
    /// Iterations when the command line gives neither --iterations nor --budget.
    #[serde(default = "default_iterations")]
    pub iterations: u32,
    /// One prior (`prior = { kind = …, weight = … }`) or several, summed (`prior = [{ … }, { … }]`).
    #[serde(default, deserialize_with = "one_or_many")]
    pub prior: Vec<PriorFile>,
    /// Filter the gradient with [1 2 1]/4 per axis, once per upsampling done (`smoothing`).
    #[serde(default = "default_smooth_gradient")]
    pub smooth_gradient: bool,
    /// Fit a global log-scale of θ beside the voxels (`Adam::fit_scale`).
    #[serde(default = "default_fit_scale")]
    pub fit_scale: bool,
    /// Fit a log-scale of θ per brick beside the voxels (`Adam::fit_brick_scales`).
    #[serde(default = "default_fit_scale")]
    pub fit_brick_scales: bool,
    /// The brick log-scales' learning rate as a multiple of `lr` (`Adam::brick_scale_lr`).
    #[serde(default = "default_brick_scale_lr")]
    pub brick_scale_lr: f32,
}

impl Default for OptimizerFile {
    fn default() -> Self {
        toml::from_str("").expect("every optimizer key has a default")
    }
}

fn default_lr() -> f32 {
    0.05
}
fn default_beta1() -> f32 {
    0.9
}
fn default_beta2() -> f32 {
    0.999
}
fn default_epsilon() -> f32 {
    1e-8
}
fn default_lr_decay() -> f32 {
    1.0
}
fn default_level_lr() -> f32 {
    0.5
}
fn default_smooth_gradient() -> bool {
    true
}
fn default_fit_scale() -> bool {
    false
}
fn default_brick_scale_lr() -> f32 {
    1.0
}
fn default_loss() -> Loss {
    Loss::L2
}
fn default_batch() -> u32 {
    4
}
fn default_spp() -> u32 {
    4
}
fn default_iterations() -> u32 {
    100
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PriorFile {
    pub kind: PriorKind,
    pub weight: f32,
    /// δ of the log prior, required by it and refused by the others.
    pub scale: Option<f32>,
}

/// A table or an array of tables, each read as a `PriorFile` (its errors, e.g. an unknown kind,
/// kept as they are: an untagged enum would replace them with "did not match any variant").
fn one_or_many<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<PriorFile>, D::Error> {
    let items = match toml::Value::deserialize(d)? {
        toml::Value::Array(items) => items,
        one => vec![one],
    };
    items
        .into_iter()
        .map(|item| PriorFile::deserialize(item).map_err(serde::de::Error::custom))
        .collect()
}

impl RunFile {
    pub fn read(path: &Path) -> Result<RunFile> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read run file '{}'", path.display()))?;
        let file: RunFile = toml::from_str(&text)
            .map_err(|e| anyhow::anyhow!("{}: {}", path.display(), e.to_string().trim_end()))?;
        file.validate()
            .with_context(|| format!("invalid run file '{}'", path.display()))?;
        Ok(file)
    }

    /// A path named in the run file, relative to it.
    pub fn resolve(run_path: &Path, name: &str) -> PathBuf {
        run_path.parent().unwrap_or(Path::new(".")).join(name)
    }

    /// The checks that need no file: numbers in range, keys that go together.
    pub fn validate(&self) -> Result<()> {
        if self.view.is_empty() && self.views.orbit.is_none() {
            bail!("no views: give [[view]] entries or a [views.orbit]");
        }
        if self.holdout.is_empty() && self.holdouts.orbit.is_none() {
            bail!("no held-out views: give [[holdout]] entries or a [holdouts.orbit] (quality is measured on views the gradients never see)");
        }
        for (key, spp) in [("target_spp", self.target_spp), ("eval_spp", self.eval_spp)] {
            if spp == 0 {
                bail!("{key} must be at least 1");
            }
        }
        for (key, n) in [
            ("eval_every", self.eval_every),
            ("checkpoint_every", self.checkpoint_every),
        ] {
            if n == 0 {
                bail!("{key} must be at least 1");
            }
        }
        let needs_truth = self
            .view
            .iter()
            .chain(&self.holdout)
            .any(|v| v.image.is_none())
            || self.views.orbit.is_some()
            || self.holdouts.orbit.is_some();
        if needs_truth && self.truth.is_none() {
            bail!("truth: views without an image ([views.orbit], [holdouts.orbit], or a [[view]] without `image`) are rendered from a true grid; give `truth = \"file.vdb\"` or an image per view");
        }
        self.unknown.validate(self.truth.is_some())?;
        self.optimizer.validate()
    }
}

impl UnknownFile {
    fn validate(&self, has_truth: bool) -> Result<()> {
        match &self.bounds {
            BoundsFile::Named(name) if name == "truth" && !has_truth => {
                bail!("unknown.bounds = \"truth\" needs a `truth` grid")
            }
            BoundsFile::Named(name) if name == "start" => {
                if !matches!(self.start, StartFile::Vdb(_)) {
                    bail!("unknown.bounds = \"start\" needs unknown.start to be a VDB file");
                }
            }
            BoundsFile::Named(name) if name != "truth" => bail!(
                "unknown.bounds must be \"truth\", \"start\" or {{ min = [x, y, z], max = [x, y, z] }} (got \"{name}\")"
            ),
            BoundsFile::Box { min, max } => {
                if !(0..3).all(|a| min[a].is_finite() && max[a].is_finite() && min[a] < max[a]) {
                    bail!("unknown.bounds: min must be below max on every axis (got {min:?}, {max:?})");
                }
                match self.voxel_size {
                    Some(v) if v > 0.0 && v.is_finite() => {}
                    Some(v) => bail!("unknown.voxel_size must be a positive number (got {v})"),
                    None => bail!("unknown.voxel_size: a world box needs the final voxel size"),
                }
            }
            BoundsFile::Named(_) => {
                if self.voxel_size.is_some() {
                    bail!("unknown.voxel_size: with bounds = \"truth\" or \"start\" the final voxel size is that grid's; leave it out");
                }
            }
        }
        if let StartFile::Constant(c) = self.start {
            if !(c >= 0.0 && c.is_finite()) {
                bail!("unknown.start must be a value ≥ 0 or a VDB file (got {c})");
            }
        }
        for (i, f) in self.levels.iter().enumerate() {
            let previous = if i == 0 { 0.0 } else { self.levels[i - 1] };
            if !(*f > previous && *f < 1.0) {
                bail!(
                    "unknown.levels must be increasing fractions of the budget in (0, 1) (got {:?})",
                    self.levels
                );
            }
        }
        if self.levels.len() > 6 {
            bail!(
                "unknown.levels: {} upsamplings start at 1/{} of the final resolution per axis; at most 6",
                self.levels.len(),
                1u32 << self.levels.len()
            );
        }
        Ok(())
    }

    /// An error unless `start_voxel_size`, upsampled `levels` times, is `final_voxel_size`.
    pub fn check_levels_reach(&self, final_voxel_size: f64) -> Result<()> {
        if let Some(start) = self.start_voxel_size {
            let reached = start as f64 / f64::from(1u32 << self.levels.len());
            if (reached / final_voxel_size - 1.0).abs() > 1e-3 {
                bail!(
                    "unknown.levels: {} upsampling(s) from start_voxel_size {start} end at voxel size {reached}, not the final {final_voxel_size} (start_voxel_size must be the final × 2^{})",
                    self.levels.len(),
                    self.levels.len()
                );
            }
        }
        Ok(())
    }
}

impl OptimizerFile {
    fn validate(&self) -> Result<()> {
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            bail!("optimizer.lr must be a positive number (got {})", self.lr);
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
        if self.loss == Loss::Mean {
            bail!("optimizer.loss must compare against the targets: l2, l1 or relative-l2");
        }
        for (key, n) in [
            ("batch", self.batch),
            ("spp", self.spp),
            ("primal_spp", self.primal_spp.unwrap_or(self.spp)),
            ("iterations", self.iterations),
        ] {
            if n == 0 {
                bail!("optimizer.{key} must be at least 1");
            }
        }
        for p in &self.prior {
            if !(p.weight >= 0.0 && p.weight.is_finite()) {
                bail!(
                    "optimizer.prior.weight must be a number ≥ 0 (got {})",
                    p.weight
                );
            }
            match (p.kind, p.scale) {
                (PriorKind::Log, Some(d)) if d > 0.0 && d.is_finite() => {}
                (PriorKind::Log, d) => bail!(
                    "optimizer.prior.scale must be a number > 0 for kind \"log\" (got {})",
                    d.map_or("nothing".into(), |d| d.to_string())
                ),
                (_, Some(_)) => bail!("optimizer.prior.scale is only for kind \"log\""),
                (_, None) => {}
            }
        }
        Ok(())
    }

    pub fn adam(&self) -> Adam {
        Adam {
            lr: self.lr,
            beta1: self.beta1,
            beta2: self.beta2,
            epsilon: self.epsilon,
            fit_scale: self.fit_scale,
            fit_brick_scales: self.fit_brick_scales,
            brick_scale_lr: self.brick_scale_lr,
        }
    }

    pub fn priors(&self) -> Vec<Prior> {
        let prior = |p: &PriorFile| Prior {
            kind: p.kind,
            weight: p.weight,
            scale: p.scale.unwrap_or(0.0),
        };
        self.prior.iter().map(prior).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"
        scene = "s.toml"
        truth = "t.vdb"
        [views.orbit]
        count = 4
        elevation_deg = [0, 45]
        distance = 10
        fov_deg = 40
        width = 8
        height = 8
        [[holdout]]
        position = [0, 0, 10]
        target = [0, 0, 0]
        fov_deg = 40
        width = 8
        height = 8
        [unknown]
        bounds = "truth"
        start = 0.1
        levels = [0.5]
    "#;

    fn check(text: &str) -> Result<RunFile> {
        let file: RunFile = toml::from_str(text).map_err(|e| anyhow::anyhow!("{e}"))?;
        file.validate()?;
        Ok(file)
    }

    #[test]
    fn a_good_file_parses_with_defaults() {
        let f = check(GOOD).unwrap();
        assert_eq!(f.optimizer.batch, 4);
        assert_eq!(f.optimizer.loss, Loss::L2);
        assert_eq!(f.unknown.moments, Moments::Resample);
        assert_eq!(f.eval_spp, 256);
    }

    /// Each bad value is refused with a message naming its key.
    #[test]
    fn bad_values_name_their_key() {
        let cases = [
            (GOOD.replace("[views.orbit]", "[x.orbit]"), "unknown field"),
            (format!("{GOOD}\n[optimizer]\nlr = 0"), "optimizer.lr"),
            (format!("{GOOD}\n[optimizer]\nlr = -1"), "optimizer.lr"),
            (format!("{GOOD}\n[optimizer]\nbatch = 0"), "optimizer.batch"),
            (
                format!("{GOOD}\n[optimizer]\nprimal_spp = 0"),
                "optimizer.primal_spp",
            ),
            (
                format!("{GOOD}\n[optimizer]\nbrick_scale_lr = 0"),
                "optimizer.brick_scale_lr",
            ),
            (
                format!("{GOOD}\n[optimizer]\nloss = \"mean\""),
                "optimizer.loss",
            ),
            (
                format!("{GOOD}\n[optimizer]\nloss = \"l3\""),
                "unknown variant",
            ),
            (format!("{GOOD}\n[optimizer]\nbeta2 = 1"), "optimizer.beta2"),
            (
                GOOD.replace("levels = [0.5]", "levels = [0.5, 0.4]"),
                "unknown.levels",
            ),
            (
                GOOD.replace("levels = [0.5]", "levels = [1.0]"),
                "unknown.levels",
            ),
            (GOOD.replace("start = 0.1", "start = -1"), "unknown.start"),
            (
                GOOD.replace("bounds = \"truth\"", "bounds = \"all\""),
                "unknown.bounds",
            ),
            (
                GOOD.replace(
                    "bounds = \"truth\"",
                    "bounds = { min = [0,0,0], max = [1,1,1] }",
                ),
                "unknown.voxel_size",
            ),
            (
                GOOD.replace(
                    "bounds = \"truth\"",
                    "bounds = { min = [0,0,0], max = [0,1,1] }\nvoxel_size = 0.1",
                ),
                "unknown.bounds",
            ),
            (GOOD.replace("truth = \"t.vdb\"", ""), "truth"),
            (
                GOOD.replace("[views.orbit]", "[holdouts.orbit]"),
                "no views",
            ),
            (GOOD.replace("[[holdout]]", "[[view]]"), "no held-out views"),
            (format!("target_spp = 0\n{GOOD}"), "target_spp"),
            (format!("colour = 1\n{GOOD}"), "unknown field"),
            (format!("eval_every = 0\n{GOOD}"), "eval_every"),
            (
                format!("{GOOD}\n[optimizer]\nlevel_lr = 0"),
                "optimizer.level_lr",
            ),
            (
                format!("{GOOD}\n[optimizer]\nprior = {{ kind = \"tvv\", weight = 1 }}"),
                "unknown variant",
            ),
            (
                format!("{GOOD}\n[optimizer]\nprior = {{ kind = \"log\", weight = 1 }}"),
                "optimizer.prior.scale",
            ),
            (
                format!("{GOOD}\n[optimizer]\nprior = {{ kind = \"log\", weight = 1, scale = 0 }}"),
                "optimizer.prior.scale",
            ),
            (
                format!(
                    "{GOOD}\n[optimizer]\nprior = [{{ kind = \"tv\", weight = 1, scale = 0.1 }}]"
                ),
                "optimizer.prior.scale",
            ),
            (
                format!("{GOOD}\n[optimizer]\nprior = [{{ kind = \"tv\", weight = -1 }}]"),
                "optimizer.prior.weight",
            ),
        ];
        for (text, key) in cases {
            let err = format!("{:#}", check(&text).unwrap_err());
            assert!(err.contains(key), "expected '{key}' in: {err}");
        }
    }

    #[test]
    fn one_prior_or_several() {
        let one = format!("{GOOD}\n[optimizer]\nprior = {{ kind = \"tv\", weight = 0.5 }}");
        let priors = check(&one).unwrap().optimizer.priors();
        assert_eq!(priors.len(), 1);
        assert_eq!((priors[0].kind, priors[0].weight), (PriorKind::Tv, 0.5));
        let two = format!(
            "{GOOD}\n[optimizer]\nprior = [{{ kind = \"tv\", weight = 0.5 }}, {{ kind = \"log\", weight = 2, scale = 0.01 }}]"
        );
        let priors = check(&two).unwrap().optimizer.priors();
        assert_eq!(priors.len(), 2);
        assert_eq!(
            (priors[1].kind, priors[1].weight, priors[1].scale),
            (PriorKind::Log, 2.0, 0.01)
        );
        assert!(check(GOOD).unwrap().optimizer.priors().is_empty());
    }

    #[test]
    fn levels_must_reach_the_final_voxel_size() {
        let mut f = check(GOOD).unwrap();
        f.unknown.start_voxel_size = Some(2.0);
        f.unknown.check_levels_reach(1.0).unwrap();
        let err = f.unknown.check_levels_reach(0.5).unwrap_err().to_string();
        assert!(err.contains("unknown.levels"), "{err}");
    }
}
