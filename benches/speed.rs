//! `cargo bench --bench speed`: paths per second and variance × time of `volgrad render` (64 spp)
//! and `volgrad grad` (joint and DRT, 16 spp) on the cloud and the smoke at 128², on 1 and 2
//! threads. With `VOLGRAD_BASELINE=<a volgrad binary>` (speed's baseline: a build of commit
//! 5c81ad2) every command also runs through that binary, interleaved with this build's, and the
//! table gives this build's ratios to it: these machines are shared and noisy, so only ratios
//! measured in one run mean anything. `VOLGRAD_CURRENT=<a volgrad binary>` times that binary in
//! this build's place (a profile-guided build, `scripts/build-pgo.sh`, against a plain one).
//!
//! Variance is measured from two seeds of the same command, E[(A − B)²]/2 per pixel or voxel,
//! averaged over the pixels or summed over the voxels; variance × time compares estimators at
//! equal spp whatever their speed (below 1 is better). `VOLGRAD_BENCH_ROUNDS` (default 2) sets how
//! many times each command runs per seed: the fastest counts; `VOLGRAD_BENCH_ONLY=render` (or
//! `joint`, `drt`) keeps the commands whose name holds it.
//!
//! Then the physical limit: the work no tracker avoids per tentative collision (one trilinear
//! density read at a random point of the grid's leaves, one exponential sample, one uniform draw),
//! timed on one thread, times the density lookups per path `--stats` counts, is the least time a
//! path can take here; each build's one-thread render is given as a fraction of it. The majorant
//! walk's steps are left out, so the limit is optimistic and the fractions are upper bounds.

use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use glam::{IVec3, Vec3};
use rand::{Rng, SeedableRng};

use volgrad::io::images::read_rgb;
use volgrad::io::vdb::{read_grid, GridSelector};
use volgrad::render::scene::Scene;

/// One measured command: its best paths/s, its density lookups per path and the variance of its
/// output between two seeds.
struct Measured {
    paths_per_second: f64,
    lookups_per_path: f64,
    variance: f64,
}

/// What one run's `--stats` report: paths/s and density lookups per path.
struct Stats {
    paths_per_second: f64,
    lookups_per_path: f64,
}

/// A scene file like `scene` at 128² with its grid's path made absolute, in `dir`.
fn bench_scene(root: &Path, scene: &str, dir: &Path) -> PathBuf {
    let path = root.join("scenes").join(scene);
    let text = std::fs::read_to_string(&path).expect("bench scene reads");
    let mut value: toml::Table = toml::from_str(&text).expect("bench scene parses");
    let camera = value["camera"].as_table_mut().expect("a camera");
    camera.insert("width".into(), 128.into());
    camera.insert("height".into(), 128.into());
    let medium = value["medium"].as_table_mut().expect("a medium");
    let vdb = medium["vdb"].as_str().expect("a vdb").to_string();
    let vdb = root.join("scenes").join(vdb);
    medium.insert("vdb".into(), vdb.display().to_string().into());
    let out = dir.join(scene);
    std::fs::write(&out, toml::to_string(&value).expect("toml")).expect("bench scene writes");
    out
}

/// Runs `binary` with `args` and the output `out`; returns what its `--stats` report.
fn run(binary: &Path, args: &[String], out: &Path) -> Stats {
    let output = Command::new(binary)
        .args(args)
        .args(["--stats", "-q", "--force", "-o"])
        .arg(out)
        .output()
        .expect("volgrad runs");
    let text = String::from_utf8_lossy(&output.stdout).into_owned()
        + &String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{binary:?} {args:?}: {text}");
    // "paths/s   832051", "lookups per path   9.06 (2.68 free-flight + 6.38 shadow)".
    let number = |key: &str| -> f64 {
        let line = (text.lines().find(|l| l.starts_with(key)))
            .unwrap_or_else(|| panic!("no {key} in {text}"));
        (line[key.len()..].split_whitespace().next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("{key} is no number: {line}"))
    };
    Stats {
        paths_per_second: number("paths/s"),
        lookups_per_path: number("lookups per path"),
    }
}

/// `VOLGRAD_BENCH_ROUNDS`: how many times each command (and the collision timing) runs; at
/// least 1.
fn rounds() -> usize {
    std::env::var("VOLGRAD_BENCH_ROUNDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(2)
        .max(1)
}

/// Mean of E[(A − B)²]/2 over the pixels (EXR), or its sum over the voxels either grid holds
/// (VDB): which voxels a gradient file holds depends on the run, and a mean over them would scale
/// one build's figure against the other's by their counts.
fn variance(a: &Path, b: &Path) -> f64 {
    let half_square = |x: f32, y: f32| f64::from(x - y).powi(2) / 2.0;
    if a.extension().is_some_and(|e| e == "exr") {
        let (a, b) = (read_rgb(a).expect("exr"), read_rgb(b).expect("exr"));
        let sum: f64 = (a.pixels.iter().zip(&b.pixels))
            .map(|(x, y)| (0..3).map(|c| half_square(x[c], y[c])).sum::<f64>() / 3.0)
            .sum();
        return sum / a.pixels.len() as f64;
    }
    let grid = |p: &Path| read_grid(p, &GridSelector::Index(0)).expect("gradient vdb");
    let (a, b) = (grid(a).bricks, grid(b).bricks);
    let mut voxels = std::collections::HashSet::new();
    for leaf in a.leaves().iter().chain(b.leaves()) {
        for i in 0..512 {
            let local = glam::IVec3::new(i >> 6, (i >> 3) & 7, i & 7);
            voxels.insert(leaf.origin + local);
        }
    }
    voxels
        .iter()
        .map(|&v| half_square(a.voxel(v), b.voxel(v)))
        .sum()
}

/// `args` through each binary, interleaved: per binary, its best paths/s over the rounds and
/// the variance between seeds 1 and 2.
fn measure(binaries: &[&Path], args: &[String], ext: &str, dir: &Path) -> Vec<Measured> {
    let rounds = rounds();
    let mut best = vec![0.0f64; binaries.len()];
    let mut lookups = vec![0.0f64; binaries.len()];
    for round in 0..rounds {
        // Each build first in turn: whatever running first costs or gains falls on both.
        let mut order: Vec<usize> = (0..binaries.len()).collect();
        order.rotate_left(round % binaries.len());
        for k in order {
            let binary = binaries[k];
            for seed in [1, 2] {
                let mut args = args.to_vec();
                args.extend(["--seed".into(), seed.to_string()]);
                let out = dir.join(format!("b{k}-s{seed}-r{round}.{ext}"));
                let stats = run(binary, &args, &out);
                best[k] = best[k].max(stats.paths_per_second);
                lookups[k] = stats.lookups_per_path;
            }
        }
    }
    (0..binaries.len())
        .map(|k| Measured {
            paths_per_second: best[k],
            lookups_per_path: lookups[k],
            variance: variance(
                &dir.join(format!("b{k}-s1-r0.{ext}")),
                &dir.join(format!("b{k}-s2-r0.{ext}")),
            ),
        })
        .collect()
}

/// Seconds per tentative collision's unavoidable work on one thread: a trilinear read of the
/// scene's density at a random point inside its leaves, an Exp(1) sample and a uniform draw.
fn seconds_per_collision(scene: &Scene) -> f64 {
    const N: usize = 1 << 22;
    let mut rng = rand::rngs::SmallRng::seed_from_u64(1);
    let leaves = scene.medium.grid.leaves();
    let points: Vec<Vec3> = (0..N)
        .map(|_| {
            let leaf = &leaves[rng.gen_range(0..leaves.len())];
            let offset = Vec3::new(rng.gen(), rng.gen(), rng.gen()) * 8.0;
            (leaf.origin.as_vec3() + offset).min((leaf.origin + IVec3::splat(8)).as_vec3())
        })
        .collect();
    let start = Instant::now();
    let mut sum = 0.0f32;
    for &p in &points {
        sum += scene.medium.sigma_t(black_box(p));
    }
    black_box(sum);
    let lookup = start.elapsed().as_secs_f64() / N as f64;
    let start = Instant::now();
    let mut sum = 0.0f32;
    for _ in 0..N {
        // The acceptance draw and the next step's exponential sample.
        sum += rng.gen::<f32>() - (1.0 - rng.gen::<f32>()).ln();
    }
    black_box(sum);
    lookup + start.elapsed().as_secs_f64() / N as f64
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let current = std::env::var("VOLGRAD_CURRENT")
        .map(PathBuf::from)
        .unwrap_or_else(|_| PathBuf::from(env!("CARGO_BIN_EXE_volgrad")));
    let baseline = std::env::var("VOLGRAD_BASELINE").ok().map(PathBuf::from);
    let dir = tempfile::tempdir().expect("temp dir");
    let mut binaries = vec![current.as_path()];
    binaries.extend(baseline.as_deref());
    println!("| scene | command | threads | paths/s | variance × time | paths/s vs baseline | variance × time vs baseline |");
    println!("|---|---|---:|---:|---:|---:|---:|");
    // Per scene, the one-thread renders (this build's, then the baseline's), for the limit.
    let mut one_thread_renders = Vec::new();
    for scene in ["cloud.toml", "smoke.toml"] {
        let file = bench_scene(&root, scene, dir.path()).display().to_string();
        let commands: [(&str, Vec<&str>, &str); 3] = [
            ("render 64 spp", vec!["render", &file, "--spp", "64"], "exr"),
            (
                "grad joint 16 spp",
                vec!["grad", &file, "--loss", "mean", "--spp", "16"],
                "vdb",
            ),
            (
                "grad drt 16 spp",
                vec![
                    "grad",
                    &file,
                    "--loss",
                    "mean",
                    "--spp",
                    "16",
                    "--estimator",
                    "drt",
                ],
                "vdb",
            ),
        ];
        let only = std::env::var("VOLGRAD_BENCH_ONLY").unwrap_or_default();
        for (name, args, ext) in commands.iter().filter(|c| c.0.contains(&only)) {
            for threads in [1, 2] {
                let mut args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
                args.extend(["--threads".into(), threads.to_string()]);
                let m = measure(&binaries, &args, ext, dir.path());
                if name.starts_with("render") && threads == 1 {
                    one_thread_renders.push((
                        scene,
                        m.iter()
                            .map(|m| (m.paths_per_second, m.lookups_per_path))
                            .collect::<Vec<_>>(),
                    ));
                }
                // Variance × time per path, relative units: variance / (paths/s).
                let cost = |m: &Measured| m.variance / m.paths_per_second;
                let (speed, cost_ratio) = match m.get(1) {
                    Some(b) => (
                        format!("{:.2}×", m[0].paths_per_second / b.paths_per_second),
                        format!("{:.2}×", cost(&m[0]) / cost(b)),
                    ),
                    None => ("".into(), "".into()),
                };
                println!(
                    "| {scene} | {name} | {threads} | {:.0} | {:.3e} | {speed} | {cost_ratio} |",
                    m[0].paths_per_second,
                    cost(&m[0]),
                );
            }
        }
    }
    println!();
    println!("| scene | ns per collision | build | lookups/path | limit paths/s (1 thread) | render paths/s (1 thread) | fraction of the limit |");
    println!("|---|---:|---|---:|---:|---:|---:|");
    for (scene, measured) in one_thread_renders {
        let loaded = Scene::load(&root.join("scenes").join(scene)).expect("bench scene loads");
        // The fastest of the rounds, as for the renders: one timing wanders by 2× between runs.
        let collision = (0..rounds())
            .map(|_| seconds_per_collision(&loaded))
            .fold(f64::INFINITY, f64::min);
        for ((paths_per_second, lookups), build) in measured.into_iter().zip(["this", "baseline"]) {
            let limit = 1.0 / (lookups * collision);
            println!(
                "| {scene} | {:.1} | {build} | {lookups:.2} | {limit:.0} | {paths_per_second:.0} | {:.2} |",
                collision * 1e9,
                paths_per_second / limit
            );
        }
    }
}
