//! Extinction gradients by path replay: a path is traced with the renderer's own sampling and
//! recorded (`render::trace`), then each of its segments adds its share of ∂pixel/∂θ_k.
//!
//! Notation (DESIGN.md, supplement eqs. 45–58): segment j leaves x_{j−1} along ω with throughput
//! β_{j−1}; ℓ = min(t, t_max) is how far it got (clipped to where it is inside the medium's box);
//! R_j = ĥ(x_j) is what the path carries back from x_j on (α·(NEE + deeper) at a collision, the
//! MIS-weighted environment radiance on escape). ∂σt(y)/∂θ_k = density_scale · (lookup weight of
//! voxel k at y).
//!
//! - joint:  β_{j−1} · ℓ · [ĥ(y) − ĥ(x_j)] · ∂σt(y),  y uniform on the segment (eq. 58);
//! - drt:    −β_{j−1} · ℓ · ĥ(x_j) · ∂σt(s)  +  β_{j−1} · W · ĥ(t′) · ∂σt(t′),  t′ ∝ T on [0, t_max];
//! - naive:  −β_{j−1} · ℓ · ĥ(x_j) · ∂σt(s)  +  β_{j−1} · ĥ(x_j) · ∂σt(x_j) / σt(x_j);
//!
//! and for all three, every NEE shadow ray adds −C · ℓ_s · ∂σt(u) (C its contribution, u uniform
//! on it). ĥ at a probe is α·(NEE + indirect): the NEE reuses the light sample of x_j (joint); the
//! indirect part is a suffix path traced from the probe, either on every segment or on one segment
//! per path picked with probability P_j ∝ |β_{j−1}|·ℓ_j and weighted by 1/P_j.

use glam::{IVec3, Vec3};
use rand::Rng;

use crate::render::lights::luminance;
use crate::render::path::{direct_light, trace, LightSample, PathRecord, PathState};
use crate::render::scene::Scene;
use crate::volume::brickmap::{corner, floor_ivec3};
use crate::volume::medium::{Filter, Medium};
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
    /// One suffix path per camera path, on a segment chosen by a reservoir (linear cost).
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
    let value = value * medium.density_scale;
    match medium.filter {
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

#[derive(Debug, Clone, Copy)]
pub struct AdjointOptions {
    pub estimator: Estimator,
    pub suffix: Suffix,
    pub max_depth: u32,
}

/// Per-thread buffers reused from path to path (no allocation in the hot loop).
#[derive(Default)]
pub struct Scratch {
    pub record: PathRecord,
    carried: Vec<Vec3>,
}

impl Scratch {
    pub fn clear(&mut self) {
        self.record.segments.clear();
        self.record.shadows.clear();
        self.carried.clear();
    }
}

/// Traces one camera path and adds its gradient samples to `sink`; returns the path's radiance.
pub fn camera_path_gradient(
    scene: &Scene,
    options: &AdjointOptions,
    origin: Vec3,
    dir: Vec3,
    rng: &mut impl Rng,
    stats: &mut TrackingStats,
    scratch: &mut Scratch,
    sink: &mut impl GradientSink,
) -> Vec3 {
    scratch.clear();
    let radiance = trace(
        scene,
        PathState::camera(origin, dir),
        options.max_depth,
        rng,
        stats,
        Some(&mut scratch.record),
    );
    replay(scene, options, rng, stats, scratch, sink);
    radiance
}

/// ĥ at a scattering point: α·(NEE with `light_sample` + `suffix_weight` × a suffix path), zero
/// beyond the maximum depth (the renderer would not scatter there either).
fn h_at(
    scene: &Scene,
    options: &AdjointOptions,
    p: Vec3,
    dir: Vec3,
    depth: u32,
    light_sample: &LightSample,
    suffix_weight: f32,
    rng: &mut impl Rng,
    stats: &mut TrackingStats,
) -> Vec3 {
    if depth > options.max_depth {
        return Vec3::ZERO;
    }
    let mut in_scattered = direct_light(scene, p, dir, light_sample, rng, stats, None);
    if suffix_weight > 0.0 {
        let state = PathState::scattered(scene, p, dir, depth, rng);
        in_scattered += suffix_weight * trace(scene, state, options.max_depth, rng, stats, None);
    }
    scene.medium.albedo * in_scattered
}

fn replay(
    scene: &Scene,
    options: &AdjointOptions,
    rng: &mut impl Rng,
    stats: &mut TrackingStats,
    scratch: &mut Scratch,
    sink: &mut impl GradientSink,
) {
    let medium = &scene.medium;
    let segments = &scratch.record.segments;
    // R_j = ĥ(x_j), from the last segment back.
    scratch.carried.resize(segments.len(), Vec3::ZERO);
    let mut deeper = Vec3::ZERO;
    for (j, seg) in segments.iter().enumerate().rev() {
        deeper = match (seg.collision, seg.light_sample) {
            (None, _) => seg.escape,
            (Some(_), None) => Vec3::ZERO, // beyond the maximum depth: the path ends unscattered
            (Some(_), Some(_)) => medium.albedo * (seg.nee + seg.continuation_weight * deeper),
        };
        scratch.carried[j] = deeper;
    }
    let in_medium = |seg: &crate::render::path::Segment| {
        (seg.collision.unwrap_or(seg.t_exit) - seg.t_enter).max(0.0)
    };

    // Which segment gets the suffix path (per path), and with what weight.
    let mut chosen = usize::MAX;
    let mut chosen_weight = 0.0;
    if options.estimator != Estimator::Naive && options.suffix == Suffix::PerPath {
        let weight = |seg: &crate::render::path::Segment| {
            if seg.depth <= options.max_depth {
                luminance(seg.throughput) * in_medium(seg)
            } else {
                0.0
            }
        };
        let total: f32 = segments.iter().map(weight).sum();
        if total > 0.0 {
            let mut u = rng.gen::<f32>() * total;
            for (j, seg) in segments.iter().enumerate() {
                let w = weight(seg);
                if w > 0.0 {
                    chosen = j;
                    chosen_weight = total / w;
                    if u < w {
                        break;
                    }
                    u -= w;
                }
            }
        }
    }

    for (j, seg) in segments.iter().enumerate() {
        let length = in_medium(seg);
        if length <= 0.0 || (seg.depth > options.max_depth && seg.collision.is_some()) {
            // Outside the medium, or a collision beyond the maximum depth: ĥ(y) = ĥ(x_j) = 0.
            continue;
        }
        let ray = medium.to_index_ray(seg.origin, seg.dir);
        let carried = scratch.carried[j];
        let suffix_weight = match options.suffix {
            Suffix::PerSegment => 1.0,
            Suffix::PerPath if j == chosen => chosen_weight,
            Suffix::PerPath => 0.0,
        };
        let s = seg.t_enter + rng.gen::<f32>() * length;
        match options.estimator {
            Estimator::Joint => {
                let light_sample = seg.light_sample.unwrap_or_else(|| LightSample::draw(rng));
                let h_probe = h_at(
                    scene,
                    options,
                    seg.origin + seg.dir * s,
                    seg.dir,
                    seg.depth,
                    &light_sample,
                    suffix_weight,
                    rng,
                    stats,
                );
                splat_d_sigma(
                    medium,
                    ray.at(s),
                    seg.throughput * (h_probe - carried) * length,
                    sink,
                );
            }
            Estimator::Drt => {
                splat_d_sigma(medium, ray.at(s), -seg.throughput * carried * length, sink);
                if seg.depth <= options.max_depth {
                    if let Some((t, w)) = sample_transmittance_distance(
                        medium,
                        &ray,
                        seg.t_enter,
                        seg.t_exit,
                        rng,
                        stats,
                    ) {
                        let light_sample = LightSample::draw(rng);
                        let h = h_at(
                            scene,
                            options,
                            seg.origin + seg.dir * t,
                            seg.dir,
                            seg.depth,
                            &light_sample,
                            suffix_weight,
                            rng,
                            stats,
                        );
                        splat_d_sigma(medium, ray.at(t), seg.throughput * h * w, sink);
                    }
                }
            }
            Estimator::Naive => {
                splat_d_sigma(medium, ray.at(s), -seg.throughput * carried * length, sink);
                if let Some(t) = seg.collision {
                    let sigma = medium.sigma_t(ray.at(t));
                    if sigma > 0.0 {
                        splat_d_sigma(medium, ray.at(t), seg.throughput * carried / sigma, sink);
                    }
                }
            }
        }
    }

    // NEE shadow rays: d/dθ of T̂ is −T̂ · ∫∂σt along the ray, one uniform point.
    for shadow in &scratch.record.shadows {
        let length = shadow.t_exit - shadow.t_enter;
        let u = shadow.t_enter + rng.gen::<f32>() * length;
        let ray = medium.to_index_ray(shadow.origin, shadow.dir);
        splat_d_sigma(medium, ray.at(u), -shadow.contribution * length, sink);
    }
}
