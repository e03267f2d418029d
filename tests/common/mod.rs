//! Scenes built in memory for the renderer's tests.
#![allow(dead_code)]

pub mod mpi;
mod png;
mod process;
#[allow(unused_imports)] // only the tests of hostile images write PNG chunks
pub use png::*;
#[allow(unused_imports)] // not every test file runs the binary
pub use process::*;

use std::path::PathBuf;

use glam::{DMat3, DVec3, IVec3, Vec3};
use volgrad::render::camera::Camera;
use volgrad::render::lights::{DirectionalLight, Environment, Lights};
use volgrad::render::scene::{RenderFile, Scene};
use volgrad::volume::albedo::Albedo;
use volgrad::volume::brickmap::BrickMap;
use volgrad::volume::majorant::Majorant;
use volgrad::volume::medium::{Filter, Medium};
use volgrad::volume::transform::IndexTransform;

/// A grid of `n`³ voxels (0..n) whose values come from `f`.
pub fn grid(n: i32, f: impl Fn(IVec3) -> f32) -> BrickMap {
    BrickMap::block(n, f)
}

/// A uniform transform with voxel (0,0,0)... centred so that the `n`³ block sits around the origin.
pub fn centred(n: i32, voxel: f64) -> IndexTransform {
    IndexTransform::uniform(voxel, DVec3::splat(-(n - 1) as f64 * 0.5 * voxel))
}

pub fn affine(linear: DMat3, n: i32) -> IndexTransform {
    IndexTransform::centred(linear, DVec3::splat((n - 1) as f64 * 0.5)).unwrap()
}

pub struct SceneBuilder {
    pub camera: Camera,
    pub lights: Lights,
    pub settings: RenderFile,
}

impl SceneBuilder {
    /// A camera on +z looking at the origin.
    pub fn new(distance: f32, fov_deg: f32, pixels: u32) -> Self {
        SceneBuilder {
            camera: Camera::new(
                Vec3::new(0.0, 0.0, distance),
                Vec3::ZERO,
                Vec3::Y,
                fov_deg,
                pixels,
                pixels,
            ),
            lights: Lights::default(),
            settings: RenderFile::default(),
        }
    }

    pub fn constant_light(mut self, radiance: Vec3) -> Self {
        self.lights.environment = Environment {
            constant: radiance,
            map: None,
        };
        self
    }

    // One call builds a scene from the medium's seven constants; tests read better with them
    // positional than through another builder.
    #[allow(clippy::too_many_arguments)]
    pub fn build(
        self,
        grid: BrickMap,
        transform: IndexTransform,
        density_scale: f32,
        albedo: Vec3,
        g: f32,
        filter: Filter,
        majorant: Majorant,
    ) -> Scene {
        let mut medium = Medium::new(grid, transform, density_scale, filter, majorant);
        medium.albedo = Albedo::Constant(albedo);
        medium.phase_g = g;
        Scene {
            path: PathBuf::from("test.toml"),
            camera: self.camera,
            medium,
            lights: self.lights,
            settings: self.settings,
            grid_name: "density".into(),
            vdb_path: Some(PathBuf::from("test.vdb")),
        }
    }
}

/// A lumpy 6³ block, optionally with empty voxels inside it, under a sky and a sun, seen by an 8×8
/// camera, 16-deep paths: every estimator has something to get right and naive, with empty voxels,
/// something to get wrong.
pub fn lumpy_block_scene(filter: Filter, empty_voxels: bool, albedo: f32) -> Scene {
    let value = move |v: IVec3| {
        if empty_voxels && (v.x + 2 * v.y + v.z) % 4 == 0 {
            0.0
        } else {
            0.6 + 0.4 * ((v.x as f32 * 1.3).sin() * (v.y as f32 * 0.8 + v.z as f32).cos())
        }
    };
    let mut s = SceneBuilder::new(14.0, 35.0, 8)
        .constant_light(Vec3::new(0.8, 0.9, 1.0))
        .build(
            grid(6, value),
            centred(6, 1.0),
            0.5,
            Vec3::splat(albedo),
            0.3,
            filter,
            Majorant::grid(4),
        );
    s.lights.directional.push(DirectionalLight {
        to_light: Vec3::new(0.4, 1.0, 0.3).normalize(),
        irradiance: Vec3::splat(2.0),
    });
    s.settings.max_depth = 16;
    s
}
