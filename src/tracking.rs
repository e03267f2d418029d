//! Free-flight sampling (delta tracking) and transmittance estimation (ratio tracking) over the
//! majorant grid. Tentative collisions are exponential steps with the cell's majorant σ̄, restarted
//! at each cell boundary (memoryless); cells with σ̄ = 0 are crossed without sampling.
//!
//! Neither tracker evaluates `exp`: transmittance comes out of products of `1 − σt/σ̄` ∈ [0, 1], so
//! an optical depth far beyond 87 gives an exact 0, never a NaN.

use rand::Rng;

use crate::medium::{IndexRay, Medium};

/// Counters kept per thread and summed once at the end.
#[derive(Debug, Default, Clone, Copy)]
pub struct TrackingStats {
    /// Density lookups made while sampling free-flight distances.
    pub lookups: u64,
    /// Real collisions found by those lookups.
    pub collisions: u64,
    /// Density lookups made by ratio tracking (shadow rays).
    pub shadow_lookups: u64,
    pub shadow_rays: u64,
}

impl std::ops::AddAssign for TrackingStats {
    fn add_assign(&mut self, o: Self) {
        self.lookups += o.lookups;
        self.collisions += o.collisions;
        self.shadow_lookups += o.shadow_lookups;
        self.shadow_rays += o.shadow_rays;
    }
}

/// The next tentative collision after `t`: an exponential step with rate `sigma_max` (> 0). In
/// absurdly dense media the step can fall below f32 resolution; always moving by at least one ulp
/// keeps every walk finite.
#[inline]
fn next_tentative(t: f32, rng: &mut impl Rng, sigma_max: f32) -> f32 {
    (t - (1.0 - rng.gen::<f32>()).ln() / sigma_max).max(t.next_up())
}

/// Delta tracking on `[t0, t1)`: the distance of the first real collision, sampled with pdf
/// T(t)σt(t), or `None` when the ray leaves the interval (probability T(t1)).
#[inline]
pub fn sample_collision(medium: &Medium, ray: &IndexRay, t0: f32, t1: f32, rng: &mut impl Rng, stats: &mut TrackingStats) -> Option<f32> {
    for seg in medium.majorant.walk(ray.o, ray.d, t0, t1) {
        if seg.sigma_max <= 0.0 {
            continue;
        }
        let mut t = seg.t0;
        loop {
            t = next_tentative(t, rng, seg.sigma_max);
            if t >= seg.t1 {
                break;
            }
            stats.lookups += 1;
            let sigma = medium.sigma_t(ray.at(t));
            if rng.gen::<f32>() * seg.sigma_max < sigma {
                stats.collisions += 1;
                return Some(t);
            }
        }
    }
    None
}

/// Below this, ratio tracking plays Russian roulette: survive with probability T/RR_BELOW and
/// continue with T = RR_BELOW (unbiased, and it ends long walks through dense media early).
const RR_BELOW: f32 = 0.1;

/// Ratio tracking on `[t0, t1)`: an unbiased estimate of T(t0 → t1).
#[inline]
pub fn transmittance(medium: &Medium, ray: &IndexRay, t0: f32, t1: f32, rng: &mut impl Rng, stats: &mut TrackingStats) -> f32 {
    stats.shadow_rays += 1;
    let mut tr = 1.0f32;
    for seg in medium.majorant.walk(ray.o, ray.d, t0, t1) {
        if seg.sigma_max <= 0.0 {
            continue;
        }
        let mut t = seg.t0;
        loop {
            t = next_tentative(t, rng, seg.sigma_max);
            if t >= seg.t1 {
                break;
            }
            stats.shadow_lookups += 1;
            tr *= (1.0 - medium.sigma_t(ray.at(t)) / seg.sigma_max).max(0.0);
            if tr < RR_BELOW {
                if tr <= 0.0 || rng.gen::<f32>() * RR_BELOW >= tr {
                    return 0.0;
                }
                tr = RR_BELOW;
            }
        }
    }
    tr
}
