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
//! (its term is −Le). Where the path stopped because β·α = 0, nothing was traced beyond: the
//! in-scattered light L_s there is estimated on the spot with NEE and one suffix path. It serves
//! that vertex's own term, and R at the stop as well: R_j = (1 − α_j)·Le + α_j·L_s holds in every
//! channel, also those whose throughput was already 0 (an RGB albedo zero in a channel at an
//! earlier vertex), where the path's radiance does not need it but that earlier vertex's derivative
//! does (∂pixel_c/∂α_{j−1,c} at α_{j−1,c} = 0 carries R_{j,c}).

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
        let stop = self.in_scattered_at_stop(segments);
        if let Some((last, in_scattered)) = stop {
            let p = segments[last].at(segments[last].collision().unwrap_or(0.0));
            let extra = self.scene.medium.albedo.at(p) * in_scattered;
            add_behind(segments, &mut scratch.carried, last, extra);
        }
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
                _ => match stop {
                    // Stopped (β·α = 0): what would have scattered on, estimated above.
                    Some((last, in_scattered)) if last == j => in_scattered,
                    // Past the maximum depth: nothing scatters.
                    _ => Vec3::ZERO,
                },
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

    /// Where the path stopped at a collision within the maximum depth (β·α = 0 in every
    /// channel): the last segment's index and the light arriving there to scatter on, estimated
    /// with NEE and one suffix path.
    fn in_scattered_at_stop(&mut self, segments: &[Segment]) -> Option<(usize, Vec3)> {
        let last = segments.len().checked_sub(1)?;
        let segment = &segments[last];
        let stopped = matches!(segment.end, SegmentEnd::Stopped { .. });
        let t = segment.collision()?;
        if !stopped || segment.depth > self.options.max_depth {
            return None;
        }
        let light_sample = LightSample::draw(self.rng);
        let one_path = SuffixPlan {
            count: 1,
            weight: 1.0,
        };
        Some((last, self.in_scattered(segment, t, &light_sample, one_path)))
    }
}

/// Adds `extra` to R at vertex `last` and what it carries back to every vertex before it:
/// R_i gains α_i·w_i·(R_{i+1}'s gain) at each scattering vertex (`carried_radiance`'s rule).
fn add_behind(segments: &[Segment], carried: &mut [Vec3], last: usize, extra: Vec3) {
    let mut gain = extra;
    carried[last] += gain;
    for i in (0..last).rev() {
        gain = match segments[i].end {
            SegmentEnd::Scattered {
                albedo,
                continuation_weight,
                ..
            } => albedo * continuation_weight * gain,
            _ => Vec3::ZERO,
        };
        carried[i] += gain;
    }
}
