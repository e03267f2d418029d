//! `volgrad compare`: speed against accuracy (the equal-time study of one scene) or the stability
//! suite. The studies themselves live in the library (`volgrad::compare`).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Result};
use clap::ValueEnum;

use super::{set_threads, values};
use volgrad::compare::{self, EqualTimeOptions, StabilityOptions};
use volgrad::gradient::adjoint::Estimator;
use volgrad::render::scene::Scene;

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Suite {
    /// Error against time for each estimator and for the renderer's majorants, on SCENE.
    EqualTime,
    /// Scenes built in memory to break estimators: bias, variance, non-finite values.
    Stability,
}

#[derive(clap::Args)]
pub struct Args {
    /// The scene file (TOML); not needed for --suite stability.
    #[arg(required_unless_present = "suite")]
    pub scene: Option<PathBuf>,
    #[arg(long, value_enum, default_value = "equal-time")]
    pub suite: Suite,
    /// Estimators to compare, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "joint,drt,naive"
    )]
    pub estimators: Vec<Estimator>,
    /// Wall time per estimator (and per majorant mode for the renderer), e.g. 120s, 2m (default:
    /// 120s).
    #[arg(long, value_parser = values::duration)]
    pub budget: Option<Duration>,
    /// Wall time per majorant mode of the forward-renderer comparison (default: budget / 4; 0s
    /// skips it).
    #[arg(long, value_parser = values::duration)]
    pub render_budget: Option<Duration>,
    /// A reference gradient written by an earlier `volgrad compare` (reference.vdb).
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Samples per pixel of each reference run (default: 64).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub reference_spp: Option<u32>,
    /// Runs of each of joint and drt averaged into the reference, 1 to 10000 (default: 8).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    pub reference_seeds: Option<u32>,
    /// Use the reference even if finite differences disagree with it (|z| > 4).
    #[arg(long)]
    pub force_reference: bool,
    /// Largest spp of a sweep (default: 4096).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_spp: Option<u32>,
    /// Voxels (of largest |gradient|) checked against finite differences (default: 3).
    #[arg(long)]
    pub fd_voxels: Option<usize>,
    /// Samples per pixel of each finite-difference render (default: 16; 4096 for the suite).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub fd_spp: Option<u32>,
    /// Finite-difference repetitions, at least 2 (default: 8).
    #[arg(long, value_parser = clap::value_parser!(u32).range(2..))]
    pub repeats: Option<u32>,
    /// Stability suite: independent runs per estimator and scene (for the standard error), at
    /// least 2 (default: 8).
    #[arg(long, value_parser = clap::value_parser!(u32).range(2..))]
    pub suite_runs: Option<u32>,
    /// Stability suite: samples per pixel of each run (default: 64).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub suite_spp: Option<u32>,
    /// Random seed (default: render.seed, or 1 for the suite).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Output directory (default: compare-<scene>/, or compare-stability/).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// No progress bars.
    #[arg(long, short)]
    pub quiet: bool,
    /// Overwrite existing outputs.
    #[arg(long)]
    pub force: bool,
}

pub fn run(args: &Args) -> Result<()> {
    set_threads(args.threads)?;
    refuse_other_suites_flags(args)?;
    // Each estimator once, in the order given (a repeat would sweep it twice into one curve).
    let mut estimators = Vec::new();
    for &e in &args.estimators {
        if !estimators.contains(&e) {
            estimators.push(e);
        }
    }
    match (args.suite, &args.scene) {
        (Suite::Stability, Some(path)) => bail!(
            "--suite stability runs its own scenes: leave out '{}'",
            path.display()
        ),
        (Suite::Stability, None) => stability(args, &estimators),
        (Suite::EqualTime, None) => bail!("give a scene file, or --suite stability"),
        (Suite::EqualTime, Some(path)) => {
            if args.budget == Some(Duration::ZERO) {
                bail!("--budget must be above 0 (each estimator's run takes that time)");
            }
            let scene = Scene::load(path)?;
            let budget = args.budget.unwrap_or(Duration::from_secs(120));
            let name = path
                .file_stem()
                .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
            let out = args
                .out
                .clone()
                .unwrap_or_else(|| PathBuf::from(format!("compare-{name}")));
            let options = EqualTimeOptions {
                estimators,
                budget,
                render_budget: args.render_budget.unwrap_or(budget / 4),
                reference: args.reference.clone(),
                reference_spp: args.reference_spp.unwrap_or(64),
                reference_seeds: args.reference_seeds.unwrap_or(8),
                force_reference: args.force_reference,
                max_spp: args.max_spp.unwrap_or(4096),
                fd_voxels: args.fd_voxels.unwrap_or(3),
                fd_spp: args.fd_spp.unwrap_or(16),
                fd_repeats: args.repeats.unwrap_or(8),
                seed: args.seed.unwrap_or(scene.settings.seed),
                progress: !args.quiet,
                overwrite: args.force,
            };
            let summary = compare::equal_time(&scene, &name, &out, &options)?;
            println!("{summary}");
            eprintln!("wrote {}", out.display());
            Ok(())
        }
    }
}

/// A flag only the other suite reads is refused by name, rather than ignored.
fn refuse_other_suites_flags(args: &Args) -> Result<()> {
    use Suite::{EqualTime, Stability};
    let flags = [
        ("--budget", args.budget.is_some(), EqualTime),
        ("--render-budget", args.render_budget.is_some(), EqualTime),
        ("--reference", args.reference.is_some(), EqualTime),
        ("--reference-spp", args.reference_spp.is_some(), EqualTime),
        (
            "--reference-seeds",
            args.reference_seeds.is_some(),
            EqualTime,
        ),
        ("--force-reference", args.force_reference, EqualTime),
        ("--max-spp", args.max_spp.is_some(), EqualTime),
        ("--fd-voxels", args.fd_voxels.is_some(), EqualTime),
        ("--suite-runs", args.suite_runs.is_some(), Stability),
        ("--suite-spp", args.suite_spp.is_some(), Stability),
    ];
    let misplaced: Vec<&str> = (flags.iter())
        .filter(|&&(_, given, suite)| given && suite != args.suite)
        .map(|&(flag, ..)| flag)
        .collect();
    let name = |suite: Suite| suite.to_possible_value().map(|v| v.get_name().to_string());
    match misplaced.as_slice() {
        [] => Ok(()),
        flags => bail!(
            "{} belong to the other suite, not --suite {}: leave them out",
            flags.join(", "),
            name(args.suite).unwrap_or_default()
        ),
    }
}

fn stability(args: &Args, estimators: &[Estimator]) -> Result<()> {
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("compare-stability"));
    let options = StabilityOptions {
        runs: args.suite_runs.unwrap_or(8),
        spp: args.suite_spp.unwrap_or(64),
        fd_spp: args.fd_spp.unwrap_or(4096),
        fd_repeats: args.repeats.unwrap_or(8),
        seed: args.seed.unwrap_or(1),
        max_depth: 16,
        progress: !args.quiet,
    };
    let report = compare::stability_suite(estimators, &options, &out, args.force)?;
    println!("{}", report.markdown);
    match report.failure() {
        Some(failure) => bail!(failure),
        None => Ok(()),
    }
}
