//! The `volgrad` command line: the subcommands and their dispatch. Each subcommand's flags and
//! its `run()` live in `cli/<command>.rs`; what a library user would want lives in the library.

// Bad input gets an error, never a panic: outside tests an unwrap must say why it cannot fail
// (`expect`). Tests (here and in tests/) may unwrap.
#![cfg_attr(not(test), deny(clippy::unwrap_used))]

mod cli;

use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};

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
    /// List every grid in a .vdb file (type, class, transform, voxel counts, bounds, metadata), or
    /// a scene file's grids and medium.
    Info(cli::info::Args),
    /// Render a scene to a linear EXR and a tonemapped PNG beside it.
    Render(cli::render::Args),
    /// Write a small analytic grid (box, sphere, slab, single dense voxel, fireball, coloured
    /// smoke) as a .vdb file.
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
    /// Reconstruct a density or emission grid from images (inverse rendering), or compare
    /// estimators on it at equal time (--estimators).
    Optimize(cli::optimize::Args),
}

fn main() -> ExitCode {
    restore_sigpipe();
    let command = match Cli::try_parse() {
        Ok(cli) => cli.command,
        Err(e) => {
            // Under mpirun every rank reads the same command line (or is asked for --help):
            // one says so.
            if volgrad::cluster::launcher_rank() == 0 {
                // Printing fails only with stderr gone, when there is no one to tell.
                let _ = e.print();
            }
            return ExitCode::from(u8::try_from(e.exit_code()).unwrap_or(2));
        }
    };
    // Under mpirun or srun, every rank runs this; `render`, `grad` and `optimize` share the work.
    let (cluster, _session) = match Cluster::from_launcher() {
        Ok(c) => c,
        Err(e) => {
            // Every process the launcher started meets it (each sees itself alone): one says so.
            if volgrad::cluster::launcher_rank() == 0 {
                eprintln!("error: {e:#}");
            }
            return ExitCode::FAILURE;
        }
    };
    // After the launcher: under mpirun its hook (MPI_Abort, ending every rank) runs inside ours.
    end_on_panic();
    let across_ranks = matches!(
        command,
        Command::Render(_) | Command::Grad(_) | Command::Optimize(_)
    );
    if cluster.size() > 1 && !across_ranks {
        // Every rank would do the same work on the same files and print the same errors.
        if cluster.is_root() {
            eprintln!("error: only render, grad and optimize run across MPI ranks; run this command as one process (without mpirun or srun)");
        }
        return ExitCode::FAILURE;
    }
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

/// Ends the whole process at the first panic, on any thread, with status 101 (Rust's for a
/// panic): the hook installed before (the default report, and under mpirun `Cluster`'s
/// MPI_Abort) runs once, and any other thread that panics meanwhile waits for the end instead of
/// printing. Without it a panic on a rayon worker unwinds while the other workers go on, each
/// panicking and printing its own report: with RUST_BACKTRACE=1 set, that went on for minutes.
fn end_on_panic() {
    let report = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        static REPORTED: AtomicBool = AtomicBool::new(false);
        if REPORTED.swap(true, Ordering::SeqCst) {
            // Another thread is reporting the first panic, and then ends the process.
            loop {
                std::thread::park();
            }
        }
        report(info);
        // _exit, not std::process::exit (which the project denies: errors end through main):
        // exit would run atexit handlers and flush streams other threads may hold locked, and
        // this must end at once, whatever those threads are doing.
        // SAFETY: _exit is async-signal-safe and takes no locks; nothing runs after it.
        unsafe { libc::_exit(101) }
    }));
}

#[cfg(test)]
mod tests {
    use std::process::Command;
    use std::time::{Duration, Instant};

    /// A panic on every rayon worker with RUST_BACKTRACE=1 set (once, rayon's workers printed
    /// backtraces for minutes): the process reports the first panic once and ends at once, with
    /// status 101. The test runs itself as a child process, which installs the hook and panics.
    #[test]
    fn a_panic_on_a_worker_ends_the_process_once() {
        const CHILD: &str = "VOLGRAD_TEST_PANIC_CHILD";
        if std::env::var_os(CHILD).is_some() {
            use rayon::prelude::*;
            super::end_on_panic();
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(4)
                .build()
                .unwrap();
            pool.install(|| {
                (0..10_000).into_par_iter().for_each(|i| {
                    std::thread::sleep(Duration::from_millis(1));
                    panic!("worker {i} fails");
                })
            });
            return;
        }
        let started = Instant::now();
        let name = "tests::a_panic_on_a_worker_ends_the_process_once";
        let out = Command::new(std::env::current_exe().unwrap())
            .args(["--exact", name, "--nocapture", "--test-threads", "1"])
            .env(CHILD, "1")
            .env("RUST_BACKTRACE", "1")
            .output()
            .unwrap();
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        assert_eq!(out.status.code(), Some(101), "{stdout}\n{stderr}");
        assert_eq!(stderr.matches("panicked at").count(), 1, "{stderr}");
        assert!(stderr.contains("fails"), "{stderr}");
        // Ended by the hook, not by the test harness catching the panic.
        assert!(!stdout.contains("test result"), "{stdout}");
        assert!(started.elapsed() < Duration::from_secs(60));
    }
}
