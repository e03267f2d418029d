//! The medium as the path tracer sees it: sparse bricks, the index ↔ world map, σt lookups,
//! majorants and free-flight / ratio tracking. Uses nothing else in the crate.
//!
//! The modules read bottom-up, each using only those listed before it (`tests/layers.rs` checks
//! that no import closes a cycle): `ray`, `sparse_index` and `transform` are leaves; `brickmap`
//! stores the voxels and `upsample` refines them; `hot_spots` finds loose cells through the
//! `MajorantCells` trait, `majorant_clusters` finds the boxes a wide medium's data lie in,
//! `majorant_cells` builds the per-cell bounds, `majorant` is the grid that
//! holds both and `majorant_walk` its DDA; `blackbody` is a temperature's colour and `emission` a
//! grid of emitted radiance; `medium` gathers grid, transform, majorant and emission; `refine`
//! tightens a walk's segments along the ray and `tracking` samples them.

pub mod albedo;
pub mod blackbody;
pub mod brickmap;
pub mod emission;
pub mod hot_spots;
pub mod majorant;
mod majorant_cells;
mod majorant_clusters;
pub mod majorant_walk;
pub mod medium;
pub mod ray;
pub mod refine;
pub mod sparse_index;
pub mod tracking;
pub mod transform;
pub mod upsample;
