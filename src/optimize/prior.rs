//! An optional smoothness prior on the unknown, for reconstructions from few views:
//!
//! R(θ) = weight · (1/N) · Σ_{pairs} φ(θ_{v+e_a} − θ_v)
//!
//! over the pairs of neighbours (a ∈ x, y, z) with at least one of the N stored voxels, with φ(d) = √(d² + ε²) − ε (total variation, smoothed at ε so its
//! gradient exists at 0) or φ(d) = d² (the "laplacian" prior: its gradient is the discrete
//! Laplacian); or R(θ) = weight · (1/N) · Σ_v θ_v ("l1", a sparsity prior). Dividing by N keeps a weight meaningful across levels of the coarse-to-fine schedule.

use glam::IVec3;

use crate::optimize::parameters::{local_of, Parameters};
use crate::volume::brickmap::{leaf_offset, BRICK_VOXELS};

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
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
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prior {
    pub kind: PriorKind,
    pub weight: f32,
}

/// Where total variation's kink at 0 is rounded off, in grid-value units.
const TV_EPSILON: f64 = 1e-3;

const AXES: [IVec3; 3] = [IVec3::X, IVec3::Y, IVec3::Z];

impl Prior {
    fn phi(&self, d: f64) -> f64 {
        match self.kind {
            PriorKind::Tv => (d * d + TV_EPSILON * TV_EPSILON).sqrt() - TV_EPSILON,
            PriorKind::Laplacian => d * d,
            PriorKind::L1 => 0.0, // not a difference prior (see `evaluate`)
        }
    }

    fn phi_derivative(&self, d: f64) -> f64 {
        match self.kind {
            PriorKind::Tv => d / (d * d + TV_EPSILON * TV_EPSILON).sqrt(),
            PriorKind::Laplacian => 2.0 * d,
            PriorKind::L1 => 0.0,
        }
    }

    /// R(θ) and ∂R/∂θ_v for every stored voxel v. Each voxel's derivative is computed from its
    /// own neighbourhood, in one expression, and the bricks are visited in key order, so the
    /// result does not depend on the hash map's order.
    pub fn evaluate(&self, p: &Parameters) -> (f64, Vec<(IVec3, f64)>) {
        let stored = p.brick_count() * BRICK_VOXELS;
        if stored == 0 || self.weight == 0.0 {
            return (0.0, Vec::new());
        }
        let scale = self.weight as f64 / stored as f64;
        let mut value = 0.0;
        let mut gradient = Vec::with_capacity(stored);
        if self.kind == PriorKind::L1 {
            let value = p.voxels().map(|(_, theta, ..)| theta as f64).sum::<f64>();
            let gradient = p.voxels().map(|(v, ..)| (v, scale)).collect();
            return (scale * value, gradient);
        }
        for (key, theta, ..) in p.sorted_bricks() {
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
                gradient.push(((key << 3) + local, scale * g));
            }
        }
        (scale * value, gradient)
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
        for kind in [PriorKind::Tv, PriorKind::Laplacian, PriorKind::L1] {
            let prior = Prior { kind, weight: 2.0 };
            let mut p = Parameters::default();
            for x in 0..8 {
                for y in 0..8 {
                    for z in 0..8 {
                        let v = IVec3::new(x, y, z);
                        p.set(v, ((x * 7 + y * 3 + z * 5) % 11) as f32 * 0.1);
                    }
                }
            }
            let (_, gradient) = prior.evaluate(&p);
            // Voxels with θ > ε (`set` clamps θ − ε at 0): a corner of the block, inside, an edge.
            for v in [
                IVec3::new(1, 0, 0),
                IVec3::new(3, 4, 5),
                IVec3::new(7, 2, 7),
            ] {
                let analytic = gradient.iter().find(|(w, _)| *w == v).unwrap().1;
                let eps = 1e-3;
                let theta = p.get(v);
                let at = |x: f32| {
                    let mut q = p.clone();
                    q.set(v, x);
                    prior.evaluate(&q).0
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
        };
        let mut p = Parameters::default();
        for x in 0..16 {
            for y in 0..8 {
                for z in 0..8 {
                    p.set(IVec3::new(x, y, z), 0.5);
                }
            }
        }
        let (_, gradient) = prior.evaluate(&p);
        let inner = gradient
            .iter()
            .find(|(v, _)| *v == IVec3::new(7, 3, 3))
            .unwrap();
        assert_eq!(inner.1, 0.0);
        // At the block's edge the field drops to 0: the prior pulls the edge voxel down.
        let edge = gradient
            .iter()
            .find(|(v, _)| *v == IVec3::new(15, 3, 3))
            .unwrap();
        assert!(edge.1 > 0.0);
    }
}
