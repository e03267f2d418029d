//! The `volgrad` command line: the subcommands and their dispatch. Each subcommand's flags and
//! its `run()` live in `cli/<command>.rs`; what a library user would want lives in the library.

// Bad input gets an error, never a panic: outside tests an unwrap must say why it cannot fail
// (`expect`). Tests (here and in tests/) may unwrap.
#![cfg_attr(not(test), deny(clippy::unwrap_used))]

mod cli;

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use volgrad::cluster::{AgreedError, Cluster};

#[derive(Parser)]
#[command(
    name = "volgrad",
    version,
    about = "Differentiable volumetric path tracing of OpenVDB density grids"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// List every grid in a .vdb file: type, class, transform, voxel counts, bounds, metadata.
    Info(cli::info::Args),
    /// Render a scene to a linear EXR and a tonemapped PNG beside it.
    Render(cli::render::Args),
    /// Write a small analytic grid (box, sphere, slab, single dense voxel) as a .vdb file.
    MakeGrid(cli::make_grid::Args),
    /// Gradient of a loss with respect to every voxel, written as a VDB (plus pictures).
    Grad(cli::grad::Args),
    /// Compare an estimator with finite differences (z-scores) before trusting its gradients.
    Gradcheck(cli::gradcheck::Args),
    /// Speed against accuracy: estimators (and the renderer) at equal time against a reference,
    /// as charts, a CSV and tables; or the stability suite (--suite stability).
    Compare(cli::compare::Args),
    /// Combine gradient VDBs from runs with different seeds, weighted by their spp.
    Merge(cli::merge::Args),
    /// Reconstruct a density grid from images (inverse rendering), or compare estimators on it
    /// at equal time (--estimators).
    Optimize(cli::optimize::Args),
}

fn main() -> ExitCode {
    restore_sigpipe();
    let command = Cli::parse().command;
    // Under mpirun or srun, every rank runs this; `render`, `grad` and `optimize` share the work.
    let (cluster, _session) = match Cluster::from_launcher() {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e:#}");
            return ExitCode::FAILURE;
        }
    };
    let result = match command {
        Command::Info(args) => cli::info::run(&args),
        Command::Render(args) => cli::render::run(&args, &cluster),
        Command::MakeGrid(args) => cli::make_grid::run(&args),
        Command::Grad(args) => cli::grad::run(&args, &cluster),
        Command::Gradcheck(args) => cli::gradcheck::run(&args),
        Command::Compare(args) => cli::compare::run(&args),
        Command::Merge(args) => cli::merge::run(&args),
        Command::Optimize(args) => cli::optimize::run(&args, &cluster),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if cluster.size() > 1 && e.downcast_ref::<AgreedError>().is_none() => {
            // Only this rank met it: the others may wait for it in a collective.
            eprintln!("error (rank {}): {e:#}", cluster.rank());
            cluster.abort();
            ExitCode::FAILURE
        }
        Err(e) => {
            if cluster.is_root() {
                eprintln!("error: {e:#}");
            }
            ExitCode::FAILURE
        }
    }
}

/// `volgrad info big.vdb | head` closes the pipe early. Rust ignores SIGPIPE, so the next
/// `println!` would panic; with the default action the process ends quietly, as `cat` would.
fn restore_sigpipe() {
    #[cfg(unix)]
    // SAFETY: called first thing in main, before any thread exists; SIG_DFL is a valid action.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
