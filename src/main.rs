//! The `volgrad` command line.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};

use volgrad::brickmap::BRICK_VOXELS;
use volgrad::image_io;
use volgrad::majorant::MajorantMode;
use volgrad::make_grid::{make_grid, GridKind, GridSpec};
use volgrad::render::{render, RenderOptions, RenderStats};
use volgrad::scene::{MajorantName, Scene};
use volgrad::vdb;

#[derive(Parser)]
#[command(name = "volgrad", version, about = "Differentiable volumetric path tracing of OpenVDB density grids")]
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
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum MajorantArg {
    /// One majorant per coarse cell of the grid (fast).
    Grid,
    /// One majorant for the whole medium (the baseline).
    Global,
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
    majorant: Option<MajorantArg>,
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
    #[arg(long, default_value_t = 1.0)]
    value: f32,
    /// Voxel size: one number, or three (x,y,z) for anisotropic voxels.
    #[arg(long, value_delimiter = ',', num_args = 1..=3, default_value = "1")]
    voxel_size: Vec<f64>,
    /// Rotation in degrees about x, then y, then z.
    #[arg(long, value_delimiter = ',', num_args = 3, allow_negative_numbers = true)]
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

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Info { file } => info(&file),
        Command::Render(args) => render_command(&args),
        Command::MakeGrid(args) => make_grid_command(&args),
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
    println!("{}: {} grid{}", file.display(), grids.len(), if grids.len() == 1 { "" } else { "s" });
    for (i, g) in grids.iter().enumerate() {
        println!("\n[{i}] {}", g.name);
        println!("  value type     {}{}", g.value_type, if g.saved_as_half { " (saved as half)" } else { "" });
        println!("  class          {}", g.grid_class);
        let v = g.voxel_size;
        let kind = match (g.linear, g.axis_aligned) {
            (false, _) => "non-linear map (not renderable)",
            (true, true) => "scale + translation",
            (true, false) => "general affine (rotated or sheared)",
        };
        println!("  voxel size     {} × {} × {}  ({kind})", v[0], v[1], v[2]);
        let m = g.index_to_world;
        for r in 0..3 {
            println!("  {}   [{:>10.5} {:>10.5} {:>10.5} | {:>10.5}]", if r == 0 { "index→world" } else { "           " }, m[4 * r], m[4 * r + 1], m[4 * r + 2], m[4 * r + 3]);
        }
        println!("  active voxels  {}", g.active_voxels);
        println!("  leaves         {}", g.leaf_count);
        println!("  active tiles   {}", g.active_tiles);
        if g.index_min.iter().zip(&g.index_max).all(|(a, b)| a <= b) {
            println!("  index bbox     {:?} .. {:?}", g.index_min, g.index_max);
            println!("  world bbox     {:?} .. {:?}", g.world_min.map(|x| (x * 1e4).round() / 1e4), g.world_max.map(|x| (x * 1e4).round() / 1e4));
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
        rayon::ThreadPoolBuilder::new().num_threads(t).build_global().context("cannot start the thread pool")?;
    }
    Ok(())
}

/// Applies the command-line overrides that change how the medium is tracked.
fn load_scene(path: &Path, majorant: Option<MajorantArg>, majorant_cell: Option<u32>) -> Result<Scene> {
    let mut scene = Scene::load(path)?;
    if majorant.is_some() || majorant_cell.is_some() {
        let cell = majorant_cell.unwrap_or(scene.settings.majorant_cell);
        if cell == 0 || cell > 1024 {
            bail!("--majorant-cell must be between 1 and 1024 voxels (got {cell})");
        }
        let global = majorant.map_or(scene.settings.majorant == MajorantName::Global, |m| m == MajorantArg::Global);
        scene.set_majorant(if global { MajorantMode::Global } else { MajorantMode::Grid { cell_voxels: cell } });
    }
    Ok(scene)
}

fn render_command(args: &RenderArgs) -> Result<()> {
    set_threads(args.threads)?;
    let exr = args.output.clone().unwrap_or_else(|| PathBuf::from(args.scene.file_stem().unwrap_or_default()).with_extension("exr"));
    if exr.extension().and_then(|e| e.to_str()) != Some("exr") {
        bail!("--output must end in .exr (got '{}'); the PNG is written beside it", exr.display());
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
    image_io::write_exr(&exr, &image, args.half)?;
    image_io::write_png(&png, &image, scene.settings.exposure)?;
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
        MajorantName::Global => "global".to_string(),
        MajorantName::Grid => format!("grid, {}³-voxel cells", scene.settings.majorant_cell),
    };
    println!("wall time            {:.3} s", stats.wall.as_secs_f64());
    println!("paths                {}", stats.paths);
    println!("paths/s              {:.0}", stats.paths_per_second());
    println!("majorant             {majorant} ({} cells)", m.majorant.cell_count());
    println!("lookups per path     {:.2} ({:.2} free-flight + {:.2} shadow)", stats.lookups_per_path(), t.lookups as f64 / stats.paths as f64, t.shadow_lookups as f64 / stats.paths as f64);
    println!("tracking efficiency  {:.3} (real collisions / free-flight lookups)", stats.tracking_efficiency());
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
        bail!("--output must end in .vdb (got '{}')", args.output.display());
    }
    let spec = GridSpec { kind: args.kind, size: args.size, thickness: args.thickness, value: args.value, voxel_size, rotate_deg, name: args.name.clone() };
    let grid = make_grid(&spec)?;
    vdb::write_grids(&args.output, &[&grid], args.half, args.force)?;
    eprintln!("wrote {} ({} active voxels)", args.output.display(), grid.bricks.active_voxel_count());
    Ok(())
}
