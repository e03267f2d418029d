//! The image loop: every pixel's paths in parallel tiles, each path with its own random stream.

use std::time::{Duration, Instant};

use glam::Vec3;
use rand::rngs::SmallRng;
use rand::Rng;
use rayon::prelude::*;

use crate::io::images::RgbImage;
use crate::render::interrupt;
use crate::render::path::trace_path;
use crate::render::pixel_set::PixelSet;
use crate::render::sampling::{sample_rng, Pass};
use crate::render::scene::Scene;
use crate::volume::tracking::TrackingStats;

const TILE: u32 = 16;
/// Pixels of a `render_pixels` set traced as one task at most, and tasks a set is cut into at
/// least (while a task keeps a pixel): an optimisation step renders a view's share of its pixel
/// batch (about 1,400 pixels), and a set of a few tasks leaves one thread waiting for the last.
const CHUNK_PIXELS: u64 = 256;
const MIN_CHUNKS: u64 = 64;

#[derive(Debug, Clone, Copy)]
pub struct RenderOptions {
    pub spp: u32,
    pub seed: u64,
    pub max_depth: u32,
    /// Show a progress bar on stderr.
    pub progress: bool,
}

#[derive(Debug, Default, Clone, Copy)]
pub struct RenderStats {
    pub paths: u64,
    pub wall: Duration,
    pub tracking: TrackingStats,
    /// Path samples (or gradient samples) that came out infinite or NaN and were dropped, i.e.
    /// counted as 0. A valid scene should give none; a count above 0 is reported on stderr.
    pub non_finite: u64,
}

impl RenderStats {
    /// Adds `other`'s passes to these: paths, time, counters.
    pub fn merge(&mut self, other: &RenderStats) {
        self.paths += other.paths;
        self.wall += other.wall;
        self.tracking += other.tracking;
        self.non_finite += other.non_finite;
    }

    pub fn paths_per_second(&self) -> f64 {
        self.paths as f64 / self.wall.as_secs_f64().max(1e-9)
    }
    pub fn lookups_per_path(&self) -> f64 {
        (self.tracking.lookups + self.tracking.shadow_lookups) as f64 / self.paths.max(1) as f64
    }
    /// Real collisions per density lookup made by free-flight sampling (1 is ideal).
    pub fn tracking_efficiency(&self) -> f64 {
        self.tracking.collisions as f64 / self.tracking.lookups.max(1) as f64
    }
}

/// What one tile of the image loop produced.
struct Tile {
    origin: (u32, u32),
    pixels: Vec<Vec3>,
    stats: TrackingStats,
    non_finite: u64,
}

/// What one chunk of a `render_pixels` set produced: (pixel index, value, lookups per path).
struct Traced {
    pixels: Vec<(u32, Vec3, f32)>,
    stats: TrackingStats,
    non_finite: u64,
}

/// A render of a set of pixels: their values, the density lookups their paths made (per path:
/// what a path through the pixel costs, which decides where an optimisation's gradient paths
/// go, `gradient::pixel_samples`) and the counters. Pixels outside the set hold 0.
pub struct PixelsRendered {
    pub image: RgbImage,
    pub lookups: Vec<f32>,
    pub stats: RenderStats,
}

/// Renders the scene's camera view. Each path has its own random stream (seed, pixel, sample), so
/// the image does not depend on the number of threads.
pub fn render(scene: &Scene, options: &RenderOptions) -> (RgbImage, RenderStats) {
    let start = Instant::now();
    let camera = &scene.camera;
    let (w, h) = (camera.width, camera.height);
    let tiles: Vec<(u32, u32)> = (0..h.div_ceil(TILE))
        .flat_map(|ty| (0..w.div_ceil(TILE)).map(move |tx| (tx * TILE, ty * TILE)))
        .collect();
    let progress = crate::io::progress::bar(options.progress, tiles.len() as u64, "rendering");
    let results: Vec<Tile> = tiles
        .par_iter()
        .map(|&(x0, y0)| {
            let mut stats = TrackingStats::default();
            let mut non_finite = 0;
            let mut pixels = Vec::with_capacity((TILE * TILE) as usize);
            for y in y0..(y0 + TILE).min(h) {
                for x in x0..(x0 + TILE).min(w) {
                    pixels.push(trace_pixel(
                        scene,
                        options,
                        &radiance_path(options.max_depth),
                        (x, y),
                        &mut stats,
                        &mut non_finite,
                    ));
                }
            }
            progress.inc(1);
            Tile {
                origin: (x0, y0),
                pixels,
                stats,
                non_finite,
            }
        })
        .collect();
    progress.finish_and_clear();
    let mut image = RgbImage::new(w, h);
    let mut stats = RenderStats {
        paths: w as u64 * h as u64 * options.spp as u64,
        ..Default::default()
    };
    for tile in results {
        let (x0, y0) = tile.origin;
        let tw = (x0 + TILE).min(w) - x0;
        for (i, c) in tile.pixels.into_iter().enumerate() {
            let (x, y) = (x0 + i as u32 % tw, y0 + i as u32 / tw);
            image.pixels[(y * w + x) as usize] = c;
        }
        stats.tracking += tile.stats;
        stats.non_finite += tile.non_finite;
    }
    stats.wall = start.elapsed();
    (image, stats)
}

/// `render` of the pixels of `set` only (a rank's share): the image holds those pixels, 0
/// elsewhere, each the value `render` gives it.
pub fn render_pixels(scene: &Scene, options: &RenderOptions, set: &PixelSet) -> PixelsRendered {
    render_pixels_of(scene, options, set, radiance_path(options.max_depth))
}

/// One camera path's value: `path(scene, origin, direction, rng, stats)`.
pub trait PathValue:
    Fn(&Scene, Vec3, Vec3, &mut SmallRng, &mut TrackingStats) -> Vec3 + Sync
{
}
impl<F: Fn(&Scene, Vec3, Vec3, &mut SmallRng, &mut TrackingStats) -> Vec3 + Sync> PathValue for F {}

/// A camera path's radiance, to `max_depth` scattering events (`render`'s paths).
fn radiance_path(max_depth: u32) -> impl PathValue {
    move |scene: &Scene, origin, dir, rng: &mut SmallRng, stats: &mut TrackingStats| {
        trace_path(scene, origin, dir, max_depth, rng, stats)
    }
}

/// `render_pixels` with each path's value from `path` (radiance, or `render::alpha`'s alpha).
pub fn render_pixels_of(
    scene: &Scene,
    options: &RenderOptions,
    set: &PixelSet,
    path: impl PathValue,
) -> PixelsRendered {
    let start = Instant::now();
    let w = scene.camera.width;
    let chunk_pixels = CHUNK_PIXELS.min(set.len().div_ceil(MIN_CHUNKS)).max(1);
    let chunks = set.len().div_ceil(chunk_pixels);
    let progress = crate::io::progress::bar(options.progress, chunks, "rendering");
    let results: Vec<Traced> = (0..chunks)
        .into_par_iter()
        .map(|chunk| {
            let (mut stats, mut non_finite) = (TrackingStats::default(), 0);
            let end = ((chunk + 1) * chunk_pixels).min(set.len());
            let pixels = (chunk * chunk_pixels..end)
                .map(|i| {
                    let p = set.pixel(i);
                    let xy = (p % w, p / w);
                    let before = stats.lookups + stats.shadow_lookups;
                    let c = trace_pixel(scene, options, &path, xy, &mut stats, &mut non_finite);
                    let lookups = stats.lookups + stats.shadow_lookups - before;
                    (p, c, lookups as f32 / options.spp.max(1) as f32)
                })
                .collect();
            progress.inc(1);
            Traced {
                pixels,
                stats,
                non_finite,
            }
        })
        .collect();
    progress.finish_and_clear();
    let mut image = RgbImage::new(w, scene.camera.height);
    let mut lookups = vec![0.0; image.pixels.len()];
    let mut stats = RenderStats {
        paths: set.len() * options.spp as u64,
        ..Default::default()
    };
    for chunk in results {
        for (p, c, l) in chunk.pixels {
            image.pixels[p as usize] = c;
            lookups[p as usize] = l;
        }
        stats.tracking += chunk.stats;
        stats.non_finite += chunk.non_finite;
    }
    stats.wall = start.elapsed();
    PixelsRendered {
        image,
        lookups,
        stats,
    }
}

/// The mean of pixel (x, y)'s `options.spp` paths, each with its own random stream; non-finite
/// paths count as 0 and are counted in `non_finite`.
fn trace_pixel(
    scene: &Scene,
    options: &RenderOptions,
    path: &impl PathValue,
    (x, y): (u32, u32),
    stats: &mut TrackingStats,
    non_finite: &mut u64,
) -> Vec3 {
    let camera = &scene.camera;
    let mut sum = Vec3::ZERO;
    for sample in 0..options.spp {
        // Checked per path, not per pixel: a pixel of many samples stops within one path.
        if interrupt::requested() {
            break;
        }
        let mut rng = sample_rng(
            options.seed,
            (y * camera.width + x) as u64,
            sample,
            Pass::Forward,
        );
        let dir = camera.direction(x as f32 + rng.gen::<f32>(), y as f32 + rng.gen::<f32>());
        let value = path(scene, camera.position, dir, &mut rng, stats);
        if value.is_finite() {
            sum += value;
        } else {
            *non_finite += 1;
        }
    }
    sum / options.spp as f32
}
