//! Targets rendered from a truth, kept between runs (`optimize --target-cache DIR`). Many runs fit
//! one run file's images — seeds, estimators, optimiser settings — and at the spp targets need
//! those images take minutes to render. An entry is named by the fingerprint of everything that
//! decides its pixels: the scene's (grids, optical constants, camera, lights), the spp, seed and
//! path depth, and the volgrad executable itself, whose renderer decides how a seed becomes
//! samples. An entry is therefore read back only by a render that would have made the same bits,
//! and a run gives the same result with the cache as without it.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::Vec3;

use crate::io::fingerprint::Fingerprint;
use crate::io::images::RgbImage;
use crate::io::output::write_bytes_whole;
use crate::render::camera::Camera;
use crate::render::fingerprint;
use crate::render::image::RenderOptions;
use crate::render::scene::Scene;

/// An entry's first bytes; the key, width, height and the pixels' checksum follow on the same
/// line, then the pixels as little-endian f32 RGB, row by row. The checksum (FNV-1a of the pixel
/// bytes, `Fingerprint`) catches pixels changed under an intact header and length: a bit flipped
/// on disk, a zeroed block, an edited file. Version 1 had none; its entries are a miss.
const MAGIC: &str = "volgrad-target 2";

pub struct TargetCache {
    dir: PathBuf,
    /// The fingerprint of the running executable's bytes.
    renderer: String,
    /// The fingerprint of the truth's medium (every view shares it; it reads every voxel).
    medium: String,
}

impl TargetCache {
    /// The cache in `dir` (created by the first write) for the targets of `truth`.
    pub fn open(dir: &Path, truth: &Scene) -> Result<TargetCache> {
        if dir.exists() && !dir.is_dir() {
            bail!(
                "the target cache '{}' is a file: it names a folder (the first run that uses it makes it)",
                dir.display()
            );
        }
        let exe = std::env::current_exe().context("cannot locate the volgrad executable")?;
        let bytes = std::fs::read(&exe)
            .with_context(|| format!("cannot read '{}' to fingerprint it", exe.display()))?;
        let mut medium = Fingerprint::default();
        fingerprint::medium(&mut medium, &truth.medium);
        Ok(TargetCache {
            dir: dir.to_path_buf(),
            renderer: Fingerprint::default().bytes(&bytes).hex(),
            medium: medium.hex(),
        })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The entry's name for the truth given to `open` seen through `scene`'s camera and lights,
    /// rendered with `options`.
    pub fn key(&self, scene: &Scene, options: &RenderOptions) -> String {
        let mut f = Fingerprint::default();
        f.text(&self.renderer).text(&self.medium).text(&format!(
            "{:?} spp {} seed {} max_depth {}",
            scene.camera, options.spp, options.seed, options.max_depth
        ));
        fingerprint::lights(&mut f, &scene.lights);
        f.hex()
    }

    fn path(&self, key: &str) -> PathBuf {
        self.dir.join(format!("{key}.target"))
    }

    /// The entry `key` for a view of `camera`'s size, if the cache holds it. A damaged entry is
    /// reported and read as missing: the target is rendered again and the entry replaced.
    pub fn read(&self, key: &str, camera: &Camera) -> Option<RgbImage> {
        let path = self.path(key);
        let bytes = crate::io::input::read_bytes(&path).ok()?;
        match decode(&bytes, key, camera.width, camera.height) {
            Ok(image) => Some(image),
            Err(e) => {
                eprintln!(
                    "warning: the target cache's '{}' is unusable ({e}); rendering the target again",
                    path.display()
                );
                None
            }
        }
    }

    /// Stores `image` as the entry `key`, written whole.
    pub fn write(&self, key: &str, image: &RgbImage) -> Result<()> {
        std::fs::create_dir_all(&self.dir)
            .with_context(|| format!("cannot create the target cache '{}'", self.dir.display()))?;
        write_bytes_whole(&self.path(key), encode(key, image))
            .with_context(|| format!("cannot write to the target cache '{}'", self.dir.display()))
    }
}

/// The entry `key` holding `image`: its header line, then its pixels.
pub fn encode(key: &str, image: &RgbImage) -> Vec<u8> {
    let pixels: Vec<u8> = (image.pixels.iter())
        .flat_map(|p| p.to_array())
        .flat_map(f32::to_le_bytes)
        .collect();
    let mut bytes = format!(
        "{MAGIC} {key} {} {} {}\n",
        image.width,
        image.height,
        checksum(&pixels)
    )
    .into_bytes();
    bytes.extend_from_slice(&pixels);
    bytes
}

fn checksum(pixels: &[u8]) -> String {
    Fingerprint::default().bytes(pixels).hex()
}

/// An entry's pixels, checked against its key and the view's size (`width` × `height`).
pub fn decode(bytes: &[u8], key: &str, width: u32, height: u32) -> Result<RgbImage> {
    let header_end = bytes
        .iter()
        .position(|&b| b == b'\n')
        .context("no header")?;
    let header = std::str::from_utf8(&bytes[..header_end])?;
    let expected = format!("{MAGIC} {key} {width} {height} ");
    let Some(sum) = header.strip_prefix(&expected) else {
        bail!("its header is '{header}', not '{expected}<checksum>'");
    };
    let data = &bytes[header_end + 1..];
    let count = width as usize * height as usize;
    if data.len() != count * 12 {
        bail!(
            "{} bytes of pixels where {count} pixels take {}",
            data.len(),
            count * 12
        );
    }
    if checksum(data) != sum {
        bail!(
            "its pixels' checksum is {}, not the {sum} it was written with: changed on disk",
            checksum(data)
        );
    }
    let values: Vec<f32> = data
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let pixels: Vec<Vec3> = values.chunks_exact(3).map(Vec3::from_slice).collect();
    if pixels.iter().any(|p| !p.is_finite()) {
        bail!("non-finite pixels");
    }
    Ok(RgbImage {
        width,
        height,
        pixels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 4×3 image of distinct pixels and its entry.
    fn entry() -> (RgbImage, Vec<u8>) {
        let image = RgbImage {
            width: 4,
            height: 3,
            pixels: (0..12)
                .map(|i| Vec3::new(i as f32, 0.5, 0.25 * i as f32))
                .collect(),
        };
        let bytes = encode("k", &image);
        (image, bytes)
    }

    /// Where an entry's pixels begin.
    fn pixels_at(bytes: &[u8]) -> usize {
        bytes.iter().position(|&b| b == b'\n').unwrap() + 1
    }

    /// An intact entry reads back; one whose pixels changed while its header and length stayed
    /// intact is refused (a miss, so the target is rendered again): every pixel scaled by 3, one
    /// bit flipped, every pixel zeroed.
    #[test]
    fn changed_pixels_are_a_miss() {
        let (image, bytes) = entry();
        assert_eq!(decode(&bytes, "k", 4, 3).unwrap().pixels, image.pixels);
        let at = pixels_at(&bytes);
        let mut tripled = bytes.clone();
        for value in tripled[at..].chunks_exact_mut(4) {
            let v = f32::from_le_bytes(value.try_into().unwrap()) * 3.0;
            value.copy_from_slice(&v.to_le_bytes());
        }
        let mut flipped = bytes.clone();
        flipped[at + 17] ^= 0x04;
        let mut zeroed = bytes.clone();
        zeroed[at..].fill(0);
        let mut header = bytes.clone();
        header[at - 2] ^= 0x01;
        for (what, damaged) in [
            ("tripled", tripled),
            ("flipped", flipped),
            ("zeroed", zeroed),
            ("its checksum changed", header),
        ] {
            assert_eq!(damaged.len(), bytes.len());
            let e = decode(&damaged, "k", 4, 3).unwrap_err().to_string();
            assert!(e.contains("checksum"), "{what}: {e}");
        }
        // Every byte zeroed: no header at all.
        assert!(decode(&vec![0; bytes.len()], "k", 4, 3).is_err());
    }
}
