//! The grid's index-to-world affine map.
//!
//! Rays are traced in index space, where voxel centres sit at integer coordinates. A world ray
//! `o + t·ω` with unit `ω` maps to the index ray `M⁻¹o + t·(M⁻¹ω)`: the parameter `t` stays a *world*
//! distance, so extinction (per world unit) and distances need no conversion even for rotated or
//! anisotropic voxels.

use glam::{DAffine3, DMat3, DVec3, Vec3};

/// The smallest voxel a grid may have, in world units. OpenVDB will not write a transform whose
/// determinant (a voxel's volume) is within 10⁻¹⁵ of 0 ("nearly singular"), so a grid of voxels
/// under 10⁻⁵ could be made and computed with but never saved; 10⁻⁴ leaves a margin.
pub const MIN_VOXEL_SIZE: f32 = 1e-4;

/// The farthest from the origin a scene places anything (a camera, a grid's voxels), in world
/// units and in a grid's index space alike. The renderer traces in f32: beyond this, squared
/// distances (up to ~1e31) approach f32::MAX (3.4e38) once scaled into index space, and a ray
/// origin's rounding error (|p| × 6e-8) exceeds any reasonable voxel.
pub const MAX_COORDINATE: f32 = 1e15;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndexTransform {
    index_to_world: DAffine3,
    world_to_index: DAffine3,
}

impl IndexTransform {
    /// From the bridge's 4×4 (column-vector convention, row-major). Fails for singular or
    /// non-finite maps.
    pub fn from_rows(m: &[f64; 16]) -> anyhow::Result<Self> {
        let linear = DMat3::from_cols(
            DVec3::new(m[0], m[4], m[8]),
            DVec3::new(m[1], m[5], m[9]),
            DVec3::new(m[2], m[6], m[10]),
        );
        let translation = DVec3::new(m[3], m[7], m[11]);
        Self::new(DAffine3::from_mat3_translation(linear, translation))
    }

    pub fn new(index_to_world: DAffine3) -> anyhow::Result<Self> {
        let det = index_to_world.matrix3.determinant();
        if !det.is_finite() || det.abs() < 1e-300 || !index_to_world.translation.is_finite() {
            anyhow::bail!("the grid's index-to-world transform is singular or not finite");
        }
        let world_to_index = index_to_world.inverse();
        // Both maps are applied in f32: a translation of 1e300 is finite in f64 and infinite in
        // f32, and rendered nothing without a word.
        let largest = |m: &DAffine3| {
            (m.matrix3.abs().to_cols_array().into_iter())
                .chain(m.translation.abs().to_array())
                .fold(0.0, f64::max)
        };
        let limit = f64::from(MAX_COORDINATE);
        if largest(&index_to_world) > limit || largest(&world_to_index) > limit {
            anyhow::bail!(
                "the grid's index-to-world transform places or scales its voxels beyond what f32 positions resolve (its largest entry {:.3e}, its inverse's {:.3e}; each at most {MAX_COORDINATE:e})",
                largest(&index_to_world),
                largest(&world_to_index)
            );
        }
        Ok(Self {
            index_to_world,
            world_to_index,
        })
    }

    /// The linear map `linear` (voxel edges, rotation) placed so that index point `centre` lands on
    /// the world origin.
    pub fn centred(linear: DMat3, centre: DVec3) -> anyhow::Result<Self> {
        Self::new(DAffine3::from_mat3_translation(linear, -(linear * centre)))
    }

    /// Uniform voxels of edge `voxel_size`, voxel (0,0,0) centred at `origin`: for constants (a
    /// voxel size or origin beyond `MAX_COORDINATE` panics; a user's go through `new`).
    pub fn uniform(voxel_size: f64, origin: DVec3) -> Self {
        Self::new(DAffine3::from_mat3_translation(
            DMat3::from_diagonal(DVec3::splat(voxel_size)),
            origin,
        ))
        .expect("a positive voxel size gives an invertible map")
    }

    /// Back to the bridge's 4×4 layout.
    pub fn to_rows(&self) -> [f64; 16] {
        let m = self.index_to_world.matrix3;
        let t = self.index_to_world.translation;
        [
            m.x_axis.x, m.y_axis.x, m.z_axis.x, t.x, //
            m.x_axis.y, m.y_axis.y, m.z_axis.y, t.y, //
            m.x_axis.z, m.y_axis.z, m.z_axis.z, t.z, //
            0.0, 0.0, 0.0, 1.0,
        ]
    }

    pub fn index_to_world(&self) -> DAffine3 {
        self.index_to_world
    }

    pub fn point_to_index(&self, world: Vec3) -> Vec3 {
        self.world_to_index
            .transform_point3(world.as_dvec3())
            .as_vec3()
    }

    pub fn vector_to_index(&self, world: Vec3) -> Vec3 {
        self.world_to_index
            .transform_vector3(world.as_dvec3())
            .as_vec3()
    }

    pub fn point_to_world(&self, index: Vec3) -> Vec3 {
        self.index_to_world
            .transform_point3(index.as_dvec3())
            .as_vec3()
    }

    /// World lengths of the three index axes.
    pub fn voxel_size(&self) -> DVec3 {
        let m = self.index_to_world.matrix3;
        DVec3::new(m.x_axis.length(), m.y_axis.length(), m.z_axis.length())
    }

    /// A bound on the world length of any segment inside one voxel (the sum of its edges, which
    /// holds for sheared transforms too).
    pub fn voxel_diagonal(&self) -> f32 {
        self.voxel_size().element_sum() as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_round_trip_and_invert() {
        let rows = [
            0.0, -2.0, 0.0, 5.0, 1.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.5, 3.0, 0.0, 0.0, 0.0, 1.0,
        ];
        let t = IndexTransform::from_rows(&rows).unwrap();
        assert_eq!(t.to_rows(), rows);
        let p = Vec3::new(1.0, 2.0, 3.0);
        let w = t.point_to_world(p);
        assert_eq!(w, Vec3::new(-4.0 + 5.0, 1.0 - 1.0, 1.5 + 3.0));
        assert!((t.point_to_index(w) - p).length() < 1e-5);
        assert_eq!(t.voxel_size(), DVec3::new(1.0, 2.0, 0.5));
    }

    #[test]
    fn singular_map_is_an_error() {
        let mut rows = [0.0; 16];
        rows[15] = 1.0;
        assert!(IndexTransform::from_rows(&rows).is_err());
    }

    /// A map finite in f64 but beyond f32's reach is refused: a translation of 1e300 (a file the
    /// fuzzer made from the sphere rendered an empty image without a word) or voxels of 1e20.
    #[test]
    fn maps_beyond_f32_positions_are_errors() {
        let ok = IndexTransform::uniform(0.25, DVec3::new(1e14, 0.0, -3.0)).to_rows();
        assert!(IndexTransform::from_rows(&ok).is_ok());
        for (entry, value) in [(3, 1e300), (7, -2e15), (0, 1e20), (10, 1e-16)] {
            let mut rows = ok;
            rows[entry] = value;
            let e = IndexTransform::from_rows(&rows).err().unwrap().to_string();
            assert!(
                e.contains("beyond what f32 positions resolve"),
                "{entry}: {e}"
            );
        }
    }
}
