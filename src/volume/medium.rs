//! The participating medium: a brick map of grid values, the grid's transform, and the optical
//! properties a scene gives it. σt(x) = density_scale · grid(x); the albedo is a constant or a grid
//! of its own (`albedo`), the phase function constant over the medium; it may emit (`emission`:
//! σa·Le from a grid of its own).

use glam::{IVec3, Vec3};

use crate::volume::albedo::Albedo;
use crate::volume::brickmap::{floor_ivec3, BrickMap};
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

    /// An unbiased estimate of σt(p) from one voxel (stochastic trilinear filtering). Along each
    /// axis the upper voxel is read with probability f, its trilinear weight, so the cell's voxel
    /// k is read with probability w_k(p) and E[σ̂] = Σ_k w_k·σ_k = σt(p). Trackers use σt only
    /// linearly (an acceptance probability σt/σ̄, a ratio factor 1 − σt/σ̄), so an estimate with
    /// randomness of its own keeps their expectation; a read may reach any of the eight voxels,
    /// so σ̄ must bound the voxels, not only the interpolated field.
    ///
    /// `bits` are 64 uniform random bits: three 21-bit uniforms u in [0, 1). u < f is never true
    /// at f = 0, so a point on a cell face never reads beyond it.
    #[inline(always)]
    pub fn sigma_t_one_voxel(&self, p: Vec3, bits: u64) -> f32 {
        match self.filter {
            Filter::Nearest => self.sigma_t(p),
            Filter::Trilinear => {
                let v0 = floor_ivec3(p);
                let f = p - v0.as_vec3();
                let u = |shift: u32| ((bits >> shift) & 0x1f_ffff) as f32 * (1.0 / 2_097_152.0);
                let upper = IVec3::new(
                    (u(0) < f.x) as i32,
                    (u(21) < f.y) as i32,
                    (u(42) < f.z) as i32,
                );
                self.density_scale * self.grid.voxel(v0 + upper)
            }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::brickmap::corner;
    use crate::volume::transform::IndexTransform;
    use glam::DVec3;
    use rand::{Rng, RngCore, SeedableRng};

    /// A one-voxel read picks each voxel of the cell with its trilinear weight: over 20 random
    /// points (some on cell faces, where the upper voxels' weight is 0 and they must never be
    /// read, one straddling bricks), each voxel's frequency in 40,000 reads is within 5 standard
    /// errors of its weight. Reading the nearest voxel, or the lower corner, fails at once.
    #[test]
    fn a_one_voxel_read_picks_each_voxel_with_its_trilinear_weight() {
        // Every voxel holds its own id, so a read says which voxel it was.
        let id = |v: IVec3| (v.x * 256 + v.y * 16 + v.z) as f32;
        let medium = Medium::new(
            BrickMap::block(16, id),
            IndexTransform::uniform(1.0, DVec3::ZERO),
            1.0,
            Filter::Trilinear,
            Majorant::grid(4),
        );
        let mut rng = rand::rngs::SmallRng::seed_from_u64(11);
        let n = 40_000;
        for k in 0..20 {
            let mut p = Vec3::new(rng.gen(), rng.gen(), rng.gen()) * 13.0 + 1.0;
            match k {
                0 => p = Vec3::new(7.3, 7.6, 7.05), // straddles the bricks of 8³
                1 => p.y = p.y.floor(),             // on a face
                2 => p = p.floor(),                 // on a voxel centre
                _ => {}
            }
            let v0 = floor_ivec3(p);
            let f = p - v0.as_vec3();
            let mut counts = [0u32; 8];
            for _ in 0..n {
                let read = medium.sigma_t_one_voxel(p, rng.next_u64());
                let c = (0..8)
                    .find(|&c| id(v0 + corner(c)) == read)
                    .unwrap_or_else(|| panic!("{p}: read {read} is not a voxel of the cell"));
                counts[c] += 1;
            }
            for (c, &count) in counts.iter().enumerate() {
                let w: f32 = (0..3)
                    .map(|a| if corner(c)[a] == 1 { f[a] } else { 1.0 - f[a] })
                    .product();
                let (w, freq) = (w as f64, count as f64 / n as f64);
                let se = (w * (1.0 - w) / n as f64).sqrt();
                assert!(
                    (freq - w).abs() <= 5.0 * se + 1e-9,
                    "{p}, corner {c}: read {freq:.4} of the time, weight {w:.4}"
                );
            }
        }
    }
}
