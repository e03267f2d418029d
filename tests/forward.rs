//! The forward renderer against closed-form answers: white furnace, homogeneous transmittance,
//! single scattering of a sun, filters, transforms, determinism.

mod common;

use common::*;
use glam::{DMat3, DVec3, IVec3, Vec3};
use rand::Rng;
use volgrad::render::image::{render, RenderOptions};
use volgrad::render::lights::{DirectionalLight, EnvMap, Environment};
use volgrad::render::sampling::pixel_rng;
use volgrad::volume::majorant::Majorant;
use volgrad::volume::medium::Filter;
use volgrad::volume::tracking::{transmittance, TrackingStats};

const GRID8: Majorant = Majorant::grid(8);
const GRID4: Majorant = Majorant::grid(4);

fn options(spp: u32, max_depth: u32) -> RenderOptions {
    RenderOptions {
        spp,
        seed: 7,
        max_depth,
        progress: false,
    }
}

/// A lumpy ball: values vary smoothly inside and drop to empty voxels outside.
fn lumpy_ball(n: i32) -> volgrad::volume::brickmap::BrickMap {
    let c = (n - 1) as f32 * 0.5;
    grid(n, |v| {
        let d = (v.as_vec3() - c).length() / c;
        if d > 1.0 {
            0.0
        } else {
            (1.0 - d) * (1.5 + (v.x as f32 * 0.9).sin() * (v.y as f32 * 0.7).cos())
        }
    })
}

#[test]
fn white_furnace_every_pixel_sees_the_environment() {
    // Albedo 1 and a constant environment: whatever the density, every pixel is L.
    let radiance = Vec3::new(0.7, 0.5, 0.3);
    for (density, filter, majorant) in [
        (0.05, Filter::Trilinear, GRID8),
        (0.6, Filter::Trilinear, Majorant::global()),
        (0.6, Filter::Nearest, GRID4),
        (2.0, Filter::Nearest, Majorant::global()),
        (2.0, Filter::Trilinear, GRID4),
    ] {
        let scene = SceneBuilder::new(30.0, 40.0, 8)
            .constant_light(radiance)
            .build(
                lumpy_ball(14),
                centred(14, 1.0),
                density,
                Vec3::ONE,
                0.3,
                filter,
                majorant,
            );
        let (image, _) = render(&scene, &options(256, 100_000));
        let mean = image.mean();
        assert!(
            (mean / radiance - 1.0).abs().max_element() < 0.01,
            "density {density} {filter:?} {majorant:?}: mean {mean} vs {radiance}"
        );
        for (i, c) in image.pixels.iter().enumerate() {
            assert!(
                (*c / radiance - 1.0).abs().max_element() < 0.12,
                "density {density} {filter:?} {majorant:?}: pixel {i} is {c}"
            );
        }
    }
}

#[test]
fn white_furnace_with_an_importance_sampled_environment_map() {
    // A constant map (plus a constant term) must also integrate to L; a non-constant map tests the
    // map's sampling density against its evaluation through the MIS weights.
    let texels = vec![Vec3::splat(0.25); 32 * 16];
    let mut scene = SceneBuilder::new(30.0, 40.0, 8).build(
        lumpy_ball(14),
        centred(14, 1.0),
        0.8,
        Vec3::ONE,
        -0.4,
        Filter::Trilinear,
        GRID8,
    );
    scene.lights.environment = Environment {
        constant: Vec3::splat(0.25),
        map: Some(EnvMap::new(32, 16, texels)),
    };
    let (image, _) = render(&scene, &options(64, 100_000));
    assert!(
        (image.mean() - Vec3::splat(0.5)).abs().max_element() < 0.005,
        "mean {}",
        image.mean()
    );
}

#[test]
fn homogeneous_box_transmits_exp_minus_sigma_length() {
    // Albedo 0: a pixel is the fraction of camera rays that cross unscattered, exp(−σℓ).
    let n = 10;
    let sigma = 0.15;
    let scene = SceneBuilder::new(200.0, 2.0, 8)
        .constant_light(Vec3::ONE)
        .build(
            grid(n, |_| 1.0),
            centred(n, 1.0),
            sigma,
            Vec3::ZERO,
            0.0,
            Filter::Nearest,
            GRID4,
        );
    let (image, _) = render(&scene, &options(1024, 64));
    let expected = (-sigma * n as f32).exp();
    for c in &image.pixels {
        // Binomial noise of 1024 samples: σ ≈ 0.015; these rays cross the whole box (ℓ = 10 ± 0.2%).
        assert!(
            (c.x - expected).abs() < 0.06,
            "pixel {} vs exp(−σℓ) = {expected}",
            c.x
        );
    }
    assert!(
        (image.mean().x - expected).abs() < 0.01,
        "mean {} vs {expected}",
        image.mean().x
    );
}

#[test]
fn ratio_tracking_is_unbiased_and_never_nan_for_huge_optical_depth() {
    let n = 16;
    for (sigma, filter) in [
        (0.05, Filter::Trilinear),
        (0.3, Filter::Nearest),
        (50.0, Filter::Trilinear),
        (1e30, Filter::Nearest),
    ] {
        let scene = SceneBuilder::new(40.0, 10.0, 1).build(
            grid(n, |_| 1.0),
            centred(n, 1.0),
            sigma,
            Vec3::ONE,
            0.0,
            filter,
            GRID8,
        );
        let medium = &scene.medium;
        let ray = medium.to_index_ray(Vec3::new(0.0, 0.3, 30.0), Vec3::new(0.0, 0.0, -1.0));
        let (t0, t1) = medium.intersect(&ray).unwrap();
        // Trilinear lookups ramp from σ/2 at a face to σ half a voxel inside (∫ = 0.375σ per
        // face); nearest ones are σ right up to the face.
        let length = if filter == Filter::Trilinear {
            n as f64 - 0.25
        } else {
            n as f64
        };
        let tau = sigma as f64 * length;
        let mut rng = pixel_rng(1, 0, 0);
        let mut stats = TrackingStats::default();
        let m = 40_000;
        let samples: Vec<f64> = (0..m)
            .map(|_| transmittance(medium, &ray, t0, t1, &mut rng, &mut stats) as f64)
            .collect();
        let mean = samples.iter().sum::<f64>() / m as f64;
        let std_err =
            (samples.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / (m * (m - 1)) as f64).sqrt();
        let expected = (-tau).exp();
        assert!(samples
            .iter()
            .all(|s| s.is_finite() && (0.0..=1.0).contains(s)));
        // 4 standard errors, and at least 1e-4 so that a zero-variance case can pass.
        assert!(
            (mean - expected).abs() < 4.0 * std_err + 1e-4,
            "σ={sigma} {filter:?}: T̂ = {mean} ± {std_err} vs {expected}"
        );
        if tau > 87.0 {
            assert_eq!(mean, 0.0);
        }
    }
}

#[test]
fn dense_media_render_finite_images() {
    let scene = SceneBuilder::new(30.0, 40.0, 6)
        .constant_light(Vec3::ONE)
        .build(
            lumpy_ball(12),
            centred(12, 1.0),
            1e4,
            Vec3::splat(0.5),
            0.9,
            Filter::Trilinear,
            GRID8,
        );
    let (image, _) = render(&scene, &options(8, 64));
    assert!(image
        .pixels
        .iter()
        .all(|c| c.is_finite() && c.min_element() >= 0.0));
}

#[test]
fn single_scattering_of_a_sun_matches_the_closed_form() {
    // Sun shining along the view direction, camera looking into a homogeneous box, one bounce:
    // light scattered back at depth s travels s back out, so
    //   L = ∫₀^ℓ σ e^{−σs} p(−1) E e^{−σs} ds = p(−1) E (1 − e^{−2σℓ}) / 2,
    // with the HG value p(−1) = (1 − g²) / (4π (1 + g)³). A sign error in g changes it 4-fold.
    let n = 8;
    let (sigma, g) = (0.1f32, 0.3f32);
    let irradiance = Vec3::new(2.0, 1.0, 0.5);
    let mut scene = SceneBuilder::new(400.0, 0.5, 4).build(
        grid(n, |_| 1.0),
        centred(n, 1.0),
        sigma,
        Vec3::ONE,
        g,
        Filter::Nearest,
        GRID4,
    );
    scene.lights.directional.push(DirectionalLight {
        to_light: Vec3::Z,
        irradiance,
    });
    let (image, _) = render(&scene, &options(4096, 1));
    let p_back = (1.0 - g * g) / (4.0 * std::f32::consts::PI * (1.0 + g).powi(3));
    let expected = irradiance * p_back * (1.0 - (-2.0 * sigma * n as f32).exp()) / 2.0;
    let mean = image.mean();
    assert!(
        (mean / expected - 1.0).abs().max_element() < 0.03,
        "{mean} vs {expected}"
    );
}

#[test]
fn nearest_and_trilinear_agree_on_constant_data_with_its_apron() {
    // With the inactive apron voxels holding the same value, both filters see the same σ at every
    // point of the medium, so the renders match exactly (same random numbers, same decisions).
    let n = 10;
    let mut b = volgrad::volume::brickmap::BrickMapBuilder::new();
    for x in -1..=n {
        for y in -1..=n {
            for z in -1..=n {
                let v = IVec3::new(x, y, z);
                let inside = v.cmpge(IVec3::ZERO).all() && v.cmplt(IVec3::splat(n)).all();
                b.set(v, 0.7, inside);
            }
        }
    }
    let make = |filter| {
        SceneBuilder::new(30.0, 40.0, 8)
            .constant_light(Vec3::ONE)
            .build(
                b_clone(&b),
                centred(n, 1.0),
                0.4,
                Vec3::splat(0.8),
                0.2,
                filter,
                GRID8,
            )
    };
    let (a, _) = render(&make(Filter::Nearest), &options(16, 64));
    let (c, _) = render(&make(Filter::Trilinear), &options(16, 64));
    assert_eq!(a, c);
}

fn b_clone(b: &volgrad::volume::brickmap::BrickMapBuilder) -> volgrad::volume::brickmap::BrickMap {
    b.clone().build()
}

/// Grid B is grid A turned 90° about y, with the voxel edges permuted to match: the same medium in
/// world space, stored with a rotated, anisotropic transform.
fn rotated_pair() -> (
    (
        volgrad::volume::brickmap::BrickMap,
        volgrad::volume::transform::IndexTransform,
    ),
    (
        volgrad::volume::brickmap::BrickMap,
        volgrad::volume::transform::IndexTransform,
    ),
) {
    let n = 12;
    let value = |v: IVec3| 0.2 + (v.x as f32) * 0.1 + ((v.y * 3 + v.z) % 5) as f32 * 0.05;
    let size_b = DVec3::new(0.5, 2.0, 1.0);
    // R·diag(size_b)·(x, y, z) = (size_b.z z, size_b.y y, −size_b.x x) for R = rot_y(90°).
    let a = (
        grid(n, value),
        affine(
            DMat3::from_diagonal(DVec3::new(size_b.z, size_b.y, size_b.x)),
            n,
        ),
    );
    let b = (
        grid(n, |v| value(IVec3::new(v.z, v.y, n - 1 - v.x))),
        affine(
            DMat3::from_rotation_y(std::f64::consts::FRAC_PI_2) * DMat3::from_diagonal(size_b),
            n,
        ),
    );
    (a, b)
}

#[test]
fn a_rotated_anisotropic_grid_is_the_same_medium_as_its_axis_aligned_equivalent() {
    let ((ga, ta), (gb, tb)) = rotated_pair();
    let scene_a = SceneBuilder::new(40.0, 30.0, 8)
        .constant_light(Vec3::ONE)
        .build(ga, ta, 0.3, Vec3::splat(0.9), 0.4, Filter::Trilinear, GRID4);
    let scene_b = SceneBuilder::new(40.0, 30.0, 8)
        .constant_light(Vec3::ONE)
        .build(gb, tb, 0.3, Vec3::splat(0.9), 0.4, Filter::Trilinear, GRID4);
    // σt along random world rays, point by point.
    let mut rng = pixel_rng(5, 0, 0);
    for _ in 0..2000 {
        let p = Vec3::new(rng.gen(), rng.gen(), rng.gen()) * 14.0 - 7.0;
        let (ia, ib) = (
            scene_a.medium.transform.point_to_index(p),
            scene_b.medium.transform.point_to_index(p),
        );
        assert!(
            (scene_a.medium.sigma_t(ia) - scene_b.medium.sigma_t(ib)).abs() < 1e-4,
            "at {p}"
        );
    }
    // And the renders agree within noise.
    let (a, _) = render(&scene_a, &options(256, 64));
    let (b, _) = render(&scene_b, &options(256, 64));
    assert!(
        (a.mean() - b.mean()).abs().max_element() < 0.01,
        "{} vs {}",
        a.mean(),
        b.mean()
    );
    let rms = (a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(x, y)| (*x - *y).length_squared())
        .sum::<f32>()
        / a.pixels.len() as f32)
        .sqrt();
    assert!(rms < 0.05, "per-pixel rms difference {rms}");
}

#[test]
fn rotated_box_transmittance_matches_world_space_geometry() {
    // A box turned by 30° about an oblique axis with anisotropic voxels: transmittance along a
    // world ray is exp(−σ·chord), the chord computed here from the world-space box.
    let n = 8;
    let size = DVec3::new(1.0, 1.5, 0.5);
    let rot = DMat3::from_axis_angle(DVec3::new(1.0, 2.0, 0.5).normalize(), 30f64.to_radians());
    let scene = SceneBuilder::new(40.0, 10.0, 1).build(
        grid(n, |_| 1.0),
        affine(rot * DMat3::from_diagonal(size), n),
        0.2,
        Vec3::ONE,
        0.0,
        Filter::Nearest,
        GRID4,
    );
    let mut rng = pixel_rng(9, 0, 0);
    let mut stats = TrackingStats::default();
    for k in 0..6 {
        let o = Vec3::new(0.3 * k as f32 - 0.8, 0.2, 20.0);
        let w = Vec3::new(0.02 * k as f32, -0.01, -1.0).normalize();
        // The chord in the box's own frame: rotate the ray back, slab-test against ±half extents.
        let half = size * n as f64 * 0.5;
        let (lo, d) = (
            rot.transpose() * o.as_dvec3(),
            rot.transpose() * w.as_dvec3(),
        );
        let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
        for a in 0..3 {
            let (u, v) = ((-half[a] - lo[a]) / d[a], (half[a] - lo[a]) / d[a]);
            t0 = t0.max(u.min(v));
            t1 = t1.min(u.max(v));
        }
        let chord = (t1 - t0).max(0.0);
        let ray = scene.medium.to_index_ray(o, w);
        let estimate = match scene.medium.intersect(&ray) {
            Some((a, b)) => {
                (0..20_000)
                    .map(|_| transmittance(&scene.medium, &ray, a, b, &mut rng, &mut stats) as f64)
                    .sum::<f64>()
                    / 20_000.0
            }
            None => 1.0,
        };
        let expected = (-0.2 * chord).exp();
        assert!(
            (estimate - expected).abs() < 0.01,
            "ray {k}: chord {chord:.3}, T̂ {estimate:.4} vs {expected:.4}"
        );
    }
}

#[test]
fn the_same_seed_gives_the_same_image_on_any_thread_count() {
    let scene = SceneBuilder::new(30.0, 40.0, 20)
        .constant_light(Vec3::ONE)
        .build(
            lumpy_ball(12),
            centred(12, 1.0),
            0.5,
            Vec3::splat(0.9),
            0.5,
            Filter::Trilinear,
            GRID8,
        );
    let run = |threads| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| render(&scene, &options(4, 64)).0)
    };
    let one = run(1);
    assert_eq!(one, run(3));
    let mut other = options(4, 64);
    other.seed = 8;
    assert_ne!(
        one,
        render(&scene, &other).0,
        "a different seed must give a different image"
    );
}

#[test]
fn majorant_grid_tracks_more_efficiently_than_a_global_majorant() {
    let make = |m| {
        SceneBuilder::new(30.0, 40.0, 8)
            .constant_light(Vec3::ONE)
            .build(
                lumpy_ball(24),
                centred(24, 1.0),
                0.5,
                Vec3::splat(0.9),
                0.0,
                Filter::Trilinear,
                m,
            )
    };
    let (_, grid_stats) = render(&make(GRID4), &options(16, 64));
    let (_, global_stats) = render(&make(Majorant::global()), &options(16, 64));
    assert!(
        grid_stats.tracking_efficiency() > 1.3 * global_stats.tracking_efficiency(),
        "{} vs {}",
        grid_stats.tracking_efficiency(),
        global_stats.tracking_efficiency()
    );
}

#[test]
fn one_light_nee_has_the_mean_of_all_light_nee() {
    // The gradient passes' probes pick one light ∝ its unoccluded contribution and divide by the
    // probability: the mean must be the all-lights NEE's. A sun and a sky of comparable size, seen
    // from a point inside the block, so that both are picked and both are partly shadowed.
    use volgrad::render::path::{direct_light, direct_light_one, LightSample};
    let scene = lumpy_block_scene(Filter::Trilinear, false, 0.9);
    let p = scene
        .medium
        .transform
        .point_to_world(Vec3::new(2.5, 1.5, 3.0));
    let dir = Vec3::new(0.3, -0.2, 0.93).normalize();
    let mut rng = pixel_rng(7, 3, 1);
    let mut stats = TrackingStats::default();
    let n = 40_000;
    let (mut all, mut one) = ([0.0f64; 2], [0.0f64; 2]);
    for _ in 0..n {
        let sample = LightSample::draw(&mut rng);
        let a = direct_light(&scene, p, dir, &sample, &mut rng, &mut stats, None).x as f64;
        let o = direct_light_one(&scene, p, dir, &sample, &mut rng, &mut stats, None).x as f64;
        all = [all[0] + a, all[1] + a * a];
        one = [one[0] + o, one[1] + o * o];
    }
    let mean_se = |s: [f64; 2]| {
        let m = s[0] / n as f64;
        (m, ((s[1] / n as f64 - m * m) / n as f64).sqrt())
    };
    let ((ma, sa), (mo, so)) = (mean_se(all), mean_se(one));
    let z = (ma - mo) / (sa * sa + so * so).sqrt();
    assert!(
        z.abs() < 4.0,
        "all lights {ma} ± {sa}, one light {mo} ± {so}"
    );
    // Not a vacuous check: resolved to 2 %, far finer than either light's share (the sun and the
    // sky are of comparable size), so a light dropped or a pick without its 1/P would fail.
    assert!(so < 0.02 * mo, "one light {mo} ± {so}");
}
