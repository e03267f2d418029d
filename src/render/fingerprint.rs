//! A scene's fingerprint: everything that decides its images — camera, the grid's values and
//! transform, the medium's optical constants, the lights — and nothing about where its files live,
//! so the same scene loaded from a relative or an absolute path, or from a copy, has one
//! fingerprint, and two different scenes that share a file name do not.

use crate::io::fingerprint::Fingerprint;
use crate::render::scene::Scene;

/// 16 hex digits (see `io::fingerprint`).
pub fn scene(scene: &Scene) -> String {
    let mut f = Fingerprint::default();
    // Debug output of floats is their shortest exact representation, so these small structs
    // hash by value.
    f.text(&format!("{:?}", scene.camera));
    let m = &scene.medium;
    f.text(&format!(
        "{:?} {:?} {} {} {} {}",
        m.transform, m.bounds, m.density_scale, m.albedo, m.phase_g, m.filter
    ));
    for leaf in m.grid.leaves() {
        f.f32s(&leaf.origin.as_vec3().to_array()).f32s(&leaf.values);
        for word in leaf.active {
            f.bytes(&word.to_le_bytes());
        }
    }
    for tile in m.grid.tiles() {
        f.text(&format!(
            "tile {:?} {} {}",
            tile.origin, tile.size, tile.value
        ));
    }
    let lights = &scene.lights;
    f.text(&format!(
        "{:?} {:?}",
        lights.environment.constant, lights.directional
    ));
    if let Some(map) = &lights.environment.map {
        let (w, h, texels) = map.texels();
        f.text(&format!("envmap {w}×{h}")).vec3s(texels);
    }
    f.hex()
}
