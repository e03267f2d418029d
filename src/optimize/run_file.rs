//! Run files (TOML): what an inverse rendering knows (a scene file's lights, medium constants and
//! render settings), what it sees (views with target images, or orbits rendered from a true grid),
//! what it solves for (the unknown grid's box, resolution, start and levels) and how (Adam, loss,
//! batch, prior). Same conventions as scene files: unknown keys are errors, paths are relative to
//! the run file, every check names its key.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::optimize::idle_keys;
use crate::optimize::optimizer_file::OptimizerFile;
use crate::optimize::resample::Moments;
use crate::optimize::scene_units::MAX_LEVELS;
use crate::optimize::view_files::{
    check_sizes, check_view_lights, one_set, view_sets, view_tables, ViewFile, ViewSetFile,
};
use crate::render::scene_file::{table_or_value, TableOr};
use crate::volume::transform::MIN_VOXEL_SIZE;

#[derive(Debug, Clone, Deserialize, Serialize)]
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
    /// Samples per pixel of the held-out renders (fixed seed): a number, or "auto" (as many as
    /// keep the evaluation's noise below the error it measures).
    #[serde(default)]
    pub eval_spp: EvalSpp,
    /// Held-out evaluation every this many iterations (and at the end).
    #[serde(default = "default_eval_every")]
    pub eval_every: u32,
    /// A checkpoint every this many iterations (and at the end).
    #[serde(default = "default_checkpoint_every")]
    pub checkpoint_every: u32,
    /// The optimisation's random numbers (`--seed` overrides it).
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// The random numbers of the targets rendered from `truth` (default: `seed`). `--seed` leaves
    /// it: runs of several seeds fit the same images.
    pub target_seed: Option<u64>,
    #[serde(default)]
    pub view: Vec<ViewFile>,
    /// `[views]`, or `[[views]]` for sets under lights of their own (never empty).
    #[serde(default = "one_set", deserialize_with = "view_sets")]
    pub views: Vec<ViewSetFile>,
    #[serde(default)]
    pub holdout: Vec<ViewFile>,
    /// `[holdouts]`, or `[[holdouts]]` for sets under lights of their own (never empty).
    #[serde(default = "one_set", deserialize_with = "view_sets")]
    pub holdouts: Vec<ViewSetFile>,
    pub unknown: UnknownFile,
    #[serde(default)]
    pub optimizer: OptimizerFile,
    /// The file's own keys, as it gives them: a key that what the run derives (the levels, left
    /// out) leaves without effect is refused then, as one the file idles is when it is read.
    #[serde(skip)]
    pub given: toml::Table,
}

fn default_target_spp() -> u32 {
    1024
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

/// The held-out renders' samples per pixel (`evaluate::evaluate` says how "auto" chooses them).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum EvalSpp {
    #[default]
    Auto,
    Fixed(u32),
}

impl<'de> Deserialize<'de> for EvalSpp {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        use serde::de::Error;
        match toml::Value::deserialize(d)? {
            toml::Value::String(word) if word == "auto" => Ok(EvalSpp::Auto),
            toml::Value::Integer(n) => u32::try_from(n)
                .map(EvalSpp::Fixed)
                .map_err(|_| D::Error::custom(format!("{n} samples per pixel is out of range"))),
            other => Err(D::Error::custom(format!(
                "{other} is neither a number of samples per pixel nor \"auto\""
            ))),
        }
    }
}

impl Serialize for EvalSpp {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            EvalSpp::Auto => s.serialize_str("auto"),
            EvalSpp::Fixed(n) => s.serialize_u32(*n),
        }
    }
}

/// The unknown grid.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct UnknownFile {
    /// Which of the scene's grids is unknown: "density" (the default), or "emission" (flame
    /// tomography: the scene's density is known, and its `medium.emission` says what the unknown
    /// emission grid's values mean).
    #[serde(default)]
    pub grid: UnknownGrid,
    /// "truth" (the truth's active box and transform), "start" (the start VDB's), or
    /// `{ min = [x, y, z], max = [x, y, z] }`, a world box.
    pub bounds: BoundsFile,
    /// The final voxel size (world units) of a world box; with "truth" or "start" the grid's own.
    pub voxel_size: Option<f32>,
    /// The voxel size of the first level, if given: it must be the final one × 2^(levels).
    pub start_voxel_size: Option<f32>,
    /// A constant (grid value), or a VDB whose (trilinear) field is sampled at the first level's
    /// voxels; default a constant of optical depth `scene_units::START_OPTICAL_DEPTH` along the
    /// box's longest edge.
    pub start: Option<StartFile>,
    /// Clear a constant start where a training view sees only the background (`hull`); default
    /// on for a density unknown. An emission unknown's scene keeps its density, so its
    /// background is not the environment: there it must stay off.
    pub carve: Option<bool>,
    /// Fractions of the budget at which the grid is upsampled ×2 per axis, increasing in (0, 1);
    /// default as many as make the coarsest voxel about a pixel (`scene_units::level_count`).
    pub levels: Option<Vec<f32>>,
    /// Adam's moments after an upsampling: "reset" or "resample".
    #[serde(default = "default_moments")]
    pub moments: Moments,
}

/// The scene grid a run solves for.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum UnknownGrid {
    #[default]
    Density,
    Emission,
}

/// A voxel size a grid can be written with.
fn voxel_size_ok(v: f32) -> bool {
    v >= MIN_VOXEL_SIZE && v.is_finite()
}

fn default_moments() -> Moments {
    Moments::Resample
}

#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum BoundsFile {
    Named(String),
    Box { min: [f32; 3], max: [f32; 3] },
}

/// `BoundsFile`'s table form, its keys checked (`scene_file::table_or_value` says why).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BoxFile {
    #[serde(deserialize_with = "crate::io::exact::array")]
    min: [f32; 3],
    #[serde(deserialize_with = "crate::io::exact::array")]
    max: [f32; 3],
}

impl<'de> Deserialize<'de> for BoundsFile {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        Ok(match table_or_value(d)? {
            TableOr::Table(BoxFile { min, max }) => BoundsFile::Box { min, max },
            TableOr::Value(name) => BoundsFile::Named(name),
        })
    }
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(untagged)]
pub enum StartFile {
    Constant(f32),
    Vdb(String),
}

impl RunFile {
    pub fn read(path: &Path) -> Result<RunFile> {
        let text = crate::io::input::read_text(path)
            .with_context(|| format!("cannot read run file '{}'", path.display()))?;
        let mut file: RunFile = toml::from_str(&text).map_err(|e| {
            // A scene file is what a run file names (the reverse of `SceneFile::parse`'s hint).
            let table = toml::from_str::<toml::Table>(&text).ok();
            match table.is_some_and(|t| t.contains_key("medium") && !t.contains_key("scene")) {
                true => anyhow::anyhow!(
                    "{} is a scene file (it has a [medium]), not a run file: give it to `volgrad render`, or name it as a run file's `scene`",
                    path.display()
                ),
                false => anyhow::anyhow!("{}: {}", path.display(), e.to_string().trim_end()),
            }
        })?;
        file.given = toml::from_str(&text)?;
        (crate::io::exact::within_f32(&text).and_then(|_| file.validate()))
            .and_then(|_| idle_keys::refuse_given(&file))
            .with_context(|| format!("invalid run file '{}'", path.display()))?;
        Ok(file)
    }

    /// A path named in the run file, relative to it.
    pub fn resolve(run_path: &Path, name: &str) -> PathBuf {
        run_path.parent().unwrap_or(Path::new(".")).join(name)
    }

    /// Whether some view's target is rendered from the truth: a view without `image`, or an orbit.
    pub fn renders_from_truth(&self) -> bool {
        (self.view.iter().chain(&self.holdout)).any(|v| v.image.is_none())
            || (self.views.iter().chain(&self.holdouts)).any(|set| !set.orbit.is_empty())
    }

    /// The checks that need no file: numbers in range, keys that go together.
    pub fn validate(&self) -> Result<()> {
        if !(self.views.iter()).any(|set| set.has_views(&self.view)) {
            bail!("no views: give [[view]] entries or a [views.orbit]");
        }
        if !(self.holdouts.iter()).any(|set| set.has_views(&self.holdout)) {
            bail!("no held-out views: give [[holdout]] entries or a [holdouts.orbit] (quality is measured on views the gradients never see)");
        }
        if self.target_spp == 0 {
            bail!("target_spp must be at least 1");
        }
        if self.eval_spp == EvalSpp::Fixed(0) {
            bail!("eval_spp must be at least 1, or \"auto\"");
        }
        for (key, n) in [
            ("eval_every", self.eval_every),
            ("checkpoint_every", self.checkpoint_every),
        ] {
            if n == 0 {
                bail!("{key} must be at least 1");
            }
        }
        if self.renders_from_truth() && self.truth.is_none() {
            bail!("truth: views without an image ([views.orbit], [holdouts.orbit], or a [[view]] without `image`) are rendered from a true grid; give `truth = \"file.vdb\"` or an image per view");
        }
        let mut sets = view_tables("view", &self.view, &self.views);
        sets.extend(view_tables("holdout", &self.holdout, &self.holdouts));
        check_sizes(&sets)?;
        check_view_lights(&sets)?;
        self.unknown.validate(self.truth.is_some())?;
        self.optimizer.validate()
    }
}

impl UnknownFile {
    fn validate(&self, has_truth: bool) -> Result<()> {
        match &self.bounds {
            BoundsFile::Named(name) if name == "truth" || name == "start" => {
                if name == "truth" && !has_truth {
                    bail!("unknown.bounds = \"truth\" needs a `truth` grid");
                }
                if name == "start" && !matches!(self.start, Some(StartFile::Vdb(_))) {
                    bail!("unknown.bounds = \"start\" needs unknown.start to be a VDB file");
                }
                if self.voxel_size.is_some() {
                    bail!("unknown.voxel_size: with bounds = \"{name}\" the final voxel size is that grid's; leave it out");
                }
            }
            BoundsFile::Named(name) if name == "views" => {
                if let Some(v) = self.voxel_size.filter(|v| !voxel_size_ok(*v)) {
                    bail!("unknown.voxel_size must be a number from {MIN_VOXEL_SIZE:e} up (got {v})");
                }
            }
            BoundsFile::Named(name) => bail!(
                "unknown.bounds must be \"truth\", \"start\", \"views\" or {{ min = [x, y, z], max = [x, y, z] }} (got \"{name}\")"
            ),
            BoundsFile::Box { min, max } => {
                if !(0..3).all(|a| min[a].is_finite() && max[a].is_finite() && min[a] < max[a]) {
                    bail!("unknown.bounds: min must be below max on every axis (got {min:?}, {max:?})");
                }
                match self.voxel_size {
                    Some(v) if voxel_size_ok(v) => {}
                    Some(v) => bail!("unknown.voxel_size must be a number from {MIN_VOXEL_SIZE:e} up (got {v})"),
                    None => bail!("unknown.voxel_size: a world box needs the final voxel size"),
                }
            }
        }
        if let Some(v) = self.start_voxel_size.filter(|v| !voxel_size_ok(*v)) {
            bail!("unknown.start_voxel_size must be a number from {MIN_VOXEL_SIZE:e} up (got {v})");
        }
        if let Some(StartFile::Constant(c)) = self.start {
            if !(c >= 0.0 && c.is_finite()) {
                bail!("unknown.start must be a value ≥ 0 or a VDB file (got {c})");
            }
        }
        if self.carve == Some(true) {
            if self.grid == UnknownGrid::Emission {
                bail!("unknown.carve: an emission unknown's scene keeps its density, so a pixel's background is not the environment; leave carve out");
            }
            if matches!(self.start, Some(StartFile::Vdb(_))) {
                bail!("unknown.carve clears a constant start; a start VDB is taken as it is");
            }
        }
        let levels = self.levels.as_deref().unwrap_or_default();
        for (i, f) in levels.iter().enumerate() {
            let previous = if i == 0 { 0.0 } else { levels[i - 1] };
            if !(*f > previous && *f < 1.0) {
                bail!(
                    "unknown.levels must be increasing fractions of the budget in (0, 1) (got {levels:?})"
                );
            }
        }
        if levels.len() > MAX_LEVELS {
            bail!(
                "unknown.levels: {} upsamplings start at 1/{} of the final resolution per axis; at most {MAX_LEVELS}",
                levels.len(),
                2f64.powi(levels.len() as i32)
            );
        }
        Ok(())
    }

    /// An error unless `start_voxel_size`, upsampled `levels` times, is `final_voxel_size`.
    pub fn check_levels_reach(&self, levels: usize, final_voxel_size: f64) -> Result<()> {
        if let Some(start) = self.start_voxel_size {
            let reached = start as f64 / f64::from(1u32 << levels);
            if (reached / final_voxel_size - 1.0).abs() > 1e-3 {
                bail!(
                    "unknown.levels: {levels} upsampling(s) from start_voxel_size {start} end at voxel size {reached}, not the final {final_voxel_size} (start_voxel_size must be the final × 2^{levels})"
                );
            }
        }
        Ok(())
    }
}

#[cfg(test)]
#[path = "run_file_tests.rs"]
mod tests;
