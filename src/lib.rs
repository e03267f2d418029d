//! volgrad: a differentiable volumetric path tracer for OpenVDB density grids.
//!
//! Data flows `.vdb → vdb (bridge) → brickmap → medium + majorant → render → image_io`; gradients
//! replay the renderer's paths (`adjoint`), accumulate per voxel (`grad`, `gradgrid`) and go back
//! out through `vdb`. `fd` is the finite-difference reference.

pub mod adjoint;
pub mod brickmap;
pub mod bridge;
pub mod camera;
pub mod chart;
pub mod colormap;
pub mod compare;
pub mod fd;
pub mod grad;
pub mod gradcheck;
pub mod gradgrid;
pub mod gradio;
pub mod image_io;
pub mod lights;
pub mod loss;
pub mod majorant;
pub mod make_grid;
pub mod medium;
pub mod progress;
pub mod render;
pub mod sampling;
pub mod scene;
pub mod tracking;
pub mod transform;
pub mod vdb;

use std::path::Path;

/// Nothing the user had is overwritten without being asked.
pub fn refuse_overwrite(path: &Path, overwrite: bool) -> anyhow::Result<()> {
    if path.exists() && !overwrite {
        anyhow::bail!(
            "'{}' already exists: pass --force to overwrite it",
            path.display()
        );
    }
    Ok(())
}
