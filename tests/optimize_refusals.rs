//! Run files that cannot give a result are refused when the run loads, with a message that says
//! why, instead of failing at a checkpoint after minutes of steps or writing settings that do not
//! reproduce the run.

mod common;
mod optimize_common;

use common::{assert_clean_error, ok, volgrad_in};
use optimize_common::*;

/// A held-out view that sees nothing but black (a camera looking away from the ball, under a sun
/// alone, which no camera sees directly) has no PSNR: it made every evaluation −inf and the run
/// fail at its first checkpoint, when the chart of the held-out PSNR found no point to draw.
#[test]
fn a_black_held_out_view_is_refused() {
    let run = run_file("0.2", "iterations = 2");
    let orbit = &run[run.find("[holdouts.orbit]").unwrap()..run.find("[unknown]").unwrap()];
    let away = "[[holdout]]\nposition = [0, 0, 12]\ntarget = [0, 0, 24]\nfov_deg = 40\nwidth = 24\nheight = 24\n\
                light = [{ type = \"directional\", direction = [-0.5, -1.0, -0.3], irradiance = 4.0 }]\n\n";
    let dir = fixture(&run.replace(orbit, away));
    assert_clean_error(
        &volgrad_in(dir.path(), &["optimize", "run.toml", "--out", "out", "-q"]),
        &["holdout[0]", "black everywhere", "PSNR"],
    );
}

/// More upsamplings than the box has voxels: the ball's 8 voxels a side at 1/64 leave the first
/// level no voxel at all. The run exited 0 with an empty result.
#[test]
fn levels_that_leave_the_first_level_no_voxel_are_refused() {
    let run = run_file("0.2", "iterations = 2").replace(
        "start = 0.2",
        "start = 0.2\nlevels = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]",
    );
    let dir = fixture(&run);
    assert_clean_error(
        &volgrad_in(dir.path(), &["optimize", "run.toml", "--out", "out", "-q"]),
        &["unknown.levels", "6 upsamplings", "no voxel", "8 voxels"],
    );
}

/// Views far from a small box: a pixel covers many voxels, and the derived upsamplings went down
/// to a first level of no voxel (settings.toml then noted "inf" paths per first-level voxel).
/// They stop at a first level of 4 voxels along the shortest edge: the ball's 8 allow one.
#[test]
fn derived_levels_leave_the_first_level_voxels() {
    let run = run_file("0.2", "iterations = 2").replace("distance = 12", "distance = 360");
    let dir = fixture(&run);
    ok(volgrad_in(
        dir.path(),
        &[
            "optimize",
            "run.toml",
            "--iterations",
            "0",
            "--out",
            "out",
            "-q",
        ],
    ));
    let text = std::fs::read_to_string(dir.path().join("out/settings.toml")).unwrap();
    let settings: toml::Value = toml::from_str(&text).unwrap();
    let levels = settings["unknown"]["levels"].as_array().unwrap();
    assert_eq!(levels.len(), 1, "{text}");
    assert!(!text.contains("inf"), "{text}");
}

/// Each upsampling keeps what the finer level's lookups read, the box and one voxel around it:
/// the coarse level's own apron (a coarse voxel past the box) stayed in the result at every
/// finer level, never read and never fitted (two levels left density up to 7 voxels past the box).
#[test]
fn upsampled_density_stays_within_a_voxel_of_the_box() {
    use glam::IVec3;
    use volgrad::io::vdb::{read_grid, GridSelector};
    let run = run_file("0.2", "iterations = 12")
        .replace("start = 0.2", "start = 0.2\nlevels = [0.3, 0.6]");
    let dir = fixture(&run);
    ok(volgrad_in(
        dir.path(),
        &["optimize", "run.toml", "--out", "out", "-q"],
    ));
    let truth = read_grid(&dir.path().join("ball.vdb"), &GridSelector::Default).unwrap();
    let (lo, hi) = truth.bricks.active_bounds().unwrap();
    let result = read_grid(&dir.path().join("out/final.vdb"), &GridSelector::Default).unwrap();
    let mut reached = (IVec3::MAX, IVec3::MIN);
    for leaf in result.bricks.leaves() {
        for (i, &v) in leaf.values.iter().enumerate() {
            if v != 0.0 {
                let p = leaf.origin
                    + IVec3::new((i >> 6) as i32, ((i >> 3) & 7) as i32, (i & 7) as i32);
                reached = (reached.0.min(p), reached.1.max(p));
            }
        }
    }
    assert!(reached.0.x <= reached.1.x, "an empty result");
    assert!(
        reached.0.cmpge(lo - 1).all() && reached.1.cmple(hi + 1).all(),
        "density over {reached:?}, the box {lo}..{hi}"
    );
}

/// A voxel size beyond what f32 positions place (1e20 world units) is refused naming the keys;
/// it was taken without a word, and then a panic once transforms were checked.
#[test]
fn a_voxel_beyond_f32s_reach_is_refused() {
    let run = run_file("0.2", "iterations = 2").replace(
        "bounds = \"truth\"",
        "bounds = { min = [-3, -3, -3], max = [3, 3, 3] }\nvoxel_size = 1e20",
    );
    let dir = fixture(&run);
    assert_clean_error(
        &volgrad_in(dir.path(), &["optimize", "run.toml", "--out", "out", "-q"]),
        &[
            "unknown.bounds / unknown.voxel_size",
            "beyond what f32 positions resolve",
        ],
    );
}

/// Settings each valid alone that give the optimiser no step: a `step_optical_depth` whose rate in
/// grid units is 0 (or beyond f32), a prior weight whose pull squared overflows Adam's second
/// moment. Both runs exited 0, having stood still (or flown to the clamp), and their settings.toml
/// did not load again.
#[test]
fn settings_that_leave_no_step_are_refused() {
    for (optimizer, says) in [
        (
            "step_optical_depth = 1e-45",
            &["optimizer.step_optical_depth", "learning rate of 0"][..],
        ),
        (
            "prior = { kind = \"l1\", weight = 1e25 }",
            &["optimizer.prior[0].weight", "too large"][..],
        ),
    ] {
        let run = run_file("0.2", optimizer).replace("lr = 0.1\n", "");
        let dir = fixture(&run);
        assert_clean_error(
            &volgrad_in(dir.path(), &["optimize", "run.toml", "--out", "out", "-q"]),
            says,
        );
    }
}

/// `--force` replaces an earlier run's checkpoints only once the new run has loaded: a run file
/// that fails to load leaves the earlier run whole, still to be resumed. Its checkpoints were
/// gone before the run file was read.
#[test]
fn a_forced_run_that_fails_to_load_leaves_the_earlier_one() {
    let run = run_file("0.2", "spp = 1").replace("checkpoint_every = 50", "checkpoint_every = 2");
    let dir = fixture(&run);
    let d = dir.path();
    ok(volgrad_in(
        d,
        &[
            "optimize",
            "run.toml",
            "--iterations",
            "2",
            "--out",
            "o",
            "-q",
        ],
    ));
    let before: Vec<_> = std::fs::read_dir(d.join("o")).unwrap().collect();
    std::fs::write(d.join("bad.toml"), run.replace("lr = 0.1", "lr = -1")).unwrap();
    assert_clean_error(
        &volgrad_in(d, &["optimize", "bad.toml", "--out", "o", "--force", "-q"]),
        &["lr must be a positive number"],
    );
    assert_eq!(
        std::fs::read_dir(d.join("o")).unwrap().count(),
        before.len()
    );
    assert!(d.join("o/checkpoint-0002.state").is_file());
}

/// A run resumed past the stop it is given has nothing to do, whether the stop is a count of
/// iterations or a replayed schedule shorter than the checkpoint's iteration (which was accepted
/// and wrote the checkpoint as final.vdb).
#[test]
fn a_schedule_shorter_than_the_resumed_run_is_refused() {
    let run = run_file("0.2", "spp = 1").replace("checkpoint_every = 50", "checkpoint_every = 2");
    let dir = fixture(&run);
    let d = dir.path();
    for (iterations, out) in [("4", "long"), ("2", "short")] {
        ok(volgrad_in(
            d,
            &[
                "optimize",
                "run.toml",
                "--iterations",
                iterations,
                "--out",
                out,
                "-q",
            ],
        ));
    }
    let args = [
        "optimize",
        "run.toml",
        "--resume",
        "long",
        "--schedule-from",
        "short/log.csv",
    ];
    assert_clean_error(
        &volgrad_in(d, &[&args[..], &["-q"]].concat()),
        &[
            "at iteration 4",
            "past the 2 steps --schedule-from replays",
            "nothing to do",
        ],
    );
}

/// Targets whose squares the optimiser cannot hold (lights of 10¹⁰: P near 10¹⁹) are refused as
/// the run loads, naming the brightest pixel. They made a run's priors' weights infinite (a
/// message about a weight the file never set), or its held-out PSNR, and then its chart, NaN.
#[test]
fn targets_too_bright_for_the_optimiser_are_refused() {
    let dir = fixture(&run_file("0.2", "iterations = 1"));
    let scene = std::fs::read_to_string(dir.path().join("scene.toml")).unwrap();
    let bright = scene
        .replace("radiance = [0.03, 0.04, 0.06]", "radiance = 1e10")
        .replace("irradiance = 4.0", "irradiance = 1e10");
    assert_ne!(bright, scene);
    std::fs::write(dir.path().join("scene.toml"), bright).unwrap();
    assert_clean_error(
        &volgrad_in(dir.path(), &["optimize", "run.toml", "--out", "out", "-q"]),
        &[
            "mean squared value",
            "brightest pixel",
            "training view",
            "scale the scene's lights",
        ],
    );
    assert!(!dir.path().join("out").exists());
}

/// `level_lr` scales the rate at each upsampling: with levels left out and derived as none (views
/// whose pixel is about the voxel), it would be ignored without a word, as `unknown.levels = []`
/// refuses it.
#[test]
fn a_level_key_is_refused_when_the_derived_levels_are_none() {
    let run = run_file("0.2", "iterations = 2\nlevel_lr = 0.7");
    let dir = fixture(&run);
    assert_clean_error(
        &volgrad_in(dir.path(), &["optimize", "run.toml", "--out", "out", "-q"]),
        &[
            "optimizer.level_lr has no effect here",
            "levels derived from the views",
        ],
    );
}
