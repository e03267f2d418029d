//! The compare machinery on tiny in-memory scenes: the reference (built, checked against finite
//! differences, saved and read back), equal-time sweeps, the CSV, the charts, and the stability
//! suite. Fixed seeds throughout; the whole file runs in well under a minute in release.

mod common;

use std::time::Duration;

use common::*;
use volgrad::compare::{self, Reference, ReferenceOptions, Row, StabilityOptions, SweepOptions};
use volgrad::gradient::adjoint::Estimator;
use volgrad::gradient::fd::FdOptions;
use volgrad::gradient::loss::Loss;
use volgrad::render::scene::Scene;
use volgrad::volume::medium::Filter;

const N: i32 = 6;

/// The shared lumpy block with empty voxels, nearest lookups (so σt = 0 there).
fn scene() -> Scene {
    lumpy_block_scene(Filter::Nearest, true, 0.9)
}

fn reference(scene: &Scene) -> Reference {
    reference_at(scene, 256)
}

fn reference_at(scene: &Scene, spp: u32) -> Reference {
    compare::build_reference(
        scene,
        &ReferenceOptions {
            spp,
            seeds: 6,
            seed: 1,
            max_depth: 16,
            progress: false,
        },
    )
}

fn sweep_options(budget_ms: u64, max_spp: u32) -> SweepOptions {
    SweepOptions {
        budget: Duration::from_millis(budget_ms),
        max_spp,
        seed: 1,
        max_depth: 16,
        progress: false,
    }
}

fn rows_of<'a>(rows: &'a [Row], method: &str) -> Vec<&'a Row> {
    rows.iter().filter(|r| r.method == method).collect()
}

#[test]
fn reference_agrees_with_fd_and_survives_a_vdb_round_trip() {
    let scene = scene();
    let r = reference(&scene);
    assert_eq!(r.runs, 12);
    assert!(r.sum_se > 0.0 && r.sum_se.is_finite());
    // Standard errors exist wherever the mean does, and their squares fall as 1/spp: a quarter
    // of the samples gives four times the variance (per-voxel gradients on an 8×8 image are
    // noisy, so the reference is judged by how its noise scales, not by its size).
    let variance = |r: &Reference| {
        let (mut n, mut se2) = (0, 0.0);
        for (v, _) in r.mean.voxels().filter(|(_, m)| *m != 0.0) {
            let se = r.stderr.get(v);
            assert!(se.is_finite() && se >= 0.0);
            n += 1;
            se2 += se * se;
        }
        assert!(n > 100, "the reference reached only {n} voxels");
        se2
    };
    let ratio = variance(&reference_at(&scene, 64)) / variance(&r);
    assert!(
        (2.5..6.5).contains(&ratio),
        "variance at 64 spp / at 256 spp = {ratio}, not about 4"
    );

    let fd = FdOptions {
        loss: Loss::Mean,
        eps: 0.15,
        spp: 2048,
        repeats: 4,
        seed: 1,
        max_depth: 16,
    };
    let checks = compare::check_reference(&scene, &r, &fd, 2).unwrap();
    assert_eq!(checks.len(), 3);
    for c in &checks {
        eprintln!("{}: z = {:.2} ({c:?})", c.name, c.z());
        assert!(c.z().abs() < 4.0, "{}: z = {:.2} ({c:?})", c.name, c.z());
    }
    // ⟨g, 1⟩ is resolved enough that the check could have failed: the estimate doubled or halved
    // would be more than 4 standard errors from the finite difference.
    let total = checks.last().unwrap();
    for wrong in [2.0, 0.5] {
        let off = (wrong * total.estimate - total.fd.value).abs();
        let se = total.estimate_se.hypot(total.fd.std_err);
        assert!(off > 4.0 * se, "×{wrong}: {off} is within 4 × {se}");
    }

    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("reference.vdb");
    compare::save_reference(&file, &scene, &r, false).unwrap();
    assert!(
        compare::save_reference(&file, &scene, &r, false).is_err(),
        "overwrote without being asked"
    );
    let back = compare::load_reference(&file, &scene).unwrap();
    assert_eq!((back.runs, back.spp_per_run), (12, 256));
    // Its seeds are recorded, so that it can be built again: 12 consecutive ones from the
    // study's seed (1) plus the offset that keeps them apart from the estimates' seeds.
    let seeds: Vec<u64> = (1 + (1 << 20)..).take(12).collect();
    let listed: Vec<u64> = back.seeds.split(',').map(|s| s.parse().unwrap()).collect();
    assert_eq!(listed, seeds);
    assert!((back.sum_se - r.sum_se).abs() <= 1e-9 * r.sum_se);
    for (v, m) in r.mean.voxels() {
        assert!((back.mean.get(v) - m).abs() <= 1e-6 * m.abs().max(1e-9));
        let se = r.stderr.get(v);
        assert!((back.stderr.get(v) - se).abs() <= 1e-6 * se.max(1e-12));
    }
    // A reference for another grid is refused.
    let mut other = scene.clone();
    other.medium.transform = centred(N, 2.0);
    assert!(compare::load_reference(&file, &other).is_err());
    // So is one of another computation on the same grid, naming what differs.
    let mut denser = scene.clone();
    denser.medium.density_scale *= 2.0;
    let e = compare::load_reference(&file, &denser)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("volgrad_scene_fingerprint"), "{e}");
    let mut deeper = scene.clone();
    deeper.settings.max_depth += 1;
    let e = compare::load_reference(&file, &deeper)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("volgrad_max_depth is '16'"), "{e}");
}

#[test]
fn sweeps_write_a_row_per_run_and_valid_charts() {
    let scene = scene();
    let r = reference(&scene);
    let estimators = [Estimator::Joint, Estimator::Drt, Estimator::Naive];
    let rows = compare::gradient_sweeps(&scene, &estimators, &r, &sweep_options(400, 32));
    for name in ["joint", "drt", "naive"] {
        let runs = rows_of(&rows, name);
        assert!(runs.len() >= 3, "{name}: only {} runs", runs.len());
        for (i, run) in runs.iter().enumerate() {
            assert_eq!(run.spp, 1 << i, "{name}: spp doubles from 1");
            assert!(run.seconds > 0.0);
            assert!(run.rel_rmse.is_finite() && run.rel_rmse_raw.is_finite());
            assert!(run.cosine.is_finite() && run.cosine <= 1.0 + 1e-9);
            assert!(run.empty_rmse.is_finite(), "the scene has empty voxels");
        }
        // Spent time stays within the budget (plus one run's overshoot at most).
        let spent: f64 = runs.iter().map(|r| r.seconds).sum();
        assert!(spent < 1.2, "{name} spent {spent} s of a 0.4 s budget");
    }
    // A sweep ends at the largest spp asked for, not at the next power of two past it.
    let capped =
        compare::gradient_sweeps(&scene, &[Estimator::Joint], &r, &sweep_options(60_000, 6));
    assert_eq!(
        capped.iter().map(|r| r.spp).collect::<Vec<_>>(),
        [1, 2, 4, 6]
    );
    let (joint, naive) = (rows_of(&rows, "joint"), rows_of(&rows, "naive"));
    let (first, last) = (joint.first().unwrap(), joint.last().unwrap());
    assert!(
        last.rel_rmse < 0.8 * first.rel_rmse,
        "joint's error does not fall with spp: {} → {}",
        first.rel_rmse,
        last.rel_rmse
    );
    assert!(last.cosine > first.cosine);
    // Naive is biased in empty voxels: more spp do not bring its error there down to joint's.
    let naive_last = naive.last().unwrap();
    assert!(
        naive_last.empty_rmse > 3.0 * last.empty_rmse,
        "naive's empty-voxel RMSE {} vs joint's {}",
        naive_last.empty_rmse,
        last.empty_rmse
    );

    let csv = compare::csv(&rows);
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(
        lines[0],
        "estimator,spp,seconds,rel_rmse,empty_rmse,cosine,bias,bias_se,rel_rmse_raw"
    );
    assert_eq!(lines.len(), rows.len() + 1);
    for line in &lines[1..] {
        assert_eq!(line.split(',').count(), 9, "{line}");
    }
    assert_eq!(
        lines.iter().filter(|l| l.starts_with("drt,")).count(),
        rows_of(&rows, "drt").len()
    );

    let dir = tempfile::tempdir().unwrap();
    let chart = compare::chart(&rows, "tiny: gradient error", "relative RMSE");
    compare::write_chart(dir.path(), "gradient-error", &chart).unwrap();
    let png = image::open(dir.path().join("gradient-error.png"))
        .expect("a PNG the image crate decodes")
        .to_rgb8();
    assert_eq!(png.dimensions(), (820, 520));
    // The first line's colour (Okabe–Ito blue) is drawn: lines are there, not only axes.
    let blue = png.pixels().filter(|p| p.0 == [0, 114, 178]).count();
    assert!(blue > 50, "{blue} pixels of the first series' colour");
    let svg = std::fs::read_to_string(dir.path().join("gradient-error.svg")).unwrap();
    let doc = roxmltree::Document::parse(&svg).expect("well-formed SVG");
    // Axes and tick marks are polylines too: a series' line is the polyline in its colour
    // (Okabe–Ito, in the order the estimators first appear), through one point per run.
    for (colour, name) in [
        ("#0072B2", "joint"),
        ("#D55E00", "drt"),
        ("#009E73", "naive"),
    ] {
        let lines: Vec<_> = doc
            .descendants()
            .filter(|n| n.has_tag_name("polyline") && n.attribute("stroke") == Some(colour))
            .collect();
        assert_eq!(lines.len(), 1, "one {colour} polyline for {name}");
        let points = lines[0].attribute("points").unwrap().split_whitespace();
        assert_eq!(points.count(), rows_of(&rows, name).len(), "{name}");
    }
    let texts: Vec<&str> = doc
        .descendants()
        .filter(|n| n.has_tag_name("text"))
        .filter_map(|n| n.text())
        .map(str::trim)
        .collect();
    for label in ["joint", "drt", "naive", "wall time (s)", "relative RMSE"] {
        assert!(texts.contains(&label), "the SVG does not label {label}");
    }

    let summary = compare::summary(
        &rows,
        &["joint", "drt", "naive"],
        "drt",
        "joint",
        "Gradient",
    );
    assert!(
        summary.contains("joint reaches drt's final error"),
        "{summary}"
    );
    assert!(
        summary.lines().any(|l| l.starts_with("| naive ")),
        "{summary}"
    );
}

#[test]
fn render_sweeps_compare_the_majorants() {
    let scene = scene();
    let r = compare::build_image_reference(&scene, 256, 4, 1, 16, false);
    assert!(r.noise_mse > 0.0 && r.noise_mse.is_finite());
    let rows = compare::render_sweeps(&scene, &r, &sweep_options(150, 64));
    for name in [compare::RENDER_GRID, compare::RENDER_GLOBAL] {
        let runs = rows_of(&rows, name);
        assert!(runs.len() >= 3, "{name}: {} runs", runs.len());
        let (first, last) = (runs.first().unwrap(), runs.last().unwrap());
        assert!(
            last.rel_rmse_raw < 0.7 * first.rel_rmse_raw,
            "{name}: image error does not fall: {} → {}",
            first.rel_rmse_raw,
            last.rel_rmse_raw
        );
        assert!(
            last.cosine.is_nan(),
            "gradient columns are empty for renders"
        );
    }
    // The method names have a comma: quoted, so that every line has the header's 9 fields.
    let csv = compare::csv(&rows);
    assert!(csv.contains(&format!("\"{}\",1,", compare::RENDER_GLOBAL)));
}

#[test]
fn stability_suite_is_finite_and_flags_naive_in_empty_voxels() {
    let scenes: Vec<_> = compare::stability_scenes()
        .into_iter()
        .filter(|s| ["empty-voxels", "dense", "rotated-anisotropic"].contains(&s.name))
        .collect();
    assert_eq!(scenes.len(), 3);
    let options = StabilityOptions {
        runs: 6,
        spp: 32,
        fd_spp: 4096,
        fd_repeats: 4,
        seed: 1,
        max_depth: 16,
        progress: false,
    };
    let estimators = [Estimator::Joint, Estimator::Naive];
    let rows = compare::stability(&scenes, &estimators, &options).unwrap();
    // Two checks on the scene with empty voxels, one on the others, per estimator.
    assert_eq!(rows.len(), 2 * (2 + 1 + 1));
    for r in &rows {
        assert_eq!(r.non_finite, 0, "{r:?}");
        assert!(r.estimate.is_finite() && r.estimate_se.is_finite() && r.fd.value.is_finite());
    }
    let find = |estimator: &str, check: &str| {
        rows.iter()
            .find(|r| r.scene == "empty-voxels" && r.estimator == estimator && r.check == check)
            .unwrap()
    };
    let naive = find("naive", "empty voxels");
    assert!(!naive.unbiased() && naive.expected_failure, "{naive:?}");
    assert!(naive.z() < -6.0, "naive is biased low: z = {}", naive.z());
    let joint = find("joint", "empty voxels");
    eprintln!("{joint:?}");
    assert!(joint.unbiased() && !joint.weak(), "{joint:?}");
    for r in rows.iter().filter(|r| r.estimator == "joint") {
        assert!(r.unbiased(), "joint on {}: z = {:.2}", r.scene, r.z());
    }
    let table = compare::stability_markdown(&scenes, &rows, &options);
    assert!(table.contains("biased (expected)"));
    assert!(!table.contains("**BIASED**"), "{table}");
    assert_eq!(
        compare::stability_csv(&rows).lines().count(),
        rows.len() + 1
    );
}

/// The command line refuses bad input before any work, with a message and exit status 1 or 2.
#[test]
fn command_line_refuses_bad_input_without_panicking() {
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/box.toml");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("runs.csv"), "mine").unwrap();
    let run = |args: &[&str]| {
        let o = volgrad(&[&["compare"], args].concat());
        (o.status.code(), stderr(&o))
    };
    let out_arg = out.to_str().unwrap();
    let (code, err) = run(&[scene, "--out", out_arg, "--budget", "1s"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("runs.csv") && err.contains("--force"), "{err}");
    assert_eq!(
        std::fs::read_to_string(out.join("runs.csv")).unwrap(),
        "mine"
    );

    // No time at all: each estimator's run would be one pass, reported "at 0.00 s".
    let (code, err) = run(&[scene, "--budget", "0s"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("--budget must be above 0"), "{err}");

    let (code, err) = run(&[scene, "--budget", "5x"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("unknown unit"), "{err}");

    let missing = dir.path().join("missing.vdb");
    let fresh = dir.path().join("fresh");
    let (code, err) = run(&[
        scene,
        "--reference",
        missing.to_str().unwrap(),
        "--out",
        fresh.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("missing.vdb"), "{err}");
    assert!(!err.contains("panicked"), "{err}");

    let (code, err) = run(&[]);
    assert_eq!(code, Some(2), "{err}");
}

/// ⟨g, 1⟩'s finite-difference step is small enough that its stencil's bias does not refuse a
/// right reference where the response curves most: one dense voxel in empty space, whose ⟨g, 1⟩
/// a step of one optical depth across the domain read 8 % low (`volgrad compare
/// scenes/single-voxel.toml` stopped at |z| = 14, the reference agreeing with gradcheck).
#[test]
fn the_sum_check_accepts_a_right_reference_on_a_single_dense_voxel() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/single-voxel.toml");
    let mut scene = Scene::load(&path).unwrap();
    let (position, target) = (glam::Vec3::new(1.0, 2.0, 10.0), glam::Vec3::ZERO);
    scene.camera =
        volgrad::render::camera::Camera::new(position, target, glam::Vec3::Y, 40.0, 32, 32);
    let r = reference_at(&scene, 64);
    let fd = FdOptions {
        loss: Loss::Mean,
        eps: 0.0,
        spp: 1024,
        repeats: 8,
        seed: 1,
        max_depth: scene.settings.max_depth,
    };
    let checks = compare::check_reference(&scene, &r, &fd, 0).unwrap();
    let total = checks.last().unwrap();
    eprintln!("{}: z = {:.2} ({total:?})", total.name, total.z());
    assert!(total.z().abs() < 4.0, "z = {:.2}", total.z());
    let bias = total.fd.value / total.estimate - 1.0;
    assert!(
        bias.abs() < 0.03,
        "the stencil's ⟨g, 1⟩ is {:.1} % off",
        100.0 * bias
    );
}
