//! A grid at `factor`× the resolution per axis, for scaling studies: the continuous trilinear field
//! of the original, sampled at the new voxel centres inside the original's leaves and tiles. The
//! world box, and so every optical depth along a ray, stays the same (up to the trilinear field's
//! own smoothing); only the number of voxels, and the memory hierarchy that serves them, grows.
//!
//! New voxel j sits at old index coordinate c = (j + ½)/f − ½ (voxel centres at integers in both
//! grids), so the new index-to-world map is the old one after j ↦ j/f + (1 − f)/(2f).

use anyhow::{bail, Result};
use glam::{DAffine3, DMat3, DVec3, IVec3};
use rayon::prelude::*;

use crate::volume::brickmap::{leaf_offset, BrickMap, Leaf, BRICK_EDGE, BRICK_VOXELS};
use crate::volume::transform::IndexTransform;

/// The most voxels an upsampled grid may hold (2³¹: 8 GiB of leaf values).
const MAX_VOXELS: u64 = 1 << 31;

/// The grid at `factor`× the resolution per axis and its transform. Tiles are voxelised (their
/// edges blend with the neighbours, as the trilinear field does); new leaves that come out all
/// zero are dropped.
pub fn upsample(
    grid: &BrickMap,
    transform: &IndexTransform,
    factor: u32,
) -> Result<(BrickMap, IndexTransform)> {
    if factor == 0 || factor > 64 {
        bail!("upsampling factor must be 1 to 64, got {factor}");
    }
    // Counted before anything is allocated: one 4096³ tile is 2²⁷ blocks of 8³.
    let tile_blocks = |size: u32| ((size / BRICK_EDGE as u32).max(1) as u64).pow(3);
    let old_blocks = grid.leaves().len() as u64
        + grid
            .tiles()
            .iter()
            .map(|t| tile_blocks(t.size))
            .sum::<u64>();
    let fits = old_blocks
        .checked_mul(BRICK_VOXELS as u64 * (factor as u64).pow(3))
        .is_some_and(|v| v <= MAX_VOXELS);
    if !fits {
        bail!("the grid upsampled {factor}× would hold more than {MAX_VOXELS} voxels");
    }
    // New index coordinates are f × the old ones: they must stay i32.
    if let Some((lo, hi)) = grid.active_bounds() {
        let (lo, hi) = (
            lo.as_i64vec3() * factor as i64,
            (hi.as_i64vec3() + 1) * factor as i64,
        );
        if lo.min_element() < i32::MIN as i64 || hi.max_element() > i32::MAX as i64 {
            bail!("the grid's index box upsampled {factor}× leaves the 32-bit index range");
        }
    }
    // Every 8³ block of old data: the leaves, and the 8³ blocks inside each tile.
    let mut blocks: Vec<IVec3> = grid.leaves().iter().map(|l| l.origin).collect();
    for tile in grid.tiles() {
        let n = (tile.size as i32 / BRICK_EDGE).max(1);
        for a in 0..n {
            for b in 0..n {
                for c in 0..n {
                    blocks.push(tile.origin + BRICK_EDGE * IVec3::new(a, b, c));
                }
            }
        }
    }
    let f = factor as i32;
    let inv = 1.0 / factor as f32;
    let leaves: Vec<Leaf> = blocks
        .par_iter()
        .flat_map_iter(|&origin| {
            let first = origin * f;
            (0..f * f * f).filter_map(move |k| {
                let sub = IVec3::new(k / (f * f), (k / f) % f, k % f);
                let new_origin = first + BRICK_EDGE * sub;
                let mut leaf = Leaf {
                    origin: new_origin,
                    values: [0.0; BRICK_VOXELS],
                    active: [0; 8],
                };
                for x in 0..BRICK_EDGE {
                    for y in 0..BRICK_EDGE {
                        for z in 0..BRICK_EDGE {
                            let local = IVec3::new(x, y, z);
                            let j = (new_origin + local).as_vec3();
                            let value = grid.trilinear((j + 0.5) * inv - 0.5);
                            if value != 0.0 {
                                let o = leaf_offset(local);
                                leaf.values[o] = value;
                                leaf.active[o >> 6] |= 1 << (o & 63);
                            }
                        }
                    }
                }
                leaf.active.iter().any(|&w| w != 0).then_some(leaf)
            })
        })
        .collect();
    let s = 1.0 / factor as f64;
    let fine_to_old = DAffine3::from_mat3_translation(
        DMat3::from_diagonal(DVec3::splat(s)),
        DVec3::splat((s - 1.0) / 2.0),
    );
    let transform = IndexTransform::new(transform.index_to_world() * fine_to_old)?;
    Ok((BrickMap::new(leaves, Vec::new()), transform))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::brickmap::Tile;
    use glam::Vec3;

    #[test]
    fn the_field_and_the_world_box_are_kept() {
        // A linear ramp in x over a leaf and a tile: trilinear reproduces it exactly inside.
        let ramp = |v: IVec3| 1.0 + 0.25 * v.x as f32;
        let leaf = {
            let mut l = Leaf {
                origin: IVec3::ZERO,
                values: [0.0; BRICK_VOXELS],
                active: [u64::MAX; 8],
            };
            for o in 0..BRICK_VOXELS {
                let v = IVec3::new((o >> 6) as i32, ((o >> 3) & 7) as i32, (o & 7) as i32);
                l.values[o] = ramp(v);
            }
            l
        };
        let tile = Tile {
            origin: IVec3::new(0, 8, 0),
            size: 8,
            value: 2.0,
        };
        let grid = BrickMap::new(vec![leaf], vec![tile]);
        let transform = IndexTransform::uniform(0.5, DVec3::new(1.0, -2.0, 3.0));
        let (fine, fine_transform) = upsample(&grid, &transform, 2).unwrap();
        // Voxel centres map to the old field's points: check a few inside the leaf.
        for j in [
            IVec3::new(3, 5, 7),
            IVec3::new(12, 2, 14),
            IVec3::new(9, 9, 9),
        ] {
            let world = fine_transform.point_to_world(j.as_vec3());
            let old = transform.point_to_index(world);
            assert!((old - ((j.as_vec3() + 0.5) / 2.0 - 0.5)).length() < 1e-5);
            // Inside the leaf, where the ramp's trilinear interpolation is the ramp itself.
            assert!((fine.voxel(j) - (1.0 + 0.25 * old.x)).abs() < 1e-6);
        }
        // Inside the tile, away from its edges: the tile's value.
        assert_eq!(fine.voxel(IVec3::new(6, 24, 6)), 2.0);
        // The world box of the data is the same (to half an old voxel).
        let (lo, hi) = fine.active_bounds().unwrap();
        let world_lo = fine_transform.point_to_world(lo.as_vec3() - 0.5);
        let world_hi = fine_transform.point_to_world(hi.as_vec3() + 0.5);
        assert!((world_lo - transform.point_to_world(Vec3::splat(-0.5))).length() < 1e-4);
        assert!((world_hi - transform.point_to_world(Vec3::new(7.5, 15.5, 7.5))).length() < 1e-4);
        assert_eq!(fine.leaves().len(), 8 * 2);
        assert!(upsample(&grid, &transform, 0).is_err());
    }

    #[test]
    fn grids_too_large_or_too_far_out_are_refused_before_any_work() {
        let transform = IndexTransform::uniform(1.0, DVec3::ZERO);
        // One 4096³ tile: 2³⁶ voxels even before upsampling.
        let tile = Tile {
            origin: IVec3::ZERO,
            size: 4096,
            value: 1.0,
        };
        let huge = BrickMap::new(Vec::new(), vec![tile]);
        let error = upsample(&huge, &transform, 2).err().unwrap().to_string();
        assert!(error.contains("voxels"), "{error}");
        // One leaf near the edge of the i32 range: ×4 would wrap around.
        let far = BrickMap::new(
            vec![Leaf {
                origin: IVec3::new(1 << 30, 0, 0),
                values: [1.0; BRICK_VOXELS],
                active: [u64::MAX; 8],
            }],
            Vec::new(),
        );
        let error = upsample(&far, &transform, 4).err().unwrap().to_string();
        assert!(error.contains("32-bit"), "{error}");
        assert!(upsample(&far, &transform, 1).is_ok());
    }
}
