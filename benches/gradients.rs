//! `cargo bench --bench gradients`: cost and variance of the gradient estimators on the default
//! scene at equal spp, measured in one run.
//!
//! - time of joint, drt and naive relative to a forward render (runs interleaved, best of
//!   VOLGRAD_BENCH_ROUNDS, so that a noisy neighbour hurts every method alike);
//! - VOLGRAD_BENCH_SUFFIX_PATHS sets the suffix paths per camera path (`grad --suffix-paths`);
//! - per-voxel variance over VOLGRAD_BENCH_SEEDS seeds (mean over the voxels any estimator's run
//!   reached, one count for all), and
//!   variance × time of joint relative to drt (the figure that decides which to use).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use volgrad::gradient::adjoint::{Estimator, DEFAULT_SUFFIX_PATHS};
use volgrad::gradient::grid::GradientGrid;
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{gradient, GradOptions};
use volgrad::io::images::RgbImage;
use volgrad::render::image::{render, RenderOptions};
use volgrad::render::scene::Scene;

fn env(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let path = std::env::var("VOLGRAD_BENCH_SCENE")
        .map(PathBuf::from)
        .unwrap_or(root.join("scenes/cloud.toml"));
    let spp = env("VOLGRAD_BENCH_SPP", 4) as u32;
    let rounds = env("VOLGRAD_BENCH_ROUNDS", 3).max(1);
    let seeds = env("VOLGRAD_BENCH_SEEDS", 6).max(2); // a variance needs two
    let scene = Scene::load(&path).expect("bench scene loads");
    let (w, h) = (scene.camera.width, scene.camera.height);
    let adjoint = Loss::Mean.adjoint(&RgbImage::new(w, h), None);
    let suffix_paths = env("VOLGRAD_BENCH_SUFFIX_PATHS", DEFAULT_SUFFIX_PATHS as u64) as u32;
    let options = |estimator, seed| {
        let mut o = GradOptions::new(estimator, spp, seed, scene.settings.max_depth);
        o.adjoint.suffix_paths = suffix_paths;
        o
    };
    let estimators = [Estimator::Joint, Estimator::Drt, Estimator::Naive];
    println!(
        "scene {} at {w}×{h}, {spp} spp, {suffix_paths} suffix paths per camera path, {} threads, loss = mean",
        path.display(),
        rayon::current_num_threads()
    );

    // Time, interleaved: forward, joint, drt, naive, forward, ...
    let mut best = [Duration::MAX; 4];
    for round in 0..rounds {
        let start = Instant::now();
        render(
            &scene,
            &RenderOptions {
                spp,
                seed: round,
                max_depth: scene.settings.max_depth,
                progress: false,
            },
        );
        best[0] = best[0].min(start.elapsed());
        for (i, &e) in estimators.iter().enumerate() {
            let start = Instant::now();
            gradient(&scene, &adjoint, &options(e, round));
            best[i + 1] = best[i + 1].min(start.elapsed());
        }
    }
    println!("\n| pass | best of {rounds} | × forward |");
    println!("|---|---:|---:|");
    for (name, t) in ["forward", "joint", "drt", "naive"].iter().zip(best) {
        println!(
            "| {name} | {:.3} s | {:.2}× |",
            t.as_secs_f64(),
            t.as_secs_f64() / best[0].as_secs_f64()
        );
    }

    // Variance over seeds.
    let mut rows = Vec::new();
    let mut reached = std::collections::HashSet::new();
    for (i, &e) in estimators.iter().enumerate() {
        let runs: Vec<GradientGrid<f32>> = (0..seeds)
            .map(|s| gradient(&scene, &adjoint, &options(e, 1000 + s)).values())
            .collect();
        let mut mean = GradientGrid::<f64>::for_medium(&scene.medium);
        let mut square = mean.empty_like();
        for r in &runs {
            mean.merge(r, 1.0 / seeds as f64);
            for (v, g) in r.voxels() {
                square.add(v, g * g / seeds as f64);
            }
        }
        // Unbiased per-voxel variance: n/(n−1)·(E[g²] − E[g]²), summed here and averaged below
        // over the voxels any estimator reached (one count for all: each estimator's own count
        // would scale its figure by how many voxels it reached).
        let n = seeds as f64;
        let variance = square.voxels().fold(0.0, |sum, (v, g2)| {
            reached.insert(v);
            let m = mean.get(v);
            sum + (g2 - m * m).max(0.0) * n / (n - 1.0)
        });
        let totals: Vec<f64> = runs.iter().map(|r| r.sum()).collect();
        let total_mean = totals.iter().sum::<f64>() / n;
        let total_se =
            (totals.iter().map(|t| (t - total_mean).powi(2)).sum::<f64>() / (n - 1.0) / n).sqrt();
        rows.push((
            e,
            total_mean,
            total_se,
            variance,
            variance * best[i + 1].as_secs_f64(),
        ));
    }
    let voxels = reached.len().max(1) as f64;
    for row in &mut rows {
        (row.3, row.4) = (row.3 / voxels, row.4 / voxels);
    }
    let drt = rows[1].4;
    println!(
        "\n| estimator | ⟨g, 1⟩ (mean ± se) | mean per-voxel variance | variance × time vs drt |"
    );
    println!("|---|---:|---:|---:|");
    for (e, total_mean, total_se, variance, vt) in rows {
        println!(
            "| {e:?} | {total_mean:.4e} ± {total_se:.1e} | {variance:.3e} | {:.3}× |",
            vt / drt
        );
    }
}
