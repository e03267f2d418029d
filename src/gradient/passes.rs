//! Gradient passes over the image: a loss's per-voxel gradient, d pixel / d ε for a box of voxels.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use glam::{IVec3, Vec3};
use rand::Rng;
use rayon::prelude::*;

use crate::gradient::adjoint::{GradientSink, Replay, Scratch};
use crate::gradient::alpha_gradient::alpha_gradient_sample;
pub use crate::gradient::bands::{BandedGradient, QuantumBands};
use crate::gradient::grid::{corner_dither, Accumulator, GradientGrid, Quanta};
use crate::gradient::in_order::InOrder;
pub use crate::gradient::options::{GradOptions, Measured, Parameter};
use crate::io::images::RgbImage;
use crate::render::alpha::alpha_sample;
use crate::render::image::RenderStats;
use crate::render::interrupt;
use crate::render::pixel_set::PixelSet;
use crate::render::sampling::{mix64, sample_rng, Pass};
use crate::render::scene::Scene;
use crate::volume::albedo::{Albedo, AlbedoGrid};
use crate::volume::brickmap::{corner, BrickMap};
use crate::volume::tracking::TrackingStats;

/// How large one path's sample of ∂pixel/∂θ can be in `scene`, per unit of adjoint, to within a
/// modest factor: the brightest radiance a path carries (its lights', its emission's) times, for
/// the extinction, the optical depth a unit of θ adds across the medium's box (density_scale ×
/// its longest edge, in world units, the units a segment's length is in). The quantum scales with
/// it, so that a scene in other units (grid values of 10¹² under a density_scale of 4·10⁻¹²,
/// lights of 10⁻¹⁰) keeps the precision and headroom of one in the usual units, where a quantum
/// from the adjoint alone rounded every sample to 0 or saturated the sums. An emission grid's
/// samples carry ∂Le/∂v (its largest, `largest_radiance_derivative`) and no optical depth.
pub fn sample_scale(scene: &Scene, parameter: Parameter) -> f64 {
    let emission = (scene.medium.emission.as_ref()).map_or(0.0, |e| e.largest_radiance().0);
    let radiance = f64::from(scene.lights.brightest()).max(emission);
    let scale = match parameter {
        Parameter::Extinction => radiance * optical_depth_per_unit(scene),
        Parameter::Albedo => radiance,
        Parameter::Emission => {
            (scene.medium.emission.as_ref()).map_or(1.0, |e| e.largest_radiance_derivative())
        }
    };
    if scale > 0.0 && scale.is_finite() {
        scale
    } else {
        1.0
    }
}

/// The optical depth one unit of θ adds across the medium's box: the scale of alpha's samples
/// (`alpha_gradient`), which carry no radiance.
pub fn optical_depth_per_unit(scene: &Scene) -> f64 {
    let medium = &scene.medium;
    let (lo, hi) = medium.bounds;
    let edges = (hi - lo).as_dvec3() * medium.transform.voxel_size();
    f64::from(medium.density_scale) * edges.max_element()
}

pub struct GradientRun {
    /// The gradient in quanta, by band of the adjoint's size.
    pub gradient: BandedGradient,
    /// The radiance of the adjoint pass's own paths (a by-product, same spp).
    pub image: RgbImage,
    pub stats: RenderStats,
}

impl GradientRun {
    /// ∂loss/∂voxel as f32 values.
    pub fn values(&self) -> GradientGrid<f32> {
        self.gradient.values()
    }
}

/// One gradient sample as a pass records it: `value` spread over the corners of a trilinear cell
/// (corner k = `base + corner(k)` with weight `weights[k]`), or on one voxel (weight 1 on corner 0).
struct Splat {
    base: IVec3,
    weights: [f32; 8],
    value: f32,
    /// The dither its corners are rounded to quanta with (`grid::corner_dither`).
    dither: f32,
}

/// Uniform dithers in [0, 1) for rounding a pass's samples to quanta, one stream per pixel of a
/// pass (SplitMix64 on a counter): like the paths' own numbers they depend on the pixel, never on
/// the thread or process, so the sum stays the same bits on any number of either.
struct Dither(u64);

impl Dither {
    fn new(seed: u64, pixel: u64) -> Self {
        Dither(seed ^ 0x5851_F42D_4C95_7F2D ^ pixel.wrapping_mul(0xD1B5_4A32_D192_ED03))
    }

    #[inline]
    fn draw(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        (mix64(self.0) >> 40) as f32 * (1.0 / (1u32 << 24) as f32)
    }
}

/// Records a unit's gradient samples in order (see `over_pixels`), weighted by the pixel's
/// δ / (spp · quantum).
/// A unit keeps its samples (about 50 bytes each), not a grid: a grid per unit or per thread would
/// cost the domain's memory each (hundreds of MiB for a cloud of 30 million voxels).
struct SplatSink<'a> {
    splats: &'a mut Vec<Splat>,
    /// δ / (spp · quantum) for the current pixel.
    weight: Vec3,
    /// The current pixel's dithers.
    dither: Dither,
    /// Non-finite samples dropped.
    dropped: u64,
}

impl SplatSink<'_> {
    /// A non-finite sample would poison every voxel it touches and every merge after it: it is
    /// dropped and counted instead, whether the path's derivative or the pixel's weight (a
    /// non-finite δ) made it so; rounded to quanta it would have become 0 or ±2⁶³ unseen.
    #[inline]
    fn push(&mut self, base: IVec3, weights: [f32; 8], d_pixel: Vec3) {
        let value = self.weight.dot(d_pixel);
        if value.is_finite() {
            self.splats.push(Splat {
                base,
                weights,
                value,
                dither: self.dither.draw(),
            });
        } else {
            self.dropped += 1;
        }
    }
}

impl GradientSink for SplatSink<'_> {
    #[inline]
    fn add(&mut self, voxel: IVec3, d_pixel: Vec3) {
        let mut weights = [0.0; 8];
        weights[0] = 1.0;
        self.push(voxel, weights, d_pixel);
    }

    #[inline]
    fn add_cell(&mut self, base: IVec3, weights: &[f32; 8], d_pixel: Vec3) {
        self.push(base, *weights, d_pixel);
    }
}

/// Adds a unit's samples to the pass's gradient, keeping only active voxels with `active`.
fn apply(grid: &mut GradientGrid<Quanta>, splats: &[Splat], active: Option<&BrickMap>) {
    for s in splats {
        match active {
            None => grid.add_cell(s.base, &s.weights, s.value, s.dither),
            Some(map) => {
                for (k, &w) in s.weights.iter().enumerate() {
                    let voxel = s.base + corner(k);
                    if w > 0.0 && map.is_active(voxel) {
                        let value =
                            Quanta::from_f32_dithered(w * s.value, corner_dither(s.dither, k));
                        grid.add(voxel, value);
                    }
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

/// What one thread keeps from path to path: its tracking counters and its replay buffers.
#[derive(Default)]
struct Worker {
    stats: TrackingStats,
    scratch: Scratch,
    /// Non-finite samples dropped (`RenderStats::non_finite`).
    non_finite: u64,
    /// Paths traced.
    paths: u64,
}

/// Paths per unit of work in a pass at most: a unit is a run of whole pixels in row-major order,
/// and its recorded samples stay near 25 MB at any spp.
const PATHS_PER_UNIT: u64 = 1 << 14;

/// Units a pass is cut into at least (while a unit keeps a pixel): the passes of an optimisation
/// are small (a 32² view at 8 spp is half of `PATHS_PER_UNIT`), and a pass of one or two units
/// runs on one thread, or waits for the slower half of the image.
const MIN_UNITS: u64 = 64;

/// Pixels per unit of a pass over `pixels` pixels at `spp`: at most `PATHS_PER_UNIT` paths and
/// at least `MIN_UNITS` units, while a unit keeps a whole pixel. A function of the image and spp
/// only, never of the thread count.
fn unit_pixels(pixels: u64, spp: u32) -> u64 {
    (PATHS_PER_UNIT / spp.max(1) as u64)
        .min(pixels.div_ceil(MIN_UNITS))
        .max(1)
}

/// Runs `per_pixel(acc, x, y, worker)` for every pixel in parallel, about `spp` paths each (the
/// units' size; `per_pixel` traces the paths and counts them in `worker`), a unit of pixels at a
/// time (`PATHS_PER_UNIT`), and hands each unit's accumulator to `consume` in unit order. Returns
/// the pass's stats (paths, wall time, tracking counters, non-finite samples dropped).
///
/// Units are consumed in order whatever the thread count (a derivative image's pixels land in
/// place either way; a gradient's quanta add up the same in any order). Units are started in
/// order and consumed as soon as their predecessors are, so only about one accumulator per thread
/// is alive at a time; one thread consumes while the others go on tracing (`InOrder`).
/// `progress`: the progress bar's label, if one is shown.
fn over_pixels<T: Send>(
    scene: &Scene,
    set: &PixelSet,
    spp: u32,
    progress: Option<&str>,
    init: impl Fn() -> T + Sync + Send,
    per_pixel: impl Fn(&mut T, u32, u32, &mut Worker) + Sync + Send,
    consume: impl FnMut(T) + Send,
) -> RenderStats {
    let start = Instant::now();
    let w = scene.camera.width;
    let pixels = set.len();
    let unit_pixels = unit_pixels(pixels, spp);
    let units = pixels.div_ceil(unit_pixels);
    let bar = crate::io::progress::bar(progress.is_some(), pixels, progress.unwrap_or_default());
    let next_unit = AtomicU64::new(0);
    let in_order = InOrder::new(consume);
    let threads = (rayon::current_num_threads() as u64).min(units);
    let workers: Vec<Worker> = (0..threads)
        .into_par_iter()
        .map(|_| {
            let mut worker = Worker::default();
            loop {
                let unit = next_unit.fetch_add(1, Ordering::Relaxed);
                if unit >= units {
                    break;
                }
                let mut acc = init();
                let first = unit * unit_pixels;
                let last = (first + unit_pixels).min(pixels);
                // An interrupted pass skips its remaining units' pixels (their result is
                // discarded) but still hands every unit on, so the in-order merge drains.
                for i in (first..last).filter(|_| !interrupt::requested()) {
                    let p = set.pixel(i);
                    per_pixel(&mut acc, p % w, p / w, &mut worker);
                }
                bar.inc(last - first);
                in_order.finish(unit, acc);
            }
            worker
        })
        .collect();
    in_order.consume_rest();
    bar.finish_and_clear();
    let mut stats = RenderStats::default();
    for worker in workers {
        stats.paths += worker.paths;
        stats.tracking += worker.stats;
        stats.non_finite += worker.non_finite;
    }
    stats.wall = start.elapsed();
    stats
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
        let seed = self.options.stream_seed();
        let mut rng = sample_rng(seed, (y * camera.width + x) as u64, sample, Pass::Adjoint);
        let dir = camera.direction(x as f32 + rng.gen::<f32>(), y as f32 + rng.gen::<f32>());
        if self.options.measured == Measured::Alpha {
            // Alpha depends on the extinction alone: with respect to other grids its gradient is 0.
            let stats = &mut worker.stats;
            return match self.options.parameter {
                Parameter::Extinction => {
                    alpha_gradient_sample(self.scene, camera.position, dir, &mut rng, stats, sink)
                }
                _ => Vec3::splat(alpha_sample(
                    self.scene,
                    camera.position,
                    dir,
                    &mut rng,
                    stats,
                )),
            };
        }
        let mut replay = Replay {
            scene: self.scene,
            options: &self.options.adjoint,
            rng: &mut rng,
            stats: &mut worker.stats,
        };
        let scratch = &mut worker.scratch;
        match self.options.parameter {
            Parameter::Extinction => {
                replay.camera_path_gradient(camera.position, dir, scratch, sink)
            }
            Parameter::Emission => {
                replay.camera_path_emission_gradient(camera.position, dir, scratch, sink)
            }
            Parameter::Albedo => {
                replay.camera_path_albedo_gradient(camera.position, dir, scratch, sink)
            }
        }
    }
}

/// The grid whose values the pass's parameter names: the density's, the emission's, or the
/// albedo's (the channel's, of an RGB grid); the density's where the medium has no such grid (the
/// gradient is then 0).
pub fn parameter_grid(scene: &Scene, parameter: Parameter, channel: Option<usize>) -> &BrickMap {
    let medium = &scene.medium;
    match (parameter, &medium.emission, medium.albedo.grid()) {
        (Parameter::Emission, Some(e), _) => &e.grid,
        (Parameter::Albedo, _, Some(a)) => &a.channels[channel_of(a, channel)],
        _ => &medium.grid,
    }
}

/// `parameter_grid`, to be changed (finite differences perturb it). The density's majorants are
/// the caller's to rebuild.
pub fn parameter_grid_mut(
    scene: &mut Scene,
    parameter: Parameter,
    channel: Option<usize>,
) -> &mut BrickMap {
    let medium = &mut scene.medium;
    match (parameter, &mut medium.emission, &mut medium.albedo) {
        (Parameter::Emission, Some(e), _) => &mut e.grid,
        (Parameter::Albedo, _, Albedo::Grid(a)) => {
            let c = channel_of(a, channel);
            &mut a.channels[c]
        }
        _ => &mut medium.grid,
    }
}

/// The brick map of `channel` (red for none; a grey grid's one map for any).
fn channel_of(grid: &AlbedoGrid, channel: Option<usize>) -> usize {
    channel.unwrap_or(0).min(grid.channels.len() - 1)
}

/// An empty gradient grid over every voxel the pass's lookups can weight.
pub fn gradient_grid_for<T: Accumulator>(scene: &Scene, options: &GradOptions) -> GradientGrid<T> {
    match (options.domain, options.parameter) {
        (Some((lo, hi)), _) => GradientGrid::for_box(lo, hi),
        (None, Parameter::Extinction) => GradientGrid::for_medium(&scene.medium),
        (None, _) => {
            GradientGrid::for_grid(parameter_grid(scene, options.parameter, options.channel))
        }
    }
}

/// The gradient of a loss whose adjoint image is `adjoint` (∂loss/∂pixel), per voxel.
pub fn gradient(scene: &Scene, adjoint: &[Vec3], options: &GradOptions) -> GradientRun {
    let pixels = scene.camera.width * scene.camera.height;
    gradient_of(scene, adjoint, options, &PixelSet::All(pixels))
}

/// `gradient` from the pixels of `set` only (a rank's share, a pixel batch); the image holds
/// those pixels, 0 elsewhere.
pub fn gradient_of(
    scene: &Scene,
    adjoint: &[Vec3],
    options: &GradOptions,
    set: &PixelSet,
) -> GradientRun {
    let scale = sample_scale(scene, options.parameter);
    let bands = QuantumBands::of([(adjoint, scale, options.samples)], options.spp);
    let mut gradient = BandedGradient::new(bands, gradient_grid_for(scene, options));
    let (image, stats) = add_gradient_of(scene, (adjoint, scale), options, set, &mut gradient);
    GradientRun {
        gradient,
        image,
        stats,
    }
}

/// `gradient_of` for an adjoint whose samples have `scale` (`sample_scale`), added into
/// `gradient` in its bands' quanta: passes whose gradients add up (an optimisation step's views,
/// Python's cameras) share one set of bands and grids instead of each filling its own that are
/// then merged (8 % of an optimisation step on the worked example). Returns the image (a pixel
/// that took no path reads 0) and the counters.
pub fn add_gradient_of(
    scene: &Scene,
    (adjoint, scale): (&[Vec3], f64),
    options: &GradOptions,
    set: &PixelSet,
    gradient: &mut BandedGradient,
) -> (RgbImage, RenderStats) {
    let camera = &scene.camera;
    let w = camera.width;
    let mut image = RgbImage::new(camera.width, camera.height);
    let active =
        options
            .active_only
            .then_some(parameter_grid(scene, options.parameter, options.channel));
    let spp = options.spp;
    let channel_mask = match options.channel {
        Some(c) => Vec3::AXES[c],
        None => Vec3::ONE,
    };
    let pass = GradientPass { scene, options };
    let seed = options.stream_seed();
    let BandedGradient { bands, grids } = gradient;
    let stats = over_pixels(
        scene,
        set,
        spp,
        options.progress.then_some("gradient"),
        || {
            let splats = (0..bands.len())
                .map(|_| Vec::<Splat>::new())
                .collect::<Vec<_>>();
            (splats, Vec::<(u32, Vec3)>::new())
        },
        |(splats, pixels), x, y, worker| {
            let index = y * w + x;
            let delta = adjoint[index as usize] * channel_mask;
            let (samples, divisor) = options.samples.draw(spp, delta, seed, index as u64);
            let path_weight = options.samples.path_weight(spp, adjoint[index as usize]);
            let band = bands.band_of(adjoint[index as usize], scale, path_weight);
            let quantum = bands.quantum(band);
            let mut sink = SplatSink {
                splats: &mut splats[band],
                // In f64: for a tiny δ, 1/quantum exceeds f32's range though δ/quantum does not.
                weight: (delta.as_dvec3() * (1.0 / (divisor * quantum))).as_vec3(),
                dither: Dither::new(seed, index as u64),
                dropped: 0,
            };
            let mut sum = Vec3::ZERO;
            for sample in 0..samples {
                let radiance = pass.sample(x, y, sample, worker, &mut sink);
                if radiance.is_finite() {
                    sum += radiance;
                }
            }
            worker.non_finite += sink.dropped;
            worker.paths += samples as u64;
            pixels.push((index, sum / samples.max(1) as f32));
        },
        |(splats, pixels)| {
            for (grid, splats) in grids.iter_mut().zip(&splats) {
                apply(grid, splats, active);
            }
            for (i, c) in pixels {
                image.pixels[i as usize] = c;
            }
        },
    );
    (image, stats)
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
    let mut image = RgbImage::new(camera.width, camera.height);
    let stats = over_pixels(
        scene,
        &PixelSet::All(camera.width * camera.height),
        spp,
        options.progress.then_some("d pixel"),
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
            worker.paths += spp as u64;
            pixels.push((y * w + x, sink.sum / spp as f32));
        },
        |pixels| {
            for (i, c) in pixels {
                image.pixels[i as usize] = c;
            }
        },
    );
    (image, stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pass_is_cut_into_enough_units_of_bounded_size() {
        // (width × height, spp): an optimisation's small views, the cloud's render, a 1-pixel
        // image, a huge spp.
        for (pixels, spp) in [
            (32 * 32, 8),
            (64 * 64, 8),
            (256 * 256, 4),
            (1, 1),
            (50, 1 << 20),
        ] {
            let unit = unit_pixels(pixels, spp);
            let units = pixels.div_ceil(unit);
            assert!(unit >= 1);
            assert!(
                units >= MIN_UNITS.min(pixels),
                "{pixels} px at {spp} spp: {units} units"
            );
            assert!(
                unit == 1 || unit * spp as u64 <= PATHS_PER_UNIT,
                "{pixels} px: {unit}"
            );
        }
        // A 32² view at 8 spp, 8192 paths, was one unit: one thread did the whole pass.
        assert_eq!(unit_pixels(32 * 32, 8), 16);
    }
}
