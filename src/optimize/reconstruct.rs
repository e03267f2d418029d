//! The optimisation loop. Each iteration:
//!
//! 1. moves to the next level when the schedule says so (×2 upsampling, `resample`);
//! 2. builds the medium from θ over the domain's fixed bounds;
//! 3. for each view of a batch (reshuffled each epoch): a primal render (`primal_spp`) and the
//!    adjoint image δ = ∂loss/∂pixel, then the estimator's gradient pass (`spp`; independent
//!    random streams), averaged over the batch; plus the priors' gradients; at the finer levels
//!    the gradient is smoothed (`smoothing`: a preconditioner);
//! 4. one Adam step with θ ≥ 0 kept by projection; bricks that stay at 0 are dropped.
//!
//! Every random number is a function of (seed, iteration, view slot, pixel, sample) and every
//! reduction runs in a fixed order, so a run's result depends on its settings only, not on the
//! thread count; a run resumed from a checkpoint continues bit for bit. Evaluation and checkpoints
//! are timed apart from the optimisation.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use rand::seq::SliceRandom;
use rand::RngCore;

use crate::gradient::adjoint::Estimator;
use crate::gradient::grid::GradientGrid;
use crate::gradient::objective::adjoint_image;
use crate::gradient::passes::{gradient, GradOptions};
use crate::io::chart::{self, Chart, Scale, Series};
use crate::io::fingerprint::Fingerprint;
use crate::io::vdb::meta;
use crate::optimize::checkpoint::{self, Position};
use crate::optimize::evaluate::{evaluate, write_holdout_picture, Evaluation};
use crate::optimize::log::LogRow;
use crate::optimize::parameters::{Adam, Parameters};
use crate::optimize::problem::Problem;
use crate::optimize::resample::upsample;
use crate::optimize::smoothing::smooth;
use crate::render::sampling::pixel_rng;
use crate::render::scene::Scene;

/// When a run ends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Stop {
    Iterations(u64),
    /// Seconds of optimisation (evaluation excluded).
    Budget(Duration),
}

impl Stop {
    /// How far the run is, in [0, 1]: what the level schedule and the learning-rate decay follow.
    fn fraction(&self, position: &Position) -> f64 {
        match *self {
            Stop::Iterations(n) => position.iteration as f64 / n.max(1) as f64,
            Stop::Budget(b) => position.optimisation_seconds / b.as_secs_f64().max(1e-9),
        }
    }
}

pub struct RunOptions<'a> {
    pub estimator: Estimator,
    pub stop: Stop,
    pub out: PathBuf,
    /// A checkpoint's state file to continue from.
    pub resume: Option<PathBuf>,
    pub progress: bool,
    /// Set (by Ctrl-C) to stop after the current iteration, with a checkpoint.
    pub interrupt: Option<&'a AtomicBool>,
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

/// Runs the optimisation, writing checkpoints, `log.csv`, `progress.png/.svg`, held-out pictures
/// and `final.vdb` into `options.out`.
pub fn reconstruct(problem: &Problem, options: &RunOptions) -> Result<Outcome> {
    let s = &problem.settings;
    let fingerprint = run_fingerprint(problem, options.estimator);
    let (mut position, mut parameters) = match &options.resume {
        Some(state) => checkpoint::read_state(state, &fingerprint)?,
        None => (Position::default(), problem.start.clone()),
    };
    let mut log = LogRow::parse_all(&position.log)?;
    std::fs::create_dir_all(&options.out).with_context(|| {
        format!(
            "cannot create the output directory '{}'",
            options.out.display()
        )
    })?;
    let bar = progress_bar(options);
    let mut evaluation = Evaluation::default();
    if position.iteration == 0 {
        // The start, so that charts and summaries show what the optimisation gained.
        let started = Instant::now();
        let level = position.level as usize;
        evaluation = evaluate(
            problem,
            &problem.scene_at(parameters.to_brickmap(), level),
            level,
        );
        position.evaluation_seconds += started.elapsed().as_secs_f64();
        let mut row = LogRow {
            evaluation_seconds: position.evaluation_seconds,
            loss: f64::NAN,
            active_voxels: parameters.active_voxels(),
            state_bytes: parameters.memory_bytes() as u64,
            ..Default::default()
        };
        row.record(&evaluation);
        log = vec![row];
    }
    let mut interrupted = false;
    while options.stop.fraction(&position) < 1.0 {
        let fraction = options.stop.fraction(&position) as f32;
        let started = Instant::now();
        let mut level = position.level as usize;
        while level < problem.domain.levels && fraction >= s.level_starts[level] {
            parameters = upsample(&parameters, &problem.domain.transform(level), s.moments)?.0;
            level += 1;
        }
        position.level = level as u32;
        // lr · decay^fraction, and × level_lr per upsampling done.
        let adam = Adam {
            lr: s.adam.lr * s.lr_decay.powf(fraction) * s.level_lr.powi(level as i32),
            ..s.adam
        };
        let mut scene = problem.scene_at(parameters.to_brickmap(), level);
        let loss = step(
            problem,
            &mut scene,
            &mut parameters,
            options.estimator,
            position.iteration,
            level,
            &adam,
        )?;
        position.iteration += 1;
        position.optimisation_seconds += started.elapsed().as_secs_f64();
        interrupted = options
            .interrupt
            .is_some_and(|flag| flag.load(Ordering::SeqCst));
        let done = interrupted || options.stop.fraction(&position) >= 1.0;
        let mut row = LogRow {
            iteration: position.iteration,
            level: position.level,
            seconds: position.optimisation_seconds,
            evaluation_seconds: position.evaluation_seconds,
            loss,
            active_voxels: parameters.active_voxels(),
            state_bytes: parameters.memory_bytes() as u64,
            ..Default::default()
        };
        let it = position.iteration;
        // A checkpoint comes with an evaluation: its VDB carries the held-out PSNR and its
        // picture shows the held-out renders.
        let checkpoint_now = it % u64::from(s.checkpoint_every) == 0 || done;
        if checkpoint_now || it % u64::from(s.eval_every) == 0 {
            let started = Instant::now();
            let scene = problem.scene_at(parameters.to_brickmap(), level);
            evaluation = evaluate(problem, &scene, level);
            row.record(&evaluation);
            if checkpoint_now {
                let saved = Saved {
                    position: &position,
                    parameters: &parameters,
                    evaluation: &evaluation,
                    log: &log,
                    row: &row,
                };
                write_checkpoint(problem, options, &saved, &fingerprint)?;
            }
            position.evaluation_seconds += started.elapsed().as_secs_f64();
            row.evaluation_seconds = position.evaluation_seconds;
        }
        let evaluated = row.psnr.is_some();
        log.push(row);
        bar.set_message(format!(
            "it {it} · level {level} · loss {loss:.3e} · held-out PSNR {:.2} dB",
            evaluation.psnr
        ));
        bar.set_position(bar_position(options.stop, &position));
        if evaluated {
            write_log(&options.out, &log)?;
        }
        if interrupted {
            break;
        }
    }
    bar.finish_and_clear();
    // Kept as text only here and in checkpoints: rebuilding it every iteration would cost time
    // quadratic in the run's length.
    position.log = LogRow::csv_rows(&log);
    if !interrupted {
        let level = position.level as usize;
        checkpoint::write_grid(
            &options.out.join("final.vdb"),
            &parameters,
            problem.domain.transform(level),
            &problem.grid_name,
            metadata(problem, options, &position, &evaluation),
        )?;
        write_progress_chart(&options.out, &log)?;
    }
    Ok(Outcome {
        position,
        parameters,
        evaluation,
        interrupted,
    })
}

/// One iteration's gradient and Adam step; returns the training loss (batch mean, prior
/// included).
fn step(
    problem: &Problem,
    scene: &mut Scene,
    parameters: &mut Parameters,
    estimator: Estimator,
    iteration: u64,
    level: usize,
    adam: &Adam,
) -> Result<f64> {
    let s = &problem.settings;
    let mut total = GradientGrid::<f64>::for_medium(&scene.medium);
    let mut loss = 0.0;
    let views = batch(problem.views.len(), s.batch, s.seed, iteration);
    let weight = 1.0 / views.len() as f64;
    for (slot, &v) in views.iter().enumerate() {
        let view = &problem.views[v];
        scene.camera = view.camera;
        let seed = pixel_rng(s.seed, iteration, slot as u64).next_u64();
        let options = GradOptions::new(estimator, s.spp, seed, s.max_depth);
        let primal = GradOptions {
            spp: s.primal_spp,
            ..options
        };
        let adjoint = adjoint_image(scene, s.loss, Some(&view.target), &primal)?;
        loss += weight * adjoint.loss.unwrap_or(0.0);
        let run = gradient(scene, &adjoint.delta, &options);
        total.merge(&run.gradient, weight);
    }
    let passes = if s.smooth_gradient { level as u32 } else { 0 };
    let (lo, hi) = problem.domain.voxel_box(level);
    let mut gradient = smooth(total.voxels(), passes, lo, hi);
    for prior in &s.priors {
        let (value, prior_gradient) = prior.evaluate(parameters);
        loss += value;
        gradient.extend(prior_gradient);
    }
    parameters.adam_step(adam, gradient);
    Ok(loss)
}

/// The views of iteration `iteration`: consecutive slots of a sequence of epochs, each epoch a
/// fresh permutation of all views, so every view is used once per epoch.
pub fn batch(views: usize, size: u32, seed: u64, iteration: u64) -> Vec<usize> {
    let n = views as u64;
    (0..u64::from(size))
        .map(|k| {
            let slot = iteration * u64::from(size) + k;
            let mut order: Vec<usize> = (0..views).collect();
            order.shuffle(&mut pixel_rng(seed, slot / n, u64::MAX));
            order[(slot % n) as usize]
        })
        .collect()
}

/// What a checkpoint saves.
struct Saved<'a> {
    position: &'a Position,
    parameters: &'a Parameters,
    evaluation: &'a Evaluation,
    /// The log before this iteration, and this iteration's row.
    log: &'a [LogRow],
    row: &'a LogRow,
}

fn write_checkpoint(
    problem: &Problem,
    options: &RunOptions,
    saved: &Saved,
    fingerprint: &str,
) -> Result<()> {
    let Saved {
        position,
        parameters,
        evaluation,
        log,
        row,
    } = *saved;
    let (vdb_path, state_path) = checkpoint::paths(&options.out, position.iteration);
    let level = position.level as usize;
    checkpoint::write_grid(
        &vdb_path,
        parameters,
        problem.domain.transform(level),
        &problem.grid_name,
        metadata(problem, options, position, evaluation),
    )?;
    // The state's log includes this iteration's row, so a resumed run's log.csv is the
    // uninterrupted run's.
    let mut with_row = log.to_vec();
    with_row.push(row.clone());
    let state = Position {
        log: LogRow::csv_rows(&with_row),
        ..position.clone()
    };
    checkpoint::write_state(&state_path, fingerprint, &state, parameters)?;
    if !evaluation.renders.is_empty() {
        write_holdout_picture(
            &options
                .out
                .join(format!("holdout-{:04}.png", position.iteration)),
            &problem.holdouts,
            &evaluation.renders,
            problem.scene.settings.exposure,
        )?;
    }
    write_progress_chart(&options.out, &with_row)
}

fn metadata(
    problem: &Problem,
    options: &RunOptions,
    position: &Position,
    evaluation: &Evaluation,
) -> Vec<crate::io::bridge::MetaEntry> {
    let s = &problem.settings;
    let mut m = vec![
        meta("volgrad_iterations", "int64", position.iteration),
        meta("volgrad_seconds", "double", position.optimisation_seconds),
        meta("volgrad_estimator", "string", options.estimator),
        meta("volgrad_loss", "string", s.loss),
        meta("volgrad_spp", "int64", s.spp),
        meta("volgrad_primal_spp", "int64", s.primal_spp),
        meta("volgrad_seed", "int64", s.seed),
        meta("volgrad_level", "int64", position.level),
    ];
    if !problem.holdouts.is_empty() && !evaluation.renders.is_empty() {
        m.push(meta("volgrad_heldout_psnr", "double", evaluation.psnr));
    }
    m
}

fn write_log(out: &Path, log: &[LogRow]) -> Result<()> {
    let path = out.join("log.csv");
    std::fs::write(&path, LogRow::csv(log)).with_context(|| format!("writing '{}'", path.display()))
}

/// progress.png/.svg: held-out PSNR (top) and training loss (bottom) against optimisation time.
fn write_progress_chart(out: &Path, log: &[LogRow]) -> Result<()> {
    let psnr: Vec<(f64, f64)> = log
        .iter()
        .filter_map(|r| r.psnr.map(|p| (r.seconds, p)))
        .collect();
    let loss: Vec<(f64, f64)> = log.iter().map(|r| (r.seconds, r.loss)).collect();
    if psnr.is_empty() || !loss.iter().any(|p| p.1 > 0.0) {
        return Ok(());
    }
    let chart = |title: &str, y: &str, scale: Scale, name: &str, points: Vec<(f64, f64)>| Chart {
        title: title.into(),
        x_label: "optimisation time (s)".into(),
        y_label: y.into(),
        x_scale: Scale::Linear,
        y_scale: scale,
        series: vec![Series {
            name: name.into(),
            points,
        }],
    };
    let top = chart(
        "held-out PSNR",
        "PSNR (dB)",
        Scale::Linear,
        "held-out",
        psnr,
    );
    let bottom = chart("training loss", "loss", Scale::Log, "training", loss);
    std::fs::write(
        out.join("progress.svg"),
        chart::stack_to_svg(&[&top, &bottom])?,
    )
    .with_context(|| format!("writing '{}'", out.join("progress.svg").display()))?;
    chart::write_stack_png(&[&top, &bottom], &out.join("progress.png"))?;
    Ok(())
}

fn progress_bar(options: &RunOptions) -> indicatif::ProgressBar {
    let total = match options.stop {
        Stop::Iterations(n) => n,
        Stop::Budget(b) => b.as_millis() as u64,
    };
    let bar = crate::io::progress::bar(options.progress, total, "optimize");
    if options.progress {
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

fn bar_position(stop: Stop, position: &Position) -> u64 {
    match stop {
        Stop::Iterations(_) => position.iteration,
        Stop::Budget(_) => (position.optimisation_seconds * 1000.0) as u64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_use_every_view_once_per_epoch() {
        let (views, size) = (6, 4);
        let slots: Vec<usize> = (0..3).flat_map(|i| batch(views, size, 7, i)).collect();
        // 12 slots = two epochs of 6 views.
        for epoch in slots.chunks(views) {
            let mut sorted = epoch.to_vec();
            sorted.sort();
            assert_eq!(sorted, (0..views).collect::<Vec<_>>());
        }
        assert_ne!(slots[..6], slots[6..], "each epoch is reshuffled");
        assert_eq!(batch(views, size, 7, 1), batch(views, size, 7, 1));
    }
}
