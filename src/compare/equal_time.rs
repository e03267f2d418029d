//! Equal-time sweeps: each method at 1, 2, 4, … spp until its budget is spent, every run scored
//! against the reference (gradients) or against a reference image (the forward renderer).

use std::time::{Duration, Instant};

use glam::{IVec3, Vec3};

use crate::compare::Reference;
use crate::gradient::adjoint::Estimator;
use crate::gradient::fd;
use crate::gradient::grid::GradientGrid;
use crate::gradient::loss::Loss;
use crate::gradient::passes::{gradient, GradOptions};
use crate::gradient::runs::{seeded_runs, MeanAndError};
use crate::io::images::RgbImage;
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
    g: &GradientGrid<f32>,
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
        // Doubling, the last step at the largest spp asked for, not past it.
        spp = spp.saturating_mul(2).min(max_spp);
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
            score(&name, spp, seconds, &run.values(), r, &scene.medium.grid)
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

/// How long something took, for messages.
pub fn timed<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let start = Instant::now();
    let v = f();
    (v, start.elapsed().as_secs_f64())
}
