//! `log.csv`: one row per iteration. Evaluation columns are empty on iterations without an
//! evaluation; volume columns are empty without a truth. And the log as a chart, `progress.png`.

use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::io::chart::{self, Chart, Scale, Series};
use crate::io::output::write_bytes_whole;
use crate::io::table::{Align, Table};
use crate::optimize::evaluate::Evaluation;

#[derive(Debug, Clone, Default, PartialEq)]
pub struct LogRow {
    pub iteration: u64,
    pub level: u32,
    /// The fraction of the run done when this iteration began: what placed its level and
    /// learning rate (`schedule::Stop`; `--schedule-from` replays this column).
    pub fraction: f32,
    /// Optimisation seconds so far (evaluation and checkpoints excluded).
    pub seconds: f64,
    /// Evaluation and checkpoint seconds so far.
    pub evaluation_seconds: f64,
    /// Training loss of this iteration (batch mean, prior included); NaN (an empty cell) for the
    /// evaluation before the first step.
    pub loss: f64,
    pub psnr: Option<f64>,
    /// What the evaluation's own noise allows (`Evaluation::noise_psnr`).
    pub noise_psnr: Option<f64>,
    /// The held-out renders' samples per pixel (`Evaluation::spp`).
    pub heldout_spp: Option<f64>,
    /// Over the relit held-out views only (`Evaluation::relit_psnr`).
    pub relit_psnr: Option<f64>,
    pub relative_rmse: Option<f64>,
    pub volume_rmse: Option<f64>,
    /// Mean density in the truth's empty voxels over the mean in its occupied ones.
    pub haze: Option<f64>,
    pub active_voxels: u64,
    /// Memory of θ and Adam's moments.
    pub state_bytes: u64,
    /// What this iteration's gradient sum over the ranks sent from each rank (0 in one
    /// process), and its seconds, included in `seconds`.
    pub reduce_bytes: u64,
    pub reduce_seconds: f64,
    /// Each capture's exposure factor after this iteration's step (1 unless fitted), written
    /// separated by spaces.
    pub exposure: Vec<f32>,
}

/// The columns of `log.csv`, in order (the manual documents each: `tests/manual.rs`).
pub const COLUMNS: [&str; 18] = [
    "iteration",
    "level",
    "fraction",
    "seconds",
    "evaluation_seconds",
    "loss",
    "heldout_psnr",
    "relit_psnr",
    "heldout_rel_rmse",
    "volume_rmse",
    "haze",
    "active_voxels",
    "state_bytes",
    "reduce_bytes",
    "reduce_seconds",
    "exposure",
    "heldout_noise_psnr",
    "heldout_spp",
];

fn optional(v: Option<f64>) -> String {
    v.map_or(String::new(), |x| format!("{x}"))
}

impl LogRow {
    /// Fills the evaluation columns.
    pub fn record(&mut self, e: &Evaluation) {
        self.psnr = Some(e.psnr);
        self.noise_psnr = Some(e.noise_psnr);
        self.heldout_spp = Some(e.spp);
        self.relit_psnr = e.relit_psnr;
        self.relative_rmse = Some(e.relative_rmse);
        self.volume_rmse = e.volume_rmse;
        self.haze = e.haze;
    }

    fn cells(&self) -> [String; 18] {
        [
            self.iteration.to_string(),
            self.level.to_string(),
            // f32's shortest text that reads back to the same bits.
            self.fraction.to_string(),
            format!("{}", self.seconds),
            format!("{}", self.evaluation_seconds),
            optional(Some(self.loss).filter(|l| !l.is_nan())),
            optional(self.psnr),
            optional(self.relit_psnr),
            optional(self.relative_rmse),
            optional(self.volume_rmse),
            optional(self.haze),
            self.active_voxels.to_string(),
            self.state_bytes.to_string(),
            self.reduce_bytes.to_string(),
            format!("{}", self.reduce_seconds),
            (self.exposure.iter().map(f32::to_string))
                .collect::<Vec<_>>()
                .join(" "),
            optional(self.noise_psnr),
            optional(self.heldout_spp),
        ]
    }

    /// The whole file: header and rows.
    pub fn csv(rows: &[LogRow]) -> String {
        let mut table = Table::new(COLUMNS.map(|c| (c, Align::Right)));
        for r in rows {
            table.push(r.cells());
        }
        table.csv()
    }

    /// The header line of `csv`: the column names.
    pub fn header() -> String {
        Self::csv(&[]).trim_end().to_string()
    }

    /// The rows without the header (what a checkpoint keeps).
    pub fn csv_rows(rows: &[LogRow]) -> String {
        let csv = Self::csv(rows);
        csv.split_once('\n')
            .map_or(String::new(), |(_, rest)| rest.to_string())
    }

    /// Rows written by `csv_rows`.
    pub fn parse_all(text: &str) -> Result<Vec<LogRow>> {
        text.lines()
            .filter(|l| !l.is_empty())
            .map(|line| Self::parse(line).with_context(|| format!("log row '{line}'")))
            .collect()
    }

    fn parse(line: &str) -> Result<LogRow> {
        let cells: Vec<&str> = line.split(',').collect();
        if cells.len() != COLUMNS.len() {
            bail!("{} cells, expected {}", cells.len(), COLUMNS.len());
        }
        let opt = |i: usize| -> Result<Option<f64>> {
            Ok(if cells[i].is_empty() {
                None
            } else {
                Some(cells[i].parse()?)
            })
        };
        Ok(LogRow {
            iteration: cells[0].parse()?,
            level: cells[1].parse()?,
            fraction: cells[2].parse()?,
            seconds: cells[3].parse()?,
            evaluation_seconds: cells[4].parse()?,
            loss: opt(5)?.unwrap_or(f64::NAN),
            psnr: opt(6)?,
            relit_psnr: opt(7)?,
            relative_rmse: opt(8)?,
            volume_rmse: opt(9)?,
            haze: opt(10)?,
            active_voxels: cells[11].parse()?,
            state_bytes: cells[12].parse()?,
            reduce_bytes: cells[13].parse()?,
            reduce_seconds: cells[14].parse()?,
            exposure: (cells[15].split_whitespace().map(str::parse)).collect::<Result<_, _>>()?,
            noise_psnr: opt(16)?,
            heldout_spp: opt(17)?,
        })
    }
}

/// progress.png/.svg: held-out PSNR (top) and training loss (bottom) against optimisation time.
pub fn write_progress_chart(out: &Path, log: &[LogRow]) -> Result<()> {
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
    write_bytes_whole(
        &out.join("progress.svg"),
        chart::stack_to_svg(&[&top, &bottom])?,
    )?;
    chart::write_stack_png(&[&top, &bottom], &out.join("progress.png"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_round_trip_through_csv() {
        let rows = vec![
            LogRow {
                iteration: 1,
                seconds: 0.5,
                loss: 1.25e-3,
                active_voxels: 10,
                ..Default::default()
            },
            LogRow {
                iteration: 2,
                level: 1,
                fraction: 0.33333334,
                seconds: 1.0,
                loss: 1e-3,
                psnr: Some(31.5),
                noise_psnr: Some(40.25),
                heldout_spp: Some(1536.5),
                relit_psnr: Some(29.25),
                relative_rmse: Some(0.1),
                volume_rmse: Some(0.02),
                haze: Some(0.01),
                state_bytes: 4096,
                reduce_bytes: 123456,
                reduce_seconds: 0.25,
                exposure: vec![1.3, 0.75],
                ..Default::default()
            },
        ];
        let csv = LogRow::csv(&rows);
        assert!(csv.starts_with("iteration,level,fraction,seconds"), "{csv}");
        assert_eq!(LogRow::parse_all(&LogRow::csv_rows(&rows)).unwrap(), rows);
        assert!(LogRow::parse_all("1,2").is_err());
    }
}
