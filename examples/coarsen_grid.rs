//! Writes a copy of a float grid box-averaged to 1/2^K of its resolution per axis and resampled
//! back to the original voxels the way an upsampling does (`optimize::resample`): the truth as
//! well as an unknown at a coarser level could hold it, to read with `haze_profile` and a
//! truth-start run (iteration 0) the haze and held-out PSNR each level's resolution allows.
//!
//! ```sh
//! cargo run --release --example coarsen_grid -- IN.vdb OUT.vdb K
//! ```

use anyhow::{bail, Context, Result};
use volgrad::io::vdb::{read_density, write_grids, GridSelector, LevelSet};
use volgrad::optimize::parameters::Parameters;
use volgrad::optimize::resample::{upsample, Moments};

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output, levels] = args.as_slice() else {
        bail!("usage: coarsen_grid IN.vdb OUT.vdb K");
    };
    let levels: u32 = levels
        .parse()
        .ok()
        .filter(|&k| (1..=4).contains(&k))
        .with_context(|| format!("K must be a whole number from 1 to 4 (got '{levels}')"))?;
    let mut grid = read_density(input.as_ref(), &GridSelector::Default, LevelSet::Refuse)?;
    // Tiles voxelised, as an unknown started from this grid would be.
    let mut theta = Parameters::from_grid(&grid.bricks)?;
    for _ in 0..levels {
        // Old voxels 2i and 2i + 1 are the halves of coarse voxel i (`resample`'s convention).
        let mut coarse = Parameters::default();
        for (voxel, value, ..) in theta.voxels() {
            let parent = voxel >> 1;
            coarse.set(parent, coarse.get(parent) + value / 8.0);
        }
        theta = coarse;
    }
    // Only the values are wanted: the transform upsample composes is that of a coarse grid, and
    // the output keeps the input's.
    for _ in 0..levels {
        theta = upsample(&theta, &grid.transform, Moments::Reset, None)?.0;
    }
    theta.prune();
    grid.bricks = theta.to_brickmap();
    write_grids(output.as_ref(), &[&grid], false, false)
}
