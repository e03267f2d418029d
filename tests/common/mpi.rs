//! Running volgrad as MPI ranks in tests (`mpirun -n N`, OpenMPI as scripts/setup.sh installs it),
//! with a time limit: a rank left waiting is a failure, not a stuck test.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

pub fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// The quick example on one thread per rank: 8 views of 32², two held out.
pub fn run_file(extra: &str) -> String {
    format!(
        r#"
scene = "{scene}"
truth = "{truth}"
target_spp = 64
eval_spp = 64
eval_every = 4
checkpoint_every = 4

[views.orbit]
count = 8
elevation_deg = [-30, 70]
distance = 12
fov_deg = 40
width = 32
height = 32

[holdouts.orbit]
count = 2
elevation_deg = [0, 40]
distance = 12
fov_deg = 40
width = 32
height = 32
azimuth_offset_deg = 60

[unknown]
bounds = "truth"
start = 0.0

[optimizer]
spp = 4
{extra}
"#,
        scene = repo("scenes/inverse/quick-scene.toml").display(),
        truth = repo("scenes/analytic/sphere.vdb").display(),
    )
}

/// `mpirun --oversubscribe` in `dir`, the ranks' programs still to be given (`-n N program args`,
/// and `: -n N …` for more).
pub fn mpirun(dir: &Path) -> Command {
    let mut command = Command::new("mpirun");
    command
        .current_dir(dir)
        // OpenMPI refuses root without these; CI runs as root.
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .arg("--oversubscribe");
    command
}

/// `volgrad args` in `dir` as `ranks` MPI ranks of one thread each (1: a plain process, no
/// mpirun), killed after `limit`: a hang is a failure, not a stuck test.
pub fn ranks(dir: &Path, ranks: usize, args: &[&str], limit: Duration) -> Output {
    let exe = env!("CARGO_BIN_EXE_volgrad");
    let mut command = if ranks == 1 {
        let mut c = Command::new(exe);
        c.current_dir(dir);
        c
    } else {
        let mut c = mpirun(dir);
        c.args(["-n", &ranks.to_string(), exe]);
        c
    };
    command.args(args);
    if !args.contains(&"--threads") {
        command.args(["--threads", "1"]);
    }
    wait(command, limit)
}

pub fn wait(mut command: Command, limit: Duration) -> Output {
    let mut child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("mpirun is installed (scripts/setup.sh installs OpenMPI)");
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > limit {
            child.kill().unwrap();
            panic!("still running after {limit:?}: a rank waits for one that has gone");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().unwrap()
}

pub const LIMIT: Duration = Duration::from_secs(120);
