//! `volgrad grad`: the gradient of a loss with respect to every voxel, as a VDB and a picture;
//! optionally the derivative image of a box; with `--estimator fd`, finite differences instead.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::builder::PossibleValue;
use clap::ValueEnum;
use glam::IVec3;

use super::values::{self, FdDirection, IndexBox};
use super::{
    check_same_job, report_non_finite, set_threads, warn_if_empty, AdjointArgs, Domain, FdArgs,
    FD_REPEATS, FD_SPP,
};
use volgrad::cluster::images::render_shared;
use volgrad::cluster::passes::{adjoint_shared, gradient_shared};
use volgrad::cluster::Cluster;
use volgrad::gradient::adjoint::{Estimator, Suffix, DEFAULT_SUFFIX_PATHS};
use volgrad::gradient::fd;
use volgrad::gradient::grid::GradientGrid;
use volgrad::gradient::loss::Loss;
use volgrad::gradient::objective::{check_target, target_options};
use volgrad::gradient::passes::{derivative_image, GradOptions, GradientRun, Parameter};
use volgrad::io::fingerprint::image as image_fingerprint;
use volgrad::io::gradient_files::{self, Provenance};
use volgrad::io::images::{self, RgbImage};
use volgrad::io::output::{refuse_overwrite, refuse_unwritable_folder, require_extension};
use volgrad::io::progress;
use volgrad::io::{colormap, vdb};
use volgrad::render::fingerprint;
use volgrad::render::lights::luminance;
use volgrad::render::scene::Scene;
use volgrad::render::scene_check;
use volgrad::volume::transform::IndexTransform;

/// `--target-spp` when not given.
const TARGET_SPP: u32 = 256;

/// What `grad` computes: an estimator's gradient of every voxel, or finite differences along
/// directions. The names are the estimators' own, plus `fd`.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum Method {
    Estimator(Estimator),
    FiniteDifferences,
}

impl ValueEnum for Method {
    fn value_variants<'a>() -> &'a [Self] {
        &[
            Method::Estimator(Estimator::Joint),
            Method::Estimator(Estimator::Drt),
            Method::Estimator(Estimator::Naive),
            Method::FiniteDifferences,
        ]
    }

    fn to_possible_value(&self) -> Option<PossibleValue> {
        match self {
            Method::Estimator(e) => e.to_possible_value(),
            Method::FiniteDifferences => Some(
                PossibleValue::new("fd")
                    .help("Finite differences along the direction given by --fd"),
            ),
        }
    }
}

#[derive(clap::Args)]
pub struct Args {
    /// The scene file (TOML).
    pub scene: PathBuf,
    #[arg(long, value_enum, default_value = "joint")]
    pub estimator: Method,
    #[arg(long, value_enum, default_value_t = Loss::Mean)]
    pub loss: Loss,
    /// Target image (EXR, PNG, ...) for l2, l1 and relative-l2.
    #[arg(long, conflicts_with = "target_scene")]
    pub target: Option<PathBuf>,
    /// A scene whose render (at --target-spp) is the target.
    #[arg(long)]
    pub target_scene: Option<PathBuf>,
    /// Samples per pixel of the --target-scene render.
    #[arg(long, default_value_t = TARGET_SPP, value_parser = clap::value_parser!(u32).range(1..))]
    pub target_spp: u32,
    /// Output gradient VDB (a picture of it goes beside it as .png). Default: <scene>.grad.vdb.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Also write d pixel / d ε for ε added to every voxel of an index box "x0,y0,z0,x1,y1,z1" (or
    /// "all"), as <output>.dpixel.exr and .png.
    #[arg(long)]
    pub image_of: Option<String>,
    /// With --estimator fd: "voxels:x,y,z;x,y,z", "box:x0,y0,z0,x1,y1,z1", "ones" or "random".
    #[arg(long)]
    pub fd: Option<String>,
    #[command(flatten)]
    pub fd_args: FdArgs,
    #[command(flatten)]
    pub adjoint: AdjointArgs,
    /// Print wall time, ms per spp, paths/s and density lookups.
    #[arg(long)]
    pub stats: bool,
    /// Overwrite existing outputs.
    #[arg(long)]
    pub force: bool,
}

/// What `grad` writes: the VDB, its picture, and with `--image-of` the derivative image as EXR and
/// PNG. All are checked before any work so that a refusal to overwrite costs nothing.
///
/// The names are the VDB's with `.vdb` replaced, whatever dots the rest holds: `cloud.grad.vdb`
/// gives `cloud.grad.png` and `cloud.grad.dpixel.exr` (`Path::with_extension` would replace
/// `.grad` and make `a.x.vdb` and `a.y.vdb` write the same pictures).
fn outputs(vdb: &Path, image_of: bool) -> Vec<PathBuf> {
    let stem = match vdb.extension() {
        Some(e) if e.eq_ignore_ascii_case("vdb") => vdb.with_extension(""),
        _ => vdb.to_path_buf(),
    };
    let beside = |suffix: &str| {
        let mut name = stem.clone().into_os_string();
        name.push(suffix);
        PathBuf::from(name)
    };
    let mut paths = vec![vdb.to_path_buf(), beside(".png")];
    if image_of {
        paths.extend([beside(".dpixel.exr"), beside(".dpixel.png")]);
    }
    paths
}

/// An index box resolved against the scene: "all" is the whole gradient domain; a box must be
/// ordered (x0 ≤ x1, …) and reach into the domain, or it would silently measure nothing.
fn resolve_box(b: IndexBox, scene: &Scene, what: &str) -> Result<(IVec3, IVec3)> {
    let (dlo, dhi) = fd::domain_bounds(&scene.medium.grid).context("the grid is empty")?;
    let IndexBox::Voxels(lo, hi) = b else {
        return Ok((dlo, dhi));
    };
    if lo.cmpgt(hi).any() {
        bail!("{what}: the box {lo}..{hi} is empty (each of x0, y0, z0 must be ≤ x1, y1, z1)");
    }
    if lo.cmpgt(dhi).any() || hi.cmplt(dlo).any() {
        bail!("{what}: the box {lo}..{hi} lies outside the gradient domain {dlo}..{dhi}");
    }
    Ok((lo, hi))
}

/// Where a loss's target comes from: an image read, or a scene to render.
enum TargetSource {
    None,
    Image(RgbImage),
    Scene(Box<Scene>),
}

/// The target's source, from --target or --target-scene: what can fail on one rank and not
/// another (a file), before any rank renders with the others.
fn load_target(args: &Args) -> Result<TargetSource> {
    let source = match (&args.target, &args.target_scene) {
        (Some(path), _) => {
            let what = format!("--target '{}'", path.display());
            let image = images::read_rgb(path).with_context(|| what.clone())?;
            scene_check::radiance_pixels(&what, &image.pixels)?;
            TargetSource::Image(image)
        }
        (None, Some(path)) => TargetSource::Scene(Box::new(
            Scene::load(path).with_context(|| format!("--target-scene '{}'", path.display()))?,
        )),
        (None, None) => TargetSource::None,
    };
    if args.loss.needs_target() && matches!(source, TargetSource::None) {
        bail!(
            "--loss {} needs --target IMAGE or --target-scene SCENE",
            args.loss
        );
    }
    Ok(source)
}

/// The target image, checked against the scene: read, or rendered with every rank tracing its
/// share of the pixels (one progress bar, rank 0's).
fn target_image(
    args: &Args,
    source: TargetSource,
    scene: &Scene,
    cluster: &Cluster,
) -> Result<Option<RgbImage>> {
    let target = match source {
        TargetSource::None => None,
        TargetSource::Image(image) => Some(image),
        TargetSource::Scene(mut other) => {
            // Through the scene's own camera: a target scene differs in its medium or lights,
            // and an image from another viewpoint would be compared pixel by pixel all the same.
            other.camera = scene.camera;
            let progress = !args.adjoint.sampling.quiet && cluster.is_root();
            let seed = scene.settings.seed;
            let options = target_options(&other, args.target_spp, seed, progress);
            Some(render_shared(cluster, &other, &options).0)
        }
    };
    if let Some(t) = &target {
        cluster.agree(check_target(t, scene))?;
    }
    Ok(target)
}

/// The flags that do not go together (the same on every rank).
fn check_flags(args: &Args, ranks: usize, vdb_out: &Path) -> Result<()> {
    if args.estimator != Method::FiniteDifferences {
        require_extension(vdb_out, "vdb")?;
    }
    if args.adjoint.parameter != Parameter::Extinction
        && (args.estimator == Method::FiniteDifferences || args.image_of.is_some())
    {
        bail!(
            "--parameter {} goes with the path estimators: --estimator fd and --image-of perturb the density",
            args.adjoint.parameter
        );
    }
    if args.fd.is_some() && args.estimator != Method::FiniteDifferences {
        bail!(
            "--fd chooses the directions of --estimator fd; leave it out with the path estimators"
        );
    }
    if !args.loss.needs_target() && (args.target.is_some() || args.target_scene.is_some()) {
        bail!("--loss {} compares with no target: leave out --target and --target-scene, or choose a loss that compares (l2, l1, relative-l2)", args.loss);
    }
    let fd = args.estimator == Method::FiniteDifferences;
    // Flags the chosen method would ignore without a word.
    let (a, f) = (&args.adjoint, &args.fd_args);
    let ignored = if fd {
        vec![
            ("--output", args.output.is_some()),
            ("--image-of", args.image_of.is_some()),
            ("--stats", args.stats),
            ("--spp", a.sampling.spp.is_some()),
            ("--suffix", a.suffix != Suffix::PerPath),
            ("--suffix-paths", a.suffix_paths != DEFAULT_SUFFIX_PATHS),
        ]
    } else {
        vec![
            ("--eps", f.eps.is_some()),
            ("--fd-spp", f.fd_spp != FD_SPP),
            ("--repeats", f.repeats != FD_REPEATS),
        ]
    }
    .into_iter()
    .find_map(|(flag, given)| given.then_some(flag));
    if let Some(flag) = ignored {
        match fd {
            true => bail!("{flag} is for the path estimators: --estimator fd prints a table of finite differences (--fd-spp samples, --repeats times) and writes no file"),
            false => bail!("{flag} is for --estimator fd; leave it out with --estimator {}", args.estimator.to_possible_value().map_or(String::new(), |v| v.get_name().to_string())),
        }
    }
    if args.target_scene.is_none() && args.target_spp != TARGET_SPP {
        bail!("--target-spp is the samples of the --target-scene render: give --target-scene, or leave it out");
    }
    if ranks > 1 && (fd || args.image_of.is_some()) {
        let what = if fd { "--estimator fd" } else { "--image-of" };
        bail!("grad {what} runs as one process: start it without mpirun");
    }
    Ok(())
}

/// Under mpirun every rank traces its share of the pixels, the gradients are summed, and rank 0
/// writes the files; finite differences and `--image-of` run as one process only.
pub fn run(args: &Args, cluster: &Cluster) -> Result<()> {
    cluster.agree(set_threads(args.adjoint.sampling.threads))?;
    let vdb_out = args.output.clone().unwrap_or_else(|| {
        PathBuf::from(format!(
            "{}.grad.vdb",
            args.scene.file_stem().unwrap_or_default().to_string_lossy()
        ))
    });
    // Every rank is given the same flags: one error, printed once.
    cluster.agree(check_flags(args, cluster.size(), &vdb_out))?;
    if args.estimator != Method::FiniteDifferences {
        let outputs = outputs(&vdb_out, args.image_of.is_some());
        cluster.agree(match cluster.is_root() {
            true => (outputs.iter()).try_for_each(|path| {
                refuse_overwrite(path, args.force).and_then(|_| refuse_unwritable_folder(path))
            }),
            false => Ok(()),
        })?;
    }
    let (scene, source) = cluster.agree(Scene::load(&args.scene).and_then(|scene| {
        let source = load_target(args)?;
        Ok((scene, source))
    }))?;
    warn_if_empty(&scene, cluster);
    // What the gradient file records, and what the ranks compare: hashed once.
    let scene_fingerprint = fingerprint::scene(&scene);
    check_same_job(cluster, || {
        let target = match &source {
            TargetSource::None => "none".to_string(),
            TargetSource::Image(image) => image_fingerprint(image),
            TargetSource::Scene(other) => fingerprint::scene(other),
        };
        vec![scene_fingerprint.clone(), target]
    })?;
    // Every flag is checked before the target is rendered (minutes, with --target-scene).
    let image_box = match &args.image_of {
        Some(spec) => Some(resolve_box(
            values::index_box(spec, "--image-of")?,
            &scene,
            "--image-of",
        )?),
        None => None,
    };
    let estimator = match args.estimator {
        Method::Estimator(e) => e,
        Method::FiniteDifferences => {
            let plan = plan_finite_differences(args, &scene)?;
            let target = target_image(args, source, &scene, cluster)?;
            return finite_differences(args, &scene, target.as_ref(), plan);
        }
    };
    let (mut options, (parameter_name, transform, channels)) = cluster.agree(
        (args.adjoint.options(&scene, estimator))
            .and_then(|o| Ok((o, parameter_grid(&scene, args.adjoint.parameter)?))),
    )?;
    let target = target_image(args, source, &scene, cluster)?;
    options.progress &= cluster.is_root();
    let adjoint = adjoint_shared(cluster, &scene, args.loss, target.as_ref(), &options)?;
    if let (Some(loss), true) = (adjoint.loss, cluster.is_root()) {
        eprintln!("loss ({}) = {loss:.6e}", args.loss);
    }
    // One pass per colour channel of an RGB parameter (the same paths each: the same seed).
    let runs: Vec<GradientRun> = (0..channels)
        .map(|c| {
            let options = GradOptions {
                channel: (channels > 1).then_some(c),
                ..options
            };
            gradient_shared(cluster, &scene, &adjoint.delta, &options)
        })
        .collect();
    // Rank 0 writes; every rank learns whether it could.
    let write = move || -> Result<()> {
        let mut stats = runs[0].stats;
        for run in &runs[1..] {
            stats.merge(&run.stats);
        }
        report_non_finite(&stats);
        let provenance = Provenance {
            estimator: estimator.to_string(),
            spp: options.spp as u64,
            seed: options.seed.to_string(),
            loss: args.loss.to_string(),
            scene: args.scene.display().to_string(),
            scene_fingerprint,
            target_fingerprint: match (&target, args.loss.needs_target()) {
                (Some(t), true) => image_fingerprint(t),
                _ => "none".into(),
            },
            domain: args.adjoint.domain.to_string(),
            max_depth: options.adjoint.max_depth,
            suffix: options.adjoint.suffix.to_string(),
            parameter: args.adjoint.parameter.to_string(),
        };
        // The derivative image needs the medium; the export does not, so the medium goes first (on
        // the ×64 cloud it is a third of what a render holds).
        let derivative =
            image_box.map(|(lo, hi)| (lo, hi, derivative_image(&scene, lo, hi, &options)));
        drop(scene);
        // What the report needs of the gradient, then the gradient itself goes, and the exported grid
        // goes as soon as its values are in the bridge's arrays: a large gradient is held twice at a
        // time, not four times.
        let mut channels: Vec<GradientGrid<f32>> =
            runs.into_iter().map(|run| run.values()).collect();
        // Every sample is finite; a sum can still exceed f32's range (lights near 1e30). The
        // voxel named is the lowest, not the first met: the bricks' order depends on how the
        // ranks' gradients were merged.
        let beyond_f32 = (channels.iter().flat_map(|g| g.voxels()))
            .filter(|(_, v)| !v.is_finite())
            .min_by_key(|(voxel, _)| voxel.to_array());
        if let Some((voxel, v)) = beyond_f32 {
            bail!("the gradient at voxel {voxel} is {v}, beyond a VDB's f32 values: scale the scene's lights (or emission) down");
        }
        let (gradient_sum, gradient_blocks, gradient_bytes) = (
            channels.iter().map(|g| g.sum()).sum::<f64>(),
            channels[0].block_count(),
            channels.iter().map(|g| g.memory_bytes()).sum::<usize>(),
        );
        let as_grid =
            |bricks| gradient_files::gradient_grid(bricks, &parameter_name, transform, &provenance);
        let png = outputs(&vdb_out, false).swap_remove(1);
        let (scale, grid_name, voxels) = if let [r, g, b] = channels.as_slice() {
            // An RGB parameter: one vec3 grid, as the input; the picture sums the channels.
            let [r, g, b] = [r, g, b].map(|c| as_grid(c.to_brickmap()));
            let mut total = channels[0].empty_like();
            channels.iter().for_each(|c| total.merge(c, 1.0));
            let scale = gradient_files::write_projection_png(&png, &as_grid(total.to_brickmap()))?;
            vdb::write_grids_with_colours(&vdb_out, &[], &[[&r, &g, &b]], false, args.force)?;
            (scale, r.name.clone(), r.bricks.active_voxel_count())
        } else {
            let gradient = channels.pop().expect("one pass at least");
            let grid = as_grid(gradient.to_brickmap());
            drop(gradient);
            let scale = gradient_files::write_projection_png(&png, &grid)?;
            let (grid_name, voxels) = (grid.name.clone(), grid.bricks.active_voxel_count());
            vdb::write_grid_consumed(&vdb_out, grid, false, args.force)?;
            (scale, grid_name, voxels)
        };
        let picture = match scale {
            Some(scale) => format!(
                "and {} (sum along index z; full colour at ±{scale:.3e})",
                png.display()
            ),
            None => "(no picture: no voxel has gradient)".into(),
        };
        eprintln!(
            "wrote {} (grid {grid_name}, {voxels} voxels with gradient, ⟨g, 1⟩ = {gradient_sum:.6e}) {picture}",
            vdb_out.display(),
        );
        if let Some((lo, hi, (image, stats))) = derivative {
            report_non_finite(&stats);
            let paths = outputs(&vdb_out, true);
            let (exr, png) = (&paths[2], &paths[3]);
            images::write_exr(exr, &image, false)?;
            let luminance: Vec<f32> = image.pixels.iter().map(|&c| luminance(c)).collect();
            let scale = colormap::write_signed_png(png, image.width, image.height, &luminance)?;
            eprintln!(
                "wrote {} and {} (d pixel / d ε for the box {lo}..{hi}; full colour at ±{scale:.3e})",
                exr.display(),
                png.display()
            );
        }
        if args.stats {
            let secs = stats.wall.as_secs_f64();
            println!("estimator            {estimator}");
            println!("wall time            {secs:.3} s");
            println!(
                "ms per spp           {:.2}",
                1e3 * secs / options.spp as f64
            );
            println!("paths/s              {:.0}", stats.paths_per_second());
            println!("lookups per path     {:.2}", stats.lookups_per_path());
            println!(
                "gradient grid        {gradient_blocks} blocks of 4³, {}",
                super::bytes(gradient_bytes)
            );
            println!("non-finite samples   {} (dropped)", stats.non_finite);
            super::print_peak_memory();
        }
        Ok(())
    };
    cluster.agree(if cluster.is_root() { write() } else { Ok(()) })
}

/// Refuses a parameter whose grid the scene does not have.
pub fn check_parameter(scene: &Scene, parameter: Parameter) -> Result<()> {
    parameter_grid(scene, parameter).map(|_| ())
}

/// The name and transform of the grid `parameter` names, and how many colour channels its gradient
/// has (3 for an RGB albedo grid, else 1); refused where the scene has no such grid.
fn parameter_grid(scene: &Scene, parameter: Parameter) -> Result<(String, IndexTransform, usize)> {
    let medium = &scene.medium;
    Ok(match parameter {
        Parameter::Extinction => (scene.grid_name.clone(), medium.transform, 1),
        Parameter::Emission => match &medium.emission {
            Some(e) => (e.name.clone(), e.transform, 1),
            None => bail!("--parameter emission: the scene's medium has no emission (medium.emission)"),
        },
        Parameter::Albedo => match medium.albedo.grid() {
            Some(a) => (a.name.clone(), a.transform, a.channels.len()),
            None => bail!("--parameter albedo: the scene's albedo is a constant, not a grid (medium.albedo = {{ grid = \"Cd\" }})"),
        },
    })
}

/// The finite-difference directions `--fd` names, each with a label.
fn fd_directions(
    spec: &str,
    scene: &Scene,
    active_only: bool,
    seed: u64,
    floor: f32,
) -> Result<Vec<(String, fd::Direction)>> {
    let grid = &scene.medium.grid;
    let (lo, hi) = fd::domain_bounds(grid).context("the grid is empty")?;
    // Every voxel of the domain, listed: refused (before any work) if there are too many.
    let domain = || -> Result<Vec<IVec3>> {
        fd::ensure_enumerable(grid, lo, hi)?;
        Ok(fd::box_voxels(grid, lo, hi, active_only))
    };
    Ok(match values::fd_direction(spec)? {
        FdDirection::Voxels(voxels) => voxels
            .into_iter()
            .map(|v| {
                let outside = v.cmplt(lo).any() || v.cmpgt(hi).any();
                if outside || (active_only && !grid.is_active(v)) {
                    bail!(
                        "--fd voxels: {v} is not a parameter (the domain is {lo}..{hi}{})",
                        if active_only {
                            ", active voxels only"
                        } else {
                            ""
                        }
                    );
                }
                Ok((format!("voxel [{}, {}, {}]", v.x, v.y, v.z), vec![(v, 1.0)]))
            })
            .collect::<Result<_>>()?,
        FdDirection::Box(b) => {
            let (a, c) = resolve_box(b, scene, "--fd box")?;
            fd::ensure_enumerable(grid, a, c)?;
            vec![(
                format!("box {a}..{c}"),
                fd::ones(&fd::box_voxels(grid, a, c, active_only)),
            )]
        }
        FdDirection::Ones => vec![("⟨g, 1⟩".into(), fd::ones(&domain()?))],
        FdDirection::Random => vec![(
            format!("random ±1 (seed {seed})"),
            fd::random_signs(grid, &domain()?, seed, floor),
        )],
    })
}

/// Finite differences' steps and directions, from the flags alone (no target needed).
type FdPlan = (fd::FdOptions, Vec<(String, fd::Direction)>);

fn plan_finite_differences(args: &Args, scene: &Scene) -> Result<FdPlan> {
    let spec = args
        .fd
        .as_deref()
        .context("--estimator fd needs --fd (voxels:..., box:..., ones or random)")?;
    let seed = args.adjoint.sampling.seed(scene);
    let max_depth = args.adjoint.sampling.max_depth(scene);
    // Finite differences of the density only (`check_flags`).
    let options = (args.fd_args).options(&scene.medium.grid, args.loss, seed, max_depth)?;
    let active_only = args.adjoint.domain == Domain::Active;
    let directions = fd_directions(spec, scene, active_only, seed, 3.0 * options.eps)?;
    Ok((options, directions))
}

fn finite_differences(
    args: &Args,
    scene: &Scene,
    target: Option<&RgbImage>,
    (options, directions): FdPlan,
) -> Result<()> {
    println!(
        "finite differences of {} ({} spp × {} repeats, common random numbers)",
        args.loss, options.spp, options.repeats
    );
    let bar = progress::bar(!args.adjoint.sampling.quiet, directions.len() as u64, "fd");
    for (name, direction) in directions {
        let mut options = options;
        options.eps = args
            .fd_args
            .eps
            .unwrap_or_else(|| fd::auto_eps(scene, &direction));
        let r = fd::directional_derivative(scene, target, &direction, &options)?;
        let one_sided = if r.one_sided {
            "  (one-sided: empty voxels)"
        } else {
            ""
        };
        bar.suspend(|| {
            println!(
                "{name:<32} {:>14.6e} ± {:.2e}  (ε = {:.3e}){one_sided}",
                r.value, r.std_err, options.eps
            )
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outputs_replace_only_the_vdb_extension() {
        let names = |vdb: &str| -> Vec<String> {
            (outputs(Path::new(vdb), true).iter())
                .map(|p| p.display().to_string())
                .collect()
        };
        assert_eq!(
            names("cloud.grad.vdb"),
            [
                "cloud.grad.vdb",
                "cloud.grad.png",
                "cloud.grad.dpixel.exr",
                "cloud.grad.dpixel.png"
            ]
        );
        // Two outputs that differ before the last dot keep their pictures apart.
        assert_ne!(names("a.x.vdb")[1..], names("a.y.vdb")[1..]);
        assert_eq!(names("out")[1], "out.png");
    }
}
