//! What a run solves for: where it lives (`Domain`, every level's transform and box), its start
//! at the first level, the truth in the final level's index space, and the scene with the unknown
//! in place — as the density (σt's grid, majorants built for it), or as the emission grid (flame
//! tomography: the scene's density is known, and its `medium.emission` says what the values mean).

use anyhow::{bail, Context, Result};
use glam::{DAffine3, DMat3, DQuat, DVec3, IVec3, Vec3};

use crate::gradient::passes::Parameter;
use crate::io::vdb;
use crate::optimize::hull::Hull;
use crate::optimize::parameters::{Parameters, MAX_VOXELS};
use crate::optimize::run_file::{StartFile, UnknownGrid};
use crate::render::scene::Scene;
use crate::volume::albedo::Albedo;
use crate::volume::brickmap::{floor_ivec3, BrickMap};
use crate::volume::emission::EmissionKind;
use crate::volume::medium::Medium;
use crate::volume::transform::IndexTransform;

/// Where the unknown lives: the final level's transform and inclusive voxel box, and how many ×2
/// upsamplings lead there. Level k (0 = coarsest) has voxels s = 2^(levels − k) times larger; its
/// index c maps to the final index f = s·c + (s − 1)/2 (what `resample::upsample` inverts), so
/// every level fills the same world box.
#[derive(Debug, Clone)]
pub struct Domain {
    pub transform: IndexTransform,
    pub lo: IVec3,
    pub hi: IVec3,
    pub levels: usize,
}

impl Domain {
    /// The final level over the world box from `min` to `max` in voxels of `voxel`, anchored at
    /// `min`, and the box's max as those voxels cover it: one voxel past `max` where the box is
    /// not a whole number of them (within 10⁻⁴ voxel). The max is rounded down to f32, as a run
    /// file holds it, so that the box written back keeps its count of voxels.
    pub fn over_box(min: DVec3, max: DVec3, voxel: f64) -> Result<(Domain, [f32; 3])> {
        let n = ((max - min) / voxel - 1e-4).ceil().max(DVec3::ONE);
        if n.max_element() > i32::MAX as f64 / 2.0 {
            bail!("unknown.bounds / unknown.voxel_size: {n} voxels per axis is too many");
        }
        let linear = DMat3::from_diagonal(DVec3::splat(voxel));
        let transform =
            IndexTransform::new(DAffine3::from_mat3_translation(linear, min + voxel / 2.0))
                .context("unknown.bounds / unknown.voxel_size")?;
        let domain = Domain {
            transform,
            lo: IVec3::ZERO,
            hi: n.as_ivec3() - IVec3::ONE,
            levels: 0,
        };
        let covered = (min + n * voxel).to_array().map(|c| {
            let f = c as f32;
            if f64::from(f) > c {
                f.next_down()
            } else {
                f
            }
        });
        Ok((domain, covered))
    }

    /// Refused above `MAX_VOXELS` at the final level.
    pub fn checked(self) -> Result<Domain> {
        if self.voxel_count() > MAX_VOXELS {
            let count = match self.voxel_count() {
                u64::MAX => "more than 1.8e19".to_string(), // saturated
                n => n.to_string(),
            };
            bail!(
                "unknown.bounds: the unknown has {count} voxels at the final level; at most {MAX_VOXELS} (each is stored with Adam's two moments)"
            );
        }
        Ok(self)
    }

    /// Voxel size of level `level` over the final one.
    pub fn scale(&self, level: usize) -> f64 {
        f64::from(1u32 << (self.levels - level.min(self.levels)))
    }

    /// Level `level`'s index → world transform (`check_levels` has made sure it is one).
    pub fn transform(&self, level: usize) -> IndexTransform {
        self.level_transform(level)
            .expect("check_levels: every level's transform is within f32's reach")
    }

    fn level_transform(&self, level: usize) -> Result<IndexTransform> {
        let s = self.scale(level);
        let coarse_to_fine = DAffine3::from_scale_rotation_translation(
            DVec3::splat(s),
            DQuat::IDENTITY,
            DVec3::splat((s - 1.0) / 2.0),
        );
        IndexTransform::new(self.transform.index_to_world() * coarse_to_fine)
    }

    /// A final-level continuous index in level `level`'s index space.
    pub fn to_level(&self, level: usize, fine: Vec3) -> Vec3 {
        let s = self.scale(level) as f32;
        (fine - (s - 1.0) / 2.0) / s
    }

    /// The continuous index box of level `level` (the final voxels' box grown by half a voxel).
    pub fn bounds(&self, level: usize) -> (Vec3, Vec3) {
        (
            self.to_level(level, self.lo.as_vec3() - 0.5),
            self.to_level(level, self.hi.as_vec3() + 0.5),
        )
    }

    /// The voxels of level `level` whose centres lie in its bounds.
    pub fn voxel_box(&self, level: usize) -> (IVec3, IVec3) {
        let (lo, hi) = self.bounds(level);
        (lo.ceil().as_ivec3(), floor_ivec3(hi))
    }

    /// The world-space box around the domain (the corners of the final box, transformed).
    pub fn world_box(&self) -> (Vec3, Vec3) {
        let (lo, hi) = self.bounds(self.levels);
        let mut out = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for k in 0..8 {
            let corner = Vec3::new(
                if k & 1 == 0 { lo.x } else { hi.x },
                if k & 2 == 0 { lo.y } else { hi.y },
                if k & 4 == 0 { lo.z } else { hi.z },
            );
            let w = self.transform.point_to_world(corner);
            out = (out.0.min(w), out.1.max(w));
        }
        out
    }

    /// The longest edge of the final box, in world units (along the grid's index axes).
    pub fn longest_edge(&self) -> f64 {
        let voxels = (self.hi - self.lo + IVec3::ONE).as_dvec3();
        (voxels * self.transform.voxel_size()).max_element()
    }

    /// Final voxels along the box's shortest edge.
    pub fn shortest_edge(&self) -> u64 {
        (self.hi - self.lo + IVec3::ONE).min_element().max(0) as u64
    }

    /// An error unless the first level has a voxel across every edge of the box and its voxels,
    /// the largest, are within f32's reach (the levels between lie between it and the final's).
    pub fn check_levels(&self) -> Result<()> {
        if self.voxel_count_at(0) == 0 {
            bail!(
                "unknown.levels: {} upsamplings leave the first level no voxel across the box's shortest edge ({} voxels); give fewer levels, or a larger box or voxel",
                self.levels,
                self.shortest_edge()
            );
        }
        self.level_transform(0).map_err(|e| {
            anyhow::anyhow!(
                "unknown.levels: the first level's voxels, 2^{} final ones: {e}",
                self.levels
            )
        })?;
        Ok(())
    }

    /// Voxels in the final box.
    pub fn voxel_count(&self) -> u64 {
        box_voxels(self.lo, self.hi)
    }

    /// Voxels of level `level` (`voxel_box`).
    pub fn voxel_count_at(&self, level: usize) -> u64 {
        let (lo, hi) = self.voxel_box(level);
        box_voxels(lo, hi)
    }
}

/// Voxels in the inclusive box `lo..=hi` (0 for an empty box), saturating at `u64::MAX`: a box of
/// 2²² voxels a side would wrap to 0 and pass every limit.
fn box_voxels(lo: IVec3, hi: IVec3) -> u64 {
    let n = (hi.as_i64vec3() - lo.as_i64vec3() + 1).max(glam::I64Vec3::ZERO);
    (n.x as u64)
        .saturating_mul(n.y as u64)
        .saturating_mul(n.z as u64)
}

/// The optimiser's settings, resolved.
impl UnknownGrid {
    /// The gradient pass's parameter for this unknown.
    pub fn parameter(self) -> Parameter {
        match self {
            UnknownGrid::Density => Parameter::Extinction,
            UnknownGrid::Emission => Parameter::Emission,
        }
    }

    /// The unknown's values in a scene `scene_with` filled: its density, or its emission grid.
    pub fn grid_in(self, scene: &Scene) -> &BrickMap {
        match (self, &scene.medium.emission) {
            (UnknownGrid::Emission, Some(emission)) => &emission.grid,
            _ => &scene.medium.grid,
        }
    }
}

/// Refuses a scene that cannot hold the unknown: an emission unknown needs the scene's emission to
/// say what its values mean, linearly (`radiance = [r, g, b]` × value: a flames grid; a
/// temperature grid's blackbody is not solved for), in a medium that absorbs somewhere.
pub fn check_scene(scene: &Scene, unknown: UnknownGrid) -> Result<()> {
    if unknown == UnknownGrid::Density {
        return Ok(());
    }
    if scene.vdb_path.is_none() {
        bail!("unknown.grid = \"emission\": the density is known, so the scene names its grid (medium.vdb)");
    }
    match &scene.medium.emission {
        None => bail!(
            "unknown.grid = \"emission\": the scene's medium has no emission (medium.emission = {{ grid = …, radiance = [r, g, b] }} says what the unknown's values mean)"
        ),
        Some(e) if !matches!(e.kind, EmissionKind::Radiance(_)) => bail!(
            "unknown.grid = \"emission\" solves for a radiance grid (medium.emission = {{ grid = …, radiance = [r, g, b] }}); a temperature grid's blackbody emission is not solved for"
        ),
        Some(e) if e.kind == EmissionKind::Radiance(Vec3::ZERO) => bail!(
            "unknown.grid = \"emission\": medium.emission.radiance is 0, so the images do not depend on the emission grid"
        ),
        Some(_) => {}
    }
    if let Albedo::Constant(albedo) = scene.medium.albedo {
        if albedo.min_element() >= 1.0 {
            bail!("unknown.grid = \"emission\": the medium's albedo is 1, so it absorbs nothing and emits nothing (σa·Le = σt·(1 − α)·Le)");
        }
    }
    Ok(())
}

/// `scene` with `theta` (in `transform`, filling `bounds`) as its unknown grid.
pub fn scene_with(
    scene: &Scene,
    unknown: UnknownGrid,
    theta: BrickMap,
    transform: IndexTransform,
    bounds: (Vec3, Vec3),
) -> Scene {
    let mut filled = scene.clone();
    match (unknown, &mut filled.medium.emission) {
        (UnknownGrid::Emission, Some(emission)) => {
            emission.grid = theta;
            emission.transform = transform;
        }
        _ => filled.medium = medium_like(scene, theta, transform, bounds),
    }
    filled
}

/// The scene a run keeps, without the unknown's values (the per-iteration scenes cloned from it
/// then carry only what is known); refused where the scene cannot hold the unknown.
pub fn without_unknown(mut scene: Scene, unknown: UnknownGrid, domain: &Domain) -> Result<Scene> {
    let empty = || BrickMap::new(Vec::new(), Vec::new());
    match (unknown, &mut scene.medium.emission) {
        (UnknownGrid::Density, _) => {
            scene.medium = medium_like(&scene, empty(), domain.transform, (Vec3::ZERO, Vec3::ZERO));
        }
        (UnknownGrid::Emission, Some(emission)) => emission.grid = empty(),
        (UnknownGrid::Emission, None) => bail!(
            "unknown.grid = \"emission\": the scene's medium has no emission (medium.emission = {{ grid = …, radiance = [r, g, b] }} says what the unknown's values mean)"
        ),
    }
    Ok(scene)
}

/// A medium with `scene`'s optical constants and majorant settings over `grid` (its emission, the
/// unknown's business, left out).
pub fn medium_like(
    scene: &Scene,
    grid: BrickMap,
    transform: IndexTransform,
    bounds: (Vec3, Vec3),
) -> Medium {
    let m = &scene.medium;
    let mut medium = Medium::with_bounds(
        grid,
        transform,
        bounds,
        m.density_scale,
        m.filter,
        scene.settings.majorant(),
    );
    medium.albedo = m.albedo.clone();
    medium.phase_g = m.phase_g;
    medium
}

/// θ at the first level: the constant (cleared where `hull` says a view sees through), or the
/// start grid's trilinear field at each voxel centre.
pub fn start_parameters(
    domain: &Domain,
    start: &StartFile,
    grid: Option<&vdb::Grid>,
    hull: Option<&Hull>,
) -> Parameters {
    let (lo, hi) = domain.voxel_box(0);
    let transform = domain.transform(0);
    let mut p = Parameters::default();
    for x in lo.x..=hi.x {
        for y in lo.y..=hi.y {
            for z in lo.z..=hi.z {
                let v = IVec3::new(x, y, z);
                let value = match (start, grid) {
                    (StartFile::Constant(_), _) if hull.is_some_and(|h| h.is_seen_through(v)) => {
                        0.0
                    }
                    (StartFile::Constant(c), _) => *c,
                    (StartFile::Vdb(_), Some(g)) => {
                        let world = transform.point_to_world(v.as_vec3());
                        g.bricks.trilinear(g.transform.point_to_index(world))
                    }
                    (StartFile::Vdb(_), None) => 0.0,
                };
                if value > 0.0 {
                    p.set(v, value);
                }
            }
        }
    }
    p
}

/// The truth's values at the final level's voxels: the grid itself when it defines the domain's
/// transform, else its trilinear field sampled at the voxel centres.
pub fn in_final_index_space(truth: vdb::Grid, domain: &Domain) -> Result<BrickMap> {
    if truth.transform.to_rows() == domain.transform.to_rows() {
        return Ok(truth.bricks);
    }
    if domain.voxel_count() > MAX_VOXELS {
        bail!("unknown.bounds: too many voxels to resample the truth onto");
    }
    let mut b = crate::volume::brickmap::BrickMapBuilder::new();
    for x in domain.lo.x..=domain.hi.x {
        for y in domain.lo.y..=domain.hi.y {
            for z in domain.lo.z..=domain.hi.z {
                let v = IVec3::new(x, y, z);
                let world = domain.transform.point_to_world(v.as_vec3());
                let value = truth
                    .bricks
                    .trilinear(truth.transform.point_to_index(world));
                if value > 0.0 {
                    b.set(v, value, true);
                }
            }
        }
    }
    Ok(b.build())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The box settings.toml writes (the max its voxels cover, in f32) gives the same voxels
    /// read back: far from the origin, the covered max rounded to the nearest f32 (0.125 units
    /// apart at 10⁶, 0.42 of these voxels) gave one voxel more in 6 of these 16 far boxes.
    #[test]
    fn the_box_a_run_writes_keeps_its_voxels() {
        let far = (0..16).map(|k| (-1e6 + 0.3, 1.1e6 + 0.13 * k as f64, 0.3));
        for (min, max, voxel) in [(-3.0, 3.0, 4.0), (-40.0, 25.0, 1.0), (0.1, 0.95, 0.05)]
            .into_iter()
            .chain(far)
        {
            // As a run file holds them: f32.
            let [min, max] = [min, max].map(|c: f64| DVec3::splat(c as f32 as f64));
            let (first, covered) = Domain::over_box(min, max, voxel).unwrap();
            let written = DVec3::from(covered.map(f64::from));
            assert!(
                (written - (max + voxel)).max_element() < 0.0,
                "{written} {max}"
            );
            let (again, _) = Domain::over_box(min, written, voxel).unwrap();
            assert_eq!(
                (again.lo, again.hi),
                (first.lo, first.hi),
                "{min} {max} {voxel}"
            );
        }
    }

    /// A box of 8 voxels of `voxel` world units a side, with `levels` upsamplings.
    fn domain(voxel: f64, levels: usize) -> Domain {
        Domain {
            transform: IndexTransform::uniform(voxel, DVec3::ZERO),
            lo: IVec3::ZERO,
            hi: IVec3::splat(7),
            levels,
        }
    }

    /// The first level needs a voxel across the box and voxels f32 can place: final voxels of
    /// 3·10¹⁴ are, their first level's 2⁴ times larger are not (it panicked when asked for
    /// that level's transform).
    #[test]
    fn levels_are_checked_for_voxels_and_reach() {
        assert!(domain(1.0, 3).check_levels().is_ok());
        let e = domain(1.0, 5).check_levels().unwrap_err().to_string();
        assert!(e.contains("no voxel"), "{e}");
        assert!(domain(3e14, 1).check_levels().is_ok());
        let e = domain(3e14, 3).check_levels().unwrap_err().to_string();
        assert!(
            e.contains("first level's voxels") && e.contains("f32"),
            "{e}"
        );
    }
}
