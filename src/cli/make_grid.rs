//! `volgrad make-grid`: a small analytic grid (box, sphere, slab, single dense voxel; a fireball
//! with its temperature, coloured smoke with its albedo) as a .vdb.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::ValueEnum;

use volgrad::io::make_grid::{
    coloured_smoke_albedo, fireball_temperature, make_grid, Class, GridKind, GridSpec,
};
use volgrad::io::output::require_extension;
use volgrad::io::vdb;
use volgrad::render::scene_check::MAX_COORDINATE;

#[derive(clap::Args)]
pub struct Args {
    /// What to make.
    #[arg(value_enum)]
    pub kind: GridKind,
    /// Output .vdb file.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Edge length in voxels.
    #[arg(long, default_value_t = 16)]
    pub size: u32,
    /// Slab thickness in voxels (slab only; default 2).
    #[arg(long)]
    pub thickness: Option<u32>,
    /// Grid value inside the shape (fog volumes only: a level set holds distances; default 1).
    #[arg(long, allow_negative_numbers = true)]
    pub value: Option<f32>,
    /// Voxel size: one number, or three (x,y,z) for anisotropic voxels.
    #[arg(long, value_delimiter = ',', default_value = "1")]
    pub voxel_size: Vec<f64>,
    /// Rotation in degrees about x, then y, then z.
    #[arg(long, value_delimiter = ',', allow_negative_numbers = true)]
    pub rotate_deg: Option<Vec<f64>>,
    /// Grid class: a fog volume of densities, or (sphere only) a level set of signed distances.
    #[arg(long, value_enum, default_value = "fog")]
    pub class: Class,
    /// Grid name.
    #[arg(long, default_value = "density")]
    pub name: String,
    /// Store values as half floats.
    #[arg(long)]
    pub half: bool,
    /// Overwrite an existing file.
    #[arg(long)]
    pub force: bool,
}

pub fn run(args: &Args) -> Result<()> {
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
    require_extension(&args.output, "vdb")?;
    if args.thickness.is_some() && args.kind != GridKind::Slab {
        bail!(
            "--thickness is a slab's: leave it out for {}",
            (args.kind.to_possible_value()).map_or(String::new(), |v| v.get_name().to_string())
        );
    }
    let thickness = args.thickness.unwrap_or(2);
    if args.kind == GridKind::Slab && !(1..=args.size).contains(&thickness) {
        bail!(
            "--thickness must be 1 to --size ({}) voxels (got {thickness})",
            args.size,
        );
    }
    if args.class == Class::Levelset && args.value.is_some() {
        bail!("--value is a fog volume's: a level set holds the distances to its surface");
    }
    // A grid no scene can place a camera beside is of no use to render.
    let extent = voxel_size.iter().fold(0.0f64, |m, &s| m.max(s)) * f64::from(args.size);
    if extent > f64::from(MAX_COORDINATE) {
        bail!(
            "--voxel-size × --size is {extent:e} world units: at most {MAX_COORDINATE:e}, the farthest a scene places anything"
        );
    }
    // The companion grid's name, which the density's must not take (every read would refuse
    // a file holding two grids of one name).
    let companion = match args.kind {
        GridKind::Fireball => Some("temperature"),
        GridKind::ColouredSmoke => Some("Cd"),
        _ => None,
    };
    if companion == Some(args.name.as_str()) {
        bail!(
            "--name {} is the name of the grid made beside it: give the density another",
            args.name
        );
    }
    let spec = GridSpec {
        kind: args.kind,
        size: args.size,
        thickness,
        value: args.value.unwrap_or(1.0),
        voxel_size,
        rotate_deg,
        name: args.name.clone(),
        class: args.class,
    };
    let grid = make_grid(&spec)?;
    if args.kind == GridKind::Fireball {
        let temperature = fireball_temperature(&spec)?;
        vdb::write_grids(&args.output, &[&grid, &temperature], args.half, args.force)?;
        eprintln!(
            "wrote {} with grids '{}' and 'temperature'",
            args.output.display(),
            grid.name
        );
        return Ok(());
    }
    if args.kind == GridKind::ColouredSmoke {
        let [r, g, b] = coloured_smoke_albedo(&spec)?;
        vdb::write_grids_with_colours(
            &args.output,
            &[&grid],
            &[[&r, &g, &b]],
            args.half,
            args.force,
        )?;
        eprintln!(
            "wrote {} with grids '{}' and 'Cd' (vec3)",
            args.output.display(),
            grid.name
        );
        return Ok(());
    }
    vdb::write_grids(&args.output, &[&grid], args.half, args.force)?;
    eprintln!(
        "wrote {} ({} active voxels)",
        args.output.display(),
        grid.bricks.active_voxel_count()
    );
    Ok(())
}
