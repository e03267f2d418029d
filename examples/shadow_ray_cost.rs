//! Where a shadow ray's time goes (docs/speed.md, "Where a path's time goes"): rays toward a
//! scene's first sun from random points inside the density, tracked by ratio tracking over the
//! majorant cells three ways with the same seeds — as they are, with each density read's value
//! taken from a list the first way recorded (the same control flow without reads), and with the
//! exponential budgets from a list too (without logarithms) — and the same rays' majorant
//! segments walked alone.
//!
//!     cargo run --release --example shadow_ray_cost -- scenes/cloud.toml
//!
//! The tracking walks as `volume::tracking` does (`common/tentative.rs`), with two hooks: where
//! a read's value and a budget come from.

#[path = "common/sun_rays.rs"]
mod sun_rays;
#[path = "common/tentative.rs"]
mod tentative;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use glam::Vec3;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use sun_rays::sun_rays;
use tentative::{exponential, roulette, walk};
use volgrad::render::scene::Scene;
use volgrad::volume::medium::Medium;
use volgrad::volume::ray::IndexRay;

const RAYS: usize = 400_000;

/// Ratio tracking from the ray's origin to where it leaves the medium, reading σt through `read`
/// and drawing each Exp(1) budget through `budget`.
#[inline(always)]
fn track(
    medium: &Medium,
    ray: &IndexRay,
    rng: &mut SmallRng,
    mut read: impl FnMut(Vec3) -> f32,
    mut budget: impl FnMut(&mut SmallRng) -> f32,
) -> f32 {
    let mut tr = 1.0f32;
    let escaped = walk(
        medium,
        ray,
        rng,
        |r| (budget(r), 0.0),
        |t, sigma_max, _, rng| {
            tr *= (1.0 - read(ray.at(t)) / sigma_max).max(0.0);
            roulette(&mut tr, rng)
        },
    );
    if escaped.is_some() {
        tr
    } else {
        0.0
    }
}

fn main() -> Result<()> {
    let path: PathBuf = std::env::args()
        .nth(1)
        .context("usage: shadow_ray_cost SCENE.toml")?
        .into();
    let scene = Scene::load(&path)?;
    let medium = &scene.medium;
    let rays = sun_rays(&scene, &path, RAYS)?;
    let (mut values, mut budgets) = (Vec::new(), Vec::new());
    for (i, ray) in rays.iter().enumerate() {
        let mut r = SmallRng::seed_from_u64(i as u64);
        let read = |p| {
            let v = medium.sigma_t(p);
            values.push(v);
            v
        };
        let draw = |r: &mut SmallRng| {
            let e = exponential(r).0;
            budgets.push(e);
            e
        };
        track(medium, ray, &mut r, read, draw);
    }
    let n = rays.len() as f64;
    println!(
        "{RAYS} rays: {:.2} reads and {:.2} budgets a ray",
        values.len() as f64 / n,
        budgets.len() as f64 / n
    );
    for round in 1..=3 {
        let time = |way: u32| {
            let start = Instant::now();
            let (mut vi, mut bi, mut sum) = (0usize, 0usize, 0.0f64);
            for (i, ray) in rays.iter().enumerate() {
                let mut r = SmallRng::seed_from_u64(i as u64);
                let listed = |_| {
                    vi += 1;
                    values[vi - 1]
                };
                sum += f64::from(match way {
                    0 => track(
                        medium,
                        ray,
                        &mut r,
                        |p| medium.sigma_t(p),
                        |r| exponential(r).0,
                    ),
                    1 => track(medium, ray, &mut r, listed, |r| exponential(r).0),
                    _ => {
                        let listed_budget = |r: &mut SmallRng| {
                            let _: f32 = r.gen(); // the draw stays, its logarithm goes
                            bi += 1;
                            budgets[bi - 1]
                        };
                        track(medium, ray, &mut r, listed, listed_budget)
                    }
                });
            }
            (start.elapsed().as_secs_f64() * 1e9 / n, sum)
        };
        let (as_is, a) = time(0);
        let (no_reads, b) = time(1);
        let (no_logs, c) = time(2);
        assert!(a == b && b == c, "the three ways must make the same walks");
        let start = Instant::now();
        let (mut segments, mut occupied, mut runs) = (0u64, 0u64, 0u64);
        for ray in &rays {
            let Some((t0, t1)) = medium.intersect(ray) else {
                continue;
            };
            let mut in_empty_run = false;
            for seg in medium.majorant.walk(ray.o, ray.d, t0, t1) {
                let empty = seg.sigma_max <= 0.0;
                runs += u64::from(empty && !in_empty_run);
                in_empty_run = empty;
                segments += 1;
                occupied += u64::from(!empty);
            }
        }
        let walk = start.elapsed().as_secs_f64() * 1e9;
        println!(
            "round {round}: a ray {as_is:.0} ns; reads from the list {no_reads:.0} ns; budgets too \
             {no_logs:.0} ns; its walk alone {:.0} ns: {:.1} segments ({:.1} occupied, {:.2} empty \
             runs) at {:.1} ns",
            walk / n,
            segments as f64 / n,
            occupied as f64 / n,
            runs as f64 / n,
            walk / segments.max(1) as f64
        );
    }
    Ok(())
}
