//! Coarse majorant grid and the 3D DDA that walks it (after pbrt-v4's `DDAMajorantIterator`).
//!
//! Cell `c` of a grid with cell edge `S` voxels covers the voxels `c·S .. c·S+S-1`, i.e. the
//! continuous index range `[c·S − ½, c·S + S − ½)`. A trilinear lookup anywhere in it reads voxels
//! `c·S − 1 ..= c·S + S` (the one-voxel apron), so the cell's majorant is the maximum σt over that
//! range; a nearest lookup reads a subset. `--majorant global` is the same walk over one cell that
//! spans the whole medium.

use glam::{IVec3, Vec3};

use crate::volume::brickmap::{leaf_offset, BrickMap, BRICK_VOXELS};

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
pub enum MajorantMode {
    /// One majorant per coarse cell of the grid (fast; the default).
    #[default]
    Grid,
    /// One majorant for the whole medium (the baseline for speed comparisons).
    Global,
}

crate::display_as_value_enum!(MajorantMode);

/// How a medium is tracked: the majorant mode and, for the grid, its cell edge in voxels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Majorant {
    pub mode: MajorantMode,
    pub cell_voxels: u32,
}

impl Majorant {
    pub const fn grid(cell_voxels: u32) -> Self {
        Majorant {
            mode: MajorantMode::Grid,
            cell_voxels,
        }
    }

    pub const fn global() -> Self {
        Majorant {
            mode: MajorantMode::Global,
            cell_voxels: 0,
        }
    }
}

#[derive(Clone)]
pub struct MajorantGrid {
    /// Continuous index coordinates of cell (0,0,0)'s low corner, and the cell edges.
    origin: Vec3,
    cell_size: Vec3,
    inv_cell_size: Vec3,
    dims: IVec3,
    /// σt majorant per cell, x-major like the brick slots.
    sigma_max: Vec<f32>,
}

/// One stretch of a ray inside one majorant cell: `[t0, t1)` in world distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MajorantSegment {
    pub t0: f32,
    pub t1: f32,
    pub sigma_max: f32,
}

impl MajorantGrid {
    /// `bounds` is the medium's continuous index box; values are multiplied by `density_scale`.
    pub fn build(
        bricks: &BrickMap,
        bounds: (Vec3, Vec3),
        density_scale: f32,
        majorant: Majorant,
    ) -> Self {
        match majorant.mode {
            MajorantMode::Global => {
                let extent = (bounds.1 - bounds.0).max(Vec3::splat(1e-6));
                MajorantGrid {
                    origin: bounds.0,
                    cell_size: extent,
                    inv_cell_size: extent.recip(),
                    dims: IVec3::ONE,
                    sigma_max: vec![bricks.max_value().max(0.0) * density_scale],
                }
            }
            MajorantMode::Grid => Self::build_cells(
                bricks,
                bounds,
                density_scale,
                majorant.cell_voxels.max(1) as i32,
            ),
        }
    }

    fn build_cells(bricks: &BrickMap, bounds: (Vec3, Vec3), density_scale: f32, s: i32) -> Self {
        // Voxel centres inside the box run from ceil(lo) to floor(hi); their cells span the box.
        let first_voxel = bounds.0.ceil().as_ivec3();
        let last_voxel = bounds.1.floor().as_ivec3();
        let c_lo = first_voxel.div_euclid(IVec3::splat(s));
        let c_hi = last_voxel.div_euclid(IVec3::splat(s));
        let dims = (c_hi - c_lo + 1).max(IVec3::ONE);
        let mut grid = MajorantGrid {
            origin: (c_lo * s).as_vec3() - 0.5,
            cell_size: Vec3::splat(s as f32),
            inv_cell_size: Vec3::splat(1.0 / s as f32),
            dims,
            sigma_max: vec![0.0; (dims.x * dims.y * dims.z) as usize],
        };
        // Voxel v lies in the apron-grown footprint of cells ceil((v − S)/S) ..= floor((v + 1)/S).
        let mut raise = |v_lo: IVec3, v_hi: IVec3, value: f32| {
            let lo = ((v_lo - s).as_vec3() / s as f32)
                .ceil()
                .as_ivec3()
                .max(c_lo)
                - c_lo;
            let hi = (v_hi + 1).div_euclid(IVec3::splat(s)).min(c_hi) - c_lo;
            for x in lo.x..=hi.x {
                for y in lo.y..=hi.y {
                    for z in lo.z..=hi.z {
                        let cell = &mut grid.sigma_max[((x * dims.y + y) * dims.z + z) as usize];
                        *cell = cell.max(value * density_scale);
                    }
                }
            }
        };
        for leaf in bricks.leaves() {
            for o in 0..BRICK_VOXELS {
                let value = leaf.values[o];
                if value > 0.0 {
                    let v = leaf.origin
                        + IVec3::new((o >> 6) as i32, ((o >> 3) & 7) as i32, (o & 7) as i32);
                    debug_assert_eq!(leaf_offset(v - leaf.origin), o);
                    raise(v, v, value);
                }
            }
        }
        for tile in bricks.tiles() {
            if tile.value > 0.0 {
                raise(
                    tile.origin,
                    tile.origin + IVec3::splat(tile.size as i32 - 1),
                    tile.value,
                );
            }
        }
        grid
    }

    pub fn cell_count(&self) -> usize {
        self.sigma_max.len()
    }

    pub fn memory_bytes(&self) -> usize {
        self.sigma_max.len() * std::mem::size_of::<f32>() + std::mem::size_of::<Self>()
    }

    /// Walks the cells the index-space ray `o + t·d` crosses for `t` in `[t0, t1)`.
    #[inline]
    pub fn walk(&self, o: Vec3, d: Vec3, t0: f32, t1: f32) -> DdaWalk<'_> {
        let p = (o + d * t0 - self.origin) * self.inv_cell_size;
        let cell = crate::volume::brickmap::floor_ivec3(p).clamp(IVec3::ZERO, self.dims - 1);
        let mut next_t = Vec3::splat(f32::INFINITY);
        let mut delta_t = Vec3::splat(f32::INFINITY);
        let mut step = IVec3::ZERO;
        for a in 0..3 {
            if d[a] > 0.0 {
                step[a] = 1;
                delta_t[a] = self.cell_size[a] / d[a];
                next_t[a] = t0 + ((cell[a] + 1) as f32 - p[a]) * delta_t[a];
            } else if d[a] < 0.0 {
                step[a] = -1;
                delta_t[a] = -self.cell_size[a] / d[a];
                next_t[a] = t0 + (p[a] - cell[a] as f32) * delta_t[a];
            }
        }
        DdaWalk {
            grid: self,
            t: t0,
            t_end: t1,
            cell,
            step,
            next_t,
            delta_t,
        }
    }
}

pub struct DdaWalk<'a> {
    grid: &'a MajorantGrid,
    t: f32,
    t_end: f32,
    cell: IVec3,
    step: IVec3,
    next_t: Vec3,
    delta_t: Vec3,
}

impl Iterator for DdaWalk<'_> {
    type Item = MajorantSegment;

    #[inline]
    fn next(&mut self) -> Option<MajorantSegment> {
        if self.t >= self.t_end {
            return None;
        }
        let dims = self.grid.dims;
        let c = self.cell;
        let sigma_max = self.grid.sigma_max[((c.x * dims.y + c.y) * dims.z + c.z) as usize];
        // Step along the axis whose boundary comes first.
        let a = if self.next_t.x < self.next_t.y {
            if self.next_t.x < self.next_t.z {
                0
            } else {
                2
            }
        } else if self.next_t.y < self.next_t.z {
            1
        } else {
            2
        };
        let t1 = self.next_t[a].min(self.t_end);
        let segment = MajorantSegment {
            t0: self.t,
            t1,
            sigma_max,
        };
        self.t = t1;
        self.cell[a] += self.step[a];
        self.next_t[a] += self.delta_t[a];
        if self.cell[a] < 0 || self.cell[a] >= dims[a] {
            self.t_end = t1; // left the grid
        }
        Some(segment)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::brickmap::BrickMapBuilder;

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
        let grid = MajorantGrid::build(&m, bounds, 2.0, Majorant::grid(8));
        assert_eq!(grid.dims, IVec3::splat(3));
        let mut state = 12345u64;
        for _ in 0..20000 {
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
}
