//! The `volgrad` command line.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};

use glam::IVec3;
use volgrad::compare;
use volgrad::gradient::adjoint::{AdjointOptions, Estimator, Suffix};
use volgrad::gradient::fd::{self, FdOptions};
use volgrad::gradient::gradcheck::{gradcheck, GradcheckOptions, Z_LIMIT};
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{derivative_image, gradient, GradOptions};
use volgrad::io::gradient_files::{self, Provenance};
use volgrad::io::images;
use volgrad::io::make_grid::{make_grid, GridKind, GridSpec};
use volgrad::io::vdb;
use volgrad::render::image::{render, RenderOptions, RenderStats};
use volgrad::render::scene::Scene;
use volgrad::volume::brickmap::BRICK_VOXELS;
use volgrad::volume::majorant::{Majorant, MajorantMode};

#[derive(Parser)]
#[command(
    name = "volgrad",
    version,
    about = "Differentiable volumetric path tracing of OpenVDB density grids"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// List every grid in a .vdb file: type, class, transform, voxel counts, bounds, metadata.
    Info {
        /// The .vdb file.
        file: PathBuf,
    },
    /// Render a scene to a linear EXR and a tonemapped PNG beside it.
    Render(RenderArgs),
    /// Write a small analytic grid (box, sphere, slab, single dense voxel) as a .vdb file.
    MakeGrid(MakeGridArgs),
    /// Gradient of a loss with respect to every voxel, written as a VDB (plus pictures).
    Grad(GradArgs),
    /// Compare an estimator with finite differences (z-scores) before trusting its gradients.
    Gradcheck(GradcheckArgs),
    /// Speed against accuracy: estimators (and the renderer) at equal time against a reference,
    /// as charts, a CSV and tables; or the stability suite (--suite stability).
    Compare(CompareArgs),
    /// Combine gradient VDBs from runs with different seeds, weighted by their spp.
    Merge {
        /// Gradient VDBs written by `volgrad grad`.
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        #[arg(short, long)]
        output: PathBuf,
        /// Overwrite an existing output.
        #[arg(long)]
        force: bool,
    },
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum EstimatorArg {
    /// Sample matching: scattering and transmittance parts at one shared probe per segment.
    Joint,
    /// Differential ratio tracking (Nimier-David et al. 2022).
    Drt,
    /// Differentiated free-flight sampling: biased where σt = 0 (a baseline).
    Naive,
    /// Finite differences along the direction given by --fd.
    Fd,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum DomainArg {
    /// Every voxel a ray can reach inside the medium's bounds, empty ones included.
    All,
    /// Only the grid's active voxels.
    Active,
}

/// Options shared by `grad` and `gradcheck`.
#[derive(Args)]
struct AdjointArgs {
    /// Samples per pixel of the gradient pass (default: render.spp).
    #[arg(long)]
    spp: Option<u32>,
    /// Random seed (default: render.seed).
    #[arg(long)]
    seed: Option<u64>,
    /// Maximum scattering events per path (default: render.max_depth).
    #[arg(long)]
    max_depth: Option<u32>,
    /// Where the indirect part of ĥ at a probe comes from.
    #[arg(long, value_enum, default_value = "per-path")]
    suffix: Suffix,
    /// Which voxels are parameters.
    #[arg(long, value_enum, default_value = "all")]
    domain: DomainArg,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
}

#[derive(Args)]
struct FdArgs {
    /// Finite-difference step, in grid-value units (default: per direction, a step that changes the
    /// optical depth along the direction's longest chord by about 0.05).
    #[arg(long)]
    eps: Option<f32>,
    /// Samples per pixel of each finite-difference render.
    #[arg(long, default_value_t = 256)]
    fd_spp: u32,
    /// Independent finite-difference repetitions, for the standard error.
    #[arg(long, default_value_t = 8)]
    repeats: u32,
}

#[derive(Args)]
struct GradArgs {
    /// The scene file (TOML).
    scene: PathBuf,
    #[arg(long, value_enum, default_value = "joint")]
    estimator: EstimatorArg,
    #[arg(long, value_enum, default_value = "mean")]
    loss: Loss,
    /// Target image (EXR, PNG, ...) for l2, l1 and relative-l2.
    #[arg(long, conflicts_with = "target_scene")]
    target: Option<PathBuf>,
    /// A scene whose render (at --target-spp) is the target.
    #[arg(long)]
    target_scene: Option<PathBuf>,
    /// Samples per pixel of the --target-scene render.
    #[arg(long, default_value_t = 256)]
    target_spp: u32,
    /// Output gradient VDB (a picture of it goes beside it as .png). Default: <scene>.grad.vdb.
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Also write d pixel / d ε for ε added to every voxel of an index box "x0,y0,z0,x1,y1,z1" (or
    /// "all"), as <output>.dpixel.exr and .png.
    #[arg(long)]
    image_of: Option<String>,
    /// With --estimator fd: "voxels:x,y,z;x,y,z", "box:x0,y0,z0,x1,y1,z1", "ones" or "random".
    #[arg(long)]
    fd: Option<String>,
    #[command(flatten)]
    fd_args: FdArgs,
    #[command(flatten)]
    adjoint: AdjointArgs,
    /// Print wall time, ms per spp, paths/s and density lookups.
    #[arg(long)]
    stats: bool,
    /// Overwrite existing outputs.
    #[arg(long)]
    force: bool,
}

#[derive(Args)]
struct GradcheckArgs {
    scene: PathBuf,
    #[arg(long, value_enum, default_value = "joint")]
    estimator: Estimator,
    /// Number of random voxels to check.
    #[arg(long, default_value_t = 4)]
    voxels: usize,
    /// Image width for the check (the height follows the scene's aspect ratio): finite differences
    /// render the image many times, so a small one keeps the check quick.
    #[arg(long, default_value_t = 32)]
    width: u32,
    #[command(flatten)]
    fd_args: FdArgs,
    #[command(flatten)]
    adjoint: AdjointArgs,
}

#[derive(Args)]
struct RenderArgs {
    /// The scene file (TOML).
    scene: PathBuf,
    /// Output EXR; the PNG goes beside it. Default: <scene name>.exr in the current directory.
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Samples per pixel (overrides render.spp).
    #[arg(long)]
    spp: Option<u32>,
    /// Random seed (overrides render.seed); the same seed gives the same image on any thread count.
    #[arg(long)]
    seed: Option<u64>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Maximum number of scattering events per path (overrides render.max_depth).
    #[arg(long)]
    max_depth: Option<u32>,
    /// Majorant structure for tracking (overrides render.majorant).
    #[arg(long, value_enum)]
    majorant: Option<MajorantMode>,
    /// Majorant cell edge in voxels (overrides render.majorant_cell).
    #[arg(long)]
    majorant_cell: Option<u32>,
    /// Store the EXR as half floats.
    #[arg(long)]
    half: bool,
    /// Print paths/s, density lookups per path, tracking efficiency and memory.
    #[arg(long)]
    stats: bool,
    /// Overwrite existing output files.
    #[arg(long)]
    force: bool,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
}

#[derive(Args)]
struct MakeGridArgs {
    /// What to make.
    #[arg(value_enum)]
    kind: GridKind,
    /// Output .vdb file.
    #[arg(short, long)]
    output: PathBuf,
    /// Edge length in voxels.
    #[arg(long, default_value_t = 16)]
    size: u32,
    /// Slab thickness in voxels.
    #[arg(long, default_value_t = 2)]
    thickness: u32,
    /// Grid value inside the shape.
    #[arg(long, default_value_t = 1.0, allow_negative_numbers = true)]
    value: f32,
    /// Voxel size: one number, or three (x,y,z) for anisotropic voxels.
    #[arg(long, value_delimiter = ',', default_value = "1")]
    voxel_size: Vec<f64>,
    /// Rotation in degrees about x, then y, then z.
    #[arg(long, value_delimiter = ',', allow_negative_numbers = true)]
    rotate_deg: Option<Vec<f64>>,
    /// Grid name.
    #[arg(long, default_value = "density")]
    name: String,
    /// Store values as half floats.
    #[arg(long)]
    half: bool,
    /// Overwrite an existing file.
    #[arg(long)]
    force: bool,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum SuiteArg {
    /// Error against time for each estimator and for the renderer's majorants, on SCENE.
    EqualTime,
    /// Scenes built in memory to break estimators: bias, variance, non-finite values.
    Stability,
}

#[derive(Args)]
struct CompareArgs {
    /// The scene file (TOML); not needed for --suite stability.
    #[arg(required_unless_present = "suite")]
    scene: Option<PathBuf>,
    #[arg(long, value_enum, default_value = "equal-time")]
    suite: SuiteArg,
    /// Estimators to compare, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "joint,drt,naive"
    )]
    estimators: Vec<Estimator>,
    /// Wall time per estimator (and per majorant mode for the renderer), e.g. 120s, 2m.
    #[arg(long, default_value = "120s", value_parser = parse_duration)]
    budget: Duration,
    /// Wall time per majorant mode of the forward-renderer comparison (default: budget / 4; 0s
    /// skips it).
    #[arg(long, value_parser = parse_duration)]
    render_budget: Option<Duration>,
    /// A reference gradient written by an earlier `volgrad compare` (reference.vdb).
    #[arg(long)]
    reference: Option<PathBuf>,
    /// Samples per pixel of each reference run.
    #[arg(long, default_value_t = 64)]
    reference_spp: u32,
    /// Runs of each of joint and drt averaged into the reference.
    #[arg(long, default_value_t = 8)]
    reference_seeds: u32,
    /// Use the reference even if finite differences disagree with it (|z| > 4).
    #[arg(long)]
    force_reference: bool,
    /// Largest spp of a sweep.
    #[arg(long, default_value_t = 4096)]
    max_spp: u32,
    /// Voxels (of largest |gradient|) checked against finite differences.
    #[arg(long, default_value_t = 3)]
    fd_voxels: usize,
    /// Samples per pixel of each finite-difference render (default: 16; 4096 for the suite).
    #[arg(long)]
    fd_spp: Option<u32>,
    /// Finite-difference repetitions (default: 8).
    #[arg(long)]
    repeats: Option<u32>,
    /// Stability suite: independent runs per estimator and scene (for the standard error).
    #[arg(long, default_value_t = 8)]
    suite_runs: u32,
    /// Stability suite: samples per pixel of each run.
    #[arg(long, default_value_t = 64)]
    suite_spp: u32,
    /// Random seed (default: render.seed, or 1 for the suite).
    #[arg(long)]
    seed: Option<u64>,
    /// Output directory (default: compare-<scene>/, or compare-stability/).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// No progress bars.
    #[arg(long, short)]
    quiet: bool,
    /// Overwrite existing outputs.
    #[arg(long)]
    force: bool,
}

/// "120s", "2m", "1.5h", "90" (seconds).
fn parse_duration(text: &str) -> Result<Duration, String> {
    let t = text.trim();
    let (number, unit) = match t.find(|c: char| c.is_ascii_alphabetic()) {
        Some(i) => t.split_at(i),
        None => (t, "s"),
    };
    let factor = match unit {
        "ms" => 1e-3,
        "s" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        _ => {
            return Err(format!(
                "unknown unit '{unit}' in '{text}' (use s, m or h, e.g. 120s)"
            ))
        }
    };
    match number.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(Duration::from_secs_f64(v * factor)),
        _ => Err(format!("'{text}' is not a duration (e.g. 120s, 2m)")),
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Info { file } => info(&file),
        Command::Render(args) => render_command(&args),
        Command::MakeGrid(args) => make_grid_command(&args),
        Command::Grad(args) => grad_command(&args),
        Command::Gradcheck(args) => gradcheck_command(&args),
        Command::Compare(args) => compare_command(&args),
        Command::Merge {
            inputs,
            output,
            force,
        } => merge_command(&inputs, &output, force),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn info(file: &Path) -> Result<()> {
    let grids = vdb::list_grids(file)?;
    println!(
        "{}: {} grid{}",
        file.display(),
        grids.len(),
        if grids.len() == 1 { "" } else { "s" }
    );
    for (i, g) in grids.iter().enumerate() {
        println!("\n[{i}] {}", g.name);
        println!(
            "  value type     {}{}",
            g.value_type,
            if g.saved_as_half {
                " (saved as half)"
            } else {
                ""
            }
        );
        println!("  class          {}", g.grid_class);
        let v = g.voxel_size;
        let kind = match (g.linear, g.axis_aligned) {
            (false, _) => "non-linear map (not renderable)",
            (true, true) => "scale + translation",
            (true, false) => "general affine (rotated or sheared)",
        };
        println!(
            "  voxel size     {:.6} × {:.6} × {:.6}  ({kind})",
            v[0], v[1], v[2]
        );
        let m = g.index_to_world;
        for r in 0..3 {
            println!(
                "  {}   [{:>10.5} {:>10.5} {:>10.5} | {:>10.5}]",
                if r == 0 {
                    "index→world"
                } else {
                    "           "
                },
                m[4 * r],
                m[4 * r + 1],
                m[4 * r + 2],
                m[4 * r + 3]
            );
        }
        println!("  active voxels  {}", g.active_voxels);
        println!("  leaves         {}", g.leaf_count);
        println!("  active tiles   {}", g.active_tiles);
        if g.index_min.iter().zip(&g.index_max).all(|(a, b)| a <= b) {
            println!("  index bbox     {:?} .. {:?}", g.index_min, g.index_max);
            println!(
                "  world bbox     {:?} .. {:?}",
                g.world_min.map(|x| (x * 1e4).round() / 1e4),
                g.world_max.map(|x| (x * 1e4).round() / 1e4)
            );
        } else {
            println!("  index bbox     (empty)");
        }
        if g.value_type == "float" {
            let grid = vdb::read_grid(file, &vdb::GridSelector::Index(i))?;
            let b = &grid.bricks;
            let leaf_bytes = b.leaves().len() * BRICK_VOXELS * 4;
            println!(
                "  brick map      {} ({:.3} × the {} of leaf values, {} tiles kept as constants)",
                bytes(b.memory_bytes()),
                b.memory_bytes() as f64 / leaf_bytes.max(1) as f64,
                bytes(leaf_bytes),
                b.tiles().len()
            );
        }
        if !g.metadata.is_empty() {
            println!("  metadata");
            for e in &g.metadata {
                println!("    {:<24} {:<8} {}", e.name, e.type_name, e.value);
            }
        }
    }
    Ok(())
}

fn bytes(n: usize) -> String {
    if n >= 1 << 20 {
        format!("{:.2} MiB", n as f64 / (1u64 << 20) as f64)
    } else {
        format!("{:.1} KiB", n as f64 / 1024.0)
    }
}

fn set_threads(threads: Option<usize>) -> Result<()> {
    if let Some(t) = threads {
        if t == 0 {
            bail!("--threads must be at least 1");
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build_global()
            .context("cannot start the thread pool")?;
    }
    Ok(())
}

/// Applies the command-line overrides that change how the medium is tracked.
fn load_scene(
    path: &Path,
    majorant: Option<MajorantMode>,
    majorant_cell: Option<u32>,
) -> Result<Scene> {
    let mut scene = Scene::load(path)?;
    if majorant.is_some() || majorant_cell.is_some() {
        let cell = majorant_cell.unwrap_or(scene.settings.majorant_cell);
        if cell == 0 || cell > 1024 {
            bail!("--majorant-cell must be between 1 and 1024 voxels (got {cell})");
        }
        scene.set_majorant(Majorant {
            mode: majorant.unwrap_or(scene.settings.majorant),
            cell_voxels: cell,
        });
    }
    Ok(scene)
}

fn render_command(args: &RenderArgs) -> Result<()> {
    set_threads(args.threads)?;
    let exr = args.output.clone().unwrap_or_else(|| {
        PathBuf::from(args.scene.file_stem().unwrap_or_default()).with_extension("exr")
    });
    if exr.extension().and_then(|e| e.to_str()) != Some("exr") {
        bail!(
            "--output must end in .exr (got '{}'); the PNG is written beside it",
            exr.display()
        );
    }
    let png = exr.with_extension("png");
    volgrad::refuse_overwrite(&exr, args.force)?;
    volgrad::refuse_overwrite(&png, args.force)?;
    let scene = load_scene(&args.scene, args.majorant, args.majorant_cell)?;
    let mut options = RenderOptions::from_scene(&scene);
    options.spp = args.spp.unwrap_or(options.spp);
    options.seed = args.seed.unwrap_or(options.seed);
    options.max_depth = args.max_depth.unwrap_or(options.max_depth);
    options.progress = !args.quiet;
    if options.spp == 0 {
        bail!("--spp must be at least 1");
    }
    let (image, stats) = render(&scene, &options);
    images::write_exr(&exr, &image, args.half)?;
    images::write_png(&png, &image, scene.settings.exposure)?;
    eprintln!("wrote {} and {}", exr.display(), png.display());
    if args.stats {
        print_stats(&scene, &stats);
    }
    Ok(())
}

fn print_stats(scene: &Scene, stats: &RenderStats) {
    let m = &scene.medium;
    let t = &stats.tracking;
    let majorant = match scene.settings.majorant {
        MajorantMode::Global => "global".to_string(),
        MajorantMode::Grid => format!("grid, {}³-voxel cells", scene.settings.majorant_cell),
    };
    println!("wall time            {:.3} s", stats.wall.as_secs_f64());
    println!("paths                {}", stats.paths);
    println!("paths/s              {:.0}", stats.paths_per_second());
    println!(
        "majorant             {majorant} ({} cells)",
        m.majorant.cell_count()
    );
    println!(
        "lookups per path     {:.2} ({:.2} free-flight + {:.2} shadow)",
        stats.lookups_per_path(),
        t.lookups as f64 / stats.paths as f64,
        t.shadow_lookups as f64 / stats.paths as f64
    );
    println!(
        "tracking efficiency  {:.3} (real collisions / free-flight lookups)",
        stats.tracking_efficiency()
    );
    let leaf_bytes = m.grid.leaves().len() * BRICK_VOXELS * 4;
    println!(
        "memory               brick map {} = {:.3} × leaf values ({} leaves, {} tiles); majorant {}",
        bytes(m.grid.memory_bytes()),
        m.grid.memory_bytes() as f64 / leaf_bytes.max(1) as f64,
        m.grid.leaves().len(),
        m.grid.tiles().len(),
        bytes(m.majorant.memory_bytes())
    );
}

fn make_grid_command(args: &MakeGridArgs) -> Result<()> {
    let voxel_size = match args.voxel_size.as_slice() {
        [s] => [*s; 3],
        [x, y, z] => [*x, *y, *z],
        _ => bail!("--voxel-size takes one number or three (x,y,z)"),
    };
    let rotate_deg = match args.rotate_deg.as_deref() {
        None => [0.0; 3],
        Some([x, y, z]) => [*x, *y, *z],
        Some(_) => bail!("--rotate-deg takes three angles (x,y,z)"),
    };
    if args.output.extension().and_then(|e| e.to_str()) != Some("vdb") {
        bail!(
            "--output must end in .vdb (got '{}')",
            args.output.display()
        );
    }
    let spec = GridSpec {
        kind: args.kind,
        size: args.size,
        thickness: args.thickness,
        value: args.value,
        voxel_size,
        rotate_deg,
        name: args.name.clone(),
    };
    let grid = make_grid(&spec)?;
    vdb::write_grids(&args.output, &[&grid], args.half, args.force)?;
    eprintln!(
        "wrote {} ({} active voxels)",
        args.output.display(),
        grid.bricks.active_voxel_count()
    );
    Ok(())
}

fn parse_ivec3s(text: &str, what: &str) -> Result<Vec<i32>> {
    text.split(',')
        .map(|x| {
            x.trim()
                .parse::<i32>()
                .with_context(|| format!("{what}: '{x}' is not an integer"))
        })
        .collect()
}

/// "x0,y0,z0,x1,y1,z1" or "all" (the whole domain).
fn parse_box(text: &str, scene: &Scene) -> Result<(IVec3, IVec3)> {
    if text == "all" {
        return fd::domain_bounds(&scene.medium.grid).context("the grid is empty");
    }
    match parse_ivec3s(text, "--image-of")?.as_slice() {
        [x0, y0, z0, x1, y1, z1] => Ok((IVec3::new(*x0, *y0, *z0), IVec3::new(*x1, *y1, *z1))),
        _ => bail!("an index box is six integers x0,y0,z0,x1,y1,z1 (got '{text}')"),
    }
}

fn adjoint_options(scene: &Scene, estimator: Estimator, args: &AdjointArgs) -> Result<GradOptions> {
    let spp = args.spp.unwrap_or(scene.settings.spp);
    if spp == 0 {
        bail!("--spp must be at least 1");
    }
    Ok(GradOptions {
        adjoint: AdjointOptions {
            estimator,
            suffix: args.suffix,
            max_depth: args.max_depth.unwrap_or(scene.settings.max_depth),
        },
        spp,
        seed: args.seed.unwrap_or(scene.settings.seed),
        active_only: args.domain == DomainArg::Active,
        progress: !args.quiet,
    })
}

fn fd_options(
    scene: &Scene,
    loss: Loss,
    args: &FdArgs,
    seed: u64,
    max_depth: u32,
) -> Result<FdOptions> {
    // Without --eps, callers pick fd::auto_eps per direction; this is the cap it never exceeds.
    let eps = args
        .eps
        .unwrap_or(0.15 * scene.medium.grid.max_value().max(1e-3));
    if !(eps > 0.0 && eps.is_finite()) {
        bail!("--eps must be a positive number (got {eps})");
    }
    if args.fd_spp == 0 || args.repeats < 2 {
        bail!("--fd-spp must be at least 1 and --repeats at least 2");
    }
    Ok(FdOptions {
        loss,
        eps,
        spp: args.fd_spp,
        repeats: args.repeats,
        seed,
        max_depth,
    })
}

/// The target image of a loss, checked against the scene's resolution.
fn load_target(args: &GradArgs, scene: &Scene) -> Result<Option<images::RgbImage>> {
    let target = match (&args.target, &args.target_scene) {
        (Some(path), _) => {
            Some(images::read_rgb(path).with_context(|| format!("--target '{}'", path.display()))?)
        }
        (None, Some(path)) => {
            let other = Scene::load(path)
                .with_context(|| format!("--target-scene '{}'", path.display()))?;
            let options = RenderOptions {
                spp: args.target_spp.max(1),
                seed: scene.settings.seed ^ 0x5eed,
                max_depth: other.settings.max_depth,
                progress: !args.adjoint.quiet,
            };
            Some(render(&other, &options).0)
        }
        (None, None) => None,
    };
    if args.loss.needs_target() && target.is_none() {
        bail!(
            "--loss {} needs --target IMAGE or --target-scene SCENE",
            args.loss
        );
    }
    if let Some(t) = &target {
        if (t.width, t.height) != (scene.camera.width, scene.camera.height) {
            bail!(
                "the target is {}×{} but the scene renders {}×{}",
                t.width,
                t.height,
                scene.camera.width,
                scene.camera.height
            );
        }
        if t.pixels.iter().any(|c| !c.is_finite()) {
            bail!("the target image has non-finite pixels");
        }
    }
    Ok(target)
}

/// What `grad` writes: the VDB, its picture, and with `--image-of` the derivative image as EXR and
/// PNG. All are checked before any work so that a refusal to overwrite costs nothing.
fn gradient_outputs(vdb: &Path, image_of: bool) -> Vec<PathBuf> {
    let stem = vdb.with_extension("");
    let mut paths = vec![vdb.to_path_buf(), vdb.with_extension("png")];
    if image_of {
        paths.extend([
            stem.with_extension("dpixel.exr"),
            stem.with_extension("dpixel.png"),
        ]);
    }
    paths
}

fn grad_command(args: &GradArgs) -> Result<()> {
    set_threads(args.adjoint.threads)?;
    let vdb_out = args.output.clone().unwrap_or_else(|| {
        PathBuf::from(format!(
            "{}.grad.vdb",
            args.scene.file_stem().unwrap_or_default().to_string_lossy()
        ))
    });
    if args.estimator != EstimatorArg::Fd {
        if vdb_out.extension().and_then(|e| e.to_str()) != Some("vdb") {
            bail!("--output must end in .vdb (got '{}')", vdb_out.display());
        }
        for path in gradient_outputs(&vdb_out, args.image_of.is_some()) {
            volgrad::refuse_overwrite(&path, args.force)?;
        }
    }
    let scene = Scene::load(&args.scene)?;
    let image_box = args
        .image_of
        .as_deref()
        .map(|spec| parse_box(spec, &scene))
        .transpose()?;
    let target = load_target(args, &scene)?;
    let estimator = match args.estimator {
        EstimatorArg::Joint => Estimator::Joint,
        EstimatorArg::Drt => Estimator::Drt,
        EstimatorArg::Naive => Estimator::Naive,
        EstimatorArg::Fd => return fd_command(args, &scene, target.as_ref()),
    };
    let options = adjoint_options(&scene, estimator, &args.adjoint)?;
    // The adjoint image: δ = ∂loss/∂pixel, from an independent primal render for losses that need one.
    let adjoint = if args.loss.needs_target() {
        let primal = render(
            &scene,
            &RenderOptions {
                spp: options.spp,
                seed: options.seed,
                max_depth: options.adjoint.max_depth,
                progress: options.progress,
            },
        )
        .0;
        eprintln!(
            "loss ({}) = {:.6e}",
            args.loss,
            args.loss.evaluate(&primal, target.as_ref())
        );
        args.loss.adjoint(&primal, target.as_ref())
    } else {
        let blank = images::RgbImage::new(scene.camera.width, scene.camera.height);
        args.loss.adjoint(&blank, None)
    };
    let run = gradient(&scene, &adjoint, &options);
    let provenance = Provenance {
        estimator: estimator.to_string(),
        spp: options.spp as u64,
        seed: options.seed.to_string(),
        loss: args.loss.to_string(),
        scene: args.scene.display().to_string(),
    };
    let grid = gradient_files::gradient_grid(
        &run.gradient,
        &scene.grid_name,
        scene.medium.transform,
        &provenance,
    );
    vdb::write_grids(&vdb_out, &[&grid], false, args.force)?;
    let png = vdb_out.with_extension("png");
    let scale = gradient_files::write_projection_png(&png, &grid)?;
    eprintln!(
        "wrote {} (grid {}, {} voxels with gradient, ⟨g, 1⟩ = {:.6e}) and {} (sum along index z; full colour at ±{:.3e})",
        vdb_out.display(),
        grid.name,
        grid.bricks.active_voxel_count(),
        run.gradient.sum(),
        png.display(),
        scale.unwrap_or(0.0)
    );
    if let Some((lo, hi)) = image_box {
        let (image, _) = derivative_image(&scene, lo, hi, &options);
        let outputs = gradient_outputs(&vdb_out, true);
        let (exr, png) = (&outputs[2], &outputs[3]);
        images::write_exr(exr, &image, false)?;
        let luminance: Vec<f32> = image
            .pixels
            .iter()
            .map(|&c| volgrad::render::lights::luminance(c))
            .collect();
        let scale =
            volgrad::io::colormap::write_signed_png(png, image.width, image.height, &luminance)?;
        eprintln!(
            "wrote {} and {} (d pixel / d ε for the box {lo}..{hi}; full colour at ±{scale:.3e})",
            exr.display(),
            png.display()
        );
    }
    if args.stats {
        let secs = run.stats.wall.as_secs_f64();
        println!("estimator            {}", provenance.estimator);
        println!("wall time            {secs:.3} s");
        println!(
            "ms per spp           {:.2}",
            1e3 * secs / options.spp as f64
        );
        println!("paths/s              {:.0}", run.stats.paths_per_second());
        println!("lookups per path     {:.2}", run.stats.lookups_per_path());
        println!("gradient bricks      {}", run.gradient.brick_count());
    }
    Ok(())
}

fn parse_fd_direction(
    spec: &str,
    scene: &Scene,
    active_only: bool,
    seed: u64,
    floor: f32,
) -> Result<Vec<(String, fd::Direction)>> {
    let grid = &scene.medium.grid;
    let (lo, hi) = fd::domain_bounds(grid).context("the grid is empty")?;
    let domain = || fd::box_voxels(grid, lo, hi, active_only);
    Ok(match spec.split_once(':') {
        Some(("voxels", list)) => list
            .split(';')
            .map(|v| match parse_ivec3s(v, "--fd voxels")?.as_slice() {
                [x, y, z] => Ok((
                    format!("voxel [{x}, {y}, {z}]"),
                    vec![(IVec3::new(*x, *y, *z), 1.0)],
                )),
                _ => bail!("--fd voxels: each voxel is x,y,z (got '{v}')"),
            })
            .collect::<Result<_>>()?,
        Some(("box", b)) => {
            let (a, c) = parse_box(b, scene)?;
            vec![(
                format!("box {a}..{c}"),
                fd::ones(&fd::box_voxels(grid, a, c, active_only)),
            )]
        }
        None if spec == "ones" => vec![("⟨g, 1⟩".into(), fd::ones(&domain()))],
        None if spec == "random" => vec![(
            format!("random ±1 (seed {seed})"),
            fd::random_signs(grid, &domain(), seed, floor),
        )],
        _ => bail!(
            "--fd takes voxels:x,y,z;x,y,z, box:x0,y0,z0,x1,y1,z1, ones or random (got '{spec}')"
        ),
    })
}

fn fd_command(args: &GradArgs, scene: &Scene, target: Option<&images::RgbImage>) -> Result<()> {
    let spec = args
        .fd
        .as_deref()
        .context("--estimator fd needs --fd (voxels:..., box:..., ones or random)")?;
    let seed = args.adjoint.seed.unwrap_or(scene.settings.seed);
    let max_depth = args.adjoint.max_depth.unwrap_or(scene.settings.max_depth);
    let options = fd_options(scene, args.loss, &args.fd_args, seed, max_depth)?;
    let directions = parse_fd_direction(
        spec,
        scene,
        args.adjoint.domain == DomainArg::Active,
        seed,
        3.0 * options.eps,
    )?;
    println!(
        "finite differences of {} ({} spp × {} repeats, common random numbers)",
        args.loss, options.spp, options.repeats
    );
    let bar = volgrad::io::progress::bar(!args.adjoint.quiet, directions.len() as u64, "fd");
    for (name, direction) in directions {
        let mut options = options;
        options.eps = args
            .fd_args
            .eps
            .unwrap_or_else(|| fd::auto_eps(scene, &direction));
        let r = fd::directional_derivative(scene, target, &direction, &options)?;
        bar.suspend(|| {
            println!(
                "{name:<32} {:>14.6e} ± {:.2e}  (ε = {:.3e}){}",
                r.value,
                r.std_err,
                options.eps,
                if r.one_sided {
                    "  (one-sided: empty voxels)"
                } else {
                    ""
                }
            )
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(())
}

fn gradcheck_command(args: &GradcheckArgs) -> Result<()> {
    set_threads(args.adjoint.threads)?;
    let mut scene = Scene::load(&args.scene)?;
    if args.width == 0 {
        bail!("--width must be at least 1");
    }
    let c = scene.camera;
    let height = ((args.width as u64 * c.height as u64) / c.width as u64).max(1) as u32;
    scene.camera = c.with_resolution(args.width, height);
    let grad = adjoint_options(&scene, args.estimator, &args.adjoint)?;
    let fd = fd_options(
        &scene,
        Loss::Mean,
        &args.fd_args,
        grad.seed,
        grad.adjoint.max_depth,
    )?;
    let options = GradcheckOptions {
        grad,
        repeats: args.fd_args.repeats,
        voxels: args.voxels,
        fd,
        fixed_eps: args.fd_args.eps.is_some(),
        progress: !args.adjoint.quiet,
    };
    let eps = match args.fd_args.eps {
        Some(e) => e.to_string(),
        None => "automatic".into(),
    };
    eprintln!("checking {:?} ({} spp × {} runs) against finite differences (ε {eps}, {} spp × {} repeats) on d(mean pixel)/dθ", args.estimator, grad.spp, options.repeats, fd.spp, fd.repeats);
    let checks = gradcheck(&scene, &options)?;
    println!(
        "{:<40} {:>24} {:>24} {:>8}",
        "check", "estimator", "finite differences", "z"
    );
    let mut failed = 0;
    for c in &checks {
        let verdict = if c.passed() { "" } else { "  FAIL" };
        failed += usize::from(!c.passed());
        println!(
            "{:<40} {:>12.4e} ± {:<9.2e} {:>12.4e} ± {:<9.2e} {:>8.2}{verdict}",
            c.name,
            c.estimate,
            c.estimate_se,
            c.fd.value,
            c.fd.std_err,
            c.z()
        );
    }
    if failed > 0 {
        bail!("{failed} of {} checks beyond |z| = {Z_LIMIT}", checks.len());
    }
    println!("all {} checks within |z| < {Z_LIMIT}", checks.len());
    Ok(())
}

fn merge_command(inputs: &[PathBuf], output: &Path, force: bool) -> Result<()> {
    let paths: Vec<&Path> = inputs.iter().map(|p| p.as_path()).collect();
    let grid = gradient_files::merge(&paths)?;
    vdb::write_grids(output, &[&grid], false, force)?;
    eprintln!("wrote {} ({} inputs)", output.display(), inputs.len());
    Ok(())
}

fn compare_command(args: &CompareArgs) -> Result<()> {
    set_threads(args.threads)?;
    let mut estimators = args.estimators.clone();
    estimators.dedup();
    let progress = !args.quiet;
    match (args.suite, &args.scene) {
        (SuiteArg::Stability, _) => {
            let out = args
                .out
                .clone()
                .unwrap_or_else(|| PathBuf::from("compare-stability"));
            let files = [out.join("stability.md"), out.join("stability.csv")];
            prepare_out_dir(&out, &files, args.force)?;
            let options = compare::StabilityOptions {
                runs: args.suite_runs.max(2),
                spp: args.suite_spp.max(1),
                fd_spp: args.fd_spp.unwrap_or(4096).max(1),
                fd_repeats: args.repeats.unwrap_or(8).max(2),
                seed: args.seed.unwrap_or(1),
                max_depth: 16,
                progress,
            };
            let scenes = compare::stability_scenes();
            let rows = compare::stability(&scenes, &estimators, &options)?;
            let table = compare::stability_markdown(&scenes, &rows, &options);
            std::fs::write(&files[0], &table)?;
            std::fs::write(&files[1], compare::stability_csv(&rows))?;
            println!("{table}");
            eprintln!("wrote {} and {}", files[0].display(), files[1].display());
            let non_finite: usize = rows.iter().map(|r| r.non_finite).sum();
            let unexpected = rows
                .iter()
                .filter(|r| !r.unbiased() && !r.expected_failure)
                .count();
            if non_finite > 0 || unexpected > 0 {
                bail!("{non_finite} non-finite values and {unexpected} unexpected biased checks");
            }
            Ok(())
        }
        (SuiteArg::EqualTime, None) => bail!("give a scene file, or --suite stability"),
        (SuiteArg::EqualTime, Some(path)) => compare_equal_time(args, path, &estimators, progress),
    }
}

/// Creates `out` and refuses, before any work, to overwrite one of `files` without --force.
fn prepare_out_dir(out: &Path, files: &[PathBuf], force: bool) -> Result<()> {
    for f in files {
        volgrad::refuse_overwrite(f, force)?;
    }
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create the output directory '{}'", out.display()))
}

fn compare_equal_time(
    args: &CompareArgs,
    path: &Path,
    estimators: &[Estimator],
    progress: bool,
) -> Result<()> {
    if estimators.is_empty() {
        bail!("--estimators needs at least one of joint, drt, naive");
    }
    if args.reference_spp == 0 || args.reference_seeds < 1 || args.max_spp == 0 {
        bail!("--reference-spp, --reference-seeds and --max-spp must be at least 1");
    }
    let scene = Scene::load(path)?;
    let stem = path
        .file_stem()
        .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(format!("compare-{stem}")));
    let render_budget = args.render_budget.unwrap_or(args.budget / 4);
    let mut files: Vec<PathBuf> = [
        "runs.csv",
        "summary.md",
        "gradient-error.png",
        "gradient-error.svg",
    ]
    .iter()
    .map(|f| out.join(f))
    .collect();
    if args.reference.is_none() {
        files.push(out.join("reference.vdb"));
    }
    if !render_budget.is_zero() {
        files.push(out.join("render-error.png"));
        files.push(out.join("render-error.svg"));
    }
    prepare_out_dir(&out, &files, args.force)?;
    let seed = args.seed.unwrap_or(scene.settings.seed);
    let max_depth = scene.settings.max_depth;

    let reference = match &args.reference {
        Some(file) => {
            let r = compare::load_reference(file, &scene)?;
            eprintln!(
                "reference: {} ({} runs × {} spp)",
                file.display(),
                r.runs,
                r.spp_per_run
            );
            r
        }
        None => {
            let options = compare::ReferenceOptions {
                spp: args.reference_spp,
                seeds: args.reference_seeds,
                seed,
                max_depth,
                progress,
            };
            eprintln!(
                "building the reference: {} runs each of joint and drt at {} spp",
                options.seeds, options.spp
            );
            let (r, seconds) = compare::timed(|| compare::build_reference(&scene, &options));
            let file = out.join("reference.vdb");
            compare::save_reference(&file, &scene, &r, args.force)?;
            eprintln!("wrote {} ({seconds:.1} s)", file.display());
            r
        }
    };
    let fd = FdOptions {
        loss: Loss::Mean,
        // Chosen per check by compare::check_reference (a step that suits one voxel is far
        // too large for the whole domain).
        eps: 0.0,
        spp: args.fd_spp.unwrap_or(16).max(1),
        repeats: args.repeats.unwrap_or(8).max(2),
        seed,
        max_depth,
    };
    eprintln!(
        "checking the reference against finite differences ({} spp × {} repeats)",
        fd.spp, fd.repeats
    );
    let checks = compare::check_reference(&scene, &reference, &fd, args.fd_voxels)?;
    let mut worst: f64 = 0.0;
    let mut check_table =
        String::from("| check | reference | finite differences | z |\n|---|---:|---:|---:|\n");
    for c in &checks {
        let z = c.z().abs();
        if z.is_nan() || z > worst {
            worst = z; // f64::max would drop a NaN
        }
        let line = format!(
            "| {} | {:.4e} ± {:.1e} | {:.4e} ± {:.1e} | {:.2} |",
            c.name,
            c.estimate,
            c.estimate_se,
            c.fd.value,
            c.fd.std_err,
            c.z()
        );
        eprintln!("  {line}");
        check_table += &line;
        check_table += "\n";
    }
    // A NaN z (no finite difference) fails too.
    if worst.is_nan() || worst >= Z_LIMIT {
        if args.force_reference {
            eprintln!("warning: the reference disagrees with finite differences (|z| = {worst:.1}); using it because of --force-reference");
        } else {
            bail!("the reference disagrees with finite differences (|z| = {worst:.1} > {Z_LIMIT}): build it with more --reference-spp/--reference-seeds, or pass --force-reference");
        }
    }

    let sweep = compare::SweepOptions {
        budget: args.budget,
        max_spp: args.max_spp,
        seed,
        max_depth,
        progress,
    };
    let mut rows = compare::gradient_sweeps(&scene, estimators, &reference, &sweep);
    let names: Vec<String> = estimators.iter().map(|e| e.to_string()).collect();
    let names: Vec<&str> = names.iter().map(|s| s.as_str()).collect();
    let mut summary = format!(
        "### `volgrad compare {}`\n\nBudget {:.0} s per estimator; reference: {} runs × {} spp (joint and drt alternating); {} threads.\n\n#### Reference against finite differences\n\n{check_table}\n",
        path.display(),
        args.budget.as_secs_f64(),
        reference.runs,
        reference.spp_per_run,
        rayon::current_num_threads()
    );
    summary += &compare::summary(&rows, &names, "drt", "joint", "Gradient");
    compare::write_chart(
        &out,
        "gradient-error",
        &compare::chart(
            &rows,
            &format!("{stem}: gradient error against time"),
            "relative RMSE vs reference",
        ),
    )?;
    if !render_budget.is_zero() {
        let image_reference = compare::build_image_reference(
            &scene,
            args.reference_spp,
            args.reference_seeds.max(2),
            seed,
            max_depth,
            progress,
        );
        let render_rows = compare::render_sweeps(
            &scene,
            &image_reference,
            &compare::SweepOptions {
                budget: render_budget,
                ..sweep
            },
        );
        summary += "\n";
        summary += &compare::summary(
            &render_rows,
            &[compare::RENDER_GRID, compare::RENDER_GLOBAL],
            compare::RENDER_GLOBAL,
            compare::RENDER_GRID,
            "Forward render",
        );
        compare::write_chart(
            &out,
            "render-error",
            &compare::chart(
                &render_rows,
                &format!("{stem}: image error against time"),
                "relative image RMSE",
            ),
        )?;
        rows.extend(render_rows);
    }
    std::fs::write(out.join("runs.csv"), compare::csv(&rows))?;
    std::fs::write(out.join("summary.md"), &summary)?;
    println!("{summary}");
    eprintln!("wrote {}", out.display());
    Ok(())
}
