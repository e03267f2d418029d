//! The `volgrad` binary as a process: run it, read what it said, check how it failed.

use std::process::{Command, Output};

pub fn volgrad(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_volgrad"))
        .args(args)
        .output()
        .expect("runs volgrad")
}

/// `volgrad` run from the folder `dir` (relative paths in `args` are relative to it).
pub fn volgrad_in(dir: &std::path::Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_volgrad"))
        .current_dir(dir)
        .args(args)
        .output()
        .expect("runs volgrad")
}

pub fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The output of a command that must have succeeded.
pub fn ok(o: Output) -> Output {
    assert!(o.status.success(), "failed: {}{}", stdout(&o), stderr(&o));
    o
}

/// Fails unless the command failed cleanly (exit status 1, no panic, one `error: ` message, which
/// may go on over a few lines such as a TOML diagnostic) with a message containing every `needle`.
pub fn assert_clean_error(o: &Output, needles: &[&str]) {
    let err = stderr(o);
    assert!(
        !o.status.success(),
        "expected failure, got success; stderr: {err}"
    );
    assert_eq!(
        o.status.code(),
        Some(1),
        "exit code (an abort or a signal is not a clean error): {err}"
    );
    assert!(!err.contains("panicked"), "panic: {err}");
    let errors = err.lines().filter(|l| l.starts_with("error: ")).count();
    assert_eq!(errors, 1, "one error message: {err}");
    for n in needles {
        assert!(err.contains(n), "error does not mention {n:?}: {err}");
    }
}

/// `dir/sphere.vdb`: a `make-grid` sphere of 12 voxels at 0.5 units, value 1, made once.
pub fn sphere_vdb(dir: &std::path::Path) -> std::path::PathBuf {
    let vdb = dir.join("sphere.vdb");
    if !vdb.exists() {
        let size = ["--size", "12", "--value", "1", "--voxel-size", "0.5"];
        let out = ["-o", vdb.to_str().expect("a UTF-8 path")];
        ok(volgrad(
            &[&["make-grid", "sphere"][..], &size, &out].concat(),
        ));
    }
    vdb
}
