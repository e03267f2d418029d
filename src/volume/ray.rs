//! The words every walk through the medium shares: rays in index space, the lookup filter, the
//! majorant segments a walk cuts a ray into, and the optical depth at which a segment is worth
//! refining.
//!
//! A leaf: it uses nothing else in the crate, so that the modules that find, bound, cut and track
//! segments (`hot_spots`, `majorant_walk`, `refine`, `tracking`) and the medium can all name these
//! without naming each other.

use glam::Vec3;

/// How σt is looked up between voxel centres.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    clap::ValueEnum,
    serde::Deserialize,
    serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Filter {
    /// The value of the voxel containing the point.
    Nearest,
    /// OpenVDB's box sampler: interpolation between the eight surrounding voxel centres.
    #[default]
    Trilinear,
}

crate::display_as_value_enum!(Filter);

/// A ray in index space; `t` is a world distance (see `transform`).
#[derive(Debug, Clone, Copy)]
pub struct IndexRay {
    pub o: Vec3,
    pub d: Vec3,
}

impl IndexRay {
    #[inline]
    pub fn at(&self, t: f32) -> Vec3 {
        self.o + self.d * t
    }
}

/// One stretch of a ray inside one majorant cell: `[t0, t1)` in world distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MajorantSegment {
    pub t0: f32,
    pub t1: f32,
    pub sigma_max: f32,
}

/// Majorant optical depth above which a stretch is worth refining (a walk through it takes about
/// this many tentative collisions): `tracking` refines such stretches (`refine`), and `hot_spots`
/// examines only the cells a crossing of which could cost that much.
pub const SPLIT_DEPTH: f32 = 16.0;
