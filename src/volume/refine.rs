//! Majorants refined along the ray where a cell's bound is loose: the work of a walk follows the
//! medium's real optical structure, not its loosest cell.
//!
//! A majorant cell is only as good as its max/min ratio: one hot voxel makes every ray that crosses
//! its cell take about σ̄·ℓ null collisions (10⁶ per cell for a voxel 10⁶ times its neighbours). So a
//! stretch whose majorant optical depth σ̄·Δt exceeds `SPLIT_DEPTH` is split in halves, and each
//! half gets the bound of the voxels a lookup inside it can read (its index-space bounding box,
//! plus the trilinear apron): near the hot voxel the bound stays high, where the ray passes beside
//! it the bound drops to its neighbours'. Halves are split again while that keeps paying (a child
//! at least a quarter below its parent, or while the stretch would still cost more than
//! `KEEP_SPLITTING_DEPTH` tentative collisions), at most `STACK / 2` levels deep. The bound is a true majorant of every lookup in the stretch, so delta tracking stays
//! exact and ratio tracking unbiased; only the random numbers' use changes.
//!
//! Dense regions (σ̄·Δt large but the medium really that dense) cost one split: their children
//! are no tighter, so the stretch is walked as it was, and real collisions end the walk quickly.

use glam::{IVec3, Vec3};

use crate::volume::brickmap::{corner, floor_ivec3};
use crate::volume::majorant::MajorantSegment;
use crate::volume::medium::{Filter, IndexRay, Medium};

/// Majorant optical depth above which a stretch is worth refining (a walk through it takes about
/// this many tentative collisions).
pub const SPLIT_DEPTH: f32 = 16.0;
/// Above this majorant optical depth a stretch is split even where the last split did not tighten
/// its bound.
const KEEP_SPLITTING_DEPTH: f32 = 16.0;
/// A half is bounded only if a lookup in it reads at most this many voxels (about 1.5 voxels of
/// ray); larger halves are split before they are bounded.
const MAX_BOUND_VOXELS: i32 = 64;
/// Pending halves per cell: a depth-first split of at most this many levels.
const STACK: usize = 24;
/// A lookup at a point that rounding moved just outside the stretch's box still reads a counted
/// voxel.
const PAD: f32 = 1e-3;

/// The segments of `inner`, with loose ones split and tightened (in order along the ray).
pub struct Refine<'a, I> {
    inner: I,
    medium: &'a Medium,
    ray: &'a IndexRay,
    /// Halves still to visit, the nearest on top.
    pending: [MajorantSegment; STACK],
    len: usize,
}

impl<'a, I> Refine<'a, I> {
    pub fn new(inner: I, medium: &'a Medium, ray: &'a IndexRay) -> Self {
        Refine {
            inner,
            medium,
            ray,
            pending: [MajorantSegment {
                t0: 0.0,
                t1: 0.0,
                sigma_max: 0.0,
            }; STACK],
            len: 0,
        }
    }

    /// The largest σt a lookup on `[t0, t1]` can see, or None when the stretch reads too many
    /// voxels to bound cheaply.
    fn bound(&self, t0: f32, t1: f32) -> Option<f32> {
        let (a, b) = (self.ray.at(t0), self.ray.at(t1));
        let (lo, hi) = (a.min(b) - PAD, a.max(b) + PAD);
        let (first, last) = match self.medium.filter {
            Filter::Trilinear => (floor_ivec3(lo), floor_ivec3(hi) + IVec3::ONE),
            Filter::Nearest => (
                floor_ivec3(lo + Vec3::splat(0.5)),
                floor_ivec3(hi + Vec3::splat(0.5)),
            ),
        };
        if self.medium.filter == Filter::Trilinear && first + IVec3::ONE == last {
            return Some(self.medium.density_scale * self.trilinear_max(first, lo, hi));
        }
        // In i64: a stretch across a huge tile spans more voxels than an i32 product can count.
        let extent = (last - first + IVec3::ONE).as_i64vec3();
        if extent.x * extent.y * extent.z > MAX_BOUND_VOXELS as i64 {
            return None;
        }
        let grid = &self.medium.grid;
        let mut max = 0.0f32;
        for x in first.x..=last.x {
            for y in first.y..=last.y {
                for z in first.z..=last.z {
                    max = max.max(grid.voxel(IVec3::new(x, y, z)));
                }
            }
        }
        Some(self.medium.density_scale * max)
    }

    /// The exact maximum of the trilinear field over the box `[lo, hi]` inside the cell between
    /// voxel centres `base` and `base + 1`: the field is multilinear there, so its maximum over a
    /// box sits at one of the box's corners. This is what lets the bound fall off with the
    /// distance from a hot voxel instead of covering its whole apron.
    fn trilinear_max(&self, base: IVec3, lo: Vec3, hi: Vec3) -> f32 {
        let grid = &self.medium.grid;
        let values: [f32; 8] = std::array::from_fn(|k| grid.voxel(base + corner(k)));
        let (f_lo, f_hi) = (
            (lo - base.as_vec3()).clamp(Vec3::ZERO, Vec3::ONE),
            (hi - base.as_vec3()).clamp(Vec3::ZERO, Vec3::ONE),
        );
        let mut max = 0.0f32;
        for k in 0..8 {
            let c = corner(k);
            let f = Vec3::new(
                if c.x == 1 { f_hi.x } else { f_lo.x },
                if c.y == 1 { f_hi.y } else { f_lo.y },
                if c.z == 1 { f_hi.z } else { f_lo.z },
            );
            let mut value = 0.0f32;
            for (j, &v) in values.iter().enumerate() {
                let o = corner(j).as_vec3();
                let w = (o * f + (Vec3::ONE - o) * (Vec3::ONE - f)).element_product();
                value += w * v;
            }
            max = max.max(value);
        }
        max
    }

    /// `seg` split in two halves with their own bounds, if that tightens either.
    fn split(&self, seg: MajorantSegment) -> Option<[MajorantSegment; 2]> {
        if seg.sigma_max * (seg.t1 - seg.t0) <= SPLIT_DEPTH {
            return None;
        }
        let mid = 0.5 * (seg.t0 + seg.t1);
        if !(mid > seg.t0 && mid < seg.t1) {
            return None; // below f32 resolution
        }
        let (near, far) = (self.bound(seg.t0, mid), self.bound(mid, seg.t1));
        // Where bounding has begun and no longer pays, the medium may simply be that dense: stop,
        // unless the stretch would cost more than `KEEP_SPLITTING_DEPTH` tentative collisions (a
        // hot voxel can sit in both halves' boxes while the ray passes beside it; the boxes shrink
        // with the halves). A really dense stretch ends the walk at its first collision, so the
        // halves beyond it are never made.
        let pays = |b: Option<f32>| b.is_none_or(|b| b < 0.75 * seg.sigma_max);
        if !pays(near) && !pays(far) && seg.sigma_max * (seg.t1 - seg.t0) <= KEEP_SPLITTING_DEPTH {
            return None;
        }
        let half = |t0: f32, t1: f32, bound: Option<f32>| MajorantSegment {
            t0,
            t1,
            sigma_max: bound.map_or(seg.sigma_max, |b| b.min(seg.sigma_max)),
        };
        Some([half(seg.t0, mid, near), half(mid, seg.t1, far)])
    }
}

impl<I: Iterator<Item = MajorantSegment>> Iterator for Refine<'_, I> {
    type Item = MajorantSegment;

    #[inline]
    fn next(&mut self) -> Option<MajorantSegment> {
        loop {
            let seg = if self.len > 0 {
                self.len -= 1;
                self.pending[self.len]
            } else {
                self.inner.next()?
            };
            if self.len + 2 > STACK {
                return Some(seg);
            }
            match self.split(seg) {
                None => return Some(seg),
                Some([near, far]) => {
                    self.pending[self.len] = far;
                    self.pending[self.len + 1] = near;
                    self.len += 2;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::brickmap::BrickMap;
    use crate::volume::majorant::{Majorant, Walk};
    use crate::volume::transform::IndexTransform;
    use glam::DVec3;
    use rand::{Rng, SeedableRng};

    /// Along random rays through a block with one voxel 10⁶ times its neighbours, the refined
    /// segments tile the ray in order, bound every lookup (both filters), and cut the majorant
    /// optical depth of rays that pass beside the hot voxel by orders of magnitude.
    #[test]
    fn refined_segments_are_ordered_majorants_and_much_tighter() {
        let hot = IVec3::splat(6);
        let grid = BrickMap::block(12, |v| {
            if v == hot {
                1e6
            } else {
                1.0 + 0.1 * v.x as f32
            }
        });
        let mut rng = rand::rngs::SmallRng::seed_from_u64(9);
        for filter in [Filter::Trilinear, Filter::Nearest] {
            let medium = Medium::new(
                grid.clone(),
                IndexTransform::uniform(1.0, DVec3::ZERO),
                0.5,
                filter,
                Majorant::grid(4),
            );
            let (mut coarse_depth, mut refined_depth) = (0.0f64, 0.0f64);
            for _ in 0..300 {
                let o = Vec3::new(rng.gen(), rng.gen(), rng.gen()) * 11.0;
                let d = (Vec3::new(rng.gen(), rng.gen(), rng.gen()) - 0.5).normalize();
                let ray = IndexRay { o, d };
                let Some((t0, t1)) = medium.intersect(&ray) else {
                    continue;
                };
                let segments = || match medium.majorant.walk(ray.o, ray.d, t0, t1) {
                    Walk::Flat(s) => s.collect::<Vec<_>>(),
                    Walk::Blocks(s) => s.collect::<Vec<_>>(),
                };
                let coarse = segments();
                let refined: Vec<MajorantSegment> =
                    Refine::new(coarse.clone().into_iter(), &medium, &ray).collect();
                let mut t = coarse.first().map_or(t0, |s| s.t0);
                for s in &refined {
                    assert!(
                        (s.t0 - t).abs() <= 1e-5 * t.abs().max(1.0),
                        "gap at {t}: {s:?}"
                    );
                    assert!(s.t1 >= s.t0);
                    t = s.t1;
                    for k in 0..8 {
                        let u = s.t0 + (s.t1 - s.t0) * (k as f32 + 0.5) / 8.0;
                        let sigma = medium.sigma_t(ray.at(u));
                        assert!(
                            sigma <= s.sigma_max * (1.0 + 1e-5),
                            "{filter}: σt {sigma} > {s:?}"
                        );
                    }
                }
                let depth = |v: &[MajorantSegment]| {
                    v.iter()
                        .map(|s| (s.sigma_max * (s.t1 - s.t0)) as f64)
                        .sum::<f64>()
                };
                // Rays that pass beside the hot voxel, not through its footprint.
                let closest = (hot.as_vec3() - o).cross(d).length();
                if closest > 1.5 {
                    coarse_depth += depth(&coarse);
                    refined_depth += depth(&refined);
                }
            }
            assert!(
                refined_depth < 1e-2 * coarse_depth,
                "{filter}: refined {refined_depth:.3e} vs coarse {coarse_depth:.3e}"
            );
        }
    }

    /// A stretch across a huge constant tile spans more voxels than an i32 product can count: it is
    /// split without being bounded voxel by voxel, and the walk ends.
    #[test]
    fn a_huge_tile_is_refined_without_counting_its_voxels() {
        use crate::volume::brickmap::Tile;
        let grid = BrickMap::new(
            Vec::new(),
            vec![Tile {
                origin: IVec3::ZERO,
                size: 4096,
                value: 2.0,
            }],
        );
        let medium = Medium::new(
            grid,
            IndexTransform::uniform(1.0, DVec3::ZERO),
            1.0,
            Filter::Trilinear,
            Majorant::global(),
        );
        let ray = IndexRay {
            o: Vec3::splat(-0.5),
            d: Vec3::ONE.normalize(),
        };
        let (t0, t1) = medium.intersect(&ray).unwrap();
        let whole = MajorantSegment {
            t0,
            t1,
            sigma_max: 2.0,
        };
        let refined: Vec<_> = Refine::new(std::iter::once(whole), &medium, &ray).collect();
        // Splitting goes on while a stretch would cost more than KEEP_SPLITTING_DEPTH tentative
        // collisions (a walk through it ends at its first ones): about τ̄ / 64 pieces, in order.
        let depth = 2.0 * (t1 - t0);
        assert!(
            refined.len() as f32 <= 2.0 * depth / KEEP_SPLITTING_DEPTH + 2.0,
            "{}",
            refined.len()
        );
        assert!(refined.iter().all(|s| s.sigma_max == 2.0));
        assert!(refined.windows(2).all(|w| w[0].t1 == w[1].t0));
        assert_eq!((refined[0].t0, refined.last().unwrap().t1), (t0, t1));
    }
}
