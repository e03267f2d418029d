//! The optimisation loop. Each iteration:
//!
//! 1. moves to the next level when the schedule says so (×2 upsampling, `resample`);
//! 2. builds the medium from θ over the domain's fixed bounds;
//! 3. the images' gradient of a batch of views or pixels (`iteration`: primal renders, adjoint
//!    images δ = ∂loss/∂pixel, the estimator's gradient passes, summed over the MPI ranks); plus
//!    the priors' gradients; the gradient is smoothed, more at the finer levels (`smoothing`: a
//!    preconditioner);
//! 4. one Adam step with θ ≥ 0 kept by projection; bricks that stay at 0 are dropped;
//! 5. from `average_from` on, θ joins the running mean that is the run's result (`average`).
//!
//! One rule sets what changes from level to level: a voxel of the next level is 1/8 of its
//! parent, so the image's derivative with respect to it is about 1/8 of the parent's while its
//! Monte Carlo noise falls only by √8. Hence Adam's moments are scaled by 1/8 and 1/64 at an
//! upsampling (`resample`), the brick scales' moments likewise, the priors are means over the
//! level's voxels (`prior`), and the gradient is smoothed once more per level (`smoothing`). The
//! learning rate's factor per level (`level_lr`) is measured, not derived: Adam normalises the
//! gradient's scale away (docs/reconstruct.md, "One rule per level").
//!
//! Every random number is a function of (seed, iteration, view slot, pixel, sample) and every
//! reduction is exact or runs in a fixed order, so a run's result depends on its settings only, not
//! on the thread or rank count; a run resumed from a checkpoint continues bit for bit. Evaluation
//! and checkpoints are timed apart from the optimisation. Every rank of an MPI job runs this loop;
//! rank 0 writes, and the ranks agree on the clock, an interruption and any write's failure.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::{anyhow, Context, Result};
use glam::IVec3;

use crate::cluster::sparse_sum::Traffic;
use crate::cluster::Cluster;
use crate::gradient::adjoint::Estimator;
use crate::io::fingerprint::Fingerprint;
use crate::io::output::write_bytes_whole;
use crate::io::vdb::meta;
use crate::optimize::adam::Adam;
use crate::optimize::brick_gradient::BrickGradient;
use crate::optimize::checkpoint::{self, Position};
use crate::optimize::evaluate::{evaluate, spp_range, Evaluation};
use crate::optimize::exposure::{factors, Exposure};
use crate::optimize::holdout_picture::write_holdout_picture;
use crate::optimize::iteration::images_gradient;
use crate::optimize::log::{write_progress_chart, LogRow};
use crate::optimize::parameters::Parameters;
use crate::optimize::problem::Problem;
use crate::optimize::resample::upsample;
use crate::optimize::run_file::UnknownGrid;
use crate::optimize::schedule::Stop;
use crate::optimize::settings_toml;
use crate::optimize::smoothing::smooth;
use crate::render::scene::Scene;

pub struct RunOptions<'a> {
    pub estimator: Estimator,
    /// When the run ends; `None`: as the checkpoint resumed from says, else the run file's
    /// `iterations`.
    pub stop: Option<Stop>,
    pub out: PathBuf,
    /// A checkpoint's state file to continue from.
    pub resume: Option<PathBuf>,
    pub progress: bool,
    /// Set (by Ctrl-C) to stop after the current iteration, with a checkpoint.
    pub interrupt: Option<&'a AtomicBool>,
    /// The ranks sharing the run (`Cluster::single()` for one process). Every rank runs the
    /// same loop; rank 0 writes the files and shows the progress bar.
    pub cluster: &'a Cluster,
}

pub struct Outcome {
    pub position: Position,
    pub parameters: Parameters,
    /// The last evaluation (at the end, or at the interruption).
    pub evaluation: Evaluation,
    pub interrupted: bool,
}

/// What a checkpoint of this run must match: the problem and the estimator.
pub fn run_fingerprint(problem: &Problem, estimator: Estimator) -> String {
    let mut f = Fingerprint::default();
    f.text(&problem.fingerprint).text(&estimator.to_string());
    f.hex()
}

/// The costs of an iteration are said once this process has made this many iterations, or spent
/// this many seconds on them, whichever comes first (or at the end of a shorter run).
const COSTS_AFTER_ITERATIONS: u64 = 10;
const COSTS_AFTER_SECONDS: f64 = 2.0;

/// Runs the optimisation, writing `settings.toml`, checkpoints, `log.csv`, `progress.png/.svg`,
/// held-out pictures and `final.vdb` into `options.out`.
pub fn reconstruct(problem: &Problem, options: &RunOptions) -> Result<Outcome> {
    let mut run = Run::start(problem, options)?;
    let (first, seconds) = (run.position.iteration, run.position.optimisation_seconds);
    let mut costs_said = false;
    while run.fraction() < 1.0 {
        run.iterate()?;
        // The first iterations are the cheapest (the start is thin; paths grow longer as the
        // density does), so the costs are said from the mean of the first few.
        let (done, spent) = (
            run.position.iteration - first,
            run.position.optimisation_seconds - seconds,
        );
        let soon = done >= COSTS_AFTER_ITERATIONS || spent >= COSTS_AFTER_SECONDS;
        if !costs_said && (soon || run.fraction() >= 1.0) {
            run.say_costs(spent / done as f64, done);
            costs_said = true;
        }
        if run.interrupted {
            break;
        }
    }
    run.finish()
}

/// A run under way: where it is, θ with Adam's state, and the log so far.
struct Run<'a> {
    problem: &'a Problem,
    options: &'a RunOptions<'a>,
    fingerprint: String,
    stop: Stop,
    position: Position,
    parameters: Parameters,
    log: Vec<LogRow>,
    evaluation: Evaluation,
    bar: indicatif::ProgressBar,
    interrupted: bool,
}

impl<'a> Run<'a> {
    /// A fresh run at the start (evaluated, so that charts show what the optimisation gained), or
    /// the checkpoint `options.resume` names.
    fn start(problem: &'a Problem, options: &'a RunOptions<'a>) -> Result<Self> {
        let cluster = options.cluster;
        let fingerprint = run_fingerprint(problem, options.estimator);
        let resumed = match &options.resume {
            Some(state) => checkpoint::read_state(state, &fingerprint),
            None => Ok((Position::default(), problem.start.clone())),
        };
        let (mut position, parameters) = cluster.agree(resumed)?;
        let stop = options
            .stop
            .clone()
            .or_else(|| position.stop.clone())
            .unwrap_or(Stop::Iterations(problem.settings.iterations.into()));
        position.stop = Some(stop.clone());
        if let (Some(state), Some(stop)) = (&options.resume, &options.stop) {
            cluster.agree(stop.not_past(position.iteration).with_context(|| {
                format!(
                    "'{}' is at iteration {}",
                    state.display(),
                    position.iteration
                )
            }))?;
        }
        cluster.agree(cluster.on_root(|| {
            std::fs::create_dir_all(&options.out).with_context(|| {
                format!(
                    "cannot create the output directory '{}'",
                    options.out.display()
                )
            })?;
            let settings =
                settings_toml::with_command(&problem.settings_toml, options.estimator, &stop);
            write_bytes_whole(&options.out.join("settings.toml"), settings)
        }))?;
        let mut run = Run {
            problem,
            options,
            fingerprint,
            // What every rank meets alike is agreed, so that it is printed once.
            log: cluster.agree(LogRow::parse_all(&position.log))?,
            bar: progress_bar(options.progress && cluster.is_root(), &stop),
            stop,
            position,
            parameters,
            evaluation: Evaluation::default(),
            interrupted: false,
        };
        if run.position.iteration == 0 {
            let started = Instant::now();
            let evaluation = run.evaluate();
            run.position.evaluation_seconds += started.elapsed().as_secs_f64();
            let mut row = run.row(f64::NAN, 0.0);
            // Cut short, it stops the run after its first iteration (Ctrl-C's flag is set).
            if let Some(evaluation) = evaluation {
                row.record(&evaluation);
                run.evaluation = evaluation;
            }
            run.log = vec![row];
        } else if run.fraction() >= 1.0 {
            // A finished run resumed has nothing to iterate, but its final.vdb and summary carry
            // an evaluation's held-out PSNR, as those of a run that ends here do.
            let evaluation = run.evaluate();
            run.interrupted = evaluation.is_none();
            run.evaluation = evaluation.unwrap_or_default();
        }
        Ok(run)
    }

    fn fraction(&self) -> f64 {
        let p = &self.position;
        self.stop.fraction(p.iteration, p.optimisation_seconds)
    }

    fn evaluate(&self) -> Option<Evaluation> {
        let level = self.position.level as usize;
        let scene = self.problem.scene_at(self.parameters.result(), level);
        let exposures = self.exposures();
        evaluate(
            self.problem,
            &scene,
            level,
            &exposures,
            self.options.cluster,
        )
    }

    /// Each capture's exposure factor (`Problem::captures`).
    fn exposures(&self) -> Vec<f32> {
        factors(&self.parameters.exposures, self.problem.captures.len())
    }

    /// This iteration's row of the log, before any evaluation.
    fn row(&self, loss: f64, fraction: f32) -> LogRow {
        LogRow {
            iteration: self.position.iteration,
            level: self.position.level,
            fraction,
            seconds: self.position.optimisation_seconds,
            evaluation_seconds: self.position.evaluation_seconds,
            loss,
            active_voxels: self.parameters.active_voxels(),
            state_bytes: self.parameters.memory_bytes() as u64,
            exposure: self.exposures(),
            ..Default::default()
        }
    }

    /// One iteration: the level the schedule asks for, a step, its row of the log, and an
    /// evaluation and a checkpoint when they are due.
    fn iterate(&mut self) -> Result<()> {
        let (problem, s) = (self.problem, &self.problem.settings);
        let fraction = self.fraction() as f32;
        let started = Instant::now();
        self.advance_levels(fraction)?;
        let level = self.position.level as usize;
        // lr · decay^fraction, and × level_lr per upsampling done.
        let adam = Adam {
            lr: s.adam.lr * s.lr_decay.powf(fraction) * s.level_lr.powi(level as i32),
            ..s.adam
        };
        let mut scene = problem.scene_at(self.parameters.to_brickmap(), level);
        let iteration = self.position.iteration;
        let estimator = self.options.estimator;
        let cluster = self.options.cluster;
        let (loss, traffic) = step(
            problem,
            cluster,
            &mut scene,
            &mut self.parameters,
            estimator,
            iteration,
            level,
            &adam,
        )?;
        // Every rank has the same loss: one message, and no rank left in a collective.
        cluster.agree(match loss.is_finite() {
            true => Ok(()),
            false => Err(anyhow!(
                "iteration {iteration}: the training loss is {loss}: a prior's weight or a target too large for the sums"
            )),
        })?;
        if fraction >= s.average_from {
            self.parameters.add_to_average();
        }
        self.position.iteration += 1;
        // The ranks agree on the time (the budget's fraction) and on an interruption: mpirun
        // forwards Ctrl-C to every rank, but they may see it in different iterations.
        let interrupted = (self.options.interrupt).is_some_and(|flag| flag.load(Ordering::SeqCst));
        let agreed = cluster.max_each([
            started.elapsed().as_secs_f64(),
            f64::from(u8::from(interrupted)),
        ]);
        self.position.optimisation_seconds += agreed[0];
        self.interrupted = agreed[1] > 0.0;
        let done = self.interrupted || self.fraction() >= 1.0;
        let mut row = self.row(loss, fraction);
        row.reduce_bytes = traffic.bytes_sent;
        row.reduce_seconds = traffic.seconds;
        let it = self.position.iteration;
        // A checkpoint comes with an evaluation, an interrupted run's not: one can take minutes,
        // and mpirun kills the ranks a second after it hands them Ctrl-C. One cut short by
        // Ctrl-C (every rank agrees) is given up, and the run stops with a checkpoint.
        let mut checkpoint_now = it.is_multiple_of(u64::from(s.checkpoint_every)) || done;
        if checkpoint_now || it.is_multiple_of(u64::from(s.eval_every)) {
            let started = Instant::now();
            let evaluation = (!self.interrupted).then(|| self.evaluate()).flatten();
            self.interrupted = evaluation.is_none();
            checkpoint_now |= self.interrupted;
            self.evaluation = evaluation.unwrap_or_default();
            if !self.interrupted {
                row.record(&self.evaluation);
            }
            // Counted before the checkpoint saves the log, so that a run resumed from it counts
            // this evaluation too; the checkpoint's own writing is added after.
            self.position.evaluation_seconds += started.elapsed().as_secs_f64();
            row.evaluation_seconds = self.position.evaluation_seconds;
            if checkpoint_now {
                let writing = Instant::now();
                cluster.agree(cluster.on_root(|| self.write_checkpoint(&row)))?;
                self.position.evaluation_seconds += writing.elapsed().as_secs_f64();
                row.evaluation_seconds = self.position.evaluation_seconds;
            }
        }
        let evaluated = row.psnr.is_some();
        self.log.push(row);
        let message = format!(
            "it {it} · level {level} · loss {loss:.3e} · held-out PSNR {:.2} dB ({:.0} spp, noise allows {:.1})",
            self.evaluation.psnr, self.evaluation.spp, self.evaluation.noise_psnr
        );
        if evaluated && self.bar.is_hidden() {
            self.say(&message);
        }
        self.bar.set_message(message);
        let p = &self.position;
        self.bar
            .set_position(self.stop.bar_position(p.iteration, p.optimisation_seconds));
        if evaluated {
            let log = self.options.out.join("log.csv");
            cluster.agree(cluster.on_root(|| write_bytes_whole(&log, LogRow::csv(&self.log))))?;
        }
        Ok(())
    }

    /// Upsamples ×2 for every level whose start the run's `fraction` has reached.
    fn advance_levels(&mut self, fraction: f32) -> Result<()> {
        let (domain, s) = (&self.problem.domain, &self.problem.settings);
        let mut level = self.position.level as usize;
        // Only what the next level's lookups can read is kept. An emission unknown's field ends
        // at its box; the density's reaches half a voxel past it (the medium's bounds), where
        // lookups read one voxel beyond. Kept further out, the coarse level's own apron (a
        // coarse voxel past the box) would stay in the result at every finer level, never read
        // and never fitted: six levels left density 24 final voxels outside a 24³ box.
        let apron = match self.problem.unknown {
            UnknownGrid::Emission => IVec3::ZERO,
            UnknownGrid::Density => IVec3::ONE,
        };
        while level < domain.levels && fraction >= s.level_starts[level] {
            let (lo, hi) = domain.voxel_box(level + 1);
            let keep = Some((lo - apron, hi + apron));
            let transform = domain.transform(level);
            let upsampled = upsample(&self.parameters, &transform, s.moments, keep);
            self.parameters = self.options.cluster.agree(upsampled)?.0;
            level += 1;
        }
        self.position.level = level as u32;
        Ok(())
    }

    /// The checkpoint's VDB, its state (the log up to `row`, included, so that a resumed run's
    /// log.csv is the uninterrupted run's), the held-out picture and the progress chart.
    fn write_checkpoint(&self, row: &LogRow) -> Result<()> {
        let (problem, out) = (self.problem, &self.options.out);
        let (vdb_path, state_path) = checkpoint::paths(out, self.position.iteration);
        self.write_grid(&vdb_path)?;
        let mut with_row = self.log.clone();
        with_row.push(row.clone());
        let state = Position {
            log: LogRow::csv_rows(&with_row),
            ..self.position.clone()
        };
        checkpoint::write_state(&state_path, &self.fingerprint, &state, &self.parameters)?;
        if !self.evaluation.renders.is_empty() {
            write_holdout_picture(
                &out.join(format!("holdout-{:04}.png", self.position.iteration)),
                &problem.holdouts,
                &self.evaluation.renders,
                &self.exposures(),
                problem.scene.settings.exposure,
            )?;
        }
        write_progress_chart(out, &with_row)
    }

    /// The result (`Parameters::result`) as a VDB at the current level's transform, with the
    /// run's metadata.
    fn write_grid(&self, path: &Path) -> Result<()> {
        let level = self.position.level as usize;
        checkpoint::write_grid(
            path,
            &self.parameters,
            self.problem.domain.transform(level),
            &self.problem.grid_name,
            self.metadata(),
        )
    }

    fn metadata(&self) -> Vec<crate::io::bridge::MetaEntry> {
        let (s, position) = (&self.problem.settings, &self.position);
        let mut m = vec![
            meta("volgrad_iterations", "int64", position.iteration),
            meta("volgrad_seconds", "double", position.optimisation_seconds),
            meta("volgrad_estimator", "string", self.options.estimator),
            meta("volgrad_loss", "string", s.loss),
            meta("volgrad_spp", "int64", s.spp),
            meta("volgrad_primal_spp", "int64", s.primal_spp),
            meta("volgrad_seed", "int64", s.seed),
            meta("volgrad_level", "int64", position.level),
            meta(
                "volgrad_averaged_steps",
                "int64",
                self.parameters.average.steps(),
            ),
        ];
        if !self.problem.holdouts.is_empty() && !self.evaluation.renders.is_empty() {
            m.push(meta("volgrad_heldout_psnr", "double", self.evaluation.psnr));
        }
        if s.fit_exposure {
            // One factor per capture, named as the run file names it (the unnamed one plainly).
            for (name, exposure) in self.problem.captures.iter().zip(self.exposures()) {
                let key = match name.as_str() {
                    "" => "volgrad_exposure".to_string(),
                    name => format!("volgrad_exposure_{name}"),
                };
                m.push(meta(&key, "double", exposure));
            }
        }
        m
    }

    /// What one iteration (`seconds`, the mean of this process's first `iterations`) and one
    /// evaluation cost, and what the stop rule then amounts to, on stderr: a run whose views are
    /// far larger than the defaults assume says so in its first seconds, not after its budget.
    fn say_costs(&self, seconds: f64, iterations: u64) {
        // Every evaluation so far (a resumed run's too) and the spp each took: an
        // evaluation's time is about proportional to its spp, which tells what "auto" may
        // come to.
        let spps: Vec<f64> = self.log.iter().filter_map(|r| r.heldout_spp).collect();
        let evaluation_seconds = self.position.evaluation_seconds;
        let evaluation = evaluation_seconds / spps.len().max(1) as f64;
        let spp = match spp_range(self.problem) {
            (first, max) if first < max => format!(
                "{:.0} spp; \"auto\" takes up to {max}, about {:.0} s, as the error falls",
                spps.last().copied().unwrap_or(0.0),
                evaluation_seconds * f64::from(max) / spps.iter().sum::<f64>().max(1.0)
            ),
            (spp, _) => format!("{spp} spp"),
        };
        let total = match &self.stop {
            Stop::Budget(budget) => format!(
                ": about {:.0} iterations in the budget",
                budget.as_secs_f64() / seconds.max(1e-9)
            ),
            Stop::Iterations(n) => format!(
                ": about {:.0} s for the {n} iterations",
                seconds * *n as f64
            ),
            Stop::Replay(_) => String::new(),
        };
        self.say(&format!(
            "{} and one evaluation {evaluation:.2} s ({spp}; every {} iterations){total}",
            match iterations {
                1 => format!("the first iteration took {seconds:.2} s"),
                n => format!("the first {n} iterations took {seconds:.2} s each"),
            },
            self.problem.settings.eval_every
        ));
    }

    /// A line for the user on stderr: above the progress bar on a terminal, and as a plain line
    /// where stderr is a file (a batch job's log), where no bar is drawn; nothing with `-q` or
    /// on ranks other than 0.
    fn say(&self, line: &str) {
        match (
            self.options.progress && self.options.cluster.is_root(),
            self.bar.is_hidden(),
        ) {
            (false, _) => {}
            (true, false) => self.bar.println(line),
            (true, true) => eprintln!("{line}"),
        }
    }

    /// `final.vdb` and the progress chart, unless the run was interrupted.
    fn finish(mut self) -> Result<Outcome> {
        self.bar.finish_and_clear();
        // Kept as text only here and in checkpoints: rebuilding it every iteration would cost
        // time quadratic in the run's length.
        self.position.log = LogRow::csv_rows(&self.log);
        if !self.interrupted {
            let out = &self.options.out;
            self.options
                .cluster
                .agree(self.options.cluster.on_root(|| {
                    self.write_grid(&out.join("final.vdb"))?;
                    // Also written at every evaluation; here for a run of 0 iterations too.
                    write_bytes_whole(&out.join("log.csv"), LogRow::csv(&self.log))?;
                    write_progress_chart(out, &self.log)
                }))?;
        }
        Ok(Outcome {
            position: self.position,
            parameters: self.parameters,
            evaluation: self.evaluation,
            interrupted: self.interrupted,
        })
    }
}

/// One iteration's gradient (`iteration`) and Adam step; returns the training loss (batch mean,
/// prior included) and what the gradient's sum over the ranks moved.
#[allow(clippy::too_many_arguments)]
fn step(
    problem: &Problem,
    cluster: &Cluster,
    scene: &mut Scene,
    parameters: &mut Parameters,
    estimator: Estimator,
    iteration: u64,
    level: usize,
    adam: &Adam,
) -> Result<(f64, Traffic)> {
    let s = &problem.settings;
    let exposures = factors(&parameters.exposures, problem.captures.len());
    let (lo, hi) = problem.domain.voxel_box(level);
    let images = images_gradient(
        problem,
        cluster,
        scene,
        estimator,
        iteration,
        &exposures,
        (lo, hi),
    )?;
    let passes = s
        .first_level_smoothing
        .map_or(0, |first| first + level as u32);
    let gradient = smooth(BrickGradient::from_voxels(images.voxels), passes, lo, hi);
    let level_voxels = problem.domain.voxel_count_at(level);
    let loss = images.loss + parameters.descend(adam, &gradient, &s.priors, level_voxels);
    if s.fit_exposure {
        let steps = parameters.steps();
        let gradients = &images.exposure_gradients;
        parameters
            .exposures
            .resize(gradients.len(), Exposure::default());
        for (exposure, &g) in parameters.exposures.iter_mut().zip(gradients) {
            exposure.step(adam, steps, g);
        }
    }
    Ok((loss, images.traffic))
}

fn progress_bar(progress: bool, stop: &Stop) -> indicatif::ProgressBar {
    let bar = crate::io::progress::bar(progress, stop.bar_total(), "optimize");
    if progress {
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "[{bar:30}] {percent:>3}% {msg} · {elapsed_precise} (eta {eta})",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_message("starting");
    }
    bar
}
