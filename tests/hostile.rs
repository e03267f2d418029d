//! Extreme but legal scenes, built in memory: whatever the renderer and the estimators are given
//! within the documented ranges, they write finite numbers, and they stay correct where that can be
//! checked in closed form; and a process whose output pipe closes early ends quietly. (Bad files and
//! bad scene values are in tests/cli.rs and tests/bridge.rs.)

mod common;

use common::*;
use glam::Vec3;
use volgrad::gradient::adjoint::Estimator;
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{gradient, GradOptions};
use volgrad::io::images::RgbImage;
use volgrad::render::image::{render, RenderOptions};
use volgrad::volume::majorant::Majorant;
use volgrad::volume::medium::Filter;

fn options(spp: u32, max_depth: u32) -> RenderOptions {
    RenderOptions {
        spp,
        seed: 5,
        max_depth,
        progress: false,
    }
}

/// Henyey–Greenstein with |g| → 1 (the density at cos θ = 1 grows as 1/(1 − g)²): every pixel and
/// every gradient voxel of every estimator is finite, and no sample had to be dropped.
#[test]
fn a_peaked_phase_function_gives_finite_images_and_gradients() {
    for g in [0.9f32, 0.99, 0.999, 0.9995, 0.9999, 0.99999] {
        for g in [g, -g] {
            let mut scene = lumpy_block_scene(Filter::Trilinear, true, 0.9);
            scene.medium.phase_g = g;
            let (image, stats) = render(&scene, &options(16, 16));
            assert_eq!(
                stats.non_finite, 0,
                "g = {g}: dropped samples in the render"
            );
            assert!(image.pixels.iter().all(|c| c.is_finite()), "g = {g}");
            let adjoint = Loss::Mean.adjoint(&RgbImage::new(8, 8), None);
            for estimator in [Estimator::Joint, Estimator::Drt, Estimator::Naive] {
                let run = gradient(&scene, &adjoint, &GradOptions::new(estimator, 8, 3, 16));
                assert_eq!(
                    run.stats.non_finite, 0,
                    "g = {g}, {estimator}: dropped samples"
                );
                let voxels = run.gradient.voxels().len();
                assert!(voxels > 100, "g = {g}, {estimator}: {voxels} voxels");
                assert!(
                    run.values().voxels().all(|(_, v)| v.is_finite()),
                    "g = {g}, {estimator}: non-finite gradient"
                );
            }
        }
    }
}

/// The white furnace (albedo 1 under a constant sky: every pixel sees the sky's radiance) with a
/// strongly peaked phase function: MIS between phase and environment sampling needs the phase
/// density to match its sampling exactly, which f32 cancellation broke near |g| = 1.
#[test]
fn white_furnace_holds_for_a_peaked_phase_function() {
    let radiance = Vec3::new(0.7, 0.5, 0.3);
    for g in [0.999, -0.999] {
        let scene = SceneBuilder::new(30.0, 40.0, 8)
            .constant_light(radiance)
            .build(
                grid(10, |_| 1.0),
                centred(10, 1.0),
                0.8,
                Vec3::ONE,
                g,
                Filter::Trilinear,
                Majorant::grid(4),
            );
        let (image, stats) = render(&scene, &options(256, 100_000));
        assert_eq!(stats.non_finite, 0);
        let mean = image.mean();
        assert!(
            (mean / radiance - 1.0).abs().max_element() < 0.01,
            "g = {g}: mean {mean} vs {radiance}"
        );
    }
}

/// A real file with one bit flipped, or cut short, at fixed offsets across its header, its
/// transform and metadata, and its compressed voxel data: `info` and `render` either succeed with a
/// finite image or fail cleanly (exit status 1, an error naming the file), never abort, hang or panic.
#[test]
fn corrupted_copies_of_a_real_file_fail_cleanly_or_render_finitely() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let original = std::fs::read(root.join("scenes/assets/wdas_cloud_sixteenth.vdb")).unwrap();
    let scene_text = std::fs::read_to_string(root.join("scenes/cloud.toml"))
        .unwrap()
        .replace("assets/wdas_cloud_sixteenth.vdb", "hostile.vdb")
        .replace("width    = 256", "width    = 12")
        .replace("height   = 256", "height   = 12");
    let dir = tempfile::tempdir().unwrap();
    let (vdb, scene, exr) = (
        dir.path().join("hostile.vdb"),
        dir.path().join("hostile.toml"),
        dir.path().join("hostile.exr"),
    );
    std::fs::write(&scene, scene_text).unwrap();
    let n = original.len();
    let flips = [
        8,
        20,
        100,
        200,
        1000,
        5000,
        n / 8,
        n / 4,
        n / 2,
        3 * n / 4,
        n - 200,
        n - 5,
    ];
    let mut cases: Vec<(String, Vec<u8>)> = flips
        .iter()
        .map(|&at| {
            let mut bytes = original.clone();
            bytes[at] ^= 0x10;
            (format!("bit flipped at byte {at}"), bytes)
        })
        .collect();
    for at in [n / 3, n - 1] {
        cases.push((format!("cut at byte {at}"), original[..at].to_vec()));
    }
    let (mut rendered, mut refused) = (0, 0);
    for (what, bytes) in cases {
        std::fs::write(&vdb, bytes).unwrap();
        let info = volgrad(&["info", vdb.to_str().unwrap()]);
        let render = volgrad(&[
            "render",
            scene.to_str().unwrap(),
            "--spp",
            "1",
            "-o",
            exr.to_str().unwrap(),
            "--force",
            "-q",
        ]);
        for (command, o) in [("info", &info), ("render", &render)] {
            if o.status.success() {
                continue;
            }
            let err = stderr(o);
            assert_eq!(
                o.status.code(),
                Some(1),
                "{what}: {command} did not fail cleanly: {err}"
            );
            assert_clean_error(o, &["hostile"]);
            refused += usize::from(command == "render");
        }
        if render.status.success() {
            let image = volgrad::io::images::read_rgb(&exr).unwrap();
            assert!(
                image.pixels.iter().all(|c| c.is_finite()),
                "{what}: non-finite pixels"
            );
            rendered += 1;
        }
    }
    // Both outcomes occur: the corpus exercises the checks, not only the happy path.
    assert!(
        rendered > 0 && refused > 0,
        "{rendered} rendered, {refused} refused"
    );
}

/// `volgrad info big.vdb | head -1`: the reader goes away early. The process must end quietly
/// (killed by SIGPIPE, as `cat` would be), not panic in `println!`.
#[test]
fn a_closed_pipe_ends_the_process_quietly() {
    use std::os::unix::process::ExitStatusExt;
    use std::process::{Command, Stdio};
    let mut child = Command::new(env!("CARGO_BIN_EXE_volgrad"))
        .args([
            "info",
            concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/scenes/assets/wdas_cloud_sixteenth.vdb"
            ),
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take()); // close the read end before volgrad writes
    let output = child.wait_with_output().unwrap();
    let err = stderr(&output);
    assert!(!err.contains("panicked"), "{err}");
    const SIGPIPE: i32 = 13; // on Linux
    assert_eq!(output.status.signal(), Some(SIGPIPE), "{err}");
}

/// A ray that is nowhere (NaN or infinite origin, direction or bounds) ends every tracker at
/// once: no collision, transmittance 1 or a finite estimate, never a walk that steps from NaN to
/// NaN forever. (A camera far from the origin used to give such rays.)
#[test]
fn trackers_end_on_rays_that_are_not_finite() {
    use volgrad::volume::ray::IndexRay;
    use volgrad::volume::tracking::{
        sample_collision, sample_transmittance_distance, transmittance, TrackingStats,
    };
    let scene = lumpy_block_scene(Filter::Trilinear, false, 0.5);
    let medium = &scene.medium;
    let good = medium.to_index_ray(Vec3::new(0.0, 0.0, 20.0), Vec3::NEG_Z);
    let nan = Vec3::splat(f32::NAN);
    let cases = [
        (good, f32::NAN, 40.0),
        (good, 0.0, f32::NAN),
        (good, f32::NEG_INFINITY, 40.0),
        (IndexRay { o: nan, d: good.d }, 0.0, 40.0),
        (IndexRay { o: good.o, d: nan }, 0.0, 40.0),
        (
            IndexRay {
                o: Vec3::splat(f32::INFINITY),
                d: good.d,
            },
            0.0,
            40.0,
        ),
    ];
    let mut rng = volgrad::render::sampling::pixel_rng(1, 0, 0);
    let mut stats = TrackingStats::default();
    let started = std::time::Instant::now();
    for (ray, t0, t1) in cases {
        for _ in 0..100 {
            assert_eq!(
                sample_collision(medium, &ray, t0, t1, &mut rng, &mut stats),
                None
            );
            let tr = transmittance(medium, &ray, t0, t1, &mut rng, &mut stats);
            assert!(tr.is_finite(), "{ray:?} {t0} {t1}: {tr}");
            let _ = sample_transmittance_distance(medium, &ray, t0, t1, &mut rng, &mut stats);
        }
    }
    assert!(started.elapsed().as_secs() < 10);
    // The good ray through the block does collide: the guard is not a blanket refusal.
    let hits = (0..100)
        .filter(|_| sample_collision(medium, &good, 0.0, 40.0, &mut rng, &mut stats).is_some())
        .count();
    assert!(hits > 50, "{hits}");
}

/// An infinite δ in one pixel of an adjoint image: its samples are dropped and counted, and every
/// other pixel's gradient is what it is without that pixel, bit for bit. (The pass's quantum was
/// once taken from the infinite value: 1, which rounded every other sample to 0.)
#[test]
fn an_infinite_adjoint_pixel_is_dropped_and_counted_not_spread() {
    let scene = lumpy_block_scene(Filter::Trilinear, false, 0.5);
    let mut adjoint = Loss::Mean.adjoint(&RgbImage::new(8, 8), None);
    let pixel = 3 * 8 + 4;
    let options = GradOptions::new(Estimator::Joint, 8, 11, 16);
    adjoint[pixel] = Vec3::ZERO;
    let without = gradient(&scene, &adjoint, &options);
    adjoint[pixel] = Vec3::new(f32::INFINITY, 0.0, 0.0);
    let with = gradient(&scene, &adjoint, &options);
    assert_eq!(without.stats.non_finite, 0);
    assert!(with.stats.non_finite > 0, "the pixel's samples are counted");
    assert_eq!(with.gradient.bands, without.gradient.bands);
    // The voxels with a gradient, in order: a pixel of δ = 0 still splats zeros, which can open
    // bricks (and change the order bricks are listed in) where the dropped samples do not.
    let voxels = |run: &volgrad::gradient::passes::GradientRun| -> Vec<_> {
        let mut voxels: Vec<_> = (run.gradient.voxels().into_iter())
            .filter(|&(_, q)| q != 0.0)
            .map(|(v, q)| (v.to_array(), q.to_bits()))
            .collect();
        voxels.sort_unstable();
        voxels
    };
    assert!(voxels(&without).iter().any(|&(_, q)| q != 0));
    assert_eq!(voxels(&with), voxels(&without));
}

/// Pixels whose δ is 10⁹ to 10²⁹ times the others' (a firefly in a target, the sun in a
/// photograph's sky) where the camera sees only sky: their paths add nothing, and the others'
/// gradient keeps its digits. The quantum once followed the largest δ alone: the others' samples,
/// 10⁹ times smaller, came out 5 times off; with one quantum for every pixel (sized for one
/// sample of the largest and for the sum of all), 10¹² left 80 voxels of a few quanta each, 10²⁰
/// and beyond a gradient of exactly 0. Beyond 2³⁶ the hot pixels get a band and quantum of their
/// own, and the others' gradient is theirs alone, bit for bit.
#[test]
fn hot_adjoint_pixels_that_see_only_sky_leave_the_others_their_digits() {
    let mut scene = lumpy_block_scene(Filter::Trilinear, false, 0.5);
    // 90° at distance 14: the 6-wide block fills the middle of the image, the corners are sky.
    scene.camera = volgrad::render::camera::Camera::new(
        Vec3::new(0.0, 0.0, 14.0),
        Vec3::ZERO,
        Vec3::Y,
        90.0,
        8,
        8,
    );
    let mut adjoint = Loss::Mean.adjoint(&RgbImage::new(8, 8), None);
    let options = GradOptions::new(Estimator::Joint, 4, 11, 16);
    let (corners, ordinary) = ([0, 7, 56, 63], adjoint[1]);
    for c in corners {
        adjoint[c] = Vec3::ZERO;
    }
    let without = gradient(&scene, &adjoint, &options).values();
    let a = without.sum();
    let hot = |hot: &[usize], factor: f32| {
        let mut adjoint = adjoint.clone();
        for &c in hot {
            adjoint[c] = Vec3::splat(factor * ordinary.x);
        }
        gradient(&scene, &adjoint, &options)
    };
    // Within the range: one band, and the others' samples rounded to the hot pixel's quantum.
    let b = hot(&corners[..1], 1e9).values().sum();
    assert!(
        a != 0.0 && ((b - a) / a).abs() < 0.01,
        "⟨g, 1⟩ {a} without the hot pixel, {b} with it"
    );
    for (pixels, factor) in [(1, 1e12), (1, 1e20), (1, 1e29), (4, 1e25)] {
        let run = hot(&corners[..pixels], factor);
        assert_eq!(run.gradient.bands.len(), 2, "{pixels} pixels of {factor:e}");
        let with: Vec<_> = (run.values().voxels())
            .map(|(v, g)| (v, g.to_bits()))
            .collect();
        let expected: Vec<_> = (without.voxels()).map(|(v, g)| (v, g.to_bits())).collect();
        assert!(
            with == expected,
            "{pixels} pixels of {factor:e}: ⟨g, 1⟩ {} against {a}",
            run.values().sum()
        );
    }
}
