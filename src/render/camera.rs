//! A pinhole camera with a horizontal field of view.

use glam::Vec3;

#[derive(Debug, Clone, Copy)]
pub struct Camera {
    pub position: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    /// tan(fov/2) horizontally and vertically.
    tan_half: (f32, f32),
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// `position != target` and `up` not parallel to the view direction (checked by the scene).
    pub fn new(
        position: Vec3,
        target: Vec3,
        up: Vec3,
        fov_deg: f32,
        width: u32,
        height: u32,
    ) -> Self {
        let forward = (target - position).normalize();
        let right = forward.cross(up).normalize();
        let up = right.cross(forward);
        let tan_x = (fov_deg.to_radians() * 0.5).tan();
        Camera {
            position,
            forward,
            right,
            up,
            tan_half: (tan_x, tan_x * height as f32 / width as f32),
            width,
            height,
        }
    }

    /// Unit direction through image position (x, y) in pixels, (0, 0) the top-left corner.
    #[inline]
    pub fn direction(&self, x: f32, y: f32) -> Vec3 {
        let sx = (2.0 * x / self.width as f32 - 1.0) * self.tan_half.0;
        let sy = (1.0 - 2.0 * y / self.height as f32) * self.tan_half.1;
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
        let sx = q.dot(self.right) / depth / self.tan_half.0;
        let sy = q.dot(self.up) / depth / self.tan_half.1;
        Some((
            (sx + 1.0) * 0.5 * self.width as f32,
            (1.0 - sy) * 0.5 * self.height as f32,
        ))
    }

    /// The width of one pixel's footprint at the depth of `point` (world units): how finely the
    /// view samples a medium there.
    pub fn pixel_footprint(&self, point: Vec3) -> f32 {
        let depth = (point - self.position).dot(self.forward).abs();
        depth * 2.0 * self.tan_half.0 / self.width as f32
    }

    /// The same view at another resolution (the horizontal field of view is kept).
    pub fn with_resolution(&self, width: u32, height: u32) -> Camera {
        Camera {
            tan_half: (
                self.tan_half.0,
                self.tan_half.0 * height as f32 / width as f32,
            ),
            width,
            height,
            ..*self
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `project` inverts `direction`: a point along the ray through (x, y) is seen at (x, y).
    #[test]
    fn projection_inverts_the_rays() {
        let camera = Camera::new(Vec3::new(3.0, 1.0, 9.0), Vec3::ZERO, Vec3::Y, 40.0, 64, 48);
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
}
