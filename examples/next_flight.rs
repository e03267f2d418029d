//! Next-flight ratio tracking against ratio tracking on a scene's shadow rays (docs/speed.md, "What
//! was tried"): rays toward the first sun from random points inside the density, each tracked
//! `RUNS` times by both estimators; their mean transmittance, their variance about each ray's mean,
//! and their time.
//!
//!     cargo run --release --example next_flight -- scenes/cloud.toml
//!
//! Ratio tracking estimates T(t0 → t1) by T̂ = W_K = Π_{j≤K} (1 − σt(t_j)/σ̄) over the K tentative
//! collisions of the walk. The next-flight estimator (Novák, Selle and Jarosz 2014, "Residual ratio tracking") sums, at the walk's
//! start and at every tentative collision, the weight so far times the probability that the next
//! flight leaves the interval: T̂_NF = Σ_{i=0..K} W_i · e^{−τ̄(t_i, t1)}, τ̄ the majorant's optical
//! depth. Each term is W_i · P(K = i | the walk up to t_i), so E[T̂_NF] = E[W_K] = T. The sum is
//! kept as S_i = S_{i−1} · e^{−b_i} + W_i, where b_i is the Exp(1) budget the walk spent reaching
//! t_i (so e^{−b_i} is 1 − u, the uniform it was drawn from: no exponential per collision), and
//! T̂_NF = S_K · e^{−τ̄(t_K, t1)}, one exponential a ray. Once Russian roulette ends the weights the
//! walk goes on without reads until its next tentative collision: S times that flight's escape
//! (0 or 1) is unbiased for S · e^{−τ̄(t_i, t1)}.
//!
//! Both walk as `volume::tracking` does (`common/tentative.rs`).

#[path = "common/sun_rays.rs"]
mod sun_rays;
#[path = "common/tentative.rs"]
mod tentative;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use rand::rngs::SmallRng;
use rand::SeedableRng;
use sun_rays::sun_rays;
use tentative::{exponential, roulette, walk};
use volgrad::render::scene::Scene;
use volgrad::volume::medium::Medium;
use volgrad::volume::ray::IndexRay;

const RAYS: usize = 50_000;
const RUNS: usize = 16;

fn ratio_tracking(medium: &Medium, ray: &IndexRay, rng: &mut SmallRng) -> f32 {
    let mut w = 1.0f32;
    let escaped = walk(medium, ray, rng, exponential, |t, sigma_max, _, rng| {
        w *= (1.0 - medium.sigma_t(ray.at(t)) / sigma_max).max(0.0);
        roulette(&mut w, rng)
    });
    if escaped.is_some() {
        w
    } else {
        0.0
    }
}

fn next_flight(medium: &Medium, ray: &IndexRay, rng: &mut SmallRng) -> f32 {
    let (mut w, mut sum, mut weighted) = (1.0f32, 1.0f32, true);
    let spent = walk(medium, ray, rng, exponential, |t, sigma_max, u, rng| {
        if !weighted {
            // The flight after the weights ended did not leave: its escape is 0.
            sum = 0.0;
            return false;
        }
        w *= (1.0 - medium.sigma_t(ray.at(t)) / sigma_max).max(0.0);
        weighted = roulette(&mut w, rng);
        sum = sum * (1.0 - u) + w;
        true
    });
    match spent {
        Some(depth) if weighted => sum * (-depth).exp(),
        Some(_) => sum,
        None => 0.0,
    }
}

fn main() -> Result<()> {
    let path: PathBuf = std::env::args()
        .nth(1)
        .context("usage: next_flight SCENE.toml")?
        .into();
    let scene = Scene::load(&path)?;
    let medium = &scene.medium;
    let rays = sun_rays(&scene, &path, RAYS)?;
    type Estimator = fn(&Medium, &IndexRay, &mut SmallRng) -> f32;
    let ways: [(&str, Estimator); 2] = [
        ("ratio tracking", ratio_tracking),
        ("next-flight", next_flight),
    ];
    for round in 1..=3 {
        for (name, estimate) in ways {
            let start = Instant::now();
            let (mut mean, mut within) = (0.0f64, 0.0f64);
            for (i, ray) in rays.iter().enumerate() {
                let mut r = SmallRng::seed_from_u64((round * RAYS + i) as u64);
                let (mut s, mut s2) = (0.0f64, 0.0f64);
                for _ in 0..RUNS {
                    let t = f64::from(estimate(medium, ray, &mut r));
                    s += t;
                    s2 += t * t;
                }
                let m = s / RUNS as f64;
                mean += m;
                within += (s2 - RUNS as f64 * m * m) / (RUNS - 1) as f64;
            }
            let n = rays.len() as f64;
            let ns = start.elapsed().as_secs_f64() * 1e9 / (n * RUNS as f64);
            println!(
                "round {round}, {name}: mean T {:.5}, variance about each ray's mean {:.3e}, {ns:.0} ns a ray, variance × time {:.3e}",
                mean / n,
                within / n,
                within / n * ns
            );
        }
    }
    Ok(())
}
