//! Alpha (1 − T along the camera ray) and its gradient against closed forms and against finite
//! differences of alpha computed by quadrature. The margins are a few standard errors of runs
//! with fixed seeds; a dropped factor (T, the segment's length, the density scale) or points that
//! skip empty voxels move the estimate many times further.

mod common;

use common::*;
use glam::{IVec3, Vec3};
use volgrad::gradient::adjoint::Estimator;
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{gradient, GradOptions, Measured};
use volgrad::io::images::RgbImage;
use volgrad::render::alpha::render_alpha_pixels;
use volgrad::render::image::RenderOptions;
use volgrad::render::pixel_set::PixelSet;
use volgrad::render::scene::Scene;
use volgrad::volume::majorant::Majorant;
use volgrad::volume::medium::Filter;

fn alpha_options(spp: u32, seed: u64) -> GradOptions {
    GradOptions {
        measured: Measured::Alpha,
        ..GradOptions::new(Estimator::Joint, spp, seed, 1)
    }
}

fn mean_alpha(scene: &Scene, spp: u32, seed: u64) -> f64 {
    let options = RenderOptions {
        spp,
        seed,
        max_depth: 1,
        progress: false,
    };
    let pixels = scene.camera.width * scene.camera.height;
    let image = render_alpha_pixels(scene, &options, &PixelSet::All(pixels)).image;
    let mean = image.mean();
    assert_eq!(mean.x, mean.z, "alpha is grey");
    mean.x as f64
}

/// Mean and standard error of `f` over seeds 0..n.
fn over_seeds(n: u64, f: impl Fn(u64) -> f64) -> (f64, f64) {
    let values: Vec<f64> = (0..n).map(f).collect();
    let mean = values.iter().sum::<f64>() / n as f64;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    (mean, (var / n as f64).sqrt())
}

#[test]
fn alpha_of_a_homogeneous_block_is_the_closed_form_and_so_is_its_gradient() {
    // Nearly parallel rays crossing n voxels of σt = s·θ: α = 1 − e^{−sθn} and, θ moving in
    // every voxel at once, dα/dθ = s·n·e^{−sθn}. Without the density scale the gradient would be
    // 10× too large, without the segment's length 8× too small. (Here the majorant is σt, so T̂ is
    // 0 or 1 and a dropped T̂ factor goes unseen: the lumpy block's test below catches that.)
    let (n, s, theta) = (8, 0.1f32, 1.0f32);
    let scene = SceneBuilder::new(300.0, 1.0, 4).build(
        grid(n, |_| theta),
        centred(n, 1.0),
        s,
        Vec3::ONE,
        0.0,
        Filter::Nearest,
        Majorant::grid(4),
    );
    let tau = (s * theta * n as f32) as f64;
    let (alpha, se) = over_seeds(6, |seed| mean_alpha(&scene, 256, seed));
    let expected = 1.0 - (-tau).exp();
    assert!(
        (alpha - expected).abs() < 4.5 * se + 1e-4,
        "{alpha} ± {se} vs {expected}"
    );
    let blank = RgbImage::new(scene.camera.width, scene.camera.height);
    // Loss::Mean's adjoint is 1/(3·pixels) per channel: its gradient is that of the mean alpha.
    let adjoint = Loss::Mean.adjoint(&blank, None);
    let (slope, se) = over_seeds(6, |seed| {
        gradient(&scene, &adjoint, &alpha_options(64, seed))
            .values()
            .sum()
    });
    let expected = s as f64 * n as f64 * (-tau).exp();
    assert!(
        (slope - expected).abs() < 4.5 * se + 0.002 * expected,
        "{slope} ± {se} vs {expected}"
    );
    assert!(
        se < 0.02 * expected,
        "standard error {se} too large to test"
    );
}

/// The mean alpha of `scene`'s image by quadrature: per pixel, 8×8 sub-pixel rays, each ray's
/// optical depth by the midpoint rule in steps of 1/64 of a voxel.
fn alpha_by_quadrature(scene: &Scene) -> f64 {
    let (camera, medium) = (&scene.camera, &scene.medium);
    let (sub, steps_per_unit) = (8, 64.0);
    let mut sum = 0.0f64;
    for y in 0..camera.height {
        for x in 0..camera.width {
            for j in 0..sub * sub {
                let (u, v) = ((j % sub) as f32 + 0.5, (j / sub) as f32 + 0.5);
                let dir = camera.direction(x as f32 + u / sub as f32, y as f32 + v / sub as f32);
                let ray = medium.to_index_ray(camera.position, dir);
                let Some((t0, t1)) = medium.intersect(&ray) else {
                    continue;
                };
                let steps = ((t1 - t0) * steps_per_unit).ceil().max(1.0) as usize;
                let dt = (t1 - t0) as f64 / steps as f64;
                let depth: f64 = (0..steps)
                    .map(|i| {
                        medium.sigma_t(ray.at(t0 + (i as f64 + 0.5) as f32 * dt as f32)) as f64
                    })
                    .sum::<f64>()
                    * dt;
                sum += 1.0 - (-depth).exp();
            }
        }
    }
    sum / (camera.width * camera.height * sub * sub) as f64
}

/// `scene` with `eps` added to every voxel of `voxels`: for quadrature only (its majorant is
/// stale, and a negative step may make voxels negative, which a sum of σt·dt takes in its stride).
fn with_added(scene: &Scene, voxels: &[IVec3], eps: f32) -> Scene {
    let mut s = scene.clone();
    let step: Vec<(IVec3, f32)> = voxels.iter().map(|&v| (v, eps)).collect();
    s.medium.grid = s.medium.grid.with_added(&step);
    s
}

#[test]
fn alpha_gradient_agrees_with_finite_differences_in_full_and_empty_voxels() {
    // The lumpy block, its rays through lumps and holes at many angles, trilinear: the
    // derivative of the mean alpha with respect to a box of voxels, and to its empty voxels alone
    // (where the majorant is lowest: points taken from tentative collisions would miss them).
    let scene = lumpy_block_scene(Filter::Trilinear, true, 0.8);
    let (lo, hi) = (IVec3::new(1, 1, 1), IVec3::new(3, 4, 2));
    let in_box: Vec<IVec3> = volgrad::gradient::fd::box_voxels(&scene.medium.grid, lo, hi, false);
    let empty: Vec<IVec3> = (in_box.iter())
        .copied()
        .filter(|&v| scene.medium.grid.voxel(v) == 0.0)
        .collect();
    assert!(empty.len() >= 3, "{} empty voxels", empty.len());
    let blank = RgbImage::new(scene.camera.width, scene.camera.height);
    // Loss::Mean's adjoint is 1/(3·pixels) per channel: its gradient is that of the mean alpha.
    let adjoint = Loss::Mean.adjoint(&blank, None);
    let runs: Vec<_> = (0..6)
        .map(|seed| gradient(&scene, &adjoint, &alpha_options(1024, seed)).values())
        .collect();
    let eps = 0.02;
    for voxels in [&in_box, &empty] {
        let fd = (alpha_by_quadrature(&with_added(&scene, voxels, eps))
            - alpha_by_quadrature(&with_added(&scene, voxels, -eps)))
            / (2.0 * eps as f64);
        let (estimate, se) = over_seeds(6, |seed| {
            voxels.iter().map(|&v| runs[seed as usize].get(v)).sum()
        });
        assert!(
            (estimate - fd).abs() < 4.5 * se + 0.005 * fd.abs(),
            "{} voxels: {estimate} ± {se} vs {fd}",
            voxels.len()
        );
        assert!(
            se < 0.02 * fd.abs(),
            "standard error {se} too large to test"
        );
    }
}
