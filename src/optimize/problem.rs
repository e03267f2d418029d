//! A run file loaded: the known scene, the views with their target images, the held-out views,
//! the truth (if any), and the unknown's domain and start. Everything here is fixed for the whole
//! run; the loop (`reconstruct`) changes only the unknown.

use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::cluster::Cluster;
use crate::gradient::loss::Loss;
use crate::io::fingerprint::Fingerprint;
use crate::io::vdb::{self, GridSelector, LevelSet};
use crate::optimize::adam::Adam;
use crate::optimize::hull::{self, Hull};
use crate::optimize::idle_keys;
use crate::optimize::optimizer_file;
use crate::optimize::parameters::Parameters;
use crate::optimize::prior::Prior;
use crate::optimize::resample::Moments;
use crate::optimize::run_file::{BoundsFile, EvalSpp, RunFile, StartFile, UnknownGrid};
use crate::optimize::scene_units::{self, SceneUnits};
use crate::optimize::settings_toml;
use crate::optimize::target_cache::TargetCache;
use crate::optimize::targets::{
    captures, check_captures, image_power, read_views, refuse_shared_pictures, view_specs,
    LightSets, ReadView, TargetRenderer,
};
use crate::optimize::view_bounds::seen_by_all;
use crate::optimize::view_files::target_pixels;
use crate::render::camera::Camera;
use crate::render::lights::Lights;
use crate::render::scene::{Scene, SceneNeeds};
use crate::render::scene_check::{MAX_EXTINCTION, MAX_LIGHT};
use crate::volume::brickmap::BrickMap;
use crate::volume::transform::MIN_VOXEL_SIZE;

pub use crate::optimize::targets::View;
pub use crate::optimize::unknown::Domain;
use crate::optimize::unknown::{
    check_scene, in_final_index_space, scene_with, start_parameters, without_unknown,
};

#[derive(Debug, Clone)]
pub struct Settings {
    pub adam: Adam,
    pub lr_decay: f32,
    pub level_lr: f32,
    pub loss: Loss,
    pub batch: u32,
    /// Pixels per iteration drawn across the training views; 0: `batch` whole views.
    pub batch_pixels: u32,
    /// Samples per pixel of the gradient pass.
    pub spp: u32,
    /// Samples per pixel of the primal render that gives the adjoint image.
    pub primal_spp: u32,
    /// The gradient pass's paths per pixel in proportion to the adjoint (`pixel_samples`).
    pub samples_follow_adjoint: bool,
    /// Suffix paths per camera path of the gradient pass (K).
    pub suffix_paths: u32,
    pub max_depth: u32,
    pub priors: Vec<Prior>,
    /// Gradient smoothing passes at the first level (`smoothing::smooth`), one more per
    /// upsampling; `None`: no smoothing.
    pub first_level_smoothing: Option<u32>,
    /// The fraction of the run from which the result is the mean of θ (`average`).
    pub average_from: f32,
    /// Fit the capture's exposure with the volume (`exposure`).
    pub fit_exposure: bool,
    /// The alpha loss's weight beside the colour's (0: colour only).
    pub alpha_weight: f32,
    pub moments: Moments,
    /// Fractions of the budget at which level k + 1 begins.
    pub level_starts: Vec<f32>,
    pub iterations: u32,
    pub eval_spp: EvalSpp,
    pub eval_every: u32,
    pub checkpoint_every: u32,
    pub seed: u64,
}

pub struct Problem {
    /// Lights, medium constants and render settings (its grid is replaced by the unknown's).
    pub scene: Scene,
    pub views: Vec<View>,
    pub holdouts: Vec<View>,
    /// The lights of the views (`View::light_set`); set 0 is the scene's.
    pub light_sets: Vec<Lights>,
    /// The training views' captures (`View::capture`; "" unnamed), each with its own exposure
    /// when it is fitted.
    pub captures: Vec<String>,
    /// The true grid, in the final level's index space.
    pub truth: Option<BrickMap>,
    pub domain: Domain,
    /// θ at level 0.
    pub start: Parameters,
    /// The name the written grids take (the scene's grid name: its density's or emission's).
    pub grid_name: String,
    /// Which of the scene's grids is unknown.
    pub unknown: UnknownGrid,
    pub settings: Settings,
    /// What a checkpoint must match to be resumed: every setting that changes the computation.
    pub fingerprint: String,
    /// The run file as this run resolved it (every key, absolute paths): `OUT/settings.toml`.
    pub settings_toml: String,
}

impl Problem {
    /// Reads the run file and everything it names (every rank reads for itself, then the ranks
    /// agree), renders the targets no image gives (all ranks together; read from and written to
    /// `target_cache` where given), and resolves what the scene decides (`scene_units`: the
    /// levels, the learning rate, the start, the priors' weights). `seed` overrides the run
    /// file's for the optimisation only: the targets are the run file's data, rendered from its
    /// own seed, so that runs of several seeds fit the same images.
    pub fn load(
        run_path: &Path,
        seed: Option<u64>,
        progress: bool,
        target_cache: Option<&Path>,
        cluster: &Cluster,
    ) -> Result<Problem> {
        let inputs = cluster.agree(Inputs::read(run_path, seed))?;
        // Files that differ between machines are named before any check of their content, which
        // could stop one rank while the others go on to render the targets together.
        if cluster.size() > 1 {
            cluster.check_same_inputs(&inputs.fingerprints())?;
        }
        let Inputs {
            mut file,
            scene,
            grids,
            mut domain,
            training,
            held_out,
            light_sets,
        } = inputs;
        let captures = captures(&training);
        let world_box = domain.world_box();
        let cameras: Vec<Camera> = training.iter().map(|v| v.camera()).collect();
        let centre = (world_box.0 + world_box.1) / 2.0;
        let voxel = domain.transform.voxel_size().min_element();
        let footprint = scene_units::footprint(&cameras, centre) / voxel;
        let levels = file.unknown.levels.clone().unwrap_or_else(|| {
            let count = scene_units::level_count(footprint)
                .min(scene_units::levels_the_box_allows(domain.shortest_edge()));
            scene_units::level_starts(count)
        });
        domain.levels = levels.len();
        domain.check_levels()?;
        file.unknown
            .check_levels_reach(levels.len(), domain.transform.voxel_size().max_element())?;
        file.unknown.levels = Some(levels);
        idle_keys::refuse_given(&file)
            .with_context(|| format!("invalid run file '{}'", run_path.display()))?;

        // A start the renderer cannot take is refused before any target is rendered.
        let theta_max = SceneUnits::theta_max_of(&scene, file.unknown.grid)?;
        let start_max = match &file.unknown.start {
            Some(StartFile::Constant(c)) => *c,
            Some(StartFile::Vdb(_)) => grids.start.as_ref().map_or(0.0, |g| g.bricks.max_value()),
            None => 0.0,
        };
        if start_max > theta_max {
            bail!(
                "unknown.start holds values up to {start_max:e}, above the largest this scene renders ({theta_max:e}: an extinction of {MAX_EXTINCTION:e} per world unit, or an emission of {MAX_LIGHT:e})"
            );
        }

        let truth = grids
            .truth
            .map(|t| in_final_index_space(t, &domain))
            .transpose()?;
        let unknown = file.unknown.grid;
        let truth_scene = truth.as_ref().map(|grid| {
            let bounds = domain.bounds(domain.levels);
            scene_with(&scene, unknown, grid.clone(), domain.transform, bounds)
        });
        // Only targets rendered from a truth are cached.
        let cache = match (target_cache, &truth_scene) {
            (Some(dir), Some(truth)) => Some(cluster.agree(TargetCache::open(dir, truth))?),
            _ => None,
        };
        let mut targets = TargetRenderer {
            truth: truth_scene,
            spp: file.target_spp,
            seed: file.target_seed.unwrap_or(file.seed),
            progress,
            rendered: 0,
            cached: 0,
            cache,
            cluster,
            alpha: file.optimizer.alpha_weight.is_some_and(|w| w > 0.0),
            rendered_alpha: 0,
        };
        let views = targets.complete(training, &light_sets, &captures, false)?;
        let mut holdouts = targets.complete(held_out, &light_sets, &captures, true)?;
        if let Some(cache) = targets.cache.as_ref().filter(|_| progress) {
            eprintln!(
                "{} of {} targets read from the target cache '{}'",
                targets.cached,
                targets.rendered,
                cache.dir().display()
            );
        }
        for holdout in &mut holdouts {
            holdout.relit = !views.iter().any(|v| v.light_set == holdout.light_set);
        }
        if let Some(batch) = file.optimizer.batch.filter(|&b| b as usize > views.len()) {
            bail!(
                "optimizer.batch is {batch} but there are only {} views",
                views.len()
            );
        }

        let units = match unknown {
            UnknownGrid::Density => SceneUnits::new(
                scene.medium.density_scale,
                domain.longest_edge(),
                image_power(&views)?,
            ),
            UnknownGrid::Emission => SceneUnits::for_emission(&scene, image_power(&views)?)?,
        };
        let view_pixels: Vec<u64> = views
            .iter()
            .map(|v| u64::from(v.camera.width) * u64::from(v.camera.height))
            .collect();
        file.optimizer.resolve(
            &units,
            &view_pixels,
            domain.voxel_count_at(0),
            unknown == UnknownGrid::Density,
        )?;
        let with_alpha = views.iter().filter(|v| v.alpha.is_some()).count();
        (file.optimizer).resolve_alpha(with_alpha, views.len(), unknown == UnknownGrid::Density)?;
        let start_file = file.unknown.start.clone().unwrap_or(StartFile::Constant(
            units.theta(scene_units::START_OPTICAL_DEPTH),
        ));
        let carve = *file.unknown.carve.get_or_insert(
            unknown == UnknownGrid::Density && matches!(start_file, StartFile::Constant(_)),
        );
        let hull = carve.then(|| {
            let tolerance = hull::BACKGROUND_TOLERANCE * hull::background_scale(&views);
            let (voxels, transform) = (domain.voxel_box(0), domain.transform(0));
            Hull::of(
                voxels,
                &transform,
                &views,
                &light_sets.lights,
                tolerance as f32,
            )
        });
        let start = start_parameters(&domain, &start_file, grids.start.as_ref(), hull.as_ref());
        file.unknown.start = Some(start_file);
        let settings = Settings::of(&file, &units, scene.settings.max_depth)?;
        refuse_exposure_with_relative_l2(&settings, &views)?;
        let mut notes = derivation_notes(unknown, &units, &settings, footprint);
        if let Some(hull) = &hull {
            notes += &format!(
                "the start's visual hull: {} of the first level's {} voxels seen through by a training view, their start 0\n",
                hull.seen_through_count(),
                domain.voxel_count_at(0)
            );
        }
        notes += &format!(
            "gradient paths per step per first-level voxel: {:.1} (by default first_level_smoothing is 1 for a density below {}, else 0)\n",
            file.optimizer.paths_per_step(&view_pixels) / domain.voxel_count_at(0) as f64,
            optimizer_file::SMOOTHING_PATHS_PER_VOXEL
        );
        let fingerprint = fingerprint(&file, &scene, views.iter().chain(&holdouts));
        let grid_name = match (unknown, &scene.medium.emission) {
            (UnknownGrid::Emission, Some(emission)) => emission.name.clone(),
            _ => scene.grid_name.clone(),
        };
        let scene = without_unknown(scene, unknown, &domain)?;
        Ok(Problem {
            settings_toml: settings_toml::resolved(&file, run_path, &notes)?,
            grid_name,
            unknown,
            scene,
            views,
            holdouts,
            light_sets: light_sets.lights,
            captures,
            truth,
            domain,
            start,
            settings,
            fingerprint,
        })
    }

    /// Points `scene` (lit by set `*lit`; `scene_at` gives set 0) at `view`: its camera, and its
    /// lights, cloned only when they change.
    pub fn look_through(&self, scene: &mut Scene, lit: &mut usize, view: &View) {
        scene.camera = view.camera;
        if *lit != view.light_set {
            scene.lights = self.light_sets[view.light_set].clone();
            *lit = view.light_set;
        }
    }

    /// The scene with `theta` (at level `level`) as its unknown grid.
    pub fn scene_at(&self, theta: BrickMap, level: usize) -> Scene {
        let (transform, bounds) = (self.domain.transform(level), self.domain.bounds(level));
        scene_with(&self.scene, self.unknown, theta, transform, bounds)
    }
}

/// A fitted exposure k moves a picture with alpha too (its background is k times the scene's
/// light), and relative-l2 divides by the target: its exposure gradient would need the target's
/// derivative in the denominator as well, which the step does not estimate. Refused rather than
/// fitted with a biased gradient.
fn refuse_exposure_with_relative_l2(settings: &Settings, views: &[View]) -> Result<()> {
    if settings.fit_exposure
        && settings.loss == Loss::RelativeL2
        && views.iter().any(|v| v.background.is_some())
    {
        bail!("optimizer.fit_exposure with loss = \"relative-l2\" and pictures with alpha is not supported (the target's background moves with the exposure, and relative-l2 divides by the target): use loss = \"l2\" or \"l1\"");
    }
    Ok(())
}

/// What a run file names, read: what one rank may fail to read while another does not.
struct Inputs {
    file: RunFile,
    scene: Scene,
    grids: KnownGrids,
    domain: Domain,
    training: Vec<ReadView>,
    held_out: Vec<ReadView>,
    light_sets: LightSets,
}

impl Inputs {
    /// The content of everything read, part by part, each named: the scene, the known grids and
    /// every view.
    fn fingerprints(&self) -> Vec<(String, u64)> {
        let mut scene = Fingerprint::default();
        scene.text(&crate::render::fingerprint::scene(&self.scene));
        let mut parts = vec![("the scene".to_string(), scene.value())];
        for (name, grid) in [
            ("truth", &self.grids.truth),
            ("unknown.start", &self.grids.start),
        ] {
            if let Some(grid) = grid {
                let mut f = Fingerprint::default();
                f.text(&format!("{:?}", grid.transform));
                crate::render::fingerprint::bricks(&mut f, &grid.bricks);
                parts.push((format!("the grid of {name}"), f.value()));
            }
        }
        parts.extend((self.training.iter().chain(&self.held_out)).map(ReadView::fingerprint));
        parts
    }

    fn read(run_path: &Path, seed: Option<u64>) -> Result<Inputs> {
        let mut file = RunFile::read(run_path)?;
        file.target_seed = Some(file.target_seed.unwrap_or(file.seed));
        file.seed = seed.unwrap_or(file.seed);
        let scene = Scene::load_as(
            &RunFile::resolve(run_path, &file.scene),
            SceneNeeds::Constants,
        )
        .context("scene")?;
        if scene.medium.density_scale <= 0.0 {
            bail!(
                "scene: medium.density_scale is {}: a vacuum's images do not depend on the grid, so it cannot be reconstructed from them",
                scene.medium.density_scale
            );
        }
        check_scene(&scene, file.unknown.grid).context("scene")?;
        let grids = KnownGrids::read(run_path, &file)?;
        if matches!(&file.unknown.bounds, BoundsFile::Named(name) if name == "views") {
            let specs = view_specs(run_path, "view", &file.view, &file.views, None)?;
            let cameras: Vec<Camera> = specs.iter().map(|s| s.camera).collect();
            let (min, max) = seen_by_all(&cameras)?;
            // Unless given: the finest view's pixel at the box's centre, the detail the views resolve.
            let voxel = file.unknown.voxel_size.map_or_else(
                || scene_units::footprint(&cameras, ((min + max) / 2.0).as_vec3()),
                f64::from,
            );
            // Found, not given: it must be one settings.toml can hold and a grid can be written with.
            if !(voxel >= f64::from(MIN_VOXEL_SIZE) && voxel <= f64::from(f32::MAX)) {
                bail!(
                    "unknown.bounds = \"views\" found a voxel of {voxel:e} (the finest view's pixel at the box's centre), which a grid cannot be written with (at least {MIN_VOXEL_SIZE:e}): give unknown.voxel_size, or the cameras in larger units"
                );
            }
            // The run goes on (and writes in settings.toml) with the box it found.
            file.unknown.bounds = BoundsFile::Box {
                min: min.as_vec3().to_array(),
                max: max.as_vec3().to_array(),
            };
            file.unknown.voxel_size = Some(voxel as f32);
        }
        let (domain, covered) = final_domain(&file, &grids)?;
        if let (BoundsFile::Box { max, .. }, Some(covered)) = (&mut file.unknown.bounds, covered) {
            // The run goes on (and writes in settings.toml) with the box its voxels cover.
            *max = covered;
        }
        let world_box = Some(domain.world_box());
        let training = view_specs(run_path, "view", &file.view, &file.views, world_box)?;
        let held_out = view_specs(
            run_path,
            "holdout",
            &file.holdout,
            &file.holdouts,
            world_box,
        )?;
        refuse_shared_pictures(&training, &held_out)?;
        let pixels = training.iter().chain(&held_out).map(|v| {
            let c = &v.camera;
            u64::from(c.width) * u64::from(c.height)
        });
        target_pixels(pixels.sum())?;
        let mut light_sets = LightSets::new(scene.lights.clone());
        let training = read_views(run_path, training, &mut light_sets)?;
        let held_out = read_views(run_path, held_out, &mut light_sets)?;
        check_captures(&held_out, &captures(&training))?;
        Ok(Inputs {
            file,
            scene,
            grids,
            domain,
            training,
            held_out,
            light_sets,
        })
    }
}

/// The grids a run file names: the truth and a start VDB.
struct KnownGrids {
    truth: Option<vdb::Grid>,
    start: Option<vdb::Grid>,
}

impl KnownGrids {
    fn read(run_path: &Path, file: &RunFile) -> Result<Self> {
        let read = |key: &str, name: &str, grid: Option<&String>| -> Result<vdb::Grid> {
            let selector = grid.map_or(GridSelector::Default, |g| GridSelector::Name(g.clone()));
            let path = RunFile::resolve(run_path, name);
            let grid = vdb::read_density(&path, &selector, LevelSet::Refuse)
                .with_context(|| key.to_string())?;
            if grid.bricks.min_value() < 0.0 {
                bail!(
                    "{key}: grid '{}' has negative values (min {}): densities are ≥ 0",
                    grid.name,
                    grid.bricks.min_value()
                );
            }
            Ok(grid)
        };
        let truth = file.truth.as_ref();
        Ok(KnownGrids {
            truth: truth
                .map(|t| read("truth", t, file.truth_grid.as_ref()))
                .transpose()?,
            start: match &file.unknown.start {
                Some(StartFile::Vdb(name)) => Some(read("unknown.start", name, None)?),
                _ => None,
            },
        })
    }
}

/// The unknown's final level: its transform and voxel box, from `unknown.bounds` (the levels
/// above it are decided later, from the views), and for a box, its max as the voxels cover it.
fn final_domain(file: &RunFile, grids: &KnownGrids) -> Result<(Domain, Option<[f32; 3]>)> {
    let (domain, covered) = match &file.unknown.bounds {
        BoundsFile::Named(name) => {
            let grid = if name == "truth" {
                grids.truth.as_ref()
            } else {
                grids.start.as_ref()
            };
            let grid = grid.context("validated: the grid named by unknown.bounds exists")?;
            let Some((lo, hi)) = grid.bricks.active_bounds() else {
                bail!(
                    "unknown.bounds = \"{name}\": grid '{}' has no active voxels",
                    grid.name
                );
            };
            let domain = Domain {
                transform: grid.transform,
                lo,
                hi,
                levels: 0,
            };
            (domain, None)
        }
        BoundsFile::Box { min, max } => {
            let voxel = file.unknown.voxel_size.context("validated")? as f64;
            let (min, max) = (min.map(f64::from).into(), max.map(f64::from).into());
            let (domain, covered) = Domain::over_box(min, max, voxel)?;
            (domain, Some(covered))
        }
    };
    Ok((domain.checked()?, covered))
}

impl Settings {
    /// From a run file whose `[optimizer]` and levels are resolved.
    fn of(file: &RunFile, units: &SceneUnits, max_depth: u32) -> Result<Settings> {
        let o = &file.optimizer;
        Ok(Settings {
            adam: o.adam(units),
            lr_decay: o.lr_decay,
            level_lr: o.level_lr,
            loss: o.loss,
            batch: o.batch.unwrap_or(1),
            batch_pixels: o.batch_pixels.unwrap_or(0),
            spp: o.spp,
            primal_spp: o.primal_spp.unwrap_or(o.spp),
            samples_follow_adjoint: o.samples_follow_adjoint,
            suffix_paths: o.suffix_paths,
            max_depth,
            priors: o.priors(units)?,
            first_level_smoothing: match o.smooth_gradient {
                true => Some(o.first_level_smoothing.context("resolved")?),
                false => None,
            },
            average_from: o.average_from,
            fit_exposure: o.fit_exposure,
            alpha_weight: o.alpha_weight.unwrap_or(0.0),
            moments: file.unknown.moments,
            level_starts: file.unknown.levels.clone().unwrap_or_default(),
            iterations: o.iterations,
            eval_spp: file.eval_spp,
            eval_every: file.eval_every,
            checkpoint_every: file.checkpoint_every,
            seed: file.seed,
        })
    }
}

/// What a run's settings.toml says of how its settings were derived.
fn derivation_notes(
    unknown: UnknownGrid,
    units: &SceneUnits,
    settings: &Settings,
    footprint_voxels: f64,
) -> String {
    let unit = match unknown {
        UnknownGrid::Density => {
            "grid value of optical depth 1 along the unknown box's longest edge"
        }
        UnknownGrid::Emission => "emission grid value of 1/25 of the targets' brightness (√P)",
    };
    let mut notes = format!(
        "Derived from the scene (see docs/reconstruct.md, \"Settings from the scene\"):\n\
         {unit}: u = {:.6e}\n\
         the targets' power (the L2 loss of a black image): P = {:.6e}\n\
         the finest view's pixel at the unknown's centre: {footprint_voxels:.2} final voxels\n\
         learning rate in grid values per step: lr = {:.6e}\n",
        units.theta_per_optical_depth, units.image_power, settings.adam.lr
    );
    for p in &settings.priors {
        notes += &format!(
            "prior {:?} in grid units: weight {:.6e}, scale {:.6e}, total variation's epsilon {:.6e}\n",
            p.kind, p.weight, p.scale, p.tv_epsilon
        );
    }
    notes
}

/// Every run-file value that changes the computation (not the evaluation or checkpoint cadence,
/// nor the iteration count: a run may be resumed and extended), the scene's content, the views'
/// cameras (a camera file changed under the same name is another run) and the target images'
/// (so is an image file replaced).
fn fingerprint<'a>(file: &RunFile, scene: &Scene, views: impl Iterator<Item = &'a View>) -> String {
    let mut optimizer = file.optimizer.clone();
    optimizer.iterations = 0;
    let mut f = Fingerprint::default();
    f.text(&format!(
        "{:?}|{:?}|{:?}|{:?}|{:?}|{:?}|{}|{}",
        file.truth,
        file.view,
        file.views,
        file.unknown,
        optimizer,
        file.truth_grid,
        file.seed,
        file.target_spp
    ))
    .text(&crate::render::fingerprint::scene(scene));
    for view in views {
        f.text(&format!("{:?}", view.camera))
            .text(&crate::io::fingerprint::image(&view.target));
        if let Some(alpha) = &view.alpha {
            f.text(&crate::io::fingerprint::image(alpha));
        }
    }
    f.hex()
}
