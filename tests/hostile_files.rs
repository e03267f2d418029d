//! Files that are not what they claim to be, end to end through the `volgrad` binary: an output
//! path that is a folder or in a missing one, an input that is a FIFO, an image without colour,
//! a finite-difference step beyond its values, a target scene seen from elsewhere. Each refused
//! before any work, or (the last) given the meaning the manual states.

use std::path::{Path, PathBuf};

mod common;
use common::*;

/// A small scene `name` around a `make-grid` sphere in `dir`, its camera at z = `camera_z`.
fn scene_in(dir: &Path, name: &str, camera_z: f32, density_scale: f32) -> PathBuf {
    sphere_vdb(dir);
    let scene = dir.join(name);
    std::fs::write(
        &scene,
        format!(
            "[camera]\nposition = [0, 1, {camera_z}]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 12\nheight = 8\n\
             [medium]\nvdb = \"sphere.vdb\"\ndensity_scale = {density_scale}\nalbedo = 0.9\n\
             [[light]]\ntype = \"constant\"\nradiance = 0.5\n\
             [render]\nspp = 2\n"
        ),
    )
    .unwrap();
    scene
}

fn path(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn an_output_that_is_a_folder_is_refused_before_anything_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene_in(dir.path(), "s.toml", 12.0, 2.0);
    let (exr, png) = (dir.path().join("q.exr"), dir.path().join("q.png"));
    std::fs::create_dir(&png).unwrap();
    let o = volgrad(&["render", path(&scene), "-o", path(&exr), "--force", "-q"]);
    assert_clean_error(&o, &["q.png", "it is a folder"]);
    assert!(
        !exr.exists(),
        "the EXR was written before the PNG was refused"
    );
    let vdb = dir.path().join("g.vdb");
    std::fs::create_dir(dir.path().join("g.png")).unwrap();
    let o = volgrad(&["grad", path(&scene), "-o", path(&vdb), "--spp", "1", "-q"]);
    assert_clean_error(&o, &["g.png", "it is a folder"]);
    assert!(!vdb.exists());
}

/// An output in a folder that does not exist is refused before the scene is even read (its VDB
/// is missing here, and the error is the folder's): it was refused after the whole render.
#[test]
fn an_output_in_a_missing_folder_is_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene_in(dir.path(), "s.toml", 12.0, 2.0);
    std::fs::remove_file(dir.path().join("sphere.vdb")).unwrap();
    let exr = dir.path().join("missing/q.exr");
    let o = volgrad(&["render", path(&scene), "-o", path(&exr), "-q"]);
    assert_clean_error(&o, &["q.exr", "missing", "does not exist"]);
    let vdb = dir.path().join("missing/g.vdb");
    let o = volgrad(&["grad", path(&scene), "-o", path(&vdb), "--spp", "1", "-q"]);
    assert_clean_error(&o, &["g.vdb", "missing", "does not exist"]);
}

/// `volgrad ARGS`, ended by `timeout` if a refusal regresses into a read that never returns.
fn volgrad_within_a_minute(args: &[&str]) -> std::process::Output {
    std::process::Command::new("timeout")
        .args(["60", env!("CARGO_BIN_EXE_volgrad")])
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn an_input_that_is_a_fifo_is_refused_not_read_forever() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = |name: &str| {
        let fifo = dir.path().join(name);
        assert!(std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success());
        fifo
    };
    let toml = fifo("f.toml");
    let o = volgrad_within_a_minute(&["render", path(&toml), "-q"]);
    assert_clean_error(&o, &["f.toml", "not a regular file"]);
    // A picture, whatever its name: the PNG reader's look at the file's first bytes blocked on
    // a FIFO, before the bridge's check could refuse it.
    let scene = scene_in(dir.path(), "s.toml", 12.0, 2.0);
    let out = dir.path().join("g.vdb");
    for name in ["t.png", "t.exr"] {
        let target = fifo(name);
        let o = volgrad_within_a_minute(&[
            "grad",
            path(&scene),
            "--loss",
            "l2",
            "--target",
            path(&target),
            "-o",
            path(&out),
            "-q",
        ]);
        assert_clean_error(&o, &[name, "not a regular file"]);
    }
}

#[test]
fn an_image_without_colour_channels_is_refused() {
    use exr::prelude::*;
    let dir = tempfile::tempdir().unwrap();
    let scene = scene_in(dir.path(), "s.toml", 12.0, 2.0);
    // A depth image of the scene's size: one channel named Z.
    let depth = dir.path().join("depth.exr");
    let channel = AnyChannel::new("Z", FlatSamples::F32(vec![3.0; 12 * 8]));
    let image = Image::from_channels(
        (12, 8),
        AnyChannels::sort(SmallVec::from_vec(vec![channel])),
    );
    image.write().to_file(&depth).unwrap();
    let out = dir.path().join("g.vdb");
    let o = volgrad(&[
        "grad",
        path(&scene),
        "--loss",
        "l2",
        "--target",
        path(&depth),
        "-o",
        path(&out),
        "-q",
    ]);
    assert_clean_error(&o, &["depth.exr", "no colour channels", "Z"]);
}

#[test]
fn a_finite_difference_step_beyond_the_values_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene_in(dir.path(), "s.toml", 12.0, 2.0);
    let o = volgrad(&[
        "grad",
        path(&scene),
        "--estimator",
        "fd",
        "--fd",
        "ones",
        "--fd-spp",
        "1",
        "--repeats",
        "2",
        "--eps",
        "1e30",
        "-q",
    ]);
    assert_clean_error(&o, &["--eps", "ten times the grid's largest value"]);
}

#[test]
fn a_target_scene_is_seen_through_the_scenes_own_camera() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene_in(dir.path(), "s.toml", 12.0, 2.0);
    // Thinner, seen from the same place; and the same from elsewhere, whose camera is not used.
    let here = scene_in(dir.path(), "here.toml", 12.0, 1.0);
    let elsewhere = scene_in(dir.path(), "elsewhere.toml", 20.0, 1.0);
    // What `grad` says of its gradient: the voxels it reached and ⟨g, 1⟩ to seven digits.
    let grad_with = |target: &Path, out: &str| {
        let out = dir.path().join(out);
        let o = ok(volgrad(&[
            "grad",
            path(&scene),
            "--loss",
            "l2",
            "--target-scene",
            path(target),
            "--target-spp",
            "8",
            "--spp",
            "2",
            "-o",
            path(&out),
        ]));
        let said = stdout(&o) + &stderr(&o);
        let at = said
            .find("voxels with gradient")
            .expect("grad reports its gradient");
        said[..at + 40]
            .rsplit('(')
            .next()
            .unwrap_or_default()
            .to_string()
    };
    let (a, b) = (grad_with(&here, "a.vdb"), grad_with(&elsewhere, "b.vdb"));
    assert!(a.contains("⟨g, 1⟩"), "{a}");
    assert_eq!(a, b);
}

/// Every file volgrad writes goes through `io::output::write_whole` (a temporary name, then a
/// rename), so that a process killed mid-write leaves the old file or none, never half of one:
/// no code outside it writes a file in place (tests excepted). `progress.png`, rewritten at
/// every checkpoint, and the studies' tables were written in place.
#[test]
fn no_output_is_written_in_place() {
    fn sources(dir: &Path, found: &mut Vec<PathBuf>) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                sources(&path, found);
            } else if path.extension().is_some_and(|e| e == "rs") {
                found.push(path);
            }
        }
    }
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    sources(&src, &mut files);
    assert!(files.len() > 50, "{} sources", files.len());
    let mut in_place = Vec::new();
    for file in files {
        let name = file.to_string_lossy();
        if name.ends_with("_tests.rs") || name.ends_with("io/output.rs") {
            continue;
        }
        let text = std::fs::read_to_string(&file).unwrap();
        let code = text.split("#[cfg(test)]").next().unwrap();
        for (n, line) in code.lines().enumerate() {
            if ["fs::write(", "File::create("]
                .iter()
                .any(|w| line.contains(w))
            {
                in_place.push(format!("{}:{}: {}", name, n + 1, line.trim()));
            }
        }
    }
    assert!(
        in_place.is_empty(),
        "written in place:\n{}",
        in_place.join("\n")
    );
}

/// A VDB or an image is written under a temporary name of the writing process's own, then renamed:
/// a user's `NAME.tmp` beside the output is not the temporary (it was truncated, then removed),
/// and nothing is left behind.
#[test]
fn a_users_file_is_never_the_temporary() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for name in ["g.vdb.tmp", ".r.tmp.exr"] {
        std::fs::write(d.join(name), "mine").unwrap();
    }
    ok(volgrad_in(
        d,
        &["make-grid", "box", "--size", "4", "-o", "g.vdb"],
    ));
    let scene = scene_in(d, "s.toml", 30.0, 1.0);
    ok(volgrad_in(
        d,
        &["render", path(&scene), "--spp", "1", "-o", "r.exr", "-q"],
    ));
    for name in ["g.vdb.tmp", ".r.tmp.exr"] {
        assert_eq!(
            std::fs::read_to_string(d.join(name)).unwrap(),
            "mine",
            "{name}"
        );
    }
    let mut left: Vec<String> = std::fs::read_dir(d)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp") && n != "g.vdb.tmp" && n != ".r.tmp.exr")
        .collect();
    left.sort();
    assert!(left.is_empty(), "left behind: {left:?}");
}
