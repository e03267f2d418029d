//! The sum of every rank's gradient grid, moving only the blocks some rank touched: the ranks
//! agree on the union of their block keys, then add the union's values in one allreduce of i64
//! quanta. Integer addition is exact, so the result is the same bits whatever order MPI adds the
//! ranks in, and the same as one process would get. A sum that could pass ±2⁶³ saturates there, as
//! one process's does, instead of wrapping (`sum_quanta`).
//!
//! The union is agreed on as a bitmap over the grid's block range (one bit per 4³ block, OR-ed
//! across ranks: 26 KB for the ×8 cloud's box, whatever the number of ranks) when the range is
//! compact, as an optimisation's unknown box is; a wide sparse box (`grad` on voxels thousands of
//! voxels apart) gathers the keys themselves instead, 12 bytes per touched block from every rank.

use glam::IVec3;

use crate::cluster::Cluster;
use crate::gradient::bands::BandedGradient;
use crate::gradient::grid::{GradientGrid, Quanta, BLOCK_EDGE, BLOCK_VOXELS};

/// Bitmaps up to this many blocks (16 MiB); wider ranges gather keys.
const MAX_BITMAP_BLOCKS: u64 = 1 << 27;

/// The first voxels of the blocks any rank touched, sorted by (x, y, z), and the bytes this rank
/// sent to agree on them.
fn agree_on_blocks(cluster: &Cluster, grid: &GradientGrid<Quanta>) -> (Vec<IVec3>, u64) {
    let n = cluster.size() as u64;
    let (lo, hi) = grid.block_range();
    let dims = (hi - lo + IVec3::ONE).max(IVec3::ZERO).as_u64vec3();
    let count = dims.x * dims.y * dims.z;
    if count <= MAX_BITMAP_BLOCKS {
        // Bit (x·dy + y)·dz + z: the bitmap's order is the keys' sorted order.
        let mut bits = vec![0u64; count.div_ceil(64) as usize];
        for (origin, _) in grid.blocks() {
            let b = (origin / BLOCK_EDGE - lo).as_u64vec3();
            let i = (b.x * dims.y + b.y) * dims.z + b.z;
            bits[(i / 64) as usize] |= 1 << (i % 64);
        }
        cluster.or_in_place(&mut bits);
        let mut union = Vec::new();
        for (w, &word) in bits.iter().enumerate() {
            let mut word = word;
            while word != 0 {
                let i = w as u64 * 64 + word.trailing_zeros() as u64;
                word &= word - 1;
                let b = glam::U64Vec3::new(i / (dims.y * dims.z), i / dims.z % dims.y, i % dims.z);
                union.push((b.as_ivec3() + lo) * BLOCK_EDGE);
            }
        }
        return (union, 2 * (n - 1) * (bits.len() as u64 * 8) / n);
    }
    let mine: Vec<i32> = grid.blocks().flat_map(|(o, _)| o.to_array()).collect();
    let mut union: Vec<IVec3> = (cluster.gather_all(&mine).chunks_exact(3))
        .map(IVec3::from_slice)
        .collect();
    union.sort_unstable_by_key(|v| (v.x, v.y, v.z));
    union.dedup();
    (union, mine.len() as u64 * 4 * (n - 1))
}

/// What one reduction moved.
#[derive(Debug, Clone, Copy, Default)]
pub struct Traffic {
    /// Blocks in the union of the ranks' keys.
    pub blocks: u64,
    /// Bytes this rank sent: its keys to every other rank, and its part of a ring allreduce of
    /// the union's values, 2·(N − 1)/N of them.
    pub bytes_sent: u64,
    pub seconds: f64,
}

/// `grid` summed over the ranks (every rank gets the sum).
pub fn sum_over_ranks(
    cluster: &Cluster,
    grid: GradientGrid<Quanta>,
) -> (GradientGrid<Quanta>, Traffic) {
    if cluster.size() == 1 {
        return (grid, Traffic::default());
    }
    let started = std::time::Instant::now();
    let (union, key_bytes) = agree_on_blocks(cluster, &grid);
    let mut values = vec![0i64; union.len() * BLOCK_VOXELS];
    for (origin, block) in grid.blocks() {
        let at = union
            .binary_search_by_key(&(origin.x, origin.y, origin.z), |v| (v.x, v.y, v.z))
            .expect("every key is in the union");
        for (slot, q) in values[at * BLOCK_VOXELS..].iter_mut().zip(block) {
            *slot = q.0;
        }
    }
    let limbs = sum_quanta(cluster, &mut values);
    let mut sum = grid.empty_like();
    for (origin, chunk) in union.iter().zip(values.chunks_exact(BLOCK_VOXELS)) {
        let block: [Quanta; BLOCK_VOXELS] = std::array::from_fn(|i| Quanta(chunk[i]));
        sum.add_block(*origin, &block);
    }
    let n = cluster.size() as u64;
    let traffic = Traffic {
        blocks: union.len() as u64,
        bytes_sent: key_bytes + 2 * (n - 1) * (values.len() as u64 * 8 * limbs) / n,
        seconds: started.elapsed().as_secs_f64(),
    };
    (sum, traffic)
}

/// `gradient`'s bands each summed over the ranks (every rank has the same bands: they follow
/// the adjoint, which every rank has whole), with what they moved together.
pub fn sum_bands_over_ranks(
    cluster: &Cluster,
    gradient: BandedGradient,
) -> (BandedGradient, Traffic) {
    let BandedGradient { bands, grids } = gradient;
    let mut traffic = Traffic::default();
    let grids = (grids.into_iter())
        .map(|grid| {
            let (sum, moved) = sum_over_ranks(cluster, grid);
            traffic.blocks += moved.blocks;
            traffic.bytes_sent += moved.bytes_sent;
            traffic.seconds += moved.seconds;
            sum
        })
        .collect();
    (BandedGradient { bands, grids }, traffic)
}

/// `values` (i64 quanta) summed over the ranks in place, saturating at ±2⁶³ as a rank's own sums
/// do, never wrapping; returns how many i64 each value took in the allreduce (1 or 2).
///
/// The ranks first agree on the largest |q| (one value): while it times the rank count stays below
/// 2⁶², a plain i64 sum cannot overflow. Otherwise each value travels as two limbs, hi = q >> 32
/// and lo = q mod 2³², whose sums cannot overflow below 2³¹ ranks, and is put back together in
/// i128 and saturated.
fn sum_quanta(cluster: &Cluster, values: &mut [i64]) -> u64 {
    let largest = values.iter().map(|q| q.unsigned_abs()).max().unwrap_or(0);
    let [largest] = cluster.max_each([largest as f64]);
    if largest * (cluster.size() as f64) < 2f64.powi(62) {
        cluster.sum_in_place(values);
        return 1;
    }
    let mut limbs: Vec<i64> = values.iter().flat_map(|&q| split(q)).collect();
    cluster.sum_in_place(&mut limbs);
    for (q, pair) in values.iter_mut().zip(limbs.chunks_exact(2)) {
        *q = join(pair[0], pair[1]);
    }
    2
}

/// q as (hi, lo): q = hi·2³² + lo, lo in [0, 2³²).
fn split(q: i64) -> [i64; 2] {
    [q >> 32, q & 0xffff_ffff]
}

/// Σhi·2³² + Σlo, saturated to i64.
fn join(hi: i64, lo: i64) -> i64 {
    let exact = (i128::from(hi) << 32) + i128::from(lo);
    exact.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Summed limb by limb, any values of any number of ranks give their exact sum, saturated:
    /// near ±2⁶³, where a plain i64 sum wraps to the other sign.
    #[test]
    fn limbs_sum_to_the_saturated_exact_sum() {
        let near = i64::MAX - 5;
        let cases: [&[i64]; 5] = [
            &[1, 2, 3],
            &[-7, 1 << 40, -(1 << 33) + 5],
            &[near, near],
            &[i64::MIN, -1, i64::MIN],
            &[near, near, -near, -near, 17],
        ];
        for values in cases {
            let exact: i128 = values.iter().map(|&q| i128::from(q)).sum();
            let (mut hi, mut lo) = (0i64, 0i64);
            for &q in values {
                let [h, l] = split(q);
                hi += h;
                lo += l;
            }
            let want = exact.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;
            assert_eq!(join(hi, lo), want, "{values:?}");
        }
        assert!(near.wrapping_add(near) < 0, "a plain sum would wrap");
    }
}
