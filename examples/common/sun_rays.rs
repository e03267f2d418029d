//! Shadow rays as a path's are: toward a scene's first sun from random points inside the density,
//! sorted by the brick they start in so that neighbouring rays share their reads, as a path's
//! reads do. Shared by the examples that time or compare shadow-ray trackers.

use std::path::Path;

use anyhow::{bail, Result};
use glam::Vec3;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use volgrad::render::scene::Scene;
use volgrad::volume::ray::IndexRay;

/// `count` rays toward `scene`'s first directional light, in index space.
pub fn sun_rays(scene: &Scene, path: &Path, count: usize) -> Result<Vec<IndexRay>> {
    let medium = &scene.medium;
    let Some(sun) = scene.lights.directional.first() else {
        bail!("{}: the scene has no directional light", path.display());
    };
    if medium.grid.max_value() <= 0.0 {
        bail!("{}: the medium has no density", path.display());
    }
    let d = medium.transform.vector_to_index(sun.to_light);
    let (lo, hi) = medium.bounds;
    let mut rng = SmallRng::seed_from_u64(9);
    let mut rays = Vec::with_capacity(count);
    // Points drawn in the box until enough fall in the density: a bounded number of draws, so
    // that a sparse grid in a wide box ends with an error rather than a wait without end.
    for _ in 0..1000 * count {
        let o = lo + (hi - lo) * Vec3::new(rng.gen(), rng.gen(), rng.gen());
        if medium.sigma_t(o) > 0.0 {
            rays.push(IndexRay { o, d });
            if rays.len() == count {
                break;
            }
        }
    }
    if rays.len() < count {
        bail!(
            "{}: the density fills under 1/1000 of the medium's box; {} of {count} origins found",
            path.display(),
            rays.len()
        );
    }
    rays.sort_by_key(|r| {
        let b = (r.o / 8.0).floor();
        (b.x as i32, b.y as i32, b.z as i32)
    });
    Ok(rays)
}
