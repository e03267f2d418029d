//! Pictures from elsewhere as targets: a picture with alpha is what a renderer saw of the medium
//! alone (colour premultiplied, alpha its coverage); composited over the scene's background it is
//! what the camera would have seen, which is what volgrad renders.

use glam::Vec3;

use crate::io::images::{Picture, RgbImage};
use crate::render::camera::Camera;
use crate::render::lights::Environment;

/// The picture as the camera saw it in front of `background`: premultiplied colour plus
/// (1 − alpha) × the environment's radiance along each pixel's central ray (`background_seen`).
/// Without alpha, the colour as it is.
pub fn over(picture: &Picture, background: &Environment, camera: &Camera) -> RgbImage {
    let mut seen = picture.color.clone();
    if let Some(behind) = background_seen(picture, background, camera) {
        (seen.pixels.iter_mut())
            .zip(&behind.pixels)
            .for_each(|(c, b)| *c += *b);
    }
    seen
}

/// What of `background` the camera saw through the medium: (1 − alpha) × the environment's
/// radiance along each pixel's central ray; `None` without alpha. A capture's exposure scales
/// it as it scales the medium's colour (`View::target_at`).
pub fn background_seen(
    picture: &Picture,
    background: &Environment,
    camera: &Camera,
) -> Option<RgbImage> {
    let alpha = picture.alpha.as_ref()?;
    let width = picture.color.width as usize;
    let pixels = (alpha.iter().enumerate())
        .map(|(i, &a)| {
            if a >= 1.0 {
                return Vec3::ZERO;
            }
            let (x, y) = ((i % width) as f32 + 0.5, (i / width) as f32 + 0.5);
            (1.0 - a) * background.eval(camera.direction(x, y))
        })
        .collect();
    Some(RgbImage {
        pixels,
        ..picture.color.clone()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::images::Decoding;

    /// Under a constant sky every pixel gains (1 − alpha) × the sky; opaque ones keep their colour.
    #[test]
    fn a_picture_with_alpha_is_composited_over_the_sky() {
        let camera = Camera::new(Vec3::new(0.0, 0.0, 5.0), Vec3::ZERO, Vec3::Y, 40.0, 2, 1);
        let picture = Picture {
            color: RgbImage {
                width: 2,
                height: 1,
                pixels: vec![Vec3::new(0.1, 0.2, 0.3), Vec3::splat(0.4)],
            },
            alpha: Some(vec![0.25, 1.0]),
            decoded: Decoding::Srgb,
        };
        let sky = Environment {
            constant: Vec3::new(1.0, 2.0, 4.0),
            map: None,
        };
        let seen = over(&picture, &sky, &camera);
        assert!((seen.pixels[0] - Vec3::new(0.85, 1.7, 3.3)).length() < 1e-6);
        assert_eq!(seen.pixels[1], Vec3::splat(0.4));
        let opaque = Picture {
            alpha: None,
            ..picture
        };
        assert_eq!(over(&opaque, &sky, &camera), opaque.color);
    }
}
