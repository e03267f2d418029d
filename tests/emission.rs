//! Emissive media: a medium gives off σa·Le from a grid of its own (`medium.emission`). Checked
//! against the closed form of an absorbing, emitting slab, a white furnace whose medium emits, a
//! scene lit by its emission alone, and the scene file's refusals.

mod common;

use std::path::Path;

use common::{assert_clean_error, ok, volgrad_in};
use glam::{IVec3, Vec3};
use volgrad::render::image::{render, RenderOptions};
use volgrad::render::scene::Scene;

/// A 16³ box of value 1 (voxel size 1, centred on the origin) in `dir/box.vdb`.
fn write_box(dir: &Path) {
    ok(volgrad_in(
        dir,
        &["make-grid", "box", "--size", "16", "-o", "box.vdb"],
    ));
}

/// A 3×3 camera on +z with a 1° field of view: every pixel sees the box along its full 16 units.
fn scene(dir: &Path, medium: &str, lights: &str) -> Scene {
    let text = format!(
        "[camera]\nposition = [0, 0, 200]\ntarget = [0, 0, 0]\nfov_deg = 1\nwidth = 3\nheight = 3\n\
         [medium]\nvdb = \"box.vdb\"\nfilter = \"nearest\"\n{medium}\n{lights}\n[render]\nmax_depth = 200\n"
    );
    let path = dir.join("scene.toml");
    std::fs::write(&path, text).unwrap();
    Scene::load(&path).unwrap()
}

fn mean_pixel(scene: &Scene, spp: u32) -> Vec3 {
    let options = RenderOptions {
        spp,
        seed: 7,
        max_depth: scene.settings.max_depth,
        progress: false,
    };
    let image = render(scene, &options).0;
    image.pixels.iter().sum::<Vec3>() / image.pixels.len() as f32
}

/// No scattering (albedo 0), no lights: L = Le·(1 − e^(−σa·d)) through d = 16 units at σa = 0.1,
/// per channel of Le = (0.5, 1, 2). 9 × 16,384 paths: the standard error is 0.2 % of the mean.
#[test]
fn an_absorbing_emitting_slab_matches_its_closed_form() {
    let dir = tempfile::tempdir().unwrap();
    write_box(dir.path());
    let s = scene(
        dir.path(),
        "density_scale = 0.1\nalbedo = 0\nemission = { grid = \"density\", radiance = [0.5, 1, 2] }",
        "",
    );
    let got = mean_pixel(&s, 16_384);
    let expected = Vec3::new(0.5, 1.0, 2.0) * (1.0 - (-1.6f32).exp());
    let error = ((got - expected) / expected).abs().max_element();
    assert!(error < 0.01, "{got} against {expected}");
}

/// A white furnace with emission: a medium that emits Le inside an environment of radiance Le is
/// in equilibrium (emission σa·Le plus in-scattering σs·Le equals extinction σt·Le), so every pixel
/// is Le whatever the albedo and density. Without the (1 − α) of σa = σt·(1 − α) it would be
/// brighter than Le.
#[test]
fn a_furnace_whose_medium_emits_its_surroundings_radiance_stays_uniform() {
    let dir = tempfile::tempdir().unwrap();
    write_box(dir.path());
    for (density, albedo) in [(0.3, 0.6), (2.0, 0.2)] {
        let s = scene(
            dir.path(),
            &format!(
                "density_scale = {density}\nalbedo = {albedo}\nemission = {{ grid = \"density\", radiance = 0.8 }}"
            ),
            "[[light]]\ntype = \"constant\"\nradiance = 0.8",
        );
        let got = mean_pixel(&s, 4096);
        let error = (got - Vec3::splat(0.8)).abs().max_element();
        assert!(error < 0.01, "σ {density}, α {albedo}: {got}");
    }
}

/// The fireball `make-grid` writes (density and temperature) renders by its own light, with no
/// light in the scene, and `grad` differentiates it with respect to its density and to its
/// temperature (`grad_temperature`); `--parameter emission` without an emission is refused.
#[test]
fn a_fireball_renders_by_its_own_light_and_is_differentiated() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(volgrad_in(
        d,
        &[
            "make-grid",
            "fireball",
            "--size",
            "24",
            "--value",
            "2",
            "-o",
            "fire.vdb",
        ],
    ));
    let text = "[camera]\nposition = [0, 0, 60]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 16\nheight = 16\n\
                [medium]\nvdb = \"fire.vdb\"\ndensity_scale = 0.3\nalbedo = 0.3\n\
                emission = { grid = \"temperature\", blackbody = { scale = 1000 }, strength = 2 }\n";
    std::fs::write(d.join("fire.toml"), text).unwrap();
    let s = Scene::load(&d.join("fire.toml")).unwrap();
    let centre = {
        let options = RenderOptions {
            spp: 64,
            seed: 1,
            max_depth: 8,
            progress: false,
        };
        render(&s, &options).0.pixels[8 * 16 + 8]
    };
    // 1000–3000 K: red brighter than green brighter than blue.
    assert!(
        centre.x > centre.y && centre.y > centre.z && centre.z >= 0.0,
        "{centre}"
    );
    assert!(centre.x > 0.05, "{centre}");
    ok(volgrad_in(
        d,
        &[
            "grad",
            "fire.toml",
            "--spp",
            "2",
            "-o",
            "fire.grad.vdb",
            "-q",
        ],
    ));
    assert!(d.join("fire.grad.vdb").exists());
    ok(volgrad_in(
        d,
        &[
            "grad",
            "fire.toml",
            "--parameter",
            "emission",
            "--spp",
            "2",
            "-o",
            "t.vdb",
            "-q",
        ],
    ));
    let grid = volgrad::io::vdb::read_grid(
        &d.join("t.vdb"),
        &volgrad::io::vdb::GridSelector::Name("grad_temperature".into()),
    )
    .unwrap();
    assert!(grid.bricks.active_voxel_count() > 0);
    write_box(d);
    let plain = "[camera]\nposition = [0, 0, 60]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 8\nheight = 8\n\
                 [medium]\nvdb = \"box.vdb\"\n[[light]]\ntype = \"constant\"\nradiance = 1\n";
    std::fs::write(d.join("plain.toml"), plain).unwrap();
    let o = volgrad_in(d, &["grad", "plain.toml", "--parameter", "emission", "-q"]);
    assert_clean_error(&o, &["no emission"]);
}

/// Each class of bad emission key is refused with its key named.
#[test]
fn bad_emission_keys_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_box(d);
    let cases = [
        ("{ grid = \"density\" }", "needs one of"),
        (
            "{ grid = \"density\", radiance = 1, blackbody = { scale = 1 } }",
            "needs one of",
        ),
        (
            "{ grid = \"density\", radiance = -1 }",
            "medium.emission.radiance",
        ),
        (
            "{ grid = \"density\", radiance = 1, strength = 2 }",
            "strength",
        ),
        (
            "{ grid = \"density\", blackbody = { scale = 0 } }",
            "blackbody.scale",
        ),
        ("{ grid = \"nope\", radiance = 1 }", "nope"),
        (
            "{ grid = \"density\", vdb = \"missing.vdb\", radiance = 1 }",
            "missing.vdb",
        ),
        ("{ grid = \"density\", colour = 1 }", "colour"),
    ];
    for (emission, needle) in cases {
        let text = format!(
            "[camera]\nposition = [0, 0, 60]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 8\nheight = 8\n\
             [medium]\nvdb = \"box.vdb\"\nemission = {emission}\n"
        );
        std::fs::write(d.join("bad.toml"), text).unwrap();
        let o = volgrad_in(
            d,
            &["render", "bad.toml", "-o", "bad.exr", "--spp", "1", "-q"],
        );
        assert_clean_error(&o, &[needle]);
    }
}

/// The extinction gradient of an emitting medium with an RGB albedo grid against finite
/// differences, where emission is most of the light (a dim sky, no sun): joint and drt carry ĥ = (1 − α)·Le + α·(NEE + indirect)
/// at their probes and path vertices, so their means agree with FD (|z| < 4.5) on single voxels
/// (one of them empty: the emission a new density there would add), an empty box and ⟨g, 1⟩.
/// With the emission term left out of the probes' ĥ they do not (seen: joint at z = −24 on the
/// first voxel).
/// Naive carries it at real collisions only, so its bias in empty voxels covers emission too.
#[test]
fn extinction_gradients_with_emission_agree_with_finite_differences() {
    use common::lumpy_block_scene;
    use glam::IVec3;
    use volgrad::gradient::adjoint::Estimator;
    use volgrad::gradient::fd::{self, FdOptions};
    use volgrad::gradient::loss::Loss;
    use volgrad::gradient::passes::{gradient, GradOptions};
    use volgrad::gradient::runs::MeanAndError;
    use volgrad::volume::albedo::{Albedo, AlbedoGrid};
    use volgrad::volume::emission::{Emission, EmissionKind};
    use volgrad::volume::medium::Filter;

    let mut scene = lumpy_block_scene(Filter::Trilinear, true, 0.5);
    scene.lights.directional.clear();
    scene.lights.environment.constant = Vec3::splat(0.05);
    scene.medium.emission = Some(Emission::new(
        "flames".into(),
        common::grid(8, |v: IVec3| 0.5 + 0.15 * v.y as f32),
        common::centred(8, 1.0),
        EmissionKind::Radiance(Vec3::new(2.0, 1.0, 0.4)),
        Filter::Trilinear,
    ));
    // An RGB albedo grid over the block's voxels (0 outside them): ĥ's (1 − α) and α are the
    // probe's own, and R_j's the collision's.
    scene.medium.albedo = Albedo::Grid(Box::new(AlbedoGrid::new(
        "Cd".into(),
        vec![
            common::grid(6, |v: IVec3| 0.3 + 0.1 * v.x as f32),
            common::grid(6, |v: IVec3| 0.8 - 0.1 * v.y as f32),
            common::grid(6, |_| 0.5),
        ],
        Vec3::ZERO,
        common::centred(6, 1.0),
        Filter::Trilinear,
    )));
    let fd_along = |direction: &fd::Direction| {
        let options = FdOptions {
            loss: Loss::Mean,
            eps: 0.15,
            spp: 4096,
            repeats: 8,
            seed: 1,
            max_depth: scene.settings.max_depth,
        };
        fd::directional_derivative(&scene, None, direction, &options).unwrap()
    };
    let probes = [
        IVec3::new(2, 3, 2),
        IVec3::new(0, 0, 0),
        IVec3::new(3, 3, 5),
    ];
    assert_eq!(scene.medium.grid.voxel(IVec3::ZERO), 0.0, "an empty voxel");
    let empty_box = (IVec3::new(-1, -1, 3), IVec3::new(2, 2, 6));
    let (lo, hi) = fd::domain_bounds(&scene.medium.grid).unwrap();
    let directions: Vec<fd::Direction> = probes
        .iter()
        .map(|&v| vec![(v, 1.0)])
        .chain([
            fd::ones(&fd::box_voxels(
                &scene.medium.grid,
                empty_box.0,
                empty_box.1,
                false,
            )),
            fd::ones(&fd::box_voxels(&scene.medium.grid, lo, hi, false)),
        ])
        .collect();
    let fds: Vec<fd::FdResult> = directions.iter().map(fd_along).collect();
    let adjoint = Loss::Mean.adjoint(
        &volgrad::io::images::RgbImage::new(scene.camera.width, scene.camera.height),
        None,
    );
    for estimator in [Estimator::Joint, Estimator::Drt] {
        let grads: Vec<_> = (0..8)
            .map(|r| {
                let o = GradOptions::new(estimator, 64, 100 + r, scene.settings.max_depth);
                gradient(&scene, &adjoint, &o).values()
            })
            .collect();
        for (direction, fd) in directions.iter().zip(&fds) {
            let values: Vec<f64> = (grads.iter())
                .map(|g| direction.iter().map(|&(v, w)| w as f64 * g.get(v)).sum())
                .collect();
            let est = MeanAndError::of(&values);
            let z = (est.mean - fd.value) / (est.se.powi(2) + fd.std_err.powi(2)).sqrt();
            assert!(
                z.abs() < 4.5,
                "{estimator:?}, {} voxels: {:.5} ± {:.5} vs fd {:.5} ± {:.5} (z = {z:.2})",
                direction.len(),
                est.mean,
                est.se,
                fd.value,
                fd.std_err
            );
        }
    }
}

fn mean_adjoint(s: &Scene) -> Vec<Vec3> {
    volgrad::gradient::loss::Loss::Mean.adjoint(
        &volgrad::io::images::RgbImage::new(s.camera.width, s.camera.height),
        None,
    )
}

/// The emission grid's active box, and its two halves along x: where the gradient is compared
/// with differences (a gradient put on the wrong voxels passes on the whole box, not on halves).
fn emission_regions(s: &Scene) -> Vec<(IVec3, IVec3)> {
    let e = s.medium.emission.as_ref().unwrap();
    let (lo, hi) = volgrad::gradient::fd::domain_bounds(&e.grid).unwrap();
    let middle = (lo.x + hi.x) / 2;
    vec![
        (lo, hi),
        (lo, IVec3::new(middle, hi.y, hi.z)),
        (IVec3::new(middle + 1, lo.y, lo.z), hi),
    ]
}

/// The mean pixel's gradient with respect to the emission grid, summed over the voxels of
/// `region` (joint; the emission pass has no probes, so the estimator does not matter).
fn emission_gradient(s: &Scene, spp: u32, region: (IVec3, IVec3)) -> f64 {
    use volgrad::gradient::adjoint::Estimator;
    use volgrad::gradient::passes::{gradient, GradOptions, Parameter};
    let options = GradOptions {
        parameter: Parameter::Emission,
        ..GradOptions::new(Estimator::Joint, spp, 3, s.settings.max_depth)
    };
    let (lo, hi) = region;
    (gradient(s, &mean_adjoint(s), &options).values().voxels())
        .filter(|(v, _)| v.cmpge(lo).all() && v.cmple(hi).all())
        .map(|(_, g)| g)
        .sum()
}

/// Central differences of the mean pixel as the active voxels of the emission grid in `region`
/// move by ±ε, on the paths of `emission_gradient` (the same seed: collisions do not depend on the
/// emission).
fn emission_finite_difference(s: &Scene, spp: u32, eps: f32, region: (IVec3, IVec3)) -> f64 {
    use volgrad::gradient::adjoint::Estimator;
    use volgrad::gradient::fd::box_voxels;
    use volgrad::gradient::passes::{gradient, GradOptions};
    let shifted = |delta: f32| {
        let mut s = s.clone();
        let e = s.medium.emission.as_mut().unwrap();
        let deltas: Vec<_> = (box_voxels(&e.grid, region.0, region.1, true).iter())
            .map(|&v| (v, delta))
            .collect();
        e.grid = e.grid.with_added(&deltas);
        let options = GradOptions::new(Estimator::Joint, spp, 3, s.settings.max_depth);
        // The gradient pass's own image: the same paths as the emission pass.
        let image = gradient(&s, &mean_adjoint(&s), &options).image;
        volgrad::gradient::loss::Loss::Mean.evaluate(&image, None)
    };
    (shifted(eps) - shifted(-eps)) / (2.0 * eps as f64)
}

/// The emission gradient agrees with the same-path differences to 1 %, over the whole grid and
/// over each half of it, and the scene responds to its emission at all.
fn assert_emission_gradient_matches_differences(s: &Scene, spp: u32, eps: f32) {
    for region in emission_regions(s) {
        let (got, fd) = (
            emission_gradient(s, spp, region),
            emission_finite_difference(s, spp, eps, region),
        );
        assert!(
            fd.abs() > 1e-4,
            "the fire must respond to its emission ({fd}) in {region:?}"
        );
        assert!(
            (got - fd).abs() < 0.01 * fd.abs(),
            "{region:?}: the gradient's sum {got} against finite differences {fd}"
        );
    }
}

/// The gradient with respect to the emission grid (`Parameter::Emission`). Through an absorbing
/// slab, L = radiance · e · (1 − e^(−σa·d)), so d(mean pixel)/d(every e_k + ε) = mean(radiance) ·
/// (1 − e^(−1.6)): ⟨g, 1⟩ within 1 %. For a temperature grid, against finite differences of the
/// active voxels shifted by ±ε with the same seed (nearest lookups, so that a collision's
/// emission comes from one active voxel): collisions do not depend on the emission, so the two see
/// the same paths and must agree to 1 %; a blackbody slope without the scale would not.
#[test]
fn emission_gradients_match_the_slab_and_finite_differences() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_box(d);
    let slab = scene(
        d,
        "density_scale = 0.1\nalbedo = 0\nemission = { grid = \"density\", radiance = [0.5, 1, 2] }",
        "",
    );
    let got = emission_gradient(&slab, 16_384, emission_regions(&slab)[0]);
    let expected = (3.5 / 3.0) * (1.0 - (-1.6f64).exp());
    assert!(
        (got - expected).abs() < 0.01 * expected,
        "{got} against {expected}"
    );

    ok(volgrad_in(
        d,
        &[
            "make-grid",
            "fireball",
            "--size",
            "16",
            "--value",
            "2",
            "-o",
            "fire.vdb",
        ],
    ));
    let text = "[camera]\nposition = [0, 0, 40]\ntarget = [0, 0, 0]\nfov_deg = 30\nwidth = 12\nheight = 12\n\
                [medium]\nvdb = \"fire.vdb\"\ndensity_scale = 0.3\nalbedo = 0.5\nfilter = \"nearest\"\n\
                emission = { grid = \"temperature\", blackbody = { scale = 1000, cutoff = 1200 }, strength = 4 }\n\
                [[light]]\ntype = \"constant\"\nradiance = 0.02\n[render]\nmax_depth = 8\n";
    std::fs::write(d.join("fire.toml"), text).unwrap();
    let fire = Scene::load(&d.join("fire.toml")).unwrap();
    assert_emission_gradient_matches_differences(&fire, 256, 0.01);
}

/// The shipped Mantaflow bake (`scenes/assets/mantaflow_fire.vdb`: half-float grids, a `flame`,
/// `temperature` and `density` of their own active sets, z up in the domain's frame) renders by
/// its own light where it is hot, blackbody-coloured (red over green over blue below 3000 K), and
/// the gradient with respect to its temperature grid agrees with same-path finite differences.
/// The cutoff sits at 500 K, where the normalised blackbody's visible part is negligible, so that
/// voxels the ±ε crosses over it add no jump the gradient cannot see.
#[test]
fn a_real_pyro_simulation_renders_by_its_own_light_and_is_differentiated() {
    let dir = tempfile::tempdir().unwrap();
    let asset = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/assets/mantaflow_fire.vdb");
    let text = format!(
        "[camera]\nposition = [2, -4.5, 2]\ntarget = [2, 2, 2]\nup = [0, 0, 1]\nfov_deg = 40\n\
         width = 12\nheight = 12\n[medium]\nvdb = {asset:?}\ndensity_scale = 10\nalbedo = 0.8\n\
         filter = \"nearest\"\n\
         emission = {{ grid = \"temperature\", blackbody = {{ scale = 1000, cutoff = 500 }}, strength = 5 }}\n\
         [render]\nmax_depth = 8\n"
    );
    let path = dir.path().join("pyro.toml");
    std::fs::write(&path, text).unwrap();
    let pyro = Scene::load(&path).unwrap();
    let options = RenderOptions {
        spp: 64,
        seed: 1,
        max_depth: 8,
        progress: false,
    };
    let image = render(&pyro, &options).0;
    let brightest = (image.pixels.iter())
        .copied()
        .max_by(|a, b| a.x.total_cmp(&b.x))
        .unwrap();
    assert!(
        brightest.x > brightest.y && brightest.y > brightest.z && brightest.z > 0.0,
        "{brightest}"
    );
    // The flame burns at the bottom of the domain: the lower half of the image is the brighter.
    let half = image.pixels.len() / 2;
    let red = |p: &[Vec3]| p.iter().map(|p| p.x as f64).sum::<f64>();
    assert!(red(&image.pixels[half..]) > 2.0 * red(&image.pixels[..half]));

    assert_emission_gradient_matches_differences(&pyro, 64, 0.005);
}

/// Emission that could exceed the light cap (`scene_check::MAX_LIGHT`, 1e30: sums over millions
/// of samples stay finite in f32) is refused: a strength above it (3e38 once gave 447 pixels above
/// 1e30 and a gradient of dropped samples, exit 0), a strength × the blackbody's largest value up
/// to the grid's hottest voxel above it (the blackbody peaks at 1.21, red, near 4550 K), a
/// radiance × the grid's largest value above it. The same strength at a cooler temperature, and
/// the same radiance on a grid of 1, render. An emission grid with a non-zero background is
/// refused, as a density's is (the brick map reads 0 outside its voxels; it was ignored).
#[test]
fn emission_above_the_light_cap_or_on_a_background_is_refused() {
    use glam::DVec3;
    use volgrad::io::vdb::{self, Grid};
    use volgrad::volume::brickmap::BrickMap;
    use volgrad::volume::transform::IndexTransform;

    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_box(d);
    let grid = |name: &str, value: f32, background: f32| Grid {
        name: name.into(),
        grid_class: "fog volume".into(),
        transform: IndexTransform::uniform(1.0, DVec3::splat(-3.5)),
        bricks: BrickMap::block(8, |_| value),
        background,
        saved_as_half: false,
        metadata: Vec::new(),
    };
    let (hot, glow) = (grid("hot", 4.0, 0.0), grid("glow", 1.0, 0.5));
    vdb::write_grids(&d.join("more.vdb"), &[&hot, &glow], false, true).unwrap();
    let render = |emission: &str| {
        let text = format!(
            "[camera]\nposition = [0, 0, 60]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 8\nheight = 8\n\
             [medium]\nvdb = \"box.vdb\"\nemission = {emission}\n"
        );
        std::fs::write(d.join("e.toml"), text).unwrap();
        volgrad_in(
            d,
            &[
                "render", "e.toml", "-o", "e.exr", "--spp", "1", "-q", "--force",
            ],
        )
    };
    let blackbody = |scale: f32, strength: &str| {
        format!(
            "{{ grid = \"density\", blackbody = {{ scale = {scale} }}, strength = {strength} }}"
        )
    };
    assert_clean_error(
        &render(&blackbody(1000.0, "3e38")),
        &["medium.emission.strength", "1e30"],
    );
    assert_clean_error(
        &render(&blackbody(4550.0, "1e30")),
        &["medium.emission", "'density'", "4550 K", "1e30"],
    );
    ok(render(&blackbody(1000.0, "1e30")));
    assert_clean_error(
        &render("{ grid = \"hot\", vdb = \"more.vdb\", radiance = 1e30 }"),
        &["medium.emission", "'hot'", "4.000e30"],
    );
    ok(render("{ grid = \"density\", radiance = 1e30 }"));
    assert_clean_error(
        &render("{ grid = \"glow\", vdb = \"more.vdb\", radiance = 1 }"),
        &["medium.emission", "'glow'", "background 0.5"],
    );
}
