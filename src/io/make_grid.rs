//! Small analytic grids for tests and examples, written as real .vdb files through the bridge.

use glam::{DMat3, DVec3, IVec3};

use crate::io::vdb::{meta, Grid};
use crate::volume::brickmap::BrickMapBuilder;
use crate::volume::transform::IndexTransform;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum GridKind {
    /// A cube of `size`³ voxels of constant value.
    Box,
    /// A ball of diameter `size` voxels of constant value (a fog sphere).
    Sphere,
    /// `size`×`size`×`thickness` voxels of constant value: a thin layer.
    Slab,
    /// A `size`³ block of active, empty voxels with one voxel of `value` at its centre.
    SingleVoxel,
}

#[derive(Debug, Clone)]
pub struct GridSpec {
    pub kind: GridKind,
    pub size: u32,
    pub thickness: u32,
    pub value: f32,
    /// World size of a voxel along each index axis.
    pub voxel_size: [f64; 3],
    /// Rotation applied after scaling: Euler angles about x, then y, then z, in degrees.
    pub rotate_deg: [f64; 3],
    pub name: String,
}

impl GridSpec {
    pub fn new(kind: GridKind, size: u32, value: f32) -> Self {
        GridSpec {
            kind,
            size,
            thickness: 2,
            value,
            voxel_size: [1.0; 3],
            rotate_deg: [0.0; 3],
            name: "density".into(),
        }
    }
}

/// Builds the grid. Its centre maps to the world origin.
pub fn make_grid(spec: &GridSpec) -> anyhow::Result<Grid> {
    if spec.size == 0 || spec.size > 1024 {
        anyhow::bail!(
            "--size must be between 1 and 1024 voxels (got {})",
            spec.size
        );
    }
    if !(spec.value.is_finite() && spec.value >= 0.0) {
        anyhow::bail!("--value must be a finite number ≥ 0 (got {})", spec.value);
    }
    if spec.voxel_size.iter().any(|&s| !(s > 0.0 && s.is_finite())) {
        anyhow::bail!("--voxel-size must be positive (got {:?})", spec.voxel_size);
    }
    let n = spec.size as i32;
    let depth = match spec.kind {
        GridKind::Slab => spec.thickness.clamp(1, spec.size) as i32,
        _ => n,
    };
    let centre = DVec3::new((n - 1) as f64, (n - 1) as f64, (depth - 1) as f64) * 0.5;
    let mut b = BrickMapBuilder::new();
    for x in 0..n {
        for y in 0..n {
            for z in 0..depth {
                let v = IVec3::new(x, y, z);
                match spec.kind {
                    GridKind::Box | GridKind::Slab => b.set(v, spec.value, true),
                    GridKind::Sphere => {
                        if (v.as_dvec3() - centre).length() <= n as f64 * 0.5 {
                            b.set(v, spec.value, true);
                        }
                    }
                    GridKind::SingleVoxel => {
                        let hot = v == IVec3::splat(n / 2);
                        b.set(v, if hot { spec.value } else { 0.0 }, true);
                    }
                }
            }
        }
    }
    let [rx, ry, rz] = spec.rotate_deg.map(f64::to_radians);
    let linear = DMat3::from_rotation_z(rz)
        * DMat3::from_rotation_y(ry)
        * DMat3::from_rotation_x(rx)
        * DMat3::from_diagonal(DVec3::from(spec.voxel_size));
    let transform = IndexTransform::centred(linear, centre)?;
    Ok(Grid {
        name: spec.name.clone(),
        grid_class: "fog volume".into(),
        transform,
        bricks: b.build(),
        saved_as_half: false,
        metadata: vec![meta(
            "generator",
            "string",
            format!("volgrad make-grid {:?}", spec.kind).to_lowercase(),
        )],
    })
}
