//! Majorants refined along the ray where a cell's bound is loose: the work of a walk follows the
//! medium's real optical structure, not its loosest cell.
//!
//! A majorant cell is only as good as its max/min ratio: one hot voxel makes every ray that crosses
//! its cell take about σ̄·ℓ null collisions (10⁶ per cell for a voxel 10⁶ times its neighbours). So a
//! stretch whose majorant optical depth σ̄·Δt exceeds `SPLIT_DEPTH` is refined, lazily and nearest
//! first (a walk that ends at a collision never refines what lies beyond):
//!
//! 1. in a cell with hot voxels (`volume::hot_spots`), the stretch is first cut where the ray
//!    enters and leaves their reach; beside it the rest of the cell's bound holds;
//! 2. a stretch is halved, and a half that spans at most two lookup cells per axis (the cells
//!    between voxel centres that trilinear lookups read, or the voxels of nearest ones) gets the
//!    exact maximum of the field over its box: per trilinear cell the field is multilinear, so its
//!    maximum over the part of the box in that cell sits at one of that part's corners. Longer
//!    halves keep their parent's bound until they are short enough;
//! 3. halves are halved again while that tightens the bound by a quarter and the stretch would
//!    still cost more than `MIN_SPLIT_DEPTH` tentative collisions, or while it would cost more
//!    than `KEEP_SPLITTING_DEPTH`.
//!
//! Near a hot voxel the bound stays high; where the ray passes beside it, or enters the ramp at the
//! edge of its trilinear reach, the bound falls with the field. Every bound is a true majorant of
//! every lookup in the stretch, so delta tracking stays exact and ratio tracking unbiased; only the
//! random numbers' use changes. A dense region (σ̄·Δt large because the medium really is that
//! dense) costs a few halvings: real collisions end the walk at once.

use glam::{IVec3, Vec3};

use crate::volume::brickmap::floor_ivec3;
use crate::volume::medium::Medium;
use crate::volume::ray::{Filter, IndexRay, MajorantSegment};

/// Above this majorant optical depth a stretch is halved even where the last halving did not
/// tighten its bound.
const KEEP_SPLITTING_DEPTH: f32 = 16.0;
/// Once refining, a stretch is refined further only while it would cost more than this many
/// tentative collisions.
const MIN_SPLIT_DEPTH: f32 = 2.0;
/// Pending pieces per majorant cell: enough for the halvings of any stretch; when full, a piece is
/// walked with the bound it has (still a majorant).
const STACK: usize = 48;
/// The box of a stretch is widened by this many ulps of its coordinates. `ray.at` is monotone in t
/// (f32 rounding is), so every lookup point of a stretch already lies in the box of its ends; the
/// pad only absorbs the different rounding of a lookup's trilinear weights. It must stay tiny:
/// where the field jumps by 10⁶ within a voxel, every 10⁻³ voxel of pad is hundreds of
/// tentative collisions.
const PAD_ULPS: f32 = 4.0;

/// The cells of the lookups a stretch can make: `first ..= last`, inside the box `[lo, hi]`.
struct StretchBox {
    lo: Vec3,
    hi: Vec3,
    first: IVec3,
    last: IVec3,
}

impl StretchBox {
    /// Cells per axis (in i64: across a huge tile the count overflows an i32).
    fn cells(&self) -> glam::I64Vec3 {
        self.last.as_i64vec3() - self.first.as_i64vec3() + glam::I64Vec3::ONE
    }
}

/// The segments of `inner`, with loose ones split and tightened (in order along the ray).
pub struct Refine<'a, I> {
    inner: I,
    medium: &'a Medium,
    ray: &'a IndexRay,
    /// Halves still to visit, the nearest on top.
    pending: [MajorantSegment; STACK],
    len: usize,
    /// The corner values of the trilinear cell bounded last: halving a stretch reads its cell
    /// again.
    corners: Option<(IVec3, [f32; 8])>,
}

impl<'a, I> Refine<'a, I> {
    pub fn new(inner: I, medium: &'a Medium, ray: &'a IndexRay) -> Self {
        let empty = MajorantSegment {
            t0: 0.0,
            t1: 0.0,
            sigma_max: 0.0,
        };
        Refine {
            inner,
            medium,
            ray,
            pending: [empty; STACK],
            len: 0,
            corners: None,
        }
    }

    /// Cells are offset by this from integer coordinates: a trilinear lookup reads the cell
    /// `[k, k + 1)` between voxel centres, a nearest one the voxel `[k − ½, k + ½)`.
    fn cell_shift(&self) -> f32 {
        match self.medium.filter {
            Filter::Trilinear => 0.0,
            Filter::Nearest => 0.5,
        }
    }

    fn stretch_box(&self, t0: f32, t1: f32) -> StretchBox {
        let (a, b) = (self.ray.at(t0), self.ray.at(t1));
        let pad = PAD_ULPS * f32::EPSILON * (1.0 + a.abs().max(b.abs()).max_element());
        let (lo, hi) = (a.min(b) - pad, a.max(b) + pad);
        let shift = Vec3::splat(self.cell_shift());
        StretchBox {
            lo,
            hi,
            first: floor_ivec3(lo + shift),
            last: floor_ivec3(hi + shift),
        }
    }

    /// The largest σt a lookup in the box can see; the box spans at most two cells per axis.
    fn box_max(&mut self, bx: &StretchBox) -> f32 {
        let mut max = 0.0f32;
        for x in bx.first.x..=bx.last.x {
            for y in bx.first.y..=bx.last.y {
                for z in bx.first.z..=bx.last.z {
                    let cell = IVec3::new(x, y, z);
                    max = max.max(match self.medium.filter {
                        Filter::Trilinear => self.cell_max(cell, bx.lo, bx.hi),
                        Filter::Nearest => self.medium.grid.voxel(cell),
                    });
                }
            }
        }
        self.medium.density_scale * max
    }

    /// The exact maximum of the trilinear field over the part of `[lo, hi]` inside the cell
    /// between voxel centres `base` and `base + 1`: the field is multilinear there, so the maximum
    /// sits at one of that part's eight corners.
    fn cell_max(&mut self, base: IVec3, lo: Vec3, hi: Vec3) -> f32 {
        let c = match self.corners {
            Some((cached, c)) if cached == base => c,
            _ => {
                let c = self.medium.grid.cell_corners(base);
                self.corners = Some((base, c));
                c
            }
        };
        let (f_lo, f_hi) = (
            (lo - base.as_vec3()).clamp(Vec3::ZERO, Vec3::ONE),
            (hi - base.as_vec3()).clamp(Vec3::ZERO, Vec3::ONE),
        );
        // The field at the part's corners, interpolated separably (z, then y, then x, as a lookup
        // does): [lo, hi] along z for each of the 4 edges, then along y, then along x.
        let lerp = |a: f32, b: f32, f: f32| a + (b - a) * f;
        let z: [[f32; 2]; 4] =
            std::array::from_fn(|e| [f_lo.z, f_hi.z].map(|f| lerp(c[2 * e], c[2 * e + 1], f)));
        let y: [[[f32; 2]; 2]; 2] = std::array::from_fn(|x| {
            std::array::from_fn(|iz| {
                [f_lo.y, f_hi.y].map(|f| lerp(z[2 * x][iz], z[2 * x + 1][iz], f))
            })
        });
        let mut max = 0.0f32;
        for (&y0, &y1) in y[0].iter().flatten().zip(y[1].iter().flatten()) {
            for f in [f_lo.x, f_hi.x] {
                max = max.max(lerp(y0, y1, f));
            }
        }
        max
    }

    /// The largest σt a lookup on `[t0, t1]` can see, or None when the stretch spans more than two
    /// cells on some axis (too long to bound cheaply; it is halved first).
    fn bound(&mut self, t0: f32, t1: f32) -> Option<f32> {
        let bx = self.stretch_box(t0, t1);
        (bx.cells().max_element() <= 2).then(|| self.box_max(&bx))
    }

    /// `seg` split in two halves with their own bounds, if that tightens either.
    fn split(&mut self, seg: MajorantSegment) -> Option<[MajorantSegment; 2]> {
        if seg.sigma_max * (seg.t1 - seg.t0) <= MIN_SPLIT_DEPTH {
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
        // An unbounded half (too long) counts as not tightening: long stretches are only halved
        // while costly, as a dense medium's are.
        let pays = |b: Option<f32>| b.is_some_and(|b| b < 0.75 * seg.sigma_max);
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
                let seg = self.inner.next()?;
                // A cell with hot voxels: cut at their reach first; beside it the rest's bound.
                let hot = &self.medium.majorant.hot_spots;
                match (!hot.is_empty())
                    .then(|| hot.split(seg, self.ray, self.medium.filter))
                    .flatten()
                {
                    Some([before, inside, after]) => {
                        self.pending[..3].copy_from_slice(&[after, inside, before]);
                        self.len = 3;
                        continue;
                    }
                    None => seg,
                }
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
    use crate::volume::majorant::Majorant;
    use crate::volume::majorant_walk::Walk;
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
                    Walk::Clusters(s) => s.collect::<Vec<_>>(),
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

/// The cuts at hot spots (`volume::hot_spots`), on the walks of whole media: they need the
/// modules above `hot_spots` that build the grid, the medium and the walk.
#[cfg(test)]
mod hot_spot_tests {
    use super::*;
    use crate::volume::brickmap::BrickMap;
    use crate::volume::majorant::Majorant;
    use crate::volume::majorant_walk::Walk;
    use crate::volume::transform::IndexTransform;
    use glam::DVec3;
    use rand::{Rng, SeedableRng};

    fn medium(filter: Filter, hot: impl Fn(IVec3) -> Option<f32>) -> Medium {
        let grid = BrickMap::block(16, |v| hot(v).unwrap_or(1.0 + 0.05 * v.y as f32));
        let transform = IndexTransform::uniform(0.5, DVec3::ZERO);
        Medium::new(grid, transform, 2.0, filter, Majorant::grid(4))
    }

    /// Along random rays through a block with a hot voxel and a hot 2³ cluster, the pieces a hot
    /// cell's stretch is cut into tile it in order, bound every lookup on them, and beside the
    /// hot voxels fall to the rest of the cell (both filters).
    #[test]
    fn pieces_tile_the_stretch_and_bound_every_lookup() {
        let hot = |v: IVec3| {
            let cluster = (v - IVec3::new(3, 12, 5)).cmpge(IVec3::ZERO).all()
                && (v - IVec3::new(3, 12, 5)).cmplt(IVec3::splat(2)).all();
            (v == IVec3::splat(8) || cluster).then_some(1e6)
        };
        let mut rng = rand::rngs::SmallRng::seed_from_u64(3);
        for filter in [Filter::Trilinear, Filter::Nearest] {
            let medium = medium(filter, hot);
            let spots = &medium.majorant.hot_spots;
            assert!(spots.len() >= 2, "{filter}: {} hot cells", spots.len());
            let (mut split, mut beside) = (0, 0);
            for _ in 0..400 {
                let aim = [IVec3::splat(8), IVec3::new(4, 13, 6)][rng.gen_range(0..2)].as_vec3();
                let aim = aim + (Vec3::new(rng.gen(), rng.gen(), rng.gen()) - 0.5) * 5.0;
                let d = (Vec3::new(rng.gen(), rng.gen(), rng.gen()) - 0.5).normalize();
                let ray = IndexRay {
                    o: aim - 20.0 * d,
                    d: d * 2.0,
                };
                let Some((t0, t1)) = medium.intersect(&ray) else {
                    continue;
                };
                let segments: Vec<MajorantSegment> =
                    match medium.majorant.walk(ray.o, ray.d, t0, t1) {
                        Walk::Flat(s) => s.collect(),
                        Walk::Clusters(s) => s.collect(),
                        Walk::Blocks(s) => s.collect(),
                    };
                for seg in segments {
                    let Some(pieces) = spots.split(seg, &ray, filter) else {
                        continue;
                    };
                    split += 1;
                    assert_eq!((pieces[0].t0, pieces[2].t1), (seg.t0, seg.t1));
                    assert!(pieces
                        .windows(2)
                        .all(|w| w[0].t1 == w[1].t0 && w[0].t0 <= w[0].t1));
                    // An empty piece is crossed without a lookup.
                    for p in pieces.into_iter().filter(|p| p.t1 > p.t0) {
                        beside += (p.sigma_max < 1e-3 * seg.sigma_max) as usize;
                        for k in 0..=64 {
                            let t = p.t0 + (p.t1 - p.t0) * k as f32 / 64.0;
                            let sigma = medium.sigma_t(ray.at(t.min(p.t1)));
                            assert!(
                                sigma <= p.sigma_max * (1.0 + 1e-5),
                                "{filter}: σ {sigma} > σ̄ {} at t {t} in {p:?} of {seg:?}",
                                p.sigma_max
                            );
                        }
                    }
                }
            }
            assert!(
                split > 100 && beside > split / 4,
                "{filter}: {split} split, {beside} beside"
            );
        }
    }

    /// A smooth medium has no hot spots: nothing to cut, nothing kept.
    #[test]
    fn a_smooth_medium_has_none() {
        let medium = medium(Filter::Trilinear, |_| None);
        assert!(medium.majorant.hot_spots.is_empty());
    }
}
