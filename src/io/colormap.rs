//! Pictures of signed quantities (gradients, derivative images): a diverging blue–white–red colour
//! map, symmetric about zero, scaled to a robust maximum so that one hot voxel does not wash out
//! the rest.

use std::path::Path;

use glam::Vec3;

use crate::io::images::{write_png, RgbImage};

/// Linear RGB for `x` in [−1, 1]: blue (negative) through white (0) to red (positive).
pub fn diverging(x: f32) -> Vec3 {
    let x = x.clamp(-1.0, 1.0);
    let (blue, white, red) = (
        Vec3::new(0.02, 0.12, 0.55),
        Vec3::ONE,
        Vec3::new(0.6, 0.02, 0.02),
    );
    if x < 0.0 {
        white.lerp(blue, -x)
    } else {
        white.lerp(red, x)
    }
}

/// The 99th percentile of |v| over the non-zero values (1 if there are none).
pub fn robust_scale(values: &[f32]) -> f32 {
    let mut mags: Vec<f32> = values
        .iter()
        .map(|v| v.abs())
        .filter(|v| *v > 0.0 && v.is_finite())
        .collect();
    if mags.is_empty() {
        return 1.0;
    }
    let k = ((mags.len() - 1) as f32 * 0.99) as usize;
    *mags.select_nth_unstable_by(k, |a, b| a.total_cmp(b)).1
}

/// Writes `values` (row-major, `width`×`height`) as a diverging-colour PNG, enlarged by whole
/// pixels until its long side is at least 384 so that small grids stay legible; returns the scale
/// used (the value shown at full saturation).
pub fn write_signed_png(
    path: &Path,
    width: u32,
    height: u32,
    values: &[f32],
) -> anyhow::Result<f32> {
    let scale = robust_scale(values);
    let k = 384u32.div_ceil(width.max(height).max(1));
    let (w, h) = (width * k, height * k);
    let pixels = (0..w * h)
        .map(|i| diverging(values[((i / w / k) * width + (i % w) / k) as usize] / scale))
        .collect();
    write_png(
        path,
        &RgbImage {
            width: w,
            height: h,
            pixels,
        },
        1.0,
    )?;
    Ok(scale)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_is_white_and_signs_differ() {
        assert_eq!(diverging(0.0), Vec3::ONE);
        assert!(diverging(-1.0).z > diverging(-1.0).x);
        assert!(diverging(1.0).x > diverging(1.0).z);
        assert_eq!(robust_scale(&[0.0, 0.0]), 1.0);
        let values: Vec<f32> = (1..=1000).map(|i| i as f32).chain([1e9]).collect();
        assert!(robust_scale(&values) < 1001.0);
    }
}
