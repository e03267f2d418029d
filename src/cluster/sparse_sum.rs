//! The sum of every rank's gradient grid, moving only the blocks some rank touched: the ranks
//! agree on the union of their block keys (an allgather of 12 bytes per block), then add the
//! union's values in one allreduce of i64 quanta. Integer addition is exact, so the result is
//! the same bits whatever order MPI adds the ranks in, and the same as one process would get.

use glam::IVec3;

use crate::cluster::Cluster;
use crate::gradient::grid::{GradientGrid, Quanta, BLOCK_VOXELS};

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
    let mine: Vec<i32> = grid.blocks().flat_map(|(o, _)| o.to_array()).collect();
    let mut union: Vec<IVec3> = cluster
        .gather_all(&mine)
        .chunks_exact(3)
        .map(IVec3::from_slice)
        .collect();
    union.sort_unstable_by_key(|v| (v.x, v.y, v.z));
    union.dedup();
    let mut values = vec![0i64; union.len() * BLOCK_VOXELS];
    for (origin, block) in grid.blocks() {
        let at = union
            .binary_search_by_key(&(origin.x, origin.y, origin.z), |v| (v.x, v.y, v.z))
            .expect("every key is in the union");
        for (slot, q) in values[at * BLOCK_VOXELS..].iter_mut().zip(block) {
            *slot = q.0;
        }
    }
    cluster.sum_in_place(&mut values);
    let mut sum = grid.empty_like();
    for (origin, chunk) in union.iter().zip(values.chunks_exact(BLOCK_VOXELS)) {
        let block: [Quanta; BLOCK_VOXELS] = std::array::from_fn(|i| Quanta(chunk[i]));
        sum.add_block(*origin, &block);
    }
    let n = cluster.size() as u64;
    let traffic = Traffic {
        blocks: union.len() as u64,
        bytes_sent: mine.len() as u64 * 4 * (n - 1) + 2 * (n - 1) * (values.len() as u64 * 8) / n,
        seconds: started.elapsed().as_secs_f64(),
    };
    (sum, traffic)
}
