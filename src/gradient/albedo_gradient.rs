//! Gradients with respect to the albedo grid's values a_k. A real collision x_j adds
//! β_{j−1}·[(1 − α)·Le + α·(NEE_j + w_j·R_{j+1})] to the pixel (R_{j+1} what the path carries
//! back from the next vertex, w_j Russian roulette's factor), and where the collisions fall does
//! not depend on α (the tracker follows density alone), so per channel
//!
//!   ∂pixel/∂a_k = Σ_j β_{j−1} · (NEE_j + w_j·R_{j+1} − Le(x_j)) · w_k(x_j),
//!
//! with w_k(x_j) the weight of voxel k in the albedo lookup at x_j (in the albedo grid's own index
//! space). Russian roulette's probability depends on α, but its estimate is unbiased for any
//! probability, so the factor is held fixed. A collision past the maximum depth scatters nothing
//! (its term is −Le). Where the path stopped because α = 0, nothing was traced beyond: the
//! in-scattered light there is estimated on the spot with NEE and one suffix path.

use glam::Vec3;
use rand::Rng;

use crate::gradient::adjoint::{
    carried_radiance, splat_lookup, GradientSink, Replay, Scratch, SuffixPlan,
};
use crate::render::path::{LightSample, Segment, SegmentEnd};

impl<R: Rng> Replay<'_, R> {
    /// Traces one camera path and adds its derivatives with respect to the albedo grid's values
    /// to `sink` (RGB: channel c of the sample is ∂pixel_c/∂a_c); returns the path's radiance.
    pub fn camera_path_albedo_gradient(
        &mut self,
        origin: Vec3,
        dir: Vec3,
        scratch: &mut Scratch,
        sink: &mut impl GradientSink,
    ) -> Vec3 {
        let radiance = self.trace_recorded(origin, dir, scratch);
        let Some(grid) = self.scene.medium.albedo.grid() else {
            return radiance;
        };
        let segments = &scratch.record.segments;
        carried_radiance(segments, &mut scratch.carried);
        for (j, segment) in segments.iter().enumerate() {
            let Some(t) = segment.collision() else {
                continue;
            };
            let p = segment.at(t);
            let scattered = match segment.end {
                SegmentEnd::Scattered {
                    nee,
                    continuation_weight,
                    ..
                } => {
                    let deeper = scratch.carried.get(j + 1).copied().unwrap_or(Vec3::ZERO);
                    nee + continuation_weight * deeper
                }
                _ if segment.depth > self.options.max_depth => Vec3::ZERO,
                // Absorbed (α = 0): what would have scattered on, estimated here.
                _ => self.absorbed_in_scattered(segment, t),
            };
            let emitted = match &self.scene.medium.emission {
                Some(e) => e.radiance(p),
                None => Vec3::ZERO,
            };
            let value = segment.throughput * (scattered - emitted);
            if value != Vec3::ZERO {
                splat_lookup(grid.filter, grid.transform.point_to_index(p), value, sink);
            }
        }
        radiance
    }

    /// NEE and one suffix path at distance `t` along `segment`, where the path stopped with α = 0.
    fn absorbed_in_scattered(&mut self, segment: &Segment, t: f32) -> Vec3 {
        let light_sample = LightSample::draw(self.rng);
        let one_path = SuffixPlan {
            count: 1,
            weight: 1.0,
        };
        self.in_scattered(segment, t, &light_sample, one_path)
    }
}
