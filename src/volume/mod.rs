//! The medium as the path tracer sees it: sparse bricks, the index ↔ world map, σt lookups,
//! majorants and free-flight / ratio tracking. Uses nothing else in the crate.

pub mod brickmap;
pub mod hot_spots;
pub mod majorant;
pub mod majorant_walk;
pub mod medium;
pub mod refine;
pub mod sparse_index;
pub mod tracking;
pub mod transform;
pub mod upsample;
