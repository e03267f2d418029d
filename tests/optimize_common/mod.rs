//! The tiny reconstruction the `optimize` tests share: a fog ball of 8³ voxels, sunlit against a
//! dark sky, seen from 6 views of 24² pixels; its run file, a folder to run it in, and its log.
#![allow(dead_code)] // not every test file uses every helper

use std::path::Path;

use crate::common::{ok, volgrad_in};

pub const SCENE: &str = r#"
[camera]
position = [0.0, 2.0, 12.0]
target = [0.0, 0.0, 0.0]
fov_deg = 40
width = 24
height = 24

[medium]
vdb = "ball.vdb"
density_scale = 0.6
albedo = 0.9
phase_g = 0.3

[[light]]
type = "constant"
radiance = [0.03, 0.04, 0.06]

[[light]]
type = "directional"
direction = [-0.5, -1.0, -0.3]
irradiance = 4.0

[render]
max_depth = 16
"#;

/// A run file over the ball; `extra` is appended (TOML tables) and `start` is the unknown's start.
pub fn run_file(start: &str, optimizer: &str) -> String {
    format!(
        r#"
scene = "scene.toml"
truth = "ball.vdb"
target_spp = 256
eval_spp = 128
eval_every = 10
checkpoint_every = 50

[views.orbit]
count = 6
elevation_deg = [-30, 70]
distance = 12
fov_deg = 40
width = 24
height = 24

[holdouts.orbit]
count = 1
elevation_deg = [20, 20]
distance = 12
fov_deg = 40
width = 24
height = 24
azimuth_offset_deg = 60

[unknown]
bounds = "truth"
start = {start}

[optimizer]
lr = 0.1
lr_decay = 0.1
batch = 3
# A ball that converges within its steps: its first level is not noise-limited, and a smoothing
# pass there only blurs it. (Spelled out, not derived: the default would follow each test's spp,
# and tests edit the line.)
first_level_smoothing = 0
{optimizer}
"#
    )
}

/// A folder with the ball (8³ voxels of 1, 0.75 world units each), the scene and `run.toml`.
pub fn fixture(run: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    ok(volgrad_in(
        dir.path(),
        &[
            "make-grid",
            "sphere",
            "--size",
            "8",
            "--value",
            "1",
            "--voxel-size",
            "0.75",
            "-o",
            "ball.vdb",
        ],
    ));
    std::fs::write(dir.path().join("scene.toml"), SCENE).unwrap();
    std::fs::write(dir.path().join("run.toml"), run).unwrap();
    dir
}

/// log.csv as rows of named cells.
pub fn log(dir: &Path) -> Vec<std::collections::HashMap<String, String>> {
    let text = std::fs::read_to_string(dir.join("log.csv")).unwrap();
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    lines
        .map(|l| {
            header
                .iter()
                .cloned()
                .zip(l.split(',').map(String::from))
                .collect()
        })
        .collect()
}

pub fn number(row: &std::collections::HashMap<String, String>, column: &str) -> f64 {
    row[column]
        .parse()
        .unwrap_or_else(|_| panic!("{column} = {:?}", row[column]))
}

/// The evaluated rows' values of `column`.
pub fn evaluated(rows: &[std::collections::HashMap<String, String>], column: &str) -> Vec<f64> {
    rows.iter()
        .filter(|r| !r["heldout_psnr"].is_empty())
        .map(|r| number(r, column))
        .collect()
}

pub fn log_rows(dir: &Path) -> usize {
    std::fs::read_to_string(dir.join("log.csv")).map_or(0, |t| t.lines().count())
}
