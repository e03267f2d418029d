//! Content fingerprints: a 64-bit FNV-1a hash of what a computation depends on, written into
//! gradient files so that runs of the same computation can be recognised wherever their files
//! live (FNV-1a because its value is fixed by its definition, unlike `std`'s hasher, and the
//! inputs are not adversarial).

use glam::Vec3;

use crate::io::images::RgbImage;

const OFFSET_BASIS: u64 = 0xcbf2_9ce4_8422_2325;
const PRIME: u64 = 0x0000_0100_0000_01b3;

#[derive(Debug, Clone, Copy)]
pub struct Fingerprint(u64);

impl Default for Fingerprint {
    fn default() -> Self {
        Fingerprint(OFFSET_BASIS)
    }
}

impl Fingerprint {
    pub fn bytes(&mut self, bytes: &[u8]) -> &mut Self {
        for &b in bytes {
            self.0 = (self.0 ^ b as u64).wrapping_mul(PRIME);
        }
        self
    }

    /// A labelled string: the label keeps ("ab", "c") and ("a", "bc") apart.
    pub fn text(&mut self, text: &str) -> &mut Self {
        self.bytes(&(text.len() as u64).to_le_bytes())
            .bytes(text.as_bytes())
    }

    pub fn f32s(&mut self, values: &[f32]) -> &mut Self {
        for v in values {
            self.bytes(&v.to_bits().to_le_bytes());
        }
        self
    }

    pub fn vec3s(&mut self, values: &[Vec3]) -> &mut Self {
        for v in values {
            self.f32s(&v.to_array());
        }
        self
    }

    pub fn value(&self) -> u64 {
        self.0
    }

    /// 16 hex digits, as stored in metadata.
    pub fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }
}

/// The fingerprint of an image's size and pixels (e.g. a loss's target).
pub fn image(image: &RgbImage) -> String {
    Fingerprint::default()
        .bytes(&image.width.to_le_bytes())
        .bytes(&image.height.to_le_bytes())
        .vec3s(&image.pixels)
        .hex()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fnv1a_reference_values_and_sensitivity() {
        // Published FNV-1a 64 test vectors.
        assert_eq!(Fingerprint::default().hex(), "cbf29ce484222325");
        assert_eq!(Fingerprint::default().bytes(b"a").hex(), "af63dc4c8601ec8c");
        assert_eq!(
            Fingerprint::default().bytes(b"foobar").hex(),
            "85944171f73967e8"
        );
        let a = RgbImage::new(2, 1);
        let mut b = a.clone();
        assert_eq!(image(&a), image(&b));
        b.pixels[1].z = 1e-30;
        assert_ne!(image(&a), image(&b));
        assert_ne!(image(&a), image(&RgbImage::new(1, 2)));
        let split = |x: &str, y: &str| Fingerprint::default().text(x).text(y).hex();
        assert_ne!(split("ab", "c"), split("a", "bc"));
    }
}
