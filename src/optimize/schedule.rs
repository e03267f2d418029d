//! When a run ends, and how far along it is. The level schedule and the learning-rate decay follow
//! the run's fraction done, in [0, 1): iterations done over an iteration count, or seconds of
//! optimisation over a budget. A budget's fractions follow the machine's speed (a busier machine
//! reaches a level at an earlier iteration), so the same command gives another result elsewhere;
//! `log.csv` records the fraction each iteration used, and a run replaying that column
//! (`--schedule-from LOG`) takes the same steps, bit for bit, on any machine.
//!
//! The rule is stored in a checkpoint, so that `--resume` without a new one continues it.

use std::path::Path;
use std::time::Duration;

use anyhow::{bail, Context, Result};

use crate::optimize::log::LogRow;

/// When a run ends.
#[derive(Debug, Clone, PartialEq)]
pub enum Stop {
    Iterations(u64),
    /// Seconds of optimisation (evaluation excluded).
    Budget(Duration),
    /// The fraction done at each iteration, as a logged run used them; ends after the last.
    Replay(Vec<f32>),
}

impl Stop {
    /// An error if a run resumed at `iteration` is past this stop, asked for on the command line.
    /// A budget's last step ends past it, so only a count of iterations (or a replayed
    /// schedule's) can be.
    pub fn not_past(&self, iteration: u64) -> Result<()> {
        let (asked, what) = match self {
            Stop::Iterations(n) => (*n, format!("--iterations {n}")),
            Stop::Replay(steps) => (
                steps.len() as u64,
                format!("the {} steps --schedule-from replays", steps.len()),
            ),
            Stop::Budget(_) => return Ok(()),
        };
        if iteration > asked {
            bail!("past {what}: nothing to do; ask for more to go on");
        }
        Ok(())
    }

    /// How far the run is after `iteration` iterations and `seconds` of optimisation, in [0, 1]
    /// (≥ 1: done).
    pub fn fraction(&self, iteration: u64, seconds: f64) -> f64 {
        match self {
            // 0 iterations: done at once (the start is evaluated and written, nothing stepped).
            Stop::Iterations(0) => 1.0,
            Stop::Iterations(n) => iteration as f64 / *n as f64,
            Stop::Budget(b) => seconds / b.as_secs_f64().max(1e-9),
            Stop::Replay(fractions) => usize::try_from(iteration)
                .ok()
                .and_then(|i| fractions.get(i))
                .map_or(1.0, |&f| f64::from(f)),
        }
    }

    /// The schedule a run's `log.csv` records: the fraction each of its iterations used.
    pub fn replay_log(path: &Path) -> Result<Stop> {
        let text = crate::io::input::read_text(path)
            .with_context(|| format!("--schedule-from: cannot read '{}'", path.display()))?;
        let (header, rows) = text.split_once('\n').unwrap_or((&text, ""));
        // Rows are read by position: a header that names other columns is another file's.
        let columns = LogRow::header();
        if header.trim_end() != columns {
            bail!(
                "--schedule-from: '{}' is not a volgrad log.csv: its header is '{}', this volgrad's '{columns}'",
                path.display(),
                header.trim_end()
            );
        }
        let rows = LogRow::parse_all(rows).with_context(|| {
            format!(
                "--schedule-from: '{}' is not a volgrad log.csv",
                path.display()
            )
        })?;
        let fractions: Vec<f32> = rows.iter().skip(1).map(|r| r.fraction).collect();
        let consecutive = rows
            .iter()
            .enumerate()
            .all(|(i, r)| r.iteration == i as u64);
        if fractions.is_empty() || !consecutive {
            bail!(
                "--schedule-from: '{}' holds no complete run (rows for iterations 0, 1, 2, … from the start)",
                path.display()
            );
        }
        if !fractions.iter().all(|f| (0.0..1.0).contains(f)) {
            bail!(
                "--schedule-from: '{}' has fractions outside [0, 1)",
                path.display()
            );
        }
        Ok(Stop::Replay(fractions))
    }

    /// One line for a checkpoint: `iterations N`, `budget SECONDS` or `replay F F …`.
    pub fn to_text(&self) -> String {
        match self {
            Stop::Iterations(n) => format!("iterations {n}"),
            Stop::Budget(b) => format!("budget {}", b.as_secs_f64()),
            Stop::Replay(fractions) => {
                let all: Vec<String> = fractions.iter().map(f32::to_string).collect();
                format!("replay {}", all.join(" "))
            }
        }
    }

    /// The inverse of `to_text`.
    pub fn parse(text: &str) -> Result<Stop> {
        let (kind, rest) = text.split_once(' ').unwrap_or((text, ""));
        Ok(match kind {
            "iterations" => Stop::Iterations(rest.parse()?),
            "budget" => Stop::Budget(Duration::try_from_secs_f64(rest.parse()?)?),
            "replay" => Stop::Replay(rest.split(' ').map(str::parse).collect::<Result<_, _>>()?),
            _ => bail!("unknown stop rule '{text}'"),
        })
    }

    /// A progress bar's length and position: iterations, or milliseconds of a budget.
    pub fn bar_total(&self) -> u64 {
        match self {
            Stop::Iterations(n) => *n,
            Stop::Budget(b) => b.as_millis() as u64,
            Stop::Replay(fractions) => fractions.len() as u64,
        }
    }

    pub fn bar_position(&self, iteration: u64, seconds: f64) -> u64 {
        match self {
            Stop::Budget(_) => (seconds * 1000.0) as u64,
            Stop::Iterations(_) | Stop::Replay(_) => iteration,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stop_rules_round_trip_as_text() {
        for stop in [
            Stop::Iterations(12),
            Stop::Budget(Duration::from_millis(8250)),
            Stop::Replay(vec![0.0, 0.125, 0.3333333, 0.99999994]),
        ] {
            assert_eq!(Stop::parse(&stop.to_text()).unwrap(), stop);
        }
        assert!(Stop::parse("forever 3").is_err());
    }

    /// A log's schedule replays; a file whose header names other columns is refused (its rows
    /// were read by position whatever the header said).
    #[test]
    fn a_log_with_another_header_is_refused() {
        let rows: Vec<LogRow> = [0.0, 0.25, 0.5]
            .into_iter()
            .enumerate()
            .map(|(i, fraction)| LogRow {
                iteration: i as u64,
                fraction,
                ..LogRow::default()
            })
            .collect();
        let csv = LogRow::csv(&rows);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("log.csv");
        std::fs::write(&path, &csv).unwrap();
        assert_eq!(
            Stop::replay_log(&path).unwrap(),
            Stop::Replay(vec![0.25, 0.5])
        );
        let (header, body) = csv.split_once('\n').unwrap();
        let fewer = header.rsplit_once(',').unwrap().0;
        for other in [
            fewer.to_string(),
            header.replace("fraction", "share"),
            "a,b".into(),
        ] {
            std::fs::write(&path, format!("{other}\n{body}")).unwrap();
            let e = Stop::replay_log(&path).err().unwrap().to_string();
            assert!(e.contains("is not a volgrad log.csv: its header"), "{e}");
        }
    }

    #[test]
    fn a_replay_gives_the_logged_fractions_then_ends() {
        let stop = Stop::Replay(vec![0.0, 0.4, 0.7]);
        assert_eq!(stop.fraction(1, 123.0), f64::from(0.4f32));
        assert_eq!(stop.fraction(3, 0.0), 1.0);
        assert_eq!(Stop::Iterations(4).fraction(1, 9.0), 0.25);
        assert_eq!(Stop::Budget(Duration::from_secs(10)).fraction(9, 2.5), 0.25);
    }
}
