//! Alpha: how much of the background a pixel's camera ray does not see through the medium,
//! α = 1 − T(camera → out of the medium), what a renderer with a transparent film writes beside
//! the colour (Cycles, Mitsuba's alpha channel). It depends on the extinction alone — no lights,
//! no albedo — so it measures the optical depth along every ray directly.
//!
//! One sample is 1 − T̂, T̂ a ratio-tracking estimate of the ray's transmittance through the
//! medium's box: unbiased, and a fraction of a path's cost (one walk, no scattering). An alpha
//! image is grey: its three channels hold the same α, so that losses, sums over ranks and
//! pictures treat it as they treat colour.

use glam::Vec3;
use rand::Rng;

use crate::render::image::{render_pixels_of, PixelsRendered, RenderOptions};
use crate::render::pixel_set::PixelSet;
use crate::render::scene::Scene;
use crate::volume::tracking::{transmittance, TrackingStats};

/// Seeds alpha's random streams apart from the colour's (a view's colour and alpha renders share
/// its seed): an alpha render and a colour render of one seed are independent.
pub const ALPHA_SEED_SALT: u64 = 0x3c6e_f372_fe94_f82b;

/// One sample of α along the ray `origin + t·dir` (unit `dir`): 1 − T̂.
#[inline]
pub fn alpha_sample(
    scene: &Scene,
    origin: Vec3,
    dir: Vec3,
    rng: &mut impl Rng,
    stats: &mut TrackingStats,
) -> f32 {
    let medium = &scene.medium;
    let ray = medium.to_index_ray(origin, dir);
    match medium.intersect(&ray) {
        Some((t0, t1)) => 1.0 - transmittance(medium, &ray, t0, t1, rng, stats),
        None => 0.0,
    }
}

/// The alpha image of the pixels of `set` (0 elsewhere), `options.spp` jittered rays each, from
/// the streams of seed `options.seed ^ ALPHA_SEED_SALT`.
pub fn render_alpha_pixels(
    scene: &Scene,
    options: &RenderOptions,
    set: &PixelSet,
) -> PixelsRendered {
    let options = RenderOptions {
        seed: options.seed ^ ALPHA_SEED_SALT,
        ..*options
    };
    render_pixels_of(scene, &options, set, |scene, origin, dir, rng, stats| {
        Vec3::splat(alpha_sample(scene, origin, dir, rng, stats))
    })
}
