//! Gradients with respect to the emission grid's values e_k. The path tracer adds
//! β_{j−1}·(1 − α)·Le(x_j) at every real collision x_j, and where the collisions fall does not
//! depend on e (the tracker follows density alone), so differentiating that estimator is unbiased:
//!
//!   ∂pixel/∂e_k = Σ_j β_{j−1} · (1 − α) · ∂Le/∂v(x_j) · w_k(x_j),
//!
//! with w_k(x_j) the weight of voxel k in the emission lookup at x_j (in the emission grid's own
//! index space). No probes, no suffix paths: every collision of the camera path already is one.

use glam::Vec3;
use rand::Rng;

use crate::gradient::adjoint::{splat_lookup, GradientSink, Replay, Scratch};
use crate::render::path::Segment;
use crate::render::scene::Scene;

impl<R: Rng> Replay<'_, R> {
    /// Traces one camera path and adds its derivatives with respect to the emission grid's
    /// values to `sink`; returns the path's radiance.
    pub fn camera_path_emission_gradient(
        &mut self,
        origin: Vec3,
        dir: Vec3,
        scratch: &mut Scratch,
        sink: &mut impl GradientSink,
    ) -> Vec3 {
        let radiance = self.trace_recorded(origin, dir, scratch);
        emission_path_gradient(self.scene, &scratch.record.segments, sink);
        radiance
    }
}

/// The emission derivatives of one recorded path, into `sink` (nothing for a medium that does
/// not emit).
pub fn emission_path_gradient(scene: &Scene, segments: &[Segment], sink: &mut impl GradientSink) {
    let medium = &scene.medium;
    let Some(emission) = &medium.emission else {
        return;
    };
    for segment in segments {
        if let Some(t) = segment.collision() {
            let p = segment.at(t);
            let (index, d_radiance) = emission.radiance_derivative(p);
            let value = segment.throughput * (Vec3::ONE - medium.albedo.at(p)) * d_radiance;
            if value != Vec3::ZERO {
                splat_lookup(emission.filter, index, value, sink);
            }
        }
    }
}
