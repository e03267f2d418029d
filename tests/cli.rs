//! The `volgrad` binary end to end: info, make-grid, render, and every bad input giving a clear
//! error and a non-zero exit (never a panic or an abort).

use std::path::{Path, PathBuf};

mod common;
use common::*;

fn assets() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/assets")
}

fn asset(name: &str) -> String {
    assets().join(name).to_str().unwrap().to_string()
}

/// A small scene around a `make-grid` grid, written into `dir`.
fn tiny_scene(dir: &Path, extra_medium: &str, extra: &str) -> PathBuf {
    sphere_vdb(dir);
    let scene = dir.join("tiny.toml");
    std::fs::write(
        &scene,
        format!(
            "[camera]\nposition = [0, 1, 12]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 24\nheight = 16\n\
             [medium]\nvdb = \"sphere.vdb\"\ndensity_scale = 2.0\nalbedo = [0.9, 0.8, 0.7]\nphase_g = 0.3\n{extra_medium}\n\
             [[light]]\ntype = \"constant\"\nradiance = 0.5\n\
             [[light]]\ntype = \"directional\"\ndirection = [0, -1, -1]\nirradiance = 2\n\
             [render]\nspp = 4\n{extra}"
        ),
    )
    .unwrap();
    scene
}

#[test]
fn info_lists_every_grid_with_its_facts() {
    let o = volgrad(&["info", &asset("wdas_cloud_sixteenth.vdb")]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    for fact in [
        "density",
        "415642",
        "active tiles   130",
        "[-66, -21, -90] .. [59, 64, 63]",
        "fog volume",
        "scale + translation",
        "brick map",
        // OpenVDB's own `vdb_print -l`: min value 0, max value 1.
        "values         0 .. 1 (mean 0.",
    ] {
        assert!(out.contains(fact), "info lacks {fact:?}:\n{out}");
    }
    let o = volgrad(&["info", &asset("grids.vdb")]);
    let out = stdout(&o);
    assert!(
        out.contains("3 grids") && out.contains("[2] density"),
        "{out}"
    );
    let o = volgrad(&["info", &asset("dragon_with_xform.vdb")]);
    assert!(stdout(&o).contains("general affine"), "{}", stdout(&o));
    let o = volgrad(&["info", &asset("smoke.vdb")]);
    assert!(stdout(&o).contains("saved as half"), "{}", stdout(&o));
    // A point grid is listed (with its type), not rejected: info describes any VDB.
    let o = volgrad(&["info", &asset("points.vdb")]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("points"), "{}", stdout(&o));
}

#[test]
fn render_writes_exr_and_srgb_png_that_independent_decoders_read() {
    let dir = tempfile::tempdir().unwrap();
    let scene = tiny_scene(dir.path(), "", "");
    let exr = dir.path().join("out.exr");
    let o = volgrad(&[
        "render",
        scene.to_str().unwrap(),
        "-o",
        exr.to_str().unwrap(),
        "--stats",
        "--quiet",
        "--threads",
        "2",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    for key in [
        "paths/s",
        "lookups per path",
        "tracking efficiency",
        "brick map",
    ] {
        assert!(stdout(&o).contains(key), "stats lack {key}: {}", stdout(&o));
    }
    // The EXR through the pure-Rust decoder.
    let image = exr::prelude::read_first_rgba_layer_from_file(
        &exr,
        |res, _| vec![[0f32; 3]; res.width() * res.height()],
        |px: &mut Vec<[f32; 3]>, pos, (r, g, b, _a): (f32, f32, f32, f32)| {
            px[pos.y() * 24 + pos.x()] = [r, g, b]
        },
    )
    .unwrap();
    let linear = image.layer_data.channel_data.pixels;
    assert_eq!(linear.len(), 24 * 16);
    assert!(linear.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
    let centre = linear[8 * 24 + 12];
    let corner = linear[0];
    assert!(
        centre[0] != corner[0],
        "the sphere must show against the sky"
    );
    // The PNG is the sRGB encoding of the same values (exposure 1).
    let png = image::open(dir.path().join("out.png")).unwrap().to_rgb8();
    assert_eq!(png.dimensions(), (24, 16));
    for (i, lin) in linear.iter().enumerate() {
        let px = png.get_pixel(i as u32 % 24, i as u32 / 24);
        for c in 0..3 {
            let expected = volgrad::io::images::srgb_encode(lin[c]) * 255.0;
            assert!(
                (px[c] as f32 - expected).abs() <= 1.0,
                "pixel {i} channel {c}: {} vs {expected}",
                px[c]
            );
        }
    }
    // Nothing is overwritten without --force.
    let again = volgrad(&[
        "render",
        scene.to_str().unwrap(),
        "-o",
        exr.to_str().unwrap(),
        "--quiet",
    ]);
    assert_clean_error(&again, &["already exists", "--force"]);
    let forced = volgrad(&[
        "render",
        scene.to_str().unwrap(),
        "-o",
        exr.to_str().unwrap(),
        "--quiet",
        "--force",
        "--majorant",
        "global",
    ]);
    assert!(forced.status.success(), "{}", stderr(&forced));
    // A symbolic link to a file not yet there is the user's too: not replaced without --force.
    let link = dir.path().join("link.exr");
    std::os::unix::fs::symlink(dir.path().join("elsewhere.exr"), &link).unwrap();
    let linked = volgrad(&[
        "render",
        scene.to_str().unwrap(),
        "-o",
        link.to_str().unwrap(),
        "--quiet",
    ]);
    assert_clean_error(&linked, &["link.exr", "already exists", "--force"]);
    assert!(link.symlink_metadata().unwrap().file_type().is_symlink());
}

#[test]
fn the_same_seed_renders_the_same_file_for_any_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let scene = tiny_scene(dir.path(), "", "");
    let mut files = Vec::new();
    for threads in ["1", "2"] {
        let exr = dir.path().join(format!("t{threads}.exr"));
        let o = volgrad(&[
            "render",
            scene.to_str().unwrap(),
            "-o",
            exr.to_str().unwrap(),
            "--quiet",
            "--threads",
            threads,
            "--seed",
            "11",
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        files.push(volgrad::io::images::read_rgb(&exr).unwrap());
    }
    assert_eq!(files[0], files[1]);
}

#[test]
fn every_sample_asset_renders() {
    let dir = tempfile::tempdir().unwrap();
    for (vdb, index, grid) in [
        ("smoke.vdb", 0, "grid = \"density\""),
        ("torus01.vdb", 0, "grid = \"voxel_fog_density\""),
        ("dragon_with_xform.vdb", 0, ""),
        ("grids.vdb", 1, "grid_index = 1"),
        ("tiny_sphere.vdb", 0, ""),
    ] {
        let (lo, hi) = world_box(&asset(vdb), index);
        let centre = [
            (lo[0] + hi[0]) / 2.0,
            (lo[1] + hi[1]) / 2.0,
            (lo[2] + hi[2]) / 2.0,
        ];
        let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
        let scene = dir.path().join(format!("{vdb}.toml"));
        std::fs::write(
            &scene,
            format!(
                "[camera]\nposition = [{}, {}, {}]\ntarget = {centre:?}\nfov_deg = 45\nwidth = 16\nheight = 16\n\
                 [medium]\nvdb = \"{}\"\n{grid}\ndensity_scale = {}\n[[light]]\ntype = \"constant\"\nradiance = 1\n[render]\nspp = 2\n",
                centre[0],
                centre[1],
                centre[2] + 2.0 * extent,
                asset(vdb),
                5.0 / extent
            ),
        )
        .unwrap();
        let out = dir.path().join(format!("{vdb}.exr"));
        let o = volgrad(&[
            "render",
            scene.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--quiet",
        ]);
        assert!(o.status.success(), "{vdb}: {}", stderr(&o));
        let image = volgrad::io::images::read_rgb(&out).unwrap();
        let min = image
            .pixels
            .iter()
            .map(|c| c.x)
            .fold(f32::INFINITY, f32::min);
        assert!(
            min < 0.95,
            "{vdb}: the medium must absorb some light (darkest pixel {min})"
        );
    }
}

/// World bounding box of grid `index`, as `info` prints it.
fn world_box(vdb: &str, index: usize) -> ([f64; 3], [f64; 3]) {
    let s = volgrad::io::vdb::list_grids(Path::new(vdb)).unwrap();
    (s[index].world_min, s[index].world_max)
}

#[test]
fn make_grid_writes_every_kind_and_refuses_to_overwrite() {
    let dir = tempfile::tempdir().unwrap();
    for (kind, active) in [
        ("box", 8 * 8 * 8),
        ("slab", 8 * 8 * 2),
        ("single-voxel", 8 * 8 * 8),
    ] {
        let path = dir.path().join(format!("{kind}.vdb"));
        let o = volgrad(&[
            "make-grid",
            kind,
            "--size",
            "8",
            "-o",
            path.to_str().unwrap(),
            "--value",
            "3",
        ]);
        assert!(o.status.success(), "{kind}: {}", stderr(&o));
        let g = volgrad::io::vdb::list_grids(&path).unwrap();
        assert_eq!(g[0].active_voxels, active, "{kind}");
        assert_eq!(g[0].name, "density");
    }
    let path = dir.path().join("sphere.vdb");
    let o = volgrad(&[
        "make-grid",
        "sphere",
        "--size",
        "10",
        "--rotate-deg",
        "30,-20,10",
        "--voxel-size",
        "1,2,0.5",
        "-o",
        path.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let g = &volgrad::io::vdb::list_grids(&path).unwrap()[0];
    assert!(!g.axis_aligned);
    assert!((g.voxel_size[1] - 2.0).abs() < 1e-9);
    assert_clean_error(
        &volgrad(&["make-grid", "box", "-o", path.to_str().unwrap()]),
        &["already exists"],
    );
    assert_clean_error(
        &volgrad(&[
            "make-grid",
            "box",
            "--value",
            "-1",
            "-o",
            dir.path().join("n.vdb").to_str().unwrap(),
        ]),
        &["--value"],
    );
}

#[test]
fn bad_inputs_give_clear_errors_and_a_nonzero_exit() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Missing and corrupt files.
    assert_clean_error(
        &volgrad(&["info", "/no/such/file.vdb"]),
        &["/no/such/file.vdb"],
    );
    let truncated = d.join("truncated.vdb");
    let bytes = std::fs::read(assets().join("tiny_sphere.vdb")).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    assert_clean_error(
        &volgrad(&["info", truncated.to_str().unwrap()]),
        &["truncated.vdb"],
    );
    let garbage = d.join("garbage.vdb");
    std::fs::write(&garbage, b"this is not a vdb file at all, just text").unwrap();
    assert_clean_error(
        &volgrad(&["info", garbage.to_str().unwrap()]),
        &["garbage.vdb"],
    );

    // Scenes: each broken in one way.
    let write_scene = |name: &str, medium: &str, extra: &str| {
        let p = d.join(name);
        std::fs::write(&p, format!("[camera]\nposition = [0, 0, 30]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 8\nheight = 8\n[medium]\n{medium}\n{extra}")).unwrap();
        p
    };
    let out = d.join("o.exr");
    let render = |scene: &Path| {
        volgrad(&[
            "render",
            scene.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--quiet",
        ])
    };
    let tiny = asset("tiny_sphere.vdb");
    let cases: Vec<(PathBuf, Vec<&str>)> = vec![
        (
            write_scene("missing_vdb.toml", "vdb = \"nope.vdb\"", ""),
            vec!["medium.vdb", "nope.vdb"],
        ),
        (
            write_scene(
                "corrupt.toml",
                &format!("vdb = {:?}", truncated.to_str().unwrap()),
                "",
            ),
            vec!["truncated.vdb"],
        ),
        (
            write_scene(
                "points.toml",
                &format!("vdb = {:?}", asset("points.vdb")),
                "",
            ),
            vec!["points.vdb", "not float"],
        ),
        (
            write_scene(
                "unknown_grid.toml",
                &format!("vdb = {tiny:?}\ngrid = \"temperature\""),
                "",
            ),
            vec!["temperature", "density"],
        ),
        (
            write_scene(
                "index.toml",
                &format!("vdb = {:?}\ngrid_index = 7", asset("grids.vdb")),
                "",
            ),
            vec!["7"],
        ),
        (
            write_scene(
                "negative.toml",
                &format!("vdb = {tiny:?}\ndensity_scale = -2"),
                "",
            ),
            vec!["medium.density_scale"],
        ),
        (
            write_scene("g.toml", &format!("vdb = {tiny:?}\nphase_g = -1"), ""),
            vec!["medium.phase_g"],
        ),
        (
            write_scene(
                "unknown_key.toml",
                &format!("vdb = {tiny:?}\ndensty_scale = 2"),
                "",
            ),
            vec!["densty_scale"],
        ),
        (
            write_scene(
                "envmap.toml",
                &format!("vdb = {tiny:?}"),
                "[[light]]\ntype = \"envmap\"\nfile = \"sky.exr\"\n",
            ),
            vec!["light[0].file", "sky.exr"],
        ),
        (
            write_scene(
                "syntax.toml",
                &format!("vdb = {tiny:?}\nalbedo = [0.5, 0.5"),
                "",
            ),
            vec!["syntax.toml"],
        ),
    ];
    for (scene, needles) in &cases {
        assert_clean_error(&render(scene), needles);
    }
    // Numbers: magnitudes are checked before anything derived from them.
    let camera = |from: &str, to: &str, needles: &[&str]| {
        let p = write_scene("numbers.toml", &format!("vdb = {tiny:?}"), "");
        let text = std::fs::read_to_string(&p).unwrap().replace(from, to);
        std::fs::write(&p, text).unwrap();
        assert_clean_error(&render(&p), needles);
    };
    let far = ["camera.position", "too far", "1e15"];
    camera("position = [0, 0, 30]", "position = [0, 0, 1e30]", &far);
    camera(
        "position = [0, 0, 30]",
        "position = [0, 0, nan]",
        &["camera.position", "finite"],
    );
    camera(
        "target = [0, 0, 0]",
        "target = [0, 0, 30]",
        &["camera.target must differ"],
    );
    camera("fov_deg = 40", "fov_deg = 180", &["camera.fov_deg"]);
    camera("fov_deg = 40", "fov_deg = nan", &["camera.fov_deg", "NaN"]);
    camera(
        "height = 8",
        "height = 100000000",
        &["camera.width × camera.height", "too large", "2^28"],
    );
    camera("width = 8", "width = 4294967296", &["width", "u32"]);
    camera(
        "fov_deg = 40",
        "fov_deg = 40\nup = [0, 0, 1e-30]",
        &["camera.up", "parallel"],
    );
    camera(
        "fov_deg = 40",
        "fov_deg = 40\nup = [0, 0, 0]",
        &["camera.up must not be zero"],
    );
    let medium = |extra: &str, needles: &[&str]| {
        let p = write_scene("medium.toml", &format!("vdb = {tiny:?}\n{extra}"), "");
        assert_clean_error(&render(&p), needles);
    };
    medium("density_scale = nan", &["medium.density_scale", "NaN"]);
    medium("density_scale = inf", &["medium.density_scale", "inf"]);
    medium(
        "density_scale = 1e30",
        &["medium.density_scale", "too large"],
    );
    medium("albedo = nan", &["medium.albedo", "NaN"]);
    // f32 would make it 0: an empty medium, without a word.
    medium(
        "density_scale = 1e-46",
        &["medium.density_scale = 1e-46", "32-bit float's range"],
    );
    let light = |body: &str, needles: &[&str]| {
        let light = format!("[[light]]\ntype = \"{body}\n");
        let p = write_scene("light.toml", &format!("vdb = {tiny:?}"), &light);
        assert_clean_error(&render(&p), needles);
    };
    light(
        "constant\"\nradiance = nan",
        &["light[0].radiance", "finite"],
    );
    light("constant\"\nradiance = -1", &["light[0].radiance", "≥ 0"]);
    light(
        "constant\"\nradiance = 1e31",
        &["light[0].radiance", "too large"],
    );
    let dir_light = "directional\"\nirradiance = 1\ndirection =";
    light(
        &format!("{dir_light} [0, 0, 0]"),
        &["light[0].direction", "zero"],
    );
    light(
        &format!("{dir_light} [0, inf, 0]"),
        &["light[0].direction", "finite"],
    );
    light(
        "directional\"\ndirection = [0, 1, 0]\nirradiance = inf",
        &["light[0].irradiance"],
    );
    // A light's own error is shown at the list's first table: the message names the light.
    light(
        "constant\"\nradiance = 1\n[[light]]\ntype = \"directional\"\ndirection = [0, 1, 0]\nirradiance = 1\nfrobnicate = 1",
        &["light[1]: unknown field `frobnicate`"],
    );
    let zero = write_scene("zero.toml", &format!("vdb = {tiny:?}"), "");
    std::fs::write(
        &zero,
        std::fs::read_to_string(&zero)
            .unwrap()
            .replace("width = 8", "width = 0"),
    )
    .unwrap();
    assert_clean_error(&render(&zero), &["camera.width"]);
    assert_clean_error(
        &volgrad(&["render", d.join("absent.toml").to_str().unwrap()]),
        &["absent.toml"],
    );

    // Unwritable output.
    let ok_scene = tiny_scene(d, "", "");
    let o = volgrad(&[
        "render",
        ok_scene.to_str().unwrap(),
        "-o",
        "/no/such/dir/out.exr",
        "--quiet",
    ]);
    assert_clean_error(&o, &["/no/such/dir/out"]);
    assert_clean_error(
        &volgrad(&[
            "render",
            ok_scene.to_str().unwrap(),
            "--spp",
            "0",
            "-o",
            out.to_str().unwrap(),
        ]),
        &["spp"],
    );
    assert!(!out.exists(), "a failed render must not leave files behind");
}

#[test]
fn an_envmap_light_from_an_exr_file_passes_the_white_furnace() {
    // A constant lat-long map and albedo 1: whatever the medium does, every pixel sees the map's
    // radiance. Exercises the scene's envmap loading (OpenImageIO) and its importance sampling.
    let dir = tempfile::tempdir().unwrap();
    let sky = volgrad::io::images::RgbImage {
        width: 32,
        height: 16,
        pixels: vec![glam::Vec3::new(0.5, 0.25, 1.0); 32 * 16],
    };
    volgrad::io::images::write_exr(&dir.path().join("sky.exr"), &sky, false).unwrap();
    let scene = tiny_scene(dir.path(), "", "");
    let text = std::fs::read_to_string(&scene).unwrap();
    let text = text
        .replace("albedo = [0.9, 0.8, 0.7]", "albedo = 1.0")
        .replace(
            "type = \"constant\"\nradiance = 0.5\n",
            "type = \"envmap\"\nfile = \"sky.exr\"\n",
        )
        .replace(
            "[[light]]\ntype = \"directional\"\ndirection = [0, -1, -1]\nirradiance = 2\n",
            "",
        )
        .replace("spp = 4", "spp = 64\nmax_depth = 10000");
    std::fs::write(&scene, text).unwrap();
    let out = dir.path().join("furnace.exr");
    let o = volgrad(&[
        "render",
        scene.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let mean = volgrad::io::images::read_rgb(&out).unwrap().mean();
    assert!(
        (mean - glam::Vec3::new(0.5, 0.25, 1.0)).abs().max_element() < 0.01,
        "mean {mean}"
    );

    // A map with negative radiance is refused, naming the light.
    let bad = volgrad::io::images::RgbImage {
        width: 2,
        height: 1,
        pixels: vec![glam::Vec3::splat(-1.0); 2],
    };
    volgrad::io::images::write_exr(&dir.path().join("sky.exr"), &bad, false).unwrap();
    assert_clean_error(
        &volgrad(&[
            "render",
            scene.to_str().unwrap(),
            "-o",
            dir.path().join("b.exr").to_str().unwrap(),
            "--quiet",
        ]),
        &["light[0].file", "negative"],
    );
}
