//! The checks of a parsed scene file: every number and vector a render depends on, with errors
//! that name the key and say what is wrong. Magnitudes are checked before anything derived from
//! them (a length that overflows f32 must not be reported as "zero" or "parallel"), and vectors
//! are normalised in f64 so that tiny but non-zero ones are accepted.

use anyhow::{bail, Result};
use glam::{DVec3, Vec3};

use crate::render::camera::{Camera, Intrinsics};
use crate::render::scene_file::{
    AlbedoFile, CameraFile, EmissionFile, LightFile, SceneFile, DEFAULT_MAJORANT_CELL,
};
use crate::volume::emission::EmissionKind;
use crate::volume::majorant::MajorantMode;

/// Largest |coordinate| of camera.position and camera.target (and of a grid's transform).
pub use crate::volume::transform::MAX_COORDINATE;
/// Largest light value (radiance, irradiance, an envmap texel × scale): sums over millions of
/// samples stay finite in f32.
pub const MAX_LIGHT: f32 = 1e30;
/// Largest extinction (density_scale × the grid's largest value) per world unit: a mean free path
/// of 1e-15 is far below what f32 positions resolve, so anything larger is simply opaque.
pub const MAX_EXTINCTION: f64 = 1e15;
/// Largest image, in pixels (2^28: a 16384 × 16384 render); beyond, buffers run to gigabytes.
pub const MAX_PIXELS: u64 = 1 << 28;
/// The most worker threads a run starts: more than any machine's cores, and each costs its start.
pub const MAX_THREADS: usize = 1024;

/// A thread count of 1 to `MAX_THREADS`; `key` names the flag or argument.
pub fn thread_count(key: &str, threads: usize) -> Result<()> {
    if threads == 0 {
        bail!("{key} must be at least 1");
    }
    if threads > MAX_THREADS {
        // The cores this process may run on (under mpirun, those bound to its rank).
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let cores = if cores == 1 {
            "1 core".into()
        } else {
            format!("{cores} cores")
        };
        bail!("{key} is at most {MAX_THREADS} (got {threads}; this process may use {cores})");
    }
    Ok(())
}

impl CameraFile {
    /// Checks the camera; messages name `camera.*` keys.
    pub fn validate(&self) -> Result<()> {
        let c = self;
        coordinates("camera.position", c.position)?;
        coordinates("camera.target", c.target)?;
        view_frame(c.position, c.target, c.up)?;
        image_size("camera.width", "camera.height", c.width, c.height)?;
        field_of_view("camera.fov_deg", c.fov_deg, c.width, c.height)
    }
}

/// A horizontal field of view strictly between 0 and 180° over an image of `width` × `height`
/// (checked first), whose focal length a float holds (at 10⁻⁴⁴° it does not).
pub fn field_of_view(key: &str, fov_deg: f32, width: u32, height: u32) -> Result<()> {
    if !(fov_deg > 0.0 && fov_deg < 180.0) {
        bail!("{key} must be between 0 and 180 degrees, exclusive (got {fov_deg})");
    }
    if !Intrinsics::from_fov(fov_deg, width, height).fx.is_finite() {
        bail!("{key} = {fov_deg:e} is too narrow: its focal length is beyond what a float holds");
    }
    Ok(())
}

/// An image size of at least one pixel and at most `MAX_PIXELS`; errors name the two keys.
pub fn image_size(width_key: &str, height_key: &str, width: u32, height: u32) -> Result<()> {
    if width == 0 || height == 0 {
        bail!("{width_key} and {height_key} must be at least 1 (got {width}×{height})");
    }
    let pixels = u64::from(width) * u64::from(height);
    if pixels > MAX_PIXELS {
        bail!(
            "{width_key} × {height_key} is too large ({width}×{height} = {pixels} pixels; at most 2^28 = {MAX_PIXELS})"
        );
    }
    Ok(())
}

/// A pinhole's intrinsics and image size: a size in range, finite positive focal lengths whose
/// field of view is under 180° (as `fov_deg`'s), a finite principal point that leaves every ray
/// under 90° from the view direction.
pub fn intrinsics(k: Intrinsics, width: u32, height: u32) -> Result<()> {
    image_size("width", "height", width, height)?;
    for (key, focal, pixels) in [("fx", k.fx, width), ("fy", k.fy, height)] {
        if !(focal > 0.0 && focal.is_finite()) {
            bail!("the focal length {key} must be a finite number of pixels > 0 (got {focal})");
        }
        let fov = 2.0 * (f64::from(pixels) / 2.0 / f64::from(focal)).atan();
        if fov >= std::f64::consts::PI {
            bail!("the focal length {key} = {focal} pixels gives a field of view of 180° over {pixels} pixels (a pinhole's is under 180°)");
        }
    }
    if !(k.cx.is_finite() && k.cy.is_finite()) {
        bail!(
            "the principal point must be finite (got {}, {})",
            k.cx,
            k.cy
        );
    }
    for (key, centre, focal, pixels) in [("cx", k.cx, k.fx, width), ("cy", k.cy, k.fy, height)] {
        let farthest = f64::from(centre).max(f64::from(pixels) - f64::from(centre));
        if farthest / f64::from(focal) > MAX_RAY_TANGENT {
            bail!(
                "the image's edge lies {:.3e} focal lengths from the view direction ({key} = {centre:?}, focal length {focal:?} pixels, {pixels} pixels): a pinhole's rays are under 90° from it, at most {MAX_RAY_TANGENT:e} focal lengths out",
                farthest / f64::from(focal)
            );
        }
    }
    Ok(())
}

/// The farthest a pinhole's image reaches from its view direction, as the tangent of a ray's
/// angle to it: 10⁶ is 89.99994°. A principal point far off the image (1e20 pixels) passed the
/// other checks and overflowed every ray's direction to the zero vector.
const MAX_RAY_TANGENT: f64 = 1e6;

/// A camera given by its frame and intrinsics (a calibrated camera: `transforms.json`, COLMAP),
/// passed through the checks a listed camera passes, in f64 before anything is rounded to f32:
/// a finite position within `MAX_COORDINATE`, a non-zero view direction and up that are not
/// parallel, finite positive focal lengths, a finite principal point, an image size in range.
pub fn calibrated_camera(
    position: DVec3,
    forward: DVec3,
    up: DVec3,
    k: Intrinsics,
    width: u32,
    height: u32,
) -> Result<Camera> {
    if !position.is_finite() || position.abs().max_element() > f64::from(MAX_COORDINATE) {
        // Debug, not Display: 1e300 as "1e300", not as 301 digits.
        bail!(
            "the camera's position {:?} must be finite and within ±{MAX_COORDINATE:e} of the origin in each coordinate",
            position.to_array()
        );
    }
    if !(forward.is_finite() && up.is_finite()) || forward == DVec3::ZERO || up == DVec3::ZERO {
        bail!("the camera's view direction and up must be finite and non-zero (got {forward} and {up})");
    }
    // Scaled to their largest component first: lengths of 1e-200 or 1e200 normalise in f64.
    let forward = (forward / forward.abs().max_element()).normalize();
    let up = (up / up.abs().max_element()).normalize();
    if forward.cross(up).length() < 1e-6 {
        bail!("the camera's up is parallel to its view direction");
    }
    intrinsics(k, width, height)?;
    Ok(Camera::looking(
        position.as_vec3(),
        forward.as_vec3(),
        up.as_vec3(),
        k,
        width,
        height,
    ))
}

impl SceneFile {
    /// Checks every value a render depends on; the message names the key.
    pub fn validate(&self) -> Result<()> {
        if let Some(camera) = &self.camera {
            camera.validate()?;
        }
        let m = &self.medium;
        if m.grid.is_some() && m.grid_index.is_some() {
            bail!("medium.grid and medium.grid_index are exclusive: give one");
        }
        if !(m.density_scale >= 0.0 && m.density_scale.is_finite()) {
            bail!(
                "medium.density_scale must be a finite number ≥ 0 (got {})",
                m.density_scale
            );
        }
        if let AlbedoFile::Constant(albedo) = m.albedo {
            let albedo = albedo.rgb();
            if !(albedo.cmpge(Vec3::ZERO).all() && albedo.cmple(Vec3::ONE).all()) {
                bail!("medium.albedo must lie in [0, 1] (got {albedo})");
            }
        }
        if m.phase_g.is_nan() || m.phase_g.abs() >= 1.0 {
            bail!("medium.phase_g must satisfy |g| < 1 (got {})", m.phase_g);
        }
        if let Some(e) = &m.emission {
            e.emission_kind()?;
        }
        check_lights(&self.light)?;
        let r = &self.render;
        if r.spp == 0 {
            bail!("render.spp must be at least 1");
        }
        if !(r.exposure > 0.0 && r.exposure.is_finite()) {
            bail!(
                "render.exposure must be a finite number > 0 (got {})",
                r.exposure
            );
        }
        if r.majorant_cell == 0 || r.majorant_cell > 1024 {
            bail!(
                "render.majorant_cell must be between 1 and 1024 voxels (got {})",
                r.majorant_cell
            );
        }
        if r.majorant == MajorantMode::Global && r.majorant_cell != DEFAULT_MAJORANT_CELL {
            bail!("render.majorant_cell sets the cells of the majorant grid: with majorant = \"global\" (one for the whole medium) it would be ignored; leave it out");
        }
        Ok(())
    }
}

impl EmissionFile {
    /// What the grid's values mean, checked: one of `blackbody` and `radiance`; finite settings.
    pub fn emission_kind(&self) -> Result<EmissionKind> {
        match (&self.blackbody, &self.radiance) {
            (Some(b), None) => {
                let strength = self.strength.unwrap_or(1.0);
                for (key, v) in [
                    ("blackbody.scale", b.scale),
                    ("blackbody.offset", b.offset),
                    ("blackbody.cutoff", b.cutoff),
                    ("strength", strength),
                ] {
                    if !v.is_finite() {
                        bail!("medium.emission.{key} must be a finite number (got {v})");
                    }
                }
                if b.scale <= 0.0 || strength < 0.0 {
                    bail!("medium.emission.blackbody.scale must be > 0 and strength ≥ 0 (got {} and {strength})", b.scale);
                }
                // The blackbody is at most 1.21 (red, near 4550 K): a strength above the light
                // cap exceeds it at some temperature. The grid's hottest voxel decides the rest
                // (`medium_grids::load_emission`).
                if strength > MAX_LIGHT {
                    bail!("medium.emission.strength is too large (got {strength:e}; at most {MAX_LIGHT:e})");
                }
                Ok(EmissionKind::Blackbody {
                    scale: b.scale,
                    offset: b.offset,
                    cutoff: b.cutoff,
                    strength,
                })
            }
            (None, Some(radiance)) => {
                if self.strength.is_some() {
                    bail!("medium.emission.strength goes with blackbody; scale `radiance` instead");
                }
                light_value("medium.emission.radiance", radiance.rgb())?;
                Ok(EmissionKind::Radiance(radiance.rgb()))
            }
            _ => bail!(
                "medium.emission needs one of `blackbody = {{ scale, offset, cutoff }}` (a temperature grid) and `radiance = [r, g, b]` (× the grid's value)"
            ),
        }
    }
}

/// The camera's unit view direction and unit up vector, computed in f64: `target − position` and
/// `up` may be far too small (or, as f32 squared lengths, too large) to normalise in f32.
pub fn view_frame(position: [f32; 3], target: [f32; 3], up: [f32; 3]) -> Result<(Vec3, Vec3)> {
    let forward = DVec3::from(target.map(f64::from)) - DVec3::from(position.map(f64::from));
    if forward == DVec3::ZERO {
        bail!("camera.target must differ from camera.position (both are {position:?})");
    }
    let forward = forward.normalize();
    let up = unit("camera.up", up)?;
    if forward.cross(up.as_dvec3()).length() < 1e-6 {
        bail!("camera.up must not be parallel to the view direction (camera.target − camera.position)");
    }
    Ok((forward.as_vec3(), up))
}

/// A non-zero finite vector, normalised in f64 (so [0, −1e-30, 0] is fine).
pub fn unit(key: &str, v: [f32; 3]) -> Result<Vec3> {
    finite3(key, v)?;
    let d = DVec3::from(v.map(f64::from));
    if d == DVec3::ZERO {
        bail!("{key} must not be zero");
    }
    Ok(d.normalize().as_vec3())
}

fn finite3(key: &str, v: [f32; 3]) -> Result<()> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        bail!("{key} must be three finite numbers (got {v:?})")
    }
}

/// Three finite numbers within `MAX_COORDINATE` of the origin.
pub fn coordinates(key: &str, v: [f32; 3]) -> Result<()> {
    finite3(key, v)?;
    if v.iter().any(|x| x.abs() > MAX_COORDINATE) {
        bail!(
            "{key} is too far from the origin to trace in f32 (got {v:?}; each coordinate must be within ±{MAX_COORDINATE:e})"
        );
    }
    Ok(())
}

/// A list of lights as a scene file's `[[light]]`s: values in range, directions non-zero, at
/// most one environment map. Errors name `light[i]`.
pub fn check_lights(lights: &[LightFile]) -> Result<()> {
    let mut envmaps = 0;
    for (i, light) in lights.iter().enumerate() {
        match light {
            LightFile::Constant { radiance } => {
                light_value(&format!("light[{i}].radiance"), radiance.rgb())?
            }
            LightFile::Envmap {
                scale,
                up,
                rotation_deg,
                ..
            } => {
                envmaps += 1;
                light_value(&format!("light[{i}].scale"), Vec3::splat(*scale))?;
                unit(&format!("light[{i}].up"), *up)?;
                if !rotation_deg.is_finite() {
                    bail!("light[{i}].rotation_deg must be finite (got {rotation_deg})");
                }
            }
            LightFile::Directional {
                direction,
                irradiance,
            } => {
                unit(&format!("light[{i}].direction"), *direction)?;
                light_value(&format!("light[{i}].irradiance"), irradiance.rgb())?;
            }
        }
    }
    if envmaps > 1 {
        bail!("at most one light of type \"envmap\" is supported (found {envmaps})");
    }
    Ok(())
}

/// A light value: finite, ≥ 0 and at most `MAX_LIGHT` in every channel.
pub fn light_value(key: &str, v: Vec3) -> Result<()> {
    if !(v.is_finite() && v.cmpge(Vec3::ZERO).all()) {
        bail!("{key} must be finite and ≥ 0 (got {v})");
    }
    if v.max_element() > MAX_LIGHT {
        bail!(
            "{key} is too large (largest channel {:e}; at most {MAX_LIGHT:e})",
            v.max_element()
        );
    }
    Ok(())
}

/// A picture of radiance a loss compares renders with (a target): every pixel finite and at most
/// `MAX_LIGHT` in magnitude (beyond it no scene renders it, and its squared difference overflows
/// f32). Small negative values are kept: a Lanczos or Mitchell pixel filter rings below 0 at
/// sharp edges, by at most about a seventh of the edge's height; a value below
/// −`RINGING` × the picture's brightest is not ringing but a picture of something else (a
/// difference image, a signed AOV). `what` names the picture.
pub fn radiance_pixels(what: &str, pixels: &[Vec3]) -> Result<()> {
    if let Some((i, p)) = (pixels.iter().enumerate())
        .find(|(_, p)| !(p.is_finite() && p.abs().max_element() <= MAX_LIGHT))
    {
        // Debug prints a float's shortest form (1e35, not 36 digits).
        bail!("{what}: pixel {i} is {:?}; radiance is finite and at most {MAX_LIGHT:e} in every channel", p.to_array());
    }
    let brightest = pixels.iter().fold(0.0f32, |m, p| m.max(p.max_element()));
    let floor = -RINGING * brightest;
    if let Some((i, p)) = (pixels.iter().enumerate()).find(|(_, p)| p.min_element() < floor) {
        bail!("{what}: pixel {i} is {p}, below what a pixel filter's ringing reaches (−{RINGING} × the picture's brightest value, {brightest}): radiance is not negative");
    }
    Ok(())
}

/// How far below 0 a target's pixel may ring, as a fraction of the picture's brightest value.
const RINGING: f32 = 0.25;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_target_may_ring_below_zero_but_not_be_negative() {
        let ok = |p: &[Vec3]| radiance_pixels("t", p).is_ok();
        // A filter's ringing beside a bright edge is kept.
        assert!(ok(&[Vec3::ONE, Vec3::new(0.5, -0.1, 0.0)]));
        assert!(!ok(&[Vec3::ONE, Vec3::new(0.5, -0.3, 0.0)]));
        // A picture with nothing bright in it has nothing to ring from.
        assert!(!ok(&[Vec3::splat(-5.0); 4]));
        assert!(!ok(&[Vec3::ZERO, Vec3::new(0.0, -1e-3, 0.0)]));
    }

    #[test]
    fn tiny_vectors_normalise_and_zero_ones_are_named() {
        assert_eq!(unit("d", [0.0, -1e-30, 0.0]).unwrap(), Vec3::NEG_Y);
        assert_eq!(unit("d", [0.0, 1e-45, 0.0]).unwrap(), Vec3::Y);
        let e = unit("light[0].direction", [0.0; 3])
            .unwrap_err()
            .to_string();
        assert!(e.contains("light[0].direction must not be zero"), "{e}");
        let (forward, up) = view_frame([0.0, 0.0, 1e-30], [0.0; 3], [0.0, 1e-30, 0.0]).unwrap();
        assert_eq!((forward, up), (Vec3::NEG_Z, Vec3::Y));
    }

    #[test]
    fn magnitudes_are_checked_before_directions() {
        let e = coordinates("camera.position", [0.0, 0.0, 1e30]).unwrap_err();
        assert!(e.to_string().contains("too far from the origin"), "{e}");
        let e = view_frame([0.0; 3], [0.0, 0.0, -1.0], [0.0, 0.0, 3e38]).unwrap_err();
        assert!(e.to_string().contains("parallel"), "{e}");
        let e = light_value("light[0].radiance", Vec3::splat(3e38)).unwrap_err();
        assert!(e.to_string().contains("too large"), "{e}");
    }
}
