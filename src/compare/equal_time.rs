//! Equal-time sweeps: each method at 1, 2, 4, … spp until its budget is spent, every run scored
//! against the reference; the CSV, the charts and the markdown summary.

use std::fmt::Write as _;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use glam::{IVec3, Vec3};

use crate::compare::Reference;
use crate::gradient::adjoint::Estimator;
use crate::gradient::fd;
use crate::gradient::grid::GradientGrid;
use crate::gradient::loss::Loss;
use crate::gradient::passes::{gradient, GradOptions};
use crate::gradient::runs::{seeded_runs, MeanAndError};
use crate::io::chart::{Chart, Series};
use crate::io::images::RgbImage;
use crate::io::table::{Align, Table};
use crate::render::image::{render, RenderOptions};
use crate::render::scene::Scene;
use crate::volume::brickmap::BrickMap;
use crate::volume::majorant::Majorant;

/// Reference runs use seeds far from the compared runs' (seed, seed + 1, …) so that no compared
/// run shares random numbers with the reference it is scored against.
pub(super) const REFERENCE_SEED_OFFSET: u64 = 1 << 20;
pub(super) const SWEEP_SEED_OFFSET: u64 = 1 << 10;

/// ∂(mean pixel)/∂pixel: the adjoint of loss `mean`.
pub(super) fn mean_adjoint(scene: &Scene) -> Vec<Vec3> {
    Loss::Mean.adjoint(
        &RgbImage::new(scene.camera.width, scene.camera.height),
        None,
    )
}

/// Calls `f(v)` for every voxel of the parameter domain (active box plus the trilinear apron).
pub(super) fn for_domain(grid: &BrickMap, mut f: impl FnMut(IVec3)) {
    if let Some((lo, hi)) = fd::domain_bounds(grid) {
        for x in lo.x..=hi.x {
            for y in lo.y..=hi.y {
                for z in lo.z..=hi.z {
                    f(IVec3::new(x, y, z));
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Scoring runs

/// One run of a method at one spp. Fields that do not apply are NaN (empty in the CSV).
#[derive(Debug, Clone)]
pub struct Row {
    pub method: String,
    pub spp: u32,
    pub seconds: f64,
    /// ‖g − ref‖ / ‖ref‖ with the reference's noise subtracted (relative image RMSE for renders).
    pub rel_rmse: f64,
    pub rel_rmse_raw: f64,
    /// RMSE over empty voxels (grid value 0) of the domain, reference noise subtracted.
    pub empty_rmse: f64,
    pub cosine: f64,
    /// Mean error over the domain, and its standard error treating voxel errors as independent.
    pub bias: f64,
    pub bias_se: f64,
}

/// Scores a gradient against the reference over the voxels where either is non-zero.
pub fn score(
    method: &str,
    spp: u32,
    seconds: f64,
    g: &GradientGrid,
    r: &Reference,
    grid: &BrickMap,
) -> Row {
    let (mut n, mut e1, mut e2, mut se2, mut ref2, mut g2, mut dot) =
        (0u64, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let (mut empty_n, mut empty_e2, mut empty_se2) = (0u64, 0.0, 0.0);
    for_domain(grid, |v| {
        let (x, m) = (g.get(v), r.mean.get(v));
        if x == 0.0 && m == 0.0 {
            return;
        }
        let (e, s) = (x - m, r.stderr.get(v));
        n += 1;
        e1 += e;
        e2 += e * e;
        se2 += s * s;
        ref2 += m * m;
        g2 += x * x;
        dot += x * m;
        if grid.voxel(v) == 0.0 {
            empty_n += 1;
            empty_e2 += e * e;
            empty_se2 += s * s;
        }
    });
    let nan_if = |cond: bool, v: f64| if cond { f64::NAN } else { v };
    Row {
        method: method.into(),
        spp,
        seconds,
        rel_rmse: nan_if(ref2 == 0.0, ((e2 - se2).max(0.0) / ref2).sqrt()),
        rel_rmse_raw: nan_if(ref2 == 0.0, (e2 / ref2).sqrt()),
        empty_rmse: nan_if(
            empty_n == 0,
            ((empty_e2 - empty_se2).max(0.0) / empty_n as f64).sqrt(),
        ),
        cosine: nan_if(g2 == 0.0 || ref2 == 0.0, dot / (g2.sqrt() * ref2.sqrt())),
        bias: nan_if(n == 0, e1 / n as f64),
        bias_se: nan_if(n == 0, e2.sqrt() / n as f64),
    }
}

/// Runs `run(spp)` at spp 1, 2, 4, … while the next run (about twice the last) still fits in the
/// budget. `run` returns the seconds to count and the scored row.
fn sweep(
    budget: Duration,
    max_spp: u32,
    bar: &indicatif::ProgressBar,
    mut run: impl FnMut(u32) -> Row,
) -> Vec<Row> {
    let mut rows = Vec::new();
    let mut spent = 0.0;
    let mut spp = 1u32;
    loop {
        bar.set_message(format!("spp {spp}"));
        let row = run(spp);
        spent += row.seconds;
        let last = row.seconds;
        rows.push(row);
        bar.set_position((spent * 1000.0).min(budget.as_secs_f64() * 1000.0) as u64);
        if spp >= max_spp || spent + 2.0 * last > budget.as_secs_f64() {
            break;
        }
        spp *= 2;
    }
    rows
}

#[derive(Debug, Clone, Copy)]
pub struct SweepOptions {
    /// Per method.
    pub budget: Duration,
    pub max_spp: u32,
    pub seed: u64,
    pub max_depth: u32,
    pub progress: bool,
}

fn budget_bar(o: &SweepOptions, what: &str) -> indicatif::ProgressBar {
    let bar = crate::io::progress::bar(o.progress, o.budget.as_millis() as u64, what);
    if o.progress {
        bar.set_style(
            indicatif::ProgressStyle::with_template("{prefix:>10} {msg:>9} [{bar:40}] {elapsed}")
                .expect("valid template")
                .progress_chars("=> "),
        );
        bar.set_prefix(what.to_string());
    }
    bar
}

/// Equal-time sweeps of the gradient estimators against the reference.
pub fn gradient_sweeps(
    scene: &Scene,
    estimators: &[Estimator],
    r: &Reference,
    o: &SweepOptions,
) -> Vec<Row> {
    let adjoint = mean_adjoint(scene);
    let mut rows = Vec::new();
    for &estimator in estimators {
        let name = estimator.to_string();
        let bar = budget_bar(o, &name);
        rows.extend(sweep(o.budget, o.max_spp, &bar, |spp| {
            let seed = o.seed.wrapping_add(SWEEP_SEED_OFFSET + spp as u64);
            let run = gradient(
                scene,
                &adjoint,
                &GradOptions::new(estimator, spp, seed, o.max_depth),
            );
            let seconds = run.stats.wall.as_secs_f64();
            score(&name, spp, seconds, &run.gradient, r, &scene.medium.grid)
        }));
        bar.finish_and_clear();
    }
    rows
}

// ---------------------------------------------------------------------------------------------
// The forward renderer

pub struct ImageReference {
    pub mean: RgbImage,
    /// Per-value variance of `mean` (averaged over pixels and channels): the floor every run's
    /// MSE against it carries.
    pub noise_mse: f64,
}

/// The mean of `seeds` renders at `spp`, and its noise.
pub fn build_image_reference(
    scene: &Scene,
    spp: u32,
    seeds: u32,
    seed: u64,
    max_depth: u32,
    progress: bool,
) -> ImageReference {
    let seeds = seeds.max(2);
    let bar = crate::io::progress::bar(progress, seeds as u64, "image ref");
    let first_seed = seed.wrapping_add(REFERENCE_SEED_OFFSET);
    let images: Vec<RgbImage> = seeded_runs(first_seed, seeds, |_, seed| {
        let options = RenderOptions {
            spp,
            seed,
            max_depth,
            progress: false,
        };
        let image = render(scene, &options).0;
        bar.inc(1);
        image
    });
    bar.finish_and_clear();
    let mut mean = RgbImage::new(scene.camera.width, scene.camera.height);
    let mut variance_sum = 0.0;
    for i in 0..mean.pixels.len() {
        for c in 0..3 {
            let values: Vec<f64> = images.iter().map(|im| im.pixels[i][c] as f64).collect();
            let m = MeanAndError::of(&values);
            mean.pixels[i][c] = m.mean as f32;
            variance_sum += m.se * m.se;
        }
    }
    ImageReference {
        noise_mse: variance_sum / (mean.pixels.len() * 3) as f64,
        mean,
    }
}

/// RMSE relative to the reference's mean pixel value: (noise-subtracted, raw).
pub fn image_error(image: &RgbImage, r: &ImageReference) -> (f64, f64) {
    let n = (image.pixels.len() * 3) as f64;
    let mut mse = 0.0;
    let mut level = 0.0;
    for (a, b) in image.pixels.iter().zip(&r.mean.pixels) {
        let d = *a - *b;
        mse += d.dot(d) as f64;
        level += (b.x + b.y + b.z) as f64;
    }
    let (mse, level) = (mse / n, (level / n).max(f64::MIN_POSITIVE));
    (
        (mse - r.noise_mse).max(0.0).sqrt() / level,
        mse.sqrt() / level,
    )
}

pub const RENDER_GRID: &str = "render, majorant grid";
pub const RENDER_GLOBAL: &str = "render, global majorant";

/// Equal-time sweeps of the forward renderer with the majorant grid and with one global majorant.
pub fn render_sweeps(scene: &Scene, r: &ImageReference, o: &SweepOptions) -> Vec<Row> {
    let cell = scene.settings.majorant_cell;
    let mut rows = Vec::new();
    for (name, mode) in [
        (RENDER_GRID, Majorant::grid(cell)),
        (RENDER_GLOBAL, Majorant::global()),
    ] {
        let mut s = scene.clone();
        s.set_majorant(mode);
        let bar = budget_bar(
            o,
            if mode == Majorant::global() {
                "global"
            } else {
                "grid"
            },
        );
        rows.extend(sweep(o.budget, o.max_spp, &bar, |spp| {
            let options = RenderOptions {
                spp,
                seed: o.seed.wrapping_add(SWEEP_SEED_OFFSET + spp as u64),
                max_depth: o.max_depth,
                progress: false,
            };
            let (image, stats) = render(&s, &options);
            let (rel, raw) = image_error(&image, r);
            Row {
                method: name.into(),
                spp,
                seconds: stats.wall.as_secs_f64(),
                rel_rmse: rel,
                rel_rmse_raw: raw,
                empty_rmse: f64::NAN,
                cosine: f64::NAN,
                bias: f64::NAN,
                bias_se: f64::NAN,
            }
        }));
        bar.finish_and_clear();
    }
    rows
}

// ---------------------------------------------------------------------------------------------
// Outputs: CSV, charts, tables

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
/// have been there before its last run), or None if either curve is missing.
pub fn speedup(rows: &[Row], baseline: &str, contender: &str) -> Option<(f64, f64, f64, bool)> {
    let b = points(&curve(rows, baseline));
    let c = points(&curve(rows, contender));
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
        None => {
            let _ = writeln!(
                s,
                "\nNo speed-up of {contender} over {baseline}: one of them has no scored run with a non-zero error (the reference's noise may hide it: build a better reference)."
            );
        }
    }
    s
}

/// Writes a chart as `<stem>.png` and `<stem>.svg` in `dir`; says so if the PNG has no labels.
pub fn write_chart(dir: &Path, stem: &str, chart: &Chart) -> Result<()> {
    std::fs::write(
        dir.join(format!("{stem}.svg")),
        crate::io::chart::to_svg(chart)?,
    )
    .with_context(|| format!("writing {stem}.svg in '{}'", dir.display()))?;
    if !crate::io::chart::write_png(chart, &dir.join(format!("{stem}.png")))? {
        eprintln!(
            "warning: no TTF font found (install fonts-dejavu-core or set VOLGRAD_FONT): {stem}.png has no labels; {stem}.svg has them"
        );
    }
    Ok(())
}

/// How long something took, for messages.
pub fn timed<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let start = Instant::now();
    let v = f();
    (v, start.elapsed().as_secs_f64())
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
            spp: 1,
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
    }
}
