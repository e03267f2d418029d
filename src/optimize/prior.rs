//! Optional priors on the unknown, for reconstructions from few views. Each is
//!
//! R(θ) = weight · (1/N) · Σ_{pairs} φ(θ_{v+e_a} − θ_v)
//!
//! over the pairs of neighbours (a ∈ x, y, z) with at least one stored voxel, N the voxels of the
//! current level's box, with
//! φ(d) = √(d² + ε²) − ε (total variation, smoothed at ε so its gradient exists at 0) or φ(d) = d²
//! (the "laplacian" prior: its gradient is the discrete Laplacian); or a sum over the voxels
//! themselves, R(θ) = weight · (1/N) · Σ_v ψ(θ_v), with ψ(θ) = θ ("l1") or ψ(θ) = δ·ln(1 + θ/δ)
//! ("log", δ its `scale`). N is fixed for a level: a finer level has 8× the voxels, so each
//! voxel's ∂R/∂θ is 1/8 of its parent's, as the images' gradient is (the rule of the levels,
//! `reconstruct`), and R itself keeps its size. (N was once the stored voxels, which grew as the
//! run went on and weakened the prior.)

use glam::IVec3;
use rayon::prelude::*;

use crate::optimize::brick_gradient::{BrickGradient, BrickValues};
use crate::optimize::parameters::{local_of, Parameters};
use crate::volume::brickmap::{leaf_offset, BRICK_VOXELS};

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum PriorKind {
    /// Total variation: penalises edges by their height, keeps them sharp.
    Tv,
    /// Squared differences: penalises edges by their height squared, smooths them.
    Laplacian,
    /// The mean of θ itself (θ ≥ 0, so its L1 norm): a constant pull towards 0. Where the images
    /// say nothing about a voxel its gradient is noise, and the θ ≥ 0 projection turns a random
    /// walk into haze; this pull is what clears it, while voxels the images need hardly feel it.
    L1,
    /// δ·ln(1 + θ/δ) per voxel (the log penalty of reweighted ℓ1, Candès, Wakin & Boyd 2008): the
    /// pull towards 0 is l1's at θ = 0 and falls as δ/(δ + θ) above the scale δ, so it clears
    /// faint density (haze, a blurred boundary's tail) and leaves dense voxels nearly alone,
    /// where l1's constant pull erodes them too.
    Log,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prior {
    pub kind: PriorKind,
    pub weight: f32,
    /// δ of the log prior (grid-value units); unused by the others.
    pub scale: f32,
    /// Where total variation's kink at 0 is rounded off, so that its gradient exists there
    /// (grid-value units).
    pub tv_epsilon: f64,
}

const AXES: [IVec3; 3] = [IVec3::X, IVec3::Y, IVec3::Z];

impl Prior {
    fn phi(&self, d: f64) -> f64 {
        match self.kind {
            PriorKind::Tv => (d * d + self.tv_epsilon.powi(2)).sqrt() - self.tv_epsilon,
            PriorKind::Laplacian => d * d,
            PriorKind::L1 | PriorKind::Log => 0.0, // not difference priors (see `evaluate`)
        }
    }

    fn phi_derivative(&self, d: f64) -> f64 {
        match self.kind {
            PriorKind::Tv => d / (d * d + self.tv_epsilon.powi(2)).sqrt(),
            PriorKind::Laplacian => 2.0 * d,
            PriorKind::L1 | PriorKind::Log => 0.0,
        }
    }

    /// R(θ) and ∂R/∂θ_v for every stored voxel v, with N = `level_voxels`, as bricks of the
    /// unknown. A brick's share depends only on its own θ and its face neighbours', so the bricks
    /// are evaluated in parallel and their values summed in key order: the result does not depend
    /// on the hash map's order or the thread count.
    pub fn evaluate(&self, p: &Parameters, level_voxels: u64) -> (f64, BrickGradient) {
        if p.brick_count() == 0 || level_voxels == 0 || self.weight == 0.0 {
            return (0.0, BrickGradient::default());
        }
        let scale = self.weight as f64 / level_voxels as f64;
        let bricks: Vec<(f64, IVec3, BrickValues)> = p
            .sorted_bricks()
            .into_par_iter()
            .map(|(key, theta, ..)| {
                let mut gradient: BrickValues = Box::new([0.0; BRICK_VOXELS]);
                let value = self.brick(p, key, theta, &mut gradient);
                gradient.iter_mut().for_each(|g| *g *= scale);
                (value, key, gradient)
            })
            .collect();
        let value: f64 = bricks.iter().map(|(v, ..)| v).sum();
        let gradient = bricks.into_iter().map(|(_, key, g)| (key, g));
        (scale * value, BrickGradient::from_bricks(gradient))
    }

    /// One brick's share of Σ φ or Σ ψ (before the weight and 1/N), its voxels' derivatives
    /// written into `gradient` (`leaf_offset` order, as θ).
    fn brick(
        &self,
        p: &Parameters,
        key: IVec3,
        theta: &[f32; BRICK_VOXELS],
        gradient: &mut [f64; BRICK_VOXELS],
    ) -> f64 {
        let delta = f64::from(self.scale);
        let mut value = 0.0;
        match self.kind {
            PriorKind::L1 | PriorKind::Log => {
                let log = self.kind == PriorKind::Log;
                for (g, &t) in gradient.iter_mut().zip(theta) {
                    let t = f64::from(t);
                    let (psi, derivative) = if log {
                        (delta * (t / delta).ln_1p(), delta / (delta + t))
                    } else {
                        (t, 1.0)
                    };
                    value += psi;
                    *g = derivative;
                }
            }
            PriorKind::Tv | PriorKind::Laplacian => {
                let around = Neighbourhood::new(p, key, theta);
                for (i, &t) in theta.iter().enumerate() {
                    let (local, t) = (local_of(i), t as f64);
                    let mut g = 0.0;
                    for e in AXES {
                        let (after, _) = around.at(local + e);
                        let (before, before_stored) = around.at(local - e);
                        let forward = after as f64 - t;
                        let backward = t - before as f64;
                        // Each pair of neighbours counts once: as the forward pair of its lower
                        // voxel when that one is stored, else here.
                        value += self.phi(forward);
                        if !before_stored {
                            value += self.phi(backward);
                        }
                        g += self.phi_derivative(backward) - self.phi_derivative(forward);
                    }
                    gradient[i] = g;
                }
            }
        }
        value
    }
}

/// θ around one brick: the brick and its six face neighbours, looked up once, so that a voxel's
/// neighbours are array reads rather than hash lookups.
struct Neighbourhood<'a> {
    own: &'a [f32; BRICK_VOXELS],
    /// +x, −x, +y, −y, +z, −z.
    faces: [Option<&'a [f32; BRICK_VOXELS]>; 6],
}

impl<'a> Neighbourhood<'a> {
    fn new(p: &'a Parameters, key: IVec3, own: &'a [f32; BRICK_VOXELS]) -> Self {
        let faces = std::array::from_fn(|f| {
            let step = if f % 2 == 0 { 1 } else { -1 };
            p.brick_theta(key + AXES[f / 2] * step)
        });
        Neighbourhood { own, faces }
    }

    /// θ at a brick-local index one step from the brick at most (one coordinate in −1 or 8),
    /// and whether its brick is stored.
    fn at(&self, local: IVec3) -> (f32, bool) {
        let outside = (0..3).find(|&a| !(0..8).contains(&local[a]));
        let brick = match outside {
            None => Some(self.own),
            Some(a) => self.faces[2 * a + usize::from(local[a] < 0)],
        };
        brick.map_or((0.0, false), |b| (b[leaf_offset(local & 7)], true))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The gradient against central differences of R, on a random-looking field.
    #[test]
    fn gradient_matches_finite_differences() {
        for kind in [
            PriorKind::Tv,
            PriorKind::Laplacian,
            PriorKind::L1,
            PriorKind::Log,
        ] {
            let prior = Prior {
                kind,
                weight: 2.0,
                scale: 0.05,
                tv_epsilon: 1e-3,
            };
            let mut p = Parameters::default();
            for x in 0..8 {
                for y in 0..8 {
                    for z in 0..8 {
                        let v = IVec3::new(x, y, z);
                        p.set(v, ((x * 7 + y * 3 + z * 5) % 11) as f32 * 0.1);
                    }
                }
            }
            let (_, gradient) = prior.evaluate(&p, 512);
            // Voxels with θ > ε (`set` clamps θ − ε at 0): a corner of the block, inside, an edge.
            for v in [
                IVec3::new(1, 0, 0),
                IVec3::new(3, 4, 5),
                IVec3::new(7, 2, 7),
            ] {
                let analytic = gradient.at(v);
                let eps = 1e-3;
                let theta = p.get(v);
                let at = |x: f32| {
                    let mut q = p.clone();
                    q.set(v, x);
                    prior.evaluate(&q, 512).0
                };
                let numeric = (at(theta + eps) - at(theta - eps)) / (2.0 * eps as f64);
                assert!(
                    (analytic - numeric).abs() < 1e-3 * numeric.abs().max(1e-3),
                    "{kind:?} at {v}: {analytic} vs {numeric}"
                );
            }
        }
    }

    #[test]
    fn a_constant_field_costs_nothing_inside() {
        let prior = Prior {
            kind: PriorKind::Laplacian,
            weight: 1.0,
            scale: 0.0,
            tv_epsilon: 1e-3,
        };
        let mut p = Parameters::default();
        for x in 0..16 {
            for y in 0..8 {
                for z in 0..8 {
                    p.set(IVec3::new(x, y, z), 0.5);
                }
            }
        }
        let (_, gradient) = prior.evaluate(&p, 512);
        assert!(gradient.get(IVec3::ZERO).is_some());
        assert_eq!(gradient.at(IVec3::new(7, 3, 3)), 0.0);
        // At the block's edge the field drops to 0: the prior pulls the edge voxel down.
        assert!(gradient.at(IVec3::new(15, 3, 3)) > 0.0);
    }
}
