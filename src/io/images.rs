//! Images in and out through OpenImageIO: linear EXR (half or float) and 8-bit sRGB PNG.

use std::path::Path;

use anyhow::{anyhow, Result};
use glam::Vec3;

use crate::io::bridge::ffi;
use crate::io::bridge::ImageData;

/// A linear RGB image, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<Vec3>,
}

impl RgbImage {
    pub fn new(width: u32, height: u32) -> Self {
        RgbImage {
            width,
            height,
            pixels: vec![Vec3::ZERO; width as usize * height as usize],
        }
    }

    pub fn mean(&self) -> Vec3 {
        self.pixels.iter().copied().sum::<Vec3>() / self.pixels.len().max(1) as f32
    }

    fn to_data(&self, encode: impl Fn(f32) -> f32) -> ImageData {
        ImageData {
            width: self.width,
            height: self.height,
            channels: 3,
            pixels: self
                .pixels
                .iter()
                .flat_map(|c| c.to_array())
                .map(encode)
                .collect(),
        }
    }
}

fn path_str(path: &Path) -> Result<&str> {
    path.to_str()
        .ok_or_else(|| anyhow!("path '{}' is not valid UTF-8", path.display()))
}

/// The sRGB transfer function (IEC 61966-2-1) of a linear value in [0, 1].
pub fn srgb_encode(linear: f32) -> f32 {
    let x = linear.clamp(0.0, 1.0);
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

/// Writes a linear EXR, as half or float.
pub fn write_exr(path: &Path, image: &RgbImage, half: bool) -> Result<()> {
    ffi::write_image(
        path_str(path)?,
        &image.to_data(|v| v),
        if half { "half" } else { "float" },
    )
    .map_err(|e| anyhow!("{}", e.what()))
}

/// Writes an 8-bit PNG: `exposure`·value, clamped, sRGB-encoded here (OpenImageIO does not).
pub fn write_png(path: &Path, image: &RgbImage, exposure: f32) -> Result<()> {
    let data = image.to_data(|v| srgb_encode(v * exposure));
    ffi::write_image(path_str(path)?, &data, "uint8").map_err(|e| anyhow!("{}", e.what()))
}

/// Reads any image OpenImageIO opens as RGB (grey images are spread to three channels). Values are
/// taken as they are stored: EXR/HDR are linear; 8-bit formats are not decoded from sRGB.
pub fn read_rgb(path: &Path) -> Result<RgbImage> {
    let data = ffi::read_image(path_str(path)?).map_err(|e| anyhow!("{}", e.what()))?;
    let c = data.channels as usize;
    if c == 0 {
        anyhow::bail!("'{}' has no channels", path.display());
    }
    let pixels = data
        .pixels
        .chunks_exact(c)
        .map(|p| {
            if c >= 3 {
                Vec3::new(p[0], p[1], p[2])
            } else {
                Vec3::splat(p[0])
            }
        })
        .collect();
    Ok(RgbImage {
        width: data.width,
        height: data.height,
        pixels,
    })
}
