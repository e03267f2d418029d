//! `volgrad compare`: speed against accuracy, and stability where estimators are known to fail.
//!
//! - A reference gradient that favours no estimator: the mean of joint and drt runs (alternating,
//!   each with its own seed) and its per-voxel standard error, checked against finite differences
//!   before it is trusted.
//! - Equal-time sweeps: each method runs at 1, 2, 4, … spp until its time budget is spent; every
//!   run is scored against the reference. The reference's own noise adds Σ se² to ‖g − ref‖², so it
//!   is subtracted (`rel_rmse`; the raw value is kept as `rel_rmse_raw`): otherwise every curve
//!   would flatten at the reference's noise floor and the speed-ups would shrink towards 1.
//! - The same for the forward renderer (image error against time, majorant grid against global).
//! - The stability suite: small in-memory scenes built to break estimators, each estimator's
//!   ⟨g, 1⟩ against finite differences, its spread, and a count of non-finite values.
//!
//! Every gradient is that of the mean pixel value (loss `mean`).

use std::fmt::Write as _;
use std::path::Path;
use std::time::{Duration, Instant};

/// `fd::directional_derivative` only fails for directions that lower a voxel below 0; the checks
/// here step up only.
use anyhow::{bail, Context, Result};
use glam::{DMat3, DVec3, IVec3, Vec3};

use crate::adjoint::{AdjointOptions, Estimator, Suffix};
use crate::brickmap::{BrickMap, BrickMapBuilder};
use crate::camera::Camera;
use crate::chart::{Chart, Series};
use crate::fd::{self, FdOptions, FdResult};
use crate::grad::{gradient, GradOptions};
use crate::gradcheck::Check;
use crate::gradgrid::GradientGrid;
use crate::gradio::{self, Provenance};
use crate::image_io::RgbImage;
use crate::lights::{DirectionalLight, Environment, Lights};
use crate::loss::Loss;
use crate::majorant::MajorantMode;
use crate::medium::{Filter, Medium};
use crate::render::{render, RenderOptions};
use crate::scene::{RenderFile, Scene};
use crate::transform::IndexTransform;
use crate::vdb::{self, meta, GridSelector};

/// Reference runs use seeds far from the compared runs' (seed, seed + 1, …) so that no compared
/// run shares random numbers with the reference it is scored against.
const REFERENCE_SEED_OFFSET: u64 = 1 << 20;
const SWEEP_SEED_OFFSET: u64 = 1 << 10;

pub fn estimator_name(e: Estimator) -> &'static str {
    match e {
        Estimator::Joint => "joint",
        Estimator::Drt => "drt",
        Estimator::Naive => "naive",
    }
}

/// ∂(mean pixel)/∂pixel: the adjoint of loss `mean`.
fn mean_adjoint(scene: &Scene) -> Vec<Vec3> {
    Loss::Mean.adjoint(
        &RgbImage::new(scene.camera.width, scene.camera.height),
        None,
    )
}

fn grad_options(estimator: Estimator, spp: u32, seed: u64, max_depth: u32) -> GradOptions {
    GradOptions {
        adjoint: AdjointOptions {
            estimator,
            suffix: Suffix::PerPath,
            max_depth,
        },
        spp,
        seed,
        active_only: false,
        progress: false,
    }
}

/// Calls `f(v)` for every voxel of the parameter domain (active box plus the trilinear apron).
fn for_domain(grid: &BrickMap, mut f: impl FnMut(IVec3)) {
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
// The reference gradient

pub struct Reference {
    pub mean: GradientGrid,
    /// Standard error of `mean`, per voxel.
    pub stderr: GradientGrid,
    /// Standard error of ⟨mean, 1⟩ (from the runs' totals: voxels are correlated within a run).
    pub sum_se: f64,
    pub spp_per_run: u32,
    pub runs: u32,
}

#[derive(Debug, Clone, Copy)]
pub struct ReferenceOptions {
    pub spp: u32,
    /// Seeds per estimator: joint and drt each run this many times.
    pub seeds: u32,
    pub seed: u64,
    pub max_depth: u32,
    pub progress: bool,
}

/// Mean of `seeds` joint runs and `seeds` drt runs at `spp` each, with per-voxel standard errors.
pub fn build_reference(scene: &Scene, o: &ReferenceOptions) -> Reference {
    let adjoint = mean_adjoint(scene);
    let mut sum = GradientGrid::for_grid(&scene.medium.grid);
    let mut squares = sum.empty_like();
    let mut totals = Vec::new();
    let runs = 2 * o.seeds.max(1);
    let bar = crate::progress::bar(o.progress, runs as u64, "reference");
    for r in 0..runs {
        let estimator = if r % 2 == 0 {
            Estimator::Joint
        } else {
            Estimator::Drt
        };
        let seed = o.seed.wrapping_add(REFERENCE_SEED_OFFSET + r as u64);
        let g = gradient(
            scene,
            &adjoint,
            &grad_options(estimator, o.spp, seed, o.max_depth),
        )
        .gradient;
        sum.merge(&g, 1.0);
        for (v, x) in g.voxels() {
            if x != 0.0 {
                squares.add(v, x * x);
            }
        }
        totals.push(g.sum());
        bar.inc(1);
    }
    bar.finish_and_clear();
    let n = runs as f64;
    let mut mean = sum;
    mean.scale(1.0 / n);
    let mut stderr = mean.empty_like();
    for (v, s2) in squares.voxels() {
        if s2 != 0.0 {
            let m = mean.get(v);
            let variance = ((s2 / n - m * m) * n / (n - 1.0)).max(0.0);
            stderr.add(v, (variance / n).sqrt());
        }
    }
    let (_, sum_se) = mean_and_se(&totals);
    Reference {
        mean,
        stderr,
        sum_se,
        spp_per_run: o.spp,
        runs,
    }
}

/// Mean and standard error of the mean.
fn mean_and_se(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    if n == 0.0 {
        return (f64::NAN, f64::NAN);
    }
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (mean, (var / n).sqrt())
}

fn reference_provenance(scene: &Scene, r: &Reference) -> Provenance {
    Provenance {
        estimator: "joint+drt".into(),
        spp: r.spp_per_run as u64 * r.runs as u64,
        seed: format!("{} runs of {} spp", r.runs, r.spp_per_run),
        loss: Loss::Mean.name().into(),
        scene: scene.path.display().to_string(),
    }
}

/// Writes `grad_<grid>` (the mean) and `grad_<grid>_stderr` to one VDB.
pub fn save_reference(path: &Path, scene: &Scene, r: &Reference, overwrite: bool) -> Result<()> {
    let provenance = reference_provenance(scene, r);
    let transform = scene.medium.transform;
    let extra = [
        meta("volgrad_sum_stderr", "string", r.sum_se),
        meta("volgrad_reference_runs", "int64", r.runs),
        meta("volgrad_reference_spp", "int64", r.spp_per_run),
    ];
    let mut mean = gradio::gradient_grid(&r.mean, &scene.grid_name, transform, &provenance);
    mean.metadata.extend(extra.iter().cloned());
    let mut se = gradio::gradient_grid(&r.stderr, &scene.grid_name, transform, &provenance);
    se.name = format!("grad_{}_stderr", scene.grid_name);
    se.metadata.extend(extra.iter().cloned());
    vdb::write_grids(path, &[&mean, &se], false, overwrite)
}

/// Reads a reference written by `save_reference` for this scene's grid.
pub fn load_reference(path: &Path, scene: &Scene) -> Result<Reference> {
    let name = format!("grad_{}", scene.grid_name);
    let read = |n: &str| {
        vdb::read_grid(path, &GridSelector::Name(n.to_string())).with_context(|| {
            format!(
                "'{}' has no grid '{n}': pass a reference written by `volgrad compare` for this scene",
                path.display()
            )
        })
    };
    let mean = read(&name)?;
    let se = read(&format!("{name}_stderr"))?;
    if mean.transform != scene.medium.transform || se.transform != scene.medium.transform {
        bail!(
            "the reference '{}' has another transform than the scene's grid: it was made for another scene",
            path.display()
        );
    }
    let get = |key: &str| {
        mean.metadata
            .iter()
            .find(|e| e.name == key)
            .map(|e| e.value.clone())
    };
    if get("volgrad_loss").as_deref() != Some(Loss::Mean.name()) {
        bail!(
            "the reference '{}' is not the gradient of loss \"mean\"",
            path.display()
        );
    }
    let number = |key: &str| -> Result<f64> {
        get(key).and_then(|s| s.parse().ok()).with_context(|| {
            format!(
                "'{}' has no {key} metadata: not a reference written by `volgrad compare`",
                path.display()
            )
        })
    };
    let sum_se = number("volgrad_sum_stderr")?;
    let runs = number("volgrad_reference_runs")? as u32;
    let spp_per_run = number("volgrad_reference_spp")? as u32;
    let to_gradient = |grid: &vdb::Grid| -> Result<GradientGrid> {
        let mut g = GradientGrid::for_grid(&scene.medium.grid);
        let domain = fd::domain_bounds(&scene.medium.grid);
        for leaf in grid.bricks.leaves() {
            for (o, &value) in leaf.values.iter().enumerate() {
                if value == 0.0 {
                    continue;
                }
                let v = leaf.origin
                    + IVec3::new((o >> 6) as i32, ((o >> 3) & 7) as i32, (o & 7) as i32);
                if !domain.is_some_and(|(lo, hi)| v.cmpge(lo).all() && v.cmple(hi).all()) {
                    bail!(
                        "the reference '{}' has a value at voxel {v}, outside this scene's grid: it was made for another grid",
                        path.display()
                    );
                }
                g.add(v, value as f64);
            }
        }
        Ok(g)
    };
    Ok(Reference {
        mean: to_gradient(&mean)?,
        stderr: to_gradient(&se)?,
        sum_se,
        spp_per_run,
        runs,
    })
}

/// Optical depth that the ⟨g, 1⟩ finite difference adds across the domain's longest side. A step
/// in grid units would not do: ε added to every voxel of the cloud's box (mostly empty space) at
/// the per-voxel step 0.15 added τ ≈ 15 and the stencil read 0.30 for a derivative of 0.43; at
/// τ = 2 the truncation error is below the noise of 16 spp × 8 repeats.
pub const ONES_OPTICAL_STEP: f64 = 2.0;

/// The fd step for ⟨g, 1⟩ over the whole domain (see `ONES_OPTICAL_STEP`).
pub fn ones_eps(scene: &Scene) -> f32 {
    let Some((lo, hi)) = fd::domain_bounds(&scene.medium.grid) else {
        return 1.0;
    };
    let side = ((hi - lo + 1).as_dvec3() * scene.medium.transform.voxel_size()).max_element();
    (ONES_OPTICAL_STEP / (scene.medium.density_scale as f64 * side).max(1e-12)) as f32
}

/// The reference against finite differences: the `voxels` voxels of largest |g| among those the
/// reference resolves (|g| > 4 se: the largest |g| overall are often one run's outlier), with
/// `fd_options.eps`, and ⟨g, 1⟩ over the whole domain with `ones_eps`.
pub fn check_reference(
    scene: &Scene,
    r: &Reference,
    fd_options: &FdOptions,
    voxels: usize,
) -> Result<Vec<Check>> {
    let grid = &scene.medium.grid;
    let mut strongest: Vec<(IVec3, f64, f64)> = r
        .mean
        .voxels()
        .map(|(v, g)| (v, g, r.stderr.get(v)))
        .filter(|&(_, g, se)| se > 0.0 && g.abs() > 4.0 * se)
        .collect();
    strongest.sort_by(|a, b| {
        b.1.abs()
            .total_cmp(&a.1.abs())
            .then((a.0.x, a.0.y, a.0.z).cmp(&(b.0.x, b.0.y, b.0.z)))
    });
    let mut checks: Vec<Check> = strongest
        .iter()
        .take(voxels)
        .map(|&(v, g, se)| {
            Ok(Check {
                name: format!("voxel {v}"),
                estimate: g,
                estimate_se: se,
                fd: fd::directional_derivative(scene, None, &vec![(v, 1.0)], fd_options)?,
            })
        })
        .collect::<Result<_>>()?;
    if let Some((lo, hi)) = fd::domain_bounds(grid) {
        let domain = fd::box_voxels(grid, lo, hi, false);
        let ones = FdOptions {
            eps: ones_eps(scene),
            ..*fd_options
        };
        checks.push(Check {
            name: format!("⟨g, 1⟩ over the domain (ε = {:.3e})", ones.eps),
            estimate: r.mean.sum(),
            estimate_se: r.sum_se,
            fd: fd::directional_derivative(scene, None, &fd::ones(&domain), &ones)?,
        });
    }
    Ok(checks)
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
    let bar = crate::progress::bar(o.progress, o.budget.as_millis() as u64, what);
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
        let name = estimator_name(estimator);
        let bar = budget_bar(o, name);
        rows.extend(sweep(o.budget, o.max_spp, &bar, |spp| {
            let seed = o.seed.wrapping_add(SWEEP_SEED_OFFSET + spp as u64);
            let run = gradient(
                scene,
                &adjoint,
                &grad_options(estimator, spp, seed, o.max_depth),
            );
            let seconds = run.stats.wall.as_secs_f64();
            score(name, spp, seconds, &run.gradient, r, &scene.medium.grid)
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
    let bar = crate::progress::bar(progress, seeds as u64, "image ref");
    let images: Vec<RgbImage> = (0..seeds)
        .map(|s| {
            let options = RenderOptions {
                spp,
                seed: seed.wrapping_add(REFERENCE_SEED_OFFSET + s as u64),
                max_depth,
                progress: false,
            };
            let image = render(scene, &options).0;
            bar.inc(1);
            image
        })
        .collect();
    bar.finish_and_clear();
    let mut mean = RgbImage::new(scene.camera.width, scene.camera.height);
    let mut variance_sum = 0.0;
    for i in 0..mean.pixels.len() {
        for c in 0..3 {
            let values: Vec<f64> = images.iter().map(|im| im.pixels[i][c] as f64).collect();
            let (m, se) = mean_and_se(&values);
            mean.pixels[i][c] = m as f32;
            variance_sum += se * se;
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
        (RENDER_GRID, MajorantMode::Grid { cell_voxels: cell }),
        (RENDER_GLOBAL, MajorantMode::Global),
    ] {
        let mut s = scene.clone();
        s.set_majorant(mode);
        let bar = budget_bar(
            o,
            if mode == MajorantMode::Global {
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

pub fn csv(rows: &[Row]) -> String {
    let mut s = String::from(
        "estimator,spp,seconds,rel_rmse,empty_rmse,cosine,bias,bias_se,rel_rmse_raw\n",
    );
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{:.6},{},{},{},{},{},{}",
            r.method,
            r.spp,
            r.seconds,
            cell(r.rel_rmse),
            cell(r.empty_rmse),
            cell(r.cosine),
            cell(r.bias),
            cell(r.bias_se),
            cell(r.rel_rmse_raw)
        );
    }
    s
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

/// How many times less time `contender` needs than `baseline` to reach `baseline`'s final error
/// (both read off their measured curves), or None if either curve is missing.
pub fn speedup(rows: &[Row], baseline: &str, contender: &str) -> Option<(f64, f64, f64, bool)> {
    let b = points(&curve(rows, baseline));
    let c = points(&curve(rows, contender));
    let &(tb, target) = b.last()?;
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
    let mut s = String::new();
    let gradients = rows.iter().any(|r| r.cosine.is_finite());
    let _ = writeln!(s, "#### {what}: final runs\n");
    if gradients {
        s += "| estimator | spp | time (s) | rel. RMSE | rel. RMSE (raw) | empty-voxel RMSE | cosine | bias ± se |\n|---|---:|---:|---:|---:|---:|---:|---:|\n";
    } else {
        s += "| method | spp | time (s) | rel. RMSE | rel. RMSE (raw) |\n|---|---:|---:|---:|---:|\n";
    }
    for m in methods {
        if let Some(r) = rows.iter().filter(|r| &r.method == m).last() {
            if gradients {
                let _ = writeln!(
                    s,
                    "| {m} | {} | {:.2} | {:.4} | {:.4} | {:.3e} | {:.4} | {:.2e} ± {:.1e} |",
                    r.spp,
                    r.seconds,
                    r.rel_rmse,
                    r.rel_rmse_raw,
                    r.empty_rmse,
                    r.cosine,
                    r.bias,
                    r.bias_se
                );
            } else {
                let _ = writeln!(
                    s,
                    "| {m} | {} | {:.2} | {:.4} | {:.4} |",
                    r.spp, r.seconds, r.rel_rmse, r.rel_rmse_raw
                );
            }
        }
    }
    let curves: Vec<(&str, Vec<(f64, f64)>)> = methods
        .iter()
        .map(|m| (*m, points(&curve(rows, m))))
        .filter(|(_, p)| !p.is_empty())
        .collect();
    let equal_time = curves
        .iter()
        .map(|(_, p)| p.last().unwrap().0)
        .fold(f64::INFINITY, f64::min);
    let target = curves
        .iter()
        .find(|(m, _)| *m == baseline)
        .and_then(|(_, p)| p.last().map(|l| l.1));
    if equal_time.is_finite() {
        let _ = writeln!(
            s,
            "\n#### {what}: equal time\n\n| method | rel. RMSE at {equal_time:.2} s | time to rel. RMSE {} (s) |\n|---|---:|---:|",
            target.map_or("—".into(), |t| format!("{t:.4}"))
        );
        for (m, p) in &curves {
            let at = error_at(p, equal_time).map_or("—".into(), |(e, x)| approx(e, x));
            let reach = target
                .and_then(|t| time_to_reach(p, t))
                .map_or("—".into(), |(t, x)| approx(t, x));
            let _ = writeln!(s, "| {m} | {at} | {reach} |");
        }
        s += "\n(~ marks values extrapolated along error ∝ 1/√time beyond the measured runs.)\n";
    }
    let _ = writeln!(
        s,
        "\n| method | error² × time (median over runs ≥ {EFFICIENCY_MIN_SPP} spp) | relative to {baseline} |\n|---|---:|---:|"
    );
    let base = inefficiency(rows, baseline);
    for m in methods {
        if let Some(e) = inefficiency(rows, m) {
            let rel = base.map_or("—".into(), |b| format!("{:.3}", e / b));
            let _ = writeln!(s, "| {m} | {e:.4e} | {rel} |");
        }
    }
    match speedup(rows, baseline, contender) {
        Some((factor, target, t, extrapolated)) => {
            let _ = writeln!(
                s,
                "\n**{contender} reaches {baseline}'s final error ({target:.4}) in {factor:.3}× the time** ({}{t:.2} s instead of {:.2} s; speed-up {:.2}×).",
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
        crate::chart::to_svg(chart)?,
    )
    .with_context(|| format!("writing {stem}.svg in '{}'", dir.display()))?;
    if !crate::chart::write_png(chart, &dir.join(format!("{stem}.png")))? {
        eprintln!(
            "warning: no TTF font found (install fonts-dejavu-core or set VOLGRAD_FONT): {stem}.png has no labels; {stem}.svg has them"
        );
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// The stability suite

pub struct StabilityScene {
    pub name: &'static str,
    /// What it is built to break.
    pub purpose: &'static str,
    pub scene: Scene,
}

const SUITE_N: i32 = 6;

/// A 6³ block seen by an 8×8 camera under a sky and a sun, with the given medium.
fn suite_scene(
    grid: BrickMap,
    transform: IndexTransform,
    density_scale: f32,
    albedo: f32,
    g: f32,
    filter: Filter,
) -> Scene {
    let mut medium = Medium::new(
        grid,
        transform,
        density_scale,
        filter,
        MajorantMode::Grid { cell_voxels: 4 },
    );
    medium.albedo = Vec3::splat(albedo);
    medium.phase_g = g;
    let mut lights = Lights {
        environment: Environment {
            constant: Vec3::new(0.8, 0.9, 1.0),
            map: None,
        },
        ..Lights::default()
    };
    lights.directional.push(DirectionalLight {
        to_light: Vec3::new(0.4, 1.0, 0.3).normalize(),
        irradiance: Vec3::splat(2.0),
    });
    let settings = RenderFile {
        max_depth: 16,
        ..RenderFile::default()
    };
    Scene {
        path: "stability.toml".into(),
        camera: Camera::new(Vec3::new(0.0, 0.0, 14.0), Vec3::ZERO, Vec3::Y, 35.0, 8, 8),
        medium,
        lights,
        settings,
        grid_name: "density".into(),
        vdb_path: "stability.vdb".into(),
    }
}

fn block(f: impl Fn(IVec3) -> f32) -> BrickMap {
    let mut b = BrickMapBuilder::new();
    for x in 0..SUITE_N {
        for y in 0..SUITE_N {
            for z in 0..SUITE_N {
                let v = IVec3::new(x, y, z);
                b.set(v, f(v), true);
            }
        }
    }
    b.build()
}

fn lumpy(v: IVec3) -> f32 {
    0.6 + 0.4 * ((v.x as f32 * 1.3).sin() * (v.y as f32 * 0.8 + v.z as f32).cos())
}

fn centred(linear: DMat3) -> IndexTransform {
    let centre = DVec3::splat((SUITE_N - 1) as f64 * 0.5);
    IndexTransform::new(glam::DAffine3::from_mat3_translation(
        linear,
        -(linear * centre),
    ))
    .expect("an invertible transform")
}

/// Scenes built to break estimators. Optical depths are across the 6-voxel block.
pub fn stability_scenes() -> Vec<StabilityScene> {
    let unit = || centred(DMat3::IDENTITY);
    let n = SUITE_N as f32;
    vec![
        StabilityScene {
            name: "empty-voxels",
            purpose: "a quarter of the voxels inside the bounds are empty, nearest lookups so that σt = 0 there (naive misses their scattering part)",
            scene: suite_scene(
                block(|v| if (v.x + 2 * v.y + v.z) % 4 == 0 { 0.0 } else { lumpy(v) }),
                unit(),
                0.5,
                0.9,
                0.3,
                Filter::Nearest,
            ),
        },
        StabilityScene {
            name: "thin",
            purpose: "τ ≈ 0.04: almost every path escapes (naive's 1/σt weights explode)",
            scene: suite_scene(block(|_| 1.0), unit(), 0.04 / n, 0.9, 0.3, Filter::Trilinear),
        },
        StabilityScene {
            name: "dense",
            purpose: "τ ≈ 96: exp underflow, long walks, h(s) − h(t) cancels",
            scene: suite_scene(block(|_| 1.0), unit(), 96.0 / n, 0.9, 0.3, Filter::Trilinear),
        },
        StabilityScene {
            name: "albedo-0.999",
            purpose: "albedo near 1: long paths carry the gradient",
            scene: suite_scene(block(lumpy), unit(), 0.5, 0.999, 0.3, Filter::Trilinear),
        },
        StabilityScene {
            name: "albedo-0.01",
            purpose: "albedo near 0: almost pure absorption",
            scene: suite_scene(block(lumpy), unit(), 0.5, 0.01, 0.3, Filter::Trilinear),
        },
        StabilityScene {
            name: "hot-voxel",
            purpose: "one voxel 1000× its neighbours: the majorant is loose everywhere around it",
            scene: suite_scene(
                block(|v| if v == IVec3::new(2, 3, 2) { 50.0 } else { 0.05 }),
                unit(),
                1.0,
                0.9,
                0.3,
                Filter::Trilinear,
            ),
        },
        StabilityScene {
            name: "rotated-anisotropic",
            purpose: "rotated index space with voxels 1.4 × 0.7 × 1.0: distances converted per axis",
            scene: suite_scene(
                block(lumpy),
                centred(
                    DMat3::from_rotation_y(0.6)
                        * DMat3::from_rotation_x(0.4)
                        * DMat3::from_diagonal(DVec3::new(1.4, 0.7, 1.0)),
                ),
                0.5,
                0.9,
                0.3,
                Filter::Trilinear,
            ),
        },
        StabilityScene {
            name: "forward-g0.95",
            purpose: "strong forward scattering (g = 0.95): peaked phase function",
            scene: suite_scene(block(lumpy), unit(), 0.5, 0.9, 0.95, Filter::Trilinear),
        },
    ]
}

#[derive(Debug, Clone, Copy)]
pub struct StabilityOptions {
    /// Independent runs per estimator (seed, seed + 1, …) for the standard error.
    pub runs: u32,
    pub spp: u32,
    pub fd_spp: u32,
    pub fd_repeats: u32,
    pub seed: u64,
    pub max_depth: u32,
    pub progress: bool,
}

#[derive(Debug, Clone)]
pub struct StabilityRow {
    pub scene: String,
    pub estimator: String,
    /// "all voxels" (⟨g, 1⟩ over the domain) or "empty voxels" (⟨g, 1⟩ over the empty ones).
    pub check: String,
    pub estimate: f64,
    pub estimate_se: f64,
    pub fd: FdResult,
    /// Standard deviation of one run's ⟨g, ·⟩ relative to |fd|: the variance a user sees.
    pub relative_sd: f64,
    /// Non-finite voxel values over all runs (there must be none).
    pub non_finite: usize,
    /// A failure the design predicts (naive in empty voxels, naive in thin media).
    pub expected_failure: bool,
}

/// |z| below which a check counts as unbiased.
pub const STABILITY_Z: f64 = 4.0;

impl StabilityRow {
    pub fn z(&self) -> f64 {
        Check {
            name: String::new(),
            estimate: self.estimate,
            estimate_se: self.estimate_se,
            fd: self.fd,
        }
        .z()
    }

    pub fn unbiased(&self) -> bool {
        self.z().abs() < STABILITY_Z
    }

    /// Finite differences too noisy to tell a biased estimator (se above half the value).
    pub fn weak(&self) -> bool {
        !(self.fd.std_err < 0.5 * self.fd.value.abs())
    }
}

/// The fd step: 0.2 optical depth across the block, so that the step means the same from τ = 0.04
/// to τ = 96 (a step in grid units would be far too big in dense media and lost in noise in thin
/// ones). At 0.5 the one-sided stencil's truncation error was 3% in the absorbing scene (z ≈ −3
/// for every estimator); at 0.1 the empty-voxel check drowned in noise.
fn suite_eps(scene: &Scene) -> f32 {
    FD_OPTICAL_STEP / (scene.medium.density_scale * SUITE_N as f32)
}

const FD_OPTICAL_STEP: f32 = 0.2;

/// Runs every estimator on `scenes` and compares ⟨g, 1⟩ (all voxels, and the empty ones if any)
/// with finite differences.
pub fn stability(
    scenes: &[StabilityScene],
    estimators: &[Estimator],
    o: &StabilityOptions,
) -> Result<Vec<StabilityRow>> {
    let mut rows = Vec::new();
    let bar = crate::progress::bar(
        o.progress,
        (scenes.len() * (estimators.len() + 1)) as u64,
        "stability",
    );
    for s in scenes {
        let scene = &s.scene;
        let grid = &scene.medium.grid;
        let Some((lo, hi)) = fd::domain_bounds(grid) else {
            continue;
        };
        let all = fd::box_voxels(grid, lo, hi, false);
        let empty: Vec<IVec3> = all
            .iter()
            .copied()
            .filter(|&v| grid.is_active(v) && grid.voxel(v) == 0.0)
            .collect();
        let fd_options = FdOptions {
            loss: Loss::Mean,
            eps: suite_eps(scene),
            spp: o.fd_spp,
            repeats: o.fd_repeats,
            seed: o.seed,
            max_depth: o.max_depth,
        };
        let has_empty = !empty.is_empty();
        let mut checks = vec![("all voxels", all.clone())];
        if has_empty {
            checks.push(("empty voxels", empty));
        }
        let fds = checks
            .iter()
            .map(|(_, voxels)| {
                fd::directional_derivative(scene, None, &fd::ones(voxels), &fd_options)
            })
            .collect::<Result<Vec<FdResult>>>()?;
        bar.inc(1);
        let adjoint = mean_adjoint(scene);
        for &estimator in estimators {
            let mut non_finite = 0;
            let mut sums = vec![Vec::new(); checks.len()];
            for r in 0..o.runs.max(2) {
                let seed = o.seed.wrapping_add(SWEEP_SEED_OFFSET + r as u64);
                let g = gradient(
                    scene,
                    &adjoint,
                    &grad_options(estimator, o.spp, seed, o.max_depth),
                )
                .gradient;
                non_finite += g.voxels().filter(|(_, x)| !x.is_finite()).count();
                for (k, (_, voxels)) in checks.iter().enumerate() {
                    sums[k].push(voxels.iter().map(|&v| g.get(v)).sum::<f64>());
                }
            }
            for (k, (check, _)) in checks.iter().enumerate() {
                let (mean, se) = mean_and_se(&sums[k]);
                let fd = fds[k];
                let naive = estimator == Estimator::Naive;
                rows.push(StabilityRow {
                    scene: s.name.into(),
                    estimator: estimator_name(estimator).into(),
                    check: (*check).into(),
                    estimate: mean,
                    estimate_se: se,
                    fd,
                    relative_sd: se * (sums[k].len() as f64).sqrt() / fd.value.abs().max(1e-300),
                    non_finite,
                    expected_failure: naive && (has_empty || s.name == "thin"),
                });
            }
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    Ok(rows)
}

pub fn stability_csv(rows: &[StabilityRow]) -> String {
    let mut s = String::from("scene,estimator,check,estimate,estimate_se,fd,fd_se,z,unbiased,relative_sd,non_finite,expected_failure\n");
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{:.6e},{:.6e},{:.6e},{:.6e},{:.3},{},{:.4e},{},{}",
            r.scene,
            r.estimator,
            r.check,
            r.estimate,
            r.estimate_se,
            r.fd.value,
            r.fd.std_err,
            r.z(),
            r.unbiased(),
            r.relative_sd,
            r.non_finite,
            r.expected_failure
        );
    }
    s
}

pub fn stability_markdown(
    scenes: &[StabilityScene],
    rows: &[StabilityRow],
    o: &StabilityOptions,
) -> String {
    let mut s = format!(
        "Each estimator: {} runs × {} spp on an 8×8 image of a 6³ grid (trilinear lookups, nearest in empty-voxels); finite differences: {} spp × {} repeats, step {FD_OPTICAL_STEP} optical depth across the block. A check passes when |z| < {STABILITY_Z}.\n\n",
        o.runs.max(2), o.spp, o.fd_spp, o.fd_repeats.max(2)
    );
    s += "| scene | estimator | ⟨g, 1⟩ over | estimate ± se | fd ± se | z | verdict | sd per run / \\|fd\\| | non-finite |\n|---|---|---|---:|---:|---:|---|---:|---:|\n";
    for r in rows {
        let verdict = match (r.unbiased(), r.expected_failure) {
            (true, _) if r.weak() => "ok (weak check: fd noisy)",
            (true, _) => "ok",
            (false, true) => "**biased (expected)**",
            (false, false) => "**BIASED**",
        };
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.4e} ± {:.1e} | {:.4e} ± {:.1e} | {:.2} | {verdict} | {:.3} | {} |",
            r.scene,
            r.estimator,
            r.check,
            r.estimate,
            r.estimate_se,
            r.fd.value,
            r.fd.std_err,
            r.z(),
            r.relative_sd,
            r.non_finite
        );
    }
    s += "\n| scene | built to break |\n|---|---|\n";
    for sc in scenes {
        let _ = writeln!(s, "| {} | {} |", sc.name, sc.purpose);
    }
    s
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
        let rows = [
            row("drt", 2.0, 1.0),
            row("drt", 8.0, 0.5),
            row("joint", 1.0, 0.7071067811865476),
            row("joint", 4.0, 0.3535533905932738),
        ];
        let (factor, target, t, extrapolated) = speedup(&rows, "drt", "joint").unwrap();
        assert!((factor - 0.25).abs() < 1e-9, "{factor}");
        assert_eq!(target, 0.5);
        assert!((t - 2.0).abs() < 1e-9 && !extrapolated);
        assert!(speedup(&rows, "drt", "naive").is_none());
    }
}

/// How long something took, for messages.
pub fn timed<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let start = Instant::now();
    let v = f();
    (v, start.elapsed().as_secs_f64())
}
