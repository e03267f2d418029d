//! `cargo bench --bench hotspot`: the cost of a hot spot. A 16³ block of ordinary density, rendered
//! as it is and with one voxel 10³ and 10⁶ times its neighbours (and a 3³ block at 10⁶), at equal
//! spp: wall time, density lookups per path and the null-collision ratio (tentative collisions
//! that were not real), each relative to the block without the hot spot, measured in one run.
//!
//! VOLGRAD_BENCH_SPP (default 4) sets the samples per pixel of the 64×64 image.

use glam::{DVec3, IVec3, Vec3};
use volgrad::render::camera::Camera;
use volgrad::render::image::{render, RenderOptions};
use volgrad::render::lights::{DirectionalLight, Environment, Lights};
use volgrad::render::scene::{RenderFile, Scene};
use volgrad::volume::albedo::Albedo;
use volgrad::volume::brickmap::BrickMap;
use volgrad::volume::majorant::Majorant;
use volgrad::volume::medium::{Filter, Medium};
use volgrad::volume::transform::IndexTransform;

const N: i32 = 16;

/// The hot value of a voxel, or None for the block's ordinary density.
type HotSpot = Box<dyn Fn(IVec3) -> Option<f32>>;

fn scene(hot: impl Fn(IVec3) -> Option<f32>, filter: Filter) -> Scene {
    let grid = BrickMap::block(N, |v| hot(v).unwrap_or(1.0));
    let transform = IndexTransform::uniform(1.0, DVec3::splat(-(N - 1) as f64 * 0.5));
    let mut medium = Medium::new(grid, transform, 0.15, filter, Majorant::grid(4));
    medium.albedo = Albedo::Constant(Vec3::splat(0.9));
    medium.phase_g = 0.3;
    let lights = Lights {
        environment: Environment {
            constant: Vec3::splat(0.5),
            map: None,
        },
        directional: vec![DirectionalLight {
            to_light: Vec3::new(0.3, 1.0, 0.2).normalize(),
            irradiance: Vec3::splat(2.0),
        }],
    };
    Scene {
        path: "hotspot".into(),
        camera: Camera::new(Vec3::new(0.0, 4.0, 40.0), Vec3::ZERO, Vec3::Y, 35.0, 64, 64),
        medium,
        lights,
        settings: RenderFile::default(),
        grid_name: "density".into(),
        vdb_path: Some("hotspot.vdb".into()),
    }
}

fn main() {
    let spp: u32 = std::env::var("VOLGRAD_BENCH_SPP")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(4);
    let centre = IVec3::splat(N / 2);
    let cases: [(&str, HotSpot); 4] = [
        ("no hot spot", Box::new(|_| None)),
        (
            "one voxel ×1e3",
            Box::new(move |v| (v == centre).then_some(1e3)),
        ),
        (
            "one voxel ×1e6",
            Box::new(move |v| (v == centre).then_some(1e6)),
        ),
        (
            "3³ block ×1e6",
            Box::new(move |v| (v - centre).abs().max_element().lt(&2).then_some(1e6)),
        ),
    ];
    println!("64×64, {spp} spp, {} threads", rayon::current_num_threads());
    for filter in [Filter::Trilinear, Filter::Nearest] {
        println!("\n{filter} lookups");
        println!("| scene | time (s) | × without | lookups/path | × without | null collisions |");
        println!("|---|---:|---:|---:|---:|---:|");
        let mut base = None;
        for (name, hot) in &cases {
            let scene = scene(hot, filter);
            let options = RenderOptions {
                spp,
                seed: 1,
                max_depth: 64,
                progress: false,
            };
            let (_, stats) = render(&scene, &options);
            let secs = stats.wall.as_secs_f64();
            let lookups = stats.lookups_per_path();
            let (b_secs, b_lookups) = *base.get_or_insert((secs, lookups));
            let t = &stats.tracking;
            let null = 1.0 - t.collisions as f64 / t.lookups.max(1) as f64;
            println!(
                "| {name} | {secs:.3} | {:.2}× | {lookups:.1} | {:.2}× | {null:.3} |",
                secs / b_secs,
                lookups / b_lookups
            );
        }
    }
}
