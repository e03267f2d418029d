//! Albedo grids (`medium.albedo = { grid = "Cd" }`): a vec3 grid (RGB per voxel) or a float grid
//! (grey), read through the bridge into brick maps of their own. Checked against the constant
//! albedo they hold, a white furnace whose albedo varies per voxel, the refusals, and the albedo
//! gradient (`grad --parameter albedo`) against finite differences.

mod common;

use std::path::Path;

use common::{assert_clean_error, ok, volgrad_in};
use glam::{DVec3, IVec3, Vec3};
use volgrad::gradient::adjoint::Estimator;
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{gradient, GradOptions, Parameter};
use volgrad::io::images::RgbImage;
use volgrad::io::vdb::{self, Grid};
use volgrad::render::image::{render, RenderOptions};
use volgrad::render::scene::Scene;
use volgrad::volume::albedo::Albedo;
use volgrad::volume::brickmap::BrickMap;
use volgrad::volume::transform::IndexTransform;

/// An 8³ block grid named `name` (voxel size 1, centred on the origin).
fn block(name: &str, value: impl Fn(IVec3) -> f32) -> Grid {
    Grid {
        name: name.into(),
        grid_class: "fog volume".into(),
        transform: IndexTransform::uniform(1.0, DVec3::splat(-3.5)),
        bricks: BrickMap::block(8, value),
        background: 0.0,
        saved_as_half: false,
        metadata: Vec::new(),
    }
}

/// `dir/grids.vdb`: "density" (0.2 + 0.1·x), "glow" (1 on every voxel), "grey" (0.6), and the
/// vec3 grid "Cd", `colour` per voxel.
fn write_grids(dir: &Path, colour: impl Fn(IVec3) -> Vec3) {
    let density = block("density", |v| 0.2 + 0.1 * v.x as f32);
    let glow = block("glow", |_| 1.0);
    let grey = block("grey", |_| 0.6);
    let [r, g, b] = [0, 1, 2].map(|c| block("Cd", |v| colour(v)[c]));
    vdb::write_grids_with_colours(
        &dir.join("grids.vdb"),
        &[&density, &glow, &grey],
        &[[&r, &g, &b]],
        false,
        true,
    )
    .unwrap();
}

/// A 3×3 camera on +z with a 1° field of view (every pixel sees the block along its 8 units),
/// nearest lookups (so that a collision reads one voxel of each grid), under `lights`.
fn scene_text(medium: &str, lights: &str, max_depth: u32) -> String {
    format!(
        "[camera]\nposition = [0, 0, 200]\ntarget = [0, 0, 0]\nfov_deg = 1\nwidth = 3\nheight = 3\n\
         [medium]\nvdb = \"grids.vdb\"\nfilter = \"nearest\"\n{medium}\n{lights}\n[render]\nmax_depth = {max_depth}\n"
    )
}

fn load(dir: &Path, medium: &str, lights: &str, max_depth: u32) -> Scene {
    let path = dir.join("scene.toml");
    std::fs::write(&path, scene_text(medium, lights, max_depth)).unwrap();
    Scene::load(&path).unwrap()
}

const SKY: &str = "[[light]]\ntype = \"constant\"\nradiance = [0.9, 0.8, 1.0]\n\
                   [[light]]\ntype = \"directional\"\ndirection = [1, -1, -1]\nirradiance = 2";

fn image(scene: &Scene, spp: u32) -> RgbImage {
    let options = RenderOptions {
        spp,
        seed: 7,
        max_depth: scene.settings.max_depth,
        progress: false,
    };
    render(scene, &options).0
}

/// A grid that holds one albedo everywhere renders exactly as that constant: the same paths, the
/// same weights, bit for bit (RGB from a vec3 grid, grey from a float grid).
#[test]
fn an_albedo_grid_of_one_value_renders_as_that_constant() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_grids(d, |_| Vec3::new(0.8, 0.5, 0.2));
    for (grid, constant) in [("Cd", "[0.8, 0.5, 0.2]"), ("grey", "0.6")] {
        let from_grid = load(
            d,
            &format!("albedo = {{ grid = \"{grid}\" }}\ndensity_scale = 0.5"),
            SKY,
            16,
        );
        assert!(matches!(from_grid.medium.albedo, Albedo::Grid(_)));
        let from_constant = load(
            d,
            &format!("albedo = {constant}\ndensity_scale = 0.5"),
            SKY,
            16,
        );
        let (a, b) = (image(&from_grid, 64), image(&from_constant, 64));
        assert!(a.pixels.iter().any(|c| c.max_element() > 0.05));
        assert_eq!(a.pixels, b.pixels, "albedo grid '{grid}'");
    }
}

/// A white furnace with an albedo grid: a medium emitting Le inside surroundings of radiance Le
/// is in equilibrium whatever its albedo at each point ((1 − α)·Le emitted + α·Le in-scattered),
/// so every pixel is Le while α varies per voxel and per channel from 0 to 1. Taking α from
/// anywhere but the collision's voxel (the constant, or another point) breaks the balance.
#[test]
fn a_furnace_with_varying_albedo_and_matching_emission_stays_uniform() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_grids(d, |v| {
        Vec3::new(v.x as f32 / 7.0, v.y as f32 / 7.0, 1.0 - v.z as f32 / 7.0)
    });
    let s = load(
        d,
        "density_scale = 1.5\nalbedo = { grid = \"Cd\" }\nemission = { grid = \"glow\", radiance = 0.8 }",
        "[[light]]\ntype = \"constant\"\nradiance = 0.8",
        200,
    );
    let pixels = image(&s, 4096).pixels;
    let mean = pixels.iter().sum::<Vec3>() / pixels.len() as f32;
    assert!(
        (mean - Vec3::splat(0.8)).abs().max_element() < 0.01,
        "{mean}"
    );
}

/// Albedo grids that cannot be are refused, naming the grid and what is wrong: a value outside
/// [0, 1] (with its voxel and channel), a background outside it, a missing grid.
#[test]
fn bad_albedo_grids_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let bright = |v: IVec3| {
        let green = if v == IVec3::new(3, 2, 1) { 1.5 } else { 0.5 };
        Vec3::new(0.5, green, 0.5)
    };
    write_grids(d, bright);
    let render = |medium: &str| {
        std::fs::write(d.join("bad.toml"), scene_text(medium, SKY, 4)).unwrap();
        volgrad_in(d, &["render", "bad.toml", "--spp", "1", "-o", "bad.exr"])
    };
    assert_clean_error(
        &render("albedo = { grid = \"Cd\" }"),
        &["'Cd'", "1.5", "voxel (3, 2, 1)", "green", "[0, 1]"],
    );
    assert_clean_error(
        &render("albedo = { grid = \"missing\" }"),
        &["medium.albedo", "no grid named 'missing'"],
    );
    // "density" holds values up to 0.9 (fine); "glow" holds 1 (fine); a background of 2 is not.
    let mut grey = block("grey", |_| 0.5);
    grey.background = 2.0;
    vdb::write_grids(&d.join("other.vdb"), &[&grey], false, true).unwrap();
    assert_clean_error(
        &render("albedo = { grid = \"grey\", vdb = \"other.vdb\" }"),
        &["'grey'", "other.vdb", "background 2"],
    );
    let negative = block("grey", |v| if v.z == 7 { -0.25 } else { 0.5 });
    vdb::write_grids(&d.join("other.vdb"), &[&negative], false, true).unwrap();
    assert_clean_error(
        &render("albedo = { grid = \"grey\", vdb = \"other.vdb\" }"),
        &["'grey'", "-0.25", "voxel (0, 0, 7)"],
    );
}

/// The albedo gradient (`Parameter::Albedo`) against finite differences of every voxel of one
/// channel shifted by ±ε with the same seed. Where collisions fall does not depend on α, and with
/// at most two scattering events Russian roulette never runs, so both sides see the same paths
/// and must agree to 1 % (a term missing from ∂/∂α = NEE + w·R − Le would not: the emission is
/// a third of the light here). Per channel of the vec3 grid, and for a grey grid; over the whole
/// block and over each half of it.
#[test]
fn albedo_gradients_match_finite_differences() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_grids(d, |v| {
        Vec3::new(0.3 + 0.05 * v.y as f32, 0.6, 0.9 - 0.1 * v.z as f32)
    });
    let adjoint =
        |s: &Scene| Loss::Mean.adjoint(&RgbImage::new(s.camera.width, s.camera.height), None);
    let options = |s: &Scene, parameter, channel| GradOptions {
        parameter,
        channel,
        ..GradOptions::new(Estimator::Joint, 512, 5, s.settings.max_depth)
    };
    for (grid, channels) in [
        ("Cd", vec![Some(0), Some(1), Some(2)]),
        ("grey", vec![None]),
    ] {
        let s = load(
            d,
            &format!(
                "density_scale = 0.4\nalbedo = {{ grid = \"{grid}\" }}\nemission = {{ grid = \"glow\", radiance = [0.3, 0.2, 0.1] }}"
            ),
            SKY,
            2,
        );
        // The 8³ block, and its halves along x: a gradient put on the wrong voxels passes on the
        // whole block, not on its halves.
        let regions = [(0, 7), (0, 3), (4, 7)];
        for channel in channels {
            let g = gradient(&s, &adjoint(&s), &options(&s, Parameter::Albedo, channel)).values();
            for (x0, x1) in regions {
                let got: f64 = (g.voxels())
                    .filter(|(v, _)| (x0..=x1).contains(&v.x))
                    .map(|(_, value)| value)
                    .sum();
                let eps = 0.02;
                let shifted = |delta: f32| {
                    let mut s = s.clone();
                    let Albedo::Grid(a) = &mut s.medium.albedo else {
                        unreachable!()
                    };
                    let map = &mut a.channels[channel.unwrap_or(0)];
                    let deltas: Vec<_> = (0..512)
                        .map(|i| IVec3::new(i / 64, (i / 8) % 8, i % 8))
                        .filter(|v| (x0..=x1).contains(&v.x))
                        .map(|v| (v, delta))
                        .collect();
                    *map = map.with_added(&deltas);
                    // The extinction pass's own image: the same camera paths as the albedo pass.
                    let o = options(&s, Parameter::Extinction, None);
                    let image = gradient(&s, &adjoint(&s), &o).image;
                    Loss::Mean.evaluate(&image, None)
                };
                let fd = (shifted(eps) - shifted(-eps)) / (2.0 * eps as f64);
                assert!(fd.abs() > 1e-4, "{grid} {channel:?} x {x0}..{x1}: {fd}");
                assert!(
                    (got - fd).abs() < 0.01 * fd.abs(),
                    "{grid} {channel:?} x {x0}..{x1}: the gradient's sum {got} against finite differences {fd}"
                );
            }
        }
    }
}

/// `make-grid coloured-smoke` writes a density and a vec3 "Cd"; a scene using it renders, `info`
/// names the albedo grid, `grad --parameter albedo` writes its gradient as a vec3 grid "grad_Cd"
/// (as the input), `merge` combines two seeds' into one and refuses to mix it with a density
/// gradient, `gradcheck --parameter albedo` passes, and a constant albedo is refused for it.
#[test]
fn coloured_smoke_renders_and_exports_an_rgb_albedo_gradient() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(volgrad_in(
        d,
        &[
            "make-grid",
            "coloured-smoke",
            "--size",
            "16",
            "-o",
            "smoke.vdb",
        ],
    ));
    let grids = vdb::list_grids(&d.join("smoke.vdb")).unwrap();
    let types: Vec<_> = grids
        .iter()
        .map(|g| (g.name.as_str(), g.value_type.as_str()))
        .collect();
    assert_eq!(types, [("density", "float"), ("Cd", "vec3s")]);
    let text = |albedo: &str| {
        "[camera]\nposition = [0, 0, 40]\ntarget = [0, 0, 0]\nfov_deg = 30\nwidth = 16\nheight = 16\n\
         [medium]\nvdb = \"smoke.vdb\"\ndensity_scale = 0.5\n"
            .to_string()
            + albedo
            + "\n[[light]]\ntype = \"constant\"\nradiance = 1\n[render]\nspp = 4\nmax_depth = 4\n"
    };
    std::fs::write(d.join("smoke.toml"), text("albedo = { grid = \"Cd\" }")).unwrap();
    ok(volgrad_in(d, &["render", "smoke.toml", "-o", "smoke.exr"]));
    let info = common::stdout(&ok(volgrad_in(d, &["info", "smoke.toml"])));
    assert!(info.contains("grid 'Cd' (RGB"), "{info}");
    ok(volgrad_in(
        d,
        &[
            "grad",
            "smoke.toml",
            "--parameter",
            "albedo",
            "--spp",
            "2",
            "-o",
            "g.vdb",
        ],
    ));
    let written = vdb::list_grids(&d.join("g.vdb")).unwrap();
    assert_eq!(written.len(), 1);
    assert_eq!(
        (written[0].name.as_str(), written[0].value_type.as_str()),
        ("grad_Cd", "vec3s")
    );
    assert!(written[0].active_voxels > 0);
    // Runs of two seeds merge into one vec3 grid; an extinction gradient does not merge with them.
    ok(volgrad_in(
        d,
        &[
            "grad",
            "smoke.toml",
            "--parameter",
            "albedo",
            "--spp",
            "2",
            "--seed",
            "2",
            "-o",
            "g2.vdb",
        ],
    ));
    ok(volgrad_in(
        d,
        &["merge", "g.vdb", "g2.vdb", "-o", "merged.vdb"],
    ));
    let merged = vdb::list_grids(&d.join("merged.vdb")).unwrap();
    assert_eq!(
        (merged[0].name.as_str(), merged[0].value_type.as_str()),
        ("grad_Cd", "vec3s")
    );
    ok(volgrad_in(
        d,
        &[
            "grad",
            "smoke.toml",
            "--spp",
            "2",
            "--seed",
            "3",
            "-o",
            "density.vdb",
        ],
    ));
    assert_clean_error(
        &volgrad_in(d, &["merge", "g.vdb", "density.vdb", "-o", "mixed.vdb"]),
        &[
            "another computation",
            "volgrad_parameter is 'albedo' there and 'extinction' here",
        ],
    );
    // gradcheck knows the parameter (plumbing: its exit status, at a few samples; the albedo
    // gradient's values are held to finite differences at 1 % in the tests above).
    ok(volgrad_in(
        d,
        &[
            "gradcheck",
            "smoke.toml",
            "--parameter",
            "albedo",
            "--channel",
            "1",
            "--voxels",
            "1",
            "--width",
            "8",
            "--spp",
            "64",
            "--fd-spp",
            "64",
        ],
    ));
    std::fs::write(d.join("plain.toml"), text("albedo = 0.5")).unwrap();
    assert_clean_error(
        &volgrad_in(
            d,
            &["grad", "plain.toml", "--parameter", "albedo", "-o", "p.vdb"],
        ),
        &["--parameter albedo", "constant"],
    );
}

/// `make-grid coloured-smoke --half` stores the colour grid as half floats, as `--half` does for
/// every other shape (it was written as f32 whatever the flag).
#[test]
fn coloured_smoke_honours_half() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let colours = |name: &str, half: bool| -> Vec<f32> {
        let mut args = vec!["make-grid", "coloured-smoke", "--size", "24", "-o", name];
        if half {
            args.push("--half");
        }
        ok(volgrad_in(d, &args));
        let cd = vdb::read_components(&d.join(name), "Cd").unwrap();
        (cd.iter())
            .flat_map(|g| g.bricks.leaves().iter().flat_map(|l| l.values))
            .filter(|&v| v != 0.0)
            .collect()
    };
    // A normal half keeps 10 of f32's 23 mantissa bits.
    let is_half = |v: &f32| v.to_bits() & 0x1fff == 0 && v.abs() > 6.2e-5;
    assert!(!colours("full.vdb", false).iter().all(is_half));
    let halves = colours("half.vdb", true);
    assert!(!halves.is_empty() && halves.iter().all(is_half));
}

/// An RGB albedo zero in a channel: the derivative there carries what the next vertex sends back
/// in that channel, even where the path stopped at that vertex because its throughput was 0 in
/// every channel. Seen from +z, a front half of red albedo (1, 0, 0) before a back half of
/// (0, 1, 1): a path that scatters in front and then collides behind stops there, and green's
/// derivative at the front (α_green = 0) needs the green light the back would have scattered.
#[test]
fn a_zero_albedo_channel_has_the_derivative_of_what_lies_behind() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let front = |v: IVec3| v.z >= 4;
    write_grids(d, |v| match front(v) {
        true => Vec3::new(1.0, 0.0, 0.0),
        false => Vec3::new(0.0, 1.0, 1.0),
    });
    let s = load(d, "density_scale = 0.4\nalbedo = { grid = \"Cd\" }", SKY, 8);
    let adjoint = Loss::Mean.adjoint(&RgbImage::new(s.camera.width, s.camera.height), None);
    let options = |parameter, channel| GradOptions {
        parameter,
        channel,
        ..GradOptions::new(Estimator::Joint, 4096, 5, s.settings.max_depth)
    };
    let g = gradient(&s, &adjoint, &options(Parameter::Albedo, Some(1))).values();
    let got: f64 = (g.voxels())
        .filter(|(v, _)| front(*v))
        .map(|(_, value)| value)
        .sum();
    let mean_at = |delta: f32| {
        let mut s = s.clone();
        let Albedo::Grid(a) = &mut s.medium.albedo else {
            unreachable!()
        };
        let deltas: Vec<_> = (0..512)
            .map(|i| IVec3::new(i / 64, (i / 8) % 8, i % 8))
            .filter(|&v| front(v))
            .map(|v| (v, delta))
            .collect();
        a.channels[1] = a.channels[1].with_added(&deltas);
        let image = gradient(&s, &adjoint, &options(Parameter::Extinction, None)).image;
        Loss::Mean.evaluate(&image, None)
    };
    // One-sided (an albedo below 0 is no albedo); the image is a polynomial in the step, whose
    // second-order part is a path scattering green twice in front.
    let eps = 0.01;
    let fd = (mean_at(eps) - mean_at(0.0)) / eps as f64;
    eprintln!("green's derivative at the front: {got} against {fd} by differences");
    assert!(fd > 1e-3, "{fd}");
    assert!((got - fd).abs() < 0.05 * fd, "{got} against {fd}");
}
