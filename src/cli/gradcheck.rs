//! `volgrad gradcheck`: an estimator against finite differences (z-scores) on a small render of the
//! scene, before its gradients are trusted.

use std::path::PathBuf;

use anyhow::{bail, Result};

use super::grad::check_parameter;
use super::{set_threads, AdjointArgs, FdArgs};
use volgrad::gradient::adjoint::Estimator;
use volgrad::gradient::gradcheck::{checks_table, gradcheck, GradcheckOptions, Z_LIMIT};
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{parameter_grid, Parameter};
use volgrad::render::scene::Scene;
use volgrad::render::scene_check;

#[derive(clap::Args)]
pub struct Args {
    pub scene: PathBuf,
    #[arg(long, value_enum, default_value_t = Estimator::Joint)]
    pub estimator: Estimator,
    /// Number of random voxels to check, 0 to 10000.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(0..=10_000))]
    pub voxels: u32,
    /// Image width for the check (the height follows the scene's aspect ratio): finite differences
    /// render the image many times, so a small one keeps the check quick.
    #[arg(long, default_value_t = 32)]
    pub width: u32,
    /// The colour channel to check of an RGB albedo grid (`--parameter albedo`): 0 red, 1 green,
    /// 2 blue.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=2))]
    pub channel: u8,
    #[command(flatten)]
    pub fd_args: FdArgs,
    #[command(flatten)]
    pub adjoint: AdjointArgs,
}

pub fn run(args: &Args) -> Result<()> {
    set_threads(args.adjoint.sampling.threads)?;
    let mut scene = Scene::load(&args.scene)?;
    let c = scene.camera;
    let height = ((u64::from(args.width) * u64::from(c.height)) / u64::from(c.width)).max(1);
    let height = u32::try_from(height).unwrap_or(u32::MAX);
    scene_check::image_size("--width", "the height it gives", args.width, height)?;
    scene.camera = c.with_resolution(args.width, height);
    let mut grad = args.adjoint.options(&scene, args.estimator)?;
    check_parameter(&scene, grad.parameter)?;
    match (grad.parameter, scene.medium.albedo.grid()) {
        (Parameter::Albedo, Some(a)) if a.channels.len() == 3 => {
            grad.channel = Some(args.channel as usize)
        }
        _ if args.channel != 0 => {
            bail!("--channel picks a channel of an RGB albedo grid: it goes with --parameter albedo and a scene whose albedo grid has three")
        }
        _ => {}
    }
    let perturbed = parameter_grid(&scene, grad.parameter, grad.channel);
    let fd = (args.fd_args).options(perturbed, Loss::Mean, grad.seed, grad.adjoint.max_depth)?;
    let options = GradcheckOptions {
        grad,
        repeats: args.fd_args.repeats,
        voxels: args.voxels as usize,
        fd,
        fixed_eps: args.fd_args.eps.is_some(),
        progress: !args.adjoint.sampling.quiet,
    };
    let eps = match args.fd_args.eps {
        Some(e) => e.to_string(),
        None => "automatic".into(),
    };
    eprintln!("checking {:?} on {} ({} spp × {} runs) against finite differences (ε {eps}, {} spp × {} repeats) on d(mean pixel)/dθ", args.estimator, grad.parameter, grad.spp, options.repeats, fd.spp, fd.repeats);
    let checks = gradcheck(&scene, &options)?;
    if checks.is_empty() {
        bail!(
            "nothing to check: the scene's {} grid has no voxels",
            grad.parameter
        );
    }
    print!("{}", checks_table(&checks).markdown());
    let failed = checks.iter().filter(|c| !c.passed()).count();
    if failed > 0 {
        bail!("{failed} of {} checks beyond |z| = {Z_LIMIT}", checks.len());
    }
    println!("all {} checks within |z| < {Z_LIMIT}", checks.len());
    Ok(())
}
