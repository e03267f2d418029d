//! The participating medium: a brick map of grid values, the grid's transform, and the optical
//! properties a scene gives it. σt(x) = density_scale · grid(x); the albedo is a constant or a grid
//! of its own (`albedo`), the phase function constant over the medium; it may emit (`emission`:
//! σa·Le from a grid of its own).

use glam::Vec3;

use crate::volume::albedo::Albedo;
use crate::volume::brickmap::BrickMap;
use crate::volume::emission::Emission;
use crate::volume::majorant::{Majorant, MajorantGrid};
use crate::volume::transform::IndexTransform;

// The layers above (scenes, gradients, tests) name a medium's filter and rays here; they live in
// `ray`, below every module that walks, so that those need not import the medium.
pub use crate::volume::ray::{Filter, IndexRay};

#[derive(Clone)]
pub struct Medium {
    pub grid: BrickMap,
    pub transform: IndexTransform,
    /// Continuous index box the medium fills: the active voxels' box grown by half a voxel (or a
    /// box given with `with_bounds`).
    pub bounds: (Vec3, Vec3),
    pub density_scale: f32,
    pub filter: Filter,
    pub albedo: Albedo,
    pub phase_g: f32,
    pub majorant: MajorantGrid,
    /// Light the medium gives off, from its own grid (none: a medium that only scatters).
    pub emission: Option<Emission>,
}

impl Medium {
    pub fn new(
        grid: BrickMap,
        transform: IndexTransform,
        density_scale: f32,
        filter: Filter,
        majorant: Majorant,
    ) -> Self {
        let bounds = match grid.active_bounds() {
            Some((lo, hi)) => (lo.as_vec3() - 0.5, hi.as_vec3() + 0.5),
            None => (Vec3::ZERO, Vec3::ZERO),
        };
        Self::with_bounds(grid, transform, bounds, density_scale, filter, majorant)
    }

    /// A medium filling the continuous index box `bounds`, whatever the grid's active voxels: an
    /// optimisation's unknown keeps its domain while bricks come and go.
    pub fn with_bounds(
        grid: BrickMap,
        transform: IndexTransform,
        bounds: (Vec3, Vec3),
        density_scale: f32,
        filter: Filter,
        majorant: Majorant,
    ) -> Self {
        let majorant = MajorantGrid::build(&grid, bounds, density_scale, majorant)
            .with_hot_spots(&grid, transform.voxel_diagonal());
        Medium {
            grid,
            transform,
            bounds,
            density_scale,
            filter,
            albedo: Albedo::default(),
            phase_g: 0.0,
            majorant,
            emission: None,
        }
    }

    /// Extinction at an index-space point.
    #[inline]
    pub fn sigma_t(&self, p: Vec3) -> f32 {
        self.density_scale
            * match self.filter {
                Filter::Nearest => self.grid.nearest(p),
                Filter::Trilinear => self.grid.trilinear(p),
            }
    }

    /// The world ray `o + t·ω` (unit ω) in index space.
    #[inline]
    pub fn to_index_ray(&self, o: Vec3, w: Vec3) -> IndexRay {
        IndexRay {
            o: self.transform.point_to_index(o),
            d: self.transform.vector_to_index(w),
        }
    }

    /// The `[t0, t1]` (t ≥ 0) where the ray is inside the medium's box, if any.
    #[inline]
    pub fn intersect(&self, ray: &IndexRay) -> Option<(f32, f32)> {
        let (lo, hi) = self.bounds;
        let mut t0 = 0.0f32;
        let mut t1 = f32::INFINITY;
        for a in 0..3 {
            if ray.d[a] == 0.0 {
                if ray.o[a] < lo[a] || ray.o[a] > hi[a] {
                    return None;
                }
                continue;
            }
            let inv = 1.0 / ray.d[a];
            let (mut near, mut far) = ((lo[a] - ray.o[a]) * inv, (hi[a] - ray.o[a]) * inv);
            if near > far {
                std::mem::swap(&mut near, &mut far);
            }
            t0 = t0.max(near);
            t1 = t1.min(far);
        }
        (t0 < t1).then_some((t0, t1))
    }

    /// Bytes held by the medium's data structures.
    pub fn memory_bytes(&self) -> usize {
        self.grid.memory_bytes() + self.majorant.memory_bytes()
    }
}
