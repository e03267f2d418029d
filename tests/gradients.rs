//! Gradient estimators against finite differences and closed forms, on small grids.
//!
//! Each estimator runs with several seeds; a check compares the mean with the finite-difference
//! value through z = (est − fd) / √(se_est² + se_fd²). A correct estimator stays within |z| < 4.5;
//! the margins were chosen so that a dropped term (the escape term, the scattering part, the shadow
//! rays' derivative) or a missing factor moves z far beyond that.

mod common;

use common::*;
use glam::{IVec3, Vec3};
use volgrad::gradient::adjoint::{Estimator, Suffix};
use volgrad::gradient::fd::{self, FdOptions};
use volgrad::gradient::grid::GradientGrid;
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{
    add_gradient_of, derivative_image, gradient, gradient_grid_for, sample_scale, BandedGradient,
    GradOptions, Parameter, QuantumBands,
};
use volgrad::gradient::pixel_samples::PixelSamples;
use volgrad::gradient::runs::MeanAndError;
use volgrad::render::pixel_set::PixelSet;
use volgrad::render::scene::Scene;
use volgrad::volume::majorant::Majorant;
use volgrad::volume::medium::Filter;

const N: i32 = 6;

fn scene(filter: Filter, empty_voxels: bool, albedo: f32) -> Scene {
    lumpy_block_scene(filter, empty_voxels, albedo)
}

/// Estimator runs and finite differences both use the scene's max_depth.
fn options(scene: &Scene, estimator: Estimator, spp: u32, seed: u64) -> GradOptions {
    GradOptions::new(estimator, spp, seed, scene.settings.max_depth)
}

/// Gradients of the mean pixel value from `repeats` seeds.
fn runs(scene: &Scene, estimator: Estimator, spp: u32, repeats: u64) -> Vec<GradientGrid<f32>> {
    let adjoint = Loss::Mean.adjoint(
        &volgrad::io::images::RgbImage::new(scene.camera.width, scene.camera.height),
        None,
    );
    (0..repeats)
        .map(|r| gradient(scene, &adjoint, &options(scene, estimator, spp, 100 + r)).values())
        .collect()
}

/// Mean and standard error of a linear functional over the runs.
fn mean_se(runs: &[GradientGrid<f32>], f: impl Fn(&GradientGrid<f32>) -> f64) -> (f64, f64) {
    let values: Vec<f64> = runs.iter().map(f).collect();
    let m = MeanAndError::of(&values);
    (m.mean, m.se)
}

fn fd_along(scene: &Scene, direction: &fd::Direction) -> fd::FdResult {
    // A larger step makes fewer tentative-collision decisions flip per unit of derivative; the
    // O(ε²) (central) and O(ε³) (one-sided) errors stay far below the noise.
    let options = FdOptions {
        loss: Loss::Mean,
        eps: 0.15,
        spp: 4096,
        repeats: 8,
        seed: 1,
        max_depth: scene.settings.max_depth,
    };
    fd::directional_derivative(scene, None, direction, &options).unwrap()
}

fn z(est: (f64, f64), fd: &fd::FdResult) -> f64 {
    (est.0 - fd.value) / (est.1 * est.1 + fd.std_err * fd.std_err).sqrt()
}

fn all_voxels(scene: &Scene) -> Vec<IVec3> {
    let (lo, hi) = fd::domain_bounds(&scene.medium.grid).unwrap();
    fd::box_voxels(&scene.medium.grid, lo, hi, false)
}

#[test]
fn joint_and_drt_agree_with_finite_differences() {
    let scene = scene(Filter::Trilinear, true, 0.8);
    let probes = [
        IVec3::new(2, 3, 2),
        IVec3::new(5, 1, 4),
        IVec3::new(0, 0, 0),
        IVec3::new(3, 3, 5),
    ];
    assert_eq!(
        scene.medium.grid.voxel(IVec3::new(0, 0, 0)),
        0.0,
        "one probe is an empty voxel"
    );
    let empty_box = (IVec3::new(-1, -1, 3), IVec3::new(2, 2, 6));
    let fd_voxels: Vec<_> = probes
        .iter()
        .map(|&v| fd_along(&scene, &vec![(v, 1.0)]))
        .collect();
    let fd_box = fd_along(
        &scene,
        &fd::ones(&fd::box_voxels(
            &scene.medium.grid,
            empty_box.0,
            empty_box.1,
            false,
        )),
    );
    let fd_all = fd_along(&scene, &fd::ones(&all_voxels(&scene)));
    for estimator in [Estimator::Joint, Estimator::Drt] {
        let grads = runs(&scene, estimator, 64, 8);
        for (v, fd) in probes.iter().zip(&fd_voxels) {
            let est = mean_se(&grads, |g| g.get(*v));
            let z = z(est, fd);
            assert!(
                z.abs() < 4.5,
                "{estimator:?} voxel {v}: {:.5} ± {:.5} vs fd {:.5} ± {:.5} (z = {z:.2})",
                est.0,
                est.1,
                fd.value,
                fd.std_err
            );
        }
        let est = mean_se(&grads, |g| g.sum_in_box(empty_box.0, empty_box.1));
        assert!(
            z(est, &fd_box).abs() < 4.5,
            "{estimator:?} box: {est:?} vs {fd_box:?}"
        );
        let est = mean_se(&grads, |g| g.sum());
        assert!(
            z(est, &fd_all).abs() < 4.5,
            "{estimator:?} ⟨g, 1⟩: {est:?} vs {fd_all:?}"
        );
        // The check has teeth: half the gradient would be far outside the error bars.
        assert!(
            ((est.0 * 0.5 - fd_all.value)
                / (est.1 * est.1 + fd_all.std_err * fd_all.std_err).sqrt())
            .abs()
                > 8.0,
            "{estimator:?}: ⟨g, 1⟩ too noisy to test"
        );
    }
}

#[test]
fn per_segment_suffixes_agree_with_per_path_ones_and_with_fd() {
    let scene = scene(Filter::Trilinear, true, 0.9);
    let fd_all = fd_along(&scene, &fd::ones(&all_voxels(&scene)));
    let adjoint = Loss::Mean.adjoint(&volgrad::io::images::RgbImage::new(8, 8), None);
    let run = |suffix, suffix_paths| -> Vec<GradientGrid<f32>> {
        (0..8)
            .map(|r| {
                let mut o = options(&scene, Estimator::Joint, 32, 300 + r);
                o.adjoint.suffix = suffix;
                o.adjoint.suffix_paths = suffix_paths;
                gradient(&scene, &adjoint, &o).values()
            })
            .collect()
    };
    let per_segment = mean_se(&run(Suffix::PerSegment, 1), |g| g.sum());
    assert!(
        z(per_segment, &fd_all).abs() < 4.5,
        "per-segment ⟨g, 1⟩: {per_segment:?} vs {fd_all:?}"
    );
    // K suffix paths per camera path, each weighted 1/(K·P_j): any K has the same mean (a weight
    // without the 1/K moves ⟨g, 1⟩ by many standard errors at K = 5).
    for k in [1, 2, 5] {
        let per_path = mean_se(&run(Suffix::PerPath, k), |g| g.sum());
        let z_between =
            (per_segment.0 - per_path.0) / (per_segment.1.powi(2) + per_path.1.powi(2)).sqrt();
        assert!(
            z_between.abs() < 4.5,
            "per-segment {per_segment:?} vs {k} per path {per_path:?}"
        );
    }
}

#[test]
fn truncated_paths_are_differentiated_at_their_own_depth() {
    // At max_depth 0, 1 and 2 the truncation carries much of the gradient: an off-by-one in the
    // depth at which a probe may still scatter moves ⟨g, 1⟩ by many standard errors (the
    // neighbouring depths' finite differences, asserted apart below).
    let mut fds = Vec::new();
    for depth in [0, 1, 2] {
        let mut scene = scene(Filter::Trilinear, true, 0.95);
        scene.settings.max_depth = depth;
        let fd_all = fd_along(&scene, &fd::ones(&all_voxels(&scene)));
        fds.push((fd_all.value, fd_all.std_err));
        for estimator in [Estimator::Joint, Estimator::Drt] {
            let est = mean_se(&runs(&scene, estimator, 32, 8), |g| g.sum());
            assert!(
                z(est, &fd_all).abs() < 4.5,
                "max_depth {depth} {estimator:?}: {est:?} vs {fd_all:?}"
            );
        }
    }
    for pair in fds.windows(2) {
        let ((a, a_se), (b, b_se)) = (pair[0], pair[1]);
        assert!((a - b).abs() > 8.0 * a_se.hypot(b_se), "{pair:?}");
    }
}

#[test]
fn homogeneous_absorber_matches_the_closed_form() {
    // Albedo 0, constant sky L, nearly parallel rays crossing n voxels of σ = s·θ:
    // pixel = L e^{−sθn}, so d(mean pixel)/dθ (θ the same in every voxel) = −L s n e^{−sθn}.
    let n = 8;
    let (s, theta, l) = (0.1f32, 1.0f32, 1.0f32);
    let scene = SceneBuilder::new(300.0, 1.0, 4)
        .constant_light(Vec3::splat(l))
        .build(
            grid(n, |_| theta),
            centred(n, 1.0),
            s,
            Vec3::ZERO,
            0.0,
            Filter::Nearest,
            Majorant::grid(4),
        );
    let expected = -(l * s * n as f32 * (-s * theta * n as f32).exp()) as f64;
    for estimator in [Estimator::Joint, Estimator::Drt, Estimator::Naive] {
        let grads = runs(&scene, estimator, 256, 6);
        let (mean, se) = mean_se(&grads, |g| g.sum());
        assert!(
            (mean - expected).abs() < 4.5 * se + 0.002 * expected.abs(),
            "{estimator:?}: {mean} ± {se} vs {expected}"
        );
        assert!(
            se < 0.02 * expected.abs(),
            "{estimator:?}: standard error {se} too large to test"
        );
    }
}

#[test]
fn naive_is_biased_in_empty_voxels_and_agrees_without_them() {
    // An empty box between lumps: the true gradient there has a scattering part that free-flight
    // sampling can never see (it only collides where σt > 0).
    let scene_empty = scene(Filter::Nearest, true, 0.9);
    let empties: Vec<IVec3> = all_voxels(&scene_empty)
        .into_iter()
        .filter(|&v| {
            scene_empty.medium.grid.voxel(v) == 0.0 && scene_empty.medium.grid.is_active(v)
        })
        .collect();
    assert!(empties.len() > 20);
    let fd_empty = fd_along(&scene_empty, &fd::ones(&empties));
    let naive = runs(&scene_empty, Estimator::Naive, 64, 8);
    let est = mean_se(&naive, |g| empties.iter().map(|&v| g.get(v)).sum());
    let z_naive = z(est, &fd_empty);
    assert!(
        z_naive < -6.0,
        "naive must be biased low in empty voxels: {est:?} vs {fd_empty:?} (z = {z_naive:.1})"
    );
    let joint = runs(&scene_empty, Estimator::Joint, 64, 8);
    let est = mean_se(&joint, |g| empties.iter().map(|&v| g.get(v)).sum());
    assert!(
        z(est, &fd_empty).abs() < 4.5,
        "joint in empty voxels: {est:?} vs {fd_empty:?}"
    );

    let scene_full = scene(Filter::Nearest, false, 0.9);
    let fd_all = fd_along(&scene_full, &fd::ones(&all_voxels(&scene_full)));
    let naive = runs(&scene_full, Estimator::Naive, 64, 8);
    let est = mean_se(&naive, |g| g.sum());
    assert!(
        z(est, &fd_all).abs() < 4.5,
        "naive without empty voxels: {est:?} vs {fd_all:?}"
    );
}

#[test]
fn gradients_stay_finite_in_extreme_media() {
    let make = |grid, density_scale, filter| {
        SceneBuilder::new(14.0, 35.0, 6)
            .constant_light(Vec3::ONE)
            .build(
                grid,
                centred(N, 1.0),
                density_scale,
                Vec3::splat(0.9),
                0.5,
                filter,
                Majorant::grid(4),
            )
    };
    let dense = make(grid(N, |_| 1.0), 1e4, Filter::Trilinear);
    let vacuum = make(grid(N, |_| 0.0), 1.0, Filter::Trilinear);
    let hot = make(
        grid(N, |v| if v == IVec3::splat(3) { 1e3 } else { 0.0 }),
        1.0,
        Filter::Nearest,
    );
    for (name, scene) in [
        ("τ ≫ 87", &dense),
        ("σ = 0", &vacuum),
        ("one dense voxel", &hot),
    ] {
        for estimator in [Estimator::Joint, Estimator::Drt, Estimator::Naive] {
            // The sink drops a non-finite sample before the grid sees it, so a finite grid alone
            // proves nothing: no sample may have been dropped.
            let adjoint = Loss::Mean.adjoint(
                &volgrad::io::images::RgbImage::new(scene.camera.width, scene.camera.height),
                None,
            );
            let run = gradient(scene, &adjoint, &options(scene, estimator, 16, 100));
            assert_eq!(
                run.stats.non_finite, 0,
                "{name} {estimator:?}: non-finite samples dropped"
            );
            assert!(
                run.values().voxels().all(|(_, x)| x.is_finite()),
                "{name} {estimator:?}: non-finite gradient"
            );
        }
    }
    // In vacuum the gradient is the pure transmittance derivative: negative and non-zero.
    let g = &runs(&vacuum, Estimator::Joint, 16, 1)[0];
    assert!(g.sum() < 0.0);
}

#[test]
fn probes_stay_inside_the_medium_bounds() {
    // Gradient samples may only land on voxels that a lookup inside the box can weight.
    let scene = scene(Filter::Trilinear, true, 0.8);
    let (lo, hi) = fd::domain_bounds(&scene.medium.grid).unwrap();
    for estimator in [Estimator::Joint, Estimator::Drt, Estimator::Naive] {
        let wide = (lo - 4, hi + 4);
        let (image, _) =
            derivative_image(&scene, wide.0, wide.1, &options(&scene, estimator, 16, 5));
        let (inside, _) = derivative_image(&scene, lo, hi, &options(&scene, estimator, 16, 5));
        assert_eq!(
            image, inside,
            "{estimator:?}: gradient samples outside the domain"
        );
        // Voxels beyond the trilinear apron (hi + 1 still gets weight from the last half voxel)
        // receive nothing.
        let (outer, _) =
            derivative_image(&scene, hi + 2, hi + 5, &options(&scene, estimator, 16, 5));
        assert!(outer.pixels.iter().all(|c| *c == Vec3::ZERO));
    }
}

#[test]
fn derivative_image_sums_to_the_gradient_of_the_mean() {
    let scene = scene(Filter::Trilinear, true, 0.8);
    let (lo, hi) = (IVec3::new(1, 1, 1), IVec3::new(3, 4, 2));
    let fd = fd_along(
        &scene,
        &fd::ones(&fd::box_voxels(&scene.medium.grid, lo, hi, false)),
    );
    // mean over pixels and channels of d pixel / d ε = d mean / d ε; the image's own standard
    // error comes from four independent images.
    let values: Vec<f64> = (0..4)
        .map(|seed| {
            let (image, _) = derivative_image(
                &scene,
                lo,
                hi,
                &options(&scene, Estimator::Joint, 128, 9 + seed),
            );
            let mean = image.mean();
            ((mean.x + mean.y + mean.z) / 3.0) as f64
        })
        .collect();
    let mean = values.iter().sum::<f64>() / 4.0;
    let se = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 12.0).sqrt();
    assert!(z((mean, se), &fd).abs() < 4.5, "{mean} ± {se} vs {fd:?}");
}

#[test]
fn adjoint_image_comes_from_a_primal_render_at_the_pass_settings() {
    use volgrad::gradient::objective::{adjoint_image, render_target};
    use volgrad::io::images::RgbImage;
    use volgrad::render::image::{render, RenderOptions};
    let scene = scene(Filter::Trilinear, true, 0.8);
    let options = options(&scene, Estimator::Joint, 4, 21);
    let pixels = (scene.camera.width * scene.camera.height) as usize;

    // mean: δ = 1/(3 · pixels) everywhere, no render and no loss value.
    let mean = adjoint_image(&scene, Loss::Mean, None, &options).unwrap();
    assert!(mean.loss.is_none());
    assert!(mean
        .delta
        .iter()
        .all(|d| *d == Vec3::splat(1.0 / (3 * pixels) as f32)));

    // l2 against the very image the primal render must produce (same spp, seed, depth): δ = 0.
    let primal = render(
        &scene,
        &RenderOptions {
            spp: 4,
            seed: 21,
            max_depth: scene.settings.max_depth,
            progress: false,
        },
    )
    .0;
    let same = adjoint_image(&scene, Loss::L2, Some(&primal), &options).unwrap();
    assert_eq!(same.loss, Some(0.0));
    assert!(same.delta.iter().all(|d| *d == Vec3::ZERO));

    // The target render is seeded apart from the pass, so its noise differs from the primal's.
    let target = render_target(&scene, 4, 21, false);
    let other = adjoint_image(&scene, Loss::L2, Some(&target), &options).unwrap();
    assert!(other.loss.unwrap() > 0.0);

    // A target of another size, or none at all for a loss that needs one, is an error.
    let small = RgbImage::new(2, 2);
    let err = adjoint_image(&scene, Loss::L2, Some(&small), &options)
        .err()
        .unwrap();
    assert!(err.to_string().contains("target is 2×2"), "{err}");
    assert!(adjoint_image(&scene, Loss::L1, None, &options).is_err());
}

#[test]
fn passes_added_into_one_grid_sum_to_their_own_gradients() {
    // An optimisation step adds its views' passes into one grid (`add_gradient_of`): voxel by
    // voxel that must be exactly the sum of the passes' own gradients (quanta add up in any
    // order), not the last pass's alone.
    let scene = scene(Filter::Trilinear, true, 0.8);
    let pixels = scene.camera.width * scene.camera.height;
    let adjoints: Vec<Vec<Vec3>> = (0..2)
        .map(|k| {
            (0..pixels)
                .map(|i| Vec3::new(1.0 + k as f32, (i % 7) as f32 * 0.1, -0.5))
                .collect()
        })
        .collect();
    let spp = 16;
    let scale = sample_scale(&scene, Parameter::Extinction);
    let bands = QuantumBands::of(
        adjoints
            .iter()
            .map(|a| (&a[..], scale, PixelSamples::Uniform)),
        spp,
    );
    let every_pixel = PixelSet::All(pixels);
    let base = options(&scene, Estimator::Joint, spp, 0);
    let mut shared = BandedGradient::new(bands.clone(), gradient_grid_for(&scene, &base));
    let mut separate = std::collections::BTreeMap::<[i32; 3], f64>::new();
    for (k, adjoint) in adjoints.iter().enumerate() {
        let pass = GradOptions {
            seed: 5 + k as u64,
            ..base
        };
        add_gradient_of(&scene, (adjoint, scale), &pass, &every_pixel, &mut shared);
        let mut own = BandedGradient::new(bands.clone(), gradient_grid_for(&scene, &pass));
        add_gradient_of(&scene, (adjoint, scale), &pass, &every_pixel, &mut own);
        for (v, q) in own.voxels() {
            *separate.entry(v.to_array()).or_default() += q;
        }
    }
    separate.retain(|_, q| *q != 0.0);
    let shared: std::collections::BTreeMap<[i32; 3], f64> = (shared.voxels().into_iter())
        .filter(|(_, q)| *q != 0.0)
        .map(|(v, q)| (v.to_array(), q))
        .collect();
    assert!(separate.len() > 20, "{} voxels", separate.len());
    assert_eq!(shared, separate);
}

#[test]
fn paths_that_follow_the_adjoint_keep_the_gradients_expectation() {
    // An optimisation's passes spread their paths over the pixels in proportion to |δ|
    // (`PixelSamples`): nine pixels in ten have a small δ and an expected count of about half a
    // path, drawn as 0 or 1 path that weighs δ / m. Over many seeds ⟨g, 1⟩ and the gradient of
    // the grid's lower half agree with uniform paths. Weighing a path by the count drawn (δ / n)
    // instead moves ⟨g, 1⟩ by a fifth (z = 8.9), by spp instead of m threefold (z = −32; both
    // checked).
    let scene = scene(Filter::Trilinear, true, 0.8);
    let pixels = scene.camera.width * scene.camera.height;
    let adjoint: Vec<Vec3> = (0..pixels)
        .map(|i| match i % 10 {
            0 => Vec3::new(1.0, 0.8, 1.2),
            _ => Vec3::splat(0.1),
        })
        .collect();
    let uniform = |seed| options(&scene, Estimator::Joint, 16, seed);
    let listed: Vec<_> = adjoint
        .iter()
        .map(|d| (d.abs().element_sum(), 1.0))
        .collect();
    let following = PixelSamples::following_adjoint(&listed, 1);
    let PixelSamples::Adjoint { per_adjoint } = following else {
        panic!("{following:?}")
    };
    let small = per_adjoint * 0.3;
    assert!(
        (0.4..0.7).contains(&small),
        "a small-δ pixel's expected count {small}"
    );
    let adjoint_paths = |seed| GradOptions {
        samples: following,
        ..options(&scene, Estimator::Joint, 1, seed)
    };
    let lower_half = |g: &GradientGrid<f32>| {
        (g.voxels().filter(|(v, _)| v.z < N / 2))
            .map(|(_, x)| x)
            .sum::<f64>()
    };
    let total = |g: &GradientGrid<f32>| g.voxels().map(|(_, x)| x).sum::<f64>();
    let run = |options: &dyn Fn(u64) -> GradOptions, repeats: u64| -> Vec<GradientGrid<f32>> {
        (0..repeats)
            .map(|r| gradient(&scene, &adjoint, &options(300 + r)).values())
            .collect()
    };
    let (reference, following_runs) = (run(&uniform, 100), run(&adjoint_paths, 1000));
    for (what, f) in [
        ("⟨g, 1⟩", &total as &dyn Fn(&_) -> f64),
        ("the lower half", &lower_half),
    ] {
        let (a, b) = (mean_se(&reference, f), mean_se(&following_runs, f));
        let z = (b.0 - a.0) / (a.1 * a.1 + b.1 * b.1).sqrt();
        assert!(
            z.abs() < 4.5,
            "{what}: uniform {:.5} ± {:.5}, following the adjoint {:.5} ± {:.5} (z = {z:.2})",
            a.0,
            a.1,
            b.0,
            b.1
        );
        assert!(
            b.1 < 0.05 * b.0.abs(),
            "{what}: too noisy to tell ({:?})",
            b
        );
    }
}

#[test]
fn samples_far_below_a_quantum_keep_their_sum() {
    // A pass adds its samples in whole quanta, sized by the largest |δ| (`bands`): beside
    // one pixel whose adjoint is 10⁸ times the others', theirs are fractions of a quantum. The
    // same paths with quanta 2²⁶ times coarser must keep ⟨g, 1⟩ and the lower half's sum in the
    // mean over seeds (the difference is rounding alone). Rounded with a dither they do; rounded
    // to the nearest quantum they lost 16 % of ⟨g, 1⟩ and 40 % of the lower half (checked: z
    // beyond 20).
    let scene = scene(Filter::Trilinear, true, 0.8);
    let pixels = scene.camera.width * scene.camera.height;
    let adjoint = vec![Vec3::ONE; pixels as usize];
    let spp = 4;
    let scale = sample_scale(&scene, Parameter::Extinction);
    let fine = QuantumBands::of([(&adjoint[..], scale, PixelSamples::Uniform)], spp).quantum(0);
    let coarse = fine * 2f64.powi(26);
    let sums = |seed: u64, quantum: f64| {
        let pass = options(&scene, Estimator::Joint, spp, seed);
        let bands = QuantumBands::one(quantum);
        let mut grid = BandedGradient::new(bands, gradient_grid_for(&scene, &pass));
        let all = PixelSet::All(pixels);
        add_gradient_of(&scene, (&adjoint, scale), &pass, &all, &mut grid);
        let sum = |lower: bool| {
            (grid.voxels().into_iter())
                .filter(|(v, _)| !lower || v.z < N / 2)
                .map(|(_, g)| g)
                .sum::<f64>()
        };
        [sum(false), sum(true)]
    };
    let (mut reference, mut rounding) = ([0.0; 2], [Vec::new(), Vec::new()]);
    let seeds = 24;
    for seed in 0..seeds {
        let (exact, rounded) = (sums(seed, fine), sums(seed, coarse));
        for k in 0..2 {
            reference[k] += exact[k] / seeds as f64;
            rounding[k].push(rounded[k] - exact[k]);
        }
    }
    for (k, what) in ["⟨g, 1⟩", "the lower half"].iter().enumerate() {
        let error = MeanAndError::of(&rounding[k]);
        let z = error.mean / error.se;
        assert!(
            z.abs() < 4.5,
            "{what}: rounding moved it by {:.4} ± {:.4} of {:.4} (z = {z:.1})",
            error.mean,
            error.se,
            reference[k]
        );
        assert!(
            error.se < 0.03 * reference[k].abs(),
            "{what}: too noisy to tell ({error:?} of {:.4})",
            reference[k]
        );
    }
}
