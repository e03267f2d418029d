//! Faults under MPI: what one rank meets and the others do not, and what every rank refuses
//! alike (bad flags, a command line that does not parse), ends every rank with one message and
//! no rank left waiting; ranks given different work are refused. Needs OpenMPI's `mpirun`.

mod common;

use std::process::Command;
use std::time::{Duration, Instant};

use common::mpi::{mpirun, ranks, run_file, wait, LIMIT};
use common::{ok, stderr};

/// The same command on every rank, but rank 1's folder lacks the target image rank 0's has (files
/// copied to one machine and not another; `mpirun -n 1 -wdir a … : -n 1 -wdir b …`): both ranks
/// end within seconds, non-zero, with the one error printed once.
#[test]
fn a_file_one_rank_cannot_read_ends_every_rank_with_one_error() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let image = "[[view]]\nposition = [0, 0, 12]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 32\nheight = 32\nimage = \"view.exr\"\n";
    // The [[view]] table goes before [views.orbit], whose keys would otherwise take it in.
    let run =
        run_file("iterations = 2").replacen("[views.orbit]", &format!("{image}\n[views.orbit]"), 1);
    for folder in ["a", "b"] {
        std::fs::create_dir(d.join(folder)).unwrap();
        std::fs::write(d.join(folder).join("run.toml"), &run).unwrap();
    }
    exr::prelude::write_rgb_file(d.join("a/view.exr"), 32, 32, |_, _| {
        (0.1f32, 0.1f32, 0.1f32)
    })
    .unwrap();
    let exe = env!("CARGO_BIN_EXE_volgrad");
    let app = |folder| {
        [
            "-n",
            "1",
            "-wdir",
            folder,
            exe,
            "optimize",
            "run.toml",
            "--out",
            "o",
            "-q",
            "--threads",
            "1",
        ]
    };
    let mut command = mpirun(d);
    command.args(app("a")).arg(":").args(app("b"));
    let started = Instant::now();
    let out = wait(command, Duration::from_secs(60));
    let err = stderr(&out);
    assert!(!out.status.success(), "{err}");
    assert!(
        started.elapsed() < Duration::from_secs(30),
        "took {:?}",
        started.elapsed()
    );
    assert_eq!(err.matches("error: ").count(), 1, "one message: {err}");
    assert!(
        err.contains("error: rank 1: ") && err.contains("view.exr"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    // The run file itself missing in rank 1's folder: named, not called a difference.
    std::fs::remove_file(d.join("b/run.toml")).unwrap();
    let mut command = mpirun(d);
    command.args(app("a")).arg(":").args(app("b"));
    let err = stderr(&wait(command, Duration::from_secs(60)));
    assert_eq!(err.matches("error: ").count(), 1, "one message: {err}");
    assert!(
        err.contains("rank 1: cannot read run file 'run.toml'"),
        "{err}"
    );
}

/// A run file or a flag every rank refuses: one message, every rank non-zero.
#[test]
fn a_bad_run_file_is_reported_once() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(
        d.join("run.toml"),
        run_file("batch = 3\nbatch_pixels = 100"),
    )
    .unwrap();
    // A bad run file, and flags every rank refuses before it reads anything.
    for (args, needle) in [
        (vec!["optimize", "run.toml", "-q"], "batch_pixels"),
        (
            vec!["optimize", "run.toml", "--threads", "100000"],
            "--threads",
        ),
        (vec!["grad", "unread.toml", "--fd", "ones", "-q"], "--fd"),
    ] {
        let out = ranks(d, 3, &args, Duration::from_secs(60));
        let err = stderr(&out);
        assert!(!out.status.success(), "{err}");
        assert_eq!(err.matches("error").count(), 1, "one message: {err}");
        assert!(err.contains(needle), "{err}");
    }
}

/// Rank 0 cannot write (`--out` names a file, not a folder): every rank ends, non-zero, with the
/// one message; no rank waits for the others.
#[test]
fn a_write_rank_0_cannot_make_ends_every_rank_with_one_error() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("run.toml"), run_file("batch = 3\niterations = 3")).unwrap();
    std::fs::write(d.join("taken"), "a file where the output folder should go").unwrap();
    let args = ["optimize", "run.toml", "--out", "taken", "--force", "-q"];
    let out = ranks(d, 2, &args, Duration::from_secs(60));
    let err = stderr(&out);
    assert!(!out.status.success(), "{err}");
    assert_eq!(err.matches("error: ").count(), 1, "one message: {err}");
    assert!(err.contains("output directory"), "{err}");
    assert!(!err.contains("error (rank"), "{err}");
}

/// Several processes that a launcher started but that cannot talk to each other (`srun
/// --mpi=none`, or PMI's variables left in the environment without a launcher) would each run
/// the whole job on the same outputs: each refuses before touching anything, and the first
/// (by the launcher's rank) says why, once for the job.
#[test]
fn processes_that_cannot_reach_each_other_refuse_to_run_as_copies() {
    let dir = tempfile::tempdir().unwrap();
    for (env, says_why) in [
        (
            &[("SLURM_STEP_NUM_TASKS", "3"), ("SLURM_PROCID", "0")][..],
            true,
        ),
        (
            &[("SLURM_STEP_NUM_TASKS", "3"), ("SLURM_PROCID", "1")][..],
            false,
        ),
        (&[("PMI_SIZE", "2"), ("PMI_RANK", "0")][..], true),
    ] {
        let mut command = Command::new(env!("CARGO_BIN_EXE_volgrad"));
        command
            .current_dir(dir.path())
            .args(["make-grid", "box", "-o", "box.vdb"])
            .envs(env.iter().copied());
        let out = wait(command, LIMIT);
        match says_why {
            true => common::assert_clean_error(
                &out,
                &["the launcher started", "MPI sees only this one"],
            ),
            false => assert!(
                !out.status.success() && stderr(&out).is_empty(),
                "{env:?}: {}",
                stderr(&out)
            ),
        }
        assert!(!dir.path().join("box.vdb").exists(), "{env:?}");
    }
    // One task of one is a plain run.
    let mut command = Command::new(env!("CARGO_BIN_EXE_volgrad"));
    command
        .current_dir(dir.path())
        .args(["make-grid", "box", "-o", "box.vdb"])
        .env("SLURM_STEP_NUM_TASKS", "1");
    ok(wait(command, LIMIT));
}

/// Commands that do not share work across ranks are refused under mpirun, once, on every rank:
/// each rank would otherwise do the whole work on the same files and print its own errors.
#[test]
fn one_process_commands_are_refused_once_under_mpirun() {
    let dir = tempfile::tempdir().unwrap();
    let mut command = mpirun(dir.path());
    command
        .args(["-n", "2", env!("CARGO_BIN_EXE_volgrad")])
        .args(["make-grid", "box", "-o", "box.vdb"]);
    let out = wait(command, LIMIT);
    let err = stderr(&out);
    assert!(!dir.path().join("box.vdb").exists());
    assert!(!out.status.success(), "{err}");
    assert_eq!(err.matches("error").count(), 1, "one message: {err}");
    assert!(err.contains("only render, grad and optimize"), "{err}");
}

/// Flags every rank refuses alike after the job has started (checked against the scene, or after
/// a first collective), and a command line that does not parse: one message from rank 0, each
/// rank non-zero, and no MPI_Abort (whose banner, and each rank's own copy of the message, said
/// as much as the error three times over).
#[test]
fn flags_every_rank_refuses_are_reported_once_without_an_abort() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("run.toml"), run_file("iterations = 2")).unwrap();
    let scene = common::mpi::repo("scenes/inverse/quick-scene.toml");
    let scene = scene.to_str().unwrap();
    for (args, needle) in [
        (
            vec!["render", scene, "-o", "x.png"],
            "--output must end in .exr",
        ),
        (
            vec!["render", scene, "--spp", "0"],
            "--spp must be at least 1",
        ),
        (
            vec!["grad", scene, "--parameter", "emission"],
            "no emission",
        ),
        (
            vec!["optimize", "run.toml", "--budget", "0s"],
            "--budget must be above 0",
        ),
        (vec!["render", scene, "--bogus"], "unexpected argument"),
    ] {
        let out = ranks(d, 2, &args, LIMIT);
        let err = stderr(&out);
        assert!(!out.status.success(), "{args:?}: {err}");
        assert_eq!(
            err.matches("error").count(),
            1,
            "{args:?}, one message: {err}"
        );
        assert!(err.contains(needle), "{args:?}: {err}");
        assert!(!err.contains("MPI_ABORT"), "{args:?}: {err}");
    }
}

/// Ranks given other flags (an MPMD launch), or the same command over files that differ between
/// machines (here: each rank in a folder of its own, one scene 8 pixels wider), would add their
/// shares into one wrong image or stop in a collective of mismatched sizes: refused, once.
#[test]
fn ranks_given_different_work_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let sphere = common::mpi::repo("scenes/analytic/sphere.vdb");
    let scene = std::fs::read_to_string(common::mpi::repo("scenes/inverse/quick-scene.toml"))
        .unwrap()
        .replace("\"../analytic/sphere.vdb\"", &format!("{sphere:?}"));
    let wider = scene.replacen("width    = 64", "width    = 72", 1);
    assert_ne!(wider, scene);
    for (folder, text) in [("a", scene), ("b", wider)] {
        std::fs::create_dir(d.join(folder)).unwrap();
        std::fs::write(d.join(folder).join("s.toml"), text).unwrap();
    }
    let exe = env!("CARGO_BIN_EXE_volgrad");
    let app = |folder: &str, spp: &str| -> Vec<String> {
        let args = [
            "-n", "1", "-wdir", folder, exe, "render", "s.toml", "-q", "--spp", spp,
        ];
        args.iter().map(|a| a.to_string()).collect()
    };
    for (first, second) in [
        (app("a", "2"), app("a", "3")),
        (app("a", "2"), app("b", "2")),
    ] {
        let mut command = mpirun(d);
        command.args(&first).arg(":").args(&second);
        let out = wait(command, LIMIT);
        let err = stderr(&out);
        assert!(!out.status.success(), "{err}");
        assert_eq!(err.matches("error").count(), 1, "one message: {err}");
        assert!(
            err.contains("rank 1 was started with other arguments, or reads other files"),
            "{err}"
        );
        assert!(!d.join("a/s.exr").exists(), "{err}");
    }
}

/// `mpirun -n 1 -wdir a volgrad ARGS : -n 1 -wdir b volgrad ARGS`, each rank on one thread.
fn in_folders(d: &std::path::Path, args: &[&str]) -> std::process::Output {
    let exe = env!("CARGO_BIN_EXE_volgrad");
    let app = |folder: &'static str| {
        let mut all = vec!["-n", "1", "-wdir", folder, exe];
        all.extend(args);
        all.extend(["-q", "--threads", "1"]);
        all
    };
    let mut command = mpirun(d);
    command.args(app("a")).arg(":").args(app("b"));
    wait(command, Duration::from_secs(90))
}

fn refused_as_other_files(out: &std::process::Output) {
    let err = stderr(out);
    assert!(!out.status.success(), "{err}");
    assert_eq!(err.matches("error").count(), 1, "one message: {err}");
    assert!(
        err.contains("rank 1 was started with other arguments, or reads other files"),
        "{err}"
    );
}

/// Inputs that differ between machines are named before any check of their content, each by its
/// place in the run: here rank
/// 1's start holds a value no scene renders, which it would refuse alone while rank 0 went on to
/// render the targets with it (a rank left in a collective the other never enters).
#[test]
fn inputs_that_differ_are_refused_before_their_content_is_checked() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let run = run_file("iterations = 2").replace("start = 0.0", "start = \"start.vdb\"");
    let sphere = common::mpi::repo("scenes/analytic/sphere.vdb");
    let mut grid =
        volgrad::io::vdb::read_grid(&sphere, &volgrad::io::vdb::GridSelector::Default).unwrap();
    for (folder, scale) in [("a", 1.0f32), ("b", 1e36)] {
        std::fs::create_dir(d.join(folder)).unwrap();
        std::fs::write(d.join(folder).join("run.toml"), &run).unwrap();
        let leaves = (grid.bricks.leaves().iter())
            .map(|leaf| volgrad::volume::brickmap::Leaf {
                values: leaf.values.map(|v| v * scale),
                ..leaf.clone()
            })
            .collect();
        let start = volgrad::volume::brickmap::BrickMap::new(leaves, vec![]);
        let original = std::mem::replace(&mut grid.bricks, start);
        volgrad::io::vdb::write_grids(&d.join(folder).join("start.vdb"), &[&grid], false, false)
            .unwrap();
        grid.bricks = original;
    }
    let out = in_folders(d, &["optimize", "run.toml", "--out", "o"]);
    refused_as_other_files(&out);
    // The message names the input to copy again.
    let err = stderr(&out);
    assert!(err.contains("(the grid of unknown.start differs)"), "{err}");
}

/// A resumed run's ranks each find their own latest checkpoint: a folder one machine sees
/// older (a network file system's cache) would start them at different iterations. Here rank
/// 1's folder holds a later one.
#[test]
fn checkpoints_that_differ_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for (folder, iterations) in [("a", "4"), ("b", "8")] {
        std::fs::create_dir(d.join(folder)).unwrap();
        std::fs::write(d.join(folder).join("run.toml"), run_file("")).unwrap();
        let args = [
            "optimize",
            "run.toml",
            "--iterations",
            iterations,
            "--out",
            "o",
            "-q",
        ];
        ok(ranks(&d.join(folder), 1, &args, Duration::from_secs(90)));
    }
    let resume = [
        "optimize",
        "run.toml",
        "--resume",
        "o",
        "--iterations",
        "12",
    ];
    refused_as_other_files(&in_folders(d, &resume));
}
