//! `volgrad render`: a scene to a linear EXR and a tonemapped PNG beside it.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Result};

use super::{bytes, check_same_job, report_non_finite, set_threads, warn_if_empty, SamplingArgs};
use volgrad::cluster::images::render_shared;
use volgrad::cluster::Cluster;
use volgrad::io::images;
use volgrad::io::output::{refuse_overwrite, refuse_unwritable_folder, require_extension};
use volgrad::render::fingerprint;
use volgrad::render::image::{RenderOptions, RenderStats};
use volgrad::render::scene::Scene;
use volgrad::volume::brickmap::BRICK_VOXELS;
use volgrad::volume::majorant::{Majorant, MajorantMode};

#[derive(clap::Args)]
pub struct Args {
    /// The scene file (TOML).
    pub scene: PathBuf,
    /// Output EXR; the PNG goes beside it. Default: <scene name>.exr in the current directory.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    #[command(flatten)]
    pub sampling: SamplingArgs,
    /// Majorant structure for tracking (overrides render.majorant).
    #[arg(long, value_enum)]
    pub majorant: Option<MajorantMode>,
    /// Majorant cell edge in voxels (overrides render.majorant_cell).
    #[arg(long)]
    pub majorant_cell: Option<u32>,
    /// Store the EXR as half floats.
    #[arg(long)]
    pub half: bool,
    /// Print paths/s, density lookups per path, tracking efficiency and memory.
    #[arg(long)]
    pub stats: bool,
    /// Overwrite existing output files.
    #[arg(long)]
    pub force: bool,
}

/// Applies the command-line overrides that change how the medium is tracked.
fn load_scene(
    path: &Path,
    majorant: Option<MajorantMode>,
    majorant_cell: Option<u32>,
) -> Result<Scene> {
    let mut scene = Scene::load(path)?;
    if majorant.unwrap_or(scene.settings.majorant) == MajorantMode::Global
        && majorant_cell.is_some()
    {
        bail!("--majorant-cell sets the cells of the majorant grid: with the global majorant (one for the whole medium) it would be ignored");
    }
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

/// Under mpirun every rank renders its share of the pixels; rank 0 writes the image.
pub fn run(args: &Args, cluster: &Cluster) -> Result<()> {
    let sampling = &args.sampling;
    let exr = args.output.clone().unwrap_or_else(|| {
        PathBuf::from(args.scene.file_stem().unwrap_or_default()).with_extension("exr")
    });
    // Every rank is given the same flags: one error, printed once.
    cluster.agree(set_threads(sampling.threads).and_then(|_| {
        require_extension(&exr, "exr").map_err(|e| anyhow!("{e}; the PNG is written beside it"))
    }))?;
    let png = exr.with_extension("png");
    let root = cluster.is_root();
    cluster.agree(if root {
        refuse_overwrite(&exr, args.force)
            .and_then(|_| refuse_overwrite(&png, args.force))
            .and_then(|_| refuse_unwritable_folder(&exr))
    } else {
        Ok(())
    })?;
    let loading = std::time::Instant::now();
    let scene = cluster.agree(load_scene(&args.scene, args.majorant, args.majorant_cell))?;
    let load_seconds = loading.elapsed().as_secs_f64();
    check_same_job(cluster, || vec![fingerprint::scene(&scene)])?;
    warn_if_empty(&scene, cluster);
    let options = RenderOptions {
        spp: cluster.agree(sampling.spp(&scene))?,
        seed: sampling.seed(&scene),
        max_depth: sampling.max_depth(&scene),
        progress: !sampling.quiet && root,
    };
    let (image, stats) = render_shared(cluster, &scene, &options);
    if !root {
        return cluster.agree(Ok(()));
    }
    report_non_finite(&stats);
    cluster.agree(
        images::write_exr(&exr, &image, args.half)
            .and_then(|_| images::write_png(&png, &image, scene.settings.exposure)),
    )?;
    eprintln!("wrote {} and {}", exr.display(), png.display());
    if args.stats {
        print_stats(&scene, &stats, load_seconds);
    }
    Ok(())
}

/// `load_seconds`: reading the scene and its grid and building the medium (brick map, majorant).
fn print_stats(scene: &Scene, stats: &RenderStats, load_seconds: f64) {
    let m = &scene.medium;
    let t = &stats.tracking;
    let majorant = match scene.settings.majorant {
        MajorantMode::Global => "global".to_string(),
        MajorantMode::Grid => format!("grid, {}³-voxel cells", scene.settings.majorant_cell),
    };
    let leaf_bytes = m.grid.leaves().len() * BRICK_VOXELS * 4;
    println!(
        "load                 {load_seconds:.3} s ({:.2} s per GiB of leaf values)",
        load_seconds / (leaf_bytes.max(1) as f64 / (1u64 << 30) as f64)
    );
    println!("wall time            {:.3} s", stats.wall.as_secs_f64());
    println!("paths                {}", stats.paths);
    println!("paths/s              {:.0}", stats.paths_per_second());
    let layout = match m.majorant.flat_boxes() {
        0 => "in blocks".to_string(),
        1 => "in one box".to_string(),
        n => format!("in {n} boxes around the data"),
    };
    println!(
        "majorant             {majorant} ({} cells {layout})",
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
    println!("non-finite samples   {} (dropped)", stats.non_finite);
    println!(
        "memory               brick map {} = {:.3} × leaf values ({} leaves, {} tiles); majorant {}",
        bytes(m.grid.memory_bytes()),
        m.grid.memory_bytes() as f64 / leaf_bytes.max(1) as f64,
        m.grid.leaves().len(),
        m.grid.tiles().len(),
        bytes(m.majorant.memory_bytes())
    );
    super::print_peak_memory();
}
