//! Flame tomography: `optimize` solving for the emission grid (`unknown.grid = "emission"`) of a
//! medium whose density is known, from views against black (`scenes/inverse/flame.toml`).

mod common;

use std::path::{Path, PathBuf};

use common::{assert_clean_error, ok, volgrad};
use volgrad::io::vdb;

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// The held-out PSNR (column `heldout_psnr`) and volume RMSE of every evaluated row of a log.
fn evaluations(log: &Path) -> Vec<(f64, Option<f64>)> {
    let text = std::fs::read_to_string(log).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let column = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let (psnr, rmse) = (column("heldout_psnr"), column("volume_rmse"));
    lines
        .map(|l| l.split(',').collect::<Vec<_>>())
        .filter(|row| !row[psnr].is_empty())
        .map(|row| (row[psnr].parse().unwrap(), row[rmse].parse().ok()))
        .collect()
}

/// Runs `optimize` on a shipped run file into `out` (with `extra` options) and returns its
/// evaluations.
fn optimize(run: &str, out: &Path, extra: &[&str]) -> Vec<(f64, Option<f64>)> {
    let run = repo(run);
    let mut args = vec![
        "optimize",
        run.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    ok(volgrad(&args));
    evaluations(&out.join("log.csv"))
}

/// The example reconstructs the fireball's emission from 8 views of 32²: the held-out views go
/// from a black start's 13.1 dB to above 30 (37.2 measured), and the volume error falls below 0.4
/// grid units and below half the start's (0.23 measured, from 0.82; the truth's values are 1 to
/// 3). That error is the written emission grid's against the truth, voxel by voxel over the
/// truth's box, as the test recomputes it from `final.vdb` (it once compared the known density
/// instead, and stayed the same within a level: seen). The written grid is the emission's
/// ("temperature"), in the truth's transform. Were the unknown put in the density (or the
/// gradient taken with respect to it), nothing would fit.
#[test]
fn flame_tomography_recovers_the_emission() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("flame");
    let rows = optimize("scenes/inverse/flame.toml", &out, &["--threads", "2"]);
    let (first, last) = (rows[0], rows[rows.len() - 1]);
    assert!(first.0 < 15.0, "the start is black: {first:?}");
    assert!(last.0 > 30.0, "held-out PSNR {:?} → {:?}", first.0, last.0);
    let (start, rmse) = (first.1.unwrap(), last.1.unwrap());
    assert!(
        rmse < 0.4 && rmse < 0.5 * start,
        "volume RMSE {start} → {rmse}"
    );
    let written = vdb::list_grids(&out.join("final.vdb")).unwrap();
    assert_eq!(written[0].name, "temperature");
    let truth = vdb::list_grids(&repo("scenes/analytic/fireball.vdb")).unwrap();
    assert_eq!(written[0].index_to_world, truth[0].index_to_world);

    let read = |path: &Path| {
        let selector = vdb::GridSelector::Name("temperature".into());
        vdb::read_grid(path, &selector).unwrap().bricks
    };
    let (found, truth) = (
        read(&out.join("final.vdb")),
        read(&repo("scenes/analytic/fireball.vdb")),
    );
    let (lo, hi) = truth.active_bounds().unwrap();
    let (mut squares, mut count) = (0.0f64, 0.0f64);
    for x in lo.x..=hi.x {
        for y in lo.y..=hi.y {
            for z in lo.z..=hi.z {
                let v = glam::IVec3::new(x, y, z);
                squares += (found.voxel(v) as f64 - truth.voxel(v) as f64).powi(2);
                count += 1.0;
            }
        }
    }
    let recomputed = (squares / count).sqrt();
    assert!(
        (recomputed - rmse).abs() < 1e-4 * rmse,
        "the log's volume RMSE {rmse} is not final.vdb's against the truth ({recomputed})"
    );
}

/// The same on a real simulation (`scenes/inverse/pyro-flame.toml`: the Mantaflow bake's `flame`
/// grid, its smoke known, an orbit about +z), cut to 60 iterations: the held-out views go from
/// 22.5 dB to above 35 (38.5 measured), and the written grid is the bake's `flame`, in its
/// transform.
#[test]
fn the_pyro_example_fits_its_views() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("pyro");
    let rows = optimize(
        "scenes/inverse/pyro-flame.toml",
        &out,
        &["--iterations", "60"],
    );
    let (first, last) = (rows[0], rows[rows.len() - 1]);
    assert!(first.0 < 25.0 && last.0 > 35.0, "{first:?} → {last:?}");
    let written = vdb::list_grids(&out.join("final.vdb")).unwrap();
    assert_eq!(written[0].name, "flame");
    let truth = vdb::list_grids(&repo("scenes/assets/mantaflow_fire.vdb")).unwrap();
    let flame = truth.iter().find(|g| g.name == "flame").unwrap();
    assert_eq!(written[0].index_to_world, flame.index_to_world);
}

/// An emission unknown needs the scene to say what its values mean, linearly: a scene without
/// emission, with a temperature grid's blackbody, or with a radiance of 0 is refused before any
/// target is rendered.
#[test]
fn an_emission_unknown_needs_a_radiance_emission() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let run = std::fs::read_to_string(repo("scenes/inverse/flame.toml")).unwrap();
    let refused = |scene: &str, needles: &[&str]| {
        let scene_path = repo(scene);
        let text = run
            .replace("\"flame-scene.toml\"", &format!("{:?}", scene_path))
            .replace(
                "\"../analytic/fireball.vdb\"",
                &format!("{:?}", repo("scenes/analytic/fireball.vdb")),
            );
        let path = d.join("run.toml");
        std::fs::write(&path, text).unwrap();
        let out = d.join("out");
        assert_clean_error(
            &volgrad(&[
                "optimize",
                path.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
            ]),
            needles,
        );
        assert!(!out.exists(), "nothing is written for a refused run");
    };
    refused(
        "scenes/inverse/quick-scene.toml",
        &["unknown.grid", "medium.emission"],
    );
    refused("scenes/fire.toml", &["unknown.grid", "blackbody"]);
    // A radiance of 0: the images say nothing of the grid (and its units would divide by 0).
    let dark = std::fs::read_to_string(repo("scenes/inverse/flame-scene.toml"))
        .unwrap()
        .replace("radiance = [1.6, 0.7, 0.25]", "radiance = 0")
        .replace(
            "\"../analytic/fireball.vdb\"",
            &format!("{:?}", repo("scenes/analytic/fireball.vdb")),
        );
    let dark_path = d.join("dark-scene.toml");
    std::fs::write(&dark_path, dark).unwrap();
    refused(
        dark_path.to_str().unwrap(),
        &["unknown.grid", "radiance is 0"],
    );
}

/// An emission unknown started empty (`start = 0`) grows, and only inside its box: its gradient
/// is taken over the unknown's whole domain, not over its current bricks (none, for an empty
/// start: the run once stayed black) and their apron (outside the box at the first level).
#[test]
fn an_empty_emission_start_grows_inside_its_box_only() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let run = std::fs::read_to_string(repo("scenes/inverse/flame.toml"))
        .unwrap()
        .replace(
            "\"flame-scene.toml\"",
            &format!("{:?}", repo("scenes/inverse/flame-scene.toml")),
        )
        .replace(
            "\"../analytic/fireball.vdb\"",
            &format!("{:?}", repo("scenes/analytic/fireball.vdb")),
        )
        .replace("bounds = \"truth\"", "bounds = \"truth\"\nstart = 0")
        .replace("iterations = 150", "iterations = 20");
    std::fs::write(d.join("run.toml"), run).unwrap();
    let out = d.join("out");
    ok(volgrad(&[
        "optimize",
        d.join("run.toml").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "-q",
    ]));
    let rows = evaluations(&out.join("log.csv"));
    let (first, last) = (rows[0].0, rows[rows.len() - 1].0);
    assert!(last > first + 5.0, "held-out PSNR {first} → {last}");
    let selector = vdb::GridSelector::Name("temperature".into());
    let found = vdb::read_grid(&out.join("final.vdb"), &selector).unwrap();
    let truth = vdb::read_grid(&repo("scenes/analytic/fireball.vdb"), &selector).unwrap();
    let (lo, hi) = truth.bricks.active_bounds().unwrap();
    // Whole bricks are stored: every voxel outside the truth's box is 0.
    let (flo, fhi) = found.bricks.active_bounds().expect("the emission grew");
    let mut inside = 0.0f64;
    for x in flo.x..=fhi.x {
        for y in flo.y..=fhi.y {
            for z in flo.z..=fhi.z {
                let v = glam::IVec3::new(x, y, z);
                let value = found.bricks.voxel(v);
                if v.cmpge(lo).all() && v.cmple(hi).all() {
                    inside += f64::from(value);
                } else {
                    assert_eq!(value, 0.0, "voxel {v} outside the box {lo}..{hi}");
                }
            }
        }
    }
    assert!(inside > 0.0);
}
