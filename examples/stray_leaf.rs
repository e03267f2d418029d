//! Writes the Disney cloud with a copy of one of its leaves moved `D` voxels along the diagonal
//! (a stray wisp far from a plume, whose box is then mostly empty), and a scene that renders it
//! with `scenes/cloud.toml`'s camera, lights and image: how much a far cluster of data slows a
//! render, against the cloud alone ([speed](../docs/speed.md#what-was-tried)).
//!
//! ```sh
//! cargo run --release --example stray_leaf -- 2000 /tmp/stray      # writes /tmp/stray.vdb and /tmp/stray.toml
//! volgrad render /tmp/stray.toml --spp 4 --threads 1 --stats
//! volgrad render scenes/cloud.toml --spp 4 --threads 1 --stats
//! ```

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::IVec3;
use volgrad::io::output::write_bytes_whole;
use volgrad::io::vdb::{read_density, write_grids, GridSelector, LevelSet};
use volgrad::volume::brickmap::BrickMap;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [distance, out] = args.as_slice() else {
        bail!("usage: stray_leaf D OUT (writes OUT.vdb and OUT.toml)");
    };
    let distance: i32 = distance
        .parse()
        .ok()
        .filter(|d| (8..=1 << 24).contains(d))
        .with_context(|| {
            format!("D must be a whole number of voxels from 8 to 2^24 (got '{distance}')")
        })?;
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let (vdb, scene) = (
        PathBuf::from(format!("{out}.vdb")),
        PathBuf::from(format!("{out}.toml")),
    );
    if scene.exists() {
        bail!("'{}' exists: choose another OUT", scene.display());
    }
    let mut grid = read_density(
        &root.join("scenes/assets/wdas_cloud_sixteenth.vdb"),
        &GridSelector::Default,
        LevelSet::Refuse,
    )?;
    let mut leaves = grid.bricks.leaves().to_vec();
    let mut stray = leaves[leaves.len() / 2].clone();
    // A whole number of leaves away, so that the copy is a leaf of its own.
    stray.origin += IVec3::splat(distance & !7);
    leaves.push(stray);
    grid.bricks = BrickMap::new(leaves, grid.bricks.tiles().to_vec());
    write_grids(&vdb, &[&grid], false, false)?;
    let cloud = std::fs::read_to_string(root.join("scenes/cloud.toml"))?;
    // The scene beside the grid names it by its file name (a scene's paths are its folder's).
    let name = vdb
        .file_name()
        .context("OUT names a file")?
        .to_string_lossy();
    let quoted = toml::Value::String(name.into_owned()).to_string();
    let text = cloud.replace("\"assets/wdas_cloud_sixteenth.vdb\"", &quoted);
    write_bytes_whole(&scene, text)?;
    eprintln!("wrote '{}' and '{}'", vdb.display(), scene.display());
    Ok(())
}
