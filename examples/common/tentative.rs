//! The tentative collisions of a shadow ray, walked as `volume::tracking` walks them (one Exp(1)
//! optical-depth budget per collision spent across the majorant cells, Russian roulette on a
//! weight below 0.1), with hooks for what the examples vary; without the refinement of loose
//! cells.

use rand::rngs::SmallRng;
use rand::Rng;
use volgrad::volume::medium::Medium;
use volgrad::volume::ray::IndexRay;

pub const RR_BELOW: f32 = 0.1;

/// An Exp(1) budget and the uniform u it was drawn from (e^{−budget} = 1 − u).
pub fn exponential(rng: &mut SmallRng) -> (f32, f32) {
    let u: f32 = rng.gen();
    (-(1.0 - u).ln(), u)
}

/// Russian roulette on a weight below `RR_BELOW`: false when it ends (the weight 0).
#[inline(always)]
pub fn roulette(w: &mut f32, rng: &mut SmallRng) -> bool {
    if *w < RR_BELOW {
        if *w <= 0.0 || rng.gen::<f32>() * RR_BELOW >= *w {
            *w = 0.0;
            return false;
        }
        *w = RR_BELOW;
    }
    true
}

/// Walks the tentative collisions of `ray` from where it enters the medium to where it leaves,
/// each budget drawn by `budget` (as `exponential` gives it). `visit(t, σ̄, u, rng)` sees each
/// collision, with the uniform u its budget came from, and returns false to end the walk. Returns
/// the optical depth the last budget had spent at the exit, `None` when the walk was ended.
#[inline(always)]
pub fn walk(
    medium: &Medium,
    ray: &IndexRay,
    rng: &mut SmallRng,
    mut budget: impl FnMut(&mut SmallRng) -> (f32, f32),
    mut visit: impl FnMut(f32, f32, f32, &mut SmallRng) -> bool,
) -> Option<f32> {
    let Some((t0, t1)) = medium.intersect(ray) else {
        return Some(0.0);
    };
    let (mut drawn, mut u) = budget(rng);
    let mut left = drawn;
    for seg in medium.majorant.walk(ray.o, ray.d, t0, t1) {
        if seg.sigma_max <= 0.0 {
            continue;
        }
        let mut t = seg.t0;
        loop {
            let depth = (seg.t1 - t) * seg.sigma_max;
            let next = (left < depth).then(|| t + left / seg.sigma_max);
            let Some(next) = next.filter(|&next| next < seg.t1) else {
                left = (left - depth).max(0.0);
                break;
            };
            t = next.max(t.next_up());
            if !visit(t, seg.sigma_max, u, rng) {
                return None;
            }
            (drawn, u) = budget(rng);
            left = drawn;
        }
    }
    Some(drawn - left)
}
