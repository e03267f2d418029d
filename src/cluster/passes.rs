//! Gradient passes run by every rank together: each traces its share of the pixels, and the
//! quanta are summed (`sparse_sum`), so every rank gets the gradient one process computes, bit for
//! bit. The adjoint image's primal render is shared the same way (`images`).

use anyhow::Result;

use crate::cluster::images::{render_shared, sum_stats};
use crate::cluster::sparse_sum::sum_bands_over_ranks;
use crate::cluster::Cluster;
use crate::gradient::loss::Loss;
use crate::gradient::objective::{adjoint_image, check_target, AdjointImage};
use crate::gradient::passes::{gradient, gradient_of, GradOptions, GradientRun};
use crate::io::images::RgbImage;
use crate::render::image::RenderOptions;
use crate::render::pixel_set::PixelSet;
use crate::render::scene::Scene;

/// `objective::adjoint_image`, its primal render shared by the ranks.
pub fn adjoint_shared(
    cluster: &Cluster,
    scene: &Scene,
    loss: Loss,
    target: Option<&RgbImage>,
    options: &GradOptions,
) -> Result<AdjointImage> {
    let (Some(target), true) = (target, cluster.size() > 1 && loss.needs_target()) else {
        return adjoint_image(scene, loss, target, options);
    };
    check_target(target, scene)?;
    let render = RenderOptions {
        spp: options.spp,
        seed: options.seed,
        max_depth: options.adjoint.max_depth,
        progress: options.progress,
    };
    let primal = render_shared(cluster, scene, &render).0;
    Ok(AdjointImage {
        delta: loss.adjoint(&primal, Some(target)),
        loss: Some(loss.evaluate(&primal, Some(target))),
    })
}

/// `passes::gradient`, its pixels shared by the ranks. The image holds this rank's pixels only.
pub fn gradient_shared(
    cluster: &Cluster,
    scene: &Scene,
    adjoint: &[glam::Vec3],
    options: &GradOptions,
) -> GradientRun {
    if cluster.size() == 1 {
        return gradient(scene, adjoint, options);
    }
    let pixels = scene.camera.width * scene.camera.height;
    let set = PixelSet::share(pixels, cluster.rank(), cluster.size());
    let mut run = gradient_of(scene, adjoint, options, &set);
    run.gradient = sum_bands_over_ranks(cluster, run.gradient).0;
    sum_stats(cluster, &mut run.stats);
    run
}
