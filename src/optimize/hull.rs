//! The start's visual hull. A training pixel that shows only the background (what the scene
//! without the unknown shows there: the environment) says that nothing along its ray scatters or
//! absorbs, so a constant start is cleared in every first-level voxel that some view sees through
//! entirely. Without it the start fills the unknown's whole box, and the images clear the density
//! far from the volume only slowly (it is faint there, and Adam's steps on faint gradients are
//! small): the smoke plume started from a constant of optical depth 7.5 kept 0.1 of the start's
//! density more than 8 voxels out after 1000 iterations.
//!
//! Cleared voxels stay part of the unknown: where the images' gradient asks for density there
//! (smoke too faint to tell from the background), the steps bring it back.

use glam::{IVec3, Vec3};
use rayon::prelude::*;

use crate::optimize::targets::{mean_square, View};
use crate::render::camera::Camera;
use crate::render::lights::Lights;
use crate::volume::brickmap::corner;
use crate::volume::transform::IndexTransform;

/// A pixel is background when each channel is within this share of the targets' brightness
/// (`background_scale`) of the environment: rendered targets show the environment exactly there;
/// a photograph's noise and smoke this faint are about this small.
pub const BACKGROUND_TOLERANCE: f64 = 0.01;

/// The targets' brightness the background tolerance is a share of: their RMS channel value √P,
/// with every channel clipped at ten times the 99th percentile of the channels that are not 0.
/// Where no pixel stands out that far (the usual case) it is √P to the bit; a few hot pixels (a
/// firefly, the sun in a photograph's sky) would otherwise raise the tolerance past the medium
/// itself, and a view would clear the start where the medium is. (Black channels are left out
/// of the percentile: a small medium on a black ground would otherwise clip everything to 0.)
pub fn background_scale(views: &[View]) -> f64 {
    // The percentile of at most 2²⁰ channels, evenly strided: the clip needs no more, and a copy
    // of every channel would add half again to what 100 views of 800² hold.
    let total: usize = views.iter().map(|v| 3 * v.target.pixels.len()).sum();
    let mut channels: Vec<f32> = (views.iter())
        .flat_map(|v| v.target.pixels.iter().flat_map(|c| c.to_array()))
        .step_by(total.div_ceil(1 << 20).max(1))
        .filter(|c| c.is_finite() && *c != 0.0)
        .collect();
    if channels.is_empty() {
        return 0.0;
    }
    let rank = (channels.len() - 1) * 99 / 100;
    let percentile = *channels.select_nth_unstable_by(rank, f32::total_cmp).1;
    mean_square(views, 10.0 * percentile.abs()).sqrt()
}

/// Environment samples per pixel side for the background a pixel averages.
const BACKGROUND_SAMPLES: u32 = 4;

/// The first level's voxels that some training view sees through.
pub struct Hull {
    lo: IVec3,
    size: IVec3,
    seen_through: Vec<bool>,
}

impl Hull {
    /// The hull of `views` (lit by `light_sets`) over the voxels `lo..=hi` of the first level,
    /// placed by `transform`; `tolerance` is in pixel values.
    pub fn of(
        (lo, hi): (IVec3, IVec3),
        transform: &IndexTransform,
        views: &[View],
        light_sets: &[Lights],
        tolerance: f32,
    ) -> Hull {
        let backgrounds: Vec<Vec<bool>> = views
            .par_iter()
            .map(|view| background_pixels(view, &light_sets[view.light_set], tolerance))
            .collect();
        let size = hi - lo + 1;
        let seen_through = (0..size.x * size.y * size.z)
            .into_par_iter()
            .map(|i| {
                let v = lo + IVec3::new(i % size.x, i / size.x % size.y, i / (size.x * size.y));
                let corners = std::array::from_fn(|k| {
                    transform.point_to_world(v.as_vec3() - 0.5 + corner(k).as_vec3())
                });
                let through = |(view, background): (&View, &Vec<bool>)| {
                    sees_only_background(&view.camera, &corners, background)
                };
                views.iter().zip(&backgrounds).any(through)
            })
            .collect();
        Hull {
            lo,
            size,
            seen_through,
        }
    }

    /// Whether some view sees through first-level voxel `v`.
    pub fn is_seen_through(&self, v: IVec3) -> bool {
        let local = v - self.lo;
        if local.cmplt(IVec3::ZERO).any() || local.cmpge(self.size).any() {
            return false;
        }
        let (x, y, z) = (local.x, local.y, local.z);
        self.seen_through[(x + self.size.x * (y + self.size.y * z)) as usize]
    }

    /// How many first-level voxels some view sees through.
    pub fn seen_through_count(&self) -> usize {
        self.seen_through.iter().filter(|&&s| s).count()
    }
}

/// Per pixel of `view`, row by row: whether its target is the environment it would show with no
/// medium (averaged over the pixel, as the target is).
fn background_pixels(view: &View, lights: &Lights, tolerance: f32) -> Vec<bool> {
    let camera = &view.camera;
    let n = BACKGROUND_SAMPLES;
    let target = &view.target.pixels;
    (0..camera.height)
        .flat_map(|y| (0..camera.width).map(move |x| (x, y)))
        .zip(target)
        .map(|((x, y), &seen)| {
            let mut background = Vec3::ZERO;
            for (i, j) in (0..n).flat_map(|i| (0..n).map(move |j| (i, j))) {
                let (u, v) = ((i as f32 + 0.5) / n as f32, (j as f32 + 0.5) / n as f32);
                let dir = camera.direction(x as f32 + u, y as f32 + v);
                background += lights.environment.eval(dir);
            }
            background /= (n * n) as f32;
            (seen - background).abs().max_element() <= tolerance
        })
        .collect()
}

/// Whether the box with `corners` lies in front of `camera`, wholly inside its image, and every
/// pixel it covers is `background`.
fn sees_only_background(camera: &Camera, corners: &[Vec3; 8], background: &[bool]) -> bool {
    let (mut min, mut max) = (
        (f32::INFINITY, f32::INFINITY),
        (f32::NEG_INFINITY, f32::NEG_INFINITY),
    );
    for &corner in corners {
        let Some((x, y)) = camera.project(corner) else {
            return false;
        };
        min = (min.0.min(x), min.1.min(y));
        max = (max.0.max(x), max.1.max(y));
    }
    let (w, h) = (camera.width as f32, camera.height as f32);
    if !(min.0 >= 0.0 && min.1 >= 0.0 && max.0 <= w && max.1 <= h) {
        return false;
    }
    // The pixels the box covers, at least one.
    let first = |m: f32, n: u32| (m.floor() as u32).min(n - 1);
    let (x0, y0) = (first(min.0, camera.width), first(min.1, camera.height));
    let (x1, y1) = (
        (max.0.ceil() as u32).max(x0 + 1),
        (max.1.ceil() as u32).max(y0 + 1),
    );
    (y0..y1).all(|y| (x0..x1).all(|x| background[(y * camera.width + x) as usize]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::images::RgbImage;

    const SKY: f32 = 0.5;

    /// A view of a ball of radius `r` at the origin: pixels whose ray passes within r (plus the
    /// pixel's own width) show `SKY + 0.1`, the others the sky.
    fn view_of_ball(position: Vec3, r: f32) -> View {
        let camera = Camera::new(position, Vec3::ZERO, Vec3::Y, 60.0, 48, 40);
        // Half a pixel's diagonal at the ball, a little more: every pixel the ball covers in part.
        let margin = 0.75 * camera.pixel_footprint(Vec3::ZERO);
        let pixels = (0..camera.height)
            .flat_map(|y| (0..camera.width).map(move |x| (x, y)))
            .map(|(x, y)| {
                let d = camera.direction(x as f32 + 0.5, y as f32 + 0.5);
                let closest = (-position).dot(d).max(0.0);
                let miss = (position + d * closest).length();
                Vec3::splat(if miss <= r + margin { SKY + 0.1 } else { SKY })
            })
            .collect();
        let target = RgbImage {
            width: camera.width,
            height: camera.height,
            pixels,
        };
        View {
            camera,
            light_set: 0,
            relit: false,
            target,
            alpha: None,
            background: None,
            capture: 0,
        }
    }

    /// Three views of a ball clear voxels around it and none that the ball touches; a voxel
    /// no view sees wholly is kept.
    #[test]
    fn views_clear_what_they_see_through_and_nothing_of_the_ball() {
        let mut sky = Lights::default();
        sky.environment.constant = Vec3::splat(SKY);
        let views: Vec<View> = [
            Vec3::new(0.0, 0.0, 40.0),
            Vec3::new(40.0, 0.0, 0.0),
            Vec3::new(0.0, 40.0, 0.1),
        ]
        .into_iter()
        .map(|p| view_of_ball(p, 3.0))
        .collect();
        // Voxels 2 units wide (a few pixels) over [-9, 9]³.
        let transform = IndexTransform::uniform(2.0, glam::DVec3::ZERO);
        let voxels = (IVec3::splat(-4), IVec3::splat(4));
        let hull = Hull::of(voxels, &transform, &views, &[sky.clone()], 0.01);
        for x in -4..=4 {
            for y in -4..=4 {
                for z in -4..=4 {
                    let v = IVec3::new(x, y, z);
                    // The voxel's nearest point to the ball's centre.
                    let near = (2.0 * v.as_vec3().abs() - 1.0).max(Vec3::ZERO).length();
                    if near <= 3.0 {
                        assert!(!hull.is_seen_through(v), "{v} touches the ball");
                    }
                    // Farther than the ball's shadow can reach in the views, plus a pixel (every
                    // voxel is wholly inside every image).
                    if 2.0 * v.as_vec3().abs().min_element() > 5.0 {
                        assert!(hull.is_seen_through(v), "{v} is seen through");
                    }
                }
            }
        }
        assert!(
            hull.seen_through_count() > 9 * 9 * 9 / 2,
            "{}",
            hull.seen_through_count()
        );
        // A voxel outside every view's image is kept: one camera looking away.
        let away = View {
            camera: Camera::new(
                Vec3::new(0.0, 0.0, 40.0),
                Vec3::new(0.0, 0.0, 80.0),
                Vec3::Y,
                30.0,
                48,
                40,
            ),
            ..views[0].clone()
        };
        let none = Hull::of(voxels, &transform, &[away], &[sky.clone()], 0.01);
        assert_eq!(none.seen_through_count(), 0);
        // The tolerance: a target 0.005 off the sky is background at 0.01, not at 0.001.
        let mut faint = views[0].clone();
        faint
            .target
            .pixels
            .iter_mut()
            .for_each(|p| *p = Vec3::splat(SKY + 0.005));
        assert!(background_pixels(&faint, &sky, 0.01).iter().all(|&b| b));
        assert!(background_pixels(&faint, &sky, 0.001).iter().all(|&b| !b));
    }

    /// A small medium on a black ground (most channels 0) keeps a tolerance: the clip is taken
    /// from the lit channels, and √P is the unclipped RMS where nothing stands out.
    #[test]
    fn the_background_scale_of_a_small_medium_on_black_is_its_rms() {
        let mut view = view_of_ball(Vec3::new(0.0, 0.0, 40.0), 0.5);
        for p in &mut view.target.pixels {
            *p = if p.x > SKY { Vec3::ONE } else { Vec3::ZERO };
        }
        let lit = view.target.pixels.iter().filter(|p| p.x > 0.0).count();
        let n = view.target.pixels.len();
        assert!(lit > 0 && lit * 100 < n, "{lit} of {n}");
        let scale = background_scale(std::slice::from_ref(&view));
        assert_eq!(scale, (lit as f64 / n as f64).sqrt());
    }
}
