//! The reference gradient: the mean of joint and drt runs with per-voxel standard errors, saved
//! to and read from a VDB, and checked against finite differences before it is trusted.

use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::IVec3;

use super::{mean_adjoint, REFERENCE_SEED_OFFSET};
use crate::gradient::adjoint::{Estimator, Suffix};
use crate::gradient::fd::{self, FdOptions};
use crate::gradient::gradcheck::Check;
use crate::gradient::grid::GradientGrid;
use crate::gradient::loss::Loss;
use crate::gradient::passes::{gradient, GradOptions};
use crate::gradient::runs::{seeded_runs, MeanAndError};
use crate::io::gradient_files::{self, Provenance};
use crate::io::vdb::{self, meta, GridSelector};
use crate::render::fingerprint;
use crate::render::scene::Scene;

pub struct Reference {
    pub mean: GradientGrid,
    /// Standard error of `mean`, per voxel.
    pub stderr: GradientGrid,
    /// Standard error of ⟨mean, 1⟩ (from the runs' totals: voxels are correlated within a run).
    pub sum_se: f64,
    pub spp_per_run: u32,
    pub runs: u32,
    /// The runs' seeds, comma-separated (joint's and drt's alternate), as `volgrad_seed` holds
    /// them: a reference can be built again from its own file.
    pub seeds: String,
}

#[derive(Debug, Clone, Copy)]
pub struct ReferenceOptions {
    pub spp: u32,
    /// Seeds per estimator: joint and drt each run this many times.
    pub seeds: u32,
    pub seed: u64,
    pub max_depth: u32,
    pub progress: bool,
}

/// Mean of `seeds` joint runs and `seeds` drt runs at `spp` each, with per-voxel standard errors.
pub fn build_reference(scene: &Scene, o: &ReferenceOptions) -> Reference {
    let adjoint = mean_adjoint(scene);
    let mut sum = GradientGrid::<f64>::for_medium(&scene.medium);
    let mut squares = sum.empty_like();
    let runs = 2 * o.seeds.max(1);
    let bar = crate::io::progress::bar(o.progress, runs as u64, "reference");
    // Each run is folded into the sums as it ends: a reference keeps two grids, not one per run.
    let first_seed = o.seed.wrapping_add(REFERENCE_SEED_OFFSET);
    let totals = seeded_runs(first_seed, runs, |r, seed| {
        let estimator = if r % 2 == 0 {
            Estimator::Joint
        } else {
            Estimator::Drt
        };
        let g = gradient(
            scene,
            &adjoint,
            &GradOptions::new(estimator, o.spp, seed, o.max_depth),
        )
        .values();
        sum.merge(&g, 1.0);
        for (v, x) in g.voxels() {
            if x != 0.0 {
                squares.add(v, x * x);
            }
        }
        bar.inc(1);
        g.sum()
    });
    bar.finish_and_clear();
    let n = runs as f64;
    let mut mean = sum;
    mean.scale(1.0 / n);
    let mut stderr = mean.empty_like();
    for (v, s2) in squares.voxels() {
        if s2 != 0.0 {
            let m = mean.get(v);
            let variance = ((s2 / n - m * m) * n / (n - 1.0)).max(0.0);
            stderr.add(v, (variance / n).sqrt());
        }
    }
    Reference {
        mean,
        stderr,
        sum_se: MeanAndError::of(&totals).se,
        spp_per_run: o.spp,
        runs,
        seeds: (0..runs)
            .map(|r| first_seed.wrapping_add(r as u64).to_string())
            .collect::<Vec<_>>()
            .join(","),
    }
}

/// What a reference of `runs` runs of `spp_per_run` with `seeds` on `scene` is the gradient of.
fn reference_provenance(scene: &Scene, runs: u32, spp_per_run: u32, seeds: &str) -> Provenance {
    Provenance {
        estimator: "joint+drt".into(),
        spp: spp_per_run as u64 * runs as u64,
        seed: seeds.into(),
        loss: Loss::Mean.to_string(),
        scene: scene.path.display().to_string(),
        scene_fingerprint: fingerprint::scene(scene),
        target_fingerprint: "none".into(),
        domain: "all".into(),
        max_depth: scene.settings.max_depth,
        suffix: Suffix::PerPath.to_string(),
        parameter: "extinction".into(),
    }
}

/// Writes `grad_<grid>` (the mean) and `grad_<grid>_stderr` to one VDB.
pub fn save_reference(path: &Path, scene: &Scene, r: &Reference, overwrite: bool) -> Result<()> {
    let provenance = reference_provenance(scene, r.runs, r.spp_per_run, &r.seeds);
    let transform = scene.medium.transform;
    let extra = [
        meta("volgrad_sum_stderr", "string", r.sum_se),
        meta("volgrad_reference_runs", "int64", r.runs),
        meta("volgrad_reference_spp", "int64", r.spp_per_run),
    ];
    let mut mean = gradient_files::gradient_grid(
        r.mean.to_brickmap(),
        &scene.grid_name,
        transform,
        &provenance,
    );
    mean.metadata.extend(extra.iter().cloned());
    let mut se = gradient_files::gradient_grid(
        r.stderr.to_brickmap(),
        &scene.grid_name,
        transform,
        &provenance,
    );
    se.name = format!("grad_{}_stderr", scene.grid_name);
    se.metadata.extend(extra.iter().cloned());
    vdb::write_grids(path, &[&mean, &se], false, overwrite)
}

/// Reads a reference written by `save_reference` for this scene's grid.
pub fn load_reference(path: &Path, scene: &Scene) -> Result<Reference> {
    let name = format!("grad_{}", scene.grid_name);
    let read = |n: &str| {
        vdb::read_grid(path, &GridSelector::Name(n.to_string())).with_context(|| {
            format!(
                "'{}' has no grid '{n}': pass a reference written by `volgrad compare` for this scene",
                path.display()
            )
        })
    };
    let mean = read(&name)?;
    let se = read(&format!("{name}_stderr"))?;
    if mean.transform != scene.medium.transform || se.transform != scene.medium.transform {
        bail!(
            "the reference '{}' has another transform than the scene's grid: it was made for another scene",
            path.display()
        );
    }
    let get = |key: &str| {
        mean.metadata
            .iter()
            .find(|e| e.name == key)
            .map(|e| e.value.clone())
    };
    // The scene's content, the loss, the parameter, the domain and the depth: a reference of
    // another computation would score every estimator against the wrong answer.
    let found = Provenance::from_metadata(&mean.metadata, path)?;
    let wanted = reference_provenance(scene, 1, 1, "").computation();
    if let Some(((field, value), (_, want))) =
        (found.computation().into_iter().zip(wanted)).find(|(a, b)| a != b)
    {
        bail!(
            "the reference '{}' is of another computation: its {field} is '{value}', this scene's '{want}' (a scene or setting changed since it was made: build it again without --reference)",
            path.display()
        );
    }
    let number = |key: &str| -> Result<f64> {
        get(key).and_then(|s| s.parse().ok()).with_context(|| {
            format!(
                "'{}' has no {key} metadata: not a reference written by `volgrad compare`",
                path.display()
            )
        })
    };
    let sum_se = number("volgrad_sum_stderr")?;
    let runs = number("volgrad_reference_runs")? as u32;
    let spp_per_run = number("volgrad_reference_spp")? as u32;
    let to_gradient = |grid: &vdb::Grid| -> Result<GradientGrid> {
        let mut g = GradientGrid::for_medium(&scene.medium);
        let domain = fd::domain_bounds(&scene.medium.grid);
        for leaf in grid.bricks.leaves() {
            for (o, &value) in leaf.values.iter().enumerate() {
                if value == 0.0 {
                    continue;
                }
                let v = leaf.origin
                    + IVec3::new((o >> 6) as i32, ((o >> 3) & 7) as i32, (o & 7) as i32);
                if !domain.is_some_and(|(lo, hi)| v.cmpge(lo).all() && v.cmple(hi).all()) {
                    bail!(
                        "the reference '{}' has a value at voxel {v}, outside this scene's grid: it was made for another grid",
                        path.display()
                    );
                }
                g.add(v, value as f64);
            }
        }
        Ok(g)
    };
    Ok(Reference {
        mean: to_gradient(&mean)?,
        stderr: to_gradient(&se)?,
        sum_se,
        spp_per_run,
        runs,
        seeds: found.seed,
    })
}

/// Optical depth that the ⟨g, 1⟩ finite difference adds across the domain's longest side. A step
/// in grid units would not do: ε added to every voxel of the cloud's box (mostly empty space) at
/// the per-voxel step 0.15 added τ ≈ 15 and the stencil read 0.30 for a derivative of 0.43. The
/// one-sided stencil reaches 3ε, and its error grows as ε³: at τ = 2 it read 6 % high on the
/// tests' lumpy block (−0.0606 ± 0.0005 at 8,192 spp against joint's −0.0570 ± 0.0007), and at
/// τ = 1 8 % low on `scenes/single-voxel.toml` (0.2379 ± 0.0014 against 0.2580 ± 0.0001), which
/// made `compare` refuse a right reference there. At 0.3 that bias is a few tenths of a percent.
pub const ONES_OPTICAL_STEP: f64 = 0.3;

/// The fd step for ⟨g, 1⟩ over the whole domain (see `ONES_OPTICAL_STEP`).
pub fn ones_eps(scene: &Scene) -> f32 {
    let Some((lo, hi)) = fd::domain_bounds(&scene.medium.grid) else {
        return 1.0;
    };
    let side = ((hi - lo + 1).as_dvec3() * scene.medium.transform.voxel_size()).max_element();
    (ONES_OPTICAL_STEP / (scene.medium.density_scale as f64 * side).max(1e-12)) as f32
}

/// The reference against finite differences: the `voxels` voxels of largest |g| among those the
/// reference resolves (|g| > 4 se: the largest |g| overall are often one run's outlier), with
/// `fd::auto_eps`, and ⟨g, 1⟩ over the whole domain with `ones_eps`. `fd_options.eps` is not used.
pub fn check_reference(
    scene: &Scene,
    r: &Reference,
    fd_options: &FdOptions,
    voxels: usize,
) -> Result<Vec<Check>> {
    let grid = &scene.medium.grid;
    let mut strongest: Vec<(IVec3, f64, f64)> = r
        .mean
        .voxels()
        .map(|(v, g)| (v, g, r.stderr.get(v)))
        .filter(|&(_, g, se)| se > 0.0 && g.abs() > 4.0 * se)
        .collect();
    strongest.sort_by(|a, b| {
        b.1.abs()
            .total_cmp(&a.1.abs())
            .then((a.0.x, a.0.y, a.0.z).cmp(&(b.0.x, b.0.y, b.0.z)))
    });
    let mut checks: Vec<Check> = strongest
        .iter()
        .take(voxels)
        .map(|&(v, g, se)| {
            let direction = vec![(v, 1.0)];
            Ok(Check {
                name: format!("voxel {v}"),
                estimate: g,
                estimate_se: se,
                fd: fd::directional_derivative(
                    scene,
                    None,
                    &direction,
                    &FdOptions {
                        eps: fd::auto_eps(scene, &direction),
                        ..*fd_options
                    },
                )?,
            })
        })
        .collect::<Result<_>>()?;
    if let Some((lo, hi)) = fd::domain_bounds(grid) {
        fd::ensure_enumerable(grid, lo, hi)?;
        let domain = fd::box_voxels(grid, lo, hi, false);
        let ones = FdOptions {
            eps: ones_eps(scene),
            ..*fd_options
        };
        checks.push(Check {
            name: format!("⟨g, 1⟩ over the domain (ε = {:.3e})", ones.eps),
            estimate: r.mean.sum(),
            estimate_se: r.sum_se,
            fd: fd::directional_derivative(scene, None, &fd::ones(&domain), &ones)?,
        });
    }
    Ok(checks)
}
