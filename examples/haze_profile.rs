//! Where a reconstruction's density sits against the truth's: the mean density of truth-empty voxels
//! by their distance to the nearest occupied one (the "haze" `volgrad optimize` reports, split into
//! the blur of the boundary and density far from the volume), and the mean density of occupied
//! voxels by their depth below the truth's surface, beside the truth's.
//!
//! ```sh
//! cargo run --release --example haze_profile -- TRUTH.vdb RECONSTRUCTION.vdb
//! ```
//!
//! Both grids must share their index space (a reconstruction's `final.vdb` has the truth's
//! transform). Distances are in voxels, Chebyshev (26-neighbour steps), counted to 8.

use std::collections::VecDeque;

use anyhow::{bail, Context, Result};
use glam::IVec3;
use volgrad::io::vdb::{read_grid, GridSelector};

const BANDS: u8 = 8;
/// The profile walks the truth's active box, grown by BANDS + 1 voxels on each side (so that the
/// truth's faces see the empty space beyond them), densely: a few bytes per voxel (two
/// distances, two flags and, while a distance is found, a queue of 4-byte indices). A wide sparse
/// truth is refused rather than sized by its box.
const MAX_BOX_VOXELS: f64 = (1u64 << 28) as f64;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [truth_path, reco_path] = args.as_slice() else {
        bail!("usage: haze_profile TRUTH.vdb RECONSTRUCTION.vdb");
    };
    let truth = read_grid(truth_path.as_ref(), &GridSelector::Default)?;
    let reco = read_grid(reco_path.as_ref(), &GridSelector::Default)?;
    if truth.transform != reco.transform {
        bail!("the two grids have different transforms: compare a run's final.vdb with its truth");
    }
    let (lo, hi) = truth.bricks.active_bounds().context("the truth is empty")?;
    let margin = IVec3::splat(BANDS as i32 + 1);
    let (lo, hi) = (lo.saturating_sub(margin), hi.saturating_add(margin));
    // In f64: the box of a wide sparse grid overflows i32 per axis and i64 in its product.
    let extent = (hi.as_dvec3() - lo.as_dvec3() + 1.0).element_product();
    if extent > MAX_BOX_VOXELS {
        bail!("the truth's active box holds {extent:.3e} voxels; the profile walks at most {MAX_BOX_VOXELS:.0}");
    }
    let cells = DenseBox {
        lo,
        size: hi - lo + IVec3::ONE,
    };
    let occupied: Vec<bool> = cells
        .voxels()
        .map(|v| truth.bricks.voxel(v) > 0.0)
        .collect();
    let empty: Vec<bool> = occupied.iter().map(|o| !o).collect();
    // Distance of an empty voxel to the volume, and depth of an occupied one below its surface.
    let distance = cells.distance_to(&occupied);
    let depth = cells.distance_to(&empty);

    // Per band (1..=BANDS, then beyond): voxels, Σ reconstruction, Σ truth.
    let mut outside = [(0u64, 0.0f64, 0.0f64); BANDS as usize + 2];
    let mut inside = outside;
    for (i, v) in cells.voxels().enumerate() {
        let (bands, d) = if occupied[i] {
            (&mut inside, depth[i])
        } else {
            (&mut outside, distance[i])
        };
        let band = &mut bands[usize::from(d.min(BANDS + 1))];
        band.0 += 1;
        band.1 += f64::from(reco.bricks.voxel(v));
        band.2 += f64::from(truth.bricks.voxel(v));
    }
    let total = |bands: &[(u64, f64, f64)]| {
        bands
            .iter()
            .fold((0, 0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2))
    };
    let (n_occupied, reco_occupied, truth_occupied) = total(&inside);
    let (n_empty, reco_empty, _) = total(&outside);
    // As `volgrad optimize` measures it: counts and the occupied mean kept off 0 (no NaN for a
    // truth without positive values or without empty voxels, or an empty reconstruction).
    let mean = |sum: f64, n: u64| sum / n.max(1) as f64;
    let occupied_mean = mean(reco_occupied, n_occupied).max(1e-30);
    println!(
        "occupied voxels {n_occupied}: truth mean {:.4}, reconstruction mean {occupied_mean:.4}",
        mean(truth_occupied, n_occupied)
    );
    let empty_mean = mean(reco_empty, n_empty);
    println!(
        "empty voxels {n_empty}: haze (mean empty / mean occupied) {:.4}, against the truth's occupied mean {:.4}",
        empty_mean / occupied_mean,
        empty_mean / mean(truth_occupied, n_occupied).max(1e-30)
    );
    let label = |d: usize| match d as u8 {
        d if d > BANDS => format!(">{BANDS}"),
        d => d.to_string(),
    };
    println!("\nempty voxels by distance to the truth's volume");
    println!("distance   voxels   mean   / occupied mean   share of the haze");
    for (d, &(n, reco_sum, _)) in outside.iter().enumerate().skip(1) {
        if n > 0 {
            let band_mean = reco_sum / n as f64;
            println!(
                "{:>8} {n:>8} {band_mean:>7.4} {:>17.3} {:>19.3}",
                label(d),
                band_mean / occupied_mean,
                reco_sum / reco_empty.max(f64::MIN_POSITIVE)
            );
        }
    }
    // Within a pixel of the cloud's 64² views (about 3 final voxels) against beyond it.
    const NEAR: usize = 3;
    let (_, reco_near, _) = total(&outside[1..=NEAR]);
    let (n_far, reco_far, _) = total(&outside[NEAR + 1..]);
    println!(
        "within {NEAR} voxels: {:.3} of the haze; {} or more voxels out: mean / occupied mean {:.3}",
        reco_near / reco_empty.max(f64::MIN_POSITIVE),
        NEAR + 1,
        mean(reco_far, n_far) / occupied_mean
    );
    println!("\noccupied voxels by depth below the truth's surface");
    println!("   depth   voxels  truth  reconstruction");
    for (d, &(n, reco_sum, truth_sum)) in inside.iter().enumerate().skip(1) {
        if n > 0 {
            println!(
                "{:>8} {n:>8} {:>6.4} {:>15.4}",
                label(d),
                truth_sum / n as f64,
                reco_sum / n as f64
            );
        }
    }
    Ok(())
}

/// A dense box of voxels, x-major.
struct DenseBox {
    lo: IVec3,
    size: IVec3,
}

impl DenseBox {
    fn voxels(&self) -> impl Iterator<Item = IVec3> + '_ {
        let s = self.size;
        (0..s.x).flat_map(move |x| {
            (0..s.y).flat_map(move |y| (0..s.z).map(move |z| self.lo + IVec3::new(x, y, z)))
        })
    }

    /// The voxel at x-major index `i` (the inverse of `index`).
    fn voxel_at(&self, i: usize) -> IVec3 {
        let (sy, sz) = (self.size.y as usize, self.size.z as usize);
        self.lo
            + IVec3::new(
                (i / (sy * sz)) as i32,
                ((i / sz) % sy) as i32,
                (i % sz) as i32,
            )
    }

    fn index(&self, v: IVec3) -> Option<usize> {
        let p = v - self.lo;
        if p.cmplt(IVec3::ZERO).any() || p.cmpge(self.size).any() {
            return None;
        }
        Some(((p.x * self.size.y + p.y) * self.size.z + p.z) as usize)
    }

    /// Chebyshev distance of every voxel to the nearest voxel in `sources` (0 there), by a
    /// breadth-first search over 26-neighbours, stopped past BANDS (those keep BANDS + 1).
    fn distance_to(&self, sources: &[bool]) -> Vec<u8> {
        let mut distance: Vec<u8> = sources
            .iter()
            .map(|&s| if s { 0 } else { u8::MAX })
            .collect();
        // Indices, not coordinates: a third of the memory on a box of 2²⁸ voxels.
        let mut queue: VecDeque<u32> = (0..sources.len() as u32)
            .filter(|&i| sources[i as usize])
            .collect();
        while let Some(i) = queue.pop_front() {
            let d = distance[i as usize];
            if d > BANDS {
                continue;
            }
            let v = self.voxel_at(i as usize);
            for offset in (0..27).map(|k| IVec3::new(k % 3, (k / 3) % 3, k / 9) - IVec3::ONE) {
                if let Some(j) = self.index(v + offset) {
                    if distance[j] == u8::MAX {
                        distance[j] = d + 1;
                        queue.push_back(j as u32);
                    }
                }
            }
        }
        distance.iter().map(|&d| d.min(BANDS + 1)).collect()
    }
}
