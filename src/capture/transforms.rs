//! Camera sets as multi-view tools and Blender's NeRF exporters write them: `transforms.json` in
//! the NeRF / instant-ngp / nerfstudio convention. Every key is read or named below as ignored;
//! any other key is an error, so that nothing a file says about its cameras is dropped unseen.
//!
//! - Intrinsics, at the top or per frame (a frame's own win, each quantity as a unit: a frame's
//!   `fl_x` replaces the top's `camera_angle_x` too, its `w`, `h` the top's pair): `fl_x`, `fl_y`
//!   (focal lengths in pixels) or `camera_angle_x`, `camera_angle_y` (fields of view in radians;
//!   fx = w / 2·tan(x/2)); `cx`, `cy` (principal point in pixels from the top-left corner, default
//!   the image centre); `w`, `h` (the image size, both or neither, whole numbers however written;
//!   without them the size of the frame's image). Without `fl_y` or
//!   `camera_angle_y` pixels are square (fy = fx). A focal length and an angle given together
//!   must agree.
//! - Distortion (`k1`–`k4`, `p1`, `p2`) must be zero: volgrad's cameras are pinholes, so images
//!   with lens distortion are refused rather than fitted with rays through the wrong pixels
//!   (undistort them first, e.g. with COLMAP's `image_undistorter`). `camera_model` may name a
//!   pinhole or OpenCV model (with zero distortion); fisheye models are refused.
//! - `frames[i].transform_matrix`: the camera-to-world matrix, rows of 4; its columns are the
//!   camera's right (+x), up (+y) and backward (+z) axes and its position: the camera looks down
//!   its −z axis (OpenGL's and Blender's camera convention). The frame must be right-handed and
//!   orthogonal, the last row (0, 0, 0, 1).
//! - `scale`, `offset`: instant-ngp's map of the file's positions into its own space,
//!   p ↦ scale·p + offset, applied to every camera's position when given (instant-ngp's defaults
//!   are not assumed: without them positions are taken as they are). `aabb_scale` (instant-ngp's
//!   sampling box) is ignored: the unknown's box is the run file's.
//! - `frames[i].file_path`: the frame's image, relative to the JSON file; without an extension
//!   (Blender's NeRF data sets) `.exr` and then `.png` are tried.
//! - Ignored, as they say nothing about the cameras: `aabb_scale`, `sharpness`, `rotation`
//!   (Blender's exporter), `colmap_im_id`, `depth_file_path`, `mask_path`, `integer_depth_scale`,
//!   `ply_file_path`, `enable_depth_loading`, `applied_transform`, `applied_scale`.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::{DMat4, DVec3, DVec4, Mat4, Vec3};
use serde::Deserialize;

use crate::capture::CapturedView;
use crate::render::camera::Intrinsics;
use crate::render::scene_check::calibrated_camera;

/// The largest a transforms file may hold: more frames than any run file may use.
const MAX_FRAMES: usize = 100_000;

/// Intrinsics and distortion, as the top level or a frame gives them.
#[derive(Deserialize, Default, Clone, Copy)]
struct Lens {
    camera_angle_x: Option<f64>,
    camera_angle_y: Option<f64>,
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    /// Whole numbers, though some writers give them as decimals (instant-ngp's `colmap2nerf.py`
    /// writes `"w": 1920.0`).
    w: Option<f64>,
    h: Option<f64>,
    k1: Option<f64>,
    k2: Option<f64>,
    k3: Option<f64>,
    k4: Option<f64>,
    p1: Option<f64>,
    p2: Option<f64>,
}

impl Lens {
    /// `self` where it says something, else `top`. What fixes one quantity is taken as a unit from
    /// one level: a frame's `fl_x` replaces the top level's `camera_angle_x` too (rather than
    /// meeting it in the check that the two agree), and a frame's `w`, `h` replace the top's pair.
    fn or(self, top: Lens) -> Lens {
        let x = if self.fl_x.is_some() || self.camera_angle_x.is_some() {
            self
        } else {
            top
        };
        let y = if self.fl_y.is_some() || self.camera_angle_y.is_some() {
            self
        } else {
            top
        };
        let size = if self.w.is_some() || self.h.is_some() {
            self
        } else {
            top
        };
        Lens {
            camera_angle_x: x.camera_angle_x,
            fl_x: x.fl_x,
            camera_angle_y: y.camera_angle_y,
            fl_y: y.fl_y,
            w: size.w,
            h: size.h,
            cx: self.cx.or(top.cx),
            cy: self.cy.or(top.cy),
            k1: self.k1.or(top.k1),
            k2: self.k2.or(top.k2),
            k3: self.k3.or(top.k3),
            k4: self.k4.or(top.k4),
            p1: self.p1.or(top.p1),
            p2: self.p2.or(top.p2),
        }
    }

    /// The image size `w`, `h` says, if it says one: both or neither, each a whole number of
    /// pixels (the camera's checks bound it).
    fn size(&self) -> Result<Option<(u32, u32)>> {
        let whole = |key: &str, v: f64| {
            if v.fract() == 0.0 && (1.0..=f64::from(u32::MAX)).contains(&v) {
                Ok(v as u32)
            } else if v.fract() == 0.0 && v > 1.0 {
                bail!("{key} = {} pixels is too large", super::quoted_number(v))
            } else {
                bail!(
                    "{key} = {} is not a whole number of pixels ≥ 1",
                    super::quoted_number(v)
                )
            }
        };
        match (self.w, self.h) {
            (Some(w), Some(h)) => Ok(Some((whole("w", w)?, whole("h", h)?))),
            (None, None) => Ok(None),
            (Some(_), None) => bail!("`w` without `h`: give both or neither"),
            (None, Some(_)) => bail!("`h` without `w`: give both or neither"),
        }
    }
}

/// The keys of `Lens`, allowed at the top and in frames.
const LENS_KEYS: [&str; 14] = [
    "camera_angle_x",
    "camera_angle_y",
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "w",
    "h",
    "k1",
    "k2",
    "k3",
    "k4",
    "p1",
    "p2",
];
const TOP_KEYS: [&str; 5] = ["camera_model", "is_fisheye", "scale", "offset", "frames"];
const FRAME_KEYS: [&str; 2] = ["file_path", "transform_matrix"];
/// Keys that say nothing about the cameras, read and dropped (see the module's documentation).
const IGNORED_KEYS: [&str; 11] = [
    "aabb_scale",
    "sharpness",
    "rotation",
    "colmap_im_id",
    "depth_file_path",
    "mask_path",
    "integer_depth_scale",
    "ply_file_path",
    "enable_depth_loading",
    "applied_transform",
    "applied_scale",
];

/// Every key of the JSON object `value` (`what` in errors) is one of `own`, a lens key or an
/// ignored one, and every lens key holds a number. (serde's `deny_unknown_fields` does not work
/// with the flattened `Lens`, and a type error inside a flattened struct loses its key's name.)
fn known_keys(value: &serde_json::Value, what: &str, own: &[&str]) -> Result<()> {
    let Some(object) = value.as_object() else {
        bail!("{what} must be a JSON object");
    };
    for (key, value) in object {
        let key = key.as_str();
        if LENS_KEYS.contains(&key) {
            // null stands for an absent key, as serde reads an `Option`.
            if !(value.is_number() || value.is_null()) {
                bail!("{what}: {key} must be a number (got {value})");
            }
        } else if !(own.contains(&key) || IGNORED_KEYS.contains(&key)) {
            bail!("{what}: unknown key \"{key}\" (the keys volgrad reads and ignores are listed in the manual, docs/pictures.md, \"Cameras\")");
        }
    }
    Ok(())
}

#[derive(Deserialize)]
struct TransformsFile {
    #[serde(flatten)]
    lens: Lens,
    camera_model: Option<String>,
    #[serde(default)]
    is_fisheye: bool,
    scale: Option<f64>,
    offset: Option<[f64; 3]>,
    frames: Vec<Frame>,
}

#[derive(Deserialize)]
struct Frame {
    file_path: Option<String>,
    transform_matrix: [[f64; 4]; 4],
    #[serde(flatten)]
    lens: Lens,
}

/// The cameras of `path` (errors name the file and the frame).
pub fn read(path: &Path) -> Result<Vec<CapturedView>> {
    let text = crate::io::input::read_text(path)
        .with_context(|| format!("cannot read '{}'", path.display()))?;
    let not_transforms = || format!("'{}' is not a transforms.json", path.display());
    let value = crate::io::json::parse(&text).with_context(not_transforms)?;
    known_keys(&value, "the top level", &TOP_KEYS)
        .and_then(|_| match value["frames"].as_array() {
            Some(frames) => frames
                .iter()
                .enumerate()
                .try_for_each(|(i, frame)| known_keys(frame, &format!("frames[{i}]"), &FRAME_KEYS)),
            None => Ok(()),
        })
        .with_context(|| format!("'{}'", path.display()))?;
    // The error's path names the key and the frame (`frames[3].transform_matrix[0][1]`).
    let file: TransformsFile = serde_path_to_error::deserialize(value)
        .map_err(|e| anyhow::anyhow!("{}: {}", e.path(), e.inner()))
        .with_context(not_transforms)?;
    file.check()
        .with_context(|| format!("'{}'", path.display()))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let views = (file.frames.iter().enumerate())
        .map(|(i, frame)| {
            file.view(frame, dir)
                .with_context(|| format!("'{}': frames[{i}]", path.display()))
        })
        .collect::<Result<Vec<_>>>()?;
    super::refuse_repeated_images(&views, |i| format!("frames[{i}]"))
        .with_context(|| format!("'{}'", path.display()))?;
    Ok(views)
}

impl TransformsFile {
    /// What holds for every frame: a pinhole model, a usable map of positions, some frames.
    fn check(&self) -> Result<()> {
        if let Some(model) = &self.camera_model {
            let pinhole = [
                "PINHOLE",
                "SIMPLE_PINHOLE",
                "OPENCV",
                "SIMPLE_RADIAL",
                "RADIAL",
                "FULL_OPENCV",
            ];
            if !pinhole.contains(&model.to_uppercase().as_str()) {
                bail!("camera_model \"{model}\" is not a pinhole: volgrad's cameras are pinholes (PINHOLE, or OPENCV with zero distortion)");
            }
        }
        if self.is_fisheye {
            bail!("is_fisheye: volgrad's cameras are pinholes");
        }
        if let Some(scale) = self.scale {
            if !(scale > 0.0 && scale.is_finite()) {
                bail!("scale must be a finite number > 0 (got {scale})");
            }
        }
        if let Some(offset) = self.offset {
            if !offset.iter().all(|v| v.is_finite()) {
                bail!("offset must be three finite numbers (got {offset:?})");
            }
        }
        if self.frames.is_empty() {
            bail!("\"frames\" is empty: a transforms file needs at least one camera");
        }
        if self.frames.len() > MAX_FRAMES {
            bail!("{} frames: at most {MAX_FRAMES}", self.frames.len());
        }
        Ok(())
    }

    fn view(&self, frame: &Frame, dir: &Path) -> Result<CapturedView> {
        let lens = frame.lens.or(self.lens);
        let image = frame
            .file_path
            .as_deref()
            .map(|name| image_path(dir, name))
            .transpose()?;
        let (width, height) = match (lens.size()?, &image) {
            (Some(size), _) => size,
            (None, Some(image)) => crate::io::images::image_size(image)?,
            (None, None) => bail!("no image and no `w`, `h`: the view's size is unknown"),
        };
        let intrinsics = intrinsics(&lens, width, height)?;
        let (position, forward, up) = pose(&frame.transform_matrix)?;
        let position =
            position * self.scale.unwrap_or(1.0) + DVec3::from(self.offset.unwrap_or_default());
        let camera = calibrated_camera(position, forward, up, intrinsics, width, height)?;
        Ok(CapturedView { camera, image })
    }
}

/// The pinhole intrinsics of `lens` for a `width` × `height` image; distortion must be zero.
fn intrinsics(lens: &Lens, width: u32, height: u32) -> Result<Intrinsics> {
    for (key, value) in [
        ("k1", lens.k1),
        ("k2", lens.k2),
        ("k3", lens.k3),
        ("k4", lens.k4),
        ("p1", lens.p1),
        ("p2", lens.p2),
    ] {
        if let Some(v) = value.filter(|&v| v != 0.0) {
            let v = super::quoted_number(v);
            bail!("{key} = {v}: lens distortion is not modelled (volgrad's cameras are pinholes); undistort the images and give zero distortion");
        }
    }
    let fx = focal("x", lens.fl_x, lens.camera_angle_x, width)?
        .context("no `fl_x` or `camera_angle_x`: the focal length is unknown")?;
    let fy = focal("y", lens.fl_y, lens.camera_angle_y, height)?.unwrap_or(fx);
    let k = Intrinsics {
        fx: fx as f32,
        fy: fy as f32,
        cx: lens.cx.unwrap_or(f64::from(width) / 2.0) as f32,
        cy: lens.cy.unwrap_or(f64::from(height) / 2.0) as f32,
    };
    Ok(k)
}

/// The focal length along one axis from `fl` (pixels) or `angle` (the field of view across
/// `size` pixels, radians); both given must agree to 0.1 %.
fn focal(axis: &str, fl: Option<f64>, angle: Option<f64>, size: u32) -> Result<Option<f64>> {
    // Checked as written: 1e-300 or 1e300 would reach the camera's check as f32's 0 or inf.
    if let Some(f) = fl.filter(|&f| !(f > 0.0 && (f as f32).is_normal())) {
        bail!(
            "fl_{axis} = {}: the focal length f{axis} must be a finite number of pixels > 0 within f32's range",
            super::quoted_number(f)
        );
    }
    let from_angle = angle
        .map(|a| {
            if !(a > 0.0 && a < std::f64::consts::PI) {
                bail!("camera_angle_{axis} must lie in (0, π) radians (got {a})");
            }
            Ok(f64::from(size) / (2.0 * (a / 2.0).tan()))
        })
        .transpose()?;
    match (fl, from_angle) {
        (Some(f), Some(a)) if (f - a).abs() > 1e-3 * a => bail!(
            "fl_{axis} = {} and camera_angle_{axis} (a focal length of {} pixels at this size) disagree: give one",
            super::quoted_number(f),
            super::quoted_number((a * 1000.0).round() / 1000.0)
        ),
        (Some(f), _) => Ok(Some(f)),
        (None, a) => Ok(a),
    }
}

/// The position, view direction (−z) and up (+y) of a camera-to-world matrix given as rows; the
/// frame must be an orthogonal, right-handed rotation (a uniform scale is allowed).
fn pose(rows: &[[f64; 4]; 4]) -> Result<(DVec3, DVec3, DVec3)> {
    let m = DMat4::from_cols_array_2d(rows).transpose();
    if !m.is_finite() {
        bail!("transform_matrix has non-finite entries");
    }
    let last = m.row(3);
    if (last - DVec4::W).abs().max_element() > 1e-6 {
        bail!("transform_matrix's last row must be (0, 0, 0, 1) (got {last}): a camera-to-world matrix is affine");
    }
    let axes = [
        m.x_axis.truncate(),
        m.y_axis.truncate(),
        m.z_axis.truncate(),
    ];
    let lengths = axes.map(|a| a.length());
    if lengths.iter().any(|&l| !(l > 1e-12 && l < 1e300)) {
        bail!("transform_matrix's axes are degenerate (lengths {lengths:?})");
    }
    let [x, y, z] = [0, 1, 2].map(|i| axes[i] / lengths[i]);
    let skew = x.dot(y).abs().max(y.dot(z).abs()).max(x.dot(z).abs());
    if skew > 1e-3 {
        bail!("transform_matrix's axes are not orthogonal (largest |cos| between them {skew:.2e}): it must be a rotation");
    }
    let (shortest, longest) =
        (lengths.iter().copied()).fold((f64::MAX, 0.0f64), |(lo, hi), l| (lo.min(l), hi.max(l)));
    if longest > shortest * (1.0 + 1e-3) {
        bail!("transform_matrix scales its axes unequally (lengths {lengths:?}): a camera-to-world matrix is a rotation, with at most a uniform scale");
    }
    if x.cross(y).dot(z) < 0.0 {
        bail!("transform_matrix is left-handed (its +x × +y is −z): a camera-to-world matrix is a rotation");
    }
    Ok((m.w_axis.truncate(), -z, y))
}

/// A frame's image: the path as given, or with `.exr` or `.png` added when it has no extension.
fn image_path(dir: &Path, name: &str) -> Result<PathBuf> {
    if name.trim().is_empty() {
        bail!("file_path is empty: it names the frame's picture");
    }
    let path = dir.join(name);
    if path.extension().is_some() {
        return Ok(path);
    }
    let tried = ["exr", "png"].map(|ext| path.with_extension(ext));
    if let Some(found) = tried.iter().find(|p| p.is_file()) {
        return Ok(found.clone());
    }
    bail!(
        "file_path '{name}' has no extension, and neither '{}' nor '{}' is a file",
        tried[0].display(),
        tried[1].display()
    )
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
#[path = "transforms_tests.rs"]
mod tests;
