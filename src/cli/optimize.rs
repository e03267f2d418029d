//! `volgrad optimize`: reconstruct the density grid of a run file from its views, or, with
//! several `--estimators`, the equal-time study of the estimators on that reconstruction. The loop
//! and the study live in the library (`volgrad::optimize`).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::ValueEnum;

use super::{check_same_job, set_threads, values};
use volgrad::cluster::{AgreedError, Cluster};
use volgrad::gradient::adjoint::Estimator;
use volgrad::io::fingerprint::Fingerprint;
use volgrad::optimize::checkpoint;
use volgrad::optimize::problem::Problem;
use volgrad::optimize::reconstruct::{reconstruct, RunOptions};
use volgrad::optimize::schedule::Stop;
use volgrad::optimize::study;
use volgrad::render::interrupt;

#[derive(clap::Args)]
pub struct Args {
    /// The run file (TOML): scene, views, unknown grid, optimiser.
    pub run: PathBuf,
    /// Output folder (default: the run file's name with `.out`, in the current folder; with
    /// --resume, the folder resumed from).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Seconds of optimisation (evaluation excluded), e.g. 90s, 10m. Exclusive with --iterations.
    #[arg(long, value_parser = values::duration, conflicts_with = "iterations")]
    pub budget: Option<Duration>,
    /// Iterations (default: the run file's optimizer.iterations; resuming, the stop rule of the
    /// run resumed). 0 evaluates the start and writes it as final.vdb: with the true grid as the
    /// start, the best score the held-out pictures allow.
    #[arg(long)]
    pub iterations: Option<u64>,
    /// Replay the schedule (levels, learning rate) a run's log.csv records, iteration by
    /// iteration: a --budget run reproduced bit for bit on any machine.
    #[arg(long, value_name = "LOG", conflicts_with_all = ["iterations", "budget"])]
    pub schedule_from: Option<PathBuf>,
    /// The gradient estimator.
    #[arg(long, value_enum, default_value_t = Estimator::Joint, conflicts_with = "estimators")]
    pub estimator: Estimator,
    /// Several estimators, comma-separated: the equal-time study, one run each into OUT/<name>/.
    #[arg(long, value_enum, value_delimiter = ',', num_args = 1..)]
    pub estimators: Option<Vec<Estimator>>,
    /// Random seed (default: the run file's), 0 to 2^63 − 1 (the run file's `seed` is a TOML
    /// integer, and the run writes the seed it used there).
    #[arg(long, value_parser = clap::value_parser!(u64).range(..=i64::MAX as u64))]
    pub seed: Option<u64>,
    /// Worker threads (default: all cores); the result does not depend on it.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Continue from the latest checkpoint in this folder (same run file, estimator and seed).
    #[arg(long, conflicts_with = "estimators")]
    pub resume: Option<PathBuf>,
    /// Keep the targets rendered from the truth in this folder, and read them back in later runs
    /// whose targets would be the same bits (same scene, views, target_spp, target seed and
    /// volgrad executable): runs of one run file then render their targets once.
    #[arg(long, value_name = "DIR")]
    pub target_cache: Option<PathBuf>,
    /// Write into an output folder that is not empty: this run's files replace an earlier run's,
    /// whose checkpoints and held-out pictures are removed first (other files stay).
    #[arg(long)]
    pub force: bool,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
}

/// Set by Ctrl-C (or SIGUSR1, SIGTERM); the loop stops after the current iteration (giving up an
/// evaluation under way) and writes a checkpoint.
static INTERRUPTED: AtomicBool = AtomicBool::new(false);

/// SIGUSR1 and SIGTERM stop the run as Ctrl-C does. Under MPI SIGUSR1 is the signal that
/// reaches the ranks: OpenMPI's mpirun answers SIGINT with SIGTERM and SIGKILL a second later,
/// but forwards SIGUSR1 (and Slurm delivers it with `scancel --signal=USR1`). SIGTERM is what
/// `timeout` and a batch job's time limit send: the run ends with a checkpoint instead of
/// half-written temporary files.
fn stop_on_signals() {
    extern "C" fn on_signal(_: libc::c_int) {
        // Only atomic operations: async-signal-safe. An evaluation under way is given up.
        INTERRUPTED.store(true, Ordering::SeqCst);
        interrupt::stop_stoppable();
    }
    #[cfg(unix)]
    // SAFETY: the handler only loads and stores atomics, which is async-signal-safe.
    unsafe {
        for signal in [libc::SIGUSR1, libc::SIGTERM] {
            libc::signal(signal, on_signal as *const () as libc::sighandler_t);
        }
    }
}

/// The flags' own checks (each rank is given the same flags: `run` agrees on them).
fn check_flags(args: &Args) -> Result<()> {
    if args.budget == Some(Duration::ZERO) {
        bail!("--budget must be above 0");
    }
    if args.iterations == Some(0) && (args.estimators.is_some() || args.resume.is_some()) {
        bail!("--iterations 0 (evaluate the start, write it as final.vdb) is for a fresh single run, not --estimators or --resume");
    }
    if args.estimators.as_ref().is_some_and(Vec::is_empty) {
        bail!("--estimators needs at least one estimator");
    }
    Ok(())
}

pub fn run(args: &Args, cluster: &Cluster) -> Result<()> {
    // Installed first: a cluster run is stopped with SIGUSR1 while it loads too (it stops after
    // its first iteration), where the signal's default action would end every rank unannounced.
    stop_on_signals();
    // Every rank is given the same flags: one error, printed once.
    cluster.agree(set_threads(args.threads).and_then(|_| check_flags(args)))?;
    if cluster.size() > 1 {
        // A run file missing on one machine is named as such, not as a difference.
        let run = cluster.agree(
            (std::fs::read(&args.run))
                .with_context(|| format!("cannot read run file '{}'", args.run.display())),
        )?;
        check_same_job(cluster, || vec![String::from_utf8_lossy(&run).into_owned()])?;
    }
    let resume = cluster.agree(args.resume.as_deref().map(checkpoint::latest).transpose())?;
    let out = match (&args.out, &args.resume) {
        (Some(out), _) => out.clone(),
        (None, Some(dir)) => dir.clone(),
        (None, None) => default_out(&args.run),
    };
    let resuming_in_place = args
        .resume
        .as_ref()
        .is_some_and(|dir| same_folder(dir, &out));
    if !args.force && !resuming_in_place {
        cluster.agree(cluster.on_root(|| refuse_non_empty(&out)))?;
    }
    let stop = match (args.iterations, args.budget, &args.schedule_from) {
        (Some(n), ..) => Some(Stop::Iterations(n)),
        (_, Some(b), _) => Some(Stop::Budget(b)),
        (.., Some(log)) => Some(cluster.agree(Stop::replay_log(log))?),
        (None, None, None) => None,
    };
    if cluster.size() > 1 {
        // Each rank found its own latest checkpoint and read its own replay log: a folder one
        // machine sees older (a network file system's cache, a disk of its own) would start the
        // ranks at different iterations, or stop them at different ones.
        let files: Vec<&Path> = resume
            .iter()
            .map(PathBuf::as_path)
            .chain(args.schedule_from.as_deref())
            .collect();
        let contents = cluster.agree(
            (files.iter())
                .map(|p| std::fs::read(p).with_context(|| format!("cannot read '{}'", p.display())))
                .collect::<Result<Vec<_>>>(),
        )?;
        check_same_job(cluster, || {
            (files.iter().zip(&contents))
                .map(|(p, bytes)| {
                    format!(
                        "{} {}",
                        p.display(),
                        Fingerprint::default().bytes(bytes).hex()
                    )
                })
                .collect()
        })?;
    }
    let progress = !args.quiet && cluster.is_root();
    let problem = cluster.agree(Problem::load(
        &args.run,
        args.seed,
        progress,
        args.target_cache.as_deref(),
        cluster,
    ))?;
    // What the files read were is compared inside `Problem::load`, before any work; the targets
    // (the problem's fingerprint holds them) may also have come from a target cache of each
    // machine's own.
    check_same_job(cluster, || vec![problem.fingerprint.clone()])?;
    if args.force && !resuming_in_place {
        // Only now that the run has loaded: a run file that fails to load leaves the earlier
        // run whole, its checkpoints too. A study's runs write into a folder per estimator.
        cluster.agree(cluster.on_root(|| {
            std::iter::once(out.clone())
                .chain(
                    Estimator::value_variants()
                        .iter()
                        .map(|e| out.join(e.to_string())),
                )
                .try_for_each(|dir| checkpoint::remove_earlier_run(&dir))
        }))?;
    }
    // Said by rank 0 alone: a launcher that hands Ctrl-C to every rank (srun's second one)
    // would otherwise print each line once per rank.
    let root = cluster.is_root();
    cluster.agree(
        ctrlc::set_handler(move || {
            // A second Ctrl-C does not wait for a long iteration to end (files being written
            // are left as they were: each is renamed into place whole).
            if INTERRUPTED.swap(true, Ordering::SeqCst) {
                if root {
                    eprintln!("error: interrupted twice: stopped without a checkpoint");
                }
                // _exit, as main's panic hook ends the process: at once, whatever the workers
                // hold (std::process::exit, which the project denies, would run atexit handlers).
                // SAFETY: _exit takes no locks; nothing runs after it.
                unsafe { libc::_exit(130) }
            }
            // An evaluation under way is given up; a step ends first: say so, or the first
            // Ctrl-C looks ignored on a long step.
            interrupt::stop_stoppable();
            if root {
                eprintln!("\nstopping: the step under way ends, then a checkpoint is written; Ctrl-C again stops at once, without a checkpoint");
            }
        })
        .context("cannot install the Ctrl-C handler"),
    )?;
    let options = RunOptions {
        estimator: args.estimator,
        stop,
        out: out.clone(),
        resume,
        progress,
        interrupt: Some(&INTERRUPTED),
        cluster,
    };
    if let Some(estimators) = &args.estimators {
        let runs = study::equal_time(&problem, estimators, &options)?;
        if !cluster.is_root() {
            return Ok(());
        }
        print!("{}", study::summary(&runs));
        println!(
            "wrote inverse.png/.svg, inverse.csv, renders.png and summary.md in '{}'",
            out.display()
        );
        return Ok(());
    }
    let outcome = reconstruct(&problem, &options)?;
    let p = &outcome.position;
    if outcome.interrupted {
        // Every rank stops at the same iteration (they agree on it): one message, from rank 0.
        // The flags the checkpoint's fingerprint holds, so that the command resumes it.
        let seed = args.seed.map_or(String::new(), |s| format!(" --seed {s}"));
        let estimator = match args.estimator {
            Estimator::Joint => String::new(),
            e => format!(" --estimator {e}"),
        };
        return Err(AgreedError(format!(
            "interrupted at iteration {}: checkpoint written; continue with `volgrad optimize {} --resume {}{seed}{estimator}`",
            p.iteration,
            args.run.display(),
            out.display()
        ))
        .into());
    }
    if !cluster.is_root() {
        return Ok(());
    }
    let e = &outcome.evaluation;
    println!(
        "{} iterations in {:.1} s (+ {:.1} s evaluating): held-out PSNR {:.2} dB (at {:.0} spp, whose noise allows {:.1}){}, relative RMSE {:.4}{}",
        p.iteration,
        p.optimisation_seconds,
        p.evaluation_seconds,
        e.psnr,
        e.spp,
        e.noise_psnr,
        e.relit_psnr
            .map_or(String::new(), |r| format!(" (relit {r:.2} dB)")),
        e.relative_rmse,
        match (e.volume_rmse, e.haze) {
            (Some(rmse), Some(haze)) => format!(", volume RMSE {rmse:.4}, haze {haze:.3}"),
            (Some(rmse), None) => format!(", volume RMSE {rmse:.4}"),
            _ => String::new(),
        }
    );
    println!(
        "active voxels {}, grid + optimiser state {}; wrote '{}'",
        outcome.parameters.active_voxels(),
        super::bytes(outcome.parameters.memory_bytes()),
        out.join("final.vdb").display()
    );
    Ok(())
}

fn default_out(run: &Path) -> PathBuf {
    let stem = run
        .file_stem()
        .map_or("optimize".into(), |s| s.to_string_lossy().into_owned());
    PathBuf::from(format!("{stem}.out"))
}

fn same_folder(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}

/// A run writes many files into its folder: it starts only in an empty or new one (or with
/// --force), so that nothing the user had is overwritten.
fn refuse_non_empty(out: &Path) -> Result<()> {
    let has_files = std::fs::read_dir(out).is_ok_and(|mut d| d.next().is_some());
    if has_files {
        bail!(
            "'{}' is not empty: pass --force to write into it, --resume to continue the run in it, or another --out",
            out.display()
        );
    }
    if out.exists() && !out.is_dir() {
        bail!("'{}' exists and is not a folder", out.display());
    }
    Ok(())
}
