//! Hot spots inside majorant cells: where a few voxels are far denser than the rest of their cell,
//! the cell's majorant is loose for every ray that passes beside them. Found once when the medium
//! is built, a hot spot records the box those voxels can reach and the majorant of the rest of the
//! cell, so that a walk crossing the cell splits its stretch at that box: beside the hot voxels it
//! walks with the rest's bound at no cost, and only the part inside the box is refined along the
//! ray (`volume::refine`).
//!
//! Only cells whose walk could need refining are examined (a crossing of the cell would cost more
//! than `SPLIT_DEPTH` tentative collisions), so a medium without hot spots pays a pass over its
//! majorant cells, not over its voxels.
//!
//! The tests cut the walks of whole media, so they sit with `refine`, the module that uses the cuts.

use glam::{IVec3, Vec3};

use crate::volume::brickmap::{floor_ivec3, BrickMap, BRICK_EDGE};
use crate::volume::ray::{Filter, IndexRay, MajorantSegment, SPLIT_DEPTH};
use crate::volume::sparse_index::KeyMap;

/// A voxel is hot when it exceeds this fraction of its cell's maximum.
const HOT_FRACTION: f32 = 1.0 / 8.0;
/// A hot spot is kept only if the rest of its cell is at most this fraction of the cell's maximum
/// (otherwise splitting at the hot box gains little).
const REST_FRACTION: f32 = 1.0 / 4.0;
/// A hot spot is kept only if its hot voxels' reach covers at most this fraction of the cell.
const MAX_REACH_FRACTION: f32 = 0.5;
/// Cells wider than this many voxels are not examined (their aprons are too large to scan).
const MAX_CELL_VOXELS: i32 = 8;

/// What finding hot spots needs of the majorant grid whose cells they sit in. A trait, because
/// that grid holds the hot spots it finds: `majorant` implements it, and this module, below
/// `majorant`, does not import it.
pub trait MajorantCells {
    /// Index-space corner of cell (0, 0, 0) and the inverse cell edges: cell `c` starts at
    /// `origin + c / inv_cell_size`.
    fn cell_geometry(&self) -> (Vec3, Vec3);
    /// Cell edge in voxels, or None for the global mode's single cell.
    fn cell_voxels(&self) -> Option<i32>;
    /// The cells of the medium's box (inclusive).
    fn cell_range(&self) -> (IVec3, IVec3);
    /// The majorant of cell `c` (0 outside the medium's box and where no data raised it).
    fn cell_majorant(&self, c: IVec3) -> f32;
}

/// The hot voxels of one majorant cell.
#[derive(Debug, Clone, Copy)]
pub struct HotSpot {
    /// The continuous index box of the cell: lookups inside it read only the cell's apron.
    cell_lo: Vec3,
    cell_hi: Vec3,
    /// The hot voxels' bounding box (voxel coordinates, inclusive).
    hot_lo: IVec3,
    hot_hi: IVec3,
    /// σt bound of every lookup in the cell that reads no hot voxel.
    rest: f32,
}

/// Hot spots by majorant cell.
#[derive(Clone, Default)]
pub struct HotSpots {
    spots: KeyMap<HotSpot>,
    /// The majorant grid's cell geometry (index space).
    origin: Vec3,
    inv_cell_size: Vec3,
}

impl HotSpots {
    /// The hot spots of `grid` in the cells of `majorant` (built from `grid`), for a medium in
    /// which no segment inside a voxel is longer than `voxel_diagonal` world units.
    pub fn find(grid: &BrickMap, majorant: &impl MajorantCells, voxel_diagonal: f32) -> Self {
        let (origin, inv_cell_size) = majorant.cell_geometry();
        let mut spots = HotSpots {
            spots: KeyMap::default(),
            origin,
            inv_cell_size,
        };
        let Some(s) = majorant.cell_voxels() else {
            return spots;
        };
        if s > MAX_CELL_VOXELS {
            return spots;
        }
        // A crossing of a cell is at most its diagonal long.
        let diagonal = s as f32 * voxel_diagonal;
        let mut seen = KeyMap::<()>::default();
        let (c_lo, c_hi) = majorant.cell_range();
        for leaf in grid.leaves() {
            // In i64: a leaf at the edge of the i32 range must not wrap around.
            let s64 = glam::I64Vec3::splat(s as i64);
            let origin = leaf.origin.as_i64vec3();
            let first = (origin - 1)
                .div_euclid(s64)
                .max(c_lo.as_i64vec3())
                .as_ivec3();
            let last = (origin + BRICK_EDGE as i64)
                .div_euclid(s64)
                .min(c_hi.as_i64vec3())
                .as_ivec3();
            for x in first.x..=last.x {
                for y in first.y..=last.y {
                    for z in first.z..=last.z {
                        let cell = IVec3::new(x, y, z);
                        let m = majorant.cell_majorant(cell);
                        if m * diagonal <= SPLIT_DEPTH || seen.insert(cell, ()).is_some() {
                            continue;
                        }
                        if let Some(spot) = hot_spot(grid, cell, s, m) {
                            spots.spots.insert(cell, spot);
                        }
                    }
                }
            }
        }
        spots
    }

    pub fn is_empty(&self) -> bool {
        self.spots.is_empty()
    }

    pub fn len(&self) -> usize {
        self.spots.len()
    }

    /// Bytes held by the table (its capacity, with a control byte per slot).
    pub fn memory_bytes(&self) -> usize {
        self.spots.capacity() * (std::mem::size_of::<(IVec3, HotSpot)>() + 1)
    }

    /// `seg` (a stretch of the walk inside one majorant cell) cut where the ray enters and leaves
    /// the reach of the cell's hot voxels: the pieces beside them get the rest's bound. Pieces in
    /// order along the ray; None when the cell has no hot spot (or rounding leaves no piece that
    /// is provably beside them).
    pub fn split(
        &self,
        seg: MajorantSegment,
        ray: &IndexRay,
        filter: Filter,
    ) -> Option<[MajorantSegment; 3]> {
        let mid = ray.at(0.5 * (seg.t0 + seg.t1));
        let cell = floor_ivec3((mid - self.origin) * self.inv_cell_size);
        let spot = self.spots.get(&cell)?;
        // Lookups outside this closed box read no hot voxel (a trilinear one at its faces gives
        // the hot corner a weight of exactly 0).
        let reach = match filter {
            Filter::Trilinear => 1.0,
            Filter::Nearest => 0.5,
        };
        let (lo, hi) = (spot.hot_lo.as_vec3() - reach, spot.hot_hi.as_vec3() + reach);
        // Where the ray is inside the hot box, widened a little so that rounding cannot put the
        // pieces beside it inside.
        let (mut ta, mut tb) = (seg.t0, seg.t1);
        for a in 0..3 {
            let inv = 1.0 / ray.d[a];
            let (mut near, mut far) = ((lo[a] - ray.o[a]) * inv, (hi[a] - ray.o[a]) * inv);
            if near > far {
                std::mem::swap(&mut near, &mut far);
            }
            if near.is_nan() || far.is_nan() {
                // Along the face: inside for every t, or never.
                if ray.o[a] < lo[a] || ray.o[a] > hi[a] {
                    (ta, tb) = (seg.t1, seg.t1);
                }
                continue;
            }
            ta = ta.max(near);
            tb = tb.min(far);
        }
        let slack = 1e-5 * (1.0 + seg.t0.abs().max(seg.t1.abs()));
        let (ta, tb) = if ta < tb {
            ((ta - slack).max(seg.t0), (tb + slack).min(seg.t1))
        } else {
            (seg.t1, seg.t1) // misses the hot box: all of it is beside
        };
        let beside = |t0: f32, t1: f32| {
            let (a, b) = (ray.at(t0), ray.at(t1));
            let (p_lo, p_hi) = (a.min(b), a.max(b));
            let in_cell = p_lo.cmpge(spot.cell_lo).all() && p_hi.cmple(spot.cell_hi).all();
            let apart = match filter {
                Filter::Trilinear => p_hi.cmple(lo).any() || p_lo.cmpge(hi).any(),
                // floor(p + ½) at the lower face is the hot voxel: strictly below it.
                Filter::Nearest => p_hi.cmplt(lo).any() || p_lo.cmpge(hi).any(),
            };
            t1 <= t0 || (in_cell && apart)
        };
        let piece = |t0: f32, t1: f32, sigma_max: f32| MajorantSegment { t0, t1, sigma_max };
        let (before, after) = (beside(seg.t0, ta), beside(tb, seg.t1));
        if !before && !after {
            return None;
        }
        let rest = spot.rest.min(seg.sigma_max);
        Some([
            piece(seg.t0, ta, if before { rest } else { seg.sigma_max }),
            piece(ta, tb, seg.sigma_max),
            piece(tb, seg.t1, if after { rest } else { seg.sigma_max }),
        ])
    }
}

/// The hot spot of cell `cell` (edge `s` voxels, majorant `majorant`), if its hot voxels stand
/// well above the rest.
fn hot_spot(grid: &BrickMap, cell: IVec3, s: i32, majorant: f32) -> Option<HotSpot> {
    // The apron in i64: a cell at the edge of the i32 range is left alone.
    let (first, last) = (
        cell.as_i64vec3() * s as i64 - 1,
        cell.as_i64vec3() * s as i64 + s as i64,
    );
    if first.min_element() < i32::MIN as i64 || last.max_element() > i32::MAX as i64 {
        return None;
    }
    let (first, last) = (first.as_ivec3(), last.as_ivec3());
    let mut apron = Vec::with_capacity(((s + 2) * (s + 2) * (s + 2)) as usize);
    for x in first.x..=last.x {
        for y in first.y..=last.y {
            for z in first.z..=last.z {
                let v = IVec3::new(x, y, z);
                apron.push((v, grid.voxel(v)));
            }
        }
    }
    let max = apron.iter().fold(0.0f32, |m, &(_, value)| m.max(value));
    let (mut hot_lo, mut hot_hi) = (IVec3::MAX, IVec3::MIN);
    let mut rest = 0.0f32;
    for &(v, value) in &apron {
        if value > HOT_FRACTION * max {
            hot_lo = hot_lo.min(v);
            hot_hi = hot_hi.max(v);
        } else {
            rest = rest.max(value);
        }
    }
    if rest > REST_FRACTION * max || hot_lo.cmpgt(hot_hi).any() {
        return None;
    }
    // Cell c spans the continuous index range [c·S − ½, c·S + S − ½).
    let cell_lo = (cell * s).as_vec3() - 0.5;
    let cell_hi = cell_lo + s as f32;
    // Worth a cut only where the hot voxels' reach leaves most of the cell beside it (not at the
    // edge of the data, where the whole cell is "hot" next to empty space).
    let reach_lo = (hot_lo.as_vec3() - 1.0).clamp(cell_lo, cell_hi);
    let reach_hi = (hot_hi.as_vec3() + 1.0).clamp(cell_lo, cell_hi);
    if (reach_hi - reach_lo).element_product() > MAX_REACH_FRACTION * (s as f32).powi(3) {
        return None;
    }
    Some(HotSpot {
        cell_lo,
        cell_hi,
        hot_lo,
        hot_hi,
        // The majorant is max × density_scale: the rest scaled alike, rounded up.
        rest: (rest * (majorant / max)).next_up(),
    })
}
