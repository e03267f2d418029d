//! Finite differences: the reference every gradient estimator is tested against.
//!
//! d loss/d ε along a direction v (a voxel, a box, all ones, random ±1) by central differences
//! (L(θ+εv) − L(θ−εv)) / 2ε with common random numbers: both renders use the same seeds and the same
//! majorant grid (built for θ + ε|v|), so they make the same tentative collisions and differ only
//! where the perturbation flips a decision. Where θ − ε|v| would be negative (empty voxels: a
//! negative σt cannot be free-flight sampled) the one-sided second-order formula
//! (−3L(θ) + 4L(θ+εv) − L(θ+2εv)) / 2ε is used instead. Repeating with several seeds gives the
//! standard error.

use glam::IVec3;
use rand::Rng;

use crate::brickmap::BrickMap;
use crate::image_io::RgbImage;
use crate::loss::Loss;
use crate::majorant::{MajorantGrid, MajorantMode};
use crate::render::{render, RenderOptions};
use crate::sampling::pixel_rng;
use crate::scene::{MajorantName, Scene};

/// A sparse direction in parameter space.
pub type Direction = Vec<(IVec3, f32)>;

/// Every voxel a lookup in the medium can weight: the active box plus the one-voxel apron.
pub fn domain_bounds(grid: &BrickMap) -> Option<(IVec3, IVec3)> {
    grid.active_bounds().map(|(lo, hi)| (lo - 1, hi + 1))
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

/// ±1 on every voxel, from `seed`.
pub fn random_signs(voxels: &[IVec3], seed: u64) -> Direction {
    let mut rng = pixel_rng(seed, u64::MAX, 7);
    voxels
        .iter()
        .map(|&v| (v, if rng.gen::<bool>() { 1.0 } else { -1.0 }))
        .collect()
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

/// The scene with its grid replaced (bounds and transform kept) and a given majorant.
fn variant(scene: &Scene, grid: BrickMap, majorant: &MajorantGrid) -> Scene {
    let mut s = scene.clone();
    s.medium.grid = grid;
    s.medium.majorant = majorant.clone();
    s
}

/// d loss / d ε along `direction`.
pub fn directional_derivative(
    scene: &Scene,
    target: Option<&RgbImage>,
    direction: &Direction,
    options: &FdOptions,
) -> FdResult {
    let grid = &scene.medium.grid;
    let eps = options.eps;
    let one_sided = direction
        .iter()
        .any(|&(v, d)| grid.voxel(v) - eps * d.abs() < 0.0);
    let reach = if one_sided { 2.0 } else { 1.0 };
    let upper = grid.with_added(
        &direction
            .iter()
            .map(|&(v, d)| (v, reach * eps * d.abs()))
            .collect::<Vec<_>>(),
    );
    let mode = match scene.settings.majorant {
        MajorantName::Global => MajorantMode::Global,
        MajorantName::Grid => MajorantMode::Grid {
            cell_voxels: scene.settings.majorant_cell,
        },
    };
    let majorant = MajorantGrid::build(
        &upper,
        scene.medium.bounds,
        scene.medium.density_scale,
        mode,
    );
    // (coefficient, scene) pairs whose weighted losses sum to the derivative estimate.
    let stencil: Vec<(f64, Scene)> = if one_sided {
        vec![
            (-3.0, variant(scene, grid.clone(), &majorant)),
            (
                4.0,
                variant(scene, grid.with_added(&scaled(direction, eps)), &majorant),
            ),
            (
                -1.0,
                variant(
                    scene,
                    grid.with_added(&scaled(direction, 2.0 * eps)),
                    &majorant,
                ),
            ),
        ]
    } else {
        vec![
            (
                1.0,
                variant(scene, grid.with_added(&scaled(direction, eps)), &majorant),
            ),
            (
                -1.0,
                variant(scene, grid.with_added(&scaled(direction, -eps)), &majorant),
            ),
        ]
    };
    let samples: Vec<f64> = (0..options.repeats.max(2))
        .map(|r| {
            let render_options = RenderOptions {
                spp: options.spp,
                seed: options.seed.wrapping_add(r as u64),
                max_depth: options.max_depth,
                progress: false,
            };
            let sum: f64 = stencil
                .iter()
                .map(|(c, s)| c * options.loss.evaluate(&render(s, &render_options).0, target))
                .sum();
            sum / (2.0 * eps as f64)
        })
        .collect();
    let n = samples.len() as f64;
    let mean = samples.iter().sum::<f64>() / n;
    let var = samples.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / (n - 1.0);
    FdResult {
        value: mean,
        std_err: (var / n).sqrt(),
        one_sided,
    }
}
