//! Writes a copy of a density grid (background 0, as every density read refuses another) with
//! every value (leaves and tiles) multiplied by a factor: e.g. the truth × 0.45, to start a run
//! from it and read the held-out PSNR of a uniformly too thin cloud at iteration 0.
//!
//! ```sh
//! cargo run --release --example scale_grid -- IN.vdb OUT.vdb FACTOR
//! ```

use anyhow::{bail, Context, Result};
use volgrad::io::vdb::{read_density, write_grids, GridSelector, LevelSet};
use volgrad::volume::brickmap::{BrickMap, Leaf, Tile};

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output, factor] = args.as_slice() else {
        bail!("usage: scale_grid IN.vdb OUT.vdb FACTOR");
    };
    let factor: f32 = factor
        .parse()
        .ok()
        .filter(|f: &f32| f.is_finite() && *f >= 0.0)
        .with_context(|| format!("FACTOR must be a finite number >= 0 (got '{factor}')"))?;
    // A density, as the other grid examples read it: a level set's distances are no density to
    // scale.
    let mut grid = read_density(input.as_ref(), &GridSelector::Default, LevelSet::Refuse)?;
    let leaves = grid.bricks.leaves().iter().map(|l| Leaf {
        values: l.values.map(|x| x * factor),
        ..l.clone()
    });
    let tiles = grid.bricks.tiles().iter().map(|t| Tile {
        value: t.value * factor,
        ..*t
    });
    grid.bricks = BrickMap::new(leaves.collect(), tiles.collect());
    write_grids(output.as_ref(), &[&grid], false, false)
}
