//! `cargo bench`: forward-rendering speed of the default scene at equal spp, majorant grid against
//! one global majorant, measured in one run (report ratios: these machines are shared and noisy).
//!
//! VOLGRAD_BENCH_SPP (default 4) and VOLGRAD_BENCH_SCENE (default scenes/cloud.toml) adjust it.

use std::path::PathBuf;

use volgrad::render::image::{render, RenderOptions, RenderStats};
use volgrad::render::scene::Scene;
use volgrad::volume::majorant::Majorant;

fn run(scene: &mut Scene, mode: Majorant, spp: u32) -> RenderStats {
    scene.set_majorant(mode);
    let options = RenderOptions {
        spp,
        seed: 1,
        max_depth: scene.settings.max_depth,
        progress: false,
    };
    render(scene, &options).1
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let path = std::env::var("VOLGRAD_BENCH_SCENE")
        .map(PathBuf::from)
        .unwrap_or(root.join("scenes/cloud.toml"));
    let spp: u32 = std::env::var("VOLGRAD_BENCH_SPP")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(4);
    let mut scene = Scene::load(&path).expect("bench scene loads");
    println!(
        "scene {} at {}×{}, {spp} spp, {} threads",
        path.display(),
        scene.camera.width,
        scene.camera.height,
        rayon::current_num_threads()
    );
    println!("| majorant | paths/s | lookups/path | tracking efficiency | speed vs global |");
    println!("|---|---:|---:|---:|---:|");
    // Global first, then the grids, interleaved with a second global run to expose drift.
    let modes = [
        ("global", Majorant::global()),
        ("grid 4³", Majorant::grid(4)),
        ("grid 8³", Majorant::grid(8)),
        ("grid 16³", Majorant::grid(16)),
        ("global (again)", Majorant::global()),
    ];
    let mut global = None;
    for (name, mode) in modes {
        let stats = run(&mut scene, mode, spp);
        let pps = stats.paths_per_second();
        let base = *global.get_or_insert(pps);
        println!(
            "| {name} | {pps:.0} | {:.1} | {:.3} | {:.2}× |",
            stats.lookups_per_path(),
            stats.tracking_efficiency(),
            pps / base
        );
    }
}
