//! What a gradient pass needs from a loss on images: a target image that fits the scene, and the
//! adjoint image δ = ∂loss/∂pixel. `grad` uses it once; an optimisation loop uses it every
//! iteration.

use anyhow::{bail, Result};
use glam::Vec3;

use crate::gradient::loss::Loss;
use crate::gradient::passes::GradOptions;
use crate::io::images::RgbImage;
use crate::render::image::{render, RenderOptions};
use crate::render::sampling::TARGET_SEED_SALT;
use crate::render::scene::Scene;

/// The render options of `target_scene`'s image that a loss compares against, at `spp` samples
/// per pixel. Its seed is derived from the gradient pass's `gradient_seed` but differs from it.
pub fn target_options(
    target_scene: &Scene,
    spp: u32,
    gradient_seed: u64,
    progress: bool,
) -> RenderOptions {
    RenderOptions {
        spp: spp.max(1),
        seed: gradient_seed ^ TARGET_SEED_SALT,
        max_depth: target_scene.settings.max_depth,
        progress,
    }
}

/// The render of `target_scene` that a loss compares against, in one process (`target_options`).
pub fn render_target(
    target_scene: &Scene,
    spp: u32,
    gradient_seed: u64,
    progress: bool,
) -> RgbImage {
    let options = target_options(target_scene, spp, gradient_seed, progress);
    render(target_scene, &options).0
}

/// An error unless `target` has the scene's resolution and only finite pixels.
pub fn check_target(target: &RgbImage, scene: &Scene) -> Result<()> {
    let (w, h) = (scene.camera.width, scene.camera.height);
    if (target.width, target.height) != (w, h) {
        bail!(
            "the target is {}×{} but the scene renders {w}×{h}",
            target.width,
            target.height
        );
    }
    if target.pixels.iter().any(|c| !c.is_finite()) {
        bail!("the target image has non-finite pixels");
    }
    Ok(())
}

/// The adjoint image of a loss, and the loss itself where it has a value worth reporting.
pub struct AdjointImage {
    /// δ = ∂loss/∂pixel, one per pixel.
    pub delta: Vec<Vec3>,
    /// The loss of the primal render (losses with a target only).
    pub loss: Option<f64>,
}

/// δ = ∂loss/∂pixel for the gradient pass `options`. Losses with a target take δ from a primal
/// render of its own (same spp and seed as the gradient pass, but `Pass::Forward` random streams),
/// so δ does not correlate with the gradient samples; `mean` needs no render (δ is constant).
pub fn adjoint_image(
    scene: &Scene,
    loss: Loss,
    target: Option<&RgbImage>,
    options: &GradOptions,
) -> Result<AdjointImage> {
    let (w, h) = (scene.camera.width, scene.camera.height);
    if !loss.needs_target() {
        return Ok(AdjointImage {
            delta: loss.adjoint(&RgbImage::new(w, h), None),
            loss: None,
        });
    }
    let Some(target) = target else {
        bail!("loss {loss} needs a target image");
    };
    check_target(target, scene)?;
    let primal = render(
        scene,
        &RenderOptions {
            spp: options.spp,
            seed: options.seed,
            max_depth: options.adjoint.max_depth,
            progress: options.progress,
        },
    )
    .0;
    Ok(AdjointImage {
        delta: loss.adjoint(&primal, Some(target)),
        loss: Some(loss.evaluate(&primal, Some(target))),
    })
}
