//! Inverse rendering: the unknown grid θ ≥ 0 with Adam's state (sparse by brick), its
//! coarse-to-fine resampling, and orbit views. Uses `volume` and `render` (and, as the loop grows,
//! `gradient`).

pub mod parameters;
pub mod resample;
pub mod views;
