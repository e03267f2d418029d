//! volgrad: a differentiable volumetric path tracer for OpenVDB density grids.
//!
//! Layers, each using only those before it: `volume` (bricks, majorants, tracking) < `io` (files
//! and the terminal) < `render` (scenes and the path tracer) < `capture` (pictures and cameras
//! from elsewhere) < `gradient` (path replay, passes, finite differences) < `cluster` (the MPI
//! processes of one job) < `compare` (equal-time studies) < `optimize` (inverse rendering). The
//! binary's `cli` sits on top.

// Bad input gets an error, never a panic: outside tests an unwrap must say why it cannot fail
// (`expect`). Tests (here and in tests/) may unwrap.
#![cfg_attr(not(test), deny(clippy::unwrap_used))]

pub mod capture;
pub mod cluster;
pub mod compare;
pub mod gradient;
pub mod io;
pub mod optimize;
pub mod render;
pub mod volume;

/// `Display` for an enum that derives `clap::ValueEnum`: its command-line name, which is also its
/// name in scene files (serde kebab-case) and in outputs. One spelling per value, written once.
#[macro_export]
macro_rules! display_as_value_enum {
    ($t:ty) => {
        impl std::fmt::Display for $t {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                let value = clap::ValueEnum::to_possible_value(self)
                    .expect("every value of a volgrad enum has a name");
                f.write_str(value.get_name())
            }
        }
    };
}
