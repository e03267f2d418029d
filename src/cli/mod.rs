//! The `volgrad` subcommands, a file each: its `Args` next to its `run()`. Options that several
//! commands share live here; the hand-written value formats (durations, index boxes, voxel
//! lists) live in `values`.

pub mod compare;
pub mod grad;
pub mod gradcheck;
pub mod info;
pub mod make_grid;
pub mod merge;
pub mod optimize;
pub mod render;
pub mod values;

#[cfg(test)]
mod manual_tests;
#[cfg(test)]
mod parse_tests;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};

use volgrad::cluster::Cluster;
use volgrad::gradient::adjoint::{AdjointOptions, Estimator, Suffix, DEFAULT_SUFFIX_PATHS};
use volgrad::gradient::fd::{self, FdOptions};
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{GradOptions, Measured, Parameter};
use volgrad::gradient::pixel_samples::PixelSamples;
use volgrad::io::fingerprint::Fingerprint;
use volgrad::render::image::RenderStats;
use volgrad::render::scene::Scene;
use volgrad::render::scene_check;
use volgrad::volume::brickmap::BrickMap;

/// Which voxels are parameters.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Domain {
    /// Every voxel a ray can reach inside the medium's bounds, empty ones included.
    All,
    /// Only the grid's active voxels.
    Active,
}

volgrad::display_as_value_enum!(Domain);

/// How many paths, from which random streams, how deep, on how many threads: every command that
/// traces paths takes these, each overriding the scene's `[render]` value.
#[derive(Args)]
pub struct SamplingArgs {
    /// Samples per pixel (default: render.spp).
    #[arg(long)]
    pub spp: Option<u32>,
    /// Random seed (default: render.seed); the same seed gives the same result on any thread count.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Maximum scattering events per path (default: render.max_depth).
    #[arg(long)]
    pub max_depth: Option<u32>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
}

impl SamplingArgs {
    /// Samples per pixel: the flag or the scene's, at least 1.
    pub fn spp(&self, scene: &Scene) -> Result<u32> {
        match self.spp.unwrap_or(scene.settings.spp) {
            0 => bail!("--spp must be at least 1"),
            spp => Ok(spp),
        }
    }

    pub fn seed(&self, scene: &Scene) -> u64 {
        self.seed.unwrap_or(scene.settings.seed)
    }

    pub fn max_depth(&self, scene: &Scene) -> u32 {
        self.max_depth.unwrap_or(scene.settings.max_depth)
    }
}

/// Options of the gradient pass, shared by `grad` and `gradcheck`.
#[derive(Args)]
pub struct AdjointArgs {
    #[command(flatten)]
    pub sampling: SamplingArgs,
    /// Where the indirect part of ĥ at a probe comes from.
    #[arg(long, value_enum, default_value_t = Suffix::PerPath)]
    pub suffix: Suffix,
    /// Suffix paths per camera path with `--suffix per-path` (K ≥ 1): more lower the variance
    /// that the suffixes carry, at a suffix's cost each.
    #[arg(long, default_value_t = DEFAULT_SUFFIX_PATHS, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub suffix_paths: u32,
    /// Which voxels are parameters.
    #[arg(long, value_enum, default_value = "all")]
    pub domain: Domain,
    /// The grid the gradient is with respect to: the density (through extinction), the scene's
    /// emission grid (`medium.emission`) or its albedo grid (`medium.albedo = { grid = … }`; an
    /// RGB grid's gradient is RGB, one pass per channel), written as grad_<its name>.
    #[arg(long, value_enum, default_value_t = Parameter::Extinction)]
    pub parameter: Parameter,
}

impl AdjointArgs {
    /// The gradient pass these flags ask for, with the scene's settings as defaults.
    pub fn options(&self, scene: &Scene, estimator: Estimator) -> Result<GradOptions> {
        let s = &self.sampling;
        Ok(GradOptions {
            adjoint: AdjointOptions {
                estimator,
                suffix: self.suffix,
                suffix_paths: self.suffix_paths,
                max_depth: s.max_depth(scene),
            },
            spp: s.spp(scene)?,
            seed: s.seed(scene),
            active_only: self.domain == Domain::Active,
            progress: !s.quiet,
            parameter: self.parameter,
            channel: None,
            domain: None,
            measured: Measured::Radiance,
            samples: PixelSamples::Uniform,
        })
    }
}

/// Finite-difference options, shared by `grad --estimator fd` and `gradcheck`.
#[derive(Args)]
pub struct FdArgs {
    /// Finite-difference step, in grid-value units (default: per direction, a step that changes the
    /// optical depth along the direction's longest chord by about 0.05).
    #[arg(long)]
    pub eps: Option<f32>,
    /// Samples per pixel of each finite-difference render.
    #[arg(long, default_value_t = FD_SPP)]
    pub fd_spp: u32,
    /// Independent finite-difference repetitions, for the standard error.
    #[arg(long, default_value_t = FD_REPEATS)]
    pub repeats: u32,
}

/// `--fd-spp` and `--repeats` when not given.
pub const FD_SPP: u32 = 256;
pub const FD_REPEATS: u32 = 8;

impl FdArgs {
    /// The options of steps in `perturbed`, the grid whose values they change (the density, or
    /// gradcheck's emission or albedo grid).
    pub fn options(
        &self,
        perturbed: &BrickMap,
        loss: Loss,
        seed: u64,
        max_depth: u32,
    ) -> Result<FdOptions> {
        // Without --eps, callers pick fd::auto_eps per direction; this is the cap it never exceeds.
        let eps = self.eps.unwrap_or(fd::max_eps(perturbed));
        if !(eps > 0.0 && eps.is_finite()) {
            bail!("--eps must be a positive number (got {eps})");
        }
        // A step f32 barely resolves at the grid's values differences rounding, not the image.
        let largest = perturbed.max_value().abs().max(perturbed.min_value().abs());
        let resolved = 1e-5 * largest;
        if eps < resolved {
            bail!("--eps {eps:e} is below what f32 resolves beside the grid's largest value {largest} (at least {resolved:e})");
        }
        // A difference over a step far beyond the values it perturbs measures no derivative, and
        // can push the extinction past what the renderer takes.
        let widest = 10.0 * largest.max(1.0);
        if eps > widest {
            bail!("--eps {eps:e} is beyond ten times the grid's largest value {largest} (at most {widest:e}): a finite difference wants a step small beside the values it changes");
        }
        if self.fd_spp == 0 || self.repeats < 2 {
            bail!("--fd-spp must be at least 1 and --repeats at least 2");
        }
        Ok(FdOptions {
            loss,
            eps,
            spp: self.fd_spp,
            repeats: self.repeats,
            seed,
            max_depth,
        })
    }
}

/// Refuses a job whose ranks were given other work than rank 0 (`Cluster::check_same_inputs`):
/// the fingerprint of this volgrad's version, the command line after the program's name, and
/// `inputs()`, the fingerprints of what the ranks read (computed only when there are ranks).
pub fn check_same_job(cluster: &Cluster, inputs: impl FnOnce() -> Vec<String>) -> Result<()> {
    if cluster.size() == 1 {
        return Ok(());
    }
    let mut f = Fingerprint::default();
    f.text(env!("CARGO_PKG_VERSION"));
    for arg in std::env::args_os().skip(1) {
        f.text(&arg.to_string_lossy());
    }
    for input in inputs() {
        f.text(&input);
    }
    cluster.check_same_inputs(&[("the command line or a file it names".into(), f.value())])
}

/// `--threads T`: a global pool of T workers (default: all cores).
pub fn set_threads(threads: Option<usize>) -> Result<()> {
    if let Some(t) = threads {
        scene_check::thread_count("--threads", t)?;
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build_global()
            .context("cannot start the thread pool")?;
    }
    Ok(())
}

/// Says on stderr (once, from rank 0) that the density grid has no active voxels: the medium is
/// empty and the picture shows the lights alone. Likelier a file whose voxels were left inactive
/// (volgrad renders active voxels and tiles) than a wish.
pub fn warn_if_empty(scene: &Scene, cluster: &Cluster) {
    if cluster.is_root() && scene.medium.grid.active_bounds().is_none() {
        eprintln!(
            "warning: the density grid '{}' has no active voxels: the medium is empty (volgrad reads active voxels and tiles; `volgrad info` lists the grid)",
            scene.grid_name
        );
    }
}

/// Says on stderr how many samples came out non-finite and were dropped (none, for a valid scene).
pub fn report_non_finite(stats: &RenderStats) {
    if stats.non_finite > 0 {
        eprintln!(
            "warning: {} non-finite samples were dropped (counted as 0) out of {} paths",
            stats.non_finite, stats.paths
        );
    }
}

/// The process's peak resident memory (Linux's VmHWM), for `--stats`; `None` where /proc does not
/// say.
pub fn peak_memory() -> Option<usize> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: usize = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// `peak memory` for `--stats`.
pub fn print_peak_memory() {
    if let Some(peak) = peak_memory() {
        println!(
            "peak memory          {} (resident high-water mark)",
            bytes(peak)
        );
    }
}

/// A byte count as people read it.
pub fn bytes(n: usize) -> String {
    if n >= 1 << 20 {
        format!("{:.2} MiB", n as f64 / (1u64 << 20) as f64)
    } else {
        format!("{:.1} KiB", n as f64 / 1024.0)
    }
}
