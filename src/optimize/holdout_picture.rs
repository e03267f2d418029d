//! The held-out picture a checkpoint writes (target | render | difference ×4, a row per held-out
//! view) and the panels it is made of, sized for a person to look at whatever the views' size: a
//! 24² view enlarged, an 800² one reduced, a strip one pixel high not made 128 times its width,
//! and at most `MAX_SHOWN_VIEWS` rows however many views a set holds.

use std::path::Path;

use crate::io::images::{self, RgbImage};
use crate::optimize::problem::View;
use anyhow::Result;

/// Panels lower than this are enlarged (pixel copies), up to `MAX_PANEL` wide.
const MIN_PANEL: u32 = 128;
/// Panels wider or higher than this are reduced (the mean of blocks of pixels).
const MAX_PANEL: u32 = 384;
/// The most held-out views a picture shows, spread evenly over the list (the first and the last
/// among them): a hundred 800² views would otherwise make a picture of gigabytes.
const MAX_SHOWN_VIEWS: usize = 16;

/// One row per held-out view (`shown_views` of them): target | render | |render − target| × 4,
/// tonemapped as the scene's PNGs are (`display_exposure`, render.exposure), each panel sized by
/// `panel`. Each target is taken at its capture's exposure (`exposures`, fitted or 1), as the
/// evaluation compares it.
pub fn write_holdout_picture(
    path: &Path,
    views: &[View],
    renders: &[RgbImage],
    exposures: &[f32],
    display_exposure: f32,
) -> Result<()> {
    let rows: Vec<RgbImage> = shown_views(views.len())
        .into_iter()
        .map(|i| {
            let (view, image) = (&views[i], &renders[i]);
            let t = view.target_at(exposures[view.capture]);
            let mut difference = image.clone();
            for (d, &t) in difference.pixels.iter_mut().zip(&t.pixels) {
                *d = (*d - t).abs() * 4.0;
            }
            side_by_side(&[&panel(&t), &panel(image), &panel(&difference)])
        })
        .collect();
    images::write_png(
        path,
        &stacked(&rows),
        display_exposure.max(f32::MIN_POSITIVE),
    )
}

/// The indices of the views a picture of `count` shows: all of them, or `MAX_SHOWN_VIEWS` spread
/// evenly from the first to the last.
fn shown_views(count: usize) -> Vec<usize> {
    if count <= MAX_SHOWN_VIEWS {
        return (0..count).collect();
    }
    (0..MAX_SHOWN_VIEWS)
        .map(|i| i * (count - 1) / (MAX_SHOWN_VIEWS - 1))
        .collect()
}

/// `image` at a size to look at: reduced by the smallest whole factor that brings both sides to
/// at most `MAX_PANEL`, or else enlarged by the largest that keeps it within `MIN_PANEL` high and
/// `MAX_PANEL` wide (at least 1).
pub fn panel(image: &RgbImage) -> RgbImage {
    let (width, height) = (image.width.max(1), image.height.max(1));
    let shrink = width.max(height).div_ceil(MAX_PANEL);
    if shrink > 1 {
        return reduced(image, shrink);
    }
    enlarged(image, (MIN_PANEL / height).min(MAX_PANEL / width).max(1))
}

/// Each pixel copied into an `f`×`f` block.
fn enlarged(image: &RgbImage, f: u32) -> RgbImage {
    let mut out = RgbImage::new(image.width * f, image.height * f);
    for y in 0..out.height {
        for x in 0..out.width {
            out.pixels[(y * out.width + x) as usize] =
                image.pixels[((y / f) * image.width + x / f) as usize];
        }
    }
    out
}

/// The mean of each `f`×`f` block (of what is left of one at the right and bottom edges).
fn reduced(image: &RgbImage, f: u32) -> RgbImage {
    let mut out = RgbImage::new(image.width.div_ceil(f), image.height.div_ceil(f));
    let mut counts = vec![0u32; out.pixels.len()];
    for y in 0..image.height {
        for x in 0..image.width {
            let o = ((y / f) * out.width + x / f) as usize;
            out.pixels[o] += image.pixels[(y * image.width + x) as usize];
            counts[o] += 1;
        }
    }
    for (p, &n) in out.pixels.iter_mut().zip(&counts) {
        *p /= n.max(1) as f32;
    }
    out
}

/// Images one above the other, left-aligned.
fn stacked(images: &[RgbImage]) -> RgbImage {
    let width = images.iter().map(|i| i.width).max().unwrap_or(1).max(1);
    let height = images.iter().map(|i| i.height).sum::<u32>().max(1);
    let mut out = RgbImage::new(width, height);
    let mut top = 0;
    for image in images {
        for y in 0..image.height {
            let row = ((top + y) * width) as usize;
            let source = (y * image.width) as usize;
            out.pixels[row..row + image.width as usize]
                .copy_from_slice(&image.pixels[source..source + image.width as usize]);
        }
        top += image.height;
    }
    out
}

/// Images side by side, top-aligned.
pub fn side_by_side(images: &[&RgbImage]) -> RgbImage {
    let width = images.iter().map(|i| i.width).sum::<u32>().max(1);
    let height = images.iter().map(|i| i.height).max().unwrap_or(1);
    let mut out = RgbImage::new(width, height);
    let mut left = 0;
    for image in images {
        for y in 0..image.height {
            for x in 0..image.width {
                out.pixels[(y * width + left + x) as usize] =
                    image.pixels[(y * image.width + x) as usize];
            }
        }
        left += image.width;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera::Camera;
    use glam::Vec3;

    /// A uniform image of `width`×`height` pixels of value `v`.
    fn uniform(width: u32, height: u32, v: f32) -> RgbImage {
        RgbImage {
            width,
            height,
            pixels: vec![Vec3::splat(v); (width * height) as usize],
        }
    }

    /// A held-out view of `width`×`height` pixels whose target is `target`, lit by capture 1.
    fn view(width: u32, height: u32, target: f32) -> View {
        View {
            camera: Camera::new(Vec3::Z, Vec3::ZERO, Vec3::Y, 40.0, width, height),
            light_set: 0,
            relit: false,
            target: uniform(width, height, target),
            alpha: None,
            background: Some(uniform(width, height, 0.25)),
            capture: 1,
        }
    }

    /// A held-out picture shows each target at its capture's fitted exposure, as the evaluation
    /// compares it: a render that matches the target of a capture twice as bright as the scene
    /// says has no difference. (It took the scene's display exposure: a difference where there
    /// was none.)
    #[test]
    fn the_holdout_picture_compares_at_each_captures_exposure() {
        let view = view(1, 1, 0.5);
        let render = view.target_at(2.0).into_owned();
        assert_eq!(render.pixels[0], Vec3::splat(0.75));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("holdout.png");
        write_holdout_picture(&path, &[view], &[render], &[1.0, 2.0], 1.0).unwrap();
        let picture = images::read_rgb(&path).unwrap();
        assert_eq!((picture.width, picture.height), (3 * MIN_PANEL, MIN_PANEL));
        let at =
            |panel: u32| picture.pixels[(64 * picture.width + panel * MIN_PANEL + 64) as usize];
        assert!(
            (at(0) - Vec3::splat(0.75)).abs().max_element() < 0.01,
            "target {}",
            at(0)
        );
        assert!(at(2).max_element() < 0.01, "difference {}", at(2));
    }

    /// Panels of every shape come out between the limits: a strip one pixel high was enlarged
    /// 128 times in both directions (a 2,048-pixel strip made a picture of 786,432 × 128, 3.7
    /// GB to build), and a large view was copied whole.
    #[test]
    fn panels_stay_within_the_limits() {
        for (w, h, want) in [
            (8, 8, (128, 128)),
            (96, 96, (96, 96)),
            (64, 32, (256, 128)),
            (2048, 1, (342, 1)),
            (800, 800, (267, 267)),
            (100_000, 3, (384, 1)),
        ] {
            let p = panel(&uniform(w, h, 0.5));
            assert_eq!((p.width, p.height), want, "{w}×{h}");
            assert!(p.width <= MAX_PANEL && p.height <= MAX_PANEL);
        }
        // A reduced panel keeps the mean of its blocks, the partial ones at the edges too.
        let mut ramp = uniform(5, 1, 0.0);
        for (x, p) in ramp.pixels.iter_mut().enumerate() {
            *p = Vec3::splat(x as f32);
        }
        let r = reduced(&ramp, 2);
        let values: Vec<f32> = r.pixels.iter().map(|p| p.x).collect();
        assert_eq!(values, [0.5, 2.5, 4.0]);
    }

    /// Many held-out views show `MAX_SHOWN_VIEWS` of them, the first and the last included, each
    /// once.
    #[test]
    fn a_picture_shows_at_most_max_views() {
        assert_eq!(shown_views(3), [0, 1, 2]);
        for count in [MAX_SHOWN_VIEWS + 1, 100, 200] {
            let shown = shown_views(count);
            assert_eq!(shown.len(), MAX_SHOWN_VIEWS);
            assert_eq!((shown[0], shown[MAX_SHOWN_VIEWS - 1]), (0, count - 1));
            assert!(shown.windows(2).all(|w| w[0] < w[1]), "{shown:?}");
        }
        let views: Vec<View> = (0..40).map(|_| view(8, 8, 0.5)).collect();
        let renders: Vec<RgbImage> = views.iter().map(|v| v.target.clone()).collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("holdout.png");
        write_holdout_picture(&path, &views, &renders, &[1.0, 1.0], 1.0).unwrap();
        let picture = images::read_rgb(&path).unwrap();
        assert_eq!(picture.height, MAX_SHOWN_VIEWS as u32 * MIN_PANEL);
    }
}
