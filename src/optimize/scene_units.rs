//! The units a run's settings are given in, and how they become the grid's own. A user reasons in
//! optical depth and pixels, not in the values their VDB happens to store (a cloud's reach 1, a
//! simulation's 100), so the settings that would be grid values are given as optical depths along
//! the unknown's box and the images' own brightness:
//!
//! - u = 1 / (density_scale · E), with E the longest edge of the unknown's box in world units: the
//!   grid value whose optical depth along that edge is 1. A learning rate, a start and a prior's
//!   scale given as an optical depth τ are τ·u in grid values, as `gradcheck` picks its ε.
//! - P = mean of the training targets' squared pixel values: the L2 loss of a black image. A
//!   prior's weight W is relative to it, so the prior holds the same share of the loss whatever
//!   the lights' brightness: R(θ) = W·P·mean φ(Δτ) is w·mean φ(Δθ) with w = W·P/u.
//! - The coarsest level's voxel is at least one pixel's footprint at the medium (finer voxels are
//!   found by the upsamplings, once the coarse structure is in place).
//!
//! The defaults below are the settings tuned on the Disney cloud (`scenes/inverse/cloud.toml`)
//! expressed in these units, so that they carry over to scenes of other sizes, grid units and
//! lights.

use crate::render::scene_check::{MAX_EXTINCTION, MAX_LIGHT};
use glam::Vec3;

use crate::optimize::prior::{Prior, PriorKind};
use crate::optimize::run_file::UnknownGrid;
use crate::render::camera::Camera;
use crate::render::lights::luminance;
use crate::render::scene::Scene;
use crate::volume::albedo::Albedo;
use crate::volume::emission::EmissionKind;

/// Optical depth along the box's longest edge that one Adam step may change (the learning rate).
/// 0.75 rather than the cloud's hand-tuned 0.5: with `LR_DECAY` 0.3, over three seeds of 10
/// minutes, the smoke plume gained +0.7–1.2 dB held-out and the cloud +0.5–1.0 dB, with 0.70–0.87×
/// the haze on both (measured at 211173b).
pub const STEP_OPTICAL_DEPTH: f32 = 0.75;
/// The learning rate at the end of a run, as a fraction of the first (exponential decay in
/// between). Budget-bound runs still improve at the end and want their steps kept long; a small
/// example that converges within its steps wants them short (`scenes/inverse/quick.toml` sets 0.1).
pub const LR_DECAY: f32 = 0.3;
/// A constant start's optical depth along the box's longest edge, in the views' visual hull
/// (`hull`: cleared where a view sees the background). From nothing, density can only grow where
/// light already scatters towards a camera; and what the views cannot see into, a thick volume's
/// inside, keeps about the start. At 2.5, before the hull, the start filled the whole box as a thin
/// haze; with the hull, 7.5 gave the smoke plume +3.7 dB held-out and a volume RMSE 0.82× at 1000
/// iterations, and the cloud +0.26 dB, 0.95× at 500 (measured at b8aa2c8).
pub const START_OPTICAL_DEPTH: f32 = 7.5;
/// Where total variation's kink at 0 is rounded off, as an optical depth.
const TV_EPSILON_OPTICAL_DEPTH: f64 = 0.05;
/// The default priors: light total variation (sharpens the boundary the pixels blur) and the log
/// prior with δ = 0.5 (clears faint haze, leaves dense voxels alone), weights relative to P. On
/// the cloud (u = 0.01948, P = 0.2517) they are its tuned 0.003 and 0.1 (δ 0.01) in grid units,
/// as strong as they were when R was a mean over the stored voxels: on the cloud's first level
/// those were 2.24× the level's voxels (the bricks its box and the trilinear apron touch).
pub const DEFAULT_TV_WEIGHT: f32 = 1.03e-4;
pub const DEFAULT_LOG_WEIGHT: f32 = 3.44e-3;
pub const DEFAULT_LOG_SCALE: f32 = 0.5;
/// An emission unknown's u is the glow unit over this (`SceneUnits::for_emission`).
const EMISSION_UNITS_PER_GLOW: f64 = 25.0;
/// The most upsamplings a run may do (each ×2 per axis).
pub const MAX_LEVELS: usize = 6;

#[derive(Debug, Clone, Copy)]
pub struct SceneUnits {
    /// u: grid value per unit of optical depth along the box's longest edge.
    pub theta_per_optical_depth: f64,
    /// P: the training targets' mean squared pixel value.
    pub image_power: f64,
    /// The largest θ the renderer takes: an extinction of `MAX_EXTINCTION`, or an emission of
    /// `MAX_LIGHT`. Steps are held below it (a medium beyond it is opaque long before, and its
    /// tracking would take hours).
    pub theta_max: f32,
}

/// The grid value of the largest extinction the renderer takes (`MAX_EXTINCTION`).
fn max_extinction_value(density_scale: f32) -> f32 {
    (MAX_EXTINCTION / f64::from(density_scale).max(1e-30)).min(f64::from(f32::MAX)) as f32
}

/// The grid value of the largest emission the renderer takes (`MAX_LIGHT`).
fn max_emission_value(radiance: Vec3) -> f32 {
    MAX_LIGHT / radiance.max_element().max(1e-30)
}

/// The radiance an emission unknown's values multiply.
fn emission_radiance(scene: &Scene) -> anyhow::Result<Vec3> {
    match scene.medium.emission.as_ref().map(|e| &e.kind) {
        Some(EmissionKind::Radiance(radiance)) => Ok(*radiance),
        _ => anyhow::bail!("an emission unknown needs radiance × value emission (checked on load)"),
    }
}

impl SceneUnits {
    pub fn new(density_scale: f32, longest_edge: f64, image_power: f64) -> Self {
        SceneUnits {
            theta_per_optical_depth: 1.0 / (f64::from(density_scale) * longest_edge).max(1e-30),
            image_power,
            theta_max: max_extinction_value(density_scale),
        }
    }

    /// `theta_max` of a scene's unknown, which needs no targets: a start beyond it is refused
    /// before any target is rendered.
    pub fn theta_max_of(scene: &Scene, unknown: UnknownGrid) -> anyhow::Result<f32> {
        Ok(match unknown {
            UnknownGrid::Density => max_extinction_value(scene.medium.density_scale),
            UnknownGrid::Emission => max_emission_value(emission_radiance(scene)?),
        })
    }

    /// The units of an emission unknown (flame tomography, `unknown.grid = "emission"` with
    /// `radiance = [r, g, b]` × value): no optical depth there, so u is 1/25 of the glow unit
    /// U = √P / (luminance(radiance) · (1 − α)), the value whose emission σa·Le, seen through a
    /// thick medium, is as bright as the targets. A step is then 0.03·U and the start 0.3·U (the
    /// images are linear in the emission, and the start need not seed anything: every voxel
    /// with density has gradient).
    pub fn for_emission(scene: &Scene, image_power: f64) -> anyhow::Result<Self> {
        let medium = &scene.medium;
        let radiance = emission_radiance(scene)?;
        // The grid's albedo varies: its absorption is taken as the middle of its range.
        let absorbed = match &medium.albedo {
            Albedo::Constant(albedo) => luminance(Vec3::ONE - *albedo),
            Albedo::Grid(_) => 0.5,
        };
        let glow = f64::from(luminance(radiance) * absorbed).max(1e-30);
        // Black targets (P = 0) would make u = 0, and a prior's weight W·P/u 0/0: their emission
        // is 0 everywhere, which a tiny unit still reaches.
        let brightness = image_power.sqrt().max(1e-12);
        Ok(SceneUnits {
            theta_per_optical_depth: brightness / glow / EMISSION_UNITS_PER_GLOW,
            image_power,
            theta_max: max_emission_value(radiance),
        })
    }

    /// The grid value of an optical depth τ along the box's longest edge.
    pub fn theta(&self, optical_depth: f32) -> f32 {
        (f64::from(optical_depth) * self.theta_per_optical_depth) as f32
    }

    /// A prior given with weight W (relative to P) and, for `log`, δ as an optical depth, in
    /// grid units: w = W·P/u^k for a penalty of degree k in θ (k = 2 for `laplacian`'s squared
    /// differences: W·P·(Δθ/u)² = (W·P/u²)·Δθ²; 1 for the others), δ·u, and total variation's ε·u.
    pub fn prior(&self, kind: PriorKind, weight: f32, scale: Option<f32>) -> Prior {
        let u = self.theta_per_optical_depth;
        let degree = if kind == PriorKind::Laplacian { 2 } else { 1 };
        Prior {
            kind,
            weight: (f64::from(weight) * self.image_power / u.powi(degree)) as f32,
            scale: scale.map_or(0.0, |d| self.theta(d)),
            tv_epsilon: TV_EPSILON_OPTICAL_DEPTH * u,
        }
    }
}

/// The finest of `cameras`' pixel footprints at `centre`, in world units.
pub fn footprint(cameras: &[Camera], centre: Vec3) -> f64 {
    let finest = cameras.iter().map(|c| c.pixel_footprint(centre));
    f64::from(finest.fold(f32::INFINITY, f32::min))
}

/// The fewest upsamplings that make the coarsest voxel at least one pixel's footprint, given in
/// final voxels: ⌈log2(footprint)⌉, in 0..=`MAX_LEVELS`. A footprint within 5 % above a power of
/// two counts as it: the voxel `bounds = "views"` derives is the footprint at the box's centre
/// before the box is rounded out to whole voxels, and the rounding moves the centre by up to half
/// a voxel (the footprint then comes back as 1.003 voxels on 24² views).
pub fn level_count(footprint_voxels: f64) -> usize {
    let levels = (footprint_voxels / FOOTPRINT_ROUNDING).log2().ceil();
    if !(levels.is_finite() && levels > 0.0) {
        return 0;
    }
    (levels as usize).min(MAX_LEVELS)
}

/// How far above a power of two a footprint may be and still count as it (`level_count`).
const FOOTPRINT_ROUNDING: f64 = 1.05;

/// The fewest voxels a derived first level has along the box's shortest edge: views far from a
/// small box would otherwise derive upsamplings down to a first level of no voxel at all.
pub const MIN_FIRST_LEVEL_VOXELS: u64 = 4;

/// The most upsamplings a box whose shortest edge is `edge_voxels` final voxels takes when the
/// count is derived: a first level of at least `MIN_FIRST_LEVEL_VOXELS` along that edge.
pub fn levels_the_box_allows(edge_voxels: u64) -> usize {
    let ratio = edge_voxels / MIN_FIRST_LEVEL_VOXELS;
    if ratio == 0 {
        0
    } else {
        (ratio.ilog2() as usize).min(MAX_LEVELS)
    }
}

/// When each of `count` levels begins, as fractions of the run: the coarsest gets the first 40 %
/// (the views pin it down best and its steps are the cheapest), the others begin evenly up to
/// 95 % (the finest level adds detail finer than a pixel, which the views see least).
pub fn level_starts(count: usize) -> Vec<f32> {
    match count {
        0 => Vec::new(),
        1 => vec![0.4],
        n => (0..n)
            .map(|k| ((40 * (n - 1) + 55 * k) as f64 / (100 * (n - 1)) as f64) as f32)
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grid in other units (values ×100, density_scale ÷100) resolves the same settings to
    /// grid values 100× larger, and so does the same medium in a box half the size at twice
    /// the density scale: the optical depths stay what they were.
    #[test]
    fn settings_follow_the_grid_units_and_the_box() {
        let cloud = SceneUnits::new(0.1, 500.0, 0.04);
        let hundred = SceneUnits::new(0.001, 500.0, 0.04);
        assert!((hundred.theta(0.5) / cloud.theta(0.5) - 100.0).abs() < 1e-3);
        assert!((cloud.theta(0.5) - 0.01).abs() < 1e-7);
        let half = SceneUnits::new(0.2, 250.0, 0.04);
        assert!((half.theta(0.5) - cloud.theta(0.5)).abs() < 1e-9);
        // The prior's grid weight scales with 1/u and with P.
        let w = |units: SceneUnits| units.prior(PriorKind::Log, 1.0, Some(0.5));
        assert!((w(hundred).weight * 100.0 / w(cloud).weight - 1.0).abs() < 1e-4);
        let brighter = SceneUnits::new(0.1, 500.0, 0.16);
        assert!((w(brighter).weight / w(cloud).weight - 4.0).abs() < 1e-4);
        assert!((w(cloud).scale - 0.01).abs() < 1e-7);
        // The Laplacian squares differences of θ: its weight scales with 1/u².
        let laplacian = |units: SceneUnits| units.prior(PriorKind::Laplacian, 1.0, None).weight;
        assert!((laplacian(hundred) * 1e4 / laplacian(cloud) - 1.0).abs() < 1e-4);
        assert!(
            (laplacian(cloud) * cloud.theta(1.0).powi(2) / (w(cloud).weight * cloud.theta(1.0))
                - 1.0)
                .abs()
                < 1e-4
        );
    }

    #[test]
    fn the_coarsest_voxel_is_about_a_pixel() {
        // 64 pixels over 2·1000·tan 20° = 728 world units: 11.4 per pixel at the centre.
        let camera = Camera::new(
            Vec3::new(0.0, 0.0, 1000.0),
            Vec3::ZERO,
            Vec3::Y,
            40.0,
            64,
            64,
        );
        assert!((camera.pixel_footprint(Vec3::ZERO) - 11.37).abs() < 0.01);
        // The Disney cloud's 3.33-unit voxels: 3.4 voxels per pixel, two upsamplings.
        let count =
            |cameras: &[Camera], voxel: f64| level_count(footprint(cameras, Vec3::ZERO) / voxel);
        assert_eq!(count(&[camera], 10.0 / 3.0), 2);
        assert_eq!(count(&[camera], 10.5), 1);
        // 1.03 voxels a pixel: within the 5 % that counts as one.
        assert_eq!(count(&[camera], 11.0), 0);
        assert_eq!(count(&[camera], 12.0), 0);
        // A voxel of the footprint itself, as `bounds = "views"` derives it, after rounding.
        assert_eq!(level_count(1.003), 0);
        assert_eq!(level_count(2.04), 1);
        assert_eq!(level_count(1.1), 1);
        assert_eq!(count(&[camera], 0.01), MAX_LEVELS);
        // The finest view decides: 2.84 units per pixel.
        let near = Camera::new(
            Vec3::new(0.0, 0.0, 250.0),
            Vec3::ZERO,
            Vec3::Y,
            40.0,
            64,
            64,
        );
        assert_eq!(count(&[camera, near], 10.0 / 3.0), 0);
        assert_eq!(count(&[camera, near], 2.0), 1);
        assert_eq!(level_starts(2), vec![0.4, 0.95]);
        let three = level_starts(3);
        assert!(
            (three[1] - 0.675).abs() < 1e-6 && three[2] == 0.95,
            "{three:?}"
        );
    }
}
