//! Inverse rendering: reconstructing the density grid (or, the density known, the emission grid)
//! from images. The unknown θ ≥ 0 with Adam's state (sparse by brick), its start (in the views'
//! visual hull), its coarse-to-fine resampling, orbit views, run files, the loop, checkpoints and
//! the equal-time study of estimators. Uses `volume`, `io`, `render` and `gradient`.

pub mod adam;
pub mod average;
pub mod brick_gradient;
pub mod checkpoint;
pub mod descent;
pub mod evaluate;
pub mod exposure;
pub mod holdout_picture;
pub mod hull;
pub mod idle_keys;
pub mod iteration;
pub mod log;
pub mod optimizer_file;
pub mod parameters;
pub mod prior;
pub mod problem;
pub mod reconstruct;
pub mod resample;
pub mod run_file;
pub mod scene_units;
pub mod schedule;
pub mod settings_toml;
pub mod smoothing;
pub mod study;
pub mod target_cache;
pub mod targets;
pub mod unknown;
pub mod view_bounds;
pub mod view_files;
pub mod views;
