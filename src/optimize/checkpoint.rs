//! Checkpoints: θ as a VDB anyone can open (`checkpoint-NNNN.vdb`, `final.vdb`), and beside it the
//! optimiser's whole state (`checkpoint-NNNN.state`): θ and Adam's moments bit for bit, the step
//! count and the global scale's moments, the iteration, level and clocks, and the log so far, so
//! that `--resume` continues exactly where the run stopped.
//!
//! The state file is little-endian binary: the magic line, the run's fingerprint, the stop rule
//! (`Stop::to_text`), the counters and the global scale's (m, v), the number of fitted exposures
//! (u32) and each one's x and (m, v) (f32 each), the log text, then the bricks in
//! key order (origin as 3 × i32, then θ, m, v as 512 × f32 each, the brick's log-scale (m, v) as
//! 2 × f32 and its idle steps as u32), then the average: its steps (u32), its bricks' count (u64)
//! and each brick in key order (origin as 3 × i32, θ̄ as 512 × f32). Last, the FNV-1a checksum
//! of every byte before it, as 16 hex digits: a value changed on disk would otherwise resume as
//! a different run, or as a medium too dense to track.

use std::io::{BufReader, Read, Write};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::IVec3;

use crate::io::bridge::MetaEntry;
use crate::io::fingerprint::Fingerprint;
use crate::io::output::write_whole;
use crate::io::vdb::{self, Grid};
use crate::optimize::adam::ScalarMoments;
use crate::optimize::average::Average;
use crate::optimize::exposure::Exposure;
use crate::optimize::parameters::Parameters;
use crate::optimize::schedule::Stop;
use crate::volume::brickmap::BRICK_VOXELS;
use crate::volume::transform::IndexTransform;

/// The format's version: 12 since θ̄ weighs its later steps more (`average`), so that a state
/// whose θ̄ is a plain mean is not resumed as one of those.
const MAGIC: &[u8] = b"volgrad optimizer state 12\n";

/// Where a run is, apart from θ and Adam's moments.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Position {
    /// Iterations done.
    pub iteration: u64,
    /// The current level (0 = coarsest).
    pub level: u32,
    /// Seconds spent optimising (evaluation excluded) and evaluating.
    pub optimisation_seconds: f64,
    pub evaluation_seconds: f64,
    /// log.csv's rows so far (without the header).
    pub log: String,
    /// When the run ends (none before a run has resolved it).
    pub stop: Option<Stop>,
}

/// The files of checkpoint `iteration`: (VDB, state).
pub fn paths(dir: &Path, iteration: u64) -> (PathBuf, PathBuf) {
    let stem = format!("checkpoint-{iteration:04}");
    (
        dir.join(format!("{stem}.vdb")),
        dir.join(format!("{stem}.state")),
    )
}

/// Removes the numbered files an earlier run left in `dir`: its checkpoints
/// (`checkpoint-NNNN.vdb`, `.state`), held-out pictures (`holdout-NNNN.png`) and the temporary
/// files (`.NAME.PID.tmp`) a run killed while writing leaves. A fresh run
/// given `--force` replaces that run, whose checkpoints `--resume` (which takes the latest it
/// finds) would otherwise mistake for this one's. Nothing else in `dir` is touched; a missing
/// `dir` has nothing to remove.
pub fn remove_earlier_run(dir: &Path) -> Result<()> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(());
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let numbered = |prefix: &str, suffix: &str| {
            name.strip_prefix(prefix)
                .and_then(|r| r.strip_suffix(suffix))
                .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
        };
        // A file being written whole is `.NAME.PID.tmp` until it is renamed: one a killed run
        // left behind (SIGKILL) is the earlier run's too.
        let left_behind = name.starts_with('.')
            && name.strip_suffix(".tmp").is_some_and(|rest| {
                rest.rsplit_once('.').is_some_and(|(_, pid)| {
                    !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit())
                })
            });
        let earlier = numbered("checkpoint-", ".vdb")
            || numbered("checkpoint-", ".state")
            || numbered("holdout-", ".png")
            || left_behind;
        if earlier && entry.path().is_file() {
            std::fs::remove_file(entry.path()).with_context(|| {
                format!(
                    "--force: cannot remove the earlier run's '{}'",
                    entry.path().display()
                )
            })?;
        }
    }
    Ok(())
}

/// The state file of the latest checkpoint in `dir`.
pub fn latest(dir: &Path) -> Result<PathBuf> {
    let entries = std::fs::read_dir(dir)
        .with_context(|| format!("--resume: cannot read the directory '{}'", dir.display()))?;
    let mut best: Option<(u64, PathBuf)> = None;
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(n) = name
            .strip_prefix("checkpoint-")
            .and_then(|r| r.strip_suffix(".state"))
            .and_then(|n| n.parse::<u64>().ok())
        else {
            continue;
        };
        if best.as_ref().is_none_or(|(b, _)| n > *b) {
            best = Some((n, entry.path()));
        }
    }
    best.map(|(_, p)| p).with_context(|| {
        format!(
            "--resume: no checkpoint-NNNN.state in '{}' (a run writes one every checkpoint_every iterations)",
            dir.display()
        )
    })
}

pub fn write_state(
    path: &Path,
    fingerprint: &str,
    position: &Position,
    parameters: &Parameters,
) -> Result<()> {
    let stop = position.stop.as_ref().map_or(String::new(), Stop::to_text);
    write_whole(path, |file| {
        let w = &mut Summed::new(file);
        w.write_all(MAGIC)?;
        write_text(w, fingerprint)?;
        write_text(w, &stop)?;
        w.write_all(&position.iteration.to_le_bytes())?;
        w.write_all(&position.level.to_le_bytes())?;
        w.write_all(&parameters.steps().to_le_bytes())?;
        write_moments(w, parameters.scale_moments())?;
        w.write_all(&(parameters.exposures.len() as u32).to_le_bytes())?;
        for exposure in &parameters.exposures {
            w.write_all(&exposure.log.to_le_bytes())?;
            write_moments(w, exposure.moments)?;
        }
        w.write_all(&position.optimisation_seconds.to_le_bytes())?;
        w.write_all(&position.evaluation_seconds.to_le_bytes())?;
        write_text(w, &position.log)?;
        let bricks = parameters.sorted_bricks();
        w.write_all(&(bricks.len() as u64).to_le_bytes())?;
        for (key, theta, m, v, scale, idle) in bricks {
            write_key(w, key)?;
            for values in [theta, m, v] {
                write_values(w, values)?;
            }
            write_moments(w, scale)?;
            w.write_all(&idle.to_le_bytes())?;
        }
        let average = parameters.average.sorted();
        w.write_all(&parameters.average.steps().to_le_bytes())?;
        w.write_all(&(average.len() as u64).to_le_bytes())?;
        for (key, values) in average {
            write_key(w, key)?;
            write_values(w, values)?;
        }
        let sum = w.sum.hex();
        w.inner.write_all(sum.as_bytes())
    })
}

/// A reader or writer that keeps the FNV-1a checksum of the bytes that pass through it.
struct Summed<T> {
    inner: T,
    sum: Fingerprint,
}

impl<T> Summed<T> {
    fn new(inner: T) -> Self {
        Summed {
            inner,
            sum: Fingerprint::default(),
        }
    }
}

impl<W: Write> Write for Summed<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.sum.bytes(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

impl<R: Read> Read for Summed<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.sum.bytes(&buf[..n]);
        Ok(n)
    }
}

fn write_key(w: &mut impl Write, key: IVec3) -> std::io::Result<()> {
    key.to_array()
        .iter()
        .try_for_each(|c| w.write_all(&c.to_le_bytes()))
}

fn write_values(w: &mut impl Write, values: &[f32; BRICK_VOXELS]) -> std::io::Result<()> {
    values
        .iter()
        .try_for_each(|x| w.write_all(&x.to_le_bytes()))
}

/// A brick's origin and values (a non-finite value is an error).
fn read_brick(r: &mut impl Read) -> Result<(IVec3, [f32; BRICK_VOXELS])> {
    let key = read_key(r)?;
    Ok((key, read_values(r)?))
}

fn read_key(r: &mut impl Read) -> Result<IVec3> {
    let mut key = [0i32; 3];
    for c in &mut key {
        *c = i32::from_le_bytes(read_array(r)?);
    }
    Ok(IVec3::from_array(key))
}

fn read_values(r: &mut impl Read) -> Result<[f32; BRICK_VOXELS]> {
    let mut values = [0f32; BRICK_VOXELS];
    for x in values.iter_mut() {
        *x = f32::from_le_bytes(read_array(r)?);
    }
    if values.iter().any(|x| !x.is_finite()) {
        bail!("non-finite values");
    }
    Ok(values)
}

fn write_moments(w: &mut impl Write, moments: ScalarMoments) -> std::io::Result<()> {
    w.write_all(&moments.m.to_le_bytes())?;
    w.write_all(&moments.v.to_le_bytes())
}

/// A log-scale's moments (a non-finite one is an error: a state is written only from finite ones).
fn read_moments(r: &mut impl Read, what: &str) -> Result<ScalarMoments> {
    let moments = ScalarMoments {
        m: f32::from_le_bytes(read_array(r)?),
        v: f32::from_le_bytes(read_array(r)?),
    };
    if !(moments.m.is_finite() && moments.v.is_finite()) {
        bail!("non-finite moments of {what}");
    }
    Ok(moments)
}

fn write_text(w: &mut impl Write, text: &str) -> std::io::Result<()> {
    w.write_all(&(text.len() as u64).to_le_bytes())?;
    w.write_all(text.as_bytes())
}

/// Reads a state file; an error if it is not one, is cut short, or belongs to another run (its
/// fingerprint differs from `fingerprint`).
pub fn read_state(path: &Path, fingerprint: &str) -> Result<(Position, Parameters)> {
    let file = crate::io::input::open_regular(path)
        .with_context(|| format!("cannot open '{}'", path.display()))?;
    let size = file.metadata().map(|m| m.len()).unwrap_or(0);
    let mut r = Summed::new(BufReader::new(file));
    let context = || {
        format!(
            "'{}' is not a complete volgrad optimizer state",
            path.display()
        )
    };
    let mut magic = vec![0u8; MAGIC.len()];
    r.read_exact(&mut magic).with_context(context)?;
    if magic != MAGIC {
        bail!("{}", context());
    }
    let stored = read_text(&mut r, size).with_context(context)?;
    if stored != fingerprint {
        bail!(
            "'{}' belongs to another run: the run file, its scene, its targets, --seed or --estimator differ from the checkpoint's, or another version of volgrad wrote it (fingerprint {stored}, now {fingerprint})",
            path.display()
        );
    }
    let mut read = || -> Result<(Position, Parameters)> {
        let stop = read_text(&mut r, size)?;
        let stop = (!stop.is_empty()).then(|| Stop::parse(&stop)).transpose()?;
        let iteration = u64::from_le_bytes(read_array(&mut r)?);
        let level = u32::from_le_bytes(read_array(&mut r)?);
        let steps = u32::from_le_bytes(read_array(&mut r)?);
        let scale = read_moments(&mut r, "the global scale")?;
        let exposure_count = u32::from_le_bytes(read_array(&mut r)?);
        if u64::from(exposure_count) * 12 > size {
            bail!("{exposure_count} exposures do not fit in {size} bytes");
        }
        let mut exposures = Vec::with_capacity(exposure_count as usize);
        for _ in 0..exposure_count {
            let exposure = Exposure {
                log: f32::from_le_bytes(read_array(&mut r)?),
                moments: read_moments(&mut r, "an exposure")?,
            };
            if !exposure.log.is_finite() {
                bail!("a non-finite exposure");
            }
            exposures.push(exposure);
        }
        let optimisation_seconds = f64::from_le_bytes(read_array(&mut r)?);
        let evaluation_seconds = f64::from_le_bytes(read_array(&mut r)?);
        let log = read_text(&mut r, size)?;
        let count = u64::from_le_bytes(read_array(&mut r)?);
        let brick_bytes = (12 + 3 * 4 * BRICK_VOXELS + 8 + 4) as u64;
        if count.saturating_mul(brick_bytes) > size {
            bail!("{count} bricks do not fit in {size} bytes");
        }
        let mut p = Parameters::default();
        for _ in 0..count {
            let (key, theta) = read_brick(&mut r)?;
            let (m, v) = (read_values(&mut r)?, read_values(&mut r)?);
            let scale = read_moments(&mut r, "a brick's scale")?;
            let idle = u32::from_le_bytes(read_array(&mut r)?);
            p.insert_brick(key, theta, m, v, scale, idle);
        }
        let average_steps = u32::from_le_bytes(read_array(&mut r)?);
        let average_count = u64::from_le_bytes(read_array(&mut r)?);
        if average_count.saturating_mul((12 + 4 * BRICK_VOXELS) as u64) > size {
            bail!("{average_count} averaged bricks do not fit in {size} bytes");
        }
        let average = (0..average_count)
            .map(|_| read_brick(&mut r))
            .collect::<Result<Vec<_>>>()?;
        p.set_steps(steps, scale);
        p.exposures = exposures;
        p.average = Average::restore(average_steps, average);
        let position = Position {
            iteration,
            level,
            optimisation_seconds,
            evaluation_seconds,
            log,
            stop,
        };
        Ok((position, p))
    };
    let state = read().with_context(context)?;
    let sum = r.sum.hex();
    let mut written = [0u8; 16];
    if r.inner.read_exact(&mut written).is_err() || written != sum.as_bytes() {
        bail!(
            "'{}' is damaged: its checksum is not the one it was written with (changed on disk; resume from an earlier checkpoint)",
            path.display()
        );
    }
    Ok(state)
}

fn read_array<const N: usize>(r: &mut impl Read) -> Result<[u8; N]> {
    let mut b = [0u8; N];
    r.read_exact(&mut b)?;
    Ok(b)
}

fn read_text(r: &mut impl Read, file_size: u64) -> Result<String> {
    let n = u64::from_le_bytes(read_array(r)?);
    if n > file_size {
        bail!("a text of {n} bytes in a file of {file_size}");
    }
    let mut bytes = vec![0u8; n as usize];
    r.read_exact(&mut bytes)?;
    Ok(String::from_utf8(bytes)?)
}

/// Writes the run's result (θ, or its average once begun: `Parameters::result`) as a fog-volume
/// float grid named `name`, with `metadata`.
pub fn write_grid(
    path: &Path,
    parameters: &Parameters,
    transform: IndexTransform,
    name: &str,
    metadata: Vec<MetaEntry>,
) -> Result<()> {
    let grid = Grid {
        name: name.to_string(),
        grid_class: "fog volume".into(),
        transform,
        bricks: parameters.result(),
        background: 0.0,
        saved_as_half: false,
        metadata,
    };
    // The run's own files: the output folder was checked for foreign files before the run.
    vdb::write_grids(path, &[&grid], false, true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optimize::adam::Adam;
    use crate::optimize::brick_gradient::BrickGradient;

    #[test]
    fn an_earlier_runs_numbered_and_temporary_files_are_removed_and_nothing_else() {
        let dir = tempfile::tempdir().unwrap();
        let earlier = [
            "checkpoint-0002.vdb",
            "checkpoint-0002.state",
            "holdout-0002.png",
            ".checkpoint-0004.vdb.11580.tmp",
            ".progress.svg.3397.tmp",
        ];
        let others = [
            "notes.txt",
            "checkpoint-.vdb",
            ".hidden.tmp",
            "log.csv",
            "x.tmp",
        ];
        for name in earlier.iter().chain(&others) {
            std::fs::write(dir.path().join(name), "x").unwrap();
        }
        remove_earlier_run(dir.path()).unwrap();
        let mut left: Vec<String> = (std::fs::read_dir(dir.path()).unwrap())
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        let mut expected = others.map(String::from).to_vec();
        expected.sort();
        assert_eq!(left, expected);
    }

    #[test]
    fn state_round_trips_bit_for_bit_and_refuses_other_runs() {
        let dir = tempfile::tempdir().unwrap();
        let mut p = Parameters::default();
        p.set(IVec3::new(-9, 3, 100), 0.25);
        // With the global and brick scales, so that their moments are not 0 (θ·g = 0.25 · 0.5 at
        // the first voxel).
        let adam = Adam {
            fit_scale: true,
            fit_brick_scales: true,
            ..Default::default()
        };
        let gradient = [(IVec3::new(-9, 3, 100), 0.5), (IVec3::new(1, 2, 3), -0.5)];
        p.adam_step(
            &adam,
            &BrickGradient::from_voxels(gradient),
            &BrickGradient::default(),
        );
        // An average of two iterates (three bricks), the second with a brick the first lacks.
        p.add_to_average();
        p.set(IVec3::new(40, 0, 0), 0.75);
        p.add_to_average();
        let position = Position {
            iteration: 42,
            level: 1,
            optimisation_seconds: 1.5,
            evaluation_seconds: 0.25,
            log: "1,2,3\n".into(),
            stop: Some(Stop::Replay(vec![0.0, 0.5])),
        };
        // Two captures' exposures, each with its own moments.
        for (k, log) in [0.125f32, -0.25].into_iter().enumerate() {
            p.exposures.push(Exposure {
                log,
                moments: ScalarMoments {
                    m: k as f32,
                    v: 0.5,
                },
            });
        }
        let path = dir.path().join("checkpoint-0042.state");
        write_state(&path, "abc", &position, &p).unwrap();
        let (back, q) = read_state(&path, "abc").unwrap();
        assert_eq!(back, position);
        assert_eq!(q.exposures, p.exposures);
        assert_eq!(q.steps(), p.steps());
        assert_ne!(p.scale_moments(), ScalarMoments::default());
        assert_eq!(q.scale_moments(), p.scale_moments());
        let brick_scale =
            |p: &Parameters| p.sorted_bricks().iter().map(|b| b.4).collect::<Vec<_>>();
        assert!(brick_scale(&p)
            .iter()
            .any(|&s| s != ScalarMoments::default()));
        let bits = |p: &Parameters| -> Vec<u32> {
            p.sorted_bricks()
                .into_iter()
                .flat_map(|(k, t, m, v, scale, _)| {
                    let scale = [scale.m, scale.v];
                    k.to_array()
                        .map(|c| c as u32)
                        .into_iter()
                        .chain(
                            t.iter()
                                .chain(m)
                                .chain(v)
                                .chain(&scale)
                                .map(|x| x.to_bits()),
                        )
                        .collect::<Vec<_>>()
                })
                .collect()
        };
        assert_eq!(bits(&q), bits(&p));
        let average = |p: &Parameters| -> (u32, Vec<(IVec3, Vec<u32>)>) {
            let bricks = p.average.sorted().into_iter();
            let bits = bricks.map(|(k, v)| (k, v.iter().map(|x| x.to_bits()).collect()));
            (p.average.steps(), bits.collect())
        };
        assert_eq!(p.average.steps(), 2);
        assert_eq!(p.average.sorted().len(), 3);
        assert_eq!(average(&q), average(&p));
        assert_eq!(latest(dir.path()).unwrap(), path);

        let err = read_state(&path, "other").err().unwrap().to_string();
        assert!(err.contains("another run"), "{err}");
        let bytes = std::fs::read(&path).unwrap();
        // One bit changed in the middle (among the bricks' θ, m and v) or in the average's last
        // value: each still a state in form, which only the checksum tells from the run's.
        for (at, flip) in [(bytes.len() / 2, 0x01u8), (bytes.len() - 17, 0x01)] {
            let mut damaged = bytes.clone();
            damaged[at] ^= flip;
            std::fs::write(&path, &damaged).unwrap();
            let err = read_state(&path, "abc").err().unwrap().to_string();
            assert!(err.contains("damaged"), "{err}");
        }
        std::fs::write(&path, &bytes[..bytes.len() - 100]).unwrap();
        let err = read_state(&path, "abc").err().unwrap().to_string();
        assert!(err.contains("not a complete"), "{err}");
    }
}
