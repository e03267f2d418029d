//! Sampling building blocks: the Henyey–Greenstein phase function, uniform sphere directions,
//! piecewise-constant distributions, and per-pixel random number streams.

use std::f32::consts::PI;

use glam::Vec3;
use rand::rngs::SmallRng;
use rand::SeedableRng;

/// Seeds the renders of target images apart from the passes that are compared with them, so
/// that their noise does not correlate (`grad --target-scene`, an optimisation's targets).
pub const TARGET_SEED_SALT: u64 = 0x7a26_e7b1_d0c5_1a11;

/// A random stream that depends only on (seed, pixel, stream), never on the thread that runs it:
/// the same seed gives the same image for any thread count.
pub fn pixel_rng(seed: u64, pixel: u64, stream: u64) -> SmallRng {
    // Mixed so that nearby pixels get unrelated streams.
    SmallRng::seed_from_u64(mix64(
        seed ^ pixel.wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ stream.wrapping_mul(0xD1B5_4A32_D192_ED03),
    ))
}

/// SplitMix64's finaliser: every bit of `z` moves about half the bits of the result.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Which pass draws the numbers: the forward render and the adjoint pass use unrelated streams.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pass {
    Forward = 0,
    Adjoint = 1,
}

/// The stream of one sample (path) of one pixel. A stream per sample, not per pixel, keeps finite
/// differences' common random numbers common: a decision flipped in one path cannot shift the
/// numbers every later path of the pixel draws.
#[inline]
pub fn sample_rng(seed: u64, pixel: u64, sample: u32, pass: Pass) -> SmallRng {
    pixel_rng(seed, pixel, ((sample as u64) << 1) | pass as u64)
}

/// An orthonormal basis around unit `n` (Duff et al. 2017).
#[inline]
pub fn basis(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1.0f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (
        Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        Vec3::new(b, sign + n.y * n.y * a, -n.y),
    )
}

/// Henyey–Greenstein phase function. `cos_theta` is the cosine between the incoming ray direction
/// and the scattered ray direction (both as the path travels), so g > 0 keeps paths going forward.
#[derive(Debug, Clone, Copy)]
pub struct HenyeyGreenstein {
    pub g: f32,
}

impl HenyeyGreenstein {
    /// p(cos θ) = (1 − g²) / (4π (1 + g² − 2g cos θ)^{3/2}).
    ///
    /// In f32, 1 + g² − 2g·cosθ cancels to exactly 0 at the peak once |g| ≳ 0.9995 (an infinite
    /// density, then NaN). With a = |g| and the cosine mirrored for g < 0 (HG(g, c) = HG(|g|, ±c)),
    /// the denominator is (1 − a)² + 2a(1 − c): 1 − a is exact for a ≥ ½ (Sterbenz), the form stays
    /// positive for every |g| < 1, and the value fits an f32 (≈ 1.6e9 at |g| = 0.99999).
    #[inline]
    pub fn eval(&self, cos_theta: f32) -> f32 {
        let a = self.g.abs();
        let c = if self.g >= 0.0 { cos_theta } else { -cos_theta };
        let one_minus_c = (1.0 - c).clamp(0.0, 2.0);
        let denom = (1.0 - a) * (1.0 - a) + 2.0 * a * one_minus_c;
        (1.0 - a) * (1.0 + a) / (4.0 * PI * denom * denom.sqrt())
    }

    /// A direction scattered from `dir`, with pdf `eval(dir · result)` (exact sampling). For
    /// a = |g| the inversion gives q = 1 − c directly, q = (1 − a)(1 − u)(s + 1 − a) / (1 − a + 2au)
    /// with s = (1 − a²) / (1 − a + 2au) — what the textbook form (1 + a² − s²)/2a loses to
    /// cancellation near a = 1 — and c is mirrored back for g < 0.
    #[inline(always)]
    pub fn sample(&self, dir: Vec3, u: [f32; 2]) -> Vec3 {
        let a = self.g.abs();
        let q = if a < 1e-3 {
            2.0 * u[0]
        } else {
            let d = 1.0 - a + 2.0 * a * u[0];
            let s = (1.0 - a) * (1.0 + a) / d;
            ((1.0 - a) * (1.0 - u[0]) * (s + 1.0 - a) / d).clamp(0.0, 2.0)
        };
        let cos_theta = if self.g >= 0.0 { 1.0 - q } else { q - 1.0 };
        let sin_theta = (q * (2.0 - q)).max(0.0).sqrt();
        let phi = 2.0 * PI * u[1];
        let (t, b) = basis(dir);
        (t * (sin_theta * phi.cos()) + b * (sin_theta * phi.sin()) + dir * cos_theta).normalize()
    }
}

#[inline]
pub fn uniform_sphere(u: [f32; 2]) -> Vec3 {
    let z = 1.0 - 2.0 * u[0];
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u[1];
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

pub const UNIFORM_SPHERE_PDF: f32 = 1.0 / (4.0 * PI);

/// Power heuristic (β = 2) weight of strategy `a` against `b`. In f64: a peaked phase function's
/// density squared overflows f32 (and ∞/∞ is NaN).
#[inline]
pub fn power_heuristic(pdf_a: f32, pdf_b: f32) -> f32 {
    let (a, b) = (pdf_a as f64, pdf_b as f64);
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 && a2.is_finite() && b2.is_finite() {
        (a2 / (a2 + b2)) as f32
    } else {
        0.0
    }
}

/// A piecewise-constant distribution over `n` equal bins of [0, 1).
#[derive(Debug, Clone)]
pub struct Distribution1D {
    cdf: Vec<f32>,
    pub total: f32,
}

impl Distribution1D {
    pub fn new(weights: &[f32]) -> Self {
        let mut cdf = Vec::with_capacity(weights.len() + 1);
        let mut sum = 0.0f64;
        cdf.push(0.0);
        for &w in weights {
            sum += w.max(0.0) as f64;
            cdf.push(sum as f32);
        }
        let total = sum as f32;
        if total > 0.0 {
            for c in &mut cdf {
                *c /= total;
            }
        } else {
            for (i, c) in cdf.iter_mut().enumerate() {
                *c = i as f32 / weights.len() as f32;
            }
        }
        Distribution1D { cdf, total }
    }

    /// The number of bins.
    pub fn bins(&self) -> usize {
        self.cdf.len() - 1
    }

    /// The probability of bin `i`.
    #[inline]
    pub fn bin_probability(&self, i: usize) -> f32 {
        self.cdf[i + 1] - self.cdf[i]
    }

    /// A bin with probability ∝ weight, and `u` rescaled to [0, 1) inside it.
    #[inline]
    pub fn sample(&self, u: f32) -> (usize, f32) {
        let i = self.cdf.partition_point(|&c| c <= u).clamp(1, self.bins()) - 1;
        let p = self.bin_probability(i);
        let du = if p > 0.0 {
            ((u - self.cdf[i]) / p).clamp(0.0, 0.99999994)
        } else {
            0.5
        };
        (i, du)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    #[test]
    fn hg_integrates_to_one_and_sampling_matches_its_mean_cosine() {
        for g in [-0.7, 0.0, 0.5, 0.95] {
            let hg = HenyeyGreenstein { g };
            // ∫ p dω = 2π ∫ p(μ) dμ.
            let n = 200_000;
            let integral: f64 = (0..n)
                .map(|i| hg.eval(-1.0 + 2.0 * (i as f32 + 0.5) / n as f32) as f64)
                .sum::<f64>()
                * 2.0
                / n as f64
                * 2.0
                * std::f64::consts::PI;
            assert!((integral - 1.0).abs() < 2e-3, "g={g}: ∫p = {integral}");
            // The mean cosine of HG is g.
            let mut rng = pixel_rng(7, 0, 0);
            let dir = Vec3::new(0.3, -0.8, 0.52).normalize();
            let m = 100_000;
            let mean: f32 = (0..m)
                .map(|_| hg.sample(dir, [rng.gen(), rng.gen()]).dot(dir))
                .sum::<f32>()
                / m as f32;
            assert!((mean - g).abs() < 0.01, "g={g}: mean cosine {mean}");
        }
    }

    /// |g| → 1: the density stays finite and exact at its peak (1 + g)/(4π(1 − g)²), sampling keeps
    /// its mean cosine, and MIS weights with such densities are numbers.
    #[test]
    fn hg_is_finite_and_exact_as_g_approaches_one() {
        let mut rng = pixel_rng(3, 0, 0);
        let dir = Vec3::new(0.3, -0.8, 0.52).normalize();
        for g in [0.9f32, 0.99, 0.999, 0.9995, 0.9999, 0.99999] {
            for g in [g, -g] {
                let hg = HenyeyGreenstein { g };
                let (gd, pi) = (g as f64, std::f64::consts::PI);
                let peak = (1.0 + gd.abs()) / (4.0 * pi * (1.0 - gd.abs()).powi(2));
                let at_peak = hg.eval(g.signum()) as f64;
                assert!(
                    (at_peak / peak - 1.0).abs() < 1e-4,
                    "g={g}: {at_peak} vs {peak}"
                );
                for cos in [-1.0f32, -0.3, 0.0, 0.7, 1.0, 1.0 + 1e-7] {
                    let p = hg.eval(cos);
                    assert!(p.is_finite() && p > 0.0, "g={g}, cos={cos}: {p}");
                }
                let m = 20_000;
                let mean = (0..m)
                    .map(|_| {
                        let w = hg.sample(dir, [rng.gen(), rng.gen()]);
                        assert!(w.is_finite() && (w.length() - 1.0).abs() < 1e-4);
                        w.dot(dir) as f64
                    })
                    .sum::<f64>()
                    / m as f64;
                assert!((mean - gd).abs() < 0.01, "g={g}: mean cosine {mean}");
                let w = power_heuristic(hg.eval(1.0), 0.1);
                assert!(w.is_finite() && (0.0..=1.0).contains(&w), "g={g}: {w}");
            }
        }
        assert_eq!(power_heuristic(f32::MAX, f32::MAX), 0.5);
        assert_eq!(power_heuristic(f32::INFINITY, 1.0), 0.0);
    }

    #[test]
    fn distribution_samples_bins_in_proportion() {
        let d = Distribution1D::new(&[1.0, 0.0, 3.0]);
        assert_eq!(d.sample(0.1).0, 0);
        assert_eq!(d.sample(0.3).0, 2);
        assert!((d.bin_probability(2) - 0.75).abs() < 1e-6);
        assert_eq!(d.bin_probability(1), 0.0);
    }
}
