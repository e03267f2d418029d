//! `volgrad gradcheck`: an estimator against finite differences on k random voxels, on an index box
//! that contains empty voxels, and on ⟨g, 1⟩, each as a z-score. The gradient is that of the mean
//! pixel value; other losses only change the per-pixel weights.

use glam::{IVec3, Vec3};
use rand::seq::SliceRandom;

use crate::gradient::fd::{self, Direction, FdOptions, FdResult};
use crate::gradient::grid::GradientGrid;
use crate::gradient::passes::{gradient, parameter_grid, GradOptions, Parameter};
use crate::gradient::runs::{seeded_runs, MeanAndError};
use crate::io::table::{Align, Table};
use crate::render::sampling::pixel_rng;
use crate::render::scene::Scene;

/// z above which a check fails.
pub const Z_LIMIT: f64 = 4.0;

#[derive(Debug, Clone)]
pub struct Check {
    pub name: String,
    pub estimate: f64,
    pub estimate_se: f64,
    pub fd: FdResult,
}

impl Check {
    pub fn z(&self) -> f64 {
        let se = (self.estimate_se.powi(2) + self.fd.std_err.powi(2)).sqrt();
        let difference = self.estimate - self.fd.value;
        if se > 0.0 {
            difference / se
        } else if difference.abs() <= 1e-12 + 1e-6 * self.fd.value.abs() {
            // Neither side has noise (a vacuum: every path alike): equal up to rounding.
            0.0
        } else {
            f64::INFINITY
        }
    }

    pub fn passed(&self) -> bool {
        self.z().abs() < Z_LIMIT
    }
}

/// The checks as `check | estimate ± se | finite differences ± se | z | verdict`, one row per
/// check in order: the `gradcheck` command's output and the reference check in `compare`'s
/// summary. A check fails at |z| ≥ `Z_LIMIT`.
pub fn checks_table(checks: &[Check]) -> Table {
    let mut table = Table::new([
        ("check", Align::Left),
        ("estimate ± se", Align::Right),
        ("finite differences ± se", Align::Right),
        ("z", Align::Right),
        ("verdict", Align::Left),
    ]);
    for c in checks {
        table.push([
            c.name.clone(),
            format!("{:.4e} ± {:.1e}", c.estimate, c.estimate_se),
            format!("{:.4e} ± {:.1e}", c.fd.value, c.fd.std_err),
            format!("{:.2}", c.z()),
            (if c.passed() { "ok" } else { "FAIL" }).to_string(),
        ]);
    }
    table
}

#[derive(Debug, Clone, Copy)]
pub struct GradcheckOptions {
    pub grad: GradOptions,
    /// Independent estimator runs (seed, seed+1, ...) for standard errors.
    pub repeats: u32,
    pub voxels: usize,
    pub fd: FdOptions,
    /// Use `fd.eps` for every check instead of `fd::auto_eps` per check.
    pub fixed_eps: bool,
    /// A progress bar on stderr (estimator runs, then checks).
    pub progress: bool,
}

pub fn gradcheck(scene: &Scene, options: &GradcheckOptions) -> anyhow::Result<Vec<Check>> {
    let (parameter, channel) = (options.grad.parameter, options.grad.channel);
    let grid = parameter_grid(scene, parameter, channel);
    let Some((lo, hi)) = fd::domain_bounds(grid) else {
        return Ok(Vec::new());
    };
    fd::ensure_enumerable(grid, lo, hi)?;
    let pixels = (scene.camera.width * scene.camera.height) as usize;
    let adjoint = vec![Vec3::ONE / (3 * pixels) as f32; pixels];
    let repeats = options.repeats.max(2);
    let bar = crate::io::progress::bar(
        options.progress,
        (repeats as usize + options.voxels + 2) as u64,
        "gradcheck",
    );
    let runs: Vec<GradientGrid<f32>> = seeded_runs(options.grad.seed, repeats, |_, seed| {
        let o = GradOptions {
            seed,
            progress: false,
            ..options.grad
        };
        bar.inc(1);
        gradient(scene, &adjoint, &o).values()
    });
    let domain = fd::box_voxels(grid, lo, hi, options.grad.active_only);
    let mut checks = Vec::new();
    let mut check = |name: String, direction: Direction| -> anyhow::Result<()> {
        let along: Vec<f64> = runs
            .iter()
            .map(|g| direction.iter().map(|&(v, d)| d as f64 * g.get(v)).sum())
            .collect();
        let MeanAndError {
            mean: estimate,
            se: estimate_se,
        } = MeanAndError::of(&along);
        let mut fd_options = options.fd;
        if !options.fixed_eps {
            fd_options.eps = match parameter {
                Parameter::Extinction => fd::auto_eps(scene, &direction),
                // Grids that do not steer sampling: the renders see the same paths, so a small
                // step costs no noise, and 1 % of the grid's range keeps the stencil's O(ε²)
                // error below the estimator's (5 % put a blackbody's ⟨g, 1⟩ 1.2 % off: seen).
                _ => 0.01 * grid.max_value().max(-grid.min_value()).max(1e-3),
            };
        }
        let fd = fd::directional_derivative_of(
            scene,
            None,
            parameter,
            channel,
            &direction,
            &fd_options,
        )?;
        bar.inc(1);
        checks.push(Check {
            name,
            estimate,
            estimate_se,
            fd,
        });
        Ok(())
    };
    // k random voxels among those the estimator reached.
    let mut reached: Vec<IVec3> = runs[0]
        .voxels()
        .filter(|(_, g)| *g != 0.0)
        .map(|(v, _)| v)
        .collect();
    reached.sort_by_key(|v| (v.x, v.y, v.z));
    let mut rng = pixel_rng(options.grad.seed, u64::MAX - 1, 3);
    if reached.len() < options.voxels {
        eprintln!(
            "note: {} voxels asked for, but the estimator reached {}: checking each of those",
            options.voxels,
            reached.len()
        );
    }
    for &v in reached.choose_multiple(&mut rng, options.voxels) {
        check(format!("voxel {v}"), vec![(v, 1.0)])?;
    }
    // A 3³ box of empty voxels: prefer one with no density at all (where free-flight sampling
    // never collides), inside the active box, near its centre.
    let density_in_box = |v: IVec3| {
        fd::box_voxels(grid, v - 1, v + 1, false)
            .iter()
            .filter(|&&u| grid.voxel(u) != 0.0)
            .count()
    };
    let centre = (lo + hi) / 2;
    let inside = |v: IVec3| {
        grid.active_bounds()
            .is_some_and(|(a, b)| v.cmpge(a).all() && v.cmple(b).all())
    };
    let empty = domain
        .iter()
        .copied()
        .filter(|&v| grid.voxel(v) == 0.0)
        .min_by_key(|&v| (density_in_box(v), !inside(v), (v - centre).length_squared()));
    if let Some(e) = empty {
        let voxels = fd::box_voxels(grid, e - 1, e + 1, options.grad.active_only);
        check(
            format!("box {}..{} (empty voxels)", e - 1, e + 1),
            fd::ones(&voxels),
        )?;
    }
    check("⟨g, 1⟩ over the domain".into(), fd::ones(&domain))?;
    bar.finish_and_clear();
    Ok(checks)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checks_table_has_a_row_per_check_with_errors_and_z() {
        let check = Check {
            name: "voxel [1, 2, 3]".into(),
            estimate: 0.5,
            estimate_se: 0.03,
            fd: FdResult {
                value: 0.46,
                std_err: 0.04,
                one_sided: false,
            },
        };
        let mut far = check.clone();
        far.estimate = 0.8; // z = 6.8
        let table = checks_table(&[check, far]);
        assert_eq!(table.header()[0], "check");
        assert_eq!(
            table.rows(),
            [
                [
                    "voxel [1, 2, 3]",
                    "5.0000e-1 ± 3.0e-2",
                    "4.6000e-1 ± 4.0e-2",
                    "0.80",
                    "ok"
                ],
                [
                    "voxel [1, 2, 3]",
                    "8.0000e-1 ± 3.0e-2",
                    "4.6000e-1 ± 4.0e-2",
                    "6.80",
                    "FAIL"
                ]
            ]
        );
    }

    /// Without noise on either side (a vacuum, where every path is alike) the two agree up to
    /// rounding or not at all: z is 0 or infinite, never a division by a zero error.
    #[test]
    fn noiseless_checks_compare_up_to_rounding() {
        let noiseless = |estimate: f64, fd: f64| Check {
            name: "vacuum".into(),
            estimate,
            estimate_se: 0.0,
            fd: FdResult {
                value: fd,
                std_err: 0.0,
                one_sided: false,
            },
        };
        assert!(noiseless(0.0, 2.47e-16).passed());
        assert!(noiseless(0.5, 0.5 + 1e-9).passed());
        assert!(!noiseless(0.0, 1e-3).passed());
        assert!(!noiseless(0.5, 0.51).passed());
    }
}
