//! Tests of `majorant_walk`: every layout's walk bounds every lookup, and the clusters' walk
//! agrees with one flat array's.

use super::*;
use crate::volume::brickmap::{BrickMap, BrickMapBuilder};
use crate::volume::hot_spots::MajorantCells;
use crate::volume::majorant::Majorant;

#[test]
fn majorant_bounds_every_trilinear_lookup() {
    // A hot voxel next to a cell boundary must raise the neighbouring cell too (the apron).
    let mut b = BrickMapBuilder::new();
    for x in 0..24 {
        for y in 0..24 {
            for z in 0..24 {
                let hot = (x, y, z) == (7, 8, 15) || (x, y, z) == (16, 3, 3);
                b.set(
                    IVec3::new(x, y, z),
                    if hot {
                        9.0
                    } else {
                        0.1 * ((x * 7 + y * 3 + z) % 5) as f32
                    },
                    true,
                );
            }
        }
    }
    let m = b.build();
    let bounds = (Vec3::splat(-0.5), Vec3::splat(23.5));
    let flat = MajorantGrid::build_cells(&m, bounds, 2.0, 8, u64::MAX);
    let blocks = MajorantGrid::build_cells(&m, bounds, 2.0, 8, 0);
    assert_eq!((flat.cell_count(), flat.blocks.len()), (27, 0));
    assert_eq!((blocks.flat.len(), blocks.blocks.len()), (0, 1));
    let mut state = 12345u64;
    for k in 0..40000 {
        let grid = if k % 2 == 0 { &flat } else { &blocks };
        let mut r = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let o = Vec3::new(r(), r(), r()) * 24.0 - 0.5;
        let d = (Vec3::new(r(), r(), r()) - 0.5).normalize();
        let exit = (0..3)
            .map(|a| {
                if d[a] > 0.0 {
                    (23.5 - o[a]) / d[a]
                } else {
                    (-0.5 - o[a]) / d[a]
                }
            })
            .fold(f32::INFINITY, f32::min);
        let mut covered = 0.0;
        for seg in grid.walk(o, d, 0.0, exit) {
            assert!(seg.t1 >= seg.t0);
            covered += seg.t1 - seg.t0;
            for k in 0..=4 {
                let t = seg.t0 + (seg.t1 - seg.t0) * (k as f32 + 0.5) / 5.0;
                let sigma = 2.0 * m.trilinear(o + d * t);
                assert!(
                    sigma <= seg.sigma_max + 1e-5,
                    "σ {sigma} > majorant {} at {}",
                    seg.sigma_max,
                    o + d * t
                );
            }
        }
        assert!(
            (covered - exit).abs() < 1e-3 * exit.max(1.0),
            "segments cover {covered} of {exit}"
        );
    }
}

/// The segments of majorant > 0 two grids of the same data yield for one ray, which must agree
/// (every segment of either must run forward); how many there were.
fn same_occupied_segments(
    a: &MajorantGrid,
    b: &MajorantGrid,
    ray: (Vec3, Vec3, f32, f32),
) -> usize {
    let (o, d, t0, t1) = ray;
    let occupied = |grid: &MajorantGrid| -> Vec<MajorantSegment> {
        let segments: Vec<_> = grid.walk(o, d, t0, t1).collect();
        assert!(segments.iter().all(|s| s.t1 >= s.t0), "{segments:?}");
        segments
            .into_iter()
            .filter(|s| s.sigma_max > 0.0 && s.t1 > s.t0)
            .collect()
    };
    let (a, b) = (occupied(a), occupied(b));
    assert_eq!(a.len(), b.len(), "ray {o} {d} [{t0}, {t1})");
    for (s, t) in a.iter().zip(&b) {
        assert_eq!(s.sigma_max, t.sigma_max);
        // The whole box's DDA adds up its boundaries from further away: f32 rounding.
        let close = |x: f32, y: f32| (x - y).abs() < 1e-3 + 1e-4 * x.abs();
        assert!(close(s.t0, t.t0) && close(s.t1, t.t1), "{s:?} {t:?}");
    }
    a.len()
}

/// Three lumpy clusters far apart (or the first alone).
fn clusters(count: usize) -> BrickMap {
    let mut b = BrickMapBuilder::new();
    for (k, centre) in [IVec3::ZERO, IVec3::new(300, 0, 0), IVec3::new(0, 200, 150)]
        .into_iter()
        .enumerate()
        .take(count)
    {
        for v in 0..27 * 8 {
            let p = centre + IVec3::new(v % 6, (v / 6) % 6, v / 36) * 3;
            b.set(p, 1.0 + ((v * 7 + k as i32) % 5) as f32, true);
        }
    }
    b.build()
}

#[test]
fn clusters_walk_the_occupied_cells_of_the_whole_box() {
    // The walk over the clusters' boxes gives the segments of majorant > 0 that the walk over
    // one array spanning all of them gives, and the same cell majorants.
    let m = clusters(3);
    let (lo, hi) = m.active_bounds().unwrap();
    let bounds = (lo.as_vec3() - 0.5, hi.as_vec3() + 0.5);
    let whole = MajorantGrid::build_cells(&m, bounds, 1.5, 4, u64::MAX);
    let clustered = MajorantGrid::build_cells(&m, bounds, 1.5, 4, whole.cell_count() as u64 - 1);
    assert_eq!((whole.flat.len(), clustered.flat.len()), (1, 3));
    assert!(clustered.cell_count() * 100 < whole.cell_count());
    for x in -1..80 {
        for y in -1..55 {
            for z in -1..42 {
                let c = IVec3::new(x, y, z);
                assert_eq!(whole.cell_majorant(c), clustered.cell_majorant(c), "{c}");
            }
        }
    }
    let mut state = 777u64;
    let mut r = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    let size = hi.as_vec3() - lo.as_vec3();
    let mut crossed = 0;
    for k in 0..20000 {
        // From a cluster toward another, or from anywhere in the box anywhere; some along an
        // axis; some from a t0 inside the box to a t1 short of its exit.
        let o = if k % 2 == 0 {
            Vec3::new(r(), r(), r()) * 16.0
        } else {
            lo.as_vec3() + Vec3::new(r(), r(), r()) * size
        };
        let d = match k % 8 {
            0 | 4 => (Vec3::new(300.0, 0.0, 0.0) + Vec3::new(r(), r(), r()) * 16.0 - o).normalize(),
            1 => Vec3::X,
            3 => -Vec3::Z,
            _ => (Vec3::new(r(), r(), r()) - 0.5).normalize(),
        };
        let (t0, t1) = match k % 3 {
            0 => (0.0, f32::INFINITY),
            1 => (r() * 100.0, f32::INFINITY),
            _ => {
                let t0 = r() * 100.0;
                (t0, t0 + r() * 200.0)
            }
        };
        crossed += same_occupied_segments(&whole, &clustered, (o, d, t0, t1));
    }
    assert!(crossed > 20000, "{crossed}");
}

#[test]
fn a_box_smaller_than_the_medium_is_entered_where_the_ray_meets_it() {
    // Data in one corner of a medium given far wider bounds (as the optimiser's domain is):
    // one box around the data, walked from where a ray enters it, not from the medium's face.
    let m = clusters(1);
    let (lo, hi) = m.active_bounds().unwrap();
    let bounds = (lo.as_vec3() - 0.5, hi.as_vec3() + 400.5);
    let whole = MajorantGrid::build_cells(&m, bounds, 1.0, 4, u64::MAX);
    let boxed = MajorantGrid::build_cells(&m, bounds, 1.0, 4, whole.cell_count() as u64 - 1);
    assert_eq!(boxed.flat.len(), 1);
    assert!(boxed.flat[0].hi.cmplt(boxed.c_hi).all());
    let far = hi.as_vec3() + 350.0;
    let d = (lo.as_vec3() + 8.0 - far).normalize();
    let segments: Vec<_> = boxed.walk(far, d, 0.0, f32::INFINITY).collect();
    let first = segments.first().unwrap().t0;
    assert!(
        first > 400.0,
        "the walk began at {first}, outside the data's box"
    );
    assert!(same_occupied_segments(&whole, &boxed, (far, d, 0.0, f32::INFINITY)) > 0);
}

#[test]
fn global_mode_is_one_cell_with_the_grid_maximum() {
    let mut b = BrickMapBuilder::new();
    b.set(IVec3::new(3, 4, 5), 7.0, true);
    b.set(IVec3::new(30, 4, 5), 1.0, true);
    let m = b.build();
    let grid = MajorantGrid::build(
        &m,
        (Vec3::new(2.5, 3.5, 4.5), Vec3::new(30.5, 4.5, 5.5)),
        0.5,
        Majorant::global(),
    );
    assert_eq!(grid.cell_count(), 1);
    let segs: Vec<_> = grid
        .walk(Vec3::new(2.5, 4.0, 5.0), Vec3::X, 0.0, 28.0)
        .collect();
    assert_eq!(
        segs,
        vec![MajorantSegment {
            t0: 0.0,
            t1: 28.0,
            sigma_max: 3.5
        }]
    );
}
