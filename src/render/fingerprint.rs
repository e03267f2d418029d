//! A scene's fingerprint: everything that decides its images — camera, the grids' values and
//! transforms (density, and albedo and emission where the medium has them), the medium's optical
//! constants, the lights — and nothing about where its files live,
//! so the same scene loaded from a relative or an absolute path, or from a copy, has one
//! fingerprint, and two different scenes that share a file name do not.

use crate::io::fingerprint::Fingerprint;
use crate::render::lights::Lights;
use crate::render::scene::Scene;
use crate::volume::albedo::Albedo;
use crate::volume::brickmap::BrickMap;
use crate::volume::medium::Medium;

/// 16 hex digits (see `io::fingerprint`).
pub fn scene(scene: &Scene) -> String {
    let mut f = Fingerprint::default();
    // Debug output of floats is their shortest exact representation, so these small structs
    // hash by value.
    f.text(&format!("{:?}", scene.camera));
    medium(&mut f, &scene.medium);
    lights(&mut f, &scene.lights);
    f.hex()
}

/// The medium's grids and optical constants, fed to `f`.
pub fn medium(f: &mut Fingerprint, m: &Medium) {
    // A constant albedo reads as it did before albedo grids, so fingerprints stay what they were.
    let albedo = match &m.albedo {
        Albedo::Constant(albedo) => albedo.to_string(),
        Albedo::Grid(grid) => format!("grid {} {:?}", grid.background, grid.transform),
    };
    f.text(&format!(
        "{:?} {:?} {} {} {} {}",
        m.transform, m.bounds, m.density_scale, albedo, m.phase_g, m.filter
    ));
    bricks(f, &m.grid);
    if let Some(grid) = m.albedo.grid() {
        grid.channels.iter().for_each(|c| bricks(f, c));
    }
    if let Some(e) = &m.emission {
        f.text(&format!("emission {:?} {:?}", e.transform, e.kind));
        bricks(f, &e.grid);
    }
}

/// The lights, fed to `f`.
pub fn lights(f: &mut Fingerprint, lights: &Lights) {
    f.text(&format!(
        "{:?} {:?}",
        lights.environment.constant, lights.directional
    ));
    if let Some(map) = &lights.environment.map {
        let (w, h, texels) = map.texels();
        f.text(&format!("envmap {w}×{h}")).vec3s(texels);
        // Only a turned map says so: an unturned one keeps the fingerprint it had before maps
        // could turn (gradient files and target caches written then still match).
        if let Some(frame) = map.frame() {
            f.text(&format!("frame {frame:?}"));
        }
    }
}

/// A brick map's values, active masks and tiles.
pub fn bricks(f: &mut Fingerprint, map: &BrickMap) {
    for leaf in map.leaves() {
        f.f32s(&leaf.origin.as_vec3().to_array()).f32s(&leaf.values);
        for word in leaf.active {
            f.bytes(&word.to_le_bytes());
        }
    }
    for tile in map.tiles() {
        f.text(&format!(
            "tile {:?} {} {}",
            tile.origin, tile.size, tile.value
        ));
    }
}
