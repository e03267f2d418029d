//! The contract between the path loop and the path replay (see the top of `gradient::adjoint`).
//!
//! `render::path::trace` adds up a path's radiance as it goes and records one `Segment` per free
//! flight; the replay re-derives, from those records alone, the radiance R_j the path carries back
//! from each vertex (`carried_radiance`). The two are the same rule written twice, once forwards
//! and once backwards. These tests trace random camera paths and demand that they agree: R_1 (the
//! camera segment's) is the traced radiance, and at every vertex j the radiance splits into what
//! was collected before it plus β_{j−1}·R_j, the part every estimator's segment term differentiates.

mod common;

use common::*;
use glam::{IVec3, Vec3};
use rand::Rng;
use volgrad::gradient::adjoint::carried_radiance;
use volgrad::render::lights::{DirectionalLight, EnvMap, Environment};
use volgrad::render::path::{trace, PathRecord, PathState, Segment, SegmentEnd};
use volgrad::render::sampling::{sample_rng, Pass};
use volgrad::render::scene::Scene;
use volgrad::volume::albedo::{Albedo, AlbedoGrid};
use volgrad::volume::emission::{Emission, EmissionKind};
use volgrad::volume::majorant::Majorant;
use volgrad::volume::medium::Filter;
use volgrad::volume::tracking::TrackingStats;

const SEEDS: [u64; 3] = [1, 2, 3];
const PATHS_PER_SEED: u64 = 400;
/// Both sides add up the same non-negative terms in a different order: a few ulps per term.
const RELATIVE_TOLERANCE: f32 = 1e-4;

/// The branches of the path loop that a scene's paths went through, counted over all its paths.
#[derive(Debug, Default, Clone, Copy)]
struct Branches {
    /// Paths with non-zero radiance (so that agreement is not 0 = 0).
    lit_paths: usize,
    /// Segments that escaped with non-zero environment radiance.
    escapes: usize,
    /// Scattering events after which Russian roulette kept the path with weight 1/q > 1.
    rr_survived: usize,
    /// Scattering events after which Russian roulette ended the path.
    rr_ended: usize,
    /// Collisions that did not scatter: past the maximum depth, or absorbed (albedo 0).
    unscattered: usize,
}

impl Branches {
    fn count(&mut self, segments: &[Segment]) {
        for segment in segments {
            match segment.end {
                SegmentEnd::Escaped { radiance } if radiance != Vec3::ZERO => self.escapes += 1,
                SegmentEnd::Escaped { .. } => {}
                SegmentEnd::Stopped { .. } => self.unscattered += 1,
                SegmentEnd::Scattered {
                    continuation_weight: w,
                    ..
                } if w > 1.0 => self.rr_survived += 1,
                SegmentEnd::Scattered {
                    continuation_weight: 0.0,
                    ..
                } => self.rr_ended += 1,
                SegmentEnd::Scattered { .. } => {}
            }
        }
    }
}

fn close(a: Vec3, b: Vec3) -> bool {
    let scale = a.abs().max_element().max(b.abs().max_element());
    (a - b).abs().max_element() <= RELATIVE_TOLERANCE * scale
}

/// Traces `PATHS_PER_SEED` camera paths per seed through random points of the image and checks
/// the replay's carried radiance against `trace`'s radiance; returns the branches the paths took.
fn check_scene(name: &str, scene: &Scene) -> Branches {
    let camera = &scene.camera;
    let max_depth = scene.settings.max_depth;
    let mut branches = Branches::default();
    let mut stats = TrackingStats::default();
    let mut record = PathRecord::default();
    let mut carried = Vec::new();
    for seed in SEEDS {
        for path in 0..PATHS_PER_SEED {
            let mut rng = sample_rng(seed, path, 0, Pass::Forward);
            let dir = camera.direction(
                rng.gen::<f32>() * camera.width as f32,
                rng.gen::<f32>() * camera.height as f32,
            );
            record.segments.clear();
            record.shadows.clear();
            let state = PathState::camera(camera.position, dir);
            let radiance = trace(
                scene,
                state,
                max_depth,
                &mut rng,
                &mut stats,
                Some(&mut record),
            );
            let segments = &record.segments;
            carried_radiance(segments, &mut carried);
            branches.count(segments);
            if radiance != Vec3::ZERO {
                branches.lit_paths += 1;
            }
            let context = || format!("{name}, seed {seed}, path {path}: {segments:#?}");

            // β_0 = 1: the camera segment carries the whole path.
            assert!(
                close(carried[0], radiance),
                "R_1 = {} but trace returned {radiance} ({name}, seed {seed}, path {path}, {} \
                 segments)\n{}",
                carried[0],
                segments.len(),
                context()
            );
            // At every vertex: collected before x_{j−1}, plus β_{j−1}·R_j from there on.
            let mut collected = Vec3::ZERO;
            for (j, segment) in segments.iter().enumerate() {
                let split = collected + segment.throughput * carried[j];
                assert!(
                    close(split, radiance),
                    "at segment {}: Σ_(i<j) β·α·NEE + β·R_j = {split} but trace returned \
                     {radiance}\n{}",
                    j + 1,
                    context()
                );
                match segment.end {
                    SegmentEnd::Escaped { .. } => {}
                    SegmentEnd::Stopped { emission, .. } => {
                        collected += segment.throughput * emission
                    }
                    SegmentEnd::Scattered {
                        emission,
                        albedo,
                        nee,
                        ..
                    } => collected += segment.throughput * (emission + albedo * nee),
                }
            }
        }
    }
    println!("{name}: {branches:?}");
    branches
}

/// A lumpy 6³ block with empty voxels (optical depth ~7 across, so that paths reach the depth
/// where Russian roulette starts) under a sky and a sun, with albedo `albedo`.
fn lumpy(albedo: Vec3, max_depth: u32) -> Scene {
    let value = |v: IVec3| {
        if (v.x + 2 * v.y + v.z) % 4 == 0 {
            0.0
        } else {
            0.6 + 0.4 * ((v.x as f32 * 1.3).sin() * (v.y as f32 * 0.8 + v.z as f32).cos())
        }
    };
    let mut scene = SceneBuilder::new(14.0, 35.0, 8)
        .constant_light(Vec3::new(0.8, 0.9, 1.0))
        .build(
            grid(6, value),
            centred(6, 1.0),
            2.0,
            albedo,
            0.3,
            Filter::Trilinear,
            Majorant::grid(4),
        );
    scene.lights.directional.push(DirectionalLight {
        to_light: Vec3::new(0.4, 1.0, 0.3).normalize(),
        irradiance: Vec3::splat(2.0),
    });
    scene.settings.max_depth = max_depth;
    scene
}

/// An 8³ block of optical depth ~48 across, strongly forward scattering: long paths.
fn dense_block() -> Scene {
    let mut scene = SceneBuilder::new(20.0, 35.0, 8)
        .constant_light(Vec3::new(0.5, 0.6, 0.7))
        .build(
            grid(8, |v: IVec3| 0.8 + 0.05 * (v.x + v.y + v.z) as f32),
            centred(8, 1.0),
            6.0,
            Vec3::splat(0.97),
            0.6,
            Filter::Nearest,
            Majorant::grid(4),
        );
    scene.lights.directional.push(DirectionalLight {
        to_light: Vec3::new(-0.3, 1.0, 0.2).normalize(),
        irradiance: Vec3::splat(3.0),
    });
    scene.settings.max_depth = 64;
    scene
}

/// The lumpy block under a lat-long map (bright band, coloured) plus a constant term and a sun.
fn envmap_scene() -> Scene {
    let (w, h) = (32, 16);
    let texels = (0..w * h)
        .map(|i| {
            let (u, v) = ((i % w) as f32 / w as f32, (i / w) as f32 / h as f32);
            let band = if (0.3..0.45).contains(&v) { 4.0 } else { 0.2 };
            Vec3::new(band * (0.5 + u), band, band * (1.5 - u))
        })
        .collect();
    let mut scene = lumpy(Vec3::new(0.9, 0.7, 0.5), 16);
    scene.lights.environment = Environment {
        constant: Vec3::splat(0.1),
        map: Some(EnvMap::new(w, h, texels)),
    };
    scene
}

#[test]
fn carried_radiance_reproduces_traced_radiance() {
    let grey = Vec3::splat(0.8);
    let coloured = Vec3::new(0.9, 0.6, 0.3);

    // Russian roulette (albedo < 1, 16-deep paths) in grey and in colour (q = max(β) < 1).
    for (name, albedo) in [("lumpy grey", grey), ("lumpy coloured", coloured)] {
        let b = check_scene(name, &lumpy(albedo, 16));
        assert!(b.rr_survived >= 100 && b.rr_ended >= 100, "{name}: {b:?}");
        assert!(b.escapes >= 500 && b.lit_paths >= 1000, "{name}: {b:?}");
    }

    // The maximum-depth cut: every collision past depth 0, 1, 2 ends the path unscattered.
    for max_depth in [0, 1, 2] {
        let name = format!("lumpy, max depth {max_depth}");
        let b = check_scene(&name, &lumpy(coloured, max_depth));
        assert!(b.unscattered >= 100 && b.lit_paths >= 300, "{name}: {b:?}");
    }

    // Long paths in a dense medium: many roulette decisions per path, some reach depth 64.
    let b = check_scene("dense block", &dense_block());
    assert!(
        b.rr_survived >= 1000 && b.rr_ended >= 200,
        "dense block: {b:?}"
    );

    // A sun alone: escapes carry nothing, all radiance comes from NEE.
    let mut sun_only = lumpy(grey, 16);
    sun_only.lights.environment = Environment::default();
    let b = check_scene("sun only", &sun_only);
    assert!(
        b.escapes == 0 && b.rr_survived >= 100 && b.lit_paths >= 500,
        "sun only: {b:?}"
    );

    // An environment map: MIS-weighted escapes after phase sampling.
    let b = check_scene("envmap", &envmap_scene());
    assert!(b.rr_survived >= 100 && b.escapes >= 500, "envmap: {b:?}");

    // Albedo 0: the first collision absorbs the path.
    let b = check_scene("absorbing", &lumpy(Vec3::ZERO, 16));
    assert!(
        b.unscattered >= 500 && b.rr_survived == 0,
        "absorbing: {b:?}"
    );

    // An emitting medium, its emission from a grid of its own (offset by half a voxel and
    // coloured): emission at scattered collisions, at collisions past the maximum depth, and
    // at absorbing ones.
    for (name, albedo, max_depth) in [
        ("emitting", coloured, 16),
        ("emitting, max depth 1", coloured, 1),
        ("emitting, absorbing", Vec3::ZERO, 16),
    ] {
        let mut scene = lumpy(albedo, max_depth);
        scene.medium.emission = Some(Emission::new(
            "flames".into(),
            grid(7, |v: IVec3| 0.5 + 0.1 * v.x as f32),
            centred(7, 1.0),
            EmissionKind::Radiance(Vec3::new(3.0, 1.5, 0.5)),
            Filter::Trilinear,
        ));
        let b = check_scene(name, &scene);
        assert!(b.lit_paths >= 1000, "{name}: {b:?}");
    }

    // An albedo grid (RGB, from 0 to 1 across the block, 0 outside it) in an emitting medium:
    // each collision's α is its own, and R_j must use the one `trace` weighted with.
    let mut scene = lumpy(Vec3::ONE, 16);
    scene.medium.albedo = Albedo::Grid(Box::new(AlbedoGrid::new(
        "Cd".into(),
        vec![
            grid(6, |v: IVec3| v.x as f32 / 5.0),
            grid(6, |v: IVec3| 1.0 - v.y as f32 / 5.0),
            grid(6, |_| 0.9),
        ],
        Vec3::ZERO,
        centred(6, 1.0),
        Filter::Trilinear,
    )));
    scene.medium.emission = Some(Emission::new(
        "flames".into(),
        grid(6, |_| 1.0),
        centred(6, 1.0),
        EmissionKind::Radiance(Vec3::new(0.5, 1.0, 2.0)),
        Filter::Trilinear,
    ));
    let b = check_scene("albedo grid", &scene);
    assert!(
        b.lit_paths >= 1000 && b.rr_survived > 0,
        "albedo grid: {b:?}"
    );
}
