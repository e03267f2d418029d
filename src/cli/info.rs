//! `volgrad info`: every grid in a .vdb file, and the brick map volgrad would build for it; or,
//! for a scene file, the grids the scene would use and what for.

use std::path::{Path, PathBuf};

use anyhow::Result;

use super::bytes;
use volgrad::io::vdb;
use volgrad::render::scene::Scene;
use volgrad::volume::brickmap::{BrickMap, BRICK_VOXELS};
use volgrad::volume::emission::EmissionKind;

#[derive(clap::Args)]
pub struct Args {
    /// The .vdb file, or a scene file (.toml).
    pub file: PathBuf,
}

pub fn run(args: &Args) -> Result<()> {
    let file = &args.file;
    if file.extension().is_some_and(|e| e == "toml") {
        return scene_grids(file);
    }
    let grids = vdb::list_grids(file)?;
    if grids.is_empty() {
        println!("{}: no grids", file.display());
        return Ok(());
    }
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
        let class_note = match g.grid_class.as_str() {
            "level set" => "  (signed distances: render with medium.levelset = \"fog\")",
            _ => "",
        };
        println!("  class          {}{class_note}", g.grid_class);
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
        // A grid volgrad cannot read (a frustum map, a NaN) says why on its values line, and the
        // listing goes on to the grids after it.
        let read =
            (g.value_type == "float").then(|| vdb::read_grid(file, &vdb::GridSelector::Index(i)));
        if let Some(Err(e)) = &read {
            println!("  values         not readable: {e:#}");
        } else if let Some(Ok(grid)) = read {
            let refused = if grid.background == 0.0 || g.grid_class == "level set" {
                ""
            } else {
                "  (not 0: render refuses it)"
            };
            println!("  background     {}{refused}", grid.background);
            let b = &grid.bricks;
            println!(
                "  values         {} .. {} (mean {:.4} over the active voxels)",
                b.min_value(),
                b.max_value(),
                active_mean(b)
            );
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

/// The mean value over the active voxels, leaves' and tiles' (0 for none): with the largest, what
/// a density scale is chosen from (σt = density_scale × value).
fn active_mean(b: &BrickMap) -> f64 {
    let in_leaves: f64 = b
        .leaves()
        .iter()
        .flat_map(|l| {
            let active = |o: usize| l.active[o / 64] >> (o % 64) & 1 == 1;
            l.values.iter().enumerate().filter(move |&(o, _)| active(o))
        })
        .map(|(_, &v)| f64::from(v))
        .sum();
    let in_tiles: f64 = b
        .tiles()
        .iter()
        .map(|t| f64::from(t.value) * f64::from(t.size).powi(3))
        .sum();
    (in_leaves + in_tiles) / b.active_voxel_count().max(1) as f64
}

/// The grids a scene would read: its density and, if it emits, its emission grid, each with its
/// file, transform and active voxels.
fn scene_grids(path: &Path) -> Result<()> {
    let scene = Scene::load(path)?;
    let m = &scene.medium;
    println!("{}:", path.display());
    println!(
        "  density    grid '{}' in '{}': {} active voxels, voxel size {:.4}, σt = {} × value",
        scene.grid_name,
        scene
            .vdb_path
            .as_deref()
            .expect("a scene loaded to render names its grid's file")
            .display(),
        m.grid.active_voxel_count(),
        m.transform.voxel_size().x,
        m.density_scale
    );
    match &m.emission {
        None => println!("  emission   none"),
        Some(e) => println!(
            "  emission   grid '{}': {} active voxels, voxel size {:.4}, {}",
            e.name,
            e.grid.active_voxel_count(),
            e.transform.voxel_size().x,
            match e.kind {
                EmissionKind::Blackbody {
                    scale,
                    offset,
                    cutoff,
                    strength,
                } => format!(
                    "blackbody at T = (value − {offset}) × {scale} K above {cutoff} K, × {strength}"
                ),
                EmissionKind::Radiance(rgb) => format!("radiance {rgb} × value"),
            }
        ),
    }
    println!("  albedo     {}, phase g {}", m.albedo, m.phase_g);
    Ok(())
}
