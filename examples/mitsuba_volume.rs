//! Writes a scene's medium as Mitsuba 3 volumes, for `scripts/mitsuba_reference.py`: the density
//! (`density.vol`) and, for an albedo grid, the albedo at the density's voxels (`albedo.vol`),
//! dense over the active box, plus `volume.json` with the two transforms Mitsuba needs.
//!
//! ```sh
//! cargo run --release --example mitsuba_volume -- SCENE.toml OUT_DIR
//! ```
//!
//! Mitsuba's `gridvolume` places its values at cell centres and clamps at its edges, while
//! volgrad's medium fills the active box grown by half a voxel and blends its edge voxels towards
//! the background (0) there. The volumes are therefore padded with one voxel of background, and
//! the medium's shape is volgrad's bounds: inside it, both renderers interpolate the same values.
//! The albedo is sampled at the density's voxel centres, which is exact when its grid shares the
//! density's voxels (as `make-grid coloured-smoke` writes it); otherwise the script's reference is
//! that of the resampled albedo.

use std::io::Write;
use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::{DAffine3, DVec3, IVec3, Vec3};
use volgrad::io::output::{write_bytes_whole, write_whole};
use volgrad::render::scene::Scene;
use volgrad::volume::ray::Filter;

/// 2^27 voxels: 512 MiB of density, 1.5 GiB of albedo.
const MAX_DENSE_VOXELS: i64 = 1 << 27;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [scene, out] = args.as_slice() else {
        bail!("usage: mitsuba_volume SCENE.toml OUT_DIR");
    };
    let scene = Scene::load(scene.as_ref())?;
    let medium = &scene.medium;
    if medium.emission.is_some() {
        bail!("Mitsuba 3's heterogeneous medium has no emission: a scene with emission has no reference there");
    }
    if medium.filter != Filter::Trilinear {
        bail!("the reference interpolates as Mitsuba's gridvolume does: the scene's filter must be trilinear");
    }
    let out = Path::new(out);
    std::fs::create_dir_all(out).with_context(|| format!("creating '{}'", out.display()))?;

    // Voxel centres lo..=hi are the active box; the padded volume runs from lo − 1 to hi + 1.
    let (min, max) = medium.bounds;
    let lo = (min + 0.5).round().as_ivec3() - 1;
    let hi = (max - 0.5).round().as_ivec3() + 1;
    let voxels = || {
        (lo.z..=hi.z).flat_map(move |z| {
            (lo.y..=hi.y).flat_map(move |y| (lo.x..=hi.x).map(move |x| IVec3::new(x, y, z)))
        })
    };
    let resolution = hi - lo + 1;
    // The volumes are dense over the active box: refuse a wide sparse grid before allocating.
    let voxels_in_box = resolution.as_i64vec3().element_product();
    if voxels_in_box > MAX_DENSE_VOXELS {
        bail!("the active box has {voxels_in_box} voxels; Mitsuba's volumes are dense, at most {MAX_DENSE_VOXELS} here");
    }
    let density: Vec<f32> = voxels().map(|v| medium.grid.voxel(v)).collect();
    write_vol(&out.join("density.vol"), resolution, 1, &density)?;
    if medium.albedo.grid().is_some() {
        let to_world = |v: IVec3| medium.transform.point_to_world(v.as_vec3());
        let albedo: Vec<f32> = voxels()
            .flat_map(|v| medium.albedo.at(to_world(v)).to_array())
            .collect();
        write_vol(&out.join("albedo.vol"), resolution, 3, &albedo)?;
    }

    // Mitsuba maps the unit cube onto the volume (cell centres at (i + ½)/n) and [−1, 1]³ onto
    // the shape that holds the medium.
    let index_to_world = medium.transform.index_to_world();
    let unit_to_index = |from: Vec3, to: Vec3| {
        let (from, to) = (from.as_dvec3(), to.as_dvec3());
        DAffine3::from_translation(from) * DAffine3::from_scale(to - from)
    };
    let grid_to_world = index_to_world * unit_to_index(lo.as_vec3() - 0.5, hi.as_vec3() + 0.5);
    let cube_to_unit =
        DAffine3::from_translation(DVec3::splat(0.5)) * DAffine3::from_scale(DVec3::splat(0.5));
    let shape_to_world = index_to_world * unit_to_index(min, max) * cube_to_unit;
    let json = format!(
        "{{\n  \"grid_to_world\": {},\n  \"shape_to_world\": {},\n  \"resolution\": [{}, {}, {}],\n  \"albedo_grid\": {}\n}}\n",
        matrix_rows(&grid_to_world),
        matrix_rows(&shape_to_world),
        resolution.x,
        resolution.y,
        resolution.z,
        medium.albedo.grid().is_some()
    );
    write_bytes_whole(&out.join("volume.json"), json)?;
    eprintln!(
        "wrote a {} × {} × {} volume to '{}'",
        resolution.x,
        resolution.y,
        resolution.z,
        out.display()
    );
    Ok(())
}

/// The 4 × 4 matrix, row by row, as a JSON list.
fn matrix_rows(m: &DAffine3) -> String {
    let (a, t) = (m.matrix3, m.translation);
    let rows = [
        [a.x_axis.x, a.y_axis.x, a.z_axis.x, t.x],
        [a.x_axis.y, a.y_axis.y, a.z_axis.y, t.y],
        [a.x_axis.z, a.y_axis.z, a.z_axis.z, t.z],
        [0.0, 0.0, 0.0, 1.0],
    ];
    format!("{rows:?}")
}

/// Mitsuba's binary volume: "VOL", version 3, encoding 1 (float32), the resolution, the channel
/// count, a bounding box (unused: the transform places it), then the values with x fastest.
fn write_vol(path: &Path, resolution: IVec3, channels: i32, values: &[f32]) -> Result<()> {
    write_whole(path, |w| {
        w.write_all(b"VOL\x03")?;
        for n in [1, resolution.x, resolution.y, resolution.z, channels] {
            w.write_all(&n.to_le_bytes())?;
        }
        for b in [0.0f32, 0.0, 0.0, 1.0, 1.0, 1.0] {
            w.write_all(&b.to_le_bytes())?;
        }
        for v in values {
            w.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    })
}
