//! Gradients of alpha (`render::alpha`) with respect to the density grid. Along a camera ray whose
//! segment in the medium's box is [t0, t1] (length L), α = 1 − T with T = exp(−∫ σt dt), so
//!
//!   ∂α/∂θ_k = T · ∫ ∂σt(x(t))/∂θ_k dt = T · density_scale · ∫ w_k(x(t)) dt,
//!
//! the transmittance term of the extinction gradient alone: no scattering, no lights, no suffix.
//! One sample is
//!
//!   T̂ · (L/K) · Σ_i ∂σt(x(t_i)),  t_i stratified uniform on [t0, t1],
//!
//! T̂ ratio tracking's estimate from a walk of its own, independent of the t_i, so the product is
//! unbiased. The points are uniform, not the majorant's tentative collisions: those never fall
//! where σ̄ = 0, and there — an empty start, a carved region — the gradient is not 0.

use glam::Vec3;
use rand::Rng;

use crate::gradient::adjoint::{splat_d_sigma, GradientSink};
use crate::render::scene::Scene;
use crate::volume::tracking::{transmittance, TrackingStats};

/// Uniform points per sample on the ray's segment (K): one point on a long ray mostly lands in
/// empty space, but a splat is no cheaper than the walk that estimates T̂ (16 points made a step of
/// the worked example 1.3× as long, `scenes/capture/README.md`).
const POINTS_PER_RAY: u32 = 4;

/// One sample of α along the ray `origin + t·dir` (unit `dir`), returned as a grey value, with
/// its derivatives ∂α/∂θ_k added to `sink`.
pub fn alpha_gradient_sample(
    scene: &Scene,
    origin: Vec3,
    dir: Vec3,
    rng: &mut impl Rng,
    stats: &mut TrackingStats,
    sink: &mut impl GradientSink,
) -> Vec3 {
    let medium = &scene.medium;
    let ray = medium.to_index_ray(origin, dir);
    let Some((t0, t1)) = medium.intersect(&ray) else {
        return Vec3::ZERO;
    };
    let tr = transmittance(medium, &ray, t0, t1, rng, stats);
    if tr > 0.0 {
        let stratum = (t1 - t0) / POINTS_PER_RAY as f32;
        let value = Vec3::splat(tr * stratum);
        for i in 0..POINTS_PER_RAY {
            let t = t0 + (i as f32 + rng.gen::<f32>()) * stratum;
            splat_d_sigma(medium, ray.at(t), value, sink);
        }
    }
    Vec3::splat(1.0 - tr)
}
