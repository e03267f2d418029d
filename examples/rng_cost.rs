//! What a random number costs (docs/speed.md, the random numbers' row): a uniform draw from a
//! path's stream (`SmallRng`, Xoshiro256++), an exponential one as the trackers draw their
//! budgets, and the seeding of a sample's stream (`sampling::sample_rng`) with its first draw.
//!
//!     cargo run --release --example rng_cost
use std::hint::black_box;
use std::time::Instant;

use rand::Rng;
use volgrad::render::sampling::{sample_rng, Pass};

const DRAWS: u64 = 100_000_000;

/// Nanoseconds per call of `f`, called `n` times.
fn time(n: u64, mut f: impl FnMut(u64)) -> f64 {
    let start = Instant::now();
    for i in 0..n {
        f(i);
    }
    start.elapsed().as_secs_f64() * 1e9 / n as f64
}

fn main() {
    for round in 1..=3 {
        let mut rng = sample_rng(round, 0, 0, Pass::Forward);
        let uniform = time(DRAWS, |_| {
            black_box(rng.gen::<f32>());
        });
        let exponential = time(DRAWS, |_| {
            black_box(-(1.0 - rng.gen::<f32>()).ln());
        });
        let seeding = time(DRAWS / 10, |i| {
            black_box(sample_rng(round, i, 3, Pass::Forward).gen::<f32>());
        });
        println!(
            "round {round}: uniform {uniform:.2} ns, exponential {exponential:.2} ns, \
             a sample's stream seeded and drawn once {seeding:.2} ns"
        );
    }
}
