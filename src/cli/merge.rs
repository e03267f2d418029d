//! `volgrad merge`: gradient VDBs of runs with different seeds, combined weighted by their spp (any
//! parameter's; an RGB albedo gradient stays a vec3 grid).

use std::path::{Path, PathBuf};

use anyhow::Result;

use volgrad::io::{gradient_files, vdb};

#[derive(clap::Args)]
pub struct Args {
    /// Gradient VDBs written by `volgrad grad`.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    #[arg(short, long)]
    pub output: PathBuf,
    /// Overwrite an existing output.
    #[arg(long)]
    pub force: bool,
}

pub fn run(args: &Args) -> Result<()> {
    let (inputs, output, force) = (&args.inputs, &args.output, args.force);
    let paths: Vec<&Path> = inputs.iter().map(|p| p.as_path()).collect();
    match gradient_files::merge(&paths)?.as_slice() {
        [grid] => vdb::write_grids(output, &[grid], false, force)?,
        [r, g, b] => vdb::write_grids_with_colours(output, &[], &[[r, g, b]], false, force)?,
        _ => unreachable!("a gradient has one or three channels"),
    }
    eprintln!("wrote {} ({} inputs)", output.display(), inputs.len());
    Ok(())
}
