//! Gradient passes over the image: per-voxel gradients of a loss (scattered into a sparse grid),
//! and per-pixel derivative images d pixel / d ε for ε added to a box of voxels.

use std::time::Instant;

use glam::{IVec3, Vec3};
use rand::Rng;
use rayon::prelude::*;

use crate::gradient::adjoint::{AdjointOptions, Estimator, GradientSink, Replay, Scratch, Suffix};
use crate::gradient::grid::GradientGrid;
use crate::io::images::RgbImage;
use crate::render::image::RenderStats;
use crate::render::sampling::{sample_rng, Pass};
use crate::render::scene::Scene;
use crate::volume::brickmap::BrickMap;
use crate::volume::tracking::TrackingStats;

#[derive(Debug, Clone, Copy)]
pub struct GradOptions {
    pub adjoint: AdjointOptions,
    pub spp: u32,
    pub seed: u64,
    /// Keep only the grid's active voxels (`--domain active`).
    pub active_only: bool,
    pub progress: bool,
}

impl GradOptions {
    /// Per-path suffixes over every voxel of the domain, without a progress bar: what tests,
    /// benchmarks and comparisons use.
    pub fn new(estimator: Estimator, spp: u32, seed: u64, max_depth: u32) -> Self {
        GradOptions {
            adjoint: AdjointOptions {
                estimator,
                suffix: Suffix::PerPath,
                max_depth,
            },
            spp,
            seed,
            active_only: false,
            progress: false,
        }
    }
}

pub struct GradientRun {
    pub gradient: GradientGrid,
    /// The radiance of the adjoint pass's own paths (a by-product, same spp).
    pub image: RgbImage,
    pub stats: RenderStats,
}

struct GridSink<'a> {
    grid: &'a mut GradientGrid,
    /// δ / spp for the current pixel.
    weight: Vec3,
    active: Option<&'a BrickMap>,
    /// Non-finite samples dropped.
    dropped: u64,
}

impl GridSink<'_> {
    /// A non-finite sample would poison every voxel it touches and every merge after it: it is
    /// dropped and counted instead.
    #[inline]
    fn finite(&mut self, d_pixel: Vec3) -> bool {
        let ok = d_pixel.is_finite();
        self.dropped += u64::from(!ok);
        ok
    }
}

impl GradientSink for GridSink<'_> {
    #[inline]
    fn add(&mut self, voxel: IVec3, d_pixel: Vec3) {
        if self.active.is_some_and(|m| !m.is_active(voxel)) || !self.finite(d_pixel) {
            return;
        }
        self.grid.add(voxel, self.weight.dot(d_pixel) as f64);
    }

    #[inline]
    fn add_cell(&mut self, base: IVec3, weights: &[f32; 8], d_pixel: Vec3) {
        if !self.finite(d_pixel) {
            return;
        }
        match self.active {
            None => self
                .grid
                .add_cell(base, weights, self.weight.dot(d_pixel) as f64),
            Some(_) => {
                for (k, &w) in weights.iter().enumerate() {
                    self.add(base + crate::volume::brickmap::corner(k), d_pixel * w);
                }
            }
        }
    }
}

/// Sums the samples whose voxel lies in an inclusive box: d pixel / d ε for ε added to the box.
struct BoxSink {
    lo: IVec3,
    hi: IVec3,
    sum: Vec3,
    /// Non-finite samples dropped (as in `GridSink`).
    dropped: u64,
}

impl GradientSink for BoxSink {
    #[inline]
    fn add(&mut self, voxel: IVec3, d_pixel: Vec3) {
        if voxel.cmpge(self.lo).all() && voxel.cmple(self.hi).all() {
            if d_pixel.is_finite() {
                self.sum += d_pixel;
            } else {
                self.dropped += 1;
            }
        }
    }
}

/// Row bands of a gradient pass (see `over_pixels`).
const ROW_BANDS: u32 = 16;

/// What one thread keeps from path to path: its tracking counters and its replay buffers.
#[derive(Default)]
struct Worker {
    stats: TrackingStats,
    scratch: Scratch,
    /// Non-finite samples dropped (`RenderStats::non_finite`).
    non_finite: u64,
}

/// Runs `per_pixel(acc, x, y, worker)` for every pixel in parallel over row bands, `spp` paths
/// each. Returns the per-band accumulators and the pass's stats (paths, wall time, tracking
/// counters, non-finite samples dropped).
fn over_pixels<T: Send>(
    scene: &Scene,
    spp: u32,
    progress: bool,
    what: &str,
    init: impl Fn() -> T + Sync + Send,
    per_pixel: impl Fn(&mut T, u32, u32, &mut Worker) + Sync + Send,
) -> (Vec<T>, RenderStats) {
    let start = Instant::now();
    let (w, h) = (scene.camera.width, scene.camera.height);
    let bar = crate::io::progress::bar(progress, h as u64, what);
    // A fixed number of row bands, whatever the thread count: the per-band sums are merged in
    // band order, so a pass's floating-point result depends on its seed only (an optimisation
    // resumed on another machine continues bit for bit). 16 bands balance the load on a few cores
    // and keep the per-band accumulators (whole gradient grids) cheap to allocate and merge.
    let bands = h.clamp(1, ROW_BANDS);
    let results: Vec<(T, Worker)> = (0..bands)
        .into_par_iter()
        .map(|band| {
            let (mut acc, mut worker) = (init(), Worker::default());
            for y in band * h / bands..(band + 1) * h / bands {
                for x in 0..w {
                    per_pixel(&mut acc, x, y, &mut worker);
                }
                bar.inc(1);
            }
            (acc, worker)
        })
        .collect();
    bar.finish_and_clear();
    let mut stats = RenderStats {
        paths: w as u64 * h as u64 * spp as u64,
        ..Default::default()
    };
    let values = results
        .into_iter()
        .map(|(v, worker)| {
            stats.tracking += worker.stats;
            stats.non_finite += worker.non_finite;
            v
        })
        .collect();
    stats.wall = start.elapsed();
    (values, stats)
}

/// The scene and options that every gradient sample of a pass shares.
struct GradientPass<'a> {
    scene: &'a Scene,
    options: &'a GradOptions,
}

impl GradientPass<'_> {
    /// One camera path through pixel (x, y) with its own random stream; its gradient samples go
    /// to `sink` and its radiance is returned.
    fn sample(
        &self,
        x: u32,
        y: u32,
        sample: u32,
        worker: &mut Worker,
        sink: &mut impl GradientSink,
    ) -> Vec3 {
        let camera = &self.scene.camera;
        let mut rng = sample_rng(
            self.options.seed,
            (y * camera.width + x) as u64,
            sample,
            Pass::Adjoint,
        );
        let dir = camera.direction(x as f32 + rng.gen::<f32>(), y as f32 + rng.gen::<f32>());
        let mut replay = Replay {
            scene: self.scene,
            options: &self.options.adjoint,
            rng: &mut rng,
            stats: &mut worker.stats,
        };
        replay.camera_path_gradient(camera.position, dir, &mut worker.scratch, sink)
    }
}

/// The gradient of a loss whose adjoint image is `adjoint` (∂loss/∂pixel), per voxel.
pub fn gradient(scene: &Scene, adjoint: &[Vec3], options: &GradOptions) -> GradientRun {
    let camera = &scene.camera;
    let w = camera.width;
    let template = GradientGrid::for_medium(&scene.medium);
    let active = options.active_only.then_some(&scene.medium.grid);
    let spp = options.spp;
    let pass = GradientPass { scene, options };
    let (parts, stats) = over_pixels(
        scene,
        spp,
        options.progress,
        "gradient",
        || (template.empty_like(), Vec::<(u32, Vec3)>::new()),
        |(grid, pixels), x, y, worker| {
            let index = y * w + x;
            let mut sink = GridSink {
                grid,
                weight: adjoint[index as usize] / spp as f32,
                active,
                dropped: 0,
            };
            let mut sum = Vec3::ZERO;
            for sample in 0..spp {
                let radiance = pass.sample(x, y, sample, worker, &mut sink);
                if radiance.is_finite() {
                    sum += radiance;
                }
            }
            worker.non_finite += sink.dropped;
            pixels.push((index, sum / spp as f32));
        },
    );
    let mut gradient = template;
    let mut image = RgbImage::new(camera.width, camera.height);
    for (grid, pixels) in parts {
        gradient.merge(&grid, 1.0);
        for (i, c) in pixels {
            image.pixels[i as usize] = c;
        }
    }
    GradientRun {
        gradient,
        image,
        stats,
    }
}

/// d pixel / d ε for ε added to every voxel in the inclusive index box `[lo, hi]`.
pub fn derivative_image(
    scene: &Scene,
    lo: IVec3,
    hi: IVec3,
    options: &GradOptions,
) -> (RgbImage, RenderStats) {
    let camera = &scene.camera;
    let w = camera.width;
    let spp = options.spp;
    let pass = GradientPass { scene, options };
    let (parts, stats) = over_pixels(
        scene,
        spp,
        options.progress,
        "d pixel",
        Vec::<(u32, Vec3)>::new,
        |pixels, x, y, worker| {
            let mut sink = BoxSink {
                lo,
                hi,
                sum: Vec3::ZERO,
                dropped: 0,
            };
            for sample in 0..spp {
                pass.sample(x, y, sample, worker, &mut sink);
            }
            worker.non_finite += sink.dropped;
            pixels.push((y * w + x, sink.sum / spp as f32));
        },
    );
    let mut image = RgbImage::new(camera.width, camera.height);
    for (i, c) in parts.into_iter().flatten() {
        image.pixels[i as usize] = c;
    }
    (image, stats)
}
