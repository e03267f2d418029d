//! `volgrad grad`, `merge` and `gradcheck` end to end, and their bad inputs.

use std::path::{Path, PathBuf};
use std::process::Command;

mod common;
use common::*;

use glam::IVec3;
use volgrad::io::vdb::{self, GridSelector};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A 16×16-pixel scene around an 8³ box with empty voxels: a sphere inside an active block.
fn scene(dir: &Path, name: &str, density_scale: f32) -> PathBuf {
    let vdb = dir.join("sphere.vdb");
    if !vdb.exists() {
        ok(volgrad(&[
            "make-grid",
            "sphere",
            "--size",
            "8",
            "--value",
            "1",
            "--voxel-size",
            "0.5",
            "-o",
            s(&vdb),
        ]));
    }
    let path = dir.join(name);
    std::fs::write(
        &path,
        format!(
            "[camera]\nposition = [0, 1, 8]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 16\nheight = 16\n\
             [medium]\nvdb = \"sphere.vdb\"\ndensity_scale = {density_scale}\nalbedo = 0.8\nphase_g = 0.2\n\
             [[light]]\ntype = \"constant\"\nradiance = 0.5\n\
             [[light]]\ntype = \"directional\"\ndirection = [0, -1, -1]\nirradiance = 2\n\
             [render]\nspp = 8\nmax_depth = 16\n"
        ),
    )
    .unwrap();
    path
}

#[test]
fn grad_writes_a_vdb_that_openvdb_reads_with_the_inputs_transform() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path(), "s.toml", 1.0);
    let out = dir.path().join("g.grad.vdb");
    let o = ok(volgrad(&[
        "grad",
        s(&scene),
        "--estimator",
        "joint",
        "--loss",
        "mean",
        "--spp",
        "8",
        "--seed",
        "3",
        "-o",
        s(&out),
        "-q",
        "--stats",
        "--image-of",
        "all",
    ]));
    assert!(stdout(&o).contains("ms per spp"), "{}", stdout(&o));
    let grids = vdb::list_grids(&out).unwrap();
    assert_eq!(grids.len(), 1);
    let g = &grids[0];
    assert_eq!(g.name, "grad_density");
    assert_eq!(g.grid_class, "fog volume");
    let input = &vdb::list_grids(&dir.path().join("sphere.vdb")).unwrap()[0];
    assert_eq!(g.index_to_world, input.index_to_world);
    let meta = |k: &str| {
        g.metadata
            .iter()
            .find(|e| e.name == k)
            .map(|e| e.value.clone())
            .unwrap_or_default()
    };
    assert_eq!(meta("volgrad_estimator"), "joint");
    assert_eq!(meta("volgrad_spp"), "8");
    assert_eq!(meta("volgrad_seed"), "3");
    assert_eq!(meta("volgrad_loss"), "mean");
    assert!(g.active_voxels > 100);
    let grid = vdb::read_grid(&out, &GridSelector::Index(0)).unwrap();
    assert!(grid
        .bricks
        .leaves()
        .iter()
        .flat_map(|l| l.values)
        .all(f32::is_finite));
    for picture in ["g.grad.png", "g.grad.dpixel.exr", "g.grad.dpixel.png"] {
        assert!(dir.path().join(picture).exists(), "{picture} missing");
    }
    // OpenVDB's own tool reads it, with our grid and transform.
    let print = Command::new("vdb_print")
        .args(["-l", s(&out)])
        .output()
        .expect("vdb_print is installed (scripts/setup.sh)");
    let text = String::from_utf8_lossy(&print.stdout);
    assert!(
        print.status.success() && text.contains("grad_density"),
        "{text}"
    );
    assert!(text.contains("0.5"), "voxel size missing: {text}");
    // No overwrite without --force.
    assert_clean_error(
        &volgrad(&["grad", s(&scene), "--spp", "1", "-o", s(&out), "-q"]),
        &["already exists"],
    );
}

#[test]
fn an_l2_loss_toward_a_denser_target_asks_for_more_density() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path(), "s.toml", 1.0);
    let denser = scene_path_with_scale(dir.path(), 3.0);
    let out = dir.path().join("g.vdb");
    let o = ok(volgrad(&[
        "grad",
        s(&scene),
        "--loss",
        "l2",
        "--target-scene",
        s(&denser),
        "--target-spp",
        "64",
        "--spp",
        "32",
        "-o",
        s(&out),
        "-q",
    ]));
    assert!(stderr(&o).contains("loss (l2)"), "{}", stderr(&o));
    let grid = vdb::read_grid(&out, &GridSelector::Index(0)).unwrap();
    let total: f64 = grid
        .bricks
        .leaves()
        .iter()
        .flat_map(|l| l.values)
        .map(|v| v as f64)
        .sum();
    assert!(
        total < 0.0,
        "⟨g, 1⟩ = {total}: raising the density must lower the loss"
    );
}

/// Lights at the largest radiance a scene takes (10³⁰): an L2 loss's gradient, a product of two
/// such radiances, goes beyond the f32 a VDB holds. Refused, with no file written, instead of a
/// grid of infinities and NaN in the report.
#[test]
fn a_gradient_beyond_f32_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let bright = |name: &str, scale: f32| {
        let path = scene(dir.path(), name, scale);
        let text = std::fs::read_to_string(&path).unwrap();
        let text = text
            .replace("radiance = 0.5", "radiance = 1e30")
            .replace("irradiance = 2", "irradiance = 1e30");
        std::fs::write(&path, text).unwrap();
        path
    };
    let (scene, target) = (bright("s.toml", 1.0), bright("target.toml", 3.0));
    let out = dir.path().join("g.vdb");
    assert_clean_error(
        &volgrad(&[
            "grad",
            s(&scene),
            "--loss",
            "l2",
            "--target-scene",
            s(&target),
            "--target-spp",
            "4",
            "--spp",
            "2",
            "-o",
            s(&out),
            "-q",
        ]),
        &["beyond a VDB's f32", "lights"],
    );
    assert!(!out.exists() && !dir.path().join("g.png").exists());
}

fn scene_path_with_scale(dir: &Path, scale: f32) -> PathBuf {
    scene(dir, "target.toml", scale)
}

#[test]
fn merge_weights_runs_by_their_spp() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path(), "s.toml", 1.0);
    let (a, b, m) = (
        dir.path().join("a.vdb"),
        dir.path().join("b.vdb"),
        dir.path().join("m.vdb"),
    );
    ok(volgrad(&[
        "grad",
        s(&scene),
        "--spp",
        "2",
        "--seed",
        "1",
        "-o",
        s(&a),
        "-q",
    ]));
    ok(volgrad(&[
        "grad",
        s(&scene),
        "--spp",
        "6",
        "--seed",
        "2",
        "-o",
        s(&b),
        "-q",
    ]));
    ok(volgrad(&["merge", s(&a), s(&b), "-o", s(&m)]));
    let read = |p: &Path| vdb::read_grid(p, &GridSelector::Index(0)).unwrap();
    let (ga, gb, gm) = (read(&a), read(&b), read(&m));
    let mut checked = 0;
    for leaf in gm.bricks.leaves() {
        for (o, &v) in leaf.values.iter().enumerate() {
            let p =
                leaf.origin + IVec3::new((o >> 6) as i32, ((o >> 3) & 7) as i32, (o & 7) as i32);
            let expected =
                (2.0 * ga.bricks.voxel(p) as f64 + 6.0 * gb.bricks.voxel(p) as f64) / 8.0;
            assert!(
                (v as f64 - expected).abs() <= 1e-6 * expected.abs().max(1e-9),
                "{p}: {v} vs {expected}"
            );
            checked += usize::from(v != 0.0);
        }
    }
    assert!(checked > 100);
    let spp = gm
        .metadata
        .iter()
        .find(|e| e.name == "volgrad_spp")
        .unwrap();
    assert_eq!(spp.value, "8");
    // A file that is not a gradient cannot be merged.
    assert_clean_error(
        &volgrad(&[
            "merge",
            s(&a),
            s(&dir.path().join("sphere.vdb")),
            "-o",
            s(&dir.path().join("x.vdb")),
        ]),
        &["sphere.vdb"],
    );
}

/// Merging averages runs of one computation; every way two files can differ in what they
/// computed is refused with the field that differs, and so is a repeated seed.
#[test]
fn merge_refuses_runs_of_different_computations() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = scene(d, "s.toml", 1.0);
    let grad = |seed: &str, out: &str, extra: &[&str]| {
        let out = d.join(out);
        let mut args = vec![
            "grad",
            s(&scene),
            "--spp",
            "1",
            "--seed",
            seed,
            "-o",
            s(&out),
            "-q",
        ];
        args.extend_from_slice(extra);
        ok(volgrad(&args));
        out
    };
    let merge =
        |a: &Path, b: &Path| volgrad(&["merge", s(a), s(b), "-o", s(&d.join("m.vdb")), "--force"]);
    let a = grad("1", "a.vdb", &[]);

    // The same scene given once absolute and once relative (run from its folder) merges.
    ok(volgrad_in(
        d,
        &[
            "grad", "s.toml", "--spp", "1", "--seed", "2", "-o", "b.vdb", "-q",
        ],
    ));
    ok(merge(&a, &d.join("b.vdb")));
    // The same file twice is the same seed twice.
    assert_clean_error(&merge(&a, &a), &["seed 1 is in both"]);

    // Another scene that is also called s.toml, in another folder.
    let other = d.join("other");
    std::fs::create_dir(&other).unwrap();
    let other_scene = self::scene(&other, "s.toml", 2.0);
    let c = d.join("c.vdb");
    ok(volgrad(&[
        "grad",
        s(&other_scene),
        "--spp",
        "1",
        "--seed",
        "3",
        "-o",
        s(&c),
        "-q",
    ]));
    assert_clean_error(&merge(&a, &c), &["volgrad_scene_fingerprint", "c.vdb"]);

    let depth = grad("4", "d.vdb", &["--max-depth", "1"]);
    assert_clean_error(
        &merge(&a, &depth),
        &["volgrad_max_depth", "'16' there and '1' here"],
    );
    let active = grad("5", "e.vdb", &["--domain", "active"]);
    assert_clean_error(&merge(&a, &active), &["volgrad_domain"]);
    let drt = grad("6", "f.vdb", &["--estimator", "drt"]);
    assert_clean_error(&merge(&a, &drt), &["volgrad_estimator"]);

    // Gradients of one loss toward two different targets.
    let target = |scale: f32, name: &str| {
        let image = d.join(name);
        let scene = scene_path_with_scale(d, scale);
        ok(volgrad(&[
            "render",
            s(&scene),
            "-o",
            s(&image),
            "--spp",
            "1",
            "-q",
            "--force",
        ]));
        image
    };
    let (t1, t2) = (target(1.5, "t1.exr"), target(2.0, "t2.exr"));
    let g1 = grad("7", "g1.vdb", &["--loss", "l2", "--target", s(&t1)]);
    let g2 = grad("8", "g2.vdb", &["--loss", "l2", "--target", s(&t2)]);
    assert_clean_error(&merge(&g1, &g2), &["volgrad_target_fingerprint"]);
    assert_clean_error(&merge(&a, &g1), &["volgrad_target_fingerprint"]);

    // Files whose metadata claim other counts (edited by hand): no samples, or counts whose sum
    // is beyond the int64 the merged file would store.
    let claiming = |spp: &str, seed: &str, name: &str| {
        let mut grid = vdb::read_grid(&a, &GridSelector::Index(0)).unwrap();
        for entry in &mut grid.metadata {
            match entry.name.as_str() {
                "volgrad_spp" => entry.value = spp.into(),
                "volgrad_seed" => entry.value = seed.into(),
                _ => {}
            }
        }
        let path = d.join(name);
        vdb::write_grids(&path, &[&grid], false, false).unwrap();
        path
    };
    assert_clean_error(
        &merge(&claiming("0", "90", "zero.vdb"), &a),
        &["volgrad_spp = 0"],
    );
    let huge = "5000000000000000000";
    assert_clean_error(
        &merge(
            &claiming(huge, "91", "huge1.vdb"),
            &claiming(huge, "92", "huge2.vdb"),
        ),
        &["huge2.vdb", "add up beyond"],
    );
}

#[test]
fn gradcheck_passes_joint_and_catches_naive_in_empty_voxels() {
    let dir = tempfile::tempdir().unwrap();
    let vdb = dir.path().join("hot.vdb");
    ok(volgrad(&[
        "make-grid",
        "single-voxel",
        "--size",
        "5",
        "--value",
        "4",
        "-o",
        s(&vdb),
    ]));
    let scene = dir.path().join("hot.toml");
    std::fs::write(
        &scene,
        "[camera]\nposition = [0, 0, 9]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 12\nheight = 12\n\
         [medium]\nvdb = \"hot.vdb\"\ndensity_scale = 0.5\nalbedo = 0.9\nfilter = \"nearest\"\n\
         [[light]]\ntype = \"constant\"\nradiance = 1\n[[light]]\ntype = \"directional\"\ndirection = [0, -1, 0]\nirradiance = 3\n\
         [render]\nmax_depth = 8\n",
    )
    .unwrap();
    let args = |e: &str| {
        volgrad(&[
            "gradcheck",
            s(&scene),
            "--estimator",
            e,
            "--spp",
            "32",
            "--fd-spp",
            "1024",
            "--repeats",
            "8",
            "--voxels",
            "2",
            "-q",
        ])
    };
    let joint = args("joint");
    assert!(
        joint.status.success(),
        "{}{}",
        stdout(&joint),
        stderr(&joint)
    );
    assert!(stdout(&joint).contains("⟨g, 1⟩"), "{}", stdout(&joint));
    let naive = args("naive");
    assert_clean_error(&naive, &["checks beyond"]);
    assert!(stdout(&naive).contains("FAIL"), "{}", stdout(&naive));
}

#[test]
fn finite_differences_print_values_with_standard_errors() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path(), "s.toml", 1.0);
    let o = ok(volgrad(&[
        "grad",
        s(&scene),
        "--estimator",
        "fd",
        "--fd",
        "voxels:3,3,3;0,0,0",
        "--fd-spp",
        "16",
        "--repeats",
        "3",
        "-q",
    ]));
    let out = stdout(&o);
    assert_eq!(out.matches(" ± ").count(), 2, "{out}");
    assert!(out.contains("one-sided"), "voxel [0,0,0] is empty: {out}");
}

#[test]
fn bad_gradient_inputs_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path(), "s.toml", 1.0);
    let out = dir.path().join("g.vdb");
    assert_clean_error(
        &volgrad(&["grad", s(&scene), "--loss", "l2", "-o", s(&out), "-q"]),
        &["--target"],
    );
    let small = dir.path().join("small.exr");
    ok(volgrad(&[
        "render",
        s(&scene),
        "-o",
        s(&small),
        "-q",
        "--spp",
        "1",
    ]));
    let tiny = scene_with_size(dir.path());
    assert_clean_error(
        &volgrad(&[
            "grad",
            s(&tiny),
            "--loss",
            "l1",
            "--target",
            s(&small),
            "-o",
            s(&out),
            "-q",
        ]),
        &["target is 16×16", "8×4"],
    );
    assert_clean_error(
        &volgrad(&[
            "grad",
            s(&scene),
            "--loss",
            "l2",
            "--target",
            s(&dir.path().join("nope.exr")),
            "-o",
            s(&out),
            "-q",
        ]),
        &["nope.exr"],
    );
    assert_clean_error(
        &volgrad(&["grad", s(&scene), "--estimator", "fd", "-q"]),
        &["--fd"],
    );
    assert_clean_error(
        &volgrad(&[
            "grad",
            s(&scene),
            "--estimator",
            "fd",
            "--fd",
            "voxels:1,2",
            "-q",
        ]),
        &["x,y,z"],
    );
    assert_clean_error(
        &volgrad(&[
            "grad",
            s(&scene),
            "--image-of",
            "1,2,3",
            "-o",
            s(&out),
            "-q",
        ]),
        &["six integers"],
    );
    // Boxes that are empty or miss the domain, and voxels that are not parameters, measure nothing.
    for (flag, spec, needle) in [
        ("--image-of", "3,3,3,1,1,1", "is empty"),
        (
            "--image-of",
            "100,100,100,200,200,200",
            "outside the gradient domain",
        ),
        (
            "--fd",
            "box:-50,-50,-50,-40,-40,-40",
            "outside the gradient domain",
        ),
        ("--fd", "voxels:3,3,3;500,0,0", "is not a parameter"),
    ] {
        let mut args = vec!["grad", s(&scene), flag, spec, "-q"];
        match flag {
            "--fd" => args.extend(["--estimator", "fd"]),
            _ => args.extend(["-o", s(&out), "--spp", "1"]),
        }
        assert_clean_error(&volgrad(&args), &[flag.trim_start_matches('-'), needle]);
    }
    assert_clean_error(
        &volgrad(&[
            "grad",
            s(&scene),
            "--spp",
            "0",
            "-o",
            s(&dir.path().join("z.vdb")),
            "-q",
        ]),
        &["--spp"],
    );
    assert_clean_error(
        &volgrad(&[
            "grad",
            s(&scene),
            "-o",
            "/no/such/dir/g.vdb",
            "-q",
            "--spp",
            "1",
        ]),
        &["/no/such/dir"],
    );
}

fn scene_with_size(dir: &Path) -> PathBuf {
    let base = std::fs::read_to_string(scene(dir, "s.toml", 1.0)).unwrap();
    let path = dir.join("tiny.toml");
    std::fs::write(
        &path,
        base.replace("width = 16", "width = 8")
            .replace("height = 16", "height = 4"),
    )
    .unwrap();
    path
}
