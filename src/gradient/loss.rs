//! Objectives on images and their adjoints δ = ∂loss/∂pixel. Every loss is a mean over pixels and
//! channels, so its size does not depend on the resolution.

use glam::Vec3;

use crate::io::images::RgbImage;

#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Loss {
    /// mean (I − T)²
    L2,
    /// mean |I − T|
    L1,
    /// mean (I − T)² / (T² + 0.01)
    #[value(name = "relative-l2")]
    RelativeL2,
    /// mean I (no target)
    Mean,
}

crate::display_as_value_enum!(Loss);

const RELATIVE_EPSILON: f32 = 0.01;

impl Loss {
    pub fn needs_target(self) -> bool {
        self != Loss::Mean
    }

    /// The loss of `image` against `target` (ignored by `Mean`).
    pub fn evaluate(self, image: &RgbImage, target: Option<&RgbImage>) -> f64 {
        let n = (image.pixels.len() * 3) as f64;
        let target_of = |i: usize| target.map_or(Vec3::ZERO, |t| t.pixels[i]);
        (image.pixels.iter().enumerate())
            .map(|(i, &c)| self.pixel_value(c, target_of(i)))
            .sum::<f64>()
            / n
    }

    /// ∂loss/∂pixel for every pixel.
    pub fn adjoint(self, image: &RgbImage, target: Option<&RgbImage>) -> Vec<Vec3> {
        let n = (image.pixels.len() * 3) as f32;
        let target_of = |i: usize| target.map_or(Vec3::ZERO, |t| t.pixels[i]);
        (image.pixels.iter().enumerate())
            .map(|(i, &c)| self.pixel_adjoint(c, target_of(i)) / n)
            .collect()
    }

    /// One pixel's term of the loss, summed over channels, before the mean: `evaluate` is the
    /// sum of these over 3 × the pixel count.
    pub fn pixel_value(self, c: Vec3, t: Vec3) -> f64 {
        // In f64: a difference of 1e20 squares beyond f32.
        let (c, t) = (c.as_dvec3(), t.as_dvec3());
        let d = c - t;
        let v = match self {
            Loss::L2 => d * d,
            Loss::L1 => d.abs(),
            Loss::RelativeL2 => d * d / (t * t + f64::from(RELATIVE_EPSILON)),
            Loss::Mean => c,
        };
        v.x + v.y + v.z
    }

    /// ∂`pixel_value`/∂c.
    pub fn pixel_adjoint(self, c: Vec3, t: Vec3) -> Vec3 {
        let d = c - t;
        match self {
            Loss::L2 => 2.0 * d,
            Loss::L1 => d.map(|x| if x == 0.0 { 0.0 } else { x.signum() }),
            Loss::RelativeL2 => 2.0 * d / (t * t + RELATIVE_EPSILON),
            Loss::Mean => Vec3::ONE,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adjoints_are_the_derivatives_of_the_losses() {
        let image = RgbImage {
            width: 2,
            height: 1,
            pixels: vec![Vec3::new(0.5, 1.0, 0.2), Vec3::new(2.0, 0.1, 0.0)],
        };
        let target = RgbImage {
            width: 2,
            height: 1,
            pixels: vec![Vec3::new(0.4, 1.2, 0.2), Vec3::new(1.0, 0.3, 0.5)],
        };
        for loss in [Loss::L2, Loss::L1, Loss::RelativeL2, Loss::Mean] {
            let adjoint = loss.adjoint(&image, Some(&target));
            for (i, d_pixel) in adjoint.iter().enumerate() {
                for c in 0..3 {
                    if loss == Loss::L1 && image.pixels[i][c] == target.pixels[i][c] {
                        continue; // not differentiable there
                    }
                    let h = 1e-3;
                    let mut plus = image.clone();
                    plus.pixels[i][c] += h;
                    let mut minus = image.clone();
                    minus.pixels[i][c] -= h;
                    let fd = (loss.evaluate(&plus, Some(&target))
                        - loss.evaluate(&minus, Some(&target)))
                        / (2.0 * h as f64);
                    assert!(
                        (fd - d_pixel[c] as f64).abs() < 1e-4,
                        "{loss:?} pixel {i} channel {c}: {fd} vs {}",
                        d_pixel[c]
                    );
                }
            }
        }
    }
}
