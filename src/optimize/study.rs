//! The equal-time study: the same reconstruction (views, start, schedule, seeds) once per
//! estimator, each into `DIR/<estimator>/`, then `inverse.png/.svg` (held-out PSNR against
//! optimisation seconds), `inverse.csv`, `renders.png` (a held-out view: target, then each
//! estimator's result) and `summary.md` (final PSNR, volume error and haze of each, PSNR at equal
//! times, and the time each needs to reach DRT's final PSNR).

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Result;

use crate::gradient::adjoint::Estimator;
use crate::io::chart::{self, Chart, Scale, Series};
use crate::io::images;
use crate::io::table::{Align, Table};
use crate::optimize::evaluate::Evaluation;
use crate::optimize::holdout_picture::{panel, side_by_side};
use crate::optimize::log::LogRow;
use crate::optimize::problem::Problem;
use crate::optimize::reconstruct::{reconstruct, RunOptions};

pub struct StudyRun {
    pub estimator: Estimator,
    pub log: Vec<LogRow>,
    pub evaluation: Evaluation,
}

impl StudyRun {
    /// (seconds, PSNR) of every evaluation.
    fn curve(&self) -> Vec<(f64, f64)> {
        self.log
            .iter()
            .filter_map(|r| r.psnr.map(|p| (r.seconds, p)))
            .collect()
    }

    /// The held-out PSNR of the last evaluation at or before `seconds`.
    pub fn psnr_at(&self, seconds: f64) -> Option<f64> {
        self.curve()
            .into_iter()
            .take_while(|&(t, _)| t <= seconds)
            .last()
            .map(|(_, p)| p)
    }

    /// The first time the held-out PSNR reaches `psnr`.
    pub fn time_to(&self, psnr: f64) -> Option<f64> {
        self.curve()
            .into_iter()
            .find(|&(_, p)| p >= psnr)
            .map(|(t, _)| t)
    }

    /// The largest fall of the held-out PSNR below its running best, counting evaluations after
    /// `after` seconds (the best may come from before): how far the run ever went back.
    pub fn largest_dip(&self, after: f64) -> Option<f64> {
        let mut best = f64::NEG_INFINITY;
        let mut dip: Option<f64> = None;
        for (t, p) in self.curve() {
            best = best.max(p);
            if t >= after {
                dip = Some(dip.unwrap_or(0.0).max(best - p));
            }
        }
        dip
    }

    fn final_row(&self) -> Option<&LogRow> {
        self.log.iter().rev().find(|r| r.psnr.is_some())
    }
}

/// Runs the study; `options` is the template of each run (its estimator and folder are set here).
pub fn equal_time(
    problem: &Problem,
    estimators: &[Estimator],
    options: &RunOptions,
) -> Result<Vec<StudyRun>> {
    let out = &options.out;
    let mut runs = Vec::new();
    for &estimator in estimators {
        if options.progress {
            eprintln!("{estimator}:");
        }
        let run_options = RunOptions {
            estimator,
            stop: options.stop.clone(),
            out: out.join(estimator.to_string()),
            resume: None,
            progress: options.progress,
            interrupt: options.interrupt,
            cluster: options.cluster,
        };
        let outcome = reconstruct(problem, &run_options)?;
        if outcome.interrupted {
            return Err(crate::cluster::AgreedError(format!(
                "interrupted during the {estimator} run (its checkpoint is in '{}')",
                run_options.out.display()
            ))
            .into());
        }
        runs.push(StudyRun {
            estimator,
            log: run_options
                .cluster
                .agree(LogRow::parse_all(&outcome.position.log))?,
            evaluation: outcome.evaluation,
        });
    }
    // Rank 0 writes; the others learn whether it could.
    let cluster = options.cluster;
    cluster.agree(cluster.on_root(|| write_outputs(problem, &runs, out)))?;
    Ok(runs)
}

fn write_outputs(problem: &Problem, runs: &[StudyRun], out: &Path) -> Result<()> {
    let write = |name: &str, text: String| {
        let path = out.join(name);
        crate::io::output::write_bytes_whole(&path, text)
    };
    let mut csv = Table::new(
        [
            "estimator",
            "iteration",
            "seconds",
            "heldout_psnr",
            "volume_rmse",
            "haze",
        ]
        .map(|c| (c, Align::Right)),
    );
    for run in runs {
        for r in run.log.iter().filter(|r| r.psnr.is_some()) {
            let opt = |v: Option<f64>| v.map_or(String::new(), |x| format!("{x}"));
            csv.push([
                run.estimator.to_string(),
                r.iteration.to_string(),
                format!("{}", r.seconds),
                opt(r.psnr),
                opt(r.volume_rmse),
                opt(r.haze),
            ]);
        }
    }
    write("inverse.csv", csv.csv())?;
    let chart = Chart {
        title: "held-out PSNR at equal optimisation time".into(),
        x_label: "optimisation time (s)".into(),
        y_label: "held-out PSNR (dB)".into(),
        x_scale: Scale::Linear,
        y_scale: Scale::Linear,
        series: runs
            .iter()
            .map(|r| Series {
                name: r.estimator.to_string(),
                points: r.curve(),
            })
            .collect(),
    };
    write("inverse.svg", chart::to_svg(&chart)?)?;
    chart::write_png(&chart, &out.join("inverse.png"))?;
    if let Some(view) = problem.holdouts.first() {
        let mut panels = vec![panel(&view.target)];
        panels.extend(
            runs.iter()
                .filter_map(|r| r.evaluation.renders.first())
                .map(panel),
        );
        images::write_png(
            &out.join("renders.png"),
            &side_by_side(&panels.iter().collect::<Vec<_>>()),
            problem.scene.settings.exposure,
        )?;
    }
    write("summary.md", summary(runs))
}

/// The held-out PSNR should never fall far below its running best after this (the first minute
/// is allowed to wander while the coarse shape forms).
const STABLE_AFTER_SECONDS: f64 = 60.0;

/// A time as a column header: tenths below 10 s.
fn seconds(t: f64) -> String {
    if t < 10.0 {
        format!("{t:.1}")
    } else {
        format!("{t:.0}")
    }
}

/// The study's table and verdict, in markdown.
pub fn summary(runs: &[StudyRun]) -> String {
    let budget = runs
        .iter()
        .filter_map(|r| r.log.last().map(|l| l.seconds))
        .fold(f64::INFINITY, f64::min);
    let drt_final = runs
        .iter()
        .find(|r| r.estimator == Estimator::Drt)
        .and_then(|r| r.final_row()?.psnr);
    let fractions = [0.25, 0.5, 1.0];
    let mut columns = vec![
        ("estimator".to_string(), Align::Left),
        ("iterations".into(), Align::Right),
        ("s / iteration".into(), Align::Right),
        ("final PSNR (dB)".into(), Align::Right),
        ("relit PSNR (dB)".into(), Align::Right),
        ("volume RMSE".into(), Align::Right),
        ("haze".into(), Align::Right),
    ];
    for f in fractions {
        columns.push((format!("PSNR at {} s", seconds(f * budget)), Align::Right));
    }
    columns.push(("time to DRT's final PSNR (s)".into(), Align::Right));
    columns.push(("largest dip after 60 s (dB)".into(), Align::Right));
    let mut table = Table::new(columns);
    let number =
        |v: Option<f64>, digits: usize| v.map_or("–".into(), |x| format!("{x:.digits$}"));
    for run in runs {
        let last = run.final_row();
        let iterations = run.log.last().map_or(0, |r| r.iteration);
        let per_iteration = run
            .log
            .last()
            .map(|r| r.seconds / r.iteration.max(1) as f64);
        let mut row = vec![
            run.estimator.to_string(),
            iterations.to_string(),
            number(per_iteration, 3),
            number(last.and_then(|r| r.psnr), 2),
            number(last.and_then(|r| r.relit_psnr), 2),
            number(last.and_then(|r| r.volume_rmse), 4),
            number(last.and_then(|r| r.haze), 3),
        ];
        for f in fractions {
            row.push(number(run.psnr_at(f * budget), 2));
        }
        row.push(number(drt_final.and_then(|p| run.time_to(p)), 1));
        row.push(number(run.largest_dip(STABLE_AFTER_SECONDS), 2));
        table.push(row);
    }
    let mut text = String::from("# Inverse rendering: estimators at equal time\n\n");
    text.push_str(&table.markdown());
    let joint = runs.iter().find(|r| r.estimator == Estimator::Joint);
    let drt = runs.iter().find(|r| r.estimator == Estimator::Drt);
    if let (Some(joint), Some(drt), Some(target)) = (joint, drt, drt_final) {
        let drt_time = drt.time_to(target);
        match (joint.time_to(target), drt_time) {
            (Some(j), Some(d)) if d > 0.0 => {
                let _ = writeln!(
                    text,
                    "\njoint reaches DRT's final held-out PSNR ({target:.2} dB) in {j:.1} s, {:.2}× DRT's {d:.1} s.",
                    j / d
                );
            }
            _ => {
                let _ = writeln!(
                    text,
                    "\njoint does not reach DRT's final held-out PSNR ({target:.2} dB) within the budget."
                );
            }
        }
        let gaps: Vec<f64> = drt
            .curve()
            .iter()
            .filter(|&&(t, _)| t > 0.0)
            .filter_map(|&(t, p)| Some(joint.psnr_at(t)? - p))
            .collect();
        if let Some(min) = gaps.iter().copied().reduce(f64::min) {
            let _ = writeln!(
                text,
                "At every evaluation of DRT after the start, joint's held-out PSNR at the same time differs from DRT's by {min:+.2} dB or more."
            );
        }
    }
    text
}
