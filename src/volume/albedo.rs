//! The medium's single-scattering albedo α = σs/σt: the fraction of a real collision's light that
//! scatters on (the rest, 1 − α, is absorbed and, in an emitting medium, weights its emission).
//! One RGB constant, or a grid of its own (`Cd`: a vec3 grid, RGB per voxel; or a float grid,
//! grey) looked up through the grid's own transform and brick maps, as density is.

use std::fmt;

use glam::Vec3;

use crate::volume::brickmap::BrickMap;
use crate::volume::ray::Filter;
use crate::volume::transform::IndexTransform;

#[derive(Clone)]
pub enum Albedo {
    Constant(Vec3),
    Grid(Box<AlbedoGrid>),
}

impl Albedo {
    /// α at world point `p`.
    #[inline]
    pub fn at(&self, p: Vec3) -> Vec3 {
        match self {
            Albedo::Constant(albedo) => *albedo,
            Albedo::Grid(grid) => grid.at(p),
        }
    }

    /// The grid, where the albedo varies over the medium.
    pub fn grid(&self) -> Option<&AlbedoGrid> {
        match self {
            Albedo::Constant(_) => None,
            Albedo::Grid(grid) => Some(grid),
        }
    }
}

impl Default for Albedo {
    fn default() -> Self {
        Albedo::Constant(Vec3::ONE)
    }
}

/// What decides the images, for scene fingerprints and `volgrad info` (the grid by name: the
/// fingerprint hashes its values separately).
impl fmt::Display for Albedo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Albedo::Constant(albedo) => write!(f, "{albedo} (constant)"),
            Albedo::Grid(grid) => write!(
                f,
                "grid '{}' ({}, outside its voxels {})",
                grid.name,
                if grid.channels.len() == 3 {
                    "RGB"
                } else {
                    "grey"
                },
                grid.background
            ),
        }
    }
}

/// An albedo grid: one brick map per channel (three for a colour, one for grey), each holding
/// value − background, so that a lookup where the file has no voxels reads the file's background
/// (OpenVDB's value of all space outside the tree) and a trilinear lookup blends towards it.
#[derive(Clone)]
pub struct AlbedoGrid {
    /// The grid's name in its file.
    pub name: String,
    pub channels: Vec<BrickMap>,
    pub background: Vec3,
    pub transform: IndexTransform,
    /// The medium's filter, so that albedo and density change at the same places.
    pub filter: Filter,
}

impl AlbedoGrid {
    /// A grid from channels whose values (and `background`) all lie in [0, 1], which the caller
    /// checks: every lookup then does too (a lookup is a convex blend of them).
    pub fn new(
        name: String,
        channels: Vec<BrickMap>,
        background: Vec3,
        transform: IndexTransform,
        filter: Filter,
    ) -> AlbedoGrid {
        debug_assert!(channels.len() == 1 || channels.len() == 3);
        AlbedoGrid {
            name,
            channels,
            background,
            transform,
            filter,
        }
    }

    #[inline]
    pub fn at(&self, p: Vec3) -> Vec3 {
        let index = self.transform.point_to_index(p);
        let value = |c: &BrickMap| match self.filter {
            Filter::Nearest => c.nearest(index),
            Filter::Trilinear => c.trilinear(index),
        };
        self.background
            + match self.channels.as_slice() {
                [grey] => Vec3::splat(value(grey)),
                [r, g, b] => Vec3::new(value(r), value(g), value(b)),
                _ => unreachable!("an albedo grid has one or three channels"),
            }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DVec3, IVec3};

    #[test]
    fn a_lookup_reads_the_channels_and_the_background_outside_them() {
        let transform = IndexTransform::uniform(1.0, DVec3::ZERO);
        // Stored as value − background: r = 0.8, g = 0.5, b = 0.2 over a 4³ block, background
        // (0.1, 0.1, 0.1).
        let channel = |v: f32| BrickMap::block(4, move |_: IVec3| v - 0.1);
        let grid = AlbedoGrid::new(
            "Cd".into(),
            vec![channel(0.8), channel(0.5), channel(0.2)],
            Vec3::splat(0.1),
            transform,
            Filter::Trilinear,
        );
        let inside = grid.at(Vec3::splat(1.5));
        assert!((inside - Vec3::new(0.8, 0.5, 0.2)).abs().max_element() < 1e-6);
        assert!(
            (grid.at(Vec3::splat(20.0)) - Vec3::splat(0.1))
                .abs()
                .max_element()
                < 1e-6
        );
        // Half a voxel past the last voxel centre (3.5 on x): halfway to the background.
        let edge = grid.at(Vec3::new(3.5, 1.5, 1.5));
        assert!((edge - Vec3::new(0.45, 0.3, 0.15)).abs().max_element() < 1e-6);
    }
}
