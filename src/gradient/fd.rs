//! Finite differences: the reference every gradient estimator is tested against.
//!
//! d loss/d ε along a direction v (a voxel, a box, all ones, random ±1) by central differences
//! (L(θ+εv) − L(θ−εv)) / 2ε with common random numbers: both renders use the same seeds and the same
//! majorant grid (built for θ + ε|v|), so they make the same tentative collisions and differ only
//! where the perturbation flips a decision (each path has its own random stream, so a flip does not
//! shift the numbers of the pixel's other paths). Where θ − ε|v| would be negative (empty voxels: a
//! negative σt cannot be free-flight sampled) the one-sided third-order formula
//! (−11L(θ) + 18L(θ+εv) − 9L(θ+2εv) + 2L(θ+3εv)) / 6ε is used instead: its O(ε³) error stays below
//! the noise where the second-order one visibly biased ⟨g, 1⟩ (empty apron voxels make every
//! all-ones direction one-sided). Repeating with several seeds gives the standard error.
//!
//! Finite differences estimate d E\[loss(Î)\]/dε; for the mean loss that is d loss(E\[Î\])/dε, what the
//! gradient estimators compute. For l2-type losses the two differ by d Var(Î)/dε, which shrinks as
//! 1/spp: compare them with the mean loss, or at high spp.

use glam::IVec3;
use rand::Rng;

use crate::gradient::loss::Loss;
use crate::gradient::passes::{parameter_grid, parameter_grid_mut, Parameter};
use crate::io::images::RgbImage;
use crate::render::image::{render, RenderOptions};
use crate::render::sampling::pixel_rng;
use crate::render::scene::Scene;
use crate::volume::brickmap::BrickMap;
use crate::volume::majorant::MajorantGrid;

/// A sparse direction in parameter space.
pub type Direction = Vec<(IVec3, f32)>;

/// Every voxel a lookup in the medium can weight: the active box plus the one-voxel apron.
pub fn domain_bounds(grid: &BrickMap) -> Option<(IVec3, IVec3)> {
    grid.active_bounds().map(|(lo, hi)| (lo - 1, hi + 1))
}

/// The most voxels a finite-difference direction may enumerate (12 bytes each: 768 MiB).
pub const MAX_BOX_VOXELS: u64 = 1 << 26;

/// Fails, before anything is allocated, when the inclusive box `[lo, hi]` clipped to the domain
/// holds more voxels than a direction can list: a sparse grid's domain can span 10⁶ voxels per
/// axis while its data is small. Call before `box_voxels` on a box the user did not size.
pub fn ensure_enumerable(grid: &BrickMap, lo: IVec3, hi: IVec3) -> anyhow::Result<()> {
    let Some((dlo, dhi)) = domain_bounds(grid) else {
        return Ok(());
    };
    let (lo, hi) = (lo.max(dlo), hi.min(dhi));
    let count = (0..3).try_fold(1u64, |acc, a| {
        acc.checked_mul((hi[a] as i64 - lo[a] as i64 + 1).max(0) as u64)
    });
    match count {
        Some(n) if n <= MAX_BOX_VOXELS => Ok(()),
        _ => anyhow::bail!(
            "the box {lo}..{hi} spans {} voxels, more than the {MAX_BOX_VOXELS} a finite-difference direction can list: choose a smaller box",
            (0..3)
                .map(|a| ((hi[a] as i64 - lo[a] as i64 + 1).max(0)).to_string())
                .collect::<Vec<_>>()
                .join(" × ")
        ),
    }
}

/// Voxels of the inclusive box `[lo, hi]` clipped to the domain (only active ones if asked).
pub fn box_voxels(grid: &BrickMap, lo: IVec3, hi: IVec3, active_only: bool) -> Vec<IVec3> {
    let Some((dlo, dhi)) = domain_bounds(grid) else {
        return Vec::new();
    };
    let (lo, hi) = (lo.max(dlo), hi.min(dhi));
    let mut out = Vec::new();
    for x in lo.x..=hi.x {
        for y in lo.y..=hi.y {
            for z in lo.z..=hi.z {
                let v = IVec3::new(x, y, z);
                if !active_only || grid.is_active(v) {
                    out.push(v);
                }
            }
        }
    }
    out
}

pub fn ones(voxels: &[IVec3]) -> Direction {
    voxels.iter().map(|&v| (v, 1.0)).collect()
}

/// ±1 on every voxel, from `seed`; +1 where the grid value is below `floor` (a step down there would
/// make σt negative).
pub fn random_signs(grid: &BrickMap, voxels: &[IVec3], seed: u64, floor: f32) -> Direction {
    let mut rng = pixel_rng(seed, u64::MAX, 7);
    voxels
        .iter()
        .map(|&v| {
            (
                v,
                if rng.gen::<bool>() || grid.voxel(v) < floor {
                    1.0
                } else {
                    -1.0
                },
            )
        })
        .collect()
}

/// A step that changes the optical depth along the direction's longest chord by about 0.05: small
/// enough that the O(ε²)/O(ε³) errors of the stencils stay below a percent, large enough to keep
/// the difference above the noise. Capped at 0.15 × the grid's largest value.
pub fn auto_eps(scene: &Scene, direction: &Direction) -> f32 {
    let Some((lo, hi)) = direction
        .iter()
        .fold(None, |acc: Option<(IVec3, IVec3)>, &(v, _)| {
            Some(acc.map_or((v, v), |(a, b)| (a.min(v), b.max(v))))
        })
    else {
        return 1e-3;
    };
    let voxels_across = (hi - lo + 1).max_element() as f64;
    let chord = voxels_across * scene.medium.transform.voxel_size().max_element();
    let magnitude = direction
        .iter()
        .map(|(_, d)| d.abs())
        .fold(0.0f32, f32::max)
        .max(1e-6);
    let by_depth = 0.05 / (scene.medium.density_scale as f64 * chord * magnitude as f64).max(1e-12);
    (by_depth as f32).min(max_eps(&scene.medium.grid))
}

/// The largest step `auto_eps` takes, and the step when none is chosen per direction: 15 % of the
/// grid's largest value, so that a step is never a large change of the medium itself.
pub fn max_eps(grid: &BrickMap) -> f32 {
    0.15 * grid.max_value().max(1e-3)
}

#[derive(Debug, Clone, Copy)]
pub struct FdOptions {
    pub loss: Loss,
    /// Step along the direction, in grid-value units.
    pub eps: f32,
    pub spp: u32,
    /// Independent repetitions (seed, seed+1, ...) for the standard error; at least 2.
    pub repeats: u32,
    pub seed: u64,
    pub max_depth: u32,
}

#[derive(Debug, Clone, Copy)]
pub struct FdResult {
    pub value: f64,
    pub std_err: f64,
    /// Whether the one-sided formula was needed.
    pub one_sided: bool,
}

fn scaled(direction: &Direction, factor: f32) -> Direction {
    direction.iter().map(|&(v, d)| (v, d * factor)).collect()
}

/// d loss / d ε along `direction` in the density. Fails if even the one-sided stencil would make a
/// voxel negative.
pub fn directional_derivative(
    scene: &Scene,
    target: Option<&RgbImage>,
    direction: &Direction,
    options: &FdOptions,
) -> anyhow::Result<FdResult> {
    directional_derivative_of(
        scene,
        target,
        Parameter::Extinction,
        None,
        direction,
        options,
    )
}

/// d loss / d ε along `direction` in the grid of `parameter` (its `channel`, for an RGB albedo
/// grid). The density's steps keep σt ≥ 0 (one-sided where needed) and share a majorant; the
/// other grids do not steer sampling, so their steps are central and the renders see the same
/// paths.
pub fn directional_derivative_of(
    scene: &Scene,
    target: Option<&RgbImage>,
    parameter: Parameter,
    channel: Option<usize>,
    direction: &Direction,
    options: &FdOptions,
) -> anyhow::Result<FdResult> {
    let grid = parameter_grid(scene, parameter, channel);
    let eps = options.eps;
    let one_sided = parameter == Parameter::Extinction
        && direction
            .iter()
            .any(|&(v, d)| grid.voxel(v) - eps * d.abs() < 0.0);
    // (coefficient, step in units of ε) pairs; the estimate is Σ c·L(θ + k·ε·v) / (denominator·ε).
    let (stencil, denominator): (&[(f64, f32)], f64) = if one_sided {
        (&[(-11.0, 0.0), (18.0, 1.0), (-9.0, 2.0), (2.0, 3.0)], 6.0)
    } else {
        (&[(1.0, 1.0), (-1.0, -1.0)], 2.0)
    };
    let reach = stencil.iter().map(|(_, k)| k.abs()).fold(0.0, f32::max);
    if let Some(&(v, _)) = direction
        .iter()
        .find(|&&(v, d)| one_sided && grid.voxel(v) + reach * eps * d.min(0.0) < 0.0)
    {
        anyhow::bail!("the direction lowers voxel {v} (value {}) below 0 within {reach}·ε = {}: use a smaller --eps or a non-negative direction", grid.voxel(v), reach * eps);
    }
    let upper = grid.with_added(
        &direction
            .iter()
            .map(|&(v, d)| (v, reach * eps * d.abs()))
            .collect::<Vec<_>>(),
    );
    let majorant = (parameter == Parameter::Extinction).then(|| {
        MajorantGrid::build(
            &upper,
            scene.medium.bounds,
            scene.medium.density_scale,
            scene.settings.majorant(),
        )
        .with_hot_spots(&upper, scene.medium.transform.voxel_diagonal())
    });
    let scenes: Vec<(f64, Scene)> = stencil
        .iter()
        .map(|&(c, k)| {
            let mut s = scene.clone();
            *parameter_grid_mut(&mut s, parameter, channel) =
                grid.with_added(&scaled(direction, k * eps));
            if let Some(majorant) = &majorant {
                s.medium.majorant = majorant.clone();
            }
            (c, s)
        })
        .collect();
    let samples: Vec<f64> = (0..options.repeats.max(2))
        .map(|r| {
            let render_options = RenderOptions {
                spp: options.spp,
                seed: options.seed.wrapping_add(r as u64),
                max_depth: options.max_depth,
                progress: false,
            };
            let sum: f64 = scenes
                .iter()
                .map(|(c, s)| c * options.loss.evaluate(&render(s, &render_options).0, target))
                .sum();
            sum / (denominator * eps as f64)
        })
        .collect();
    let n = samples.len() as f64;
    let mean = samples.iter().sum::<f64>() / n;
    let var = samples.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / (n - 1.0);
    Ok(FdResult {
        value: mean,
        std_err: (var / n).sqrt(),
        one_sided,
    })
}
