//! What the sweeps mean: error at equal time and time to equal error (interpolated log–log,
//! extrapolated along error ∝ 1/√time), error² × time, and the CSV, charts and markdown tables
//! that show them.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Result;

use crate::compare::Row;
use crate::io::chart::{Chart, Scale, Series};
use crate::io::table::{Align, Table};

fn cell(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.6e}")
    } else {
        String::new()
    }
}

/// runs.csv: one row per run.
pub fn csv(rows: &[Row]) -> String {
    use Align::{Left, Right};
    let mut table = Table::new([
        ("estimator", Left),
        ("spp", Right),
        ("seconds", Right),
        ("rel_rmse", Right),
        ("empty_rmse", Right),
        ("cosine", Right),
        ("bias", Right),
        ("bias_se", Right),
        ("rel_rmse_raw", Right),
    ]);
    for r in rows {
        table.push([
            r.method.clone(),
            r.spp.to_string(),
            format!("{:.6}", r.seconds),
            cell(r.rel_rmse),
            cell(r.empty_rmse),
            cell(r.cosine),
            cell(r.bias),
            cell(r.bias_se),
            cell(r.rel_rmse_raw),
        ]);
    }
    table.csv()
}

/// Error against time, one line per method, in the order the methods first appear.
pub fn chart(rows: &[Row], title: &str, y_label: &str) -> Chart {
    let mut series: Vec<Series> = Vec::new();
    for r in rows {
        let point = (r.seconds, r.rel_rmse);
        match series.iter_mut().find(|s| s.name == r.method) {
            Some(s) => s.points.push(point),
            None => series.push(Series {
                name: r.method.clone(),
                points: vec![point],
            }),
        }
    }
    Chart {
        title: title.into(),
        x_label: "wall time (s)".into(),
        y_label: y_label.into(),
        x_scale: Scale::Log,
        y_scale: Scale::Log,
        series,
    }
}

fn curve<'a>(rows: &'a [Row], method: &str) -> Vec<&'a Row> {
    rows.iter()
        .filter(|r| r.method == method && r.rel_rmse.is_finite() && r.rel_rmse > 0.0)
        .collect()
}

/// Monte Carlo error falls as 1/√t: outside the measured range that slope extrapolates.
const MC_SLOPE: f64 = -0.5;

/// Error at time `t` by log–log interpolation; `true` if extrapolated.
pub fn error_at(points: &[(f64, f64)], t: f64) -> Option<(f64, bool)> {
    let (first, last) = (points.first()?, points.last()?);
    if t <= first.0 {
        return Some((first.1 * (t / first.0).powf(MC_SLOPE), t < first.0));
    }
    if t >= last.0 {
        return Some((last.1 * (t / last.0).powf(MC_SLOPE), t > last.0));
    }
    let w = points.windows(2).find(|w| w[0].0 <= t && t <= w[1].0)?;
    let f = (t / w[0].0).ln() / (w[1].0 / w[0].0).ln();
    Some(((w[0].1.ln() * (1.0 - f) + w[1].1.ln() * f).exp(), false))
}

/// First time the error reaches `target`, by log–log interpolation; `true` if extrapolated.
pub fn time_to_reach(points: &[(f64, f64)], target: f64) -> Option<(f64, bool)> {
    let first = points.first()?;
    if first.1 <= target {
        return Some((first.0 * (target / first.1).powf(1.0 / MC_SLOPE), true));
    }
    for w in points.windows(2) {
        if w[1].1 <= target {
            let f = (target / w[0].1).ln() / (w[1].1 / w[0].1).ln();
            return Some(((w[0].0.ln() * (1.0 - f) + w[1].0.ln() * f).exp(), false));
        }
    }
    let last = points.last()?;
    Some((last.0 * (target / last.1).powf(1.0 / MC_SLOPE), true))
}

/// Runs below this spp are left out of the efficiency: their time is mostly fixed overhead.
const EFFICIENCY_MIN_SPP: u32 = 4;

/// Error² × time, the median over a method's runs of at least `EFFICIENCY_MIN_SPP` spp: a constant
/// for a Monte Carlo method once overheads are paid, and robust to one run's outlier (heavy-tailed
/// estimators such as drt jump up and down between runs).
pub fn inefficiency(rows: &[Row], method: &str) -> Option<f64> {
    let mut v: Vec<f64> = curve(rows, method)
        .iter()
        .filter(|r| r.spp >= EFFICIENCY_MIN_SPP)
        .map(|r| r.rel_rmse * r.rel_rmse * r.seconds)
        .collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

fn points(rows: &[&Row]) -> Vec<(f64, f64)> {
    rows.iter().map(|r| (r.seconds, r.rel_rmse)).collect()
}

fn approx(v: f64, extrapolated: bool) -> String {
    format!("{}{v:.3}", if extrapolated { "~" } else { "" })
}

/// The time `contender` needs to reach `baseline`'s final error, as a fraction of the time
/// `baseline` first reached it (both read off their measured curves: a heavy-tailed baseline may
/// have been there before its last run), or None if either curve is missing. Only runs of at
/// least `EFFICIENCY_MIN_SPP` count, as for the efficiency: a budget that buys a run of 1 spp in
/// no measurable time would compare start-up costs.
pub fn speedup(rows: &[Row], baseline: &str, contender: &str) -> Option<(f64, f64, f64, bool)> {
    let timed = |method| {
        let runs = curve(rows, method);
        let runs: Vec<&Row> = runs
            .into_iter()
            .filter(|r| r.spp >= EFFICIENCY_MIN_SPP)
            .collect();
        points(&runs)
    };
    let (b, c) = (timed(baseline), timed(contender));
    let &(_, target) = b.last()?;
    let (tb, _) = time_to_reach(&b, target)?;
    let (tc, extrapolated) = time_to_reach(&c, target)?;
    Some((tc / tb, target, tc, extrapolated))
}

/// The markdown summary of one set of sweeps: final runs, error at equal time, time to reach the
/// baseline's final error, and the contender's speed-up.
pub fn summary(
    rows: &[Row],
    methods: &[&str],
    baseline: &str,
    contender: &str,
    what: &str,
) -> String {
    use Align::{Left, Right};
    let mut s = format!("#### {what}: final runs\n\n");
    let gradients = rows.iter().any(|r| r.cosine.is_finite());
    let mut finals = if gradients {
        Table::new([
            ("estimator", Left),
            ("spp", Right),
            ("time (s)", Right),
            ("rel. RMSE", Right),
            ("rel. RMSE (raw)", Right),
            ("empty-voxel RMSE", Right),
            ("cosine", Right),
            ("bias ± se", Right),
        ])
    } else {
        Table::new([
            ("method", Left),
            ("spp", Right),
            ("time (s)", Right),
            ("rel. RMSE", Right),
            ("rel. RMSE (raw)", Right),
        ])
    };
    for m in methods {
        if let Some(r) = rows.iter().rfind(|r| &r.method == m) {
            let mut cells = vec![
                m.to_string(),
                r.spp.to_string(),
                format!("{:.2}", r.seconds),
                format!("{:.4}", r.rel_rmse),
                format!("{:.4}", r.rel_rmse_raw),
            ];
            if gradients {
                cells.extend([
                    format!("{:.3e}", r.empty_rmse),
                    format!("{:.4}", r.cosine),
                    format!("{:.2e} ± {:.1e}", r.bias, r.bias_se),
                ]);
            }
            finals.push(cells);
        }
    }
    s += &finals.markdown();
    let curves: Vec<(&str, Vec<(f64, f64)>)> = methods
        .iter()
        .map(|m| (*m, points(&curve(rows, m))))
        .filter(|(_, p)| !p.is_empty())
        .collect();
    // The longest time every curve reached (each is non-empty, filtered above).
    let equal_time = curves
        .iter()
        .filter_map(|(_, p)| p.last().map(|l| l.0))
        .fold(f64::INFINITY, f64::min);
    let target = curves
        .iter()
        .find(|(m, _)| *m == baseline)
        .and_then(|(_, p)| p.last().map(|l| l.1));
    if equal_time.is_finite() {
        let target_text = target.map_or("—".into(), |t| format!("{t:.4}"));
        let mut at_equal_time = Table::new([
            ("method".to_string(), Left),
            (format!("rel. RMSE at {equal_time:.2} s"), Right),
            (format!("time to rel. RMSE {target_text} (s)"), Right),
        ]);
        for (m, p) in &curves {
            let at = error_at(p, equal_time).map_or("—".into(), |(e, x)| approx(e, x));
            let reach = target
                .and_then(|t| time_to_reach(p, t))
                .map_or("—".into(), |(t, x)| approx(t, x));
            at_equal_time.push([m.to_string(), at, reach]);
        }
        let _ = write!(
            s,
            "\n#### {what}: equal time\n\n{}\n(~ marks values extrapolated along error ∝ 1/√time beyond the measured runs.)\n",
            at_equal_time.markdown()
        );
    }
    let mut efficiency = Table::new([
        ("method".to_string(), Left),
        (
            format!("error² × time (median over runs ≥ {EFFICIENCY_MIN_SPP} spp)"),
            Right,
        ),
        (format!("relative to {baseline}"), Right),
    ]);
    let base = inefficiency(rows, baseline);
    for m in methods {
        if let Some(e) = inefficiency(rows, m) {
            let rel = base.map_or("—".into(), |b| format!("{:.3}", e / b));
            efficiency.push([m.to_string(), format!("{e:.4e}"), rel]);
        }
    }
    s += "\n";
    s += &efficiency.markdown();
    match speedup(rows, baseline, contender) {
        Some((factor, target, t, extrapolated)) => {
            let _ = writeln!(
                s,
                "\n**{contender} reaches {baseline}'s final error ({target:.4}) in {factor:.3}× the time** ({}{t:.2} s where {baseline} first got there in {:.2} s; speed-up {:.2}×).",
                if extrapolated { "~" } else { "" },
                t / factor,
                1.0 / factor
            );
        }
        // Only a pair that was compared has a speed-up to report.
        None if [baseline, contender]
            .iter()
            .all(|m| rows.iter().any(|r| r.method == *m)) =>
        {
            let _ = writeln!(
                s,
                "\nNo speed-up of {contender} over {baseline}: one of them has no scored run of at least {EFFICIENCY_MIN_SPP} spp with a non-zero error (raise --budget; or the reference's noise hides it: build a better reference)."
            );
        }
        None => {}
    }
    s
}

/// Writes a chart as `<stem>.png` and `<stem>.svg` in `dir`; says so if the PNG has no labels.
pub fn write_chart(dir: &Path, stem: &str, chart: &Chart) -> Result<()> {
    crate::io::output::write_bytes_whole(
        &dir.join(format!("{stem}.svg")),
        crate::io::chart::to_svg(chart)?,
    )?;
    if !crate::io::chart::write_png(chart, &dir.join(format!("{stem}.png")))? {
        eprintln!(
            "warning: no TTF font found (install fonts-dejavu-core or set VOLGRAD_FONT): {stem}.png has no labels; {stem}.svg has them"
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_and_time_interpolate_log_log_and_extrapolate_as_one_over_root_t() {
        let p = [(1.0, 1.0), (4.0, 0.5), (16.0, 0.25)];
        assert!((error_at(&p, 2.0).unwrap().0 - 0.5f64.sqrt()).abs() < 1e-12);
        assert_eq!(error_at(&p, 4.0).unwrap(), (0.5, false));
        let (e, extrapolated) = error_at(&p, 64.0).unwrap();
        assert!((e - 0.125).abs() < 1e-12 && extrapolated);
        let (t, extrapolated) = time_to_reach(&p, 0.5f64.sqrt()).unwrap();
        assert!((t - 2.0).abs() < 1e-9 && !extrapolated);
        let (t, extrapolated) = time_to_reach(&p, 0.125).unwrap();
        assert!((t - 64.0).abs() < 1e-9 && extrapolated);
    }

    #[test]
    fn speedup_reads_the_contender_curve_at_the_baseline_final_error() {
        let row = |m: &str, t: f64, e: f64| Row {
            method: m.into(),
            spp: EFFICIENCY_MIN_SPP,
            seconds: t,
            rel_rmse: e,
            rel_rmse_raw: e,
            empty_rmse: f64::NAN,
            cosine: f64::NAN,
            bias: f64::NAN,
            bias_se: f64::NAN,
        };
        // drt ends at error 0.5 after 8 s; joint reaches 0.5 at 2 s: a quarter of the time.
        // (An extra drt run that dips to 0.5 early would move drt's time, see below.)
        let rows = [
            row("drt", 2.0, 1.0),
            row("drt", 8.0, 0.5),
            row("joint", 1.0, std::f64::consts::FRAC_1_SQRT_2),
            row("joint", 4.0, std::f64::consts::FRAC_1_SQRT_2 / 2.0),
        ];
        let (factor, target, t, extrapolated) = speedup(&rows, "drt", "joint").unwrap();
        assert!((factor - 0.25).abs() < 1e-9, "{factor}");
        assert_eq!(target, 0.5);
        assert!((t - 2.0).abs() < 1e-9 && !extrapolated);
        assert!(speedup(&rows, "drt", "naive").is_none());
        // A heavy-tailed baseline that was at its final error before its last run is timed from
        // the first time it got there: 4 s, so joint's 2 s are half of it.
        let mut zigzag = rows.to_vec();
        zigzag.insert(1, row("drt", 4.0, 0.5));
        let (factor, _, _, _) = speedup(&zigzag, "drt", "joint").unwrap();
        assert!((factor - 0.5).abs() < 1e-9, "{factor}");
        // A pair that was compared and has no speed-up says so; one that was not says nothing.
        let noise = [row("drt", 2.0, 0.0), row("joint", 1.0, 0.5)];
        let said = summary(&noise, &["drt", "joint"], "drt", "joint", "gradients");
        assert!(said.contains("No speed-up of joint over drt"), "{said}");
        let alone = summary(&rows[2..], &["joint"], "drt", "joint", "gradients");
        assert!(!alone.contains("speed-up"), "{alone}");
        // Runs below EFFICIENCY_MIN_SPP (a budget of 0 s buys 1 spp in no measurable time)
        // time start-up, not the estimators: no speed-up from them.
        let short: Vec<Row> = (rows.iter())
            .map(|r| Row {
                spp: 1,
                ..r.clone()
            })
            .collect();
        assert!(speedup(&short, "drt", "joint").is_none());
        let said = summary(&short, &["drt", "joint"], "drt", "joint", "gradients");
        assert!(
            said.contains("No speed-up") && said.contains("raise --budget"),
            "{said}"
        );
    }
}
