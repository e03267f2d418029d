//! How many paths a gradient pass traces through each pixel.
//!
//! A pass estimates Σᵢ δᵢ · ∂Iᵢ/∂θ, δ the adjoint image. With nᵢ paths through pixel i the
//! estimate's variance is Σᵢ |δᵢ|² sᵢ² / nᵢ (sᵢ² one path's variance), and it costs Σᵢ nᵢ cᵢ
//! (cᵢ one path's cost). Uniform samples spend as much on a pixel whose δ is nearly 0 as on the
//! one that decides the step. Drawn in proportion to |δᵢ| at the cost of a uniform pass
//! (nᵢ = k|δᵢ|, k = spp Σc / Σ|δ|c), the variance is Σ|δ| · Σ|δ|c / (Σc · Σδ²) times the
//! uniform pass's (for equal costs E\[|δ|\]² / E\[δ²\] ≤ 1): the paths go where the adjoint weighs
//! them.
//!
//! Unbiased for any expected count mᵢ > 0 that depends on δ alone: nᵢ is mᵢ rounded up or down
//! at random (E\[nᵢ\] = mᵢ) and each path weighs δᵢ / mᵢ, so E\[Σ paths\] = δᵢ · E\[∂Iᵢ/∂θ\]. The
//! adjoint comes from renders independent of the pass's paths, so the choice does not correlate
//! with what the paths find. A path weighs |δᵢ|/mᵢ: about 1/k = Σ|δ|c / (spp Σc) (a mean of |δ|₁,
//! over spp) at every pixel, however small its δ, or, capped, |δᵢ| / (8 spp); the gradient's quanta
//! are sized by that weight (`path_weight`, `bands::QuantumBands`), so that a capped hot pixel's
//! paths get a band of their own rather than a quantum that rounds every other path away.

use glam::Vec3;
use rand::Rng;

use crate::render::sampling::{sample_rng, Pass};

/// A pixel never takes more than this many times the pass's spp, so one pixel whose δ is an
/// outlier (a firefly in the residual) cannot hold a pass up.
const MOST_PER_PIXEL: f64 = 8.0;

/// The sample index of the stream that rounds a pixel's expected count (beyond any real sample's:
/// a pixel takes at most `MOST_PER_PIXEL` × spp paths).
const ROUNDING_STREAM: u32 = u32::MAX;

/// Paths per pixel in a gradient pass.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub enum PixelSamples {
    /// `spp` paths through every pixel.
    #[default]
    Uniform,
    /// min(`per_adjoint` · |δᵢ|₁, 8 · spp) paths through pixel i on average (from
    /// `following_adjoint`).
    Adjoint { per_adjoint: f64 },
}

impl PixelSamples {
    /// Samples through a pixel whose adjoint is `delta`, each weighing δ / `divisor`: (n, divisor)
    /// with E\[n\] = divisor. `seed` and `pixel` pick the rounding's random stream.
    #[inline]
    pub fn draw(&self, spp: u32, delta: Vec3, seed: u64, pixel: u64) -> (u32, f64) {
        let expected = self.expected(spp, delta);
        match *self {
            PixelSamples::Uniform => (spp, expected),
            PixelSamples::Adjoint { .. } if expected <= 0.0 => (0, 1.0),
            PixelSamples::Adjoint { .. } => {
                let u: f64 = sample_rng(seed, pixel, ROUNDING_STREAM, Pass::Adjoint).gen();
                let n = expected.floor() as u32 + (u < expected.fract()) as u32;
                (n, expected)
            }
        }
    }

    /// E\[n\], the paths through a pixel whose adjoint is `delta` on average.
    #[inline]
    fn expected(&self, spp: u32, delta: Vec3) -> f64 {
        match *self {
            PixelSamples::Uniform => spp as f64,
            PixelSamples::Adjoint { per_adjoint } => {
                // Below the rounding's own stream whatever the spp (and u32's range).
                let most = (MOST_PER_PIXEL * spp as f64).min((ROUNDING_STREAM - 1) as f64);
                (per_adjoint * delta.abs().element_sum() as f64).min(most)
            }
        }
    }

    /// What a path through a pixel whose adjoint is `delta` weighs against a path of `spp`
    /// uniform ones: spp / E\[n\] (each weighs δ / E\[n\]); exactly 1 for uniform paths, 0 where
    /// the pixel takes none. The gradient's quanta are sized by it (`QuantumBands`): a pixel
    /// far below the others in |δ| takes a path rarely and a heavy one.
    #[inline]
    pub fn path_weight(&self, spp: u32, delta: Vec3) -> f64 {
        let expected = self.expected(spp, delta);
        if expected > 0.0 {
            spp as f64 / expected
        } else {
            0.0
        }
    }

    /// Samples in proportion to |δ|₁ that cost what `spp` uniform samples do: over the pixels
    /// (|δᵢ|₁, cᵢ), cᵢ one path's cost there, `per_adjoint` = k with Σ min(k·|δᵢ|₁, 8·spp)·cᵢ =
    /// spp·Σ cᵢ. The cap counts in that sum: else one outlier (a firefly in a target: 10⁴ beside
    /// residuals of 0.01) would take most of the budget and keep only its 8·spp paths of it,
    /// leaving the pass a hundredth of its cost. Uniform when every δ is 0 (or no pixel is
    /// given). A non-finite δ is left out of the sums: its samples are dropped and counted by the
    /// pass whatever their number, and in the sums it would leave every other pixel without a
    /// path.
    pub fn following_adjoint(pixels: &[(f32, f32)], spp: u32) -> Self {
        let pixels: Vec<(f64, f64)> = (pixels.iter())
            .filter(|(a, _)| a.is_finite())
            .map(|&(a, c)| (f64::from(a), f64::from(c)))
            .collect();
        let budget = spp as f64 * pixels.iter().map(|&(_, c)| c).sum::<f64>();
        let most = MOST_PER_PIXEL * spp as f64;
        let weighted: f64 = pixels.iter().map(|&(a, c)| a * c).sum();
        let mut per_adjoint = budget / weighted;
        if weighted > 0.0 && pixels.iter().any(|&(a, _)| a * per_adjoint >= most) {
            per_adjoint = filled_below_the_cap(pixels, budget, most);
        }
        if weighted > 0.0 && per_adjoint.is_finite() {
            PixelSamples::Adjoint { per_adjoint }
        } else {
            PixelSamples::Uniform
        }
    }
}

/// k with Σ min(k·aᵢ, most)·cᵢ = budget over `pixels` (aᵢ, cᵢ), some of which k = budget / Σ aᵢcᵢ
/// puts at the cap (water-filling). In order of a, largest first: with the first j pixels capped,
/// k_j = (budget − most·Σ_{i<j} cᵢ) / Σ_{i≥j} aᵢcᵢ. Capping a pixel that k_j puts at the cap
/// frees cost, so k_{j+1} ≥ k_j and those before stay capped; the first j whose own pixel k_j
/// leaves below the cap is the answer. One sort, where capping pixels round by round took a
/// pass over every pixel per round.
fn filled_below_the_cap(mut pixels: Vec<(f64, f64)>, budget: f64, most: f64) -> f64 {
    pixels.sort_unstable_by(|x, y| y.0.total_cmp(&x.0));
    // Σ_{i≥j} aᵢcᵢ summed from the end, so that no running difference drifts.
    let mut below: Vec<f64> = (pixels.iter().rev())
        .scan(0.0, |sum, &(a, c)| {
            *sum += a * c;
            Some(*sum)
        })
        .collect();
    below.reverse();
    let mut capped_cost = 0.0;
    for (&(a, c), &rest) in pixels.iter().zip(&below) {
        let k = (budget - capped_cost) / rest;
        if rest <= 0.0 || k * a < most {
            return k;
        }
        capped_cost += most * c;
    }
    // Unreachable with most > spp (every pixel capped would cost more than the budget).
    f64::NAN
}

/// One path's cost through a pixel whose primal paths made `lookups` density lookups each on
/// average, in lookups: one each, and two for the gradient path's own work (its camera ray, the
/// walk through empty cells, its splats). With one instead of two, an optimisation step on the
/// worked example took 0.85× the uniform pass's time; with four, 1.07×.
pub fn path_cost(lookups: f32) -> f32 {
    2.0 + lookups
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rounding keeps each pixel's expected count: the mean of n over many pixels with the
    /// same δ is the expected count, whatever its fraction.
    #[test]
    fn a_pixels_paths_average_its_expected_count() {
        for expected in [0.03, 0.5, 1.25, 7.9] {
            let samples = PixelSamples::Adjoint {
                per_adjoint: expected,
            };
            let delta = Vec3::new(0.25, -0.5, 0.25);
            let pixels = 40_000;
            let total: u64 = (0..pixels)
                .map(|p| {
                    let (n, divisor) = samples.draw(8, delta, 7, p);
                    assert_eq!(divisor, expected);
                    assert!(n == divisor.floor() as u32 || n == divisor.ceil() as u32);
                    n as u64
                })
                .sum();
            let mean = total as f64 / pixels as f64;
            // The standard error of the mean of a Bernoulli(fraction) is at most 0.0025 here.
            assert!((mean - expected).abs() < 0.01, "{expected}: {mean}");
        }
    }

    #[test]
    fn samples_follow_the_adjoint_at_the_cost_of_uniform_ones() {
        let pixels = [(0.0, 1.0), (1.0, 3.0), (3.0, 10.0), (0.5, 2.0)];
        let spp = 8;
        let samples = PixelSamples::following_adjoint(&pixels, spp);
        let uniform_cost: f64 = pixels.iter().map(|&(_, c)| c as f64 * spp as f64).sum();
        let expected = |a: f32| samples.draw(spp, Vec3::new(a, 0.0, 0.0), 1, 0);
        let cost: f64 = (pixels.iter())
            .filter(|&&(a, _)| a > 0.0)
            .map(|&(a, c)| expected(a).1 * c as f64)
            .sum();
        assert!(
            (cost - uniform_cost).abs() < 1e-9 * uniform_cost,
            "{cost} vs {uniform_cost}"
        );
        // A pixel whose adjoint is 0 takes no path; three times the adjoint, three times the
        // paths (below the cap).
        assert_eq!(expected(0.0).0, 0);
        assert!((expected(3.0).1 / expected(1.0).1 - 3.0).abs() < 1e-12);
    }

    #[test]
    fn an_outlier_pixel_takes_at_most_eight_times_the_spp() {
        let samples = PixelSamples::Adjoint { per_adjoint: 1e9 };
        assert_eq!(samples.draw(8, Vec3::ONE, 1, 0), (64, 64.0));
    }

    /// One pixel of |δ| 10⁴ beside a thousand of 0.01, a firefly in a target: it takes its 8·spp
    /// paths and the others share the rest of the uniform pass's cost, 7.9 paths each at spp 8.
    /// Without the cap in the sum k was set as if the outlier took 7,920 paths: the pass cost
    /// 72 paths in all, not 8,008, the others 0.008 each.
    #[test]
    fn an_outlier_pixel_leaves_the_others_the_uniform_pass_cost() {
        let mut pixels = vec![(0.01f32, 1.0f32); 1000];
        pixels.push((1e4, 1.0));
        let samples = PixelSamples::following_adjoint(&pixels, 8);
        let expected = |a: f32| samples.draw(8, Vec3::new(a, 0.0, 0.0), 1, 0).1;
        let cost: f64 = pixels.iter().map(|&(a, _)| expected(a)).sum();
        assert!((cost - 8.0 * 1001.0).abs() < 1e-6 * cost, "{cost}");
        assert_eq!(expected(1e4), 64.0);
        assert!((expected(0.01) - 7.944).abs() < 1e-3, "{}", expected(0.01));
        // Capping one pixel raises k and caps the next: 50 at the first round, 30 at the
        // second, and the twenty of 1 take k = 0.3 each; the cost still comes out whole.
        let mut pixels = vec![(1.0f32, 1.0f32); 20];
        pixels.extend([(50.0, 1.0), (30.0, 1.0)]);
        let samples = PixelSamples::following_adjoint(&pixels, 1);
        assert_eq!(samples, PixelSamples::Adjoint { per_adjoint: 0.3 });
    }

    /// A heavy tail (aᵢ = 1/i², 200,000 pixels of costs 1 to 3): hundreds of pixels at the cap,
    /// each capping raising k towards the next, and the cost still the uniform pass's.
    #[test]
    fn a_heavy_tail_of_adjoints_costs_the_uniform_pass() {
        let pixels: Vec<(f32, f32)> = (1..=200_000)
            .map(|i| (1.0 / (i as f32).powi(2), 1.0 + (i % 3) as f32))
            .collect();
        let samples = PixelSamples::following_adjoint(&pixels, 8);
        let draw = |a: f32| samples.draw(8, Vec3::new(a, 0.0, 0.0), 1, 0).1;
        let capped = pixels.iter().filter(|&&(a, _)| draw(a) == 64.0).count();
        let cost: f64 = pixels.iter().map(|&(a, c)| draw(a) * c as f64).sum();
        let uniform: f64 = pixels.iter().map(|&(_, c)| 8.0 * c as f64).sum();
        assert!(capped > 100, "{capped} pixels at the cap");
        assert!(
            (cost - uniform).abs() < 1e-9 * uniform,
            "{cost} vs {uniform}"
        );
    }

    #[test]
    fn a_huge_spp_keeps_the_count_below_the_rounding_stream() {
        let samples = PixelSamples::Adjoint { per_adjoint: 1e30 };
        let (n, divisor) = samples.draw(u32::MAX / 2, Vec3::ONE, 1, 0);
        assert!(n < ROUNDING_STREAM && divisor.is_finite(), "{n} {divisor}");
    }

    #[test]
    fn without_an_adjoint_the_samples_stay_uniform() {
        assert_eq!(
            PixelSamples::following_adjoint(&[(0.0, 1.0), (0.0, 5.0)], 8),
            PixelSamples::Uniform
        );
        assert_eq!(
            PixelSamples::following_adjoint(&[], 8),
            PixelSamples::Uniform
        );
    }

    #[test]
    fn a_non_finite_adjoint_leaves_the_other_pixels_their_paths() {
        let with = |bad| PixelSamples::following_adjoint(&[(1.0, 3.0), (bad, 3.0), (2.0, 1.0)], 8);
        let without = PixelSamples::following_adjoint(&[(1.0, 3.0), (2.0, 1.0)], 8);
        for bad in [f32::INFINITY, f32::NAN] {
            assert_eq!(with(bad), without, "{bad}");
        }
        // The bad pixel itself takes the cap: its samples are dropped and counted by the pass.
        assert_eq!(without.draw(8, Vec3::splat(f32::NAN), 1, 0), (64, 64.0));
    }
}
