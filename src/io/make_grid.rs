//! Small analytic grids for tests and examples, written as real .vdb files through the bridge.

use glam::{DMat3, DVec3, IVec3};

use crate::io::vdb::{meta, Grid};
use crate::volume::brickmap::{BrickMap, BrickMapBuilder};
use crate::volume::transform::IndexTransform;
use crate::volume::transform::MIN_VOXEL_SIZE;

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
    /// A ball of diameter `size` whose density falls from `value` at the centre as 1 − (r/R)²,
    /// and beside it a grid "temperature", 3 at the centre falling to 1 at the rim (× 1000 K with
    /// `blackbody = { scale = 1000 }`): a test fire with no download.
    Fireball,
    /// The fireball's density ball, and beside it a vec3 grid "Cd", an RGB albedo from orange at
    /// the bottom (y = 0) to blue at the top: coloured smoke with no download.
    ColouredSmoke,
}

/// The OpenVDB class of the grid written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Class {
    /// Densities: the shape's voxels hold `value`, background 0.
    #[default]
    Fog,
    /// Signed distances in world units (negative inside) in a narrow band of
    /// 3 voxels (OpenVDB's default half-width) either side of the surface; background the half-width.
    /// Sphere only, cubic voxels only (the distance is then exact).
    Levelset,
}

/// OpenVDB's default narrow-band half-width (`openvdb::LEVEL_SET_HALF_WIDTH`), in voxels.
pub const LEVEL_SET_HALF_WIDTH: i32 = 3;

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
    pub class: Class,
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
            class: Class::Fog,
        }
    }
}

/// Builds the grid. Its centre maps to the world origin.
/// The largest edge `make_grid` makes: 512³ voxels are 0.5 GiB of values, held three times over
/// while the file is written (1024³ asked for more memory than most machines have).
pub const MAX_SIZE: u32 = 512;

pub fn make_grid(spec: &GridSpec) -> anyhow::Result<Grid> {
    if spec.size == 0 || spec.size > MAX_SIZE {
        anyhow::bail!(
            "--size must be between 1 and {MAX_SIZE} voxels (got {})",
            spec.size
        );
    }
    if !(spec.value.is_finite() && spec.value >= 0.0) {
        anyhow::bail!("--value must be a finite number ≥ 0 (got {})", spec.value);
    }
    if (spec.voxel_size.iter()).any(|&s| !(s >= f64::from(MIN_VOXEL_SIZE) && s.is_finite())) {
        anyhow::bail!(
            "--voxel-size must be from {MIN_VOXEL_SIZE:e} up (got {:?})",
            spec.voxel_size
        );
    }
    if !spec.rotate_deg.iter().all(|a| a.is_finite()) {
        anyhow::bail!(
            "--rotate-deg must be three finite angles (got {:?})",
            spec.rotate_deg
        );
    }
    if spec.class == Class::Levelset {
        if spec.kind != GridKind::Sphere {
            anyhow::bail!(
                "--class levelset makes spheres only (got {})",
                format!("{:?}", spec.kind).to_lowercase()
            );
        }
        if spec.voxel_size.iter().any(|&s| s != spec.voxel_size[0]) {
            anyhow::bail!("--class levelset needs cubic voxels: give one --voxel-size");
        }
    }
    let n = spec.size as i32;
    let depth = match spec.kind {
        GridKind::Slab => spec.thickness.clamp(1, spec.size) as i32,
        _ => n,
    };
    let centre = DVec3::new((n - 1) as f64, (n - 1) as f64, (depth - 1) as f64) * 0.5;
    if spec.class == Class::Levelset {
        return finish(
            spec,
            level_set_sphere(n, centre, spec.voxel_size[0]),
            centre,
        );
    }
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
                    GridKind::Fireball | GridKind::ColouredSmoke => {
                        let r = fireball_radius(v, centre, n);
                        if r <= 1.0 {
                            b.set(v, spec.value * (1.0 - r * r) as f32, true);
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
    finish(spec, b.build(), centre)
}

/// Voxel `v`'s distance from the ball's centre over its radius (n/2 voxels).
fn fireball_radius(v: IVec3, centre: DVec3, n: i32) -> f64 {
    (v.as_dvec3() - centre).length() / (n as f64 * 0.5)
}

/// The fireball's "temperature" grid (`GridKind::Fireball`): 1 + 2·(1 − r/R) inside the ball, in
/// the density grid's index space and transform.
pub fn fireball_temperature(spec: &GridSpec) -> anyhow::Result<Grid> {
    let n = spec.size as i32;
    let centre = DVec3::splat((n - 1) as f64 * 0.5);
    let mut b = BrickMapBuilder::new();
    for x in 0..n {
        for y in 0..n {
            for z in 0..n {
                let v = IVec3::new(x, y, z);
                let r = fireball_radius(v, centre, n);
                if r <= 1.0 {
                    b.set(v, (1.0 + 2.0 * (1.0 - r)) as f32, true);
                }
            }
        }
    }
    let spec = GridSpec {
        name: "temperature".into(),
        ..spec.clone()
    };
    finish(&spec, b.build(), centre)
}

/// The coloured smoke's "Cd" grid (`GridKind::ColouredSmoke`) as its three components (a vec3 grid
/// when written with `vdb::write_grids_with_colours`): over the ball's voxels, an albedo blending
/// from (0.95, 0.55, 0.2) at y = 0 to (0.2, 0.45, 0.95) at the top.
pub fn coloured_smoke_albedo(spec: &GridSpec) -> anyhow::Result<[Grid; 3]> {
    let n = spec.size as i32;
    let centre = DVec3::splat((n - 1) as f64 * 0.5);
    let (bottom, top) = (DVec3::new(0.95, 0.55, 0.2), DVec3::new(0.2, 0.45, 0.95));
    let mut channels = [(); 3].map(|_| BrickMapBuilder::new());
    for x in 0..n {
        for y in 0..n {
            for z in 0..n {
                let v = IVec3::new(x, y, z);
                if fireball_radius(v, centre, n) <= 1.0 {
                    let colour = bottom.lerp(top, y as f64 / (n - 1).max(1) as f64);
                    for (c, channel) in channels.iter_mut().enumerate() {
                        channel.set(v, colour[c] as f32, true);
                    }
                }
            }
        }
    }
    let spec = GridSpec {
        name: "Cd".into(),
        ..spec.clone()
    };
    let [r, g, b] = channels.map(|c| finish(&spec, c.build(), centre));
    Ok([r?, g?, b?])
}

/// Signed distances to the sphere of diameter `n` voxels around `centre`, in world units
/// (`voxel` per index unit): active within the narrow band, ±half-width elsewhere in its leaves.
fn level_set_sphere(n: i32, centre: DVec3, voxel: f64) -> BrickMap {
    let band = LEVEL_SET_HALF_WIDTH;
    let mut b = BrickMapBuilder::new();
    for x in -band..n + band {
        for y in -band..n + band {
            for z in -band..n + band {
                let v = IVec3::new(x, y, z);
                let d = (v.as_dvec3() - centre).length() - n as f64 * 0.5;
                let active = d.abs() < band as f64;
                let d = d.clamp(-band as f64, band as f64) * voxel;
                b.set(v, d as f32, active);
            }
        }
    }
    b.build()
}

/// The grid around `bricks`, with the spec's transform, name and class.
fn finish(spec: &GridSpec, bricks: BrickMap, centre: DVec3) -> anyhow::Result<Grid> {
    let [rx, ry, rz] = spec.rotate_deg.map(f64::to_radians);
    let linear = DMat3::from_rotation_z(rz)
        * DMat3::from_rotation_y(ry)
        * DMat3::from_rotation_x(rx)
        * DMat3::from_diagonal(DVec3::from(spec.voxel_size));
    let transform = IndexTransform::centred(linear, centre)?;
    let (grid_class, background) = match spec.class {
        Class::Fog => ("fog volume", 0.0),
        Class::Levelset => (
            "level set",
            (LEVEL_SET_HALF_WIDTH as f64 * spec.voxel_size[0]) as f32,
        ),
    };
    Ok(Grid {
        name: spec.name.clone(),
        grid_class: grid_class.into(),
        background,
        transform,
        bricks,
        saved_as_half: false,
        metadata: vec![meta(
            "generator",
            "string",
            format!("volgrad make-grid {:?}", spec.kind).to_lowercase(),
        )],
    })
}
