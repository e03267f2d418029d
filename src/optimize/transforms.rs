//! Camera sets as multi-view tools and Blender's NeRF exporters write them: `transforms.json` in
//! the NeRF / instant-ngp convention.
//!
//! - `camera_angle_x`: the horizontal field of view in radians (or `fl_x` with `w`, the focal length
//!   in pixels: fov = 2·atan(w / 2·fl_x)).
//! - `w`, `h`: the image size, at the top or per frame; without them the size of the frame's image.
//! - `frames[i].transform_matrix`: the camera-to-world matrix, rows of 4; its columns are the
//!   camera's right (+x), up (+y) and backward (+z) axes and its position: the camera looks down
//!   its −z axis (OpenGL's and Blender's camera convention). Positions are world units of the run
//!   (no `scale` or `offset` is applied: such a file is refused, rather than read in other units).
//! - `frames[i].file_path`: the frame's image, relative to the JSON file; without an extension
//!   (Blender's NeRF data sets) `.exr` and then `.png` are tried. Images are read as linear
//!   radiance, as every target is.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::{Mat4, Vec3, Vec4Swizzles};
use serde::Deserialize;

use crate::render::camera::Camera;

#[derive(Deserialize)]
struct TransformsFile {
    camera_angle_x: Option<f32>,
    fl_x: Option<f32>,
    w: Option<u32>,
    h: Option<u32>,
    scale: Option<serde_json::Value>,
    offset: Option<serde_json::Value>,
    frames: Vec<Frame>,
}

#[derive(Deserialize)]
struct Frame {
    file_path: Option<String>,
    transform_matrix: [[f32; 4]; 4],
    w: Option<u32>,
    h: Option<u32>,
}

/// A camera of a transforms file and its image, if it names one.
pub struct TransformsView {
    pub camera: Camera,
    pub image: Option<PathBuf>,
}

/// The cameras of `path` (errors name the file and the frame).
pub fn read(path: &Path) -> Result<Vec<TransformsView>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read '{}'", path.display()))?;
    let file: TransformsFile = serde_json::from_str(&text)
        .with_context(|| format!("'{}' is not a transforms.json", path.display()))?;
    if file.scale.is_some() || file.offset.is_some() {
        bail!(
            "'{}': `scale` and `offset` (instant-ngp's rescaling) are not applied; write the matrices in the run's world units and leave them out",
            path.display()
        );
    }
    let dir = path.parent().unwrap_or(Path::new("."));
    file.frames
        .iter()
        .enumerate()
        .map(|(i, frame)| {
            view(&file, frame, dir).with_context(|| format!("'{}': frames[{i}]", path.display()))
        })
        .collect()
}

fn view(file: &TransformsFile, frame: &Frame, dir: &Path) -> Result<TransformsView> {
    let image = frame
        .file_path
        .as_deref()
        .map(|name| image_path(dir, name))
        .transpose()?;
    let (width, height) = match (frame.w.or(file.w), frame.h.or(file.h), &image) {
        (Some(w), Some(h), _) => (w, h),
        (_, _, Some(image)) => {
            let pixels = crate::io::images::read_rgb(image)?;
            (pixels.width, pixels.height)
        }
        _ => bail!("no image and no `w`, `h`: the view's size is unknown"),
    };
    if width == 0 || height == 0 {
        bail!("the image size is {width}×{height}");
    }
    let fov = match (file.camera_angle_x, file.fl_x) {
        (Some(angle), _) => angle,
        (None, Some(focal)) => 2.0 * (width as f32 / (2.0 * focal)).atan(),
        (None, None) => bail!("no `camera_angle_x` (or `fl_x`): the field of view is unknown"),
    };
    if !(fov > 0.0 && fov < std::f32::consts::PI) {
        bail!("the horizontal field of view must lie in (0, π) radians (got {fov})");
    }
    // serde reads the rows; glam takes columns.
    let c2w = Mat4::from_cols_array_2d(&frame.transform_matrix).transpose();
    if !c2w.is_finite() {
        bail!("transform_matrix has non-finite entries");
    }
    let position = c2w.w_axis.xyz();
    let forward = -c2w.z_axis.xyz();
    let up = c2w.y_axis.xyz();
    if forward.length() < 1e-6
        || up.length() < 1e-6
        || forward.cross(up).length() < 1e-6 * forward.length() * up.length()
    {
        bail!("transform_matrix's axes are degenerate (its −z and +y must be independent)");
    }
    Ok(TransformsView {
        camera: Camera::new(
            position,
            position + forward.normalize(),
            up.normalize(),
            fov.to_degrees(),
            width,
            height,
        ),
        image,
    })
}

/// A frame's image: the path as given, or with `.exr` or `.png` added when it has no extension.
fn image_path(dir: &Path, name: &str) -> Result<PathBuf> {
    let path = dir.join(name);
    if path.extension().is_some() {
        return Ok(path);
    }
    for ext in ["exr", "png"] {
        let with = path.with_extension(ext);
        if with.is_file() {
            return Ok(with);
        }
    }
    bail!("file_path '{name}': no '{}.exr' or '.png'", path.display())
}

/// The camera-to-world matrix, rows of 4, of a camera at `position` looking at `target` with `up`
/// (the inverse of what `read` does; for writing transforms files and for tests).
pub fn camera_to_world(position: Vec3, target: Vec3, up: Vec3) -> [[f32; 4]; 4] {
    let back = (position - target).normalize();
    let right = up.cross(back).normalize();
    let up = back.cross(right);
    Mat4::from_cols(
        right.extend(0.0),
        up.extend(0.0),
        back.extend(0.0),
        position.extend(1.0),
    )
    .transpose()
    .to_cols_array_2d()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The convention, pinned by a matrix written by hand: the identity rotation at (0, 0, 5)
    /// looks down −z with +y up and +x to the right, as a Blender or OpenGL camera does.
    #[test]
    fn an_identity_camera_looks_down_minus_z() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("transforms.json");
        let json = r#"{ "camera_angle_x": 0.5, "w": 20, "h": 10, "frames": [
            { "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]] } ] }"#;
        std::fs::write(&path, json).unwrap();
        let views = read(&path).unwrap();
        let camera = views[0].camera;
        assert_eq!(camera.position, Vec3::new(0.0, 0.0, 5.0));
        assert!((camera.direction(10.0, 5.0) - Vec3::NEG_Z).length() < 1e-6);
        assert!(camera.direction(10.0, 0.0).y > 0.0, "the top row looks up");
        assert!(
            camera.direction(20.0, 5.0).x > 0.0,
            "the right column looks right"
        );
        // The horizontal field of view is camera_angle_x: the right edge is 0.25 rad off-axis.
        let edge = camera.direction(20.0, 5.0);
        assert!((edge.x.atan2(-edge.z) - 0.25).abs() < 1e-5);
        let m = camera_to_world(Vec3::new(0.0, 0.0, 5.0), Vec3::ZERO, Vec3::Y);
        assert_eq!(
            m,
            [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 5.0],
                [0.0, 0.0, 0.0, 1.0]
            ]
        );
    }

    #[test]
    fn files_in_other_units_or_without_a_field_of_view_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.json");
        let frame =
            r#"{ "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]] }"#;
        for (json, needle) in [
            (format!(r#"{{ "camera_angle_x": 0.5, "w": 8, "h": 8, "scale": 0.3, "frames": [{frame}] }}"#), "scale"),
            (format!(r#"{{ "w": 8, "h": 8, "frames": [{frame}] }}"#), "camera_angle_x"),
            (format!(r#"{{ "camera_angle_x": 0.5, "frames": [{frame}] }}"#), "size is unknown"),
            (r#"{ "camera_angle_x": 0.5, "w": 8, "h": 8, "frames": [{ "transform_matrix": [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 5], [0, 0, 0, 1]] }] }"#.to_string(), "degenerate"),
            ("{ not json".to_string(), "not a transforms.json"),
        ] {
            std::fs::write(&path, json).unwrap();
            let err = format!("{:#}", read(&path).err().unwrap());
            assert!(err.contains(needle), "{needle}: {err}");
        }
    }
}
