//! Inverse rendering: the unknown grid θ ≥ 0 with Adam's state, kept sparse by brick, and its
//! coarse-to-fine resampling. Uses `volume` (and, as the loop grows, `render` and `gradient`).

pub mod parameters;
pub mod resample;
