//! The processes of one job. Started by `mpirun` or Slurm's `srun`, volgrad runs as MPI ranks:
//! every rank holds the scene and the unknown and traces its share of the pixels
//! (`render::pixel_set`), and the ranks add their results (`sparse_sum` for gradients, `images`
//! for images, `passes` for whole gradient passes) so that every rank takes the same step.
//! Started any other way, it is one process and every collective here returns its input.
//! Uses `gradient` (its passes and grids), `render` and `io`; `optimize` and the commands run their
//! passes through it.
//!
//! Faults: an error that one rank meets and the others do not (an unreadable file, a failing
//! write) must not leave the others waiting in a collective. Every such point goes through
//! `agree`, which ends every rank with the first failing rank's error; `main` prints it on rank 0
//! only.

pub mod images;
pub mod passes;
pub mod sparse_sum;

use anyhow::{anyhow, Result};

/// The most values one MPI call moves from a rank: MPI's counts and displacements are 32-bit, so
/// larger arrays (a gradient of 2048³ voxels is 2³³ values) go in pieces.
#[cfg_attr(not(feature = "mpi"), allow(dead_code))]
const MAX_COUNT: usize = 1 << 30;

/// This process's place in the job, and the communicator to the other ranks.
pub struct Cluster {
    rank: usize,
    size: usize,
    #[cfg(feature = "mpi")]
    world: Option<mpi::topology::SimpleCommunicator>,
}

/// Keeps MPI initialised while it lives (MPI_Finalize when dropped); `None` for one process.
pub struct Session {
    #[cfg(feature = "mpi")]
    _universe: Option<mpi::environment::Universe>,
}

/// Whether a launcher started this process as one rank of several (OpenMPI's mpirun, PMIx, or
/// Slurm's PMI): a plain start must not initialise MPI, which would look for a launcher.
fn launched_as_rank() -> bool {
    ["OMPI_COMM_WORLD_SIZE", "PMIX_RANK", "PMI_SIZE", "PMI_RANK"]
        .iter()
        .any(|name| std::env::var_os(name).is_some())
}

/// This process's rank as the launcher's variables say, before MPI is initialised (0 when not
/// launched as a rank): for what every rank would print alike before the job exists, such as an
/// error in the command line.
pub fn launcher_rank() -> usize {
    [
        "OMPI_COMM_WORLD_RANK",
        "PMIX_RANK",
        "PMI_RANK",
        "SLURM_PROCID",
    ]
    .iter()
    .find_map(|name| std::env::var(name).ok()?.trim().parse().ok())
    .unwrap_or(0)
}

/// How many processes the launcher says it started, by the variables it sets for each: MPI's
/// (OpenMPI, PMI) and Slurm's for a job step (`srun`, with or without MPI).
fn declared_size() -> Option<(String, usize)> {
    ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "SLURM_STEP_NUM_TASKS"]
        .iter()
        .find_map(|name| {
            let value = std::env::var(name).ok()?;
            Some((format!("{name}={value}"), value.trim().parse().ok()?))
        })
}

/// A launcher that started several processes which cannot talk to each other (`srun
/// --mpi=none`, PMI variables left in the environment without a launcher) would run that many
/// copies of the same job on the same outputs: refuse it in every one.
fn check_size(mpi_size: usize) -> Result<()> {
    match declared_size() {
        Some((variable, declared)) if declared > 1 && mpi_size == 1 => Err(anyhow!(
            "the launcher started {declared} processes ({variable}) but MPI sees only this one: they would each run the whole job on the same outputs. Launch with `mpirun`, or `srun --mpi=pmix` (or your site's MPI plugin), or unset the launcher's variables to run one process"
        )),
        _ => Ok(()),
    }
}

impl Cluster {
    /// One process, no MPI.
    pub fn single() -> Cluster {
        Cluster {
            rank: 0,
            size: 1,
            #[cfg(feature = "mpi")]
            world: None,
        }
    }

    /// The job this process was launched in: MPI ranks under mpirun or srun, else one process.
    pub fn from_launcher() -> Result<(Cluster, Session)> {
        if !launched_as_rank() {
            check_size(1)?;
            return Ok((
                Cluster::single(),
                Session {
                    #[cfg(feature = "mpi")]
                    _universe: None,
                },
            ));
        }
        #[cfg(feature = "mpi")]
        {
            use mpi::traits::Communicator;
            // Funneled: only the main thread calls MPI; rayon's threads only render.
            let (universe, _) = mpi::initialize_with_threading(mpi::Threading::Funneled)
                .ok_or_else(|| anyhow!("MPI was already initialised"))?;
            let world = universe.world();
            // A panic unwinds into MPI_Finalize, which would wait for ranks that wait for this
            // one: end the whole job instead.
            let report = std::panic::take_hook();
            std::panic::set_hook(Box::new(move |info| {
                report(info);
                mpi::topology::SimpleCommunicator::world().abort(101);
            }));
            let cluster = Cluster {
                rank: world.rank() as usize,
                size: world.size() as usize,
                world: Some(world),
            };
            check_size(cluster.size)?;
            Ok((
                cluster,
                Session {
                    _universe: Some(universe),
                },
            ))
        }
        #[cfg(not(feature = "mpi"))]
        Err(anyhow!(
            "started by an MPI launcher, but this volgrad was built without the `mpi` feature"
        ))
    }

    pub fn rank(&self) -> usize {
        self.rank
    }

    pub fn size(&self) -> usize {
        self.size
    }

    /// Rank 0: the one that writes files, the log and the progress bar.
    pub fn is_root(&self) -> bool {
        self.rank == 0
    }

    /// `values` summed over the ranks, in place. Exact (and so independent of MPI's reduction
    /// order) for integers, and for floating-point values that are non-zero on at most one rank
    /// each (x + 0 = x): pixels of disjoint shares.
    pub fn sum_in_place<T: Summable>(&self, values: &mut [T]) {
        #[cfg(feature = "mpi")]
        if let Some(world) = &self.world {
            use mpi::collective::{CommunicatorCollectives, SystemOperation};
            for piece in values.chunks_mut(MAX_COUNT) {
                let mine = piece.to_vec();
                world.all_reduce_into(&mine[..], piece, SystemOperation::sum());
            }
        }
        let _ = values;
    }

    /// `bits` OR-ed over the ranks, in place.
    pub fn or_in_place(&self, bits: &mut [u64]) {
        #[cfg(feature = "mpi")]
        if let Some(world) = &self.world {
            use mpi::collective::{CommunicatorCollectives, SystemOperation};
            for piece in bits.chunks_mut(MAX_COUNT) {
                let mine = piece.to_vec();
                world.all_reduce_into(&mine[..], piece, SystemOperation::bitwise_or());
            }
        }
        let _ = bits;
    }

    /// The largest of each value over the ranks.
    pub fn max_each<const N: usize>(&self, values: [f64; N]) -> [f64; N] {
        #[cfg(feature = "mpi")]
        if let Some(world) = &self.world {
            use mpi::collective::{CommunicatorCollectives, SystemOperation};
            let mut out = values;
            world.all_reduce_into(&values[..], &mut out[..], SystemOperation::max());
            return out;
        }
        values
    }

    /// Every rank's `mine`, concatenated in rank order. In rounds of at most `MAX_COUNT / size`
    /// values from each rank, so that a round's counts and displacements fit MPI's 32 bits.
    pub fn gather_all<T: Summable>(&self, mine: &[T]) -> Vec<T> {
        #[cfg(feature = "mpi")]
        if let Some(world) = &self.world {
            use mpi::collective::CommunicatorCollectives;
            use mpi::datatype::PartitionMut;
            let mut lens = vec![0u64; self.size];
            world.all_gather_into(&(mine.len() as u64), &mut lens[..]);
            let lens: Vec<usize> = lens.into_iter().map(|n| n as usize).collect();
            let starts = prefix_sums(&lens);
            let mut all = vec![T::default(); lens.iter().sum()];
            let piece = (MAX_COUNT / self.size).max(1);
            let rounds = lens.iter().max().map_or(0, |n| n.div_ceil(piece));
            for round in 0..rounds {
                let counts = round_counts(&lens, piece, round);
                let displs = prefix_sums(&counts);
                let mut received = vec![T::default(); counts.iter().sum()];
                let sent = &mine[(round * piece).min(mine.len())..][..counts[self.rank]];
                let as_count = |v: &[usize]| v.iter().map(|&n| n as mpi::Count).collect::<Vec<_>>();
                let (c, d) = (as_count(&counts), as_count(&displs));
                world.all_gather_varcount_into(
                    sent,
                    &mut PartitionMut::new(&mut received[..], c, &d[..]),
                );
                for k in 0..self.size {
                    let to = starts[k] + round * piece;
                    all[to..to + counts[k]].copy_from_slice(&received[displs[k]..][..counts[k]]);
                }
            }
            return all;
        }
        mine.to_vec()
    }

    /// `result` if every rank's is `Ok`; else, on every rank, the error of the first rank that
    /// failed (its message, sent to all), so that all ranks end together with one message. Where
    /// rank 0 did not fail, the message names the rank: its machine or folder lacks what rank 0's
    /// has.
    pub fn agree<T>(&self, result: Result<T>) -> Result<T> {
        if self.size == 1 {
            return result;
        }
        let failed = if result.is_err() {
            self.rank
        } else {
            self.size
        };
        let first = self.gather_all(&[failed as u64]).into_iter().min();
        let Some(first) = first.filter(|&r| (r as usize) < self.size) else {
            return result;
        };
        let mine = match &result {
            Err(e) if self.rank == first as usize => match first {
                0 => format!("{e:#}").into_bytes(),
                _ => format!("rank {first}: {e:#}").into_bytes(),
            },
            _ => Vec::new(),
        };
        let message = self.gather_all(&mine);
        Err(AgreedError(String::from_utf8_lossy(&message).into_owned()).into())
    }

    /// Refuses a job whose ranks were not given the same work: each rank's fingerprints of its
    /// arguments and inputs (`parts`, each named as rank 0 prints it), against rank 0's. Ranks
    /// started with other flags (an MPMD launch) or reading other files (copies out of date on one
    /// machine) would add their shares into one wrong result, or stop a collective with
    /// mismatched sizes. The first part that differs is named: which file to copy again.
    pub fn check_same_inputs(&self, parts: &[(String, u64)]) -> Result<()> {
        if self.size == 1 {
            return Ok(());
        }
        let counts = self.gather_all(&[parts.len() as u64]);
        let mine: Vec<u64> = parts.iter().map(|&(_, f)| f).collect();
        let all = self.gather_all(&mine);
        let mut lists = counts.iter().scan(0, |start, &count| {
            let list = &all[*start..*start + count as usize];
            *start += count as usize;
            Some(list)
        });
        let Some(root) = lists.next() else {
            return Ok(());
        };
        let Some((rank, list)) = (lists.enumerate())
            .map(|(i, list)| (i + 1, list))
            .find(|(_, list)| list != &root)
        else {
            return Ok(());
        };
        let what = match list.iter().zip(root).position(|(a, b)| a != b) {
            Some(i) if list.len() == root.len() => format!(" ({} differs)", parts[i].0),
            _ => format!(" ({} inputs where rank 0 has {})", list.len(), root.len()),
        };
        Err(AgreedError(format!(
            "rank {rank} was started with other arguments, or reads other files, than rank 0{what}: every rank must run the same command on the same inputs (files copied alike to every machine)"
        ))
        .into())
    }

    /// `write()` on rank 0; `Ok` on the others (whose result comes from `agree`).
    pub fn on_root(&self, write: impl FnOnce() -> Result<()>) -> Result<()> {
        if self.is_root() {
            write()
        } else {
            Ok(())
        }
    }

    /// Ends every rank of the job at once (MPI_Abort): for an error only this rank met outside
    /// `agree`, or a panic, where the others may be waiting in a collective.
    pub fn abort(&self) {
        #[cfg(feature = "mpi")]
        if let Some(world) = &self.world {
            use mpi::topology::Communicator;
            world.abort(1);
        }
    }
}

/// Where each of `counts` begins when they are laid end to end.
#[cfg_attr(not(feature = "mpi"), allow(dead_code))]
fn prefix_sums(counts: &[usize]) -> Vec<usize> {
    counts
        .iter()
        .scan(0, |at, &n| {
            let start = *at;
            *at += n;
            Some(start)
        })
        .collect()
}

/// How many values each rank, holding `lens`, sends in round `round` of a gather in pieces of at
/// most `piece` values: values `round·piece ..` of its own, up to `piece` of them.
#[cfg_attr(not(feature = "mpi"), allow(dead_code))]
fn round_counts(lens: &[usize], piece: usize, round: usize) -> Vec<usize> {
    lens.iter()
        .map(|&n| n.saturating_sub(round * piece).min(piece))
        .collect()
}

/// An error every rank of the job returns together (`Cluster::agree`): rank 0 prints it, and
/// every rank ends normally.
#[derive(Debug)]
pub struct AgreedError(pub String);

impl std::fmt::Display for AgreedError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for AgreedError {}

/// Values the collectives move: plain numbers MPI has a type for.
#[cfg(feature = "mpi")]
pub trait Summable: Copy + Default + mpi::traits::Equivalence {}
#[cfg(feature = "mpi")]
impl<T: Copy + Default + mpi::traits::Equivalence> Summable for T {}
#[cfg(not(feature = "mpi"))]
pub trait Summable: Copy + Default {}
#[cfg(not(feature = "mpi"))]
impl<T: Copy + Default> Summable for T {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_gather_in_rounds_moves_every_value_once_and_no_round_overflows() {
        // Three ranks' arrays, gathered in pieces of 4: each value of each rank is sent in exactly
        // one round, at its place, and no round moves more than a piece from a rank.
        let lens = [10usize, 0, 7];
        let piece = 4;
        let rounds = lens.iter().max().unwrap().div_ceil(piece);
        let mut sent = [0usize; 3];
        for round in 0..rounds {
            let counts = round_counts(&lens, piece, round);
            for (k, &c) in counts.iter().enumerate() {
                assert!(c <= piece);
                // A round's values start where the last round's ended.
                assert_eq!(sent[k], (round * piece).min(lens[k]));
                sent[k] += c;
            }
        }
        assert_eq!(sent, lens);
        assert_eq!(prefix_sums(&lens), vec![0, 10, 10]);
        // MAX_COUNT values from each of 2,048 ranks still fit a 32-bit count per round.
        let size = 2048;
        assert!((MAX_COUNT / size) * size <= i32::MAX as usize);
    }
}
