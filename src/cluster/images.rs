//! Images rendered by every rank together: each traces its share of the pixels
//! (`PixelSet::share`), and the shares are summed. A pixel is non-zero on one rank only and
//! x + 0 = x, so the sum is exact: every rank gets the image one process renders, bit for bit.

use std::time::Duration;

use glam::Vec3;

use crate::cluster::Cluster;
use crate::io::images::RgbImage;
use crate::render::alpha::render_alpha_pixels;
use crate::render::image::{render, render_pixels, PixelsRendered, RenderOptions, RenderStats};
use crate::render::pixel_set::PixelSet;
use crate::render::scene::Scene;

/// The scene's camera view, rendered by all ranks.
pub fn render_shared(
    cluster: &Cluster,
    scene: &Scene,
    options: &RenderOptions,
) -> (RgbImage, RenderStats) {
    if cluster.size() == 1 {
        return render(scene, options);
    }
    let pixels = scene.camera.width * scene.camera.height;
    let set = PixelSet::share(pixels, cluster.rank(), cluster.size());
    let rendered = render_pixels(scene, options, &set);
    let (mut image, mut stats) = (rendered.image, rendered.stats);
    sum_image(cluster, &mut image);
    sum_stats(cluster, &mut stats);
    (image, stats)
}

/// The scene's camera view's alpha (`render::alpha`), rendered by all ranks.
pub fn render_alpha_shared(cluster: &Cluster, scene: &Scene, options: &RenderOptions) -> RgbImage {
    let pixels = scene.camera.width * scene.camera.height;
    let set = PixelSet::share(pixels, cluster.rank(), cluster.size());
    let mut image = render_alpha_pixels(scene, options, &set).image;
    sum_image(cluster, &mut image);
    image
}

/// This rank's `stats` made the job's, on every rank: paths, dropped samples and tracking
/// counters summed over the ranks (so lookups per path are every rank's lookups over every
/// rank's paths, not rank 0's over all), and the wall time the slowest rank's (the job ends
/// with it). Integers, so the sums are exact: the counts of one process.
pub fn sum_stats(cluster: &Cluster, stats: &mut RenderStats) {
    if cluster.size() == 1 {
        return;
    }
    let t = &mut stats.tracking;
    let mut counts = [
        stats.paths,
        stats.non_finite,
        t.lookups,
        t.collisions,
        t.shadow_lookups,
        t.shadow_rays,
    ];
    cluster.sum_in_place(&mut counts);
    [
        stats.paths,
        stats.non_finite,
        t.lookups,
        t.collisions,
        t.shadow_lookups,
        t.shadow_rays,
    ] = counts;
    let [wall] = cluster.max_each([stats.wall.as_secs_f64()]);
    stats.wall = Duration::from_secs_f64(wall);
}

/// `image` summed over the ranks, in place (exact where each pixel is non-zero on one rank).
pub fn sum_image(cluster: &Cluster, image: &mut RgbImage) {
    let all: Vec<u32> = (0..image.pixels.len() as u32).collect();
    sum_pixels(cluster, image, &all);
}

/// The pixels `pixels` (indices) of `image` summed over the ranks, in place; the others are left
/// as they are: a pixel batch moves its pixels, not the image.
pub fn sum_pixels(cluster: &Cluster, image: &mut RgbImage, pixels: &[u32]) {
    if cluster.size() == 1 {
        return;
    }
    let values = pixels.iter().map(|&p| image.pixels[p as usize].to_array());
    for (&p, v) in pixels.iter().zip(summed(cluster, values.collect())) {
        image.pixels[p as usize] = Vec3::from_array(v);
    }
}

/// The pixels `pixels` of a render summed over the ranks, in place: their values and their
/// lookups per path (each non-zero on one rank, so exact as `sum_pixels`).
pub fn sum_rendered_pixels(cluster: &Cluster, rendered: &mut PixelsRendered, pixels: &[u32]) {
    if cluster.size() == 1 {
        return;
    }
    let (image, lookups) = (&mut rendered.image.pixels, &mut rendered.lookups);
    let values = pixels
        .iter()
        .map(|&p| image[p as usize].extend(lookups[p as usize]).to_array());
    for (&p, [r, g, b, l]) in pixels.iter().zip(summed(cluster, values.collect())) {
        image[p as usize] = Vec3::new(r, g, b);
        lookups[p as usize] = l;
    }
}

/// Each pixel's N values summed over the ranks, in one message.
fn summed<const N: usize>(cluster: &Cluster, values: Vec<[f32; N]>) -> Vec<[f32; N]> {
    let mut flat: Vec<f32> = values.into_iter().flatten().collect();
    cluster.sum_in_place(&mut flat);
    let sums = flat.chunks_exact(N);
    sums.map(|v| v.try_into().expect("N values a pixel"))
        .collect()
}
