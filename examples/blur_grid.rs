//! Writes a copy of a float grid filtered with [1 2 1]/4 per axis `PASSES` times (the filter of
//! `smooth_gradient`; k passes blur by σ = √(k/2) voxels): e.g. the truth blurred by about a pixel
//! of the cloud's 64² views (2 passes, σ = 1 voxel), to read with `haze_profile` how much haze a
//! boundary placed only to within a pixel would leave.
//!
//! ```sh
//! cargo run --release --example blur_grid -- IN.vdb OUT.vdb PASSES
//! ```

use anyhow::{bail, Context, Result};
use glam::IVec3;
use volgrad::io::vdb::{read_density, write_grids, GridSelector, LevelSet};
use volgrad::optimize::brick_gradient::BrickGradient;
use volgrad::optimize::parameters::Parameters;
use volgrad::optimize::smoothing::smooth;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output, passes] = args.as_slice() else {
        bail!("usage: blur_grid IN.vdb OUT.vdb PASSES");
    };
    let passes: u32 =
        passes.parse().ok().filter(|&p| p <= 16).with_context(|| {
            format!("PASSES must be a whole number from 0 to 16 (got '{passes}')")
        })?;
    // A density: a level set, a non-zero background or negative values would not be blurred
    // as they are (the voxels below are kept ≥ 0).
    let mut grid = read_density(input.as_ref(), &GridSelector::Default, LevelSet::Refuse)?;
    if grid.bricks.min_value() < 0.0 {
        bail!("'{input}' has negative values; the filter reads densities (≥ 0)");
    }
    let Some((lo, hi)) = grid.bricks.active_bounds() else {
        bail!("'{input}' has no active voxels");
    };
    // Tiles voxelised, as an unknown started from this grid would be.
    let voxels = Parameters::from_grid(&grid.bricks)?;
    let voxels =
        BrickGradient::from_voxels(voxels.voxels().map(|(v, value, ..)| (v, f64::from(value))));
    // Each pass widens the support by one voxel per side.
    let margin = IVec3::splat(passes as i32);
    let mut blurred = Parameters::default();
    for (voxel, value) in smooth(voxels, passes, lo - margin, hi + margin).voxels() {
        blurred.set(voxel, value as f32);
    }
    blurred.prune();
    grid.bricks = blurred.to_brickmap();
    write_grids(output.as_ref(), &[&grid], false, false)
}
