//! The stability suite: small in-memory scenes built to break estimators (empty voxels, thin and
//! dense media, extreme albedos, a hot voxel, a rotated anisotropic grid, strong forward
//! scattering), each estimator's ⟨g, 1⟩ against finite differences, its spread, and a count of
//! non-finite values. Expected failures are marked, not hidden.

use anyhow::Result;
use glam::{DMat3, DVec3, IVec3, Vec3};

use super::{mean_adjoint, SWEEP_SEED_OFFSET};
use crate::gradient::adjoint::Estimator;
use crate::gradient::fd::{self, FdOptions, FdResult};
use crate::gradient::gradcheck::Check;
use crate::gradient::loss::Loss;
use crate::gradient::passes::{gradient, GradOptions};
use crate::gradient::runs::{seeded_runs, MeanAndError};
use crate::io::table::{Align, Table};
use crate::render::camera::Camera;
use crate::render::lights::{DirectionalLight, Environment, Lights};
use crate::render::scene::{RenderFile, Scene};
use crate::volume::albedo::Albedo;
use crate::volume::brickmap::BrickMap;
use crate::volume::majorant::Majorant;
use crate::volume::medium::{Filter, Medium};
use crate::volume::transform::IndexTransform;

pub struct StabilityScene {
    pub name: &'static str,
    /// What it is built to break.
    pub purpose: &'static str,
    pub scene: Scene,
}

const SUITE_N: i32 = 6;

/// A 6³ block seen by an 8×8 camera under a sky and a sun, with the given medium.
fn suite_scene(
    grid: BrickMap,
    transform: IndexTransform,
    density_scale: f32,
    albedo: f32,
    g: f32,
    filter: Filter,
) -> Scene {
    let mut medium = Medium::new(grid, transform, density_scale, filter, Majorant::grid(4));
    medium.albedo = Albedo::Constant(Vec3::splat(albedo));
    medium.phase_g = g;
    let mut lights = Lights {
        environment: Environment {
            constant: Vec3::new(0.8, 0.9, 1.0),
            map: None,
        },
        ..Lights::default()
    };
    lights.directional.push(DirectionalLight {
        to_light: Vec3::new(0.4, 1.0, 0.3).normalize(),
        irradiance: Vec3::splat(2.0),
    });
    let settings = RenderFile {
        max_depth: 16,
        ..RenderFile::default()
    };
    Scene {
        path: "stability.toml".into(),
        camera: Camera::new(Vec3::new(0.0, 0.0, 14.0), Vec3::ZERO, Vec3::Y, 35.0, 8, 8),
        medium,
        lights,
        settings,
        grid_name: "density".into(),
        vdb_path: Some("stability.vdb".into()),
    }
}

fn block(f: impl Fn(IVec3) -> f32) -> BrickMap {
    BrickMap::block(SUITE_N, f)
}

fn lumpy(v: IVec3) -> f32 {
    0.6 + 0.4 * ((v.x as f32 * 1.3).sin() * (v.y as f32 * 0.8 + v.z as f32).cos())
}

fn centred(linear: DMat3) -> IndexTransform {
    IndexTransform::centred(linear, DVec3::splat((SUITE_N - 1) as f64 * 0.5))
        .expect("an invertible transform")
}

/// Scenes built to break estimators. Optical depths are across the 6-voxel block.
pub fn stability_scenes() -> Vec<StabilityScene> {
    let unit = || centred(DMat3::IDENTITY);
    let n = SUITE_N as f32;
    vec![
        StabilityScene {
            name: "empty-voxels",
            purpose: "a quarter of the voxels inside the bounds are empty, nearest lookups so that σt = 0 there (naive misses their scattering part)",
            scene: suite_scene(
                block(|v| if (v.x + 2 * v.y + v.z) % 4 == 0 { 0.0 } else { lumpy(v) }),
                unit(),
                0.5,
                0.9,
                0.3,
                Filter::Nearest,
            ),
        },
        StabilityScene {
            name: "thin",
            purpose: "τ ≈ 0.04: almost every path escapes (naive's 1/σt weights explode)",
            scene: suite_scene(block(|_| 1.0), unit(), 0.04 / n, 0.9, 0.3, Filter::Trilinear),
        },
        StabilityScene {
            name: "dense",
            purpose: "τ ≈ 96: exp underflow, long walks, h(s) − h(t) cancels",
            scene: suite_scene(block(|_| 1.0), unit(), 96.0 / n, 0.9, 0.3, Filter::Trilinear),
        },
        StabilityScene {
            name: "albedo-0.999",
            purpose: "albedo near 1: long paths carry the gradient",
            scene: suite_scene(block(lumpy), unit(), 0.5, 0.999, 0.3, Filter::Trilinear),
        },
        StabilityScene {
            name: "albedo-0.01",
            purpose: "albedo near 0: almost pure absorption",
            scene: suite_scene(block(lumpy), unit(), 0.5, 0.01, 0.3, Filter::Trilinear),
        },
        StabilityScene {
            name: "hot-voxel",
            purpose: "one voxel 1000× its neighbours: the majorant is loose everywhere around it",
            scene: suite_scene(
                block(|v| if v == IVec3::new(2, 3, 2) { 50.0 } else { 0.05 }),
                unit(),
                1.0,
                0.9,
                0.3,
                Filter::Trilinear,
            ),
        },
        StabilityScene {
            name: "rotated-anisotropic",
            purpose: "rotated index space with voxels 1.4 × 0.7 × 1.0: distances converted per axis",
            scene: suite_scene(
                block(lumpy),
                centred(
                    DMat3::from_rotation_y(0.6)
                        * DMat3::from_rotation_x(0.4)
                        * DMat3::from_diagonal(DVec3::new(1.4, 0.7, 1.0)),
                ),
                0.5,
                0.9,
                0.3,
                Filter::Trilinear,
            ),
        },
        StabilityScene {
            name: "forward-g0.95",
            purpose: "strong forward scattering (g = 0.95): peaked phase function",
            scene: suite_scene(block(lumpy), unit(), 0.5, 0.9, 0.95, Filter::Trilinear),
        },
    ]
}

#[derive(Debug, Clone, Copy)]
pub struct StabilityOptions {
    /// Independent runs per estimator (seed, seed + 1, …) for the standard error.
    pub runs: u32,
    pub spp: u32,
    pub fd_spp: u32,
    pub fd_repeats: u32,
    pub seed: u64,
    pub max_depth: u32,
    pub progress: bool,
}

#[derive(Debug, Clone)]
pub struct StabilityRow {
    pub scene: String,
    pub estimator: String,
    /// "all voxels" (⟨g, 1⟩ over the domain) or "empty voxels" (⟨g, 1⟩ over the empty ones).
    pub check: String,
    pub estimate: f64,
    pub estimate_se: f64,
    pub fd: FdResult,
    /// Standard deviation of one run's ⟨g, ·⟩ relative to |fd|: the variance a user sees.
    pub relative_sd: f64,
    /// Non-finite voxel values over all runs (there must be none).
    pub non_finite: usize,
    /// A failure the design predicts (naive in empty voxels, naive in thin media).
    pub expected_failure: bool,
}

/// |z| below which a check counts as unbiased.
pub const STABILITY_Z: f64 = 4.0;

impl StabilityRow {
    pub fn z(&self) -> f64 {
        Check {
            name: String::new(),
            estimate: self.estimate,
            estimate_se: self.estimate_se,
            fd: self.fd,
        }
        .z()
    }

    pub fn unbiased(&self) -> bool {
        self.z().abs() < STABILITY_Z
    }

    /// Finite differences too noisy to tell a biased estimator (se above half the value).
    pub fn weak(&self) -> bool {
        // NaN (no finite difference) counts as weak.
        self.fd.std_err.is_nan() || self.fd.std_err >= 0.5 * self.fd.value.abs()
    }
}

/// The fd step: 0.2 optical depth across the block, so that the step means the same from τ = 0.04
/// to τ = 96 (a step in grid units would be far too big in dense media and lost in noise in thin
/// ones). At 0.5 the one-sided stencil's truncation error was 3% in the absorbing scene (z ≈ −3
/// for every estimator); at 0.1 the empty-voxel check drowned in noise.
fn suite_eps(scene: &Scene) -> f32 {
    FD_OPTICAL_STEP / (scene.medium.density_scale * SUITE_N as f32)
}

const FD_OPTICAL_STEP: f32 = 0.2;

/// Runs every estimator on `scenes` and compares ⟨g, 1⟩ (all voxels, and the empty ones if any)
/// with finite differences.
pub fn stability(
    scenes: &[StabilityScene],
    estimators: &[Estimator],
    o: &StabilityOptions,
) -> Result<Vec<StabilityRow>> {
    let mut rows = Vec::new();
    let bar = crate::io::progress::bar(
        o.progress,
        (scenes.len() * (estimators.len() + 1)) as u64,
        "stability",
    );
    for s in scenes {
        let scene = &s.scene;
        let grid = &scene.medium.grid;
        let Some((lo, hi)) = fd::domain_bounds(grid) else {
            continue;
        };
        let all = fd::box_voxels(grid, lo, hi, false);
        let empty: Vec<IVec3> = all
            .iter()
            .copied()
            .filter(|&v| grid.is_active(v) && grid.voxel(v) == 0.0)
            .collect();
        let fd_options = FdOptions {
            loss: Loss::Mean,
            eps: suite_eps(scene),
            spp: o.fd_spp,
            repeats: o.fd_repeats,
            seed: o.seed,
            max_depth: o.max_depth,
        };
        let has_empty = !empty.is_empty();
        let mut checks = vec![("all voxels", all.clone())];
        if has_empty {
            checks.push(("empty voxels", empty));
        }
        let fds = checks
            .iter()
            .map(|(_, voxels)| {
                fd::directional_derivative(scene, None, &fd::ones(voxels), &fd_options)
            })
            .collect::<Result<Vec<FdResult>>>()?;
        bar.inc(1);
        let adjoint = mean_adjoint(scene);
        for &estimator in estimators {
            let mut non_finite = 0;
            // Per run, ⟨g, 1⟩ over each check's voxels: runs[r][k].
            let first_seed = o.seed.wrapping_add(SWEEP_SEED_OFFSET);
            let runs = seeded_runs(first_seed, o.runs.max(2), |_, seed| {
                let g = gradient(
                    scene,
                    &adjoint,
                    &GradOptions::new(estimator, o.spp, seed, o.max_depth),
                )
                .values();
                non_finite += g.voxels().filter(|(_, x)| !x.is_finite()).count();
                checks
                    .iter()
                    .map(|(_, voxels)| voxels.iter().map(|&v| g.get(v)).sum::<f64>())
                    .collect::<Vec<f64>>()
            });
            for (k, (check, _)) in checks.iter().enumerate() {
                let sums: Vec<f64> = runs.iter().map(|run| run[k]).collect();
                let MeanAndError { mean, se } = MeanAndError::of(&sums);
                let fd = fds[k];
                let naive = estimator == Estimator::Naive;
                rows.push(StabilityRow {
                    scene: s.name.into(),
                    estimator: estimator.to_string(),
                    check: (*check).into(),
                    estimate: mean,
                    estimate_se: se,
                    fd,
                    relative_sd: se * (sums.len() as f64).sqrt() / fd.value.abs().max(1e-300),
                    non_finite,
                    expected_failure: naive && (has_empty || s.name == "thin"),
                });
            }
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    Ok(rows)
}

/// stability.csv: one row per scene, estimator and check, full precision.
pub fn stability_csv(rows: &[StabilityRow]) -> String {
    use Align::{Left, Right};
    let mut table = Table::new([
        ("scene", Left),
        ("estimator", Left),
        ("check", Left),
        ("estimate", Right),
        ("estimate_se", Right),
        ("fd", Right),
        ("fd_se", Right),
        ("z", Right),
        ("unbiased", Left),
        ("relative_sd", Right),
        ("non_finite", Right),
        ("expected_failure", Left),
    ]);
    for r in rows {
        table.push([
            r.scene.clone(),
            r.estimator.clone(),
            r.check.clone(),
            format!("{:.6e}", r.estimate),
            format!("{:.6e}", r.estimate_se),
            format!("{:.6e}", r.fd.value),
            format!("{:.6e}", r.fd.std_err),
            format!("{:.3}", r.z()),
            r.unbiased().to_string(),
            format!("{:.4e}", r.relative_sd),
            r.non_finite.to_string(),
            r.expected_failure.to_string(),
        ]);
    }
    table.csv()
}

/// stability.md: the options, the checks with their verdicts, and what each scene is built to break.
pub fn stability_markdown(
    scenes: &[StabilityScene],
    rows: &[StabilityRow],
    o: &StabilityOptions,
) -> String {
    use Align::{Left, Right};
    let mut checks = Table::new([
        ("scene", Left),
        ("estimator", Left),
        ("⟨g, 1⟩ over", Left),
        ("estimate ± se", Right),
        ("fd ± se", Right),
        ("z", Right),
        ("verdict", Left),
        ("sd per run / |fd|", Right),
        ("non-finite", Right),
    ]);
    for r in rows {
        let verdict = match (r.unbiased(), r.expected_failure) {
            (true, _) if r.weak() => "ok (weak check: fd noisy)",
            (true, _) => "ok",
            (false, true) => "**biased (expected)**",
            (false, false) => "**BIASED**",
        };
        checks.push([
            r.scene.clone(),
            r.estimator.clone(),
            r.check.clone(),
            format!("{:.4e} ± {:.1e}", r.estimate, r.estimate_se),
            format!("{:.4e} ± {:.1e}", r.fd.value, r.fd.std_err),
            format!("{:.2}", r.z()),
            verdict.to_string(),
            format!("{:.3}", r.relative_sd),
            r.non_finite.to_string(),
        ]);
    }
    let mut purposes = Table::new([("scene", Left), ("built to break", Left)]);
    for sc in scenes {
        purposes.push([sc.name, sc.purpose]);
    }
    format!(
        "Each estimator: {} runs × {} spp on an 8×8 image of a 6³ grid (trilinear lookups, nearest in empty-voxels); finite differences: {} spp × {} repeats, step {FD_OPTICAL_STEP} optical depth across the block. A check passes when |z| < {STABILITY_Z}.\n\n{}\n{}",
        o.runs.max(2),
        o.spp,
        o.fd_spp,
        o.fd_repeats.max(2),
        checks.markdown(),
        purposes.markdown()
    )
}
