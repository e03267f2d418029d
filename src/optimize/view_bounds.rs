//! `[unknown] bounds = "views"`: the unknown's box from the cameras alone, for pictures that come
//! without a grid to take it from. The medium must be seen by every training view (a voxel some
//! view never sees is not pinned down by it), so the box is that of the region every camera sees:
//! the points in front of each camera that project inside its image. The visual-hull start then
//! carves it further where the views' background is known.

use anyhow::{bail, Result};
use glam::{DMat3, DVec3, Vec3};
use rayon::prelude::*;

use crate::render::camera::Camera;

/// Sample points per axis of the search box: the box found is accurate to about 1/SAMPLES of the
/// cameras' spread, and padded by that much.
const SAMPLES: usize = 96;

/// The box (min, max) around the region every camera sees.
pub fn seen_by_all(cameras: &[Camera]) -> Result<(DVec3, DVec3)> {
    if cameras.len() < 2 {
        bail!("unknown.bounds = \"views\" needs at least two training views to intersect what they see (got {})", cameras.len());
    }
    let centre = closest_to_axes(cameras)?;
    let radius = cameras
        .iter()
        .map(|c| (c.position.as_dvec3() - centre).length())
        .fold(0.0, f64::max);
    let (lo, step) = (centre - radius, 2.0 * radius / SAMPLES as f64);
    // Slices in parallel (thousands of views test up to 96³ points each); min and max do not
    // depend on the order they are taken in.
    let found = (0..SAMPLES)
        .into_par_iter()
        .filter_map(|z| {
            let mut slice: Option<(DVec3, DVec3)> = None;
            for i in 0..SAMPLES * SAMPLES {
                let (x, y) = (i % SAMPLES, i / SAMPLES);
                let p = lo + DVec3::new(x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5) * step;
                if cameras.iter().all(|c| sees(c, p.as_vec3())) {
                    slice = Some(slice.map_or((p, p), |(a, b)| (a.min(p), b.max(p))));
                }
            }
            slice
        })
        .reduce_with(|(a, b), (c, d)| (a.min(c), b.max(d)));
    match found {
        Some((a, b)) => Ok((a - step, b + step)),
        None => bail!(
            "unknown.bounds = \"views\": no point is seen by every training view (they do not look at one region); give the box, bounds = {{ min = [x, y, z], max = [x, y, z] }}"
        ),
    }
}

/// Whether `camera` sees `point`: in front of it, inside its image.
fn sees(camera: &Camera, point: Vec3) -> bool {
    camera.project(point).is_some_and(|(x, y)| {
        (0.0..=camera.width as f32).contains(&x) && (0.0..=camera.height as f32).contains(&y)
    })
}

/// The point closest, in the least-squares sense, to every camera's optical axis (the ray through
/// its principal point): where the cameras look.
fn closest_to_axes(cameras: &[Camera]) -> Result<DVec3> {
    // Σ (I − d dᵀ) p = Σ (I − d dᵀ) o over the axes o + t·d.
    let (mut a, mut b) = (DMat3::ZERO, DVec3::ZERO);
    for c in cameras {
        let k = c.intrinsics();
        let d = c.direction(k.cx, k.cy).as_dvec3();
        let projector = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += projector;
        b += projector * c.position.as_dvec3();
    }
    if a.determinant().abs() < 1e-9 * cameras.len().pow(3) as f64 {
        bail!("unknown.bounds = \"views\": the training views all look along one line, so where they meet is not known; give the box, bounds = {{ min = [x, y, z], max = [x, y, z] }}");
    }
    Ok(a.inverse() * b)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Four cameras at distance 10 around the origin, 30° fields of view, looking at the centre:
    /// every camera sees a cone of half-angle ~15° (the diagonal a little more), so what all see is
    /// a region of about ±10·tan 15° ≈ ±2.7 around the origin along each axis.
    #[test]
    fn cameras_around_a_point_bound_the_region_they_all_see() {
        let centre = Vec3::new(1.0, 2.0, -3.0);
        let cameras: Vec<Camera> = [
            Vec3::X,
            Vec3::Z,
            -Vec3::X,
            -Vec3::Z,
            Vec3::new(0.3, 0.9, 0.3),
        ]
        .iter()
        .map(|d| {
            let up = if d.y > 0.5 { Vec3::Z } else { Vec3::Y };
            Camera::new(centre + *d * 10.0, centre, up, 30.0, 32, 32)
        })
        .collect();
        let (lo, hi) = seen_by_all(&cameras).unwrap();
        let (lo, hi) = (lo.as_vec3() - centre, hi.as_vec3() - centre);
        for axis in 0..3 {
            assert!(lo[axis] < -1.5 && lo[axis] > -3.5, "{lo} {hi}");
            assert!(hi[axis] > 1.5 && hi[axis] < 3.5, "{lo} {hi}");
        }
        // Every corner region the box claims is seen, give or take the padding.
        let camera = cameras[0];
        assert!(sees(&camera, centre));
    }

    #[test]
    fn views_that_do_not_meet_are_refused() {
        let one = Camera::new(Vec3::new(0.0, 0.0, 10.0), Vec3::ZERO, Vec3::Y, 30.0, 8, 8);
        let e = seen_by_all(&[one]).unwrap_err().to_string();
        assert!(e.contains("at least two"), "{e}");
        let parallel = Camera::new(Vec3::new(0.0, 0.0, 20.0), Vec3::ZERO, Vec3::Y, 30.0, 8, 8);
        let e = seen_by_all(&[one, parallel]).unwrap_err().to_string();
        assert!(e.contains("one line"), "{e}");
        // Back to back: they look at opposite sides and see nothing in common.
        let away = Camera::new(
            Vec3::new(0.0, 0.0, -10.0),
            Vec3::new(0.0, 0.0, -20.0),
            Vec3::Y,
            30.0,
            8,
            8,
        );
        let side = Camera::new(
            Vec3::new(10.0, 0.0, 0.0),
            Vec3::new(20.0, 0.0, 0.0),
            Vec3::Y,
            30.0,
            8,
            8,
        );
        let e = seen_by_all(&[one, away, side]).unwrap_err().to_string();
        assert!(e.contains("no point"), "{e}");
    }
}
