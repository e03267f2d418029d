//! One iteration's gradient of the images' loss, on every rank of a job at once:
//!
//! 1. the batch: `batch` views (each epoch a fresh permutation), or `batch_pixels` pixels drawn
//!    across every training view (a uniform view, then a uniform pixel of it);
//! 2. each view's primal render (and its alpha render, when the run fits alpha), its pixels split
//!    over the ranks and summed, so every rank has the same images, losses and adjoint images
//!    δ = ∂loss/∂pixel;
//! 3. the gradient passes (colour's, then alpha's), each rank over its share of the pixels, their
//!    paths spread over the pixels in proportion to δ (`pixel_samples`),
//!    accumulated as quanta of one set of bands for the whole batch (`gradient::bands`);
//! 4. the sum over the ranks (`cluster::sparse_sum`), exact, so that the step is the same bits at
//!    any number of ranks and threads.
//!
//! The view batch's loss is the mean over its views of each view's mean over pixels; a pixel
//! batch of N draws estimates the same mean as (1/N) Σ over its draws of the pixel's loss, and its
//! gradient as the same sum of the pixels' gradients (a pixel drawn twice counts twice).

use anyhow::Result;
use glam::{IVec3, Vec3};
use rand::seq::SliceRandom;
use rand::{Rng, RngCore};

use crate::cluster::images::sum_rendered_pixels;
use crate::cluster::sparse_sum::{sum_bands_over_ranks, Traffic};
use crate::cluster::Cluster;
use crate::gradient::adjoint::Estimator;
use crate::gradient::objective::check_target;
use crate::gradient::passes::{
    add_gradient_of, gradient_grid_for, optical_depth_per_unit, sample_scale, BandedGradient,
    GradOptions, Measured, Parameter, QuantumBands,
};
use crate::gradient::pixel_samples::{path_cost, PixelSamples};
use crate::io::images::RgbImage;
use crate::optimize::problem::Problem;
use crate::render::alpha::render_alpha_pixels;
use crate::render::image::{render_pixels, PixelsRendered, RenderOptions};
use crate::render::pixel_set::PixelSet;
use crate::render::sampling::pixel_rng;
use crate::render::scene::Scene;

/// Seeds the pixel batches' draws apart from every other stream of a run.
const PIXEL_BATCH_SALT: u64 = 0x91c5_e1ba_7c40_0001;

/// Seeds the second half of a primal render apart from the first (`piece_adjoint`).
const EXPOSURE_HALF_SALT: u64 = 0x5bd1_e995_0e5b_0002;

/// The images' gradient of one iteration, the same on every rank.
pub struct ImagesGradient {
    /// ∂loss/∂θ per voxel that some path reached.
    pub voxels: Vec<(glam::IVec3, f64)>,
    /// The batch's loss.
    pub loss: f64,
    /// ∂loss/∂x of each capture's exposure log-factor x (`exposure`): Σ δ′·(I′ − k·B) over the
    /// batch's views of that capture (B: `piece_adjoint`).
    pub exposure_gradients: Vec<f64>,
    pub traffic: Traffic,
}

/// One view's part of a batch: all its pixels, or the pixels drawn from it with their counts.
struct Piece {
    view: usize,
    seed: u64,
    drawn: Option<Vec<(u32, u32)>>,
}

impl Piece {
    /// This rank's share of the pixels the piece traces.
    fn pixels(&self, pixels: u32, cluster: &Cluster) -> PixelSet {
        match &self.drawn {
            None => PixelSet::share(pixels, cluster.rank(), cluster.size()),
            Some(_) => {
                PixelSet::share_of_list(&self.listed(pixels), cluster.rank(), cluster.size())
            }
        }
    }

    /// Every pixel the piece traces, on all ranks together.
    fn listed(&self, pixels: u32) -> Vec<u32> {
        match &self.drawn {
            None => (0..pixels).collect(),
            Some(drawn) => drawn.iter().map(|&(p, _)| p).collect(),
        }
    }
}

/// The images' gradient at iteration `iteration` of the scene `scene` (θ at the current level,
/// whose voxels span `level_box`), each view's render scaled by its capture's exposure factor
/// (`exposures`) before it meets its target.
pub fn images_gradient(
    problem: &Problem,
    cluster: &Cluster,
    scene: &mut Scene,
    estimator: Estimator,
    iteration: u64,
    exposures: &[f32],
    level_box: (IVec3, IVec3),
) -> Result<ImagesGradient> {
    let s = &problem.settings;
    let pieces = batch_pieces(problem, iteration);
    let (mut loss, mut adjoints, mut lit) = (0.0, Vec::with_capacity(pieces.len()), 0);
    let mut exposure_gradients = vec![0.0; exposures.len()];
    let view_weight = 1.0 / pieces.len() as f64;
    let mut alpha_adjoints = Vec::with_capacity(pieces.len());
    // Each adjoint's samples' scale, under its view's lights (`passes::sample_scale`).
    let mut scales = Vec::with_capacity(pieces.len());
    let parameter = problem.unknown.parameter();
    for piece in &pieces {
        let view = &problem.views[piece.view];
        problem.look_through(scene, &mut lit, view);
        let exposure = exposures[view.capture];
        let adjoint = piece_adjoint(problem, cluster, scene, piece, view_weight, exposure)?;
        loss += adjoint.loss;
        exposure_gradients[view.capture] += adjoint.exposure_gradient;
        adjoints.push(adjoint);
        scales.push(sample_scale(scene, parameter));
        let alpha = alpha_adjoint(problem, cluster, scene, piece, view_weight);
        if let Some(alpha) = &alpha {
            loss += alpha.loss;
        }
        alpha_adjoints.push(alpha);
    }
    let alpha_scale = optical_depth_per_unit(scene);
    let colour_samples = pixel_samples(problem, &pieces, adjoints.iter().map(Some));
    let alpha_samples = pixel_samples(problem, &pieces, alpha_adjoints.iter().map(Option::as_ref));
    let colour_deltas =
        (adjoints.iter().zip(&scales)).map(|(a, &scale)| (&a.delta[..], scale, colour_samples));
    let alpha_deltas =
        (alpha_adjoints.iter().flatten()).map(|a| (&a.delta[..], alpha_scale, alpha_samples));
    let bands = QuantumBands::of(colour_deltas.chain(alpha_deltas), s.spp);
    // An emission unknown's gradient is wanted over its whole box: the pass would otherwise
    // cover only its current bricks (none for an empty start, which then never grows) and their
    // apron (outside the box). The density's domain is the medium's bounds already.
    let domain = (parameter != Parameter::Extinction).then_some(level_box);
    let mut pass = GradOptions {
        parameter,
        domain,
        ..GradOptions::new(estimator, s.spp, 0, s.max_depth)
    };
    pass.adjoint.suffix_paths = s.suffix_paths;
    let mut total = BandedGradient::new(bands, gradient_grid_for(scene, &pass));
    let passes = (pieces.iter().zip(&adjoints))
        .zip(scales)
        .zip(&alpha_adjoints);
    for (((piece, adjoint), scale), alpha) in passes {
        problem.look_through(scene, &mut lit, &problem.views[piece.view]);
        let pixels = piece.pixels(scene.camera.width * scene.camera.height, cluster);
        let options = GradOptions {
            seed: piece.seed,
            samples: colour_samples,
            ..pass
        };
        add_gradient_of(
            scene,
            (&adjoint.delta, scale),
            &options,
            &pixels,
            &mut total,
        );
        if let Some(alpha) = alpha {
            let options = GradOptions {
                measured: Measured::Alpha,
                samples: alpha_samples,
                ..options
            };
            let alpha = (&alpha.delta[..], alpha_scale);
            add_gradient_of(scene, alpha, &options, &pixels, &mut total);
        }
    }
    let (total, traffic) = sum_bands_over_ranks(cluster, total);
    let inside = |v: &IVec3| domain.is_none_or(|(lo, hi)| v.cmpge(lo).all() && v.cmple(hi).all());
    let voxels = (total.voxels().into_iter())
        .filter(|(v, _)| inside(v))
        .collect();
    Ok(ImagesGradient {
        voxels,
        loss,
        exposure_gradients,
        traffic,
    })
}

/// A piece's share of the batch: its loss, the adjoint image the gradient pass traces (k·δ′,
/// zero where it draws no pixel), its primal paths' lookups per path and its part of ∂loss/∂x
/// (Σ δ′·(I′ − k·B)).
struct PieceAdjoint {
    loss: f64,
    delta: Vec<Vec3>,
    lookups: Vec<f32>,
    exposure_gradient: f64,
}

/// How a batch's gradient pass spreads its paths over the pixels: in proportion to the pieces'
/// adjoints |δ|, at the cost of `spp` uniform paths (each pixel's primal lookups telling what
/// a path there costs), when the run asks for it; one rule for every piece, so that the pieces
/// with the larger residuals get the more paths. Every rank has the same adjoints and lookups,
/// hence the same rule.
fn pixel_samples<'a>(
    problem: &Problem,
    pieces: &[Piece],
    adjoints: impl Iterator<Item = Option<&'a PieceAdjoint>>,
) -> PixelSamples {
    if !problem.settings.samples_follow_adjoint {
        return PixelSamples::Uniform;
    }
    let mut listed = Vec::new();
    for (piece, adjoint) in pieces.iter().zip(adjoints) {
        let Some(adjoint) = adjoint else { continue };
        for p in piece.listed(adjoint.delta.len() as u32) {
            let (delta, lookups) = (adjoint.delta[p as usize], adjoint.lookups[p as usize]);
            listed.push((delta.abs().element_sum(), path_cost(lookups)));
        }
    }
    PixelSamples::following_adjoint(&listed, problem.settings.spp)
}

/// A piece's part of the batch from a primal render whose pixels the ranks share and sum, scaled
/// by the exposure factor `exposure` (k); `scene` looks through its view.
///
/// When the exposure is fitted, the primal render is two independent halves A and B of its
/// samples: ∂loss/∂x = Σ δ′·I′ from one render would correlate the noise of δ′ with that of I′
/// (for L2, E[(kI − T)·kI] carries k²·Var I: a bias that pulls the exposure down), so it is
/// ½ Σ (δ′_A·I′_B + δ′_B·I′_A) instead, each factor from the other half's paths.
fn piece_adjoint(
    problem: &Problem,
    cluster: &Cluster,
    scene: &Scene,
    piece: &Piece,
    view_weight: f64,
    exposure: f32,
) -> Result<PieceAdjoint> {
    let s = &problem.settings;
    let view = &problem.views[piece.view];
    let target = view.target_at(exposure);
    check_target(&target, scene)?;
    let halves = if s.fit_exposure { 2 } else { 1 };
    let pixels = scene.camera.width * scene.camera.height;
    let render = |half: u64| {
        let options = RenderOptions {
            spp: (s.primal_spp / halves).max(1),
            seed: piece.seed ^ half.wrapping_mul(EXPOSURE_HALF_SALT),
            max_depth: s.max_depth,
            progress: false,
        };
        let mut rendered = shared_render(cluster, piece, pixels, |set| {
            render_pixels(scene, &options, set)
        });
        rendered.image.scale(exposure);
        rendered
    };
    let (image, lookups, halves) = if s.fit_exposure {
        let (a, b) = (render(0), render(1));
        let lookups = a
            .lookups
            .iter()
            .zip(&b.lookups)
            .map(|(a, b)| 0.5 * (a + b))
            .collect();
        (
            RgbImage::average(&a.image, &b.image),
            lookups,
            Some((a.image, b.image)),
        )
    } else {
        let rendered = render(0);
        (rendered.image, rendered.lookups, None)
    };
    let adjoint_of =
        |image: &RgbImage| weighed_adjoint(problem, piece, (image, &target), view_weight, 1.0);
    let (loss, mut delta) = adjoint_of(&image);
    // ∂(kI − T(k))/∂x = I′ − k·B, B the background a picture with alpha was composited over
    // (`View::target_at`; 0 elsewhere).
    let dot = |d: &[Vec3], c: &RgbImage| -> f64 {
        let background = |p: usize| view.background.as_ref().map_or(Vec3::ZERO, |b| b.pixels[p]);
        (d.iter().zip(&c.pixels).enumerate())
            .map(|(p, (d, c))| f64::from(d.dot(*c - exposure * background(p))))
            .sum()
    };
    let exposure_gradient = match &halves {
        Some((a, b)) => 0.5 * (dot(&adjoint_of(a).1, b) + dot(&adjoint_of(b).1, a)),
        None => dot(&delta, &image),
    };
    // The pass traces k·δ′: ∂I′/∂θ = k·∂I/∂θ.
    if exposure != 1.0 {
        delta.iter_mut().for_each(|d| *d *= exposure);
    }
    Ok(PieceAdjoint {
        loss,
        delta,
        lookups,
        exposure_gradient,
    })
}

/// The loss of `image` against `target` over a piece's pixels, weighed by `weight` (alpha's
/// `alpha_weight`, colour's 1), and its adjoint δ = ∂loss/∂pixel (zero off the drawn pixels). A
/// whole view's pixels count as one of the batch's views (`view_weight`); a draw as one of its
/// `batch_pixels` draws.
fn weighed_adjoint(
    problem: &Problem,
    piece: &Piece,
    (image, target): (&RgbImage, &RgbImage),
    view_weight: f64,
    weight: f64,
) -> (f64, Vec<Vec3>) {
    let s = &problem.settings;
    match &piece.drawn {
        None => {
            let weight = view_weight * weight;
            let loss = weight * s.loss.evaluate(image, Some(target));
            let delta = s.loss.adjoint(image, Some(target));
            (loss, delta.into_iter().map(|d| d * weight as f32).collect())
        }
        Some(drawn) => {
            // Each draw weighs 1/(3N): the loss is a mean over draws and channels.
            let per_draw = weight / (3.0 * s.batch_pixels as f64);
            let (mut loss, mut delta) = (0.0, vec![Vec3::ZERO; image.pixels.len()]);
            for &(p, count) in drawn {
                let (c, t) = (image.pixels[p as usize], target.pixels[p as usize]);
                let weight = count as f64 * per_draw;
                loss += weight * s.loss.pixel_value(c, t);
                delta[p as usize] = s.loss.pixel_adjoint(c, t) * weight as f32;
            }
            (loss, delta)
        }
    }
}

/// A piece's render of a `pixels`-pixel view from `render` of each rank's share of its pixels,
/// summed over the ranks: every rank has the piece's pixels and their lookups.
fn shared_render(
    cluster: &Cluster,
    piece: &Piece,
    pixels: u32,
    render: impl Fn(&PixelSet) -> PixelsRendered,
) -> PixelsRendered {
    let mut rendered = render(&piece.pixels(pixels, cluster));
    sum_rendered_pixels(cluster, &mut rendered, &piece.listed(pixels));
    rendered
}

/// A piece's alpha loss, adjoint image and lookups, when the run fits alpha and the piece's view
/// has an alpha target: α from its own primal render (`render::alpha`; the exposure scales
/// colour, not coverage), weighed by `alpha_weight` beside the colour's loss.
fn alpha_adjoint(
    problem: &Problem,
    cluster: &Cluster,
    scene: &Scene,
    piece: &Piece,
    view_weight: f64,
) -> Option<PieceAdjoint> {
    let s = &problem.settings;
    let target = problem.views[piece.view].alpha.as_ref()?;
    if s.alpha_weight <= 0.0 {
        return None;
    }
    let options = RenderOptions {
        spp: s.primal_spp,
        seed: piece.seed,
        max_depth: 1,
        progress: false,
    };
    let pixels = scene.camera.width * scene.camera.height;
    let rendered = shared_render(cluster, piece, pixels, |set| {
        render_alpha_pixels(scene, &options, set)
    });
    let weight = f64::from(s.alpha_weight);
    let (loss, delta) = weighed_adjoint(
        problem,
        piece,
        (&rendered.image, target),
        view_weight,
        weight,
    );
    Some(PieceAdjoint {
        loss,
        delta,
        lookups: rendered.lookups,
        exposure_gradient: 0.0,
    })
}

/// The views of iteration `iteration` with their seeds: the view batch, or the views a pixel
/// batch drew from, in view order, with the pixels drawn from each.
fn batch_pieces(problem: &Problem, iteration: u64) -> Vec<Piece> {
    let s = &problem.settings;
    let seed_of = |slot: usize| pixel_rng(s.seed, iteration, slot as u64).next_u64();
    if s.batch_pixels == 0 {
        let views = batch(problem.views.len(), s.batch, s.seed, iteration);
        return (views.into_iter().enumerate())
            .map(|(slot, view)| Piece {
                view,
                seed: seed_of(slot),
                drawn: None,
            })
            .collect();
    }
    let sizes: Vec<u32> = (problem.views.iter())
        .map(|v| v.camera.width * v.camera.height)
        .collect();
    let draws = pixel_batch(&sizes, s.batch_pixels, s.seed, iteration);
    (draws.into_iter().enumerate())
        .map(|(slot, (view, drawn))| Piece {
            view,
            seed: seed_of(slot),
            drawn: Some(drawn),
        })
        .collect()
}

/// `count` draws of a uniform view (of views with `sizes[v]` pixels), then a uniform pixel of it,
/// as (view, [(pixel, times drawn)]) in view and pixel order.
pub fn pixel_batch(
    sizes: &[u32],
    count: u32,
    seed: u64,
    iteration: u64,
) -> Vec<(usize, Vec<(u32, u32)>)> {
    let mut rng = pixel_rng(seed ^ PIXEL_BATCH_SALT, iteration, 0);
    let mut draws: Vec<(usize, u32)> = (0..count)
        .map(|_| {
            let view = rng.gen_range(0..sizes.len());
            (view, rng.gen_range(0..sizes[view]))
        })
        .collect();
    draws.sort_unstable();
    let mut grouped: Vec<(usize, Vec<(u32, u32)>)> = Vec::new();
    for (view, pixel) in draws {
        if grouped.last().is_none_or(|g| g.0 != view) {
            grouped.push((view, Vec::new()));
        }
        let pixels = &mut grouped.last_mut().expect("pushed above").1;
        match pixels.last_mut() {
            Some((p, n)) if *p == pixel => *n += 1,
            _ => pixels.push((pixel, 1)),
        }
    }
    grouped
}

/// The views of iteration `iteration`: consecutive slots of a sequence of epochs, each epoch a
/// fresh permutation of all views, so every view is used once per epoch.
pub fn batch(views: usize, size: u32, seed: u64, iteration: u64) -> Vec<usize> {
    let n = views as u64;
    (0..u64::from(size))
        .map(|k| {
            let slot = iteration * u64::from(size) + k;
            let mut order: Vec<usize> = (0..views).collect();
            order.shuffle(&mut pixel_rng(seed, slot / n, u64::MAX));
            order[(slot % n) as usize]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_use_every_view_once_per_epoch() {
        let (views, size) = (6, 4);
        let slots: Vec<usize> = (0..3).flat_map(|i| batch(views, size, 7, i)).collect();
        // 12 slots = two epochs of 6 views.
        for epoch in slots.chunks(views) {
            let mut sorted = epoch.to_vec();
            sorted.sort();
            assert_eq!(sorted, (0..views).collect::<Vec<_>>());
        }
        assert_ne!(slots[..6], slots[6..], "each epoch is reshuffled");
        assert_eq!(batch(views, size, 7, 1), batch(views, size, 7, 1));
    }

    /// Every draw is counted once, in a view that has the pixel, and views are drawn uniformly
    /// whatever their size (a pixel of a small view is more likely than one of a large view).
    #[test]
    fn pixel_batches_draw_a_uniform_view_then_a_uniform_pixel() {
        let sizes = [16, 4096];
        let mut per_view = [0u32; 2];
        for iteration in 0..50 {
            let drawn = pixel_batch(&sizes, 1000, 3, iteration);
            let total: u32 = drawn.iter().flat_map(|g| g.1.iter().map(|d| d.1)).sum();
            assert_eq!(total, 1000);
            for (view, pixels) in &drawn {
                assert!(pixels.windows(2).all(|w| w[0].0 < w[1].0), "sorted, merged");
                assert!(pixels.iter().all(|&(p, _)| p < sizes[*view]));
                per_view[*view] += pixels.iter().map(|d| d.1).sum::<u32>();
            }
        }
        // 50,000 draws: each view's share within 5 standard errors (±112) of 25,000.
        assert!(per_view[0].abs_diff(25_000) < 560, "{per_view:?}");
    }
}
