//! Pictures and cameras from elsewhere in `volgrad optimize`, on the tiny reconstruction
//! (`optimize_common`): transforms files and COLMAP models written from the orbit give it back,
//! pictures alone need no grid, an unknown exposure is fitted, and alpha targets pin the density.

mod common;
mod optimize_common;

use std::path::Path;

use common::{assert_clean_error, ok, volgrad_in};
use optimize_common::*;
use volgrad::cluster::Cluster;
use volgrad::optimize::problem::Problem;

/// The problem `d/run.toml` gives, loaded as one process.
fn run_problem(d: &Path) -> Problem {
    Problem::load(&d.join("run.toml"), None, false, None, &Cluster::single()).unwrap()
}

/// `d/transforms.json` with the fixture's 24² views at 40° and `frames` (JSON objects).
fn write_transforms(d: &Path, frames: &[String]) {
    let json = format!(
        "{{ \"camera_angle_x\": {}, \"w\": 24, \"h\": 24, \"frames\": [{}] }}",
        40f32.to_radians(),
        frames.join(", ")
    );
    std::fs::write(d.join("transforms.json"), json).unwrap();
}

/// The fixture's training orbit as its run file writes it (what the camera-file tests replace).
const ORBIT: &str =
    "[views.orbit]\ncount = 6\nelevation_deg = [-30, 70]\ndistance = 12\nfov_deg = 40\nwidth = 24\nheight = 24\n";

/// The two problems' training views are the same cameras: positions within `tolerance`, the same
/// rays through pixels across the image.
fn assert_same_cameras(a: &Problem, b: &Problem, tolerance: f32) {
    assert_eq!(a.views.len(), b.views.len());
    for (a, b) in a.views.iter().zip(&b.views) {
        assert!((a.camera.position - b.camera.position).length() < tolerance);
        for (x, y) in [(0.5, 0.5), (23.5, 0.5), (12.0, 12.0), (3.5, 20.5)] {
            let (da, db) = (a.camera.direction(x, y), b.camera.direction(x, y));
            assert!((da - db).length() < 1e-5, "pixel ({x}, {y}): {da} vs {db}");
        }
    }
}

/// A `transforms.json` (NeRF / instant-ngp: camera-to-world rows, the camera looking down −z)
/// written from an orbit's cameras gives those cameras back: the same positions and rays. A frame
/// whose `file_path` has no extension finds its `.exr`, which becomes its target as written.
#[test]
fn a_transforms_file_gives_back_the_orbit_it_was_written_from() {
    use volgrad::capture::transforms::camera_to_world;
    let dir = fixture(&run_file("0.2", ""));
    let d = dir.path();
    let orbit_problem = run_problem(d);
    let centre = {
        let (lo, hi) = orbit_problem.domain.world_box();
        (lo + hi) / 2.0
    };
    let frames: Vec<String> = orbit_problem
        .views
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let m = camera_to_world(v.camera.position, centre, glam::Vec3::Y);
            let image = if i == 0 {
                "\"file_path\": \"./first\", "
            } else {
                ""
            };
            format!("{{ {image}\"transform_matrix\": {m:?} }}")
        })
        .collect();
    write_transforms(d, &frames);
    let first = &orbit_problem.views[0].target;
    volgrad::io::images::write_exr(&d.join("first.exr"), first, false).unwrap();
    let run = run_file("0.2", "").replace(ORBIT, "[views]\ntransforms = \"transforms.json\"\n");
    assert!(run.contains("transforms.json"), "{run}");
    std::fs::write(d.join("run.toml"), run).unwrap();
    let json_problem = run_problem(d);
    assert_same_cameras(&orbit_problem, &json_problem, 1e-5);
    assert_eq!(json_problem.views[0].target.pixels, first.pixels);
    // A pose changed in the file, under the same name, is another run: a checkpoint of this one
    // would not be resumed by it.
    let json = std::fs::read_to_string(d.join("transforms.json")).unwrap();
    let mut moved: serde_json::Value = serde_json::from_str(&json).unwrap();
    let x = &mut moved["frames"][1]["transform_matrix"][0][3];
    *x = serde_json::json!(x.as_f64().unwrap() + 0.5);
    std::fs::write(d.join("transforms.json"), moved.to_string()).unwrap();
    let moved_problem = Problem::load(&d.join("run.toml"), None, false, None, &Cluster::single());
    let moved_problem = moved_problem.unwrap();
    assert_ne!(moved_problem.fingerprint, json_problem.fingerprint);
}

/// The same orbit as a COLMAP text model (world-to-camera quaternions, OpenCV axes) gives the
/// same cameras back; the first view's image, an 8-bit sRGB PNG with alpha as Blender writes
/// one over a transparent film, becomes its target decoded to radiance and composited over the
/// scene's sky (radiance (0.03, 0.04, 0.06)).
#[test]
fn a_colmap_model_with_a_png_gives_back_the_orbit_and_its_picture_over_the_sky() {
    use glam::{DMat3, DQuat, Vec3};
    let dir = fixture(&run_file("0.2", ""));
    let d = dir.path();
    let orbit_problem = run_problem(d);
    let mut images = String::from("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    for (i, v) in orbit_problem.views.iter().enumerate() {
        let c = &v.camera;
        // The camera's axes in the world, as COLMAP's: +x right, +y down, +z forward.
        let forward = c.direction(12.0, 12.0).as_dvec3();
        let down = (c.direction(12.0, 13.0) - c.direction(12.0, 11.0)).as_dvec3();
        let down = (down - forward * down.dot(forward)).normalize();
        let right = down.cross(forward);
        let world_to_camera = DMat3::from_cols(right, down, forward).transpose();
        let q = DQuat::from_mat3(&world_to_camera);
        let t = -(world_to_camera * c.position.as_dvec3());
        images += &format!(
            "{i} {} {} {} {} {} {} {} 3 view{i}.png\n\n",
            q.w, q.x, q.y, q.z, t.x, t.y, t.z
        );
    }
    let focal = 12.0 / 20f64.to_radians().tan();
    std::fs::create_dir_all(d.join("project/sparse/0")).unwrap();
    std::fs::create_dir_all(d.join("project/images")).unwrap();
    std::fs::write(
        d.join("project/sparse/0/cameras.txt"),
        format!("3 PINHOLE 24 24 {focal} {focal} 12 12\n"),
    )
    .unwrap();
    std::fs::write(d.join("project/sparse/0/images.txt"), images).unwrap();
    // Opaque red-ish in the top-left pixel, half-covered grey beside it, empty elsewhere.
    let mut rgba = vec![0u8; 24 * 24 * 4];
    rgba[..8].copy_from_slice(&[255, 128, 0, 255, 128, 128, 128, 128]);
    // One picture per view (a picture named twice is refused): the same pixels in each.
    for i in 0..orbit_problem.views.len() {
        image::RgbaImage::from_raw(24, 24, rgba.clone())
            .unwrap()
            .save(d.join(format!("project/images/view{i}.png")))
            .unwrap();
    }
    let run = run_file("0.2", "").replace(ORBIT, "[views.colmap]\nmodel = \"project/sparse/0\"\n");
    std::fs::write(d.join("run.toml"), run).unwrap();
    let colmap_problem = run_problem(d);
    assert_same_cameras(&orbit_problem, &colmap_problem, 1e-4);
    // sRGB 128/255 is radiance 0.2158; alpha 128/255 lets 0.498 of the sky through.
    let sky = Vec3::new(0.03, 0.04, 0.06);
    let target = &colmap_problem.views[0].target.pixels;
    assert!(
        (target[0] - Vec3::new(1.0, 0.2158, 0.0)).length() < 1e-3,
        "{}",
        target[0]
    );
    let a = 128.0 / 255.0;
    let grey = Vec3::splat(0.2158 * a) + (1.0 - a) * sky;
    assert!(
        (target[1] - grey).length() < 1e-3,
        "{} vs {grey}",
        target[1]
    );
    assert!((target[2] - sky).length() < 1e-6, "{}", target[2]);
    // The alpha channel is kept as the view's alpha target, and with every training picture
    // carrying one the run fits it by default; the orbit's rendered targets have none.
    let alpha = colmap_problem.views[0]
        .alpha
        .as_ref()
        .expect("an alpha target");
    assert_eq!(alpha.pixels[..3], [Vec3::ONE, Vec3::splat(a), Vec3::ZERO]);
    assert_eq!(colmap_problem.settings.alpha_weight, 1.0);
    assert!(orbit_problem.views.iter().all(|v| v.alpha.is_none()));
    assert_eq!(orbit_problem.settings.alpha_weight, 0.0);
}

/// The fixture's views as pictures from elsewhere, in `d`: the targets (× `brightness`) as EXRs
/// with their cameras in a transforms file, the held-out view as a listed camera and image, a
/// scene with the optical constants and lights only (no `vdb`, no camera), and a run file
/// `images.toml` over them with `bounds = "views"` and `optimizer` in its `[optimizer]`. Where
/// the fixture's run renders alpha targets, the pictures are RGBA over a transparent film, as a
/// renderer writes them: the medium's light alone (× `brightness`) and its alpha.
fn write_pictures(d: &Path, brightness: f32, optimizer: &str) {
    use volgrad::capture::transforms::camera_to_world;
    use volgrad::optimize::problem::View;
    let orbit_problem = run_problem(d);
    let (lo, hi) = orbit_problem.domain.world_box();
    let centre = (lo + hi) / 2.0;
    let sky = orbit_problem.scene.lights.environment.constant;
    let write = |name: &str, view: &View| {
        let (w, h) = (view.camera.width as usize, view.camera.height as usize);
        let target = &view.target.pixels;
        let path = d.join(name);
        match &view.alpha {
            None => exr::prelude::write_rgb_file(path, w, h, |x, y| {
                let c = target[y * w + x] * brightness;
                (c.x, c.y, c.z)
            }),
            Some(alpha) => exr::prelude::write_rgba_file(path, w, h, |x, y| {
                let a = alpha.pixels[y * w + x].x;
                let c = (target[y * w + x] - (1.0 - a) * sky) * brightness;
                (c.x, c.y, c.z, a)
            }),
        }
        .unwrap();
    };
    let frames: Vec<String> = (orbit_problem.views.iter().enumerate())
        .map(|(i, v)| {
            let name = format!("view{i}.exr");
            write(&name, v);
            let m = camera_to_world(v.camera.position, centre, glam::Vec3::Y);
            format!("{{ \"file_path\": \"{name}\", \"transform_matrix\": {m:?} }}")
        })
        .collect();
    write_transforms(d, &frames);
    let holdout = &orbit_problem.holdouts[0];
    write("holdout.exr", holdout);
    let scene = std::fs::read_to_string(d.join("scene.toml")).unwrap();
    let constants = scene.replace("vdb = \"ball.vdb\"\n", "").replace(
        "[camera]\nposition = [0.0, 2.0, 12.0]\ntarget = [0.0, 0.0, 0.0]\nfov_deg = 40\nwidth = 24\nheight = 24\n",
        "",
    );
    assert!(!constants.contains("vdb") && !constants.contains("[camera]"));
    std::fs::write(d.join("constants.toml"), &constants).unwrap();
    let run = run_file("0.2", optimizer);
    let (top, rest) = run.split_at(run.find("[views.orbit]").unwrap());
    // No truth: every target is a picture, so target_spp would be refused as idle too.
    let top = top.replace(
        "scene = \"scene.toml\"\ntruth = \"ball.vdb\"\ntarget_spp = 256\n",
        "scene = \"constants.toml\"\n",
    );
    let unknown =
        rest[rest.find("[unknown]").unwrap()..].replace("bounds = \"truth\"", "bounds = \"views\"");
    let (p, t) = (holdout.camera.position, centre);
    let run = format!(
        "{top}[views]\ntransforms = \"transforms.json\"\n\n[[holdout]]\nposition = [{}, {}, {}]\ntarget = [{}, {}, {}]\nfov_deg = 40\nwidth = 24\nheight = 24\nimage = \"holdout.exr\"\n\n{unknown}",
        p.x, p.y, p.z, t.x, t.y, t.z
    );
    assert!(
        !run.contains("truth =") && !run.contains("target_spp"),
        "{run}"
    );
    std::fs::write(d.join("images.toml"), run).unwrap();
}

/// Pictures without a grid: a scene with the optical constants and lights only (no `vdb`, no
/// camera), images with their cameras in a transforms file, and `bounds = "views"`. The run finds
/// the box every camera sees, writes it in settings.toml and reconstructs; the same scene is
/// refused by `render`, which needs a grid and a camera.
#[test]
fn pictures_alone_need_no_grid_and_give_their_own_box() {
    let dir = fixture(&run_file("0.2", ""));
    let d = dir.path();
    write_pictures(d, 1.0, "iterations = 2");
    ok(volgrad_in(
        d,
        &["optimize", "images.toml", "--out", "out", "-q"],
    ));
    let settings: toml::Value =
        toml::from_str(&std::fs::read_to_string(d.join("out/settings.toml")).unwrap()).unwrap();
    let bounds = &settings["unknown"]["bounds"];
    let corner = |key: &str| -> Vec<f64> {
        let v = bounds[key].as_array().unwrap();
        v.iter().map(|x| x.as_float().unwrap()).collect()
    };
    let (min, max) = (corner("min"), corner("max"));
    // The ball (radius 3 around the origin) is inside what every camera sees; the box is not
    // the whole space between the cameras (12 from the centre).
    for a in 0..3 {
        assert!(min[a] < -3.0 && min[a] > -11.0, "{min:?} {max:?}");
        assert!(max[a] > 3.0 && max[a] < 11.0, "{min:?} {max:?}");
    }
    let voxel = settings["unknown"]["voxel_size"].as_float().unwrap();
    assert!(voxel > 0.0);
    // The box as its voxels cover it, a whole number of them (the box found is not).
    for a in 0..3 {
        let n = (max[a] - min[a]) / voxel;
        assert!((n - n.round()).abs() < 1e-3, "{n} voxels along axis {a}");
    }
    // The voxel is the finest pixel's footprint: no coarser level to start from.
    let levels = settings["unknown"]["levels"].as_array().unwrap();
    assert!(levels.is_empty(), "{levels:?}");
    assert!(d.join("out/final.vdb").is_file());
    assert_clean_error(
        &volgrad_in(d, &["render", "constants.toml", "-o", "x.exr"]),
        &["names no camera"],
    );
}

/// One hot pixel in a training picture's sky (a firefly; the sun in a photograph) does not clear
/// the start: the background tolerance is a share of the pictures' brightness, which the pixel
/// must not raise past the medium's (at 10⁴ among 24² views it counted every pixel as sky).
#[test]
fn a_hot_pixel_in_the_sky_does_not_clear_the_start() {
    let dir = fixture(&run_file("0.2", ""));
    let d = dir.path();
    write_pictures(d, 1.0, "iterations = 1");
    let active_at_start = |out: &str| {
        ok(volgrad_in(
            d,
            &[
                "optimize",
                "images.toml",
                "--iterations",
                "0",
                "--out",
                out,
                "-q",
            ],
        ));
        number(&log(&d.join(out))[0], "active_voxels")
    };
    let clean = active_at_start("clean");
    let path = d.join("view0.exr");
    let image = exr::prelude::read_first_rgba_layer_from_file(
        &path,
        |size, _| (size.width(), vec![[0f32; 3]; size.width() * size.height()]),
        |(w, px): &mut (usize, Vec<[f32; 3]>), pos, (r, g, b, _): (f32, f32, f32, f32)| {
            px[pos.y() * *w + pos.x()] = [r, g, b];
        },
    )
    .unwrap();
    let (w, mut pixels) = image.layer_data.channel_data.pixels;
    pixels[0] = [1e4; 3];
    std::fs::remove_file(&path).unwrap();
    exr::prelude::write_rgb_file(&path, w, pixels.len() / w, |x, y| {
        let [r, g, b] = pixels[y * w + x];
        (r, g, b)
    })
    .unwrap();
    // Within a percent: the pixel, clipped, still moves the tolerance a little.
    let hot = active_at_start("hot");
    assert!(
        clean > 0.0 && (hot - clean).abs() <= 0.01 * clean,
        "{clean} {hot}"
    );
}

/// A held-out picture that a training view also uses, however its path is written (a hard link
/// included) or whichever camera source names it, is refused: the held-out score would be of the training pictures.
#[test]
fn a_training_picture_is_refused_as_a_held_out_one() {
    let dir = fixture(&run_file("0.2", ""));
    let d = dir.path();
    write_pictures(d, 1.0, "iterations = 1");
    let run = std::fs::read_to_string(d.join("images.toml")).unwrap();
    let listed = run.replace("image = \"holdout.exr\"", "image = \"./sub/../view0.exr\"");
    std::fs::create_dir(d.join("sub")).unwrap();
    std::fs::write(d.join("listed.toml"), listed).unwrap();
    assert_clean_error(
        &volgrad_in(d, &["optimize", "listed.toml", "--out", "a", "-q"]),
        &["view0.exr", "no training view uses"],
    );
    // A hard link is the same file under another name (a symbolic link resolves to it).
    std::fs::hard_link(d.join("view0.exr"), d.join("linked.exr")).unwrap();
    let linked = run.replace("image = \"holdout.exr\"", "image = \"linked.exr\"");
    std::fs::write(d.join("linked.toml"), linked).unwrap();
    assert_clean_error(
        &volgrad_in(d, &["optimize", "linked.toml", "--out", "c", "-q"]),
        &["linked.exr", "no training view uses"],
    );
    let holdout = &run[run.find("[[holdout]]").unwrap()..run.find("[unknown]").unwrap()];
    let same_file = run.replace(holdout, "[holdouts]\ntransforms = \"transforms.json\"\n\n");
    std::fs::write(d.join("same.toml"), same_file).unwrap();
    assert_clean_error(
        &volgrad_in(d, &["optimize", "same.toml", "--out", "b", "-q"]),
        &[
            "views.transforms camera 0",
            "holdouts.transforms camera 0",
            "view0.exr",
            "no training view uses",
        ],
    );
}

/// A capture 30 % brighter than the scene's lights say (an exposure nobody wrote down): with
/// `fit_exposure` the run finds the factor (the sky behind the ball pins it) and the held-out
/// view fits far better than without, where no density can brighten the sky.
#[test]
fn an_unknown_exposure_is_fitted_with_the_volume() {
    let dir = fixture(&run_file("0.2", ""));
    let d = dir.path();
    let mut last = Vec::new();
    for fit in [true, false] {
        write_pictures(d, 1.3, &format!("iterations = 60\nfit_exposure = {fit}"));
        let out = format!("out-{fit}");
        ok(volgrad_in(
            d,
            &["optimize", "images.toml", "--out", &out, "-q"],
        ));
        let rows = log(&d.join(&out));
        let row = rows.last().unwrap().clone();
        last.push((
            row["exposure"].parse::<f64>().unwrap(),
            row["heldout_psnr"].parse::<f64>().unwrap(),
        ));
    }
    let ((fitted, with), (fixed, without)) = (last[0], last[1]);
    eprintln!("exposure {fitted} (PSNR {with}) against {fixed} (PSNR {without})");
    assert!((fitted - 1.3).abs() < 0.05, "{fitted}");
    assert_eq!(fixed, 1.0);
    assert!(with > without + 2.0, "{with} vs {without}");
}

/// Two captures at their own exposures (× 1.3 and × 0.8), named as two view sets: each set's
/// factor is fitted on its own, and a held-out set compared at its capture's. Without naming the
/// held-out views' capture, the run refuses to guess it.
#[test]
fn each_capture_has_its_own_exposure() {
    let bright = fixture(&run_file("0.2", ""));
    let dim = fixture(&run_file("0.2", ""));
    write_pictures(dim.path(), 0.8, "");
    let d = bright.path();
    write_pictures(d, 1.3, "iterations = 80\nfit_exposure = true");
    let run = std::fs::read_to_string(d.join("images.toml")).unwrap();
    let one_set = "[views]\ntransforms = \"transforms.json\"\n";
    assert!(run.contains(one_set), "{run}");
    let two_sets = format!(
        "[[views]]\ntransforms = \"transforms.json\"\ncapture = \"bright\"\n\n[[views]]\ntransforms = \"{}\"\ncapture = \"dim\"\n",
        dim.path().join("transforms.json").display()
    );
    let run = run.replace(one_set, &two_sets);
    std::fs::write(d.join("unnamed.toml"), &run).unwrap();
    assert_clean_error(
        &volgrad_in(d, &["optimize", "unnamed.toml", "--out", "x", "-q"]),
        &["holdout[0]", "the unnamed capture is no training set's"],
    );
    std::fs::write(
        d.join("named.toml"),
        format!("{run}\n[holdouts]\ncapture = \"bright\"\n"),
    )
    .unwrap();
    ok(volgrad_in(
        d,
        &["optimize", "named.toml", "--out", "out", "-q"],
    ));
    let rows = log(&d.join("out"));
    let last = rows.last().unwrap();
    let fitted: Vec<f64> = (last["exposure"].split_whitespace())
        .map(|x| x.parse().unwrap())
        .collect();
    eprintln!(
        "exposures {fitted:?}, held-out PSNR {}",
        last["heldout_psnr"]
    );
    assert_eq!(fitted.len(), 2, "{fitted:?}");
    assert!((fitted[0] - 1.3).abs() < 0.05, "{fitted:?}");
    assert!((fitted[1] - 0.8).abs() < 0.04, "{fitted:?}");
    let settings = std::fs::read_to_string(d.join("out/settings.toml")).unwrap();
    assert!(settings.contains("capture = \"dim\""), "{settings}");
}

/// Alpha targets pin the density down: from the same start and at the same iterations, the run
/// that fits alpha beside colour (alpha targets rendered from the truth) ends nearer the true
/// grid than the run that fits colour alone.
#[test]
fn alpha_targets_bring_the_volume_nearer_the_truth() {
    let mut rmse = Vec::new();
    for weight in [1, 0] {
        let dir = fixture(&run_file(
            "0.02",
            &format!("iterations = 100\nalpha_weight = {weight}"),
        ));
        let d = dir.path();
        ok(volgrad_in(
            d,
            &["optimize", "run.toml", "--out", "out", "-q"],
        ));
        let rows = log(&d.join("out"));
        rmse.push(number(rows.last().unwrap(), "volume_rmse"));
    }
    eprintln!(
        "volume RMSE with alpha {} against {} without",
        rmse[0], rmse[1]
    );
    // Seen 0.118 against 0.215: colour alone leaves the ball's inside and edge loosely fixed.
    assert!(rmse[0] < 0.7 * rmse[1], "{rmse:?}");
}

/// The fixture with alpha targets and a sky brighter than the lit ball, over most of every
/// picture.
fn bright_sky_fixture() -> tempfile::TempDir {
    let dir = fixture(&run_file("0.2", "alpha_weight = 1"));
    let scene = SCENE.replace(
        "radiance = [0.03, 0.04, 0.06]",
        "radiance = [0.8, 1.0, 1.2]",
    );
    assert_ne!(scene, SCENE, "the fixture's sky is where this expects it");
    std::fs::write(dir.path().join("scene.toml"), scene).unwrap();
    dir
}

/// RGBA pictures of a capture 30 % brighter than the lights say: the fitted exposure scales the
/// sky seen through the medium as it scales the medium's light, so it finds 1.3 from pictures
/// over a transparent film as from opaque ones.
#[test]
fn an_unknown_exposure_is_fitted_from_pictures_with_alpha() {
    // The fixture's bright sky: were it left at the scene's brightness behind the medium, it
    // would hold the exposure near 1.
    let dir = bright_sky_fixture();
    let d = dir.path();
    write_pictures(d, 1.3, "iterations = 60\nfit_exposure = true");
    ok(volgrad_in(
        d,
        &["optimize", "images.toml", "--out", "out", "-q"],
    ));
    let settings = std::fs::read_to_string(d.join("out/settings.toml")).unwrap();
    assert!(settings.contains("alpha_weight = 1.0"), "{settings}");
    let rows = log(&d.join("out"));
    let fitted = number(rows.last().unwrap(), "exposure");
    // Seen 1.292; with the sky behind the medium left at the scene's brightness, 1.243.
    assert!((fitted - 1.3).abs() < 0.03, "{fitted}");
}

/// The exposure's gradient is the loss's derivative in its log-factor x (k = eˣ). With the render
/// held (one iteration's seeds) the fixture's L2 loss is quadratic in k (alpha's loss does not
/// depend on k), so a central difference in k gives it to rounding. Pictures with alpha over a
/// bright sky: the target's composited background moves with k too (T(k) = P + k·(1 − α)·B), and
/// the gradient must carry that term. The exposure is not fitted here, so the gradient comes
/// from one render; a fitted exposure's pairs two halves of it, by design not the derivative
/// of either half's loss (`piece_adjoint`).
#[test]
fn the_exposure_gradient_is_the_derivative_of_the_loss() {
    use volgrad::gradient::adjoint::Estimator;
    use volgrad::optimize::iteration::images_gradient;
    let dir = bright_sky_fixture();
    let d = dir.path();
    write_pictures(d, 1.3, "alpha_weight = 1");
    let cluster = Cluster::single();
    let problem = Problem::load(&d.join("images.toml"), None, false, None, &cluster).unwrap();
    assert!(problem.views.iter().all(|v| v.background.is_some()));
    let mut scene = problem.scene_at(problem.start.to_brickmap(), 0);
    let level_box = problem.domain.voxel_box(0);
    let mut at = |k: f32| {
        images_gradient(
            &problem,
            &cluster,
            &mut scene,
            Estimator::Joint,
            3,
            &[k],
            level_box,
        )
        .unwrap()
    };
    let (k, h) = (1.1f32, 0.01f32);
    let gradient = at(k).exposure_gradients[0];
    let step = f64::from(k + h) - f64::from(k - h);
    let difference = (at(k + h).loss - at(k - h).loss) / step;
    // ∂loss/∂x = k·∂loss/∂k.
    let expected = f64::from(k) * difference;
    eprintln!("∂loss/∂x {gradient} against {expected} by differences");
    assert!(expected.abs() > 1e-3, "{expected}");
    assert!(
        (gradient - expected).abs() < 1e-3 * expected.abs(),
        "{gradient} vs {expected}"
    );
}

/// A fitted exposure with relative-l2 and pictures with alpha is refused: the target's background
/// moves with the exposure and relative-l2 divides by the target, a term the step's exposure
/// gradient leaves out (seen: −0.0387 against −0.0452 by differences in the test above's setting).
#[test]
fn a_fitted_exposure_with_relative_l2_over_alpha_is_refused() {
    let dir = bright_sky_fixture();
    let d = dir.path();
    write_pictures(
        d,
        1.3,
        "iterations = 2\nfit_exposure = true\nloss = \"relative-l2\"",
    );
    let out = volgrad_in(d, &["optimize", "images.toml", "--out", "out", "-q"]);
    assert_clean_error(&out, &["fit_exposure", "relative-l2", "alpha"]);
}
