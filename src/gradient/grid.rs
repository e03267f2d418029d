//! Sparse accumulation of per-voxel gradients: blocks of 4³ voxels appear where gradient arrives.
//! The block index (a `SparseIndex`, memory proportional to the blocks touched, whatever the
//! bounding box) accepts the medium's block range (the active box plus the trilinear apron), so
//! every voxel a lookup can weight has a place; accumulation is a few array reads.
//!
//! Why 4³ and not the brick map's 8³: a gradient reaches every voxel that paths cross, empty space
//! included, and thinly at a few spp — on the cloud upsampled to 26 million voxels, 4 spp fill 12 %
//! of the touched 4³ blocks' voxels, and 8³ bricks stored 1.7× as many bytes (`cargo bench --bench
//! scaling`). Blocks live in
//! chunks of 256 (64 KiB of f32), so that a block costs its values and 12 bytes of origin, without a
//! heap allocation of its own.
//!
//! The value type is a parameter: a pass accumulates whole quanta (`Quanta`, integers, so that its
//! sum does not depend on the order samples arrive in: threads or processes), results are f32 or
//! f64, and runs are reduced into f64 grids, where sums over many runs keep their precision.

use std::ops::AddAssign;

use glam::IVec3;

use crate::volume::brickmap::{corner, floor_ivec3, leaf_offset, BrickMap, Leaf, BRICK_VOXELS};
use crate::volume::medium::Medium;
use crate::volume::sparse_index::{KeyMap, SparseIndex};

/// Voxels per block edge (log2), per block, and blocks per storage chunk.
const BLOCK_LOG2: i32 = 2;
/// Voxels per block edge.
pub const BLOCK_EDGE: i32 = 1 << BLOCK_LOG2;
const BLOCK_MASK: i32 = (1 << BLOCK_LOG2) - 1;
pub const BLOCK_VOXELS: usize = 1 << (3 * BLOCK_LOG2);
const CHUNK_BLOCKS: usize = 256;

/// Offset of voxel `local` (0..4 per axis) in its block, x-major like the leaves.
#[inline]
fn block_offset(local: IVec3) -> usize {
    ((local.x << (2 * BLOCK_LOG2)) | (local.y << BLOCK_LOG2) | local.z) as usize
}

#[inline]
fn offset_voxel(o: usize) -> IVec3 {
    let m = BLOCK_MASK as usize;
    IVec3::new(
        (o >> (2 * BLOCK_LOG2)) as i32,
        ((o >> BLOCK_LOG2) & m) as i32,
        (o & m) as i32,
    )
}

/// A value a gradient grid accumulates: quanta for a pass's splats, f32 or f64 for results.
pub trait Accumulator: Copy + Default + AddAssign + Send + Sync + 'static {
    fn from_f32(v: f32) -> Self;
    /// `v` with a dither `u` in [0, 1) for a type that rounds it (`Quanta`); others ignore `u`.
    #[inline]
    fn from_f32_dithered(v: f32, _u: f32) -> Self {
        Self::from_f32(v)
    }
    fn from_f64(v: f64) -> Self;
    fn to_f64(self) -> f64;
}

impl Accumulator for f32 {
    fn from_f32(v: f32) -> Self {
        v
    }
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
}

impl Accumulator for f64 {
    fn from_f32(v: f32) -> Self {
        v as f64
    }
    fn from_f64(v: f64) -> Self {
        v
    }
    fn to_f64(self) -> f64 {
        self
    }
}

/// A gradient in whole quanta of its pass (`GradientRun::quantum`). Integer sums are exact, hence
/// associative: the pass's result is the same whatever order its samples are added in, on any
/// number of threads or processes, where a floating-point sum would change in its last bits. A
/// sum beyond ±2⁶³ quanta saturates (`bands::quantum_for` says what headroom the quantum leaves).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Quanta(pub i64);

impl AddAssign for Quanta {
    #[inline]
    fn add_assign(&mut self, other: Quanta) {
        self.0 = self.0.saturating_add(other.0);
    }
}

impl Accumulator for Quanta {
    /// Rounded to the nearest quantum (`as` saturates, and maps NaN to 0).
    #[inline]
    fn from_f32(v: f32) -> Self {
        Quanta(v.round() as i64)
    }
    /// ⌊v + u⌋, whose mean over a uniform u is v exactly: a pass's samples are rounded this way,
    /// so that samples far below a quantum (the pixels beside one whose adjoint is 10⁸ times
    /// theirs, which sets the quantum) still add up to their sum instead of rounding to 0.
    #[inline]
    fn from_f32_dithered(v: f32, u: f32) -> Self {
        // In f64: an f32 sum would round v + u to even above 2²², leaning the mean up.
        let x = f64::from(v) + f64::from(u);
        // ⌊x⌋ as truncation, one less below a negative non-integer: `floor` is a call into libm
        // on x86-64's baseline (SSE2 has no rounding instruction), 8 per sample in this hot loop.
        // `as` saturates beyond i64 and maps NaN to 0, as `floor() as i64` did.
        let t = x as i64;
        Quanta(t.saturating_sub(i64::from((t as f64) > x)))
    }
    fn from_f64(v: f64) -> Self {
        Quanta(v.round() as i64)
    }
    fn to_f64(self) -> f64 {
        self.0 as f64
    }
}

/// The dither of corner k of a cell whose sample drew `u`: u + k/φ (mod 1), uniform for each
/// corner, which is all each rounding's mean needs.
#[inline]
pub fn corner_dither(u: f32, k: usize) -> f32 {
    // x ≥ 0 and below 6, so truncating through i32 is its integer part: the bits `fract` gives,
    // without `fract`'s call into libm.
    let x = u + k as f32 * 0.618_034;
    x - (x as i32) as f32
}

#[derive(Clone)]
pub struct GradientGrid<T: Accumulator = f64> {
    /// Inclusive block range accepted (voxels beyond it are never weighted by a lookup).
    block_lo: IVec3,
    block_hi: IVec3,
    /// Block coordinates → index + 1 into `origins` (0 = no block yet).
    slots: SparseIndex,
    /// The first voxel of every block, in the order blocks were created.
    origins: Vec<IVec3>,
    /// Block i's values: `chunks[i / CHUNK_BLOCKS][i % CHUNK_BLOCKS]`.
    chunks: Vec<Box<[[T; BLOCK_VOXELS]; CHUNK_BLOCKS]>>,
}

impl<T: Accumulator> GradientGrid<T> {
    /// An empty accumulator covering the voxels from `lo` to `hi` (inclusive).
    pub fn new(lo: IVec3, hi: IVec3) -> Self {
        Self::with_flat_budget(lo, hi, 1 << 12)
    }

    /// As `new`; the block index is one flat table when the box holds at most `flat_budget`
    /// blocks (one array read per lookup), a sparse index otherwise.
    fn with_flat_budget(lo: IVec3, hi: IVec3, flat_budget: u64) -> Self {
        let (block_lo, block_hi) = (lo >> BLOCK_LOG2, hi >> BLOCK_LOG2);
        GradientGrid {
            block_lo,
            block_hi,
            slots: SparseIndex::with_flat_budget(block_lo, block_hi, flat_budget),
            origins: Vec::new(),
            chunks: Vec::new(),
        }
    }

    /// The flat-table budget for a grid of `leaves` leaves: 128 slots (512 bytes) per 2 KiB leaf,
    /// or 2¹² for tiny grids; a wider box gets the sparse index. A gradient's blocks scatter
    /// thinly over the box paths cross, so the sparse index's 8³-slot nodes would cost as much as
    /// the flat table (measured on the upsampled cloud) and a read more per lookup.
    fn budget(leaves: usize) -> u64 {
        (128 * leaves as u64).max(1 << 12)
    }

    /// Covers every voxel a lookup in `grid`'s medium can weight.
    pub fn for_grid(grid: &BrickMap) -> Self {
        match grid.active_bounds() {
            Some((lo, hi)) => Self::with_flat_budget(
                lo.saturating_sub(IVec3::ONE),
                hi.saturating_add(IVec3::ONE),
                Self::budget(grid.leaves().len()),
            ),
            None => Self::new(IVec3::ZERO, IVec3::splat(-1)),
        }
    }

    /// Covers the voxels from `lo` to `hi` (inclusive), and whatever else their blocks hold.
    pub fn for_box(lo: IVec3, hi: IVec3) -> Self {
        Self::with_flat_budget(lo, hi, Self::budget(0))
    }

    /// Covers every voxel a lookup inside `medium`'s bounds can weight (the same as `for_grid` for
    /// a medium that ends at its active voxels; an optimisation's fixed domain otherwise).
    pub fn for_medium(medium: &Medium) -> Self {
        let (lo, hi) = medium.bounds;
        if !(lo.cmplt(hi).all()) {
            return Self::new(IVec3::ZERO, IVec3::splat(-1));
        }
        // A trilinear lookup at p weights the voxels floor(p) and floor(p) + 1 (voxel centres sit
        // at integer indices).
        let first = floor_ivec3(lo);
        let last = floor_ivec3(hi).saturating_add(IVec3::ONE);
        Self::with_flat_budget(first, last, Self::budget(medium.grid.leaves().len()))
    }

    /// An empty accumulator of the same extent.
    pub fn empty_like(&self) -> Self {
        GradientGrid {
            block_lo: self.block_lo,
            block_hi: self.block_hi,
            slots: self.slots.empty_like(),
            origins: Vec::new(),
            chunks: Vec::new(),
        }
    }

    #[inline]
    fn values(&self, index: usize) -> &[T; BLOCK_VOXELS] {
        &self.chunks[index / CHUNK_BLOCKS][index % CHUNK_BLOCKS]
    }

    /// The values of the block holding voxel `v`, created on first touch; `None` outside the
    /// extent.
    #[inline]
    fn block_mut(&mut self, v: IVec3) -> Option<&mut [T; BLOCK_VOXELS]> {
        let slot = self.slots.slot_mut(v >> BLOCK_LOG2)?;
        if *slot == 0 {
            let index = self.origins.len();
            if index.is_multiple_of(CHUNK_BLOCKS) {
                self.chunks
                    .push(Box::new([[T::default(); BLOCK_VOXELS]; CHUNK_BLOCKS]));
            }
            self.origins.push(v & !BLOCK_MASK);
            *slot = self.origins.len() as u32;
        }
        let index = *slot as usize - 1;
        Some(&mut self.chunks[index / CHUNK_BLOCKS][index % CHUNK_BLOCKS])
    }

    /// Adds `value` to voxel `v`; voxels outside the extent are ignored (no lookup reaches them).
    #[inline]
    pub fn add(&mut self, v: IVec3, value: T) {
        if let Some(values) = self.block_mut(v) {
            values[block_offset(v & BLOCK_MASK)] += value;
        }
    }

    /// Adds `weights[k] · value` to corner k of the trilinear cell at `base` (rounded with the
    /// dither `corner_dither(dither, k)`), resolving the block once when the cell does not
    /// straddle blocks.
    #[inline]
    pub fn add_cell(&mut self, base: IVec3, weights: &[f32; 8], value: f32, dither: f32) {
        let local = base & BLOCK_MASK;
        if local.cmplt(IVec3::splat(BLOCK_MASK)).all() {
            let Some(values) = self.block_mut(base) else {
                return;
            };
            let o = block_offset(local);
            for (k, &w) in weights.iter().enumerate() {
                values[o + block_offset(corner(k))] +=
                    T::from_f32_dithered(w * value, corner_dither(dither, k));
            }
        } else {
            for (k, &w) in weights.iter().enumerate() {
                if w > 0.0 {
                    let value = T::from_f32_dithered(w * value, corner_dither(dither, k));
                    self.add(base + corner(k), value);
                }
            }
        }
    }

    pub fn get(&self, v: IVec3) -> f64 {
        match self.slots.get(v >> BLOCK_LOG2) {
            0 => 0.0,
            i => self.values(i as usize - 1)[block_offset(v & BLOCK_MASK)].to_f64(),
        }
    }

    /// The inclusive range of block coordinates the grid accepts (a block's first voxel is its
    /// coordinates × `BLOCK_EDGE`).
    pub fn block_range(&self) -> (IVec3, IVec3) {
        (self.block_lo, self.block_hi)
    }

    /// Blocks of 4³ voxels stored.
    pub fn block_count(&self) -> usize {
        self.origins.len()
    }

    /// Bytes held: the blocks' chunks and origins, and the block index.
    pub fn memory_bytes(&self) -> usize {
        self.chunks.len() * std::mem::size_of::<[[T; BLOCK_VOXELS]; CHUNK_BLOCKS]>()
            + self.origins.capacity() * std::mem::size_of::<IVec3>()
            + self.slots.memory_bytes()
    }

    /// `self += weight · other` (same extent), block by block, computed in f64.
    pub fn merge<U: Accumulator>(&mut self, other: &GradientGrid<U>, weight: f64) {
        assert_eq!(
            (self.block_lo, self.block_hi),
            (other.block_lo, other.block_hi),
            "gradient grids of different extents"
        );
        for (i, &origin) in other.origins.iter().enumerate() {
            let theirs = other.values(i);
            let mine = self.block_mut(origin).expect("same extent");
            for (m, v) in mine.iter_mut().zip(theirs.iter()) {
                *m = T::from_f64(m.to_f64() + weight * v.to_f64());
            }
        }
    }

    /// `factor · self` with values of type `U` (quanta to values: `factor` = the quantum).
    pub fn converted<U: Accumulator>(&self, factor: f64) -> GradientGrid<U> {
        GradientGrid {
            block_lo: self.block_lo,
            block_hi: self.block_hi,
            slots: self.slots.clone(),
            origins: self.origins.clone(),
            chunks: self
                .chunks
                .iter()
                .map(|chunk| {
                    Box::new(chunk.map(|values| values.map(|v| U::from_f64(factor * v.to_f64()))))
                })
                .collect(),
        }
    }

    /// Every stored block: its first voxel and its values.
    pub fn blocks(&self) -> impl Iterator<Item = (IVec3, &[T; BLOCK_VOXELS])> + '_ {
        (self.origins.iter().enumerate()).map(|(i, &origin)| (origin, self.values(i)))
    }

    /// Adds `values` to the block whose first voxel is `origin`, created if need be; `false`
    /// (nothing added) for a block outside the extent.
    pub fn add_block(&mut self, origin: IVec3, values: &[T; BLOCK_VOXELS]) -> bool {
        let Some(mine) = self.block_mut(origin) else {
            return false;
        };
        for (m, &v) in mine.iter_mut().zip(values) {
            *m += v;
        }
        true
    }

    pub fn scale(&mut self, factor: f64) {
        let blocks = self.origins.len();
        for (c, chunk) in self.chunks.iter_mut().enumerate() {
            for values in chunk.iter_mut().take(blocks - c * CHUNK_BLOCKS) {
                for v in values.iter_mut() {
                    *v = T::from_f64(v.to_f64() * factor);
                }
            }
        }
    }

    /// Every voxel with a stored (possibly zero) value.
    pub fn voxels(&self) -> impl Iterator<Item = (IVec3, f64)> + '_ {
        self.origins.iter().enumerate().flat_map(|(i, origin)| {
            self.values(i)
                .iter()
                .enumerate()
                .map(move |(o, &v)| (*origin + offset_voxel(o), v.to_f64()))
        })
    }

    /// ⟨g, 1⟩ over the voxels inside the inclusive box `[lo, hi]`.
    pub fn sum_in_box(&self, lo: IVec3, hi: IVec3) -> f64 {
        self.voxels()
            .filter(|(v, _)| v.cmpge(lo).all() && v.cmple(hi).all())
            .map(|(_, g)| g)
            .sum()
    }

    pub fn sum(&self) -> f64 {
        self.voxels().map(|(_, g)| g).sum()
    }

    /// As a brick map of f32 values for export: voxels that received a non-zero gradient are
    /// active. Blocks are gathered into 8³ leaves through a map of leaf origins (one entry per
    /// leaf, not per voxel).
    pub fn to_brickmap(&self) -> BrickMap {
        let mut leaves: Vec<Leaf> = Vec::new();
        let mut leaf_of: KeyMap<usize> = KeyMap::default();
        for (i, &origin) in self.origins.iter().enumerate() {
            let values = self.values(i);
            if values.iter().all(|v| v.to_f64() as f32 == 0.0) {
                continue;
            }
            let leaf_origin = origin & !7;
            let index = *leaf_of.entry(leaf_origin).or_insert_with(|| {
                leaves.push(Leaf {
                    origin: leaf_origin,
                    values: [0.0; BRICK_VOXELS],
                    active: [0; 8],
                });
                leaves.len() - 1
            });
            let leaf = &mut leaves[index];
            for (o, v) in values.iter().enumerate() {
                let g = v.to_f64() as f32;
                if g != 0.0 {
                    let lo = leaf_offset(origin - leaf_origin + offset_voxel(o));
                    leaf.values[lo] = g;
                    leaf.active[lo >> 6] |= 1 << (lo & 63);
                }
            }
        }
        BrickMap::new(leaves, Vec::new())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accumulates_sparsely_and_merges() {
        let mut g = GradientGrid::new(IVec3::splat(-10), IVec3::splat(30));
        g.add(IVec3::new(-9, 0, 3), 1.5);
        g.add(IVec3::new(-9, 0, 3), 1.0);
        g.add(IVec3::new(29, 29, 29), -2.0);
        g.add(IVec3::new(500, 0, 0), 7.0); // outside: ignored
        assert_eq!(g.block_count(), 2);
        assert_eq!(g.get(IVec3::new(-9, 0, 3)), 2.5);
        let mut h = g.empty_like();
        h.merge(&g, 0.5);
        h.merge(&g, 0.5);
        assert_eq!(h.get(IVec3::new(29, 29, 29)), -2.0);
        // A cell inside one brick and one straddling bricks give the same per-corner sums.
        let weights = [0.1, 0.2, 0.05, 0.15, 0.1, 0.1, 0.2, 0.1];
        for base in [IVec3::new(1, 2, 3), IVec3::new(7, 7, 7)] {
            let mut a = g.empty_like();
            a.add_cell(base, &weights, 2.0, 0.0);
            for (k, &w) in weights.iter().enumerate() {
                assert!((a.get(base + corner(k)) - 2.0 * w as f64).abs() < 1e-7);
            }
        }
        assert_eq!(h.sum(), 0.5);
        assert_eq!(h.sum_in_box(IVec3::splat(0), IVec3::splat(29)), -2.0);
        let map = h.to_brickmap();
        assert_eq!(map.active_voxel_count(), 2);
        assert_eq!(map.voxel(IVec3::new(-9, 0, 3)), 2.5);
    }

    #[test]
    fn dithered_rounding_is_floor_and_corner_dithers_are_fractions() {
        // The hand-written ⌊v + u⌋ and u + k/φ (mod 1) give what `floor` and `fract` give, at
        // integers, below 0, at f32's and i64's extremes and at NaN.
        let values = [
            0.0,
            -0.0,
            0.25,
            -0.25,
            1.0,
            -1.0,
            2.5,
            -2.5,
            1e7,
            -1e7,
            16777217.0,
            -3.000_000_2,
            1e18,
            -1e18,
            1e30,
            -1e30,
            f32::MAX,
            f32::MIN,
            f32::NAN,
        ];
        for &v in &values {
            for u in [0.0, 0.25, 0.5, 0.999_999_94] {
                let expected = (f64::from(v) + f64::from(u)).floor() as i64;
                assert_eq!(Quanta::from_f32_dithered(v, u).0, expected, "v {v}, u {u}");
            }
        }
        for u in [0.0, 0.3, 0.618_034, 0.999_999_94] {
            for k in 0..8 {
                let expected = (u + k as f32 * 0.618_034).fract();
                assert_eq!(
                    corner_dither(u, k).to_bits(),
                    expected.to_bits(),
                    "u {u}, k {k}"
                );
            }
        }
    }

    #[test]
    fn blocks_gather_into_leaves_for_export() {
        // Voxels in several 4³ blocks of one leaf and of neighbouring leaves, negative ones too.
        let mut g = GradientGrid::<f32>::new(IVec3::splat(-20), IVec3::splat(20));
        let mut expected = Vec::new();
        for k in 0..200 {
            let v = IVec3::new((k * 7) % 37 - 18, (k * 13) % 29 - 14, (k * 5) % 31 - 15);
            let value = if k % 3 == 0 {
                0.0
            } else {
                k as f32 * 0.25 - 20.0
            };
            g.add(v, value);
            expected.push(v);
        }
        let map = g.to_brickmap();
        for v in expected {
            assert_eq!(map.voxel(v) as f64, g.get(v), "voxel {v}");
            assert_eq!(map.is_active(v), g.get(v) != 0.0, "voxel {v}");
        }
        assert!(map.leaves().iter().all(|l| l.origin % 8 == IVec3::ZERO));
    }
}
