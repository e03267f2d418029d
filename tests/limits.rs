//! Every quantity a user types has a limit, checked before it is used: sizes whose product would
//! wrap an integer, durations past any clock, thread counts past any machine, densities past what
//! the renderer tracks. Each class gets a clean error, never a panic, an abort or a wait without
//! end.

mod common;
mod optimize_common;

use std::path::Path;
use std::process::Output;

use common::{assert_clean_error, ok, stderr, volgrad_in};
use optimize_common::*;
use volgrad::io::vdb::{read_grid, GridSelector};

/// `grad` of the L2 loss against the picture `target`, one sample per pixel.
fn grad_against(dir: &Path, target: &str) -> Output {
    let args = ["grad", "scene.toml", "--loss", "l2", "--target", target];
    volgrad_in(
        dir,
        &[&args[..], &["--spp", "1", "-o", "g.vdb", "-q"]].concat(),
    )
}

/// A value clap refuses: exit status 2 and its one `error: ` line naming `needle`.
fn assert_flag_refused(o: &Output, needle: &str) {
    let err = stderr(o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(err.contains(needle), "{err}");
}

#[test]
fn flags_beyond_any_machine_are_refused() {
    let dir = fixture(&run_file("0.1", "spp = 1\niterations = 2"));
    let d = dir.path();
    let render = ["render", "scene.toml", "-o", "a.exr", "--spp", "1", "-q"];
    let threads = volgrad_in(d, &[&render[..], &["--threads", "100000"]].concat());
    assert_clean_error(&threads, &["--threads", "at most 1024"]);
    // A thread count above the machine's cores is taken, without a warning from the VDB reader's
    // thread pool (TBB's) on stderr.
    let o = ok(volgrad_in(d, &[&render[..], &["--threads", "64"]].concat()));
    assert!(!stderr(&o).contains("TBB"), "{}", stderr(&o));

    // 10²¹ seconds: `Duration` would panic on it, and an `Instant` plus a long one overflows.
    let eon = "1000000000000000000000s";
    let budget = volgrad_in(d, &["optimize", "run.toml", "--budget", eon, "-q"]);
    assert_flag_refused(&budget, "too long a duration");
    let render_budget = [
        "compare",
        "scene.toml",
        "--render-budget",
        "99999999999999999999h",
    ];
    assert_flag_refused(&volgrad_in(d, &render_budget), "too long a duration");

    // gradcheck's image: 10¹⁰ pixels would be a 120 GB allocation (an abort), and 2³² − 1 a side
    // overflows the pixel count's capacity (a panic).
    for width in ["100000", "4294967295"] {
        let check = [
            "gradcheck",
            "scene.toml",
            "--width",
            width,
            "--spp",
            "1",
            "-q",
        ];
        assert_clean_error(&volgrad_in(d, &check), &["--width", "too large", "2^28"]);
    }
}

/// An unknown's box of 2²² voxels a side: its voxel count, 2⁶⁶, wrapped to 0 in u64 and passed
/// the limit (then a panic in the visual hull, or hours of resampling the truth).
#[test]
fn an_unknown_box_whose_voxel_count_overflows_is_refused() {
    let run = run_file("0.1", "iterations = 1").replace(
        "bounds = \"truth\"",
        "bounds = { min = [-2097152, -2097152, -4194324], max = [2097152, 2097152, -20] }\nvoxel_size = 1.0",
    );
    let dir = fixture(&run);
    let o = volgrad_in(dir.path(), &["optimize", "run.toml", "-q"]);
    assert_clean_error(
        &o,
        &["unknown.bounds", "more than 1.8e19 voxels", "at most"],
    );
}

/// Voxels smaller than a VDB transform can hold (OpenVDB calls it nearly singular below about
/// 1e-5): refused before anything runs, not by the first checkpoint's write after the targets.
#[test]
fn voxels_too_small_to_write_are_refused() {
    let run = run_file("0.1", "iterations = 1").replace(
        "bounds = \"truth\"",
        "bounds = { min = [0, 0, 0], max = [1e-5, 1e-5, 1e-5] }\nvoxel_size = 1e-6",
    );
    let dir = fixture(&run);
    let cached = ["optimize", "run.toml", "--target-cache", "cache", "-q"];
    let o = volgrad_in(dir.path(), &cached);
    assert_clean_error(&o, &["unknown.voxel_size", "1e-4"]);
    assert!(!dir.path().join("cache").exists(), "targets were rendered");
    let grid = ["make-grid", "box", "--voxel-size", "1e-5", "-o", "g.vdb"];
    assert_clean_error(&volgrad_in(dir.path(), &grid), &["--voxel-size", "1e-4"]);
}

/// Values beyond an extinction of 1e15 per unit (the cap every grid the renderer loads is held
/// to): a start there is refused before any target is rendered, and steps that would go there (a
/// learning rate of 1e30, which ran for hours) stop at it.
#[test]
fn the_unknown_stays_within_what_the_renderer_tracks() {
    let dir = fixture(&run_file("1e20", "iterations = 1"));
    let cached = ["optimize", "run.toml", "--target-cache", "cache", "-q"];
    let o = volgrad_in(dir.path(), &cached);
    let rendered = std::fs::read_dir(dir.path().join("cache")).map_or(0, |d| d.count());
    assert_eq!(
        rendered, 0,
        "targets were rendered before the start was checked"
    );
    // density_scale 0.6: at most 1e15 / 0.6 ≈ 1.7e15.
    assert_clean_error(
        &o,
        &[
            "unknown.start",
            "1e20",
            "1.666",
            "e15",
            "extinction of 1e15",
        ],
    );

    let dir = fixture(&run_file("0.1", "spp = 1\niterations = 2").replace("lr = 0.1", "lr = 1e30"));
    ok(volgrad_in(dir.path(), &["optimize", "run.toml", "-q"]));
    let result = read_grid(
        &dir.path().join("run.out/final.vdb"),
        &GridSelector::Default,
    )
    .unwrap();
    let largest = result.bricks.max_value();
    // At the cap, 1e15 / density_scale: not 1e15 (the cap without the scene's scale).
    assert!(largest > 1.5e15 && largest <= 1e15 / 0.6, "{largest:e}");
}

/// Nothing beyond half floats' range is stored as half (it would come back infinite): an image
/// with `render --half`, a grid with `make-grid --half`.
#[test]
fn values_beyond_half_floats_are_not_stored_as_half() {
    let dir = fixture(&run_file("0.1", ""));
    let d = dir.path();
    let bright = SCENE.replace("radiance = [0.03, 0.04, 0.06]", "radiance = 1e5");
    std::fs::write(d.join("bright.toml"), bright).unwrap();
    let o = volgrad_in(
        d,
        &[
            "render",
            "bright.toml",
            "-o",
            "b.exr",
            "--spp",
            "1",
            "--half",
            "-q",
        ],
    );
    assert_clean_error(&o, &["b.exr", "half floats", "65504", "float"]);
    assert!(!d.join("b.exr").exists() && !d.join("b.png").exists());
    let o = volgrad_in(
        d,
        &[
            "make-grid",
            "box",
            "--value",
            "1e6",
            "--half",
            "-o",
            "h.vdb",
        ],
    );
    assert_clean_error(&o, &["1e6", "half floats"]);
    assert!(!d.join("h.vdb").exists());
}

/// A picture a loss compares with holds radiance: finite and at most 1e30 in magnitude (beyond
/// it no scene renders it, and its squared difference overflows f32: an infinite loss, an
/// adjoint dropped as non-finite), and its alpha is in [0, 1]. For `grad --target` and for a
/// view's image.
#[test]
fn target_pictures_hold_radiance() {
    let dir = fixture(&run_file("0.1", "iterations = 1"));
    let d = dir.path();
    let write = |name: &str, at: usize, rgb: f32, alpha: f32| {
        let path = d.join(name);
        exr::prelude::write_rgba_file(&path, 24, 24, |x, y| {
            let v = if y * 24 + x == at { rgb } else { 0.25 };
            let a = if y * 24 + x == at { alpha } else { 1.0 };
            (v, v, v, a)
        })
        .unwrap();
    };
    write("huge.exr", 5, 3e38, 1.0);
    write("negative.exr", 7, -3e38, 1.0);
    write("alpha.exr", 9, 0.25, 2.0);
    let grad = |target: &str| grad_against(d, target);
    assert_clean_error(
        &grad("huge.exr"),
        &["--target 'huge.exr'", "pixel 5", "1e30"],
    );
    assert_clean_error(&grad("negative.exr"), &["pixel 7", "1e30"]);
    let run = std::fs::read_to_string(d.join("run.toml")).unwrap();
    for (image, needles) in [
        ("huge.exr", ["pixel 5", "1e30"]),
        ("negative.exr", ["pixel 7", "1e30"]),
        ("alpha.exr", ["pixel 9", "alpha of 2"]),
    ] {
        let view = "\n[[view]]\nposition = [0, 0, 12]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 24\nheight = 24\n";
        std::fs::write(
            d.join("r.toml"),
            format!("{run}{view}image = \"{image}\"\n"),
        )
        .unwrap();
        let o = volgrad_in(
            d,
            &["optimize", "r.toml", "--out", &format!("o-{image}"), "-q"],
        );
        assert_clean_error(&o, &[&["view[0].image", image][..], &needles[..]].concat());
    }
}

/// A prior's weight is relative to the images and the box: one too large to be a weight in grid
/// units (its penalty infinite) is refused naming it, not found at the first step.
#[test]
fn a_prior_weight_beyond_f32_in_grid_units_is_refused() {
    // A 12-unit box: u = 1/(0.6 · 12), and the Laplacian's weight W·P/u² ≈ 1.4·W.
    let prior = "[[optimizer.prior]]\nkind = \"laplacian\"\nweight = 3e38\n";
    let run = run_file("0.1", "spp = 1\niterations = 2").replace(
        "bounds = \"truth\"",
        "bounds = { min = [-6, -6, -6], max = [6, 6, 6] }\nvoxel_size = 1.0",
    );
    let dir = fixture(&format!("{run}{prior}"));
    let o = volgrad_in(dir.path(), &["optimize", "run.toml", "-q"]);
    assert_clean_error(&o, &["optimizer.prior[0].weight", "3e38", "too large"]);
}

/// A flag the command would ignore, or a value it would replace by another, is refused: the user
/// asked for something the run would not do.
#[test]
fn flags_that_would_be_ignored_or_replaced_are_refused() {
    let dir = fixture(&run_file("0.1", ""));
    let d = dir.path();
    let render = ["render", "scene.toml", "-o", "t.exr", "--spp", "1", "-q"];
    ok(volgrad_in(d, &render));
    let grad = |extra: &[&str]| {
        let args = ["grad", "scene.toml", "--spp", "1", "-o", "g.vdb", "-q"];
        volgrad_in(d, &[&args[..], extra].concat())
    };
    assert_clean_error(
        &grad(&["--loss", "mean", "--target", "t.exr"]),
        &["--loss mean", "no target"],
    );
    assert_clean_error(&grad(&["--fd", "ones"]), &["--fd", "--estimator fd"]);
    // Each method's own flags with the other: finite differences write no file and take their
    // samples from --fd-spp; the path estimators take no step.
    let fd = |extra: &[&str]| {
        let args = [
            "grad",
            "scene.toml",
            "--estimator",
            "fd",
            "--fd",
            "ones",
            "-q",
        ];
        volgrad_in(d, &[&args[..], extra].concat())
    };
    for extra in [
        &["-o", "g.vdb"][..],
        &["--spp", "4"],
        &["--stats"],
        &["--image-of", "all"],
        &["--suffix-paths", "3"],
    ] {
        assert_clean_error(&fd(extra), &[extra[0], "path estimators", "--fd-spp"]);
    }
    assert_clean_error(&grad(&["--fd-spp", "4"]), &["--fd-spp", "--estimator fd"]);
    assert_clean_error(&grad(&["--repeats", "2"]), &["--repeats", "joint"]);
    assert_clean_error(
        &grad(&["--target-spp", "4"]),
        &["--target-spp", "--target-scene"],
    );
    let check = [
        "gradcheck",
        "scene.toml",
        "--channel",
        "1",
        "--spp",
        "1",
        "-q",
    ];
    assert_clean_error(&volgrad_in(d, &check), &["--channel", "albedo"]);
    // The global majorant has no cells to size.
    let global = [
        &render[..],
        &["--force", "--majorant", "global", "--majorant-cell", "8"],
    ]
    .concat();
    assert_clean_error(
        &volgrad_in(d, &global),
        &["--majorant-cell", "global", "ignored"],
    );
    let scene = std::fs::read_to_string(d.join("scene.toml")).unwrap();
    let file = scene.replace(
        "[render]\n",
        "[render]\nmajorant = \"global\"\nmajorant_cell = 8\n",
    );
    std::fs::write(d.join("global.toml"), file).unwrap();
    let global = ["render", "global.toml", "-o", "g.exr", "--spp", "1", "-q"];
    assert_clean_error(
        &volgrad_in(d, &global),
        &["render.majorant_cell", "global", "ignored"],
    );
    // A finite-difference step below what f32 resolves beside the grid's values differences
    // rounding: a meaningless value that passed or failed a check at random.
    let check = [
        "gradcheck",
        "scene.toml",
        "--eps",
        "1e-40",
        "--spp",
        "1",
        "-q",
    ];
    assert_clean_error(&volgrad_in(d, &check), &["--eps", "f32 resolves"]);
    assert_clean_error(&fd(&["--eps", "1e-45"]), &["--eps"]);
    for thickness in ["0", "1000"] {
        let slab = [
            "make-grid",
            "slab",
            "--size",
            "4",
            "--thickness",
            thickness,
            "-o",
            "s.vdb",
        ];
        assert_clean_error(&volgrad_in(d, &slab), &["--thickness", "1 to --size"]);
    }
    let suite = ["compare", "--suite", "stability", "scene.toml"];
    assert_clean_error(&volgrad_in(d, &suite), &["--suite stability", "scene.toml"]);
    // Counts below what the method needs were raised to it without a word.
    for (args, flag) in [
        (
            vec![
                "grad",
                "scene.toml",
                "--loss",
                "l2",
                "--target-scene",
                "scene.toml",
                "--target-spp",
                "0",
            ],
            "--target-spp",
        ),
        (vec!["compare", "scene.toml", "--repeats", "1"], "--repeats"),
        (vec!["compare", "scene.toml", "--fd-spp", "0"], "--fd-spp"),
        (
            vec!["compare", "--suite", "stability", "--suite-runs", "1"],
            "--suite-runs",
        ),
        (
            vec!["compare", "--suite", "stability", "--suite-spp", "0"],
            "--suite-spp",
        ),
        // 2 × 2³¹ runs wrapped to none (a reference of NaN standard errors).
        (
            vec!["compare", "scene.toml", "--reference-seeds", "2147483648"],
            "--reference-seeds",
        ),
    ] {
        assert_flag_refused(&volgrad_in(d, &args), flag);
    }
    // A flag only the other suite reads is refused, not ignored.
    for (args, flags) in [
        (
            vec![
                "compare",
                "--suite",
                "stability",
                "--budget",
                "1s",
                "--max-spp",
                "8",
            ],
            "--budget, --max-spp",
        ),
        (
            vec!["compare", "scene.toml", "--suite-runs", "4"],
            "--suite-runs",
        ),
    ] {
        assert_clean_error(&volgrad_in(d, &args), &[flags, "belong to the"]);
    }
}

/// A PNG's header declaring 10¹⁰ pixels (a few bytes on disk) is refused with its size named,
/// before a buffer for them is asked for (it was `std::bad_alloc`, or an abort).
#[test]
fn an_image_header_declaring_too_many_pixels_is_refused() {
    let side = 100_000u32.to_be_bytes();
    let header = [&side[..], &side, &[8, 2, 0, 0, 0]].concat(); // 8-bit RGB
    let png = [
        &b"\x89PNG\r\n\x1a\n"[..],
        &common::png_chunk(b"IHDR", &header),
        &common::png_chunk(b"IDAT", &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01]), // an empty zlib stream
        &common::png_chunk(b"IEND", &[]),
    ]
    .concat();
    let dir = fixture(&run_file("0.1", ""));
    let d = dir.path();
    std::fs::write(d.join("bomb.png"), png).unwrap();
    assert_clean_error(
        &grad_against(d, "bomb.png"),
        &["bomb.png", "100000x100000", "2^28"],
    );
}

/// `grad --target-scene` renders its target (256 spp by default, and here a billion) only once
/// every flag has been checked: a parameter the scene has no grid for was refused after it.
#[test]
fn a_bad_flag_is_refused_before_the_target_is_rendered() {
    let dir = fixture(&run_file("0.1", ""));
    let args = [
        "grad",
        "scene.toml",
        "--parameter",
        "albedo",
        "--loss",
        "l2",
        "--target-scene",
        "scene.toml",
        "--target-spp",
        "1000000000",
        "-o",
        "g.vdb",
        "-q",
    ];
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_volgrad"))
        .args(args)
        .current_dir(dir.path())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while child.try_wait().unwrap().is_none() {
        if std::time::Instant::now() > deadline {
            child.kill().unwrap();
            panic!("still rendering the target after 60 s: the flags were not checked first");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    assert_clean_error(&child.wait_with_output().unwrap(), &["albedo"]);
}

/// make-grid refuses what it would otherwise ignore or make unreadable, naming the flag: a slab's
/// thickness on a box, a fog value on a level set, the companion grid's name for the density
/// (every read refuses two grids of one name), angles and sizes no scene can use.
#[test]
fn make_grid_refuses_what_it_would_ignore() {
    let dir = tempfile::tempdir().unwrap();
    for (args, needles) in [
        (
            vec!["box", "--thickness", "4"],
            vec!["--thickness is a slab's", "box"],
        ),
        (
            vec!["sphere", "--class", "levelset", "--value", "5"],
            vec!["--value is a fog volume's"],
        ),
        (
            vec!["fireball", "--name", "temperature"],
            vec!["--name temperature"],
        ),
        (vec!["coloured-smoke", "--name", "Cd"], vec!["--name Cd"]),
        (
            vec!["box", "--rotate-deg", "nan,0,0"],
            vec!["--rotate-deg must be three finite angles"],
        ),
        (
            vec!["box", "--voxel-size", "1e200"],
            vec!["--voxel-size × --size"],
        ),
        (
            vec!["box", "--size", "1024"],
            vec!["--size must be between 1 and 512"],
        ),
    ] {
        let out = volgrad_in(
            dir.path(),
            &[&["make-grid"], &args[..], &["-o", "g.vdb"]].concat(),
        );
        assert_clean_error(&out, &needles);
        assert!(!dir.path().join("g.vdb").exists(), "{args:?}");
    }
}

/// A density grid with no active voxels: render says the medium is empty (and renders the
/// lights), gradcheck has nothing to check (an error, not "all 0 checks" and exit 0). gradcheck's
/// voxel count is bounded like every count a flag gives.
#[test]
fn a_grid_with_no_voxels_is_named() {
    let dir = fixture(&run_file("0.1", ""));
    let d = dir.path();
    let mut grid = read_grid(&d.join("ball.vdb"), &GridSelector::Default).unwrap();
    grid.bricks = volgrad::volume::brickmap::BrickMap::new(vec![], vec![]);
    volgrad::io::vdb::write_grids(&d.join("empty.vdb"), &[&grid], false, false).unwrap();
    let scene = std::fs::read_to_string(d.join("scene.toml")).unwrap();
    std::fs::write(d.join("empty.toml"), scene.replace("ball.vdb", "empty.vdb")).unwrap();
    let out = ok(volgrad_in(
        d,
        &["render", "empty.toml", "--spp", "1", "-o", "e.exr", "-q"],
    ));
    assert!(
        stderr(&out).contains("has no active voxels: the medium is empty"),
        "{}",
        stderr(&out)
    );
    let out = volgrad_in(d, &["gradcheck", "empty.toml", "--fd-spp", "4", "-q"]);
    assert_clean_error(&out, &["nothing to check"]);
    let out = volgrad_in(d, &["gradcheck", "scene.toml", "--voxels", "10001"]);
    assert_flag_refused(&out, "--voxels");
}

/// A target cache that names a file is refused as the run loads ("File exists (os error 17)"
/// came when the first target, rendered, was to be stored).
#[test]
fn a_target_cache_that_is_a_file_is_refused() {
    let dir = fixture(&run_file("0.2", "iterations = 1"));
    std::fs::write(dir.path().join("file"), "mine").unwrap();
    let cached = ["optimize", "run.toml", "--target-cache", "file", "-q"];
    assert_clean_error(
        &volgrad_in(dir.path(), &cached),
        &["target cache 'file' is a file"],
    );
    assert_eq!(
        std::fs::read_to_string(dir.path().join("file")).unwrap(),
        "mine"
    );
}
