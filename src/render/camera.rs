//! A pinhole camera: a frame in the world and intrinsics in pixels (focal lengths and principal
//! point), as calibrated cameras (COLMAP, OpenCV, NeRF's `transforms.json`) describe them. The
//! usual horizontal field of view is the case fx = fy = width / (2·tan(fov/2)) with the principal
//! point at the image centre.

use glam::Vec3;

/// Pinhole intrinsics in pixels; (0, 0) is the top-left corner of the image, so a centred principal
/// point is (width/2, height/2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
}

impl Intrinsics {
    /// Square pixels, a centred principal point and a horizontal field of view of `fov_deg`.
    pub fn from_fov(fov_deg: f32, width: u32, height: u32) -> Self {
        let focal = width as f32 / (2.0 * (fov_deg.to_radians() * 0.5).tan());
        Intrinsics {
            fx: focal,
            fy: focal,
            cx: width as f32 * 0.5,
            cy: height as f32 * 0.5,
        }
    }
}

#[derive(Debug, Clone, Copy)]
pub struct Camera {
    pub position: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    intrinsics: Intrinsics,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// A camera at `position` looking at `target`: `position != target` and `up` not parallel to
    /// the view direction (checked by the scene).
    pub fn new(
        position: Vec3,
        target: Vec3,
        up: Vec3,
        fov_deg: f32,
        width: u32,
        height: u32,
    ) -> Self {
        Camera::looking(
            position,
            (target - position).normalize(),
            up,
            Intrinsics::from_fov(fov_deg, width, height),
            width,
            height,
        )
    }

    /// A camera at `position` looking along the unit vector `forward`, with `up` independent of it
    /// (the image's up is `up` made orthogonal to `forward`). Built from a direction rather than a
    /// target, so that a camera far from the origin keeps its direction exactly.
    pub fn looking(
        position: Vec3,
        forward: Vec3,
        up: Vec3,
        intrinsics: Intrinsics,
        width: u32,
        height: u32,
    ) -> Self {
        let right = forward.cross(up).normalize();
        let up = right.cross(forward);
        Camera {
            position,
            forward,
            right,
            up,
            intrinsics,
            width,
            height,
        }
    }

    pub fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }

    /// Unit direction through image position (x, y) in pixels, (0, 0) the top-left corner.
    #[inline]
    pub fn direction(&self, x: f32, y: f32) -> Vec3 {
        let k = &self.intrinsics;
        let sx = (x - k.cx) / k.fx;
        let sy = (k.cy - y) / k.fy;
        (self.forward + self.right * sx + self.up * sy).normalize()
    }

    /// The image position (pixels, (0, 0) the top-left corner) at which `point` is seen, as
    /// `direction` maps positions to rays; `None` for a point not in front of the camera.
    pub fn project(&self, point: Vec3) -> Option<(f32, f32)> {
        let q = point - self.position;
        let depth = q.dot(self.forward);
        if depth.is_nan() || depth <= 0.0 {
            return None;
        }
        let k = &self.intrinsics;
        Some((
            k.cx + q.dot(self.right) / depth * k.fx,
            k.cy - q.dot(self.up) / depth * k.fy,
        ))
    }

    /// The width of one pixel's footprint at the depth of `point` (world units): how finely the
    /// view samples a medium there.
    pub fn pixel_footprint(&self, point: Vec3) -> f32 {
        let depth = (point - self.position).dot(self.forward).abs();
        depth / self.intrinsics.fx
    }

    /// The same view at another resolution: the image plane's extent is kept, each axis scaled by
    /// its own factor.
    pub fn with_resolution(&self, width: u32, height: u32) -> Camera {
        let (sx, sy) = (
            width as f32 / self.width as f32,
            height as f32 / self.height as f32,
        );
        let k = self.intrinsics;
        Camera {
            intrinsics: Intrinsics {
                fx: k.fx * sx,
                fy: k.fy * sy,
                cx: k.cx * sx,
                cy: k.cy * sy,
            },
            width,
            height,
            ..*self
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `project` inverts `direction`: a point along the ray through (x, y) is seen at (x, y), for a
    /// centred camera and for one with non-square pixels and an off-centre principal point.
    #[test]
    fn projection_inverts_the_rays() {
        let centred = Camera::new(Vec3::new(3.0, 1.0, 9.0), Vec3::ZERO, Vec3::Y, 40.0, 64, 48);
        let skewed = Camera::looking(
            Vec3::new(-2.0, 5.0, 1.0),
            Vec3::new(0.6, -0.8, 0.0),
            Vec3::Z,
            Intrinsics {
                fx: 70.0,
                fy: 55.0,
                cx: 20.0,
                cy: 30.5,
            },
            64,
            48,
        );
        for camera in [centred, skewed] {
            for (x, y) in [(0.5, 0.5), (63.2, 10.0), (31.0, 47.9), (7.25, 30.5)] {
                let point = camera.position + camera.direction(x, y) * 12.5;
                let (px, py) = camera.project(point).unwrap();
                assert!(
                    (px - x).abs() < 1e-3 && (py - y).abs() < 1e-3,
                    "{x},{y} → {px},{py}"
                );
            }
            assert!(camera.project(camera.position - camera.forward).is_none());
        }
        // The principal point is where the camera looks; fy sets the vertical angle per pixel.
        assert!((skewed.direction(20.0, 30.5) - Vec3::new(0.6, -0.8, 0.0)).length() < 1e-6);
        let d = skewed.direction(20.0, 30.5 - 55.0);
        assert!((d.dot(Vec3::Z) - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
    }

    #[test]
    fn a_field_of_view_is_a_centred_square_pixel_pinhole() {
        let camera = Camera::new(Vec3::new(0.0, 0.0, 5.0), Vec3::ZERO, Vec3::Y, 60.0, 40, 20);
        let edge = camera.direction(40.0, 10.0);
        assert!((edge.x.atan2(-edge.z).to_degrees() - 30.0).abs() < 1e-4);
        let half = camera.with_resolution(20, 10);
        assert_eq!(half.direction(20.0, 0.0), camera.direction(40.0, 0.0));
    }
}
