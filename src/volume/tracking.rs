//! Free-flight sampling (delta tracking) and transmittance estimation (ratio tracking) over the
//! majorant grid. Tentative collisions are exponential steps with the cell's majorant σ̄, restarted
//! at each cell boundary (memoryless); cells with σ̄ = 0 are crossed without sampling.
//!
//! Neither tracker evaluates `exp`: transmittance comes out of products of `1 − σt/σ̄` ∈ [0, 1], so
//! an optical depth far beyond 87 gives an exact 0, never a NaN.

use rand::Rng;

use crate::volume::majorant_walk::Walk;
use crate::volume::medium::Medium;
use crate::volume::ray::{IndexRay, MajorantSegment, SPLIT_DEPTH};
use crate::volume::refine::Refine;

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

/// An optical-depth budget for the next tentative collision: Exp(1).
#[inline]
fn exponential(rng: &mut impl Rng) -> f32 {
    -(1.0 - rng.gen::<f32>()).ln()
}

/// Walks the tentative collisions on `[t0, t1)`: a Poisson process whose rate is each majorant
/// cell's σ̄. One Exp(1) optical-depth budget is drawn per tentative collision and spent across
/// cells (σ̄·Δt per cell), so crossing a cell costs a multiply, not a logarithm; cells with σ̄ = 0
/// are crossed for free. `visit(t, σ̄, rng)` sees every tentative collision in order and returns
/// true to stop the walk there (its t is returned).
#[inline(always)]
fn walk_tentative<R: Rng>(
    medium: &Medium,
    ray: &IndexRay,
    t0: f32,
    t1: f32,
    rng: &mut R,
    visit: impl FnMut(f32, f32, &mut R) -> bool,
) -> Option<f32> {
    // One dispatch per walk: each layout gets its own specialised loop. Loose cells are refined
    // along the ray (`volume::refine`) except in the global mode, the plain baseline.
    if !(ray.o.is_finite() && ray.d.is_finite() && t0.is_finite()) {
        // Nothing to walk on a ray that is nowhere (t1 may be +∞: the walks clip it).
        return None;
    }
    let refine = medium.majorant.refine.then_some((medium, ray));
    match medium.majorant.walk(ray.o, ray.d, t0, t1) {
        Walk::Flat(segments) => walk_segments(segments, refine, rng, visit),
        Walk::Clusters(segments) => walk_segments(segments, refine, rng, visit),
        Walk::Blocks(segments) => walk_segments(segments, refine, rng, visit),
    }
}

#[inline(always)]
fn walk_segments<R: Rng>(
    segments: impl Iterator<Item = MajorantSegment>,
    refine: Option<(&Medium, &IndexRay)>,
    rng: &mut R,
    mut visit: impl FnMut(f32, f32, &mut R) -> bool,
) -> Option<f32> {
    let mut budget = exponential(rng);
    for seg in segments {
        match refine {
            // Only a cell whose walk would cost many tentative collisions is worth refining; the
            // test keeps the common case (a few collisions per cell) as fast as an unrefined walk.
            Some((medium, ray)) if seg.sigma_max * (seg.t1 - seg.t0) > SPLIT_DEPTH => {
                for sub in Refine::new(std::iter::once(seg), medium, ray) {
                    if let Some(t) = cross(sub, &mut budget, rng, &mut visit) {
                        return Some(t);
                    }
                }
            }
            _ => {
                if let Some(t) = cross(seg, &mut budget, rng, &mut visit) {
                    return Some(t);
                }
            }
        }
    }
    None
}

/// Spends the optical-depth budget across one majorant segment; the first tentative collision that
/// `visit` accepts ends the walk.
#[inline(always)]
fn cross<R: Rng>(
    seg: MajorantSegment,
    budget: &mut f32,
    rng: &mut R,
    visit: &mut impl FnMut(f32, f32, &mut R) -> bool,
) -> Option<f32> {
    if seg.sigma_max <= 0.0 {
        return None;
    }
    let mut t = seg.t0;
    loop {
        // The budget against the optical depth left in the segment: crossing a segment waits on
        // a multiply, and only a collision on a division. Comparisons a NaN fails (a ray whose
        // origin or bounds are not finite) end the segment rather than step from NaN to NaN,
        // and so does a collision that rounding would put at t1 or beyond.
        let depth = (seg.t1 - t) * seg.sigma_max;
        let next = (*budget < depth).then(|| t + *budget / seg.sigma_max);
        let Some(next) = next.filter(|&next| next < seg.t1) else {
            *budget = (*budget - depth).max(0.0);
            return None;
        };
        // In absurdly dense media a step can fall below f32 resolution: moving by at least one
        // ulp keeps every walk finite.
        t = next.max(t.next_up());
        if visit(t, seg.sigma_max, rng) {
            return Some(t);
        }
        *budget = exponential(rng);
    }
}

/// Delta tracking on `[t0, t1)`: the distance of the first real collision, sampled with pdf
/// T(t)σt(t), or `None` when the ray leaves the interval (probability T(t1)).
#[inline]
pub fn sample_collision(
    medium: &Medium,
    ray: &IndexRay,
    t0: f32,
    t1: f32,
    rng: &mut impl Rng,
    stats: &mut TrackingStats,
) -> Option<f32> {
    let hit = walk_tentative(medium, ray, t0, t1, rng, |t, sigma_max, rng| {
        stats.lookups += 1;
        rng.gen::<f32>() * sigma_max < medium.sigma_t(ray.at(t))
    });
    stats.collisions += hit.is_some() as u64;
    hit
}

/// Below this, ratio tracking plays Russian roulette: survive with probability T/RR_BELOW and
/// continue with T = RR_BELOW (unbiased, and it ends long walks through dense media early).
const RR_BELOW: f32 = 0.1;

/// One ratio-tracking update of T̂ at a tentative collision; false when the walk is over (T̂ = 0).
#[inline]
fn ratio_step(tr: &mut f32, sigma: f32, sigma_max: f32, rng: &mut impl Rng) -> bool {
    *tr *= (1.0 - sigma / sigma_max).max(0.0);
    if *tr < RR_BELOW {
        if *tr <= 0.0 || rng.gen::<f32>() * RR_BELOW >= *tr {
            *tr = 0.0;
            return false;
        }
        *tr = RR_BELOW;
    }
    true
}

/// Ratio tracking on `[t0, t1)`: an unbiased estimate of T(t0 → t1).
#[inline]
pub fn transmittance(
    medium: &Medium,
    ray: &IndexRay,
    t0: f32,
    t1: f32,
    rng: &mut impl Rng,
    stats: &mut TrackingStats,
) -> f32 {
    stats.shadow_rays += 1;
    let mut tr = 1.0f32;
    walk_tentative(medium, ray, t0, t1, rng, |t, sigma_max, rng| {
        stats.shadow_lookups += 1;
        !ratio_step(&mut tr, medium.sigma_t(ray.at(t)), sigma_max, rng)
    });
    tr
}

/// Samples a distance t′ ∝ T(t′) on `[t0, t1)` from one ratio-tracking walk (differential ratio
/// tracking). Between tentative collisions the ratio-tracking estimate T̂ is constant and unbiased
/// for T at every t, so ∫T ≈ W = Σ T̂·Δt; an interval is picked with probability ∝ T̂·Δt (weighted
/// reservoir, no allocation) and t′ is uniform inside it. Returns `(t′, W)`, so that
/// W·f(t′) estimates ∫ T(t) f(t) dt; `None` when W = 0.
pub fn sample_transmittance_distance(
    medium: &Medium,
    ray: &IndexRay,
    t0: f32,
    t1: f32,
    rng: &mut impl Rng,
    stats: &mut TrackingStats,
) -> Option<(f32, f32)> {
    let mut tr = 1.0f32;
    let mut total = 0.0f32;
    let mut chosen = None;
    let mut last = t0;
    let mut add = |a: f32, b: f32, tr: f32, u: f32| {
        let w = tr * (b - a);
        if w > 0.0 {
            total += w;
            if u * total < w {
                chosen = Some((a, b));
            }
        }
    };
    let stopped = walk_tentative(medium, ray, t0, t1, rng, |t, sigma_max, rng| {
        add(last, t, tr, rng.gen());
        last = t;
        stats.shadow_lookups += 1;
        !ratio_step(&mut tr, medium.sigma_t(ray.at(t)), sigma_max, rng)
    });
    if stopped.is_none() {
        add(last, t1, tr, rng.gen());
    }
    chosen.map(|(a, b)| (a + rng.gen::<f32>() * (b - a), total))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{rngs::StdRng, SeedableRng};

    /// One ratio-tracking step keeps the expectation E[T̂′] = T̂·(1 − σ/σ̄) whether or not its
    /// Russian roulette plays (a walk whose majorant is loose spends most of its steps below
    /// `RR_BELOW`, where a wrong survival weight would bias every shadow ray; the transmittance
    /// tests through tight majorants seldom get there).
    #[test]
    fn a_ratio_step_keeps_its_expectation_through_russian_roulette() {
        let mut rng = StdRng::seed_from_u64(3);
        let n = 200_000;
        for (tr, ratio) in [
            (0.8, 0.3),
            (0.15, 0.5),
            (0.1, 0.1),
            (0.05, 0.9),
            (0.02, 0.0),
        ] {
            let (mut sum, mut sum_sq) = (0.0f64, 0.0f64);
            for _ in 0..n {
                let mut t = tr;
                ratio_step(&mut t, ratio, 1.0, &mut rng);
                assert!((0.0..=1.0).contains(&t));
                sum += f64::from(t);
                sum_sq += f64::from(t) * f64::from(t);
            }
            let mean = sum / n as f64;
            let std_err = ((sum_sq / n as f64 - mean * mean) / n as f64).sqrt();
            let expected = f64::from(tr) * (1.0 - f64::from(ratio));
            assert!(
                (mean - expected).abs() < 4.0 * std_err + 1e-7,
                "T̂ {tr}, σ/σ̄ {ratio}: mean {mean:.5} ± {std_err:.1e}, expected {expected:.5}"
            );
        }
    }
}
