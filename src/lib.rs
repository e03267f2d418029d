//! volgrad: a differentiable volumetric path tracer for OpenVDB density grids.
//!
//! Layers, each using only those before it: `volume` (bricks, majorants, tracking) < `io` (files
//! and the terminal) < `render` (scenes and the path tracer) < `gradient` (path replay, passes,
//! finite differences) < `compare` (equal-time studies). The binary's `cli` sits on top.

pub mod compare;
pub mod gradient;
pub mod io;
pub mod render;
pub mod volume;

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
