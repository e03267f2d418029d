//! `cargo bench --bench scaling`: how the renderer and the joint gradient grow with the grid.
//!
//! The Disney cloud ships at 1/16 of its published resolution. This bench writes (to a temporary
//! folder, never the repo) the cloud upsampled 2× and 4× per axis (`volume::upsample`: ×8 and ×64
//! the voxels, the same world box, so the same optical depths) and the cloud with one far speck of
//! density 20,000 voxels away (a mostly empty bounding box), then measures each against the 1/16
//! cloud at the default scene's image size and spp, in one run:
//!
//! - load: reading the VDB through the bridge and building brick map and majorant, per GiB of leaf
//!   data (best of two);
//! - memory of the brick map and the majorant;
//! - forward paths/s and density lookups per path;
//! - a joint gradient pass: its time against the forward render, and its gradient grid's memory
//!   against the brick map's (and, in a second table, how many of its stored voxels are non-zero);
//! - the load's parts: the bridge's read (and, for comparison, the same read through OpenVDB's own
//!   reader, as before the bridge decoded buffers in parallel), the value checks and brick map, the
//!   majorant;
//! - peak resident memory of `volgrad render` and `volgrad grad` on the same scene, each run as a
//!   child process that reports its own high-water mark (`--stats`).
//!
//! VOLGRAD_BENCH_SPP (default 4) and VOLGRAD_BENCH_FACTORS (default "1,2,4") adjust it;
//! VOLGRAD_BENCH_GRIDS=DIR writes the grids and scenes into DIR and keeps them (a grid already
//! there is reused), e.g. to time `volgrad render DIR/scene2.toml --stats` on its own.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use glam::IVec3;
use volgrad::gradient::adjoint::Estimator;
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{gradient, GradOptions};
use volgrad::io::bridge::ffi;
use volgrad::io::images::RgbImage;
use volgrad::io::vdb::{self, GridSelector, LevelSet};
use volgrad::render::image::{render, RenderOptions};
use volgrad::render::scene::Scene;
use volgrad::volume::brickmap::{BrickMap, Leaf, BRICK_VOXELS};
use volgrad::volume::majorant::{Majorant, MajorantGrid};
use volgrad::volume::transform::IndexTransform;
use volgrad::volume::upsample::upsample;

const MIB: f64 = (1 << 20) as f64;

/// The peak resident memory (MiB) that `volgrad args… --stats` reports for itself: a child
/// process's own high-water mark (wait4's ru_maxrss would include this process's, which the child
/// inherits at exec).
fn child_peak_mib(args: &[&str]) -> f64 {
    let output = Command::new(env!("CARGO_BIN_EXE_volgrad"))
        .args(args)
        .arg("--stats")
        .stderr(Stdio::null())
        .output()
        .expect("volgrad starts");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "volgrad {args:?} failed");
    let line = stdout
        .lines()
        .find_map(|l| l.strip_prefix("peak memory"))
        .expect("--stats reports the peak memory (Linux)");
    let mut words = line.split_whitespace();
    let (value, unit) = (words.next().unwrap(), words.next().unwrap());
    let value: f64 = value.parse().expect("a number");
    if unit == "MiB" {
        value
    } else {
        value / 1024.0
    }
}

/// The scene file `cloud.toml` with its medium read from `vdb` (absolute), written into `dir`.
fn scene_for(dir: &Path, name: &str, vdb: &Path, template: &str) -> PathBuf {
    let text: String = template
        .lines()
        .map(|line| {
            if line.trim_start().starts_with("vdb") {
                format!("vdb = {:?}", vdb.display().to_string())
            } else {
                line.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, text).expect("scene written");
    path
}

/// A grid named and classed like `source`, holding `bricks`.
fn like(source: &vdb::Grid, bricks: BrickMap, transform: IndexTransform) -> vdb::Grid {
    vdb::Grid {
        name: source.name.clone(),
        grid_class: source.grid_class.clone(),
        transform,
        bricks,
        background: 0.0,
        saved_as_half: false,
        metadata: Vec::new(),
    }
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let spp: u32 = std::env::var("VOLGRAD_BENCH_SPP")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(4);
    let mut factors: Vec<u32> = std::env::var("VOLGRAD_BENCH_FACTORS")
        .unwrap_or("1,2,4".into())
        .split(',')
        .map(|s| s.trim().parse().expect("factors are integers ≥ 1"))
        .filter(|&f| f != 1)
        .collect();
    // The 1/16 cloud is always measured, first: every ratio is against it.
    factors.insert(0, 1);
    let template =
        std::fs::read_to_string(root.join("scenes/cloud.toml")).expect("cloud scene reads");
    let source = root.join("scenes/assets/wdas_cloud_sixteenth.vdb");
    let cloud =
        vdb::read_density(&source, &GridSelector::Default, LevelSet::Refuse).expect("cloud reads");
    let temporary = tempfile::tempdir().expect("temporary folder");
    let kept = std::env::var_os("VOLGRAD_BENCH_GRIDS").map(PathBuf::from);
    if let Some(kept) = &kept {
        std::fs::create_dir_all(kept).expect("VOLGRAD_BENCH_GRIDS can be created");
    }
    let dir = kept.as_deref().unwrap_or(temporary.path());

    // The grids: the cloud upsampled, and the cloud with a far speck.
    let mut cases: Vec<(String, PathBuf)> = Vec::new();
    for &f in &factors {
        if f == 1 {
            cases.push(("cloud (1/16 resolution)".into(), source.clone()));
            continue;
        }
        let path = dir.join(format!("cloud-x{f}.vdb"));
        if path.exists() {
            cases.push((format!("cloud ×{f} per axis"), path));
            continue;
        }
        let start = Instant::now();
        let (bricks, transform) =
            upsample(&cloud.bricks, &cloud.transform, f).expect("upsampling fits");
        let grid = like(&cloud, bricks, transform);
        vdb::write_grids(&path, &[&grid], false, true).expect("grid written");
        eprintln!(
            "cloud ×{f}: {} leaves, written in {:.1} s",
            grid.bricks.leaves().len(),
            start.elapsed().as_secs_f64()
        );
        cases.push((format!("cloud ×{f} per axis"), path));
    }
    {
        let (lo, _) = cloud.bricks.active_bounds().expect("the cloud has voxels");
        let mut leaves = cloud.bricks.leaves().to_vec();
        let mut speck = Leaf {
            origin: (lo + IVec3::new(20_000, 0, 0)) & !7,
            values: [0.0; BRICK_VOXELS],
            active: [0; 8],
        };
        speck.values[0] = 1.0;
        speck.active[0] = 1;
        leaves.push(speck);
        let grid = like(
            &cloud,
            BrickMap::new(leaves, cloud.bricks.tiles().to_vec()),
            cloud.transform,
        );
        let path = dir.join("cloud-speck.vdb");
        vdb::write_grids(&path, &[&grid], false, true).expect("grid written");
        cases.push(("cloud + speck 20,000 voxels away".into(), path));
    }

    println!(
        "scene scenes/cloud.toml with each grid, {spp} spp, {} threads\n",
        rayon::current_num_threads()
    );
    println!(
        "| grid | active voxels | leaf data | load | brick map | majorant | paths/s | lookups/path | joint ÷ forward | gradient grid | peak render | peak grad |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut base_pps = None;
    let mut parts = Vec::new();
    for (i, (name, vdb_path)) in cases.iter().enumerate() {
        let scene_path = scene_for(dir, &format!("scene{i}"), vdb_path, &template);
        let mut load = f64::MAX;
        let mut scene = None;
        for _ in 0..2 {
            let start = Instant::now();
            let s = Scene::load(&scene_path).expect("scene loads");
            load = load.min(start.elapsed().as_secs_f64());
            scene = Some(s);
        }
        let scene = scene.expect("loaded");
        let grid = &scene.medium.grid;
        let leaf_bytes = (grid.leaves().len() * BRICK_VOXELS * 4) as f64;
        let options = RenderOptions {
            spp,
            seed: 1,
            max_depth: scene.settings.max_depth,
            progress: false,
        };
        let forward = render(&scene, &options).1;
        let pps = forward.paths_per_second();
        let base = *base_pps.get_or_insert(pps);
        let (w, h) = (scene.camera.width, scene.camera.height);
        let adjoint = Loss::Mean.adjoint(&RgbImage::new(w, h), None);
        let run = gradient(
            &scene,
            &adjoint,
            &GradOptions::new(Estimator::Joint, spp, 1, scene.settings.max_depth),
        );
        let spp_arg = spp.to_string();
        let scene_arg = scene_path.to_str().expect("utf-8 temp path");
        let exr = dir.join(format!("render{i}.exr"));
        let peak_render = child_peak_mib(&[
            "render",
            scene_arg,
            "--spp",
            &spp_arg,
            "-o",
            exr.to_str().unwrap(),
            "--force",
        ]);
        let out = dir.join(format!("grad{i}.vdb"));
        let peak_grad = child_peak_mib(&[
            "grad",
            scene_arg,
            "--estimator",
            "joint",
            "--spp",
            &spp_arg,
            "-o",
            out.to_str().unwrap(),
            "--force",
        ]);
        let (openvdb, bridge, from_data, majorant) = load_parts(vdb_path, &scene);
        let stored = run.gradient.block_count() * 64;
        let nonzero = run
            .gradient
            .voxels()
            .iter()
            .filter(|&&(_, g)| g != 0.0)
            .count();
        parts.push(format!(
            "| {name} | {openvdb:.3} s | {bridge:.3} s | {from_data:.3} s | {majorant:.3} s | {nonzero} of {stored} ({:.0} %) |",
            100.0 * nonzero as f64 / stored.max(1) as f64
        ));
        let brick_map = grid.memory_bytes() as f64;
        println!(
            "| {name} | {} | {:.1} MiB | {:.2} s ({:.2} s/GiB) | {:.1} MiB ({:.3}× leaf data) | {:.2} MiB | {pps:.0} ({:.2}×) | {:.1} | {:.2}× | {:.1} MiB ({:.2}× brick map) | {:.0} MiB | {:.0} MiB |",
            grid.active_voxel_count(),
            leaf_bytes / MIB,
            load,
            load / (leaf_bytes / (1u64 << 30) as f64),
            brick_map / MIB,
            brick_map / leaf_bytes,
            scene.medium.majorant.memory_bytes() as f64 / MIB,
            pps / base,
            forward.lookups_per_path(),
            run.stats.wall.as_secs_f64() / forward.wall.as_secs_f64(),
            run.gradient.memory_bytes() as f64 / MIB,
            run.gradient.memory_bytes() as f64 / brick_map,
            peak_render,
            peak_grad,
        );
    }
    println!(
        "\nWhere the load goes (best of two), and how full the joint gradient's 4³ blocks are:\n"
    );
    println!("| grid | OpenVDB's reader and a copy (before) | the bridge: topology, then buffers decoded in parallel | checks and brick map | majorant | gradient voxels ≠ 0 of stored |");
    println!("|---|---:|---:|---:|---:|---:|");
    for row in parts {
        println!("{row}");
    }
}

/// Seconds (best of two) of the three parts of loading `path` as `scene` does: the bridge's read,
/// `Grid::from_data` (value checks and the brick map) and the majorant grid (with its hot spots);
/// first, for comparison, the bridge's read through OpenVDB's own reader (every buffer decoded
/// in turn into its tree, then copied), as it was read before.
fn load_parts(path: &Path, scene: &Scene) -> (f64, f64, f64, f64) {
    let mut best = [f64::MAX; 4];
    let path = path.to_str().expect("utf-8 temp path");
    let threads = rayon::current_num_threads() as u32;
    for _ in 0..2 {
        let start = Instant::now();
        let reference = ffi::read_float_grid_through_openvdb(path, "density", -1, false, threads)
            .expect("grid reads");
        let openvdb = start.elapsed().as_secs_f64();
        drop(reference);
        let start = Instant::now();
        let data = ffi::read_float_grid(path, "density", -1, false, threads).expect("grid reads");
        let bridge = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let grid = vdb::Grid::from_data(data).expect("valid grid");
        let from_data = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let majorant = MajorantGrid::build(
            &grid.bricks,
            scene.medium.bounds,
            scene.medium.density_scale,
            Majorant::grid(scene.settings.majorant_cell),
        )
        .with_hot_spots(&grid.bricks, scene.medium.transform.voxel_diagonal());
        let built = start.elapsed().as_secs_f64();
        assert_eq!(
            majorant.memory_bytes(),
            scene.medium.majorant.memory_bytes()
        );
        for (b, t) in best.iter_mut().zip([openvdb, bridge, from_data, built]) {
            *b = b.min(t);
        }
    }
    (best[0], best[1], best[2], best[3])
}
