//! volgrad across MPI ranks (`mpirun -n N`): the same bits at 1, 2 and 3 ranks for `optimize`,
//! `render` and `grad`; a run resumed at 2 ranks from a checkpoint written at 3; SIGUSR1 stopping
//! every rank. Faults are in `cluster_faults.rs`. Needs OpenMPI's `mpirun` (scripts/setup.sh).

mod common;

use std::path::Path;
use std::process::{Output, Stdio};
use std::time::{Duration, Instant};

use common::mpi::{mpirun, ranks, repo, run_file, LIMIT};
use common::{ok, stderr};
use volgrad::io::vdb::{read_grid, GridSelector};

/// Every active voxel's value (index and bits), in the file's order.
fn voxels(path: &Path) -> Vec<([i32; 3], u32)> {
    let grid = read_grid(path, &GridSelector::Index(0)).unwrap();
    let mut out = Vec::new();
    for leaf in grid.bricks.leaves() {
        for (i, v) in leaf.values.iter().enumerate() {
            if leaf.active[i >> 6] & (1 << (i & 63)) != 0 {
                out.push((leaf.origin.to_array().map(|c| c + i as i32), v.to_bits()));
            }
        }
    }
    out
}

fn exr_pixels(path: &Path) -> Vec<[u32; 3]> {
    let image = volgrad::io::images::read_rgb(path).unwrap();
    image
        .pixels
        .iter()
        .map(|c| c.to_array().map(f32::to_bits))
        .collect()
}

/// One run's outputs at 1, 2 and 3 ranks: `final.vdb`, `grad.vdb` and a render's EXR, bit for bit,
/// and the held-out evaluations (`eval_spp = "auto"`, whose rounds every rank decides alone from
/// the same images): the same spp and the same PSNR.
#[test]
fn results_do_not_depend_on_the_number_of_ranks() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let run = run_file("batch = 3\niterations = 6").replace("eval_spp = 64", "eval_spp = \"auto\"");
    std::fs::write(d.join("run.toml"), run).unwrap();
    let scene = repo("scenes/inverse/quick-scene.toml");
    let scene = scene.to_str().unwrap();
    let mut finals = Vec::new();
    for n in 1..=3 {
        let out = format!("o{n}");
        ok(ranks(
            d,
            n,
            &["optimize", "run.toml", "--out", &out, "-q"],
            LIMIT,
        ));
        finals.push(voxels(&d.join(&out).join("final.vdb")));
        let grad = format!("g{n}.vdb");
        ok(ranks(
            d,
            n,
            &["grad", scene, "--spp", "4", "-o", &grad, "-q"],
            LIMIT,
        ));
        finals.push(voxels(&d.join(&grad)));
        let exr = format!("r{n}.exr");
        ok(ranks(
            d,
            n,
            &["render", scene, "--spp", "4", "-o", &exr, "-q"],
            LIMIT,
        ));
    }
    assert!(!finals[0].is_empty() && !finals[1].is_empty());
    for n in 1..3 {
        assert!(finals[2 * n] == finals[0], "final.vdb at {} ranks", n + 1);
        assert!(
            finals[2 * n + 1] == finals[1],
            "grad.vdb at {} ranks",
            n + 1
        );
        let (one, many) = (
            exr_pixels(&d.join("r1.exr")),
            exr_pixels(&d.join(format!("r{}.exr", n + 1))),
        );
        assert!(one == many, "render at {} ranks", n + 1);
    }
    // Only rank 0 writes the log: one header, one row per iteration.
    let log = std::fs::read_to_string(d.join("o3/log.csv")).unwrap();
    assert_eq!(log.lines().count(), 1 + 7, "{log}");
    let evaluations = |n: usize| -> Vec<String> {
        let log = std::fs::read_to_string(d.join(format!("o{n}/log.csv"))).unwrap();
        let header: Vec<&str> = log.lines().next().unwrap().split(',').collect();
        let column = |name: &str| header.iter().position(|c| *c == name).unwrap();
        let (psnr, spp) = (column("heldout_psnr"), column("heldout_spp"));
        (log.lines().skip(1))
            .map(|row| row.split(',').collect::<Vec<_>>())
            .filter(|cells| !cells[psnr].is_empty())
            .map(|cells| format!("{} at {} spp", cells[psnr], cells[spp]))
            .collect()
    };
    assert_eq!(evaluations(1).len(), 3, "{:?}", evaluations(1));
    for n in 2..=3 {
        assert_eq!(
            evaluations(n),
            evaluations(1),
            "held-out evaluations at {n} ranks"
        );
    }
}

/// A target cache filled by 2 ranks (rank 0 writes) serves one process and 3 ranks (rank 0 reads
/// and sends the pixels): every run ends where a run without the cache ends, bit for bit.
#[test]
fn a_target_cache_serves_any_number_of_ranks() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("run.toml"), run_file("batch = 3\niterations = 2")).unwrap();
    let optimize = |n: usize, out: &str, cache: bool| {
        let mut args = vec!["optimize", "run.toml", "--out", out];
        if cache {
            args.extend(["--target-cache", "cache"]);
        }
        ok(ranks(d, n, &args, LIMIT))
    };
    optimize(1, "plain", false);
    optimize(2, "filled", true);
    assert_eq!(std::fs::read_dir(d.join("cache")).unwrap().count(), 10);
    for (n, out) in [(1, "one"), (3, "three")] {
        let run = optimize(n, out, true);
        let err = String::from_utf8_lossy(&run.stderr);
        assert!(err.contains("10 of 10 targets read"), "{err}");
    }
    let plain = voxels(&d.join("plain/final.vdb"));
    for out in ["filled", "one", "three"] {
        assert!(voxels(&d.join(out).join("final.vdb")) == plain, "{out}");
    }
}

/// A run resumed at 2 ranks from the checkpoint a 3-rank run wrote halfway ends where the
/// uninterrupted one-process run ends.
#[test]
fn a_run_resumed_at_another_rank_count_continues_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("run.toml"), run_file("batch = 3\niterations = 8")).unwrap();
    ok(ranks(
        d,
        1,
        &["optimize", "run.toml", "--out", "whole", "-q"],
        LIMIT,
    ));
    ok(ranks(
        d,
        3,
        &["optimize", "run.toml", "--out", "three", "-q"],
        LIMIT,
    ));
    std::fs::create_dir(d.join("half")).unwrap();
    for ext in ["vdb", "state"] {
        let name = format!("checkpoint-0004.{ext}");
        std::fs::copy(d.join("three").join(&name), d.join("half").join(&name)).unwrap();
    }
    ok(ranks(
        d,
        2,
        &["optimize", "run.toml", "--resume", "half", "-q"],
        LIMIT,
    ));
    assert!(
        voxels(&d.join("half/final.vdb")) == voxels(&d.join("whole/final.vdb")),
        "resumed at 2 ranks from 3"
    );
}

/// `grad` on three voxels 30,000 voxels apart along the diagonal: a box whose block bitmap would
/// not fit, so the ranks gather the touched blocks' keys instead. 1 and 3 ranks: the same voxels.
#[test]
fn a_wide_sparse_gradient_is_summed_by_its_keys() {
    use glam::{DVec3, IVec3};
    use volgrad::io::vdb::{self, Grid};
    use volgrad::volume::brickmap::BrickMapBuilder;
    use volgrad::volume::transform::IndexTransform;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut bricks = BrickMapBuilder::new();
    for v in [0, 30_000, 60_000].map(IVec3::splat) {
        bricks.set(v, 1.0, true);
    }
    let grid = Grid {
        transform: IndexTransform::uniform(1.0, DVec3::ZERO),
        bricks: bricks.build(),
        name: "density".into(),
        grid_class: "fog volume".into(),
        saved_as_half: false,
        background: 0.0,
        metadata: Vec::new(),
    };
    vdb::write_grids(&d.join("diagonal.vdb"), &[&grid], false, false).unwrap();
    std::fs::write(
        d.join("diagonal.toml"),
        "[camera]\nposition = [-50, -40, -60]\ntarget = [60000, 60000, 60000]\nfov_deg = 20\nwidth = 32\nheight = 32\n\
         [medium]\nvdb = \"diagonal.vdb\"\ndensity_scale = 0.5\nalbedo = 0.5\n\
         [[light]]\ntype = \"constant\"\nradiance = 0.5\n",
    )
    .unwrap();
    let mut grads = Vec::new();
    for n in [1, 3] {
        let out = format!("g{n}.vdb");
        let args = [
            "grad",
            "diagonal.toml",
            "--spp",
            "1",
            "--loss",
            "mean",
            "-o",
            &out,
            "-q",
        ];
        ok(ranks(d, n, &args, LIMIT));
        grads.push(voxels(&d.join(&out)));
    }
    assert!(!grads[0].is_empty());
    assert!(grads[0] == grads[1], "3 ranks against 1");
}

/// Ends a run of 100,000 iterations if its test fails before it has: SIGTERM to mpirun, which
/// passes it on to the ranks and kills them a second later (left running, they slowed the rest of
/// the suite threefold).
struct EndOnFailure(libc::pid_t);

impl Drop for EndOnFailure {
    fn drop(&mut self) {
        // SAFETY: a plain kill(2) of our own child, not yet waited for.
        unsafe { libc::kill(self.0, libc::SIGTERM) };
    }
}

/// SIGUSR1 to mpirun (which forwards it) stops every rank after the same iteration with a
/// checkpoint, and one message saying how to resume. So does Ctrl-C handed to every rank (as
/// srun's second one is), which says once that it is stopping, and Ctrl-C to mpirun, which hands
/// the ranks SIGTERM and SIGKILL a second later: with an evaluation of seconds (8,192 spp) after
/// every step, the evaluation under way is given up and the checkpoint waits for none (with
/// either, the ranks were killed and left no checkpoint).
#[test]
fn sigusr1_to_mpirun_stops_every_rank_with_a_checkpoint() {
    let run = run_file("batch = 3\niterations = 100000");
    let slow_evaluations = (run.replace("eval_spp = 64", "eval_spp = 8192"))
        .replace("eval_every = 4", "eval_every = 1")
        .replace("checkpoint_every = 4", "checkpoint_every = 100000");
    for (signal, to_ranks, run) in [
        (libc::SIGUSR1, false, &run),
        (libc::SIGINT, true, &run),
        (libc::SIGINT, false, &slow_evaluations),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::write(d.join("run.toml"), run).unwrap();
        let exe = env!("CARGO_BIN_EXE_volgrad");
        let mut child = mpirun(d)
            .args(["-n", "2", exe, "optimize", "run.toml", "--out", "o"])
            .args(["-q", "--threads", "1"])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let ender = EndOnFailure(child.id() as libc::pid_t);
        // Running once the first evaluation's log is written.
        let started = Instant::now();
        while !d.join("o/log.csv").exists() {
            assert!(started.elapsed() < LIMIT, "the run never started");
            std::thread::sleep(Duration::from_millis(100));
        }
        let pid = child.id().to_string();
        let ranks = std::process::Command::new("pgrep")
            .args(["-P", &pid, "-x", "volgrad"])
            .output()
            .unwrap();
        let to: Vec<libc::pid_t> = match to_ranks {
            false => vec![child.id() as libc::pid_t],
            true => (String::from_utf8_lossy(&ranks.stdout).split_whitespace())
                .map(|p| p.parse().unwrap())
                .collect(),
        };
        assert!(!to.is_empty(), "no rank found");
        for p in to {
            // SAFETY: a plain kill(2) of our own child or its children.
            unsafe { libc::kill(p, signal) };
        }
        let deadline = Instant::now() + Duration::from_secs(60);
        while child.try_wait().unwrap().is_none() {
            assert!(Instant::now() < deadline, "the ranks did not stop");
            std::thread::sleep(Duration::from_millis(50));
        }
        let out = child.wait_with_output().unwrap();
        std::mem::forget(ender);
        let err = stderr(&out);
        assert!(!out.status.success(), "{err}");
        assert_eq!(
            err.matches("error: interrupted at iteration").count(),
            1,
            "{err}"
        );
        // Said for Ctrl-C, not for the SIGTERM mpirun turns it into (a batch job's time limit).
        assert_eq!(
            err.matches("stopping: ").count(),
            usize::from(to_ranks),
            "{err}"
        );
        assert!(!err.contains("error (rank"), "{err}");
        let states = std::fs::read_dir(d.join("o"))
            .unwrap()
            .filter(|e| {
                e.as_ref()
                    .unwrap()
                    .path()
                    .extension()
                    .is_some_and(|x| x == "state")
            })
            .count();
        assert!(states >= 1, "{err}");
    }
}

/// Pixel batches split their pixels, not their views, over the ranks: the same `final.vdb` at 1
/// and 3 ranks.
#[test]
fn pixel_batches_do_not_depend_on_the_number_of_ranks() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(
        d.join("run.toml"),
        run_file("batch_pixels = 700\niterations = 5"),
    )
    .unwrap();
    let mut finals = Vec::new();
    for n in [1, 3] {
        let out = format!("o{n}");
        ok(ranks(
            d,
            n,
            &["optimize", "run.toml", "--out", &out, "-q"],
            LIMIT,
        ));
        finals.push(voxels(&d.join(&out).join("final.vdb")));
    }
    assert!(!finals[0].is_empty());
    assert!(finals[0] == finals[1], "3 ranks against 1");
}

/// `render --stats` and `grad --stats` count every rank's work: each pixel is traced as one
/// process traces it, so the paths and lookups per path are those of one process, whatever the
/// number of ranks (rank 0's counters over every rank's paths gave 3.08 → 1.55 → 1.12).
#[test]
fn stats_count_every_rank() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = repo("scenes/inverse/quick-scene.toml");
    let scene = scene.to_str().unwrap();
    // The counting lines of `--stats` (render's paths and lookups, grad's lookups): not times,
    // rates or memory.
    let counts = |o: &Output| -> Vec<String> {
        let text = String::from_utf8_lossy(&o.stdout).into_owned();
        let lines: Vec<String> = (text.lines())
            .filter(|l| l.starts_with("paths ") || l.starts_with("lookups per path"))
            .map(str::to_string)
            .collect();
        assert!(lines.iter().any(|l| l.starts_with("lookups")), "{text}");
        assert!(text.contains("wall time"), "{text}");
        lines
    };
    let mut seen = Vec::new();
    for n in 1..=3 {
        let exr = format!("r{n}.exr");
        let render = ok(ranks(
            d,
            n,
            &["render", scene, "--spp", "4", "-o", &exr, "-q", "--stats"],
            LIMIT,
        ));
        let grad = format!("g{n}.vdb");
        let grad = ok(ranks(
            d,
            n,
            &["grad", scene, "--spp", "2", "-o", &grad, "-q", "--stats"],
            LIMIT,
        ));
        seen.push((counts(&render), counts(&grad)));
    }
    for n in 1..3 {
        assert_eq!(seen[n].0, seen[0].0, "render at {} ranks", n + 1);
        assert_eq!(seen[n].1, seen[0].1, "grad at {} ranks", n + 1);
    }
}
