//! Camera sets as COLMAP exports them in text: a model folder with `cameras.txt` and `images.txt`
//! (`colmap model_converter --output_type TXT`, or the `sparse/0` folder of a text export).
//!
//! - `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS…` per line. Pinhole models are read:
//!   SIMPLE_PINHOLE (f, cx, cy), PINHOLE (fx, fy, cx, cy), and SIMPLE_RADIAL (f, cx, cy, k),
//!   RADIAL (f, cx, cy, k1, k2), OPENCV (fx, fy, cx, cy, k1, k2, p1, p2) and FULL_OPENCV when
//!   their distortion is zero (volgrad's cameras are pinholes: undistort first, e.g. with
//!   `colmap image_undistorter`, which writes PINHOLE cameras). Other models are refused.
//!   COLMAP's image coordinates put the top-left pixel's centre at (0.5, 0.5), as volgrad's do.
//! - `images.txt`: two lines per image, `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` and its 2D
//!   points (not read). The pose maps world to camera, x_cam = R(q)·x_world + t, with the
//!   camera's +x right, +y down and +z forward (OpenCV's convention): the camera sits at −Rᵀt,
//!   looks along Rᵀ·(0, 0, 1) with up Rᵀ·(0, −1, 0). `NAME` is the image's path in the images
//!   folder.
//!
//! Lines starting with `#` are comments. Errors name the file and line.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::{DQuat, DVec3};

use crate::capture::CapturedView;
use crate::render::camera::Intrinsics;
use crate::render::scene_check::{self, calibrated_camera};

/// A camera of `cameras.txt`: its size and intrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Sensor {
    width: u32,
    height: u32,
    intrinsics: Intrinsics,
}

/// Where a model's pictures are unless a run file says: the `images` folder beside the model's
/// `sparse` folder, as COLMAP lays a project out — `P/sparse/0` → `P/images`, and `P/dense/sparse`
/// (where `image_undistorter` writes the undistorted model) → `P/dense/images`, its undistorted
/// pictures. A model in a folder of another name looks beside itself.
pub fn default_images(model: &Path) -> PathBuf {
    let parent = model.parent().unwrap_or(Path::new("."));
    if parent.file_name().is_some_and(|name| name == "sparse") {
        parent.parent().unwrap_or(Path::new(".")).join("images")
    } else {
        parent.join("images")
    }
}

/// The views of the COLMAP text model in `model` (a folder with `cameras.txt` and `images.txt`),
/// their images in the folder `images`.
pub fn read(model: &Path, images: &Path) -> Result<Vec<CapturedView>> {
    let cameras_path = model.join("cameras.txt");
    let images_path = model.join("images.txt");
    refuse_binary_model(model)?;
    let read = |path: &Path| {
        crate::io::input::read_text(path).with_context(|| {
            format!(
                "cannot read '{}' (a COLMAP text model: cameras.txt and images.txt)",
                path.display()
            )
        })
    };
    let sensors =
        sensors(&read(&cameras_path)?).with_context(|| format!("'{}'", cameras_path.display()))?;
    views(&read(&images_path)?, &sensors, images)
        .with_context(|| format!("'{}'", images_path.display()))
}

/// COLMAP's own binary model (`cameras.bin`, `images.bin`, what its mapper writes) where the text
/// model is missing: named, with the command that converts it, instead of "No such file".
fn refuse_binary_model(model: &Path) -> Result<()> {
    let text_missing = ["cameras.txt", "images.txt"].map(|name| !model.join(name).exists());
    let binary = ["cameras.bin", "images.bin"].map(|name| model.join(name).is_file());
    if text_missing.iter().any(|&missing| missing) && binary.iter().any(|&found| found) {
        bail!(
            "'{}' holds a binary COLMAP model (cameras.bin, images.bin); volgrad reads the text one: \
             convert it with `colmap model_converter --input_path {0} --output_path {0} --output_type TXT`",
            model.display()
        );
    }
    Ok(())
}

/// The lines of a COLMAP text file that are not comments, numbered from 1 as an editor does.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line))
        .filter(|(_, line)| !line.trim_start().starts_with('#'))
}

fn sensors(text: &str) -> Result<HashMap<u32, Sensor>> {
    let mut sensors = HashMap::new();
    for (number, line) in data_lines(text).filter(|(_, l)| !l.trim().is_empty()) {
        let id = first_number(line).with_context(|| format!("line {number}"))?;
        let sensor = sensor(line).with_context(|| format!("line {number}"))?;
        if sensors.insert(id, sensor).is_some() {
            bail!("line {number}: camera {id} is defined twice");
        }
    }
    if sensors.is_empty() {
        bail!("no cameras");
    }
    Ok(sensors)
}

/// The words as finite numbers, or an error naming the first that is not one.
fn finite_numbers(words: &[&str]) -> Result<Vec<f64>> {
    (words.iter())
        .map(|w| {
            w.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .with_context(|| format!("'{w}' is not a finite number"))
        })
        .collect()
}

fn first_number(line: &str) -> Result<u32> {
    let word = line.split_whitespace().next().unwrap_or_default();
    word.parse()
        .with_context(|| format!("'{word}' is not an id (a whole number)"))
}

/// One line of `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS…`.
fn sensor(line: &str) -> Result<Sensor> {
    let words: Vec<&str> = line.split_whitespace().collect();
    if words.len() < 4 {
        bail!("expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS…");
    }
    let model = words[1];
    let size = |i: usize, key: &str| -> Result<u32> {
        words[i]
            .parse()
            .with_context(|| format!("{key} '{}' is not a whole number", words[i]))
    };
    let (width, height) = (size(2, "WIDTH")?, size(3, "HEIGHT")?);
    let params = finite_numbers(&words[4..])?;
    // (fx, fy, cx, cy) and the distortion terms, by model.
    let (pinhole, distortion, expected): ([f64; 4], &[f64], usize) = match model {
        "SIMPLE_PINHOLE" | "SIMPLE_RADIAL" | "RADIAL" if params.len() >= 3 => {
            let n = match model {
                "SIMPLE_PINHOLE" => 3,
                "SIMPLE_RADIAL" => 4,
                _ => 5,
            };
            let p = &params;
            ([p[0], p[0], p[1], p[2]], &p[3..], n)
        }
        "PINHOLE" | "OPENCV" | "FULL_OPENCV" if params.len() >= 4 => {
            let n = match model {
                "PINHOLE" => 4,
                "OPENCV" => 8,
                _ => 12,
            };
            let p = &params;
            ([p[0], p[1], p[2], p[3]], &p[4..], n)
        }
        "SIMPLE_PINHOLE" | "SIMPLE_RADIAL" | "RADIAL" | "PINHOLE" | "OPENCV" | "FULL_OPENCV" => {
            bail!("{model} with {} parameters: too few", params.len())
        }
        _ => bail!(
            "camera model {model} is not one volgrad reads: it reads COLMAP's SIMPLE_PINHOLE and PINHOLE, and SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV with zero distortion, as COLMAP writes them, in capitals (undistort other models with `colmap image_undistorter`)"
        ),
    };
    if params.len() != expected {
        bail!("{model} takes {expected} parameters (got {})", params.len());
    }
    if let Some(&k) = distortion.iter().find(|&&k| k != 0.0) {
        let k = super::quoted_number(k);
        bail!("{model} with distortion {k}: lens distortion is not modelled (volgrad's cameras are pinholes); undistort the images (`colmap image_undistorter`)");
    }
    let [fx, fy, cx, cy] = pinhole.map(|v| v as f32);
    let intrinsics = Intrinsics { fx, fy, cx, cy };
    scene_check::intrinsics(intrinsics, width, height)?;
    Ok(Sensor {
        width,
        height,
        intrinsics,
    })
}

fn views(text: &str, sensors: &HashMap<u32, Sensor>, images: &Path) -> Result<Vec<CapturedView>> {
    // Two lines per image: the pose, then its points (possibly empty, possibly missing at the end
    // of the file).
    let lines: Vec<(usize, &str)> = data_lines(text).collect();
    let (mut views, mut ids) = (Vec::new(), std::collections::HashSet::new());
    let mut line_numbers = Vec::new();
    for pair in lines.chunks(2) {
        let (number, line) = pair[0];
        if line.trim().is_empty() {
            if pair.iter().all(|(_, l)| l.trim().is_empty()) {
                continue; // blank lines at the end
            }
            bail!("line {number}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, found an empty line");
        }
        let view = view(line, sensors, images).with_context(|| format!("line {number}"))?;
        let id = first_number(line).with_context(|| format!("line {number}: IMAGE_ID"))?;
        if !ids.insert(id) {
            bail!("line {number}: image {id} is listed twice");
        }
        if let Some(&(number, points)) = pair.get(1) {
            points_line(points).with_context(|| format!("line {number}: expected the POINTS2D line of image {id} (X Y POINT3D_ID triples, or empty: COLMAP writes one after each image's line)"))?;
        }
        views.push(view);
        line_numbers.push(number);
    }
    if views.is_empty() {
        bail!("no images");
    }
    super::refuse_repeated_images(&views, |i| format!("line {}", line_numbers[i]))?;
    Ok(views)
}

/// A POINTS2D line: `X Y POINT3D_ID` triples (the ID −1 where a point has no 3D point), not read
/// but checked, so that a file without these lines is not read as every other image.
fn points_line(line: &str) -> Result<()> {
    let words: Vec<&str> = line.split_whitespace().collect();
    if !words.len().is_multiple_of(3) {
        bail!("{} values, not a multiple of 3", words.len());
    }
    for triple in words.chunks(3) {
        finite_numbers(&triple[..2])?;
        triple[2]
            .parse::<i64>()
            .with_context(|| format!("'{}' is not a POINT3D_ID", triple[2]))?;
    }
    Ok(())
}

/// What follows the first `n` words of `line`, as it stands there.
fn after_words(line: &str, n: usize) -> &str {
    let mut rest = line.trim_start();
    for _ in 0..n {
        rest = rest
            .trim_start_matches(|c: char| !c.is_whitespace())
            .trim_start();
    }
    rest.trim_end()
}

/// One pose line of `images.txt`.
fn view(line: &str, sensors: &HashMap<u32, Sensor>, images: &Path) -> Result<CapturedView> {
    let words: Vec<&str> = line.split_whitespace().collect();
    if words.len() < 10 {
        bail!("expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME");
    }
    let numbers = finite_numbers(&words[1..8])?;
    let q = DQuat::from_xyzw(numbers[1], numbers[2], numbers[3], numbers[0]);
    // Scaled by its largest component first: the length of (1e200, 1e200, 0, 0) overflows, and
    // a quaternion of length 1e-200 is a rotation all the same.
    let largest = numbers[..4].iter().fold(0.0, |m: f64, v| m.max(v.abs()));
    if largest == 0.0 {
        bail!("the rotation quaternion is zero");
    }
    let world_to_camera = (q / largest).normalize();
    let t = DVec3::new(numbers[4], numbers[5], numbers[6]);
    let camera_to_world = world_to_camera.inverse();
    let position = -(camera_to_world * t);
    let forward = camera_to_world * DVec3::Z;
    let up = camera_to_world * DVec3::NEG_Y;
    let id = first_number(words[8]).context("CAMERA_ID")?;
    let sensor = sensors
        .get(&id)
        .with_context(|| format!("camera {id} is not in cameras.txt"))?;
    // A name may hold spaces, two in a row too: it is the rest of the line.
    let name = after_words(line, 9);
    let camera = calibrated_camera(
        position,
        forward,
        up,
        sensor.intrinsics,
        sensor.width,
        sensor.height,
    )?;
    Ok(CapturedView {
        camera,
        image: Some(images.join(PathBuf::from(name))),
    })
}

#[cfg(test)]
#[path = "colmap_tests.rs"]
mod tests;
