//! Extinction gradients by path replay: a path is traced with the renderer's own sampling and
//! recorded (`render::path::trace`), then each of its segments adds its share of ∂pixel/∂θ_k.
//!
//! Notation (DESIGN.md, supplement eqs. 45–58): segment j leaves x_{j−1} along ω with throughput
//! β_{j−1}; ℓ = min(t, t_max) is how far it got (clipped to where it is inside the medium's box);
//! R_j = ĥ(x_j) is what the path carries back from x_j on ((1 − α)·Le + α·(NEE + deeper) at a
//! collision, the MIS-weighted environment radiance on escape: the supplement's h, eq. 45, with
//! the emission term volgrad adds). ∂σt(y)/∂θ_k = density_scale · (lookup weight of
//! voxel k at y).
//!
//! - joint:  β_{j−1} · ℓ · [ĥ(y) − ĥ(x_j)] · ∂σt(y),  y uniform on the segment (eq. 58);
//! - drt:    −β_{j−1} · ℓ · ĥ(x_j) · ∂σt(s)  +  β_{j−1} · W · ĥ(t′) · ∂σt(t′),  t′ ∝ T on [0, t_max];
//! - naive:  −β_{j−1} · ℓ · ĥ(x_j) · ∂σt(s)  +  β_{j−1} · ĥ(x_j) · ∂σt(x_j) / σt(x_j);
//!
//! and for all three, every NEE shadow ray adds −C · ℓ_s · ∂σt(u) (C its contribution, u uniform
//! on it). ĥ at a probe is (1 − α)·Le + α·(NEE + indirect): the emission there (none in a medium
//! that does not emit); the NEE reuses the light sample of x_j (joint) and walks one shadow ray, to
//! a light picked ∝ its unoccluded contribution (`direct_light_one`); the indirect part is suffix
//! paths traced from the probes, either one on every segment or K per path on segments picked with
//! probability P_j ∝ |β_{j−1}|·ℓ_j (systematic sampling), each weighted by 1/(K·P_j).
//!
//! In the code: [`carried_radiance`] gives R_j, `Replay::plan_suffixes` the suffix segments and
//! their weights, and `joint_term`, `drt_term`, `naive_term` (with the `transmittance_term` that drt
//! and naive share) and `shadow_term` are the formulas above, one function each.
//!
//! # The contract between `trace` and the replay
//!
//! `trace` pushes exactly one [`Segment`] per free flight: where it ran (origin, direction, where
//! it enters and leaves the medium's box, the collision distance or none), the throughput β_{j−1}
//! entering it, and what its end contributed — after a collision that scattered, the light sample,
//! the NEE radiance before the albedo and the Russian-roulette factor w_j (1/q, or 0 where the path
//! ended); on escape, the MIS-weighted environment radiance; at every collision, scattered or not
//! (past the maximum depth, or absorbed with albedo 0), the medium's emission (1 − α)·Le there
//! (zero in a medium that does not emit). From these fields alone the replay
//! re-derives, last segment first, the radiance the path carries back from each vertex,
//! R_j = (1 − α)·Le_j + α·(NEE_j + w_j·R_{j+1}) (`carried_radiance`; the emission term at any
//! collision, the rest where it scattered), and every estimator uses R_j as ĥ(x_j). That
//! rule is the one `trace` used to add up the pixel, written a second time, backwards; the test
//! `carried_radiance_reproduces_traced_radiance` in `tests/replay.rs` ties the two together: for
//! random camera paths in scenes where Russian roulette, the max-depth cut, absorption, a sun and
//! environment maps all occur, R_1 must equal the radiance `trace` returned, and at every vertex
//! the radiance must split into Σ_{i<j} β_{i−1}·α·NEE_i + β_{j−1}·R_j. Change what `trace` records
//! or how it weights a path, and that test says which half was forgotten.

use glam::{IVec3, Vec3};
use rand::Rng;

use crate::render::lights::luminance;
use crate::render::path::{
    direct_light_one, emitted, trace, LightSample, PathRecord, PathState, Segment, SegmentEnd,
    ShadowRay,
};
use crate::render::scene::Scene;
use crate::volume::brickmap::{corner, floor_ivec3};
use crate::volume::medium::{Filter, IndexRay, Medium};
use crate::volume::tracking::{sample_transmittance_distance, TrackingStats};

#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Estimator {
    /// Sample matching: scattering and transmittance parts at one shared probe per segment.
    Joint,
    /// Differential ratio tracking (Nimier-David et al. 2022).
    Drt,
    /// Differentiated free-flight sampling: biased where σt = 0, noisy where σt is small.
    Naive,
}

crate::display_as_value_enum!(Estimator);

#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Suffix {
    /// K suffix paths per camera path (`--suffix-paths`, 2 by default), on segments picked
    /// ∝ |β|·ℓ (linear cost).
    PerPath,
    /// A suffix path on every segment (quadratic cost).
    PerSegment,
}

crate::display_as_value_enum!(Suffix);

/// Receives one sample of ∂pixel/∂θ_k (RGB) for voxel k.
pub trait GradientSink {
    fn add(&mut self, voxel: IVec3, d_pixel: Vec3);

    /// The eight corners of a trilinear cell at once (corner k = `base + corner(k)`), so that
    /// sinks can resolve the cell's brick once.
    #[inline]
    fn add_cell(&mut self, base: IVec3, weights: &[f32; 8], d_pixel: Vec3) {
        for (k, &w) in weights.iter().enumerate() {
            if w > 0.0 {
                self.add(base + corner(k), d_pixel * w);
            }
        }
    }
}

/// Adds `value · ∂σt(p)/∂θ_k` for every voxel k that the lookup at index point `p` weights.
#[inline]
pub fn splat_d_sigma(medium: &Medium, p: Vec3, value: Vec3, sink: &mut impl GradientSink) {
    splat_lookup(medium.filter, p, value * medium.density_scale, sink);
}

/// `value` spread over the voxels a lookup at index point `p` through `filter` weights, by their
/// weights.
pub fn splat_lookup(filter: Filter, p: Vec3, value: Vec3, sink: &mut impl GradientSink) {
    match filter {
        Filter::Nearest => sink.add(floor_ivec3(p + 0.5), value),
        Filter::Trilinear => {
            let base = floor_ivec3(p);
            let f = p - base.as_vec3();
            let (g, h) = (Vec3::ONE - f, f);
            // Corner k has bits x = 4, y = 2, z = 1 (see `brickmap::corner`).
            let weights = [
                g.x * g.y * g.z,
                g.x * g.y * h.z,
                g.x * h.y * g.z,
                g.x * h.y * h.z,
                h.x * g.y * g.z,
                h.x * g.y * h.z,
                h.x * h.y * g.z,
                h.x * h.y * h.z,
            ];
            sink.add_cell(base, &weights, value);
        }
    }
}

/// Suffix paths per camera path (`Suffix::PerPath`): two instead of one cut joint's per-voxel
/// variance by about 40 % on the cloud and 27 % on the smoke, for a variance × time of 0.69–0.90×
/// on the cloud (four runs) and 0.77× on the smoke (one); three or four gain no more than they
/// cost (`VOLGRAD_BENCH_SUFFIX_PATHS=K cargo bench --bench gradients`,
/// docs/results-rendering.md).
pub const DEFAULT_SUFFIX_PATHS: u32 = 2;

#[derive(Debug, Clone, Copy)]
pub struct AdjointOptions {
    pub estimator: Estimator,
    pub suffix: Suffix,
    /// Suffix paths per camera path with `Suffix::PerPath` (K).
    pub suffix_paths: u32,
    pub max_depth: u32,
}

/// Per-thread buffers reused from path to path (no allocation in the hot loop).
#[derive(Default)]
pub struct Scratch {
    pub record: PathRecord,
    /// R_j of the recorded path (`carried_radiance`).
    pub carried: Vec<Vec3>,
    suffixes: Vec<SuffixPlan>,
}

impl Scratch {
    pub fn clear(&mut self) {
        self.record.segments.clear();
        self.record.shadows.clear();
        self.carried.clear();
    }
}

/// R_j = ĥ(x_j) for every segment of a recorded path (into `carried`, index j − 1), computed from
/// the last segment back: what the path carries back from the end of segment j, before the
/// throughput β_{j−1} that reaches it.
///
/// - escape: the MIS-weighted environment radiance;
/// - a collision that scattered: R_j = (1 − α)·Le_j + α·(NEE_j + w_j·R_{j+1}), w_j the
///   Russian-roulette factor (1/q, or 0 where the path ended, which is also where R_{j+1} would
///   be missing), Le_j the medium's emission there (zero where it does not emit);
/// - a collision that did not scatter (past the maximum depth, or absorbed with albedo 0): the
///   emission term (1 − α)·Le_j alone.
///
/// This is `trace`'s sum read backwards: with β_0 = 1, R_1 is the path's radiance.
pub fn carried_radiance(segments: &[Segment], carried: &mut Vec<Vec3>) {
    carried.clear();
    carried.resize(segments.len(), Vec3::ZERO);
    let mut deeper = Vec3::ZERO;
    for (j, segment) in segments.iter().enumerate().rev() {
        deeper = match segment.end {
            SegmentEnd::Escaped { radiance } => radiance,
            SegmentEnd::Stopped { emission, .. } => emission,
            SegmentEnd::Scattered {
                emission,
                albedo,
                nee,
                continuation_weight,
                ..
            } => emission + albedo * (nee + continuation_weight * deeper),
        };
        carried[j] = deeper;
    }
}

/// What every step of a replay needs: the scene, the options, the path's random stream and the
/// tracking counters. They travel together from the camera ray down to every probe's suffix.
pub struct Replay<'a, R> {
    pub scene: &'a Scene,
    pub options: &'a AdjointOptions,
    pub rng: &'a mut R,
    pub stats: &'a mut TrackingStats,
}

/// How many suffix paths (the indirect part of ĥ) a segment's probe traces, and the weight of each.
#[derive(Debug, Clone, Copy, Default)]
pub struct SuffixPlan {
    pub count: u32,
    pub weight: f32,
}

/// Segment j as the estimators' terms see it.
struct ReplayedSegment<'s> {
    segment: &'s Segment,
    /// The segment in index space, where ∂σt is looked up.
    ray: IndexRay,
    /// ℓ, from where the segment enters the medium's box.
    length: f32,
    /// ĥ(x_j) = R_j.
    h_end: Vec3,
    /// s ~ U[t_enter, t_enter + ℓ]: the probe y of joint, the transmittance point of drt and naive.
    probe: f32,
    /// The suffix paths of this segment's ĥ evaluations (none: NEE only).
    suffix: SuffixPlan,
}

impl<R: Rng> Replay<'_, R> {
    /// Traces one camera path and adds its gradient samples to `sink`; returns the path's radiance.
    pub fn camera_path_gradient(
        &mut self,
        origin: Vec3,
        dir: Vec3,
        scratch: &mut Scratch,
        sink: &mut impl GradientSink,
    ) -> Vec3 {
        let radiance = self.trace_recorded(origin, dir, scratch);
        carried_radiance(&scratch.record.segments, &mut scratch.carried);
        self.add_path_gradient(
            &scratch.record,
            &scratch.carried,
            &mut scratch.suffixes,
            sink,
        );
        radiance
    }

    /// Traces one camera path into `scratch.record`; returns its radiance. Every gradient pass
    /// traces its camera paths here, so that passes with the same seed follow the same paths.
    pub fn trace_recorded(&mut self, origin: Vec3, dir: Vec3, scratch: &mut Scratch) -> Vec3 {
        scratch.clear();
        trace(
            self.scene,
            PathState::camera(origin, dir),
            self.options.max_depth,
            self.rng,
            self.stats,
            Some(&mut scratch.record),
        )
    }

    /// Every segment's term of the chosen estimator, then every shadow ray's. The random numbers
    /// are drawn in a fixed order (suffix choice; per segment the probe s, then the estimator's
    /// own; then the shadow rays), which is what makes a seed reproduce a gradient.
    fn add_path_gradient(
        &mut self,
        record: &PathRecord,
        carried: &[Vec3],
        suffixes: &mut Vec<SuffixPlan>,
        sink: &mut impl GradientSink,
    ) {
        let medium = &self.scene.medium;
        self.plan_suffixes(&record.segments, suffixes);
        for (j, segment) in record.segments.iter().enumerate() {
            let length = segment.length_in_medium();
            let beyond = segment.depth > self.options.max_depth && segment.collision().is_some();
            if length <= 0.0 || (beyond && medium.emission.is_none()) {
                // Outside the medium, or a collision beyond the maximum depth in a medium that
                // does not emit: ĥ(y) = ĥ(x_j) = 0.
                continue;
            }
            let replayed = ReplayedSegment {
                segment,
                ray: medium.to_index_ray(segment.origin, segment.dir),
                length,
                h_end: carried[j],
                probe: segment.t_enter + self.rng.gen::<f32>() * length,
                suffix: suffixes[j],
            };
            match self.options.estimator {
                Estimator::Joint => self.joint_term(&replayed, sink),
                Estimator::Drt => self.drt_term(&replayed, sink),
                Estimator::Naive => self.naive_term(&replayed, sink),
            }
        }
        for shadow in &record.shadows {
            self.shadow_term(shadow, sink);
        }
    }

    /// Which probes trace suffix paths: with `Suffix::PerPath`, K = `suffix_paths` per camera
    /// path, on segments picked with probability P_j ∝ |β_{j−1}|·ℓ_j among those that can scatter
    /// (systematic sampling: the K picks sit at (i + ξ)/K of the way through the cumulative P_j, one
    /// random number for all), each weighted by 1/(K·P_j) (linear cost); with `Suffix::PerSegment`,
    /// one on every segment, weight 1 (quadratic cost).
    fn plan_suffixes(&mut self, segments: &[Segment], plan: &mut Vec<SuffixPlan>) {
        plan.clear();
        plan.resize(segments.len(), SuffixPlan::default());
        match (self.options.suffix, self.options.estimator) {
            (Suffix::PerSegment, _) => {
                plan.fill(SuffixPlan {
                    count: 1,
                    weight: 1.0,
                });
                return;
            }
            (Suffix::PerPath, Estimator::Naive) => return,
            (Suffix::PerPath, _) => {}
        }
        let max_depth = self.options.max_depth;
        let p_unnormalised = |segment: &Segment| {
            if segment.depth <= max_depth {
                luminance(segment.throughput) * segment.length_in_medium()
            } else {
                0.0
            }
        };
        let total: f32 = segments.iter().map(p_unnormalised).sum();
        if total <= 0.0 {
            return;
        }
        let k = self.options.suffix_paths.max(1);
        let step = total / k as f32;
        let xi = self.rng.gen::<f32>();
        let (mut picked, mut cumulative, mut last_positive) = (0, 0.0f32, None);
        for (j, segment) in segments.iter().enumerate() {
            let p = p_unnormalised(segment);
            if p > 0.0 {
                plan[j].weight = total / (k as f32 * p);
                cumulative += p;
                while picked < k && (picked as f32 + xi) * step < cumulative {
                    plan[j].count += 1;
                    picked += 1;
                }
                last_positive = Some(j);
            }
        }
        // Rounding can leave the last picks just past the end: they belong to the last segment.
        if let Some(j) = last_positive {
            plan[j].count += k - picked;
        }
    }

    /// joint (eq. 58): β_{j−1}·ℓ·[ĥ(y) − ĥ(x_j)]·∂σt(y) at the probe y. ĥ(y) reuses x_j's light
    /// sample, so that its NEE is correlated with the one in ĥ(x_j) and the difference stays
    /// small; a segment that ended without one (escape, absorption) draws a fresh one.
    fn joint_term(&mut self, replayed: &ReplayedSegment, sink: &mut impl GradientSink) {
        let segment = replayed.segment;
        let light_sample = match segment.end {
            SegmentEnd::Scattered { light_sample, .. } => light_sample,
            _ => LightSample::draw(self.rng),
        };
        let h_probe = self.h_at(segment, replayed.probe, &light_sample, replayed.suffix);
        splat_d_sigma(
            &self.scene.medium,
            replayed.ray.at(replayed.probe),
            segment.throughput * (h_probe - replayed.h_end) * replayed.length,
            sink,
        );
    }

    /// drt: the transmittance part, plus the scattering part β_{j−1}·W·ĥ(t′)·∂σt(t′) with t′ ∝ T
    /// on [0, t_max] from one ratio-tracking walk (W = Σ T̂·Δt) and ĥ(t′) from a fresh light
    /// sample.
    fn drt_term(&mut self, replayed: &ReplayedSegment, sink: &mut impl GradientSink) {
        self.transmittance_term(replayed, sink);
        let segment = replayed.segment;
        let medium = &self.scene.medium;
        if segment.depth > self.options.max_depth && medium.emission.is_none() {
            return;
        }
        let ray = &replayed.ray;
        let Some((t, w)) = sample_transmittance_distance(
            medium,
            ray,
            segment.t_enter,
            segment.t_exit,
            self.rng,
            self.stats,
        ) else {
            return;
        };
        let light_sample = LightSample::draw(self.rng);
        let h = self.h_at(segment, t, &light_sample, replayed.suffix);
        splat_d_sigma(medium, ray.at(t), segment.throughput * h * w, sink);
    }

    /// naive: the transmittance part, plus the scattering part β_{j−1}·ĥ(x_j)·∂σt(x_j)/σt(x_j)
    /// at a real collision (nothing where σt(x_j) = 0: the bias in empty voxels).
    fn naive_term(&mut self, replayed: &ReplayedSegment, sink: &mut impl GradientSink) {
        self.transmittance_term(replayed, sink);
        let segment = replayed.segment;
        if let Some(t) = segment.collision() {
            let medium = &self.scene.medium;
            let x = replayed.ray.at(t);
            let sigma = medium.sigma_t(x);
            if sigma > 0.0 {
                splat_d_sigma(medium, x, segment.throughput * replayed.h_end / sigma, sink);
            }
        }
    }

    /// The transmittance part that drt and naive share: −β_{j−1}·ℓ·ĥ(x_j)·∂σt(s).
    fn transmittance_term(&self, replayed: &ReplayedSegment, sink: &mut impl GradientSink) {
        splat_d_sigma(
            &self.scene.medium,
            replayed.ray.at(replayed.probe),
            -replayed.segment.throughput * replayed.h_end * replayed.length,
            sink,
        );
    }

    /// A NEE shadow ray's transmittance derivative: d T̂ = −T̂·∫∂σt along the ray, so the term is
    /// −C·ℓ_s·∂σt(u) with C the ray's contribution and u uniform on it.
    fn shadow_term(&mut self, shadow: &ShadowRay, sink: &mut impl GradientSink) {
        let medium = &self.scene.medium;
        let length = shadow.t_exit - shadow.t_enter;
        let u = shadow.t_enter + self.rng.gen::<f32>() * length;
        let ray = medium.to_index_ray(shadow.origin, shadow.dir);
        splat_d_sigma(medium, ray.at(u), -shadow.contribution * length, sink);
    }

    /// ĥ at distance `t` along `segment`: the emission there, (1 − α)·Le, plus α·(NEE with
    /// `light_sample` + the weighted sum of `suffix.count` suffix paths), the latter zero past the
    /// maximum depth (the renderer would not scatter there either).
    fn h_at(
        &mut self,
        segment: &Segment,
        t: f32,
        light_sample: &LightSample,
        suffix: SuffixPlan,
    ) -> Vec3 {
        let medium = &self.scene.medium;
        let p = segment.at(t);
        let albedo = medium.albedo.at(p);
        let emission = emitted(medium, p, albedo);
        if segment.depth > self.options.max_depth {
            return emission;
        }
        emission + albedo * self.in_scattered(segment, t, light_sample, suffix)
    }

    /// The light arriving at distance `t` along `segment` to scatter on, before the albedo: NEE
    /// with `light_sample` plus the weighted sum of `suffix.count` suffix paths.
    pub fn in_scattered(
        &mut self,
        segment: &Segment,
        t: f32,
        light_sample: &LightSample,
        suffix: SuffixPlan,
    ) -> Vec3 {
        let scene = self.scene;
        let (p, dir) = (segment.at(t), segment.dir);
        let mut in_scattered =
            direct_light_one(scene, p, dir, light_sample, self.rng, self.stats, None);
        for _ in 0..suffix.count {
            let state = PathState::scattered(scene, p, dir, segment.depth, self.rng);
            let max_depth = self.options.max_depth;
            in_scattered +=
                suffix.weight * trace(scene, state, max_depth, self.rng, self.stats, None);
        }
        in_scattered
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::brickmap::{BrickMap, BrickMapBuilder};
    use rand::{rngs::StdRng, SeedableRng};

    /// Records every splat as (voxel, weight).
    struct Recorded(Vec<(IVec3, f32)>);

    impl GradientSink for Recorded {
        fn add(&mut self, voxel: IVec3, d_pixel: Vec3) {
            self.0.push((voxel, d_pixel.x));
        }
    }

    /// A splat is the adjoint of the lookup: the weights it gives the voxels, applied to any grid,
    /// give back that grid's lookup at the point, Σₖ wₖ(p)·θₖ = σ(p). A splat that gave a corner
    /// its mirror's weight, or named the corners in another order than the lookup reads them,
    /// would still sum to 1 (and pass every test through ⟨g, 1⟩); this catches it.
    #[test]
    fn a_splat_is_the_adjoint_of_the_lookup() {
        let mut rng = StdRng::seed_from_u64(7);
        let mut builder = BrickMapBuilder::new();
        for x in -3..13 {
            for y in -3..13 {
                for z in -3..13 {
                    builder.set(IVec3::new(x, y, z), rng.gen::<f32>(), true);
                }
            }
        }
        let grid: BrickMap = builder.build();
        for _ in 0..200 {
            // Inside the block, straddling brick boundaries (at 0 and 8) too.
            let p = Vec3::new(rng.gen(), rng.gen(), rng.gen()) * 14.0 - 2.0;
            for (filter, lookup) in [
                (Filter::Trilinear, grid.trilinear(p)),
                (Filter::Nearest, grid.nearest(p)),
            ] {
                let mut splats = Recorded(Vec::new());
                splat_lookup(filter, p, Vec3::ONE, &mut splats);
                let adjoint: f32 = (splats.0.iter()).map(|&(v, w)| w * grid.voxel(v)).sum();
                assert!(
                    (adjoint - lookup).abs() < 1e-5,
                    "{filter:?} at {p}: Σ w·θ = {adjoint}, lookup {lookup}"
                );
            }
        }
    }
}
